//! What the run measured: per-interval rows while it runs (throughput, latency percentiles, drops, deadline
//! misses, the server's resident memory), then the totals over the measured window, the SLO verdict, the
//! JSON results and the latency plot.

use std::collections::HashMap;
use std::net::SocketAddr;
use std::sync::{Arc, Mutex, PoisonError};
use std::time::{Duration, Instant};

use anyhow::Context;
use hdrhistogram::Histogram;
use holoface_harness::plot::{Series, series_plot_png};
use holoface_process::stop::{Signal, Stop};
use serde_json::json;

use crate::Args;

/// Frames counted over a window (one report interval) or the whole measured run.
#[derive(Default)]
pub(crate) struct Counts {
    /// Frames sent.
    pub(crate) sent: u64,
    /// Frames answered with landmarks.
    pub(crate) answered: u64,
    /// Answers later than the deadline.
    pub(crate) misses: u64,
    /// Frames the server dropped, by reason.
    pub(crate) dropped: HashMap<&'static str, u64>,
    /// Frames that fell due while the headset had no connection (the server was unreachable).
    pub(crate) unsent: u64,
}

/// The share of the frames that fell due (sent, or unsendable while the server was unreachable) that got
/// landmarks. A frame the server dropped was not answered: a server that drops everything answers 0.
/// (Replies to frames sent in the warm-up can land in the totals: at most everything was answered.)
pub(crate) fn answered_fraction(answered: u64, sent: u64, unsent: u64) -> f64 {
    let due = sent + unsent;
    if due == 0 {
        return 0.0;
    }
    (answered as f64 / due as f64).min(1.0)
}

/// A time a headset had no connection to the server.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Outage {
    /// Which headset.
    pub(crate) headset: usize,
    /// When the connection broke.
    pub(crate) at: Instant,
    /// How long until it reconnected; `None` when the run ended first.
    pub(crate) length: Option<Duration>,
}

/// What every headset records into, and the report reads out.
pub(crate) struct Stats {
    /// Latencies of the current interval, µs.
    pub(crate) interval: Histogram<u64>,
    /// Latencies after the warm-up, µs.
    pub(crate) total: Histogram<u64>,
    /// Counts of the current interval.
    pub(crate) window: Counts,
    /// Counts after the warm-up.
    pub(crate) totals: Counts,
    /// Whether the warm-up is over.
    pub(crate) measuring: bool,
    /// Headsets that stopped sending because the server said Goaway.
    pub(crate) goaways: u64,
    /// Every time a headset lost its connection.
    pub(crate) outages: Vec<Outage>,
}

impl Stats {
    pub(crate) fn new() -> anyhow::Result<Self> {
        Ok(Self {
            interval: Histogram::new_with_bounds(1, 60_000_000, 3)?,
            total: Histogram::new_with_bounds(1, 60_000_000, 3)?,
            window: Counts::default(),
            totals: Counts::default(),
            measuring: false,
            goaways: 0,
            outages: Vec::new(),
        })
    }

    /// Applies `f` to the interval's counts and, once measuring, to the totals.
    pub(crate) fn each(&mut self, f: impl Fn(&mut Counts)) {
        f(&mut self.window);
        if self.measuring {
            f(&mut self.totals);
        }
    }
}

/// Resident memory of process `pid` (this one when `None`), KiB.
fn rss_kib(pid: Option<u32>) -> Option<u64> {
    let path = pid.map_or_else(|| "/proc/self/status".to_owned(), |p| format!("/proc/{p}/status"));
    let text = std::fs::read_to_string(path).ok()?;
    let line = text.lines().find(|l| l.starts_with("VmRSS:"))?;
    line.split_whitespace().nth(1)?.parse().ok()
}

/// The measurement window and what was sampled over it.
pub(crate) struct Measured {
    /// When the headsets started (outages are reported from here).
    t0: Instant,
    /// One row per report interval.
    timeline: Vec<serde_json::Value>,
    /// Resident memory at the end of the warm-up and at the last interval, KiB.
    rss: (Option<u64>, Option<u64>),
    /// Length of the measured window (shorter when every headset left on the server's Goaway, or when a
    /// signal ended the test).
    duration: Duration,
    /// The signal that ended the test early, if one did (the report covers the time it ran).
    pub(crate) stopped_by: Option<Signal>,
}

/// The run's clock: headsets start at `t0`, measuring starts after `warmup` and stops at `end`.
#[derive(Clone, Copy)]
pub(crate) struct Window {
    pub(crate) t0: Instant,
    pub(crate) warmup: Duration,
    pub(crate) duration: Duration,
    pub(crate) end: Instant,
}

/// Prints one row per `interval_s` until the window ends (or every headset has left on a Goaway), sampling
/// the resident memory of `rss_pid` (`Some(u32::MAX)`: none; `None`: this process).
pub(crate) fn monitor(
    stats: &Mutex<Stats>,
    window: &Window,
    interval_s: f64,
    rss_pid: Option<u32>,
    tasks: &[tokio::task::JoinHandle<anyhow::Result<()>>],
    stop: &Stop,
) -> Measured {
    let Window {
        t0,
        warmup,
        mut duration,
        end,
    } = *window;
    let rss = move || {
        if rss_pid == Some(u32::MAX) {
            None
        } else {
            rss_kib(rss_pid)
        }
    };
    println!(
        "{:>7} {:>8} {:>8} {:>8} {:>8} {:>8} {:>7} {:>7} {:>9}",
        "t s", "sent/s", "ok/s", "p50 ms", "p99 ms", "p999 ms", "drops", "misses", "rss MiB"
    );
    let mut timeline = Vec::new();
    let (mut rss_start, mut rss_end) = (None, None);
    let interval = Duration::from_secs_f64(interval_s);
    let mut next = t0 + interval;
    let warm_at = t0 + warmup;
    let mut warmed = false;
    while next <= end + interval / 2 {
        // The totals cover exactly [t0 + warm-up, end), whatever the report interval.
        if !warmed && warm_at < next {
            std::thread::sleep(warm_at.saturating_duration_since(Instant::now()));
            stats.lock().unwrap_or_else(PoisonError::into_inner).measuring = true;
            rss_start = rss();
            warmed = true;
        }
        // Sleep to the row's time in short steps: Ctrl-C or SIGTERM ends the test with a report of the time it ran.
        while Instant::now() < next && stop.requested().is_none() {
            std::thread::sleep(
                next.saturating_duration_since(Instant::now())
                    .min(Duration::from_millis(50)),
            );
        }
        if stop.requested().is_some() {
            let mut s = stats.lock().unwrap_or_else(PoisonError::into_inner);
            s.measuring = false;
            duration = if warmed {
                Instant::now().saturating_duration_since(warm_at).min(duration)
            } else {
                Duration::ZERO
            };
            break;
        }
        let now_rss = rss();
        rss_end = now_rss;
        let mut s = stats.lock().unwrap_or_else(PoisonError::into_inner);
        let secs = interval.as_secs_f64();
        let ms = |q: f64, h: &Histogram<u64>| h.value_at_quantile(q) as f64 / 1e3;
        let drops: u64 = s.window.dropped.values().sum();
        let row = json!({
            "t_s": next.duration_since(t0).as_secs_f64(),
            "sent_per_s": s.window.sent as f64 / secs, "answered_per_s": s.window.answered as f64 / secs,
            "p50_ms": ms(0.5, &s.interval), "p99_ms": ms(0.99, &s.interval), "p999_ms": ms(0.999, &s.interval),
            "drops": drops, "misses": s.window.misses, "rss_kib": now_rss,
        });
        println!(
            "{:>7.1} {:>8.1} {:>8.1} {:>8.2} {:>8.2} {:>8.2} {:>7} {:>7} {:>9}",
            next.duration_since(t0).as_secs_f64(),
            s.window.sent as f64 / secs,
            s.window.answered as f64 / secs,
            ms(0.5, &s.interval),
            ms(0.99, &s.interval),
            ms(0.999, &s.interval),
            drops,
            s.window.misses,
            now_rss.map_or("-".to_owned(), |k| format!("{:.1}", k as f64 / 1024.0)),
        );
        timeline.push(row);
        s.interval.reset();
        s.window = Counts::default();
        let all_left = s.goaways > 0 && tasks.iter().all(tokio::task::JoinHandle::is_finished);
        drop(s);
        next += interval;
        if all_left {
            // Every headset left on the server's Goaway: the run is over early.
            duration = Instant::now().saturating_duration_since(warm_at).min(duration);
            break;
        }
    }
    Measured {
        t0,
        timeline,
        rss: (rss_start, rss_end),
        duration,
        stopped_by: stop.requested(),
    }
}

/// What the measured window adds up to.
struct Summary {
    secs: f64,
    dropped: u64,
    lost: u64,
    throughput: f64,
    drop_rate: f64,
    answered_fraction: f64,
    /// RSS growth over the window, %.
    growth: Option<f64>,
    /// Latency p50, p99, p999, ms.
    p50: f64,
    p99: f64,
    p999: f64,
}

impl Summary {
    fn of(s: &Stats, duration: Duration, rss: (Option<u64>, Option<u64>)) -> Self {
        let secs = duration.as_secs_f64();
        let dropped: u64 = s.totals.dropped.values().sum();
        let lost = s.totals.sent.saturating_sub(s.totals.answered + dropped);
        let p = |q: f64| s.total.value_at_quantile(q) as f64 / 1e3;
        Self {
            secs,
            dropped,
            lost,
            throughput: s.totals.answered as f64 / secs,
            drop_rate: (dropped + lost) as f64 / s.totals.sent.max(1) as f64,
            answered_fraction: answered_fraction(s.totals.answered, s.totals.sent, s.totals.unsent),
            growth: match rss {
                (Some(a), Some(b)) if a > 0 => Some(100.0 * (b as f64 - a as f64) / a as f64),
                _ => None,
            },
            p50: p(0.5),
            p99: p(0.99),
            p999: p(0.999),
        }
    }
}

/// The service levels `args` set that the run broke, in words.
fn broken_slos(args: &Args, s: &Stats, m: &Summary) -> Vec<String> {
    let (dropped, lost) = (m.dropped, m.lost);
    let mut broken = Vec::new();
    if let Some(limit) = args.max_p99_ms.filter(|&limit| m.p99 > limit) {
        broken.push(format!("p99 {:.2} ms > {limit} ms", m.p99));
    }
    if args.min_answered > 0.0 && m.answered_fraction < args.min_answered {
        broken.push(format!(
            "answered {:.3} of the frames < {} ({dropped} dropped by the server, {lost} sent frames got no answer, \
             {} could not be sent while the server was unreachable)",
            m.answered_fraction, args.min_answered, s.totals.unsent
        ));
    }
    if s.totals.answered == 0 && s.totals.sent + s.totals.unsent > 0 {
        broken.push(format!(
            "no frame was answered ({} sent, {dropped} dropped by the server, {} unsent)",
            s.totals.sent, s.totals.unsent
        ));
    }
    if let Some(limit) = args.max_drop_rate.filter(|&limit| m.drop_rate > limit) {
        broken.push(format!("drop rate {:.4} > {limit}", m.drop_rate));
    }
    if let Some(limit) = args.min_throughput.filter(|&limit| m.throughput < limit) {
        broken.push(format!("throughput {:.1}/s < {limit}/s", m.throughput));
    }
    if let Some(limit) = args.max_rss_growth_pct {
        match m.growth {
            Some(g) if g > limit => broken.push(format!("RSS grew {g:.2} % > {limit} %")),
            None => broken.push("RSS growth SLO set but RSS could not be sampled".to_owned()),
            _ => {}
        }
    }
    broken
}

/// Totals over the measured window, the SLO verdict (`Ok(false)`: broken), the JSON results and the plot.
pub(crate) fn finish(
    args: &Args,
    stats: &Arc<Mutex<Stats>>,
    measured: Measured,
    server: SocketAddr,
    stagger: Duration,
) -> anyhow::Result<bool> {
    let Measured {
        t0,
        timeline,
        rss: (rss_start, rss_end),
        duration,
        stopped_by,
    } = measured;
    let s = stats.lock().unwrap_or_else(PoisonError::into_inner);
    let m = Summary::of(&s, duration, (rss_start, rss_end));
    let (secs, dropped, lost) = (m.secs, m.dropped, m.lost);
    let outages: Vec<serde_json::Value> = s
        .outages
        .iter()
        .map(|o| {
            json!({
                "headset": o.headset,
                "at_s": o.at.saturating_duration_since(t0).as_secs_f64(),
                "length_s": o.length.map(|l| l.as_secs_f64()),
                "recovered": o.length.is_some(),
            })
        })
        .collect();
    let broken = broken_slos(args, &s, &m);
    let report = json!({
        "config": {
            "clients": args.clients, "fps": args.fps, "duration_s": args.duration_s, "warmup_s": args.warmup_s,
            "deadline_ms": args.deadline_ms, "stagger_ms": stagger.as_secs_f64() * 1e3,
            "recordings": args.recordings, "server": server.to_string(), "spawned_server": args.spawn_server,
        },
        "totals": {
            "sent": s.totals.sent, "answered": s.totals.answered, "dropped": s.totals.dropped,
            "unanswered": lost, "deadline_misses": s.totals.misses, "throughput_per_s": m.throughput,
            "drop_rate": m.drop_rate, "headsets_told_goaway": s.goaways,
            "unsent": s.totals.unsent, "answered_fraction": m.answered_fraction,
            "latency_ms": {"p50": m.p50, "p99": m.p99, "p999": m.p999, "max": s.total.max() as f64 / 1e3,
                           "mean": s.total.mean() / 1e3},
        },
        "rss_kib": {"start": rss_start, "end": rss_end, "growth_pct": m.growth},
        "timeline": timeline,
        "outages": outages,
        "slo": {"broken": broken},
        // A signal ended the test early: the totals cover the `measured_s` it ran.
        "interrupted": stopped_by.map(Signal::name),
        "measured_s": secs,
    });
    if let Some(sig) = stopped_by {
        println!(
            "interrupted by {} after {secs:.1} s of measurement: the report covers that time",
            sig.name()
        );
    }
    println!(
        "total: {} sent, {} unsent, {} answered ({:.1}/s), {dropped} dropped, {lost} unanswered, {} deadline \
         misses; latency p50 {:.2} p99 {:.2} p999 {:.2} ms; RSS growth {}",
        s.totals.sent,
        s.totals.unsent,
        s.totals.answered,
        m.throughput,
        s.totals.misses,
        m.p50,
        m.p99,
        m.p999,
        m.growth.map_or("n/a".to_owned(), |g| format!("{g:.2} %"))
    );
    write_report(args, &report)?;
    if s.goaways > 0 {
        println!(
            "{} of {} headsets stopped early on the server's Goaway",
            s.goaways, args.clients
        );
    }
    for o in &s.outages {
        let at = o.at.saturating_duration_since(t0).as_secs_f64();
        match o.length {
            Some(l) => eprintln!(
                "outage: headset {} without a server from {at:.1} s for {:.2} s",
                o.headset,
                l.as_secs_f64()
            ),
            None => eprintln!(
                "outage: headset {} without a server from {at:.1} s to the end of the run",
                o.headset
            ),
        }
    }
    for b in &broken {
        eprintln!("SLO broken: {b}");
    }
    Ok(broken.is_empty())
}

/// Writes the JSON results to `--out` and the latency plot over time to `--plot`.
fn write_report(args: &Args, report: &serde_json::Value) -> anyhow::Result<()> {
    for path in [&args.out, &args.plot] {
        if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
            std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
        }
    }
    let temporaries = holoface_sources::output::Temporaries::new();
    holoface_sources::output::write_atomic(&args.out, serde_json::to_string_pretty(report)?, &temporaries)?;
    let series = |key: &str, label: &str| Series {
        label: label.to_owned(),
        points: report["timeline"]
            .as_array()
            .into_iter()
            .flatten()
            .filter_map(|r| Some((r["t_s"].as_f64()?, r[key].as_f64()?)))
            .collect(),
    };
    let png = series_plot_png(
        &[
            series("p50_ms", "p50"),
            series("p99_ms", "p99"),
            series("p999_ms", "p999"),
        ],
        "time s",
        "latency ms",
    );
    holoface_sources::output::write_atomic(&args.plot, png, &holoface_sources::output::Temporaries::new())?;
    println!("wrote {} and {}", args.out.display(), args.plot.display());
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::answered_fraction;

    #[test]
    fn dropped_frames_are_not_answers() {
        // 100 frames due, the server dropped every one: nothing was answered.
        assert_eq!(answered_fraction(0, 100, 0), 0.0);
        // Unsent frames (server unreachable) count as due.
        assert!((answered_fraction(45, 80, 20) - 0.45).abs() < 1e-12);
        // Warm-up replies cannot push it past 1; nothing due is nothing answered.
        assert_eq!(answered_fraction(12, 10, 0), 1.0);
        assert_eq!(answered_fraction(0, 0, 0), 0.0);
    }
}
