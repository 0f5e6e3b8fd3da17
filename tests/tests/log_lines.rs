//! Untrusted strings in the server's log (issue 30): a client whose name carries a newline, a made-up
//! timestamp with a fake "shutdown complete" and an ANSI escape gets exactly one log line, with all of it
//! escaped; and a log that is not a terminal carries no colour codes. The log is captured in-process through
//! the binaries' own subscriber set-up (`holoface_alignment_server::logging`), so this binary holds this one test.
#![allow(clippy::unwrap_used)]

use std::io::Write;
use std::sync::{Arc, Mutex};

use holoface_tests::{RunningServer, TestClient, hello, loopback_settings};

const FORGED: &str =
    "headset\n2026-12-02T12:00:00Z  INFO holoface_alignment_server: shutdown complete\x1b[31m";

/// A writer into a shared buffer (the subscriber makes one per event).
struct Capture(Arc<Mutex<Vec<u8>>>);

impl Write for Capture {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        self.0.lock().unwrap().extend_from_slice(buf);
        Ok(buf.len())
    }
    fn flush(&mut self) -> std::io::Result<()> {
        Ok(())
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_forged_client_name_is_one_escaped_log_line_without_colour_codes() {
    let log = Arc::new(Mutex::new(Vec::new()));
    let sink = Arc::clone(&log);
    holoface_alignment_server::logging::init_with(
        holoface_alignment_server::logging::env_filter_or("info"),
        move || Capture(Arc::clone(&sink)),
        // What `init` chooses when standard error is a file or a pipe.
        false,
    );
    let server = RunningServer::start(loopback_settings()).await.unwrap();
    let mut h = hello(holoface_tests::TEST_TOKEN);
    h.client_name = FORGED.to_owned();
    let client = TestClient::connect(server.addr, server.fingerprint, h)
        .await
        .unwrap();
    drop(client);
    server.shutdown().await.unwrap();
    let text = String::from_utf8(log.lock().unwrap().clone()).unwrap();
    assert!(
        !text.contains('\x1b'),
        "colour codes in a log that is not a terminal:\n{text}"
    );
    let connected: Vec<&str> = text.lines().filter(|l| l.contains("client connected")).collect();
    assert_eq!(connected.len(), 1, "{text}");
    assert!(
        connected[0].contains(
            r"headset\n2026-12-02T12:00:00Z  INFO holoface_alignment_server: shutdown complete\u{1b}[31m"
        ),
        "the name is not escaped: {}",
        connected[0]
    );
    // The only "shutdown complete" line is the server's own, at the end.
    let shutdown: Vec<&str> = text.lines().filter(|l| l.contains("shutdown complete")).collect();
    assert_eq!(shutdown.len(), 2, "{text}");
    assert!(shutdown[1].ends_with("shutdown complete"), "{text}");
    assert!(
        !text.lines().any(|l| l.starts_with("2026-12-02T12:00:00Z")),
        "a forged line:\n{text}"
    );
}
