//! `seamstress view OUTDIR`: the view page over a folder `process` wrote,
//! on loopback. The folder is served under the routes the service uses for
//! one job ([`LOCAL_JOB`]), so the page is the same.

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use axum::extract::{Path as UrlPath, State};
use axum::http::{header, StatusCode};
use axum::response::{IntoResponse, Redirect, Response};
use axum::routing::get;
use axum::{Json, Router};
use serde_json::{json, Value};

use super::assets::{asset, JOB_PAGE, LIST_PAGE};

/// The id the folder is served as.
pub const LOCAL_JOB: &str = "local";

#[derive(Debug, thiserror::Error)]
pub enum ViewError {
    #[error("{0}: no report.json; give the folder of one model's outputs of `seamstress process`")]
    NoReport(PathBuf),
    #[error("cannot read {path}: {source}")]
    Read {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{path}: not a report: {source}")]
    Report {
        path: PathBuf,
        #[source]
        source: serde_json::Error,
    },
    #[error("cannot listen on {addr}: {source}")]
    Bind {
        addr: SocketAddr,
        #[source]
        source: std::io::Error,
    },
    #[error("the server stopped: {0}")]
    Serve(#[source] std::io::Error),
}

/// What the routes read: the folder and the job it is shown as.
struct Folder {
    dir: PathBuf,
    /// The job as `GET /v1/jobs/{id}` shows one, with the folder's report.
    job: Value,
}

/// The folder as a succeeded job: its report and its files.
fn job_of(dir: &Path) -> Result<Value, ViewError> {
    let path = dir.join("report.json");
    if !path.is_file() {
        return Err(ViewError::NoReport(dir.to_path_buf()));
    }
    let read = |p: &Path| {
        std::fs::read(p).map_err(|source| ViewError::Read {
            path: p.to_path_buf(),
            source,
        })
    };
    let report: Value = serde_json::from_slice(&read(&path)?)
        .map_err(|source| ViewError::Report { path, source })?;
    let entries = std::fs::read_dir(dir).map_err(|source| ViewError::Read {
        path: dir.to_path_buf(),
        source,
    })?;
    let mut files = Vec::new();
    for entry in entries.flatten() {
        let meta = entry.metadata().ok();
        if !meta.as_ref().is_some_and(|m| m.is_file()) {
            continue;
        }
        if let Some(name) = entry.file_name().to_str() {
            let bytes = meta.map_or(0, |m| m.len());
            files.push(json!({ "name": name, "bytes": bytes }));
        }
    }
    files.sort_by(|a, b| a["name"].as_str().cmp(&b["name"].as_str()));
    let input = report["input"].as_str().unwrap_or("model").to_string();
    Ok(json!({
        "id": LOCAL_JOB,
        "state": "succeeded",
        "input": { "name": input },
        "progress": { "stage": "done", "fraction": 1.0 },
        "report": report,
        "files": files,
    }))
}

/// Serves `dir` on 127.0.0.1:`port` (0: any free port) until Ctrl-C;
/// `ready` is told the page's URL once the socket listens.
pub async fn serve_folder(
    dir: &Path,
    port: u16,
    ready: impl FnOnce(&str),
) -> Result<(), ViewError> {
    let folder = Arc::new(Folder {
        dir: dir.to_path_buf(),
        job: job_of(dir)?,
    });
    let addr = SocketAddr::from(([127, 0, 0, 1], port));
    let listener = tokio::net::TcpListener::bind(addr)
        .await
        .map_err(|source| ViewError::Bind { addr, source })?;
    let local = listener
        .local_addr()
        .map_err(|source| ViewError::Bind { addr, source })?;
    let url = format!("http://{local}/v1/jobs/{LOCAL_JOB}/view");
    tracing::info!(dir = %dir.display(), %url, "serving the view page");
    ready(&url);
    axum::serve(listener, router(folder))
        .with_graceful_shutdown(async {
            let _ = tokio::signal::ctrl_c().await;
        })
        .await
        .map_err(ViewError::Serve)
}

fn router(folder: Arc<Folder>) -> Router {
    let page = format!("/v1/jobs/{LOCAL_JOB}/view");
    Router::new()
        .route("/", get(move || async move { Redirect::to(&page) }))
        .route("/v1/view", get(|| async { html(LIST_PAGE) }))
        .route("/v1/view/assets/{*path}", get(serve_asset))
        .route("/v1/jobs", get(list))
        .route("/v1/jobs/{id}", get(job))
        .route("/v1/jobs/{id}/view", get(job_page))
        .route("/v1/jobs/{id}/files/{*name}", get(file))
        .with_state(folder)
}

fn html(page: &'static str) -> Response {
    ([(header::CONTENT_TYPE, "text/html; charset=utf-8")], page).into_response()
}

fn not_found() -> Response {
    (StatusCode::NOT_FOUND, "not found").into_response()
}

async fn serve_asset(UrlPath(path): UrlPath<String>) -> Response {
    match asset(&path) {
        Some(a) => ([(header::CONTENT_TYPE, a.content_type)], a.bytes).into_response(),
        None => not_found(),
    }
}

async fn list(State(folder): State<Arc<Folder>>) -> Response {
    let mut job = folder.job.clone();
    // As the service lists jobs: without their reports.
    if let Some(o) = job.as_object_mut() {
        o.remove("report");
    }
    Json(json!({ "jobs": [job], "next_cursor": null })).into_response()
}

async fn job(State(folder): State<Arc<Folder>>, UrlPath(id): UrlPath<String>) -> Response {
    if id != LOCAL_JOB {
        return not_found();
    }
    Json(folder.job.clone()).into_response()
}

async fn job_page(UrlPath(id): UrlPath<String>) -> Response {
    if id != LOCAL_JOB {
        return not_found();
    }
    html(JOB_PAGE)
}

/// A file of the folder, if the folder listed it: nothing else of the disk
/// is reachable.
async fn file(
    State(folder): State<Arc<Folder>>,
    UrlPath((id, name)): UrlPath<(String, String)>,
) -> Response {
    let listed = folder.job["files"]
        .as_array()
        .is_some_and(|f| f.iter().any(|f| f["name"] == name.as_str()));
    if id != LOCAL_JOB || !listed {
        return not_found();
    }
    match tokio::fs::read(folder.dir.join(&name)).await {
        Ok(bytes) => bytes.into_response(),
        Err(e) => {
            tracing::warn!(file = %name, error = %e, "cannot read a listed file");
            not_found()
        }
    }
}
