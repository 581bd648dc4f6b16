//! `bench repr`: the bytes of every representation a server offers for one depth frame,
//! one color frame and the merged point cloud of a scene, and how long each takes to
//! encode (the server's work) and to decode (the client's), medians over the runs.

use std::net::SocketAddr;
use std::time::{Duration, Instant};

use anyhow::Context as _;
use coap::ContentFormat;
use rgbd::{Camera as _, Scene, SyntheticCamera};

use crate::client::CamClient;
use crate::client::measure::prepare_cameras;
use crate::repr::{self, CloudSource, cbor, clouds, packet, ply, raster, rvl};
use crate::server::SceneServer;
use crate::stats;

/// What the benchmark measured.
pub struct Report {
    /// Encodings and decodings per representation.
    pub runs: u32,
    /// The camera whose frames were encoded.
    pub serial: String,
    /// The cameras whose clouds were merged.
    pub cameras: usize,
    /// The depth frame's width and height.
    pub depth: [u32; 2],
    /// The color frame's width and height.
    pub color: [u32; 2],
    /// The points of the (prepared) merged cloud.
    pub points: usize,
    /// Every representation's figures, in the order encoded.
    pub rows: Vec<Row>,
}

/// One representation's figures.
pub struct Row {
    /// What was encoded: `depth`, `color`, `merged cloud` (prepared), `merged cloud,
    /// unprepared`.
    pub what: &'static str,
    /// In which representation.
    pub format: ContentFormat,
    /// Its bytes.
    pub bytes: usize,
    /// The median time to encode it, milliseconds.
    pub encode_ms: f64,
    /// The median time to decode it, milliseconds.
    pub decode_ms: f64,
}

/// The median of `runs` timings of `f`, in milliseconds, and its last result.
fn time<T>(runs: u32, mut f: impl FnMut() -> anyhow::Result<T>) -> anyhow::Result<(f64, T)> {
    let mut ms = Vec::new();
    let mut last = None;
    for _ in 0..runs {
        let started = Instant::now();
        last = Some(f()?);
        ms.push(started.elapsed().as_secs_f64() * 1000.0);
    }
    let result = last.context("no run")?;
    Ok((stats::median(&ms).unwrap_or(f64::NAN), result))
}

/// Times `encode`, then `decode` of what it made.
fn row(
    what: &'static str,
    format: ContentFormat,
    runs: u32,
    encode: impl FnMut() -> anyhow::Result<Vec<u8>>,
    mut decode: impl FnMut(&[u8]) -> anyhow::Result<()>,
) -> anyhow::Result<Row> {
    let (encode_ms, body) = time(runs, encode)?;
    let (decode_ms, ()) = time(runs, || decode(&body))?;
    Ok(Row {
        what,
        format,
        bytes: body.len(),
        encode_ms,
        decode_ms,
    })
}

/// Parses a CBOR document (the representations' maps): what a client does first.
fn parse_cbor(body: &[u8]) -> anyhow::Result<()> {
    let _: ciborium::Value = ciborium::from_reader(body).context("parsing CBOR")?;
    Ok(())
}

/// Encodes and decodes every representation of `scene`'s first camera's depth and color
/// frames and of its merged cloud (served by a `SceneServer` in this process), `runs`
/// times each.
pub async fn run(scene: &Scene, runs: u32) -> anyhow::Result<Report> {
    let camera = SyntheticCamera::all(scene)?
        .into_iter()
        .next()
        .context("the scene has no camera")?;
    let serial = camera.serial();
    let depth = camera.render_depth(1);
    let depth_k = camera.depth_intrinsics()?;
    let color = camera.render_color(1);
    let (color_k, to_color) = (camera.color_intrinsics()?, camera.depth_to_color()?);

    let mut rows = Vec::new();
    let d = &depth;
    rows.push(row(
        "depth",
        ContentFormat::OCTET_STREAM,
        runs,
        || Ok(packet::depth_packet(d)),
        |b| Ok(packet::depth(b).map(drop)?),
    )?);
    rows.push(row(
        "depth",
        ContentFormat::IMAGE_PNG,
        runs,
        || Ok(raster::depth_png(d)?),
        |b| Ok(raster::depth_from_png(b).map(drop)?),
    )?);
    rows.push(row(
        "depth",
        repr::RVL,
        runs,
        || Ok(rvl::depth_rvl(d)),
        |b| Ok(rvl::depth_from_rvl(b).map(drop)?),
    )?);
    rows.push(row(
        "depth",
        repr::RVL_ZSTD,
        runs,
        || Ok(rvl::depth_rvl_zstd(d)?),
        |b| Ok(rvl::depth_from_rvl_zstd(b).map(drop)?),
    )?);
    rows.push(row(
        "depth",
        ContentFormat::CBOR,
        runs,
        || Ok(cbor::depth_cbor(d, &depth_k, &serial)?),
        parse_cbor,
    )?);

    let c = &color;
    let format = camera.color_settings().format;
    rows.push(row(
        "color",
        ContentFormat::OCTET_STREAM,
        runs,
        || Ok(packet::color_packet(c)),
        |b| Ok(packet::color(b, format.name()).map(drop)?),
    )?);
    rows.push(row(
        "color",
        ContentFormat::IMAGE_PNG,
        runs,
        || Ok(raster::color_png(c)?),
        |b| Ok(image::load_from_memory(b).map(drop)?),
    )?);
    rows.push(row(
        "color",
        ContentFormat::IMAGE_JPEG,
        runs,
        || Ok(raster::color_jpeg(c, raster::JPEG_QUALITY)?),
        |b| Ok(image::load_from_memory(b).map(drop)?),
    )?);
    rows.push(row(
        "color",
        ContentFormat::CBOR,
        runs,
        || Ok(cbor::color_cbor(c, &color_k, &to_color, &serial)?),
        |b| Ok(cbor::ColorCapture::from_cbor(b).map(drop)?),
    )?);

    // The merged cloud of every camera, as the cameras start and prepared as `measure
    // --prepare` does. The server sends it compactly; its points are the packet's.
    let state = std::env::temp_dir().join(format!("coapcam-bench-repr-{}", std::process::id()));
    let server = SceneServer::start(scene, &state, SocketAddr::from(([127, 0, 0, 1], 0))).await?;
    let client = CamClient::at(server.addr()?, Duration::from_secs(30))?;
    let serials: Vec<String> = scene.cameras.iter().map(|c| c.serial.to_string()).collect();
    let all: Vec<rgbd::Serial> = scene.cameras.iter().map(|c| c.serial).collect();
    let source = CloudSource::Merged { serials: &all };
    let mut points = 0;
    for (what, prepare) in [("merged cloud, unprepared", false), ("merged cloud", true)] {
        if prepare {
            prepare_cameras(&client, &serials, 1.0, false).await?;
        }
        let merged = client.grab_all(Some(repr::DEPTH_CLOUD)).await?;
        let mut parts = clouds::parts_from_depth_cloud(&merged.payload)?;
        let mut cloud = Vec::new();
        let mut timestamp_us = 0;
        for part in &mut parts {
            cloud.extend(part.points()?);
            timestamp_us = timestamp_us.max(part.depth.timestamp_us);
        }
        points = cloud.len();
        let (p, parts) = (&cloud, &parts);
        let seconds = packet::unix_seconds(timestamp_us);
        rows.push(row(
            what,
            ContentFormat::OCTET_STREAM,
            runs,
            || Ok(packet::cloud_packet(p, seconds)),
            |b| Ok(packet::cloud(b).map(drop)?),
        )?);
        rows.push(row(
            what,
            repr::PLY,
            runs,
            || Ok(ply::cloud_ply(p, timestamp_us, source)?),
            |b| Ok(geometry::decode_ply(b).map(drop)?),
        )?);
        rows.push(row(
            what,
            ContentFormat::CBOR,
            runs,
            || Ok(cbor::cloud_cbor(p, timestamp_us, source)?),
            |b| Ok(cbor::Cloud::from_cbor(b).map(drop)?),
        )?);
        rows.push(row(
            what,
            repr::DEPTH_CLOUD,
            runs,
            || Ok(clouds::depth_cloud(parts)?),
            |b| Ok(clouds::cloud_from_depth_cloud(b).map(drop)?),
        )?);
        rows.push(row(
            what,
            repr::CLOUD_MM,
            runs,
            || Ok(clouds::cloud_mm(p, timestamp_us, source)?),
            |b| Ok(clouds::cloud_from_mm(b).map(drop)?),
        )?);
    }
    drop(server);
    let _ = std::fs::remove_dir_all(&state);
    Ok(Report {
        runs,
        serial: serial.to_string(),
        cameras: scene.cameras.len(),
        depth: [depth.width, depth.height],
        color: [color.width, color.height],
        points,
        rows,
    })
}
