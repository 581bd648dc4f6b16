use rgbd::{
    AdvancedConfig, AdvancedError, AdvancedMode, Camera, CameraError, ModeError, Scene,
    SettingError, SyntheticCamera, VisualPreset,
};

/// Thesis Listing A.5 as printed (including its four odd key spellings).
const LISTING_A5: &str = r#"{
  "aux-param-autoexposure-setpoint": "400",
  "aux-param-colorcorrection1": "0.461914",
  "aux-param-colorcorrection10": "-0.553711",
  "aux-param-colorcorrection11": "-0.553711",
  "aux-param-colorcorrection12": "0.0458984",
  "aux-param-colorcorrection2": "0.540039",
  "aux-param-colorcorrection3": "0.540039",
  "aux-param-colorcorrection4": "0.208008",
  "aux-param-colorcorrection5": "-0.332031",
  "aux-param-colorcorrection6": "-0.212891",
  "aux-param-colorcorrection7": "-0.212891",
  "aux-param-colorcorrection8": "0.68457",
  "aux-param-colorcorrection9": "0.930664",
  "aux-param-depthclampmax": "65536",
  "aux-param-depthclampmin": "0",
  "aux-param-disparityshift": "0",
  "controls-autoexposure-auto": "True",
  "controls-autoexposure-manual": "33000",
  "controls-color-autoexposure-auto": "False",
  "controls-color-autoexposure-manual": "650",
  "controls-color-backlight-compensation": "0",
  "controls-color-brightness": "0",
  "controls-color-contrast": "50",
  "controls-color-gain": "64",
  "controls-color-gamma": "300",
  "controls-color-hue": "0",
  "controls-color-power-line-frequency": "3",
  "controls-color-saturation": "64",
  "controls-color-sharpness": "50",
  "controls-color-white-balance-auto": "True",
  "controls-color-white-balance-manual": "4600",
  "controls-depth-gain": "16",
  "controls-depth-white-balance-auto": "False",
  "controls-laserpower": "150",
  "controls-laserstate": "on",
  "ignoreSAD": "0",
  "param-autoexposure-setpoint": "400",
  "param-censusenablereg-udiameter": "9",
  "param-censusenablereg-vdiameter": "9",
  "param-censususize": "9",
  "param-censusvsiz": "9",
  "param-depthclampmax": "65536",
  "param-depthclampmin": "0",
  "param-depthunits": "1000",
  "param-disableraucolor": "0",
  "param-disablesadcolor": "0",
  "param-disablesadnormalize": "0",
  "param-disablesloleftcolor": "0",
  "param-disableslorightcolor": "0",
  "param-disparitymode": "0",
  "param-disparityshift": "0",
  "param-lambdaad": "800",
  "param-lambdaacensus": "26",
  "param-leftrightthreshold": "24",
  "param-maxscorethreshb": "2047",
  "param-medianthresha": "500",
  "param-minscorethresha": "1",
  "param-neighborthresh": "7",
  "param-raumine": "1",
  "param-rauminn": "1",
  "param-rauminssum": "3",
  "param-raumins": "1",
  "param-rauminw": "1",
  "param-rauminwesum": "3",
  "param-regioncolorthresholdb": "0.0499022",
  "param-regioncolorthresholdg": "0.0499022",
  "param-regioncolorthresholdr": "0.0499022",
  "param-regionshrinku": "3",
  "param-regionshrinkv": "1",
  "param-robbinsmonrodecrement": "10",
  "param-robbinsmonroincrement": "10",
  "param-rsmdiffthreshold": "4",
  "param-rsmrauslodiffthreshold": "1",
  "param-rsmremovethreshold": "0.375",
  "param-scanlineedgetaub": "72",
  "param-scanlineedgetaug": "72",
  "param-scanlineedgetaur": "72",
  "param-scanlinep1": "60",
  "param-scanlinep1onediscon": "105",
  "param-scanlinep1twodiscon": "70",
  "param-scanlinep2": "342",
  "param-scanlinep2onediscon": "190",
  "param-scanlinep2twodiscon": "130",
  "param-secondpeakdelta": "325",
  "param-texturecountthresh": "0",
  "param-texturedifferencethresh": "0",
  "param-usersm": "1",
  "param-zunits": "1000",
  "stream-depth-format": "Z16",
  "stream-fps": "30",
  "stream-height": "720",
  "stream-width": "1280"
}"#;

#[test]
fn listing_a5_as_printed_loads() {
    let doc = AdvancedConfig::from_json(LISTING_A5.as_bytes()).unwrap();
    assert!(doc.is_complete(), "{} keys", doc.len());
    // The listing's spellings land on librealsense's keys.
    assert_eq!(doc.get("param-medianthreshold"), Some("500"));
    assert_eq!(doc.get("param-lambdacensus"), Some("26"));
    assert_eq!(doc.get("param-censusvsize"), Some("9"));
    assert_eq!(doc.get("param-rauminnssum"), Some("3"));
    assert_eq!(doc.get("param-medianthresha"), None);
    assert_eq!(doc.depth_units_um(), Some(1000));
}

#[test]
fn advanced_config_errors_name_the_key_and_what_is_allowed() {
    let e = AdvancedConfig::from_json(br#"{"param-notakey": "1"}"#).unwrap_err();
    assert_eq!(e, AdvancedError::UnknownKey("param-notakey".into()));
    assert_eq!(
        e.to_string(),
        "advanced-config: \"param-notakey\" is not a D400 advanced-mode key"
    );

    let e = AdvancedConfig::from_json(br#"{"param-depthunits": 1000}"#).unwrap_err();
    assert_eq!(e, AdvancedError::NotAString("param-depthunits".into()));

    let e = AdvancedConfig::from_json(br#"{"controls-autoexposure-auto": "yes"}"#).unwrap_err();
    assert_eq!(
        e.to_string(),
        "advanced-config: \"controls-autoexposure-auto\" = \"yes\" is not allowed; expected \"True\" or \"False\""
    );
    let e = AdvancedConfig::from_json(br#"{"controls-laserstate": "bright"}"#).unwrap_err();
    assert!(e.to_string().contains("\"off\", \"on\" or \"auto\""), "{e}");
    let e = AdvancedConfig::from_json(br#"{"param-lambdaad": "lots"}"#).unwrap_err();
    assert!(matches!(e, AdvancedError::BadValue { .. }));
    let e = AdvancedConfig::from_json(br#"{"param-depthunits": "0"}"#).unwrap_err();
    assert!(e.to_string().contains("an integer from 1 to 10000"), "{e}");
    let e = AdvancedConfig::from_json(br#"{"param-depthunits": "1000", "param-zunits": "100"}"#)
        .unwrap_err();
    assert!(matches!(e, AdvancedError::Conflict { .. }), "{e}");
    assert_eq!(
        AdvancedConfig::from_json(b"[1, 2]"),
        Err(AdvancedError::NotAnObject)
    );
    assert!(matches!(
        AdvancedConfig::from_json(b"{"),
        Err(AdvancedError::Json(_))
    ));
}

#[test]
fn visual_presets_are_complete_documents_by_name() {
    let ha = AdvancedConfig::preset(VisualPreset::from_name("High Accuracy").unwrap());
    assert!(ha.is_complete());
    assert_eq!(ha.get("param-medianthreshold"), Some("796"));
    assert_eq!(ha.get("param-leftrightthreshold"), Some("10"));
    assert_eq!(ha.get("param-rsmremovethreshold"), Some("0.809524"));
    assert_eq!(ha.get("param-regioncolorthresholdr"), Some("0.985323"));
    let hd = AdvancedConfig::preset(VisualPreset::from_name("high density").unwrap());
    assert_eq!(hd.get("param-maxscorethreshb"), Some("1443"));
    assert_eq!(hd.get("param-lambdaad"), Some("618"));
    for name in ["Default", "Hand", "Medium Density", "Remove IR Pattern"] {
        assert!(
            AdvancedConfig::preset(VisualPreset::from_name(name).unwrap()).is_complete(),
            "{name}"
        );
    }
    let e = VisualPreset::from_name("Super Accuracy").unwrap_err();
    assert!(e.to_string().contains("High Accuracy, High Density"), "{e}");
    // The default document agrees with the thesis listing on the depth parameters.
    let default = AdvancedConfig::preset(VisualPreset::Default);
    let listing = AdvancedConfig::from_json(LISTING_A5.as_bytes()).unwrap();
    for (key, value) in listing.iter().filter(|(k, _)| k.starts_with("param-")) {
        assert_eq!(default.get(key), Some(value), "{key}");
    }
}

#[test]
fn a_camera_loads_partial_documents_and_reports_complete_ones() {
    let scene = Scene::default_single();
    let cam = SyntheticCamera::new(&scene, &scene.cameras[0].serial).unwrap();
    assert!(cam.advanced_config().unwrap().is_complete());

    cam.set_advanced_config(&AdvancedConfig::preset(VisualPreset::HighDensity))
        .unwrap();
    let partial =
        AdvancedConfig::from_json(br#"{"param-depthunits": "100", "stream-fps": "15"}"#).unwrap();
    cam.set_advanced_config(&partial).unwrap();
    let now = cam.advanced_config().unwrap();
    assert_eq!(now.get("param-maxscorethreshb"), Some("1443"));
    assert_eq!(now.get("param-zunits"), Some("100"));
    assert_eq!(now.get("stream-fps"), Some("15"));
    assert_eq!(cam.depth_settings().fps, 15);
    assert!((cam.depth_scale() - 0.0001).abs() < 1e-9);
    assert!((cam.render_depth(1).depth_scale - 0.0001).abs() < 1e-9);

    let too_fast = AdvancedConfig::from_json(br#"{"stream-fps": "90"}"#).unwrap();
    assert!(matches!(
        cam.set_advanced_config(&too_fast),
        Err(CameraError::InvalidSetting(SettingError::Mode(
            ModeError::FpsNotOffered { .. }
        )))
    ));
    assert_eq!(cam.depth_settings().fps, 15);
}

#[test]
fn parameters_wrapper_must_hold_an_object_and_no_other_top_level_keys() {
    assert_eq!(
        AdvancedConfig::from_json(br#"{"parameters": 5}"#),
        Err(AdvancedError::NotAnObject)
    );
    let e = AdvancedConfig::from_json(
        br#"{"parameters": {"param-depthunits": "1000"}, "param-zunits": "100"}"#,
    )
    .unwrap_err();
    assert_eq!(e, AdvancedError::UnknownWrapperKey("param-zunits".into()));
    assert!(e.to_string().contains("\"param-zunits\""), "{e}");
    let doc = AdvancedConfig::from_json(
        br#"{"device": {"name": "Intel RealSense D415"}, "parameters": {"param-depthunits": "1000"}, "schema version": 1}"#,
    )
    .expect("viewer wrapper loads");
    assert_eq!(doc.depth_units_um(), Some(1000));
}

#[test]
fn advanced_config_errors_echo_at_most_64_characters_of_client_strings() {
    let huge = "x".repeat(300_000);
    let docs = [
        format!(r#"{{"{huge}": "1"}}"#),
        format!(r#"{{"{huge}": 1}}"#),
        format!(r#"{{"param-depthunits": "{huge}"}}"#),
        format!(r#"{{"parameters": {{}}, "{huge}": 1}}"#),
    ];
    for doc in docs {
        let text = AdvancedConfig::from_json(doc.as_bytes())
            .unwrap_err()
            .to_string();
        assert!(text.len() < 300, "{} bytes: {}", text.len(), &text[..300]);
        assert!(text.contains(&format!("{}…", "x".repeat(64))), "{text}");
    }
    let text = VisualPreset::from_name(&huge).unwrap_err().to_string();
    assert!(text.len() < 300, "{} bytes", text.len());
}
