//! Criterion benchmarks: the per-grab transform + ROI over a 1280x720 cloud, ICP of two
//! ~20k-point views, voxel downsampling and dimensioning.

// criterion_group! defines an undocumented pub fn.
#![allow(missing_docs)]

use criterion::{Criterion, criterion_group, criterion_main};
use geometry::{
    DimensionConfig, IcpConfig, IcpMethod, Point3, PointCloud, Roi3, Transform, Transformation,
    dimension, icp, voxel_downsample,
};
use nalgebra::{Isometry3, Vector3};
use std::hint::black_box;

#[path = "../tests/it/scene.rs"]
#[allow(
    dead_code,
    reason = "the tests use more of the scene helpers than the bench"
)]
mod scene;

use scene::{Sampler, parcel, scene};

/// A 1280x720 camera cloud (921,600 points): a table 0.9 m away with a parcel whose lid is
/// 0.7 m away in the middle third of the image, deprojected with D415-like intrinsics.
fn camera_cloud() -> Vec<Point3> {
    let (fx, fy, cx, cy) = (910.0_f32, 910.0_f32, 640.0_f32, 360.0_f32);
    let mut points = Vec::with_capacity(1280 * 720);
    for v in 0..720 {
        for u in 0..1280 {
            let lid = (427..853).contains(&u) && (240..480).contains(&v);
            let z = if lid { 0.7 } else { 0.9 };
            points.push(Point3::new(
                (u as f32 - cx) / fx * z,
                (v as f32 - cy) / fy * z,
                z,
            ));
        }
    }
    points
}

fn listing_a4() -> Transform {
    let doc = Transformation::from_json(
        br#"{
  "scale_matrix" : [[1.000000],[1.000000],[1.000000]],
  "rotation_matrix" : [[0.999524,0.030429,-0.005019],
                      [0.030511,-0.999388,0.017115],
                      [-0.004495,-0.017260,-0.999841]],
  "translation_matrix" : [[-0.113241],[0.111672],[-0.769009]],
  "post_scale_matrix" : [[1.000000],[1.000000],[1.000000]],
  "post_rotation_matrix" : [[0.000000],[0.000000],[0.000000]],
  "post_translation_matrix" : [[0.000000],[0.000000],[0.000000]]
}"#,
    );
    match doc.map(|d| d.to_transform()) {
        Ok(Ok(t)) => t,
        other => panic!("Listing A.4 must compile: {other:?}"),
    }
}

fn transform_and_roi(c: &mut Criterion) {
    let points = camera_cloud();
    let transform = listing_a4();
    let roi = match Roi3::new(Point3::new(-0.3, -0.3, -1.7), Point3::new(0.3, 0.3, -1.4)) {
        Ok(roi) => roi,
        Err(e) => panic!("{e}"),
    };
    let kept = transform.apply_and_crop(&points, &roi).len();
    let mut group = c.benchmark_group("transform");
    group.sample_size(20);
    group.bench_function(
        format!("apply_and_crop 921600 points (keeps {kept})"),
        |b| {
            b.iter(|| transform.apply_and_crop(black_box(&points), black_box(&roi)));
        },
    );
    group.bench_function("apply_in_place 921600 points", |b| {
        let mut cloud = PointCloud::from(points.clone());
        b.iter(|| transform.apply_in_place(black_box(&mut cloud)));
    });
    group.bench_function("voxel_downsample 921600 points at 5 mm", |b| {
        let cloud = PointCloud::from(points.clone());
        b.iter(|| voxel_downsample(black_box(&cloud), 0.005));
    });
    group.finish();
}

fn registration(c: &mut Criterion) {
    let truth = Isometry3::new(
        Vector3::new(0.02_f32, -0.015, 0.0158),
        Vector3::new(0.1_f32, -0.1, 1.0).normalize() * 5.0_f32.to_radians(),
    );
    let target = scene(&mut Sampler::new(1), 20_000, 0.35, &parcel());
    let mut source = scene(&mut Sampler::new(2), 20_000, 0.35, &parcel());
    Transform::from(truth.inverse()).apply_in_place(&mut source);
    let mut group = c.benchmark_group("icp");
    group.sample_size(10);
    for (name, method, max_iterations) in [
        (
            "point_to_plane 20k/20k to convergence",
            IcpMethod::PointToPlane,
            100,
        ),
        (
            "point_to_point 20k/20k 30 iterations",
            IcpMethod::PointToPoint,
            30,
        ),
    ] {
        let config = IcpConfig {
            method,
            max_iterations,
            max_correspondence_m: 0.1,
            ..IcpConfig::default()
        };
        group.bench_function(name, |b| {
            b.iter(|| {
                icp(
                    black_box(&source),
                    black_box(&target),
                    &Isometry3::identity(),
                    &config,
                )
            });
        });
    }
    group.finish();

    let mut sampler = Sampler::new(11);
    let mut parcel_cloud = scene(&mut sampler, 60_000, 0.7, &parcel());
    for p in &mut parcel_cloud.points {
        p.z += sampler.normal(0.001);
    }
    let mut group = c.benchmark_group("dimension");
    group.sample_size(10);
    group.bench_function("dimension 60k-point scene", |b| {
        b.iter(|| dimension(black_box(&parcel_cloud), &DimensionConfig::default()));
    });
    group.finish();
}

criterion_group!(benches, transform_and_roi, registration);
criterion_main!(benches);
