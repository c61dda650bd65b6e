//! `GET /v1/jobs/{id}/files/{name}`: a result file, whole or one byte
//! range, streamed from the file store a piece at a time so that a large
//! file never sits whole in the server's memory; or, with `?redirect=1` on
//! a store that can sign URLs, a redirect to the store itself.

use std::sync::atomic::Ordering;
use std::time::Duration;

use axum::body::{Body, Bytes};
use axum::extract::{Path, RawQuery, State};
use axum::http::{header, HeaderMap, HeaderValue, StatusCode};
use axum::response::{IntoResponse, Response};

use super::api::{caller, owned_job};
use super::app::{blocking, Shared};
use super::error::ApiError;
use super::job::{FileEntry, JobState};
use super::store::keys;

/// Bytes read from the store per piece of a response: what one download
/// holds in memory at a time. An object store's ranged GET costs a round
/// trip per piece, small beside a mebibyte's transfer.
const PIECE: u64 = 1 << 20;

/// How long a redirect's signed URL stays valid: long enough to start a
/// download, short enough that a leaked URL soon stops working.
const SIGNED_FOR: Duration = Duration::from_secs(300);

pub async fn get_file(
    State(app): State<Shared>,
    Path((id, name)): Path<(String, String)>,
    RawQuery(query): RawQuery,
    headers: HeaderMap,
) -> Result<Response, ApiError> {
    let owner = caller(&app, &headers)?;
    let job = owned_job(&app, &id, &owner).await?;
    if job.state != JobState::Succeeded {
        return Err(ApiError::new(
            StatusCode::CONFLICT,
            "job_not_succeeded",
            format!("the job is {}: it has no files", job.state.as_str()),
        ));
    }
    let entry = job
        .files
        .iter()
        .find(|f| f.name == name)
        .cloned()
        .ok_or_else(|| ApiError::not_found("the job has no such file"))?;
    let key = keys::output(&job.id, &entry.name);
    let etag = format!("\"{}\"", entry.sha256);
    let mut resp = if etag_matches(&headers, &etag) {
        StatusCode::NOT_MODIFIED.into_response()
    } else if let Some(url) = redirect_to(&app, &query, &key).await? {
        let mut r = StatusCode::TEMPORARY_REDIRECT.into_response();
        if let Ok(v) = HeaderValue::from_str(&url) {
            r.headers_mut().insert(header::LOCATION, v);
        }
        // A signed URL is the caller's alone.
        r.headers_mut()
            .insert(header::CACHE_CONTROL, HeaderValue::from_static("no-store"));
        return Ok(r);
    } else {
        body(&app, &headers, &etag, &entry, key).await?
    };
    let h = resp.headers_mut();
    if let Ok(v) = HeaderValue::from_str(&etag) {
        h.insert(header::ETAG, v);
    }
    h.insert(
        header::CACHE_CONTROL,
        HeaderValue::from_static("private, max-age=31536000, immutable"),
    );
    Ok(resp)
}

/// The signed URL to send the caller to, if it asked for one
/// (`redirect=1`) and the store can sign.
async fn redirect_to(
    app: &Shared,
    query: &Option<String>,
    key: &str,
) -> Result<Option<String>, ApiError> {
    let asked = query
        .as_deref()
        .unwrap_or("")
        .split('&')
        .any(|p| matches!(p, "redirect=1" | "redirect=true"));
    if !asked {
        return Ok(None);
    }
    let key = key.to_string();
    blocking(app, move |a| Ok(a.files.presign(&key, SIGNED_FOR)?)).await
}

/// The file, or the range the request asks for, as a streamed body.
async fn body(
    app: &Shared,
    headers: &HeaderMap,
    etag: &str,
    entry: &FileEntry,
    key: String,
) -> Result<Response, ApiError> {
    let len = entry.bytes;
    // A Range for another version of the file (If-Range) gets it whole.
    let if_range_ok = headers
        .get(header::IF_RANGE)
        .is_none_or(|v| v.to_str().is_ok_and(|v| v.trim() == etag));
    let range = headers
        .get(header::RANGE)
        .and_then(|v| v.to_str().ok())
        .filter(|_| if_range_ok);
    let (status, first, last) = match byte_range(range, len) {
        Span::Whole => (StatusCode::OK, 0, len),
        Span::Part(first, last) => (StatusCode::PARTIAL_CONTENT, first, last + 1),
        Span::Unsatisfiable => {
            let mut r = ApiError::new(
                StatusCode::RANGE_NOT_SATISFIABLE,
                "range_not_satisfiable",
                format!("the file holds {len} bytes"),
            )
            .into_response();
            if let Ok(v) = HeaderValue::from_str(&format!("bytes */{len}")) {
                r.headers_mut().insert(header::CONTENT_RANGE, v);
            }
            return Ok(r);
        }
    };
    // The first piece before the answer: a file missing from the store is
    // an error response, not a body cut short.
    let head = read_piece(app, &key, first, last).await.inspect_err(|_| {
        tracing::error!(file = %key, "result file missing or unreadable");
    })?;
    let next = first + head.len() as u64;
    let rest = futures_util::stream::try_unfold(
        (app.clone(), key, next),
        move |(app, key, at)| async move {
            if at >= last {
                return Ok(None);
            }
            // Mid-body, an error can only cut the response short; the
            // client sees fewer bytes than Content-Length promised.
            let piece = read_piece(&app, &key, at, last).await.map_err(|_| {
                tracing::error!(file = %key, at, "result file unreadable mid-download");
                std::io::Error::other("the file store failed mid-download")
            })?;
            let end = at + piece.len() as u64;
            Ok::<_, std::io::Error>(Some((piece, (app, key, end))))
        },
    );
    let pieces = futures_util::StreamExt::chain(
        futures_util::stream::once(async move { Ok::<_, std::io::Error>(head) }),
        rest,
    );
    let mut r = (status, Body::from_stream(pieces)).into_response();
    let h = r.headers_mut();
    h.insert(header::CONTENT_LENGTH, HeaderValue::from(last - first));
    if status == StatusCode::PARTIAL_CONTENT {
        // A piece of a file is bytes, whatever the whole is: a piece of
        // report.json is not JSON.
        if let Ok(v) = HeaderValue::from_str(&format!("bytes {first}-{}/{len}", last - 1)) {
            h.insert(header::CONTENT_RANGE, v);
        }
    } else if let Ok(v) = HeaderValue::from_str(&entry.content_type) {
        h.insert(header::CONTENT_TYPE, v);
    }
    h.insert(header::ACCEPT_RANGES, HeaderValue::from_static("bytes"));
    app.metrics
        .bytes_out
        .fetch_add(last - first, Ordering::Relaxed);
    Ok(r)
}

/// Up to [`PIECE`] bytes of the file from `at`, not past `end`.
async fn read_piece(app: &Shared, key: &str, at: u64, end: u64) -> Result<Bytes, ApiError> {
    let key = key.to_string();
    let to = end.min(at + PIECE);
    blocking(app, move |a| {
        let bytes = a.files.read_range(&key, at..to)?;
        if bytes.len() as u64 != to - at {
            return Err(ApiError::internal(
                "the file in the file store is not the one the job recorded",
            ));
        }
        Ok(Bytes::from(bytes))
    })
    .await
}

fn etag_matches(headers: &HeaderMap, etag: &str) -> bool {
    headers
        .get_all(header::IF_NONE_MATCH)
        .iter()
        .filter_map(|v| v.to_str().ok())
        .flat_map(|v| v.split(','))
        .map(str::trim)
        .any(|t| t == "*" || t == etag || t.strip_prefix("W/") == Some(etag))
}

/// What a `Range` header asks of a file of `len` bytes.
#[derive(Debug, PartialEq, Eq)]
enum Span {
    Whole,
    /// First and last byte, inclusive.
    Part(u64, u64),
    Unsatisfiable,
}

/// One byte range (`bytes=a-b`, `bytes=a-`, `bytes=-n`) is served; a header
/// that is malformed or asks for several ranges gets the whole file, as
/// RFC 9110 lets a server do.
fn byte_range(header: Option<&str>, len: u64) -> Span {
    let Some(spec) = header.and_then(|h| h.trim().strip_prefix("bytes=")) else {
        return Span::Whole;
    };
    if spec.contains(',') {
        return Span::Whole;
    }
    let Some((a, b)) = spec.trim().split_once('-') else {
        return Span::Whole;
    };
    let num = |t: &str| -> Option<u64> {
        (!t.is_empty() && t.bytes().all(|c| c.is_ascii_digit()))
            .then(|| t.parse().ok())
            .flatten()
    };
    let (first, last) = match (num(a.trim()), num(b.trim())) {
        (Some(first), Some(last)) if first <= last => (first, last.min(len.saturating_sub(1))),
        (Some(first), None) if b.trim().is_empty() => (first, len.saturating_sub(1)),
        (None, Some(suffix)) if a.trim().is_empty() => {
            if suffix == 0 {
                return Span::Unsatisfiable;
            }
            (len.saturating_sub(suffix), len.saturating_sub(1))
        }
        _ => return Span::Whole,
    };
    if len == 0 || first >= len {
        return Span::Unsatisfiable;
    }
    Span::Part(first, last)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn byte_ranges() {
        assert_eq!(byte_range(None, 10), Span::Whole);
        assert_eq!(byte_range(Some("bytes=0-3"), 10), Span::Part(0, 3));
        assert_eq!(byte_range(Some("bytes=4-"), 10), Span::Part(4, 9));
        assert_eq!(byte_range(Some("bytes=-3"), 10), Span::Part(7, 9));
        assert_eq!(byte_range(Some("bytes=8-100"), 10), Span::Part(8, 9));
        assert_eq!(byte_range(Some("bytes=-100"), 10), Span::Part(0, 9));
        assert_eq!(byte_range(Some("bytes=10-"), 10), Span::Unsatisfiable);
        assert_eq!(byte_range(Some("bytes=-0"), 10), Span::Unsatisfiable);
        assert_eq!(byte_range(Some("bytes=0-1,4-5"), 10), Span::Whole);
        assert_eq!(byte_range(Some("bytes=5-2"), 10), Span::Whole);
        assert_eq!(byte_range(Some("items=0-1"), 10), Span::Whole);
        assert_eq!(byte_range(Some("bytes=x-1"), 10), Span::Whole);
    }

    #[test]
    fn etags() {
        let mut h = HeaderMap::new();
        h.insert(
            header::IF_NONE_MATCH,
            HeaderValue::from_static("\"a\", \"b\""),
        );
        assert!(etag_matches(&h, "\"b\""));
        assert!(!etag_matches(&h, "\"c\""));
    }
}
