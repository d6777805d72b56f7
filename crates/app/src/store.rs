//! The service's storage port: the [`Store`] trait, the writes it takes and its one error
//! type. The engines implement it in `seasonloc-store` (sled, the embedded default;
//! PostgreSQL, shared by any number of replicas); the use cases ([`crate::App`]) hold an
//! `Arc<dyn Store>` and are its only caller.
//!
//! The trait is shaped for engines shared by many processes at once (a PostgreSQL database
//! behind several replicas), not only for the embedded one:
//!
//! * **Every write that spans several records is atomic** (a batch of images and the map's new
//!   `image_count`; a localization and its index entry; a trip batch's state, record and
//!   estimates; a map and everything under it), and **durable before the call returns**.
//! * **Writes that depend on what was read are conditional**: a trip batch names the frame
//!   count it was computed after ([`TripBatch::expected_frames`]), a co-occurrence map the bytes
//!   it replaces ([`CoocWrite::previous`]); a stale write fails with
//!   [`StoreError::TripConflict`] / [`StoreError::Conflict`] and changes nothing, so two
//!   replicas can never both apply a batch computed from one state.
//! * **Ids are chosen by the caller** (`NewMap::id`, `NewLocalization::id`, `NewTrip::id`:
//!   the use-case layer's random, time-ordered ids, see `crate::ids`); an engine stores a
//!   new object under exactly that id, or fails with [`StoreError::IdTaken`] and writes nothing
//!   when the id exists. Ids grow with creation time, so listings can go newest first.
//! * **A map's descriptors are versioned by its `image_count`**: images are append-only, rows
//!   `0..image_count` never change, so a reader that caches a map's matrix checks the map's
//!   current count ([`Store::get_map`]) and reads only the new rows ([`Store::descriptors`]).
//! * **Listings are cursor-paginated** ([`PageRequest`] / [`Page`]: newest first, `before` an
//!   exclusive id).
//! * **No engine type appears in a signature**; failures are [`StoreError`], whose
//!   [`StoreError::Unavailable`] means "the engine cannot be reached now" (the API answers 503)
//!   and every other engine failure is [`StoreError::Backend`] or [`StoreError::Corrupt`].
//!
//! What the store keeps is the domain model ([`crate::model`]); the engines (in
//! `seasonloc-store`) encode it, the API converts it to its own wire types, so a wire change
//! cannot silently change stored data.

// Request paths must not panic: no `unwrap` outside tests (clippy.toml allows it there), and a
// new enum variant must be handled explicitly rather than fall into `_` (CI denies warnings).
#![warn(clippy::unwrap_used, clippy::wildcard_enum_match_arm)]

use std::ops::Range;

use async_trait::async_trait;

use crate::model::{
    DescriptorSettings, ImageMeta, LocalizationRecord, LocalizationResult, MapRecord, TripRecord,
};
use seasonloc_core::trip::{FrameEstimate, TripParams, TripStatus};
use seasonloc_core::Matrix;

/// A boxed engine error, kept as the source of [`StoreError::Backend`] and
/// [`StoreError::Open`] without naming the engine's type.
pub type BoxError = Box<dyn std::error::Error + Send + Sync + 'static>;

/// Errors of the store layer (every engine).
#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    /// The store could not be opened (e.g. a data folder locked by another process).
    #[error("cannot open the store at {location}: {source}")]
    Open {
        /// Where the store is (a folder, or a database address without credentials).
        location: String,
        /// The engine's error.
        #[source]
        source: BoxError,
    },
    /// The engine cannot be reached right now (connection refused, pool exhausted, shutting
    /// down); retrying later may succeed. The API answers 503.
    #[error("the store is unavailable: {0}")]
    Unavailable(String),
    /// A read or write failed inside the engine.
    #[error("store I/O: {0}")]
    Backend(#[source] BoxError),
    /// A write found no space left on the store's disk (or a quota reached); nothing was
    /// acknowledged. The store stays readable and takes writes again once space is freed,
    /// without a restart. The API answers 507 `storage_full`.
    #[error("no space left for the store: {0}")]
    StorageFull(String),
    /// The store's files are damaged (truncated, rolled back to an older state, or unreadable
    /// in places): it is refused at start rather than served with data silently missing.
    #[error(
        "the store at {location} is damaged and was not opened: {reason}. Restore the data \
         folder from a backup, or see docs/operations.md (damaged embedded store) to repair it"
    )]
    Damaged {
        /// The data folder.
        location: String,
        /// What the start-up check found.
        reason: String,
    },
    /// A stored value could not be decoded.
    #[error("corrupt record at key {key}: {reason}")]
    Corrupt {
        /// The record's key, hex-encoded.
        key: String,
        /// What is wrong with the value.
        reason: String,
    },
    /// The store was written by a layout this build does not know.
    #[error("store layout version {found} is not supported (this build knows up to {supported})")]
    UnsupportedSchema {
        /// Version found in the store.
        found: u32,
        /// Newest version this build knows.
        supported: u32,
    },
    /// No map with this id.
    #[error("map `{0:016x}` does not exist")]
    MapNotFound(u64),
    /// No localization with this id.
    #[error("localization `{0:016x}` does not exist")]
    LocalizationNotFound(u64),
    /// Descriptors of a batch do not have the map's descriptor length.
    #[error(
        "descriptors have length {got}, map {map:016x} stores descriptors of length {expected}"
    )]
    DimensionMismatch {
        /// The map.
        map: u64,
        /// The map's descriptor length.
        expected: u32,
        /// The batch's descriptor length.
        got: usize,
    },
    /// A co-occurrence map changed between reading and writing it (a concurrent write).
    #[error("map {0:016x} was changed by another request; retry")]
    Conflict(u64),
    /// No trip with this id.
    #[error("trip `{0:016x}` does not exist")]
    TripNotFound(u64),
    /// The trip was closed; it accepts no more frames.
    #[error("trip `{0:016x}` is closed; open a new trip")]
    TripClosed(u64),
    /// A batch was computed from a state that is no longer the stored one.
    #[error("trip {id:016x} has {stored} frames, the batch was computed after {expected}")]
    TripConflict {
        /// The trip.
        id: u64,
        /// Frames stored.
        stored: u64,
        /// Frames the batch assumed.
        expected: u64,
    },
    /// A new object was given an id that another object of its kind already has (two
    /// processes drew the same random id); nothing was written, the caller draws another.
    #[error("id {0:016x} is taken")]
    IdTaken(u64),
    /// A map cannot grow further (more than `u32::MAX` images).
    #[error("map `{0:016x}` cannot hold more images")]
    MapFull(u64),
    /// A write carried an [`IdempotencyRecord`] whose key another write stored first (a
    /// concurrent retry): nothing was written; read the stored record and answer from it.
    #[error("idempotency key `{key}` of {scope} was used meanwhile")]
    IdempotencyKeyTaken {
        /// The key's scope.
        scope: String,
        /// The key.
        key: String,
    },
}

impl StoreError {
    /// The code of this error in the one table ([`crate::ErrorCode`]): what a client can act
    /// on keeps its own code; every failure of the engine itself is `internal`, except an
    /// engine that cannot be reached now (`not_ready`, retry later).
    pub fn code(&self) -> crate::ErrorCode {
        use crate::ErrorCode as C;
        match self {
            StoreError::MapNotFound(_) => C::MapNotFound,
            StoreError::LocalizationNotFound(_) => C::LocalizationNotFound,
            StoreError::TripNotFound(_) => C::TripNotFound,
            StoreError::TripClosed(_) => C::TripClosed,
            StoreError::TripConflict { .. } => C::TripConflict,
            StoreError::MapFull(_) => C::MapFull,
            StoreError::DimensionMismatch { .. } => C::DescriptorLength,
            StoreError::Conflict(_) | StoreError::IdempotencyKeyTaken { .. } => C::MapChanged,
            StoreError::Unavailable(_) => C::NotReady,
            StoreError::StorageFull(_) => C::StorageFull,
            StoreError::Open { .. }
            | StoreError::Damaged { .. }
            | StoreError::IdTaken(_)
            | StoreError::Backend(_)
            | StoreError::Corrupt { .. }
            | StoreError::UnsupportedSchema { .. } => C::Internal,
        }
    }

    /// [`StoreError::Corrupt`] for the record under `key`.
    pub fn corrupt(key: &[u8], reason: impl Into<String>) -> Self {
        StoreError::Corrupt {
            key: key.iter().map(|b| format!("{b:02x}")).collect(),
            reason: reason.into(),
        }
    }
}

/// Result alias of the store layer.
pub type StoreResult<T> = Result<T, StoreError>;

/// What a client gives to create a map.
#[derive(Clone, Debug, PartialEq)]
pub struct NewMap {
    /// The new map's id (must not exist yet).
    pub id: u64,
    /// User-given name.
    pub name: String,
    /// Validated descriptor settings.
    pub descriptor: DescriptorSettings,
    /// Stored in the same write, when the request had an idempotency key (scope
    /// [`IdempotencyRecord::maps_scope`], its response the map's id); fails with
    /// [`StoreError::IdempotencyKeyTaken`] when the key is stored already. Deleting the map
    /// deletes it.
    pub idempotency: Option<IdempotencyRecord>,
}

/// What a request sent with an `Idempotency-Key` did (decision D5), stored in the same atomic
/// write as the change itself, so that a retry — on any replica, after a crash of the first —
/// finds either both or neither.
#[derive(Clone, Debug, PartialEq)]
pub struct IdempotencyRecord {
    /// What the key is scoped to ([`IdempotencyRecord::trip_scope`],
    /// [`IdempotencyRecord::images_scope`]); the map or trip it names owns the record (deleting
    /// the map deletes it).
    pub scope: String,
    /// The client's key.
    pub key: String,
    /// A hash of the request; a retry with another one is refused.
    pub fingerprint: Vec<u8>,
    /// The answer to replay, opaque to the store (encoded by the use-case layer).
    pub response: Vec<u8>,
    /// For image appends: the indices the write gave the images (set by the engine when it
    /// writes; `None` otherwise).
    pub indices: Option<Range<u32>>,
}

impl IdempotencyRecord {
    /// The scope of the keys of trip `id`'s batches.
    pub fn trip_scope(id: u64) -> String {
        format!("trip/{id:016x}/frames")
    }

    /// The scope of the keys of map creations (their response is the new map's id, 8 bytes
    /// little-endian).
    pub fn maps_scope() -> String {
        "maps".to_string()
    }

    /// The scope of the keys of map `id`'s appends (images, descriptors, drives) and of the
    /// trips opened on it.
    pub fn images_scope(id: u64) -> String {
        format!("map/{id:016x}/images")
    }
}

/// A batch of reference images for [`Store::append_images`]: one metadata entry per
/// descriptor row (checked by [`ImageBatch::new`]), and optionally one JPEG thumbnail per row
/// ([`ImageBatch::with_thumbnails`]; precomputed descriptors come without images).
#[derive(Clone, Debug, PartialEq)]
pub struct ImageBatch {
    map: u64,
    descriptors: Matrix,
    metas: Vec<ImageMeta>,
    geometry: Option<(u32, u32)>,
    thumbnails: Vec<Vec<u8>>,
    idempotency: Option<IdempotencyRecord>,
}

impl ImageBatch {
    /// A batch for `map`: one descriptor row per image in route order, one metadata entry per
    /// row ([`seasonloc_core::Error::Shape`] otherwise).
    pub fn new(
        map: u64,
        descriptors: Matrix,
        metas: Vec<ImageMeta>,
    ) -> seasonloc_core::Result<Self> {
        if descriptors.rows() != metas.len() {
            return Err(seasonloc_core::Error::Shape(format!(
                "{} metadata entries for {} descriptor rows",
                metas.len(),
                descriptors.rows()
            )));
        }
        Ok(ImageBatch {
            map,
            descriptors,
            metas,
            thumbnails: Vec::new(),
            idempotency: None,
            geometry: None,
        })
    }

    /// The same batch with one JPEG thumbnail per row (`seasonloc_core::picture::thumbnail_jpeg`),
    /// stored in the same atomic write ([`seasonloc_core::Error::Shape`] when the count differs).
    pub fn with_thumbnails(mut self, thumbnails: Vec<Vec<u8>>) -> seasonloc_core::Result<Self> {
        if thumbnails.len() != self.descriptors.rows() {
            return Err(seasonloc_core::Error::Shape(format!(
                "{} thumbnails for {} descriptor rows",
                thumbnails.len(),
                self.descriptors.rows()
            )));
        }
        self.thumbnails = thumbnails;
        Ok(self)
    }

    /// The batch, stored together with `record` (whose `indices` the engine sets); the write
    /// fails with [`StoreError::IdempotencyKeyTaken`] when the key is stored already.
    pub fn with_idempotency(mut self, record: Option<IdempotencyRecord>) -> Self {
        self.idempotency = record;
        self
    }

    /// The idempotency record to store with the batch.
    pub fn idempotency(&self) -> Option<&IdempotencyRecord> {
        self.idempotency.as_ref()
    }

    /// The input geometry `(width, height)` of a HOG map's first batch (the size of its first
    /// image, `features::geometry`): the store records it as the map's `resize` when the batch
    /// is the map's first and the map has none, so that later images of any size are brought
    /// to it. Ignored otherwise.
    pub fn with_geometry(mut self, geometry: Option<(u32, u32)>) -> Self {
        self.geometry = geometry;
        self
    }

    /// See [`ImageBatch::with_geometry`].
    pub fn geometry(&self) -> Option<(u32, u32)> {
        self.geometry
    }

    /// The map.
    pub fn map(&self) -> u64 {
        self.map
    }

    /// The descriptor rows.
    pub fn descriptors(&self) -> &Matrix {
        &self.descriptors
    }

    /// The metadata, one entry per row.
    pub fn metas(&self) -> &[ImageMeta] {
        &self.metas
    }

    /// The thumbnails, one per row, or none at all.
    pub fn thumbnails(&self) -> &[Vec<u8>] {
        &self.thumbnails
    }
}

/// A replacement of a co-occurrence map for [`Store::put_cooc_map`].
#[derive(Clone, Debug, PartialEq)]
pub struct CoocWrite {
    /// The map.
    pub map: u64,
    /// The encoded map this one was computed from (`None`: there was none yet). The write
    /// fails with [`StoreError::Conflict`] when the stored bytes differ.
    pub previous: Option<Vec<u8>>,
    /// The new encoded map (`CoocMap::to_bytes`), opaque to the store.
    pub encoded: Vec<u8>,
    /// Metadata of the reference images the write adds (no descriptor rows).
    pub new_images: Vec<ImageMeta>,
    /// Stored in the same write (its `indices` set by the engine), when the request had a key.
    pub idempotency: Option<IdempotencyRecord>,
}

/// A result to store with [`Store::create_localization`].
#[derive(Clone, Debug, PartialEq)]
pub struct NewLocalization {
    /// The new result's id (must not exist yet).
    pub id: u64,
    /// The map it was computed against (must exist).
    pub map_id: u64,
    /// The result; the engine adds the id, map id and creation time to its document.
    pub result: LocalizationResult,
    /// The PNG of the similarity-matrix picture that `result.picture` describes, stored in
    /// the same atomic write (`None` when the result has no picture).
    pub picture: Option<Vec<u8>>,
    /// Stored in the same write, when the request had an idempotency key (its response is the
    /// result's id); fails with [`StoreError::IdempotencyKeyTaken`] when the key is stored
    /// already.
    pub idempotency: Option<IdempotencyRecord>,
}

/// A trip to open with [`Store::create_trip`].
#[derive(Clone, Debug, PartialEq)]
pub struct NewTrip {
    /// The new trip's id (must not exist yet).
    pub id: u64,
    /// The map (must exist).
    pub map_id: u64,
    /// The map's image count the trip localizes against.
    pub reference_count: u32,
    /// Its parameters.
    pub params: TripParams,
    /// The name of the API key that opens it (see [`TripRecord::owner`]).
    pub owner: Option<String>,
    /// Its initial state's constant part (opaque bytes owned by `seasonloc_core::trip`).
    pub base: Vec<u8>,
    /// Its initial snapshot (opaque bytes owned by `seasonloc_core::trip`); the log starts empty.
    pub snapshot: Vec<u8>,
    /// Stored in the same write, when the request had an idempotency key (its response names
    /// the trip); fails with [`StoreError::IdempotencyKeyTaken`] when the key is stored already.
    pub idempotency: Option<IdempotencyRecord>,
}

/// A trip's solver state as stored: opaque parts owned by `seasonloc_core::trip` (`trip::persist`).
#[derive(Clone, Debug, PartialEq)]
pub enum TripState {
    /// The parts this version writes: the constant base, the latest snapshot and the log
    /// rows after it, `(frame, bytes)` in frame order.
    Parts {
        /// Written at open, never changed.
        base: Vec<u8>,
        /// The latest snapshot.
        snapshot: Vec<u8>,
        /// The log rows from the snapshot's frame on.
        log: Vec<(u64, Vec<u8>)>,
    },
    /// One blob written by an earlier version (sled layout 4-5, PostgreSQL schema 1-3),
    /// replaced by parts when the trip's next batch writes a base.
    Legacy(Vec<u8>),
}

/// What one batch changes in a trip's stored state ([`TripState::Parts`]): written in the
/// same atomic write as the batch's record, estimates and idempotency record.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct TripStateWrite {
    /// A base to store; replaces a [`TripState::Legacy`] blob.
    pub base: Option<Vec<u8>>,
    /// A snapshot replacing the stored one.
    pub snapshot: Option<Vec<u8>>,
    /// Log rows to add, `(frame, bytes)`.
    pub log: Vec<(u64, Vec<u8>)>,
    /// Drop the log rows of frames below this one.
    pub drop_log_before: Option<u64>,
}

impl TripStateWrite {
    /// Bytes of state this write stores (base, snapshot, log rows).
    pub fn bytes(&self) -> usize {
        self.base.as_ref().map_or(0, Vec::len)
            + self.snapshot.as_ref().map_or(0, Vec::len)
            + self.log.iter().map(|(_, r)| r.len()).sum::<usize>()
    }
}

/// What one batch of frames changes, written with [`Store::put_trip_batch`].
#[derive(Clone, Debug, PartialEq)]
pub struct TripBatch {
    /// Frames the batch was computed after: the write applies only if the stored
    /// `frame_count` still equals it (compare-and-swap on the state's version).
    pub expected_frames: u64,
    /// Frames after the batch.
    pub frame_count: u64,
    /// Status after the batch.
    pub status: TripStatus,
    /// The change of the solver state (a delta: new log rows, sometimes a snapshot).
    pub state: TripStateWrite,
    /// New or revised estimates (the batch's frames and the re-traced lag window).
    pub estimates: Vec<FrameEstimate>,
    /// Stored in the same write, when the request had an idempotency key.
    pub idempotency: Option<IdempotencyRecord>,
}

/// Which page of a listing to read: records with ids below `before` (all when `None`), at
/// most `limit` of them, newest first.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct PageRequest {
    /// Exclusive upper bound on ids: the previous page's [`Page::next`].
    pub before: Option<u64>,
    /// Most records returned (at least 1).
    pub limit: usize,
}

/// One page of a listing, newest first.
#[derive(Clone, Debug, PartialEq)]
pub struct Page<T> {
    /// Records, newest first.
    pub items: Vec<T>,
    /// Pass as `before` to get the next page; `None` on the last page.
    pub next: Option<u64>,
}

/// A storage engine of the service. Object-safe: the use-case layer holds an
/// `Arc<dyn Store>`. Every method is async and never blocks the calling task (an embedded
/// engine runs its I/O on blocking threads). See the module doc for the rules every engine
/// keeps (atomic, durable, conditional writes; caller-chosen ids; versioned descriptors).
#[async_trait]
pub trait Store: Send + Sync + 'static {
    /// Where the data lives, for logs (a folder, or a database address without credentials).
    fn location(&self) -> String;

    /// Checks that the store answers reads (for `/readyz`).
    async fn check(&self) -> StoreResult<()>;

    /// Makes everything durable (at shutdown; every acknowledged write already is).
    async fn flush(&self) -> StoreResult<()>;

    /// Creates an empty map under `new.id` and returns it ([`StoreError::IdTaken`] when a map
    /// has that id).
    async fn create_map(&self, new: NewMap) -> StoreResult<MapRecord>;

    /// One map.
    async fn get_map(&self, id: u64) -> StoreResult<MapRecord>;

    /// All maps, oldest first.
    async fn list_maps(&self) -> StoreResult<Vec<MapRecord>>;

    /// Deletes a map with its images, co-occurrence map, localizations and trips, atomically.
    async fn delete_map(&self, id: u64) -> StoreResult<()>;

    /// Appends one descriptor row per image (in route order) with its metadata and raises the
    /// map's `image_count`, atomically. Returns the indices given to the rows. Fails without
    /// writing when the map is gone, full, or the length differs from the map's.
    async fn append_images(&self, batch: ImageBatch) -> StoreResult<Range<u32>>;

    /// Descriptor rows `rows` of a map (`rows.end` at most its `image_count`), one per image
    /// in route order, of the map's descriptor length.
    async fn descriptors(&self, map: u64, rows: Range<u32>) -> StoreResult<Matrix>;

    /// Metadata of the images `rows` of a map, in order.
    async fn image_metadata(&self, map: u64, rows: Range<u32>) -> StoreResult<Vec<ImageMeta>>;

    /// The JPEG thumbnail of image `index` of a map, `None` when it has none (stored before
    /// thumbnails existed, precomputed descriptors, or no such image). Fails with
    /// [`StoreError::MapNotFound`] when the map is gone.
    async fn thumbnail(&self, map: u64, index: u32) -> StoreResult<Option<Vec<u8>>>;

    /// The encoded co-occurrence map of `map`, `None` before its first images.
    async fn cooc_map(&self, map: u64) -> StoreResult<Option<Vec<u8>>>;

    /// Replaces the encoded co-occurrence map if the stored one still equals
    /// [`CoocWrite::previous`], and appends its new (descriptor-less) images, atomically.
    /// Returns the indices of the new images.
    async fn put_cooc_map(&self, write: CoocWrite) -> StoreResult<Range<u32>>;

    /// Stores a localization result under `new.id`, atomically with its index entry. Fails
    /// with [`StoreError::MapNotFound`] when the map is gone, [`StoreError::IdTaken`] when a
    /// result has that id.
    async fn create_localization(&self, new: NewLocalization) -> StoreResult<LocalizationRecord>;

    /// One stored result.
    async fn get_localization(&self, id: u64) -> StoreResult<LocalizationRecord>;

    /// The PNG of a stored result's similarity-matrix picture, `None` when it has none.
    /// Fails with [`StoreError::LocalizationNotFound`] when the result is gone.
    async fn localization_picture(&self, id: u64) -> StoreResult<Option<Vec<u8>>>;

    /// A page of results, newest first; only `map`'s when given (which must exist).
    async fn list_localizations(
        &self,
        map: Option<u64>,
        page: PageRequest,
    ) -> StoreResult<Page<LocalizationRecord>>;

    /// Opens a trip under `new.id` with its initial state; fails when the map is gone or a
    /// trip has that id ([`StoreError::IdTaken`]).
    async fn create_trip(&self, new: NewTrip) -> StoreResult<TripRecord>;

    /// One trip's record.
    async fn get_trip(&self, id: u64) -> StoreResult<TripRecord>;

    /// A trip's record and solver state, read consistently (one point in time: the log
    /// rows are those after the snapshot, up to the record's `frame_count`).
    async fn trip_state(&self, id: u64) -> StoreResult<(TripRecord, TripState)>;

    /// Applies one batch: record, state delta and estimates in one atomic write, only if the trip
    /// is open and its `frame_count` still equals [`TripBatch::expected_frames`]
    /// ([`StoreError::TripClosed`] / [`StoreError::TripConflict`] otherwise, writing nothing).
    async fn put_trip_batch(&self, id: u64, batch: TripBatch) -> StoreResult<TripRecord>;

    /// Closes a trip (idempotent: closing twice keeps the first time).
    async fn close_trip(&self, id: u64) -> StoreResult<TripRecord>;

    /// The latest estimate of every frame from `from` on, in frame order (`from` 0: all).
    async fn trip_estimates(&self, id: u64, from: u32) -> StoreResult<Vec<FrameEstimate>>;

    /// A page of `map`'s trips, newest first (the map must exist).
    async fn list_trips(&self, map: u64, page: PageRequest) -> StoreResult<Page<TripRecord>>;

    /// The record stored under an idempotency key, if any.
    async fn idempotency_record(
        &self,
        scope: &str,
        key: &str,
    ) -> StoreResult<Option<IdempotencyRecord>>;
}

/// The end of `rows` images appended to a map at index `start`, or [`StoreError::MapFull`] when
/// it does not fit a `u32` index (both engines).
pub fn append_end(map: u64, start: u32, rows: usize) -> StoreResult<u32> {
    u32::try_from(rows)
        .ok()
        .and_then(|n| start.checked_add(n))
        .ok_or(StoreError::MapFull(map))
}

/// Milliseconds since the Unix epoch (0 if the clock is before it).
pub fn now_ms() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| u64::try_from(d.as_millis()).unwrap_or(u64::MAX))
}
