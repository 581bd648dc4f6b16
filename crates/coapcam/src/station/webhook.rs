//! Webhooks (`serve --webhook URL`): every record of the results log POSTed as JSON to an
//! HTTP URL, in id order, each until it is answered 2xx. The position is a durable cursor
//! in the log (consumer [`CONSUMER`]), moved past a record only once the receiver took it:
//! a receiver that is down, a restart of the station, lose nothing; a record whose answer
//! was lost is sent again (receivers drop an `id` they have).
//!
//! `http://`, or `https://` (TLS on OpenSSL, [`super::tls`]: the server's certificate
//! checked against the system's trust store and the URL's host); HTTP/1.1 through
//! hyper's client connection, one connection kept while it works. A user and password in the URL
//! (`http://USER:PASSWORD@HOST/PATH`) go out as basic authentication, never in the Host
//! header or the log. Of an answer, only its status counts: its body is read up to
//! [`ANSWER_LIMIT`] and a longer one ends the connection.
//!
//! With a secret (`--webhook-secret-file`) each POST is signed: [`SIGNATURE_HEADER`] is
//! `t=UNIX,v1=HEX`, HEX the HMAC-SHA256 (RFC 2104) under the secret of the time, a dot
//! and the body, the convention of the large webhook senders. With a template
//! (`--webhook-template`, a [`Template`]) the body is the receiver's own fields.

use std::fmt;
use std::path::{Path, PathBuf};
use std::str::FromStr;
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use base64::prelude::{BASE64_STANDARD, Engine as _};
use bytes::Bytes;
use http_body_util::{BodyExt as _, Full, Limited};
use hyper::client::conn::http1::SendRequest;
use hyper::header::{self, HeaderValue};
use hyper::{Method, Request, Uri};
use hyper_util::rt::TokioIo;
use openssl::ssl::SslConnector;
use serde_json::Value;
use sha2::{Digest as _, Sha256};
use tokio::net::TcpStream;
use tokio::task::JoinHandle;

use super::follow::{self, Feed, Next, Output, OutputId, Sink, Start};
use super::log::ResultsLog;
use crate::api::record::Record;

/// The cursor name in the results log of the webhook its flag gives (of one with an `id`
/// of its own: `webhook/ID`).
pub const CONSUMER: &str = "webhook";

/// How long connecting, or one request's answer, may take.
const TIMEOUT: Duration = Duration::from_secs(10);
/// The most of an answer's body read; a receiver that sends more loses the connection
/// (the record still counts as taken when the status was 2xx).
pub const ANSWER_LIMIT: usize = 64 * 1024;
/// The header of the signature: `t=UNIX,v1=HEX`.
pub const SIGNATURE_HEADER: &str = "x-coapcam-signature";

/// Where records are POSTed: an `http[s]://[USER[:PASSWORD]@]HOST[:PORT][/PATH]` URL.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Target {
    /// The URL without its user and password.
    uri: Uri,
    host: String,
    port: u16,
    /// `https://`: over TLS.
    tls: bool,
    /// `Basic ...` of the URL's user and password.
    authorization: Option<HeaderValue>,
}

impl FromStr for Target {
    type Err = String;

    fn from_str(text: &str) -> Result<Self, String> {
        let uri: Uri = text
            .parse()
            .map_err(|e| format!("{text}: not a URL ({e})"))?;
        let tls = match uri.scheme_str() {
            Some("http") => false,
            Some("https") => true,
            Some(other) => {
                return Err(format!(
                    "{text}: a webhook is http:// or https:// ({other}:// is not supported)"
                ));
            }
            None => {
                return Err(format!(
                    "{text}: a webhook URL is http[s]://HOST[:PORT]/PATH"
                ));
            }
        };
        let host = uri
            .host()
            .ok_or_else(|| format!("{text}: the URL has no host"))?
            .trim_start_matches('[')
            .trim_end_matches(']')
            .to_owned();
        let port = uri.port_u16().unwrap_or(if tls { 443 } else { 80 });
        let (uri, authorization) = match uri.authority().map(|a| a.as_str()) {
            Some(authority) if authority.contains('@') => {
                let (userinfo, hostport) = authority.rsplit_once('@').unwrap_or_default();
                let (user, password) = userinfo.split_once(':').unwrap_or((userinfo, ""));
                let decode = |part: &str| {
                    coap_net::uri::percent_decode(part).ok_or_else(|| {
                        "the URL's user or password is not percent-encoded UTF-8".to_owned()
                    })
                };
                let credentials = format!("{}:{}", decode(user)?, decode(password)?);
                let value = format!("Basic {}", BASE64_STANDARD.encode(credentials));
                let mut value = HeaderValue::from_str(&value)
                    .map_err(|_| "the URL's user or password cannot be sent".to_owned())?;
                value.set_sensitive(true);
                let path = uri.path_and_query().map_or("/", |p| p.as_str());
                let scheme = if tls { "https" } else { "http" };
                let bare: Uri = format!("{scheme}://{hostport}{path}")
                    .parse()
                    .map_err(|e| format!("the URL without its user: {e}"))?;
                (bare, Some(value))
            }
            _ => (uri, None),
        };
        Ok(Self {
            uri,
            host,
            port,
            tls,
            authorization,
        })
    }
}

impl fmt::Display for Target {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}", self.uri)
    }
}

/// The flag of the webhook (`serve --webhook`).
#[derive(Debug, Clone, Default, clap::Args)]
#[group(skip)]
pub struct Args {
    /// POST every record of the results log as JSON to this http:// or https:// URL (TLS:
    /// the server's certificate checked against the system's trust store), in id order,
    /// each until it is answered 2xx (retrying 0.25 s, doubling to 5 s). The position
    /// is kept in the log (cursor `webhook`), so nothing is lost while the
    /// receiver is down or the station restarts; a record may come twice (same `id`).
    /// A new log's whole history is sent first. USER:PASSWORD@ goes out as basic
    /// authentication (never printed); an answer's body is read up to 64 KiB.
    #[arg(long, value_name = "http[s]://[USER:PASSWORD@]HOST[:PORT]/PATH")]
    webhook: Option<Target>,
    /// With --webhook: sign each POST with the secret this file holds (its bytes, without
    /// a final line break): the header X-Coapcam-Signature: t=UNIX,v1=HEX, HEX the
    /// HMAC-SHA256 of "UNIX.BODY" (UNIX the sending time in seconds). Keep the file
    /// readable by the station only.
    #[arg(long, value_name = "FILE", requires = "webhook")]
    webhook_secret_file: Option<PathBuf>,
    /// With --webhook: POST this JSON object instead of the record, each string value
    /// replaced by the record's value at that JSON Pointer (RFC 6901), e.g. {"barcode":
    /// "/measurement/codes/0/text", "length": "/measurement/length_mm"}; one that points
    /// at nothing is null, other values are sent as they are (docs/station.md).
    #[arg(long, value_name = "FILE", requires = "webhook")]
    webhook_template: Option<PathBuf>,
}

impl Args {
    /// Whether `--webhook` is given.
    pub(super) fn configured(&self) -> bool {
        self.webhook.is_some()
    }

    /// The webhook `--webhook` asks for, as output `id` (its cursor's name).
    pub(super) async fn start(
        &self,
        feed: &Feed<'_>,
        id: &OutputId,
    ) -> Result<Option<Box<dyn Output>>, SetupError> {
        let Some(target) = self.webhook.clone() else {
            return Ok(None);
        };
        let secret = match &self.webhook_secret_file {
            Some(path) => Some(read_secret(path)?),
            None => None,
        };
        let template = match &self.webhook_template {
            Some(path) => Some(Template::load(path)?),
            None => None,
        };
        let body = Body { secret, template };
        Ok(Some(Box::new(Webhook::start_with(
            target,
            feed.log.clone(),
            body,
            id.cursor(CONSUMER),
        ))))
    }
}

/// The webhook's secret or template could not be read.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum SetupError {
    /// A file (the secret, the template) could not be read.
    #[error("reading {}", path.display())]
    File {
        /// The file.
        path: PathBuf,
        /// Why.
        source: std::io::Error,
    },
    /// The secret file holds nothing but line breaks.
    #[error("{}: the webhook's secret is empty", .0.display())]
    EmptySecret(PathBuf),
    /// The template is not one (the JSON parser's or the template's words).
    #[error("{}: {reason}", path.display())]
    Template {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        reason: String,
    },
}

/// The secret in the file at `path`: its bytes without a final line break; never empty.
fn read_secret(path: &Path) -> Result<Vec<u8>, SetupError> {
    let mut secret = std::fs::read(path).map_err(|source| SetupError::File {
        path: path.to_owned(),
        source,
    })?;
    while secret.last().is_some_and(|b| matches!(b, b'\n' | b'\r')) {
        secret.pop();
    }
    if secret.is_empty() {
        return Err(SetupError::EmptySecret(path.to_owned()));
    }
    Ok(secret)
}

/// A body of the receiver's own: a JSON object whose string values are JSON Pointers
/// (RFC 6901) into the record's JSON, replaced by what they point at (null for
/// nothing); objects inside are templates too; other values stay as they are.
#[derive(Debug, Clone, PartialEq)]
pub struct Template(serde_json::Map<String, Value>);

impl Template {
    /// The template of `text`: a JSON object whose pointers start with `/`.
    pub fn parse(text: &str) -> Result<Self, String> {
        let value: Value = serde_json::from_str(text).map_err(|e| e.to_string())?;
        let Value::Object(map) = value else {
            return Err("a template is a JSON object".into());
        };
        fn check(map: &serde_json::Map<String, Value>) -> Result<(), String> {
            for (key, value) in map {
                match value {
                    Value::String(p) if !p.starts_with('/') => {
                        return Err(format!(
                            "`{key}`: {p:?} is no JSON Pointer (they start with /, e.g. \"/measurement/length_mm\")"
                        ));
                    }
                    Value::Object(inner) => check(inner)?,
                    _ => {}
                }
            }
            Ok(())
        }
        check(&map)?;
        Ok(Self(map))
    }

    /// The template in the file at `path`.
    pub fn load(path: &Path) -> Result<Self, SetupError> {
        let text = std::fs::read_to_string(path).map_err(|source| SetupError::File {
            path: path.to_owned(),
            source,
        })?;
        Self::parse(&text).map_err(|reason| SetupError::Template {
            path: path.to_owned(),
            reason,
        })
    }

    /// The body for `record` (its JSON).
    pub fn fill(&self, record: &Value) -> Value {
        fn fill(map: &serde_json::Map<String, Value>, record: &Value) -> Value {
            Value::Object(
                map.iter()
                    .map(|(k, v)| {
                        let v = match v {
                            Value::String(p) => record.pointer(p).cloned().unwrap_or(Value::Null),
                            Value::Object(inner) => fill(inner, record),
                            other => other.clone(),
                        };
                        (k.clone(), v)
                    })
                    .collect(),
            )
        }
        fill(&self.0, record)
    }
}

/// What a webhook POSTs for a record and how it signs it.
#[derive(Debug, Clone, Default)]
pub struct Body {
    /// The shared secret of the signature; none: unsigned.
    pub secret: Option<Vec<u8>>,
    /// The receiver's fields; none: the record's JSON.
    pub template: Option<Template>,
}

/// HMAC-SHA256 (RFC 2104) of `message` under `key`.
pub fn hmac_sha256(key: &[u8], message: &[u8]) -> [u8; 32] {
    const BLOCK: usize = 64;
    let mut block = [0u8; BLOCK];
    if key.len() > BLOCK {
        block[..32].copy_from_slice(&Sha256::digest(key));
    } else {
        block[..key.len()].copy_from_slice(key);
    }
    let pad = |byte: u8| block.map(|b| b ^ byte);
    let inner = Sha256::new()
        .chain_update(pad(0x36))
        .chain_update(message)
        .finalize();
    Sha256::new()
        .chain_update(pad(0x5c))
        .chain_update(inner)
        .finalize()
        .into()
}

/// The value of [`SIGNATURE_HEADER`] for `body` sent at `unix` seconds.
pub fn signature(secret: &[u8], unix: u64, body: &[u8]) -> String {
    let mut message = format!("{unix}.").into_bytes();
    message.extend_from_slice(body);
    let hex: String = hmac_sha256(secret, &message)
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect();
    format!("t={unix},v1={hex}")
}

/// The webhook's task: delivering until dropped.
#[derive(Debug)]
pub struct Webhook {
    task: JoinHandle<()>,
    /// The receiver, as said when the station starts.
    target: Target,
}

impl Output for Webhook {
    fn describe(&self) -> String {
        format!("webhook to {}", self.target)
    }
}

impl Drop for Webhook {
    fn drop(&mut self) {
        self.task.abort();
    }
}

impl Webhook {
    /// Delivers the records of `log` after its cursor to `target`, then each new one.
    pub fn start(target: Target, log: ResultsLog) -> Self {
        Self::start_with(target, log, Body::default(), CONSUMER.to_owned())
    }

    /// As [`Webhook::start`], each record's body made and signed as `body` says, its
    /// position kept in the cursor named `cursor`.
    pub fn start_with(target: Target, log: ResultsLog, body: Body, cursor: String) -> Self {
        Self {
            task: tokio::spawn(follow::run(
                log,
                Hook {
                    target: target.clone(),
                    connection: None,
                    tls: None,
                    body,
                    cursor,
                },
            )),
            target,
        }
    }
}

/// The webhook as a [`Sink`]: a record per POST, over one connection while it works.
struct Hook {
    target: Target,
    connection: Option<SendRequest<Full<Bytes>>>,
    /// For an `https://` target: the TLS context, made at its first connection and kept
    /// for the others (it reads the trust store).
    tls: Option<SslConnector>,
    body: Body,
    /// Its durable cursor's name.
    cursor: String,
}

impl Sink for Hook {
    type Event = std::convert::Infallible;

    fn name(&self) -> String {
        format!(
            "{}: {}",
            super::output_name("webhook", &self.cursor),
            self.target
        )
    }

    fn start(&self) -> Start {
        Start::Cursor(self.cursor.clone())
    }

    async fn deliver(&mut self, record: &Record) -> Next {
        match self.post(record).await {
            Ok(()) => Next::Go,
            Err(why) => {
                self.connection = None;
                Next::Retry(why)
            }
        }
    }

    async fn handle(&mut self, event: Self::Event) -> Next {
        match event {}
    }
}

impl Hook {
    /// POSTs `record`; done when answered 2xx.
    async fn post(&mut self, record: &Record) -> Result<(), String> {
        let usable = match self.connection.as_mut() {
            Some(sender) => sender.ready().await.is_ok(),
            None => false,
        };
        let sender = match &mut self.connection {
            Some(sender) if usable => sender,
            connection => connection.insert(connect(&self.target, &mut self.tls).await?),
        };
        let encoded = match &self.body.template {
            Some(template) => serde_json::to_value(record)
                .and_then(|json| serde_json::to_vec(&template.fill(&json))),
            None => serde_json::to_vec(record),
        };
        let body = encoded.map_err(|e| format!("encoding record {}: {e}", record.id))?;
        let signed = self.body.secret.as_deref().map(|secret| {
            let unix = SystemTime::now()
                .duration_since(UNIX_EPOCH)
                .map_or(0, |d| d.as_secs());
            signature(secret, unix, &body)
        });
        let mut request = Request::builder()
            .method(Method::POST)
            .uri(self.target.uri.path_and_query().map_or("/", |p| p.as_str()))
            .header(header::CONTENT_TYPE, "application/json")
            .header(
                header::USER_AGENT,
                concat!("coapcam/", env!("CARGO_PKG_VERSION")),
            )
            .header("x-coapcam-record", record.id)
            .body(Full::new(Bytes::from(body)))
            .map_err(|e| format!("the request: {e}"))?;
        if let Some(authority) = self.target.uri.authority()
            && let Ok(host) = HeaderValue::from_str(authority.as_str())
        {
            request.headers_mut().insert(header::HOST, host);
        }
        if let Some(signed) = signed
            && let Ok(value) = HeaderValue::from_str(&signed)
        {
            request.headers_mut().insert(SIGNATURE_HEADER, value);
        }
        if let Some(authorization) = &self.target.authorization {
            request
                .headers_mut()
                .insert(header::AUTHORIZATION, authorization.clone());
        }
        let answer = tokio::time::timeout(TIMEOUT, sender.send_request(request))
            .await
            .map_err(|_| format!("no answer within {TIMEOUT:?}"))?
            .map_err(|e| format!("sending record {}: {e}", record.id))?;
        let status = answer.status();
        // The answer's body is read (so that the connection can carry the next record) up
        // to a bound, and dropped; a longer or slower one ends the connection.
        let body = Limited::new(answer.into_body(), ANSWER_LIMIT);
        if !matches!(
            tokio::time::timeout(TIMEOUT, body.collect()).await,
            Ok(Ok(_))
        ) {
            tracing::debug!("webhook: the answer to record {} was cut off", record.id);
            self.connection = None;
        }
        if !status.is_success() {
            return Err(format!("record {} answered {status}", record.id));
        }
        Ok(())
    }
}

/// A connection to `target`; over TLS with the context in `tls` (made there when it is
/// none yet) for an `https://` one.
async fn connect(
    target: &Target,
    tls: &mut Option<SslConnector>,
) -> Result<SendRequest<Full<Bytes>>, String> {
    let stream = tokio::time::timeout(
        TIMEOUT,
        TcpStream::connect((target.host.as_str(), target.port)),
    )
    .await
    .map_err(|_| format!("connecting took over {TIMEOUT:?}"))?
    .map_err(|e| format!("connecting: {e}"))?;
    let _ = stream.set_nodelay(true);
    if target.tls {
        let connector = match tls {
            Some(connector) => connector,
            none => none.insert(super::tls::connector()?),
        };
        let tls = tokio::time::timeout(
            TIMEOUT,
            super::tls::connect(connector, stream, &target.host),
        )
        .await
        .map_err(|_| format!("the TLS handshake took over {TIMEOUT:?}"))??;
        handshake(tls).await
    } else {
        handshake(stream).await
    }
}

/// The HTTP/1.1 connection over `io`, driven by a task of its own.
async fn handshake<T>(io: T) -> Result<SendRequest<Full<Bytes>>, String>
where
    T: tokio::io::AsyncRead + tokio::io::AsyncWrite + Send + Unpin + 'static,
{
    let (sender, connection) = hyper::client::conn::http1::handshake(TokioIo::new(io))
        .await
        .map_err(|e| format!("HTTP handshake: {e}"))?;
    tokio::spawn(async move {
        if let Err(e) = connection.await {
            tracing::debug!("webhook: connection: {e}");
        }
    });
    Ok(sender)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn two_webhooks_to_one_url_say_in_their_messages_which_they_are() {
        let target: Target = "http://127.0.0.1:9/in".parse().unwrap();
        let hook = |cursor: &str| Hook {
            target: target.clone(),
            connection: None,
            tls: None,
            body: Body::default(),
            cursor: cursor.into(),
        };
        // The name starts every message of `follow::run`: its failures, its backlog.
        assert_eq!(hook(CONSUMER).name(), "webhook: http://127.0.0.1:9/in");
        assert_eq!(
            hook("webhook/wms").name(),
            "webhook `wms`: http://127.0.0.1:9/in"
        );
    }

    #[test]
    fn targets() {
        let t: Target = "http://127.0.0.1:9000/hook?x=1".parse().unwrap();
        assert_eq!((t.host.as_str(), t.port), ("127.0.0.1", 9000));
        let t: Target = "http://[::1]/h".parse().unwrap();
        assert_eq!((t.host.as_str(), t.port), ("::1", 80));
        let t: Target = "https://example.invalid/hook".parse().unwrap();
        assert_eq!(
            (t.host.as_str(), t.port, t.tls),
            ("example.invalid", 443, true)
        );
        assert!("ftp://example.invalid/".parse::<Target>().is_err());
        assert!("127.0.0.1:9000".parse::<Target>().is_err());
    }

    /// RFC 4231's test cases 1, 2 and 6 (a key longer than a block).
    #[test]
    fn hmac_sha256_gives_rfc_4231s_values() {
        let hex = |b: [u8; 32]| b.iter().map(|b| format!("{b:02x}")).collect::<String>();
        assert_eq!(
            hex(hmac_sha256(&[0x0b; 20], b"Hi There")),
            "b0344c61d8db38535ca8afceaf0bf12b881dc200c9833da726e9376c2e32cff7"
        );
        assert_eq!(
            hex(hmac_sha256(b"Jefe", b"what do ya want for nothing?")),
            "5bdcc146bf60754e6a042426089575c75a003f089d2739839dec58b964ec3843"
        );
        assert_eq!(
            hex(hmac_sha256(
                &[0xaa; 131],
                b"Test Using Larger Than Block-Size Key - Hash Key First"
            )),
            "60e431591ee0b67f0d8a26aacbf5b77f8e0bc6213728c5140546040f0ee37f54"
        );
        let s = signature(b"Jefe", 1_700_000_000, b"{}");
        assert!(
            s.starts_with("t=1700000000,v1=") && s.len() == 16 + 64,
            "{s}"
        );
    }

    #[test]
    fn a_template_takes_the_records_fields_by_pointer() {
        let t = Template::parse(
            r#"{"barcode": "/measurement/codes/0/text", "length": "/measurement/length_mm",
                "unit": 1, "site": {"station": "/station"}, "none": "/no/such"}"#,
        )
        .unwrap();
        let record = serde_json::json!({
            "station": "dock-1",
            "measurement": {"length_mm": 400.5, "codes": [{"text": "PKG-1"}]}
        });
        assert_eq!(
            t.fill(&record),
            serde_json::json!({"barcode": "PKG-1", "length": 400.5, "unit": 1,
                               "site": {"station": "dock-1"}, "none": null})
        );
        assert!(Template::parse("[1]").is_err());
        assert!(Template::parse(r#"{"length": "length_mm"}"#).is_err());
        assert!(Template::parse("{").is_err());
    }

    #[test]
    fn a_user_and_password_are_basic_authentication_and_never_shown() {
        let t: Target = "http://station:s%40cret@127.0.0.1:9000/hook"
            .parse()
            .unwrap();
        assert_eq!(t.to_string(), "http://127.0.0.1:9000/hook");
        assert_eq!(
            t.uri.authority().map(|a| a.as_str()),
            Some("127.0.0.1:9000")
        );
        let value = t.authorization.expect("credentials");
        // base64("station:s@cret")
        assert_eq!(value.to_str().unwrap(), "Basic c3RhdGlvbjpzQGNyZXQ=");
        assert!(value.is_sensitive());
        assert!(!format!("{:?}", t.uri).contains("cret"));
    }
}
