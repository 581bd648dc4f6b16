//! What a measurement reports, wherever it was made (the client's `measure`, or the
//! server's `/cams/dimensions`): one typed [`Measurement`] (`measurement.rs`: its
//! document, docs/design.md §6, and the text `measure` prints), the parcel, its billing,
//! the codes seen and the query of `/cams/dimensions`.

mod measurement;

use std::collections::BTreeMap;
use std::time::Duration;

use geometry::{DimensionConfig, DimensionError, Dimensions, PointCloud};
use serde::{Deserialize, Serialize};

use crate::vision::codes::Code;

pub use measurement::{Found, Measurement, MeasurementError, Reported, VERSION};

/// How a measurement is reported to an integrator's billing: the volumetric divisor and
/// the scale division the dimensions are rounded up to.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Billing {
    /// Divisor of the volumetric weight, cm³ per kg: 5000 by default (the courier
    /// convention), 6000 with some carriers.
    pub divisor_cm3_per_kg: f64,
    /// Round each dimension up to a multiple of this many millimetres (a scale
    /// division, e.g. 5); `None` reports them to 0.1 mm.
    pub division_mm: Option<f64>,
}

impl Default for Billing {
    fn default() -> Self {
        Self {
            divisor_cm3_per_kg: 5000.0,
            division_mm: None,
        }
    }
}

impl Billing {
    /// Length, width and height in millimetres as reported: rounded up to the division,
    /// else to 0.1 mm.
    pub fn dimensions_mm(&self, d: &Dimensions) -> [f64; 3] {
        [d.length_mm, d.width_mm, d.height_mm].map(|v| match self.division_mm {
            Some(step) => (v / step - 1e-9).ceil() * step,
            None => (v * 10.0).round() / 10.0,
        })
    }

    /// The volume of the reported dimensions, litres.
    pub fn volume_l(&self, d: &Dimensions) -> f64 {
        let [l, w, h] = self.dimensions_mm(d);
        l * w * h / 1e6
    }

    /// The volumetric weight of the reported dimensions: cm³ over the divisor, kg.
    pub fn volumetric_weight_kg(&self, d: &Dimensions) -> f64 {
        self.volume_l(d) * 1000.0 / self.divisor_cm3_per_kg
    }
}

/// What a measurement found on the table.
#[derive(Debug, Clone)]
pub enum Parcel {
    /// The largest object above the floor, measured.
    Measured(Dimensions),
    /// Nothing on the table: the largest object above the floor has fewer points than a
    /// measurement needs.
    Nothing {
        /// Points of the largest object above the floor (0 when there is none).
        points: usize,
    },
}

impl Parcel {
    /// Measures the largest parcel in `cloud` (blocking: run it off the executor).
    pub fn measure(cloud: &PointCloud, config: &DimensionConfig) -> Result<Self, DimensionError> {
        match geometry::dimension(cloud, config) {
            Ok(d) => Ok(Self::Measured(d)),
            Err(DimensionError::TooFewPoints { found, .. }) => Ok(Self::Nothing { points: found }),
            Err(e) => Err(e),
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
    /// `volumetric_divisor=` and `round_up_mm=`.
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
        if let Some(mm) = self.billing.division_mm {
            q.push(format!("round_up_mm={mm}"));
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
                    "unknown query item {key}: /cams/dimensions takes codes, min_height_mm, cluster_mm, volumetric_divisor and round_up_mm"
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
                _ => q.billing.division_mm = Some(v),
            }
        }
        Ok(q)
    }

    /// The numeric query items and the values each takes (millimetres; cm³ per kg); the
    /// client's flags take the same. A cluster radius below 5 mm is finer than the
    /// spacing of a D415's points at a metre or more (after decimation), so a parcel
    /// falls apart into pieces; above 500 mm it merges whatever stands beside it.
    pub const RANGES: [(&str, f64, f64); 4] = [
        ("min_height_mm", 0.0, 1_000.0),
        ("cluster_mm", 5.0, 500.0),
        ("volumetric_divisor", 100.0, 100_000.0),
        ("round_up_mm", 0.1, 1_000.0),
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

    #[test]
    fn the_query_round_trips_and_refuses_what_it_does_not_know() {
        assert_eq!(EdgeQuery::parse([""; 0]), Ok(EdgeQuery::default()));
        let q = EdgeQuery::parse(["codes", "cluster_mm=30", "round_up_mm=5"]).expect("valid");
        assert!(q.codes);
        assert_eq!(q.config.cluster_radius_m, 0.03);
        assert_eq!(q.billing.division_mm, Some(5.0));
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
    }
}
