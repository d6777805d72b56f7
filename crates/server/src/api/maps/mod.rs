//! `/v1/maps`: create, list, get, delete, and append reference images (multipart) or
//! precomputed descriptors (JSON or raw `f32`).
//!
//! Handlers decode and validate the wire input (errors name the request's fields), call the
//! use cases ([`seasonloc_app::App`]) and encode the answer. An append is all-or-nothing (see
//! `app::maps`).

use std::path::PathBuf;

use axum::body::Bytes;
use axum::extract::multipart::{Multipart, MultipartRejection};
use axum::extract::rejection::BytesRejection;
use axum::extract::{Path, Query, State};
use axum::http::{header, HeaderMap, StatusCode};
use axum::routing::{get, post};
use axum::{Json, Router};
pub mod dto;

use self::dto::{
    AppendDescriptorsRequest, AppendResponse, CnnResizeDto, CreateMapRequest, DescriptorDto,
    ImageMetaDto, MapListResponse, MapResponse, ModelIdentityDto, RawQuery, MAX_DESCRIPTOR_DIM,
    MAX_NAME_CHARS,
};
use crate::api::error::ApiError;
use crate::api::extract::{bytes_rejection, map_id, parse_json, parse_json_object, ApiJsonBody};
use crate::api::state::AppState;
use crate::api::{idempotency, upload, views};
use seasonloc_app::model::{DescriptorSettings, ImageMeta};
use seasonloc_app::{AppendOutcome, DescriptorSpec, NewMapSpec, Upload};
use seasonloc_core::cooc::CoocParams;
use seasonloc_core::features::cnn::{CnnOptions, CnnResize};
use seasonloc_core::features::hog::{HogOptions, HogSpec};

/// The routes of this resource.
pub fn router() -> Router<AppState> {
    Router::new()
        .route("/v1/maps", post(create).get(list))
        .route("/v1/maps/{id}", get(read).delete(remove))
        .route(
            "/v1/maps/{id}/images",
            post(append_images).get(views::list_images),
        )
        .route(
            "/v1/maps/{id}/images/{index}/thumbnail",
            get(views::thumbnail),
        )
        .route("/v1/maps/{id}/descriptors", post(append_descriptors))
}

/// Turns the CNN fields of a create request into validated options; the model is `model` or
/// the server's default.
fn cnn_options(
    descriptor: CnnRequest,
    default_model: Option<&std::path::Path>,
) -> Result<CnnOptions, ApiError> {
    if descriptor.identity.is_some() {
        return Err(ApiError::param(
            "descriptor.identity",
            "is recorded by the server at creation; do not send it",
        ));
    }
    let model = match (descriptor.model, default_model) {
        (Some(m), _) if m.trim().is_empty() => {
            return Err(ApiError::param("descriptor.model", "must not be empty"))
        }
        (Some(m), _) => PathBuf::from(m),
        (None, Some(d)) => d.to_path_buf(),
        (None, None) => {
            return Err(ApiError::inconsistent(
                "descriptor.model",
                "is required: this server has no default CNN model (--cnn-model / \
                 SEASONLOC_CNN_MODEL)",
            ))
        }
    };
    let mut o = CnnOptions::efficientnet_lite0(model);
    o.layer = descriptor.layer;
    if let Some([w, h]) = descriptor.input_size {
        o.input_size = (w, h);
    }
    let (w, h) = o.input_size;
    o.resize = match (descriptor.resize, descriptor.short_side) {
        (Some(CnnResizeDto::Stretch), Some(_)) => {
            return Err(ApiError::inconsistent(
                "descriptor.short_side",
                "applies to `resize: crop` only",
            ))
        }
        (Some(CnnResizeDto::Stretch), None) => CnnResize::Stretch,
        (_, side) => CnnResize::ShortSideCrop {
            // 256/224 of the larger side, in u64: an oversized input side must reach
            // `CnnOptions::validate` (a 400 naming it), not overflow here.
            short_side: side.unwrap_or_else(|| {
                u32::try_from((u64::from(w.max(h)) * 256).div_ceil(224)).unwrap_or(u32::MAX)
            }),
        },
    };
    if let Some(m) = descriptor.mean {
        o.mean = m;
    }
    if let Some(sc) = descriptor.scale {
        o.scale = sc;
    }
    Ok(o)
}

/// The fields of a `cnn` descriptor in a create request.
struct CnnRequest {
    model: Option<String>,
    layer: String,
    input_size: Option<[u32; 2]>,
    resize: Option<CnnResizeDto>,
    short_side: Option<u32>,
    mean: Option<[f32; 3]>,
    scale: Option<[f32; 3]>,
    identity: Option<ModelIdentityDto>,
}

/// Checks a create request for everything that needs no file (a CNN model is loaded and
/// checked by the use case).
fn validate(
    req: CreateMapRequest,
    default_model: Option<&std::path::Path>,
) -> Result<NewMapSpec, ApiError> {
    let name = req.name.trim().to_string();
    // PostgreSQL's `text` cannot hold U+0000: refused on every engine, so that both accept the
    // same names (and a NUL in a name is a client's bug, not a character anyone types).
    if name.contains('\0') {
        return Err(ApiError::param("name", "must not contain U+0000 (NUL)"));
    }
    let chars = name.chars().count();
    if chars == 0 || chars > MAX_NAME_CHARS {
        return Err(ApiError::param(
            "name",
            format!("must be 1 to {MAX_NAME_CHARS} characters (not all blank), got {chars}"),
        ));
    }
    let descriptor = match req.descriptor {
        DescriptorDto::Hog { cell_size, resize } => {
            if let Some([w, h]) = resize {
                if w == 0 || h == 0 {
                    return Err(ApiError::param(
                        "descriptor.resize",
                        format!("must be positive, got [{w}, {h}]"),
                    ));
                }
            }
            let resize = resize.map(|[w, h]| (w, h));
            HogSpec::new(HogOptions { cell_size, resize })?;
            DescriptorSettings::Hog { cell_size, resize }
        }
        DescriptorDto::Cooc {
            vocabulary_branching,
            vocabulary_depth,
            upsample,
            max_keypoints,
            grid,
            spatial_tolerance,
            merge_adjacent_drives,
            seed,
        } => {
            let mut p = CoocParams::default();
            p.vocabulary_branching = vocabulary_branching.unwrap_or(p.vocabulary_branching);
            p.vocabulary_depth = vocabulary_depth.unwrap_or(p.vocabulary_depth);
            p.keypoints.upsample = upsample.unwrap_or(p.keypoints.upsample);
            p.keypoints.max_keypoints = max_keypoints.unwrap_or(p.keypoints.max_keypoints);
            if let Some([c, r]) = grid {
                p.grid_cols = c;
                p.grid_rows = r;
            }
            p.spatial_tolerance = spatial_tolerance.unwrap_or(p.spatial_tolerance);
            p.merge_adjacent_drives = merge_adjacent_drives.unwrap_or(p.merge_adjacent_drives);
            p.seed = seed.unwrap_or(p.seed);
            p.validate().map_err(|e| match e {
                seasonloc_core::Error::InvalidParameter { name, reason } => {
                    ApiError::param(format!("descriptor.{name}"), reason)
                }
                seasonloc_core::Error::Inconsistent { name, reason } => {
                    ApiError::inconsistent(format!("descriptor.{name}"), reason)
                }
                other @ (seasonloc_core::Error::NonFinite { .. }
                | seasonloc_core::Error::Shape(_)
                | seasonloc_core::Error::Empty(_)
                | seasonloc_core::Error::Image { .. }
                | seasonloc_core::Error::Io { .. }
                | seasonloc_core::Error::Format { .. }) => other.into(),
            })?;
            DescriptorSettings::Cooc(Box::new(p))
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
        DescriptorDto::Cnn {
            model,
            layer,
            input_size,
            resize,
            short_side,
            mean,
            scale,
            identity,
        } => {
            let request = CnnRequest {
                model,
                layer,
                input_size,
                resize,
                short_side,
                mean,
                scale,
                identity,
            };
            let options = cnn_options(request, default_model)?;
            return Ok(NewMapSpec {
                name,
                descriptor: DescriptorSpec::Cnn(options),
            });
        }
    };
    Ok(NewMapSpec {
        name,
        descriptor: DescriptorSpec::Settings(descriptor),
    })
}

async fn create(
    State(state): State<AppState>,
    headers: HeaderMap,
    ApiJsonBody(req, body): ApiJsonBody<CreateMapRequest>,
) -> Result<(StatusCode, HeaderMap, Json<MapResponse>), ApiError> {
    let spec = validate(req, state.settings.default_cnn_model.as_deref())?;
    let key = idempotency::from_parts(&headers, "maps", &[&body])?;
    let (map, replayed) = state.app.create_map(spec, key).await?;
    Ok((
        StatusCode::CREATED,
        idempotency::headers(replayed),
        Json(map.into()),
    ))
}

async fn list(State(state): State<AppState>) -> Result<Json<MapListResponse>, ApiError> {
    let maps = state.app.list_maps().await?;
    Ok(Json(MapListResponse {
        maps: maps.into_iter().map(MapResponse::from).collect(),
    }))
}

async fn read(
    State(state): State<AppState>,
    Path(id): Path<String>,
) -> Result<Json<MapResponse>, ApiError> {
    Ok(Json(state.app.get_map(map_id(&id)?).await?.into()))
}

async fn remove(
    State(state): State<AppState>,
    Path(id): Path<String>,
) -> Result<StatusCode, ApiError> {
    state.app.delete_map(map_id(&id)?).await?;
    Ok(StatusCode::NO_CONTENT)
}

fn metadata(json: Option<&[u8]>, count: usize) -> Result<Vec<ImageMeta>, ApiError> {
    let Some(json) = json else {
        return Ok(vec![ImageMeta::default(); count]);
    };
    let entries: Vec<ImageMetaDto> = parse_json(json, Some("metadata"))?;
    if entries.len() != count {
        return Err(ApiError::inconsistent(
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

/// Records an append's stages and answers with its indices.
fn appended(state: &AppState, outcome: &AppendOutcome) -> AppendResponse {
    let m = &state.metrics;
    if let Some(s) = outcome.features_seconds {
        m.observe_stage("features", s);
    }
    if let Some(s) = outcome.store_seconds {
        m.observe_stage("store", s);
    }
    if !outcome.replayed {
        m.add_images_ingested(outcome.indices.len() as u64);
    }
    AppendResponse {
        indices: outcome.indices.clone().collect(),
        image_count: outcome.indices.end,
    }
}

async fn append_images(
    State(state): State<AppState>,
    Path(id): Path<String>,
    headers: HeaderMap,
    multipart: Result<Multipart, MultipartRejection>,
) -> Result<(HeaderMap, Json<AppendResponse>), ApiError> {
    let map = state.app.map_for(map_id(&id)?, Upload::Images).await?;
    let s = &state.settings;
    let batch = upload::read(
        multipart.map_err(|r| upload::rejection(r, &headers))?,
        Some("metadata"),
        s.max_batch_images,
        s.max_body_bytes,
    )
    .await?;
    let metas = metadata(batch.json.as_deref(), batch.images.len())?;
    let key = idempotency::from_request(&headers, &batch)?;
    let outcome = state
        .app
        .append_images(map, batch.images, metas, key)
        .await?;
    let headers = idempotency::headers(outcome.replayed);
    Ok((headers, Json(appended(&state, &outcome))))
}

async fn append_descriptors(
    State(state): State<AppState>,
    Path(id): Path<String>,
    query: Result<Query<RawQuery>, axum::extract::rejection::QueryRejection>,
    headers: HeaderMap,
    body: Result<Bytes, BytesRejection>,
) -> Result<(HeaderMap, Json<AppendResponse>), ApiError> {
    let id = map_id(&id)?;
    let body = body.map_err(|r| bytes_rejection(r, state.settings.max_body_bytes))?;
    let map = state.app.map_for(id, Upload::Descriptors).await?;
    let max = state.settings.max_batch_images;
    let content_type = headers
        .get(header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .unwrap_or("");
    // `?dim=` is checked whatever the body, so a bound the document states is never ignored.
    let Query(q) = query.map_err(|e| ApiError::param("query", e.body_text()))?;
    if let Some(d) = q.dim {
        if d == 0 || d > MAX_DESCRIPTOR_DIM {
            return Err(ApiError::param(
                "dim",
                format!("must be between 1 and {MAX_DESCRIPTOR_DIM}, got {d}"),
            ));
        }
    }
    let (descriptors, metas) = if content_type.starts_with("application/json") {
        let req: AppendDescriptorsRequest = parse_json_object(&body, None)?;
        let m = upload::descriptor_matrix(&req.descriptors, map.dim, max)?;
        let metas = match req.metadata {
            None => vec![ImageMeta::default(); m.rows()],
            Some(entries) if entries.len() == m.rows() => entries
                .into_iter()
                .enumerate()
                .map(|(k, e)| e.validate(k))
                .collect::<Result<_, _>>()?,
            Some(entries) => {
                return Err(ApiError::inconsistent(
                    "metadata",
                    format!("has {} entries for {} descriptors", entries.len(), m.rows()),
                ))
            }
        };
        (m, metas)
    } else if content_type.starts_with("application/octet-stream") {
        let dim = match (q.dim, map.dim) {
            (Some(d), _) => d,
            (None, Some(d)) => d,
            (None, None) => {
                return Err(ApiError::inconsistent(
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
    // The request is its media type, `?dim=` and body (a JSON retry is sent byte for byte).
    let kind: &[u8] = if content_type.starts_with("application/json") {
        b"json"
    } else {
        b"octet-stream"
    };
    let dim = q.dim.map(|d| d.to_string()).unwrap_or_default();
    let key = idempotency::from_parts(&headers, "descriptors", &[kind, dim.as_bytes(), &body])?;
    let outcome = state
        .app
        .append_descriptors(id, descriptors, metas, key)
        .await?;
    let headers = idempotency::headers(outcome.replayed);
    Ok((headers, Json(appended(&state, &outcome))))
}
