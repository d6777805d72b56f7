//! Reads that show a map and a localization to people (the dashboard uses them; any reader
//! may): the images' metadata page by page (`GET /v1/maps/{id}/images`), an image's JPEG
//! thumbnail (`GET /v1/maps/{id}/images/{index}/thumbnail`) and a localization's
//! similarity-matrix picture (`GET /v1/localizations/{id}/picture`).
//!
//! Thumbnails and pictures never change once stored (images are append-only, a result is
//! written once, ids are never reused), so they are sent cacheable for a day.

use axum::extract::{Path, Query, State};
use axum::http::{header, HeaderValue};
use axum::response::{IntoResponse, Response};
use axum::Json;
pub mod dto;

use self::dto::{ImageInfo, ImagePage, ImagesQuery};
use crate::api::error::{ApiError, IdKind};
use crate::api::extract::map_id;
use crate::api::state::AppState;
use crate::api::wire::{format_id, parse_id};

/// Default and largest page of `GET /v1/maps/{id}/images`.
const DEFAULT_IMAGES: u32 = 100;
/// Largest page of `GET /v1/maps/{id}/images` (a 30,000-image map is 30 pages).
pub const MAX_IMAGES: u32 = 1000;

/// `GET /v1/maps/{id}/images`.
pub async fn list_images(
    State(state): State<AppState>,
    Path(id): Path<String>,
    query: Result<Query<ImagesQuery>, axum::extract::rejection::QueryRejection>,
) -> Result<Json<ImagePage>, ApiError> {
    let map = map_id(&id)?;
    let Query(q) = query.map_err(|e| ApiError::param("query", e.body_text()))?;
    let limit = q.limit.unwrap_or(DEFAULT_IMAGES);
    if limit == 0 || limit > MAX_IMAGES {
        return Err(ApiError::param(
            "limit",
            format!("must be between 1 and {MAX_IMAGES}, got {limit}"),
        ));
    }
    let from = q.from.unwrap_or(0);
    let (record, metas) = state.app.image_metadata(map, from, limit).await?;
    let items: Vec<ImageInfo> = metas
        .into_iter()
        .zip(from..)
        .map(|(m, index)| ImageInfo {
            index,
            timestamp: m.timestamp,
            latitude: m.latitude,
            longitude: m.longitude,
            label: m.label,
        })
        .collect();
    let end = from.saturating_add(items.len() as u32);
    Ok(Json(ImagePage {
        next: (end < record.image_count && !items.is_empty()).then_some(end),
        image_count: record.image_count,
        items,
    }))
}

/// Bytes that never change, with their type.
fn immutable(bytes: Vec<u8>, content_type: &'static str) -> Response {
    let mut r = bytes.into_response();
    let h = r.headers_mut();
    h.insert(header::CONTENT_TYPE, HeaderValue::from_static(content_type));
    h.insert(
        header::CACHE_CONTROL,
        HeaderValue::from_static("private, max-age=86400, immutable"),
    );
    h.insert(
        header::X_CONTENT_TYPE_OPTIONS,
        HeaderValue::from_static("nosniff"),
    );
    r
}

/// `GET /v1/maps/{id}/images/{index}/thumbnail`.
pub async fn thumbnail(
    State(state): State<AppState>,
    Path((id, index)): Path<(String, String)>,
) -> Result<Response, ApiError> {
    let map = map_id(&id)?;
    let Ok(i) = index.parse::<u32>() else {
        return Err(ApiError::param(
            "index",
            format!("must be an image index (0, 1, 2, ...), got `{index}`"),
        ));
    };
    match state.app.thumbnail(map, i).await? {
        Some(jpeg) => Ok(immutable(jpeg, "image/jpeg")),
        None => {
            let count = state.app.get_map(map).await?.image_count;
            Err(ApiError::ThumbnailNotFound(if i >= count {
                format!(
                    "map `{}` has {count} images; there is no image {i}",
                    format_id(map)
                )
            } else {
                format!(
                    "image {i} of map `{}` has no thumbnail (stored before thumbnails existed, \
                     or not uploaded as an image)",
                    format_id(map)
                )
            }))
        }
    }
}

/// `GET /v1/localizations/{id}/picture`.
pub async fn picture(
    State(state): State<AppState>,
    Path(id): Path<String>,
) -> Result<Response, ApiError> {
    let lid =
        parse_id(&id).ok_or_else(|| ApiError::no_such_id(IdKind::Localization, id.clone()))?;
    match state.app.localization_picture(lid).await? {
        Some(png) => Ok(immutable(png, "image/png")),
        None => Err(ApiError::PictureNotFound(format!(
            "localization `{id}` has no similarity picture (made before pictures existed, or \
             by a co-occurrence method)"
        ))),
    }
}
