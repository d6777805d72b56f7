//! Localizing a query sequence against a map, storing the result, and reading stored results.
//!
//! A localization reads the map's record and reference descriptors (from the cache, topped up
//! from the store), describes the queries and runs [`seasonloc_core::localize::localize`] on the CPU
//! pool, and stores the result document under a new id; a co-occurrence map runs one of its
//! methods instead ([`super::cooc`]).

use std::time::Instant;

use super::error::{AppError, AppResult};
use super::idempotency::{answered_id, id_answer, Idempotency};
use super::images::{self, ImageInput};
use super::kind::{kind, Kind};
use super::{ids, map_extractor, App};
use crate::model::{
    LocalizationParams, LocalizationRecord, LocalizationResult, LocalizationTimings, PictureInfo,
};
use crate::store::{IdempotencyRecord, NewLocalization, Page, PageRequest};
use seasonloc_core::cooc::CoocMethod;
use seasonloc_core::localize::{localize_with_picture, Localization, LocalizeOptions};
use seasonloc_core::picture::MatrixPicture;
use seasonloc_core::Matrix;

/// The queries of a localization, in driving order.
#[derive(Clone, Debug)]
pub enum Queries {
    /// Images, described with the map's settings.
    Images(Vec<ImageInput>),
    /// Precomputed descriptors, one row per query.
    Descriptors(Matrix),
}

/// A localization to run.
#[derive(Clone, Debug)]
pub struct LocalizeInput {
    /// The queries.
    pub queries: Queries,
    /// Solver, normalisation and confidence parameters.
    pub options: LocalizeOptions,
    /// For co-occurrence maps, the method (default [`CoocMethod::Flow`]); must be `None` for
    /// other maps.
    pub method: Option<CoocMethod>,
}

/// The name the service's clients use for a method (`params.method`): `flow`, `cooc`,
/// `cooc-seq` (the CLI says `cooc-flow` for the first).
pub fn service_name(m: CoocMethod) -> &'static str {
    match m {
        CoocMethod::Flow => "flow",
        CoocMethod::Single => "cooc",
        CoocMethod::Sequence => "cooc-seq",
    }
}

impl App {
    /// Localizes `input` against map `id` and stores the result under a new id.
    pub async fn localize(&self, id: u64, input: LocalizeInput) -> AppResult<LocalizationRecord> {
        Ok(self.localize_once(id, input, None).await?.0)
    }

    /// [`App::localize`] with an optional idempotency key (the map's key space): a request
    /// whose key was answered already (on any replica) is not computed again but answered with
    /// the stored result, with `true` (a replay). [`App::replayed_localization`] looks first,
    /// so that a caller can answer a replay before it queues for a CPU.
    pub async fn localize_once(
        &self,
        id: u64,
        input: LocalizeInput,
        idempotency: Option<Idempotency>,
    ) -> AppResult<(LocalizationRecord, bool)> {
        self.localize_once_then(id, input, idempotency, || {}).await
    }

    /// [`App::localize_once`] that calls `cpu_done` as soon as the result is computed, before
    /// it is stored (not at all for a replay or when the computation fails): a front end that
    /// bounds how many requests compute at once lets the next one in there, instead of holding
    /// a CPU turn through the store's flushed write.
    pub async fn localize_once_then(
        &self,
        id: u64,
        input: LocalizeInput,
        idempotency: Option<Idempotency>,
        cpu_done: impl FnOnce() + Send,
    ) -> AppResult<(LocalizationRecord, bool)> {
        let replay = |record: IdempotencyRecord| async move {
            Ok(self.store.get_localization(answered_id(&record)?).await?)
        };
        let compute = |record| self.compute_localization(id, input, record, cpu_done);
        let scope = IdempotencyRecord::images_scope(id);
        self.once(idempotency, scope, replay, compute).await
    }

    /// The stored result of the request with `key` on map `id`, if there was one (a key of
    /// another request is [`AppError::IdempotencyKeyReused`]).
    pub async fn replayed_localization(
        &self,
        id: u64,
        key: &Idempotency,
    ) -> AppResult<Option<LocalizationRecord>> {
        let scope = IdempotencyRecord::images_scope(id);
        let Some(record) = self.stored_answer(key, &scope).await? else {
            return Ok(None);
        };
        tracing::info!(%scope, key = %record.key, "idempotent retry answered from its record");
        Ok(Some(
            self.store.get_localization(answered_id(&record)?).await?,
        ))
    }

    async fn compute_localization(
        &self,
        id: u64,
        input: LocalizeInput,
        idempotency: Option<IdempotencyRecord>,
        cpu_done: impl FnOnce() + Send,
    ) -> AppResult<LocalizationRecord> {
        let LocalizeInput {
            queries,
            options,
            method,
        } = input;
        let started = Instant::now();
        let map = self.get_map(id).await?;
        let image_count = map.image_count as usize;
        let (result, load_references, features, query_count, reference_count, method, picture) =
            match kind(&map) {
                Kind::Cooc(_) => {
                    let Queries::Images(parts) = queries else {
                        return Err(AppError::MapKind(format!(
                            "co-occurrence map `{id:016x}` localizes images (multipart), not \
                             descriptors"
                        )));
                    };
                    let method = method.unwrap_or_default();
                    let query_count = parts.len();
                    let (result, load, features) = self
                        .localize_cooc(&map, parts, method, options.clone())
                        .await?;
                    // The co-occurrence methods keep no similarity picture (yet).
                    (
                        result,
                        load,
                        features,
                        query_count,
                        image_count,
                        Some(method),
                        None,
                    )
                }
                Kind::Descriptors(_) => {
                    if let Some(m) = method {
                        return Err(AppError::MapKind(format!(
                            "`{}` applies to co-occurrence maps only; map `{id:016x}` uses the \
                             flow graph",
                            service_name(m)
                        )));
                    }
                    if map.image_count == 0 {
                        return Err(AppError::MapEmpty(id));
                    }
                    let references = self
                        .references
                        .get(self.store.as_ref(), &self.pool, &map, map.image_count)
                        .await?;
                    let load = started.elapsed().as_secs_f64();
                    let max_pixels = self.config.max_image_pixels;
                    let max_len = self.config.max_descriptor_len;
                    let job_options = options.clone();
                    let (result, features, query_count, picture) = self
                        .pool
                        .run(move || {
                            let started = Instant::now();
                            let queries = match queries {
                                Queries::Descriptors(m) => {
                                    if m.cols() != references.cols() {
                                        return Err(AppError::DescriptorLength(format!(
                                            "query descriptors have length {}, map `{id:016x}` \
                                             stores length {}",
                                            m.cols(),
                                            references.cols()
                                        )));
                                    }
                                    m
                                }
                                Queries::Images(parts) => {
                                    let Some(extractor) = map_extractor(&map)? else {
                                        return Err(AppError::MapKind(format!(
                                            "map `{id:016x}` stores precomputed descriptors; \
                                             send descriptors, not images"
                                        )));
                                    };
                                    images::describe(
                                        extractor.as_ref(),
                                        &parts,
                                        max_pixels,
                                        max_len,
                                        map.dim,
                                    )?
                                }
                            };
                            let features = started.elapsed().as_secs_f64();
                            let (result, picture): (Localization, MatrixPicture) =
                                localize_with_picture(&queries, &references, &job_options)?;
                            let png = picture.to_png()?;
                            Ok((result, features, queries.rows(), Some((picture, png))))
                        })
                        .await?;
                    (
                        result,
                        load,
                        features,
                        query_count,
                        image_count,
                        None,
                        picture,
                    )
                }
            };
        cpu_done();
        // Bounded hidden costs keep every cost finite; a non-finite one would be stored and
        // sent as `null`, against the schema, so it is a bug, never a result.
        let total_cost = result.solution.total_cost();
        if !total_cost.is_finite() {
            return Err(AppError::Internal(format!(
                "map `{id:016x}`: the solution's total cost is {total_cost}"
            )));
        }
        let result = LocalizationResult {
            query_count,
            reference_count,
            params: LocalizationParams::new(&options, result.solution.hidden_cost, method),
            total_cost,
            hypotheses: result.solution.hypotheses,
            predictions: result.predictions,
            timings: LocalizationTimings {
                load_references,
                features,
                similarity: result.timings.similarity,
                solve: result.timings.solve,
            },
            picture: picture.as_ref().map(|(p, _)| PictureInfo {
                rows: p.rows,
                cols: p.cols,
                lo: p.lo,
                hi: p.hi,
            }),
        };
        let new = NewLocalization {
            id: 0,
            map_id: id,
            result,
            picture: picture.map(|(_, png)| png),
            idempotency,
        };
        // A keyed request's record answers with the result's id.
        let set_id = |n: &mut NewLocalization, id: u64| {
            n.id = id;
            if let Some(r) = n.idempotency.as_mut() {
                r.response = id_answer(id);
            }
        };
        let record =
            ids::create_with_new_id(new, set_id, |n| self.store.create_localization(n)).await?;
        tracing::info!(
            map = %format!("{id:016x}"),
            localization = %format!("{:016x}", record.id),
            queries = query_count,
            "localized"
        );
        Ok(record)
    }

    /// One stored result.
    pub async fn get_localization(&self, id: u64) -> AppResult<LocalizationRecord> {
        Ok(self.store.get_localization(id).await?)
    }

    /// The PNG of a stored result's similarity picture, `None` when it has none.
    pub async fn localization_picture(&self, id: u64) -> AppResult<Option<Vec<u8>>> {
        Ok(self.store.localization_picture(id).await?)
    }

    /// A page of stored results, newest first; only `map`'s when given.
    pub async fn list_localizations(
        &self,
        map: Option<u64>,
        page: PageRequest,
    ) -> AppResult<Page<LocalizationRecord>> {
        Ok(self.store.list_localizations(map, page).await?)
    }
}
