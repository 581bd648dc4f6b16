//! The HTTP-CoAP proxy of `serve --http` (RFC 8075): `/hc/<coap URI>` (the default
//! mapping of §5.3, the target URI as it is or percent-encoded whole) forwards the request
//! to that CoAP server through coapcam's client, which does the block-wise transfers, and
//! maps back: the method (§6), the response code (§7, Table 4), Content-Format and media
//! type, ETag, Max-Age (as `Cache-Control: max-age`), Location-Path. 502 when the CoAP
//! side fails, 504 when it does not answer within [`TIMEOUT`].
//!
//! The mappings are functions without IO, tested here; the forwarding is in
//! `super::App`.

use std::time::Duration;

use coap::{Code, ContentFormat, OptionNumber, Options};
use hyper::{Method, StatusCode};

/// The most time a forwarded request may take, every block included: 504 after it.
pub const TIMEOUT: Duration = Duration::from_secs(15);

/// The most bytes of a CoAP response the proxy takes (502 beyond).
pub const MAX_RESPONSE: usize = 16 << 20;

/// The most bytes of a request body the proxy forwards (413 beyond).
pub const MAX_REQUEST: usize = 1 << 20;

/// The path prefix of the proxy.
pub const PREFIX: &str = "/hc/";

/// The target URI of a request-target under [`PREFIX`] (path and query): as written, or
/// percent-decoded when the scheme itself is encoded (`coap%3A%2F%2F...`).
pub fn target(path_and_query: &str) -> Option<String> {
    let rest = path_and_query.strip_prefix(PREFIX)?;
    let lower = rest.to_ascii_lowercase();
    if lower.starts_with("coap%3a") || lower.starts_with("coaps%3a") {
        let mut out = Vec::with_capacity(rest.len());
        let mut bytes = rest.bytes();
        while let Some(b) = bytes.next() {
            if b == b'%' {
                let hex = [bytes.next()?, bytes.next()?];
                out.push(u8::from_str_radix(std::str::from_utf8(&hex).ok()?, 16).ok()?);
            } else {
                out.push(b);
            }
        }
        return String::from_utf8(out).ok();
    }
    Some(rest.to_owned())
}

/// The CoAP method of an HTTP method (RFC 8075 §6; HEAD is a GET whose body is not
/// sent); `None` for the others (501).
pub fn method(m: &Method) -> Option<Code> {
    match *m {
        Method::GET | Method::HEAD => Some(Code::GET),
        Method::POST => Some(Code::POST),
        Method::PUT => Some(Code::PUT),
        Method::DELETE => Some(Code::DELETE),
        _ => None,
    }
}

/// The HTTP status of a CoAP response code (RFC 8075 §7, Table 4). `empty`: the response
/// has no payload (2.02 and 2.04 become 204 then).
pub fn status(code: Code, empty: bool) -> StatusCode {
    let (class, detail) = (code.0 >> 5, code.0 & 0x1f);
    match (class, detail) {
        (2, 1) => StatusCode::CREATED,
        (2, 2 | 4) if empty => StatusCode::NO_CONTENT,
        (2, 2 | 4 | 5) => StatusCode::OK,
        (2, 3) => StatusCode::NOT_MODIFIED,
        (2, _) => StatusCode::OK,
        // 4.01 Unauthorized: HTTP's 401 needs a WWW-Authenticate CoAP has no counterpart
        // of; 4.05 Method Not Allowed: HTTP's 405 needs an Allow header.
        (4, 1 | 3) => StatusCode::FORBIDDEN,
        (4, 4) => StatusCode::NOT_FOUND,
        (4, 6) => StatusCode::NOT_ACCEPTABLE,
        (4, 9) => StatusCode::CONFLICT,
        (4, 12) => StatusCode::PRECONDITION_FAILED,
        (4, 13) => StatusCode::PAYLOAD_TOO_LARGE,
        (4, 15) => StatusCode::UNSUPPORTED_MEDIA_TYPE,
        (4, 22) => StatusCode::UNPROCESSABLE_ENTITY,
        (4, 29) => StatusCode::TOO_MANY_REQUESTS,
        (4, _) => StatusCode::BAD_REQUEST,
        (5, 1) => StatusCode::NOT_IMPLEMENTED,
        // 5.05 Proxying Not Supported: the CoAP side could not serve it.
        (5, 2 | 5) => StatusCode::BAD_GATEWAY,
        (5, 3) => StatusCode::SERVICE_UNAVAILABLE,
        (5, 4) => StatusCode::GATEWAY_TIMEOUT,
        _ => StatusCode::INTERNAL_SERVER_ERROR,
    }
}

/// The media type of a Content-Format: the registered ones, then coapcam's own
/// (experimental numbers, `repr::FORMATS`), else `application/octet-stream`.
pub fn media_type(cf: ContentFormat) -> String {
    cf.media_type()
        .map(str::to_owned)
        .or_else(|| {
            crate::repr::FORMATS
                .iter()
                .find(|f| f.format == cf)
                .map(|f| f.media_type.to_owned())
        })
        .unwrap_or_else(|| "application/octet-stream".to_owned())
}

/// The Content-Format of a media type (parameters kept for `text/plain;charset=utf-8`,
/// else dropped), or `None` when CoAP has no number for it.
pub fn content_format(media_type: &str) -> Option<ContentFormat> {
    ContentFormat::from_media_type(media_type)
        .or_else(|| {
            let bare = media_type.split(';').next().unwrap_or("").trim();
            ContentFormat::from_media_type(bare).or_else(|| {
                bare.eq_ignore_ascii_case("text/plain")
                    .then_some(ContentFormat(0))
            })
        })
        .or_else(|| {
            let bare = media_type.split(';').next().unwrap_or("").trim();
            crate::repr::FORMATS
                .iter()
                .find(|f| f.media_type.eq_ignore_ascii_case(bare))
                .map(|f| f.format)
        })
}

/// The first media type of an Accept header CoAP has a number for (`*/*` and unknown
/// ones skipped).
pub fn accept(header: &str) -> Option<ContentFormat> {
    header
        .split(',')
        .map(|item| item.split(';').next().unwrap_or("").trim())
        .filter(|t| !t.contains('*'))
        .find_map(content_format)
}

/// An HTTP entity tag of a CoAP ETag: its bytes in hex, quoted.
pub fn etag(bytes: &[u8]) -> String {
    let hex: String = bytes.iter().map(|b| format!("{b:02x}")).collect();
    format!("\"{hex}\"")
}

/// The CoAP ETags of an HTTP `If-Match` or `If-None-Match` list of [`etag`]s (weak and
/// foreign tags skipped; `*` gives none).
pub fn etags(header: &str) -> Vec<Vec<u8>> {
    header
        .split(',')
        .filter_map(|t| {
            let hex = t.trim().strip_prefix('"')?.strip_suffix('"')?;
            if hex.len() % 2 != 0 || hex.len() > 16 || hex.is_empty() {
                return None;
            }
            (0..hex.len())
                .step_by(2)
                .map(|i| u8::from_str_radix(&hex[i..i + 2], 16).ok())
                .collect()
        })
        .collect()
}

/// The `Cache-Control` of a response's Max-Age (60 s when absent, RFC 7252 §5.10.5).
pub fn cache_control(options: &Options) -> String {
    let max_age = options.uint(OptionNumber::MAX_AGE).unwrap_or(60);
    format!("max-age={max_age}")
}

/// The HTTP `Location` of a response's Location-Path and Location-Query: the resource
/// on `authority` (`host:port`) through this proxy.
pub fn location(options: &Options, scheme: &str, authority: &str) -> Option<String> {
    let path: Vec<String> = options
        .values(OptionNumber::LOCATION_PATH)
        .map(|s| String::from_utf8_lossy(s).into_owned())
        .collect();
    let query: Vec<String> = options
        .values(OptionNumber::LOCATION_QUERY)
        .map(|s| String::from_utf8_lossy(s).into_owned())
        .collect();
    if path.is_empty() && query.is_empty() {
        return None;
    }
    let mut loc = format!("{PREFIX}{scheme}://{authority}/{}", path.join("/"));
    if !query.is_empty() {
        loc.push('?');
        loc.push_str(&query.join("&"));
    }
    Some(loc)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn targets_methods_and_codes() {
        assert_eq!(
            target("/hc/coap://127.0.0.1:5683/.well-known/core?rt=x").as_deref(),
            Some("coap://127.0.0.1:5683/.well-known/core?rt=x")
        );
        assert_eq!(
            target("/hc/coap%3A%2F%2F%5B%3A%3A1%5D%2Fa").as_deref(),
            Some("coap://[::1]/a")
        );
        assert_eq!(target("/api/x"), None);
        assert_eq!(method(&Method::HEAD), Some(Code::GET));
        assert_eq!(method(&Method::PATCH), None);
        assert_eq!(status(Code::CONTENT, false), StatusCode::OK);
        assert_eq!(status(Code::CHANGED, true), StatusCode::NO_CONTENT);
        assert_eq!(status(Code::CREATED, true), StatusCode::CREATED);
        assert_eq!(status(Code::VALID, true), StatusCode::NOT_MODIFIED);
        assert_eq!(status(Code::NOT_FOUND, false), StatusCode::NOT_FOUND);
        assert_eq!(status(Code::UNAUTHORIZED, false), StatusCode::FORBIDDEN);
        assert_eq!(status(Code::BAD_OPTION, false), StatusCode::BAD_REQUEST);
        assert_eq!(
            status(Code::REQUEST_ENTITY_TOO_LARGE, false),
            StatusCode::PAYLOAD_TOO_LARGE
        );
        assert_eq!(
            status(Code::PROXYING_NOT_SUPPORTED, false),
            StatusCode::BAD_GATEWAY
        );
        assert_eq!(
            status(Code::SERVICE_UNAVAILABLE, false),
            StatusCode::SERVICE_UNAVAILABLE
        );
    }

    #[test]
    fn formats_tags_and_ages() {
        assert_eq!(
            media_type(ContentFormat::LINK_FORMAT),
            "application/link-format"
        );
        assert_eq!(media_type(ContentFormat(65100)), "application/x-ply");
        assert_eq!(media_type(ContentFormat(65000)), "application/octet-stream");
        assert_eq!(
            content_format("application/json; charset=utf-8"),
            Some(ContentFormat::JSON)
        );
        assert_eq!(content_format("text/plain"), Some(ContentFormat(0)));
        assert_eq!(content_format("application/x-unknown"), None);
        assert_eq!(
            accept("text/html, */*;q=0.8, image/png"),
            Some(ContentFormat::IMAGE_PNG)
        );
        assert_eq!(accept("*/*"), None);
        assert_eq!(etag(&[0xab, 0x01]), "\"ab01\"");
        assert_eq!(etags("\"ab01\", W/\"x\", \"zz\""), vec![vec![0xab, 0x01]]);
        let mut o = Options::new();
        assert_eq!(cache_control(&o), "max-age=60");
        o.set_uint(OptionNumber::MAX_AGE, 5);
        assert_eq!(cache_control(&o), "max-age=5");
        o.push(OptionNumber::LOCATION_PATH, b"files");
        o.push(OptionNumber::LOCATION_PATH, b"x1");
        assert_eq!(
            location(&o, "coap", "127.0.0.1:5683").as_deref(),
            Some("/hc/coap://127.0.0.1:5683/files/x1")
        );
    }
}
