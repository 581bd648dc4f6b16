//! A uniform grid of cubic cells over a slice of points: the points of a cell and of its
//! 26 neighbours, in time linear in the number of points (where a k-d tree query per point
//! costs microseconds each on dense, nearly planar clouds).

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
        let k = |v: f32| (v / self.size_m).floor() as i64;
        (k(p.x), k(p.y), k(p.z))
    }

    /// Every occupied cell with its points.
    pub(crate) fn cells(&self) -> impl Iterator<Item = (&Cell, &Vec<u32>)> {
        self.cells.iter()
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
