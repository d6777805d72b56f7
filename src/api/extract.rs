//! Extractors whose rejections use the API's error shape instead of axum's plain-text bodies,
//! and the parsers of what every resource reads the same way (JSON documents, map ids).

use axum::extract::rejection::{BytesRejection, JsonRejection};
use axum::extract::{FromRequest, Request};
use axum::http::StatusCode;
use serde::de::DeserializeOwned;

use super::error::ApiError;
use super::state::AppState;
use super::wire::parse_id;

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

#[allow(
    clippy::wildcard_enum_match_arm,
    reason = "axum's JsonRejection is #[non_exhaustive]: a fallback arm is required"
)]
fn json_rejection(r: JsonRejection, max_body: usize) -> ApiError {
    match r {
        JsonRejection::JsonDataError(e) => ApiError::param("body", e.body_text()),
        JsonRejection::JsonSyntaxError(e) => ApiError::BadRequest(e.body_text()),
        JsonRejection::MissingJsonContentType(e) => ApiError::UnsupportedMediaType(e.body_text()),
        JsonRejection::BytesRejection(e) => bytes_rejection(e, max_body),
        other => ApiError::BadRequest(other.body_text()),
    }
}

/// Whether a body read failed because the body stalled longer than the body read timeout
/// (`tower_http`'s `TimeoutError` somewhere in the error's source chain).
pub fn is_body_timeout(err: &(dyn std::error::Error + 'static)) -> bool {
    let mut cause = Some(err);
    while let Some(e) = cause {
        if e.is::<tower_http::timeout::TimeoutError>() {
            return true;
        }
        cause = e.source();
    }
    false
}

/// Maps a failure to read the body: over the limit is 413, a stalled body 408, anything else
/// 400.
pub fn bytes_rejection(r: BytesRejection, max_body: usize) -> ApiError {
    if is_body_timeout(&r) {
        ApiError::BodyTimeout
    } else if r.status() == StatusCode::PAYLOAD_TOO_LARGE {
        ApiError::PayloadTooLarge(max_body)
    } else {
        ApiError::BadRequest(r.body_text())
    }
}

/// Parses a map id from a path or query; ids that cannot exist are 404.
pub fn map_id(s: &str) -> Result<u64, ApiError> {
    parse_id(s).ok_or_else(|| ApiError::MapNotFound(s.to_string()))
}

/// Parses a JSON document already read. Type errors and unknown fields are 400
/// `invalid_parameter` naming the field by its path (prefixed with `root` when given, e.g.
/// `params.flows`); syntax errors are 400 `bad_request`.
pub fn parse_json<T: DeserializeOwned>(bytes: &[u8], root: Option<&str>) -> Result<T, ApiError> {
    let mut de = serde_json::Deserializer::from_slice(bytes);
    let value = serde_path_to_error::deserialize(&mut de).map_err(|e| {
        let path = e.path().to_string();
        let inner = e.into_inner();
        match inner.classify() {
            serde_json::error::Category::Data => {
                let name = match (root, path.as_str()) {
                    (Some(r), ".") => r.to_string(),
                    (Some(r), p) if p.starts_with('[') => format!("{r}{p}"),
                    (Some(r), p) => format!("{r}.{p}"),
                    (None, ".") => "body".to_string(),
                    (None, p) => p.to_string(),
                };
                ApiError::param(name, inner.to_string())
            }
            serde_json::error::Category::Io
            | serde_json::error::Category::Syntax
            | serde_json::error::Category::Eof => {
                ApiError::BadRequest(format!("malformed JSON: {inner}"))
            }
        }
    })?;
    de.end()
        .map_err(|e| ApiError::BadRequest(format!("malformed JSON: {e}")))?;
    Ok(value)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn errors_name_the_field_path() {
        #[derive(serde::Deserialize, Debug)]
        #[serde(deny_unknown_fields)]
        struct Inner {
            #[allow(dead_code)]
            exact: bool,
        }
        #[derive(serde::Deserialize, Debug)]
        struct Outer {
            #[allow(dead_code)]
            params: Inner,
        }
        let e = parse_json::<Outer>(br#"{"params": {"exact": "yes"}}"#, None).unwrap_err();
        assert!(
            matches!(&e, ApiError::InvalidParameter { name, .. } if name == "params.exact"),
            "{e}"
        );
        let e = parse_json::<Inner>(br#"{"exact": 1}"#, Some("params")).unwrap_err();
        assert!(e.to_string().contains("params.exact"), "{e}");
        let e = parse_json::<Inner>(br#"{"exact": true} x"#, None).unwrap_err();
        assert!(matches!(e, ApiError::BadRequest(_)), "{e}");
    }
}
