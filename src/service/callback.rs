//! Callbacks: a finished job is POSTed to the URL its submitter gave, so
//! an asset server is told instead of polling.
//!
//! The body is the job as `GET /v1/jobs/{id}` shows it. It is signed the
//! way webhook providers sign theirs: `Seamstress-Signature: t=T,v1=HEX`,
//! where HEX is HMAC-SHA256 over `T.BODY` (T in Unix seconds), keyed with
//! the SHA-256 of the token's secret (of `--callback-secret` on a server
//! without tokens), so a receiver that knows the secret checks both the
//! sender and the freshness. Only hosts on `--callback-allow` are called:
//! a job must not make the server reach into a private network. Deliveries
//! are kept in the job store and retried with backoff, across restarts,
//! for a bounded time; each try shows on the job.

use std::time::Duration;

use hmac::{Hmac, Mac};
use sha2::Sha256;

use super::app::Shared;
use super::config::{hex, Config};
use super::job::{now_ms, view, Callback, Job};

/// The header that carries the signature.
pub const SIGNATURE_HEADER: &str = "Seamstress-Signature";

/// Tries per callback: with waits of 1, 2, 4, ... 64 s between them, the
/// last comes about two minutes after the job finished.
const MAX_ATTEMPTS: u32 = 8;
const FIRST_WAIT_MS: u64 = 1000;
/// How long one delivery may take before it counts as failed.
const DELIVERY_TIMEOUT: Duration = Duration::from_secs(10);
/// How often due callbacks are looked for when no job has finished.
const SCAN_EVERY: Duration = Duration::from_secs(1);

/// Checks a callback URL against the allow-list: `http` or `https`, a host
/// listed (with its port, or any port when the entry has none).
pub fn check_url(cfg: &Config, url: &str) -> Result<String, String> {
    let parsed = reqwest::Url::parse(url).map_err(|e| format!("callback {url:?}: {e}"))?;
    if !matches!(parsed.scheme(), "http" | "https") {
        return Err(format!("callback {url:?}: only http and https are called"));
    }
    let host = parsed
        .host_str()
        .ok_or_else(|| format!("callback {url:?} has no host"))?
        .to_ascii_lowercase();
    let with_port = parsed
        .port_or_known_default()
        .map(|p| format!("{host}:{p}"))
        .unwrap_or_else(|| host.clone());
    if cfg
        .callback_allow
        .iter()
        .any(|a| *a == host || *a == with_port)
    {
        Ok(parsed.to_string())
    } else {
        Err(format!(
            "callback host {with_port} is not on the server's --callback-allow list"
        ))
    }
}

/// The signing key of `owner`'s callbacks, if there is one.
pub fn key_for(cfg: &Config, owner: &str) -> Option<[u8; 32]> {
    if cfg.tokens.is_empty() {
        cfg.callback_key
    } else {
        cfg.tokens
            .iter()
            .find(|t| t.owner == owner)
            .map(|t| t.digest)
    }
}

/// The signature header's value for `body` sent at `unix_secs`.
pub fn signature(key: &[u8], unix_secs: u64, body: &[u8]) -> String {
    let mut mac = Hmac::<Sha256>::new_from_slice(key).expect("HMAC takes keys of any length");
    mac.update(unix_secs.to_string().as_bytes());
    mac.update(b".");
    mac.update(body);
    let hex = hex(&mac.finalize().into_bytes());
    format!("t={unix_secs},v1={hex}")
}

/// Delivers due callbacks until the server stops: woken by every finished
/// job, and once a second for retries.
pub async fn dispatch(app: Shared) {
    let client = match reqwest::Client::builder()
        .timeout(DELIVERY_TIMEOUT)
        // A redirect could lead off the allow-list.
        .redirect(reqwest::redirect::Policy::none())
        .build()
    {
        Ok(c) => c,
        Err(e) => {
            tracing::error!(error = %e, "callbacks disabled: no HTTP client");
            return;
        }
    };
    let mut finished = app.finished.subscribe();
    let mut stopping = app.stopping.subscribe();
    loop {
        let store = app.jobs.clone();
        let due = tokio::task::spawn_blocking(move || store.callbacks_due(now_ms(), 16)).await;
        match due {
            Ok(Ok(jobs)) => {
                for job in jobs {
                    deliver(&app, &client, job).await;
                }
            }
            Ok(Err(e)) => tracing::warn!(error = %e, "cannot read due callbacks"),
            Err(e) => tracing::error!(error = %e, "callback scan failed"),
        }
        tokio::select! {
            _ = finished.changed() => {}
            _ = tokio::time::sleep(SCAN_EVERY) => {}
            _ = stopping.changed() => return,
        }
    }
}

/// One try of `job`'s callback, recorded on the job.
async fn deliver(app: &Shared, client: &reqwest::Client, job: Job) {
    let Some(mut status) = job.callback.clone() else {
        return;
    };
    let Some(key) = key_for(&app.cfg, &job.owner) else {
        // Its token was removed from the configuration since.
        status.gave_up = true;
        status.last_error = Some("no secret to sign it with".into());
        record(app, &job.id, status, None).await;
        return;
    };
    let body = serde_json::to_vec(&view(&job, true)).unwrap_or_default();
    let now_secs = now_ms() / 1000;
    status.attempts += 1;
    let sent = client
        .post(&status.url)
        .header(reqwest::header::CONTENT_TYPE, "application/json")
        .header(SIGNATURE_HEADER, signature(&key, now_secs, &body))
        .body(body)
        .send()
        .await;
    let outcome = match sent {
        Ok(r) if r.status().is_success() => Ok(()),
        Ok(r) => Err(format!("answered {}", r.status())),
        Err(e) => Err(e.to_string()),
    };
    let next = match outcome {
        Ok(()) => {
            status.delivered_ms = Some(now_ms());
            status.last_error = None;
            tracing::info!(job = %job.id, attempts = status.attempts, "callback delivered");
            None
        }
        Err(why) => {
            tracing::warn!(job = %job.id, attempts = status.attempts, error = %why, "callback failed");
            status.last_error = Some(why);
            if status.attempts >= MAX_ATTEMPTS {
                status.gave_up = true;
                None
            } else {
                Some(now_ms() + (FIRST_WAIT_MS << (status.attempts - 1)))
            }
        }
    };
    record(app, &job.id, status, next).await;
}

async fn record(app: &Shared, id: &str, status: Callback, next: Option<u64>) {
    let store = app.jobs.clone();
    let id = id.to_string();
    match tokio::task::spawn_blocking(move || store.callback_tried(&id, &status, next)).await {
        Ok(Ok(())) => {}
        Ok(Err(e)) => tracing::error!(error = %e, "cannot record a callback's delivery"),
        Err(e) => tracing::error!(error = %e, "callback record task failed"),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn only_listed_hosts_are_called() {
        let cfg = Config {
            callback_allow: vec!["hooks.example".into(), "127.0.0.1:9000".into()],
            ..Config::default()
        };
        assert!(check_url(&cfg, "https://hooks.example/done").is_ok());
        assert!(check_url(&cfg, "http://hooks.example:8080/done").is_ok());
        assert!(check_url(&cfg, "http://127.0.0.1:9000/x").is_ok());
        assert!(check_url(&cfg, "http://127.0.0.1:9001/x").is_err());
        assert!(check_url(&cfg, "http://169.254.169.254/latest").is_err());
        assert!(check_url(&cfg, "file:///etc/passwd").is_err());
        assert!(check_url(&cfg, "not a url").is_err());
    }
}
