//! `coapcam serve --static DIR --writable`: clients change regular files and nothing else.

use std::os::unix::fs::symlink;

use coap::Code;

use crate::support::{TempDir, client, our_server, our_server_with, runtime, send};

#[test]
fn only_regular_files_are_replaced_or_removed() {
    let served = TempDir::new("files-regular");
    let outside = TempDir::new("files-outside");
    let dir = served.path();
    std::fs::write(dir.join("a.txt"), b"a").expect("a.txt");
    std::fs::create_dir(dir.join("sub")).expect("sub");
    std::fs::write(outside.path().join("target.txt"), b"kept").expect("target");
    symlink(outside.path().join("target.txt"), dir.join("link")).expect("symlink");
    let made = std::process::Command::new("mkfifo")
        .arg(dir.join("pipe"))
        .status()
        .expect("mkfifo runs");
    assert!(made.success());
    let (_server, addr) = our_server(dir, true);
    runtime().block_on(async {
        let c = client();
        for (method, name) in [
            (Code::DELETE, "sub"),
            (Code::PUT, "sub"),
            (Code::PUT, "link"),
            (Code::DELETE, "link"),
            (Code::PUT, "pipe"),
            (Code::DELETE, "pipe"),
        ] {
            let r = send(&c, addr, method, &format!("/files/{name}"), b"new", None).await;
            assert_eq!(r.code, Code::METHOD_NOT_ALLOWED, "{method:?} {name}");
            let text = String::from_utf8_lossy(&r.payload);
            assert!(text.contains("not a regular file"), "{text}");
            assert!(!text.contains("os error"), "no OS text: {text}");
        }
        // The longest name whose temporary file still fits 255 bytes, and one more.
        let longest = "x".repeat(200);
        let path = format!("/files/{longest}");
        assert_eq!(
            send(&c, addr, Code::PUT, &path, b"x", None).await.code,
            Code::CREATED
        );
        let r = send(
            &c,
            addr,
            Code::PUT,
            &format!("/files/{longest}y"),
            b"x",
            None,
        )
        .await;
        assert_eq!(r.code, Code::BAD_REQUEST);
        assert!(String::from_utf8_lossy(&r.payload).contains("200 bytes"));
        assert_eq!(
            send(&c, addr, Code::PUT, "/files/a.txt", b"b", None)
                .await
                .code,
            Code::CHANGED
        );
        assert_eq!(
            send(&c, addr, Code::DELETE, "/files/a.txt", b"", None)
                .await
                .code,
            Code::DELETED
        );
    });
    assert!(dir.join("sub").is_dir());
    assert!(
        dir.join("link")
            .symlink_metadata()
            .expect("link")
            .file_type()
            .is_symlink()
    );
    assert_eq!(
        std::fs::read(outside.path().join("target.txt")).expect("target"),
        b"kept"
    );
    assert!(dir.join("pipe").symlink_metadata().is_ok());
    assert!(!dir.join("a.txt").exists());
}

#[test]
fn writes_beyond_the_quota_answer_4_13_and_write_nothing() {
    let served = TempDir::new("files-quota");
    let dir = served.path();
    // Each file is charged its bytes in whole 4 KiB blocks and its link in discovery:
    // room for two small files.
    let (_server, addr) = our_server_with(dir, &["--writable", "--quota", "8400"]);
    runtime().block_on(async {
        let c = client();
        let put = |name: &str, n: usize| {
            let c = &c;
            let path = format!("/files/{name}");
            async move { send(c, addr, Code::PUT, &path, &vec![7; n], None).await }
        };
        assert_eq!(put("a.bin", 60).await.code, Code::CREATED);
        let r = put("b.bin", 4097).await;
        assert_eq!(r.code, Code::REQUEST_ENTITY_TOO_LARGE);
        assert!(String::from_utf8_lossy(&r.payload).contains("quota of 8400 bytes"));
        let r = send(&c, addr, Code::POST, "/files", &[7; 4097], None).await;
        assert_eq!(r.code, Code::REQUEST_ENTITY_TOO_LARGE);
        assert_eq!(put("b.bin", 40).await.code, Code::CREATED);
        // A third file, however small, is past the quota: it would take a block too.
        assert_eq!(put("c.bin", 1).await.code, Code::REQUEST_ENTITY_TOO_LARGE);
    });
    let mut names: Vec<String> = std::fs::read_dir(dir)
        .expect("the directory")
        .filter_map(|e| e.ok()?.file_name().into_string().ok())
        .collect();
    names.sort();
    assert_eq!(names, ["a.bin", "b.bin"], "nothing else written");
}
