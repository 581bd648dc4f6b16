//! DTLS with pre-shared keys (`coaps://`): our client and server over loopback, the
//! identity reaching the handlers, a wrong key getting nothing.

use std::sync::Arc;
use std::time::Duration;

use coap::{Code, EndpointConfig, Request, Response};
use coap_net::{Client, Psk, Resource, Router, Server, ServerConfig, handler};

use crate::{body, within};

fn keys() -> Psk {
    Psk::Server(Arc::new(|identity: &[u8]| match identity {
        b"alice" => Some(b"secret-of-alice".to_vec()),
        _ => None,
    }))
}

fn client(identity: &str, key: &str, peer: std::net::SocketAddr) -> Client {
    let psk = Psk::Client {
        identity: identity.as_bytes().to_vec(),
        key: key.as_bytes().to_vec(),
    };
    Client::for_peer_secured(peer, EndpointConfig::default(), Some(&psk))
        .unwrap_or_else(|e| panic!("{e}"))
}

#[tokio::test]
async fn dtls_psk_carries_requests_block_wise_and_names_the_identity() {
    let router = Router::new();
    let big = body(20_000);
    let served = big.clone();
    router.add(
        "/who",
        Resource::new().get(handler(|ctx| async move {
            let who = ctx
                .request
                .identity
                .as_deref()
                .unwrap_or("nobody")
                .to_string();
            Response::new(Code::CONTENT).with_payload(who)
        })),
    );
    router.add(
        "/big",
        Resource::new().get(handler(move |_| {
            let b = served.clone();
            async move { Response::new(Code::CONTENT).with_payload(b) }
        })),
    );
    let config = ServerConfig {
        secure: vec!["127.0.0.1:0".parse().unwrap_or_else(|_| unreachable!())],
        psk: Some(keys()),
        ..ServerConfig::default()
    };
    let server = Server::bind(&[], config, router).unwrap_or_else(|e| panic!("{e}"));
    let addr = server.local_addrs()[0];

    let alice = client("alice", "secret-of-alice", addr);
    let who = within(alice.send(addr, Request::new(Code::GET, "/who")))
        .await
        .unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(&who.payload[..], b"alice");
    let got = within(alice.send(addr, Request::new(Code::GET, "/big")))
        .await
        .unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(got.payload, big);

    // A wrong key: the handshake fails and nothing is answered.
    let mallory = client("alice", "guessed", addr);
    let mut req = Request::new(Code::GET, "/who");
    req.timeout = Some(Duration::from_secs(3));
    assert!(within(mallory.send(addr, req)).await.is_err());
}
