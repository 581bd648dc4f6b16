//! A soft parcel's sides (a polybag's shoulders), continued to the floor.

use super::rect::{RectFrame, dot, sub};
use super::view::View;
use crate::Point3;

/// A soft side's profile is read in bins this wide across the edge (metres): two pixel
/// footprints at the farthest range a lane camera stands, so that no bin falls between
/// two rows of pixels.
const BIN_M: f64 = 0.004;

/// The profile is read from this far beyond the edge ...
const BEYOND_M: f64 = 0.020;

/// ... to this far inside it (metres), at most a third of the way across.
const INSIDE_M: f64 = 0.060;

/// The surface's point count per bin is the median of the bins of the inner half of the
/// profile; the seen surface ends before the first bin, going outwards from there, with
/// fewer than a fifth of it (beyond lie the few flying pixels between the side and the
/// floor, and a gap).
const SURFACE_SHARE: usize = 5;

/// The surface slopes down towards the edge (a shoulder) when its end lies lower than
/// the inner half of the profile by more than this (metres): a lid's edge does not.
const FALL_M: f32 = 0.005;

/// The widest band (metres, see [`shoulders`]) a side's foot may be placed in and still
/// be measured. A side that no camera sees down towards the floor (it faces away from
/// them all, seen only over the top by a camera far off) leaves a band as wide as the
/// grazing ray's run from where it is lost. Read off the certification set's seed 1
/// (scenes 0-499) with the limit at 60 mm: it refused 11 bags that had come out within
/// one division of an irregular item (10 mm), 9 of them with bands of 61 to 88 mm, and
/// the 13 bags it caught 16 to 57 mm off with no flag had bands of 87 to 334 mm (scene
/// 329: 33 mm off in a band of 233). A pillow seen from above leaves bands of 10 to 25
/// mm.
pub(super) const BAND_MAX_M: f64 = 0.09;

/// The rectangle `corners` with each edge where a soft parcel's side (a polybag's
/// shoulder) meets the floor. Seen from above, such a side curves down and away: a
/// camera's pixels fall ever farther apart on it as it steepens towards their rays (their
/// density is 1 - m t of a level top's, m its slope, t the rays' run over their fall),
/// until the rays graze it; of the last pixels before the floor a D415 keeps little (the
/// right imager cannot see them, or they straddle the depth step and fly). The seen
/// surface ends at a height `z` some millimetres inside the true edge, still sloping.
/// Below that the side cannot reach beyond the camera's grazing ray, which meets the
/// floor `z * t` farther out (t from the camera that looks down on the edge most
/// steeply); where in that band it stands upright is not seen. The side is taken as a
/// quarter ellipse, a filled pillow's section: level at the top's height `h`, upright on
/// the floor, along the grazing ray where the seen surface ends. Such an arc reaches
/// `c / (1 + c)` of the band farther out, c = sqrt(1 - (z / h)^2): half the band for a
/// side seen nearly down to the floor, less the higher up the camera loses it. An edge
/// whose surface arrives level (a lid) stays where it is. Without views the band is
/// unknown and the rectangle stays.
///
/// Also the widest of the bands (metres; a level edge's too, which stays where it is but
/// may have its foot anywhere in its band; 0 without views): where it exceeds
/// [`BAND_MAX_M`], the foot is not known.
pub(super) fn shoulders(
    corners: [[f64; 2]; 4],
    points: &[Point3],
    height_m: f32,
    views: &[View],
) -> ([[f64; 2]; 4], f64) {
    let Some(frame) = RectFrame::new(&corners).filter(|_| !views.is_empty()) else {
        return (corners, 0.0);
    };
    let (la, lb) = (frame.la, frame.lb);
    let local: Vec<(f64, f64, f32)> = points
        .iter()
        .map(|p| {
            let (s, t) = frame.local_point(p);
            (s, t, p.z)
        })
        .collect();
    let mut moved = [[0.0f64; 2]; 2];
    let mut widest = 0.0f64;
    for (axis, len, other_len) in [(0usize, la, lb), (1usize, lb, la)] {
        let inside_m = INSIDE_M.min(len / 3.0);
        let outer = (BEYOND_M / BIN_M).round() as usize;
        let bins = outer + (inside_m / BIN_M).floor() as usize;
        let half = outer + (bins - outer) / 2;
        if bins < outer + 4 {
            continue;
        }
        for side in [0usize, 1] {
            // Bin k holds the points from (k - outer) to (k - outer + 1) bins inside the
            // edge, in the middle of the edge (a pillow's corners are lower).
            let mut profile: Vec<Vec<f32>> = vec![Vec::new(); bins];
            for q in &local {
                let (along, across) = if axis == 0 { (q.0, q.1) } else { (q.1, q.0) };
                if across < 0.2 * other_len || across > 0.8 * other_len {
                    continue;
                }
                let depth = if side == 0 { along } else { len - along };
                let k = (depth / BIN_M).floor() + outer as f64;
                if k >= 0.0 && (k as usize) < bins {
                    profile[k as usize].push(q.2);
                }
            }
            let mut counts: Vec<usize> = profile[half..].iter().map(Vec::len).collect();
            let Some(reference) = median_usize(&mut counts) else {
                continue;
            };
            let mut inner: Vec<f32> = profile[half..].iter().flatten().copied().collect();
            let Some(z_inner) = median(&mut inner) else {
                continue;
            };
            // Outwards from the innermost bin: the last bin of the surface.
            let mut end = None;
            for k in (0..bins).rev() {
                if profile[k].len() * SURFACE_SHARE < reference || profile[k].is_empty() {
                    break;
                }
                end = Some(k);
            }
            let Some(end) = end else {
                continue;
            };
            let Some(z_end) = median(&mut profile[end]) else {
                continue;
            };
            // The upper quarter of the last bin: where an upright wall seen from outside
            // adds points below a lid's edge, the lid's edge still reads level.
            let Some(upper) = quantile(&mut profile[end], 0.75) else {
                continue;
            };
            if z_end <= 0.0 {
                continue;
            }
            // A surface that arrives level (a lid's edge) keeps its edge; its band still
            // counts: seen only over the top, such a side may fall anywhere below it.
            let level = z_inner - upper <= FALL_M;
            // Where the seen surface ends, inside the edge. The edge was placed by the
            // density of these points already, to a fraction of a bin, where the seen
            // surface reaching beyond it ends: a bin beyond it that still holds a fifth
            // of the surface's count (a low bag's foot, seen down to the floor) moved
            // such sides out by a whole bin (+4 mm; 720 scenes of seed 1, 536: +13 mm
            // across two sides).
            let depth = (end as f64 - outer as f64).max(0.0) * BIN_M;
            let mid_along = 0.5 * other_len;
            let at = if side == 0 { depth } else { len - depth };
            let (s, t) = if axis == 0 {
                (at, mid_along)
            } else {
                (mid_along, at)
            };
            let m = frame.at(s, t);
            let outward = frame.outward(axis, side == 1);
            let p = Point3::new(m[0] as f32, m[1] as f32, z_end);
            let run = views
                .iter()
                .filter(|v| v.sees(&p, 0.0))
                .filter_map(|v| {
                    let eye = v.to_common.translation;
                    let fall = f64::from(eye.z - z_end);
                    (fall > 0.0).then(|| {
                        let h = dot(sub(m, [f64::from(eye.x), f64::from(eye.y)]), outward);
                        h.max(0.0) / fall
                    })
                })
                .min_by(f64::total_cmp);
            if let Some(run) = run {
                let r = (f64::from(z_end) / f64::from(height_m)).clamp(0.0, 1.0);
                let c = (1.0 - r * r).sqrt();
                let band = f64::from(z_end) * run;
                widest = widest.max(band);
                if !level {
                    moved[axis][side] = -depth + c / (1.0 + c) * band;
                }
            }
        }
    }
    let (s0, s1) = (-moved[0][0], la + moved[0][1]);
    let (t0, t1) = (-moved[1][0], lb + moved[1][1]);
    (frame.corners(s0, s1, t0, t1), widest)
}

/// The median of `v` (reordered), `None` when empty.
fn median_usize(v: &mut [usize]) -> Option<usize> {
    if v.is_empty() {
        return None;
    }
    let mid = v.len() / 2;
    Some(*v.select_nth_unstable(mid).1)
}

/// The median of `v` (reordered), `None` when empty.
fn median(v: &mut [f32]) -> Option<f32> {
    quantile(v, 0.5)
}

/// The `q` quantile (0 to 1) of `v` (reordered), `None` when empty.
fn quantile(v: &mut [f32], q: f64) -> Option<f32> {
    if v.is_empty() {
        return None;
    }
    let at = ((v.len() - 1) as f64 * q).round() as usize;
    Some(*v.select_nth_unstable_by(at, f32::total_cmp).1)
}
