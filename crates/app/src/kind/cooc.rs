//! Co-occurrence (`cooc`) maps: building the map from its reference images, adding further
//! drives, and localizing with the method's single-image recognition, its sequence matching, or
//! its scores in the flow graph.
//!
//! When the map is built: from the **first** batch of reference images, which is the first
//! mapping drive in route order (image `k` = location `k`); the visual vocabulary is learned
//! from it and never changes afterwards, so a map's words keep their meaning. A later image
//! batch is [`AppError::MapKind`] (the route's locations are fixed by the first drive); further
//! drives of the same route go to [`App::add_drive`], each image naming its location. Every
//! change writes the whole encoded map (`CoocMap::to_bytes`) with the map record in one atomic
//! store write, conditional on the bytes it was computed from ([`AppError::MapChanged`] when a
//! concurrent request won).
//!
//! Trips on a co-occurrence map ([`RowSource::Cooc`]): each batch of frames is quantised and
//! scored against every location, and the score rows (`s + 1`, as `cooc-flow` offline) feed
//! the same online graph, status and confidence as a HOG/CNN trip; the prior column means come
//! from the map's own images ([`CoocMap::trip_prior`]).

use std::sync::Arc;
use std::time::Instant;

use async_trait::async_trait;

use super::{AppendOutcome, Computed, MapKind, Queries, RowSource, Upload};
use crate::error::{AppError, AppResult};
use crate::idempotency::Idempotency;
use crate::images::{decode_gray, each_gray, ImageInput};
use crate::model::{DescriptorSettings, ImageMeta, MapRecord};
use crate::store::{CoocWrite, IdempotencyRecord};
use crate::App;
use seasonloc_core::cooc::{CoocMap, CoocMethod, CoocOptions, CoocParams, CoocQueries, Drive};
use seasonloc_core::localize::{Localization, LocalizeOptions};

/// How many of a map's own images [`App::cooc_trip_prior`] scores (as for descriptor maps).
const TRIP_PRIOR_SAMPLE: usize = 256;

/// The kind of feature co-occurrence maps.
pub(crate) struct CoocMaps;

#[async_trait]
impl MapKind for CoocMaps {
    fn accepts(&self, map: &MapRecord, upload: Upload) -> AppResult<()> {
        let id = map.id;
        match upload {
            Upload::Images | Upload::Drive => Ok(()),
            Upload::Descriptors => Err(AppError::MapKind(format!(
                "co-occurrence map `{id:016x}` is built from images; post them to \
                 /v1/maps/{id:016x}/images"
            ))),
        }
    }

    async fn append_images(
        &self,
        app: &App,
        map: MapRecord,
        images: Vec<ImageInput>,
        metas: Vec<ImageMeta>,
        idempotency: Option<IdempotencyRecord>,
    ) -> AppResult<AppendOutcome> {
        let DescriptorSettings::Cooc(params) = &map.descriptor else {
            return Err(AppError::Internal(format!(
                "map `{:016x}` is not a co-occurrence map",
                map.id
            )));
        };
        let params = params.as_ref().clone();
        app.build_cooc(map, params, images, metas, idempotency)
            .await
    }

    async fn localize(
        &self,
        app: &App,
        map: MapRecord,
        queries: Queries,
        options: &LocalizeOptions,
        method: Option<CoocMethod>,
    ) -> AppResult<Computed> {
        let Queries::Images(parts) = queries else {
            return Err(AppError::MapKind(format!(
                "co-occurrence map `{:016x}` localizes images (multipart), not descriptors",
                map.id
            )));
        };
        let method = method.unwrap_or_default();
        let query_count = parts.len();
        let (localization, load_references, features) = app
            .localize_cooc(&map, parts, method, options.clone())
            .await?;
        // The co-occurrence methods keep no similarity picture (yet).
        Ok(Computed {
            localization,
            load_references,
            features,
            query_count,
            method: Some(method),
            picture: None,
        })
    }

    async fn trip_prior(&self, app: &App, map: &MapRecord) -> AppResult<Arc<Vec<f32>>> {
        app.cooc_trip_prior(map).await
    }

    async fn trip_rows(
        &self,
        app: &App,
        map: &MapRecord,
        _reference_count: u32,
    ) -> AppResult<RowSource> {
        Ok(RowSource::Cooc(Box::new(app.load_cooc(map).await?.1)))
    }
}

/// A further drive of a co-occurrence map's route.
#[derive(Clone, Debug)]
pub struct DriveInput {
    /// The drive's images, in order.
    pub images: Vec<ImageInput>,
    /// Location (reference image index) of each image.
    pub locations: Vec<u64>,
    /// Time key ordering the drives (only the order matters).
    pub time: f64,
}

/// The result of [`App::add_drive`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct DriveOutcome {
    /// Drives in the map now (the first mapping drive included).
    pub drives: usize,
    /// Images added by this drive.
    pub images: usize,
    /// Whether this is the stored answer of an earlier request with the same idempotency key
    /// (nothing was fused).
    pub replayed: bool,
}

/// A drive's answer as stored for replays: the drive count after it and its image count.
fn encode_drive(drives: usize, images: usize) -> Vec<u8> {
    [drives as u64, images as u64]
        .iter()
        .flat_map(|v| v.to_le_bytes())
        .collect()
}

/// [`encode_drive`] read back.
fn decode_drive(bytes: &[u8]) -> AppResult<(usize, usize)> {
    let Ok::<[u8; 16], _>(b) = bytes.try_into() else {
        return Err(AppError::Internal(format!(
            "a stored drive answer has {} bytes, not 16",
            bytes.len()
        )));
    };
    let (mut drives, mut images) = ([0u8; 8], [0u8; 8]);
    drives.copy_from_slice(&b[..8]);
    images.copy_from_slice(&b[8..]);
    Ok((
        u64::from_le_bytes(drives) as usize,
        u64::from_le_bytes(images) as usize,
    ))
}

impl App {
    /// The encoded and decoded co-occurrence map of `map`, decoded on the CPU pool.
    pub(super) async fn load_cooc(&self, map: &MapRecord) -> AppResult<(Vec<u8>, CoocMap)> {
        let id = map.id;
        let Some(bytes) = self.store.cooc_map(id).await? else {
            return Err(AppError::MapEmpty(id));
        };
        self.pool
            .run(move || {
                let decoded = CoocMap::from_bytes(&bytes).map_err(|e| {
                    AppError::Internal(format!(
                        "stored co-occurrence map {id:016x} is unreadable: {e}"
                    ))
                })?;
                Ok((bytes, decoded))
            })
            .await
    }

    /// Builds a `cooc` map from its first batch of reference images and stores it with their
    /// metadata.
    pub(super) async fn build_cooc(
        &self,
        map: MapRecord,
        params: CoocParams,
        images: Vec<ImageInput>,
        metas: Vec<ImageMeta>,
        idempotency: Option<IdempotencyRecord>,
    ) -> AppResult<AppendOutcome> {
        let id = map.id;
        if map.image_count > 0 {
            return Err(AppError::MapKind(format!(
                "co-occurrence map `{id:016x}` was built from its first batch of {} reference \
                 images (the vocabulary is learned from that drive); add further drives of the \
                 route with POST /v1/maps/{id:016x}/drives",
                map.image_count
            )));
        }
        let started = Instant::now();
        let (max_pixels, max_batch) = (self.config.max_image_pixels, self.config.max_batch_pixels);
        let encoded = self
            .pool
            .run(move || {
                let gray = decode_gray(&images, max_pixels, max_batch)?;
                let built = CoocMap::build(&params, &[Drive::sequential(0.0, gray)?])?;
                Ok(built.to_bytes())
            })
            .await?;
        let indices = self
            .store
            .put_cooc_map(CoocWrite {
                map: id,
                previous: None,
                encoded,
                new_images: metas,
                idempotency,
            })
            .await?;
        tracing::info!(map = %format!("{id:016x}"), images = indices.len(), "co-occurrence map built");
        Ok(AppendOutcome {
            indices,
            features_seconds: Some(started.elapsed().as_secs_f64()),
            store_seconds: None,
            replayed: false,
        })
    }

    /// Adds a further drive of the route to a co-occurrence map, with an optional idempotency
    /// key (the map's key space, shared with its image appends): a drive whose key was applied already is not fused again but answered
    /// as the first time (`app/idempotency.rs`).
    pub async fn add_drive(
        &self,
        id: u64,
        drive: DriveInput,
        idempotency: Option<Idempotency>,
    ) -> AppResult<DriveOutcome> {
        let replay = |record: IdempotencyRecord| async move {
            let (drives, images) = decode_drive(&record.response)?;
            Ok(DriveOutcome {
                drives,
                images,
                replayed: true,
            })
        };
        let fuse = |record| self.fuse_drive(id, drive, record);
        let scope = IdempotencyRecord::images_scope(id);
        Ok(self.once(idempotency, scope, replay, fuse).await?.0)
    }

    /// Fuses `drive` into the map and stores it, with the idempotency `record` (its answer
    /// filled in) in the same write when there is one.
    async fn fuse_drive(
        &self,
        id: u64,
        drive: DriveInput,
        record: Option<IdempotencyRecord>,
    ) -> AppResult<DriveOutcome> {
        // Re-read: the map may have been built since the caller's check.
        let map = self.map_for(id, Upload::Drive).await?;
        if drive.locations.len() != drive.images.len() {
            return Err(AppError::inconsistent(
                "drive.locations",
                format!(
                    "has {} entries for {} images; give one location per image",
                    drive.locations.len(),
                    drive.images.len()
                ),
            ));
        }
        if let Some((k, l)) = drive
            .locations
            .iter()
            .enumerate()
            .find(|(_, &l)| l >= u64::from(map.image_count))
        {
            return Err(if map.image_count == 0 {
                AppError::MapEmpty(id)
            } else {
                AppError::inconsistent(
                    format!("drive.locations[{k}]"),
                    format!(
                        "location {l} does not exist: the map has {} locations (0..={})",
                        map.image_count,
                        map.image_count - 1
                    ),
                )
            });
        }
        let (previous, mut cooc) = self.load_cooc(&map).await?;
        let (max_pixels, max_batch) = (self.config.max_image_pixels, self.config.max_batch_pixels);
        let images = drive.images.len();
        let (encoded, drives) = self
            .pool
            .run(move || {
                let gray = decode_gray(&drive.images, max_pixels, max_batch)?;
                let locations = drive.locations.iter().map(|&l| l as usize).collect();
                cooc.add_drive(&Drive::new(drive.time, gray, locations)?)?;
                Ok((cooc.to_bytes(), cooc.locations().drives().len()))
            })
            .await?;
        let idempotency = record.map(|r| IdempotencyRecord {
            response: encode_drive(drives, images),
            ..r
        });
        self.store
            .put_cooc_map(CoocWrite {
                map: id,
                previous: Some(previous),
                encoded,
                new_images: Vec::new(),
                idempotency,
            })
            .await?;
        tracing::info!(map = %format!("{id:016x}"), images, drives, "drive added");
        Ok(DriveOutcome {
            drives,
            images,
            replayed: false,
        })
    }

    /// A trip's prior column means on a co-occurrence map ([`CoocMap::trip_prior`]); computed
    /// at every opening (not cached: a further drive changes it without changing the image
    /// count).
    pub(super) async fn cooc_trip_prior(&self, map: &MapRecord) -> AppResult<Arc<Vec<f32>>> {
        if map.image_count == 0 {
            return Err(AppError::MapEmpty(map.id));
        }
        let (_, cooc) = self.load_cooc(map).await?;
        self.pool
            .run(move || Ok(Arc::new(cooc.trip_prior(TRIP_PRIOR_SAMPLE)?)))
            .await
    }

    /// Quantises the query images and localizes them on a `cooc` map with `method` (the one
    /// entry point of the co-occurrence methods, [`CoocQueries::localize`]; `options` are the
    /// flow graph's). Returns the result and the seconds spent loading the map and describing
    /// the queries.
    pub(super) async fn localize_cooc(
        &self,
        map: &MapRecord,
        parts: Vec<ImageInput>,
        method: CoocMethod,
        options: LocalizeOptions,
    ) -> AppResult<(Localization, f64, f64)> {
        let started = Instant::now();
        let (_, cooc) = self.load_cooc(map).await?;
        let load_seconds = started.elapsed().as_secs_f64();
        let max_pixels = self.config.max_image_pixels;
        self.pool
            .run(move || {
                let started = Instant::now();
                // Each query is decoded, quantised and dropped in turn (no batch held decoded).
                let words = each_gray(&parts, max_pixels, |p, gray| {
                    Ok(cooc.quantize(&p.name, gray)?)
                })?;
                let queries = CoocQueries::from_words(&cooc, words);
                let features = started.elapsed().as_secs_f64();
                let options = CoocOptions {
                    flow: options,
                    ..CoocOptions::default()
                };
                let result = queries.localize(method, &options)?;
                Ok((result, load_seconds, features))
            })
            .await
    }
}
