//! A [`Store`] that times every call of the engine it wraps and reports it to a
//! [`StoreObserver`] (the service's metrics: store latency by operation), each call in a
//! `store` span with its `operation` (a child of the request's span in a trace).
//! Engine-neutral: it wraps either engine behind the one trait, and changes nothing of what a
//! call does.

use std::ops::Range;
use std::sync::Arc;
use std::time::Instant;

use async_trait::async_trait;

use crate::model::{ImageMeta, LocalizationRecord, MapRecord, TripRecord};
use crate::store::{
    CoocWrite, IdempotencyRecord, ImageBatch, NewLocalization, NewMap, NewTrip, Page, PageRequest,
    Store, StoreResult, TripBatch, TripState,
};
use seasonloc_core::trip::FrameEstimate;
use seasonloc_core::Matrix;

/// Receives the duration of each store call.
pub trait StoreObserver: Send + Sync + 'static {
    /// One call of `operation` (the [`Store`] method's name) took `seconds`; `ok` says whether
    /// it succeeded.
    fn store_call(&self, operation: &'static str, seconds: f64, ok: bool);
}

/// `inner`, timed.
pub struct TimedStore {
    inner: Arc<dyn Store>,
    observer: Arc<dyn StoreObserver>,
}

impl TimedStore {
    /// Wraps `inner`, reporting to `observer`.
    pub fn new(inner: Arc<dyn Store>, observer: Arc<dyn StoreObserver>) -> TimedStore {
        TimedStore { inner, observer }
    }
}

macro_rules! timed {
    ($self:ident, $op:literal, $call:expr) => {{
        let started = Instant::now();
        let span = tracing::info_span!("store", operation = $op);
        let out = tracing::Instrument::instrument($call, span).await;
        $self
            .observer
            .store_call($op, started.elapsed().as_secs_f64(), out.is_ok());
        out
    }};
}

#[async_trait]
impl Store for TimedStore {
    fn location(&self) -> String {
        self.inner.location()
    }

    async fn check(&self) -> StoreResult<()> {
        timed!(self, "check", self.inner.check())
    }

    async fn flush(&self) -> StoreResult<()> {
        timed!(self, "flush", self.inner.flush())
    }

    async fn create_map(&self, new: NewMap) -> StoreResult<MapRecord> {
        timed!(self, "create_map", self.inner.create_map(new))
    }

    async fn get_map(&self, id: u64) -> StoreResult<MapRecord> {
        timed!(self, "get_map", self.inner.get_map(id))
    }

    async fn list_maps(&self) -> StoreResult<Vec<MapRecord>> {
        timed!(self, "list_maps", self.inner.list_maps())
    }

    async fn delete_map(&self, id: u64) -> StoreResult<()> {
        timed!(self, "delete_map", self.inner.delete_map(id))
    }

    async fn append_images(&self, batch: ImageBatch) -> StoreResult<Range<u32>> {
        timed!(self, "append_images", self.inner.append_images(batch))
    }

    async fn descriptors(&self, map: u64, rows: Range<u32>) -> StoreResult<Matrix> {
        timed!(self, "descriptors", self.inner.descriptors(map, rows))
    }

    async fn image_metadata(&self, map: u64, rows: Range<u32>) -> StoreResult<Vec<ImageMeta>> {
        timed!(self, "image_metadata", self.inner.image_metadata(map, rows))
    }

    async fn thumbnail(&self, map: u64, index: u32) -> StoreResult<Option<Vec<u8>>> {
        timed!(self, "thumbnail", self.inner.thumbnail(map, index))
    }

    async fn cooc_map(&self, map: u64) -> StoreResult<Option<Vec<u8>>> {
        timed!(self, "cooc_map", self.inner.cooc_map(map))
    }

    async fn put_cooc_map(&self, write: CoocWrite) -> StoreResult<Range<u32>> {
        timed!(self, "put_cooc_map", self.inner.put_cooc_map(write))
    }

    async fn create_localization(&self, new: NewLocalization) -> StoreResult<LocalizationRecord> {
        timed!(
            self,
            "create_localization",
            self.inner.create_localization(new)
        )
    }

    async fn get_localization(&self, id: u64) -> StoreResult<LocalizationRecord> {
        timed!(self, "get_localization", self.inner.get_localization(id))
    }

    async fn localization_picture(&self, id: u64) -> StoreResult<Option<Vec<u8>>> {
        timed!(
            self,
            "localization_picture",
            self.inner.localization_picture(id)
        )
    }

    async fn list_localizations(
        &self,
        map: Option<u64>,
        page: PageRequest,
    ) -> StoreResult<Page<LocalizationRecord>> {
        timed!(
            self,
            "list_localizations",
            self.inner.list_localizations(map, page)
        )
    }

    async fn create_trip(&self, new: NewTrip) -> StoreResult<TripRecord> {
        timed!(self, "create_trip", self.inner.create_trip(new))
    }

    async fn get_trip(&self, id: u64) -> StoreResult<TripRecord> {
        timed!(self, "get_trip", self.inner.get_trip(id))
    }

    async fn trip_state(&self, id: u64) -> StoreResult<(TripRecord, TripState)> {
        timed!(self, "trip_state", self.inner.trip_state(id))
    }

    async fn put_trip_batch(&self, id: u64, batch: TripBatch) -> StoreResult<TripRecord> {
        timed!(self, "put_trip_batch", self.inner.put_trip_batch(id, batch))
    }

    async fn close_trip(&self, id: u64) -> StoreResult<TripRecord> {
        timed!(self, "close_trip", self.inner.close_trip(id))
    }

    async fn trip_estimates(&self, id: u64, from: u32) -> StoreResult<Vec<FrameEstimate>> {
        timed!(self, "trip_estimates", self.inner.trip_estimates(id, from))
    }

    async fn list_trips(&self, map: u64, page: PageRequest) -> StoreResult<Page<TripRecord>> {
        timed!(self, "list_trips", self.inner.list_trips(map, page))
    }

    async fn idempotency_record(
        &self,
        scope: &str,
        key: &str,
    ) -> StoreResult<Option<IdempotencyRecord>> {
        timed!(
            self,
            "idempotency_record",
            self.inner.idempotency_record(scope, key)
        )
    }
}
