//! The lane set: seeded synthetic scenes that look like a parcel lane, each with its
//! case and the truth of its parcels, for measuring how well a station measures
//! (`bench accuracy`). Scene `index` of seed `seed` is always the same scene; its case is
//! `Case::ALL[index % Case::ALL.len()]`, so any run of consecutive indices mixes the
//! cases evenly.
//!
//! Every scene has one or two calibrated D415s (noise `"d415"`) above the table; with two,
//! they stand on either side of the parcels along the long axis of what they look at, and
//! the image's wide axis runs along it. Apart from the `cut` case every parcel is wholly in
//! view of every camera, with a margin.

use super::d415;
use super::render::mix64;
use super::scene::{
    Bag, ColorSensor, Cylinder, Finish, Floor, Noise, Scene, SceneBox, SceneCamera, Timeline,
    Truth, Tube,
};
use crate::camera::Serial;

/// What a lane scene is about: the situation the station has to measure (or refuse).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
#[non_exhaustive]
pub enum Case {
    /// One matte box, 100 to 600 mm long.
    Clean,
    /// One matte box over 600 mm long (600 to 800 mm).
    Large,
    /// One dark box (reflectivity 0.03 to 0.35): from nearly whole depth to nearly none.
    Dark,
    /// One glossy box (gloss 0.4 to 1): the projector's glare takes depth where it
    /// mirrors into the imagers.
    Glossy,
    /// One cylinder: standing upright (turns 0, 1, 4, 5, ... of the case) or a tube
    /// lying on the floor (turns 2, 3, 6, 7, ...).
    Cylinder,
    /// One polybag (a pillow, sagging up to 30 %, a little glossy).
    Polybag,
    /// Two boxes on the table, 60 to 250 mm apart.
    Apart,
    /// Two boxes side by side, touching along a face.
    Touching,
    /// One box partly outside every camera's view (10 to 35 % of its length).
    Cut,
}

impl Case {
    /// Every case, in the order the set cycles through them.
    pub const ALL: [Self; 9] = [
        Self::Clean,
        Self::Large,
        Self::Dark,
        Self::Glossy,
        Self::Cylinder,
        Self::Polybag,
        Self::Apart,
        Self::Touching,
        Self::Cut,
    ];

    /// The case's name in reports (`clean`, `large`, `dark`, `glossy`, `cylinder`,
    /// `polybag`, `apart`, `touching`, `cut`).
    pub fn name(self) -> &'static str {
        match self {
            Self::Clean => "clean",
            Self::Large => "large",
            Self::Dark => "dark",
            Self::Glossy => "glossy",
            Self::Cylinder => "cylinder",
            Self::Polybag => "polybag",
            Self::Apart => "apart",
            Self::Touching => "touching",
            Self::Cut => "cut",
        }
    }
}

impl std::fmt::Display for Case {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// The number of scenes `bench accuracy` measures by default: eight of each case and
/// more.
pub const LANE_SET_SIZE: usize = 72;

/// One scene of the lane set.
#[derive(Debug, Clone, PartialEq)]
pub struct LaneScene {
    /// Its index in the set.
    pub index: usize,
    /// What it is about.
    pub case: Case,
    /// The scene (cameras, parcels).
    pub scene: Scene,
    /// The truth of its parcels ([`Scene::truths`]), the largest footprint first.
    pub truths: Vec<Truth>,
}

/// The first `count` scenes of the set of `seed`.
pub fn lane_set(seed: u64, count: usize) -> Vec<LaneScene> {
    (0..count).map(|i| lane_scene(seed, i)).collect()
}

/// Counter-based random numbers (SplitMix64) for the generator.
pub(super) struct Draw(pub(super) u64);

impl Draw {
    pub(super) fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        mix64(self.0)
    }

    /// Uniform in [lo, hi).
    pub(super) fn uniform(&mut self, lo: f64, hi: f64) -> f64 {
        let unit = (self.next() >> 11) as f64 / (1u64 << 53) as f64;
        lo + (hi - lo) * unit
    }

    /// A parcel's matte color: cardboard browns and greys, lighter or darker.
    pub(super) fn cardboard(&mut self) -> [u8; 3] {
        let base = [
            [180.0, 140.0, 90.0],
            [200.0, 170.0, 120.0],
            [150.0, 150.0, 145.0],
            [210.0, 205.0, 195.0],
        ][(self.next() % 4) as usize];
        let shade = self.uniform(0.8, 1.1);
        base.map(|c: f64| (c * shade).min(255.0) as u8)
    }
}

/// Half-angle tangents of the D415 depth view at 1280x720 (wide axis, narrow axis),
/// from the principal point to the nearer image edge.
fn half_view_tan() -> [f64; 2] {
    let k = d415::depth_intrinsics(1280, 720);
    let (w, h) = (f64::from(k.width), f64::from(k.height));
    let (ppx, ppy, fx, fy) = (
        f64::from(k.ppx),
        f64::from(k.ppy),
        f64::from(k.fx),
        f64::from(k.fy),
    );
    [ppx.min(w - ppx) / fx, ppy.min(h - ppy) / fy]
}

/// Share of the half view a parcel may fill (the rest is margin).
const VIEW_MARGIN: f64 = 0.85;
/// Highest camera above the floor, metres.
const CAMERA_Z_MAX: f64 = 1.9;
/// Lowest camera above the floor, metres.
const CAMERA_Z_MIN: f64 = 0.8;
/// Nearest a camera comes to the highest lid, metres: clear of the D415's minimum range
/// (0.39 m at 1280x720).
const LID_DISTANCE_MIN: f64 = 0.5;
/// How far two cameras stand from the middle of what they look at, along its length,
/// metres.
const PAIR_OFFSET: f64 = 0.12;

/// What the cameras look at: a rectangle on the floor (centre, yaw of its length,
/// length, width) and the highest parcel's height.
struct Group {
    center: [f64; 2],
    yaw_deg: f64,
    length: f64,
    width: f64,
    height: f64,
}

/// Cameras above `group`: one straight above it or two on either end of its length,
/// high enough that the group is in view with a margin. `shift` moves the single camera
/// along the length (the `cut` case), `z` overrides the height.
fn cameras(
    draw: &mut Draw,
    group: &Group,
    two: bool,
    shift: f64,
    z: Option<f64>,
) -> Vec<SceneCamera> {
    let [wide, narrow] = half_view_tan().map(|t| t * VIEW_MARGIN);
    let offset = if two { PAIR_OFFSET } else { 0.0 };
    let needed = ((group.length / 2.0 + offset) / wide).max(group.width / 2.0 / narrow);
    let lowest = (group.height + needed.max(LID_DISTANCE_MIN)).max(CAMERA_Z_MIN);
    let camera_z = z.unwrap_or_else(|| draw.uniform(lowest, CAMERA_Z_MAX.max(lowest + 0.05)));
    let (sin, cos) = group.yaw_deg.to_radians().sin_cos();
    // Image up is the group's width axis, so the image's x runs along its length.
    let up = [-sin, cos, 0.0];
    let camera = |n: u64, along: f64, z: f64| SceneCamera {
        serial: Serial::from_digits(serial_digits(840_412_061_000 + n)),
        position: [
            group.center[0] + along * cos,
            group.center[1] + along * sin,
            z,
        ],
        look_at: [
            group.center[0] + shift * cos,
            group.center[1] + shift * sin,
            group.height,
        ],
        up: Some(up),
        noise: Noise::D415,
        calibrated: true,
        stall_s: None,
        color_sensor: ColorSensor::default(),
    };
    if two {
        vec![
            camera(1, offset, camera_z),
            camera(2, -offset, camera_z - 0.05),
        ]
    } else {
        vec![camera(0, shift, camera_z)]
    }
}

/// Noise, blur and exposure of the lane set's color sensors, drawn per camera: noise 1.5
/// to 3 levels at mid grey, blur 0.15 to 0.3 pixels, exposure 0.85 to 1.1. The blur and
/// the exposure stay where the QR reader (rqrr) still reads the demo scene's label from
/// both cameras: from a blur of 0.5 pixels, or an exposure of 1.15 with a blur of 0.3,
/// it loses the farther camera's code.
pub const LANE_COLOR_NOISE: [f64; 2] = [1.5, 3.0];
/// See [`LANE_COLOR_NOISE`].
pub const LANE_BLUR_PX: [f64; 2] = [0.15, 0.3];
/// See [`LANE_COLOR_NOISE`].
pub const LANE_EXPOSURE: [f64; 2] = [0.85, 1.1];

fn lane_color_sensor(draw: &mut Draw) -> ColorSensor {
    ColorSensor {
        noise: draw.uniform(LANE_COLOR_NOISE[0], LANE_COLOR_NOISE[1]),
        blur_px: draw.uniform(LANE_BLUR_PX[0], LANE_BLUR_PX[1]),
        exposure: draw.uniform(LANE_EXPOSURE[0], LANE_EXPOSURE[1]),
    }
}

/// Twelve ASCII digits of `n` (below 10^12).
pub(super) fn serial_digits(n: u64) -> [u8; 12] {
    let mut digits = [b'0'; 12];
    let mut n = n % 1_000_000_000_000;
    for d in digits.iter_mut().rev() {
        *d = b'0' + (n % 10) as u8;
        n /= 10;
    }
    digits
}

fn matte_box(draw: &mut Draw, size: [f64; 3], center: [f64; 2], yaw_deg: f64) -> SceneBox {
    SceneBox {
        size,
        center,
        yaw_deg,
        color: draw.cardboard(),
        label: None,
        finish: Finish::default(),
        timeline: Timeline::default(),
    }
}

/// Length and width of a box, length first, each in [lo, hi).
fn footprint(draw: &mut Draw, lo: f64, hi: f64) -> (f64, f64) {
    let a = draw.uniform(lo, hi);
    let b = draw.uniform(lo, hi);
    (a.max(b), a.min(b))
}

/// Scene `index` of the set of `seed`.
pub fn lane_scene(seed: u64, index: usize) -> LaneScene {
    let case = Case::ALL[index % Case::ALL.len()];
    let mut draw = Draw(mix64(seed ^ 0x6c61_6e65) ^ mix64(index as u64));
    // Each case alternates one camera and two through its scenes.
    let two = (index / Case::ALL.len()) % 2 == 1;
    let center = [draw.uniform(-0.05, 0.05), draw.uniform(-0.05, 0.05)];
    let yaw_deg = draw.uniform(-90.0, 90.0);
    let mut boxes = Vec::new();
    let mut cylinders = Vec::new();
    let mut tubes = Vec::new();
    let mut bags = Vec::new();
    let cams = match case {
        Case::Clean | Case::Large | Case::Dark | Case::Glossy | Case::Cut => {
            let (length, width) = if case == Case::Large {
                (draw.uniform(0.60, 0.80), draw.uniform(0.30, 0.60))
            } else {
                let length = draw.uniform(0.10, 0.60);
                (length, draw.uniform(0.08, length))
            };
            let height = draw.uniform(0.03, if case == Case::Large { 0.40 } else { 0.50 });
            let mut parcel = matte_box(&mut draw, [length, width, height], center, yaw_deg);
            if case == Case::Dark {
                let grey = draw.uniform(12.0, 60.0) as u8;
                parcel.color = [grey, grey, grey.saturating_add(4)];
                parcel.finish.reflectivity = draw.uniform(0.03, 0.35);
            } else if case == Case::Glossy {
                parcel.finish.gloss = draw.uniform(0.4, 1.0);
            }
            boxes.push(parcel);
            let group = Group {
                center,
                yaw_deg,
                length,
                width,
                height,
            };
            if case == Case::Cut {
                // One camera whose view along the length ends `out` short of the box's far
                // end: `out` of the length lies beyond the image's edge.
                let out = draw.uniform(0.10, 0.35) * length;
                let [wide, narrow] = half_view_tan().map(|t| t * VIEW_MARGIN);
                let needed = ((length - out) / 2.0 / wide)
                    .max(width / 2.0 / narrow)
                    .max(LID_DISTANCE_MIN);
                let lowest = (height + needed).max(CAMERA_Z_MIN);
                let camera_z = draw.uniform(lowest, lowest + 0.3);
                // Where the view along the length ends at the lid, from the camera's axis.
                let half = half_view_tan()[0] * (camera_z - height);
                let shift = length / 2.0 - out - half;
                cameras(&mut draw, &group, false, shift, Some(camera_z))
            } else {
                cameras(&mut draw, &group, two, 0.0, None)
            }
        }
        Case::Cylinder if (index / (2 * Case::ALL.len())).is_multiple_of(2) => {
            // Standing upright.
            let radius = draw.uniform(0.04, 0.15);
            let height = draw.uniform(0.10, 0.50);
            cylinders.push(Cylinder {
                radius,
                height,
                center,
                color: draw.cardboard(),
                finish: Finish::default(),
                timeline: Timeline::default(),
            });
            let group = Group {
                center,
                yaw_deg,
                length: 2.0 * radius,
                width: 2.0 * radius,
                height,
            };
            cameras(&mut draw, &group, two, 0.0, None)
        }
        Case::Cylinder => {
            // A mailing tube lying on the floor.
            let radius = draw.uniform(0.03, 0.10);
            let length = draw.uniform(0.30, 0.90);
            tubes.push(Tube {
                radius,
                length,
                center,
                yaw_deg,
                color: draw.cardboard(),
                finish: Finish::default(),
                timeline: Timeline::default(),
            });
            let group = Group {
                center,
                yaw_deg,
                length,
                width: 2.0 * radius,
                height: 2.0 * radius,
            };
            cameras(&mut draw, &group, two, 0.0, None)
        }
        Case::Polybag => {
            let (length, width) = footprint(&mut draw, 0.15, 0.60);
            let bag = Bag {
                size: [length, width, draw.uniform(0.04, 0.25)],
                center,
                yaw_deg,
                sag: draw.uniform(0.0, 0.3),
                color: [
                    draw.uniform(190.0, 235.0) as u8,
                    draw.uniform(190.0, 235.0) as u8,
                    draw.uniform(200.0, 240.0) as u8,
                ],
                finish: Finish {
                    reflectivity: 1.0,
                    gloss: draw.uniform(0.0, 0.3),
                },
                timeline: Timeline::default(),
            };
            let group = Group {
                center,
                yaw_deg,
                length,
                width,
                height: bag.size[2],
            };
            bags.push(bag);
            cameras(&mut draw, &group, two, 0.0, None)
        }
        Case::Apart | Case::Touching => {
            // Two boxes along the group's length: the first at its low end, the second
            // after a gap (none when touching, then with the same yaw, face to face).
            let (la, wa) = footprint(&mut draw, 0.10, 0.40);
            let (lb, wb) = footprint(&mut draw, 0.10, 0.40);
            let (ha, hb) = (draw.uniform(0.05, 0.40), draw.uniform(0.05, 0.40));
            let (gap, turn) = if case == Case::Touching {
                (0.0, 0.0)
            } else {
                (draw.uniform(0.06, 0.25), draw.uniform(-15.0, 15.0))
            };
            // The second box's extent along the group's length, turned by `turn`.
            let (ts, tc) = turn.to_radians().sin_cos();
            let lb_along = lb * tc.abs() + wb * ts.abs();
            let wb_across = lb * ts.abs() + wb * tc.abs();
            let lateral = draw.uniform(-0.25, 0.25) * wa.min(wb_across);
            let length = la + gap + lb_along;
            let (sin, cos) = yaw_deg.to_radians().sin_cos();
            let at = |along: f64, across: f64| {
                [
                    center[0] + along * cos - across * sin,
                    center[1] + along * sin + across * cos,
                ]
            };
            boxes.push(matte_box(
                &mut draw,
                [la, wa, ha],
                at(-length / 2.0 + la / 2.0, 0.0),
                yaw_deg,
            ));
            boxes.push(matte_box(
                &mut draw,
                [lb, wb, hb],
                at(length / 2.0 - lb_along / 2.0, lateral),
                yaw_deg + turn,
            ));
            let group = Group {
                center,
                yaw_deg,
                length,
                width: wa.max(wb_across) + 2.0 * lateral.abs(),
                height: ha.max(hb),
            };
            cameras(&mut draw, &group, two, 0.0, None)
        }
    };
    // The color sensor from a stream of its own, so the geometry does not depend on it.
    let mut sensor = Draw(mix64(seed ^ 0x0063_6f6c_6f72) ^ mix64(index as u64));
    let mut cams = cams;
    for camera in &mut cams {
        camera.color_sensor = lane_color_sensor(&mut sensor);
    }
    let scene = Scene {
        seed: draw.next(),
        floor: Floor::default(),
        cameras: cams,
        boxes,
        cylinders,
        tubes,
        bags,
        markers: Vec::new(),
    };
    let mut truths = scene.truths();
    truths.sort_by(|a, b| b.footprint_m2().total_cmp(&a.footprint_m2()));
    LaneScene {
        index,
        case,
        scene,
        truths,
    }
}
