//! `quic-bench`: one file over QUIC (quinn with BBR), the modern-transport reference that
//! `coapcam bench transfer` times beside coapcam's CoAP transfers through the same
//! emulated link.
//!
//! ```text
//! quic-bench serve ADDR FILE CERT_OUT    serve FILE to every connection; write the
//!                                        self-signed certificate (DER) to CERT_OUT
//! quic-bench get ADDR CERT OUT           fetch it over one stream into OUT
//! ```
//!
//! The client opens one bidirectional stream, sends nothing but its end, and reads the
//! body to the stream's end; a run is the whole process, handshake included, as a
//! user of `coapcam get` waits for it.

use std::net::SocketAddr;
use std::path::Path;
use std::sync::Arc;

use anyhow::{Context as _, bail};
use quinn::congestion::BbrConfig;
use quinn::rustls::pki_types::{CertificateDer, PrivatePkcs8KeyDer};

/// The largest body a client takes.
const MAX_BODY: usize = 256 << 20;

fn transport() -> Arc<quinn::TransportConfig> {
    let mut t = quinn::TransportConfig::default();
    t.congestion_controller_factory(Arc::new(BbrConfig::default()));
    Arc::new(t)
}

async fn serve(addr: SocketAddr, file: &Path, cert_out: &Path) -> anyhow::Result<()> {
    let body: Arc<[u8]> = std::fs::read(file)
        .with_context(|| format!("reading {}", file.display()))?
        .into();
    let cert = rcgen::generate_simple_self_signed(vec!["localhost".into()])?;
    let der = CertificateDer::from(cert.cert);
    std::fs::write(cert_out, &der).with_context(|| format!("writing {}", cert_out.display()))?;
    let key = PrivatePkcs8KeyDer::from(cert.key_pair.serialize_der());
    let mut config = quinn::ServerConfig::with_single_cert(vec![der], key.into())?;
    config.transport_config(transport());
    let endpoint = quinn::Endpoint::server(config, addr)?;
    println!("ready {}", endpoint.local_addr()?);
    while let Some(incoming) = endpoint.accept().await {
        let body = body.clone();
        tokio::spawn(async move {
            let sent = async {
                let conn = incoming.await?;
                let (mut send, _recv) = conn.accept_bi().await?;
                send.write_all(&body).await?;
                send.finish()?;
                // Wait for the client to close once it has read everything.
                conn.closed().await;
                anyhow::Ok(())
            };
            if let Err(e) = sent.await {
                eprintln!("quic-bench serve: {e:#}");
            }
        });
    }
    Ok(())
}

async fn get(addr: SocketAddr, cert: &Path, out: &Path) -> anyhow::Result<()> {
    let der = std::fs::read(cert).with_context(|| format!("reading {}", cert.display()))?;
    let mut roots = quinn::rustls::RootCertStore::empty();
    roots.add(CertificateDer::from(der))?;
    let mut config = quinn::ClientConfig::with_root_certificates(Arc::new(roots))?;
    config.transport_config(transport());
    let bind: SocketAddr = if addr.is_ipv4() {
        "0.0.0.0:0".parse()?
    } else {
        "[::]:0".parse()?
    };
    let mut endpoint = quinn::Endpoint::client(bind)?;
    // The close frame is queued; the process ends without waiting for the peer's.
    endpoint.set_default_client_config(config);
    let conn = endpoint.connect(addr, "localhost")?.await?;
    let (mut send, mut recv) = conn.open_bi().await?;
    send.finish()?;
    let body = recv.read_to_end(MAX_BODY).await?;
    conn.close(0u32.into(), b"done");
    std::fs::write(out, &body).with_context(|| format!("writing {}", out.display()))
}

#[tokio::main(flavor = "current_thread")]
async fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    match args
        .iter()
        .map(String::as_str)
        .collect::<Vec<_>>()
        .as_slice()
    {
        ["serve", addr, file, cert] => serve(addr.parse()?, Path::new(file), Path::new(cert)).await,
        ["get", addr, cert, out] => get(addr.parse()?, Path::new(cert), Path::new(out)).await,
        _ => bail!("usage: quic-bench serve ADDR FILE CERT_OUT | quic-bench get ADDR CERT OUT"),
    }
}
