use geometry::{IcpConfig, IcpError, IcpMethod, IcpOutcome, PointCloud, Transform, icp};
use nalgebra::{Isometry3, Vector3};

use crate::scene::{Sampler, parcel, scene};

/// The displacement of the issue: 3 cm and 5 degrees (about a tilted vertical axis).
fn displacement() -> Isometry3<f32> {
    let axis = Vector3::new(0.1_f32, -0.1, 1.0).normalize();
    Isometry3::new(
        Vector3::new(0.02, -0.015, 0.0158), // |t| = 3.0 cm
        axis * 5.0_f32.to_radians(),
    )
}

/// Two independent samplings of `n` points of one scene (a 70 cm measuring table with the
/// parcel); the source is displaced so that `displacement()` maps it back onto the target.
fn views(n: usize) -> (PointCloud, PointCloud) {
    let target = scene(&mut Sampler::new(1), n, 0.35, &parcel());
    let mut source = scene(&mut Sampler::new(2), n, 0.35, &parcel());
    Transform::from(displacement().inverse()).apply_in_place(&mut source);
    (source, target)
}

fn config(method: IcpMethod) -> IcpConfig {
    IcpConfig {
        method,
        max_iterations: 100,
        max_correspondence_m: 0.1,
        ..IcpConfig::default()
    }
}

/// Translation error (m) and rotation error (deg) of `found` against the truth.
fn errors(found: &IcpOutcome) -> (f32, f32) {
    let truth = displacement();
    let residual = found.transform * truth.inverse();
    let translation = (found.transform.translation.vector - truth.translation.vector).norm();
    (translation, residual.rotation.angle().to_degrees())
}

#[test]
fn point_to_point_recovers_3_cm_and_5_deg_within_2_mm_and_0_2_deg() {
    // Point-to-point creeps along the table plane (about 70 iterations here), so this test
    // uses fewer points to stay quick in debug builds.
    let (source, target) = views(5_000);
    let outcome = icp(
        &source,
        &target,
        &Isometry3::identity(),
        &config(IcpMethod::PointToPoint),
    )
    .expect("icp runs");
    let (t_err, r_err) = errors(&outcome);
    assert!(
        t_err < 0.002 && r_err < 0.2,
        "{t_err} m, {r_err} deg, {outcome:?}"
    );
    assert!(outcome.converged, "{outcome:?}");
    assert!(
        outcome.fitness > 0.95 && outcome.rmse_m < 0.01,
        "{outcome:?}"
    );
}

#[test]
fn point_to_plane_recovers_3_cm_and_5_deg_within_2_mm_and_0_2_deg() {
    let (source, target) = views(20_000);
    let outcome = icp(
        &source,
        &target,
        &Isometry3::identity(),
        &config(IcpMethod::PointToPlane),
    )
    .expect("icp runs");
    let (t_err, r_err) = errors(&outcome);
    assert!(
        t_err < 0.002 && r_err < 0.2,
        "{t_err} m, {r_err} deg, {outcome:?}"
    );
    assert!(outcome.converged, "{outcome:?}");
}

#[test]
fn icp_stops_at_max_iterations_without_claiming_convergence() {
    let (source, target) = views(20_000);
    for method in [IcpMethod::PointToPoint, IcpMethod::PointToPlane] {
        let limited = IcpConfig {
            max_iterations: 2,
            ..config(method)
        };
        let outcome = icp(&source, &target, &Isometry3::identity(), &limited).expect("icp runs");
        assert_eq!(outcome.iterations, 2, "{method:?}");
        assert!(!outcome.converged, "{method:?}");
    }
}

#[test]
fn icp_stops_on_convergence_before_the_limit() {
    let (source, target) = views(20_000);
    let outcome = icp(
        &source,
        &target,
        &Isometry3::identity(),
        &config(IcpMethod::PointToPlane),
    )
    .expect("icp runs");
    assert!(outcome.converged && outcome.iterations < 100, "{outcome:?}");
    // Started at the answer on identical points, the first increment is already tiny.
    let exact = icp(
        &target,
        &target,
        &Isometry3::identity(),
        &config(IcpMethod::PointToPoint),
    )
    .expect("icp runs");
    assert_eq!((exact.iterations, exact.converged), (1, true), "{exact:?}");
    assert!(exact.rmse_m < 1e-6 && exact.fitness == 1.0, "{exact:?}");
}

#[test]
fn icp_refuses_invalid_limits_naming_the_field() {
    let (source, target) = views(20_000);
    let bad = [
        (
            IcpConfig {
                max_iterations: 0,
                ..IcpConfig::default()
            },
            "max_iterations",
        ),
        (
            IcpConfig {
                max_correspondence_m: f32::NAN,
                ..IcpConfig::default()
            },
            "max_correspondence_m",
        ),
        (
            IcpConfig {
                method: IcpMethod::PointToPlane,
                min_correspondences: 5,
                ..IcpConfig::default()
            },
            "min_correspondences",
        ),
    ];
    for (config, name) in bad {
        match icp(&source, &target, &Isometry3::identity(), &config) {
            Err(IcpError::InvalidConfig { field, .. }) => assert_eq!(field, name),
            other => panic!("{name}: {other:?}"),
        }
    }
}

#[test]
fn icp_refuses_clouds_without_enough_points_or_pairs() {
    let (source, target) = views(20_000);
    let empty = PointCloud::default();
    assert!(matches!(
        icp(
            &empty,
            &target,
            &Isometry3::identity(),
            &IcpConfig::default()
        ),
        Err(IcpError::TooFewPoints {
            cloud: "source",
            found: 0,
            ..
        })
    ));
    let far = Isometry3::translation(10.0, 0.0, 0.0);
    assert!(matches!(
        icp(&source, &target, &far, &IcpConfig::default()),
        Err(IcpError::TooFewCorrespondences {
            iteration: 1,
            found: 0,
            ..
        })
    ));
}

#[test]
fn point_to_point_reports_degenerate_when_all_pairs_lie_on_one_line() {
    // 50 points along a tilted line: the rotation about the line is undetermined.
    let direction = Vector3::new(0.3_f32, -0.5, 0.8).normalize();
    let line: PointCloud = (0..50)
        .map(|i| geometry::Point3::from(direction * (i as f32 * 0.01)))
        .collect();
    let shifted = Isometry3::translation(0.002, -0.001, 0.003);
    for max_iterations in [1, 2, 3, 7] {
        let limited = IcpConfig {
            max_iterations,
            ..config(IcpMethod::PointToPoint)
        };
        for init in [Isometry3::identity(), shifted] {
            assert!(
                matches!(
                    icp(&line, &line, &init, &limited),
                    Err(IcpError::Degenerate { iteration: 1 })
                ),
                "{max_iterations} iterations from {init:?}: {:?}",
                icp(&line, &line, &init, &limited)
            );
        }
    }
}

#[test]
fn point_to_plane_fitness_counts_pairs_whose_target_has_no_normal() {
    // The scene plus a line of points 1 m away: the line's neighbourhoods are collinear,
    // so its target points get no normal, yet they pair exactly with the source.
    let (_, mut target) = views(5_000);
    let scene_len = target.len();
    target
        .points
        .extend((0..30).map(|i| geometry::Point3::new(1.0 + i as f32 * 0.01, 1.0, 1.0)));
    let outcome = icp(
        &target,
        &target,
        &Isometry3::identity(),
        &config(IcpMethod::PointToPlane),
    )
    .expect("icp runs");
    assert!(scene_len < target.len());
    assert_eq!(outcome.fitness, 1.0, "{outcome:?}");
    assert!(outcome.rmse_m < 1e-6, "{outcome:?}");
}
