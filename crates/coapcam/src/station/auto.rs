//! Automatic measurement's core, sans-IO: the table as a coarse [`HeightMap`] (heights
//! above the floor in the table frame, from the cameras' calibrated depth, decimated), and
//! [`Stillness`], which is fed one map per look with its time and says when a parcel
//! arrived, stood still long enough to be measured, moved, or left. No clock, no camera:
//! the watcher (`station::watch`) grabs, builds the maps and acts on the events; the tests
//! feed literal sequences.
//!
//! How it decides (docs/station.md, "Automatic measurement"):
//! - a cell is *occupied* when its mean height is at least `min_height_m`; the table is
//!   occupied when at least `min_cells` cells are;
//! - two maps are *the same* when at most `max(changed_cells, changed_share x occupied)`
//!   cells seen in both differ by more than `tolerance_m` (only cells occupied in one of
//!   them count, so the floor's noise never does);
//! - a parcel is *still* when every map for `still` after a first one is the same as that
//!   first one: comparing with the window's first map, not the previous one, catches a
//!   slow push as well as a quick one;
//! - it is measured once: after [`Event::Still`] the map it stood still in is the
//!   reference; a later change ([`Event::Moved`]) that settles into a map the same as the
//!   one measured (a hand that reached in and left) is not measured again; one that
//!   settles elsewhere is. An empty table ([`Event::Left`]) forgets everything.

use std::time::{Duration, Instant};

use geometry::{Point3, Transform};
use rgbd::{DepthFrame, Intrinsics};

/// The grid of a height map: a square centred on the table frame's origin.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Grid {
    /// Half the side of the square, metres (the grid covers -half..half in x and y).
    pub half_m: f32,
    /// The side of a cell, metres.
    pub cell_m: f32,
}

impl Default for Grid {
    /// 1.6 m x 1.6 m in 2 cm cells (6,400 cells): a measuring table and its edges. A
    /// 2 cm cell holds about 16 points of a 1280x720 depth image decimated by 4 seen from
    /// 1 m, so its mean height is steady to about half a millimetre.
    fn default() -> Self {
        Self {
            half_m: 0.8,
            cell_m: 0.02,
        }
    }
}

impl Grid {
    /// Cells per side.
    pub fn side(&self) -> usize {
        ((2.0 * self.half_m / self.cell_m).ceil() as usize).max(1)
    }

    /// The cell of table point (x, y), if on the grid.
    fn cell(&self, x: f32, y: f32) -> Option<usize> {
        let side = self.side();
        let col = ((x + self.half_m) / self.cell_m).floor();
        let row = ((y + self.half_m) / self.cell_m).floor();
        let n = side as f32;
        ((0.0..n).contains(&col) && (0.0..n).contains(&row))
            .then(|| row as usize * side + col as usize)
    }
}

/// Points higher than this above the floor (metres) are ignored: nothing on a measuring
/// table is, and a camera's own stray points are.
const MAX_HEIGHT_M: f32 = 2.5;
/// Points further below the floor than this are ignored (noise of a floor point is far
/// smaller).
const MIN_HEIGHT_M: f32 = -0.1;

/// Heights above the floor over a [`Grid`], as the mean of the points in each cell.
#[derive(Debug, Clone, PartialEq)]
pub struct HeightMap {
    grid: Grid,
    sums: Vec<f32>,
    counts: Vec<u32>,
}

impl HeightMap {
    /// An empty map (no cell seen).
    pub fn new(grid: Grid) -> Self {
        let cells = grid.side() * grid.side();
        Self {
            grid,
            sums: vec![0.0; cells],
            counts: vec![0; cells],
        }
    }

    /// A map from literal rows of heights in metres (`None`: not seen), for tests and
    /// tools: `rows[0]` is the row of lowest y. The grid is `rows.len()` cells of
    /// `cell_m` square.
    pub fn from_rows(cell_m: f32, rows: &[Vec<Option<f32>>]) -> Self {
        let side = rows.len();
        let grid = Grid {
            half_m: side as f32 * cell_m / 2.0,
            cell_m,
        };
        let mut map = Self::new(grid);
        debug_assert_eq!(map.grid.side(), side);
        for (r, row) in rows.iter().enumerate() {
            for (c, h) in row.iter().enumerate().take(side) {
                if let Some(h) = h {
                    map.sums[r * side + c] = *h;
                    map.counts[r * side + c] = 1;
                }
            }
        }
        map
    }

    /// The grid.
    pub fn grid(&self) -> Grid {
        self.grid
    }

    /// Adds one point of the table frame (metres, z up from the floor).
    pub fn add(&mut self, p: [f32; 3]) {
        if !(MIN_HEIGHT_M..=MAX_HEIGHT_M).contains(&p[2]) {
            return;
        }
        if let Some(i) = self.grid.cell(p[0], p[1]) {
            self.sums[i] += p[2];
            self.counts[i] += 1;
        }
    }

    /// Adds every `step`-th pixel of every `step`-th row of `depth` (decimated), seen
    /// through `intrinsics` and placed in the table frame by `to_table` (the camera's
    /// 3d-transformation). Pixels without depth add nothing.
    pub fn add_depth(
        &mut self,
        depth: &DepthFrame,
        intrinsics: &Intrinsics,
        to_table: &Transform,
        step: usize,
    ) {
        let step = step.max(1);
        for v in (0..depth.height as usize).step_by(step) {
            let Some(row) = depth.data.get(v * depth.stride..) else {
                break;
            };
            for (u, &raw) in row
                .iter()
                .take(depth.width as usize)
                .enumerate()
                .step_by(step)
            {
                if raw == 0 {
                    continue;
                }
                let z = f32::from(raw) * depth.depth_scale;
                let p = intrinsics.deproject([u as f32, v as f32], z);
                let q = to_table.apply(&Point3::new(p[0], p[1], p[2]));
                self.add([q.x, q.y, q.z]);
            }
        }
    }

    /// Adds the points of `other` (same grid; another camera's view of the same moment).
    pub fn merge(&mut self, other: &Self) {
        if other.grid != self.grid {
            return;
        }
        for (i, (s, c)) in other.sums.iter().zip(&other.counts).enumerate() {
            self.sums[i] += s;
            self.counts[i] += c;
        }
    }

    /// The mean height of cell `i`, `None` when no point fell in it.
    fn height(&self, i: usize) -> Option<f32> {
        let n = *self.counts.get(i)?;
        (n > 0).then(|| self.sums[i] / n as f32)
    }

    /// Cells with any point.
    pub fn seen_cells(&self) -> usize {
        self.counts.iter().filter(|&&n| n > 0).count()
    }

    /// Cells whose mean height is at least `min_height_m`.
    pub fn occupied_cells(&self, min_height_m: f32) -> usize {
        (0..self.counts.len())
            .filter(|&i| self.height(i).is_some_and(|h| h >= min_height_m))
            .count()
    }

    /// Cells seen in both maps, occupied in at least one, whose heights differ by more
    /// than `tolerance_m`; every cell when the grids differ.
    fn changed_cells(&self, other: &Self, min_height_m: f32, tolerance_m: f32) -> usize {
        if other.grid != self.grid {
            return self.counts.len();
        }
        (0..self.counts.len())
            .filter(|&i| match (self.height(i), other.height(i)) {
                (Some(a), Some(b)) => {
                    (a >= min_height_m || b >= min_height_m) && (a - b).abs() > tolerance_m
                }
                _ => false,
            })
            .count()
    }
}

/// How [`Stillness`] decides; see the module documentation.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StillnessConfig {
    /// How long the maps must stay the same before a parcel counts as still
    /// (`serve --still-ms`).
    pub still: Duration,
    /// A cell this high above the floor (metres) holds something.
    pub min_height_m: f32,
    /// Occupied cells that make the table occupied.
    pub min_cells: usize,
    /// Two heights of a cell further apart than this (metres) differ.
    pub tolerance_m: f32,
    /// Differing cells two maps may have and still be the same, at least ...
    pub changed_cells: usize,
    /// ... or this share of the occupied cells, when that is more.
    pub changed_share: f32,
}

/// The default `--still-ms`: long enough that a parcel let go of has settled and the hand
/// is out of the way (about four looks at the active rate), short enough that a parcel is
/// measured within about a second of standing still.
pub const DEFAULT_STILL: Duration = Duration::from_millis(600);

impl Default for StillnessConfig {
    /// 600 ms; 2 cm above the floor; 4 cells (16 cm², smaller than any parcel but more
    /// than a stray speck); 1.5 cm, several times a cell mean's noise at 1 m and less
    /// than any push; 3 cells or 2 % of the occupied ones (the cells along an edge whose
    /// share of parcel and floor a noisy frame tips).
    fn default() -> Self {
        Self {
            still: DEFAULT_STILL,
            min_height_m: 0.02,
            min_cells: 4,
            tolerance_m: 0.015,
            changed_cells: 3,
            changed_share: 0.02,
        }
    }
}

/// What [`Stillness::observe`] reports.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Event {
    /// Something is on the table that was empty.
    Arrived,
    /// What is on the table stood still for `still` and is not what was measured last:
    /// measure it now.
    Still,
    /// What stood still changed (pushed, moved, or something reached in).
    Moved,
    /// The table is empty again.
    Left,
}

#[derive(Debug, Clone)]
enum State {
    /// Nothing on the table.
    Empty,
    /// Something on the table, the same as `first` since `since`.
    Settling { since: Instant, first: HeightMap },
    /// Still as in `reference`, and measured (or the same as what was).
    Settled { reference: HeightMap },
}

/// Decides from a sequence of height maps when a parcel stands still; see the module
/// documentation.
#[derive(Debug, Clone)]
pub struct Stillness {
    config: StillnessConfig,
    state: State,
    /// The map of the last measurement, until the table is empty.
    measured: Option<HeightMap>,
}

impl Stillness {
    /// A detector of an empty table.
    pub fn new(config: StillnessConfig) -> Self {
        Self {
            config,
            state: State::Empty,
            measured: None,
        }
    }

    /// The configuration.
    pub fn config(&self) -> &StillnessConfig {
        &self.config
    }

    /// Whether the table is empty, as far as the maps so far tell.
    pub fn is_empty(&self) -> bool {
        matches!(self.state, State::Empty)
    }

    /// Forgets what was measured last (a measurement that failed or was discarded): what
    /// stands on the table at `now` is measured once it has stood still for `still` from
    /// `now` on, even where it stood before.
    pub fn forget(&mut self, now: Instant) {
        self.measured = None;
        let state = std::mem::replace(&mut self.state, State::Empty);
        self.state = match state {
            State::Settled { reference } => State::Settling {
                since: now,
                first: reference,
            },
            other => other,
        };
    }

    fn same(&self, a: &HeightMap, b: &HeightMap) -> bool {
        let c = &self.config;
        let occupied = a
            .occupied_cells(c.min_height_m)
            .max(b.occupied_cells(c.min_height_m));
        let allowed = c
            .changed_cells
            .max((c.changed_share * occupied as f32).floor() as usize);
        a.changed_cells(b, c.min_height_m, c.tolerance_m) <= allowed
    }

    /// Feeds the map of the table seen at `now` (times must not go backwards).
    pub fn observe(&mut self, now: Instant, map: &HeightMap) -> Option<Event> {
        let occupied = map.occupied_cells(self.config.min_height_m) >= self.config.min_cells;
        let state = std::mem::replace(&mut self.state, State::Empty);
        let (next, event) = match state {
            State::Empty if !occupied => (State::Empty, None),
            State::Empty => (
                State::Settling {
                    since: now,
                    first: map.clone(),
                },
                Some(Event::Arrived),
            ),
            State::Settling { .. } | State::Settled { .. } if !occupied => {
                self.measured = None;
                (State::Empty, Some(Event::Left))
            }
            State::Settling { since, first } => {
                if !self.same(&first, map) {
                    (
                        State::Settling {
                            since: now,
                            first: map.clone(),
                        },
                        None,
                    )
                } else if now.saturating_duration_since(since) < self.config.still {
                    (State::Settling { since, first }, None)
                } else if self.measured.as_ref().is_some_and(|m| self.same(m, map)) {
                    // Back as it was measured: nothing new to measure.
                    (
                        State::Settled {
                            reference: map.clone(),
                        },
                        None,
                    )
                } else {
                    self.measured = Some(map.clone());
                    (
                        State::Settled {
                            reference: map.clone(),
                        },
                        Some(Event::Still),
                    )
                }
            }
            State::Settled { reference } => {
                if self.same(&reference, map) {
                    (State::Settled { reference }, None)
                } else {
                    (
                        State::Settling {
                            since: now,
                            first: map.clone(),
                        },
                        Some(Event::Moved),
                    )
                }
            }
        };
        self.state = next;
        event
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A map of 8 x 8 cells of 2 cm from a picture, row 0 first (lowest y): `.` the
    /// floor, `?` not seen, a digit d a parcel d x 5 cm high, `h` a hand 40 cm up.
    fn map(rows: [&str; 8]) -> HeightMap {
        let rows: Vec<Vec<Option<f32>>> = rows
            .iter()
            .map(|r| {
                r.chars()
                    .map(|c| match c {
                        '.' => Some(0.0),
                        '?' => None,
                        'h' => Some(0.4),
                        d => Some(d.to_digit(10).expect("a digit") as f32 * 0.05),
                    })
                    .collect()
            })
            .collect();
        HeightMap::from_rows(0.02, &rows)
    }

    const EMPTY: [&str; 8] = ["........"; 8];

    /// A 3 x 3-cell parcel 20 cm high with its lower-left cell at (`col`, `row`).
    fn parcel(col: usize, row: usize) -> [&'static str; 8] {
        const ROWS: [&str; 6] = [
            "444.....", ".444....", "..444...", "...444..", "....444.", ".....444",
        ];
        let mut m = EMPTY;
        for r in &mut m[row..row + 3] {
            *r = ROWS[col];
        }
        m
    }

    /// Feeds `(ms, map)` looks from a common start; the events with their times.
    fn run(detector: &mut Stillness, looks: &[(u64, [&str; 8])]) -> Vec<(u64, Event)> {
        let t0 = Instant::now();
        looks
            .iter()
            .filter_map(|(ms, rows)| {
                let now = t0 + Duration::from_millis(*ms);
                detector.observe(now, &map(*rows)).map(|e| (*ms, e))
            })
            .collect()
    }

    fn detector() -> Stillness {
        Stillness::new(StillnessConfig::default())
    }

    /// Looks every 150 ms from `from` (inclusive) to `to` (exclusive) at one map.
    fn hold(from: u64, to: u64, rows: [&'static str; 8]) -> Vec<(u64, [&'static str; 8])> {
        (from..to).step_by(150).map(|t| (t, rows)).collect()
    }

    #[test]
    fn an_empty_table_says_nothing() {
        let mut d = detector();
        assert_eq!(run(&mut d, &hold(0, 5000, EMPTY)), []);
        assert!(d.is_empty());
    }

    #[test]
    fn a_parcel_slid_in_is_measured_once_after_standing_still_for_the_time() {
        let mut d = detector();
        let mut looks = vec![(0, EMPTY), (150, parcel(0, 2)), (300, parcel(1, 2))];
        looks.extend(hold(450, 3000, parcel(2, 2)));
        looks.extend(hold(3000, 3600, EMPTY));
        let events = run(&mut d, &looks);
        // Still since 450 ms, for 600 ms: the look at 1050 ms is the first that counts.
        assert_eq!(
            events,
            [
                (150, Event::Arrived),
                (1050, Event::Still),
                (3000, Event::Left)
            ]
        );
        assert!(d.is_empty());
    }

    #[test]
    fn while_it_moves_it_is_never_still() {
        let mut d = detector();
        // A parcel pushed one cell along every 300 ms (6.7 cm/s): each look differs from
        // the one before only every other time, never for 600 ms.
        let mut looks = vec![(0, EMPTY)];
        for (i, col) in [0, 0, 1, 1, 2, 2, 3, 3, 4, 4, 5, 5].into_iter().enumerate() {
            looks.push((150 * (i as u64 + 1), parcel(col, 2)));
        }
        assert_eq!(run(&mut d, &looks), [(150, Event::Arrived)]);
    }

    #[test]
    fn noise_and_unseen_cells_do_not_count_as_motion() {
        let mut d = detector();
        let steady = parcel(2, 2);
        let mut noisy = steady;
        noisy[2] = "..3?4..."; // an edge cell 5 cm lower, a cell not seen
        let mut hidden = steady;
        hidden[4] = "..???...";
        let looks = [
            (0, steady),
            (150, noisy),
            (300, steady),
            (450, hidden),
            (600, noisy),
        ];
        assert_eq!(
            run(&mut d, &looks),
            [(0, Event::Arrived), (600, Event::Still)]
        );
    }

    #[test]
    fn a_parcel_moved_on_the_table_is_measured_again_where_it_stands() {
        let mut d = detector();
        let mut looks = hold(0, 900, parcel(1, 1));
        looks.push((900, parcel(2, 2)));
        looks.extend(hold(1050, 2000, parcel(3, 3)));
        assert_eq!(
            run(&mut d, &looks),
            [
                (0, Event::Arrived),
                (600, Event::Still),
                (900, Event::Moved),
                (1650, Event::Still)
            ]
        );
    }

    #[test]
    fn a_hand_that_reaches_in_and_leaves_does_not_make_a_new_measurement() {
        let mut d = detector();
        let still = parcel(2, 2);
        let mut hand = still;
        hand[6] = "hhhhh...";
        hand[7] = "hhhhh...";
        let mut looks = hold(0, 900, still);
        looks.extend(hold(900, 1200, hand));
        looks.extend(hold(1200, 3000, still));
        assert_eq!(
            run(&mut d, &looks),
            [
                (0, Event::Arrived),
                (600, Event::Still),
                (900, Event::Moved)
            ]
        );
    }

    #[test]
    fn a_second_parcel_after_an_empty_table_is_measured_even_in_the_same_place() {
        let mut d = detector();
        let mut looks = hold(0, 900, parcel(2, 2));
        looks.extend(hold(900, 1200, EMPTY));
        looks.extend(hold(1200, 2100, parcel(2, 2)));
        assert_eq!(
            run(&mut d, &looks),
            [
                (0, Event::Arrived),
                (600, Event::Still),
                (900, Event::Left),
                (1200, Event::Arrived),
                (1800, Event::Still)
            ]
        );
    }

    #[test]
    fn a_forgotten_measurement_is_made_again_after_the_still_time() {
        let mut d = detector();
        let t0 = Instant::now();
        let at = |ms| t0 + Duration::from_millis(ms);
        let m = map(parcel(2, 2));
        assert_eq!(d.observe(at(0), &m), Some(Event::Arrived));
        assert_eq!(d.observe(at(600), &m), Some(Event::Still));
        assert_eq!(d.observe(at(700), &m), None);
        d.forget(at(750));
        assert_eq!(d.observe(at(900), &m), None);
        assert_eq!(d.observe(at(1350), &m), Some(Event::Still));
    }

    #[test]
    fn a_speck_smaller_than_the_least_parcel_is_no_parcel() {
        let mut d = detector();
        let mut speck = EMPTY;
        speck[3] = "...99...";
        assert_eq!(run(&mut d, &hold(0, 2000, speck)), []);
    }

    #[test]
    fn a_synthetic_depth_frame_gives_the_parcel_s_footprint_and_height() {
        use rgbd::{Camera as _, Scene, SyntheticCamera};
        let scene = Scene::default_single();
        let camera = &SyntheticCamera::all(&scene).expect("camera")[0];
        let depth = camera.render_depth(1);
        let k = camera.depth_intrinsics().expect("intrinsics");
        let pose = camera.true_pose().expect("calibrated");
        let to_table = crate::vision::calibration::pose_transformation(&pose)
            .to_transform()
            .expect("transform");
        let mut m = HeightMap::new(Grid::default());
        m.add_depth(&depth, &k, &to_table, 4);
        // A 40 x 30 cm footprint is 300 cells of 2 cm; the cells its 1.4 m outline
        // crosses (about 70) count when enough of them is parcel.
        let occupied = m.occupied_cells(0.02);
        assert!((300..=400).contains(&occupied), "{occupied}");
        let top = (0..m.counts.len())
            .filter_map(|i| m.height(i))
            .fold(0.0f32, f32::max);
        assert!((0.19..0.21).contains(&top), "{top}");
        // Two views of one moment merge into the same map, twice the points.
        let mut twice = m.clone();
        twice.merge(&m);
        assert_eq!(twice.occupied_cells(0.02), occupied);
        assert!(Stillness::new(StillnessConfig::default()).same(&m, &twice));
    }
}
