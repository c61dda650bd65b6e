//! Prometheus metrics in the text exposition format.

use std::collections::BTreeMap;
use std::fmt::Write;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Mutex;

use super::job::JobState;

/// Upper bounds in seconds: from a cached submission to a 2048² texture
/// with every option on.
const BUCKETS: [f64; 16] = [
    0.001, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0, 60.0, 120.0, 300.0,
];

#[derive(Default, Clone)]
struct Histogram {
    counts: [u64; BUCKETS.len()],
    sum: f64,
    count: u64,
}

impl Histogram {
    fn observe(&mut self, secs: f64) {
        for (c, &b) in self.counts.iter_mut().zip(BUCKETS.iter()) {
            if secs <= b {
                *c += 1;
            }
        }
        self.sum += secs;
        self.count += 1;
    }
}

#[derive(Default)]
pub struct Metrics {
    pub submitted: AtomicU64,
    pub cache_hits: AtomicU64,
    pub rejected_full: AtomicU64,
    pub bytes_in: AtomicU64,
    pub bytes_out: AtomicU64,
    pub busy_workers: AtomicU64,
    finished: Mutex<BTreeMap<&'static str, u64>>,
    stages: Mutex<BTreeMap<&'static str, Histogram>>,
    requests: Mutex<BTreeMap<u16, u64>>,
    submit_latency: Mutex<Histogram>,
    /// Jobs claimed, by this process's worker.
    claimed: Mutex<BTreeMap<String, u64>>,
    /// Leases this process found run out, by the worker that held them.
    leases_expired: Mutex<BTreeMap<String, u64>>,
}

fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|p| p.into_inner())
}

impl Metrics {
    pub fn stage(&self, stage: &'static str, ms: u64) {
        lock(&self.stages)
            .entry(stage)
            .or_default()
            .observe(ms as f64 / 1000.0);
    }

    pub fn finished(&self, state: JobState) {
        *lock(&self.finished).entry(state.as_str()).or_default() += 1;
    }

    pub fn request(&self, status: u16) {
        *lock(&self.requests).entry(status).or_default() += 1;
    }

    pub fn claimed(&self, worker: &str) {
        *lock(&self.claimed).entry(worker.to_string()).or_default() += 1;
    }

    pub fn lease_expired(&self, worker: &str) {
        *lock(&self.leases_expired)
            .entry(worker.to_string())
            .or_default() += 1;
    }

    pub fn submission(&self, secs: f64) {
        lock(&self.submit_latency).observe(secs);
    }

    /// The exposition text; `counts` are the jobs by state in the store.
    /// The exposition text. `counts` is `None` when the job store does not
    /// answer; `up` says, per dependency, whether it does.
    pub fn render(
        &self,
        counts: Option<&BTreeMap<JobState, u64>>,
        up: &[(&str, bool)],
        workers: usize,
    ) -> String {
        let mut out = String::new();
        let gauge = |out: &mut String, name: &str, help: &str, v: u64| {
            let _ = writeln!(out, "# HELP {name} {help}\n# TYPE {name} gauge\n{name} {v}");
        };
        let counter = |out: &mut String, name: &str, help: &str, v: u64| {
            let _ = writeln!(
                out,
                "# HELP {name} {help}\n# TYPE {name} counter\n{name} {v}"
            );
        };
        if let Some(counts) = counts {
            gauge(
                &mut out,
                "seamstress_queue_depth",
                "Jobs waiting for a worker.",
                counts.get(&JobState::Queued).copied().unwrap_or(0),
            );
            let _ = writeln!(
                out,
                "# HELP seamstress_jobs Jobs in the store by state.\n# TYPE seamstress_jobs gauge"
            );
            for (state, n) in counts {
                let _ = writeln!(out, "seamstress_jobs{{state=\"{}\"}} {n}", state.as_str());
            }
        }
        let _ = writeln!(
            out,
            "# HELP seamstress_dependency_up Whether a dependency answered its last probe.\n\
             # TYPE seamstress_dependency_up gauge"
        );
        for (name, is_up) in up {
            let _ = writeln!(
                out,
                "seamstress_dependency_up{{dependency=\"{name}\"}} {}",
                u8::from(*is_up)
            );
        }
        gauge(
            &mut out,
            "seamstress_workers",
            "Worker slots.",
            workers as u64,
        );
        gauge(
            &mut out,
            "seamstress_workers_busy",
            "Workers running a job.",
            self.busy_workers.load(Ordering::Relaxed),
        );
        for (name, help, map) in [
            (
                "seamstress_jobs_claimed_total",
                "Jobs claimed by this process's workers.",
                &self.claimed,
            ),
            (
                "seamstress_leases_expired_total",
                "Leases found run out by this process, by the worker that held them.",
                &self.leases_expired,
            ),
        ] {
            let _ = writeln!(out, "# HELP {name} {help}\n# TYPE {name} counter");
            for (worker, n) in lock(map).iter() {
                let _ = writeln!(out, "{name}{{worker=\"{worker}\"}} {n}");
            }
        }
        counter(
            &mut out,
            "seamstress_jobs_submitted_total",
            "Jobs accepted.",
            self.submitted.load(Ordering::Relaxed),
        );
        counter(
            &mut out,
            "seamstress_jobs_cached_total",
            "Jobs answered from an earlier identical job's result.",
            self.cache_hits.load(Ordering::Relaxed),
        );
        counter(
            &mut out,
            "seamstress_jobs_rejected_queue_full_total",
            "Submissions refused because the queue was full.",
            self.rejected_full.load(Ordering::Relaxed),
        );
        let _ = writeln!(
            out,
            "# HELP seamstress_jobs_finished_total Jobs that reached a final state since start.\n\
             # TYPE seamstress_jobs_finished_total counter"
        );
        for (state, n) in lock(&self.finished).iter() {
            let _ = writeln!(
                out,
                "seamstress_jobs_finished_total{{state=\"{state}\"}} {n}"
            );
        }
        counter(
            &mut out,
            "seamstress_bytes_in_total",
            "Bytes of uploaded models and files.",
            self.bytes_in.load(Ordering::Relaxed),
        );
        counter(
            &mut out,
            "seamstress_bytes_out_total",
            "Bytes of result files sent.",
            self.bytes_out.load(Ordering::Relaxed),
        );
        let _ = writeln!(
            out,
            "# HELP seamstress_http_requests_total HTTP responses by status.\n\
             # TYPE seamstress_http_requests_total counter"
        );
        for (status, n) in lock(&self.requests).iter() {
            let _ = writeln!(
                out,
                "seamstress_http_requests_total{{status=\"{status}\"}} {n}"
            );
        }
        let _ = writeln!(
            out,
            "# HELP seamstress_stage_duration_seconds Time jobs spent in each stage.\n\
             # TYPE seamstress_stage_duration_seconds histogram"
        );
        for (stage, h) in lock(&self.stages).iter() {
            write_histogram(
                &mut out,
                "seamstress_stage_duration_seconds",
                &format!("stage=\"{stage}\","),
                h,
            );
        }
        let _ = writeln!(
            out,
            "# HELP seamstress_submit_duration_seconds Time to accept a submission.\n\
             # TYPE seamstress_submit_duration_seconds histogram"
        );
        write_histogram(
            &mut out,
            "seamstress_submit_duration_seconds",
            "",
            &lock(&self.submit_latency),
        );
        out
    }
}

fn write_histogram(out: &mut String, name: &str, labels: &str, h: &Histogram) {
    for (c, b) in h.counts.iter().zip(BUCKETS.iter()) {
        let _ = writeln!(out, "{name}_bucket{{{labels}le=\"{b}\"}} {c}");
    }
    let _ = writeln!(out, "{name}_bucket{{{labels}le=\"+Inf\"}} {}", h.count);
    let bare = labels.trim_end_matches(',');
    let braces = if bare.is_empty() {
        String::new()
    } else {
        format!("{{{bare}}}")
    };
    let _ = writeln!(out, "{name}_sum{braces} {}", h.sum);
    let _ = writeln!(out, "{name}_count{braces} {}", h.count);
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn exposition_has_histograms_and_gauges() {
        let m = Metrics::default();
        m.stage("process", 1500);
        m.stage("process", 20);
        m.finished(JobState::Succeeded);
        let counts = JobState::ALL.iter().map(|&s| (s, 1)).collect();
        let text = m.render(Some(&counts), &[("job store", true)], 2);
        assert!(text.contains("seamstress_queue_depth 1"));
        assert!(text.contains("seamstress_jobs{state=\"running\"} 1"));
        assert!(text
            .contains("seamstress_stage_duration_seconds_bucket{stage=\"process\",le=\"2.5\"} 2"));
        assert!(text.contains(
            "seamstress_stage_duration_seconds_bucket{stage=\"process\",le=\"0.025\"} 1"
        ));
        assert!(text.contains("seamstress_stage_duration_seconds_count{stage=\"process\"} 2"));
        assert!(text.contains("seamstress_jobs_finished_total{state=\"succeeded\"} 1"));
    }
}
