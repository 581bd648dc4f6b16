//! `coapcam serve --depth-pngs DIR`: a folder that `coapcam grab depth` filled from a
//! synthetic camera, with that camera's `camera.toml`, served as a camera: a grab of depth
//! returns the PNG's pixels, in the order of the names and round again, and `measure`
//! finds the parcel the synthetic camera's server found; a folder the server cannot play
//! stops it, saying why.

use std::path::{Path, PathBuf};
use std::time::Duration;

use rgbd::{Camera as _, Scene, SyntheticCamera};

use crate::support::{COAPCAM, Finished, Proc, SN, TempDir, serve_with};

/// Bound on one command (the servers stop by themselves after 120 s).
const LIMIT: Duration = Duration::from_secs(110);

fn ok(args: &[&str]) -> Finished {
    Proc::run(COAPCAM, args, LIMIT).expect_success(&format!("coapcam {}", args.join(" ")))
}

fn path(p: &Path) -> &str {
    p.to_str().expect("UTF-8 path")
}

/// A scene file in `dir`: a noise-free D415 1 m above a 400 x 300 x 200 mm box, so that
/// every frame has the same pixels.
fn ideal_scene(dir: &Path) -> PathBuf {
    let scene = dir.join("ideal.toml");
    std::fs::write(
        &scene,
        format!(
            "[[camera]]\nserial = \"{SN}\"\nposition = [0.0, 0.0, 1.0]\nlook_at = [0.0, 0.0, 0.0]\n\
             noise = \"ideal\"\n[[box]]\nsize = [0.40, 0.30, 0.20]\ncenter = [0.0, 0.0]\nyaw_deg = 15.0\n"
        ),
    )
    .expect("writing the scene");
    scene
}

/// The `camera.toml` of the scene's camera, from the library's camera in its first mode,
/// which a new server's camera is in.
fn camera_toml(scene: &Path) -> String {
    let scene = Scene::load(scene).expect("the scene");
    let cameras = SyntheticCamera::all(&scene).expect("its cameras");
    let camera = cameras.first().expect("a camera");
    let k = camera.depth_intrinsics().expect("intrinsics");
    let baseline = camera
        .stereo_baseline_m()
        .map(|b| format!("baseline_m = {b:?}\n"))
        .unwrap_or_default();
    format!(
        "serial = \"{}\"\ndepth_scale = {:?}\n{baseline}[intrinsics]\nwidth = {}\nheight = {}\n\
         fx = {:?}\nfy = {:?}\nppx = {:?}\nppy = {:?}\nmodel = \"{}\"\ncoeffs = {:?}\n",
        camera.serial(),
        camera.depth_scale(),
        k.width,
        k.height,
        k.fx,
        k.fy,
        k.ppx,
        k.ppy,
        k.model.name(),
        k.coeffs
    )
}

/// The size and the raw units of a 16-bit grayscale PNG.
fn units(png: &Path) -> (u32, u32, Vec<u16>) {
    match image::open(png).unwrap_or_else(|e| panic!("{}: {e}", png.display())) {
        image::DynamicImage::ImageLuma16(units) => {
            (units.width(), units.height(), units.into_raw())
        }
        other => panic!("{} is {:?}", png.display(), other.color()),
    }
}

/// What a `measure --json` document says of the parcel: found or not, where, how large.
fn parcel(m: &serde_json::Value) -> [&serde_json::Value; 8] {
    [
        "parcel",
        "length_mm",
        "width_mm",
        "height_mm",
        "yaw_deg",
        "unrounded_mm",
        "corners_m",
        "parcel_points",
    ]
    .map(|key| &m[key])
}

#[test]
fn a_folder_grabbed_from_a_synthetic_camera_serves_its_pixels_and_measures_its_parcel() {
    let dir = TempDir::new("depth-pngs");
    let scene = ideal_scene(dir.path());
    let synthetic_state = TempDir::new("depth-pngs-synthetic");
    let (_synthetic, a) = serve_with(synthetic_state.path(), &["--scene", path(&scene)]);
    let a = format!("coap://{a}");
    let frames = dir.join("frames");
    std::fs::create_dir(&frames).expect("the folder");
    let first = frames.join("0001.png");
    ok(&["grab", "depth", "--server", &a, "-o", path(&first)]);
    std::fs::write(frames.join("camera.toml"), camera_toml(&scene)).expect("camera.toml");
    let transformation = ok(&["get", &format!("{a}/cams/{SN}/3d-transformation")]).stdout_text();
    let measured = ok(&["measure", "--server", &a, "--json"]).json();
    assert_eq!(measured["parcel"], "measured", "{measured}");

    let state = TempDir::new("depth-pngs-served");
    let (_served, b) = serve_with(state.path(), &["--depth-pngs", path(&frames)]);
    let b = format!("coap://{b}");
    let got = dir.join("got.png");
    ok(&["grab", "depth", "--server", &b, "-o", path(&got)]);
    assert!(units(&got) == units(&first), "the served depth differs");
    ok(&[
        "put",
        &format!("{b}/cams/{SN}/3d-transformation"),
        "--payload",
        transformation.trim(),
    ]);
    let m = ok(&["measure", "--server", &b, "--json"]).json();
    assert_eq!(parcel(&m), parcel(&measured), "{m}\n{measured}");
}

#[test]
fn the_frames_are_served_in_the_order_of_their_names_and_round_again() {
    let dir = TempDir::new("depth-pngs-order");
    let frames = dir.join("frames");
    std::fs::create_dir(&frames).expect("the folder");
    std::fs::write(
        frames.join("camera.toml"),
        format!(
            "serial = \"{SN}\"\ndepth_scale = 0.001\n\
             [intrinsics]\nwidth = 4\nheight = 3\nfx = 4.0\nfy = 4.0\nppx = 2.0\nppy = 1.5\n"
        ),
    )
    .expect("camera.toml");
    // Named so that their order is not the order they are written in.
    let names = ["b.png", "a.png", "c.png"];
    for (i, name) in names.iter().enumerate() {
        let value = 1000 * (u16::try_from(i).expect("small") + 1);
        image::ImageBuffer::from_pixel(4, 3, image::Luma([value]))
            .save(frames.join(name))
            .expect("a PNG");
    }
    let state = TempDir::new("depth-pngs-order-served");
    let (_served, b) = serve_with(state.path(), &["--depth-pngs", path(&frames)]);
    let b = format!("coap://{b}");
    let got = dir.join("got.png");
    for name in ["a.png", "b.png", "c.png", "a.png"] {
        ok(&["grab", "depth", "--server", &b, "-o", path(&got)]);
        assert!(units(&got) == units(&frames.join(name)), "not {name}");
    }
}

#[test]
fn a_folder_the_server_cannot_play_stops_it_saying_why() {
    let dir = TempDir::new("depth-pngs-bad");
    let toml = "serial = \"rec-1\"\ndepth_scale = 0.001\n\
                [intrinsics]\nwidth = 4\nheight = 3\nfx = 4.0\nfy = 4.0\nppx = 2.0\nppy = 1.5\n";
    let folder = |name: &str, png: Option<image::DynamicImage>| {
        let f = dir.join(name);
        std::fs::create_dir(&f).expect("a folder");
        std::fs::write(f.join("camera.toml"), toml).expect("camera.toml");
        if let Some(png) = png {
            png.save(f.join("0001.png")).expect("a PNG");
        }
        f
    };
    let gray16 =
        |width, height| image::DynamicImage::ImageLuma16(image::ImageBuffer::new(width, height));
    let gray8 = image::DynamicImage::ImageLuma8(image::ImageBuffer::new(4, 3));
    let eight_bit = folder("eight-bit", Some(gray8));
    let bigger = folder("bigger", Some(gray16(5, 3)));
    let empty = folder("empty", None);
    let unknown_model = folder("model", Some(gray16(4, 3)));
    std::fs::write(
        unknown_model.join("camera.toml"),
        format!("{toml}model = \"fisheye\"\n"),
    )
    .expect("camera.toml");
    let missing = dir.join("missing");
    let cases = [
        (&missing, format!("reading {}", missing.display())),
        (
            &empty,
            format!("no .png file in {}: a depth frame", empty.display()),
        ),
        (
            &eight_bit,
            format!(
                "{} is L8, not a 16-bit grayscale PNG",
                eight_bit.join("0001.png").display()
            ),
        ),
        (
            &bigger,
            format!(
                "{} is 5x3, but camera.toml's intrinsics are 4x3",
                bigger.join("0001.png").display()
            ),
        ),
        (
            &unknown_model,
            "intrinsics.model \"fisheye\" is none of None, ".to_owned(),
        ),
    ];
    for (folder, said) in cases {
        let state = TempDir::new("depth-pngs-bad-state");
        let f = Proc::run(
            COAPCAM,
            &[
                "serve",
                "--bind",
                "127.0.0.1:0",
                "--state-dir",
                path(state.path()),
                "--duration",
                "10",
                "--depth-pngs",
                path(folder),
            ],
            LIMIT,
        );
        assert!(!f.status.success(), "{}: served", folder.display());
        assert!(f.stderr.contains(&said), "{said:?} in {}", f.stderr);
    }
}
