//! Co-occurrence (`cooc`) maps over HTTP: `POST /v1/maps/{id}/drives` (a further drive of the
//! route, each image naming its location) and the `method` parameter of a localization.
//! Building the map from its first images and localizing it are use cases (`app::cooc`).

use axum::extract::multipart::{Multipart, MultipartRejection};
use axum::extract::{Path, State};
use axum::routing::post;
use axum::{Json, Router};
use serde::{Deserialize, Serialize};

use super::error::ApiError;
use super::maps::map_id;
use super::state::AppState;
use super::upload;
use crate::app::DriveInput;
use crate::cooc::CoocMethod;

/// The routes of this resource.
pub fn router() -> Router<AppState> {
    Router::new().route("/v1/maps/{id}/drives", post(add_drive))
}

/// How a `cooc` map localizes a query sequence (`params.method`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Deserialize, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum CoocMethodDto {
    /// The co-occurrence scores (`s + 1`, column-normalised) as the flow graph's similarity
    /// matrix; the solver parameters apply (default).
    #[default]
    Flow,
    /// Single-image recognition: the best location per query, confidence = the size of its
    /// spatially consistent group; no hypotheses.
    Cooc,
    /// The paper's forward-only sequence matching (ds = 10); no hypotheses.
    CoocSeq,
}

impl From<CoocMethodDto> for CoocMethod {
    fn from(m: CoocMethodDto) -> Self {
        match m {
            CoocMethodDto::Flow => CoocMethod::Flow,
            CoocMethodDto::Cooc => CoocMethod::Single,
            CoocMethodDto::CoocSeq => CoocMethod::Sequence,
        }
    }
}

/// `drive` part of `POST /v1/maps/{id}/drives`.
#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DriveDto {
    /// Location (reference image index) of each image, in part order.
    pub locations: Vec<u64>,
    /// Time key ordering the drives (e.g. the hour of day); only the order matters (default 0,
    /// the first drive's).
    #[serde(default)]
    pub time: Option<f64>,
}

/// Answer of `POST /v1/maps/{id}/drives`.
#[derive(Clone, Debug, Serialize)]
pub struct DriveResponse {
    /// Drives in the map now (the first mapping drive included).
    pub drives: usize,
    /// Images added by this drive.
    pub images: usize,
}

async fn add_drive(
    State(state): State<AppState>,
    Path(id): Path<String>,
    multipart: Result<Multipart, MultipartRejection>,
) -> Result<Json<DriveResponse>, ApiError> {
    let id = map_id(&id)?;
    state.app.map_for_drives(id).await?;
    let s = &state.settings;
    let batch = upload::read(
        multipart.map_err(upload::rejection)?,
        "drive",
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
    let drive: DriveDto = super::extract::parse_json(json, Some("drive"))?;
    if drive.locations.len() != batch.images.len() {
        return Err(ApiError::param(
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
    let outcome = state
        .app
        .add_drive(
            id,
            DriveInput {
                images: batch.images,
                locations: drive.locations,
                time,
            },
        )
        .await?;
    Ok(Json(DriveResponse {
        drives: outcome.drives,
        images: outcome.images,
    }))
}
