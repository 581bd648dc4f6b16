use geometry::{Point3, PointCloud, VoxelError, voxel_downsample};

use crate::assert_near;
use crate::scene::Sampler;

#[test]
fn merge_concatenates_clouds_in_the_order_given() {
    let a = PointCloud::from(vec![Point3::new(1.0, 0.0, 0.0), Point3::new(2.0, 0.0, 0.0)]);
    let b = PointCloud::default();
    let c = PointCloud::from(vec![Point3::new(3.0, 0.0, 0.0)]);
    let merged = PointCloud::merge([&a, &b, &c]);
    assert_eq!(
        merged.points,
        vec![
            Point3::new(1.0, 0.0, 0.0),
            Point3::new(2.0, 0.0, 0.0),
            Point3::new(3.0, 0.0, 0.0)
        ]
    );
    assert!(PointCloud::merge([]).is_empty());
}

#[test]
fn voxel_downsample_keeps_one_centroid_per_occupied_voxel() {
    let cloud = PointCloud::from(vec![
        // voxel (0, 0, 0) of 0.1 m: centroid (0.03, 0.04, 0.05)
        Point3::new(0.01, 0.02, 0.03),
        Point3::new(0.05, 0.06, 0.07),
        // voxel (-1, 0, 0): a single point stays where it is
        Point3::new(-0.05, 0.05, 0.05),
        // voxel (2, 2, 2): three points
        Point3::new(0.21, 0.21, 0.21),
        Point3::new(0.22, 0.22, 0.22),
        Point3::new(0.29, 0.29, 0.29),
        // not finite: dropped
        Point3::new(f32::NAN, 0.0, 0.0),
    ]);
    let down = voxel_downsample(&cloud, 0.1).expect("valid size");
    assert_eq!(down.len(), 3);
    // Voxels come out in index order: (-1,0,0), (0,0,0), (2,2,2).
    assert_near(down.points[0], Point3::new(-0.05, 0.05, 0.05), 1e-7);
    assert_near(down.points[1], Point3::new(0.03, 0.04, 0.05), 1e-7);
    assert_near(down.points[2], Point3::new(0.24, 0.24, 0.24), 1e-7);
}

#[test]
fn voxel_downsample_is_deterministic_and_independent_of_input_order() {
    let mut sampler = Sampler::new(7);
    let points: Vec<Point3> = (0..50_000)
        .map(|_| {
            Point3::new(
                sampler.range(-0.5, 0.5),
                sampler.range(-0.5, 0.5),
                sampler.range(0.0, 0.3),
            )
        })
        .collect();
    let cloud = PointCloud::from(points.clone());
    let first = voxel_downsample(&cloud, 0.05).expect("valid size");
    let second = voxel_downsample(&cloud, 0.05).expect("valid size");
    assert_eq!(first, second);
    let reversed: PointCloud = points.into_iter().rev().collect();
    let third = voxel_downsample(&reversed, 0.05).expect("valid size");
    assert_eq!(first.len(), third.len());
    // 20 x 20 x 6 voxels, all occupied at ~20 points each.
    assert_eq!(first.len(), 20 * 20 * 6);
    for (a, b) in first.points.iter().zip(&third.points) {
        assert_near(*a, *b, 1e-6);
    }
}

#[test]
fn voxel_downsample_refuses_a_size_that_is_not_positive_and_finite() {
    let cloud = PointCloud::from(vec![Point3::origin()]);
    for voxel_m in [0.0, -0.01, f32::NAN, f32::INFINITY] {
        assert!(matches!(
            voxel_downsample(&cloud, voxel_m),
            Err(VoxelError::InvalidSize { .. })
        ));
    }
}
