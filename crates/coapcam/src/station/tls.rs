//! A TLS client connection over tokio for the webhook's `https://` targets, on OpenSSL
//! (which the workspace already links for CoAP's DTLS): the server's certificate checked
//! against the system's trust store (OpenSSL's default paths, or the file
//! `SSL_CERT_FILE` names) and the target's host name or address. OpenSSL works on two
//! buffers ([`Buffers`]); [`TlsStream`] moves bytes between them and the TCP connection,
//! so no blocking call and no unsafe code is needed.

use std::io::{self, Read, Write};
use std::pin::Pin;
use std::task::{Context, Poll, ready};

use openssl::ssl::{ErrorCode, SslConnector, SslMethod, SslStream};
use tokio::io::{AsyncRead, AsyncWrite, AsyncWriteExt as _, ReadBuf};
use tokio::net::TcpStream;

/// OpenSSL's verification result for a certificate of other host names
/// (`X509_V_ERR_HOSTNAME_MISMATCH`).
const HOSTNAME_MISMATCH: i32 = 62;
/// OpenSSL's verification result for a certificate of other addresses
/// (`X509_V_ERR_IP_ADDRESS_MISMATCH`).
const IP_ADDRESS_MISMATCH: i32 = 64;

/// The most read from the TCP connection at a time.
const CHUNK: usize = 16 * 1024;

/// What OpenSSL reads from and writes to: the bytes received and not yet taken, and the
/// bytes to send.
#[derive(Default)]
struct Buffers {
    incoming: Vec<u8>,
    outgoing: Vec<u8>,
    /// The peer closed the TCP connection.
    closed: bool,
}

impl Read for Buffers {
    fn read(&mut self, buf: &mut [u8]) -> io::Result<usize> {
        if self.incoming.is_empty() {
            return if self.closed {
                Ok(0)
            } else {
                Err(io::ErrorKind::WouldBlock.into())
            };
        }
        let n = buf.len().min(self.incoming.len());
        buf[..n].copy_from_slice(&self.incoming[..n]);
        self.incoming.drain(..n);
        Ok(n)
    }
}

impl Write for Buffers {
    fn write(&mut self, buf: &[u8]) -> io::Result<usize> {
        self.outgoing.extend_from_slice(buf);
        Ok(buf.len())
    }

    fn flush(&mut self) -> io::Result<()> {
        Ok(())
    }
}

/// A TLS connection to a server, as tokio reads and writes.
pub(super) struct TlsStream {
    tcp: TcpStream,
    tls: SslStream<Buffers>,
}

/// The TLS client side of an output, made once and used for each of its connections:
/// OpenSSL's context with the system's trust store (read as it is made).
pub(super) fn connector() -> Result<SslConnector, String> {
    Ok(SslConnector::builder(SslMethod::tls_client())
        .map_err(|e| format!("TLS: {e}"))?
        .build())
}

/// The TLS client connection to `host` over `tcp` made with `connector`, once its
/// handshake is done and the server's certificate checked for `host`.
pub(super) async fn connect(
    connector: &SslConnector,
    tcp: TcpStream,
    host: &str,
) -> Result<TlsStream, String> {
    let ssl = connector
        .configure()
        .and_then(|c| c.into_ssl(host))
        .map_err(|e| format!("TLS for {host}: {e}"))?;
    let tls = SslStream::new(ssl, Buffers::default()).map_err(|e| format!("TLS: {e}"))?;
    let mut stream = TlsStream { tcp, tls };
    loop {
        let step = stream.tls.connect();
        stream.send_all().await?;
        match step {
            Ok(()) => return Ok(stream),
            Err(e) if e.code() == ErrorCode::WANT_READ => {
                if !stream.receive().await? {
                    return Err("TLS handshake: the server closed the connection".into());
                }
            }
            Err(e) => {
                let verify = stream.tls.ssl().verify_result();
                return Err(match verify.as_raw() {
                    0 => format!("TLS handshake: {e}"),
                    HOSTNAME_MISMATCH | IP_ADDRESS_MISMATCH => format!(
                        "TLS handshake: the server's certificate is not for {host} ({verify}: it names other hosts)"
                    ),
                    _ => format!("TLS handshake: the server's certificate: {verify}"),
                });
            }
        }
    }
}

impl TlsStream {
    /// Sends what OpenSSL wrote.
    async fn send_all(&mut self) -> Result<(), String> {
        let out = std::mem::take(&mut self.tls.get_mut().outgoing);
        self.tcp
            .write_all(&out)
            .await
            .map_err(|e| format!("TLS: sending: {e}"))
    }

    /// Receives more for OpenSSL; false when the server closed the connection.
    async fn receive(&mut self) -> Result<bool, String> {
        use tokio::io::AsyncReadExt as _;
        let mut chunk = vec![0; CHUNK];
        let n = self
            .tcp
            .read(&mut chunk)
            .await
            .map_err(|e| format!("TLS: receiving: {e}"))?;
        let buffers = self.tls.get_mut();
        buffers.incoming.extend_from_slice(&chunk[..n]);
        buffers.closed = n == 0;
        Ok(n > 0)
    }

    /// Sends what OpenSSL wrote, as far as the connection takes it now.
    fn poll_send(&mut self, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        let Self { tcp, tls } = self;
        let out = &mut tls.get_mut().outgoing;
        while !out.is_empty() {
            let n = ready!(Pin::new(&mut *tcp).poll_write(cx, out))?;
            if n == 0 {
                return Poll::Ready(Err(io::ErrorKind::WriteZero.into()));
            }
            out.drain(..n);
        }
        Poll::Ready(Ok(()))
    }

    /// Receives more for OpenSSL, as far as there is some now.
    fn poll_receive(&mut self, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        let mut chunk = [0; CHUNK];
        let mut buf = ReadBuf::new(&mut chunk);
        ready!(Pin::new(&mut self.tcp).poll_read(cx, &mut buf))?;
        let buffers = self.tls.get_mut();
        buffers.incoming.extend_from_slice(buf.filled());
        buffers.closed = buf.filled().is_empty();
        Poll::Ready(Ok(()))
    }
}

/// An OpenSSL error as an I/O error.
fn io_error(e: openssl::ssl::Error) -> io::Error {
    e.into_io_error()
        .unwrap_or_else(|e| io::Error::other(e.to_string()))
}

impl AsyncRead for TlsStream {
    fn poll_read(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<io::Result<()>> {
        let this = self.get_mut();
        loop {
            // Whatever OpenSSL wrote before (an alert, a key update) goes out first: once
            // `ssl_read` has taken bytes, they must reach `buf` whatever the sending does.
            ready!(this.poll_send(cx))?;
            match this.tls.ssl_read(buf.initialize_unfilled()) {
                Ok(n) => {
                    buf.advance(n);
                    return Poll::Ready(Ok(()));
                }
                Err(e) if e.code() == ErrorCode::ZERO_RETURN => return Poll::Ready(Ok(())),
                Err(e) if e.code() == ErrorCode::WANT_READ => {
                    ready!(this.poll_send(cx))?;
                    if this.tls.get_ref().closed {
                        return Poll::Ready(Ok(()));
                    }
                    ready!(this.poll_receive(cx))?;
                }
                Err(e) => return Poll::Ready(Err(io_error(e))),
            }
        }
    }
}

impl AsyncWrite for TlsStream {
    fn poll_write(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &[u8],
    ) -> Poll<io::Result<usize>> {
        let this = self.get_mut();
        // At most one write's bytes wait in memory.
        ready!(this.poll_send(cx))?;
        let n = this.tls.ssl_write(buf).map_err(io_error)?;
        // Sent as far as it goes now; the rest on the next write or flush.
        let _ = this.poll_send(cx)?;
        Poll::Ready(Ok(n))
    }

    fn poll_flush(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        let this = self.get_mut();
        ready!(this.poll_send(cx))?;
        Pin::new(&mut this.tcp).poll_flush(cx)
    }

    fn poll_shutdown(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        let this = self.get_mut();
        // The close_notify alert is written into the buffer: it cannot fail for want of
        // room, and an error here leaves only the TCP close.
        let _ = this.tls.shutdown();
        ready!(this.poll_send(cx))?;
        Pin::new(&mut this.tcp).poll_shutdown(cx)
    }
}
