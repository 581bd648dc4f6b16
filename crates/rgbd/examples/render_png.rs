//! Renders scenes to PNG for a visual check:
//! `cargo run -p rgbd --example render_png [OUT_DIR [SCENE ...]]` (default
//! `/tmp/rgbd-check` and the built-in single-camera and demo scenes), where a SCENE is a
//! scene file or `lane:SEED:INDEX`, scene INDEX of the lane set of SEED ([`rgbd::lane`]).
//!
//! For each camera of each scene it writes `<scene>-<serial>-color.png` (1280x720 RGB)
//! and `<scene>-<serial>-depth.png`, a depth visualization: near = bright, far = dark, no
//! depth (0) = red. It prints a hash (FNV-1a) of each frame's raw bytes, which tells
//! whether a change of the renderer changed a frame.

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

/// FNV-1a, 64 bits.
fn fnv1a(bytes: &[u8]) -> u64 {
    bytes.iter().fold(0xcbf2_9ce4_8422_2325, |h, &b| {
        (h ^ u64::from(b)).wrapping_mul(0x0000_0100_0000_01b3)
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
        let color_hash = fnv1a(&color.data);
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
        let depth_bytes: Vec<u8> = depth.data.iter().flat_map(|v| v.to_le_bytes()).collect();
        println!(
            "{} {}: wrote {} and {} ({:.1} % of depth pixels are 0; depth {:016x}, color {:016x})",
            name,
            cam.serial(),
            color_path.display(),
            depth_path.display(),
            100.0 * zeros as f64 / depth.data.len() as f64,
            fnv1a(&depth_bytes),
            color_hash,
        );
    }
    Ok(())
}

fn main() -> ExitCode {
    let mut args = std::env::args().skip(1);
    let dir = args
        .next()
        .map_or_else(|| PathBuf::from("/tmp/rgbd-check"), PathBuf::from);
    let mut scenes = Vec::new();
    for path in args {
        if let Some(lane) = path.strip_prefix("lane:") {
            let numbers: Vec<Option<u64>> = lane.split(':').map(|n| n.parse().ok()).collect();
            let [Some(seed), Some(index)] = numbers[..] else {
                eprintln!("{path}: expected lane:SEED:INDEX");
                return ExitCode::from(2);
            };
            let lane = rgbd::lane::lane_scene(seed, index as usize);
            println!("{path}: {} {:?}", lane.case, lane.truths);
            scenes.push((format!("lane-{seed}-{index}-{}", lane.case), lane.scene));
            continue;
        }
        let name = Path::new(&path)
            .file_stem()
            .map_or_else(|| path.clone(), |s| s.to_string_lossy().into_owned());
        match Scene::load(Path::new(&path)) {
            Ok(scene) => scenes.push((name, scene)),
            Err(e) => {
                eprintln!("{e}");
                return ExitCode::FAILURE;
            }
        }
    }
    if scenes.is_empty() {
        scenes = vec![
            ("single".to_owned(), Scene::default_single()),
            ("demo".to_owned(), Scene::default_demo()),
        ];
    }
    if let Err(e) = std::fs::create_dir_all(&dir) {
        eprintln!("cannot create {}: {e}", dir.display());
        return ExitCode::FAILURE;
    }
    for (name, scene) in &scenes {
        if let Err(e) = render(name, scene, &dir) {
            eprintln!("{name}: {e}");
            return ExitCode::FAILURE;
        }
    }
    ExitCode::SUCCESS
}
