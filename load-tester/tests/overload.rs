//! The load tester against a real in-process server: measures capacity, then offers twice that and checks
//! the server degrades the way it promises (bounded queues: stale frames dropped, answered latency
//! bounded, throughput kept), and that SLO flags and bad input give the documented exit codes.
#![allow(clippy::unwrap_used)]

use std::path::{Path, PathBuf};
use std::process::Command;

use crate::common;
use crate::common::{recording, workspace};

fn load(dir: &Path, rec: &Path, tag: &str, extra: &[&str]) -> (Option<i32>, serde_json::Value) {
    let out = dir.join(format!("{tag}.json"));
    let status = Command::new(env!("CARGO_BIN_EXE_holoface-load"))
        .current_dir(workspace())
        .args([
            "--spawn-server",
            "--server-threads",
            "1",
            "--warmup-s",
            "1",
            "--interval-s",
            "1",
        ])
        .arg("--recording")
        .arg(rec)
        .arg("--out")
        .arg(&out)
        .arg("--plot")
        .arg(dir.join(format!("{tag}.png")))
        .args(extra)
        .status()
        .unwrap();
    let report =
        std::fs::read_to_string(&out).map_or(serde_json::Value::Null, |t| serde_json::from_str(&t).unwrap());
    (status.code(), report)
}

#[test]
fn twice_the_capacity_drops_stale_frames_and_keeps_latency_and_throughput_bounded() {
    let dir = std::env::temp_dir().join(format!("holoface-load-test-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let rec = recording(&dir);
    // Capacity: two headsets sending far more than one ONNX Runtime thread can align.
    let (code, cap) = load(
        &dir,
        &rec,
        "capacity",
        // Most frames are shed here by design (dropped frames count against --min-answered): this run measures
        // capacity, not the answered share.
        &[
            "--clients",
            "2",
            "--fps",
            "200",
            "--duration-s",
            "3",
            "--min-answered",
            "0",
        ],
    );
    assert_eq!(code, Some(0));
    let capacity = cap["totals"]["throughput_per_s"].as_f64().unwrap();
    assert!(capacity > 5.0, "capacity {capacity}/s");

    // Twice the capacity from four headsets.
    let fps = format!("{:.1}", 2.0 * capacity / 4.0);
    let (code, over) = load(
        &dir,
        &rec,
        "overload",
        &[
            "--clients",
            "4",
            "--fps",
            &fps,
            "--duration-s",
            "4",
            "--deadline-ms",
            "100",
            "--max-p99-ms",
            "400",
            // About half is shed as stale by design: the answered share is checked below, not by the SLO.
            "--min-answered",
            "0",
        ],
    );
    let t = &over["totals"];
    assert_eq!(code, Some(0), "{t}");
    let dropped: u64 = t["dropped"]
        .as_object()
        .unwrap()
        .values()
        .map(|v| v.as_u64().unwrap())
        .sum();
    let sent = t["sent"].as_u64().unwrap();
    assert!(
        dropped > sent / 5,
        "about half the frames must be shed as stale: {t}"
    );
    assert!(
        t["throughput_per_s"].as_f64().unwrap() > 0.6 * capacity,
        "throughput collapsed: {t}"
    );
    assert!(
        t["unanswered"].as_u64().unwrap() <= sent / 50,
        "frames vanished without a reply: {t}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn slo_breach_exits_3_and_bad_input_exits_1_with_a_message() {
    let dir = std::env::temp_dir().join(format!("holoface-load-slo-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let rec = recording(&dir);
    let (code, report) = load(
        &dir,
        &rec,
        "slo",
        &[
            "--clients",
            "1",
            "--fps",
            "10",
            "--duration-s",
            "2",
            "--max-p99-ms",
            "0.001",
        ],
    );
    assert_eq!(code, Some(3));
    assert!(
        report["slo"]["broken"][0].as_str().unwrap().contains("p99"),
        "{report}"
    );

    let garbage = dir.join("garbage.hfrec");
    std::fs::write(&garbage, b"not a recording").unwrap();
    let out = Command::new(env!("CARGO_BIN_EXE_holoface-load"))
        .args(["--spawn-server", "--duration-s", "1", "--recording"])
        .arg(&garbage)
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(1));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("garbage.hfrec"), "{err}");

    // Results that cannot be written are an error, not a silent success.
    let out = Command::new(env!("CARGO_BIN_EXE_holoface-load"))
        .current_dir(workspace())
        .args([
            "--spawn-server",
            "--server-threads",
            "1",
            "--clients",
            "1",
            "--fps",
            "5",
            "--duration-s",
            "1",
        ])
        .args([
            "--warmup-s",
            "0.5",
            "--interval-s",
            "1",
            "--out",
            "/proc/holoface.json",
            "--recording",
        ])
        .arg(&rec)
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&out.stderr).contains("/proc/holoface.json"));
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn headsets_stop_sending_on_the_servers_goaway() {
    let dir = std::env::temp_dir().join(format!("holoface-load-goaway-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let rec = recording(&dir);
    let ort = std::env::var_os("ORT_DYLIB_PATH").map_or_else(
        || workspace().join(".cache/holoface/libonnxruntime.so.1.31.1"),
        PathBuf::from,
    );
    let mut s = holoface_alignment_server::config::Settings::for_loopback(
        "goaway-test",
        workspace().join("models/assets/dan.onnx"),
        Some(workspace().join("models/assets/refiner.bin")),
        ort,
    )
    .unwrap();
    s.engine.intra_threads = 1;
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .unwrap();
    let server = rt
        .block_on(holoface_alignment_server::AlignmentServer::bind(s))
        .unwrap();
    let (addr, fp) = (server.local_addr().unwrap(), server.fingerprint());
    let metrics = server.metrics();
    let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
    let task = rt.spawn(server.run(async move {
        let _ = stopped.await;
    }));
    let out = dir.join("goaway.json");
    let started = std::time::Instant::now();
    let mut child = Command::new(env!("CARGO_BIN_EXE_holoface-load"))
        .current_dir(workspace())
        .args(["--server", &addr.to_string(), "--fingerprint", &fp.to_string()])
        .args(["--token", "goaway-test", "--clients", "2", "--fps", "10"])
        .args(["--duration-s", "30", "--warmup-s", "0", "--interval-s", "1"])
        .arg("--recording")
        .arg(&rec)
        .arg("--out")
        .arg(&out)
        .arg("--plot")
        .arg(dir.join("goaway.png"))
        .spawn()
        .unwrap();
    // The Goaway comes once both headsets are being answered (20 frames: a second of the load).
    common::wait_for_some("the load's frames to be aligned", || {
        (metrics.frames_aligned.load(std::sync::atomic::Ordering::Relaxed) >= 20).then_some(())
    });
    stop.send(()).unwrap();
    rt.block_on(task).unwrap().unwrap();
    let status = child.wait().unwrap();
    let took = started.elapsed();
    assert_eq!(status.code(), Some(0));
    // It left on the Goaway, not at the end of its 30 s.
    assert!(took < std::time::Duration::from_secs(15), "the load ran {took:?}");
    let report: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&out).unwrap()).unwrap();
    assert_eq!(report["totals"]["headsets_told_goaway"], 2, "{report}");
    assert!(report["totals"]["answered"].as_u64().unwrap() > 0, "{report}");
    let _ = std::fs::remove_dir_all(&dir);
}
