//! The application layer: the domain model ([`model`]), the storage port ([`store::Store`],
//! implemented by the engines of `seasonloc-store`), the one table of error codes
//! ([`ErrorCode`]), and the use cases: one async method of [`App`] per thing a client can do
//! (create a map, append images / descriptors / drives, localize, open a trip, post frames,
//! close it, read and list, delete), taking typed input and returning the model's records.
//!
//! [`App`] is the only caller of the [`Store`]; what differs between kinds of map is one small
//! trait with one module per kind (`kind/`: global descriptors, co-occurrence maps), chosen in
//! one place. Front ends (the HTTP API) decode their input, call a use case and encode its
//! answer. Rules every use case keeps:
//!
//! * CPU work (decoding, extraction, similarities, solving, encoding a trip's state) runs on
//!   the [`CpuPool`]; store I/O is awaited outside pool jobs, never inside one.
//! * Nothing is written until everything that can fail on the input has been checked, and
//!   every write is one atomic store call, so a failed request changes nothing.
//! * What a process caches (`cache.rs`) is checked against the store's versions first, so
//!   several processes may serve one shared store.

// Request paths must not panic: no `unwrap` outside tests (clippy.toml allows it there), and a
// new enum variant must be handled explicitly rather than fall into `_` (CI denies warnings).
#![warn(clippy::unwrap_used, clippy::wildcard_enum_match_arm)]

mod cache;
pub mod caller;
mod error;
mod idempotency;
pub mod ids;
mod images;
mod kind;
mod localize;
mod maps;
pub mod model;
pub mod models;
pub mod pool;
pub mod store;
pub mod timed_store;
mod trips;

use std::path::PathBuf;
use std::sync::Arc;

use crate::store::Store;

pub use error::{AppError, AppResult, ErrorCode};
pub use idempotency::Idempotency;
pub use ids::new_id;
pub use images::ImageInput;
pub use kind::cooc::{DriveInput, DriveOutcome};
pub use kind::descriptors::map_extractor;
pub use kind::{AppendOutcome, Queries, Upload};
pub use localize::LocalizeInput;
pub use maps::{DescriptorSpec, NewMapSpec};
pub use models::{ModelPolicy, ModelRules};
pub use pool::CpuPool;
pub use trips::{FramesOutcome, FramesTimings, OpenTripCounts};

/// Settings of the use-case layer.
#[derive(Clone, Debug, PartialEq)]
pub struct AppConfig {
    /// Threads of the CPU pool (at least 1).
    pub worker_threads: usize,
    /// Largest accepted image in pixels, checked from the header before decoding.
    pub max_image_pixels: u64,
    /// Most decoded pixels of a batch that is held decoded as a whole (a co-occurrence map's
    /// first batch or drive), the sum of its images' sizes checked from their headers before
    /// decoding. Batches described image by image need no such budget: at most one decoded
    /// image per CPU-pool thread is alive at a time.
    pub max_batch_pixels: u64,
    /// Model of CNN maps created without one.
    pub default_cnn_model: Option<PathBuf>,
    /// Longest descriptor an image may give or a map may have (f32 values).
    pub max_descriptor_len: usize,
    /// Where model files named by requests may come from.
    pub models: ModelPolicy,
}

/// The use cases over one store. Share it behind an `Arc`.
pub struct App {
    store: Arc<dyn Store>,
    pool: CpuPool,
    config: AppConfig,
    references: cache::References,
    priors: cache::Priors,
    normalized: cache::NormalizedReferences,
    open_trips: cache::OpenTrips,
    trip_locks: cache::TripLocks,
}

impl App {
    /// The use cases over `store`, with a CPU pool of `config.worker_threads` threads.
    pub fn new(store: Arc<dyn Store>, config: AppConfig) -> AppResult<App> {
        let pool = CpuPool::new(config.worker_threads)
            .map_err(|e| AppError::Internal(format!("starting the CPU pool: {e}")))?;
        Ok(App {
            store,
            pool,
            config,
            references: cache::References::default(),
            priors: cache::Priors::default(),
            normalized: cache::NormalizedReferences::default(),
            open_trips: cache::OpenTrips::default(),
            trip_locks: cache::TripLocks::default(),
        })
    }

    /// The rules a map's model file is read under at every use.
    pub(crate) fn model_rules(&self) -> ModelRules {
        ModelRules {
            policy: self.config.models.clone(),
            default: self.config.default_cnn_model.clone(),
        }
    }

    /// Where the store keeps its data (for logs).
    pub fn store_location(&self) -> String {
        self.store.location()
    }

    /// Whether the store answers (for readiness probes).
    pub async fn ready(&self) -> AppResult<()> {
        Ok(self.store.check().await?)
    }

    /// Makes everything durable (at shutdown).
    pub async fn flush(&self) -> AppResult<()> {
        Ok(self.store.flush().await?)
    }
}
