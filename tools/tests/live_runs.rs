//! A live run keeps what it saw (issue 57): `holoface track --source -` fed like a camera through ffmpeg (a
//! YUV4MPEG2 stream on standard input, one frame every 30 ms), then stopped the ways a live run ends: Ctrl-C
//! (SIGINT), a service stop (SIGTERM), two signals, `kill -9`, and a reader of standard output.
#![allow(clippy::unwrap_used)]

use std::io::{BufRead as _, Write as _};
use std::path::Path;
use std::process::{Child, ChildStdin, Command, Stdio};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::time::{Duration, Instant};

use crate::common;
use crate::common::{tmp, workspace};

const W: usize = 64;
const H: usize = 48;

/// `holoface track --source - --out OUT` (and `extra`) with piped standard input.
fn track(out: &str, stdout: Stdio) -> Child {
    track_with(out, stdout, &[])
}

fn track_with(out: &str, stdout: Stdio, extra: &[&str]) -> Child {
    let mut args = vec!["track", "--source", "-", "--out", out];
    args.extend(extra);
    live(&args, &workspace(), stdout)
}

/// `holoface ARGS` in `dir`, its standard input piped (for a [`Camera`]) and its standard error captured.
fn live(args: &[&str], dir: &Path, stdout: Stdio) -> Child {
    Command::new(env!("CARGO_BIN_EXE_holoface"))
        .args(args)
        .current_dir(dir)
        .env("RUST_BACKTRACE", "0")
        .stdin(Stdio::piped())
        .stdout(stdout)
        .stderr(Stdio::piped())
        .spawn()
        .unwrap()
}

/// A camera feeding a run's standard input: the stream header, then a gray frame every 30 ms until it goes quiet
/// (or the reader has gone); then it stays open and idle, so only a signal ends the run. Goes quiet when dropped.
struct Camera {
    quiet: Arc<AtomicBool>,
    sent: Arc<AtomicUsize>,
}

impl Camera {
    fn start(child: &mut Child) -> Self {
        let mut stdin: ChildStdin = child.stdin.take().unwrap();
        let (quiet, sent) = (Arc::new(AtomicBool::new(false)), Arc::new(AtomicUsize::new(0)));
        let (q, n) = (quiet.clone(), sent.clone());
        std::thread::spawn(move || {
            if stdin
                .write_all(format!("YUV4MPEG2 W{W} H{H} F30:1 Cmono\n").as_bytes())
                .is_err()
            {
                return;
            }
            let mut k = 0u8;
            while !q.load(Ordering::SeqCst) {
                let mut frame = b"FRAME\n".to_vec();
                frame.extend(std::iter::repeat_n(100u8.wrapping_add(k), W * H));
                // Counted before it is sent: the run may track it before this thread runs again.
                n.fetch_add(1, Ordering::SeqCst);
                if stdin.write_all(&frame).and_then(|()| stdin.flush()).is_err() {
                    return;
                }
                k = k.wrapping_add(1);
                std::thread::sleep(Duration::from_millis(30));
            }
            std::thread::sleep(Duration::from_secs(30));
        });
        Self { quiet, sent }
    }

    /// Frames sent so far (at most one of them not delivered).
    fn sent(&self) -> usize {
        self.sent.load(Ordering::SeqCst)
    }

    /// Stops sending frames (the stream stays open).
    fn go_quiet(&self) {
        self.quiet.store(true, Ordering::SeqCst);
    }
}

impl Drop for Camera {
    fn drop(&mut self) {
        self.go_quiet();
    }
}

/// Every line of `path` parses as a frame's JSON, numbered 0, 1, 2, ...; returns how many.
fn whole_lines(path: &Path) -> usize {
    let text = std::fs::read_to_string(path).unwrap_or_default();
    assert!(
        text.is_empty() || text.ends_with('\n'),
        "the last line is cut: {text:?}"
    );
    for (i, line) in text.lines().enumerate() {
        let v: serde_json::Value =
            serde_json::from_str(line).unwrap_or_else(|e| panic!("line {i}: {e}: {line}"));
        assert_eq!(v["frame"], i, "{line}");
    }
    text.lines().count()
}

/// Waits until `path` holds at least `n` lines (under its real name, while the run goes on).
fn wait_for_lines(path: &Path, n: usize, child: &mut Child) {
    let t0 = Instant::now();
    while std::fs::read_to_string(path).map_or(0, |t| t.lines().count()) < n {
        assert!(child.try_wait().unwrap().is_none(), "the run ended early");
        assert!(
            t0.elapsed() < Duration::from_secs(60),
            "no {n} lines in {} after 60 s",
            path.display()
        );
        std::thread::sleep(Duration::from_millis(20));
    }
}

fn kill(child: &Child, signal: &str) {
    assert!(
        Command::new("kill")
            .args([signal, &child.id().to_string()])
            .status()
            .unwrap()
            .success()
    );
}

/// Stops a live run with `signal` while the camera keeps sending; returns its exit code, the lines seen before
/// the signal, the lines kept, and its standard error.
fn stop_with(signal: &str, name: &str) -> (Option<i32>, usize, usize, String) {
    let d = tmp(name);
    let out = d.join("o.jsonl");
    // A temporary file an earlier, killed run left beside the output: never removed behind the user's back.
    let earlier = d.join("o.jsonl.partial-999999999");
    std::fs::write(&earlier, b"{\"frame\":0}\n").unwrap();
    let mut child = track(out.to_str().unwrap(), Stdio::piped());
    let cam = Camera::start(&mut child);
    wait_for_lines(&out, 3, &mut child);
    let before = whole_lines(&out);
    kill(&child, signal);
    let t0 = Instant::now();
    let res = child.wait_with_output().unwrap();
    assert!(
        t0.elapsed() < Duration::from_secs(10),
        "the run took {:?} to stop",
        t0.elapsed()
    );
    cam.go_quiet();
    let kept = whole_lines(&out);
    assert!(earlier.exists(), "an earlier run's file was removed");
    assert!(kept <= cam.sent(), "more lines than frames sent");
    (
        res.status.code(),
        before,
        kept,
        format!(
            "{}{}",
            String::from_utf8_lossy(&res.stdout),
            String::from_utf8_lossy(&res.stderr)
        ),
    )
}

#[test]
fn ctrl_c_ends_a_live_run_after_the_frame_in_hand_keeping_every_line() {
    let (code, before, kept, stderr) = stop_with("-INT", "live-int");
    assert_eq!(code, Some(130), "{stderr}");
    assert!(
        kept >= before,
        "{kept} lines kept of {before} seen before the signal: {stderr}"
    );
    assert!(
        stderr.contains(&format!("stopped by SIGINT after {kept} frames")),
        "{stderr}"
    );
}

#[test]
fn ctrl_c_finishes_the_annotated_video_of_a_live_run() {
    let d = tmp("live-mp4");
    let (out, mp4) = (d.join("o.jsonl"), d.join("a.mp4"));
    let mut child = track_with(
        out.to_str().unwrap(),
        Stdio::piped(),
        &["--annotate", mp4.to_str().unwrap()],
    );
    let cam = Camera::start(&mut child);
    wait_for_lines(&out, 5, &mut child);
    kill(&child, "-INT");
    let res = child.wait_with_output().unwrap();
    drop(cam);
    assert_eq!(
        res.status.code(),
        Some(130),
        "{}",
        String::from_utf8_lossy(&res.stderr)
    );
    let kept = whole_lines(&out);
    // The video is finished (its index written), so it plays: tracked again, it gives one line per frame kept.
    let again = d.join("again.jsonl");
    let (ok, text) = common::holoface(&[
        "track",
        "--source",
        mp4.to_str().unwrap(),
        "--out",
        again.to_str().unwrap(),
    ]);
    assert!(ok, "{text}");
    assert_eq!(whole_lines(&again), kept, "{text}");
}

#[test]
fn sigterm_ends_a_live_run_the_same_way() {
    let (code, before, kept, stderr) = stop_with("-TERM", "live-term");
    assert_eq!(code, Some(143), "{stderr}");
    assert!(kept >= before, "{kept} of {before}: {stderr}");
    assert!(
        stderr.contains(&format!("stopped by SIGTERM after {kept} frames")),
        "{stderr}"
    );
}

#[test]
fn a_second_signal_stops_at_once_and_keeps_what_is_on_disk() {
    let d = tmp("live-twice");
    let out = d.join("o.jsonl");
    let mut child = track(out.to_str().unwrap(), Stdio::null());
    let cam = Camera::start(&mut child);
    wait_for_lines(&out, 3, &mut child);
    // The camera goes quiet, and the run has tracked every frame it sent: the first signal then waits for a
    // frame that does not come, the second ends the run.
    cam.go_quiet();
    std::thread::sleep(Duration::from_millis(100)); // a frame being written when the camera stopped is sent
    let t0 = Instant::now();
    while std::fs::read_to_string(&out).map_or(0, |t| t.lines().count()) < cam.sent() {
        assert!(
            t0.elapsed() < Duration::from_secs(60),
            "the run did not catch up with the camera"
        );
        std::thread::sleep(Duration::from_millis(20));
    }
    kill(&child, "-INT");
    std::thread::sleep(Duration::from_millis(300));
    assert!(
        child.try_wait().unwrap().is_none(),
        "one signal on an idle source waits for the frame in hand"
    );
    kill(&child, "-INT");
    let res = child.wait_with_output().unwrap();
    drop(cam);
    let stderr = String::from_utf8_lossy(&res.stderr);
    assert_eq!(res.status.code(), Some(130), "{stderr}");
    assert!(whole_lines(&out) >= 3, "{stderr}");
    assert!(stderr.contains("stopped at once"), "{stderr}");
}

#[test]
fn a_killed_live_run_leaves_whole_lines_under_the_files_name() {
    let d = tmp("live-kill");
    let out = d.join("o.jsonl");
    let mut child = track(out.to_str().unwrap(), Stdio::null());
    let cam = Camera::start(&mut child);
    wait_for_lines(&out, 5, &mut child);
    kill(&child, "-KILL");
    child.wait().unwrap();
    drop(cam);
    assert!(whole_lines(&out) >= 5);
}

#[test]
fn out_dash_streams_json_lines_on_standard_output_and_nothing_else() {
    let d = tmp("live-stdout");
    let mut child = live(&["track", "--source", "-", "--out", "-"], &d, Stdio::piped());
    let cam = Camera::start(&mut child);
    // Each frame arrives on standard output as it is tracked: read 10, then go away (`| head -n 10`).
    let mut lines = std::io::BufReader::new(child.stdout.take().unwrap()).lines();
    for i in 0..10 {
        let line = lines.next().unwrap().unwrap();
        let v: serde_json::Value = serde_json::from_str(&line).unwrap_or_else(|e| panic!("{e}: {line}"));
        assert_eq!(v["frame"], i);
    }
    drop(lines);
    let res = child.wait_with_output().unwrap();
    drop(cam);
    let stderr = String::from_utf8_lossy(&res.stderr);
    assert_eq!(
        res.status.code(),
        Some(0),
        "a reader that has gone ends the run: {stderr}"
    );
    assert!(
        stderr.contains("frames"),
        "the summary goes to standard error: {stderr}"
    );
    assert!(!d.join("-").exists(), "`--out -` wrote a file named -");
}

/// `holoface record --source - --out OUT` with piped standard input.
fn record(out: &Path) -> Child {
    Command::new(env!("CARGO_BIN_EXE_holoface"))
        .args(["record", "--source", "-", "--out", out.to_str().unwrap()])
        .current_dir(workspace())
        .env("RUST_BACKTRACE", "0")
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap()
}

/// The whole frame records of a recording, read strictly (`Err` names the first problem).
fn strict_records(path: &Path) -> Result<usize, String> {
    let file = std::io::BufReader::new(std::fs::File::open(path).unwrap());
    let reader = holoface_protocol::RecordingReader::new(file).map_err(|e| e.to_string())?;
    let mut n = 0;
    for r in reader {
        r.map_err(|e| e.to_string())?;
        n += 1;
    }
    Ok(n)
}

/// Waits until the recording at `path` holds at least `n` whole frame records (read as it grows).
fn wait_for_records(path: &Path, n: usize, child: &mut Child) {
    let t0 = Instant::now();
    let whole = || {
        let Ok(file) = std::fs::File::open(path) else {
            return 0;
        };
        let Ok(reader) = holoface_protocol::RecordingReader::new(std::io::BufReader::new(file)) else {
            return 0;
        };
        reader.tolerate_cut().map_while(Result::ok).count()
    };
    while whole() < n {
        assert!(child.try_wait().unwrap().is_none(), "the recording ended early");
        assert!(
            t0.elapsed() < Duration::from_secs(60),
            "{} did not grow",
            path.display()
        );
        std::thread::sleep(Duration::from_millis(20));
    }
}

#[test]
fn a_live_recording_stopped_by_a_signal_is_whole_and_a_killed_one_is_read_to_its_last_record() {
    let d = tmp("live-record");
    // SIGTERM (a service stop): every frame so far, a file any reader takes whole.
    let out = d.join("r.hfrec");
    let mut child = record(&out);
    let cam = Camera::start(&mut child);
    wait_for_records(&out, 5, &mut child);
    kill(&child, "-TERM");
    let res = child.wait_with_output().unwrap();
    cam.go_quiet();
    let text = format!(
        "{}{}",
        String::from_utf8_lossy(&res.stdout),
        String::from_utf8_lossy(&res.stderr)
    );
    assert_eq!(res.status.code(), Some(143), "{text}");
    let kept = strict_records(&out).unwrap_or_else(|e| panic!("{e}: {text}"));
    assert!(kept >= 5 && kept <= cam.sent(), "{kept}: {text}");
    assert!(
        text.contains(&format!("stopped by SIGTERM after {kept} frames")),
        "{text}"
    );

    // kill -9 part-way through a record: the readers take every whole record and say where the file ends.
    let cut = d.join("cut.hfrec");
    let mut child = record(&cut);
    let cam = Camera::start(&mut child);
    wait_for_records(&cut, 5, &mut child);
    kill(&child, "-KILL");
    child.wait().unwrap();
    drop(cam);
    // Cut it inside its last record, as a kill mid-write leaves it.
    let bytes = std::fs::read(&cut).unwrap();
    std::fs::write(&cut, &bytes[..bytes.len() - 10]).unwrap();
    let strict = strict_records(&cut);
    assert!(strict.as_ref().is_err_and(|e| e.contains("inside")), "{strict:?}");
    let lines = d.join("cut.jsonl");
    let (ok, text) = common::holoface(&[
        "track",
        "--source",
        cut.to_str().unwrap(),
        "--out",
        lines.to_str().unwrap(),
    ]);
    assert!(ok, "{text}");
    assert!(text.contains("a recording cut short"), "{text}");
    assert!(whole_lines(&lines) >= 4, "{text}");
}

/// `holoface stability` on a camera: a first Ctrl-C ends it after the frame in hand and its report covers every
/// frame it read (as `track`'s live run keeps them), with the shell's exit code for the signal.
#[test]
fn ctrl_c_ends_a_live_stability_run_with_a_report_of_its_frames() {
    let d = tmp("live-stability");
    let report = d.join("stability.json");
    let args = [
        "stability",
        "--source",
        "-",
        "--aligners",
        "krfws",
        "--out",
        report.to_str().unwrap(),
    ];
    let mut child = live(&args, &workspace(), Stdio::piped());
    let cam = Camera::start(&mut child);
    // The pipe holds about 20 frames: past 40 sent, the run is reading them.
    let t0 = Instant::now();
    while cam.sent() < 40 {
        assert!(child.try_wait().unwrap().is_none(), "the run ended early");
        assert!(t0.elapsed() < Duration::from_secs(60), "the run reads no frames");
        std::thread::sleep(Duration::from_millis(20));
    }
    kill(&child, "-INT");
    let res = child.wait_with_output().unwrap();
    cam.go_quiet();
    let stderr = String::from_utf8_lossy(&res.stderr);
    assert_eq!(res.status.code(), Some(130), "{stderr}");
    let r: serde_json::Value = serde_json::from_slice(&std::fs::read(&report).unwrap()).unwrap();
    let frames = r["frames"].as_u64().unwrap();
    assert!(
        frames >= 1 && frames as usize <= cam.sent(),
        "{frames} frames of {}",
        cam.sent()
    );
    assert!(
        stderr.contains(&format!("stopped by SIGINT after {frames} frames")),
        "{stderr}"
    );
}
