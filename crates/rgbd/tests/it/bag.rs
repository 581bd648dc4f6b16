//! Playback of librealsense recordings (`.bag` from librealsense 2.56.5, `.db3` from
//! 2.59.1), compared with what librealsense's own playback returned for the same
//! files. The recordings and `<file>.expected.json` are committed in
//! `tests/fixtures/bag`, written by `tools/record_bags.py` (`tools/record_bags.sh`
//! makes both, one virtual environment per pyrealsense2 version).

use std::path::{Path, PathBuf};
use std::time::Duration;

use rgbd::backend::playback::{PlaybackCamera, PlaybackError};
use rgbd::{Camera, CameraError, DepthSettings, Extrinsics, Intrinsics, Stream};
use serde::Deserialize;

#[derive(Deserialize)]
struct Expected {
    librealsense: String,
    serial: String,
    name: String,
    depth_scale: f32,
    depth_to_color: Extrinsics,
    streams: Streams,
    frames: Frames,
}

#[derive(Deserialize)]
struct Streams {
    depth: StreamInfo,
    color: StreamInfo,
}

#[derive(Deserialize)]
struct StreamInfo {
    format: String,
    fps: u32,
    intrinsics: Intrinsics,
}

#[derive(Deserialize)]
struct Frames {
    depth: Vec<FrameInfo>,
    color: Vec<FrameInfo>,
}

#[derive(Deserialize)]
struct FrameInfo {
    frame_number: u64,
    bytes: usize,
    fnv1a64: String,
    units: Option<f32>,
}

pub(crate) fn fixtures() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/bag")
}

fn fnv1a64(bytes: &[u8]) -> String {
    let h = bytes.iter().fold(0xcbf2_9ce4_8422_2325_u64, |h, &b| {
        (h ^ u64::from(b)).wrapping_mul(0x0100_0000_01b3)
    });
    format!("{h:016x}")
}

fn expected(file: &str) -> Expected {
    let path = fixtures().join(format!("{file}.expected.json"));
    serde_json::from_slice(&std::fs::read(&path).unwrap()).unwrap()
}

fn only_camera(path: &Path) -> PlaybackCamera {
    let mut cameras = PlaybackCamera::open(path).unwrap();
    assert_eq!(cameras.len(), 1, "one recorded device");
    cameras.remove(0)
}

const T: Duration = Duration::from_millis(100);

fn check_against_librealsense(file: &str) {
    let want = expected(file);
    let cam = only_camera(&fixtures().join(file));
    assert_eq!(cam.serial().as_str(), want.serial);
    assert_eq!(cam.model(), want.name);
    assert_eq!(cam.depth_scale(), want.depth_scale, "{file}");
    // These recordings have no Stereo_Baseline option: the D415's nominal.
    assert_eq!(
        cam.stereo_baseline_m(),
        Some(rgbd::d415::BASELINE_M),
        "{file}"
    );
    assert_eq!(
        cam.depth_intrinsics().unwrap(),
        want.streams.depth.intrinsics,
        "{file}"
    );
    assert_eq!(
        cam.color_intrinsics().unwrap(),
        want.streams.color.intrinsics,
        "{file}"
    );
    let e = cam.depth_to_color().unwrap();
    for (ours, theirs) in e.rotation.iter().chain(&e.translation).zip(
        want.depth_to_color
            .rotation
            .iter()
            .chain(&want.depth_to_color.translation),
    ) {
        // librealsense composes the recorded transforms in its own order; the
        // recorded values themselves have 6 decimals in a .db3.
        assert!(
            (ours - theirs).abs() < 1e-6,
            "{file}: {e:?} vs librealsense"
        );
    }
    let depth = cam.depth_settings();
    assert_eq!(depth.format.name(), want.streams.depth.format);
    assert_eq!(depth.fps, want.streams.depth.fps);
    let color = cam.color_settings();
    assert_eq!(color.format.name(), want.streams.color.format);
    assert_eq!(color.fps, want.streams.color.fps);

    let numbers = |f: &[FrameInfo]| f.iter().map(|f| f.frame_number).collect::<Vec<_>>();
    assert_eq!(
        cam.recorded_frame_numbers(Stream::Depth),
        numbers(&want.frames.depth)
    );
    assert_eq!(
        cam.recorded_frame_numbers(Stream::Color),
        numbers(&want.frames.color)
    );
    assert!(!want.frames.depth.is_empty() && !want.frames.color.is_empty());
    // Two rounds: playback loops, and grabs keep counting.
    for round in 0..2u64 {
        for (i, w) in want.frames.depth.iter().enumerate() {
            let f = cam.grab_depth(T).unwrap();
            let bytes: Vec<u8> = f.data.iter().flat_map(|v| v.to_le_bytes()).collect();
            assert_eq!(bytes.len(), w.bytes);
            assert_eq!(fnv1a64(&bytes), w.fnv1a64, "{file}: depth frame {i}");
            assert_eq!(Some(f.depth_scale), w.units, "{file}: depth units");
            assert_eq!(
                f.frame_number,
                round * want.frames.depth.len() as u64 + i as u64 + 1
            );
        }
        for (i, w) in want.frames.color.iter().enumerate() {
            let f = cam.grab_color(T).unwrap();
            assert_eq!(f.data.len(), w.bytes);
            assert_eq!(fnv1a64(&f.data), w.fnv1a64, "{file}: color frame {i}");
        }
    }
    eprintln!(
        "{file}: matches librealsense {}'s playback",
        want.librealsense
    );
}

#[test]
fn ros1_bag_plays_back_as_librealsense_plays_it() {
    check_against_librealsense("d415.bag");
}

#[test]
fn ros2_db3_plays_back_as_librealsense_plays_it() {
    check_against_librealsense("d415.db3");
}

#[test]
fn the_recorded_mode_is_the_only_mode() {
    for file in ["d415.bag", "d415.db3"] {
        let cam = only_camera(&fixtures().join(file));
        let recorded = cam.depth_settings();
        cam.set_depth_settings(recorded).unwrap();
        let other = DepthSettings {
            width: 1280,
            height: 720,
            ..recorded
        };
        let e = cam.set_depth_settings(other).unwrap_err();
        assert!(matches!(e, CameraError::InvalidSetting(_)), "{e:?}");
        assert!(e.to_string().contains("640x480"), "{e}");
        assert_eq!(cam.depth_settings(), recorded);
        assert!(
            cam.advanced_mode().is_none(),
            "a recording has no advanced mode"
        );
    }
}

fn corrupted_copies(original: &[u8]) -> Vec<(String, Vec<u8>)> {
    let mut out = Vec::new();
    let len = original.len();
    for cut in [
        0,
        10,
        13,
        40,
        200,
        1000,
        len / 3,
        len / 2,
        len - 100,
        len - 1,
    ] {
        out.push((format!("truncated to {cut}"), original[..cut].to_vec()));
    }
    // Overwrite spans with 0xff (huge lengths) and with zeros, across the file.
    let mut state = 0x9e37_79b9_u32;
    for i in 0..60 {
        state ^= state << 13;
        state ^= state >> 17;
        state ^= state << 5;
        let at = state as usize % len;
        let mut copy = original.to_vec();
        let fill = if i % 2 == 0 { 0xff } else { 0x00 };
        for b in copy.iter_mut().skip(at).take(8) {
            *b = fill;
        }
        out.push((format!("8 bytes of {fill:#04x} at {at}"), copy));
    }
    out
}

/// Truncated and corrupted copies of both recordings: every one either opens (the
/// damage hit bytes the reader does not use) or fails with an error; none panics.
#[test]
fn damaged_recordings_give_errors_not_panics() {
    let dir = std::env::temp_dir().join(format!("rgbd-bag-damage-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let mut errors = 0;
    for file in ["d415.bag", "d415.db3"] {
        let original = std::fs::read(fixtures().join(file)).unwrap();
        for (what, bytes) in corrupted_copies(&original) {
            let path = dir.join(file);
            std::fs::write(&path, &bytes).unwrap();
            match PlaybackCamera::open(&path) {
                Ok(cameras) => {
                    for cam in cameras {
                        cam.grab_depth(T).unwrap();
                        cam.grab_color(T).unwrap();
                    }
                }
                Err(e) => {
                    errors += 1;
                    assert!(!e.to_string().is_empty(), "{file} {what}");
                }
            }
        }
    }
    std::fs::remove_dir_all(&dir).unwrap();
    assert!(errors >= 20, "only {errors} damaged copies were refused");
}

#[test]
fn other_files_are_not_recordings() {
    let path = fixtures().join("d415.bag.expected.json");
    let e = PlaybackCamera::open(&path).unwrap_err();
    assert!(matches!(e, PlaybackError::UnknownFormat { .. }), "{e:?}");
    let e = PlaybackCamera::open(&fixtures().join("missing.bag")).unwrap_err();
    assert!(matches!(e, PlaybackError::Io { .. }), "{e:?}");
}
