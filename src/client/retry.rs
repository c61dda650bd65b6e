//! Retrying a request the way an unattended batch needs: a server that is
//! restarting, busy (`503` with `Retry-After`) or briefly unreachable is
//! waited for, with exponential backoff, for a bounded time.

use std::time::{Duration, Instant};

use reqwest::blocking::Response;
use reqwest::StatusCode;

/// How long a request is retried, and how the waits grow.
#[derive(Clone, Copy, Debug)]
pub struct RetryParams {
    /// The first wait; each next one doubles, up to `max_wait`.
    pub first_wait: Duration,
    pub max_wait: Duration,
    /// After this long, the last error stands. Ten minutes covers a
    /// server's restart and a full queue draining, not a server gone.
    pub give_up_after: Duration,
}

impl Default for RetryParams {
    fn default() -> Self {
        RetryParams {
            first_wait: Duration::from_millis(250),
            max_wait: Duration::from_secs(15),
            give_up_after: Duration::from_secs(600),
        }
    }
}

/// A request that could not be answered in time, or was answered with a
/// status no retry changes.
#[derive(Debug, thiserror::Error)]
pub enum RequestError {
    #[error("{0}")]
    Transport(String),
    #[error("{status}: {body}")]
    Status { status: StatusCode, body: String },
}

/// Statuses a retry may change: the server is busy, restarting, or behind
/// a proxy that lost it for a moment.
fn transient(status: StatusCode) -> bool {
    matches!(
        status,
        StatusCode::TOO_MANY_REQUESTS
            | StatusCode::BAD_GATEWAY
            | StatusCode::SERVICE_UNAVAILABLE
            | StatusCode::GATEWAY_TIMEOUT
            | StatusCode::INTERNAL_SERVER_ERROR
    )
}

/// The server's `Retry-After` in seconds (the date form is not used by
/// the service and is ignored).
fn retry_after(resp: &Response) -> Option<Duration> {
    let secs = resp
        .headers()
        .get(reqwest::header::RETRY_AFTER)?
        .to_str()
        .ok()?
        .trim()
        .parse::<u64>()
        .ok()?;
    Some(Duration::from_secs(secs))
}

/// Sends what `send` builds until a response comes that a retry would not
/// change; success statuses and other errors are returned as they are.
pub fn with_retries(
    params: &RetryParams,
    what: &str,
    mut send: impl FnMut() -> reqwest::Result<Response>,
) -> Result<Response, RequestError> {
    let started = Instant::now();
    let mut wait = params.first_wait;
    loop {
        let (error, asked) = match send() {
            Ok(resp) if resp.status().is_success() || resp.status().is_redirection() => {
                return Ok(resp)
            }
            Ok(resp) if transient(resp.status()) => {
                let asked = retry_after(&resp);
                let status = resp.status();
                let body = resp.text().unwrap_or_default();
                (RequestError::Status { status, body }, asked)
            }
            Ok(resp) => {
                let status = resp.status();
                let body = resp.text().unwrap_or_default();
                return Err(RequestError::Status { status, body });
            }
            Err(e) => (RequestError::Transport(format!("{what}: {e}")), None),
        };
        let pause = asked.unwrap_or(wait).min(params.max_wait.max(wait));
        if started.elapsed() + pause > params.give_up_after {
            return Err(error);
        }
        tracing::debug!(request = what, error = %error, wait_ms = pause.as_millis() as u64, "retrying");
        std::thread::sleep(pause);
        wait = (wait * 2).min(params.max_wait);
    }
}
