//! Reading codes at a module size: for each symbology and each width of a module in
//! pixels, labels with seeded random texts on a parcel turned by a random yaw, seen by a
//! synthetic D415 straight above at 1920x1080 through its color sensor (Gaussian blur and
//! noise), each image read by our reader, by rxing, and by both
//! ([`crate::vision::codes::Reader`]). A read counts when the label's own text comes out
//! with its symbology ([`crate::vision::codes::Code::shows`]: an EAN-13 beginning with 0
//! may come out as the UPC-A of the same bars).

use rand_chacha::ChaCha8Rng;
use rand_core::{RngCore as _, SeedableRng as _};
use rgbd::scene::{Label, LabelKind};
use rgbd::{Camera as _, ColorFormat, ColorSettings, Scene, SyntheticCamera};

use crate::vision::codes::{CodeKind, Reader, read_with};

/// The readers compared, in the order of [`Cell::read`].
pub const READERS: [Reader; 3] = [Reader::Ours, Reader::Rxing, Reader::Both];

/// What the labels are seen through.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Sensor {
    /// Standard deviation of the lens's Gaussian blur, pixels.
    pub blur_px: f64,
    /// Sensor noise at mid grey, 8-bit levels (rgbd's `color_sensor.noise`).
    pub noise: f64,
}

/// One symbology at one module width.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct Cell {
    /// The symbology.
    pub kind: CodeKind,
    /// A module's width in the image, pixels.
    pub module_px: f64,
    /// Labels shown.
    pub labels: u32,
    /// Labels read, by each of [`READERS`].
    pub read: [u32; 3],
    /// Milliseconds each of [`READERS`] took over all of its images.
    pub ms: [f64; 3],
}

/// Distance from the camera to the label, metres.
const DISTANCE_M: f64 = 0.6;
/// Height of the parcel the label is on, metres.
const PARCEL_M: f64 = 0.1;

/// A random text for `kind`: what shipping labels carry (tracking numbers, GTINs, a
/// few fields of an address).
fn text(kind: LabelKind, rng: &mut ChaCha8Rng) -> String {
    let mut digits =
        |n: usize| -> Vec<u32> { (0..n).map(|_| rng.next_u32() % 10).collect::<Vec<u32>>() };
    let alnum = |rng: &mut ChaCha8Rng, n: usize| -> String {
        const SET: &[u8] = b"0123456789ABCDEFGHIJKLMNOPQRSTUVWXYZ";
        (0..n)
            .map(|_| char::from(SET[rng.next_u32() as usize % SET.len()]))
            .collect()
    };
    match kind {
        LabelKind::Ean13 | LabelKind::Upca => {
            let n = if kind == LabelKind::Ean13 { 12 } else { 11 };
            let d = digits(n);
            // GS1 check digit: weights 3 and 1 from the right.
            let sum: u32 = d
                .iter()
                .rev()
                .enumerate()
                .map(|(i, v)| if i % 2 == 0 { 3 * v } else { *v })
                .sum();
            let check = (10 - sum % 10) % 10;
            d.iter()
                .chain([&check])
                .map(|v| char::from_digit(*v, 10).unwrap_or('0'))
                .collect()
        }
        LabelKind::Code128 => {
            // Up to 165 modules: 5 px modules still fit the image, turned.
            let n = 8 + rng.next_u32() as usize % 3;
            alnum(rng, n)
        }
        LabelKind::Qr | LabelKind::DataMatrix | LabelKind::Pdf417 => {
            let n = 10 + rng.next_u32() as usize % 11;
            format!("PKG-{}", alnum(rng, n))
        }
    }
}

/// The scene of one label: a parcel turned by `yaw_deg` under a camera straight above.
fn scene(label: &Label, yaw_deg: f64, sensor: Sensor, seed: u64) -> anyhow::Result<Scene> {
    let (lx, ly) = label.extent_m();
    let toml = format!(
        "seed = {seed}\n\
         [[camera]]\nserial = \"840412060746\"\nposition = [0.0, 0.0, {z}]\n\
         look_at = [0.0, 0.0, 0.0]\nup = [0.0, 1.0, 0.0]\n\
         color_sensor = {{ noise = {noise}, blur_px = {blur} }}\n\
         [[box]]\nsize = [{bx}, {by}, {PARCEL_M}]\ncenter = [0.0, 0.0]\nyaw_deg = {yaw_deg}\n",
        z = PARCEL_M + DISTANCE_M,
        noise = sensor.noise,
        blur = sensor.blur_px,
        bx = lx + 0.02,
        by = ly + 0.02,
    );
    let mut scene = Scene::from_toml(&toml)?;
    scene.boxes[0].label = Some(label.clone());
    scene.validate()?;
    Ok(scene)
}

/// Reads `per_cell` labels of each symbology of `kinds` at each module width of
/// `module_px` through `sensor`, with texts and yaws drawn from `seed`.
pub fn run(
    kinds: &[LabelKind],
    module_px: &[f64],
    per_cell: u32,
    sensor: Sensor,
    seed: u64,
) -> anyhow::Result<Vec<Cell>> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let probe = Label {
        kind: LabelKind::Qr,
        text: "x".into(),
        size: 0.05,
        appear_s: None,
        remove_s: None,
    };
    let fx = f64::from(color(&SyntheticCamera::all(&scene(&probe, 0.0, sensor, 0)?)?[0])?.fx);
    let mut cells = Vec::new();
    for &kind in kinds {
        for &px in module_px {
            let mut cell = Cell {
                kind: CodeKind::from(kind),
                module_px: px,
                labels: 0,
                read: [0; 3],
                ms: [0.0; 3],
            };
            for _ in 0..per_cell {
                let text = text(kind, &mut rng);
                let mut label = Label {
                    kind,
                    text,
                    size: 1.0,
                    appear_s: None,
                    remove_s: None,
                };
                let across = label.modules_across().map_err(anyhow::Error::msg)?;
                // A module of `px` pixels at the label's distance.
                label.size = px * DISTANCE_M / fx * across as f64;
                let yaw = f64::from(rng.next_u32() % 36_000) / 100.0;
                let scene = scene(&label, yaw, sensor, rng.next_u64() % 1_000_000)?;
                let camera = &SyntheticCamera::all(&scene)?[0];
                color(camera)?;
                let frame = camera.render_color(1);
                let rgb = image::RgbImage::from_raw(frame.width, frame.height, frame.data)
                    .ok_or_else(|| anyhow::anyhow!("a color frame of the wrong size"))?;
                let gray = image::DynamicImage::from(rgb).to_luma8();
                cell.labels += 1;
                for (i, reader) in READERS.into_iter().enumerate() {
                    let started = std::time::Instant::now();
                    let codes = read_with(&gray, reader);
                    cell.ms[i] += started.elapsed().as_secs_f64() * 1e3;
                    let hit = codes.iter().any(|c| c.shows(cell.kind, &label.text));
                    cell.read[i] += u32::from(hit);
                }
            }
            eprintln!(
                "coapcam: {} at {px} px a module: read {:?} of {} (ours, rxing, both); {:.0}, {:.0} and {:.0} ms an image",
                cell.kind.name(),
                cell.read,
                cell.labels,
                cell.ms[0] / f64::from(cell.labels.max(1)),
                cell.ms[1] / f64::from(cell.labels.max(1)),
                cell.ms[2] / f64::from(cell.labels.max(1)),
            );
            cells.push(cell);
        }
    }
    Ok(cells)
}

/// Per symbology of `cells`, in their order: the labels read by both readers and the
/// labels shown, over the cells whose modules span the reader's limit for their
/// symbology ([`CodeKind::min_px_per_module`]) or more.
pub fn at_the_limit(cells: &[Cell]) -> Vec<(CodeKind, u32, u32)> {
    let mut out: Vec<(CodeKind, u32, u32)> = Vec::new();
    for cell in cells
        .iter()
        .filter(|c| c.module_px >= c.kind.min_px_per_module())
    {
        match out.iter_mut().find(|(kind, ..)| *kind == cell.kind) {
            Some((_, read, labels)) => {
                *read += cell.read[2];
                *labels += cell.labels;
            }
            None => out.push((cell.kind, cell.read[2], cell.labels)),
        }
    }
    out
}

/// Sets `camera`'s color to 1920x1080 RGB and returns its intrinsics.
fn color(camera: &SyntheticCamera) -> anyhow::Result<rgbd::Intrinsics> {
    camera.set_color_settings(ColorSettings {
        format: ColorFormat::Rgb8,
        fps: 30,
        width: 1920,
        height: 1080,
    })?;
    Ok(camera.color_intrinsics()?)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cell(kind: CodeKind, module_px: f64, read: u32, labels: u32) -> Cell {
        Cell {
            kind,
            module_px,
            labels,
            read: [0, 0, read],
            ms: [0.0; 3],
        }
    }

    #[test]
    fn the_rate_at_the_limit_counts_only_cells_at_or_above_it() {
        let cells = [
            cell(CodeKind::DataMatrix, 3.0, 38, 40),
            cell(CodeKind::DataMatrix, 4.0, 40, 40),
            cell(CodeKind::DataMatrix, 5.0, 39, 40),
            cell(CodeKind::Qr, 2.5, 1, 40),
            cell(CodeKind::Qr, 3.0, 39, 40),
        ];
        // Data Matrix's limit is 4 px, QR's 3.
        assert_eq!(
            at_the_limit(&cells),
            [(CodeKind::DataMatrix, 79, 80), (CodeKind::Qr, 39, 40)]
        );
    }
}
