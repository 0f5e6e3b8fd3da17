//! `holoface-load` stopped by a signal (issue 57): not a latency contract, so it runs beside other tests, not in
//! the timing-sensitive group.
#![allow(clippy::unwrap_used)]

use std::process::Command;

use crate::common::{recording, workspace};

/// Ctrl-C (or a service stop) ends a load test early with its report for the time it ran (issue 57): the
/// table, `--out` and `--plot`, `interrupted` and `measured_s` in the JSON, the shell's exit code.
#[test]
fn a_signal_ends_a_load_test_with_its_report_for_the_time_it_ran() {
    use std::io::BufRead as _;
    let dir = std::env::temp_dir().join(format!("holoface-load-interrupt-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let rec = recording(&dir);
    let out = dir.join("interrupted.json");
    let mut child = Command::new(env!("CARGO_BIN_EXE_holoface-load"))
        .current_dir(workspace())
        .args([
            "--spawn-server",
            "--server-threads",
            "1",
            "--clients",
            "2",
            "--fps",
            "10",
        ])
        .args(["--duration-s", "60", "--warmup-s", "0", "--interval-s", "1"])
        .arg("--recording")
        .arg(&rec)
        .arg("--out")
        .arg(&out)
        .arg("--plot")
        .arg(dir.join("interrupted.png"))
        .stdout(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    // Two rows of the table (two measured seconds), then SIGINT.
    let mut lines = std::io::BufReader::new(child.stdout.take().unwrap()).lines();
    let mut rows = 0;
    while rows < 2 {
        let line = lines.next().expect("the table ended early").unwrap();
        if line
            .split_whitespace()
            .next()
            .is_some_and(|t| t.parse::<f64>().is_ok())
        {
            rows += 1;
        }
    }
    let started = std::time::Instant::now();
    assert!(
        Command::new("kill")
            .args(["-INT", &child.id().to_string()])
            .status()
            .unwrap()
            .success()
    );
    let rest: Vec<String> = lines.map(Result::unwrap).collect();
    let status = child.wait().unwrap();
    assert!(
        started.elapsed() < std::time::Duration::from_secs(15),
        "it took {:?} to stop",
        started.elapsed()
    );
    assert_eq!(status.code(), Some(130), "{rest:?}");
    assert!(
        rest.iter().any(|l| l.starts_with("interrupted by SIGINT")),
        "{rest:?}"
    );
    let report: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&out).unwrap()).unwrap();
    assert_eq!(report["interrupted"], "SIGINT", "{report}");
    let secs = report["measured_s"].as_f64().unwrap();
    assert!((1.5..30.0).contains(&secs), "measured {secs} s: {report}");
    assert!(report["totals"]["answered"].as_u64().unwrap() > 0, "{report}");
    assert!(dir.join("interrupted.png").is_file());
    let _ = std::fs::remove_dir_all(&dir);
}
