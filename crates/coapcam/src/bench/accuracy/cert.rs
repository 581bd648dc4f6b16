//! `bench accuracy --set cert`: the certification set (`rgbd::cert`: random stations of
//! 1 to 4 cameras, objects of every shape and surface, alone and in groups at set
//! spacings, boxes labelled) measured end to end over CoAP on loopback, the cameras
//! prepared as `measure --prepare --codes` prepares them, the codes read from a new color
//! image of every camera. Every object is held against its truth and against what a
//! certified system accepts (isolated by 20 mm, in view, returning depth): per class the
//! first-pass rate (within 1 d on each axis and its code read), false refusals, phantom
//! parcels, merged pairs, silently wrong numbers and missing objects.

use std::time::Instant;

use anyhow::bail;
use geometry::{DimensionConfig, ParcelFit};
use rgbd::cert::{CertObject, CertScene, MIN_SPACING_M, SPACINGS_MM, cert_scene, footprint_gap};
use rgbd::scene::Truth;

use super::lane::{Outcome, judged_shape, outside};
use crate::client::CamClient;
use crate::client::codes;
use crate::client::measure::{self, Source, prepare_cameras};
use crate::report::Billing;
use crate::vision::codes::CodeKind;

/// What to run.
#[derive(Debug, Clone)]
pub struct Config {
    /// Number of scenes (at least 1).
    pub scenes: usize,
    /// The first scene's index (a run may cover part of a set).
    pub first: usize,
    /// Seed of the set.
    pub seed: u64,
    /// The measurement's thresholds.
    pub dimension: DimensionConfig,
    /// The accuracy division.
    pub billing: Billing,
}

/// What became of one object of a scene.
#[derive(Debug, Clone, PartialEq)]
pub struct ObjectResult {
    /// The object, its truth and what a certified system makes of it.
    pub object: CertObject,
    /// What the station said where it stands.
    pub outcome: Outcome,
    /// Whether its label's text was read by any camera; `None` without a label.
    pub code_read: Option<bool>,
    /// The widest its label's modules span in a camera's color image, pixels
    /// ([`label_module_px`]); `None` without a label or when no camera sees it.
    pub module_px: Option<f64>,
    /// The parcel matched to it also holds another object 20 mm or more from it.
    pub merged: bool,
    /// Parcels reported that match no object, nearest to this one.
    pub phantoms: usize,
}

impl ObjectResult {
    /// Reported minus true, mm, per axis; `None` without a number.
    pub fn reported_errors(&self) -> Option<[f64; 3]> {
        let t = truth_mm(&self.object.truth);
        match &self.outcome {
            Outcome::Measured { reported, .. } => Some([0, 1, 2].map(|k| reported[k] - t[k])),
            _ => None,
        }
    }

    /// Measured (unrounded) minus true, mm.
    pub fn raw_errors(&self) -> Option<[f64; 3]> {
        let t = truth_mm(&self.object.truth);
        match &self.outcome {
            Outcome::Measured { raw, .. } => Some([0, 1, 2].map(|k| raw[k] - t[k])),
            _ => None,
        }
    }

    /// A number on every axis within `factor` divisions of the truth.
    fn within(&self, billing: &Billing, factor: f64) -> bool {
        let t = truth_mm(&self.object.truth);
        let shape = judged_shape(self.object.truth.kind);
        self.reported_errors().is_some_and(|e| {
            (0..3).all(|k| e[k].abs() <= factor * billing.division.of_axis(k, t[k], shape) + 1e-6)
        })
    }

    /// Measured within 1 d on each axis.
    pub fn within_1d(&self, billing: &Billing) -> bool {
        self.within(billing, 1.0)
    }

    /// A number more than 2 d from the truth, with no flag (the lane set's measure).
    pub fn silently_wrong(&self, billing: &Billing) -> bool {
        self.reported_errors().is_some() && !self.within(billing, 2.0)
    }

    /// Whether its label's modules span the reader's limit for its symbology
    /// ([`CodeKind::min_px_per_module`]) in some camera: a label below it no camera of the
    /// station can resolve, whatever reads it.
    pub fn label_in_reach(&self) -> bool {
        self.object.label.as_ref().is_some_and(|l| {
            self.module_px
                .is_some_and(|px| px >= CodeKind::from(l.kind).min_px_per_module())
        })
    }

    /// Its label is in reach and its code was not read.
    pub fn unread(&self) -> bool {
        self.code_read == Some(false) && self.label_in_reach()
    }

    /// Accepted, measured within 1 d on each axis, and its code read if its label is in
    /// reach ([`ObjectResult::label_in_reach`]; a label below it is counted apart).
    pub fn first_pass(&self, billing: &Billing) -> bool {
        self.object.accepted() && self.within_1d(billing) && !self.unread()
    }

    /// Accepted and refused.
    pub fn false_refusal(&self) -> bool {
        self.object.accepted() && matches!(self.outcome, Outcome::Refused(_))
    }

    /// The classes it counts in, as (class, value).
    pub fn classes(&self, cameras: usize) -> [(&'static str, String); 6] {
        let o = &self.object;
        let spacing = match o.judged.gap_m {
            None => "alone".to_owned(),
            Some(g) => {
                let mm = g * 1e3 + 0.5;
                let bucket = SPACINGS_MM
                    .iter()
                    .rev()
                    .find(|s| **s <= mm)
                    .copied()
                    .unwrap_or(0.0);
                format!("{bucket:.0} mm")
            }
        };
        [
            ("shape", o.truth.kind.name().to_owned()),
            ("surface", o.surface.name().to_owned()),
            ("height", if o.flat { "flat" } else { "tall" }.to_owned()),
            ("spacing", spacing),
            ("cameras", cameras.to_string()),
            (
                "label",
                o.label.as_ref().map_or_else(
                    || "none".to_owned(),
                    |l| format!("{:?}", l.kind).to_lowercase(),
                ),
            ),
        ]
    }
}

fn truth_mm(t: &Truth) -> [f64; 3] {
    [t.length_mm(), t.width_mm(), t.height_mm()]
}

/// One scene's measurement.
#[derive(Debug, Clone)]
pub struct Row {
    /// The scene's index in the set.
    pub index: usize,
    /// Its cameras.
    pub cameras: usize,
    /// The spacing of its group, mm (`None`: one object).
    pub spacing_mm: Option<f64>,
    /// Its objects.
    pub objects: Vec<ObjectResult>,
    /// Parcels reported that match no object.
    pub phantoms: usize,
    /// The measurement's cycle (grabs and geometry), ms.
    pub cycle_ms: f64,
    /// Reading the codes, ms.
    pub codes_ms: f64,
    /// Why nothing could be measured.
    pub error: Option<String>,
}

/// Share of `t`'s footprint that `fit`'s footprint covers, from a grid of 15 x 15
/// points over it (a point within 5 mm of the fit's footprint counts).
fn covered(t: &Truth, fit: &ParcelFit) -> f64 {
    const N: usize = 15;
    let [c0, c1, _, c3] = t.footprint;
    let mut inside = 0;
    for i in 0..N {
        for j in 0..N {
            let (a, b) = ((i as f64 + 0.5) / N as f64, (j as f64 + 0.5) / N as f64);
            let p = [
                c0[0] + a * (c1[0] - c0[0]) + b * (c3[0] - c0[0]),
                c0[1] + a * (c1[1] - c0[1]) + b * (c3[1] - c0[1]),
            ];
            inside += usize::from(outside(&fit.dimensions.corners_m, p) <= 0.005);
        }
    }
    inside as f64 / (N * N) as f64
}

/// For each truth, the fit covering most of its footprint (`None` when no fit covers
/// any of it); and the fits no truth took (phantoms), by index.
fn assign(truths: &[Truth], fits: &[ParcelFit]) -> (Vec<Option<usize>>, Vec<usize>) {
    let matched: Vec<Option<usize>> = truths
        .iter()
        .map(|t| {
            fits.iter()
                .enumerate()
                .map(|(i, f)| (i, covered(t, f)))
                .filter(|(_, c)| *c > 0.0)
                .max_by(|a, b| a.1.total_cmp(&b.1))
                .map(|(i, _)| i)
        })
        .collect();
    let phantoms = (0..fits.len())
        .filter(|i| !matched.contains(&Some(*i)))
        .collect();
    (matched, phantoms)
}

/// The centre of a fit's footprint.
fn centre(fit: &ParcelFit) -> [f64; 2] {
    let c = &fit.dimensions.corners_m;
    [0, 1].map(|k| c.iter().map(|p| p[k]).sum::<f64>() / 4.0)
}

/// The widest a module of object `o`'s label spans in the 1920x1080 color image of a
/// camera of `scene` that sees the label's centre, pixels: one module laid at the label's
/// centre on the box's top face, along the label's width and (for a 2D code) across it,
/// projected through the color intrinsics from the camera's pose (the 15 mm between the
/// D415's color and depth sensors left out); the narrower of the two. `None` without a
/// label, for a label off a box, or when no camera sees its centre.
pub fn label_module_px(scene: &rgbd::Scene, o: &CertObject) -> Option<f64> {
    let label = o.label.as_ref()?;
    if o.truth.kind != rgbd::scene::ObjectKind::Box {
        return None;
    }
    let parcel = scene.boxes.get(o.truth.index)?;
    let module = label.size / label.modules_across().ok()? as f64;
    let (sin, cos) = parcel.yaw_deg.to_radians().sin_cos();
    let centre = [parcel.center[0], parcel.center[1], parcel.size[2]];
    let along = [cos * module / 2.0, sin * module / 2.0, 0.0];
    let across = [-sin * module / 2.0, cos * module / 2.0, 0.0];
    let k = rgbd::d415::color_intrinsics(1920, 1080);
    let (width, height) = (f64::from(k.width), f64::from(k.height));
    scene
        .cameras
        .iter()
        .filter_map(|camera| {
            let pose = camera.pose()?;
            let pixel = |p: [f64; 3]| -> Option<[f64; 2]> {
                let d = [0, 1, 2].map(|i| p[i] - pose.translation[i]);
                let r = pose.rotation;
                let q = [0, 1, 2].map(|j| r[0][j] * d[0] + r[1][j] * d[1] + r[2][j] * d[2]);
                (q[2] > 0.0).then(|| {
                    [
                        f64::from(k.fx) * q[0] / q[2] + f64::from(k.ppx),
                        f64::from(k.fy) * q[1] / q[2] + f64::from(k.ppy),
                    ]
                })
            };
            let c = pixel(centre)?;
            if !(0.0..width).contains(&c[0]) || !(0.0..height).contains(&c[1]) {
                return None;
            }
            let span = |half: [f64; 3]| -> Option<f64> {
                let a = pixel([0, 1, 2].map(|i| centre[i] - half[i]))?;
                let b = pixel([0, 1, 2].map(|i| centre[i] + half[i]))?;
                Some((a[0] - b[0]).hypot(a[1] - b[1]))
            };
            let wide = span(along)?;
            Some(if label.kind.is_linear() {
                wide
            } else {
                wide.min(span(across)?)
            })
        })
        .max_by(f64::total_cmp)
}

/// Holds what the station measured (`fits`) and read (`codes`, the texts) against the
/// objects of `cert`.
pub fn judge_scene(
    cert: &CertScene,
    fits: &[ParcelFit],
    codes: &[String],
    config: &Config,
) -> (Vec<ObjectResult>, usize) {
    let truths: Vec<Truth> = cert.objects.iter().map(|o| o.truth).collect();
    let (matched, phantoms) = assign(&truths, fits);
    let mut results: Vec<ObjectResult> = cert
        .objects
        .iter()
        .enumerate()
        .map(|(i, o)| {
            let merged = matched[i].is_some_and(|f| {
                (0..truths.len()).any(|j| {
                    j != i
                        && matched[j] == Some(f)
                        && footprint_gap(&truths[i].footprint, &truths[j].footprint)
                            >= MIN_SPACING_M - 1e-9
                })
            });
            ObjectResult {
                object: o.clone(),
                outcome: matched[i].map_or(Outcome::Missing, |f| {
                    Outcome::of(&fits[f], &config.billing, config.dimension.min_coverage)
                }),
                code_read: o.label.as_ref().map(|l| codes.contains(&l.text)),
                module_px: label_module_px(&cert.scene, o),
                merged,
                phantoms: 0,
            }
        })
        .collect();
    for &p in &phantoms {
        let at = centre(&fits[p]);
        let nearest = (0..truths.len()).min_by(|a, b| {
            outside(&truths[*a].footprint, at).total_cmp(&outside(&truths[*b].footprint, at))
        });
        if let Some(n) = nearest {
            results[n].phantoms += 1;
        }
    }
    (results, phantoms.len())
}

/// Measures scene `cert` through `client`: prepares its cameras (roi above the floor,
/// spatial filter, color at 1920x1080), measures, reads the codes.
async fn measure_scene(
    client: &CamClient,
    cert: &CertScene,
    config: &Config,
) -> anyhow::Result<Row> {
    let serials: Vec<String> = cert
        .scene
        .cameras
        .iter()
        .map(|c| c.serial.to_string())
        .collect();
    prepare_cameras(client, &serials, 1.0, true).await?;
    let mut row = Row {
        index: cert.index,
        cameras: serials.len(),
        spacing_mm: cert.spacing_mm,
        objects: Vec::new(),
        phantoms: 0,
        cycle_ms: f64::NAN,
        codes_ms: f64::NAN,
        error: None,
    };
    let failed = |row: &mut Row, e: &(dyn std::error::Error + 'static)| {
        row.error = Some(crate::error_text(e));
        row.objects = cert
            .objects
            .iter()
            .map(|o| ObjectResult {
                object: o.clone(),
                outcome: Outcome::Missing,
                code_read: o.label.as_ref().map(|_| false),
                module_px: label_module_px(&cert.scene, o),
                merged: false,
                phantoms: 0,
            })
            .collect();
    };
    let m = match measure::measure_once(client, &Source::All, &config.dimension).await {
        Ok(m) => m,
        Err(e) => {
            failed(&mut row, &e);
            return Ok(row);
        }
    };
    row.cycle_ms = m.cycle.as_secs_f64() * 1e3;
    let started = Instant::now();
    let seen = match codes::read_cameras(client, &m.grabbed.cameras).await {
        Ok(seen) => seen,
        Err(e) => {
            failed(&mut row, &e);
            return Ok(row);
        }
    };
    row.codes_ms = started.elapsed().as_secs_f64() * 1e3;
    // An EAN-13 label beginning with 0 may be read as the UPC-A of the same bars.
    let texts: Vec<String> = seen.iter().flat_map(|s| s.code.label_texts()).collect();
    let (objects, phantoms) = judge_scene(cert, &m.table.fits, &texts, config);
    row.objects = objects;
    row.phantoms = phantoms;
    Ok(row)
}

/// Runs scenes `first .. first + scenes` of the set one after the other, handing each row
/// to `on_row` as it is measured; every row.
pub async fn run(
    config: &Config,
    mut on_row: impl FnMut(&Row) -> anyhow::Result<()>,
) -> anyhow::Result<Vec<Row>> {
    if config.scenes == 0 {
        bail!("--scenes must be at least 1");
    }
    let mut rows = Vec::new();
    let indices = config.first..config.first + config.scenes;
    let make = |index| cert_scene(config.seed, index);
    super::each_scene(
        "cert",
        indices,
        make,
        |c| &c.scene,
        async |client, cert| {
            let row = measure_scene(client, cert, config).await?;
            on_row(&row)?;
            rows.push(row);
            Ok(())
        },
    )
    .await?;
    Ok(rows)
}

/// What the objects of one class say together.
#[derive(Debug, Clone, PartialEq)]
pub struct ClassSummary {
    /// The class (`all`, `shape`, `surface`, `height`, `spacing`, `cameras`, `label`).
    pub class: &'static str,
    /// Its value (`box`, `black`, `20 mm`, `3`, ...).
    pub value: String,
    /// Objects.
    pub objects: usize,
    /// Of them, accepted by a certified system.
    pub accepted: usize,
    /// Accepted, within 1 d and read.
    pub first_pass: usize,
    /// Accepted and refused.
    pub false_refusals: usize,
    /// Accepted, given a number more than 1 d off on some axis.
    pub off: usize,
    /// Accepted, its label in reach, the code not read.
    pub unread: usize,
    /// Accepted, labelled, the label below the reader's limit in every camera.
    pub out_of_reach: usize,
    /// Labelled objects whose code was read (accepted or not), and labelled objects.
    pub read: [usize; 2],
    /// The same over the labels whose modules span the reader's limit or more in some
    /// camera ([`ObjectResult::label_in_reach`]).
    pub read_at_limit: [usize; 2],
    /// Not found where they stand, or the scene failed.
    pub missing: usize,
    /// In a pair 20 mm or more apart measured as one parcel.
    pub merged: usize,
    /// Phantom parcels nearest to these objects.
    pub phantoms: usize,
    /// A number more than 2 d off, with no flag.
    pub silently_wrong: usize,
}

impl ClassSummary {
    /// First pass as a share of the accepted, percent (NaN with none accepted).
    pub fn first_pass_pct(&self) -> f64 {
        if self.accepted == 0 {
            f64::NAN
        } else {
            100.0 * self.first_pass as f64 / self.accepted as f64
        }
    }

    fn of<'a>(
        class: &'static str,
        value: String,
        objects: impl Iterator<Item = &'a ObjectResult>,
        billing: &Billing,
    ) -> Self {
        let mut s = Self {
            class,
            value,
            objects: 0,
            accepted: 0,
            first_pass: 0,
            false_refusals: 0,
            off: 0,
            unread: 0,
            out_of_reach: 0,
            read: [0, 0],
            read_at_limit: [0, 0],
            missing: 0,
            merged: 0,
            phantoms: 0,
            silently_wrong: 0,
        };
        for o in objects {
            let accepted = o.object.accepted();
            s.objects += 1;
            s.accepted += usize::from(accepted);
            s.first_pass += usize::from(o.first_pass(billing));
            s.false_refusals += usize::from(o.false_refusal());
            s.off +=
                usize::from(accepted && o.reported_errors().is_some() && !o.within_1d(billing));
            s.unread += usize::from(accepted && o.unread());
            s.out_of_reach += usize::from(accepted && o.code_read.is_some() && !o.label_in_reach());
            if let Some(read) = o.code_read {
                s.read[0] += usize::from(read);
                s.read[1] += 1;
                if o.label_in_reach() {
                    s.read_at_limit[0] += usize::from(read);
                    s.read_at_limit[1] += 1;
                }
            }
            s.missing += usize::from(o.outcome == Outcome::Missing);
            s.merged += usize::from(o.merged);
            s.phantoms += o.phantoms;
            s.silently_wrong += usize::from(o.silently_wrong(billing));
        }
        s
    }

    /// Every class of `rows`: `all` first, then each class's values in a fixed order.
    pub fn all(rows: &[Row], billing: &Billing) -> Vec<Self> {
        let objects: Vec<(&ObjectResult, usize)> = rows
            .iter()
            .flat_map(|r| r.objects.iter().map(move |o| (o, r.cameras)))
            .collect();
        let mut out = vec![Self::of(
            "all",
            "all".to_owned(),
            objects.iter().map(|(o, _)| *o),
            billing,
        )];
        for k in 0..6 {
            let mut values: Vec<(&'static str, String)> = Vec::new();
            for (o, cameras) in &objects {
                let c = o.classes(*cameras)[k].clone();
                if !values.contains(&c) {
                    values.push(c);
                }
            }
            values.sort_by(|a, b| order(&a.1).cmp(&order(&b.1)).then(a.1.cmp(&b.1)));
            for (class, value) in values {
                let of = objects
                    .iter()
                    .filter(|(o, cameras)| o.classes(*cameras)[k].1 == value)
                    .map(|(o, _)| *o);
                out.push(Self::of(class, value.clone(), of, billing));
            }
        }
        out
    }
}

/// Sort key of a class value: spacings by their number, `alone` last.
fn order(value: &str) -> (u8, u64) {
    if value == "alone" {
        return (2, 0);
    }
    match value.trim_end_matches(" mm").parse::<u64>() {
        Ok(n) => (1, n),
        Err(_) => (0, 0),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use geometry::Dimensions;
    use rgbd::Scene;
    use rgbd::cert::{Surface, judge};

    /// A parcel measured `l` x `w` x `h` mm at `center` (metres), seen whole and alone.
    fn fit(center: [f64; 2], l: f64, w: f64, h: f64) -> ParcelFit {
        let (x, y) = (l / 2e3, w / 2e3);
        ParcelFit::whole_box(Dimensions {
            length_mm: l,
            width_mm: w,
            height_mm: h,
            yaw_deg: 0.0,
            corners_m: [[-x, -y], [x, -y], [x, y], [-x, y]]
                .map(|[a, b]| [center[0] + a, center[1] + b]),
            volume_l: l * w * h / 1e6,
            points: 1000,
        })
    }

    /// Two boxes 300 x 200 x 100 mm under one camera at (-0.17, 0) and (0.17, 0) (a gap
    /// of 40 mm), the first labelled.
    fn two_boxes() -> CertScene {
        let scene = Scene::from_toml(
            "[[camera]]\nserial = \"840412060746\"\nposition = [0.0, 0.0, 1.5]\n\
             look_at = [0.0, 0.0, 0.0]\nup = [0.0, 1.0, 0.0]\n\
             [[box]]\nsize = [0.3, 0.2, 0.1]\ncenter = [-0.17, 0.0]\n\
             label = { kind = \"qr\", text = \"ONE\", size = 0.12 }\n\
             [[box]]\nsize = [0.3, 0.2, 0.1]\ncenter = [0.17, 0.0]\n",
        )
        .unwrap();
        let objects = scene
            .truths()
            .into_iter()
            .zip(judge(&scene))
            .map(|(truth, judged)| CertObject {
                truth,
                surface: Surface::Cardboard,
                flat: false,
                label: scene.boxes[truth.index].label.clone(),
                judged,
            })
            .collect();
        CertScene {
            index: 0,
            scene,
            objects,
            spacing_mm: Some(40.0),
        }
    }

    fn config() -> Config {
        Config {
            scenes: 1,
            first: 0,
            seed: 1,
            dimension: DimensionConfig::default(),
            billing: Billing::default(),
        }
    }

    #[test]
    fn a_labels_module_spans_focal_length_times_module_over_distance() {
        let mut cert = two_boxes();
        // The camera 1.5 m above the floor, the label on a lid 0.1 m up, 0.17 m off the
        // axis: 1.4 m along the axis, seen nearly square on.
        let label = cert.objects[0].label.clone().unwrap();
        let module = label.size / label.modules_across().unwrap() as f64;
        let fx = f64::from(rgbd::d415::color_intrinsics(1920, 1080).fx);
        let px = label_module_px(&cert.scene, &cert.objects[0]).unwrap();
        assert!((px - fx * module / 1.4).abs() < 0.01 * px, "{px}");
        assert_eq!(label_module_px(&cert.scene, &cert.objects[1]), None);
        // Out of the camera's view: seen by none.
        cert.scene.boxes[0].center = [5.0, 0.0];
        cert.objects[0].truth.index = 0;
        assert_eq!(label_module_px(&cert.scene, &cert.objects[0]), None);
    }

    #[test]
    fn each_object_takes_the_parcel_over_it_and_the_rest_are_phantoms() {
        let cert = two_boxes();
        assert!(cert.objects.iter().all(CertObject::accepted));
        let billing = Billing::default();
        // Both measured, the first's code read; a sliver inside the first box and a
        // parcel where nothing stands are phantoms, nearest to the first.
        let fits = [
            fit([-0.17, 0.0], 301.0, 199.0, 100.4),
            fit([0.17, 0.0], 306.0, 200.0, 100.0),
            fit([-0.25, 0.05], 40.0, 20.0, 3.0),
            fit([-0.6, 0.3], 60.0, 60.0, 20.0),
        ];
        let (objects, phantoms) = judge_scene(&cert, &fits, &["ONE".to_owned()], &config());
        assert_eq!(phantoms, 2);
        assert_eq!(objects[0].phantoms, 2);
        assert_eq!(objects[0].code_read, Some(true));
        assert!(objects[0].first_pass(&billing));
        // The second: 306 reads 305, 1 d off: within 1 d, no label.
        assert_eq!(objects[1].code_read, None);
        assert!(objects[1].first_pass(&billing));
        // 308 reads 310: 2 d, not a first pass, not silently wrong; 313 reads 315: 3 d.
        let (off, _) = judge_scene(
            &cert,
            &[fits[0].clone(), fit([0.17, 0.0], 308.0, 200.0, 100.0)],
            &[],
            &config(),
        );
        assert_eq!(off[0].code_read, Some(false));
        assert!(!off[0].first_pass(&billing) && !off[1].first_pass(&billing));
        assert!(!off[1].silently_wrong(&billing));
        let (wrong, _) = judge_scene(
            &cert,
            &[fits[0].clone(), fit([0.17, 0.0], 313.0, 200.0, 100.0)],
            &[],
            &config(),
        );
        assert!(wrong[1].silently_wrong(&billing));
    }

    #[test]
    fn a_label_below_the_readers_limit_is_counted_apart_not_against_the_first_pass() {
        let mut cert = two_boxes();
        let billing = Billing::default();
        let fits = [
            fit([-0.17, 0.0], 301.0, 199.0, 100.4),
            fit([0.17, 0.0], 301.0, 200.0, 100.0),
        ];
        // The QR of 21 modules 1 cm wide from 1.4 m: under half a pixel a module.
        if let Some(l) = cert.scene.boxes[0].label.as_mut() {
            l.size = 0.01;
        }
        cert.objects[0].label = cert.scene.boxes[0].label.clone();
        let (small, _) = judge_scene(&cert, &fits, &[], &config());
        assert!(small[0].module_px.is_some_and(|px| px < 1.0));
        assert!(!small[0].label_in_reach());
        assert_eq!(small[0].code_read, Some(false));
        assert!(!small[0].unread() && small[0].first_pass(&billing));
        let rows = [Row {
            index: 0,
            cameras: 1,
            spacing_mm: None,
            cycle_ms: 0.0,
            codes_ms: 0.0,
            error: None,
            phantoms: 0,
            objects: small,
        }];
        let all = &ClassSummary::all(&rows, &billing)[0];
        assert_eq!((all.first_pass, all.unread, all.out_of_reach), (2, 0, 1));
        assert_eq!((all.read, all.read_at_limit), ([0, 1], [0, 0]));
    }

    #[test]
    fn one_parcel_over_two_objects_40_mm_apart_is_a_merged_pair() {
        let cert = two_boxes();
        let billing = Billing::default();
        let (objects, phantoms) = judge_scene(
            &cert,
            &[fit([0.0, 0.0], 640.0, 200.0, 100.0)],
            &[],
            &config(),
        );
        assert_eq!(phantoms, 0);
        assert!(objects.iter().all(|o| o.merged));
        assert!(objects.iter().all(|o| o.silently_wrong(&billing)));
        // Refused as side by side: false refusals, merged all the same.
        let mut refused = fit([0.0, 0.0], 640.0, 200.0, 100.0);
        refused.isolated = false;
        let (objects, _) = judge_scene(&cert, &[refused], &[], &config());
        assert!(objects.iter().all(|o| o.merged && o.false_refusal()));
        assert!(!objects.iter().any(|o| o.silently_wrong(&billing)));
        // Nothing measured: both missing.
        let (objects, phantoms) = judge_scene(&cert, &[], &[], &config());
        assert_eq!(phantoms, 0);
        assert!(objects.iter().all(|o| o.outcome == Outcome::Missing));
    }
}
