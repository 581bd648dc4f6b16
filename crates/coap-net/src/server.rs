//! The server: one endpoint task per bound address, a [`Router`] shared by all of them,
//! handlers run as spawned tasks, Observe registrations kept per path. Every answer goes
//! to the endpoint as soon as its handler returns; the endpoint holds a multicast
//! request's answer for its leisure (`EndpointConfig::leisure`).

use std::collections::HashMap;
use std::net::{IpAddr, SocketAddr};
use std::sync::{Arc, Mutex, PoisonError};

use coap::{EndpointConfig, IncomingRequest, ObservationId, OptionNumber};
use tokio::sync::{mpsc, oneshot};

use crate::Error;
use crate::driver::{self, Command, EndpointHandle, ServerEvent};
use crate::dtls::Psk;
use crate::observers::Sent;
use crate::router::{ObservationEnd, Router};
use crate::socket::Socket;

/// Server settings.
#[derive(Debug, Clone, Default)]
pub struct ServerConfig {
    /// The protocol endpoint's settings.
    pub endpoint: EndpointConfig,
    /// Addresses answered with DTLS (`coaps://`, RFC 7252 §9), with `psk`'s keys.
    pub secure: Vec<SocketAddr>,
    /// The keys of the DTLS addresses (a [`Psk::Server`]).
    pub psk: Option<Psk>,
}

struct Observer {
    id: ObservationId,
    endpoint: usize,
    request: IncomingRequest,
    /// What the observer was last sent: the registration's answer, then each
    /// notification.
    last: Sent,
    /// The resource's [`Resource::on_observation_end`](crate::Resource::on_observation_end),
    /// told when the observation ends.
    ended: Option<ObservationEnd>,
}

#[derive(Default)]
struct Observers {
    by_path: Mutex<HashMap<String, Vec<Observer>>>,
}

impl Observers {
    fn lock(&self) -> std::sync::MutexGuard<'_, HashMap<String, Vec<Observer>>> {
        self.by_path.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// Forgets observation `id` of `endpoint`, and tells its resource (outside the lock).
    fn remove(&self, endpoint: usize, id: ObservationId) {
        let mut gone = Vec::new();
        for list in self.lock().values_mut() {
            list.retain(|o| {
                let keep = !(o.endpoint == endpoint && o.id == id);
                if !keep && let Some(ended) = &o.ended {
                    gone.push((ended.clone(), o.request.peer));
                }
                keep
            });
        }
        for (ended, peer) in gone {
            ended(peer, id);
        }
    }

    /// Keeps a registration: a new one, or the same peer and token registering again
    /// (the endpoint gives it the same id), which replaces the one before.
    fn add(&self, path: String, observer: Observer) {
        let mut by_path = self.lock();
        let list = by_path.entry(path).or_default();
        list.retain(|o| !(o.endpoint == observer.endpoint && o.id == observer.id));
        list.push(observer);
    }

    /// Takes `next` as the observer's newest representation, unless it is the one the
    /// observer has already (or the observer is gone): then false, and nothing is to go
    /// out.
    fn advance(&self, path: &str, endpoint: usize, id: ObservationId, next: Sent) -> bool {
        let mut by_path = self.lock();
        let Some(o) = by_path
            .get_mut(path)
            .and_then(|l| l.iter_mut().find(|o| o.endpoint == endpoint && o.id == id))
        else {
            return false;
        };
        if o.last.repeats(&next) {
            return false;
        }
        o.last = next;
        true
    }
}

/// A running CoAP server.
pub struct Server {
    router: Arc<Router>,
    endpoints: Vec<EndpointHandle>,
    /// How many of `endpoints` are plain (not DTLS): they come first.
    plain: usize,
    observers: Arc<Observers>,
    /// Held through [`Server::notify`]: one round of notifications at a time, so an
    /// observer's representations go out in the order they were read.
    notifying: tokio::sync::Mutex<()>,
}

impl std::fmt::Debug for Server {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Server")
            .field("local_addrs", &self.local_addrs())
            .finish()
    }
}

impl Server {
    /// Binds every address and starts serving `router`.
    pub fn bind(
        addrs: &[SocketAddr],
        config: ServerConfig,
        router: Arc<Router>,
    ) -> std::io::Result<Self> {
        if !config.secure.is_empty() && config.psk.is_none() {
            return Err(std::io::Error::new(
                std::io::ErrorKind::InvalidInput,
                "DTLS addresses need pre-shared keys",
            ));
        }
        let observers = Arc::new(Observers::default());
        let mut endpoints = Vec::new();
        let plain = addrs.iter().map(|a| (a, None));
        let secure = config.secure.iter().map(|a| (a, config.psk.as_ref()));
        for (index, (addr, psk)) in plain.chain(secure).enumerate() {
            // The error names the address: of several, which one is busy.
            let socket = Socket::bind(*addr)
                .map_err(|e| std::io::Error::new(e.kind(), format!("{addr}: {e}")))?;
            // The policy must know what came from this machine.
            socket.read_arrivals()?;
            let (tx, rx) = mpsc::unbounded_channel();
            let mut ep_config = config.endpoint.clone();
            ep_config.rng_seed = ep_config.rng_seed.wrapping_add(index as u64);
            // A DTLS handshake proves the peer's address (and its key): no Echo check.
            ep_config.verify_addresses &= psk.is_none();
            let handle = driver::spawn(socket, ep_config, Some(tx), psk)?;
            tokio::spawn(serve(
                rx,
                handle.clone(),
                index,
                router.clone(),
                observers.clone(),
            ));
            endpoints.push(handle);
        }
        Ok(Self {
            router,
            endpoints,
            plain: addrs.len(),
            observers,
            notifying: tokio::sync::Mutex::new(()),
        })
    }

    /// A client that sends from this server's own plain socket of `peer`'s address
    /// family (the first such bound address), so `peer` sees the server's address and
    /// port as the source: a resource directory derives the server's base URI from it
    /// (RFC 9176 §5.3). `None` when no plain address of that family is bound.
    pub fn client_for(&self, peer: SocketAddr) -> Option<crate::Client> {
        self.endpoints
            .iter()
            .take(self.plain)
            .find(|h| h.local_addr().is_ipv4() == peer.is_ipv4())
            .map(|h| crate::Client::from_handle(h.clone()))
    }

    /// The bound addresses: those given to [`Server::bind`], then the DTLS ones.
    pub fn local_addrs(&self) -> Vec<SocketAddr> {
        self.endpoints
            .iter()
            .map(EndpointHandle::local_addr)
            .collect()
    }

    /// The router, to add and remove resources while serving.
    pub fn router(&self) -> &Arc<Router> {
        &self.router
    }

    /// Joins a multicast group on every socket of the group's address family
    /// (`interface`: an IPv6 interface index, 0 for the default).
    pub async fn join(&self, group: IpAddr, interface: u32) -> Result<usize, Error> {
        self.membership(group, interface, true).await
    }

    /// Leaves a multicast group.
    pub async fn leave(&self, group: IpAddr, interface: u32) -> Result<usize, Error> {
        self.membership(group, interface, false).await
    }

    async fn membership(&self, group: IpAddr, interface: u32, join: bool) -> Result<usize, Error> {
        let mut n = 0;
        for h in &self.endpoints {
            if h.local_addr().is_ipv4() != group.is_ipv4() {
                continue;
            }
            let (done, rx) = oneshot::channel();
            h.send(Command::Membership {
                group,
                interface,
                join,
                done,
            })?;
            rx.await.map_err(|_| Error::Closed)?.map_err(Error::Io)?;
            n += 1;
        }
        Ok(n)
    }

    /// Tells the observers of `path` that it changed: the GET handler runs again for each
    /// registration and the result goes out as a notification, unless it is the
    /// representation that observer was sent last (the registration's answer or the last
    /// notification: the same code, Content-Format and ETag, or the same body when there
    /// is no ETag). A change that crosses the registration, or a notification that
    /// already read the next change, thus sends nothing twice. Calls run one at a time.
    /// Returns how many were sent over UDP; the observers over streams are told through
    /// the router ([`Router::changed`]), and their connections notify them on their own.
    pub async fn notify(&self, path: &str) -> usize {
        self.router.changed(path);
        let _round = self.notifying.lock().await;
        let targets: Vec<(usize, ObservationId, IncomingRequest)> = self
            .observers
            .lock()
            .get(path)
            .map(|l| {
                l.iter()
                    .map(|o| (o.endpoint, o.id, o.request.clone()))
                    .collect()
            })
            .unwrap_or_default();
        // Every notification is handed to its endpoint before any answer is awaited: one
        // round trip to the endpoint threads for all observers, not one each.
        let mut handed = Vec::with_capacity(targets.len());
        for (endpoint, id, request) in targets {
            let response = self.router.dispatch(request).await;
            let Some(h) = self.endpoints.get(endpoint) else {
                continue;
            };
            if !self
                .observers
                .advance(path, endpoint, id, Sent::of(&response))
            {
                continue;
            }
            let (done, rx) = oneshot::channel();
            if h.send(Command::Notify { id, response, done }).is_ok() {
                handed.push((endpoint, id, rx));
            }
        }
        let mut sent = 0;
        for (endpoint, id, rx) in handed {
            if rx.await.unwrap_or(false) {
                sent += 1;
            } else {
                self.observers.remove(endpoint, id);
            }
        }
        sent
    }

    /// Paths with at least one observer.
    pub fn observed_paths(&self) -> Vec<String> {
        self.observers
            .lock()
            .iter()
            .filter(|(_, l)| !l.is_empty())
            .map(|(p, _)| p.clone())
            .collect()
    }
}

impl Drop for Server {
    fn drop(&mut self) {
        for h in &self.endpoints {
            let _ = h.send(Command::Shutdown);
        }
    }
}

async fn serve(
    mut rx: mpsc::UnboundedReceiver<ServerEvent>,
    handle: EndpointHandle,
    endpoint: usize,
    router: Arc<Router>,
    observers: Arc<Observers>,
) {
    while let Some(ev) = rx.recv().await {
        match ev {
            ServerEvent::ObservationEnded(id) => observers.remove(endpoint, id),
            ServerEvent::Request(request) => {
                let handle = handle.clone();
                let router = router.clone();
                let observers = observers.clone();
                tokio::spawn(async move {
                    let request = *request;
                    let id = request.id;
                    let registration = request.observe.map(|obs| (obs, request.clone()));
                    let (peer, method) = (request.peer, request.method);
                    let path = request.options.path_string();
                    let response = router.dispatch(request).await;
                    // The path and the diagnostic are the peer's text: escaped (`?`, Debug),
                    // so a newline or a terminal escape in them cannot forge a log line.
                    // A client error (4.xx: nothing there, not allowed, a bad request) is
                    // the answer the client asked for, said to it; only the server's own
                    // failures (5.xx) are warnings.
                    if response.code.class() == 5 {
                        let diagnostic = String::from_utf8_lossy(&response.payload);
                        tracing::warn!(%peer, %method, ?path, code = %response.code, ?diagnostic, "request failed");
                    } else if response.code.is_error() {
                        let diagnostic = String::from_utf8_lossy(&response.payload);
                        tracing::info!(%peer, %method, ?path, code = %response.code, ?diagnostic, "request refused");
                    } else {
                        tracing::debug!(%peer, %method, ?path, code = %response.code, bytes = response.payload.len(), "request");
                    }
                    if let Some((obs, request)) = registration
                        && response.options.contains(OptionNumber::OBSERVE)
                    {
                        let path = request.options.path_string();
                        let ended = router
                            .find(
                                &request
                                    .options
                                    .uri_path()
                                    .map(|s| s.into_owned())
                                    .collect::<Vec<_>>(),
                            )
                            .and_then(|(resource, _)| resource.observation_end().cloned());
                        observers.add(
                            path,
                            Observer {
                                id: obs,
                                endpoint,
                                request,
                                last: Sent::of(&response),
                                ended,
                            },
                        );
                    }
                    let _ = handle.send(Command::Respond { id, response });
                });
            }
        }
    }
}
