//! Fault tests of the headset link against a real server process: kill it mid-stream (every frame is still
//! answered, locally, within two frame intervals), restart it (the client returns to the remote aligner), a
//! lossy and delaying relay (fallback and recovery), and an overloaded server (bounded, stale frames dropped).
#![allow(clippy::unwrap_used)]

use std::io::{BufRead, BufReader, Write};
use std::net::SocketAddr;
use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use holoface_harness::data::{Split, default_data_root, load_folder};
use holoface_harness::relay::UdpRelay;
use holoface_models::geometry::Point2;
use holoface_models::image::GrayImage;
use holoface_quic::Fingerprint;
use holoface_runtime::align::{Aligner, AnsweredBy, KrfwsAligner};
use holoface_runtime::link::{
    Backoff, ConnectConfig, FailureKind, LinkInfo, LinkOptions, LinkState, LinkedAligner, Mode, RemoteLink,
};
use holoface_tests::{TEST_TOKEN, workspace_root};

const FRAME: Duration = Duration::from_micros(33_333);

/// A server child process on a fixed port with a fixed certificate (so it can be restarted).
struct ServerProcess {
    child: Child,
    addr: SocketAddr,
    fingerprint: Fingerprint,
}

struct Identity {
    _dir: PathBuf,
    cert: PathBuf,
    key: PathBuf,
}

fn identity(tag: &str) -> Identity {
    let dir = std::env::temp_dir().join(format!("holoface-faults-{tag}-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let c = rcgen::generate_simple_self_signed(vec!["localhost".to_owned()]).unwrap();
    let (cert, key) = (dir.join("cert.pem"), dir.join("key.pem"));
    std::fs::write(&cert, c.cert.pem()).unwrap();
    std::fs::write(&key, c.signing_key.serialize_pem()).unwrap();
    Identity { _dir: dir, cert, key }
}

impl ServerProcess {
    fn start(listen: SocketAddr, id: &Identity) -> Self {
        let mut child = Command::new(env!("CARGO_BIN_EXE_holoface-e2e-server"))
            .args([
                listen.to_string(),
                id.cert.display().to_string(),
                id.key.display().to_string(),
            ])
            .current_dir(workspace_root())
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .spawn()
            .unwrap();
        let mut line = String::new();
        BufReader::new(child.stdout.take().unwrap())
            .read_line(&mut line)
            .unwrap();
        let mut parts = line.split_whitespace();
        assert_eq!(parts.next(), Some("ready"), "server did not start: {line:?}");
        let addr = parts.next().unwrap().parse().unwrap();
        let fingerprint = parts.next().unwrap().parse().unwrap();
        Self {
            child,
            addr,
            fingerprint,
        }
    }

    fn kill(mut self) {
        self.child.kill().unwrap();
        let _ = self.child.wait();
    }
}

impl Drop for ServerProcess {
    fn drop(&mut self) {
        if let Some(stdin) = self.child.stdin.as_mut() {
            let _ = stdin.flush();
        }
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

fn free_udp_port() -> SocketAddr {
    std::net::UdpSocket::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
}

/// A real validation face and its ground-truth landmarks (the initial shape of every frame).
fn face() -> (GrayImage, [Point2; 68]) {
    let root = default_data_root().join("faces68/train");
    let mut faces = load_folder(&root, Split::Validation, true).unwrap();
    let s = faces.swap_remove(0);
    (s.image, s.landmarks.unwrap())
}

fn krfws() -> KrfwsAligner {
    let bytes = std::fs::read(workspace_root().join("models/assets/krfws.bin")).unwrap();
    KrfwsAligner::new(holoface_models::krfws::Krfws::from_bytes(&bytes).unwrap())
}

fn linked(addr: SocketAddr, fingerprint: Fingerprint) -> LinkedAligner<KrfwsAligner> {
    let mut cfg = ConnectConfig::new(addr, fingerprint, TEST_TOKEN);
    cfg.idle_timeout = Duration::from_secs(2);
    let backoff = Backoff {
        initial: Duration::from_millis(50),
        max: Duration::from_millis(400),
    };
    // 50 ms: the server's answer (about 20 ms here) fits with room for a loaded CI machine, and a missed
    // frame still answers (deadline + KRFWS) within two frame intervals (66.7 ms).
    let opts = LinkOptions {
        deadline: Duration::from_millis(50),
        ..LinkOptions::default()
    };
    LinkedAligner::new(RemoteLink::start(cfg, backoff).unwrap(), krfws(), opts)
}

/// One paced frame: aligns, returns who answered and how long the answer took.
struct Pacer {
    next: Instant,
}

impl Pacer {
    fn new() -> Self {
        Self { next: Instant::now() }
    }
    fn frame(
        &mut self,
        a: &mut LinkedAligner<KrfwsAligner>,
        img: &GrayImage,
        init: &[Point2; 68],
    ) -> (AnsweredBy, Duration) {
        if let Some(wait) = self.next.checked_duration_since(Instant::now()) {
            std::thread::sleep(wait);
        }
        self.next += FRAME;
        let t = Instant::now();
        let out = a.align(&img.view(), init).expect("every frame gets an answer");
        if std::env::var_os("LINK_DEBUG").is_some() {
            eprintln!("{:?} {:?}", a.last_report(), t.elapsed());
        }
        (out.answered_by, t.elapsed())
    }
}

/// Runs frames until `pred(answered_by)` holds for `n` frames in a row, at most `limit` frames.
fn run_until(
    a: &mut LinkedAligner<KrfwsAligner>,
    p: &mut Pacer,
    img: &GrayImage,
    init: &[Point2; 68],
    by: AnsweredBy,
    n: usize,
    limit: usize,
) -> usize {
    let mut streak = 0;
    for i in 0..limit {
        if p.frame(a, img, init).0 == by {
            streak += 1;
            if streak == n {
                return i + 1;
            }
        } else {
            streak = 0;
        }
    }
    panic!(
        "no {n} frames in a row answered by {by:?} within {limit} frames; link {:?}",
        a.link()
    );
}

#[test]
fn server_kill_falls_back_within_two_frames_and_restart_returns_to_remote() {
    let id = identity("kill");
    let listen = free_udp_port();
    let server = ServerProcess::start(listen, &id);
    let (img, init) = face();
    let mut a = linked(server.addr, server.fingerprint);
    let mut p = Pacer::new();
    // Hold-off (1 s = 30 frames) then remote.
    run_until(&mut a, &mut p, &img, &init, AnsweredBy::RemoteDan, 10, 300);

    server.kill();
    let mut worst = Duration::ZERO;
    let mut by = Vec::new();
    for _ in 0..45 {
        let (who, took) = p.frame(&mut a, &img, &init);
        worst = worst.max(took);
        by.push(who);
    }
    // Printed for BENCHMARKS.md (`--no-capture`).
    eprintln!("after the kill: slowest answer {worst:?}; answered by {by:?}");
    assert!(
        worst <= 2 * FRAME,
        "slowest answer after the kill took {worst:?}, more than two frame intervals"
    );
    let first_local = by.iter().position(|b| *b == AnsweredBy::Krfws).unwrap();
    assert_eq!(
        first_local, 0,
        "the frame that missed is answered locally: {by:?}"
    );
    assert!(by[3..].iter().all(|b| *b == AnsweredBy::Krfws), "{by:?}");
    assert_eq!(a.policy().mode(), Mode::Local);

    let restarted = ServerProcess::start(listen, &id);
    assert_eq!(restarted.fingerprint, server_fingerprint_of(&id));
    run_until(&mut a, &mut p, &img, &init, AnsweredBy::RemoteDan, 10, 600);
    assert!(
        a.link()
            .counters()
            .connects
            .load(std::sync::atomic::Ordering::Relaxed)
            >= 2
    );
}

fn server_fingerprint_of(id: &Identity) -> Fingerprint {
    holoface_alignment_server::tls::ServerIdentity::from_pem_files(&id.cert, &id.key)
        .unwrap()
        .fingerprint
}

#[test]
fn lossy_delaying_relay_falls_back_and_recovers() {
    let id = identity("relay");
    let server = ServerProcess::start(free_udp_port(), &id);
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(1)
        .enable_all()
        .build()
        .unwrap();
    let relay = rt.block_on(UdpRelay::start(server.addr)).unwrap();
    let (img, init) = face();
    let mut a = linked(relay.addr(), server.fingerprint);
    let mut p = Pacer::new();
    run_until(&mut a, &mut p, &img, &init, AnsweredBy::RemoteDan, 10, 300);

    // 40 ms each way: every reply misses the 50 ms deadline; 3 misses in a row fall back.
    relay.faults().set_delay(Duration::from_millis(40));
    relay.faults().set_loss(0.2);
    let mut worst = Duration::ZERO;
    for _ in 0..30 {
        worst = worst.max(p.frame(&mut a, &img, &init).1);
    }
    assert_eq!(a.policy().mode(), Mode::Local, "link {:?}", a.link());
    assert!(worst <= 2 * FRAME, "slowest answer on the bad link: {worst:?}");
    // Stays local while the link is bad (hysteresis: no flapping).
    let switches = a.policy().switches();
    for _ in 0..60 {
        assert_eq!(p.frame(&mut a, &img, &init).0, AnsweredBy::Krfws);
    }
    assert_eq!(a.policy().switches(), switches);

    relay.faults().set_delay(Duration::ZERO);
    relay.faults().set_loss(0.0);
    run_until(&mut a, &mut p, &img, &init, AnsweredBy::RemoteDan, 10, 600);
    let (fwd, dropped) = relay.faults().counts();
    assert!(
        fwd > 0 && dropped > 0,
        "relay saw {fwd} forwarded, {dropped} dropped"
    );
}

/// Polls `link` until `done(status)` holds or `limit` passes; returns the last status.
fn wait_status(link: &RemoteLink, limit: Duration, done: impl Fn(&LinkInfo) -> bool) -> LinkInfo {
    let end = Instant::now() + limit;
    loop {
        let s = link.status();
        if done(&s) || Instant::now() >= end {
            return s;
        }
        std::thread::sleep(Duration::from_millis(20));
    }
}

fn fast_backoff() -> Backoff {
    Backoff {
        initial: Duration::from_millis(50),
        max: Duration::from_millis(200),
    }
}

fn connect_failures(link: &RemoteLink) -> u64 {
    link.counters()
        .connect_failures
        .load(std::sync::atomic::Ordering::Relaxed)
}

/// A wrong token or a certificate that is not the pinned one cannot be fixed by retrying: the link says
/// why and stops (one attempt), instead of retrying forever as if the network were down.
#[test]
fn wrong_token_and_wrong_certificate_fail_once_with_the_reason() {
    let id = identity("auth");
    let server = ServerProcess::start(free_udp_port(), &id);
    let other = server_fingerprint_of(&identity("other"));
    let cases = [
        (
            ConnectConfig::new(server.addr, server.fingerprint, "not-the-token"),
            FailureKind::Unauthorized,
        ),
        (
            ConnectConfig::new(server.addr, other, TEST_TOKEN),
            FailureKind::CertificateMismatch,
        ),
    ];
    for (cfg, kind) in cases {
        let link = RemoteLink::start(cfg, fast_backoff()).unwrap();
        let status = wait_status(&link, Duration::from_secs(10), |s| {
            matches!(s, LinkInfo::Failed(_))
        });
        assert_eq!(status.state(), LinkState::Failed(kind), "{status:?}");
        assert!(!status.failure().unwrap().message.is_empty());
        // Several backoff periods later (at most 200 ms each): still the one attempt. An absence can only be
        // checked after a while; this is the one fixed wait of these tests.
        std::thread::sleep(Duration::from_millis(600));
        assert_eq!(connect_failures(&link), 1, "{kind:?} was retried");
        assert_eq!(link.status().state(), LinkState::Failed(kind));
    }
}

/// Nothing listening: the link reports the server unreachable and keeps retrying (the network may come
/// back), and a linked aligner answers every frame locally with that state in its report.
#[test]
fn unreachable_server_is_reported_and_retried() {
    let mut cfg = ConnectConfig::new(
        free_udp_port(),
        server_fingerprint_of(&identity("none")),
        TEST_TOKEN,
    );
    cfg.connect_timeout = Duration::from_millis(200);
    let link = RemoteLink::start(cfg, fast_backoff()).unwrap();
    let status = wait_status(&link, Duration::from_secs(10), has_failed_once);
    assert_eq!(
        status.state(),
        LinkState::Retrying(FailureKind::Unreachable),
        "{status:?}"
    );
    let failures = wait_status(&link, Duration::from_secs(10), |_| connect_failures(&link) >= 3);
    assert!(connect_failures(&link) >= 3, "not retried: {failures:?}");

    let (img, init) = face();
    let mut a = LinkedAligner::new(link, krfws(), LinkOptions::default());
    let out = a.align(&img.view(), &init).unwrap();
    assert_eq!(out.answered_by, AnsweredBy::Krfws);
    assert_eq!(
        a.last_report().link,
        Some(LinkState::Retrying(FailureKind::Unreachable))
    );
}

fn has_failed_once(s: &LinkInfo) -> bool {
    matches!(s, LinkInfo::Connecting { last_error: Some(_) })
}
