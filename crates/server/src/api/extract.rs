//! Extractors whose rejections use the API's error shape instead of axum's plain-text bodies,
//! and the parsers of what every resource reads the same way (JSON documents, map ids).

use axum::body::Bytes;
use axum::extract::rejection::BytesRejection;
use axum::extract::{FromRequest, Request};
use axum::http::{header, HeaderMap, StatusCode};
use serde::de::DeserializeOwned;

use super::error::{ApiError, IdKind};
use super::state::AppState;
use super::wire::parse_id;

/// A JSON object body whose failures are [`ApiError`]s: a content type other than JSON is 415,
/// then everything [`parse_json_object`] says (syntax 400 `bad_request`; not an object, unknown
/// fields and wrong types 400 `invalid_parameter` naming the field).
pub struct ApiJson<T>(pub T);

impl<T: DeserializeOwned> FromRequest<AppState> for ApiJson<T> {
    type Rejection = ApiError;

    async fn from_request(req: Request, state: &AppState) -> Result<Self, Self::Rejection> {
        let ApiJsonBody(value, _) = ApiJsonBody::from_request(req, state).await?;
        Ok(ApiJson(value))
    }
}

/// [`ApiJson`] with the body's bytes kept as well (what an `Idempotency-Key` fingerprints).
pub struct ApiJsonBody<T>(pub T, pub Bytes);

impl<T: DeserializeOwned> FromRequest<AppState> for ApiJsonBody<T> {
    type Rejection = ApiError;

    async fn from_request(req: Request, state: &AppState) -> Result<Self, Self::Rejection> {
        if !is_json(req.headers()) {
            return Err(ApiError::UnsupportedMediaType(
                "expected a request with `Content-Type: application/json`".into(),
            ));
        }
        let body = Bytes::from_request(req, state)
            .await
            .map_err(|e| bytes_rejection(e, state.settings.max_body_bytes))?;
        let value = parse_json_object(&body, None)?;
        Ok(ApiJsonBody(value, body))
    }
}

/// Whether the request says its body is JSON (`application/json` or a `+json` type, any
/// parameters).
pub fn is_json(headers: &HeaderMap) -> bool {
    let Some(value) = headers
        .get(header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
    else {
        return false;
    };
    let essence = value.split(';').next().unwrap_or("").trim();
    let Some((kind, sub)) = essence.split_once('/') else {
        return false;
    };
    kind.eq_ignore_ascii_case("application")
        && (sub.eq_ignore_ascii_case("json") || sub.to_ascii_lowercase().ends_with("+json"))
}

/// Whether a body read failed because the body stalled longer than the body read timeout
/// (`tower_http`'s `TimeoutError` somewhere in the error's source chain) or did not arrive whole
/// within its deadline ([`super::body::BodyDeadlineExceeded`]).
pub fn is_body_timeout(err: &(dyn std::error::Error + 'static)) -> bool {
    let mut cause = Some(err);
    while let Some(e) = cause {
        if e.is::<tower_http::timeout::TimeoutError>()
            || e.is::<super::body::BodyDeadlineExceeded>()
        {
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
    parse_id(s).ok_or_else(|| ApiError::no_such_id(IdKind::Map, s))
}

/// Parses a JSON document that must be an object (a request body, the `params` or `drive`
/// part): serde would also fill a struct from an array (`[4, null]` as `{"fan_out": 4}`), which
/// the schema does not allow, so other JSON is 400 `invalid_parameter` naming `root` (or
/// `body`). What is not JSON at all, or nothing, is 400 `bad_request` ("malformed JSON"), as
/// from [`parse_json`].
pub fn parse_json_object<T: DeserializeOwned>(
    bytes: &[u8],
    root: Option<&str>,
) -> Result<T, ApiError> {
    let what = || root.map_or_else(|| "the body".to_string(), |r| format!("`{r}`"));
    match bytes.iter().find(|b| !b.is_ascii_whitespace()) {
        Some(b'{') => parse_json(bytes, root),
        Some(_) => match serde_json::from_slice::<serde::de::IgnoredAny>(bytes) {
            Ok(_) => Err(ApiError::param(
                root.unwrap_or("body"),
                "must be a JSON object",
            )),
            Err(e) => Err(ApiError::BadRequest(format!(
                "malformed JSON in {}: {e}",
                what()
            ))),
        },
        None => Err(ApiError::BadRequest(format!(
            "malformed JSON: {} is empty",
            what()
        ))),
    }
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
    use seasonloc_app::AppError;

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
            matches!(&e, ApiError::App(AppError::InvalidParameter { name, .. }) if name == "params.exact"),
            "{e}"
        );
        let e = parse_json::<Inner>(br#"{"exact": 1}"#, Some("params")).unwrap_err();
        assert!(e.to_string().contains("params.exact"), "{e}");
        let e = parse_json::<Inner>(br#"{"exact": true} x"#, None).unwrap_err();
        assert!(matches!(e, ApiError::BadRequest(_)), "{e}");
    }
}
