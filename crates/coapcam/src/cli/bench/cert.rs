//! `bench accuracy --set cert`: a line per scene, then per class the first-pass rate and
//! what kept the rest from it (or one JSON object).

use crate::cli::{Exit, outln};
use coapcam::bench::accuracy::cert::{self, ClassSummary, ObjectResult, Row};
use coapcam::bench::accuracy::lane::Outcome;
use coapcam::report::{Billing, Division};

/// One object in a scene's line: kind, truth, and what became of it.
fn describe(o: &ObjectResult, billing: &Billing) -> String {
    let t = &o.object.truth;
    let mut text = format!(
        "{} {} {:.0}x{:.0}x{:.0}",
        o.object.surface.name(),
        t.kind.name(),
        t.length_mm(),
        t.width_mm(),
        t.height_mm()
    );
    if !o.object.accepted() {
        let j = &o.object.judged;
        let why: Vec<&str> = [
            (!j.isolated(), "close"),
            (!j.in_view, "out of view"),
            (!j.returns_depth, "no depth"),
            (!j.measurable, "within 1 d of the minimum"),
        ]
        .iter()
        .filter(|(b, _)| *b)
        .map(|(_, w)| *w)
        .collect();
        text.push_str(&format!(" (not accepted: {})", why.join(", ")));
    }
    text.push_str(": ");
    text.push_str(&match (&o.outcome, o.raw_errors()) {
        (Outcome::Measured { .. }, Some(e)) => format!(
            "{:+.1} {:+.1} {:+.1} mm{}",
            e[0],
            e[1],
            e[2],
            if o.silently_wrong(billing) {
                " SILENTLY WRONG"
            } else if !o.within_1d(billing) {
                " OFF"
            } else {
                ""
            }
        ),
        (Outcome::Refused(why), _) => format!("refused: {why}"),
        _ => "MISSING".to_owned(),
    });
    match o.code_read {
        Some(true) => text.push_str(", code read"),
        Some(false) => text.push_str(", CODE UNREAD"),
        None => {}
    }
    if o.code_read.is_some() {
        match o.module_px {
            Some(px) => text.push_str(&format!(" ({px:.1} px a module)")),
            None => text.push_str(" (label seen by no camera)"),
        }
    }
    if o.merged {
        text.push_str(", MERGED");
    }
    if o.phantoms > 0 {
        text.push_str(&format!(", {} PHANTOM", o.phantoms));
    }
    text
}

fn print_row(row: &Row, billing: &Billing) -> anyhow::Result<()> {
    let each: Vec<String> = row.objects.iter().map(|o| describe(o, billing)).collect();
    let failed = row
        .error
        .as_deref()
        .map_or(String::new(), |e| format!(" FAILED: {e}"));
    let spacing = row
        .spacing_mm
        .map_or_else(|| "alone".to_owned(), |s| format!("{s:.0} mm"));
    outln!(
        "scene {:>3} {} cam {:>6} {:>5.0} ms  {}{failed}",
        row.index,
        row.cameras,
        spacing,
        row.cycle_ms,
        each.join("; ")
    );
    Ok(())
}

fn json_object(o: &ObjectResult, billing: &Billing) -> serde_json::Value {
    let t = &o.object.truth;
    let j = &o.object.judged;
    let outcome = match &o.outcome {
        Outcome::Measured {
            raw,
            reported,
            shape,
        } => {
            serde_json::json!({"measured": raw, "reported": reported, "shape": shape})
        }
        Outcome::Refused(why) => serde_json::json!({"refused": why}),
        Outcome::Missing => serde_json::json!({"missing": true}),
    };
    serde_json::json!({
        "kind": t.kind.name(), "surface": o.object.surface.name(), "flat": o.object.flat,
        "truth": [t.length_mm(), t.width_mm(), t.height_mm()], "center_m": t.center,
        "label": o.object.label.as_ref().map(|l| serde_json::json!({
            "kind": format!("{:?}", l.kind).to_lowercase(), "text": l.text, "size_m": l.size,
            "module_px": o.module_px})),
        "gap_mm": j.gap_m.map(|g| g * 1e3), "in_view": j.in_view,
        "returns_depth": j.returns_depth, "measurable": j.measurable,
        "accepted": j.accepted(),
        "outcome": outcome, "code_read": o.code_read, "merged": o.merged,
        "phantoms": o.phantoms, "first_pass": o.first_pass(billing),
        "silently_wrong": o.silently_wrong(billing),
    })
}

/// `v` when it is a number, `None` (JSON null) when it is NaN or infinite.
fn finite(v: f64) -> Option<f64> {
    v.is_finite().then_some(v)
}

/// The flags of `bench accuracy` that `--set cert` takes.
pub(super) struct Options {
    pub(super) scenes: Option<u32>,
    pub(super) first: u32,
    pub(super) seed: u64,
    pub(super) json: bool,
    pub(super) division_mm: f64,
    pub(super) dimension: geometry::DimensionConfig,
    pub(super) write_scenes: Option<std::path::PathBuf>,
}

/// Writes scenes `first .. first + count` of the set of `seed` into `dir`, a line for
/// each with its objects and what a certified system makes of them.
fn write_scenes(
    dir: &std::path::Path,
    seed: u64,
    first: usize,
    count: usize,
) -> anyhow::Result<Exit> {
    use anyhow::Context as _;
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    for index in first..first + count {
        let cert = rgbd::cert::cert_scene(seed, index);
        let path = dir.join(format!("cert-{seed}-{index}.toml"));
        std::fs::write(&path, cert.scene.to_toml())
            .with_context(|| format!("writing {}", path.display()))?;
        let each: Vec<String> = cert
            .objects
            .iter()
            .map(|o| {
                let t = &o.truth;
                let j = &o.judged;
                format!(
                    "{} {} {:.0}x{:.0}x{:.0} at ({:.3}, {:.3}) gap {} in view {} depth {} -> {}",
                    o.surface.name(),
                    t.kind.name(),
                    t.length_mm(),
                    t.width_mm(),
                    t.height_mm(),
                    t.center[0],
                    t.center[1],
                    j.gap_m
                        .map_or_else(|| "-".to_owned(), |g| format!("{:.1} mm", g * 1e3)),
                    j.in_view,
                    j.returns_depth,
                    if j.accepted() {
                        "accepted"
                    } else {
                        "not accepted"
                    }
                )
            })
            .collect();
        outln!("{}: {}", path.display(), each.join("; "));
    }
    Ok(Exit::Success)
}

/// The whole run as one JSON object: every scene's objects, and per class the summary.
fn print_json(
    args: &Options,
    rows: &[Row],
    classes: &[ClassSummary],
    billing: &Billing,
    failed: usize,
) -> anyhow::Result<()> {
    let scenes: Vec<serde_json::Value> = rows
        .iter()
        .map(|r| {
            let objects: Vec<serde_json::Value> =
                r.objects.iter().map(|o| json_object(o, billing)).collect();
            serde_json::json!({"scene": r.index, "cameras": r.cameras,
                "spacing_mm": r.spacing_mm, "cycle_ms": finite(r.cycle_ms),
                "codes_ms": finite(r.codes_ms), "error": r.error, "phantoms": r.phantoms,
                "objects": objects})
        })
        .collect();
    let summary: Vec<serde_json::Value> = classes
        .iter()
        .map(|c| {
            serde_json::json!({"class": c.class, "value": c.value, "objects": c.objects,
                "accepted": c.accepted, "first_pass": c.first_pass,
                "first_pass_pct": finite(c.first_pass_pct()),
                "false_refusals": c.false_refusals, "off": c.off, "unread": c.unread,
                "out_of_reach": c.out_of_reach,
                "codes_read": c.read[0], "labelled": c.read[1],
                "codes_read_at_limit": c.read_at_limit[0],
                "labelled_at_limit": c.read_at_limit[1], "missing": c.missing,
                "merged": c.merged, "phantoms": c.phantoms,
                "silently_wrong": c.silently_wrong})
        })
        .collect();
    outln!(
        "{}",
        serde_json::json!({"set": "cert", "seed": args.seed, "first": args.first,
            "division_mm": args.division_mm, "scenes": scenes, "classes": summary,
            "failed": failed})
    );
    Ok(())
}

/// Per class a line of the table, then what its columns mean.
fn print_table(
    args: &Options,
    rows: &[Row],
    classes: &[ClassSummary],
    phantoms: usize,
    failed: usize,
) -> anyhow::Result<()> {
    outln!("");
    outln!(
        "{:<8} {:<10} {:>5} {:>5} {:>5} {:>6} {:>4} {:>4} {:>6} {:>5} {:>9} {:>9} {:>4} {:>6} {:>7} {:>6}",
        "class",
        "value",
        "n",
        "acc",
        "pass",
        "pass%",
        "ref",
        "off",
        "unread",
        "small",
        "read",
        "read>=lim",
        "miss",
        "merged",
        "phantom",
        "silent"
    );
    for c in classes {
        outln!(
            "{:<8} {:<10} {:>5} {:>5} {:>5} {:>6.1} {:>4} {:>4} {:>6} {:>5} {:>9} {:>9} {:>4} {:>6} {:>7} {:>6}",
            c.class,
            c.value,
            c.objects,
            c.accepted,
            c.first_pass,
            c.first_pass_pct(),
            c.false_refusals,
            c.off,
            c.unread,
            c.out_of_reach,
            format!("{}/{}", c.read[0], c.read[1]),
            format!("{}/{}", c.read_at_limit[0], c.read_at_limit[1]),
            c.missing,
            c.merged,
            c.phantoms,
            c.silently_wrong
        );
    }
    outln!(
        "acc = accepted by a certified system (isolated by 20 mm, wholly in a camera's view, \
         returning depth); pass = accepted, every reported dimension within 1 d (d = {} mm) \
         and its code read if its label is in reach (modules of {lim} px or more in a camera's \
         color image, {lim1} px for Data Matrix: the reader's limits); ref = accepted but refused; off = accepted, a number \
         more than 1 d off; unread = accepted, its label in reach, its code not read; small = \
         accepted, its label below the limit in every camera (no reader resolves it: a station \
         that must read it needs the camera nearer or a larger label); read = codes read / labels (all objects); \
         read>=lim = the same over the labels in reach; merged = in a pair 20 mm or more apart measured as one; silent = a number more than \
         2 d off with no flag. {} scenes, {phantoms} phantom parcels, {failed} failed.",
        args.division_mm,
        rows.len(),
        lim = coapcam::vision::codes::MIN_PX_PER_MODULE,
        lim1 = coapcam::vision::codes::CodeKind::DataMatrix.min_px_per_module(),
    );
    Ok(())
}

/// Runs `bench accuracy --set cert`.
pub(super) async fn run(args: Options) -> anyhow::Result<Exit> {
    let count = args
        .scenes
        .map_or(rgbd::cert::CERT_SET_SIZE, |n| n as usize);
    if let Some(dir) = &args.write_scenes {
        return write_scenes(dir, args.seed, args.first as usize, count);
    }
    let billing = Billing {
        division: Division {
            d_mm: args.division_mm,
        },
        ..Billing::default()
    };
    let config = cert::Config {
        scenes: count,
        first: args.first as usize,
        seed: args.seed,
        dimension: args.dimension,
        billing,
    };
    let rows = cert::run(&config, |row| {
        if args.json {
            Ok(())
        } else {
            print_row(row, &billing)
        }
    })
    .await?;
    let classes = ClassSummary::all(&rows, &billing);
    let phantoms: usize = rows.iter().map(|r| r.phantoms).sum();
    let failed = rows.iter().filter(|r| r.error.is_some()).count();
    if args.json {
        print_json(&args, &rows, &classes, &billing, failed)?;
    } else {
        print_table(&args, &rows, &classes, phantoms, failed)?;
    }
    let all = &classes[0];
    Ok(if all.silently_wrong == 0 && failed == 0 {
        Exit::Success
    } else {
        Exit::Failure
    })
}
