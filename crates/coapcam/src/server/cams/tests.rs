//! The resource tree driven through a real server on 127.0.0.1 with a hub the test owns:
//! cameras plugged in and pulled out at run time, a grab that outlasts its timeout, a
//! camera that disappears.

use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;

use coap::{Code, EndpointConfig, OptionNumber, Request, Response};
use coap_net::{Client, Router, Server, ServerConfig};
use rgbd::{Camera as _, CameraHub, Scene, SyntheticCamera};
use tokio::sync::mpsc;

use super::Cams;
use crate::ScratchDir;

const LIMIT: Duration = Duration::from_secs(60);

/// The tree on a server of its own, an empty hub, and a client.
struct Rig {
    hub: Arc<CameraHub>,
    router: Arc<Router>,
    cams: Arc<Cams>,
    _server: Server,
    addr: SocketAddr,
    client: Client,
}

impl Rig {
    fn start(state: &ScratchDir) -> Self {
        let hub = Arc::new(CameraHub::new());
        let router = Router::new();
        let (changed, _) = mpsc::unbounded_channel();
        let clock = Arc::new(crate::server::clock::ServerClock::default());
        let cams =
            Cams::start(hub.clone(), router.clone(), &state.0, changed, clock).expect("cams");
        let server = Server::bind(
            &[SocketAddr::from(([127, 0, 0, 1], 0))],
            ServerConfig::default(),
            router.clone(),
        )
        .expect("server");
        let addr = server.local_addrs()[0];
        let client = Client::bind(
            SocketAddr::from(([127, 0, 0, 1], 0)),
            EndpointConfig::default(),
        )
        .expect("client");
        Self {
            hub,
            router,
            cams,
            _server: server,
            addr,
            client,
        }
    }

    async fn send(&self, method: Code, path: &str, payload: &[u8]) -> Response {
        let mut request = Request::new(method, path).with_payload(payload.to_vec());
        request.timeout = Some(LIMIT);
        self.client
            .send(self.addr, request)
            .await
            .unwrap_or_else(|e| panic!("{method:?} {path}: {e}"))
    }

    async fn discovery(&self) -> String {
        let r = self.send(Code::GET, "/.well-known/core", b"").await;
        String::from_utf8_lossy(&r.payload).into_owned()
    }

    /// Waits (bounded) until the hub listener has added or removed `path`.
    async fn routed(&self, path: &str, present: bool) {
        let wait = async {
            while self.router.patterns().iter().any(|p| p == path) != present {
                tokio::time::sleep(Duration::from_millis(5)).await;
            }
        };
        tokio::time::timeout(LIMIT, wait)
            .await
            .unwrap_or_else(|_| panic!("{path} present = {present} never happened"));
    }
}

fn runtime() -> tokio::runtime::Runtime {
    tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .expect("runtime")
}

fn cameras() -> Vec<Arc<SyntheticCamera>> {
    SyntheticCamera::all(&Scene::default_demo()).expect("the demo scene's cameras")
}

#[test]
fn cameras_plugged_in_and_pulled_out_appear_in_and_vanish_from_discovery() {
    let state = ScratchDir::new("hotplug");
    runtime().block_on(async {
        let rig = Rig::start(&state);
        let cams = cameras();
        let (a, b) = (cams[0].clone(), cams[1].clone());
        let (sa, sb) = (a.serial(), b.serial());
        rig.hub.add(a).expect("plug in a");
        rig.routed(&format!("/cams/{sa}/color"), true).await;
        let links = rig.discovery().await;
        assert!(
            links.contains(&format!("</cams/{sa}/pointcloud>")),
            "{links}"
        );
        assert!(!links.contains(&sb.to_string()), "{links}");
        // Each grab resource lists every format it offers, the default first.
        assert!(
            links.contains(&format!(
                "</cams/{sa}/depth>;rt=\"rgbd.depth\";if=\"core.p\";ct=\"42 23 60 65101 65102\""
            )),
            "{links}"
        );

        rig.hub.add(b).expect("plug in b");
        rig.routed(&format!("/cams/{sb}/color"), true).await;
        let links = rig.discovery().await;
        for name in crate::repr::Stream::ALL
            .iter()
            .map(|s| s.name())
            .chain(super::CONFIGS)
        {
            assert!(
                links.contains(&format!("</cams/{sb}/{name}>")),
                "{name}: {links}"
            );
        }
        // A setting of b, to see it re-applied when b returns.
        let settings = format!("/cams/{sb}/color-settings");
        let doc = r#"{"format": "RGB8", "fps": 15, "width": 640, "height": 480}"#;
        let put = rig.send(Code::PUT, &settings, doc.as_bytes()).await;
        assert_eq!(put.code, Code::CHANGED);
        let before = rig.send(Code::GET, &settings, b"").await.payload;

        let b = rig.hub.remove(&sb).expect("pull out b");
        rig.routed(&format!("/cams/{sb}/color"), false).await;
        let links = rig.discovery().await;
        assert!(!links.contains(&sb.to_string()), "{links}");
        assert!(links.contains(&format!("</cams/{sa}/color>")), "{links}");
        for path in [format!("/cams/{sb}/color"), settings.clone()] {
            assert_eq!(rig.send(Code::GET, &path, b"").await.code, Code::NOT_FOUND);
        }
        let create = rig
            .send(Code::POST, "/cams/color", sb.as_str().as_bytes())
            .await;
        assert_eq!(create.code, Code::BAD_REQUEST);
        let grab = rig
            .send(Code::POST, &format!("/cams/{sa}/depth"), b"")
            .await;
        assert_eq!(grab.code, Code::CONTENT, "the other camera still serves");

        rig.hub.add(b).expect("plug b in again");
        rig.routed(&settings, true).await;
        assert_eq!(rig.send(Code::GET, &settings, b"").await.payload, before);
    });
}

#[test]
fn a_grab_that_outlasts_its_timeout_answers_5_03_with_max_age() {
    let state = ScratchDir::new("timeout");
    runtime().block_on(async {
        let rig = Rig::start(&state);
        let camera = cameras().swap_remove(0);
        let sn = camera.serial();
        rig.hub.add(camera.clone()).expect("plug in");
        let config = format!("/cams/{sn}/application-config");
        rig.routed(&config, true).await;
        let doc = rig.send(Code::GET, &config, b"").await.payload;
        let mut doc: serde_json::Value = serde_json::from_slice(&doc).expect("JSON");
        doc["depth_grab_timeout_ms"] = 1500.into();
        let put = rig
            .send(Code::PUT, &config, doc.to_string().as_bytes())
            .await;
        assert_eq!(put.code, Code::CHANGED);

        camera.set_frame_delay(Duration::from_secs(5));
        for grab in ["depth", "pointcloud"] {
            let r = rig
                .send(Code::POST, &format!("/cams/{sn}/{grab}"), b"")
                .await;
            assert_eq!(r.code, Code::SERVICE_UNAVAILABLE, "{grab}");
            assert_eq!(
                r.options.uint(OptionNumber::MAX_AGE),
                Some(2),
                "{grab}: Max-Age is the timeout in whole seconds, rounded up"
            );
            let text = String::from_utf8_lossy(&r.payload);
            assert!(text.contains("no frame within 1500 ms"), "{grab}: {text}");
        }
        // The server keeps serving: discovery, and the grab once frames come in time.
        assert!(
            rig.discovery()
                .await
                .contains(&format!("</cams/{sn}/depth>"))
        );
        camera.set_frame_delay(Duration::ZERO);
        let r = rig
            .send(Code::POST, &format!("/cams/{sn}/depth"), b"")
            .await;
        assert_eq!(r.code, Code::CONTENT);

        // A camera that stops delivering (pulled out, not yet noticed by the hub).
        camera.set_connected(false);
        let r = rig
            .send(Code::POST, &format!("/cams/{sn}/color"), b"")
            .await;
        assert_eq!(r.code, Code::NOT_FOUND);
        assert!(String::from_utf8_lossy(&r.payload).contains("disconnected"));
    });
}

#[test]
fn icp_brings_a_displaced_camera_back_onto_the_cloud_merged_before_it() {
    use geometry::{PointCloud, Transform};
    use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};

    let cams = SyntheticCamera::all(&Scene::default_demo()).expect("the demo scene's cameras");
    let cam = &cams[0];
    let pose = crate::vision::calibration::pose_transformation(
        &cam.true_pose().expect("a calibrated camera"),
    );
    let app = crate::documents::AppConfig::default();
    let Ok(super::grab::Frame::Cloud { points, part, .. }) =
        super::grab::cloud(cam.as_ref(), &app, &pose)
    else {
        panic!("no cloud")
    };
    let truth = PointCloud::from(points);
    // The same view with its pose 15 mm and 1 degree off, as a second camera's.
    let error = Isometry3::from_parts(
        Translation3::new(0.012, -0.008, 0.004),
        UnitQuaternion::from_axis_angle(&Vector3::z_axis(), 1f32.to_radians()),
    );
    let mut displaced = truth.clone();
    Transform::from(error).apply_in_place(&mut displaced);
    let mean_error = |cloud: &[nalgebra::Point3<f32>]| {
        let pairs = cloud
            .iter()
            .zip(&truth.points)
            .filter(|(p, _)| p.x.is_finite());
        let (sum, n) = pairs.fold((0.0, 0), |(s, n), (p, q)| (s + (p - q).norm(), n + 1));
        sum / n as f32
    };
    assert!(mean_error(&displaced.points) > 0.010);

    let n = truth.points.len();
    let (merged, parts) = super::register_and_merge(vec![
        (
            rgbd::Serial::parse("111111111111").expect("a serial"),
            false,
            truth.points.clone(),
            part.clone(),
        ),
        (
            rgbd::Serial::parse("222222222222").expect("a serial"),
            true,
            displaced.points,
            part,
        ),
    ]);
    assert_eq!(merged.points.len(), 2 * n, "every point kept");
    // The compact cloud carries the correction for the client to apply.
    assert!(parts[0].correction.is_none() && parts[1].correction.is_some());
    let registered = mean_error(&merged.points[n..]);
    assert!(
        registered < 0.003,
        "{:.1} mm off after ICP",
        registered * 1000.0
    );
}

#[test]
fn concurrent_puts_leave_one_of_them_in_memory_and_the_same_on_disk() {
    let state = ScratchDir::new("concurrent-puts");
    runtime().block_on(async {
        let rig = Rig::start(&state);
        let camera = cameras().swap_remove(0);
        let sn = camera.serial();
        rig.hub.add(camera).expect("plug in");
        let config = format!("/cams/{sn}/application-config");
        rig.routed(&config, true).await;
        let doc = rig.send(Code::GET, &config, b"").await.payload;
        let doc: serde_json::Value = serde_json::from_slice(&doc).expect("JSON");
        // Four clients, each PUTting its own documents as fast as it can.
        let mut tasks = tokio::task::JoinSet::new();
        for client in 0..4u64 {
            let sender = Client::bind(
                SocketAddr::from(([127, 0, 0, 1], 0)),
                EndpointConfig::default(),
            )
            .expect("client");
            let (addr, config, mut doc) = (rig.addr, config.clone(), doc.clone());
            tasks.spawn(async move {
                for round in 0..25u64 {
                    doc["depth_grab_timeout_ms"] = (1000 + client * 100 + round).into();
                    let mut request =
                        Request::new(Code::PUT, &config).with_payload(doc.to_string().into_bytes());
                    request.timeout = Some(LIMIT);
                    let r = sender.send(addr, request).await.expect("an answer");
                    assert_eq!(r.code, Code::CHANGED);
                }
            });
        }
        while let Some(done) = tasks.join_next().await {
            done.expect("a client");
        }
        let served = rig.send(Code::GET, &config, b"").await.payload;
        let served: serde_json::Value = serde_json::from_slice(&served).expect("JSON");
        let dir = state.0.join(sn.as_str());
        let on_disk = std::fs::read(dir.join("application-config.json")).expect("the file");
        let on_disk: serde_json::Value =
            serde_json::from_slice(&on_disk).expect("the file is JSON");
        assert_eq!(on_disk, served, "memory and disk disagree");
        let left: Vec<_> = std::fs::read_dir(&dir)
            .expect("the camera's state")
            .filter_map(|e| e.ok()?.file_name().into_string().ok())
            .filter(|n| n.ends_with(".tmp"))
            .collect();
        assert!(left.is_empty(), "temporary files left: {left:?}");
    });
}

#[test]
fn a_stranger_may_grab_but_not_change_the_cameras() {
    let state = ScratchDir::new("stranger");
    runtime().block_on(async {
        let rig = Rig::start(&state);
        rig.router
            .set_policy(Arc::new(crate::server::loopback_only));
        let cam = cameras()[0].clone();
        let sn = cam.serial();
        rig.hub.add(cam).expect("plug in");
        rig.routed(&format!("/cams/{sn}/color"), true).await;
        // A request from `peer`, arrived over loopback or not.
        let from = |(peer, loopback): (&str, bool), method: Code, path: &str, payload: &[u8]| {
            let request = Request::new(method, path);
            rig.router.dispatch(coap::IncomingRequest {
                id: coap::IncomingId(1),
                peer: peer.parse().expect("address"),
                method,
                options: request.options,
                payload: bytes::Bytes::copy_from_slice(payload),
                multicast: false,
                confirmable: true,
                observe: None,
                identity: None,
                loopback,
            })
        };
        let app = format!("/cams/{sn}/application-config");
        let before = rig.send(Code::GET, &app, b"").await.payload;
        let changed = String::from_utf8_lossy(&before).replace("\"icp\": 0", "\"icp\": 1");
        assert_ne!(changed.as_bytes(), &before[..], "a real change");
        for (method, path, payload) in [
            (Code::PUT, app.as_str(), changed.as_bytes()),
            (Code::DELETE, app.as_str(), &b""[..]),
            (Code::DELETE, &format!("/cams/{sn}/color"), b""),
            (Code::POST, "/cams/color", sn.as_str().as_bytes()),
        ] {
            // Strangers, and strangers whose source looks like loopback but who came in
            // from a network interface.
            for stranger in [
                ("192.0.2.7:5683", false),
                ("[2001:db8::7]:5683", false),
                ("[::ffff:127.0.0.1]:5683", false),
                ("127.0.0.1:5683", false),
                ("[::1]:5683", false),
            ] {
                let r = from(stranger, method, path, payload).await;
                assert_eq!(
                    r.code,
                    Code::FORBIDDEN,
                    "{method:?} {path} from {stranger:?}"
                );
            }
        }
        assert_eq!(
            rig.send(Code::GET, &app, b"").await.payload,
            before,
            "nothing changed"
        );
        assert!(rig.router.patterns().contains(&format!("/cams/{sn}/color")));
        // Reading is for everyone; this machine (what came over loopback) may change
        // things, whatever address it used.
        let grab = from(
            ("192.0.2.7:5683", false),
            Code::POST,
            &format!("/cams/{sn}/depth"),
            b"",
        )
        .await;
        assert_eq!(grab.code, Code::CONTENT);
        let get = from(("192.0.2.7:5683", false), Code::GET, &app, b"").await;
        assert_eq!(get.code, Code::CONTENT);
        let put = from(
            ("[2001:db8::2]:5683", true),
            Code::PUT,
            &app,
            changed.as_bytes(),
        )
        .await;
        assert_eq!(put.code, Code::CHANGED);
    });
}

#[test]
fn grabs_past_the_memory_budget_answer_5_03_with_max_age_until_memory_is_free() {
    let state = ScratchDir::new("budget");
    runtime().block_on(async {
        let rig = Rig::start(&state);
        let cam = cameras()[0].clone();
        let sn = cam.serial();
        rig.hub.add(cam).expect("plug in");
        rig.routed(&format!("/cams/{sn}/pointcloud"), true).await;
        rig.cams.set_grab_memory(80 << 20);
        // Another grab holds 60 MiB: a point cloud (about 29 MiB at 1280x720) does not fit.
        let other = rig
            .cams
            .budget
            .take(60 << 20)
            .expect("the first reservation");
        for path in [
            format!("/cams/{sn}/pointcloud"),
            "/cams/pointclouds".to_string(),
        ] {
            let busy = rig.send(Code::POST, &path, b"").await;
            assert_eq!(busy.code, Code::SERVICE_UNAVAILABLE, "{path}");
            assert_eq!(busy.options.uint(OptionNumber::MAX_AGE), Some(1), "{path}");
        }
        let busy = rig.send(Code::POST, "/cams/dimensions", b"").await;
        assert_eq!(busy.code, Code::SERVICE_UNAVAILABLE);
        // Color (at most 14 MiB at 1920x1080) still fits; once the other grab ends, so does
        // the cloud.
        let color = rig
            .send(Code::POST, &format!("/cams/{sn}/color"), b"")
            .await;
        assert_eq!(color.code, Code::CONTENT);
        drop(other);
        let cloud = rig
            .send(Code::POST, &format!("/cams/{sn}/pointcloud"), b"")
            .await;
        assert_eq!(cloud.code, Code::CONTENT);
    });
}

/// A results log that keeps the events it is given, or refuses them.
#[derive(Default)]
struct Audit {
    refuse: std::sync::atomic::AtomicBool,
    events: std::sync::Mutex<Vec<crate::api::record::Event>>,
}

impl crate::server::measure::Records for Audit {
    fn keep(
        &self,
        _measured: crate::server::measure::Measured,
    ) -> std::pin::Pin<Box<dyn Future<Output = Result<(), String>> + Send + '_>> {
        Box::pin(async { Ok(()) })
    }

    fn change(&self, event: crate::api::record::Event) -> Result<(), String> {
        if self.refuse.load(std::sync::atomic::Ordering::SeqCst) {
            return Err("the disk is full".into());
        }
        self.events.lock().expect("events").push(event);
        Ok(())
    }
}

/// Issue 48, item 2: a PUT or DELETE of a legally relevant document is handed to the log
/// as an event (the document, its SHA-256 before and after as GET serves it, who); one
/// the log cannot keep is undone, in memory and in the state directory, and answered
/// 5.03. Other documents are no events.
#[test]
fn a_change_of_a_legal_document_is_an_event_and_undone_when_it_cannot_be_recorded() {
    use crate::api::record::{Change, sha256_hex};
    let state = ScratchDir::new("audited-puts");
    runtime().block_on(async {
        let rig = Rig::start(&state);
        let audit = Arc::new(Audit::default());
        rig.cams.set_records(audit.clone());
        let camera = cameras().swap_remove(0);
        let sn = camera.serial();
        rig.hub.add(camera).expect("plug in");
        let config = format!("/cams/{sn}/application-config");
        let transformation = format!("/cams/{sn}/3d-transformation");
        rig.routed(&transformation, true).await;
        let before = rig.send(Code::GET, &config, b"").await.payload;
        let mut doc: serde_json::Value = serde_json::from_slice(&before).expect("JSON");
        doc["depth_grab_timeout_ms"] = 1234.into();
        let put = rig
            .send(Code::PUT, &config, doc.to_string().as_bytes())
            .await;
        assert_eq!(put.code, Code::CHANGED);
        let after = rig.send(Code::GET, &config, b"").await.payload;
        {
            let events = audit.events.lock().expect("events");
            assert_eq!(events.len(), 1);
            let e = &events[0];
            assert_eq!(e.document, config);
            assert_eq!(e.change, Change::Put);
            assert_eq!(e.old_sha256, sha256_hex(&before));
            assert_eq!(e.new_sha256, sha256_hex(&after));
            assert!(e.by.starts_with("coap://127.0.0.1:"), "{}", e.by);
            assert_eq!(
                e.parameters_sha256,
                crate::server::measure::Rig::parameters_sha256(&*rig.cams)
            );
        }
        // The log refuses: nothing changes.
        audit
            .refuse
            .store(true, std::sync::atomic::Ordering::SeqCst);
        let pose = rig.send(Code::GET, &transformation, b"").await.payload;
        let mut moved: serde_json::Value = serde_json::from_slice(&pose).expect("JSON");
        moved["translation_matrix"] = serde_json::json!([[0.5], [0.5], [0.5]]);
        let put = rig
            .send(Code::PUT, &transformation, moved.to_string().as_bytes())
            .await;
        assert_eq!(put.code, Code::SERVICE_UNAVAILABLE);
        let why = String::from_utf8_lossy(&put.payload);
        assert!(
            why.contains("could not be recorded (the disk is full)"),
            "{why}"
        );
        assert_eq!(
            rig.send(Code::GET, &transformation, b"").await.payload,
            pose
        );
        let dir = state.0.join(sn.as_str());
        assert!(!dir.join("3d-transformation.json").exists());
        let deleted = rig.send(Code::DELETE, &config, b"").await;
        assert_eq!(deleted.code, Code::SERVICE_UNAVAILABLE);
        assert_eq!(rig.send(Code::GET, &config, b"").await.payload, after);
        let kept = std::fs::read(dir.join("application-config.json")).expect("kept");
        assert_eq!(kept, after);
        assert!(rig.router.patterns().contains(&config));
        // Not a legally relevant document: no event, and the refusal does not matter.
        let depth = format!("/cams/{sn}/depth-settings");
        let settings = rig.send(Code::GET, &depth, b"").await.payload;
        assert_eq!(
            rig.send(Code::PUT, &depth, &settings).await.code,
            Code::CHANGED
        );
        assert_eq!(audit.events.lock().expect("events").len(), 1);
    });
}

/// A camera with only what every depth camera has, under a name no D400 has: a synthetic
/// camera's frames, without a stereo pair or the advanced mode (as a time-of-flight
/// camera of another backend would be).
struct Plain(SyntheticCamera);

impl rgbd::Camera for Plain {
    fn serial(&self) -> rgbd::Serial {
        self.0.serial()
    }
    fn model(&self) -> &str {
        "a camera without a stereo pair"
    }
    fn stream_modes(&self) -> &rgbd::ModeTable {
        self.0.stream_modes()
    }
    fn color_settings(&self) -> rgbd::ColorSettings {
        self.0.color_settings()
    }
    fn set_color_settings(&self, s: rgbd::ColorSettings) -> Result<(), rgbd::CameraError> {
        self.0.set_color_settings(s)
    }
    fn depth_settings(&self) -> rgbd::DepthSettings {
        self.0.depth_settings()
    }
    fn set_depth_settings(&self, s: rgbd::DepthSettings) -> Result<(), rgbd::CameraError> {
        self.0.set_depth_settings(s)
    }
    fn grab_color(&self, timeout: Duration) -> Result<rgbd::ColorFrame, rgbd::CameraError> {
        self.0.grab_color(timeout)
    }
    fn grab_depth(&self, timeout: Duration) -> Result<rgbd::DepthFrame, rgbd::CameraError> {
        self.0.grab_depth(timeout)
    }
    fn depth_intrinsics(&self) -> Result<rgbd::Intrinsics, rgbd::CameraError> {
        self.0.depth_intrinsics()
    }
    fn color_intrinsics(&self) -> Result<rgbd::Intrinsics, rgbd::CameraError> {
        self.0.color_intrinsics()
    }
    fn depth_to_color(&self) -> Result<rgbd::Extrinsics, rgbd::CameraError> {
        self.0.depth_to_color()
    }
    fn depth_scale(&self) -> f32 {
        self.0.depth_scale()
    }
    fn stereo_baseline_m(&self) -> Option<f32> {
        None
    }
    fn true_pose(&self) -> Option<rgbd::Pose> {
        self.0.true_pose()
    }
}

#[test]
fn a_camera_without_the_d400_extras_serves_all_else_and_says_what_it_lacks() {
    let state = ScratchDir::new("plain");
    runtime().block_on(async {
        let rig = Rig::start(&state);
        let mut scene = Scene::default_single();
        let sn = rgbd::Serial::parse("rec-01").expect("a serial");
        scene.cameras[0].serial = sn;
        let plain = Plain(SyntheticCamera::new(&scene, &sn).expect("the camera"));
        rig.hub.add(Arc::new(plain)).expect("plug in");
        rig.routed("/cams/rec-01/color", true).await;
        let links = rig.discovery().await;
        for name in ["color", "depth", "pointcloud", "application-config"] {
            assert!(links.contains(&format!("</cams/rec-01/{name}>")), "{links}");
        }
        assert!(!links.contains("</cams/rec-01/advanced-config>"), "{links}");

        // The advanced-config: 4.04 with the reason, whatever the method; creating it is
        // refused with the same reason.
        for method in [Code::GET, Code::PUT, Code::DELETE] {
            let r = rig
                .send(method, "/cams/rec-01/advanced-config", b"{}")
                .await;
            assert_eq!(r.code, Code::NOT_FOUND, "{method:?}");
            let text = String::from_utf8_lossy(&r.payload);
            assert!(text.contains("has no advanced mode"), "{method:?}: {text}");
        }
        let r = rig
            .send(Code::POST, "/cams/advanced-config", b"rec-01")
            .await;
        assert_eq!(r.code, Code::BAD_REQUEST);
        assert!(String::from_utf8_lossy(&r.payload).contains("has no advanced mode"));
        let r = rig
            .send(Code::GET, "/cams/rec-02/advanced-config", b"")
            .await;
        assert_eq!(
            (r.code, String::from_utf8_lossy(&r.payload).as_ref()),
            (Code::NOT_FOUND, "no such resource")
        );

        // The spatial filter works on disparity: refused; the other filters run.
        let config = "/cams/rec-01/application-config";
        let doc = rig.send(Code::GET, config, b"").await.payload;
        let mut doc: serde_json::Value = serde_json::from_slice(&doc).expect("JSON");
        doc["postprocessing"] = serde_json::json!({"spatial": 1});
        let r = rig
            .send(Code::PUT, config, doc.to_string().as_bytes())
            .await;
        assert_eq!(r.code, Code::BAD_REQUEST);
        let text = String::from_utf8_lossy(&r.payload);
        assert!(text.contains("needs a stereo pair"), "{text}");
        doc["postprocessing"] = serde_json::json!({"decimation": 1, "holefilling": 1});
        let r = rig
            .send(Code::PUT, config, doc.to_string().as_bytes())
            .await;
        assert_eq!(r.code, Code::CHANGED);
        for grab in ["color", "depth", "pointcloud"] {
            let path = format!("/cams/rec-01/{grab}");
            assert_eq!(rig.send(Code::POST, &path, b"").await.code, Code::CONTENT);
        }
        let r = rig.send(Code::POST, "/cams/pointclouds", b"").await;
        assert_eq!(r.code, Code::CONTENT);
    });
}

/// The flying-pixel stage drops pixels at depth steps, pixels that returned depth: the
/// parts of the table without depth are found before it, so the holes it leaves are no
/// phantom parcels. A certification-set station (seed 1, scene 93: a glossy 1,056 x 554 x
/// 546 mm box under four cameras) listed one when they were found after the stage.
#[test]
fn the_holes_the_flying_pixel_stage_leaves_are_no_part_of_the_table_without_depth() {
    use geometry::{Point3, Roi3};
    use rgbd::filter::{FlyingPixelsConfig, SpatialConfig};

    // As drawn before the set's labels took every symbology (rgbd's tests/fixtures/cert).
    let scene = Scene::from_toml(include_str!(
        "../../../../rgbd/tests/fixtures/cert/cert-1-93.toml"
    ))
    .expect("a scene");
    let defaults = crate::documents::AppConfig::default();
    let app = crate::documents::AppConfig {
        roi3d: Roi3::new(Point3::new(-1.5, -1.5, 0.005), Point3::new(1.5, 1.5, 3.0)).unwrap(),
        postprocessing: rgbd::PostProcessingConfig {
            spatial: Some(SpatialConfig::default()),
            flying_pixels: Some(FlyingPixelsConfig::default()),
            ..defaults.postprocessing
        },
        ..defaults
    };
    let (mut before, mut after) = (0, 0);
    for cam in SyntheticCamera::all(&scene).expect("the station's cameras") {
        let pose = crate::vision::calibration::pose_transformation(
            &cam.true_pose().expect("a calibrated camera"),
        );
        let Ok(super::grab::Frame::Cloud { no_depth, .. }) =
            super::grab::cloud(cam.as_ref(), &app, &pose)
        else {
            panic!("no cloud")
        };
        after += no_depth.len();
        // Found after the stages, as they were.
        let frame = cam.grab_depth(Duration::from_secs(1)).expect("a frame");
        let k = cam.depth_intrinsics().expect("intrinsics");
        let baseline = cam.stereo_baseline_m();
        let mut chain =
            rgbd::PostProcessing::new(&app.postprocessing, baseline.map(|b| b * 1000.0)).unwrap();
        let (processed, k) = chain.process(&frame, &k).unwrap();
        let part = crate::repr::clouds::DepthPart {
            serial: String::new(),
            depth: processed.clone(),
            intrinsics: k,
            transform: pose.to_transform().unwrap(),
            roi: app.roi3d,
            correction: None,
        };
        before += part.no_depth(baseline).len();
    }
    assert_eq!(after, 0, "regions without depth found before the stages");
    assert!(
        before > 0,
        "found after the stages, the stage's holes were regions"
    );
}
