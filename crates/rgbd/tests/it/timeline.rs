//! Scenes with a timeline: objects that appear, slide in, stand still and are removed.

use std::time::Duration;

use rgbd::scene::{Noise, Timeline};
use rgbd::{Scene, SyntheticCamera};

use crate::support::{floor_scene, only_camera};

/// One ideal camera 1 m above the floor and one box that appears at 1 s 0.3 m to the
/// right, slides to the middle until 2 s, and is removed at 4 s.
const SLIDING: &str = r#"
seed = 3
[[camera]]
serial = "000000000001"
position = [0.0, 0.0, 1.0]
look_at = [0.0, 0.0, 0.0]
up = [0.0, 1.0, 0.0]
noise = "ideal"

[[box]]
size = [0.20, 0.10, 0.15]
center = [0.0, 0.0]
appear_s = 1.0
from = [0.3, 0.0]
still_s = 2.0
remove_s = 4.0
label = { kind = "qr", text = "LATE", size = 0.08, appear_s = 3.0 }
"#;

fn at(s: f64) -> Duration {
    Duration::from_secs_f64(s)
}

fn error_of(text: &str) -> String {
    Scene::from_toml(text).unwrap_err().to_string()
}

/// `SLIDING` with the box's lines replaced by `timeline` (TOML key = value lines).
fn with_box_timeline(timeline: &str) -> String {
    format!(
        r#"[[box]]
size = [0.2, 0.1, 0.15]
center = [0.0, 0.0]
{timeline}
"#
    )
}

#[test]
fn a_timeline_is_parsed_and_places_the_object_in_time() {
    let scene = Scene::from_toml(SLIDING).unwrap();
    assert!(scene.is_timed());
    let b = &scene.boxes[0];
    assert_eq!(
        b.timeline,
        Timeline {
            appear_s: Some(1.0),
            remove_s: Some(4.0),
            from: Some([0.3, 0.0]),
            still_s: Some(2.0),
        }
    );
    let t = b.timeline;
    assert_eq!(t.position(b.center, 0.999), None);
    assert_eq!(t.position(b.center, 1.0), Some([0.3, 0.0]));
    let mid = t.position(b.center, 1.5).unwrap();
    assert!((mid[0] - 0.15).abs() < 1e-12 && mid[1] == 0.0, "{mid:?}");
    assert_eq!(t.position(b.center, 2.0), Some([0.0, 0.0]));
    assert_eq!(t.position(b.center, 3.999), Some([0.0, 0.0]));
    assert_eq!(t.position(b.center, 4.0), None);
    assert!(t.moving(1.5) && !t.moving(0.5) && !t.moving(2.0) && !t.moving(5.0));
    assert!(!t.present(0.5) && t.present(1.0) && t.present(3.0) && !t.present(4.0));
    assert_eq!((t.appear(), t.still()), (1.0, 2.0));
    let label = b.label.as_ref().unwrap().timeline();
    assert!(!label.present(2.5) && label.present(3.0));
}

#[test]
fn a_scene_without_timelines_is_untimed_and_the_same_at_every_moment() {
    let scene = Scene::default_demo();
    assert!(!scene.is_timed());
    assert_eq!(scene.at(0.0), scene);
    assert_eq!(scene.at(1.0e6), scene);
    let plain = Scene::from_toml(
        r#"[[box]]
size = [0.2, 0.1, 0.15]
center = [0.1, 0.0]"#,
    )
    .unwrap();
    assert!(plain.boxes[0].timeline.is_always());
    assert!(plain.boxes[0].timeline.present(0.0));
}

#[test]
fn the_scene_at_a_moment_holds_what_is_there_then_where_it_is() {
    let scene = Scene::from_toml(SLIDING).unwrap();
    assert!(scene.at(0.5).boxes.is_empty());
    let sliding = scene.at(1.5);
    assert!((sliding.boxes[0].center[0] - 0.15).abs() < 1e-12);
    assert!(sliding.boxes[0].label.is_none(), "the label comes at 3 s");
    assert!(!sliding.is_timed());
    let labelled = scene.at(3.5);
    assert_eq!(labelled.boxes[0].center, [0.0, 0.0]);
    assert_eq!(labelled.boxes[0].label.as_ref().unwrap().text, "LATE");
    assert!(scene.at(4.0).boxes.is_empty());
}

#[test]
fn timelines_are_checked_with_errors_that_name_the_field() {
    let cases = [
        (
            "from = [0.5, 0.0]",
            "scene: box[0].from: needs still_s: the time it stands at its centre after sliding from `from`",
        ),
        (
            "still_s = 2.0",
            "scene: box[0].still_s: needs from: the point it slides from, starting at appear_s",
        ),
        (
            "appear_s = 2.0\nfrom = [0.5, 0.0]\nstill_s = 2.0",
            "scene: box[0].still_s: must be after appear_s (2 s), got 2",
        ),
        (
            "from = [0.5, 0.0]\nstill_s = 2.0\nremove_s = 1.5",
            "scene: box[0].remove_s: must be after still_s (2 s), got 1.5",
        ),
        (
            "appear_s = 3.0\nremove_s = 3.0",
            "scene: box[0].remove_s: must be after appear_s (3 s), got 3",
        ),
        (
            "appear_s = -1.0",
            "scene: box[0].appear_s: must be seconds of scene time from 0 to 10000000, got -1",
        ),
        (
            "remove_s = nan",
            "scene: box[0].remove_s: must be seconds of scene time from 0 to 10000000, got NaN",
        ),
        (
            "from = [5000.0, 0.0]\nstill_s = 1.0",
            "scene: box[0].from: must be finite numbers within ±1000 m, got [5000.0, 0.0]",
        ),
    ];
    for (timeline, want) in cases {
        assert_eq!(error_of(&with_box_timeline(timeline)), want, "{timeline}");
    }
    let cylinder = "[[cylinder]]\nradius = 0.1\nheight = 0.2\ncenter = [0.0, 0.0]\nstill_s = 1.0";
    assert_eq!(
        error_of(cylinder),
        "scene: cylinder[0].still_s: needs from: the point it slides from, starting at appear_s"
    );
    let marker = "[[marker]]\nfamily = \"tag36h11\"\nid = 0\nsize = 0.1\ncenter = [0.0, 0.0]\nappear_s = 5.0\nremove_s = 1.0";
    assert_eq!(
        error_of(marker),
        "scene: marker[0].remove_s: must be after appear_s (5 s), got 1"
    );
    let label = with_box_timeline(
        "label = { kind = \"qr\", text = \"X\", size = 0.05, appear_s = 2.0, remove_s = 1.0 }",
    );
    assert_eq!(
        error_of(&label),
        "scene: box[0].label.remove_s: must be after appear_s (2 s), got 1"
    );
    // A label moves with its box: it has no path of its own.
    let sliding_label = with_box_timeline(
        "label = { kind = \"qr\", text = \"X\", size = 0.05, from = [1.0, 0.0] }",
    );
    assert!(error_of(&sliding_label).contains("unknown field `from`"));
}

/// The scene of `SLIDING` without its timeline, with the box at `center` (or none).
fn still_scene(center: Option<[f64; 2]>, label: bool) -> Scene {
    let mut scene = Scene::from_toml(SLIDING).unwrap();
    match center {
        Some(center) => {
            let b = &mut scene.boxes[0];
            b.center = center;
            b.timeline = Timeline::default();
            if label {
                let l = b.label.as_mut().unwrap();
                l.appear_s = None;
            } else {
                b.label = None;
            }
        }
        None => scene.boxes.clear(),
    }
    scene
}

#[test]
fn a_frame_is_rendered_as_the_scene_stands_at_its_scene_time() {
    let timed = only_camera(&Scene::from_toml(SLIDING).unwrap());
    let render = |scene: &Scene| only_camera(scene).render_depth_at(1, Duration::ZERO);
    let empty = render(&still_scene(None, false));
    assert_eq!(timed.render_depth_at(1, at(0.5)).data, empty.data);
    assert_eq!(timed.render_depth_at(1, at(4.0)).data, empty.data);
    let there = render(&still_scene(Some([0.0, 0.0]), false));
    assert_eq!(timed.render_depth_at(1, at(2.0)).data, there.data);
    assert_eq!(timed.render_depth_at(1, at(3.9)).data, there.data);
    let sliding = render(&still_scene(Some([0.15, 0.0]), false));
    assert_eq!(timed.render_depth_at(1, at(1.5)).data, sliding.data);
    assert_ne!(sliding.data, there.data);
    // The box's top (0.85 m away) is under the image centre only once it is there.
    let centre =
        |f: &rgbd::DepthFrame| f.data[(f.height as usize / 2) * f.stride + f.width as usize / 2];
    assert_eq!(centre(&timed.render_depth_at(1, at(0.5))), 1000);
    assert_eq!(centre(&timed.render_depth_at(1, at(2.5))), 850);
}

#[test]
fn a_label_stuck_on_later_shows_in_color_from_then_on() {
    let timed = only_camera(&Scene::from_toml(SLIDING).unwrap());
    let bare =
        only_camera(&still_scene(Some([0.0, 0.0]), false)).render_color_at(1, Duration::ZERO);
    let labelled =
        only_camera(&still_scene(Some([0.0, 0.0]), true)).render_color_at(1, Duration::ZERO);
    assert_ne!(bare.data, labelled.data);
    assert_eq!(timed.render_color_at(1, at(2.5)).data, bare.data);
    assert_eq!(timed.render_color_at(1, at(3.5)).data, labelled.data);
}

#[test]
fn a_marker_on_a_timeline_is_drawn_only_while_it_is_there() {
    let mut scene = floor_scene(1.0, Noise::Ideal);
    scene.markers.push(rgbd::scene::SceneMarker {
        family: "tag36h11".to_owned(),
        id: 3,
        size: 0.16,
        center: [0.0, 0.0],
        yaw_deg: 0.0,
        timeline: Timeline {
            appear_s: Some(1.0),
            remove_s: Some(2.0),
            ..Timeline::default()
        },
    });
    scene.validate().unwrap();
    let cam = only_camera(&scene);
    let floor = only_camera(&floor_scene(1.0, Noise::Ideal)).render_color_at(1, Duration::ZERO);
    assert_eq!(cam.render_color_at(1, at(0.5)).data, floor.data);
    assert_ne!(cam.render_color_at(1, at(1.5)).data, floor.data);
    assert_eq!(cam.render_color_at(1, at(2.5)).data, floor.data);
}

#[test]
fn grabs_follow_the_scene_time_since_the_cameras_were_made() {
    use rgbd::Camera as _;
    let scene = Scene::from_toml(SLIDING).unwrap();
    // Scene time 0 was 2.5 s ago: the box stands in the middle.
    let epoch = std::time::Instant::now() - at(2.5);
    let cams = SyntheticCamera::all_since(&scene, epoch).unwrap();
    assert!(cams[0].scene_time() >= at(2.5));
    let frame = cams[0].grab_depth(Duration::from_secs(1)).unwrap();
    let centre = frame.data[(frame.height as usize / 2) * frame.stride + frame.width as usize / 2];
    assert_eq!(centre, 850);
    let fresh = SyntheticCamera::all(&scene).unwrap();
    let frame = fresh[0].grab_depth(Duration::from_secs(1)).unwrap();
    let centre = frame.data[(frame.height as usize / 2) * frame.stride + frame.width as usize / 2];
    assert_eq!(centre, 1000, "at scene time 0 the box is not there yet");
}

#[test]
fn the_lane_scene_places_two_parcels_one_after_the_other() {
    let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../../scenes/lane.toml");
    let scene = Scene::load(std::path::Path::new(path)).unwrap();
    assert!(scene.is_timed());
    let [first, second] = [&scene.boxes[0], &scene.boxes[1]];
    assert!(first.timeline.remove_s.unwrap() < second.timeline.appear());
    for t in [0.0, 1.9, 9.5, 10.9, 18.0, 25.0] {
        assert!(scene.at(t).boxes.is_empty(), "{t} s");
    }
    assert_eq!(scene.at(5.0).boxes[0].center, first.center);
    assert_eq!(scene.at(14.0).boxes[0].center, second.center);
}

#[test]
fn every_object_kind_takes_the_same_timeline_fields_and_refuses_unknown_ones() {
    let timeline = "appear_s = 1\nfrom = [0.5, 0.25]\nstill_s = 2.5\nremove_s = 7";
    let scene = Scene::from_toml(&format!(
        "[[box]]\nsize = [0.2, 0.1, 0.1]\ncenter = [0.0, 0.0]\n{timeline}\n\
         [[cylinder]]\nradius = 0.1\nheight = 0.2\ncenter = [0.3, 0.0]\n{timeline}\n\
         [[marker]]\nfamily = \"tag36h11\"\nid = 3\nsize = 0.1\ncenter = [0.0, 0.4]\n{timeline}\n"
    ))
    .unwrap();
    let expected = Timeline {
        appear_s: Some(1.0),
        remove_s: Some(7.0),
        from: Some([0.5, 0.25]),
        still_s: Some(2.5),
    };
    assert_eq!(scene.boxes[0].timeline, expected);
    assert_eq!(scene.cylinders[0].timeline, expected);
    assert_eq!(scene.markers[0].timeline, expected);
    for object in [
        "[[box]]\nsize = [0.2, 0.1, 0.1]\ncenter = [0.0, 0.0]",
        "[[cylinder]]\nradius = 0.1\nheight = 0.2\ncenter = [0.3, 0.0]",
        "[[marker]]\nfamily = \"tag36h11\"\nid = 3\nsize = 0.1\ncenter = [0.0, 0.4]",
    ] {
        let e = error_of(&format!("{object}\nappear = 1.0\n"));
        assert!(e.contains("unknown field `appear`"), "{e}");
        let e = error_of(&format!("{object}\nstill_s = \"soon\"\n"));
        assert!(e.contains("invalid type"), "{e}");
    }
}

#[test]
fn a_stalled_camera_serves_the_frame_of_its_stall_again() {
    use rgbd::Camera as _;
    let timeout = Duration::from_secs(5);
    let stalled = SLIDING.replace("noise = \"ideal\"", "noise = \"d415\"\nstall_s = 0.0");
    let scene = Scene::from_toml(&stalled).expect("scene");
    assert_eq!(scene.cameras[0].stall_s, Some(0.0));
    let cam = SyntheticCamera::all(&scene).expect("cameras").remove(0);
    let first = cam.grab_depth(timeout).expect("grab");
    std::thread::sleep(Duration::from_millis(5));
    let again = cam.grab_depth(timeout).expect("grab");
    assert_eq!(
        again, first,
        "number, capture time and noisy pixels all repeat"
    );
    let color = cam.grab_color(timeout).expect("grab");
    assert_eq!(cam.grab_color(timeout).expect("grab"), color);

    // Without a stall (the default) a noisy camera's frames change.
    let moving = SLIDING.replace("noise = \"ideal\"", "noise = \"d415\"");
    let scene = Scene::from_toml(&moving).expect("scene");
    assert_eq!(scene.cameras[0].stall_s, None);
    let cam = SyntheticCamera::all(&scene).expect("cameras").remove(0);
    let first = cam.grab_depth(timeout).expect("grab");
    let next = cam.grab_depth(timeout).expect("grab");
    assert_eq!(next.frame_number, first.frame_number + 1);
    assert!(next.timestamp_us > first.timestamp_us);
    assert_ne!(next.data, first.data);

    let e = error_of(&SLIDING.replace("noise = \"ideal\"", "stall_s = -1.0"));
    assert!(e.contains("camera[0].stall_s"), "{e}");
}
