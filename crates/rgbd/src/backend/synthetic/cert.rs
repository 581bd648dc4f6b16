//! The certification set: seeded random stations and parcels built the way a type test
//! of a dimensioner (OIML R 129 style) would build them, and, from the scene alone, what
//! a certified system is expected to accept. Scene `index` of seed `seed` is always the
//! same scene and depends on nothing but the two numbers, so a seed kept back is a set
//! that no one has seen.
//!
//! A station has 1 to 4 calibrated D415s (noise `"d415"`), each 1.0 to 2.2 m above the
//! floor, tilted 0 to 45 degrees from straight down towards a point near the middle of
//! the table, from any side, its image turned at random about its axis. The color
//! sensors blur about 1 pixel (0.8 to 1.2), as real lenses do.
//!
//! On the table stands one object, or a group of 2 to 4 in a row with one spacing
//! between neighbours (0, 10, 20, 30, 50, 80 or 120 mm between their enclosing
//! footprints along the row): boxes, standing cylinders, lying tubes and polybags, flat
//! (20 to 50 mm high) or tall, 50 mm (10 d at d = 5) long and wide up to the largest the
//! cameras' view allows (drawn large and made smaller until the group is in view), turned
//! at random, with a surface of cardboard, white, black (reflectivity 0.05 to 0.5),
//! glossy (gloss 0.4 to 1) or a bright colour. Every box carries a label of a symbology
//! from [`SYMBOLOGIES`] and a random size that fits its top face; cylinders, tubes and
//! bags carry none (the synthetic scene puts labels on boxes only).
//!
//! [`judge`] decides, from any scene, what a certified system accepts: an object isolated
//! by [`MIN_SPACING_M`] or more from every other, wholly inside the view of at least one
//! camera and every point of its top seen by some camera past every other object,
//! returning depth, and a division or more above the smallest measurable object on each
//! axis ([`MIN_M`]).

use super::d415;
use super::kinds::Object;
use super::lane::{Draw, serial_digits};
use super::raycast::{Stage, V3, World};
use super::render::{SIGNAL_FULL, mix64};
use super::scene::{
    Bag, ColorSensor, Cylinder, Finish, Floor, Label, LabelKind, Noise, ObjectKind, Scene,
    SceneBox, SceneCamera, Timeline, Truth, Tube,
};
use crate::camera::Serial;
use crate::intrinsics::Pose;

/// The symbologies the set's labels are drawn from: every one a scene's label takes (the
/// symbologies of shipping labels). Since 2026-12-02; before, QR and Code 128 only, so a
/// seed's scenes from before differ from the first labelled box on.
pub const SYMBOLOGIES: &[LabelKind] = &LabelKind::ALL;

/// The spacings of a group, millimetres between neighbouring footprints along its row.
pub const SPACINGS_MM: [f64; 7] = [0.0, 10.0, 20.0, 30.0, 50.0, 80.0, 120.0];

/// The least gap between an object's footprint and every other one for a certified
/// system to measure it as a parcel of its own (Datalogic DM3610, Hikrobot: 20 mm).
pub const MIN_SPACING_M: f64 = 0.02;

/// The division the set is judged at (d = 5 mm), metres.
pub const DIVISION_M: f64 = 0.005;

/// The smallest measurable length, width and height (10 d, 10 d and 2 d, as certified
/// dimensioners state them), metres. An instrument's minimum applies to what it measures
/// (OIML R 129): an object that reads below it gets no number, and one within a division
/// of it may read below, so a certified system is expected to measure only objects a
/// division or more above it.
pub const MIN_M: [f64; 3] = [0.05, 0.05, 0.01];

/// The number of scenes `bench accuracy --set cert` measures by default.
pub const CERT_SET_SIZE: usize = 500;

/// Lowest and highest camera above the floor, metres.
pub const CAMERA_Z_M: [f64; 2] = [1.0, 2.2];
/// Largest tilt of a camera from straight down, degrees.
pub const MAX_TILT_DEG: f64 = 45.0;
/// Blur of the color sensors, pixels.
pub const BLUR_PX: [f64; 2] = [0.8, 1.2];
/// Half the side of the square on the table the objects stay in, metres (inside the
/// region `measure --prepare` keeps, 1 m either side of the origin).
const TABLE_HALF_M: f64 = 0.95;
/// Pixels an object's corners keep from the image's edges to count as in view.
const EDGE_PX: f64 = 1.0;
/// Depth image the view is judged in (the D415's default 1280x720).
const DEPTH_SIZE: [u32; 2] = [1280, 720];
/// Largest side of the cells of an object's top whose centres are judged in view, metres
/// (two divisions: a strip of the outline narrower than one division goes unjudged).
const TOP_STEP_M: f64 = 0.01;
/// Most cells along an object's length or width (a 1.2 m side is judged every 30 mm).
const TOP_CELLS: usize = 40;

/// What an object's surface is made of.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Surface {
    /// Matte browns and greys.
    Cardboard,
    /// Matte white.
    White,
    /// Black: dark in color, reflectivity 0.05 to 0.5 in the infrared.
    Black,
    /// A cardboard colour with gloss 0.4 to 1.
    Glossy,
    /// A matte, bright, saturated colour.
    Coloured,
}

impl Surface {
    /// Every surface.
    pub const ALL: [Self; 5] = [
        Self::Cardboard,
        Self::White,
        Self::Black,
        Self::Glossy,
        Self::Coloured,
    ];

    /// Its name in reports.
    pub fn name(self) -> &'static str {
        match self {
            Self::Cardboard => "cardboard",
            Self::White => "white",
            Self::Black => "black",
            Self::Glossy => "glossy",
            Self::Coloured => "coloured",
        }
    }
}

/// One object of a scene: its truth, how it was made, and what a certified system would
/// make of it.
#[derive(Debug, Clone, PartialEq)]
pub struct CertObject {
    /// Its smallest enclosing upright cuboid.
    pub truth: Truth,
    /// Its surface.
    pub surface: Surface,
    /// Whether it is flat (20 to 50 mm high).
    pub flat: bool,
    /// Its label (boxes only).
    pub label: Option<Label>,
    /// What [`judge`] says.
    pub judged: Judged,
}

impl CertObject {
    /// Whether a certified system measures it ([`Judged::accepted`]).
    pub fn accepted(&self) -> bool {
        self.judged.accepted()
    }
}

/// One scene of the set.
#[derive(Debug, Clone, PartialEq)]
pub struct CertScene {
    /// Its index in the set.
    pub index: usize,
    /// The scene.
    pub scene: Scene,
    /// Its objects, in the order of [`Scene::truths`].
    pub objects: Vec<CertObject>,
    /// The spacing its group was built with, mm; `None` for one object alone.
    pub spacing_mm: Option<f64>,
}

/// What a certified system would make of one object of a scene.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Judged {
    /// The gap from its enclosing footprint to the nearest other object's, metres (0 when
    /// they touch or overlap); `None` when it stands alone.
    pub gap_m: Option<f64>,
    /// Every corner of its enclosing cuboid lies inside the depth image of at least one
    /// camera, in front of it and beyond its minimum range, each point of its top is in
    /// some camera's depth image with no other object between (for a bag, not itself
    /// either), and so is a point a division past each edge ([`judge`] says which
    /// points).
    pub in_view: bool,
    /// Its top returns depth everywhere to a camera that has it in view: the light coming
    /// back from the top's centre (reflectivity x cos(incidence) / distance^2) is at
    /// least what the D415 needs to lose no pixel.
    pub returns_depth: bool,
    /// Its length, width and height are each at least [`MIN_M`] plus one division
    /// ([`DIVISION_M`]).
    pub measurable: bool,
}

impl Judged {
    /// Whether it is isolated: alone, or [`MIN_SPACING_M`] or more from every other.
    pub fn isolated(&self) -> bool {
        self.gap_m.is_none_or(|g| g >= MIN_SPACING_M - 1e-9)
    }

    /// Isolated, in view, returning depth and measurable: a parcel a certified system
    /// measures.
    pub fn accepted(&self) -> bool {
        self.isolated() && self.in_view && self.returns_depth && self.measurable
    }
}

/// The first `count` scenes of the set of `seed`.
pub fn cert_set(seed: u64, count: usize) -> Vec<CertScene> {
    (0..count).map(|i| cert_scene(seed, i)).collect()
}

/// A camera as the judge looks through it: its pose, and its position for the ray
/// caster.
struct Eye {
    pose: Pose,
    from: V3,
    /// The depth stream's intrinsics at [`DEPTH_SIZE`].
    k: crate::Intrinsics,
    /// The depth range, metres: the minimum range at `k`, the maximum.
    range: (f64, f64),
}

impl Eye {
    /// `None` without a pose.
    fn of(c: &SceneCamera) -> Option<Self> {
        let k = d415::depth_intrinsics(DEPTH_SIZE[0], DEPTH_SIZE[1]);
        Some(Self {
            pose: c.pose()?,
            from: c.position.map(|v| v as f32).into(),
            range: (
                f64::from(d415::min_range_m(k.fx)),
                f64::from(d415::MAX_RANGE_M),
            ),
            k,
        })
    }

    /// Where it sees world point `p` in its depth image (pixels) and how far in front of
    /// it (metres along its axis).
    fn project(&self, p: [f64; 3]) -> Option<([f64; 2], f64)> {
        let d = [0, 1, 2].map(|i| p[i] - self.pose.translation[i]);
        let r = self.pose.rotation;
        let q = [0, 1, 2].map(|j| r[0][j] * d[0] + r[1][j] * d[1] + r[2][j] * d[2]);
        let k = &self.k;
        if q[2] <= 0.0 {
            return None;
        }
        let uv = [
            f64::from(k.fx) * q[0] / q[2] + f64::from(k.ppx),
            f64::from(k.fy) * q[1] / q[2] + f64::from(k.ppy),
        ];
        Some((uv, q[2]))
    }

    /// Whether it has world point `p` in its depth image, [`EDGE_PX`] or more from the
    /// image's edges, in front of it beyond its minimum range and within its greatest.
    fn holds(&self, p: [f64; 3]) -> bool {
        let (near, far) = self.range;
        let (w, h) = (f64::from(DEPTH_SIZE[0]), f64::from(DEPTH_SIZE[1]));
        self.project(p).is_some_and(|(uv, z)| {
            z > near
                && z < far
                && (EDGE_PX..w - EDGE_PX).contains(&uv[0])
                && (EDGE_PX..h - EDGE_PX).contains(&uv[1])
        })
    }

    /// Whether it has every corner of `t`'s enclosing cuboid in its depth image.
    fn sees_whole(&self, t: &Truth) -> bool {
        t.footprint
            .iter()
            .flat_map(|f| [[f[0], f[1], 0.0], [f[0], f[1], t.size[2]]])
            .all(|p| self.holds(p))
    }
}

/// The scene's cameras that have a pose (every camera of a valid scene).
fn eyes(scene: &Scene) -> Vec<Eye> {
    scene.cameras.iter().filter_map(Eye::of).collect()
}

/// Whether each point of the top of the object `t` describes, primitive `index` of
/// `world`, is seen by one of `eyes`: in its depth image ([`Eye::holds`]) with no other
/// primitive on the segment from the camera to it. The points are the centres of a grid
/// of cells over its enclosing footprint, at most [`TOP_STEP_M`] a side (at most
/// [`TOP_CELLS`] along a side of the footprint); each is where a ray straight down first
/// meets the object (a box's or a cylinder's lid, a tube's or a bag's upper surface out
/// to its outline), and a cell the object does not stand over has none.
///
/// A soft object (a bag) also hides its own top: where its sides come down to the floor
/// follows from nothing else a camera sees of it, as a box's edges follow from its lid, a
/// cylinder's from its rim and a tube's from its circle. Its point counts as seen when a
/// point of its top at most a division ([`DIVISION_M`]) further in towards its centre is:
/// a camera above never sees the last steep millimetres of a bag's side, and what it
/// misses of them is less than a division of its length or width.
fn top_seen(eyes: &[Eye], world: &World, index: usize, t: &Truth) -> bool {
    let soft = t.kind == ObjectKind::Bag;
    let hiders = || world.all().filter(move |j| *j != index || soft);
    // `None` where the object does not stand over (x, y).
    let seen = |x: f64, y: f64| {
        world.top_of(index, x as f32, y as f32).map(|p| {
            let at = [p.x, p.y, p.z].map(f64::from);
            eyes.iter()
                .any(|e| e.holds(at) && !world.occluded(&e.from, &p, hiders()))
        })
    };
    // The points further in that may stand for a bag's: a fifth of a division apart.
    const STEPS: u32 = 5;
    let (s, c) = t.yaw_deg.to_radians().sin_cos();
    let cells = |side: f64| ((side / TOP_STEP_M).ceil() as usize).clamp(1, TOP_CELLS);
    let (nl, nw) = (cells(t.size[0]), cells(t.size[1]));
    (0..nl).all(|a| {
        let along = t.size[0] * ((a as f64 + 0.5) / nl as f64 - 0.5);
        (0..nw).all(|b| {
            let across = t.size[1] * ((b as f64 + 0.5) / nw as f64 - 0.5);
            let x = t.center[0] + along * c - across * s;
            let y = t.center[1] + along * s + across * c;
            seen(x, y).is_none_or(|seen_here| {
                let r = along.hypot(across);
                seen_here
                    || (soft
                        && r > 0.0
                        && (1..=STEPS).any(|k| {
                            let f = 1.0 - DIVISION_M * f64::from(k) / f64::from(STEPS) / r;
                            let (xi, yi) = (
                                t.center[0] + (x - t.center[0]) * f,
                                t.center[1] + (y - t.center[1]) * f,
                            );
                            seen(xi, yi) == Some(true)
                        }))
            })
        })
    })
}

/// Whether some camera sees past each edge of the object `t` describes, primitive
/// `index` of `world`: a point a division ([`DIVISION_M`]) beyond each corner and the
/// middle of each side of its enclosing footprint, outwards from its centre, at its top's
/// height, in a camera's depth image with no other primitive on the segment from the
/// camera to it. A lid whose edge a neighbour's wall meets in the image (the neighbour
/// hides what lies just past it) could go on under the wall: where the parcel ends is not
/// seen.
fn past_edges_seen(eyes: &[Eye], world: &World, index: usize, t: &Truth) -> bool {
    let others = || world.all().filter(move |j| *j != index);
    let f = &t.footprint;
    (0..4)
        .flat_map(|k| {
            let (p, q) = (f[k], f[(k + 1) % 4]);
            [p, [(p[0] + q[0]) / 2.0, (p[1] + q[1]) / 2.0]]
        })
        .all(|at| {
            let away = [at[0] - t.center[0], at[1] - t.center[1]];
            let n = away[0].hypot(away[1]).max(1e-9);
            let probe = [
                at[0] + away[0] / n * DIVISION_M,
                at[1] + away[1] / n * DIVISION_M,
                t.size[2],
            ];
            let p = V3::new(probe[0] as f32, probe[1] as f32, probe[2] as f32);
            eyes.iter()
                .any(|e| e.holds(probe) && !world.occluded(&e.from, &p, others()))
        })
}

/// The finish of the object `t` describes.
fn finish_of(scene: &Scene, t: &Truth) -> Finish {
    scene
        .objects()
        .find(|(i, o)| o.kind() == t.kind && *i == t.index)
        .map(|(_, o)| *o.finish())
        .expect("every truth is of an object of the scene")
}

/// Gap between two convex footprints (corners in order around each), metres; 0 when they
/// touch or overlap.
pub fn footprint_gap(a: &[[f64; 2]; 4], b: &[[f64; 2]; 4]) -> f64 {
    separation(a, b).max(0.0)
}

/// The gap between two convex footprints when they are apart; when they overlap, minus
/// how far they overlap along the axis that separates them best.
fn separation(a: &[[f64; 2]; 4], b: &[[f64; 2]; 4]) -> f64 {
    // Separating axes: the edges' normals of both.
    let mut best = f64::NEG_INFINITY;
    for poly in [a, b] {
        for i in 0..4 {
            let (p, q) = (poly[i], poly[(i + 1) % 4]);
            let len = (q[0] - p[0]).hypot(q[1] - p[1]).max(1e-12);
            let n = [(q[1] - p[1]) / len, (p[0] - q[0]) / len];
            let along = |c: &[f64; 2]| c[0] * n[0] + c[1] * n[1];
            let range = |r: &[[f64; 2]; 4]| {
                r.iter()
                    .map(along)
                    .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), v| {
                        (lo.min(v), hi.max(v))
                    })
            };
            let ((a0, a1), (b0, b1)) = (range(a), range(b));
            best = best.max((b0 - a1).max(a0 - b1));
        }
    }
    if best <= 0.0 {
        return best;
    }
    let to_segment = |p: [f64; 2], s: [f64; 2], e: [f64; 2]| {
        let d = [e[0] - s[0], e[1] - s[1]];
        let len2 = (d[0] * d[0] + d[1] * d[1]).max(1e-18);
        let t = (((p[0] - s[0]) * d[0] + (p[1] - s[1]) * d[1]) / len2).clamp(0.0, 1.0);
        (p[0] - s[0] - t * d[0]).hypot(p[1] - s[1] - t * d[1])
    };
    let mut best = f64::INFINITY;
    for (from, to) in [(a, b), (b, a)] {
        for p in from {
            for i in 0..4 {
                best = best.min(to_segment(*p, to[i], to[(i + 1) % 4]));
            }
        }
    }
    best
}

/// What a certified system would make of each object of `scene`, in the order of
/// [`Scene::truths`] ([`Judged`] says what each part means).
///
/// In view asks what the cameras see, not only where they look: the object's enclosing
/// cuboid wholly inside one camera's depth image (its corners), and every point of its
/// top seen by some camera, inside its depth image with the segment from the camera to
/// the point passing through no other object. The points are the centres of 10 mm cells
/// over its footprint (40 along a side at most), each on the surface a ray straight down
/// meets first: a box's or a cylinder's lid, a tube's or a bag's upper surface out to its
/// outline. A low object that a taller neighbour hides from the only camera looking at it
/// is not in view, nor is one whose top is partly hidden from every camera, nor one past
/// whose edges no camera sees ([`past_edges_seen`]): a dimensioner cannot measure what it
/// does not see. A rigid object is not counted as hiding its own top (a tube's far flank
/// from a tilted camera); a bag is ([`top_seen`]). A camera's position stands for both
/// its imagers, and every object stands where the scene puts it, whatever its timeline.
///
/// # Panics
///
/// If `scene` is not valid ([`Scene::validate`]).
pub fn judge(scene: &Scene) -> Vec<Judged> {
    let truths = scene.truths();
    // The objects alone: labels do not change what hides what.
    let mut bare = scene.clone();
    for b in &mut bare.boxes {
        b.label = None;
    }
    let world = Stage::new(&bare)
        .expect("the judge is given a valid scene")
        .every_object();
    let eyes = eyes(scene);
    truths
        .iter()
        .enumerate()
        .map(|(i, t)| {
            let gap_m = truths
                .iter()
                .enumerate()
                .filter(|(j, _)| *j != i)
                .map(|(_, o)| footprint_gap(&t.footprint, &o.footprint))
                .reduce(f64::min);
            let seeing: Vec<&Eye> = eyes.iter().filter(|e| e.sees_whole(t)).collect();
            let reflectivity = finish_of(scene, t).reflectivity;
            let top = [t.center[0], t.center[1], t.size[2]];
            let returns_depth = seeing.iter().any(|e| {
                let d = [0, 1, 2].map(|k| e.pose.translation[k] - top[k]);
                let distance = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
                let signal = reflectivity * (d[2] / distance).max(0.0) / (distance * distance);
                reflectivity >= 1.0 || signal >= f64::from(SIGNAL_FULL)
            });
            let lwh = [t.length_mm(), t.width_mm(), t.height_mm()];
            let measurable = (0..3).all(|k| lwh[k] >= (MIN_M[k] + DIVISION_M) * 1e3 - 1e-9);
            Judged {
                gap_m,
                in_view: !seeing.is_empty()
                    && top_seen(&eyes, &world, i, t)
                    && past_edges_seen(&eyes, &world, i, t),
                returns_depth,
                measurable,
            }
        })
        .collect()
}

/// The station: 1 to 4 cameras around a point near the middle of the table.
fn station(draw: &mut Draw) -> (Vec<SceneCamera>, [f64; 2]) {
    let count = 1 + (draw.next() % 4) as usize;
    let middle = [draw.uniform(-0.1, 0.1), draw.uniform(-0.1, 0.1)];
    let azimuth = draw.uniform(0.0, 360.0);
    let cameras = (0..count)
        .map(|k| {
            let z = draw.uniform(CAMERA_Z_M[0], CAMERA_Z_M[1]);
            let tilt = draw.uniform(0.0, MAX_TILT_DEG).to_radians();
            let turn = (azimuth + 360.0 * k as f64 / count as f64 + draw.uniform(-25.0, 25.0))
                .to_radians();
            let look = [
                middle[0] + draw.uniform(-0.1, 0.1),
                middle[1] + draw.uniform(-0.1, 0.1),
            ];
            let out = z * tilt.tan();
            let roll = draw.uniform(0.0, 360.0).to_radians();
            SceneCamera {
                serial: Serial::from_digits(serial_digits(840_412_062_000 + k as u64)),
                position: [look[0] + out * turn.cos(), look[1] + out * turn.sin(), z],
                look_at: [look[0], look[1], 0.0],
                // Horizontal, so never parallel to a view at most 45 degrees from
                // straight down.
                up: Some([roll.cos(), roll.sin(), 0.0]),
                noise: Noise::D415,
                calibrated: true,
                stall_s: None,
                color_sensor: ColorSensor::default(),
            }
        })
        .collect();
    (cameras, middle)
}

/// An object before it is placed: standing at the origin.
#[derive(Debug, Clone)]
enum Piece {
    Box(SceneBox),
    Cylinder(Cylinder),
    Tube(Tube),
    Bag(Bag),
}

impl Piece {
    /// The object.
    fn object(&self) -> &dyn Object {
        match self {
            Self::Box(b) => b,
            Self::Cylinder(c) => c,
            Self::Tube(t) => t,
            Self::Bag(b) => b,
        }
    }

    /// Length and width of its enclosing footprint and the yaw of the length, degrees.
    fn footprint(&self) -> (f64, f64, f64) {
        let ([l, w], yaw) = self.object().footprint();
        (l, w, yaw)
    }

    /// Its extent along and across a row turned `row_deg`, metres.
    fn extent(&self, row_deg: f64) -> (f64, f64) {
        let (l, w, yaw) = self.footprint();
        let (s, c) = (yaw - row_deg).to_radians().sin_cos();
        (l * c.abs() + w * s.abs(), l * s.abs() + w * c.abs())
    }

    /// Its enclosing footprint's corners, in order around it, standing at `at`.
    fn corners(&self, at: [f64; 2]) -> [[f64; 2]; 4] {
        let (l, w, yaw) = self.footprint();
        let (s, c) = yaw.to_radians().sin_cos();
        [[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]].map(|[a, b]: [f64; 2]| {
            let (x, y) = (a * l / 2.0, b * w / 2.0);
            [at[0] + x * c - y * s, at[1] + x * s + y * c]
        })
    }

    fn place(&mut self, at: [f64; 2]) {
        let object: &mut dyn Object = match self {
            Self::Box(b) => b,
            Self::Cylinder(c) => c,
            Self::Tube(t) => t,
            Self::Bag(b) => b,
        };
        *object.place_mut().0 = at;
    }
}

const ALNUM: &[u8] = b"0123456789ABCDEFGHIJKLMNOPQRSTUVWXYZ";

/// `n` random digits and capitals.
fn alnum(draw: &mut Draw, n: usize) -> String {
    (0..n)
        .map(|_| char::from(ALNUM[(draw.next() % ALNUM.len() as u64) as usize]))
        .collect()
}

/// A shipping label's text for symbology `kind`, unique in its scene by `k`.
fn label_text(draw: &mut Draw, kind: LabelKind, k: usize) -> String {
    match kind {
        // A tracking number: 18 characters, as a carrier's.
        LabelKind::Code128 => format!("1Z{k}{}", alnum(draw, 15)),
        // A URL-like reference of 20 to 40 characters.
        LabelKind::Qr | LabelKind::DataMatrix | LabelKind::Pdf417 => {
            let n = 14 + (draw.next() % 21) as usize;
            format!("PKG-{k}-{}", alnum(draw, n))
        }
        // A GTIN: 12 or 11 random digits and the GS1 check digit.
        LabelKind::Ean13 | LabelKind::Upca => {
            let n = if kind == LabelKind::Ean13 { 12 } else { 11 };
            let digits: Vec<u64> = (0..n).map(|_| draw.next() % 10).collect();
            let sum: u64 = digits
                .iter()
                .rev()
                .enumerate()
                .map(|(i, d)| if i % 2 == 0 { 3 * d } else { *d })
                .sum();
            digits
                .iter()
                .chain([&((10 - sum % 10) % 10)])
                .map(u64::to_string)
                .collect()
        }
    }
}

/// A label of a random symbology and size on a box top `length` x `width` (metres).
fn label(draw: &mut Draw, k: usize, length: f64, width: f64) -> Label {
    let kind = SYMBOLOGIES[(draw.next() % SYMBOLOGIES.len() as u64) as usize];
    let text = label_text(draw, kind, k);
    let mut label = Label {
        kind,
        text,
        size: 1.0,
        appear_s: None,
        remove_s: None,
    };
    // Extent per metre of size, along the box's length and width.
    let (lx, ly) = label.extent_m();
    let wanted = match kind {
        LabelKind::Qr | LabelKind::DataMatrix => draw.uniform(0.03, 0.10),
        LabelKind::Code128 | LabelKind::Pdf417 => draw.uniform(0.06, 0.20),
        // EAN-13 and UPC-A at 80 % to 200 % of their nominal 37 mm.
        LabelKind::Ean13 | LabelKind::Upca => draw.uniform(0.03, 0.075),
    };
    label.size = wanted.min(0.9 * length / lx).min(0.9 * width / ly);
    label
}

/// Surface, color and finish drawn for one object.
fn surface(draw: &mut Draw) -> (Surface, [u8; 3], Finish) {
    let surface = Surface::ALL[(draw.next() % Surface::ALL.len() as u64) as usize];
    let mut finish = Finish::default();
    let color = match surface {
        Surface::Cardboard => draw.cardboard(),
        Surface::White => {
            let v = draw.uniform(225.0, 250.0) as u8;
            [v, v, v]
        }
        Surface::Black => {
            finish.reflectivity = draw.uniform(0.05, 0.5);
            let v = draw.uniform(15.0, 40.0) as u8;
            [v, v, v.saturating_add(3)]
        }
        Surface::Glossy => {
            finish.gloss = draw.uniform(0.4, 1.0);
            draw.cardboard()
        }
        Surface::Coloured => [
            [200, 40, 40],
            [40, 90, 200],
            [40, 160, 70],
            [230, 200, 40],
            [230, 120, 30],
        ][(draw.next() % 5) as usize],
    };
    (surface, color, finish)
}

/// One object standing at the origin, its length and width at most `largest`, its height
/// at most `tallest` (metres); with its surface and whether it is flat.
fn piece(draw: &mut Draw, k: usize, largest: f64, tallest: f64) -> (Piece, Surface, bool) {
    const SMALLEST: f64 = 0.05;
    let largest = largest.max(SMALLEST + 0.01);
    let flat = draw.uniform(0.0, 1.0) < 0.3;
    let mut height = if flat {
        draw.uniform(0.02, 0.05)
    } else {
        draw.uniform(0.05, tallest.max(0.06))
    };
    let yaw_deg = draw.uniform(-90.0, 90.0);
    let (surface, color, finish) = surface(draw);
    let shape = draw.uniform(0.0, 1.0);
    let timeline = Timeline::default();
    let piece = if shape < 0.4 {
        let length = draw.uniform(SMALLEST, largest);
        let width = draw.uniform(SMALLEST, length);
        Piece::Box(SceneBox {
            size: [length, width, height],
            center: [0.0, 0.0],
            yaw_deg,
            color,
            label: Some(label(draw, k, length, width)),
            finish,
            timeline,
        })
    } else if shape < 0.6 {
        Piece::Cylinder(Cylinder {
            radius: draw.uniform(SMALLEST, largest.min(0.4)) / 2.0,
            height,
            center: [0.0, 0.0],
            color,
            finish,
            timeline,
        })
    } else if shape < 0.8 {
        // A tube is as high as it is wide: at least 10 d, never flat.
        let diameter = draw.uniform(SMALLEST, largest.min(0.2));
        height = diameter;
        Piece::Tube(Tube {
            radius: diameter / 2.0,
            length: draw.uniform((2.0 * diameter).max(0.15), largest.max(0.16)),
            center: [0.0, 0.0],
            yaw_deg,
            color,
            finish,
            timeline,
        })
    } else {
        let length = draw.uniform(0.1, largest.max(0.11));
        let width = draw.uniform(0.1, length);
        height = height.min(0.3);
        let mut bag = Bag {
            size: [length, width, height],
            center: [0.0, 0.0],
            yaw_deg,
            sag: draw.uniform(0.0, 0.3),
            color,
            finish,
            timeline,
        };
        // A sagging bag's top is lower than its size says: the top is the height drawn.
        bag.size[2] *= height / bag.top_m();
        Piece::Bag(bag)
    };
    (piece, surface, flat && height <= 0.05)
}

/// Scene `index` of the set of `seed`.
pub fn cert_scene(seed: u64, index: usize) -> CertScene {
    let mut draw = Draw(mix64(seed ^ 0x6365_7274) ^ mix64(index as u64));
    let (mut cameras, middle) = station(&mut draw);
    // The color sensors from a stream of their own.
    let mut sensor = Draw(mix64(seed ^ 0x6365_7274_636f_6c6f) ^ mix64(index as u64));
    for c in &mut cameras {
        c.color_sensor = ColorSensor {
            noise: sensor.uniform(1.5, 3.0),
            blur_px: sensor.uniform(BLUR_PX[0], BLUR_PX[1]),
            exposure: sensor.uniform(0.85, 1.1),
        };
    }
    let count = match draw.uniform(0.0, 1.0) {
        u if u < 0.35 => 1,
        u if u < 0.7 => 2,
        u if u < 0.9 => 3,
        _ => 4,
    };
    let spacing_mm =
        (count > 1).then(|| SPACINGS_MM[(draw.next() % SPACINGS_MM.len() as u64) as usize]);
    // Most groups are wholly in view; some reach out of it.
    let whole = draw.uniform(0.0, 1.0) >= 0.15;
    let lowest = cameras
        .iter()
        .map(|c| c.position[2])
        .fold(f64::INFINITY, f64::min);
    let tallest = (lowest - 0.5).min(0.6);
    let mut largest = 1.2 / (count as f64).sqrt();
    let mut built = None;
    for _ in 0..40 {
        let pieces: Vec<(Piece, Surface, bool)> = (0..count)
            .map(|k| piece(&mut draw, k, largest, tallest))
            .collect();
        let row_deg = draw.uniform(-90.0, 90.0);
        let centre = [
            middle[0] + draw.uniform(-0.1, 0.1),
            middle[1] + draw.uniform(-0.1, 0.1),
        ];
        let gap = spacing_mm.unwrap_or(0.0) / 1e3;
        let extents: Vec<(f64, f64)> = pieces.iter().map(|p| p.0.extent(row_deg)).collect();
        let total: f64 = extents.iter().map(|e| e.0).sum::<f64>() + gap * (count - 1) as f64;
        let narrowest = extents.iter().map(|e| e.1).fold(f64::INFINITY, f64::min);
        let (s, c) = row_deg.to_radians().sin_cos();
        let mut along = -total / 2.0;
        let mut placed: Vec<[[f64; 2]; 4]> = Vec::new();
        let mut previous: Option<f64> = None;
        let mut scene = Scene {
            seed: 0,
            floor: Floor::default(),
            cameras: cameras.clone(),
            boxes: Vec::new(),
            cylinders: Vec::new(),
            tubes: Vec::new(),
            bags: Vec::new(),
            markers: Vec::new(),
        };
        let mut made: Vec<(ObjectKind, usize, Surface, bool)> = Vec::new();
        for ((mut p, surface, flat), (ext, _)) in pieces.into_iter().zip(&extents) {
            let across = draw.uniform(-0.2, 0.2) * narrowest;
            let at = |m: f64| {
                [
                    centre[0] + m * c - across * s,
                    centre[1] + m * s + across * c,
                ]
            };
            // Along the row its extent keeps `gap` from the one before; slid back
            // towards it until the nearest footprint is `gap` away (turned footprints
            // otherwise keep more).
            let mut mid = along + ext / 2.0;
            if let Some(before) = previous {
                let nearest = |m: f64| {
                    let here = p.corners(at(m));
                    placed
                        .iter()
                        .map(|f| separation(&here, f))
                        .fold(f64::INFINITY, f64::min)
                };
                let (mut lo, mut hi) = (before, mid);
                for _ in 0..50 {
                    let m = (lo + hi) / 2.0;
                    if nearest(m) < gap { lo = m } else { hi = m }
                }
                mid = hi;
            }
            p.place(at(mid));
            placed.push(p.corners(at(mid)));
            previous = Some(mid);
            along = mid + ext / 2.0 + gap;
            let (kind, at) = match p {
                Piece::Box(b) => {
                    scene.boxes.push(b);
                    (ObjectKind::Box, scene.boxes.len())
                }
                Piece::Cylinder(x) => {
                    scene.cylinders.push(x);
                    (ObjectKind::Cylinder, scene.cylinders.len())
                }
                Piece::Tube(t) => {
                    scene.tubes.push(t);
                    (ObjectKind::Tube, scene.tubes.len())
                }
                Piece::Bag(b) => {
                    scene.bags.push(b);
                    (ObjectKind::Bag, scene.bags.len())
                }
            };
            made.push((kind, at - 1, surface, flat));
        }
        // Whether the group fits the view asks where the cameras look, not what hides
        // what (the judgement's occlusion leaves the scenes as they were drawn).
        let eyes = eyes(&scene);
        let truths = scene.truths();
        let framed = truths
            .iter()
            .filter(|t| eyes.iter().any(|e| e.sees_whole(t)))
            .count();
        let on_table = truths.iter().all(|t| {
            t.footprint
                .iter()
                .all(|p| p[0].abs() <= TABLE_HALF_M && p[1].abs() <= TABLE_HALF_M)
        });
        let fits = on_table && if whole { framed == count } else { framed > 0 };
        built = Some((scene, made));
        if fits {
            break;
        }
        largest = (largest * 0.85).max(0.06);
    }
    let (mut scene, made) = built.expect("at least one attempt");
    let judged = judge(&scene);
    // Within TOML's integers, so the scene can be written as a file.
    scene.seed = draw.next() >> 1;
    let objects = scene
        .truths()
        .into_iter()
        .zip(judged)
        .map(|(truth, judged)| {
            let &(_, _, surface, flat) = made
                .iter()
                .find(|m| m.0 == truth.kind && m.1 == truth.index)
                .expect("every truth was made");
            let label = match truth.kind {
                ObjectKind::Box => scene.boxes[truth.index].label.clone(),
                _ => None,
            };
            CertObject {
                truth,
                surface,
                flat,
                label,
                judged,
            }
        })
        .collect();
    CertScene {
        index,
        scene,
        objects,
        spacing_mm,
    }
}
