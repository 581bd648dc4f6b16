//! RFC 7959 block-wise transfer, run in the simulator, with and without loss.

use std::cell::Cell;
use std::rc::Rc;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::time::Duration;

use bytes::Bytes;
use coap::{
    BlockOpt, BlockSource, Code, Endpoint, EndpointConfig, Event, Limits, Message, OptionNumber,
    Request, RequestError, Response, Token, Type,
};

use crate::sim::{Handler, LinkConfig, Reply, Sim};

pub(crate) fn cfg(seed: u64) -> EndpointConfig {
    EndpointConfig {
        rng_seed: seed,
        ..EndpointConfig::default()
    }
}

/// Deterministic pseudo-random bytes, so a misplaced block cannot go unnoticed.
pub(crate) fn body(len: usize, seed: u32) -> Bytes {
    let mut x = seed.wrapping_mul(2_654_435_761).wrapping_add(1);
    (0..len)
        .map(|_| {
            x ^= x << 13;
            x ^= x >> 17;
            x ^= x << 5;
            x as u8
        })
        .collect::<Vec<u8>>()
        .into()
}

pub(crate) fn serve(body: Bytes, calls: Rc<Cell<usize>>) -> Handler {
    Box::new(move |_| {
        calls.set(calls.get() + 1);
        Reply::Now(Response::new(Code::CONTENT).with_payload(body.clone()))
    })
}

/// An endpoint configuration (seed `seed`) that stores no Block2 representation: every
/// continuation is rendered again by the application.
pub(crate) fn no_store(seed: u64) -> EndpointConfig {
    EndpointConfig {
        limits: Limits {
            block2_store_bytes: 0,
            ..Limits::default()
        },
        ..cfg(seed)
    }
}

/// The first event of `node`, which must be a response.
pub(crate) fn response(sim: &Sim, node: usize) -> &Response {
    match &sim.nodes[node].events[0].1 {
        Event::Response { response, .. } => response,
        other => panic!("expected a response, got {other:?}"),
    }
}

/// A GET of `len` bytes over a link with `loss`; returns the simulation for inspection.
fn block2_transfer(len: usize, loss: f64, method: Code) -> (Sim, Bytes, usize) {
    let data = body(len, 42);
    let calls = Rc::new(Cell::new(0));
    let mut sim = Sim::new(if loss > 0.0 {
        LinkConfig::lossy(loss, 99)
    } else {
        LinkConfig::default()
    });
    sim.record = false;
    let c = sim.add(cfg(1), None);
    let s = sim.add(cfg(2), Some(serve(data.clone(), calls.clone())));
    let server = sim.nodes[s].addr;
    let now = sim.now;
    sim.nodes[c]
        .ep
        .request(now, server, Request::new(method, "/big"));
    assert!(
        sim.run_to_event(c, Duration::from_secs(100_000)),
        "no outcome"
    );
    (sim, data, calls.get())
}

fn check_block2(len: usize, loss: f64) {
    let (sim, data, calls) = block2_transfer(len, loss, Code::GET);
    let r = response(&sim, 0);
    assert_eq!(r.code, Code::CONTENT);
    assert_eq!(r.payload.len(), data.len());
    assert!(r.payload == data, "body differs at {loss} loss");
    assert_eq!(
        calls, 1,
        "the handler runs once; the other blocks come from the store"
    );
    assert_eq!(r.options.uint(OptionNumber::SIZE2), Some(len as u32));
    assert!(r.options.etag().is_some());
}

#[test]
fn rfc7959_2_4_block2_10_mb_bit_exact_without_loss() {
    check_block2(10_032_012, 0.0);
}

#[test]
fn rfc7959_2_4_block2_10_mb_bit_exact_at_5_percent_loss() {
    check_block2(10_032_012, 0.05);
}

#[test]
fn rfc7959_2_4_block2_10_mb_bit_exact_at_20_percent_loss_resumes_missing_blocks() {
    check_block2(10_032_012, 0.20);
}

fn block1_upload(len: usize, loss: f64, server_szx: u8) -> (Sim, Bytes, Rc<Cell<usize>>) {
    let data = body(len, 7);
    let got = Rc::new(Cell::new(0));
    let seen = got.clone();
    let expected = data.clone();
    let handler: Handler = Box::new(move |req| {
        seen.set(seen.get() + 1);
        let ok = req.payload == expected;
        Reply::Now(Response::new(if ok {
            Code::CHANGED
        } else {
            Code::BAD_REQUEST
        }))
    });
    let mut sim = Sim::new(if loss > 0.0 {
        LinkConfig::lossy(loss, 5)
    } else {
        LinkConfig::default()
    });
    let c = sim.add(cfg(3), None);
    let s = sim.add(
        EndpointConfig {
            max_block_szx: server_szx,
            ..cfg(4)
        },
        Some(handler),
    );
    let server = sim.nodes[s].addr;
    let now = sim.now;
    let req = Request::new(Code::PUT, "/advanced-config").with_payload(data.clone());
    sim.nodes[c].ep.request(now, server, req);
    assert!(sim.run_to_event(c, Duration::from_secs(10_000)));
    (sim, data, got)
}

#[test]
fn rfc7959_2_5_block1_3500_bytes_arrive_bit_exact_at_0_5_20_percent_loss() {
    for loss in [0.0, 0.05, 0.20] {
        let (sim, _, calls) = block1_upload(3500, loss, 6);
        assert_eq!(response(&sim, 0).code, Code::CHANGED, "loss {loss}");
        assert_eq!(
            calls.get(),
            1,
            "assembled body handed over once, loss {loss}"
        );
    }
}

#[test]
fn rfc7959_2_5_block1_sends_size1_and_gets_2_31_continue() {
    let (sim, _, _) = block1_upload(3500, 0.0, 6);
    let l: Vec<String> = sim.log.iter().map(|r| r.line()).collect();
    // 4 blocks of 1024 (the last 428 bytes), 2.31 after each but the last.
    assert_eq!(
        l.iter().filter(|l| l.contains("ACK 2.31")).count(),
        3,
        "{l:#?}"
    );
    assert!(
        l.last()
            .is_some_and(|l| l.contains("ACK 2.04") && l.contains("b1=3/0/1024")),
        "{l:#?}"
    );
    let first = sim.log[0]
        .msg
        .as_ref()
        .map(|m| m.options.uint(OptionNumber::SIZE1));
    assert_eq!(first, Some(Some(3500)));
}

#[test]
fn rfc7959_2_3_block1_szx_renegotiation_to_smaller_server_blocks() {
    let (sim, _, calls) = block1_upload(3500, 0.0, 4);
    assert_eq!(response(&sim, 0).code, Code::CHANGED);
    assert_eq!(calls.get(), 1);
    let l: Vec<String> = sim.log.iter().map(|r| r.line()).collect();
    // First block 1024 bytes, the server asks for 256; the client continues at offset
    // 1024 = block 4 of 256 bytes.
    assert!(l[0].contains("b1=0/1/1024"), "{l:#?}");
    assert!(
        l[1].contains("ACK 2.31") && l[1].contains("b1=0/1/256"),
        "{l:#?}"
    );
    assert!(l[2].contains("b1=4/1/256"), "{l:#?}");
}

#[test]
fn rfc7959_2_9_3_block1_over_server_limit_gives_4_13_with_size1() {
    let mut sim = Sim::new(LinkConfig::default());
    let c = sim.add(cfg(1), None);
    let small = EndpointConfig {
        limits: Limits {
            block1_peer_bytes: 2048,
            ..Limits::default()
        },
        ..cfg(2)
    };
    let s = sim.add(
        small,
        Some(Box::new(|_| Reply::Now(Response::new(Code::CHANGED)))),
    );
    let server = sim.nodes[s].addr;
    let now = sim.now;
    sim.nodes[c].ep.request(
        now,
        server,
        Request::new(Code::PUT, "/x").with_payload(body(3500, 1)),
    );
    assert!(sim.run_to_event(c, Duration::from_secs(10)));
    let r = response(&sim, c);
    assert_eq!(r.code, Code::REQUEST_ENTITY_TOO_LARGE);
    assert_eq!(r.options.uint(OptionNumber::SIZE1), Some(2048));
    assert_eq!(sim.nodes[s].requests_seen, 0);
}

#[test]
fn rfc7959_2_4_post_block2_continuations_never_call_the_handler_again() {
    let (sim, data, calls) = block2_transfer(100_000, 0.0, Code::POST);
    assert!(response(&sim, 0).payload == data);
    assert_eq!(calls, 1, "a grab happens once per POST, not once per block");
}

#[test]
fn rfc7959_2_4_early_negotiation_asks_for_smaller_blocks() {
    let data = body(1000, 3);
    let mut sim = Sim::new(LinkConfig::default());
    let c = sim.add(cfg(1), None);
    let s = sim.add(cfg(2), Some(serve(data.clone(), Rc::new(Cell::new(0)))));
    let server = sim.nodes[s].addr;
    let mut req = Request::new(Code::GET, "/x");
    req.block_szx = Some(2);
    let now = sim.now;
    sim.nodes[c].ep.request(now, server, req);
    assert!(sim.run_to_event(c, Duration::from_secs(10)));
    assert!(response(&sim, c).payload == data);
    let blocks = sim
        .log
        .iter()
        .filter(|r| r.msg.as_ref().is_some_and(|m| m.code == Code::CONTENT))
        .count();
    assert_eq!(blocks, 16, "1000 bytes in 64-byte blocks");
}

#[test]
fn rfc7959_2_4_etag_change_restarts_the_transfer() {
    let seen = Rc::new(Cell::new(0u32));
    // The representation changes on every request that reaches the handler: the store
    // expires at once, so each GET continuation re-renders with a new ETag. After four
    // restarts the client gives up with RepresentationChanged.
    let handler: Handler = Box::new(move |_| {
        seen.set(seen.get() + 1);
        let mut r = Response::new(Code::CONTENT).with_payload(body(3000, seen.get()));
        r.options.set(OptionNumber::ETAG, seen.get().to_be_bytes());
        Reply::Now(r)
    });
    let mut sim = Sim::new(LinkConfig::default());
    let c = sim.add(cfg(1), None);
    let no_store = no_store(2);
    let s = sim.add(no_store, Some(handler));
    let server = sim.nodes[s].addr;
    let now = sim.now;
    sim.nodes[c]
        .ep
        .request(now, server, Request::new(Code::GET, "/changing"));
    assert!(sim.run_to_event(c, Duration::from_secs(10)));
    assert!(matches!(
        sim.nodes[c].events[0].1,
        Event::RequestFailed {
            error: RequestError::RepresentationChanged,
            ..
        }
    ));
}

/// A body read through [`BlockSource`] that stops being readable after `readable` reads,
/// as a file changed in place does.
struct Fading {
    body: Bytes,
    reads: AtomicUsize,
    readable: usize,
}

impl BlockSource for Fading {
    fn len(&self) -> usize {
        self.body.len()
    }

    fn read(&self, range: std::ops::Range<usize>) -> Option<Bytes> {
        let reads = self.reads.fetch_add(1, Ordering::Relaxed) + 1;
        (reads <= self.readable).then(|| self.body.slice(range))
    }

    fn held(&self) -> usize {
        0
    }
}

#[test]
fn a_source_is_read_block_by_block_and_a_source_gone_unreadable_is_rendered_again() {
    // First rendering: a source that fails at its 11th read. The continuation that finds it
    // unreadable reaches the handler again (as if nothing were stored), which renders the
    // new content with a new ETag; the client starts over from block 0 and gets that whole.
    let calls = Rc::new(Cell::new(0u32));
    let seen = calls.clone();
    let (old, new) = (body(20_000, 1), body(30_000, 2));
    let latest = new.clone();
    let handler: Handler = Box::new(move |_| {
        seen.set(seen.get() + 1);
        let mut r = Response::new(Code::CONTENT);
        let first = seen.get() == 1;
        r.options
            .set(OptionNumber::ETAG, [if first { 1 } else { 2 }]);
        Reply::Now(if first {
            r.with_source(Fading {
                body: old.clone(),
                reads: AtomicUsize::new(0),
                readable: 10,
            })
        } else {
            r.with_payload(latest.clone())
        })
    });
    let mut sim = Sim::new(LinkConfig::default());
    let c = sim.add(cfg(1), None);
    let s = sim.add(cfg(2), Some(handler));
    let server = sim.nodes[s].addr;
    let now = sim.now;
    sim.nodes[c]
        .ep
        .request(now, server, Request::new(Code::GET, "/file"));
    assert!(sim.run_to_event(c, Duration::from_secs(100)));
    let r = response(&sim, c);
    assert!(r.payload == new, "the new content, whole");
    assert_eq!(r.options.etag(), Some(&[2][..]));
    assert_eq!(
        calls.get(),
        3,
        "block 0, the continuation that found the source unreadable, block 0 again"
    );
}

/// A body of `len` zero bytes that exists only as it is read.
struct Zeros(usize);

impl BlockSource for Zeros {
    fn len(&self) -> usize {
        self.0
    }

    fn read(&self, range: std::ops::Range<usize>) -> Option<Bytes> {
        Some(vec![0; range.len()].into())
    }

    fn held(&self) -> usize {
        0
    }
}

#[test]
fn rfc7959_2_2_a_body_past_the_20_bit_block_number_is_refused_not_wrapped() {
    // 16-byte blocks: block numbers end at 16 MiB.
    let handler: Handler =
        Box::new(|_| Reply::Now(Response::new(Code::CONTENT).with_source(Zeros((16 << 20) + 1))));
    let mut sim = Sim::new(LinkConfig::default());
    let c = sim.add(cfg(1), None);
    let s = sim.add(cfg(2), Some(handler));
    let server = sim.nodes[s].addr;
    let now = sim.now;
    let mut req = Request::new(Code::GET, "/huge");
    req.block_szx = Some(0);
    sim.nodes[c].ep.request(now, server, req);
    assert!(sim.run_to_event(c, Duration::from_secs(100)));
    assert_eq!(response(&sim, c).code, Code::INTERNAL_SERVER_ERROR);
}

/// Bytes whose memory reports when it is freed.
struct Tracked(Vec<u8>, Arc<AtomicBool>);

impl AsRef<[u8]> for Tracked {
    fn as_ref(&self) -> &[u8] {
        &self.0
    }
}

impl Drop for Tracked {
    fn drop(&mut self) {
        self.1.store(true, Ordering::Relaxed);
    }
}

#[test]
fn the_reply_kept_for_duplicates_does_not_keep_the_representation() {
    // Block 0's reply is remembered for duplicates for EXCHANGE_LIFETIME (247 s); the
    // representation only for the Block2 lifetime, here 10 s. After that, the body's memory
    // is freed although the reply is still remembered.
    let freed = Arc::new(AtomicBool::new(false));
    let flag = freed.clone();
    let calls = Rc::new(Cell::new(0));
    let seen = calls.clone();
    let handler: Handler = Box::new(move |_| {
        seen.set(seen.get() + 1);
        let body = if seen.get() == 1 {
            Bytes::from_owner(Tracked(body(5000, 3).to_vec(), flag.clone()))
        } else {
            body(5000, 4)
        };
        Reply::Now(Response::new(Code::CONTENT).with_payload(body))
    });
    let mut sim = Sim::new(LinkConfig::default());
    let c = sim.add(cfg(1), None);
    let server_cfg = EndpointConfig {
        limits: Limits {
            blockwise_lifetime: Duration::from_secs(10),
            ..Limits::default()
        },
        ..cfg(2)
    };
    let s = sim.add(server_cfg, Some(handler));
    let server = sim.nodes[s].addr;
    for _ in 0..2 {
        let now = sim.now;
        sim.nodes[c]
            .ep
            .request(now, server, Request::new(Code::GET, "/file"));
        assert!(sim.run_to_event(c, Duration::from_secs(100)));
        sim.nodes[c].events.clear();
        // Past the Block2 lifetime; the next representation stored expires the first.
        sim.run_until(Duration::from_secs(20), |_| false);
    }
    assert_eq!(calls.get(), 2);
    assert!(freed.load(Ordering::Relaxed), "the first body was freed");
}

#[test]
fn rfc7959_2_4_stable_representation_without_store_still_reassembles() {
    // With no store at all, a GET continuation is re-rendered by the application; with a
    // stable ETag the blocks fit together.
    let data = body(5000, 9);
    let mut sim = Sim::new(LinkConfig::default());
    let c = sim.add(cfg(1), None);
    let no_store = no_store(2);
    let d = data.clone();
    let handler: Handler = Box::new(move |_| {
        let mut r = Response::new(Code::CONTENT).with_payload(d.clone());
        r.options.set(OptionNumber::ETAG, b"v1");
        Reply::Now(r)
    });
    let s = sim.add(no_store, Some(handler));
    let server = sim.nodes[s].addr;
    let now = sim.now;
    sim.nodes[c]
        .ep
        .request(now, server, Request::new(Code::GET, "/stable"));
    assert!(sim.run_to_event(c, Duration::from_secs(10)));
    assert!(response(&sim, c).payload == data);
    assert_eq!(sim.nodes[s].requests_seen, 5);
}

#[test]
fn rfc7959_2_2_block2_beyond_the_end_gives_4_02() {
    let mut sim = Sim::new(LinkConfig::default());
    let c = sim.add(cfg(1), None);
    let s = sim.add(cfg(2), Some(serve(body(100, 1), Rc::new(Cell::new(0)))));
    let server = sim.nodes[s].addr;
    let mut req = Request::new(Code::GET, "/x");
    req.options.set_block(
        OptionNumber::BLOCK2,
        BlockOpt {
            num: 9,
            more: false,
            szx: 2,
        },
    );
    let now = sim.now;
    sim.nodes[c].ep.request(now, server, req);
    assert!(sim.run_to_event(c, Duration::from_secs(10)));
    assert_eq!(response(&sim, c).code, Code::BAD_OPTION);
}

#[test]
fn rfc7959_2_4_random_access_block_is_delivered_as_is() {
    let data = body(1000, 4);
    let mut sim = Sim::new(LinkConfig::default());
    let c = sim.add(cfg(1), None);
    let s = sim.add(cfg(2), Some(serve(data.clone(), Rc::new(Cell::new(0)))));
    let server = sim.nodes[s].addr;
    let mut req = Request::new(Code::GET, "/x");
    req.options.set_block(
        OptionNumber::BLOCK2,
        BlockOpt {
            num: 2,
            more: false,
            szx: 2,
        },
    );
    let now = sim.now;
    sim.nodes[c].ep.request(now, server, req);
    assert!(sim.run_to_event(c, Duration::from_secs(10)));
    let r = response(&sim, c);
    assert_eq!(&r.payload[..], &data[128..192]);
    assert_eq!(
        r.options.block2(),
        Some(BlockOpt {
            num: 2,
            more: true,
            szx: 2
        })
    );
}

#[test]
fn client_refuses_a_body_over_its_limit_at_its_first_block() {
    let mut sim = Sim::new(LinkConfig::default());
    let small = EndpointConfig {
        limits: Limits {
            client_body_bytes: 4096,
            ..Limits::default()
        },
        ..cfg(1)
    };
    let c = sim.add(small, None);
    // The server renders each block again, so `calls` counts the blocks asked for.
    let calls = Rc::new(Cell::new(0));
    let s = sim.add(no_store(2), Some(serve(body(10_000, 1), calls.clone())));
    let server = sim.nodes[s].addr;
    let now = sim.now;
    sim.nodes[c]
        .ep
        .request(now, server, Request::new(Code::GET, "/x"));
    assert!(sim.run_to_event(c, Duration::from_secs(10)));
    assert!(matches!(
        sim.nodes[c].events[0].1,
        Event::RequestFailed {
            error: RequestError::TooLarge { limit: 4096 },
            ..
        }
    ));
    // Block 0's Size2 said 10,000 bytes: no block after it was fetched.
    assert_eq!(calls.get(), 1);
}

#[test]
fn rfc7959_2_4_non_block2_transfer_resends_lost_requests() {
    let data = body(200_000, 8);
    let mut sim = Sim::new(LinkConfig::lossy(0.2, 17));
    sim.record = false;
    let c = sim.add(cfg(1), None);
    let s = sim.add(cfg(2), Some(serve(data.clone(), Rc::new(Cell::new(0)))));
    let server = sim.nodes[s].addr;
    let mut req = Request::new(Code::GET, "/non");
    req.confirmable = false;
    let now = sim.now;
    sim.nodes[c].ep.request(now, server, req);
    assert!(sim.run_to_event(c, Duration::from_secs(100_000)));
    assert!(response(&sim, c).payload == data);
}

#[test]
fn progress_events_every_64_kib_and_at_the_end_when_asked() {
    let data = body(200_000, 2);
    let mut sim = Sim::new(LinkConfig::default());
    let c = sim.add(cfg(1), None);
    let s = sim.add(cfg(2), Some(serve(data, Rc::new(Cell::new(0)))));
    let server = sim.nodes[s].addr;
    let mut req = Request::new(Code::GET, "/p");
    req.progress = true;
    let now = sim.now;
    sim.nodes[c].ep.request(now, server, req);
    assert!(sim.run_until(Duration::from_secs(10), |s| {
        s.nodes[c]
            .events
            .iter()
            .any(|(_, e)| matches!(e, Event::Response { .. }))
    }));
    let progress: Vec<(usize, Option<usize>)> = sim.nodes[c]
        .events
        .iter()
        .filter_map(|(_, e)| match e {
            Event::Progress { done, total, .. } => Some((*done, *total)),
            _ => None,
        })
        .collect();
    assert_eq!(
        progress,
        [65536, 131_072, 196_608, 200_000].map(|d| (d, Some(200_000)))
    );
}

/// Runs a streamed GET of `/s` from node `c` to `server` until it ends; returns the
/// pieces (offset, bytes) and the last event.
fn streamed_get(
    sim: &mut Sim,
    c: usize,
    server: std::net::SocketAddr,
) -> (Vec<(usize, Bytes)>, Event) {
    let mut req = Request::new(Code::GET, "/s");
    req.stream = true;
    let now = sim.now;
    sim.nodes[c].ep.request(now, server, req);
    let ended = |e: &Event| matches!(e, Event::Response { .. } | Event::RequestFailed { .. });
    assert!(sim.run_until(Duration::from_secs(100_000), |s| {
        s.nodes[c].events.iter().any(|(_, e)| ended(e))
    }));
    let mut pieces = Vec::new();
    let mut last = None;
    for (_, e) in &sim.nodes[c].events {
        match e {
            Event::BodyChunk { offset, data, .. } => pieces.push((*offset, data.clone())),
            e if ended(e) => last = Some(e.clone()),
            _ => {}
        }
    }
    let last = last.unwrap_or_else(|| unreachable!("run_until saw the end"));
    (pieces, last)
}

#[test]
fn streamed_block2_10_mb_at_20_percent_loss_arrives_in_order_and_whole() {
    let data = body(10_032_012, 7);
    let mut sim = Sim::new(LinkConfig::lossy(0.2, 5));
    sim.record = false;
    let c = sim.add(cfg(1), None);
    let s = sim.add(cfg(2), Some(serve(data.clone(), Rc::new(Cell::new(0)))));
    let server = sim.nodes[s].addr;
    let (pieces, last) = streamed_get(&mut sim, c, server);
    let Event::Response { response, .. } = last else {
        panic!("expected the response, got {last:?}");
    };
    assert_eq!(response.code, Code::CONTENT);
    assert!(response.payload.is_empty(), "the body came in the pieces");
    assert_eq!(response.options.uint(OptionNumber::SIZE2), Some(10_032_012));
    let (last_piece, whole_pieces) = pieces.split_last().unwrap_or_else(|| panic!("no pieces"));
    assert!(whole_pieces.iter().all(|(_, p)| p.len() >= 64 << 10));
    assert!(!last_piece.1.is_empty());
    let mut next = 0;
    let mut got = Vec::with_capacity(data.len());
    for (offset, piece) in &pieces {
        assert_eq!(*offset, next, "pieces in order, without gaps or repeats");
        next += piece.len();
        got.extend_from_slice(piece);
    }
    assert!(got == data[..], "streamed body differs");
}

#[test]
fn streamed_small_response_is_one_piece_and_errors_keep_their_diagnostic() {
    let mut sim = Sim::new(LinkConfig::default());
    let c = sim.add(cfg(1), None);
    let handler: Handler = Box::new(|req| {
        Reply::Now(if req.options.path_string() == "/s" {
            Response::new(Code::CONTENT).with_payload("small")
        } else {
            Response::diagnostic(Code::NOT_FOUND, "nothing here")
        })
    });
    let s = sim.add(cfg(2), Some(handler));
    let server = sim.nodes[s].addr;
    let (pieces, last) = streamed_get(&mut sim, c, server);
    assert_eq!(pieces, vec![(0, Bytes::from_static(b"small"))]);
    assert!(matches!(last, Event::Response { response, .. } if response.payload.is_empty()));

    sim.nodes[c].events.clear();
    let mut req = Request::new(Code::GET, "/missing");
    req.stream = true;
    let now = sim.now;
    sim.nodes[c].ep.request(now, server, req);
    assert!(sim.run_to_event(c, Duration::from_secs(10)));
    assert!(matches!(
        &sim.nodes[c].events[0].1,
        Event::Response { response, .. }
            if response.code == Code::NOT_FOUND && &response.payload[..] == b"nothing here"
    ));
}

#[test]
fn streamed_etag_change_fails_at_once_instead_of_restarting() {
    let seen = Rc::new(Cell::new(0u32));
    // No store: every continuation is rendered again, with a new ETag each time.
    let handler: Handler = Box::new(move |_| {
        seen.set(seen.get() + 1);
        let mut r = Response::new(Code::CONTENT).with_payload(body(3000, seen.get()));
        r.options.set(OptionNumber::ETAG, seen.get().to_be_bytes());
        Reply::Now(r)
    });
    let mut sim = Sim::new(LinkConfig::default());
    let c = sim.add(cfg(1), None);
    let no_store = no_store(2);
    let s = sim.add(no_store, Some(handler));
    let server = sim.nodes[s].addr;
    let (pieces, last) = streamed_get(&mut sim, c, server);
    assert!(
        pieces.is_empty(),
        "less than a piece arrived before the change"
    );
    assert!(matches!(
        last,
        Event::RequestFailed {
            error: RequestError::RepresentationChanged,
            ..
        }
    ));
    let block0_requests = sim
        .log
        .iter()
        .filter_map(|r| r.msg.as_ref().filter(|m| m.code.is_request()))
        .filter(|m| m.options.block2().is_none_or(|b| b.num == 0))
        .count();
    assert_eq!(block0_requests, 1, "no restart from block 0");
}

#[test]
fn a_block_whose_message_id_comes_round_again_is_answered_not_replayed() {
    // After 65,536 messages a client's message IDs start over, well within the 247 s that
    // the reply to block 0 is kept for duplicates, and its token stays the same for the
    // whole transfer. A continuation with block 0's message ID must get its own block.
    let mut ep = Endpoint::new(cfg(2));
    let peer = "127.0.0.9:5683".parse().unwrap_or_else(|_| unreachable!());
    let now = crate::sim::epoch();
    let data = body(4096, 7);
    let get = |num| {
        let mut m = Message::empty(Type::Con, 7);
        m.code = Code::GET;
        m.token = Token::new(b"tk").unwrap_or_default();
        m.options.set_path("/x");
        let block = BlockOpt {
            num,
            more: false,
            szx: 6,
        };
        m.options.set_block(OptionNumber::BLOCK2, block);
        m.encode()
    };
    let sent = |ep: &mut Endpoint| {
        let t = ep.poll_transmit().expect("a reply");
        Message::decode(&t.data).expect("a valid reply")
    };
    ep.handle(now, peer, &get(0), false);
    let Some(Event::Request(req)) = ep.poll_event() else {
        panic!("the first block reaches the application");
    };
    ep.respond(
        now,
        req.id,
        Response::new(Code::CONTENT).with_payload(data.clone()),
    );
    assert_eq!(sent(&mut ep).payload, data.slice(..1024));

    ep.handle(now, peer, &get(2), false);
    let reply = sent(&mut ep);
    assert_eq!(reply.options.block2().map(|b| b.num), Some(2));
    assert_eq!(reply.payload, data.slice(2048..3072));
    // A real duplicate of block 0 still gets block 0's reply.
    ep.handle(now, peer, &get(0), false);
    assert_eq!(sent(&mut ep).payload, data.slice(..1024));
    assert!(ep.poll_event().is_none());

    // The same for an upload: block 1 with block 0's message ID is not answered with block
    // 0's 2.31 Continue.
    let put = |num| {
        let mut m = Message::empty(Type::Con, 9);
        m.code = Code::PUT;
        m.token = Token::new(b"up").unwrap_or_default();
        m.options.set_path("/y");
        let block = BlockOpt {
            num,
            more: true,
            szx: 0,
        };
        m.options.set_block(OptionNumber::BLOCK1, block);
        m.payload = Bytes::from_static(&[1; 16]);
        m.encode()
    };
    for num in [0, 1] {
        ep.handle(now, peer, &put(num), false);
        let reply = sent(&mut ep);
        assert_eq!(reply.code, Code::CONTINUE);
        assert_eq!(reply.options.block1().map(|b| b.num), Some(num));
    }
}

#[test]
fn a_piggybacked_answer_for_another_block_is_asked_again() {
    // A server that answers block 1 with block 3 in the ACK: the client's exchange is over,
    // so it must ask for block 1 again instead of waiting for an answer that cannot come.
    let mut ep = Endpoint::new(cfg(1));
    let server = "127.0.0.9:5683".parse().unwrap_or_else(|_| unreachable!());
    let now = crate::sim::epoch();
    let sent = |ep: &mut Endpoint| {
        let t = ep.poll_transmit().expect("a request");
        Message::decode(&t.data).expect("a valid request")
    };
    let ack = |req: &Message, num| {
        let mut m = Message::empty(Type::Ack, req.message_id);
        m.code = Code::CONTENT;
        m.token = req.token;
        let block = BlockOpt {
            num,
            more: true,
            szx: 6,
        };
        m.options.set_block(OptionNumber::BLOCK2, block);
        m.payload = Bytes::from(vec![7; 1024]);
        m.encode()
    };
    let mut req = Request::new(Code::GET, "/big");
    req.transfer = Some(coap::Transfer::StopAndWait);
    ep.request(now, server, req);
    let first = sent(&mut ep);
    ep.handle(now, server, &ack(&first, 0), false);
    let second = sent(&mut ep);
    assert_eq!(second.options.block2().map(|b| b.num), Some(1));
    ep.handle(now, server, &ack(&second, 3), false);
    let again = sent(&mut ep);
    assert_eq!(again.options.block2().map(|b| b.num), Some(1));
    assert_ne!(again.message_id, second.message_id);
}

#[test]
fn idle_uploads_and_stored_representations_expire_without_another_request() {
    let mut sim = Sim::new(LinkConfig::default());
    let c = sim.add(cfg(1), None);
    let handler: Handler = Box::new(|req| {
        let body = if req.payload.is_empty() { 4000 } else { 10 };
        Reply::Now(Response::new(Code::CONTENT).with_payload(vec![5u8; body]))
    });
    let s = sim.add(cfg(2), Some(handler));
    let server = sim.nodes[s].addr;
    // A GET whose 4,000-byte answer is stored for its continuations, whose client asks
    // for block 0 only; and the first block of an upload that never goes on.
    let now = sim.now;
    let mut get = Request::new(Code::GET, "/big");
    get.options.set_block(
        OptionNumber::BLOCK2,
        BlockOpt {
            num: 0,
            more: false,
            szx: 6,
        },
    );
    sim.nodes[c].ep.request(now, server, get);
    assert!(sim.run_to_event(c, Duration::from_secs(10)));
    let mut first = Message::empty(Type::Con, 77);
    first.code = Code::PUT;
    first.token = Token::new(&[7]).unwrap_or_default();
    first.options.set_path("/up");
    first.options.set_block(
        OptionNumber::BLOCK1,
        BlockOpt {
            num: 0,
            more: true,
            szx: 6,
        },
    );
    first.payload = vec![1u8; 1024].into();
    let client = sim.nodes[c].addr;
    sim.inject(client, s, &first.encode());
    sim.run_until(Duration::from_secs(1), |_| false);
    let held = sim.nodes[s].ep.server_stats();
    assert!(
        held.upload_bytes >= 1024 && held.stored_bytes >= 4000,
        "{held:?}"
    );
    // Nothing more arrives; the blockwise lifetime (247 s) passes.
    let lifetime = cfg(2).limits.blockwise_lifetime;
    sim.run_until(lifetime + Duration::from_secs(5), |_| false);
    let held = sim.nodes[s].ep.server_stats();
    assert_eq!((held.upload_bytes, held.stored_bytes), (0, 0), "{held:?}");
}
