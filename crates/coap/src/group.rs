//! RFC 7390 §2.6.2 group configuration: the `application/coap-group+json` payload
//! (content format 256) of the `/coap-group` resource.
//!
//! One group membership is a JSON object with an optional group name `"n"` and the IP
//! multicast address `"a"` in URI authority form (`"224.0.1.187"`, `"224.0.1.187:5683"`,
//! `"[ff02::fd]:5683"`); the port defaults to 5683. `GET /coap-group` answers with a JSON
//! object that maps each membership resource's name to its membership object.
//!
//! RFC 7390 also allows a membership that carries only a group name, to be resolved through
//! DNS. The protocol core does no name resolution, so here `"a"` is required.
//!
//! Errors say which field is wrong and what is allowed, so a server can send them as the
//! text of a 4.00 (Bad Request) response.
//!
//! ```
//! use coap::group::{GroupAddr, GroupConfig};
//!
//! let config = GroupConfig::from_json(br#"{"n": "cams.floor1", "a": "[ff05::fd]:5683"}"#)?;
//! assert_eq!(config.name.as_deref(), Some("cams.floor1"));
//! assert_eq!(config.addr, "[ff05::fd]".parse::<GroupAddr>()?);
//! assert_eq!(config.to_json(), r#"{"n":"cams.floor1","a":"[ff05::fd]"}"#);
//! # Ok::<(), coap::group::Error>(())
//! ```

use std::collections::BTreeMap;
use std::fmt;
use std::net::{IpAddr, Ipv4Addr, Ipv6Addr, SocketAddr};
use std::str::FromStr;

use serde::de::Error as _;
use serde::ser::SerializeMap as _;
use serde_json::Value;

/// The default CoAP port, used when `"a"` names no port (RFC 7252 §6.1).
pub const DEFAULT_PORT: u16 = 5683;

/// The longest group name accepted, in bytes: a DNS name (253) plus a `:port` suffix.
pub const MAX_NAME_LEN: usize = 253 + 6;

/// A group's IP multicast address and UDP port (the `"a"` member, RFC 7390 §2.6.2.1).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct GroupAddr {
    ip: IpAddr,
    port: u16,
}

impl GroupAddr {
    /// A group address, if `ip` is a multicast address (RFC 7390 §2.6.2.1) and `port` is
    /// not 0.
    ///
    /// # Errors
    ///
    /// [`Error::NotMulticast`] or [`Error::InvalidPort`].
    pub fn new(ip: IpAddr, port: u16) -> Result<Self, Error> {
        if !ip.is_multicast() {
            return Err(Error::NotMulticast { ip });
        }
        if port == 0 {
            return Err(Error::InvalidPort {
                value: port.to_string(),
            });
        }
        Ok(Self { ip, port })
    }

    /// The multicast IP address.
    #[must_use]
    pub fn ip(&self) -> IpAddr {
        self.ip
    }

    /// The UDP port (5683 unless the authority named another).
    #[must_use]
    pub fn port(&self) -> u16 {
        self.port
    }

    /// The address and port as a socket address, to join and send to.
    #[must_use]
    pub fn socket_addr(&self) -> SocketAddr {
        SocketAddr::new(self.ip, self.port)
    }
}

impl FromStr for GroupAddr {
    type Err = Error;

    /// Parses a URI authority with an IP literal host (RFC 3986 §3.2): `IPv4[:port]`,
    /// `[IPv6][:port]`, or a bare IPv6 address without a port.
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        let invalid = || Error::InvalidAddr {
            value: s.to_owned(),
        };
        let (ip, port) = if let Some(rest) = s.strip_prefix('[') {
            let (host, after) = rest.split_once(']').ok_or_else(invalid)?;
            let ip = host.parse::<Ipv6Addr>().map_err(|_| invalid())?;
            let port = match after {
                "" => None,
                _ => Some(after.strip_prefix(':').ok_or_else(invalid)?),
            };
            (IpAddr::V6(ip), port)
        } else if let Ok(ip) = s.parse::<Ipv6Addr>() {
            (IpAddr::V6(ip), None)
        } else {
            let (host, port) = match s.split_once(':') {
                Some((host, port)) => (host, Some(port)),
                None => (s, None),
            };
            (
                IpAddr::V4(host.parse::<Ipv4Addr>().map_err(|_| invalid())?),
                port,
            )
        };
        let port = match port {
            None => DEFAULT_PORT,
            Some(p) if !p.is_empty() && p.bytes().all(|b| b.is_ascii_digit()) => {
                p.parse::<u16>().map_err(|_| Error::InvalidPort {
                    value: p.to_owned(),
                })?
            }
            Some(p) => {
                return Err(Error::InvalidPort {
                    value: p.to_owned(),
                });
            }
        };
        Self::new(ip, port)
    }
}

impl fmt::Display for GroupAddr {
    /// Writes the URI authority form; the port is left out when it is 5683, and IPv6
    /// addresses are always in brackets.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self.ip {
            IpAddr::V4(ip) => write!(f, "{ip}")?,
            IpAddr::V6(ip) => write!(f, "[{ip}]")?,
        }
        if self.port != DEFAULT_PORT {
            write!(f, ":{}", self.port)?;
        }
        Ok(())
    }
}

impl serde::Serialize for GroupAddr {
    fn serialize<S: serde::Serializer>(&self, serializer: S) -> Result<S::Ok, S::Error> {
        serializer.collect_str(self)
    }
}

impl<'de> serde::Deserialize<'de> for GroupAddr {
    fn deserialize<D: serde::Deserializer<'de>>(deserializer: D) -> Result<Self, D::Error> {
        let s = <std::borrow::Cow<'de, str>>::deserialize(deserializer)?;
        s.parse().map_err(D::Error::custom)
    }
}

/// One group membership (RFC 7390 §2.6.2.1): `{"n": name, "a": address}`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct GroupConfig {
    /// The group name, `"n"` (RFC 7390 §2.2): a host name, optionally with a port, or a
    /// URI. Optional.
    pub name: Option<String>,
    /// The IP multicast address and port, `"a"`.
    pub addr: GroupAddr,
}

impl GroupConfig {
    /// Decodes an `application/coap-group+json` membership object.
    ///
    /// Keys other than `"n"` and `"a"` are ignored, so later extensions still parse.
    ///
    /// # Errors
    ///
    /// [`Error`] naming the field that is wrong and what it must be.
    pub fn from_json(payload: &[u8]) -> Result<Self, Error> {
        let value = serde_json::from_slice::<Value>(payload).map_err(json_error)?;
        Self::try_from(value)
    }

    /// Encodes the membership object, e.g. `{"n":"cams","a":"224.0.1.187"}`.
    #[must_use]
    pub fn to_json(&self) -> String {
        // NOTE: serializing strings into a String cannot fail.
        serde_json::to_string(self).unwrap_or_default()
    }
}

impl TryFrom<Value> for GroupConfig {
    type Error = Error;

    /// RFC 7390 §2.6.2.1.
    fn try_from(value: Value) -> Result<Self, Self::Error> {
        let Value::Object(mut object) = value else {
            return Err(Error::NotAnObject {
                found: kind(&value),
            });
        };
        let name = match object.remove("n") {
            None => None,
            Some(Value::String(n)) if n.is_empty() => return Err(Error::EmptyName),
            Some(Value::String(n)) if n.len() > MAX_NAME_LEN => {
                return Err(Error::NameTooLong { len: n.len() });
            }
            Some(Value::String(n)) => Some(n),
            Some(other) => {
                return Err(Error::FieldType {
                    field: "n",
                    found: kind(&other),
                });
            }
        };
        let addr = match object.remove("a") {
            None => return Err(Error::MissingAddr),
            Some(Value::String(a)) => a.parse()?,
            Some(other) => {
                return Err(Error::FieldType {
                    field: "a",
                    found: kind(&other),
                });
            }
        };
        Ok(Self { name, addr })
    }
}

impl serde::Serialize for GroupConfig {
    fn serialize<S: serde::Serializer>(&self, serializer: S) -> Result<S::Ok, S::Error> {
        let mut map = serializer.serialize_map(Some(1 + usize::from(self.name.is_some())))?;
        if let Some(name) = &self.name {
            map.serialize_entry("n", name)?;
        }
        map.serialize_entry("a", &self.addr)?;
        map.end()
    }
}

impl<'de> serde::Deserialize<'de> for GroupConfig {
    fn deserialize<D: serde::Deserializer<'de>>(deserializer: D) -> Result<Self, D::Error> {
        Self::try_from(Value::deserialize(deserializer)?).map_err(D::Error::custom)
    }
}

/// Decodes the membership list returned by `GET /coap-group` (RFC 7390 §2.6.2.3): a JSON
/// object mapping each membership resource's name (the last path segment of its
/// Location-Path, e.g. `"12"` for `/coap-group/12`) to its membership object.
///
/// # Errors
///
/// [`Error::InMember`] naming the membership whose object is wrong, or [`Error`] for a
/// payload that is not a JSON object.
pub fn decode_list(payload: &[u8]) -> Result<BTreeMap<String, GroupConfig>, Error> {
    let value = serde_json::from_slice::<Value>(payload).map_err(json_error)?;
    let Value::Object(object) = value else {
        return Err(Error::NotAnObject {
            found: kind(&value),
        });
    };
    object
        .into_iter()
        .map(|(key, member)| match GroupConfig::try_from(member) {
            Ok(config) => Ok((key, config)),
            Err(source) => Err(Error::InMember {
                key,
                source: Box::new(source),
            }),
        })
        .collect()
}

/// Encodes the membership list of `GET /coap-group` (RFC 7390 §2.6.2.3), keys in order.
#[must_use]
pub fn encode_list(memberships: &BTreeMap<String, GroupConfig>) -> String {
    // NOTE: serializing strings into a String cannot fail.
    serde_json::to_string(memberships).unwrap_or_default()
}

/// Why a group configuration payload is rejected; the text is fit for a 4.00 diagnostic.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum Error {
    /// The payload is not JSON.
    #[error("payload is not JSON ({detail}); expected application/coap-group+json")]
    InvalidJson {
        /// What the JSON parser reported.
        detail: String,
    },
    /// The payload is JSON but not an object.
    #[error("expected a JSON object, found {found}")]
    NotAnObject {
        /// The JSON type found instead.
        found: &'static str,
    },
    /// `"a"` is absent.
    #[error(r#"field "a" is required: the group's IP multicast address, e.g. "224.0.1.187" or "[ff05::fd]:5683""#)]
    MissingAddr,
    /// A field has the wrong JSON type.
    #[error(r#"field "{field}" must be a string, found {found}"#)]
    FieldType {
        /// The field, `"n"` or `"a"`.
        field: &'static str,
        /// The JSON type found instead.
        found: &'static str,
    },
    /// `"n"` is the empty string.
    #[error(r#"field "n" must not be empty: leave it out or give the group's host name"#)]
    EmptyName,
    /// `"n"` is longer than [`MAX_NAME_LEN`].
    #[error(r#"field "n" is {len} bytes long; at most {max} are allowed"#, max = MAX_NAME_LEN)]
    NameTooLong {
        /// Its length in bytes.
        len: usize,
    },
    /// `"a"` is not an IP literal authority.
    #[error(
        r#"field "a" = {value:?} is not an IP address with optional port: use "224.0.1.187", "224.0.1.187:5683", "[ff05::fd]" or "[ff05::fd]:5683""#
    )]
    InvalidAddr {
        /// The rejected value.
        value: String,
    },
    /// `"a"` names a port that is not a number in 1-65535.
    #[error(r#"field "a" has port {value:?}; the port must be a number in 1-65535"#)]
    InvalidPort {
        /// The rejected port text.
        value: String,
    },
    /// `"a"` names a unicast address.
    #[error(
        r#"field "a" = {ip} is not a multicast address: use 224.0.0.0/4 for IPv4 or ff00::/8 for IPv6"#
    )]
    NotMulticast {
        /// The rejected address.
        ip: IpAddr,
    },
    /// A membership of a list is wrong.
    #[error("membership {key:?}: {source}")]
    InMember {
        /// The membership resource name.
        key: String,
        /// What is wrong with it.
        source: Box<Self>,
    },
}

fn json_error(e: serde_json::Error) -> Error {
    Error::InvalidJson {
        detail: e.to_string(),
    }
}

fn kind(value: &Value) -> &'static str {
    match value {
        Value::Null => "null",
        Value::Bool(_) => "a boolean",
        Value::Number(_) => "a number",
        Value::String(_) => "a string",
        Value::Array(_) => "an array",
        Value::Object(_) => "an object",
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn addr(s: &str) -> GroupAddr {
        s.parse().unwrap_or_else(|e| panic!("{s:?}: {e}"))
    }

    #[test]
    fn parses_ipv4_with_and_without_port() {
        let a = addr("224.0.1.187");
        assert_eq!(a.ip(), IpAddr::V4(Ipv4Addr::new(224, 0, 1, 187)));
        assert_eq!(a.port(), DEFAULT_PORT);
        let a = addr("239.255.0.1:1234");
        assert_eq!(a.socket_addr(), "239.255.0.1:1234".parse().unwrap());
    }

    #[test]
    fn parses_ipv6_bracketed_bare_and_with_port() {
        let ip: IpAddr = "ff02::fd".parse().unwrap();
        assert_eq!(addr("[ff02::fd]:5683"), GroupAddr::new(ip, 5683).unwrap());
        assert_eq!(
            addr("[ff02::fd]"),
            GroupAddr::new(ip, DEFAULT_PORT).unwrap()
        );
        assert_eq!(addr("ff02::fd"), GroupAddr::new(ip, DEFAULT_PORT).unwrap());
        assert_eq!(addr("[ff15::4200:f7fe:ed37:abcd]:1234").port(), 1234);
    }

    #[test]
    fn display_is_authority_form_without_default_port() {
        assert_eq!(addr("224.0.1.187:5683").to_string(), "224.0.1.187");
        assert_eq!(addr("224.0.1.187:1234").to_string(), "224.0.1.187:1234");
        assert_eq!(addr("ff02::fd").to_string(), "[ff02::fd]");
        assert_eq!(addr("[ff02::fd]:61616").to_string(), "[ff02::fd]:61616");
    }

    #[test]
    fn rejects_unicast_addresses_by_name() {
        for s in [
            "192.168.1.10",
            "127.0.0.1:5683",
            "[::1]:5683",
            "fe80::1",
            "0.0.0.0",
        ] {
            let err = s.parse::<GroupAddr>().unwrap_err();
            assert!(matches!(err, Error::NotMulticast { .. }), "{s}: {err}");
            assert!(err.to_string().contains("not a multicast address"));
        }
        let err = "10.0.0.1".parse::<GroupAddr>().unwrap_err().to_string();
        assert!(err.contains("10.0.0.1"), "{err}");
    }

    #[test]
    fn rejects_malformed_addresses_and_ports() {
        for s in [
            "",
            "cams.example.com",
            "224.0.1",
            "[ff02::fd",
            "[ff02::fd]x",
            "[224.0.1.187]",
            "ff02::fd:5683x",
            "[ff02::1%eth0]",
            " 224.0.1.187",
        ] {
            assert!(
                matches!(s.parse::<GroupAddr>(), Err(Error::InvalidAddr { .. })),
                "{s:?}"
            );
        }
        for s in [
            "224.0.1.187:",
            "224.0.1.187:0",
            "224.0.1.187:65536",
            "224.0.1.187:+1",
            "[ff02::fd]:port",
            "[ff02::fd]:",
        ] {
            assert!(
                matches!(s.parse::<GroupAddr>(), Err(Error::InvalidPort { .. })),
                "{s:?}"
            );
        }
    }

    #[test]
    fn decodes_membership_objects() {
        let c = GroupConfig::from_json(
            br#"{"n": "All-Devices.floor1.west.bldg6.example.com", "a": "[ff15::4200:f7fe:ed37:abcd]:1234"}"#,
        )
        .unwrap();
        assert_eq!(
            c.name.as_deref(),
            Some("All-Devices.floor1.west.bldg6.example.com")
        );
        assert_eq!(c.addr, addr("[ff15::4200:f7fe:ed37:abcd]:1234"));

        let c = GroupConfig::from_json(br#"{"a": "224.0.1.187", "x": [1, 2]}"#).unwrap();
        assert_eq!(c.name, None);
        assert_eq!(c.addr.port(), DEFAULT_PORT);
    }

    #[test]
    fn membership_errors_name_the_field() {
        let cases: &[(&[u8], Error)] = &[
            (br#"{"n": "cams"}"#, Error::MissingAddr),
            (
                br#"{"a": 5683}"#,
                Error::FieldType {
                    field: "a",
                    found: "a number",
                },
            ),
            (
                br#"{"n": null, "a": "224.0.1.187"}"#,
                Error::FieldType {
                    field: "n",
                    found: "null",
                },
            ),
            (br#"{"n": "", "a": "224.0.1.187"}"#, Error::EmptyName),
            (br#"[]"#, Error::NotAnObject { found: "an array" }),
            (
                br#"{"a": "192.0.2.1"}"#,
                Error::NotMulticast {
                    ip: IpAddr::V4(Ipv4Addr::new(192, 0, 2, 1)),
                },
            ),
        ];
        for (payload, expected) in cases {
            assert_eq!(
                GroupConfig::from_json(payload).as_ref(),
                Err(expected),
                "{}",
                String::from_utf8_lossy(payload)
            );
        }
        let long = format!(r#"{{"n": "{}", "a": "224.0.1.187"}}"#, "x".repeat(300));
        assert_eq!(
            GroupConfig::from_json(long.as_bytes()),
            Err(Error::NameTooLong { len: 300 })
        );
        assert!(matches!(
            GroupConfig::from_json(b"{\"a\":"),
            Err(Error::InvalidJson { .. })
        ));
        assert!(matches!(
            GroupConfig::from_json(&[0xff, 0xfe]),
            Err(Error::InvalidJson { .. })
        ));
        let message = GroupConfig::from_json(br#"{"n": "cams"}"#)
            .unwrap_err()
            .to_string();
        assert!(message.starts_with(r#"field "a" is required"#), "{message}");
    }

    #[test]
    fn membership_round_trips() {
        for config in [
            GroupConfig {
                name: Some("cams.floor1".to_owned()),
                addr: addr("[ff05::fd]:61616"),
            },
            GroupConfig {
                name: None,
                addr: addr("224.0.1.187"),
            },
        ] {
            assert_eq!(
                GroupConfig::from_json(config.to_json().as_bytes()),
                Ok(config.clone())
            );
            let via_serde = serde_json::to_string(&config).unwrap();
            assert_eq!(via_serde, config.to_json());
            assert_eq!(
                serde_json::from_str::<GroupConfig>(&via_serde).unwrap(),
                config
            );
        }
        assert_eq!(
            GroupConfig {
                name: Some("cams".to_owned()),
                addr: addr("224.0.1.187:5683"),
            }
            .to_json(),
            r#"{"n":"cams","a":"224.0.1.187"}"#
        );
    }

    #[test]
    fn serde_deserialize_reports_the_field() {
        let err = serde_json::from_str::<GroupConfig>(r#"{"a": "10.0.0.1"}"#).unwrap_err();
        assert!(err.to_string().contains("not a multicast address"), "{err}");
        let err = serde_json::from_str::<GroupAddr>(r#""10.0.0.1""#).unwrap_err();
        assert!(err.to_string().contains("not a multicast address"), "{err}");
        assert_eq!(
            serde_json::from_str::<GroupAddr>(r#""[ff02::fd]:1""#).unwrap(),
            addr("[ff02::fd]:1")
        );
    }

    proptest::proptest! {
        #[test]
        fn any_multicast_addr_round_trips(
            v4 in 0xe000_0000u32..=0xefff_ffff,
            v6_low in proptest::prelude::any::<u128>(),
            port in 1u16..,
        ) {
            let v6 = (0xffu128 << 120) | (v6_low >> 8);
            for ip in [IpAddr::V4(Ipv4Addr::from(v4)), IpAddr::V6(Ipv6Addr::from(v6))] {
                let a = GroupAddr::new(ip, port).unwrap();
                proptest::prop_assert_eq!(a.to_string().parse::<GroupAddr>(), Ok(a));
            }
        }

        #[test]
        fn decoding_never_panics(payload in proptest::prelude::any::<Vec<u8>>(), s in ".{0,40}") {
            let _ = GroupConfig::from_json(&payload);
            let _ = decode_list(&payload);
            let _ = s.parse::<GroupAddr>();
        }
    }

    /// The `GET /coap-group` response of RFC 7390 §2.6.2.3.
    #[test]
    fn decodes_and_encodes_membership_list() {
        let payload = br#"{
            "8": {"a": "[ff15::4200:f7fe:ed37:14ca]"},
            "11": {"n": "sensors.floor1.west.bldg6.example.com", "a": "[ff15::4200:f7fe:ed37:25cb]"},
            "12": {"n": "All-Devices.floor1.west.bldg6.example.com", "a": "[ff15::4200:f7fe:ed37:abcd]:4567"}
        }"#;
        let list = decode_list(payload).unwrap();
        assert_eq!(list.keys().collect::<Vec<_>>(), ["11", "12", "8"]);
        assert_eq!(list["8"].name, None);
        assert_eq!(list["12"].addr.port(), 4567);
        assert_eq!(
            list["11"].name.as_deref(),
            Some("sensors.floor1.west.bldg6.example.com")
        );
        let encoded = encode_list(&list);
        assert_eq!(decode_list(encoded.as_bytes()), Ok(list));
        assert_eq!(encode_list(&BTreeMap::new()), "{}");
        assert_eq!(decode_list(b"{}"), Ok(BTreeMap::new()));
    }

    #[test]
    fn list_errors_name_the_membership() {
        let err =
            decode_list(br#"{"3": {"a": "224.0.1.187"}, "7": {"a": "10.1.1.1"}}"#).unwrap_err();
        assert!(
            matches!(&err, Error::InMember { key, source } if key == "7"
                && matches!(**source, Error::NotMulticast { .. })),
            "{err:?}"
        );
        assert!(
            err.to_string().starts_with(r#"membership "7": field "a""#),
            "{err}"
        );
        assert_eq!(
            decode_list(b"\"x\""),
            Err(Error::NotAnObject { found: "a string" })
        );
    }
}
