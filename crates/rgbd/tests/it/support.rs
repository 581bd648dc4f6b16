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

/// The only camera of a scene.
pub(crate) fn only_camera(scene: &Scene) -> SyntheticCamera {
    SyntheticCamera::new(scene, &scene.cameras[0].serial).unwrap()
}
