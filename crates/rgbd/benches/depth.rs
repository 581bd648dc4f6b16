//! The depth chain of a point-cloud grab on one 1280x720 synthetic D415 depth frame:
//! decimation (2) -> spatial (librealsense's defaults, disparity domain) -> hole
//! filling (farest_from_around) -> deprojection -> transform into the world + 3D ROI
//! (geometry crate), plus each stage on its own.
//!
//! The input frame is also written to `$TMPDIR/rgbd-bench-1280x720.{z16,json}` so that
//! `tools/rs_bench.py` runs librealsense's blocks on the very same data;
//! `scripts/bench-depth.sh` runs both and prints the ratio. Target (issue 4): at least
//! 2x faster than librealsense and at most 15 ms on 2 cores.

#![allow(missing_docs)]

use std::path::PathBuf;

use criterion::{Criterion, criterion_group, criterion_main};
use geometry::{Point3, Roi3, Transform};
use nalgebra::{Matrix3, Vector3};
use rgbd::FrameFilter as _;
use rgbd::filter::{
    Decimation, HoleFilling, HoleFillingMode, PostProcessing, PostProcessingConfig,
};
use rgbd::{Camera, Deprojector, DepthFrame, Intrinsics, Scene, SyntheticCamera, d415};

struct Input {
    frame: DepthFrame,
    k: Intrinsics,
    to_world: Transform,
    roi: Roi3,
}

fn input() -> Input {
    let scene = Scene::default_single();
    let Ok(cam) = SyntheticCamera::new(&scene, &scene.cameras[0].serial) else {
        panic!("the built-in scene is valid");
    };
    let (Ok(k), Some(pose)) = (cam.depth_intrinsics(), cam.true_pose()) else {
        panic!("the built-in camera is calibrated");
    };
    let r = pose.rotation;
    let to_world = Transform {
        linear: Matrix3::from_fn(|i, j| r[i][j] as f32),
        translation: Vector3::from(pose.translation.map(|t| t as f32)),
    };
    // The box (400 x 300 x 200 mm) and a margin, without the floor.
    let Ok(roi) = Roi3::new(
        Point3::new(-0.35, -0.35, 0.01),
        Point3::new(0.35, 0.35, 0.5),
    ) else {
        panic!("a valid box");
    };
    Input {
        frame: cam.render_depth(1),
        k,
        to_world,
        roi,
    }
}

/// Writes the frame and the chain's parameters for tools/rs_bench.py.
fn export(input: &Input) {
    let base = std::env::temp_dir().join("rgbd-bench-1280x720");
    let bytes: Vec<u8> = input
        .frame
        .data
        .iter()
        .flat_map(|v| v.to_le_bytes())
        .collect();
    let l = &input.to_world.linear;
    let meta = serde_json::json!({
        "width": input.frame.width,
        "height": input.frame.height,
        "depth_scale": input.frame.depth_scale,
        "baseline_mm": d415::BASELINE_M * 1000.0,
        "intrinsics": input.k,
        "to_world": {
            "linear": [[l[(0, 0)], l[(0, 1)], l[(0, 2)]], [l[(1, 0)], l[(1, 1)], l[(1, 2)]], [l[(2, 0)], l[(2, 1)], l[(2, 2)]]],
            "translation": input.to_world.translation.as_slice(),
        },
        "roi": {"min": input.roi.min().coords.as_slice(), "max": input.roi.max().coords.as_slice()},
    });
    let written = std::fs::write(PathBuf::from(format!("{}.z16", base.display())), bytes)
        .and_then(|()| std::fs::write(format!("{}.json", base.display()), meta.to_string()));
    if let Err(e) = written {
        eprintln!(
            "could not export the bench frame to {}: {e}",
            base.display()
        );
    }
}

fn chain_config() -> PostProcessingConfig {
    match PostProcessingConfig::from_json(
        br#"{"decimation": {"magnitude": 2}, "spatial": 1, "holefilling": {"mode": "farest_from_around"}}"#,
    ) {
        Ok(c) => c,
        Err(e) => panic!("{e}"),
    }
}

fn depth(c: &mut Criterion) {
    let input = input();
    export(&input);
    let baseline_mm = d415::BASELINE_M * 1000.0;
    let Ok(mut chain) = PostProcessing::new(&chain_config(), Some(baseline_mm)) else {
        panic!("a valid chain");
    };
    let mut deprojector = Deprojector::new();
    let mut points = Vec::new();
    let mut group = c.benchmark_group("depth_chain_1280x720");
    group.sample_size(40);
    group.bench_function("full_chain", |b| {
        b.iter(|| {
            let Ok((frame, k)) = chain.process(&input.frame, &input.k) else {
                panic!("the chain accepts the frame");
            };
            if deprojector.deproject_frame(frame, &k, &mut points).is_err() {
                panic!("deprojection accepts the frame");
            }
            input.to_world.apply_and_crop(&points, &input.roi)
        });
    });
    group.bench_function("filters_and_points", |b| {
        b.iter(|| {
            let Ok((frame, k)) = chain.process(&input.frame, &input.k) else {
                panic!("the chain accepts the frame");
            };
            if deprojector.deproject_frame(frame, &k, &mut points).is_err() {
                panic!("deprojection accepts the frame");
            }
            points.len()
        });
    });
    group.bench_function("filters", |b| {
        b.iter(|| {
            chain
                .process(&input.frame, &input.k)
                .map(|(f, _)| f.data.len())
        });
    });
    let Ok(mut decimation) = Decimation::new(2) else {
        panic!("magnitude 2 is valid");
    };
    group.bench_function("decimation_2", |b| {
        b.iter(|| {
            decimation
                .process(&input.frame, &input.k)
                .map(|(f, _)| f.data.len())
        });
    });
    let mut holes = HoleFilling::new(HoleFillingMode::FarestFromAround);
    group.bench_function("hole_filling_full_res", |b| {
        b.iter(|| {
            holes
                .process(&input.frame, &input.k)
                .map(|(f, _)| f.data.len())
        });
    });
    group.bench_function("deproject_full_res", |b| {
        b.iter(|| deprojector.deproject_frame(&input.frame, &input.k, &mut points));
    });
    group.finish();
}

criterion_group!(benches, depth);
criterion_main!(benches);
