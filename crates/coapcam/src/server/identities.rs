//! Who may do what: the DTLS pre-shared keys of `serve --psk-file`, each with a role.
//!
//! The file has one identity per line, `IDENTITY KEY ROLE`, separated by blanks; `#`
//! starts a comment. The role is `read` (GET, grabs, discovery, Observe) or `configure`
//! (also what changes the server: PUT and DELETE, POST to `/coap-group`, `/files` and the
//! creation resources). Identities and keys are text, as libcoap's tools take them.

use std::collections::HashMap;
use std::path::Path;
use std::sync::Arc;

use anyhow::{Context as _, bail};
use coap::{Code, IncomingRequest, Response};
use coap_net::Psk;

/// What an identity may do.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Role {
    /// Read: GET, grabs, discovery, Observe.
    Read,
    /// Read and change the configuration.
    Configure,
}

/// The identities of a server, with their keys and roles.
#[derive(Debug, Default)]
pub struct Identities {
    by_name: HashMap<String, (Vec<u8>, Role)>,
}

impl Identities {
    /// Reads a `--psk-file`.
    pub fn load(path: &Path) -> anyhow::Result<Self> {
        let text =
            std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
        Self::parse(&text).with_context(|| format!("in {}", path.display()))
    }

    /// Parses the text of a `--psk-file`.
    pub fn parse(text: &str) -> anyhow::Result<Self> {
        let mut by_name = HashMap::new();
        for (n, line) in text.lines().enumerate() {
            let line = line.split('#').next().unwrap_or_default().trim();
            if line.is_empty() {
                continue;
            }
            let fields: Vec<&str> = line.split_whitespace().collect();
            let [identity, key, role] = fields[..] else {
                bail!("line {}: expected IDENTITY KEY ROLE", n + 1);
            };
            let role = match role {
                "read" => Role::Read,
                "configure" => Role::Configure,
                other => bail!(
                    "line {}: role {other:?} is neither read nor configure",
                    n + 1
                ),
            };
            // OpenSSL's limits: an identity of up to 128 bytes, a key of up to 64.
            if identity.len() > 128 || key.len() > 64 {
                bail!("line {}: identities are at most 128 bytes, keys 64", n + 1);
            }
            if by_name
                .insert(identity.to_string(), (key.as_bytes().to_vec(), role))
                .is_some()
            {
                bail!("line {}: identity {identity:?} appears twice", n + 1);
            }
        }
        if by_name.is_empty() {
            bail!("no identities");
        }
        Ok(Self { by_name })
    }

    /// The role of an identity.
    pub fn role(&self, identity: &str) -> Option<Role> {
        self.by_name.get(identity).map(|(_, r)| *r)
    }

    /// The keys, for the DTLS server.
    pub fn keys(self: &Arc<Self>) -> Psk {
        let me = self.clone();
        Psk::Server(Arc::new(move |identity: &[u8]| {
            let name = std::str::from_utf8(identity).ok()?;
            me.by_name.get(name).map(|(k, _)| k.clone())
        }))
    }
}

/// The policy for configuration changes when identities are configured: an identity with
/// the `configure` role may (4.03 for one that may only read), this machine may over plain
/// CoAP, and anyone else gets 4.01: they must come over DTLS with such an identity.
pub fn by_role(identities: Arc<Identities>) -> impl Fn(&IncomingRequest) -> Option<Response> {
    move |request| match request.identity.as_deref() {
        Some(id) if identities.role(id) == Some(Role::Configure) => None,
        Some(id) => Some(Response::diagnostic(
            Code::FORBIDDEN,
            &format!("identity {id:?} may read but not change the configuration"),
        )),
        None if request.loopback => None,
        None => Some(Response::diagnostic(
            Code::UNAUTHORIZED,
            "configuration changes need coaps:// with an identity of the configure role",
        )),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_file_gives_keys_and_roles_and_refuses_what_it_cannot_read() {
        let ids = Identities::parse("# station\nalice secret-a configure\nbob s-b read # ro\n")
            .expect("parses");
        assert_eq!(ids.role("alice"), Some(Role::Configure));
        assert_eq!(ids.role("bob"), Some(Role::Read));
        assert_eq!(ids.role("carol"), None);
        for bad in [
            "alice key admin",
            "alice key",
            "a k read\na k2 read",
            "# nothing",
        ] {
            assert!(Identities::parse(bad).is_err(), "{bad:?}");
        }
    }

    #[test]
    fn configuration_changes_need_the_configure_role() {
        let ids = Arc::new(Identities::parse("alice a configure\nbob b read").expect("parses"));
        let policy = by_role(ids);
        // A request from `peer`, over loopback or from a network interface.
        let request = |(peer, loopback): (&str, bool), identity: Option<&str>| IncomingRequest {
            id: coap::IncomingId(1),
            peer: peer.parse().expect("address"),
            method: Code::PUT,
            options: coap::Request::new(Code::PUT, "/x").options,
            payload: bytes::Bytes::new(),
            multicast: false,
            confirmable: true,
            observe: None,
            identity: identity.map(Into::into),
            loopback,
        };
        let code = |r: Option<Response>| r.map(|r| r.code);
        let stranger = ("192.0.2.1:1", false);
        assert_eq!(code(policy(&request(stranger, Some("alice")))), None);
        assert_eq!(
            code(policy(&request(stranger, Some("bob")))),
            Some(Code::FORBIDDEN)
        );
        assert_eq!(
            code(policy(&request(stranger, None))),
            Some(Code::UNAUTHORIZED)
        );
        assert_eq!(code(policy(&request(("127.0.0.1:1", true), None))), None);
        // What decides is the way in, not the address.
        assert_eq!(
            code(policy(&request(("[::ffff:127.0.0.1]:1", false), None))),
            Some(Code::UNAUTHORIZED)
        );
        assert_eq!(
            code(policy(&request(("[2001:db8::1]:1", true), None))),
            None
        );
    }
}
