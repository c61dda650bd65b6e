//! The HTTP service: uploads, a durable job queue, a worker pool, results.
//!
//! `seamstress serve` accepts models over HTTP (`api`), stores each job
//! and its upload durably before answering, and a pool of workers
//! (`worker`) runs the same loader and pipeline as `seamstress process`
//! (`engine`) off the async runtime. Routes and workers reach storage only
//! through the [`store::JobStore`] and [`store::FileStore`] traits; the
//! embedded implementations are SQLite ([`sqlite`]) and a local folder
//! ([`files`]), the cluster's PostgreSQL ([`postgres`]) and an
//! S3-compatible object store ([`objects`]). `seamstress worker`
//! (`worker_role.rs`) runs workers without the API.

mod api;
mod app;
pub mod callback;
pub mod config;
mod data_dir;
mod download;
mod engine;
mod error;
pub mod files;
mod health;
mod isolate;
pub mod job;
mod listen;
mod metrics;
pub mod objects;
pub mod postgres;
mod server;
pub mod sqlite;
pub mod store;
pub mod upload;
mod view;
mod worker;
mod worker_role;

pub use config::{Config, ServeArgs};
pub use server::{serve, ServeError};
pub use worker_role::{work, WorkerArgs};

/// `seamstress run-job DIR`: one job in a process of its own, for a
/// server's worker (see `service/isolate.rs`).
pub fn run_job(dir: &std::path::Path) -> std::io::Result<()> {
    isolate::child(dir)
}

/// Every route as (method, path), paths in OpenAPI syntax: what
/// `openapi.yaml` must describe.
pub fn route_table() -> Vec<(String, String)> {
    api::routes()
        .into_iter()
        .map(|(method, path, _)| {
            (
                method.as_str().to_ascii_lowercase(),
                path.replace("{*", "{"),
            )
        })
        .collect()
}

/// The OpenAPI document the server serves at `/openapi.yaml`.
pub const OPENAPI: &str = api::OPENAPI;
