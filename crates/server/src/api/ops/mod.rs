//! Operations routes: `/healthz` (the process answers), `/readyz` (the store answers reads),
//! `/metrics` (Prometheus text) and `/openapi.json` (the shipped `openapi/openapi.yaml` as JSON).

use axum::extract::State;
use axum::http::{header, HeaderValue};
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use axum::{Json, Router};

pub mod dto;

use self::dto::StatusResponse;
use crate::api::error::ApiError;
use crate::api::metrics::Snapshot;
use crate::api::state::AppState;

/// The routes of this resource.
pub fn router() -> Router<AppState> {
    Router::new()
        .route("/healthz", get(healthz))
        .route("/readyz", get(readyz))
        .route("/metrics", get(metrics))
        .route("/openapi.json", get(openapi))
}

async fn healthz() -> Json<StatusResponse> {
    Json(StatusResponse { status: "ok" })
}

async fn readyz(State(state): State<AppState>) -> Result<Json<StatusResponse>, ApiError> {
    state
        .app
        .ready()
        .await
        .map_err(|e| ApiError::NotReady(e.to_string()))?;
    Ok(Json(StatusResponse { status: "ready" }))
}

async fn metrics(State(state): State<AppState>) -> Response {
    // A scrape must answer even when the store does not: the count is left out then.
    let counted = tokio::time::timeout(
        std::time::Duration::from_secs(2),
        state.app.open_trip_counts(),
    )
    .await;
    let open_trips = match counted {
        Ok(Ok(c)) => Some(vec![
            ("new", c.new),
            ("localized", c.localized),
            ("lost", c.lost),
            ("relocalized", c.relocalized),
        ]),
        Ok(Err(e)) => {
            tracing::warn!("metrics: cannot count the open trips: {e}");
            None
        }
        Err(_) => {
            tracing::warn!("metrics: counting the open trips took over 2 s; left out");
            None
        }
    };
    let snapshot = Snapshot {
        open_trips,
        cache: state.app.descriptor_cache_usage(),
        queue_depth: state.admission.depth(),
    };
    let mut text = state.metrics.render(&snapshot);
    let a = &state.admission;
    text.push_str(&format!(
        "# HELP seasonloc_localize_waiting Localize requests waiting for a CPU turn.\n\
         # TYPE seasonloc_localize_waiting gauge\nseasonloc_localize_waiting {}\n\
         # HELP seasonloc_localize_arrivals_total Localize requests that asked for a CPU turn.\n\
         # TYPE seasonloc_localize_arrivals_total counter\nseasonloc_localize_arrivals_total {}\n",
        a.waiting(),
        a.arrivals()
    ));
    let mut r = text.into_response();
    r.headers_mut().insert(
        header::CONTENT_TYPE,
        HeaderValue::from_static("text/plain; version=0.0.4"),
    );
    r
}

async fn openapi(State(state): State<AppState>) -> Response {
    let mut r = state.openapi_json.clone().into_response();
    r.headers_mut().insert(
        header::CONTENT_TYPE,
        HeaderValue::from_static("application/json"),
    );
    r
}
