//! `seamstress submit`: a batch's models run on a server instead of here.
//!
//! [`Remote`] is a [`Runner`] for [`crate::batch::run::run_batch`], so a
//! batch against a server has the same inputs, output tree, cache stamps,
//! progress and summary as `process`. Each model is uploaded with its
//! cache key as the `Idempotency-Key`: a retried upload, or a batch run
//! again after it (or the server) stopped, finds the job it started instead
//! of running the model twice. Files are downloaded, checked against their
//! ETag (their SHA-256) and published into the model's folder as `process`
//! would write them.

pub mod retry;

use std::path::Path;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

use reqwest::blocking::{multipart, Client, RequestBuilder};
use serde::Deserialize;
use serde_json::Value;
use sha2::{Digest, Sha256};

use crate::batch::run::{write_outputs, ModelFiles, RunError, Runner, Staging, Written};
use crate::model::rewrite::referenced_files;
use crate::pipeline::{ProcessOptions, Progress, Sink};
use crate::service::config::hex;
use retry::{with_retries, RequestError, RetryParams};

/// Where the server is and how to talk to it.
#[derive(Clone, Debug)]
pub struct RemoteParams {
    /// `http://host:port` (or `host:port`, taken as `http://`), without
    /// the `/v1/...` path.
    pub server: String,
    pub token: Option<String>,
    pub retry: RetryParams,
    /// How often a running job's progress is asked for.
    pub poll: Duration,
}

/// A server that runs a batch's models.
pub struct Remote {
    params: RemoteParams,
    options: ProcessOptions,
    http: Client,
    /// Set once a request has waited its whole retry budget for the
    /// server: the batch's later models then fail at once instead of each
    /// waiting as long again for a server that is gone.
    unreachable: AtomicBool,
}

/// Why `--server` cannot name a server this client can talk to.
#[derive(Debug, thiserror::Error)]
pub enum ServerUrlError {
    #[error("--server {text}: not a URL: {reason}")]
    Unparsable { text: String, reason: String },
    #[error(
        "--server {text}: this client speaks plain HTTP only; give the server's http:// \
         address (TLS belongs to a proxy on the server's side)"
    )]
    Https { text: String },
    #[error(
        "--server {text}: {scheme}:// is not a scheme this client speaks; give http://HOST:PORT"
    )]
    Scheme { text: String, scheme: String },
    #[error("--server {text}: a server's address has no query or fragment; give http://HOST:PORT")]
    QueryOrFragment { text: String },
    #[error("--server {text}: no scheme; give http://{text}")]
    NoScheme { text: String },
}

/// The address requests are made under, from what `--server` says.
/// Anything the client cannot reach is refused at once (exit status 2)
/// rather than retried for ten minutes: a bare `HOST:PORT` too, whose
/// scheme the user should say (the error shows the fix).
pub fn server_base(text: &str) -> Result<String, ServerUrlError> {
    let text = text.trim();
    if !text.contains("://") {
        return Err(ServerUrlError::NoScheme { text: text.into() });
    }
    let url = reqwest::Url::parse(text).map_err(|e| ServerUrlError::Unparsable {
        text: text.to_string(),
        reason: e.to_string(),
    })?;
    match url.scheme() {
        "http" => {}
        "https" => return Err(ServerUrlError::Https { text: text.into() }),
        scheme => {
            return Err(ServerUrlError::Scheme {
                text: text.into(),
                scheme: scheme.into(),
            })
        }
    }
    if url.host_str().is_none_or(str::is_empty) {
        return Err(ServerUrlError::Unparsable {
            text: text.into(),
            reason: "no host".into(),
        });
    }
    if url.query().is_some() || url.fragment().is_some() {
        return Err(ServerUrlError::QueryOrFragment { text: text.into() });
    }
    Ok(url.as_str().trim_end_matches('/').to_string())
}

/// What the client reads of a job.
#[derive(Debug, Deserialize)]
struct JobView {
    id: String,
    state: String,
    progress: ProgressView,
    error: Option<ErrorView>,
    files: Vec<FileView>,
}

#[derive(Debug, Deserialize)]
struct ProgressView {
    stage: String,
    fraction: f64,
    /// The texture being processed (from 1) and how many there are.
    #[serde(default)]
    texture: Option<[usize; 2]>,
}

#[derive(Debug, Deserialize)]
struct ErrorView {
    code: String,
    message: String,
}

#[derive(Debug, Deserialize)]
struct FileView {
    name: String,
    etag: String,
    url: String,
}

/// Error codes of a failed job that the input is at fault for.
const BAD_INPUT_CODES: &[&str] = &["invalid_model", "too_large", "invalid_options"];

impl Remote {
    /// A client for `params.server`; an address it cannot reach is the
    /// caller's input at fault.
    pub fn new(params: RemoteParams, options: ProcessOptions) -> Result<Remote, RunError> {
        let server = server_base(&params.server).map_err(|e| RunError::BadInput(e.to_string()))?;
        let http = Client::builder()
            .connect_timeout(Duration::from_secs(10))
            // Uploads and downloads of large models take a while; a stuck
            // connection still ends.
            .timeout(Duration::from_secs(600))
            .build()
            .map_err(|e| RunError::Internal(format!("cannot start the HTTP client: {e}")))?;
        Ok(Remote {
            params: RemoteParams { server, ..params },
            options,
            http,
            unreachable: AtomicBool::new(false),
        })
    }

    /// [`with_retries`], unless an earlier request already found the
    /// server gone for a whole retry budget.
    fn retried(
        &self,
        what: &str,
        send: impl FnMut() -> reqwest::Result<reqwest::blocking::Response>,
    ) -> Result<reqwest::blocking::Response, RequestError> {
        if self.unreachable.load(Ordering::Relaxed) {
            return Err(RequestError::Transport(format!(
                "{what}: not tried: {} stayed unreachable for an earlier model",
                self.params.server
            )));
        }
        let result = with_retries(&self.params.retry, what, send);
        if matches!(result, Err(RequestError::Transport(_))) {
            self.unreachable.store(true, Ordering::Relaxed);
        }
        result
    }

    fn authorised(&self, req: RequestBuilder) -> RequestBuilder {
        match &self.params.token {
            Some(t) => req.bearer_auth(t),
            None => req,
        }
    }

    /// Uploads the model (a `.glb` raw, a `.gltf` as a form with its
    /// files) and returns the job the server made or already had.
    fn upload(&self, model: &ModelFiles, input: &Path, key: &str) -> Result<JobView, RunError> {
        let file_name = input
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_else(|| "model.glb".into());
        let glb = file_name.to_ascii_lowercase().ends_with(".glb");
        let url = format!("{}/v1/jobs", self.params.server);
        let options = Value::Object(self.options.to_json()).to_string();
        let parts: Vec<(String, Vec<u8>)> = if glb {
            Vec::new()
        } else {
            let mut parts = Vec::new();
            for uri in referenced_files(&model.main).unwrap_or_default() {
                // A file that cannot be read is left out: the server then
                // names it in the job's error, as `process` would.
                if let Ok(bytes) = crate::model::Resolver::read(&model.files, &uri) {
                    parts.push((uri, bytes.into_owned()));
                }
            }
            parts
        };
        let send = || {
            let req = if glb {
                self.http
                    .post(&url)
                    .query(&[("name", file_name.as_str())])
                    .query(&query_options(&self.options))
                    .header(reqwest::header::CONTENT_TYPE, "model/gltf-binary")
                    .body(model.main.clone())
            } else {
                let mut form = multipart::Form::new()
                    .part(
                        "model",
                        multipart::Part::bytes(model.main.clone()).file_name(file_name.clone()),
                    )
                    .text("options", options.clone());
                for (uri, bytes) in &parts {
                    form = form.part(
                        uri.clone(),
                        multipart::Part::bytes(bytes.clone()).file_name(uri.clone()),
                    );
                }
                self.http.post(&url).multipart(form)
            };
            self.authorised(req.header("Idempotency-Key", key)).send()
        };
        let resp = self
            .retried("upload", send)
            .map_err(|e| request_failed(&model.name, "upload", e))?;
        resp.json::<JobView>()
            .map_err(|e| RunError::Internal(format!("{}: the server's answer: {e}", model.name)))
    }

    fn job(&self, id: &str, name: &str) -> Result<JobView, RunError> {
        let url = format!("{}/v1/jobs/{id}", self.params.server);
        let resp = self
            .retried("job status", || self.authorised(self.http.get(&url)).send())
            .map_err(|e| request_failed(name, "job status", e))?;
        resp.json::<JobView>()
            .map_err(|e| RunError::Internal(format!("{name}: the server's answer: {e}")))
    }

    /// Waits for the job to end, telling `sink` how far it is; a stop from
    /// the sink cancels the job on the server.
    fn wait(&self, mut job: JobView, name: &str, sink: &mut dyn Sink) -> Result<JobView, RunError> {
        while matches!(job.state.as_str(), "queued" | "running") {
            let at = Progress {
                stage: &job.progress.stage,
                texture: job.progress.texture.map(|[i, n]| (i.saturating_sub(1), n)),
                fraction: job.progress.fraction,
            };
            if let Err(stop) = sink.progress(&at) {
                let url = format!("{}/v1/jobs/{}", self.params.server, job.id);
                let _ = self.authorised(self.http.delete(&url)).send();
                return Err(RunError::Internal(format!("{name}: stopped ({stop:?})")));
            }
            std::thread::sleep(self.params.poll);
            job = self.job(&job.id, name)?;
        }
        Ok(job)
    }

    /// Downloads one file and checks it against its ETag.
    fn download(&self, file: &FileView, name: &str) -> Result<Vec<u8>, RunError> {
        let url = format!("{}{}", self.params.server, file.url);
        let what = format!("download of {}", file.name);
        let resp = self
            .retried(&what, || self.authorised(self.http.get(&url)).send())
            .map_err(|e| request_failed(name, &what, e))?;
        let bytes = resp
            .bytes()
            .map_err(|e| RunError::Internal(format!("{name}: {what}: {e}")))?;
        let sha = hex(&Sha256::digest(&bytes));
        if file.etag.trim_matches('"') != sha {
            return Err(RunError::Internal(format!(
                "{name}: {} arrived damaged (its SHA-256 is not its ETag {})",
                file.name, file.etag
            )));
        }
        Ok(bytes.to_vec())
    }
}

/// The options as query parameters, for a raw upload (which has no part
/// to carry them).
fn query_options(options: &ProcessOptions) -> Vec<(String, String)> {
    options
        .to_json()
        .into_iter()
        .map(|(k, v)| {
            let text = match v {
                Value::String(s) => s,
                other => other.to_string(),
            };
            (k, text)
        })
        .collect()
}

fn request_failed(name: &str, what: &str, e: RequestError) -> RunError {
    match e {
        // A token the server does not take: no retry can succeed, and the
        // fix is the caller's, as for a bad model.
        RequestError::Status { status, body } if status == reqwest::StatusCode::UNAUTHORIZED => {
            RunError::BadInput(format!(
                "{name}: {what}: {status}: {} (check --token or SEAMSTRESS_TOKEN)",
                message(&body)
            ))
        }
        // The server refused the upload itself: the input is at fault.
        RequestError::Status { status, body } if status.is_client_error() => {
            RunError::BadInput(format!("{name}: {what}: {status}: {}", message(&body)))
        }
        RequestError::Status { status, body } => {
            RunError::Internal(format!("{name}: {what}: {status}: {}", message(&body)))
        }
        RequestError::Transport(m) | RequestError::Unusable(m) => {
            RunError::Internal(format!("{name}: {m}"))
        }
    }
}

/// The message of the service's `{code, message}` error body, or the body.
fn message(body: &str) -> String {
    serde_json::from_str::<ErrorView>(body)
        .map(|e| e.message)
        .unwrap_or_else(|_| body.chars().take(300).collect())
}

impl Runner for Remote {
    fn options(&self) -> &ProcessOptions {
        &self.options
    }

    fn run(
        &self,
        model: &ModelFiles,
        input: &Path,
        out: &Path,
        key: &str,
        sink: &mut dyn Sink,
    ) -> Result<Written, RunError> {
        let mut staging = Staging::open(out)?;
        let job = self.upload(model, input, key)?;
        tracing::debug!(model = %model.name, job = %job.id, "submitted");
        let job = self.wait(job, &model.name, sink)?;
        match job.state.as_str() {
            "succeeded" => {
                let mut files = Vec::with_capacity(job.files.len());
                for f in &job.files {
                    files.push((f.name.clone(), self.download(f, &model.name)?));
                }
                write_outputs(&mut staging, model, input, files.into_iter())
            }
            "failed" => {
                let (code, msg) = job
                    .error
                    .map(|e| (e.code, e.message))
                    .unwrap_or_else(|| ("failed".into(), "no reason given".into()));
                if BAD_INPUT_CODES.contains(&code.as_str()) {
                    Err(RunError::BadInput(msg))
                } else {
                    Err(RunError::Internal(format!("{}: {code}: {msg}", model.name)))
                }
            }
            other => Err(RunError::Internal(format!(
                "{}: the job ended {other} on the server",
                model.name
            ))),
        }
    }
}
