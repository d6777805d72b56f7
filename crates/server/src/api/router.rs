//! The application: every resource's routes, the fallbacks, and the tower layers that enforce
//! limits and record requests.
//!
//! Layers, outermost first: request id (`x-request-id` kept when it is a short token,
//! [`request_id_ok`], otherwise replaced by a generated one, so a client's 16 KB id is neither
//! echoed nor logged) -> trace span carrying it (and the API key's name once known) -> request
//! id copied to the response -> the access log line ([`super::access_log`]) -> JSON bodies for limit errors -> metrics (labels from closed
//! sets) -> `Host` check (421, [`crate::config::HostPolicy`]) -> cross-site guard of a server
//! without keys (403 `cross_site_request`, [`cross_site`]) -> CORS (when `--cors-origin` is
//! set; answers preflights before any key is asked for) -> access control ([`super::auth`]:
//! 401/403, per-key in-flight cap 429) -> panic guard (a handler that panics answers 500
//! `internal` in the API's error shape and is logged, instead of dropping the connection) ->
//! load shedding (503 `overloaded`) over a global concurrency limit, which the probes and `/`
//! are outside of ([`UNLIMITED`]) -> timeout (503 `timeout`) -> body deadline (a body not
//! whole within `--body-deadline-secs` fails with 408 `body_timeout`, [`super::body`]) -> body
//! read timeout (a body that stalls fails with 408 `body_timeout`) -> body size limit (413).
//! Axum's own 2 MB extractor default is disabled so the configured limit is the only one.

use std::sync::Arc;
use std::time::Duration;

use axum::error_handling::HandleErrorLayer;
use axum::extract::{DefaultBodyLimit, MatchedPath, Request};
use axum::http::{header, HeaderName, HeaderValue, Method, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::{middleware, BoxError, Router};
use tokio::sync::Semaphore;
use tower::ServiceBuilder;
use tower_http::catch_panic::CatchPanicLayer;
use tower_http::cors::{AllowOrigin, CorsLayer};
use tower_http::limit::RequestBodyLimitLayer;
use tower_http::request_id::{MakeRequestUuid, PropagateRequestIdLayer, SetRequestIdLayer};
use tower_http::timeout::RequestBodyTimeoutLayer;
use tower_http::trace::TraceLayer;

use super::error::ApiError;
use super::state::AppState;
use super::{access_log, auth, body, cooc, dashboard, localize, maps, metrics, ops, trips};

/// Every route of the service as `(method, path template)`; `openapi/openapi.yaml` must
/// describe exactly these (checked by the integration tests).
pub const ROUTES: &[(&str, &str)] = &[
    ("post", "/v1/maps"),
    ("get", "/v1/maps"),
    ("get", "/v1/maps/{id}"),
    ("delete", "/v1/maps/{id}"),
    ("post", "/v1/maps/{id}/images"),
    ("get", "/v1/maps/{id}/images"),
    ("get", "/v1/maps/{id}/images/{index}/thumbnail"),
    ("post", "/v1/maps/{id}/descriptors"),
    ("post", "/v1/maps/{id}/drives"),
    ("post", "/v1/maps/{id}/localize"),
    ("get", "/v1/localizations"),
    ("get", "/v1/localizations/{id}"),
    ("get", "/v1/localizations/{id}/picture"),
    ("post", "/v1/maps/{id}/trips"),
    ("get", "/v1/maps/{id}/trips"),
    ("post", "/v1/trips/{id}/frames"),
    ("get", "/v1/trips/{id}"),
    ("post", "/v1/trips/{id}/close"),
    ("get", "/healthz"),
    ("get", "/readyz"),
    ("get", "/metrics"),
    ("get", "/openapi.json"),
    ("get", "/"),
    ("get", "/maps/{id}"),
    ("get", "/localizations/{id}"),
    ("get", "/trips/{id}"),
    ("get", "/assets/{name}"),
];

const REQUEST_ID: HeaderName = HeaderName::from_static("x-request-id");

/// Paths outside the global concurrency limit: the probes (an orchestrator restarts a pod
/// whose probes fail, so a burst of slow uploads must not make them fail) and the dashboard's
/// front page. They are cheap and never read a body.
pub const UNLIMITED: &[&str] = &["/healthz", "/readyz", "/"];

/// Longest `x-request-id` kept from a client (longer ones are replaced).
pub const MAX_REQUEST_ID: usize = 128;

/// The whole service as an axum router.
pub fn app(state: AppState) -> Router {
    let s = &state.settings;
    let timeout: Duration = s.request_timeout;
    let limits = ServiceBuilder::new()
        .layer(HandleErrorLayer::new(limit_error))
        .timeout(timeout);
    let global = Arc::new(Semaphore::new(s.max_concurrent_requests));
    let edge = ServiceBuilder::new()
        .layer(middleware::map_request(drop_bad_request_id))
        .layer(SetRequestIdLayer::new(REQUEST_ID, MakeRequestUuid))
        .layer(
            TraceLayer::new_for_http()
                .make_span_with(|req: &Request| {
                    let id = req
                        .headers()
                        .get(REQUEST_ID)
                        .and_then(|v| v.to_str().ok())
                        .unwrap_or("-");
                    let route = req
                        .extensions()
                        .get::<MatchedPath>()
                        .map_or(req.uri().path(), |p| p.as_str());
                    let method = metrics::method_label(req.method());
                    let span = tracing::info_span!(
                        "request",
                        request_id = %id,
                        method = %method,
                        route = %route,
                        key = tracing::field::Empty,
                        status = tracing::field::Empty,
                        map_id = tracing::field::Empty,
                        trip_id = tracing::field::Empty,
                        localization_id = tracing::field::Empty,
                        otel.name = tracing::field::Empty,
                        otel.kind = tracing::field::Empty,
                    );
                    if crate::telemetry::tracing_enabled() {
                        span.record("otel.name", format!("{method} {route}").as_str());
                        span.record("otel.kind", "server");
                        crate::telemetry::adopt_parent(&span, req.headers());
                    }
                    span
                })
                // The access log writes the one line per request (with its status, error code
                // and ids); the span carries the request's fields to every other event.
                .on_response(())
                .on_failure(()),
        )
        .layer(PropagateRequestIdLayer::new(REQUEST_ID))
        .layer(middleware::from_fn(access_log::log))
        .layer(middleware::map_response(json_limit_errors))
        .layer(middleware::from_fn_with_state(
            state.metrics.clone(),
            metrics::track,
        ))
        .layer(middleware::from_fn_with_state(state.clone(), check_host))
        .layer(middleware::from_fn_with_state(
            state.clone(),
            guard_cross_site,
        ))
        .option_layer(cors(&s.cors_origins))
        .layer(middleware::from_fn_with_state(
            state.auth.clone(),
            auth::authorize,
        ))
        .layer(CatchPanicLayer::custom(panic_response))
        .layer(middleware::from_fn_with_state(global, global_limit))
        .layer(limits)
        .layer(middleware::from_fn_with_state(
            s.body_deadline,
            body::deadline,
        ))
        .layer(RequestBodyTimeoutLayer::new(s.body_read_timeout))
        .layer(RequestBodyLimitLayer::new(s.max_body_bytes))
        .layer(DefaultBodyLimit::disable());
    let max_body = s.max_body_bytes;
    Router::new()
        .merge(maps::router())
        .merge(cooc::router())
        .merge(localize::router())
        .merge(trips::router())
        .merge(ops::router())
        .merge(dashboard::router())
        .fallback(|req: Request| async move {
            ApiError::RouteNotFound(format!("{} {}", req.method(), req.uri().path()))
        })
        .method_not_allowed_fallback(|| async { ApiError::MethodNotAllowed })
        .layer(edge)
        .layer(axum::Extension(BodyLimit(max_body)))
        .with_state(state)
}

/// Whether a client's `x-request-id` is kept: 1 to [`MAX_REQUEST_ID`] characters of
/// `A-Z a-z 0-9 - _ . : + / =` (a UUID, a trace id, a short token). Anything else is replaced
/// by a generated id, so what is echoed and logged is bounded.
pub fn request_id_ok(id: &[u8]) -> bool {
    !id.is_empty()
        && id.len() <= MAX_REQUEST_ID
        && id
            .iter()
            .all(|b| b.is_ascii_alphanumeric() || b"-_.:+/=".contains(b))
}

/// Removes an `x-request-id` that [`request_id_ok`] refuses (the next layer generates one).
async fn drop_bad_request_id(mut req: Request) -> Request {
    let bad = req
        .headers()
        .get_all(REQUEST_ID)
        .iter()
        .any(|v| !request_id_ok(v.as_bytes()))
        || req.headers().get_all(REQUEST_ID).iter().count() > 1;
    if bad {
        req.headers_mut().remove(REQUEST_ID);
    }
    req
}

/// The global concurrency limit (`--max-concurrent-requests`): a request past it is shed at
/// once with 503 `overloaded`, except on the [`UNLIMITED`] paths.
async fn global_limit(
    axum::extract::State(limit): axum::extract::State<Arc<Semaphore>>,
    req: Request,
    next: middleware::Next,
) -> Response {
    if UNLIMITED.contains(&req.uri().path()) {
        return next.run(req).await;
    }
    match limit.try_acquire_owned() {
        Ok(_permit) => next.run(req).await,
        Err(_) => ApiError::Overloaded.into_response(),
    }
}

/// The answer to a request whose handler panicked: logged with its message (a bug to fix),
/// answered 500 `internal` like any other internal error, never with the panic's text.
fn panic_response(err: Box<dyn std::any::Any + Send + 'static>) -> Response {
    let message = err
        .downcast_ref::<String>()
        .map(String::as_str)
        .or_else(|| err.downcast_ref::<&str>().copied())
        .unwrap_or("(no message)");
    ApiError::internal(format!("request handler panicked: {message}")).into_response()
}

/// The CORS layer for the configured origins (`None` when there are none: no cross-origin
/// access). Preflights from a listed origin are answered 200 with the allowed methods and
/// headers; other origins get no `Access-Control-Allow-Origin`, so browsers refuse.
fn cors(origins: &[String]) -> Option<CorsLayer> {
    if origins.is_empty() {
        return None;
    }
    // `Settings::validate` checked each origin is a valid header value.
    let list: Vec<HeaderValue> = origins
        .iter()
        .filter_map(|o| HeaderValue::from_str(o).ok())
        .collect();
    Some(
        CorsLayer::new()
            .allow_origin(AllowOrigin::list(list))
            .allow_methods([Method::GET, Method::POST, Method::DELETE])
            .allow_headers([
                header::AUTHORIZATION,
                header::CONTENT_TYPE,
                HeaderName::from_static("idempotency-key"),
                REQUEST_ID,
            ])
            .expose_headers([REQUEST_ID, header::RETRY_AFTER])
            .max_age(Duration::from_secs(600)),
    )
}

/// Rejects requests whose `Host` the server does not answer ([`crate::config::HostPolicy`]:
/// `--allowed-host`, or without keys by default only `localhost` and IP addresses) with 421:
/// against DNS rebinding, where a hostile page on a name that resolves to this server would
/// otherwise be same-origin with it. The probes stay reachable under any name (orchestrators
/// often call them by IP or a service name).
async fn check_host(
    axum::extract::State(state): axum::extract::State<AppState>,
    req: Request,
    next: middleware::Next,
) -> Response {
    let path = req.uri().path();
    if path == "/healthz" || path == "/readyz" {
        return next.run(req).await;
    }
    let host = req
        .headers()
        .get(header::HOST)
        .and_then(|h| h.to_str().ok())
        .or_else(|| req.uri().authority().map(|a| a.as_str()));
    if state.settings.hosts.allows(host) {
        next.run(req).await
    } else {
        let shown: String = host.unwrap_or_default().chars().take(100).collect();
        ApiError::MisdirectedRequest(format!(
            "Host `{shown}` is not one this server answers for (see --allowed-host)"
        ))
        .into_response()
    }
}

/// The header a non-browser client (or a page of this server) may send to say a request is
/// not a cross-site form: a browser sends a custom header cross-site only after a CORS
/// preflight, which this server grants only to `--cors-origin`.
pub const CSRF_HEADER: &str = "x-requested-with";

/// Why a state-changing request to a server without API keys looks like one a browser sent on
/// behalf of another site (`None`: it does not). On such a server anyone who can reach the
/// port may write, so a page on the web that the operator's browser visits must not: a request
/// whose `Origin` is another site (or `null`), or whose `Sec-Fetch-Site` says `cross-site` or
/// `same-site`, is 403 `cross_site_request`; one whose body is `text/plain` or
/// `application/x-www-form-urlencoded` (what an HTML form or a no-CORS `fetch` sends, also from
/// browsers that send neither header; no route takes them) is 415 `unsupported_media_type`.
/// Either passes with [`CSRF_HEADER`], which a browser sends cross-site only after a CORS
/// preflight. `curl` and programs send no `Origin`, so their requests pass.
pub fn cross_site(req: &Request, cors_origins: &[String]) -> Option<ApiError> {
    let m = req.method();
    if m == Method::GET || m == Method::HEAD || m == Method::OPTIONS {
        return None;
    }
    let h = req.headers();
    if h.contains_key(CSRF_HEADER) {
        return None;
    }
    let text = |name: header::HeaderName| {
        h.get(name).map(|v| {
            String::from_utf8_lossy(v.as_bytes())
                .trim()
                .to_ascii_lowercase()
        })
    };
    if let Some(site) = text(HeaderName::from_static("sec-fetch-site")) {
        if site == "cross-site" || site == "same-site" {
            return Some(ApiError::CrossSite(format!(
                "a request a browser sent from another site (`Sec-Fetch-Site: {site}`) may not \
                 change anything on a server without API keys"
            )));
        }
    }
    if let Some(origin) = text(header::ORIGIN) {
        let host = text(header::HOST).unwrap_or_default();
        let same = origin
            .split_once("://")
            .is_some_and(|(_, authority)| authority == host);
        if !same && !cors_origins.iter().any(|o| o.eq_ignore_ascii_case(&origin)) {
            let shown: String = origin.chars().take(100).collect();
            return Some(ApiError::CrossSite(format!(
                "a request from the page of another origin (`{shown}`) may not change anything \
                 on a server without API keys (start it with --api-keys, or list the origin \
                 with --cors-origin)"
            )));
        }
    }
    let ct = text(header::CONTENT_TYPE)?;
    let essence = ct.split(';').next().unwrap_or("").trim();
    (essence == "text/plain" || essence == "application/x-www-form-urlencoded").then(|| {
        ApiError::UnsupportedMediaType(format!(
            "no route takes a `{essence}` body (what an HTML form or another site's page \
             sends, refused on a server without API keys): send the route's own content type \
             (JSON, multipart or octet-stream), or add an `X-Requested-With` header"
        ))
    })
}

/// Middleware of [`cross_site`] on servers without API keys (with keys, a request needs its
/// `Authorization` header, which no other site's page can send without a preflight).
async fn guard_cross_site(
    axum::extract::State(state): axum::extract::State<AppState>,
    req: Request,
    next: middleware::Next,
) -> Response {
    if state.auth.is_none() {
        if let Some(refusal) = cross_site(&req, &state.settings.cors_origins) {
            return refusal.into_response();
        }
    }
    next.run(req).await
}

/// The configured body limit, for messages of responses built outside the handlers.
#[derive(Clone, Copy)]
struct BodyLimit(usize);

async fn limit_error(err: BoxError) -> ApiError {
    if err.is::<tower::timeout::error::Elapsed>() {
        ApiError::Timeout
    } else {
        ApiError::internal(format!("middleware: {err}"))
    }
}

/// `RequestBodyLimitLayer` answers an over-long `Content-Length` itself with a plain-text 413;
/// give it the API's error shape.
async fn json_limit_errors(
    limit: Option<axum::Extension<BodyLimit>>,
    response: Response,
) -> Response {
    let is_json = response
        .headers()
        .get(header::CONTENT_TYPE)
        .is_some_and(|v| v.as_bytes().starts_with(b"application/json"));
    if response.status() == StatusCode::PAYLOAD_TOO_LARGE && !is_json {
        let limit = limit.map_or(0, |axum::Extension(BodyLimit(n))| n);
        return ApiError::PayloadTooLarge(limit).into_response();
    }
    response
}

#[cfg(test)]
mod tests {
    use super::*;
    use axum::body::Body;
    use axum::routing::get;
    use tower::ServiceExt;

    #[tokio::test]
    async fn a_panicking_handler_answers_500_in_the_error_shape_without_its_message() {
        let router: Router = Router::new()
            .route(
                "/boom",
                get(|| async {
                    let side: Option<u32> = std::hint::black_box(None);
                    side.expect("secret detail of the panic").to_string()
                }),
            )
            .layer(CatchPanicLayer::custom(panic_response));
        let r = router
            .oneshot(Request::get("/boom").body(Body::empty()).unwrap())
            .await
            .unwrap();
        assert_eq!(r.status(), StatusCode::INTERNAL_SERVER_ERROR);
        let bytes = axum::body::to_bytes(r.into_body(), 1 << 20).await.unwrap();
        let body: serde_json::Value = serde_json::from_slice(&bytes).unwrap();
        assert_eq!(body["error"]["code"], "internal");
        assert!(!body.to_string().contains("secret"), "{body}");
    }

    #[test]
    fn request_ids_are_short_tokens() {
        assert!(request_id_ok(b"0f8fad5b-d9cb-469f-a165-70867728950e"));
        assert!(request_id_ok(b"trace:abc/def+1=="));
        assert!(request_id_ok(&[b'r'; MAX_REQUEST_ID]));
        assert!(!request_id_ok(&[b'r'; MAX_REQUEST_ID + 1]));
        assert!(!request_id_ok(b""));
        assert!(!request_id_ok(b"has space"));
        assert!(!request_id_ok(b"line\nbreak"));
    }

    fn post(headers: &[(&str, &str)]) -> Request {
        let mut b = Request::post("/v1/trips/00000000000000ff/close");
        for (k, v) in headers {
            b = b.header(*k, *v);
        }
        b.body(Body::empty()).unwrap()
    }

    #[test]
    fn cross_site_writes_are_told_apart_from_programs() {
        let host = ("host", "127.0.0.1:8080");
        // What curl and programs send: no Origin.
        assert!(cross_site(&post(&[host]), &[]).is_none());
        let multipart = ("content-type", "multipart/form-data; boundary=x");
        assert!(cross_site(&post(&[host, multipart]), &[]).is_none());
        let json = ("content-type", "application/json");
        // A page of this server.
        let own = ("origin", "http://127.0.0.1:8080");
        assert!(cross_site(&post(&[host, own, json]), &[]).is_none());
        assert!(cross_site(&post(&[host, ("sec-fetch-site", "same-origin")]), &[]).is_none());
        // Another site's page.
        let evil = ("origin", "http://evil.example");
        for refused in [
            post(&[host, evil, multipart]),
            post(&[host, ("origin", "null")]),
            post(&[host, ("sec-fetch-site", "cross-site")]),
            post(&[host, ("content-type", "text/plain;charset=UTF-8")]),
            post(&[host, ("content-type", "application/x-www-form-urlencoded")]),
        ] {
            assert!(
                cross_site(&refused, &[]).is_some(),
                "{:?}",
                refused.headers()
            );
        }
        // A listed CORS origin, or the custom header, is let through.
        let listed = vec!["http://evil.example".to_string()];
        assert!(cross_site(&post(&[host, evil, json]), &listed).is_none());
        let custom = ("x-requested-with", "seasonloc");
        assert!(cross_site(
            &post(&[host, evil, ("content-type", "text/plain"), custom]),
            &[]
        )
        .is_none());
        // Reads are never refused.
        let get = Request::get("/v1/maps")
            .header("origin", "http://evil.example")
            .body(Body::empty())
            .unwrap();
        assert!(cross_site(&get, &[]).is_none());
    }
}
