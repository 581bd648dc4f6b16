//! Pictures for people: depth in grayscale (near is bright, as the thesis shows it) and
//! colour-mapped, a top view of a point cloud coloured by height, and the measured box
//! drawn onto a color image with its dimensions.

use std::path::{Path, PathBuf};

use geometry::{Dimensions, PointCloud, Transform};
use image::{GrayImage, ImageFormat, Luma, Rgb, RgbImage};
use rgbd::{Extrinsics, Intrinsics};

use crate::repr::packet::DepthImage;

/// The shortest depth range a picture spreads its shades over, metres: an empty table's
/// depths span only its noise (8 mm from above), which stretched over every shade is
/// colour noise (and a JPEG of 1.5 MB); over 30 cm the floor is one far colour and a
/// parcel 2 cm high stands out from it.
const MIN_RANGE_M: f32 = 0.3;

/// The depth values at the 1st and 99th percentile of the valid (non-zero) pixels, so a
/// few flying pixels do not flatten the picture, widened towards the camera to at least
/// [`MIN_RANGE_M`]; `None` without valid pixels.
fn depth_range(values: &[u16], depth_scale: f32) -> Option<(u16, u16)> {
    let mut valid: Vec<u16> = values.iter().copied().filter(|v| *v != 0).collect();
    if valid.is_empty() {
        return None;
    }
    let last = valid.len() - 1;
    let (lo_at, hi_at) = (last / 100, last - last / 100);
    let (_, lo, _) = valid.select_nth_unstable(lo_at);
    let lo = *lo;
    let (_, hi, _) = valid.select_nth_unstable(hi_at);
    let hi = (*hi).max(lo + 1);
    let min_units = (MIN_RANGE_M / depth_scale.max(f32::EPSILON))
        .round()
        .min(65535.0) as u16;
    Some((lo.min(hi.saturating_sub(min_units)), hi))
}

/// 0 at `lo` (near) to 1 at `hi` (far), clamped.
fn normalized(v: u16, lo: u16, hi: u16) -> f32 {
    ((f32::from(v) - f32::from(lo)) / f32::from(hi - lo)).clamp(0.0, 1.0)
}

/// Depth as 8-bit grayscale (near bright, far dark) and colour-mapped (near blue, far red,
/// as librealsense's "Jet" colorizer) over one depth range; pixels without depth black.
pub fn depth_views(depth: &DepthImage) -> (GrayImage, RgbImage) {
    let range = depth_range(&depth.values, depth.depth_scale);
    // 0 (near) to 1 (far) at a pixel with depth.
    let at = |x: u32, y: u32| {
        let v = depth.values[(y * depth.width + x) as usize];
        match range {
            Some((lo, hi)) if v != 0 => Some(normalized(v, lo, hi)),
            _ => None,
        }
    };
    let shade = |t: f32| (255.0 - 215.0 * t) as u8;
    let mut gray = GrayImage::from_fn(depth.width, depth.height, |x, y| {
        Luma([at(x, y).map_or(0, shade)])
    });
    let mut colored = RgbImage::from_fn(depth.width, depth.height, |x, y| {
        Rgb(at(x, y).map_or([0, 0, 0], jet))
    });
    if let Some((lo, hi)) = range {
        let mm = |v: u16| f64::from(v) * f64::from(depth.depth_scale) * 1e3;
        let scale = text_scale(&colored);
        gray_key(&mut gray, [mm(lo), mm(hi)], scale, shade);
        let bar = ColourBar {
            title: "depth",
            lo: format!("{:.0} mm near", mm(lo)),
            hi: format!("{:.0} mm far", mm(hi)),
        };
        let size = bar.size(scale);
        if colored.width() > size.0 && colored.height() > size.1 {
            let at = (colored.width() - size.0, colored.height() - size.1);
            bar.draw(&mut colored, at, scale);
        }
    }
    (gray, colored)
}

/// The key of the grayscale depth picture in its bottom-right corner: the gray ramp from
/// near (bright) to far (dark) with the depths at its ends, and that black is no depth.
/// Drawn in colour, then turned gray.
fn gray_key(gray: &mut GrayImage, mm: [f64; 2], scale: u32, shade: impl Fn(f32) -> u8) {
    const STEPS: u32 = 128;
    let near = format!("depth {:.0} mm near", mm[0]);
    let far = format!("{:.0} mm far; black: no depth", mm[1]);
    let width = text_width(&near, scale) + STEPS * scale + text_width(&far, scale) + 8 * scale;
    let height = line_height(scale) + 2 * scale;
    if gray.width() <= width || gray.height() <= height {
        return;
    }
    let mut key = RgbImage::new(width, height);
    let (mut x, y) = (2 * scale, 2 * scale);
    draw_text(&mut key, (x, y), &near, scale, WHITE);
    x += text_width(&near, scale) + 2 * scale;
    for i in 0..STEPS {
        let v = shade(i as f32 / (STEPS - 1) as f32);
        fill(
            &mut key,
            (x + i * scale, y),
            (scale, GLYPH_PX * scale),
            Rgb([v; 3]),
        );
    }
    x += STEPS * scale + 2 * scale;
    draw_text(&mut key, (x, y), &far, scale, WHITE);
    let at = (gray.width() - width, gray.height() - height);
    image::imageops::replace(
        gray,
        &image::imageops::grayscale(&key),
        i64::from(at.0),
        i64::from(at.1),
    );
}

/// The jet colour map: blue, cyan, green, yellow, red for `t` from 0 to 1.
pub fn jet(t: f32) -> [u8; 3] {
    let c = |offset: f32| ((1.5 - (4.0 * t - offset).abs()).clamp(0.0, 1.0) * 255.0) as u8;
    [c(3.0), c(2.0), c(1.0)]
}

/// Longest side of a top view's plot, pixels.
const TOP_VIEW_MAX_PX: f32 = 1024.0;

/// The cloud seen from above (x right, y up), one pixel per millimetre or coarser so the
/// longer side fits in 1024 pixels, each pixel coloured by the highest point in it (blue
/// low, red high), empty pixels black; the world axes where the origin is in view, and
/// with a measurement its footprint outlined in white. Below the plot: a millimetre scale bar, the
/// colour bar of heights and the dimensions.
pub fn top_view(cloud: &PointCloud, measured: Option<&Dimensions>) -> RgbImage {
    plot(cloud, measured, Looking::Down)
}

/// The cloud seen from the side, looking along +y: x right, z up, each pixel coloured by
/// the nearest point in it (blue far, red near), drawn like [`top_view`].
pub fn side_view(cloud: &PointCloud) -> RgbImage {
    let turned = PointCloud {
        points: cloud
            .points
            .iter()
            .map(|p| geometry::Point3::new(p.x, p.z, -p.y))
            .collect(),
    };
    plot(&turned, None, Looking::Side)
}

/// Where a plot looks from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Looking {
    /// From above: the plot's axes are x and y, the colour is z.
    Down,
    /// From -y: the plot's axes are x and z, the colour is -y.
    Side,
}

impl Looking {
    fn axes(self) -> [&'static str; 2] {
        match self {
            Self::Down => ["x", "y"],
            Self::Side => ["x", "z"],
        }
    }
}

fn plot(cloud: &PointCloud, measured: Option<&Dimensions>, looking: Looking) -> RgbImage {
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
    let plot = RgbImage::from_fn(w, h, |x, y| {
        let z = top[(y * w + x) as usize];
        if z == f32::MIN {
            Rgb([0, 0, 0])
        } else {
            Rgb(jet((z - lo[2]) / z_span))
        }
    });
    // World metres to plot pixels.
    let to_px = |x: f64, y: f64| {
        [
            ((x - f64::from(lo[0])) / f64::from(metres_per_px)) as f32,
            (f64::from(h - 1) - (y - f64::from(lo[1])) / f64::from(metres_per_px)) as f32,
        ]
    };
    let scale = text_scale(&plot).max(if w < 400 { 1 } else { 2 });
    let key = TopKey {
        looking,
        mm_per_px: f64::from(metres_per_px) * 1e3,
        heights_mm: [f64::from(lo[2]) * 1e3, f64::from(hi[2]) * 1e3],
        measured,
    };
    // A gap of a line between the plot and its key, so points on the plot's lowest row
    // (a floor seen from the side) and the axes' names stay clear of the caption.
    let gap = line_height(scale);
    let mut image = RgbImage::new(w.max(key.width(scale)), h + gap + key.height(scale));
    image::imageops::replace(&mut image, &plot, 0, 0);
    if let Some(d) = measured {
        let corner = |i: usize| to_px(d.corners_m[i][0], d.corners_m[i][1]);
        for i in 0..4 {
            draw_line(&mut image, corner(i), corner((i + 1) % 4), WHITE, scale);
        }
    }
    let origin = to_px(0.0, 0.0);
    if (0.0..w as f32).contains(&origin[0]) && (0.0..h as f32).contains(&origin[1]) {
        draw_axes(
            &mut image,
            origin,
            60.0 * scale as f32,
            scale,
            looking.axes(),
        );
    }
    key.draw(&mut image, (0, h + gap), scale);
    image
}

/// What is drawn under a top view's plot.
struct TopKey<'a> {
    looking: Looking,
    mm_per_px: f64,
    heights_mm: [f64; 2],
    measured: Option<&'a Dimensions>,
}

impl TopKey<'_> {
    /// The round length of the scale bar: at most a quarter of 1024 plot pixels.
    fn bar_mm(&self) -> f64 {
        [10.0, 20.0, 50.0, 100.0, 200.0, 500.0, 1000.0, 2000.0]
            .into_iter()
            .rev()
            .find(|mm| mm / self.mm_per_px <= 256.0)
            .unwrap_or(10.0)
    }

    fn lines(&self) -> Vec<String> {
        let view = match self.looking {
            Looking::Down => "top view",
            Looking::Side => "side view (looking along +y)",
        };
        let mut lines = vec![format!("{view}, scale bar {:.0} mm", self.bar_mm())];
        if let Some(d) = self.measured {
            lines.push(format!(
                "white: footprint {:.0} x {:.0} mm, height {:.0} mm",
                d.length_mm, d.width_mm, d.height_mm
            ));
        }
        lines
    }

    fn width(&self, scale: u32) -> u32 {
        let text = self.lines().iter().map(|l| text_width(l, scale)).max();
        text.unwrap_or(0).max(self.bar().size(scale).0) + 4 * scale
    }

    fn height(&self, scale: u32) -> u32 {
        (2 + self.lines().len() as u32) * line_height(scale) + self.bar().size(scale).1 + 4 * scale
    }

    fn bar(&self) -> ColourBar {
        ColourBar {
            title: match self.looking {
                Looking::Down => "height",
                Looking::Side => "-y",
            },
            lo: format!("{:.0} mm", self.heights_mm[0]),
            hi: format!("{:.0} mm", self.heights_mm[1]),
        }
    }

    fn draw(&self, image: &mut RgbImage, at: (u32, u32), scale: u32) {
        let (x0, mut y) = (at.0 + 2 * scale, at.1 + 2 * scale);
        for line in self.lines() {
            draw_text(image, (x0, y), &line, scale, WHITE);
            y += line_height(scale);
        }
        // The scale bar with end ticks.
        let bar_px = (self.bar_mm() / self.mm_per_px) as f32;
        let ym = (y + line_height(scale) / 2) as f32;
        let (a, b) = ([x0 as f32, ym], [x0 as f32 + bar_px, ym]);
        draw_line(image, a, b, WHITE, scale);
        for x in [a[0], b[0]] {
            let tick = 3.0 * scale as f32;
            draw_line(image, [x, ym - tick], [x, ym + tick], WHITE, scale);
        }
        y += 2 * line_height(scale);
        self.bar().draw(image, (x0, y), scale);
    }
}

/// A horizontal jet colour bar with its title and the values at both ends.
struct ColourBar {
    title: &'static str,
    lo: String,
    hi: String,
}

impl ColourBar {
    /// Pixels of the gradient.
    const STEPS: u32 = 128;

    fn text(&self) -> String {
        format!("{} {}", self.title, self.lo)
    }

    fn size(&self, scale: u32) -> (u32, u32) {
        let width = text_width(&self.text(), scale)
            + Self::STEPS * scale
            + text_width(&self.hi, scale)
            + 8 * scale;
        (width, line_height(scale) + 2 * scale)
    }

    fn draw(&self, image: &mut RgbImage, at: (u32, u32), scale: u32) {
        let size = self.size(scale);
        fill(image, at, size, BLACK);
        let (mut x, y) = (at.0 + 2 * scale, at.1 + 2 * scale);
        draw_text(image, (x, y), &self.text(), scale, WHITE);
        x += text_width(&self.text(), scale) + 2 * scale;
        for i in 0..Self::STEPS {
            let colour = Rgb(jet(i as f32 / (Self::STEPS - 1) as f32));
            fill(image, (x + i * scale, y), (scale, GLYPH_PX * scale), colour);
        }
        x += Self::STEPS * scale + 2 * scale;
        draw_text(image, (x, y), &self.hi, scale, WHITE);
    }
}

/// The world's x axis (right) and y axis (up) from `origin`, `len` pixels, in magenta,
/// a colour the height scale does not use.
fn draw_axes(image: &mut RgbImage, origin: [f32; 2], len: f32, scale: u32, names: [&str; 2]) {
    let [ox, oy] = origin;
    for (tip, colour, name, above) in [
        ([ox + len, oy], MAGENTA, names[0], true),
        ([ox, oy - len], MAGENTA, names[1], false),
    ] {
        draw_line(image, origin, tip, colour, scale);
        // The x axis's name above its line, so it stays inside the plot.
        let lift = if above { line_height(scale) } else { 0 };
        let at = (
            tip[0].max(0.0) as u32 + 2 * scale,
            (tip[1].max(0.0) as u32).saturating_sub(lift),
        );
        draw_text(image, at, name, scale, colour);
    }
}

/// A camera's calibration through which world points cannot be drawn on its color frames.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum ProjectError {
    /// The camera's 3d-transformation has no inverse.
    #[error("the 3d-transformation cannot be inverted")]
    NotInvertible,
    /// The color stream is distorted (the model's name).
    #[error("the color stream's {0} distortion cannot be drawn through")]
    Distorted(&'static str),
}

/// The pixel at which a world point (the 3d-transformation's output frame) is seen by a
/// color camera with `intrinsics`, `depth_to_color` from its depth camera, whose
/// 3d-transformation is `depth_to_world`; `None` behind the camera. Fails for a
/// transformation that cannot be inverted and for distorted color streams.
pub fn projector(
    intrinsics: Intrinsics,
    depth_to_color: Extrinsics,
    depth_to_world: &Transform,
) -> Result<impl Fn([f64; 3]) -> Option<[f32; 2]> + use<>, ProjectError> {
    let inverse = depth_to_world
        .linear
        .try_inverse()
        .ok_or(ProjectError::NotInvertible)?;
    let translation = depth_to_world.translation;
    if !intrinsics.is_pinhole() {
        return Err(ProjectError::Distorted(intrinsics.model.name()));
    }
    Ok(move |[x, y, z]: [f64; 3]| {
        let world = nalgebra::Vector3::new(x as f32, y as f32, z as f32);
        let depth = inverse * (world - translation);
        let c = depth_to_color.transform([depth.x, depth.y, depth.z]);
        (c[2] > 1e-3).then(|| intrinsics.project(c).ok()).flatten()
    })
}

/// Draws `dims` onto `image`, a color frame of a camera with `intrinsics` and
/// `depth_to_color`, whose 3d-transformation is `depth_to_world` ([`annotate`] through
/// [`projector`]).
pub fn annotate_frame(
    image: &mut RgbImage,
    dims: &Dimensions,
    caption: &str,
    codes: Option<&[String]>,
    intrinsics: Intrinsics,
    depth_to_color: Extrinsics,
    depth_to_world: &Transform,
) -> Result<(), ProjectError> {
    // The camera in the world: where its depth frame's origin goes.
    let camera = depth_to_world.translation.map(f64::from);
    let project = projector(intrinsics, depth_to_color, depth_to_world)?;
    annotate(
        image,
        dims,
        caption,
        codes,
        [camera.x, camera.y, camera.z],
        project,
    );
    Ok(())
}

/// Draws the measured box onto `image` through `project` (world point in metres ->
/// pixel), seen from `camera` (the camera's position in the world): the footprint on the
/// floor red, the lid green, the vertical edges yellow; an edge the box hides from the
/// camera (no face it borders faces the camera) dashed. A legend in the top-left corner
/// says so, with `caption` (the dimensions, as `report::box_caption` writes them) and, when they were read (`codes`, each
/// as `qr "PKG-0001"`), the codes found ("none" when none was).
pub fn annotate(
    image: &mut RgbImage,
    dims: &Dimensions,
    caption: &str,
    codes: Option<&[String]>,
    camera: [f64; 3],
    project: impl Fn([f64; 3]) -> Option<[f32; 2]>,
) {
    let h = dims.height_mm / 1e3;
    let c = &dims.corners_m;
    let centre = [0, 1].map(|k| c.iter().map(|p| p[k]).sum::<f64>() / 4.0);
    // Whether the face through `point` with outward normal `normal` faces the camera.
    let faces = |point: [f64; 3], normal: [f64; 3]| {
        (0..3)
            .map(|k| (camera[k] - point[k]) * normal[k])
            .sum::<f64>()
            > 0.0
    };
    let top = faces([c[0][0], c[0][1], h], [0.0, 0.0, 1.0]);
    let bottom = faces([c[0][0], c[0][1], 0.0], [0.0, 0.0, -1.0]);
    // Side i runs from corner i to corner i + 1; its normal points away from the centre.
    let side: Vec<bool> = (0..4)
        .map(|i| {
            let (a, b) = (c[i], c[(i + 1) % 4]);
            let mut n = [b[1] - a[1], a[0] - b[0], 0.0];
            let mid = [(a[0] + b[0]) / 2.0, (a[1] + b[1]) / 2.0];
            if (mid[0] - centre[0]) * n[0] + (mid[1] - centre[1]) * n[1] < 0.0 {
                n = [-n[0], -n[1], 0.0];
            }
            faces([mid[0], mid[1], h / 2.0], n)
        })
        .collect();
    let thickness = (image.width() / 400).max(2);
    let corner = |i: usize, z: f64| project([c[i][0], c[i][1], z]);
    // (from, to, colour, visible): hidden edges first, so visible ones are drawn over them.
    let mut edges = Vec::new();
    for i in 0..4 {
        let j = (i + 1) % 4;
        edges.push((corner(i, 0.0), corner(j, 0.0), RED, bottom || side[i]));
        edges.push((corner(i, h), corner(j, h), GREEN, top || side[i]));
        edges.push((
            corner(i, 0.0),
            corner(i, h),
            YELLOW,
            side[i] || side[(i + 3) % 4],
        ));
    }
    edges.sort_by_key(|e| e.3);
    for (a, b, colour, visible) in edges {
        if let (Some(a), Some(b)) = (a, b) {
            if visible {
                draw_line(image, a, b, colour, thickness);
            } else {
                draw_dashed(image, a, b, colour, thickness);
            }
        }
    }
    let mut lines = vec![(caption.to_owned(), WHITE)];
    lines.extend(codes_line(codes));
    lines.extend([
        ("red: footprint on the floor".to_owned(), RED),
        ("green: lid".to_owned(), GREEN),
        ("yellow: vertical edges".to_owned(), YELLOW),
        ("dashed: edges hidden behind the box".to_owned(), WHITE),
    ]);
    legend(image, (0, 0), &lines, text_scale(image));
}

/// Draws onto `image` (a color frame, as [`annotate_frame`]) the parcel the measurement
/// refused: its footprint on the floor (`corners_m`, when the measurement has it) in
/// magenta, and a legend that says it was refused and why, with the codes read.
pub fn annotate_refused_frame(
    image: &mut RgbImage,
    corners_m: Option<&[[f64; 2]; 4]>,
    reason: &str,
    codes: Option<&[String]>,
    intrinsics: Intrinsics,
    depth_to_color: Extrinsics,
    depth_to_world: &Transform,
) -> Result<(), ProjectError> {
    let project = projector(intrinsics, depth_to_color, depth_to_world)?;
    annotate_refused(image, corners_m, reason, codes, project);
    Ok(())
}

/// [`annotate_refused_frame`] through `project` (world point in metres -> pixel).
pub fn annotate_refused(
    image: &mut RgbImage,
    corners_m: Option<&[[f64; 2]; 4]>,
    reason: &str,
    codes: Option<&[String]>,
    project: impl Fn([f64; 3]) -> Option<[f32; 2]>,
) {
    let thickness = (image.width() / 400).max(2);
    if let Some(c) = corners_m {
        for i in 0..4 {
            let j = (i + 1) % 4;
            let (a, b) = (
                project([c[i][0], c[i][1], 0.0]),
                project([c[j][0], c[j][1], 0.0]),
            );
            if let (Some(a), Some(b)) = (a, b) {
                draw_line(image, a, b, MAGENTA, thickness);
            }
        }
    }
    let scale = text_scale(image);
    // The reason in lines that fit the image's width.
    let room = (image.width() * 9 / 10).max(1);
    let mut lines: Vec<(String, Rgb<u8>)> = vec![("refused: no dimensions".to_owned(), WHITE)];
    let mut line = String::new();
    for word in reason.split_whitespace() {
        let longer = if line.is_empty() {
            word.to_owned()
        } else {
            format!("{line} {word}")
        };
        if !line.is_empty() && text_width(&longer, scale) > room {
            lines.push((std::mem::replace(&mut line, word.to_owned()), WHITE));
        } else {
            line = longer;
        }
    }
    if !line.is_empty() {
        lines.push((line, WHITE));
    }
    lines.extend(codes_line(codes));
    let footprint = if corners_m.is_some() {
        "magenta: footprint of the refused parcel"
    } else {
        "no footprint to draw"
    };
    lines.push((footprint.to_owned(), MAGENTA));
    legend(image, (0, 0), &lines, scale);
}

/// The legend's line of the codes read, when they were looked for (`Some`).
fn codes_line(codes: Option<&[String]>) -> Option<(String, Rgb<u8>)> {
    let read = match codes? {
        [] => "none read".to_owned(),
        codes => codes.join(", "),
    };
    Some((format!("codes: {read}"), WHITE))
}

/// Lines of text, each in its colour, on a black box at `at`.
pub fn legend(image: &mut RgbImage, at: (u32, u32), lines: &[(String, Rgb<u8>)], scale: u32) {
    let width = lines
        .iter()
        .map(|(l, _)| text_width(l, scale))
        .max()
        .unwrap_or(0);
    let height = line_height(scale) * lines.len() as u32;
    fill(image, at, (width + 4 * scale, height + 2 * scale), BLACK);
    for (i, (line, colour)) in lines.iter().enumerate() {
        let y = at.1 + 2 * scale + i as u32 * line_height(scale);
        draw_text(image, (at.0 + 2 * scale, y), line, scale, *colour);
    }
}

const WHITE: Rgb<u8> = Rgb([255, 255, 255]);
const BLACK: Rgb<u8> = Rgb([0, 0, 0]);
const RED: Rgb<u8> = Rgb([255, 64, 64]);
const GREEN: Rgb<u8> = Rgb([64, 255, 64]);
const YELLOW: Rgb<u8> = Rgb([255, 220, 0]);
const MAGENTA: Rgb<u8> = Rgb([255, 0, 255]);

fn fill(image: &mut RgbImage, at: (u32, u32), size: (u32, u32), color: Rgb<u8>) {
    for y in at.1..(at.1 + size.1).min(image.height()) {
        for x in at.0..(at.0 + size.0).min(image.width()) {
            image.put_pixel(x, y, color);
        }
    }
}

/// A line `thickness` pixels wide; the parts outside the image are skipped.
pub fn draw_line(image: &mut RgbImage, a: [f32; 2], b: [f32; 2], color: Rgb<u8>, thickness: u32) {
    draw_pattern(image, a, b, color, thickness, |_| true);
}

/// A dashed line: dashes and gaps of four times its thickness.
fn draw_dashed(image: &mut RgbImage, a: [f32; 2], b: [f32; 2], color: Rgb<u8>, thickness: u32) {
    let period = 8 * thickness.max(1);
    draw_pattern(image, a, b, color, thickness, |step| {
        step % period < period / 2
    });
}

/// The pixels of the line from `a` to `b` whose step along it `on` keeps.
fn draw_pattern(
    image: &mut RgbImage,
    a: [f32; 2],
    b: [f32; 2],
    color: Rgb<u8>,
    thickness: u32,
    on: impl Fn(u32) -> bool,
) {
    let (dx, dy) = (b[0] - a[0], b[1] - a[1]);
    let steps = dx.abs().max(dy.abs()).ceil().min(1e5) as u32;
    let half = thickness as i64 / 2;
    for s in (0..=steps).filter(|s| on(*s)) {
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

/// `dir/name-suffix.png` for `dir/name.png`.
pub fn sibling(path: &Path, suffix: &str) -> PathBuf {
    let stem = path.file_stem().and_then(|s| s.to_str()).unwrap_or("view");
    path.with_file_name(format!("{stem}{suffix}.png"))
}

/// Saves a picture as PNG (quietly: callers say what they wrote where their output goes).
pub fn save<P, C>(image: &image::ImageBuffer<P, C>, path: &Path) -> Result<(), SaveError>
where
    P: image::PixelWithColorType,
    [P::Subpixel]: image::EncodableLayout,
    C: std::ops::Deref<Target = [P::Subpixel]>,
{
    image
        .save_with_format(path, ImageFormat::Png)
        .map_err(|source| SaveError {
            path: path.to_owned(),
            source,
        })
}

/// A picture could not be written.
#[derive(Debug, thiserror::Error)]
#[error("writing {}", path.display())]
pub struct SaveError {
    /// Where it was to go.
    pub path: PathBuf,
    /// The encoder's or the file system's error.
    pub source: image::ImageError,
}

/// Side of a glyph of the 8x8 font, in font pixels.
const GLYPH_PX: u32 = 8;

/// Font pixels per glyph pixel for text on `image`: larger on larger images.
/// The text size for a picture of this size (1 up to 960 pixels wide, then larger).
pub fn text_scale(image: &RgbImage) -> u32 {
    (image.width() / 640).max(1)
}

/// Height of a line of text, glyph and spacing.
fn line_height(scale: u32) -> u32 {
    (GLYPH_PX + 3) * scale
}

/// Width of `text` drawn at `scale`.
pub fn text_width(text: &str, scale: u32) -> u32 {
    text.chars().count() as u32 * GLYPH_PX * scale
}

/// Text in the public-domain 8x8 font of `font8x8`, each font pixel `scale` x `scale`
/// image pixels; characters it lacks are left blank.
pub fn draw_text(image: &mut RgbImage, at: (u32, u32), text: &str, scale: u32, color: Rgb<u8>) {
    use font8x8::UnicodeFonts as _;
    for (i, c) in text.chars().enumerate() {
        let x0 = at.0 + i as u32 * GLYPH_PX * scale;
        let rows = font8x8::BASIC_FONTS.get(c).unwrap_or_default();
        for (row, bits) in rows.iter().enumerate() {
            for col in 0..GLYPH_PX {
                // Bit 0 is the leftmost pixel.
                if bits & (1 << col) != 0 {
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
    fn an_empty_tables_floor_is_one_far_colour_and_a_parcel_stands_out() {
        // A floor 1.5 m away, its depth noise 8 mm from end to end (issue 51: stretched
        // over every colour, the page showed colour noise for an empty table).
        let floor: Vec<u16> = (0..400u32)
            .map(|i| 1496 + ((i * 7919) % 9) as u16)
            .collect();
        let (gray, colored) = depth_views(&depth(floor.clone(), 20));
        let far = jet(1.0);
        for p in colored.pixels().take(20 * 10) {
            let off = (0..3).map(|k| p.0[k].abs_diff(far[k])).max().unwrap();
            assert!(off <= 40, "{:?} is not the far end's {far:?}", p.0);
        }
        let shades: std::collections::BTreeSet<u8> =
            gray.pixels().take(200).map(|p| p.0[0]).collect();
        assert!(shades.len() <= 8, "{} shades of floor noise", shades.len());
        // A parcel 20 mm high on it is told apart.
        let mut with_parcel = floor;
        with_parcel[..40].fill(1480);
        let (_, colored) = depth_views(&depth(with_parcel, 20));
        let (parcel, table) = (colored.get_pixel(0, 0).0, colored.get_pixel(0, 10).0);
        let diff = (0..3).map(|k| parcel[k].abs_diff(table[k])).max().unwrap();
        assert!(
            diff >= 20,
            "parcel {parcel:?} and floor {table:?} look alike"
        );
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
            geometry::Point3::new(0.1, 0.05, 0.0),
            geometry::Point3::new(0.05, 0.02, 0.0),
            geometry::Point3::new(0.05, 0.02, 0.2),
        ]
        .into();
        let img = top_view(&cloud, None);
        // The plot (101 x 51 pixels, one per millimetre) is at the top left.
        // The 0.2 m point hides the floor point under it, near (50, 30).
        assert_eq!(count(&img, 48..53, 28..33, Rgb(jet(1.0))), 1);
        assert_eq!(count(&img, 48..53, 28..33, Rgb(jet(0.0))), 0);
        assert_eq!(img.get_pixel(100, 0).0, jet(0.0));
        assert_eq!(img.get_pixel(25, 10).0, [0, 0, 0]);
        assert!(img.height() > 51);
    }

    fn measured_box() -> Dimensions {
        Dimensions {
            length_mm: 400.0,
            width_mm: 300.0,
            height_mm: 200.0,
            yaw_deg: 0.0,
            corners_m: [[-0.2, -0.15], [0.2, -0.15], [0.2, 0.15], [-0.2, 0.15]],
            volume_l: 24.0,
            points: 1000,
        }
    }

    /// Pixels of `colour` in a rectangle.
    fn count(
        img: &RgbImage,
        x: std::ops::Range<u32>,
        y: std::ops::Range<u32>,
        colour: Rgb<u8>,
    ) -> usize {
        y.flat_map(|y| x.clone().map(move |x| (x, y)))
            .filter(|&(x, y)| img.get_pixel(x, y) == &colour)
            .count()
    }

    #[test]
    fn the_top_view_has_a_scale_bar_a_colour_bar_and_the_footprint() {
        // A floor 0.8 m square at z = 0 and the box's lid at 0.2 m.
        let mut points = Vec::new();
        for i in 0..=80 {
            for j in 0..=80 {
                let (x, y) = (-0.4 + i as f32 * 0.01, -0.4 + j as f32 * 0.01);
                let z = if x.abs() < 0.2 && y.abs() < 0.15 {
                    0.2
                } else {
                    0.0
                };
                points.push(geometry::Point3::new(x, y, z));
            }
        }
        let cloud: PointCloud = points.into();
        let img = top_view(&cloud, Some(&measured_box()));
        // 801 x 801 plot pixels; the footprint's edge at x = -0.2 m is white.
        assert_eq!(img.get_pixel(200, 400), &WHITE);
        // Under the plot: the text, the scale bar and the colour bar's gradient.
        let below = 801..img.height();
        assert!(count(&img, 0..img.width(), below.clone(), WHITE) > 500);
        assert!(count(&img, 0..img.width(), below.clone(), Rgb(jet(0.0))) > 0);
        assert!(count(&img, 0..img.width(), below, Rgb(jet(1.0))) > 0);
        // The axes at the origin (the plot's centre): x to the right.
        assert_eq!(img.get_pixel(430, 400), &MAGENTA);
    }

    #[test]
    fn the_depth_colours_come_with_their_colour_bar() {
        let values: Vec<u16> = (0..640 * 480).map(|i| 800 + (i % 640) as u16).collect();
        let (_, c) = depth_views(&depth(values, 640));
        let bottom = 440..480;
        // Near and far ends of the bar, and its labels, in the bottom-right corner.
        assert!(count(&c, 300..640, bottom.clone(), WHITE) > 50);
        assert!(count(&c, 300..640, bottom, BLACK) > 100);
    }

    #[test]
    fn the_gray_depth_view_has_its_key() {
        let values: Vec<u16> = (0..640 * 480).map(|i| 800 + (i % 640) as u16).collect();
        let (g, _) = depth_views(&depth(values, 640));
        let key: Vec<u8> = (440..480)
            .flat_map(|y| (200..640).map(move |x| (x, y)))
            .map(|(x, y)| g.get_pixel(x, y).0[0])
            .collect();
        // White text on black, and the ramp's shades between them.
        assert!(key.iter().filter(|v| **v == 255).count() > 50);
        assert!(key.iter().filter(|v| **v == 0).count() > 100);
        assert!(key.iter().any(|v| (41..250).contains(v)));
    }

    #[test]
    fn the_side_view_keeps_its_caption_clear_of_the_floor() {
        // A floor 1 m wide at z = 0 (its points on the plot's lowest row) and a box.
        let mut points = Vec::new();
        for i in 0..=100 {
            let x = -0.5 + i as f32 * 0.01;
            points.push(geometry::Point3::new(x, 0.0, 0.0));
            if x.abs() < 0.2 {
                points.push(geometry::Point3::new(x, 0.0, 0.2));
            }
        }
        let img = side_view(&points.into());
        // The plot is 1001 x 201 pixels; a line's height below it holds no caption.
        let gap = 201..201 + line_height(text_scale(&img).max(2));
        assert_eq!(count(&img, 0..img.width(), gap.clone(), WHITE), 0);
        assert!(count(&img, 0..img.width(), gap.end..img.height(), WHITE) > 100);
    }

    #[test]
    fn the_annotated_legend_names_the_codes_read() {
        let legend_pixels = |codes: Option<&[String]>| {
            let mut img = RgbImage::new(640, 480);
            annotate(
                &mut img,
                &measured_box(),
                "measured box 400 x 300 x 200 mm, yaw 0.0 deg",
                codes,
                [0.0, 0.0, 1.0],
                from_above(1.0),
            );
            count(&img, 0..640, 0..120, WHITE)
        };
        let without = legend_pixels(None);
        let read = ["qr \"PKG-0001\"".to_owned()];
        assert!(legend_pixels(Some(&read)) > without + 100);
        assert!(legend_pixels(Some(&[])) > without + 50, "codes: none read");
    }

    /// A camera `height` m above the origin looking down, 500 px focal length.
    fn from_above(height: f64) -> impl Fn([f64; 3]) -> Option<[f32; 2]> {
        move |[x, y, z]: [f64; 3]| {
            let d = height - z;
            Some([
                (320.0 + 500.0 * x / d) as f32,
                (240.0 - 500.0 * y / d) as f32,
            ])
        }
    }

    #[test]
    fn the_box_its_legend_and_its_numbers_are_drawn() {
        let mut img = RgbImage::new(640, 480);
        annotate(
            &mut img,
            &measured_box(),
            "measured box 400 x 300 x 200 mm, yaw 0.0 deg",
            None,
            [0.0, 0.0, 1.0],
            from_above(1.0),
        );
        // Lid edge at x = -0.2 m, 0.8 m away -> u = 195, drawn solid.
        assert_eq!(img.get_pixel(195, 240).0, GREEN.0);
        assert_eq!(img.get_pixel(320, 240).0, [0, 0, 0]);
        let text_pixels = count(&img, 0..400, 0..60, WHITE);
        assert!(text_pixels > 300, "{text_pixels}");
        assert!(
            count(&img, 0..400, 0..60, RED) > 20,
            "the legend's red line"
        );
    }

    #[test]
    fn edges_the_box_hides_are_dashed_and_the_others_solid() {
        let mut img = RgbImage::new(640, 480);
        // Straight above: the sides face away, so the footprint on the floor and the
        // vertical edges are hidden under the lid.
        annotate(
            &mut img,
            &measured_box(),
            "measured box 400 x 300 x 200 mm, yaw 0.0 deg",
            None,
            [0.0, 0.0, 1.0],
            from_above(1.0),
        );
        // The floor edge at x = -0.2 m -> u = 220, from v = 165 to 315.
        let floor: Vec<bool> = (170..310).map(|v| img.get_pixel(220, v) == &RED).collect();
        let drawn = floor.iter().filter(|d| **d).count();
        assert!(
            drawn > 20 && drawn < floor.len() - 20,
            "dashed: {drawn} of {}",
            floor.len()
        );
        // The lid edge at u = 195 is solid from v = 146 to 334.
        assert!((150..330).all(|v| img.get_pixel(195, v) == &GREEN));
        // Seen from the side (x = 2 m, 0.5 m up), the side facing the camera is visible:
        // its floor edge at x = +0.2 m is drawn solid.
        let mut side = RgbImage::new(640, 480);
        let from_side = |[x, y, z]: [f64; 3]| {
            let d = 2.0 - x;
            Some([
                (320.0 + 500.0 * y / d) as f32,
                (240.0 - 500.0 * (z - 0.5) / d) as f32,
            ])
        };
        annotate(
            &mut side,
            &measured_box(),
            "measured box 400 x 300 x 200 mm, yaw 0.0 deg",
            None,
            [2.0, 0.0, 0.5],
            from_side,
        );
        // Floor edge x = 0.2, z = 0: v = 240 + 500 * 0.5 / 1.8 = 378.9.
        assert!(
            (285..355).all(|u| side.get_pixel(u, 379) == &RED || side.get_pixel(u, 378) == &RED)
        );
    }
}
