//! `coapcam bench`: the subcommands' flags; `bench accuracy` here, printing what
//! `coapcam::bench::accuracy` measured (a line per scene and the summary, or JSON);
//! `bench transfer`, `bench repr` and `bench load` are the files beside this one (a
//! command with subcommands is a folder of `cli/`).

use clap::{Args, Subcommand};

use super::{DimensionArgs, Exit, outln};
use coapcam::bench::accuracy::lane::{self, CaseSummary, Outcome};
use coapcam::bench::accuracy::{self, Quantiles, Row, Summary};
use coapcam::report::{Billing, Division};

mod cert;
mod codes;
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
    /// Measure a built-in set of synthetic parcels (10-80 cm, yaw 0-90 deg, 2-60 cm high,
    /// one or two D415s 0.8-1.5 m above the floor) end to end over CoAP and print the
    /// errors.
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
        return accuracy_lane(args).await;
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
    let failed = summary.failed;
    let cycle = summary.cycle_ms;
    let names = ["length_mm", "width_mm", "height_mm", "yaw_deg"];
    if args.json {
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
        outln!(
            "{}",
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
        );
    } else {
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
    }
    Ok(if failed == 0 {
        Exit::Success
    } else {
        Exit::Failure
    })
}

async fn accuracy_lane(args: AccuracyArgs) -> anyhow::Result<Exit> {
    if args.calibrate {
        anyhow::bail!("--calibrate has its own scenes: leave out --set lane");
    }
    let billing = Billing {
        division: Division {
            d_mm: args.division_mm,
        },
        ..Billing::default()
    };
    let config = lane::Config {
        scenes: args
            .scenes
            .map_or(rgbd::lane::LANE_SET_SIZE, |n| n as usize),
        seed: args.seed,
        repeat: args.repeat as usize,
        raw: args.raw,
        dimension: args.dimension.config(),
        billing,
    };
    let rows = lane::run(&config, |row| {
        if args.json {
            return Ok(());
        }
        let each: Vec<String> = row
            .objects
            .iter()
            .map(|o| {
                let t = o.truth;
                let what = match (&o.outcome, o.errors()) {
                    (Outcome::Measured { shape, .. }, Some(e)) => format!(
                        "{:+.1} {:+.1} {:+.1} mm {shape}{}",
                        e[0],
                        e[1],
                        e[2],
                        if o.silently_wrong(&billing) {
                            " SILENTLY WRONG"
                        } else {
                            ""
                        }
                    ),
                    (Outcome::Refused(why), _) => format!("refused: {why}"),
                    _ => "MISSING".to_owned(),
                };
                format!("{:.0} x {:.0} x {:.0}: {what}", t[0], t[1], t[2])
            })
            .collect();
        let failed = row
            .error
            .as_deref()
            .map_or(String::new(), |e| format!(" FAILED: {e}"));
        outln!(
            "scene {:>2}.{} {:<9} {} cam {:>5.0} ms  {}{failed}",
            row.index,
            row.run,
            row.case,
            row.cameras,
            row.cycle_ms,
            each.join("; ")
        );
        Ok(())
    })
    .await?;
    let mut cases: Vec<&str> = Vec::new();
    for r in &rows {
        if !cases.contains(&r.case) {
            cases.push(r.case);
        }
    }
    let mut summaries: Vec<CaseSummary> = cases
        .iter()
        .map(|c| CaseSummary::of(&rows, Some(c), &billing))
        .collect();
    summaries.push(CaseSummary::of(&rows, None, &billing));
    let spreads = lane::spreads(&rows);
    let cycles: Vec<f64> = rows.iter().map(|r| r.cycle_ms).collect();
    let cycle = Quantiles::of(&cycles);
    if args.json {
        let json: Vec<serde_json::Value> = summaries
            .iter()
            .map(|s| {
                // A case with nothing measured has no errors: null, never NaN.
                let e = |k: usize| {
                    serde_json::json!({"mean_signed": finite(s.mean_signed[k]),
                        "mae": finite(s.errors[k].mean), "p95": finite(s.errors[k].p95),
                        "max": finite(s.errors[k].max)})
                };
                serde_json::json!({"case": s.case, "parcels": s.objects, "measured": s.measured,
                    "refused": s.refused, "missing": s.missing, "silently_wrong": s.silently_wrong,
                    "length_mm": e(0), "width_mm": e(1), "height_mm": e(2)})
            })
            .collect();
        let scenes: Vec<serde_json::Value> = rows
            .iter()
            .map(|r| {
                let objects: Vec<serde_json::Value> = r
                    .objects
                    .iter()
                    .map(|o| match &o.outcome {
                        Outcome::Measured {
                            raw,
                            reported,
                            shape,
                        } => serde_json::json!({
                            "truth": o.truth, "measured": raw, "reported": reported,
                            "shape": shape, "silently_wrong": o.silently_wrong(&billing)}),
                        Outcome::Refused(why) => {
                            serde_json::json!({"truth": o.truth, "refused": why})
                        }
                        Outcome::Missing => serde_json::json!({"truth": o.truth, "missing": true}),
                    })
                    .collect();
                serde_json::json!({"scene": r.index, "run": r.run, "case": r.case,
                    "cameras": r.cameras, "cycle_ms": r.cycle_ms, "error": r.error,
                    "parcels": objects})
            })
            .collect();
        let spread: Vec<serde_json::Value> = spreads
            .iter()
            .map(|(i, p, rep, raw)| {
                serde_json::json!({"scene": i, "parcel": p, "reported_mm": rep, "measured_mm": raw})
            })
            .collect();
        outln!(
            "{}",
            serde_json::json!({"set": "lane", "seed": args.seed, "division_mm": args.division_mm,
                "raw": args.raw, "scenes": scenes, "cases": json,
                "cycle_ms": {"median": cycle.median, "p95": cycle.p95, "max": cycle.max},
                "spreads": if args.repeat > 1 { serde_json::json!(spread) } else { serde_json::Value::Null }})
        );
    } else {
        outln!("");
        outln!(
            "{:<9} {:>4} {:>4} {:>4} {:>4} {:>6} | {:>22} | {:>22} | {:>22}",
            "case",
            "n",
            "ok",
            "ref",
            "miss",
            "silent",
            "length mean/MAE/p95/max",
            "width",
            "height"
        );
        for s in &summaries {
            // A case with nothing measured (every parcel refused) has no errors: "-".
            let e = |k: usize| {
                if s.measured == 0 {
                    "-".to_owned()
                } else {
                    format!(
                        "{:+.1}/{:.1}/{:.1}/{:.1}",
                        s.mean_signed[k], s.errors[k].mean, s.errors[k].p95, s.errors[k].max
                    )
                }
            };
            outln!(
                "{:<9} {:>4} {:>4} {:>4} {:>4} {:>6} | {:>22} | {:>22} | {:>22}",
                s.case,
                s.objects,
                s.measured,
                s.refused,
                s.missing,
                s.silently_wrong,
                e(0),
                e(1),
                e(2)
            );
        }
        outln!(
            "errors in mm (unrounded); silent = a reported number more than 2 d from the truth with no flag (d = {} mm); cycle median {:.0} ms, p95 {:.0} ms",
            args.division_mm,
            cycle.median,
            cycle.p95
        );
        if args.repeat > 1 {
            for (i, p, rep, raw) in &spreads {
                if rep.iter().chain(raw).any(|v| v.is_nan()) {
                    outln!(
                        "scene {i} parcel {p}: no number in any of {} runs (refused or not found)",
                        args.repeat
                    );
                    continue;
                }
                outln!(
                    "scene {i} parcel {p}: spread over {} runs, reported {:.0} / {:.0} / {:.0} mm, measured {:.2} / {:.2} / {:.2} mm",
                    args.repeat,
                    rep[0],
                    rep[1],
                    rep[2],
                    raw[0],
                    raw[1],
                    raw[2]
                );
            }
        }
    }
    let wrong: usize = summaries.last().map_or(0, |s| s.silently_wrong);
    Ok(if wrong == 0 {
        Exit::Success
    } else {
        Exit::Failure
    })
}

/// `v` when it is a number, `None` (JSON null) when it is NaN or infinite.
fn finite(v: f64) -> Option<f64> {
    v.is_finite().then_some(v)
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
