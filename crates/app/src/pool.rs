//! The CPU pool: a rayon pool that runs decoding, extraction and solving off the async workers,
//! replying through a oneshot channel.
//!
//! Invariant: no use case runs CPU-heavy work on a tokio worker, and no pool job waits on the
//! store (store I/O is awaited before or after the job). A panic in a job becomes
//! [`AppError::Internal`] instead of killing a worker.

use std::panic::{catch_unwind, AssertUnwindSafe};
use std::sync::Arc;

use super::error::AppError;

/// A rayon pool whose jobs reply through a oneshot channel. Cheap to clone.
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
    /// result; a panic becomes [`AppError::Internal`].
    pub async fn run<T, F>(&self, job: F) -> Result<T, AppError>
    where
        F: FnOnce() -> Result<T, AppError> + Send + 'static,
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
            Ok(Err(panic)) => Err(AppError::Internal(format!(
                "CPU job panicked: {}",
                panic_message(&*panic)
            ))),
            Err(_) => Err(AppError::Internal("CPU job was dropped".into())),
        }
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
            matches!(&err, AppError::Internal(m) if m.contains("boom in solver")),
            "{err}"
        );
    }
}
