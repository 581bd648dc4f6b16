//! Where a lid's edges lie: placed by the lid points' density, then moved out by what the
//! cameras' pixels, the side walls and the spatial filter's blur say.

use super::rect::{RectFrame, centre, dot, side_middles, sub};
use super::view::View;
use crate::Point3;

/// The stretch (metres) inside an edge over which [`edges`] takes the lid's density, at
/// least: a camera's points lie in rows a pixel apart (1-2 mm at 1-2 m), and a window
/// of 1 cm holds one row more or less (10-20 %) depending on where the rows fall; over
/// 2 cm that is half as much, and the density still is the edge's where it changes
/// across the lid (a glossy lid loses more depth near its middle, where the projector
/// glares: windows of 3-5 cm read the edges of glossy boxes 1-2 mm out).
const DENSITY_WINDOW_M: f64 = 0.02;

/// An edge whose outward normal is more than this cosine away from a camera's x axis
/// (towards its right imager), negatively, lies wholly in that camera's stereo shadow.
const SHADOW_COS: f64 = 0.25;

/// How far from a side of the lid's rectangle [`walls`] looks for its wall's points
/// (metres): the lid's density places the side within about 2 mm; the flying pixels
/// beyond a side seen from the other side lie centimetres out.
const WALL_REACH_M: f64 = 0.006;

/// The distance between a stereo camera's imagers (metres): a D415's 55 mm (a D435's is
/// 50 mm); it sets how wide the stereo shadow beside a parcel is.
const STEREO_BASELINE_M: f64 = 0.055;

/// The rectangle `corners` (in order around it) with each edge moved to where `lid`'s
/// points put it (see [`edges`]): at most `inward` inside the rectangle's and `beyond`
/// outside it, and side `k` (from corner `k` to `k + 1`) at most `noise[k]` inside the
/// outermost of `lid`'s points.
pub(super) fn refine(
    corners: [[f64; 2]; 4],
    lid: &[Point3],
    margin: f64,
    (inward, noise): (f64, [f64; 4]),
    beyond: f64,
) -> [[f64; 2]; 4] {
    let Some(frame) = RectFrame::new(&corners) else {
        return corners;
    };
    let mut sa = Vec::with_capacity(lid.len());
    let mut sb = Vec::with_capacity(lid.len());
    for p in lid {
        let (s, t) = frame.local_point(p);
        sa.push(s);
        sb.push(t);
    }
    // Side 3 lies at s = 0, side 1 at s = la; side 0 at t = 0, side 2 at t = lb.
    let (a0, a1) = edges(
        &sa,
        frame.la,
        margin,
        (inward, [noise[3], noise[1]]),
        beyond,
    );
    let (b0, b1) = edges(
        &sb,
        frame.lb,
        margin,
        (inward, [noise[0], noise[2]]),
        beyond,
    );
    frame.corners(a0, a1, b0, b1)
}

/// How far (metres) the outermost of the lid's points within `slab` of its height
/// `height_m` can lie beyond each side of the rectangle `corners` (side `k` from corner
/// `k` to `k + 1`) by their noise alone: depth noise moves a point along its camera's ray,
/// and a point kept within `slab` of the lid moved at most `slab` up or down, so at most
/// `slab` times the ray's slope across the side sideways (the slope is the same all
/// along a side of a level lid). The largest over the cameras that see the side's middle;
/// `None` for a side no camera sees.
pub(super) fn noise_reach(
    corners: &[[f64; 2]; 4],
    height_m: f32,
    slab: f32,
    views: &[View],
) -> [Option<f64>; 4] {
    let mut out = [None; 4];
    for (reach, side) in out.iter_mut().zip(side_middles(corners)) {
        let Some((mid, normal)) = side else {
            continue;
        };
        let at = Point3::new(mid[0] as f32, mid[1] as f32, height_m);
        for v in views.iter().filter(|v| v.sees(&at, 0.0)) {
            let eye = v.to_common.translation;
            let rise = f64::from(eye.z - height_m);
            if rise <= 0.0 {
                continue;
            }
            let d = [mid[0] - f64::from(eye.x), mid[1] - f64::from(eye.y)];
            let sideways = f64::from(slab) * dot(d, normal).abs() / rise;
            *reach = Some(reach.map_or(sideways, |r: f64| r.max(sideways)));
        }
    }
    out
}

/// The two edges along one axis of positions `s` in about [0, `len`]. From a line
/// `margin` inside each end, the points beyond it are counted in 1 mm bins, each bin
/// at most 1.5 times the density of the band just inside the line; the edge lies where that
/// many points at that density would end. Noise moves points about an edge without
/// adding any, so the count keeps the edge where the outermost points do not; the cap
/// keeps points piled up on the edge itself (the top of a side wall seen from the side)
/// from counting as lid. The density is taken over up to [`DENSITY_WINDOW_M`] inside
/// the line: a camera's points lie in rows a pixel apart, and a short window holds one
/// row more or less depending on where the rows fall. An axis too short for two such
/// bands keeps the hull's edges. An edge lies at most `inward` inside its end of
/// [0, `len`] and `beyond` outside it, and the low edge at most `noise[0]` inside the
/// outermost point of `s`, the high one `noise[1]` (what noise can have moved that point
/// out: holes never move a point out, but they thin the band beyond the line unevenly).
pub(super) fn edges(
    s: &[f64],
    len: f64,
    margin: f64,
    (inward, noise): (f64, [f64; 2]),
    beyond: f64,
) -> (f64, f64) {
    const BIN_M: f64 = 0.001;
    let shortest = (2.0 * margin).max(0.01);
    let window = (len / 2.0 - margin).min(shortest.max(DENSITY_WINDOW_M));
    if window < shortest {
        return (0.0, len);
    }
    // Only the points near the ends are counted: sort those.
    let reach = margin + window;
    let mut near: Vec<f64> = s
        .iter()
        .copied()
        .filter(|v| *v <= reach || *v >= len - reach)
        .collect();
    near.sort_unstable_by(f64::total_cmp);
    let count =
        |lo: f64, hi: f64| near.partition_point(|v| *v < hi) - near.partition_point(|v| *v < lo);
    // The edge moves at most `inward` (and `margin`) inwards (holes along an edge thin
    // it), and at most `beyond` past the outermost point.
    let limit = margin + beyond;
    let place = |line: f64, outwards: f64, noise: f64| {
        let outermost = if outwards > 0.0 {
            near.last().map(|v| v - line)
        } else {
            near.first().map(|v| line - v)
        };
        let least = (margin - inward)
            .max(outermost.map_or(0.0, |o| o - noise))
            .clamp(0.0, limit);
        let (a, b) = if outwards > 0.0 {
            (line - window, line)
        } else {
            (line, line + window)
        };
        let inside = count(a, b);
        if inside == 0 {
            return line + outwards * margin;
        }
        let density = inside as f64 / window;
        let cap = 1.5 * density * BIN_M;
        let mut mass = 0.0;
        let mut at = 0.0;
        while at < margin {
            let (x0, x1) = (line + outwards * at, line + outwards * (at + BIN_M));
            mass += (count(x0.min(x1), x0.max(x1)) as f64).min(cap);
            at += BIN_M;
        }
        line + outwards * (mass / density).clamp(least, limit)
    };
    (
        place(margin, -1.0, noise[0]),
        place(len - margin, 1.0, noise[1]),
    )
}

/// How far each side of the lid's rectangle `corners` (side `k` from corner `k` to
/// `k + 1`) lies beyond where its points' density ends, metres, from the cameras that
/// see it. A pixel across the edge sees the lid and the floor and reads a depth between
/// them, off the lid: the lid's points end half a pixel's footprint (across the edge)
/// inside it. Not so on the side away from a camera's right imager: the floor beside it
/// there is hidden from the right imager (the stereo shadow), so the pixel across the
/// edge matches the lid alone and reads the lid's depth. The cameras are weighted by
/// their points' density there.
pub(super) fn pixel_offsets(corners: &[[f64; 2]; 4], height_m: f32, views: &[View]) -> [f64; 4] {
    let mut out = [0.0; 4];
    for (offset, side) in out.iter_mut().zip(side_middles(corners)) {
        let Some((mid, normal)) = side else {
            continue;
        };
        let at = Point3::new(mid[0] as f32, mid[1] as f32, height_m);
        let (mut sum, mut weights) = (0.0, 0.0);
        for v in views {
            let Some(footprint) = v.footprint(&at) else {
                continue;
            };
            let [du, dv] = footprint;
            let across = dot(du, normal).abs() + dot(dv, normal).abs();
            let area = (du[0] * dv[1] - du[1] * dv[0]).abs();
            if across <= 0.0 || area <= 0.0 {
                continue;
            }
            // The camera's x axis (towards its right imager) on the floor.
            let x = v.to_common.linear.column(0);
            let (xx, xy) = (f64::from(x.x), f64::from(x.y));
            let xn = xx.hypot(xy);
            let facing = if xn > 0.0 {
                dot([xx / xn, xy / xn], normal)
            } else {
                0.0
            };
            // The shadow spans fx B (1 / lid depth - 1 / floor depth) pixels along x:
            // several beside a parcel over about 5 cm high, less than the pixel across
            // the edge beside a lower one. It hides the floor across the edge unless the
            // edge runs almost along x.
            let eye = v.to_common.translation;
            let lid_m = f64::from((eye - at.coords).norm());
            let floor_m = f64::from((eye - nalgebra::Vector3::new(at.x, at.y, 0.0)).norm());
            let shadow_px = f64::from(v.fx) * STEREO_BASELINE_M * (1.0 / lid_m - 1.0 / floor_m);
            let shadowed = (-facing / SHADOW_COS).clamp(0.0, 1.0) * shadow_px.clamp(0.0, 1.0);
            sum += (1.0 - shadowed) * across / 2.0 / area;
            weights += 1.0 / area;
        }
        if weights > 0.0 {
            *offset = sum / weights;
        }
    }
    out
}

/// Where the side walls under the sides of the lid's rectangle `corners` (side `k` from
/// corner `k` to `k + 1`) stand, as how far each lies outside its side (metres), for
/// the sides whose wall a camera sees from outside: the median position across the side
/// of the points on the wall's middle half (from a quarter to three quarters of the
/// `height_m`), within [`WALL_REACH_M`] of the side and 1 cm in from its ends. A
/// camera beyond a side sees the wall join the lid with no step in depth, and the
/// spatial filter rounds that corner: the lid's last pixels sink below its top and its
/// points end 1-2 mm short (the demo's oblique cameras; parcels apart, off the axis of
/// a camera between them), while the wall's middle, flat and seen whole, is where the
/// side is. `None` for a side whose wall has fewer points than two per pixel of its
/// length (none seen, or seen edge-on), or without cameras.
pub(super) fn walls(
    corners: &[[f64; 2]; 4],
    cluster: &[Point3],
    height_m: f32,
    views: &[View],
    pixel: f64,
) -> [Option<f64>; 4] {
    let mut out = [None; 4];
    if pixel <= 0.0 {
        return out;
    }
    let centre = centre(corners);
    let (low, high) = (0.25 * height_m, 0.75 * height_m);
    let wall: Vec<[f64; 2]> = cluster
        .iter()
        .filter(|p| p.z >= low && p.z <= high)
        .map(|p| [f64::from(p.x), f64::from(p.y)])
        .collect();
    for (k, found) in out.iter_mut().enumerate() {
        let (p, q) = (corners[k], corners[(k + 1) % 4]);
        let along = sub(q, p);
        let span = along[0].hypot(along[1]);
        if span <= 0.02 {
            continue;
        }
        let dir = [along[0] / span, along[1] / span];
        let mut normal = [dir[1], -dir[0]];
        if dot(sub(p, centre), normal) < 0.0 {
            normal = [-normal[0], -normal[1]];
        }
        let line = dot(p, normal);
        let mid = [(p[0] + q[0]) / 2.0, (p[1] + q[1]) / 2.0];
        let middle = Point3::new(mid[0] as f32, mid[1] as f32, height_m / 2.0);
        let seen = views.iter().any(|v| {
            let eye = v.to_common.translation;
            dot([f64::from(eye.x), f64::from(eye.y)], normal) > line && v.sees(&middle, 0.0)
        });
        if !seen {
            continue;
        }
        let mut across: Vec<f64> = wall
            .iter()
            .filter(|w| {
                let t = dot(sub(**w, p), dir);
                t >= 0.01 && t <= span - 0.01
            })
            .map(|w| dot(*w, normal) - line)
            .filter(|d| d.abs() <= WALL_REACH_M)
            .collect();
        if (across.len() as f64) < 2.0 * span / pixel {
            continue;
        }
        let mid = across.len() / 2;
        let (_, median, _) = across.select_nth_unstable_by(mid, f64::total_cmp);
        *found = Some(*median);
    }
    out
}

/// The rectangle `corners` (in order around it) with side `k` (from corner `k` to
/// `k + 1`) moved out by `by[k]`.
pub(super) fn move_sides(corners: [[f64; 2]; 4], by: [f64; 4]) -> [[f64; 2]; 4] {
    let Some(frame) = RectFrame::new(&corners) else {
        return corners;
    };
    // Side 0 lies at t = 0, side 1 at s = la, side 2 at t = lb, side 3 at s = 0.
    frame.corners(-by[3], frame.la + by[1], -by[0], frame.lb + by[2])
}

/// How far beyond a side [`unblur`] counts at most (metres): a 60 cm parcel's edge
/// pixels reading half its height land up to 8 cm out on a ray at 15 degrees.
const COUNT_REACH_M: f64 = 0.08;

/// How far [`unblur`] moves a side out at most (metres): the blur of a low lid puts its
/// points' end 8-10 mm inside the step.
const COUNT_MOVE_M: f64 = 0.03;

/// The lid rectangle `rect` of a parcel `height_m` high whose sides were placed from the
/// points within `slab_m` of its top, each side moved out to where the pixels that see
/// the lid end where those pixels sank out of the slab.
///
/// A pixel whose centre sees the lid reads nearer the lid than the floor, above half the
/// height, however the spatial filter moved its depth. The filter (an edge-preserving
/// moving average along rows and columns, both ways) smooths a step lower than its
/// threshold (20/32 pixel of disparity: a lid lower than about 3 to 4.5 cm from 1.5 to 2
/// m up) into the floor symmetrically, so the pixels on the lid's side of the step stay
/// above half of it (a 37 mm lid's points ended 5-7 mm short of one such side). Where the
/// pixel across an edge (mostly lid, its depth between lid and floor) reads within the
/// threshold of the lid, the filter drags the lid's last pixels down towards it, 7-20 mm
/// over 5-10 mm, out of the slab (a 75 mm box's side ended 5 mm short); the step beyond
/// it stays. The pixels are counted where their points land (a pixel's point moves along
/// its ray with its depth): in bins two pixels wide from a line inside the side out to
/// where a point of the edge reading half the height lands on the steepest camera's ray
/// (at most [`COUNT_REACH_M`]) and [`COUNT_MOVE_M`] beyond, each bin at most 1.5 times
/// the density of the lid's first 2 cm inside that line (two bins in from the side: a
/// glossy lid's glare thins it towards the middle); they end where that many points at
/// that density would. The same count of the slab's points ends where the side was
/// placed; when all of them end at least a pixel beyond that, the lid sank there and the
/// side moves out (only out: the pixel across the edge of a lid taller than twice the
/// cluster radius hangs too far below it to be in its cluster, so the count can fall a
/// pixel short). A side a camera sees from outside (its wall's upper half reads above half
/// the height too) goes where the blur's crossing of half the height puts it
/// ([`blur_crossing`]); the sides of lids too low for half their height to clear the
/// floor cut by 3 mm (the points between are cut) or too short across stay.
pub(super) fn unblur(
    rect: [[f64; 2]; 4],
    cluster: &[Point3],
    (height_m, slab_m): (f32, f32),
    (views, pixel_m): (&[View], f64),
    min_height_m: f32,
) -> [[f64; 2]; 4] {
    const INSET_M: f64 = 0.02;
    // Two pixels a bin, and the density over whole bins: where a camera's rows run
    // along a side, each bin holds two rows wherever they fall (without views, 2.5 mm).
    let bin_m = if pixel_m > 0.0 { 2.0 * pixel_m } else { 0.0025 };
    // The density over about 2 cm of whole bins (without views the points' rows may
    // alias with the bins), the count from two bins farther in.
    let reference = (DENSITY_WINDOW_M / bin_m).round().max(2.0);
    let from_m = (reference + 2.0) * bin_m;
    let half = height_m / 2.0;
    // Half the height must clear the floor cut for the lid's pixels to be told apart.
    if half < min_height_m + 0.003 {
        return rect;
    }
    let Some(frame) = RectFrame::new(&rect) else {
        return rect;
    };
    let (la, lb) = (frame.la, frame.lb);
    let shortest = 2.0 * INSET_M.max(from_m);
    if la <= shortest || lb <= shortest {
        return rect;
    }
    // The points in the rectangle's frame, once: the counts take those nearer the lid
    // than the floor, the blur's crossing all of them. Neither looks farther in from a
    // side than its first bin begins: the lid's middle is left out (a millimetre more
    // kept, for the rounding of the bins' arithmetic).
    let ring = from_m.max(crossing_bins(pixel_m).1) + 0.001;
    let near_side = |v: f64, len: f64| v <= ring || v >= len - ring;
    let local: Vec<(f64, f64, f32)> = cluster
        .iter()
        .filter_map(|p| {
            let (s, t) = frame.local_point(p);
            (near_side(s, la) || near_side(t, lb)).then_some((s, t, p.z))
        })
        .collect();
    // How far beyond the side the lid's pixels end (negative: inside), counted out to
    // `reach_m` beyond it: all of them (nearer the lid than the floor), and those within
    // the slab of the top that placed the side.
    let count = |along_b: bool, high: bool, reach_m: f64| -> Option<(f64, f64)> {
        let (len, other) = if along_b { (lb, la) } else { (la, lb) };
        let bins = ((from_m + reach_m) / bin_m).ceil() as usize;
        let mut all = vec![0usize; bins.max(reference as usize)];
        let mut flat = all.clone();
        for &(s, t, z) in &local {
            let (across, along) = if along_b { (t, s) } else { (s, t) };
            if z <= half || along < INSET_M || along > other - INSET_M {
                continue;
            }
            let level = z >= height_m - slab_m;
            let out = if high { across - len } else { -across } + from_m;
            let k = (out / bin_m) as usize;
            if out >= 0.0 && k < all.len() {
                all[k] += 1;
                if level {
                    flat[k] += 1;
                }
            }
        }
        let end = |per_bin: &[usize]| -> Option<f64> {
            let full = per_bin[..reference as usize].iter().sum::<usize>() as f64 / reference;
            let mass: f64 = per_bin.iter().map(|&n| (n as f64).min(1.5 * full)).sum();
            (full > 0.0).then(|| mass / full * bin_m - from_m)
        };
        Some((end(&all)?, end(&flat)?))
    };
    // How far out the cameras that have the side's middle in view put a point of the
    // lid's edge that reads half the height (its ray's outward run over half the
    // height); `None` when one of them stands beyond the side, or when none has it in
    // view (without a camera's ray a sunk lid's pixels cannot be told from the upper
    // half of a wall seen from outside).
    let reach = |mid: [f64; 2], outward: [f64; 2]| -> Option<f64> {
        let p = Point3::new(mid[0] as f32, mid[1] as f32, height_m);
        let mut most = None;
        for v in views.iter().filter(|v| v.sees(&p, 0.0)) {
            let eye = v.to_common.translation;
            let run = dot(sub(mid, [f64::from(eye.x), f64::from(eye.y)]), outward);
            if run < 0.0 {
                return None;
            }
            let rise = f64::from(eye.z - height_m).max(1e-3);
            let r = f64::from(half) * run / rise;
            most = Some(most.map_or(r, |m: f64| m.max(r)));
        }
        most
    };
    // A side a camera sees from outside (or that no camera has in view) keeps where the
    // blur's crossing of half the height puts it: its wall's upper half reads above half
    // the height too (found when a side needs it).
    let crossed = std::cell::OnceCell::new();
    let crossed = || {
        *crossed.get_or_init(|| {
            let c = blur_crossing(&frame, &local, height_m, (views, pixel_m));
            (frame.local(c[0]), frame.local(c[2]))
        })
    };
    let mut lo = [0.0, 0.0];
    let mut hi = [la, lb];
    for axis in [0, 1] {
        let along_b = axis == 1;
        let len = frame.len(axis);
        for high in [false, true] {
            let (mid, outward) = frame.side_middle(axis, high);
            let Some(r) = reach(mid, outward) else {
                let (c_lo, c_hi) = crossed();
                let (l, h) = if axis == 0 {
                    (c_lo.0, c_hi.0)
                } else {
                    (c_lo.1, c_hi.1)
                };
                if high {
                    hi[axis] = h;
                } else {
                    lo[axis] = l;
                }
                continue;
            };
            let Some((moved, level)) = count(along_b, high, r.min(COUNT_REACH_M) + COUNT_MOVE_M)
            else {
                continue;
            };
            // Nothing sank here (or no more than the pixel across the edge): the slab's
            // edge stands.
            if moved - level < pixel_m.max(0.001) {
                continue;
            }
            let moved = moved.clamp(0.0, COUNT_MOVE_M);
            if high {
                hi[axis] = len + moved;
            } else {
                lo[axis] = -moved;
            }
        }
    }
    frame.corners(lo[0], hi[0], lo[1], hi[1])
}

/// [`blur_crossing`]'s bins: their width, two pixels and at least 2.5 mm (so that rows
/// of pixels do not alias), and how far inside the edge the first begins (two bins, at
/// least 8 mm), metres.
fn crossing_bins(pixel_m: f64) -> (f64, f64) {
    let bin_m = (2.0 * pixel_m).max(0.0025);
    (bin_m, (2.0 * bin_m).max(0.008))
}

/// (For the sides [`unblur`] leaves: those a camera sees from outside, or that none has
/// in view.) The lid rectangle of `frame` (`local`: the parcel's points in that frame,
/// with their heights) of a parcel `height_m` high with each edge that the spatial
/// filter blurred into the floor moved out to where the blur says the step was.
///
/// The filter (an edge-preserving moving average over neighbouring pixels, run both ways
/// along rows and columns) leaves a step alone only where the disparity changes by more
/// than its threshold (20/32 pixel by default): from 1.5 to 2 m up, a lid lower than
/// about 3 to 4.5 cm is smoothed into the floor, and its points fall below the lid band
/// well inside the edge (scene 64: a 35 mm lid ended 8-10 mm short on each blurred side).
/// The smoothing is symmetric, so across the blur the depth passes half the step at the
/// pixel where the step was; that pixel's ray met the lid's edge and, for an edge facing
/// away from the camera, reaches half the height `height / 2 x tan(angle)` farther out.
/// An edge is moved when, outwards from 8 mm inside it, every bin (two pixels wide, at
/// least 2.5 mm, so that rows of pixels do not alias) holds points (at least a quarter of
/// the lid's density) on one surface (the middle half of their heights within a quarter
/// of the height: not a side wall, nor flying pixels spread over the height) down to a
/// bin below half the height (or, where the floor cut emptied the bins beyond, down to
/// one below three quarters of it). Edges that end sharply (a tall step, the stereo
/// shadow's holes) stay as they are; so do (in [`unblur`]) lids too low for half their
/// height to clear the floor cut by 3 mm, and rectangles too short across.
///
/// An edge that every camera seeing it sees from outside is where the points on the
/// middle half of the height stand (their median across the edge), if they are at least
/// a quarter of a bin's lid points: such a camera sees the lid, the wall and the floor
/// beyond as one surface with no step in depth (a wall of 6-16 cm seen 10-20 cm beyond
/// it takes 2-9 pixels, under the filter's threshold each), so the filter rounds the
/// lid's corner into the wall and its last 3-4 pixels sink out of the lid's band (the
/// lane set's 720 scenes: boxes 64-156 mm high apart from another, 4.2-6.4 mm short).
/// The wall is upright and the rounding symmetric about its middle, so the middle half
/// of the height (the wall's, or the rounded ramp's middle) stands at the edge; those
/// points span the wall's height within a bin, which the one-surface test would refuse.
fn blur_crossing(
    frame: &RectFrame,
    local: &[(f64, f64, f32)],
    height_m: f32,
    (views, pixel_m): (&[View], f64),
) -> [[f64; 2]; 4] {
    const REACH_M: f64 = 0.03;
    const INSET_M: f64 = 0.02;
    let (bin_m, from_m) = crossing_bins(pixel_m);
    let half = height_m / 2.0;
    let (la, lb) = (frame.la, frame.lb);
    let bins = ((from_m + REACH_M) / bin_m).round() as usize;
    // Where, outwards of the edge, the blurred step passes half the height (`wall_seen`:
    // every camera that sees the edge sees its wall from outside).
    let crossing = |along_b: bool, high: bool, wall_seen: bool| -> Option<f64> {
        let (len, other) = if along_b { (lb, la) } else { (la, lb) };
        let mut z: Vec<Vec<f32>> = vec![Vec::new(); bins];
        let mut sum = vec![0.0f64; bins];
        let mut middle = Vec::new();
        for &(s, t, pz) in local {
            let (across, along) = if along_b { (t, s) } else { (s, t) };
            if along < INSET_M || along > other - INSET_M {
                continue;
            }
            let out = if high { across - len } else { -across };
            let k = ((out + from_m) / bin_m).floor();
            if k >= 0.0 && (k as usize) < bins {
                z[k as usize].push(pz);
                sum[k as usize] += out;
                if pz >= 0.25 * height_m && pz <= 0.75 * height_m {
                    middle.push(out);
                }
            }
        }
        let inside = 2;
        let density = z[..inside].iter().map(Vec::len).sum::<usize>() as f64 / inside as f64;
        // The wall's middle half stands at the edge (and so does a rounded ramp's).
        if wall_seen {
            if (middle.len() as f64) < (0.25 * density).max(3.0) {
                return None;
            }
            let mid = middle.len() / 2;
            let (_, median, _) = middle.select_nth_unstable_by(mid, f64::total_cmp);
            return Some(*median);
        }
        // (centre, median) of the bins at or above half the height.
        let mut last: Vec<(f64, f32)> = Vec::new();
        for (k, bin) in z.iter_mut().enumerate() {
            // Where the bin's points lie on average (rows of pixels fill bins unevenly).
            let centre = sum[k] / bin.len().max(1) as f64;
            if (bin.len() as f64) < 0.25 * density || bin.len() < 3 {
                return match last[..] {
                    // The floor cut may empty the bins beyond one well down the ramp:
                    // the line through the last two bins then meets half the height
                    // within a bin.
                    [.., (c0, m0), (c1, m1)] if m1 < 0.75 * height_m && m1 < m0 => {
                        let t = f64::from(m1 - half) / f64::from(m0 - m1);
                        (t <= 1.0).then_some(c1 + t * (c1 - c0))
                    }
                    _ => None,
                };
            }
            bin.sort_unstable_by(f32::total_cmp);
            let n = bin.len();
            let (q1, median, q3) = (bin[n / 4], bin[n / 2], bin[(3 * n) / 4]);
            if q3 - q1 > height_m / 4.0 {
                return None;
            }
            if median < half {
                let &(c, m) = last.last()?;
                let t = f64::from(m - half) / f64::from(m - median).max(1e-6);
                return Some(c + t * (centre - c));
            }
            last.push((centre, median));
        }
        None
    };
    // Half the height times the outward tangent of the rays of the cameras that see the
    // edge (0 for a camera beyond the edge: it sees the side wall, whose middle is at
    // the edge), and whether every camera that sees the edge stands beyond it.
    let reach = |mid: [f64; 2], outward: [f64; 2]| -> (f64, bool) {
        let p = Point3::new(mid[0] as f32, mid[1] as f32, height_m);
        let slopes: Vec<f64> = views
            .iter()
            .filter(|v| v.sees(&p, 0.0))
            .map(|v| {
                let eye = v.to_common.translation;
                let rise = f64::from(eye.z - height_m).max(1e-3);
                let d = [mid[0] - f64::from(eye.x), mid[1] - f64::from(eye.y)];
                dot(d, outward) / rise
            })
            .collect();
        if slopes.is_empty() {
            (0.0, false)
        } else {
            let mean = slopes.iter().map(|s| s.max(0.0)).sum::<f64>() / slopes.len() as f64;
            (f64::from(half) * mean, slopes.iter().all(|s| *s < 0.0))
        }
    };
    let mut lo = [0.0, 0.0];
    let mut hi = [la, lb];
    for axis in [0, 1] {
        let along_b = axis == 1;
        let len = frame.len(axis);
        for high in [false, true] {
            let (mid, outward) = frame.side_middle(axis, high);
            let (back, wall_seen) = reach(mid, outward);
            let Some(c) = crossing(along_b, high, wall_seen) else {
                continue;
            };
            let moved = (c - back).clamp(0.0, REACH_M);
            if high {
                hi[axis] = len + moved;
            } else {
                lo[axis] = -moved;
            }
        }
    }
    frame.corners(lo[0], hi[0], lo[1], hi[1])
}
