//! Every parcel on the table (docs/design.md §6): the objects standing on the floor, each
//! measured as the smallest cuboid that encloses it, with how well a cuboid fits, whether
//! it touches another parcel and whether the data show all of it.
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
//!   rectangle (an L or a step: the lids of two boxes of nearly one height);
//! - coverage: the share of cells inside the footprint that hold points (holes from dark
//!   or shiny surfaces lower it); with camera views, whether every top corner is inside
//!   some camera's image.

use std::collections::HashMap;

use foldhash::fast::FixedState;
use geo::{
    Area, ConvexHull, Coord, Distance as _, Euclidean, Intersects as _, LineString, MultiPoint,
    Point, Polygon,
};

use crate::dimension::{
    DimensionConfig, DimensionError, Dimensions, above_floor, clusters, hull, lid, min_rect,
    rect_around, rect_dimensions, robust_height,
};
use crate::{Point3, PointCloud, Transform};

/// Side of a height-map cell, metres.
const CELL_M: f64 = 0.005;
/// Neighbouring cells of one top differ in height by less than this (metres), or by the
/// lid band when that is deeper.
const TOP_STEP_M: f32 = 0.010;
/// A cell is flat (may belong to a top) when the middle half of its points spans less
/// than this (metres) or the lid band, whichever is more.
const FLAT_M: f32 = 0.004;
/// A top counts when this many of its cells have all eight neighbours in it (a core of
/// about 2 x 2 cm), and it has at least [`TOP_SHARE`] of the largest top's cells.
const TOP_CORE_CELLS: usize = 16;
/// See [`TOP_CORE_CELLS`].
const TOP_SHARE: f64 = 0.05;
/// A cuboid's lid covers at least this share of its rectangle (a disc covers 0.785).
/// So do the lid's flattest points (see `flat_fit` in `fit`). Boxes of the lane set
/// (seeds 1 and 2, prepared and raw), dark and glossy ones too, read 0.983 to 1 (the
/// noise of their edges); a filled polybag's lid misses its lower, rounded corners and
/// reads 0.94 to 0.969, even a low, flat one whose shoulders hold too few points to
/// count as outside, or one whose lid band raw noise deepens down to its corners.
const CUBOID_FIT: f64 = 0.975;
/// Of a cuboid, at most this share of the dense points lies farther outside the lid's
/// rectangle than [`OUTSIDE_M`] (the sides of a lying tube or a polybag's belly do).
const CUBOID_OUTSIDE: f64 = 0.05;
/// See [`CUBOID_OUTSIDE`], metres.
const OUTSIDE_M: f64 = 0.010;
/// A cell is dense when it holds at least this share of the median cell's points.
const DENSE_SHARE: f64 = 0.15;
/// Objects with fewer points than this share of the largest one's are not parcels
/// (fragments of flying pixels, specks).
const MIN_SHARE: f64 = 0.005;
/// Parcels whose footprints come closer than this (metres) are side by side: a taller
/// parcel hides a strip of the lower one beside it from an oblique camera.
const TOUCH_M: f64 = 0.05;
/// An object with fewer points than this share of a larger one's, whose footprint comes
/// within [`TOUCH_M`] of the larger one's, is a fragment of it (a sliver of a side wall,
/// flying pixels between its edge and the floor), not a parcel (see [`fragment_of`]).
const FRAGMENT_SHARE: f64 = 0.01;
/// An object dropped as overlapping a larger one, with at least this share of its points
/// and most of them beyond its footprint, is a parcel standing beside it that could not be
/// told apart (a ring of flying pixels or a strip of side wall holds a few per cent).
const NEIGHBOUR_SHARE: f64 = 0.1;
/// An object whose footprint and a larger one's overlap by at least this share of the
/// smaller footprint is a ring of flying pixels or floor speckle around it (see
/// [`fragment_of`]); parcels side by side overlap by the few millimetres of noise on
/// their edges, a share of a few per cent.
const OVERLAP_SHARE: f64 = 0.2;
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
/// Side of the columns in which the floor's speckle is told from a parcel (metres; see
/// [`without_speckle`]).
const SPECKLE_CELL_M: f64 = 0.01;
/// In a column of the floor, the points just above the floor cut are speckle when they
/// are fewer than this share of the column's points near the floor (raw scene 15, 1.8 m
/// up: speckle columns hold 2-9 %, median 4 %).
const SPECKLE_SHARE: f64 = 0.25;
/// How far beyond a parcel's edges the cameras must see (metres) for it to be whole.
const PROBE_M: f64 = 0.015;
/// A top corner counts as seen when it projects at least this far inside an image.
const VIEW_MARGIN_PX: f32 = 3.0;

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

/// How well a cuboid describes the object.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Shape {
    /// A box: its lid fills its rectangle and nothing reaches beyond it.
    Cuboid,
    /// Anything else (tubes, bags, several parcels together), measured as the smallest
    /// enclosing cuboid.
    Irregular,
}

/// What a camera sees: its pose and pinhole intrinsics (the depth stream's).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct View {
    /// The camera's frame to the common frame.
    pub to_common: Transform,
    /// Focal lengths, pixels.
    pub fx: f32,
    /// See `fx`.
    pub fy: f32,
    /// Principal point, pixels.
    pub ppx: f32,
    /// See `ppx`.
    pub ppy: f32,
    /// Image width, pixels.
    pub width: u32,
    /// Image height, pixels.
    pub height: u32,
}

impl View {
    /// Whether `p` (common frame) lies in front of the camera and projects at least
    /// `margin_px` inside the image.
    pub fn sees(&self, p: &Point3, margin_px: f32) -> bool {
        let Some(inverse) = self.to_common.linear.try_inverse() else {
            return false;
        };
        let q = inverse * (p.coords - self.to_common.translation);
        if q.z <= 0.0 {
            return false;
        }
        let u = self.fx * q.x / q.z + self.ppx;
        let v = self.fy * q.y / q.z + self.ppy;
        u >= margin_px
            && v >= margin_px
            && u <= self.width as f32 - margin_px
            && v <= self.height as f32 - margin_px
    }
}

impl View {
    /// The footprint on the horizontal plane through `p` (common frame) of the pixel
    /// that sees `p`: how far the plane's point moves (x, y, metres) from one pixel to
    /// the next along the image's u and along its v. `None` when the camera does not
    /// have `p` in its image.
    pub fn footprint(&self, p: &Point3) -> Option<[[f64; 2]; 2]> {
        if !self.sees(p, 0.0) {
            return None;
        }
        let inverse = self.to_common.linear.try_inverse()?;
        let q = inverse * (p.coords - self.to_common.translation);
        let (u, v) = (
            self.fx * q.x / q.z + self.ppx,
            self.fy * q.y / q.z + self.ppy,
        );
        let on_plane = |u: f32, v: f32| {
            let ray = self.to_common.linear
                * nalgebra::Vector3::new((u - self.ppx) / self.fx, (v - self.ppy) / self.fy, 1.0);
            let t = (p.z - self.to_common.translation.z) / ray.z;
            (t.is_finite() && t > 0.0).then(|| self.to_common.translation + ray * t)
        };
        let (here, right, down) = (
            on_plane(u, v)?,
            on_plane(u + 1.0, v)?,
            on_plane(u, v + 1.0)?,
        );
        let d = |a: nalgebra::Vector3<f32>| [f64::from(a.x - here.x), f64::from(a.y - here.y)];
        Some([d(right), d(down)])
    }
}

/// One object on the table, measured.
#[derive(Debug, Clone, PartialEq)]
pub struct ParcelFit {
    /// Its smallest enclosing cuboid.
    pub dimensions: Dimensions,
    /// Cuboid or irregular.
    pub shape: Shape,
    /// How well a cuboid fits: the area of the lid's hull over its rectangle's (1 for a
    /// box seen whole; a disc 0.785).
    pub fit: f64,
    /// Flat tops found on it: 1 for one parcel, 2 or more for parcels side by side.
    pub tops: usize,
    /// False when it touches another parcel: more than one top, or another object's
    /// footprint within 5 cm.
    pub isolated: bool,
    /// The share of the footprint's cells that hold points (1 without holes).
    pub coverage: f64,
    /// Just beyond an edge, at the top's height, lies a point outside every camera's
    /// image, or behind another parcel from each camera that has it in its image: more of
    /// the parcel may be there, unseen (only known with views).
    pub out_of_view: bool,
    /// Seen whole: in view, and coverage at least the configured minimum.
    pub complete: bool,
}

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
    let mut found = Vec::new();
    let mut first_error = None;
    for cluster in clusters.iter().take_while(|c| c.len() >= needed) {
        match fit(cluster, config, views) {
            Ok(f) => found.push((f, &cluster[..])),
            Err(e) => {
                first_error.get_or_insert(e);
            }
        }
    }
    if found.is_empty()
        && let Some(e) = first_error
    {
        return Err(e);
    }
    // Fragments of larger objects (more points) go.
    found.sort_by_key(|(f, _)| std::cmp::Reverse(f.dimensions.points));
    let mut kept: Vec<ParcelFit> = Vec::with_capacity(found.len());
    for (f, points) in found {
        match kept.iter().position(|k| fragment_of(&f, points, k)) {
            None => kept.push(f),
            Some(i) => {
                if neighbour_of(&f, points, &kept[i]) {
                    kept[i].isolated = false;
                }
            }
        }
    }
    let mut found = kept;
    let area = |f: &ParcelFit| f.dimensions.length_mm * f.dimensions.width_mm;
    found.sort_by(|a, b| area(b).total_cmp(&area(a)));
    // Objects whose footprints come closer than TOUCH_M touch: one leans on the other,
    // or a lower one stands beside a higher one with nothing seen between them.
    let footprints: Vec<Polygon<f64>> = found
        .iter()
        .map(|f| polygon(&f.dimensions.corners_m))
        .collect();
    for i in 0..found.len() {
        for j in i + 1..found.len() {
            if Euclidean.distance(&footprints[i], &footprints[j]) < TOUCH_M {
                found[i].isolated = false;
                found[j].isolated = false;
            }
        }
    }
    // Just beyond each edge, at the top's height: a point there that no camera has in
    // its image, or that every camera that has it sees only through another parcel,
    // might be more of the parcel, hidden.
    if !views.is_empty() {
        for i in 0..found.len() {
            let hidden = probes(&found[i].dimensions).iter().any(|p| {
                !views.iter().any(|v| {
                    let eye = Point3::from(v.to_common.translation);
                    v.sees(p, VIEW_MARGIN_PX)
                        && !found
                            .iter()
                            .enumerate()
                            .any(|(j, other)| j != i && blocks(other, &eye, p))
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

/// Whether the object `f` (of `points`) is a piece of the larger object `k` rather than a
/// parcel of its own:
/// - most of its points lie within [`OUTSIDE_M`] of `k`'s footprint: a strip of `k`'s
///   side wall that holes (a dark or glaring finish) cut off from its lid, or points
///   under its edge; a parcel beside `k` has its lid away from it;
/// - its footprint and `k`'s overlap by at least [`OVERLAP_SHARE`] of the smaller one's
///   area: a ring of flying pixels around `k`, or the speckle of floor noise above the
///   floor cut spread around it (two parcels side by side overlap by a sliver at most);
/// - it has fewer than [`FRAGMENT_SHARE`] of `k`'s points and comes within [`TOUCH_M`].
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
    under || overlap || (small && Euclidean.distance(&p, &q) < TOUCH_M)
}

/// Whether `f`, dropped as a fragment of `k` (with its `points`), is rather a parcel
/// standing beside `k` that could not be told apart: a parcel's worth of points, most of
/// them beyond `k`'s footprint (a lower parcel whose outline ran into the higher one's
/// wall, so that their rectangles overlap). Nothing is said of it, so `k` is not alone.
fn neighbour_of(f: &ParcelFit, points: &[Point3], k: &ParcelFit) -> bool {
    let xy = |p: &Point3| [f64::from(p.x), f64::from(p.y)];
    let beside = share_outside(&k.dimensions.corners_m, points.iter().map(xy), OUTSIDE_M) >= 0.5;
    beside && f.dimensions.points as f64 >= NEIGHBOUR_SHARE * k.dimensions.points as f64
}

/// Measures one object.
fn fit(
    cluster: &[Point3],
    config: &DimensionConfig,
    views: &[View],
) -> Result<ParcelFit, DimensionError> {
    let height_m = robust_height(cluster, config);
    let lid = lid(cluster, height_m, config)?;
    if lid.points.len() < 3 {
        return Err(DimensionError::Footprint);
    }
    let xy = |p: &Point3| [f64::from(p.x), f64::from(p.y)];
    // One hull of the lid for its rectangle and its area.
    let lid_hull = hull(lid.points.iter().map(xy));
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
    let centre = Point3::new(
        (hull_rect.iter().map(|c| c[0]).sum::<f64>() / 4.0) as f32,
        (hull_rect.iter().map(|c| c[1]).sum::<f64>() / 4.0) as f32,
        height_m,
    );
    let pixel = views
        .iter()
        .filter(|v| v.sees(&centre, 0.0))
        .map(|v| f64::from((v.to_common.translation - centre.coords).norm() / v.fx))
        .fold(0.0, f64::max);
    // Noise moves the outermost points out by a few deviations (the band is four) times
    // the tangent of the ray's angle: the edges move in no farther than that. (A low
    // parcel whose edge the spatial filter blurred into the floor keeps the hull's.)
    let inward = (0.75 * f64::from(lid.band_m)).max(0.0015);
    let refined = refine(hull_rect, &flat, margin, inward, pixel / 2.0);
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
    let flat_fit = min_rect(flat.iter().map(xy)).map_or(fit, |r| {
        let all: MultiPoint<f64> = flat
            .iter()
            .map(|p| Point::new(f64::from(p.x), f64::from(p.y)))
            .collect();
        (all.convex_hull().unsigned_area() / rect_area(&r)).min(1.0)
    });

    let map = HeightMap::new(cluster);
    let dense = map.dense_points(cluster);
    let tops = map.tops(TOP_STEP_M.max(lid.band_m), FLAT_M.max(lid.band_m));
    let outside = share_outside(&lid_rect, dense.iter().map(xy), OUTSIDE_M);
    // A tube lying on the floor has a lid strip that fills its rectangle, and with a deep
    // lid band nothing reaches beyond it: its curved top tells it from a box.
    let tube = if tops <= 1 {
        lying_tube(&lid_rect, &dense, height_m, lid.band_m)
    } else {
        None
    };
    let shape = if tube.is_none()
        && tops <= 1
        && fit.min(flat_fit) >= CUBOID_FIT
        && outside <= CUBOID_OUTSIDE
    {
        Shape::Cuboid
    } else {
        Shape::Irregular
    };
    // A standing cylinder: a disc of a lid with nothing of the object beyond it.
    let disc = if tube.is_none() && tops <= 1 && shape == Shape::Irregular {
        standing_disc(&hull_rect, &lid.points, &flat, &dense, margin, inward)
            .map(|d| d.grown(pixel / 2.0))
    } else {
        None
    };
    // One flat plateau that reaches out to the object's walls but leaves a notch cut
    // into its rectangle from a side: lids of boxes are rectangles, so this is most
    // likely two parcels of nearly the same height side by side (their lids joined
    // into one top), or an item no cuboid describes. A polybag's lid is a dome that
    // ends well inside its shoulders; a disc's lid is taken above.
    let several = shape == Shape::Irregular && tube.is_none() && disc.is_none() && tops <= 1 && {
        let (reach, notch, solid) = map.plateau(&lid.points, &hull_rect);
        reach >= PLATEAU_REACH && notch >= NOTCH_SHARE && solid >= PLATEAU_SOLID
    };
    let corners = match (shape, &tube) {
        // Along its axis the lid strip, which runs the tube's whole length at its top
        // (the flying pixels beyond its round ends lie lower); across it the circle.
        (_, Some(t)) => t.footprint(&lid_rect),
        _ if disc.is_some() => disc.map_or(hull_rect, |d| d.footprint(&hull_rect)),
        (Shape::Cuboid, None) => unblur(
            lid_rect,
            cluster,
            height_m,
            (views, pixel),
            config.min_height_m,
        ),
        // Around every dense point, each edge placed by the points' density as a lid's
        // is: the thin fringe of flying pixels around a tall object counts little.
        (Shape::Irregular, None) => {
            let around = min_rect(dense.iter().map(xy)).map_or(hull_rect, |r| {
                refine(r, &dense, margin.max(0.006), 0.003, 0.0)
            });
            // A lid with rounded corners is a pillow's: its sides curve down to the floor.
            // (A lying tube's lid fills its rectangle; it is irregular for its sides.)
            if fit.min(flat_fit) < CUBOID_FIT {
                shoulders(around, &dense, height_m, views)
            } else {
                around
            }
        }
    };
    let peak = map.peak();
    let top_m = match (shape, &tube) {
        // The circle's top, where the noise is averaged over the whole section.
        (_, Some(t)) => (2.0 * t.radius) as f32,
        // A flat lid: the band's median, as a box's.
        _ if disc.is_some() => height_m,
        (Shape::Cuboid, None) => height_m,
        (Shape::Irregular, None) => peak.map_or(height_m, |p| p.max(height_m)),
    };
    // A box or a tube seen from above covers its footprint, a standing cylinder its
    // disc; other shapes their dense points' hull (a raw camera's floor noise joined to
    // a tube is no hole in it).
    let coverage = match (shape, &tube) {
        (Shape::Cuboid, _) | (_, Some(_)) => map.coverage(&polygon(&corners)),
        _ if disc.is_some() => disc.map_or(1.0, |d| map.coverage(&d.polygon())),
        (Shape::Irregular, None) => {
            let all: MultiPoint<f64> = dense
                .iter()
                .map(|p| Point::new(f64::from(p.x), f64::from(p.y)))
                .collect();
            map.coverage(&all.convex_hull())
        }
    };
    Ok(ParcelFit {
        dimensions: rect_dimensions(corners, f64::from(top_m), cluster.len()),
        shape,
        fit,
        tops,
        isolated: tops <= 1 && !several,
        coverage,
        out_of_view: false,
        complete: coverage >= f64::from(config.min_coverage),
    })
}

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

/// The rectangle `corners` with each edge where a soft parcel's side (a polybag's
/// shoulder) meets the floor. Seen from above, such a side curves down and away: each
/// camera sees it until its rays graze it, and of the last pixels before the floor a D415
/// keeps little (the right imager cannot see them, or they straddle the depth step and
/// fly). The seen surface ends at a height `z` some millimetres inside the true edge,
/// still sloping. Below that the side cannot reach beyond the camera's grazing ray, which
/// meets the floor `z * t` farther out (t the ray's run over its fall, from the camera
/// that looks down on the edge most steeply); where in that band it stands upright is
/// not seen. The side is taken as a quarter ellipse, a filled pillow's section: level at
/// the top's height `h`, upright on the floor, along the grazing ray where the seen
/// surface ends. Such an arc reaches `c / (1 + c)` of the band farther out, c = sqrt(1 -
/// (z / h)^2): half the band for a side seen nearly down to the floor, less the higher
/// up the camera loses it. An edge whose surface arrives level (a lid) stays where it is.
/// Without views the band is unknown and the rectangle stays.
fn shoulders(
    corners: [[f64; 2]; 4],
    points: &[Point3],
    height_m: f32,
    views: &[View],
) -> [[f64; 2]; 4] {
    let c0 = corners[0];
    let (e0, e1) = (sub(corners[1], c0), sub(corners[3], c0));
    let (la, lb) = (e0[0].hypot(e0[1]), e1[0].hypot(e1[1]));
    if views.is_empty() || la <= 0.0 || lb <= 0.0 {
        return corners;
    }
    let a = [e0[0] / la, e0[1] / la];
    let b = [e1[0] / lb, e1[1] / lb];
    let local: Vec<(f64, f64, f32)> = points
        .iter()
        .map(|p| {
            let d = sub([f64::from(p.x), f64::from(p.y)], c0);
            (dot(d, a), dot(d, b), p.z)
        })
        .collect();
    let mut moved = [[0.0f64; 2]; 2];
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
            if z_inner - upper <= FALL_M || z_end <= 0.0 {
                continue;
            }
            // Where the seen surface ends, inside the edge (negative: beyond it).
            let depth = (end as f64 - outer as f64) * BIN_M;
            let mid_along = 0.5 * other_len;
            let at = if side == 0 { depth } else { len - depth };
            let (s, t) = if axis == 0 {
                (at, mid_along)
            } else {
                (mid_along, at)
            };
            let m = [c0[0] + a[0] * s + b[0] * t, c0[1] + a[1] * s + b[1] * t];
            let outward = match (axis, side) {
                (0, 0) => [-a[0], -a[1]],
                (0, _) => a,
                (_, 0) => [-b[0], -b[1]],
                _ => b,
            };
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
                moved[axis][side] = -depth + c / (1.0 + c) * f64::from(z_end) * run;
            }
        }
    }
    let at = |s: f64, t: f64| [c0[0] + a[0] * s + b[0] * t, c0[1] + a[1] * s + b[1] * t];
    let (s0, s1) = (-moved[0][0], la + moved[0][1]);
    let (t0, t1) = (-moved[1][0], lb + moved[1][1]);
    [at(s0, t0), at(s1, t0), at(s1, t1), at(s0, t1)]
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

/// A tube lying on the floor: its cross-section, in the frame of the lid's rectangle.
#[derive(Debug, Clone, Copy, PartialEq)]
struct LyingTube {
    /// Whether the axis runs along the rectangle's first edge (corner 0 to 1).
    along_first: bool,
    /// The axis's position across the rectangle, from corner 0, metres.
    centre: f64,
    /// The radius, metres: the tube rests on the floor, so its top is at twice this.
    radius: f64,
}

impl LyingTube {
    /// The footprint: the lid's rectangle along the axis, the circle's diameter across.
    fn footprint(&self, rect: &[[f64; 2]; 4]) -> [[f64; 2]; 4] {
        let c0 = rect[0];
        let (mut e0, mut e1) = (sub(rect[1], c0), sub(rect[3], c0));
        if !self.along_first {
            std::mem::swap(&mut e0, &mut e1);
        }
        let (la, lb) = (e0[0].hypot(e0[1]), e1[0].hypot(e1[1]));
        if la <= 0.0 || lb <= 0.0 {
            return *rect;
        }
        let (a, b) = ([e0[0] / la, e0[1] / la], [e1[0] / lb, e1[1] / lb]);
        let at = |s: f64, t: f64| [c0[0] + a[0] * s + b[0] * t, c0[1] + a[1] * s + b[1] * t];
        let (t0, t1) = (self.centre - self.radius, self.centre + self.radius);
        [at(0.0, t0), at(la, t0), at(la, t1), at(0.0, t1)]
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
/// [`DISC_ROUND_M`]) ...
const DISC_ROUND: f64 = 0.04;
/// See [`DISC_ROUND`], metres.
const DISC_ROUND_M: f64 = 0.004;

/// Whether the lid (`points`, its rectangle `rect`) is a disc with nothing of the object
/// beyond it (a standing cylinder), and its radius. The radius is placed as a box's edges
/// are ([`edges`]), in rings instead of strips: depth noise moves the lid's points
/// sideways without adding or losing any, so the edge lies where the `flat` points
/// beyond a circle `margin` inside the outermost ones, at the density of the ring just
/// inside it, would end; each 1 mm ring counts at most 1.5 times that density (the top
/// of the side wall seen from the side is no lid). Where the disc's rectangle was placed
/// by strips, a disc thins towards each extreme as a square root, and the strip count put
/// its edges about 3 mm inside: cylinders came out 3.5-6.7 mm narrow.
fn standing_disc(
    rect: &[[f64; 2]; 4],
    points: &[Point3],
    flat: &[Point3],
    dense: &[Point3],
    margin: f64,
    inward: f64,
) -> Option<Disc> {
    let (e0, e1) = (sub(rect[1], rect[0]), sub(rect[3], rect[0]));
    let (la, lb) = (e0[0].hypot(e0[1]), e1[0].hypot(e1[1]));
    if la <= 0.0 || lb <= 0.0 || la.max(lb) > 1.1 * la.min(lb) {
        return None;
    }
    let hull = points
        .iter()
        .map(|p| Point::new(f64::from(p.x), f64::from(p.y)))
        .collect::<MultiPoint<f64>>()
        .convex_hull();
    let fit = hull.unsigned_area() / (la * lb);
    if !(DISC_FIT[0]..=DISC_FIT[1]).contains(&fit) {
        return None;
    }
    let centre = [0, 1].map(|k| rect.iter().map(|c| c[k]).sum::<f64>() / 4.0);
    let radii: Vec<f64> = hull
        .exterior()
        .coords()
        .map(|c| (c.x - centre[0]).hypot(c.y - centre[1]))
        .collect();
    let outer = radii.iter().copied().fold(0.0, f64::max);
    let inner = radii.iter().copied().fold(f64::MAX, f64::min);
    if outer - inner > (DISC_ROUND * outer).max(DISC_ROUND_M) {
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
/// share of its diameter across the axis: the camera sees its top half from above.
const TUBE_SPAN: f64 = 0.8;
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
/// circle's top is not.
fn lying_tube(
    rect: &[[f64; 2]; 4],
    dense: &[Point3],
    height_m: f32,
    band_m: f32,
) -> Option<LyingTube> {
    let c0 = rect[0];
    let (e0, e1) = (sub(rect[1], c0), sub(rect[3], c0));
    let (l0, l1) = (e0[0].hypot(e0[1]), e1[0].hypot(e1[1]));
    if l0 <= 0.0 || l1 <= 0.0 {
        return None;
    }
    let along_first = l0 >= l1;
    let (long, across, len) = if along_first {
        (e0, e1, l0)
    } else {
        (e1, e0, l1)
    };
    let a = [long[0] / len, long[1] / len];
    let la = across[0].hypot(across[1]);
    let b = [across[0] / la, across[1] / la];
    let height = f64::from(height_m);
    let profile: Vec<[f64; 2]> = dense
        .iter()
        .filter_map(|p| {
            let d = sub([f64::from(p.x), f64::from(p.y)], c0);
            let s = dot(d, a);
            (s >= 0.2 * len && s <= 0.8 * len && f64::from(p.z) >= height / 2.0)
                .then(|| [dot(d, b), f64::from(p.z)])
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
    // A tube's crest runs its whole length and its ends are upright discs: beyond the
    // lid strip's ends only a few flying pixels stay dense. A bag's top curves down along
    // its length as across it, and its rounded ends lie beyond the strip.
    let beyond = dense
        .iter()
        .filter(|p| {
            let s = dot(sub([f64::from(p.x), f64::from(p.y)], c0), a);
            s < -OUTSIDE_M || s > len + OUTSIDE_M
        })
        .count() as f64
        / dense.len().max(1) as f64;
    (round && beyond <= TUBE_BEYOND_SHARE).then_some(LyingTube {
        along_first,
        centre,
        radius,
    })
}

/// The lid rectangle `rect` of a parcel `height_m` high with each edge that the spatial
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
/// shadow's holes) and lids too low for half their height to clear the floor cut by
/// 3 mm stay as they are.
fn unblur(
    rect: [[f64; 2]; 4],
    cluster: &[Point3],
    height_m: f32,
    (views, pixel_m): (&[View], f64),
    min_height_m: f32,
) -> [[f64; 2]; 4] {
    const REACH_M: f64 = 0.03;
    const INSET_M: f64 = 0.02;
    let bin_m = (2.0 * pixel_m).max(0.0025);
    let from_m = (2.0 * bin_m).max(0.008);
    let half = height_m / 2.0;
    // Half the height must clear the floor cut for its crossing to be seen.
    if half < min_height_m + 0.003 {
        return rect;
    }
    let c0 = rect[0];
    let (e0, e1) = (sub(rect[1], c0), sub(rect[3], c0));
    let (la, lb) = (e0[0].hypot(e0[1]), e1[0].hypot(e1[1]));
    if la <= 2.0 * INSET_M || lb <= 2.0 * INSET_M {
        return rect;
    }
    let (a, b) = ([e0[0] / la, e0[1] / la], [e1[0] / lb, e1[1] / lb]);
    let local: Vec<(f64, f64, f32)> = cluster
        .iter()
        .map(|p| {
            let d = sub([f64::from(p.x), f64::from(p.y)], c0);
            (dot(d, a), dot(d, b), p.z)
        })
        .collect();
    let bins = ((from_m + REACH_M) / bin_m).round() as usize;
    // Where, outwards of the edge, the blurred step passes half the height.
    let crossing = |along_b: bool, high: bool| -> Option<f64> {
        let (len, other) = if along_b { (lb, la) } else { (la, lb) };
        let mut z: Vec<Vec<f32>> = vec![Vec::new(); bins];
        let mut sum = vec![0.0f64; bins];
        for &(s, t, pz) in &local {
            let (across, along) = if along_b { (t, s) } else { (s, t) };
            if along < INSET_M || along > other - INSET_M {
                continue;
            }
            let out = if high { across - len } else { -across };
            let k = ((out + from_m) / bin_m).floor();
            if k >= 0.0 && (k as usize) < bins {
                z[k as usize].push(pz);
                sum[k as usize] += out;
            }
        }
        let inside = 2;
        let density = z[..inside].iter().map(Vec::len).sum::<usize>() as f64 / inside as f64;
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
    // the edge).
    let reach = |mid: [f64; 2], outward: [f64; 2]| -> f64 {
        let p = Point3::new(mid[0] as f32, mid[1] as f32, height_m);
        let slopes: Vec<f64> = views
            .iter()
            .filter(|v| v.sees(&p, 0.0))
            .map(|v| {
                let eye = v.to_common.translation;
                let rise = f64::from(eye.z - height_m).max(1e-3);
                let d = [mid[0] - f64::from(eye.x), mid[1] - f64::from(eye.y)];
                (dot(d, outward) / rise).max(0.0)
            })
            .collect();
        if slopes.is_empty() {
            0.0
        } else {
            f64::from(half) * slopes.iter().sum::<f64>() / slopes.len() as f64
        }
    };
    let at = |s: f64, t: f64| [c0[0] + a[0] * s + b[0] * t, c0[1] + a[1] * s + b[1] * t];
    let mut lo = [0.0, 0.0];
    let mut hi = [la, lb];
    for (axis, along_b) in [(0, false), (1, true)] {
        let len = if along_b { lb } else { la };
        let (dir, mid_other) = if along_b {
            (b, la / 2.0)
        } else {
            (a, lb / 2.0)
        };
        for high in [false, true] {
            let Some(c) = crossing(along_b, high) else {
                continue;
            };
            let outward = if high { dir } else { [-dir[0], -dir[1]] };
            let edge = if high { len } else { 0.0 };
            let mid = if along_b {
                at(mid_other, edge)
            } else {
                at(edge, mid_other)
            };
            let moved = (c - reach(mid, outward)).clamp(0.0, REACH_M);
            if high {
                hi[axis] = len + moved;
            } else {
                lo[axis] = -moved;
            }
        }
    }
    [
        at(lo[0], lo[1]),
        at(hi[0], lo[1]),
        at(hi[0], hi[1]),
        at(lo[0], hi[1]),
    ]
}

fn sub(a: [f64; 2], b: [f64; 2]) -> [f64; 2] {
    [a[0] - b[0], a[1] - b[1]]
}

fn dot(a: [f64; 2], b: [f64; 2]) -> f64 {
    a[0] * b[0] + a[1] * b[1]
}

fn rect_area(c: &[[f64; 2]; 4]) -> f64 {
    let (e0, e1) = (sub(c[1], c[0]), sub(c[3], c[0]));
    (e0[0] * e1[1] - e0[1] * e1[0]).abs()
}

/// The rectangle `corners` (in order around it) with each edge moved to where `lid`'s
/// points put it (see [`edges`]), at most `inward` inside the hull's and `beyond`
/// outside it.
pub(crate) fn refine(
    corners: [[f64; 2]; 4],
    lid: &[Point3],
    margin: f64,
    inward: f64,
    beyond: f64,
) -> [[f64; 2]; 4] {
    let c0 = corners[0];
    let (e0, e1) = (sub(corners[1], c0), sub(corners[3], c0));
    let (la, lb) = (e0[0].hypot(e0[1]), e1[0].hypot(e1[1]));
    if la <= 0.0 || lb <= 0.0 {
        return corners;
    }
    let a = [e0[0] / la, e0[1] / la];
    let b = [e1[0] / lb, e1[1] / lb];
    let mut sa = Vec::with_capacity(lid.len());
    let mut sb = Vec::with_capacity(lid.len());
    for p in lid {
        let d = sub([f64::from(p.x), f64::from(p.y)], c0);
        sa.push(dot(d, a));
        sb.push(dot(d, b));
    }
    let (a0, a1) = edges(&sa, la, margin, inward, beyond);
    let (b0, b1) = edges(&sb, lb, margin, inward, beyond);
    let at = |s: f64, t: f64| [c0[0] + a[0] * s + b[0] * t, c0[1] + a[1] * s + b[1] * t];
    [at(a0, b0), at(a1, b0), at(a1, b1), at(a0, b1)]
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
/// bands keeps the hull's edges. An edge lies at most `inward` inside the outermost
/// point and `beyond` outside it.
fn edges(s: &[f64], len: f64, margin: f64, inward: f64, beyond: f64) -> (f64, f64) {
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
    let least = (margin - inward).max(0.0);
    let place = |line: f64, outwards: f64| {
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
    (place(margin, -1.0), place(len - margin, 1.0))
}

/// How far each side of the lid's rectangle `corners` (side `k` from corner `k` to
/// `k + 1`) lies beyond where its points' density ends, metres, from the cameras that
/// see it. A pixel across the edge sees the lid and the floor and reads a depth between
/// them, off the lid: the lid's points end half a pixel's footprint (across the edge)
/// inside it. Not so on the side away from a camera's right imager: the floor beside it
/// there is hidden from the right imager (the stereo shadow), so the pixel across the
/// edge matches the lid alone and reads the lid's depth. The cameras are weighted by
/// their points' density there.
fn pixel_offsets(corners: &[[f64; 2]; 4], height_m: f32, views: &[View]) -> [f64; 4] {
    let centre = [0, 1].map(|k| corners.iter().map(|c| c[k]).sum::<f64>() / 4.0);
    let mut out = [0.0; 4];
    for (k, offset) in out.iter_mut().enumerate() {
        let (p, q) = (corners[k], corners[(k + 1) % 4]);
        let mid = [(p[0] + q[0]) / 2.0, (p[1] + q[1]) / 2.0];
        let away = sub(mid, centre);
        let n = away[0].hypot(away[1]);
        if n <= 0.0 {
            continue;
        }
        let normal = [away[0] / n, away[1] / n];
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
/// Points [`PROBE_M`] outside the footprint of `d` at its height: beyond each corner and
/// each edge's middle.
fn probes(d: &Dimensions) -> Vec<Point3> {
    let c = &d.corners_m;
    let centre = [0, 1].map(|k| c.iter().map(|p| p[k]).sum::<f64>() / 4.0);
    let z = (d.height_mm / 1e3) as f32;
    let mut out = Vec::with_capacity(8);
    for k in 0..4 {
        let (p, q) = (c[k], c[(k + 1) % 4]);
        for at in [p, [(p[0] + q[0]) / 2.0, (p[1] + q[1]) / 2.0]] {
            let away = sub(at, centre);
            let n = away[0].hypot(away[1]).max(1e-9);
            out.push(Point3::new(
                (at[0] + away[0] / n * PROBE_M) as f32,
                (at[1] + away[1] / n * PROBE_M) as f32,
                z,
            ));
        }
    }
    out
}

/// Whether the upright box of `fit` (its footprint, from the floor to its height) lies
/// on the segment from `from` to 1 cm short of `to`.
fn blocks(fit: &ParcelFit, from: &Point3, to: &Point3) -> bool {
    let c = &fit.dimensions.corners_m;
    let c0 = c[0];
    let (e0, e1) = (sub(c[1], c0), sub(c[3], c0));
    let (la, lb) = (e0[0].hypot(e0[1]), e1[0].hypot(e1[1]));
    if la <= 0.0 || lb <= 0.0 {
        return false;
    }
    let (a, b) = ([e0[0] / la, e0[1] / la], [e1[0] / lb, e1[1] / lb]);
    let local = |p: &Point3| {
        let d = sub([f64::from(p.x), f64::from(p.y)], c0);
        [dot(d, a), dot(d, b), f64::from(p.z)]
    };
    let (p, q) = (local(from), local(to));
    let length = ((q[0] - p[0]).powi(2) + (q[1] - p[1]).powi(2) + (q[2] - p[2]).powi(2)).sqrt();
    if length <= 0.01 {
        return false;
    }
    let (mut t0, mut t1) = (0.0f64, 1.0 - 0.01 / length);
    let high = [la, lb, fit.dimensions.height_mm / 1e3];
    for k in 0..3 {
        let d = q[k] - p[k];
        if d.abs() < 1e-12 {
            if p[k] < 0.0 || p[k] > high[k] {
                return false;
            }
            continue;
        }
        let (mut u, mut v) = ((0.0 - p[k]) / d, (high[k] - p[k]) / d);
        if u > v {
            std::mem::swap(&mut u, &mut v);
        }
        t0 = t0.max(u);
        t1 = t1.min(v);
        if t0 > t1 {
            return false;
        }
    }
    true
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
fn walls(
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
    let centre = [0, 1].map(|k| corners.iter().map(|c| c[k]).sum::<f64>() / 4.0);
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
fn move_sides(corners: [[f64; 2]; 4], by: [f64; 4]) -> [[f64; 2]; 4] {
    let c0 = corners[0];
    let (e0, e1) = (sub(corners[1], c0), sub(corners[3], c0));
    let (la, lb) = (e0[0].hypot(e0[1]), e1[0].hypot(e1[1]));
    if la <= 0.0 || lb <= 0.0 {
        return corners;
    }
    let (a, b) = ([e0[0] / la, e0[1] / la], [e1[0] / lb, e1[1] / lb]);
    let at = |s: f64, t: f64| [c0[0] + a[0] * s + b[0] * t, c0[1] + a[1] * s + b[1] * t];
    // Side 0 lies at t = 0, side 1 at s = la, side 2 at t = lb, side 3 at s = 0.
    [
        at(-by[3], -by[0]),
        at(la + by[1], -by[0]),
        at(la + by[1], lb + by[2]),
        at(-by[3], lb + by[2]),
    ]
}

/// The share of `points` lying more than `tolerance` outside the rectangle `corners`.
fn share_outside(
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
fn polygon(corners: &[[f64; 2]; 4]) -> Polygon<f64> {
    let ring: Vec<Coord<f64>> = corners.iter().map(|c| Coord { x: c[0], y: c[1] }).collect();
    Polygon::new(LineString::from(ring), Vec::new())
}

type Cell2 = (i64, i64);

/// The object's points binned into [`CELL_M`] cells in (x, y): count and median z (a
/// cell where a higher parcel's side meets a lower one's lid holds a few side points and
/// many lid points: its median is the lid's, where its highest point would make a
/// staircase joining the two tops).
struct HeightMap {
    cells: HashMap<Cell2, (u32, f32), FixedState>,
    /// How far the middle half of each cell's points spans in z: a cell holding a side
    /// wall, or the lids of two parcels, is not flat.
    spread: HashMap<Cell2, f32, FixedState>,
    /// Cells with fewer points are not dense.
    dense_min: u32,
}

fn cell_of(x: f64, y: f64) -> Cell2 {
    ((x / CELL_M).floor() as i64, (y / CELL_M).floor() as i64)
}

impl HeightMap {
    fn new(points: &[Point3]) -> Self {
        let mut heights: HashMap<Cell2, Vec<f32>, FixedState> = HashMap::default();
        for p in points {
            heights
                .entry(cell_of(f64::from(p.x), f64::from(p.y)))
                .or_default()
                .push(p.z);
        }
        let mut spread: HashMap<Cell2, f32, FixedState> = HashMap::default();
        let cells: HashMap<Cell2, (u32, f32), FixedState> = heights
            .into_iter()
            .map(|(cell, mut z)| {
                z.sort_unstable_by(f32::total_cmp);
                let n = z.len();
                spread.insert(cell, z[(3 * n) / 4] - z[n / 4]);
                (cell, (n as u32, z[n / 2]))
            })
            .collect();
        let mut counts: Vec<u32> = cells.values().map(|c| c.0).collect();
        let mid = counts.len() / 2;
        let median = if counts.is_empty() {
            0
        } else {
            *counts.select_nth_unstable(mid).1
        };
        let dense_min = ((f64::from(median) * DENSE_SHARE).ceil() as u32).max(2);
        Self {
            cells,
            spread,
            dense_min,
        }
    }

    fn is_dense(&self, c: &Cell2) -> bool {
        self.cells.get(c).is_some_and(|v| v.0 >= self.dense_min)
    }

    /// The points of `points` in dense cells (flying pixels between an edge and the floor
    /// scatter thinly and are left out).
    fn dense_points(&self, points: &[Point3]) -> Vec<Point3> {
        points
            .iter()
            .filter(|p| self.is_dense(&cell_of(f64::from(p.x), f64::from(p.y))))
            .copied()
            .collect()
    }

    /// The highest point of a smooth top: the greatest mean of the median heights of a
    /// dense cell and its eight neighbours (all dense), `None` when no cell has them.
    /// Averaging nine medians leaves little of the depth noise, where the points' own
    /// maximum would read a few deviations high; a domed top keeps its apex, where the
    /// median of a band below the highest points lies lower.
    fn peak(&self) -> Option<f32> {
        let mut best: Option<f32> = None;
        for (&(x, y), _) in self.cells.iter().filter(|(c, _)| self.is_dense(c)) {
            let mut sum = 0.0;
            let mut all = true;
            for dx in -1..=1 {
                for dy in -1..=1 {
                    match self.cells.get(&(x + dx, y + dy)) {
                        Some(&(n, z)) if n >= self.dense_min => sum += z,
                        _ => all = false,
                    }
                }
            }
            if all {
                let mean = sum / 9.0;
                best = Some(best.map_or(mean, |b| b.max(mean)));
            }
        }
        best
    }

    /// The number of tops: regions of dense cells connected (8-neighbourhood) where
    /// neighbouring median heights differ by less than `step`, counted when their core
    /// (cells whose eight neighbours are all in the region) has [`TOP_CORE_CELLS`] and
    /// their cells are at least [`TOP_SHARE`] of the largest region's.
    fn tops(&self, step: f32, flatness: f32) -> usize {
        let flat =
            |c: &Cell2| self.is_dense(c) && self.spread.get(c).is_some_and(|s| *s < flatness);
        let mut region: HashMap<Cell2, usize, FixedState> = HashMap::default();
        let mut sizes: Vec<(usize, usize)> = Vec::new();
        let mut dense: Vec<Cell2> = self.cells.keys().filter(|c| flat(c)).copied().collect();
        dense.sort_unstable();
        let neighbours = |(x, y): Cell2| {
            (-1..=1)
                .flat_map(move |dx| (-1..=1).map(move |dy| (x + dx, y + dy)))
                .filter(move |c| *c != (x, y))
        };
        let mut stack = Vec::new();
        for start in dense {
            if region.contains_key(&start) {
                continue;
            }
            let id = sizes.len();
            let mut members = Vec::new();
            region.insert(start, id);
            stack.push(start);
            while let Some(c) = stack.pop() {
                members.push(c);
                let z = self.cells[&c].1;
                for n in neighbours(c) {
                    if region.contains_key(&n) || !flat(&n) {
                        continue;
                    }
                    if (self.cells[&n].1 - z).abs() < step {
                        region.insert(n, id);
                        stack.push(n);
                    }
                }
            }
            let core = members
                .iter()
                .filter(|c| neighbours(**c).all(|n| region.get(&n) == Some(&id)))
                .count();
            sizes.push((members.len(), core));
        }
        let largest = sizes.iter().map(|s| s.0).max().unwrap_or(0);
        sizes
            .iter()
            .filter(|(n, core)| *core >= TOP_CORE_CELLS && *n as f64 >= TOP_SHARE * largest as f64)
            .count()
            .max(1)
    }

    /// How a flat lid (`lid`, its rectangle `rect`) lies on the object: the share of the
    /// dense cells that hold lid points (how far the lid reaches out towards the
    /// object's walls), and the share of the rectangle's cells in notches cut into it
    /// from its sides (cells with no lid point in their 3 x 3 neighbourhood, connected
    /// to a cell within two cells of the rectangle's border; a hole in a dark lid's
    /// middle is no notch, nor the ragged cell or two along a lid's edge), and the share
    /// of the rectangle's other cells that hold lid points (a solid lid, not a sparse
    /// scatter of flying pixels).
    fn plateau(&self, lid: &[Point3], rect: &[[f64; 2]; 4]) -> (f64, f64, f64) {
        use geo::Contains as _;
        let lid_cells: std::collections::HashSet<Cell2, FixedState> = lid
            .iter()
            .map(|p| cell_of(f64::from(p.x), f64::from(p.y)))
            .collect();
        let dense: Vec<&Cell2> = self.cells.keys().filter(|c| self.is_dense(c)).collect();
        let reach = if dense.is_empty() {
            0.0
        } else {
            dense.iter().filter(|c| lid_cells.contains(c)).count() as f64 / dense.len() as f64
        };
        let poly = polygon(rect);
        let centre = |(i, j): Cell2| ((i as f64 + 0.5) * CELL_M, (j as f64 + 0.5) * CELL_M);
        let inside = |c: Cell2| {
            let (x, y) = centre(c);
            poly.contains(&Point::new(x, y))
        };
        let (mut lo, mut hi) = ((i64::MAX, i64::MAX), (i64::MIN, i64::MIN));
        for c in rect {
            let (i, j) = cell_of(c[0], c[1]);
            lo = (lo.0.min(i), lo.1.min(j));
            hi = (hi.0.max(i), hi.1.max(j));
        }
        let (mut total, mut held) = (0usize, 0usize);
        let mut empty: std::collections::HashSet<Cell2, FixedState> = Default::default();
        let mut seeds = Vec::new();
        for i in lo.0..=hi.0 {
            for j in lo.1..=hi.1 {
                if !inside((i, j)) {
                    continue;
                }
                total += 1;
                held += usize::from(lid_cells.contains(&(i, j)));
                let bare =
                    (-1..=1).all(|di| (-1..=1).all(|dj| !lid_cells.contains(&(i + di, j + dj))));
                if bare {
                    empty.insert((i, j));
                    if (-2..=2).any(|di| (-2..=2).any(|dj| !inside((i + di, j + dj)))) {
                        seeds.push((i, j));
                    }
                }
            }
        }
        let mut notch: std::collections::HashSet<Cell2, FixedState> = Default::default();
        while let Some(c) = seeds.pop() {
            if !notch.insert(c) {
                continue;
            }
            for di in -1..=1 {
                for dj in -1..=1 {
                    let n = (c.0 + di, c.1 + dj);
                    if empty.contains(&n) && !notch.contains(&n) {
                        seeds.push(n);
                    }
                }
            }
        }
        if total == 0 {
            return (reach, 0.0, 0.0);
        }
        let rest = (total - notch.len()).max(1);
        (
            reach,
            notch.len() as f64 / total as f64,
            held as f64 / rest as f64,
        )
    }

    /// The share of the cells inside `polygon` (1.5 cells in from its edges) that hold
    /// points.
    fn coverage(&self, polygon: &Polygon<f64>) -> f64 {
        let (mut x0, mut y0, mut x1, mut y1) = (f64::MAX, f64::MAX, f64::MIN, f64::MIN);
        for c in polygon.exterior().coords() {
            x0 = x0.min(c.x);
            y0 = y0.min(c.y);
            x1 = x1.max(c.x);
            y1 = y1.max(c.y);
        }
        let (lo, hi) = (cell_of(x0, y0), cell_of(x1, y1));
        let inside = |x: f64, y: f64| {
            use geo::Contains as _;
            polygon.contains(&Point::new(x, y))
        };
        let (mut cells, mut held) = (0usize, 0usize);
        for i in lo.0..=hi.0 {
            for j in lo.1..=hi.1 {
                // The cell and a cell's width around it inside the rectangle.
                let (cx, cy) = ((i as f64 + 0.5) * CELL_M, (j as f64 + 0.5) * CELL_M);
                let d = 1.5 * CELL_M;
                if [(-d, -d), (d, -d), (d, d), (-d, d)]
                    .iter()
                    .all(|(dx, dy)| inside(cx + dx, cy + dy))
                {
                    cells += 1;
                    held += usize::from(self.cells.contains_key(&(i, j)));
                }
            }
        }
        if cells == 0 {
            1.0
        } else {
            held as f64 / cells as f64
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn edges_land_where_the_points_end_not_where_noise_threw_the_outermost() {
        // Twenty rows of points 1 mm apart over 0..300 mm (standing for 300.0 +- 0.5
        // mm), each moved by up to +-2 mm: the extremes lie 2 mm beyond the ends.
        let mut s: Vec<f64> = Vec::new();
        for row in 0..20u64 {
            for i in 0..=300u64 {
                let k = (row * 301 + i).wrapping_mul(7919) % 1000;
                s.push(i as f64 * 0.001 + 0.002 * (k as f64 / 500.0 - 1.0));
            }
        }
        let min = s.iter().copied().fold(f64::MAX, f64::min);
        let max = s.iter().copied().fold(f64::MIN, f64::max);
        assert!(max - min > 0.3035, "{min} {max}");
        let shifted: Vec<f64> = s.iter().map(|v| v - min).collect();
        let (lo, hi) = edges(&shifted, max - min, 0.006, 0.006, 0.0);
        let (lo, hi) = (lo + min, hi + min);
        assert!((lo + 0.0005).abs() < 0.0003, "{lo}");
        assert!((hi - 0.3005).abs() < 0.0003, "{hi}");
    }

    /// The top of an object 160 mm across lying along x from -0.2 to 0.2 m, every 2 mm:
    /// across, a circle resting on the floor; along, level up to `level` from the middle,
    /// then (a bag's rounded end) a quarter ellipse down to the floor at 0.2 m.
    fn lying_top(level: f64) -> Vec<Point3> {
        let r = 0.08;
        let mut out = Vec::new();
        for i in 0..=200 {
            let x = -0.2 + f64::from(i) * 0.002;
            let end = if x.abs() <= level {
                1.0
            } else {
                let u = (x.abs() - level) / (0.2 - level);
                (1.0 - u * u).max(0.0).sqrt()
            };
            for j in 0..=80 {
                let y = -r + f64::from(j) * 0.002;
                let z = (r + (r * r - y * y).max(0.0).sqrt()) * end;
                out.push(Point3::new(x as f32, y as f32, z as f32));
            }
        }
        out
    }

    #[test]
    fn a_bag_with_a_round_section_and_rounded_ends_is_no_lying_tube() {
        // The lid strip: the crest's 5 cm wide band within 1 cm of the top.
        let strip = |half: f64| {
            [
                [-half, -0.025],
                [half, -0.025],
                [half, 0.025],
                [-half, 0.025],
            ]
        };
        let tube = lying_top(0.2);
        let found = lying_tube(&strip(0.2), &tube, 0.16, 0.01).expect("a tube");
        assert!((found.radius - 0.08).abs() < 0.002, "{}", found.radius);
        // The same section, but the top curves down over the last 6 cm of each end: the
        // crest strip is 28 cm long and the bag's ends lie beyond it.
        let bag = lying_top(0.14);
        assert!(lying_tube(&strip(0.14), &bag, 0.16, 0.01).is_none());
    }

    /// Points every 2 mm over the rectangle [x0, x1] x [y0, y1] at height z.
    fn lid_points(x: [f64; 2], y: [f64; 2], z: f64) -> Vec<Point3> {
        let steps = |r: [f64; 2]| ((r[1] - r[0]) / 0.002).round() as usize;
        let mut out = Vec::new();
        for i in 0..=steps(x) {
            for j in 0..=steps(y) {
                out.push(Point3::new(
                    (x[0] + i as f64 * 0.002) as f32,
                    (y[0] + j as f64 * 0.002) as f32,
                    z as f32,
                ));
            }
        }
        out
    }

    #[test]
    fn a_lower_parcel_beside_a_higher_one_is_found_and_both_are_flagged() {
        // Noise makes the lower lid reach 2 mm into the higher one's footprint: the two
        // rectangles overlap by a sliver, which does not make the lower one a fragment.
        let mut points = lid_points([-0.32, 0.0], [-0.085, 0.085], 0.225);
        points.extend(lid_points([-0.002, 0.35], [-0.075, 0.075], 0.177));
        let found = parcels(&PointCloud { points }, &DimensionConfig::default(), &[]).unwrap();
        assert_eq!(found.parcels.len(), 2, "{found:?}");
        assert!(found.parcels.iter().all(|p| !p.isolated), "{found:?}");
    }

    #[test]
    fn two_boxes_of_one_height_side_by_side_in_an_l_are_not_one_isolated_parcel() {
        // 377 x 166 and 217 x 113 mm, both 114 mm high, touching along a face: their lids
        // make one flat top whose outline is an L, no box's.
        let mut points = lid_points([0.0, 0.377], [0.0, 0.166], 0.114);
        points.extend(lid_points([0.379, 0.594], [0.0, 0.113], 0.114));
        let found = parcels(&PointCloud { points }, &DimensionConfig::default(), &[]).unwrap();
        assert_eq!(found.parcels.len(), 1, "{found:?}");
        assert_eq!(found.parcels[0].shape, Shape::Irregular, "{found:?}");
        assert!(!found.parcels[0].isolated, "{found:?}");
        // One box of the L's whole rectangle is one parcel.
        let points = lid_points([0.0, 0.594], [0.0, 0.166], 0.114);
        let found = parcels(&PointCloud { points }, &DimensionConfig::default(), &[]).unwrap();
        assert_eq!(found.parcels.len(), 1, "{found:?}");
        assert!(found.parcels[0].isolated, "{found:?}");
    }

    #[test]
    fn a_strip_of_side_wall_cut_off_by_holes_is_part_of_its_parcel() {
        // A dark box 100 x 95 x 66 mm whose side wall kept points only low down, 3 cm
        // below its lid (too far to join it): that strip stands under the lid's edge.
        let mut points = lid_points([0.0, 0.1], [0.0, 0.095], 0.066);
        for i in 0..50 {
            for k in 0..10 {
                let (y, z) = (i as f32 * 0.002, 0.012 + k as f32 * 0.002);
                points.push(Point3::new(0.1005, y, z));
            }
        }
        let found = parcels(&PointCloud { points }, &DimensionConfig::default(), &[]).unwrap();
        assert_eq!(found.parcels.len(), 1, "{found:?}");
        assert!(found.parcels[0].isolated);
    }

    #[test]
    fn a_wall_seen_from_outside_places_its_side_where_the_lid_ends_short() {
        // A 300 x 200 x 200 mm box from x = y = 0; the lid's points stop 2 mm short of
        // x = 0.3 (the filter rounded that corner), the wall at x = 0.3 is seen by a
        // camera beyond it (x = 0.8, 1 m up, looking down and back at the box).
        let mut cluster = Vec::new();
        for i in 0..=149 {
            for j in 0..=100 {
                cluster.push(Point3::new(i as f32 * 0.002, j as f32 * 0.002, 0.2));
            }
        }
        for k in 0..100 {
            for j in 0..=100 {
                let x = 0.3 + 0.0005 * ((k + j) % 3) as f32 - 0.0005;
                cluster.push(Point3::new(x, j as f32 * 0.002, k as f32 * 0.002));
            }
        }
        // The camera's z axis (looking) from (0.8, 0.1, 1.0) towards (0.15, 0.1, 0.1).
        let look = nalgebra::Vector3::new(-0.65f32, 0.0, -0.9).normalize();
        let x_axis = nalgebra::Vector3::new(0.0f32, 1.0, 0.0);
        let y_axis = look.cross(&x_axis);
        let view = View {
            to_common: Transform {
                linear: nalgebra::Matrix3::from_columns(&[x_axis, y_axis, look]),
                translation: nalgebra::Vector3::new(0.8, 0.1, 1.0),
            },
            fx: 900.0,
            fy: 900.0,
            ppx: 640.0,
            ppy: 360.0,
            width: 1280,
            height: 720,
        };
        let lid = [[0.0, 0.0], [0.298, 0.0], [0.298, 0.2], [0.0, 0.2]];
        let found = walls(&lid, &cluster, 0.2, &[view], 0.0015);
        // Side 1 runs from corner 1 to corner 2, at x = 0.298: its wall lies 2 mm out.
        let out = found[1].expect("the wall facing the camera");
        assert!((out - 0.002).abs() < 0.0003, "{out}");
        // The camera stands beyond no other side.
        assert_eq!([found[0], found[2], found[3]], [None, None, None]);
        // Without cameras no wall is trusted.
        assert_eq!(walls(&lid, &cluster, 0.2, &[], 0.0015), [None; 4]);
    }

    #[test]
    fn a_low_lid_blurred_into_the_floor_is_measured_to_its_step() {
        // A 300 x 200 x 35 mm box whose edges the spatial filter smoothed: the height
        // falls from the lid to the floor over about 2 cm around each edge, passing half
        // the height at the edge (seen from straight above; 2 mm between points as a D415
        // 1.8 m up); the floor cut drops what is
        // lower than 1 cm.
        let mut points = Vec::new();
        for i in 0..=180 {
            for j in 0..=130 {
                let (x, y) = (-0.03 + i as f64 * 0.002, -0.03 + j as f64 * 0.002);
                let out = (-x).max(x - 0.3).max(-y).max(y - 0.2);
                let z = 0.035 * 0.5 * (1.0 - (out / 0.006).tanh());
                if z >= 0.01 {
                    points.push(Point3::new(x as f32, y as f32, z as f32));
                }
            }
        }
        let found = parcels(&PointCloud { points }, &DimensionConfig::default(), &[]).unwrap();
        let d = &found.parcels[0].dimensions;
        assert_eq!(found.parcels[0].shape, Shape::Cuboid);
        assert!((d.length_mm - 300.0).abs() < 1.5, "{d:?}");
        assert!((d.width_mm - 200.0).abs() < 1.5, "{d:?}");
    }

    #[test]
    fn the_speckle_of_a_noisy_floor_in_the_cloud_does_not_join_parcels_apart() {
        // An unprepared camera far up sends the floor with 5.5 mm of noise: 3.5 % of its
        // points land above the 1 cm cut, a few millimetres apart, all over the floor.
        // Two 200 x 200 x 100 mm boxes stand 200 mm apart on it.
        let mut state = 0x2545_f491_4f6c_dd1du64;
        let mut uniform = move || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            (state >> 11) as f64 / (1u64 << 53) as f64
        };
        let on_box = |x: f64, y: f64| (0.1..0.3).contains(&x.abs()) && (-0.1..0.1).contains(&y);
        let mut points = Vec::new();
        for i in 0..400 {
            for j in 0..400 {
                let (x, y) = (-0.4 + i as f64 * 0.002, -0.4 + j as f64 * 0.002);
                let noise = (-2.0 * uniform().max(1e-12).ln()).sqrt()
                    * (std::f64::consts::TAU * uniform()).cos();
                // (The lids, nearer, get a millimetre.)
                let z = if on_box(x, y) {
                    0.1 + 0.001 * noise
                } else {
                    0.0055 * noise
                };
                points.push(Point3::new(x as f32, y as f32, z as f32));
            }
        }
        // Their side walls, seen from the floor up to the lids, join each lid to the floor.
        for k in 0..50 {
            let z = k as f32 * 0.002;
            for i in 0..100 {
                for x0 in [-0.3f32, 0.1] {
                    let x = x0 + i as f32 * 0.002;
                    points.push(Point3::new(x, -0.1, z));
                    points.push(Point3::new(x, 0.1, z));
                }
                let y = -0.1 + i as f32 * 0.002;
                for x in [-0.3f32, -0.1, 0.1, 0.3] {
                    points.push(Point3::new(x, y, z));
                }
            }
        }
        let found = parcels(&PointCloud { points }, &DimensionConfig::default(), &[]).unwrap();
        // Joined through the speckle they would be one object with two tops.
        assert_eq!(found.parcels.len(), 2, "{found:?}");
        for p in &found.parcels {
            assert!(p.isolated, "{found:?}");
            assert!((p.dimensions.length_mm - 200.0).abs() < 10.0, "{found:?}");
        }
    }

    #[test]
    fn a_dropped_object_standing_beside_the_kept_one_takes_its_isolation() {
        let rect = |x0: f64, y0: f64, x1: f64, y1: f64| [[x0, y0], [x1, y0], [x1, y1], [x0, y1]];
        let fit = |corners, points| ParcelFit {
            dimensions: rect_dimensions(corners, 0.2, points),
            shape: Shape::Cuboid,
            fit: 1.0,
            tops: 1,
            isolated: true,
            coverage: 1.0,
            out_of_view: false,
            complete: true,
        };
        // The kept parcel: 0.3 x 0.3 m, 10,000 points.
        let kept = fit(rect(0.0, 0.0, 0.3, 0.3), 10_000);
        // Points on a 1 cm grid over x0..x1, y 0..0.2 m.
        let grid = |x0: f64, x1: f64| -> Vec<Point3> {
            let mut v = Vec::new();
            let mut x = x0;
            while x < x1 {
                for j in 0..20 {
                    v.push(Point3::new(x as f32, j as f32 * 0.01, 0.1));
                }
                x += 0.01;
            }
            v
        };
        // A lower box beside it whose outline ran 10 cm into the kept one: a neighbour.
        let beside = grid(0.31, 0.55);
        let lower = fit(rect(0.2, 0.0, 0.55, 0.2), 3_000);
        assert!(neighbour_of(&lower, &beside, &kept));
        // The same points but a few of them (a ring of flying pixels): not a parcel.
        let ring = fit(rect(0.2, 0.0, 0.55, 0.2), 500);
        assert!(!neighbour_of(&ring, &beside, &kept));
        // A strip of the kept one's own wall, under its edge: not beside it.
        let under = grid(0.22, 0.3);
        let strip = fit(rect(0.2, 0.0, 0.3, 0.2), 3_000);
        assert!(!neighbour_of(&strip, &under, &kept));
    }

    #[test]
    fn a_view_sees_what_lies_inside_its_image() {
        let down = Transform {
            linear: nalgebra::Matrix3::new(1.0, 0.0, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0, -1.0),
            translation: nalgebra::Vector3::new(0.0, 0.0, 1.0),
        };
        let v = View {
            to_common: down,
            fx: 600.0,
            fy: 600.0,
            ppx: 320.0,
            ppy: 240.0,
            width: 640,
            height: 480,
        };
        assert!(v.sees(&Point3::new(0.0, 0.0, 0.0), 3.0));
        assert!(v.sees(&Point3::new(0.5, 0.0, 0.0), 3.0));
        assert!(!v.sees(&Point3::new(0.6, 0.0, 0.0), 3.0));
        assert!(!v.sees(&Point3::new(0.0, 0.0, 2.0), 3.0));
    }
}
