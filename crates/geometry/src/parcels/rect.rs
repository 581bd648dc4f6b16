//! Small helpers for rectangles on the floor plane (corners in order around them).

use geo::{Coord, LineString, Polygon};

/// Of a cuboid, at most this share of the dense points lies farther outside the lid's
/// rectangle than [`OUTSIDE_M`] (the sides of a lying tube or a polybag's belly do).
pub(super) const CUBOID_OUTSIDE: f64 = 0.05;

/// See [`CUBOID_OUTSIDE`], metres.
pub(super) const OUTSIDE_M: f64 = 0.010;

pub(super) fn sub(a: [f64; 2], b: [f64; 2]) -> [f64; 2] {
    [a[0] - b[0], a[1] - b[1]]
}

pub(super) fn dot(a: [f64; 2], b: [f64; 2]) -> f64 {
    a[0] * b[0] + a[1] * b[1]
}

pub(super) fn rect_area(c: &[[f64; 2]; 4]) -> f64 {
    let (e0, e1) = (sub(c[1], c[0]), sub(c[3], c[0]));
    (e0[0] * e1[1] - e0[1] * e1[0]).abs()
}

/// The share of `points` lying more than `tolerance` outside the rectangle `corners`.
pub(super) fn share_outside(
    corners: &[[f64; 2]; 4],
    points: impl Iterator<Item = [f64; 2]>,
    tolerance: f64,
) -> f64 {
    let c0 = corners[0];
    let (e0, e1) = (sub(corners[1], c0), sub(corners[3], c0));
    let (la, lb) = (e0[0].hypot(e0[1]), e1[0].hypot(e1[1]));
    if la <= 0.0 || lb <= 0.0 {
        return 1.0;
    }
    let (a, b) = ([e0[0] / la, e0[1] / la], [e1[0] / lb, e1[1] / lb]);
    let (mut n, mut out) = (0usize, 0usize);
    for p in points {
        let d = sub(p, c0);
        let (s, t) = (dot(d, a), dot(d, b));
        n += 1;
        if s < -tolerance || s > la + tolerance || t < -tolerance || t > lb + tolerance {
            out += 1;
        }
    }
    if n == 0 { 0.0 } else { out as f64 / n as f64 }
}

/// The rectangle `corners` as a polygon.
pub(super) fn polygon(corners: &[[f64; 2]; 4]) -> Polygon<f64> {
    let ring: Vec<Coord<f64>> = corners.iter().map(|c| Coord { x: c[0], y: c[1] }).collect();
    Polygon::new(LineString::from(ring), Vec::new())
}
