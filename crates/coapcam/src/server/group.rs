//! `/coap-group` (RFC 7390 §2.6.2): the server's multicast group memberships as
//! `application/coap-group+json` (content format 256), listed, created, read, replaced and
//! deleted by clients; `serve --group ADDR` memberships are listed from the start.
//!
//! The handlers are registered before the server's sockets exist, so they ask the server
//! task to join and leave through a channel ([`MembershipChange`], applied by
//! [`apply`]). A group must use a port the server listens on with a socket of the group's
//! address family: a membership on another port would need a socket the server does not
//! have, so it is refused with 4.00. Several memberships may name one address; the
//! sockets join it with the first and leave it with the last.

use std::collections::BTreeMap;
use std::net::{IpAddr, SocketAddr};
use std::sync::{Arc, OnceLock};

use coap::group::{GroupAddr, GroupConfig, encode_list};
use coap::{Code, ContentFormat, IncomingRequest, OptionNumber, Response};
use coap_net::{Ctx, Resource, Router, Server, handler};
use tokio::sync::{Mutex, mpsc, oneshot};

use super::error::StartError;

/// Most memberships held at once (Linux allows 20 IPv4 groups per socket by default).
pub(crate) const MAX_MEMBERSHIPS: usize = 16;

/// A join or leave for the server task, answered on `done`.
#[derive(Debug)]
pub(crate) struct MembershipChange {
    /// The multicast address.
    group: IpAddr,
    /// Join (`true`) or leave.
    join: bool,
    /// The outcome, as text for a diagnostic.
    done: oneshot::Sender<Result<(), String>>,
}

/// Applies a membership change to `server`'s sockets (`interface`: the IPv6 interface
/// index, 0 for the default) and reports the outcome to the handler that asked.
pub(crate) async fn apply(server: &Server, change: MembershipChange, interface: u32) {
    let result = if change.join {
        server.join(change.group, interface).await
    } else {
        server.leave(change.group, interface).await
    };
    let outcome = match result {
        Ok(0) => Err(format!("the server has no socket for {}", change.group)),
        Ok(_) => Ok(()),
        Err(e) => Err(e.to_string()),
    };
    // The handler may have given up (its request timed out): nothing to tell then.
    let _ = change.done.send(outcome);
}

/// The memberships, by resource name (the last Location-Path segment).
#[derive(Debug, Default)]
struct Memberships {
    by_index: BTreeMap<String, GroupConfig>,
    next_index: u64,
}

impl Memberships {
    fn uses(&self, ip: IpAddr) -> usize {
        self.by_index.values().filter(|c| c.addr.ip() == ip).count()
    }

    fn insert(&mut self, config: GroupConfig) -> String {
        self.next_index += 1;
        let index = self.next_index.to_string();
        self.by_index.insert(index.clone(), config);
        index
    }
}

/// The `/coap-group` resources.
pub(crate) struct Groups {
    /// Held across a join or leave, so changes apply one at a time.
    memberships: Mutex<Memberships>,
    changes: mpsc::UnboundedSender<MembershipChange>,
    /// The server's bound addresses, known once it has bound them.
    local: OnceLock<Vec<SocketAddr>>,
}

impl Groups {
    /// Registers `/coap-group` and `/coap-group/{index}` on `router`; joins and leaves go
    /// to `changes`, to be applied by the server task with [`apply`].
    pub(crate) fn register(
        router: &Router,
        changes: mpsc::UnboundedSender<MembershipChange>,
    ) -> Arc<Self> {
        let me = Arc::new(Self {
            memberships: Mutex::default(),
            changes,
            local: OnceLock::new(),
        });
        let (get, post) = (me.clone(), me.clone());
        router.add(
            "/coap-group",
            Resource::new()
                .get(handler(move |_ctx| {
                    let me = get.clone();
                    async move { me.list().await }
                }))
                .post(handler(move |ctx| {
                    let me = post.clone();
                    async move { me.create(&ctx.request).await }
                }))
                .attr("rt", "core.gp")
                .attr("ct", ContentFormat::COAP_GROUP_JSON.0.to_string())
                .configuring(&[Code::POST]),
        );
        let (get, put, delete) = (me.clone(), me.clone(), me.clone());
        router.add(
            "/coap-group/{index}",
            Resource::new()
                .get(handler(move |ctx| {
                    let me = get.clone();
                    async move { me.read(index_of(&ctx)).await }
                }))
                .put(handler(move |ctx| {
                    let me = put.clone();
                    async move { me.replace(index_of(&ctx), &ctx.request).await }
                }))
                .delete(handler(move |ctx| {
                    let me = delete.clone();
                    async move { me.delete(index_of(&ctx)).await }
                }))
                .configuring(&[Code::PUT, Code::DELETE]),
        );
        me
    }

    /// Records the server's bound addresses and joins the `--group` addresses on the
    /// server's port, listing each as a membership.
    pub(crate) async fn start(
        &self,
        server: &Server,
        groups: &[IpAddr],
        interface: u32,
    ) -> Result<(), StartError> {
        let local = server.local_addrs();
        let mut memberships = self.memberships.lock().await;
        for ip in groups {
            let port = local
                .iter()
                .find(|a| a.is_ipv4() == ip.is_ipv4())
                .map(SocketAddr::port)
                .ok_or(StartError::NoGroupFamily { ip: *ip })?;
            let addr = GroupAddr::new(*ip, port)
                .map_err(|source| StartError::Group { ip: *ip, source })?;
            if memberships.uses(*ip) == 0 {
                let joined = server.join(*ip, interface).await;
                joined.map_err(|source| StartError::Join { ip: *ip, source })?;
            }
            memberships.insert(GroupConfig { name: None, addr });
        }
        // Set once, here; a second call would find it set and keep the first list.
        let _ = self.local.set(local);
        Ok(())
    }

    /// The groups joined now, each once, as the address and port a request to it goes to.
    pub(crate) async fn addrs(&self) -> Vec<SocketAddr> {
        let mut addrs: Vec<SocketAddr> = (self.memberships.lock().await.by_index.values())
            .map(|c| c.addr.socket_addr())
            .collect();
        addrs.sort_unstable();
        addrs.dedup();
        addrs
    }

    async fn list(&self) -> Response {
        let body = encode_list(&self.memberships.lock().await.by_index);
        json(Code::CONTENT, body)
    }

    async fn read(&self, index: String) -> Response {
        match self.memberships.lock().await.by_index.get(&index) {
            Some(config) => json(Code::CONTENT, config.to_json()),
            None => Response::diagnostic(Code::NOT_FOUND, "no such group membership"),
        }
    }

    /// A membership from a request body, or the 4.xx that refuses it.
    #[expect(
        clippy::result_large_err,
        reason = "a refusal is the Response sent; it keeps its options inline"
    )]
    fn parse(&self, request: &IncomingRequest) -> Result<GroupConfig, Response> {
        if let Some(cf) = request.options.content_format()
            && cf != ContentFormat::COAP_GROUP_JSON
            && cf != ContentFormat::JSON
        {
            return Err(Response::diagnostic(
                Code::UNSUPPORTED_CONTENT_FORMAT,
                "a group membership is application/coap-group+json (256)",
            ));
        }
        let config = GroupConfig::from_json(&request.payload)
            .map_err(|e| Response::diagnostic(Code::BAD_REQUEST, &e.to_string()))?;
        let port = config.addr.port();
        let family: Vec<u16> = self
            .local
            .get()
            .map(|l| {
                l.iter()
                    .filter(|a| a.is_ipv4() == config.addr.ip().is_ipv4())
                    .map(SocketAddr::port)
                    .collect()
            })
            .unwrap_or_default();
        if !family.contains(&port) {
            let listening = if family.is_empty() {
                "no port of that address family".to_string()
            } else {
                let ports: Vec<String> = family.iter().map(u16::to_string).collect();
                format!("port {}", ports.join(", "))
            };
            return Err(Response::diagnostic(
                Code::BAD_REQUEST,
                &format!(
                    "field \"a\": the server listens on {listening}, not on {port}; give the group one of those ports"
                ),
            ));
        }
        Ok(config)
    }

    /// Asks the server task to join or leave `group`.
    async fn change(&self, group: IpAddr, join: bool) -> Result<(), String> {
        let (done, outcome) = oneshot::channel();
        self.changes
            .send(MembershipChange { group, join, done })
            .map_err(|_| "the server is shutting down".to_string())?;
        outcome
            .await
            .map_err(|_| "the server is shutting down".to_string())?
    }

    async fn create(&self, request: &IncomingRequest) -> Response {
        let config = match self.parse(request) {
            Ok(c) => c,
            Err(refused) => return refused,
        };
        let mut memberships = self.memberships.lock().await;
        if memberships.by_index.len() >= MAX_MEMBERSHIPS {
            return Response::diagnostic(
                Code::BAD_REQUEST,
                &format!("the server holds at most {MAX_MEMBERSHIPS} memberships; DELETE one"),
            );
        }
        let ip = config.addr.ip();
        if memberships.uses(ip) == 0
            && let Err(e) = self.change(ip, true).await
        {
            return Response::diagnostic(
                Code::INTERNAL_SERVER_ERROR,
                &format!("joining {ip}: {e}"),
            );
        }
        let index = memberships.insert(config);
        let mut r = Response::new(Code::CREATED);
        for seg in ["coap-group", index.as_str()] {
            r.options.push(OptionNumber::LOCATION_PATH, seg.as_bytes());
        }
        r
    }

    /// PUT: the new group is joined before the old one is left, so a failed join
    /// changes nothing.
    async fn replace(&self, index: String, request: &IncomingRequest) -> Response {
        let config = match self.parse(request) {
            Ok(c) => c,
            Err(refused) => return refused,
        };
        let mut memberships = self.memberships.lock().await;
        let Some(old) = memberships.by_index.get(&index).cloned() else {
            return Response::diagnostic(Code::NOT_FOUND, "no such group membership");
        };
        let (new_ip, old_ip) = (config.addr.ip(), old.addr.ip());
        if new_ip != old_ip {
            if memberships.uses(new_ip) == 0
                && let Err(e) = self.change(new_ip, true).await
            {
                return Response::diagnostic(
                    Code::INTERNAL_SERVER_ERROR,
                    &format!("joining {new_ip}: {e}"),
                );
            }
            if memberships.uses(old_ip) == 1 {
                self.leave_logged(old_ip).await;
            }
        }
        memberships.by_index.insert(index, config);
        Response::new(Code::CHANGED)
    }

    async fn delete(&self, index: String) -> Response {
        let mut memberships = self.memberships.lock().await;
        let Some(old) = memberships.by_index.remove(&index) else {
            return Response::diagnostic(Code::NOT_FOUND, "no such group membership");
        };
        if memberships.uses(old.addr.ip()) == 0 {
            self.leave_logged(old.addr.ip()).await;
        }
        Response::new(Code::DELETED)
    }

    /// Leaves a group; a failure is logged (the membership is gone either way).
    async fn leave_logged(&self, ip: IpAddr) {
        if let Err(e) = self.change(ip, false).await {
            tracing::warn!(group = %ip, "leaving: {e}");
        }
    }
}

fn index_of(ctx: &Ctx) -> String {
    ctx.param("index").unwrap_or_default().to_string()
}

fn json(code: Code, body: String) -> Response {
    let mut r = Response::new(code).with_payload(body);
    r.options.set_uint(
        OptionNumber::CONTENT_FORMAT,
        u32::from(ContentFormat::COAP_GROUP_JSON.0),
    );
    r
}
