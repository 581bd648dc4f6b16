//! RFC 9177 Q-Block2 downloads and Q-Block1 uploads in the simulator: bit-exact under
//! loss, duplication and reordering, deterministic per seed, and the sets, 'Continue's
//! and missing-block requests on the wire for a fixed seed.

use std::cell::RefCell;
use std::rc::Rc;
use std::time::Duration;

use bytes::Bytes;
use coap::{Code, Request, Response, Transfer};

use crate::blockwise::{body, cfg, response};
use crate::sim::{LinkConfig, Reply, Sim};
use crate::window::{self, Outcome, link};

const TEN_MB: usize = 10_032_012;

fn download(link: LinkConfig, data: &Bytes, record: bool) -> Outcome {
    window::download(link, data, Transfer::QBlock, record)
}

/// A PUT of `data` with Q-Block1; returns what the server's application received and
/// the response code.
fn upload(link: LinkConfig, data: &Bytes, record: bool) -> (Bytes, Code, Vec<String>) {
    let mut sim = Sim::new(link);
    sim.record = record;
    let got = Rc::new(RefCell::new(Vec::new()));
    let seen = got.clone();
    let handler = Box::new(move |req: &coap::IncomingRequest| {
        seen.borrow_mut().push(req.payload.clone());
        Reply::Now(Response::new(Code::CHANGED))
    });
    let c = sim.add(cfg(1), None);
    // Room for a 10 MB body (the default takes 8 MB from one peer).
    let mut server_cfg = cfg(2);
    server_cfg.limits.block1_peer_bytes = 16 << 20;
    let s = sim.add(server_cfg, Some(handler));
    let server = sim.nodes[s].addr;
    let now = sim.now;
    let mut req = Request::new(Code::PUT, "/up");
    req.payload = data.clone();
    req.transfer = Some(Transfer::QBlock);
    sim.nodes[c].ep.request(now, server, req);
    assert!(sim.run_to_event(c, Duration::from_secs(3600)), "no outcome");
    let code = response(&sim, c).code;
    let bodies = got.borrow();
    assert_eq!(
        bodies.len(),
        1,
        "the application saw {} bodies",
        bodies.len()
    );
    let trace = sim.log.iter().map(|r| r.line()).collect();
    (bodies[0].clone(), code, trace)
}

#[test]
fn q_block2_ten_mb_arrive_bit_exact_at_0_2_5_and_20_percent_loss() {
    let data = body(TEN_MB, 7);
    for loss in [0.0, 0.02, 0.05, 0.20] {
        let o = download(link(loss, 11), &data, false);
        assert!(o.body == data, "body differs at {loss} loss");
        assert!(
            o.stats.srtt.is_some(),
            "no round-trip estimate at {loss} loss"
        );
    }
}

#[test]
fn q_block1_ten_mb_arrive_bit_exact_at_0_2_5_and_20_percent_loss() {
    let data = body(TEN_MB, 8);
    for loss in [0.0, 0.02, 0.05, 0.20] {
        let (got, code, _) = upload(link(loss, 12), &data, false);
        assert_eq!(code, Code::CHANGED, "at {loss} loss");
        assert!(got == data, "body differs at {loss} loss");
    }
}

#[test]
fn a_seed_gives_the_same_q_block_transfer_every_time() {
    let data = body(300_000, 3);
    let a = download(link(0.05, 5), &data, true);
    let b = download(link(0.05, 5), &data, true);
    assert!(a.body == data);
    assert_eq!((a.elapsed, &a.trace), (b.elapsed, &b.trace));
    let (x, _, tx) = upload(link(0.05, 5), &data, true);
    let (y, _, ty) = upload(link(0.05, 5), &data, true);
    assert!(x == data && y == data);
    assert_eq!(tx, ty);
}

#[test]
fn a_large_error_to_a_q_block2_request_goes_in_blocks_within_the_mtu() {
    // Found by fuzzing: an error answer to a Q-Block2 request went whole, 3.8 KB in one
    // datagram. It is cut with Block2 like any answer.
    let mut sim = Sim::new(link(0.0, 1));
    let c = sim.add(cfg(1), None);
    let handler: crate::sim::Handler = Box::new(|_| {
        Reply::Now(Response::new(Code::INTERNAL_SERVER_ERROR).with_payload(vec![b'e'; 3840]))
    });
    let s = sim.add(cfg(2), Some(handler));
    let server = sim.nodes[s].addr;
    let now = sim.now;
    let mut req = Request::new(Code::GET, "/broken");
    req.transfer = Some(Transfer::QBlock);
    sim.nodes[c].ep.request(now, server, req);
    assert!(sim.run_to_event(c, Duration::from_secs(60)), "no outcome");
    assert_eq!(response(&sim, c).code, Code::INTERNAL_SERVER_ERROR);
    let largest = sim.log.iter().map(|r| r.len).max().unwrap_or(0);
    assert!(largest <= 1152, "a {largest}-byte datagram");
}
