//! Pictures for people: depth in grayscale (near is bright, as the thesis shows it) and
//! colour-mapped, a top view of a point cloud coloured by height, and the measured box
//! drawn onto a color image with its dimensions.

use std::path::{Path, PathBuf};

use anyhow::Context as _;
use geometry::{Dimensions, PointCloud};
use image::{GrayImage, ImageFormat, Luma, Rgb, RgbImage};

use crate::repr::packet::DepthImage;

/// The depth values at the 1st and 99th percentile of the valid (non-zero) pixels, so a
/// few flying pixels do not flatten the picture; `None` without valid pixels.
fn depth_range(values: &[u16]) -> Option<(u16, u16)> {
    let mut valid: Vec<u16> = values.iter().copied().filter(|v| *v != 0).collect();
    if valid.is_empty() {
        return None;
    }
    let last = valid.len() - 1;
    let (lo_at, hi_at) = (last / 100, last - last / 100);
    let (_, lo, _) = valid.select_nth_unstable(lo_at);
    let lo = *lo;
    let (_, hi, _) = valid.select_nth_unstable(hi_at);
    Some((lo, (*hi).max(lo + 1)))
}

/// 0 at `lo` (near) to 1 at `hi` (far), clamped.
fn normalized(v: u16, lo: u16, hi: u16) -> f32 {
    ((f32::from(v) - f32::from(lo)) / f32::from(hi - lo)).clamp(0.0, 1.0)
}

/// Depth as 8-bit grayscale (near bright, far dark) and colour-mapped (near blue, far red,
/// as librealsense's "Jet" colorizer) over one depth range; pixels without depth black.
pub fn depth_views(depth: &DepthImage) -> (GrayImage, RgbImage) {
    let range = depth_range(&depth.values);
    // 0 (near) to 1 (far) at a pixel with depth.
    let at = |x: u32, y: u32| {
        let v = depth.values[(y * depth.width + x) as usize];
        match range {
            Some((lo, hi)) if v != 0 => Some(normalized(v, lo, hi)),
            _ => None,
        }
    };
    let gray = GrayImage::from_fn(depth.width, depth.height, |x, y| {
        Luma([at(x, y).map_or(0, |t| (255.0 - 215.0 * t) as u8)])
    });
    let colored = RgbImage::from_fn(depth.width, depth.height, |x, y| {
        Rgb(at(x, y).map_or([0, 0, 0], jet))
    });
    (gray, colored)
}

/// The jet colour map: blue, cyan, green, yellow, red for `t` from 0 to 1.
pub fn jet(t: f32) -> [u8; 3] {
    let c = |offset: f32| ((1.5 - (4.0 * t - offset).abs()).clamp(0.0, 1.0) * 255.0) as u8;
    [c(3.0), c(2.0), c(1.0)]
}

/// Longest side of a top view, pixels.
const TOP_VIEW_MAX_PX: f32 = 1024.0;

/// The cloud seen from above (x right, y up), one pixel per millimetre or coarser so the
/// longer side fits in 1024 pixels, each pixel coloured by the highest point in it (blue
/// low, red high); empty pixels black.
pub fn top_view(cloud: &PointCloud) -> RgbImage {
    let finite = || {
        cloud
            .points
            .iter()
            .filter(|p| p.x.is_finite() && p.y.is_finite() && p.z.is_finite())
    };
    let (mut lo, mut hi) = ([f32::MAX; 3], [f32::MIN; 3]);
    for p in finite() {
        for (i, c) in [p.x, p.y, p.z].into_iter().enumerate() {
            lo[i] = lo[i].min(c);
            hi[i] = hi[i].max(c);
        }
    }
    if lo[0] > hi[0] {
        return RgbImage::new(1, 1);
    }
    let span = (hi[0] - lo[0]).max(hi[1] - lo[1]).max(1e-3);
    let metres_per_px = (span / TOP_VIEW_MAX_PX).max(1e-3);
    let w = ((hi[0] - lo[0]) / metres_per_px) as u32 + 1;
    let h = ((hi[1] - lo[1]) / metres_per_px) as u32 + 1;
    let mut top = vec![f32::MIN; (w * h) as usize];
    for p in finite() {
        let x = ((p.x - lo[0]) / metres_per_px) as u32;
        let y = h - 1 - ((p.y - lo[1]) / metres_per_px) as u32;
        let cell = &mut top[(y.min(h - 1) * w + x.min(w - 1)) as usize];
        *cell = cell.max(p.z);
    }
    let z_span = (hi[2] - lo[2]).max(1e-3);
    RgbImage::from_fn(w, h, |x, y| {
        let z = top[(y * w + x) as usize];
        if z == f32::MIN {
            Rgb([0, 0, 0])
        } else {
            Rgb(jet((z - lo[2]) / z_span))
        }
    })
}

/// Draws the measured box (footprint on the floor, lid at the measured height, and the
/// vertical edges) onto `image` through `project` (world point in metres -> pixel), and
/// the dimensions as text in the top-left corner.
pub fn annotate(
    image: &mut RgbImage,
    dims: &Dimensions,
    project: impl Fn([f64; 3]) -> Option<[f32; 2]>,
) {
    let h = dims.height_mm / 1e3;
    let corner = |i: usize, z: f64| project([dims.corners_m[i][0], dims.corners_m[i][1], z]);
    let thickness = (image.width() / 400).max(2);
    let (floor, lid, edge) = (Rgb([255, 64, 64]), Rgb([64, 255, 64]), Rgb([255, 220, 0]));
    for i in 0..4 {
        let j = (i + 1) % 4;
        for (z, color) in [(0.0, floor), (h, lid)] {
            if let (Some(a), Some(b)) = (corner(i, z), corner(j, z)) {
                draw_line(image, a, b, color, thickness);
            }
        }
        if let (Some(a), Some(b)) = (corner(i, 0.0), corner(i, h)) {
            draw_line(image, a, b, edge, thickness);
        }
    }
    let lines = [
        format!(
            "{:.0} x {:.0} x {:.0} mm",
            dims.length_mm, dims.width_mm, dims.height_mm
        ),
        format!("yaw {:.1} deg", dims.yaw_deg),
    ];
    let scale = (image.width() / 320).max(2);
    let line_height = (GLYPH_ROWS as u32 + 3) * scale;
    let text_width = lines.iter().map(|l| l.len()).max().unwrap_or(0) as u32 * 6 * scale;
    fill(
        image,
        (0, 0),
        (
            text_width + 4 * scale,
            line_height * lines.len() as u32 + 2 * scale,
        ),
        Rgb([0, 0, 0]),
    );
    for (i, line) in lines.iter().enumerate() {
        draw_text(
            image,
            (2 * scale, 2 * scale + i as u32 * line_height),
            line,
            scale,
            Rgb([255, 255, 255]),
        );
    }
}

fn fill(image: &mut RgbImage, at: (u32, u32), size: (u32, u32), color: Rgb<u8>) {
    for y in at.1..(at.1 + size.1).min(image.height()) {
        for x in at.0..(at.0 + size.0).min(image.width()) {
            image.put_pixel(x, y, color);
        }
    }
}

/// A line `thickness` pixels wide; the parts outside the image are skipped.
fn draw_line(image: &mut RgbImage, a: [f32; 2], b: [f32; 2], color: Rgb<u8>, thickness: u32) {
    let (dx, dy) = (b[0] - a[0], b[1] - a[1]);
    let steps = dx.abs().max(dy.abs()).ceil().min(1e5) as u32;
    let half = thickness as i64 / 2;
    for s in 0..=steps {
        let t = if steps == 0 {
            0.0
        } else {
            s as f32 / steps as f32
        };
        let (x, y) = (
            (a[0] + t * dx).round() as i64,
            (a[1] + t * dy).round() as i64,
        );
        for oy in -half..=half {
            for ox in -half..=half {
                let (px, py) = (x + ox, y + oy);
                if px >= 0
                    && py >= 0
                    && px < i64::from(image.width())
                    && py < i64::from(image.height())
                {
                    image.put_pixel(px as u32, py as u32, color);
                }
            }
        }
    }
}

/// Rows of a glyph.
const GLYPH_ROWS: usize = 7;

/// A 5x7 bitmap font for the characters of the annotations; each row's low 5 bits, the
/// leftmost pixel in bit 4.
fn glyph(c: char) -> [u8; GLYPH_ROWS] {
    match c {
        '0' => [14, 17, 19, 21, 25, 17, 14],
        '1' => [4, 12, 4, 4, 4, 4, 14],
        '2' => [14, 17, 1, 2, 4, 8, 31],
        '3' => [30, 1, 1, 14, 1, 1, 30],
        '4' => [2, 6, 10, 18, 31, 2, 2],
        '5' => [31, 16, 30, 1, 1, 17, 14],
        '6' => [6, 8, 16, 30, 17, 17, 14],
        '7' => [31, 1, 2, 4, 8, 8, 8],
        '8' => [14, 17, 17, 14, 17, 17, 14],
        '9' => [14, 17, 17, 15, 1, 2, 12],
        '.' => [0, 0, 0, 0, 0, 12, 12],
        '-' => [0, 0, 0, 31, 0, 0, 0],
        'a' => [0, 0, 14, 1, 15, 17, 15],
        'd' => [1, 1, 13, 19, 17, 17, 15],
        'e' => [0, 0, 14, 17, 31, 16, 14],
        'g' => [0, 15, 17, 17, 15, 1, 14],
        'k' => [16, 16, 18, 20, 24, 20, 18],
        'm' => [0, 0, 26, 21, 21, 21, 21],
        'w' => [0, 0, 17, 17, 21, 21, 10],
        'x' => [0, 0, 17, 10, 4, 10, 17],
        'y' => [0, 0, 17, 17, 15, 1, 14],
        _ => [0; GLYPH_ROWS],
    }
}

/// Text in the 5x7 font, each font pixel `scale` x `scale` image pixels.
fn draw_text(image: &mut RgbImage, at: (u32, u32), text: &str, scale: u32, color: Rgb<u8>) {
    for (i, c) in text.chars().enumerate() {
        let x0 = at.0 + i as u32 * 6 * scale;
        for (row, bits) in glyph(c).iter().enumerate() {
            for col in 0..5u32 {
                if bits & (16 >> col) != 0 {
                    fill(
                        image,
                        (x0 + col * scale, at.1 + row as u32 * scale),
                        (scale, scale),
                        color,
                    );
                }
            }
        }
    }
}

/// `dir/name-suffix.png` for `dir/name.png`.
pub fn sibling(path: &Path, suffix: &str) -> PathBuf {
    let stem = path.file_stem().and_then(|s| s.to_str()).unwrap_or("view");
    path.with_file_name(format!("{stem}{suffix}.png"))
}

/// Saves a picture as PNG (quietly: callers say what they wrote where their output goes).
pub fn save<P, C>(image: &image::ImageBuffer<P, C>, path: &Path) -> anyhow::Result<()>
where
    P: image::PixelWithColorType,
    [P::Subpixel]: image::EncodableLayout,
    C: std::ops::Deref<Target = [P::Subpixel]>,
{
    image
        .save_with_format(path, ImageFormat::Png)
        .with_context(|| format!("writing {}", path.display()))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn depth(values: Vec<u16>, width: u32) -> DepthImage {
        DepthImage {
            width,
            height: values.len() as u32 / width,
            timestamp_s: 0,
            depth_scale: 0.001,
            values,
        }
    }

    #[test]
    fn near_is_bright_far_is_dark_and_holes_are_black() {
        let (g, _) = depth_views(&depth(vec![800, 1000, 1200, 0], 4));
        let px: Vec<u8> = g.pixels().map(|p| p.0[0]).collect();
        assert!(px[0] > px[1] && px[1] > px[2] && px[2] > 0, "{px:?}");
        assert_eq!(px[3], 0);
        let (_, c) = depth_views(&depth(vec![800, 1200, 0], 3));
        assert_eq!(c.get_pixel(0, 0).0, jet(0.0));
        assert_eq!(c.get_pixel(1, 0).0, jet(1.0));
        assert_eq!(c.get_pixel(2, 0).0, [0, 0, 0]);
    }

    #[test]
    fn jet_runs_from_blue_to_red() {
        assert_eq!(jet(0.0), [0, 0, 127]);
        assert_eq!(jet(0.5), [127, 255, 127]);
        assert_eq!(jet(1.0), [127, 0, 0]);
    }

    #[test]
    fn the_top_view_colours_the_highest_point_of_each_pixel() {
        let cloud: PointCloud = vec![
            geometry::Point3::new(0.0, 0.0, 0.0),
            geometry::Point3::new(0.0, 0.0, 0.2),
            geometry::Point3::new(0.1, 0.05, 0.0),
        ]
        .into();
        let img = top_view(&cloud);
        assert_eq!((img.width(), img.height()), (101, 51));
        assert_eq!(img.get_pixel(0, 50).0, jet(1.0));
        assert_eq!(img.get_pixel(100, 0).0, jet(0.0));
        assert_eq!(img.get_pixel(50, 25).0, [0, 0, 0]);
    }

    #[test]
    fn the_box_and_its_numbers_are_drawn() {
        let dims = Dimensions {
            length_mm: 400.0,
            width_mm: 300.0,
            height_mm: 200.0,
            yaw_deg: 0.0,
            corners_m: [[-0.2, -0.15], [0.2, -0.15], [0.2, 0.15], [-0.2, 0.15]],
            volume_l: 24.0,
            points: 1000,
        };
        let mut img = RgbImage::new(640, 480);
        // A camera 1 m above the origin looking down, 500 px focal length.
        annotate(&mut img, &dims, |[x, y, z]| {
            let d = 1.0 - z;
            Some([
                (320.0 + 500.0 * x / d) as f32,
                (240.0 - 500.0 * y / d) as f32,
            ])
        });
        // Floor edge at x = -0.2 m -> u = 220; lid edge at x = -0.2 m, 0.8 m away -> 195.
        assert_eq!(img.get_pixel(220, 240).0, [255, 64, 64]);
        assert_eq!(img.get_pixel(195, 240).0, [64, 255, 64]);
        assert_eq!(img.get_pixel(320, 240).0, [0, 0, 0]);
        let text_pixels = (0..40)
            .flat_map(|y| (0..200).map(move |x| (x, y)))
            .filter(|&(x, y)| img.get_pixel(x, y).0 == [255, 255, 255])
            .count();
        assert!(text_pixels > 100, "{text_pixels}");
    }
}
