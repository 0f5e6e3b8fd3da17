//! `--link-cuts`: a link schedule in media time for `holoface track` and `holoface stability`. The remote
//! aligner talks to its server through a loopback relay ([`holoface_harness::relay::UdpRelay`], the demo's) that drops
//! every datagram while the frame being tracked lies inside a cut, so a clip run remote shows the local
//! answers (and their adaptation) where a real link would have dropped. The link itself runs on the wall
//! clock (connecting, its hold-off after a loss, its backoff, the deadlines), so the frames are fed at their
//! own timestamps ([`Pacer`]), as a camera's come: a file or pipe read faster than real time would otherwise
//! see the link recover after far more media time than a headset would, and by how much would depend on how
//! fast the machine decodes.

use std::net::SocketAddr;
use std::str::FromStr;
use std::time::{Duration, Instant};

use holoface_harness::relay::UdpRelay;

/// Cuts of the link, each `(start, length)` in seconds of media time from the first frame.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct LinkCuts(Vec<(f64, f64)>);

impl FromStr for LinkCuts {
    type Err = String;

    /// `START:LENGTH[,START:LENGTH...]` in seconds, e.g. `20:10,60:10` (cut at 20 s for 10 s, at 60 s for
    /// 10 s); cuts in order and apart.
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        let mut cuts: Vec<(f64, f64)> = Vec::new();
        for part in s.split(',') {
            let (start, len) = part
                .split_once(':')
                .ok_or_else(|| format!("{part:?}: expected START:LENGTH in seconds"))?;
            let num = |v: &str| {
                v.trim()
                    .parse::<f64>()
                    .ok()
                    .filter(|v| v.is_finite() && *v >= 0.0)
                    .ok_or_else(|| format!("{part:?}: {v:?} is not a number of seconds >= 0"))
            };
            let (start, len) = (num(start)?, num(len)?);
            if len <= 0.0 {
                return Err(format!("{part:?}: a cut lasts more than 0 s"));
            }
            if let Some(&(s0, l0)) = cuts.last()
                && start < s0 + l0
            {
                return Err(format!(
                    "{part:?}: starts before the previous cut ends ({} s)",
                    s0 + l0
                ));
            }
            cuts.push((start, len));
        }
        Ok(Self(cuts))
    }
}

impl LinkCuts {
    /// Whether media time `t` (seconds from the first frame) lies inside a cut.
    pub fn contains(&self, t: f64) -> bool {
        self.0.iter().any(|&(s, l)| t >= s && t < s + l)
    }

    /// The cuts, `(start, length)` in seconds.
    pub fn windows(&self) -> &[(f64, f64)] {
        &self.0
    }
}

/// Feeds frames at their own timestamps, as a camera delivers them: [`Pacer::wait`] returns when the frame's
/// time has come on the wall clock, counted from the first frame. A frame that is already late (the source
/// is live, or the tracker is slower than real time) is not waited for.
#[derive(Debug, Default)]
pub struct Pacer {
    origin: Option<(Instant, u64)>,
    waited: Duration,
}

impl Pacer {
    /// Waits until the frame at `timestamp_us` is due.
    pub fn wait(&mut self, timestamp_us: u64) {
        let (t0, ts0) = *self.origin.get_or_insert((Instant::now(), timestamp_us));
        let due = t0 + Duration::from_micros(timestamp_us.saturating_sub(ts0));
        let wait = due.saturating_duration_since(Instant::now());
        self.waited += wait;
        std::thread::sleep(wait);
    }

    /// How long the frames were held back in all: the time a faster-than-real-time source would have saved.
    pub fn waited(&self) -> Duration {
        self.waited
    }
}

/// A relay in front of a server that cuts the link on [`LinkCuts`]' schedule as frames go by.
#[derive(Debug)]
pub struct CutRelay {
    // Declared before the runtime it runs on, so it is dropped first.
    relay: UdpRelay,
    _rt: tokio::runtime::Runtime,
    cuts: LinkCuts,
    origin_us: Option<u64>,
}

impl CutRelay {
    /// Starts relaying to `upstream` on its own thread.
    pub fn start(upstream: SocketAddr, cuts: LinkCuts) -> anyhow::Result<Self> {
        let rt = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(1)
            .thread_name("holoface-cut-relay")
            .enable_all()
            .build()?;
        let relay = rt.block_on(UdpRelay::start(upstream))?;
        Ok(Self {
            relay,
            _rt: rt,
            cuts,
            origin_us: None,
        })
    }

    /// Where the client connects instead of the server.
    pub fn addr(&self) -> SocketAddr {
        self.relay.addr()
    }

    /// Cuts or restores the link for the frame at `timestamp_us` (media time counts from the first frame
    /// seen); whether it is cut.
    pub fn at(&mut self, timestamp_us: u64) -> bool {
        let origin = *self.origin_us.get_or_insert(timestamp_us);
        let cut = self
            .cuts
            .contains(timestamp_us.saturating_sub(origin) as f64 * 1e-6);
        self.relay.faults().set_cut(cut);
        cut
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_pacer_holds_frames_until_their_time_and_never_waits_for_a_late_one() {
        let mut p = Pacer::default();
        let t0 = Instant::now();
        p.wait(1_000_000);
        p.wait(1_030_000);
        p.wait(1_060_000);
        assert!(t0.elapsed() >= Duration::from_millis(60), "{:?}", t0.elapsed());
        // A frame already late: no wait.
        std::thread::sleep(Duration::from_millis(50));
        let before = p.waited();
        p.wait(1_070_000);
        assert_eq!(p.waited(), before);
    }

    #[test]
    fn schedules_parse_and_say_what_is_wrong() {
        let c: LinkCuts = "20:10,60:10".parse().unwrap();
        assert_eq!(c.windows(), &[(20.0, 10.0), (60.0, 10.0)]);
        assert!(!c.contains(19.99) && c.contains(20.0) && c.contains(29.9) && !c.contains(30.0));
        assert!(c.contains(65.0) && !c.contains(75.0));
        let c: LinkCuts = "0.5:1.5".parse().unwrap();
        assert!(c.contains(1.0) && !c.contains(2.0));
        for (bad, says) in [
            ("20", "START:LENGTH"),
            ("x:1", "not a number"),
            ("-1:2", "not a number"),
            ("5:0", "more than 0 s"),
            ("10:5,12:3", "before the previous cut ends"),
            ("inf:1", "not a number"),
        ] {
            let e = bad.parse::<LinkCuts>().unwrap_err();
            assert!(e.contains(says), "{bad}: {e}");
        }
    }
}
