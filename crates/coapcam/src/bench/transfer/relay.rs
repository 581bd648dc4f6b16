//! A `netem` relay in this process, between a benchmark's client and its server.

use std::net::{Ipv4Addr, SocketAddr};
use std::sync::mpsc;
use std::thread::{self, JoinHandle};

use anyhow::{Context as _, bail};
use netem::{Counters, DeliveredBytes, LinkConfig, Netem};

/// A `netem` relay on a thread of its own (its own tokio runtime), until dropped.
pub(super) struct Relay {
    pub(super) addr: SocketAddr,
    /// The bytes it has delivered to each client so far.
    pub(super) delivered: DeliveredBytes,
    stop: Option<tokio::sync::oneshot::Sender<()>>,
    thread: Option<JoinHandle<anyhow::Result<Counters>>>,
}

impl Relay {
    /// Binds a relay on 127.0.0.1 to `forward` through `config`.
    pub(super) fn start(forward: SocketAddr, config: LinkConfig) -> anyhow::Result<Self> {
        let (stop_tx, stop_rx) = tokio::sync::oneshot::channel::<()>();
        let (addr_tx, addr_rx) = mpsc::channel();
        let thread = thread::Builder::new()
            .name("netem".into())
            .spawn(move || -> anyhow::Result<Counters> {
                let runtime = tokio::runtime::Builder::new_current_thread()
                    .enable_all()
                    .build()
                    .context("starting the relay's tokio runtime")?;
                runtime.block_on(async move {
                    let listen = SocketAddr::from((Ipv4Addr::LOCALHOST, 0));
                    let bound = Netem::bind(listen, forward, config, None)
                        .and_then(|n| Ok((n.local_addr()?, n)));
                    let netem = match bound {
                        Ok((addr, netem)) => {
                            let _ = addr_tx.send(Ok((addr, netem.delivered())));
                            netem
                        }
                        Err(e) => {
                            let _ = addr_tx.send(Err(e.to_string()));
                            bail!("binding the relay: {e}");
                        }
                    };
                    // A dropped sender stops the relay too.
                    let stop = async move {
                        let _ = stop_rx.await;
                        Ok(())
                    };
                    Ok(netem.run(stop).await?)
                })
            })
            .context("starting the relay's thread")?;
        let mut relay = Self {
            addr: SocketAddr::from((Ipv4Addr::LOCALHOST, 0)),
            delivered: DeliveredBytes::default(),
            stop: Some(stop_tx),
            thread: Some(thread),
        };
        (relay.addr, relay.delivered) = match addr_rx.recv() {
            Ok(Ok(bound)) => bound,
            Ok(Err(e)) => bail!("binding a relay on 127.0.0.1: {e}"),
            Err(_) => bail!("the relay's thread ended before it bound"),
        };
        Ok(relay)
    }

    /// Stops it and returns its counters.
    pub(super) fn finish(mut self) -> anyhow::Result<Counters> {
        self.stop.take();
        let thread = self.thread.take().context("the relay already stopped")?;
        match thread.join() {
            Ok(counters) => counters,
            Err(_) => bail!("the relay's thread panicked"),
        }
    }
}

impl Drop for Relay {
    fn drop(&mut self) {
        self.stop.take();
        if let Some(thread) = self.thread.take() {
            let _ = thread.join();
        }
    }
}
