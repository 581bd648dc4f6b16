//! Small helpers for rectangles on the floor plane (corners in order around them).

use geo::{Coord, LineString, Polygon};

use crate::Point3;

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

/// A rectangle's own frame: the origin at corner 0, the unit axis `a` towards corner 1
/// and `b` towards corner 3, the sides `la` and `lb` long. A point's local coordinates
/// `(s, t)` run along `a` and `b`: the rectangle is `0..=la` by `0..=lb`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(super) struct RectFrame {
    /// Corner 0.
    pub(super) origin: [f64; 2],
    /// The unit vector from corner 0 towards corner 1.
    pub(super) a: [f64; 2],
    /// The unit vector from corner 0 towards corner 3.
    pub(super) b: [f64; 2],
    /// The length from corner 0 to corner 1, metres.
    pub(super) la: f64,
    /// The length from corner 0 to corner 3, metres.
    pub(super) lb: f64,
}

impl RectFrame {
    /// The frame of the rectangle `corners` (in order around it), `None` when a side
    /// has no length.
    pub(super) fn new(corners: &[[f64; 2]; 4]) -> Option<Self> {
        let origin = corners[0];
        let (e0, e1) = (sub(corners[1], origin), sub(corners[3], origin));
        let (la, lb) = (e0[0].hypot(e0[1]), e1[0].hypot(e1[1]));
        if la <= 0.0 || lb <= 0.0 {
            return None;
        }
        Some(Self {
            origin,
            a: [e0[0] / la, e0[1] / la],
            b: [e1[0] / lb, e1[1] / lb],
            la,
            lb,
        })
    }

    /// The same frame with its axes exchanged (`a` towards corner 3, `b` towards 1).
    pub(super) fn swapped(self) -> Self {
        Self {
            a: self.b,
            b: self.a,
            la: self.lb,
            lb: self.la,
            ..self
        }
    }

    /// The local coordinates `(s, t)` of the floor point `xy`.
    pub(super) fn local(&self, xy: [f64; 2]) -> (f64, f64) {
        let d = sub(xy, self.origin);
        (dot(d, self.a), dot(d, self.b))
    }

    /// The local coordinates `(s, t)` of `p`'s position on the floor.
    pub(super) fn local_point(&self, p: &Point3) -> (f64, f64) {
        self.local([f64::from(p.x), f64::from(p.y)])
    }

    /// The floor point at local coordinates `(s, t)`.
    pub(super) fn at(&self, s: f64, t: f64) -> [f64; 2] {
        let (o, a, b) = (self.origin, self.a, self.b);
        [o[0] + a[0] * s + b[0] * t, o[1] + a[1] * s + b[1] * t]
    }

    /// The rectangle from `s0` to `s1` along `a` and from `t0` to `t1` along `b`, its
    /// corners in the frame's order.
    pub(super) fn corners(&self, s0: f64, s1: f64, t0: f64, t1: f64) -> [[f64; 2]; 4] {
        [
            self.at(s0, t0),
            self.at(s1, t0),
            self.at(s1, t1),
            self.at(s0, t1),
        ]
    }

    /// The unit vector along axis `axis` (0: `a`, 1: `b`).
    pub(super) fn axis(&self, axis: usize) -> [f64; 2] {
        if axis == 0 { self.a } else { self.b }
    }

    /// The rectangle's length along axis `axis` (0: `la`, 1: `lb`).
    pub(super) fn len(&self, axis: usize) -> f64 {
        if axis == 0 { self.la } else { self.lb }
    }

    /// The outward normal of the side across axis `axis` (0: `a`, 1: `b`) at its `high`
    /// end (`s = la` or `t = lb`) or its low end (0).
    pub(super) fn outward(&self, axis: usize, high: bool) -> [f64; 2] {
        let dir = self.axis(axis);
        if high { dir } else { [-dir[0], -dir[1]] }
    }

    /// The middle of the side across axis `axis` at its `high` or low end, and that side's
    /// outward normal ([`RectFrame::outward`]).
    pub(super) fn side_middle(&self, axis: usize, high: bool) -> ([f64; 2], [f64; 2]) {
        let mid_other = self.len(1 - axis) / 2.0;
        let edge = if high { self.len(axis) } else { 0.0 };
        let mid = if axis == 1 {
            self.at(mid_other, edge)
        } else {
            self.at(edge, mid_other)
        };
        (mid, self.outward(axis, high))
    }
}

/// The middle of the rectangle `corners`: the mean of its corners.
pub(super) fn centre(corners: &[[f64; 2]; 4]) -> [f64; 2] {
    [0, 1].map(|k| corners.iter().map(|c| c[k]).sum::<f64>() / 4.0)
}

/// Each side `k` of the rectangle `corners` (from corner `k` to `k + 1`): its middle and
/// its outward unit normal, from the centre through the middle; `None` for a side whose
/// middle is the centre.
pub(super) fn side_middles(corners: &[[f64; 2]; 4]) -> [Option<([f64; 2], [f64; 2])>; 4] {
    let centre = centre(corners);
    std::array::from_fn(|k| {
        let (p, q) = (corners[k], corners[(k + 1) % 4]);
        let mid = [(p[0] + q[0]) / 2.0, (p[1] + q[1]) / 2.0];
        let away = sub(mid, centre);
        let n = away[0].hypot(away[1]);
        (n > 0.0).then(|| (mid, [away[0] / n, away[1] / n]))
    })
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
    let Some(frame) = RectFrame::new(corners) else {
        return 1.0;
    };
    let (la, lb) = (frame.la, frame.lb);
    let (mut n, mut out) = (0usize, 0usize);
    for p in points {
        let (s, t) = frame.local(p);
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

#[cfg(test)]
mod tests {
    use super::*;

    /// A 0.3 x 0.2 m rectangle turned by 30 degrees, away from the origin.
    fn turned() -> [[f64; 2]; 4] {
        let (c, s) = (30f64.to_radians().cos(), 30f64.to_radians().sin());
        let at = |u: f64, v: f64| [0.5 + c * u - s * v, -0.2 + s * u + c * v];
        [at(0.0, 0.0), at(0.3, 0.0), at(0.3, 0.2), at(0.0, 0.2)]
    }

    fn close(p: [f64; 2], q: [f64; 2]) -> bool {
        (p[0] - q[0]).abs() < 1e-12 && (p[1] - q[1]).abs() < 1e-12
    }

    #[test]
    fn frame_round_trips_and_rebuilds_its_corners() {
        let corners = turned();
        let f = RectFrame::new(&corners).expect("a rectangle");
        assert!((f.la - 0.3).abs() < 1e-12 && (f.lb - 0.2).abs() < 1e-12);
        let (s, t) = f.local(f.at(0.07, -0.04));
        assert!((s - 0.07).abs() < 1e-12 && (t + 0.04).abs() < 1e-12);
        let (s, t) = f.local(corners[2]);
        assert!((s - 0.3).abs() < 1e-12 && (t - 0.2).abs() < 1e-12);
        let back = f.corners(0.0, f.la, 0.0, f.lb);
        for k in 0..4 {
            assert!(close(back[k], corners[k]), "corner {k}: {:?}", back[k]);
        }
        // Outward normals point away from the middle.
        let m = centre(&corners);
        for axis in [0, 1] {
            for high in [false, true] {
                let mid = if axis == 0 {
                    f.at(if high { f.la } else { 0.0 }, f.lb / 2.0)
                } else {
                    f.at(f.la / 2.0, if high { f.lb } else { 0.0 })
                };
                assert!(dot(sub(mid, m), f.outward(axis, high)) > 0.0);
            }
        }
        let g = f.swapped();
        assert_eq!((g.la, g.lb, g.a, g.b), (f.lb, f.la, f.b, f.a));
        let (s, t) = g.local(corners[1]);
        assert!(s.abs() < 1e-12 && (t - 0.3).abs() < 1e-12);
    }

    #[test]
    fn degenerate_rectangles_have_no_frame() {
        let p = [1.0, 2.0];
        assert!(RectFrame::new(&[p, p, [1.5, 2.0], p]).is_none());
        assert!(RectFrame::new(&[p, [1.0, 2.5], [1.5, 2.5], p]).is_none());
        assert_eq!(share_outside(&[p; 4], [[1.0, 2.0]].into_iter(), 0.01), 1.0);
    }
}
