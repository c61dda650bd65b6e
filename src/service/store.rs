//! The two stores the service depends on, as small traits.
//!
//! Routes and workers see only [`JobStore`] and [`FileStore`]. The embedded
//! implementations ([`super::sqlite::SqliteJobStore`],
//! [`super::files::LocalFileStore`]) serve one process; the cluster's
//! ([`super::postgres::PgJobStore`], [`super::objects::ObjectFileStore`])
//! are shared by any number of API servers and workers. Calls block: the
//! service makes them from blocking threads, never on the async runtime.
//!
//! A running job is held by one worker under a lease: the worker renews it
//! while it runs, and a job whose lease ran out (its worker died, or lost
//! the store) goes back to the queue. Every write a worker makes to a
//! running job names the worker, so a worker whose job was taken from it
//! can no longer change it.

use std::collections::BTreeMap;
use std::sync::Arc;

use super::job::{Job, JobState};

#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    #[error("job store: {0}")]
    Jobs(String),
    #[error("file store: {0}")]
    Files(String),
    #[error("stored job {id} is unreadable: {message}")]
    Corrupt { id: String, message: String },
    /// The disk (or quota) under a store is full: the client may retry later.
    #[error("storage full: {0}")]
    Full(String),
    /// The store does not answer (refused, timed out, shutting down): an
    /// outage, not a verdict on what was asked of it.
    #[error("{which} unavailable: {message}")]
    Unavailable {
        which: &'static str,
        message: String,
    },
}

impl StoreError {
    /// The job error code for a job that this error stopped.
    pub fn job_code(&self) -> &'static str {
        match self {
            StoreError::Full(_) => "storage_full",
            StoreError::Unavailable { .. } => "store_unavailable",
            _ => "internal",
        }
    }

    /// Whether the error is the world's and passes: a store that does not
    /// answer, or a full disk. Work it interrupts waits and goes on; it
    /// never fails a job.
    pub fn is_outage(&self) -> bool {
        matches!(self, StoreError::Full(_) | StoreError::Unavailable { .. })
    }

    pub fn jobs_unavailable(message: impl Into<String>) -> Self {
        StoreError::Unavailable {
            which: "job store",
            message: message.into(),
        }
    }

    pub fn files_unavailable(message: impl Into<String>) -> Self {
        StoreError::Unavailable {
            which: "file store",
            message: message.into(),
        }
    }
}

/// Whether an I/O error means the disk or quota is full.
pub fn is_full(e: &std::io::Error) -> bool {
    e.kind() == std::io::ErrorKind::StorageFull
        || e.kind() == std::io::ErrorKind::QuotaExceeded
        || matches!(e.raw_os_error(), Some(libc::ENOSPC) | Some(libc::EDQUOT))
}

/// The outcome of [`JobStore::submit`].
#[derive(Debug)]
pub enum Submitted {
    /// The job was stored.
    Created,
    /// The owner already used this idempotency key, for this job.
    Existing(Box<Job>),
    /// Nothing was stored: the queue holds its limit.
    QueueFull,
}

/// Durable job records and the queue order.
pub trait JobStore: Send + Sync + 'static {
    /// Stores `job` unless the owner already has a job with the same
    /// idempotency key (that job is returned instead), or `job` is queued
    /// and `queue_limit` jobs are already queued. Atomic: two submissions
    /// with one key store one job.
    fn submit(&self, job: &Job, queue_limit: usize) -> Result<Submitted, StoreError>;

    fn get(&self, id: &str) -> Result<Option<Job>, StoreError>;

    /// The owner's jobs, newest first, with `seq` below `before` if given.
    fn list(&self, owner: &str, before: Option<i64>, limit: usize) -> Result<Vec<Job>, StoreError>;

    /// A succeeded job of `owner` with this input key, whose files can be reused.
    fn find_succeeded(&self, owner: &str, input_key: &str) -> Result<Option<Job>, StoreError>;

    /// Moves the oldest queued job to `running` (counting the attempt)
    /// under `lease`, and returns it with `job.worker` set; `None` when
    /// nothing is queued. Concurrent claims never take one job twice.
    fn claim(&self, lease: &Lease<'_>, now_ms: u64) -> Result<Option<Job>, StoreError>;

    /// Extends the lease that `lease.worker` holds on job `id`. False when
    /// the worker no longer holds it (canceled, deleted, or reclaimed).
    fn renew(&self, id: &str, lease: &Lease<'_>) -> Result<bool, StoreError>;

    /// Replaces a running job's record (progress, or its final state).
    /// Returns false, changing nothing, unless the job is still running
    /// under `job.worker` (canceled, timed out or reclaimed meanwhile).
    fn update_running(&self, job: &Job) -> Result<bool, StoreError>;

    /// Cancels a queued or running job; returns it as it is now, or `None`
    /// if it was not queued or running.
    fn cancel(&self, id: &str, now_ms: u64) -> Result<Option<Job>, StoreError>;

    /// Puts a job that `worker` is running back in the queue (shutdown);
    /// the interrupted attempt is not counted.
    fn requeue(&self, id: &str, worker: &str) -> Result<bool, StoreError>;

    /// Jobs whose lease ran out before `expired_before_ms` go back to the
    /// queue uncounted (their worker's process died or lost the store), or
    /// fail once their leases have run out `max_lost` times (a job that
    /// somehow kills the server running it must not do so forever).
    fn reclaim(
        &self,
        expired_before_ms: u64,
        max_lost: u32,
        now_ms: u64,
    ) -> Result<Reclaimed, StoreError>;

    fn delete(&self, id: &str) -> Result<(), StoreError>;
    /// Finished jobs whose callback is due at `now_ms`, oldest due first.
    fn callbacks_due(&self, now_ms: u64, limit: usize) -> Result<Vec<Job>, StoreError>;
    /// Records a delivery of `id`'s callback; `next_ms` is when to try
    /// again, `None` when no more tries are due (delivered or given up).
    fn callback_tried(
        &self,
        id: &str,
        status: &super::job::Callback,
        next_ms: Option<u64>,
    ) -> Result<(), StoreError>;

    /// Finished jobs whose `finished_ms` is before `before_ms`.
    fn expired(&self, before_ms: u64, limit: usize) -> Result<Vec<Job>, StoreError>;

    fn counts(&self) -> Result<BTreeMap<JobState, u64>, StoreError>;

    /// Whether the store answers (`/readyz`).
    fn check(&self) -> Result<(), StoreError> {
        Ok(())
    }

    /// Calls `on` when any process sharing the store queues a job or
    /// finishes one, so that idle workers and `Prefer: wait` need not poll.
    /// A store only one process uses has nothing to tell.
    fn listen(&self, on: Arc<dyn Fn(StoreEvent) + Send + Sync>) {
        let _ = on;
    }
}

/// A worker's hold on a running job.
#[derive(Debug, Clone, Copy)]
pub struct Lease<'a> {
    /// The worker's name, unique among every process on the store.
    pub worker: &'a str,
    /// Until when the job is the worker's, unless renewed.
    pub until_ms: u64,
}

/// What [`JobStore::reclaim`] did: the jobs as they were stored (their
/// `worker` is the one whose lease ran out).
#[derive(Debug, Default)]
pub struct Reclaimed {
    pub requeued: Vec<Job>,
    pub failed: Vec<Job>,
}

impl Reclaimed {
    /// Every job taken back, re-queued or failed.
    pub fn jobs(&self) -> impl Iterator<Item = &Job> {
        self.requeued.iter().chain(&self.failed)
    }
}

/// What [`JobStore::listen`] reports.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum StoreEvent {
    Queued,
    Finished,
}

/// Durable named blobs. Keys are `/`-separated relative paths. A `put` is
/// all or nothing: a reader sees the old content, the new, or nothing.
pub trait FileStore: Send + Sync + 'static {
    fn put(&self, key: &str, bytes: &[u8]) -> Result<(), StoreError>;

    /// Several `put`s; a store whose writes are round trips makes them at
    /// once. On an error some may be stored: the caller removes them.
    fn put_all(&self, blobs: &[(String, &[u8])]) -> Result<(), StoreError> {
        blobs
            .iter()
            .try_for_each(|(key, bytes)| self.put(key, bytes))
    }

    /// Removes one blob; absent is not an error.
    fn remove(&self, key: &str) -> Result<(), StoreError> {
        self.delete_prefix(key)
    }

    fn get(&self, key: &str) -> Result<Option<Vec<u8>>, StoreError>;

    /// Bytes `range` of a blob (fewer where the blob ends first), so that
    /// a large blob can be served a piece at a time.
    fn read_range(&self, key: &str, range: std::ops::Range<u64>) -> Result<Vec<u8>, StoreError>;

    /// Copies a blob (the local store links it, an object store would copy
    /// server-side).
    fn copy(&self, from: &str, to: &str) -> Result<(), StoreError>;

    /// Removes `prefix` and everything under it; absent is not an error.
    fn delete_prefix(&self, prefix: &str) -> Result<(), StoreError>;

    /// Names directly under `prefix` (one level, no recursion).
    fn list(&self, prefix: &str) -> Result<Vec<String>, StoreError>;

    /// Whether the store answers (`/readyz`).
    fn check(&self) -> Result<(), StoreError> {
        Ok(())
    }

    /// A URL a client may fetch the blob from directly for `ttl`, where the
    /// store can sign one (`?redirect=1`).
    fn presign(&self, key: &str, ttl: std::time::Duration) -> Result<Option<String>, StoreError> {
        let _ = (key, ttl);
        Ok(None)
    }
}

/// Where a job's files live in the [`FileStore`].
pub mod keys {
    pub fn job(id: &str) -> String {
        format!("jobs/{id}")
    }
    pub fn input(id: &str) -> String {
        format!("jobs/{id}/input.bundle")
    }
    pub fn output(id: &str, name: &str) -> String {
        format!("jobs/{id}/out/{name}")
    }
    pub fn outputs(id: &str) -> String {
        format!("jobs/{id}/out")
    }
}

/// A job from the JSON a store keeps of it, with the store's sequence
/// number (kept beside the JSON, not in it).
pub(super) fn decode(seq: i64, id: &str, data: &str) -> Result<Job, StoreError> {
    let mut job: Job = serde_json::from_str(data).map_err(|e| StoreError::Corrupt {
        id: id.to_string(),
        message: e.to_string(),
    })?;
    job.seq = seq;
    Ok(job)
}

/// The JSON a store keeps of a job.
pub(super) fn encode(job: &Job) -> Result<String, StoreError> {
    serde_json::to_string(job).map_err(|e| StoreError::Corrupt {
        id: job.id.clone(),
        message: e.to_string(),
    })
}
