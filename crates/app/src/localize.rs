//! Localizing a query sequence against a map, storing the result, and reading stored results.
//!
//! A localization reads the map's record and reference descriptors (from the cache, topped up
//! from the store), describes the queries and runs [`seasonloc_core::localize::localize`] on the CPU
//! pool, and stores the result document under a new id; a co-occurrence map runs one of its
//! methods instead (`kind/cooc.rs`).

use super::error::{AppError, AppResult};
use super::idempotency::{answered_id, id_answer, Idempotency};
use super::kind::{self, Computed, Queries};
use super::{ids, App};
use crate::model::{
    LocalizationParams, LocalizationRecord, LocalizationResult, LocalizationTimings, PictureInfo,
};
use crate::store::{IdempotencyRecord, NewLocalization, Page, PageRequest};
use seasonloc_core::cooc::CoocMethod;
use seasonloc_core::localize::LocalizeOptions;

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

impl App {
    /// Localizes `input` against map `id` and stores the result under a new id, with an
    /// optional idempotency key (the map's key space): a request whose key was answered already
    /// (on any replica) is not computed again but answered with the stored result, with `true`
    /// (a replay); [`App::replayed_localization`] looks first, so that a caller can answer a
    /// replay before it queues for a CPU. Calls `cpu_done` as soon as the result is computed,
    /// before it is stored (not at all for a replay or when the computation fails): a front end that
    /// bounds how many requests compute at once lets the next one in there, instead of holding
    /// a CPU turn through the store's flushed write.
    pub async fn localize(
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
        let map = self.get_map(id).await?;
        let reference_count = map.image_count as usize;
        let Computed {
            localization: result,
            load_references,
            features,
            query_count,
            method,
            picture,
        } = {
            // Describing the queries, the similarities and the solve, in a trace.
            let span = tracing::info_span!("localize", descriptor = map.descriptor.kind_name());
            tracing::Instrument::instrument(
                kind::of(&map).localize(self, map, queries, &options, method),
                span,
            )
            .await?
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
