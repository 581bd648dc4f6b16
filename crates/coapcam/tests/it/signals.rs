//! `coapcam serve` stops cleanly on SIGTERM and SIGINT: exit status 0, well before the
//! `--duration` (120 s) that would stop it otherwise.

use std::process::Command;
use std::time::{Duration, Instant};

use coap::Code;

use crate::cams::{SN, TempDir, client, runtime, send, serve};

/// Longest wait for the process to exit; far below the server's 120 s `--duration`.
const EXIT_BOUND: Duration = Duration::from_secs(30);

#[test]
fn serve_exits_with_status_0_on_sigterm_and_sigint() {
    for signal in ["TERM", "INT"] {
        let state = TempDir::new(&format!("signal-{signal}"));
        let (mut server, addr) = serve(state.path());
        runtime().block_on(async {
            let r = send(
                &client(),
                addr,
                Code::GET,
                &format!("/cams/{SN}/depth-settings"),
                b"",
                None,
            )
            .await;
            assert_eq!(r.code, Code::CONTENT, "serving before SIG{signal}");
        });
        let pid = server.process().id().to_string();
        let sent = Command::new("kill")
            .args(["-s", signal, &pid])
            .status()
            .expect("running kill");
        assert!(sent.success(), "kill -s {signal} {pid}");
        let deadline = Instant::now() + EXIT_BOUND;
        let status = loop {
            match server.process().try_wait().expect("waiting for coapcam") {
                Some(status) => break status,
                None if Instant::now() < deadline => std::thread::sleep(Duration::from_millis(20)),
                None => panic!("coapcam serve still runs {EXIT_BOUND:?} after SIG{signal}"),
            }
        };
        assert_eq!(status.code(), Some(0), "SIG{signal}: {status}");
    }
}
