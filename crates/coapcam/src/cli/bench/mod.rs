//! `coapcam bench`: the subcommands' flags; `bench accuracy` here, printing what
//! `coapcam::bench::accuracy` measured (a line per scene and the summary, or JSON), its
//! `--set cert` and `--set lane` in `cert.rs` and `lane.rs`; `bench transfer`, `bench
//! repr`, `bench codes`, `bench load` and `bench rd` are the other files beside this one
//! (a command with subcommands is a folder of `cli/`).

use clap::{Args, Subcommand};

use super::{DimensionArgs, Exit, outln};
use coapcam::bench::accuracy::{self, Quantiles, Row, Summary};

mod cert;
mod codes;
mod lane;
mod load;
mod rd;
mod repr;
mod transfer;

/// Flags of `bench`.
#[derive(Debug, Args)]
pub(crate) struct BenchArgs {
    #[command(subcommand)]
    what: BenchKind,
}

#[derive(Debug, Subcommand)]
enum BenchKind {
    /// Measure a built-in set of synthetic scenes end to end over CoAP and print the errors
    /// against each scene's truth: by --set, plain boxes (the default: 10-80 cm, yaw 0-90
    /// deg, 2-60 cm high, one or two D415s 0.8-1.5 m above the floor), the lane set or the
    /// certification set; with --calibrate, boxes on cameras calibrated by markers first.
    Accuracy(AccuracyArgs),
    /// Time whole-body GETs through emulated links (loopback, 20 ms, 2 % and 5 % loss, a
    /// 50 Mbit/s bottleneck) with our stop-and-wait, window and Q-Block2 clients, libcoap
    /// 4.3.1 and 4.3.5 and QUIC, each body checked bit-exact; print a markdown table,
    /// optionally JSON and a PNG plot.
    Transfer(transfer::TransferArgs),
    /// Print the bytes of every representation of one depth frame, one color frame and
    /// the merged point cloud of a scene, and the milliseconds to encode and decode each.
    Repr(repr::ReprArgs),
    /// Read labels of every symbology (QR, Code 128, Data Matrix, EAN-13, UPC-A, PDF417)
    /// at several module widths through a blurred, noisy synthetic color sensor, with our
    /// reader, rxing and both; print each one's read rate.
    Codes(codes::CodesArgs),
    /// Run many concurrent clients (discovery, uploads, grabs, observers) against a
    /// running server for a while; print discovery latency and what each role counted,
    /// every transfer checked; exit 1 when anything failed, mismatched or was lost.
    Load(load::LoadArgs),
    /// Fill a `coapcam rd` (a child process) with registrations over loopback (10,000 by
    /// default) and time lookups of each kind; print its resident memory before and
    /// after and each lookup's median, 95th percentile and longest time.
    Rd(rd::RdArgs),
}

#[derive(Debug, Args)]
struct AccuracyArgs {
    /// Number of scenes, at least 1 (by default 40 for `boxes`, every scene of the lane
    /// set for `lane`, 500 for `cert`).
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..=100_000))]
    scenes: Option<u32>,
    /// Which set: `boxes` (one plain box per scene, one or two cameras), `lane`
    /// (rgbd's lane set: clean and large boxes, cylinders, parcels apart and side by
    /// side, parcels partly out of view, ...; every parcel of a scene held against its
    /// truth, and per case the errors, refusals and silently wrong results) or `cert`
    /// (rgbd's certification set: random stations of 1 to 4 cameras 1.0-2.2 m high and
    /// tilted up to 45 degrees, boxes, cylinders, tubes and bags of every surface, alone
    /// and in groups 0-120 mm apart, labelled boxes; per class the first-pass rate, false
    /// refusals, phantoms, merged pairs and silently wrong results).
    #[arg(long, default_value = "boxes", value_parser = ["boxes", "lane", "cert"])]
    set: String,
    /// With --set cert: the first scene's index (run part of a set, e.g. in two
    /// processes at once).
    #[arg(long, default_value_t = 0)]
    first: u32,
    /// With --set cert: write each scene as a scene file `cert-SEED-INDEX.toml` into DIR
    /// (for `serve --scene`) instead of measuring it.
    #[arg(long, value_name = "DIR")]
    write_scenes: Option<std::path::PathBuf>,
    /// With --set lane: measure every scene this many times (new frames each time) and
    /// print the spread of each parcel's dimensions.
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..=1000))]
    repeat: u32,
    /// With --set lane: leave the cameras as they start (the floor sent, no spatial
    /// filter), as `measure --all` without --prepare measures.
    #[arg(long)]
    raw: bool,
    /// With --set lane or cert: the accuracy division d, mm (see `measure --division-mm`).
    #[arg(long, value_name = "MM", default_value = "5", value_parser = super::values::division_mm)]
    division_mm: f64,
    /// Seed of the scene generator.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Print one JSON object (every scene and the summary) instead of tables.
    #[arg(long)]
    json: bool,
    /// Start every scene with its cameras uncalibrated (identity 3d-transformation), as
    /// real cameras start: calibrate them on the empty table, where 25 tag36h11 markers
    /// lie, then put the parcel on it and measure. Prints the cameras' pose errors too.
    /// The scenes differ: one to three D415s 0.8-1.6 m from the parcel's lid, tilted
    /// 0-35 degrees, parcels 10-60 cm wide and 2-40 cm high.
    #[arg(long)]
    calibrate: bool,
    #[command(flatten)]
    dimension: DimensionArgs,
}

/// Runs `bench`.
pub(crate) async fn run(args: BenchArgs) -> anyhow::Result<Exit> {
    match args.what {
        BenchKind::Accuracy(a) => accuracy(a).await,
        BenchKind::Transfer(a) => transfer::run(a).await,
        BenchKind::Repr(a) => repr::run(a).await,
        BenchKind::Codes(a) => codes::run(a).await,
        BenchKind::Load(a) => load::run(a).await,
        BenchKind::Rd(a) => rd::run(a).await,
    }
}

async fn accuracy(args: AccuracyArgs) -> anyhow::Result<Exit> {
    if args.set == "lane" {
        if args.calibrate {
            anyhow::bail!("--calibrate has its own scenes: leave out --set lane");
        }
        return lane::run(&lane::Options {
            scenes: args.scenes,
            seed: args.seed,
            repeat: args.repeat,
            raw: args.raw,
            json: args.json,
            division_mm: args.division_mm,
            dimension: args.dimension.config(),
        })
        .await;
    }
    if args.set == "cert" {
        if args.calibrate || args.raw || args.repeat != 1 {
            anyhow::bail!("--set cert takes neither --calibrate, --raw nor --repeat");
        }
        return cert::run(cert::Options {
            scenes: args.scenes,
            first: args.first,
            seed: args.seed,
            json: args.json,
            division_mm: args.division_mm,
            dimension: args.dimension.config(),
            write_scenes: args.write_scenes,
        })
        .await;
    }
    let config = accuracy::Config {
        scenes: args.scenes.map_or(40, |n| n as usize),
        seed: args.seed,
        calibrate: args.calibrate,
        dimension: args.dimension.config(),
    };
    let rows = accuracy::run(&config, |row| {
        for w in &row.warnings {
            eprintln!("coapcam: warning: {w}");
        }
        if args.json { Ok(()) } else { print_row(row) }
    })
    .await?;
    let summary = Summary::of(&rows);
    if args.json {
        outln!("{}", accuracy_document(&rows, &summary));
    } else {
        print_summary(&rows, &summary)?;
    }
    Ok(if summary.failed == 0 {
        Exit::Success
    } else {
        Exit::Failure
    })
}

/// `bench accuracy --json`'s document: each scene, and the summary of them all.
fn accuracy_document(rows: &[Row], summary: &Summary) -> serde_json::Value {
    let failed = summary.failed;
    let cycle = summary.cycle_ms;
    let names = ["length_mm", "width_mm", "height_mm", "yaw_deg"];
    let scenes: Vec<serde_json::Value> = rows
        .iter()
        .map(|r| {
            serde_json::json!({
                "scene": r.index, "cameras": r.cameras, "camera_z_m": r.camera_z,
                "truth": r.truth, "measured": r.measured, "cycle_ms": r.cycle_ms, "grab_ms": r.grab_ms,
                "error": r.error,
                "pose_errors_mm_deg": r.calibration.as_ref().map(|c| &c.0),
                "calibrate_ms": r.calibration.as_ref().map(|c| c.1),
                "measured_with_true_poses": r.with_true_poses,
            })
        })
        .collect();
    let errors: serde_json::Map<String, serde_json::Value> = names
        .iter()
        .zip(summary.errors)
        .map(|(n, e)| {
            let json = serde_json::json!({"mae": e.mean, "p95": e.p95, "max": e.max});
            ((*n).to_owned(), json)
        })
        .collect();
    let quantiles =
        |q: Quantiles| serde_json::json!({"median": q.median, "p95": q.p95, "max": q.max});
    serde_json::json!({
        "scenes": scenes, "summary": errors, "failed": failed,
        "cycle_ms": quantiles(cycle),
        "calibration": summary.calibration.as_ref().map(|c| serde_json::json!({
            "cameras": c.cameras,
            "position_mm": quantiles(c.position_mm),
            "angle_deg": quantiles(c.angle_deg),
            "per_camera_ms": {"median": c.median_per_camera_ms, "max": c.max_per_camera_ms},
        })),
    })
}

/// `bench accuracy`'s summary after its lines: the errors, the cycle, the calibration.
fn print_summary(rows: &[Row], summary: &Summary) -> anyhow::Result<()> {
    let failed = summary.failed;
    let cycle = summary.cycle_ms;
    outln!("");
    outln!("{:<10} {:>8} {:>8} {:>8}", "", "MAE", "p95", "max");
    for (name, e) in ["length mm", "width mm", "height mm", "yaw deg"]
        .iter()
        .zip(summary.errors)
    {
        outln!("{name:<10} {:>8.2} {:>8.2} {:>8.2}", e.mean, e.p95, e.max);
    }
    outln!(
        "{} scenes, {failed} failed; cycle median {:.0} ms, p95 {:.0} ms, max {:.0} ms",
        rows.len(),
        cycle.median,
        cycle.p95,
        cycle.max
    );
    if let Some(c) = &summary.calibration {
        outln!("");
        outln!(
            "{:<13} {:>8} {:>8} {:>8}",
            "pose error",
            "median",
            "p95",
            "max"
        );
        for (name, q) in [("position mm", c.position_mm), ("angle deg", c.angle_deg)] {
            outln!("{name:<13} {:>8.2} {:>8.2} {:>8.3}", q.median, q.p95, q.max);
        }
        outln!(
            "{} cameras calibrated; per camera median {:.0} ms, max {:.0} ms (grabs over CoAP, detection, fit)",
            c.cameras,
            c.median_per_camera_ms,
            c.max_per_camera_ms
        );
    }
    Ok(())
}

fn print_row(r: &Row) -> anyhow::Result<()> {
    if let Some((errors, ms)) = &r.calibration {
        let each: Vec<String> = errors
            .iter()
            .map(|[mm, deg]| format!("{mm:.2} mm {deg:.3} deg"))
            .collect();
        let truth = r.with_true_poses.map_or(String::new(), |m| {
            format!(
                "; with the true poses {:.1} x {:.1} x {:.1} mm",
                m[0], m[1], m[2]
            )
        });
        outln!(
            "scene {:>2}: calibrated in {ms:.0} ms, pose errors: {}{truth}",
            r.index,
            each.join(", ")
        );
    }
    let t = r.truth;
    match (r.errors(), &r.error) {
        (Some(e), _) => outln!(
            "scene {:>2}: {} cam at {:.2} m  {:>5.0} x {:>5.0} x {:>5.0} mm  yaw {:>4.1}  error {:>+6.1} {:>+6.1} {:>+6.1} mm {:>+5.1} deg  {:>4.0} ms ({:.0} grab)",
            r.index,
            r.cameras,
            r.camera_z,
            t[0],
            t[1],
            t[2],
            t[3],
            e[0],
            e[1],
            e[2],
            e[3],
            r.cycle_ms,
            r.grab_ms
        ),
        (None, Some(err)) => outln!(
            "scene {:>2}: {} cam at {:.2} m  {:>5.0} x {:>5.0} x {:>5.0} mm  FAILED: {err}",
            r.index,
            r.cameras,
            r.camera_z,
            t[0],
            t[1],
            t[2]
        ),
        (None, None) => {}
    }
    Ok(())
}
