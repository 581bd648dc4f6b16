//! `coapcam bench repr`: its flags, and what `coapcam::bench::repr` measured printed as
//! a Markdown table or one JSON object.

use std::path::PathBuf;

use anyhow::Context as _;
use clap::Args;
use coap::ContentFormat;
use rgbd::Scene;

use crate::cli::{Exit, outln};
use coapcam::bench::repr::{self, Report};
use coapcam::repr::Format;

/// Flags of `bench repr`.
#[derive(Debug, Args)]
pub(super) struct ReprArgs {
    /// The scene (TOML); the built-in demo scene (two cameras, 1280x720) by default. The
    /// first camera's frames are encoded; the cloud is every camera's, merged.
    #[arg(long, value_name = "FILE")]
    scene: Option<PathBuf>,
    /// How often each representation is encoded and decoded; the medians are printed.
    #[arg(long, value_name = "N", default_value_t = 11,
          value_parser = clap::value_parser!(u32).range(1..))]
    runs: u32,
    /// Print one JSON object instead of the table.
    #[arg(long)]
    json: bool,
}

/// Runs `bench repr`.
pub(super) async fn run(args: ReprArgs) -> anyhow::Result<Exit> {
    let scene = match &args.scene {
        Some(path) => {
            Scene::load(path).with_context(|| format!("loading scene {}", path.display()))?
        }
        None => Scene::default_demo(),
    };
    let report = repr::run(&scene, args.runs).await?;
    let Report {
        runs,
        ref serial,
        cameras,
        depth,
        color,
        points,
        ref rows,
    } = report;
    if args.json {
        let list: Vec<serde_json::Value> = rows
            .iter()
            .map(|r| {
                serde_json::json!({
                    "what": r.what,
                    "content_format": r.format.0,
                    "name": Format::describe(r.format),
                    "bytes": r.bytes,
                    "encode_ms": r.encode_ms,
                    "decode_ms": r.decode_ms,
                })
            })
            .collect();
        let doc = serde_json::json!({
            "runs": runs,
            "depth": depth,
            "color": color,
            "points": points,
            "representations": list,
        });
        outln!("{doc}");
        return Ok(Exit::Success);
    }
    outln!(
        "one {}x{} depth frame and one {}x{} color frame of camera {serial}, the merged cloud \
         of {} camera(s) as they start and prepared ({} points); medians of {runs} runs",
        depth[0],
        depth[1],
        color[0],
        color[1],
        cameras,
        points
    );
    outln!();
    outln!("| what | content format | bytes | of the packet | encode ms | decode ms |");
    outln!("|---|---|---:|---:|---:|---:|");
    for r in rows {
        let packet = rows
            .iter()
            .find(|p| p.what == r.what && p.format == ContentFormat::OCTET_STREAM)
            .map_or(0, |p| p.bytes);
        outln!(
            "| {} | {} {} | {} | {:.3} | {:.2} | {:.2} |",
            r.what,
            r.format.0,
            Format::describe(r.format),
            r.bytes,
            r.bytes as f64 / packet as f64,
            r.encode_ms,
            r.decode_ms
        );
    }
    Ok(Exit::Success)
}
