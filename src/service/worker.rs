//! The worker pool: each worker claims the oldest queued job from the job
//! store, runs it on a thread of the worker's own, and stores its files and
//! outcome.

use std::panic::AssertUnwindSafe;
use std::sync::atomic::{AtomicU64, AtomicU8, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use sha2::{Digest, Sha256};
use tokio::sync::oneshot;
use tracing::Instrument;

use super::app::{stop_of, Running, Shared, CANCELED, RUN, TIMED_OUT};
use super::config::hex;
use super::engine::{EngineError, Produced, Stop};
use super::isolate::{self, Isolation};
use super::job::{now_ms, FileEntry, Job, JobError, JobState, Progress};
use super::store::{keys, Lease, StoreError};
use crate::budget::Limits;

/// A job whose lease has run out this many times fails instead of running
/// again. Leases run out when the server running the job dies (or loses its
/// job store for longer than a lease); a job runs in a process of its own,
/// so that is not the job's doing, and a few such losses are not charged.
/// Ten in a row is no longer weather: a job that somehow takes its server
/// down with it must not do so forever.
pub const MAX_LOST_LEASES: u32 = 10;

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
        // A job claimed now could neither be read nor stored: leave it
        // queued, where another process whose stores answer may take it.
        if app.health.down().is_some() {
            tokio::select! {
                _ = app.health.until_up(POLL * 5) => {}
                _ = stopping.changed() => {}
            }
            continue;
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
                app.health.saw(&e);
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
        let snapshot = job.clone();
        let waited = Arc::new(AtomicU64::new(0));
        let (task_app, task_flag, task_waited) = (app.clone(), flag.clone(), waited.clone());
        let mut handle = thread.run(move || {
            let run = Run {
                app: &task_app,
                flag: &task_flag,
                waited: &task_waited,
            };
            execute(&run, job)
        });
        let outcome = within_limit(app, &mut handle, &flag, &waited, &snapshot).await;
        settle(app, outcome, snapshot, worker, started).await;
        heartbeat.abort();
        app.running().remove(&id);
        app.metrics.busy_workers.fetch_sub(1, Ordering::Relaxed);
        app.announce_finished();
    }
    .instrument(span)
    .await
}

/// What the job thread's end means for the job: nothing more when it
/// recorded its own end; back to the queue, uncharged, after an outage;
/// failed when the store refused it for good or the thread panicked.
async fn settle(
    app: &Shared,
    outcome: Result<std::thread::Result<Result<JobState, StoreError>>, oneshot::error::RecvError>,
    job: Job,
    worker: &str,
    started: Instant,
) {
    let (code, message) = match outcome {
        Ok(Ok(Ok(state))) => {
            tracing::info!(state = state.as_str(), "job ended");
            return;
        }
        Ok(Ok(Err(e))) if e.is_outage() => {
            // Whatever the store did not take is done again: the job goes
            // back to the queue, this run not charged. Should the store
            // still be away, the lease runs out and whoever finds it puts
            // the job back the same way.
            tracing::warn!(error = %e, "job interrupted by an outage; back to the queue");
            let (store, id, worker) = (app.jobs.clone(), job.id.clone(), worker.to_string());
            let _ = tokio::task::spawn_blocking(move || store.requeue(&id, &worker)).await;
            app.work.notify_one();
            return;
        }
        Ok(Ok(Err(e))) => {
            tracing::error!(error = %e, "job store failed during the job");
            (e.job_code(), e.to_string())
        }
        // A bug, not the input's fault: the job fails as any failed job
        // does, rather than stay running for ever.
        Ok(Err(_)) | Err(_) => {
            tracing::error!("job thread panicked");
            ("internal", "the engine failed unexpectedly".to_string())
        }
    };
    let task_app = app.clone();
    let failed =
        tokio::task::spawn_blocking(move || fail_after(&task_app, job, code, &message, started))
            .await;
    if !matches!(failed, Ok(Ok(_))) {
        tracing::error!("cannot record the failure");
    }
}

/// Waits for the job thread, stopping the job at its time limit. Time the
/// job spent waiting out an outage does not count against the limit: the
/// limit is for jobs that outrun themselves, not for stores that are away.
async fn within_limit<T>(
    app: &Shared,
    handle: &mut oneshot::Receiver<T>,
    flag: &AtomicU8,
    waited: &AtomicU64,
    job: &Job,
) -> Result<T, oneshot::error::RecvError> {
    let start = tokio::time::Instant::now();
    loop {
        let excused = Duration::from_millis(waited.load(Ordering::Acquire));
        let deadline = start + app.cfg.job_timeout + excused;
        tokio::select! {
            r = &mut *handle => return r,
            _ = tokio::time::sleep_until(deadline) => {
                if waited.load(Ordering::Acquire) != excused.as_millis() as u64 {
                    continue;
                }
                flag.store(TIMED_OUT, Ordering::Release);
                time_out(app, job.clone()).await;
                // The thread stops at its next checkpoint; the slot stays
                // taken until then so that no more jobs run than workers.
                return handle.await;
            }
        }
    }
}

/// What a job's run reads besides the job: the process's shared state, the
/// job's stop flag, and the milliseconds it has spent waiting out outages.
struct Run<'a> {
    app: &'a Shared,
    flag: &'a AtomicU8,
    waited: &'a AtomicU64,
}

/// The first and the longest pause between tries of a store call that met
/// an outage: soon enough to catch a blip, rare enough not to hammer a
/// store that is coming back.
const OUTAGE_FIRST_WAIT: Duration = Duration::from_millis(500);
const OUTAGE_LONGEST_WAIT: Duration = Duration::from_secs(15);

impl Run<'_> {
    /// Calls `f` until it answers or fails for a reason of its own. An
    /// outage (a store that does not answer, a full disk) is waited out,
    /// with backoff, for as long as the job is not stopped; the lease is
    /// kept meanwhile by the heartbeat, as long as the job store answers.
    fn patiently<T>(
        &self,
        what: &'static str,
        mut f: impl FnMut() -> Result<T, StoreError>,
    ) -> Result<T, StoreError> {
        let mut wait = OUTAGE_FIRST_WAIT;
        let mut tries = 0u32;
        loop {
            let e = match f() {
                Ok(v) => return Ok(v),
                Err(e) if e.is_outage() && stop_of(self.flag).is_none() => e,
                Err(e) => return Err(e),
            };
            tries += 1;
            self.app.health.saw(&e);
            tracing::warn!(
                what,
                tries,
                retry_in_ms = wait.as_millis() as u64,
                error = %e,
                "waiting out an outage"
            );
            self.pause(wait);
            wait = (wait * 2).min(OUTAGE_LONGEST_WAIT);
        }
    }

    /// Sleeps for `d` or until the job is stopped, counting the time as
    /// waited out.
    fn pause(&self, d: Duration) {
        let began = Instant::now();
        while began.elapsed() < d && stop_of(self.flag).is_none() {
            std::thread::sleep(Duration::from_millis(50).min(d));
        }
        self.waited
            .fetch_add(began.elapsed().as_millis() as u64, Ordering::AcqRel);
    }
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
fn execute(r: &Run<'_>, mut job: Job) -> Result<JobState, StoreError> {
    let (app, started) = (r.app, Instant::now());
    let earlier = r.patiently("find an earlier result", || {
        app.jobs.find_succeeded(&job.owner, &job.input_key)
    })?;
    if let Some(earlier) = earlier {
        // An identical job finished while this one waited.
        if reuse(app, &earlier, &mut job).is_ok() {
            return finish(r, job, started);
        }
    }
    let upload = r.patiently("read the upload", || app.files.get(&keys::input(&job.id)))?;
    let Some(upload) = upload else {
        return fail(
            r,
            job,
            "internal",
            "the upload is missing from the file store",
            started,
        );
    };
    let outcome = run_engine(r, &mut job, &upload);
    drop(upload);
    match outcome {
        Ok(produced) => {
            if let Some(stop) = stop_of(r.flag) {
                return stopped(r, job, stop);
            }
            store_results(r, job, produced, started)
        }
        Err(EngineError::BadInput(message)) => fail(r, job, "invalid_model", message, started),
        Err(EngineError::TooLarge(message)) => fail(r, job, "too_large", message, started),
        Err(EngineError::Crashed(message)) => fail(r, job, "crashed", message, started),
        Err(EngineError::StorageFull(message)) => fail(r, job, "storage_full", message, started),
        Err(EngineError::Failed(message)) => fail(r, job, "processing_failed", message, started),
        Err(EngineError::Stopped(stop)) => stopped(r, job, stop),
    }
}

/// A disk that stays full while the job's process is started this many
/// times, with the outage waits between them (about ten minutes in all),
/// is no longer a moment: the job needs more room than there is.
const STORAGE_FULL_RUNS: u32 = 40;

/// Runs the job's process. One that dies is tried once more: a crash may
/// be the machine's (the OOM killer, a signal), not the input's. One that
/// finds the disk full waits for room and runs again, uncharged.
fn run_engine(r: &Run<'_>, job: &mut Job, upload: &[u8]) -> Result<Produced, EngineError> {
    let app = r.app;
    let limits = Limits {
        max_memory: app.cfg.max_memory,
    };
    let exe = std::env::current_exe()
        .map_err(|e| EngineError::Failed(format!("cannot find the binary: {e}")))?;
    let iso = Isolation {
        exe,
        address_space: app.cfg.job_address_space,
        scratch: app.cfg.data.join("tmp"),
    };
    let options = job.options;
    let (mut crashes, mut full, mut wait) = (0, 0, OUTAGE_FIRST_WAIT);
    loop {
        // A folder of this run's own: a process of an earlier run (of a
        // server that died) may still be writing its own.
        let tag = format!("{}-{}-{}", job.id, std::process::id(), crashes + full);
        let mut checkpoint = |at: &Progress| -> Result<(), Stop> {
            if let Some(stop) = stop_of(r.flag) {
                return Err(stop);
            }
            job.progress = at.clone();
            match app.jobs.update_running(job) {
                Ok(true) => Ok(()),
                // Canceled, or timed out, through the store.
                Ok(false) => Err(Stop::Canceled),
                // Progress is not worth waiting for: the job goes on, and
                // the next checkpoint or the result says it again.
                Err(e) => {
                    app.health.saw(&e);
                    tracing::warn!(error = %e, "cannot record progress");
                    Ok(())
                }
            }
        };
        let outcome = isolate::run(
            &iso,
            &tag,
            upload,
            &options,
            app.cfg.max_texture_size,
            &limits,
            &mut checkpoint,
            &|| stop_of(r.flag),
        );
        match &outcome {
            Err(EngineError::Crashed(_)) if crashes == 0 => {
                crashes += 1;
                tracing::warn!("job process crashed; trying once more");
            }
            Err(EngineError::StorageFull(message))
                if full + 1 < STORAGE_FULL_RUNS && stop_of(r.flag).is_none() =>
            {
                full += 1;
                app.health.saw(&StoreError::Full(message.clone()));
                tracing::warn!(runs = full, retry_in_ms = wait.as_millis() as u64, message = %message, "disk full under the job; waiting for room");
                r.pause(wait);
                wait = (wait * 2).min(OUTAGE_LONGEST_WAIT);
            }
            _ => return outcome,
        }
    }
}

/// Stores a finished run's files and its record. A store that is away is
/// waited for: the results are in hand, and running the job again would
/// cost more than waiting.
fn store_results(
    r: &Run<'_>,
    mut job: Job,
    produced: Produced,
    started: Instant,
) -> Result<JobState, StoreError> {
    let app = r.app;
    job.progress = Progress::at("store", 0.95);
    if !r.patiently("record progress", || app.jobs.update_running(&job))? {
        return stopped(r, job, Stop::Canceled);
    }
    let t = Instant::now();
    let blobs: Vec<(String, &[u8])> = produced
        .files
        .iter()
        .map(|(name, bytes)| (keys::output(&job.id, name), bytes.as_slice()))
        .collect();
    let put = r.patiently("store the results", || app.files.put_all(&blobs));
    if let Err(e) = put {
        // No partial results, even should recording the failure fail too
        // (`fail` then removes the rest).
        let _ = app.files.delete_prefix(&keys::outputs(&job.id));
        let message = format!("cannot store the results: {e}");
        return fail(r, job, e.job_code(), message, started);
    }
    job.files = produced
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
    finish(r, job, started)
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

fn finish(r: &Run<'_>, mut job: Job, started: Instant) -> Result<JobState, StoreError> {
    let app = r.app;
    job.state = JobState::Succeeded;
    job.finished_ms = Some(now_ms());
    job.progress = Progress::at("done", 1.0);
    job.timings_ms.total = Some(started.elapsed().as_millis() as u64);
    if !r.patiently("record the result", || app.jobs.update_running(&job))? {
        return lost(r, &job.id);
    }
    r.patiently("remove the upload", || {
        app.files.remove(&keys::input(&job.id))
    })?;
    if let Some(ms) = job.timings_ms.total {
        app.metrics.stage("total", ms);
    }
    app.metrics.finished(JobState::Succeeded);
    Ok(JobState::Succeeded)
}

fn fail(
    r: &Run<'_>,
    mut job: Job,
    code: &str,
    message: impl Into<String>,
    started: Instant,
) -> Result<JobState, StoreError> {
    let app = r.app;
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
    if !r.patiently("record the failure", || app.jobs.update_running(&job))? {
        return lost(r, &job.id);
    }
    r.patiently("remove the job's files", || {
        app.files.delete_prefix(&keys::job(&job.id))
    })?;
    app.metrics.finished(JobState::Failed);
    Ok(JobState::Failed)
}

/// Records the failure of a run whose thread has ended without doing so
/// (it panicked, or its store failed for good).
fn fail_after(
    app: &Shared,
    job: Job,
    code: &str,
    message: &str,
    started: Instant,
) -> Result<JobState, StoreError> {
    let (flag, waited) = (AtomicU8::new(RUN), AtomicU64::new(0));
    let r = Run {
        app,
        flag: &flag,
        waited: &waited,
    };
    fail(&r, job, code, message, started)
}

fn stopped(r: &Run<'_>, job: Job, stop: Stop) -> Result<JobState, StoreError> {
    match stop {
        Stop::ShuttingDown => {
            r.app
                .jobs
                .requeue(&job.id, job.worker.as_deref().unwrap_or_default())?;
            tracing::info!("job re-queued for the next start");
            Ok(JobState::Queued)
        }
        Stop::Canceled | Stop::TimedOut => lost(r, &job.id),
    }
}

/// The store no longer has the job as running (canceled, timed out,
/// re-queued or deleted meanwhile): whatever this run wrote goes, unless
/// the job is waiting to run again.
fn lost(r: &Run<'_>, id: &str) -> Result<JobState, StoreError> {
    let app = r.app;
    let current = r.patiently("read the job", || app.jobs.get(id))?;
    let state = match current.as_ref().map(|j| j.state) {
        Some(JobState::Queued) => return Ok(JobState::Queued),
        Some(state) => state,
        None => JobState::Canceled,
    };
    r.patiently("remove the job's files", || {
        app.files.delete_prefix(&keys::job(id))
    })?;
    Ok(state)
}

pub fn content_type(name: &str) -> &'static str {
    let ext = name.rsplit('.').next().unwrap_or("").to_ascii_lowercase();
    match ext.as_str() {
        "dds" => "image/vnd-ms.dds",
        "ktx2" => "image/ktx2",
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
