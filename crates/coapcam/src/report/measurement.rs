//! The measurement report as one typed value, [`Measurement`]: what the server's edge
//! measurement answers, what `measure --json` prints, what the text output is rendered
//! from, and what a results log keeps. Its document (JSON, or CBOR by Accept) is the
//! serde form of this type; the field names carry their units (docs/design.md §6).
//!
//! Versions: the document carries `"v"` ([`VERSION`]); a document without it is version 1
//! (the servers before the field). Fields are only ever added, each optional for a
//! reader (missing means "not known"), and a reader ignores the fields it does not know,
//! so an addition keeps the version. Removing a field or changing what one means
//! increments it, and a reader refuses a version newer than its own
//! ([`MeasurementError::Version`]).

use std::fmt::Write as _;
use std::net::SocketAddr;
use std::time::Duration;

use geometry::{Dimensions, ParcelFit, Shape};
use serde::{Deserialize, Serialize};

use super::{Billing, Parcel, Seen, Table, describe, format_mm, ms};
use crate::timesync::FrameTime;

/// The version of the document this program writes and the newest it reads.
pub const VERSION: u32 = 1;

/// One measurement, wherever it was made (the client from clouds, or the server at the
/// edge), with what it was made from and how long it took.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Measurement {
    /// The document's version ([`VERSION`]; 1 when absent).
    #[serde(default = "first_version")]
    pub v: u32,
    /// `"parcel": "measured"` with its dimensions, `"parcel": "nothing"`, or `"parcel":
    /// "uncalibrated"` with the cameras that are not.
    #[serde(flatten)]
    pub parcel: Found,
    /// Points of the parcel (the largest object above the floor; 0 when there is none).
    pub parcel_points: u64,
    /// Points of the merged cloud measured.
    pub cloud_points: u64,
    /// Serials of the cameras in the cloud, in merge order.
    pub cameras: Vec<String>,
    /// The server of each camera, in the order of `cameras` (the client fills it; the
    /// server leaves it out).
    #[serde(default, skip_serializing_if = "Vec::is_empty", with = "addresses")]
    pub servers: Vec<SocketAddr>,
    /// The frames' times, microseconds since the UNIX epoch (one per cloud).
    pub frames_unix_us: Vec<u64>,
    /// Each camera's frame: its number and capture time on its server's clock, the
    /// server's clock offset where the client estimated it (docs/design.md, "Frames that
    /// belong together").
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub frames: Vec<FrameTime>,
    /// Until the last cloud was grabbed (and, on the client, received), ms.
    pub grab_ms: f64,
    /// On the client: from the first request until the result was known, ms.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cycle_ms: Option<f64>,
    /// On the client: bytes of clouds (or of this document) received.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub received_bytes: Option<u64>,
    /// At the edge: the server's time from the request to the answer, ms.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub measure_ms: Option<f64>,
    /// The codes read, each once with the cameras that read it, when they were asked for.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub codes: Option<Vec<Seen>>,
    /// How long grabbing the color images and reading the codes took, ms.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub codes_ms: Option<f64>,
    /// What may make the result wrong or incomplete (cameras left out, uncalibrated).
    #[serde(default)]
    pub warnings: Vec<String>,
    /// Every parcel on the table, the largest first (the top-level fields describe the
    /// first, with the same numbers), each rounded as [`Billing`] says or refused with the
    /// reason; absent in documents from before the list.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub parcels: Vec<ParcelReport>,
}

/// One parcel of [`Measurement::parcels`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ParcelReport {
    /// `"measured"`, or `"refused"` with a `reason` and no dimensions.
    pub parcel: String,
    /// Why the data cannot support a number.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub reason: Option<String>,
    /// Length of its smallest enclosing cuboid, mm, as billed ([`Billing::billed_mm`]:
    /// rounded to the nearest multiple of its division).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub length_mm: Option<f64>,
    /// Width, the same way.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub width_mm: Option<f64>,
    /// Height, the same way.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub height_mm: Option<f64>,
    /// The division of length, width and height, mm (d, or 2 d above the switchover and
    /// for an irregular item's length and width; the step of `round_up_mm` when that was
    /// asked for).
    pub division_mm: [f64; 3],
    /// Length, width and height as measured, to 0.1 mm, before the rounding: to check
    /// accuracy with, not to bill on; absent for a refused parcel and in documents from
    /// before the field.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub unrounded_mm: Option<[f64; 3]>,
    /// Direction of the long side from +x towards +y, degrees in (-90, 90], to 0.01.
    pub yaw_deg: f64,
    /// The footprint's corners `[x, y]` in metres, to 0.1 mm.
    pub corners_m: [[f64; 2]; 4],
    /// `"cuboid"`, `"round"` (a tube or a cylinder) or `"irregular"` (a bag: its length
    /// and width take 2 d), each measured as its smallest enclosing cuboid.
    pub shape: String,
    /// How well a cuboid fits: the share of the lid's rectangle (its edges where the lid's
    /// density puts them) that the lid's hull covers, to 0.001.
    pub fit: f64,
    /// False when it touches another parcel (side by side).
    pub isolated: bool,
    /// False when it reaches beyond the view or holes hide part of it.
    pub complete: bool,
    /// The share of its footprint's cells that hold points, to 0.001.
    pub coverage: f64,
    /// Its points.
    pub points: u64,
}

impl ParcelReport {
    /// `fit` as `billing` reports it: rounded to its division, or refused.
    pub fn new(fit: &ParcelFit, billing: &Billing, min_coverage: f32) -> Self {
        let d = &fit.dimensions;
        let reason = billing.division.refusal(fit, min_coverage);
        let value = |k: usize, v: f64| reason.is_none().then(|| billing.billed_mm(k, v, fit.shape));
        let thousandth = |v: f64| (v * 1000.0).round() / 1000.0;
        let unrounded_mm = reason.is_none().then(|| unrounded(d));
        Self {
            parcel: if reason.is_some() {
                "refused"
            } else {
                "measured"
            }
            .into(),
            length_mm: value(0, d.length_mm),
            width_mm: value(1, d.width_mm),
            height_mm: value(2, d.height_mm),
            reason,
            division_mm: [(0, d.length_mm), (1, d.width_mm), (2, d.height_mm)]
                .map(|(k, v)| billing.division_of(k, v, fit.shape)),
            unrounded_mm,
            yaw_deg: (d.yaw_deg * 100.0).round() / 100.0,
            corners_m: d.corners_m.map(|c| c.map(|v| (v * 1e4).round() / 1e4)),
            shape: shape_name(fit.shape).into(),
            fit: thousandth(fit.fit),
            isolated: fit.isolated,
            complete: fit.complete,
            coverage: thousandth(fit.coverage),
            points: d.points as u64,
        }
    }
}

/// A shape's name in [`ParcelReport::shape`].
fn shape_name(shape: Shape) -> &'static str {
    match shape {
        Shape::Cuboid => "cuboid",
        Shape::Round => "round",
        Shape::Irregular => "irregular",
    }
}

fn first_version() -> u32 {
    1
}

/// Length, width and height to 0.1 mm, unrounded otherwise.
fn unrounded(d: &Dimensions) -> [f64; 3] {
    [d.length_mm, d.width_mm, d.height_mm].map(|v| (v * 10.0).round() / 10.0)
}

/// What a measurement found on the table.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "parcel", rename_all = "lowercase")]
pub enum Found {
    /// The largest object above the floor, measured.
    Measured(Reported),
    /// Nothing on the table.
    Nothing,
    /// No dimensions: the station is not calibrated. A camera of the measurement has the
    /// identity 3d-transformation (nothing was ever written for it, as every real camera,
    /// recording and `calibrated = false` synthetic camera starts), so its points are in
    /// its own frame, where the floor is not at z = 0 and any "parcel" is nonsense.
    Uncalibrated {
        /// The cameras with the identity 3d-transformation.
        #[serde(default)]
        uncalibrated: Vec<String>,
    },
    /// The largest object was found but the data cannot support a number: not seen
    /// whole, holes, side by side, or out of the measurable range.
    Refused {
        /// Why.
        reason: String,
    },
    /// Not measured: the frames do not belong together (capture times further apart
    /// than the allowed skew, or a stale camera); `reason` names the camera.
    Unsynced {
        /// Why, naming the camera(s).
        reason: String,
    },
}

/// A measured parcel as reported: the dimensions rounded as its [`Billing`] says, the
/// numbers to bill on (the same as the first of [`Measurement::parcels`]).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Reported {
    /// Longer side of the footprint, mm, as billed ([`Billing::billed_mm`]).
    pub length_mm: f64,
    /// Shorter side of the footprint, mm, as billed.
    pub width_mm: f64,
    /// Height above the floor, mm, as billed.
    pub height_mm: f64,
    /// The division the length and width were rounded to: the accuracy division d (2 d for
    /// an irregular item; a dimension above 200 d takes 2 d, as `parcels[0].division_mm`
    /// gives each), or the step of `round_up_mm`; `null` in documents made before the
    /// rounding to the division (their dimensions to 0.1 mm).
    pub division_mm: Option<f64>,
    /// Length, width and height as measured, to 0.1 mm, before the rounding: to check
    /// accuracy with, not to bill on; absent in documents from before the field.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub unrounded_mm: Option<[f64; 3]>,
    /// Direction of the long side from +x towards +y, degrees in (-90, 90], to 0.01.
    pub yaw_deg: f64,
    /// The footprint's corners `[x, y]` in metres, around the rectangle, to 0.1 mm.
    pub corners_m: [[f64; 2]; 4],
    /// Volume of the reported dimensions, litres.
    pub volume_l: f64,
    /// cm³ over the divisor, kg.
    pub volumetric_weight_kg: f64,
    /// The divisor of the volumetric weight, cm³ per kg.
    pub volumetric_divisor_cm3_per_kg: f64,
}

impl Reported {
    /// `d`, of a parcel of `shape`, as `billing` reports it.
    pub fn new(d: &Dimensions, shape: Shape, billing: &Billing) -> Self {
        let [length_mm, width_mm, height_mm] = billing.dimensions_mm(d, shape);
        let milli = |v: f64| (v * 1000.0).round() / 1000.0;
        Self {
            length_mm,
            width_mm,
            height_mm,
            division_mm: Some(billing.division_mm(shape)),
            unrounded_mm: Some(unrounded(d)),
            yaw_deg: (d.yaw_deg * 100.0).round() / 100.0,
            // To 0.1 mm, as the dimensions.
            corners_m: d.corners_m.map(|c| c.map(|v| (v * 1e4).round() / 1e4)),
            volume_l: milli(billing.volume_l(d, shape)),
            volumetric_weight_kg: milli(billing.volumetric_weight_kg(d, shape)),
            volumetric_divisor_cm3_per_kg: billing.divisor_cm3_per_kg,
        }
    }

    /// The numbers to bill on as every output writes them ([`format_mm`]): `325 x 240 x
    /// 100 mm`.
    pub fn dimensions_text(&self) -> String {
        let mm = |v: f64| format_mm(v, self.division_mm);
        format!(
            "{} x {} x {} mm",
            mm(self.length_mm),
            mm(self.width_mm),
            mm(self.height_mm)
        )
    }

    /// The reported parcel as dimensions of `points` points (the volume of the reported
    /// dimensions, unrounded).
    pub fn dimensions(&self, points: usize) -> Dimensions {
        Dimensions {
            length_mm: self.length_mm,
            width_mm: self.width_mm,
            height_mm: self.height_mm,
            yaw_deg: self.yaw_deg,
            corners_m: self.corners_m,
            volume_l: self.length_mm * self.width_mm * self.height_mm / 1e6,
            points,
        }
    }
}

/// Why a measurement document could not be read or written.
#[derive(Debug, thiserror::Error)]
pub enum MeasurementError {
    /// Not JSON, or JSON that is not a measurement document.
    #[error("the measurement is not a JSON measurement document: {0}")]
    Json(#[from] serde_json::Error),
    /// Not CBOR, or CBOR that is not a measurement document.
    #[error("the measurement is not a CBOR measurement document: {0}")]
    Cbor(#[from] ciborium::de::Error<std::io::Error>),
    /// Encoding as CBOR failed.
    #[error("encoding the measurement as CBOR: {0}")]
    CborEncode(#[from] ciborium::ser::Error<std::io::Error>),
    /// A document of a newer version than this program reads.
    #[error("the measurement document is version {found}; this program reads up to {VERSION}")]
    Version {
        /// The document's `v`.
        found: u32,
    },
}

impl Measurement {
    /// A measurement of `parcel` (reported as `billing` says; a measured parcel's shape
    /// picks the division of its length and width) in a merged cloud of `cloud_points`
    /// points from `cameras`, whose frames are of `frames_unix_us`, grabbed in `grab`; no
    /// codes, no warnings, no client's fields yet.
    pub fn new(
        parcel: &Parcel,
        billing: &Billing,
        cloud_points: usize,
        cameras: Vec<String>,
        frames_unix_us: Vec<u64>,
        grab: Duration,
    ) -> Self {
        let (found, parcel_points) = match parcel {
            Parcel::Measured(d, shape) => {
                (Found::Measured(Reported::new(d, *shape, billing)), d.points)
            }
            Parcel::Nothing { points } => (Found::Nothing, *points),
            Parcel::Refused { reason, points } => (
                Found::Refused {
                    reason: reason.clone(),
                },
                *points,
            ),
        };
        Self {
            v: VERSION,
            parcel: found,
            parcel_points: parcel_points as u64,
            cloud_points: cloud_points as u64,
            cameras,
            servers: Vec::new(),
            frames_unix_us,
            frames: Vec::new(),
            grab_ms: ms(grab),
            cycle_ms: None,
            received_bytes: None,
            measure_ms: None,
            codes: None,
            codes_ms: None,
            warnings: Vec::new(),
            parcels: Vec::new(),
        }
    }

    /// A measurement of every parcel of `table` (see [`Measurement::new`]): the top-level
    /// fields describe the largest, refused (`"parcel": "refused"`) when its data cannot
    /// support a number; `parcels` lists them all.
    pub fn of_table(
        table: &Table,
        billing: &Billing,
        min_coverage: f32,
        cloud_points: usize,
        cameras: Vec<String>,
        frames_unix_us: Vec<u64>,
        grab: Duration,
    ) -> Self {
        let parcels: Vec<ParcelReport> = table
            .fits
            .iter()
            .map(|f| ParcelReport::new(f, billing, min_coverage))
            .collect();
        let largest = match (table.largest(), parcels.first()) {
            (
                Parcel::Measured(d, _),
                Some(ParcelReport {
                    reason: Some(reason),
                    ..
                }),
            ) => Parcel::Refused {
                reason: reason.clone(),
                points: d.points,
            },
            (largest, _) => largest,
        };
        // The top level is the largest's numbers, billed as its own shape says.
        let mut m = Self::new(
            &largest,
            billing,
            cloud_points,
            cameras,
            frames_unix_us,
            grab,
        );
        m.parcels = parcels;
        m
    }

    /// Adds the codes read, in `took`.
    pub fn set_codes(&mut self, seen: Vec<Seen>, took: Duration) {
        self.codes = Some(seen);
        self.codes_ms = Some(ms(took));
    }

    /// The reported parcel; `None` when nothing is on the table or the station is not
    /// calibrated.
    pub fn reported(&self) -> Option<&Reported> {
        match &self.parcel {
            Found::Measured(r) => Some(r),
            Found::Nothing
            | Found::Uncalibrated { .. }
            | Found::Refused { .. }
            | Found::Unsynced { .. } => None,
        }
    }

    /// The parcel as reported (see [`Reported::dimensions`]); an uncalibrated station's
    /// measurement has none (`Nothing`, its `parcel_points` 0): ask [`Measurement::parcel`]
    /// first where that matters.
    pub fn parcel(&self) -> Parcel {
        let points = usize::try_from(self.parcel_points).unwrap_or(usize::MAX);
        match &self.parcel {
            Found::Measured(r) => Parcel::Measured(r.dimensions(points), self.reported_shape()),
            Found::Nothing | Found::Uncalibrated { .. } | Found::Unsynced { .. } => {
                Parcel::Nothing { points }
            }
            Found::Refused { reason } => Parcel::Refused {
                reason: reason.clone(),
                points,
            },
        }
    }

    /// The shape of the reported parcel, the first of `parcels`: a box in a document from
    /// before the list, when every parcel was measured as one (and for a shape this
    /// program does not know).
    fn reported_shape(&self) -> Shape {
        let named = |name: &str| {
            [Shape::Cuboid, Shape::Round, Shape::Irregular]
                .into_iter()
                .find(|&s| shape_name(s) == name)
        };
        self.parcels
            .first()
            .and_then(|p| named(&p.shape))
            .unwrap_or(Shape::Cuboid)
    }

    /// Withholds the dimensions because `cameras` are not calibrated (their
    /// 3d-transformation is the identity): the parcel becomes `uncalibrated`, with no
    /// parcel points and no `parcels`; nothing if `cameras` is empty. The warnings stay
    /// as they are.
    pub fn withhold_uncalibrated(&mut self, cameras: &[String]) {
        if cameras.is_empty() {
            return;
        }
        self.parcel = Found::Uncalibrated {
            uncalibrated: cameras.to_vec(),
        };
        self.parcel_points = 0;
        self.parcels.clear();
    }

    /// The document as JSON.
    pub fn to_json(&self) -> Result<String, MeasurementError> {
        Ok(serde_json::to_string(self)?)
    }

    /// The document as CBOR.
    pub fn to_cbor(&self) -> Result<Vec<u8>, MeasurementError> {
        let mut out = Vec::new();
        ciborium::into_writer(self, &mut out)?;
        Ok(out)
    }

    /// Reads a JSON document.
    pub fn from_json(bytes: &[u8]) -> Result<Self, MeasurementError> {
        Self::checked(serde_json::from_slice(bytes)?)
    }

    /// Reads a CBOR document.
    pub fn from_cbor(bytes: &[u8]) -> Result<Self, MeasurementError> {
        Self::checked(ciborium::from_reader(bytes)?)
    }

    fn checked(m: Self) -> Result<Self, MeasurementError> {
        if m.v > VERSION {
            return Err(MeasurementError::Version { found: m.v });
        }
        Ok(m)
    }

    /// The text `measure` prints.
    pub fn text(&self) -> String {
        let timing = match self.measure_ms {
            Some(t) => format!("measured on the server in {t:.0} ms"),
            None => format!("grab and transfer {:.0} ms", self.grab_ms),
        };
        let received = match self.received_bytes {
            Some(n) if n < 100_000 => format!("{n} bytes"),
            n => format!("{:.2} MB", n.map_or(f64::NAN, |n| n as f64) / 1e6),
        };
        let provenance = format!(
            "{} points from {} camera(s): {}\n\
             cycle {:.0} ms ({timing}), {received} received",
            self.cloud_points,
            self.cameras.len(),
            self.cameras.join(", "),
            self.cycle_ms.unwrap_or(f64::NAN),
        );
        let mut out = match &self.parcel {
            Found::Measured(r) => {
                let mm = |v: f64| format_mm(v, r.division_mm);
                let rounded = match (r.division_mm, r.unrounded_mm) {
                    (Some(s), Some([l, w, h])) => {
                        format!("  (division {s} mm; unrounded {l:.1} x {w:.1} x {h:.1} mm)")
                    }
                    (Some(s), None) => format!("  (division {s} mm)"),
                    (None, _) => String::new(),
                };
                let mut corners = String::new();
                for [x, y] in r.corners_m {
                    if !corners.is_empty() {
                        corners.push(' ');
                    }
                    let _ = write!(corners, "({x:.3}, {y:.3})");
                }
                format!(
                    "length {} mm  width {} mm  height {} mm{rounded}\n\
                     yaw {:.1} deg  volume {:.2} l  volumetric weight {:.2} kg (divisor {} cm3/kg)\n\
                     footprint corners (m): {corners}\n\
                     parcel {} points of {provenance}",
                    mm(r.length_mm),
                    mm(r.width_mm),
                    mm(r.height_mm),
                    r.yaw_deg,
                    r.volume_l,
                    r.volumetric_weight_kg,
                    r.volumetric_divisor_cm3_per_kg,
                    self.parcel_points,
                )
            }
            Found::Nothing => format!(
                "nothing on the table (the largest object above the floor has {} points)\n{provenance}",
                self.parcel_points
            ),
            Found::Uncalibrated { uncalibrated } => format!(
                "not calibrated: no dimensions (camera(s) {} have the identity 3d-transformation, so their points are not in the table's frame; run coapcam calibrate)\n{provenance}",
                uncalibrated.join(", ")
            ),
            Found::Refused { reason } => format!(
                "refused: {reason}\nparcel {} points of {provenance}",
                self.parcel_points
            ),
            Found::Unsynced { reason } => {
                format!("not measured: the frames do not belong together: {reason}\n{provenance}")
            }
        };
        if self.parcels.len() > 1 {
            for (k, p) in self.parcels.iter().enumerate() {
                let what = match (p.length_mm, p.width_mm, p.height_mm) {
                    (Some(l), Some(w), Some(h)) => {
                        let [dl, dw, dh] = p.division_mm.map(Some);
                        format!(
                            "{} x {} x {} mm",
                            format_mm(l, dl),
                            format_mm(w, dw),
                            format_mm(h, dh)
                        )
                    }
                    _ => format!("refused: {}", p.reason.as_deref().unwrap_or("")),
                };
                let _ = write!(
                    out,
                    "\nparcel {}: {what}, {}{}{}",
                    k + 1,
                    p.shape,
                    if p.isolated { "" } else { ", side by side" },
                    if p.complete { "" } else { ", not complete" },
                );
            }
        }
        if let Some(seen) = &self.codes {
            let _ = write!(
                out,
                "\ncodes: {} (grabbed and read in {:.0} ms)",
                describe(seen),
                self.codes_ms.unwrap_or(f64::NAN)
            );
        }
        out
    }
}

/// Socket addresses as their text (`127.0.0.1:5683`, `[::1]:5683`) in every format, CBOR
/// included (serde's own form is a tuple outside human-readable formats).
mod addresses {
    use std::net::SocketAddr;

    use serde::{Deserialize as _, Deserializer, Serializer, de::Error as _};

    pub(super) fn serialize<S: Serializer>(a: &[SocketAddr], s: S) -> Result<S::Ok, S::Error> {
        s.collect_seq(a.iter().map(ToString::to_string))
    }

    pub(super) fn deserialize<'de, D: Deserializer<'de>>(
        d: D,
    ) -> Result<Vec<SocketAddr>, D::Error> {
        Vec::<String>::deserialize(d)?
            .iter()
            .map(|s| {
                s.parse()
                    .map_err(|e| D::Error::custom(format!("server {s:?}: {e}")))
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::vision::codes::{Code, CodeKind};

    fn measured() -> Measurement {
        let d = Dimensions {
            length_mm: 400.04,
            width_mm: 300.0,
            height_mm: 200.0,
            yaw_deg: 15.004,
            corners_m: [[0.1, 0.2], [0.5, 0.2], [0.5, 0.5], [0.1, 0.500_04]],
            volume_l: 24.0,
            points: 1234,
        };
        let mut m = Measurement::new(
            &Parcel::Measured(d, Shape::Cuboid),
            &Billing::default(),
            5000,
            vec!["840412060746".into()],
            vec![1_700_000_000_000_000],
            Duration::from_millis(42),
        );
        m.set_codes(
            vec![Seen {
                code: Code {
                    kind: CodeKind::Qr,
                    text: "PKG-0001".into(),
                },
                cameras: vec!["840412060746".into()],
            }],
            Duration::from_millis(7),
        );
        m.servers = vec!["127.0.0.1:5683".parse().expect("address")];
        m.cycle_ms = Some(50.0);
        m.received_bytes = Some(321);
        m
    }

    #[test]
    fn the_document_has_the_fields_of_measure_json_and_round_trips() {
        let m = measured();
        let doc: serde_json::Value =
            serde_json::from_str(&m.to_json().expect("JSON")).expect("parses");
        assert_eq!(doc["v"], 1);
        assert_eq!(doc["parcel"], "measured");
        assert_eq!(doc["length_mm"], 400.0);
        assert_eq!(doc["division_mm"], 5.0);
        assert_eq!(
            doc["unrounded_mm"],
            serde_json::json!([400.0, 300.0, 200.0])
        );
        assert_eq!(doc["yaw_deg"], 15.0);
        assert_eq!(doc["corners_m"][3][1], 0.5);
        assert_eq!(doc["volume_l"], 24.0);
        assert_eq!(doc["volumetric_weight_kg"], 4.8);
        assert_eq!(doc["volumetric_divisor_cm3_per_kg"], 5000.0);
        assert_eq!(doc["parcel_points"], 1234);
        assert_eq!(doc["servers"][0], "127.0.0.1:5683");
        assert_eq!(doc["codes"][0]["kind"], "qr");
        assert_eq!(doc["codes"][0]["text"], "PKG-0001");
        assert_eq!(doc["codes_ms"], 7.0);
        assert_eq!(doc["warnings"], serde_json::json!([]));
        assert!(doc.get("measure_ms").is_none());
        let json = m.to_json().expect("JSON");
        assert_eq!(Measurement::from_json(json.as_bytes()).expect("reads"), m);
        let cbor = m.to_cbor().expect("CBOR");
        assert_eq!(Measurement::from_cbor(&cbor).expect("reads"), m);
        let as_value: serde_json::Value = ciborium::from_reader(&cbor[..]).expect("CBOR");
        assert_eq!(as_value, doc, "the same document in CBOR");
    }

    #[test]
    fn nothing_on_the_table_has_no_dimensions() {
        let mut m = Measurement::new(
            &Parcel::Nothing { points: 12 },
            &Billing::default(),
            100,
            Vec::new(),
            Vec::new(),
            Duration::ZERO,
        );
        m.measure_ms = Some(3.0);
        let doc: serde_json::Value =
            serde_json::from_str(&m.to_json().expect("JSON")).expect("parses");
        assert_eq!(doc["parcel"], "nothing");
        assert_eq!(doc["parcel_points"], 12);
        assert!(doc.get("length_mm").is_none() && doc.get("servers").is_none());
        let back = Measurement::from_json(doc.to_string().as_bytes()).expect("reads");
        assert!(matches!(back.parcel(), Parcel::Nothing { points: 12 }));
        assert!(back.text().starts_with("nothing on the table"));
    }

    #[test]
    fn an_uncalibrated_station_gives_no_dimensions() {
        let mut m = measured();
        m.withhold_uncalibrated(&[]);
        assert!(m.reported().is_some(), "nothing withheld without cameras");
        m.withhold_uncalibrated(&["840412060746".into()]);
        let doc: serde_json::Value =
            serde_json::from_str(&m.to_json().expect("JSON")).expect("parses");
        assert_eq!(doc["parcel"], "uncalibrated");
        assert_eq!(doc["uncalibrated"], serde_json::json!(["840412060746"]));
        assert_eq!(doc["parcel_points"], 0);
        assert!(doc.get("length_mm").is_none() && doc.get("volume_l").is_none());
        let back = Measurement::from_json(doc.to_string().as_bytes()).expect("reads");
        assert_eq!(back, m);
        assert_eq!(
            Measurement::from_cbor(&m.to_cbor().expect("CBOR")).expect("reads"),
            m
        );
        assert!(back.reported().is_none());
        assert!(
            back.text().starts_with("not calibrated: no dimensions"),
            "{}",
            back.text()
        );
    }

    #[test]
    fn old_documents_read_and_newer_or_broken_ones_are_refused() {
        let mut doc: serde_json::Value =
            serde_json::from_str(&measured().to_json().expect("JSON")).expect("parses");
        let object = doc.as_object_mut().expect("a map");
        object.remove("v");
        object.insert("added_later".into(), 1.into());
        let old = Measurement::from_json(doc.to_string().as_bytes()).expect("version 1");
        assert_eq!(old.v, 1);
        doc["v"] = 2.into();
        assert!(matches!(
            Measurement::from_json(doc.to_string().as_bytes()),
            Err(MeasurementError::Version { found: 2 })
        ));
        doc["v"] = 1.into();
        doc["parcel"] = "floating".into();
        assert!(matches!(
            Measurement::from_json(doc.to_string().as_bytes()),
            Err(MeasurementError::Json(_))
        ));
        doc["parcel"] = "measured".into();
        doc["servers"] = serde_json::json!(["not an address"]);
        assert!(Measurement::from_json(doc.to_string().as_bytes()).is_err());
        assert!(matches!(
            Measurement::from_cbor(b"\xff"),
            Err(MeasurementError::Cbor(_))
        ));
    }

    #[test]
    fn the_text_names_the_dimensions_codes_and_timing() {
        let text = measured().text();
        assert!(
            text.starts_with(
                "length 400 mm  width 300 mm  height 200 mm  (division 5 mm; unrounded 400.0 x 300.0 x 200.0 mm)\n"
            ),
            "{text}"
        );
        assert!(text.contains("volumetric weight 4.80 kg (divisor 5000 cm3/kg)"));
        assert!(text.contains("cycle 50 ms (grab and transfer 42 ms), 321 bytes received"));
        assert!(text.ends_with("codes: qr \"PKG-0001\" (840412060746) (grabbed and read in 7 ms)"));
    }
}
