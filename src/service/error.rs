//! Every error response: JSON `{code, message}` with a stable `code`.

use axum::http::{header, HeaderValue, StatusCode};
use axum::response::{IntoResponse, Response};

use super::store::StoreError;

/// What `Retry-After` says while a store is away: the prober looks four
/// times a second then, so a client coming back this soon finds it back
/// if it is.
pub const STORE_RETRY_AFTER_S: u64 = 5;

#[derive(Debug)]
pub struct ApiError {
    pub status: StatusCode,
    pub code: &'static str,
    pub message: String,
    pub retry_after: Option<u64>,
}

impl ApiError {
    pub fn new(status: StatusCode, code: &'static str, message: impl Into<String>) -> Self {
        ApiError {
            status,
            code,
            message: message.into(),
            retry_after: None,
        }
    }

    pub fn bad_request(message: impl Into<String>) -> Self {
        Self::new(StatusCode::BAD_REQUEST, "bad_request", message)
    }

    pub fn invalid_options(message: impl Into<String>) -> Self {
        Self::new(StatusCode::BAD_REQUEST, "invalid_options", message)
    }

    pub fn not_found(message: impl Into<String>) -> Self {
        Self::new(StatusCode::NOT_FOUND, "not_found", message)
    }

    pub fn job_not_found() -> Self {
        Self::not_found("no such job")
    }

    pub fn internal(message: impl Into<String>) -> Self {
        Self::new(StatusCode::INTERNAL_SERVER_ERROR, "internal", message)
    }

    pub fn unavailable(code: &'static str, message: impl Into<String>, retry: u64) -> Self {
        ApiError {
            retry_after: Some(retry),
            ..Self::new(StatusCode::SERVICE_UNAVAILABLE, code, message)
        }
    }

    pub fn too_large(limit: usize) -> Self {
        Self::new(
            StatusCode::PAYLOAD_TOO_LARGE,
            "payload_too_large",
            format!("the request body is larger than {limit} bytes"),
        )
    }
}

impl From<StoreError> for ApiError {
    fn from(e: StoreError) -> Self {
        if let StoreError::Full(_) = e {
            tracing::error!(error = %e, "storage full");
            return ApiError {
                retry_after: Some(60),
                ..Self::new(
                    StatusCode::INSUFFICIENT_STORAGE,
                    "storage_full",
                    "the server's storage is full; try again later",
                )
            };
        }
        if let StoreError::Unavailable { which, .. } = &e {
            tracing::warn!(error = %e, "store unavailable");
            return ApiError::unavailable(
                "store_unavailable",
                format!("the {which} does not answer; try again shortly"),
                STORE_RETRY_AFTER_S,
            );
        }
        tracing::error!(error = %e, "store failure");
        ApiError::internal("the job store failed; try again")
    }
}

/// The JSON body of an error, for responses built outside handlers.
pub fn body(code: &str, message: &str) -> String {
    serde_json::json!({ "code": code, "message": message }).to_string()
}

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        let mut resp = (
            self.status,
            [(header::CONTENT_TYPE, "application/json")],
            body(self.code, &self.message),
        )
            .into_response();
        if let Some(secs) = self.retry_after {
            resp.headers_mut()
                .insert(header::RETRY_AFTER, HeaderValue::from(secs));
        }
        if self.status == StatusCode::UNAUTHORIZED {
            resp.headers_mut().insert(
                header::WWW_AUTHENTICATE,
                HeaderValue::from_static("Bearer realm=\"seamstress\""),
            );
        }
        resp
    }
}
