//! Jobs as stored, and as clients see them.

use serde::{Deserialize, Serialize};
use serde_json::value::RawValue;

use crate::pipeline::ProcessOptions;

#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum JobState {
    Queued,
    Running,
    Succeeded,
    Failed,
    Canceled,
}

impl JobState {
    pub const ALL: [JobState; 5] = [
        JobState::Queued,
        JobState::Running,
        JobState::Succeeded,
        JobState::Failed,
        JobState::Canceled,
    ];

    pub fn as_str(self) -> &'static str {
        match self {
            JobState::Queued => "queued",
            JobState::Running => "running",
            JobState::Succeeded => "succeeded",
            JobState::Failed => "failed",
            JobState::Canceled => "canceled",
        }
    }

    pub fn parse(s: &str) -> Option<JobState> {
        JobState::ALL.into_iter().find(|st| st.as_str() == s)
    }

    pub fn is_terminal(self) -> bool {
        matches!(
            self,
            JobState::Succeeded | JobState::Failed | JobState::Canceled
        )
    }
}

/// What was uploaded.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct InputInfo {
    /// The model file's name (the report's `input`).
    pub name: String,
    /// `glb` or `gltf`.
    pub format: String,
    /// Size of the model and its files together.
    pub bytes: u64,
    /// The files uploaded beside a `.gltf`, by the names its URIs use.
    pub files: Vec<String>,
}

#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct Progress {
    /// `queued`, `load`, `process`, `rewrite`, `store` or `done`.
    pub stage: String,
    /// Of the whole job, 0 to 1.
    pub fraction: f64,
    /// In the `process` stage: the texture being processed (from 1) and
    /// how many there are.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub texture: Option<[usize; 2]>,
}

impl Progress {
    pub fn at(stage: &str, fraction: f64) -> Progress {
        Progress {
            stage: stage.to_string(),
            fraction,
            texture: None,
        }
    }

    /// The pipeline's progress event, as a job shows it.
    pub fn of(at: &crate::pipeline::Progress<'_>) -> Progress {
        Progress {
            stage: at.stage.to_string(),
            fraction: at.fraction,
            texture: at.texture.map(|(i, n)| [i + 1, n]),
        }
    }
}

/// Milliseconds spent in each stage.
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct StageTimings {
    #[serde(skip_serializing_if = "Option::is_none")]
    pub queued: Option<u64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub load: Option<u64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub process: Option<u64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub rewrite: Option<u64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub store: Option<u64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub total: Option<u64>,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct JobError {
    pub code: String,
    pub message: String,
}

/// One result file.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FileEntry {
    pub name: String,
    pub bytes: u64,
    /// Hex SHA-256 of the content: the strong ETag.
    pub sha256: String,
    pub content_type: String,
}

/// A job with everything the store keeps about it.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct Job {
    /// Insertion order, assigned by the store (the listing cursor).
    #[serde(skip)]
    pub seq: i64,
    pub id: String,
    pub owner: String,
    pub state: JobState,
    pub input: InputInfo,
    /// SHA-256 over owner, options and upload: equal keys give equal results.
    pub input_key: String,
    pub idempotency_key: Option<String>,
    pub options: ProcessOptions,
    pub created_ms: u64,
    pub started_ms: Option<u64>,
    pub finished_ms: Option<u64>,
    pub progress: Progress,
    pub timings_ms: StageTimings,
    /// `report.json`'s content, kept as text so that its numbers stay exact.
    pub report: Option<Box<RawValue>>,
    pub error: Option<JobError>,
    pub files: Vec<FileEntry>,
    /// The earlier job whose result this one reuses.
    pub cached_from: Option<String>,
    /// Runs charged to the job: started, and not interrupted through no
    /// fault of its own.
    pub attempts: u32,
    /// Runs that were interrupted through no fault of the job (its server
    /// stopped or died, a store or the disk failed) and re-queued uncounted.
    #[serde(default)]
    pub interruptions: u32,
    /// Of those, runs whose worker vanished without a word: its lease ran
    /// out.
    #[serde(default)]
    pub lost_leases: u32,
    pub warnings: Vec<String>,
    /// Where the finished job is posted, and how that went.
    #[serde(default)]
    pub callback: Option<Callback>,
    /// The worker that holds (or last held) the job's lease.
    #[serde(default)]
    pub worker: Option<String>,
}

impl Job {
    /// The record of a claim by `worker`: one more attempt, from now.
    pub fn start(&mut self, worker: &str, now_ms: u64) {
        self.state = JobState::Running;
        self.started_ms = Some(now_ms);
        self.attempts += 1;
        self.progress = Progress::at("load", 0.0);
        self.timings_ms.queued = Some(now_ms.saturating_sub(self.created_ms));
        self.worker = Some(worker.to_string());
    }

    /// Back in the queue, to be claimed again.
    pub fn requeue(&mut self) {
        self.state = JobState::Queued;
        self.started_ms = None;
        self.progress = Progress::at("queued", 0.0);
    }

    /// Back in the queue after a shutdown or an outage interrupted it: the
    /// attempt was not the job's fault, so it is not counted.
    pub fn requeue_uncounted(&mut self) {
        self.requeue();
        self.attempts = self.attempts.saturating_sub(1);
        self.interruptions += 1;
    }

    /// A running job whose worker is gone (its process died, or lost the
    /// store for longer than the lease): back in the queue uncounted, or
    /// failed once its lease has run out `max_lost` times. True if
    /// re-queued.
    pub fn reclaim(&mut self, max_lost: u32, now_ms: u64) -> bool {
        self.lost_leases += 1;
        if self.lost_leases < max_lost {
            self.requeue_uncounted();
            return true;
        }
        self.state = JobState::Failed;
        self.finished_ms = Some(now_ms);
        self.progress = Progress::at("done", self.progress.fraction);
        self.error = Some(JobError {
            code: "interrupted".into(),
            message: format!(
                "the server running it stopped without a word {} times",
                self.lost_leases
            ),
        });
        false
    }

    /// The record of a cancel: finished now.
    pub fn cancel(&mut self, now_ms: u64) {
        self.state = JobState::Canceled;
        self.finished_ms = Some(now_ms);
        self.progress = Progress::at("done", self.progress.fraction);
    }
}

/// A job's callback: its URL and its deliveries so far.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Callback {
    pub url: String,
    /// Deliveries tried.
    pub attempts: u32,
    /// When one was answered with a 2xx, ms since the epoch.
    pub delivered_ms: Option<u64>,
    /// Set when no more deliveries will be tried without success.
    pub gave_up: bool,
    /// Why the last delivery failed (a status or a connection error).
    pub last_error: Option<String>,
}

/// Milliseconds since the Unix epoch.
pub fn now_ms() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_millis() as u64)
}

/// RFC 3339 in UTC with milliseconds, e.g. `2025-01-31T12:00:00.123Z`.
pub fn rfc3339(ms: u64) -> String {
    let secs = ms / 1000;
    let (days, rem) = ((secs / 86400) as i64, secs % 86400);
    // Civil date from days since 1970-01-01 (H. Hinnant's algorithm).
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z - era * 146_097;
    let yoe = (doe - doe / 1460 + doe / 36524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let day = doy - (153 * mp + 2) / 5 + 1;
    let month = if mp < 10 { mp + 3 } else { mp - 9 };
    let year = yoe + era * 400 + i64::from(month <= 2);
    format!(
        "{year:04}-{month:02}-{day:02}T{:02}:{:02}:{:02}.{:03}Z",
        rem / 3600,
        rem % 3600 / 60,
        rem % 60,
        ms % 1000
    )
}

/// Random bytes from the operating system, hex-encoded: 128 bits make job
/// ids that cannot be guessed or enumerated.
pub fn random_id() -> std::io::Result<String> {
    let mut b = [0u8; 16];
    getrandom::fill(&mut b).map_err(std::io::Error::other)?;
    Ok(super::config::hex(&b))
}

pub fn is_job_id(s: &str) -> bool {
    s.len() == 32 && s.bytes().all(|b| matches!(b, b'0'..=b'9' | b'a'..=b'f'))
}

#[derive(Serialize)]
struct FileView<'a> {
    name: &'a str,
    bytes: u64,
    content_type: &'a str,
    etag: String,
    url: String,
}

#[derive(Serialize)]
struct Links {
    #[serde(rename = "self")]
    this: String,
}

/// What clients see of a job.
#[derive(Serialize)]
pub struct View<'a> {
    id: &'a str,
    state: JobState,
    created_at: String,
    started_at: Option<String>,
    finished_at: Option<String>,
    input: &'a InputInfo,
    options: &'a ProcessOptions,
    progress: &'a Progress,
    timings_ms: &'a StageTimings,
    #[serde(skip_serializing_if = "Option::is_none")]
    report: Option<Option<&'a RawValue>>,
    error: &'a Option<JobError>,
    files: Vec<FileView<'a>>,
    cached: bool,
    attempts: u32,
    interruptions: u32,
    warnings: &'a [String],
    #[serde(skip_serializing_if = "Option::is_none")]
    callback: Option<&'a Callback>,
    #[serde(skip_serializing_if = "Option::is_none")]
    worker: Option<&'a str>,
    links: Links,
}

/// The job as clients see it; lists leave the report out.
pub fn view(job: &Job, with_report: bool) -> View<'_> {
    View {
        id: &job.id,
        state: job.state,
        created_at: rfc3339(job.created_ms),
        started_at: job.started_ms.map(rfc3339),
        finished_at: job.finished_ms.map(rfc3339),
        input: &job.input,
        options: &job.options,
        progress: &job.progress,
        timings_ms: &job.timings_ms,
        report: with_report.then_some(job.report.as_deref()),
        error: &job.error,
        files: job
            .files
            .iter()
            .map(|f| FileView {
                name: &f.name,
                bytes: f.bytes,
                content_type: &f.content_type,
                etag: format!("\"{}\"", f.sha256),
                url: format!("/v1/jobs/{}/files/{}", job.id, f.name),
            })
            .collect(),
        cached: job.cached_from.is_some(),
        attempts: job.attempts,
        interruptions: job.interruptions,
        warnings: &job.warnings,
        callback: job.callback.as_ref(),
        worker: job.worker.as_deref(),
        links: Links {
            this: format!("/v1/jobs/{}", job.id),
        },
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn timestamps() {
        assert_eq!(rfc3339(0), "1970-01-01T00:00:00.000Z");
        assert_eq!(rfc3339(951_782_400_123), "2000-02-29T00:00:00.123Z");
        assert_eq!(rfc3339(1_735_689_599_999), "2024-12-31T23:59:59.999Z");
    }

    #[test]
    fn ids_are_random_hex() {
        let a = random_id().unwrap();
        assert!(is_job_id(&a));
        assert_ne!(a, random_id().unwrap());
        assert!(!is_job_id("../etc"));
    }
}
