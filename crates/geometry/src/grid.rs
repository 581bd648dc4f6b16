//! A uniform grid of cubic cells over a slice of points: the points of a cell and of its
//! 26 neighbours, in time linear in the number of points (where a k-d tree query per point
//! costs microseconds each on dense, nearly planar clouds). [`Grid`] keeps the occupied
//! cells in a hash map, whatever the points' extent; [`Block`] numbers every cell of the
//! points' bounding box and sorts the points by cell, so that the points of three cells
//! side by side along x lie next to each other, found without hashing (a lid's neighbour
//! filter looked up 27 cells of a hash map for each of 150,000 points).

use std::collections::HashMap;

use foldhash::fast::FixedState;

use crate::Point3;

/// A map keyed by cells, with a fast fixed-seed hash (the keys are our own coordinates,
/// not input an attacker chooses freely, and the work is bounded by the point count).
pub(crate) type CellMap<V> = HashMap<Cell, V, FixedState>;

/// Integer cell coordinates.
pub(crate) type Cell = (i64, i64, i64);

/// Points bucketed by cell; items are indices into the slice the grid was built from.
pub(crate) struct Grid {
    size_m: f32,
    cells: CellMap<Vec<u32>>,
}

impl Grid {
    /// Buckets finite `points` into cells of `size_m` (> 0). Callers keep the slice
    /// below `u32::MAX` points.
    pub(crate) fn new(points: &[Point3], size_m: f32) -> Self {
        let mut grid = Self {
            size_m,
            cells: CellMap::default(),
        };
        for (i, p) in points.iter().enumerate() {
            let cell = grid.cell(p);
            grid.cells.entry(cell).or_default().push(i as u32);
        }
        grid
    }

    /// The cell holding `p`.
    pub(crate) fn cell(&self, p: &Point3) -> Cell {
        cell_of(p, self.size_m)
    }

    /// Every occupied cell with its points.
    pub(crate) fn cells(&self) -> impl Iterator<Item = (&Cell, &Vec<u32>)> {
        self.cells.iter()
    }

    /// The points of `cell` (none when it is empty).
    pub(crate) fn members(&self, cell: Cell) -> &[u32] {
        self.cells.get(&cell).map_or(&[], Vec::as_slice)
    }

    /// `cell` first, then the cells touching it, those that hold points.
    pub(crate) fn occupied_around(&self, cell: Cell) -> impl Iterator<Item = Cell> + '_ {
        let (x, y, z) = cell;
        let touching = (-1..=1).flat_map(move |dx| {
            (-1..=1).flat_map(move |dy| {
                (-1..=1)
                    .filter(move |dz| (dx, dy, *dz) != (0, 0, 0))
                    .map(move |dz| (x + dx, y + dy, z + dz))
            })
        });
        std::iter::once(cell)
            .chain(touching)
            .filter(|c| self.cells.contains_key(c))
    }

    /// The points of `cell` and of the occupied cells touching it.
    pub(crate) fn around(&self, cell: Cell) -> impl Iterator<Item = &[u32]> {
        self.occupied_around(cell)
            .filter_map(|c| self.cells.get(&c).map(Vec::as_slice))
    }
}

/// The cell holding `p` among cells of `size_m`.
pub(crate) fn cell_of(p: &Point3, size_m: f32) -> Cell {
    let k = |v: f32| coordinate(v, size_m);
    (k(p.x), k(p.y), k(p.z))
}

/// `(v / size).floor() as i64`, the same value for every `v` (NaN and the infinities
/// too), without the library call that `floor` is on x86-64 without SSE4.1.
fn coordinate(v: f32, size: f32) -> i64 {
    let q = v / size;
    // Saturating, towards zero; one less when that rounded a negative fraction up.
    let t = q as i64;
    if (t as f32) > q {
        t.saturating_sub(1)
    } else {
        t
    }
}

/// Points sorted by cell into a dense block of cells of one size: every cell of the
/// points' bounding box has a number, x varying fastest, so each row of three cells
/// along x is one run of sorted points. Cells are those of [`Grid`] (the same
/// coordinates for the same size), so both find the same points around a cell.
///
/// It keeps 16 bytes a point and 4 a cell (a sorted point's cell is found again from the
/// point): every buffer of a few MB is new memory to the kernel (the server's fixed
/// malloc threshold maps each one afresh), and the page faults of a block that also kept
/// each point's cell coordinates, twice, cost more than the sorting.
pub(crate) struct Block {
    /// Cells along each axis.
    dims: [usize; 3],
    /// The lowest cell's coordinates.
    low: [i64; 3],
    /// The cells' side, metres.
    size_m: f32,
    /// Where each cell's points start in `points`, and one past the last cell's end.
    start: Vec<u32>,
    /// The points, sorted by cell (in input order within a cell).
    points: Vec<Point3>,
    /// Each sorted point's index in the slice the block was built from.
    index: Vec<u32>,
}

impl Block {
    /// Sorts finite `points` (fewer than `u32::MAX`) into cells of `size_m` (> 0);
    /// `None` when their bounding box holds more than `max_cells` cells (a sparse cloud
    /// spread wide, for which [`Grid`] is the better index), or `u32::MAX` or more.
    pub(crate) fn new(points: &[Point3], size_m: f32, max_cells: usize) -> Option<Self> {
        let cell = |p: &Point3| [p.x, p.y, p.z].map(|v| coordinate(v, size_m));
        let (mut low, mut high) = ([i64::MAX; 3], [i64::MIN; 3]);
        for p in points {
            let c = cell(p);
            for k in 0..3 {
                low[k] = low[k].min(c[k]);
                high[k] = high[k].max(c[k]);
            }
        }
        if points.is_empty() {
            (low, high) = ([0; 3], [-1; 3]);
        }
        let mut dims = [0usize; 3];
        let mut total = 1usize;
        for k in 0..3 {
            let n = u32::try_from(high[k].checked_sub(low[k])?.checked_add(1)?).ok()?;
            dims[k] = n as usize;
            total = total.checked_mul(dims[k])?;
        }
        if total > max_cells || u32::try_from(total).is_err() {
            return None;
        }
        let n = u32::try_from(points.len()).ok()?;
        // Counting sort by cell number: counts, their running sums (where each cell's
        // points end), then each point, last first, at its cell's last free place, so
        // that the running sums end where each cell's points start.
        let numbers: Vec<u32> = points
            .iter()
            .map(|p| {
                let c = cell(p);
                let r = [0, 1, 2].map(|k| (c[k] - low[k]) as usize);
                (r[0] + dims[0] * (r[1] + dims[1] * r[2])) as u32
            })
            .collect();
        let mut start = vec![0u32; total + 1];
        for &c in &numbers {
            start[c as usize] += 1;
        }
        for i in 1..start.len() {
            start[i] += start[i - 1];
        }
        let mut sorted = vec![Point3::origin(); points.len()];
        let mut index = vec![0u32; points.len()];
        for (i, (p, &c)) in points.iter().zip(&numbers).enumerate().rev() {
            let slot = &mut start[c as usize];
            *slot -= 1;
            let at = *slot as usize;
            sorted[at] = *p;
            index[at] = i as u32;
        }
        debug_assert_eq!(start[total], n);
        Some(Self {
            dims,
            low,
            size_m,
            start,
            points: sorted,
            index,
        })
    }

    /// The points, sorted by cell.
    pub(crate) fn points(&self) -> &[Point3] {
        &self.points
    }

    /// The index of sorted point `at` in the slice the block was built from.
    pub(crate) fn index(&self, at: usize) -> usize {
        self.index[at] as usize
    }

    /// The runs of sorted points in the cells around sorted point `at` (its cell and the
    /// 26 touching it), as up to nine ranges into [`Block::points`]; the row through its
    /// own cell first.
    pub(crate) fn around(&self, at: usize) -> impl Iterator<Item = std::ops::Range<usize>> + '_ {
        let p = &self.points[at];
        let [x, y, z] = [0, 1, 2].map(|k| {
            let v = [p.x, p.y, p.z][k];
            (coordinate(v, self.size_m) - self.low[k]) as usize
        });
        let span = |v: usize, k: usize| v.saturating_sub(1)..=(v + 1).min(self.dims[k] - 1);
        let (x0, x1) = (x.saturating_sub(1), (x + 1).min(self.dims[0] - 1));
        let row = move |(yy, zz): (usize, usize)| {
            let first = x0 + self.dims[0] * (yy + self.dims[1] * zz);
            let last = x1 + self.dims[0] * (yy + self.dims[1] * zz);
            self.start[first] as usize..self.start[last + 1] as usize
        };
        std::iter::once((y, z))
            .chain(
                span(z, 2)
                    .flat_map(move |zz| span(y, 1).map(move |yy| (yy, zz)))
                    .filter(move |c| *c != (y, z)),
            )
            .map(row)
    }
}

/// Values grouped by the column (a 2-D cell) each belongs to, in one buffer: column `k`
/// holds `values[start[k]..start[k + 1]]`, in input order. Columns are numbered in order
/// of their first value, and each input's column is kept. Where the columns' bounding box
/// holds few cells per value, they are found by their place in it, else through a hash
/// map (a height map of 200,000 points pushed into a vector per cell of a hash map, and
/// looked each point up again for its cell's count). The cells and the values come as
/// iterators, read twice and once: a list of (cell, value) pairs was 24 bytes a point
/// more, new pages each time (see [`Block`]).
pub(crate) struct Columns {
    /// Each column's cell.
    pub(crate) cells: Vec<(i64, i64)>,
    /// Where each column's values start in `values`, and one past the last one's end.
    start: Vec<usize>,
    /// The values, by column.
    values: Vec<f32>,
    /// Each input's column.
    pub(crate) column_of: Vec<u32>,
}

/// At most this many cells of the bounding box per value are numbered by their place.
const COLUMN_CELLS_PER_VALUE: usize = 8;

impl Columns {
    /// Groups the values `values` by their cells `cells` (the same number of each, fewer
    /// than `u32::MAX`; `cells` is read twice).
    pub(crate) fn new(
        cells: impl Iterator<Item = (i64, i64)> + Clone,
        values: impl Iterator<Item = f32>,
    ) -> Self {
        let (mut low, mut high) = ([i64::MAX; 2], [i64::MIN; 2]);
        let mut len = 0usize;
        for (x, y) in cells.clone() {
            low = [low[0].min(x), low[1].min(y)];
            high = [high[0].max(x), high[1].max(y)];
            len += 1;
        }
        let span = |k: usize| {
            high[k]
                .checked_sub(low[k])
                .and_then(|d| d.checked_add(1))
                .and_then(|d| usize::try_from(d).ok())
        };
        let boxed = match (span(0), span(1)) {
            (Some(w), Some(h)) => w
                .checked_mul(h)
                .filter(|n| *n <= COLUMN_CELLS_PER_VALUE * len + 64)
                .map(|_| w),
            _ => None,
        };
        let mut numbered: Vec<(i64, i64)> = Vec::new();
        let mut column_of: Vec<u32> = Vec::with_capacity(len);
        let mut number = |cell: (i64, i64), found: &mut u32| {
            if *found == u32::MAX {
                *found = numbered.len() as u32;
                numbered.push(cell);
            }
            *found
        };
        match boxed {
            Some(w) => {
                let h = span(1).unwrap_or(0);
                let mut numbers = vec![u32::MAX; w * h];
                for cell in cells {
                    let at = (cell.0 - low[0]) as usize + w * (cell.1 - low[1]) as usize;
                    column_of.push(number(cell, &mut numbers[at]));
                }
            }
            None => {
                let mut numbers: HashMap<(i64, i64), u32, FixedState> = HashMap::default();
                for cell in cells {
                    column_of.push(number(cell, numbers.entry(cell).or_insert(u32::MAX)));
                }
            }
        }
        let cells = numbered;
        // Counting sort by column.
        let mut start = vec![0usize; cells.len() + 1];
        for c in &column_of {
            start[*c as usize + 1] += 1;
        }
        for i in 1..start.len() {
            start[i] += start[i - 1];
        }
        let mut next = start.clone();
        let mut sorted = vec![0.0f32; column_of.len()];
        for (v, c) in values.zip(&column_of) {
            let slot = &mut next[*c as usize];
            sorted[*slot] = v;
            *slot += 1;
        }
        let values = sorted;
        Self {
            cells,
            start,
            values,
            column_of,
        }
    }

    /// The values of column `k`, to reorder.
    pub(crate) fn values_mut(&mut self, k: usize) -> &mut [f32] {
        &mut self.values[self.start[k]..self.start[k + 1]]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The columns as (cell, values in input order), in column order.
    fn groups(items: &[((i64, i64), f32)]) -> Vec<((i64, i64), Vec<f32>)> {
        let mut c = Columns::new(items.iter().map(|i| i.0), items.iter().map(|i| i.1));
        for (i, (cell, _)) in items.iter().enumerate() {
            assert_eq!(c.cells[c.column_of[i] as usize], *cell);
        }
        (0..c.cells.len())
            .map(|k| (c.cells[k], c.values_mut(k).to_vec()))
            .collect()
    }

    #[test]
    fn columns_group_values_by_cell_in_input_order_near_and_far_apart() {
        let near = [
            ((3, -2), 1.0),
            ((4, -2), 2.0),
            ((3, -2), 3.0),
            ((-1, 5), 4.0),
        ];
        assert_eq!(
            groups(&near),
            vec![
                ((3, -2), vec![1.0, 3.0]),
                ((4, -2), vec![2.0]),
                ((-1, 5), vec![4.0]),
            ]
        );
        // Cells too far apart for a box of cells: the same through the hash map.
        let far = near.map(|((x, y), v)| ((x * 1_000_000, y * 1_000_000), v));
        let scaled = |g: Vec<((i64, i64), Vec<f32>)>| {
            g.into_iter()
                .map(|((x, y), v)| ((x * 1_000_000, y * 1_000_000), v))
                .collect::<Vec<_>>()
        };
        assert_eq!(groups(&far), scaled(groups(&near)));
        assert!(groups(&[]).is_empty());
        let extreme = [((i64::MIN, 0), 1.0), ((i64::MAX, 0), 2.0)];
        assert_eq!(groups(&extreme).len(), 2);
    }
}
