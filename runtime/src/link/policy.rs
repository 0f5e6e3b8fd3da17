//! When to use the remote aligner and when to fall back: an IO-free state machine.
//!
//! The policy never reads a clock; every event carries its `now`. States:
//!
//! * **Remote**: frames go to the server. A reply within the deadline resets the miss counter; a missed
//!   deadline (or a `Dropped` reply) counts as a miss, and `max_misses` in a row, or the link going down,
//!   switch to Local at once. The frame that missed is aligned locally by the caller, so it still gets an
//!   answer.
//! * **Local**: frames are aligned on the headset. While the link is up the caller also sends each crop to
//!   the server as a *probe* (the reply is not used, only its timeliness). The policy switches back once
//!   probes have answered in time continuously for `hold_off` and at least `min_probe_answers` times: one
//!   late or lost probe restarts the hold-off. This hysteresis keeps a flaky link from flapping.

use std::time::{Duration, Instant};

/// Settings of the fallback policy.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct PolicyConfig {
    /// Missed deadlines in a row that switch Remote to Local.
    pub max_misses: u32,
    /// How long probes must answer in time before switching back to Remote.
    pub hold_off: Duration,
    /// Minimum number of timely probe answers within the hold-off.
    pub min_probe_answers: u32,
}

impl Default for PolicyConfig {
    fn default() -> Self {
        Self {
            max_misses: 3,
            hold_off: Duration::from_secs(1),
            min_probe_answers: 10,
        }
    }
}

/// Which aligner the policy currently prefers.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Mode {
    /// The server's DAN over QUIC.
    Remote,
    /// The headset's KRFWS.
    Local,
}

/// What to do with the current frame.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Route {
    /// Send the crop and wait for the reply until the deadline; align locally if it does not come.
    Remote,
    /// Align locally; when `probe`, also send the crop to measure the link.
    Local {
        /// Send a probe crop.
        probe: bool,
    },
}

/// The fallback state machine (see the module docs).
#[derive(Clone, Debug)]
pub struct FallbackPolicy {
    cfg: PolicyConfig,
    mode: Mode,
    misses: u32,
    healthy_since: Option<Instant>,
    probe_answers: u32,
    switches: u32,
}

impl FallbackPolicy {
    /// Starts in Local mode: the link has to prove itself first (the same hold-off as a recovery).
    pub fn new(cfg: PolicyConfig) -> Self {
        Self {
            cfg,
            mode: Mode::Local,
            misses: 0,
            healthy_since: None,
            probe_answers: 0,
            switches: 0,
        }
    }

    /// The current mode.
    pub fn mode(&self) -> Mode {
        self.mode
    }

    /// How many times the mode changed.
    pub fn switches(&self) -> u32 {
        self.switches
    }

    /// Routes the next frame; `link_up` is whether a connection with a completed handshake exists.
    pub fn route(&mut self, now: Instant, link_up: bool) -> Route {
        if !link_up {
            self.on_link_down(now);
            return Route::Local { probe: false };
        }
        match self.mode {
            Mode::Remote => Route::Remote,
            Mode::Local => Route::Local { probe: true },
        }
    }

    /// A remote reply (frame or probe) arrived within its deadline.
    pub fn on_answer(&mut self, now: Instant) {
        match self.mode {
            Mode::Remote => self.misses = 0,
            Mode::Local => {
                let since = *self.healthy_since.get_or_insert(now);
                self.probe_answers += 1;
                if self.probe_answers >= self.cfg.min_probe_answers
                    && now.saturating_duration_since(since) >= self.cfg.hold_off
                {
                    self.set_mode(Mode::Remote);
                }
            }
        }
    }

    /// A remote frame or probe missed its deadline or was dropped by the server.
    pub fn on_miss(&mut self, _now: Instant) {
        match self.mode {
            Mode::Remote => {
                self.misses += 1;
                if self.misses >= self.cfg.max_misses {
                    self.set_mode(Mode::Local);
                }
            }
            Mode::Local => {
                self.healthy_since = None;
                self.probe_answers = 0;
            }
        }
    }

    /// The connection is gone: Local at once.
    pub fn on_link_down(&mut self, _now: Instant) {
        self.healthy_since = None;
        self.probe_answers = 0;
        if self.mode == Mode::Remote {
            self.set_mode(Mode::Local);
        }
    }

    fn set_mode(&mut self, mode: Mode) {
        if self.mode != mode {
            self.mode = mode;
            self.switches += 1;
        }
        self.misses = 0;
        self.healthy_since = None;
        self.probe_answers = 0;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const FRAME: Duration = Duration::from_millis(33);

    fn at(t0: Instant, frame: u32) -> Instant {
        t0 + FRAME * frame
    }

    /// Drives the policy with a healthy link until it reaches Remote; returns the frame index it switched at.
    fn warm_up(p: &mut FallbackPolicy, t0: Instant) -> u32 {
        for f in 0..1000 {
            match p.route(at(t0, f), true) {
                Route::Remote => return f,
                Route::Local { probe } => {
                    assert!(probe);
                    p.on_answer(at(t0, f));
                }
            }
        }
        panic!("never switched to remote");
    }

    #[test]
    fn starts_local_and_switches_after_the_hold_off() {
        let t0 = Instant::now();
        let mut p = FallbackPolicy::new(PolicyConfig::default());
        assert_eq!(p.mode(), Mode::Local);
        let f = warm_up(&mut p, t0);
        // 1 s of answers at 33 ms = frame 31 (first answer at frame 0 starts the clock).
        assert_eq!(f, 32);
        assert_eq!(p.switches(), 1);
    }

    #[test]
    fn three_misses_in_a_row_fall_back_two_do_not() {
        let t0 = Instant::now();
        let mut p = FallbackPolicy::new(PolicyConfig::default());
        let mut f = warm_up(&mut p, t0);
        p.on_miss(at(t0, f));
        p.on_miss(at(t0, f + 1));
        p.on_answer(at(t0, f + 2));
        p.on_miss(at(t0, f + 3));
        p.on_miss(at(t0, f + 4));
        assert_eq!(p.mode(), Mode::Remote);
        f += 5;
        p.on_miss(at(t0, f));
        assert_eq!(p.mode(), Mode::Local);
        assert_eq!(p.route(at(t0, f + 1), true), Route::Local { probe: true });
    }

    #[test]
    fn link_down_falls_back_immediately_without_probes() {
        let t0 = Instant::now();
        let mut p = FallbackPolicy::new(PolicyConfig::default());
        let f = warm_up(&mut p, t0);
        assert_eq!(p.route(at(t0, f + 1), false), Route::Local { probe: false });
        assert_eq!(p.mode(), Mode::Local);
    }

    #[test]
    fn a_flaky_link_does_not_flap() {
        // Every 20th probe is lost: the hold-off (30 frames) never completes, so the client stays local.
        let t0 = Instant::now();
        let mut p = FallbackPolicy::new(PolicyConfig::default());
        for f in 0..2000 {
            assert_eq!(p.route(at(t0, f), true), Route::Local { probe: true });
            if f % 20 == 19 {
                p.on_miss(at(t0, f));
            } else {
                p.on_answer(at(t0, f));
            }
        }
        assert_eq!(p.switches(), 0);
    }

    #[test]
    fn recovery_needs_enough_answers_not_just_time() {
        // Two answers 2 s apart satisfy the hold-off duration but not the answer count.
        let t0 = Instant::now();
        let mut p = FallbackPolicy::new(PolicyConfig::default());
        p.on_answer(t0);
        p.on_answer(t0 + Duration::from_secs(2));
        assert_eq!(p.mode(), Mode::Local);
    }
}
