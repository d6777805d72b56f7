//! `POST /v1/maps/{id}/localize` and the stored results under `/v1/localizations`.
//!
//! A localization takes a query sequence (multipart `image` parts, or JSON descriptors) and
//! its parameters; the use case ([`seasonloc_app::App::localize`]) runs it against the map and
//! stores the result, which is returned. Admission is bounded: when `localize_queue` requests
//! are already running or waiting, the answer is 503 `queue_full` with `Retry-After`. A request
//! takes its place in the queue only once its map is known to exist and its body has been read
//! and parsed, so a client that trickles its body (or names no map) holds no place.

use axum::body::Body;
use axum::extract::multipart::Multipart;
use axum::extract::{FromRequest, Path, Query, Request, State};
use axum::http::{header, HeaderValue};
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};
use axum::Router;
pub mod dto;

use self::dto::{
    ListQuery, LocalizationListResponse, LocalizationResponse, LocalizeDescriptorsRequest,
    LocalizeParams,
};
use crate::api::admission::Refusal;
use crate::api::error::{ApiError, IdKind};
use crate::api::extract::{bytes_rejection, map_id, parse_json_object};
use crate::api::state::AppState;
use crate::api::views;
use crate::api::wire::{format_id, parse_id, DEFAULT_PAGE, MAX_PAGE};
use crate::api::{idempotency, upload};
use seasonloc_app::model::LocalizationRecord;
use seasonloc_app::store::PageRequest;
use seasonloc_app::{Idempotency, LocalizeInput, Queries};

/// The routes of this resource.
pub fn router() -> Router<AppState> {
    Router::new()
        .route("/v1/maps/{id}/localize", post(run))
        .route("/v1/localizations", get(list))
        .route("/v1/localizations/{id}", get(read))
        .route("/v1/localizations/{id}/picture", get(views::picture))
}

/// The request's input and its idempotency key (fingerprinted over the JSON body, or over the
/// multipart parts, behind the route's tag: a map's appends share its key space).
async fn parse(
    state: &AppState,
    req: Request,
) -> Result<(LocalizeInput, Option<Idempotency>), ApiError> {
    let headers = req.headers().clone();
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
            .map_err(|r| bytes_rejection(r, s.max_body_bytes))?;
        let body: LocalizeDescriptorsRequest = parse_json_object(&bytes, None)?;
        let method = body.params.method.map(Into::into);
        let options = body.params.into_options()?;
        let m = upload::descriptor_matrix(&body.descriptors, None, s.max_batch_images)?;
        let key = idempotency::from_parts(&headers, "localize", &[b"json", &bytes])?;
        let input = LocalizeInput {
            queries: Queries::Descriptors(m),
            options,
            method,
        };
        Ok((input, key))
    } else {
        let multipart = Multipart::from_request(req, state)
            .await
            .map_err(|r| upload::rejection(r, &headers))?;
        let batch = upload::read(
            multipart,
            Some("params"),
            s.max_batch_images,
            s.max_body_bytes,
        )
        .await?;
        let params = match &batch.json {
            Some(json) => LocalizeParams::from_json(json)?,
            None => LocalizeParams::default(),
        };
        let method = params.method.map(Into::into);
        let key = idempotency::from_tagged_request(&headers, "localize", &batch)?;
        let input = LocalizeInput {
            queries: Queries::Images(batch.images),
            options: params.into_options()?,
            method,
        };
        Ok((input, key))
    }
}

async fn run(
    State(state): State<AppState>,
    Path(id): Path<String>,
    req: Request,
) -> Result<Response, ApiError> {
    let map = map_id(&id)?;
    // An unknown map fails before the body is read.
    state.app.get_map(map).await?;
    let (input, key) = parse(&state, req).await?;
    // A retry of an answered request is answered from the store, without a CPU turn.
    if let Some(k) = &key {
        if let Some(done) = state.app.replayed_localization(map, k).await? {
            return json_document(&done, true);
        }
    }
    // A place in the queue once the request is read (a slow upload holds none), then the CPU
    // turn in arrival order.
    let reservation = state.admission.reserve().map_err(|r| refused(&state, r))?;
    let waited = std::time::Instant::now();
    let turn = reservation.turn().await.map_err(|r| refused(&state, r))?;
    state
        .metrics
        .observe_queue_wait(waited.elapsed().as_secs_f64());
    // The turn ends with the computation: storing the result (a flushed write) and answering
    // wait on the disk and the network, not on a CPU.
    let (record, replayed) = state
        .app
        .localize(map, input, key, move || turn.finish())
        .await?;
    if replayed {
        return json_document(&record, true);
    }
    let r = &record.result;
    let m = &state.metrics;
    m.observe_stage("load_references", r.timings.load_references);
    m.observe_stage("features", r.timings.features);
    m.observe_stage("similarity", r.timings.similarity);
    m.observe_stage("solve", r.timings.solve);
    m.add_queries_localized(r.query_count as u64);
    json_document(&record, false)
}

/// The answer to a request the localize queue did not admit.
fn refused(state: &AppState, refusal: Refusal) -> ApiError {
    state.metrics.add_queue_rejection();
    let max_wait = state.settings.localize_max_wait.as_secs();
    let message = match refusal {
        Refusal::Full { .. } => format!(
            "the localize queue is full ({} requests); retry later",
            state.settings.localize_queue
        ),
        Refusal::Busy { retry_after } => format!(
            "the localize queue would make this request wait about {retry_after} s, longer \
             than the limit of {max_wait} s; retry later"
        ),
        Refusal::Waited { .. } => format!(
            "this request waited {max_wait} s for a CPU without its turn coming; retry later"
        ),
    };
    ApiError::QueueFull {
        message,
        retry_after: refusal.retry_after(),
    }
}

/// The wire form of a stored result: the stored document's fields, byte for byte the JSON the
/// store keeps (a test checks it on the golden store).
/// `replayed` adds `Idempotent-Replayed: true`.
fn json_document(record: &LocalizationRecord, replayed: bool) -> Result<Response, ApiError> {
    let bytes = serde_json::to_vec(&LocalizationResponse::from(record))
        .map_err(|e| ApiError::internal(format!("serializing a result: {e}")))?;
    let mut r = Body::from(bytes).into_response();
    r.headers_mut().insert(
        header::CONTENT_TYPE,
        HeaderValue::from_static("application/json"),
    );
    r.headers_mut().extend(idempotency::headers(replayed));
    Ok(r)
}

async fn read(State(state): State<AppState>, Path(id): Path<String>) -> Result<Response, ApiError> {
    let lid = parse_id(&id).ok_or_else(|| ApiError::no_such_id(IdKind::Localization, id))?;
    json_document(&state.app.get_localization(lid).await?, false)
}

async fn list(
    State(state): State<AppState>,
    query: Result<Query<ListQuery>, axum::extract::rejection::QueryRejection>,
) -> Result<axum::Json<LocalizationListResponse>, ApiError> {
    let Query(q) = query.map_err(|e| ApiError::param("query", e.body_text()))?;
    let map = match q.map.as_deref() {
        Some("") => {
            return Err(ApiError::param(
                "map",
                "is empty: give a map id, or leave `map` out to list every map's localizations",
            ))
        }
        other => other.map(map_id).transpose()?,
    };
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
    let page = state
        .app
        .list_localizations(map, PageRequest { before, limit })
        .await?;
    Ok(axum::Json(LocalizationListResponse {
        items: page.items.iter().map(LocalizationResponse::from).collect(),
        next: page.next.map(format_id),
    }))
}
