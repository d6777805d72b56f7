//! What one process keeps between requests: each map's reference descriptors, the column
//! priors of maps with trips, the in-memory state of open trips, and the locks that order one
//! trip's batches.
//!
//! The caches are safe when other processes write the same store: a map's descriptor matrix
//! is versioned by its `image_count` (images are append-only), and every use case reads the
//! map's record from the store first, so a cached matrix with fewer rows is topped up with the
//! missing rows only ([`References::get`]) and a localization that starts after an append was
//! acknowledged (by any process) always sees it. An open trip's cached state is versioned by
//! its frame count (every batch adds frames, and the store applies a batch only on the count
//! it was computed after): it is used only when the stored record still has that count, so a
//! batch another process applied meanwhile is never missed ([`OpenTrips`]).

use std::collections::HashMap;
use std::sync::{Arc, Mutex, MutexGuard};

use super::error::{AppError, AppResult};
use super::pool::CpuPool;
use crate::model::MapRecord;
use crate::store::Store;
use seasonloc_core::trip::Trip;
use seasonloc_core::Matrix;

fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    // The maps only ever hold complete entries, so a poisoned lock is safe to reuse.
    m.lock().unwrap_or_else(|p| p.into_inner())
}

/// Reference descriptor matrices by map id.
#[derive(Default)]
pub struct References {
    /// Each map's matrix with its descriptor kind (for [`References::usage`]).
    maps: Mutex<HashMap<u64, (Arc<Matrix>, &'static str)>>,
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
        let cached = lock(&self.maps).get(&map.id).map(|(m, _)| Arc::clone(m));
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
            let longer = maps
                .get(&map.id)
                .is_none_or(|(m, _)| m.rows() < full.rows());
            if longer && full.rows() > 0 {
                maps.insert(map.id, (Arc::clone(&full), map.descriptor.kind_name()));
            }
        }
        prefix(pool, full, count).await
    }

    /// Drops a map's matrix (after it was deleted).
    pub fn forget(&self, map: u64) {
        lock(&self.maps).remove(&map);
    }

    /// Maps cached and their matrices' bytes, by descriptor kind.
    pub fn usage(&self) -> std::collections::BTreeMap<&'static str, (usize, usize)> {
        let mut out = std::collections::BTreeMap::new();
        for (m, kind) in lock(&self.maps).values() {
            let e: &mut (usize, usize) = out.entry(*kind).or_default();
            e.0 += 1;
            e.1 += std::mem::size_of_val(m.as_slice());
        }
        out
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

/// A map's L2-normalised reference matrix with the image count it was computed for.
type CachedNormalized = (u32, Arc<Matrix>);

/// L2-normalised reference matrices of maps with trips, by map id: a trip's batch compares its
/// frames with them ([`seasonloc_core::similarity::cosine_matrix_normalized`], the same values as
/// [`seasonloc_core::similarity::cosine_matrix`]) instead of copying and normalising the whole map per
/// batch (about 100 ms on a 30,790-image map). A map's first `count` rows never change
/// (images are append-only), so an entry is valid for as long as the map exists.
#[derive(Default)]
pub struct NormalizedReferences {
    maps: Mutex<HashMap<u64, CachedNormalized>>,
}

impl NormalizedReferences {
    /// The normalised first `count` reference rows of `map` (from [`References`]).
    pub async fn get(
        &self,
        references: &References,
        store: &dyn Store,
        pool: &CpuPool,
        map: &MapRecord,
        count: u32,
    ) -> AppResult<Arc<Matrix>> {
        let cached = lock(&self.maps)
            .get(&map.id)
            .filter(|(n, _)| *n == count)
            .map(|(_, m)| Arc::clone(m));
        if let Some(m) = cached {
            return Ok(m);
        }
        let raw = references.get(store, pool, map, count).await?;
        let normalized = pool
            .run(move || {
                Ok(Arc::new(seasonloc_core::similarity::l2_normalized_rows(
                    &raw,
                )))
            })
            .await?;
        lock(&self.maps).insert(map.id, (count, Arc::clone(&normalized)));
        Ok(normalized)
    }

    /// Drops a map's matrix (after it was deleted).
    pub fn forget(&self, map: u64) {
        lock(&self.maps).remove(&map);
    }
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

/// Heap bytes of open trips a process keeps at most ([`OpenTrips`]): about 450 trips on a
/// 2,400-image map at the default lag of 32 (1.1 MB each), about 30 on 30,790 images.
pub const OPEN_TRIPS_BYTES: usize = 512 << 20;

/// A cached trip: its state, its size and when it was last used.
struct CachedTrip {
    trip: Trip,
    bytes: usize,
    used: u64,
}

#[derive(Default)]
struct OpenTripsInner {
    trips: HashMap<u64, CachedTrip>,
    bytes: usize,
    clock: u64,
}

/// The in-memory state of open trips, so the common path of a batch (the same process as the
/// trip's previous batch) restores nothing from the store. Bounded by [`OPEN_TRIPS_BYTES`],
/// least recently used first out. A batch *takes* its trip out and *keeps* it back only after
/// the store acknowledged the batch's write, so a failed or conflicting batch leaves nothing
/// stale behind.
pub struct OpenTrips {
    inner: Mutex<OpenTripsInner>,
    budget: usize,
}

impl Default for OpenTrips {
    fn default() -> Self {
        OpenTrips::with_budget(OPEN_TRIPS_BYTES)
    }
}

impl OpenTrips {
    /// A cache holding at most `budget` heap bytes of trips.
    pub fn with_budget(budget: usize) -> Self {
        OpenTrips {
            inner: Mutex::new(OpenTripsInner::default()),
            budget,
        }
    }

    /// Takes trip `id` out of the cache if it is at `frames` (the stored record's count); a
    /// cached state at another count is stale and dropped.
    pub fn take(&self, id: u64, frames: u64) -> Option<Trip> {
        let mut inner = lock(&self.inner);
        let cached = inner.trips.remove(&id)?;
        inner.bytes -= cached.bytes;
        (cached.trip.frames() as u64 == frames).then_some(cached.trip)
    }

    /// Keeps trip `id` (as the store now holds it), evicting the least recently used trips
    /// beyond the budget. A trip larger than the whole budget is not kept.
    pub fn keep(&self, id: u64, trip: Trip) {
        let bytes = trip.heap_bytes();
        if bytes > self.budget {
            return;
        }
        let mut inner = lock(&self.inner);
        inner.clock += 1;
        let used = inner.clock;
        if let Some(old) = inner.trips.insert(id, CachedTrip { trip, bytes, used }) {
            inner.bytes -= old.bytes;
        }
        inner.bytes += bytes;
        while inner.bytes > self.budget {
            let Some(oldest) = inner
                .trips
                .iter()
                .min_by_key(|(_, c)| c.used)
                .map(|(k, _)| *k)
            else {
                break;
            };
            if let Some(gone) = inner.trips.remove(&oldest) {
                inner.bytes -= gone.bytes;
            }
        }
    }

    /// Drops trip `id` (closed or deleted).
    pub fn forget(&self, id: u64) {
        let mut inner = lock(&self.inner);
        if let Some(gone) = inner.trips.remove(&id) {
            inner.bytes -= gone.bytes;
        }
    }

    /// Trips and heap bytes held.
    #[cfg(test)]
    pub fn usage(&self) -> (usize, usize) {
        let inner = lock(&self.inner);
        (inner.trips.len(), inner.bytes)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use seasonloc_core::trip::TripParams;

    fn trip(frames: usize) -> Trip {
        let mut t = Trip::new(vec![0.5; 20], TripParams::default()).unwrap();
        if frames > 0 {
            let c = Matrix::from_vec(frames, 20, vec![0.4; frames * 20]).unwrap();
            t.push_batch(&c).unwrap();
        }
        t
    }

    #[test]
    fn a_trip_is_used_only_at_the_stored_frame_count_and_the_budget_evicts_the_oldest() {
        let cache = OpenTrips::with_budget(3 * trip(5).heap_bytes() + 10);
        cache.keep(1, trip(5));
        // Another process applied a batch: the stored count moved on, the state is stale.
        assert!(cache.take(1, 8).is_none());
        assert!(cache.take(1, 5).is_none(), "a stale state is dropped");
        cache.keep(1, trip(5));
        assert_eq!(cache.take(1, 5).map(|t| t.frames()), Some(5));
        assert!(cache.take(1, 5).is_none(), "taken out while its batch runs");
        for id in 1..=3 {
            cache.keep(id, trip(5));
        }
        assert_eq!(cache.usage().0, 3);
        // Keeping a fourth evicts the least recently kept (1).
        cache.keep(4, trip(5));
        assert_eq!(cache.usage().0, 3);
        assert!(cache.take(1, 5).is_none());
        assert!(cache.take(2, 5).is_some());
        cache.forget(3);
        assert_eq!(cache.usage().0, 1);
        assert_eq!(cache.usage().1, trip(5).heap_bytes());
        // A trip larger than the budget is not kept.
        let tiny = OpenTrips::with_budget(10);
        tiny.keep(9, trip(1));
        assert_eq!(tiny.usage(), (0, 0));
    }
}
