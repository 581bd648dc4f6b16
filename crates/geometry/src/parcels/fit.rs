//! One object measured: its top, its footprint, its shape.

use geo::{Area, Polygon};

use super::edges::{move_sides, noise_reach, pixel_offsets, refine, unblur, walls};
use super::height_map::{HeightMap, opened};
use super::rect::{CUBOID_OUTSIDE, OUTSIDE_M};
use super::rect::{RectFrame, centre, polygon, rect_area, share_outside};
use super::round;
use super::shape::{Object, Shape, ShapeFit, ShapeRule};
use super::shoulders::{BAND_MAX_M, shoulders};
use super::view::View;
use crate::Point3;
use crate::dimension::{
    DimensionConfig, DimensionError, Dimensions, Lid, hull, lid, rect_around, rect_dimensions,
    robust_height,
};

/// A cuboid's lid covers at least this share of its rectangle (a disc covers 0.785).
/// So do the lid's flattest points (see `flat_fit` in `fit`). Boxes of the lane set
/// (seeds 1 and 2, prepared and raw), dark and glossy ones too, read 0.983 to 1 (the
/// noise of their edges); a filled polybag's lid misses its lower, rounded corners and
/// reads 0.94 to 0.969, even a low, flat one whose shoulders hold too few points to
/// count as outside, or one whose lid band raw noise deepens down to its corners.
/// (The rectangle is where the lid's density puts its edges, see [`filled_within`].)
const CUBOID_FIT: f64 = 0.975;

/// A cuboid's lid is level: the median height of its middle (the inner 40 % of its
/// rectangle each way) and of its outer ring (60 to 85 % out) differ by at most this share
/// of the lid band. Boxes of the certification set's seed 1 (scenes 0-499) differ by at
/// most 0.1 of it; low polybags whose rounded corners their rectangle's edges cut off
/// (their lids then fill it) by 0.23 to 0.33, a full one higher in its middle, a sagging
/// one lower.
const LEVEL_SHARE: f64 = 0.15;

/// The shape rules, tried in this order on an object with one top: the first that
/// answers measures it. An object none answers is a cuboid when it passes the box test
/// ([`cuboid`]), else irregular ([`irregular`]), as is every object with more than one
/// top. A new shape is a module of its own with a [`ShapeRule`] and its line here.
const SHAPES: &[ShapeRule] = &[round::rule];

/// One object on the table, measured.
#[derive(Debug, Clone, PartialEq)]
pub struct ParcelFit {
    /// Its smallest enclosing cuboid.
    pub dimensions: Dimensions,
    /// Cuboid, round or irregular.
    pub shape: Shape,
    /// How well a cuboid fits: the share of the lid's rectangle (its edges where the lid's
    /// density puts them) that the lid's hull covers (1 for a box seen whole; a disc
    /// 0.785).
    pub fit: f64,
    /// Flat tops found on it: 1 for one parcel, 2 or more for parcels side by side.
    pub tops: usize,
    /// False when it touches another parcel: more than one top, or another object's
    /// outline within 20 mm.
    pub isolated: bool,
    /// The share of the footprint's cells that hold points (1 without holes).
    pub coverage: f64,
    /// Just beyond an edge, at the top's height, lies a point outside every camera's
    /// image, or behind another parcel from each camera that has it in its image; or a
    /// soft parcel's side faces away from every camera, which see it only over its top,
    /// and its foot may lie far beyond (see `shoulders`): more of the parcel may be
    /// there, unseen (only known with views).
    pub out_of_view: bool,
    /// Seen whole: in view, and coverage at least the configured minimum.
    pub complete: bool,
    /// No point came from it: a part of the table from which the cameras' pixels returned
    /// no depth at all (a parcel too dark or too shiny for the stereo match), its
    /// footprint where their rays meet the floor, its height 0 ([`ParcelFit::no_depth`]).
    pub no_depth: bool,
}

impl ParcelFit {
    /// A box measured as `dimensions` and seen whole and alone: a cuboid whose lid fills
    /// its rectangle, one top, isolated, every cell covered, in view, complete (what a
    /// fit of one box in clear view reads).
    pub fn whole_box(dimensions: Dimensions) -> Self {
        Self {
            dimensions,
            shape: Shape::Cuboid,
            fit: 1.0,
            tops: 1,
            isolated: true,
            coverage: 1.0,
            out_of_view: false,
            complete: true,
            no_depth: false,
        }
    }

    /// A part of the table that returned no depth, whose footprint `corners_m` (in order
    /// around its rectangle) is where the cameras' rays meet the floor: no points, no
    /// height, nothing covered, not complete.
    pub fn no_depth(corners_m: [[f64; 2]; 4]) -> Self {
        Self {
            dimensions: rect_dimensions(corners_m, 0.0, 0),
            shape: Shape::Irregular,
            fit: 0.0,
            tops: 0,
            isolated: true,
            coverage: 0.0,
            out_of_view: false,
            complete: false,
            no_depth: true,
        }
    }
}

/// Neighbouring cells of one top differ in height by less than this (metres), or by the
/// lid band when that is deeper.
pub(super) const TOP_STEP_M: f32 = 0.010;

/// A cell is flat (may belong to a top) when the middle half of its points spans less
/// than this (metres) or the lid band, whichever is more.
const FLAT_M: f32 = 0.004;

/// One plateau that holds at least this share of its object's dense cells reaches out
/// to its walls: a box's lid does (0.95-1 in the lane set, the rest its walls' cells);
/// a polybag's domed lid ends well inside its shoulders (0.54-0.78).
const PLATEAU_REACH: f64 = 0.9;

/// ... and leaves this share of its rectangle in notches cut in from its sides: not one
/// box. A box's ragged edges or a polybag's rounded corners leave a few per cent (no
/// single parcel of the lane set's 720 scenes reaches this); two boxes side by side in
/// an L or a step leave their missing corner (0.06 to 0.65 in its touching pairs).
const NOTCH_SHARE: f64 = 0.05;

/// ... and holds lid points in this share of the rest of its rectangle (a scatter of
/// flying pixels, whose lid is sparse, is no plateau).
const PLATEAU_SOLID: f64 = 0.8;

/// An object whose points, opened (see `height_map::opened`), have a rectangle of at
/// most this share of all its points' one holds lines of points reaching out from it
/// (see [`core_of`]).
const CORE_SHRINK: f64 = 0.9;

/// The object without lines of points reaching out from it, with its height and lid,
/// when its lid does not fill its rectangle (`CUBOID_FIT`) but the object's opened
/// points (see `height_map::opened`) have a rectangle at most [`CORE_SHRINK`] of its
/// own and a lid that does. A lower box beside a higher one holds such lines: single
/// rows of depth pixels that run on from its lid over the floor, and strips of the
/// higher box's side wall (lane set, 720 scenes: lower boxes of 223-287 mm read 427-754
/// mm long, their rectangles over the higher box's, and were dropped as its fragments;
/// where those lines held more than a hundredth of its points they set its height too).
fn core_of(
    cluster: &[Point3],
    lid_hull: &Polygon<f64>,
    config: &DimensionConfig,
) -> Option<(Vec<Point3>, f32, Lid, Polygon<f64>)> {
    let xy = |p: &Point3| [f64::from(p.x), f64::from(p.y)];
    let filled_hull = |hull: &Polygon<f64>| {
        rect_around(hull).map(|r| (hull.unsigned_area() / rect_area(&r), rect_area(&r)))
    };
    let filled = |points: &[Point3]| filled_hull(&hull(points.iter().map(xy)));
    if filled_hull(lid_hull)?.0 >= CUBOID_FIT {
        return None;
    }
    let core = opened(cluster);
    if core.len() < 3 || filled(&core)?.1 > CORE_SHRINK * filled(cluster)?.1 {
        return None;
    }
    let height_m = robust_height(&core, config);
    let mut lid = lid(&core, height_m, config).ok()?;
    lid.points = opened(&lid.points);
    let lid_hull = hull(lid.points.iter().map(xy));
    (lid.points.len() >= 3 && filled_hull(&lid_hull)?.0 >= CUBOID_FIT)
        .then_some((core, height_m, lid, lid_hull))
}

/// The share of the rectangle `rect` that the hull of `points` covers, each point moved to
/// the nearest place in the rectangle first: points beyond its edges add nothing but where
/// they lie along it. `None` for a degenerate rectangle.
fn filled_within(points: &[Point3], rect: &[[f64; 2]; 4]) -> Option<f64> {
    let frame = RectFrame::new(rect)?;
    let area = frame.la * frame.lb;
    let inside = hull(points.iter().map(|p| {
        let (s, t) = frame.local_point(p);
        [s.clamp(0.0, frame.la), t.clamp(0.0, frame.lb)]
    }));
    (area > 0.0).then(|| (inside.unsigned_area() / area).min(1.0))
}

/// How much higher the middle of `lid` (its points within the inner 40 % of the rectangle
/// `rect` each way) stands than its outer ring (60 to 85 % out), metres, by their medians;
/// `None` for a degenerate rectangle or a part without points.
fn middle_over_ring(lid: &[Point3], rect: &[[f64; 2]; 4]) -> Option<f64> {
    let frame = RectFrame::new(rect)?;
    let (mut middle, mut ring) = (Vec::new(), Vec::new());
    for p in lid {
        let (s, t) = frame.local_point(p);
        let out = (2.0 * s / frame.la - 1.0)
            .abs()
            .max((2.0 * t / frame.lb - 1.0).abs());
        if out < 0.4 {
            middle.push(p.z);
        } else if (0.6..0.85).contains(&out) {
            ring.push(p.z);
        }
    }
    let median = |v: &mut [f32]| {
        let mid = v.len() / 2;
        (!v.is_empty()).then(|| f64::from(*v.select_nth_unstable_by(mid, f32::total_cmp).1))
    };
    Some(median(&mut middle)? - median(&mut ring)?)
}

/// Measures one object.
pub(super) fn fit(
    cluster: &[Point3],
    config: &DimensionConfig,
    views: &[View],
) -> Result<ParcelFit, DimensionError> {
    let height_m = robust_height(cluster, config);
    let lid = lid(cluster, height_m, config)?;
    if lid.points.len() < 3 {
        return Err(DimensionError::Footprint);
    }
    // One hull of the lid, for its rectangle, its area and whether it fills it.
    let lid_hull = hull(lid.points.iter().map(|p| [f64::from(p.x), f64::from(p.y)]));
    match core_of(cluster, &lid_hull, config) {
        Some((core, height_m, lid, lid_hull)) => {
            measure(&core, height_m, (lid, lid_hull), config, views)
        }
        None => measure(cluster, height_m, (lid, lid_hull), config, views),
    }
}

/// Measures one object of the points `cluster`, its lid (and the lid's hull) at `height_m`.
fn measure(
    cluster: &[Point3],
    height_m: f32,
    (lid, lid_hull): (Lid, Polygon<f64>),
    config: &DimensionConfig,
    views: &[View],
) -> Result<ParcelFit, DimensionError> {
    let xy = |p: &Point3| [f64::from(p.x), f64::from(p.y)];
    let hull_rect = rect_around(&lid_hull).ok_or(DimensionError::Footprint)?;
    let margin = f64::from(lid.band_m) + 0.003;
    // The edges from the points within a quarter band (about one noise deviation, at
    // least 3 mm) of the top, on both sides, so that noise moves as many outwards as
    // inwards, and few of the points piled up on a side wall's top count.
    let slab = (lid.band_m / 4.0).max(0.003);
    let flat: Vec<Point3> = lid
        .points
        .iter()
        .filter(|p| (p.z - height_m).abs() <= slab)
        .copied()
        .collect();
    // Each point stands for its pixel's footprint: the edges lie where the points'
    // density says, up to half a pixel beyond the outermost point (where a camera's rows
    // run along an edge, the outermost row lies anywhere up to a pixel inside where the
    // density ends, half a pixel on average; further out, the density only says that the
    // lid thins towards its middle, as a glossy lid's glare does); then each edge moves
    // out by what its cameras' pixels hide there (see `pixel_offsets`), or to its wall
    // (see `walls`).
    let middle = centre(&hull_rect);
    let centre = Point3::new(middle[0] as f32, middle[1] as f32, height_m);
    let pixel = views
        .iter()
        .filter(|v| v.sees(&centre, 0.0))
        .map(|v| f64::from((v.to_common.translation - centre.coords).norm() / v.fx))
        .fold(0.0, f64::max);
    // Noise moves the outermost points out by a few deviations (the band is four) times
    // the tangent of the ray's angle: the edges move in no farther than that. (A low
    // parcel whose edge the spatial filter blurred into the floor keeps the hull's.) The
    // flat points moved at most `slab` up or down, so sideways at most `slab` times their
    // ray's slope across the side (see `noise_reach`): no edge lies farther in than that
    // from the outermost flat point. Holes never move a point out, but the patches a dark
    // lid loses thin the band beyond the density's line unevenly, and the density alone
    // pulled such edges in by up to 6 mm (seed 1, scene 20: 550 x 398 mm read 3.7 mm
    // short; the 720 scenes' scene 164, 5.8 mm).
    let inward = (0.75 * f64::from(lid.band_m)).max(0.0015);
    let noise = noise_reach(&hull_rect, height_m, slab, views).map(|r| r.unwrap_or(f64::INFINITY));
    let refined = refine(hull_rect, &flat, margin, (inward, noise), pixel / 2.0);
    let offsets = pixel_offsets(&refined, height_m, views);
    let walls = walls(&refined, cluster, height_m, views, pixel);
    let lid_rect = move_sides(
        refined,
        [0, 1, 2, 3].map(|k| walls[k].unwrap_or(offsets[k])),
    );
    let lid_area = lid_hull.unsigned_area();
    let fit = (lid_area / rect_area(&hull_rect)).min(1.0);
    // The same of the lid's flattest points (within a quarter band of the top): on a
    // box they are spread over the whole lid; on a domed or sagging top, where raw noise
    // deepens the band down to its rounded corners, only the plateau holds them.
    // (One hull for the rectangle and the area.)
    let flat_hull = hull(flat.iter().map(xy));
    let flat_fit = rect_around(&flat_hull).map_or(fit, |r| {
        (flat_hull.unsigned_area() / rect_area(&r)).min(1.0)
    });

    // Whether the lid fills its rectangle, judged within its edges as the lid's density
    // places them (at the outermost points' line, half a pixel inside `refined`): a few
    // points beyond a small lid's edge (the top of its wall within a deep band, seen
    // obliquely) widened its hull's rectangle by more than its lid fills (seed 1 of the
    // certification set, scenes 0-499: 20 boxes of 51 to 545 mm read 0.90 to 0.974, and
    // irregular; within their edges 0.979 to 1).
    let within = move_sides(refined, [-pixel / 2.0; 4]);
    let fill = filled_within(&lid.points, &within).unwrap_or(fit);
    let flat_fill = filled_within(&flat, &within).unwrap_or(flat_fit);
    let level = middle_over_ring(&lid.points, &within)
        .is_none_or(|rise| rise.abs() <= LEVEL_SHARE * f64::from(lid.band_m));
    let map = HeightMap::new(cluster);
    let dense = map.dense_points(cluster);
    let tops = map.tops(TOP_STEP_M.max(lid.band_m), FLAT_M.max(lid.band_m));
    let outside = share_outside(&lid_rect, dense.iter().map(xy), OUTSIDE_M);
    let object = Object {
        cluster,
        dense: &dense,
        map: &map,
        height_m,
        band_m: lid.band_m,
        flat: &flat,
        slab,
        lid_hull: &lid_hull,
        hull_rect,
        lid_rect,
        margin,
        inward,
        views,
        pixel,
        box_like: fill.min(flat_fill) >= CUBOID_FIT && level && outside <= CUBOID_OUTSIDE,
    };
    let ruled = if tops <= 1 {
        SHAPES.iter().find_map(|rule| rule(&object))
    } else {
        None
    };
    // One flat plateau that reaches out to the object's walls but leaves a notch cut
    // into its rectangle from a side: lids of boxes are rectangles, so this is most
    // likely two parcels of nearly the same height side by side (their lids joined
    // into one top), or an item no cuboid describes. A polybag's lid is a dome that
    // ends well inside its shoulders; a round lid is its rule's.
    let several = tops <= 1 && ruled.is_none() && !object.box_like && {
        let (reach, notch, solid) = map.plateau(&lid.points, &hull_rect);
        reach >= PLATEAU_REACH && notch >= NOTCH_SHARE && solid >= PLATEAU_SOLID
    };
    // Two lids side by side, their step blurred into one top (the lid band may hold
    // both): parcels side by side whatever the shape says (looked for only where
    // nothing has said so yet: the profile costs a pass over the height map).
    let seam = tops <= 1 && !several && map.seam(&hull_rect, height_m, FLAT_M.max(lid.band_m));
    let measured = match ruled {
        Some(measured) => measured,
        None if tops <= 1 && object.box_like => cuboid(&object, config.min_height_m),
        None => irregular(&object, fit.min(flat_fit)),
    };
    Ok(ParcelFit {
        dimensions: rect_dimensions(measured.footprint, f64::from(measured.top_m), cluster.len()),
        shape: measured.shape,
        fit: fill,
        tops: if seam { tops.max(2) } else { tops },
        isolated: tops <= 1 && !several && !seam,
        coverage: measured.coverage,
        out_of_view: measured.foot_unseen,
        complete: measured.coverage >= f64::from(config.min_coverage) && !measured.foot_unseen,
        no_depth: false,
    })
}

/// The cuboid fallback, for an object with one top that passes the box test: its lid's
/// rectangle with the sides the spatial filter sank or rounded moved out (see `unblur`),
/// its top the lid band's median, and it covers its footprint.
fn cuboid(object: &Object<'_>, min_height_m: f32) -> ShapeFit {
    let footprint = unblur(
        object.lid_rect,
        object.cluster,
        (object.height_m, object.slab),
        (object.views, object.pixel),
        min_height_m,
    );
    ShapeFit {
        shape: Shape::Cuboid,
        footprint,
        top_m: object.height_m,
        coverage: object.map.coverage(&polygon(&footprint)),
        foot_unseen: false,
    }
}

/// The irregular fallback: the rectangle around every dense point, each edge placed by
/// the points' density as a lid's is (the thin fringe of flying pixels around a tall
/// object counts little), and where the lid has rounded corners, a pillow's (`lid_fill`,
/// the lesser of the shares of their rectangles that the lid's hull and its flattest
/// points' hull fill, under [`CUBOID_FIT`]), its sides continued down to the floor (see
/// `shoulders`). Its top is its apex (the height map's `peak`, at least the lid's
/// height); it covers its dense points' hull.
fn irregular(object: &Object<'_>, lid_fill: f64) -> ShapeFit {
    let xy = |p: &Point3| [f64::from(p.x), f64::from(p.y)];
    let dense_hull = hull(object.dense.iter().map(xy));
    let around = rect_around(&dense_hull).map_or(object.hull_rect, |r| {
        refine(
            r,
            object.dense,
            object.margin.max(0.006),
            (0.003, [f64::INFINITY; 4]),
            0.0,
        )
    });
    let (footprint, band_m) = if lid_fill < CUBOID_FIT {
        shoulders(around, object.dense, object.height_m, object.views)
    } else {
        (around, 0.0)
    };
    ShapeFit {
        shape: Shape::Irregular,
        footprint,
        foot_unseen: band_m > BAND_MAX_M,
        top_m: object
            .map
            .peak()
            .map_or(object.height_m, |p| p.max(object.height_m)),
        coverage: object.map.coverage(&dense_hull),
    }
}
