//! The misbehaving-client log, bounded: a flood of bad clients (wrong tokens, garbage datagrams, no hello)
//! must not grow the log as fast as they connect. Per close code, the first [`BURST`] closes of each
//! [`WINDOW`] get a line each, with their client's address and detail; the rest are counted, and one line
//! sums them up when the window ends (on the next close of that code, or on the server's periodic flush, so
//! the tail of a flood is reported too). The metrics count every close whatever the log says. Sans-IO: the
//! caller passes `now`.

use std::collections::HashMap;
use std::time::{Duration, Instant};

use holoface_protocol::CloseCode;

/// Closes of one code logged one line each per window.
pub(super) const BURST: u32 = 5;
/// The window over which [`BURST`] applies.
pub(super) const WINDOW: Duration = Duration::from_secs(10);

/// Closes of one code that were not logged one by one in a window that has ended.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) struct Suppressed {
    pub(super) code: CloseCode,
    pub(super) count: u64,
}

#[derive(Debug, Clone, Copy)]
struct Window {
    start: Instant,
    logged: u32,
    suppressed: u64,
}

/// Which closes the log shows one by one.
#[derive(Debug, Default)]
pub(super) struct LogThrottle {
    windows: HashMap<CloseCode, Window>,
}

impl LogThrottle {
    /// Whether this close of `code` gets a line of its own, and the summary of this code's previous window
    /// when it ended with closes left out.
    pub(super) fn admit(&mut self, code: CloseCode, now: Instant) -> (bool, Option<Suppressed>) {
        let mut ended = None;
        let w = self.windows.entry(code).or_insert(Window {
            start: now,
            logged: 0,
            suppressed: 0,
        });
        if now.saturating_duration_since(w.start) >= WINDOW {
            if w.suppressed > 0 {
                ended = Some(Suppressed {
                    code,
                    count: w.suppressed,
                });
            }
            *w = Window {
                start: now,
                logged: 0,
                suppressed: 0,
            };
        }
        if w.logged < BURST {
            w.logged += 1;
            (true, ended)
        } else {
            w.suppressed += 1;
            (false, ended)
        }
    }

    /// The summaries of the windows that have ended by `now` with closes left out (each reported once).
    pub(super) fn flush(&mut self, now: Instant) -> Vec<Suppressed> {
        let mut out = Vec::new();
        self.windows.retain(|&code, w| {
            let ended = now.saturating_duration_since(w.start) >= WINDOW;
            if ended && w.suppressed > 0 {
                out.push(Suppressed {
                    code,
                    count: w.suppressed,
                });
            }
            !ended
        });
        out.sort_by_key(|s| s.code.as_u32());
        out
    }

    /// Every window's closes left out so far, ended or not (at shutdown, so that the log accounts for every
    /// close).
    pub(super) fn drain(&mut self) -> Vec<Suppressed> {
        let mut out: Vec<_> = self
            .windows
            .drain()
            .filter(|(_, w)| w.suppressed > 0)
            .map(|(code, w)| Suppressed {
                code,
                count: w.suppressed,
            })
            .collect();
        out.sort_by_key(|s| s.code.as_u32());
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_flood_gets_a_burst_of_lines_then_one_summary_per_window() {
        let t0 = Instant::now();
        let mut t = LogThrottle::default();
        let mut lines = 0;
        // 1,000 wrong tokens in 10 s (the probe), then one more after the window.
        for k in 0..1_000u32 {
            let (log, ended) = t.admit(
                CloseCode::Unauthorized,
                t0 + Duration::from_millis(u64::from(k) * 9),
            );
            lines += u32::from(log);
            assert_eq!(ended, None);
        }
        assert_eq!(lines, BURST);
        // Another code has its own burst.
        assert!(t.admit(CloseCode::Malformed, t0).0);
        let (log, ended) = t.admit(CloseCode::Unauthorized, t0 + WINDOW);
        assert!(log, "a new window starts with a line");
        assert_eq!(
            ended,
            Some(Suppressed {
                code: CloseCode::Unauthorized,
                count: 1_000 - u64::from(BURST)
            })
        );
    }

    #[test]
    fn the_tail_of_a_flood_is_reported_by_the_flush_and_only_once() {
        let t0 = Instant::now();
        let mut t = LogThrottle::default();
        for k in 0..(BURST + 3) {
            t.admit(CloseCode::Unauthorized, t0 + Duration::from_millis(u64::from(k)));
        }
        for k in 0..BURST {
            t.admit(CloseCode::BadVersion, t0 + Duration::from_millis(u64::from(k)));
        }
        assert!(t.flush(t0 + WINDOW / 2).is_empty(), "the window has not ended");
        assert_eq!(
            t.flush(t0 + WINDOW),
            vec![Suppressed {
                code: CloseCode::Unauthorized,
                count: 3
            }],
            "BadVersion stayed within its burst: nothing to sum up"
        );
        assert!(t.flush(t0 + WINDOW * 3).is_empty());
        t.admit(CloseCode::Malformed, t0 + WINDOW * 3);
        assert!(t.drain().is_empty(), "within its burst");
        // A quiet code starts over with its burst; at shutdown what a window left out so far is summed up.
        for k in 0..=BURST {
            let (log, ended) = t.admit(CloseCode::Unauthorized, t0 + WINDOW * 4);
            assert_eq!((log, ended), (k < BURST, None));
        }
        assert_eq!(
            t.drain(),
            vec![Suppressed {
                code: CloseCode::Unauthorized,
                count: 1
            }]
        );
    }
}
