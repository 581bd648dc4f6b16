//! Windowed Block2 downloads in the simulator: bit-exact under loss, duplication and
//! reordering, deterministic per seed, faster than stop-and-wait, fair to each other, and
//! back to stop-and-wait with servers that do not serve blocks out of order.

use std::cell::Cell;
use std::rc::Rc;
use std::time::Duration;

use bytes::Bytes;
use coap::{
    Code, Congestion, Event, OptionNumber, PathStats, Request, RequestId, Response, RoundTrace,
    Transfer,
};

use crate::blockwise::{body, cfg, no_store, response, serve};
use crate::sim::{Handler, LinkConfig, Reply, Sim, Wakeups};

const TEN_MB: usize = 10_032_012;

/// A 20 ms round trip (10 ms each way), with `loss` each way and, if lossy, duplicates
/// and up to 4 ms of reordering jitter.
pub(crate) fn link(loss: f64, seed: u64) -> LinkConfig {
    LinkConfig {
        loss,
        duplicate: loss / 4.0,
        delay: Duration::from_millis(10),
        jitter: if loss > 0.0 {
            Duration::from_millis(4)
        } else {
            Duration::ZERO
        },
        seed,
        ..LinkConfig::default()
    }
}

/// What one download did: the simulated time it took, the body, the path's counters.
pub(crate) struct Outcome {
    pub(crate) elapsed: Duration,
    pub(crate) body: Bytes,
    pub(crate) stats: PathStats,
    /// Every datagram, as `Record::line` prints it (when recorded).
    pub(crate) trace: Vec<String>,
    /// The client's congestion controller, round by round.
    pub(crate) rounds: Vec<RoundTrace>,
}

/// A GET of `data` with `transfer` through `link`.
pub(crate) fn download(
    link: LinkConfig,
    data: &Bytes,
    transfer: Transfer,
    record: bool,
) -> Outcome {
    download_waking(link, data, transfer, record, None)
}

/// The same, with the client's thread waking up as `wakeups` says.
fn download_waking(
    link: LinkConfig,
    data: &Bytes,
    transfer: Transfer,
    record: bool,
    wakeups: Option<Wakeups>,
) -> Outcome {
    let mut sim = Sim::new(link);
    sim.record = record;
    let c = sim.add(
        coap::EndpointConfig {
            trace_congestion: true,
            ..cfg(1)
        },
        None,
    );
    sim.nodes[c].wakeups = wakeups;
    let s = sim.add(cfg(2), Some(serve(data.clone(), Rc::new(Cell::new(0)))));
    let server = sim.nodes[s].addr;
    let now = sim.now;
    let mut req = Request::new(Code::GET, "/big");
    req.transfer = Some(transfer);
    sim.nodes[c].ep.request(now, server, req);
    assert!(sim.run_to_event(c, Duration::from_secs(3600)), "no outcome");
    let body = response(&sim, c).payload.clone();
    let mut rounds = Vec::new();
    while let Some((peer, round)) = sim.nodes[c].ep.poll_round_trace() {
        assert_eq!(peer, server);
        rounds.push(round);
    }
    Outcome {
        rounds,
        elapsed: sim.elapsed(),
        body,
        stats: sim.nodes[c].ep.path_stats(server).expect("a path"),
        trace: sim.log.iter().map(|r| r.line()).collect(),
    }
}

#[test]
fn ten_mb_arrive_bit_exact_at_0_2_5_and_20_percent_loss_with_duplicates_and_reordering() {
    let data = body(TEN_MB, 7);
    for loss in [0.0, 0.02, 0.05, 0.20] {
        let o = download(link(loss, 11), &data, Transfer::Window, false);
        assert!(o.body == data, "body differs at {loss} loss");
        if loss > 0.0 {
            assert!(o.stats.blocks_lost > 0, "loss {loss} found no lost block");
        }
    }
}

#[test]
fn with_nstart_chosen_a_window_keeps_nstart_block_requests_in_flight() {
    let data = body(300_000, 6);
    let mut sim = Sim::new(link(0.02, 3));
    sim.record = false;
    let mut client = cfg(1);
    client.congestion = Congestion::Nstart;
    client.nstart = 4;
    let c = sim.add(client, None);
    let s = sim.add(cfg(2), Some(serve(data.clone(), Rc::new(Cell::new(0)))));
    let server = sim.nodes[s].addr;
    let now = sim.now;
    sim.nodes[c]
        .ep
        .request(now, server, Request::new(Code::GET, "/big"));
    assert!(sim.run_to_event(c, Duration::from_secs(3600)), "no outcome");
    assert!(response(&sim, c).payload == data);
    let stats = sim.nodes[c].ep.path_stats(server).expect("a path");
    assert_eq!(stats.max_window, 4, "{stats:?}");
    assert!(stats.blocks_lost > 0, "2 % loss found no lost block");
    // BBR's initial window alone is 10 requests.
    let bbr = download(link(0.02, 3), &data, Transfer::Window, false);
    assert!(bbr.stats.max_window > 4, "{:?}", bbr.stats);
}

#[test]
fn a_seed_gives_the_same_transfer_every_time() {
    let data = body(300_000, 3);
    let a = download(link(0.05, 5), &data, Transfer::Window, true);
    let b = download(link(0.05, 5), &data, Transfer::Window, true);
    assert!(a.body == data);
    assert_eq!(a.elapsed, b.elapsed);
    assert_eq!(a.trace, b.trace);
    assert_eq!(a.stats, b.stats);
}

#[test]
fn the_window_is_an_order_of_magnitude_faster_than_stop_and_wait() {
    let data = body(921_610, 9);
    for loss in [0.0, 0.02] {
        let window = download(link(loss, 2), &data, Transfer::Window, false);
        let stop = download(link(loss, 2), &data, Transfer::StopAndWait, false);
        assert!(window.body == data && stop.body == data);
        assert!(
            window.elapsed * 10 < stop.elapsed,
            "at {loss} loss: window {:?}, stop-and-wait {:?}",
            window.elapsed,
            stop.elapsed
        );
    }
}

#[test]
fn two_downloads_through_one_bottleneck_share_it() {
    // 50 Mbit/s out of the server with a 64 KB drop-tail queue, 20 ms round trip.
    let data = body(2_764_810, 4);
    let mut sim = Sim::new(LinkConfig {
        rate: Some(6_250_000),
        queue_bytes: 64_000,
        ..link(0.0, 8)
    });
    sim.record = false;
    let clients = [sim.add(cfg(1), None), sim.add(cfg(3), None)];
    let s = sim.add(cfg(2), Some(serve(data.clone(), Rc::new(Cell::new(0)))));
    let server = sim.nodes[s].addr;
    let now = sim.now;
    for c in clients {
        let mut req = Request::new(Code::GET, "/big");
        req.progress = true;
        sim.nodes[c].ep.request(now, server, req);
    }
    let finished = |sim: &Sim, c: usize| {
        sim.nodes[c]
            .events
            .iter()
            .any(|(_, e)| matches!(e, Event::Response { .. }))
    };
    assert!(sim.run_until(Duration::from_secs(60), |sim| {
        clients.iter().any(|&c| finished(sim, c))
    }));
    let done = |c: usize| {
        sim.nodes[c]
            .events
            .iter()
            .filter_map(|(_, e)| match e {
                Event::Progress { done, .. } => Some(*done),
                _ => None,
            })
            .max()
            .unwrap_or(0)
    };
    let (a, b) = (done(clients[0]), done(clients[1]));
    let share = a as f64 / (a + b) as f64;
    assert!(
        (0.35..=0.65).contains(&share),
        "shares {a} and {b} bytes when the first finished"
    );
    assert!(sim.run_until(Duration::from_secs(60), |sim| {
        clients.iter().all(|&c| finished(sim, c))
    }));
    for c in clients {
        match &sim.nodes[c].events.last().expect("an outcome").1 {
            Event::Response { response, .. } => assert!(response.payload == data),
            other => panic!("expected the body, got {other:?}"),
        }
    }
}

/// The window for a fixed seed, datagram by datagram: block 0's response is lost and
/// its CON sent again after ACK_TIMEOUT (no estimate yet); then the initial window of 10
/// NON requests goes at once, block 2's response is lost, and block 2 is asked for again
/// one loss delay (`9/8 (SRTT + 4 RTTVAR)`) after its request, while the window has moved
/// on to block 11.
#[test]
fn the_window_and_its_loss_timer_for_a_fixed_seed() {
    let data = body(12_000, 1);
    let o = download(link(0.15, 3), &data, Transfer::Window, true);
    assert!(o.body == data);
    let expected = [
        "0 ms CON 0.01 mid=36460",
        "11 ms ACK 2.05 mid=36460 b2=0/1/1024 LOST",
        "2211 ms CON 0.01 mid=36460",
        "2221 ms ACK 2.05 mid=36460 b2=0/1/1024",
        "2232 ms NON 0.01 mid=36461 b2=1/0/1024",
        "2232 ms NON 0.01 mid=36462 b2=2/0/1024",
        "2232 ms NON 0.01 mid=36463 b2=3/0/1024",
        "2232 ms NON 0.01 mid=36464 b2=4/0/1024",
        "2232 ms NON 0.01 mid=36465 b2=5/0/1024",
        "2232 ms NON 0.01 mid=36466 b2=6/0/1024",
        "2232 ms NON 0.01 mid=36467 b2=7/0/1024",
        "2232 ms NON 0.01 mid=36468 b2=8/0/1024",
        "2232 ms NON 0.01 mid=36469 b2=9/0/1024",
        "2232 ms NON 0.01 mid=36470 b2=10/0/1024",
        "2243 ms NON 2.05 mid=35786 b2=8/1/1024",
        "2243 ms NON 2.05 mid=35787 b2=2/1/1024 LOST",
        "2244 ms NON 2.05 mid=35788 b2=7/1/1024",
        "2244 ms NON 2.05 mid=35789 b2=5/1/1024",
        "2244 ms NON 2.05 mid=35790 b2=1/1/1024",
        "2245 ms NON 2.05 mid=35791 b2=4/1/1024",
        "2245 ms NON 2.05 mid=35792 b2=9/1/1024",
        "2245 ms NON 2.05 mid=35793 b2=6/1/1024",
        "2245 ms NON 2.05 mid=35794 b2=10/1/1024",
        "2246 ms NON 2.05 mid=35795 b2=3/1/1024",
        "2255 ms NON 0.01 mid=36471 b2=11/0/1024",
        "2267 ms NON 2.05 mid=35796 b2=11/0/1024",
        "2273 ms NON 0.01 mid=36472 b2=2/0/1024",
        "2285 ms NON 2.05 mid=35797 b2=2/1/1024",
    ];
    assert_eq!(o.trace, expected);
    assert_eq!(o.elapsed.as_millis(), 2296);
    let s = o.stats;
    assert_eq!(s.srtt.map(|d| d.as_micros()), Some(23_744));
    assert_eq!(s.rttvar.as_micros(), 2_374);
    assert_eq!(
        (
            s.retransmissions,
            s.block_requests,
            s.blocks_lost,
            s.max_window
        ),
        (1, 12, 1, 10)
    );
}

#[test]
fn a_server_that_serves_blocks_only_in_order_gets_stop_and_wait() {
    // No store: every block request reaches the handler, which (as a server generating
    // its body as it goes would) refuses a block beyond the next one it has.
    let data = body(40_000, 5);
    let served = data.clone();
    let next = Rc::new(Cell::new(0u32));
    let refused = Rc::new(Cell::new(0u32));
    let (expected, refusals) = (next.clone(), refused.clone());
    let handler: Handler = Box::new(move |req| {
        let num = req.options.block2().map_or(0, |b| b.num);
        if num > expected.get() {
            refusals.set(refusals.get() + 1);
            return Reply::Now(Response::diagnostic(
                Code::REQUEST_ENTITY_INCOMPLETE,
                "blocks in order only",
            ));
        }
        expected.set(expected.get().max(num + 1));
        let mut response = Response::new(Code::CONTENT).with_payload(served.clone());
        response.options.set(OptionNumber::ETAG, *b"v1");
        Reply::Now(response)
    });
    // Jitter reorders the window's requests on their way.
    let mut sim = Sim::new(LinkConfig {
        jitter: Duration::from_millis(4),
        ..link(0.0, 1)
    });
    let c = sim.add(cfg(1), None);
    let s = sim.add(no_store(2), Some(handler));
    let server = sim.nodes[s].addr;
    let now = sim.now;
    sim.nodes[c]
        .ep
        .request(now, server, Request::new(Code::GET, "/big"));
    assert!(sim.run_to_event(c, Duration::from_secs(600)));
    let got = response(&sim, c);
    assert_eq!(got.code, Code::CONTENT);
    assert!(got.payload == data);
    assert_eq!(
        got.options.uint(OptionNumber::SIZE2),
        Some(data.len() as u32)
    );
    assert!(refused.get() > 0, "the window asked out of order");
    assert_eq!(next.get(), 40);
}

#[test]
fn two_downloads_from_one_peer_share_its_window() {
    // NSTART 2: both run at once, drawing on the one controller of their path.
    let (a, b) = (body(300_000, 1), body(200_000, 2));
    let mut sim = Sim::new(link(0.02, 4));
    sim.record = false;
    let c = sim.add(
        coap::EndpointConfig {
            nstart: 2,
            ..cfg(1)
        },
        None,
    );
    let (sa, sb) = (a.clone(), b.clone());
    let handler: Handler = Box::new(move |req| {
        let body = if req.options.path_string() == "/a" {
            &sa
        } else {
            &sb
        };
        Reply::Now(Response::new(Code::CONTENT).with_payload(body.clone()))
    });
    let s = sim.add(cfg(2), Some(handler));
    let server = sim.nodes[s].addr;
    let now = sim.now;
    let ia = sim.nodes[c]
        .ep
        .request(now, server, Request::new(Code::GET, "/a"));
    let ib = sim.nodes[c]
        .ep
        .request(now, server, Request::new(Code::GET, "/b"));
    both_bodies(&mut sim, c, Duration::from_secs(60), [(ia, &a), (ib, &b)]);
}

/// Runs `sim` for at most `limit` until client `c` holds two events, and checks that they
/// are the responses to the two requests, each with its body.
fn both_bodies(sim: &mut Sim, c: usize, limit: Duration, expected: [(RequestId, &Bytes); 2]) {
    assert!(sim.run_until(limit, |sim| sim.nodes[c].events.len() == 2));
    for (_, e) in &sim.nodes[c].events {
        match e {
            Event::Response { id, response } => {
                let (_, body) = expected
                    .iter()
                    .find(|(want, _)| want == id)
                    .unwrap_or_else(|| panic!("a response to no request of the two: {id:?}"));
                assert!(response.payload == **body);
            }
            other => panic!("expected the two bodies, got {other:?}"),
        }
    }
}

#[test]
fn no_message_id_comes_round_within_the_exchange_lifetime() {
    // 80 MB are 78,000 block requests: more than the 65,536 message IDs. With an
    // EXCHANGE_LIFETIME of 60 s the window must wait for the first IDs to be free again,
    // where without the rule it would take a few seconds.
    let data = body(80_000_000, 6);
    let mut sim = Sim::new(link(0.0, 1));
    sim.record = false;
    let lifetime = Duration::from_secs(60);
    let c = sim.add(
        coap::EndpointConfig {
            exchange_lifetime: lifetime,
            ..cfg(1)
        },
        None,
    );
    let s = sim.add(cfg(2), Some(serve(data.clone(), Rc::new(Cell::new(0)))));
    let server = sim.nodes[s].addr;
    let now = sim.now;
    sim.nodes[c]
        .ep
        .request(now, server, Request::new(Code::GET, "/big"));
    assert!(sim.run_to_event(c, Duration::from_secs(3600)));
    assert!(response(&sim, c).payload == data);
    // One lifetime of waiting, and the IDs free again at the pace they were used.
    let took = sim.elapsed();
    assert!(
        took > lifetime && took < lifetime + Duration::from_secs(5),
        "{took:?}"
    );
}

#[test]
fn each_server_has_message_ids_of_its_own() {
    // Two 40 MB downloads at once from two servers are 78,000 block requests: more than the
    // 65,536 message IDs in all, 39,000 with each server. An ID must be unique per pair of
    // endpoints within EXCHANGE_LIFETIME (RFC 7252 §4.4), so neither download waits for
    // the lifetime of 60 s; counted over both servers together, the IDs ran out and the
    // downloads waited for the first ones to be free again.
    let a = body(40_000_000, 7);
    let b = body(40_000_000, 8);
    let mut sim = Sim::new(link(0.0, 1));
    sim.record = false;
    let lifetime = Duration::from_secs(60);
    let c = sim.add(
        coap::EndpointConfig {
            exchange_lifetime: lifetime,
            ..cfg(1)
        },
        None,
    );
    let sa = sim.add(cfg(2), Some(serve(a.clone(), Rc::new(Cell::new(0)))));
    let sb = sim.add(cfg(3), Some(serve(b.clone(), Rc::new(Cell::new(0)))));
    let (server_a, server_b) = (sim.nodes[sa].addr, sim.nodes[sb].addr);
    let now = sim.now;
    let ia = sim.nodes[c]
        .ep
        .request(now, server_a, Request::new(Code::GET, "/big"));
    let ib = sim.nodes[c]
        .ep
        .request(now, server_b, Request::new(Code::GET, "/big"));
    both_bodies(&mut sim, c, Duration::from_secs(3600), [(ia, &a), (ib, &b)]);
    let took = sim.elapsed();
    assert!(took < lifetime, "{took:?}");
}

#[test]
fn a_slow_answer_that_comes_separately_in_blocks_is_fetched_whole() {
    // The handler takes 2 s: the server sends an empty ACK, then block 0 as a separate
    // CON; the client fetches the rest with its window (or stop-and-wait).
    for transfer in [Transfer::Window, Transfer::StopAndWait] {
        let data = body(20_000, 9);
        let mut sim = Sim::new(link(0.0, 1));
        let c = sim.add(cfg(1), None);
        let served = data.clone();
        let handler: Handler = Box::new(move |_| {
            Reply::After(
                Duration::from_secs(2),
                Response::new(Code::CONTENT).with_payload(served.clone()),
            )
        });
        let s = sim.add(cfg(2), Some(handler));
        let server = sim.nodes[s].addr;
        let now = sim.now;
        let mut req = Request::new(Code::POST, "/grab");
        req.transfer = Some(transfer);
        sim.nodes[c].ep.request(now, server, req);
        assert!(
            sim.run_to_event(c, Duration::from_secs(60)),
            "{transfer:?}: no outcome"
        );
        assert_eq!(response(&sim, c).payload, data, "{transfer:?}");
    }
}

#[test]
fn downloads_after_a_fallback_still_get_a_window() {
    // A path so lossy that the window gives up on it (three probe timeouts in a row) and
    // goes stop-and-wait; then the loss ends. The requests the window declared lost must
    // have left the path's count of requests in flight, or later windows never open.
    let data = body(100_000, 3);
    let mut l = link(0.45, 1);
    l.delay = Duration::from_millis(1);
    let mut sim = Sim::new(l);
    let c = sim.add(cfg(1), None);
    let s = sim.add(cfg(2), Some(serve(data.clone(), Rc::new(Cell::new(0)))));
    let server = sim.nodes[s].addr;
    let now = sim.now;
    sim.nodes[c]
        .ep
        .request(now, server, Request::new(Code::GET, "/big"));
    assert!(sim.run_to_event(c, Duration::from_secs(3600)), "no outcome");
    assert_eq!(response(&sim, c).payload, data);
    let fallbacks = sim.nodes[c]
        .ep
        .path_stats(server)
        .expect("a path")
        .window_fallbacks;
    assert!(fallbacks >= 1, "the lossy download fell back");
    sim.link.loss = 0.0;
    sim.link.duplicate = 0.0;
    sim.link.jitter = Duration::ZERO;
    for round in 0..5 {
        sim.nodes[c].events.clear();
        let started = sim.now;
        sim.nodes[c]
            .ep
            .request(started, server, Request::new(Code::GET, "/big"));
        assert!(
            sim.run_to_event(c, Duration::from_secs(60)),
            "round {round}: no outcome"
        );
        assert_eq!(response(&sim, c).payload, data, "round {round}");
        assert!(
            sim.now - started < Duration::from_secs(1),
            "round {round}: {:?} for 100 KB over a clean 2 ms path",
            sim.now - started
        );
    }
}

/// Issue 33's stall, in virtual time: a client whose timers wake 1-2 ticks of 4 ms late
/// (a receive timeout counted in jiffies) and whose thread does not run for 30 ms during
/// startup. Before the pacer learned how late its wake-ups are and before a sender behind
/// its schedule marked its samples app-limited, this download took 2.09 s with at most 13
/// requests in flight (the rate locked at what the first rounds showed); on time it takes
/// 168 ms.
#[test]
fn a_window_keeps_its_rate_when_timers_wake_late_and_the_thread_stalls() {
    let data = body(921_610, 9);
    let on_time = download_waking(link(0.0, 2), &data, Transfer::Window, false, None);
    let cases = [
        (
            0.0,
            Wakeups {
                tick: Duration::from_millis(4),
                stalls: vec![(Duration::from_millis(60), Duration::from_millis(30))],
            },
        ),
        (
            0.02,
            Wakeups {
                tick: Duration::from_millis(8),
                stalls: vec![
                    (Duration::from_millis(30), Duration::from_millis(15)),
                    (Duration::from_millis(60), Duration::from_millis(30)),
                    (Duration::from_millis(120), Duration::from_millis(10)),
                ],
            },
        ),
    ];
    for (loss, wakeups) in cases {
        let stalled: Duration = wakeups.stalls.iter().map(|s| s.1).sum();
        let o = download_waking(link(loss, 2), &data, Transfer::Window, false, Some(wakeups));
        assert!(o.body == data);
        // Within 1.3 times the on-time transfer, once the time the thread did not run
        // is added, and loss's share (about a loss delay per lost block's tail).
        let bound = (on_time.elapsed + stalled).mul_f64(if loss > 0.0 { 1.6 } else { 1.3 });
        assert!(
            o.elapsed <= bound,
            "at {loss} loss: {:?} (on time {:?}), max window {}",
            o.elapsed,
            on_time.elapsed,
            o.stats.max_window
        );
        // The 20 ms round trip carries over 5,000 blocks a second here: the window must
        // grow far past the initial 10 (the stall left it at 13).
        assert!(o.stats.max_window >= 200, "{:?}", o.stats);
        let after_startup: Vec<&RoundTrace> =
            o.rounds.iter().filter(|r| r.mode != "startup").collect();
        assert!(
            after_startup.iter().all(|r| r.window >= 100),
            "a round's window fell: {after_startup:?}"
        );
    }
}

#[test]
fn the_controllers_trace_has_a_round_per_round_trip_and_nothing_when_off() {
    let data = body(100_000, 4);
    let o = download_waking(link(0.0, 1), &data, Transfer::Window, false, None);
    assert!(o.body == data);
    // 97 blocks after block 0: startup doubles the initial 10 each round trip.
    let rounds: Vec<u64> = o.rounds.iter().map(|r| r.round).collect();
    assert!((3..=8).contains(&rounds.len()), "{rounds:?}");
    assert_eq!(rounds, (1..=rounds.len() as u64).collect::<Vec<_>>());
    // The first round: the initial window of 10 answered one round trip later (500
    // blocks a second), and what startup's gain sent meanwhile.
    let first = &o.rounds[0];
    assert_eq!((first.mode, first.samples), ("startup", 10));
    assert_eq!(first.max_sample, Some((500.0, false)));
    assert_eq!(first.window, 29, "2.885 times 10 blocks in flight");
    assert_eq!(first.min_rtt, Some(Duration::from_millis(20)));
    assert!(
        o.rounds.iter().all(|r| r.window >= 10 && r.late_sends == 0),
        "{:#?}",
        o.rounds
    );
    let sent: u32 = o.rounds.iter().map(|r| r.sent).sum();
    assert!(u64::from(sent) <= o.stats.block_requests);
    // Off (the default): nothing is recorded.
    let mut sim = Sim::new(link(0.0, 1));
    let c = sim.add(cfg(1), None);
    let s = sim.add(cfg(2), Some(serve(data, Rc::new(Cell::new(0)))));
    let server = sim.nodes[s].addr;
    let now = sim.now;
    sim.nodes[c]
        .ep
        .request(now, server, Request::new(Code::GET, "/big"));
    assert!(sim.run_to_event(c, Duration::from_secs(60)));
    assert_eq!(sim.nodes[c].ep.poll_round_trace(), None);
}
