//! `POST /v1/maps/{id}/localize` and the stored results under `/v1/localizations`.
//!
//! A localization takes a query sequence (multipart `image` parts, or JSON descriptors), runs
//! [`crate::localize::localize`] against the map's reference descriptors on the CPU pool, stores
//! the result with the parameters it used, and returns it. Admission is bounded: when
//! `localize_queue` requests are already running or waiting, the answer is 503 `queue_full`
//! with `Retry-After`.

use std::sync::Arc;
use std::time::Instant;

use axum::body::Body;
use axum::extract::multipart::Multipart;
use axum::extract::{FromRequest, Path, Query, Request, State};
use axum::http::{header, HeaderValue};
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};
use axum::Router;
use serde::Deserialize;

use super::descriptors::query_descriptors;
use super::dto::{
    format_id, parse_id, HypothesisDto, LocalizationListResponse, LocalizationResponse,
    LocalizeDescriptorsRequest, LocalizeParams, ParamsUsed, PredictionDto, TimingsDto,
};
use super::error::ApiError;
use super::maps::map_id;
use super::state::{blocking, AppState};
use super::upload::{self, ImagePart};
use crate::localize::{localize, LocalizeOptions};
use crate::Matrix;

/// The routes of this resource.
pub fn router() -> Router<AppState> {
    Router::new()
        .route("/v1/maps/{id}/localize", post(run))
        .route("/v1/localizations", get(list))
        .route("/v1/localizations/{id}", get(read))
}

/// Default and largest page size of `GET /v1/localizations`.
pub const DEFAULT_PAGE: usize = 20;
/// Largest page size.
pub const MAX_PAGE: usize = 100;

enum Queries {
    Images(Vec<ImagePart>),
    Descriptors(Matrix),
}

async fn parse(state: &AppState, req: Request) -> Result<(Queries, LocalizeOptions), ApiError> {
    let content_type = req
        .headers()
        .get(header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .unwrap_or("")
        .to_string();
    let s = &state.settings;
    if content_type.starts_with("application/json") {
        let bytes = axum::body::Bytes::from_request(req, state)
            .await
            .map_err(|r| super::extract::bytes_rejection(r, s.max_body_bytes))?;
        let body: LocalizeDescriptorsRequest = super::extract::parse_json(&bytes, None)?;
        let options = body.params.into_options()?;
        let m = upload::descriptor_matrix(&body.descriptors, None, s.max_batch_images)?;
        Ok((Queries::Descriptors(m), options))
    } else {
        let multipart = Multipart::from_request(req, state)
            .await
            .map_err(upload::rejection)?;
        let batch = upload::read(multipart, "params", s.max_batch_images, s.max_body_bytes).await?;
        let params = match &batch.json {
            Some(json) => LocalizeParams::from_json(json)?,
            None => LocalizeParams::default(),
        };
        Ok((Queries::Images(batch.images), params.into_options()?))
    }
}

async fn run(
    State(state): State<AppState>,
    Path(id): Path<String>,
    req: Request,
) -> Result<Response, ApiError> {
    let map = map_id(&id)?;
    let (queries, options) = parse(&state, req).await?;
    let Ok(_permit) = Arc::clone(&state.localize_slots).try_acquire_owned() else {
        state.metrics.add_queue_rejection();
        return Err(ApiError::QueueFull);
    };
    let store = Arc::clone(&state.store);
    let max_pixels = state.settings.max_image_pixels;
    let job_options = options.clone();
    let (result, timings, query_count, reference_count) = state
        .pool
        .run(move || {
            let started = Instant::now();
            let (record, references) = store.references(map)?;
            if record.image_count == 0 {
                return Err(ApiError::MapEmpty(format_id(map)));
            }
            let load = started.elapsed().as_secs_f64();
            let started = Instant::now();
            let queries = match queries {
                Queries::Descriptors(m) => {
                    if m.cols() != references.cols() {
                        return Err(ApiError::DescriptorLength(format!(
                            "query descriptors have length {}, map `{}` stores length {}",
                            m.cols(),
                            format_id(map),
                            references.cols()
                        )));
                    }
                    m
                }
                Queries::Images(parts) => {
                    let Some(m) = query_descriptors(&record, &parts, max_pixels)? else {
                        return Err(ApiError::BadRequest(format!(
                            "map `{}` stores precomputed descriptors; send query descriptors as JSON",
                            format_id(map)
                        )));
                    };
                    m
                }
            };
            let features = started.elapsed().as_secs_f64();
            let result = localize(&queries, &references, &job_options)?;
            let timings = TimingsDto::new(load, features, result.timings);
            Ok((result, timings, queries.rows(), references.rows()))
        })
        .await?;
    let m = &state.metrics;
    m.observe_stage("load_references", timings.load_references);
    m.observe_stage("features", timings.features);
    m.observe_stage("similarity", timings.similarity);
    m.observe_stage("solve", timings.solve);
    m.add_queries_localized(query_count as u64);

    let store = Arc::clone(&state.store);
    let (id, doc) = blocking(move || {
        let id = store.new_localization_id()?;
        let mut doc = LocalizationResponse {
            id: format_id(id),
            map_id: format_id(map),
            created_at_ms: crate::store::now_ms(),
            query_count,
            reference_count,
            params: ParamsUsed::new(&options, result.solution.hidden_cost),
            total_cost: result.solution.total_cost(),
            hypotheses: result
                .solution
                .hypotheses
                .iter()
                .map(HypothesisDto::from)
                .collect(),
            predictions: result.predictions.iter().map(PredictionDto::from).collect(),
            timings,
        };
        let bytes = serde_json::to_vec(&doc)
            .map_err(|e| ApiError::Internal(format!("serializing a result: {e}")))?;
        doc.created_at_ms = store.put_localization(id, map, bytes.clone())?;
        // The stored creation time is the store's; keep the answer identical to a read-back.
        let bytes = serde_json::to_vec(&doc)
            .map_err(|e| ApiError::Internal(format!("serializing a result: {e}")))?;
        Ok((id, bytes))
    })
    .await?;
    tracing::info!(map = %format_id(map), localization = %format_id(id), queries = query_count, "localized");
    Ok(json_bytes(doc))
}

fn json_bytes(bytes: Vec<u8>) -> Response {
    let mut r = Body::from(bytes).into_response();
    r.headers_mut().insert(
        header::CONTENT_TYPE,
        HeaderValue::from_static("application/json"),
    );
    r
}

async fn read(State(state): State<AppState>, Path(id): Path<String>) -> Result<Response, ApiError> {
    let lid = parse_id(&id).ok_or(ApiError::LocalizationNotFound(id))?;
    let store = Arc::clone(&state.store);
    let record = blocking(move || Ok(store.get_localization(lid)?)).await?;
    Ok(json_bytes(record.document))
}

/// Query of `GET /v1/localizations`.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct ListQuery {
    map: Option<String>,
    limit: Option<usize>,
    before: Option<String>,
}

async fn list(
    State(state): State<AppState>,
    query: Result<Query<ListQuery>, axum::extract::rejection::QueryRejection>,
) -> Result<axum::Json<LocalizationListResponse>, ApiError> {
    let Query(q) = query.map_err(|e| ApiError::param("query", e.body_text()))?;
    let map = q.map.as_deref().map(map_id).transpose()?;
    let limit = q.limit.unwrap_or(DEFAULT_PAGE);
    if limit == 0 || limit > MAX_PAGE {
        return Err(ApiError::param(
            "limit",
            format!("must be between 1 and {MAX_PAGE}, got {limit}"),
        ));
    }
    let before =
        match q.before.as_deref() {
            None => None,
            Some(b) => Some(parse_id(b).ok_or_else(|| {
                ApiError::param("before", format!("`{b}` is not a localization id"))
            })?),
        };
    let store = Arc::clone(&state.store);
    let page = blocking(move || Ok(store.list_localizations(map, before, limit)?)).await?;
    let items = page
        .items
        .iter()
        .map(|r| {
            serde_json::from_slice::<LocalizationResponse>(&r.document).map_err(|e| {
                ApiError::Internal(format!(
                    "stored localization {:016x} is unreadable: {e}",
                    r.id
                ))
            })
        })
        .collect::<Result<Vec<_>, _>>()?;
    Ok(axum::Json(LocalizationListResponse {
        items,
        next: page.next.map(format_id),
    }))
}
