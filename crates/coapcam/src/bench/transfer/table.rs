//! The Markdown tables of `bench transfer`: one row per (link, size) with a column per
//! mode and the ratios of medians, one row per (size, mode) of the pair runs, and the
//! failed runs under each.

use std::fmt::Write as _;

use super::body::Body;
use super::config::{BLOCK_BYTES, Config, FAIR_SHARE, MIN_RATIO_RUNS, Mode, PAIR_LINK};
use super::runs::{Cell, PairCell};
use crate::stats::Spread;

pub(super) fn table(config: &Config, bodies: &[Body], cells: &[Cell]) -> String {
    let (links, modes) = (&config.links, &config.modes);
    let mut s = String::new();
    let _ = writeln!(
        s,
        "Whole-body GETs, {BLOCK_BYTES}-byte blocks for CoAP, through netem (in process): \
         seconds of the client's whole process, median of the successful runs [min-max], \
         their 95th percentile (nearest rank) and successful/runs (runs per cell: {}, \
         stop-and-wait and libcoap: {}; cap {} s; seed {}). Ratios are of medians, and only \
         where both cells have at least {MIN_RATIO_RUNS} successful runs. Every body compared \
         bit-exact with the original.",
        config.runs,
        config.slow_runs,
        config.cap.as_secs_f64(),
        config.seed
    );
    let _ = writeln!(s);
    let ratios = ratio_columns(modes);
    let mut header = vec!["link".to_owned(), "bytes".to_owned()];
    header.extend(modes.iter().map(|m| m.name().to_owned()));
    header.extend(
        ratios
            .iter()
            .map(|(a, b)| format!("{} / {}", a.short(), b.short())),
    );
    let mut rows = Vec::new();
    for &link in links {
        for body in bodies {
            let cell = |m: Mode| {
                cells
                    .iter()
                    .find(|c| c.link == link && c.size == body.size && c.mode == m)
            };
            let mut row = vec![link.name().to_owned(), body.size.to_string()];
            row.extend(
                modes
                    .iter()
                    .map(|&m| cell(m).map_or_else(String::new, Cell::text)),
            );
            for &(a, b) in &ratios {
                let median = |m| {
                    cell(m)
                        .filter(|c| c.ok_count() >= MIN_RATIO_RUNS)
                        .and_then(Cell::stats)
                        .map(|s| s.median)
                };
                row.push(match (median(a), median(b)) {
                    (Some(a), Some(b)) if b > 0.0 => format!("{:.2}x", a / b),
                    _ => "-".into(),
                });
            }
            rows.push(row);
        }
    }
    s += &markdown(&header, &rows, 1);
    let mut notes = Vec::new();
    for c in cells {
        if let Some(why) = &c.skipped {
            notes.push(format!(
                "{} {} B {}: unavailable: {why}",
                c.link.name(),
                c.size,
                c.mode.name()
            ));
            continue;
        }
        for (i, r) in c.runs.iter().enumerate() {
            if let Some(e) = &r.error {
                notes.push(format!(
                    "{} {} B {} run {}: {e}",
                    c.link.name(),
                    c.size,
                    c.mode.name(),
                    i + 1
                ));
            }
        }
    }
    failures(&mut s, &notes);
    s.trim_end().to_owned()
}

/// The list of failed runs under a table, if any.
fn failures(s: &mut String, notes: &[String]) {
    if !notes.is_empty() {
        let _ = writeln!(s, "\nFailed or not run:");
        for n in notes {
            let _ = writeln!(s, "- {n}");
        }
    }
}

/// A markdown table of `header` and `rows`, its columns padded to their widest cell: the
/// first `text` columns to the left, the others (numbers) to the right.
fn markdown(header: &[String], rows: &[Vec<String>], text: usize) -> String {
    let widths: Vec<usize> = (0..header.len())
        .map(|i| {
            rows.iter()
                .map(|r| r[i].chars().count())
                .chain([header[i].chars().count()])
                .max()
                .unwrap_or(0)
        })
        .collect();
    let line = |cells: &[String]| {
        let mut l = String::from("|");
        for (i, c) in cells.iter().enumerate() {
            if i < text {
                let _ = write!(l, " {c:<w$} |", w = widths[i]);
            } else {
                let _ = write!(l, " {c:>w$} |", w = widths[i]);
            }
        }
        l
    };
    let mut s = String::new();
    let _ = writeln!(s, "{}", line(header));
    let mut rule = String::from("|");
    for (i, w) in widths.iter().enumerate() {
        let dashes = "-".repeat(*w);
        if i < text {
            let _ = write!(rule, "-{dashes}-|");
        } else {
            let _ = write!(rule, "-{dashes}:|");
        }
    }
    let _ = writeln!(s, "{rule}");
    for row in rows {
        let _ = writeln!(s, "{}", line(row));
    }
    s
}

/// The markdown table of the pair runs, its heading and the failures under it.
pub(super) fn pair_table(config: &Config, cells: &[PairCell]) -> String {
    let mut s = String::new();
    let _ = writeln!(
        s,
        "Two transfers at once through {}: two clients of one mode started together through \
         one relay to one server ({} runs per row; cap {} s; seed {}). Smaller share: the \
         smaller client's part of the payload bytes the relay had delivered to the two when \
         the first one ended; a run holds when it is at least {:.0} %. Link utilisation: both \
         bodies over the later client's time, as a fraction of 50 Mbit/s. Medians of the \
         successful runs (both clients bit-exact within the cap) [min-max].",
        PAIR_LINK.name(),
        config.pairs,
        config.cap.as_secs_f64(),
        config.seed,
        FAIR_SHARE * 100.0
    );
    let _ = writeln!(s);
    let header = [
        "bytes",
        "mode",
        "smaller share",
        "holds",
        "link utilisation",
        "ok",
    ]
    .map(str::to_owned);
    let rows: Vec<Vec<String>> = cells.iter().map(PairCell::row).collect();
    s += &markdown(&header, &rows, 2);
    let mut notes = Vec::new();
    for c in cells {
        if let Some(why) = &c.skipped {
            notes.push(format!(
                "{} B {}: unavailable: {why}",
                c.size,
                c.mode.name()
            ));
            continue;
        }
        for (i, run) in c.runs.iter().enumerate() {
            for (k, client) in run.clients.iter().enumerate() {
                if let Some(e) = &client.error {
                    notes.push(format!(
                        "{} B {} pair run {} client {}: {e}",
                        c.size,
                        c.mode.name(),
                        i + 1,
                        k + 1
                    ));
                }
            }
        }
    }
    failures(&mut s, &notes);
    s.trim_end().to_owned()
}

impl Cell {
    /// The table's text: `median [min-max] p95 P ok/runs`.
    pub(super) fn text(&self) -> String {
        if self.skipped.is_some() {
            return "unavailable".into();
        }
        let count = format!("{}/{}", self.ok_count(), self.runs.len());
        match (self.stats(), self.p95()) {
            (Some(Spread { median, min, max }), Some(p95)) => {
                format!("{median:.3} [{min:.3}-{max:.3}] p95 {p95:.3} {count}")
            }
            _ => format!("failed {count}"),
        }
    }
}

impl PairCell {
    /// The table's row.
    pub(super) fn row(&self) -> Vec<String> {
        let mut row = vec![self.size.to_string(), self.mode.name().to_owned()];
        if self.skipped.is_some() {
            row.extend(["unavailable", "", "", ""].map(str::to_owned));
            return row;
        }
        let percent = |s: Option<Spread>| {
            s.map_or_else(
                || "-".to_owned(),
                |Spread { median, min, max }| {
                    format!(
                        "{:.1} % [{:.1}-{:.1}]",
                        median * 100.0,
                        min * 100.0,
                        max * 100.0
                    )
                },
            )
        };
        let ok = self.ok_runs().count();
        let runs = self.runs.len();
        row.extend([
            percent(self.smaller_shares()),
            format!("{}/{runs}", self.holding()),
            percent(self.utilisation()),
            format!("{ok}/{runs}"),
        ]);
        row
    }
}

/// A ratio column: the median of `num`'s cell over `den`'s.
fn ratio_columns(modes: &[Mode]) -> Vec<(Mode, Mode)> {
    let has = |m: Mode| modes.contains(&m);
    let mut out = Vec::new();
    if has(Mode::Window) && has(Mode::Quic) {
        out.push((Mode::Window, Mode::Quic));
    }
    let reference = if has(Mode::Window) {
        Some(Mode::Window)
    } else if has(Mode::Quic) {
        Some(Mode::Quic)
    } else {
        None
    };
    if let Some(den) = reference {
        for &m in modes {
            if m != Mode::Window && m != Mode::Quic {
                out.push((m, den));
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ratios_compare_with_window_and_window_with_quic() {
        let all = [
            Mode::StopAndWait,
            Mode::Window,
            Mode::QBlock,
            Mode::Libcoap431,
            Mode::Libcoap435,
            Mode::Quic,
        ];
        let names: Vec<String> = ratio_columns(&all)
            .iter()
            .map(|(a, b)| format!("{} / {}", a.short(), b.short()))
            .collect();
        assert_eq!(
            names,
            [
                "window / QUIC",
                "stop-and-wait / window",
                "q-block / window",
                "libcoap-4.3.1 / window",
                "libcoap-4.3.5 / window"
            ]
        );
        assert_eq!(ratio_columns(&[Mode::Libcoap431, Mode::Quic]).len(), 1);
        assert!(ratio_columns(&[Mode::Libcoap431]).is_empty());
    }
}
