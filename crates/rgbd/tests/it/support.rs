//! Helpers shared by the integration tests.

use rgbd::scene::{Floor, Noise, SceneCamera};
use rgbd::{Scene, Serial, SyntheticCamera};

pub(crate) fn serial(text: &str) -> Serial {
    Serial::parse(text).unwrap()
}

/// A scene with only the floor, seen straight down from `height_m`.
pub(crate) fn floor_scene(height_m: f64, noise: Noise) -> Scene {
    Scene {
        seed: 11,
        floor: Floor::default(),
        cameras: vec![SceneCamera {
            serial: serial("000000000001"),
            position: [0.0, 0.0, height_m],
            look_at: [0.0, 0.0, 0.0],
            up: Some([0.0, 1.0, 0.0]),
            noise,
            calibrated: true,
            stall_s: None,
            color_sensor: rgbd::scene::ColorSensor::default(),
        }],
        boxes: Vec::new(),
        cylinders: Vec::new(),
        tubes: Vec::new(),
        bags: Vec::new(),
        markers: Vec::new(),
    }
}

/// A scene of `objects` (TOML tables) under one camera, serial 000000000001, at
/// `position`, looking at the origin with world +y up in its image, with `noise` (`d415`
/// or `ideal`); its random choices seeded with `seed`.
pub(crate) fn under_one_camera(seed: u64, position: [f64; 3], noise: &str, objects: &str) -> Scene {
    let camera = format!(
        "seed = {seed}\n[[camera]]\nserial = \"000000000001\"\nposition = {position:?}\n\
         look_at = [0.0, 0.0, 0.0]\nup = [0.0, 1.0, 0.0]\nnoise = \"{noise}\"\n"
    );
    Scene::from_toml(&format!("{camera}\n{objects}")).unwrap()
}

/// The only camera of a scene.
pub(crate) fn only_camera(scene: &Scene) -> SyntheticCamera {
    SyntheticCamera::new(scene, &scene.cameras[0].serial).unwrap()
}
