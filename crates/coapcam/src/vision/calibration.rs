//! A camera's pose from markers on the floor (docs/design.md, "Calibration").
//!
//! 1. The corners of every known marker the color image shows give the color camera's
//!    pose by PnP (a plane's homography, refined on the reprojection error).
//! 2. Through the depth->color extrinsics that pose selects the depth points near the
//!    floor; a least-squares plane of them (two passes, 50 then 20 mm) gives roll, pitch
//!    and the camera's height, far better than the corners of a small marker can.
//! 3. The corners' rays, met with that plane, are points of the floor; the rigid motion
//!    of the plane that lays them onto the map's corners gives yaw and the position.
//!
//! The world frame is the origin marker's: its centre at (0, 0, 0), z up, x along the
//! marker's x axis. Every other marker counts only through a map of where it lies.

use nalgebra::{Isometry3, Matrix3, Rotation2, Rotation3, UnitQuaternion, Vector2, Vector3};

use geometry::{Point3, Sighting, Transformation, floor_transformation, plane_near};
use markers::{Detection, Family};
use rgbd::intrinsics::pixel_to_ray;
use rgbd::{Extrinsics, Intrinsics, Scene};

/// The first floor pass keeps depth points this close to the floor the markers give.
const FLOOR_BAND_M: f64 = 0.05;
/// The second pass keeps points this close to the first pass's plane.
const FLOOR_INLIER_M: f64 = 0.02;
/// Fewer floor points than this and the camera is refused.
pub const MIN_FLOOR_POINTS: usize = 2_000;

/// A marker of the map, in the origin marker's frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MapMarker {
    /// Its id.
    pub id: u32,
    /// Side of its black square, metres.
    pub size: f64,
    /// Its centre on the floor.
    pub center: Vector2<f64>,
    /// Its x axis's angle from the world's x axis, radians.
    pub yaw: f64,
}

impl MapMarker {
    /// Its corners on the floor, in [`Detection::corners`]'s order.
    fn corners(&self) -> [Vector2<f64>; 4] {
        let h = self.size / 2.0;
        let turn = Rotation2::new(self.yaw);
        [(-h, -h), (h, -h), (h, h), (-h, h)].map(|(x, y)| self.center + turn * Vector2::new(x, y))
    }
}

/// Where the markers lie: the origin marker at (0, 0) with yaw 0, every other one
/// relative to it.
#[derive(Debug, Clone, PartialEq)]
pub struct MarkerMap {
    /// Their family.
    pub family: Family,
    /// The id of the marker that defines the world frame.
    pub origin: u32,
    markers: Vec<MapMarker>,
}

/// A scene's markers do not make a map.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum MapError {
    /// The origin marker is not among the scene's markers of the family.
    #[error("the map has no {family} marker {origin} (the origin); it has {ids:?}")]
    NoOrigin {
        /// The markers' family.
        family: Family,
        /// The origin's id.
        origin: u32,
        /// The ids of the family's markers the scene has.
        ids: Vec<u32>,
    },
    /// Two markers of the family have the same id.
    #[error("the map has {family} marker {id} twice")]
    Twice {
        /// The markers' family.
        family: Family,
        /// The id.
        id: u32,
    },
}

impl MarkerMap {
    /// A map of the origin marker alone, `size` metres wide.
    pub fn single(family: Family, origin: u32, size: f64) -> Self {
        Self {
            family,
            origin,
            markers: vec![MapMarker {
                id: origin,
                size,
                center: Vector2::zeros(),
                yaw: 0.0,
            }],
        }
    }

    /// The markers of `family` in a scene file's `[[marker]]` tables, expressed in the
    /// frame of marker `origin`, which must be among them.
    pub fn from_scene(scene: &Scene, family: Family, origin: u32) -> Result<Self, MapError> {
        let name = family.to_string();
        let of_family: Vec<_> = scene.markers.iter().filter(|m| m.family == name).collect();
        let Some(o) = of_family.iter().find(|m| m.id == origin) else {
            return Err(MapError::NoOrigin {
                family,
                origin,
                ids: of_family.iter().map(|m| m.id).collect(),
            });
        };
        let (o_center, o_yaw) = (Vector2::from(o.center), o.yaw_deg.to_radians());
        let to_origin = Rotation2::new(-o_yaw);
        let mut markers = Vec::with_capacity(of_family.len());
        for m in &of_family {
            if markers.iter().any(|k: &MapMarker| k.id == m.id) {
                return Err(MapError::Twice { family, id: m.id });
            }
            markers.push(MapMarker {
                id: m.id,
                size: m.size,
                center: to_origin * (Vector2::from(m.center) - o_center),
                yaw: m.yaw_deg.to_radians() - o_yaw,
            });
        }
        Ok(Self {
            family,
            origin,
            markers,
        })
    }

    /// The map's marker `id`.
    pub fn get(&self, id: u32) -> Option<&MapMarker> {
        self.markers.iter().find(|m| m.id == id)
    }
}

/// What a camera shows, as `calibrate` grabbed it.
#[derive(Debug, Clone, Copy)]
pub struct CameraView<'a> {
    /// The markers found in the color image.
    pub detections: &'a [Detection],
    /// The color camera's intrinsics.
    pub color: &'a Intrinsics,
    /// Where a depth-frame point lies in the color camera's frame.
    pub depth_to_color: &'a Extrinsics,
    /// The depth image's points, in the depth camera's frame, metres.
    pub depth_points: &'a [Point3],
}

/// A camera's calibration.
#[derive(Debug, Clone, PartialEq)]
pub struct Calibration {
    /// Depth frame -> world: the 3d-transformation's rotation and translation.
    pub depth_to_world: Isometry3<f64>,
    /// The map's markers seen, which placed the camera.
    pub used: Vec<u32>,
    /// Markers seen that the map does not hold (ignored).
    pub unknown: Vec<u32>,
    /// Root mean square distance of the corners from where the pose projects them, px.
    pub reprojection_px: f64,
    /// Depth points on the floor.
    pub floor_points: usize,
    /// Their root mean square distance from the fitted floor, metres.
    pub floor_rms_m: f64,
}

impl Calibration {
    /// The 3d-transformation document of this pose.
    pub fn transformation(&self) -> Transformation {
        Transformation::rigid(
            *self.depth_to_world.rotation.to_rotation_matrix().matrix(),
            self.depth_to_world.translation.vector,
        )
    }

    /// How far this pose is from `truth`: position (mm) and angle (degrees).
    pub fn error_from(&self, truth: &rgbd::Pose) -> [f64; 2] {
        let t = pose_isometry(truth);
        let position = (self.depth_to_world.translation.vector - t.translation.vector).norm();
        let angle = self.depth_to_world.rotation.angle_to(&t.rotation);
        [position * 1000.0, angle.to_degrees()]
    }
}

/// A known pose (depth frame -> world) as an isometry.
fn pose_isometry(pose: &rgbd::Pose) -> Isometry3<f64> {
    isometry(
        Matrix3::from_row_slice(&pose.rotation.concat()),
        Vector3::from(pose.translation),
    )
}

/// The 3d-transformation document of a known pose (depth frame -> world).
pub fn pose_transformation(pose: &rgbd::Pose) -> Transformation {
    Transformation::rigid(
        Matrix3::from_row_slice(&pose.rotation.concat()),
        Vector3::from(pose.translation),
    )
}

/// Why a camera could not be calibrated.
#[derive(Debug, thiserror::Error)]
pub enum CalibrationError {
    /// None of the map's markers is in the image.
    #[error("sees no marker of the map ({family} {known:?}); markers seen: {seen:?}")]
    NoMarker {
        /// The map's family.
        family: Family,
        /// The map's ids.
        known: Vec<u32>,
        /// What the image showed.
        seen: Vec<u32>,
    },
    /// The corners admit no pose (degenerate).
    #[error("the markers' corners give no camera pose")]
    NoPose,
    /// Too little floor in the depth image.
    #[error(
        "only {0} depth points lie near the floor the markers give (at least {MIN_FLOOR_POINTS} needed); does its depth see the floor, or does a roi3d cut it away?"
    )]
    NoFloor(usize),
}

fn isometry(rotation: Matrix3<f64>, translation: Vector3<f64>) -> Isometry3<f64> {
    let rotation =
        UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(rotation));
    Isometry3::from_parts(translation.into(), rotation)
}

/// Depth frame -> color frame, from the extrinsics (rotation column-major).
fn depth_to_color(e: &Extrinsics) -> Isometry3<f64> {
    let r = Matrix3::from_column_slice(&e.rotation.map(f64::from));
    isometry(r, Vector3::from(e.translation.map(f64::from)))
}

/// The camera's pose in the map's frame (see the module's documentation).
pub fn calibrate(view: &CameraView<'_>, map: &MarkerMap) -> Result<Calibration, CalibrationError> {
    let mut used = Vec::new();
    let mut unknown = Vec::new();
    let mut sightings = Vec::new();
    for d in view.detections {
        let Some(m) = map.get(d.id) else {
            unknown.push(d.id);
            continue;
        };
        if used.contains(&d.id) {
            continue; // the same id twice in one image (a misread): the first counts
        }
        used.push(d.id);
        for (pixel, world) in d.corners.iter().zip(m.corners()) {
            let ray = pixel_to_ray(view.color, [pixel[0] as f32, pixel[1] as f32]);
            sightings.push(Sighting {
                world,
                ray: Vector2::new(f64::from(ray[0]), f64::from(ray[1])),
            });
        }
    }
    if used.is_empty() {
        return Err(CalibrationError::NoMarker {
            family: map.family,
            known: map.markers.iter().map(|m| m.id).collect(),
            seen: unknown,
        });
    }
    let world_to_color = geometry::planar_pnp(&sightings).ok_or(CalibrationError::NoPose)?;
    let depth_to_color = depth_to_color(view.depth_to_color);
    let first_guess = world_to_color.inverse() * depth_to_color;

    // The floor z = 0 of the first guess, in the depth frame: normal · p + offset = 0.
    let normal = first_guess.rotation.inverse() * Vector3::z();
    let offset = first_guess.translation.vector.z;
    let floor = plane_near(view.depth_points, normal, offset, FLOOR_BAND_M)
        .and_then(|p| plane_near(view.depth_points, p.normal, p.offset, FLOOR_INLIER_M))
        .map_err(|_| CalibrationError::NoFloor(0))?;
    if floor.inliers < MIN_FLOOR_POINTS {
        return Err(CalibrationError::NoFloor(floor.inliers));
    }
    let level = floor_transformation(&floor);

    // The corners' rays from the color camera's centre, met with the floor, levelled.
    let color_to_depth = depth_to_color.inverse();
    let origin = color_to_depth.translation.vector;
    let mut on_floor = Vec::with_capacity(sightings.len());
    for s in &sightings {
        let direction = color_to_depth.rotation * Vector3::new(s.ray.x, s.ray.y, 1.0);
        let along = floor.normal.dot(&direction);
        if along.abs() < 1e-9 {
            return Err(CalibrationError::NoPose);
        }
        let point = origin + direction * (-(floor.normal.dot(&origin) + floor.offset) / along);
        on_floor.push((level.rotation * point + level.translation).xy());
    }
    let world: Vec<Vector2<f64>> = sightings.iter().map(|s| s.world).collect();
    let (yaw, shift) = geometry::rigid_2d(&on_floor, &world).ok_or(CalibrationError::NoPose)?;
    let turn = Rotation3::from_axis_angle(&Vector3::z_axis(), yaw);
    let depth_to_world = isometry(
        turn * level.rotation,
        turn * level.translation + Vector3::new(shift.x, shift.y, 0.0),
    );

    let world_to_color = depth_to_color * depth_to_world.inverse();
    let reprojection_px =
        geometry::reprojection_rms(&sightings, &world_to_color) * f64::from(view.color.fx);
    Ok(Calibration {
        depth_to_world,
        used,
        unknown,
        reprojection_px,
        floor_points: floor.inliers,
        floor_rms_m: floor.rms,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use rgbd::{Camera as _, ColorFormat, ColorSettings, SyntheticCamera};

    /// A scene of one D415 (noise on) at `position` looking at `look_at`, two tag36h11
    /// markers on the floor and a box.
    fn scene(position: [f64; 3], look_at: [f64; 3]) -> Scene {
        Scene::from_toml(&format!(
            "seed = 3\n\
             [[camera]]\nserial = \"000000000001\"\nposition = {position:?}\nlook_at = {look_at:?}\ncalibrated = false\n\
             [[marker]]\nfamily = \"tag36h11\"\nid = 0\nsize = 0.16\ncenter = [0.0, 0.0]\n\
             [[marker]]\nfamily = \"tag36h11\"\nid = 5\nsize = 0.16\ncenter = [0.45, 0.25]\nyaw_deg = 40.0\n\
             [[box]]\nsize = [0.3, 0.2, 0.15]\ncenter = [-0.35, 0.3]\n"
        ))
        .expect("a valid scene")
    }

    /// What the synthetic camera shows, and its true pose (depth -> world).
    struct Shown {
        detections: Vec<Detection>,
        color: Intrinsics,
        extrinsics: Extrinsics,
        points: Vec<Point3>,
        truth: rgbd::Pose,
    }

    impl Shown {
        fn view(&self) -> CameraView<'_> {
            CameraView {
                detections: &self.detections,
                color: &self.color,
                depth_to_color: &self.extrinsics,
                depth_points: &self.points,
            }
        }
    }

    /// What the scene's camera shows; with `noise` above 0 the color image gets a 3 x 3
    /// box blur and uniform noise of +-`noise` gray levels, as a lens and sensor add.
    fn grab_with(scene: &Scene, noise: u8) -> Shown {
        let mut truth = scene.clone();
        truth.cameras[0].calibrated = true;
        let cam = SyntheticCamera::new(&truth, &truth.cameras[0].serial).expect("camera");
        cam.set_color_settings(ColorSettings {
            format: ColorFormat::Rgb8,
            fps: 30,
            width: 1920,
            height: 1080,
        })
        .expect("full resolution");
        let color = cam.render_color(1);
        let mut gray: Vec<u8> = color
            .data
            .chunks_exact(3)
            .map(|p| ((u16::from(p[0]) + u16::from(p[1]) + u16::from(p[2])) / 3) as u8)
            .collect();
        if noise > 0 {
            let (w, h) = (1920usize, 1080usize);
            let sharp = gray.clone();
            let mut state = 0x2545_f491_4f6c_dd1d_u64;
            for y in 1..h - 1 {
                for x in 1..w - 1 {
                    let sum: u32 = (0..9)
                        .map(|k| u32::from(sharp[(y + k / 3 - 1) * w + x + k % 3 - 1]))
                        .sum();
                    state ^= state << 13;
                    state ^= state >> 7;
                    state ^= state << 17;
                    let n = (state % (2 * u64::from(noise) + 1)) as i32 - i32::from(noise);
                    gray[y * w + x] = (sum as i32 / 9 + n).clamp(0, 255) as u8;
                }
            }
        }
        let detections = markers::detect(Family::Tag36h11, &gray, 1920, 1080).expect("detect");
        let depth = cam.render_depth(1);
        let points =
            rgbd::deproject_frame(&depth, &cam.depth_intrinsics().expect("k")).expect("points");
        Shown {
            detections,
            color: cam.color_intrinsics().expect("k"),
            extrinsics: cam.depth_to_color().expect("e"),
            points,
            truth: cam.true_pose().expect("pose"),
        }
    }

    #[test]
    fn a_map_without_its_origin_or_with_a_marker_twice_says_so() {
        let scene = scene([0.9, -1.1, 1.3], [0.1, 0.1, 0.0]);
        let no_origin = MarkerMap::from_scene(&scene, Family::Tag36h11, 7).map(|m| m.origin);
        assert_eq!(
            no_origin,
            Err(MapError::NoOrigin {
                family: Family::Tag36h11,
                origin: 7,
                ids: vec![0, 5],
            })
        );
        assert_eq!(
            no_origin.expect_err("no marker 7").to_string(),
            "the map has no tag36h11 marker 7 (the origin); it has [0, 5]"
        );
        let mut twice = scene.clone();
        twice.markers.push(scene.markers[1].clone());
        let twice = MarkerMap::from_scene(&twice, Family::Tag36h11, 0).map(|m| m.origin);
        assert_eq!(
            twice.expect_err("marker 5 twice").to_string(),
            "the map has tag36h11 marker 5 twice"
        );
    }

    #[test]
    fn a_tilted_camera_is_placed_within_2_mm_and_0_2_degrees_by_two_mapped_markers() {
        let scene = scene([0.9, -1.1, 1.3], [0.1, 0.1, 0.0]);
        let shown = grab_with(&scene, 0);
        let map = MarkerMap::from_scene(&scene, Family::Tag36h11, 0).expect("map");
        let view = shown.view();
        let c = calibrate(&view, &map).expect("calibrated");
        let [mm, deg] = c.error_from(&shown.truth);
        eprintln!("{c:?}: {mm:.2} mm, {deg:.3} deg");
        assert_eq!(c.used.len(), 2, "{c:?}");
        assert!(mm < 2.0 && deg < 0.2, "{mm} mm, {deg} deg");
        // The origin marker alone places it too.
        let single = MarkerMap::single(Family::Tag36h11, 0, 0.16);
        let c = calibrate(&view, &single).expect("calibrated");
        let [mm, deg] = c.error_from(&shown.truth);
        eprintln!(
            "origin only: {mm:.2} mm, {deg:.3} deg, unknown {:?}",
            c.unknown
        );
        assert_eq!(c.unknown, vec![5]);
        assert!(mm < 5.0 && deg < 0.5, "{mm} mm, {deg} deg");
    }

    #[test]
    fn a_noisy_blurred_color_image_still_places_the_camera_within_2_mm_and_0_2_degrees() {
        let scene = scene([-0.7, 1.2, 1.1], [0.1, 0.1, 0.0]);
        let map = MarkerMap::from_scene(&scene, Family::Tag36h11, 0).expect("map");
        for noise in [8, 20] {
            let shown = grab_with(&scene, noise);
            let c = calibrate(&shown.view(), &map).expect("calibrated");
            let [mm, deg] = c.error_from(&shown.truth);
            eprintln!(
                "noise +-{noise}: {mm:.2} mm, {deg:.3} deg, {:.2} px",
                c.reprojection_px
            );
            assert_eq!(c.used.len(), 2, "{c:?}");
            assert!(mm < 2.0 && deg < 0.2, "{mm} mm, {deg} deg");
        }
    }

    #[test]
    fn a_camera_that_sees_no_marker_of_the_map_is_refused_naming_what_it_saw() {
        let scene = scene([0.9, -1.1, 1.3], [0.1, 0.1, 0.0]);
        let shown = grab_with(&scene, 0);
        let e =
            calibrate(&shown.view(), &MarkerMap::single(Family::Tag36h11, 9, 0.16)).unwrap_err();
        assert!(matches!(e, CalibrationError::NoMarker { .. }), "{e}");
        assert!(e.to_string().contains("[9]"), "{e}");
    }
}
