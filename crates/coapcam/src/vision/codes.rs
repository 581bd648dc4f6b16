//! Reading the codes printed on a parcel from an image, a pure function of the pixels.
//! The station reads with rxing (the Rust port of ZXing), over the whole image and over
//! each printed region turned upright, and with our Code 128 reader (along scan lines at
//! several angles; a read counts only with its start and stop patterns and a matching
//! check symbol) over each printed region. Our QR reader (`rqrr`) and our Code 128 reader
//! over the whole image stay for `coapcam bench codes` to compare.

use std::collections::BTreeSet;
use std::fmt;

use image::GrayImage;

/// The symbology of a code.
#[derive(
    Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, serde::Serialize, serde::Deserialize,
)]
#[serde(rename_all = "lowercase")]
pub enum CodeKind {
    /// QR code (ISO/IEC 18004).
    Qr,
    /// Code 128 (ISO/IEC 15417).
    Code128,
    /// Data Matrix ECC 200 (ISO/IEC 16022).
    #[serde(rename = "datamatrix")]
    DataMatrix,
    /// EAN-13 (ISO/IEC 15420): 13 digits with the check digit.
    Ean13,
    /// UPC-A (ISO/IEC 15420): 12 digits with the check digit.
    Upca,
    /// PDF417 (ISO/IEC 15438).
    Pdf417,
}

impl CodeKind {
    /// The name the scene files and the JSON output use.
    pub fn name(self) -> &'static str {
        match self {
            Self::Qr => "qr",
            Self::Code128 => "code128",
            Self::DataMatrix => "datamatrix",
            Self::Ean13 => "ean13",
            Self::Upca => "upca",
            Self::Pdf417 => "pdf417",
        }
    }

    /// The reader's limit for this symbology: the narrowest module, in pixels of the
    /// image, from which it reads at 1 px of lens blur and sensor noise of 3 levels
    /// (`coapcam bench codes --labels 50 --module-px 3,4 --seed 11`, and `--seed 12`: 100
    /// labels a cell, 2026-12-02): QR, Code 128 and PDF417 100 of 100 at 3 px; Data Matrix
    /// 97 at 3 px and 100 at 4. EAN-13 and UPC-A read 95 and 96 of 100 at 3 px and 92
    /// and 96 at 4: below 99 % at both, so what they miss is not the module's width
    /// (docs/station.md); their limit stays at 3 px.
    pub fn min_px_per_module(self) -> f64 {
        match self {
            Self::DataMatrix => MIN_PX_PER_MODULE + 1.0,
            _ => MIN_PX_PER_MODULE,
        }
    }
}

impl From<rgbd::scene::LabelKind> for CodeKind {
    /// The symbology of a synthetic scene's label.
    fn from(kind: rgbd::scene::LabelKind) -> Self {
        match kind {
            rgbd::scene::LabelKind::Qr => Self::Qr,
            rgbd::scene::LabelKind::Code128 => Self::Code128,
            rgbd::scene::LabelKind::DataMatrix => Self::DataMatrix,
            rgbd::scene::LabelKind::Ean13 => Self::Ean13,
            rgbd::scene::LabelKind::Upca => Self::Upca,
            rgbd::scene::LabelKind::Pdf417 => Self::Pdf417,
        }
    }
}

/// A code read from an image.
#[derive(
    Debug, Clone, PartialEq, Eq, PartialOrd, Ord, Hash, serde::Serialize, serde::Deserialize,
)]
pub struct Code {
    /// Symbology.
    pub kind: CodeKind,
    /// The decoded text.
    pub text: String,
}

impl Code {
    /// Whether a label of `kind` printing `text` shows this code. The same symbology and
    /// text, or an EAN-13 whose first digit is 0 read as a UPC-A: the two are the same
    /// bars (a UPC-A is an EAN-13 with a leading 0, ISO/IEC 15420), and a reader that
    /// reads both names them UPC-A.
    pub fn shows(&self, kind: CodeKind, text: &str) -> bool {
        (self.kind == kind && self.text == text)
            || (self.kind == CodeKind::Upca
                && kind == CodeKind::Ean13
                && text.strip_prefix('0') == Some(self.text.as_str()))
    }

    /// The texts a label showing this code carries ([`Code::shows`]): its own, and for a
    /// UPC-A also the EAN-13 of the same bars.
    pub fn label_texts(&self) -> Vec<String> {
        let mut texts = vec![self.text.clone()];
        if self.kind == CodeKind::Upca {
            texts.push(format!("0{}", self.text));
        }
        texts
    }
}

impl fmt::Display for Code {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{} {:?}", self.kind.name(), self.text)
    }
}

/// The reader's limit for every symbology but Data Matrix: the
/// narrowest module it reads, in pixels of the image, at 1 px of lens blur and sensor
/// noise (docs/station.md's "Codes"; `coapcam bench codes` measures it). Data Matrix
/// needs a pixel more ([`CodeKind::min_px_per_module`]). The station's
/// start message and its warning speak of Code 128, a logistic label's symbology.
pub const MIN_PX_PER_MODULE: f64 = 3.0;

/// The narrowest module of a GS1 logistic label (a GS1-128 SSCC), millimetres: the
/// station warns at start when its cameras cannot read modules this narrow.
pub const LOGISTIC_MODULE_MM: f64 = 0.495;

/// The narrowest module, millimetres, that the reader reads on a surface `distance_m`
/// from a camera of focal length `fx_px` pixels, looked at square on.
pub fn narrowest_module_mm(fx_px: f64, distance_m: f64) -> f64 {
    MIN_PX_PER_MODULE * distance_m * 1e3 / fx_px
}

/// The farthest distance, metres, from which a camera of focal length `fx_px` pixels
/// reads modules of `module_mm`.
pub fn farthest_m(fx_px: f64, module_mm: f64) -> f64 {
    module_mm * fx_px / (MIN_PX_PER_MODULE * 1e3)
}

/// Every code found in `image`, each once, in order of kind and text ([`Reader::Both`]).
pub fn read(image: &GrayImage) -> Vec<Code> {
    read_with(image, Reader::Both)
}

/// Which reader reads the codes ([`read_with`]; `coapcam bench codes` compares them;
/// the station reads with rxing, [`read`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Reader {
    /// Ours over the whole image: QR through `rqrr`, Code 128 along scan lines.
    Ours,
    /// rxing (the Rust port of ZXing): every symbology of [`CodeKind`], over the whole
    /// image and each printed region turned upright.
    Rxing,
    /// rxing, and our Code 128 reader over each printed region: what the station reads
    /// with ([`read`]). rxing reads every QR that `rqrr` reads (docs/station.md's "Codes");
    /// our Code 128 reader reads narrower modules than rxing (scenes/lane.toml's label at
    /// 1.1 px a module without blur).
    Both,
}

/// The codes `reader` finds in `image`, each once, in order of kind and text.
pub fn read_with(image: &GrayImage, reader: Reader) -> Vec<Code> {
    if image.width() == 0 || image.height() == 0 {
        return Vec::new();
    }
    if reader != Reader::Ours {
        return read_rxing(image, reader == Reader::Both)
            .into_iter()
            .collect();
    }
    let mut found = BTreeSet::new();
    // rqrr's finder search misses some sharp-edged codes it reads once the image is
    // slightly blurred (as a lens blurs): a second look, only when the first found none.
    let mut qr = read_qr_guarded(image);
    if qr.is_empty() {
        qr = read_qr_guarded(&image::imageops::blur(image, QR_SECOND_LOOK_BLUR_PX));
    }
    found.extend(qr);
    read_code128(image, SCAN_SPACING_PX, &mut found);
    found.into_iter().collect()
}

/// The codes rxing finds in `image`: first in the whole image, then in each printed
/// region of it ([`printed_regions`]) turned so that its bars stand upright
/// ([`upright`]), as it is and binarised against its own surroundings ([`binarised`]);
/// with `our_code128`, our Code 128 reader also reads each region (it reads modules
/// narrower than rxing does, and a region costs it a tenth of the whole image).
/// rxing's linear and PDF417 readers scan rows, and a row's threshold comes from the
/// row's histogram: a code turned from the rows, or lying on a gray parcel, escapes them.
fn read_rxing(image: &GrayImage, our_code128: bool) -> BTreeSet<Code> {
    let mut found = rxing_codes(image);
    for (x, y, width, height) in printed_regions(image) {
        let crop = image::imageops::crop_imm(image, x, y, width, height).to_image();
        if our_code128 {
            read_code128(&crop, REGION_SCAN_SPACING_PX, &mut found);
        }
        let turned = upright(&crop);
        let mut here = rxing_codes(&turned);
        if here.is_empty() {
            here = rxing_codes(&binarised(&turned));
        }
        // One label, two EAN-13 or UPC-A texts: one is a misread (their check digit
        // catches one wrong digit, not two), and which is unknown.
        let products = here
            .iter()
            .filter(|c| matches!(c.kind, CodeKind::Ean13 | CodeKind::Upca))
            .count();
        if products > 1 {
            here.retain(|c| !matches!(c.kind, CodeKind::Ean13 | CodeKind::Upca));
        }
        found.extend(here);
    }
    found
}

/// The codes rxing finds in `image` as it is: several at once, trying harder (rxing's
/// helper sets it), only the symbologies of [`CodeKind`].
fn rxing_codes(image: &GrayImage) -> BTreeSet<Code> {
    use rxing::BarcodeFormat as F;
    let mut hints = rxing::DecodeHints {
        PossibleFormats: Some(
            [
                F::QR_CODE,
                F::CODE_128,
                F::DATA_MATRIX,
                F::EAN_13,
                F::UPC_A,
                F::PDF_417,
            ]
            .into_iter()
            .collect(),
        ),
        TryHarder: Some(true),
        ..Default::default()
    };
    let results = rxing::helpers::detect_multiple_in_luma_with_hints(
        image.as_raw().clone(),
        image.width(),
        image.height(),
        &mut hints,
    )
    .unwrap_or_default();
    results
        .into_iter()
        .filter_map(|r| {
            let kind = match r.getBarcodeFormat() {
                F::QR_CODE => CodeKind::Qr,
                F::CODE_128 => CodeKind::Code128,
                F::DATA_MATRIX => CodeKind::DataMatrix,
                F::EAN_13 => CodeKind::Ean13,
                F::UPC_A => CodeKind::Upca,
                F::PDF_417 => CodeKind::Pdf417,
                _ => return None,
            };
            Some(Code {
                kind,
                text: r.getText().to_owned(),
            })
        })
        .collect()
}

/// Side of the square blocks in which [`printed_regions`] looks for print, pixels.
const BLOCK_PX: u32 = 16;
/// Smallest difference between a block's darkest and lightest pixel (0-255) for it to
/// count as printed: a label's black on white differs by far more, a parcel's edge
/// against the floor and sensor noise by less.
const BLOCK_CONTRAST: u8 = 60;
/// Fewest blocks of a printed region worth reading: smaller ones are text or edges.
const MIN_REGION_BLOCKS: usize = 6;
/// Blocks added around a region on each side: the quiet zones inside a label's border.
const REGION_MARGIN_BLOCKS: u32 = 2;

/// The rectangles (x, y, width, height) around each group of touching printed blocks
/// of `image`, a margin added.
fn printed_regions(image: &GrayImage) -> Vec<(u32, u32, u32, u32)> {
    let (width, height) = (image.width(), image.height());
    let (columns, rows) = (width / BLOCK_PX, height / BLOCK_PX);
    let pixels = image.as_raw();
    let mut printed = vec![false; (columns * rows) as usize];
    for by in 0..rows {
        for bx in 0..columns {
            let (mut low, mut high) = (u8::MAX, u8::MIN);
            for y in by * BLOCK_PX..(by + 1) * BLOCK_PX {
                let row = (y * width) as usize;
                let from = row + (bx * BLOCK_PX) as usize;
                for &v in &pixels[from..from + BLOCK_PX as usize] {
                    low = low.min(v);
                    high = high.max(v);
                }
            }
            printed[(by * columns + bx) as usize] = high - low >= BLOCK_CONTRAST;
        }
    }
    let mut seen = vec![false; printed.len()];
    let mut regions = Vec::new();
    for start in 0..printed.len() {
        if !printed[start] || seen[start] {
            continue;
        }
        // The blocks touching this one, diagonals included, and theirs.
        seen[start] = true;
        let mut stack = vec![start];
        let (mut x0, mut y0, mut x1, mut y1, mut blocks) = (u32::MAX, u32::MAX, 0, 0, 0);
        while let Some(i) = stack.pop() {
            let (bx, by) = (i as u32 % columns, i as u32 / columns);
            (x0, y0, x1, y1) = (x0.min(bx), y0.min(by), x1.max(bx), y1.max(by));
            blocks += 1;
            for ny in by.saturating_sub(1)..=(by + 1).min(rows - 1) {
                for nx in bx.saturating_sub(1)..=(bx + 1).min(columns - 1) {
                    let j = (ny * columns + nx) as usize;
                    if printed[j] && !seen[j] {
                        seen[j] = true;
                        stack.push(j);
                    }
                }
            }
        }
        if blocks < MIN_REGION_BLOCKS {
            continue;
        }
        let (left, top) = (
            x0.saturating_sub(REGION_MARGIN_BLOCKS) * BLOCK_PX,
            y0.saturating_sub(REGION_MARGIN_BLOCKS) * BLOCK_PX,
        );
        let right = ((x1 + 1 + REGION_MARGIN_BLOCKS) * BLOCK_PX).min(width);
        let bottom = ((y1 + 1 + REGION_MARGIN_BLOCKS) * BLOCK_PX).min(height);
        regions.push((left, top, right - left, bottom - top));
    }
    regions
}

/// `image` turned about its centre so that its dominant gradient runs along the rows
/// (a bar code's bars stand upright), on a canvas that holds all of it, white outside.
/// The direction is the structure tensor's: the mean of the gradients' doubled angles,
/// weighted by their squared length.
fn upright(image: &GrayImage) -> GrayImage {
    let (w, h) = (image.width() as usize, image.height() as usize);
    if w < 3 || h < 3 {
        return image.clone();
    }
    let pixels = image.as_raw();
    let p = |x: usize, y: usize| f32::from(pixels[y * w + x]);
    let (mut along, mut across) = (0.0f64, 0.0f64);
    for y in 1..h - 1 {
        for x in 1..w - 1 {
            let gx = p(x + 1, y) - p(x - 1, y);
            let gy = p(x, y + 1) - p(x, y - 1);
            along += f64::from(gx * gx - gy * gy);
            across += f64::from(2.0 * gx * gy);
        }
    }
    let angle = 0.5 * across.atan2(along) as f32;
    // Turning the image by -angle: a canvas pixel at d from the centre shows the
    // image's pixel at d turned by +angle.
    let (sin, cos) = angle.sin_cos();
    let (wf, hf) = (w as f32, h as f32);
    let side_w = (wf * cos.abs() + hf * sin.abs()).ceil() as u32;
    let side_h = (wf * sin.abs() + hf * cos.abs()).ceil() as u32;
    let (cx, cy) = (wf / 2.0, hf / 2.0);
    let (ox, oy) = (side_w as f32 / 2.0, side_h as f32 / 2.0);
    GrayImage::from_fn(side_w, side_h, |x, y| {
        let (dx, dy) = (x as f32 + 0.5 - ox, y as f32 + 0.5 - oy);
        let (sx, sy) = (
            cos * dx - sin * dy + cx - 0.5,
            sin * dx + cos * dy + cy - 0.5,
        );
        if sx < 0.0 || sy < 0.0 || sx >= wf - 1.0 || sy >= hf - 1.0 {
            return image::Luma([u8::MAX]);
        }
        image::Luma([bilinear(pixels, w, sx, sy).round() as u8])
    })
}

/// Half the side of the window whose mean is a pixel's threshold in [`binarised`]: some
/// 20 modules at the limit, so that a window holds bars and spaces both.
const BINARISE_HALF_WINDOW: usize = 30;
/// Smallest standard deviation of that window (gray levels) for its pixels to count as
/// printed; flat ones are white.
const BINARISE_MIN_DEVIATION: f64 = 12.0;

/// `image` in black and white: black where a pixel is darker than the mean of the
/// window around it and the window is not flat. rxing's row readers then see a bar
/// code's bars whatever the parcel's gray around the label.
fn binarised(image: &GrayImage) -> GrayImage {
    let (w, h) = (image.width() as usize, image.height() as usize);
    let pixels = image.as_raw();
    // Sums of the pixels and of their squares over [0, x) x [0, y).
    let stride = w + 1;
    let mut sum = vec![0.0f64; stride * (h + 1)];
    let mut squares = vec![0.0f64; stride * (h + 1)];
    for y in 0..h {
        let (mut row, mut row_squares) = (0.0, 0.0);
        for x in 0..w {
            let v = f64::from(pixels[y * w + x]);
            row += v;
            row_squares += v * v;
            sum[(y + 1) * stride + x + 1] = sum[y * stride + x + 1] + row;
            squares[(y + 1) * stride + x + 1] = squares[y * stride + x + 1] + row_squares;
        }
    }
    let half = BINARISE_HALF_WINDOW;
    GrayImage::from_fn(w as u32, h as u32, |x, y| {
        let (x, y) = (x as usize, y as usize);
        let (x0, y0) = (x.saturating_sub(half), y.saturating_sub(half));
        let (x1, y1) = ((x + half + 1).min(w), (y + half + 1).min(h));
        let n = ((x1 - x0) * (y1 - y0)) as f64;
        let over = |t: &[f64]| {
            t[y1 * stride + x1] - t[y0 * stride + x1] - t[y1 * stride + x0] + t[y0 * stride + x0]
        };
        let mean = over(&sum) / n;
        let variance = over(&squares) / n - mean * mean;
        let dark = variance > BINARISE_MIN_DEVIATION * BINARISE_MIN_DEVIATION
            && f64::from(pixels[y * w + x]) < mean;
        image::Luma([if dark { 0 } else { u8::MAX }])
    })
}

/// Standard deviation of the Gaussian blur of the QR reader's second look, pixels.
const QR_SECOND_LOOK_BLUR_PX: f32 = 1.0;

/// The QR codes in `image`. rqrr asserts on some grids it cannot sample (its issue #54);
/// a code it cannot read must not cost the Code 128 reads or the other cameras' codes.
fn read_qr_guarded(image: &GrayImage) -> BTreeSet<Code> {
    let qr = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
        let mut qr = BTreeSet::new();
        read_qr(image, &mut qr);
        qr
    }));
    qr.unwrap_or_else(|_| {
        tracing::warn!("the QR reader failed on this image; QR codes skipped");
        BTreeSet::new()
    })
}

fn read_qr(image: &GrayImage, found: &mut BTreeSet<Code>) {
    let (width, height) = (image.width() as usize, image.height() as usize);
    let mut prepared = rqrr::PreparedImage::prepare_from_greyscale(width, height, |x, y| {
        image.get_pixel(x as u32, y as u32).0[0]
    });
    for grid in prepared.detect_grids() {
        if let Ok((_, text)) = grid.decode() {
            found.insert(Code {
                kind: CodeKind::Qr,
                text,
            });
        }
    }
}

/// Directions of the scan lines; a bar code turned up to half a step from the nearest
/// one is still crossed whole when its bars are at least a fifth as tall as it is long.
const SCAN_ANGLES: usize = 8;
/// Distance between parallel scan lines over a whole image, pixels.
const SCAN_SPACING_PX: f32 = 6.0;
/// The same over a printed region (a tenth of the image or less): a line crosses a code
/// turned between two directions whole only near the code's middle, and finer lines
/// find that middle for codes of modules near one pixel.
const REGION_SCAN_SPACING_PX: f32 = 2.0;
/// Half width of the window that sets a sample's threshold, samples.
const THRESHOLD_HALF_WINDOW: usize = 16;
/// Smallest difference between the darkest and the lightest gray level (0-255) in that
/// window for a sample to count as printed: flat regions are neither bars nor spaces.
const MIN_CONTRAST: f32 = 40.0;
/// Shortest space after the stop pattern, modules (the standard asks for 10).
const QUIET_MODULES: f32 = 5.0;
/// Largest summed deviation, in modules, of a symbol's six widths from its pattern.
const MAX_SYMBOL_ERROR: f32 = 1.6;

fn read_code128(image: &GrayImage, spacing_px: f32, found: &mut BTreeSet<Code>) {
    let (w, h) = (image.width() as usize, image.height() as usize);
    if w < 2 || h < 2 {
        return;
    }
    let pixels = image.as_raw();
    // Samples stay inside [0, w - 1) x [0, h - 1), where bilinear has four neighbours.
    let (x_max, y_max) = ((w - 1) as f32, (h - 1) as f32);
    let half_diagonal = 0.5 * x_max.hypot(y_max);
    let (cx, cy) = (0.5 * x_max, 0.5 * y_max);
    let mut samples = Vec::new();
    for a in 0..SCAN_ANGLES {
        let angle = std::f32::consts::PI * a as f32 / SCAN_ANGLES as f32;
        let (dx, dy) = (angle.cos(), angle.sin());
        // Positions count in whole steps: an f32 that grows by 1 stops growing at 2^24.
        let lines = (2.0 * half_diagonal / spacing_px) as u32;
        for line in 0..=lines {
            let offset = line as f32 * spacing_px - half_diagonal;
            // The line through the centre's offset point, along (dx, dy), clipped to
            // the image.
            let (ox, oy) = (cx - dy * offset, cy + dx * offset);
            let (mut from, mut to) = (f32::NEG_INFINITY, f32::INFINITY);
            for (o, d, max) in [(ox, dx, x_max), (oy, dy, y_max)] {
                if d.abs() < 1e-6 {
                    if !(0.0..max).contains(&o) {
                        (from, to) = (1.0, 0.0);
                    }
                } else {
                    let (t0, t1) = ((0.0 - o) / d, (max - o) / d);
                    from = from.max(t0.min(t1));
                    to = to.min(t0.max(t1));
                }
            }
            samples.clear();
            let first = from.ceil();
            let steps = if to > first {
                (to - first).ceil() as u32
            } else {
                0
            };
            for step in 0..steps {
                let t = first + step as f32;
                let (x, y) = (ox + dx * t, oy + dy * t);
                if x >= 0.0 && y >= 0.0 && x < x_max && y < y_max {
                    samples.push(bilinear(pixels, w, x, y));
                }
            }
            let runs = runs(&samples);
            if let Some(text) = decode_runs(&runs) {
                found.insert(Code {
                    kind: CodeKind::Code128,
                    text,
                });
            }
        }
    }
}

/// The gray level at (`x`, `y`), both non-negative and at least one pixel inside the
/// last row and column, interpolated between the four pixels around it.
fn bilinear(pixels: &[u8], width: usize, x: f32, y: f32) -> f32 {
    // Truncation is the floor for the non-negative coordinates here.
    let (x0, y0) = (x as usize, y as usize);
    let (fx, fy) = (x - x0 as f32, y - y0 as f32);
    let at = y0 * width + x0;
    let p = |i: usize| f32::from(pixels[i]);
    let top = p(at) * (1.0 - fx) + p(at + 1) * fx;
    let bottom = p(at + width) * (1.0 - fx) + p(at + width + 1) * fx;
    top * (1.0 - fy) + bottom * fy
}

/// The alternating bars (`true`) and spaces of a scan line with their widths in samples.
/// A sample's threshold is halfway between the darkest and the lightest sample near it,
/// and edges fall where the signal crosses it, interpolated between samples. Samples
/// without contrast nearby are spaces.
fn runs(samples: &[f32]) -> Vec<(bool, f32)> {
    let n = samples.len();
    let lows = sliding(samples, THRESHOLD_HALF_WINDOW, |a, b| a <= b);
    let highs = sliding(samples, THRESHOLD_HALF_WINDOW, |a, b| a >= b);
    // Signed distance of each sample above its threshold.
    let level: Vec<f32> = (0..n)
        .map(|i| {
            if highs[i] - lows[i] < MIN_CONTRAST {
                1.0
            } else {
                samples[i] - 0.5 * (lows[i] + highs[i])
            }
        })
        .collect();
    let mut out = Vec::new();
    let mut edge = 0.0f32;
    for i in 1..n {
        let (a, b) = (level[i - 1], level[i]);
        if (a < 0.0) != (b < 0.0) {
            let at = (i - 1) as f32 + a / (a - b);
            out.push((a < 0.0, at - edge));
            edge = at;
        }
    }
    if n > 0 {
        out.push((level[n - 1] < 0.0, n as f32 - edge));
    }
    out
}

/// For each sample, the extreme of the samples within `half` of it: the minimum when
/// `keeps(a, b)` is `a <= b`, the maximum when it is `a >= b` (a monotonic queue, linear).
fn sliding(samples: &[f32], half: usize, keeps: impl Fn(f32, f32) -> bool) -> Vec<f32> {
    let n = samples.len();
    let mut queue = std::collections::VecDeque::new();
    let mut out = Vec::with_capacity(n);
    let mut pushed = 0;
    for i in 0..n {
        while pushed < n && pushed <= i + half {
            while queue
                .back()
                .is_some_and(|&j: &usize| keeps(samples[pushed], samples[j]))
            {
                queue.pop_back();
            }
            queue.push_back(pushed);
            pushed += 1;
        }
        while queue.front().is_some_and(|&j| j + half < i) {
            queue.pop_front();
        }
        out.push(samples[queue[0]]);
    }
    out
}

/// Module widths of the 103 data symbols, the three start symbols (103-105: A, B, C),
/// bar first; ISO/IEC 15417 table 1.
const PATTERNS: [[u8; 6]; 106] = [
    [2, 1, 2, 2, 2, 2],
    [2, 2, 2, 1, 2, 2],
    [2, 2, 2, 2, 2, 1],
    [1, 2, 1, 2, 2, 3],
    [1, 2, 1, 3, 2, 2],
    [1, 3, 1, 2, 2, 2],
    [1, 2, 2, 2, 1, 3],
    [1, 2, 2, 3, 1, 2],
    [1, 3, 2, 2, 1, 2],
    [2, 2, 1, 2, 1, 3],
    [2, 2, 1, 3, 1, 2],
    [2, 3, 1, 2, 1, 2],
    [1, 1, 2, 2, 3, 2],
    [1, 2, 2, 1, 3, 2],
    [1, 2, 2, 2, 3, 1],
    [1, 1, 3, 2, 2, 2],
    [1, 2, 3, 1, 2, 2],
    [1, 2, 3, 2, 2, 1],
    [2, 2, 3, 2, 1, 1],
    [2, 2, 1, 1, 3, 2],
    [2, 2, 1, 2, 3, 1],
    [2, 1, 3, 2, 1, 2],
    [2, 2, 3, 1, 1, 2],
    [3, 1, 2, 1, 3, 1],
    [3, 1, 1, 2, 2, 2],
    [3, 2, 1, 1, 2, 2],
    [3, 2, 1, 2, 2, 1],
    [3, 1, 2, 2, 1, 2],
    [3, 2, 2, 1, 1, 2],
    [3, 2, 2, 2, 1, 1],
    [2, 1, 2, 1, 2, 3],
    [2, 1, 2, 3, 2, 1],
    [2, 3, 2, 1, 2, 1],
    [1, 1, 1, 3, 2, 3],
    [1, 3, 1, 1, 2, 3],
    [1, 3, 1, 3, 2, 1],
    [1, 1, 2, 3, 1, 3],
    [1, 3, 2, 1, 1, 3],
    [1, 3, 2, 3, 1, 1],
    [2, 1, 1, 3, 1, 3],
    [2, 3, 1, 1, 1, 3],
    [2, 3, 1, 3, 1, 1],
    [1, 1, 2, 1, 3, 3],
    [1, 1, 2, 3, 3, 1],
    [1, 3, 2, 1, 3, 1],
    [1, 1, 3, 1, 2, 3],
    [1, 1, 3, 3, 2, 1],
    [1, 3, 3, 1, 2, 1],
    [3, 1, 3, 1, 2, 1],
    [2, 1, 1, 3, 3, 1],
    [2, 3, 1, 1, 3, 1],
    [2, 1, 3, 1, 1, 3],
    [2, 1, 3, 3, 1, 1],
    [2, 1, 3, 1, 3, 1],
    [3, 1, 1, 1, 2, 3],
    [3, 1, 1, 3, 2, 1],
    [3, 3, 1, 1, 2, 1],
    [3, 1, 2, 1, 1, 3],
    [3, 1, 2, 3, 1, 1],
    [3, 3, 2, 1, 1, 1],
    [3, 1, 4, 1, 1, 1],
    [2, 2, 1, 4, 1, 1],
    [4, 3, 1, 1, 1, 1],
    [1, 1, 1, 2, 2, 4],
    [1, 1, 1, 4, 2, 2],
    [1, 2, 1, 1, 2, 4],
    [1, 2, 1, 4, 2, 1],
    [1, 4, 1, 1, 2, 2],
    [1, 4, 1, 2, 2, 1],
    [1, 1, 2, 2, 1, 4],
    [1, 1, 2, 4, 1, 2],
    [1, 2, 2, 1, 1, 4],
    [1, 2, 2, 4, 1, 1],
    [1, 4, 2, 1, 1, 2],
    [1, 4, 2, 2, 1, 1],
    [2, 4, 1, 2, 1, 1],
    [2, 2, 1, 1, 1, 4],
    [4, 1, 3, 1, 1, 1],
    [2, 4, 1, 1, 1, 2],
    [1, 3, 4, 1, 1, 1],
    [1, 1, 1, 2, 4, 2],
    [1, 2, 1, 1, 4, 2],
    [1, 2, 1, 2, 4, 1],
    [1, 1, 4, 2, 1, 2],
    [1, 2, 4, 1, 1, 2],
    [1, 2, 4, 2, 1, 1],
    [4, 1, 1, 2, 1, 2],
    [4, 2, 1, 1, 1, 2],
    [4, 2, 1, 2, 1, 1],
    [2, 1, 2, 1, 4, 1],
    [2, 1, 4, 1, 2, 1],
    [4, 1, 2, 1, 2, 1],
    [1, 1, 1, 1, 4, 3],
    [1, 1, 1, 3, 4, 1],
    [1, 3, 1, 1, 4, 1],
    [1, 1, 4, 1, 1, 3],
    [1, 1, 4, 3, 1, 1],
    [4, 1, 1, 1, 1, 3],
    [4, 1, 1, 3, 1, 1],
    [1, 1, 3, 1, 4, 1],
    [1, 1, 4, 1, 3, 1],
    [3, 1, 1, 1, 4, 1],
    [4, 1, 1, 1, 3, 1],
    [2, 1, 1, 4, 1, 2],
    [2, 1, 1, 2, 1, 4],
    [2, 1, 1, 2, 3, 2],
];
/// The stop pattern (with its final bar), 13 modules.
const STOP: [u8; 7] = [2, 3, 3, 1, 1, 1, 2];
const START_A: usize = 103;
const START_C: usize = 105;

/// Summed deviation, in modules, of `widths` from `pattern` once the widths are scaled
/// to the pattern's module count.
fn deviation(widths: &[f32], pattern: &[u8]) -> f32 {
    let total: f32 = widths.iter().sum();
    let modules: u8 = pattern.iter().sum();
    let scale = f32::from(modules) / total;
    widths
        .iter()
        .zip(pattern)
        .map(|(w, &p)| (w * scale - f32::from(p)).abs())
        .sum()
}

/// The symbol (0-105) closest to six element widths, if it is close enough.
fn symbol(widths: &[f32]) -> Option<usize> {
    let (best, error) = PATTERNS
        .iter()
        .enumerate()
        .map(|(i, p)| (i, deviation(widths, p)))
        .min_by(|a, b| a.1.total_cmp(&b.1))?;
    (error < MAX_SYMBOL_ERROR).then_some(best)
}

/// The first complete Code 128 symbol along a scan line's runs, read in either
/// direction.
fn decode_runs(runs: &[(bool, f32)]) -> Option<String> {
    [false, true].into_iter().find_map(|backwards| {
        let ordered: Vec<(bool, f32)> = if backwards {
            runs.iter().rev().copied().collect()
        } else {
            runs.to_vec()
        };
        let widths: Vec<f32> = ordered.iter().map(|r| r.1).collect();
        (0..ordered.len())
            .filter(|&i| ordered[i].0)
            .find_map(|i| decode_from(&widths[i..]))
    })
}

/// Decodes the symbol that starts with a start pattern at `widths[0]` (a bar).
fn decode_from(widths: &[f32]) -> Option<String> {
    let first = widths.get(..6)?;
    let start = (START_A..=START_C).find(|&s| deviation(first, &PATTERNS[s]) < MAX_SYMBOL_ERROR)?;
    let mut values = Vec::new();
    let mut at = 6;
    loop {
        let next = widths.get(at..at + 7)?;
        // The stop pattern is followed by a quiet zone (or the line's end), which tells
        // it from a data symbol and the element after it.
        let module = next.iter().sum::<f32>() / 13.0;
        let quiet = match widths.get(at + 7) {
            Some(&w) => w >= QUIET_MODULES * module || at + 8 == widths.len(),
            None => true,
        };
        if quiet && deviation(next, &STOP) < MAX_SYMBOL_ERROR {
            break;
        }
        let value = symbol(&next[..6]).filter(|&v| v < START_A)?;
        values.push(value);
        at += 6;
    }
    let (&check, data) = values.split_last()?;
    if data.is_empty() {
        return None;
    }
    let sum = data
        .iter()
        .enumerate()
        .fold(start, |acc, (i, &v)| (acc + (i + 1) * v) % 103);
    (sum == check).then(|| text(start, data)).flatten()
}

/// The code sets of Code 128.
#[derive(Clone, Copy, PartialEq)]
enum Set {
    A,
    B,
    C,
}

/// The text of the data symbols under the code set `start` selects. FNC1 first marks
/// GS1-128 and carries no text, later it is the GS1 separator (0x1D); FNC2 and FNC3 carry
/// no text; FNC4 adds 128 to the next character (Latin-1), two in a row to every
/// character until the next two.
fn text(start: usize, data: &[usize]) -> Option<String> {
    let mut set = match start {
        START_A => Set::A,
        START_C => Set::C,
        _ => Set::B,
    };
    let mut shift = false;
    let (mut fnc4, mut fnc4_latched) = (false, false);
    let mut out = String::new();
    for (i, &v) in data.iter().enumerate() {
        let current = if shift {
            if set == Set::A { Set::B } else { Set::A }
        } else {
            set
        };
        shift = false;
        let character = match (current, v) {
            (Set::C, 0..=99) => {
                out.push(char::from(b'0' + (v / 10) as u8));
                out.push(char::from(b'0' + (v % 10) as u8));
                continue;
            }
            (Set::A, 0..=63) | (Set::B, 0..=95) => 32 + v as u8,
            (Set::A, 64..=95) => v as u8 - 64,
            (Set::A, 101) | (Set::B, 100) => {
                if fnc4 {
                    fnc4_latched = !fnc4_latched;
                }
                fnc4 = !fnc4;
                continue;
            }
            (Set::A | Set::B, 98) => {
                shift = true;
                continue;
            }
            (Set::A | Set::B, 99) => {
                set = Set::C;
                continue;
            }
            (Set::A | Set::C, 100) => {
                set = Set::B;
                continue;
            }
            (Set::B | Set::C, 101) => {
                set = Set::A;
                continue;
            }
            (_, 102) if i > 0 => {
                out.push('\u{1d}');
                continue;
            }
            (_, 96 | 97 | 102) => continue,
            _ => return None,
        };
        let high = if fnc4 != fnc4_latched { 128 } else { 0 };
        fnc4 = false;
        out.push(char::from(character + high));
    }
    Some(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The bars of a Code 128 symbol as `barcoders` encodes them (one entry per module),
    /// with quiet zones, drawn `module_px` wide and `height` tall.
    /// What our reader reads in `image` (the station reads with rxing: [`read`]).
    fn ours(image: &GrayImage) -> Vec<Code> {
        read_with(image, Reader::Ours)
    }

    fn draw(modules: &[u8], module_px: u32, height: u32) -> GrayImage {
        let quiet = 10;
        let width = (modules.len() as u32 + 2 * quiet) * module_px;
        GrayImage::from_fn(width, height, |x, _| {
            let m = (x / module_px) as usize;
            let dark = m >= quiet as usize && modules.get(m - quiet as usize) == Some(&1);
            image::Luma([if dark { 20 } else { 235 }])
        })
    }

    fn encode(text: &str) -> Vec<u8> {
        barcoders::sym::code128::Code128::new(text)
            .expect("encodable")
            .encode()
    }

    #[test]
    fn every_printable_ascii_character_reads_back_from_set_b() {
        let all: String = (32u8..127).map(char::from).collect();
        for chunk in all.as_bytes().chunks(12) {
            let text = std::str::from_utf8(chunk).unwrap();
            let image = draw(&encode(&format!("\u{0181}{text}")), 2, 20);
            assert_eq!(
                ours(&image),
                [Code {
                    kind: CodeKind::Code128,
                    text: text.into()
                }],
                "{text:?}"
            );
        }
    }

    #[test]
    fn digits_read_back_from_set_c_and_control_characters_from_set_a() {
        let image = draw(&encode("\u{0106}0123456789998877"), 3, 20);
        assert_eq!(ours(&image)[0].text, "0123456789998877");
        let image = draw(&encode("\u{00C0}AB\u{0106}1234\u{0181}xy"), 2, 20);
        assert_eq!(ours(&image)[0].text, "AB1234xy");
    }

    #[test]
    fn a_code_reads_right_to_left_and_turned() {
        let image = draw(&encode("\u{0181}PKG-0001"), 3, 120);
        let flipped = image::imageops::rotate180(&image);
        assert_eq!(ours(&flipped)[0].text, "PKG-0001");
        let turned = image::imageops::rotate90(&image);
        assert_eq!(ours(&turned)[0].text, "PKG-0001");
    }

    #[test]
    fn a_wrong_check_symbol_or_a_missing_stop_reads_nothing() {
        let mut modules = encode("\u{0181}PKG-0001");
        // The check symbol is the 11 modules before the 13 of the stop pattern: swap it
        // for the pattern of another value.
        let check = modules.len() - 13 - 11;
        let other: Vec<u8> = PATTERNS[8]
            .iter()
            .enumerate()
            .flat_map(|(i, &w)| std::iter::repeat_n(u8::from(i % 2 == 0), usize::from(w)))
            .collect();
        let original = modules[check..check + 11].to_vec();
        assert_ne!(original, other, "pick another value");
        modules[check..check + 11].copy_from_slice(&other);
        assert_eq!(ours(&draw(&modules, 2, 20)), []);
        let mut cut = encode("\u{0181}PKG-0001");
        cut.truncate(cut.len() - 13);
        assert_eq!(ours(&draw(&cut, 2, 20)), []);
    }

    #[test]
    fn a_flat_image_and_noise_read_nothing() {
        let flat = GrayImage::from_pixel(200, 100, image::Luma([128]));
        let mut state = 12345u32;
        let noise = GrayImage::from_fn(300, 200, |_, _| {
            state = state.wrapping_mul(1_103_515_245).wrapping_add(12345);
            image::Luma([(state >> 24) as u8])
        });
        for reader in [Reader::Ours, Reader::Rxing, Reader::Both] {
            assert_eq!(read_with(&flat, reader), [], "{reader:?}");
            assert_eq!(read_with(&noise, reader), [], "{reader:?}");
        }
    }

    /// The modules of start symbol `start`, the data `values`, their check symbol and
    /// the stop pattern.
    fn symbol_modules(start: usize, values: &[usize]) -> Vec<u8> {
        let check = values
            .iter()
            .enumerate()
            .fold(start, |acc, (i, &v)| (acc + (i + 1) * v) % 103);
        let mut widths: Vec<u8> = Vec::new();
        for v in std::iter::once(start)
            .chain(values.iter().copied())
            .chain([check])
        {
            widths.extend(PATTERNS[v]);
        }
        widths.extend(STOP);
        widths
            .iter()
            .enumerate()
            .flat_map(|(i, &w)| std::iter::repeat_n(u8::from(i % 2 == 0), usize::from(w)))
            .collect()
    }

    #[test]
    fn fnc4_extends_the_next_character_and_two_extend_until_two_more() {
        const B: usize = 104;
        const FNC4: usize = 100;
        let (a, b) = (33, 34);
        let read_text = |values: &[usize]| ours(&draw(&symbol_modules(B, values), 2, 20));
        assert_eq!(read_text(&[FNC4, a, b])[0].text, "\u{c1}B");
        assert_eq!(
            read_text(&[FNC4, FNC4, a, b, FNC4, a, FNC4, FNC4, b])[0].text,
            "\u{c1}\u{c2}AB"
        );
    }

    #[test]
    fn a_stop_pattern_at_the_edge_of_the_image_still_ends_the_code() {
        let modules = encode("\u{0181}PKG-0001");
        for gap in 0..=6 {
            let drawn = draw(&modules, 2, 20);
            // Cut the right quiet zone down to `gap` modules.
            let width = drawn.width() - (10 - gap) * 2;
            let cut = image::imageops::crop_imm(&drawn, 0, 0, width, 20).to_image();
            assert_eq!(ours(&cut).len(), 1, "{gap} modules after the stop");
        }
    }

    #[test]
    fn an_empty_image_reads_nothing() {
        assert_eq!(read(&GrayImage::new(0, 5)), []);
        assert_eq!(read(&GrayImage::new(5, 0)), []);
        assert_eq!(read(&GrayImage::new(1, 1)), []);
    }

    /// The gray image camera `index` of `scene` sees at 1920x1080.
    fn photograph(scene: &rgbd::Scene, index: usize) -> GrayImage {
        use rgbd::Camera as _;
        let cameras = rgbd::SyntheticCamera::all(scene).expect("scene");
        let camera = &cameras[index];
        camera
            .set_color_settings(rgbd::ColorSettings {
                format: rgbd::ColorFormat::Rgb8,
                fps: 30,
                width: 1920,
                height: 1080,
            })
            .expect("1920x1080 is a D415 color mode");
        let frame = camera.render_color(1);
        let rgb = image::RgbImage::from_raw(frame.width, frame.height, frame.data).unwrap();
        image::DynamicImage::from(rgb).to_luma8()
    }

    #[test]
    fn both_demo_cameras_read_the_qr_label_of_the_parcel() {
        let scene = rgbd::Scene::default_demo();
        for index in 0..scene.cameras.len() {
            assert_eq!(
                read(&photograph(&scene, index)),
                [Code {
                    kind: CodeKind::Qr,
                    text: "PKG-0001".into()
                }],
                "camera {index}"
            );
        }
    }

    #[test]
    fn a_code128_label_on_a_turned_parcel_reads_and_a_bare_parcel_reads_nothing() {
        let mut scene = rgbd::Scene::default_single();
        let parcel = &mut scene.boxes[0];
        parcel.yaw_deg = 35.0;
        parcel.label = Some(rgbd::scene::Label {
            kind: rgbd::scene::LabelKind::Code128,
            text: "1Z999AA10123456784".into(),
            size: 0.25,
            appear_s: None,
            remove_s: None,
        });
        assert_eq!(
            read(&photograph(&scene, 0)),
            [Code {
                kind: CodeKind::Code128,
                text: "1Z999AA10123456784".into()
            }]
        );
        scene.boxes[0].label = None;
        assert_eq!(read(&photograph(&scene, 0)), []);
    }

    #[test]
    fn labels_read_through_the_lane_sets_color_sensor_at_its_extremes() {
        // The noisiest, blurriest, brightest and darkest color sensor of the lane set.
        let [noise, blur_px] = [rgbd::lane::LANE_COLOR_NOISE[1], rgbd::lane::LANE_BLUR_PX[1]];
        for exposure in rgbd::lane::LANE_EXPOSURE {
            let sensor = rgbd::scene::ColorSensor {
                noise,
                blur_px,
                exposure,
            };
            let mut scene = rgbd::Scene::default_demo();
            for camera in &mut scene.cameras {
                camera.color_sensor = sensor;
            }
            for index in 0..scene.cameras.len() {
                assert_eq!(
                    read(&photograph(&scene, index)),
                    [Code {
                        kind: CodeKind::Qr,
                        text: "PKG-0001".into()
                    }],
                    "camera {index}, {sensor:?}"
                );
            }
            let mut single = rgbd::Scene::default_single();
            single.cameras[0].color_sensor = sensor;
            single.boxes[0].yaw_deg = 35.0;
            single.boxes[0].label = Some(rgbd::scene::Label {
                kind: rgbd::scene::LabelKind::Code128,
                text: "1Z999AA10123456784".into(),
                size: 0.25,
                appear_s: None,
                remove_s: None,
            });
            assert_eq!(
                read(&photograph(&single, 0)),
                [Code {
                    kind: CodeKind::Code128,
                    text: "1Z999AA10123456784".into()
                }],
                "{sensor:?}"
            );
        }
    }

    #[test]
    fn a_upc_a_read_shows_the_ean_13_of_the_same_bars_and_nothing_else() {
        let upca = Code {
            kind: CodeKind::Upca,
            text: "036000291452".into(),
        };
        assert!(upca.shows(CodeKind::Upca, "036000291452"));
        assert!(upca.shows(CodeKind::Ean13, "0036000291452"));
        assert!(!upca.shows(CodeKind::Ean13, "1036000291452"));
        assert!(!upca.shows(CodeKind::Ean13, "036000291452"));
        assert!(!upca.shows(CodeKind::Code128, "036000291452"));
        assert_eq!(upca.label_texts(), ["036000291452", "0036000291452"]);
        let ean = Code {
            kind: CodeKind::Ean13,
            text: "0036000291452".into(),
        };
        assert!(!ean.shows(CodeKind::Upca, "036000291452"));
        assert_eq!(ean.label_texts(), ["0036000291452"]);
    }

    /// A parcel turned `yaw_deg` under a camera 0.6 m above its top, its label `kind`
    /// of `text` sized so that a module spans `module_px` pixels of the 1920x1080 color
    /// image, seen through 1 px of lens blur and 3 levels of noise.
    fn labelled(
        kind: rgbd::scene::LabelKind,
        text: &str,
        module_px: f64,
        yaw_deg: f64,
    ) -> GrayImage {
        let mut label = rgbd::scene::Label {
            kind,
            text: text.into(),
            size: 1.0,
            appear_s: None,
            remove_s: None,
        };
        // fx of the D415's color at 1920x1080.
        let fx = 1368.75;
        label.size = module_px * 0.6 / fx * label.modules_across().unwrap() as f64;
        let (lx, ly) = label.extent_m();
        let mut scene = rgbd::Scene::from_toml(&format!(
            "seed = 7\n[[camera]]\nserial = \"840412060746\"\nposition = [0.0, 0.0, 0.7]\n\
             look_at = [0.0, 0.0, 0.0]\nup = [0.0, 1.0, 0.0]\n\
             color_sensor = {{ noise = 3.0, blur_px = 1.0 }}\n\
             [[box]]\nsize = [{}, {}, 0.1]\ncenter = [0.0, 0.0]\nyaw_deg = {yaw_deg}\n",
            lx + 0.02,
            ly + 0.02
        ))
        .unwrap();
        scene.boxes[0].label = Some(label);
        photograph(&scene, 0)
    }

    #[test]
    fn rxing_reads_turned_linear_and_pdf417_labels_at_the_limit_through_blur() {
        use rgbd::scene::LabelKind;
        for (kind, text) in [
            (LabelKind::Ean13, "4006381333931"),
            (LabelKind::Upca, "036000291452"),
            (LabelKind::Pdf417, "PKG-7Q2L9XW4C1"),
        ] {
            for yaw in [20.0, 45.0, 70.0] {
                let image = labelled(kind, text, MIN_PX_PER_MODULE, yaw);
                assert_eq!(
                    read_with(&image, Reader::Rxing),
                    [Code {
                        kind: kind.into(),
                        text: text.into()
                    }],
                    "{kind:?} turned {yaw} deg"
                );
            }
        }
    }

    /// A Code 128 symbol of `modules` (with 10-module quiet zones), `module_px` pixels
    /// per module, its bars a quarter as tall as the symbol is long (the reader's scan
    /// lines cross bars at least a fifth as tall whole), turned `yaw_deg` about the
    /// image's centre, as a camera images it: each pixel the mean of 4x4 samples over
    /// its area.
    fn render_turned(modules: &[u8], module_px: f32, yaw_deg: f32) -> GrayImage {
        let quiet = 10.0;
        let length = (modules.len() as f32 + 2.0 * quiet) * module_px;
        let height = length / 4.0;
        let side = (length.hypot(height) + 8.0).ceil() as u32;
        let (c, (sin, cos)) = (side as f32 / 2.0, yaw_deg.to_radians().sin_cos());
        let dark = |x: f32, y: f32| {
            // Into the symbol's frame: u along the bars' sequence, v along the bars.
            let (dx, dy) = (x - c, y - c);
            let (u, v) = (dx * cos + dy * sin + length / 2.0, -dx * sin + dy * cos);
            let m = (u / module_px - quiet).floor();
            v.abs() <= height / 2.0 && m >= 0.0 && modules.get(m as usize) == Some(&1)
        };
        GrayImage::from_fn(side, side, |x, y| {
            let mut sum = 0.0;
            for j in 0..4 {
                for i in 0..4 {
                    let (sx, sy) = (
                        x as f32 + (i as f32 + 0.5) / 4.0,
                        y as f32 + (j as f32 + 0.5) / 4.0,
                    );
                    sum += if dark(sx, sy) { 25.0 } else { 240.0 };
                }
            }
            image::Luma([(sum / 16.0) as u8])
        })
    }

    #[test]
    fn code128_reads_at_every_yaw_down_to_two_pixels_per_module() {
        let text = "1Z999AA10123456784";
        let modules = encode(&format!("\u{0181}{text}"));
        for module_px in [2.0, 2.5, 3.5] {
            for yaw in [0.0, 10.0, 25.0, 40.0, 55.0, 70.0, 90.0, 115.0, 140.0, 165.0] {
                let image = render_turned(&modules, module_px, yaw);
                assert_eq!(
                    read(&image),
                    [Code {
                        kind: CodeKind::Code128,
                        text: text.into()
                    }],
                    "{module_px} px per module, turned {yaw} deg"
                );
            }
        }
    }
}
