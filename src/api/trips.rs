//! Trips over HTTP (spec §6): a vehicle opens a trip on a map, posts its frames in small
//! multipart batches as it drives, and gets its current position back with every batch.
//!
//! * `POST /v1/maps/{id}/trips` opens a trip (optional JSON body of [`TripParamsDto`]);
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
use axum::{Json, Router};
use serde::{Deserialize, Serialize};

use super::dto::{format_id, parse_id};
use super::error::ApiError;
use super::localize::{DEFAULT_PAGE, MAX_PAGE};
use super::maps::map_id;
use super::state::AppState;
use super::upload;
use crate::store::{FrameRecord, PageRequest, TripParamsDocument, TripRecord};
use crate::trip::{FrameEstimate, TripParams, TripStatus};

/// The routes of this resource.
pub fn router() -> Router<AppState> {
    Router::new()
        .route("/v1/maps/{id}/trips", post(open).get(list))
        .route("/v1/trips/{id}", get(read))
        .route("/v1/trips/{id}/frames", post(frames))
        .route("/v1/trips/{id}/close", post(close))
}

/// Optional parameters of a trip (JSON body of `POST /v1/maps/{id}/trips`).
#[derive(Clone, Debug, Default, Deserialize, Serialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct TripParamsDto {
    /// `K`, fan-out (default 4).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub fan_out: Option<usize>,
    /// `W`: a number > 0 or `"auto"` (default: resolved from the first batch).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub hidden_cost: Option<serde_json::Value>,
    /// Horizontal edges (default true).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub horizontal: Option<bool>,
    /// Frames whose estimates may still be revised (default 32).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub lag: Option<usize>,
    /// Allow re-entry anywhere on the map (default true).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub relocalization: Option<bool>,
    /// Cost `R` of a re-entry (default 1.0).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub relocalization_cost: Option<f64>,
    /// Frames' worth of weight of the map's prior column means (default 100).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub prior_weight: Option<f64>,
    /// Online column normalisation (default true).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub normalize: Option<bool>,
}

impl TripParamsDto {
    /// Resolves defaults and validates every range (errors name the field).
    pub fn into_params(self) -> Result<TripParams, ApiError> {
        let d = TripParams::default();
        let hidden_cost =
            match self.hidden_cost {
                None => d.hidden_cost,
                Some(serde_json::Value::String(s)) if s == "auto" => None,
                Some(serde_json::Value::Number(n)) => Some(n.as_f64().ok_or_else(|| {
                    ApiError::param("hidden_cost", format!("{n} is not a number"))
                })?),
                Some(other) => {
                    return Err(ApiError::param(
                        "hidden_cost",
                        format!("must be a number > 0 or \"auto\", got {other}"),
                    ))
                }
            };
        if self.relocalization == Some(false) && self.relocalization_cost.is_some() {
            return Err(ApiError::param(
                "relocalization_cost",
                "is set but `relocalization` is false",
            ));
        }
        let relocalization = match self.relocalization {
            Some(false) => None,
            Some(true) | None => Some(
                self.relocalization_cost
                    .unwrap_or(crate::trip::DEFAULT_RELOCALIZATION_COST),
            ),
        };
        let params = TripParams {
            fan_out: self.fan_out.unwrap_or(d.fan_out),
            horizontal: self.horizontal.unwrap_or(d.horizontal),
            hidden_cost,
            lag: self.lag.unwrap_or(d.lag),
            relocalization,
            prior_weight: self.prior_weight.unwrap_or(d.prior_weight),
            normalize: self.normalize.unwrap_or(d.normalize),
            confidence: d.confidence,
        };
        // Every range is checked by the core.
        params.validate()?;
        Ok(params)
    }
}

/// The parameters a trip uses, defaults resolved.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct TripParamsUsed {
    /// `K`.
    pub fan_out: usize,
    /// `W`, or `null` when resolved from the first batch (see `hidden_cost` of a batch).
    pub hidden_cost: Option<f64>,
    /// Horizontal edges.
    pub horizontal: bool,
    /// Lag window in frames.
    pub lag: usize,
    /// `R`, or `null` when relocalization is off.
    pub relocalization_cost: Option<f64>,
    /// Prior weight in frames.
    pub prior_weight: f64,
    /// Online column normalisation.
    pub normalize: bool,
}

impl From<&TripParamsDocument> for TripParamsUsed {
    fn from(p: &TripParamsDocument) -> Self {
        TripParamsUsed {
            fan_out: p.fan_out,
            hidden_cost: p.hidden_cost,
            horizontal: p.horizontal,
            lag: p.lag,
            relocalization_cost: p.relocalization_cost,
            prior_weight: p.prior_weight,
            normalize: p.normalize,
        }
    }
}

/// One frame's estimate on the wire.
#[derive(Clone, Copy, Debug, Serialize, Deserialize, PartialEq)]
pub struct FrameEstimateDto {
    /// Frame index since the trip started.
    pub frame: usize,
    /// Estimated reference index, `null` when not on the map.
    #[serde(rename = "ref")]
    pub reference: Option<usize>,
    /// Local min-marginal ratio (0 when not on the map).
    pub confidence: f64,
}

impl From<&FrameEstimate> for FrameEstimateDto {
    fn from(e: &FrameEstimate) -> Self {
        FrameEstimateDto {
            frame: e.frame,
            reference: e.reference,
            confidence: e.confidence,
        }
    }
}

impl From<&FrameRecord> for FrameEstimateDto {
    fn from(e: &FrameRecord) -> Self {
        FrameEstimateDto {
            frame: e.frame as usize,
            reference: e.reference.map(|j| j as usize),
            confidence: e.confidence,
        }
    }
}

/// A trip as returned by open, read, close and list.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct TripResponse {
    /// Trip id.
    pub id: String,
    /// The map.
    pub map_id: String,
    /// Creation time, ms since the epoch.
    pub created_at_ms: u64,
    /// Close time, `null` while open.
    pub closed_at_ms: Option<u64>,
    /// Frames consumed.
    pub frame_count: u64,
    /// Map images the trip localizes against (the map's count when it was opened).
    pub reference_count: u32,
    /// Status after the last batch, `null` before the first.
    pub status: Option<String>,
    /// Parameters.
    pub params: TripParamsUsed,
    /// Every frame's latest estimate (`GET /v1/trips/{id}` only).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub estimates: Option<Vec<FrameEstimateDto>>,
}

/// A page of `GET /v1/maps/{id}/trips`.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct TripListResponse {
    /// Trips, newest first.
    pub items: Vec<TripResponse>,
    /// Cursor for the next page.
    pub next: Option<String>,
}

/// Seconds per stage of a batch.
#[derive(Clone, Copy, Debug, Serialize, Deserialize, PartialEq)]
pub struct BatchTimings {
    /// Loading state and references.
    pub load: f64,
    /// Decoding and describing the images.
    pub features: f64,
    /// Similarities and the online solve.
    pub solve: f64,
    /// The atomic store write.
    pub store: f64,
}

/// The answer to a batch of frames.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct FramesResponse {
    /// Trip id.
    pub trip_id: String,
    /// Frames consumed, this batch included.
    pub frame_count: u64,
    /// One estimate per new frame.
    pub estimates: Vec<FrameEstimateDto>,
    /// `localized`, `lost` or `relocalized`.
    pub status: String,
    /// The current best hypothesis over the lag window (older frames first).
    pub window: Vec<FrameEstimateDto>,
    /// The hidden cost `W` in use.
    pub hidden_cost: f64,
    /// Seconds per stage.
    pub timings: BatchTimings,
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
    parse_id(s).ok_or_else(|| ApiError::TripNotFound(s.to_string()))
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
        params: TripParamsUsed::from(&r.params),
        estimates: None,
    }
}

async fn open(
    State(state): State<AppState>,
    Path(id): Path<String>,
    headers: HeaderMap,
    body: Result<Bytes, BytesRejection>,
) -> Result<(StatusCode, Json<TripResponse>), ApiError> {
    let map = map_id(&id)?;
    let body =
        body.map_err(|r| super::extract::bytes_rejection(r, state.settings.max_body_bytes))?;
    let dto = if body.iter().all(u8::is_ascii_whitespace) {
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
        super::extract::parse_json(&body, None)?
    };
    let params = dto.into_params()?;
    let record = state.app.open_trip(map, params).await?;
    Ok((StatusCode::CREATED, Json(response(&record))))
}

async fn frames(
    State(state): State<AppState>,
    Path(id): Path<String>,
    headers: HeaderMap,
    multipart: Result<Multipart, MultipartRejection>,
) -> Result<(HeaderMap, Json<FramesResponse>), ApiError> {
    let trip = trip_id(&id)?;
    let s = &state.settings;
    let batch = upload::read(
        multipart.map_err(upload::rejection)?,
        "params",
        s.max_batch_images,
        s.max_body_bytes,
    )
    .await?;
    if batch.json.is_some() {
        return Err(ApiError::BadRequest(
            "frames take no `params` part: a trip's parameters are fixed when it is opened".into(),
        ));
    }
    let key = super::idempotency::from_request(&headers, &batch)?;
    let outcome = state.app.post_frames_once(trip, batch.images, key).await?;
    let t = &outcome.timings;
    if !outcome.replayed {
        let m = &state.metrics;
        m.observe_stage("features", t.features);
        m.observe_stage("solve", t.solve);
        m.observe_stage("store", t.store);
    }
    let update = &outcome.update;
    let headers = super::idempotency::headers(outcome.replayed);
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

/// Query of `GET /v1/trips/{id}`.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct ReadQuery {
    /// Only the estimates of frames `since..` (a live view's poll); all when absent.
    since: Option<u32>,
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
    r.estimates = Some(estimates.iter().map(FrameEstimateDto::from).collect());
    Ok(Json(r))
}

async fn close(
    State(state): State<AppState>,
    Path(id): Path<String>,
) -> Result<Json<TripResponse>, ApiError> {
    let record = state.app.close_trip(trip_id(&id)?).await?;
    Ok(Json(response(&record)))
}

/// Query of `GET /v1/maps/{id}/trips`.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct ListQuery {
    limit: Option<usize>,
    before: Option<String>,
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
