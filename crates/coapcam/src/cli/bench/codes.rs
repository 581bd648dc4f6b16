//! `coapcam bench codes`: its flags, and the read rates `coapcam::bench::codes` measured
//! as a Markdown table or JSON.

use clap::Args;
use rgbd::scene::LabelKind;

use crate::cli::{Exit, outln};
use coapcam::bench::codes::{self, Sensor};

/// Flags of `bench codes`.
#[derive(Debug, Args)]
pub(super) struct CodesArgs {
    /// Labels of each symbology at each module width.
    #[arg(long, value_name = "N", default_value_t = 40,
          value_parser = clap::value_parser!(u32).range(1..=10_000))]
    labels: u32,
    /// Module widths in the image, pixels, comma-separated.
    #[arg(
        long,
        value_name = "PX,...",
        value_delimiter = ',',
        default_value = "2,3,4,5"
    )]
    module_px: Vec<f64>,
    /// The lens's Gaussian blur (standard deviation), pixels.
    #[arg(long, value_name = "PX", default_value_t = 1.0)]
    blur_px: f64,
    /// Sensor noise at mid grey, 8-bit levels.
    #[arg(long, value_name = "LEVELS", default_value_t = 3.0)]
    noise: f64,
    /// Seed of the texts and yaws.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Print one JSON array (a cell per symbology and module width) instead of a table.
    #[arg(long)]
    json: bool,
}

/// Runs `bench codes`.
pub(super) async fn run(args: CodesArgs) -> anyhow::Result<Exit> {
    if args
        .module_px
        .iter()
        .any(|&px| !(0.25..=20.0).contains(&px))
    {
        anyhow::bail!("--module-px: each from 0.25 to 20 pixels");
    }
    let sensor = Sensor {
        blur_px: args.blur_px,
        noise: args.noise,
    };
    let cells = tokio::task::spawn_blocking(move || {
        codes::run(
            &LabelKind::ALL,
            &args.module_px,
            args.labels,
            sensor,
            args.seed,
        )
    })
    .await??;
    if args.json {
        outln!("{}", serde_json::to_string(&cells)?);
        return Ok(Exit::Success);
    }
    outln!(
        "blur {} px, noise {} levels, {} labels a cell, seed {}; read rate %, ms an image",
        args.blur_px,
        args.noise,
        args.labels,
        args.seed
    );
    outln!("| symbology | module px | ours | rxing | both | ms ours | ms rxing | ms both |");
    outln!("| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |");
    for c in &cells {
        let rate = |i: usize| 100.0 * f64::from(c.read[i]) / f64::from(c.labels.max(1));
        let ms = |i: usize| c.ms[i] / f64::from(c.labels.max(1));
        outln!(
            "| {} | {} | {:.1} | {:.1} | {:.1} | {:.0} | {:.0} | {:.0} |",
            c.kind.name(),
            c.module_px,
            rate(0),
            rate(1),
            rate(2),
            ms(0),
            ms(1),
            ms(2)
        );
    }
    outln!("\nAt each symbology's limit and above, the station's reader (both):");
    for (kind, read, labels) in codes::at_the_limit(&cells) {
        let rate = 100.0 * f64::from(read) / f64::from(labels.max(1));
        outln!(
            "- {} (from {} px a module): {read} of {labels} read ({rate:.1} %)",
            kind.name(),
            kind.min_px_per_module()
        );
    }
    Ok(Exit::Success)
}
