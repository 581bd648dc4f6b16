//! Bodies streamed to a writer as their blocks arrive (`Client::send_streamed`).

use std::net::SocketAddr;

use bytes::Bytes;
use coap::{BlockOpt, Code, Message, OptionNumber, Request, RequestError, Response, Type};
use coap_net::{BodyPart, Resource, Router, handler};

use crate::{body, client, server, within};

#[tokio::test]
async fn a_10_mb_body_streamed_into_a_writer_equals_the_original() {
    let data = body(10_032_012);
    let router = Router::new();
    let d = data.clone();
    router.add(
        "/big",
        Resource::new().get(handler(move |_| {
            let d = d.clone();
            async move { Response::new(Code::CONTENT).with_payload(d) }
        })),
    );
    let (_s, addr) = server(router);
    let c = client(addr);
    within(async {
        let mut sink = Vec::new();
        let (r, written) = c
            .send_to_writer(addr, Request::new(Code::GET, "/big"), &mut sink)
            .await
            .unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(r.code, Code::CONTENT);
        assert!(r.payload.is_empty(), "the body went to the writer");
        assert_eq!(r.options.uint(OptionNumber::SIZE2), Some(10_032_012));
        assert_eq!(written, data.len());
        assert!(sink == data[..], "streamed body differs");
    })
    .await;
}

/// A server that answers every GET for block n with 1024 bytes and ETag 1, except that
/// from block `change_at` on its ETag is 2.
async fn changing_server(change_at: u32) -> SocketAddr {
    let socket = tokio::net::UdpSocket::bind("127.0.0.1:0")
        .await
        .unwrap_or_else(|e| panic!("bind: {e}"));
    let addr = socket.local_addr().unwrap_or_else(|e| panic!("{e}"));
    tokio::spawn(async move {
        let mut buf = [0u8; 2048];
        while let Ok((n, peer)) = socket.recv_from(&mut buf).await {
            let Ok(req) = Message::decode(&buf[..n]) else {
                continue;
            };
            let num = req.options.block2().map_or(0, |b| b.num);
            let mut options = coap::Options::new();
            let etag: u8 = if num >= change_at { 2 } else { 1 };
            options.set(OptionNumber::ETAG, vec![etag]);
            options.set_block(
                OptionNumber::BLOCK2,
                BlockOpt {
                    num,
                    more: true,
                    szx: 6,
                },
            );
            let reply = Message {
                ty: Type::Ack,
                code: Code::CONTENT,
                message_id: req.message_id,
                token: req.token,
                options,
                payload: Bytes::from(vec![num as u8; 1024]),
            };
            if socket.send_to(&reply.encode(), peer).await.is_err() {
                return;
            }
        }
    });
    addr
}

#[tokio::test]
async fn a_streamed_body_whose_etag_changes_mid_transfer_is_an_error() {
    let addr = changing_server(100).await;
    let c = client(addr);
    within(async {
        let mut stream = c
            .send_streamed(addr, Request::new(Code::GET, "/changing"))
            .unwrap_or_else(|e| panic!("{e}"));
        let mut got = Vec::new();
        let error = loop {
            match stream.next().await {
                Ok(BodyPart::Chunk { data, .. }) => got.extend_from_slice(&data),
                Ok(BodyPart::End(r)) => panic!("a changed body ended as {r:?}"),
                Err(e) => break e,
            }
        };
        // One 64 KiB piece (blocks 0 to 63) left before the change at block 100.
        let want: Vec<u8> = (0..64u8).flat_map(|n| [n; 1024]).collect();
        assert!(got == want, "the blocks before the change, in order");
        assert!(
            matches!(
                error,
                coap_net::Error::Request(RequestError::RepresentationChanged)
            ),
            "{error}"
        );
        assert!(matches!(stream.next().await, Err(coap_net::Error::Closed)));
    })
    .await;
}

#[test]
fn a_socket_receives_datagrams_in_order_and_then_waits_until_its_timeout() {
    use coap_net::socket::{RECV_BUFFER, Socket};
    let socket = Socket::bind("127.0.0.1:0".parse().unwrap_or_else(|_| unreachable!()))
        .unwrap_or_else(|e| panic!("bind: {e}"));
    socket
        .set_read_timeout(Some(std::time::Duration::from_millis(100)))
        .unwrap_or_else(|e| panic!("{e}"));
    let sender = std::net::UdpSocket::bind("127.0.0.1:0").unwrap_or_else(|e| panic!("{e}"));
    let sent = [&b"first"[..], &[7u8; 1500][..], b"", b"fourth"];
    for d in sent {
        sender
            .send_to(d, socket.local_addr())
            .unwrap_or_else(|e| panic!("{e}"));
    }
    let mut buf = vec![0u8; RECV_BUFFER];
    let mut got: Vec<Vec<u8>> = Vec::new();
    while got.len() < sent.len() {
        let d = socket.recv(&mut buf).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(
            d.peer,
            sender.local_addr().unwrap_or_else(|e| panic!("{e}"))
        );
        assert!(!d.multicast);
        // A socket that does not read arrivals does not know the interface.
        assert_eq!(d.loopback, None);
        assert!(!d.forged_loopback());
        got.push(buf[..d.len].to_vec());
    }
    // The empty datagram counts too: the endpoint threads are woken by them.
    assert_eq!(got, sent.map(<[u8]>::to_vec));
    // A server's socket reads arrivals: this machine's datagrams come in over loopback.
    socket.read_arrivals().unwrap_or_else(|e| panic!("{e}"));
    sender
        .send_to(b"fifth", socket.local_addr())
        .unwrap_or_else(|e| panic!("{e}"));
    let d = socket.recv(&mut buf).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(&buf[..d.len], b"fifth");
    assert_eq!(d.loopback, Some(true));
    // Drained: the next receive waits for the read timeout.
    let waited = socket.recv(&mut buf);
    assert!(
        waited
            .as_ref()
            .is_err_and(|e| e.kind() == std::io::ErrorKind::WouldBlock),
        "{waited:?}"
    );
}
