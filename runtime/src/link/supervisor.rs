//! When the link reconnects, how long it waits and when it gives up: an IO-free state machine, like
//! [`super::policy`].
//!
//! The link thread (`super::supervise`) does the IO (QUIC connection attempts, serving a connection, sleeping)
//! and reports each outcome here; the supervisor never reads a clock (every failure carries its `now`) and
//! answers with the link's new status and what to do next:
//!
//! * a connection is up: the status is `Up` and the next failure waits the initial backoff again;
//! * an attempt failed or a connection ended, and retrying can help: the status is `Connecting` with the
//!   failure, and the next attempt is due after the current delay, which then doubles up to the maximum;
//! * retrying cannot help (wrong token, certificate mismatch, protocol version: [`FailureKind::is_permanent`]),
//!   or the client endpoint itself could not be opened: the status is `Failed` and the link stops;
//! * whether a failure is worth a warning: only when its kind differs from the previous one, so a link that
//!   keeps failing the same way (an unreachable server, every 2 s) is not logged on every retry.

use std::sync::Arc;
use std::time::{Duration, Instant};

use holoface_protocol::ServerWelcome;

use super::{Backoff, FailureKind, LinkError, LinkFailure, LinkInfo};

/// What the link thread does after a failure.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Next {
    /// Try to connect again at this instant (`after` from the failure).
    RetryAt {
        /// When.
        at: Instant,
        /// The wait from the failure.
        after: Duration,
    },
    /// Stop: retrying cannot help. Every frame is answered locally from now on.
    GiveUp,
}

/// The supervisor's answer to a failure.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Decision {
    /// What to do next.
    pub next: Next,
    /// The failure is of the same kind as the previous one (log it quietly).
    pub repeated: bool,
}

/// The link's reconnection state (see the module docs).
#[derive(Debug)]
pub struct Supervisor {
    backoff: Backoff,
    delay: Duration,
    last_kind: Option<FailureKind>,
    status: LinkInfo,
}

impl Supervisor {
    /// A link about to make its first attempt (`Connecting`, no failure yet).
    pub fn new(backoff: Backoff) -> Self {
        Self {
            backoff,
            delay: backoff.initial,
            last_kind: None,
            status: LinkInfo::Connecting { last_error: None },
        }
    }

    /// The link's status.
    pub fn status(&self) -> &LinkInfo {
        &self.status
    }

    /// The client endpoint (the UDP socket, TLS) could not be opened: nothing to retry with.
    pub fn cannot_start(&mut self, failure: LinkFailure) {
        self.last_kind = Some(failure.kind);
        self.status = LinkInfo::Failed(failure);
    }

    /// A connection is up (handshake done): the backoff starts over.
    pub fn connected(&mut self, welcome: Arc<ServerWelcome>) {
        self.delay = self.backoff.initial;
        self.status = LinkInfo::Up(super::ServerInfo::new(welcome));
    }

    /// A connection attempt failed, or an established connection ended, at `now`.
    pub fn failed(&mut self, now: Instant, failure: LinkFailure) -> Decision {
        let repeated = self.last_kind == Some(failure.kind);
        self.last_kind = Some(failure.kind);
        if failure.kind.is_permanent() {
            self.status = LinkInfo::Failed(failure);
            return Decision {
                next: Next::GiveUp,
                repeated,
            };
        }
        let after = self.delay;
        self.delay = (self.delay * 2).min(self.backoff.max);
        self.status = LinkInfo::Connecting {
            last_error: Some(failure),
        };
        Decision {
            next: Next::RetryAt {
                at: now + after,
                after,
            },
            repeated,
        }
    }

    /// The owner shut the link down.
    pub fn stopped(&mut self) {
        self.status = LinkInfo::Stopped;
    }
}

/// How an established connection ended: a timeout there is the connection going silent (idle timeout), not
/// an unreachable server.
pub fn established_failure(e: LinkError) -> LinkFailure {
    let mut f = e.failure();
    if f.kind == FailureKind::Unreachable {
        f.kind = FailureKind::ConnectionLost;
    }
    f
}

#[cfg(test)]
mod tests {
    use super::*;

    fn unreachable() -> LinkFailure {
        LinkFailure::new(FailureKind::Unreachable, "timed out after 2s")
    }

    fn welcome() -> Arc<ServerWelcome> {
        Arc::new(ServerWelcome {
            version: holoface_protocol::PROTOCOL_VERSION,
            model_id: "dan".into(),
            model_version: "0.4.0".into(),
            landmark_count: 68,
            crop_size: 112,
            mean_shape: Vec::new(),
            face_threshold: 0.5,
            encoding: holoface_protocol::CropEncoding::Jpeg,
            reply_channel: holoface_protocol::ReplyChannel::Datagram,
            max_in_flight: 4,
            max_frame_age_ms: 100,
        })
    }

    #[test]
    fn retries_double_from_the_initial_delay_up_to_the_maximum() {
        let mut s = Supervisor::new(Backoff::default());
        let t0 = Instant::now();
        let mut now = t0;
        let mut waits = Vec::new();
        for _ in 0..7 {
            let d = s.failed(now, unreachable());
            let Next::RetryAt { at, after } = d.next else {
                panic!("{d:?}: an unreachable server is retried")
            };
            assert_eq!(at, now + after);
            waits.push(after.as_millis());
            now = at;
        }
        assert_eq!(waits, [100, 200, 400, 800, 1600, 2000, 2000]);
        assert_eq!(now - t0, Duration::from_millis(7100));
        assert!(matches!(
            s.status(),
            LinkInfo::Connecting { last_error: Some(f) } if f.kind == FailureKind::Unreachable
        ));
    }

    #[test]
    fn a_connection_starts_the_backoff_over() {
        let mut s = Supervisor::new(Backoff::default());
        let t0 = Instant::now();
        for _ in 0..4 {
            s.failed(t0, unreachable());
        }
        s.connected(welcome());
        assert!(s.status().welcome().is_some());
        let lost = LinkFailure::new(FailureKind::ConnectionLost, "idle timeout");
        let d = s.failed(t0 + Duration::from_secs(60), lost);
        assert_eq!(
            d.next,
            Next::RetryAt {
                at: t0 + Duration::from_secs(60) + Duration::from_millis(100),
                after: Duration::from_millis(100)
            }
        );
    }

    #[test]
    fn failures_retrying_cannot_fix_stop_the_link() {
        for kind in [
            FailureKind::Unauthorized,
            FailureKind::CertificateMismatch,
            FailureKind::BadVersion,
        ] {
            let mut s = Supervisor::new(Backoff::default());
            let d = s.failed(Instant::now(), LinkFailure::new(kind, "no"));
            assert_eq!(d.next, Next::GiveUp, "{kind}");
            assert!(
                matches!(s.status(), LinkInfo::Failed(f) if f.kind == kind),
                "{kind}"
            );
        }
        for kind in [
            FailureKind::ServerFull,
            FailureKind::ShuttingDown,
            FailureKind::Protocol,
            FailureKind::Local,
        ] {
            let mut s = Supervisor::new(Backoff::default());
            let d = s.failed(Instant::now(), LinkFailure::new(kind, "later"));
            assert!(matches!(d.next, Next::RetryAt { .. }), "{kind} is retried");
        }
        let mut s = Supervisor::new(Backoff::default());
        s.cannot_start(LinkFailure::new(FailureKind::Local, "no UDP socket"));
        assert!(matches!(s.status(), LinkInfo::Failed(f) if f.kind == FailureKind::Local));
        s.stopped();
        assert!(matches!(s.status(), LinkInfo::Stopped));
    }

    #[test]
    fn only_a_new_kind_of_failure_is_loud() {
        let mut s = Supervisor::new(Backoff::default());
        let t = Instant::now();
        let full = || LinkFailure::new(FailureKind::ServerFull, "at its client limit");
        let repeats: Vec<bool> = [unreachable(), unreachable(), full(), full(), unreachable()]
            .into_iter()
            .map(|f| s.failed(t, f).repeated)
            .collect();
        assert_eq!(repeats, [false, true, false, true, false]);
    }

    #[test]
    fn an_established_connection_that_goes_silent_is_lost_not_unreachable() {
        let f = established_failure(LinkError::Timeout(Duration::from_secs(3)));
        assert_eq!(f.kind, FailureKind::ConnectionLost);
        let f = established_failure(LinkError::Protocol("early end of stream".into()));
        assert_eq!(f.kind, FailureKind::Protocol);
    }
}
