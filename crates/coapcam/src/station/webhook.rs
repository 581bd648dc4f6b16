//! Webhooks (`serve --webhook URL`): every record of the results log POSTed as JSON to an
//! HTTP URL, in id order, each until it is answered 2xx. The position is a durable cursor
//! in the log (consumer [`CONSUMER`]), moved past a record only once the receiver took it:
//! a receiver that is down, a restart of the station, lose nothing; a record whose answer
//! was lost is sent again (receivers drop an `id` they have).
//!
//! Plain `http://` only (no TLS); HTTP/1.1 through hyper's client connection, one
//! connection kept while it works. A user and password in the URL
//! (`http://USER:PASSWORD@HOST/PATH`) go out as basic authentication, never in the Host
//! header or the log. Of an answer, only its status counts: its body is read up to
//! [`ANSWER_LIMIT`] and a longer one ends the connection.

use std::fmt;
use std::str::FromStr;
use std::time::Duration;

use base64::prelude::{BASE64_STANDARD, Engine as _};
use bytes::Bytes;
use http_body_util::{BodyExt as _, Full, Limited};
use hyper::client::conn::http1::SendRequest;
use hyper::header::{self, HeaderValue};
use hyper::{Method, Request, Uri};
use hyper_util::rt::TokioIo;
use tokio::net::TcpStream;
use tokio::task::JoinHandle;

use super::follow::{self, Feed, Next, Output, Sink, Start};
use super::log::ResultsLog;
use crate::api::record::Record;

/// The cursor name of the webhook in the results log.
pub const CONSUMER: &str = "webhook";

/// How long connecting, or one request's answer, may take.
const TIMEOUT: Duration = Duration::from_secs(10);
/// The most of an answer's body read; a receiver that sends more loses the connection
/// (the record still counts as taken when the status was 2xx).
pub const ANSWER_LIMIT: usize = 64 * 1024;

/// Where records are POSTed: an `http://[USER[:PASSWORD]@]HOST[:PORT][/PATH]` URL.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Target {
    /// The URL without its user and password.
    uri: Uri,
    host: String,
    port: u16,
    /// `Basic ...` of the URL's user and password.
    authorization: Option<HeaderValue>,
}

impl FromStr for Target {
    type Err = String;

    fn from_str(text: &str) -> Result<Self, String> {
        let uri: Uri = text
            .parse()
            .map_err(|e| format!("{text}: not a URL ({e})"))?;
        match uri.scheme_str() {
            Some("http") => {}
            Some(other) => {
                return Err(format!(
                    "{text}: a webhook is http:// ({other}:// is not supported)"
                ));
            }
            None => return Err(format!("{text}: a webhook URL is http://HOST[:PORT]/PATH")),
        }
        let host = uri
            .host()
            .ok_or_else(|| format!("{text}: the URL has no host"))?
            .trim_start_matches('[')
            .trim_end_matches(']')
            .to_owned();
        let port = uri.port_u16().unwrap_or(80);
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
                let bare: Uri = format!("http://{hostport}{path}")
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
    /// POST every record of the results log as JSON to this http:// URL (no TLS), in id
    /// order, each until it is answered 2xx (retrying 0.25 s, doubling to 5 s). The
    /// position is kept in the log (cursor `webhook`), so nothing is lost while the
    /// receiver is down or the station restarts; a record may come twice (same `id`).
    /// A new log's whole history is sent first. USER:PASSWORD@ goes out as basic
    /// authentication (never printed); an answer's body is read up to 64 KiB.
    #[arg(long, value_name = "http://[USER:PASSWORD@]HOST[:PORT]/PATH")]
    webhook: Option<Target>,
}

impl Args {
    /// Whether `--webhook` is given.
    pub(super) fn configured(&self) -> bool {
        self.webhook.is_some()
    }

    /// The webhook `--webhook` asks for.
    pub(super) async fn start(&self, feed: &Feed<'_>) -> anyhow::Result<Option<Box<dyn Output>>> {
        Ok(self
            .webhook
            .clone()
            .map(|target| Box::new(Webhook::start(target, feed.log.clone())) as Box<dyn Output>))
    }
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
        Self {
            task: tokio::spawn(follow::run(
                log,
                Hook {
                    target: target.clone(),
                    connection: None,
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
}

impl Sink for Hook {
    type Event = std::convert::Infallible;

    fn name(&self) -> String {
        format!("webhook: {}", self.target)
    }

    fn start(&self) -> Start {
        Start::Cursor(CONSUMER)
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
            connection => connection.insert(connect(&self.target).await?),
        };
        let body = serde_json::to_vec(record)
            .map_err(|e| format!("encoding record {}: {e}", record.id))?;
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

async fn connect(target: &Target) -> Result<SendRequest<Full<Bytes>>, String> {
    let stream = tokio::time::timeout(
        TIMEOUT,
        TcpStream::connect((target.host.as_str(), target.port)),
    )
    .await
    .map_err(|_| format!("connecting took over {TIMEOUT:?}"))?
    .map_err(|e| format!("connecting: {e}"))?;
    let _ = stream.set_nodelay(true);
    let (sender, connection) = hyper::client::conn::http1::handshake(TokioIo::new(stream))
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
    fn targets() {
        let t: Target = "http://127.0.0.1:9000/hook?x=1".parse().unwrap();
        assert_eq!((t.host.as_str(), t.port), ("127.0.0.1", 9000));
        let t: Target = "http://[::1]/h".parse().unwrap();
        assert_eq!((t.host.as_str(), t.port), ("::1", 80));
        assert!("https://example.invalid/".parse::<Target>().is_err());
        assert!("127.0.0.1:9000".parse::<Target>().is_err());
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
