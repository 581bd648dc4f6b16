//! Writes the depth fixtures of the librealsense differential tests:
//! `cargo run -p rgbd --example depth_fixtures -- OUT_DIR` (the committed set lives in
//! `crates/rgbd/tests/fixtures/rgbd`; `tools/regen-rgbd-fixtures.sh` runs this).
//!
//! Each fixture is a 128x96 window of a 1280x720 synthetic D415 depth frame (D415
//! noise, shadows, dropouts and flying pixels), cropped with the crate's own ROI crop
//! so that its intrinsics are the camera's with the principal point moved. It is
//! written as `<name>.z16` (raw little-endian u16, row-major) and `<name>.json`
//! (size, depth scale, stereo baseline, intrinsics, and which goldens to make of it).

use std::path::{Path, PathBuf};
use std::process::ExitCode;

use rgbd::FrameFilter as _;
use rgbd::filter::{Roi2, RoiCrop};
use rgbd::{Camera, DepthSettings, Scene, SyntheticCamera, d415};

/// (name, scene, camera index, window, goldens `tools/rs_reference.py` writes for it).
type Fixture = (&'static str, Scene, usize, Roi2, &'static [&'static str]);

fn fixtures() -> Vec<Fixture> {
    let window = |px, py| Roi2 {
        px,
        py,
        width: 128,
        height: 96,
    };
    vec![
        // The box's right edge over the floor, seen from straight above.
        (
            "box_edge",
            Scene::default_single(),
            0,
            window(832, 300),
            &[
                "decimation",
                "threshold",
                "disparity",
                "chain",
                "pointcloud",
            ],
        ),
        // The tilted demo view: box corner, side face and its shadow.
        (
            "box_tilted",
            Scene::default_demo(),
            1,
            window(464, 250),
            &[
                "decimation",
                "hole_filling",
                "spatial",
                "chain",
                "deproject",
            ],
        ),
    ]
}

fn write(dir: &Path, fixture: &Fixture) -> Result<(), String> {
    let (name, scene, index, roi, goldens) = fixture;
    let (index, roi) = (*index, *roi);
    let cams = SyntheticCamera::all(scene).map_err(|e| e.to_string())?;
    let cam = cams.get(index).ok_or("no such camera in the scene")?;
    cam.set_depth_settings(DepthSettings::default())
        .map_err(|e| e.to_string())?;
    let frame = cam.render_depth(1);
    let k = cam.depth_intrinsics().map_err(|e| e.to_string())?;
    let mut crop = RoiCrop::new(roi);
    let (window, k) = crop.process(&frame, &k).map_err(|e| e.to_string())?;
    let bytes: Vec<u8> = window.data.iter().flat_map(|v| v.to_le_bytes()).collect();
    let holes = window.data.iter().filter(|&&v| v == 0).count();
    let meta = serde_json::json!({
        "width": window.width,
        "height": window.height,
        "depth_scale": window.depth_scale,
        "baseline_mm": d415::BASELINE_M * 1000.0,
        "intrinsics": k,
        "goldens": goldens,
        "source": format!(
            "synthetic D415 1280x720, camera {} of the built-in scene, window {}x{} at ({}, {})",
            cam.serial(), roi.width, roi.height, roi.px, roi.py
        ),
    });
    std::fs::write(dir.join(format!("{name}.z16")), bytes).map_err(|e| e.to_string())?;
    let text = serde_json::to_string_pretty(&meta).map_err(|e| e.to_string())?;
    std::fs::write(dir.join(format!("{name}.json")), text + "\n").map_err(|e| e.to_string())?;
    println!("{name}: {}x{}, {holes} holes", window.width, window.height);
    Ok(())
}

fn main() -> ExitCode {
    let Some(dir) = std::env::args_os().nth(1).map(PathBuf::from) else {
        eprintln!("usage: depth_fixtures OUT_DIR");
        return ExitCode::FAILURE;
    };
    if let Err(e) = std::fs::create_dir_all(&dir) {
        eprintln!("{}: {e}", dir.display());
        return ExitCode::FAILURE;
    }
    for fixture in fixtures() {
        if let Err(e) = write(&dir, &fixture) {
            eprintln!("{}: {e}", fixture.0);
            return ExitCode::FAILURE;
        }
    }
    ExitCode::SUCCESS
}
