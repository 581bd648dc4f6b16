//! Every parcel on the table (docs/design.md §6): the objects standing on the floor, each
//! measured as the smallest cuboid that encloses it, with how well a cuboid fits, whether
//! it touches another parcel and whether the data show all of it.
//!
//! Per object (a cluster of [`crate::dimension`]'s grid):
//! - the top: the lid band below a robust maximum of z, as [`crate::dimension`] has always
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
//!   around all its dense points (OIML R 129: the smallest enclosing box);
//! - tops: flat regions of a height map of the object, connected where neighbouring cells
//!   differ by less than a step; two large ones mean two parcels side by side;
//! - coverage: the share of cells inside the footprint that hold points (holes from dark
//!   or shiny surfaces lower it); with camera views, whether every top corner is inside
//!   some camera's image.

use std::collections::HashMap;

use foldhash::fast::FixedState;
use geo::{
    Area, ConvexHull, Coord, Distance as _, Euclidean, LineString, MultiPoint, Point, Polygon,
};

use crate::dimension::{
    DimensionConfig, DimensionError, Dimensions, above_floor, clusters, lid, min_rect,
    rect_dimensions, robust_height,
};
use crate::{Point3, PointCloud, Transform};

/// Side of a height-map cell, metres.
const CELL_M: f64 = 0.005;
/// Neighbouring cells of one top differ in height by less than this (metres), or by the
/// lid band when that is deeper.
const TOP_STEP_M: f32 = 0.010;
/// A top counts when this many of its cells have all eight neighbours in it (a core of
/// about 2 x 2 cm), and it has at least [`TOP_SHARE`] of the largest top's cells.
const TOP_CORE_CELLS: usize = 16;
/// See [`TOP_CORE_CELLS`].
const TOP_SHARE: f64 = 0.05;
/// A cuboid's lid covers at least this share of its rectangle (a disc covers 0.785).
const CUBOID_FIT: f64 = 0.93;
/// Of a cuboid, at most this share of the dense points lies farther outside the lid's
/// rectangle than [`OUTSIDE_M`] (the sides of a lying tube or a polybag's belly do).
const CUBOID_OUTSIDE: f64 = 0.01;
/// See [`CUBOID_OUTSIDE`], metres.
const OUTSIDE_M: f64 = 0.008;
/// A cell is dense when it holds at least this share of the median cell's points.
const DENSE_SHARE: f64 = 0.15;
/// Objects with fewer points than this share of the largest one's are not parcels
/// (fragments of flying pixels, specks).
const MIN_SHARE: f64 = 0.005;
/// Parcels whose footprints come closer than this (metres) are side by side.
const TOUCH_M: f64 = 0.02;
/// A top corner counts as seen when it projects at least this far inside an image.
const VIEW_MARGIN_PX: f32 = 3.0;

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
    /// footprint within 2 cm.
    pub isolated: bool,
    /// The share of the footprint's cells that hold points (1 without holes).
    pub coverage: f64,
    /// A top corner lies outside every camera's image (only known with views).
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

/// Measures every object standing on the floor of `cloud` (output frame: z up, floor at
/// z = 0, metres). `views` are the cameras the cloud came from, if known: a parcel with a
/// top corner outside all of them is not complete.
pub fn parcels(
    cloud: &PointCloud,
    config: &DimensionConfig,
    views: &[View],
) -> Result<Parcels, DimensionError> {
    config.validate()?;
    let above = above_floor(cloud, config);
    let clusters = clusters(&above, config.cluster_radius_m)?;
    let largest_points = clusters.first().map_or(0, Vec::len);
    let needed = config
        .min_points
        .max((largest_points as f64 * MIN_SHARE).ceil() as usize);
    let mut found = Vec::new();
    let mut first_error = None;
    for cluster in clusters.iter().take_while(|c| c.len() >= needed) {
        match fit(cluster, config, views) {
            Ok(f) => found.push(f),
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
    Ok(Parcels {
        parcels: found,
        largest_points,
    })
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
    let hull_rect = min_rect(lid.points.iter().map(xy)).ok_or(DimensionError::Footprint)?;
    let margin = f64::from(lid.band_m) + 0.003;
    // The edges from the points within a quarter band (about one noise deviation) of the
    // top, on both sides, so that noise moves as many outwards as inwards, and few of the
    // points piled up on a side wall's top count.
    let slab = (lid.band_m / 4.0).max(0.001);
    let flat: Vec<Point3> = lid
        .points
        .iter()
        .filter(|p| (p.z - height_m).abs() <= slab)
        .copied()
        .collect();
    let lid_rect = refine(hull_rect, &flat, margin);
    let lid_area = hull_area(lid.points.iter().map(xy));
    let fit = (lid_area / rect_area(&hull_rect)).min(1.0);

    let map = HeightMap::new(cluster);
    let dense = map.dense_points(cluster);
    let tops = map.tops(TOP_STEP_M.max(lid.band_m));
    let outside = share_outside(&lid_rect, dense.iter().map(xy), OUTSIDE_M);
    let shape = if tops <= 1 && fit >= CUBOID_FIT && outside <= CUBOID_OUTSIDE {
        Shape::Cuboid
    } else {
        Shape::Irregular
    };
    let corners = match shape {
        Shape::Cuboid => lid_rect,
        Shape::Irregular => min_rect(dense.iter().map(xy)).unwrap_or(hull_rect),
    };
    let coverage = map.coverage(&corners);
    let top = height_m;
    let out_of_view = !views.is_empty()
        && corners.iter().any(|c| {
            let p = Point3::new(c[0] as f32, c[1] as f32, top);
            !views.iter().any(|v| v.sees(&p, VIEW_MARGIN_PX))
        });
    Ok(ParcelFit {
        dimensions: rect_dimensions(corners, f64::from(height_m), cluster.len()),
        shape,
        fit,
        tops,
        isolated: tops <= 1,
        coverage,
        out_of_view,
        complete: !out_of_view && coverage >= f64::from(config.min_coverage),
    })
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

fn hull_area(points: impl Iterator<Item = [f64; 2]>) -> f64 {
    let all: MultiPoint<f64> = points.map(|[x, y]| Point::new(x, y)).collect();
    all.convex_hull().unsigned_area()
}

/// The rectangle `corners` (in order around it) with each edge moved to where `lid`'s
/// points put it (see [`edges`]).
pub(crate) fn refine(corners: [[f64; 2]; 4], lid: &[Point3], margin: f64) -> [[f64; 2]; 4] {
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
    let (a0, a1) = edges(&mut sa, la, margin);
    let (b0, b1) = edges(&mut sb, lb, margin);
    let at = |s: f64, t: f64| [c0[0] + a[0] * s + b[0] * t, c0[1] + a[1] * s + b[1] * t];
    [at(a0, b0), at(a1, b0), at(a1, b1), at(a0, b1)]
}

/// The two edges along one axis of positions `s` in about [0, `len`]. From a line
/// `margin` inside each end, the points beyond it are counted in 1 mm bins, each bin
/// at most 1.5 times the density of the band just inside the line; the edge lies where that
/// many points at that density would end. Noise moves points about an edge without
/// adding any, so the count keeps the edge where the outermost points do not; the cap
/// keeps points piled up on the edge itself (the top of a side wall seen from the side)
/// from counting as lid. An axis too short for two such bands keeps the hull's edges.
fn edges(s: &mut [f64], len: f64, margin: f64) -> (f64, f64) {
    const BIN_M: f64 = 0.001;
    let window = (2.0 * margin).max(0.01);
    if len < 2.0 * (margin + window) {
        return (0.0, len);
    }
    s.sort_unstable_by(f64::total_cmp);
    let count = |lo: f64, hi: f64| s.partition_point(|v| *v < hi) - s.partition_point(|v| *v < lo);
    // The edge moves at most `margin` inwards (holes along an edge thin it), and never
    // beyond the outermost point.
    let limit = margin;
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
        while at < limit {
            let (x0, x1) = (line + outwards * at, line + outwards * (at + BIN_M));
            mass += (count(x0.min(x1), x0.max(x1)) as f64).min(cap);
            at += BIN_M;
        }
        line + outwards * (mass / density).min(limit)
    };
    (place(margin, -1.0), place(len - margin, 1.0))
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

/// The object's points binned into [`CELL_M`] cells in (x, y): count and highest z.
struct HeightMap {
    cells: HashMap<Cell2, (u32, f32), FixedState>,
    /// Cells with fewer points are not dense.
    dense_min: u32,
}

fn cell_of(x: f64, y: f64) -> Cell2 {
    ((x / CELL_M).floor() as i64, (y / CELL_M).floor() as i64)
}

impl HeightMap {
    fn new(points: &[Point3]) -> Self {
        let mut cells: HashMap<Cell2, (u32, f32), FixedState> = HashMap::default();
        for p in points {
            let e = cells
                .entry(cell_of(f64::from(p.x), f64::from(p.y)))
                .or_insert((0, f32::NEG_INFINITY));
            e.0 += 1;
            e.1 = e.1.max(p.z);
        }
        let mut counts: Vec<u32> = cells.values().map(|c| c.0).collect();
        let mid = counts.len() / 2;
        let median = if counts.is_empty() {
            0
        } else {
            *counts.select_nth_unstable(mid).1
        };
        let dense_min = ((f64::from(median) * DENSE_SHARE).ceil() as u32).max(2);
        Self { cells, dense_min }
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

    /// The number of tops: regions of dense cells connected (8-neighbourhood) where
    /// neighbouring highest points differ by less than `step`, counted when their core
    /// (cells whose eight neighbours are all in the region) has [`TOP_CORE_CELLS`] and
    /// their cells are at least [`TOP_SHARE`] of the largest region's.
    fn tops(&self, step: f32) -> usize {
        let mut region: HashMap<Cell2, usize, FixedState> = HashMap::default();
        let mut sizes: Vec<(usize, usize)> = Vec::new();
        let mut dense: Vec<Cell2> = self
            .cells
            .iter()
            .filter(|(_, v)| v.0 >= self.dense_min)
            .map(|(c, _)| *c)
            .collect();
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
                    if region.contains_key(&n) || !self.is_dense(&n) {
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

    /// The share of the cells inside the rectangle `corners` (one cell in from its edges)
    /// that hold points.
    fn coverage(&self, corners: &[[f64; 2]; 4]) -> f64 {
        let polygon = polygon(corners);
        let (mut x0, mut y0, mut x1, mut y1) = (f64::MAX, f64::MAX, f64::MIN, f64::MIN);
        for c in corners {
            x0 = x0.min(c[0]);
            y0 = y0.min(c[1]);
            x1 = x1.max(c[0]);
            y1 = y1.max(c[1]);
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
        let mut shifted: Vec<f64> = s.iter().map(|v| v - min).collect();
        let (lo, hi) = edges(&mut shifted, max - min, 0.006);
        let (lo, hi) = (lo + min, hi + min);
        assert!((lo + 0.0005).abs() < 0.0003, "{lo}");
        assert!((hi - 0.3005).abs() < 0.0003, "{hi}");
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
