//! What carries a stream connection's frames (RFC 8323): a TCP stream (`coap+tcp`), whose
//! bytes the [`Connection`] cuts into frames itself, or a WebSocket over one (`coap+ws`,
//! §4), each of whose binary messages is one frame; either of them over TLS on the TCP
//! stream (`coaps+tcp`, `coaps+ws`; the handshake is `tls.rs`'s). The WebSocket
//! handshakes and framing are tokio-tungstenite's; what is CoAP's here is the endpoint's
//! path, `/.well-known/coap`, and the subprotocol `coap` (§4.1), which both ends ask for.

use std::io;
use std::net::SocketAddr;
use std::pin::Pin;
use std::task::{Context, Poll};

use bytes::Bytes;
use coap::connection::Connection;
use futures_util::{SinkExt, StreamExt};
use tokio::io::{AsyncRead, AsyncReadExt, AsyncWrite, AsyncWriteExt, ReadBuf};
use tokio::net::TcpStream;
use tokio_openssl::SslStream;
use tokio_tungstenite::WebSocketStream;
use tokio_tungstenite::tungstenite::handshake::client::Request as ClientRequest;
use tokio_tungstenite::tungstenite::handshake::server::{ErrorResponse, Request, Response};
use tokio_tungstenite::tungstenite::http::{HeaderValue, StatusCode, header};
use tokio_tungstenite::tungstenite::protocol::WebSocketConfig;
use tokio_tungstenite::tungstenite::{Message, client::IntoClientRequest};

/// The path of a server's CoAP WebSocket endpoint (RFC 8323 §4.1, §8.2).
pub const WS_PATH: &str = "/.well-known/coap";

/// The WebSocket subprotocol of CoAP (RFC 8323 §4.1).
const SUBPROTOCOL: &str = "coap";

/// The bytes under a connection: a TCP stream, or TLS on one.
#[derive(Debug)]
pub(crate) enum Stream {
    /// TCP as it is (`coap+tcp`, `coap+ws`).
    Plain(TcpStream),
    /// TLS on TCP (`coaps+tcp`, `coaps+ws`), its handshake done (boxed: OpenSSL's
    /// stream carries its buffers).
    Tls(Box<SslStream<TcpStream>>),
}

impl Stream {
    /// Whether this is TLS.
    pub(crate) fn is_tls(&self) -> bool {
        matches!(self, Self::Tls(_))
    }
}

impl AsyncRead for Stream {
    fn poll_read(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<io::Result<()>> {
        match self.get_mut() {
            Self::Plain(s) => Pin::new(s).poll_read(cx, buf),
            Self::Tls(s) => Pin::new(&mut **s).poll_read(cx, buf),
        }
    }
}

impl AsyncWrite for Stream {
    fn poll_write(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &[u8],
    ) -> Poll<io::Result<usize>> {
        match self.get_mut() {
            Self::Plain(s) => Pin::new(s).poll_write(cx, buf),
            Self::Tls(s) => Pin::new(&mut **s).poll_write(cx, buf),
        }
    }

    fn poll_flush(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        match self.get_mut() {
            Self::Plain(s) => Pin::new(s).poll_flush(cx),
            Self::Tls(s) => Pin::new(&mut **s).poll_flush(cx),
        }
    }

    fn poll_shutdown(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        match self.get_mut() {
            Self::Plain(s) => Pin::new(s).poll_shutdown(cx),
            Self::Tls(s) => Pin::new(&mut **s).poll_shutdown(cx),
        }
    }
}

/// One connection's carrier.
#[derive(Debug)]
pub(crate) enum Link {
    /// A stream and its read buffer.
    Tcp(Stream, Vec<u8>),
    /// A WebSocket (boxed: its state is large) and the last message received.
    Ws(Box<WebSocketStream<Stream>>, Bytes),
}

impl Link {
    /// A stream as it is.
    pub(crate) fn tcp(stream: Stream) -> Self {
        Self::Tcp(stream, vec![0; 64 * 1024])
    }

    /// The URI scheme of what this carries.
    pub(crate) fn scheme(&self) -> &'static str {
        match self {
            Self::Tcp(s, _) if s.is_tls() => "coaps+tcp",
            Self::Tcp(..) => "coap+tcp",
            Self::Ws(ws, _) if ws.get_ref().is_tls() => "coaps+ws",
            Self::Ws(..) => "coap+ws",
        }
    }

    /// The connection for this carrier, accepting messages of up to `max_message_size`.
    pub(crate) fn connection(&self, max_message_size: u32) -> Connection {
        match self {
            Self::Tcp(..) => Connection::new(max_message_size),
            Self::Ws(..) => Connection::websocket(max_message_size),
        }
    }

    /// What came next: bytes of the stream, or one WebSocket message; `None` once the
    /// peer closed, reading failed, or a WebSocket message was text (CoAP goes in binary
    /// messages only, §4.2). WebSocket Pings are answered by the WebSocket layer.
    pub(crate) async fn recv(&mut self) -> Option<&[u8]> {
        match self {
            Self::Tcp(stream, buf) => match stream.read(buf).await {
                Ok(0) | Err(_) => None,
                Ok(n) => Some(&buf[..n]),
            },
            Self::Ws(ws, last) => loop {
                match ws.next().await? {
                    Ok(Message::Binary(bytes)) => {
                        *last = bytes;
                        return Some(&last[..]);
                    }
                    Ok(Message::Ping(_) | Message::Pong(_) | Message::Frame(_)) => {}
                    Ok(Message::Text(_) | Message::Close(_)) | Err(_) => return None,
                }
            },
        }
    }

    /// Sends what [`Connection::poll_transmit`] gave: bytes of the stream, or one
    /// WebSocket message.
    pub(crate) async fn send(&mut self, bytes: Vec<u8>) -> io::Result<()> {
        match self {
            Self::Tcp(stream, _) => stream.write_all(&bytes).await,
            Self::Ws(ws, _) => ws
                .send(Message::Binary(bytes.into()))
                .await
                .map_err(io::Error::other),
        }
    }

    /// Closes this side: the TCP stream's write half, or the WebSocket with a Close.
    pub(crate) async fn close(&mut self) {
        match self {
            Self::Tcp(stream, _) => drop(stream.shutdown().await),
            Self::Ws(ws, _) => drop(WebSocketStream::close(ws, None).await),
        }
    }
}

/// The WebSocket limits for messages of up to `max_message_size` bytes: the WebSocket
/// layer refuses a longer message or frame before it has buffered it.
fn ws_config(max_message_size: u32) -> WebSocketConfig {
    let max = Some(max_message_size as usize);
    WebSocketConfig::default()
        .max_message_size(max)
        .max_frame_size(max)
}

/// The server's side of the WebSocket handshake on `stream`: a GET of [`WS_PATH`]
/// asking for the subprotocol `coap` is accepted with it; another path is answered 404,
/// a request without the subprotocol 400, each with a sentence saying why.
#[expect(
    clippy::result_large_err,
    reason = "tungstenite's handshake callback returns its HTTP response as the error"
)]
pub(crate) async fn accept_ws(stream: Stream, max_message_size: u32) -> io::Result<Link> {
    let check = |request: &Request, mut response: Response| {
        if request.uri().path() != WS_PATH {
            let why = format!("CoAP over WebSockets is served at {WS_PATH}");
            return Err(refusal(StatusCode::NOT_FOUND, why));
        }
        let asked = request
            .headers()
            .get_all(header::SEC_WEBSOCKET_PROTOCOL)
            .iter()
            .filter_map(|v| v.to_str().ok())
            .flat_map(|v| v.split(','))
            .any(|p| p.trim() == SUBPROTOCOL);
        if !asked {
            let why = format!("the WebSocket subprotocol {SUBPROTOCOL:?} is required");
            return Err(refusal(StatusCode::BAD_REQUEST, why));
        }
        let protocol = HeaderValue::from_static(SUBPROTOCOL);
        response
            .headers_mut()
            .insert(header::SEC_WEBSOCKET_PROTOCOL, protocol);
        Ok(response)
    };
    let config = Some(ws_config(max_message_size));
    let ws = tokio_tungstenite::accept_hdr_async_with_config(stream, check, config)
        .await
        .map_err(io::Error::other)?;
    Ok(Link::Ws(Box::new(ws), Bytes::new()))
}

/// Answers a WebSocket handshake on `stream` with `status` and `why`, refusing it.
#[expect(
    clippy::result_large_err,
    reason = "tungstenite's handshake callback returns its HTTP response as the error"
)]
pub(crate) async fn refuse_ws(stream: Stream, status: StatusCode, why: String) {
    let refuse = |_: &Request, _: Response| Err(refusal(status, why));
    let _ = tokio_tungstenite::accept_hdr_async(stream, refuse).await;
}

/// An HTTP answer of `status` with `why` as its body.
fn refusal(status: StatusCode, why: String) -> ErrorResponse {
    let mut response = ErrorResponse::new(Some(why));
    *response.status_mut() = status;
    response
}

/// The client's side of the WebSocket handshake with `peer` on `stream`: a GET of
/// [`WS_PATH`] asking for the subprotocol `coap`, which the server must choose.
pub(crate) async fn connect_ws(
    stream: Stream,
    peer: SocketAddr,
    max_message_size: u32,
) -> io::Result<Link> {
    let scheme = if stream.is_tls() { "wss" } else { "ws" };
    let mut request: ClientRequest = format!("{scheme}://{peer}{WS_PATH}")
        .into_client_request()
        .map_err(io::Error::other)?;
    let protocol = HeaderValue::from_static(SUBPROTOCOL);
    request
        .headers_mut()
        .insert(header::SEC_WEBSOCKET_PROTOCOL, protocol);
    let config = Some(ws_config(max_message_size));
    let (ws, _) = tokio_tungstenite::client_async_with_config(request, stream, config)
        .await
        .map_err(|e| io::Error::other(format!("WebSocket handshake: {e}")))?;
    Ok(Link::Ws(Box::new(ws), Bytes::new()))
}
