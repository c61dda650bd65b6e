//! Start-up, recovery, the background tasks, and graceful shutdown.

use std::io::Write;
use std::net::SocketAddr;
use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::time::Duration;

use super::app::{App, Shared, SHUTTING_DOWN};
use super::config::{Config, ConfigError, FilesAt, ServeArgs};
use super::data_dir::{self, DataDirError, DataLock};
use super::files::LocalFileStore;
use super::health::Dependency;
use super::job::{is_job_id, now_ms};
use super::objects::ObjectFileStore;
use super::postgres::PgJobStore;
use super::sqlite::SqliteJobStore;
use super::store::{keys, FileStore, JobStore, Reclaimed, StoreError, StoreEvent};
use super::worker::{self, MAX_LOST_LEASES};

#[derive(Debug, thiserror::Error)]
pub enum ServeError {
    #[error(transparent)]
    Config(#[from] ConfigError),
    #[error(transparent)]
    Store(#[from] StoreError),
    #[error(transparent)]
    DataDir(#[from] DataDirError),
    #[error("cannot listen on {addr}: {source}")]
    Listen {
        addr: String,
        source: std::io::Error,
    },
    #[error("{0}")]
    Io(#[from] std::io::Error),
}

impl ServeError {
    /// Whether the operator must change something (exit status 2): the
    /// settings, the address, or the data folder; else the machine failed.
    pub fn is_usage(&self) -> bool {
        match self {
            ServeError::Config(_) | ServeError::Listen { .. } => true,
            ServeError::DataDir(e) => !matches!(e, DataDirError::Io { .. }),
            ServeError::Store(_) | ServeError::Io(_) => false,
        }
    }
}

/// `seamstress serve`: runs until SIGTERM or SIGINT.
pub fn serve(args: ServeArgs) -> Result<(), ServeError> {
    let cfg = Config::resolve(&args)?;
    let addrs = cfg.listen_addrs()?;
    let rt = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .thread_name("seamstress-http")
        .build()?;
    let result = rt.block_on(run(cfg, addrs));
    // Job threads still inside a stage after the grace period are not
    // waited for: their jobs are back in the queue.
    rt.shutdown_timeout(Duration::from_secs(1));
    result
}

/// The two stores a server runs on, and its hold on its data folder.
pub struct Stores {
    pub jobs: Arc<dyn JobStore>,
    pub files: Arc<dyn FileStore>,
    pub lock: DataLock,
    /// Whether this process is the stores' only user (the embedded ones),
    /// so that whatever is running in them at start was left by a crash.
    pub exclusive: bool,
}

/// Opens the stores `cfg` names, holding its data folder first: the
/// embedded ones once the job store is known to be the folder's own, or
/// the shared ones (PostgreSQL, an object store) whose connections run on
/// `rt`.
pub fn open_stores(cfg: &Config, rt: &tokio::runtime::Handle) -> Result<Stores, ServeError> {
    std::fs::create_dir_all(&cfg.data)
        .map_err(|e| StoreError::Files(format!("cannot create {}: {e}", cfg.data.display())))?;
    let lock = data_dir::lock(&cfg.data)?;
    // Scratch folders of job processes that a crash left behind, and the
    // processes themselves if they still run.
    super::isolate::stop_leftovers(&cfg.data.join("tmp"));
    let _ = std::fs::remove_dir_all(cfg.data.join("tmp"));
    let files_root = cfg.data.join("files");
    let jobs: Arc<dyn JobStore> = match &cfg.store {
        Some(url) => Arc::new(PgJobStore::open(url, rt.clone())?),
        None => {
            let store = data_dir::store_path(&cfg.data);
            // Job folders tell a lost store from a new one only when they
            // are kept here.
            let jobs_dir = files_root.join("jobs");
            let beside = cfg.files.is_none().then_some(jobs_dir.as_path());
            data_dir::check_store(&store, beside, cfg.rebuild_store)?;
            Arc::new(SqliteJobStore::open(&store)?)
        }
    };
    let files: Arc<dyn FileStore> = match &cfg.files {
        Some(FilesAt::Bucket(url)) => Arc::new(ObjectFileStore::open(url, rt.clone())?),
        Some(FilesAt::Folder(root)) => Arc::new(LocalFileStore::open(root)?),
        None => Arc::new(LocalFileStore::open(&files_root)?),
    };
    Ok(Stores {
        jobs,
        files,
        lock,
        exclusive: cfg.store.is_none(),
    })
}

/// Puts back what a crash interrupted. A process that owns its stores
/// takes back every running job at once, and removes files no job owns;
/// on shared stores others are running jobs, whose leases tell. Returns
/// the jobs taken back, for the lease counters.
fn recover(
    jobs: &dyn JobStore,
    files: &dyn FileStore,
    exclusive: bool,
) -> Result<Reclaimed, StoreError> {
    let now = now_ms();
    let expired_before = if exclusive { u64::MAX } else { now };
    let reclaimed = jobs.reclaim(expired_before, MAX_LOST_LEASES, now)?;
    for job in &reclaimed.requeued {
        tracing::info!(job_id = %job.id, "interrupted job re-queued");
    }
    for job in &reclaimed.failed {
        tracing::warn!(job_id = %job.id, "job failed: interrupted too often");
        files.delete_prefix(&keys::job(&job.id))?;
    }
    // On shared stores a file may be stored just before its job is: only
    // the lone owner can tell an orphan.
    if exclusive {
        for id in files.list("jobs")? {
            if !is_job_id(&id) || jobs.get(&id)?.is_none() {
                tracing::info!(dir = %id, "removing files of no job");
                files.delete_prefix(&keys::job(&id))?;
            }
        }
    }
    Ok(reclaimed)
}

/// Opens the stores and recovers them, off the async runtime.
async fn start_stores(cfg: &Config) -> Result<(Stores, Reclaimed), ServeError> {
    let (cfg, rt) = (cfg.clone(), tokio::runtime::Handle::current());
    tokio::task::spawn_blocking(move || {
        let stores = open_stores(&cfg, &rt)?;
        let reclaimed = recover(
            stores.jobs.as_ref(),
            stores.files.as_ref(),
            stores.exclusive,
        )?;
        Ok((stores, reclaimed))
    })
    .await
    .map_err(|e| StoreError::Jobs(e.to_string()))?
}

/// Wakes this process's idle workers and waiting requests when another
/// process sharing the store queues or finishes a job.
fn relay_store_events(app: &Shared) {
    let weak = Arc::downgrade(app);
    app.jobs.listen(Arc::new(move |event| {
        if let Some(app) = weak.upgrade() {
            match event {
                StoreEvent::Queued => {
                    // Every idle worker tries; the permit covers one that
                    // is between a claim and its wait.
                    app.work.notify_waiters();
                    app.work.notify_one();
                }
                StoreEvent::Finished => app.announce_finished(),
            }
        }
    }));
}

/// Every quarter of a lease, puts back the jobs whose lease ran out: their
/// worker died, or lost the store for longer than the lease.
async fn leases(app: Shared) {
    let mut stopping = app.stopping.subscribe();
    loop {
        tokio::select! {
            _ = tokio::time::sleep(app.lease() / 4) => {}
            _ = stopping.changed() => return,
        }
        // Without the job store no lease can be renewed, so leases that
        // ran out meanwhile say nothing of their workers: look only once
        // the store has answered for half a lease, time for every live
        // worker to renew (every third of a lease).
        if app
            .health
            .up_for(Dependency::Jobs)
            .is_none_or(|up| up < app.lease() / 2)
        {
            continue;
        }
        let (jobs, files) = (app.jobs.clone(), app.files.clone());
        let reclaimed = tokio::task::spawn_blocking(move || {
            let now = now_ms();
            let reclaimed = jobs.reclaim(now, MAX_LOST_LEASES, now)?;
            for job in &reclaimed.failed {
                files.delete_prefix(&keys::job(&job.id))?;
            }
            Ok::<_, StoreError>(reclaimed)
        })
        .await;
        match reclaimed {
            Ok(Ok(r)) => {
                for job in r.jobs() {
                    let worker = job.worker.as_deref().unwrap_or("");
                    tracing::warn!(job_id = %job.id, worker, "lease ran out; job taken back");
                    app.metrics.lease_expired(worker);
                }
                if !r.requeued.is_empty() {
                    app.work.notify_waiters();
                }
                if !r.failed.is_empty() {
                    app.announce_finished();
                }
            }
            Ok(Err(e)) => tracing::error!(error = %e, "cannot take back expired leases"),
            Err(e) => tracing::error!(error = %e, "lease task failed"),
        }
    }
}

async fn run(cfg: Config, addrs: Vec<SocketAddr>) -> Result<(), ServeError> {
    run_process(cfg, addrs, Role::Api).await
}

/// What a process serves besides its workers.
#[derive(Clone, Copy, PartialEq, Eq)]
pub(super) enum Role {
    /// The API, retention and callbacks (`serve`).
    Api,
    /// `/metrics` and `/healthz` only (`worker`).
    Worker,
}

/// A process's life: opens and recovers the stores, listens on `addrs`,
/// starts its workers and background tasks, serves until SIGTERM or
/// SIGINT, then shuts down within the grace period.
pub(super) async fn run_process(
    cfg: Config,
    addrs: Vec<SocketAddr>,
    role: Role,
) -> Result<(), ServeError> {
    let (
        Stores {
            jobs,
            files,
            lock: _lock,
            ..
        },
        reclaimed,
    ) = start_stores(&cfg).await?;
    let listener = super::listen::bind(&addrs).map_err(|source| ServeError::Listen {
        addr: cfg.listen.clone(),
        source,
    })?;
    let local = listener.local_addr()?;
    let workers = cfg.workers;
    let grace = cfg.grace;
    let limits = super::listen::Limits::of(&cfg);
    let app: Shared = Arc::new(App::new(cfg, jobs, files));
    // Leases taken back at start count as those the lease task takes back:
    // a process restarted while another's worker lay dead found its lease.
    for job in reclaimed.jobs() {
        app.metrics
            .lease_expired(job.worker.as_deref().unwrap_or(""));
    }

    relay_store_events(&app);
    for index in 0..workers {
        let thread = worker::JobThread::spawn(index)?;
        tokio::spawn(worker::worker(app.clone(), index, thread));
    }
    tokio::spawn(leases(app.clone()));
    tokio::spawn(super::health::probe(app.clone()));
    let routes = match role {
        Role::Api => {
            tokio::spawn(reaper(app.clone()));
            tokio::spawn(super::callback::dispatch(app.clone()));
            super::api::router(app.clone())
        }
        Role::Worker => super::api::operations_router(app.clone()),
    };

    let (stop_http, stopped) = tokio::sync::oneshot::channel::<()>();
    let mut server = tokio::spawn(super::listen::serve(listener, routes, limits, async move {
        let _ = stopped.await;
    }));
    // Tests and scripts read the address from the first line of stdout.
    {
        let mut out = std::io::stdout().lock();
        let _ = writeln!(out, "listening on {local}");
        let _ = out.flush();
    }
    // A relative default (`./data`) lands wherever the server was started:
    // the log says where.
    let data = std::path::absolute(&app.cfg.data).unwrap_or_else(|_| app.cfg.data.clone());
    tracing::info!(
        addr = %local,
        workers,
        process = %app.process,
        data = %data.display(),
        "listening"
    );

    tokio::select! {
        _ = shutdown_signal() => {}
        r = &mut server => {
            // The accept loop stopped on its own: it panicked.
            return r.map_err(|e| std::io::Error::other(e).into());
        }
    }
    shutdown(app, stop_http, grace).await;
    Ok(())
}

/// Stops accepting, lets running jobs finish within `grace`, and puts the
/// rest back in the queue (queued jobs stay queued: the store keeps them).
async fn shutdown(app: Shared, stop_http: tokio::sync::oneshot::Sender<()>, grace: Duration) {
    let deadline = tokio::time::Instant::now() + grace;
    tracing::info!(grace_s = grace.as_secs(), "shutting down");
    app.accepting.store(false, Ordering::Release);
    app.stopping.send_replace(true);
    let _ = stop_http.send(());
    while app.metrics.busy_workers.load(Ordering::Relaxed) > 0
        && tokio::time::Instant::now() < deadline
    {
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    let left: Vec<(String, String)> = {
        let running = app.running();
        for r in running.values() {
            r.flag.store(SHUTTING_DOWN, Ordering::Release);
        }
        running
            .iter()
            .map(|(id, r)| (id.clone(), r.worker.clone()))
            .collect()
    };
    if !left.is_empty() {
        let jobs = app.jobs.clone();
        let requeued = tokio::task::spawn_blocking(move || {
            left.iter()
                .filter(|(id, worker)| jobs.requeue(id, worker).unwrap_or(false))
                .count()
        })
        .await
        .unwrap_or(0);
        tracing::info!(requeued, "running jobs re-queued after the grace period");
    }
    tracing::info!("stopped");
}

async fn shutdown_signal() {
    #[cfg(unix)]
    {
        use tokio::signal::unix::{signal, SignalKind};
        match signal(SignalKind::terminate()) {
            Ok(mut term) => {
                tokio::select! {
                    _ = term.recv() => {}
                    _ = tokio::signal::ctrl_c() => {}
                }
            }
            Err(_) => {
                let _ = tokio::signal::ctrl_c().await;
            }
        }
    }
    #[cfg(not(unix))]
    {
        let _ = tokio::signal::ctrl_c().await;
    }
}

/// Deletes finished jobs older than the retention time, every minute.
async fn reaper(app: Shared) {
    let mut stopping = app.stopping.subscribe();
    loop {
        let retention = app.cfg.retention.as_millis() as u64;
        let cutoff = now_ms().saturating_sub(retention);
        let (jobs, files) = (app.jobs.clone(), app.files.clone());
        let swept = tokio::task::spawn_blocking(move || -> Result<usize, StoreError> {
            let mut n = 0;
            loop {
                let batch = jobs.expired(cutoff, 100)?;
                if batch.is_empty() {
                    return Ok(n);
                }
                for job in batch {
                    files.delete_prefix(&keys::job(&job.id))?;
                    jobs.delete(&job.id)?;
                    n += 1;
                }
            }
        })
        .await;
        match swept {
            Ok(Ok(0)) => {}
            Ok(Ok(n)) => tracing::info!(jobs = n, "expired jobs deleted"),
            Ok(Err(e)) => tracing::error!(error = %e, "cannot delete expired jobs"),
            Err(e) => tracing::error!(error = %e, "expiry task failed"),
        }
        tokio::select! {
            _ = tokio::time::sleep(Duration::from_secs(60)) => {}
            _ = stopping.changed() => return,
        }
    }
}
