use geometry::{DimensionConfig, DimensionError, Dimensions, Point3, PointCloud, dimension};

use crate::scene::{BoxSpec, Sampler, parcel, scene};

/// A parcel scene as an overhead camera sees it: depth noise (mostly along z), a little
/// lateral noise, and outliers scattered through the volume at least 5 cm from the box
/// (an outlier touching the parcel is, to geometry, part of it).
fn noisy_scene(b: &BoxSpec, seed: u64) -> PointCloud {
    let mut sampler = Sampler::new(seed);
    let mut cloud = scene(&mut sampler, 60_000, 0.7, b);
    for p in &mut cloud.points {
        p.x += sampler.normal(0.0002);
        p.y += sampler.normal(0.0002);
        p.z += sampler.normal(0.001);
    }
    let grown = BoxSpec {
        length_m: b.length_m + 0.1,
        width_m: b.width_m + 0.1,
        ..*b
    };
    let mut outliers = 0;
    while outliers < 60 {
        let p = Point3::new(
            sampler.range(-0.7, 0.7),
            sampler.range(-0.7, 0.7),
            sampler.range(0.0, 0.6),
        );
        if !(grown.covers(p.x, p.y) && p.z < b.height_m + 0.05) {
            cloud.points.push(p);
            outliers += 1;
        }
    }
    cloud
}

/// Distance between two angles in degrees, modulo 90.
fn yaw_error_mod_90(a: f64, b: f64) -> f64 {
    let d = (a - b).rem_euclid(90.0);
    d.min(90.0 - d)
}

#[track_caller]
fn assert_measures(found: &Dimensions, b: &BoxSpec, tol_mm: f64) {
    let expect = [
        f64::from(b.length_m.max(b.width_m)) * 1e3,
        f64::from(b.length_m.min(b.width_m)) * 1e3,
        f64::from(b.height_m) * 1e3,
    ];
    let got = [found.length_mm, found.width_mm, found.height_mm];
    for (g, e) in got.iter().zip(expect) {
        assert!((g - e).abs() <= tol_mm, "{got:?} vs {expect:?}: {found:?}");
    }
    assert!(
        yaw_error_mod_90(found.yaw_deg, f64::from(b.yaw_deg)) < 0.5,
        "yaw {} vs {}",
        found.yaw_deg,
        b.yaw_deg
    );
}

#[test]
fn box_on_the_floor_measures_within_3_mm_and_yaw_modulo_90() {
    let b = parcel();
    let found = dimension(&noisy_scene(&b, 11), &DimensionConfig::default()).expect("measures");
    assert_measures(&found, &b, 3.0);
    let volume = found.length_mm * found.width_mm * found.height_mm * 1e-6;
    assert!((found.volume_l - volume).abs() < 1e-9);
    assert!((found.volume_l - 24.0).abs() < 0.5, "{found:?}");
    // The corners are the footprint of the box, in order around it.
    for corner in found.corners_m {
        let d = ((corner[0] - 0.05).powi(2) + (corner[1] + 0.03).powi(2)).sqrt();
        assert!(
            (d - 0.25).abs() < 0.003,
            "{corner:?} is not a corner: {found:?}"
        );
    }
    assert!(found.points > 10_000 && found.points < 60_000, "{found:?}");
}

#[test]
fn a_cloud_merged_from_the_same_view_three_times_measures_as_one() {
    let b = parcel();
    let once = noisy_scene(&b, 12);
    let mut thrice = once.clone();
    for _ in 0..2 {
        thrice.points.extend_from_slice(&once.points);
    }
    let config = DimensionConfig::default();
    let one = dimension(&once, &config).expect("measures once");
    let three = dimension(&thrice, &config).expect("measures the same points three times");
    assert_measures(&three, &b, 3.0);
    assert!(
        (three.length_mm - one.length_mm).abs() < 1.0,
        "{one:?} vs {three:?}"
    );
}

#[test]
fn length_is_the_longer_side_whatever_the_orientation() {
    for (yaw_deg, seed) in [(0.0, 21), (75.0, 22), (-40.0, 23), (100.0, 24)] {
        let b = BoxSpec {
            center_xy: [-0.1, 0.1],
            length_m: 0.25,
            width_m: 0.5, // the long side runs along the box's local y
            height_m: 0.12,
            yaw_deg,
        };
        let found =
            dimension(&noisy_scene(&b, seed), &DimensionConfig::default()).expect("measures");
        assert!(found.length_mm >= found.width_mm);
        assert!(found.yaw_deg > -90.0 && found.yaw_deg <= 90.0, "{found:?}");
        assert_measures(&found, &b, 3.0);
    }
}

#[test]
fn the_largest_object_is_measured_and_smaller_ones_ignored() {
    let big = parcel();
    let mut cloud = noisy_scene(&big, 31);
    // A small carton 30 cm away from the parcel: not connected, fewer points.
    let small = BoxSpec {
        center_xy: [-0.45, 0.45],
        length_m: 0.1,
        width_m: 0.1,
        height_m: 0.1,
        yaw_deg: 10.0,
    };
    let mut extra = scene(&mut Sampler::new(32), 20_000, 0.7, &small);
    extra.points.retain(|p| p.z > 0.0);
    cloud.extend_from(&extra);
    let found = dimension(&cloud, &DimensionConfig::default()).expect("measures");
    assert_measures(&found, &big, 3.0);
}

/// Flying pixels: a stereo camera 1 m above the origin reports points part way along
/// the ray between a lid edge and the floor behind it. They touch the parcel, so they are
/// in its cluster, and they lie outside its footprint.
#[test]
fn flying_pixels_between_the_lid_edge_and_the_floor_do_not_widen_the_footprint() {
    let b = parcel();
    let mut cloud = noisy_scene(&b, 41);
    let mut sampler = Sampler::new(42);
    let camera = Point3::new(0.0, 0.0, 1.0);
    let mut flying = 0;
    while flying < 600 {
        // A point on the lid's outline ...
        let (u, v) = (sampler.range(-0.5, 0.5), sampler.range(-0.5, 0.5));
        let (u, v) = if sampler.unit() < 0.5 {
            (u.signum() * 0.5, v)
        } else {
            (u, v.signum() * 0.5)
        };
        let (lx, ly) = (u * b.length_m, v * b.width_m);
        let edge = b.world_point(lx, ly, b.height_m);
        // ... pushed away from the camera along its ray, to somewhere above the floor.
        let ray = edge - camera;
        let t = sampler.range(1.0, 1.0 / (1.0 - b.height_m) * 0.98);
        let p = camera + ray * t;
        if p.z > 0.012 && p.z < b.height_m - 0.003 {
            cloud.points.push(p);
            flying += 1;
        }
    }
    let found = dimension(&cloud, &DimensionConfig::default()).expect("measures");
    assert_measures(&found, &b, 3.0);
    let all_points = DimensionConfig {
        lid_band_m: 1.0,
        min_neighbours: 0,
        ..DimensionConfig::default()
    };
    let naive = dimension(&cloud, &all_points).expect("measures");
    assert!(
        naive.length_mm > found.length_mm + 10.0,
        "the flying pixels must matter without the lid band: {naive:?}"
    );
}

#[test]
fn an_empty_floor_has_nothing_to_measure() {
    let floor: PointCloud = (0..1000)
        .map(|i| Point3::new((i % 40) as f32 * 0.01, (i / 40) as f32 * 0.01, 0.002))
        .collect();
    assert_eq!(
        dimension(&floor, &DimensionConfig::default()),
        Err(DimensionError::TooFewPoints {
            found: 0,
            needed: 50
        })
    );
}

#[test]
fn invalid_thresholds_are_refused_naming_the_field() {
    let config = DimensionConfig {
        height_quantile: 1.5,
        ..DimensionConfig::default()
    };
    let e = dimension(&PointCloud::default(), &config).expect_err("refused");
    assert_eq!(
        e.to_string(),
        "dimension: `height_quantile` must be in (0, 1]"
    );
}
