//! `bench accuracy --set lane`: a line per scene as it is measured, then per case the
//! parcels measured, refused and missed with their errors, and with `--repeat` each
//! parcel's spread (or one JSON object).

use coapcam::bench::accuracy::Quantiles;
use coapcam::bench::accuracy::lane::{self, CaseSummary, Outcome, Row};
use coapcam::report::{Billing, Division};

use crate::cli::{Exit, outln};

/// What `bench accuracy --set lane` was asked.
pub(super) struct Options {
    pub(super) scenes: Option<u32>,
    pub(super) seed: u64,
    pub(super) repeat: u32,
    pub(super) raw: bool,
    pub(super) json: bool,
    pub(super) division_mm: f64,
    pub(super) dimension: geometry::DimensionConfig,
}

/// A parcel's spread over the runs: scene, parcel, reported and measured L x W x H, mm.
type Spread = (usize, usize, [f64; 3], [f64; 3]);

/// Runs `bench accuracy --set lane`: a failure when a number was silently wrong.
pub(super) async fn run(args: &Options) -> anyhow::Result<Exit> {
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
        dimension: args.dimension,
        billing,
    };
    let rows = lane::run(&config, |row| {
        if args.json {
            return Ok(());
        }
        print_row(row, &billing)
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
        outln!(
            "{}",
            document(args, &rows, &summaries, &spreads, cycle, &billing)
        );
    } else {
        print_summary(args, &summaries, &spreads, cycle)?;
    }
    let wrong: usize = summaries.last().map_or(0, |s| s.silently_wrong);
    Ok(if wrong == 0 {
        Exit::Success
    } else {
        Exit::Failure
    })
}

/// A scene's line: each parcel's truth and its errors, refusal or absence.
fn print_row(row: &Row, billing: &Billing) -> anyhow::Result<()> {
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
                    if o.silently_wrong(billing) {
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
}

/// The JSON object: the scenes, each case's summary, the cycle, the spreads.
fn document(
    args: &Options,
    rows: &[Row],
    summaries: &[CaseSummary],
    spreads: &[Spread],
    cycle: Quantiles,
    billing: &Billing,
) -> serde_json::Value {
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
                        "shape": shape, "silently_wrong": o.silently_wrong(billing)}),
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
    serde_json::json!({"set": "lane", "seed": args.seed, "division_mm": args.division_mm,
            "raw": args.raw, "scenes": scenes, "cases": json,
            "cycle_ms": {"median": cycle.median, "p95": cycle.p95, "max": cycle.max},
            "spreads": if args.repeat > 1 { serde_json::json!(spread) } else { serde_json::Value::Null }})
}

/// The table of the cases after the scenes' lines, and with --repeat the spreads.
fn print_summary(
    args: &Options,
    summaries: &[CaseSummary],
    spreads: &[Spread],
    cycle: Quantiles,
) -> anyhow::Result<()> {
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
    for s in summaries {
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
        for (i, p, rep, raw) in spreads {
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
    Ok(())
}

/// `v` when it is a number, `None` (JSON null) when it is NaN or infinite.
fn finite(v: f64) -> Option<f64> {
    v.is_finite().then_some(v)
}
