//! What routes and workers share.

use std::collections::HashMap;
use std::sync::atomic::{AtomicBool, AtomicU8, Ordering};
use std::sync::{Arc, Mutex};

use tokio::sync::{watch, Notify};

use super::config::Config;
use super::engine::Stop;
use super::error::ApiError;
use super::health::Health;
use super::metrics::Metrics;
use super::store::{FileStore, JobStore};

/// Stop signals a running job reads between stages.
pub const RUN: u8 = 0;
pub const CANCELED: u8 = 1;
pub const TIMED_OUT: u8 = 2;
pub const SHUTTING_DOWN: u8 = 3;

pub fn stop_of(flag: &AtomicU8) -> Option<Stop> {
    match flag.load(Ordering::Acquire) {
        CANCELED => Some(Stop::Canceled),
        TIMED_OUT => Some(Stop::TimedOut),
        SHUTTING_DOWN => Some(Stop::ShuttingDown),
        _ => None,
    }
}

pub struct App {
    pub cfg: Config,
    pub jobs: Arc<dyn JobStore>,
    pub files: Arc<dyn FileStore>,
    pub metrics: Metrics,
    /// Whether the stores and the disk answer, as last probed.
    pub health: Health,
    /// Bumped whenever a job reaches a final state; `Prefer: wait` listens.
    pub finished: watch::Sender<u64>,
    /// Wakes an idle worker when a job is queued.
    pub work: Notify,
    /// Set once on shutdown: stop accepting and claiming.
    pub stopping: watch::Sender<bool>,
    pub accepting: AtomicBool,
    /// The jobs running in this process: their stop flags, and the worker
    /// holding each one's lease.
    pub running: Mutex<HashMap<String, Running>>,
    /// This process among all that share the store: `HOST-PID`.
    pub process: String,
}

/// A job running in this process.
pub struct Running {
    pub flag: Arc<AtomicU8>,
    pub worker: String,
}

pub type Shared = Arc<App>;

impl App {
    pub fn new(cfg: Config, jobs: Arc<dyn JobStore>, files: Arc<dyn FileStore>) -> App {
        App {
            cfg,
            jobs,
            files,
            metrics: Metrics::default(),
            health: Health::default(),
            finished: watch::channel(0).0,
            work: Notify::new(),
            stopping: watch::channel(false).0,
            accepting: AtomicBool::new(true),
            running: Mutex::new(HashMap::new()),
            process: format!("{}-{}", host_name(), std::process::id()),
        }
    }

    pub fn running(&self) -> std::sync::MutexGuard<'_, HashMap<String, Running>> {
        self.running.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Signals a job running here to stop at its next checkpoint.
    pub fn signal(&self, id: &str, how: u8) {
        if let Some(r) = self.running().get(id) {
            r.flag.store(how, Ordering::Release);
        }
    }

    /// The name worker `index` of this process holds leases under.
    pub fn worker_name(&self, index: usize) -> String {
        format!("{}-{index}", self.process)
    }

    /// How long a claim holds before its worker must renew it.
    pub fn lease(&self) -> std::time::Duration {
        self.cfg.lease
    }

    pub fn announce_finished(&self) {
        self.finished.send_modify(|n| *n = n.wrapping_add(1));
    }

    pub fn is_stopping(&self) -> bool {
        *self.stopping.borrow()
    }
}

/// The machine's name, to tell apart the workers of a cluster.
fn host_name() -> String {
    let mut buf = [0u8; 256];
    // SAFETY: the buffer is valid for its length; the name is cut to it.
    let ok = unsafe { libc::gethostname(buf.as_mut_ptr().cast(), buf.len()) } == 0;
    let len = buf.iter().position(|&b| b == 0).unwrap_or(buf.len());
    match std::str::from_utf8(&buf[..len]) {
        Ok(name) if ok && !name.is_empty() => name.to_string(),
        _ => "localhost".to_string(),
    }
}

/// Runs store or file work on the blocking pool, off the async runtime.
pub async fn blocking<T, F>(app: &Shared, f: F) -> Result<T, ApiError>
where
    T: Send + 'static,
    F: FnOnce(&App) -> Result<T, ApiError> + Send + 'static,
{
    let app = app.clone();
    tokio::task::spawn_blocking(move || f(&app))
        .await
        .map_err(|e| {
            tracing::error!(error = %e, "blocking task failed");
            ApiError::internal("an internal task failed")
        })?
}
