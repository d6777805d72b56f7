//! Global-descriptor maps (HOG, CNN, precomputed), the flow graph's kind of map
//! ([`DescriptorMaps`], its [`MapKind`]): appends describe the images with the map's settings,
//! localizations and trips compare descriptors. [`map_extractor`] is the one place that turns
//! a map's descriptor settings into an extractor for its images.

use std::sync::Arc;
use std::time::Instant;

use async_trait::async_trait;

use super::{service_name, AppendOutcome, Computed, MapKind, Queries, RowSource, Upload};
use crate::error::{AppError, AppResult};
use crate::images::{self, ImageInput};
use crate::model::{DescriptorSettings, ImageMeta, MapRecord};
use crate::models::ModelRules;
use crate::store::{IdempotencyRecord, ImageBatch};
use crate::App;
use seasonloc_core::cooc::CoocMethod;
use seasonloc_core::features::cnn::CnnSpec;
use seasonloc_core::features::hog::{HogOptions, HogSpec};
use seasonloc_core::features::Extractor;
use seasonloc_core::localize::{localize_with_picture, LocalizeOptions};
use seasonloc_core::trip::column_prior;

/// The kind of maps of global descriptors.
pub(crate) struct DescriptorMaps;

#[async_trait]
impl MapKind for DescriptorMaps {
    fn accepts(&self, map: &MapRecord, upload: Upload) -> AppResult<()> {
        let id = map.id;
        match upload {
            Upload::Images => match map.descriptor {
                DescriptorSettings::Precomputed { .. } => Err(AppError::MapKind(format!(
                    "map `{id:016x}` stores precomputed descriptors; post them to \
                     /v1/maps/{id:016x}/descriptors"
                ))),
                DescriptorSettings::Hog { .. }
                | DescriptorSettings::Cnn(_)
                | DescriptorSettings::Cooc(_) => Ok(()),
            },
            Upload::Descriptors => Ok(()),
            Upload::Drive => Err(AppError::MapKind(format!(
                "map `{id:016x}` is not a co-occurrence map; drives apply to maps of kind `cooc`"
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
        let started = Instant::now();
        let max_pixels = app.config.max_image_pixels;
        let max_len = app.config.max_descriptor_len;
        let id = map.id;
        let rules = app.model_rules();
        let (descriptors, thumbnails, geometry) = app
            .pool
            .run(move || {
                let mut map = map;
                let geometry = first_batch_geometry(&mut map, &images)?;
                let Some(extractor) = map_extractor(&map, &rules)? else {
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
        let mut outcome = app.store_batch(batch).await?;
        outcome.features_seconds = Some(features_seconds);
        Ok(outcome)
    }

    async fn localize(
        &self,
        app: &App,
        map: MapRecord,
        queries: Queries,
        options: &LocalizeOptions,
        method: Option<CoocMethod>,
    ) -> AppResult<Computed> {
        let id = map.id;
        if let Some(m) = method {
            return Err(AppError::MapKind(format!(
                "`{}` applies to co-occurrence maps only; map `{id:016x}` uses the flow graph",
                service_name(m)
            )));
        }
        if map.image_count == 0 {
            return Err(AppError::MapEmpty(id));
        }
        let started = Instant::now();
        let references = app
            .references
            .get(app.store.as_ref(), &app.pool, &map, map.image_count)
            .await?;
        let load_references = started.elapsed().as_secs_f64();
        let max_pixels = app.config.max_image_pixels;
        let max_len = app.config.max_descriptor_len;
        let options = options.clone();
        let rules = app.model_rules();
        app.pool
            .run(move || {
                let started = Instant::now();
                let queries = match queries {
                    Queries::Descriptors(m) => {
                        if m.cols() != references.cols() {
                            return Err(AppError::DescriptorLength(format!(
                                "query descriptors have length {}, map `{id:016x}` stores length \
                                 {}",
                                m.cols(),
                                references.cols()
                            )));
                        }
                        m
                    }
                    Queries::Images(parts) => {
                        let Some(extractor) = map_extractor(&map, &rules)? else {
                            return Err(AppError::MapKind(format!(
                                "map `{id:016x}` stores precomputed descriptors; send \
                                 descriptors, not images"
                            )));
                        };
                        images::describe(extractor.as_ref(), &parts, max_pixels, max_len, map.dim)?
                    }
                };
                let features = started.elapsed().as_secs_f64();
                let (localization, picture) =
                    localize_with_picture(&queries, &references, &options)?;
                let png = picture.to_png()?;
                Ok(Computed {
                    localization,
                    load_references,
                    features,
                    query_count: queries.rows(),
                    method: None,
                    picture: Some((picture, png)),
                })
            })
            .await
    }

    async fn trip_prior(&self, app: &App, map: &MapRecord) -> AppResult<Arc<Vec<f32>>> {
        let id = map.id;
        let checked = map.clone();
        let rules = app.model_rules();
        let has_extractor = app
            .pool
            .run(move || Ok(map_extractor(&checked, &rules)?.is_some()))
            .await?;
        if !has_extractor {
            return Err(AppError::MapKind(format!(
                "map `{id:016x}` stores client-computed descriptors; trips need a map that can \
                 describe images (e.g. `hog`)"
            )));
        }
        if map.image_count == 0 {
            return Err(AppError::MapEmpty(id));
        }
        let count = map.image_count;
        if let Some(p) = app.priors.get(id, count) {
            return Ok(p);
        }
        let references = app
            .references
            .get(app.store.as_ref(), &app.pool, map, count)
            .await?;
        let prior = app
            .pool
            .run(move || Ok(Arc::new(column_prior(&references)?)))
            .await?;
        app.priors.keep(id, count, Arc::clone(&prior));
        Ok(prior)
    }

    async fn trip_rows(
        &self,
        app: &App,
        map: &MapRecord,
        reference_count: u32,
    ) -> AppResult<RowSource> {
        Ok(RowSource::Descriptors(
            app.normalized
                .get(
                    &app.references,
                    app.store.as_ref(),
                    &app.pool,
                    map,
                    reference_count,
                )
                .await?,
        ))
    }
}

/// The input geometry a HOG map without one gets from its first batch: the size of the batch's
/// first image (`features::geometry`), set into `map` so that the whole batch is described at
/// it, and returned for the store to record. `None` (and `map` unchanged) for other maps, maps
/// that already have images or a `resize`, and a first image that cannot hold one HOG cell
/// (which the description then reports by name).
pub(crate) fn first_batch_geometry(
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

/// The extractor of a map's images (references and queries): `None` for precomputed maps.
///
/// For a CNN map the recorded path is first checked with the server's model rules, as at
/// creation ([`ModelRules::check_in_use`]); then the model at that path is loaded (from the shared cache when its
/// content is unchanged) and checked against the identity recorded at creation: a model file
/// that changed, no longer loads or is gone is [`AppError::ModelMismatch`], never silently
/// used. A co-occurrence map has no global descriptors ([`AppError::MapKind`]). Blocking (it
/// hashes the model file): call it on the CPU pool.
pub fn map_extractor(map: &MapRecord, rules: &ModelRules) -> AppResult<Option<Box<dyn Extractor>>> {
    let id = map.id;
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
            rules.check_in_use(&c.options.model).map_err(|reason| {
                AppError::ModelMismatch(format!(
                    "map `{id:016x}` was created with the model at {path} (sha256 {}), which may \
                     no longer be read: {reason}",
                    c.identity.sha256
                ))
            })?;
            let spec = CnnSpec::new(c.options.clone()).map_err(|e| {
                AppError::ModelMismatch(format!(
                    "map `{id:016x}` was created with the model at {path} (sha256 {}), which no \
                     longer loads: {e}",
                    c.identity.sha256
                ))
            })?;
            if let Some(diff) = c.identity.mismatch(&spec.identity()) {
                return Err(AppError::ModelMismatch(format!(
                    "map `{id:016x}`: the model at {path} is not the one the map was created with \
                     ({diff}); restore that file or create a new map"
                )));
            }
            Ok(Some(Box::new(spec)))
        }
        DescriptorSettings::Cooc(_) => Err(AppError::MapKind(format!(
            "map `{id:016x}` is a co-occurrence map: it has no global descriptors (localize it \
             with POST /v1/maps/{id:016x}/localize, add drives with /drives)"
        ))),
    }
}
