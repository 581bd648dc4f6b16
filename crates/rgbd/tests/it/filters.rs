//! The filters' own contracts: configuration, sizes, intrinsics, invalid pixels.
//! (Agreement with librealsense is tested in `librealsense.rs`.)

use rgbd::FrameFilter as _;
use rgbd::filter::{
    Decimation, DisparityFrame, FilterError, HoleFilling, HoleFillingMode, PostProcessing,
    PostProcessingConfig, PostProcessingError, Roi2, RoiCrop, SpatialFilter, SpatialParams,
    Threshold,
};
use rgbd::{ColorFormat, ColorFrame, Deprojector, DepthFrame, Intrinsics, d415, deproject_frame};

fn frame(width: u32, height: u32, value: impl Fn(u32, u32) -> u16) -> DepthFrame {
    DepthFrame {
        width,
        height,
        stride: width as usize,
        depth_scale: DepthFrame::DEFAULT_DEPTH_SCALE,
        timestamp_us: 0,
        frame_number: 1,
        data: (0..height)
            .flat_map(|y| (0..width).map(move |x| (x, y)))
            .map(|(x, y)| value(x, y))
            .collect(),
    }
}

#[test]
fn the_thesis_postprocessing_section_parses_as_on_off_flags() {
    let c = PostProcessingConfig::from_json(br#"{"decimation":1,"spatial":1,"holefilling":0}"#)
        .unwrap();
    assert_eq!(c.decimation.unwrap().magnitude, 2);
    assert_eq!(c.spatial.unwrap().delta, 20);
    assert!(c.holefilling.is_none());
    assert_eq!(
        c.to_json(),
        r#"{"decimation":1,"holefilling":0,"spatial":1}"#
    );
}

#[test]
fn stage_objects_set_parameters_and_round_trip() {
    let json = br#"{"decimation":{"magnitude":4},
        "spatial":{"alpha":0.35,"delta":8,"iterations":3,"holes_fill":2},
        "holefilling":{"mode":"nearest_from_around"}}"#;
    let c = PostProcessingConfig::from_json(json).unwrap();
    assert_eq!(c.decimation.unwrap().magnitude, 4);
    assert_eq!(c.spatial.unwrap().iterations, 3);
    assert_eq!(
        c.holefilling.unwrap().mode,
        HoleFillingMode::NearestFromAround
    );
    assert_eq!(
        PostProcessingConfig::from_json(c.to_json().as_bytes()),
        Ok(c)
    );
}

#[test]
fn out_of_range_values_name_the_field_and_what_it_accepts() {
    let err = |json: &str| PostProcessingConfig::from_json(json.as_bytes()).unwrap_err();
    assert_eq!(
        err(r#"{"decimation":{"magnitude":9}}"#),
        PostProcessingError::Invalid {
            field: "postprocessing.decimation.magnitude",
            found: "9".to_owned(),
            allowed: "an integer from 1 to 8",
        }
    );
    let e = err(r#"{"spatial":{"delta":300}}"#).to_string();
    assert!(
        e.contains("postprocessing.spatial.delta") && e.contains("1 to 50"),
        "{e}"
    );
    let e = err(r#"{"spatial":{"alpha":0.1}}"#).to_string();
    assert!(
        e.contains("postprocessing.spatial.alpha") && e.contains("0.25 to 1"),
        "{e}"
    );
    let e = err(r#"{"holefilling":2}"#).to_string();
    assert!(e.contains("postprocessing.holefilling: 0 (off), 1"), "{e}");
    let e = err(r#"{"holefilling":{"mode":"average"}}"#).to_string();
    assert!(e.contains("fill_from_left"), "{e}");
    let e = err(r#"{"temporal":1}"#).to_string();
    assert!(e.contains("temporal"), "{e}");
}

#[test]
fn decimated_sizes_are_padded_to_multiples_of_four_as_in_librealsense() {
    let size = |s, w, h| Decimation::new(s).unwrap().output_size(w, h);
    assert_eq!(size(3, 1280, 720), ((426, 240), (428, 240)));
    assert_eq!(size(8, 1280, 720), ((160, 90), (160, 92)));
    assert_eq!(size(5, 848, 480), ((169, 96), (172, 96)));
    assert!(matches!(
        Decimation::new(9),
        Err(FilterError::Parameter {
            field: "magnitude",
            ..
        })
    ));
    assert!(Decimation::new(0).is_err());
}

#[test]
fn a_crop_moves_the_principal_point_so_pixels_keep_their_rays() {
    let k = d415::depth_intrinsics(1280, 720);
    let f = frame(1280, 720, |x, y| 500 + (x + y) as u16 % 300);
    let roi = Roi2 {
        px: 100,
        py: 50,
        width: 64,
        height: 32,
    };
    let mut crop = RoiCrop::new(roi);
    let (out, kc) = crop.process(&f, &k).unwrap();
    assert_eq!(
        (out.width, out.height, kc.width, kc.height),
        (64, 32, 64, 32)
    );
    assert_eq!(out.raw_at(3, 4), f.raw_at(103, 54));
    assert_eq!(
        kc.deproject([3.0, 4.0], 1.0),
        k.deproject([103.0, 54.0], 1.0)
    );
    let outside = Roi2 { px: 1250, ..roi };
    assert!(matches!(
        RoiCrop::new(outside).process(&f, &k),
        Err(FilterError::RoiOutside { .. })
    ));
}

#[test]
fn pixels_without_depth_give_no_point() {
    let k = d415::depth_intrinsics(640, 360);
    let f = frame(640, 360, |x, y| if (x + y) % 3 == 0 { 0 } else { 1000 });
    let points = deproject_frame(&f, &k).unwrap();
    let valid = f.data.iter().filter(|&&v| v != 0).count();
    assert_eq!(points.len(), valid);
    assert!(points.iter().all(|p| (p.z - 1.0).abs() < 1e-6));
    // Row-major: the first point is pixel (1, 0).
    let p = k.deproject([1.0, 0.0], 1.0);
    assert_eq!([points[0].x, points[0].y, points[0].z], p);
}

#[test]
fn frames_that_do_not_match_their_size_or_intrinsics_are_refused() {
    let k = d415::depth_intrinsics(640, 360);
    let mut short = frame(640, 360, |_, _| 1000);
    short.data.truncate(1000);
    let mut d = Deprojector::new();
    assert!(matches!(
        d.deproject_frame(&short, &k, &mut Vec::new()),
        Err(FilterError::FrameSize { .. })
    ));
    let other: Intrinsics = d415::depth_intrinsics(1280, 720);
    let ok = frame(640, 360, |_, _| 1000);
    assert!(matches!(
        Decimation::new(2).unwrap().process(&ok, &other),
        Err(FilterError::IntrinsicsSize { .. })
    ));
}

#[test]
fn a_chain_with_every_stage_off_returns_the_frame() {
    let k = d415::depth_intrinsics(640, 360);
    let f = frame(640, 360, |x, _| if x % 7 == 0 { 0 } else { 900 });
    let config = PostProcessingConfig::from_json(b"{}").unwrap();
    let mut chain = PostProcessing::new(&config, Some(55.0)).unwrap();
    let (out, kout) = chain.process(&f, &k).unwrap();
    assert_eq!((out, kout), (&f, k));
}

#[test]
fn a_camera_without_a_stereo_pair_has_every_stage_but_the_spatial_filter() {
    let k = d415::depth_intrinsics(640, 360);
    let f = frame(640, 360, |x, _| if x % 7 == 0 { 0 } else { 900 });
    let config =
        PostProcessingConfig::from_json(br#"{"decimation": 1, "holefilling": 1}"#).unwrap();
    let mut chain = PostProcessing::new(&config, None).unwrap();
    let (out, _) = chain.process(&f, &k).unwrap();
    assert_eq!((out.width, out.height), (320, 180));
    let spatial = PostProcessingConfig::from_json(br#"{"spatial": 1}"#).unwrap();
    assert_eq!(
        PostProcessing::new(&spatial, None).err(),
        Some(FilterError::NoStereoPair)
    );
    assert!(PostProcessing::new(&spatial, Some(55.0)).is_ok());
}

#[test]
fn the_threshold_keeps_both_bounds() {
    let k = d415::depth_intrinsics(640, 360);
    let f = frame(640, 360, |x, _| [499, 500, 1000, 1001][x as usize % 4]);
    let mut t = Threshold::new(0.5, 1.0).unwrap();
    let (out, _) = t.process(&f, &k).unwrap();
    assert_eq!(&out.data[..4], &[0, 500, 1000, 0]);
    assert!(Threshold::new(0.1, 17.0).is_err());
}

#[test]
fn a_frame_of_width_0_and_stride_0_with_rows_but_no_data_is_filtered_without_panic() {
    let empty = DepthFrame {
        width: 0,
        height: 7,
        stride: 0,
        depth_scale: DepthFrame::DEFAULT_DEPTH_SCALE,
        timestamp_us: 0,
        frame_number: 1,
        data: Vec::new(),
    };
    let k = Intrinsics {
        width: 0,
        height: 7,
        ..d415::depth_intrinsics(640, 360)
    };
    let threshold = Threshold::new(0.5, 1.0).unwrap();
    let mut in_place = empty.clone();
    assert_eq!(threshold.apply_in_place(&mut in_place), Ok(()));
    assert_eq!(in_place, empty);
    let mut copy = Threshold::new(0.5, 1.0).unwrap();
    let (out, _) = copy.process(&empty, &k).unwrap();
    assert_eq!((out.width, out.height, out.data.len()), (0, 7, 0));
    for roi in [
        Roi2 {
            px: 0,
            py: 3,
            width: 0,
            height: 4,
        },
        Roi2 {
            px: 0,
            py: 7,
            width: 0,
            height: 0,
        },
    ] {
        let mut crop = RoiCrop::new(roi);
        let (out, kc) = crop.process(&empty, &k).unwrap();
        assert_eq!(
            (out.width, out.height, kc.height),
            (0, roi.height, roi.height)
        );
    }
    let mut holes = HoleFilling::new(HoleFillingMode::FarestFromAround);
    assert_eq!(holes.apply_in_place(&mut empty.clone()), Ok(()));
}

#[test]
fn spatial_filter_refuses_disparity_data_shorter_than_width_times_height() {
    let mut short = DisparityFrame {
        width: 64,
        height: 32,
        depth_scale: DepthFrame::DEFAULT_DEPTH_SCALE,
        factor: 1.0,
        timestamp_us: 0,
        frame_number: 1,
        data: vec![100.0; 64 * 32 - 1],
    };
    let mut filter = SpatialFilter::new(SpatialParams::default()).unwrap();
    assert_eq!(
        filter.apply(&mut short),
        Err(FilterError::DisparitySize {
            width: 64,
            height: 32,
            needed: 2048,
            len: 2047,
        })
    );
    short.width = u32::MAX;
    short.height = u32::MAX;
    assert!(matches!(
        filter.apply(&mut short),
        Err(FilterError::DisparitySize { .. })
    ));
    short.data.resize(64 * 32, 100.0);
    (short.width, short.height) = (64, 32);
    assert_eq!(filter.apply(&mut short), Ok(()));
}

#[test]
fn pixel_lookups_with_overflowing_stride_give_none() {
    let mut depth = frame(4, 4, |_, _| 1000);
    depth.stride = usize::MAX;
    assert_eq!(depth.raw_at(0, 0), Some(1000));
    assert_eq!(depth.raw_at(1, 3), None);
    let color = ColorFrame {
        width: 4,
        height: 4,
        stride: usize::MAX,
        format: ColorFormat::Rgb8,
        timestamp_us: 0,
        frame_number: 1,
        data: vec![7; 48],
    };
    assert_eq!(color.rgb_at(0, 0), Some([7, 7, 7]));
    assert_eq!(color.rgb_at(3, 2), None);
}
