//! The shipped `holoface-server` binary as a service manager runs it (issue 57): SIGTERM (systemd stop, a
//! container stop) and Ctrl-C drain the frames in flight (each answered or explicitly dropped, none silently
//! lost), close the connection with `ShuttingDown` and exit 0 within the shutdown timeout.
//!
//! Needs the model and ONNX Runtime as server_e2e does, and the binary built beside the tests (`make test`
//! builds every binary first).
#![allow(clippy::unwrap_used)]

use std::collections::BTreeSet;
use std::io::{BufRead as _, BufReader, Read as _};
use std::net::SocketAddr;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use holoface_protocol::{CloseCode, DropReason, Message, ReplyOutcome};
use holoface_quic::Fingerprint;
use holoface_tests::{
    TEST_TOKEN, TestClient, frame, hello, model_path, ort_dylib_path, refiner_path, server_binary, within,
    workspace_root,
};

const SHUTDOWN_TIMEOUT: Duration = Duration::from_secs(3);
/// Frames sent back to back just before the signal: more than one batch, so some are queued.
const IN_FLIGHT: u64 = 12;

struct Server {
    child: Child,
    addr: SocketAddr,
    fingerprint: Fingerprint,
}

fn start() -> Server {
    let mut child = Command::new(server_binary())
        .current_dir(workspace_root())
        .args(["--listen", "127.0.0.1:0", "--self-signed-name", "localhost"])
        .args([
            "--token",
            TEST_TOKEN,
            "--intra-threads",
            "1",
            "--max-frame-age-ms",
            "5000",
        ])
        .arg("--shutdown-timeout-ms")
        .arg(SHUTDOWN_TIMEOUT.as_millis().to_string())
        .arg("--model")
        .arg(model_path())
        .arg("--refine-model")
        .arg(refiner_path())
        .arg("--ort-dylib")
        .arg(ort_dylib_path())
        .env("RUST_LOG", "info")
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    // "holoface-server on ADDR certificate-sha256 FP metrics off"
    let mut line = String::new();
    BufReader::new(child.stdout.take().unwrap())
        .read_line(&mut line)
        .unwrap();
    let words: Vec<&str> = line.split_whitespace().collect();
    assert!(
        words.len() >= 5 && words[..2] == ["holoface-server", "on"],
        "the server did not start: {line:?}"
    );
    Server {
        child,
        addr: words[2].parse().unwrap(),
        fingerprint: words[4].parse().unwrap(),
    }
}

/// Frames in flight when `signal` arrives: every one is answered (landmarks) or explicitly dropped,
/// the client sees the Goaway and the close code, and the process exits 0 within the shutdown timeout and
/// says so in its log.
async fn drains_on(signal: &str) {
    let mut server = start();
    let mut client = TestClient::connect(server.addr, server.fingerprint, hello(TEST_TOKEN))
        .await
        .unwrap();
    assert!(
        within("the first reply", client.request(&frame(1, 1, 5_000)))
            .await
            .is_ok()
    );
    for id in 2..2 + IN_FLIGHT {
        client.send_frame(&frame(id, 3, 5_000)).await.unwrap();
    }
    let signalled = Instant::now();
    let kill = Command::new("kill")
        .args([format!("-{signal}"), server.child.id().to_string()])
        .status()
        .unwrap();
    assert!(kill.success());
    let goaway = within("the Goaway", client.next_control()).await.unwrap();
    assert!(
        matches!(&goaway, Message::Goaway(g) if g.reason == CloseCode::ShuttingDown),
        "{goaway:?}"
    );
    let mut waiting: BTreeSet<u64> = (2..2 + IN_FLIGHT).collect();
    let mut answered = 0;
    let mut dropped = Vec::new();
    while !waiting.is_empty() {
        let Ok(reply) = within("the in-flight replies", client.next_reply()).await else {
            panic!("the connection ended with frames {waiting:?} unanswered")
        };
        assert!(waiting.remove(&reply.frame_id), "{reply:?}");
        match reply.outcome {
            ReplyOutcome::Landmarks { .. } => answered += 1,
            // An explicit refusal: ShuttingDown from the draining scheduler, or Superseded where a newer
            // frame of the same face replaced a queued one (one frame per face queued).
            ReplyOutcome::Dropped { reason } => dropped.push(reason),
        }
    }
    assert_eq!(answered + dropped.len() as u64, IN_FLIGHT, "{dropped:?}");
    assert!(
        dropped
            .iter()
            .all(|r| matches!(r, DropReason::ShuttingDown | DropReason::Superseded)),
        "{dropped:?}"
    );
    assert_eq!(
        within("the close", client.close_code()).await,
        Some(CloseCode::ShuttingDown)
    );
    let status = loop {
        if let Some(status) = server.child.try_wait().unwrap() {
            break status;
        }
        assert!(
            signalled.elapsed() < SHUTDOWN_TIMEOUT + Duration::from_secs(5),
            "still running {:?} after {signal}",
            signalled.elapsed()
        );
        tokio::time::sleep(Duration::from_millis(20)).await;
    };
    let mut log = String::new();
    server
        .child
        .stderr
        .take()
        .unwrap()
        .read_to_string(&mut log)
        .unwrap();
    assert_eq!(status.code(), Some(0), "{log}");
    assert!(log.contains("shutdown complete"), "{log}");
    assert!(!log.contains("WARN"), "{log}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sigterm_drains_the_frames_in_flight_and_exits_0() {
    drains_on("TERM").await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn ctrl_c_drains_the_frames_in_flight_and_exits_0() {
    drains_on("INT").await;
}
