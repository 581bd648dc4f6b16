//! RFC 9175 §2.4: a server answers a peer whose address it has not verified with at most
//! three times what that peer sent. A unicast request from it is challenged with Echo
//! before any work; a GET it sent to a group is worked on (a bounded number a second),
//! and answered if the answer fits, silently if it is an error (RFC 7390 §2.7), else with
//! the challenge. Spoofed requests come from addresses no node has (`Sim::inject`); the
//! log counts every byte sent to them.

use std::cell::{Cell, RefCell};
use std::net::SocketAddr;
use std::rc::Rc;
use std::time::Duration;

use coap::{
    Code, EndpointConfig, Event, Message, ObservationId, OptionNumber, Request, Response, Token,
    Type,
};

use crate::sim::{Handler, LinkConfig, Reply, Sim};

const SERVER: SocketAddr = SocketAddr::new(
    std::net::IpAddr::V4(std::net::Ipv4Addr::new(198, 51, 100, 1)),
    5683,
);

fn victim(n: u16) -> SocketAddr {
    SocketAddr::from(([192, 0, 2, (n % 250) as u8 + 1], 40000 + n / 250))
}

fn cfg(seed: u64) -> EndpointConfig {
    EndpointConfig {
        rng_seed: seed,
        ..EndpointConfig::default()
    }
}

/// A server off loopback: `/small` (2 bytes), `/big` (5,000), `/obs` (observable),
/// POST `/grab` (20,000, whatever the body), PUT `/cfg`. Counts the requests its handler
/// ran.
fn server(sim: &mut Sim) -> (usize, Rc<Cell<usize>>) {
    let (s, ran, _) = observable_server(sim);
    (s, ran)
}

/// The observations a test server registered.
type Registered = Rc<RefCell<Vec<ObservationId>>>;

/// [`server`], and the observations it registered.
fn observable_server(sim: &mut Sim) -> (usize, Rc<Cell<usize>>, Registered) {
    let ran = Rc::new(Cell::new(0));
    let count = ran.clone();
    let registered = Rc::new(RefCell::new(Vec::new()));
    let last = registered.clone();
    let handler: Handler = Box::new(move |req| {
        count.set(count.get() + 1);
        if let Some(obs) = req.observe {
            last.borrow_mut().push(obs);
        }
        let path = req.options.path_string();
        let r = match (req.method, path.as_str()) {
            (Code::GET, "/small") => Response::new(Code::CONTENT).with_payload("ok"),
            (Code::GET, "/big") => Response::new(Code::CONTENT).with_payload(vec![7u8; 5000]),
            (Code::GET, "/obs") => {
                let mut r = Response::new(Code::CONTENT).with_payload("v0");
                r.options.set_uint(OptionNumber::OBSERVE, 0);
                r
            }
            (Code::POST, "/grab") => {
                Response::new(Code::CONTENT).with_payload(vec![req.payload.len() as u8; 20_000])
            }
            (Code::PUT, "/cfg") => Response::new(Code::CHANGED),
            _ => Response::new(Code::NOT_FOUND),
        };
        Reply::Now(r)
    });
    (sim.add_at(SERVER, cfg(2), Some(handler)), ran, registered)
}

fn raw(ty: Type, code: Code, mid: u16, path: &str, observe: Option<u32>) -> Vec<u8> {
    let mut msg = Message::empty(ty, mid);
    msg.code = code;
    msg.token = Token::new(&mid.to_be_bytes()).unwrap_or_default();
    msg.options.set_path(path);
    if let Some(o) = observe {
        msg.options.set_uint(OptionNumber::OBSERVE, o);
    }
    msg.encode()
}

/// Bytes the server sent to `peers`, and bytes they sent it (the datagrams injected).
fn sent_to(sim: &Sim, peers: &[SocketAddr]) -> usize {
    sim.log
        .iter()
        .filter(|r| r.from == SERVER && peers.contains(&r.to))
        .map(|r| r.len)
        .sum()
}

fn replies_to(sim: &Sim, peer: SocketAddr) -> Vec<Message> {
    sim.log
        .iter()
        .filter(|r| r.from == SERVER && r.to == peer)
        .filter_map(|r| r.msg.clone())
        .collect()
}

#[test]
fn rfc9175_2_4_spoofed_observe_registrations_get_a_challenge_and_no_notifications() {
    let mut sim = Sim::new(LinkConfig::default());
    let (s, ran, registered) = observable_server(&mut sim);
    // One registration from each of 1,024 spoofed sources, each sent 4 times as a CON's
    // retransmissions would be.
    let victims: Vec<SocketAddr> = (0..1024).map(victim).collect();
    let mut received = 0;
    for (i, v) in victims.iter().enumerate() {
        let reg = raw(Type::Con, Code::GET, i as u16, "/obs", Some(0));
        for _ in 0..4 {
            sim.inject(*v, s, &reg);
            received += reg.len();
        }
    }
    sim.run_until(Duration::from_secs(1), |_| false);
    // A spoofed NON POST that would trigger a grab and notify every observer.
    let trigger = raw(Type::Non, Code::POST, 9999, "/grab", None);
    sim.inject(victims[0], s, &trigger);
    received += trigger.len();
    // The application notifies its observers of a new grab every 10 s for 130 s.
    for _ in 0..13 {
        sim.run_until(Duration::from_secs(10), |_| false);
        let now = sim.now;
        for obs in registered.borrow().iter() {
            let body = Response::new(Code::CONTENT).with_payload(vec![1u8; 1000]);
            sim.nodes[s].ep.notify(now, *obs, body);
        }
    }
    sim.run_until(Duration::from_secs(10), |_| false);

    let sent = sent_to(&sim, &victims);
    let factor = sent as f64 / received as f64;
    eprintln!("spoofed registrations: {received} B in, {sent} B out, factor {factor:.2}");
    assert!(factor <= 3.0, "amplification {factor:.2}");
    assert_eq!(ran.get(), 0, "no handler ran for an unverified peer");
    for m in replies_to(&sim, victims[7]) {
        assert_eq!(m.code, Code::UNAUTHORIZED);
        assert!(m.options.first(OptionNumber::ECHO).is_some());
        assert!(m.options.uint(OptionNumber::OBSERVE).is_none());
    }
}

#[test]
fn rfc9175_2_4_unverified_requests_get_at_most_three_times_their_size() {
    let mut sim = Sim::new(LinkConfig::default());
    let (s, ran) = server(&mut sim);
    let v = victim(1);
    let requests = [
        raw(Type::Non, Code::POST, 1, "/grab", None),
        raw(Type::Con, Code::GET, 2, "/big", None),
        raw(Type::Con, Code::PUT, 3, "/cfg", None),
        raw(Type::Con, Code::GET, 4, "/small", None),
        // A CON POST with an empty token and no options: even the challenge is too large.
        Message {
            code: Code::POST,
            ..Message::empty(Type::Con, 5)
        }
        .encode(),
    ];
    let mut continuation = Message::decode(&requests[1]).unwrap_or_else(|e| panic!("{e:?}"));
    continuation.message_id = 6;
    continuation.token = Token::new(&6u16.to_be_bytes()).unwrap_or_default();
    continuation.options.set_block(
        OptionNumber::BLOCK2,
        coap::BlockOpt {
            num: 3,
            more: false,
            szx: 6,
        },
    );
    let continuation = continuation.encode();
    let mut received = 0;
    for r in requests.iter().chain([&continuation]) {
        sim.inject(v, s, r);
        received += r.len();
        sim.run_until(Duration::from_millis(50), |_| false);
    }
    sim.run_until(Duration::from_secs(5), |_| false);
    let sent = sent_to(&sim, &[v]);
    let factor = sent as f64 / received as f64;
    eprintln!("unverified requests: {received} B in, {sent} B out, factor {factor:.2}");
    assert!(factor <= 3.0, "amplification {factor:.2}");

    let replies = replies_to(&sim, v);
    let by_mid = |mid: u16| -> Vec<&Message> {
        let token = Token::new(&mid.to_be_bytes()).unwrap_or_default();
        replies.iter().filter(|m| m.token == token).collect()
    };
    // Every unicast request is challenged before any work, the small GET too: its
    // answer is not known until made.
    for mid in [1, 2, 3, 4, 6] {
        let r = by_mid(mid);
        assert_eq!(r.len(), 1, "one reply to request {mid}");
        assert_eq!(r[0].code, Code::UNAUTHORIZED, "request {mid}");
        assert!(r[0].options.first(OptionNumber::ECHO).is_some());
        assert!(r[0].encoded_len() <= 3 * requests[0].len().min(continuation.len()));
    }
    assert!(
        replies
            .iter()
            .any(|m| m.ty == Type::Rst && m.message_id == 5),
        "the tiny POST gets a Reset"
    );
    // No handler ran.
    assert_eq!(ran.get(), 0);
}

#[test]
fn rfc9175_2_3_a_client_off_loopback_answers_one_challenge_and_then_works() {
    let mut sim = Sim::new(LinkConfig::default());
    let (s, ran, registered) = observable_server(&mut sim);
    let c = sim.add_at(SocketAddr::from(([192, 0, 2, 200], 5683)), cfg(1), None);
    let now = sim.now;
    let mut post = Request::new(Code::POST, "/grab");
    post.payload = vec![1u8; 3000].into();
    sim.nodes[c].ep.request(now, SERVER, post);
    assert!(sim.run_to_event(c, Duration::from_secs(20)));
    let now = sim.now;
    sim.nodes[c]
        .ep
        .request(now, SERVER, Request::new(Code::GET, "/big"));
    let mut observe = Request::new(Code::GET, "/obs");
    observe.options.set_uint(OptionNumber::OBSERVE, 0);
    sim.nodes[c].ep.request(now, SERVER, observe);
    assert!(sim.run_until(Duration::from_secs(20), |s| s.nodes[c].events.len() >= 3));

    let bodies: Vec<(Code, usize)> = sim.nodes[c]
        .events
        .iter()
        .filter_map(|(_, e)| match e {
            Event::Response { response, .. } => Some((response.code, response.payload.len())),
            _ => None,
        })
        .collect();
    assert!(bodies.contains(&(Code::CONTENT, 20_000)), "{bodies:?}");
    assert!(bodies.contains(&(Code::CONTENT, 5000)), "{bodies:?}");
    assert!(bodies.contains(&(Code::CONTENT, 2)), "{bodies:?}");
    let challenges = sim
        .log
        .iter()
        .filter(|r| r.msg.as_ref().is_some_and(|m| m.code == Code::UNAUTHORIZED))
        .count();
    assert_eq!(challenges, 1, "only the first request is challenged");
    // The POST ran once (its first block was challenged before it was stored), the GET
    // and the registration once each.
    assert_eq!(ran.get(), 3);
    // The registration came from a verified address, so the observation notifies.
    let obs = *registered
        .borrow()
        .first()
        .unwrap_or_else(|| panic!("no registration"));
    let now = sim.now;
    let update = Response::new(Code::CONTENT).with_payload("v1");
    assert!(sim.nodes[s].ep.notify(now, obs, update));
    assert!(sim.run_until(Duration::from_secs(5), |s| s.nodes[c].events.len() >= 4));
}

#[test]
fn rfc9175_2_4_only_an_echo_keeps_an_address_verified_not_spoofed_requests() {
    let mut sim = Sim::new(LinkConfig::default());
    let (s, _ran) = server(&mut sim);
    let v = victim(3);
    let big = |mid: u16, echo: Option<&[u8]>| {
        let mut msg = Message::decode(&raw(Type::Con, Code::GET, mid, "/big", None))
            .unwrap_or_else(|e| panic!("{e:?}"));
        if let Some(e) = echo {
            msg.options.set(OptionNumber::ECHO, e);
        }
        msg.encode()
    };
    // The answer to request `mid`: its code and whether it carries an Echo value.
    let answer = |sim: &Sim, mid: u16| -> (Code, Option<Vec<u8>>) {
        let token = Token::new(&mid.to_be_bytes()).unwrap_or_default();
        let m = replies_to(sim, v)
            .into_iter()
            .rfind(|m| m.token == token)
            .unwrap_or_else(|| panic!("no answer to request {mid}"));
        let echo = m.options.first(OptionNumber::ECHO).map(<[u8]>::to_vec);
        (m.code, echo)
    };
    // The address proves itself once.
    sim.inject(v, s, &big(1, None));
    sim.run_until(Duration::from_millis(50), |_| false);
    let (code, echo) = answer(&sim, 1);
    assert_eq!(code, Code::UNAUTHORIZED);
    let echo = echo.unwrap_or_else(|| panic!("no Echo value"));
    sim.inject(v, s, &big(2, Some(&echo)));
    sim.run_until(Duration::from_millis(50), |_| false);
    assert_eq!(answer(&sim, 2).0, Code::CONTENT, "verified by its Echo");
    let t0 = sim.now;
    // Someone else sends small requests in its name every minute for 11 minutes: they
    // prove nothing, so 10 minutes after the Echo the address is a stranger's again.
    for n in 0..11u16 {
        sim.run_until(Duration::from_secs(60), |_| false);
        // The simulator's clock stops when nothing is due; a minute passes all the same.
        sim.now = sim.now.max(t0 + Duration::from_secs(60 * u64::from(n + 1)));
        sim.inject(v, s, &raw(Type::Non, Code::GET, 100 + n, "/small", None));
    }
    // The address's own large request is challenged again; its Echo verifies it anew.
    sim.inject(v, s, &big(3, None));
    sim.run_until(Duration::from_millis(50), |_| false);
    let (code, echo) = answer(&sim, 3);
    assert_eq!(
        code,
        Code::UNAUTHORIZED,
        "spoofed requests kept the address verified"
    );
    let echo = echo.unwrap_or_else(|| panic!("no Echo value"));
    sim.inject(v, s, &big(4, Some(&echo)));
    sim.run_until(Duration::from_millis(50), |_| false);
    assert_eq!(
        answer(&sim, 4).0,
        Code::CONTENT,
        "verified again by its Echo"
    );
}

#[test]
fn rfc9175_2_2_1_an_echo_value_over_40_bytes_is_not_sent_back() {
    let mut sim = Sim::new(LinkConfig::default());
    let c = sim.add_at(SocketAddr::from(([192, 0, 2, 200], 5683)), cfg(1), None);
    // A server that is not a node: its answers are written by hand.
    let server = SocketAddr::from(([198, 51, 100, 9], 5683));
    let requests_with_echo = |sim: &Sim| -> Vec<usize> {
        sim.log
            .iter()
            .filter(|r| r.from == sim.nodes[c].addr && r.to == server)
            .filter_map(|r| r.msg.as_ref()?.options.first(OptionNumber::ECHO))
            .map(<[u8]>::len)
            .collect()
    };
    for (n, len) in [(0u8, 40usize), (1, 1000)] {
        let now = sim.now;
        let id = sim.nodes[c]
            .ep
            .request(now, server, Request::new(Code::GET, "/x"));
        sim.run_until(Duration::from_millis(10), |_| false);
        let request = sim
            .log
            .iter()
            .rev()
            .find(|r| r.from == sim.nodes[c].addr && r.to == server)
            .and_then(|r| r.msg.clone())
            .unwrap_or_else(|| panic!("no request"));
        let mut challenge = Message::empty(Type::Ack, request.message_id);
        challenge.code = Code::UNAUTHORIZED;
        challenge.token = request.token;
        challenge.options.set(OptionNumber::ECHO, vec![n; len]);
        sim.inject(server, c, &challenge.encode());
        sim.run_until(Duration::from_millis(10), |_| false);
        let echoed = requests_with_echo(&sim);
        if len <= 40 {
            // Within the option's bounds: the request goes again, with the value.
            assert_eq!(echoed, [len], "a {len}-byte Echo value");
            sim.nodes[c].ep.cancel(sim.now, id);
        } else {
            assert_eq!(echoed, [40], "a {len}-byte Echo value was sent back");
            let answered = sim.nodes[c].events.iter().any(|(_, e)| {
                matches!(e, Event::Response { id: got, response }
                    if *got == id && response.code == Code::UNAUTHORIZED)
            });
            assert!(answered, "the 4.01 is the answer");
        }
    }
}

/// The body a verified client fetched from `/big`, and the messages the exchange took.
fn fetch_big(sim: &mut Sim, c: usize) -> (usize, usize) {
    let before = sim.log.len();
    let now = sim.now;
    sim.nodes[c]
        .ep
        .request(now, SERVER, Request::new(Code::GET, "/big"));
    assert!(sim.run_to_event(c, Duration::from_secs(20)));
    let got = match sim.nodes[c].events.pop() {
        Some((_, Event::Response { response, .. })) => {
            assert_eq!(response.code, Code::CONTENT);
            response.payload.len()
        }
        other => panic!("no response: {other:?}"),
    };
    let me = sim.nodes[c].addr;
    let messages = sim.log[before..]
        .iter()
        .filter(|r| r.from == me || r.to == me)
        .count();
    (got, messages)
}

#[test]
fn rfc9175_2_4_spoofed_gets_are_challenged_before_any_work() {
    let mut sim = Sim::new(LinkConfig::default());
    let (s, ran) = server(&mut sim);
    // A client on loopback (verified) fetches /big before the flood, to compare.
    let c = sim.add(cfg(1), None);
    let quiet = fetch_big(&mut sim, c);
    assert_eq!(ran.get(), 1);
    // A second of a flood: 1,000 GETs of the large resource from 1,000 forged sources,
    // the client's GET in the middle of it.
    let victims: Vec<SocketAddr> = (0..1000).map(victim).collect();
    let mut received = 0;
    let mut during = None;
    let t0 = sim.now;
    for (i, v) in victims.iter().enumerate() {
        sim.now = sim.now.max(t0 + Duration::from_millis(i as u64));
        let get = raw(Type::Con, Code::GET, i as u16, "/big", None);
        sim.inject(*v, s, &get);
        received += get.len();
        sim.run_until(Duration::from_millis(1), |_| false);
        if i == 500 {
            during = Some(fetch_big(&mut sim, c));
        }
    }
    sim.run_until(Duration::from_secs(1), |_| false);
    // The handler ran for the client only: the answer could not go to an unverified
    // peer, so it was not made; the client's GET took the same exchange as in quiet.
    assert_eq!(ran.get(), 2, "handlers ran for spoofed GETs");
    assert_eq!(
        during,
        Some(quiet),
        "(body, messages) in the flood and in quiet"
    );
    let sent = sent_to(&sim, &victims);
    assert!(sent <= 3 * received, "{sent} B sent for {received} B");
    for v in [victims[9], victims[999]] {
        let replies = replies_to(&sim, v);
        assert_eq!(replies.len(), 1);
        assert_eq!(replies[0].code, Code::UNAUTHORIZED);
        assert!(replies[0].options.first(OptionNumber::ECHO).is_some());
    }
}

#[test]
fn rfc7390_2_7_an_unverified_group_get_is_worked_on_and_its_error_stays_silent() {
    let mut sim = Sim::new(LinkConfig::default());
    let (s, ran) = server(&mut sim);
    let v = victim(5);
    // Group requests are NON (RFC 7252 §8.1): one the member lacks, one whose answer
    // fits three times the request, one whose answer does not.
    let requests = [
        raw(Type::Non, Code::GET, 1, "/missing", None),
        raw(Type::Non, Code::GET, 2, "/small", None),
        raw(Type::Non, Code::GET, 3, "/big", None),
    ];
    for r in &requests {
        sim.inject_to_group(v, s, r);
    }
    // Past every answer's leisure.
    sim.run_until(Duration::from_secs(2), |_| false);
    assert_eq!(ran.get(), 3, "each group GET was worked on");
    let replies = replies_to(&sim, v);
    let by_mid = |mid: u16| -> Vec<&Message> {
        let token = Token::new(&mid.to_be_bytes()).unwrap_or_default();
        replies.iter().filter(|m| m.token == token).collect()
    };
    // The 4.04 is suppressed, not replaced by a challenge whose unicast retry would
    // draw it after all.
    assert!(by_mid(1).is_empty(), "{:?}", by_mid(1));
    let small = by_mid(2);
    assert_eq!(small.len(), 1);
    assert_eq!(
        (small[0].code, &small[0].payload[..]),
        (Code::CONTENT, &b"ok"[..])
    );
    let big = by_mid(3);
    assert_eq!(big.len(), 1);
    assert_eq!(big[0].code, Code::UNAUTHORIZED);
    assert!(big[0].options.first(OptionNumber::ECHO).is_some());
    let received: usize = requests.iter().map(Vec::len).sum();
    assert!(sent_to(&sim, &[v]) <= 3 * received);
}

/// A server whose every answer takes the application `took`: a 5,000-byte body. Counts
/// the requests its handler ran.
fn slow_server(sim: &mut Sim, took: Duration) -> (usize, Rc<Cell<usize>>) {
    let ran = Rc::new(Cell::new(0));
    let count = ran.clone();
    let handler: Handler = Box::new(move |_| {
        count.set(count.get() + 1);
        Reply::After(
            took,
            Response::new(Code::CONTENT).with_payload(vec![7u8; 5000]),
        )
    });
    (sim.add_at(SERVER, cfg(2), Some(handler)), ran)
}

#[test]
fn rfc9175_2_4_a_flood_of_unverified_group_gets_takes_a_bounded_share_of_the_application() {
    let mut sim = Sim::new(LinkConfig::default());
    let took = Duration::from_millis(20);
    let (s, ran) = slow_server(&mut sim, took);
    let share = EndpointConfig::default().limits.unverified_group_work;
    // Four seconds of 1,000 spoofed group GETs a second.
    let victims: Vec<SocketAddr> = (0..4000).map(victim).collect();
    let mut received = 0;
    let t0 = sim.now;
    for (i, v) in victims.iter().enumerate() {
        // The simulator's clock stops when nothing is due; a millisecond passes all the
        // same.
        sim.now = sim.now.max(t0 + Duration::from_millis(i as u64));
        let get = raw(Type::Non, Code::GET, i as u16, "/big", None);
        sim.inject_to_group(*v, s, &get);
        received += get.len();
        sim.run_until(Duration::from_millis(1), |_| false);
    }
    let elapsed = sim.now - t0;
    sim.run_until(Duration::from_secs(2), |_| false);
    // Ten seconds' worth of the share at first, then the share of every second; the
    // last ones in progress (four at most) may overdraw it by their own time.
    let allowed = share * 10 + share.mul_f64(elapsed.as_secs_f64()) + took * 4;
    let worked = took * ran.get() as u32;
    eprintln!(
        "{} of 4,000 spoofed group GETs worked on in {elapsed:?}: {worked:?}, {allowed:?} allowed",
        ran.get()
    );
    assert!(worked <= allowed, "{worked:?} of work, {allowed:?} allowed");
    assert!(
        worked + took * 4 >= allowed,
        "the share was not used: {worked:?}"
    );
    // The rest were challenged before any work; nothing passed three times the bytes.
    let sent = sent_to(&sim, &victims);
    assert!(sent <= 3 * received, "{sent} B sent for {received} B");
    for v in [victims[0], victims[3999]] {
        let replies = replies_to(&sim, v);
        assert_eq!(replies.len(), 1);
        assert_eq!(replies[0].code, Code::UNAUTHORIZED);
    }
}

#[test]
fn rfc9175_2_4_unverified_group_gets_are_worked_on_a_few_at_a_time() {
    let mut sim = Sim::new(LinkConfig::default());
    // Each GET takes the application 10 s.
    let (s, ran) = slow_server(&mut sim, Duration::from_secs(10));
    // Five seconds of 100 spoofed group GETs a second.
    let t0 = sim.now;
    for i in 0..500u16 {
        sim.now = sim.now.max(t0 + Duration::from_millis(10 * u64::from(i)));
        sim.inject_to_group(victim(i), s, &raw(Type::Non, Code::GET, i, "/x", None));
        sim.run_until(Duration::from_millis(10), |_| false);
    }
    // The share had room for the first four; the others found them in progress.
    assert_eq!(ran.get(), 4, "GETs handed to the application");
    // Once they answered, their 40 s overdrew the share: the next are challenged too.
    sim.run_until(Duration::from_secs(6), |_| false);
    let v = victim(600);
    sim.inject_to_group(v, s, &raw(Type::Non, Code::GET, 600, "/x", None));
    sim.run_until(Duration::from_secs(1), |_| false);
    assert_eq!(ran.get(), 4);
    assert_eq!(
        replies_to(&sim, v).first().map(|m| m.code),
        Some(Code::UNAUTHORIZED)
    );
}

#[test]
fn rfc9175_2_3_an_echo_asked_for_a_whole_block1_body_sends_the_body_again_with_it() {
    // An application that wants its own fresh Echo value with the request, as coapcam's
    // resource directory does with a registration: it sees the body only once all its
    // blocks arrived, so its challenge answers the last block.
    let mut sim = Sim::new(LinkConfig::default());
    let ran = Rc::new(Cell::new(0));
    let count = ran.clone();
    let handler: Handler = Box::new(move |req| {
        count.set(count.get() + 1);
        if req.options.first(OptionNumber::ECHO) != Some(&b"app-value"[..]) {
            let mut challenge = Response::new(Code::UNAUTHORIZED);
            challenge.options.set(OptionNumber::ECHO, b"app-value");
            return Reply::Now(challenge);
        }
        Reply::Now(Response::new(Code::CREATED).with_payload(req.payload.len().to_string()))
    });
    sim.add_at(SERVER, cfg(2), Some(handler));
    let c = sim.add_at(SocketAddr::from(([192, 0, 2, 201], 5683)), cfg(1), None);
    let body = vec![5u8; 3000];
    let now = sim.now;
    let id = sim.nodes[c].ep.request(
        now,
        SERVER,
        Request::new(Code::POST, "/rd").with_payload(body.clone()),
    );
    assert!(sim.run_to_event(c, Duration::from_secs(30)));
    let response = sim.nodes[c].events.iter().find_map(|(_, e)| match e {
        Event::Response { id: got, response } if *got == id => Some(response.clone()),
        _ => None,
    });
    let response = response.expect("an answer");
    // The CoAP layer's challenge came first (this client is off loopback), then the
    // application's: the whole body went again with its value, and was taken.
    assert_eq!(response.code, Code::CREATED, "{response:?}");
    assert_eq!(response.payload, body.len().to_string().as_bytes());
    assert_eq!(ran.get(), 2, "the application saw the body twice");
}
