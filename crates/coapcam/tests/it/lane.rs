//! `serve --auto-measure` on scenes with a timeline: parcels slid onto the table, left
//! standing, moved and taken away, measured by the station by itself. Each test plays
//! a scene of some 20 seconds and then reads the station's records (`coapcam results
//! --server --json`), checking them against the timeline: how many, how close to the
//! truth, and that every frame measured was captured while its parcel stood still.

use std::io::{BufRead as _, BufReader};
use std::net::SocketAddr;
use std::process::{Child, Command, Stdio};
use std::sync::{Arc, Mutex, MutexGuard, PoisonError};
use std::thread;
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use coapcam::api::record::{Record, Trigger};
use rgbd::Scene;
use rgbd::scene::SceneBox;

use crate::support::{COAPCAM, Proc, TempDir};

/// One lane at a time: each renders and measures continuously, and three at once on a
/// busy 2-core machine would slow the measurements past the time a parcel stands.
static ONE_AT_A_TIME: Mutex<()> = Mutex::new(());

/// One calibrated D415 1.1 m above the table, looking down.
pub(crate) const ONE_CAMERA: &str = r#"
seed = 5
[[camera]]
serial = "840412060746"
position = [0.0, 0.0, 1.1]
look_at = [0.0, 0.0, 0.0]
up = [0.0, 1.0, 0.0]
"#;

/// The two calibrated D415s of the demo scene, from opposite sides.
const TWO_CAMERAS: &str = r#"
seed = 7
[[camera]]
serial = "840412060746"
position = [0.45, -0.25, 1.0]
look_at = [0.0, 0.0, 0.1]

[[camera]]
serial = "840412060757"
position = [-0.40, 0.30, 1.2]
look_at = [0.0, 0.0, 0.1]
"#;

/// How long each parcel stands still: a measurement (grabs, codes, photo, annotated
/// picture) in a debug build on a busy 2-core machine takes 3 to 5 s (8 s seen while the
/// machine also compiled), and one still running when its parcel is taken away is not
/// recorded.
pub(crate) const STILL_S: f64 = 16.0;

/// A parcel `size` (metres) yawed `yaw`, slid from `from` to `center` between `appear`
/// and `appear + 1`, standing still for [`STILL_S`], then taken away.
pub(crate) fn parcel(
    size: [f64; 3],
    yaw: f64,
    center: [f64; 2],
    from: [f64; 2],
    appear: f64,
) -> String {
    let label = format!("{{ kind = \"qr\", text = \"PKG-{appear}\", size = 0.08 }}");
    labelled(size, yaw, center, from, appear, &label)
}

/// As [`parcel`], with `label` (a scene file's inline table).
pub(crate) fn labelled(
    size: [f64; 3],
    yaw: f64,
    center: [f64; 2],
    from: [f64; 2],
    appear: f64,
    label: &str,
) -> String {
    format!(
        "[[box]]\nsize = {size:?}\ncenter = {center:?}\nyaw_deg = {yaw}\nappear_s = {appear}\n\
         from = {from:?}\nstill_s = {}\nremove_s = {}\nlabel = {label}\n",
        appear + 1.0,
        appear + 1.0 + STILL_S,
    )
}

/// A station playing `scene` with `--auto-measure`; the times around its start bound
/// when its scene time began (the cameras are made before it says it serves). Its log
/// lines are kept for the failure messages.
pub(crate) struct Lane {
    server: Child,
    log: Arc<Mutex<Vec<String>>>,
    _turn: MutexGuard<'static, ()>,
    pub(crate) addr: SocketAddr,
    pub(crate) scene: Scene,
    results: std::path::PathBuf,
    started_after_us: u64,
    started_before_us: u64,
}

fn unix_us() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| d.as_micros() as u64)
}

impl Lane {
    fn start(dir: &TempDir, scene_text: &str) -> Self {
        Self::start_with(dir, scene_text, &[])
    }

    /// As [`Lane::start`], with more `serve` flags.
    pub(crate) fn start_with(dir: &TempDir, scene_text: &str, extra: &[&str]) -> Self {
        let scene = Scene::from_toml(scene_text).expect("the test's scene");
        let path = dir.join("lane.toml");
        std::fs::write(&path, scene_text).expect("writing the scene");
        let results = dir.join("results.sqlite");
        let state = dir.join("state");
        let turn = ONE_AT_A_TIME.lock().unwrap_or_else(PoisonError::into_inner);
        let started_after_us = unix_us();
        let mut server = Command::new(COAPCAM)
            .args([
                "serve",
                "--bind",
                "127.0.0.1:0",
                "--duration",
                "120",
                "--scene",
            ])
            .arg(&path)
            .arg("--state-dir")
            .arg(&state)
            .arg("--results")
            .arg(&results)
            .args(["--auto-measure", "--station-name", "lane-1"])
            .args(extra)
            .env("RUST_LOG", "coapcam::station=info")
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(Stdio::piped())
            .spawn()
            .expect("starting coapcam serve");
        let stderr = server.stderr.take().expect("stderr pipe");
        // The server stops by itself after --duration, which bounds this read.
        let mut lines = BufReader::new(stderr).lines().map_while(Result::ok);
        let mut before = Vec::new();
        let addr = lines
            .by_ref()
            .find_map(|l| {
                let addr = l
                    .strip_prefix("coapcam: serving on ")
                    .and_then(|a| a.trim().parse().ok());
                before.push(l);
                addr
            })
            .expect("coapcam serve printed no address");
        let started_before_us = unix_us();
        let log = Arc::new(Mutex::new(before));
        let keep = Arc::clone(&log);
        thread::spawn(move || {
            for line in lines {
                keep.lock()
                    .unwrap_or_else(PoisonError::into_inner)
                    .push(line);
            }
        });
        Self {
            server,
            log,
            _turn: turn,
            addr,
            scene,
            results,
            started_after_us,
            started_before_us,
        }
    }

    /// What the station logged so far.
    pub(crate) fn log(&self) -> String {
        self.log
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .join("\n")
    }

    /// The scene's last moment: when its last object is taken away.
    fn end_s(&self) -> f64 {
        self.scene
            .boxes
            .iter()
            .filter_map(|b| b.timeline.remove_s)
            .fold(0.0, f64::max)
    }

    /// Waits until the scene has played out (and a second more), then lists the records.
    pub(crate) fn records_after_the_scene(&self) -> Vec<Record> {
        let end_us = self.started_before_us + ((self.end_s() + 1.0) * 1e6) as u64;
        let now = unix_us();
        if end_us > now {
            thread::sleep(Duration::from_micros(end_us - now));
        }
        let server = format!("coap://{}", self.addr);
        let out = Proc::run(
            COAPCAM,
            &["results", "--server", &server, "--json"],
            Duration::from_secs(60),
        )
        .expect_success("coapcam results");
        // The listing holds the events too (a camera's application-config PUT): their
        // lines carry `event`.
        let mut records: Vec<Record> = out
            .stdout_text()
            .lines()
            .map(|l| serde_json::from_str::<serde_json::Value>(l).expect("a JSON line"))
            .filter(|line| line.get("event").is_none())
            .map(|line| serde_json::from_value(line).expect("a record"))
            .collect();
        records.sort_by_key(|r| r.id);
        records
    }

    /// Checks that `record` measured `b` standing still: within 5 mm of its size, its
    /// footprint centred where it stood still, every frame captured (whatever the exact
    /// start of the scene's time within the start-up) between `still_s` and `remove_s`.
    pub(crate) fn check(&self, record: &Record, b: &SceneBox) {
        assert_eq!(record.trigger, Trigger::Auto);
        assert_eq!(record.station, "lane-1");
        let r = record.measurement.reported().expect("a measured parcel");
        let [l, w] = if b.size[0] >= b.size[1] {
            [b.size[0], b.size[1]]
        } else {
            [b.size[1], b.size[0]]
        };
        for (got, want, what) in [
            (r.length_mm, l * 1e3, "length"),
            (r.width_mm, w * 1e3, "width"),
            (r.height_mm, b.size[2] * 1e3, "height"),
        ] {
            assert!(
                (got - want).abs() <= 5.0,
                "record {}: {what} {got} mm, truth {want} mm\n{}",
                record.id,
                self.log()
            );
        }
        let centre = [0, 1].map(|k| r.corners_m.iter().map(|c| c[k]).sum::<f64>() / 4.0);
        let off = ((centre[0] - b.center[0]).powi(2) + (centre[1] - b.center[1]).powi(2)).sqrt();
        assert!(
            off < 0.005,
            "record {}: footprint centred {centre:?}, the parcel stood at {:?}\n{}",
            record.id,
            b.center,
            self.log()
        );
        let (still, remove) = (b.timeline.still(), b.timeline.remove_s.expect("removed"));
        assert!(!record.measurement.frames_unix_us.is_empty());
        for &frame_us in &record.measurement.frames_unix_us {
            // Scene time of the frame: between these two, as scene time 0 was between
            // the two start times.
            let earliest = frame_us.saturating_sub(self.started_before_us) as f64 / 1e6;
            let latest = frame_us.saturating_sub(self.started_after_us) as f64 / 1e6;
            assert!(
                earliest >= still && latest < remove,
                "record {}: a frame at scene time {earliest:.2}..{latest:.2} s, the parcel stood still {still}..{remove} s\n{}",
                record.id,
                self.log()
            );
        }
        assert!(record.has_photo && record.photo_sha256.is_some(), "a photo");
        assert!(record.has_annotated, "an annotated picture");
    }

    /// `results verify` passes on the log.
    pub(crate) fn verify(&self) {
        Proc::run(
            COAPCAM,
            &["results", "verify", &self.results.to_string_lossy()],
            Duration::from_secs(60),
        )
        .expect_success("coapcam results verify");
    }

    /// Where the station keeps its results log.
    pub(crate) fn results(&self) -> &std::path::Path {
        &self.results
    }

    /// Stops the station as Ctrl-C does and waits for it to end (bounded): its exit
    /// status.
    pub(crate) fn interrupt(&mut self) -> std::process::ExitStatus {
        let pid = self.server.id().to_string();
        let sent = Command::new("kill").args(["-INT", &pid]).status();
        assert!(sent.is_ok_and(|s| s.success()), "kill -INT {pid}");
        let deadline = Instant::now() + Duration::from_secs(60);
        loop {
            if let Some(status) = self.server.try_wait().expect("waiting for the station") {
                return status;
            }
            assert!(
                Instant::now() < deadline,
                "the station still ran 60 s after SIGINT\n{}",
                self.log()
            );
            thread::sleep(Duration::from_millis(50));
        }
    }

    /// Checks that there are `n` records, with the station's log if not.
    pub(crate) fn expect_count(&self, records: &[Record], n: usize) {
        assert_eq!(
            records.len(),
            n,
            "records: {records:#?}\nthe station's log:\n{}",
            self.log()
        );
    }
}

impl Drop for Lane {
    fn drop(&mut self) {
        let _ = self.server.kill();
        let _ = self.server.wait();
    }
}

#[test]
fn two_parcels_placed_one_after_the_other_are_measured_once_each_and_never_while_moving() {
    let dir = TempDir::new("lane-two");
    let scene = format!(
        "{ONE_CAMERA}{}{}",
        parcel([0.40, 0.30, 0.20], 15.0, [0.0, 0.0], [0.45, 0.0], 2.0),
        parcel(
            [0.32, 0.22, 0.12],
            -20.0,
            [0.02, -0.03],
            [0.0, -0.45],
            4.0 + STILL_S
        ),
    );
    let lane = Lane::start(&dir, &scene);
    let records = lane.records_after_the_scene();
    lane.expect_count(&records, 2);
    lane.check(&records[0], &lane.scene.boxes[0]);
    lane.check(&records[1], &lane.scene.boxes[1]);
    lane.verify();
}

/// scenes/lane.toml's parcels and labels on its timeline's pattern: the second parcel's
/// Code 128 of 18 characters, 20 cm long, has modules of 0.79 mm, under one pixel of a
/// 1280x720 color image 1.1 m above the table. The station reads it with no command
/// given first: it set the color stream the codes need at start, and said so.
#[test]
fn the_lane_scenes_labels_are_read_with_no_extra_command() {
    let dir = TempDir::new("lane-codes");
    let code128 = "1Z999AA10123456784";
    let scene = format!(
        "{ONE_CAMERA}{}{}",
        labelled(
            [0.40, 0.30, 0.20],
            15.0,
            [0.0, 0.0],
            [0.45, 0.0],
            2.0,
            r#"{ kind = "qr", text = "PKG-0001", size = 0.08 }"#
        ),
        labelled(
            [0.32, 0.22, 0.12],
            -20.0,
            [0.02, -0.03],
            [0.0, -0.45],
            4.0 + STILL_S,
            &format!(r#"{{ kind = "code128", text = "{code128}", size = 0.20 }}"#)
        ),
    );
    let lane = Lane::start(&dir, &scene);
    let records = lane.records_after_the_scene();
    lane.expect_count(&records, 2);
    for (record, (kind, text)) in records
        .iter()
        .zip([("qr", "PKG-0001"), ("code128", code128)])
    {
        let read: Vec<(&str, &str)> = record
            .measurement
            .codes
            .iter()
            .flatten()
            .map(|c| (c.code.kind.name(), c.code.text.as_str()))
            .collect();
        assert_eq!(
            read,
            [(kind, text)],
            "record {}\nthe station's log:\n{}",
            record.id,
            lane.log()
        );
    }
    let log = lane.log();
    assert!(
        log.contains("camera 840412060746: codes read at color 1920x1080 (set from 1280x720)"),
        "{log}"
    );
}

#[test]
fn a_parcel_moved_to_a_new_place_on_the_table_is_measured_again_there() {
    let dir = TempDir::new("lane-moved");
    // The parcel stands at (-0.1, 0) from 3 s; at 3 s + STILL_S it is pushed to
    // (0.12, 0.05) (the second box takes the first's place and slides), still there a
    // second later.
    let first = parcel([0.30, 0.25, 0.18], 10.0, [-0.1, 0.0], [-0.5, 0.0], 2.0);
    let moved = parcel(
        [0.30, 0.25, 0.18],
        10.0,
        [0.12, 0.05],
        [-0.1, 0.0],
        3.0 + STILL_S,
    );
    let scene = format!("{ONE_CAMERA}{first}{moved}");
    let lane = Lane::start(&dir, &scene);
    let records = lane.records_after_the_scene();
    lane.expect_count(&records, 2);
    lane.check(&records[0], &lane.scene.boxes[0]);
    lane.check(&records[1], &lane.scene.boxes[1]);
}

#[test]
fn a_parcel_seen_by_two_cameras_is_measured_once_with_both() {
    let dir = TempDir::new("lane-two-cameras");
    let scene = format!(
        "{TWO_CAMERAS}{}",
        parcel([0.36, 0.26, 0.16], 25.0, [0.0, 0.02], [0.0, 0.5], 2.0)
    );
    let lane = Lane::start(&dir, &scene);
    let records = lane.records_after_the_scene();
    lane.expect_count(&records, 1);
    lane.check(&records[0], &lane.scene.boxes[0]);
    let serials: Vec<&str> = records[0]
        .cameras
        .iter()
        .map(|c| c.serial.as_str())
        .collect();
    assert_eq!(serials, ["840412060746", "840412060757"]);
    assert_eq!(records[0].measurement.cameras.len(), 2);
}

#[test]
fn a_hand_that_reaches_in_beside_a_measured_parcel_makes_no_new_measurement() {
    let dir = TempDir::new("lane-hand");
    // The parcel stands from 3 s to 27 s; at 18 s a hand (a cylinder 30 cm tall) slides
    // in beside it, rests half a second and is gone at 19 s: less than the still time
    // (600 ms) however slow the looks, as the station times them by their frames.
    let mut scene = format!(
        "{ONE_CAMERA}{}",
        parcel([0.34, 0.24, 0.15], 5.0, [-0.05, 0.0], [-0.5, 0.0], 2.0)
    );
    scene = scene.replace(&format!("remove_s = {}", 3.0 + STILL_S), "remove_s = 27");
    scene.push_str(
        "[[cylinder]]\nradius = 0.05\nheight = 0.30\ncenter = [0.2, 0.1]\nappear_s = 18.0\n\
         from = [0.5, 0.3]\nstill_s = 18.5\nremove_s = 19.0\n",
    );
    let lane = Lane::start(&dir, &scene);
    assert_eq!(lane.scene.boxes[0].timeline.remove_s, Some(27.0));
    let records = lane.records_after_the_scene();
    lane.expect_count(&records, 1);
    lane.check(&records[0], &lane.scene.boxes[0]);
    assert!(
        lane.log().contains("what stood on the table moved"),
        "the hand was seen:\n{}",
        lane.log()
    );
}
