//! Renders the built-in scenes to PNG for a visual check:
//! `cargo run -p rgbd --example render_png [OUT_DIR]` (default `/tmp/rgbd-check`).
//!
//! For each camera of the single-camera and the demo scene it writes
//! `<scene>-<serial>-color.png` (1280x720 RGB) and `<scene>-<serial>-depth.png`, a
//! depth visualization: near = bright, far = dark, no depth (0) = red.

use std::path::{Path, PathBuf};
use std::process::ExitCode;

use image::{Rgb, RgbImage};
use rgbd::{Camera, ColorFormat, ColorSettings, DepthFrame, Scene, SyntheticCamera};

fn depth_image(frame: &DepthFrame) -> RgbImage {
    let valid = frame.data.iter().copied().filter(|&v| v != 0);
    let (lo, hi) = valid.fold((u16::MAX, 0), |(lo, hi), v| (lo.min(v), hi.max(v)));
    let span = f32::from(hi.saturating_sub(lo).max(1));
    RgbImage::from_fn(frame.width, frame.height, |x, y| match frame.raw_at(x, y) {
        Some(0) | None => Rgb([200, 0, 0]),
        Some(v) => {
            let g = 255.0 - 215.0 * f32::from(v - lo) / span;
            Rgb([g as u8; 3])
        }
    })
}

fn render(name: &str, scene: &Scene, dir: &Path) -> Result<(), String> {
    let cams = SyntheticCamera::all(scene).map_err(|e| e.to_string())?;
    for cam in cams {
        cam.set_color_settings(ColorSettings {
            format: ColorFormat::Rgb8,
            fps: 30,
            width: 1280,
            height: 720,
        })
        .map_err(|e| e.to_string())?;
        let color = cam.render_color(1);
        let depth = cam.render_depth(1);
        let color_img = RgbImage::from_raw(color.width, color.height, color.data)
            .ok_or("color buffer does not match its size")?;
        let base = dir.join(format!("{name}-{}", cam.serial()));
        let color_path = base.with_file_name(format!("{name}-{}-color.png", cam.serial()));
        let depth_path = base.with_file_name(format!("{name}-{}-depth.png", cam.serial()));
        color_img
            .save(&color_path)
            .map_err(|e| format!("{}: {e}", color_path.display()))?;
        depth_image(&depth)
            .save(&depth_path)
            .map_err(|e| format!("{}: {e}", depth_path.display()))?;
        let zeros = depth.data.iter().filter(|&&v| v == 0).count();
        println!(
            "{} {}: wrote {} and {} ({:.1} % of depth pixels are 0)",
            name,
            cam.serial(),
            color_path.display(),
            depth_path.display(),
            100.0 * zeros as f64 / depth.data.len() as f64
        );
    }
    Ok(())
}

fn main() -> ExitCode {
    let dir = std::env::args()
        .nth(1)
        .map_or_else(|| PathBuf::from("/tmp/rgbd-check"), PathBuf::from);
    if let Err(e) = std::fs::create_dir_all(&dir) {
        eprintln!("cannot create {}: {e}", dir.display());
        return ExitCode::FAILURE;
    }
    for (name, scene) in [
        ("single", Scene::default_single()),
        ("demo", Scene::default_demo()),
    ] {
        if let Err(e) = render(name, &scene, &dir) {
            eprintln!("{name}: {e}");
            return ExitCode::FAILURE;
        }
    }
    ExitCode::SUCCESS
}
