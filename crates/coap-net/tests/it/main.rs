//! coap-net over real loopback sockets: client and server together.

mod dtls;
mod multicast;
mod stream;
mod tcp;
mod tls;
mod ws;

use std::net::SocketAddr;
use std::sync::Arc;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::Duration;

use bytes::Bytes;
use coap::{Code, EndpointConfig, OptionNumber, Request, Response};
use coap_net::{Client, Resource, Router, Server, ServerConfig, handler};

fn body(len: usize) -> Bytes {
    (0..len)
        .map(|i| (i.wrapping_mul(31) ^ (i >> 7)) as u8)
        .collect::<Vec<u8>>()
        .into()
}

fn server(router: Arc<Router>) -> (Server, SocketAddr) {
    let s = Server::bind(
        &["127.0.0.1:0".parse().unwrap_or_else(|_| unreachable!())],
        ServerConfig::default(),
        router,
    )
    .unwrap_or_else(|e| panic!("bind: {e}"));
    let addr = s.local_addrs()[0];
    (s, addr)
}

fn client(peer: SocketAddr) -> Client {
    Client::for_peer(
        peer,
        EndpointConfig {
            rng_seed: 5,
            ..EndpointConfig::default()
        },
    )
    .unwrap_or_else(|e| panic!("{e}"))
}

async fn within<T>(f: impl Future<Output = T>) -> T {
    tokio::time::timeout(Duration::from_secs(20), f)
        .await
        .unwrap_or_else(|_| panic!("test took too long"))
}

#[tokio::test]
async fn methods_4_04_and_4_05_through_the_router() {
    let router = Router::new();
    router.add(
        "/things/{name}",
        Resource::new()
            .get(handler(|ctx| async move {
                Response::new(Code::CONTENT)
                    .with_payload(format!("thing {}", ctx.param("name").unwrap_or("")))
            }))
            .put(handler(|ctx| async move {
                Response::new(Code::CHANGED).with_payload(ctx.request.payload)
            }))
            .delete(handler(|_| async { Response::new(Code::DELETED) })),
    );
    let (_s, addr) = server(router);
    let c = client(addr);
    within(async {
        let r = c
            .send(addr, Request::new(Code::GET, "/things/a"))
            .await
            .unwrap_or_else(|e| panic!("{e}"));
        assert_eq!((r.code, &r.payload[..]), (Code::CONTENT, &b"thing a"[..]));
        let r = c
            .send(addr, Request::new(Code::PUT, "/things/a").with_payload("x"))
            .await
            .unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(r.code, Code::CHANGED);
        let r = c
            .send(addr, Request::new(Code::DELETE, "/things/a"))
            .await
            .unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(r.code, Code::DELETED);
        let r = c
            .send(addr, Request::new(Code::POST, "/things/a"))
            .await
            .unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(r.code, Code::METHOD_NOT_ALLOWED);
        let r = c
            .send(addr, Request::new(Code::GET, "/nothing"))
            .await
            .unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(r.code, Code::NOT_FOUND);
    })
    .await;
}

#[tokio::test]
async fn rfc6690_4_1_discovery_with_filter_and_runtime_add_remove() {
    let router = Router::new();
    let ok = || handler(|_| async { Response::new(Code::CONTENT) });
    router.add(
        "/cams/111111111111/color",
        Resource::new()
            .get(ok())
            .attr("rt", "rgbd.color")
            .attr("ct", "42"),
    );
    router.add(
        "/cams/111111111111/depth",
        Resource::new().get(ok()).attr("rt", "rgbd.depth"),
    );
    let (_s, addr) = server(router.clone());
    let c = client(addr);
    within(async {
        let mut req = Request::new(Code::GET, "/.well-known/core");
        req.options.push(OptionNumber::URI_QUERY, b"rt=rgbd.c*");
        let r = c
            .send(addr, req.clone())
            .await
            .unwrap_or_else(|e| panic!("{e}"));
        let text = String::from_utf8_lossy(&r.payload).into_owned();
        assert!(
            text.contains("</cams/111111111111/color>") && !text.contains("depth"),
            "{text}"
        );
        assert_eq!(
            r.options.content_format(),
            Some(coap::ContentFormat::LINK_FORMAT)
        );
        assert!(router.remove("/cams/111111111111/color"));
        let r = c.send(addr, req).await.unwrap_or_else(|e| panic!("{e}"));
        assert!(
            r.payload.is_empty(),
            "removed resources vanish from discovery"
        );
        let r = c
            .send(addr, Request::new(Code::GET, "/cams/111111111111/color"))
            .await
            .unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(r.code, Code::NOT_FOUND);
    })
    .await;
}

#[tokio::test]
async fn rfc7959_large_get_and_post_over_loopback_bit_exact_handler_once() {
    let data = body(2_764_810);
    let calls = Arc::new(AtomicUsize::new(0));
    let router = Router::new();
    let (d, n) = (data.clone(), calls.clone());
    router.add(
        "/grab",
        Resource::new().post(handler(move |_| {
            let (d, n) = (d.clone(), n.clone());
            async move {
                n.fetch_add(1, Ordering::SeqCst);
                Response::new(Code::CONTENT).with_payload(d)
            }
        })),
    );
    let (_s, addr) = server(router);
    let c = client(addr);
    within(async {
        let r = c
            .send(addr, Request::new(Code::POST, "/grab"))
            .await
            .unwrap_or_else(|e| panic!("{e}"));
        assert!(r.payload == data);
        assert_eq!(calls.load(Ordering::SeqCst), 1);
    })
    .await;
}

#[tokio::test]
async fn rfc7959_block1_upload_over_loopback() {
    let data = body(3500);
    let router = Router::new();
    let d = data.clone();
    router.add(
        "/up",
        Resource::new().put(handler(move |ctx| {
            let ok = ctx.request.payload == d;
            async move { Response::new(if ok { Code::CHANGED } else { Code::BAD_REQUEST }) }
        })),
    );
    let (_s, addr) = server(router);
    let c = client(addr);
    within(async {
        let r = c
            .send(addr, Request::new(Code::PUT, "/up").with_payload(data))
            .await
            .unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(r.code, Code::CHANGED);
    })
    .await;
}

#[tokio::test]
async fn rfc7252_5_2_2_slow_handler_gets_separate_response() {
    let router = Router::new();
    router.add(
        "/slow",
        Resource::new().get(handler(|_| async {
            tokio::time::sleep(Duration::from_millis(1300)).await;
            Response::new(Code::CONTENT).with_payload("late")
        })),
    );
    let (_s, addr) = server(router);
    let c = client(addr);
    within(async {
        let r = c
            .send(addr, Request::new(Code::GET, "/slow"))
            .await
            .unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(&r.payload[..], b"late");
    })
    .await;
}

#[tokio::test]
async fn rfc7641_observe_five_notifications_then_cancel() {
    let counter = Arc::new(AtomicUsize::new(0));
    let router = Router::new();
    let n = counter.clone();
    router.add(
        "/counter",
        Resource::new()
            .get(handler(move |_| {
                let v = n.load(Ordering::SeqCst);
                async move { Response::new(Code::CONTENT).with_payload(v.to_string()) }
            }))
            .observable(),
    );
    let (s, addr) = server(router);
    let c = client(addr);
    within(async {
        let mut obs = c
            .observe(addr, Request::new(Code::GET, "/counter"))
            .await
            .unwrap_or_else(|e| panic!("{e}"));
        let first = obs
            .next()
            .await
            .unwrap_or_else(|| panic!("ended"))
            .unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(&first.payload[..], b"0");
        for k in 1..=5 {
            counter.store(k, Ordering::SeqCst);
            assert_eq!(s.notify("/counter").await, 1);
            let r = obs
                .next()
                .await
                .unwrap_or_else(|| panic!("ended"))
                .unwrap_or_else(|e| panic!("{e}"));
            assert_eq!(r.payload, k.to_string().as_bytes());
        }
        drop(obs);
        // The next notification is answered with a Reset and the observation ends.
        counter.store(6, Ordering::SeqCst);
        s.notify("/counter").await;
        for _ in 0..50 {
            if s.observed_paths().is_empty() {
                break;
            }
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
        assert!(s.observed_paths().is_empty());
    })
    .await;
}

async fn next(obs: &mut coap_net::Observation) -> Response {
    obs.next()
        .await
        .unwrap_or_else(|| panic!("ended"))
        .unwrap_or_else(|e| panic!("{e}"))
}

/// A change notified after the registration was answered with its state, or a second
/// notify of a state already sent: nothing goes out twice. The next notification the
/// observer gets is the next state.
#[tokio::test]
async fn rfc7641_an_observer_is_not_sent_the_representation_it_has() {
    let counter = Arc::new(AtomicUsize::new(0));
    let router = Router::new();
    let n = counter.clone();
    router.add(
        "/counter",
        Resource::new()
            .get(handler(move |_| {
                let v = n.load(Ordering::SeqCst);
                async move { Response::new(Code::CONTENT).with_payload(v.to_string()) }
            }))
            .observable(),
    );
    let tagged = counter.clone();
    router.add(
        "/tagged",
        Resource::new()
            .get(handler(move |_| {
                // The body changes on every read; the ETag names the state.
                let v = tagged.load(Ordering::SeqCst);
                let read = READS.fetch_add(1, Ordering::SeqCst);
                async move {
                    let mut r =
                        Response::new(Code::CONTENT).with_payload(format!("{v} read {read}"));
                    r.options.set(OptionNumber::ETAG, [v as u8]);
                    r
                }
            }))
            .observable(),
    );
    static READS: AtomicUsize = AtomicUsize::new(0);
    let (s, addr) = server(router);
    let c = client(addr);
    within(async {
        let mut plain = c
            .observe(addr, Request::new(Code::GET, "/counter"))
            .await
            .unwrap_or_else(|e| panic!("{e}"));
        let mut tagged = c
            .observe(addr, Request::new(Code::GET, "/tagged"))
            .await
            .unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(&next(&mut plain).await.payload[..], b"0");
        assert!(next(&mut tagged).await.payload.starts_with(b"0 read"));
        // The change that led to state 0 reaches the notifier after the registrations
        // were answered with it.
        assert_eq!(
            s.notify("/counter").await,
            0,
            "the registration's state again"
        );
        assert_eq!(
            s.notify("/tagged").await,
            0,
            "the registration's ETag again"
        );
        counter.store(1, Ordering::SeqCst);
        assert_eq!(s.notify("/counter").await, 1);
        assert_eq!(s.notify("/tagged").await, 1);
        // The notification of the next change read state 1 already.
        assert_eq!(
            s.notify("/counter").await,
            0,
            "the last notification's state again"
        );
        assert_eq!(
            s.notify("/tagged").await,
            0,
            "the last notification's ETag again"
        );
        counter.store(2, Ordering::SeqCst);
        assert_eq!(s.notify("/counter").await, 1);
        assert_eq!(s.notify("/tagged").await, 1);
        for want in ["1", "2"] {
            assert_eq!(next(&mut plain).await.payload, want.as_bytes());
            let r = next(&mut tagged).await;
            assert!(r.payload.starts_with(format!("{want} read").as_bytes()));
        }
    })
    .await;
}

#[tokio::test]
async fn rfc7959_2_6_notifications_sent_block_wise_arrive_whole() {
    let counter = Arc::new(AtomicUsize::new(0));
    let router = Router::new();
    let n = counter.clone();
    router.add(
        "/big",
        Resource::new()
            .get(handler(move |_| {
                let len = 3000 + 1000 * n.load(Ordering::SeqCst);
                async move { Response::new(Code::CONTENT).with_payload(body(len)) }
            }))
            .observable(),
    );
    let (s, addr) = server(router);
    let c = client(addr);
    within(async {
        let mut obs = c
            .observe(addr, Request::new(Code::GET, "/big"))
            .await
            .unwrap_or_else(|e| panic!("{e}"));
        for k in 0..3 {
            if k > 0 {
                counter.store(k, Ordering::SeqCst);
                assert_eq!(s.notify("/big").await, 1);
            }
            let r = obs
                .next()
                .await
                .unwrap_or_else(|| panic!("ended"))
                .unwrap_or_else(|e| panic!("{e}"));
            assert_eq!(r.payload, body(3000 + 1000 * k), "response {k}");
            assert!(r.options.contains(OptionNumber::OBSERVE), "response {k}");
        }
    })
    .await;
}

/// A notification sent block-wise whose resource changes before its other blocks are
/// asked (the server stores the newer representation for the client, so block 1 carries
/// another ETag): the observer fetches the new representation whole instead of failing,
/// and the observation goes on.
#[tokio::test]
async fn rfc7959_2_6_a_notification_changed_mid_transfer_is_fetched_again() {
    let counter = Arc::new(AtomicUsize::new(0));
    let router = Router::new();
    let n = counter.clone();
    router.add(
        "/big",
        Resource::new()
            .get(handler(move |_| {
                let k = n.load(Ordering::SeqCst);
                async move {
                    let mut r = Response::new(Code::CONTENT).with_payload(body(3000 + 1000 * k));
                    r.options.set(OptionNumber::ETAG, [k as u8]);
                    r
                }
            }))
            .observable(),
    );
    let (s, addr) = server(router);
    let c = client(addr);
    within(async {
        let mut obs = c
            .observe(addr, Request::new(Code::GET, "/big"))
            .await
            .unwrap_or_else(|e| panic!("{e}"));
        let first = obs.next().await.unwrap_or_else(|| panic!("ended"));
        assert_eq!(first.unwrap_or_else(|e| panic!("{e}")).payload, body(3000));
        // Two changes before the observer reads on: the first notification's block 0 is
        // waiting, but the server already stores the second's body.
        for k in 1..=2 {
            counter.store(k, Ordering::SeqCst);
            assert_eq!(s.notify("/big").await, 1);
        }
        let r = obs
            .next()
            .await
            .unwrap_or_else(|| panic!("ended"))
            .unwrap_or_else(|e| panic!("a changed notification ends the observer: {e}"));
        assert_eq!(r.payload, body(5000), "the newest representation");
        assert_eq!(r.options.etag(), Some(&[2u8][..]));
        assert!(r.options.contains(OptionNumber::OBSERVE));
        let r = obs
            .next()
            .await
            .unwrap_or_else(|| panic!("ended"))
            .unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(r.payload, body(5000));
        counter.store(3, Ordering::SeqCst);
        assert_eq!(s.notify("/big").await, 1);
        let r = obs
            .next()
            .await
            .unwrap_or_else(|| panic!("ended"))
            .unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(r.payload, body(6000), "observing after the change");
    })
    .await;
}

#[tokio::test]
async fn rfc7252_5_10_6_matching_etag_gets_2_03_valid() {
    let router = Router::new();
    router.add(
        "/tagged",
        Resource::new().get(handler(|_| async {
            let mut r = Response::new(Code::CONTENT).with_payload("body");
            r.options.set(OptionNumber::ETAG, b"t1");
            r
        })),
    );
    let (_s, addr) = server(router);
    let c = client(addr);
    within(async {
        let mut req = Request::new(Code::GET, "/tagged");
        req.options.push(OptionNumber::ETAG, b"t1");
        let r = c.send(addr, req).await.unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(r.code, Code::VALID);
        assert!(r.payload.is_empty());
        assert_eq!(r.options.etag(), Some(&b"t1"[..]));
    })
    .await;
}

#[tokio::test]
async fn rfc7252_4_3_ping_over_loopback() {
    let (_s, addr) = server(Router::new());
    let c = client(addr);
    within(async { c.ping(addr).await.unwrap_or_else(|e| panic!("{e}")) }).await;
}

#[tokio::test]
async fn ipv6_loopback_works() {
    let router = Router::new();
    router.add(
        "/v6",
        Resource::new().get(handler(|_| async {
            Response::new(Code::CONTENT).with_payload("six")
        })),
    );
    let s = match Server::bind(
        &["[::1]:0".parse().unwrap_or_else(|_| unreachable!())],
        ServerConfig::default(),
        router,
    ) {
        Ok(s) => s,
        Err(e) => {
            eprintln!("SKIP ipv6_loopback_works: no IPv6 loopback here ({e})");
            return;
        }
    };
    let addr = s.local_addrs()[0];
    let c = client(addr);
    within(async {
        let r = c
            .send(addr, Request::new(Code::GET, "/v6"))
            .await
            .unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(&r.payload[..], b"six");
    })
    .await;
}

#[tokio::test]
async fn retransmission_backs_off_to_timeout() {
    // A peer that never answers; with a 20 ms ACK_TIMEOUT and no random factor the five
    // transmissions go out at 0, 20, 60, 140 and 300 ms and the request fails at 620 ms,
    // and the datagrams really cross the loopback.
    let silent = std::net::UdpSocket::bind("127.0.0.1:0").unwrap_or_else(|e| panic!("{e}"));
    let peer = silent.local_addr().unwrap_or_else(|e| panic!("{e}"));
    let c = Client::for_peer(
        peer,
        EndpointConfig {
            ack_timeout: Duration::from_millis(20),
            ack_random_factor: 1.0,
            ..EndpointConfig::default()
        },
    )
    .unwrap_or_else(|e| panic!("{e}"));
    let started = std::time::Instant::now();
    let r = within(c.send(peer, Request::new(Code::GET, "/x"))).await;
    assert!(
        matches!(
            r,
            Err(coap_net::Error::Request(coap::RequestError::Timeout))
        ),
        "{r:?}"
    );
    // Never before the back-off has run its course (a lower bound: no speed is asserted).
    let waited = started.elapsed();
    assert!(waited >= Duration::from_millis(620), "{waited:?}");
    silent
        .set_nonblocking(true)
        .unwrap_or_else(|e| panic!("{e}"));
    let mut buf = [0u8; 64];
    let mut n = 0;
    while silent.recv_from(&mut buf).is_ok() {
        n += 1;
    }
    assert_eq!(
        n, 5,
        "one transmission and MAX_RETRANSMIT = 4 retransmissions"
    );
}

#[tokio::test]
async fn a_second_server_on_a_taken_unicast_address_fails_to_bind() {
    let (_first, addr) = server(Router::new());
    let second = Server::bind(&[addr], ServerConfig::default(), Router::new());
    let Err(error) = second else {
        panic!("a second server bound {addr}, which the first one holds");
    };
    assert_eq!(error.kind(), std::io::ErrorKind::AddrInUse, "{error}");
}

#[tokio::test]
async fn a_request_to_a_port_nothing_listens_on_fails_at_once() {
    // A port that was free a moment ago: nothing listens there.
    let peer = std::net::UdpSocket::bind("127.0.0.1:0")
        .and_then(|s| s.local_addr())
        .unwrap_or_else(|e| panic!("{e}"));
    let c = client(peer);
    // Unreachable, not Timeout: the ICMP error ended it, not the retransmissions.
    let result = within(c.send(peer, Request::new(Code::GET, "/x"))).await;
    assert!(
        matches!(
            result,
            Err(coap_net::Error::Request(coap::RequestError::Unreachable))
        ),
        "{result:?}"
    );
}
