//! `coapcam serve` with the built-in synthetic camera: thesis Table 3.1 (every row and
//! method), the JSON resources, persistence across restarts, packet sizes and Block2.

use coap::{Code, OptionNumber, Request};

use crate::support::{
    COLOR_640, DEPTH_640, LIMIT, SN, TempDir, client, runtime, send, serve, serve_with,
};

#[test]
fn table_3_1_every_row_and_method() {
    let state = TempDir::new("cams-table");
    let (_server, addr) = serve(state.path());
    runtime().block_on(async {
        let c = client();
        let code = |method, path: String, payload: &'static str| {
            let c = &c;
            async move {
                send(c, addr, method, &path, payload.as_bytes(), None)
                    .await
                    .code
            }
        };
        use Code as C;
        // Smaller frames keep the grabs quick.
        assert_eq!(
            code(C::PUT, format!("/cams/{SN}/color-settings"), COLOR_640).await,
            C::CHANGED
        );
        assert_eq!(
            code(C::PUT, format!("/cams/{SN}/depth-settings"), DEPTH_640).await,
            C::CHANGED
        );
        // /cams and /cams/pointclouds.
        for (m, want) in [
            (C::GET, C::CONTENT),
            (C::POST, C::METHOD_NOT_ALLOWED),
            (C::PUT, C::METHOD_NOT_ALLOWED),
            (C::DELETE, C::METHOD_NOT_ALLOWED),
        ] {
            assert_eq!(code(m, "/cams".into(), "").await, want, "{m:?} /cams");
        }
        for (m, want) in [
            (C::GET, C::METHOD_NOT_ALLOWED),
            (C::POST, C::CONTENT),
            (C::PUT, C::METHOD_NOT_ALLOWED),
            (C::DELETE, C::METHOD_NOT_ALLOWED),
        ] {
            assert_eq!(
                code(m, "/cams/pointclouds".into(), "").await,
                want,
                "{m:?} /cams/pointclouds"
            );
        }
        let names = [
            "color",
            "depth",
            "pointcloud",
            "color-settings",
            "depth-settings",
            "application-config",
            "3d-transformation",
            "advanced-config",
        ];
        for name in names {
            let create = format!("/cams/{name}");
            for m in [C::GET, C::PUT, C::DELETE] {
                assert_eq!(
                    code(m, create.clone(), SN).await,
                    C::METHOD_NOT_ALLOWED,
                    "{m:?} {create}"
                );
            }
            assert_eq!(
                code(C::POST, create.clone(), "84041206074").await,
                C::BAD_REQUEST
            );
            assert_eq!(
                code(C::POST, create.clone(), "000000000000").await,
                C::BAD_REQUEST
            );
            let r = send(&c, addr, C::POST, &create, SN.as_bytes(), None).await;
            assert_eq!(r.code, C::CREATED, "POST {create}");
            let location: Vec<&[u8]> = r.options.values(OptionNumber::LOCATION_PATH).collect();
            assert_eq!(
                location,
                [b"cams".as_slice(), SN.as_bytes(), name.as_bytes()]
            );

            let path = format!("/cams/{SN}/{name}");
            if ["color", "depth", "pointcloud"].contains(&name) {
                assert_eq!(
                    code(C::GET, path.clone(), "").await,
                    C::NOT_FOUND,
                    "GET {path} before a grab"
                );
                assert_eq!(
                    code(C::POST, path.clone(), "").await,
                    C::CONTENT,
                    "POST {path}"
                );
                assert_eq!(
                    code(C::GET, path.clone(), "").await,
                    C::CONTENT,
                    "GET {path}"
                );
                assert_eq!(
                    code(C::PUT, path.clone(), "").await,
                    C::METHOD_NOT_ALLOWED,
                    "PUT {path}"
                );
            } else {
                let doc = send(&c, addr, C::GET, &path, b"", None).await;
                assert_eq!(doc.code, C::CONTENT, "GET {path}");
                let mut put = Request::new(C::PUT, &path).with_payload(doc.payload.clone());
                put.timeout = Some(LIMIT);
                assert_eq!(
                    c.send(addr, put).await.map(|r| r.code).ok(),
                    Some(C::CHANGED),
                    "PUT {path}"
                );
                assert_eq!(
                    code(C::POST, path.clone(), "").await,
                    C::METHOD_NOT_ALLOWED,
                    "POST {path}"
                );
            }
            assert_eq!(
                code(C::DELETE, path.clone(), "").await,
                C::DELETED,
                "DELETE {path}"
            );
            assert_eq!(
                code(C::GET, path.clone(), "").await,
                C::NOT_FOUND,
                "{path} after DELETE"
            );
            let links = send(&c, addr, C::GET, "/.well-known/core", b"", None).await;
            let gone = !String::from_utf8_lossy(&links.payload).contains(&format!("<{path}>"));
            assert!(gone, "{path} still in discovery");
            assert_eq!(code(C::POST, create, SN).await, C::CREATED);
        }
        let accept = send(
            &c,
            addr,
            C::POST,
            &format!("/cams/{SN}/pointcloud"),
            b"",
            Some(23),
        )
        .await;
        assert_eq!(accept.code, C::NOT_ACCEPTABLE);
        let png = send(
            &c,
            addr,
            C::POST,
            &format!("/cams/{SN}/depth"),
            b"",
            Some(23),
        )
        .await;
        assert!(png.payload.starts_with(b"\x89PNG"));
        let jpeg = send(
            &c,
            addr,
            C::POST,
            &format!("/cams/{SN}/color"),
            b"",
            Some(22),
        )
        .await;
        assert!(jpeg.payload.starts_with(&[0xff, 0xd8]));
    });
}

#[test]
fn json_resources_refuse_bad_documents_and_survive_a_restart() {
    let state = TempDir::new("cams-json");
    let app_config = format!("/cams/{SN}/application-config");
    let custom = r#"{"roi2d": {"px": 10, "py": 20, "width": 300, "height": 200},
        "roi3d": {"min_x": -0.5, "max_x": 0.5, "min_y": -0.5, "max_y": 0.5, "min_z": -0.1, "max_z": 0.5},
        "depth_grab_timeout_ms": 5000, "color_grab_timeout_ms": 4000, "icp": 0,
        "postprocessing": {"decimation": 1, "spatial": 0, "holefilling": 0}}"#;
    let (first_doc, color_doc) = {
        let (_server, addr) = serve(state.path());
        runtime().block_on(async {
            let c = client();
            let put = |path: String, body: String| {
                let c = &c;
                async move { send(c, addr, Code::PUT, &path, body.as_bytes(), None).await }
            };
            assert_eq!(
                put(app_config.clone(), custom.to_string()).await.code,
                Code::CHANGED
            );
            assert_eq!(
                put(format!("/cams/{SN}/color-settings"), COLOR_640.to_string())
                    .await
                    .code,
                Code::CHANGED
            );
            let before = send(&c, addr, Code::GET, &app_config, b"", None)
                .await
                .payload;
            for (bad, field) in [
                (custom.replace("\"icp\": 0", "\"icp\": 7"), "icp"),
                (custom.replace("\"width\": 300", "\"width\": 0"), "roi2d"),
                (custom.replace("\"max_z\": 0.5", "\"max_z\": -0.5"), "roi3d"),
                ("not json".to_string(), "JSON"),
            ] {
                let r = put(app_config.clone(), bad).await;
                assert_eq!(r.code, Code::BAD_REQUEST);
                assert!(
                    String::from_utf8_lossy(&r.payload).contains(field),
                    "{:?}",
                    r.payload
                );
                assert_eq!(
                    send(&c, addr, Code::GET, &app_config, b"", None)
                        .await
                        .payload,
                    before
                );
            }
            for (name, bad) in [
                (
                    "color-settings",
                    r#"{"format": "BGR8", "fps": 31, "width": 640, "height": 480}"#,
                ),
                (
                    "depth-settings",
                    r#"{"format": "Y8", "fps": 30, "width": 640, "height": 480}"#,
                ),
                ("3d-transformation", r#"{"rotation_matrix": 1}"#),
                ("advanced-config", r#"{"no-such-key": "1"}"#),
            ] {
                let path = format!("/cams/{SN}/{name}");
                let old = send(&c, addr, Code::GET, &path, b"", None).await.payload;
                assert_eq!(
                    put(path.clone(), bad.to_string()).await.code,
                    Code::BAD_REQUEST,
                    "{name}"
                );
                assert_eq!(
                    send(&c, addr, Code::GET, &path, b"", None).await.payload,
                    old,
                    "{name}"
                );
            }
            // roi2d crops the color image.
            let r = send(
                &c,
                addr,
                Code::POST,
                &format!("/cams/{SN}/color"),
                b"",
                None,
            )
            .await;
            assert_eq!(r.payload.len(), 10 + 300 * 200 * 3);
            let color = send(
                &c,
                addr,
                Code::GET,
                &format!("/cams/{SN}/color-settings"),
                b"",
                None,
            )
            .await
            .payload;
            (before, color)
        })
    };
    let (server, addr) = serve(state.path());
    runtime().block_on(async {
        let c = client();
        assert_eq!(
            send(&c, addr, Code::GET, &app_config, b"", None)
                .await
                .payload,
            first_doc
        );
        let color = send(
            &c,
            addr,
            Code::GET,
            &format!("/cams/{SN}/color-settings"),
            b"",
            None,
        )
        .await
        .payload;
        assert_eq!(color, color_doc);
    });

    // Stopped before the next one starts: one server to a state folder's log.
    drop(server);

    // A document broken on disk: the server starts, serves the defaults, and keeps the
    // broken file aside under a new name for a person to look at.
    let saved = state.path().join(SN).join("application-config.json");
    std::fs::write(&saved, b"{ broken").expect("break the saved document");
    let (_server, addr) = serve(state.path());
    runtime().block_on(async {
        let c = client();
        let r = send(&c, addr, Code::GET, &app_config, b"", None).await;
        assert_eq!(r.code, Code::CONTENT);
        assert_ne!(
            r.payload, first_doc,
            "the defaults, not the document before"
        );
        let color = format!("/cams/{SN}/color-settings");
        assert_eq!(
            send(&c, addr, Code::GET, &color, b"", None).await.payload,
            color_doc
        );
    });
    let aside: Vec<_> = std::fs::read_dir(state.path().join(SN))
        .expect("the camera's state directory")
        .filter_map(Result::ok)
        .filter(|e| {
            e.file_name()
                .to_string_lossy()
                .starts_with("application-config.json.corrupt-")
        })
        .collect();
    assert_eq!(aside.len(), 1, "one document set aside");
    assert_eq!(std::fs::read(aside[0].path()).expect("kept"), b"{ broken");
    assert!(!saved.exists(), "nothing in its place until a PUT");
}

#[test]
fn packet_sizes_and_block2_grab_once() {
    let state = TempDir::new("cams-sizes");
    let (_server, addr) = serve(state.path());
    runtime().block_on(async {
        let c = client();
        let color = format!("/cams/{SN}/color");
        let r = send(
            &c,
            addr,
            Code::PUT,
            &format!("/cams/{SN}/color-settings"),
            COLOR_640.as_bytes(),
            None,
        )
        .await;
        assert_eq!(r.code, Code::CHANGED);
        let mut post = Request::new(Code::POST, &color);
        post.block_szx = Some(4);
        post.timeout = Some(LIMIT);
        let grabbed = c.send(addr, post).await.expect("POST color");
        assert_eq!(grabbed.payload.len(), 921_610);
        assert_eq!(&grabbed.payload[..6], &[1, 0x02, 0x80, 0x01, 0xe0, 3]);
        // The continuations came from the stored answer: the latest frame is that grab.
        let latest = send(&c, addr, Code::GET, &color, b"", None).await;
        assert_eq!(latest.options.etag(), grabbed.options.etag());
        assert_eq!(latest.payload, grabbed.payload);

        let cloud = send(
            &c,
            addr,
            Code::POST,
            &format!("/cams/{SN}/pointcloud"),
            b"",
            None,
        )
        .await;
        let n = u32::from_be_bytes([
            cloud.payload[4],
            cloud.payload[5],
            cloud.payload[6],
            cloud.payload[7],
        ]);
        assert!(n > 0);
        assert_eq!(cloud.payload.len(), 12 + 12 * n as usize);
        let all = send(&c, addr, Code::POST, "/cams/pointclouds", b"", None).await;
        let m = u32::from_be_bytes([
            all.payload[4],
            all.payload[5],
            all.payload[6],
            all.payload[7],
        ]);
        assert_eq!(all.payload.len(), 12 + 12 * m as usize);
        assert!(m > 0);

        let depth = send(
            &c,
            addr,
            Code::POST,
            &format!("/cams/{SN}/depth"),
            b"",
            None,
        )
        .await;
        assert_eq!(depth.payload.len(), 14 + 1280 * 720 * 2);
    });
}

/// Two calibrated, noise-free cameras looking at one box from opposite sides.
const TWO_CAMERAS: &str = r#"
seed = 3
[floor]
z = 0.0
color = [120, 120, 120]

[[camera]]
serial = "111111111111"
position = [0.6, 0.0, 1.0]
look_at = [0.0, 0.0, 0.0]
noise = "ideal"
calibrated = true

[[camera]]
serial = "222222222222"
position = [-0.6, 0.0, 1.0]
look_at = [0.0, 0.0, 0.0]
noise = "ideal"
calibrated = true

[[box]]
size = [0.40, 0.30, 0.20]
center = [0.0, 0.0]
yaw_deg = 15.0
color = [180, 140, 90]
"#;

fn point_count(packet: &[u8]) -> usize {
    assert_eq!(packet.get(..2), Some(&[3u8, 12][..]), "point-cloud header");
    let n = u32::from_be_bytes([packet[4], packet[5], packet[6], packet[7]]) as usize;
    assert_eq!(packet.len(), 12 + 12 * n);
    n
}

#[test]
fn pointclouds_merges_every_camera_of_a_scene_and_notifies_observers() {
    let state = TempDir::new("cams-scene");
    let scene = state.path().join("two.toml");
    std::fs::write(&scene, TWO_CAMERAS).expect("scene file");
    let (_server, addr) = serve_with(state.path(), &["--scene", &scene.to_string_lossy()]);
    runtime().block_on(async {
        let c = client();
        let mut single = 0;
        for sn in ["111111111111", "222222222222"] {
            let put = send(
                &c,
                addr,
                Code::PUT,
                &format!("/cams/{sn}/depth-settings"),
                DEPTH_640.as_bytes(),
                None,
            )
            .await;
            assert_eq!(put.code, Code::CHANGED);
            let cloud = send(
                &c,
                addr,
                Code::POST,
                &format!("/cams/{sn}/pointcloud"),
                b"",
                None,
            )
            .await;
            let n = point_count(&cloud.payload);
            assert!(n > 0, "camera {sn} sees nothing");
            single += n;
        }
        let all = send(&c, addr, Code::POST, "/cams/pointclouds", b"", None).await;
        assert_eq!(all.code, Code::CONTENT);
        assert_eq!(point_count(&all.payload), single);

        // ICP on the second camera registers its cloud; it keeps every point.
        let path = "/cams/222222222222/application-config";
        let doc = send(&c, addr, Code::GET, path, b"", None).await.payload;
        let text = String::from_utf8_lossy(&doc).replace("\"icp\": 0", "\"icp\": 1");
        assert_eq!(
            send(&c, addr, Code::PUT, path, text.as_bytes(), None)
                .await
                .code,
            Code::CHANGED
        );
        let registered = send(&c, addr, Code::POST, "/cams/pointclouds", b"", None).await;
        assert_eq!(point_count(&registered.payload), single);

        // An observer of a grab resource hears of each new grab (a 4.04 before the first
        // grab would end the observation, RFC 7641 §3.2).
        let depth = "/cams/111111111111/depth";
        let before = send(&c, addr, Code::POST, depth, b"", None).await;
        let mut register = Request::new(Code::GET, depth);
        register.timeout = Some(LIMIT);
        let mut observation = c.observe(addr, register).await.expect("observe");
        match tokio::time::timeout(LIMIT, observation.next()).await {
            Ok(Some(Ok(r))) => assert_eq!(r.options.etag(), before.options.etag()),
            other => panic!("no first observe response: {other:?}"),
        }
        let grabbed = send(&c, addr, Code::POST, depth, b"", None).await;
        assert_eq!(grabbed.payload.len(), 14 + 640 * 480 * 2);
        let note = tokio::time::timeout(LIMIT, observation.next()).await;
        match note {
            Ok(Some(Ok(r))) => assert_eq!(r.options.etag(), grabbed.options.etag()),
            other => panic!("no notification after a grab: {other:?}"),
        }
    });
}

#[test]
fn a_camera_named_otherwise_than_a_d400_is_served_under_its_name() {
    let state = TempDir::new("cams-named");
    let scene = state.join("scene.toml");
    std::fs::write(&scene, crate::group::box_scene("rec-01", [0.0, 0.0, 1.0]))
        .expect("writing the scene");
    let scene = scene.to_str().expect("UTF-8 path").to_owned();
    let states = state.join("state");
    let app_config = "/cams/rec-01/application-config";
    let custom = r#"{"roi2d": {"px": 10, "py": 20, "width": 300, "height": 200},
        "roi3d": {"min_x": -0.5, "max_x": 0.5, "min_y": -0.5, "max_y": 0.5, "min_z": -0.1, "max_z": 0.5},
        "depth_grab_timeout_ms": 5000, "color_grab_timeout_ms": 4000, "icp": 0,
        "postprocessing": {"decimation": 1, "spatial": 1, "holefilling": 0}}"#;
    let first_doc = {
        let (_server, addr) = serve_with(&states, &["--scene", &scene]);
        runtime().block_on(async {
            let c = client();
            let links = send(&c, addr, Code::GET, "/.well-known/core", b"", None).await;
            let links = String::from_utf8_lossy(&links.payload).into_owned();
            for name in ["color", "depth", "pointcloud", "application-config"] {
                assert!(links.contains(&format!("</cams/rec-01/{name}>")), "{links}");
            }
            let put = |path: &'static str, body: &'static str| {
                let c = &c;
                async move { send(c, addr, Code::PUT, path, body.as_bytes(), None).await }
            };
            assert_eq!(
                put("/cams/rec-01/color-settings", COLOR_640).await.code,
                Code::CHANGED
            );
            assert_eq!(
                put("/cams/rec-01/depth-settings", DEPTH_640).await.code,
                Code::CHANGED
            );
            assert_eq!(put(app_config, custom).await.code, Code::CHANGED);
            for name in ["color", "depth", "pointcloud"] {
                let path = format!("/cams/rec-01/{name}");
                let r = send(&c, addr, Code::POST, &path, b"", None).await;
                assert_eq!(r.code, Code::CONTENT, "POST {path}");
            }
            // The creation resources take the name as they take a D400's serial.
            let r = send(&c, addr, Code::DELETE, "/cams/rec-01/color", b"", None).await;
            assert_eq!(r.code, Code::DELETED);
            let r = send(&c, addr, Code::POST, "/cams/color", b"rec-01", None).await;
            assert_eq!(r.code, Code::CREATED);
            let location: Vec<&[u8]> = r.options.values(OptionNumber::LOCATION_PATH).collect();
            assert_eq!(location, [b"cams".as_slice(), b"rec-01", b"color"]);
            let r = send(&c, addr, Code::POST, "/cams/color", b"rec/01", None).await;
            assert_eq!(r.code, Code::BAD_REQUEST);
            send(&c, addr, Code::GET, app_config, b"", None)
                .await
                .payload
        })
    };
    let saved = states.join("rec-01").join("application-config.json");
    assert!(saved.is_file(), "kept under the camera's name");
    // Persisted under its name, and named so by the client's flags and outputs.
    let (_server, addr) = serve_with(&states, &["--scene", &scene]);
    runtime().block_on(async {
        let c = client();
        let doc = send(&c, addr, Code::GET, app_config, b"", None).await;
        assert_eq!(doc.payload, first_doc);
        let r = send(&c, addr, Code::DELETE, app_config, b"", None).await;
        assert_eq!(r.code, Code::DELETED);
    });
    let uri = format!("coap://{addr}");
    let png = state.join("color.png");
    let png = png.to_str().expect("UTF-8 path");
    crate::support::Proc::run(
        crate::support::COAPCAM,
        &[
            "grab", "color", "--server", &uri, "--camera", "rec-01", "-o", png,
        ],
        LIMIT,
    )
    .expect_success("grab color --camera rec-01");
    assert!(std::fs::metadata(png).is_ok_and(|m| m.len() > 0));
    let m = crate::support::Proc::run(
        crate::support::COAPCAM,
        &["measure", "--server", &uri, "--camera", "rec-01", "--json"],
        LIMIT,
    )
    .expect_success("measure --camera rec-01")
    .json();
    assert_eq!(m["cameras"], serde_json::json!(["rec-01"]), "{m}");
}
