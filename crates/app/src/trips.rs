//! Trips: a vehicle opens a trip on a map, posts its frames in small batches as it drives,
//! and gets its current position back with every batch.
//!
//! * Opening pins the map's current image count: the trip localizes against those references,
//!   even if images are appended later (its column prior and solver state have that width).
//! * A batch takes the trip's state from this process's cache of open trips when it is at the
//!   stored frame count ([`super::cache::OpenTrips`]), else restores it from the store
//!   ([`seasonloc_core::trip::Trip::restore`]: the snapshot and the log rows after it); describes the
//!   frames with the map's settings, pushes their similarities through the trip, and writes
//!   the state's delta ([`seasonloc_core::trip::Trip::take_delta`]: the batch's rows, sometimes a
//!   snapshot), record and estimates in one atomic store write, conditional on the frame count
//!   the batch was computed after. When another process applied a batch of the same trip in
//!   between (a shared store), the batch is recomputed from the new state, at most
//!   [`CONFLICT_RETRIES`] times; so batches of one trip apply one at a time, wherever they
//!   arrive. Within this process a per-trip lock orders them by arrival.
//! * A batch that fails (bad image, closed trip) writes nothing: the trip is unchanged.

use std::time::Instant;

use super::error::{AppError, AppResult};
use super::idempotency::{self, answered_id, id_answer, Idempotency};
use super::images::{self, ImageInput};
use super::kind;
use super::kind::RowSource;
use super::{ids, map_extractor, App};
use crate::caller::Caller;
use crate::model::{MapRecord, TripRecord};
use crate::store::{
    IdempotencyRecord, NewTrip, Page, PageRequest, StoreError, TripBatch, TripState, TripStateWrite,
};
use seasonloc_core::similarity;
use seasonloc_core::trip::{BatchUpdate, FrameEstimate, Trip, TripParams, TripStatus};

/// How often a batch is recomputed when another process changed the trip meanwhile.
pub const CONFLICT_RETRIES: usize = 4;

/// Seconds per stage of a batch.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct FramesTimings {
    /// Loading state and references.
    pub load: f64,
    /// Decoding and describing the images.
    pub features: f64,
    /// Similarities and the online solve.
    pub solve: f64,
    /// The atomic store write.
    pub store: f64,
}

/// Open trips by the status of their last batch ([`App::open_trip_counts`]).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct OpenTripCounts {
    /// No batch yet.
    pub new: usize,
    /// Last batch `localized`.
    pub localized: usize,
    /// Last batch `lost`.
    pub lost: usize,
    /// Last batch `relocalized`.
    pub relocalized: usize,
}

/// The result of a batch of frames.
#[derive(Clone, Debug, PartialEq)]
pub struct FramesOutcome {
    /// The trip after the batch.
    pub trip: TripRecord,
    /// The trip's answer: new estimates, the lag window, the status.
    pub update: BatchUpdate,
    /// The hidden cost `W` in use.
    pub hidden_cost: f64,
    /// Seconds per stage (all zero for a replay).
    pub timings: FramesTimings,
    /// Whether this is the stored answer of an earlier request with the same idempotency key
    /// (nothing was applied).
    pub replayed: bool,
}

impl App {
    /// Opens a trip on map `id`, with an optional idempotency key (the map's key space): a request
    /// whose key opened a trip already (on any replica) opens none but answers that trip, as
    /// it is now, with `true` (a replay).
    pub async fn open_trip(
        &self,
        id: u64,
        params: TripParams,
        idempotency: Option<Idempotency>,
        caller: Option<&Caller>,
    ) -> AppResult<(TripRecord, bool)> {
        let replay = |record: IdempotencyRecord| async move {
            Ok(self.store.get_trip(answered_id(&record)?).await?)
        };
        let owner = caller.map(|c| c.name.clone());
        let open = |record| self.open_new_trip(id, params, owner, record);
        let scope = IdempotencyRecord::images_scope(id);
        self.once(idempotency, scope, replay, open).await
    }

    async fn open_new_trip(
        &self,
        id: u64,
        params: TripParams,
        owner: Option<String>,
        idempotency: Option<IdempotencyRecord>,
    ) -> AppResult<TripRecord> {
        let map = self.get_map(id).await?;
        let prior = kind::of(&map).trip_prior(self, &map).await?;
        self.create_trip(&map, prior, params, owner, idempotency)
            .await
    }

    /// Stores a new trip on `map` (all its current images) with the map's prior column means.
    async fn create_trip(
        &self,
        map: &MapRecord,
        prior: std::sync::Arc<Vec<f32>>,
        params: TripParams,
        owner: Option<String>,
        idempotency: Option<IdempotencyRecord>,
    ) -> AppResult<TripRecord> {
        let (id, count) = (map.id, map.image_count);
        let state = self
            .pool
            .run(move || Ok(Trip::new(prior.as_ref().clone(), params)?.stored_state()))
            .await?;
        let new = NewTrip {
            id: 0,
            map_id: id,
            reference_count: count,
            params,
            owner,
            base: state.base,
            snapshot: state.snapshot,
            idempotency,
        };
        // A keyed request's record answers with the trip's id.
        let set_id = |n: &mut NewTrip, id: u64| {
            n.id = id;
            if let Some(r) = n.idempotency.as_mut() {
                r.response = id_answer(id);
            }
        };
        let record = ids::create_with_new_id(new, set_id, |n| self.store.create_trip(n)).await?;
        tracing::info!(map = %format!("{id:016x}"), trip = %format!("{:016x}", record.id), "trip opened");
        Ok(record)
    }

    /// Posts a batch of frames to trip `id`, with an optional idempotency key: a batch whose
    /// key was applied
    /// already (by any process) is not applied again but answered as the first time
    /// (`app/idempotency.rs`).
    pub async fn post_frames(
        &self,
        id: u64,
        frames: Vec<ImageInput>,
        idempotency: Option<Idempotency>,
        caller: Option<&Caller>,
    ) -> AppResult<FramesOutcome> {
        if frames.is_empty() {
            return Err(AppError::EmptyBatch("the batch has no frames".into()));
        }
        let lock = self.trip_locks.of(id);
        let _order = lock.lock().await;
        let frames = std::sync::Arc::new(frames);
        let scope = IdempotencyRecord::trip_scope(id);
        let mut attempt = 0;
        loop {
            if let Some(key) = &idempotency {
                let stored = self.store.idempotency_record(&scope, key.key()).await?;
                if let Some(record) = key.replay(stored)? {
                    return self.replayed_frames(id, &record, caller).await;
                }
            }
            let keyed = idempotency.as_ref().map(|k| (k, scope.clone()));
            match self
                .apply_batch(id, std::sync::Arc::clone(&frames), keyed, caller)
                .await
            {
                Err(AppError::TripConflict(why)) if attempt < CONFLICT_RETRIES => {
                    attempt += 1;
                    tracing::info!(trip = %format!("{id:016x}"), attempt, %why, "trip changed meanwhile; recomputing the batch");
                }
                done @ (Ok(_) | Err(_)) => return done,
            }
        }
    }

    /// The stored answer of an applied batch, with the trip as it is now.
    async fn replayed_frames(
        &self,
        id: u64,
        record: &IdempotencyRecord,
        caller: Option<&Caller>,
    ) -> AppResult<FramesOutcome> {
        let (frame_count, update, hidden_cost) = idempotency::decode_frames(&record.response)?;
        let mut trip = self.store.get_trip(id).await?;
        Caller::may_change(caller, &trip)?;
        trip.frame_count = frame_count;
        tracing::info!(trip = %format!("{id:016x}"), key = %record.key, "idempotent retry answered from the stored batch");
        Ok(FramesOutcome {
            trip,
            update,
            hidden_cost,
            timings: FramesTimings::default(),
            replayed: true,
        })
    }

    async fn apply_batch(
        &self,
        id: u64,
        frames: std::sync::Arc<Vec<ImageInput>>,
        idempotency: Option<(&Idempotency, String)>,
        caller: Option<&Caller>,
    ) -> AppResult<FramesOutcome> {
        let started = Instant::now();
        let mut record = self.store.get_trip(id).await?;
        Caller::may_change(caller, &record)?;
        if record.closed_ms.is_some() {
            return Err(AppError::Store(StoreError::TripClosed(id)));
        }
        // The common path: this process applied the trip's previous batch.
        let cached = self.open_trips.take(id, record.frame_count);
        let stored = match cached {
            Some(_) => None,
            None => {
                let (fresh, state) = self.store.trip_state(id).await?;
                if fresh.closed_ms.is_some() {
                    return Err(AppError::Store(StoreError::TripClosed(id)));
                }
                record = fresh;
                Some(state)
            }
        };
        let map = self.get_map(record.map_id).await?;
        let source = kind::of(&map)
            .trip_rows(self, &map, record.reference_count)
            .await?;
        let max_pixels = self.config.max_image_pixels;
        let max_len = self.config.max_descriptor_len;
        let rules = self.model_rules();
        let frame_count = record.frame_count;
        // The request's span, for the stages' spans on the pool's thread.
        let parent = tracing::Span::current();
        let (update, live, delta, hidden_cost, mut timings) = self
            .pool
            .run(move || {
                let mut trip = match (cached, stored) {
                    (Some(trip), _) => trip,
                    (
                        None,
                        Some(TripState::Parts {
                            base,
                            snapshot,
                            log,
                        }),
                    ) => {
                        let log: Vec<(u64, &[u8])> =
                            log.iter().map(|(f, r)| (*f, &r[..])).collect();
                        Trip::restore(&base, &snapshot, &log, frame_count)?
                    }
                    (None, Some(TripState::Legacy(bytes))) => Trip::from_legacy_bytes(&bytes)?,
                    (None, None) => {
                        return Err(AppError::Internal("a trip with no state to use".into()))
                    }
                };
                let load = started.elapsed().as_secs_f64();
                let t = Instant::now();
                let c = match &source {
                    RowSource::Descriptors(references) => {
                        let describe = tracing::info_span!(parent: &parent, "describe").entered();
                        let Some(extractor) = map_extractor(&map, &rules)? else {
                            return Err(AppError::MapKind(format!(
                                "map `{:016x}` cannot describe images",
                                map.id
                            )));
                        };
                        let queries = images::describe(
                            extractor.as_ref(),
                            &frames,
                            max_pixels,
                            max_len,
                            map.dim,
                        )?;
                        drop(describe);
                        let _similarity =
                            tracing::info_span!(parent: &parent, "similarity").entered();
                        similarity::cosine_matrix_normalized(&queries, references)?
                    }
                    RowSource::Cooc(cooc) => {
                        let _describe =
                            tracing::info_span!(parent: &parent, "describe", kind = "cooc")
                                .entered();
                        RowSource::cooc_rows(cooc, &frames, max_pixels)?
                    }
                };
                // Features and scores for cooc maps (their rows come from the images at once).
                let features = t.elapsed().as_secs_f64();
                let t = Instant::now();
                // The online solve and the confidence of each estimate.
                let solve_span = tracing::info_span!(parent: &parent, "solve").entered();
                let update = trip.push_batch(&c)?;
                let hidden_cost = trip.hidden_cost().ok_or_else(|| {
                    AppError::Internal("the first batch did not resolve the hidden cost".into())
                })?;
                let delta = trip.take_delta();
                drop(solve_span);
                let solve = t.elapsed().as_secs_f64();
                let timings = FramesTimings {
                    load,
                    features,
                    solve,
                    store: 0.0,
                };
                Ok((update, trip, delta, hidden_cost, timings))
            })
            .await?;
        let estimates: Vec<FrameEstimate> = update
            .window
            .iter()
            .chain(&update.estimates)
            .copied()
            .collect();
        let frame_count = record.frame_count + update.estimates.len() as u64;
        let state = TripStateWrite {
            base: delta.base,
            snapshot: delta.snapshot,
            log: delta.log,
            drop_log_before: delta.drop_log_before,
        };
        let idempotency = match idempotency {
            Some((key, scope)) => Some(key.record(
                scope,
                idempotency::encode_frames(frame_count, &update, hidden_cost)?,
            )),
            None => None,
        };
        let batch = TripBatch {
            expected_frames: record.frame_count,
            frame_count,
            status: update.status,
            state,
            estimates,
            idempotency,
        };
        let t = Instant::now();
        let trip = match self.store.put_trip_batch(id, batch).await {
            Ok(r) => r,
            // Another process applied a batch (maybe this one, under the same key) meanwhile:
            // recompute, or replay what it stored.
            Err(e @ (StoreError::TripConflict { .. } | StoreError::IdempotencyKeyTaken { .. })) => {
                return Err(AppError::TripConflict(e.to_string()))
            }
            Err(e) => return Err(e.into()),
        };
        timings.store = t.elapsed().as_secs_f64();
        // The store holds what `trip` holds now: keep it for the trip's next batch.
        self.open_trips.keep(id, live);
        tracing::debug!(trip = %format!("{id:016x}"), frames = trip.frame_count, "batch applied");
        Ok(FramesOutcome {
            trip,
            update,
            hidden_cost,
            timings,
            replayed: false,
        })
    }

    /// Closes trip `id` (after a batch in flight in this process); closing twice is harmless.
    /// Only the key that opened it or an admin may ([`Caller::may_change`]).
    pub async fn close_trip(&self, id: u64, caller: Option<&Caller>) -> AppResult<TripRecord> {
        let lock = self.trip_locks.of(id);
        let _order = lock.lock().await;
        Caller::may_change(caller, &self.store.get_trip(id).await?)?;
        let record = self.store.close_trip(id).await?;
        self.open_trips.forget(id);
        tracing::info!(trip = %format!("{id:016x}"), "trip closed");
        Ok(record)
    }

    /// A trip and the latest estimate of every frame from `since` on (0: all of them). A live
    /// view polls with `since` = the frames it has minus the lag window, since estimates in
    /// the window may still be revised.
    pub async fn get_trip(
        &self,
        id: u64,
        since: u32,
    ) -> AppResult<(TripRecord, Vec<FrameEstimate>)> {
        let record = self.store.get_trip(id).await?;
        let estimates = self.store.trip_estimates(id, since).await?;
        Ok((record, estimates))
    }

    /// Open trips of every map by the status of their last batch, read from the store (so
    /// every replica of a shared store counts the same trips). Pages through all trips: for
    /// a metrics scrape, not a request path.
    pub async fn open_trip_counts(&self) -> AppResult<OpenTripCounts> {
        let mut counts = OpenTripCounts::default();
        for map in self.store.list_maps().await? {
            let mut before = None;
            loop {
                let page = match self
                    .store
                    .list_trips(map.id, PageRequest { before, limit: 500 })
                    .await
                {
                    Ok(page) => page,
                    // Deleted between the two calls.
                    Err(StoreError::MapNotFound(_)) => break,
                    Err(e) => return Err(e.into()),
                };
                for t in page.items.iter().filter(|t| t.closed_ms.is_none()) {
                    match t.status {
                        None => counts.new += 1,
                        Some(TripStatus::Localized) => counts.localized += 1,
                        Some(TripStatus::Lost) => counts.lost += 1,
                        Some(TripStatus::Relocalized) => counts.relocalized += 1,
                    }
                }
                match page.next {
                    Some(next) => before = Some(next),
                    None => break,
                }
            }
        }
        Ok(counts)
    }

    /// Maps whose descriptors this process caches, and the bytes of their matrices, by
    /// descriptor kind (`hog`, `cnn`, `precomputed`).
    pub fn descriptor_cache_usage(
        &self,
    ) -> std::collections::BTreeMap<&'static str, (usize, usize)> {
        self.references.usage()
    }

    /// A page of map `id`'s trips, newest first.
    pub async fn list_trips(&self, id: u64, page: PageRequest) -> AppResult<Page<TripRecord>> {
        Ok(self.store.list_trips(id, page).await?)
    }
}
