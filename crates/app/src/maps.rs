//! Maps and their reference images: create (a CNN map's model is checked and its identity
//! recorded), read, list, delete, and append images or precomputed descriptors.
//!
//! An append is all-or-nothing: every image is decoded and described first (on the CPU pool),
//! then the batch is one atomic store write; any error before that writes nothing.

use std::time::Instant;

use super::error::{AppError, AppResult};
use super::idempotency::{answered_id, id_answer, Idempotency};
use super::images::ImageInput;
use super::kind::{self, AppendOutcome, Upload};
use super::{ids, App};
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
    /// Creates a map, with an optional idempotency key: a request whose key created a
    /// map already (on any replica, and the map still exists) creates none but answers that
    /// map, as it is now, with `true` (a replay).
    pub async fn create_map(
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

    /// The map that `upload` is about to be sent to: fails before the body is read when the
    /// map is gone or its kind does not take it (`map_kind`).
    pub async fn map_for(&self, id: u64, upload: Upload) -> AppResult<MapRecord> {
        let map = self.get_map(id).await?;
        kind::of(&map).accepts(&map, upload)?;
        Ok(map)
    }

    /// Appends reference images (in route order, one metadata entry each) to `map` (from
    /// [`App::map_for`]): described with the map's settings and stored, or, for a
    /// co-occurrence map, its first batch builds the map. With an optional idempotency key: a
    /// batch whose key was applied
    /// already (by any process) is not appended again but answered with the indices it got
    /// (`app/idempotency.rs`).
    pub async fn append_images(
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
        kind::of(&map)
            .append_images(self, map, images, metas, idempotency)
            .await
    }

    /// Appends precomputed descriptors (one row per image, in route order) to a map of global
    /// descriptors, with an optional idempotency key, as
    /// [`App::append_images`] (one key space per map for both kinds of append).
    pub async fn append_descriptors(
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

    pub(crate) async fn store_batch(&self, batch: ImageBatch) -> AppResult<AppendOutcome> {
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
