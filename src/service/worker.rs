//! The worker pool: each worker claims the oldest queued job from the job
//! store, runs it on a thread of the worker's own, and stores its files and
//! outcome.

use std::panic::AssertUnwindSafe;
use std::sync::atomic::{AtomicU8, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use sha2::{Digest, Sha256};
use tokio::sync::oneshot;
use tracing::Instrument;

use super::app::{stop_of, Running, Shared, CANCELED, RUN, TIMED_OUT};
use super::config::hex;
use super::engine::{EngineError, Stop};
use super::isolate::{self, Isolation};
use super::job::{now_ms, FileEntry, Job, JobError, JobState, Progress};
use super::store::{keys, Lease, StoreError};
use crate::budget::Limits;

/// A job that has been started this many times without finishing (each
/// start interrupted by a crash) fails instead of running again.
pub const MAX_ATTEMPTS: u32 = 3;

/// How often an idle worker looks at the queue without being woken: other
/// processes sharing the store may have queued work.
const POLL: Duration = Duration::from_secs(1);

/// A worker's own thread for the engine: every job of the worker runs on it.
///
/// The engine's dense kernels (faer's gemm) keep a scratch buffer of twice
/// the L3 cache in every thread that runs them, for the thread's life. On
/// tokio's blocking pool, whose threads come and go, each new thread that
/// ran a job added one (64 MB here), and the heap kept the pages after the
/// thread ended: a server's resident memory grew with the jobs it had run.
/// With one thread per worker there are as many buffers as workers.
pub struct JobThread {
    tasks: std::sync::mpsc::Sender<Box<dyn FnOnce() + Send>>,
}

impl JobThread {
    pub fn spawn(index: usize) -> std::io::Result<JobThread> {
        let (tasks, queue) = std::sync::mpsc::channel::<Box<dyn FnOnce() + Send>>();
        std::thread::Builder::new()
            .name(format!("seamstress-job-{index}"))
            .spawn(move || {
                for task in queue {
                    task();
                }
            })?;
        Ok(JobThread { tasks })
    }

    /// Runs `f` on the thread, inside the caller's tracing span. The answer
    /// is `f`'s result, or an error if `f` panicked (the thread lives on).
    fn run<T: Send + 'static>(
        &self,
        f: impl FnOnce() -> T + Send + 'static,
    ) -> oneshot::Receiver<std::thread::Result<T>> {
        let (answer, receiver) = oneshot::channel();
        let span = tracing::Span::current();
        let task = Box::new(move || {
            let _entered = span.enter();
            let _ = answer.send(std::panic::catch_unwind(AssertUnwindSafe(f)));
        });
        // If the thread is gone, the task and its sender drop here, and the
        // receiver reports that.
        let _ = self.tasks.send(task);
        receiver
    }
}

pub async fn worker(app: Shared, index: usize, thread: JobThread) {
    let name = app.worker_name(index);
    let mut stopping = app.stopping.subscribe();
    // Whether jobs have run since this worker last handed freed memory back.
    let mut used = false;
    loop {
        if app.is_stopping() {
            return;
        }
        let (store, worker, lease) = (app.jobs.clone(), name.clone(), app.lease());
        let claimed = tokio::task::spawn_blocking(move || {
            let now = now_ms();
            let lease = Lease {
                worker: &worker,
                until_ms: now + lease.as_millis() as u64,
            };
            store.claim(&lease, now)
        })
        .await;
        match claimed {
            Ok(Ok(Some(job))) => {
                app.metrics.claimed(&name);
                run(&app, job, &name, &thread).await;
                used = true;
            }
            Ok(Ok(None)) => {
                // Idle: hand the jobs' freed memory back (see `heap`). Not
                // after every job: back to back, the next job reuses those
                // pages, where fresh ones cost a fault each (a tenth or more
                // of a 2048² job's time).
                if std::mem::take(&mut used) {
                    crate::heap::release_freed_memory();
                }
                tokio::select! {
                    _ = app.work.notified() => {}
                    _ = tokio::time::sleep(POLL) => {}
                    _ = stopping.changed() => {}
                }
            }
            Ok(Err(e)) => {
                tracing::error!(worker = index, error = %e, "cannot claim a job");
                tokio::time::sleep(POLL).await;
            }
            Err(e) => {
                tracing::error!(worker = index, error = %e, "claim task failed");
                tokio::time::sleep(POLL).await;
            }
        }
    }
}

async fn run(app: &Shared, job: Job, worker: &str, thread: &JobThread) {
    let id = job.id.clone();
    let span = tracing::info_span!("job", job_id = %id, worker);
    async {
        let flag = Arc::new(AtomicU8::new(RUN));
        app.running().insert(
            id.clone(),
            Running {
                flag: flag.clone(),
                worker: worker.to_string(),
            },
        );
        let heartbeat = tokio::spawn(keep_lease(
            app.clone(),
            id.clone(),
            worker.to_string(),
            flag.clone(),
        ));
        app.metrics.busy_workers.fetch_add(1, Ordering::Relaxed);
        if let Some(q) = job.timings_ms.queued {
            app.metrics.stage("queued", q);
        }
        tracing::info!(attempt = job.attempts, input = %job.input.name, "job started");

        let started = Instant::now();
        let deadline = tokio::time::Instant::now() + app.cfg.job_timeout;
        let snapshot = job.clone();
        let (task_app, task_flag) = (app.clone(), flag.clone());
        let mut handle = thread.run(move || execute(&task_app, job, &task_flag));
        let outcome = tokio::select! {
            r = &mut handle => r,
            _ = tokio::time::sleep_until(deadline) => {
                flag.store(TIMED_OUT, Ordering::Release);
                time_out(app, snapshot.clone()).await;
                // The thread stops at its next checkpoint; the slot stays
                // taken until then so that no more jobs run than workers.
                handle.await
            }
        };
        match outcome {
            Ok(Ok(Ok(state))) => {
                tracing::info!(state = state.as_str(), "job ended");
            }
            Ok(Ok(Err(e))) => {
                tracing::error!(error = %e, "job store failed during the job");
                let (task_app, job) = (app.clone(), snapshot);
                let (code, message) = (e.job_code(), e.to_string());
                let failed = tokio::task::spawn_blocking(move || {
                    fail(&task_app, job, code, message, started)
                })
                .await;
                if !matches!(failed, Ok(Ok(_))) {
                    tracing::error!("cannot record the failure");
                }
            }
            // A bug, not the input's fault: the job fails as any failed job
            // does, rather than stay running for ever.
            Ok(Err(_)) | Err(_) => {
                tracing::error!("job thread panicked");
                let (task_app, job) = (app.clone(), snapshot);
                let message = "the engine failed unexpectedly";
                let failed = tokio::task::spawn_blocking(move || {
                    fail(&task_app, job, "internal", message, started)
                })
                .await;
                if !matches!(failed, Ok(Ok(_))) {
                    tracing::error!("cannot record the failure");
                }
            }
        }
        heartbeat.abort();
        app.running().remove(&id);
        app.metrics.busy_workers.fetch_sub(1, Ordering::Relaxed);
        app.announce_finished();
    }
    .instrument(span)
    .await
}

/// Renews the lease on a running job every third of its length, so that
/// it outlives any one stage. A renewal the store refuses means the job was
/// canceled (perhaps through another server) or given to another worker:
/// the job stops at its next checkpoint.
async fn keep_lease(app: Shared, id: String, worker: String, flag: Arc<AtomicU8>) {
    let every = app.lease() / 3;
    loop {
        tokio::time::sleep(every).await;
        let (store, job, name, lease) = (app.jobs.clone(), id.clone(), worker.clone(), app.lease());
        let renewed = tokio::task::spawn_blocking(move || {
            let lease = Lease {
                worker: &name,
                until_ms: now_ms() + lease.as_millis() as u64,
            };
            store.renew(&job, &lease)
        })
        .await;
        match renewed {
            Ok(Ok(true)) => {}
            Ok(Ok(false)) => {
                tracing::info!("lease refused: the job was canceled or reclaimed");
                let _ = flag.compare_exchange(RUN, CANCELED, Ordering::AcqRel, Ordering::Acquire);
                return;
            }
            // The store is unreachable: keep running, and keep trying; if
            // the lease runs out meanwhile, the store refuses the results.
            Ok(Err(e)) => tracing::warn!(error = %e, "cannot renew the lease"),
            Err(e) => tracing::warn!(error = %e, "lease task failed"),
        }
    }
}

async fn time_out(app: &Shared, mut job: Job) {
    let limit = app.cfg.job_timeout.as_secs();
    job.state = JobState::Failed;
    job.finished_ms = Some(now_ms());
    job.progress = Progress::at("done", job.progress.fraction);
    job.error = Some(JobError {
        code: "timeout".into(),
        message: format!("the job took longer than its limit of {limit} s"),
    });
    let store = app.jobs.clone();
    match tokio::task::spawn_blocking(move || store.update_running(&job)).await {
        Ok(Ok(true)) => {
            tracing::warn!(limit_s = limit, "job timed out");
            app.metrics.finished(JobState::Failed);
            app.announce_finished();
        }
        Ok(Ok(false)) => {}
        Ok(Err(e)) => tracing::error!(error = %e, "cannot record the time-out"),
        Err(e) => tracing::error!(error = %e, "time-out task failed"),
    }
}

/// Runs a claimed job to its end on the current thread (the worker's
/// [`JobThread`]) and returns the state it ended in.
fn execute(app: &Shared, mut job: Job, flag: &AtomicU8) -> Result<JobState, StoreError> {
    let started = Instant::now();
    if let Some(earlier) = app.jobs.find_succeeded(&job.owner, &job.input_key)? {
        // An identical job finished while this one waited.
        if reuse(app, &earlier, &mut job).is_ok() {
            return finish(app, job, started);
        }
    }
    let Some(upload) = app.files.get(&keys::input(&job.id))? else {
        return fail(
            app,
            job,
            "internal",
            "the upload is missing from the file store",
            started,
        );
    };
    let options = job.options;
    let limits = Limits {
        max_memory: app.cfg.max_memory,
    };
    let iso = Isolation {
        exe: match std::env::current_exe() {
            Ok(exe) => exe,
            Err(e) => {
                return fail(
                    app,
                    job,
                    "internal",
                    format!("cannot find the binary: {e}"),
                    started,
                )
            }
        },
        address_space: app.cfg.job_address_space,
        scratch: app.cfg.data.join("tmp"),
    };
    let mut outcome = Err(EngineError::Crashed(String::new()));
    // A job process that dies is tried once more: a crash may be the
    // machine's (the OOM killer, a signal), not the input's.
    for attempt in 0..2 {
        if attempt > 0 {
            tracing::warn!(attempt, "job process crashed; trying once more");
        }
        let tag = format!("{}-{attempt}", job.id);
        let mut checkpoint = |at: &Progress| -> Result<(), Stop> {
            if let Some(stop) = stop_of(flag) {
                return Err(stop);
            }
            job.progress = at.clone();
            match app.jobs.update_running(&job) {
                Ok(true) => Ok(()),
                // Canceled, or timed out, through the store.
                Ok(false) => Err(Stop::Canceled),
                Err(e) => {
                    tracing::warn!(error = %e, "cannot record progress");
                    Ok(())
                }
            }
        };
        outcome = isolate::run(
            &iso,
            &tag,
            &upload,
            &options,
            app.cfg.max_texture_size,
            &limits,
            &mut checkpoint,
            &|| stop_of(flag),
        );
        if !matches!(outcome, Err(EngineError::Crashed(_))) {
            break;
        }
    }
    drop(upload);
    match outcome {
        Ok(produced) => {
            if let Some(stop) = stop_of(flag) {
                return stopped(app, job, stop);
            }
            job.progress = Progress::at("store", 0.95);
            if !app.jobs.update_running(&job)? {
                return stopped(app, job, Stop::Canceled);
            }
            let t = Instant::now();
            let blobs: Vec<(String, &[u8])> = produced
                .files
                .iter()
                .map(|(name, bytes)| (keys::output(&job.id, name), bytes.as_slice()))
                .collect();
            if let Err(e) = app.files.put_all(&blobs) {
                // No partial results, even should recording the failure
                // fail too (`fail` then removes the rest).
                let _ = app.files.delete_prefix(&keys::outputs(&job.id));
                let message = format!("cannot store the results: {e}");
                return fail(app, job, e.job_code(), message, started);
            }
            let files = produced
                .files
                .iter()
                .map(|(name, bytes)| FileEntry {
                    name: name.clone(),
                    bytes: bytes.len() as u64,
                    sha256: hex(&Sha256::digest(bytes)),
                    content_type: content_type(name).to_string(),
                })
                .collect();
            job.timings_ms.load = produced.timings.load;
            job.timings_ms.process = produced.timings.process;
            job.timings_ms.rewrite = produced.timings.rewrite;
            job.timings_ms.store = Some(t.elapsed().as_millis() as u64);
            job.report = Some(produced.report);
            job.files = files;
            job.warnings = produced.warnings;
            for (stage, ms) in [
                ("load", job.timings_ms.load),
                ("process", job.timings_ms.process),
                ("rewrite", job.timings_ms.rewrite),
                ("store", job.timings_ms.store),
            ] {
                if let Some(ms) = ms {
                    app.metrics.stage(stage, ms);
                }
            }
            finish(app, job, started)
        }
        Err(EngineError::BadInput(message)) => fail(app, job, "invalid_model", message, started),
        Err(EngineError::TooLarge(message)) => fail(app, job, "too_large", message, started),
        Err(EngineError::Crashed(message)) => fail(app, job, "crashed", message, started),
        Err(EngineError::StorageFull(message)) => fail(app, job, "storage_full", message, started),
        Err(EngineError::Failed(message)) => fail(app, job, "processing_failed", message, started),
        Err(EngineError::Stopped(stop)) => stopped(app, job, stop),
    }
}

/// Takes the files of an earlier identical job.
fn reuse(app: &Shared, earlier: &Job, job: &mut Job) -> Result<(), StoreError> {
    for f in &earlier.files {
        app.files.copy(
            &keys::output(&earlier.id, &f.name),
            &keys::output(&job.id, &f.name),
        )?;
    }
    job.files = earlier.files.clone();
    job.report = earlier.report.clone();
    job.warnings = earlier.warnings.clone();
    job.cached_from = Some(earlier.id.clone());
    app.metrics.cache_hits.fetch_add(1, Ordering::Relaxed);
    tracing::info!(from = %earlier.id, "result reused");
    Ok(())
}

fn finish(app: &Shared, mut job: Job, started: Instant) -> Result<JobState, StoreError> {
    job.state = JobState::Succeeded;
    job.finished_ms = Some(now_ms());
    job.progress = Progress::at("done", 1.0);
    job.timings_ms.total = Some(started.elapsed().as_millis() as u64);
    if !app.jobs.update_running(&job)? {
        return lost(app, &job.id);
    }
    app.files.remove(&keys::input(&job.id))?;
    if let Some(ms) = job.timings_ms.total {
        app.metrics.stage("total", ms);
    }
    app.metrics.finished(JobState::Succeeded);
    Ok(JobState::Succeeded)
}

fn fail(
    app: &Shared,
    mut job: Job,
    code: &str,
    message: impl Into<String>,
    started: Instant,
) -> Result<JobState, StoreError> {
    let message = message.into();
    tracing::warn!(code, message = %message, "job failed");
    job.state = JobState::Failed;
    job.finished_ms = Some(now_ms());
    job.progress = Progress::at("done", job.progress.fraction);
    job.timings_ms.total = Some(started.elapsed().as_millis() as u64);
    job.error = Some(JobError {
        code: code.into(),
        message,
    });
    if !app.jobs.update_running(&job)? {
        return lost(app, &job.id);
    }
    app.files.delete_prefix(&keys::job(&job.id))?;
    app.metrics.finished(JobState::Failed);
    Ok(JobState::Failed)
}

fn stopped(app: &Shared, job: Job, stop: Stop) -> Result<JobState, StoreError> {
    match stop {
        Stop::ShuttingDown => {
            app.jobs
                .requeue(&job.id, job.worker.as_deref().unwrap_or_default())?;
            tracing::info!("job re-queued for the next start");
            Ok(JobState::Queued)
        }
        Stop::Canceled | Stop::TimedOut => lost(app, &job.id),
    }
}

/// The store no longer has the job as running (canceled, timed out,
/// re-queued or deleted meanwhile): whatever this run wrote goes, unless
/// the job is waiting to run again.
fn lost(app: &Shared, id: &str) -> Result<JobState, StoreError> {
    let current = app.jobs.get(id)?;
    match current.as_ref().map(|j| j.state) {
        Some(JobState::Queued) => Ok(JobState::Queued),
        Some(state) => {
            app.files.delete_prefix(&keys::job(id))?;
            Ok(state)
        }
        None => {
            app.files.delete_prefix(&keys::job(id))?;
            Ok(JobState::Canceled)
        }
    }
}

pub fn content_type(name: &str) -> &'static str {
    let ext = name.rsplit('.').next().unwrap_or("").to_ascii_lowercase();
    match ext.as_str() {
        "dds" => "image/vnd-ms.dds",
        "png" => "image/png",
        "jpg" | "jpeg" => "image/jpeg",
        "json" => "application/json",
        "gltf" => "model/gltf+json",
        "glb" => "model/gltf-binary",
        _ => "application/octet-stream",
    }
}

#[cfg(test)]
mod tests {
    use super::JobThread;

    #[test]
    fn jobs_share_one_thread_that_outlives_a_panic() {
        let t = JobThread::spawn(7).unwrap();
        let thread = || std::thread::current().id();
        let before = t.run(thread).blocking_recv().unwrap().unwrap();
        let panicked = t.run(|| -> u32 { panic!("a bug in a job") });
        assert!(panicked.blocking_recv().unwrap().is_err());
        let after = t.run(thread).blocking_recv().unwrap().unwrap();
        assert_eq!(before, after);
        assert_ne!(before, std::thread::current().id());
        let name = t.run(|| std::thread::current().name().map(str::to_owned));
        assert_eq!(
            name.blocking_recv().unwrap().unwrap().as_deref(),
            Some("seamstress-job-7")
        );
    }
}
