//! The certification set (`rgbd::cert`): generated from the seed alone, within its
//! ranges, and its judgement of what a certified system accepts right on scenes built by
//! hand.

use rgbd::cert::{
    CAMERA_Z_M, DIVISION_M, MAX_TILT_DEG, MIN_M, MIN_SPACING_M, SPACINGS_MM, SYMBOLOGIES, Surface,
    cert_scene, cert_set, footprint_gap, judge,
};
use rgbd::scene::{Finish, ObjectKind, Scene, SceneBox};

/// The set is the same from the same seed, another from another seed.
#[test]
fn the_cert_set_is_made_from_the_seed_alone() {
    let set = cert_set(11, 24);
    assert_eq!(set[5], cert_scene(11, 5));
    assert_eq!(set[23], cert_scene(11, 23));
    assert_ne!(set[5].scene, cert_scene(12, 5).scene);
    for (i, s) in set.iter().enumerate() {
        assert_eq!(s.index, i);
        assert_eq!(s.objects.len(), s.scene.truths().len());
    }
}

/// Stations and objects stay in the ranges the set promises, every scene is valid, and
/// the groups keep at least their spacing.
#[test]
fn the_cert_set_covers_its_ranges() {
    let set = cert_set(3, 60);
    let mut cameras = [0usize; 5];
    let mut kinds = Vec::new();
    let mut surfaces = Vec::new();
    let mut spacings = Vec::new();
    let mut symbologies = Vec::new();
    let (mut accepted, mut refused_ones) = (0, 0);
    for s in &set {
        s.scene.validate().unwrap();
        cameras[s.scene.cameras.len()] += 1;
        for c in &s.scene.cameras {
            assert!(c.calibrated);
            let z = c.position[2];
            assert!((CAMERA_Z_M[0]..CAMERA_Z_M[1]).contains(&z), "{c:?}");
            let d: Vec<f64> = (0..3).map(|k| c.look_at[k] - c.position[k]).collect();
            let tilt = (-d[2] / (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt())
                .acos()
                .to_degrees();
            assert!(tilt <= MAX_TILT_DEG + 1e-9, "{tilt}");
        }
        for o in &s.objects {
            let t = &o.truth;
            assert!(t.size[1] >= 0.05 - 1e-9, "scene {}: {t:?}", s.index);
            assert!(t.size[2] >= 0.02 - 1e-9, "scene {}: {t:?}", s.index);
            if o.flat {
                assert!(t.size[2] <= 0.05 + 1e-9, "{t:?}");
            }
            assert_eq!(o.label.is_some(), t.kind == ObjectKind::Box);
            if let Some(l) = &o.label {
                symbologies.push(l.kind);
            }
            kinds.push(t.kind);
            surfaces.push(o.surface);
            accepted += usize::from(o.accepted());
            refused_ones += usize::from(!o.accepted());
            for p in t.footprint {
                assert!(p[0].abs() <= 1.0 && p[1].abs() <= 1.0, "{p:?}");
            }
        }
        match s.spacing_mm {
            None => assert_eq!(s.objects.len(), 1),
            Some(mm) => {
                assert!(SPACINGS_MM.contains(&mm));
                assert!(s.objects.len() >= 2);
                let gaps: Vec<f64> = s
                    .objects
                    .iter()
                    .map(|o| o.judged.gap_m.expect("a group"))
                    .collect();
                // Every object is its spacing or more from the others, and the nearest
                // two exactly that.
                for gap in &gaps {
                    assert!(*gap >= mm / 1e3 - 1e-9, "scene {}: {gap} < {mm}", s.index);
                }
                let nearest = gaps.iter().copied().fold(f64::INFINITY, f64::min);
                assert!(
                    (nearest - mm / 1e3).abs() < 1e-6,
                    "scene {}: {gaps:?}",
                    s.index
                );
                spacings.push(mm);
            }
        }
    }
    assert!(cameras[1..].iter().all(|n| *n > 0), "{cameras:?}");
    for k in [
        ObjectKind::Box,
        ObjectKind::Cylinder,
        ObjectKind::Tube,
        ObjectKind::Bag,
    ] {
        assert!(kinds.contains(&k), "{k:?}");
    }
    for surface in Surface::ALL {
        assert!(surfaces.contains(&surface), "{surface:?}");
    }
    for kind in SYMBOLOGIES {
        assert!(symbologies.contains(kind), "{kind:?}");
    }
    assert!(spacings.contains(&0.0) && spacings.iter().any(|s| *s >= 50.0));
    // Most objects are what a certified system measures, not all.
    assert!(
        accepted > refused_ones && refused_ones > 0,
        "{accepted} {refused_ones}"
    );
}

/// One camera `z` metres straight above the origin.
fn one_camera(z: f64) -> String {
    format!(
        "seed = 1\n[[camera]]\nserial = \"840412060746\"\nposition = [0.0, 0.0, {z:?}]\n\
         look_at = [0.0, 0.0, 0.0]\nup = [0.0, 1.0, 0.0]\n"
    )
}

fn boxed(size: [f64; 3], center: [f64; 2], yaw: f64) -> String {
    format!("[[box]]\nsize = {size:?}\ncenter = {center:?}\nyaw_deg = {yaw:?}\n")
}

#[test]
fn the_gap_between_footprints_is_their_least_distance() {
    let square = |c: [f64; 2], half: f64, yaw: f64| {
        let (s, co) = yaw.to_radians().sin_cos();
        [[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]].map(|[a, b]: [f64; 2]| {
            let (x, y) = (a * half, b * half);
            [c[0] + x * co - y * s, c[1] + x * s + y * co]
        })
    };
    // Side by side, 20 mm apart.
    let a = square([0.0, 0.0], 0.1, 0.0);
    assert!((footprint_gap(&a, &square([0.22, 0.0], 0.1, 0.0)) - 0.02).abs() < 1e-12);
    // Touching, overlapping: 0.
    assert_eq!(footprint_gap(&a, &square([0.2, 0.05], 0.1, 0.0)), 0.0);
    assert_eq!(footprint_gap(&a, &square([0.1, 0.0], 0.1, 30.0)), 0.0);
    // Corner to corner along the diagonal: two squares turned 45 degrees whose tips are
    // 30 mm apart, though their projections on x overlap.
    let h = 0.1 / 2f64.sqrt();
    let tip = 2.0 * h * 2f64.sqrt();
    let b = square([0.0, 0.0], h, 45.0);
    let c = square([tip + 0.03, 0.0], h, 45.0);
    assert!((footprint_gap(&b, &c) - 0.03).abs() < 1e-9);
    // Diagonally offset, corner to corner: the Euclidean distance.
    let d = square([0.23, 0.24], 0.1, 0.0);
    assert!((footprint_gap(&a, &d) - 0.03f64.hypot(0.04)).abs() < 1e-12);
}

#[test]
fn isolated_means_20_mm_or_more_from_every_other_object() {
    let scene = |second_x: f64| {
        Scene::from_toml(&format!(
            "{}{}{}",
            one_camera(1.6),
            boxed([0.2, 0.15, 0.1], [-0.1, 0.0], 0.0),
            boxed([0.2, 0.15, 0.1], [second_x, 0.0], 0.0)
        ))
        .unwrap()
    };
    // The first box ends at x = 0: the second starts 19 mm, 20 mm, 0 mm after it.
    let close = judge(&scene(0.119));
    assert!((close[0].gap_m.unwrap() - 0.019).abs() < 1e-9);
    assert!(!close[0].isolated() && !close[1].isolated() && !close[0].accepted());
    assert!(close[0].in_view && close[0].returns_depth);
    let apart = judge(&scene(0.12));
    assert!(
        apart.iter().all(|j| j.isolated() && j.accepted()),
        "{apart:?}"
    );
    const { assert!(MIN_SPACING_M == 0.02) };
    let touching = judge(&scene(0.1));
    assert_eq!(touching[0].gap_m, Some(0.0));
    assert!(!touching[1].accepted());
    let alone = judge(
        &Scene::from_toml(&format!(
            "{}{}",
            one_camera(1.0),
            boxed([0.2, 0.1, 0.1], [0.0, 0.0], 10.0)
        ))
        .unwrap(),
    );
    assert_eq!(alone[0].gap_m, None);
    assert!(alone[0].accepted());
}

/// An instrument's minimum (10 d, 10 d, 2 d at d = 5 mm) applies to what it measures:
/// a box 52 mm wide may read 49.x mm and be refused, so a certified system is held to
/// measure it only from 55 mm (found by the set: 50.x mm boxes refused as under 50).
#[test]
fn measurable_means_a_division_or_more_above_the_smallest_object() {
    let at = |size: [f64; 3]| {
        judge(
            &Scene::from_toml(&format!(
                "{}{}",
                one_camera(1.2),
                boxed(size, [0.0, 0.0], 0.0)
            ))
            .unwrap(),
        )[0]
    };
    assert!(at([0.2, 0.055, 0.1]).accepted());
    for small in [[0.2, 0.052, 0.1], [0.054, 0.054, 0.1], [0.2, 0.1, 0.014]] {
        let j = at(small);
        assert!(
            !j.measurable && !j.accepted() && j.in_view && j.returns_depth,
            "{small:?}"
        );
    }
    assert!(at([0.2, 0.1, 0.015]).measurable);
    const { assert!(MIN_M[0] == 0.05 && MIN_M[2] == 0.01 && DIVISION_M == 0.005) };
}

#[test]
fn in_view_means_every_corner_in_one_cameras_depth_image_beyond_its_minimum_range() {
    // A D415 1 m up, 1280x720: the floor it sees spans about +-0.64 m across and +-0.37 m
    // along its image's height (world y here).
    let at = |center: [f64; 2], size: [f64; 3], z: f64| {
        judge(&Scene::from_toml(&format!("{}{}", one_camera(z), boxed(size, center, 0.0))).unwrap())
            [0]
    };
    assert!(at([0.0, 0.0], [0.3, 0.2, 0.2], 1.0).in_view);
    // The lid's far corners leave the image sooner than the floor's: at 0.2 m high the
    // lid is 0.8 m away and the image's half height there is about 0.29 m.
    assert!(at([0.0, 0.15], [0.3, 0.2, 0.02], 1.0).in_view);
    assert!(!at([0.0, 0.25], [0.3, 0.2, 0.2], 1.0).in_view);
    assert!(!at([0.8, 0.0], [0.3, 0.2, 0.1], 1.0).in_view);
    // A lid 0.35 m below the camera is nearer than the minimum range (0.39 m).
    assert!(!at([0.0, 0.0], [0.2, 0.2, 0.65], 1.0).in_view);
    assert!(at([0.0, 0.0], [0.2, 0.2, 0.55], 1.0).in_view);
    // Out of one camera's view but wholly in another's.
    let two = format!(
        "{}[[camera]]\nserial = \"840412060757\"\nposition = [0.8, 0.0, 1.0]\n\
         look_at = [0.8, 0.0, 0.0]\nup = [0.0, 1.0, 0.0]\n{}",
        one_camera(1.0),
        boxed([0.3, 0.2, 0.1], [0.8, 0.0], 0.0)
    );
    assert!(judge(&Scene::from_toml(&two).unwrap())[0].in_view);
}

/// A dimensioner knows where a lid ends only where it sees past the end: a flat box
/// whose every corner lies in the image 2-3 mm from its edge is not in view, as a point
/// a division past its far side is not in the image; 6 mm nearer the middle it is.
#[test]
fn in_view_means_seen_a_division_past_each_edge() {
    let at = |y: f64| {
        judge(
            &Scene::from_toml(&format!(
                "{}{}",
                one_camera(1.0),
                boxed([0.3, 0.2, 0.02], [0.0, y], 0.0)
            ))
            .unwrap(),
        )[0]
    };
    assert!(at(0.288).in_view);
    let edge = at(0.294);
    assert!(
        !edge.in_view && edge.returns_depth && edge.measurable,
        "{edge:?}"
    );
    // 3.5 mm farther out its corners leave the image too.
    assert!(!at(0.2975).in_view);
}

/// A camera at `position` looking at (0.1, 0, 0), its image's rows along world y.
fn camera_at(serial: &str, position: [f64; 3]) -> String {
    format!(
        "[[camera]]\nserial = \"{serial}\"\nposition = {position:?}\n\
         look_at = [0.1, 0.0, 0.0]\nup = [0.0, 1.0, 0.0]\n"
    )
}

/// In view is what a camera sees: a low box 40 mm behind a 500 mm one, from the only
/// camera (tilted 30 degrees, on the tall box's side), is hidden though every corner of
/// it lies in the camera's image; alone, or with a second camera on its own side, it is
/// in view and accepted (scenes 182 and 379 of seed 1 before: counted accepted, 0 and 4
/// pixels of depth from them).
#[test]
fn in_view_means_seen_past_every_other_object() {
    let judged = |cameras: &str, tall: bool| {
        let objects = format!(
            "{}{}",
            boxed([0.1, 0.1, 0.05], [0.19, 0.0], 0.0),
            if tall {
                boxed([0.2, 0.3, 0.5], [0.0, 0.0], 0.0)
            } else {
                String::new()
            }
        );
        judge(&Scene::from_toml(&format!("seed = 1\n{cameras}{objects}")).unwrap())
    };
    let one = camera_at("840412060746", [-0.6, 0.0, 1.2]);
    let hidden = judged(&one, true);
    assert!((hidden[0].gap_m.unwrap() - 0.04).abs() < 1e-9);
    assert!(
        hidden[0].isolated() && hidden[0].returns_depth && hidden[0].measurable,
        "{hidden:?}"
    );
    assert!(!hidden[0].in_view && !hidden[0].accepted(), "{hidden:?}");
    assert!(hidden[1].in_view && hidden[1].accepted(), "{hidden:?}");
    let alone = judged(&one, false);
    assert!(alone[0].in_view && alone[0].accepted(), "{alone:?}");
    let two = format!("{one}{}", camera_at("840412060757", [0.8, 0.0, 1.2]));
    let seen = judged(&two, true);
    assert!(seen[0].in_view && seen[0].accepted(), "{seen:?}");
}

/// A bag hides its own foot from a camera off to its side: where its far side meets the
/// floor follows from nothing the camera sees, so it is not in view; under a camera 1 m
/// above it the last steep millimetres of its sides are hidden too (of the points the
/// judge looks at, the outermost, 5 mm inside its outline, on the side away from the
/// camera), but less than a division, and it is. A tube whose far flank the same camera cannot see is in view:
/// its circle gives that flank (seed 1 of the set: 18 of the 22 bags the station refused
/// as reaching beyond the view were in view before).
#[test]
fn a_bag_is_in_view_where_its_foot_is_seen_within_a_division() {
    let judged = |camera: &str, object: &str| {
        judge(&Scene::from_toml(&format!("seed = 1\n{camera}{object}")).unwrap())[0]
    };
    let bag = "[[bag]]\nsize = [0.3, 0.2, 0.2]\ncenter = [0.1, 0.0]\n";
    let tube = "[[tube]]\nradius = 0.1\nlength = 0.3\ncenter = [0.1, 0.0]\n";
    let above = camera_at("840412060746", [0.2, 0.0, 1.2]);
    let aside = camera_at("840412060746", [0.1, -0.9, 1.2]);
    let (bag_above, bag_aside) = (judged(&above, bag), judged(&aside, bag));
    assert!(bag_above.in_view && bag_above.accepted(), "{bag_above:?}");
    assert!(
        !bag_aside.in_view && bag_aside.returns_depth && bag_aside.measurable,
        "{bag_aside:?}"
    );
    let tube_aside = judged(&aside, tube);
    assert!(
        tube_aside.in_view && tube_aside.accepted(),
        "{tube_aside:?}"
    );
}

#[test]
fn returning_depth_is_enough_light_back_from_the_top() {
    let dark = |reflectivity: f64, z: f64| {
        let mut scene = Scene::from_toml(&format!(
            "{}{}",
            one_camera(z),
            boxed([0.3, 0.2, 0.2], [0.0, 0.0], 0.0)
        ))
        .unwrap();
        scene.boxes[0].finish = Finish {
            reflectivity,
            gloss: 0.0,
        };
        judge(&scene)[0]
    };
    assert!(dark(1.0, 2.0).returns_depth);
    // 0.3 from 0.8 m: 0.47 comes back, more than the 0.15 that loses no pixel.
    assert!(dark(0.3, 1.0).returns_depth);
    // 0.1 from 1.3 m: 0.059, some pixels lost.
    let black = dark(0.1, 1.5);
    assert!(!black.returns_depth && !black.accepted() && black.in_view);
    // Glossy boxes return depth (their glare takes a patch, not the top).
    let mut glossy = Scene::from_toml(&format!(
        "{}{}",
        one_camera(1.2),
        boxed([0.3, 0.2, 0.2], [0.0, 0.0], 0.0)
    ))
    .unwrap();
    glossy.boxes[0].finish.gloss = 0.9;
    assert!(judge(&glossy)[0].accepted());
    // Out of view, nothing returns depth to a camera that sees it whole.
    let mut out = glossy.clone();
    out.boxes[0] = SceneBox {
        center: [0.9, 0.0],
        ..out.boxes[0].clone()
    };
    assert!(!judge(&out)[0].in_view && !judge(&out)[0].returns_depth);
}

/// Every scene of the set written as a scene file reads back as the same scene, and so
/// do the built-in scenes and one with every kind of object, a label and a timeline.
#[test]
fn cert_scenes_written_as_scene_files_read_back_the_same() {
    for s in cert_set(5, 20) {
        let text = s.scene.to_toml();
        assert_eq!(Scene::from_toml(&text).unwrap(), s.scene, "{text}");
    }
    let every = Scene::from_toml(
        "seed = 9\n[floor]\nz = 0.01\ncolor = [1, 2, 3]\n\
         [[camera]]\nserial = \"840412060746\"\nposition = [0.1, 0.0, 1.0]\nlook_at = [0.0, 0.0, 0.0]\n\
         noise = \"ideal\"\ncalibrated = false\nstall_s = 4.0\n\
         color_sensor = { noise = 2.0, blur_px = 0.3, exposure = 1.1 }\n\
         [[box]]\nsize = [0.4, 0.3, 0.2]\ncenter = [0.0, 0.0]\nyaw_deg = 15.0\nappear_s = 1.0\n\
         from = [0.6, 0.0]\nstill_s = 2.0\nremove_s = 6.0\nreflectivity = 0.2\n\
         label = { kind = \"code128\", text = \"A \\\"q\\\" \\\\ b\", size = 0.1, appear_s = 3.0 }\n\
         [[cylinder]]\nradius = 0.1\nheight = 0.25\ncenter = [0.3, -0.2]\ngloss = 0.5\n\
         [[tube]]\nradius = 0.05\nlength = 0.6\ncenter = [0.0, -0.3]\nyaw_deg = -15.0\n\
         [[bag]]\nsize = [0.4, 0.28, 0.16]\ncenter = [-0.2, 0.1]\nyaw_deg = 25.0\nsag = 0.2\n\
         [[marker]]\nfamily = \"tag36h11\"\nid = 3\nsize = 0.16\ncenter = [0.5, 0.5]\nyaw_deg = 30.0\n",
    )
    .unwrap();
    for scene in [every, Scene::default_demo(), Scene::default_single()] {
        let text = scene.to_toml();
        assert_eq!(Scene::from_toml(&text).unwrap(), scene, "{text}");
    }
}
