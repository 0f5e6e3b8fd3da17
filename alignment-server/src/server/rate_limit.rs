//! The per-connection frame-rate limit.

use std::time::Instant;

/// A token bucket over frames: `rate` per second, a burst of `rate`
/// (one second's worth). Sans-IO: the caller passes `now`.
#[derive(Debug, Clone, Copy)]
pub(super) struct RateLimit {
    rate: f64,
    tokens: f64,
    last: Instant,
}

impl RateLimit {
    /// `rate == 0` means unlimited.
    pub(super) fn new(rate: u32, now: Instant) -> Self {
        Self {
            rate: f64::from(rate),
            tokens: f64::from(rate),
            last: now,
        }
    }

    /// Takes one token; `false` when the client is over its rate.
    pub(super) fn take(&mut self, now: Instant) -> bool {
        if self.rate <= 0.0 {
            return true;
        }
        let elapsed = now.saturating_duration_since(self.last).as_secs_f64();
        self.last = now;
        self.tokens = (self.tokens + elapsed * self.rate).min(self.rate);
        if self.tokens >= 1.0 {
            self.tokens -= 1.0;
            true
        } else {
            false
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    #[test]
    fn rate_limit_allows_a_burst_then_the_rate() {
        let t0 = Instant::now();
        let mut r = RateLimit::new(10, t0);
        assert!((0..10).all(|_| r.take(t0)), "one second of burst");
        assert!(!r.take(t0), "then empty");
        assert!(r.take(t0 + Duration::from_millis(100)), "refills at 10/s");
        assert!(!r.take(t0 + Duration::from_millis(100)));
        // 30 fps forever is fine under a 240/s limit.
        let mut r = RateLimit::new(240, t0);
        assert!((0..3000_u32).all(|i| r.take(t0 + Duration::from_millis(33) * i)));
        let mut unlimited = RateLimit::new(0, t0);
        assert!((0..10_000).all(|_| unlimited.take(t0)));
    }
}
