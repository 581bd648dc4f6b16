//! Parts of the table from which a camera's pixels returned no depth at all: a parcel
//! too dark (or too shiny) for the stereo match leaves a hole in the depth image where it
//! stands. A camera prepared with a floor cut does not send the floor, so its cloud cannot
//! tell such a hole from an empty table; the camera's server can, before the pixels
//! outside the region are zeroed ([`DepthPart::no_depth`]). The regions travel beside a
//! cloud in the [`NO_DEPTH`] option and become a refusal ("no depth from part of the
//! table"), never a silent "nothing there" (docs/design.md §6).
//!
//! A region is a connected set of pixels without depth whose rays meet the floor inside
//! the region kept (`roi3d`'s x and y), bordered mostly by floor, and whose floor under
//! it is at least as large as the smallest measurable parcel. The stereo shadow is not
//! one: a D415's depth is the left imager's, and beside a parcel's left edge (in the
//! image) the right imager cannot see the floor; that run of a row is at most as wide as
//! the disparities of the parcel's edge and of the floor behind it differ. Where the
//! parcel's own wall returned no depth either, the run holds both: its first pixels, that
//! wide, are the shadow and are left out, and count as floor on the region's border.

use coap::{OptionNumber, Options};

use geometry::{Roi3, Transform};
use rgbd::{DepthFrame, Intrinsics};

use super::codec::DepthPart;

/// The response option that carries a cloud's no-depth regions (experimental range,
/// elective and safe to forward: a client that does not know it ignores it). Its value is
/// up to [`MAX_REGIONS`] regions of six little-endian f32: min x, min y, max x, max y
/// (metres, the common frame), the floor's area under the region (m²) and the share of
/// its border that reads floor, then a u32: its pixels.
pub const NO_DEPTH: OptionNumber = OptionNumber(65004);

/// Most regions an option carries (the largest): 16 x 28 bytes.
pub const MAX_REGIONS: usize = 16;

/// Bytes of one region in the option.
const REGION_LEN: usize = 28;

/// A part of the table from which one camera's pixels returned no depth: where their rays
/// meet the floor.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct NoDepth {
    /// Smallest x and y of the rays' floor points, metres, the common frame.
    pub min_m: [f32; 2],
    /// Largest x and y.
    pub max_m: [f32; 2],
    /// The floor's area under the region's pixels, m².
    pub area_m2: f32,
    /// The share of the pixels with depth around it that read floor (0 to 1; of regions
    /// joined, the largest): at least [`PARCEL_FLOOR_BORDER`] for a parcel that returns
    /// nothing, less for the rim of one that returns a little.
    pub floor_border: f32,
    /// Its pixels.
    pub pixels: u32,
}

impl NoDepth {
    /// Whether the two regions' rectangles overlap.
    pub fn overlaps(&self, other: &Self) -> bool {
        (0..2).all(|k| self.min_m[k] <= other.max_m[k] && other.min_m[k] <= self.max_m[k])
    }

    /// Whether its rectangle reaches beyond `other`'s on every side: a rim around it.
    pub fn rings(&self, other: &Self) -> bool {
        (0..2).all(|k| self.min_m[k] < other.min_m[k] && self.max_m[k] > other.max_m[k])
    }

    /// The area of its rectangle, m².
    pub fn rect_m2(&self) -> f32 {
        (self.max_m[0] - self.min_m[0]) * (self.max_m[1] - self.min_m[1])
    }

    /// The area both rectangles cover, m².
    pub fn intersection_m2(&self, other: &Self) -> f32 {
        let side = |k: usize| {
            (self.max_m[k].min(other.max_m[k]) - self.min_m[k].max(other.min_m[k])).max(0.0)
        };
        side(0) * side(1)
    }

    /// The rectangle around both, their areas and pixels added.
    #[must_use]
    pub fn joined(&self, other: &Self) -> Self {
        Self {
            min_m: [0, 1].map(|k| self.min_m[k].min(other.min_m[k])),
            max_m: [0, 1].map(|k| self.max_m[k].max(other.max_m[k])),
            area_m2: self.area_m2 + other.area_m2,
            floor_border: self.floor_border.max(other.floor_border),
            pixels: self.pixels.saturating_add(other.pixels),
        }
    }

    /// The rectangle's corners, in order around it.
    pub fn corners_m(&self) -> [[f64; 2]; 4] {
        let ([x0, y0], [x1, y1]) = (self.min_m.map(f64::from), self.max_m.map(f64::from));
        [[x0, y0], [x1, y0], [x1, y1], [x0, y1]]
    }
}

/// The option's value for `regions` (the first [`MAX_REGIONS`]).
pub fn encode(regions: &[NoDepth]) -> Vec<u8> {
    let mut out = Vec::with_capacity(regions.len().min(MAX_REGIONS) * REGION_LEN);
    for r in regions.iter().take(MAX_REGIONS) {
        for v in [
            r.min_m[0],
            r.min_m[1],
            r.max_m[0],
            r.max_m[1],
            r.area_m2,
            r.floor_border,
        ] {
            out.extend_from_slice(&v.to_le_bytes());
        }
        out.extend_from_slice(&r.pixels.to_le_bytes());
    }
    out
}

/// Why a No-Depth option was not read.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum NoDepthError {
    /// Not a whole number of regions, or more than [`MAX_REGIONS`].
    #[error("a No-Depth option of {0} bytes (a multiple of {REGION_LEN}, at most {max})", max = MAX_REGIONS * REGION_LEN)]
    Length(usize),
    /// A value that is not finite, a minimum above its maximum, a negative area, or a
    /// share outside 0 to 1.
    #[error("a No-Depth option with a region that is not one")]
    Region,
}

/// The regions of an option's value.
pub fn decode(value: &[u8]) -> Result<Vec<NoDepth>, NoDepthError> {
    if !value.len().is_multiple_of(REGION_LEN) || value.len() > MAX_REGIONS * REGION_LEN {
        return Err(NoDepthError::Length(value.len()));
    }
    value
        .chunks_exact(REGION_LEN)
        .map(|c| {
            let word = |i: usize| [c[4 * i], c[4 * i + 1], c[4 * i + 2], c[4 * i + 3]];
            let f = |i: usize| f32::from_le_bytes(word(i));
            let r = NoDepth {
                min_m: [f(0), f(1)],
                max_m: [f(2), f(3)],
                area_m2: f(4),
                floor_border: f(5),
                pixels: u32::from_le_bytes(word(6)),
            };
            let finite = (0..6).all(|i| f(i).is_finite());
            if finite
                && r.min_m[0] <= r.max_m[0]
                && r.min_m[1] <= r.max_m[1]
                && r.area_m2 >= 0.0
                && (0.0..=1.0).contains(&r.floor_border)
            {
                Ok(r)
            } else {
                Err(NoDepthError::Region)
            }
        })
        .collect()
}

/// The regions of a response's options (none without the option).
pub fn of_options(options: &Options) -> Result<Vec<NoDepth>, NoDepthError> {
    options.first(NO_DEPTH).map_or(Ok(Vec::new()), decode)
}

/// A pixel reading this high or lower above the floor (metres) is floor: the floor's
/// depth noise at 2 m (a few millimetres, more unfiltered) stays well inside it, and the
/// lowest measurable parcel (10 mm at d = 5) is near it, so a parcel's lid is not taken
/// for floor but its lowest wall pixels may be.
const FLOOR_BAND_M: f32 = 0.02;

/// A region's floor is at least this large (m²): the smallest measurable parcel's
/// footprint (10 d by 10 d, 50 x 50 mm at d = 5). The dark boxes the lane set loses
/// leave 0.1-0.5 m² (box, its own shadow and the floor its lid hides).
const MIN_AREA_M2: f32 = 0.05 * 0.05;

/// A parcel that returns no depth is bordered by floor: at least this share of the pixels
/// with depth around its region read floor. A region bordered less by floor is a hole in
/// a surface the cloud holds (a lid, a wall at a grazing angle) or the rim of a parcel
/// measured inside it, never a parcel of its own (`report::Table::with_no_depth`).
pub const PARCEL_FLOOR_BORDER: f32 = 0.5;

/// At least this share of the pixels with depth around a region read floor, or it is
/// not sent: a hole in a lid is bordered by the lid alone. A parcel that returns a
/// little (a black bag: the middle of its top and a speckle of its sides) leaves a rim
/// bordered by floor outside and mostly by its own speckle (16 to 31 % floor in the
/// certification set's black bags), which the client judges against the parcel measured
/// inside it.
const MIN_FLOOR_BORDER: f32 = 0.1;

/// A run of a row without depth this much wider (pixels) than the stereo shadow the
/// depths at its ends give is not that shadow alone: the spatial filter and the pixels
/// mixing an edge with the floor move the ends by a pixel or so. Of a wider run, the
/// shadow's width is left out.
const SHADOW_SLACK_PX: f32 = 2.0;

impl DepthPart {
    /// The parts of the table from which this camera's pixels returned no depth (see the
    /// module), the largest first. Call it before [`DepthPart::points`], which zeroes the
    /// pixels outside the region (the floor of a camera with a floor cut among them).
    /// `baseline_m` is the camera's stereo baseline; a camera without a stereo pair
    /// (`None`) casts no stereo shadow, so every run of pixels without depth counts.
    pub fn no_depth(&self, baseline_m: Option<f32>) -> Vec<NoDepth> {
        let to_common = match &self.correction {
            Some(c) => self.transform.then(c),
            None => self.transform,
        };
        no_depth(
            &self.depth,
            &self.intrinsics,
            &to_common,
            &self.roi,
            baseline_m,
        )
    }
}

/// [`DepthPart::no_depth`] of a frame the caller keeps: `d` with its intrinsics `k`, moved
/// into the common frame by `to_common`, inside `roi` (the server finds the regions on
/// the depth as the camera returned it, before the post-processing stages).
pub fn no_depth(
    d: &DepthFrame,
    k: &Intrinsics,
    to_common: &Transform,
    roi: &Roi3,
    baseline_m: Option<f32>,
) -> Vec<NoDepth> {
    let (w, h) = (d.width as usize, d.height as usize);
    if w == 0 || h == 0 {
        return Vec::new();
    }
    let raw = |x: usize, y: usize| d.data.get(y * d.stride + x).copied().unwrap_or(0);
    let metres = |v: u16| f32::from(v) * d.depth_scale;
    // The transform's numbers as plain arrays: this runs per pixel of every hole.
    let l = &to_common.linear;
    let rows = [0, 1, 2].map(|r| [l[(r, 0)], l[(r, 1)], l[(r, 2)]]);
    let origin = [0, 1, 2].map(|r| to_common.translation[r]);
    let moved = |v: [f32; 3], r: usize| rows[r][0] * v[0] + rows[r][1] * v[1] + rows[r][2] * v[2];
    let is_floor = |x: usize, y: usize| {
        let p = k.deproject([x as f32, y as f32], metres(raw(x, y)));
        origin[2] + moved(p, 2) <= FLOOR_BAND_M
    };
    // Pixels without depth that are not a stereo shadow.
    // Runs of rows (row, first, end) first: most frames have none, and then no image
    // of flags is made.
    let mut runs = Vec::new();
    // The shadows left out of wider runs: floor the left imager sees, so a region
    // bordering one borders floor.
    let mut shades = Vec::new();
    let disparity = k.fx * baseline_m.unwrap_or(0.0);
    for (y, row) in d.data.chunks(d.stride.max(1)).take(h).enumerate() {
        let row = &row[..w.min(row.len())];
        let mut x = 0;
        while let Some(from) = row[x..].iter().position(|&v| v == 0) {
            let start = x + from;
            x = row[start..]
                .iter()
                .position(|&v| v != 0)
                .map_or(row.len(), |n| start + n);
            // The run is start..x; the stereo shadow lies left of a nearer surface, as
            // wide as the two disparities differ (at the image's left edge, where the
            // right imager sees nothing, the far side's disparity is 0). A run no wider
            // is that shadow. A wider one beside floor holds the shadow and the nearer
            // surface's own near part that returned no depth (a dark parcel's wall):
            // its first pixels, the shadow's width, are left out.
            let shadow = if x < row.len() {
                let near = metres(row[x]);
                let far_inverse = if start == 0 {
                    0.0
                } else {
                    1.0 / metres(row[start - 1])
                };
                (disparity * (1.0 / near - far_inverse)).max(0.0)
            } else {
                0.0
            };
            if x >= row.len() || (x - start) as f32 > shadow + SHADOW_SLACK_PX {
                let beside_floor = start == 0 || is_floor(start - 1, y);
                let from = if beside_floor {
                    start + shadow.floor() as usize
                } else {
                    start
                };
                runs.push((y, from, x));
                if from > start {
                    shades.push((y, start, from));
                }
            }
            if x >= row.len() {
                break;
            }
        }
    }
    if runs.is_empty() {
        return Vec::new();
    }
    let mut hole = vec![false; w * h];
    for &(y, start, end) in &runs {
        hole[y * w + start..y * w + end].fill(true);
    }
    let mut shade = vec![false; if shades.is_empty() { 0 } else { w * h }];
    for &(y, start, end) in &shades {
        shade[y * w + start..y * w + end].fill(true);
    }
    // Where each pixel's ray meets the floor (z = 0), and the floor's area it covers.
    let floor_of = |x: usize, y: usize| -> Option<([f32; 2], f32)> {
        let ray = k.deproject([x as f32, y as f32], 1.0);
        let dz = moved(ray, 2);
        if dz >= -1e-6 {
            return None;
        }
        let t = -origin[2] / dz;
        if t <= 0.0 {
            return None;
        }
        let p = [0, 1].map(|r| origin[r] + moved(ray, r) * t);
        // The pixel's solid angle is 1 / (fx fy |ray|^3) for a ray (x, y, 1), its
        // footprint at distance t |ray| on a floor tilted from it by cos = |dz| /
        // |ray|: t^2 / (fx fy |dz|).
        Some((p, t * t / (k.fx * k.fy * -dz)))
    };
    let (min, max) = (roi.min(), roi.max());
    let on_table = |p: [f32; 2]| (min.x..=max.x).contains(&p[0]) && (min.y..=max.y).contains(&p[1]);
    // Connected regions of holes (4-neighbours); a pixel taken into a region leaves
    // `hole` (it has no depth, so it is no region's border either).
    let mut regions = Vec::new();
    let mut stack = Vec::new();
    let pixels = runs
        .iter()
        .flat_map(|&(y, start, end)| y * w + start..y * w + end);
    for start in pixels {
        if !hole[start] {
            continue;
        }
        hole[start] = false;
        stack.push(start);
        let mut region: Option<NoDepth> = None;
        let (mut floor_border, mut border) = (0u32, 0u32);
        while let Some(i) = stack.pop() {
            let (x, y) = (i % w, i / w);
            if let Some((p, area)) = floor_of(x, y).filter(|(p, _)| on_table(*p)) {
                let one = NoDepth {
                    min_m: p,
                    max_m: p,
                    area_m2: area,
                    floor_border: 0.0,
                    pixels: 1,
                };
                region = Some(region.map_or(one, |r| r.joined(&one)));
            }
            let neighbours = [
                (x > 0).then(|| i - 1),
                (x + 1 < w).then_some(i + 1),
                (y > 0).then(|| i - w),
                (y + 1 < h).then_some(i + w),
            ];
            for n in neighbours.into_iter().flatten() {
                if hole[n] {
                    hole[n] = false;
                    stack.push(n);
                } else if raw(n % w, n / w) != 0 {
                    border += 1;
                    floor_border += u32::from(is_floor(n % w, n / w));
                } else if shade.get(n) == Some(&true) {
                    border += 1;
                    floor_border += 1;
                }
            }
        }
        if let Some(r) = region
            && r.area_m2 >= MIN_AREA_M2
            && floor_border as f32 >= MIN_FLOOR_BORDER * border as f32
        {
            regions.push(NoDepth {
                floor_border: floor_border as f32 / border.max(1) as f32,
                ..r
            });
        }
    }
    regions.sort_by(|a, b| b.area_m2.total_cmp(&a.area_m2));
    regions
}

#[cfg(test)]
mod tests {
    use geometry::Point3;

    use super::*;

    /// A camera 1.5 m over the floor looking straight down (image x along the common x,
    /// image y along -y), 160 x 120 pixels of focal length 400, with `depth` (mm) at
    /// each pixel.
    fn looking_down(depth: impl Fn(usize, usize) -> u16) -> DepthPart {
        let (w, h) = (160usize, 120usize);
        let data = (0..w * h).map(|i| depth(i % w, i / w)).collect();
        DepthPart {
            serial: "840412060746".into(),
            depth: DepthFrame {
                width: w as u32,
                height: h as u32,
                stride: w,
                depth_scale: 0.001,
                timestamp_us: 0,
                frame_number: 1,
                data,
            },
            intrinsics: Intrinsics {
                width: w as u32,
                height: h as u32,
                ppx: 80.0,
                ppy: 60.0,
                fx: 400.0,
                fy: 400.0,
                model: rgbd::DistortionModel::None,
                coeffs: [0.0; 5],
            },
            transform: Transform {
                linear: nalgebra::Matrix3::new(1.0, 0.0, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0, -1.0),
                translation: nalgebra::Vector3::new(0.0, 0.0, 1.5),
            },
            roi: Roi3::new(Point3::new(-1.0, -1.0, 0.005), Point3::new(1.0, 1.0, 3.0))
                .expect("a region"),
            correction: None,
        }
    }

    #[test]
    fn a_parcel_without_depth_is_found_and_shadows_and_lid_holes_are_not() {
        let inside = |x: usize, y: usize, xs: (usize, usize), ys: (usize, usize)| {
            (xs.0..xs.1).contains(&x) && (ys.0..ys.1).contains(&y)
        };
        let part = looking_down(|x, y| {
            if x < 3 {
                // The band at the image's left edge that the right imager does not see.
                0
            } else if inside(x, y, (115, 125), (50, 70)) {
                // A hole in the lid of a box 30 cm high (dark tape): bordered by lid.
                0
            } else if inside(x, y, (100, 140), (10, 110)) {
                1200
            } else if inside(x, y, (96, 100), (10, 110)) {
                // The stereo shadow left of the box: 400 x 0.055 x (1/1.2 - 1/1.5) =
                // 3.7 pixels wide.
                0
            } else if inside(x, y, (20, 60), (40, 90)) {
                // A box that returns no depth at all, bordered by floor.
                0
            } else {
                1500
            }
        });
        let found = part.no_depth(Some(0.055));
        assert_eq!(found.len(), 1, "{found:?}");
        let r = found[0];
        assert_eq!(r.pixels, 40 * 50);
        // Pixel x 20..59 at 1.5 m: x from (20 - 80) / 400 x 1.5 to (59 - 80) / 400 x 1.5;
        // rows 40..89: y from -(89 - 60) / 400 x 1.5 to -(40 - 60) / 400 x 1.5.
        let near = |a: f32, b: f32| (a - b).abs() < 1e-4;
        assert!(
            near(r.min_m[0], -0.225) && near(r.max_m[0], -0.07875),
            "{r:?}"
        );
        assert!(
            near(r.min_m[1], -0.10875) && near(r.max_m[1], 0.075),
            "{r:?}"
        );
        // Each pixel covers (1.5 / 400)^2 of floor.
        assert!((r.area_m2 - 2000.0 * 1.40625e-5).abs() < 1e-5, "{r:?}");
        assert_eq!(r.floor_border, 1.0, "bordered by floor alone");
        // A narrower shadow rule would take the shadow for a parcel (400 pixels, 0.0056
        // m²), and without the border rule the lid's hole would be one (200 pixels).
        assert!(
            part.no_depth(None).len() > 1,
            "a camera without a stereo pair casts no shadow"
        );
    }

    /// A black bag returns depth from the middle of its top and a speckle of its sides
    /// only: the region of its rim is bordered by floor outside, by the bag inside and
    /// around every speckle. It is a region all the same (the client judges it against the
    /// parcel measured inside it); a lid's hole, bordered by lid alone, is still not one.
    #[test]
    fn a_dark_parcels_rim_bordered_mostly_by_its_own_speckle_is_a_region() {
        let inside = |x: usize, y: usize, xs: (usize, usize), ys: (usize, usize)| {
            (xs.0..xs.1).contains(&x) && (ys.0..ys.1).contains(&y)
        };
        let part = looking_down(|x, y| {
            if inside(x, y, (115, 125), (50, 70)) {
                0
            } else if inside(x, y, (100, 140), (10, 110)) {
                1200
            } else if inside(x, y, (30, 50), (55, 75)) {
                // The bag's top.
                1200
            } else if inside(x, y, (20, 60), (40, 90)) {
                // Its sides: a pixel in twelve returns depth.
                if x % 6 == 0 && y % 2 == 0 { 1250 } else { 0 }
            } else {
                1500
            }
        });
        let found = part.no_depth(None);
        assert_eq!(found.len(), 1, "{found:?}");
        let r = found[0];
        // The rim reaches the bag's edges: pixel x 20..59 at 1.5 m.
        assert!((r.min_m[0] + 0.225).abs() < 0.01, "{r:?}");
        assert!((r.max_m[0] + 0.07875).abs() < 0.01, "{r:?}");
        assert!(r.floor_border < PARCEL_FLOOR_BORDER, "{r:?}");
    }

    /// A dark box's wall returns no depth where it meets the stereo shadow beside it: one
    /// run of each row holds both. The region is the wall's: its floor points start where
    /// the shadow ends, not where the shadow starts (a black cylinder's region reached 23
    /// mm beyond what it hides, and took in the parcel standing there; cert scene 462).
    #[test]
    fn the_stereo_shadow_beside_a_dark_wall_is_left_out_of_its_region() {
        let inside = |x: usize, y: usize, xs: (usize, usize), ys: (usize, usize)| {
            (xs.0..xs.1).contains(&x) && (ys.0..ys.1).contains(&y)
        };
        let part = looking_down(|x, y| {
            if inside(x, y, (96, 110), (10, 110)) {
                // 3.7 pixels of shadow (as above), then the box's dark left part.
                0
            } else if inside(x, y, (110, 140), (10, 110)) {
                1200
            } else {
                1500
            }
        });
        let found = part.no_depth(Some(0.055));
        assert_eq!(found.len(), 1, "{found:?}");
        let r = found[0];
        // Pixel 99 on, at 1.5 m: x from (99 - 80) / 400 x 1.5.
        assert!((r.min_m[0] - 0.07125).abs() < 1e-4, "{r:?}");
        assert_eq!(r.pixels, 11 * 100);
        // The shadow left out is floor the left imager sees: the region borders floor
        // there (else a black parcel bordered by its shadow and a neighbour was no region,
        // and went missing: cert scene 467).
        assert!((r.floor_border - 122.0 / 222.0).abs() < 1e-6, "{r:?}");
        // Without a stereo pair there is no shadow: the run is a hole from its start.
        let all = part.no_depth(None);
        assert!((all[0].min_m[0] - 0.06).abs() < 1e-4, "{all:?}");
    }

    #[test]
    fn regions_survive_the_option() {
        let r = [
            NoDepth {
                min_m: [-0.2, 0.1],
                max_m: [0.05, 0.3],
                area_m2: 0.04,
                floor_border: 0.8,
                pixels: 2500,
            },
            NoDepth {
                min_m: [0.3, -0.4],
                max_m: [0.5, -0.1],
                area_m2: 0.03,
                floor_border: 0.25,
                pixels: 1900,
            },
        ];
        assert_eq!(decode(&encode(&r)), Ok(r.to_vec()));
        assert_eq!(decode(&[0; 7]), Err(NoDepthError::Length(7)));
        let mut bad = encode(&r[..1]);
        bad[..4].copy_from_slice(&1.0f32.to_le_bytes());
        assert_eq!(decode(&bad), Err(NoDepthError::Region), "min above max");
    }
}
