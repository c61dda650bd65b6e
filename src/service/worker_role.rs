//! `seamstress worker`: a process that claims and runs jobs from a shared
//! job store, with no API. It serves only `/metrics` and `/healthz`, on
//! `--metrics-listen`.
//!
//! Any number of workers and API servers share one PostgreSQL store and
//! one file store; the worker takes the same settings (flags, environment,
//! `--config` file) as `seamstress serve`, and its own `--workers` and
//! memory budget.

use std::path::PathBuf;
use std::time::Duration;

use super::config::{Config, ConfigError, ServeArgs};
use super::server::{self, Role, ServeError};

/// `seamstress worker`'s options: the part of `serve`'s that a worker uses.
#[derive(clap::Args, Clone, Debug, Default)]
pub struct WorkerArgs {
    /// The job store shared with the API servers: postgres://USER@HOST:PORT/DB.
    #[arg(long, env = "SEAMSTRESS_STORE", hide_env_values = true)]
    pub store: Option<String>,
    /// Where job files live, shared with the API servers: s3://BUCKET/PREFIX
    /// (endpoint and credentials from the AWS_* environment variables) or
    /// a folder every process mounts.
    #[arg(long, env = "SEAMSTRESS_FILES")]
    pub files: Option<String>,
    /// Address of /metrics and /healthz [default: 127.0.0.1:9090].
    #[arg(long, env = "SEAMSTRESS_METRICS_LISTEN")]
    pub metrics_listen: Option<String>,
    /// Scratch space for the jobs' processes [default: ./data].
    #[arg(long, env = "SEAMSTRESS_DATA")]
    pub data: Option<PathBuf>,
    /// TOML file with any of `serve`'s options; those a worker has no use
    /// for are ignored.
    #[arg(long, env = "SEAMSTRESS_CONFIG")]
    pub config: Option<PathBuf>,
    /// Jobs processed at once [default: the number of cores].
    #[arg(long, env = "SEAMSTRESS_WORKERS")]
    pub workers: Option<usize>,
    /// Time limit of one job, e.g. 600s, 10m [default: 10m].
    #[arg(long, env = "SEAMSTRESS_JOB_TIMEOUT")]
    pub job_timeout: Option<String>,
    /// On SIGTERM, how long running jobs may take to finish before they are
    /// re-queued [default: 30s].
    #[arg(long, env = "SEAMSTRESS_GRACE")]
    pub grace: Option<String>,
    /// How long a claim holds without renewal [default: 30s].
    #[arg(long, env = "SEAMSTRESS_LEASE")]
    pub lease: Option<String>,
    /// Largest texture width or height [default: 16384].
    #[arg(long, env = "SEAMSTRESS_MAX_TEXTURE_SIZE")]
    pub max_texture_size: Option<u32>,
    /// Peak memory one job may use, e.g. 2GiB [default: the memory
    /// available at start divided among its workers].
    #[arg(long, env = "SEAMSTRESS_MAX_MEMORY")]
    pub max_memory: Option<String>,
    /// Address space each job's process may map [default: twice
    /// --max-memory, at least 2GiB more than it].
    #[arg(long, env = "SEAMSTRESS_JOB_ADDRESS_SPACE")]
    pub job_address_space: Option<String>,
}

impl WorkerArgs {
    fn config(&self) -> Result<Config, ConfigError> {
        let mut cfg = Config::resolve(&ServeArgs {
            data: self.data.clone(),
            config: self.config.clone(),
            store: self.store.clone(),
            files: self.files.clone(),
            lease: self.lease.clone(),
            workers: self.workers,
            job_timeout: self.job_timeout.clone(),
            grace: self.grace.clone(),
            max_texture_size: self.max_texture_size,
            max_memory: self.max_memory.clone(),
            job_address_space: self.job_address_space.clone(),
            ..ServeArgs::default()
        })?;
        cfg.listen = self
            .metrics_listen
            .clone()
            .unwrap_or_else(|| "127.0.0.1:9090".into());
        let invalid = |option, message: &str| ConfigError::Invalid {
            option,
            message: message.to_string(),
        };
        if cfg.store.is_none() {
            return Err(invalid(
                "store",
                "a worker shares the API servers' job store: pass --store postgres://…",
            ));
        }
        if cfg.files.is_none() {
            return Err(invalid(
                "files",
                "a worker shares the API servers' files: pass --files s3://… or a shared folder",
            ));
        }
        if cfg.workers == 0 {
            return Err(invalid("workers", "a worker process needs at least 1"));
        }
        Ok(cfg)
    }
}

/// `seamstress worker`: runs until SIGTERM or SIGINT.
pub fn work(args: WorkerArgs) -> Result<(), ServeError> {
    let cfg = args.config()?;
    // Metrics only: no tokens guard them, so they stay on loopback unless
    // the operator says otherwise with an explicit address.
    let addrs = cfg.listen_addrs_unchecked()?;
    let rt = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .thread_name("seamstress-worker")
        .build()?;
    let result = rt.block_on(server::run_process(cfg, addrs, Role::Worker));
    rt.shutdown_timeout(Duration::from_secs(1));
    result
}
