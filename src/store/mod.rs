//! The embedded store of the service: maps, their reference descriptors in route order, and
//! stored localization results, in one sled database.
//!
//! Only this module knows sled. It owns the key layout ([`codec`]), the layout version and its
//! upgrades ([`migrate`]), and the write rules:
//!
//! * every change that spans several keys (a batch of images plus the map's `image_count`, a
//!   localization plus its index entry, a map and everything under it) is one `sled::Batch`,
//!   applied atomically, so a crash leaves either all of it or none of it;
//! * every write is flushed to disk before the call returns, so whatever the API acknowledged
//!   survives a crash;
//! * writes go through one mutex, so `image_count` read-modify-write cycles never interleave.
//!
//! Localization results are stored as opaque documents (bytes) chosen by the caller: the store
//! does not know the wire format.

pub mod codec;
mod cooc;
mod localizations;
mod maps;
pub mod migrate;
mod trips;

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex, MutexGuard};

use crate::Matrix;

pub use maps::NewMap;
pub use trips::{BatchWrite, TripPage};

/// Errors of the store layer.
#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    /// The database could not be opened (e.g. locked by another process).
    #[error("cannot open the store at {path}: {source}")]
    Open {
        /// The data folder.
        path: PathBuf,
        /// The underlying sled error.
        #[source]
        source: sled::Error,
    },
    /// A read or write failed.
    #[error("store I/O: {0}")]
    Sled(#[from] sled::Error),
    /// A stored value could not be decoded.
    #[error("corrupt record at key {key}: {reason}")]
    Corrupt {
        /// The key, hex-encoded.
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
    #[error("map {0:016x} does not exist")]
    MapNotFound(u64),
    /// No localization with this id.
    #[error("localization {0:016x} does not exist")]
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
    #[error("trip {0:016x} does not exist")]
    TripNotFound(u64),
    /// The trip was closed; it accepts no more frames.
    #[error("trip {0:016x} is closed")]
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
    /// A map cannot grow further (more than `u32::MAX` images).
    #[error("map {0:016x} is full")]
    MapFull(u64),
}

impl StoreError {
    pub(crate) fn corrupt(key: &[u8], reason: impl Into<String>) -> Self {
        StoreError::Corrupt {
            key: key.iter().map(|b| format!("{b:02x}")).collect(),
            reason: reason.into(),
        }
    }
}

/// Result alias of the store layer.
pub type StoreResult<T> = Result<T, StoreError>;

/// How a map's descriptors are computed.
#[derive(Clone, Debug, PartialEq)]
pub enum DescriptorSettings {
    /// HOG of `features::hog` with these options.
    Hog {
        /// Cell side in pixels.
        cell_size: u32,
        /// Optional resize before extraction.
        resize: Option<(u32, u32)>,
    },
    /// Descriptors computed by the client, of a fixed length.
    Precomputed {
        /// Descriptor length.
        dim: u32,
    },
    /// One layer of an ONNX model (`features::cnn`), with the identity of the model the map
    /// was created with (layout >= 3).
    Cnn(Box<CnnSettings>),
    /// A feature co-occurrence map (`cooc`) with these parameters (layout >= 3). Its images
    /// have no descriptor rows; the encoded `CoocMap` is stored under its own key.
    Cooc(Box<crate::cooc::CoocParams>),
}

/// The CNN descriptor of a map: the settings to rebuild the extractor, and what the model was
/// when the map was created, so that a changed model file is detected, never silently used.
#[derive(Clone, Debug, PartialEq)]
pub struct CnnSettings {
    /// Model path, layer and preprocessing.
    pub options: crate::features::cnn::CnnOptions,
    /// File hash, layer and preprocessing summary at creation.
    pub identity: crate::features::cnn::ModelIdentity,
}

/// A stored map.
#[derive(Clone, Debug, PartialEq)]
pub struct MapRecord {
    /// Map id.
    pub id: u64,
    /// User-given name.
    pub name: String,
    /// Descriptor settings.
    pub descriptor: DescriptorSettings,
    /// Descriptor length, fixed by the first stored batch (or at creation for precomputed).
    pub dim: Option<u32>,
    /// Number of reference images; their indices are `0..image_count`.
    pub image_count: u32,
    /// Creation time, milliseconds since the Unix epoch.
    pub created_ms: u64,
}

/// Optional per-image metadata.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ImageMeta {
    /// Capture time as given by the client.
    pub timestamp: Option<String>,
    /// Latitude in degrees.
    pub latitude: Option<f64>,
    /// Longitude in degrees.
    pub longitude: Option<f64>,
    /// Free-form label.
    pub label: Option<String>,
}

/// A stored localization result.
#[derive(Clone, Debug, PartialEq)]
pub struct LocalizationRecord {
    /// Localization id (increasing with creation time).
    pub id: u64,
    /// The map it was computed against.
    pub map_id: u64,
    /// Creation time, milliseconds since the Unix epoch.
    pub created_ms: u64,
    /// The caller's serialized result.
    pub document: Vec<u8>,
}

/// A stored trip (its solver state is kept separately, see [`Store::trip_state`]).
#[derive(Clone, Debug, PartialEq)]
pub struct TripRecord {
    /// Trip id (increasing with creation time).
    pub id: u64,
    /// The map it localizes against.
    pub map_id: u64,
    /// Creation time, milliseconds since the Unix epoch.
    pub created_ms: u64,
    /// When it was closed, if it was.
    pub closed_ms: Option<u64>,
    /// Frames consumed so far.
    pub frame_count: u64,
    /// The map's image count when the trip was opened: the trip localizes against those.
    pub reference_count: u32,
    /// The caller's status code after the last batch (0 before the first).
    pub status: u8,
    /// The caller's serialized parameters.
    pub params: Vec<u8>,
}

/// The latest estimate of one frame of a trip.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FrameRecord {
    /// Frame index since the trip started.
    pub frame: u32,
    /// Estimated reference, `None` when not on the map.
    pub reference: Option<u32>,
    /// Confidence of the estimate.
    pub confidence: f64,
}

/// The store. Cheap to share behind an `Arc`; all methods are blocking (call them off the
/// async workers).
pub struct Store {
    db: sled::Db,
    path: PathBuf,
    write: Mutex<()>,
    /// Reference matrices by map id, valid while their row count equals the map's
    /// `image_count`; filled and invalidated under the write lock.
    cache: Mutex<HashMap<u64, Arc<Matrix>>>,
}

/// One page of a listing, newest first.
#[derive(Clone, Debug, PartialEq)]
pub struct Page<T> {
    /// Records, newest first.
    pub items: Vec<T>,
    /// Pass as `before` to get the next page; `None` on the last page.
    pub next: Option<u64>,
}

impl Store {
    /// The newest-first page of the index keys in `lo..hi` (each holding an id at
    /// `key[at..at + 8]`): at most `limit` records read with `get`, and the `before` of the
    /// next page. `hi` is exclusive, so an id of `u64::MAX` (never issued) is never listed.
    fn page<T>(
        &self,
        lo: &[u8],
        hi: &[u8],
        at: usize,
        limit: usize,
        get: impl Fn(u64) -> StoreResult<T>,
    ) -> StoreResult<Page<T>> {
        let mut ids = Vec::with_capacity(limit + 1);
        for kv in self.db.range(lo..hi).rev().take(limit + 1) {
            ids.push(codec::id_at(&kv?.0, at)?);
        }
        let next = if ids.len() > limit {
            ids.truncate(limit);
            ids.last().copied()
        } else {
            None
        };
        let items = ids.into_iter().map(get).collect::<StoreResult<Vec<_>>>()?;
        Ok(Page { items, next })
    }

    /// Opens (or creates) the store in `dir` and upgrades its layout to
    /// [`migrate::CURRENT_VERSION`].
    pub fn open(dir: &Path) -> StoreResult<Store> {
        let db = sled::Config::new()
            .path(dir)
            .open()
            .map_err(|source| StoreError::Open {
                path: dir.to_path_buf(),
                source,
            })?;
        migrate::migrate(&db)?;
        Ok(Store {
            db,
            path: dir.to_path_buf(),
            write: Mutex::new(()),
            cache: Mutex::new(HashMap::new()),
        })
    }

    /// The data folder.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// The layout version on disk.
    pub fn schema_version(&self) -> StoreResult<u32> {
        migrate::read_version(&self.db)?.ok_or_else(|| {
            StoreError::corrupt(codec::SCHEMA_VERSION_KEY, "schema_version is missing")
        })
    }

    /// Checks that the store answers reads (for `/readyz`).
    pub fn check(&self) -> StoreResult<()> {
        self.schema_version().map(|_| ())
    }

    /// Flushes everything to disk (at shutdown; every write already flushes).
    pub fn flush(&self) -> StoreResult<()> {
        self.db.flush()?;
        Ok(())
    }

    fn lock(&self) -> MutexGuard<'_, ()> {
        // A panic while holding the lock cannot leave sled half-written (batches are
        // atomic), so a poisoned lock is safe to reuse.
        self.write.lock().unwrap_or_else(|p| p.into_inner())
    }

    fn cache(&self) -> MutexGuard<'_, HashMap<u64, Arc<Matrix>>> {
        self.cache.lock().unwrap_or_else(|p| p.into_inner())
    }

    fn next_id(&self) -> StoreResult<u64> {
        Ok(self.db.generate_id()?)
    }
}

pub(crate) fn now_ms() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_millis() as u64)
}

/// A new empty map of 1-D precomputed descriptors, for the store's unit tests.
#[cfg(test)]
pub(crate) fn test_map(store: &Store) -> u64 {
    store
        .create_map(NewMap {
            name: "m".into(),
            descriptor: DescriptorSettings::Precomputed { dim: 1 },
        })
        .expect("a new map in a fresh store")
        .id
}

#[cfg(test)]
mod golden;
