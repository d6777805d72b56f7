//! Trips over HTTP (spec §6): a vehicle opens a trip on a map, posts its frames in small
//! multipart batches as it drives, and gets its current position back with every batch.
//!
//! * `POST /v1/maps/{id}/trips` opens a trip (optional JSON body of [`TripParamsDto`]) and pins
//!   the map's current image count: the trip localizes against those references, even if
//!   images are appended to the map later (its column prior and solver state have that width).
//! * `POST /v1/trips/{id}/frames` extends it: the images are described with the map's
//!   settings ([`super::descriptors`]), compared with the references and pushed through
//!   [`crate::trip::Trip`], whose state is restored from the store, advanced, and written back
//!   with the batch's estimates in one atomic, flushed store write before the answer.
//! * `GET /v1/trips/{id}`, `GET /v1/maps/{id}/trips` (newest first, paginated),
//!   `POST /v1/trips/{id}/close` (later frames are 409 `trip_closed`).
//!
//! Concurrency: the batches of one trip run one at a time, in arrival order (a per-trip
//! `tokio::sync::Mutex`); different trips only share the store's brief write lock and the CPU
//! pool. A batch that fails (bad image, closed trip) writes nothing, so the trip's state is
//! unchanged.

use std::collections::HashMap;
use std::sync::{Arc, Mutex};
use std::time::Instant;

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
use super::maps::{map_extractor, map_id};
use super::state::{blocking, AppState};
use super::upload;
use crate::store::{BatchWrite, FrameRecord, TripRecord};
use crate::trip::{column_prior, FrameEstimate, Trip, TripParams, TripStatus};
use crate::{similarity, Matrix};

/// The routes of this resource.
pub fn router() -> Router<AppState> {
    Router::new()
        .route("/v1/maps/{id}/trips", post(open).get(list))
        .route("/v1/trips/{id}", get(read))
        .route("/v1/trips/{id}/frames", post(frames))
        .route("/v1/trips/{id}/close", post(close))
}

/// A map's column prior with the image count it was computed for.
type CachedPrior = (u32, Arc<Vec<f32>>);

/// Per-trip locks and the column priors of maps with trips.
#[derive(Default)]
pub struct TripShared {
    locks: Mutex<HashMap<u64, Arc<tokio::sync::Mutex<()>>>>,
    /// Map id -> (image count the prior was computed for, prior).
    priors: Mutex<HashMap<u64, CachedPrior>>,
}

impl TripShared {
    /// The lock that orders `trip`'s batches.
    fn lock_of(&self, trip: u64) -> Arc<tokio::sync::Mutex<()>> {
        let mut locks = self.locks.lock().unwrap_or_else(|p| p.into_inner());
        if locks.len() > 1024 {
            // Forget locks nobody holds or waits for.
            locks.retain(|_, l| Arc::strong_count(l) > 1);
        }
        Arc::clone(locks.entry(trip).or_default())
    }

    fn prior(&self, map: u64, count: u32) -> Option<Arc<Vec<f32>>> {
        let priors = self.priors.lock().unwrap_or_else(|p| p.into_inner());
        priors
            .get(&map)
            .filter(|(n, _)| *n == count)
            .map(|(_, p)| Arc::clone(p))
    }

    fn keep_prior(&self, map: u64, count: u32, prior: Arc<Vec<f32>>) {
        let mut priors = self.priors.lock().unwrap_or_else(|p| p.into_inner());
        priors.insert(map, (count, prior));
    }
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
            _ => Some(
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
        // Every range is checked by the core, on a one-column stand-in map.
        Trip::new(vec![1.0], params)?;
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

impl From<&TripParams> for TripParamsUsed {
    fn from(p: &TripParams) -> Self {
        TripParamsUsed {
            fan_out: p.fan_out,
            hidden_cost: p.hidden_cost,
            horizontal: p.horizontal,
            lag: p.lag,
            relocalization_cost: p.relocalization,
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

fn status_code(s: TripStatus) -> u8 {
    match s {
        TripStatus::Localized => 1,
        TripStatus::Lost => 2,
        TripStatus::Relocalized => 3,
    }
}

fn status_name(code: u8) -> Option<String> {
    match code {
        1 => Some("localized".into()),
        2 => Some("lost".into()),
        3 => Some("relocalized".into()),
        _ => None,
    }
}

fn trip_id(s: &str) -> Result<u64, ApiError> {
    parse_id(s).ok_or_else(|| ApiError::TripNotFound(s.to_string()))
}

fn response(r: &TripRecord) -> Result<TripResponse, ApiError> {
    let params: TripParamsUsed = serde_json::from_slice(&r.params).map_err(|e| {
        ApiError::Internal(format!("trip {:016x} has unreadable parameters: {e}", r.id))
    })?;
    Ok(TripResponse {
        id: format_id(r.id),
        map_id: format_id(r.map_id),
        created_at_ms: r.created_ms,
        closed_at_ms: r.closed_ms,
        frame_count: r.frame_count,
        reference_count: r.reference_count,
        status: status_name(r.status),
        params,
        estimates: None,
    })
}

/// The first `count` references (all of them unless images were appended after the trip
/// opened).
fn pinned(references: Arc<Matrix>, count: u32) -> Result<Arc<Matrix>, ApiError> {
    let count = count as usize;
    if references.rows() == count {
        return Ok(references);
    }
    if references.rows() < count {
        return Err(ApiError::Internal(format!(
            "the map has {} images, fewer than the trip's {count}",
            references.rows()
        )));
    }
    let d = references.cols();
    Ok(Arc::new(Matrix::from_vec(
        count,
        d,
        references.as_slice()[..count * d].to_vec(),
    )?))
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
    let store = Arc::clone(&state.store);
    let shared = Arc::clone(&state.trips);
    let record = state
        .pool
        .run(move || {
            let record = store.get_map(map)?;
            if map_extractor(&record)?.is_none() {
                return Err(ApiError::MapKind(format!(
                    "map `{}` stores client-computed descriptors; trips need a map that can \
                     describe images (e.g. `hog`)",
                    format_id(map)
                )));
            }
            if record.image_count == 0 {
                return Err(ApiError::MapEmpty(format_id(map)));
            }
            let count = record.image_count;
            let prior = match shared.prior(map, count) {
                Some(p) => p,
                None => {
                    let (_, references) = store.references(map)?;
                    let pinned = pinned(references, count)?;
                    let prior = Arc::new(column_prior(&pinned)?);
                    shared.keep_prior(map, count, Arc::clone(&prior));
                    prior
                }
            };
            let trip = Trip::new(prior.as_ref().clone(), params)?;
            let doc = serde_json::to_vec(&TripParamsUsed::from(&params))
                .map_err(|e| ApiError::Internal(format!("serializing parameters: {e}")))?;
            Ok(store.create_trip(map, count, doc, trip.to_bytes())?)
        })
        .await?;
    tracing::info!(map = %format_id(map), trip = %format_id(record.id), "trip opened");
    Ok((StatusCode::CREATED, Json(response(&record)?)))
}

async fn frames(
    State(state): State<AppState>,
    Path(id): Path<String>,
    multipart: Result<Multipart, MultipartRejection>,
) -> Result<Json<FramesResponse>, ApiError> {
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
    let lock = state.trips.lock_of(trip);
    let _order = lock.lock().await;

    let started = Instant::now();
    let store = Arc::clone(&state.store);
    let (record, bytes, map) = blocking(move || {
        let (record, bytes) = store.trip_state(trip)?;
        if record.closed_ms.is_some() {
            return Err(ApiError::TripClosed(format_id(trip)));
        }
        let map = store.get_map(record.map_id)?;
        Ok((record, bytes, map))
    })
    .await?;
    let store = Arc::clone(&state.store);
    let max_pixels = s.max_image_pixels;
    let (update, new_state, hidden_cost, load, features, solve) = state
        .pool
        .run(move || {
            let (_, references) = store.references(map.id)?;
            let references = pinned(references, record.reference_count)?;
            let mut trip_state = Trip::from_bytes(&bytes)?;
            let load = started.elapsed().as_secs_f64();
            let t = Instant::now();
            let Some(extractor) = map_extractor(&map)? else {
                return Err(ApiError::MapKind(format!(
                    "map `{}` cannot describe images",
                    format_id(map.id)
                )));
            };
            let queries = upload::extract(extractor.as_ref(), &batch.images, max_pixels, map.dim)?;
            let features = t.elapsed().as_secs_f64();
            let t = Instant::now();
            let c = similarity::cosine_matrix(&queries, &references)?;
            let update = trip_state.push_batch(&c)?;
            let hidden_cost = trip_state
                .hidden_cost()
                .expect("the first batch resolves the hidden cost");
            let solve = t.elapsed().as_secs_f64();
            Ok((
                update,
                trip_state.to_bytes(),
                hidden_cost,
                load,
                features,
                solve,
            ))
        })
        .await?;
    let revised: Vec<FrameRecord> = update
        .window
        .iter()
        .chain(&update.estimates)
        .map(|e| FrameRecord {
            frame: e.frame as u32,
            reference: e.reference.map(|j| j as u32),
            confidence: e.confidence,
        })
        .collect();
    let frame_count = record.frame_count + update.estimates.len() as u64;
    let write = BatchWrite {
        expected_frames: record.frame_count,
        frame_count,
        status: status_code(update.status),
        state: new_state,
        estimates: revised,
    };
    let t = Instant::now();
    let store = Arc::clone(&state.store);
    blocking(move || Ok(store.put_trip_batch(trip, write)?)).await?;
    let store_secs = t.elapsed().as_secs_f64();
    let m = &state.metrics;
    m.observe_stage("features", features);
    m.observe_stage("solve", solve);
    m.observe_stage("store", store_secs);
    let status = status_name(status_code(update.status)).expect("every status has a name");
    tracing::debug!(trip = %format_id(trip), frames = frame_count, %status, "batch applied");
    Ok(Json(FramesResponse {
        trip_id: format_id(trip),
        frame_count,
        estimates: update
            .estimates
            .iter()
            .map(FrameEstimateDto::from)
            .collect(),
        status,
        window: update.window.iter().map(FrameEstimateDto::from).collect(),
        hidden_cost,
        timings: BatchTimings {
            load,
            features,
            solve,
            store: store_secs,
        },
    }))
}

async fn read(
    State(state): State<AppState>,
    Path(id): Path<String>,
) -> Result<Json<TripResponse>, ApiError> {
    let trip = trip_id(&id)?;
    let store = Arc::clone(&state.store);
    let (record, estimates) = blocking(move || {
        let record = store.get_trip(trip)?;
        let estimates = store.trip_estimates(trip)?;
        Ok((record, estimates))
    })
    .await?;
    let mut r = response(&record)?;
    r.estimates = Some(estimates.iter().map(FrameEstimateDto::from).collect());
    Ok(Json(r))
}

async fn close(
    State(state): State<AppState>,
    Path(id): Path<String>,
) -> Result<Json<TripResponse>, ApiError> {
    let trip = trip_id(&id)?;
    // Wait for a batch in flight, so the close lands after it.
    let lock = state.trips.lock_of(trip);
    let _order = lock.lock().await;
    let store = Arc::clone(&state.store);
    let record = blocking(move || Ok(store.close_trip(trip)?)).await?;
    tracing::info!(trip = %format_id(trip), "trip closed");
    Ok(Json(response(&record)?))
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
    let store = Arc::clone(&state.store);
    let page = blocking(move || Ok(store.list_trips(map, before, limit)?)).await?;
    Ok(Json(TripListResponse {
        items: page.items.iter().map(response).collect::<Result<_, _>>()?,
        next: page.next.map(format_id),
    }))
}
