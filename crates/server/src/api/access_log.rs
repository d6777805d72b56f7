//! The access log: one event per request once its response is known, at `info` (`warn` for a
//! 4xx, `error` for a 5xx), target `seasonloc::access`.
//!
//! Its fields, at the top level of a JSON line: `request_id`, `method`, `route` (the matched
//! template, or `unmatched`: ids never make the route unbounded), `status`, `latency_ms`,
//! `key` (the API key's name, never the key), `map_id` / `trip_id` / `localization_id` where
//! the path names one, and `error_code` (the code of the API's error body) on every 4xx/5xx.

use std::time::Instant;

use axum::extract::{MatchedPath, Request};
use axum::middleware::Next;
use axum::response::Response;

use super::auth::KeyName;
use super::error::ErrorCodeTag;
use super::metrics::method_label;

/// The ids a request's path names, from its matched route template.
#[derive(Debug, Default, PartialEq, Eq)]
pub struct PathIds {
    /// After `maps/`.
    pub map: Option<String>,
    /// After `trips/`.
    pub trip: Option<String>,
    /// After `localizations/`.
    pub localization: Option<String>,
}

/// Longest id kept in the log (a map id is 16 hex digits; a longer path segment is a bad
/// request, logged as `invalid`).
const MAX_ID: usize = 32;

impl PathIds {
    /// Reads the `{id}` segments of `path` where `template` has them, named by the segment
    /// before.
    pub fn of(template: &str, path: &str) -> PathIds {
        let mut ids = PathIds::default();
        let t: Vec<&str> = template.split('/').collect();
        let p: Vec<&str> = path.split('/').collect();
        for (i, seg) in t.iter().enumerate() {
            if *seg != "{id}" || i == 0 {
                continue;
            }
            let Some(value) = p.get(i) else { continue };
            let value = if value.len() <= MAX_ID && value.bytes().all(|b| b.is_ascii_alphanumeric())
            {
                (*value).to_string()
            } else {
                "invalid".to_string()
            };
            match t[i - 1] {
                "maps" => ids.map = Some(value),
                "trips" => ids.trip = Some(value),
                "localizations" => ids.localization = Some(value),
                _ => {}
            }
        }
        ids
    }
}

/// Middleware writing the access log line of every request.
pub async fn log(req: Request, next: Next) -> Response {
    let started = Instant::now();
    let method = method_label(req.method());
    let route = req
        .extensions()
        .get::<MatchedPath>()
        .map(|p| p.as_str().to_string());
    let ids = route
        .as_deref()
        .map(|t| PathIds::of(t, req.uri().path()))
        .unwrap_or_default();
    let request_id = req
        .headers()
        .get("x-request-id")
        .and_then(|v| v.to_str().ok())
        .unwrap_or("-")
        .to_string();
    let span = tracing::Span::current();
    for (field, value) in [
        ("map_id", &ids.map),
        ("trip_id", &ids.trip),
        ("localization_id", &ids.localization),
    ] {
        if let Some(v) = value {
            span.record(field, v.as_str());
        }
    }
    let mut response = next.run(req).await;
    let status = response.status().as_u16();
    span.record("status", status);
    crate::telemetry::inject_context(&span, response.headers_mut());
    let key = response.extensions().get::<KeyName>().map(|k| k.0.clone());
    let error_code = response.extensions().get::<ErrorCodeTag>().map(|c| c.0);
    let latency_ms = (started.elapsed().as_secs_f64() * 1e3 * 1e3).round() / 1e3;
    macro_rules! line {
        ($level:expr) => {
            tracing::event!(
                target: "seasonloc::access",
                $level,
                request_id = %request_id,
                method,
                route = route.as_deref().unwrap_or("unmatched"),
                status,
                latency_ms,
                key = key.as_deref(),
                map_id = ids.map.as_deref(),
                trip_id = ids.trip.as_deref(),
                localization_id = ids.localization.as_deref(),
                error_code,
                "request"
            )
        };
    }
    match status {
        500.. => line!(tracing::Level::ERROR),
        400..=499 => line!(tracing::Level::WARN),
        _ => line!(tracing::Level::INFO),
    }
    response
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ids_come_from_the_template_positions() {
        let ids = PathIds::of("/v1/maps/{id}/trips", "/v1/maps/0cb564b57e957e7c/trips");
        assert_eq!(ids.map.as_deref(), Some("0cb564b57e957e7c"));
        assert_eq!(ids.trip, None);
        let ids = PathIds::of("/v1/trips/{id}/frames", "/v1/trips/00ab/frames");
        assert_eq!(ids.trip.as_deref(), Some("00ab"));
        let ids = PathIds::of("/v1/localizations/{id}", "/v1/localizations/x%20y");
        assert_eq!(ids.localization.as_deref(), Some("invalid"));
        let ids = PathIds::of(
            "/v1/maps/{id}/images/{index}/thumbnail",
            "/v1/maps/12/images/3/thumbnail",
        );
        assert_eq!(ids.map.as_deref(), Some("12"));
        assert_eq!(PathIds::of("/v1/maps", "/v1/maps"), PathIds::default());
    }
}
