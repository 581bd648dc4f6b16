//! Bad flags and values end every command with status 2 (usage) before it sends
//! anything: each invocation of a list is run against a UDP socket that counts what
//! arrives, and none may reach it. Then the small promises of how a command ends: an
//! error response names its request, a folder that does not exist fails before the grab,
//! `-o -` writes to standard output, SIGINT is said the same way everywhere, and a busy
//! address among several is named.

use std::net::UdpSocket;
use std::time::Duration;

use crate::support::{COAPCAM, Finished, LIMIT, Proc, SN, TempDir, serve, serve_with};

fn coapcam(args: &[&str]) -> Finished {
    Proc::run(COAPCAM, args, LIMIT)
}

/// A socket that never answers and counts the datagrams that reached it.
struct Counter(UdpSocket);

impl Counter {
    fn new() -> Self {
        let socket = UdpSocket::bind("127.0.0.1:0").expect("a socket");
        socket.set_nonblocking(true).expect("non-blocking");
        Self(socket)
    }

    fn uri(&self) -> String {
        format!("coap://{}", self.0.local_addr().expect("its address"))
    }

    /// The datagrams that arrived since the last call.
    fn count(&self) -> usize {
        let mut buf = [0u8; 2048];
        let mut n = 0;
        while self.0.recv(&mut buf).is_ok() {
            n += 1;
        }
        n
    }
}

#[test]
fn every_bad_flag_or_value_exits_2_before_anything_is_sent() {
    let dir = TempDir::new("usage");
    let counter = Counter::new();
    let s = counter.uri();
    let file = |name: &str| dir.join(name).to_str().expect("UTF-8 path").to_owned();
    let (png, jpg, txt) = (file("c.png"), file("c.jpg"), file("c.txt"));
    let (pdf, svg) = (file("m.pdf"), file("m.svg"));
    let no_cameras = file("no-cameras.toml");
    std::fs::write(&no_cameras, "# a scene without a [[camera]]\n").expect("a scene file");
    let x = format!("{s}/x");
    let cases: Vec<Vec<&str>> = vec![
        // URIs: another scheme, none, a port out of range, a broken percent-encoding.
        vec!["get", "http://127.0.0.1/x"],
        vec!["get", "127.0.0.1/x"],
        vec!["get", "coap://127.0.0.1:99999/x"],
        vec!["get", "coap://127.0.0.1/%ZZ"],
        vec!["grab", "color", "--server", "http://127.0.0.1", "-o", &png],
        vec!["measure", "--server", "127.0.0.1"],
        vec!["results", "--server", "coap://127.0.0.1:0"],
        vec!["discover", "coap://[::1"],
        // Times: negative, zero where it cannot be, not a number, too large.
        vec!["get", &x, "--timeout", "0"],
        vec!["get", &x, "--timeout=-1"],
        vec!["get", &x, "--timeout", "nan"],
        vec!["get", &x, "--timeout", "1e300"],
        vec!["discover", &s, "--wait=-1"],
        vec!["monitor", "color", "--server", &s, "--interval=-1"],
        vec!["monitor", "color", "--server", &s, "--interval", "0"],
        vec!["measure", "--group", "224.0.1.187", "--wait=-1"],
        vec!["bench", "load", "--server", &s, "--duration=-1"],
        vec!["serve", "--bind", "127.0.0.1:0", "--duration=-1"],
        vec!["serve", "--bind", "127.0.0.1:0", "--grab-memory", "0"],
        vec!["serve", "--bind", "127.0.0.1:0", "--scene", &no_cameras],
        vec![
            "netem",
            "--listen",
            "127.0.0.1:0",
            "--forward",
            "127.0.0.1:9",
            "--duration=-1",
        ],
        // A method that cannot observe.
        vec!["post", &x, "--observe", "1"],
        // grab: the file's extension and the stream, flags for other formats.
        vec!["grab", "color", "--server", &s, "-o", &txt],
        vec!["grab", "depth", "--server", &s, "-o", &jpg],
        vec!["grab", "color", "--server", &s, "--all", "-o", &png],
        vec![
            "grab",
            "color",
            "--server",
            &s,
            "-o",
            &png,
            "--jpeg-quality",
            "80",
        ],
        vec!["grab", "color", "--server", &s, "-o", &png, "--view", &jpg],
        vec![
            "grab", "color", "--server", &s, "-o", &png, "--format", "png",
        ],
        vec![
            "grab", "depth", "--server", &s, "-o", "-", "--format", "jpg",
        ],
        // measure: the thresholds and billing the server would refuse, and more.
        vec!["measure", "--server", &s, "--min-height-mm=-10"],
        vec!["measure", "--server", &s, "--cluster-mm", "0"],
        vec!["measure", "--server", &s, "--cluster-mm", "nan"],
        vec![
            "measure",
            "--server",
            &s,
            "--cluster-mm",
            "0.001",
            "--clouds",
        ],
        vec!["measure", "--server", &s, "--round-up-mm", "1e9"],
        vec!["measure", "--server", &s, "--volumetric-divisor", "0"],
        vec!["measure", "--server", &s, "--annotate", &jpg],
        vec!["measure", "--server", &s, "--expect", "2"],
        vec!["measure", "--group", "127.0.0.1"],
        vec!["measure", "--group", "224.0.1.187", "--expect", "0"],
        vec!["monitor", "measure", "--server", &s, "--accept", "png"],
        vec!["monitor", "measure", "--server", &s, "--cluster-mm=-1"],
        // calibrate: the marker's size, family and id.
        vec!["calibrate", "--server", &s, "--marker-size=-0.16"],
        vec!["calibrate", "--server", &s, "--marker-size", "0"],
        vec!["calibrate", "--server", &s, "--family", "aruco"],
        vec!["calibrate", "--server", &s, "--origin-id", "9999"],
        vec!["calibrate", "--server", &s, "--view", &jpg],
        // A serial is letters, digits, '-' and '_', at most 32 of them.
        vec![
            "grab", "color", "--server", &s, "--camera", "rec/01", "-o", &png,
        ],
        vec!["measure", "--server", &s, "--camera", "rec.01"],
        vec![
            "measure",
            "--server",
            &s,
            "--camera",
            "a-serial-longer-than-thirty-two-characters",
        ],
        // bench.
        vec!["bench", "accuracy", "--scenes", "0"],
        // markers.
        vec!["markers", "--size", "0", "-o", &pdf],
        vec!["markers", "--size=-0.16", "-o", &pdf],
        vec!["markers", "--ids", "0-9999", "-o", &pdf],
        vec!["markers", "--ids", "3-1", "-o", &pdf],
        vec!["markers", "-o", &svg],
        // A map is of one page; four 16 cm markers take four.
        vec!["markers", "--size", "0.16", "-o", &pdf, "--map", &txt],
    ];
    let mut wrong = Vec::new();
    for args in &cases {
        let f = coapcam(args);
        let sent = counter.count();
        // Rust's own words for a failed conversion ("cannot convert float seconds to
        // Duration: value is negative") must never reach a user.
        let leaked = f.stderr.contains("Duration") || f.stderr.contains("float seconds");
        if f.status.code() != Some(2) || sent > 0 || leaked || f.stderr.trim().is_empty() {
            wrong.push(format!(
                "{args:?}: status {:?}, {sent} datagram(s) sent: {}",
                f.status.code(),
                f.stderr.trim()
            ));
        }
    }
    assert!(wrong.is_empty(), "not a usage error:\n{}", wrong.join("\n"));
}

#[test]
fn a_folder_that_does_not_exist_fails_before_the_grab() {
    let counter = Counter::new();
    let s = counter.uri();
    let missing = "/nonexistent/dir/c.png";
    for args in [
        vec!["grab", "color", "--server", &s, "-o", missing],
        vec![
            "grab", "color", "--server", &s, "-o", "-", "--view", missing,
        ],
        vec!["measure", "--server", &s, "--annotate", missing],
        vec!["calibrate", "--server", &s, "--view", missing],
    ] {
        let f = coapcam(&args);
        assert_eq!(f.status.code(), Some(1), "{args:?}: {}", f.stderr);
        assert!(f.stderr.contains(missing), "{args:?}: {}", f.stderr);
        assert_eq!(counter.count(), 0, "{args:?} sent: {}", f.stderr);
    }
}

/// Issue 51, item 13: a missing `calibrate --map` file is named as the marker map, not
/// as a scene file (it said "cannot read scene file"), before anything is sent; `bench
/// accuracy --help` says each set's default number of scenes in words that parse, and
/// its first line names every set, not the boxes alone.
#[test]
fn small_messages_say_what_they_mean() {
    let counter = Counter::new();
    let s = counter.uri();
    let missing = "/nonexistent/nope.toml";
    let f = coapcam(&["calibrate", "--server", &s, "--map", missing]);
    assert_eq!(f.status.code(), Some(1), "{}", f.stderr);
    assert!(
        f.stderr
            .contains(&format!("--map {missing}: cannot read the marker map: ")),
        "{}",
        f.stderr
    );
    assert!(!f.stderr.contains("scene file"), "{}", f.stderr);
    assert_eq!(counter.count(), 0, "sent: {}", f.stderr);
    let help = coapcam(&["bench", "accuracy", "--help"]).stdout_text();
    let about = help.lines().next().unwrap_or_default();
    for named in [
        "--set",
        "plain boxes",
        "the lane set",
        "the certification set",
    ] {
        assert!(about.contains(named), "{named:?} is not in {about:?}");
    }
    let scenes = help
        .lines()
        .find(|l| l.trim_start().starts_with("--scenes"))
        .unwrap_or_else(|| panic!("no --scenes line: {help}"));
    assert!(
        scenes.contains(
            "by default 40 for `boxes`, every scene of the lane set for `lane`, 500 for `cert`"
        ),
        "{scenes}"
    );
}

#[test]
fn grab_writes_to_standard_output_and_errors_name_their_request() {
    let state = TempDir::new("usage-stdout");
    let (_server, addr) = serve(state.path());
    let uri = format!("coap://{addr}");
    let f = coapcam(&[
        "grab", "color", "--server", &uri, "-o", "-", "--format", "png",
    ]);
    assert_eq!(f.status.code(), Some(0), "{}", f.stderr);
    assert!(f.stdout.starts_with(b"\x89PNG\r\n"), "not a PNG on stdout");
    // Without --format: the thesis packet, 1280 x 720 x 3 bytes and a header.
    let f = coapcam(&["grab", "color", "--server", &uri, "-o", "-"]);
    assert_eq!(f.status.code(), Some(0), "{}", f.stderr);
    assert!(f.stdout.len() > 1280 * 720 * 3, "{} bytes", f.stdout.len());
    // An error response names the method and the path.
    let f = coapcam(&["get", &format!("{uri}/cams/999999999999/color-settings")]);
    assert_eq!(f.status.code(), Some(3), "{}", f.stderr);
    assert!(
        f.stderr
            .contains("coapcam: GET /cams/999999999999/color-settings: 4.04 Not Found"),
        "{}",
        f.stderr
    );
    // An unknown serial is a refusal (3) with markers as with --floor.
    for method in [&[][..], &["--floor"][..]] {
        let mut args = vec!["calibrate", "--server", &uri, "--camera", "999999999999"];
        args.extend_from_slice(method);
        let f = coapcam(&args);
        assert_eq!(f.status.code(), Some(3), "{args:?}: {}", f.stderr);
        assert!(f.stderr.contains("4.04"), "{args:?}: {}", f.stderr);
    }
}

#[test]
fn annotate_says_when_there_is_nothing_to_draw() {
    let state = TempDir::new("usage-annotate");
    let scene = state.join("empty.toml");
    std::fs::write(
        &scene,
        format!(
            "[[camera]]\nserial = \"{SN}\"\nposition = [0.0, 0.0, 1.0]\nlook_at = [0.0, 0.0, 0.0]\ncalibrated = true\n"
        ),
    )
    .expect("a scene file");
    let (_server, addr) = serve_with(state.path(), &["--scene", scene.to_str().expect("UTF-8")]);
    let picture = state.join("a.png");
    let f = coapcam(&[
        "measure",
        "--server",
        &format!("coap://{addr}"),
        "--annotate",
        picture.to_str().expect("UTF-8"),
    ]);
    assert_eq!(f.status.code(), Some(5), "{}", f.stderr);
    assert!(f.stderr.contains("not written"), "{}", f.stderr);
    assert!(!picture.exists());
}

/// Starts `args` against a socket that never answers, waits until its first datagram
/// arrived (the command is waiting for the answer), and interrupts it.
fn interrupted(counter: &Counter, args: &[&str]) -> Finished {
    let mut p = Proc::spawn(COAPCAM, args);
    let deadline = std::time::Instant::now() + LIMIT;
    while counter.count() == 0 {
        assert!(
            std::time::Instant::now() < deadline,
            "{args:?} sent nothing"
        );
        std::thread::sleep(Duration::from_millis(20));
    }
    p.interrupt()
}

#[test]
fn sigint_ends_every_command_with_130_and_says_so() {
    let dir = TempDir::new("usage-signal");
    let counter = Counter::new();
    let s = counter.uri();
    let png = dir.join("c.png");
    let png = png.to_str().expect("UTF-8");
    let x = format!("{s}/x");
    for args in [
        vec!["get", &x],
        vec!["grab", "color", "--server", &s, "-o", png],
        vec!["measure", "--server", &s],
        vec!["calibrate", "--server", &s],
        vec!["monitor", "color", "--server", &s],
    ] {
        let f = interrupted(&counter, &args);
        assert_eq!(f.status.code(), Some(130), "{args:?}: {}", f.stderr);
        assert!(
            f.stderr.contains("interrupted by signal 2"),
            "{args:?}: {}",
            f.stderr
        );
    }
    let left: Vec<_> = std::fs::read_dir(dir.path())
        .expect("the folder")
        .map(|e| e.expect("an entry").file_name())
        .collect();
    assert!(left.is_empty(), "left behind: {left:?}");
}

#[test]
fn a_busy_address_among_several_is_named() {
    let taken = UdpSocket::bind("127.0.0.1:0").expect("a socket");
    let busy = taken.local_addr().expect("its address").to_string();
    let f = coapcam(&[
        "serve",
        "--no-cameras",
        "--bind",
        &busy,
        "--bind",
        "127.0.0.1:0",
        "--duration",
        "30",
    ]);
    assert_eq!(f.status.code(), Some(1), "{}", f.stderr);
    assert!(f.stderr.contains(&format!("{busy}: ")), "{}", f.stderr);
    assert!(f.stderr.contains("in use"), "{}", f.stderr);
}

/// docs/usage.md's `monitor color` example: the command as written, against a server
/// here, prints results of the size the page shows.
#[test]
fn the_monitor_example_of_usage_md_prints_the_size_it_shows() {
    const USAGE: &str = include_str!("../../../../docs/usage.md");
    let command = USAGE
        .lines()
        .find(|l| l.contains("coapcam monitor color"))
        .expect("usage.md's monitor example");
    let shown = USAGE
        .lines()
        .find(|l| l.starts_with("#1 "))
        .and_then(|l| l.split_whitespace().nth(3))
        .expect("the example's first result line")
        .replace(',', "");
    let state = TempDir::new("usage-monitor");
    let (_server, addr) = serve(state.path());
    let mut args: Vec<String> = command
        .split_whitespace()
        .skip_while(|w| !w.ends_with("coapcam"))
        .skip(1)
        .map(|w| w.replace("coap://127.0.0.1", &format!("coap://{addr}")))
        .collect();
    // Two results, at once, are enough to see their size.
    let count = args.iter().position(|a| a == "--count").expect("--count") + 1;
    args[count] = "2".into();
    args.extend(["--interval".into(), "0".into()]);
    let args: Vec<&str> = args.iter().map(String::as_str).collect();
    let f = coapcam(&args);
    assert_eq!(f.status.code(), Some(0), "{args:?}: {}", f.stderr);
    let out = f.stdout_text();
    let first = out
        .lines()
        .find(|l| l.starts_with("#1 "))
        .and_then(|l| l.split_whitespace().nth(3))
        .expect("a result line")
        .replace(',', "");
    assert_eq!(
        first, shown,
        "usage.md shows {shown} B per result, its command prints {first} B:\n{out}"
    );
}
