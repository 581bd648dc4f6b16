//! `coap+tcp://` serving (RFC 8323): a listener whose every connection is a
//! [`coap::connection::Connection`], its requests handed to the same [`Router`] the UDP
//! [`Server`](crate::Server) uses. Nothing here decides protocol behaviour: the connection
//! answers signalling and frames the answers; this moves bytes and runs handlers.
//!
//! One task per connection owns its `Connection`; handlers run as spawned tasks, as the
//! UDP server's do, at most [`MAX_IN_FLIGHT`] per connection, and send their answers
//! back to it. What the connection does not do
//! yet (Observe, block-wise transfer, requests of its own, Pings, timeouts) this server
//! does not either.

use std::net::SocketAddr;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Duration;

use coap::connection::{Connection, ConnectionEvent};
use coap::{IncomingId, IncomingRequest, Response, Token};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::{mpsc, watch};

use crate::router::Router;

/// The Max-Message-Size a [`TcpServer`] announces unless told otherwise: a request of up
/// to 1 MiB, whole (there is no block-wise transfer over TCP yet).
pub const DEFAULT_MAX_MESSAGE_SIZE: u32 = 1 << 20;

/// How many of a connection's requests its handlers may work on at once. At the limit the
/// connection reads no more until one is answered, so a peer that sends faster than the
/// handlers answer is held back by TCP's flow control, not queued here.
pub const MAX_IN_FLIGHT: usize = 32;

/// How long the listener waits after a failed accept (out of file descriptors, say)
/// before it tries again.
const ACCEPT_RETRY: Duration = Duration::from_millis(100);

/// A running `coap+tcp` server; dropped, it stops listening and closes its connections.
#[derive(Debug)]
pub struct TcpServer {
    local_addr: SocketAddr,
    /// Dropped with the server: the listener and every connection see it and end.
    _stop: watch::Sender<()>,
}

impl TcpServer {
    /// Listens on `addr` and serves `router` on every connection, accepting messages of
    /// up to `max_message_size` bytes.
    pub async fn bind(
        addr: SocketAddr,
        router: Arc<Router>,
        max_message_size: u32,
    ) -> std::io::Result<Self> {
        let listener = TcpListener::bind(addr)
            .await
            .map_err(|e| std::io::Error::new(e.kind(), format!("{addr}: {e}")))?;
        let local_addr = listener.local_addr()?;
        let (stop, stopped) = watch::channel(());
        tokio::spawn(listen(listener, router, max_message_size, stopped));
        Ok(Self {
            local_addr,
            _stop: stop,
        })
    }

    /// The bound address.
    pub fn local_addr(&self) -> SocketAddr {
        self.local_addr
    }
}

async fn listen(
    listener: TcpListener,
    router: Arc<Router>,
    max_message_size: u32,
    mut stopped: watch::Receiver<()>,
) {
    let ids = Arc::new(AtomicU64::new(0));
    loop {
        tokio::select! {
            accepted = listener.accept() => match accepted {
                Ok((stream, peer)) => {
                    let conn = Connection::new(max_message_size);
                    let served = serve(stream, peer, conn, router.clone(), ids.clone(), stopped.clone());
                    tokio::spawn(served);
                }
                Err(e) => {
                    tracing::warn!(error = %e, "coap+tcp accept failed");
                    tokio::time::sleep(ACCEPT_RETRY).await;
                }
            },
            _ = stopped.changed() => return,
        }
    }
}

/// Moves one connection's bytes between its stream and its `Connection`, and its
/// requests to the router, until either side ends it.
async fn serve(
    stream: TcpStream,
    peer: SocketAddr,
    mut conn: Connection,
    router: Arc<Router>,
    ids: Arc<AtomicU64>,
    mut stopped: watch::Receiver<()>,
) {
    let _ = stream.set_nodelay(true);
    let (mut read, mut write) = stream.into_split();
    let (answer, mut answers) = mpsc::unbounded_channel::<(Token, Response)>();
    let mut buf = vec![0u8; 64 * 1024];
    let mut in_flight = 0;
    loop {
        let mut closing = false;
        while in_flight < MAX_IN_FLIGHT
            && let Some(event) = conn.poll_event()
        {
            match event {
                ConnectionEvent::Request(request) => {
                    let request = *request;
                    in_flight += 1;
                    let id = IncomingId(ids.fetch_add(1, Ordering::Relaxed));
                    let incoming = IncomingRequest {
                        id,
                        peer,
                        method: request.method,
                        options: request.options,
                        payload: request.payload,
                        multicast: false,
                        // Reliable, as a CON is.
                        confirmable: true,
                        observe: None,
                        identity: None,
                        // Not known over TCP yet: the safe answer.
                        loopback: false,
                    };
                    let (router, answer, token) = (router.clone(), answer.clone(), request.token);
                    tokio::spawn(async move {
                        let (method, path) = (incoming.method, incoming.options.path_string());
                        let response = router.dispatch(incoming).await;
                        tracing::debug!(%peer, %method, ?path, code = %response.code, "coap+tcp request");
                        let _ = answer.send((token, response));
                    });
                }
                ConnectionEvent::Closed(why) => {
                    tracing::debug!(%peer, ?why, "coap+tcp connection closed");
                    closing = true;
                }
                // The server sends no requests or Pings of its own.
                ConnectionEvent::Response(..)
                | ConnectionEvent::Failed(..)
                | ConnectionEvent::Pong(_) => {}
            }
        }
        if let Some(bytes) = conn.poll_transmit()
            && write.write_all(&bytes).await.is_err()
        {
            return;
        }
        if closing {
            let _ = write.shutdown().await;
            return;
        }
        tokio::select! {
            n = read.read(&mut buf), if in_flight < MAX_IN_FLIGHT => match n {
                Ok(0) | Err(_) => return,
                Ok(n) => conn.handle(&buf[..n]),
            },
            Some((token, response)) = answers.recv() => {
                in_flight -= 1;
                conn.respond(token, &response);
            }
            _ = stopped.changed() => return,
        }
    }
}
