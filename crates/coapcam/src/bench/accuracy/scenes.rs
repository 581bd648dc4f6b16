//! The scenes of `bench accuracy`: seeded synthetic parcels, one plain box each, seen by
//! calibrated D415s above it, or (`--calibrate`) by uncalibrated, tilted ones with a table
//! of tag36h11 markers to calibrate them on.

use rand_chacha::ChaCha8Rng;
use rand_core::{RngCore as _, SeedableRng as _};
use rgbd::scene::{Finish, Noise, SceneBox, SceneCamera, SceneMarker, Timeline};
use rgbd::{Scene, Serial};

/// Half fields of view of the D415 depth stream, degrees (wide and narrow axis).
const DEPTH_HALF_FOV_DEG: [f64; 2] = [32.5, 21.0];

fn uniform(rng: &mut ChaCha8Rng, lo: f64, hi: f64) -> f64 {
    let unit = (rng.next_u64() >> 11) as f64 / (1u64 << 53) as f64;
    lo + (hi - lo) * unit
}

/// Scene `index` of the set: a box with random size, yaw and position near the origin,
/// seen by one camera above it (even indices) or two cameras on either end of its long
/// side (odd ones), turned so the long side runs along the image's wide axis and high
/// enough that the whole lid is in view.
pub fn scene(seed: u64, index: usize) -> anyhow::Result<Scene> {
    let mut rng =
        ChaCha8Rng::seed_from_u64(seed.wrapping_mul(1_000_003).wrapping_add(index as u64));
    let (length, width) = {
        let a = uniform(&mut rng, 0.10, 0.80);
        let b = uniform(&mut rng, 0.10, 0.80);
        (a.max(b), a.min(b))
    };
    let two = index % 2 == 1;
    let offset = if two { 0.12 } else { 0.0 };
    // A camera `d` above the lid sees d * tan(half angle) either side of its axis; keep
    // 15 % of margin.
    let [wide, narrow] = DEPTH_HALF_FOV_DEG.map(|a| a.to_radians().tan() * 0.85);
    let needed = ((length / 2.0 + offset) / wide).max(width / 2.0 / narrow);
    let height_max = (1.5 - needed).min(0.60);
    let height = uniform(&mut rng, 0.02, height_max.max(0.02));
    let camera_z = uniform(&mut rng, (height + needed).max(0.8), 1.5).min(1.5);
    let yaw_deg = uniform(&mut rng, 0.0, 90.0);
    let center = [
        uniform(&mut rng, -0.05, 0.05),
        uniform(&mut rng, -0.05, 0.05),
    ];
    let (sin, cos) = yaw_deg.to_radians().sin_cos();
    // Up in the image is the box's width axis, so the image's x runs along its length.
    let up = [-sin, cos, 0.0];
    let camera = |n: u64, along: f64, z: f64| -> anyhow::Result<SceneCamera> {
        Ok(SceneCamera {
            serial: Serial::parse(&format!("{:012}", 840_412_060_700 + n))
                .map_err(|e| anyhow::anyhow!("{e}"))?,
            position: [center[0] + along * cos, center[1] + along * sin, z],
            look_at: [center[0], center[1], height],
            up: Some(up),
            noise: Noise::D415,
            calibrated: true,
            stall_s: None,
            color_sensor: rgbd::scene::ColorSensor::default(),
        })
    };
    let cameras = if two {
        vec![
            camera(1, offset, camera_z)?,
            camera(2, -offset, camera_z - 0.05)?,
        ]
    } else {
        vec![camera(0, 0.0, camera_z)?]
    };
    Ok(parcel_scene(
        rng.next_u64(),
        cameras,
        [length, width, height],
        center,
        yaw_deg,
    ))
}

/// A scene of one plain box (no label) seen by `cameras`.
fn parcel_scene(
    seed: u64,
    cameras: Vec<SceneCamera>,
    size: [f64; 3],
    center: [f64; 2],
    yaw_deg: f64,
) -> Scene {
    Scene {
        seed,
        cameras,
        boxes: vec![SceneBox {
            size,
            center,
            yaw_deg,
            color: [180, 140, 90],
            label: None,
            finish: Finish::default(),
            timeline: Timeline::default(),
        }],
        ..Scene::default_single()
    }
}

/// The markers of the calibration table: a 5 x 5 grid 0.22 m apart, 12 cm wide, id 0
/// (the origin) in the middle at the world's origin, the others turned by 15 degree steps.
fn marker_grid() -> Vec<SceneMarker> {
    let mut grid = Vec::with_capacity(25);
    let mut id = 1;
    for row in -2i32..=2 {
        for col in -2i32..=2 {
            let origin = row == 0 && col == 0;
            grid.push(SceneMarker {
                family: "tag36h11".to_owned(),
                id: if origin { 0 } else { id },
                size: 0.12,
                center: [f64::from(col) * 0.22, f64::from(row) * 0.22],
                yaw_deg: if origin {
                    0.0
                } else {
                    f64::from(id % 6) * 15.0
                },
                timeline: Timeline::default(),
            });
            id += u32::from(!origin);
        }
    }
    grid
}

/// Scene `index` of the `--calibrate` set, as (the parcel's scene, the empty table's): a
/// box 10-60 cm wide and 2-40 cm high near the origin, seen by one to three uncalibrated
/// cameras spread around it, each 0.8-1.6 m from the centre of its lid (far enough that
/// the whole lid is in view) and tilted 0-35 degrees from straight down; the table has
/// the same cameras and `marker_grid` instead of the box.
pub fn calibration_scenes(seed: u64, index: usize) -> anyhow::Result<(Scene, Scene)> {
    let mut rng = ChaCha8Rng::seed_from_u64(
        seed.wrapping_mul(1_000_033)
            .wrapping_add(index as u64)
            .wrapping_add(0xca1b),
    );
    let (length, width) = {
        let a = uniform(&mut rng, 0.10, 0.60);
        let b = uniform(&mut rng, 0.10, 0.60);
        (a.max(b), a.min(b))
    };
    let height = uniform(&mut rng, 0.02, 0.40);
    let yaw_deg = uniform(&mut rng, 0.0, 90.0);
    let center = [
        uniform(&mut rng, -0.05, 0.05),
        uniform(&mut rng, -0.05, 0.05),
    ];
    // The lid's half diagonal within 85 % of the narrow half angle.
    let narrow = DEPTH_HALF_FOV_DEG[1].to_radians().tan() * 0.85;
    let needed = (length.hypot(width) / 2.0 / narrow).max(0.8);
    let count = index % 3 + 1;
    let azimuth = uniform(&mut rng, 0.0, 360.0);
    let mut cameras = Vec::with_capacity(count);
    for k in 0..count {
        let distance = uniform(&mut rng, needed, 1.6_f64.max(needed));
        let tilt = uniform(&mut rng, if count == 1 { 0.0 } else { 10.0 }, 35.0).to_radians();
        let turn = (azimuth + 360.0 * k as f64 / count as f64 + uniform(&mut rng, -20.0, 20.0))
            .to_radians();
        let lid = [center[0], center[1], height];
        cameras.push(SceneCamera {
            serial: Serial::parse(&format!("{:012}", 840_412_060_800 + k))
                .map_err(|e| anyhow::anyhow!("{e}"))?,
            position: [
                lid[0] + distance * tilt.sin() * turn.cos(),
                lid[1] + distance * tilt.sin() * turn.sin(),
                lid[2] + distance * tilt.cos(),
            ],
            look_at: lid,
            up: None,
            noise: Noise::D415,
            calibrated: false,
            stall_s: None,
            color_sensor: rgbd::scene::ColorSensor::default(),
        });
    }
    let parcel = parcel_scene(
        rng.next_u64(),
        cameras,
        [length, width, height],
        center,
        yaw_deg,
    );
    let table = Scene {
        boxes: Vec::new(),
        markers: marker_grid(),
        ..parcel.clone()
    };
    parcel.validate()?;
    table.validate()?;
    Ok((parcel, table))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_scene_set_covers_the_ranges_and_is_reproducible() {
        let scenes: Vec<Scene> = (0..40).map(|i| scene(1, i).unwrap()).collect();
        assert_eq!(scenes[7], scene(1, 7).unwrap());
        let boxes: Vec<&SceneBox> = scenes.iter().map(|s| &s.boxes[0]).collect();
        for b in &boxes {
            assert!(
                b.size[0] >= 0.1 && b.size[0] <= 0.8 && b.size[1] >= 0.1,
                "{b:?}"
            );
            assert!(b.size[2] >= 0.02 && b.size[2] <= 0.6, "{b:?}");
            assert!((0.0..=90.0).contains(&b.yaw_deg));
        }
        for s in &scenes {
            for c in &s.cameras {
                assert!(c.position[2] >= 0.75 && c.position[2] <= 1.5, "{c:?}");
            }
        }
        assert!(scenes.iter().any(|s| s.cameras.len() == 2));
        assert!(scenes.iter().any(|s| s.cameras.len() == 1));
    }

    #[test]
    fn the_calibration_set_has_one_to_three_uncalibrated_tilted_cameras_and_a_marker_table() {
        let sets: Vec<(Scene, Scene)> =
            (0..30).map(|i| calibration_scenes(1, i).unwrap()).collect();
        assert_eq!(sets[4], calibration_scenes(1, 4).unwrap());
        let mut tilts = Vec::new();
        for (i, (parcel, table)) in sets.iter().enumerate() {
            assert_eq!(parcel.cameras.len(), i % 3 + 1);
            assert_eq!(parcel.cameras, table.cameras);
            assert!(table.boxes.is_empty() && table.markers.len() == 25);
            assert!(parcel.markers.is_empty());
            let b = &parcel.boxes[0];
            assert!(
                b.size[0] <= 0.6 && b.size[1] >= 0.1 && b.size[2] <= 0.4,
                "{b:?}"
            );
            for c in &parcel.cameras {
                assert!(!c.calibrated);
                let d: Vec<f64> = (0..3).map(|k| c.position[k] - c.look_at[k]).collect();
                let distance = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
                assert!((0.8..=1.6).contains(&distance), "{c:?}");
                let tilt = (d[2] / distance).acos().to_degrees();
                assert!(tilt <= 35.0, "{c:?}");
                tilts.push(tilt);
            }
        }
        assert!(tilts.iter().any(|t| *t > 30.0) && tilts.iter().any(|t| *t < 10.0));
        let origin = &sets[0].1.markers.iter().find(|m| m.id == 0).unwrap();
        assert_eq!((origin.center, origin.yaw_deg), ([0.0, 0.0], 0.0));
    }
}
