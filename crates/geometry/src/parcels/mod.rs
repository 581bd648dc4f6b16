//! Every parcel on the table (docs/design.md §6): the objects standing on the floor, each
//! measured as the smallest cuboid that encloses it, with how well a cuboid fits, whether
//! it touches another parcel and whether the data show all of it.
//!
//! Fragments of a larger object go (a ring of flying pixels, a sliver of wall, and with
//! the cameras known a sheet of flying pixels on the rays through its edge, parted from
//! it by holes).
//!
//! Per object (a cluster of [`crate::dimension()`]'s grid):
//! - the top: the lid band below a robust maximum of z, as [`crate::dimension()`] has always
//!   taken it;
//! - the footprint of a cuboid: the minimum-area rectangle around the lid gives the
//!   directions; each of its four edges is then placed where the lid's points say, not
//!   where the outermost one lies. Depth noise moves a point along its camera ray, so a
//!   lid point off the camera's axis also moves sideways (by the depth error times the
//!   tangent of the ray's angle); the outermost point of hundreds along an edge is the one
//!   that moved outwards most, and a hull grows by about three noise deviations on every
//!   side, more the farther the edge is from the axis: large boxes came out too big. The
//!   points are not lost, only moved, so the edge lies where the lid's points beyond a line
//!   well inside it, at the density just inside that line, would end (mass conservation);
//! - the shape: a cuboid when the lid fills its rectangle and nothing of the object
//!   reaches beyond it; otherwise `irregular`, measured as the minimum-area rectangle
//!   around all its dense points (OIML R 129: the smallest enclosing box); where such an
//!   object's lid has rounded corners (a polybag), each side that still slopes down
//!   where the cameras lose it is continued to the floor within the band the cameras'
//!   grazing rays leave unseen (see `shoulders`); an irregular object's height is the
//!   apex of its top (the highest mean of a 15 mm patch of the height map), where a
//!   band's median lies below a domed top. A tube lying on the floor is irregular too,
//!   though its top strip fills a rectangle: across the strip its points lie on a circle
//!   resting on the floor, whose diameter is its width and height, and the strip gives
//!   its length (the flying pixels off its round ends lie below it);
//! - tops: flat regions of a height map of the object, connected where neighbouring cells
//!   differ by less than a step; two large ones mean two parcels side by side, and so
//!   does one flat top that reaches out to the object's walls but leaves a notch in its
//!   rectangle (an L or a step: the lids of two boxes of nearly one height), and so
//!   does a seam: two level lids a step apart that the spatial filter blurred into one
//!   top;
//! - an object whose lid does not fill its rectangle but whose opened cells (thin lines
//!   of points reaching out of it left out) have a lid that does is measured from those
//!   (a lower box beside a higher one, with flying pixels along the higher one's side);
//! - coverage: the share of cells inside the footprint that hold points (holes from dark
//!   or shiny surfaces lower it); with camera views, whether every top corner is inside
//!   some camera's image.

mod edges;
mod fit;
mod height_map;
mod rect;
mod round;
mod shape;
mod shoulders;
mod split;
mod view;

use std::collections::HashMap;

use foldhash::fast::FixedState;
use geo::{Area, Distance as _, Euclidean, Intersects as _, Polygon};

use crate::dimension::{DimensionConfig, DimensionError, Dimensions, above_floor, clusters, hull};
use crate::{Point3, PointCloud};

pub use fit::ParcelFit;
use fit::fit;
use height_map::Cell2;
use rect::{OUTSIDE_M, RectFrame, centre, polygon, share_outside, sub};
pub use shape::Shape;
pub use view::{View, hidden_bounds, hidden_share};

/// Objects with fewer points than this share of the largest one's are not parcels
/// (fragments of flying pixels, specks).
const MIN_SHARE: f64 = 0.005;

/// Parcels whose outlines (see [`outline`]) come closer than this (metres) are side by
/// side: one leans on the other, or nothing was seen between them. Certified
/// dimensioners state a spacing of 20 mm (Datalogic DM3610, Hikrobot); parcels that far
/// apart are measured each. Their outlines are measured, each edge within a division or
/// so of the truth, so the threshold lies half that spacing below it: at 20 mm, pairs 20
/// mm apart read 14-19 mm and were refused (cert scenes 58 and 84). A lower parcel that a
/// taller one hides in part is told by the views ([`probes`]), not by this.
const TOUCH_M: f64 = 0.01;

/// An object with fewer points than this share of a larger one's, whose footprint comes
/// within [`FRAGMENT_M`] of the larger one's, is a fragment of it (a sliver of a side
/// wall, flying pixels between its edge and the floor), not a parcel (see
/// [`fragment_of`]).
const FRAGMENT_SHARE: f64 = 0.01;

/// See [`FRAGMENT_SHARE`] (metres): the certified spacing, as far as flying pixels off an
/// edge reach.
const FRAGMENT_M: f64 = 0.02;

/// An object whose footprint and a larger one's overlap by at least this share of the
/// smaller footprint is a ring of flying pixels or floor speckle around it (see
/// [`fragment_of`]); parcels side by side overlap by the few millimetres of noise on
/// their edges, a share of a few per cent.
const OVERLAP_SHARE: f64 = 0.2;

/// Of an object of flying pixels off a parcel's edge (see [`curtain_of`]), at least this
/// share lies on rays through that edge: the 720-scene set's dark boxes parted from
/// theirs by holes, sheets 0.1-2 mm thick, up to 12 cm high and as long as the edge.
const CURTAIN_SHARE: f64 = 0.9;

/// ... within this many pixels of the edge (the pixel across it, and the next) ...
const CURTAIN_PX: f64 = 2.0;

/// ... and this far besides (metres): where the lid's outline was placed, give or take.
const CURTAIN_M: f64 = 0.003;

/// Side of the columns in which the floor's speckle is told from a parcel (metres; see
/// [`without_speckle`]).
const SPECKLE_CELL_M: f64 = 0.01;

/// In a column of the floor, the points just above the floor cut are speckle when they
/// are fewer than this share of the column's points near the floor (raw scene 15, 1.8 m
/// up: speckle columns hold 2-9 %, median 4 %).
const SPECKLE_SHARE: f64 = 0.25;

/// How far beyond a parcel's edges, at its top's height, some camera must see past every
/// other parcel (metres) for it to be whole. An edge is placed by the lid's density, some
/// millimetres inside its last pixels, so a point a division (5 mm) past it may still be
/// in sight where a taller neighbour hides the rest of the lid: a lower box touching a
/// taller one under one camera then read 11-22 mm short with no flag (`bench accuracy
/// --set lane --scenes 720`, 4 scenes).
const PROBE_M: f64 = 0.015;

/// How far beyond a parcel's edges, at its top's height, that camera's image must reach
/// (metres): a division. Nothing but the image's border hides the lid there, and the
/// border cuts the lid's last pixels themselves, so the edge then lies at the border and
/// a point a division past it is out of the image. Asking [`PROBE_M`] of the image too
/// refused tall boxes under one camera whose edges the image holds (certification set,
/// seed 295841469: 4 of 15 false refusals).
const PROBE_IMAGE_M: f64 = 0.005;

/// A top corner counts as seen when it projects at least this far inside an image.
const VIEW_MARGIN_PX: f32 = 3.0;

/// What [`parcels`] found.
#[derive(Debug, Clone, PartialEq)]
pub struct Parcels {
    /// The objects with enough points, the largest footprint first.
    pub parcels: Vec<ParcelFit>,
    /// Points of the largest object above the floor (0 when there is none).
    pub largest_points: usize,
}

/// Measures the largest object standing on the floor of `cloud` (output frame: z up,
/// floor at z = 0, metres): the first of [`parcels()`] without camera views.
pub fn dimension(
    cloud: &PointCloud,
    config: &DimensionConfig,
) -> Result<Dimensions, DimensionError> {
    let found = parcels(cloud, config, &[])?;
    Ok(found
        .parcels
        .into_iter()
        .next()
        .ok_or(DimensionError::TooFewPoints {
            found: found.largest_points,
            needed: config.min_points,
        })?
        .dimensions)
}

/// Measures every object standing on the floor of `cloud` (output frame: z up, floor at
/// z = 0, metres). `views` are the cameras the cloud came from, if known: a parcel with a
/// top corner outside all of them is not complete.
pub fn parcels(
    cloud: &PointCloud,
    config: &DimensionConfig,
    views: &[View],
) -> Result<Parcels, DimensionError> {
    config.validate()?;
    let above = without_speckle(cloud, above_floor(cloud, config), config);
    let clusters = clusters(&above, config.cluster_radius_m)?;
    let largest_points = clusters.first().map_or(0, Vec::len);
    let needed = config
        .min_points
        .max((largest_points as f64 * MIN_SHARE).ceil() as usize);
    let mut fits = Vec::new();
    let mut objects: Vec<Vec<Point3>> = Vec::new();
    let mut first_error = None;
    for cluster in clusters.into_iter().take_while(|c| c.len() >= needed) {
        let fitted = fit(&cluster, config, views);
        // Parcels side by side may be parcels apart that flying pixels joined: each
        // part whose dense columns stand apart is measured on its own.
        let parts = match &fitted {
            Ok(f) if !f.isolated => split::apart(&cluster),
            _ => None,
        };
        let measured = match parts {
            Some(parts) => parts
                .into_iter()
                .filter(|p| p.len() >= needed)
                .map(|p| (fit(&p, config, views), p))
                .collect(),
            None => vec![(fitted, cluster)],
        };
        for (fitted, points) in measured {
            match fitted {
                Ok(f) => {
                    fits.push(f);
                    objects.push(points);
                }
                Err(e) => {
                    first_error.get_or_insert(e);
                }
            }
        }
    }
    let found: Vec<(ParcelFit, &[Point3])> = fits
        .into_iter()
        .zip(objects.iter().map(|o| &o[..]))
        .collect();
    if found.is_empty()
        && let Some(e) = first_error
    {
        return Err(e);
    }
    let kept = without_fragments(found, views);
    // Pieces of one top that holes cut apart (a dark lid returns depth in patches) are one
    // object: those that each miss much of their top and touch are measured together.
    let groups = pieces(&kept);
    let unions: Vec<Vec<Point3>> = groups
        .iter()
        .map(|g| g.iter().flat_map(|&i| kept[i].1.iter().copied()).collect())
        .collect();
    let joined: Vec<Option<ParcelFit>> =
        unions.iter().map(|u| fit(u, config, views).ok()).collect();
    let joined_any = joined.iter().any(Option::is_some);
    let gone: Vec<usize> = groups
        .iter()
        .zip(&joined)
        .filter(|(_, f)| f.is_some())
        .flat_map(|(g, _)| g.iter().copied())
        .collect();
    let kept: Vec<(ParcelFit, &[Point3])> = kept
        .into_iter()
        .enumerate()
        .filter(|(i, _)| !gone.contains(i))
        .map(|(_, k)| k)
        .chain(
            joined
                .into_iter()
                .zip(&unions)
                .filter_map(|(f, u)| Some((f?, &u[..]))),
        )
        .collect();
    // A patch of a dark top too far from the others to join them lies inside what they
    // measure together: a fragment of it now.
    let mut kept = if joined_any {
        without_fragments(kept, views)
    } else {
        kept
    };
    let area = |f: &ParcelFit| f.dimensions.length_mm * f.dimensions.width_mm;
    kept.sort_by(|a, b| area(&b.0).total_cmp(&area(&a.0)));
    // Objects whose outlines come closer than TOUCH_M touch: one leans on the other, or
    // a lower one stands beside a higher one with nothing seen between them.
    let footprints: Vec<Polygon<f64>> = kept.iter().map(|(f, p)| outline(f, p)).collect();
    let mut found: Vec<ParcelFit> = kept.into_iter().map(|(f, _)| f).collect();
    for i in 0..found.len() {
        for j in i + 1..found.len() {
            if Euclidean.distance(&footprints[i], &footprints[j]) < TOUCH_M {
                found[i].isolated = false;
                found[j].isolated = false;
            }
        }
    }
    // Just beyond each edge, at the top's height: a point there that no camera has in
    // its image (a division out), or that every camera that has it sees only through
    // another parcel (further out), might be more of the parcel, hidden.
    if !views.is_empty() {
        for i in 0..found.len() {
            let hidden = probes(&found[i].dimensions, &footprints[i])
                .iter()
                .any(|[near, far]| {
                    !views.iter().any(|v| {
                        let eye = Point3::from(v.to_common.translation);
                        v.sees(near, VIEW_MARGIN_PX)
                            && !found.iter().enumerate().any(|(j, other)| {
                                j != i
                                    && blocks(
                                        &footprints[j],
                                        other.dimensions.height_mm / 1e3,
                                        &eye,
                                        far,
                                    )
                            })
                    })
                });
            if hidden {
                found[i].out_of_view = true;
                found[i].complete = false;
            }
        }
    }
    Ok(Parcels {
        parcels: found,
        largest_points,
    })
}

/// The groups (two or more, by index into `objects`) of objects that each miss much of
/// their top (coverage below the configured minimum) and whose outlines come within
/// [`TOUCH_M`] of another of the group's: the patches of one dark or glossy top.
fn pieces(objects: &[(ParcelFit, &[Point3])]) -> Vec<Vec<usize>> {
    let holed: Vec<usize> = (0..objects.len())
        .filter(|&i| !objects[i].0.complete)
        .collect();
    if holed.len() < 2 {
        return Vec::new();
    }
    let outlines: Vec<Polygon<f64>> = holed
        .iter()
        .map(|&i| outline(&objects[i].0, objects[i].1))
        .collect();
    // Each holed object's group, by the smallest position (in `holed`) it is joined to.
    let mut group: Vec<usize> = (0..holed.len()).collect();
    for a in 0..holed.len() {
        for b in a + 1..holed.len() {
            if Euclidean.distance(&outlines[a], &outlines[b]) < TOUCH_M {
                let (ga, gb) = (group[a], group[b]);
                let (keep, drop) = (ga.min(gb), ga.max(gb));
                for g in &mut group {
                    if *g == drop {
                        *g = keep;
                    }
                }
            }
        }
    }
    let mut out: Vec<Vec<usize>> = Vec::new();
    for root in 0..holed.len() {
        let members: Vec<usize> = (0..holed.len())
            .filter(|&k| group[k] == root)
            .map(|k| holed[k])
            .collect();
        if members.len() >= 2 {
            out.push(members);
        }
    }
    out
}

/// Where object `f` of `points` stands on the floor: its footprint's rectangle within
/// the hull of its points. Each holds the object (the rectangle is its cuboid's, the
/// hull holds every point of it), so their common part does too, and it is the closer
/// fit of the two: a disc's or a tube's rounded sides lie well inside the corners of its
/// rectangle (two cylinders 80 mm apart came within 20 mm at their rectangles' corners),
/// a box's rectangle inside the flying pixels that fringe its hull.
fn outline(f: &ParcelFit, points: &[Point3]) -> Polygon<f64> {
    use geo::BooleanOps as _;
    let rect = polygon(&f.dimensions.corners_m);
    let around = hull(points.iter().map(|p| [f64::from(p.x), f64::from(p.y)]));
    rect.intersection(&around)
        .0
        .into_iter()
        .max_by(|a, b| a.unsigned_area().total_cmp(&b.unsigned_area()))
        .unwrap_or(rect)
}

/// `above` (the points of `cloud` above the floor cut) without the floor's speckle, when
/// the floor itself is in the cloud (unprepared cameras send it).
///
/// Depth noise grows with the square of the range (a D415 1.9 m from the floor: about
/// 5.5 mm), and a few per cent of the floor's points then land above the floor cut: at
/// some millimetres apart they join into one object across the whole floor, with every
/// parcel in it (raw scenes 15, 51, 64 were refused as reaching beyond the view). Such a
/// point lies within a few noise deviations of the floor, in a column of the floor's
/// points: where fewer than [`SPECKLE_SHARE`] of a [`SPECKLE_CELL_M`] column's points
/// near the floor lie above the cut, those are floor. A parcel's side or lid there is
/// higher, or fills its column.
fn without_speckle(
    cloud: &PointCloud,
    above: Vec<Point3>,
    config: &DimensionConfig,
) -> Vec<Point3> {
    let cut = config.min_height_m;
    let mut floor: Vec<f32> = cloud
        .points
        .iter()
        .filter(|p| crate::cloud::is_finite(p) && p.z.abs() < cut)
        .map(|p| p.z)
        .collect();
    // The floor is in the cloud when half its noise, below zero, is.
    let below = floor.iter().filter(|z| **z < 0.0).count();
    if below < config.min_points || floor.is_empty() {
        return above;
    }
    let mid = floor.len() / 2;
    let (_, median, _) = floor.select_nth_unstable_by(mid, f32::total_cmp);
    let median = *median;
    let mut deviations: Vec<f32> = floor.iter().map(|z| (z - median).abs()).collect();
    let (_, mad, _) = deviations.select_nth_unstable_by(mid, f32::total_cmp);
    let reach = cut + 3.0 * 1.4826 * *mad;
    let cell = |p: &Point3| {
        (
            (f64::from(p.x) / SPECKLE_CELL_M).floor() as i64,
            (f64::from(p.y) / SPECKLE_CELL_M).floor() as i64,
        )
    };
    let mut counts: HashMap<Cell2, (u32, u32), FixedState> = HashMap::default();
    for p in &cloud.points {
        if crate::cloud::is_finite(p) && p.z.abs() < cut {
            counts.entry(cell(p)).or_default().0 += 1;
        }
    }
    for p in above.iter().filter(|p| p.z < reach) {
        counts.entry(cell(p)).or_default().1 += 1;
    }
    above
        .into_iter()
        .filter(|p| {
            p.z >= reach
                || counts.get(&cell(p)).is_none_or(|&(floor, high)| {
                    f64::from(high) >= SPECKLE_SHARE * f64::from(floor + high)
                })
        })
        .collect()
}

/// The objects of `found` that are not fragments of larger ones (more points,
/// [`fragment_of`]) nor flying pixels off a larger one's edge ([`curtain_of`]), largest
/// first.
fn without_fragments<'a>(
    mut found: Vec<(ParcelFit, &'a [Point3])>,
    views: &[View],
) -> Vec<(ParcelFit, &'a [Point3])> {
    found.sort_by_key(|(f, _)| std::cmp::Reverse(f.dimensions.points));
    let mut kept: Vec<(ParcelFit, &[Point3])> = Vec::with_capacity(found.len());
    for (f, points) in found {
        if !kept
            .iter()
            .any(|(k, _)| fragment_of(&f, points, k) || curtain_of(points, k, views))
        {
            kept.push((f, points));
        }
    }
    kept
}

/// Whether the object `f` (of `points`) is a piece of the larger object `k` rather than a
/// parcel of its own:
/// - most of its points lie within [`OUTSIDE_M`] of `k`'s footprint: a strip of `k`'s
///   side wall that holes (a dark or glaring finish) cut off from its lid, or points
///   under its edge; a parcel beside `k` has its lid away from it;
/// - its footprint and `k`'s overlap by at least [`OVERLAP_SHARE`] of the smaller one's
///   area: a ring of flying pixels around `k`, or the speckle of floor noise above the
///   floor cut spread around it (two parcels side by side overlap by a sliver at most);
/// - it has fewer than [`FRAGMENT_SHARE`] of `k`'s points and comes within [`FRAGMENT_M`].
fn fragment_of(f: &ParcelFit, points: &[Point3], k: &ParcelFit) -> bool {
    use geo::BooleanOps as _;
    let xy = |p: &Point3| [f64::from(p.x), f64::from(p.y)];
    let (p, q) = (
        polygon(&f.dimensions.corners_m),
        polygon(&k.dimensions.corners_m),
    );
    let under = share_outside(&k.dimensions.corners_m, points.iter().map(xy), OUTSIDE_M) < 0.5;
    let least = p.unsigned_area().min(q.unsigned_area());
    let overlap = p.intersects(&q)
        && (least <= 0.0 || p.intersection(&q).unsigned_area() >= OVERLAP_SHARE * least);
    let small = (f.dimensions.points as f64) < FRAGMENT_SHARE * k.dimensions.points as f64;
    under || overlap || (small && Euclidean.distance(&p, &q) < FRAGMENT_M)
}

/// Whether `points` (an object's) are flying pixels off the lid of `k`, parted from it by
/// holes (a dark box's lid and walls lose most of their depth): a pixel across an edge
/// reads a depth between the lid and what lies behind, so its point lies on the pixel's
/// ray through the edge, below the lid. From one of the `views`, at least
/// [`CURTAIN_SHARE`] of the points lie below `k`'s top on rays that pass within
/// [`CURTAIN_PX`] pixels (and the lid's own error, [`CURTAIN_M`]) of `k`'s outline at
/// its height. A parcel beside `k` stands on the floor beside it, off those rays.
fn curtain_of(points: &[Point3], k: &ParcelFit, views: &[View]) -> bool {
    let Some(frame) = RectFrame::new(&k.dimensions.corners_m) else {
        return false;
    };
    let top = k.dimensions.height_mm / 1e3;
    views.iter().any(|v| {
        let eye = v.to_common.translation;
        let (ex, ey, ez) = (f64::from(eye.x), f64::from(eye.y), f64::from(eye.z));
        if ez <= top {
            return false;
        }
        let on = points
            .iter()
            .filter(|p| {
                let (px, py, pz) = (f64::from(p.x), f64::from(p.y), f64::from(p.z));
                if pz >= top {
                    return false;
                }
                // Where the ray from the camera to the point crosses the lid's height.
                let t = (ez - top) / (ez - pz);
                let q = [ex + (px - ex) * t, ey + (py - ey) * t];
                let pixel = (ez - top).hypot((q[0] - ex).hypot(q[1] - ey)) / f64::from(v.fx);
                let (s, u) = frame.local(q);
                let inside = s.min(frame.la - s).min(u).min(frame.lb - u);
                let outline = if inside >= 0.0 {
                    inside
                } else {
                    let beyond = |x: f64, len: f64| (-x).max(x - len).max(0.0);
                    beyond(s, frame.la).hypot(beyond(u, frame.lb))
                };
                outline <= CURTAIN_PX * pixel + CURTAIN_M
            })
            .count();
        on as f64 >= CURTAIN_SHARE * points.len() as f64
    })
}

/// Pairs of points [`PROBE_IMAGE_M`] and [`PROBE_M`] beyond the `outline` of `d` at its
/// height: on the lines from its rectangle's centre through each corner and each edge's
/// middle, past where they leave the outline (a cylinder's probes lie beside its wall,
/// not beyond its square's corners).
fn probes(d: &Dimensions, outline: &Polygon<f64>) -> Vec<[Point3; 2]> {
    use geo::Contains as _;
    let c = &d.corners_m;
    let centre = centre(c);
    let z = (d.height_mm / 1e3) as f32;
    let mut out = Vec::with_capacity(8);
    for k in 0..4 {
        let (p, q) = (c[k], c[(k + 1) % 4]);
        for at in [p, [(p[0] + q[0]) / 2.0, (p[1] + q[1]) / 2.0]] {
            let away = sub(at, centre);
            let n = away[0].hypot(away[1]).max(1e-9);
            // The last point of the line inside the outline, to a hundredth of the way.
            let point = |t: f64| geo::Point::new(centre[0] + t * away[0], centre[1] + t * away[1]);
            let (mut inside, mut beyond) = (0.0, 1.0);
            if !outline.contains(&point(1.0)) {
                for _ in 0..7 {
                    let mid = 0.5 * (inside + beyond);
                    if outline.contains(&point(mid)) {
                        inside = mid;
                    } else {
                        beyond = mid;
                    }
                }
            } else {
                inside = 1.0;
            }
            let edge = point(inside);
            out.push([PROBE_IMAGE_M, PROBE_M].map(|past| {
                Point3::new(
                    (edge.x() + away[0] / n * past) as f32,
                    (edge.y() + away[1] / n * past) as f32,
                    z,
                )
            }));
        }
    }
    out
}

/// Whether the upright prism of `outline` (convex, from the floor to `height_m`) lies on
/// the segment from `from` to 1 cm short of `to`.
fn blocks(outline: &Polygon<f64>, height_m: f64, from: &Point3, to: &Point3) -> bool {
    let p = [f64::from(from.x), f64::from(from.y), f64::from(from.z)];
    let q = [f64::from(to.x), f64::from(to.y), f64::from(to.z)];
    let d = [q[0] - p[0], q[1] - p[1], q[2] - p[2]];
    let length = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
    if length <= 0.01 {
        return false;
    }
    let (mut t0, mut t1) = (0.0f64, 1.0 - 0.01 / length);
    // Each bound as a half-space a . x <= b, the segment clipped to it.
    let mut clip = |a: [f64; 3], b: f64| {
        let at = a[0] * p[0] + a[1] * p[1] + a[2] * p[2];
        let rate = a[0] * d[0] + a[1] * d[1] + a[2] * d[2];
        if rate.abs() < 1e-12 {
            return at <= b;
        }
        let t = (b - at) / rate;
        if rate > 0.0 {
            t1 = t1.min(t);
        } else {
            t0 = t0.max(t);
        }
        t0 <= t1
    };
    if !clip([0.0, 0.0, 1.0], height_m) || !clip([0.0, 0.0, -1.0], 0.0) {
        return false;
    }
    use geo::Winding as _;
    let ring = &outline.exterior().0;
    // The ring's turn, so that every edge's outward normal points away from the inside.
    let turn = if outline.exterior().is_cw() {
        -1.0
    } else {
        1.0
    };
    for w in ring.windows(2) {
        let (a, b) = (w[0], w[1]);
        let normal = [turn * (b.y - a.y), -turn * (b.x - a.x), 0.0];
        if !clip(normal, normal[0] * a.x + normal[1] * a.y) {
            return false;
        }
    }
    true
}

#[cfg(test)]
mod tests;
