use geometry::{Point3, PointCloud, Roi3, RoiError};

fn unit_box() -> Roi3 {
    Roi3::new(Point3::new(-0.25, -0.25, 0.1), Point3::new(0.25, 0.25, 0.3)).expect("valid roi")
}

#[test]
fn roi_keeps_exactly_the_points_inside_with_bounds_inclusive() {
    let roi = unit_box();
    let up = |v: f32| v.next_up();
    let down = |v: f32| v.next_down();
    let inside = [
        Point3::new(0.0, 0.0, 0.2),
        Point3::new(-0.25, -0.25, 0.1), // the min corner
        Point3::new(0.25, 0.25, 0.3),   // the max corner
        Point3::new(0.25, 0.0, 0.2),    // on a face
        Point3::new(0.0, -0.25, 0.3),   // on an edge
    ];
    let outside = [
        Point3::new(up(0.25), 0.0, 0.2),
        Point3::new(down(-0.25), 0.0, 0.2),
        Point3::new(0.0, up(0.25), 0.2),
        Point3::new(0.0, down(-0.25), 0.2),
        Point3::new(0.0, 0.0, up(0.3)),
        Point3::new(0.0, 0.0, down(0.1)),
        Point3::new(f32::NAN, 0.0, 0.2),
        Point3::new(0.0, f32::INFINITY, 0.2),
    ];
    let mut cloud: PointCloud = outside
        .iter()
        .zip(inside.iter())
        .flat_map(|(o, i)| [*o, *i])
        .chain(outside[inside.len()..].iter().copied())
        .collect();
    let cropped = roi.crop(&cloud.points);
    roi.retain(&mut cloud);
    assert_eq!(cloud.points, inside.to_vec());
    assert_eq!(cropped, cloud);
    for p in inside {
        assert!(roi.contains(&p), "{p:?}");
    }
    for p in outside {
        assert!(!roi.contains(&p), "{p:?}");
    }
}

#[test]
fn roi_json_uses_the_thesis_keys_and_round_trips() {
    let json = r#"{"min_x":-0.25,"max_x":0.25,"min_y":-0.25,"max_y":0.25,"min_z":0.1,"max_z":0.3}"#;
    let roi: Roi3 = serde_json::from_str(json).expect("Listing A.3 roi3d parses");
    assert_eq!(roi, unit_box());
    assert_eq!(serde_json::to_string(&roi).expect("serialises"), json);
}

#[test]
fn inverted_roi_is_refused_naming_the_axis() {
    let e = Roi3::new(Point3::new(0.0, 0.5, 0.0), Point3::new(1.0, 0.4, 1.0))
        .expect_err("min_y > max_y");
    assert_eq!(
        e,
        RoiError::Inverted {
            axis: "y",
            min: 0.5,
            max: 0.4
        }
    );
    assert_eq!(
        e.to_string(),
        "roi3d: `min_y` (0.5) must not exceed `max_y` (0.4)"
    );
    let json = r#"{"min_x":0,"max_x":1,"min_y":0,"max_y":1,"min_z":2,"max_z":1}"#;
    let e = serde_json::from_str::<Roi3>(json).expect_err("min_z > max_z");
    assert!(
        e.to_string()
            .contains("`min_z` (2) must not exceed `max_z` (1)"),
        "{e}"
    );
}

#[test]
fn non_finite_roi_bound_is_refused_naming_the_field() {
    let e = Roi3::new(
        Point3::new(0.0, 0.0, f32::NEG_INFINITY),
        Point3::new(1.0, 1.0, 1.0),
    )
    .expect_err("infinite bound");
    assert!(matches!(e, RoiError::NonFinite { field: "min_z", .. }));
}

#[test]
fn everything_keeps_every_finite_point() {
    let mut cloud = PointCloud::from(vec![
        Point3::new(f32::MAX, f32::MIN, 0.0),
        Point3::new(f32::NAN, 0.0, 0.0),
    ]);
    Roi3::everything().retain(&mut cloud);
    assert_eq!(cloud.points, vec![Point3::new(f32::MAX, f32::MIN, 0.0)]);
}
