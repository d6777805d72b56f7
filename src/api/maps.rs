//! `/v1/maps`: create, list, get, delete, and append reference images (multipart) or
//! precomputed descriptors (JSON or raw `f32`).
//!
//! An append is all-or-nothing: every part is decoded and extracted first, then the batch is
//! written in one atomic, flushed store write; any error before that writes nothing.

use std::sync::Arc;

use axum::body::Bytes;
use axum::extract::multipart::{Multipart, MultipartRejection};
use axum::extract::rejection::BytesRejection;
use axum::extract::{Path, Query, State};
use axum::http::{header, HeaderMap, StatusCode};
use axum::routing::{get, post};
use axum::{Json, Router};
use serde::Deserialize;

use super::dto::{
    format_id, parse_id, AppendDescriptorsRequest, AppendResponse, CreateMapRequest, DescriptorDto,
    ImageMetaDto, MapListResponse, MapResponse, MAX_DESCRIPTOR_DIM, MAX_NAME_BYTES,
};
use super::error::ApiError;
use super::extract::ApiJson;
use super::state::{blocking, AppState};
use super::upload;
use crate::features::hog::{HogOptions, HogSpec};
use crate::store::{DescriptorSettings, ImageMeta, MapRecord, NewMap};
use crate::Matrix;

/// The routes of this resource.
pub fn router() -> Router<AppState> {
    Router::new()
        .route("/v1/maps", post(create).get(list))
        .route("/v1/maps/{id}", get(read).delete(remove))
        .route("/v1/maps/{id}/images", post(append_images))
        .route("/v1/maps/{id}/descriptors", post(append_descriptors))
}

/// Parses a map id from a path or query; ids that cannot exist are 404.
pub fn map_id(s: &str) -> Result<u64, ApiError> {
    parse_id(s).ok_or_else(|| ApiError::MapNotFound(s.to_string()))
}

/// The HOG extractor of a map with HOG settings.
pub fn hog_spec(d: DescriptorSettings) -> Result<Option<HogSpec>, ApiError> {
    match d {
        DescriptorSettings::Hog { cell_size, resize } => {
            Ok(Some(HogSpec::new(HogOptions { cell_size, resize })?))
        }
        DescriptorSettings::Precomputed { .. } => Ok(None),
    }
}

fn validate(req: CreateMapRequest) -> Result<NewMap, ApiError> {
    let name = req.name.trim().to_string();
    if name.is_empty() || name.len() > MAX_NAME_BYTES {
        return Err(ApiError::param(
            "name",
            format!("must be 1 to {MAX_NAME_BYTES} bytes, got {}", name.len()),
        ));
    }
    let descriptor = match req.descriptor {
        DescriptorDto::Hog { cell_size, resize } => {
            if cell_size == 0 {
                return Err(ApiError::param(
                    "descriptor.cell_size",
                    "must be at least 1 pixel",
                ));
            }
            if let Some([w, h]) = resize {
                if w == 0 || h == 0 {
                    return Err(ApiError::param(
                        "descriptor.resize",
                        format!("must be positive, got [{w}, {h}]"),
                    ));
                }
            }
            let settings = DescriptorSettings::Hog {
                cell_size,
                resize: resize.map(|[w, h]| (w, h)),
            };
            hog_spec(settings)?;
            settings
        }
        DescriptorDto::Precomputed { dim } => {
            if dim == 0 || dim > MAX_DESCRIPTOR_DIM {
                return Err(ApiError::param(
                    "descriptor.dim",
                    format!("must be between 1 and {MAX_DESCRIPTOR_DIM}, got {dim}"),
                ));
            }
            DescriptorSettings::Precomputed { dim }
        }
        DescriptorDto::Cnn { .. } => return Err(ApiError::param(
            "descriptor.kind",
            "`cnn` descriptors are not available in this server build; use `hog` or `precomputed`",
        )),
    };
    Ok(NewMap { name, descriptor })
}

async fn create(
    State(state): State<AppState>,
    ApiJson(req): ApiJson<CreateMapRequest>,
) -> Result<(StatusCode, Json<MapResponse>), ApiError> {
    let new = validate(req)?;
    let store = Arc::clone(&state.store);
    let map = blocking(move || Ok(store.create_map(new)?)).await?;
    tracing::info!(map = %format_id(map.id), name = %map.name, "map created");
    Ok((StatusCode::CREATED, Json(map.into())))
}

async fn list(State(state): State<AppState>) -> Result<Json<MapListResponse>, ApiError> {
    let store = Arc::clone(&state.store);
    let maps = blocking(move || Ok(store.list_maps()?)).await?;
    Ok(Json(MapListResponse {
        maps: maps.into_iter().map(MapResponse::from).collect(),
    }))
}

async fn get_map(state: &AppState, id: u64) -> Result<MapRecord, ApiError> {
    let store = Arc::clone(&state.store);
    blocking(move || Ok(store.get_map(id)?)).await
}

async fn read(
    State(state): State<AppState>,
    Path(id): Path<String>,
) -> Result<Json<MapResponse>, ApiError> {
    Ok(Json(get_map(&state, map_id(&id)?).await?.into()))
}

async fn remove(
    State(state): State<AppState>,
    Path(id): Path<String>,
) -> Result<StatusCode, ApiError> {
    let id = map_id(&id)?;
    let store = Arc::clone(&state.store);
    blocking(move || Ok(store.delete_map(id)?)).await?;
    tracing::info!(map = %format_id(id), "map deleted");
    Ok(StatusCode::NO_CONTENT)
}

fn metadata(json: Option<&[u8]>, count: usize) -> Result<Vec<ImageMeta>, ApiError> {
    let Some(json) = json else {
        return Ok(vec![ImageMeta::default(); count]);
    };
    let entries: Vec<ImageMetaDto> = super::extract::parse_json(json, Some("metadata"))?;
    if entries.len() != count {
        return Err(ApiError::param(
            "metadata",
            format!(
                "has {} entries for {count} images; send one per image",
                entries.len()
            ),
        ));
    }
    entries
        .into_iter()
        .enumerate()
        .map(|(k, m)| m.validate(k))
        .collect()
}

async fn store_batch(
    state: &AppState,
    id: u64,
    descriptors: Matrix,
    metas: Vec<ImageMeta>,
) -> Result<AppendResponse, ApiError> {
    let store = Arc::clone(&state.store);
    let started = std::time::Instant::now();
    let range = blocking(move || Ok(store.append_images(id, &descriptors, &metas)?)).await?;
    state
        .metrics
        .observe_stage("store", started.elapsed().as_secs_f64());
    state.metrics.add_images_ingested(range.len() as u64);
    tracing::info!(map = %format_id(id), first = range.start, count = range.len(), "batch stored");
    Ok(AppendResponse {
        indices: range.clone().collect(),
        image_count: range.end,
    })
}

async fn append_images(
    State(state): State<AppState>,
    Path(id): Path<String>,
    multipart: Result<Multipart, MultipartRejection>,
) -> Result<Json<AppendResponse>, ApiError> {
    let id = map_id(&id)?;
    let map = get_map(&state, id).await?;
    let Some(spec) = hog_spec(map.descriptor)? else {
        return Err(ApiError::BadRequest(format!(
            "map `{}` stores precomputed descriptors; post them to /v1/maps/{}/descriptors",
            format_id(id),
            format_id(id)
        )));
    };
    let s = &state.settings;
    let batch = upload::read(
        multipart.map_err(upload::rejection)?,
        "metadata",
        s.max_batch_images,
        s.max_body_bytes,
    )
    .await?;
    let metas = metadata(batch.json.as_deref(), batch.images.len())?;
    let (max_pixels, dim) = (s.max_image_pixels, map.dim);
    let started = std::time::Instant::now();
    let descriptors = state
        .pool
        .run(move || upload::extract(&spec, &batch.images, max_pixels, dim))
        .await?;
    state
        .metrics
        .observe_stage("features", started.elapsed().as_secs_f64());
    Ok(Json(store_batch(&state, id, descriptors, metas).await?))
}

/// Query of the raw-float form of `/descriptors`.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawQuery {
    dim: Option<u32>,
}

async fn append_descriptors(
    State(state): State<AppState>,
    Path(id): Path<String>,
    query: Result<Query<RawQuery>, axum::extract::rejection::QueryRejection>,
    headers: HeaderMap,
    body: Result<Bytes, BytesRejection>,
) -> Result<Json<AppendResponse>, ApiError> {
    let id = map_id(&id)?;
    let body =
        body.map_err(|r| super::extract::bytes_rejection(r, state.settings.max_body_bytes))?;
    let map = get_map(&state, id).await?;
    let max = state.settings.max_batch_images;
    let content_type = headers
        .get(header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .unwrap_or("");
    let (descriptors, metas) = if content_type.starts_with("application/json") {
        let req: AppendDescriptorsRequest = super::extract::parse_json(&body, None)?;
        let m = upload::descriptor_matrix(&req.descriptors, map.dim, max)?;
        let metas = match req.metadata {
            None => vec![ImageMeta::default(); m.rows()],
            Some(entries) if entries.len() == m.rows() => entries
                .into_iter()
                .enumerate()
                .map(|(k, e)| e.validate(k))
                .collect::<Result<_, _>>()?,
            Some(entries) => {
                return Err(ApiError::param(
                    "metadata",
                    format!("has {} entries for {} descriptors", entries.len(), m.rows()),
                ))
            }
        };
        (m, metas)
    } else if content_type.starts_with("application/octet-stream") {
        let Query(q) = query.map_err(|e| ApiError::param("query", e.body_text()))?;
        let dim = match (q.dim, map.dim) {
            (Some(d), _) => d,
            (None, Some(d)) => d,
            (None, None) => {
                return Err(ApiError::param(
                    "dim",
                    "required until the map has descriptors",
                ))
            }
        };
        let m = upload::raw_descriptor_matrix(&body, dim, max)?;
        let n = m.rows();
        (m, vec![ImageMeta::default(); n])
    } else {
        return Err(ApiError::UnsupportedMediaType(format!(
            "descriptors must be sent as application/json or application/octet-stream, got `{content_type}`"
        )));
    };
    Ok(Json(store_batch(&state, id, descriptors, metas).await?))
}
