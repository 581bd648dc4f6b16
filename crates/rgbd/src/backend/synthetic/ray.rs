//! What the ray caster asks of every object kind's primitive ([`Primitive`]), and the
//! intersection arithmetic the kinds share: slabs, the distance from an axis, capped
//! cylinders, turning into and out of an object's own frame.

use std::fmt::Debug;
use std::sync::Arc;

use nalgebra::Vector3;

pub(crate) type V3 = Vector3<f32>;

/// Parameter distance below which an intersection counts as the ray's own start.
pub(crate) const T_EPS: f32 = 1e-4;

/// An object of a scene as the ray caster sees it (f32, world frame, standing on the
/// floor). Each object kind has one (`kinds/`); the caster holds them behind this trait
/// and knows none of them.
pub(crate) trait Primitive: Debug + Send + Sync {
    /// Where the ray `o + t d` is inside it, and the face it enters through.
    fn interval(&self, o: &V3, d: &V3) -> Option<Interval>;

    /// Unit normal (world) where the ray `o + t d` enters through `face` at `t`; never
    /// asked for [`Face::Z`], a horizontal face, which the caster handles for every kind.
    fn normal(&self, face: Face, o: &V3, d: &V3, t: f32) -> V3;

    /// The centre of its footprint on the floor.
    fn center(&self) -> V3;

    /// The same primitive standing at `center`.
    fn moved(&self, center: V3) -> Arc<dyn Primitive>;

    /// Its bounding sphere (centre, radius), for culling.
    fn sphere(&self) -> (V3, f32);

    /// The same primitive without its label; `None` when it has none.
    fn unlabelled(&self) -> Option<Arc<dyn Primitive>> {
        None
    }

    /// Whether a point of its top lies on its label.
    fn on_label(&self, _p: &V3) -> bool {
        false
    }

    /// Whether its label is black at a point of its top.
    fn label_dark(&self, _p: &V3) -> bool {
        false
    }

    /// Where a ray straight down through the floor point (`x`, `y`) from height `above`
    /// (over the whole primitive) first meets it; `None` when it misses it.
    fn top_over(&self, x: f32, y: f32, above: f32) -> Option<V3> {
        let o = V3::new(x, y, above);
        let d = V3::new(0.0, 0.0, -1.0);
        self.interval(&o, &d).map(|iv| o + d * iv.near)
    }
}

/// Which face of a primitive a ray enters through.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Face {
    /// A box face across local x.
    X,
    /// A box face across local y.
    Y,
    /// A horizontal face (box or cylinder cap).
    Z,
    /// The cylinder's or the tube's curved side.
    Side,
    /// A bag's surface.
    Surface,
}

/// An entry/exit interval along a ray and the face at the entry.
pub(crate) struct Interval {
    pub(crate) near: f32,
    pub(crate) far: f32,
    pub(crate) face: Face,
}

/// Where the ray `o + t d` (one coordinate of it) is from `lo` to `hi`: every `t` when it
/// runs parallel to them and lies between, `None` when it runs parallel outside.
pub(crate) fn slab(o: f32, d: f32, lo: f32, hi: f32) -> Option<(f32, f32)> {
    if d.abs() < 1e-12 {
        return (lo..=hi)
            .contains(&o)
            .then_some((f32::NEG_INFINITY, f32::INFINITY));
    }
    let inv = 1.0 / d;
    let (t0, t1) = ((lo - o) * inv, (hi - o) * inv);
    Some(if t0 < t1 { (t0, t1) } else { (t1, t0) })
}

/// A world vector in a frame turned by the yaw whose cosine and sine are given.
pub(crate) fn to_local(cos: f32, sin: f32, v: &V3) -> V3 {
    V3::new(cos * v.x + sin * v.y, -sin * v.x + cos * v.y, v.z)
}

/// A vector of a frame turned by the yaw whose cosine and sine are given, in the world.
pub(crate) fn from_local(cos: f32, sin: f32, v: &V3) -> V3 {
    V3::new(cos * v.x - sin * v.y, sin * v.x + cos * v.y, v.z)
}

/// The ray parameters within which a ray is within `radius` of an axis: `p` and `d` are
/// the ray's origin and direction in the two coordinates across the axis. `None` when it
/// never is; a ray along the axis is within it throughout or never.
pub(crate) fn across_axis(p: [f32; 2], d: [f32; 2], radius: f32) -> Option<(f32, f32)> {
    let a = d[0] * d[0] + d[1] * d[1];
    let b = 2.0 * (p[0] * d[0] + p[1] * d[1]);
    let c = p[0] * p[0] + p[1] * p[1] - radius * radius;
    if a < 1e-12 {
        if c > 0.0 {
            return None;
        }
        return Some((f32::NEG_INFINITY, f32::INFINITY));
    }
    let disc = b * b - 4.0 * a * c;
    if disc < 0.0 {
        return None;
    }
    let sq = disc.sqrt();
    Some(((-b - sq) / (2.0 * a), (-b + sq) / (2.0 * a)))
}

/// Where a ray is inside a capped cylinder: both `across` the axis (from
/// [`across_axis`]) and `along` it between the caps (from [`slab`]). It enters through
/// `cap` when it crosses a cap last, else through the curved side.
pub(crate) fn capped(across: (f32, f32), along: (f32, f32), cap: Face) -> Option<Interval> {
    let near = across.0.max(along.0);
    let far = across.1.min(along.1);
    if near > far {
        return None;
    }
    let face = if near == along.0 { cap } else { Face::Side };
    Some(Interval { near, far, face })
}
