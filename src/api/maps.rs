//! `/v1/maps`: create, list, get, delete, and append reference images (multipart) or
//! precomputed descriptors (JSON or raw `f32`).
//!
//! An append is all-or-nothing: every part is decoded and extracted first, then the batch is
//! written in one atomic, flushed store write; any error before that writes nothing.

use std::path::PathBuf;
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
    format_id, parse_id, AppendDescriptorsRequest, AppendResponse, CnnResizeDto, CreateMapRequest,
    DescriptorDto, ImageMetaDto, MapListResponse, MapResponse, MAX_DESCRIPTOR_DIM, MAX_NAME_BYTES,
};
use super::error::ApiError;
use super::extract::ApiJson;
use super::state::{blocking, AppState};
use super::upload::{self, ImagePart};
use crate::cooc::CoocParams;
use crate::features::cnn::{CnnOptions, CnnResize, CnnSpec};
use crate::features::hog::{HogOptions, HogSpec};
use crate::features::Extractor;
use crate::store::{CnnSettings, DescriptorSettings, ImageMeta, MapRecord, NewMap};
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

/// The extractor of a map's images (references and queries): `None` for precomputed maps.
///
/// For a CNN map the model at the recorded path is loaded (from the shared cache when its
/// content is unchanged) and checked against the identity recorded at creation: a model file
/// that changed, no longer loads or is gone is 409 `model_mismatch`, never silently used.
/// This is the one place that turns a map's descriptor settings into an extractor; call it on
/// the CPU pool (it hashes the model file).
pub fn map_extractor(map: &MapRecord) -> Result<Option<Box<dyn Extractor>>, ApiError> {
    match &map.descriptor {
        DescriptorSettings::Hog { cell_size, resize } => {
            Ok(Some(Box::new(HogSpec::new(HogOptions {
                cell_size: *cell_size,
                resize: *resize,
            })?)))
        }
        DescriptorSettings::Precomputed { .. } => Ok(None),
        DescriptorSettings::Cnn(c) => {
            let path = c.options.model.display();
            let id = format_id(map.id);
            let spec = CnnSpec::new(c.options.clone()).map_err(|e| {
                ApiError::ModelMismatch(format!(
                    "map `{id}` was created with the model at {path} (sha256 {}), which no \
                     longer loads: {e}",
                    c.identity.sha256
                ))
            })?;
            if let Some(diff) = c.identity.mismatch(&spec.identity()) {
                return Err(ApiError::ModelMismatch(format!(
                    "map `{id}`: the model at {path} is not the one the map was created with \
                     ({diff}); restore that file or create a new map"
                )));
            }
            Ok(Some(Box::new(spec)))
        }
        DescriptorSettings::Cooc(_) => Err(ApiError::MapKind(format!(
            "map `{}` is a co-occurrence map: it has no global descriptors (localize it with \
             POST /v1/maps/{}/localize, add drives with /drives)",
            format_id(map.id),
            format_id(map.id)
        ))),
    }
}

/// The descriptors of uploaded images for `map` (one row per part, in order): the single
/// dispatch from a map's descriptor settings to extraction, used by appends and localize.
/// Precomputed maps are 400 (they take descriptors, not images). Blocking: run on the CPU pool.
pub fn extract_for_map(
    map: &MapRecord,
    parts: &[ImagePart],
    max_pixels: u64,
) -> Result<Matrix, ApiError> {
    let Some(extractor) = map_extractor(map)? else {
        return Err(ApiError::BadRequest(format!(
            "map `{}` stores precomputed descriptors; send descriptors, not images",
            format_id(map.id)
        )));
    };
    upload::extract(extractor.as_ref(), parts, max_pixels, map.dim)
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
            return Err(ApiError::param(
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
            return Err(ApiError::param(
                "descriptor.short_side",
                "applies to `resize: crop` only",
            ))
        }
        (Some(CnnResizeDto::Stretch), None) => CnnResize::Stretch,
        (_, side) => CnnResize::ShortSideCrop {
            short_side: side.unwrap_or_else(|| (w.max(h) * 256).div_ceil(224)),
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
    identity: Option<super::dto::ModelIdentityDto>,
}

/// A CNN settings error at creation as a 400 naming the request's field.
fn cnn_error(e: crate::Error) -> ApiError {
    let field = |name: &str| -> &'static str {
        match name {
            "cnn_layer" => "descriptor.layer",
            "cnn_input_size" => "descriptor.input_size",
            "cnn_short_side" => "descriptor.short_side",
            "cnn_mean" => "descriptor.mean",
            "cnn_scale" => "descriptor.scale",
            _ => "descriptor.model",
        }
    };
    match e {
        crate::Error::InvalidParameter { name, reason } => ApiError::param(field(name), reason),
        crate::Error::Io { path, source } => ApiError::param(
            "descriptor.model",
            format!("cannot read {}: {source}", path.display()),
        ),
        other => ApiError::param("descriptor.model", other.to_string()),
    }
}

/// Loads and checks a CNN model for a new map (blocking): every failure is a 400 naming the
/// descriptor field (missing file, not ONNX, unknown layer with the available ones, input size).
fn check_cnn(options: CnnOptions) -> Result<CnnSettings, ApiError> {
    let spec = CnnSpec::new(options.clone()).map_err(cnn_error)?;
    Ok(CnnSettings {
        identity: spec.identity(),
        options,
    })
}

/// A create request checked for everything that needs no file: either a finished map, or
/// CNN options still to be checked against the model (blocking, see [`check_cnn`]).
enum Validated {
    Ready(NewMap),
    Cnn { name: String, options: CnnOptions },
}

fn validate(
    req: CreateMapRequest,
    default_model: Option<&std::path::Path>,
) -> Result<Validated, ApiError> {
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
                crate::Error::InvalidParameter { name, reason } => {
                    ApiError::param(format!("descriptor.{name}"), reason)
                }
                other => other.into(),
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
            options.validate().map_err(cnn_error)?;
            return Ok(Validated::Cnn { name, options });
        }
    };
    Ok(Validated::Ready(NewMap { name, descriptor }))
}

async fn create(
    State(state): State<AppState>,
    ApiJson(req): ApiJson<CreateMapRequest>,
) -> Result<(StatusCode, Json<MapResponse>), ApiError> {
    let validated = validate(req, state.settings.default_cnn_model.as_deref())?;
    let new = match validated {
        Validated::Ready(new) => new,
        Validated::Cnn { name, options } => {
            let settings = state.pool.run(move || check_cnn(options)).await?;
            NewMap {
                name,
                descriptor: DescriptorSettings::Cnn(Box::new(settings)),
            }
        }
    };
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
    if let DescriptorSettings::Precomputed { .. } = map.descriptor {
        return Err(ApiError::BadRequest(format!(
            "map `{}` stores precomputed descriptors; post them to /v1/maps/{}/descriptors",
            format_id(id),
            format_id(id)
        )));
    }
    let s = &state.settings;
    let batch = upload::read(
        multipart.map_err(upload::rejection)?,
        "metadata",
        s.max_batch_images,
        s.max_body_bytes,
    )
    .await?;
    let metas = metadata(batch.json.as_deref(), batch.images.len())?;
    let max_pixels = s.max_image_pixels;
    if let DescriptorSettings::Cooc(_) = map.descriptor {
        let store = Arc::clone(&state.store);
        let started = std::time::Instant::now();
        let range = state
            .pool
            .run(move || {
                super::cooc::build_from_images(&store, &map, &batch.images, &metas, max_pixels)
            })
            .await?;
        state
            .metrics
            .observe_stage("features", started.elapsed().as_secs_f64());
        state.metrics.add_images_ingested(range.len() as u64);
        tracing::info!(map = %format_id(id), images = range.len(), "co-occurrence map built");
        return Ok(Json(AppendResponse {
            indices: range.clone().collect(),
            image_count: range.end,
        }));
    }
    let started = std::time::Instant::now();
    let descriptors = state
        .pool
        .run(move || extract_for_map(&map, &batch.images, max_pixels))
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
    if let DescriptorSettings::Cooc(_) = map.descriptor {
        return Err(ApiError::MapKind(format!(
            "co-occurrence map `{}` is built from images; post them to /v1/maps/{}/images",
            format_id(id),
            format_id(id)
        )));
    }
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
