//! The API's one error type: every failure of a request becomes an [`ApiError`], which maps to
//! an HTTP status and a JSON body `{"error": {"code", "message"}}` in one exhaustive match.
//!
//! Codes are stable snake_case strings that clients may match on (they are listed in
//! `openapi/openapi.yaml`). Messages of 4xx errors name the offending input; 5xx bodies say
//! nothing internal (the cause is logged instead).

use axum::http::{header, HeaderValue, StatusCode};
use axum::response::{IntoResponse, Response};

use seasonloc_app::AppError;

/// Seconds a client is asked to wait after a 503.
pub const RETRY_AFTER_SECS: u64 = 1;

/// Every way a request can fail. The doc line of each variant gives its status and code.
#[derive(Debug, thiserror::Error)]
pub enum ApiError {
    /// 404 `map_not_found`.
    #[error("map `{0}` does not exist")]
    MapNotFound(String),
    /// 404 `localization_not_found`.
    #[error("localization `{0}` does not exist")]
    LocalizationNotFound(String),
    /// 404 `trip_not_found`.
    #[error("trip `{0}` does not exist")]
    TripNotFound(String),
    /// 409 `trip_closed`: frames posted to a closed trip.
    #[error("trip `{0}` is closed; open a new trip")]
    TripClosed(String),
    /// 409 `trip_conflict`: the trip changed while a batch was computed (retry the batch).
    #[error("{0}")]
    TripConflict(String),
    /// 404 `thumbnail_not_found`: no such image, or an image stored without a thumbnail.
    #[error("{0}")]
    ThumbnailNotFound(String),
    /// 404 `picture_not_found`: a localization stored without a similarity picture.
    #[error("{0}")]
    PictureNotFound(String),
    /// 404 `asset_not_found`: a dashboard file that does not exist.
    #[error("no dashboard file `{0}`")]
    AssetNotFound(String),
    /// 404 `route_not_found`.
    #[error("no route for {0}")]
    RouteNotFound(String),
    /// 405 `method_not_allowed`.
    #[error("method not allowed on this route")]
    MethodNotAllowed,
    /// 400 `invalid_parameter`: an unknown, missing or out-of-range parameter.
    #[error("invalid parameter `{name}`: {reason}")]
    InvalidParameter {
        /// The parameter, e.g. `fan_out` or `descriptor.cell_size`.
        name: String,
        /// Why it was rejected.
        reason: String,
    },
    /// 422 `inconsistent_parameter`: a parameter valid on its own (by the published schema)
    /// that does not fit the request's other parameters, the server's limits or the model it
    /// names.
    #[error("invalid parameter `{name}`: {reason}")]
    InconsistentParameter {
        /// The parameter, e.g. `relocalization_cost`.
        name: String,
        /// What it does not fit, and why.
        reason: String,
    },
    /// 400 `bad_request`: a malformed body (JSON syntax, multipart framing, unknown part).
    #[error("{0}")]
    BadRequest(String),
    /// 400 `empty_batch`.
    #[error("empty batch: {0}")]
    EmptyBatch(String),
    /// 400 `batch_too_large`.
    #[error("batch has more than {limit} {what} (the configured limit)")]
    BatchTooLarge {
        /// "images" or "descriptors".
        what: &'static str,
        /// The configured limit.
        limit: usize,
    },
    /// 409 `map_empty`: localizing against a map without reference images.
    #[error("map `{0}` has no reference images yet")]
    MapEmpty(String),
    /// 409 `model_mismatch`: a CNN map's model file is no longer the model the map was
    /// created with (changed, truncated or removed).
    #[error("{0}")]
    ModelMismatch(String),
    /// 409 `map_kind`: the request does not apply to this kind of map (e.g. a second batch of
    /// reference images on a `cooc` map, drives on a non-`cooc` map).
    #[error("{0}")]
    MapKind(String),
    /// 409 `map_changed`: a concurrent request changed the map first; retrying is safe.
    #[error("{0}")]
    MapChanged(String),
    /// 409 `map_full`.
    #[error("map `{0}` cannot hold more images")]
    MapFull(String),
    /// 409 `idempotency_key_reused`: an `Idempotency-Key` sent again with a different request.
    #[error("{0}")]
    IdempotencyKeyReused(String),
    /// 413 `payload_too_large`: the body exceeds the configured size limit.
    #[error("request body is larger than the configured limit of {0} bytes")]
    PayloadTooLarge(usize),
    /// 413 `image_too_large`: an image exceeds the configured pixel limit.
    #[error(
        "{part} is {width}x{height} = {pixels} pixels, more than the configured limit of {limit}"
    )]
    ImageTooLarge {
        /// The part, e.g. `image #2 ("a.png")`.
        part: String,
        /// Width in pixels.
        width: u32,
        /// Height in pixels.
        height: u32,
        /// `width * height`.
        pixels: u64,
        /// The configured limit.
        limit: u64,
    },
    /// 415 `unsupported_media_type`.
    #[error("{0}")]
    UnsupportedMediaType(String),
    /// 422 `invalid_image`: a part that is not a decodable JPEG/PNG.
    #[error("{part}: {reason}")]
    InvalidImage {
        /// The part.
        part: String,
        /// What is wrong with it.
        reason: String,
    },
    /// 422 `descriptor_length`: descriptors (or images giving them) do not fit the map.
    #[error("{0}")]
    DescriptorLength(String),
    /// 422 `non_finite`: NaN or infinity in a descriptor.
    #[error("{0}")]
    NonFinite(String),
    /// 422 `shape_mismatch`: inputs whose shapes do not fit together.
    #[error("{0}")]
    ShapeMismatch(String),
    /// 401 `unauthorized` with `WWW-Authenticate: Bearer`: no key, or a key the service does
    /// not know.
    #[error("{0}")]
    Unauthorized(String),
    /// 403 `forbidden`: a known key whose role does not allow the request.
    #[error("{0}")]
    Forbidden(String),
    /// 421 `misdirected_request`: a `Host` header that is not in `--allowed-host`.
    #[error("{0}")]
    MisdirectedRequest(String),
    /// 429 `too_many_requests` with `Retry-After`: the key has its limit of requests in flight.
    #[error("{0}")]
    TooManyRequests(String),
    /// 503 `queue_full` with `Retry-After`: the localize queue is full, or the request would
    /// wait (or has waited) longer than `--localize-max-wait-secs` for a CPU.
    #[error("{message}")]
    QueueFull {
        /// What happened, for the client.
        message: String,
        /// Seconds to send in `Retry-After`.
        retry_after: u64,
    },
    /// 408 `body_timeout`: the request body stalled longer than `--body-read-timeout-secs`.
    #[error("the request body stalled longer than the server's body read timeout")]
    BodyTimeout,
    /// 503 `overloaded` with `Retry-After`: the concurrency limit is reached.
    #[error("the server is at its concurrency limit; retry later")]
    Overloaded,
    /// 503 `timeout`: the request took longer than the configured timeout.
    #[error("the request took longer than the configured timeout")]
    Timeout,
    /// 503 `not_ready` with `Retry-After`: the store is not usable (it cannot be reached).
    #[error("the store is not ready")]
    NotReady(String),
    /// 500 `internal`: the message is logged, never sent.
    #[error("internal error: {0}")]
    Internal(String),
}

impl ApiError {
    /// Status, machine-readable code, and whether to send `Retry-After`.
    pub fn parts(&self) -> (StatusCode, &'static str, bool) {
        use StatusCode as S;
        match self {
            ApiError::MapNotFound(_) => (S::NOT_FOUND, "map_not_found", false),
            ApiError::LocalizationNotFound(_) => (S::NOT_FOUND, "localization_not_found", false),
            ApiError::RouteNotFound(_) => (S::NOT_FOUND, "route_not_found", false),
            ApiError::AssetNotFound(_) => (S::NOT_FOUND, "asset_not_found", false),
            ApiError::ThumbnailNotFound(_) => (S::NOT_FOUND, "thumbnail_not_found", false),
            ApiError::PictureNotFound(_) => (S::NOT_FOUND, "picture_not_found", false),
            ApiError::TripNotFound(_) => (S::NOT_FOUND, "trip_not_found", false),
            ApiError::TripClosed(_) => (S::CONFLICT, "trip_closed", false),
            ApiError::TripConflict(_) => (S::CONFLICT, "trip_conflict", false),
            ApiError::MethodNotAllowed => (S::METHOD_NOT_ALLOWED, "method_not_allowed", false),
            ApiError::InvalidParameter { .. } => (S::BAD_REQUEST, "invalid_parameter", false),
            ApiError::InconsistentParameter { .. } => {
                (S::UNPROCESSABLE_ENTITY, "inconsistent_parameter", false)
            }
            ApiError::BadRequest(_) => (S::BAD_REQUEST, "bad_request", false),
            ApiError::EmptyBatch(_) => (S::BAD_REQUEST, "empty_batch", false),
            ApiError::BatchTooLarge { .. } => (S::BAD_REQUEST, "batch_too_large", false),
            ApiError::MapEmpty(_) => (S::CONFLICT, "map_empty", false),
            ApiError::MapFull(_) => (S::CONFLICT, "map_full", false),
            ApiError::ModelMismatch(_) => (S::CONFLICT, "model_mismatch", false),
            ApiError::MapKind(_) => (S::CONFLICT, "map_kind", false),
            ApiError::MapChanged(_) => (S::CONFLICT, "map_changed", false),
            ApiError::IdempotencyKeyReused(_) => (S::CONFLICT, "idempotency_key_reused", false),
            ApiError::PayloadTooLarge(_) => (S::PAYLOAD_TOO_LARGE, "payload_too_large", false),
            ApiError::ImageTooLarge { .. } => (S::PAYLOAD_TOO_LARGE, "image_too_large", false),
            ApiError::UnsupportedMediaType(_) => {
                (S::UNSUPPORTED_MEDIA_TYPE, "unsupported_media_type", false)
            }
            ApiError::InvalidImage { .. } => (S::UNPROCESSABLE_ENTITY, "invalid_image", false),
            ApiError::DescriptorLength(_) => (S::UNPROCESSABLE_ENTITY, "descriptor_length", false),
            ApiError::NonFinite(_) => (S::UNPROCESSABLE_ENTITY, "non_finite", false),
            ApiError::ShapeMismatch(_) => (S::UNPROCESSABLE_ENTITY, "shape_mismatch", false),
            ApiError::Unauthorized(_) => (S::UNAUTHORIZED, "unauthorized", false),
            ApiError::Forbidden(_) => (S::FORBIDDEN, "forbidden", false),
            ApiError::MisdirectedRequest(_) => {
                (S::MISDIRECTED_REQUEST, "misdirected_request", false)
            }
            ApiError::TooManyRequests(_) => (S::TOO_MANY_REQUESTS, "too_many_requests", true),
            ApiError::QueueFull { .. } => (S::SERVICE_UNAVAILABLE, "queue_full", true),
            ApiError::BodyTimeout => (S::REQUEST_TIMEOUT, "body_timeout", false),
            ApiError::Overloaded => (S::SERVICE_UNAVAILABLE, "overloaded", true),
            ApiError::Timeout => (S::SERVICE_UNAVAILABLE, "timeout", true),
            ApiError::NotReady(_) => (S::SERVICE_UNAVAILABLE, "not_ready", true),
            ApiError::Internal(_) => (S::INTERNAL_SERVER_ERROR, "internal", false),
        }
    }

    /// Seconds to send in `Retry-After` (when [`ApiError::parts`] says to send it).
    pub fn retry_after(&self) -> u64 {
        if let ApiError::QueueFull { retry_after, .. } = self {
            (*retry_after).max(1)
        } else {
            RETRY_AFTER_SECS
        }
    }

    /// Shorthand for [`ApiError::InvalidParameter`].
    pub fn param(name: impl Into<String>, reason: impl Into<String>) -> Self {
        ApiError::InvalidParameter {
            name: name.into(),
            reason: reason.into(),
        }
    }

    /// Shorthand for [`ApiError::InconsistentParameter`].
    pub fn inconsistent(name: impl Into<String>, reason: impl Into<String>) -> Self {
        ApiError::InconsistentParameter {
            name: name.into(),
            reason: reason.into(),
        }
    }
}

impl IntoResponse for ApiError {
    #[allow(
        clippy::wildcard_enum_match_arm,
        reason = "every variant but the two logged ones is a client error whose Display is its message"
    )]
    fn into_response(self) -> Response {
        let (status, code, retry) = self.parts();
        let message = match &self {
            ApiError::Internal(cause) => {
                tracing::error!(%code, %cause, "request failed");
                "internal server error".to_string()
            }
            ApiError::NotReady(cause) => {
                tracing::warn!(%code, %cause, "store not ready");
                "the store is not ready".to_string()
            }
            other => other.to_string(),
        };
        let body = serde_json::json!({"error": {"code": code, "message": message}});
        let mut response = (status, axum::Json(body)).into_response();
        if retry {
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
        ApiError::from(AppError::from(e))
    }
}

impl From<AppError> for ApiError {
    fn from(e: AppError) -> Self {
        use super::wire::format_id as id;
        match e {
            AppError::MapNotFound(m) => ApiError::MapNotFound(id(m)),
            AppError::LocalizationNotFound(l) => ApiError::LocalizationNotFound(id(l)),
            AppError::TripNotFound(t) => ApiError::TripNotFound(id(t)),
            AppError::TripClosed(t) => ApiError::TripClosed(id(t)),
            AppError::TripConflict(m) => ApiError::TripConflict(m),
            AppError::InvalidParameter { name, reason } => {
                ApiError::InvalidParameter { name, reason }
            }
            AppError::InconsistentParameter { name, reason } => {
                ApiError::InconsistentParameter { name, reason }
            }
            AppError::EmptyBatch(m) => ApiError::EmptyBatch(m),
            AppError::MapEmpty(m) => ApiError::MapEmpty(id(m)),
            AppError::ModelMismatch(m) => ApiError::ModelMismatch(m),
            AppError::MapKind(m) => ApiError::MapKind(m),
            AppError::MapChanged(m) => ApiError::MapChanged(m),
            AppError::MapFull(m) => ApiError::MapFull(id(m)),
            AppError::ImageTooLarge {
                part,
                width,
                height,
                pixels,
                limit,
            } => ApiError::ImageTooLarge {
                part,
                width,
                height,
                pixels,
                limit,
            },
            AppError::InvalidImage { part, reason } => ApiError::InvalidImage { part, reason },
            AppError::DescriptorLength(m) => ApiError::DescriptorLength(m),
            AppError::NonFinite(m) => ApiError::NonFinite(m),
            AppError::ShapeMismatch(m) => ApiError::ShapeMismatch(m),
            AppError::IdempotencyKeyReused(m) => ApiError::IdempotencyKeyReused(m),
            AppError::Unavailable(cause) => ApiError::NotReady(cause),
            AppError::Internal(cause) => ApiError::Internal(cause),
        }
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
        let (status, body, _) = body_of(ApiError::Internal("sled: /secret/path".into())).await;
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
        assert_eq!(e.parts().0, StatusCode::UNPROCESSABLE_ENTITY);
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
}
