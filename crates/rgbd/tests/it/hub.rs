use std::sync::Arc;
use std::sync::mpsc::TryRecvError;
use std::time::Duration;

use rgbd::{Camera, CameraError, CameraHub, HubError, HubEvent, Scene, SyntheticCamera};

use crate::support::serial;

#[test]
fn hot_plug_add_and_remove_are_observed_through_the_hub() {
    let hub = CameraHub::new();
    let events = hub.subscribe();
    let cams = SyntheticCamera::all(&Scene::default_demo()).unwrap();
    let (a, b) = (serial("840412060746"), serial("840412060757"));

    for cam in &cams {
        hub.add(Arc::clone(cam) as Arc<dyn Camera>).unwrap();
    }
    assert_eq!(events.try_recv(), Ok(HubEvent::Added(a)));
    assert_eq!(events.try_recv(), Ok(HubEvent::Added(b)));
    assert_eq!(hub.serials(), vec![a, b]);

    let removed = hub.remove(&a).unwrap();
    assert_eq!(removed.serial(), a);
    assert_eq!(events.try_recv(), Ok(HubEvent::Removed(a)));
    assert!(hub.get(&a).is_none());
    assert!(hub.remove(&a).is_none(), "removing twice reports nothing");
    assert_eq!(events.try_recv(), Err(TryRecvError::Empty));

    // Plugged back in at run time.
    hub.add(removed).unwrap();
    assert_eq!(events.try_recv(), Ok(HubEvent::Added(a)));
}

#[test]
fn late_subscribers_first_learn_the_cameras_already_connected() {
    let hub = CameraHub::new();
    for cam in SyntheticCamera::all(&Scene::default_demo()).unwrap() {
        hub.add(cam).unwrap();
    }
    let events = hub.subscribe();
    let seen: Vec<_> = events.try_iter().collect();
    assert_eq!(
        seen,
        vec![
            HubEvent::Added(serial("840412060746")),
            HubEvent::Added(serial("840412060757"))
        ]
    );
}

#[test]
fn the_same_serial_cannot_be_connected_twice() {
    let hub = CameraHub::new();
    let scene = Scene::default_single();
    let s = scene.cameras[0].serial;
    hub.add(Arc::new(SyntheticCamera::new(&scene, &s).unwrap()))
        .unwrap();
    let again = hub.add(Arc::new(SyntheticCamera::new(&scene, &s).unwrap()));
    assert_eq!(again, Err(HubError::Duplicate(s)));
}

#[test]
fn grabs_through_the_hub_count_frames_and_fail_when_unplugged() {
    let hub = CameraHub::new();
    let scene = Scene::default_single();
    let cam = Arc::new(SyntheticCamera::new(&scene, &scene.cameras[0].serial).unwrap());
    hub.add(Arc::clone(&cam) as Arc<dyn Camera>).unwrap();
    let dyn_cam = hub.get(&scene.cameras[0].serial).unwrap();

    let first = dyn_cam.grab_depth(Duration::from_secs(1)).unwrap();
    let second = dyn_cam.grab_depth(Duration::from_secs(1)).unwrap();
    assert_eq!((first.frame_number, second.frame_number), (1, 2));
    assert!(second.timestamp_us > first.timestamp_us);
    assert_eq!(
        dyn_cam
            .grab_color(Duration::from_secs(1))
            .unwrap()
            .frame_number,
        1
    );

    cam.set_connected(false);
    assert!(matches!(
        dyn_cam.grab_color(Duration::from_secs(1)),
        Err(CameraError::Disconnected { .. })
    ));
}

#[test]
fn a_grab_times_out_when_the_frame_is_later_than_the_timeout() {
    let scene = Scene::default_single();
    let cam = SyntheticCamera::new(&scene, &scene.cameras[0].serial).unwrap();
    cam.set_frame_delay(Duration::from_millis(200));
    assert_eq!(
        cam.grab_depth(Duration::from_millis(5))
            .map(|f| f.frame_number),
        Err(CameraError::Timeout { timeout_ms: 5 })
    );
}
