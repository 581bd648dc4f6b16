//! Parcels apart that flying pixels joined into one object.
//!
//! Points cluster within a few millimetres of each other, and a depth camera scatters a
//! thin sheet of points along its rays off every lid edge (pixels that straddle the edge
//! and the floor). Between two parcels 20 mm apart those sheets reach across the gap, so
//! the clustering takes the pair for one object, which the fit then finds side by side
//! (two tops) and refuses. Seen from above the sheets are thin: their columns hold a
//! small share of a surface's points. The parcels' own dense columns stay apart.
//!
//! A lid that the projector's glare or a dark finish leaves in patches falls apart in
//! the same way, its patches joined by its walls: patches of one level lid stand at one
//! height, and stay together. Two parcels of one height a gap apart look the same, and
//! stay side by side.

use std::collections::HashMap;

use foldhash::fast::FixedState;

use super::fit::TOP_STEP_M;
use super::height_map::{Cell2, HeightMap, cell_of};
use crate::Point3;

/// A part holds at least this many dense cells (5 mm a side; a core of about 2 x 2 cm,
/// as a top must have).
const PART_MIN_CELLS: usize = 16;

/// A point in a column that is not dense goes with the part whose dense cells lie within
/// this many cells of its own (10 mm: a wall's foot and the edge's blur) ...
const REACH_CELLS: i64 = 2;

/// ... unless another part's lie within this many (20 mm, the spacing certified
/// dimensioners state): then it lies in the gap between two parts, a flying pixel of
/// either, and is no part's (each part's outline ends at its own dense columns, so the
/// gap between the parts reads as wide as it is).
const BETWEEN_CELLS: i64 = 4;

/// The parts of `cluster` whose dense columns do not touch (8-neighbours), when there
/// are two or more of at least [`PART_MIN_CELLS`] at different heights: each with its
/// dense points and the thin points near it, pieces whose tops lie within a top's step
/// ([`TOP_STEP_M`]) of each other as one part. `None` when the dense columns are one
/// piece, or all their pieces stand at one height.
pub(super) fn apart(cluster: &[Point3]) -> Option<Vec<Vec<Point3>>> {
    let map = HeightMap::new(cluster);
    let label = components(&map.dense_cells());
    let mut sizes: HashMap<usize, usize, FixedState> = HashMap::default();
    for l in label.values() {
        *sizes.entry(*l).or_default() += 1;
    }
    // The large components, numbered 0.. in order of their first cell.
    let mut large: Vec<usize> = sizes
        .iter()
        .filter(|(_, n)| **n >= PART_MIN_CELLS)
        .map(|(l, _)| *l)
        .collect();
    if large.len() < 2 {
        return None;
    }
    large.sort_unstable();
    let part_of = |c: &Cell2| label.get(c).and_then(|l| large.iter().position(|k| k == l));
    let mut pieces = vec![Vec::new(); large.len()];
    for p in cluster {
        let cell = cell_of(f64::from(p.x), f64::from(p.y));
        let piece = part_of(&cell).or_else(|| nearest(&cell, &part_of));
        if let Some(k) = piece {
            pieces[k].push(*p);
        }
    }
    let parts = by_height(pieces);
    (parts.len() >= 2).then_some(parts)
}

/// `pieces` joined where their tops (each one's [`HeightMap::peak`], or its highest
/// point) lie within [`TOP_STEP_M`] of each other, chained.
fn by_height(pieces: Vec<Vec<Point3>>) -> Vec<Vec<Point3>> {
    let top = |p: &[Point3]| {
        HeightMap::new(p)
            .peak()
            .unwrap_or_else(|| p.iter().map(|q| q.z).fold(f32::MIN, f32::max))
    };
    let mut order: Vec<(f32, Vec<Point3>)> = pieces.into_iter().map(|p| (top(&p), p)).collect();
    order.sort_by(|a, b| a.0.total_cmp(&b.0));
    let mut parts: Vec<(f32, Vec<Point3>)> = Vec::new();
    for (z, piece) in order {
        match parts.last_mut() {
            Some((last, part)) if z - *last < TOP_STEP_M => {
                *last = z;
                part.extend(piece);
            }
            _ => parts.push((z, piece)),
        }
    }
    parts.into_iter().map(|(_, p)| p).collect()
}

/// The part of the nearest large dense cell within [`REACH_CELLS`] of `cell`, when no
/// other part's lies within [`BETWEEN_CELLS`].
fn nearest(cell: &Cell2, part_of: &impl Fn(&Cell2) -> Option<usize>) -> Option<usize> {
    let mut best: Option<(i64, usize)> = None;
    for dx in -BETWEEN_CELLS..=BETWEEN_CELLS {
        for dy in -BETWEEN_CELLS..=BETWEEN_CELLS {
            let Some(part) = part_of(&(cell.0 + dx, cell.1 + dy)) else {
                continue;
            };
            let ring = dx.abs().max(dy.abs());
            match best {
                Some((_, other)) if other != part => return None,
                Some((r, _)) if r <= ring => {}
                _ => best = Some((ring, part)),
            }
        }
    }
    best.filter(|(ring, _)| *ring <= REACH_CELLS)
        .map(|(_, part)| part)
}

/// Each cell's component (8-neighbours), numbered by the component's smallest cell's
/// place in `cells` sorted.
fn components(cells: &[Cell2]) -> HashMap<Cell2, usize, FixedState> {
    let mut sorted = cells.to_vec();
    sorted.sort_unstable();
    let mut label: HashMap<Cell2, usize, FixedState> = HashMap::default();
    for (i, start) in sorted.iter().enumerate() {
        if label.contains_key(start) {
            continue;
        }
        label.insert(*start, i);
        let mut stack = vec![*start];
        while let Some((x, y)) = stack.pop() {
            for dx in -1..=1 {
                for dy in -1..=1 {
                    let n = (x + dx, y + dy);
                    if !label.contains_key(&n) && sorted.binary_search(&n).is_ok() {
                        label.insert(n, i);
                        stack.push(n);
                    }
                }
            }
        }
    }
    label
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A level lid of `side` millimetres square from `(x, y)` mm, `z` metres high, a
    /// point every millimetre (at its middle: clear of the cells' edges).
    fn lid(x: i32, y: i32, side: i32, z: f32) -> Vec<Point3> {
        (0..side)
            .flat_map(|i| (0..side).map(move |j| (x + i, y + j)))
            .map(|(i, j)| Point3::new((i as f32 + 0.5) * 1e-3, (j as f32 + 0.5) * 1e-3, z))
            .collect()
    }

    #[test]
    fn lids_20_mm_apart_joined_by_a_thin_sheet_are_two_parts() {
        let mut cluster = lid(0, 0, 100, 0.3);
        let one = cluster.len();
        cluster.extend(lid(120, 0, 100, 0.2));
        // A sheet of flying pixels across the gap: one point per 5 mm column.
        let sheet: Vec<Point3> = (0..20)
            .flat_map(|k| (0..4).map(move |g| (k, g)))
            .map(|(k, g)| Point3::new(0.1025 + g as f32 * 0.005, 0.0025 + k as f32 * 0.005, 0.25))
            .collect();
        cluster.extend(&sheet);
        let parts = apart(&cluster).expect("two parts");
        assert_eq!(parts.len(), 2);
        // Each lid whole in its own part; of the sheet in the gap, nothing.
        let xs = |p: &[Point3]| {
            p.iter()
                .map(|q| q.x)
                .fold((f32::MAX, f32::MIN), |(a, b), x| (a.min(x), b.max(x)))
        };
        // The lower part first.
        let (a, b) = (xs(&parts[1]), xs(&parts[0]));
        assert!(parts.iter().all(|p| p.len() == one), "{one}");
        assert!(a.1 < 0.1 && b.0 >= 0.12, "{a:?} {b:?}");
    }

    #[test]
    fn patches_of_one_level_lid_stay_together() {
        // A lid that glare cut across, its patches joined by its walls below (seen
        // steeply: a point per 5 mm column).
        let mut cluster = lid(0, 0, 100, 0.3);
        cluster.extend(lid(140, 0, 100, 0.3));
        let wall: Vec<Point3> = (0..48)
            .map(|k| Point3::new((k as f32 + 0.5) * 5e-3, 0.0025, 0.15))
            .collect();
        cluster.extend(&wall);
        assert!(apart(&cluster).is_none());
        // The same patches with a lower parcel beside them: two parts.
        cluster.extend(lid(0, 120, 100, 0.1));
        let parts = apart(&cluster).expect("two parts");
        assert_eq!(parts.len(), 2);
        assert!(parts[0].len() == 100 * 100 && parts[1].len() > 2 * 100 * 100);
    }

    #[test]
    fn one_lid_and_lids_that_touch_stay_whole() {
        assert!(apart(&lid(0, 0, 200, 0.3)).is_none());
        let mut touching = lid(0, 0, 100, 0.3);
        touching.extend(lid(100, 0, 100, 0.2));
        assert!(apart(&touching).is_none());
    }
}
