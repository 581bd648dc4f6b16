use rgbd::scene::Noise;
use rgbd::{Camera, ColorFormat, ColorSettings, DepthFrame, Scene, SyntheticCamera, d415};

use crate::support::{floor_scene, only_camera};

/// World point seen at depth pixel (u, v) of `frame`, via the camera's intrinsics and
/// true pose.
fn world_point(cam: &SyntheticCamera, frame: &DepthFrame, u: u32, v: u32) -> Option<[f64; 3]> {
    let z = frame.metres_at(u, v)?;
    let k = cam.depth_intrinsics().unwrap();
    let p = k.deproject([u as f32, v as f32], z);
    Some(cam.true_pose().unwrap().transform_point(p.map(f64::from)))
}

/// Pixel at which the depth camera sees world point `w`.
fn pixel_of(cam: &SyntheticCamera, w: [f64; 3]) -> (u32, u32) {
    let pose = cam.true_pose().unwrap();
    let d = [
        w[0] - pose.translation[0],
        w[1] - pose.translation[1],
        w[2] - pose.translation[2],
    ];
    let r = pose.rotation;
    let c = [0, 1, 2].map(|j| (r[0][j] * d[0] + r[1][j] * d[1] + r[2][j] * d[2]) as f32);
    let px = cam.depth_intrinsics().unwrap().project(c).unwrap();
    (px[0].round() as u32, px[1].round() as u32)
}

#[test]
fn a_pixel_on_the_box_top_deprojects_to_the_true_top_within_the_noise() {
    let scene = Scene::default_single();
    let cam = only_camera(&scene);
    let frame = cam.render_depth(1);
    let top_z = scene.boxes[0].size[2];
    let sigma = f64::from(d415::depth_rms_m(0.8, cam.depth_intrinsics().unwrap().fx));
    // Points across the top face (box frame, yawed 15 degrees), away from the edges.
    let yaw = scene.boxes[0].yaw_deg.to_radians();
    let mut checked = 0;
    for (lx, ly) in [
        (0.0, 0.0),
        (0.15, 0.1),
        (-0.15, -0.1),
        (0.1, -0.12),
        (-0.17, 0.12),
    ] {
        let w = [
            lx * yaw.cos() - ly * yaw.sin(),
            lx * yaw.sin() + ly * yaw.cos(),
            top_z,
        ];
        let (u, v) = pixel_of(&cam, w);
        for (du, dv) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
            let Some(p) = world_point(&cam, &frame, u + du, v + dv) else {
                continue; // dropout
            };
            // Height within 5 sigma plus half a depth unit; position within two pixels.
            assert!(
                (p[2] - top_z).abs() < 5.0 * sigma + 0.0005,
                "height {} at ({u},{v})",
                p[2]
            );
            assert!(
                (p[0] - w[0]).abs() < 0.003 && (p[1] - w[1]).abs() < 0.003,
                "{p:?} vs {w:?}"
            );
            checked += 1;
        }
    }
    assert!(checked >= 15, "only {checked} pixels had depth");
}

#[test]
fn depth_noise_sigma_is_within_20_percent_of_the_d415_formula_at_0_6_1_0_and_1_5_m() {
    for height in [0.6, 1.0, 1.5] {
        let cam = only_camera(&floor_scene(height, Noise::D415));
        let frame = cam.render_depth(1);
        let errors: Vec<f64> = frame
            .data
            .iter()
            .filter(|&&raw| raw != 0)
            .map(|&raw| f64::from(raw) * f64::from(frame.depth_scale) - height)
            .collect();
        assert!(errors.len() > 800_000, "{} valid pixels", errors.len());
        let n = errors.len() as f64;
        let mean = errors.iter().sum::<f64>() / n;
        let sigma = (errors.iter().map(|e| (e - mean).powi(2)).sum::<f64>() / n).sqrt();
        let expected = f64::from(d415::depth_rms_m(
            height as f32,
            cam.depth_intrinsics().unwrap().fx,
        ));
        let ratio = sigma / expected;
        assert!(
            (0.8..=1.2).contains(&ratio),
            "at {height} m: sigma {sigma} vs formula {expected} (ratio {ratio})"
        );
        assert!(
            mean.abs() < 0.2 * expected + 0.0002,
            "bias {mean} at {height} m"
        );
    }
}

#[test]
fn about_one_percent_of_pixels_drop_out() {
    let cam = only_camera(&floor_scene(1.0, Noise::D415));
    let frame = cam.render_depth(3);
    let zeros = frame.data.iter().filter(|&&v| v == 0).count() as f64 / frame.data.len() as f64;
    assert!((0.008..0.012).contains(&zeros), "{zeros}");
}

#[test]
fn ideal_noise_renders_exact_depth() {
    let cam = only_camera(&floor_scene(1.0, Noise::Ideal));
    assert!(cam.render_depth(1).data.iter().all(|&v| v == 1000));
    let scene = Scene::default_single();
    let mut ideal = scene;
    ideal.cameras[0].noise = Noise::Ideal;
    let frame = only_camera(&ideal).render_depth(1);
    assert!(
        frame.data.iter().all(|&v| v == 800 || v == 1000),
        "only the top and the floor"
    );
}

#[test]
fn the_floor_beside_the_left_box_edge_is_in_the_right_imagers_shadow() {
    let scene = Scene::default_single();
    let cam = only_camera(&scene);
    let frame = cam.render_depth(1);
    let k = cam.depth_intrinsics().unwrap();
    // Shadow width along a row = disparity(top) - disparity(floor) = fx B (1/0.8 - 1/1.0).
    let expected = f64::from(k.fx * d415::BASELINE_M) * (1.0 / 0.8 - 1.0);
    let mut widths = Vec::new();
    for v in (300..420).step_by(10) {
        let row: Vec<u16> = (0..frame.width)
            .map(|u| frame.raw_at(u, v).unwrap())
            .collect();
        let Some(edge) = row.iter().position(|&z| (700..900).contains(&z)) else {
            continue;
        };
        let run = row[..edge].iter().rev().take_while(|&&z| z == 0).count();
        widths.push(run as f64);
    }
    assert!(widths.len() >= 10);
    let mean = widths.iter().sum::<f64>() / widths.len() as f64;
    assert!(
        (mean - expected).abs() < 2.0,
        "mean shadow width {mean} px, expected {expected}"
    );
    // The right side of the box casts no shadow.
    let v = 360;
    let row: Vec<u16> = (0..frame.width)
        .map(|u| frame.raw_at(u, v).unwrap())
        .collect();
    let last_top = row.iter().rposition(|&z| (700..900).contains(&z)).unwrap();
    let zeros_after = row[last_top + 1..last_top + 10]
        .iter()
        .filter(|&&z| z == 0)
        .count();
    assert!(zeros_after <= 1, "{zeros_after}");
}

#[test]
fn flying_pixels_appear_only_at_depth_edges_and_only_with_d415_noise() {
    let scene = Scene::default_single();
    let between = |f: &DepthFrame| f.data.iter().filter(|&&z| (830..970).contains(&z)).count();
    let noisy = only_camera(&scene).render_depth(1);
    let flying = between(&noisy);
    // The box outline is ~1400 px long; a share of its pixels straddle the edge.
    assert!((50..3000).contains(&flying), "{flying} flying pixels");
    let mut ideal = scene;
    ideal.cameras[0].noise = Noise::Ideal;
    assert_eq!(between(&only_camera(&ideal).render_depth(1)), 0);
}

#[test]
fn nothing_nearer_than_the_minimum_range_is_reported() {
    let cam = only_camera(&floor_scene(0.35, Noise::D415));
    assert!(cam.render_depth(1).data.iter().all(|&v| v == 0));
    // At 640x360 (fx 448) the minimum range is ~0.2 m, so the floor at 0.35 m is seen.
    cam.set_depth_settings(rgbd::DepthSettings {
        fps: 30,
        width: 640,
        height: 360,
        ..cam.depth_settings()
    })
    .unwrap();
    assert!(cam.render_depth(1).data.iter().filter(|&&v| v != 0).count() > 200_000);
}

#[test]
fn same_seed_and_frame_number_give_identical_bytes() {
    let scene = Scene::default_demo();
    let serial = scene.cameras[1].serial;
    let a = SyntheticCamera::new(&scene, &serial).unwrap();
    let b = SyntheticCamera::new(&scene, &serial).unwrap();
    assert_eq!(a.render_depth(5), b.render_depth(5));
    assert_eq!(a.render_color(5), b.render_color(5));
    assert_ne!(
        a.render_depth(5).data,
        a.render_depth(6).data,
        "noise changes per frame"
    );

    let mut reseeded = scene;
    reseeded.seed += 1;
    let c = SyntheticCamera::new(&reseeded, &serial).unwrap();
    assert_ne!(
        a.render_depth(5).data,
        c.render_depth(5).data,
        "noise follows the seed"
    );
}

#[test]
fn color_frames_use_the_configured_format_and_show_the_label() {
    let scene = Scene::default_single();
    let cam = only_camera(&scene);
    let rgb = cam.render_color(1);
    assert_eq!(
        (rgb.width, rgb.height, rgb.format),
        (1280, 720, ColorFormat::Bgr8)
    );
    assert_eq!(rgb.stride, 1280 * 3);
    assert_eq!(rgb.data.len(), 1280 * 720 * 3);
    cam.set_color_settings(ColorSettings {
        format: ColorFormat::Rgba8,
        fps: 30,
        width: 1920,
        height: 1080,
    })
    .unwrap();
    let rgba = cam.render_color(1);
    assert_eq!((rgba.stride, rgba.data.len()), (1920 * 4, 1920 * 1080 * 4));
    assert!(rgba.data.chunks(4).all(|p| p[3] == 255));

    // Around the label centre (box centre, top face) there are black and white modules.
    let k = cam.color_intrinsics().unwrap();
    let centre = k.project([0.015, 0.0, 0.8]).unwrap();
    let (cu, cv) = (centre[0] as u32, centre[1] as u32);
    let mut dark = 0;
    let mut light = 0;
    for v in cv - 40..cv + 40 {
        for u in cu - 40..cu + 40 {
            let [r, g, b] = rgba.rgb_at(u, v).unwrap();
            if r < 40 && g < 40 && b < 40 {
                dark += 1;
            } else if r > 200 && g > 200 && b > 200 {
                light += 1;
            }
        }
    }
    assert!(dark > 500 && light > 500, "dark {dark}, light {light}");
}

#[test]
fn calibrated_cameras_expose_their_true_pose() {
    let scene = Scene::default_single();
    let cam = only_camera(&scene);
    let pose = cam.true_pose().unwrap();
    assert_eq!(pose.translation, [0.0, 0.0, 1.0]);
    // The optical axis points straight down.
    assert_eq!(pose.transform_point([0.0, 0.0, 1.0]), [0.0, 0.0, 0.0]);
    let mut uncalibrated = scene;
    uncalibrated.cameras[0].calibrated = false;
    assert!(only_camera(&uncalibrated).true_pose().is_none());
}

/// Where the color camera of `cam` sees world point `w`, through its true pose, the
/// depth->color extrinsics and the color intrinsics.
fn color_pixel_of(cam: &SyntheticCamera, w: [f64; 3]) -> [f32; 2] {
    let pose = cam.true_pose().unwrap();
    let d = [0, 1, 2].map(|i| w[i] - pose.translation[i]);
    let r = pose.rotation;
    let depth = [0, 1, 2].map(|j| (r[0][j] * d[0] + r[1][j] * d[1] + r[2][j] * d[2]) as f32);
    let c = cam.depth_to_color().unwrap().transform(depth);
    cam.color_intrinsics().unwrap().project(c).unwrap()
}

/// Issue 51, item 2: a marker at the world origin (where docs/markers.md lays marker 0)
/// is drawn where it lies, not over the whole floor: a floor pixel far from it has the
/// colour it has with no marker at all (it had the marker's centre cell's, near black).
#[test]
fn a_marker_at_the_origin_leaves_the_rest_of_the_floor_its_colour() {
    let render = |markers: Vec<rgbd::scene::SceneMarker>| {
        let mut scene = floor_scene(1.2, Noise::D415);
        scene.markers = markers;
        scene.validate().unwrap();
        only_camera(&scene).render_color(1)
    };
    let marker = rgbd::scene::SceneMarker {
        family: "tag36h11".to_owned(),
        id: 0,
        size: 0.16,
        center: [0.0, 0.0],
        yaw_deg: 0.0,
        timeline: rgbd::scene::Timeline::default(),
    };
    let (with, without) = (render(vec![marker]), render(Vec::new()));
    // Image corners and edge middles: the floor, over 0.5 m from the marker.
    let (w, h) = (with.width - 1, with.height - 1);
    for (u, v) in [(0, 0), (w, 0), (0, h), (w, h), (w / 2, 0), (0, h / 2)] {
        let level = |f: &rgbd::ColorFrame| {
            f.rgb_at(u, v)
                .unwrap()
                .iter()
                .map(|&c| i32::from(c))
                .sum::<i32>()
                / 3
        };
        assert!(
            (level(&with) - level(&without)).abs() <= 12,
            "({u}, {v}): {} with the marker, {} without",
            level(&with),
            level(&without)
        );
    }
}

#[test]
fn a_floor_marker_is_drawn_with_its_family_pattern_where_the_color_camera_sees_it() {
    let mut scene = floor_scene(1.2, Noise::D415);
    scene.cameras[0].position = [0.3, -0.5, 1.2];
    scene.markers.push(rgbd::scene::SceneMarker {
        family: "tag36h11".to_owned(),
        id: 7,
        size: 0.16,
        center: [0.1, 0.05],
        yaw_deg: 30.0,
        timeline: rgbd::scene::Timeline::default(),
    });
    scene.validate().unwrap();
    let cam = only_camera(&scene);
    cam.set_color_settings(ColorSettings {
        format: ColorFormat::Rgb8,
        fps: 30,
        width: 1920,
        height: 1080,
    })
    .unwrap();
    let frame = cam.render_color(1);
    let gray: Vec<u8> = (0..frame.height as usize)
        .flat_map(|v| (0..frame.width as usize).map(move |u| (v, u)))
        .map(|(v, u)| {
            frame
                .rgb_at(u as u32, v as u32)
                .unwrap()
                .iter()
                .map(|&c| u32::from(c))
                .sum::<u32>() as u8
                / 3
        })
        .collect();
    let found = markers::detect(markers::Family::Tag36h11, &gray, 1920, 1080).unwrap();
    assert_eq!(found.len(), 1, "{found:?}");
    assert_eq!(found[0].id, 7);
    // The corners in marker order: (-, -), (+, -), (+, +), (-, +) in the marker frame.
    let yaw = 30f64.to_radians();
    for (corner, (sx, sy)) in
        found[0]
            .corners
            .iter()
            .zip([(-1.0, -1.0), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0)])
    {
        let (x, y) = (sx * 0.08, sy * 0.08);
        let w = [
            0.1 + x * yaw.cos() - y * yaw.sin(),
            0.05 + x * yaw.sin() + y * yaw.cos(),
            0.0,
        ];
        let want = color_pixel_of(&cam, w);
        let error = ((corner[0] - f64::from(want[0])).powi(2)
            + (corner[1] - f64::from(want[1])).powi(2))
        .sqrt();
        // The detector's sub-pixel edges are good to a few tenths of a pixel.
        assert!(
            error < 0.6,
            "corner {corner:?}, expected {want:?}: {error} px"
        );
    }
}

/// Mean and standard deviation of the first channel over the whole frame.
fn channel_stats(data: &[u8], bpp: usize) -> (f64, f64) {
    let values: Vec<f64> = data.chunks(bpp).map(|p| f64::from(p[0])).collect();
    let n = values.len() as f64;
    let mean = values.iter().sum::<f64>() / n;
    let var = values.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / n;
    (mean, var.sqrt())
}

#[test]
fn the_color_sensor_adds_noise_blur_and_exposure_only_when_asked() {
    use rgbd::scene::ColorSensor;
    let mut scene = floor_scene(1.0, Noise::D415);
    let clean = only_camera(&scene).render_color(1);
    assert!(scene.cameras[0].color_sensor.is_off());
    let (level, spread) = channel_stats(&clean.data, 3);
    assert_eq!(spread, 0.0, "the floor is evenly lit: one level");
    // Noise: its standard deviation follows noise * sqrt((level + 16) / 144).
    scene.cameras[0].color_sensor = ColorSensor {
        noise: 4.0,
        ..ColorSensor::default()
    };
    let cam = only_camera(&scene);
    let noisy = cam.render_color(1);
    let (mean, sigma) = channel_stats(&noisy.data, 3);
    let expected = 4.0 * ((level + 16.0) / 144.0).sqrt();
    assert!((mean - level).abs() < 0.1, "{mean} vs {level}");
    assert!(
        (sigma / expected - 1.0).abs() < 0.05,
        "{sigma} vs {expected}"
    );
    // New each frame, the same for the same frame.
    assert_eq!(noisy.data, cam.render_color(1).data);
    assert_ne!(noisy.data, cam.render_color(2).data);
    // Exposure multiplies the light, and clips at 255.
    scene.cameras[0].color_sensor = ColorSensor {
        exposure: 1.5,
        ..ColorSensor::default()
    };
    let bright = only_camera(&scene).render_color(1);
    let (mean, _) = channel_stats(&bright.data, 3);
    assert!(
        (mean - (level * 1.5).round()).abs() <= 1.0,
        "{mean} vs {level}"
    );
    scene.cameras[0].color_sensor.exposure = 10.0;
    assert!(
        only_camera(&scene)
            .render_color(1)
            .data
            .iter()
            .all(|&c| c == 255)
    );
    // Blur spreads an edge: the box's outline gets levels between the box's and the
    // floor's, which the sharp image has only where a pixel straddles it.
    let mut boxed = Scene::default_single();
    boxed.boxes[0].label = None;
    let between = |scene: &Scene| {
        let data = only_camera(scene).render_color(1).data;
        let row = &data[360 * 1280 * 3..361 * 1280 * 3];
        let floor = row[0];
        let lid = row[640 * 3];
        row.chunks(3)
            .filter(|p| p[0] > floor.min(lid) + 2 && p[0] < floor.max(lid) - 2)
            .count()
    };
    let sharp = between(&boxed);
    boxed.cameras[0].color_sensor.blur_px = 2.0;
    let blurred = between(&boxed);
    assert!(blurred >= sharp + 8, "{sharp} -> {blurred}");
    // Alpha stays opaque.
    let cam = only_camera(&boxed);
    cam.set_color_settings(ColorSettings {
        format: ColorFormat::Rgba8,
        fps: 30,
        width: 640,
        height: 480,
    })
    .unwrap();
    assert!(cam.render_color(1).data.chunks(4).all(|p| p[3] == 255));
}

#[test]
fn color_sensor_values_out_of_range_are_refused_naming_the_field() {
    let camera = "[[camera]]\nserial = \"000000000001\"\nposition = [0.0, 0.0, 1.0]\nlook_at = [0.0, 0.0, 0.0]\n";
    for (sensor, error) in [
        (
            "{ noise = -1.0 }",
            "camera[0].color_sensor.noise: must be from 0 to 64 levels, got -1",
        ),
        (
            "{ blur_px = 9.0 }",
            "camera[0].color_sensor.blur_px: must be from 0 to 8 pixels, got 9",
        ),
        (
            "{ exposure = 0.0 }",
            "camera[0].color_sensor.exposure: must be from 0.1 to 10, got 0",
        ),
    ] {
        let e = Scene::from_toml(&format!("{camera}color_sensor = {sensor}\n"))
            .unwrap_err()
            .to_string();
        assert_eq!(e, format!("scene: {error}"));
    }
    let e = Scene::from_toml(&format!("{camera}color_sensor = {{ gain = 2.0 }}\n"))
        .unwrap_err()
        .to_string();
    assert!(e.contains("unknown field `gain`"), "{e}");
    let ok = Scene::from_toml(&format!(
        "{camera}color_sensor = {{ noise = 2.5, blur_px = 0.7, exposure = 1.2 }}\n"
    ))
    .unwrap();
    let s = ok.cameras[0].color_sensor;
    assert_eq!((s.noise, s.blur_px, s.exposure), (2.5, 0.7, 1.2));
}
