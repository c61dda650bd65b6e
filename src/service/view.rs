//! The view pages: `GET /v1/view` (the job list) and
//! `GET /v1/jobs/{id}/view` (one job's model in 3D), and their scripts
//! under `GET /v1/view/assets/{path}`.
//!
//! The pages hold nothing of any job, so they are served to anyone: a
//! browser cannot send a header when it navigates. The page's scripts then
//! fetch the job and its files with the token in an `Authorization` header,
//! as any client does, and a token never appears in a URL.

use axum::extract::Path;
use axum::http::header;
use axum::response::{IntoResponse, Response};

use super::error::ApiError;
use super::job::is_job_id;
use crate::view::{asset, JOB_PAGE, LIST_PAGE};

fn html(page: &'static str) -> Response {
    ([(header::CONTENT_TYPE, "text/html; charset=utf-8")], page).into_response()
}

/// `GET /v1/view`.
pub async fn list_page() -> Response {
    html(LIST_PAGE)
}

/// `GET /v1/jobs/{id}/view`.
pub async fn job_page(Path(id): Path<String>) -> Result<Response, ApiError> {
    if !is_job_id(&id) {
        return Err(ApiError::job_not_found());
    }
    Ok(html(JOB_PAGE))
}

/// `GET /v1/view/assets/{path}`: the pages' embedded scripts.
pub async fn get_asset(Path(path): Path<String>) -> Result<Response, ApiError> {
    let a = asset(&path).ok_or_else(|| ApiError::not_found("no such asset"))?;
    Ok((
        [
            (header::CONTENT_TYPE, a.content_type),
            (header::CACHE_CONTROL, "public, max-age=3600"),
        ],
        a.bytes,
    )
        .into_response())
}
