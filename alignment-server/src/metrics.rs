//! Server metrics: lock-free atomics updated by the session and batcher
//! layers, rendered as Prometheus text by the internal listener
//! ([`crate::metrics_http`]).

use std::fmt::Write as _;
use std::sync::atomic::{AtomicBool, AtomicI64, AtomicU64, Ordering};
use std::time::Duration;

use holoface_inference::{Execution, ModelInfo};
use holoface_protocol::{CloseCode, DropReason};

/// A Prometheus histogram with fixed upper bounds, in integer units.
#[derive(Debug)]
pub struct Histogram {
    bounds: Vec<u64>,
    buckets: Vec<AtomicU64>,
    sum: AtomicU64,
    count: AtomicU64,
}

impl Histogram {
    /// A histogram with the given ascending upper bounds (`+Inf` is implicit).
    pub fn new(bounds: &[u64]) -> Self {
        Self {
            bounds: bounds.to_vec(),
            buckets: bounds.iter().map(|_| AtomicU64::new(0)).collect(),
            sum: AtomicU64::new(0),
            count: AtomicU64::new(0),
        }
    }

    /// Records one value.
    pub fn observe(&self, value: u64) {
        if let Some(i) = self.bounds.iter().position(|b| value <= *b)
            && let Some(bucket) = self.buckets.get(i)
        {
            bucket.fetch_add(1, Ordering::Relaxed);
        }
        self.sum.fetch_add(value, Ordering::Relaxed);
        self.count.fetch_add(1, Ordering::Relaxed);
    }

    /// Records a duration in microseconds.
    pub fn observe_duration(&self, d: Duration) {
        self.observe(u64::try_from(d.as_micros()).unwrap_or(u64::MAX));
    }

    /// Number of values recorded.
    pub fn count(&self) -> u64 {
        self.count.load(Ordering::Relaxed)
    }

    /// Sum of values recorded.
    pub fn sum(&self) -> u64 {
        self.sum.load(Ordering::Relaxed)
    }

    /// Writes `name_bucket`, `name_sum`, `name_count`; values are divided by
    /// `scale` (1e6 turns microseconds into seconds).
    fn render(&self, out: &mut String, name: &str, help: &str, scale: f64) {
        let _ = writeln!(out, "# HELP {name} {help}\n# TYPE {name} histogram");
        let mut cumulative = 0;
        for (bound, bucket) in self.bounds.iter().zip(&self.buckets) {
            cumulative += bucket.load(Ordering::Relaxed);
            let le = *bound as f64 / scale;
            let _ = writeln!(out, "{name}_bucket{{le=\"{le}\"}} {cumulative}");
        }
        let count = self.count();
        let _ = writeln!(out, "{name}_bucket{{le=\"+Inf\"}} {count}");
        let _ = writeln!(out, "{name}_sum {}", self.sum() as f64 / scale);
        let _ = writeln!(out, "{name}_count {count}");
    }
}

const LATENCY_BOUNDS_US: &[u64] = &[
    100, 250, 500, 1_000, 2_500, 5_000, 10_000, 25_000, 50_000, 100_000, 250_000, 500_000, 1_000_000,
];

/// Every metric the server exports.
#[derive(Debug)]
pub struct Metrics {
    /// Clients currently connected (past the cap check).
    pub connected_clients: AtomicI64,
    /// Connections accepted by QUIC.
    pub connections_total: AtomicU64,
    /// Clients rejected for a wrong protocol version.
    pub auth_bad_version: AtomicU64,
    /// Clients rejected for a missing or wrong token.
    pub auth_unauthorized: AtomicU64,
    /// Connections refused because the client cap was reached.
    pub rejected_overloaded: AtomicU64,
    /// Connections without an authenticated hello yet (TLS under way or no hello).
    pub pending_connections: AtomicI64,
    /// Pending connections evicted for a newer one at the pending budget.
    pub pending_evicted: AtomicU64,
    /// Connection attempts answered with a QUIC Retry (address validation).
    pub pending_retries: AtomicU64,
    /// Connections the server closed, by close code.
    pub closed_by_code: [AtomicU64; CloseCode::ALL.len()],
    /// Frame requests decoded.
    pub frames_received: AtomicU64,
    /// Frames answered with landmarks.
    pub frames_aligned: AtomicU64,
    /// Frames answered `Dropped`, by reason.
    pub drops: [AtomicU64; DropReason::ALL.len()],
    /// Frames whose model output was unusable (non-finite, or shaped against the model's declaration).
    pub model_output_errors: AtomicU64,
    /// Frames in each inference batch.
    pub batch_size: Histogram,
    /// Time from arrival to batch formation, microseconds.
    pub queue_wait_us: Histogram,
    /// Engine time per batch, microseconds.
    pub inference_us: Histogram,
    /// Refinement-cascade time per crop refined, microseconds.
    pub refine_us: Histogram,
    /// Inference calls that failed.
    pub inference_errors: AtomicU64,
    /// Clients' QUIC round-trip time, sampled every few seconds, microseconds.
    pub client_rtt_us: Histogram,
    /// Packets the server sent to clients that QUIC declared lost.
    pub client_lost_packets: AtomicU64,
    /// Frames waiting in the batcher (the autoscaling signal).
    pub queued_frames: AtomicI64,
    /// The engine is loaded and the endpoint accepts clients.
    pub ready: AtomicBool,
    /// Shutdown has started.
    pub draining: AtomicBool,
    /// The `holoface_engine_info` labels, set once the engine is loaded.
    engine_info: std::sync::OnceLock<String>,
}

/// A Prometheus label value: backslash, double quote and newline escaped.
fn label_value(v: &str) -> String {
    v.replace('\\', "\\\\").replace('"', "\\\"").replace('\n', "\\n")
}

impl Metrics {
    /// Zeroed metrics; `max_batch` sizes the batch histogram.
    pub fn new(max_batch: usize) -> Self {
        let mut bounds: Vec<u64> = [1_u64, 2, 4, 8, 16, 32, 64, 128, 256]
            .into_iter()
            .filter(|b| *b < max_batch as u64)
            .collect();
        bounds.push(max_batch as u64);
        Self {
            connected_clients: AtomicI64::new(0),
            queued_frames: AtomicI64::new(0),
            connections_total: AtomicU64::new(0),
            auth_bad_version: AtomicU64::new(0),
            auth_unauthorized: AtomicU64::new(0),
            rejected_overloaded: AtomicU64::new(0),
            pending_connections: AtomicI64::new(0),
            pending_evicted: AtomicU64::new(0),
            pending_retries: AtomicU64::new(0),
            closed_by_code: std::array::from_fn(|_| AtomicU64::new(0)),
            frames_received: AtomicU64::new(0),
            frames_aligned: AtomicU64::new(0),
            drops: std::array::from_fn(|_| AtomicU64::new(0)),
            batch_size: Histogram::new(&bounds),
            queue_wait_us: Histogram::new(LATENCY_BOUNDS_US),
            inference_us: Histogram::new(LATENCY_BOUNDS_US),
            refine_us: Histogram::new(LATENCY_BOUNDS_US),
            inference_errors: AtomicU64::new(0),
            model_output_errors: AtomicU64::new(0),
            client_rtt_us: Histogram::new(LATENCY_BOUNDS_US),
            client_lost_packets: AtomicU64::new(0),
            ready: AtomicBool::new(false),
            draining: AtomicBool::new(false),
            engine_info: std::sync::OnceLock::new(),
        }
    }

    /// Records what the server runs, for `holoface_engine_info` (the first call wins): the model and its
    /// precision, the CPU's int8 instructions (`cpu_int8`: `avx512_vnni`, `avx_vnni` or `none`, which decided
    /// `engine.precision = "auto"`), the provider; `refiner` is the refinement cascade's identity (`none` when off).
    pub fn set_engine_info(
        &self,
        model: &ModelInfo,
        execution: &Execution,
        instances: usize,
        refiner: Option<&str>,
    ) {
        let _ = self.engine_info.set(format!(
            "model=\"{}\",version=\"{}\",precision=\"{}\",cpu_int8=\"{}\",provider=\"{}\",fallback=\"{}\",instances=\"{instances}\",refiner=\"{}\"",
            label_value(&model.name),
            label_value(&model.version),
            label_value(&model.precision),
            holoface_inference::CpuInt8::detect().label(),
            label_value(&execution.provider),
            execution.fallback.is_some(),
            label_value(refiner.unwrap_or("none")),
        ));
    }

    /// Counts a dropped frame.
    pub fn count_drop(&self, reason: DropReason) {
        if let Some(c) = self.drops.get(usize::from(reason.as_u8())) {
            c.fetch_add(1, Ordering::Relaxed);
        }
    }

    /// Dropped frames for one reason so far.
    pub fn drops_for(&self, reason: DropReason) -> u64 {
        self.drops
            .get(usize::from(reason.as_u8()))
            .map_or(0, |c| c.load(Ordering::Relaxed))
    }

    /// Counts a connection the server closed with `code`.
    pub fn count_close(&self, code: CloseCode) {
        if let Some(c) = usize::try_from(code.as_u32())
            .ok()
            .and_then(|i| self.closed_by_code.get(i))
        {
            c.fetch_add(1, Ordering::Relaxed);
        }
    }

    /// Connections closed with `code` so far.
    pub fn closes_for(&self, code: CloseCode) -> u64 {
        usize::try_from(code.as_u32())
            .ok()
            .and_then(|i| self.closed_by_code.get(i))
            .map_or(0, |c| c.load(Ordering::Relaxed))
    }

    /// `true` when `/health` should answer 200.
    pub fn healthy(&self) -> bool {
        self.ready.load(Ordering::Relaxed) && !self.draining.load(Ordering::Relaxed)
    }

    /// The Prometheus text exposition (format 0.0.4).
    pub fn render(&self) -> String {
        let mut out = String::with_capacity(4096);
        self.render_connections(&mut out);
        self.render_frames(&mut out);
        out
    }

    /// The engine, the connections and the handshakes.
    fn render_connections(&self, out: &mut String) {
        if let Some(labels) = self.engine_info.get() {
            let _ = writeln!(
                out,
                "# HELP holoface_engine_info The model, its precision and the ONNX Runtime execution provider \
                 running it (fallback=\"true\": the requested GPU provider could not run; cpu_int8: the CPU's \
                 8-bit dot products, which engine.precision = auto reads; the log says why).\n\
                 # TYPE holoface_engine_info gauge\nholoface_engine_info{{{labels}}} 1"
            );
        }
        gauge(
            out,
            "holoface_connected_clients",
            "Clients currently connected.",
            self.connected_clients.load(Ordering::Relaxed),
        );
        gauge(
            out,
            "holoface_pending_connections",
            "Connections without an authenticated hello yet (they hold no client slot).",
            self.pending_connections.load(Ordering::Relaxed),
        );
        gauge(
            out,
            "holoface_queued_frames",
            "Frames waiting in the batcher for inference (scale out when it stays above zero).",
            self.queued_frames.load(Ordering::Relaxed),
        );
        gauge(
            out,
            "holoface_ready",
            "1 when the engine is loaded and clients are accepted.",
            i64::from(self.healthy()),
        );
        counter(
            out,
            "holoface_connections_total",
            "QUIC connections accepted.",
            load(&self.connections_total),
        );
        counter(
            out,
            "holoface_rejected_overloaded_total",
            "Connections refused at the client cap.",
            load(&self.rejected_overloaded),
        );
        counter(
            out,
            "holoface_pending_evicted_total",
            "Unauthenticated connections evicted for a newer one at the pending budget.",
            load(&self.pending_evicted),
        );
        counter(
            out,
            "holoface_pending_retries_total",
            "Connection attempts answered with a QUIC Retry (address validation under pressure).",
            load(&self.pending_retries),
        );
        let _ = writeln!(
            out,
            "# HELP holoface_auth_failures_total Clients rejected during the handshake.\n\
             # TYPE holoface_auth_failures_total counter\n\
             holoface_auth_failures_total{{reason=\"bad_version\"}} {}\n\
             holoface_auth_failures_total{{reason=\"unauthorized\"}} {}",
            load(&self.auth_bad_version),
            load(&self.auth_unauthorized)
        );
        let _ = writeln!(
            out,
            "# HELP holoface_connections_closed_total Connections closed by the server, by close code.\n\
             # TYPE holoface_connections_closed_total counter"
        );
        for code in CloseCode::ALL {
            let _ = writeln!(
                out,
                "holoface_connections_closed_total{{code=\"{}\"}} {}",
                code.name(),
                self.closes_for(code)
            );
        }
    }

    /// The frames, their outcomes and the time they took.
    fn render_frames(&self, out: &mut String) {
        counter(
            out,
            "holoface_frames_received_total",
            "Frame requests decoded.",
            load(&self.frames_received),
        );
        counter(
            out,
            "holoface_frames_aligned_total",
            "Frames answered with landmarks.",
            load(&self.frames_aligned),
        );
        let _ = writeln!(
            out,
            "# HELP holoface_frames_dropped_total Frames answered Dropped, by reason.\n\
             # TYPE holoface_frames_dropped_total counter"
        );
        for reason in DropReason::ALL {
            let _ = writeln!(
                out,
                "holoface_frames_dropped_total{{reason=\"{}\"}} {}",
                reason.name(),
                self.drops_for(*reason)
            );
        }
        counter(
            out,
            "holoface_inference_errors_total",
            "Inference calls that failed.",
            load(&self.inference_errors),
        );
        counter(
            out,
            "holoface_model_output_errors_total",
            "Frames whose model output was unusable (non-finite, or shaped against the model's declaration).",
            load(&self.model_output_errors),
        );
        counter(
            out,
            "holoface_client_lost_packets_total",
            "Packets to clients that QUIC declared lost.",
            load(&self.client_lost_packets),
        );
        self.client_rtt_us.render(
            out,
            "holoface_client_rtt_seconds",
            "Client QUIC round-trip time, sampled per connection every few seconds.",
            1e6,
        );
        self.batch_size
            .render(out, "holoface_batch_size", "Frames per inference batch.", 1.0);
        self.queue_wait_us.render(
            out,
            "holoface_queue_wait_seconds",
            "Time from frame arrival to batch formation.",
            1e6,
        );
        self.inference_us.render(
            out,
            "holoface_inference_seconds",
            "Engine time per batch (DAN and, when on, the refinement cascade).",
            1e6,
        );
        self.refine_us.render(
            out,
            "holoface_refine_seconds",
            "Refinement-cascade time per refined crop (a batch's refinement time over its refined crops).",
            1e6,
        );
    }
}

/// One gauge family with a single sample.
fn gauge(out: &mut String, name: &str, help: &str, v: i64) {
    let _ = writeln!(out, "# HELP {name} {help}\n# TYPE {name} gauge\n{name} {v}");
}

/// One counter family with a single sample.
fn counter(out: &mut String, name: &str, help: &str, v: u64) {
    let _ = writeln!(out, "# HELP {name} {help}\n# TYPE {name} counter\n{name} {v}");
}

fn load(a: &AtomicU64) -> u64 {
    a.load(Ordering::Relaxed)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn histogram_buckets_are_cumulative() {
        let h = Histogram::new(&[1, 10]);
        h.observe(1);
        h.observe(5);
        h.observe(50);
        let mut out = String::new();
        h.render(&mut out, "x", "help", 1.0);
        assert!(out.contains("x_bucket{le=\"1\"} 1\n"), "{out}");
        assert!(out.contains("x_bucket{le=\"10\"} 2\n"), "{out}");
        assert!(out.contains("x_bucket{le=\"+Inf\"} 3\n"), "{out}");
        assert!(out.contains("x_sum 56\n") && out.contains("x_count 3\n"), "{out}");
    }

    #[test]
    fn engine_info_names_the_provider_and_escapes_labels() {
        let m = Metrics::new(8);
        assert!(!m.render().contains("holoface_engine_info"), "no engine yet");
        use holoface_inference::InferenceEngine as _;
        let mut model = holoface_inference::FakeEngine::new(1).info().clone();
        model.name = "da\"n".into();
        let execution = Execution {
            fallback: Some("no libcudart".into()),
            ..Execution::cpu()
        };
        m.set_engine_info(&model, &execution, 2, Some("ert 0.1 (crc 0000abcd)"));
        let text = m.render();
        assert!(
            text.contains(&format!(
                "holoface_engine_info{{model=\"da\\\"n\",version=\"0\",precision=\"fp32\",\
                 cpu_int8=\"{}\",provider=\"CPUExecutionProvider\",fallback=\"true\",instances=\"2\",\
                 refiner=\"ert 0.1 (crc 0000abcd)\"}} 1\n",
                holoface_inference::CpuInt8::detect().label()
            )),
            "{text}"
        );
    }

    #[test]
    fn render_has_every_family() {
        let m = Metrics::new(8);
        m.count_drop(DropReason::Expired);
        m.count_close(CloseCode::Unauthorized);
        m.auth_unauthorized.fetch_add(1, Ordering::Relaxed);
        m.batch_size.observe(8);
        let text = m.render();
        for needle in [
            "holoface_frames_dropped_total{reason=\"expired\"} 1",
            "holoface_connections_closed_total{code=\"unauthorized\"} 1",
            "holoface_auth_failures_total{reason=\"unauthorized\"} 1",
            "holoface_batch_size_bucket{le=\"8\"} 1",
            "holoface_connected_clients 0",
            "holoface_queue_wait_seconds_count 0",
            "holoface_inference_seconds_count 0",
            "holoface_refine_seconds_count 0",
        ] {
            assert!(text.contains(needle), "missing {needle} in\n{text}");
        }
        assert!(!m.healthy());
        m.ready.store(true, Ordering::Relaxed);
        assert!(m.healthy());
    }
}
