//! The load tester when the server dies (issue 30): killed for good, the run breaks its SLO (exit 3) and
//! reports the outage and the frames it could not send; killed and restarted on the same address with the
//! same certificate, the headsets reconnect and the outage is reported as recovered. (It used to go quiet,
//! never reconnect, and exit 0.)
#![allow(clippy::unwrap_used)]

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::Duration;

use crate::common;
use crate::common::{recording, workspace};
use holoface_alignment_server::config::{Settings, TlsSource};

const TOKEN: &str = "outage-test";

/// A server on its own runtime, so that dropping the runtime kills it the way SIGKILL does: no Goaway, no
/// close frames, the socket simply gone.
struct Killable {
    rt: tokio::runtime::Runtime,
    metrics: std::sync::Arc<holoface_alignment_server::metrics::Metrics>,
}

fn start(dir: &Path, listen: SocketAddr) -> (Killable, SocketAddr, String) {
    let ort = std::env::var_os("ORT_DYLIB_PATH").map_or_else(
        || workspace().join(".cache/holoface/libonnxruntime.so.1.31.1"),
        PathBuf::from,
    );
    let mut s = Settings::for_loopback(
        TOKEN,
        workspace().join("models/assets/dan.onnx"),
        Some(workspace().join("models/assets/refiner.bin")),
        ort,
    )
    .unwrap();
    s.engine.intra_threads = 1;
    s.listen = listen;
    s.tls = TlsSource::Files {
        cert: dir.join("cert.pem"),
        key: dir.join("key.pem"),
    };
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(1)
        .enable_all()
        .build()
        .unwrap();
    // A killed server's port is free once its runtime has dropped the socket: bind again until it is.
    let server = common::wait_for_some("the port to bind", || {
        rt.block_on(holoface_alignment_server::AlignmentServer::bind(s.clone()))
            .ok()
    });
    let metrics = server.metrics();
    let (addr, fp) = (server.local_addr().unwrap(), server.fingerprint().to_string());
    rt.spawn(server.run(std::future::pending()));
    (Killable { rt, metrics }, addr, fp)
}

impl Killable {
    fn kill(self) {
        self.rt.shutdown_background();
    }

    /// Returns once the server has aligned `frames` frames: the load is under way (20 a second here).
    fn wait_aligned(&self, frames: u64) {
        let m = &self.metrics;
        common::wait_for_some("the load's frames to be aligned", || {
            (m.frames_aligned.load(std::sync::atomic::Ordering::Relaxed) >= frames).then_some(())
        });
    }
}

fn setup(tag: &str) -> (PathBuf, PathBuf) {
    let dir = std::env::temp_dir().join(format!("holoface-load-{tag}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let c = rcgen::generate_simple_self_signed(vec!["localhost".to_owned()]).unwrap();
    std::fs::write(dir.join("cert.pem"), c.cert.pem()).unwrap();
    std::fs::write(dir.join("key.pem"), c.signing_key.serialize_pem()).unwrap();
    let rec = recording(&dir);
    (dir, rec)
}

fn load(dir: &Path, rec: &Path, addr: SocketAddr, fp: &str, extra: &[&str]) -> Child {
    Command::new(env!("CARGO_BIN_EXE_holoface-load"))
        .current_dir(workspace())
        .args([
            "--server",
            &addr.to_string(),
            "--fingerprint",
            fp,
            "--token",
            TOKEN,
        ])
        .args([
            "--clients",
            "2",
            "--fps",
            "10",
            "--duration-s",
            "9",
            "--warmup-s",
            "0",
        ])
        .args(["--interval-s", "1"])
        .arg("--recording")
        .arg(rec)
        .arg("--out")
        .arg(dir.join("load.json"))
        .arg("--plot")
        .arg(dir.join("load.png"))
        .args(extra)
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap()
}

fn finish(child: Child, dir: &Path) -> (Option<i32>, String, serde_json::Value) {
    let out = child.wait_with_output().unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr).into_owned();
    let report = std::fs::read_to_string(dir.join("load.json"))
        .map(|t| serde_json::from_str(&t).unwrap())
        .unwrap_or(serde_json::Value::Null);
    (out.status.code(), stderr, report)
}

#[test]
fn a_server_killed_for_good_breaks_the_slo_and_the_outage_is_reported() {
    let (dir, rec) = setup("killed");
    let (server, addr, fp) = start(&dir, "127.0.0.1:0".parse().unwrap());
    let child = load(&dir, &rec, addr, &fp, &[]);
    server.wait_aligned(40);
    server.kill();
    let (code, stderr, report) = finish(child, &dir);
    assert_eq!(code, Some(3), "{stderr}\n{report}");
    assert!(stderr.contains("SLO broken: answered"), "{stderr}");
    assert!(
        stderr.contains("lost") && stderr.contains("to the end of the run"),
        "{stderr}"
    );
    let outages = report["outages"].as_array().unwrap();
    assert!(!outages.is_empty(), "{report}");
    assert!(outages.iter().all(|o| o["recovered"] == false), "{report}");
    // Both headsets noticed the loss (none took it for a Goaway and quietly left).
    assert_eq!(
        stderr.matches("still unreachable at the end of the run").count(),
        2,
        "{stderr}"
    );
    assert!(report["totals"]["unsent"].as_u64().unwrap() > 0, "{report}");
    assert!(report["totals"]["answered"].as_u64().unwrap() > 0, "{report}");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_server_killed_and_restarted_is_reconnected_to() {
    let (dir, rec) = setup("restarted");
    let (server, addr, fp) = start(&dir, "127.0.0.1:0".parse().unwrap());
    // The frames sent between the kill and QUIC noticing it (its idle timeout) go unanswered; the SLO
    // here asks only that the run goes on.
    let child = load(&dir, &rec, addr, &fp, &["--min-answered", "0.3"]);
    server.wait_aligned(40);
    server.kill();
    // The outage: half a second without a server (the scenario, not a wait for something).
    std::thread::sleep(Duration::from_millis(500));
    let (server, again, fp2) = start(&dir, addr);
    assert_eq!(
        (again, fp2.as_str()),
        (addr, fp.as_str()),
        "the same address and certificate"
    );
    let (code, stderr, report) = finish(child, &dir);
    server.kill();
    assert_eq!(code, Some(0), "{stderr}\n{report}");
    assert!(stderr.contains("reconnected"), "{stderr}");
    let outages = report["outages"].as_array().unwrap();
    assert!(!outages.is_empty(), "{report}");
    assert!(outages.iter().all(|o| o["recovered"] == true), "{report}");
    // Timed from the last answer, not from when QUIC noticed: at least the 0.5 s the server was down.
    assert!(
        outages.iter().all(|o| o["length_s"].as_f64().unwrap() >= 0.5),
        "{report}"
    );
    // Every headset lost its connection and came back (none mistook the loss for a Goaway).
    assert_eq!(stderr.matches("reconnected").count(), 2, "{stderr}");
    // Answers came again after the restart: the last report interval has some.
    let last = report["timeline"].as_array().unwrap().last().unwrap().clone();
    assert!(last["answered_per_s"].as_f64().unwrap() > 0.0, "{report}");
    let _ = std::fs::remove_dir_all(&dir);
}
