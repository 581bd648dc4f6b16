use rgbd::scene::{LabelKind, Noise};
use rgbd::{Scene, SceneError};

/// The example scene of docs/design.md §7.
const DESIGN_EXAMPLE: &str = r#"
seed = 7
[floor]
z = 0.0
color = [120, 120, 120]

[[camera]]
serial = "840412060746"
position = [0.0, 0.0, 1.0]
look_at = [0.0, 0.0, 0.0]
up = [0.0, 1.0, 0.0]        # optional
noise = "d415"              # or "ideal"
calibrated = true           # preload the true camera->world transform into 3d-transformation

[[box]]
size = [0.40, 0.30, 0.20]   # length (along x before yaw), width, height
center = [0.0, 0.0]         # footprint centre on the floor
yaw_deg = 15.0
color = [180, 140, 90]
label = { kind = "qr", text = "PKG-0001", size = 0.08 }   # optional, on the top face

[[cylinder]]
radius = 0.10
height = 0.25
center = [0.3, -0.2]
"#;

fn error_of(text: &str) -> String {
    Scene::from_toml(text).unwrap_err().to_string()
}

#[test]
fn the_design_example_parses() {
    let scene = Scene::from_toml(DESIGN_EXAMPLE).unwrap();
    assert_eq!(scene.seed, 7);
    assert_eq!(scene.cameras[0].serial.as_str(), "840412060746");
    assert_eq!(scene.cameras[0].noise, Noise::D415);
    assert!(scene.cameras[0].calibrated);
    assert_eq!(scene.boxes[0].size, [0.40, 0.30, 0.20]);
    assert_eq!(scene.boxes[0].label.as_ref().unwrap().kind, LabelKind::Qr);
    assert_eq!(scene.cylinders[0].radius, 0.10);
}

#[test]
fn the_committed_scene_files_load_and_the_demo_file_is_the_built_in_demo() {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../scenes");
    let demo = Scene::load(&dir.join("demo.toml")).expect("scenes/demo.toml");
    assert_eq!(demo, Scene::default_demo());
    let code128 = Scene::load(&dir.join("code128.toml")).expect("scenes/code128.toml");
    let label = code128.boxes[0].label.as_ref().expect("a label");
    assert_eq!(label.kind, LabelKind::Code128);
}

#[test]
fn the_built_in_scenes_are_valid() {
    let single = Scene::default_single();
    single.validate().unwrap();
    assert_eq!(single.cameras.len(), 1);
    assert_eq!(single.boxes[0].size, [0.40, 0.30, 0.20]);
    assert_eq!(single.boxes[0].yaw_deg, 15.0);
    assert_eq!(single.cameras[0].position, [0.0, 0.0, 1.0]);
    let demo = Scene::default_demo();
    demo.validate().unwrap();
    assert_eq!(demo.cameras.len(), 2);
    assert!(demo.cameras.iter().all(|c| c.calibrated));
}

#[test]
fn scene_parse_errors_are_clear() {
    let bad_serial = DESIGN_EXAMPLE.replace("\"840412060746\"", "\"8404/1206\"");
    assert_eq!(
        error_of(&bad_serial),
        "scene: camera[0].serial: a serial number is 1 to 32 ASCII letters, digits, '-' and '_', \
         the first a letter or digit; got \"8404/1206\""
    );

    let negative =
        DESIGN_EXAMPLE.replace("size = [0.40, 0.30, 0.20]", "size = [0.40, -0.30, 0.20]");
    let e = error_of(&negative);
    assert!(e.starts_with("scene: box[0].size: must be positive"), "{e}");

    let zero_radius = DESIGN_EXAMPLE.replace("radius = 0.10", "radius = 0.0");
    assert!(error_of(&zero_radius).starts_with("scene: cylinder[0].radius: must be positive"));

    let big_label = DESIGN_EXAMPLE.replace("size = 0.08", "size = 0.35");
    let e = error_of(&big_label);
    assert!(
        e.contains("box[0].label.size") && e.contains("does not fit"),
        "{e}"
    );

    let unknown = DESIGN_EXAMPLE.replace("yaw_deg = 15.0", "yaw = 15.0");
    let e = error_of(&unknown);
    assert!(e.contains("unknown field `yaw`"), "{e}");
    assert!(e.contains("line"), "the TOML error points at the line: {e}");

    // At the key's own line (issue 51, item 13: an object's table also takes its finish
    // and timeline, and the error pointed at the table's `[[box]]` line).
    let line = unknown
        .lines()
        .position(|l| l.starts_with("yaw = "))
        .expect("the line")
        + 1;
    assert!(
        e.contains(&format!("at line {line}, column 1\n")),
        "not at line {line}: {e}"
    );
    assert!(e.contains(&format!("{line} | yaw = 15.0\n")), "{e}");
    let glossy =
        DESIGN_EXAMPLE.replace("center = [0.3, -0.2]", "center = [0.3, -0.2]\n  glos = 0.5");
    let e = error_of(&glossy);
    let line = glossy
        .lines()
        .position(|l| l.trim_start().starts_with("glos = "))
        .expect("the line")
        + 1;
    assert!(
        e.contains(&format!("at line {line}, column 3\n")) && e.contains("unknown field `glos`"),
        "not at line {line}: {e}"
    );

    let noise = DESIGN_EXAMPLE.replace("noise = \"d415\"", "noise = \"d435\"");
    let e = error_of(&noise);
    assert!(e.contains("d435") && e.contains("ideal"), "{e}");

    let same_place =
        DESIGN_EXAMPLE.replace("look_at = [0.0, 0.0, 0.0]", "look_at = [0.0, 0.0, 1.0]");
    assert_eq!(
        error_of(&same_place),
        "scene: camera[0].look_at: must differ from position"
    );

    let parallel_up = DESIGN_EXAMPLE.replace("up = [0.0, 1.0, 0.0]", "up = [0.0, 0.0, 1.0]");
    assert_eq!(
        error_of(&parallel_up),
        "scene: camera[0].up: must not be parallel to the view direction"
    );

    let twice = format!(
        "{DESIGN_EXAMPLE}\n[[camera]]\nserial = \"840412060746\"\nposition = [1.0, 0.0, 1.0]\nlook_at = [0.0, 0.0, 0.0]\n"
    );
    assert_eq!(
        error_of(&twice),
        "scene: camera[1].serial: 840412060746 is used by another camera"
    );

    let code128 = DESIGN_EXAMPLE.replace(
        "kind = \"qr\", text = \"PKG-0001\"",
        "kind = \"code128\", text = \"Größe\"",
    );
    assert!(error_of(&code128).contains("printable ASCII"));

    assert!(matches!(
        Scene::from_toml("seed = "),
        Err(SceneError::Parse(_))
    ));
    assert!(matches!(
        Scene::load(std::path::Path::new("/nonexistent/scene.toml")),
        Err(SceneError::Io { .. })
    ));
}

#[test]
fn scene_bounds_coordinates_sizes_counts_and_label_text_naming_the_field() {
    let far = DESIGN_EXAMPLE.replace("center = [0.3, -0.2]", "center = [0.3, -1000.5]");
    let e = error_of(&far);
    assert!(
        e.starts_with("scene: cylinder[0].center: must be finite numbers within"),
        "{e}"
    );
    let high = DESIGN_EXAMPLE.replace("position = [0.0, 0.0, 1.0]", "position = [0.0, 0.0, 1e6]");
    assert!(error_of(&high).starts_with("scene: camera[0].position:"));

    let huge = DESIGN_EXAMPLE.replace("size = [0.40, 0.30, 0.20]", "size = [0.40, 0.30, 100.5]");
    let e = error_of(&huge);
    assert!(e.starts_with("scene: box[0].size: must be positive"), "{e}");
    assert!(e.contains("at most 100 m"), "{e}");

    let mut scene = Scene::default_single();
    scene.cameras = (0..17)
        .map(|i| rgbd::scene::SceneCamera {
            serial: rgbd::Serial::parse(&format!("{}", 840_412_060_000_u64 + i)).unwrap(),
            ..scene.cameras[0].clone()
        })
        .collect();
    let e = scene.validate().unwrap_err().to_string();
    assert_eq!(e, "scene: camera: at most 16 cameras, got 17");

    let mut scene = Scene::default_single();
    scene.boxes = vec![scene.boxes[0].clone(); 200];
    scene.cylinders = vec![
        rgbd::scene::Cylinder {
            radius: 0.1,
            height: 0.2,
            center: [0.0, 0.0],
            color: [0, 0, 0],
            finish: rgbd::scene::Finish::default(),
            timeline: rgbd::scene::Timeline::default(),
        };
        57
    ];
    let e = scene.validate().unwrap_err().to_string();
    assert_eq!(
        e,
        "scene: box, cylinder, tube, bag: at most 256 boxes, cylinders, tubes and bags together, got 257"
    );
    scene.cylinders.pop();
    scene.validate().unwrap();

    let mut scene = Scene::default_single();
    if let Some(label) = scene.boxes[0].label.as_mut() {
        label.text = "A".repeat(257);
    }
    let e = scene.validate().unwrap_err().to_string();
    assert_eq!(
        e,
        "scene: box[0].label.text: at most 256 characters, got 257"
    );
}

#[test]
fn every_toml_example_of_docs_scenes_md_is_a_valid_scene() {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../docs/scenes.md");
    let text = std::fs::read_to_string(&path).unwrap();
    let blocks: Vec<&str> = text
        .split("```toml\n")
        .skip(1)
        .map(|b| b.split("```").next().unwrap())
        .collect();
    assert!(blocks.len() >= 3, "{} toml blocks", blocks.len());
    for block in blocks {
        if let Err(e) = Scene::from_toml(block) {
            panic!("{e} in\n{block}");
        }
    }
    let full = Scene::from_toml(
        text.split("```toml\n")
            .nth(1)
            .unwrap()
            .split("```")
            .next()
            .unwrap(),
    )
    .unwrap();
    assert_eq!((full.tubes.len(), full.bags.len()), (1, 1));
}
