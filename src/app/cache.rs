//! What one process keeps between requests: each map's reference descriptors, the column
//! priors of maps with trips, and the locks that order one trip's batches.
//!
//! The caches are safe when other processes write the same store: a map's descriptor matrix
//! is versioned by its `image_count` (images are append-only), and every use case reads the
//! map's record from the store first, so a cached matrix with fewer rows is topped up with the
//! missing rows only ([`References::get`]) and a localization that starts after an append was
//! acknowledged (by any process) always sees it.

use std::collections::HashMap;
use std::sync::{Arc, Mutex, MutexGuard};

use super::error::{AppError, AppResult};
use super::pool::CpuPool;
use crate::store::{MapRecord, Store};
use crate::Matrix;

fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    // The maps only ever hold complete entries, so a poisoned lock is safe to reuse.
    m.lock().unwrap_or_else(|p| p.into_inner())
}

/// Reference descriptor matrices by map id.
#[derive(Default)]
pub struct References {
    maps: Mutex<HashMap<u64, Arc<Matrix>>>,
}

impl References {
    /// The first `count` descriptor rows of `map` (`count` at most the record's
    /// `image_count`), reading from the store only the rows not cached yet. Copies run on the
    /// CPU pool.
    pub async fn get(
        &self,
        store: &dyn Store,
        pool: &CpuPool,
        map: &MapRecord,
        count: u32,
    ) -> AppResult<Arc<Matrix>> {
        let cached = lock(&self.maps).get(&map.id).cloned();
        let have = cached.as_ref().map_or(0, |m| m.rows());
        if have >= count as usize {
            if let Some(m) = cached {
                return prefix(pool, m, count).await;
            }
        }
        let target = map.image_count.max(count);
        let start = u32::try_from(have).unwrap_or(u32::MAX).min(target);
        let fresh = store.descriptors(map.id, start..target).await?;
        let id = map.id;
        let full = match cached {
            Some(old) if old.rows() > 0 => {
                pool.run(move || {
                    if old.cols() != fresh.cols() {
                        return Err(AppError::Internal(format!(
                            "map {id:016x}: cached descriptors have length {}, stored {}",
                            old.cols(),
                            fresh.cols()
                        )));
                    }
                    let mut data =
                        Vec::with_capacity(old.as_slice().len() + fresh.as_slice().len());
                    data.extend_from_slice(old.as_slice());
                    data.extend_from_slice(fresh.as_slice());
                    Ok(Arc::new(Matrix::from_vec(
                        old.rows() + fresh.rows(),
                        old.cols(),
                        data,
                    )?))
                })
                .await?
            }
            Some(_) | None => Arc::new(fresh),
        };
        {
            let mut maps = lock(&self.maps);
            let longer = maps.get(&map.id).is_none_or(|m| m.rows() < full.rows());
            if longer && full.rows() > 0 {
                maps.insert(map.id, Arc::clone(&full));
            }
        }
        prefix(pool, full, count).await
    }

    /// Drops a map's matrix (after it was deleted).
    pub fn forget(&self, map: u64) {
        lock(&self.maps).remove(&map);
    }
}

/// The first `count` rows of `m` (the same matrix when it has exactly that many).
async fn prefix(pool: &CpuPool, m: Arc<Matrix>, count: u32) -> AppResult<Arc<Matrix>> {
    let count = count as usize;
    if m.rows() == count {
        return Ok(m);
    }
    pool.run(move || {
        let d = m.cols();
        let rows = m.as_slice().get(..count * d).ok_or_else(|| {
            AppError::Internal(format!("{} rows cached, {count} asked for", m.rows()))
        })?;
        Ok(Arc::new(Matrix::from_vec(count, d, rows.to_vec())?))
    })
    .await
}

/// A map's prior column means with the image count they were computed for.
type CachedPrior = (u32, Arc<Vec<f32>>);

/// Column priors of maps with trips, by map id.
#[derive(Default)]
pub struct Priors {
    maps: Mutex<HashMap<u64, CachedPrior>>,
}

impl Priors {
    /// The prior of `map` computed for its first `count` images, if cached.
    pub fn get(&self, map: u64, count: u32) -> Option<Arc<Vec<f32>>> {
        lock(&self.maps)
            .get(&map)
            .filter(|(n, _)| *n == count)
            .map(|(_, p)| Arc::clone(p))
    }

    /// Keeps the prior of `map`'s first `count` images.
    pub fn keep(&self, map: u64, count: u32, prior: Arc<Vec<f32>>) {
        lock(&self.maps).insert(map, (count, prior));
    }

    /// Drops a map's prior (after it was deleted).
    pub fn forget(&self, map: u64) {
        lock(&self.maps).remove(&map);
    }
}

/// Per-trip locks: one process applies a trip's batches one at a time, in arrival order
/// (across processes the store's conditional write keeps them apart).
#[derive(Default)]
pub struct TripLocks {
    locks: Mutex<HashMap<u64, Arc<tokio::sync::Mutex<()>>>>,
}

impl TripLocks {
    /// The lock that orders `trip`'s batches.
    pub fn of(&self, trip: u64) -> Arc<tokio::sync::Mutex<()>> {
        let mut locks = lock(&self.locks);
        if locks.len() > 1024 {
            // Forget locks nobody holds or waits for.
            locks.retain(|_, l| Arc::strong_count(l) > 1);
        }
        Arc::clone(locks.entry(trip).or_default())
    }
}
