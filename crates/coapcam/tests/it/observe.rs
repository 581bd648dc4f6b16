//! `monitor --observe` while other clients grab: a notification whose representation
//! changes while its blocks are fetched is fetched again, and the monitor goes on.

use std::time::Duration;

use crate::support::{COAPCAM, Proc, SN, TempDir, serve};

/// The case: `monitor color --observe --count 4` (the thesis packet, 2.7 MB in
/// 1 KiB blocks) while another client grabs a new frame every ~0.15 s, so most
/// notifications change before their last block arrives. Every result is printed and
/// the monitor ends with status 0, not with "representation changed during a
/// block-wise transfer".
#[test]
fn monitor_observe_goes_on_when_a_notification_changes_mid_transfer() {
    let state = TempDir::new("observe-changing");
    let (_server, addr) = serve(state.path());
    let uri = format!("coap://{addr}");
    let color = format!("{uri}/cams/{SN}/color");
    let grab = || {
        Proc::run(
            COAPCAM,
            &["post", &color, "-o", "/dev/null"],
            crate::support::LIMIT,
        )
    };
    grab().expect_success("the first grab");
    let mut monitor = Proc::spawn(
        COAPCAM,
        &[
            "monitor",
            "color",
            "--observe",
            "--server",
            &uri,
            "--count",
            "4",
            "--json",
        ],
    );
    let mut finished = None;
    for _ in 0..200 {
        grab().expect_success("a grab");
        std::thread::sleep(Duration::from_millis(100));
        finished = monitor.wait(Duration::ZERO);
        if finished.is_some() {
            break;
        }
    }
    let f = finished
        .unwrap_or_else(|| monitor.kill())
        .expect_success("monitor --observe");
    let lines = f.json_lines();
    let last = lines.last().expect("the statistics");
    assert_eq!(lines.len(), 5, "four results and the statistics");
    assert!(last["statistics"]["count"].as_u64() >= Some(1), "{last}");
}
