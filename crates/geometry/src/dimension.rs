//! Parcel dimensioning (docs/design.md §6): points in the output frame (z up, floor at
//! z = 0) -> drop points below a minimum height -> keep the largest connected cluster ->
//! height from a robust maximum of z -> convex hull of (x, y) -> minimum-area rectangle
//! (one side always lies on a hull edge, so geo's search over hull edges is exact) ->
//! length >= width.
//!
//! The robust maximum: take the `height_quantile` quantile of z over the cluster (so the
//! highest outliers and noise tails are ignored), then the median z of the cluster points
//! within `top_band_m` below it. On a box this is the median of the lid, which is unbiased
//! by depth noise, where a plain quantile would read about two noise deviations high.

use std::num::NonZeroUsize;

use geo::algorithm::convex_hull::quick_hull;
use geo::{Coord, MinimumRotatedRect, Polygon};
use rayon::prelude::*;

use crate::cloud::is_finite;
use crate::grid::{Block, Cell, CellMap, Columns, Grid, cell_of};
use crate::index::Index;
use crate::{Point3, PointCloud};

/// Thresholds of [`crate::dimension()`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DimensionConfig {
    /// Points lower than this (metres above the floor) are floor, not parcel.
    pub min_height_m: f32,
    /// Two points closer than this (metres) belong to one object (two points in one cell
    /// of this side, up to 1.7 times as far apart, do too; see `clusters`).
    pub cluster_radius_m: f32,
    /// Quantile of z taken as the top before the band median (in (0, 1]).
    pub height_quantile: f32,
    /// Depth of the band below that quantile whose median is the height (metres, >= 0).
    pub top_band_m: f32,
    /// Fewer points in the largest cluster is an error (at least 3).
    pub min_points: usize,
    /// Deepest band below the height whose points make the footprint (metres, > 0): the
    /// upper surface, as the thesis measures it. The band used is four robust standard
    /// deviations of the lid's z (at least 3 mm), up to this; points lower down (sides
    /// seen at an angle, flying pixels between an edge and the floor) lie outside a
    /// parcel's lid.
    pub lid_band_m: f32,
    /// A lid point with fewer other lid points than this within three typical point
    /// spacings is a flying pixel and not part of the footprint.
    pub min_neighbours: usize,
    /// A parcel is complete when at least this share of the cells inside its footprint
    /// hold points (in [0, 1]; holes from dark or shiny surfaces lower the share).
    pub min_coverage: f32,
}

impl Default for DimensionConfig {
    /// 1 cm above the floor, 1 cm cluster radius, 99 % quantile, 1 cm top band, 50 points,
    /// a 2 cm lid band, 4 neighbours, 80 % coverage.
    fn default() -> Self {
        Self {
            min_height_m: 0.01,
            cluster_radius_m: 0.01,
            height_quantile: 0.99,
            top_band_m: 0.01,
            min_points: 50,
            lid_band_m: 0.02,
            min_neighbours: 4,
            min_coverage: 0.8,
        }
    }
}

/// Why no measurement came out.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[non_exhaustive]
pub enum DimensionError {
    /// A configuration value is out of range.
    #[error("dimension: `{field}` must be {allowed}")]
    InvalidConfig {
        /// The [`DimensionConfig`] field.
        field: &'static str,
        /// What is allowed.
        allowed: &'static str,
    },
    /// The largest object above the floor has too few points.
    #[error(
        "dimension: the largest object above the floor has {found} points, at least {needed} are needed"
    )]
    TooFewPoints {
        /// Points in the largest cluster (0 if nothing is above the floor).
        found: usize,
        /// The minimum.
        needed: usize,
    },
    /// The cloud is too large for the nearest-neighbour index.
    #[error("dimension: {points} points above the floor are more than the index can number")]
    TooManyPoints {
        /// Points above the floor.
        points: usize,
    },
    /// The footprint has no area-defining hull (all points coincide).
    #[error("dimension: the object's footprint is a single point")]
    Footprint,
}

/// A measured parcel.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Dimensions {
    /// Longer side of the footprint rectangle, millimetres.
    pub length_mm: f64,
    /// Shorter side of the footprint rectangle, millimetres.
    pub width_mm: f64,
    /// Height above the floor, millimetres.
    pub height_mm: f64,
    /// Direction of the long side from the +x axis towards +y, degrees in (-90, 90].
    pub yaw_deg: f64,
    /// Footprint rectangle corners [x, y] in metres, in order around the rectangle.
    pub corners_m: [[f64; 2]; 4],
    /// length x width x height, litres.
    pub volume_l: f64,
    /// Points in the measured cluster.
    pub points: usize,
}

impl DimensionConfig {
    pub(crate) fn validate(&self) -> Result<(), DimensionError> {
        let checks = [
            (
                self.min_height_m.is_finite(),
                "min_height_m",
                "a finite number of metres",
            ),
            (
                self.cluster_radius_m.is_finite() && self.cluster_radius_m > 0.0,
                "cluster_radius_m",
                "a positive finite number of metres",
            ),
            (
                self.height_quantile > 0.0 && self.height_quantile <= 1.0,
                "height_quantile",
                "in (0, 1]",
            ),
            (
                self.top_band_m.is_finite() && self.top_band_m >= 0.0,
                "top_band_m",
                "a finite number of metres >= 0",
            ),
            (self.min_points >= 3, "min_points", "at least 3"),
            (
                self.lid_band_m.is_finite() && self.lid_band_m > 0.0,
                "lid_band_m",
                "a positive finite number of metres",
            ),
            (
                (0.0..=1.0).contains(&self.min_coverage),
                "min_coverage",
                "in [0, 1]",
            ),
        ];
        match checks.into_iter().find(|(ok, _, _)| !ok) {
            None => Ok(()),
            Some((_, field, allowed)) => Err(DimensionError::InvalidConfig { field, allowed }),
        }
    }
}

/// The points of `cloud` at or above `min_height_m` that are finite.
pub(crate) fn above_floor(cloud: &PointCloud, config: &DimensionConfig) -> Vec<Point3> {
    cloud
        .points
        .iter()
        .copied()
        .filter(|p| is_finite(p) && p.z >= config.min_height_m)
        .collect()
}

/// The convex hull of `points` (x, y in metres): geo's quick hull over them in their
/// order, as `MultiPoint::convex_hull` runs it, without the multipoint (which it copies
/// into coordinates first: two buffers of 16 bytes a point, where one does).
pub(crate) fn hull(points: impl Iterator<Item = [f64; 2]>) -> Polygon<f64> {
    let mut coords: Vec<Coord<f64>> = points.map(|[x, y]| Coord { x, y }).collect();
    Polygon::new(quick_hull(&mut coords), Vec::new())
}

/// The minimum-area rectangle around the points whose convex hull is `hull` (x, y in
/// metres), as its four corners in order around it; `None` when they span no area.
pub(crate) fn rect_around(hull: &Polygon<f64>) -> Option<[[f64; 2]; 4]> {
    let rect = hull.minimum_rotated_rect()?;
    match rect.exterior().0.as_slice() {
        [a, b, c, d, ..] => Some([a, b, c, d].map(|c| [c.x, c.y])),
        _ => None,
    }
}

/// The dimensions of the rectangle `corners` (in order around it) at `height_m` over
/// `points` points: length >= width, yaw of the long side in (-90, 90].
pub(crate) fn rect_dimensions(corners: [[f64; 2]; 4], height_m: f64, points: usize) -> Dimensions {
    let [c0, c1, c2, _] = corners;
    let e0 = [c1[0] - c0[0], c1[1] - c0[1]];
    let e1 = [c2[0] - c1[0], c2[1] - c1[1]];
    let (n0, n1) = (e0[0].hypot(e0[1]), e1[0].hypot(e1[1]));
    let (length_m, width_m, long) = if n0 >= n1 { (n0, n1, e0) } else { (n1, n0, e1) };
    let mut yaw_deg = long[1].atan2(long[0]).to_degrees();
    if yaw_deg <= -90.0 {
        yaw_deg += 180.0;
    } else if yaw_deg > 90.0 {
        yaw_deg -= 180.0;
    }
    Dimensions {
        length_mm: length_m * 1e3,
        width_mm: width_m * 1e3,
        height_mm: height_m * 1e3,
        yaw_deg,
        corners_m: corners,
        volume_l: length_m * width_m * height_m * 1e3,
        points,
    }
}

/// The sets of points connected through a grid of `radius_m` cells, the largest first:
/// points in one cell belong together, and two touching cells (26-neighbourhood) do when
/// a point of one lies within `radius_m` of a point of the other, so points closer than
/// `radius_m` always do and points more than 1.74 radii apart (a cell's diagonal) only
/// through others. (Touching cells alone joined points up to 3.5 radii apart: with the
/// 20 mm radius of before, parcels 60-70 mm apart under several cameras were one object.)
/// Near linear in the number of points: on a surface the first points compared are
/// neighbours. Sets of equal size go in the order of their lowest input index; the points
/// of a set keep their input order.
pub(crate) fn clusters(
    points: &[Point3],
    radius_m: f32,
) -> Result<Vec<Vec<Point3>>, DimensionError> {
    if u32::try_from(points.len()).is_err() {
        return Err(DimensionError::TooManyPoints {
            points: points.len(),
        });
    }
    let grid = Grid::new(points, radius_m);
    // Union-find over cells; a set's root is its lowest cell number, and cells are
    // numbered in order of their lowest point.
    let mut number: CellMap<usize> = CellMap::default();
    let mut cells: Vec<(Cell, usize)> = grid
        .cells()
        .map(|(cell, members)| (*cell, members.iter().min().copied().unwrap_or(0) as usize))
        .collect();
    cells.sort_unstable_by_key(|&(_, first)| first);
    for (n, (cell, _)) in cells.iter().enumerate() {
        number.insert(*cell, n);
    }
    let mut parent: Vec<usize> = (0..cells.len()).collect();
    fn root(parent: &mut [usize], mut i: usize) -> usize {
        while parent[i] != i {
            parent[i] = parent[parent[i]];
            i = parent[i];
        }
        i
    }
    let reach = radius_m * radius_m;
    let near = |a: &[u32], b: &[u32]| {
        a.iter().any(|&i| {
            let p = points[i as usize];
            b.iter()
                .any(|&j| (points[j as usize] - p).norm_squared() <= reach)
        })
    };
    for (n, (cell, _)) in cells.iter().enumerate() {
        let members = grid.members(*cell);
        for neighbour in grid.occupied_around(*cell) {
            let (a, b) = (root(&mut parent, n), root(&mut parent, number[&neighbour]));
            if a != b && near(members, grid.members(neighbour)) {
                parent[a.max(b)] = a.min(b);
            }
        }
    }
    let mut size = vec![0usize; cells.len()];
    for (cell, members) in grid.cells() {
        let r = root(&mut parent, number[cell]);
        size[r] += members.len();
    }
    // Roots in order of size, the lowest (first point) first among equals.
    let mut roots: Vec<usize> = (0..size.len()).filter(|&r| size[r] > 0).collect();
    roots.sort_by(|&a, &b| size[b].cmp(&size[a]).then(a.cmp(&b)));
    let mut slot = vec![usize::MAX; cells.len()];
    for (k, &r) in roots.iter().enumerate() {
        slot[r] = k;
    }
    let mut out: Vec<Vec<Point3>> = roots.iter().map(|&r| Vec::with_capacity(size[r])).collect();
    for p in points {
        let r = root(&mut parent, number[&grid.cell(p)]);
        out[slot[r]].push(*p);
    }
    Ok(out)
}

/// The lid: points of the cluster in the lid band below `height_m` that have at least
/// `min_neighbours` other lid points within three typical point spacings (the median
/// distance from a lid point to its nearest neighbour, over a sample).
pub(crate) struct Lid {
    /// Its points.
    pub(crate) points: Vec<Point3>,
    /// The depth of the band, metres.
    pub(crate) band_m: f32,
}

pub(crate) fn lid(
    cluster: &[Point3],
    height_m: f32,
    config: &DimensionConfig,
) -> Result<Lid, DimensionError> {
    let band_m = lid_band(cluster, height_m, config);
    let floor = (height_m - band_m).max(config.min_height_m);
    let band: Vec<Point3> = cluster.iter().copied().filter(|p| p.z >= floor).collect();
    if band.len() < 2 || config.min_neighbours == 0 {
        return Ok(Lid {
            points: band,
            band_m,
        });
    }
    if u32::try_from(band.len()).is_err() {
        return Err(DimensionError::TooManyPoints { points: band.len() });
    }
    const SAMPLES: usize = 1000;
    let step = (band.len() / SAMPLES).max(1);
    let samples: Vec<usize> = (0..band.len()).step_by(step).collect();
    let mut spacing = match spacings_near(&band, &samples) {
        Some(found) => found,
        None => spacings_indexed(&band, &samples)?,
    };
    spacing.sort_unstable_by(f32::total_cmp);
    let Some(&median) = spacing.get(spacing.len() / 2) else {
        return Ok(Lid {
            points: band,
            band_m,
        });
    };
    let radius = 3.0 * median.max(1e-4);
    let crowded = crowded(&band, radius, config.min_neighbours, CELLS_PER_POINT);
    // The lid in the band's own buffer, in order (a new one was fresh pages).
    let mut points = band;
    let mut keep = crowded.into_iter();
    points.retain(|_| keep.next() == Some(true));
    Ok(Lid { points, band_m })
}

/// The distance from each of `samples` (indices into `points`) to its nearest other point
/// that is not at the same place: a cloud merged from cameras that see the same thing (the
/// same camera served twice) holds exact duplicates, whose distance 0 would shrink the
/// radius to nothing. A sample with three or more duplicates has none (its four nearest
/// points are all at its place). Through a k-d tree of all the points.
fn spacings_indexed(points: &[Point3], samples: &[usize]) -> Result<Vec<f32>, DimensionError> {
    let index = Index::new(points).map_err(|e| DimensionError::TooManyPoints { points: e.0 })?;
    let four = NonZeroUsize::new(4).unwrap_or(NonZeroUsize::MIN);
    Ok(samples
        .iter()
        .filter_map(|&i| {
            let p = &points[i];
            let near = index.nearest_n(p, four);
            near.iter()
                .map(|&j| (points[j] - p).norm())
                .find(|d| *d > 0.0)
        })
        .collect())
}

/// [`spacings_indexed`] without the tree: the points in the 27 cells around each sample,
/// of a grid whose cells are four spacings wide were the points spread evenly over
/// their bounding box in (x, y), are all looked at (one pass over the points, where
/// building the tree cost as much as the lid's neighbour filter). `None` when a sample's
/// nearest point might lie beyond those cells (a sparse or uneven cloud).
fn spacings_near(points: &[Point3], samples: &[usize]) -> Option<Vec<f32>> {
    spacings_in_cells(points, samples, CELLS_PER_POINT)
}

/// [`spacings_near`], through a [`Block`] when its box holds at most `cells_per_point`
/// cells a point (the points sorted by cell once, without hashing each to find it among
/// the samples' cells), else through a hash map of the samples' cells: both look at the
/// same cells, so the answers are the same.
fn spacings_in_cells(
    points: &[Point3],
    samples: &[usize],
    cells_per_point: usize,
) -> Option<Vec<f32>> {
    let (mut low, mut high) = ([f32::MAX; 2], [f32::MIN; 2]);
    for p in points {
        low = [low[0].min(p.x), low[1].min(p.y)];
        high = [high[0].max(p.x), high[1].max(p.y)];
    }
    let area = f64::from(high[0] - low[0]) * f64::from(high[1] - low[1]);
    let size = (4.0 * (area / points.len().max(1) as f64).sqrt()).max(1e-4) as f32;
    // A point outside the 27 cells lies more than a cell away along some axis (less the
    // rounding of the cell coordinates): a nearest point within 0.9 cells is the nearest.
    let certain = 0.9 * size;
    // The nearest distance of sample `p` among `others` (it among them), `None` for a
    // sample with three or more duplicates.
    let nearest = |p: &Point3, others: &mut dyn Iterator<Item = &Point3>| {
        let (mut same, mut best) = (0usize, f32::INFINITY);
        for q in others {
            let d = (q - p).norm();
            if d > 0.0 {
                best = best.min(d);
            } else {
                same += 1;
            }
        }
        (same < 4).then_some(best)
    };
    let max_cells = cells_per_point
        .saturating_mul(points.len())
        .saturating_add(64);
    if let Some(block) = Block::new(points, size, max_cells) {
        let mut at_of = vec![0u32; points.len()];
        for at in 0..points.len() {
            at_of[block.index(at)] = at as u32;
        }
        let sorted = block.points();
        let mut out = Vec::with_capacity(samples.len());
        for &i in samples {
            let runs = block.around(at_of[i] as usize);
            let Some(best) = nearest(&points[i], &mut runs.flat_map(|r| &sorted[r])) else {
                continue;
            };
            if best > certain {
                return None;
            }
            out.push(best);
        }
        return Some(out);
    }
    let around = |(x, y, z): Cell| {
        (-1..=1).flat_map(move |dx| {
            (-1..=1).flat_map(move |dy| (-1..=1).map(move |dz| (x + dx, y + dy, z + dz)))
        })
    };
    let mut near: CellMap<Vec<u32>> = CellMap::default();
    for &i in samples {
        for c in around(cell_of(&points[i], size)) {
            near.entry(c).or_default();
        }
    }
    for (j, p) in points.iter().enumerate() {
        if let Some(members) = near.get_mut(&cell_of(p, size)) {
            members.push(j as u32);
        }
    }
    let mut out = Vec::with_capacity(samples.len());
    for &i in samples {
        let p = &points[i];
        let mut others = around(cell_of(p, size)).flat_map(|c| {
            near.get(&c)
                .map_or(&[][..], Vec::as_slice)
                .iter()
                .map(|&j| &points[j as usize])
        });
        let Some(best) = nearest(p, &mut others) else {
            continue;
        };
        if best > certain {
            return None;
        }
        out.push(best);
    }
    Some(out)
}

/// At most this many cells per point make a [`Block`] for the neighbour filter (4 bytes
/// each); a lid spread wider uses the hashed [`Grid`]. A merged two-camera lid of
/// 158,000 points spans about 141,000 cells of its radius (the demo scene).
const CELLS_PER_POINT: usize = 8;

/// For each of `points` (finite, fewer than `u32::MAX`), whether at least `needed` other
/// points lie within `radius` of it. Through a [`Block`] of cells of `radius` when its
/// box holds at most `cells_per_point` cells a point, else through a [`Grid`]: both
/// look at the same 27 cells around each point, so the answers are the same.
fn crowded(points: &[Point3], radius: f32, needed: usize, cells_per_point: usize) -> Vec<bool> {
    let near = |p: &Point3, q: &Point3| (q - p).norm_squared() <= radius * radius;
    let max_cells = cells_per_point
        .saturating_mul(points.len())
        .saturating_add(64);
    if let Some(block) = Block::new(points, radius, max_cells) {
        let sorted = block.points();
        let found: Vec<bool> = (0..sorted.len())
            .into_par_iter()
            .map(|at| {
                let p = &sorted[at];
                let mut others = 0;
                for run in block.around(at) {
                    for j in run {
                        if j != at && near(p, &sorted[j]) {
                            others += 1;
                            if others >= needed {
                                return true;
                            }
                        }
                    }
                }
                false
            })
            .collect();
        let mut out = vec![false; points.len()];
        for (at, keep) in found.into_iter().enumerate() {
            out[block.index(at)] = keep;
        }
        return out;
    }
    let grid = Grid::new(points, radius);
    points
        .par_iter()
        .enumerate()
        .map(|(i, p)| {
            let mut others = 0;
            for members in grid.around(grid.cell(p)) {
                for &j in members {
                    if j as usize != i && near(p, &points[j as usize]) {
                        others += 1;
                        if others >= needed {
                            return true;
                        }
                    }
                }
            }
            false
        })
        .collect()
}

/// Four robust standard deviations (1.4826 x the median absolute deviation) of z over
/// the points within `lid_band_m` of the height, clamped to [3 mm, `lid_band_m`].
fn lid_band(cluster: &[Point3], height_m: f32, config: &DimensionConfig) -> f32 {
    const MIN_BAND_M: f32 = 0.003;
    let mut deviations: Vec<f32> = cluster
        .iter()
        .map(|p| (p.z - height_m).abs())
        .filter(|d| *d <= config.lid_band_m)
        .collect();
    if deviations.is_empty() {
        return config.lid_band_m;
    }
    let mid = deviations.len() / 2;
    let (_, mad, _) = deviations.select_nth_unstable_by(mid, f32::total_cmp);
    (4.0 * 1.4826 * *mad).clamp(MIN_BAND_M.min(config.lid_band_m), config.lid_band_m)
}

/// Median z of the points within a band below the `height_quantile` quantile of z: the
/// band is `top_band_m` deep, or five deviations of the depth noise where that is more.
/// The quantile lies about 2.3 deviations above the lid's middle (more for a small
/// share of points above it): a band of 10 mm lies wholly above the lid's middle once the
/// noise passes about 4 mm (an unfiltered D415 1.7 m away), and its median read 2-4 mm
/// high. A band of five deviations reaches as far below the lid's middle as the quantile
/// lies above it.
pub(crate) fn robust_height(points: &[Point3], config: &DimensionConfig) -> f32 {
    let mut z: Vec<f32> = points.iter().map(|p| p.z).collect();
    let last = z.len().saturating_sub(1);
    let q_index = ((last as f64) * f64::from(config.height_quantile)).round() as usize;
    // The quantile and the values below it, unordered (what a sort would put there).
    let (below, top, _) = z.select_nth_unstable_by(q_index.min(last), f32::total_cmp);
    let top = *top;
    // One buffer for the bands (each as deep as the last or deeper).
    let mut band: Vec<f32> = Vec::new();
    let mut median_below = |depth: f32| {
        band.clear();
        band.extend(below.iter().copied().filter(|v| *v >= top - depth));
        band.push(top);
        let mid = band.len() / 2;
        *band.select_nth_unstable_by(mid, f32::total_cmp).1
    };
    let first = median_below(config.top_band_m);
    let noise = depth_noise(points, first - config.top_band_m);
    let mut depth = config.top_band_m.max(5.0 * noise);
    let mut middle = if depth > config.top_band_m {
        median_below(depth)
    } else {
        first
    };
    // The cells see the noise of a lid whose depth the spatial filter smoothed only
    // within each patch the holes left (a dark lid): neighbouring points agree there and
    // the patches scatter (seed 1's 720 scenes, dark 479: 2 mm in the cells, 5 mm over
    // the lid; its band of 10 mm read 8 mm high). A band that reaches as far below its
    // median as the quantile lies above it is centred on a level lid however noisy: deepen
    // it until it does. On a rounded top (a tube, a dome) the points crowd towards the top
    // and the band does not deepen.
    let deepest = MAX_BAND_DEPTHS * config.top_band_m;
    for _ in 0..8 {
        let wanted = 2.0 * (top - middle);
        if wanted <= depth || depth >= deepest {
            break;
        }
        depth = wanted.min(deepest);
        middle = median_below(depth);
    }
    middle
}

/// [`robust_height`]'s band reaches at most this many times `top_band_m` down: 3 cm, five
/// deviations of the noisiest lid of the lane set (6 mm, a dark lid's patches).
const MAX_BAND_DEPTHS: f32 = 3.0;

/// The deviation of the depth noise on the surfaces above `above` (metres): 1.4826
/// times the median distance in z of a point from the median of its 5 mm cell, pooled
/// over cells of at least [`NOISE_CELL_POINTS`] points. Within a cell the surface is
/// nearly flat, so what spreads its points is the noise, not the shape (a rounded top
/// spreads over centimetres); 0 without such cells.
fn depth_noise(points: &[Point3], above: f32) -> f32 {
    const CELL_M: f32 = 0.005;
    let lid = points.iter().filter(|p| p.z >= above);
    let mut cells = Columns::new(
        lid.clone().map(|p| {
            let cell = ((p.x / CELL_M).floor() as i32, (p.y / CELL_M).floor() as i32);
            (i64::from(cell.0), i64::from(cell.1))
        }),
        lid.map(|p| p.z),
    );
    let mut deviations = Vec::with_capacity(cells.column_of.len());
    for k in 0..cells.cells.len() {
        let cell = cells.values_mut(k);
        if cell.len() < NOISE_CELL_POINTS {
            continue;
        }
        let mid = cell.len() / 2;
        let (_, median, _) = cell.select_nth_unstable_by(mid, f32::total_cmp);
        let median = *median;
        deviations.extend(cell.iter().map(|z| (z - median).abs()));
    }
    if deviations.is_empty() {
        return 0.0;
    }
    let mid = deviations.len() / 2;
    let (_, mad, _) = deviations.select_nth_unstable_by(mid, f32::total_cmp);
    // A cell's own median sits among its points: with few of them the distances come out
    // short by about 1 / (1 - 1 / n).
    1.4826 * *mad * NOISE_CELL_POINTS as f32 / (NOISE_CELL_POINTS as f32 - 1.0)
}

/// Cells with fewer points do not count in [`depth_noise`].
const NOISE_CELL_POINTS: usize = 5;

#[cfg(test)]
mod tests {
    use super::*;

    /// Uniform values in [0, 1) from a 64-bit linear congruential generator seeded with
    /// `state`.
    fn uniforms(mut state: u64) -> impl FnMut() -> f32 {
        move || {
            state = state
                .wrapping_mul(6_364_136_223_846_793_005)
                .wrapping_add(1_442_695_040_888_963_407);
            (state >> 11) as f32 / (1u64 << 53) as f32
        }
    }

    #[test]
    fn a_noisy_lid_reads_its_middle_not_above_it() {
        // A 300 x 200 mm lid 200 mm up, points 2 mm apart, z with noise of 5 mm deviation
        // (an unfiltered D415 about 1.8 m away): the 99 % quantile lies 11-12 mm above
        // the lid, so a 1 cm band below it missed the lid's middle by about 3 mm.
        let mut uniform = uniforms(0x2545_f491_4f6c_dd1d_u64);
        let mut points = Vec::new();
        for i in 0..150 {
            for j in 0..100 {
                // Twelve uniforms: near-Gaussian, unit deviation.
                let g: f32 = (0..12).map(|_| uniform()).sum::<f32>() - 6.0;
                points.push(Point3::new(
                    i as f32 * 0.002,
                    j as f32 * 0.002,
                    0.2 + 0.005 * g,
                ));
            }
        }
        let noise = depth_noise(&points, 0.15);
        assert!((noise - 0.005).abs() < 0.0008, "{noise}");
        let h = robust_height(&points, &DimensionConfig::default());
        assert!((h - 0.2).abs() < 0.0005, "{h}");
    }

    #[test]
    fn a_dark_lid_whose_filtered_patches_scatter_reads_its_middle() {
        // A 170 x 170 mm lid 210 mm up, a point every 1.8 mm; the lid lost 85 % of its
        // depth in patches of 4 x 4 points, and the spatial filter smoothed each patch
        // left alone: the points of a patch agree to 0.5 mm, the patches scatter by 5 mm.
        // Cells of 5 mm see the 0.5 mm, and a band of 1 cm below the quantile read high.
        let mut uniform = uniforms(0x9e37_79b9_7f4a_7c15_u64);
        let mut points = Vec::new();
        for pi in 0..24 {
            for pj in 0..24 {
                let kept = uniform() < 0.15;
                let offset = 0.005 * ((0..12).map(|_| uniform()).sum::<f32>() - 6.0);
                for i in 0..4 {
                    for j in 0..4 {
                        let own = 0.0005 * ((0..12).map(|_| uniform()).sum::<f32>() - 6.0);
                        if kept {
                            points.push(Point3::new(
                                (pi * 4 + i) as f32 * 0.0018,
                                (pj * 4 + j) as f32 * 0.0018,
                                0.21 + offset + own,
                            ));
                        }
                    }
                }
            }
        }
        assert!(points.len() > 600, "{}", points.len());
        let h = robust_height(&points, &DimensionConfig::default());
        assert!((h - 0.21).abs() < 0.0015, "{h}");
    }

    /// A noisy 6 x 4 cm patch at 1 mm spacing.
    fn patch() -> Vec<Point3> {
        let mut points = Vec::new();
        let jitter =
            |k: u64| ((k.wrapping_mul(2_654_435_761) % 1000) as f32 / 1000.0 - 0.5) * 0.0008;
        for i in 0..60u64 {
            for j in 0..40u64 {
                let k = i * 40 + j;
                points.push(Point3::new(
                    i as f32 * 0.001 + jitter(k),
                    j as f32 * 0.001 + jitter(k + 7),
                    0.2 + jitter(k + 13),
                ));
            }
        }
        points
    }

    #[test]
    fn spacings_near_the_samples_are_the_trees() {
        // Exact duplicates: once, and three times (four at one place: no spacing there).
        let mut points = patch();
        for k in (0..points.len()).step_by(37) {
            let copies = if k % 2 == 0 { 1 } else { 3 };
            for _ in 0..copies {
                points.push(points[k]);
            }
        }
        let samples: Vec<usize> = (0..points.len()).step_by(7).collect();
        let every_pair: Vec<f32> = samples
            .iter()
            .filter_map(|&i| {
                let p = &points[i];
                let same = points.iter().filter(|q| (*q - p).norm() == 0.0).count();
                let nearest = points
                    .iter()
                    .map(|q| (q - p).norm())
                    .filter(|d| *d > 0.0)
                    .fold(f32::INFINITY, f32::min);
                (same < 4).then_some(nearest)
            })
            .collect();
        assert!(every_pair.len() < samples.len());
        assert_eq!(spacings_near(&points, &samples), Some(every_pair.clone()));
        // Through the hash map of the samples' cells too.
        assert_eq!(
            spacings_in_cells(&points, &samples, 0),
            Some(every_pair.clone())
        );
        assert_eq!(spacings_indexed(&points, &samples), Ok(every_pair));
        // A stray sample whose nearest point lies beyond its cells: the tree answers.
        points.push(Point3::new(0.2, 0.0, 0.2));
        assert_eq!(spacings_near(&points, &[points.len() - 1]), None);
        assert_eq!(spacings_in_cells(&points, &[points.len() - 1], 0), None);
    }

    #[test]
    fn the_neighbour_filter_counts_as_a_search_of_every_pair_does() {
        // The patch, exact duplicates of some points, points on cell boundaries, and
        // sparse strays above it.
        let mut points = patch();
        for k in (0..points.len()).step_by(37) {
            points.push(points[k]);
        }
        for k in 0..40u64 {
            points.push(Point3::new(
                k as f32 * 0.0015,
                0.003,
                0.2 + k as f32 * 0.004,
            ));
        }
        let radius = 0.0015;
        for needed in [1, 4, 6] {
            let every_pair: Vec<bool> = points
                .iter()
                .enumerate()
                .map(|(i, p)| {
                    let others = points
                        .iter()
                        .enumerate()
                        .filter(|&(j, q)| j != i && (q - p).norm_squared() <= radius * radius)
                        .count();
                    others >= needed
                })
                .collect();
            let kept = every_pair.iter().filter(|k| **k).count();
            assert!(kept > 0 && kept < points.len(), "{needed}: {kept}");
            // Dense block, then (no room for a block) the hashed grid.
            assert_eq!(crowded(&points, radius, needed, 8), every_pair);
            assert_eq!(crowded(&points, radius, needed, 0), every_pair);
        }
    }
}
