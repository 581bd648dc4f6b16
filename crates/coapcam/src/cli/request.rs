//! The generic CoAP commands: `get`, `post`, `put`, `delete` and `discover`.

use std::io::{IsTerminal as _, Write as _};
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use anyhow::{Context as _, bail};
use bytes::Bytes;
use clap::Args;
use coap::link_format;
use coap::{BlockOpt, Code, ContentFormat, OptionNumber, Request, Response};
use coap_net::{BodyPart, Client, Uri};
use coapcam::repr::Format;

use super::part_file::PartFile;
use super::{Bar, Exit, Signals, TransmissionArgs, outln, usage, values};
use coapcam::client::{check_size, describe};

/// Flags shared by `get`, `post`, `put` and `delete`.
#[derive(Debug, Args)]
pub(crate) struct RequestArgs {
    /// The resource, e.g. coap://127.0.0.1:5683/cams/pointclouds?x=1 (IPv6: coap://[::1]/...;
    /// coaps:// for DTLS, coap+tcp:// for TCP).
    #[arg(value_parser = values::coap_uri)]
    uri: String,
    /// Request payload as text.
    #[arg(long, conflicts_with = "file")]
    payload: Option<String>,
    /// Request payload from a file (sent block-wise when larger than one block).
    #[arg(long)]
    file: Option<PathBuf>,
    /// Content-Format of the payload: a number, a media type, or a short name
    /// (text, json, cbor, png, jpeg, octet-stream, link-format, ply).
    #[arg(long, value_name = "CF", value_parser = Format::parse)]
    content_format: Option<ContentFormat>,
    /// Accept: the Content-Format wanted in the response (same forms as --content-format).
    #[arg(long, value_name = "CF", value_parser = Format::parse)]
    accept: Option<ContentFormat>,
    /// Block size in bytes for block-wise transfers: 16, 32, 64, 128, 256, 512 or 1024.
    #[arg(long, value_name = "N", value_parser = parse_block_size)]
    block_size: Option<u8>,
    /// Send a Non-confirmable request (no ACKs; lost requests are sent again).
    #[arg(long)]
    non: bool,
    /// Write the response body to FILE instead of standard output.
    #[arg(short = 'o', long = "output", value_name = "FILE")]
    output: Option<PathBuf>,
    /// Observe the resource (GET only) and print this many notifications after the first
    /// response, then stop.
    #[arg(long, value_name = "N")]
    observe: Option<usize>,
    /// Print one JSON object per response (code, options, size, time) instead of the body.
    #[arg(long)]
    json: bool,
    #[command(flatten)]
    transmission: TransmissionArgs,
}

fn parse_block_size(s: &str) -> Result<u8, String> {
    let n: usize = s.parse().map_err(|_| format!("{s:?} is not a number"))?;
    if !(16..=1024).contains(&n) || !n.is_power_of_two() {
        return Err(format!("{n} is not one of 16, 32, 64, 128, 256, 512, 1024"));
    }
    Ok(BlockOpt::szx_for(n))
}

/// Flags of `discover`.
#[derive(Debug, Args)]
pub(crate) struct DiscoverArgs {
    /// The server (coap://host[:port], coaps://, coap+tcp://, coap+ws://, coaps+tcp:// or
    /// coaps+ws://); a multicast address (coap:// only) asks every server in the group.
    #[arg(required_unless_present = "rd", value_parser = values::coap_uri)]
    uri: Option<String>,
    /// List the endpoints (stations) registered with this resource directory instead
    /// (RFC 9176 endpoint lookup, its path discovered through rt=core.rd-lookup-ep): one
    /// line per endpoint with its name (ep), base address and attributes, e.g. the
    /// groups it joined (grp). --query narrows it, e.g. et=coapcam.station or
    /// grp=224.0.1.187:5683.
    #[arg(long, value_name = "coap://HOST[:PORT]", conflicts_with = "uri",
          value_parser = values::coap_uri)]
    rd: Option<String>,
    /// A /.well-known/core filter (RFC 6690 §4.1), e.g. rt=rgbd.color or href=/cams*;
    /// with --rd a lookup's criteria, `&`-separated.
    #[arg(long)]
    query: Option<String>,
    /// How long to collect answers from a multicast group, in seconds (above 0).
    #[arg(long, value_name = "SECONDS", default_value = "2", value_parser = values::positive_seconds)]
    wait: Duration,
    /// Print JSON: one object per link with its server, target and attributes.
    #[arg(long)]
    json: bool,
    #[command(flatten)]
    transmission: TransmissionArgs,
}

/// Runs `get|post|put|delete`: a success for a 2.xx whose body arrived whole,
/// [`Exit::Refused`] for an error response.
pub(crate) async fn run(method: Code, args: RequestArgs) -> anyhow::Result<Exit> {
    if args.observe.is_some() && method != Code::GET {
        usage!("--observe needs GET");
    }
    let uri = Uri::parse(&args.uri)?;
    let peer = uri
        .resolve()
        .await
        .with_context(|| format!("resolving {}", uri.host))?;
    let mut request = Request::new(method, "/");
    request.options = uri.options();
    request.confirmable = !args.non;
    request.block_szx = args.block_size;
    request.timeout = Some(args.transmission.timeout());
    if let Some(cf) = args.content_format {
        request
            .options
            .set_uint(OptionNumber::CONTENT_FORMAT, u32::from(cf.0));
    }
    if let Some(cf) = args.accept {
        request
            .options
            .set_uint(OptionNumber::ACCEPT, u32::from(cf.0));
    }
    request.payload = match (&args.payload, &args.file) {
        (Some(text), _) => Bytes::from(text.clone().into_bytes()),
        (None, Some(path)) => {
            Bytes::from(std::fs::read(path).with_context(|| format!("reading {}", path.display()))?)
        }
        (None, None) => Bytes::new(),
    };
    let client = args.transmission.client(&uri, peer)?;
    let started = Instant::now();
    let what = || format!("{} {}", method.name().unwrap_or("request"), args.uri);
    // An error response names the method and the resource's path, as README.md shows.
    let refused = format!(
        "{} /{}{}",
        method.name().unwrap_or("request"),
        uri.path.join("/"),
        if uri.query.is_empty() {
            String::new()
        } else {
            format!("?{}", uri.query.join("&"))
        }
    );
    if let Some(count) = args.observe {
        return observe(&client, peer, request, count, &args, started, &refused).await;
    }
    let bar = std::io::stderr().is_terminal() && !args.json;
    if let Some(path) = &args.output {
        // SIGINT and SIGTERM end the transfer through this select, which drops it and
        // with it the temporary file (its Drop removes it), instead of killing the
        // process where it stands.
        let mut signals = Signals::install()?;
        let (response, size) = tokio::select! {
            done = to_file(&client, peer, request, path, bar) => done.with_context(what)?,
            signal = signals.recv() => return Err(signal.into()),
        };
        let path = path_json(&client, peer, args.json).await;
        output(&response, size, &args, started, path)?;
        return Ok(report_code(&response, &refused));
    }
    let response = if bar {
        send_with_bar(&client, peer, request).await
    } else {
        client.send(peer, request).await
    }
    .with_context(what)?;
    check_size(&response, response.payload.len())?;
    let path = path_json(&client, peer, args.json).await;
    output(&response, response.payload.len(), &args, started, path)?;
    Ok(report_code(&response, &refused))
}

/// Streams the body of a success response into a temporary file next to `path`, and
/// renames it to `path` only when the body arrived whole: a failed transfer leaves `path`
/// as it was. Returns the response (its payload is the diagnostic of an error response,
/// which is not written) and the size of the body.
async fn to_file(
    client: &Client,
    peer: SocketAddr,
    request: Request,
    path: &Path,
    show_bar: bool,
) -> anyhow::Result<(Response, usize)> {
    let mut part = PartFile::create(path)?;
    let mut stream = client.send_streamed(peer, request)?;
    let mut bar = Bar::new(show_bar);
    let mut written = 0;
    loop {
        match stream.next().await? {
            BodyPart::Chunk { data, total } => {
                part.write(&data)?;
                written += data.len();
                bar.show(written, total);
            }
            BodyPart::End(response) => {
                bar.finish();
                if response.code.is_success() {
                    check_size(&response, written)?;
                    part.keep()?;
                }
                return Ok((*response, written));
            }
        }
    }
}

async fn observe(
    client: &Client,
    peer: SocketAddr,
    request: Request,
    count: usize,
    args: &RequestArgs,
    started: Instant,
    what: &str,
) -> anyhow::Result<Exit> {
    let mut obs = client.observe(peer, request).await?;
    let mut seen = 0;
    while let Some(r) = obs.next().await {
        let response = r?;
        if let Some(path) = &args.output {
            std::fs::write(path, &response.payload)
                .with_context(|| format!("writing {}", path.display()))?;
        }
        output(
            &response,
            response.payload.len(),
            args,
            started,
            serde_json::Value::Null,
        )?;
        if !response.code.is_success() {
            return Ok(report_code(&response, what));
        }
        if !response.options.contains(OptionNumber::OBSERVE) {
            if seen == 0 {
                eprintln!(
                    "coapcam: the server answered without Observe: it does not let this resource be observed"
                );
                return Ok(Exit::Refused);
            }
            // The server ended the observation (RFC 7641 §3.2) after `seen` notifications.
            bail!("the server ended the observation after {seen} notifications");
        }
        if seen == count {
            return Ok(Exit::Success);
        }
        seen += 1;
    }
    bail!("the observation ended after {seen} notifications")
}

/// Transfers over 1 MB show a progress bar on a terminal.
async fn send_with_bar(
    client: &Client,
    peer: SocketAddr,
    request: Request,
) -> Result<Response, coap_net::Error> {
    let (tx, rx) = tokio::sync::mpsc::unbounded_channel::<coap_net::Progress>();
    let bar = Bar::new(true).follow(rx);
    let (response, ()) = tokio::join!(client.send_with_progress(peer, request, tx), bar);
    response
}

/// A success for a 2.xx response, else [`Exit::Refused`] with the request (`what`: its
/// method and URI), the code and diagnostic printed.
fn report_code(r: &Response, what: &str) -> Exit {
    if r.code.is_success() {
        return Exit::Success;
    }
    eprintln!("coapcam: {what}: {}", describe(r));
    Exit::Refused
}

/// Prints a response: the body (unless it went to --output) or, with --json, one line
/// with its code, every option, the body's size and the time since the request.
/// What the client's endpoint knows of the path to `peer` after the request, for
/// `--json` (asked of the endpoint only then): its round-trip estimate and what the
/// window counted.
async fn path_json(client: &Client, peer: SocketAddr, json: bool) -> serde_json::Value {
    let ms = |d: Duration| (d.as_secs_f64() * 1e4).round() / 10.0;
    // The next process to this server starts from the round trip measured here.
    coapcam::client::rtt_cache::save(client, peer).await;
    if !json {
        return serde_json::Value::Null;
    }
    match client.path_stats(peer).await {
        Ok(Some(p)) => serde_json::json!({
            "srtt_ms": p.srtt.map(ms),
            "rttvar_ms": ms(p.rttvar),
            "min_rtt_ms": p.min_rtt.map(ms),
            "retransmissions": p.retransmissions,
            "block_requests": p.block_requests,
            "blocks_lost": p.blocks_lost,
            "blocks_late": p.blocks_late,
            "blocks_duplicate": p.blocks_duplicate,
            "window_fallbacks": p.window_fallbacks,
            "max_window": p.max_window,
        }),
        _ => serde_json::Value::Null,
    }
}

fn output(
    r: &Response,
    size: usize,
    args: &RequestArgs,
    started: Instant,
    path: serde_json::Value,
) -> anyhow::Result<()> {
    if args.json {
        let v = serde_json::json!({
            "code": format!("{:?}", r.code),
            "options": options_json(&r.options),
            "content_format": r.options.content_format().map(|c| c.0),
            "etag": r.options.etag().map(hex),
            "observe": r.options.uint(OptionNumber::OBSERVE),
            "size_bytes": size,
            "time_ms": (started.elapsed().as_secs_f64() * 1e4).round() / 10.0,
            "payload": if args.output.is_none() { std::str::from_utf8(&r.payload).ok() } else { None },
            "transfer": path,
        });
        outln!("{v}");
    } else if args.output.is_none() && r.code.is_success() {
        let mut out = std::io::stdout().lock();
        out.write_all(&r.payload)
            .context("writing standard output")?;
        if !r.payload.ends_with(b"\n")
            && std::str::from_utf8(&r.payload).is_ok()
            && !r.payload.is_empty()
        {
            out.write_all(b"\n").context("writing standard output")?;
        }
    }
    Ok(())
}

/// Every option of a response: `{"Location-Path": ["a", "b"], "ETag": ["0a1b"], ...}`,
/// values as the registry's format says (text, number, or hex for opaque values and
/// options the registry does not know, named by number).
fn options_json(options: &coap::Options) -> serde_json::Map<String, serde_json::Value> {
    use coap::msg::option::ValueFormat;
    let mut out = serde_json::Map::new();
    for o in options.iter() {
        let info = o.number.info();
        let name = info.map_or_else(|| o.number.0.to_string(), |i| i.name.to_owned());
        let bytes = o.value.as_slice();
        let value = match info.map(|i| i.format) {
            Some(ValueFormat::Uint) => coap::msg::option::decode_uint(bytes)
                .map_or_else(|| hex(bytes).into(), serde_json::Value::from),
            Some(ValueFormat::String) => String::from_utf8_lossy(bytes).into_owned().into(),
            Some(ValueFormat::Empty) => serde_json::Value::Bool(true),
            _ => hex(bytes).into(),
        };
        match out
            .entry(name)
            .or_insert_with(|| serde_json::Value::Array(Vec::new()))
        {
            serde_json::Value::Array(values) => values.push(value),
            _ => unreachable!("every entry is an array"),
        }
    }
    out
}

fn hex(b: &[u8]) -> String {
    b.iter().map(|x| format!("{x:02x}")).collect()
}

/// Runs `discover`: a success when a server answered with its links,
/// [`Exit::NoAnswer`] when no member of a group answered.
pub(crate) async fn discover(args: DiscoverArgs) -> anyhow::Result<Exit> {
    if let Some(rd) = &args.rd {
        return discover_rd(rd, &args).await;
    }
    let Some(uri_text) = &args.uri else {
        bail!("give a server URI or --rd");
    };
    let uri = Uri::parse(uri_text)?;
    let peer = uri
        .resolve()
        .await
        .with_context(|| format!("resolving {}", uri.host))?;
    let mut request = Request::new(Code::GET, "/.well-known/core");
    if let Some(q) = &args.query {
        request.options.push(OptionNumber::URI_QUERY, q.as_bytes());
    }
    let client = args.transmission.client(&uri, peer)?;
    let answers: Vec<(SocketAddr, Response)> = if peer.ip().is_multicast() {
        request.timeout = Some(args.wait);
        client.multicast(peer, request).await?
    } else {
        request.timeout = Some(args.transmission.timeout());
        vec![(
            peer,
            client
                .send(peer, request)
                .await
                .with_context(|| format!("discovering {uri_text}"))?,
        )]
    };
    let mut exit = Exit::NoAnswer;
    for (server, r) in &answers {
        if report_code(r, &format!("GET {server}/.well-known/core")) != Exit::Success {
            if exit == Exit::NoAnswer {
                exit = Exit::Refused;
            }
            continue;
        }
        exit = Exit::Success;
        let text =
            std::str::from_utf8(&r.payload).context("the link-format document is not UTF-8")?;
        let links =
            link_format::parse(text).with_context(|| format!("parsing the answer of {server}"))?;
        for l in links {
            if args.json {
                let attrs = attrs_json(&l.attrs);
                let link = serde_json::json!({"server": server.to_string(), "target": l.target, "attrs": attrs});
                outln!("{link}");
            } else if answers.len() > 1 {
                outln!("{server} {l}");
            } else {
                outln!("{l}");
            }
        }
    }
    if answers.is_empty() {
        eprintln!(
            "coapcam: no server answered within {} s",
            args.wait.as_secs_f64()
        );
    }
    Ok(exit)
}

/// A link's attributes as a JSON object: each value a string, or `true` for an
/// attribute given without one.
fn attrs_json(attrs: &[(String, Option<String>)]) -> serde_json::Map<String, serde_json::Value> {
    attrs
        .iter()
        .map(|(k, v)| {
            (
                k.clone(),
                v.clone().map_or(serde_json::Value::Bool(true), Into::into),
            )
        })
        .collect()
}

/// `discover --rd`: the endpoints a resource directory lists.
async fn discover_rd(rd_text: &str, args: &DiscoverArgs) -> anyhow::Result<Exit> {
    let uri = Uri::parse(rd_text)?;
    let rd = uri
        .resolve()
        .await
        .with_context(|| format!("resolving {}", uri.host))?;
    let client = args.transmission.client(&uri, rd)?;
    let query: Vec<String> = args
        .query
        .iter()
        .flat_map(|q| q.split('&'))
        .filter(|q| !q.is_empty())
        .map(str::to_owned)
        .collect();
    let endpoints =
        coap_rd::registrant::lookup_endpoints(&client, rd, &query, args.transmission.timeout())
            .await?;
    for e in &endpoints {
        if args.json {
            let attrs = attrs_json(&e.link.attrs);
            let line = serde_json::json!({
                "rd": rd.to_string(),
                "ep": e.ep,
                "base": e.base,
                "target": e.link.target,
                "attrs": attrs,
            });
            outln!("{line}");
        } else {
            outln!("{}", e.link);
        }
    }
    if endpoints.is_empty() {
        eprintln!("coapcam: no endpoint is registered with {rd_text} that matches");
        return Ok(Exit::NoAnswer);
    }
    Ok(Exit::Success)
}
