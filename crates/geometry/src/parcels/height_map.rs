//! The object's height map: cells of its points in (x, y), their tops, peak and coverage.

use std::collections::{HashMap, HashSet};

use foldhash::fast::FixedState;
use geo::{Point, Polygon};

use super::rect::polygon;
use crate::Point3;
use crate::grid::Columns;

/// Side of a height-map cell, metres.
const CELL_M: f64 = 0.005;

/// A cell is dense when it holds at least this share of the median cell's points.
const DENSE_SHARE: f64 = 0.15;

/// A top counts when this many of its cells have all eight neighbours in it (a core of
/// about 2 x 2 cm), and it has at least [`TOP_SHARE`] of the largest top's cells.
const TOP_CORE_CELLS: usize = 16;

/// See [`TOP_CORE_CELLS`].
const TOP_SHARE: f64 = 0.05;

/// A top at least this much (metres) lower than the highest counts however small: a
/// level lid well below the object's top is another parcel's (a small box beside a
/// polybag, whose dome holds many times its cells), not a shelf of the same parcel.
const LOWER_LID_M: f32 = 0.03;

/// How far below the top a seam between two lids is looked for (metres): the spatial
/// filter smooths a step whose disparity changes by less than its delta (20/32 pixel),
/// which at the lane's 2 m is a step of up to about 50 mm; higher steps stay sharp and
/// [`HeightMap::tops`] finds them.
const SEAM_REACH_M: f32 = 0.06;

/// Slices of the profile across a seam that its blur leaves out on each side (10 mm:
/// the filter spreads a step of a few centimetres over 10-20 mm).
const SEAM_BLUR_SLICES: i64 = 2;

/// Slices (100 mm) on each side of a seam over which each lid's level is fitted: a lid
/// is level edge to edge, a polybag's or a tube's top curves over that length.
const SEAM_SIDE_SLICES: i64 = 20;

/// Each side must have this many slices (40 mm) holding lid cells.
const SEAM_MIN_SLICES: usize = 8;

/// A lid is level: the line through either side's profile rises by at most this
/// (0.02 = 1.1 degrees; the lids of the lane set's touching pairs by 0.0001-0.01, the
/// curved tops of bags and tubes more where they are steady).
const SEAM_SLOPE: f64 = 0.02;

/// The step between the two lids is at least this (metres): twice a D415's depth unit
/// (1 mm), by which the quantized depths of one level lid can step.
const SEAM_MIN_M: f64 = 0.002;

/// ... and at least this many times the residual of the two lines through the profile
/// (the lane set, seed 1, prepared and raw: one box, tube or bag reads at most 5; the
/// lids of two boxes side by side 48 and more, 3.6 mm apart at the least).
const SEAM_SIGMAS: f64 = 15.0;

pub(super) type Cell2 = (i64, i64);

pub(super) fn cell_of(x: f64, y: f64) -> Cell2 {
    (floor_i64(x / CELL_M), floor_i64(y / CELL_M))
}

/// `q.floor() as i64` for every `q` (NaN and the infinities too), without the library
/// call that `floor` is on x86-64 without SSE4.1 (the height map finds each point's cell
/// several times).
fn floor_i64(q: f64) -> i64 {
    // Saturating, towards zero; one less when that rounded a negative fraction up.
    let t = q as i64;
    if (t as f64) > q {
        t.saturating_sub(1)
    } else {
        t
    }
}

/// The points of `points` whose cells survive an opening of the occupied cells (each
/// cell kept that lies in some 3 x 3 block of occupied cells): an area such as a lid
/// keeps its cells, corners and straight edges too; a line of points a pixel or two
/// wide (a row of depth pixels the filter carried out over the floor, a strip of a side
/// wall) is left out.
pub(super) fn opened(points: &[Point3]) -> Vec<Point3> {
    let occupied: HashSet<Cell2, FixedState> = points
        .iter()
        .map(|p| cell_of(f64::from(p.x), f64::from(p.y)))
        .collect();
    let block =
        |(x, y): Cell2| (-1..=1).all(|dx| (-1..=1).all(|dy| occupied.contains(&(x + dx, y + dy))));
    let kept: HashSet<Cell2, FixedState> = occupied
        .iter()
        .filter(|c| (-1..=1).any(|dx| (-1..=1).any(|dy| block((c.0 + dx, c.1 + dy)))))
        .copied()
        .collect();
    points
        .iter()
        .filter(|p| kept.contains(&cell_of(f64::from(p.x), f64::from(p.y))))
        .copied()
        .collect()
}

/// The object's points binned into [`CELL_M`] cells in (x, y): count and median z (a
/// cell where a higher parcel's side meets a lower one's lid holds a few side points and
/// many lid points: its median is the lid's, where its highest point would make a
/// staircase joining the two tops).
pub(super) struct HeightMap {
    cells: HashMap<Cell2, (u32, f32), FixedState>,
    /// How far the middle half of each cell's points spans in z: a cell holding a side
    /// wall, or the lids of two parcels, is not flat.
    spread: HashMap<Cell2, f32, FixedState>,
    /// Cells with fewer points are not dense.
    dense_min: u32,
    /// Of the points the map was made of: each one's column, and whether each column
    /// is dense.
    of_points: (Vec<u32>, Vec<bool>),
}

impl HeightMap {
    pub(super) fn new(points: &[Point3]) -> Self {
        let mut columns = Columns::new(
            points
                .iter()
                .map(|p| cell_of(f64::from(p.x), f64::from(p.y))),
            points.iter().map(|p| p.z),
        );
        let mut spread: HashMap<Cell2, f32, FixedState> = HashMap::default();
        let mut cells: HashMap<Cell2, (u32, f32), FixedState> = HashMap::default();
        let mut counts: Vec<u32> = Vec::with_capacity(columns.cells.len());
        for k in 0..columns.cells.len() {
            let cell = columns.cells[k];
            let z = columns.values_mut(k);
            z.sort_unstable_by(f32::total_cmp);
            let n = z.len();
            spread.insert(cell, z[(3 * n) / 4] - z[n / 4]);
            cells.insert(cell, (n as u32, z[n / 2]));
            counts.push(n as u32);
        }
        let mut sorted = counts.clone();
        let mid = sorted.len() / 2;
        let median = if sorted.is_empty() {
            0
        } else {
            *sorted.select_nth_unstable(mid).1
        };
        let dense_min = ((f64::from(median) * DENSE_SHARE).ceil() as u32).max(2);
        let dense_columns = counts.iter().map(|n| *n >= dense_min).collect();
        Self {
            cells,
            spread,
            dense_min,
            of_points: (columns.column_of, dense_columns),
        }
    }

    /// Its dense cells.
    pub(super) fn dense_cells(&self) -> Vec<Cell2> {
        self.cells
            .iter()
            .filter(|(_, v)| v.0 >= self.dense_min)
            .map(|(c, _)| *c)
            .collect()
    }

    fn is_dense(&self, c: &Cell2) -> bool {
        self.cells.get(c).is_some_and(|v| v.0 >= self.dense_min)
    }

    /// The points of `points` in dense cells (flying pixels between an edge and the floor
    /// scatter thinly and are left out).
    pub(super) fn dense_points(&self, points: &[Point3]) -> Vec<Point3> {
        let (column_of, dense) = &self.of_points;
        if column_of.len() == points.len() {
            // The points the map was made of: their columns are known.
            return points
                .iter()
                .zip(column_of)
                .filter(|(_, c)| dense[**c as usize])
                .map(|(p, _)| *p)
                .collect();
        }
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
    pub(super) fn peak(&self) -> Option<f32> {
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
    /// their cells are at least [`TOP_SHARE`] of the largest region's, or they are the
    /// highest such region, or at least [`LOWER_LID_M`] below it.
    pub(super) fn tops(&self, step: f32, flatness: f32) -> usize {
        let flat =
            |c: &Cell2| self.is_dense(c) && self.spread.get(c).is_some_and(|s| *s < flatness);
        let mut region: HashMap<Cell2, usize, FixedState> = HashMap::default();
        let mut sizes: Vec<(usize, usize, f32)> = Vec::new();
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
            let mean = members.iter().map(|c| self.cells[c].1).sum::<f32>() / members.len() as f32;
            sizes.push((members.len(), core, mean));
        }
        let largest = sizes.iter().map(|s| s.0).max().unwrap_or(0);
        // The highest top counts however small: a thin post beside a wide, low parcel
        // (its disc a few per cent of the other's lid) is a top of its own.
        let highest = sizes
            .iter()
            .filter(|s| s.1 >= TOP_CORE_CELLS)
            .map(|s| s.2)
            .fold(f32::NEG_INFINITY, f32::max);
        sizes
            .iter()
            .filter(|(n, core, mean)| {
                *core >= TOP_CORE_CELLS
                    && (*n as f64 >= TOP_SHARE * largest as f64
                        || *mean >= highest
                        || *mean <= highest - LOWER_LID_M)
            })
            .count()
            .max(1)
    }

    /// Whether the object's top holds a seam: two level lids side by side, one a step
    /// higher than the other, that the spatial filter has blurred into one surface (a
    /// step of a few millimetres to a few centimetres, too gradual from cell to cell
    /// for [`Self::tops`]). Along each axis of `rect`, the profile of the flat dense
    /// cells within [`SEAM_REACH_M`] of `top_m` (per 5 mm slice, the mean of the cells'
    /// medians within 2 mm of the slice's median) is fitted on each side of every
    /// slice boundary by a line, leaving out the blur next to it: a seam is where both
    /// lines are level and meet the boundary [`SEAM_MIN_M`] and [`SEAM_SIGMAS`] of
    /// their residual apart. Two boxes of one height, or within a depth unit or two,
    /// leave no such step and are not found (nor is there anything else in the depth
    /// to tell them from one box).
    pub(super) fn seam(&self, rect: &[[f64; 2]; 4], top_m: f32, flatness: f32) -> bool {
        let c0 = rect[0];
        let cells: Vec<([f64; 2], f64)> = self
            .cells
            .iter()
            .filter(|(c, v)| {
                v.0 >= self.dense_min
                    && v.1 >= top_m - SEAM_REACH_M
                    && self.spread.get(c).is_some_and(|s| *s < flatness)
            })
            .map(|(&(i, j), v)| {
                let centre = [(i as f64 + 0.5) * CELL_M, (j as f64 + 0.5) * CELL_M];
                ([centre[0] - c0[0], centre[1] - c0[1]], f64::from(v.1))
            })
            .collect();
        [rect[1], rect[3]].iter().any(|to| {
            let e = [to[0] - c0[0], to[1] - c0[1]];
            let n = e[0].hypot(e[1]);
            n > 0.0 && {
                let axis = [e[0] / n, e[1] / n];
                let along = cells
                    .iter()
                    .map(|(d, z)| (d[0] * axis[0] + d[1] * axis[1], *z));
                step_in(&profile(along))
            }
        })
    }

    /// How a flat lid (`lid`, its rectangle `rect`) lies on the object: the share of the
    /// dense cells that hold lid points (how far the lid reaches out towards the
    /// object's walls), and the share of the rectangle's cells in notches cut into it
    /// from its sides (cells with no lid point in their 3 x 3 neighbourhood, connected
    /// to a cell within two cells of the rectangle's border; a hole in a dark lid's
    /// middle is no notch, nor the ragged cell or two along a lid's edge), and the share
    /// of the rectangle's other cells that hold lid points (a solid lid, not a sparse
    /// scatter of flying pixels).
    pub(super) fn plateau(&self, lid: &[Point3], rect: &[[f64; 2]; 4]) -> (f64, f64, f64) {
        use geo::Contains as _;
        let lid_cells: HashSet<Cell2, FixedState> = lid
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
        let mut empty: HashSet<Cell2, FixedState> = Default::default();
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
        let mut notch: HashSet<Cell2, FixedState> = Default::default();
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
    pub(super) fn coverage(&self, polygon: &Polygon<f64>) -> f64 {
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

/// The profile of `(position, height)` pairs: per [`CELL_M`] slice of position, its
/// index, the mean of the heights within 2 mm of the slice's median, and how many.
fn profile(along: impl Iterator<Item = (f64, f64)>) -> Vec<(i64, f64, usize)> {
    let mut slices: HashMap<i64, Vec<f64>, FixedState> = HashMap::default();
    for (s, z) in along {
        slices
            .entry((s / CELL_M).floor() as i64)
            .or_default()
            .push(z);
    }
    let mut out: Vec<(i64, f64, usize)> = slices
        .into_iter()
        .filter_map(|(k, mut z)| {
            z.sort_unstable_by(f64::total_cmp);
            let median = z[z.len() / 2];
            let near: Vec<f64> = z
                .into_iter()
                .filter(|v| (v - median).abs() <= 0.002)
                .collect();
            (near.len() >= 3).then(|| (k, near.iter().sum::<f64>() / near.len() as f64, near.len()))
        })
        .collect();
    out.sort_unstable_by_key(|s| s.0);
    out
}

/// Whether `profile` (see [`profile`]) steps between two level lines (see
/// [`HeightMap::seam`]).
fn step_in(profile: &[(i64, f64, usize)]) -> bool {
    let (Some(first), Some(last)) = (profile.first(), profile.last()) else {
        return false;
    };
    let mut counts: Vec<usize> = profile.iter().map(|s| s.2).collect();
    let mid = counts.len() / 2;
    let typical = *counts.select_nth_unstable(mid).1;
    let least = 3.max((0.2 * typical as f64).ceil() as usize);
    let held: Vec<(f64, f64)> = profile
        .iter()
        .filter(|s| s.2 >= least)
        .map(|s| (s.0 as f64 + 0.5, s.1))
        .collect();
    let side = |lo: f64, hi: f64| -> Vec<(f64, f64)> {
        held.iter()
            .filter(|(x, _)| *x >= lo && *x < hi)
            .copied()
            .collect()
    };
    (first.0..=last.0 + 1).any(|split| {
        let at = split as f64;
        let left = side(
            at - (SEAM_BLUR_SLICES + SEAM_SIDE_SLICES) as f64,
            at - SEAM_BLUR_SLICES as f64,
        );
        let right = side(
            at + SEAM_BLUR_SLICES as f64,
            at + (SEAM_BLUR_SLICES + SEAM_SIDE_SLICES) as f64,
        );
        if left.len() < SEAM_MIN_SLICES || right.len() < SEAM_MIN_SLICES {
            return false;
        }
        let (Some((l0, l1, lr)), Some((r0, r1, rr))) = (line(&left), line(&right)) else {
            return false;
        };
        let level = l1.abs().max(r1.abs()) / CELL_M < SEAM_SLOPE;
        let gap = ((r0 + r1 * at) - (l0 + l1 * at)).abs();
        let residual = ((lr + rr) / (left.len() + right.len()) as f64).sqrt();
        level && gap >= SEAM_MIN_M && gap >= SEAM_SIGMAS * residual
    })
}

/// The least-squares line `y = a + b x` through `points`, and its sum of squared
/// residuals.
fn line(points: &[(f64, f64)]) -> Option<(f64, f64, f64)> {
    let n = points.len() as f64;
    let (mx, my) = points
        .iter()
        .fold((0.0, 0.0), |(x, y), p| (x + p.0 / n, y + p.1 / n));
    let (sxx, sxy) = points.iter().fold((0.0, 0.0), |(xx, xy), p| {
        (xx + (p.0 - mx).powi(2), xy + (p.0 - mx) * (p.1 - my))
    });
    if sxx <= 0.0 {
        return None;
    }
    let b = sxy / sxx;
    let a = my - b * mx;
    let ss = points.iter().map(|p| (p.1 - a - b * p.0).powi(2)).sum();
    Some((a, b, ss))
}

#[cfg(test)]
mod tests {
    use super::floor_i64;

    #[test]
    fn floor_i64_is_floor_then_cast_everywhere() {
        let mut values = vec![
            0.0,
            -0.0,
            0.5,
            -0.5,
            1.0,
            -1.0,
            -1.0 - f64::EPSILON,
            2.0f64.powi(52) + 0.5,
            -(2.0f64.powi(52)) - 0.5,
            2.0f64.powi(63),
            -(2.0f64.powi(63)),
            -(2.0f64.powi(63)) * 1.5,
            1e300,
            -1e300,
            f64::MIN_POSITIVE,
            -f64::MIN_POSITIVE,
            f64::INFINITY,
            f64::NEG_INFINITY,
            f64::NAN,
        ];
        // Cells of points a few metres either side of the origin, 5 mm each.
        values.extend((-4000..4000).map(|k| f64::from(k) * 0.0013 / 0.005));
        for q in values {
            assert_eq!(floor_i64(q), q.floor() as i64, "{q}");
        }
    }
}
