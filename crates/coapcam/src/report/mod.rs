//! What a measurement reports, wherever it was made (the client's `measure`, or the
//! server's `/cams/dimensions`): one typed [`Measurement`] (`measurement.rs`: its
//! document, docs/design.md §6, and the text `measure` prints), the parcel, its billing,
//! the codes seen and the query of `/cams/dimensions`.

mod measurement;

use std::collections::BTreeMap;
use std::time::Duration;

use geometry::{DimensionConfig, DimensionError, Dimensions, ParcelFit, PointCloud, Shape, View};
use serde::{Deserialize, Serialize};

use crate::repr::no_depth::{NoDepth, PARCEL_FLOOR_BORDER};
use crate::vision::codes::Code;

pub use measurement::{Found, Measurement, MeasurementError, ParcelReport, Reported, VERSION};

/// How a measurement is reported to an integrator's billing: the volumetric divisor and
/// the division the dimensions are rounded to. Each dimension is given as the number to
/// bill on, the legal result ([`Billing::billed_mm`]): rounded to the nearest multiple of
/// its accuracy division, as a certified dimensioner displays it, or up to a multiple of
/// `round_up_mm` when that is asked for.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Billing {
    /// Divisor of the volumetric weight, cm³ per kg: 5000 by default (the courier
    /// convention), 6000 with some carriers.
    pub divisor_cm3_per_kg: f64,
    /// Round each dimension up to a multiple of this many millimetres instead of to the
    /// nearest multiple of its division (a carrier's rule, e.g. 10); `None` rounds to the
    /// division.
    pub round_up_mm: Option<f64>,
    /// The accuracy division the dimensions are rounded to, and which bounds the range.
    pub division: Division,
}

impl Default for Billing {
    fn default() -> Self {
        Self {
            divisor_cm3_per_kg: 5000.0,
            round_up_mm: None,
            division: Division::default(),
        }
    }
}

/// The accuracy division `d` of the `parcels` list, as a legal-for-trade dimensioner
/// states it: each dimension is rounded to the nearest multiple of its division, which is
/// `d` up to 200 d (1,000 mm at d = 5) and 2 d above (the range switchover); a dimension
/// below 10 d (length, width) or 2 d (height), or above 300 d (length, width) or 200 d
/// (height), is outside the measurable range and refused. An irregular item's length and
/// width take 2 d ([`Division::IRREGULAR`]): the parcel's shape is given with each axis
/// ([`Division::of_axis`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Division {
    /// `d`, millimetres (5 by default).
    pub d_mm: f64,
}

impl Default for Division {
    fn default() -> Self {
        Self { d_mm: 5.0 }
    }
}

impl Division {
    /// Lengths above this many divisions take the doubled division.
    pub const SWITCH: f64 = 200.0;

    /// An irregular item's length and width take this many d, as certificates of
    /// dimensioners state a division of its own for such items (10 mm where boxes have 5).
    /// A camera above sees a bag's top and where its sides start to curve down, not its
    /// foot below them: under a camera straight above, the seen surface of a 167 mm bag
    /// ends at about 80 % of its height, and where the foot lies is known to 3-7 mm, more
    /// than d. Its height, the top of what is seen, keeps d.
    pub const IRREGULAR: f64 = 2.0;

    /// The division of a dimension of `value_mm` (a box's or a height).
    pub fn of(&self, value_mm: f64) -> f64 {
        if value_mm > Self::SWITCH * self.d_mm {
            2.0 * self.d_mm
        } else {
            self.d_mm
        }
    }

    /// The division of dimension `axis` (0 length, 1 width, 2 height) of `value_mm` of a
    /// parcel of `shape`: [`Division::of`], or [`Division::IRREGULAR`] d for the length
    /// and width of an irregular item (neither a box nor round: a bag, a pillow). The one
    /// place a shape picks a division.
    pub fn of_axis(&self, axis: usize, value_mm: f64, shape: Shape) -> f64 {
        let of = self.of(value_mm);
        if shape == Shape::Irregular && axis < 2 {
            of.max(Self::IRREGULAR * self.d_mm)
        } else {
            of
        }
    }

    /// The division of the length and width of a parcel of `shape` up to the switchover:
    /// d, or [`Division::IRREGULAR`] d for an irregular item's ([`Division::of_axis`] of
    /// a short length).
    pub fn footprint_of(&self, shape: Shape) -> f64 {
        self.of_axis(0, 0.0, shape)
    }

    /// `value_mm` rounded to the nearest multiple of its division.
    pub fn round(&self, value_mm: f64) -> f64 {
        let step = self.of(value_mm);
        (value_mm / step).round() * step
    }

    /// The smallest measurable length, width and height, mm.
    pub fn min_mm(&self) -> [f64; 3] {
        [10.0, 10.0, 2.0].map(|k| k * self.d_mm)
    }

    /// The largest measurable length, width and height, mm.
    pub fn max_mm(&self) -> [f64; 3] {
        [300.0, 300.0, 200.0].map(|k| k * self.d_mm)
    }

    /// Why `fit` cannot be given as a number, if it cannot: no depth from it at all, not
    /// seen whole, touching another parcel, or outside the measurable range.
    pub fn refusal(&self, fit: &ParcelFit, min_coverage: f32) -> Option<String> {
        let d = &fit.dimensions;
        if fit.no_depth {
            return Some(NO_DEPTH_REASON.into());
        }
        // Side by side first: a lower parcel beside a higher one is also hidden behind
        // it (out of view), and separating them is what makes both measurable.
        if !fit.isolated {
            return Some("parcels side by side: the parcel touches another one".into());
        }
        if fit.out_of_view {
            return Some("the parcel reaches beyond the cameras' view".into());
        }
        if fit.coverage < f64::from(min_coverage) {
            return Some(format!(
                "holes hide {:.0} % of the parcel's top (a dark or shiny surface returns no depth)",
                (1.0 - fit.coverage) * 100.0
            ));
        }
        let values = [d.length_mm, d.width_mm, d.height_mm];
        let names = ["length", "width", "height"];
        let (lo, hi) = (self.min_mm(), self.max_mm());
        for k in 0..3 {
            if values[k] < lo[k] || values[k] > hi[k] {
                return Some(format!(
                    "the {} ({:.0} mm) is outside the measurable range {:.0}-{:.0} mm",
                    names[k], values[k], lo[k], hi[k]
                ));
            }
        }
        None
    }
}

impl Billing {
    /// The division the length and width of a parcel of `shape` are given in:
    /// `round_up_mm`, or the accuracy division `d` (2 d for an irregular item's:
    /// [`Division::footprint_of`]; a dimension above the switchover takes 2 d:
    /// [`Billing::division_of`]).
    pub fn division_mm(&self, shape: Shape) -> f64 {
        self.round_up_mm
            .unwrap_or_else(|| self.division.footprint_of(shape))
    }

    /// The division of dimension `axis` (0 length, 1 width, 2 height) of `value_mm` of a
    /// parcel of `shape`: `round_up_mm`, or d or 2 d ([`Division::of_axis`]).
    pub fn division_of(&self, axis: usize, value_mm: f64, shape: Shape) -> f64 {
        self.round_up_mm
            .unwrap_or_else(|| self.division.of_axis(axis, value_mm, shape))
    }

    /// Dimension `axis` of a parcel of `shape` as the number to bill on, the legal
    /// result: `value_mm` rounded up to a multiple of `round_up_mm`, else to the nearest
    /// multiple of its division, written with no more decimals than the division has
    /// (320, not 320.00000000000006).
    pub fn billed_mm(&self, axis: usize, value_mm: f64, shape: Shape) -> f64 {
        let step = self.division_of(axis, value_mm, shape);
        let steps = match self.round_up_mm {
            Some(_) => (value_mm / step - 1e-9).ceil(),
            None => (value_mm / step).round(),
        };
        let scale = 10f64.powi(decimals(step) as i32);
        (steps * step * scale).round() / scale
    }

    /// Length, width and height of a parcel of `shape` as billed ([`Billing::billed_mm`]),
    /// mm.
    pub fn dimensions_mm(&self, d: &Dimensions, shape: Shape) -> [f64; 3] {
        let lwh = [d.length_mm, d.width_mm, d.height_mm];
        [0, 1, 2].map(|k| self.billed_mm(k, lwh[k], shape))
    }

    /// The volume of the billed dimensions of a parcel of `shape`, litres.
    pub fn volume_l(&self, d: &Dimensions, shape: Shape) -> f64 {
        let [l, w, h] = self.dimensions_mm(d, shape);
        l * w * h / 1e6
    }

    /// The volumetric weight of the billed dimensions of a parcel of `shape`: cm³ over
    /// the divisor, kg.
    pub fn volumetric_weight_kg(&self, d: &Dimensions, shape: Shape) -> f64 {
        self.volume_l(d, shape) * 1000.0 / self.divisor_cm3_per_kg
    }
}

/// How many decimals a multiple of `division_mm` needs: 0 for 5 or 10 mm, 1 for 0.5 or
/// 0.1 mm, 2 for 0.25 mm (at most 4).
pub fn decimals(division_mm: f64) -> usize {
    (0..4)
        .find(|&k| {
            let scaled = division_mm * 10f64.powi(k as i32);
            (scaled - scaled.round()).abs() < 1e-6 * scaled.max(1.0)
        })
        .unwrap_or(4)
}

/// A dimension as every output writes it (the record's text, the line output, `results`
/// and its CSV, the annotated picture's legend; the page does the same in JavaScript):
/// with the decimals of its division (`320` at 5 mm, `322.5` at 2.5 mm), so the number
/// shown is the number billed; a record made before the division was given (`None`, to
/// 0.1 mm) with one decimal.
pub fn format_mm(value_mm: f64, division_mm: Option<f64>) -> String {
    let places = division_mm.map_or(1, decimals);
    format!("{value_mm:.places$}")
}

/// The line of a measured box in an annotated picture's legend: its dimensions as every
/// output writes them ([`format_mm`]: the numbers to bill on with the decimals of
/// `division_mm`, one decimal without a division) and its yaw.
pub fn box_caption(dims: &Dimensions, division_mm: Option<f64>) -> String {
    let mm = |v: f64| format_mm(v, division_mm);
    format!(
        "measured box {} x {} x {} mm, yaw {:.1} deg",
        mm(dims.length_mm),
        mm(dims.width_mm),
        mm(dims.height_mm),
        dims.yaw_deg
    )
}

/// The reason given for a part of the table that returned no depth at all.
pub const NO_DEPTH_REASON: &str =
    "no depth from part of the table (a parcel too dark or too shiny for the cameras?)";

/// A part of the table without depth is a measured parcel's own (its walls, glare or
/// shadow) when at least this share of its rectangle lies where that parcel covers or
/// hides the floor from a camera.
pub const EXPLAINED_SHARE: f64 = 0.9;

/// A no-depth region reaching this far (metres) beyond what the parcels in it cover or
/// hide is more than their holes: part of them returned no depth where they were
/// measured to end (a pixel's footprint and the edge's noise are a few millimetres).
const BEYOND_M: f64 = 0.005;

/// The part of region `r` beyond the rectangle `lo`-`hi` (what a measured parcel covers
/// or hides, give or take [`BEYOND_M`]) on the side where most of it lies, when that part
/// is at least as wide as the smallest measurable parcel (`MIN_SIDE_M`) across the whole
/// of `r`, and `r` ends within it on the opposite side: another parcel there returned no
/// depth. `None` when every part of `r` beyond it is narrower, or `r` reaches beyond it
/// on opposite sides (a rim around the parcel, its holes).
fn beyond(r: &NoDepth, lo: [f64; 2], hi: [f64; 2]) -> Option<NoDepth> {
    let (min, max) = (r.min_m.map(f64::from), r.max_m.map(f64::from));
    // The four strips of r outside lo-hi: (axis, low side, width).
    let strips = [0, 1].into_iter().flat_map(|k| {
        [
            (k, true, lo[k] - BEYOND_M - min[k]),
            (k, false, max[k] - hi[k] - BEYOND_M),
        ]
    });
    let (k, low, width) = strips.max_by(|a, b| a.2.total_cmp(&b.2))?;
    // A rim reaches beyond it on the opposite side too.
    let opposite = if low {
        max[k] - hi[k] - BEYOND_M
    } else {
        lo[k] - BEYOND_M - min[k]
    };
    if width < MIN_SIDE_M || opposite > 0.0 {
        return None;
    }
    let mut cut = *r;
    let share = (width / (max[k] - min[k])).clamp(0.0, 1.0) as f32;
    if low {
        cut.max_m[k] = (lo[k] - BEYOND_M) as f32;
    } else {
        cut.min_m[k] = (hi[k] + BEYOND_M) as f32;
    }
    cut.area_m2 *= share;
    cut.pixels = (f64::from(cut.pixels) * f64::from(share)).round() as u32;
    Some(cut)
}

/// A parcel that returned depth from all of it: a box whose lid fills its rectangle,
/// seen whole. What little depth a dark parcel returns (its middle, a sliver of wall, a
/// rim) is not.
fn returned_whole(f: &ParcelFit) -> bool {
    f.shape == Shape::Cuboid && f.complete && f.coverage >= WHOLE_COVERAGE
}

/// See [`returned_whole`].
const WHOLE_COVERAGE: f64 = 0.95;

/// The side of the smallest measurable parcel (10 d at d = 5), metres.
const MIN_SIDE_M: f64 = 0.05;

/// What a measurement found on the table.
#[derive(Debug, Clone)]
pub enum Parcel {
    /// The largest object above the floor, measured: its smallest enclosing cuboid, and
    /// its shape, which picks the division of its length and width ([`Billing`]).
    Measured(Dimensions, Shape),
    /// Nothing on the table: the largest object above the floor has fewer points than a
    /// measurement needs.
    Nothing {
        /// Points of the largest object above the floor (0 when there is none).
        points: usize,
    },
    /// The largest object was found but the data cannot support a number.
    Refused {
        /// Why.
        reason: String,
        /// Its points.
        points: usize,
    },
}

impl Parcel {
    /// Measures the largest parcel in `cloud` (blocking: run it off the executor).
    pub fn measure(cloud: &PointCloud, config: &DimensionConfig) -> Result<Self, DimensionError> {
        Ok(Table::measure(cloud, config, &[])?.largest())
    }
}

/// Every parcel on the table, measured (blocking: run it off the executor).
#[derive(Debug, Clone, Default)]
pub struct Table {
    /// The parcels, the largest first (see [`geometry::parcels()`]).
    pub fits: Vec<ParcelFit>,
    /// Points of the largest object above the floor.
    pub largest_points: usize,
}

impl Table {
    /// Measures every parcel in `cloud`; `views` are the cameras' when known.
    pub fn measure(
        cloud: &PointCloud,
        config: &DimensionConfig,
        views: &[View],
    ) -> Result<Self, DimensionError> {
        match geometry::parcels(cloud, config, views) {
            Ok(found) => Ok(Self {
                fits: found.parcels,
                largest_points: found.largest_points,
            }),
            Err(DimensionError::TooFewPoints { found, .. }) => Ok(Self {
                fits: Vec::new(),
                largest_points: found,
            }),
            Err(e) => Err(e),
        }
    }

    /// The table with the parts of it that returned no depth (`regions`, every camera's;
    /// those overlapping joined: one parcel under several cameras). A parcel found lies
    /// in a region when half its footprint's rectangle does. A region with no parcel in it
    /// is one only when bordered mostly by floor ([`PARCEL_FLOOR_BORDER`]). When the
    /// parcels in a region
    /// have at least as many points as the region has pixels, and the region lies within
    /// what they cover or hide from the cameras ([`geometry::hidden_bounds`], give or
    /// take `BEYOND_M`, 5 mm), it is their holes, which their coverage judges; otherwise
    /// those parcels are what little depth a parcel
    /// that returns (almost) none gave (a sliver of wall, the flying pixels along its
    /// edges), and the region with them is one parcel that gives no number
    /// ([`ParcelFit::no_depth`]), placed among the others by footprint. A region of
    /// which at least [`EXPLAINED_SHARE`] lies where a measured parcel covers or hides
    /// the floor from one of the cameras (`views`) is that parcel's walls at a grazing
    /// angle, its glare or its shadow ([`geometry::hidden_share`]), not a parcel. A box
    /// measured whole (`returned_whole`) is no part of a region that reaches a parcel's
    /// side beyond what it covers or hides on one side only: that is another parcel
    /// beside it, and the region is cut back to it (`beyond`). A soft parcel (irregular)
    /// that the region rings is refused on its own: its sides returned no depth, so where
    /// it meets the floor is not known.
    #[must_use]
    pub fn with_no_depth(mut self, regions: &[NoDepth], views: &[View]) -> Self {
        let footprint = |f: &ParcelFit| {
            let c = f.dimensions.corners_m;
            let lo = [0, 1].map(|k| c.iter().map(|p| p[k]).fold(f64::INFINITY, f64::min));
            let hi = [0, 1].map(|k| c.iter().map(|p| p[k]).fold(f64::NEG_INFINITY, f64::max));
            NoDepth {
                min_m: lo.map(|v| v as f32),
                max_m: hi.map(|v| v as f32),
                area_m2: 0.0,
                floor_border: 0.0,
                pixels: 0,
            }
        };
        let mut joined: Vec<NoDepth> = Vec::new();
        for r in regions {
            let mut one = *r;
            // Joining may make it overlap regions kept before: take them in until none.
            while let Some(i) = joined.iter().position(|b| b.overlaps(&one)) {
                one = one.joined(&joined.swap_remove(i));
            }
            joined.push(one);
        }
        let rects: Vec<NoDepth> = self.fits.iter().map(footprint).collect();
        let mut taken = vec![false; self.fits.len()];
        let mut blind = Vec::new();
        for mut r in joined {
            // A box measured whole beside a parcel that returned no depth: the region
            // reaches a parcel's width beyond what the box covers or hides, on one side.
            // The region is the other parcel's, cut back to beyond the box.
            let mut beside = vec![false; rects.len()];
            for i in 0..rects.len() {
                let f = &self.fits[i];
                if taken[i]
                    || rects[i].intersection_m2(&r) < 0.5 * rects[i].rect_m2()
                    || !returned_whole(f)
                {
                    continue;
                }
                if let Some(cut) = geometry::hidden_bounds(&f.dimensions, views)
                    .and_then(|(lo, hi)| beyond(&r, lo, hi))
                {
                    r = cut;
                    beside[i] = true;
                }
            }
            let inside: Vec<usize> = (0..rects.len())
                .filter(|&i| {
                    !taken[i]
                        && !beside[i]
                        && rects[i].intersection_m2(&r) >= 0.5 * rects[i].rect_m2()
                })
                .collect();
            // A soft parcel (irregular: a polybag), measured whole, that the region rings
            // and that holds at least as many points as the region has pixels (its rim, not
            // a parcel that returned almost nothing): its sides, which curve down to the
            // floor, returned no depth (a black bag's shoulders), so where it meets the
            // floor is not known. It is refused on its own, and the region is its rim: the
            // parcels with sharp edges in it keep their numbers.
            let soft: Vec<usize> = inside
                .iter()
                .copied()
                .filter(|&i| {
                    let f = &self.fits[i];
                    f.shape == Shape::Irregular
                        && f.complete
                        && f.dimensions.points as u64 >= u64::from(r.pixels)
                        && r.rings(&rects[i])
                })
                .collect();
            if !soft.is_empty() {
                for i in soft {
                    taken[i] = true;
                    blind.push(ParcelFit::no_depth(self.fits[i].dimensions.corners_m));
                }
                continue;
            }
            // Bordered mostly by depth that is not floor, with no parcel in it: a hole in
            // a surface the cloud holds (a wall at a grazing angle), not a parcel.
            if inside.is_empty() && r.floor_border < PARCEL_FLOOR_BORDER {
                continue;
            }
            let points: usize = inside.iter().map(|&i| self.fits[i].dimensions.points).sum();
            // Every pixel that sees one of the parcels meets the floor within what they
            // cover or hide: a region reaching beyond that comes from more parcel than
            // was measured (a black bag's rim, read short). With several parcels in the
            // region (one's holes reaching under another's), beyond the union of what
            // they cover or hide; not known (`None`) when no camera is above one of them.
            let union = inside.iter().try_fold(
                ([f64::INFINITY; 2], [f64::NEG_INFINITY; 2]),
                |(lo, hi), &i| {
                    let (l, h) = geometry::hidden_bounds(&self.fits[i].dimensions, views)?;
                    Some((
                        [0, 1].map(|k| lo[k].min(l[k])),
                        [0, 1].map(|k| hi[k].max(h[k])),
                    ))
                },
            );
            let within = union.is_none_or(|(lo, hi)| {
                (0..2).all(|k| {
                    f64::from(r.min_m[k]) >= lo[k] - BEYOND_M
                        && f64::from(r.max_m[k]) <= hi[k] + BEYOND_M
                })
            });
            if points as u64 >= u64::from(r.pixels) && within {
                continue;
            }
            let (min, max) = (r.min_m.map(f64::from), r.max_m.map(f64::from));
            let explained = self.fits.iter().enumerate().any(|(i, f)| {
                !f.no_depth
                    && !inside.contains(&i)
                    && geometry::hidden_share(&f.dimensions, views, min, max) >= EXPLAINED_SHARE
            });
            if explained {
                continue;
            }
            let mut whole = r;
            for i in inside {
                taken[i] = true;
                whole.min_m = [0, 1].map(|k| whole.min_m[k].min(rects[i].min_m[k]));
                whole.max_m = [0, 1].map(|k| whole.max_m[k].max(rects[i].max_m[k]));
            }
            blind.push(ParcelFit::no_depth(whole.corners_m()));
        }
        let mut kept = taken.iter().map(|t| !t);
        self.fits.retain(|_| kept.next().unwrap_or(true));
        self.fits.extend(blind);
        let area = |f: &ParcelFit| f.dimensions.length_mm * f.dimensions.width_mm;
        self.fits.sort_by(|a, b| area(b).total_cmp(&area(a)));
        self
    }

    /// The largest parcel as today's single result: its dimensions, or nothing.
    pub fn largest(&self) -> Parcel {
        match self.fits.first() {
            Some(f) if f.no_depth => Parcel::Refused {
                reason: NO_DEPTH_REASON.into(),
                points: 0,
            },
            Some(f) => Parcel::Measured(f.dimensions, f.shape),
            None => Parcel::Nothing {
                points: self.largest_points,
            },
        }
    }
}

/// What a `POST /cams/dimensions` asks for, as its query (the names of `measure`'s
/// flags).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct EdgeQuery {
    /// Read the codes from a new color image of every camera (`codes`).
    pub codes: bool,
    /// `min_height_mm=` and `cluster_mm=`.
    pub config: DimensionConfig,
    /// `volumetric_divisor=`, `round_up_mm=` and `division_mm=`.
    pub billing: Billing,
}

impl EdgeQuery {
    /// The Uri-Query items that ask for this (defaults left out).
    pub fn to_query(&self) -> Vec<String> {
        // Millimetres of f32 metres to 0.1 µm, without the f32's tail (30, not 29.999999).
        let mm = |m: f32| (f64::from(m) * 1e7).round() / 1e4;
        let d = Self::default();
        let mut q = Vec::new();
        if self.codes {
            q.push("codes".into());
        }
        if self.config.min_height_m != d.config.min_height_m {
            q.push(format!("min_height_mm={}", mm(self.config.min_height_m)));
        }
        if self.config.cluster_radius_m != d.config.cluster_radius_m {
            q.push(format!("cluster_mm={}", mm(self.config.cluster_radius_m)));
        }
        if self.billing.divisor_cm3_per_kg != d.billing.divisor_cm3_per_kg {
            q.push(format!(
                "volumetric_divisor={}",
                self.billing.divisor_cm3_per_kg
            ));
        }
        if let Some(mm) = self.billing.round_up_mm {
            q.push(format!("round_up_mm={mm}"));
        }
        if self.billing.division != d.billing.division {
            q.push(format!("division_mm={}", self.billing.division.d_mm));
        }
        q
    }

    /// Reads the query items; an unknown item or a value outside its range
    /// ([`EdgeQuery::RANGES`]) is refused with the reason.
    pub fn parse<S: AsRef<str>>(items: impl IntoIterator<Item = S>) -> Result<Self, String> {
        let mut q = Self::default();
        for item in items {
            let item = item.as_ref();
            let (key, value) = item.split_once('=').unwrap_or((item, ""));
            if key == "codes" {
                q.codes = match value {
                    "" | "1" | "true" => true,
                    "0" | "false" => false,
                    _ => return Err(format!("codes={value}: give codes, codes=1 or codes=0")),
                };
                continue;
            }
            let Some((_, lo, hi)) = Self::RANGES.iter().find(|(k, ..)| *k == key) else {
                return Err(format!(
                    "unknown query item {key}: a measurement takes codes, min_height_mm, cluster_mm, volumetric_divisor, round_up_mm and division_mm"
                ));
            };
            let v = match value.parse::<f64>() {
                Ok(v) if (*lo..=*hi).contains(&v) => v,
                _ => return Err(format!("{key}={value}: not a number from {lo} to {hi}")),
            };
            match key {
                "min_height_mm" => q.config.min_height_m = (v / 1e3) as f32,
                "cluster_mm" => q.config.cluster_radius_m = (v / 1e3) as f32,
                "volumetric_divisor" => q.billing.divisor_cm3_per_kg = v,
                "division_mm" => q.billing.division.d_mm = v,
                _ => q.billing.round_up_mm = Some(v),
            }
        }
        Ok(q)
    }

    /// The numeric query items and the values each takes (millimetres; cm³ per kg); the
    /// client's flags take the same. A cluster radius below 5 mm is finer than the
    /// spacing of a D415's points at a metre or more (after decimation), so a parcel
    /// falls apart into pieces; above 500 mm it merges whatever stands beside it.
    pub const RANGES: [(&str, f64, f64); 5] = [
        ("min_height_mm", 0.0, 1_000.0),
        ("cluster_mm", 5.0, 500.0),
        ("volumetric_divisor", 100.0, 100_000.0),
        ("round_up_mm", 0.1, 1_000.0),
        ("division_mm", 0.1, 100.0),
    ];
}

/// A code and the cameras that read it (in the document: `kind`, `text`, `cameras`).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct Seen {
    /// The code.
    #[serde(flatten)]
    pub code: Code,
    /// Serials of the cameras whose image it was read from.
    pub cameras: Vec<String>,
}

impl Seen {
    /// Each code once, with the cameras that read it, from what each camera read.
    pub fn gather(per_camera: impl IntoIterator<Item = (String, Vec<Code>)>) -> Vec<Self> {
        let mut seen: BTreeMap<Code, Vec<String>> = BTreeMap::new();
        for (serial, codes) in per_camera {
            for code in codes {
                seen.entry(code).or_default().push(serial.clone());
            }
        }
        seen.into_iter()
            .map(|(code, mut cameras)| {
                cameras.sort();
                Self { code, cameras }
            })
            .collect()
    }
}

/// The codes one line of text names: `qr "PKG-0001" (840412060746, ...)`, or `none`.
pub fn describe(seen: &[Seen]) -> String {
    if seen.is_empty() {
        return "none".into();
    }
    let each: Vec<String> = seen
        .iter()
        .map(|s| format!("{} ({})", s.code, s.cameras.join(", ")))
        .collect();
    each.join(", ")
}

/// How far the lowest points of a calibrated cloud may lie from z = 0 (the floor of the
/// common frame) before the measurement warns.
const FLOOR_TOLERANCE_M: f32 = 0.05;

/// The height of the lowest points of a view, metres: the 2nd percentile of their `z`;
/// `None` for fewer than 100 points (too few to tell).
pub fn floor_level(z: impl IntoIterator<Item = f32>) -> Option<f32> {
    let mut z: Vec<f32> = z.into_iter().filter(|z| z.is_finite()).collect();
    if z.len() < 100 {
        return None;
    }
    let k = z.len() / 50;
    let (_, low, _) = z.select_nth_unstable_by(k, f32::total_cmp);
    Some(*low)
}

/// Warnings that the dimensions may be nonsense because the cameras are not calibrated:
/// each camera of `uncalibrated` (its 3d-transformation the identity, as a real camera
/// starts), and each view of `floors` (a camera's serial, or `None` for a merged cloud,
/// with its [`floor_level`]) whose lowest points are not near the floor at z = 0.
pub fn calibration_warnings(
    uncalibrated: &[String],
    floors: &[(Option<String>, Option<f32>)],
) -> Vec<String> {
    let mut out: Vec<String> = uncalibrated
        .iter()
        .map(|sn| {
            format!(
                "camera {sn} is not calibrated (its 3d-transformation is the identity): the dimensions are in its own frame; run coapcam calibrate"
            )
        })
        .collect();
    for (camera, low) in floors {
        let Some(low) = low.filter(|low| low.abs() > FLOOR_TOLERANCE_M) else {
            continue;
        };
        let whose = camera
            .as_ref()
            .map_or_else(String::new, |sn| format!("camera {sn}: "));
        out.push(format!(
            "{whose}the floor is not near z = 0: the lowest points lie at {:.0} mm; check the cameras' 3d-transformation (coapcam calibrate)",
            low * 1000.0
        ));
    }
    out
}

/// Milliseconds to 0.1 ms, as the document gives durations.
pub fn ms(d: Duration) -> f64 {
    (d.as_secs_f64() * 1e4).round() / 10.0
}

#[cfg(test)]
mod tests {
    use super::*;

    fn fit(l: f64, w: f64, h: f64) -> ParcelFit {
        ParcelFit::whole_box(Dimensions {
            length_mm: l,
            width_mm: w,
            height_mm: h,
            yaw_deg: 0.0,
            corners_m: [[0.0; 2]; 4],
            volume_l: l * w * h / 1e6,
            points: 1000,
        })
    }

    #[test]
    fn the_division_doubles_above_200_d_and_bounds_the_range() {
        let d = Division::default();
        assert_eq!((d.of(1000.0), d.of(1000.1)), (5.0, 10.0));
        assert_eq!(
            [Shape::Cuboid, Shape::Round, Shape::Irregular].map(|s| d.footprint_of(s)),
            [5.0, 5.0, 10.0]
        );
        assert_eq!(
            (d.round(612.4), d.round(612.6), d.round(1234.0)),
            (610.0, 615.0, 1230.0)
        );
        assert_eq!(
            (d.min_mm(), d.max_mm()),
            ([50.0, 50.0, 10.0], [1500.0, 1500.0, 1000.0])
        );
        assert_eq!(d.refusal(&fit(400.0, 300.0, 200.0), 0.8), None);
        let small = d
            .refusal(&fit(400.0, 40.0, 200.0), 0.8)
            .expect("too narrow");
        assert!(
            small.contains("width (40 mm)") && small.contains("50-1500"),
            "{small}"
        );
        let mut holed = fit(400.0, 300.0, 200.0);
        holed.coverage = 0.6;
        assert!(d.refusal(&holed, 0.8).expect("holes").contains("40 %"));
        let mut touching = fit(400.0, 300.0, 200.0);
        touching.isolated = false;
        assert!(
            d.refusal(&touching, 0.8)
                .expect("side by side")
                .contains("side by side")
        );
        let mut cut = fit(400.0, 300.0, 200.0);
        cut.out_of_view = true;
        assert!(d.refusal(&cut, 0.8).expect("out of view").contains("view"));
    }

    /// A box `l` x `w` mm of `points` points whose footprint's corner nearest the
    /// origin is at `at` (metres), its sides along x and y.
    fn placed(l: f64, w: f64, at: [f64; 2], points: usize) -> ParcelFit {
        let mut f = fit(l, w, 100.0);
        let [x, y] = at;
        let (l, w) = (l / 1e3, w / 1e3);
        f.dimensions.corners_m = [[x, y], [x + l, y], [x + l, y + w], [x, y + w]];
        f.dimensions.points = points;
        f
    }

    fn region(min: [f32; 2], max: [f32; 2], pixels: u32) -> NoDepth {
        NoDepth {
            min_m: min,
            max_m: max,
            area_m2: (max[0] - min[0]) * (max[1] - min[1]),
            floor_border: 1.0,
            pixels,
        }
    }

    /// A region bordered mostly by depth that is not floor, with no parcel in it (a hole
    /// in a tall box's wall whose rays leave its shadow), is no parcel; bordered by floor,
    /// the same region is one that returned no depth.
    #[test]
    fn a_region_bordered_mostly_by_a_surface_is_a_parcel_only_around_one() {
        let table = Table {
            fits: vec![placed(400.0, 300.0, [0.0, 0.0], 20_000)],
            largest_points: 20_000,
        };
        let hole = NoDepth {
            floor_border: 0.2,
            ..region([0.6, 0.6], [0.7, 0.7], 2_000)
        };
        let kept = table.clone().with_no_depth(&[hole], &[]);
        assert!(
            kept.fits.len() == 1 && !kept.fits[0].no_depth,
            "{:?}",
            kept.fits
        );
        let parcel = region([0.6, 0.6], [0.7, 0.7], 2_000);
        let refused = table.with_no_depth(&[parcel], &[]);
        assert!(refused.fits.len() == 2 && refused.fits.iter().any(|f| f.no_depth));
    }

    /// A region of pixels that looked at a measured box's end wall at a grazing angle
    /// (their rays meet the floor inside its footprint and in its shadow) is that box's,
    /// not a parcel; the same region with no box there is a parcel that returned no
    /// depth, refused.
    #[test]
    fn a_part_of_the_table_a_measured_parcel_hides_from_a_camera_is_no_parcel() {
        // A 400 x 300 x 100 mm box from (0, 0); a camera 1 m up beyond its +x end.
        let boxed = placed(400.0, 300.0, [0.0, 0.0], 20_000);
        let eye = geometry::Transform {
            linear: nalgebra::Matrix3::identity(),
            translation: nalgebra::Vector3::new(0.9, 0.15, 1.0),
        };
        let view = View::pinhole(eye, 600.0, 600.0, 320.0, 240.0, 640, 480);
        // Behind its far (-x) end wall: 100 mm high, the shadow reaches 0.9 * 0.1 / 0.9 =
        // 0.1 m beyond it.
        let wall = region([-0.05, 0.02], [0.03, 0.28], 3_000);
        let table = Table {
            fits: vec![boxed.clone()],
            largest_points: 20_000,
        };
        let explained = table.clone().with_no_depth(&[wall], &[view]);
        assert_eq!(explained.fits, vec![boxed.clone()]);
        // Without the camera's view nothing explains it.
        let unexplained = table.with_no_depth(&[wall], &[]);
        assert_eq!(unexplained.fits.len(), 2);
        // A black box beside the measured one, in no shadow of it: refused.
        let black = region([-0.45, 0.0], [-0.15, 0.3], 6_000);
        let beside = Table {
            fits: vec![boxed],
            largest_points: 20_000,
        }
        .with_no_depth(&[black], &[view]);
        assert_eq!(beside.fits.len(), 2);
        assert!(beside.fits.iter().any(|f| f.no_depth), "{:?}", beside.fits);
    }

    /// A black box 50 mm beside a box measured whole: four cameras' regions of the black
    /// box, joined, reach over most of the measured box (each camera's rays through the
    /// black box meet the floor beyond it). The measured box keeps its number and the
    /// black box is refused on its own (cert scene 10: both were one refusal).
    #[test]
    fn a_box_measured_whole_beside_one_that_returned_no_depth_keeps_its_number() {
        let eye = geometry::Transform {
            linear: nalgebra::Matrix3::identity(),
            translation: nalgebra::Vector3::new(0.1, 0.1, 1.5),
        };
        let view = View::pinhole(eye, 600.0, 600.0, 320.0, 240.0, 640, 480);
        let boxed = placed(212.0, 173.0, [0.0, 0.0], 20_000);
        let table = Table {
            fits: vec![boxed.clone()],
            largest_points: 20_000,
        };
        let black = region([0.05, -0.05], [0.8, 0.25], 30_000);
        let beside = table.with_no_depth(&[black], &[view]);
        assert_eq!(beside.fits.len(), 2, "{:?}", beside.fits);
        assert!(beside.fits.contains(&boxed), "{:?}", beside.fits);
        let blind = beside
            .fits
            .iter()
            .find(|f| f.no_depth)
            .expect("the black box");
        // Cut back to beyond what the measured box covers or hides.
        let min_x = blind
            .dimensions
            .corners_m
            .iter()
            .map(|c| c[0])
            .fold(1.0, f64::min);
        assert!(min_x > 0.212, "{:?}", blind.dimensions.corners_m);
        // A box that is not whole (a dark parcel's middle, read short) stays inside.
        let part = ParcelFit {
            coverage: 0.6,
            ..boxed
        };
        let inside = Table {
            fits: vec![part],
            largest_points: 20_000,
        }
        .with_no_depth(&[black], &[view]);
        assert!(
            inside.fits.len() == 1 && inside.fits[0].no_depth,
            "{:?}",
            inside.fits
        );
    }

    /// A black bag returns depth from the middle of its top only: it is measured short,
    /// and the ring of its rim that returned none reaches beyond what the short parcel
    /// covers or hides. Its number is refused, not given.
    #[test]
    fn a_parcel_whose_no_depth_rim_reaches_beyond_it_is_refused() {
        // Measured 400 x 300 x 100 mm from (0, 0); a camera 1 m up beyond its +x end.
        let eye = geometry::Transform {
            linear: nalgebra::Matrix3::identity(),
            translation: nalgebra::Vector3::new(0.9, 0.15, 1.0),
        };
        let view = View::pinhole(eye, 600.0, 600.0, 320.0, 240.0, 640, 480);
        let table = Table {
            fits: vec![placed(400.0, 300.0, [0.0, 0.0], 20_000)],
            largest_points: 20_000,
        };
        // Holes inside its footprint and shadow: its own.
        let holes = region([-0.05, 0.01], [0.39, 0.29], 5_000);
        let kept = table.clone().with_no_depth(&[holes], &[view]);
        assert!(
            kept.fits.len() == 1 && !kept.fits[0].no_depth,
            "{:?}",
            kept.fits
        );
        // The rim 20 mm beyond its near (+x) end and its sides: refused.
        let rim = region([-0.05, -0.02], [0.42, 0.32], 5_000);
        let refused = table.with_no_depth(&[rim], &[view]);
        assert!(
            refused.fits.len() == 1 && refused.fits[0].no_depth,
            "{:?}",
            refused.fits
        );
    }

    /// A black bag under a camera straight above: its top returned depth, its shoulders
    /// none, so it reads short and the ring of its shoulders lies within what the short
    /// parcel covers or hides (cert scenes 110, 442: read 25-67 mm short, billed). A soft
    /// parcel ringed by pixels without depth is refused; a box with the same ring (a dark
    /// box's walls) keeps its number, and so does a bag that a neighbour's region only
    /// reaches under.
    #[test]
    fn a_soft_parcel_ringed_by_no_depth_is_refused() {
        let eye = geometry::Transform {
            linear: nalgebra::Matrix3::identity(),
            translation: nalgebra::Vector3::new(0.2, 0.15, 1.5),
        };
        let view = View::pinhole(eye, 600.0, 600.0, 320.0, 240.0, 640, 480);
        let mut bag = placed(400.0, 300.0, [0.0, 0.0], 20_000);
        bag.dimensions.height_mm = 300.0;
        bag.shape = Shape::Irregular;
        let ring = region([-0.02, -0.02], [0.42, 0.32], 8_000);
        let table = |f: &ParcelFit| Table {
            fits: vec![f.clone()],
            largest_points: 20_000,
        };
        let refused = table(&bag).with_no_depth(&[ring], &[view]);
        assert!(
            refused.fits.len() == 1 && refused.fits[0].no_depth,
            "{:?}",
            refused.fits
        );
        let boxed = ParcelFit {
            shape: Shape::Cuboid,
            ..bag
        };
        assert_eq!(
            table(&boxed).with_no_depth(&[ring], &[view]).fits,
            vec![boxed]
        );
        let under = region([0.3, -0.02], [0.6, 0.32], 8_000);
        let beside = table(&bag).with_no_depth(&[under], &[view]);
        assert!(beside.fits.contains(&bag), "{:?}", beside.fits);
        // A box in the ring's region with the bag keeps its number.
        let mut both = table(&bag);
        let small = placed(100.0, 100.0, [0.25, 0.1], 5_000);
        both.fits.push(small.clone());
        let wide = region([-0.02, -0.02], [0.42, 0.32], 20_000);
        let kept = both.with_no_depth(&[wide], &[view]);
        assert!(
            kept.fits.len() == 2 && kept.fits.contains(&small),
            "{:?}",
            kept.fits
        );
        // What little a parcel that returns almost nothing gave (fewer points than the
        // region has pixels) is no rim of its own: the region with it is one refusal.
        let sliver = ParcelFit {
            dimensions: Dimensions {
                points: 500,
                ..bag.dimensions
            },
            ..bag
        };
        let one = table(&sliver).with_no_depth(&[ring], &[view]);
        assert!(
            one.fits.len() == 1 && one.fits[0].no_depth,
            "{:?}",
            one.fits
        );
        let c = one.fits[0].dimensions.corners_m;
        assert!(
            (c[0][0] + 0.02).abs() < 1e-6,
            "the region's rectangle: {c:?}"
        );
    }

    /// A tall box's holes reach the floor far into its shadow, under a low box standing
    /// there: the region holds both, and lies within what the two cover or hide (cert
    /// scenes 415 and 205: a black cylinder's region took a measured neighbour with it
    /// into a refusal). A region reaching beyond both is still more parcel than measured.
    #[test]
    fn holes_reaching_under_a_neighbour_are_the_parcels_own() {
        // A camera 1 m up at (0.9, 0.1); a 200 x 200 x 400 mm box from (0, 0), which
        // hides the floor to x = -0.6 from it, and a 100 x 100 x 100 mm box 200 mm
        // beyond, in that shadow.
        let eye = geometry::Transform {
            linear: nalgebra::Matrix3::identity(),
            translation: nalgebra::Vector3::new(0.9, 0.1, 1.0),
        };
        let view = View::pinhole(eye, 600.0, 600.0, 320.0, 240.0, 640, 480);
        let mut tall = placed(200.0, 200.0, [0.0, 0.0], 20_000);
        tall.dimensions.height_mm = 400.0;
        let low = placed(100.0, 100.0, [-0.3, 0.0], 5_000);
        let table = Table {
            fits: vec![tall, low],
            largest_points: 20_000,
        };
        let holes = region([-0.55, -0.03], [0.19, 0.25], 5_000);
        let kept = table.clone().with_no_depth(&[holes], &[view]);
        assert!(
            kept.fits.len() == 2 && kept.fits.iter().all(|f| !f.no_depth),
            "{:?}",
            kept.fits
        );
        let beyond = region([-0.55, -0.03], [0.19, 0.30], 5_000);
        let refused = table.with_no_depth(&[beyond], &[view]);
        assert!(
            refused.fits.len() == 1 && refused.fits[0].no_depth,
            "{:?}",
            refused.fits
        );
    }

    #[test]
    fn a_part_of_the_table_without_depth_is_a_refused_parcel_unless_one_found_explains_it() {
        let d = Division::default();
        // A measured box whose dark walls lose depth around its lid: its holes.
        let boxed = placed(400.0, 300.0, [0.2, 0.2], 20_000);
        // The sliver of wall a box that returns no depth gave: 70 points in a region of
        // 3,000 pixels (two cameras', overlapping: one parcel).
        let sliver = placed(120.0, 2.0, [-0.30, -0.20], 70);
        let table = Table {
            fits: vec![boxed.clone(), sliver],
            largest_points: 20_000,
        }
        .with_no_depth(
            &[
                region([0.15, 0.15], [0.65, 0.55], 4_000),
                region([-0.35, -0.25], [-0.15, -0.05], 1_500),
                region([-0.33, -0.27], [-0.14, -0.06], 1_500),
            ],
            &[],
        );
        assert_eq!(table.fits.len(), 2, "{:?}", table.fits);
        assert_eq!(table.fits[0], boxed);
        let blind = &table.fits[1];
        assert!(blind.no_depth && !blind.complete, "{blind:?}");
        // The joined regions' rectangle, with the sliver in it.
        let c = blind.dimensions.corners_m;
        let near = |a: f64, b: f64| (a - b).abs() < 1e-6;
        assert!(near(c[0][0], -0.35) && near(c[0][1], -0.27), "{c:?}");
        assert!(near(c[2][0], -0.14) && near(c[2][1], -0.05), "{c:?}");
        assert_eq!(
            d.refusal(blind, 0.8).as_deref(),
            Some(NO_DEPTH_REASON),
            "{blind:?}"
        );
        // Alone on the table, it is the answer: refused, not "nothing there".
        let alone = Table::default().with_no_depth(&[region([0.0, 0.0], [0.2, 0.2], 2_000)], &[]);
        assert!(
            matches!(alone.largest(), Parcel::Refused { reason, .. } if reason == NO_DEPTH_REASON)
        );
        // A region smaller in pixels than the parcel in it is that parcel's holes.
        let holed = Table {
            fits: vec![placed(400.0, 300.0, [0.0, 0.0], 5_000)],
            largest_points: 5_000,
        }
        .with_no_depth(&[region([-0.05, -0.05], [0.45, 0.35], 4_999)], &[]);
        assert!(!holed.fits[0].no_depth && holed.fits.len() == 1);
    }

    #[test]
    fn a_table_reports_every_parcel_and_refuses_the_largest_when_it_must() {
        let mut side = fit(400.0, 300.0, 200.0);
        side.isolated = false;
        let table = Table {
            fits: vec![side, fit(1203.0, 251.0, 99.0)],
            largest_points: 1000,
        };
        let m = Measurement::of_table(
            &table,
            &Billing::default(),
            0.8,
            5000,
            Vec::new(),
            Vec::new(),
            Duration::ZERO,
        );
        let doc: serde_json::Value =
            serde_json::from_str(&m.to_json().expect("JSON")).expect("parses");
        assert_eq!(doc["parcel"], "refused");
        assert!(
            doc["reason"]
                .as_str()
                .expect("a reason")
                .contains("side by side")
        );
        assert!(doc.get("length_mm").is_none());
        assert_eq!(doc["parcels"][0]["parcel"], "refused");
        assert_eq!(doc["parcels"][0]["isolated"], false);
        assert_eq!(doc["parcels"][1]["parcel"], "measured");
        assert_eq!(doc["parcels"][1]["length_mm"], 1200.0);
        assert_eq!(doc["parcels"][1]["width_mm"], 250.0);
        assert_eq!(doc["parcels"][1]["height_mm"], 100.0);
        assert_eq!(
            doc["parcels"][1]["division_mm"],
            serde_json::json!([10.0, 5.0, 5.0])
        );
        assert_eq!(doc["parcels"][1]["shape"], "cuboid");
        let back = Measurement::from_json(doc.to_string().as_bytes()).expect("reads");
        assert_eq!(back, m);
        assert!(matches!(back.parcel(), Parcel::Refused { .. }));
        assert!(
            m.text().contains("parcel 2: 1200 x 250 x 100 mm, cuboid"),
            "{}",
            m.text()
        );
    }

    /// Issue 51, item 4: one record gave 320.2 at the top level (the line output, MQTT,
    /// CSV), 320 on the page and 320.0 with a 5 mm division in `parcels`, while the top
    /// level said `"division_mm": null`. The top level bills the numbers of `parcels[0]`
    /// and names its division; the unrounded numbers are kept, named so.
    #[test]
    fn the_top_level_bills_the_numbers_of_its_parcel_and_names_the_division() {
        let doc = |table: &Table, billing: &Billing| -> serde_json::Value {
            let m = Measurement::of_table(
                table,
                billing,
                0.8,
                5000,
                Vec::new(),
                Vec::new(),
                Duration::ZERO,
            );
            serde_json::from_str(&m.to_json().expect("JSON")).expect("parses")
        };
        let one = |l, w, h| Table {
            fits: vec![fit(l, w, h)],
            largest_points: 1000,
        };
        let table = one(322.6, 241.3, 99.8);
        let m = doc(&table, &Billing::default());
        for key in ["length_mm", "width_mm", "height_mm"] {
            assert_eq!(m[key], m["parcels"][0][key], "{key}: {m}");
        }
        assert_eq!(
            [&m["length_mm"], &m["width_mm"], &m["height_mm"]],
            [325.0, 240.0, 100.0]
                .map(serde_json::Value::from)
                .each_ref()
        );
        assert_eq!(m["division_mm"], 5.0, "{m}");
        assert_eq!(
            m["parcels"][0]["division_mm"],
            serde_json::json!([5.0, 5.0, 5.0])
        );
        assert_eq!(m["unrounded_mm"], serde_json::json!([322.6, 241.3, 99.8]));
        assert_eq!(m["parcels"][0]["unrounded_mm"], m["unrounded_mm"]);
        // The volume and the volumetric weight are those of the billed numbers.
        assert_eq!(m["volume_l"], 7.8);
        assert_eq!(m["volumetric_weight_kg"], 1.56);
        let text = Measurement::from_json(m.to_string().as_bytes())
            .expect("reads")
            .text();
        assert!(
            text.starts_with("length 325 mm  width 240 mm  height 100 mm  (division 5 mm; unrounded 322.6 x 241.3 x 99.8 mm)\n"),
            "{text}"
        );

        // Rounded up to a carrier's 10 mm: the same numbers at the top and in the list.
        let up = Billing {
            round_up_mm: Some(10.0),
            ..Billing::default()
        };
        let m = doc(&table, &up);
        for key in ["length_mm", "width_mm", "height_mm"] {
            assert_eq!(m[key], m["parcels"][0][key], "{key}: {m}");
        }
        assert_eq!(m["length_mm"], 330.0);
        assert_eq!(m["height_mm"], 100.0);
        assert_eq!(
            (&m["division_mm"], &m["parcels"][0]["division_mm"][0]),
            (&10.0.into(), &10.0.into())
        );

        // Above the switchover the length takes 2 d; the top level names d.
        let m = doc(&one(1203.0, 251.0, 99.0), &Billing::default());
        assert_eq!(
            (&m["length_mm"], &m["parcels"][0]["length_mm"]),
            (&1200.0.into(), &1200.0.into())
        );
        assert_eq!(m["division_mm"], 5.0);
        assert_eq!(
            m["parcels"][0]["division_mm"],
            serde_json::json!([10.0, 5.0, 5.0])
        );

        // A bag's length and width take 2 d, its height d, at the top level as in the list;
        // a tube or a cylinder keeps d.
        let mut bag = one(322.6, 241.3, 99.8);
        bag.fits[0].shape = Shape::Irregular;
        let m = doc(&bag, &Billing::default());
        assert_eq!(
            [&m["length_mm"], &m["width_mm"], &m["height_mm"]],
            [320.0, 240.0, 100.0]
                .map(serde_json::Value::from)
                .each_ref()
        );
        for key in ["length_mm", "width_mm", "height_mm"] {
            assert_eq!(m[key], m["parcels"][0][key], "{key}: {m}");
        }
        assert_eq!(
            (&m["division_mm"], &m["parcels"][0]["division_mm"]),
            (&10.0.into(), &serde_json::json!([10.0, 10.0, 5.0]))
        );
        assert_eq!(m["parcels"][0]["shape"], "irregular");
        bag.fits[0].shape = Shape::Round;
        let m = doc(&bag, &Billing::default());
        assert_eq!(
            (&m["length_mm"], &m["division_mm"]),
            (&325.0.into(), &5.0.into())
        );
        assert_eq!(m["parcels"][0]["shape"], "round");

        // A division of 0.1 mm gives 322.6, not 322.6000000000000X.
        let fine = Billing {
            division: Division { d_mm: 0.1 },
            ..Billing::default()
        };
        assert_eq!(fine.billed_mm(0, 322.63, Shape::Cuboid), 322.6);
        assert_eq!(fine.billed_mm(0, 0.3 + 0.6, Shape::Cuboid), 0.9);
    }

    /// The largest parcel carries its shape from the fit to the document and back: a
    /// document read again gives the shape it was billed as; one from before the list of
    /// parcels (and its shapes), a box's.
    #[test]
    fn the_reported_parcel_keeps_its_shape_through_the_document() {
        for shape in [Shape::Cuboid, Shape::Round, Shape::Irregular] {
            let mut one = fit(322.6, 241.3, 99.8);
            one.shape = shape;
            let table = Table {
                fits: vec![one],
                largest_points: 1000,
            };
            assert!(matches!(table.largest(), Parcel::Measured(_, s) if s == shape));
            let m = Measurement::of_table(
                &table,
                &Billing::default(),
                0.8,
                5000,
                Vec::new(),
                Vec::new(),
                Duration::ZERO,
            );
            let mut back =
                Measurement::from_json(m.to_json().expect("JSON").as_bytes()).expect("reads");
            assert!(
                matches!(back.parcel(), Parcel::Measured(_, s) if s == shape),
                "{shape:?}"
            );
            back.parcels.clear();
            assert!(matches!(back.parcel(), Parcel::Measured(_, Shape::Cuboid)));
        }
    }

    /// Issue 51, item 4: the picture's legend wrote whole millimetres whatever the
    /// division; it writes the numbers to bill on as every output does.
    #[test]
    fn the_legend_writes_the_dimensions_as_every_output_does() {
        let d = |length_mm| fit(length_mm, 300.0, 200.0).dimensions;
        assert_eq!(
            box_caption(&d(322.5), Some(2.5)),
            "measured box 322.5 x 300.0 x 200.0 mm, yaw 0.0 deg"
        );
        assert_eq!(
            box_caption(&d(400.0), Some(5.0)),
            "measured box 400 x 300 x 200 mm, yaw 0.0 deg"
        );
    }

    #[test]
    fn a_dimension_is_written_with_the_decimals_of_its_division() {
        assert_eq!(format_mm(325.0, Some(5.0)), "325");
        assert_eq!(format_mm(1200.0, Some(10.0)), "1200");
        assert_eq!(format_mm(320.5, Some(0.5)), "320.5");
        assert_eq!(format_mm(320.0, Some(0.5)), "320.0");
        assert_eq!(format_mm(320.25, Some(0.25)), "320.25");
        assert_eq!(format_mm(322.6, Some(0.1)), "322.6");
        // A record made before the division: its 0.1 mm.
        assert_eq!(format_mm(322.6, None), "322.6");
        assert_eq!(format_mm(400.0, None), "400.0");
    }

    #[test]
    fn the_query_round_trips_and_refuses_what_it_does_not_know() {
        assert_eq!(EdgeQuery::parse([""; 0]), Ok(EdgeQuery::default()));
        let q = EdgeQuery::parse(["codes", "cluster_mm=30", "round_up_mm=5"]).expect("valid");
        assert!(q.codes);
        assert_eq!(q.config.cluster_radius_m, 0.03);
        assert_eq!(q.billing.round_up_mm, Some(5.0));
        let items = q.to_query();
        assert_eq!(items, ["codes", "cluster_mm=30", "round_up_mm=5"]);
        assert_eq!(
            EdgeQuery::parse(["min_height_mm=0"]).map(|q| q.config.min_height_m),
            Ok(0.0)
        );
        assert_eq!(EdgeQuery::parse(&items), Ok(q));
        for bad in [
            "colour",
            "cluster_mm=-1",
            "cluster_mm=0",
            "round_up_mm=x",
            "codes=yes",
            "min_height_mm=inf",
            "min_height_mm=1e300",
            "volumetric_divisor=1e-300",
        ] {
            let why = EdgeQuery::parse([bad]).expect_err(bad);
            assert!(why.contains(bad.split('=').next().unwrap_or(bad)), "{why}");
        }
        // The page's POST /api/measure takes the same query: the error names no path
        // (issue 51, item 13: `/api/measure?cdoes` was told about /cams/dimensions).
        let why = EdgeQuery::parse(["cdoes"]).expect_err("a typo");
        assert!(
            why.starts_with("unknown query item cdoes: a measurement takes codes,"),
            "{why}"
        );
    }
}
