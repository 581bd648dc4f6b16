//! The `coapcam` library in one process, without the binary: a `SceneServer` on a loopback
//! port, the typed client, measuring, and the decoders reading what the server's encoders
//! wrote.

use std::net::SocketAddr;
use std::time::Duration;

use bytes::Bytes;
use coap::{Code, ContentFormat, EndpointConfig};
use coapcam::client::CamClient;
use coapcam::client::measure::{
    Source, grab_clouds, measure_once, prepare_cameras, truth, yaw_difference,
};
use coapcam::report::{Billing, EdgeQuery, Measurement};
use coapcam::repr::{self, Stream, cbor, clouds, packet, raster, rvl};
use coapcam::server::SceneServer;
use geometry::DimensionConfig;
use rgbd::Scene;

use crate::support::{TempDir, runtime};

/// A scene server and a client of it.
async fn start(scene: &Scene, state: &TempDir) -> (SceneServer, CamClient) {
    let server = SceneServer::start(scene, state.path(), SocketAddr::from(([127, 0, 0, 1], 0)))
        .await
        .expect("scene server");
    let uri = format!("coap://{}", server.addr().expect("its address"));
    let client = CamClient::connect(
        &uri,
        EndpointConfig::default(),
        None,
        Duration::from_secs(60),
    )
    .await
    .expect("client");
    (server, client)
}

#[test]
fn the_library_measures_the_demo_scene_in_process() {
    let state = TempDir::new("library-measure");
    let scene = Scene::default_demo();
    runtime().block_on(async {
        let (_server, client) = start(&scene, &state).await;
        let serials = client.cameras().await.expect("discovery");
        assert_eq!(serials.len(), scene.cameras.len());
        prepare_cameras(&client, &serials, 1.0, false)
            .await
            .expect("prepare");
        let m = measure_once(&client, &Source::All, &DimensionConfig::default())
            .await
            .expect("measure");
        let [length, width, height, yaw] = truth(&scene).expect("the scene has a box");
        let d = m.dimensions().expect("the box is measured");
        for (got, want, what) in [
            (d.length_mm, length, "length"),
            (d.width_mm, width, "width"),
            (d.height_mm, height, "height"),
        ] {
            assert!(
                (got - want).abs() < 5.0,
                "{what}: {got:.1} mm, truth {want:.1} mm"
            );
        }
        assert!(
            yaw_difference(d.yaw_deg, yaw).abs() < 2.0,
            "yaw {}",
            d.yaw_deg
        );
        assert_eq!(m.grabbed.cameras.len(), scene.cameras.len());
    });
}

#[test]
fn every_representation_decodes_to_the_same_frame() {
    let state = TempDir::new("library-repr");
    let scene = Scene::default_single();
    runtime().block_on(async {
        let (_server, client) = start(&scene, &state).await;
        let sn = client.one_camera(None).await.expect("one camera");
        // A grab makes a new frame; GET answers the last one in any format.
        client
            .grab(&sn, Stream::Depth, None)
            .await
            .expect("depth grab");
        let get = |cf: ContentFormat| {
            let path = format!("/cams/{sn}/depth");
            let client = &client;
            async move {
                client
                    .call(Code::GET, &path, Bytes::new(), None, Some(cf))
                    .await
                    .expect("GET depth")
                    .payload
            }
        };
        let from_packet = packet::depth(&get(ContentFormat::OCTET_STREAM).await).expect("packet");
        let from_png = raster::depth_from_png(&get(ContentFormat::IMAGE_PNG).await).expect("png");
        assert_eq!(from_png.values, from_packet.values);
        assert_eq!(
            (from_png.width, from_png.height),
            (from_packet.width, from_packet.height)
        );
        for from_rvl in [
            rvl::depth_from_rvl(&get(repr::RVL).await).expect("rvl"),
            rvl::depth_from_rvl_zstd(&get(repr::RVL_ZSTD).await).expect("rvl+zstd"),
        ] {
            // Everything the packet carries, the depth scale and the second included.
            assert_eq!(from_rvl, from_packet);
        }

        client
            .grab(&sn, Stream::Pointcloud, None)
            .await
            .expect("cloud grab");
        let path = format!("/cams/{sn}/pointcloud");
        let mut clouds: Vec<geometry::PointCloud> = Vec::new();
        for cf in Stream::Pointcloud.formats() {
            let body = client
                .call(Code::GET, &path, Bytes::new(), None, Some(cf))
                .await
                .expect("GET pointcloud")
                .payload;
            clouds.push(match cf {
                ContentFormat::OCTET_STREAM => packet::cloud(&body).expect("packet").cloud,
                ContentFormat::CBOR => cbor::Cloud::from_cbor(&body).expect("cbor").cloud,
                repr::PLY => geometry::decode_ply(&body).expect("ply"),
                repr::DEPTH_CLOUD => {
                    clouds::cloud_from_depth_cloud(&body)
                        .expect("compact")
                        .cloud
                }
                repr::CLOUD_MM => {
                    let mm = clouds::cloud_from_mm(&body).expect("mm").cloud;
                    assert_eq!(mm.len(), clouds[0].len());
                    for (a, b) in mm.points.iter().zip(&clouds[0].points) {
                        assert!((a - b).abs().max() <= 0.000_51, "{a} {b}");
                    }
                    continue;
                }
                other => panic!("a format the table does not list: {other:?}"),
            });
        }
        assert!(!clouds[0].is_empty());
        // Bit for bit: the compact cloud's points are computed again by the client.
        assert!(clouds.iter().all(|c| bits(c) == bits(&clouds[0])));
    });
}

#[test]
fn both_cameras_read_the_code128_label_of_the_code128_scene() {
    let state = TempDir::new("library-code128");
    let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../../scenes/code128.toml");
    let scene = Scene::load(std::path::Path::new(path)).expect("scenes/code128.toml");
    runtime().block_on(async {
        let (_server, client) = start(&scene, &state).await;
        let serials = client.cameras().await.expect("discovery");
        prepare_cameras(&client, &serials, 1.0, true)
            .await
            .expect("prepare for codes");
        let cameras: Vec<(SocketAddr, String)> = serials
            .iter()
            .map(|sn| (client.server(), sn.clone()))
            .collect();
        let seen = coapcam::client::codes::read_cameras(&client, &cameras)
            .await
            .expect("reading codes");
        assert_eq!(seen.len(), 1, "{seen:?}");
        assert_eq!(seen[0].code.text, "1Z999AA10123456784", "{seen:?}");
        assert_eq!(seen[0].cameras.len(), 2, "{seen:?}");
    });
}

#[test]
fn the_default_scenes_qr_label_reads_at_1920x1080() {
    let state = TempDir::new("library-qr");
    let scene = Scene::default_single();
    runtime().block_on(async {
        let (_server, client) = start(&scene, &state).await;
        let serials = client.cameras().await.expect("discovery");
        prepare_cameras(&client, &serials, 1.0, true)
            .await
            .expect("prepare for codes");
        let cameras = vec![(client.server(), serials[0].clone())];
        let seen = coapcam::client::codes::read_cameras(&client, &cameras)
            .await
            .expect("reading codes");
        let texts: Vec<&str> = seen.iter().map(|s| s.code.text.as_str()).collect();
        assert_eq!(texts, ["PKG-0001"], "{seen:?}");
    });
}

#[test]
fn the_client_chooses_the_jpeg_quality() {
    let state = TempDir::new("library-jpeg");
    let scene = Scene::default_single();
    runtime().block_on(async {
        let (_server, client) = start(&scene, &state).await;
        let sn = client.one_camera(None).await.expect("one camera");
        let low = client.grab_jpeg(&sn, 20).await.expect("q=20");
        let high = client.grab_jpeg(&sn, 95).await.expect("q=95");
        for r in [&low, &high] {
            assert!(r.payload.starts_with(&[0xff, 0xd8]), "not a JPEG");
        }
        // Quality 20 is well below 95 (28 KB against 46 KB for the default scene).
        assert!(
            low.payload.len() * 4 < high.payload.len() * 3,
            "{} and {} bytes",
            low.payload.len(),
            high.payload.len()
        );
        // The latest frame at two qualities: two representations, two ETags.
        let get = |query: &'static str, accept: ContentFormat| {
            let mut request = client.request(
                Code::GET,
                &format!("/cams/{sn}/color"),
                Bytes::new(),
                None,
                Some(accept),
            );
            request
                .options
                .push(coap::OptionNumber::URI_QUERY, query.as_bytes());
            let c = client.coap().clone();
            let server = client.server();
            async move { c.send(server, request).await.expect("an answer") }
        };
        let (a, b) = (
            get("q=30", ContentFormat::IMAGE_JPEG).await,
            get("q=31", ContentFormat::IMAGE_JPEG).await,
        );
        assert_eq!((a.code, b.code), (Code::CONTENT, Code::CONTENT));
        assert_ne!(a.options.etag(), b.options.etag());
        for (query, accept) in [
            ("q=0", ContentFormat::IMAGE_JPEG),
            ("q=101", ContentFormat::IMAGE_JPEG),
            ("q=high", ContentFormat::IMAGE_JPEG),
            ("q=50", ContentFormat::IMAGE_PNG),
        ] {
            let r = get(query, accept).await;
            assert_eq!(r.code, Code::BAD_REQUEST, "{query} {accept}");
        }
    });
}

#[test]
fn the_server_measures_at_the_edge_as_the_client_does() {
    let state = TempDir::new("library-edge");
    let scene = Scene::default_demo();
    runtime().block_on(async {
        let (server, client) = start(&scene, &state).await;
        let serials = client.cameras().await.expect("discovery");
        prepare_cameras(&client, &serials, 1.0, true)
            .await
            .expect("prepare");
        // Before the first measurement GET has nothing; the observer hears of the next.
        let get = |accept| client.call(Code::GET, "/cams/dimensions", Bytes::new(), None, accept);
        let none = get(None).await.expect_err("nothing measured yet");
        assert!(format!("{none:#}").contains("4.04"), "{none:#}");
        let query = EdgeQuery {
            codes: true,
            ..EdgeQuery::default()
        };
        let (measured, bytes) = client
            .measure_edge(&query)
            .await
            .expect("POST /cams/dimensions")
            .expect("the server offers it");
        let doc = serde_json::to_value(&measured).expect("a document");
        // About a kilobyte (two cameras' frames, a parcel, a code), not the clouds' megabytes.
        assert!(bytes < 2000, "{bytes} bytes");
        let [length, width, height, _] = truth(&scene).expect("the scene has a box");
        for (key, want) in [
            ("length_mm", length),
            ("width_mm", width),
            ("height_mm", height),
        ] {
            let got = doc[key].as_f64().expect(key);
            assert!(
                (got - want).abs() < 5.0,
                "{key}: {got:.1} mm, truth {want:.1} mm"
            );
        }
        assert_eq!(doc["cameras"], serde_json::json!(serials));
        assert_eq!(doc["warnings"], serde_json::json!([]));
        let codes = doc["codes"].as_array().expect("codes");
        assert!(
            codes
                .iter()
                .any(|c| c["text"] == "PKG-0001" && c["kind"] == "qr"),
            "{codes:?}"
        );

        // The same fields as the client's own measurement (which adds where it measured
        // from and how long the transfer took).
        let here = measure_once(&client, &Source::All, &DimensionConfig::default())
            .await
            .expect("measure here")
            .report(&Billing::default());
        let here = serde_json::to_value(&here).expect("a document");
        let keys = |v: &serde_json::Value| {
            let mut k: Vec<String> = v.as_object().expect("a map").keys().cloned().collect();
            k.retain(|k| {
                ![
                    "servers",
                    "cycle_ms",
                    "received_bytes",
                    "codes",
                    "codes_ms",
                    "warnings",
                    "measure_ms",
                ]
                .contains(&k.as_str())
            });
            k
        };
        assert_eq!(keys(&doc), keys(&here));
        // Two measurements of other frames: their numbers before the rounding agree (the
        // rounded ones could fall either side of a division's midpoint).
        for (k, key) in ["length", "width", "height"].into_iter().enumerate() {
            let (a, b) = (
                doc["unrounded_mm"][k].as_f64().expect(key),
                here["unrounded_mm"][k].as_f64().expect(key),
            );
            assert!((a - b).abs() < 3.0, "{key}: {a} at the edge, {b} here");
        }

        // GET gives the latest, as JSON or CBOR; an Observe registration the next one.
        let json: serde_json::Value =
            serde_json::from_slice(&get(None).await.expect("GET").payload).expect("JSON");
        assert_eq!(json, doc);
        let cbor = get(Some(ContentFormat::CBOR))
            .await
            .expect("GET CBOR")
            .payload;
        let cbor: serde_json::Value = ciborium::from_reader(&cbor[..]).expect("CBOR");
        assert_eq!(cbor, doc);
        let refused = get(Some(ContentFormat::OCTET_STREAM))
            .await
            .expect_err("4.06");
        assert!(format!("{refused:#}").contains("4.06"), "{refused:#}");
        let mut register = coap::Request::new(Code::GET, "/cams/dimensions");
        register.timeout = Some(Duration::from_secs(60));
        let mut observation = client
            .coap()
            .observe(client.server(), register)
            .await
            .expect("observe");
        let first = tokio::time::timeout(Duration::from_secs(60), observation.next()).await;
        assert!(matches!(first, Ok(Some(Ok(_)))), "{first:?}");
        let (next, _) = client
            .measure_edge(&EdgeQuery::default())
            .await
            .expect("measure again")
            .expect("offered");
        assert!(next.codes.is_none(), "codes only when asked");
        let note = tokio::time::timeout(Duration::from_secs(60), observation.next()).await;
        match note {
            Ok(Some(Ok(r))) => {
                let noted = Measurement::from_json(&r.payload).expect("JSON");
                assert_eq!(noted, next);
            }
            other => panic!("no notification after a measurement: {other:?}"),
        }

        // In process, the same measurement without CoAP; it becomes the latest.
        let local = server
            .measure_now(&EdgeQuery::default())
            .await
            .expect("measured in process");
        assert!(
            local.servers.is_empty() && local.cycle_ms.is_none(),
            "{local:?}"
        );
        assert_eq!(local.cameras, next.cameras);
        let latest = Measurement::from_json(&get(None).await.expect("GET").payload).expect("JSON");
        assert_eq!(latest, local);

        // A query it does not know is refused, naming what it takes.
        let mut request = client.request(Code::POST, "/cams/dimensions", Bytes::new(), None, None);
        request
            .options
            .push(coap::OptionNumber::URI_QUERY, b"colour");
        let refused = client
            .coap()
            .send(client.server(), request)
            .await
            .expect("an answer");
        assert_eq!(refused.code, Code::BAD_REQUEST);
        assert!(String::from_utf8_lossy(&refused.payload).contains("min_height_mm"));
    });
}

#[test]
fn depth_and_clouds_come_compact_and_as_packets_from_a_server_without_them() {
    let state = TempDir::new("library-depth");
    let scene = Scene::default_single();
    runtime().block_on(async {
        // Ours offers RVL+zstd and the compact cloud: each equals the packet of the same
        // frame (the cloud bit for bit).
        let (_server, client) = start(&scene, &state).await;
        let sn = client.one_camera(None).await.expect("one camera");
        let compact = client.grab_depth(&sn).await.expect("RVL+zstd depth");
        let compact_cloud = grab_clouds(&client, &Source::Camera(sn.clone()))
            .await
            .expect("compact cloud");
        let mut packets = Vec::new();
        for stream in [Stream::Depth, Stream::Pointcloud] {
            let path = format!("/cams/{sn}/{}", stream.name());
            let get = client
                .call(Code::GET, &path, Bytes::new(), None, None)
                .await
                .expect("GET the packet");
            packets.push((path, get.payload));
        }
        assert_eq!(compact, packet::depth(&packets[0].1).expect("packet"));
        let from_packet = packet::cloud(&packets[1].1).expect("packet").cloud;
        assert!(compact_cloud.bytes * 3 < packets[1].1.len());
        assert_eq!(bits(&compact_cloud.cloud), bits(&from_packet));

        // A server that knows only the thesis packet answers 4.06 to anything else.
        let router = coap_net::Router::new();
        for (path, body) in packets {
            router.add(
                &path,
                coap_net::Resource::new().post(coap_net::handler(move |ctx| {
                    let body = body.clone();
                    async move {
                        match ctx.request.options.accept() {
                            None | Some(ContentFormat::OCTET_STREAM) => {
                                coap::Response::new(Code::CONTENT).with_payload(body)
                            }
                            Some(_) => coap::Response::new(Code::NOT_ACCEPTABLE),
                        }
                    }
                })),
            );
        }
        let loopback = SocketAddr::from(([127, 0, 0, 1], 0));
        let old = coap_net::Server::bind(&[loopback], coap_net::ServerConfig::default(), router)
            .expect("a thesis-only server");
        let uri = format!("coap://{}", old.local_addrs()[0]);
        let thesis = CamClient::connect(
            &uri,
            EndpointConfig::default(),
            None,
            Duration::from_secs(10),
        )
        .await
        .expect("client");
        let image = thesis
            .grab_depth(&sn)
            .await
            .expect("the packet, after a 4.06");
        assert_eq!(image, compact);
        let cloud = grab_clouds(&thesis, &Source::Camera(sn.clone()))
            .await
            .expect("the cloud packet, after a 4.06");
        assert_eq!(bits(&cloud.cloud), bits(&from_packet));
        assert_eq!(cloud.cameras, [(thesis.server(), sn)]);
        // Nor does it measure: the client measures the clouds itself.
        let edge = thesis.measure_edge(&EdgeQuery::default()).await;
        assert!(matches!(edge, Ok(None)), "{edge:?}");
    });
}

fn bits(c: &geometry::PointCloud) -> Vec<[u32; 3]> {
    c.points
        .iter()
        .map(|p| [p.x.to_bits(), p.y.to_bits(), p.z.to_bits()])
        .collect()
}

/// The cameras `client` finds at `server` (`GET /.well-known/core?rt=rgbd.color`).
async fn serials_at(client: &coap_net::Client, server: SocketAddr) -> Vec<String> {
    let mut request = coap::Request::new(Code::GET, "/.well-known/core");
    request
        .options
        .push(coap::OptionNumber::URI_QUERY, b"rt=rgbd.color");
    let response = client.send(server, request).await.expect("discovery");
    let text = std::str::from_utf8(&response.payload).expect("UTF-8");
    let mut serials: Vec<String> = coap::link_format::parse(text)
        .expect("link format")
        .into_iter()
        .filter_map(|l| {
            let (sn, name) = l.target.strip_prefix("/cams/")?.split_once('/')?;
            (name == "color").then(|| sn.to_owned())
        })
        .collect();
    serials.sort();
    serials
}

#[test]
fn a_new_socket_on_an_earlier_ones_port_gets_todays_answers() {
    // A server takes a request with the message ID and token of one it answered within
    // EXCHANGE_LIFETIME from the same address and port for a duplicate and sends the
    // stored answer again. A client socket given the port of an earlier one must therefore
    // not start where that one started: with the seed of every client alike, this second
    // client is answered with the first scene's cameras.
    let state = TempDir::new("library-fresh-seed");
    let serials = |s: &Scene| {
        let mut v: Vec<String> = s.cameras.iter().map(|c| c.serial.to_string()).collect();
        v.sort();
        v
    };
    let first = rgbd::lane::lane_scene(1, 0).scene;
    let second = (1..100)
        .map(|i| rgbd::lane::lane_scene(1, i).scene)
        .find(|s| serials(s) != serials(&first))
        .expect("a scene with other cameras");
    runtime().block_on(async {
        let server =
            SceneServer::start(&first, state.path(), SocketAddr::from(([127, 0, 0, 1], 0)))
                .await
                .expect("scene server");
        let addr = server.addr().expect("its address");
        let config = || EndpointConfig {
            rng_seed: coap_net::fresh_seed(),
            ..EndpointConfig::default()
        };
        let client = coap_net::Client::bind(SocketAddr::from(([127, 0, 0, 1], 0)), config())
            .expect("a client");
        let port = client.local_addr();
        assert_eq!(serials_at(&client, addr).await, serials(&first));
        drop(client);
        server.load(&second).expect("the second scene");
        // The first socket closes once its driver has seen the handle go.
        let mut again = None;
        for _ in 0..200 {
            match coap_net::Client::bind(port, config()) {
                Ok(c) => {
                    again = Some(c);
                    break;
                }
                Err(_) => tokio::time::sleep(Duration::from_millis(10)).await,
            }
        }
        let again = again.expect("the first client's port, free again");
        assert_eq!(serials_at(&again, addr).await, serials(&second));
    });
}

#[test]
fn a_malformed_no_depth_option_is_ignored_as_the_elective_option_it_is() {
    let state = TempDir::new("library-no-depth");
    let scene = Scene::default_single();
    runtime().block_on(async {
        let (_server, client) = start(&scene, &state).await;
        let sn = client.one_camera(None).await.expect("one camera");
        let real = client.grab_cloud(Some(&sn)).await.expect("a cloud");
        // A server (or a path) that sends the same cloud with a No-Depth option of 7 bytes,
        // which is no whole region: elective, so it is left out, not fatal.
        let router = coap_net::Router::new();
        let (payload, options) = (real.payload.clone(), real.options.clone());
        router.add(
            &format!("/cams/{sn}/pointcloud"),
            coap_net::Resource::new().post(coap_net::handler(move |_| {
                let (payload, mut options) = (payload.clone(), options.clone());
                async move {
                    options.set(repr::no_depth::NO_DEPTH, [0u8; 7]);
                    let mut r = coap::Response::new(Code::CONTENT).with_payload(payload);
                    r.options = options;
                    r
                }
            })),
        );
        let loopback = SocketAddr::from(([127, 0, 0, 1], 0));
        let odd = coap_net::Server::bind(&[loopback], coap_net::ServerConfig::default(), router)
            .expect("a server with a malformed option");
        let uri = format!("coap://{}", odd.local_addrs()[0]);
        let odd_client = CamClient::connect(
            &uri,
            EndpointConfig::default(),
            None,
            Duration::from_secs(10),
        )
        .await
        .expect("client");
        let through = grab_clouds(&odd_client, &Source::Camera(sn.clone()))
            .await
            .expect("the cloud, the malformed option left out");
        assert!(through.no_depth.is_empty());
        assert!(
            through.cloud.len() > 10_000,
            "{} points",
            through.cloud.len()
        );
        assert_eq!(through.cameras, [(odd_client.server(), sn)]);
    });
}

/// A backend of the test's own: the synthetic cameras of a scene, and a flag set when it
/// is dropped.
struct Flagged {
    scene: Scene,
    dropped: std::sync::Arc<std::sync::atomic::AtomicBool>,
}

impl coapcam::backends::Backend for Flagged {
    fn start(
        &mut self,
        hub: &std::sync::Arc<rgbd::CameraHub>,
    ) -> Result<Vec<rgbd::Serial>, coapcam::backends::StartError> {
        let cameras = rgbd::SyntheticCamera::all(&self.scene)
            .map_err(coapcam::backends::StartError::Scene)?;
        coapcam::backends::synthetic::add(hub, cameras)
    }
}

impl Drop for Flagged {
    fn drop(&mut self) {
        self.dropped
            .store(true, std::sync::atomic::Ordering::SeqCst);
    }
}

/// The built-in single-camera scene, and the same with its camera's serial
/// 111111111111 (served beside it, or instead of it).
fn default_and_another() -> (Scene, Scene) {
    let single = Scene::default_single();
    let mut other = single.clone();
    other.cameras[0].serial = "111111111111".parse().expect("a serial");
    (single, other)
}

#[test]
fn a_camera_server_serves_the_cameras_of_every_backend_in_its_list_until_it_is_dropped() {
    let state = TempDir::new("library-backends");
    let (single, other) = default_and_another();
    let dropped = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
    let cameras: Vec<Box<dyn coapcam::backends::Backend>> = vec![
        Box::new(coapcam::backends::synthetic::Synthetic(other)),
        Box::new(Flagged {
            scene: single,
            dropped: dropped.clone(),
        }),
    ];
    runtime().block_on(async {
        let server = coapcam::server::CameraServer::start(coapcam::server::Config {
            binds: vec![SocketAddr::from(([127, 0, 0, 1], 0))],
            cameras,
            state_dir: state.path().to_path_buf(),
            static_dir: None,
            writable: false,
            quota: None,
            groups: Vec::new(),
            group_interface: 0,
            endpoint: EndpointConfig::default(),
            allow_unauthenticated_config: false,
            grab_memory: 1 << 28,
            secure_binds: Vec::new(),
            tcp_binds: Vec::new(),
            ws_binds: Vec::new(),
            tls_binds: Vec::new(),
            wss_binds: Vec::new(),
            identities: None,
            clock_offset_us: 0,
            live: coapcam::server::LiveLimits::default(),
        })
        .await
        .expect("camera server");
        let addr = server.local_addrs()[0];
        let client = coap_net::Client::bind(
            SocketAddr::from(([127, 0, 0, 1], 0)),
            EndpointConfig::default(),
        )
        .expect("a client");
        assert_eq!(
            serials_at(&client, addr).await,
            ["111111111111", "840412060746"]
        );
        assert!(!dropped.load(std::sync::atomic::Ordering::SeqCst));
        drop(server);
        assert!(dropped.load(std::sync::atomic::Ordering::SeqCst));
    });
}

#[test]
fn a_scene_that_cannot_be_built_leaves_the_cameras_served_before_it() {
    let state = TempDir::new("library-bad-scene");
    let (first, mut bad) = default_and_another();
    // Looking at its own position: no pose, so no camera.
    bad.cameras[0].look_at = bad.cameras[0].position;
    runtime().block_on(async {
        let server =
            SceneServer::start(&first, state.path(), SocketAddr::from(([127, 0, 0, 1], 0)))
                .await
                .expect("scene server");
        let addr = server.addr().expect("its address");
        let client = coap_net::Client::bind(
            SocketAddr::from(([127, 0, 0, 1], 0)),
            EndpointConfig::default(),
        )
        .expect("a client");
        let e = server.load(&bad).expect_err("a camera without a pose");
        assert!(
            matches!(
                e,
                coapcam::server::StartError::Cameras(coapcam::backends::StartError::Scene(_))
            ),
            "{e:?}"
        );
        assert!(
            coapcam::error_text(&e).starts_with("building the scene's cameras"),
            "{e:#}"
        );
        assert_eq!(serials_at(&client, addr).await, ["840412060746"]);
    });
}
