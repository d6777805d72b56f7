//! The storage engines of seasonloc, each behind the application's port
//! [`seasonloc_app::store::Store`]: [`sled`] (embedded, the default) and [`postgres`] (one
//! database shared by any number of replicas). Nothing outside this crate knows a database;
//! the server picks an engine at start-up and hands the use cases an `Arc<dyn Store>`.

// Request paths must not panic: no `unwrap` outside tests (clippy.toml allows it there), and a
// new enum variant must be handled explicitly rather than fall into `_` (CI denies warnings).
#![warn(clippy::unwrap_used, clippy::wildcard_enum_match_arm)]
#![warn(missing_docs)]

pub mod document;
pub mod postgres;
pub mod sled;

pub use self::postgres::{PgOptions, PgStore};
pub use self::sled::{SledOptions, SledStore};

/// Distinct, increasing ids for the engines' unit tests (the service draws random ones in
/// `seasonloc_app::ids`).
#[cfg(test)]
pub(crate) fn test_id() -> u64 {
    static NEXT: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(1);
    NEXT.fetch_add(1, std::sync::atomic::Ordering::Relaxed)
}

/// `?` for an engine's own errors inside the engines: the orphan rule keeps
/// `From<sled::Error> for StoreError` out of this crate (the error type is the application's
/// port), so each engine result is converted by name, `.or_store()?`.
pub(crate) trait OrStore<T> {
    /// The engine error as a [`StoreError`](seasonloc_app::store::StoreError).
    fn or_store(self) -> seasonloc_app::store::StoreResult<T>;
}

impl<T> OrStore<T> for Result<T, ::sled::Error> {
    fn or_store(self) -> seasonloc_app::store::StoreResult<T> {
        self.map_err(|e| {
            if let ::sled::Error::Io(io) = &e {
                if sled::is_storage_full(io) {
                    return seasonloc_app::store::StoreError::StorageFull(format!(
                        "the embedded store: {io}"
                    ));
                }
            }
            seasonloc_app::store::StoreError::Backend(Box::new(e))
        })
    }
}

impl<T> OrStore<T> for Result<T, tokio_postgres::Error> {
    fn or_store(self) -> seasonloc_app::store::StoreResult<T> {
        self.map_err(postgres::db_error)
    }
}
