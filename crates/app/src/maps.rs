//! Maps and their reference images: create (a CNN map's model is checked and its identity
//! recorded), read, list, delete, and append images or precomputed descriptors.
//!
//! An append is all-or-nothing: every image is decoded and described first (on the CPU pool),
//! then the batch is one atomic store write; any error before that writes nothing.

use std::ops::Range;
use std::time::Instant;

use super::error::{AppError, AppResult};
use super::idempotency::{answered_id, id_answer, Idempotency};
use super::images::{self, ImageInput};
use super::kind::{kind, Kind};
use super::{ids, map_extractor, App};
use crate::model::{CnnSettings, DescriptorSettings, ImageMeta, MapRecord};
use crate::store::{IdempotencyRecord, ImageBatch, NewMap};
use seasonloc_core::features::cnn::{CnnOptions, CnnSpec};
use seasonloc_core::features::hog::{HogOptions, HogSpec};
use seasonloc_core::features::Extractor;
use seasonloc_core::Matrix;

/// A map to create.
#[derive(Clone, Debug, PartialEq)]
pub struct NewMapSpec {
    /// Its name (checked by the front end).
    pub name: String,
    /// How its descriptors are computed.
    pub descriptor: DescriptorSpec,
}

/// How a new map's descriptors are computed.
#[derive(Clone, Debug, PartialEq)]
pub enum DescriptorSpec {
    /// Complete, validated settings (HOG, precomputed, co-occurrence).
    Settings(DescriptorSettings),
    /// A CNN layer: the model is loaded and checked at creation, and its identity recorded.
    Cnn(CnnOptions),
}

/// The result of an append.
#[derive(Clone, Debug, PartialEq)]
pub struct AppendOutcome {
    /// Route indices given to the new images.
    pub indices: Range<u32>,
    /// Seconds spent decoding and describing the images (none for descriptors).
    pub features_seconds: Option<f64>,
    /// Seconds of the store write, when it was a separate stage.
    pub store_seconds: Option<f64>,
    /// Whether this is the stored answer of an earlier request with the same idempotency key
    /// (nothing was appended).
    pub replayed: bool,
}

/// A CNN settings error at creation, naming the map spec's field.
fn cnn_error(e: seasonloc_core::Error) -> AppError {
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
        seasonloc_core::Error::InvalidParameter { name, reason } => {
            AppError::param(field(name), reason)
        }
        seasonloc_core::Error::Inconsistent { name, reason } => {
            AppError::inconsistent(field(name), reason)
        }
        seasonloc_core::Error::Io { path, source } => AppError::inconsistent(
            "descriptor.model",
            format!("cannot read {}: {source}", path.display()),
        ),
        other @ (seasonloc_core::Error::NonFinite { .. }
        | seasonloc_core::Error::Shape(_)
        | seasonloc_core::Error::Empty(_)
        | seasonloc_core::Error::Image { .. }
        | seasonloc_core::Error::Format { .. }) => {
            AppError::inconsistent("descriptor.model", other.to_string())
        }
    }
}

/// Checks CNN options and loads the model for a new map (blocking): every failure names the
/// descriptor field (a range, a missing file, not ONNX, an unknown layer with the available
/// ones, the input size).
fn check_cnn(options: CnnOptions, max_len: usize) -> AppResult<CnnSettings> {
    options.validate().map_err(cnn_error)?;
    let spec = CnnSpec::new(options.clone()).map_err(cnn_error)?;
    if spec.dim() > max_len {
        return Err(AppError::inconsistent(
            "descriptor.layer",
            format!(
                "`{}` gives descriptors of length {}, more than the server's limit of {max_len}",
                options.layer,
                spec.dim()
            ),
        ));
    }
    Ok(CnnSettings {
        identity: spec.identity(),
        options,
    })
}

/// A HOG map with a `resize` gives every image the descriptor length of that size: one over the
/// server's limit could never take an image, so it is refused when created, naming `resize`.
fn check_hog_resize(cell_size: u32, (w, h): (u32, u32), max_len: usize) -> AppResult<()> {
    let options = HogOptions {
        cell_size,
        resize: Some((w, h)),
    };
    let dim = HogSpec::new(options)
        .and_then(|spec| spec.dim_for(w, h))
        .map_err(|e| AppError::inconsistent("descriptor.resize", e.to_string()))?;
    if dim > max_len {
        return Err(AppError::inconsistent(
            "descriptor.resize",
            format!(
                "{w}x{h} with {cell_size} px cells gives descriptors of length {dim}, more than \
                 the server's limit of {max_len} (use a smaller `resize` or larger cells)"
            ),
        ));
    }
    Ok(())
}

impl App {
    /// Creates a map.
    pub async fn create_map(&self, spec: NewMapSpec) -> AppResult<MapRecord> {
        Ok(self.create_map_once(spec, None).await?.0)
    }

    /// [`App::create_map`] with an optional idempotency key: a request whose key created a
    /// map already (on any replica, and the map still exists) creates none but answers that
    /// map, as it is now, with `true` (a replay).
    pub async fn create_map_once(
        &self,
        spec: NewMapSpec,
        idempotency: Option<Idempotency>,
    ) -> AppResult<(MapRecord, bool)> {
        let replay =
            |record: IdempotencyRecord| async move { self.get_map(answered_id(&record)?).await };
        let create = |record| self.create_new_map(spec, record);
        self.once(idempotency, IdempotencyRecord::maps_scope(), replay, create)
            .await
    }

    async fn create_new_map(
        &self,
        spec: NewMapSpec,
        idempotency: Option<IdempotencyRecord>,
    ) -> AppResult<MapRecord> {
        let max_len = self.config.max_descriptor_len;
        let descriptor = match spec.descriptor {
            DescriptorSpec::Settings(DescriptorSettings::Precomputed { dim })
                if dim as usize > max_len =>
            {
                return Err(AppError::inconsistent(
                    "descriptor.dim",
                    format!("{dim} is more than the server's limit of {max_len}"),
                ));
            }
            DescriptorSpec::Settings(DescriptorSettings::Hog {
                cell_size,
                resize: Some(size),
            }) => {
                check_hog_resize(cell_size, size, max_len)?;
                DescriptorSettings::Hog {
                    cell_size,
                    resize: Some(size),
                }
            }
            DescriptorSpec::Settings(d) => d,
            DescriptorSpec::Cnn(mut options) => {
                // Ranges first (no file is touched): a side out of range is the same 400
                // whatever model the request names.
                options.validate().map_err(cnn_error)?;
                // A model the request named is checked against the model directory first,
                // on a blocking thread (stat only), so a hostile path never reaches the
                // loader or the CPU pool.
                if self.config.default_cnn_model.as_ref() != Some(&options.model) {
                    let policy = self.config.models.clone();
                    let requested = options.model.clone();
                    options.model = tokio::task::spawn_blocking(move || policy.resolve(&requested))
                        .await
                        .map_err(|e| AppError::Internal(format!("model check: {e}")))??;
                }
                let max_len = self.config.max_descriptor_len;
                let settings = self.pool.run(move || check_cnn(options, max_len)).await?;
                DescriptorSettings::Cnn(Box::new(settings))
            }
        };
        let new = NewMap {
            id: 0,
            name: spec.name,
            descriptor,
            idempotency,
        };
        // A keyed request's record answers with the map's id.
        let set_id = |n: &mut NewMap, id: u64| {
            n.id = id;
            if let Some(r) = n.idempotency.as_mut() {
                r.response = id_answer(id);
            }
        };
        let map = ids::create_with_new_id(new, set_id, |n| self.store.create_map(n)).await?;
        tracing::info!(map = %format!("{:016x}", map.id), name = %map.name, "map created");
        Ok(map)
    }

    /// One map.
    pub async fn get_map(&self, id: u64) -> AppResult<MapRecord> {
        Ok(self.store.get_map(id).await?)
    }

    /// All maps, oldest first.
    pub async fn list_maps(&self) -> AppResult<Vec<MapRecord>> {
        Ok(self.store.list_maps().await?)
    }

    /// Deletes a map and everything under it.
    pub async fn delete_map(&self, id: u64) -> AppResult<()> {
        self.store.delete_map(id).await?;
        self.references.forget(id);
        self.priors.forget(id);
        self.normalized.forget(id);
        tracing::info!(map = %format!("{id:016x}"), "map deleted");
        Ok(())
    }

    /// The map that a batch of reference images is about to be appended to: fails before the
    /// images are read when the map is gone or takes descriptors, not images.
    pub async fn map_for_images(&self, id: u64) -> AppResult<MapRecord> {
        let map = self.get_map(id).await?;
        if let DescriptorSettings::Precomputed { .. } = map.descriptor {
            return Err(AppError::MapKind(format!(
                "map `{id:016x}` stores precomputed descriptors; post them to \
                 /v1/maps/{id:016x}/descriptors"
            )));
        }
        Ok(map)
    }

    /// The map that precomputed descriptors are about to be appended to: fails when it is gone
    /// or is a co-occurrence map (built from images).
    pub async fn map_for_descriptors(&self, id: u64) -> AppResult<MapRecord> {
        let map = self.get_map(id).await?;
        if let Kind::Cooc(_) = kind(&map) {
            return Err(AppError::MapKind(format!(
                "co-occurrence map `{id:016x}` is built from images; post them to \
                 /v1/maps/{id:016x}/images"
            )));
        }
        Ok(map)
    }

    /// Appends reference images (in route order, one metadata entry each) to `map` (from
    /// [`App::map_for_images`]): described with the map's settings and stored, or, for a
    /// co-occurrence map, its first batch builds the map.
    pub async fn append_images(
        &self,
        map: MapRecord,
        images: Vec<ImageInput>,
        metas: Vec<ImageMeta>,
    ) -> AppResult<AppendOutcome> {
        self.append_images_once(map, images, metas, None).await
    }

    /// [`App::append_images`] with an optional idempotency key: a batch whose key was applied
    /// already (by any process) is not appended again but answered with the indices it got
    /// (`app/idempotency.rs`).
    pub async fn append_images_once(
        &self,
        map: MapRecord,
        images: Vec<ImageInput>,
        metas: Vec<ImageMeta>,
        idempotency: Option<Idempotency>,
    ) -> AppResult<AppendOutcome> {
        let id = map.id;
        let append = |record| self.append_keyed(map, images, metas, record);
        self.append_once(id, idempotency, append).await
    }

    /// Runs `append` once per idempotency key of map `map`'s appends ([`App::once`]); a
    /// replay answers the indices the first append got.
    async fn append_once<Fut>(
        &self,
        map: u64,
        idempotency: Option<Idempotency>,
        append: impl FnOnce(Option<IdempotencyRecord>) -> Fut,
    ) -> AppResult<AppendOutcome>
    where
        Fut: std::future::Future<Output = AppResult<AppendOutcome>>,
    {
        let replay = |record: IdempotencyRecord| async move {
            let indices = record.indices.ok_or_else(|| {
                AppError::Internal(format!(
                    "the stored append of key `{}` has no indices",
                    record.key
                ))
            })?;
            Ok(AppendOutcome {
                indices,
                features_seconds: None,
                store_seconds: None,
                replayed: true,
            })
        };
        let scope = IdempotencyRecord::images_scope(map);
        Ok(self.once(idempotency, scope, replay, append).await?.0)
    }

    async fn append_keyed(
        &self,
        map: MapRecord,
        images: Vec<ImageInput>,
        metas: Vec<ImageMeta>,
        idempotency: Option<IdempotencyRecord>,
    ) -> AppResult<AppendOutcome> {
        if images.len() != metas.len() {
            return Err(AppError::ShapeMismatch(format!(
                "{} metadata entries for {} images",
                metas.len(),
                images.len()
            )));
        }
        if let Kind::Cooc(params) = kind(&map) {
            let params = params.clone();
            return self
                .build_cooc(map, params, images, metas, idempotency)
                .await;
        }
        let started = Instant::now();
        let max_pixels = self.config.max_image_pixels;
        let max_len = self.config.max_descriptor_len;
        let id = map.id;
        let (descriptors, thumbnails, geometry) = self
            .pool
            .run(move || {
                let mut map = map;
                let geometry = first_batch_geometry(&mut map, &images)?;
                let Some(extractor) = map_extractor(&map)? else {
                    return Err(AppError::MapKind(format!(
                        "map `{id:016x}` stores precomputed descriptors; send descriptors, not \
                         images"
                    )));
                };
                let rows = images::describe_with_thumbnails(
                    extractor.as_ref(),
                    &images,
                    max_pixels,
                    max_len,
                    map.dim,
                )?;
                Ok((rows.0, rows.1, geometry))
            })
            .await?;
        let features_seconds = started.elapsed().as_secs_f64();
        let batch = ImageBatch::new(id, descriptors, metas)?
            .with_thumbnails(thumbnails)?
            .with_geometry(geometry)
            .with_idempotency(idempotency);
        let mut outcome = self.store_batch(batch).await?;
        outcome.features_seconds = Some(features_seconds);
        Ok(outcome)
    }

    /// Appends precomputed descriptors (one row per image, in route order) to a map of
    /// global descriptors.
    pub async fn append_descriptors(
        &self,
        map: u64,
        descriptors: Matrix,
        metas: Vec<ImageMeta>,
    ) -> AppResult<AppendOutcome> {
        self.append_descriptors_once(map, descriptors, metas, None)
            .await
    }

    /// [`App::append_descriptors`] with an optional idempotency key, as
    /// [`App::append_images_once`] (one key space per map for both kinds of append).
    pub async fn append_descriptors_once(
        &self,
        map: u64,
        descriptors: Matrix,
        metas: Vec<ImageMeta>,
        idempotency: Option<Idempotency>,
    ) -> AppResult<AppendOutcome> {
        let batch = ImageBatch::new(map, descriptors, metas)?;
        let append = |record| self.store_batch(batch.with_idempotency(record));
        self.append_once(map, idempotency, append).await
    }

    /// The JPEG thumbnail of image `index` of map `id` (stored at upload), `None` when the
    /// image has none (stored before thumbnails existed, or not an image upload).
    pub async fn thumbnail(&self, id: u64, index: u32) -> AppResult<Option<Vec<u8>>> {
        Ok(self.store.thumbnail(id, index).await?)
    }

    /// The metadata of up to `limit` images of map `id` from index `from` on, in route order,
    /// with the map (whose `image_count` tells whether more follow).
    pub async fn image_metadata(
        &self,
        id: u64,
        from: u32,
        limit: u32,
    ) -> AppResult<(MapRecord, Vec<ImageMeta>)> {
        let map = self.get_map(id).await?;
        let start = from.min(map.image_count);
        let end = start.saturating_add(limit).min(map.image_count);
        let metas = self.store.image_metadata(id, start..end).await?;
        Ok((map, metas))
    }

    async fn store_batch(&self, batch: ImageBatch) -> AppResult<AppendOutcome> {
        let map = batch.map();
        let started = Instant::now();
        let indices = self.store.append_images(batch).await?;
        let store_seconds = started.elapsed().as_secs_f64();
        tracing::info!(
            map = %format!("{map:016x}"),
            first = indices.start,
            count = indices.len(),
            "batch stored"
        );
        Ok(AppendOutcome {
            indices,
            features_seconds: None,
            store_seconds: Some(store_seconds),
            replayed: false,
        })
    }
}

/// The input geometry a HOG map without one gets from its first batch: the size of the batch's
/// first image (`features::geometry`), set into `map` so that the whole batch is described at
/// it, and returned for the store to record. `None` (and `map` unchanged) for other maps, maps
/// that already have images or a `resize`, and a first image that cannot hold one HOG cell
/// (which the description then reports by name).
fn first_batch_geometry(
    map: &mut MapRecord,
    images: &[ImageInput],
) -> AppResult<Option<(u32, u32)>> {
    let has_images = map.dim.is_some();
    let DescriptorSettings::Hog { cell_size, resize } = &mut map.descriptor else {
        return Ok(None);
    };
    let (Some(first), None, false) = (images.first(), *resize, has_images) else {
        return Ok(None);
    };
    let (w, h) = images::dimensions(first)?;
    let usable =
        |side: u32| (*cell_size..=seasonloc_core::features::hog::MAX_RESIZE_SIDE).contains(&side);
    if !(usable(w) && usable(h)) {
        return Ok(None);
    }
    *resize = Some((w, h));
    Ok(Some((w, h)))
}
