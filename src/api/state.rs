//! Shared state of the handlers and the CPU pool that keeps decoding, extraction and solving off
//! the async workers.
//!
//! Invariant: no handler runs CPU-heavy or blocking work on a tokio worker; it goes through
//! [`CpuPool::run`] (rayon, for parallel CPU work) or [`blocking`] (tokio's blocking threads,
//! for store I/O). A panic in either becomes [`ApiError::Internal`] instead of killing a worker.

use std::panic::{catch_unwind, AssertUnwindSafe};
use std::sync::Arc;

use axum::body::Bytes;
use tokio::sync::Semaphore;

use super::error::ApiError;
use super::metrics::Metrics;
use crate::config::Settings;
use crate::store::Store;

/// Everything a handler needs; cheap to clone.
#[derive(Clone)]
pub struct AppState {
    /// The embedded store.
    pub store: Arc<Store>,
    /// Validated settings.
    pub settings: Arc<Settings>,
    /// CPU pool.
    pub pool: CpuPool,
    /// Admission slots of `/localize` (running + waiting).
    pub localize_slots: Arc<Semaphore>,
    /// Prometheus metrics.
    pub metrics: Arc<Metrics>,
    /// `openapi/openapi.yaml` as JSON.
    pub openapi_json: Bytes,
    /// Per-trip locks and per-map column priors of open trips.
    pub trips: Arc<super::trips::TripShared>,
}

impl AppState {
    /// Builds the state over an open store.
    pub fn new(store: Arc<Store>, settings: Settings) -> anyhow::Result<Self> {
        let pool = CpuPool::new(settings.worker_threads)?;
        let openapi_json = Bytes::from(super::ops::openapi_json()?);
        Ok(AppState {
            store,
            localize_slots: Arc::new(Semaphore::new(settings.localize_queue)),
            settings: Arc::new(settings),
            pool,
            metrics: Arc::new(Metrics::default()),
            openapi_json,
            trips: Arc::default(),
        })
    }
}

/// A rayon pool whose jobs reply through a oneshot channel.
#[derive(Clone)]
pub struct CpuPool {
    pool: Arc<rayon::ThreadPool>,
}

impl CpuPool {
    /// A pool of `threads` threads named `seasonloc-cpu-N`.
    pub fn new(threads: usize) -> Result<Self, rayon::ThreadPoolBuildError> {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .thread_name(|i| format!("seasonloc-cpu-{i}"))
            .build()?;
        Ok(CpuPool {
            pool: Arc::new(pool),
        })
    }

    /// Runs `job` on the pool (rayon parallelism inside it uses this pool) and awaits its
    /// result; a panic becomes [`ApiError::Internal`].
    pub async fn run<T, F>(&self, job: F) -> Result<T, ApiError>
    where
        F: FnOnce() -> Result<T, ApiError> + Send + 'static,
        T: Send + 'static,
    {
        let (tx, rx) = tokio::sync::oneshot::channel();
        self.pool.spawn(move || {
            let result = catch_unwind(AssertUnwindSafe(job));
            // The receiver is gone when the request was cancelled (timeout, disconnect).
            let _ = tx.send(result);
        });
        match rx.await {
            Ok(Ok(result)) => result,
            Ok(Err(panic)) => Err(ApiError::Internal(format!(
                "CPU job panicked: {}",
                panic_message(&*panic)
            ))),
            Err(_) => Err(ApiError::Internal("CPU job was dropped".into())),
        }
    }
}

/// Runs blocking `job` (store I/O) on tokio's blocking threads; a panic becomes
/// [`ApiError::Internal`].
pub async fn blocking<T, F>(job: F) -> Result<T, ApiError>
where
    F: FnOnce() -> Result<T, ApiError> + Send + 'static,
    T: Send + 'static,
{
    match tokio::task::spawn_blocking(job).await {
        Ok(result) => result,
        Err(e) => Err(ApiError::Internal(format!("blocking job failed: {e}"))),
    }
}

fn panic_message(panic: &(dyn std::any::Any + Send)) -> String {
    if let Some(s) = panic.downcast_ref::<&str>() {
        (*s).to_string()
    } else if let Some(s) = panic.downcast_ref::<String>() {
        s.clone()
    } else {
        "non-string panic payload".into()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test]
    async fn pool_returns_results_and_catches_panics() {
        let pool = CpuPool::new(2).unwrap();
        let sum = pool
            .run(|| {
                use rayon::prelude::*;
                Ok((0..1000u64).into_par_iter().sum::<u64>())
            })
            .await
            .unwrap();
        assert_eq!(sum, 499_500);
        let err = pool
            .run::<(), _>(|| panic!("boom in solver"))
            .await
            .unwrap_err();
        assert!(
            matches!(&err, ApiError::Internal(m) if m.contains("boom in solver")),
            "{err}"
        );
        let err = blocking::<(), _>(|| panic!("store")).await.unwrap_err();
        assert!(matches!(err, ApiError::Internal(_)));
    }
}
