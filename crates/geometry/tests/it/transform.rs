use geometry::{Point3, PointCloud, Roi3, Transform, TransformError, Transformation};
use nalgebra::{Isometry3, Matrix3, Vector3};

use crate::assert_near;

/// Thesis Listing A.4, verbatim.
const LISTING_A4: &str = r#"{
  "scale_matrix" : [[1.000000],[1.000000],[1.000000]],
  "rotation_matrix" : [[0.999524,0.030429,-0.005019],
                      [0.030511,-0.999388,0.017115],
                      [-0.004495,-0.017260,-0.999841]],
  "translation_matrix" : [[-0.113241],[0.111672],[-0.769009]],
  "post_scale_matrix" : [[1.000000],[1.000000],[1.000000]],
  "post_rotation_matrix" : [[0.000000],[0.000000],[0.000000]],
  "post_translation_matrix" : [[0.000000],[0.000000],[0.000000]]
}"#;

fn compile(doc: &Transformation) -> Transform {
    doc.to_transform().expect("valid document")
}

fn with_post_rotation(roll: f64, pitch: f64, yaw: f64) -> Transformation {
    Transformation {
        post_rotation_deg: Vector3::new(roll, pitch, yaw),
        ..Transformation::identity()
    }
}

fn refusal(json: &str) -> TransformError {
    Transformation::from_json(json.as_bytes()).expect_err("document must be refused")
}

#[test]
fn identity_document_maps_every_point_to_itself() {
    let t = compile(&Transformation::identity());
    assert_eq!(t, Transform::identity());
    for p in [Point3::new(0.1, -2.0, 3.5), Point3::origin()] {
        assert_eq!(t.apply(&p), p);
    }
    let identity_json =
        r#"{"rotation_matrix":[[1,0,0],[0,1,0],[0,0,1]],"translation_matrix":[[0],[0],[0]]}"#;
    let parsed = Transformation::from_json(identity_json.as_bytes()).expect("identity parses");
    assert_eq!(parsed, Transformation::identity());
}

#[test]
fn scale_applies_first_then_rotation_translation_post_translation_and_post_scale_last() {
    // p = (1, 1, 1); scale (2, 3, 4) -> (2, 3, 4); R = Rz(90) -> (-3, 2, 4);
    // + t (1, 2, 3) -> (-2, 4, 7); + t_post (0.5, 0, 0) -> (-1.5, 4, 7);
    // post_scale (1, 2, 1) -> (-1.5, 8, 7).
    let doc = Transformation {
        scale: Vector3::new(2.0, 3.0, 4.0),
        rotation: Matrix3::new(0.0, -1.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0),
        translation: Vector3::new(1.0, 2.0, 3.0),
        post_scale: Vector3::new(1.0, 2.0, 1.0),
        post_rotation_deg: Vector3::zeros(),
        post_translation: Vector3::new(0.5, 0.0, 0.0),
    };
    let p = compile(&doc).apply(&Point3::new(1.0, 1.0, 1.0));
    assert_near(p, Point3::new(-1.5, 8.0, 7.0), 1e-6);
}

#[test]
fn post_rotation_turns_roll_about_x_first_then_pitch_about_y() {
    // Rx(90): (0, 1, 0) -> (0, 0, 1); Ry(90): (0, 0, 1) -> (1, 0, 0).
    // The other order would give (0, 0, 1).
    let p = compile(&with_post_rotation(90.0, 90.0, 0.0)).apply(&Point3::new(0.0, 1.0, 0.0));
    assert_near(p, Point3::new(1.0, 0.0, 0.0), 1e-6);
}

#[test]
fn post_rotation_turns_pitch_before_yaw_about_z() {
    // Ry(90): (0, 0, 1) -> (1, 0, 0); Rz(90): (1, 0, 0) -> (0, 1, 0).
    let p = compile(&with_post_rotation(0.0, 90.0, 90.0)).apply(&Point3::new(0.0, 0.0, 1.0));
    assert_near(p, Point3::new(0.0, 1.0, 0.0), 1e-6);
}

#[test]
fn post_rotation_of_all_three_angles_is_rz_ry_rx() {
    let t = compile(&with_post_rotation(90.0, 90.0, 90.0));
    // (0, 1, 0): Rx -> (0, 0, 1), Ry -> (1, 0, 0), Rz -> (0, 1, 0); Rx Ry Rz would give (0, -1, 0).
    assert_near(
        t.apply(&Point3::new(0.0, 1.0, 0.0)),
        Point3::new(0.0, 1.0, 0.0),
        1e-6,
    );
    // (0, 0, 1): Rx -> (0, -1, 0), Ry -> (0, -1, 0), Rz -> (1, 0, 0).
    assert_near(
        t.apply(&Point3::new(0.0, 0.0, 1.0)),
        Point3::new(1.0, 0.0, 0.0),
        1e-6,
    );
    // A 30 degree roll, by hand: (0, 1, 0) -> (0, cos 30, sin 30).
    let roll = compile(&with_post_rotation(30.0, 0.0, 0.0)).apply(&Point3::new(0.0, 1.0, 0.0));
    assert_near(roll, Point3::new(0.0, 0.866_025_4, 0.5), 1e-6);
}

#[test]
fn post_rotation_acts_on_the_translated_point_and_post_translation_is_not_rotated() {
    let doc = Transformation {
        translation: Vector3::new(1.0, 0.0, 0.0),
        post_rotation_deg: Vector3::new(0.0, 0.0, 90.0),
        post_translation: Vector3::new(0.0, 0.0, 0.25),
        ..Transformation::identity()
    };
    // p1 = (0, 0, 0) + (1, 0, 0); Rz(90) -> (0, 1, 0); + (0, 0, 0.25).
    let p = compile(&doc).apply(&Point3::origin());
    assert_near(p, Point3::new(0.0, 1.0, 0.25), 1e-6);
}

#[test]
fn thesis_listing_a4_parses_and_maps_the_camera_origin_to_its_translation() {
    let doc = Transformation::from_json(LISTING_A4.as_bytes()).expect("Listing A.4 parses");
    assert_eq!(doc.rotation[(0, 1)], 0.030429);
    assert_eq!(doc.rotation[(1, 0)], 0.030511);
    let t = compile(&doc);
    assert_near(
        t.apply(&Point3::origin()),
        Point3::new(-0.113241, 0.111672, -0.769009),
        1e-7,
    );
    // A point 1 m in front of the camera: R * (0, 0, 1) + t is the third column plus t.
    assert_near(
        t.apply(&Point3::new(0.0, 0.0, 1.0)),
        Point3::new(
            -0.113241 - 0.005019,
            0.111672 + 0.017115,
            -0.769009 - 0.999841,
        ),
        1e-6,
    );
}

#[test]
fn json_round_trip_is_exact_and_keeps_the_thesis_keys() {
    let doc = Transformation {
        scale: Vector3::new(1.0, 0.999, 1.001),
        rotation: Matrix3::new(0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9),
        translation: Vector3::new(-0.113241, 0.111672, -0.769009),
        post_scale: Vector3::new(1.0, 1.0, -1.0),
        post_rotation_deg: Vector3::new(1.5, -2.25, 180.0),
        post_translation: Vector3::new(0.01, 0.02, 0.03),
    };
    let json = doc.to_json();
    for key in [
        "\"scale_matrix\"",
        "\"rotation_matrix\"",
        "\"translation_matrix\"",
        "\"post_scale_matrix\"",
        "\"post_rotation_matrix\"",
        "\"post_translation_matrix\"",
    ] {
        assert!(json.contains(key), "{key} missing from {json}");
    }
    assert_eq!(Transformation::from_json(json.as_bytes()), Ok(doc));
    // serde's own path agrees with from_json.
    let via_serde: Transformation = serde_json::from_str(&json).expect("serde reads it");
    assert_eq!(via_serde, doc);
    assert_eq!(
        serde_json::to_string_pretty(&doc).expect("serialises"),
        json
    );
}

#[test]
fn rotation_matrix_of_wrong_size_is_refused_naming_the_field_and_the_shape() {
    let e = refusal(r#"{"rotation_matrix":[[1,0,0],[0,1,0]],"translation_matrix":[[0],[0],[0]]}"#);
    assert!(matches!(
        e,
        TransformError::Shape {
            field: "rotation_matrix",
            ..
        }
    ));
    let text = e.to_string();
    assert!(
        text.contains("`rotation_matrix` must be a 3x3 matrix"),
        "{text}"
    );
    let e = refusal(
        r#"{"rotation_matrix":[[1,0,0],[0,1],[0,0,1]],"translation_matrix":[[0],[0],[0]]}"#,
    );
    assert!(e.to_string().contains("3 rows of [3, 2, 3] entries"), "{e}");
}

#[test]
fn shape_error_of_a_huge_matrix_stays_under_300_bytes() {
    let rows = vec!["[1,2]"; 100_000].join(",");
    let json = format!(r#"{{"rotation_matrix":[{rows}],"translation_matrix":[[0],[0],[0]]}}"#);
    assert!(json.len() > 500_000);
    let text = refusal(&json).to_string();
    assert!(text.len() < 300, "{} bytes: {text}", text.len());
    assert!(
        text.contains("100000 rows of [2, 2, 2, …] entries"),
        "{text}"
    );
    let column =
        format!(r#"{{"rotation_matrix":[[1,0,0],[0,1,0],[0,0,1]],"translation_matrix":[{rows}]}}"#);
    let text = refusal(&column).to_string();
    assert!(text.len() < 300, "{} bytes: {text}", text.len());
}

#[test]
fn column_of_wrong_size_is_refused_naming_the_field() {
    let e = refusal(
        r#"{"rotation_matrix":[[1,0,0],[0,1,0],[0,0,1]],"translation_matrix":[[0],[0],[0]],"post_rotation_matrix":[[0,0,0]]}"#,
    );
    assert!(matches!(
        e,
        TransformError::Shape {
            field: "post_rotation_matrix",
            ..
        }
    ));
    assert!(e.to_string().contains("a 3x1 column [[x],[y],[z]]"), "{e}");
}

#[test]
fn number_outside_f32_range_is_refused_naming_the_entry() {
    let e = refusal(
        r#"{"rotation_matrix":[[1,0,0],[0,1,1e39],[0,0,1]],"translation_matrix":[[0],[0],[0]]}"#,
    );
    assert_eq!(
        e,
        TransformError::NonFinite {
            field: "rotation_matrix",
            row: 1,
            col: 2,
            value: 1e39
        }
    );
    assert!(
        e.to_string()
            .contains("`rotation_matrix[1][2]` must be a finite number")
    );
}

#[test]
fn non_finite_entries_of_a_built_document_are_refused() {
    let doc = Transformation {
        post_translation: Vector3::new(0.0, f64::NAN, 0.0),
        ..Transformation::identity()
    };
    assert!(matches!(
        doc.to_transform(),
        Err(TransformError::NonFinite {
            field: "post_translation_matrix",
            row: 1,
            col: 0,
            ..
        })
    ));
    let doc = Transformation {
        rotation: Matrix3::new(1.0, 0.0, 0.0, 0.0, 1.0, 0.0, f64::INFINITY, 0.0, 1.0),
        ..Transformation::identity()
    };
    assert!(matches!(
        doc.validate(),
        Err(TransformError::NonFinite {
            field: "rotation_matrix",
            row: 2,
            col: 0,
            ..
        })
    ));
    // JSON cannot carry NaN: the writer emits null, which the reader refuses.
    assert!(matches!(
        Transformation::from_json(doc.to_json().as_bytes()),
        Err(TransformError::Json { .. })
    ));
}

#[test]
fn composition_overflowing_f32_is_refused() {
    let doc = Transformation {
        scale: Vector3::repeat(1e30),
        post_scale: Vector3::repeat(1e30),
        ..Transformation::identity()
    };
    assert_eq!(doc.to_transform(), Err(TransformError::Overflow));
}

#[test]
fn unknown_missing_and_mistyped_keys_are_refused_naming_the_key() {
    let unknown = refusal(
        r#"{"rotation_matrix":[[1,0,0],[0,1,0],[0,0,1]],"translation_matrix":[[0],[0],[0]],"rotation":1}"#,
    );
    assert!(
        unknown.to_string().contains("unknown field `rotation`"),
        "{unknown}"
    );
    let missing = refusal(r#"{"rotation_matrix":[[1,0,0],[0,1,0],[0,0,1]]}"#);
    assert!(
        missing
            .to_string()
            .contains("missing field `translation_matrix`"),
        "{missing}"
    );
    let mistyped = refusal(
        r#"{"rotation_matrix":[[1,0,0],[0,1,0],[0,0,1]],"translation_matrix":[["a"],[0],[0]]}"#,
    );
    assert!(matches!(mistyped, TransformError::Json { .. }));
    assert!(matches!(refusal("not json"), TransformError::Json { .. }));
}

#[test]
fn then_applies_self_first() {
    let a = Transform::from(Isometry3::translation(1.0, 0.0, 0.0));
    let b = compile(&with_post_rotation(0.0, 0.0, 90.0));
    let p = Point3::new(0.0, 0.0, 2.0);
    assert_near(a.then(&b).apply(&p), b.apply(&a.apply(&p)), 1e-6);
    assert_near(a.then(&b).apply(&p), Point3::new(0.0, 1.0, 2.0), 1e-6);
}

#[test]
fn isometry_becomes_the_same_affine_map() {
    let iso = Isometry3::new(Vector3::new(0.1, 0.2, 0.3), Vector3::new(0.0, 0.0, 0.5));
    let p = Point3::new(1.0, -1.0, 0.5);
    assert_near(Transform::from(iso).apply(&p), iso * p, 1e-6);
}

#[test]
fn apply_and_crop_equals_apply_in_place_then_retain() {
    let doc = Transformation::from_json(LISTING_A4.as_bytes()).expect("Listing A.4 parses");
    let t = compile(&doc);
    let points: Vec<Point3> = (0..2000)
        .map(|i| {
            let f = i as f32;
            Point3::new(
                (f * 0.37).sin() * 0.4,
                (f * 0.11).cos() * 0.4,
                0.4 + (f * 0.05).sin() * 0.3,
            )
        })
        .chain([Point3::new(f32::NAN, 0.0, 0.5)])
        .collect();
    // Listing A.4 turns the camera over: z forward becomes about -z, 0.77 m down.
    let roi =
        Roi3::new(Point3::new(-0.3, -0.3, -1.3), Point3::new(0.2, 0.3, -1.0)).expect("valid roi");
    let fused = t.apply_and_crop(&points, &roi);
    let mut stepwise = PointCloud::from(points);
    t.apply_in_place(&mut stepwise);
    roi.retain(&mut stepwise);
    assert!(fused.len() > 100 && fused.len() < 2000, "{}", fused.len());
    assert_eq!(fused, stepwise);
}
