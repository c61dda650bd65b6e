//! The two stores the service depends on, as small traits.
//!
//! Routes and workers see only [`JobStore`] and [`FileStore`]. The embedded
//! implementations ([`super::sqlite::SqliteJobStore`],
//! [`super::files::LocalFileStore`]) serve one process; a PostgreSQL queue
//! (claims with `FOR UPDATE SKIP LOCKED`, shared by several servers) and an
//! S3-compatible object store fit the same traits. Calls block: the service
//! makes them from blocking threads, never on the async runtime.

use std::collections::BTreeMap;

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
}

impl StoreError {
    /// The job error code for a job that this error stopped.
    pub fn job_code(&self) -> &'static str {
        match self {
            StoreError::Full(_) => "storage_full",
            _ => "internal",
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

    /// Moves the oldest queued job to `running` (counting the attempt) and
    /// returns it; `None` when nothing is queued.
    fn claim(&self, now_ms: u64) -> Result<Option<Job>, StoreError>;

    /// Replaces a running job's record (progress, or its final state).
    /// Returns false, changing nothing, if the job is no longer running
    /// (canceled or timed out meanwhile).
    fn update_running(&self, job: &Job) -> Result<bool, StoreError>;

    /// Cancels a queued or running job; returns it as it is now, or `None`
    /// if it was not queued or running.
    fn cancel(&self, id: &str, now_ms: u64) -> Result<Option<Job>, StoreError>;

    /// Puts a running job back in the queue (shutdown).
    fn requeue(&self, id: &str) -> Result<bool, StoreError>;

    /// After a restart: every job left running goes back to the queue, or
    /// fails if it has already been started `max_attempts` times (a job
    /// that kills the server must not do so forever). Returns the re-queued
    /// and the failed ids.
    fn recover(
        &self,
        max_attempts: u32,
        now_ms: u64,
    ) -> Result<(Vec<String>, Vec<String>), StoreError>;

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
}

/// Durable named blobs. Keys are `/`-separated relative paths. A `put` is
/// all or nothing: a reader sees the old content, the new, or nothing.
pub trait FileStore: Send + Sync + 'static {
    fn put(&self, key: &str, bytes: &[u8]) -> Result<(), StoreError>;

    fn get(&self, key: &str) -> Result<Option<Vec<u8>>, StoreError>;

    /// Copies a blob (the local store links it, an object store would copy
    /// server-side).
    fn copy(&self, from: &str, to: &str) -> Result<(), StoreError>;

    /// Removes `prefix` and everything under it; absent is not an error.
    fn delete_prefix(&self, prefix: &str) -> Result<(), StoreError>;

    /// Names directly under `prefix` (one level, no recursion).
    fn list(&self, prefix: &str) -> Result<Vec<String>, StoreError>;
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
