//! Fiducial markers for calibration, from the AprilTag C library (through `apriltag` and
//! `apriltag-sys`): the patterns of a family, which the synthetic camera paints onto its
//! floor, and the detector, which `coapcam calibrate` runs on color images. Both sides
//! use the library's own tables, so a synthetic marker is the marker one prints.
//!
//! `sheet` lays markers out on paper at a true size and writes them as a PDF to print.
//!
//! The marker frame, used by every function here: the pattern as printed, seen from the
//! front, with x to the right, y up and z out of the paper; the origin at the centre.

// The library's families are C structs; reading a pattern needs two FFI calls, kept in
// `pattern` below. Detection goes through the `apriltag` crate's safe wrappers.
#![allow(unsafe_code)]

pub mod sheet;

use std::fmt;
use std::str::FromStr;

use apriltag::{DetectorBuilder, Image, image_buf::DEFAULT_ALIGNMENT_U8};
use apriltag_sys as sys;

/// A marker family.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Family {
    /// AprilTag 36h11: 587 markers, 6 x 6 data bits, minimum Hamming distance 11.
    Tag36h11,
}

/// Families that can be parsed, by name.
pub const FAMILIES: &[&str] = &["tag36h11"];

/// Why a family name was refused.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{0}")]
pub struct UnknownFamily(String);

impl FromStr for Family {
    type Err = UnknownFamily;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s {
            "tag36h11" => Ok(Self::Tag36h11),
            "aruco_mip_36h12" => Err(UnknownFamily(
                "family aruco_mip_36h12 (the thesis's ArUco markers) is not in the AprilTag library; use tag36h11".to_owned(),
            )),
            other => Err(UnknownFamily(format!(
                "unknown marker family {other:?}; known: {}",
                FAMILIES.join(", ")
            ))),
        }
    }
}

impl fmt::Display for Family {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Self::Tag36h11 => "tag36h11",
        })
    }
}

/// A family's C table, destroyed on drop.
struct Table(*mut sys::apriltag_family_t);

impl Table {
    fn new(family: Family) -> Self {
        // SAFETY: the constructor allocates and fills a table; null only when out of
        // memory, which aborts in Rust terms anyway.
        let ptr = match family {
            Family::Tag36h11 => unsafe { sys::tag36h11_create() },
        };
        assert!(
            !ptr.is_null(),
            "the AprilTag library could not allocate a family"
        );
        Self(ptr)
    }

    fn codes(&self) -> u32 {
        // SAFETY: `self.0` is a live table from its constructor.
        unsafe { (*self.0).ncodes }
    }
}

impl Drop for Table {
    fn drop(&mut self) {
        // SAFETY: the pointer came from the matching constructor and is dropped once.
        unsafe { sys::tag36h11_destroy(self.0) }
    }
}

/// One marker's pattern as printed: `cells` x `cells` squares, row 0 at the top. It
/// includes the white ring around the black border, one cell wide.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Pattern {
    /// Squares per side, the white ring included (10 for tag36h11).
    pub cells: usize,
    /// Squares per side of the black border's outline (8 for tag36h11): the marker's
    /// size is measured on it.
    pub black_cells: usize,
    /// Row-major, `true` for white.
    pub white: Vec<bool>,
}

impl Pattern {
    /// Whether the square at `col`, `row` (0 at the left and top) is white.
    pub fn is_white(&self, col: usize, row: usize) -> bool {
        self.white[row * self.cells + col]
    }
}

impl Family {
    /// How many markers the family has (valid ids are below this).
    pub fn ids(self) -> u32 {
        Table::new(self).codes()
    }

    /// The pattern of marker `id`, as the library draws it; `None` if there is no such id.
    pub fn pattern(self, id: u32) -> Option<Pattern> {
        let table = Table::new(self);
        if id >= table.codes() {
            return None;
        }
        // SAFETY: `id` is below `ncodes` (the function asserts that), the table is live,
        // and the image it returns is read within its width, height and stride, then
        // destroyed once.
        unsafe {
            let image = sys::apriltag_to_image(table.0, id as i32);
            assert!(
                !image.is_null(),
                "the AprilTag library could not draw a marker"
            );
            let (w, h, stride) = (
                (*image).width as usize,
                (*image).height as usize,
                (*image).stride as usize,
            );
            let buf = std::slice::from_raw_parts((*image).buf, stride * h);
            let white = (0..h)
                .flat_map(|r| buf[r * stride..r * stride + w].iter().map(|&v| v > 127))
                .collect();
            let black_cells = (*table.0).width_at_border as usize;
            sys::image_u8_destroy(image);
            debug_assert_eq!(w, h);
            Some(Pattern {
                cells: w,
                black_cells,
                white,
            })
        }
    }
}

/// A marker found in an image.
#[derive(Debug, Clone, PartialEq)]
pub struct Detection {
    /// Its id in the family.
    pub id: u32,
    /// The corners of its black square in pixels (x right, y down, (0, 0) the centre of
    /// the top-left pixel), in the marker frame's order:
    /// (-, -), (+, -), (+, +), (-, +); that is bottom-left, bottom-right, top-right and
    /// top-left of the pattern as printed.
    pub corners: [[f64; 2]; 4],
    /// Bits the detector corrected (0 is best).
    pub hamming: u32,
    /// The library's decision margin: how clearly the bits were read.
    pub margin: f32,
}

/// Why detection failed.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum DetectError {
    /// The image buffer does not hold `width * height` bytes.
    #[error("a {width} x {height} gray image needs {need} bytes, got {got}")]
    Size {
        /// Width.
        width: usize,
        /// Height.
        height: usize,
        /// Bytes needed.
        need: usize,
        /// Bytes given.
        got: usize,
    },
    /// The library refused (out of memory, or an image too large).
    #[error("AprilTag: {0}")]
    Library(String),
}

/// The markers of `family` in a gray image (`width` x `height` bytes, row-major), at full
/// resolution with edge refinement. Detections with
/// more than 2 corrected bits are dropped.
pub fn detect(
    family: Family,
    gray: &[u8],
    width: usize,
    height: usize,
) -> Result<Vec<Detection>, DetectError> {
    if gray.len() != width * height {
        return Err(DetectError::Size {
            width,
            height,
            need: width * height,
            got: gray.len(),
        });
    }
    let library = |e: apriltag::error::Error| DetectError::Library(e.to_string());
    let mut image =
        Image::zeros_with_alignment(width, height, DEFAULT_ALIGNMENT_U8).map_err(library)?;
    let stride = image.stride();
    let buf = image.as_slice_mut();
    for (row, src) in gray.chunks_exact(width).enumerate() {
        buf[row * stride..row * stride + width].copy_from_slice(src);
    }
    let family_handle = match family {
        Family::Tag36h11 => apriltag::Family::tag_36h11(),
    };
    let mut detector = DetectorBuilder::new()
        .add_family_bits(family_handle, 2)
        .build()
        .map_err(library)?;
    detector.set_decimation(1.0);
    detector.set_refine_edges(true);
    let threads = std::thread::available_parallelism().map_or(1, |n| n.get().min(8));
    detector.set_thread_number(threads as u8);
    Ok(detector
        .detect(&image)
        .into_iter()
        .filter(|d| d.hamming() <= 2)
        .map(|d| {
            // The library's pixel centres are at +0.5 (its (0, 0) is the top-left
            // pixel's corner).
            let corners = d.corners().map(|[x, y]| [x - 0.5, y - 0.5]);
            Detection {
                id: d.id() as u32,
                corners,
                hamming: d.hamming() as u32,
                margin: d.decision_margin(),
            }
        })
        .collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Marker `id` drawn upright at `px` pixels per cell, its top-left cell at (`x0`,
    /// `y0`), on a white `size` x `size` image.
    fn drawn(id: u32, px: usize, x0: usize, y0: usize, size: usize) -> Vec<u8> {
        let p = Family::Tag36h11.pattern(id).expect("an id of the family");
        let mut image = vec![255u8; size * size];
        for r in 0..p.cells * px {
            for c in 0..p.cells * px {
                if !p.is_white(c / px, r / px) {
                    image[(y0 + r) * size + x0 + c] = 0;
                }
            }
        }
        image
    }

    #[test]
    fn tag36h11_has_587_ten_cell_patterns_with_a_white_ring_and_black_border() {
        assert_eq!(Family::Tag36h11.ids(), 587);
        assert!(Family::Tag36h11.pattern(587).is_none());
        let p = Family::Tag36h11.pattern(0).expect("id 0");
        assert_eq!((p.cells, p.black_cells), (10, 8));
        for i in 0..10 {
            assert!(p.is_white(i, 0) && p.is_white(0, i) && p.is_white(i, 9) && p.is_white(9, i));
        }
        for i in 1..9 {
            assert!(
                !p.is_white(i, 1) && !p.is_white(1, i) && !p.is_white(i, 8) && !p.is_white(8, i)
            );
        }
        assert_ne!(p, Family::Tag36h11.pattern(1).expect("id 1"));
    }

    #[test]
    fn a_drawn_marker_is_detected_with_its_id_and_corners_in_marker_order() {
        // 20 px per cell, the marker's top-left cell at (100, 60): the black square spans
        // x 120..280 and y 80..240 (pixel edges), so its corners, in pixel-centre
        // coordinates, are 0.5 px less.
        let image = drawn(42, 20, 100, 60, 400);
        let found = detect(Family::Tag36h11, &image, 400, 400).expect("detection runs");
        assert_eq!(found.len(), 1, "{found:?}");
        assert_eq!(found[0].id, 42);
        let expected = [[119.5, 239.5], [279.5, 239.5], [279.5, 79.5], [119.5, 79.5]];
        for (got, want) in found[0].corners.iter().zip(expected) {
            assert!(
                (got[0] - want[0]).abs() < 0.5 && (got[1] - want[1]).abs() < 0.5,
                "{:?}",
                found[0].corners
            );
        }
    }

    #[test]
    fn names_parse_and_the_thesis_family_is_refused_with_a_reason() {
        assert_eq!("tag36h11".parse::<Family>(), Ok(Family::Tag36h11));
        let e = "aruco_mip_36h12".parse::<Family>().unwrap_err();
        assert!(e.to_string().contains("use tag36h11"), "{e}");
        assert!("qr".parse::<Family>().is_err());
    }
}
