//! Frame times of the synthetic D415, for comparing a change of the renderer before and
//! after: `cargo run -p rgbd --example frame_time [FRAMES] [SCENE.toml]` renders FRAMES
//! (default 40) 1280x720 depth and color frames of the built-in default scene (or the
//! scene file's first camera) and prints the median and the fastest time per stream.
//! Run it on a quiet machine; the median of a busy one says little.

use std::path::Path;
use std::process::ExitCode;
use std::time::{Duration, Instant};

use rgbd::{Camera, ColorFormat, ColorSettings, DepthSettings, Scene, SyntheticCamera};

fn summary(mut times: Vec<Duration>) -> String {
    times.sort();
    let ms = |d: Duration| d.as_secs_f64() * 1e3;
    format!(
        "median {:.2} ms, fastest {:.2} ms",
        ms(times[times.len() / 2]),
        ms(times[0])
    )
}

fn main() -> ExitCode {
    let mut args = std::env::args().skip(1);
    let frames: u64 = match args.next().map(|a| a.parse()) {
        None => 40,
        Some(Ok(n)) if n > 0 => n,
        Some(_) => {
            eprintln!("usage: frame_time [FRAMES > 0] [SCENE.toml]");
            return ExitCode::from(2);
        }
    };
    let scene = match args.next() {
        None => Scene::default_single(),
        Some(path) => match Scene::load(Path::new(&path)) {
            Ok(scene) if !scene.cameras.is_empty() => scene,
            Ok(_) => {
                eprintln!("{path}: the scene has no camera");
                return ExitCode::FAILURE;
            }
            Err(e) => {
                eprintln!("{e}");
                return ExitCode::FAILURE;
            }
        },
    };
    let cam = match SyntheticCamera::new(&scene, &scene.cameras[0].serial) {
        Ok(cam) => cam,
        Err(e) => {
            eprintln!("{e}");
            return ExitCode::FAILURE;
        }
    };
    let color = ColorSettings {
        format: ColorFormat::Rgb8,
        fps: 30,
        width: 1280,
        height: 720,
    };
    if let Err(e) = cam
        .set_color_settings(color)
        .and_then(|()| cam.set_depth_settings(DepthSettings::default()))
    {
        eprintln!("{e}");
        return ExitCode::FAILURE;
    }
    let (mut depth, mut color) = (Vec::new(), Vec::new());
    for frame in 1..=frames {
        let start = Instant::now();
        std::hint::black_box(cam.render_depth(frame));
        depth.push(start.elapsed());
        let start = Instant::now();
        std::hint::black_box(cam.render_color(frame));
        color.push(start.elapsed());
    }
    println!("depth 1280x720: {}", summary(depth));
    println!("color 1280x720: {}", summary(color));
    ExitCode::SUCCESS
}
