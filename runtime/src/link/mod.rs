//! The remote link: crops to the alignment server over QUIC, with local fallback.
//!
//! * [`connection`]: one connection (handshake, frame streams, replies), async; shared with the load tester.
//! * [`RemoteLink`]: owns a background thread with a single-threaded tokio runtime that keeps a
//!   connection up (reconnecting with exponential backoff) and gives the frame loop a blocking API:
//!   [`RemoteLink::send`] and [`RemoteLink::wait_until`] with a deadline.
//! * [`policy`]: the IO-free fallback state machine (misses, hold-off, hysteresis).
//! * [`supervisor`]: the IO-free reconnection state machine (backoff, giving up, which failures to warn
//!   about); the link thread below only does what it says.
//! * [`LinkedAligner`]: an [`crate::align::Aligner`] that asks the server first and answers the **same
//!   frame** with the local aligner when the reply misses its deadline or the link is down.
//! * [`CropCodec`] (from [`crate::crop_codec`]): raw / PNG / JPEG crops.

mod aligner;

pub mod connection;
pub mod policy;
mod remote;
pub mod supervisor;

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, PoisonError, mpsc};
use std::time::{Duration, Instant};

use holoface_protocol::{CloseCode, FrameReply, FrameRequest, ServerWelcome};
use tokio::sync::{mpsc as tmpsc, oneshot};

pub use crate::crop_codec::CropCodec;
pub use aligner::{LinkOptions, LinkReport, LinkedAligner};
pub use connection::{ConnectConfig, FailureKind, LinkError, LinkFailure};
pub use policy::{FallbackPolicy, Mode, PolicyConfig, Route};
pub use remote::{MAX_DEADLINE, RemoteOptions, RemoteOptionsError, RemoteStartError};

/// Reconnection backoff: `initial`, doubling up to `max`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Backoff {
    /// First retry delay.
    pub initial: Duration,
    /// Largest retry delay.
    pub max: Duration,
}

impl Default for Backoff {
    fn default() -> Self {
        Self {
            initial: Duration::from_millis(100),
            max: Duration::from_secs(2),
        }
    }
}

/// State of the link as the frame loop sees it.
#[derive(Clone, Debug)]
pub enum LinkInfo {
    /// Connecting or waiting to retry; the last failure, if any.
    Connecting {
        /// Why the previous attempt or connection ended.
        last_error: Option<LinkFailure>,
    },
    /// Handshake done; frames may be sent.
    Up(ServerInfo),
    /// The link gave up: retrying cannot help (wrong token, certificate mismatch, protocol version) or the
    /// UDP socket could not be opened. Every frame is answered locally.
    Failed(LinkFailure),
    /// The link was shut down by its owner.
    Stopped,
}

/// The server a link is up to, as its welcome said.
#[derive(Clone, Debug)]
pub struct ServerInfo(Arc<ServerWelcome>);

impl ServerInfo {
    pub(crate) fn new(welcome: Arc<ServerWelcome>) -> Self {
        Self(welcome)
    }

    /// The alignment model the server runs (its identifier, e.g. `holoface-dan`).
    pub fn model_id(&self) -> &str {
        &self.0.model_id
    }

    /// The alignment model's version.
    pub fn model_version(&self) -> &str {
        &self.0.model_version
    }

    /// The protocol version the server speaks.
    pub fn protocol_version(&self) -> u16 {
        self.0.version
    }

    /// Frames the client may have in flight at once.
    pub fn max_in_flight(&self) -> u16 {
        self.0.max_in_flight
    }
}

impl LinkInfo {
    /// The server's welcome when the link is up (the aligner cuts its crops by it).
    pub(crate) fn welcome(&self) -> Option<&Arc<ServerWelcome>> {
        match self {
            Self::Up(w) => Some(&w.0),
            _ => None,
        }
    }

    /// The compact, copyable form for per-frame results and the C ABI.
    pub fn state(&self) -> LinkState {
        match self {
            Self::Connecting { last_error: None } => LinkState::Connecting,
            Self::Connecting { last_error: Some(f) } => LinkState::Retrying(f.kind),
            Self::Up(_) => LinkState::Up,
            Self::Failed(f) => LinkState::Failed(f.kind),
            Self::Stopped => LinkState::Stopped,
        }
    }

    /// Why the link is not up, if it has failed at least once.
    pub fn failure(&self) -> Option<&LinkFailure> {
        match self {
            Self::Connecting { last_error } => last_error.as_ref(),
            Self::Failed(f) => Some(f),
            Self::Up(_) | Self::Stopped => None,
        }
    }
}

/// [`LinkInfo`] without the welcome and the message: what each frame's result carries.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case", tag = "state", content = "failure")]
pub enum LinkState {
    /// First connection attempt under way.
    Connecting,
    /// Connected.
    Up,
    /// Down for this reason; retrying with backoff.
    Retrying(FailureKind),
    /// Gave up for this reason (see [`FailureKind::is_permanent`]).
    Failed(FailureKind),
    /// Shut down.
    Stopped,
}

/// Something the link thread observed.
#[derive(Debug)]
pub enum LinkEvent {
    /// A reply and when it arrived.
    Reply(FrameReply, Instant),
    /// The connection ended (a reconnect follows unless the failure is permanent).
    Down(Instant, LinkFailure),
}

/// Why [`RemoteLink::wait_until`] returned before its caller was done.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum WaitError {
    /// The deadline passed.
    #[error("deadline missed")]
    Deadline,
    /// The connection went down while waiting.
    #[error("link down: {0}")]
    Down(LinkFailure),
    /// The link thread is gone.
    #[error("link stopped")]
    Stopped,
}

/// Counters of a link (monotonic).
#[derive(Debug, Default)]
pub struct LinkCounters {
    /// Frames handed to the link.
    pub frames_sent: AtomicU64,
    /// HoloFace message bytes sent (frame requests only).
    pub payload_bytes: AtomicU64,
    /// UDP bytes sent over all connections (QUIC and TLS overhead included).
    pub udp_tx_bytes: AtomicU64,
    /// UDP bytes received over all connections.
    pub udp_rx_bytes: AtomicU64,
    /// Successful handshakes.
    pub connects: AtomicU64,
    /// Failed connection attempts.
    pub connect_failures: AtomicU64,
}

struct Shared {
    status: Mutex<LinkInfo>,
    counters: LinkCounters,
    current: Mutex<Option<quinn::Connection>>,
}

impl Shared {
    fn set(&self, s: LinkInfo) {
        *self.status.lock().unwrap_or_else(PoisonError::into_inner) = s;
    }

    fn get(&self) -> LinkInfo {
        self.status.lock().unwrap_or_else(PoisonError::into_inner).clone()
    }
}

/// A connection to the alignment server kept up by a background thread.
///
/// Thread-safety: the handle is `Send` and used from one frame loop; the background thread is private.
/// Dropping the handle closes the connection (`NoError`) and joins the thread.
pub struct RemoteLink {
    frames: tmpsc::UnboundedSender<FrameRequest>,
    events: mpsc::Receiver<LinkEvent>,
    shared: Arc<Shared>,
    shutdown: Option<oneshot::Sender<()>>,
    thread: Option<std::thread::JoinHandle<()>>,
}

impl std::fmt::Debug for RemoteLink {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("RemoteLink")
            .field("status", &self.status())
            .finish_non_exhaustive()
    }
}

impl RemoteLink {
    /// Starts the link thread; it connects in the background (check [`Self::status`]).
    pub fn start(cfg: ConnectConfig, backoff: Backoff) -> std::io::Result<Self> {
        let (frames, frames_rx) = tmpsc::unbounded_channel();
        let (events_tx, events) = mpsc::channel();
        let (shutdown, shutdown_rx) = oneshot::channel();
        let shared = Arc::new(Shared {
            status: Mutex::new(LinkInfo::Connecting { last_error: None }),
            counters: LinkCounters::default(),
            current: Mutex::new(None),
        });
        let runtime = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()?;
        let thread_shared = Arc::clone(&shared);
        let thread = std::thread::Builder::new()
            .name("holoface-link".into())
            .spawn(move || {
                let end = runtime.block_on(supervise(
                    cfg,
                    backoff,
                    frames_rx,
                    events_tx,
                    &thread_shared,
                    shutdown_rx,
                ));
                thread_shared.set(end);
            })?;
        Ok(Self {
            frames,
            events,
            shared,
            shutdown: Some(shutdown),
            thread: Some(thread),
        })
    }

    /// The current status.
    pub fn status(&self) -> LinkInfo {
        self.shared.get()
    }

    /// A handle that reads this link's status from anywhere (it stays valid after the link is moved into
    /// a [`LinkedAligner`]).
    pub fn watch(&self) -> LinkWatch {
        LinkWatch {
            shared: Arc::clone(&self.shared),
        }
    }

    /// Counters since start.
    pub fn counters(&self) -> &LinkCounters {
        &self.shared.counters
    }

    /// UDP bytes (sent, received) over all connections so far, the live one included.
    pub fn udp_bytes(&self) -> (u64, u64) {
        let c = &self.shared.counters;
        let (mut tx, mut rx) = (
            c.udp_tx_bytes.load(Ordering::Relaxed),
            c.udp_rx_bytes.load(Ordering::Relaxed),
        );
        if let Some(conn) = self
            .shared
            .current
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .as_ref()
        {
            let s = conn.stats();
            tx += s.udp_tx.bytes;
            rx += s.udp_rx.bytes;
        }
        (tx, rx)
    }

    /// Queues a frame for sending (never blocks). Frames queued while the link is down are discarded.
    pub fn send(&self, req: FrameRequest) -> Result<(), WaitError> {
        self.frames.send(req).map_err(|_| WaitError::Stopped)
    }

    /// Hands every event to `each` until it returns `true` (`Ok`), the deadline passes
    /// ([`WaitError::Deadline`]) or the link thread is gone ([`WaitError::Stopped`]). The frame loop waits
    /// this way for all the faces of one frame at once.
    pub fn wait_until(
        &self,
        deadline: Instant,
        each: &mut dyn FnMut(LinkEvent) -> bool,
    ) -> Result<(), WaitError> {
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            match self.events.recv_timeout(left) {
                Ok(ev) => {
                    if each(ev) {
                        return Ok(());
                    }
                }
                Err(mpsc::RecvTimeoutError::Timeout) => return Err(WaitError::Deadline),
                Err(mpsc::RecvTimeoutError::Disconnected) => return Err(WaitError::Stopped),
            }
        }
    }

    /// Events that arrived since the last call (non-blocking).
    pub fn drain(&self, mut each: impl FnMut(LinkEvent)) {
        while let Ok(ev) = self.events.try_recv() {
            each(ev);
        }
    }
}

/// Reads a [`RemoteLink`]'s status (see [`RemoteLink::watch`]); cheap to clone.
#[derive(Clone)]
pub struct LinkWatch {
    shared: Arc<Shared>,
}

impl std::fmt::Debug for LinkWatch {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("LinkWatch")
            .field("status", &self.status())
            .finish()
    }
}

impl LinkWatch {
    /// The link's current status.
    pub fn status(&self) -> LinkInfo {
        self.shared.get()
    }
}

/// What [`LinkedAligner`] needs from a link: [`RemoteLink`] in the headset, a scripted link in unit tests.
pub trait Link {
    /// Where the link stands (the server's welcome when up).
    fn status(&self) -> LinkInfo;
    /// Queues a frame for sending (never blocks).
    fn send(&self, req: FrameRequest) -> Result<(), WaitError>;
    /// Hands every event to `each` until it returns `true`, the deadline passes
    /// ([`WaitError::Deadline`]) or the link is gone ([`WaitError::Stopped`]).
    fn wait_until(&self, deadline: Instant, each: &mut dyn FnMut(LinkEvent) -> bool)
    -> Result<(), WaitError>;
    /// Events that arrived since the last call (non-blocking).
    fn drain(&self, each: &mut dyn FnMut(LinkEvent));
}

impl Link for RemoteLink {
    fn status(&self) -> LinkInfo {
        Self::status(self)
    }
    fn send(&self, req: FrameRequest) -> Result<(), WaitError> {
        Self::send(self, req)
    }
    fn wait_until(
        &self,
        deadline: Instant,
        each: &mut dyn FnMut(LinkEvent) -> bool,
    ) -> Result<(), WaitError> {
        Self::wait_until(self, deadline, each)
    }
    fn drain(&self, each: &mut dyn FnMut(LinkEvent)) {
        Self::drain(self, each);
    }
}

/// Where the frame loop's time comes from: the system clock in the headset, a made-up one in tests.
pub trait Clock {
    /// The current instant.
    fn now(&self) -> Instant;
}

/// [`Instant::now`].
#[derive(Clone, Copy, Debug, Default)]
pub struct SystemClock;

impl Clock for SystemClock {
    fn now(&self) -> Instant {
        Instant::now()
    }
}

impl Drop for RemoteLink {
    fn drop(&mut self) {
        if let Some(tx) = self.shutdown.take() {
            let _ = tx.send(());
        }
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

/// The link thread: connect, serve, reconnect, until shut down or until a failure that retrying cannot fix
/// ([`supervisor::Supervisor`] decides; this function does the IO and the logging). Returns the final status.
async fn supervise(
    cfg: ConnectConfig,
    backoff: Backoff,
    mut frames: tmpsc::UnboundedReceiver<FrameRequest>,
    events: mpsc::Sender<LinkEvent>,
    shared: &Shared,
    mut shutdown: oneshot::Receiver<()>,
) -> LinkInfo {
    let mut sup = supervisor::Supervisor::new(backoff);
    let endpoint = match connection::client_endpoint(&cfg) {
        Ok(e) => e,
        Err(e) => {
            let failure = LinkFailure::new(
                FailureKind::Local,
                format!("cannot open the client endpoint: {e}"),
            );
            tracing::warn!(server = %cfg.server, error = %failure, "alignment server link failed; answering locally");
            sup.cannot_start(failure);
            return sup.status().clone();
        }
    };
    let mut gave_up = false;
    loop {
        let attempt = tokio::select! {
            _ = &mut shutdown => break,
            r = connection::connect(&endpoint, &cfg) => r,
        };
        let (failure, established) = match attempt {
            Ok(s) => {
                shared.counters.connects.fetch_add(1, Ordering::Relaxed);
                let (conn, welcome, control, replies) = s.split();
                tracing::info!(server = %cfg.server, model = %holoface_protocol::untrusted(&welcome.model_version), encoding = ?welcome.encoding, "link up");
                // Frames queued while down are stale.
                while frames.try_recv().is_ok() {}
                *shared.current.lock().unwrap_or_else(PoisonError::into_inner) = Some(conn.clone());
                sup.connected(Arc::new(welcome));
                shared.set(sup.status().clone());
                let end = serve(
                    &conn,
                    control,
                    replies,
                    &mut frames,
                    &events,
                    shared,
                    &mut shutdown,
                )
                .await;
                shared
                    .current
                    .lock()
                    .unwrap_or_else(PoisonError::into_inner)
                    .take();
                let stats = conn.stats();
                shared
                    .counters
                    .udp_tx_bytes
                    .fetch_add(stats.udp_tx.bytes, Ordering::Relaxed);
                shared
                    .counters
                    .udp_rx_bytes
                    .fetch_add(stats.udp_rx.bytes, Ordering::Relaxed);
                let Some(failure) = end else {
                    conn.close(CloseCode::NoError.as_u32().into(), b"client shutting down");
                    break;
                };
                let _ = events.send(LinkEvent::Down(Instant::now(), failure.clone()));
                (failure, true)
            }
            Err(e) => {
                shared.counters.connect_failures.fetch_add(1, Ordering::Relaxed);
                (e.failure(), false)
            }
        };
        let decision = sup.failed(Instant::now(), failure.clone());
        let supervisor::Next::RetryAt { at, after } = decision.next else {
            tracing::warn!(server = %cfg.server, error = %failure,
                "giving up on the alignment server: retrying cannot fix this; answering locally");
            gave_up = true;
            break;
        };
        if established {
            tracing::warn!(server = %cfg.server, error = %failure, "link down; answering locally");
        } else if decision.repeated {
            tracing::debug!(error = %failure, retry_in = ?after, "connect failed again");
        } else {
            tracing::warn!(server = %cfg.server, error = %failure, retry_in = ?after,
                "cannot connect to the alignment server; answering locally");
        }
        shared.set(sup.status().clone());
        tokio::select! {
            _ = &mut shutdown => break,
            () = tokio::time::sleep_until(at.into()) => {}
        }
        while frames.try_recv().is_ok() {}
    }
    if !gave_up {
        sup.stopped();
    }
    // Let the close frame go out.
    let _ = tokio::time::timeout(Duration::from_millis(200), endpoint.wait_idle()).await;
    sup.status().clone()
}

/// Serves one connection. `None` = shut down by us; `Some(failure)` = the connection ended.
async fn serve(
    conn: &quinn::Connection,
    mut control: connection::Control,
    mut replies: connection::ReplyReader,
    frames: &mut tmpsc::UnboundedReceiver<FrameRequest>,
    events: &mpsc::Sender<LinkEvent>,
    shared: &Shared,
    shutdown: &mut oneshot::Receiver<()>,
) -> Option<LinkFailure> {
    let reader_events = events.clone();
    let mut reader = tokio::spawn(async move {
        loop {
            match replies.next().await {
                Ok(r) => {
                    if reader_events.send(LinkEvent::Reply(r, Instant::now())).is_err() {
                        return LinkFailure::new(FailureKind::Local, "frame loop gone");
                    }
                }
                Err(e) => return supervisor::established_failure(e),
            }
        }
    });
    let end = loop {
        tokio::select! {
            _ = &mut *shutdown => break None,
            f = frames.recv() => match f {
                Some(req) => {
                    let conn = conn.clone();
                    shared.counters.frames_sent.fetch_add(1, Ordering::Relaxed);
                    // One task per frame: a slow stream never holds up the next frame.
                    let len = holoface_protocol::Message::FrameRequest(req.clone()).encoded_len();
                    shared.counters.payload_bytes.fetch_add(len as u64, Ordering::Relaxed);
                    tokio::spawn(async move {
                        if let Err(e) = connection::send_frame(&conn, &req).await {
                            tracing::debug!(frame = req.frame_id, error = %e, "send failed");
                        }
                    });
                }
                None => break None,
            },
            r = &mut reader => break Some(r.unwrap_or_else(|e| {
                LinkFailure::new(FailureKind::Local, format!("reply reader failed: {e}"))
            })),
            c = control.next() => if let Err(e) = c { break Some(supervisor::established_failure(e)) },
            e = conn.closed() => break Some(supervisor::established_failure(LinkError::from(e))),
        }
    };
    reader.abort();
    end
}
