//! Round parcels (standing cylinders, lying tubes) under one camera, straight above or
//! tilted, and under several: measured, never refused for being round.

use geometry::{DimensionConfig, Point3, PointCloud, Transform, View, parcels};
use nalgebra::{Matrix3, Vector3};
use rgbd::{Camera, Scene, SyntheticCamera};

/// The world points above a 5 mm floor cut of every camera of `scene` after the
/// flying-pixel stage and the spatial filter (librealsense's defaults), as cameras
/// prepared by `measure --prepare` send them, and their views.
pub(crate) fn prepared_clouds(scene: &Scene) -> (PointCloud, Vec<View>) {
    clouds(scene, true)
}

/// The same, with the flying-pixel stage before the spatial filter when `flying`.
fn clouds(scene: &Scene, flying: bool) -> (PointCloud, Vec<View>) {
    use rgbd::filter::{FlyingPixelsConfig, SpatialConfig};
    use rgbd::{PostProcessing, PostProcessingConfig};
    let mut cloud = PointCloud::default();
    let mut views = Vec::new();
    for camera in &scene.cameras {
        let cam = SyntheticCamera::new(scene, &camera.serial).unwrap();
        let k = cam.depth_intrinsics().unwrap();
        let raw = cam.render_depth(1);
        let config = PostProcessingConfig {
            flying_pixels: flying.then(FlyingPixelsConfig::default),
            spatial: Some(SpatialConfig::default()),
            ..PostProcessingConfig::from_json(b"{}").unwrap()
        };
        let mut chain = PostProcessing::new(&config, Some(55.0)).unwrap();
        let (frame, _) = chain.process(&raw, &k).unwrap();
        let pose = cam.true_pose().unwrap();
        for v in 0..frame.height {
            for u in 0..frame.width {
                if let Some(z) = frame.metres_at(u, v) {
                    let p =
                        pose.transform_point(k.deproject([u as f32, v as f32], z).map(f64::from));
                    if p[2] >= 0.005 {
                        cloud
                            .points
                            .push(Point3::new(p[0] as f32, p[1] as f32, p[2] as f32));
                    }
                }
            }
        }
        let r = pose.rotation.map(|row| row.map(|v| v as f32));
        let t = pose.translation.map(|v| v as f32);
        let to_common = Transform {
            linear: Matrix3::new(
                r[0][0], r[0][1], r[0][2], r[1][0], r[1][1], r[1][2], r[2][0], r[2][1], r[2][2],
            ),
            translation: Vector3::new(t[0], t[1], t[2]),
        };
        views.push(View::pinhole(
            to_common, k.fx, k.fy, k.ppx, k.ppy, k.width, k.height,
        ));
    }
    (cloud, views)
}

fn scene(seed: u64, cameras: &[[f64; 3]], object: &str) -> Scene {
    let mut text = format!("seed = {seed}\n");
    for (n, c) in cameras.iter().enumerate() {
        text += &format!(
            "[[camera]]\nserial = \"{:012}\"\nposition = {c:?}\nlook_at = [0.0, 0.0, 0.0]\n",
            n + 1
        );
    }
    Scene::from_toml(&format!("{text}\n{object}")).unwrap()
}

/// A cylinder 160 mm across and 300 mm high (issue 44) under one D415 1.3 m up, straight
/// above it and tilted 40 degrees, eight noise seeds each.
#[test]
fn a_standing_cylinder_is_measured_not_refused_straight_below_and_tilted() {
    let object = "[[cylinder]]\nradius = 0.08\nheight = 0.30\ncenter = [0.0, 0.0]\n";
    for camera in [[0.0, 0.0, 1.3], [0.0, -1.09, 1.3]] {
        for seed in 0..8 {
            let s = scene(seed, &[camera], object);
            let (cloud, views) = prepared_clouds(&s);
            let found = parcels(&cloud, &DimensionConfig::default(), &views).unwrap();
            assert_eq!(found.parcels.len(), 1, "seed {seed}, {camera:?}");
            let p = &found.parcels[0];
            let d = &p.dimensions;
            // The lid's rim seen from the side ends short of the wall, or the pixels'
            // noise moves its corners: the disc was no disc, and its rectangle's empty
            // corners read as a notch (two parcels side by side).
            assert!(p.isolated && p.complete, "seed {seed}, {camera:?}: {p:?}");
            for (got, truth) in [d.length_mm, d.width_mm, d.height_mm]
                .into_iter()
                .zip([160.0, 160.0, 300.0])
            {
                assert!((got - truth).abs() <= 5.0, "seed {seed}, {camera:?}: {d:?}");
            }
        }
    }
}

/// Counter-based random numbers (SplitMix64) for the variants.
struct Draw(u64);

impl Draw {
    /// Uniform in [lo, hi).
    fn uniform(&mut self, lo: f64, hi: f64) -> f64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^= z >> 31;
        lo + (hi - lo) * ((z >> 11) as f64 / (1u64 << 53) as f64)
    }
}

/// Variant `index` of the round things: a standing cylinder (even indices: radius 30-200
/// mm, 50-500 mm high) or a lying tube (odd: radius 30-100 mm, 200-900 mm long, any
/// yaw), or with `bag` a polybag (150-600 mm long, 100 mm to its length wide, 50-300 mm
/// high, sagging 0-0.5, any yaw), 5 cm about the origin, under one D415 (two of every three pairs of indices) or
/// two or three around it, each 1-2.2 m up (high enough to see the whole object) and
/// tilted 0-45 degrees towards it. Its description and the scene.
fn variant(index: u64, bag: bool) -> (String, Scene) {
    let mut d = Draw(index.wrapping_mul(0x2545_f491_4f6c_dd1d) ^ 0x0072_6f75_6e64);
    let lying = index % 2 == 1;
    let centre = [d.uniform(-0.05, 0.05), d.uniform(-0.05, 0.05)];
    let (object, what, top, extent) = if bag {
        let l = d.uniform(0.15, 0.6);
        let w = d.uniform(0.1, l);
        let h = d.uniform(0.05, 0.3);
        let sag = d.uniform(0.0, 0.5);
        let yaw = d.uniform(-90.0, 90.0);
        (
            format!(
                "[[bag]]\nsize = [{l}, {w}, {h}]\nsag = {sag}\ncenter = {centre:?}\nyaw_deg = {yaw}\n"
            ),
            format!(
                "bag {:.0}x{:.0}x{:.0} sag {sag:.2} yaw {yaw:.0}",
                l * 1e3,
                w * 1e3,
                h * 1e3
            ),
            h,
            l,
        )
    } else if lying {
        let r = d.uniform(0.03, 0.10);
        let l = d.uniform(0.2, 0.9);
        let yaw = d.uniform(-90.0, 90.0);
        (
            format!("[[tube]]\nradius = {r}\nlength = {l}\ncenter = {centre:?}\nyaw_deg = {yaw}\n"),
            format!("tube r {:.0} l {:.0} yaw {yaw:.0}", r * 1e3, l * 1e3),
            2.0 * r,
            l,
        )
    } else {
        let r = d.uniform(0.03, 0.20);
        let h = d.uniform(0.05, 0.5);
        (
            format!("[[cylinder]]\nradius = {r}\nheight = {h}\ncenter = {centre:?}\n"),
            format!("cylinder r {:.0} h {:.0}", r * 1e3, h * 1e3),
            h,
            2.0 * r,
        )
    };
    let cameras = if (index / 2) % 3 == 2 {
        2 + (index / 6) % 2
    } else {
        1
    };
    let azimuth = d.uniform(0.0, 360.0);
    let lowest = 1.0f64.max(top + 0.5 + extent);
    let mut text = format!("seed = {index}\n");
    let mut what = what;
    for k in 0..cameras {
        let z = d.uniform(lowest, 2.2f64.max(lowest + 0.1));
        let tilt = d.uniform(0.0, 45.0);
        let a = (azimuth + 360.0 * k as f64 / cameras as f64 + d.uniform(-30.0, 30.0)).to_radians();
        let off = z * tilt.to_radians().tan();
        let at = [centre[0] + off * a.cos(), centre[1] + off * a.sin(), z];
        text += &format!(
            "[[camera]]\nserial = \"{:012}\"\nposition = {at:?}\nlook_at = [{}, {}, 0.0]\n",
            k + 1,
            centre[0],
            centre[1]
        );
        what += &format!(", camera {z:.2} m up tilted {tilt:.0} deg");
    }
    (
        what,
        Scene::from_toml(&format!("{text}\n{object}")).unwrap(),
    )
}

/// Standing cylinders of every size under one camera tilted up to 45 degrees or under
/// several ([`variant`]): each one parcel, measured (not refused), within one division
/// (5 mm) of its smallest enclosing cuboid. The first 8 by default;
/// `ROUND_VARIANTS=N` runs N, `ROUND_KIND=tube` the lying tubes instead, `ROUND_KIND=bag`
/// polybags under the same cameras (see
/// docs/benchmarks.md for what more of them give).
#[test]
fn standing_cylinders_under_a_tilted_camera_or_several_are_measured_within_a_division() {
    let count: u64 = std::env::var("ROUND_VARIANTS").map_or(8, |v| v.parse().unwrap());
    let lying = std::env::var("ROUND_KIND").is_ok_and(|k| k == "tube");
    let bag = std::env::var("ROUND_KIND").is_ok_and(|k| k == "bag");
    let mut failed = Vec::new();
    for index in (0..count).map(|k| 2 * k + u64::from(lying)) {
        let (what, s) = variant(index, bag);
        let truth = &s.truths()[0];
        let (cloud, views) = prepared_clouds(&s);
        let found = parcels(&cloud, &DimensionConfig::default(), &views).unwrap();
        let p = &found.parcels[0];
        let d = &p.dimensions;
        let errors = [
            d.length_mm - truth.length_mm(),
            d.width_mm - truth.width_mm(),
            d.height_mm - truth.height_mm(),
        ];
        let measured = found.parcels.len() == 1 && p.isolated && p.complete;
        let line = format!(
            "{index}: {what}: {:+.1} {:+.1} {:+.1} mm, {:?}{}",
            errors[0],
            errors[1],
            errors[2],
            p.shape,
            if measured {
                String::new()
            } else {
                format!(
                    ", refused ({} parcels; isolated {}, complete {}, coverage {:.3})",
                    found.parcels.len(),
                    p.isolated,
                    p.complete,
                    p.coverage
                )
            }
        );
        eprintln!("{line}");
        if !measured || errors.iter().any(|e| e.abs() > 5.0) {
            failed.push(line);
        }
    }
    assert!(
        failed.is_empty(),
        "{} of {count}: {failed:#?}",
        failed.len()
    );
}

/// A short, thick tube (224 mm long, radius 84 mm) under one camera 2.04 m up tilted 44
/// degrees (variant 49): the camera sees its near flank and its crest, and the far side
/// until it turns away, 0.755 of the diameter once the flying-pixel stage has dropped
/// the grazing pixels. It is round, and complete over the strip where its circle was
/// seen (its whole footprint, of which the far side's strip is out of every camera's
/// sight, is 0.77 covered).
#[test]
fn a_short_tube_under_a_camera_tilted_44_degrees_is_round_and_seen_whole() {
    let (what, s) = variant(49, false);
    let truth = &s.truths()[0];
    let (cloud, views) = prepared_clouds(&s);
    let found = parcels(&cloud, &DimensionConfig::default(), &views).unwrap();
    let p = &found.parcels[0];
    let d = &p.dimensions;
    assert_eq!(found.parcels.len(), 1, "{what}: {found:?}");
    assert_eq!(p.shape, geometry::Shape::Round, "{what}: {p:?}");
    assert!(p.isolated && p.complete, "{what}: {p:?}");
    for (m, t) in [
        (d.length_mm, truth.length_mm()),
        (d.width_mm, truth.width_mm()),
        (d.height_mm, truth.height_mm()),
    ] {
        assert!((m - t).abs() <= 5.0, "{what}: {m:.1} for {t:.1}");
    }
}

/// A tube 340 mm long beside three boxes under four cameras (certification set, seed 1,
/// scene 256): one camera alone sees its far end, from 1.6 m at a slant, and its points
/// there lie at an eighth of the density the others give the rest of it, too sparse for
/// the lid, which ended 71 mm short of that end. Over CoAP the tube read round and 269 mm
/// long, accepted; here (another frame's noise) irregular and out of view. Its crest runs
/// on to the end, and so does the tube.
#[test]
fn a_tube_whose_far_end_one_camera_sees_sparsely_is_measured_to_its_end() {
    let scene = crate::parcels::cert_1(256);
    let truths = scene.truths();
    let tube = truths
        .iter()
        .find(|t| t.kind == rgbd::scene::ObjectKind::Tube)
        .expect("a tube");
    let (cloud, views) = prepared_clouds(&scene);
    let found = parcels(&cloud, &DimensionConfig::default(), &views).unwrap();
    let centre = |c: &[[f64; 2]; 4]| [0, 1].map(|k| c.iter().map(|p| p[k]).sum::<f64>() / 4.0);
    let p = found
        .parcels
        .iter()
        .min_by(|a, b| {
            let d = |f: &geometry::ParcelFit| {
                let c = centre(&f.dimensions.corners_m);
                (c[0] - tube.center[0]).hypot(c[1] - tube.center[1])
            };
            d(a).total_cmp(&d(b))
        })
        .expect("parcels");
    let d = &p.dimensions;
    assert_eq!(p.shape, geometry::Shape::Round, "{p:?}");
    assert!(p.isolated && p.complete && !p.out_of_view, "{p:?}");
    for (m, t) in [
        (d.length_mm, tube.length_mm()),
        (d.width_mm, tube.width_mm()),
        (d.height_mm, tube.height_mm()),
    ] {
        assert!((m - t).abs() <= 5.0, "{m:.1} for {t:.1}: {p:?}");
    }
}

/// How many points of `cloud` lie from `margin_m` to 100 mm beyond the footprint of
/// `truth` (a convex quadrilateral), where flying pixels land; farther out lies the floor's
/// noise, which prepared cameras cut away.
fn beyond_footprint(cloud: &PointCloud, truth: &rgbd::scene::Truth, margin_m: f64) -> usize {
    let f = &truth.footprint;
    let centre = [
        f.iter().map(|c| c[0]).sum::<f64>() / 4.0,
        f.iter().map(|c| c[1]).sum::<f64>() / 4.0,
    ];
    cloud
        .points
        .iter()
        .filter(|p| {
            let q = [f64::from(p.x), f64::from(p.y)];
            let out = (0..4).map(|k| {
                let (a, b) = (f[k], f[(k + 1) % 4]);
                let edge = [b[0] - a[0], b[1] - a[1]];
                let n = edge[0].hypot(edge[1]);
                // The outward normal: away from the centre.
                let mut normal = [edge[1] / n, -edge[0] / n];
                if (centre[0] - a[0]) * normal[0] + (centre[1] - a[1]) * normal[1] > 0.0 {
                    normal = [-normal[0], -normal[1]];
                }
                (q[0] - a[0]) * normal[0] + (q[1] - a[1]) * normal[1]
            });
            let farthest = out.fold(f64::MIN, f64::max);
            farthest > margin_m && farthest <= 0.1
        })
        .count()
}

/// A polybag under tilted cameras: the pixels that straddle its edge and the floor float
/// along their rays, centimetres beyond its side (0.4 to 1.5 % of the cloud lies from 10
/// to 100 mm beyond its foot); the flying-pixel stage drops them (under one in 500
/// points there then, the floor's noise).
#[test]
fn the_flying_pixel_stage_drops_the_points_floating_beyond_a_bag() {
    for index in [0, 6, 8, 10] {
        let (what, s) = variant(index, true);
        let truth = &s.truths()[0];
        let (cloud, _) = clouds(&s, false);
        let (beyond, all) = (beyond_footprint(&cloud, truth, 0.010), cloud.points.len());
        assert!(
            beyond * 250 > all,
            "{what}, without: {beyond} of {all} points"
        );
        let (cloud, _) = clouds(&s, true);
        let (beyond, all) = (beyond_footprint(&cloud, truth, 0.010), cloud.points.len());
        assert!(beyond * 500 < all, "{what}, with: {beyond} of {all} points");
    }
}
