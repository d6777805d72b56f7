//! The API's one error type: every failure of a request becomes an [`ApiError`], answered as
//! its code's HTTP status and a JSON body `{"error": {"code", "message"}}`. The codes, their
//! statuses and `Retry-After` are the application's one table ([`ErrorCode`]); `ApiError` is
//! the application's error plus what only HTTP has.
//!
//! Codes are stable snake_case strings that clients may match on (`openapi/openapi.yaml`
//! lists them; a test checks the list against the table). Messages of 4xx errors name the
//! offending input; the bodies of `internal` and `not_ready` say nothing internal (the cause is
//! logged instead).

use axum::http::{header, HeaderValue, StatusCode};
use axum::response::{IntoResponse, Response};

use seasonloc_app::store::StoreError;
use seasonloc_app::{AppError, ErrorCode};

/// Seconds a client is asked to wait after a 503.
pub const RETRY_AFTER_SECS: u64 = 1;

/// Every way a request can fail: what the use cases say ([`ApiError::App`], with their
/// codes), plus what only HTTP has. Each variant's code is in [`ApiError::code`]; status,
/// `Retry-After` and whether the message is shown come from the one table ([`ErrorCode`]).
#[derive(Debug, thiserror::Error)]
pub enum ApiError {
    /// A use case failed: its code and message as the application layer says them.
    #[error(transparent)]
    App(#[from] AppError),
    /// `map_not_found`, `localization_not_found` or `trip_not_found` for a path id that is not
    /// an id at all (no object can have it).
    #[error("{kind} `{id}` does not exist")]
    NoSuchId {
        /// What the id names.
        kind: IdKind,
        /// The id as the client wrote it.
        id: String,
    },
    /// `thumbnail_not_found`: no such image, or an image stored without a thumbnail.
    #[error("{0}")]
    ThumbnailNotFound(String),
    /// `picture_not_found`: a localization stored without a similarity picture.
    #[error("{0}")]
    PictureNotFound(String),
    /// `asset_not_found`: a dashboard file that does not exist.
    #[error("no dashboard file `{0}`")]
    AssetNotFound(String),
    /// `route_not_found`.
    #[error("no route for {0}")]
    RouteNotFound(String),
    /// `method_not_allowed`.
    #[error("method not allowed on this route")]
    MethodNotAllowed,
    /// `bad_request`: a malformed body (JSON syntax, multipart framing, unknown part).
    #[error("{0}")]
    BadRequest(String),
    /// `batch_too_large`.
    #[error("batch has more than {limit} {what} (the configured limit)")]
    BatchTooLarge {
        /// "images" or "descriptors".
        what: &'static str,
        /// The configured limit.
        limit: usize,
    },
    /// `payload_too_large`: the body exceeds the configured size limit.
    #[error("request body is larger than the configured limit of {0} bytes")]
    PayloadTooLarge(usize),
    /// `unsupported_media_type`.
    #[error("{0}")]
    UnsupportedMediaType(String),
    /// `unauthorized` with `WWW-Authenticate: Bearer`: no key, or a key the service does not
    /// know.
    #[error("{0}")]
    Unauthorized(String),
    /// `forbidden`: a known key whose role does not allow the request.
    #[error("{0}")]
    Forbidden(String),
    /// `misdirected_request`: a `Host` header the server does not answer (`--allowed-host`;
    /// without keys, by default, only `localhost` and IP addresses).
    #[error("{0}")]
    MisdirectedRequest(String),
    /// `cross_site_request`: a state-changing request to a server without API keys that a
    /// browser sent on behalf of another site (a cross-site `Origin` or `Sec-Fetch-Site`)
    /// without `X-Requested-With`.
    #[error("{0}")]
    CrossSite(String),
    /// `too_many_requests` with `Retry-After`: the key has its limit of requests in flight.
    #[error("{0}")]
    TooManyRequests(String),
    /// `queue_full` with `Retry-After`: the localize queue is full, or the request would
    /// wait (or has waited) longer than `--localize-max-wait-secs` for a CPU.
    #[error("{message}")]
    QueueFull {
        /// What happened, for the client.
        message: String,
        /// Seconds to send in `Retry-After`.
        retry_after: u64,
    },
    /// `body_timeout`: the request body stalled longer than `--body-read-timeout-secs`, or did
    /// not arrive whole within `--body-deadline-secs`.
    #[error(
        "the request body stalled longer than the server's body read timeout, or did not \
         arrive whole within its deadline"
    )]
    BodyTimeout,
    /// `overloaded` with `Retry-After`: the concurrency limit is reached.
    #[error("the server is at its concurrency limit; retry later")]
    Overloaded,
    /// `timeout`: the request took longer than the configured timeout.
    #[error("the request took longer than the configured timeout")]
    Timeout,
    /// `not_ready` with `Retry-After`: the readiness probe found the store unusable.
    #[error("the store is not ready")]
    NotReady(String),
}

impl ApiError {
    /// The code of this error in the one table.
    pub fn code(&self) -> ErrorCode {
        use ErrorCode as C;
        match self {
            ApiError::App(e) => e.code(),
            ApiError::NoSuchId { kind, .. } => match kind {
                IdKind::Map => C::MapNotFound,
                IdKind::Localization => C::LocalizationNotFound,
                IdKind::Trip => C::TripNotFound,
            },
            ApiError::ThumbnailNotFound(_) => C::ThumbnailNotFound,
            ApiError::PictureNotFound(_) => C::PictureNotFound,
            ApiError::AssetNotFound(_) => C::AssetNotFound,
            ApiError::RouteNotFound(_) => C::RouteNotFound,
            ApiError::MethodNotAllowed => C::MethodNotAllowed,
            ApiError::BadRequest(_) => C::BadRequest,
            ApiError::BatchTooLarge { .. } => C::BatchTooLarge,
            ApiError::PayloadTooLarge(_) => C::PayloadTooLarge,
            ApiError::UnsupportedMediaType(_) => C::UnsupportedMediaType,
            ApiError::Unauthorized(_) => C::Unauthorized,
            ApiError::Forbidden(_) => C::Forbidden,
            ApiError::MisdirectedRequest(_) => C::MisdirectedRequest,
            ApiError::CrossSite(_) => C::CrossSiteRequest,
            ApiError::TooManyRequests(_) => C::TooManyRequests,
            ApiError::QueueFull { .. } => C::QueueFull,
            ApiError::BodyTimeout => C::BodyTimeout,
            ApiError::Overloaded => C::Overloaded,
            ApiError::Timeout => C::Timeout,
            ApiError::NotReady(_) => C::NotReady,
        }
    }

    /// The HTTP status of this error (from the table).
    pub fn status(&self) -> StatusCode {
        StatusCode::from_u16(self.code().status()).unwrap_or(StatusCode::INTERNAL_SERVER_ERROR)
    }

    /// Seconds to send in `Retry-After` (when the code asks for it).
    pub fn retry_after(&self) -> u64 {
        if let ApiError::QueueFull { retry_after, .. } = self {
            (*retry_after).max(1)
        } else {
            RETRY_AFTER_SECS
        }
    }

    /// `invalid_parameter` (see [`AppError::param`]).
    pub fn param(name: impl Into<String>, reason: impl Into<String>) -> Self {
        ApiError::App(AppError::param(name, reason))
    }

    /// `inconsistent_parameter` (see [`AppError::inconsistent`]).
    pub fn inconsistent(name: impl Into<String>, reason: impl Into<String>) -> Self {
        ApiError::App(AppError::inconsistent(name, reason))
    }

    /// `internal`: the cause is logged, never sent.
    pub fn internal(cause: impl Into<String>) -> Self {
        ApiError::App(AppError::Internal(cause.into()))
    }

    /// A path id of `kind` that no object can have.
    pub fn no_such_id(kind: IdKind, id: impl Into<String>) -> Self {
        ApiError::NoSuchId {
            kind,
            id: id.into(),
        }
    }
}

/// What a path id names, for [`ApiError::NoSuchId`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum IdKind {
    /// A map.
    Map,
    /// A localization.
    Localization,
    /// A trip.
    Trip,
}

impl std::fmt::Display for IdKind {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            IdKind::Map => "map",
            IdKind::Localization => "localization",
            IdKind::Trip => "trip",
        })
    }
}

/// The error code of a response, set when the error body is built, so the access log names it
/// without parsing the body.
#[derive(Clone, Copy, Debug)]
pub struct ErrorCodeTag(pub &'static str);

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        let code = self.code();
        let status = self.status();
        let message = if code.hides_message() {
            let cause = self.to_string();
            if status == StatusCode::INTERNAL_SERVER_ERROR {
                tracing::error!(%code, %cause, "request failed");
                "internal server error".to_string()
            } else {
                tracing::warn!(%code, %cause, "store not ready");
                "the store is not ready".to_string()
            }
        } else {
            self.to_string()
        };
        let body = serde_json::json!({"error": {"code": code.as_str(), "message": message}});
        let mut response = (status, axum::Json(body)).into_response();
        response
            .extensions_mut()
            .insert(ErrorCodeTag(code.as_str()));
        if code.retry_after() {
            response
                .headers_mut()
                .insert(header::RETRY_AFTER, HeaderValue::from(self.retry_after()));
        }
        if status == StatusCode::UNAUTHORIZED {
            response.headers_mut().insert(
                header::WWW_AUTHENTICATE,
                HeaderValue::from_static("Bearer realm=\"seasonloc\""),
            );
        }
        response
    }
}

/// Core errors reach the wire the way the use-case layer classifies them (one mapping).
impl From<seasonloc_core::Error> for ApiError {
    fn from(e: seasonloc_core::Error) -> Self {
        ApiError::App(AppError::from(e))
    }
}

/// Store errors reach the wire with the store's codes.
impl From<StoreError> for ApiError {
    fn from(e: StoreError) -> Self {
        ApiError::App(AppError::Store(e))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    async fn body_of(e: ApiError) -> (StatusCode, serde_json::Value, Option<HeaderValue>) {
        let r = e.into_response();
        let status = r.status();
        let retry = r.headers().get(header::RETRY_AFTER).cloned();
        let bytes = axum::body::to_bytes(r.into_body(), 1 << 20).await.unwrap();
        (status, serde_json::from_slice(&bytes).unwrap(), retry)
    }

    #[tokio::test]
    async fn internal_errors_say_nothing_internal() {
        let (status, body, _) = body_of(ApiError::internal("sled: /secret/path")).await;
        assert_eq!(status, StatusCode::INTERNAL_SERVER_ERROR);
        assert_eq!(body["error"]["code"], "internal");
        assert!(!body.to_string().contains("secret"));
    }

    #[tokio::test]
    async fn queue_full_sets_retry_after() {
        let (status, body, retry) = body_of(ApiError::QueueFull {
            message: "the localize queue is full; retry later".into(),
            retry_after: 1,
        })
        .await;
        assert_eq!(status, StatusCode::SERVICE_UNAVAILABLE);
        assert_eq!(body["error"]["code"], "queue_full");
        assert_eq!(retry.unwrap(), "1");
        let (_, _, retry) = body_of(ApiError::QueueFull {
            message: "would wait 40 s".into(),
            retry_after: 40,
        })
        .await;
        assert_eq!(retry.unwrap(), "40");
    }

    #[tokio::test]
    async fn core_errors_map_to_client_errors() {
        let e: ApiError =
            seasonloc_core::Error::param("fan_out", "must be at most 1024, got 5000").into();
        let (status, body, _) = body_of(e).await;
        assert_eq!(status, StatusCode::BAD_REQUEST);
        assert!(body["error"]["message"]
            .as_str()
            .unwrap()
            .contains("fan_out"));
        let e: ApiError = seasonloc_core::Error::Image {
            name: "image #2".into(),
            reason: "truncated".into(),
        }
        .into();
        assert_eq!(e.status(), StatusCode::UNPROCESSABLE_ENTITY);
        let e: ApiError = AppError::from(seasonloc_app::store::StoreError::MapNotFound(255)).into();
        assert_eq!(e.to_string(), "map `00000000000000ff` does not exist");
    }

    #[tokio::test]
    async fn an_unavailable_store_is_503_with_retry_after() {
        let e: ApiError = AppError::from(seasonloc_app::store::StoreError::Unavailable(
            "connection refused by db.internal".into(),
        ))
        .into();
        let (status, body, retry) = body_of(e).await;
        assert_eq!(status, StatusCode::SERVICE_UNAVAILABLE);
        assert_eq!(body["error"]["code"], "not_ready");
        assert!(retry.is_some());
        assert!(!body.to_string().contains("db.internal"), "{body}");
    }

    #[tokio::test]
    async fn a_full_disk_is_507_storage_full_with_retry_after() {
        let e: ApiError = AppError::from(seasonloc_app::store::StoreError::StorageFull(
            "the embedded store: No space left on device".into(),
        ))
        .into();
        let (status, body, retry) = body_of(e).await;
        assert_eq!(status, StatusCode::INSUFFICIENT_STORAGE);
        assert_eq!(body["error"]["code"], "storage_full");
        assert!(retry.is_some());
    }
}
