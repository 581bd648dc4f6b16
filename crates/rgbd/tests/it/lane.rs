//! The lane set (`rgbd::lane`): seeded scenes of parcels with their case and truth.

use rgbd::lane::{Case, LANE_SET_SIZE, lane_scene, lane_set};
use rgbd::scene::{ObjectKind, SceneCamera, Truth};
use rgbd::{Camera, SyntheticCamera};

/// Where camera `c` sees world point `p` in its 1280x720 depth image; `None` behind it.
fn image_point(c: &SceneCamera, p: [f64; 3]) -> Option<[f64; 2]> {
    let pose = c.pose()?;
    let d = [0, 1, 2].map(|i| p[i] - pose.translation[i]);
    let r = pose.rotation;
    let q = [0, 1, 2].map(|j| r[0][j] * d[0] + r[1][j] * d[1] + r[2][j] * d[2]);
    let k = rgbd::d415::depth_intrinsics(1280, 720);
    (q[2] > 0.0).then(|| {
        [
            f64::from(k.fx) * q[0] / q[2] + f64::from(k.ppx),
            f64::from(k.fy) * q[1] / q[2] + f64::from(k.ppy),
        ]
    })
}

/// The enclosing cuboid's eight corners.
fn corners(t: &Truth) -> Vec<[f64; 3]> {
    t.footprint
        .iter()
        .flat_map(|c| [[c[0], c[1], 0.0], [c[0], c[1], t.size[2]]])
        .collect()
}

fn in_image(p: [f64; 2]) -> bool {
    (0.0..1280.0).contains(&p[0]) && (0.0..720.0).contains(&p[1])
}

#[test]
fn the_lane_set_is_reproducible_and_cycles_through_the_cases() {
    let set = lane_set(1, LANE_SET_SIZE);
    const { assert!(LANE_SET_SIZE >= 60) };
    assert_eq!(set.len(), LANE_SET_SIZE);
    assert_eq!(set[17], lane_scene(1, 17));
    assert_ne!(set[17].scene, lane_scene(2, 17).scene);
    for (i, s) in set.iter().enumerate() {
        assert_eq!(s.index, i);
        assert_eq!(s.case, Case::ALL[i % Case::ALL.len()]);
        s.scene.validate().unwrap();
        let mut truths = s.scene.truths();
        truths.sort_by(|a, b| b.footprint_m2().total_cmp(&a.footprint_m2()));
        assert_eq!(s.truths, truths);
        let kinds: Vec<ObjectKind> = s.truths.iter().map(|t| t.kind).collect();
        match s.case {
            Case::Cylinder => assert!(
                kinds == [ObjectKind::Cylinder] || kinds == [ObjectKind::Tube],
                "{kinds:?}"
            ),
            Case::Polybag => assert_eq!(kinds, [ObjectKind::Bag]),
            Case::Apart | Case::Touching => assert_eq!(kinds, [ObjectKind::Box; 2]),
            _ => assert_eq!(kinds, [ObjectKind::Box]),
        }
        let parcels = if matches!(s.case, Case::Apart | Case::Touching) {
            2
        } else {
            1
        };
        assert_eq!(s.truths.len(), parcels, "{}", s.case);
        assert!(s.scene.cameras.iter().all(|c| c.calibrated));
        for c in &s.scene.cameras {
            let sensor = c.color_sensor;
            assert!((1.5..3.0).contains(&sensor.noise), "{sensor:?}");
            assert!((0.15..0.3).contains(&sensor.blur_px), "{sensor:?}");
            assert!((0.85..1.1).contains(&sensor.exposure), "{sensor:?}");
        }
        let cameras = s.scene.cameras.len();
        assert!(
            cameras == 1 || (cameras == 2 && s.case != Case::Cut),
            "{}",
            s.case
        );
        for t in &s.truths {
            let lid = s.scene.cameras.iter().map(|c| c.position[2] - t.size[2]);
            assert!(lid.clone().all(|d| d >= 0.5), "{} lid too near", s.case);
        }
    }
    let names: Vec<&str> = Case::ALL.iter().map(|c| c.name()).collect();
    assert_eq!(
        names,
        [
            "clean", "large", "dark", "glossy", "cylinder", "polybag", "apart", "touching", "cut"
        ]
    );
    for s in &set {
        let finish = s.scene.boxes.first().map(|b| b.finish).unwrap_or_default();
        match s.case {
            Case::Dark => assert!((0.03..0.35).contains(&finish.reflectivity)),
            Case::Glossy => assert!((0.4..1.0).contains(&finish.gloss)),
            _ => assert!(finish.is_default(), "{}", s.case),
        }
    }
    for case in Case::ALL {
        let of_case: Vec<_> = set.iter().filter(|s| s.case == case).collect();
        assert!(of_case.iter().any(|s| s.scene.cameras.len() == 1), "{case}");
        if case != Case::Cut {
            assert!(of_case.iter().any(|s| s.scene.cameras.len() == 2), "{case}");
        }
    }
    let large = set.iter().filter(|s| s.case == Case::Large);
    assert!(large.clone().all(|s| s.truths[0].size[0] > 0.6));
    let cylinders = set.iter().filter(|s| s.case == Case::Cylinder);
    assert!(
        cylinders
            .clone()
            .any(|s| s.truths[0].kind == ObjectKind::Tube)
    );
    assert!(
        cylinders
            .clone()
            .any(|s| s.truths[0].kind == ObjectKind::Cylinder)
    );
    let clean = set.iter().filter(|s| s.case == Case::Clean);
    assert!(clean.clone().all(|s| s.truths[0].size[0] <= 0.6));
    assert!(clean.clone().any(|s| s.truths[0].size[0] < 0.25));
}

#[test]
fn every_parcel_is_in_every_cameras_view_but_in_the_cut_case_one_end_is_not() {
    for s in lane_set(3, LANE_SET_SIZE) {
        for c in &s.scene.cameras {
            for t in &s.truths {
                let seen: Vec<bool> = corners(t)
                    .into_iter()
                    .map(|p| image_point(c, p).is_some_and(in_image))
                    .collect();
                if s.case == Case::Cut {
                    let n = seen.iter().filter(|v| **v).count();
                    assert!(n > 0 && n < 8, "cut scene {}: {n} corners in view", s.index);
                } else {
                    assert!(
                        seen.iter().all(|v| *v),
                        "scene {} ({}): {seen:?}",
                        s.index,
                        s.case
                    );
                }
            }
        }
    }
}

/// Gap between two footprints (convex quadrilaterals): the largest separation of their
/// projections onto the edges' normals (negative when they overlap).
fn gap(a: &[[f64; 2]; 4], b: &[[f64; 2]; 4]) -> f64 {
    let mut best = f64::NEG_INFINITY;
    for poly in [a, b] {
        for i in 0..4 {
            let (p, q) = (poly[i], poly[(i + 1) % 4]);
            let len = ((q[0] - p[0]).powi(2) + (q[1] - p[1]).powi(2)).sqrt();
            let n = [(q[1] - p[1]) / len, -(q[0] - p[0]) / len];
            let range = |r: &[[f64; 2]; 4]| {
                let d: Vec<f64> = r.iter().map(|c| c[0] * n[0] + c[1] * n[1]).collect();
                (
                    d.iter().copied().fold(f64::INFINITY, f64::min),
                    d.iter().copied().fold(f64::NEG_INFINITY, f64::max),
                )
            };
            let ((a0, a1), (b0, b1)) = (range(a), range(b));
            best = best.max((b0 - a1).max(a0 - b1));
        }
    }
    best
}

#[test]
fn apart_parcels_have_a_gap_and_touching_ones_share_a_face() {
    for s in lane_set(5, LANE_SET_SIZE) {
        let g = match s.case {
            Case::Apart | Case::Touching => gap(&s.truths[0].footprint, &s.truths[1].footprint),
            _ => continue,
        };
        if s.case == Case::Apart {
            assert!((0.06..0.26).contains(&g), "scene {}: gap {g}", s.index);
        } else {
            assert!(g.abs() < 1e-9, "scene {}: gap {g}", s.index);
            let (a, b) = (&s.scene.boxes[0], &s.scene.boxes[1]);
            assert_eq!(a.yaw_deg, b.yaw_deg, "face to face");
        }
    }
}

#[test]
fn a_scene_of_each_case_renders_and_has_depth_on_its_matte_parcels_lids() {
    for case in Case::ALL {
        let index = Case::ALL.iter().position(|c| *c == case).unwrap();
        let s = lane_scene(7, index);
        let cam = SyntheticCamera::new(&s.scene, &s.scene.cameras[0].serial).unwrap();
        let frame = cam.render_depth(1);
        let k = cam.depth_intrinsics().unwrap();
        let pose = cam.true_pose().unwrap();
        for t in &s.truths {
            // Around the lid's centre, within a quarter of the width.
            let lid = [t.center[0], t.center[1], t.size[2]];
            let [u, v] = image_point(&s.scene.cameras[0], lid).unwrap();
            let reach = 0.25 * t.size[1] * f64::from(k.fx) / (pose.translation[2] - t.size[2]);
            let r = reach.max(2.0) as i64;
            let mut on_lid = 0;
            let mut total = 0;
            for dv in -r..=r {
                for du in -r..=r {
                    let (pu, pv) = (u as i64 + du, v as i64 + dv);
                    if !(0..1280).contains(&pu) || !(0..720).contains(&pv) {
                        continue;
                    }
                    total += 1;
                    let Some(z) = frame.metres_at(pu as u32, pv as u32) else {
                        continue;
                    };
                    let p = k.deproject([pu as f32, pv as f32], z);
                    let w = pose.transform_point(p.map(f64::from));
                    // A box's or a cylinder's lid is flat; a bag's and a tube's top are
                    // not: there, anything between a third of the height and the top.
                    on_lid += usize::from(if t.cuboid || t.kind == ObjectKind::Cylinder {
                        (w[2] - t.size[2]).abs() < 0.01
                    } else {
                        w[2] > t.size[2] / 3.0 && w[2] < t.size[2] + 0.003
                    });
                }
            }
            assert!(total > 0, "{case}: the lid's centre is out of view");
            // Dark and glossy lids (polybags are a little glossy) lose part of their
            // depth by design.
            if !matches!(case, Case::Dark | Case::Glossy | Case::Polybag) {
                assert!(
                    on_lid * 10 > total * 9,
                    "{case}: {on_lid} of {total} pixels on the lid"
                );
            }
        }
    }
}
