//! Scene files for the synthetic camera (docs/design.md §7): TOML, world frame in metres,
//! z up, floor at `floor.z` (0 by default).
//!
//! ```toml
//! seed = 7
//! [floor]
//! z = 0.0
//! color = [120, 120, 120]
//!
//! [[camera]]
//! serial = "840412060746"
//! position = [0.0, 0.0, 1.0]
//! look_at = [0.0, 0.0, 0.0]
//! up = [0.0, 1.0, 0.0]        # optional
//! noise = "d415"              # or "ideal"
//! calibrated = true           # false: starts with the identity 3d-transformation
//! stall_s = 5.0               # optional: frames freeze from 5 s of scene time on
//!
//! [[box]]
//! size = [0.40, 0.30, 0.20]   # length (along x before yaw), width, height
//! center = [0.0, 0.0]         # footprint centre on the floor
//! yaw_deg = 15.0
//! color = [180, 140, 90]
//! label = { kind = "qr", text = "PKG-0001", size = 0.08 }
//!
//! [[cylinder]]
//! radius = 0.10
//! height = 0.25
//! center = [0.3, -0.2]
//!
//! [[tube]]                    # a cylinder lying on the floor
//! radius = 0.05
//! length = 0.60               # along its axis, which points along x turned by yaw_deg
//! center = [0.0, -0.3]        # footprint centre on the floor
//! yaw_deg = -15.0
//!
//! [[bag]]                     # a filled polybag: a pillow over its footprint
//! size = [0.40, 0.28, 0.16]   # length, width, greatest height (without sag)
//! center = [-0.2, 0.1]
//! yaw_deg = 25.0
//! sag = 0.2                   # 0 (full, default) to 0.5: how far the middle of the top sinks
//!
//! [[marker]]                  # a calibration marker printed on the floor
//! family = "tag36h11"
//! id = 0
//! size = 0.16                 # side of the black square, metres
//! center = [0.0, 0.0]
//! yaw_deg = 0.0
//! ```
//!
//! Tubes default to the cylinder color, bags to [215, 215, 222]. A bag's height over
//! its footprint is `size[2] * q(u) q(v) (1 - sag (1 - u^2)(1 - v^2))`, u and v from -1
//! to 1 across its length and width, q(s) = (1 - s^4)^(1/4): flat in the middle,
//! shoulders rounding down to meet the floor upright, lower corners (see [`Bag`]).
//! [`Scene::truths`] gives every object's smallest upright enclosing cuboid.
//!
//! Boxes, cylinders, tubes and bags take a finish, how their surface returns the D415's infrared
//! light: `reflectivity` (0 black to 1, default 1: enough light everywhere) and `gloss`
//! (0 matte, the default, to 1 mirror-like), e.g. `reflectivity = 0.08` for black shrink
//! wrap, `gloss = 0.7` for glossy tape. The synthetic camera's module documentation says
//! how they change depth and color.
//!
//! Defaults: `seed` 0, floor at z = 0 colored [120, 120, 120], `up` world +z unless the
//! camera looks (nearly) straight up or down, then world +y; `noise` "d415";
//! `calibrated` true (the camera exposes its true pose, which a server preloads as its
//! 3d-transformation; false starts with the identity, as a real camera does); box color
//! [180, 140, 90]; cylinder color [70, 110, 160].
//! A label lies centred on the box's top face, its x along the box's length. Its `size`
//! is its width in metres; a QR label is square, a Code 128 label is half as tall as
//! wide. Both carry a white quiet zone.
//!
//! Objects on a timeline: every `[[box]]`, `[[cylinder]]`, `[[tube]]`, `[[bag]]` and
//! `[[marker]]` (and a box's label) may say when it is there, in seconds of scene time
//! (the time since the cameras were made, i.e. since the server started):
//!
//! ```toml
//! [[box]]
//! size = [0.30, 0.20, 0.15]
//! center = [0.0, 0.0]
//! appear_s = 1.0              # absent before (default: there from the start)
//! from = [0.6, 0.0]           # where it appears; it slides in a straight line ...
//! still_s = 2.0               # ... to `center`, where it stands from `still_s` on
//! remove_s = 6.0              # absent from then on (default: never removed)
//! label = { kind = "qr", text = "PKG-2", size = 0.08, appear_s = 3.0 }  # stuck on later
//! ```
//!
//! `from` and `still_s` go together; `still_s` must be after `appear_s`, `remove_s`
//! after both. Yaw does not change while sliding. A label moves with its box and takes
//! only `appear_s` and `remove_s`. Without these fields an object is there, still, all
//! the time: a scene without them renders exactly as before timelines existed.
//!
//! A marker lies flat on the floor (it changes color, not depth), drawn with its
//! family's real pattern (the `markers` crate): the black square `size` wide, the data
//! bits inside it, one white cell around it. Its x axis (the pattern's rows, left to
//! right) points along world x turned by `yaw_deg`, its top towards world y turned
//! likewise, as if printed and laid face up.

use std::path::Path;

use serde::Deserialize;

pub use super::fields::{
    Finish, MAX_COORDINATE_M, MAX_SCENE_TIME_S, MAX_SIZE_M, SceneError, Timeline,
};
use super::fields::{TimelineFile, check_place, coordinates, invalid, positive};
pub use super::kinds::{
    Bag, Cylinder, MAX_LABEL_CHARS, MAX_SAG, ObjectKind, SceneBox, Tube, bag_profile,
};
use super::kinds::{Object, default_box_color};
pub use super::label::{Label, LabelKind};
use crate::camera::Serial;
use crate::intrinsics::Pose;

/// How a scene camera's depth is rendered.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Noise {
    /// As a D415 measures: stereo noise growing with z^2, occlusion shadows, random
    /// dropout, flying pixels, minimum and maximum range.
    D415,
    /// Exact depth at each pixel centre (see the synthetic backend for the definition).
    Ideal,
}

fn default_floor_color() -> [u8; 3] {
    [120, 120, 120]
}
fn default_noise() -> Noise {
    Noise::D415
}

/// The floor plane.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Floor {
    /// Height of the floor, metres.
    #[serde(default)]
    pub z: f64,
    /// Color.
    #[serde(default = "default_floor_color")]
    pub color: [u8; 3],
}

impl Default for Floor {
    fn default() -> Self {
        Self {
            z: 0.0,
            color: default_floor_color(),
        }
    }
}

/// A synthetic D415 in the scene.
#[derive(Debug, Clone, PartialEq)]
pub struct SceneCamera {
    /// Serial number.
    pub serial: Serial,
    /// Position of the depth origin (left imager), world metres.
    pub position: [f64; 3],
    /// A point the optical axis passes through.
    pub look_at: [f64; 3],
    /// World direction that appears upwards in the image; `None` = the default.
    pub up: Option<[f64; 3]>,
    /// Depth rendering.
    pub noise: Noise,
    /// Whether the camera exposes its true pose ([`crate::Camera::true_pose`]).
    pub calibrated: bool,
    /// From this scene time on (seconds) the camera is stuck: every grab returns the
    /// frame of that moment again, its number and capture time included, as a camera
    /// whose driver keeps serving its last frame. `None`: never.
    pub stall_s: Option<f64>,
    /// What its color sensor adds to the color image (default: nothing).
    pub color_sensor: ColorSensor,
}

/// What the color sensor adds to the rendered image: blur, exposure and noise. The
/// default is none of them, the clean image every scene rendered before.
#[derive(Debug, Clone, Copy, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ColorSensor {
    /// Standard deviation of the sensor noise at mid grey (level 128), 8-bit levels; it
    /// grows with the square root of the level (photon noise) over a floor (read noise):
    /// noise * sqrt((level + 16) / 144). 0 (the default) to 64.
    #[serde(default)]
    pub noise: f64,
    /// Standard deviation of a Gaussian blur (focus, lens), pixels. 0 (the default) to 8.
    #[serde(default)]
    pub blur_px: f64,
    /// Gain on the light before the sensor clips at 255: above 1 brighter (white labels
    /// clip), below 1 darker. 1 (the default); from 0.1 to 10.
    #[serde(default = "default_exposure")]
    pub exposure: f64,
}

fn default_exposure() -> f64 {
    1.0
}

impl Default for ColorSensor {
    fn default() -> Self {
        Self {
            noise: 0.0,
            blur_px: 0.0,
            exposure: 1.0,
        }
    }
}

/// Largest color sensor noise, 8-bit levels.
pub const MAX_COLOR_NOISE: f64 = 64.0;
/// Largest color blur, pixels.
pub const MAX_BLUR_PX: f64 = 8.0;
/// Exposure gains allowed.
pub const EXPOSURE_RANGE: std::ops::RangeInclusive<f64> = 0.1..=10.0;

impl ColorSensor {
    /// Whether it adds nothing (the default).
    pub fn is_off(&self) -> bool {
        *self == Self::default()
    }

    fn validate(&self, at: &dyn Fn(&str) -> String) -> Result<(), SceneError> {
        if !(0.0..=MAX_COLOR_NOISE).contains(&self.noise) {
            return Err(invalid(
                at("color_sensor.noise"),
                format!(
                    "must be from 0 to {MAX_COLOR_NOISE} levels, got {}",
                    self.noise
                ),
            ));
        }
        if !(0.0..=MAX_BLUR_PX).contains(&self.blur_px) {
            return Err(invalid(
                at("color_sensor.blur_px"),
                format!(
                    "must be from 0 to {MAX_BLUR_PX} pixels, got {}",
                    self.blur_px
                ),
            ));
        }
        if !EXPOSURE_RANGE.contains(&self.exposure) {
            return Err(invalid(
                at("color_sensor.exposure"),
                format!(
                    "must be from {} to {}, got {}",
                    EXPOSURE_RANGE.start(),
                    EXPOSURE_RANGE.end(),
                    self.exposure
                ),
            ));
        }
        Ok(())
    }
}

/// A calibration marker printed on the floor.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(from = "MarkerFile")]
pub struct SceneMarker {
    /// Family name, e.g. `"tag36h11"` ([`markers::FAMILIES`]).
    pub family: String,
    /// Id within the family.
    pub id: u32,
    /// Side of the black square, metres.
    pub size: f64,
    /// Centre on the floor, (x, y) metres.
    pub center: [f64; 2],
    /// Rotation about world z, degrees, counter-clockwise seen from above.
    pub yaw_deg: f64,
    /// When it is there, and whether it slides in.
    pub timeline: Timeline,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct MarkerFile {
    family: String,
    id: u32,
    size: f64,
    center: [f64; 2],
    #[serde(default)]
    yaw_deg: f64,
    #[serde(flatten)]
    timeline: TimelineFile,
}

impl From<MarkerFile> for SceneMarker {
    fn from(f: MarkerFile) -> Self {
        Self {
            family: f.family,
            id: f.id,
            size: f.size,
            center: f.center,
            yaw_deg: f.yaw_deg,
            timeline: f.timeline.into(),
        }
    }
}

/// A scene: what the synthetic cameras see.
#[derive(Debug, Clone, PartialEq)]
pub struct Scene {
    /// Seed of every random choice (noise, dropout).
    pub seed: u64,
    /// The floor.
    pub floor: Floor,
    /// Cameras.
    pub cameras: Vec<SceneCamera>,
    /// Boxes.
    pub boxes: Vec<SceneBox>,
    /// Cylinders.
    pub cylinders: Vec<Cylinder>,
    /// Tubes lying on the floor.
    pub tubes: Vec<Tube>,
    /// Polybags.
    pub bags: Vec<Bag>,
    /// Calibration markers on the floor.
    pub markers: Vec<SceneMarker>,
}

/// The true extent of an object standing on the floor: its smallest enclosing upright
/// cuboid (what OIML R 129 measures for any shape), from the scene's numbers rather than
/// from any rendering. For a box it is the box itself.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Truth {
    /// What the object is.
    pub kind: ObjectKind,
    /// Its index among the scene's objects of its kind (`box[index]`).
    pub index: usize,
    /// Length, width, height of the enclosing cuboid in metres, length >= width.
    pub size: [f64; 3],
    /// Centre of the cuboid's footprint on the floor, (x, y) metres.
    pub center: [f64; 2],
    /// Direction of the length on the floor, degrees counter-clockwise from world x, in
    /// (-90, 90].
    pub yaw_deg: f64,
    /// The footprint's corners on the floor, (x, y) metres, counter-clockwise seen from
    /// above.
    pub footprint: [[f64; 2]; 4],
    /// Whether the object is itself a cuboid (a box), so a cuboid fits it exactly.
    pub cuboid: bool,
}

impl Truth {
    /// The truth of an object whose enclosing cuboid is `size` (along its own x, y, z)
    /// turned by `yaw_deg` about `center`.
    fn new(kind: ObjectKind, index: usize, size: [f64; 3], center: [f64; 2], yaw_deg: f64) -> Self {
        let (length, width, yaw) = if size[0] >= size[1] {
            (size[0], size[1], yaw_deg)
        } else {
            (size[1], size[0], yaw_deg + 90.0)
        };
        // Into (-90, 90].
        let mut yaw = (yaw + 90.0).rem_euclid(180.0) - 90.0;
        if yaw <= -90.0 {
            yaw += 180.0;
        }
        let (sin, cos) = yaw.to_radians().sin_cos();
        let corner = |a: f64, b: f64| {
            let (x, y) = (a * length / 2.0, b * width / 2.0);
            [center[0] + x * cos - y * sin, center[1] + x * sin + y * cos]
        };
        Self {
            kind,
            index,
            size: [length, width, size[2]],
            center,
            yaw_deg: yaw,
            footprint: [
                corner(-1.0, -1.0),
                corner(1.0, -1.0),
                corner(1.0, 1.0),
                corner(-1.0, 1.0),
            ],
            cuboid: kind == ObjectKind::Box,
        }
    }

    /// Length in millimetres.
    pub fn length_mm(&self) -> f64 {
        self.size[0] * 1e3
    }

    /// Width in millimetres.
    pub fn width_mm(&self) -> f64 {
        self.size[1] * 1e3
    }

    /// Height in millimetres.
    pub fn height_mm(&self) -> f64 {
        self.size[2] * 1e3
    }

    /// Footprint area, square metres.
    pub fn footprint_m2(&self) -> f64 {
        self.size[0] * self.size[1]
    }
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct SceneFile {
    #[serde(default)]
    seed: u64,
    #[serde(default)]
    floor: Floor,
    #[serde(default)]
    camera: Vec<CameraFile>,
    #[serde(default, rename = "box")]
    boxes: Vec<SceneBox>,
    #[serde(default)]
    cylinder: Vec<Cylinder>,
    #[serde(default)]
    tube: Vec<Tube>,
    #[serde(default)]
    bag: Vec<Bag>,
    #[serde(default)]
    marker: Vec<SceneMarker>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct CameraFile {
    serial: String,
    position: [f64; 3],
    look_at: [f64; 3],
    #[serde(default)]
    up: Option<[f64; 3]>,
    #[serde(default = "default_noise")]
    noise: Noise,
    #[serde(default = "default_calibrated")]
    calibrated: bool,
    #[serde(default)]
    stall_s: Option<f64>,
    #[serde(default)]
    color_sensor: ColorSensor,
}

fn default_calibrated() -> bool {
    true
}

fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}
fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}
fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}
fn scale(a: [f64; 3], s: f64) -> [f64; 3] {
    [a[0] * s, a[1] * s, a[2] * s]
}
fn normalized(a: [f64; 3]) -> Option<[f64; 3]> {
    let n = dot(a, a).sqrt();
    (n > 1e-9 && n.is_finite()).then(|| scale(a, 1.0 / n))
}

impl SceneCamera {
    /// The up direction used when `up` is not given.
    fn default_up(forward: [f64; 3]) -> [f64; 3] {
        if forward[2].abs() > 0.99 {
            [0.0, 1.0, 0.0]
        } else {
            [0.0, 0.0, 1.0]
        }
    }

    /// The camera's pose: depth frame (x right, y down, z forward) -> world.
    /// `None` if `look_at` equals `position` or `up` is parallel to the view direction
    /// (a validated scene has neither).
    pub fn pose(&self) -> Option<Pose> {
        let z = normalized(sub(self.look_at, self.position))?;
        let up = self.up.unwrap_or_else(|| Self::default_up(z));
        // y (image down) is minus the part of `up` orthogonal to the view direction.
        let up_orth = sub(up, scale(z, dot(up, z)));
        let y = scale(normalized(up_orth)?, -1.0);
        let x = cross(y, z);
        Some(Pose {
            rotation: [[x[0], y[0], z[0]], [x[1], y[1], z[1]], [x[2], y[2], z[2]]],
            translation: self.position,
        })
    }
}

/// Most cameras in a scene.
pub const MAX_CAMERAS: usize = 16;
/// Most objects (boxes, cylinders, tubes and bags together) in a scene.
pub const MAX_OBJECTS: usize = 256;
/// Most markers in a scene.
pub const MAX_MARKERS: usize = 256;

/// The markers of `markers` there at scene time `t_s`, each where it lies then and without
/// a timeline.
fn markers_at(markers: &[SceneMarker], t_s: f64) -> Vec<SceneMarker> {
    markers
        .iter()
        .filter_map(|m| {
            let mut m = m.clone();
            m.center = m.timeline.position(m.center, t_s)?;
            m.timeline = Timeline::default();
            Some(m)
        })
        .collect()
}

/// The objects of `objects` there at scene time `t_s`, each where it stands then and
/// without a timeline.
fn objects_at<T: Object + Clone>(objects: &[T], t_s: f64) -> Vec<T> {
    objects.iter().filter_map(|o| o.at(t_s)).collect()
}

/// Every object of `objects` as an [`Object`], with its index among them.
fn each<T: Object>(objects: &[T]) -> impl Iterator<Item = (usize, &dyn Object)> {
    objects.iter().map(|o| o as &dyn Object).enumerate()
}

/// toml's error for `text`, at the line of the key it names. serde reports a key that an
/// object's table does not take without the key's place when the table also takes
/// flattened fields (the finish and the timeline), so toml points at the table's header;
/// here such a key is found in its table and pointed at, in toml's own layout.
fn parse_error(text: &str, e: &toml::de::Error) -> String {
    let key = e
        .message()
        .strip_prefix("unknown field `")
        .and_then(|rest| rest.split('`').next());
    let (Some(key), Some(span)) = (key, e.span()) else {
        return e.to_string();
    };
    // The table runs from its header to the next header (or the span's end, if later).
    let start = span.start.min(text.len());
    let body_start = text[start..]
        .find('\n')
        .map_or(text.len(), |n| start + n + 1);
    let next_header = text[body_start..]
        .match_indices('\n')
        .map(|(n, _)| body_start + n + 1)
        .chain([body_start])
        .filter(|&at| text[at..].trim_start_matches([' ', '\t']).starts_with('['))
        .min()
        .unwrap_or(text.len());
    let end = next_header.max(span.end.min(text.len()));
    let table = &text[start..end];
    let Some(at) = table.match_indices(key).map(|(i, _)| start + i).find(|&i| {
        let before = text[..i].trim_end_matches([' ', '\t']);
        let after = text[i + key.len()..].trim_start_matches([' ', '\t']);
        (before.is_empty() || before.ends_with(['\n', '{', ','])) && after.starts_with('=')
    }) else {
        return e.to_string();
    };
    let line_start = text[..at].rfind('\n').map_or(0, |n| n + 1);
    let line_end = text[at..].find('\n').map_or(text.len(), |n| at + n);
    let line = text[..at].matches('\n').count() + 1;
    let column = text[line_start..at].chars().count() + 1;
    let number = line.to_string();
    let gutter = " ".repeat(number.len());
    format!(
        "TOML parse error at line {line}, column {column}\n{gutter} |\n{number} | {}\n{gutter} | {}{}\n{}\n",
        text[line_start..line_end].trim_end_matches('\r'),
        " ".repeat(column - 1),
        "^".repeat(key.chars().count()),
        e.message().trim_end(),
    )
}

impl Scene {
    /// Parses and validates a scene from TOML text.
    pub fn from_toml(text: &str) -> Result<Self, SceneError> {
        let file: SceneFile =
            toml::from_str(text).map_err(|e| SceneError::Parse(parse_error(text, &e)))?;
        let mut cameras = Vec::with_capacity(file.camera.len());
        for (i, c) in file.camera.into_iter().enumerate() {
            let serial = Serial::parse(&c.serial)
                .map_err(|e| invalid(format!("camera[{i}].serial"), e.to_string()))?;
            cameras.push(SceneCamera {
                serial,
                position: c.position,
                look_at: c.look_at,
                up: c.up,
                noise: c.noise,
                calibrated: c.calibrated,
                stall_s: c.stall_s,
                color_sensor: c.color_sensor,
            });
        }
        let scene = Self {
            seed: file.seed,
            floor: file.floor,
            cameras,
            boxes: file.boxes,
            cylinders: file.cylinder,
            tubes: file.tube,
            bags: file.bag,
            markers: file.marker,
        };
        scene.validate()?;
        Ok(scene)
    }

    /// Reads, parses and validates a scene file.
    pub fn load(path: &Path) -> Result<Self, SceneError> {
        let text = std::fs::read_to_string(path).map_err(|source| SceneError::Io {
            path: path.display().to_string(),
            source,
        })?;
        Self::from_toml(&text)
    }

    /// Checks every rule a scene file must follow.
    pub fn validate(&self) -> Result<(), SceneError> {
        coordinates("floor.z", &[self.floor.z])?;
        if self.cameras.len() > MAX_CAMERAS {
            return Err(invalid(
                "camera",
                format!("at most {MAX_CAMERAS} cameras, got {}", self.cameras.len()),
            ));
        }
        let objects = self.objects().count();
        if objects > MAX_OBJECTS {
            return Err(invalid(
                "box, cylinder, tube, bag",
                format!(
                    "at most {MAX_OBJECTS} boxes, cylinders, tubes and bags together, got {objects}"
                ),
            ));
        }
        for (i, c) in self.cameras.iter().enumerate() {
            let at = |f: &str| format!("camera[{i}].{f}");
            coordinates(&at("position"), &c.position)?;
            coordinates(&at("look_at"), &c.look_at)?;
            if let Some(up) = c.up {
                coordinates(&at("up"), &up)?;
            }
            if normalized(sub(c.look_at, c.position)).is_none() {
                return Err(invalid(at("look_at"), "must differ from position"));
            }
            if c.pose().is_none() {
                return Err(invalid(
                    at("up"),
                    "must not be parallel to the view direction",
                ));
            }
            if self.cameras[..i].iter().any(|o| o.serial == c.serial) {
                return Err(invalid(
                    at("serial"),
                    format!("{} is used by another camera", c.serial),
                ));
            }
            if let Some(stall) = c.stall_s
                && !(stall.is_finite() && stall >= 0.0)
            {
                return Err(invalid(
                    at("stall_s"),
                    format!("must be a time of 0 s or later, got {stall}"),
                ));
            }
            c.color_sensor.validate(&at)?;
        }
        for (i, o) in self.objects() {
            o.validate(&|f: &str| format!("{}[{i}].{f}", o.kind().name()))?;
        }
        if self.markers.len() > MAX_MARKERS {
            return Err(invalid(
                "marker",
                format!("at most {MAX_MARKERS} markers, got {}", self.markers.len()),
            ));
        }
        for (i, m) in self.markers.iter().enumerate() {
            let at = |f: &str| format!("marker[{i}].{f}");
            let family: markers::Family = m
                .family
                .parse()
                .map_err(|e: markers::UnknownFamily| invalid(at("family"), e.to_string()))?;
            if m.id >= family.ids() {
                return Err(invalid(
                    at("id"),
                    format!("{family} has ids 0 to {}, got {}", family.ids() - 1, m.id),
                ));
            }
            positive(&at("size"), &[m.size])?;
            check_place(&at, &m.center, Some(m.yaw_deg))?;
            m.timeline.validate(&at)?;
        }
        Ok(())
    }

    /// Whether any object (or label) has a timeline: without one the scene is the same
    /// at every moment.
    pub fn is_timed(&self) -> bool {
        self.objects().any(|(_, o)| {
            !o.timeline().is_always() || o.label().is_some_and(|l| !l.timeline().is_always())
        }) || self.markers.iter().any(|m| !m.timeline.is_always())
    }

    /// The scene as it stands at scene time `t_s`: the objects there then, each where it
    /// is then, without timelines (labels not yet stuck on, or peeled off, left out).
    pub fn at(&self, t_s: f64) -> Self {
        let mut scene = self.clone();
        scene.boxes = objects_at(&self.boxes, t_s);
        scene.cylinders = objects_at(&self.cylinders, t_s);
        scene.tubes = objects_at(&self.tubes, t_s);
        scene.bags = objects_at(&self.bags, t_s);
        scene.markers = markers_at(&self.markers, t_s);
        scene
    }

    /// The true enclosing cuboid of every object standing on the floor (boxes, then
    /// cylinders, tubes and bags, each in file order; markers are printed on the floor and are no
    /// objects), where each stands at rest (its `center`); `scene.at(t_s).truths()`
    /// gives those of one moment.
    pub fn truths(&self) -> Vec<Truth> {
        self.objects()
            .map(|(i, o)| {
                let ([length, width], yaw_deg) = o.footprint();
                Truth::new(
                    o.kind(),
                    i,
                    [length, width, o.height()],
                    o.center(),
                    yaw_deg,
                )
            })
            .collect()
    }

    /// Every object with its index among those of its kind: boxes, then cylinders, tubes
    /// and bags, each in file order (the order of [`Scene::truths`]). A kind added is
    /// listed here.
    pub(crate) fn objects(&self) -> impl Iterator<Item = (usize, &dyn Object)> {
        each(&self.boxes)
            .chain(each(&self.cylinders))
            .chain(each(&self.tubes))
            .chain(each(&self.bags))
    }

    /// The camera with this serial.
    pub fn camera(&self, serial: &Serial) -> Option<&SceneCamera> {
        self.cameras.iter().find(|c| &c.serial == serial)
    }

    /// The built-in default scene: one 400 x 300 x 200 mm box, yawed 15 degrees and
    /// carrying a QR label, under one calibrated camera 1.0 m above the floor looking
    /// straight down.
    pub fn default_single() -> Self {
        Self {
            seed: 7,
            floor: Floor::default(),
            cameras: vec![SceneCamera {
                serial: Serial::from_digits(*b"840412060746"),
                position: [0.0, 0.0, 1.0],
                look_at: [0.0, 0.0, 0.0],
                up: Some([0.0, 1.0, 0.0]),
                noise: Noise::D415,
                calibrated: true,
                stall_s: None,
                color_sensor: ColorSensor::default(),
            }],
            boxes: vec![Self::default_box()],
            cylinders: Vec::new(),
            tubes: Vec::new(),
            bags: Vec::new(),
            markers: Vec::new(),
        }
    }

    /// The built-in demo scene: the default box seen by two calibrated cameras from
    /// opposite sides, 1.0 m and 1.2 m above the floor, tilted towards the box.
    pub fn default_demo() -> Self {
        let camera = |serial: &[u8; 12], position: [f64; 3]| SceneCamera {
            serial: Serial::from_digits(*serial),
            position,
            look_at: [0.0, 0.0, 0.1],
            up: None,
            noise: Noise::D415,
            calibrated: true,
            stall_s: None,
            color_sensor: ColorSensor::default(),
        };
        Self {
            seed: 7,
            floor: Floor::default(),
            cameras: vec![
                camera(b"840412060746", [0.45, -0.25, 1.0]),
                camera(b"840412060757", [-0.40, 0.30, 1.2]),
            ],
            boxes: vec![Self::default_box()],
            cylinders: Vec::new(),
            tubes: Vec::new(),
            bags: Vec::new(),
            markers: Vec::new(),
        }
    }

    fn default_box() -> SceneBox {
        SceneBox {
            size: [0.40, 0.30, 0.20],
            center: [0.0, 0.0],
            yaw_deg: 15.0,
            color: default_box_color(),
            label: Some(Label {
                kind: LabelKind::Qr,
                text: "PKG-0001".to_owned(),
                size: 0.08,
                appear_s: None,
                remove_s: None,
            }),
            finish: Finish::default(),
            timeline: Timeline::default(),
        }
    }
}
