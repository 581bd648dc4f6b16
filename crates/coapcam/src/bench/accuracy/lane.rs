//! `bench accuracy --set lane`: the lane set (`rgbd::lane`: clean and large boxes,
//! cylinders, parcels apart and side by side, parcels partly out of view, ...) measured
//! end to end over CoAP on loopback, every parcel of every scene held against its truth
//! (the smallest upright enclosing cuboid), and per case: the errors, how often the
//! station refused, and how often it was silently wrong (a number more than 2 d from the
//! truth with no flag).

use anyhow::bail;
use geometry::{DimensionConfig, ParcelFit, Shape};
use rgbd::lane::{LaneScene, lane_scene};
use rgbd::scene::{ObjectKind, Truth};

use crate::client::CamClient;
use crate::client::measure::{self, Source, prepare_cameras};
use crate::report::{Billing, ParcelReport};
use crate::stats::{self, AbsSummary};

/// What to run.
#[derive(Debug, Clone)]
pub struct Config {
    /// Number of scenes (at least 1).
    pub scenes: usize,
    /// Seed of the set.
    pub seed: u64,
    /// Measure every scene this many times (new frames each time).
    pub repeat: usize,
    /// Leave the cameras as they start (no floor cut, no spatial filter) instead of
    /// preparing them as `demo` and `measure --prepare` do.
    pub raw: bool,
    /// The measurement's thresholds.
    pub dimension: DimensionConfig,
    /// The accuracy division.
    pub billing: Billing,
}

/// What became of one parcel of a scene.
#[derive(Debug, Clone, PartialEq)]
pub enum Outcome {
    /// A number was given: the unrounded dimensions (mm) and the reported ones (rounded
    /// to the division).
    Measured {
        /// Length, width, height as measured, mm.
        raw: [f64; 3],
        /// As reported, mm.
        reported: [f64; 3],
        /// `cuboid`, `round` or `irregular`.
        shape: String,
    },
    /// The station said why it gives no number.
    Refused(String),
    /// Nothing was measured where the parcel stands.
    Missing,
}

impl Outcome {
    /// What the station's report of `fit` says: its numbers, or its reason to give none.
    pub fn of(fit: &ParcelFit, billing: &Billing, min_coverage: f32) -> Self {
        let report = ParcelReport::new(fit, billing, min_coverage);
        match (
            report.reason,
            report.length_mm,
            report.width_mm,
            report.height_mm,
        ) {
            (None, Some(l), Some(w), Some(h)) => {
                let d = &fit.dimensions;
                Self::Measured {
                    raw: [d.length_mm, d.width_mm, d.height_mm],
                    reported: [l, w, h],
                    shape: report.shape,
                }
            }
            (reason, ..) => Self::Refused(reason.unwrap_or_default()),
        }
    }
}

/// One parcel of one measurement of a scene.
#[derive(Debug, Clone, PartialEq)]
pub struct Object {
    /// Length, width, height of its smallest enclosing cuboid, mm.
    pub truth: [f64; 3],
    /// Whether it is a box.
    pub cuboid: bool,
    /// What it is: the shape it is judged as ([`judged_shape`]).
    pub kind: ObjectKind,
    /// What the station said.
    pub outcome: Outcome,
}

impl Object {
    /// Measured minus true, mm (unrounded).
    pub fn errors(&self) -> Option<[f64; 3]> {
        match &self.outcome {
            Outcome::Measured { raw, .. } => Some([0, 1, 2].map(|k| raw[k] - self.truth[k])),
            _ => None,
        }
    }

    /// A number more than twice its division from the truth, with no flag.
    pub fn silently_wrong(&self, billing: &Billing) -> bool {
        let shape = judged_shape(self.kind);
        match &self.outcome {
            Outcome::Measured { reported, .. } => (0..3).any(|k| {
                (reported[k] - self.truth[k]).abs()
                    > 2.0 * billing.division.of_axis(k, self.truth[k], shape)
            }),
            _ => false,
        }
    }
}

/// The shape an object of `kind` is judged as, which picks the division of each axis
/// ([`Division::of_axis`](crate::report::Division::of_axis)), as a certificate states it:
/// a bag is irregular (its length and width take their own division), whatever shape the
/// station read.
pub fn judged_shape(kind: ObjectKind) -> Shape {
    match kind {
        ObjectKind::Bag => Shape::Irregular,
        ObjectKind::Cylinder | ObjectKind::Tube => Shape::Round,
        _ => Shape::Cuboid,
    }
}

/// One measurement of one scene.
#[derive(Debug, Clone)]
pub struct Row {
    /// The scene's index in the set.
    pub index: usize,
    /// Which time it was measured (0 ..).
    pub run: usize,
    /// The scene's case.
    pub case: &'static str,
    /// Its cameras.
    pub cameras: usize,
    /// Its parcels, largest first, each with what the station said.
    pub objects: Vec<Object>,
    /// The measurement's cycle, ms.
    pub cycle_ms: f64,
    /// Why nothing could be measured.
    pub error: Option<String>,
}

/// How far `p` lies outside the rectangle `corners` (in order around it), metres; 0
/// inside.
pub(crate) fn outside(corners: &[[f64; 2]; 4], p: [f64; 2]) -> f64 {
    let c0 = corners[0];
    let axis = |to: [f64; 2]| {
        let e = [to[0] - c0[0], to[1] - c0[1]];
        let n = e[0].hypot(e[1]).max(1e-9);
        ([e[0] / n, e[1] / n], n)
    };
    let ((a, la), (b, lb)) = (axis(corners[1]), axis(corners[3]));
    let d = [p[0] - c0[0], p[1] - c0[1]];
    let (s, t) = (d[0] * a[0] + d[1] * a[1], d[0] * b[0] + d[1] * b[1]);
    let beyond = |v: f64, len: f64| (-v).max(v - len).max(0.0);
    beyond(s, la).hypot(beyond(t, lb))
}

/// The measured parcel standing where `truth` stands: the one whose footprint holds the
/// truth's centre, or comes nearest to it, within a quarter of the truth's width (two
/// parcels side by side measured as one both match it).
fn matching<'a>(truth: &Truth, fits: &'a [ParcelFit]) -> Option<&'a ParcelFit> {
    let d = |f: &&ParcelFit| outside(&f.dimensions.corners_m, truth.center);
    fits.iter()
        .min_by(|a, b| d(a).total_cmp(&d(b)))
        .filter(|f| d(f) <= truth.size[1] / 4.0)
}

/// Measures scene `lane` once through `client`.
async fn measure_scene(
    client: &CamClient,
    lane: &LaneScene,
    run: usize,
    config: &Config,
) -> anyhow::Result<Row> {
    let serials: Vec<String> = lane
        .scene
        .cameras
        .iter()
        .map(|c| c.serial.to_string())
        .collect();
    if !config.raw && run == 0 {
        prepare_cameras(client, &serials, 1.0, false).await?;
    }
    let mut row = Row {
        index: lane.index,
        run,
        case: lane.case.name(),
        cameras: serials.len(),
        objects: Vec::new(),
        cycle_ms: f64::NAN,
        error: None,
    };
    let m = match measure::measure_once(client, &Source::All, &config.dimension).await {
        Ok(m) => m,
        Err(e) => {
            row.error = Some(crate::error_text(&e));
            return Ok(row);
        }
    };
    row.cycle_ms = m.cycle.as_secs_f64() * 1e3;
    for truth in &lane.truths {
        let outcome = match matching(truth, &m.table.fits) {
            None => Outcome::Missing,
            Some(fit) => Outcome::of(fit, &config.billing, config.dimension.min_coverage),
        };
        row.objects.push(Object {
            truth: [truth.length_mm(), truth.width_mm(), truth.height_mm()],
            cuboid: truth.cuboid,
            kind: truth.kind,
            outcome,
        });
    }
    Ok(row)
}

/// Runs the scenes of `config` one after the other (each `repeat` times), handing each
/// row to `on_row` as it is measured; every row.
pub async fn run(
    config: &Config,
    mut on_row: impl FnMut(&Row) -> anyhow::Result<()>,
) -> anyhow::Result<Vec<Row>> {
    if config.scenes == 0 || config.repeat == 0 {
        bail!("--scenes and --repeat must be at least 1");
    }
    let mut rows = Vec::new();
    let make = |index| lane_scene(config.seed, index);
    super::each_scene(
        "lane",
        0..config.scenes,
        make,
        |l| &l.scene,
        async |client, lane| {
            for run in 0..config.repeat {
                let row = measure_scene(client, lane, run, config).await?;
                on_row(&row)?;
                rows.push(row);
            }
            Ok(())
        },
    )
    .await?;
    Ok(rows)
}

/// What the rows of one case say together.
#[derive(Debug, Clone, PartialEq)]
pub struct CaseSummary {
    /// The case.
    pub case: String,
    /// Parcels measured (a parcel measured `repeat` times counts `repeat` times).
    pub objects: usize,
    /// Given a number.
    pub measured: usize,
    /// Refused with a reason.
    pub refused: usize,
    /// Not found where they stand, or the measurement failed.
    pub missing: usize,
    /// A number more than 2 d from the truth, with no flag.
    pub silently_wrong: usize,
    /// Mean signed error of length, width, height of the measured ones, mm.
    pub mean_signed: [f64; 3],
    /// Their absolute errors (mean, p95, max), mm.
    pub errors: [AbsSummary; 3],
}

impl CaseSummary {
    /// Of the rows of `case` (every case with `None`).
    pub fn of(rows: &[Row], case: Option<&str>, billing: &Billing) -> Self {
        let objects: Vec<&Object> = rows
            .iter()
            .filter(|r| case.is_none_or(|c| r.case == c))
            .flat_map(|r| r.objects.iter())
            .collect();
        let errors: Vec<[f64; 3]> = objects.iter().filter_map(|o| o.errors()).collect();
        let column = |k: usize| errors.iter().map(|e| e[k]).collect::<Vec<f64>>();
        let mean = |v: Vec<f64>| {
            if v.is_empty() {
                f64::NAN
            } else {
                v.iter().sum::<f64>() / v.len() as f64
            }
        };
        let failed: usize = rows
            .iter()
            .filter(|r| case.is_none_or(|c| r.case == c) && r.error.is_some())
            .count();
        Self {
            case: case.unwrap_or("all").to_owned(),
            objects: objects.len(),
            measured: errors.len(),
            refused: objects
                .iter()
                .filter(|o| matches!(o.outcome, Outcome::Refused(_)))
                .count(),
            missing: objects
                .iter()
                .filter(|o| o.outcome == Outcome::Missing)
                .count()
                + failed,
            silently_wrong: objects.iter().filter(|o| o.silently_wrong(billing)).count(),
            mean_signed: [0, 1, 2].map(|k| mean(column(k))),
            errors: [0, 1, 2].map(|k| AbsSummary::of(&column(k))),
        }
    }
}

/// Per scene and parcel, the spread (largest minus smallest) of the repeated
/// measurements' reported and unrounded length, width and height, mm.
pub fn spreads(rows: &[Row]) -> Vec<(usize, usize, [f64; 3], [f64; 3])> {
    let mut out = Vec::new();
    let mut indices: Vec<usize> = rows.iter().map(|r| r.index).collect();
    indices.dedup();
    for index in indices {
        let runs: Vec<&Row> = rows.iter().filter(|r| r.index == index).collect();
        let parcels = runs.iter().map(|r| r.objects.len()).max().unwrap_or(0);
        for p in 0..parcels {
            let values = |reported: bool| {
                [0, 1, 2].map(|k| {
                    let v: Vec<f64> = runs
                        .iter()
                        .filter_map(|r| match r.objects.get(p).map(|o| &o.outcome) {
                            Some(Outcome::Measured {
                                raw, reported: rep, ..
                            }) => Some(if reported { rep[k] } else { raw[k] }),
                            _ => None,
                        })
                        .collect();
                    stats::Spread::of(&v).map_or(f64::NAN, |s| s.max - s.min)
                })
            };
            out.push((index, p, values(true), values(false)));
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Every kind of synthetic object, with the shape it is judged as: a kind added to
    /// rgbd's scenes (and `ObjectKind::ALL`) fails here until it says how it is judged.
    /// `ObjectKind` is non-exhaustive, so `judged_shape` ends in a wildcard that would
    /// judge a new kind as a box without a word.
    #[test]
    fn every_kind_of_object_is_judged_as_a_shape_stated_here() {
        assert_eq!(
            ObjectKind::ALL.map(|kind| (kind, judged_shape(kind))),
            [
                (ObjectKind::Box, Shape::Cuboid),
                (ObjectKind::Cylinder, Shape::Round),
                (ObjectKind::Tube, Shape::Round),
                (ObjectKind::Bag, Shape::Irregular),
            ]
        );
    }
}
