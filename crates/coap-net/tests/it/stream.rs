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
    let addr = changing_server(3).await;
    let c = client(addr);
    within(async {
        let mut stream = c
            .send_streamed(addr, Request::new(Code::GET, "/changing"))
            .unwrap_or_else(|e| panic!("{e}"));
        let mut pieces = Vec::new();
        let error = loop {
            match stream.next().await {
                Ok(BodyPart::Chunk { data, .. }) => pieces.push(data[0]),
                Ok(BodyPart::End(r)) => panic!("a changed body ended as {r:?}"),
                Err(e) => break e,
            }
        };
        assert_eq!(pieces, [0, 1, 2], "blocks before the change, in order");
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
