//! Round parcels: a tube lying on the floor, a cylinder standing on it. Its shape rule is
//! [`rule`].

use geo::{Area, Coord, LineString, Polygon};

use super::rect::{CUBOID_OUTSIDE, OUTSIDE_M};
use super::rect::{RectFrame, polygon, sub};
use super::shape::{Object, Shape, ShapeFit};
use super::view::View;
use crate::Point3;

/// The round shape rule: a tube lying on the floor, or else, when the object fails the box
/// test, a standing cylinder (a lid that passes as a box is a box).
///
/// A lying tube's lid strip fills its rectangle, and with a deep lid band nothing reaches
/// beyond it: its curved top tells it from a box. Its footprint is the lid strip along
/// its axis (the strip runs the tube's whole length at its top; the flying pixels beyond
/// its round ends lie lower) and the circle across it; its top the circle's, where the
/// noise is averaged over the whole section; it covers the strip where its circle was seen
/// (a raw camera's floor noise joined to it is no hole in it).
///
/// A standing cylinder's lid is a disc with nothing of the object beyond it: its footprint
/// the square around the disc (grown by half a pixel, as a box's edges are), its top the
/// lid band's median, as a box's, and it covers its disc.
pub(super) fn rule(object: &Object<'_>) -> Option<ShapeFit> {
    if let Some(tube) = lying_tube(
        &object.lid_rect,
        (object.dense, object.cluster),
        object.height_m,
        object.band_m,
    ) {
        return Some(ShapeFit {
            shape: Shape::Round,
            footprint: tube.footprint(&object.lid_rect),
            top_m: (2.0 * tube.radius) as f32,
            coverage: object.map.coverage(&polygon(&tube.seen(&object.lid_rect))),
            foot_unseen: false,
        });
    }
    if object.box_like {
        return None;
    }
    let disc = standing_disc(
        (&object.hull_rect, object.lid_hull),
        object.flat,
        object.dense,
        (object.margin, object.inward),
        &DiscView {
            views: object.views,
            pixel: object.pixel,
            height_m: f64::from(object.height_m),
            band_m: f64::from(object.band_m),
        },
    )?
    .grown(object.pixel / 2.0);
    Some(ShapeFit {
        shape: Shape::Round,
        footprint: disc.footprint(&object.hull_rect),
        top_m: object.height_m,
        coverage: object.map.coverage(&disc.polygon()),
        foot_unseen: false,
    })
}

/// A tube lying on the floor: its cross-section, in the frame of the lid's rectangle.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(super) struct LyingTube {
    /// Whether the axis runs along the rectangle's first edge (corner 0 to 1).
    along_first: bool,
    /// The axis's position across the rectangle, from corner 0, metres.
    centre: f64,
    /// The radius, metres: the tube rests on the floor, so its top is at twice this.
    pub(super) radius: f64,
    /// Along the axis, from corner 0, where its ends lie, metres: the lid strip's, or
    /// beyond them as far as its crest runs ([`crest_ends`]).
    pub(super) ends: [f64; 2],
    /// Across the rectangle, from corner 0, where the circle's points lie, metres: a
    /// tilted camera sees the near flank, the crest and the far side only until it
    /// turns away.
    seen: [f64; 2],
}

impl LyingTube {
    /// The part of the footprint the cameras see the tube over: the lid's rectangle
    /// along the axis, across it where the circle's points lie. (Beyond the far side's
    /// turn no camera above sees anything, hole or not.)
    fn seen(&self, rect: &[[f64; 2]; 4]) -> [[f64; 2]; 4] {
        self.across(rect, self.seen)
    }

    /// The footprint: its ends along the axis, the circle's diameter across.
    fn footprint(&self, rect: &[[f64; 2]; 4]) -> [[f64; 2]; 4] {
        self.across(rect, [self.centre - self.radius, self.centre + self.radius])
    }

    /// Its ends along the axis of the lid's rectangle `rect`, from `t[0]` to `t[1]`
    /// across it.
    fn across(&self, rect: &[[f64; 2]; 4], t: [f64; 2]) -> [[f64; 2]; 4] {
        let Some(frame) = RectFrame::new(rect) else {
            return *rect;
        };
        let frame = if self.along_first {
            frame
        } else {
            frame.swapped()
        };
        frame.corners(self.ends[0], self.ends[1], t[0], t[1])
    }
}

/// A standing cylinder's lid.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Disc {
    centre: [f64; 2],
    radius: f64,
}

impl Disc {
    fn grown(self, by: f64) -> Self {
        Self {
            radius: self.radius + by,
            ..self
        }
    }

    /// The square around it, along the rectangle `rect`'s edges.
    fn footprint(&self, rect: &[[f64; 2]; 4]) -> [[f64; 2]; 4] {
        let e = sub(rect[1], rect[0]);
        let n = e[0].hypot(e[1]);
        let a = if n > 0.0 {
            [e[0] / n, e[1] / n]
        } else {
            [1.0, 0.0]
        };
        let b = [-a[1], a[0]];
        let r = self.radius;
        let at = |s: f64, t: f64| {
            [
                self.centre[0] + a[0] * s + b[0] * t,
                self.centre[1] + a[1] * s + b[1] * t,
            ]
        };
        [at(-r, -r), at(r, -r), at(r, r), at(-r, r)]
    }

    /// The disc as a polygon of 64 sides.
    fn polygon(&self) -> Polygon<f64> {
        let ring: Vec<Coord<f64>> = (0..64)
            .map(|k| {
                let a = f64::from(k) * std::f64::consts::TAU / 64.0;
                Coord {
                    x: self.centre[0] + self.radius * a.cos(),
                    y: self.centre[1] + self.radius * a.sin(),
                }
            })
            .collect();
        Polygon::new(LineString::from(ring), Vec::new())
    }
}

/// A disc's lid hull fills this share of its rectangle at least (pi / 4 = 0.785; a
/// square lid 1, a lying tube's strip about 0.99) ...
const DISC_FIT: [f64; 2] = [0.72, 0.86];

/// ... its hull's corners lie this close to one circle (share of the radius, at least
/// [`DISC_ROUND_M`]), besides what the cameras' pixels and noise put there
/// ([`DISC_ROLL_PX`], and the lid band's noise along the rays) ...
const DISC_ROUND: f64 = 0.04;

/// See [`DISC_ROUND`], metres.
const DISC_ROUND_M: f64 = 0.004;

/// ... and the pixels of the lid's rim, of which the spatial filter rolls this many (at
/// the camera's range) into a side wall that a camera sees beside it: the lid ends that
/// much short on the walls' side and reaches the rim elsewhere. Cylinders of 30-200 mm
/// radius under one to three D415s 1-2.2 m up, tilted up to 45 degrees (199 of them):
/// their hull's corners lie within 1.2 pixels and the noise's reach beyond the first two
/// terms around the circle through them, up to 8.1 mm apart in all (a cylinder of 123 mm radius,
/// 369 mm high, under a camera 2.15 m up tilted 7 degrees: its lid ended 8 mm short on
/// the camera's side).
const DISC_ROLL_PX: f64 = 2.5;

/// The centre and radius of the circle nearest to `points` (the algebraic least-squares
/// fit), `None` for fewer than three or points on a line.
fn circle_through(points: &[[f64; 2]]) -> Option<([f64; 2], f64)> {
    if points.len() < 3 {
        return None;
    }
    let n = points.len() as f64;
    let (mx, my) = points
        .iter()
        .fold((0.0, 0.0), |(x, y), p| (x + p[0] / n, y + p[1] / n));
    let (mut suu, mut suv, mut svv, mut b1, mut b2) = (0.0, 0.0, 0.0, 0.0, 0.0);
    for p in points {
        let (u, v) = (p[0] - mx, p[1] - my);
        suu += u * u;
        suv += u * v;
        svv += v * v;
        b1 += 0.5 * u * (u * u + v * v);
        b2 += 0.5 * v * (u * u + v * v);
    }
    let det = suu * svv - suv * suv;
    if det.abs() < 1e-18 {
        return None;
    }
    let (uc, vc) = ((b1 * svv - b2 * suv) / det, (suu * b2 - suv * b1) / det);
    let radius = (uc * uc + vc * vc + (suu + svv) / n).sqrt();
    radius.is_finite().then_some(([mx + uc, my + vc], radius))
}

/// How the cameras see a disc: the size of a pixel on it, and the lid band's noise
/// (`band_m` deep) along their rays, sideways at its rim (metres; see
/// `super::edges::noise_reach`).
#[derive(Debug, Clone, Copy, PartialEq)]
struct DiscView<'a> {
    /// The cameras.
    views: &'a [View],
    /// A pixel's size at the lid, metres (0 without cameras).
    pixel: f64,
    /// The lid's height and its band's depth, metres.
    height_m: f64,
    /// See `height_m`.
    band_m: f64,
}

impl DiscView<'_> {
    /// How far the lid band's noise can move a point on the rim of the disc at `centre`
    /// of `radius` sideways: the band's depth times the slope of the steepest ray to its
    /// far side.
    fn reach(&self, centre: [f64; 2], radius: f64) -> f64 {
        self.views
            .iter()
            .filter_map(|v| {
                let eye = v.to_common.translation;
                let rise = f64::from(eye.z) - self.height_m;
                let out = (f64::from(eye.x) - centre[0]).hypot(f64::from(eye.y) - centre[1]);
                (rise > 0.0).then(|| self.band_m * (out + radius) / rise)
            })
            .fold(0.0, f64::max)
    }
}

/// Whether the lid (its points' convex `hull`, its rectangle `rect`) is a disc with
/// nothing of the object beyond it (a standing cylinder), and its radius. The disc's
/// centre is that of the circle nearest the hull's corners, which lie within
/// [`DISC_ROUND`] of it and what the cameras' pixels and noise can have moved them
/// (`seen`: the lid band's noise along the rays, [`DISC_ROLL_PX`] pixels). The radius is
/// placed as a box's edges are ([`super::edges::edges`]), in rings instead of strips:
/// depth noise moves the lid's points sideways without adding or losing any, so the edge
/// lies where the `flat` points beyond a circle `margin` inside the outermost ones, at the
/// density of the ring just inside it, would end; each 1 mm ring counts at most 1.5 times
/// that density (the top of the side wall seen from the side is no lid). Where the disc's
/// rectangle was placed by strips, a disc thins towards each extreme as a square root, and
/// the strip count put its edges about 3 mm inside: cylinders came out 3.5-6.7 mm narrow.
fn standing_disc(
    (rect, hull): (&[[f64; 2]; 4], &Polygon<f64>),
    flat: &[Point3],
    dense: &[Point3],
    (margin, inward): (f64, f64),
    seen: &DiscView<'_>,
) -> Option<Disc> {
    let RectFrame { la, lb, .. } = RectFrame::new(rect)?;
    if la.max(lb) > 1.1 * la.min(lb) {
        return None;
    }
    let fit = hull.unsigned_area() / (la * lb);
    if !(DISC_FIT[0]..=DISC_FIT[1]).contains(&fit) {
        return None;
    }
    // The ring is closed: its first corner comes again at its end.
    let mut corners: Vec<[f64; 2]> = hull.exterior().coords().map(|c| [c.x, c.y]).collect();
    corners.pop();
    let (centre, _) = circle_through(&corners)?;
    let radii: Vec<f64> = corners
        .iter()
        .map(|c| (c[0] - centre[0]).hypot(c[1] - centre[1]))
        .collect();
    let outer = radii.iter().copied().fold(0.0, f64::max);
    let inner = radii.iter().copied().fold(f64::MAX, f64::min);
    let round = (DISC_ROUND * outer).max(DISC_ROUND_M)
        + DISC_ROLL_PX * seen.pixel
        + seen.reach(centre, outer);
    if outer - inner > round {
        return None;
    }
    let reach = |p: &Point3| (f64::from(p.x) - centre[0]).hypot(f64::from(p.y) - centre[1]);
    // Nothing of the object beyond the lid (as of a cuboid).
    let beyond = dense
        .iter()
        .filter(|p| reach(p) > outer + OUTSIDE_M)
        .count();
    if beyond as f64 > CUBOID_OUTSIDE * dense.len() as f64 {
        return None;
    }
    const BIN_M: f64 = 0.001;
    let window = (2.0 * margin).max(0.01);
    let line = outer - margin;
    if line - window <= 0.0 {
        return None;
    }
    let r: Vec<f64> = flat.iter().map(reach).collect();
    let ring = |lo: f64, hi: f64| std::f64::consts::PI * (hi * hi - lo * lo);
    let inside = r
        .iter()
        .filter(|v| **v >= line - window && **v < line)
        .count();
    if inside == 0 {
        return None;
    }
    let density = inside as f64 / ring(line - window, line);
    let mut bins = vec![0usize; (margin / BIN_M).ceil() as usize + 1];
    for v in &r {
        if *v >= line {
            let k = ((v - line) / BIN_M) as usize;
            if let Some(b) = bins.get_mut(k) {
                *b += 1;
            }
        }
    }
    let mass: f64 = bins
        .iter()
        .enumerate()
        .map(|(k, n)| {
            let lo = line + k as f64 * BIN_M;
            (*n as f64).min(1.5 * density * ring(lo, lo + BIN_M))
        })
        .sum();
    let radius = (line * line + mass / (std::f64::consts::PI * density)).sqrt();
    Some(Disc {
        centre,
        radius: radius.clamp(outer - inward.min(margin), outer),
    })
}

/// Profile points used for the circle (a sample is as good and keeps this cheap).
const TUBE_SAMPLE: usize = 4000;

/// The circle's residuals may reach this (metres) or a quarter of the lid band (about one
/// depth-noise deviation), whichever is more: a box's edges or a bag's flat top miss
/// a circle resting on the floor by centimetres.
const TUBE_RMS_M: f64 = 0.002;

/// Of a tube, the points above half its height (inliers of the circle) span at least this
/// share of its diameter across the axis. A camera whose rays meet the tube at θ from
/// the vertical sees its upper half from the near side to where the far side turns away,
/// (1 + cos θ) / 2 of the diameter: 0.85 at 45 degrees, 0.79 at the 55 degrees such a
/// camera's rays reach off-centre; the flying-pixel stage drops the last grazing pixels
/// before that turn (rgbd round variant 49: 224 mm long, r 84 mm, one camera 2.04 m up
/// tilted 44 degrees, 0.755).
const TUBE_SPAN: f64 = 0.7;

/// Of a tube, at most this share of its dense points lies more than [`OUTSIDE_M`] beyond
/// its lid strip's ends (lane sets: lying tubes 0 to 0.2 %, flying pixels off their
/// ends; a tall polybag whose cross-section is round, 18 %: its rounded ends).
const TUBE_BEYOND_SHARE: f64 = 0.02;

/// Whether the object is a tube lying on the floor (a cylinder with a horizontal axis along
/// the lid rectangle `rect`'s long side): the dense points above half its height, across
/// the middle of its length (away from the round ends' flying pixels), lie on a circle
/// that rests on the floor (centre at the radius's height) and whose top is the
/// object's height, and nothing of it lies beyond the ends of its lid strip (a bag as
/// high as it is wide has a round section too, but its top curves down to rounded ends
/// beyond the strip: polybag scene 644 of the 720, 349 mm long, read as a tube 248 mm
/// long). Depth noise moves each point along its ray by about a quarter of the
/// lid band, so the circle fits to that; the height read from the top band is a median
/// of the strip below the crest (about a quarter of the band low on a circle), the
/// circle's top is not. Its ends are where its crest ends ([`crest_ends`], of all the
/// object's points, `cluster`), which may lie beyond the lid strip's.
pub(super) fn lying_tube(
    rect: &[[f64; 2]; 4],
    (dense, cluster): (&[Point3], &[Point3]),
    height_m: f32,
    band_m: f32,
) -> Option<LyingTube> {
    // The frame along the long side.
    let frame = RectFrame::new(rect)?;
    let along_first = frame.la >= frame.lb;
    let frame = if along_first { frame } else { frame.swapped() };
    let len = frame.la;
    let height = f64::from(height_m);
    let profile: Vec<[f64; 2]> = dense
        .iter()
        .filter_map(|p| {
            let (s, t) = frame.local_point(p);
            (s >= 0.2 * len && s <= 0.8 * len && f64::from(p.z) >= height / 2.0)
                .then(|| [t, f64::from(p.z)])
        })
        .collect();
    let step = (profile.len() / TUBE_SAMPLE).max(1);
    let profile: Vec<[f64; 2]> = profile.into_iter().step_by(step).collect();
    if profile.len() < 50 {
        return None;
    }
    // Start at the crest: the middle of the points near the top, half the height.
    let crest: Vec<f64> = profile
        .iter()
        .filter(|q| q[1] >= height - f64::from(band_m))
        .map(|q| q[0])
        .collect();
    if crest.is_empty() {
        return None;
    }
    let mut centre = crest.iter().sum::<f64>() / crest.len() as f64;
    let mut radius = height / 2.0;
    let residual = |q: &[f64; 2], c: f64, r: f64| (q[0] - c).hypot(q[1] - r) - r;
    // Gauss-Newton on (centre, radius), three rounds, each after the first on the points
    // within three robust deviations (at least 2 mm) of the last round's circle.
    let mut keep = f64::INFINITY;
    for _ in 0..3 {
        for _ in 0..10 {
            let (mut h00, mut h01, mut h11, mut g0, mut g1) = (0.0, 0.0, 0.0, 0.0, 0.0);
            for q in &profile {
                let (dt, dz) = (q[0] - centre, q[1] - radius);
                let rho = dt.hypot(dz).max(1e-9);
                let r = rho - radius;
                if r.abs() > keep {
                    continue;
                }
                let (j0, j1) = (-dt / rho, -dz / rho - 1.0);
                h00 += j0 * j0;
                h01 += j0 * j1;
                h11 += j1 * j1;
                g0 += j0 * r;
                g1 += j1 * r;
            }
            let det = h00 * h11 - h01 * h01;
            if det.abs() < 1e-18 {
                return None;
            }
            centre -= (h11 * g0 - h01 * g1) / det;
            radius -= (h00 * g1 - h01 * g0) / det;
            if !(radius > 0.005 && radius.is_finite()) {
                return None;
            }
        }
        let mut spread: Vec<f64> = profile
            .iter()
            .map(|q| residual(q, centre, radius).abs())
            .collect();
        let mid = spread.len() / 2;
        let mad = *spread.select_nth_unstable_by(mid, f64::total_cmp).1;
        keep = (3.0 * 1.4826 * mad).max(0.002);
    }
    let inliers: Vec<&[f64; 2]> = profile
        .iter()
        .filter(|q| residual(q, centre, radius).abs() <= keep)
        .collect();
    let rms = (inliers
        .iter()
        .map(|q| residual(q, centre, radius).powi(2))
        .sum::<f64>()
        / inliers.len().max(1) as f64)
        .sqrt();
    let (lo, hi) = inliers.iter().fold((f64::MAX, f64::MIN), |(lo, hi), q| {
        (lo.min(q[0]), hi.max(q[0]))
    });
    let round = inliers.len() as f64 >= 0.9 * profile.len() as f64
        && rms <= TUBE_RMS_M.max(f64::from(band_m) / 4.0)
        && hi - lo >= TUBE_SPAN * 2.0 * radius
        && (2.0 * radius - height).abs() <= (0.05 * height).max(0.006);
    if !round {
        return None;
    }
    let ends = crest_ends(&frame, cluster, centre, radius, band_m);
    // A tube's crest runs its whole length and its ends are upright discs: beyond its
    // ends only a few flying pixels stay dense. A bag's top curves down along its length
    // as across it, and its rounded ends lie beyond the strip.
    let beyond = dense
        .iter()
        .filter(|p| {
            let (s, _) = frame.local_point(p);
            s < ends[0] - OUTSIDE_M || s > ends[1] + OUTSIDE_M
        })
        .count() as f64
        / dense.len().max(1) as f64;
    (beyond <= TUBE_BEYOND_SHARE).then_some(LyingTube {
        along_first,
        centre,
        radius,
        ends,
        seen: [lo, hi],
    })
}

/// A tube's crest runs on beyond its lid strip's end by more than this (metres) before
/// the end moves out to it: within it, the strip's edges (placed by the points' density
/// and the cameras' pixels) say where the end is better than the outermost crest points.
const CREST_BEYOND_M: f64 = 0.01;

/// Crest points further apart along the axis than this (metres) are not one crest.
const CREST_GAP_M: f64 = 0.01;

/// Along the axis of `frame` (the tube's), where the crest of a tube whose axis lies
/// `centre` across it and whose radius is `radius` ends on each side: the lid strip's ends
/// (0 and the frame's length), or, where the crest runs on beyond one by more than
/// [`CREST_BEYOND_M`] without a gap of [`CREST_GAP_M`], its last points there (the fifth
/// from the end: a stray point is no crest). The crest is the points of `cluster` within a
/// quarter radius of the axis and within half the lid band (at least 4 mm) of its top.
///
/// The lid keeps the points with enough others near them, by the merged cloud's typical
/// spacing; the end of a tube that only one camera sees, from afar or at a grazing
/// angle, holds its points at a fraction of that density and drops out of the lid, and the
/// strip ends short of the tube (certification set, seed 1, scene 256: a tube 340 mm long
/// under four cameras, its far end seen by one at an eighth of the density, read 269 mm
/// long and round). Its crest there is at the tube's full height, where no flying pixel
/// off an end lies farther out than the depth noise moves it.
fn crest_ends(
    frame: &RectFrame,
    cluster: &[Point3],
    centre: f64,
    radius: f64,
    band_m: f32,
) -> [f64; 2] {
    const STRAY: usize = 4;
    let top = 2.0 * radius;
    let depth = (f64::from(band_m) / 2.0).max(0.004);
    let mut along: Vec<f64> = cluster
        .iter()
        .filter_map(|p| {
            let (s, t) = frame.local_point(p);
            ((t - centre).abs() <= radius / 4.0 && f64::from(p.z) >= top - depth).then_some(s)
        })
        .collect();
    along.sort_unstable_by(f64::total_cmp);
    let len = frame.la;
    if along.len() <= 2 * STRAY {
        return [0.0, len];
    }
    // From inside the strip's end outwards, as far as the crest runs without a gap.
    let run = |points: &mut dyn Iterator<Item = f64>, from: f64| -> Vec<f64> {
        let mut last = from;
        points
            .take_while(|s| {
                let joined = (s - last).abs() <= CREST_GAP_M;
                last = *s;
                joined
            })
            .collect()
    };
    let low = run(&mut along.iter().rev().copied().filter(|s| *s < 0.0), 0.0);
    let high = run(&mut along.iter().copied().filter(|s| *s > len), len);
    let reach = |run: &[f64]| run.len().checked_sub(STRAY + 1).map(|k| run[k]);
    let low = reach(&low).filter(|s| *s < -CREST_BEYOND_M).unwrap_or(0.0);
    let high = reach(&high)
        .filter(|s| *s > len + CREST_BEYOND_M)
        .unwrap_or(len);
    [low, high]
}
