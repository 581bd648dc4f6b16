//! RFC 7252 message layer, run in the simulator: piggybacked and separate responses,
//! retransmission instants, timeouts, deduplication, ping, NSTART, bad options.

use std::time::Duration;

use coap::{
    Code, EndpointConfig, Event, Message, OptionNumber, Request, RequestError, Response, Type,
};

use crate::sim::{LinkConfig, Reply, Sim};

fn cfg(seed: u64) -> EndpointConfig {
    EndpointConfig {
        rng_seed: seed,
        ..EndpointConfig::default()
    }
}

fn echo_server() -> crate::sim::Handler {
    Box::new(|req| {
        Reply::Now(
            Response::new(Code::CONTENT)
                .with_payload(format!("echo {}", req.options.path_string())),
        )
    })
}

fn lines(sim: &Sim) -> Vec<String> {
    sim.log.iter().map(|r| r.line()).collect()
}

#[test]
fn rfc7252_5_2_1_piggybacked_response_in_the_ack() {
    let mut sim = Sim::new(LinkConfig::default());
    let c = sim.add(cfg(1), None);
    let s = sim.add(cfg(2), Some(echo_server()));
    let server = sim.nodes[s].addr;
    let now = sim.now;
    let id = sim.nodes[c]
        .ep
        .request(now, server, Request::new(Code::GET, "/a/b"));
    assert!(sim.run_to_event(c, Duration::from_secs(10)));
    match &sim.nodes[c].events[0].1 {
        Event::Response { id: got, response } => {
            assert_eq!(*got, id);
            assert_eq!(response.code, Code::CONTENT);
            assert_eq!(&response.payload[..], b"echo /a/b");
        }
        other => panic!("unexpected {other:?}"),
    }
    let l = lines(&sim);
    assert_eq!(l.len(), 2, "{l:#?}");
    assert!(l[0].contains("CON 0.01"), "{l:?}");
    assert!(l[1].contains("ACK 2.05"), "{l:?}");
}

#[test]
fn rfc7252_5_2_2_separate_response_after_empty_ack() {
    let mut sim = Sim::new(LinkConfig::default());
    let c = sim.add(cfg(1), None);
    let slow: crate::sim::Handler = Box::new(|_| {
        Reply::After(
            Duration::from_secs(5),
            Response::new(Code::CONTENT).with_payload("late"),
        )
    });
    let s = sim.add(cfg(2), Some(slow));
    let server = sim.nodes[s].addr;
    let now = sim.now;
    sim.nodes[c]
        .ep
        .request(now, server, Request::new(Code::POST, "/slow"));
    assert!(sim.run_to_event(c, Duration::from_secs(60)));
    let (at, ev) = &sim.nodes[c].events[0];
    assert!(matches!(ev, Event::Response { response, .. } if &response.payload[..] == b"late"));
    assert_eq!(
        at.as_millis(),
        5010,
        "response sent at 5 s plus 5 ms link delay, ACKed"
    );
    // Transcript with literal times: request at 0, empty ACK after the 1 s separate-ACK
    // delay, CON response at 5 s, its ACK from the client. No retransmission of the request.
    assert_eq!(
        lines(&sim)
            .iter()
            .map(|l| l.split(" mid=").next().unwrap_or("").to_string())
            .collect::<Vec<_>>(),
        [
            "0 ms CON 0.02",
            "1005 ms ACK 0.00",
            "5005 ms CON 2.05",
            "5010 ms ACK 0.00"
        ]
    );
}

#[test]
fn rfc7252_4_2_retransmission_instants_double_with_jitter() {
    // Nobody answers: the CON goes out five times, at 0, T, 3T, 7T, 15T, where the initial
    // timeout T = ACK_TIMEOUT * U[1, 1.5] from the endpoint's seed; the exchange fails at 31T.
    let mut sim = Sim::new(LinkConfig {
        loss: 1.0,
        ..LinkConfig::default()
    });
    let c = sim.add(cfg(7), None);
    let s = sim.add(cfg(8), None);
    let server = sim.nodes[s].addr;
    let now = sim.now;
    sim.nodes[c]
        .ep
        .request(now, server, Request::new(Code::GET, "/x"));
    assert!(sim.run_to_event(c, Duration::from_secs(200)));
    let times: Vec<u128> = sim.log.iter().map(|r| r.at.as_millis()).collect();
    assert_eq!(
        times,
        [0, 2270, 6810, 15890, 34051],
        "seed 7 gives T = 2270 ms"
    );
    let t = times[1] as f64;
    assert!((2000.0..=3000.0).contains(&t));
    for (k, at) in times.iter().enumerate() {
        let expected = t * f64::from((1u32 << k) - 1);
        assert!(
            (*at as f64 - expected).abs() <= 2.0,
            "transmission {k} at {at} ms, expected {expected}"
        );
    }
    let (failed_at, ev) = &sim.nodes[c].events[0];
    assert!(matches!(
        ev,
        Event::RequestFailed {
            error: RequestError::Timeout,
            ..
        }
    ));
    assert_eq!(
        failed_at.as_millis(),
        70372,
        "31 T, within MAX_TRANSMIT_WAIT (93 s)"
    );
}

#[test]
fn cocoa_a_measured_path_retransmits_after_its_rto_backing_off_by_three() {
    // One exchange over 10 ms each way gives SRTT 20 ms, RTTVAR 10 ms: the RTO is
    // SRTT + max(4 RTTVAR, 100 ms) = 120 ms (no 1 s floor), T = 120-180 ms with the jitter;
    // below 1 s the timeout triples at each retransmission: 0, T, 4T, 13T, 40T, failing at
    // 121T (RFC 7252's doubling from ACK_TIMEOUT would wait 2-3 s before the first).
    let mut sim = Sim::new(LinkConfig {
        delay: Duration::from_millis(10),
        ..LinkConfig::default()
    });
    let c = sim.add(cfg(7), None);
    let s = sim.add(cfg(8), Some(echo_server()));
    let server = sim.nodes[s].addr;
    let now = sim.now;
    sim.nodes[c]
        .ep
        .request(now, server, Request::new(Code::GET, "/x"));
    assert!(sim.run_to_event(c, Duration::from_secs(10)));
    assert!(matches!(sim.nodes[c].events[0].1, Event::Response { .. }));
    sim.link.loss = 1.0;
    sim.log.clear();
    sim.nodes[c].events.clear();
    let start = sim.elapsed();
    let now = sim.now;
    sim.nodes[c]
        .ep
        .request(now, server, Request::new(Code::GET, "/y"));
    assert!(sim.run_to_event(c, Duration::from_secs(60)));
    let times: Vec<f64> = sim
        .log
        .iter()
        .map(|r| (r.at - start).as_secs_f64() * 1e3)
        .collect();
    assert_eq!(times.len(), 5, "{times:?}");
    let t = times[1];
    assert!((120.0..=180.0).contains(&t), "first timeout {t} ms");
    for (k, at) in times.iter().enumerate() {
        let expected = t * (3f64.powi(k as i32) - 1.0) / 2.0;
        assert!(
            (at - expected).abs() <= 2.0,
            "transmission {k} at {at} ms, expected {expected}"
        );
    }
    let failed_at = (sim.nodes[c].events[0].0 - start).as_secs_f64() * 1e3;
    assert!(
        (failed_at - 121.0 * t).abs() <= 3.0,
        "failed at {failed_at} ms, T = {t} ms"
    );
}

#[test]
fn rfc7252_4_8_transmission_parameters_are_configurable() {
    let mut sim = Sim::new(LinkConfig {
        loss: 1.0,
        ..LinkConfig::default()
    });
    let fast = EndpointConfig {
        ack_timeout: Duration::from_millis(100),
        ack_random_factor: 1.0,
        max_retransmit: 2,
        ..cfg(3)
    };
    let c = sim.add(fast, None);
    let s = sim.add(cfg(4), None);
    let server = sim.nodes[s].addr;
    let now = sim.now;
    sim.nodes[c]
        .ep
        .request(now, server, Request::new(Code::GET, "/x"));
    assert!(sim.run_to_event(c, Duration::from_secs(10)));
    let times: Vec<u128> = sim.log.iter().map(|r| r.at.as_millis()).collect();
    assert_eq!(times, [0, 100, 300]);
    assert_eq!(sim.nodes[c].events[0].0.as_millis(), 700);
}

#[test]
fn rfc7252_4_5_duplicate_con_answered_from_cache_handler_runs_once() {
    let mut sim = Sim::new(LinkConfig::default());
    let s = sim.add(cfg(2), Some(echo_server()));
    let peer = "127.0.0.9:5683".parse().unwrap_or_else(|_| unreachable!());
    let mut req = Message::empty(Type::Con, 0x1234);
    req.code = Code::GET;
    req.token = coap::Token::new(&[9, 9]).unwrap_or_default();
    req.options.set_path("/dup");
    let bytes = req.encode();
    sim.inject(peer, s, &bytes);
    sim.run_until(Duration::from_secs(1), |_| false);
    sim.inject(peer, s, &bytes);
    sim.run_until(Duration::from_secs(1), |_| false);
    assert_eq!(sim.nodes[s].requests_seen, 1);
    let replies: Vec<_> = sim
        .log
        .iter()
        .filter(|r| r.from == sim.nodes[s].addr)
        .collect();
    assert_eq!(replies.len(), 2);
    assert_eq!(replies[0].msg, replies[1].msg, "the same ACK again");
    assert_eq!(replies[0].msg.as_ref().map(|m| m.message_id), Some(0x1234));
}

#[test]
fn rfc7252_4_5_duplicate_of_pending_request_gets_empty_ack() {
    let mut sim = Sim::new(LinkConfig::default());
    let s = sim.add(
        cfg(2),
        Some(Box::new(|_| {
            Reply::After(Duration::from_secs(30), Response::new(Code::CHANGED))
        })),
    );
    let peer = "127.0.0.9:5683".parse().unwrap_or_else(|_| unreachable!());
    let mut req = Message::empty(Type::Con, 77);
    req.code = Code::PUT;
    req.token = coap::Token::new(&[1]).unwrap_or_default();
    let bytes = req.encode();
    sim.inject(peer, s, &bytes);
    sim.run_until(Duration::from_millis(100), |_| false);
    sim.inject(peer, s, &bytes);
    sim.run_until(Duration::from_millis(100), |_| false);
    assert_eq!(sim.nodes[s].requests_seen, 1);
    let l = lines(&sim);
    assert_eq!(l.len(), 1, "{l:?}");
    assert!(l[0].starts_with("105 ms ACK 0.00 mid=77"), "{l:?}");
}

#[test]
fn rfc7252_4_3_ping_is_answered_with_reset() {
    let mut sim = Sim::new(LinkConfig::default());
    let c = sim.add(cfg(1), None);
    let s = sim.add(cfg(2), None);
    let server = sim.nodes[s].addr;
    let now = sim.now;
    let id = sim.nodes[c].ep.ping(now, server);
    assert!(sim.run_to_event(c, Duration::from_secs(5)));
    assert!(matches!(sim.nodes[c].events[0].1, Event::Pong { id: got } if got == id));
    let l = lines(&sim);
    assert!(
        l[0].contains("CON 0.00") && l[1].contains("RST 0.00"),
        "{l:?}"
    );
}

#[test]
fn rfc7252_5_4_1_unknown_critical_option_in_con_request_gives_4_02() {
    let mut sim = Sim::new(LinkConfig::default());
    let c = sim.add(cfg(1), None);
    let s = sim.add(cfg(2), Some(echo_server()));
    let server = sim.nodes[s].addr;
    let mut req = Request::new(Code::GET, "/x");
    req.options.push(OptionNumber(2051), b"?");
    let now = sim.now;
    sim.nodes[c].ep.request(now, server, req);
    assert!(sim.run_to_event(c, Duration::from_secs(5)));
    match &sim.nodes[c].events[0].1 {
        Event::Response { response, .. } => {
            assert_eq!(response.code, Code::BAD_OPTION);
            assert!(String::from_utf8_lossy(&response.payload).contains("2051"));
        }
        other => panic!("{other:?}"),
    }
    assert_eq!(
        sim.nodes[s].requests_seen, 0,
        "never reaches the application"
    );
}

#[test]
fn rfc7252_5_4_1_unknown_critical_option_in_non_request_is_rejected_with_reset() {
    let mut sim = Sim::new(LinkConfig::default());
    let s = sim.add(cfg(2), Some(echo_server()));
    let peer = "127.0.0.9:5683".parse().unwrap_or_else(|_| unreachable!());
    let mut req = Message::empty(Type::Non, 5);
    req.code = Code::GET;
    req.options.push(OptionNumber(2051), b"?");
    sim.inject(peer, s, &req.encode());
    sim.run_until(Duration::from_secs(1), |_| false);
    let l = lines(&sim);
    assert_eq!(l.len(), 1);
    assert!(l[0].contains("RST 0.00 mid=5"), "{l:?}");
}

#[test]
fn rfc7252_5_4_1_unknown_elective_option_is_ignored() {
    let mut sim = Sim::new(LinkConfig::default());
    let c = sim.add(cfg(1), None);
    let s = sim.add(cfg(2), Some(echo_server()));
    let server = sim.nodes[s].addr;
    let mut req = Request::new(Code::GET, "/x");
    req.options.push(OptionNumber(2050), b"?");
    let now = sim.now;
    sim.nodes[c].ep.request(now, server, req);
    assert!(sim.run_to_event(c, Duration::from_secs(5)));
    assert!(
        matches!(&sim.nodes[c].events[0].1, Event::Response { response, .. } if response.code == Code::CONTENT)
    );
}

#[test]
fn rfc7252_4_2_reset_fails_the_request() {
    let mut sim = Sim::new(LinkConfig::default());
    let c = sim.add(cfg(1), None);
    let s = sim.add(cfg(2), None);
    let server = sim.nodes[s].addr;
    let now = sim.now;
    sim.nodes[c]
        .ep
        .request(now, server, Request::new(Code::GET, "/x"));
    // The server answers the CON with a Reset by hand.
    sim.run_until(Duration::from_millis(6), |_| false);
    let mid = sim.log[0].msg.as_ref().map_or(0, |m| m.message_id);
    sim.inject(server, c, &Message::empty(Type::Rst, mid).encode());
    assert!(sim.run_to_event(c, Duration::from_secs(5)));
    assert!(matches!(
        sim.nodes[c].events[0].1,
        Event::RequestFailed {
            error: RequestError::Reset,
            ..
        }
    ));
}

#[test]
fn rfc7252_4_3_non_request_gets_non_response() {
    let mut sim = Sim::new(LinkConfig::default());
    let c = sim.add(cfg(1), None);
    let s = sim.add(cfg(2), Some(echo_server()));
    let server = sim.nodes[s].addr;
    let mut req = Request::new(Code::GET, "/n");
    req.confirmable = false;
    let now = sim.now;
    sim.nodes[c].ep.request(now, server, req);
    assert!(sim.run_to_event(c, Duration::from_secs(5)));
    let l = lines(&sim);
    assert!(
        l[0].contains("NON 0.01") && l[1].contains("NON 2.05"),
        "{l:?}"
    );
}

#[test]
fn rfc7252_5_3_2_unmatched_con_response_is_reset() {
    let mut sim = Sim::new(LinkConfig::default());
    let c = sim.add(cfg(1), None);
    let stranger = "127.0.0.9:5683".parse().unwrap_or_else(|_| unreachable!());
    let mut resp = Message::empty(Type::Con, 40);
    resp.code = Code::CONTENT;
    resp.token = coap::Token::new(&[1, 2, 3, 4]).unwrap_or_default();
    sim.inject(stranger, c, &resp.encode());
    sim.run_until(Duration::from_secs(1), |_| false);
    assert!(lines(&sim)[0].contains("RST 0.00 mid=40"));
    assert!(sim.nodes[c].events.is_empty());
}

#[test]
fn rfc7252_4_7_nstart_limits_outstanding_interactions_per_peer() {
    for nstart in [1usize, 2] {
        let mut sim = Sim::new(LinkConfig::default());
        let c = sim.add(EndpointConfig { nstart, ..cfg(1) }, None);
        let slow: crate::sim::Handler =
            Box::new(|_| Reply::After(Duration::from_secs(3), Response::new(Code::CONTENT)));
        let s = sim.add(cfg(2), Some(slow));
        let server = sim.nodes[s].addr;
        let now = sim.now;
        for _ in 0..4 {
            sim.nodes[c]
                .ep
                .request(now, server, Request::new(Code::GET, "/q"));
        }
        assert!(sim.run_until(Duration::from_secs(60), |s| s.nodes[c].events.len() == 4));
        let requests: Vec<u128> = sim
            .log
            .iter()
            .filter(|r| r.msg.as_ref().is_some_and(|m| m.code == Code::GET))
            .map(|r| r.at.as_millis() / 1000)
            .collect();
        // Each interaction takes about 3 s; with NSTART requests at a time they go out in
        // waves of NSTART.
        let expected: Vec<u128> = (0..4).map(|k| (k / nstart as u128) * 3).collect();
        assert_eq!(requests, expected, "nstart {nstart}");
    }
}

#[test]
fn rfc7390_2_7_no_error_response_to_multicast_request() {
    let mut sim = Sim::new(LinkConfig::default());
    let s = sim.add(
        cfg(2),
        Some(Box::new(|_| {
            Reply::Now(Response::diagnostic(Code::NOT_FOUND, "no"))
        })),
    );
    let peer = "127.0.0.9:5683".parse().unwrap_or_else(|_| unreachable!());
    let mut req = Message::empty(Type::Non, 9);
    req.code = Code::GET;
    let data = req.encode();
    let now = sim.now;
    sim.nodes[s].ep.handle(now, peer, &data, true);
    sim.run_until(Duration::from_secs(1), |_| false);
    assert_eq!(sim.nodes[s].requests_seen, 1);
    assert!(sim.log.is_empty(), "{:?}", lines(&sim));
}

#[test]
fn same_seed_gives_identical_transcript() {
    let run = || {
        let mut sim = Sim::new(LinkConfig::lossy(0.2, 11));
        let c = sim.add(cfg(5), None);
        let s = sim.add(cfg(6), Some(echo_server()));
        let server = sim.nodes[s].addr;
        let now = sim.now;
        for _ in 0..5 {
            sim.nodes[c]
                .ep
                .request(now, server, Request::new(Code::GET, "/d"));
        }
        sim.run_until(Duration::from_secs(600), |s| s.nodes[c].events.len() == 5);
        sim.log
            .iter()
            .map(|r| (r.at, r.msg.as_ref().map(Message::encode), r.lost))
            .collect::<Vec<_>>()
    };
    let a = run();
    assert!(a.len() > 10);
    assert_eq!(a, run());
}

#[test]
fn malformed_datagram_to_con_gets_reset_and_never_panics() {
    let mut sim = Sim::new(LinkConfig::default());
    let s = sim.add(cfg(2), Some(echo_server()));
    let peer = "127.0.0.9:5683".parse().unwrap_or_else(|_| unreachable!());
    // CON, token length 9: a message format error (RFC 7252 §3), answered with RST.
    sim.inject(peer, s, &[0x49, 0x01, 0x00, 0x10]);
    // Version 2: silently ignored.
    sim.inject(peer, s, &[0x80, 0x01, 0x00, 0x11]);
    sim.run_until(Duration::from_secs(1), |_| false);
    let l = lines(&sim);
    assert_eq!(l.len(), 1, "{l:?}");
    assert!(l[0].contains("RST 0.00 mid=16"));
}

#[test]
fn rfc7252_5_3_1_token_length_is_configurable_and_echoed() {
    for token_len in [0usize, 1, 4, 8] {
        let mut sim = Sim::new(LinkConfig::default());
        let c = sim.add(
            EndpointConfig {
                token_len,
                ..cfg(1)
            },
            None,
        );
        let s = sim.add(cfg(2), Some(echo_server()));
        let server = sim.nodes[s].addr;
        let now = sim.now;
        sim.nodes[c]
            .ep
            .request(now, server, Request::new(Code::GET, "/t"));
        assert!(sim.run_to_event(c, Duration::from_secs(5)));
        let tokens: Vec<usize> = sim
            .log
            .iter()
            .filter_map(|r| r.msg.as_ref())
            .map(|m| m.token.len())
            .collect();
        assert_eq!(tokens, [token_len, token_len]);
    }
}

#[test]
fn rfc7252_4_4_message_ids_differ_between_messages() {
    let mut sim = Sim::new(LinkConfig::default());
    let c = sim.add(
        EndpointConfig {
            nstart: 8,
            ..cfg(1)
        },
        None,
    );
    let s = sim.add(cfg(2), Some(echo_server()));
    let server = sim.nodes[s].addr;
    let now = sim.now;
    for _ in 0..8 {
        sim.nodes[c]
            .ep
            .request(now, server, Request::new(Code::GET, "/m"));
    }
    assert!(sim.run_until(Duration::from_secs(5), |s| s.nodes[c].events.len() == 8));
    let mut mids: Vec<u16> = sim
        .log
        .iter()
        .filter(|r| r.from == sim.nodes[c].addr)
        .filter_map(|r| r.msg.as_ref().map(|m| m.message_id))
        .collect();
    mids.sort_unstable();
    mids.dedup();
    assert_eq!(mids.len(), 8);
}

#[test]
fn rfc7252_5_2_2_separate_responses_survive_20_percent_loss() {
    let mut sim = Sim::new(LinkConfig::lossy(0.2, 3));
    let c = sim.add(
        EndpointConfig {
            nstart: 4,
            ..cfg(1)
        },
        None,
    );
    let slow: crate::sim::Handler = Box::new(|req| {
        let body = format!("done {}", req.options.path_string());
        Reply::After(
            Duration::from_secs(2),
            Response::new(Code::CONTENT).with_payload(body),
        )
    });
    let s = sim.add(cfg(2), Some(slow));
    let server = sim.nodes[s].addr;
    let now = sim.now;
    for k in 0..20 {
        sim.nodes[c]
            .ep
            .request(now, server, Request::new(Code::POST, &format!("/job/{k}")));
    }
    assert!(sim.run_until(Duration::from_secs(3600), |s| s.nodes[c].events.len() == 20));
    let ok = sim.nodes[c]
        .events
        .iter()
        .filter(|(_, e)| matches!(e, Event::Response { response, .. } if response.payload.starts_with(b"done /job/")))
        .count();
    // A request whose five transmissions are all lost (0.2^5) may time out; the rest
    // complete, each exactly once.
    assert!(ok >= 19, "{ok} of 20");
    assert!(
        sim.nodes[s].requests_seen <= 20,
        "duplicates never reach the handler twice"
    );
}

#[test]
fn an_acknowledged_exchange_leaves_no_timer_to_wake_for() {
    // A block-wise transfer acknowledges each block long before its retransmission
    // timer would fire; such timers must not keep waking the endpoint's owner.
    let mut sim = Sim::new(LinkConfig::default());
    let c = sim.add(cfg(1), None);
    let s = sim.add(cfg(2), Some(echo_server()));
    let server = sim.nodes[s].addr;
    let now = sim.now;
    sim.nodes[c]
        .ep
        .request(now, server, Request::new(Code::GET, "/a"));
    assert!(sim.run_to_event(c, Duration::from_secs(10)));
    assert!(matches!(&sim.nodes[c].events[0].1, Event::Response { .. }));
    assert_eq!(
        sim.nodes[c].ep.poll_timeout(),
        None,
        "a stale retransmission timer"
    );

    // With a deadline set, the deadline is the only timer left while the request runs.
    sim.nodes[c].events.clear();
    let mut req = Request::new(Code::GET, "/b");
    req.timeout = Some(Duration::from_secs(60));
    let now = sim.now;
    sim.nodes[c].ep.request(now, server, req);
    let armed = sim.nodes[c].ep.poll_timeout();
    assert!(
        armed.is_some_and(|t| t < now + Duration::from_secs(60)),
        "retransmission first"
    );
    assert!(sim.run_to_event(c, Duration::from_secs(10)));
    assert_eq!(sim.nodes[c].ep.poll_timeout(), None);
}

#[test]
fn a_remembered_round_trip_times_out_a_lost_first_con_in_milliseconds() {
    // The first CON is lost. Without an estimate it waits ACK_TIMEOUT (2-3 s); with a
    // round trip remembered from an earlier process (10 ms each way), SRTT + max(4 RTTVAR,
    // 100 ms) = 120 ms times the random factor (at most 1.5).
    for remembered in [None, Some(Duration::from_millis(20))] {
        let mut sim = Sim::new(LinkConfig {
            delay: Duration::from_millis(10),
            loss: 1.0,
            ..LinkConfig::default()
        });
        let c = sim.add(cfg(1), None);
        let s = sim.add(cfg(2), Some(echo_server()));
        let server = sim.nodes[s].addr;
        let now = sim.now;
        if let Some(rtt) = remembered {
            sim.nodes[c].ep.remember_rtt(now, server, rtt);
        }
        sim.nodes[c]
            .ep
            .request(now, server, Request::new(Code::GET, "/x"));
        sim.run_until(Duration::from_millis(1), |_| false);
        sim.link.loss = 0.0;
        assert!(sim.run_to_event(c, Duration::from_secs(10)));
        let sent: Vec<Duration> = sim
            .log
            .iter()
            .filter(|r| r.from == sim.nodes[c].addr)
            .map(|r| r.at)
            .collect();
        assert_eq!(sent.len(), 2, "{:?}", lines(&sim));
        let wait = sent[1] - sent[0];
        match remembered {
            None => assert!(wait >= Duration::from_secs(2), "{wait:?}"),
            Some(_) => assert!(
                (Duration::from_millis(120)..=Duration::from_millis(180)).contains(&wait),
                "{wait:?}"
            ),
        }
        let stats = sim.nodes[c].ep.path_stats(server).expect("a path");
        // The exchange gave a sample of its own (weak: its CON went twice), taken in.
        assert!(stats.srtt.is_some_and(|s| s > Duration::from_millis(20)));
    }
}

#[test]
fn a_new_port_on_a_known_host_starts_from_that_hosts_round_trip() {
    // Client A's slow request gets a separate response, a CON whose ACK gives the server
    // a round trip to A. Client B, another port of the same host (a later process),
    // starts from it: its own first CON would time out after about that, not 2-3 s.
    let mut sim = Sim::new(LinkConfig {
        delay: Duration::from_millis(10),
        ..LinkConfig::default()
    });
    let a = sim.add_at(([127, 0, 0, 1], 40001).into(), cfg(1), None);
    let b = sim.add_at(([127, 0, 0, 1], 40002).into(), cfg(3), None);
    let handler: crate::sim::Handler = Box::new(|_| {
        Reply::After(
            Duration::from_millis(1500),
            Response::new(Code::CONTENT).with_payload("late"),
        )
    });
    let s = sim.add_at(([127, 0, 0, 9], 5683).into(), cfg(2), Some(handler));
    let server = sim.nodes[s].addr;
    let (addr_a, addr_b) = (sim.nodes[a].addr, sim.nodes[b].addr);
    let now = sim.now;
    sim.nodes[a]
        .ep
        .request(now, server, Request::new(Code::GET, "/slow"));
    assert!(sim.run_to_event(a, Duration::from_secs(10)));
    // The client's ACK reaches the server.
    sim.run_until(Duration::from_millis(15), |_| false);
    let to_a = sim.nodes[s].ep.path_stats(addr_a).and_then(|p| p.srtt);
    assert!(
        to_a.is_some_and(|d| d >= Duration::from_millis(20)),
        "{to_a:?}"
    );
    let now = sim.now;
    sim.nodes[b]
        .ep
        .request(now, server, Request::new(Code::GET, "/slow"));
    // The server's separate response to B has left (at 1.5 s) and is not acknowledged
    // yet: its timeout came from A's round trip.
    sim.run_until(Duration::from_millis(1515), |_| false);
    let to_b = sim.nodes[s].ep.path_stats(addr_b).and_then(|p| p.srtt);
    assert_eq!(to_b, to_a);
    // Another host learns nothing from it.
    assert_eq!(sim.nodes[a].ep.path_stats(addr_b), None);
}
