//! Untrusted strings in the server's log (issue 30): a client whose name carries a newline, a made-up
//! timestamp with a fake "shutdown complete" and an ANSI escape gets exactly one log line, with all of it
//! escaped; and a log that is not a terminal carries no colour codes. A flood of clients with a wrong token
//! (issue 68: 1,203 lines for as many clients) is a few lines, and the metrics count every one. The log is
//! captured in-process through the binaries' own subscriber set-up (`holoface_process::logging`),
//! which is global: each test runs in a process of its own (nextest, `make test`'s runner).
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

/// Captures this process's log, as the binaries set it up when standard error is a file or a pipe.
fn capture_log() -> Arc<Mutex<Vec<u8>>> {
    let log = Arc::new(Mutex::new(Vec::new()));
    let sink = Arc::clone(&log);
    holoface_process::logging::init_with(
        holoface_process::logging::env_filter_or("info"),
        move || Capture(Arc::clone(&sink)),
        false,
    );
    log
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_forged_client_name_is_one_escaped_log_line_without_colour_codes() {
    let log = capture_log();
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

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_flood_of_wrong_tokens_is_a_few_log_lines_and_every_one_is_counted() {
    const CLIENTS: usize = 1_000;
    let log = capture_log();
    let server = RunningServer::start(loopback_settings()).await.unwrap();
    let (addr, fp) = (server.addr, server.fingerprint);
    // Twenty at a time, as fast as the handshakes go.
    let mut refused = 0;
    for _ in 0..CLIENTS / 20 {
        let wave: Vec<_> = (0..20)
            .map(|_| tokio::spawn(TestClient::connect(addr, fp, hello("not-the-token"))))
            .collect();
        for c in wave {
            refused += usize::from(c.await.unwrap().is_err());
        }
    }
    assert_eq!(refused, CLIENTS);
    // The metrics count every close (the last ones may still be closing).
    holoface_tests::within("every refusal counted", async {
        while server
            .metrics
            .auth_unauthorized
            .load(std::sync::atomic::Ordering::Relaxed)
            < CLIENTS as u64
        {
            tokio::time::sleep(std::time::Duration::from_millis(10)).await;
        }
    })
    .await;
    server.shutdown().await.unwrap();
    let text = String::from_utf8(log.lock().unwrap().clone()).unwrap();
    let warnings: Vec<&str> = text.lines().filter(|l| l.contains("WARN")).collect();
    let closes = warnings
        .iter()
        .filter(|l| l.contains("closing misbehaving client"))
        .count();
    // One line each for the first five of each ten seconds, and a line summing up the rest per window.
    assert!(
        (1..=10).contains(&closes) && warnings.len() <= 24,
        "{} warnings for {CLIENTS} wrong tokens:\n{text}",
        warnings.len()
    );
    assert!(warnings.iter().all(|l| l.contains("code=unauthorized")), "{text}");
    // Every close is in the log, one by one or summed up (the server sums up what is left at shutdown).
    let summed: usize = warnings
        .iter()
        .filter_map(|l| l.split("closes=").nth(1))
        .map(|n| n.split_whitespace().next().unwrap().parse::<usize>().unwrap())
        .sum();
    assert_eq!(closes + summed, CLIENTS, "{text}");
}
