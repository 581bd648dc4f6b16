//! `[[bag]]`: a soft, filled polybag lying on the floor, a pillow over its footprint.

use std::fmt::Write as _;
use std::sync::Arc;

use serde::Deserialize;

use super::{Object, ObjectKind};
use crate::backend::synthetic::fields::{
    Finish, SceneError, Timeline, TimelineFile, check_place, check_surface, invalid, positive,
    write_finish, write_timeline,
};
use crate::backend::synthetic::ray::{
    Face, Interval, Primitive, T_EPS, V3, from_local, slab, to_local,
};

/// The color of a bag that names none.
fn default_color() -> [u8; 3] {
    [215, 215, 222]
}

/// A soft, filled polybag lying on the floor, modelled as a pillow: over its rectangular
/// footprint the height is `height * q(u) * q(v) * (1 - sag (1 - u^2) (1 - v^2))`, where
/// u and v run from -1 to 1 across its length and width and q(s) = (1 - s^4)^(1/4). The
/// top is nearly flat in the middle, the edges round down to meet the floor upright
/// (q falls steeply near |s| = 1), the corners are lower than the middle of the sides,
/// and `sag` lowers the middle of the top (a bag not quite full). Its smallest
/// enclosing cuboid is the footprint times its highest point ([`Bag::top_m`]).
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(from = "BagFile")]
pub struct Bag {
    /// Length (along x before yaw), width and greatest possible height (without sag),
    /// metres.
    pub size: [f64; 3],
    /// Footprint centre on the floor, (x, y) metres.
    pub center: [f64; 2],
    /// Rotation about world z, degrees, counter-clockwise seen from above.
    pub yaw_deg: f64,
    /// How much the middle of the top sinks, 0 (a full pillow, the default) to 0.5.
    pub sag: f64,
    /// Color.
    pub color: [u8; 3],
    /// How its surface returns the D415's light.
    pub finish: Finish,
    /// When it is there, and whether it slides in.
    pub timeline: Timeline,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct BagFile {
    size: [f64; 3],
    center: [f64; 2],
    #[serde(default)]
    yaw_deg: f64,
    #[serde(default)]
    sag: f64,
    #[serde(default = "default_color")]
    color: [u8; 3],
    #[serde(flatten)]
    finish: Finish,
    #[serde(flatten)]
    timeline: TimelineFile,
}

impl From<BagFile> for Bag {
    fn from(f: BagFile) -> Self {
        Self {
            size: f.size,
            center: f.center,
            yaw_deg: f.yaw_deg,
            sag: f.sag,
            color: f.color,
            finish: f.finish,
            timeline: f.timeline.into(),
        }
    }
}

/// Most a bag's top may sink in the middle ([`Bag::sag`]).
pub const MAX_SAG: f64 = 0.5;

/// The pillow profile across a bag: (1 - s^4)^(1/4) for |s| < 1, else 0.
pub fn bag_profile(s: f64) -> f64 {
    let s2 = s * s;
    let r = 1.0 - s2 * s2;
    if r <= 0.0 { 0.0 } else { r.sqrt().sqrt() }
}

impl Bag {
    /// Height of the bag's top at (u, v), each from -1 to 1 across its length and width,
    /// as a share of `size[2]`.
    pub fn shape(u: f64, v: f64, sag: f64) -> f64 {
        bag_profile(u) * bag_profile(v) * (1.0 - sag * (1.0 - u * u) * (1.0 - v * v))
    }

    /// Its highest point above the floor, metres (`size[2]` without sag, lower with it),
    /// found by a grid search refined twice (to far below a micrometre).
    pub fn top_m(&self) -> f64 {
        let mut best = (0.0, 0.0, Self::shape(0.0, 0.0, self.sag));
        let mut step = 0.02;
        let mut center = (0.0, 0.0);
        for _ in 0..3 {
            for i in -50..=50 {
                for j in -50..=50 {
                    let (u, v) = (
                        (center.0 + f64::from(i) * step).clamp(-1.0, 1.0),
                        (center.1 + f64::from(j) * step).clamp(-1.0, 1.0),
                    );
                    let h = Self::shape(u, v, self.sag);
                    if h > best.2 {
                        best = (u, v, h);
                    }
                }
            }
            center = (best.0, best.1);
            step /= 50.0;
        }
        best.2 * self.size[2]
    }
}

impl Object for Bag {
    fn kind(&self) -> ObjectKind {
        ObjectKind::Bag
    }

    fn validate(&self, at: &dyn Fn(&str) -> String) -> Result<(), SceneError> {
        positive(&at("size"), &self.size)?;
        check_place(at, &self.center, Some(self.yaw_deg))?;
        if !(0.0..=MAX_SAG).contains(&self.sag) {
            return Err(invalid(
                at("sag"),
                format!("must be from 0 to {MAX_SAG}, got {}", self.sag),
            ));
        }
        check_surface(at, &self.finish, &self.timeline)
    }

    fn footprint(&self) -> ([f64; 2], f64) {
        ([self.size[0], self.size[1]], self.yaw_deg)
    }

    /// Its highest point ([`Bag::top_m`]).
    fn height(&self) -> f64 {
        self.top_m()
    }

    fn center(&self) -> [f64; 2] {
        self.center
    }

    fn color(&self) -> [u8; 3] {
        self.color
    }

    fn finish(&self) -> &Finish {
        &self.finish
    }

    fn timeline(&self) -> &Timeline {
        &self.timeline
    }

    fn place_mut(&mut self) -> (&mut [f64; 2], &mut Timeline) {
        (&mut self.center, &mut self.timeline)
    }

    fn primitive(
        &self,
        floor_z: f32,
        _at: &dyn Fn(&str) -> String,
    ) -> Result<Arc<dyn Primitive>, SceneError> {
        let yaw = (self.yaw_deg as f32).to_radians();
        Ok(Arc::new(BagPrim {
            center: V3::new(self.center[0] as f32, self.center[1] as f32, floor_z),
            cos: yaw.cos(),
            sin: yaw.sin(),
            half: [self.size[0] as f32 / 2.0, self.size[1] as f32 / 2.0],
            height: self.size[2] as f32,
            sag: self.sag as f32,
        }))
    }

    fn write_toml(&self, out: &mut String) {
        let _ = writeln!(
            out,
            "\n[[bag]]\nsize = {:?}\ncenter = {:?}\nyaw_deg = {:?}\nsag = {:?}\ncolor = {:?}",
            self.size, self.center, self.yaw_deg, self.sag, self.color
        );
        write_finish(out, &self.finish);
        write_timeline(out, &self.timeline);
    }
}

/// A polybag as the ray caster sees it: the pillow height field of [`Bag`] over a
/// rectangle.
#[derive(Debug, Clone)]
struct BagPrim {
    /// Footprint centre on the floor.
    center: V3,
    cos: f32,
    sin: f32,
    half: [f32; 2],
    /// Greatest height without sag.
    height: f32,
    sag: f32,
}

/// Height above the floor, as a share of the greatest, below which a bag's surface
/// counts as not reached (keeps a ray that leaves the surface from meeting it again).
const BAG_INSIDE: f32 = 2e-5;
/// Bisection steps that place a ray's entry into a bag (each halves the uncertainty).
const BAG_BISECTIONS: u32 = 16;

impl BagPrim {
    /// Height of the top over local point (x, y), metres; 0 off the footprint.
    fn top(&self, x: f32, y: f32) -> f32 {
        let (u, v) = (x / self.half[0], y / self.half[1]);
        let profile = |s: f32| {
            let s2 = s * s;
            let r = 1.0 - s2 * s2;
            if r <= 0.0 { 0.0 } else { r.sqrt().sqrt() }
        };
        self.height * profile(u) * profile(v) * (1.0 - self.sag * (1.0 - u * u) * (1.0 - v * v))
    }

    /// How far above the local point `p` the surface is (positive: `p` is inside).
    fn inside(&self, p: &V3) -> f32 {
        self.top(p.x, p.y) - p.z
    }

    /// Unit normal (world) of the surface over world point `p` (from the height's
    /// slopes by central differences).
    fn surface_normal(&self, p: &V3) -> V3 {
        let l = to_local(self.cos, self.sin, &(p - self.center));
        let h = 1e-3 * self.half[0].min(self.half[1]);
        let dx = (self.top(l.x + h, l.y) - self.top(l.x - h, l.y)) / (2.0 * h);
        let dy = (self.top(l.x, l.y + h) - self.top(l.x, l.y - h)) / (2.0 * h);
        from_local(self.cos, self.sin, &V3::new(-dx, -dy, 1.0).normalize())
    }
}

impl Primitive for BagPrim {
    /// The first entry of the ray into the bag within its bounding box: a march over
    /// the box to the first sample inside, then bisection. `far` is the box's exit.
    /// The march takes 24 steps for each footprint the ray crosses and each height it
    /// falls (the two added): a ray from a camera above falls nearly straight past
    /// a shoulder, crossing little of the footprint, and steps by the footprint alone
    /// (two or three samples down such a ray) passed over the shoulder's lower half,
    /// so rays that meet a side below about 0.6 of its height met the floor instead.
    #[inline(never)]
    fn interval(&self, o: &V3, d: &V3) -> Option<Interval> {
        let lo = to_local(self.cos, self.sin, &(o - self.center));
        let ld = to_local(self.cos, self.sin, d);
        let (x0, x1) = slab(lo.x, ld.x, -self.half[0], self.half[0])?;
        let (y0, y1) = slab(lo.y, ld.y, -self.half[1], self.half[1])?;
        let (z0, z1) = slab(lo.z, ld.z, 0.0, self.height)?;
        let start = x0.max(y0).max(z0).max(T_EPS);
        let far = x1.min(y1).min(z1);
        if start >= far {
            return None;
        }
        let at = |t: f32| self.inside(&(lo + ld * t)) > BAG_INSIDE * self.height;
        let span = far - start;
        let across = span * (ld.x.abs() / self.half[0] + ld.y.abs() / self.half[1]);
        let fall = span * ld.z.abs() / self.height;
        let steps = (((across + fall) * 24.0).ceil() as u32).clamp(2, 96);
        let mut before = start;
        for k in 0..=steps {
            let t = start + span * k as f32 / steps as f32;
            if at(t) {
                let near = if k == 0 {
                    start
                } else {
                    let (mut out, mut inn) = (before, t);
                    for _ in 0..BAG_BISECTIONS {
                        let mid = 0.5 * (out + inn);
                        if at(mid) {
                            inn = mid;
                        } else {
                            out = mid;
                        }
                    }
                    inn
                };
                return Some(Interval {
                    near,
                    far,
                    face: Face::Surface,
                });
            }
            before = t;
        }
        None
    }

    fn normal(&self, _face: Face, o: &V3, d: &V3, t: f32) -> V3 {
        self.surface_normal(&(o + d * t))
    }

    fn center(&self) -> V3 {
        self.center
    }

    fn moved(&self, center: V3) -> Arc<dyn Primitive> {
        Arc::new(Self {
            center,
            ..self.clone()
        })
    }

    fn sphere(&self) -> (V3, f32) {
        let (half, height) = (self.half, self.height);
        (
            self.center + V3::new(0.0, 0.0, height / 2.0),
            (half[0] * half[0] + half[1] * half[1] + height * height / 4.0).sqrt(),
        )
    }

    /// A height field: straight down meets it at its height, where it counts as reached
    /// (the march's test, without the march).
    fn top_over(&self, x: f32, y: f32, _above: f32) -> Option<V3> {
        let l = to_local(
            self.cos,
            self.sin,
            &(V3::new(x, y, self.center.z) - self.center),
        );
        let h = self.top(l.x, l.y);
        (h > BAG_INSIDE * self.height).then(|| V3::new(x, y, self.center.z + h))
    }
}
