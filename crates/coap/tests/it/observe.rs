//! RFC 7641 Observe and RFC 7390 multicast requests, in the simulator.

use std::time::Duration;

use coap::{Code, EndpointConfig, Event, ObservationId, OptionNumber, Request, Response};

use crate::sim::{GROUP, LinkConfig, Reply, Sim};

fn cfg(seed: u64) -> EndpointConfig {
    EndpointConfig {
        rng_seed: seed,
        ..EndpointConfig::default()
    }
}

fn observe_request(path: &str) -> Request {
    let mut req = Request::new(Code::GET, path);
    req.options.set_uint(OptionNumber::OBSERVE, 0);
    req
}

/// A client observing a server that answers registrations; returns the simulation, the
/// client and server indexes and the observation.
fn observed(link: LinkConfig) -> (Sim, usize, usize, ObservationId) {
    observed_by(link, cfg(2))
}

/// [`observed`] with the server's configuration.
fn observed_by(link: LinkConfig, server_cfg: EndpointConfig) -> (Sim, usize, usize, ObservationId) {
    let mut sim = Sim::new(link);
    let c = sim.add(cfg(1), None);
    let reg = std::rc::Rc::new(std::cell::Cell::new(None));
    let seen = reg.clone();
    let handler: crate::sim::Handler = Box::new(move |req| {
        seen.set(req.observe);
        let mut r = Response::new(Code::CONTENT).with_payload("v0");
        r.options.set_uint(OptionNumber::OBSERVE, 0);
        Reply::Now(r)
    });
    let s = sim.add(server_cfg, Some(handler));
    let server = sim.nodes[s].addr;
    let now = sim.now;
    sim.nodes[c]
        .ep
        .request(now, server, observe_request("/temp"));
    assert!(sim.run_to_event(c, Duration::from_secs(10)));
    let obs = reg.get().unwrap_or_else(|| panic!("no registration"));
    (sim, c, s, obs)
}

#[test]
fn rfc7641_3_observe_registration_then_five_notifications_in_order() {
    let (mut sim, c, s, obs) = observed(LinkConfig::default());
    assert!(
        matches!(&sim.nodes[c].events[0].1, Event::Response { response, .. }
        if response.options.uint(OptionNumber::OBSERVE).is_some() && &response.payload[..] == b"v0")
    );
    for k in 1..=5 {
        let now = sim.now;
        let body = format!("v{k}");
        assert!(
            sim.nodes[s]
                .ep
                .notify(now, obs, Response::new(Code::CONTENT).with_payload(body))
        );
        sim.run_until(Duration::from_secs(1), |_| false);
    }
    let bodies: Vec<String> = sim.nodes[c].events[1..]
        .iter()
        .map(|(_, e)| match e {
            Event::Notification { response, .. } => {
                String::from_utf8_lossy(&response.payload).into_owned()
            }
            other => panic!("{other:?}"),
        })
        .collect();
    assert_eq!(bodies, ["v1", "v2", "v3", "v4", "v5"]);
    // RFC 7641 §4.5: the fifth notification is confirmable.
    let types: Vec<bool> = sim
        .log
        .iter()
        .filter_map(|r| r.msg.as_ref())
        .filter(|m| m.options.contains(OptionNumber::OBSERVE) && m.code == Code::CONTENT)
        .map(|m| m.ty == coap::Type::Con)
        .collect();
    assert_eq!(types, [false, false, false, false, false, true]);
}

#[test]
fn rfc7641_3_4_reordered_older_notification_is_dropped() {
    let (mut sim, c, s, obs) = observed(LinkConfig {
        jitter: Duration::from_millis(50),
        ..LinkConfig::default()
    });
    // Two notifications sent 1 ms apart; with 50 ms of jitter the second may overtake the
    // first, and then the first (older) must not be delivered after it.
    for seed in 0..20 {
        let now = sim.now;
        let a = format!("a{seed}");
        let b = format!("b{seed}");
        sim.nodes[s]
            .ep
            .notify(now, obs, Response::new(Code::CONTENT).with_payload(a));
        sim.run_until(Duration::from_millis(1), |_| false);
        let now = sim.now;
        sim.nodes[s]
            .ep
            .notify(now, obs, Response::new(Code::CONTENT).with_payload(b));
        sim.run_until(Duration::from_secs(1), |_| false);
    }
    let bodies: Vec<String> = sim.nodes[c].events[1..]
        .iter()
        .filter_map(|(_, e)| match e {
            Event::Notification { response, .. } => {
                Some(String::from_utf8_lossy(&response.payload).into_owned())
            }
            _ => None,
        })
        .collect();
    for k in 0..20 {
        let b = bodies.iter().position(|x| *x == format!("b{k}"));
        let a = bodies.iter().position(|x| *x == format!("a{k}"));
        assert!(b.is_some(), "newest always delivered");
        if let (Some(a), Some(b)) = (a, b) {
            assert!(a < b, "older a{k} delivered after newer b{k}");
        }
    }
}

#[test]
fn rfc7641_3_6_cancelled_client_resets_next_notification_and_observation_ends() {
    let (mut sim, c, s, obs) = observed(LinkConfig::default());
    let id = match sim.nodes[c].events[0].1 {
        Event::Response { id, .. } => id,
        ref other => panic!("{other:?}"),
    };
    let now = sim.now;
    sim.nodes[c].ep.cancel(now, id);
    let now = sim.now;
    assert!(
        sim.nodes[s]
            .ep
            .notify(now, obs, Response::new(Code::CONTENT).with_payload("x"))
    );
    sim.run_until(Duration::from_secs(1), |_| false);
    assert!(
        sim.log
            .iter()
            .any(|r| r.msg.as_ref().is_some_and(|m| m.ty == coap::Type::Rst))
    );
    let now = sim.now;
    assert!(
        !sim.nodes[s]
            .ep
            .notify(now, obs, Response::new(Code::CONTENT)),
        "observation gone"
    );
}

#[test]
fn rfc7641_4_1_response_without_observe_declines_the_registration() {
    let mut sim = Sim::new(LinkConfig::default());
    let c = sim.add(cfg(1), None);
    let reg = std::rc::Rc::new(std::cell::Cell::new(None));
    let seen = reg.clone();
    let handler: crate::sim::Handler = Box::new(move |req| {
        seen.set(req.observe);
        Reply::Now(Response::new(Code::CONTENT).with_payload("plain"))
    });
    let s = sim.add(cfg(2), Some(handler));
    let server = sim.nodes[s].addr;
    let now = sim.now;
    sim.nodes[c]
        .ep
        .request(now, server, observe_request("/plain"));
    assert!(sim.run_to_event(c, Duration::from_secs(10)));
    let obs = reg.get().unwrap_or_else(|| panic!("no registration"));
    let now = sim.now;
    assert!(
        !sim.nodes[s]
            .ep
            .notify(now, obs, Response::new(Code::CONTENT))
    );
    assert_eq!(
        sim.nodes[c].ep.requests_in_flight(),
        0,
        "client request finished"
    );
}

#[test]
fn rfc7641_3_6_observe_1_deregisters() {
    let (mut sim, c, s, obs) = observed(LinkConfig::default());
    let mut req = Request::new(Code::GET, "/temp");
    req.options.set_uint(OptionNumber::OBSERVE, 1);
    // A deregistration must carry the registration's token: send it raw.
    let token = sim.log[0].msg.as_ref().map(|m| m.token).unwrap_or_default();
    let mut msg = coap::Message::empty(coap::Type::Con, 999);
    msg.code = Code::GET;
    msg.token = token;
    msg.options = req.options;
    let client = sim.nodes[c].addr;
    sim.inject(client, s, &msg.encode());
    sim.run_until(Duration::from_secs(1), |_| false);
    let now = sim.now;
    assert!(
        !sim.nodes[s]
            .ep
            .notify(now, obs, Response::new(Code::CONTENT))
    );
}

#[test]
fn rfc7959_2_6_large_notification_first_block_then_continuations_from_store() {
    let (mut sim, _c, s, obs) = observed(LinkConfig::default());
    let now = sim.now;
    let big = vec![7u8; 5000];
    assert!(
        sim.nodes[s]
            .ep
            .notify(now, obs, Response::new(Code::CONTENT).with_payload(big))
    );
    sim.run_until(Duration::from_secs(1), |_| false);
    let first = sim
        .log
        .iter()
        .rev()
        .find_map(|r| r.msg.as_ref().filter(|m| m.code == Code::CONTENT))
        .cloned();
    let first = first.unwrap_or_else(|| panic!("no notification"));
    assert_eq!(
        first.options.block2().map(|b| (b.num, b.more)),
        Some((0, true))
    );
    assert_eq!(first.options.uint(OptionNumber::SIZE2), Some(5000));
}

/// Block `num` of `/temp` (1 KiB blocks), asked by the client as RFC 7959 §2.6 has the
/// rest of a notification asked: a GET without Observe.
fn block_of_temp(sim: &mut Sim, c: usize, s: usize, num: u32) -> Response {
    let mut req = Request::new(Code::GET, "/temp");
    let opt = coap::BlockOpt {
        num,
        more: false,
        szx: 6,
    };
    req.options.set_block(OptionNumber::BLOCK2, opt);
    sim.nodes[c].events.clear();
    let (now, server) = (sim.now, sim.nodes[s].addr);
    let id = sim.nodes[c].ep.request(now, server, req);
    assert!(sim.run_to_event(c, Duration::from_secs(10)));
    let answer = sim.nodes[c].events.iter().find_map(|(_, e)| match e {
        Event::Response { id: got, response } if *got == id => Some(response.clone()),
        _ => None,
    });
    answer.unwrap_or_else(|| panic!("no answer to block {num}"))
}

/// RFC 7959 §2.6: a client fetching the rest of a large notification must not have it
/// replaced under it by the next notification. While it is partway through, the newer
/// representation waits; its blocks are served once the last block of the one being
/// fetched has been. (Replaced at once, every notification of a resource that changes
/// faster than its blocks arrive was fetched again whole, and a client ran out of
/// message IDs: 65,536 per EXCHANGE_LIFETIME.)
#[test]
fn rfc7959_2_6_a_notification_being_fetched_is_not_replaced_by_the_next() {
    let (mut sim, c, s, obs) = observed(LinkConfig::default());
    let notify = |sim: &mut Sim, byte: u8| {
        let now = sim.now;
        sim.nodes[c].events.clear();
        let body = Response::new(Code::CONTENT).with_payload(vec![byte; 5000]);
        assert!(sim.nodes[s].ep.notify(now, obs, body));
        assert!(sim.run_to_event(c, Duration::from_secs(1)));
        let first = sim.nodes[c].events.iter().find_map(|(_, e)| match e {
            Event::Notification { response, .. } => Some(response.clone()),
            _ => None,
        });
        let first = first.unwrap_or_else(|| panic!("no notification"));
        assert_eq!(first.payload[0], byte);
        first.options.etag().map(<[u8]>::to_vec)
    };
    let etag = |r: &Response| r.options.etag().map(<[u8]>::to_vec);
    let a = notify(&mut sim, 1);
    let b1 = block_of_temp(&mut sim, c, s, 1);
    assert_eq!((etag(&b1), b1.payload[0]), (a.clone(), 1));
    // The next notification comes while the client is partway through the first.
    let b = notify(&mut sim, 2);
    assert_ne!(a, b);
    for num in 2..=4 {
        let r = block_of_temp(&mut sim, c, s, num);
        assert_eq!(etag(&r), a, "block {num} of the first notification");
        assert_eq!(r.payload[0], 1, "block {num}");
        assert_eq!(r.options.block2().map(|o| o.more), Some(num < 4));
    }
    // The first was fetched whole: the second's blocks are served now.
    for num in 1..=4 {
        let r = block_of_temp(&mut sim, c, s, num);
        assert_eq!(etag(&r), b, "block {num} of the second notification");
        assert_eq!(r.payload[0], 2, "block {num}");
    }
}

#[test]
fn rfc7390_2_5_multicast_request_collects_every_servers_response() {
    let mut sim = Sim::new(LinkConfig::default());
    let c = sim.add(cfg(1), None);
    for k in 0..3u64 {
        let h: crate::sim::Handler = Box::new(move |_| {
            Reply::Now(Response::new(Code::CONTENT).with_payload(format!("server {k}")))
        });
        sim.add(cfg(10 + k), Some(h));
    }
    // One more that errs: its error is suppressed (RFC 7390 §2.7).
    sim.add(
        cfg(20),
        Some(Box::new(|_| {
            Reply::Now(Response::diagnostic(Code::NOT_FOUND, "nope"))
        })),
    );
    let mut req = Request::new(Code::GET, "/.well-known/core");
    req.multicast = true;
    req.timeout = Some(Duration::from_secs(2));
    let now = sim.now;
    sim.nodes[c].ep.request(now, GROUP, req);
    sim.run_until(Duration::from_secs(5), |_| false);
    let mut got: Vec<String> = sim.nodes[c]
        .events
        .iter()
        .filter_map(|(_, e)| match e {
            Event::MulticastResponse { response, .. } => {
                Some(String::from_utf8_lossy(&response.payload).into_owned())
            }
            _ => None,
        })
        .collect();
    got.sort();
    assert_eq!(got, ["server 0", "server 1", "server 2"]);
    assert!(matches!(
        sim.nodes[c].events.last().map(|(_, e)| e),
        Some(Event::MulticastDone { .. })
    ));
    let sent = sim
        .log
        .iter()
        .filter(|r| r.from == sim.nodes[c].addr)
        .count();
    assert_eq!(sent, 1, "a multicast request is sent once, as NON");
}

/// When each server of a group answered a multicast GET sent at time 0 (in
/// milliseconds, sorted), with `leisure` and a handler that takes `handler_ms`.
fn group_answer_times(leisure: Duration, handler_ms: u64, seed: u64) -> Vec<u128> {
    let mut sim = Sim::new(LinkConfig::default());
    let c = sim.add(cfg(1), None);
    let mut servers = Vec::new();
    for k in 0..6u64 {
        let h: crate::sim::Handler = Box::new(move |_| {
            let r = Response::new(Code::CONTENT).with_payload(format!("server {k}"));
            Reply::After(Duration::from_millis(handler_ms), r)
        });
        let config = EndpointConfig {
            leisure,
            ..cfg(seed + k)
        };
        let s = sim.add(config, Some(h));
        servers.push(sim.nodes[s].addr);
    }
    let mut req = Request::new(Code::GET, "/who");
    req.multicast = true;
    req.timeout = Some(Duration::from_secs(3));
    let now = sim.now;
    sim.nodes[c].ep.request(now, GROUP, req);
    sim.run_until(Duration::from_secs(4), |_| false);
    let answered = sim.nodes[c]
        .events
        .iter()
        .filter(|(_, e)| matches!(e, Event::MulticastResponse { .. }))
        .count();
    assert_eq!(answered, servers.len(), "every server answers once");
    let mut times: Vec<u128> = sim
        .log
        .iter()
        .filter(|r| servers.contains(&r.from))
        .map(|r| r.at.as_millis())
        .collect();
    times.sort();
    times
}

/// RFC 7252 §8.2: each group member answers a multicast request at a random instant
/// within Leisure of its arrival, drawn from its seeded generator; an answer the
/// application gives later than that goes at once; without Leisure, all at once.
#[test]
fn rfc7252_8_2_leisure_spreads_the_answers_to_a_multicast_request() {
    // The request arrives at 5 ms; the answers leave within the next second.
    let spread = group_answer_times(Duration::from_secs(1), 0, 30);
    assert_eq!(spread.len(), 6);
    assert!(spread.iter().all(|&t| (5..1005).contains(&t)), "{spread:?}");
    let mut distinct = spread.clone();
    distinct.dedup();
    assert!(distinct.len() >= 5, "not spread: {spread:?}");
    assert!(spread[5] - spread[0] >= 300, "not spread: {spread:?}");
    // Same seeds, same instants.
    assert_eq!(group_answer_times(Duration::from_secs(1), 0, 30), spread);
    // No Leisure: every answer as its request arrives.
    assert_eq!(group_answer_times(Duration::ZERO, 0, 30), [5; 6]);
    // A handler slower than every member's leisure: each answer as soon as it is made.
    assert_eq!(
        group_answer_times(Duration::from_millis(100), 400, 30),
        [405; 6]
    );
}

/// RFC 7641 §4.5.2: one CON notification in flight per observer. An observer that
/// stopped answering gets the first CON notification and its retransmissions, nothing for
/// the changes after it, and is removed when that CON times out.
#[test]
fn rfc7641_4_5_2_one_con_notification_in_flight_and_a_silent_observer_removed() {
    let every_con = EndpointConfig {
        notify_con_interval: 1,
        ..cfg(2)
    };
    let (mut sim, _c, s, obs) = observed_by(LinkConfig::default(), every_con);
    let server = sim.nodes[s].addr;
    let count = |sim: &Sim| {
        let notifications = sim.log.iter().filter_map(|r| {
            let m = r.msg.as_ref()?;
            (r.from == server && m.code == Code::CONTENT && m.ty == coap::Type::Con)
                .then_some(m.message_id)
        });
        let mids: Vec<u16> = notifications.collect();
        let mut distinct = mids.clone();
        distinct.sort_unstable();
        distinct.dedup();
        (mids.len(), distinct.len())
    };

    // While the observer answers, every change arrives.
    for k in 1..=3 {
        let now = sim.now;
        let body = format!("v{k}");
        assert!(
            sim.nodes[s]
                .ep
                .notify(now, obs, Response::new(Code::CONTENT).with_payload(body))
        );
        sim.run_until(Duration::from_millis(200), |_| false);
    }
    assert_eq!(count(&sim), (3, 3));

    // The observer goes silent; ten changes follow, 100 ms apart.
    sim.link.loss = 1.0;
    for k in 4..=13 {
        let now = sim.now;
        let body = format!("v{k}");
        assert!(
            sim.nodes[s]
                .ep
                .notify(now, obs, Response::new(Code::CONTENT).with_payload(body))
        );
        sim.run_until(Duration::from_millis(100), |_| false);
    }
    sim.run_until(Duration::from_secs(300), |_| false);
    let (sent, distinct) = count(&sim);
    assert_eq!(
        distinct, 4,
        "one new CON notification after the observer went silent"
    );
    assert_eq!(sent, 3 + 5, "that one, sent MAX_RETRANSMIT + 1 times");
    let now = sim.now;
    assert!(
        !sim.nodes[s]
            .ep
            .notify(now, obs, Response::new(Code::CONTENT)),
        "the observation ended with the notification's timeout"
    );
}

#[test]
fn a_notification_reusing_an_earlier_message_id_is_new_when_its_observe_value_is() {
    // A busy server's message IDs come round while it notifies: a CON notification may
    // carry the ID of an earlier NON one to the same client, with the same token. It is
    // a new message (its Observe value tells), and must be acknowledged and delivered.
    let (mut sim, c, s, _obs) = observed(LinkConfig::default());
    let token = sim.log[0].msg.as_ref().map(|m| m.token).unwrap_or_default();
    let server = sim.nodes[s].addr;
    let notification = |ty, seq: u32, body: &str| {
        let mut m = coap::Message::empty(ty, 4242);
        m.code = Code::CONTENT;
        m.token = token;
        m.options.set_uint(OptionNumber::OBSERVE, seq);
        m.payload = bytes::Bytes::copy_from_slice(body.as_bytes());
        m.encode()
    };
    sim.inject(server, c, &notification(coap::Type::Non, 10, "a"));
    sim.run_until(Duration::from_secs(1), |_| false);
    sim.inject(server, c, &notification(coap::Type::Con, 11, "b"));
    sim.run_until(Duration::from_secs(1), |_| false);
    let bodies: Vec<&[u8]> = sim.nodes[c]
        .events
        .iter()
        .filter_map(|(_, e)| match e {
            Event::Response { response, .. } | Event::Notification { response, .. } => {
                Some(&response.payload[..])
            }
            _ => None,
        })
        .collect();
    assert_eq!(bodies, [&b"v0"[..], b"a", b"b"]);
    assert!(
        sim.log.iter().any(|r| r.from == sim.nodes[c].addr
            && r.msg
                .as_ref()
                .is_some_and(|m| m.ty == coap::Type::Ack && m.message_id == 4242)),
        "the CON notification is acknowledged"
    );
}

/// RFC 7641 §4.5.1: NON notifications are paced by the CON among them. Every fifth is a
/// CON, and the next waits for its ACK: at most four NONs go out per round trip of the
/// observer, and an observer that stopped answering (or a forged registration, had the
/// address check let one through) gets four NONs and one CON with its retransmissions
/// for any number of changes.
#[test]
fn rfc7641_4_5_1_non_notifications_are_paced_by_the_con_among_them() {
    let (mut sim, _c, s, obs) = observed(LinkConfig::default());
    let server = sim.nodes[s].addr;
    sim.link.loss = 1.0;
    for k in 0..1000 {
        let now = sim.now;
        let body = format!("change {k}");
        sim.nodes[s]
            .ep
            .notify(now, obs, Response::new(Code::CONTENT).with_payload(body));
        sim.run_until(Duration::from_millis(10), |_| false);
    }
    sim.run_until(Duration::from_secs(300), |_| false);
    let sent: Vec<coap::Type> = sim
        .log
        .iter()
        .filter(|r| r.from == server)
        .filter_map(|r| r.msg.as_ref())
        .filter(|m| m.code == Code::CONTENT && m.options.uint(OptionNumber::OBSERVE).is_some())
        .map(|m| m.ty)
        .collect();
    // The registration's answer (an ACK), four NONs, one CON sent five times.
    let non = sent.iter().filter(|t| **t == coap::Type::Non).count();
    let con = sent.iter().filter(|t| **t == coap::Type::Con).count();
    assert_eq!((non, con), (4, 5), "{sent:?}");
    let now = sim.now;
    assert!(
        !sim.nodes[s]
            .ep
            .notify(now, obs, Response::new(Code::CONTENT))
    );
}

/// A peer that the network says no longer listens (an ICMP port unreachable for a
/// datagram sent to it: `Endpoint::peer_unreachable`) has its observations ended at once:
/// the owner is told, and the next notification to it does not go out.
#[test]
fn an_unreachable_peer_s_observations_end() {
    let (mut sim, c, s, obs) = observed(LinkConfig::default());
    let client = sim.nodes[c].addr;
    let other: std::net::SocketAddr = "192.0.2.1:5683".parse().expect("an address");
    sim.nodes[s].ep.peer_unreachable(other);
    assert!(
        std::iter::from_fn(|| sim.nodes[s].ep.poll_event())
            .next()
            .is_none()
    );
    sim.nodes[s].ep.peer_unreachable(client);
    let events: Vec<Event> = std::iter::from_fn(|| sim.nodes[s].ep.poll_event()).collect();
    assert!(
        matches!(events.as_slice(), [Event::ObservationEnded { id }] if *id == obs),
        "{events:?}"
    );
    let now = sim.now;
    let next = Response::new(Code::CONTENT).with_payload("v1");
    assert!(!sim.nodes[s].ep.notify(now, obs, next));
}
