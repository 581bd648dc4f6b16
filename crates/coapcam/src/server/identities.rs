//! Who may do what: the DTLS pre-shared keys of `serve --psk-file`, each with a role.
//!
//! The file has one identity per line, `IDENTITY KEY ROLE`, separated by blanks; `#`
//! starts a comment. The role is `read` (GET, grabs, discovery, Observe) or `configure`
//! (also what changes the server: PUT and DELETE, POST to `/coap-group`, `/files` and the
//! creation resources). Identities and keys are text, as libcoap's tools take them.

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;

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

/// A `--psk-file` that could not be read.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum LoadError {
    /// The file could not be read.
    #[error("reading {}", path.display())]
    Read {
        /// The file.
        path: PathBuf,
        /// Why.
        source: std::io::Error,
    },
    /// Its text is not a list of identities.
    #[error("in {}", path.display())]
    Parse {
        /// The file.
        path: PathBuf,
        /// What is wrong, and on which line.
        source: ParseError,
    },
}

/// The text of a `--psk-file` is not a list of identities (lines counted from 1).
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum ParseError {
    /// A line without three fields.
    #[error("line {line}: expected IDENTITY KEY ROLE")]
    Fields {
        /// The line.
        line: usize,
    },
    /// A role other than `read` and `configure`.
    #[error("line {line}: role {role:?} is neither read nor configure")]
    Role {
        /// The line.
        line: usize,
        /// The role given.
        role: String,
    },
    /// An identity or key longer than OpenSSL takes.
    #[error("line {line}: identities are at most 128 bytes, keys 64")]
    TooLong {
        /// The line.
        line: usize,
    },
    /// An identity given twice.
    #[error("line {line}: identity {identity:?} appears twice")]
    Twice {
        /// The line of the second.
        line: usize,
        /// The identity.
        identity: String,
    },
    /// No line names an identity.
    #[error("no identities")]
    Empty,
}

/// The identities of a server, with their keys and roles.
#[derive(Debug, Default)]
pub struct Identities {
    by_name: HashMap<String, (Vec<u8>, Role)>,
}

impl Identities {
    /// Reads a `--psk-file`.
    pub fn load(path: &Path) -> Result<Self, LoadError> {
        let text = std::fs::read_to_string(path).map_err(|source| LoadError::Read {
            path: path.to_owned(),
            source,
        })?;
        Self::parse(&text).map_err(|source| LoadError::Parse {
            path: path.to_owned(),
            source,
        })
    }

    /// Parses the text of a `--psk-file`.
    pub fn parse(text: &str) -> Result<Self, ParseError> {
        let mut by_name = HashMap::new();
        for (n, line) in text.lines().enumerate() {
            let line = line.split('#').next().unwrap_or_default().trim();
            if line.is_empty() {
                continue;
            }
            let fields: Vec<&str> = line.split_whitespace().collect();
            let line = n + 1;
            let [identity, key, role] = fields[..] else {
                return Err(ParseError::Fields { line });
            };
            let role = match role {
                "read" => Role::Read,
                "configure" => Role::Configure,
                other => {
                    return Err(ParseError::Role {
                        line,
                        role: other.to_owned(),
                    });
                }
            };
            // OpenSSL's limits: an identity of up to 128 bytes, a key of up to 64.
            if identity.len() > 128 || key.len() > 64 {
                return Err(ParseError::TooLong { line });
            }
            if by_name
                .insert(identity.to_string(), (key.as_bytes().to_vec(), role))
                .is_some()
            {
                return Err(ParseError::Twice {
                    line,
                    identity: identity.to_owned(),
                });
            }
        }
        if by_name.is_empty() {
            return Err(ParseError::Empty);
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
/// CoAP, and anyone else gets 4.01: they must come over DTLS (or TLS, `coaps+tcp` and
/// `coaps+ws`) with such an identity.
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
            "configuration changes need coaps:// (or coaps+tcp://, coaps+ws://) with an identity of the configure role",
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
        for (bad, why) in [
            (
                "alice key admin",
                r#"line 1: role "admin" is neither read nor configure"#,
            ),
            ("# a\nalice key", "line 2: expected IDENTITY KEY ROLE"),
            (
                "a k read\na k2 read",
                r#"line 2: identity "a" appears twice"#,
            ),
            ("# nothing", "no identities"),
        ] {
            let said = Identities::parse(bad)
                .map(|_| ())
                .map_err(|e| e.to_string());
            assert_eq!(said, Err(why.to_owned()), "{bad:?}");
        }
        assert!(matches!(
            Identities::parse(&format!("{} k read", "i".repeat(129))),
            Err(ParseError::TooLong { line: 1 })
        ));
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
