//! Trips over HTTP (spec §6): a vehicle opens a trip on a map, posts its frames in small
//! multipart batches as it drives, and gets its current position back with every batch.
//!
//! * `POST /v1/maps/{id}/trips` opens a trip (optional JSON body of [`dto::TripParamsDto`]);
//! * `POST /v1/trips/{id}/frames` extends it with a batch of `image` parts;
//! * `GET /v1/trips/{id}`, `GET /v1/maps/{id}/trips` (newest first, paginated),
//!   `POST /v1/trips/{id}/close` (later frames are 409 `trip_closed`).
//!
//! What a trip does with its frames, and how batches of one trip are ordered, is the use
//! case's (`app::trips`); this module decodes, calls it, and encodes.

use axum::body::Bytes;
use axum::extract::multipart::{Multipart, MultipartRejection};
use axum::extract::rejection::BytesRejection;
use axum::extract::{Path, Query, State};
use axum::http::{header, HeaderMap, StatusCode};
use axum::routing::{get, post};
use axum::Extension;
use axum::{Json, Router};
pub mod dto;

use self::dto::{
    BatchTimings, FrameEstimateDto, FramesResponse, ListQuery, ReadQuery, TripListResponse,
    TripParamsDto, TripParamsUsed, TripResponse,
};
use crate::api::error::{ApiError, IdKind};
use crate::api::extract::{bytes_rejection, map_id, parse_json_object};
use crate::api::state::AppState;
use crate::api::wire::{format_id, parse_id, DEFAULT_PAGE, MAX_PAGE};
use crate::api::{idempotency, upload};
use seasonloc_app::caller::Caller;
use seasonloc_app::model::TripRecord;
use seasonloc_app::store::PageRequest;
use seasonloc_core::trip::TripStatus;

/// The routes of this resource.
pub fn router() -> Router<AppState> {
    Router::new()
        .route("/v1/maps/{id}/trips", post(open).get(list))
        .route("/v1/trips/{id}", get(read))
        .route("/v1/trips/{id}/frames", post(frames))
        .route("/v1/trips/{id}/close", post(close))
}

fn status_name(s: TripStatus) -> String {
    match s {
        TripStatus::Localized => "localized",
        TripStatus::Lost => "lost",
        TripStatus::Relocalized => "relocalized",
    }
    .into()
}

fn trip_id(s: &str) -> Result<u64, ApiError> {
    parse_id(s).ok_or_else(|| ApiError::no_such_id(IdKind::Trip, s))
}

fn response(r: &TripRecord) -> TripResponse {
    TripResponse {
        id: format_id(r.id),
        map_id: format_id(r.map_id),
        created_at_ms: r.created_ms,
        closed_at_ms: r.closed_ms,
        frame_count: r.frame_count,
        reference_count: r.reference_count,
        status: r.status.map(status_name),
        latest_status: None,
        params: TripParamsUsed::from(&r.params),
        opened_by: r.owner.clone(),
        estimates: None,
    }
}

async fn open(
    State(state): State<AppState>,
    Path(id): Path<String>,
    caller: Option<Extension<Caller>>,
    headers: HeaderMap,
    body: Result<Bytes, BytesRejection>,
) -> Result<(StatusCode, HeaderMap, Json<TripResponse>), ApiError> {
    let map = map_id(&id)?;
    let body = body.map_err(|r| bytes_rejection(r, state.settings.max_body_bytes))?;
    // No body at all takes the defaults; anything else must be a JSON object (a body of
    // whitespace is not a JSON document).
    let dto = if body.is_empty() {
        TripParamsDto::default()
    } else {
        let content_type = headers
            .get(header::CONTENT_TYPE)
            .and_then(|v| v.to_str().ok())
            .unwrap_or("");
        if !content_type.starts_with("application/json") {
            return Err(ApiError::UnsupportedMediaType(format!(
                "trip parameters must be sent as application/json, got `{content_type}`"
            )));
        }
        parse_json_object(&body, None)?
    };
    let params = dto.into_params()?;
    let key = idempotency::from_parts(&headers, "trips", &[&body])?;
    let (record, replayed) = state
        .app
        .open_trip(map, params, key, caller.as_deref())
        .await?;
    Ok((
        StatusCode::CREATED,
        idempotency::headers(replayed),
        Json(response(&record)),
    ))
}

async fn frames(
    State(state): State<AppState>,
    Path(id): Path<String>,
    caller: Option<Extension<Caller>>,
    headers: HeaderMap,
    multipart: Result<Multipart, MultipartRejection>,
) -> Result<(HeaderMap, Json<FramesResponse>), ApiError> {
    let trip = trip_id(&id)?;
    let s = &state.settings;
    // Frames are `image` parts only: a trip's parameters are fixed when it is opened.
    let batch = upload::read(
        multipart.map_err(|r| upload::rejection(r, &headers))?,
        None,
        s.max_batch_images,
        s.max_body_bytes,
    )
    .await?;
    let key = idempotency::from_request(&headers, &batch)?;
    let started = std::time::Instant::now();
    let outcome = state
        .app
        .post_frames(trip, batch.images, key, caller.as_deref())
        .await?;
    let t = &outcome.timings;
    if !outcome.replayed {
        let m = &state.metrics;
        m.observe_stage("features", t.features);
        m.observe_stage("solve", t.solve);
        m.observe_stage("store", t.store);
        let frames: Vec<(&'static str, f64)> = outcome
            .update
            .estimates
            .iter()
            .map(|e| (e.status.as_str(), e.p_correct))
            .collect();
        m.observe_trip_batch(started.elapsed().as_secs_f64(), &frames);
    }
    let update = &outcome.update;
    let headers = idempotency::headers(outcome.replayed);
    Ok((
        headers,
        Json(FramesResponse {
            trip_id: format_id(trip),
            frame_count: outcome.trip.frame_count,
            estimates: update
                .estimates
                .iter()
                .map(FrameEstimateDto::from)
                .collect(),
            status: status_name(update.status),
            latest_status: update.latest_status().into(),
            window: update.window.iter().map(FrameEstimateDto::from).collect(),
            hidden_cost: outcome.hidden_cost,
            timings: BatchTimings {
                load: t.load,
                features: t.features,
                solve: t.solve,
                store: t.store,
            },
        }),
    ))
}

async fn read(
    State(state): State<AppState>,
    Path(id): Path<String>,
    query: Result<Query<ReadQuery>, axum::extract::rejection::QueryRejection>,
) -> Result<Json<TripResponse>, ApiError> {
    let Query(q) = query.map_err(|e| ApiError::param("query", e.body_text()))?;
    let since = q.since.unwrap_or(0);
    let (record, estimates) = state.app.get_trip(trip_id(&id)?, since).await?;
    let mut r = response(&record);
    // The latest frame is in every read (a poll's `since` is at most the frame count).
    let latest = record.frame_count.checked_sub(1);
    r.latest_status = Some(
        estimates
            .iter()
            .find(|e| Some(e.frame as u64) == latest)
            .map(|e| e.status.into()),
    );
    r.estimates = Some(estimates.iter().map(FrameEstimateDto::from).collect());
    Ok(Json(r))
}

async fn close(
    State(state): State<AppState>,
    Path(id): Path<String>,
    caller: Option<Extension<Caller>>,
) -> Result<Json<TripResponse>, ApiError> {
    let record = state
        .app
        .close_trip(trip_id(&id)?, caller.as_deref())
        .await?;
    Ok(Json(response(&record)))
}

async fn list(
    State(state): State<AppState>,
    Path(id): Path<String>,
    query: Result<Query<ListQuery>, axum::extract::rejection::QueryRejection>,
) -> Result<Json<TripListResponse>, ApiError> {
    let map = map_id(&id)?;
    let Query(q) = query.map_err(|e| ApiError::param("query", e.body_text()))?;
    let limit = q.limit.unwrap_or(DEFAULT_PAGE);
    if limit == 0 || limit > MAX_PAGE {
        return Err(ApiError::param(
            "limit",
            format!("must be between 1 and {MAX_PAGE}, got {limit}"),
        ));
    }
    let before = match q.before.as_deref() {
        None => None,
        Some(b) => Some(
            parse_id(b)
                .ok_or_else(|| ApiError::param("before", format!("`{b}` is not a trip id")))?,
        ),
    };
    let page = state
        .app
        .list_trips(map, PageRequest { before, limit })
        .await?;
    Ok(Json(TripListResponse {
        items: page.items.iter().map(response).collect(),
        next: page.next.map(format_id),
    }))
}
