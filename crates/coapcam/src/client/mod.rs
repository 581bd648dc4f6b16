//! The typed camera client: what `grab`, `measure`, `monitor` and `demo` ask of a
//! coapcam server (the resource API of docs/design.md §5), over one `coap_net::Client`,
//! and what is built on it: measuring, reading the parcel's codes, the annotated picture.

pub mod annotate;
pub mod calibrate;
pub mod clocks;
pub mod codes;
pub mod frames;
pub mod live;
pub mod measure;
pub mod results;
pub mod rtt_cache;
pub mod timed;

use std::net::{IpAddr, SocketAddr};
use std::sync::Arc;
use std::time::Duration;

use bytes::Bytes;
use coap::link_format;
use coap::{Code, ContentFormat, EndpointConfig, OptionNumber, Request, Response};
use coap_net::{Client, Psk, Uri};

use crate::report::{EdgeQuery, Measurement, MeasurementError};
use crate::repr::packet::DepthImage;
use crate::repr::{self, DecodeError, Stream, cbor};
use crate::timesync::SERVER_TIME;

/// A client for `server`, its transport chosen by `uri`'s scheme: a plain socket for
/// `coap://`, DTLS with `psk` for `coaps://`, a TCP connection for `coap+tcp://` (TLS
/// with `psk` on it for `coaps+tcp://`), a WebSocket for `coap+ws://` (over TLS with
/// `psk` for `coaps+ws://`). Every command that takes a server URI comes here, so each
/// speaks every scheme.
pub fn secured_client(
    uri: &Uri,
    server: SocketAddr,
    config: EndpointConfig,
    psk: Option<&Psk>,
) -> Result<Client, ConnectError> {
    let scheme = match (uri.secure, uri.tcp, uri.ws) {
        (true, true, _) => "coaps+tcp",
        (true, _, true) => "coaps+ws",
        _ => "coaps",
    };
    let psk = match (uri.secure, psk) {
        (true, None) => return Err(ConnectError::NoKey(scheme)),
        (true, psk) => psk,
        (false, _) => None,
    };
    match (uri.tcp, uri.ws, psk) {
        (true, _, None) => return Ok(Client::tcp(&config)),
        (_, true, None) => return Ok(Client::ws(&config)),
        (true, _, Some(key)) => return Client::tls(&config, key).map_err(ConnectError::Tls),
        (_, true, Some(key)) => return Client::wss(&config, key).map_err(ConnectError::Tls),
        (false, false, _) => {}
    }
    let client = Client::for_peer_secured(server, config, psk).map_err(ConnectError::Bind)?;
    if !server.ip().is_multicast() {
        rtt_cache::seed(&client, server);
    }
    Ok(client)
}

/// The longest Max-Age of a 5.03 that [`CamClient`] waits out and asks again after.
const BUSY_RETRY: Duration = Duration::from_secs(5);

/// A client of one coapcam server.
pub struct CamClient {
    client: Client,
    server: SocketAddr,
    timeout: Duration,
    /// What shows the progress of answers, when the command shows it.
    progress: Option<Arc<dyn ShowProgress>>,
    /// What this client learnt of its servers' clocks and cameras.
    clocks: Arc<clocks::Clocks>,
}

/// What shows the progress of a client's transfers (the command line's bars; the library
/// draws nothing itself).
pub trait ShowProgress: Send + Sync {
    /// A watcher of one transfer: told `(done, total)` as its body arrives, dropped when
    /// it ends.
    fn watch(&self) -> Box<dyn WatchProgress>;
}

/// The watcher of one transfer's progress ([`ShowProgress::watch`]).
pub trait WatchProgress: Send {
    /// `done` bytes of `total` (when known) have arrived.
    fn show(&mut self, done: usize, total: Option<usize>);
}

impl CamClient {
    /// A client for the server at `uri` (`coap://host[:port]`, or any other scheme
    /// [`secured_client`] takes); every request gives up after `timeout`.
    pub async fn connect(
        uri: &str,
        config: EndpointConfig,
        psk: Option<&Psk>,
        timeout: Duration,
    ) -> Result<Self, ConnectError> {
        let uri = Uri::parse(uri)?;
        let server = uri
            .resolve()
            .await
            .map_err(|source| ConnectError::Resolve {
                host: uri.host.clone(),
                source,
            })?;
        let client = secured_client(&uri, server, config, psk)?;
        Ok(Self {
            client,
            server,
            timeout,
            progress: None,
            clocks: Arc::default(),
        })
    }

    /// A plain CoAP client of the server at `server` (an in-process one, for `demo` and
    /// the benchmarks), with the default transmission parameters and message IDs and
    /// tokens of its own ([`coap_net::fresh_seed`]).
    pub fn at(server: SocketAddr, timeout: Duration) -> Result<Self, ConnectError> {
        let config = EndpointConfig {
            rng_seed: coap_net::fresh_seed(),
            ..EndpointConfig::default()
        };
        let client = Client::for_peer(server, config).map_err(ConnectError::Bind)?;
        Ok(Self {
            client,
            server,
            timeout,
            progress: None,
            clocks: Arc::default(),
        })
    }

    /// Shows the progress of every answer through `progress`.
    #[must_use]
    pub fn with_progress(mut self, progress: Arc<dyn ShowProgress>) -> Self {
        self.progress = Some(progress);
        self
    }

    /// A client for requests to the multicast group `group` (answers come from each
    /// server's unicast address), sending from `bind` if given. The unicast follow-ups of
    /// block-wise answers must leave from the address the multicast request left from (a
    /// server keeps an answer for the peer that asked); on loopback an unbound socket sends
    /// each follow-up from the server's own 127.0.0.N, so bind 127.0.0.1 there.
    pub fn for_group(
        group: SocketAddr,
        bind: Option<IpAddr>,
        config: EndpointConfig,
        timeout: Duration,
    ) -> Result<Self, ConnectError> {
        let client = match bind {
            Some(ip) => Client::bind(SocketAddr::new(ip, 0), config)
                .map_err(|source| ConnectError::BindTo { ip, source })?,
            None => Client::for_peer(group, config).map_err(ConnectError::Bind)?,
        };
        Ok(Self {
            client,
            server: group,
            timeout,
            progress: None,
            clocks: Arc::default(),
        })
    }

    /// A client of `server` sharing `other`'s socket and timeout.
    pub fn unicast(other: &Self, server: SocketAddr) -> Self {
        rtt_cache::seed(&other.client, server);
        Self {
            client: other.client.clone(),
            server,
            timeout: other.timeout,
            progress: other.progress.clone(),
            clocks: other.clocks.clone(),
        }
    }

    /// The server's address.
    pub fn server(&self) -> SocketAddr {
        self.server
    }

    /// The underlying CoAP client (for multicast requests).
    pub fn coap(&self) -> &Client {
        &self.client
    }

    /// What this client (and every client sharing its socket) learnt of its servers'
    /// clocks and cameras.
    pub fn clocks(&self) -> &clocks::Clocks {
        &self.clocks
    }

    /// Sends `method path` and returns the response if it is a 2.xx whose body arrived
    /// whole; any other code becomes an error carrying the code and the diagnostic.
    pub async fn call(
        &self,
        method: Code,
        path: &str,
        payload: Bytes,
        content_format: Option<ContentFormat>,
        accept: Option<ContentFormat>,
    ) -> Result<Response, CallError> {
        let request = self.request(method, path, payload, content_format, accept);
        let what = format!("{} {path}", method.name().unwrap_or("request"));
        self.exchange(request, &what).await
    }

    /// Sends `request` (`what` names it in errors) and returns the response if it is a
    /// 2.xx whose body arrived whole. A server that is busy for a few seconds (5.03 with
    /// Max-Age up to [`BUSY_RETRY`], e.g. grabs past its memory budget) is asked again
    /// after Max-Age, within the request's timeout.
    async fn exchange(&self, request: Request, what: &str) -> Result<Response, CallError> {
        let deadline = tokio::time::Instant::now() + self.timeout;
        loop {
            let sent_us = clocks::unix_now_us();
            let started = std::time::Instant::now();
            let response = match &self.progress {
                Some(shown) => {
                    let (tx, mut rx) = tokio::sync::mpsc::unbounded_channel();
                    let sent = self
                        .client
                        .send_with_progress(self.server, request.clone(), tx);
                    let follow = async {
                        let mut watch = shown.watch();
                        while let Some(p) = rx.recv().await {
                            watch.show(p.done, p.total);
                        }
                    };
                    let (response, ()) = tokio::join!(sent, follow);
                    response
                }
                None => self.client.send(self.server, request.clone()).await,
            };
            let response = response.map_err(|source| CallError::Exchange {
                what: what.to_owned(),
                server: self.server,
                source,
            })?;
            // T4 from the monotonic clock: a step of the wall clock meanwhile is not a delay.
            let took = i64::try_from(started.elapsed().as_micros()).unwrap_or(i64::MAX);
            self.clocks
                .exchanged(self.server, sent_us, &response.options, sent_us + took);
            if response.code == Code::SERVICE_UNAVAILABLE
                && let Some(wait) = response
                    .options
                    .uint(OptionNumber::MAX_AGE)
                    .map(|s| Duration::from_secs(u64::from(s)).max(Duration::from_millis(100)))
                    .filter(|w| *w <= BUSY_RETRY)
                && tokio::time::Instant::now() + wait < deadline
            {
                tracing::debug!(%what, ?wait, "the server is busy; asking again");
                tokio::time::sleep(wait).await;
                continue;
            }
            rtt_cache::save(&self.client, self.server).await;
            return check(what, response);
        }
    }

    /// The request `call` sends, for callers that send it themselves (multicast).
    pub fn request(
        &self,
        method: Code,
        path: &str,
        payload: Bytes,
        content_format: Option<ContentFormat>,
        accept: Option<ContentFormat>,
    ) -> Request {
        let mut request = Request::new(method, path).with_payload(payload);
        request.timeout = Some(self.timeout);
        // Every answer tells the server's times of the exchange (crate::timesync).
        request.options.set(SERVER_TIME, b"");
        if let Some(cf) = content_format {
            request
                .options
                .set_uint(OptionNumber::CONTENT_FORMAT, u32::from(cf.0));
        }
        if let Some(cf) = accept {
            request
                .options
                .set_uint(OptionNumber::ACCEPT, u32::from(cf.0));
        }
        request
    }

    /// `GET path?query` (each item one Uri-Query option), as [`CamClient::call`].
    pub async fn get_query(
        &self,
        path: &str,
        query: &[String],
        accept: Option<ContentFormat>,
    ) -> Result<Response, CallError> {
        let mut request = self.request(Code::GET, path, Bytes::new(), None, accept);
        for item in query {
            request
                .options
                .push(OptionNumber::URI_QUERY, item.as_bytes());
        }
        let what = if query.is_empty() {
            format!("GET {path}")
        } else {
            format!("GET {path}?{}", query.join("&"))
        };
        self.exchange(request, &what).await
    }

    /// The serials of the server's cameras, from discovery (`rt=rgbd.color`), sorted.
    pub async fn cameras(&self) -> Result<Vec<String>, DiscoveryError> {
        let mut request = Request::new(Code::GET, "/.well-known/core");
        request
            .options
            .push(OptionNumber::URI_QUERY, b"rt=rgbd.color");
        request.timeout = Some(self.timeout);
        let response = self
            .client
            .send(self.server, request)
            .await
            .map_err(|source| DiscoveryError::Exchange {
                server: self.server,
                source,
            })?;
        let response = check("discovery", response)?;
        let text = std::str::from_utf8(&response.payload).map_err(DiscoveryError::NotUtf8)?;
        let mut serials: Vec<String> = link_format::parse(text)
            .map_err(DiscoveryError::LinkFormat)?
            .into_iter()
            .filter_map(|l| {
                let rest = l.target.strip_prefix("/cams/")?;
                let (sn, name) = rest.split_once('/')?;
                (name == "color").then(|| sn.to_owned())
            })
            .collect();
        serials.sort();
        serials.dedup();
        Ok(serials)
    }

    /// The camera to use: `camera` if given, else the server's only camera.
    pub async fn one_camera(&self, camera: Option<&str>) -> Result<String, DiscoveryError> {
        if let Some(sn) = camera {
            return Ok(sn.to_owned());
        }
        let mut serials = self.cameras().await?;
        match serials.len() {
            1 => Ok(serials.remove(0)),
            0 => Err(DiscoveryError::NoCamera {
                server: self.server,
            }),
            _ => Err(DiscoveryError::Several {
                server: self.server,
                serials,
            }),
        }
    }

    /// GET a camera's JSON document (`color-settings`, `application-config`, ...) as its
    /// type ([`rgbd::ColorSettings`], [`crate::documents::AppConfig`], ...).
    pub async fn get_json<T: serde::de::DeserializeOwned>(
        &self,
        serial: &str,
        name: &str,
    ) -> Result<T, DocumentError> {
        let r = self
            .call(
                Code::GET,
                &crate::api::paths::camera(serial, name),
                Bytes::new(),
                None,
                None,
            )
            .await?;
        serde_json::from_slice(&r.payload).map_err(|source| DocumentError::Parse {
            name: name.to_owned(),
            serial: serial.to_owned(),
            source,
        })
    }

    /// PUT a camera's JSON document.
    pub async fn put_json<T: serde::Serialize>(
        &self,
        serial: &str,
        name: &str,
        doc: &T,
    ) -> Result<(), DocumentError> {
        let body = serde_json::to_vec(doc).map_err(|source| DocumentError::Encode {
            name: name.to_owned(),
            source,
        })?;
        self.call(
            Code::PUT,
            &crate::api::paths::camera(serial, name),
            Bytes::from(body),
            Some(ContentFormat::JSON),
            None,
        )
        .await?;
        Ok(())
    }

    /// Grabs a new frame of one camera (POST), in the representation `accept` (the
    /// thesis packet when `None`).
    pub async fn grab(
        &self,
        serial: &str,
        stream: Stream,
        accept: Option<ContentFormat>,
    ) -> Result<Response, CallError> {
        let path = crate::api::paths::camera(serial, stream.name());
        self.call(Code::POST, &path, Bytes::new(), None, accept)
            .await
    }

    /// Grabs a new frame of one camera (POST) in its stream's compact form ([`Stream::compact`]):
    /// color as JPEG at the server's quality, depth as RVL+zstd, a cloud as the compact
    /// cloud; the thesis packet from a server that does not offer it (4.06).
    pub async fn grab_compact(&self, serial: &str, stream: Stream) -> Result<Response, CallError> {
        match self.grab(serial, stream, Some(stream.compact())).await {
            Err(e) if not_acceptable(&e) => self.grab(serial, stream, None).await,
            other => other,
        }
    }

    /// Grabs a new depth frame of one camera (POST), compactly ([`Self::grab_compact`]).
    pub async fn grab_depth(&self, serial: &str) -> Result<DepthImage, FrameError> {
        let r = self.grab_compact(serial, Stream::Depth).await?;
        Ok(repr::Format::received(r.options.content_format())?.decode_depth(&r.payload)?)
    }

    /// Grabs a new color frame of one camera (POST) as a JPEG of `quality` (1-100).
    pub async fn grab_jpeg(&self, serial: &str, quality: u8) -> Result<Response, CallError> {
        let path = crate::api::paths::camera(serial, "color");
        let accept = Some(ContentFormat::IMAGE_JPEG);
        let mut request = self.request(Code::POST, &path, Bytes::new(), None, accept);
        request
            .options
            .push(OptionNumber::URI_QUERY, format!("q={quality}").as_bytes());
        self.exchange(request, &format!("POST {path}?q={quality}"))
            .await
    }

    /// Grabs every camera of the server and merges their clouds (POST /cams/pointclouds).
    pub async fn grab_all(&self, accept: Option<ContentFormat>) -> Result<Response, CallError> {
        self.call(
            Code::POST,
            crate::api::paths::POINTCLOUDS,
            Bytes::new(),
            None,
            accept,
        )
        .await
    }

    /// Grabs a new point cloud (POST) of camera `serial`, or of every camera merged
    /// (`/cams/pointclouds`) when `None`; as the compact cloud (65103), or the thesis
    /// packet from a server that does not offer it (4.06). [`cloud_of`] reads either.
    pub async fn grab_cloud(&self, serial: Option<&str>) -> Result<Response, CallError> {
        let Some(sn) = serial else {
            return match self.grab_all(Some(Stream::Pointcloud.compact())).await {
                Err(e) if not_acceptable(&e) => self.grab_all(None).await,
                other => other,
            };
        };
        self.grab_compact(sn, Stream::Pointcloud).await
    }

    /// Measures at the edge (`POST /cams/dimensions`, an extension): the server grabs
    /// every camera it has, merges, measures and answers the document of
    /// `measure --json` (asked for as CBOR), returned with its size in bytes. `None` when
    /// the server does not offer it (4.04 or 4.05: a server without the extension).
    pub async fn measure_edge(
        &self,
        query: &EdgeQuery,
    ) -> Result<Option<(Measurement, usize)>, EdgeError> {
        let mut request = self.request(
            Code::POST,
            crate::api::paths::DIMENSIONS,
            Bytes::new(),
            None,
            Some(ContentFormat::CBOR),
        );
        for item in query.to_query() {
            request
                .options
                .push(OptionNumber::URI_QUERY, item.as_bytes());
        }
        let response = match self.exchange(request, "POST /cams/dimensions").await {
            Ok(r) => r,
            Err(e) if matches!(e.code(), Some(Code::NOT_FOUND | Code::METHOD_NOT_ALLOWED)) => {
                return Ok(None);
            }
            Err(e) => return Err(e.into()),
        };
        let m = Measurement::from_cbor(&response.payload).map_err(EdgeError::Measurement)?;
        Ok(Some((m, response.payload.len())))
    }
}

/// True for an [`ErrorResponse`] 4.06 Not Acceptable: the server does not offer the format.
fn not_acceptable(e: &CallError) -> bool {
    e.code() == Some(Code::NOT_ACCEPTABLE)
}

/// The point cloud of a response in any of its representations, with the cameras and
/// the time of the grab where the representation carries them (the thesis packet names
/// no camera and has whole seconds). Deprojecting a compact cloud takes a few
/// milliseconds: call it off the executor.
pub fn cloud_of(response: &Response) -> Result<cbor::Cloud, FrameError> {
    let cf = response.options.content_format();
    let Ok(row) = repr::Format::received(cf) else {
        return Err(FrameError::UnknownCloudFormat(repr::Format::describe(
            cf.unwrap_or(ContentFormat::OCTET_STREAM),
        )));
    };
    Ok(row.decode_cloud(&response.payload)?)
}

/// A client that could not be made.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum ConnectError {
    /// The server's URI is not one.
    #[error(transparent)]
    Uri(#[from] coap_net::uri::UriError),
    /// A `coaps://`, `coaps+tcp://` or `coaps+ws://` URI (the scheme named) without a
    /// key.
    #[error("{0}:// needs a pre-shared key: --psk-identity ID --psk-key KEY")]
    NoKey(&'static str),
    /// OpenSSL's TLS could not be set up for `coaps+tcp://` or `coaps+ws://`.
    #[error("setting up TLS")]
    Tls(#[source] std::io::Error),
    /// The URI's host did not resolve.
    #[error("resolving {host}")]
    Resolve {
        /// The host.
        host: String,
        /// Why.
        source: std::io::Error,
    },
    /// The client's socket could not be bound.
    #[error("binding the client socket")]
    Bind(#[source] std::io::Error),
    /// The client's socket could not be bound to the address asked for.
    #[error("binding the client socket to {ip}")]
    BindTo {
        /// The address.
        ip: IpAddr,
        /// Why.
        source: std::io::Error,
    },
}

/// The server's cameras could not be found, or not the one camera asked for.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum DiscoveryError {
    /// Discovery was not answered (the [`coap_net::Error`] a link of the chain, where the
    /// command's exit status finds a timeout).
    #[error("discovering the cameras of {server}")]
    Exchange {
        /// The server asked.
        server: SocketAddr,
        /// Why.
        source: coap_net::Error,
    },
    /// Discovery was refused (transparent: the causes the command's exit status looks
    /// for are the [`CallError`]'s sources, not itself).
    #[error(transparent)]
    Call(#[from] CallError),
    /// The document is not text.
    #[error("the link-format document is not UTF-8")]
    NotUtf8(#[source] std::str::Utf8Error),
    /// The document is not link-format.
    #[error("parsing the link-format document")]
    LinkFormat(#[source] link_format::ParseError),
    /// The server has no camera.
    #[error("{server} has no camera")]
    NoCamera {
        /// The server.
        server: SocketAddr,
    },
    /// No camera was named, and the server has several.
    #[error("{server} has {} cameras ({}); choose one with --camera", serials.len(), serials.join(", "))]
    Several {
        /// The server.
        server: SocketAddr,
        /// Its cameras.
        serials: Vec<String>,
    },
}

/// A camera's JSON document could not be read or written.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum DocumentError {
    /// The request failed (transparent, as [`DiscoveryError::Call`]).
    #[error(transparent)]
    Call(#[from] CallError),
    /// The document read is not one of its type.
    #[error("parsing {name} of {serial}")]
    Parse {
        /// The document, e.g. `depth-settings`.
        name: String,
        /// The camera.
        serial: String,
        /// Why.
        source: serde_json::Error,
    },
    /// The document to write did not encode.
    #[error("encoding {name}")]
    Encode {
        /// The document.
        name: String,
        /// Why.
        source: serde_json::Error,
    },
}

/// A frame grabbed could not be had or read.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum FrameError {
    /// The grab failed (transparent, as [`DiscoveryError::Call`]).
    #[error(transparent)]
    Call(#[from] CallError),
    /// A point cloud in a content format that is not one.
    #[error("a point cloud in an unknown content format ({0})")]
    UnknownCloudFormat(String),
    /// The body did not decode.
    #[error(transparent)]
    Decode(#[from] DecodeError),
}

/// A measurement at the edge failed.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum EdgeError {
    /// The request failed (transparent, as [`DiscoveryError::Call`]).
    #[error(transparent)]
    Call(#[from] CallError),
    /// The answer is not a measurement.
    #[error("reading the measurement from /cams/dimensions")]
    Measurement(#[source] MeasurementError),
}

/// A request that failed: not answered, answered with an error response, or answered
/// with a body shorter or longer than announced.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum CallError {
    /// Not sent, or not answered (the request timed out, the port is unreachable).
    #[error("{what} on {server}")]
    Exchange {
        /// The request, e.g. `GET /cams/840412060746/depth-settings`.
        what: String,
        /// The server asked.
        server: SocketAddr,
        /// Why.
        source: coap_net::Error,
    },
    /// Answered with an error response (4.xx, 5.xx). Said as the [`ErrorResponse`] says
    /// itself, which is also the source (not `transparent`), so that the command's exit
    /// status finds it among the causes; [`crate::error_text`] says it once.
    #[error("{0}")]
    Refused(#[source] ErrorResponse),
    /// A successful answer whose body is not as long as its Size2 said.
    #[error("{what}")]
    Incomplete {
        /// The request.
        what: String,
        /// How long it was and was said to be.
        source: SizeError,
    },
}

impl CallError {
    /// The code of the error response, if the request was answered with one.
    pub fn code(&self) -> Option<Code> {
        match self {
            Self::Refused(r) => Some(r.response.code),
            _ => None,
        }
    }
}

/// A request answered with an error response (4.xx, 5.xx).
#[derive(Debug, thiserror::Error)]
#[error("{what}: {}", describe(.response))]
pub struct ErrorResponse {
    /// The request, e.g. `GET /cams/840412060746/depth-settings`.
    pub what: String,
    /// The response, its payload the diagnostic.
    pub response: Box<Response>,
}

/// Nothing answered in time: no server at the address, or no member of a group.
#[derive(Debug, thiserror::Error)]
#[error("{0}")]
pub struct NoAnswer(pub String);

/// `response` if it is a 2.xx whose body is as long as its Size2 says; an error response
/// becomes an [`ErrorResponse`].
pub fn check(what: &str, response: Response) -> Result<Response, CallError> {
    if !response.code.is_success() {
        return Err(CallError::Refused(ErrorResponse {
            what: what.to_owned(),
            response: Box::new(response),
        }));
    }
    check_size(&response, response.payload.len()).map_err(|source| CallError::Incomplete {
        what: what.to_owned(),
        source,
    })?;
    Ok(response)
}

/// The code and the diagnostic of a response, e.g. "4.04 Not Found: no such resource".
pub fn describe(response: &Response) -> String {
    let diagnostic = String::from_utf8_lossy(&response.payload);
    if diagnostic.is_empty() {
        response.code.to_string()
    } else {
        format!("{}: {diagnostic}", response.code)
    }
}

/// Refuses a successful body of `size` bytes when the server announced another size
/// (Size2).
pub fn check_size(response: &Response, size: usize) -> Result<(), SizeError> {
    if let Some(size2) = response.options.uint(OptionNumber::SIZE2)
        && response.code.is_success()
        && size2 as usize != size
    {
        return Err(SizeError {
            announced: size2,
            arrived: size,
        });
    }
    Ok(())
}

/// A body not as long as the server announced (Size2).
#[derive(Debug, thiserror::Error)]
#[error("incomplete body: the server announced {announced} bytes (Size2), {arrived} arrived")]
pub struct SizeError {
    /// The size announced.
    pub announced: u32,
    /// The bytes that arrived.
    pub arrived: usize,
}
