//! Render timings of the synthetic D415: one 1280x720 depth frame and one 1280x720
//! color frame of the built-in default scene (target: both within 30 ms).

#![allow(missing_docs)]

use criterion::{Criterion, criterion_group, criterion_main};
use rgbd::{Camera, ColorFormat, ColorSettings, DepthSettings, Scene, SyntheticCamera};

fn camera() -> SyntheticCamera {
    let scene = Scene::default_single();
    let serial = scene.cameras[0].serial;
    let Ok(cam) = SyntheticCamera::new(&scene, &serial) else {
        panic!("the built-in scene is valid");
    };
    let color = ColorSettings {
        format: ColorFormat::Rgb8,
        fps: 30,
        width: 1280,
        height: 720,
    };
    if cam.set_color_settings(color).is_err()
        || cam.set_depth_settings(DepthSettings::default()).is_err()
    {
        panic!("1280x720 at 30 fps is a D415 mode");
    }
    cam
}

fn render(c: &mut Criterion) {
    let cam = camera();
    let mut group = c.benchmark_group("synthetic_d415_1280x720");
    let mut frame = 0u64;
    group.bench_function("depth", |b| {
        b.iter(|| {
            frame += 1;
            cam.render_depth(frame)
        });
    });
    group.bench_function("color", |b| {
        b.iter(|| {
            frame += 1;
            cam.render_color(frame)
        });
    });
    group.bench_function("depth_and_color", |b| {
        b.iter(|| {
            frame += 1;
            (cam.render_depth(frame), cam.render_color(frame))
        });
    });
    group.finish();
}

criterion_group!(benches, render);
criterion_main!(benches);
