use std::collections::BTreeSet;

use rgbd::{
    Camera, CameraError, ColorSettings, DepthSettings, ModeError, ModeTable, Scene, SettingError,
    SettingsError, Stream, SyntheticCamera,
};

/// The thesis's modes, written out independently of the crate's table (§3.3.3 and the
/// D415 resolution lists).
fn thesis_modes(stream: Stream) -> BTreeSet<(u32, u32, u32)> {
    let (resolutions, fps): (&[(u32, u32)], &[u32]) = match stream {
        Stream::Color => (
            &[
                (1920, 1080),
                (1280, 720),
                (960, 540),
                (848, 480),
                (640, 480),
                (640, 360),
                (424, 240),
                (320, 240),
                (320, 180),
            ],
            &[6, 15, 30, 60],
        ),
        Stream::Depth => (
            &[
                (1280, 720),
                (848, 480),
                (640, 480),
                (640, 360),
                (480, 270),
                (424, 240),
            ],
            &[6, 15, 25, 30, 60, 90],
        ),
    };
    let largest = resolutions[0];
    let mut modes = BTreeSet::new();
    for &(w, h) in resolutions {
        for &f in fps {
            if (w, h) != largest || f <= 30 {
                modes.insert((w, h, f));
            }
        }
    }
    modes
}

#[test]
fn mode_tables_accept_exactly_the_thesis_modes() {
    let table = ModeTable::d415();
    let widths = [
        160, 256, 320, 424, 480, 640, 848, 960, 1024, 1280, 1920, 3840,
    ];
    let heights = [
        90, 100, 144, 180, 240, 270, 360, 480, 540, 720, 768, 1080, 2160,
    ];
    for stream in [Stream::Color, Stream::Depth] {
        let expected = thesis_modes(stream);
        let mut accepted = BTreeSet::new();
        for w in widths {
            for h in heights {
                for fps in 0..=400 {
                    if table.check(stream, w, h, fps).is_ok() {
                        accepted.insert((w, h, fps));
                    }
                }
            }
        }
        assert_eq!(accepted, expected, "{stream:?}");
    }
    for name in ["RGB8", "BGR8", "RGBA8", "BGRA8"] {
        assert!(table.color_format(name).is_ok());
    }
    assert!(table.depth_format("Z16").is_ok());
}

#[test]
fn refusals_name_the_reason() {
    let t = ModeTable::d415();
    let e = t.color_format("YUYV").unwrap_err();
    assert!(matches!(
        e,
        ModeError::UnknownFormat {
            stream: Stream::Color,
            ..
        }
    ));
    assert_eq!(
        e.to_string(),
        "color format \"YUYV\" is not offered; allowed: RGB8, BGR8, RGBA8, BGRA8"
    );
    assert!(matches!(
        t.depth_format("Y16"),
        Err(ModeError::UnknownFormat { .. })
    ));

    let e = t.check(Stream::Depth, 1920, 1080, 30).unwrap_err();
    assert!(matches!(
        e,
        ModeError::ResolutionNotOffered {
            width: 1920,
            height: 1080,
            ..
        }
    ));
    assert!(
        e.to_string()
            .starts_with("depth resolution 1920x1080 is not offered; allowed: 1280x720, 848x480"),
        "{e}"
    );

    assert_eq!(
        t.check(Stream::Depth, 1280, 720, 60),
        Err(ModeError::FpsNotOffered {
            stream: Stream::Depth,
            fps: 60,
            width: 1280,
            height: 720,
            allowed: vec![6, 15, 25, 30]
        })
    );
    let e = t.check(Stream::Color, 1920, 1080, 60).unwrap_err();
    assert_eq!(
        e.to_string(),
        "color fps 60 is not offered at 1920x1080; allowed: [6, 15, 30]"
    );
    assert!(matches!(
        t.check(Stream::Color, 640, 480, 25),
        Err(ModeError::FpsNotOffered { .. })
    ));
}

#[test]
fn settings_documents_are_checked_against_the_table() {
    let t = ModeTable::d415();
    let e = DepthSettings::from_json(
        br#"{"format":"Z16","fps":90,"width":1280,"height":720}"#,
        &t,
    );
    assert!(matches!(
        e,
        Err(SettingsError::Mode(ModeError::FpsNotOffered { .. }))
    ));
    let e = ColorSettings::from_json(
        br#"{"format":"YUYV","fps":30,"width":1280,"height":720}"#,
        &t,
    );
    assert!(matches!(
        e,
        Err(SettingsError::Mode(ModeError::UnknownFormat { .. }))
    ));
    let ok = ColorSettings::from_json(
        br#"{"format":"RGBA8","fps":60,"width":640,"height":480}"#,
        &t,
    );
    assert!(ok.is_ok());
}

#[test]
fn a_camera_refuses_settings_outside_its_table_and_keeps_the_old_ones() {
    let scene = Scene::default_single();
    let cam = SyntheticCamera::new(&scene, &scene.cameras[0].serial).unwrap();
    let before = cam.depth_settings();
    let bad = DepthSettings { fps: 90, ..before };
    assert!(matches!(
        cam.set_depth_settings(bad),
        Err(CameraError::InvalidSetting(SettingError::Mode(
            ModeError::FpsNotOffered { .. }
        )))
    ));
    assert_eq!(cam.depth_settings(), before);

    let small = DepthSettings {
        fps: 90,
        width: 640,
        height: 360,
        ..before
    };
    cam.set_depth_settings(small).unwrap();
    let k = cam.depth_intrinsics().unwrap();
    assert_eq!((k.width, k.height), (640, 360));
    assert_eq!(cam.render_depth(1).data.len(), 640 * 360);
}

#[test]
fn unknown_format_error_echoes_at_most_64_characters_of_the_name() {
    let huge = "Y".repeat(300_000);
    let t = ModeTable::d415();
    for e in [
        t.color_format(&huge).unwrap_err(),
        t.depth_format(&huge).unwrap_err(),
    ] {
        let text = e.to_string();
        assert!(text.len() < 300, "{} bytes", text.len());
        assert!(text.contains(&format!("\"{}…\"", "Y".repeat(64))), "{text}");
    }
}

#[test]
fn settings_json_error_of_a_huge_unknown_key_stays_under_300_bytes() {
    let huge = "k".repeat(300_000);
    let doc =
        format!(r#"{{"{huge}": 1, "format": "Z16", "fps": 30, "width": 848, "height": 480}}"#);
    let text = DepthSettings::from_json(doc.as_bytes(), &ModeTable::d415())
        .unwrap_err()
        .to_string();
    assert!(text.len() < 300, "{} bytes", text.len());
}
