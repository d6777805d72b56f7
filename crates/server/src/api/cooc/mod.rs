//! Co-occurrence (`cooc`) maps over HTTP: `POST /v1/maps/{id}/drives` (a further drive of the
//! route, each image naming its location) and the `method` parameter of a localization.
//! Building the map from its first images and localizing it are use cases (`app::cooc`).

use axum::extract::multipart::{Multipart, MultipartRejection};
use axum::extract::{Path, State};
use axum::http::HeaderMap;
use axum::routing::post;
use axum::{Json, Router};
pub mod dto;

use self::dto::{DriveDto, DriveResponse};
use crate::api::error::ApiError;
use crate::api::extract::{map_id, parse_json_object};
use crate::api::state::AppState;
use crate::api::{idempotency, upload};
use seasonloc_app::{DriveInput, Upload};

/// The routes of this resource.
pub fn router() -> Router<AppState> {
    Router::new().route("/v1/maps/{id}/drives", post(add_drive))
}

async fn add_drive(
    State(state): State<AppState>,
    Path(id): Path<String>,
    headers: HeaderMap,
    multipart: Result<Multipart, MultipartRejection>,
) -> Result<(HeaderMap, Json<DriveResponse>), ApiError> {
    let id = map_id(&id)?;
    state.app.map_for(id, Upload::Drive).await?;
    let s = &state.settings;
    let batch = upload::read(
        multipart.map_err(|r| upload::rejection(r, &headers))?,
        Some("drive"),
        s.max_batch_images,
        s.max_body_bytes,
    )
    .await?;
    let Some(json) = batch.json.as_deref() else {
        return Err(ApiError::param(
            "drive",
            "missing: send a JSON part `drive` = {\"locations\": [one index per image], \"time\"?}",
        ));
    };
    let drive: DriveDto = parse_json_object(json, Some("drive"))?;
    if drive.locations.len() != batch.images.len() {
        return Err(ApiError::inconsistent(
            "drive.locations",
            format!(
                "has {} entries for {} images; give one location per image",
                drive.locations.len(),
                batch.images.len()
            ),
        ));
    }
    let time = drive.time.unwrap_or(0.0);
    if !time.is_finite() {
        return Err(ApiError::param("drive.time", "must be a finite number"));
    }
    let key = idempotency::from_tagged_request(&headers, "drives", &batch)?;
    let outcome = state
        .app
        .add_drive(
            id,
            DriveInput {
                images: batch.images,
                locations: drive.locations,
                time,
            },
            key,
        )
        .await?;
    let headers = idempotency::headers(outcome.replayed);
    Ok((
        headers,
        Json(DriveResponse {
            drives: outcome.drives,
            images: outcome.images,
        }),
    ))
}
