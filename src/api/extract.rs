//! Extractors whose rejections use the API's error shape instead of axum's plain-text bodies.

use axum::extract::rejection::{BytesRejection, JsonRejection};
use axum::extract::{FromRequest, Request};
use axum::http::StatusCode;
use serde::de::DeserializeOwned;

use super::error::ApiError;
use super::state::AppState;

/// `Json<T>` whose failures are [`ApiError`]s: syntax errors are 400 `bad_request`, unknown
/// fields and wrong types 400 `invalid_parameter`, a missing JSON content type 415.
pub struct ApiJson<T>(pub T);

impl<T: DeserializeOwned> FromRequest<AppState> for ApiJson<T> {
    type Rejection = ApiError;

    async fn from_request(req: Request, state: &AppState) -> Result<Self, Self::Rejection> {
        match axum::Json::<T>::from_request(req, state).await {
            Ok(axum::Json(v)) => Ok(ApiJson(v)),
            Err(r) => Err(json_rejection(r, state.settings.max_body_bytes)),
        }
    }
}

fn json_rejection(r: JsonRejection, max_body: usize) -> ApiError {
    match r {
        JsonRejection::JsonDataError(e) => ApiError::param("body", e.body_text()),
        JsonRejection::JsonSyntaxError(e) => ApiError::BadRequest(e.body_text()),
        JsonRejection::MissingJsonContentType(e) => ApiError::UnsupportedMediaType(e.body_text()),
        JsonRejection::BytesRejection(e) => bytes_rejection(e, max_body),
        other => ApiError::BadRequest(other.body_text()),
    }
}

/// Maps a failure to read the body: over the limit is 413, anything else 400.
pub fn bytes_rejection(r: BytesRejection, max_body: usize) -> ApiError {
    if r.status() == StatusCode::PAYLOAD_TOO_LARGE {
        ApiError::PayloadTooLarge(max_body)
    } else {
        ApiError::BadRequest(r.body_text())
    }
}

/// Parses a JSON body already read; errors as for [`ApiJson`].
pub fn parse_json<T: DeserializeOwned>(bytes: &[u8]) -> Result<T, ApiError> {
    serde_json::from_slice(bytes).map_err(|e| match e.classify() {
        serde_json::error::Category::Data => ApiError::param("body", e.to_string()),
        serde_json::error::Category::Io
        | serde_json::error::Category::Syntax
        | serde_json::error::Category::Eof => ApiError::BadRequest(format!("malformed JSON: {e}")),
    })
}
