//! Routes and handlers. Every route is listed once, in [`routes`], which
//! both builds the router and tells the tests what `openapi.yaml` must hold.

use std::collections::BTreeMap;
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

use axum::body::Body;
use axum::extract::{DefaultBodyLimit, FromRequest, Path, RawQuery, Request, State};
use axum::http::{header, HeaderMap, HeaderValue, Method, StatusCode};
use axum::middleware::{self, Next};
use axum::response::{IntoResponse, Response};
use axum::routing::{delete, get, post, MethodRouter};
use axum::{Json, Router};
use http_body_util::BodyExt;
use serde_json::json;
use sha2::{Digest, Sha256};
use tracing::Instrument;

use super::app::{blocking, Shared, CANCELED};
use super::callback;
use super::data_dir;
use super::engine;
use super::error::STORE_RETRY_AFTER_S;
use super::error::{self, ApiError};
use super::health::Dependency;
use super::job::{self, is_job_id, now_ms, random_id, InputInfo, Job, JobState, Progress};
use super::store::{keys, StoreError, Submitted};
use super::upload::{base_name, check_media_type, safe_name, Bundle};
use crate::budget::Limits;
use crate::pipeline::{JobError, OptionPatch, ProcessOptions};

pub const OPENAPI: &str = include_str!("../../openapi.yaml");

/// Every route: method, path (axum syntax), handler.
pub fn routes() -> Vec<(Method, &'static str, MethodRouter<Shared>)> {
    vec![
        (Method::POST, "/v1/jobs", post(submit)),
        (Method::GET, "/v1/jobs", get(list_jobs)),
        (Method::GET, "/v1/jobs/{id}", get(get_job)),
        (Method::DELETE, "/v1/jobs/{id}", delete(delete_job)),
        (
            Method::GET,
            "/v1/jobs/{id}/files/{*name}",
            get(super::download::get_file),
        ),
        (
            Method::GET,
            "/v1/jobs/{id}/view",
            get(super::view::job_page),
        ),
        (Method::GET, "/v1/view", get(super::view::list_page)),
        (
            Method::GET,
            "/v1/view/assets/{*path}",
            get(super::view::get_asset),
        ),
        (Method::GET, "/healthz", get(healthz)),
        (Method::GET, "/readyz", get(readyz)),
        (Method::GET, "/metrics", get(metrics)),
        (Method::GET, "/openapi.yaml", get(openapi)),
    ]
}

pub fn router(app: Shared) -> Router {
    let mut r: Router<Shared> = Router::new();
    for (_, path, handler) in routes() {
        r = r.route(path, handler);
    }
    let limit = app.cfg.max_body;
    r.fallback(fallback)
        .layer(DefaultBodyLimit::max(limit))
        .layer(middleware::from_fn_with_state(app.clone(), store_gate))
        .layer(middleware::from_fn_with_state(app.clone(), request_context))
        .layer(tower_http::catch_panic::CatchPanicLayer::custom(
            |_: Box<dyn std::any::Any + Send>| {
                tracing::error!("handler panicked");
                ApiError::internal("internal error").into_response()
            },
        ))
        .with_state(app)
}

/// A worker process's routes: `/metrics` and `/healthz`, nothing else.
pub fn operations_router(app: Shared) -> Router {
    Router::new()
        .route("/metrics", get(metrics))
        .route("/healthz", get(healthz))
        .fallback(fallback)
        .with_state(app)
}

async fn fallback() -> ApiError {
    ApiError::not_found("no such route")
}

/// Answers 503 at once when a store the request needs is known to be
/// away, instead of holding the client while the store does not answer.
/// Health, metrics and the OpenAPI document need no store and are served.
async fn store_gate(State(app): State<Shared>, req: Request, next: Next) -> Response {
    let path = req.uri().path();
    if path.starts_with("/v1/") {
        let needs_files = req.method() != Method::GET || path.contains("/files/");
        let needs: &[Dependency] = if needs_files {
            &[Dependency::Jobs, Dependency::Files]
        } else {
            &[Dependency::Jobs]
        };
        if let Some(down) = app.health.down_among(needs) {
            return ApiError::unavailable("store_unavailable", down.message(), STORE_RETRY_AFTER_S)
                .into_response();
        }
    }
    next.run(req).await
}

/// Whether a request announces a body (chunks, or a length above zero).
fn has_body(req: &Request) -> bool {
    let h = req.headers();
    let length = h
        .get(header::CONTENT_LENGTH)
        .and_then(|v| v.to_str().ok())
        .and_then(|v| v.trim().parse::<u64>().ok());
    h.contains_key(header::TRANSFER_ENCODING) || length.is_some_and(|n| n > 0)
}

/// Request ids, one log line per request, JSON bodies for the errors the
/// framework itself produces (unknown method, malformed path), and
/// `Connection: close` on errors to requests with a body.
///
/// Most errors answer before the body is read (a store away, a bad token or
/// query, shutting down), and the server then drops the connection after
/// the answer. Said in the answer, a client does not send its next request
/// down a connection about to close (it did, and got no answer, while still
/// sending an upload). Where the body was read after all, the client opens
/// one connection more.
async fn request_context(State(app): State<Shared>, req: Request, next: Next) -> Response {
    let uploads = has_body(&req);
    let request_id = req
        .headers()
        .get("x-request-id")
        .and_then(|v| v.to_str().ok())
        .filter(|v| {
            !v.is_empty()
                && v.len() <= 64
                && v.bytes()
                    .all(|b| b.is_ascii_alphanumeric() || b == b'-' || b == b'_')
        })
        .map(str::to_string)
        .or_else(|| random_id().ok().map(|id| id[..16].to_string()))
        .unwrap_or_default();
    let span = tracing::info_span!(
        "request",
        request_id = %request_id,
        method = %req.method(),
        path = %req.uri().path()
    );
    let started = Instant::now();
    let mut resp = next.run(req).instrument(span.clone()).await;
    let status = resp.status();
    let failed = status.is_client_error() || status.is_server_error();
    if failed && !is_json(resp.headers()) {
        resp = json_error(resp).await;
    }
    if failed && uploads {
        resp.headers_mut()
            .insert(header::CONNECTION, HeaderValue::from_static("close"));
    }
    if let Ok(v) = HeaderValue::from_str(&request_id) {
        resp.headers_mut().insert("x-request-id", v);
    }
    app.metrics.request(status.as_u16());
    span.in_scope(|| {
        tracing::info!(
            status = status.as_u16(),
            ms = started.elapsed().as_millis() as u64,
            "request done"
        )
    });
    resp
}

fn is_json(headers: &HeaderMap) -> bool {
    headers
        .get(header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .is_some_and(|v| v.starts_with("application/json"))
}

async fn json_error(resp: Response) -> Response {
    let (mut parts, body) = resp.into_parts();
    let text = match body.collect().await {
        Ok(b) => String::from_utf8_lossy(&b.to_bytes()).trim().to_string(),
        Err(_) => String::new(),
    };
    let code = match parts.status {
        StatusCode::BAD_REQUEST => "bad_request",
        StatusCode::UNAUTHORIZED => "unauthorized",
        StatusCode::NOT_FOUND => "not_found",
        StatusCode::METHOD_NOT_ALLOWED => "method_not_allowed",
        StatusCode::PAYLOAD_TOO_LARGE => "payload_too_large",
        StatusCode::UNSUPPORTED_MEDIA_TYPE => "unsupported_media_type",
        s if s.is_server_error() => "internal",
        _ => "error",
    };
    let message = if text.is_empty() {
        parts
            .status
            .canonical_reason()
            .unwrap_or("error")
            .to_string()
    } else {
        text
    };
    parts.headers.insert(
        header::CONTENT_TYPE,
        HeaderValue::from_static("application/json"),
    );
    parts.headers.remove(header::CONTENT_LENGTH);
    Response::from_parts(parts, Body::from(error::body(code, &message)))
}

/// The owner the request acts for: its token's, or everyone's when the
/// server has no tokens (it then listens on loopback only, unless told).
pub(super) fn caller(app: &Shared, headers: &HeaderMap) -> Result<String, ApiError> {
    if app.cfg.tokens.is_empty() {
        return Ok(String::new());
    }
    let unauthorized = |m: &str| ApiError::new(StatusCode::UNAUTHORIZED, "unauthorized", m);
    let value = headers
        .get(header::AUTHORIZATION)
        .ok_or_else(|| unauthorized("an Authorization: Bearer token is required"))?;
    let token = value
        .to_str()
        .ok()
        .and_then(|v| {
            v.strip_prefix("Bearer ")
                .or_else(|| v.strip_prefix("bearer "))
        })
        .map(str::trim)
        .ok_or_else(|| unauthorized("the Authorization header must be \"Bearer <token>\""))?;
    // Comparing digests keeps the comparison's time independent of how
    // much of a guess matches.
    let digest: [u8; 32] = Sha256::digest(token.as_bytes()).into();
    app.cfg
        .tokens
        .iter()
        .find(|t| t.digest == digest)
        .map(|t| t.owner.clone())
        .ok_or_else(|| unauthorized("unknown token"))
}

/// `Prefer: wait=N` (RFC 7240), capped by the configuration.
fn prefer_wait(app: &Shared, headers: &HeaderMap) -> Option<Duration> {
    headers
        .get_all("prefer")
        .iter()
        .filter_map(|v| v.to_str().ok())
        .flat_map(|v| v.split([',', ';']))
        .filter_map(|p| {
            let (k, v) = p.split_once('=')?;
            (k.trim().eq_ignore_ascii_case("wait"))
                .then(|| v.trim().trim_matches('"').parse::<u64>().ok())
                .flatten()
        })
        .next()
        .map(|secs| Duration::from_secs(secs).min(app.cfg.max_wait))
}

async fn load_job(app: &Shared, id: &str) -> Result<Option<Job>, ApiError> {
    let id = id.to_string();
    blocking(app, move |a| Ok(a.jobs.get(&id)?)).await
}

/// The job if it exists and belongs to `owner`; others' jobs do not exist.
pub(super) async fn owned_job(app: &Shared, id: &str, owner: &str) -> Result<Job, ApiError> {
    if !is_job_id(id) {
        return Err(ApiError::job_not_found());
    }
    match load_job(app, id).await? {
        Some(job) if job.owner == owner => Ok(job),
        _ => Err(ApiError::job_not_found()),
    }
}

/// Waits until the job is final, the time is up, or the server stops.
async fn wait_for(app: &Shared, mut job: Job, wait: Duration) -> Result<Job, ApiError> {
    let deadline = tokio::time::Instant::now() + wait;
    let mut finished = app.finished.subscribe();
    let mut stopping = app.stopping.subscribe();
    while !job.state.is_terminal() && tokio::time::Instant::now() < deadline && !app.is_stopping() {
        tokio::select! {
            _ = finished.changed() => {}
            _ = stopping.changed() => {}
            // Another process sharing the store may finish it.
            _ = tokio::time::sleep(Duration::from_secs(1)) => {}
            _ = tokio::time::sleep_until(deadline) => {}
        }
        job = match load_job(app, &job.id).await? {
            Some(j) => j,
            None => return Err(ApiError::job_not_found()),
        };
    }
    Ok(job)
}

fn job_response(status: StatusCode, job: &Job, waited: Option<Duration>) -> Response {
    let mut resp = (status, Json(job::view(job, true))).into_response();
    if status == StatusCode::ACCEPTED {
        if let Ok(v) = HeaderValue::from_str(&format!("/v1/jobs/{}", job.id)) {
            resp.headers_mut().insert(header::LOCATION, v);
        }
    }
    if let Some(w) = waited {
        if let Ok(v) = HeaderValue::from_str(&format!("wait={}", w.as_secs())) {
            resp.headers_mut().insert("preference-applied", v);
        }
    }
    resp
}

fn idempotency_key(headers: &HeaderMap) -> Result<Option<String>, ApiError> {
    let Some(v) = headers.get("idempotency-key") else {
        return Ok(None);
    };
    let key = v
        .to_str()
        .ok()
        .filter(|k| !k.is_empty() && k.len() <= 255 && k.bytes().all(|b| b.is_ascii_graphic()));
    match key {
        Some(k) => Ok(Some(k.to_string())),
        None => Err(ApiError::bad_request(
            "Idempotency-Key must be 1 to 255 printable ASCII characters",
        )),
    }
}

fn media_type(headers: &HeaderMap) -> String {
    headers
        .get(header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .and_then(|v| v.split(';').next())
        .map(|v| v.trim().to_ascii_lowercase())
        .unwrap_or_default()
}

async fn read_body(body: Body, limit: usize) -> Result<Vec<u8>, ApiError> {
    match http_body_util::Limited::new(body, limit).collect().await {
        Ok(b) => Ok(b.to_bytes().to_vec()),
        Err(e) if e.is::<http_body_util::LengthLimitError>() => Err(ApiError::too_large(limit)),
        Err(e) => Err(ApiError::bad_request(format!(
            "cannot read the request body: {e}"
        ))),
    }
}

/// Reads the upload: a raw `.glb` or `.gltf`, or a multipart form.
async fn read_upload(
    app: &Shared,
    req: Request,
    name: Option<String>,
) -> Result<(Bundle, OptionPatch, Option<String>), ApiError> {
    let limit = app.cfg.max_body;
    let declared = req
        .headers()
        .get(header::CONTENT_LENGTH)
        .and_then(|v| v.to_str().ok())
        .and_then(|v| v.parse::<u64>().ok());
    if declared.is_some_and(|n| n > limit as u64) {
        return Err(ApiError::too_large(limit));
    }
    let media = media_type(req.headers());
    match media.as_str() {
        "model/gltf-binary" | "application/octet-stream" | "model/gltf+json" => {
            let glb = media != "model/gltf+json";
            let main = read_body(req.into_body(), limit).await?;
            check_media_type(&media, &main).map_err(|m| {
                ApiError::new(
                    StatusCode::UNSUPPORTED_MEDIA_TYPE,
                    "unsupported_media_type",
                    m,
                )
            })?;
            let default = if glb { "model.glb" } else { "model.gltf" };
            let main_name = match name {
                Some(n) => base_name(&n).to_string(),
                None => default.to_string(),
            };
            Ok((
                Bundle {
                    main_name,
                    main,
                    files: BTreeMap::new(),
                },
                OptionPatch::default(),
                None,
            ))
        }
        "multipart/form-data" => read_multipart(app, req, name).await,
        "" => Err(ApiError::new(
            StatusCode::UNSUPPORTED_MEDIA_TYPE,
            "unsupported_media_type",
            "Content-Type is required: model/gltf-binary, model/gltf+json or multipart/form-data",
        )),
        other => Err(ApiError::new(
            StatusCode::UNSUPPORTED_MEDIA_TYPE,
            "unsupported_media_type",
            format!(
                "Content-Type {other} is not accepted: use model/gltf-binary, model/gltf+json \
                 or multipart/form-data"
            ),
        )),
    }
}

fn is_model_name(name: &str) -> bool {
    let lower = name.to_ascii_lowercase();
    lower.ends_with(".gltf") || lower.ends_with(".glb")
}

async fn read_multipart(
    app: &Shared,
    req: Request,
    name: Option<String>,
) -> Result<(Bundle, OptionPatch, Option<String>), ApiError> {
    let limit = app.cfg.max_body;
    let multipart_err = |e: axum::extract::multipart::MultipartError| {
        if e.status() == StatusCode::PAYLOAD_TOO_LARGE {
            ApiError::too_large(limit)
        } else {
            ApiError::bad_request(format!("malformed multipart body: {}", e.body_text()))
        }
    };
    let mut form = axum::extract::Multipart::from_request(req, app)
        .await
        .map_err(|e| ApiError::bad_request(e.body_text()))?;
    let mut main: Option<(String, Vec<u8>)> = None;
    let mut files = BTreeMap::new();
    let mut options = OptionPatch::default();
    let mut callback = None;
    while let Some(field) = form.next_field().await.map_err(multipart_err)? {
        let field_name = field.name().unwrap_or("").to_string();
        let file_name = field.file_name().map(str::to_string);
        match file_name {
            _ if field_name == "options" => {
                let text = field.bytes().await.map_err(multipart_err)?;
                options = OptionPatch::from_json(&text)
                    .map_err(|e| ApiError::invalid_options(format!("the options part: {e}")))?;
            }
            _ if field_name == "callback" => {
                callback = Some(field.text().await.map_err(multipart_err)?);
            }
            None => {
                return Err(ApiError::bad_request(format!(
                    "form field {field_name:?} is neither a file nor \"options\" or \"callback\""
                )))
            }
            Some(file_name) => {
                let safe = safe_name(&file_name).ok_or_else(|| {
                    ApiError::bad_request(format!(
                        "file name {file_name:?} must be a relative path inside the upload"
                    ))
                })?;
                let bytes = field.bytes().await.map_err(multipart_err)?.to_vec();
                if is_model_name(&safe) {
                    if main.is_some() {
                        return Err(ApiError::bad_request(
                            "the form holds more than one .gltf or .glb file",
                        ));
                    }
                    main = Some((safe, bytes));
                } else if files.insert(safe.clone(), bytes).is_some() {
                    return Err(ApiError::bad_request(format!(
                        "file {safe:?} appears twice in the form"
                    )));
                }
            }
        }
    }
    let (main_name, main) =
        main.ok_or_else(|| ApiError::bad_request("the form holds no .gltf or .glb file"))?;
    let main_name = match name {
        Some(n) => base_name(&n).to_string(),
        None => base_name(&main_name).to_string(),
    };
    Ok((
        Bundle {
            main_name,
            main,
            files,
        },
        options,
        callback,
    ))
}

/// A job's callback, if its URL may be called and there is a secret to
/// sign it with.
fn callback_for(app: &Shared, owner: &str, url: &str) -> Result<job::Callback, ApiError> {
    let url = callback::check_url(&app.cfg, url)
        .map_err(|m| ApiError::new(StatusCode::BAD_REQUEST, "invalid_callback", m))?;
    if callback::key_for(&app.cfg, owner).is_none() {
        return Err(ApiError::new(
            StatusCode::BAD_REQUEST,
            "invalid_callback",
            "this server has no secret to sign callbacks with (--callback-secret)",
        ));
    }
    Ok(job::Callback {
        url,
        ..job::Callback::default()
    })
}

/// What a request's query holds besides options.
#[derive(Debug, Default)]
struct QueryExtras {
    /// The model's file name for a raw upload.
    name: Option<String>,
    /// Where to post the finished job.
    callback: Option<String>,
}

/// Splits the query into options, the model's name and the callback.
fn parse_query(query: Option<&str>) -> Result<(OptionPatch, QueryExtras), ApiError> {
    let mut options = OptionPatch::default();
    let mut extras = QueryExtras::default();
    for pair in query.unwrap_or("").split('&').filter(|p| !p.is_empty()) {
        let (k, v) = pair.split_once('=').unwrap_or((pair, ""));
        let decode = |s: &str| {
            percent_encoding::percent_decode_str(&s.replace('+', " "))
                .decode_utf8()
                .map(|c| c.into_owned())
                .map_err(|_| ApiError::bad_request("the query is not UTF-8"))
        };
        let (k, v) = (decode(k)?, decode(v)?);
        if k == "name" {
            // A raw upload is one file: its name has no folder part.
            let safe = safe_name(&v)
                .filter(|n| is_model_name(n) && !n.contains('/'))
                .ok_or_else(|| {
                    ApiError::bad_request("name must be a file name ending in .glb or .gltf")
                })?;
            extras.name = Some(safe);
        } else if k == "callback" {
            extras.callback = Some(v);
        } else if ProcessOptions::is_option(&k) {
            options
                .set_from_query(&k, &v)
                .map_err(|e| ApiError::invalid_options(e.to_string()))?;
        } else {
            return Err(ApiError::bad_request(format!(
                "unknown query parameter {k:?}"
            )));
        }
    }
    Ok((options, extras))
}

async fn submit(
    State(app): State<Shared>,
    RawQuery(query): RawQuery,
    req: Request,
) -> Result<Response, ApiError> {
    let started = Instant::now();
    let owner = caller(&app, req.headers())?;
    if !app.accepting.load(Ordering::Acquire) {
        return Err(ApiError::unavailable(
            "shutting_down",
            "the server is shutting down",
            5,
        ));
    }
    let (query_options, extras) = parse_query(query.as_deref())?;
    let idem = idempotency_key(req.headers())?;
    let wait = prefer_wait(&app, req.headers());

    let (bundle, part_options, part_callback) = read_upload(&app, req, extras.name).await?;
    let given = part_callback.or(extras.callback);
    let callback = match given.or_else(|| app.cfg.callback_defaults.get(&owner).cloned()) {
        Some(url) => Some(callback_for(&app, &owner, &url)?),
        None => None,
    };
    app.metrics
        .bytes_in
        .fetch_add(bundle.total_bytes(), Ordering::Relaxed);
    let options = query_options
        .overridden_by(part_options)
        .resolve(&ProcessOptions::service_default())
        .map_err(|e| ApiError::invalid_options(e.to_string()))?;
    let id = random_id().map_err(|e| ApiError::internal(e.to_string()))?;
    let now = now_ms();
    let mut job = Job {
        seq: 0,
        id: id.clone(),
        owner,
        state: JobState::Queued,
        input: InputInfo {
            name: bundle.main_name.clone(),
            format: if bundle.is_glb() { "glb" } else { "gltf" }.into(),
            bytes: bundle.total_bytes(),
            files: bundle.files.keys().cloned().collect(),
        },
        input_key: String::new(),
        idempotency_key: idem,
        options,
        created_ms: now,
        started_ms: None,
        finished_ms: None,
        progress: Progress::at("queued", 0.0),
        timings_ms: Default::default(),
        report: None,
        error: None,
        files: Vec::new(),
        cached_from: None,
        attempts: 0,
        interruptions: 0,
        lost_leases: 0,
        warnings: Vec::new(),
        callback,
        worker: None,
    };

    let queue_size = app.cfg.queue_size;
    let max_texture_size = app.cfg.max_texture_size;
    let limits = Limits {
        max_memory: app.cfg.max_memory,
    };
    if storage_low(&app) {
        return Err(StoreError::Full("free space under --min-free".into()).into());
    }
    let outcome = blocking(&app, move |a| {
        job.input_key = bundle.key(&job.owner, &job.options);
        if let Some(earlier) = a.jobs.find_succeeded(&job.owner, &job.input_key)? {
            if copy_result(a, &earlier, &mut job).is_ok() {
                let submitted = a.jobs.submit(&job, queue_size)?;
                if !matches!(submitted, Submitted::Created) {
                    a.files.delete_prefix(&keys::job(&job.id))?;
                }
                return Ok((submitted, job));
            }
        }
        match engine::validate(&bundle, &job.options, max_texture_size, &limits) {
            Ok(_) => {}
            Err(JobError::TooLarge(message)) => {
                return Err(ApiError::new(
                    StatusCode::UNPROCESSABLE_ENTITY,
                    "too_large",
                    message,
                ));
            }
            Err(JobError::BadInput(message)) => {
                return Err(ApiError::new(
                    StatusCode::UNPROCESSABLE_ENTITY,
                    "invalid_model",
                    message,
                ));
            }
            Err(e) => {
                tracing::error!(error = %e, "cannot check the upload");
                return Err(ApiError::internal("cannot check the upload"));
            }
        }
        a.files.put(&keys::input(&job.id), &bundle.encode())?;
        let submitted = a.jobs.submit(&job, queue_size)?;
        if !matches!(submitted, Submitted::Created) {
            a.files.delete_prefix(&keys::job(&job.id))?;
        }
        Ok((submitted, job))
    })
    .await?;

    let job = match outcome {
        (Submitted::Created, job) => {
            app.metrics.submitted.fetch_add(1, Ordering::Relaxed);
            if job.state == JobState::Queued {
                app.work.notify_one();
            } else {
                app.metrics.finished(job.state);
            }
            tracing::info!(
                job_id = %job.id,
                input = %job.input.name,
                bytes = job.input.bytes,
                cached = job.cached_from.is_some(),
                "job accepted"
            );
            job
        }
        (Submitted::Existing(existing), job) => {
            if existing.input_key != job.input_key {
                return Err(ApiError::new(
                    StatusCode::UNPROCESSABLE_ENTITY,
                    "idempotency_key_reused",
                    "this Idempotency-Key was used for a different upload or options",
                ));
            }
            *existing
        }
        (Submitted::QueueFull, _) => {
            app.metrics.rejected_full.fetch_add(1, Ordering::Relaxed);
            return Err(ApiError::unavailable(
                "queue_full",
                format!("the queue holds its limit of {queue_size} jobs; retry later"),
                retry_after(&app),
            ));
        }
    };
    app.metrics.submission(started.elapsed().as_secs_f64());
    let job = match wait {
        Some(w) => wait_for(&app, job, w).await?,
        None => job,
    };
    Ok(job_response(StatusCode::ACCEPTED, &job, wait))
}

/// Jobs take seconds: a short back-off lets a retry find room without
/// clients hammering a full queue.
fn retry_after(app: &Shared) -> u64 {
    if app.metrics.busy_workers.load(Ordering::Relaxed) == 0 {
        1
    } else {
        5
    }
}

/// A new job answered by an earlier identical one: its files are copied
/// (linked) so that each job's files live and die with it.
fn copy_result(app: &super::app::App, earlier: &Job, job: &mut Job) -> Result<(), ApiError> {
    for f in &earlier.files {
        app.files.copy(
            &keys::output(&earlier.id, &f.name),
            &keys::output(&job.id, &f.name),
        )?;
    }
    let now = now_ms();
    job.state = JobState::Succeeded;
    job.started_ms = Some(now);
    job.finished_ms = Some(now);
    job.progress = Progress::at("done", 1.0);
    job.report = earlier.report.clone();
    job.files = earlier.files.clone();
    job.warnings = earlier.warnings.clone();
    job.cached_from = Some(earlier.id.clone());
    job.timings_ms.total = Some(0);
    app.metrics.cache_hits.fetch_add(1, Ordering::Relaxed);
    Ok(())
}

async fn get_job(
    State(app): State<Shared>,
    Path(id): Path<String>,
    headers: HeaderMap,
) -> Result<Response, ApiError> {
    let owner = caller(&app, &headers)?;
    let job = owned_job(&app, &id, &owner).await?;
    let wait = prefer_wait(&app, &headers);
    let job = match wait {
        Some(w) => wait_for(&app, job, w).await?,
        None => job,
    };
    Ok(job_response(StatusCode::OK, &job, wait))
}

async fn list_jobs(
    State(app): State<Shared>,
    RawQuery(query): RawQuery,
    headers: HeaderMap,
) -> Result<Response, ApiError> {
    let owner = caller(&app, &headers)?;
    let mut limit = 20usize;
    let mut before = None;
    for pair in query
        .as_deref()
        .unwrap_or("")
        .split('&')
        .filter(|p| !p.is_empty())
    {
        let (k, v) = pair.split_once('=').unwrap_or((pair, ""));
        match k {
            "limit" => {
                limit = v
                    .parse()
                    .ok()
                    .filter(|n| (1..=100).contains(n))
                    .ok_or_else(|| ApiError::bad_request("limit must be 1 to 100"))?
            }
            "cursor" => {
                // As the contract's pattern: 1 to 18 digits, no leading 0.
                let well_formed = (1..=18).contains(&v.len())
                    && v.bytes().all(|b| b.is_ascii_digit())
                    && !v.starts_with('0');
                before = Some(
                    v.parse::<i64>()
                        .ok()
                        .filter(|_| well_formed)
                        .ok_or_else(|| ApiError::bad_request("invalid cursor"))?,
                )
            }
            _ => {
                return Err(ApiError::bad_request(format!(
                    "unknown query parameter {k:?}"
                )))
            }
        }
    }
    let jobs = blocking(&app, move |a| Ok(a.jobs.list(&owner, before, limit + 1)?)).await?;
    let more = jobs.len() > limit;
    let page = &jobs[..jobs.len().min(limit)];
    let next = if more {
        page.last().map(|j| j.seq.to_string())
    } else {
        None
    };
    let items: Vec<job::View<'_>> = page.iter().map(|j| job::view(j, false)).collect();
    Ok(Json(json!({ "jobs": items, "next_cursor": next })).into_response())
}

async fn delete_job(
    State(app): State<Shared>,
    Path(id): Path<String>,
    headers: HeaderMap,
) -> Result<Response, ApiError> {
    let owner = caller(&app, &headers)?;
    let job = owned_job(&app, &id, &owner).await?;
    if !job.state.is_terminal() {
        let jid = job.id.clone();
        let canceled = blocking(&app, move |a| Ok(a.jobs.cancel(&jid, now_ms())?)).await?;
        if let Some(canceled) = canceled {
            app.signal(&canceled.id, CANCELED);
            if job.state == JobState::Queued {
                let jid = canceled.id.clone();
                blocking(&app, move |a| {
                    Ok(a.files.delete_prefix(&keys::job(&jid))?)
                })
                .await?;
            }
            app.metrics.finished(JobState::Canceled);
            app.announce_finished();
            tracing::info!(job_id = %canceled.id, "job canceled");
            return Ok((StatusCode::OK, Json(job::view(&canceled, true))).into_response());
        }
    }
    let jid = job.id.clone();
    blocking(&app, move |a| {
        a.files.delete_prefix(&keys::job(&jid))?;
        a.jobs.delete(&jid)?;
        Ok(())
    })
    .await?;
    tracing::info!(job_id = %job.id, "job deleted");
    Ok(StatusCode::NO_CONTENT.into_response())
}

async fn healthz() -> Response {
    Json(json!({ "status": "ok" })).into_response()
}

/// Whether the data folder's disk has less free space than it must keep.
fn storage_low(app: &Shared) -> bool {
    data_dir::free_space(&app.cfg.data).is_some_and(|free| free < app.cfg.min_free)
}

async fn readyz(State(app): State<Shared>) -> Result<Response, ApiError> {
    if !app.accepting.load(Ordering::Acquire) {
        return Err(ApiError::unavailable(
            "shutting_down",
            "the server is shutting down",
            5,
        ));
    }
    if storage_low(&app) {
        return Err(ApiError::unavailable(
            "storage_low",
            "the server's disk is nearly full",
            60,
        ));
    }
    // Both stores must answer: a server that cannot reach either can take
    // no job in, nor hand one out. The prober has asked them within the
    // last second; asking again here would hold the probe as long as a
    // store that does not answer holds it.
    if let Some(down) = app
        .health
        .down_among(&[Dependency::Jobs, Dependency::Files])
    {
        return Err(ApiError::unavailable(
            "store_unavailable",
            down.message(),
            STORE_RETRY_AFTER_S,
        ));
    }
    Ok(Json(json!({ "status": "ready" })).into_response())
}

async fn metrics(State(app): State<Shared>) -> Result<Response, ApiError> {
    // Without the job store, the job counts are left out and the rest is
    // served: an outage is when the metrics matter most.
    let counts = if app.health.down_among(&[Dependency::Jobs]).is_some() {
        None
    } else {
        blocking(&app, |a| Ok(a.jobs.counts().ok())).await?
    };
    let up: Vec<(&str, bool)> = Dependency::ALL
        .iter()
        .map(|&d| (d.name(), app.health.down_among(&[d]).is_none()))
        .collect();
    let text = app.metrics.render(counts.as_ref(), &up, app.cfg.workers);
    Ok((
        [(
            header::CONTENT_TYPE,
            "text/plain; version=0.0.4; charset=utf-8",
        )],
        text,
    )
        .into_response())
}

async fn openapi() -> Response {
    ([(header::CONTENT_TYPE, "application/yaml")], OPENAPI).into_response()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn query_options_and_name() {
        let (o, n) = parse_query(Some("mode=global&mips=0&name=Box%20A.glb")).unwrap();
        assert_eq!(n.name.as_deref(), Some("Box A.glb"));
        assert!(!o.resolve(&ProcessOptions::default()).unwrap().mips);
        assert!(parse_query(Some("name=../x.glb")).is_err());
        assert!(parse_query(Some("name=x.png")).is_err());
        assert!(parse_query(Some("colour=red")).is_err());
        assert!(parse_query(Some("mode=sideways")).is_err());
        assert!(parse_query(None).unwrap().1.name.is_none());
    }
}
