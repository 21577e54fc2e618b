//! Server metrics in the Prometheus text format (`GET /metrics`). Lock-free counters and
//! fixed-bucket histograms; labels carry no dataset names or other data that could identify a
//! patient.

use std::fmt::Write as _;
use std::sync::Mutex;
use std::sync::atomic::{AtomicI64, AtomicU64, Ordering};
use std::time::Duration;

use voxlight_protocol::{ErrorCode, FrameFormat};

/// Upper bounds (seconds) of the latency and duration histograms.
const BUCKETS: &[f64] = &[
    0.001, 0.0025, 0.005, 0.01, 0.016, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0,
];

/// A cumulative histogram over `BUCKETS`.
#[derive(Default)]
pub struct Histogram {
    counts: [AtomicU64; 14],
    count: AtomicU64,
    /// Sum in microseconds.
    sum_micros: AtomicU64,
}

impl Histogram {
    pub fn observe(&self, value: Duration) {
        let seconds = value.as_secs_f64();
        if let Some(i) = BUCKETS.iter().position(|&b| seconds <= b) {
            self.counts[i].fetch_add(1, Ordering::Relaxed);
        }
        self.count.fetch_add(1, Ordering::Relaxed);
        self.sum_micros
            .fetch_add(value.as_micros() as u64, Ordering::Relaxed);
    }

    fn render(&self, out: &mut String, name: &str, help: &str, labels: &str) {
        let _ = writeln!(out, "# HELP {name} {help}\n# TYPE {name} histogram");
        let mut cumulative = 0;
        let sep = if labels.is_empty() { "" } else { "," };
        for (bound, count) in BUCKETS.iter().zip(&self.counts) {
            cumulative += count.load(Ordering::Relaxed);
            let _ = writeln!(
                out,
                "{name}_bucket{{{labels}{sep}le=\"{bound}\"}} {cumulative}"
            );
        }
        let total = self.count.load(Ordering::Relaxed);
        let _ = writeln!(out, "{name}_bucket{{{labels}{sep}le=\"+Inf\"}} {total}");
        let braces = if labels.is_empty() {
            String::new()
        } else {
            format!("{{{labels}}}")
        };
        let sum = self.sum_micros.load(Ordering::Relaxed) as f64 / 1e6;
        let _ = writeln!(
            out,
            "{name}_sum{braces} {sum}\n{name}_count{braces} {total}"
        );
    }
}

/// Everything `/metrics` reports.
#[derive(Default)]
pub struct Metrics {
    /// Shared sessions alive (with viewers or in their reconnect grace period) or being
    /// opened: the autoscaling signal.
    pub sessions_active: AtomicI64,
    /// Most sessions this process holds; negative: no limit (rendered as `+Inf`).
    pub session_capacity: AtomicI64,
    /// 1 while the process drains (no new sessions).
    pub draining: AtomicI64,
    /// The adapter's name and whether it is a CPU rasterizer, set once at start.
    pub adapter: std::sync::OnceLock<(String, bool)>,
    pub sessions_total: AtomicU64,
    /// Connected viewers over all sessions.
    pub viewers_active: AtomicI64,
    /// Viewers that joined an existing session (shared link or reconnect).
    pub joins_total: AtomicU64,
    /// Sessions closed after their grace period without viewers.
    pub sessions_expired_total: AtomicU64,
    /// Pictures the render thread produced (once per session, whatever the viewer count).
    pub frames_rendered: AtomicU64,
    /// Encodings made (once per frame and quality, shared by the viewers wanting it).
    pub frames_encoded: AtomicU64,
    /// Frames a viewer never got because a newer one was ready first.
    pub frames_skipped: AtomicU64,
    /// Frames sent and not yet acknowledged, over all viewers that acknowledge.
    pub frames_in_flight: AtomicI64,
    /// GPU memory accounted to sessions and volumes.
    pub gpu_memory_bytes: AtomicU64,
    pub frames_jpeg: AtomicU64,
    pub frames_png: AtomicU64,
    pub bytes_sent: AtomicU64,
    pub upgrades_refused: AtomicU64,
    errors: Mutex<Vec<(ErrorCode, u64)>>,
    pub encode_seconds: Histogram,
    /// Client edit received → first frame of that edit sent.
    pub input_to_frame_seconds: Histogram,
    gpu_seconds: Mutex<Vec<(String, f64, u64)>>,
}

fn code_name(code: ErrorCode) -> String {
    serde_json::to_value(code)
        .ok()
        .and_then(|v| v.as_str().map(str::to_owned))
        .unwrap_or_else(|| "unknown".into())
}

impl Metrics {
    pub fn frame_sent(&self, format: FrameFormat, bytes: usize) {
        match format {
            FrameFormat::Jpeg => &self.frames_jpeg,
            FrameFormat::Png => &self.frames_png,
        }
        .fetch_add(1, Ordering::Relaxed);
        self.bytes_sent.fetch_add(bytes as u64, Ordering::Relaxed);
    }

    pub fn frame_encoded(&self, encode: Duration) {
        self.frames_encoded.fetch_add(1, Ordering::Relaxed);
        self.encode_seconds.observe(encode);
    }

    pub fn error_sent(&self, code: ErrorCode) {
        if let Ok(mut errors) = self.errors.lock() {
            match errors.iter_mut().find(|(c, _)| *c == code) {
                Some((_, n)) => *n += 1,
                None => errors.push((code, 1)),
            }
        }
    }

    /// GPU time spent by a technique (summed over sessions).
    pub fn gpu_time(&self, technique: &str, time: Duration) {
        if let Ok(mut gpu) = self.gpu_seconds.lock() {
            match gpu.iter_mut().find(|(t, _, _)| t == technique) {
                Some((_, seconds, steps)) => {
                    *seconds += time.as_secs_f64();
                    *steps += 1;
                }
                None => gpu.push((technique.to_owned(), time.as_secs_f64(), 1)),
            }
        }
    }

    /// The Prometheus text exposition.
    pub fn render(&self) -> String {
        let mut out = String::new();
        let mut counter = |name: &str, help: &str, kind: &str, value: String| {
            let _ = writeln!(
                out,
                "# HELP {name} {help}\n# TYPE {name} {kind}\n{name} {value}"
            );
        };
        let gauges: [(&str, &str, &AtomicI64); 3] = [
            (
                "voxlight_sessions_active",
                "Sessions alive (with viewers or within their reconnect grace period).",
                &self.sessions_active,
            ),
            (
                "voxlight_viewers_active",
                "Viewers connected, over all sessions.",
                &self.viewers_active,
            ),
            (
                "voxlight_frames_in_flight",
                "Frames sent and not yet acknowledged.",
                &self.frames_in_flight,
            ),
        ];
        for (name, help, value) in gauges {
            counter(
                name,
                help,
                "gauge",
                value.load(Ordering::Relaxed).to_string(),
            );
        }
        let capacity = self.session_capacity.load(Ordering::Relaxed);
        counter(
            "voxlight_session_capacity",
            "Most sessions this process holds (+Inf: no limit but GPU memory).",
            "gauge",
            if capacity < 0 {
                "+Inf".to_owned()
            } else {
                capacity.to_string()
            },
        );
        counter(
            "voxlight_draining",
            "1 while the process drains for a restart or scale-down (no new sessions).",
            "gauge",
            self.draining.load(Ordering::Relaxed).to_string(),
        );
        counter(
            "voxlight_gpu_memory_bytes",
            "GPU memory accounted to sessions and volumes.",
            "gauge",
            self.gpu_memory_bytes.load(Ordering::Relaxed).to_string(),
        );
        let counters: [(&str, &str, &AtomicU64); 6] = [
            (
                "voxlight_sessions_total",
                "Sessions opened since start.",
                &self.sessions_total,
            ),
            (
                "voxlight_joins_total",
                "Viewers that joined an existing session.",
                &self.joins_total,
            ),
            (
                "voxlight_sessions_expired_total",
                "Sessions closed after their grace period without viewers.",
                &self.sessions_expired_total,
            ),
            (
                "voxlight_frames_rendered_total",
                "Pictures rendered (once per session, whatever the number of viewers).",
                &self.frames_rendered,
            ),
            (
                "voxlight_frames_encoded_total",
                "Frame encodings (once per frame and quality, shared by viewers).",
                &self.frames_encoded,
            ),
            (
                "voxlight_frames_skipped_total",
                "Frames a viewer skipped because a newer one was ready first.",
                &self.frames_skipped,
            ),
        ];
        for (name, help, value) in counters {
            counter(
                name,
                help,
                "counter",
                value.load(Ordering::Relaxed).to_string(),
            );
        }
        counter(
            "voxlight_bytes_sent_total",
            "Bytes of frames sent.",
            "counter",
            self.bytes_sent.load(Ordering::Relaxed).to_string(),
        );
        counter(
            "voxlight_upgrades_refused_total",
            "WebSocket upgrades and API requests refused (token or origin).",
            "counter",
            self.upgrades_refused.load(Ordering::Relaxed).to_string(),
        );
        let _ = writeln!(
            out,
            "# HELP voxlight_frames_sent_total Frames sent, by encoding.\n# TYPE voxlight_frames_sent_total counter"
        );
        let _ = writeln!(
            out,
            "voxlight_frames_sent_total{{format=\"jpeg\"}} {}",
            self.frames_jpeg.load(Ordering::Relaxed)
        );
        let _ = writeln!(
            out,
            "voxlight_frames_sent_total{{format=\"png\"}} {}",
            self.frames_png.load(Ordering::Relaxed)
        );
        let _ = writeln!(
            out,
            "# HELP voxlight_errors_total Error replies sent, by code.\n# TYPE voxlight_errors_total counter"
        );
        if let Ok(errors) = self.errors.lock() {
            for (code, n) in errors.iter() {
                let _ = writeln!(
                    out,
                    "voxlight_errors_total{{code=\"{}\"}} {n}",
                    code_name(*code)
                );
            }
        }
        let _ = writeln!(
            out,
            "# HELP voxlight_gpu_seconds_total GPU time of rendering steps, by technique.\n# TYPE voxlight_gpu_seconds_total counter"
        );
        if let Ok(gpu) = self.gpu_seconds.lock() {
            for (technique, seconds, _) in gpu.iter() {
                let _ = writeln!(
                    out,
                    "voxlight_gpu_seconds_total{{technique=\"{technique}\"}} {seconds}"
                );
            }
        }
        self.encode_seconds.render(
            &mut out,
            "voxlight_encode_seconds",
            "Frame encoding time.",
            "",
        );
        self.input_to_frame_seconds.render(
            &mut out,
            "voxlight_input_to_frame_seconds",
            "From a client's edit arriving to the first frame of it being sent.",
            "",
        );
        if let Some((adapter, software)) = self.adapter.get() {
            let adapter = adapter.replace('\\', "\\\\").replace('"', "\\\"");
            let _ = writeln!(
                out,
                "# HELP voxlight_adapter_info The GPU adapter that renders (software_renderer=\"true\": a CPU rasterizer).\n# TYPE voxlight_adapter_info gauge\nvoxlight_adapter_info{{adapter=\"{adapter}\",software_renderer=\"{software}\"}} 1"
            );
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn exposition_has_counters_and_cumulative_buckets() {
        let m = Metrics::default();
        m.frame_sent(FrameFormat::Jpeg, 100);
        m.frame_encoded(Duration::from_millis(3));
        m.frame_sent(FrameFormat::Png, 50);
        m.frame_encoded(Duration::from_millis(30));
        m.error_sent(ErrorCode::BadMessage);
        m.error_sent(ErrorCode::BadMessage);
        m.gpu_time("raymarch", Duration::from_millis(500));
        let text = m.render();
        assert!(text.contains("voxlight_frames_sent_total{format=\"jpeg\"} 1"));
        assert!(text.contains("voxlight_bytes_sent_total 150"));
        assert!(text.contains("voxlight_errors_total{code=\"bad_message\"} 2"));
        assert!(text.contains("voxlight_gpu_seconds_total{technique=\"raymarch\"} 0.5"));
        assert!(text.contains("voxlight_encode_seconds_bucket{le=\"0.005\"} 1"));
        assert!(text.contains("voxlight_encode_seconds_bucket{le=\"0.05\"} 2"));
        assert!(text.contains("voxlight_encode_seconds_bucket{le=\"+Inf\"} 2"));
        assert!(text.contains("voxlight_encode_seconds_count 2"));
        assert!(text.contains("voxlight_frames_encoded_total 2"));
        assert!(text.contains("# TYPE voxlight_viewers_active gauge\nvoxlight_viewers_active 0"));
        assert!(
            text.contains("# TYPE voxlight_session_capacity gauge\nvoxlight_session_capacity 0")
        );
        let _ = m.adapter.set(("llvmpipe \"x\"".into(), true));
        assert!(m.render().contains(
            "\nvoxlight_adapter_info{adapter=\"llvmpipe \\\"x\\\"\",software_renderer=\"true\"} 1\n"
        ));
        m.session_capacity.store(-1, Ordering::Relaxed);
        assert!(m.render().contains("\nvoxlight_session_capacity +Inf\n"));
    }
}
