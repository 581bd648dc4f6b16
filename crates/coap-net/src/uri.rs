//! `coap://host[:port]/path?query` and `coaps://` URIs (RFC 7252 §6), and
//! `coap+tcp://`, `coaps+tcp://`, `coap+ws://` and `coaps+ws://` ones (RFC 8323 §8), to a
//! socket address and request options, and back.

use std::net::{IpAddr, SocketAddr};

use coap::{OptionNumber, Options};

/// A parsed `coap://`, `coaps://`, `coap+tcp://`, `coaps+tcp://`, `coap+ws://` or
/// `coaps+ws://` URI.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Uri {
    /// `coaps`: the server is reached through DTLS (`coaps://`, RFC 7252 §6.2), or TLS
    /// with `tcp` or `ws` (`coaps+tcp://`, `coaps+ws://`).
    pub secure: bool,
    /// `coap+tcp://` (or `coaps+tcp://`): the server is reached over TCP (RFC 8323 §8).
    pub tcp: bool,
    /// `coap+ws://` (or `coaps+ws://`): the server is reached over WebSockets, at its
    /// `/.well-known/coap` (RFC 8323 §8); the path is the resource's, as ever.
    pub ws: bool,
    /// Host as written: an IP literal (IPv6 without brackets or zone) or a name.
    pub host: String,
    /// The zone of an IPv6 link-local literal (RFC 6874, `[ff02::fd%25eth0]`): an
    /// interface name or index.
    pub zone: Option<String>,
    /// Port (5683 when absent, for `coap+tcp://` too; 5684 for `coaps://` and
    /// `coaps+tcp://`; 80 for `coap+ws://`, 443 for `coaps+ws://`).
    pub port: u16,
    /// Path segments, percent-decoded.
    pub path: Vec<String>,
    /// Query items, percent-decoded.
    pub query: Vec<String>,
}

/// Why a URI was refused.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum UriError {
    /// Only `coap://`, `coaps://`, `coap+tcp://`, `coaps+tcp://`, `coap+ws://` and
    /// `coaps+ws://` are supported.
    #[error(
        "unsupported scheme in {0:?}: only coap://, coaps://, coap+tcp://, coaps+tcp://, coap+ws:// and coaps+ws:// are supported"
    )]
    Scheme(String),
    /// No host.
    #[error("no host in {0:?}")]
    Host(String),
    /// A port that is not a number from 1 to 65535.
    #[error("bad port in {0:?}: a port is a number from 1 to 65535")]
    Port(String),
    /// A `%` not followed by two hex digits, or bytes that are not UTF-8.
    #[error("bad percent-encoding in {0:?}")]
    Percent(String),
    /// A fragment (`#`), which CoAP URIs must not have (RFC 7252 §6.1).
    #[error("fragment not allowed in {0:?}")]
    Fragment(String),
}

/// The default CoAP port.
pub const DEFAULT_PORT: u16 = 5683;
/// The default port of CoAP over DTLS (`coaps://`) and over TLS (`coaps+tcp://`).
pub const DEFAULT_SECURE_PORT: u16 = 5684;
/// The default port of CoAP over WebSockets (`coap+ws://`, RFC 8323 §8): HTTP's.
pub const DEFAULT_WS_PORT: u16 = 80;
/// The default port of CoAP over WebSockets over TLS (`coaps+ws://`): HTTPS's.
pub const DEFAULT_WSS_PORT: u16 = 443;

impl Uri {
    /// Parses `coap://host[:port][/path][?query]` (or `coaps://`, `coap+tcp://`,
    /// `coaps+tcp://`, `coap+ws://` or `coaps+ws://`).
    pub fn parse(s: &str) -> Result<Self, UriError> {
        // Scheme, secure, tcp, ws.
        let schemes = [
            ("coap://", false, false, false),
            ("coaps://", true, false, false),
            ("coap+tcp://", false, true, false),
            ("coaps+tcp://", true, true, false),
            ("coap+ws://", false, false, true),
            ("coaps+ws://", true, false, true),
        ];
        let Some((rest, secure, tcp, ws)) = schemes.iter().find_map(|(scheme, secure, tcp, ws)| {
            Some((s.strip_prefix(scheme)?, *secure, *tcp, *ws))
        }) else {
            return Err(UriError::Scheme(s.to_string()));
        };
        if rest.contains('#') {
            return Err(UriError::Fragment(s.to_string()));
        }
        let (authority, path_query) = match rest.find(['/', '?']) {
            Some(i) => rest.split_at(i),
            None => (rest, ""),
        };
        let (host, port) = if let Some(v6) = authority.strip_prefix('[') {
            let (h, after) = v6
                .split_once(']')
                .ok_or_else(|| UriError::Host(s.to_string()))?;
            let port = match after.strip_prefix(':') {
                Some(p) => Some(p),
                None if after.is_empty() => None,
                None => return Err(UriError::Host(s.to_string())),
            };
            // RFC 6874 writes the zone separator as %25; a bare % is accepted too.
            (h.replacen("%25", "%", 1), port)
        } else {
            match authority.rsplit_once(':') {
                Some((h, p)) => (h.to_string(), Some(p)),
                None => (authority.to_string(), None),
            }
        };
        let (host, zone) = match host.split_once('%') {
            Some((h, z)) if !z.is_empty() => (h.to_string(), Some(z.to_string())),
            Some(_) => return Err(UriError::Host(s.to_string())),
            None => (host, None),
        };
        if host.is_empty() {
            return Err(UriError::Host(s.to_string()));
        }
        let port = match port {
            Some(p) => p
                .parse::<u16>()
                .ok()
                .filter(|p| *p != 0)
                .ok_or_else(|| UriError::Port(s.to_string()))?,
            None if secure && ws => DEFAULT_WSS_PORT,
            None if secure => DEFAULT_SECURE_PORT,
            None if ws => DEFAULT_WS_PORT,
            None => DEFAULT_PORT,
        };
        let (path, query) = match path_query.split_once('?') {
            Some((p, q)) => (p, Some(q)),
            None => (path_query, None),
        };
        let decode =
            |part: &str| percent_decode(part).ok_or_else(|| UriError::Percent(s.to_string()));
        let path = path
            .split('/')
            .filter(|seg| !seg.is_empty())
            .map(decode)
            .collect::<Result<Vec<_>, _>>()?;
        let query = query
            .map(|q| {
                q.split('&')
                    .filter(|i| !i.is_empty())
                    .map(decode)
                    .collect::<Result<Vec<_>, _>>()
            })
            .transpose()?
            .unwrap_or_default();
        Ok(Self {
            secure,
            tcp,
            ws,
            host,
            zone,
            port,
            path,
            query,
        })
    }

    /// The host as an IP address, when it is a literal.
    pub fn ip(&self) -> Option<IpAddr> {
        self.host.parse().ok()
    }

    /// Resolves the host (a literal, or a name through the system resolver). A zone
    /// becomes the IPv6 scope (an interface index, or a name looked up in
    /// `/sys/class/net/NAME/ifindex`).
    pub async fn resolve(&self) -> std::io::Result<SocketAddr> {
        if let Some(ip) = self.ip() {
            let mut addr = SocketAddr::new(ip, self.port);
            if let (SocketAddr::V6(a), Some(zone)) = (&mut addr, &self.zone) {
                a.set_scope_id(interface_index(zone)?);
            }
            return Ok(addr);
        }
        tokio::net::lookup_host((self.host.as_str(), self.port))
            .await?
            .next()
            .ok_or_else(|| {
                std::io::Error::new(
                    std::io::ErrorKind::NotFound,
                    format!("{} does not resolve", self.host),
                )
            })
    }

    /// The request options this URI stands for (RFC 7252 §6.4): Uri-Host for a name,
    /// Uri-Path and Uri-Query for each segment and item.
    pub fn options(&self) -> Options {
        let mut o = Options::new();
        if self.ip().is_none() {
            o.push(OptionNumber::URI_HOST, self.host.as_bytes());
        }
        for seg in &self.path {
            o.push(OptionNumber::URI_PATH, seg.as_bytes());
        }
        for q in &self.query {
            o.push(OptionNumber::URI_QUERY, q.as_bytes());
        }
        o
    }

    /// The path with a leading `/`.
    pub fn path_string(&self) -> String {
        format!("/{}", self.path.join("/"))
    }
}

/// An interface index from a number or an interface name.
pub fn interface_index(zone: &str) -> std::io::Result<u32> {
    if let Ok(n) = zone.parse() {
        return Ok(n);
    }
    let path = format!("/sys/class/net/{zone}/ifindex");
    let text = std::fs::read_to_string(&path)
        .map_err(|e| std::io::Error::new(e.kind(), format!("interface {zone:?}: {e}")))?;
    text.trim().parse().map_err(|_| {
        std::io::Error::new(
            std::io::ErrorKind::InvalidData,
            format!("{path}: not an index"),
        )
    })
}

/// `s` with its `%XX` escapes decoded (RFC 3986 §2.1); `None` when an escape is broken or
/// the result is not UTF-8.
pub fn percent_decode(s: &str) -> Option<String> {
    let bytes = s.as_bytes();
    let mut out = Vec::with_capacity(bytes.len());
    let mut i = 0;
    while let Some(&b) = bytes.get(i) {
        if b == b'%' {
            let hex = std::str::from_utf8(bytes.get(i + 1..i + 3)?).ok()?;
            out.push(u8::from_str_radix(hex, 16).ok()?);
            i += 3;
        } else {
            out.push(b);
            i += 1;
        }
    }
    String::from_utf8(out).ok()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rfc7252_6_parses_host_port_path_query() {
        let u = Uri::parse("coap://127.0.0.1:5684/cams/pointclouds?rt=rgbd.color&x=%20y").unwrap();
        assert_eq!(u.port, 5684);
        assert_eq!(u.path, ["cams", "pointclouds"]);
        assert_eq!(u.query, ["rt=rgbd.color", "x= y"]);
        assert!(!u.options().contains(OptionNumber::URI_HOST));
        let u = Uri::parse("coap://[::1]/.well-known/core").unwrap();
        assert_eq!((u.host.as_str(), u.port), ("::1", 5683));
        let u = Uri::parse("coap://[ff02::fd%25lo]:5683/.well-known/core").unwrap();
        assert_eq!(
            (u.host.as_str(), u.zone.as_deref()),
            ("ff02::fd", Some("lo"))
        );
        let u = Uri::parse("coap://[fe80::1%3]").unwrap();
        assert_eq!(u.zone.as_deref(), Some("3"));
        let u = Uri::parse("coap://camera-1.local").unwrap();
        assert!(u.path.is_empty());
        assert!(u.options().contains(OptionNumber::URI_HOST));
    }

    #[test]
    fn rfc8323_8_1_coap_tcp_uris_default_to_port_5683() {
        let u = Uri::parse("coap+tcp://[::1]/cams/840412060746/color?x=1").unwrap();
        assert_eq!((u.tcp, u.secure), (true, false));
        assert_eq!((u.host.as_str(), u.port), ("::1", 5683));
        assert_eq!(u.path, ["cams", "840412060746", "color"]);
        assert_eq!(u.query, ["x=1"]);
        let u = Uri::parse("coap+tcp://camera-1.local:6000").unwrap();
        assert_eq!((u.port, u.path.len()), (6000, 0));
        assert!(!Uri::parse("coap://x").unwrap().tcp);
    }

    #[test]
    fn rfc8323_8_coaps_tcp_and_coaps_ws_uris_are_tls_on_ports_5684_and_443() {
        let u = Uri::parse("coaps+tcp://127.0.0.1/cams?x=1").unwrap();
        assert_eq!((u.secure, u.tcp, u.ws), (true, true, false));
        assert_eq!((u.port, u.path_string()), (5684, "/cams".into()));
        let u = Uri::parse("coaps+ws://[::1]/cams").unwrap();
        assert_eq!((u.secure, u.tcp, u.ws), (true, false, true));
        assert_eq!((u.host.as_str(), u.port), ("::1", 443));
        let u = Uri::parse("coaps+ws://camera-1.local:8443").unwrap();
        assert_eq!(u.port, 8443);
        // Not a scheme of RFC 8323's.
        assert!(matches!(
            Uri::parse("coaps+udp://x/"),
            Err(UriError::Scheme(_))
        ));
    }

    #[test]
    fn rfc8323_8_2_coap_ws_uris_default_to_port_80_and_keep_the_resource_path() {
        let u = Uri::parse("coap+ws://127.0.0.1/cams?x=1").unwrap();
        assert_eq!((u.ws, u.tcp, u.secure), (true, false, false));
        assert_eq!((u.port, u.path_string()), (80, "/cams".into()));
        assert_eq!(u.query, ["x=1"]);
        let u = Uri::parse("coap+ws://[::1]:8080").unwrap();
        assert_eq!((u.host.as_str(), u.port), ("::1", 8080));
        assert!(!Uri::parse("coap+tcp://x").unwrap().ws);
    }

    #[test]
    fn rfc7252_6_rejects_bad_uris() {
        assert!(matches!(Uri::parse("http://x/"), Err(UriError::Scheme(_))));
        assert!(matches!(Uri::parse("coap://x:0/"), Err(UriError::Port(_))));
        assert!(matches!(
            Uri::parse("coap://x:99999/"),
            Err(UriError::Port(_))
        ));
        // The message says what a port may be (issue 51, item 13).
        let e = Uri::parse("coap://x:99999/").expect_err("a bad port");
        assert!(
            e.to_string()
                .ends_with(": a port is a number from 1 to 65535"),
            "{e}"
        );
        assert!(matches!(Uri::parse("coap:///a"), Err(UriError::Host(_))));
        assert!(matches!(
            Uri::parse("coap://x/a%zz"),
            Err(UriError::Percent(_))
        ));
        assert!(matches!(
            Uri::parse("coap://x/a#f"),
            Err(UriError::Fragment(_))
        ));
    }
}
