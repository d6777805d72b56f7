//! Co-occurrence (`cooc`) maps in the service: building the map from its reference images,
//! adding further drives (`POST /v1/maps/{id}/drives`), and localizing with the method's
//! single-image recognition, its sequence matching, or its scores in the flow graph.
//!
//! When the map is built: from the **first** batch of reference images (`POST .../images`),
//! which is the first mapping drive in route order (image `k` = location `k`); the visual
//! vocabulary is learned from it and never changes afterwards, so a map's words keep their
//! meaning. A later `/images` batch is 409 `map_kind` (the route's locations are fixed by the
//! first drive); further drives of the same route go to `/drives`, each image naming its
//! location. Every change writes the whole encoded map (`CoocMap::to_bytes`) with the map record
//! in one atomic, flushed batch, guarded against concurrent writers (409 `map_changed`).

use std::sync::Arc;
use std::time::Instant;

use axum::extract::multipart::{Multipart, MultipartRejection};
use axum::extract::{Path, State};
use axum::routing::post;
use axum::{Json, Router};
use image::GrayImage;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::dto::format_id;
use super::error::ApiError;
use super::maps::map_id;
use super::state::{blocking, AppState};
use super::upload::{self, ImagePart};
use crate::cooc::sequence::match_sequences;
use crate::cooc::{flow_similarity, CoocMap, CoocParams, Drive, Schedule, SequenceParams};
use crate::eval::Prediction;
use crate::features::decode_image;
use crate::localize::{solve_with_confidence, Localization, LocalizeOptions, StageTimings};
use crate::similarity::Normalization;
use crate::solver::Solution;
use crate::store::{DescriptorSettings, ImageMeta, MapRecord, Store};

/// The routes of this resource.
pub fn router() -> Router<AppState> {
    Router::new().route("/v1/maps/{id}/drives", post(add_drive))
}

/// How a `cooc` map localizes a query sequence (`params.method`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Deserialize, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum CoocMethod {
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

impl CoocMethod {
    /// The wire name (`flow`, `cooc`, `cooc-seq`).
    pub fn name(self) -> &'static str {
        match self {
            CoocMethod::Flow => "flow",
            CoocMethod::Cooc => "cooc",
            CoocMethod::CoocSeq => "cooc-seq",
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

fn decode_gray(parts: &[ImagePart], max_pixels: u64) -> Result<Vec<GrayImage>, ApiError> {
    parts
        .par_iter()
        .map(|p| {
            let img = decode_image(&p.name, &p.bytes, max_pixels).map_err(ApiError::from)?;
            Ok(img.to_luma8())
        })
        .collect()
}

fn params_of(map: &MapRecord) -> Option<&CoocParams> {
    match &map.descriptor {
        DescriptorSettings::Cooc(p) => Some(p),
        _ => None,
    }
}

fn load(store: &Store, map: &MapRecord) -> Result<(Vec<u8>, CoocMap), ApiError> {
    let Some(bytes) = store.cooc_map(map.id)? else {
        return Err(ApiError::MapEmpty(format_id(map.id)));
    };
    let decoded = CoocMap::from_bytes(&bytes).map_err(|e| {
        ApiError::Internal(format!(
            "stored co-occurrence map {} is unreadable: {e}",
            format_id(map.id)
        ))
    })?;
    Ok((bytes, decoded))
}

/// Builds a `cooc` map from its first batch of reference images and stores it with their
/// metadata (blocking: run on the CPU pool). Returns the indices given to the images.
pub fn build_from_images(
    store: &Store,
    map: &MapRecord,
    parts: &[ImagePart],
    metas: &[ImageMeta],
    max_pixels: u64,
) -> Result<std::ops::Range<u32>, ApiError> {
    let params = params_of(map).expect("called for cooc maps only");
    if map.image_count > 0 {
        return Err(ApiError::MapKind(format!(
            "co-occurrence map `{}` was built from its first batch of {} reference images (the \
             vocabulary is learned from that drive); add further drives of the route with \
             POST /v1/maps/{}/drives",
            format_id(map.id),
            map.image_count,
            format_id(map.id)
        )));
    }
    let images = decode_gray(parts, max_pixels)?;
    let built = CoocMap::build(params, &[Drive::sequential(0.0, images)?])?;
    Ok(store.put_cooc_map(map.id, None, &built.to_bytes(), metas)?)
}

/// Quantises `queries` and localizes them on a `cooc` map with `method` (blocking).
pub fn localize(
    store: &Store,
    map: &MapRecord,
    parts: &[ImagePart],
    max_pixels: u64,
    method: CoocMethod,
    options: &LocalizeOptions,
) -> Result<(Localization, f64, f64), ApiError> {
    let started = Instant::now();
    let (_, cooc) = load(store, map)?;
    let load_seconds = started.elapsed().as_secs_f64();
    let started = Instant::now();
    let words = cooc.quantize_all(&decode_gray(parts, max_pixels)?)?;
    let features = started.elapsed().as_secs_f64();
    let empty = |hidden_cost: f64| Solution {
        hidden_cost,
        hypotheses: Vec::new(),
    };
    let started = Instant::now();
    let result = match method {
        CoocMethod::Cooc => {
            let predictions: Vec<Prediction> = words
                .par_iter()
                .enumerate()
                .filter_map(|(i, q)| {
                    cooc.recognize_words(q, Schedule::BestFirst)
                        .map(|r| Prediction {
                            query: i,
                            reference: r.location,
                            confidence: r.score as f64,
                        })
                })
                .collect();
            Localization {
                solution: empty(0.0),
                predictions,
                timings: StageTimings {
                    similarity: 0.0,
                    solve: started.elapsed().as_secs_f64(),
                },
            }
        }
        CoocMethod::CoocSeq => {
            let scores = cooc.score_matrix_words(&words);
            let similarity = started.elapsed().as_secs_f64();
            let t = Instant::now();
            let predictions = match_sequences(&scores, &SequenceParams::default())?;
            Localization {
                solution: empty(0.0),
                predictions,
                timings: StageTimings {
                    similarity,
                    solve: t.elapsed().as_secs_f64(),
                },
            }
        }
        CoocMethod::Flow => {
            let scores = cooc.score_matrix_words(&words);
            let chat = Normalization::apply(options.normalization, &flow_similarity(&scores))?;
            let similarity = started.elapsed().as_secs_f64();
            let t = Instant::now();
            let (solution, predictions) = solve_with_confidence(&chat, options)?;
            Localization {
                solution,
                predictions,
                timings: StageTimings {
                    similarity,
                    solve: t.elapsed().as_secs_f64(),
                },
            }
        }
    };
    Ok((result, load_seconds, features))
}

async fn add_drive(
    State(state): State<AppState>,
    Path(id): Path<String>,
    multipart: Result<Multipart, MultipartRejection>,
) -> Result<Json<DriveResponse>, ApiError> {
    let id = map_id(&id)?;
    let store = Arc::clone(&state.store);
    let map = blocking(move || Ok(store.get_map(id)?)).await?;
    if params_of(&map).is_none() {
        return Err(ApiError::MapKind(format!(
            "map `{}` is not a co-occurrence map; drives apply to maps of kind `cooc`",
            format_id(id)
        )));
    }
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
    let store = Arc::clone(&state.store);
    let max_pixels = s.max_image_pixels;
    let images = batch.images.len();
    let drives = state
        .pool
        .run(move || {
            // Re-read under the pool: the map may have been built since the check above.
            let map = store.get_map(id)?;
            if let Some((k, l)) = drive
                .locations
                .iter()
                .enumerate()
                .find(|(_, &l)| l >= u64::from(map.image_count))
            {
                return Err(if map.image_count == 0 {
                    ApiError::MapEmpty(format_id(id))
                } else {
                    ApiError::param(
                        format!("drive.locations[{k}]"),
                        format!(
                            "location {l} does not exist: the map has {} locations (0..={})",
                            map.image_count,
                            map.image_count - 1
                        ),
                    )
                });
            }
            let (previous, mut cooc) = load(&store, &map)?;
            let gray = decode_gray(&batch.images, max_pixels)?;
            let locations = drive.locations.iter().map(|&l| l as usize).collect();
            cooc.add_drive(&Drive::new(time, gray, locations)?)?;
            store.put_cooc_map(id, Some(&previous), &cooc.to_bytes(), &[])?;
            Ok(cooc.locations().drives().len())
        })
        .await?;
    tracing::info!(map = %format_id(id), images, drives, "drive added");
    Ok(Json(DriveResponse { drives, images }))
}
