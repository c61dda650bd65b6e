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
    /// The request cannot even be built (a URL the HTTP client refuses):
    /// waiting would only hide that.
    #[error("{0}")]
    Unusable(String),
    /// No answer within the retry budget.
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
        StatusCode::REQUEST_TIMEOUT
            | StatusCode::TOO_MANY_REQUESTS
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

/// The innermost cause of a transport error ("Connection refused (os error
/// 111)"): the outer ones repeat the whole URL, options and all.
fn cause(e: &reqwest::Error) -> String {
    let mut inner: &dyn std::error::Error = e;
    while let Some(next) = inner.source() {
        inner = next;
    }
    inner.to_string()
}

/// A wait as a person reads it: "250 ms", "8 s", "9 min 20 s".
pub fn human(d: Duration) -> String {
    let secs = d.as_secs_f64().round() as u64;
    match d.as_millis() {
        ms if ms < 1000 => format!("{ms} ms"),
        _ if secs < 60 => format!("{secs} s"),
        _ if secs.is_multiple_of(60) => format!("{} min", secs / 60),
        _ => format!("{} min {} s", secs / 60, secs % 60),
    }
}

/// Sends what `send` builds until a response comes that a retry would not
/// change; success statuses and other errors are returned as they are.
/// Each retry is logged as a warning: a batch waiting on a server that is
/// down must say so, not sit silent for the whole budget.
pub fn with_retries(
    params: &RetryParams,
    what: &str,
    mut send: impl FnMut() -> reqwest::Result<Response>,
) -> Result<Response, RequestError> {
    let started = Instant::now();
    let mut wait = params.first_wait;
    let mut retries = 0u32;
    loop {
        let (error, asked, reason) = match send() {
            Ok(resp) if resp.status().is_success() || resp.status().is_redirection() => {
                return Ok(resp)
            }
            Ok(resp) if transient(resp.status()) => {
                let asked = retry_after(&resp);
                let status = resp.status();
                let body = resp.text().unwrap_or_default();
                let reason = format!("server answered {status}");
                (RequestError::Status { status, body }, asked, reason)
            }
            Ok(resp) => {
                let status = resp.status();
                let body = resp.text().unwrap_or_default();
                return Err(RequestError::Status { status, body });
            }
            Err(e) if e.is_builder() => {
                return Err(RequestError::Unusable(format!("{what}: {}", cause(&e))))
            }
            Err(e) => {
                let error = RequestError::Transport(cause(&e));
                (error, None, "server unreachable".to_string())
            }
        };
        let pause = asked.unwrap_or(wait).min(params.max_wait.max(wait));
        let elapsed = started.elapsed();
        if elapsed + pause > params.give_up_after {
            return Err(match error {
                RequestError::Transport(cause) => RequestError::Transport(format!(
                    "{what}: {reason}, gave up after {retries} {} in {}: {cause}",
                    if retries == 1 { "retry" } else { "retries" },
                    human(elapsed)
                )),
                other => other,
            });
        }
        retries += 1;
        let left = params.give_up_after.saturating_sub(elapsed);
        tracing::warn!(
            request = what,
            error = %error,
            retry = retries,
            wait_ms = pause.as_millis() as u64,
            give_up_in_ms = left.as_millis() as u64,
            "{reason}, retry {retries} in {}, giving up in {}",
            human(pause),
            human(left)
        );
        std::thread::sleep(pause);
        wait = (wait * 2).min(params.max_wait);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn waits_read_as_a_person_says_them() {
        assert_eq!(human(Duration::from_millis(250)), "250 ms");
        assert_eq!(human(Duration::from_millis(8_200)), "8 s");
        assert_eq!(human(Duration::from_secs(560)), "9 min 20 s");
        assert_eq!(human(Duration::from_secs(600)), "10 min");
    }
}
