//! The embedded engine: one sled database in a data folder (the default; the README's first
//! command needs nothing but the binary).
//!
//! Only this module knows sled. It owns the key layout and value encodings ([`codec`]), the
//! layout version and its upgrades ([`migrate`]), and the write rules of [`seasonloc_app::store`]:
//!
//! * every change that spans several keys (a batch of images plus the map's `image_count`, a
//!   localization plus its index entry, a trip batch, a map and everything under it) is one
//!   `sled::Batch`, applied atomically, so a crash leaves either all of it or none of it;
//! * every write is flushed to disk before the call returns, so whatever the API acknowledged
//!   survives a crash;
//! * writes go through one mutex, so read-modify-write cycles (`image_count`, a trip's frame
//!   count, a co-occurrence map) never interleave and conditional writes are checked and
//!   applied as one step.
//!
//! The inherent methods of [`SledStore`] are blocking (for tools, tests and benches); the
//! service uses the [`Store`] implementation, which runs each of them on tokio's blocking
//! threads.

pub mod codec;
mod cooc;
#[cfg(test)]
mod damage_tests;
#[cfg(test)]
mod full_disk_tests;
#[cfg(test)]
mod golden;
pub mod ledger;
mod localizations;
mod maps;
pub mod migrate;
mod trips;
pub mod verify;

use crate::OrStore;
use std::ops::Range;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard, RwLock};
use std::time::{Duration, Instant};

use async_trait::async_trait;

use seasonloc_app::model::{ImageMeta, LocalizationRecord, MapRecord, TripRecord};
use seasonloc_app::store::{
    CoocWrite, IdempotencyRecord, ImageBatch, NewLocalization, NewMap, NewTrip, Page, PageRequest,
    Store, StoreError, StoreResult, TripBatch, TripState,
};
use seasonloc_core::trip::FrameEstimate;
use seasonloc_core::Matrix;

/// How long [`SledStore::open`] waits for a data folder locked by a handle that is closing.
pub const LOCK_WAIT: Duration = Duration::from_secs(2);

/// The least time between two attempts to reopen a store after an I/O failure.
pub const REOPEN_PAUSE: Duration = Duration::from_millis(500);

/// sled's page cache when no size is given (`serve --store-cache-bytes`): sled's own default is
/// 1 GiB, more than a small pod has.
pub const DEFAULT_CACHE_BYTES: u64 = 128 * 1024 * 1024;

/// How the embedded store is opened.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct SledOptions {
    /// sled's page cache, in bytes (approximate: sled counts the pages it keeps in memory).
    pub cache_bytes: u64,
}

impl Default for SledOptions {
    fn default() -> Self {
        SledOptions {
            cache_bytes: DEFAULT_CACHE_BYTES,
        }
    }
}

/// Whether sled failed to open because another handle holds the folder's lock; every other
/// error is reported at once. sled 0.34 reports it as an `Other` I/O error whose message
/// starts "could not acquire lock" (`open_tests` pins this against the sled in use).
fn is_lock_contention(e: &sled::Error) -> bool {
    if let sled::Error::Io(io) = e {
        io.kind() == std::io::ErrorKind::WouldBlock
            || io.to_string().starts_with("could not acquire lock")
    } else {
        false
    }
}

/// Whether an I/O error means "no space left" (a full disk, or a quota reached).
pub fn is_storage_full(e: &std::io::Error) -> bool {
    const ENOSPC: i32 = 28;
    const EDQUOT: i32 = 122;
    e.kind() == std::io::ErrorKind::StorageFull
        || e.kind() == std::io::ErrorKind::QuotaExceeded
        || matches!(e.raw_os_error(), Some(ENOSPC | EDQUOT))
}

/// Whether `e` is an I/O failure of sled itself, after which sled refuses every later
/// operation of that handle (it keeps the first I/O error as a global error): the store then
/// reopens its database.
fn is_io_failure(e: &StoreError) -> bool {
    if let StoreError::Backend(source) = e {
        return source
            .downcast_ref::<sled::Error>()
            .is_some_and(|e| matches!(e, sled::Error::Io(_)));
    }
    matches!(e, StoreError::StorageFull(_))
}

/// What clones of a [`SledStore`] share.
struct Shared {
    path: PathBuf,
    options: SledOptions,
    /// The open database; `None` from an I/O failure until it is reopened.
    db: RwLock<Option<sled::Db>>,
    /// Held by every write (and by a reopen).
    write: Mutex<()>,
    /// The generation of the newest write (under `write`).
    generation: AtomicU64,
    ledger: Mutex<ledger::Ledger>,
    /// Set by an I/O failure of the handle, cleared when it is reopened.
    failed: Mutex<Option<Failure>>,
    /// When a reopen was last tried (attempts are at least [`REOPEN_PAUSE`] apart).
    reopen: Mutex<Option<Instant>>,
}

/// Why the handle failed.
#[derive(Clone, Copy, Debug)]
struct Failure {
    /// No space left (writes answer `storage_full`), rather than another I/O error.
    full: bool,
}

/// The reserve file in the data folder: [`RESERVE_BYTES`] kept free for the store's own
/// use. On a full disk it is removed, so sled can reopen (its recovery writes) and serve reads,
/// and writes are taken again only once it can be made again.
pub const RESERVE_FILE: &str = "seasonloc.reserve";

/// The reserve file's size: a few of sled's 512 KiB log segments.
pub const RESERVE_BYTES: usize = 4 * 1024 * 1024;

/// Makes the reserve file in `dir` (whole, synced); whether it is there.
fn reserve(dir: &Path) -> bool {
    use std::io::Write;
    let path = dir.join(RESERVE_FILE);
    if std::fs::metadata(&path).is_ok_and(|m| m.len() == RESERVE_BYTES as u64) {
        return true;
    }
    let made = std::fs::File::create(&path)
        .and_then(|mut f| {
            f.write_all(&vec![0x5a; RESERVE_BYTES])?;
            f.sync_all()
        })
        .is_ok();
    if !made {
        let _ = std::fs::remove_file(&path);
    }
    made
}

/// The sled engine. Cheap to clone (clones share the database and its write lock).
///
/// After an I/O failure (a full disk) sled keeps the error and refuses every later call of
/// that handle until the process restarts. This store instead drops the handle and reopens
/// the database at once (removing its [reserve file](RESERVE_FILE) first on a full disk, so
/// the reopen has room): reads go on, writes answer [`StoreError::StorageFull`] until the
/// reserve can be made again (checked by [`SledStore::ensure_open`] before each call of the
/// service, at most every [`REOPEN_PAUSE`]), without a restart.
#[derive(Clone)]
pub struct SledStore {
    shared: Arc<Shared>,
}

/// Opens sled in `dir`, waiting up to [`LOCK_WAIT`] for a lock held by a closing handle.
fn open_db(dir: &Path, options: &SledOptions) -> StoreResult<sled::Db> {
    let config = sled::Config::new()
        .path(dir)
        .cache_capacity(options.cache_bytes);
    let started = Instant::now();
    let mut pause = Duration::from_millis(5);
    loop {
        match config.open() {
            Ok(db) => return Ok(db),
            Err(e) if is_lock_contention(&e) && started.elapsed() < LOCK_WAIT => {
                std::thread::sleep(pause);
                pause = (pause * 2).min(Duration::from_millis(100));
            }
            Err(sled::Error::Corruption { at, .. }) => {
                return Err(verify::damaged(
                    dir,
                    format!("the storage engine found corrupt data at {at:?} while opening"),
                ))
            }
            Err(source) => {
                return Err(StoreError::Open {
                    location: dir.display().to_string(),
                    source: Box::new(source),
                })
            }
        }
    }
}

impl SledStore {
    /// Opens (or creates) the store in `dir` with the default [`SledOptions`].
    pub fn open(dir: &Path) -> StoreResult<SledStore> {
        SledStore::open_with(dir, SledOptions::default())
    }

    /// Opens (or creates) the store in `dir`, checks it ([`verify::full`]: every record read,
    /// the generation against the [`ledger`]) and upgrades its layout to
    /// [`migrate::CURRENT_VERSION`]. A damaged store fails with [`StoreError::Damaged`] (never
    /// a panic).
    ///
    /// sled locks the folder for as long as a database handle (or its background flusher
    /// thread) lives, and dropping a handle releases the lock only when that thread has
    /// exited, a moment later. An open that finds the folder locked therefore waits up to
    /// [`LOCK_WAIT`] for the lock before it fails, so a store closed and reopened at once (a
    /// restart in the same process, tests) opens, while a folder held by another running
    /// process still fails with [`StoreError::Open`] after that bound.
    pub fn open_with(dir: &Path, options: SledOptions) -> StoreResult<SledStore> {
        let started = Instant::now();
        let (db, checked) = verify::catch(dir, "opening the store", || {
            let db = open_db(dir, &options)?;
            let checked = verify::full(&db, dir)?;
            migrate::migrate(&db)?;
            Ok((db, checked))
        })?;
        tracing::info!(
            records = checked.records,
            bytes = checked.bytes,
            generation = checked.generation,
            ms = started.elapsed().as_millis() as u64,
            "store checked: every record read, the generation matches the ledger"
        );
        let ledger = ledger::Ledger::create_or_set(dir, checked.generation)?;
        if !reserve(dir) {
            tracing::warn!(
                bytes = RESERVE_BYTES,
                "no room for the store's reserve file: a full disk will close the store to \
                 reads until space is freed"
            );
        }
        Ok(SledStore {
            shared: Arc::new(Shared {
                path: dir.to_path_buf(),
                options,
                db: RwLock::new(Some(db)),
                write: Mutex::new(()),
                generation: AtomicU64::new(checked.generation),
                ledger: Mutex::new(ledger),
                failed: Mutex::new(None),
                reopen: Mutex::new(None),
            }),
        })
    }

    /// The data folder.
    pub fn path(&self) -> &Path {
        &self.shared.path
    }

    /// The open database, or [`StoreError::Unavailable`] while it is being reopened after
    /// an I/O failure.
    fn db(&self) -> StoreResult<sled::Db> {
        self.shared
            .db
            .read()
            .unwrap_or_else(|p| p.into_inner())
            .clone()
            .ok_or_else(|| {
                StoreError::Unavailable(
                    "the embedded store is reopening after an I/O failure".into(),
                )
            })
    }

    /// Brings the store back after an I/O failure (at most every [`REOPEN_PAUSE`]; a
    /// concurrent attempt is not waited for): reopens the database if it is closed, and after
    /// a full disk takes writes again once the reserve file can be made again (so there is
    /// room for at least [`RESERVE_BYTES`] more).
    pub fn ensure_open(&self) {
        let failed = *self.shared.failed.lock().unwrap_or_else(|p| p.into_inner());
        let closed = self
            .shared
            .db
            .read()
            .unwrap_or_else(|p| p.into_inner())
            .is_none();
        if failed.is_none() && !closed {
            return;
        }
        let Ok(mut last) = self.shared.reopen.try_lock() else {
            return;
        };
        if last.is_some_and(|t| t.elapsed() < REOPEN_PAUSE) {
            return;
        }
        *last = Some(Instant::now());
        if closed && !self.reopen() {
            return;
        }
        if failed.is_some_and(|f| f.full) && !reserve(&self.shared.path) {
            return;
        }
        *self.shared.failed.lock().unwrap_or_else(|p| p.into_inner()) = None;
        *last = None;
        tracing::info!("the embedded store takes writes again");
    }

    /// Drops the handle and opens the database again (its generation checked against the
    /// ledger, so a reopen never serves a store that lost acknowledged writes); whether it is
    /// open.
    fn reopen(&self) -> bool {
        let _guard = self.lock();
        // The failed handle must be gone (its lock on the folder released) before sled opens
        // the folder again; reads wait for the reopen meanwhile.
        let mut slot = self.shared.db.write().unwrap_or_else(|p| p.into_inner());
        slot.take();
        let dir = &self.shared.path;
        let reopened = verify::catch(dir, "reopening the store", || {
            let db = open_db(dir, &self.shared.options)?;
            let generation = verify::against_ledger(&db, dir)?;
            Ok((db, generation))
        });
        match reopened {
            Ok((db, generation)) => {
                self.shared.generation.store(generation, Ordering::SeqCst);
                *slot = Some(db);
                tracing::info!(generation, "store reopened after an I/O failure");
                true
            }
            Err(e) => {
                tracing::warn!(error = %e, "the store could not be reopened yet");
                false
            }
        }
    }

    /// After an operation failed with `e`: an I/O failure of sled drops the handle (sled
    /// would refuse its later writes, and may hold a batch it could not flush) and reopens
    /// the database at once; after a full disk, the reserve file is removed first so the
    /// reopen has room, and writes stay refused until it can be made again.
    fn after_error(&self, e: &StoreError) {
        if !is_io_failure(e) {
            return;
        }
        let full = matches!(e, StoreError::StorageFull(_));
        {
            let mut failed = self.shared.failed.lock().unwrap_or_else(|p| p.into_inner());
            if failed.is_some() {
                return;
            }
            tracing::warn!(error = %e, "store I/O failed: reopening the embedded store");
            *failed = Some(Failure { full });
        }
        {
            // Never under `failed`: a write holds the write lock and then reads `failed`.
            let _guard = self.lock();
            self.shared
                .db
                .write()
                .unwrap_or_else(|p| p.into_inner())
                .take();
        }
        if full {
            let _ = std::fs::remove_file(self.shared.path.join(RESERVE_FILE));
        }
        // Held meanwhile, so a concurrent `ensure_open` does not reopen a second time.
        let mut last = self.shared.reopen.lock().unwrap_or_else(|p| p.into_inner());
        *last = Some(Instant::now());
        self.reopen();
    }

    /// The error of a write while the handle is failed.
    fn refuse_write(&self) -> StoreResult<()> {
        match *self.shared.failed.lock().unwrap_or_else(|p| p.into_inner()) {
            None => Ok(()),
            Some(Failure { full: true }) => Err(StoreError::StorageFull(
                "the disk of the embedded store is full; writes resume once space is freed".into(),
            )),
            Some(Failure { full: false }) => Err(StoreError::Unavailable(
                "the embedded store is reopening after an I/O failure".into(),
            )),
        }
    }

    /// Applies `batch` with the next generation, flushes it, and records the generation in
    /// the ledger: only then may the write be acknowledged. Call under the write lock.
    fn commit(&self, mut batch: sled::Batch) -> StoreResult<()> {
        self.refuse_write()?;
        let db = self.db()?;
        let generation = self.shared.generation.load(Ordering::SeqCst) + 1;
        batch.insert(codec::GENERATION_KEY, &generation.to_be_bytes());
        db.apply_batch(batch).or_store()?;
        db.flush().or_store()?;
        self.shared.generation.store(generation, Ordering::SeqCst);
        self.shared
            .ledger
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .record(generation)
    }

    /// The layout version on disk.
    pub fn schema_version(&self) -> StoreResult<u32> {
        migrate::read_version(&self.db()?)?.ok_or_else(|| {
            StoreError::corrupt(codec::SCHEMA_VERSION_KEY, "schema_version is missing")
        })
    }

    /// Checks that the store answers reads.
    pub fn check(&self) -> StoreResult<()> {
        self.schema_version().map(|_| ())
    }

    /// Flushes everything to disk (at shutdown; every write already flushes).
    pub fn flush(&self) -> StoreResult<()> {
        self.db()?.flush().or_store()?;
        Ok(())
    }

    fn lock(&self) -> MutexGuard<'_, ()> {
        // A panic while holding the lock cannot leave sled half-written (batches are
        // atomic), so a poisoned lock is safe to reuse.
        self.shared.write.lock().unwrap_or_else(|p| p.into_inner())
    }

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
        for kv in self.db()?.range(lo..hi).rev().take(limit + 1) {
            ids.push(codec::id_at(&kv.or_store()?.0, at)?);
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

    /// The record stored under an idempotency key, if any.
    pub fn idempotency_record(
        &self,
        scope: &str,
        key: &str,
    ) -> StoreResult<Option<IdempotencyRecord>> {
        let k = codec::idempotency_key(scope, key);
        self.db()?
            .get(&k)
            .or_store()?
            .map(|v| codec::decode_idempotency(&k, scope, key, &v))
            .transpose()
    }

    /// Adds `record` (with `indices`, for appends) to `batch`; fails when its key is stored
    /// already. Call under the write lock.
    fn claim_key(
        &self,
        record: Option<&IdempotencyRecord>,
        indices: Option<Range<u32>>,
        batch: &mut sled::Batch,
    ) -> StoreResult<()> {
        let Some(record) = record else {
            return Ok(());
        };
        let k = codec::idempotency_key(&record.scope, &record.key);
        if self.db()?.contains_key(&k).or_store()? {
            return Err(StoreError::IdempotencyKeyTaken {
                scope: record.scope.clone(),
                key: record.key.clone(),
            });
        }
        let stored = IdempotencyRecord {
            indices,
            ..record.clone()
        };
        batch.insert(k, codec::encode_idempotency(&stored));
        Ok(())
    }

    /// Adds the removal of the record of the key that created map `id`, if any, to `batch`
    /// (creations share one scope; the record's response names the map).
    fn remove_creation_key(&self, id: u64, batch: &mut sled::Batch) -> StoreResult<()> {
        let scope = IdempotencyRecord::maps_scope();
        let prefix = codec::idempotency_prefix(&scope);
        for kv in self.db()?.scan_prefix(&prefix) {
            let (k, v) = kv.or_store()?;
            let key = String::from_utf8_lossy(&k[prefix.len()..]).into_owned();
            if codec::decode_idempotency(&k, &scope, &key, &v)?.response == id.to_le_bytes() {
                batch.remove(k);
            }
        }
        Ok(())
    }

    /// Adds the removal of every idempotency record of `scope` to `batch`.
    fn remove_keys(&self, scope: &str, batch: &mut sled::Batch) -> StoreResult<()> {
        for kv in self.db()?.scan_prefix(codec::idempotency_prefix(scope)) {
            batch.remove(kv.or_store()?.0);
        }
        Ok(())
    }

    /// Runs a blocking method on tokio's blocking threads.
    async fn run<T, F>(&self, job: F) -> StoreResult<T>
    where
        T: Send + 'static,
        F: FnOnce(&SledStore) -> StoreResult<T> + Send + 'static,
    {
        let store = self.clone();
        tokio::task::spawn_blocking(move || {
            store.ensure_open();
            let result = job(&store);
            if let Err(e) = &result {
                store.after_error(e);
            }
            result
        })
        .await
        .map_err(|e| StoreError::Backend(format!("store task failed: {e}").into()))?
    }
}

#[async_trait]
impl Store for SledStore {
    fn location(&self) -> String {
        self.shared.path.display().to_string()
    }

    async fn check(&self) -> StoreResult<()> {
        self.run(SledStore::check).await
    }

    async fn flush(&self) -> StoreResult<()> {
        self.run(SledStore::flush).await
    }

    async fn create_map(&self, new: NewMap) -> StoreResult<MapRecord> {
        self.run(move |s| s.create_map(new)).await
    }

    async fn get_map(&self, id: u64) -> StoreResult<MapRecord> {
        self.run(move |s| s.get_map(id)).await
    }

    async fn list_maps(&self) -> StoreResult<Vec<MapRecord>> {
        self.run(SledStore::list_maps).await
    }

    async fn delete_map(&self, id: u64) -> StoreResult<()> {
        self.run(move |s| s.delete_map(id)).await
    }

    async fn append_images(&self, batch: ImageBatch) -> StoreResult<Range<u32>> {
        self.run(move |s| s.append_images(&batch)).await
    }

    async fn descriptors(&self, map: u64, rows: Range<u32>) -> StoreResult<Matrix> {
        self.run(move |s| s.descriptors(map, rows)).await
    }

    async fn image_metadata(&self, map: u64, rows: Range<u32>) -> StoreResult<Vec<ImageMeta>> {
        self.run(move |s| s.image_metadata(map, rows)).await
    }

    async fn thumbnail(&self, map: u64, index: u32) -> StoreResult<Option<Vec<u8>>> {
        self.run(move |s| s.thumbnail(map, index)).await
    }

    async fn cooc_map(&self, map: u64) -> StoreResult<Option<Vec<u8>>> {
        self.run(move |s| s.cooc_map(map)).await
    }

    async fn put_cooc_map(&self, write: CoocWrite) -> StoreResult<Range<u32>> {
        self.run(move |s| s.put_cooc_map(write)).await
    }

    async fn create_localization(&self, new: NewLocalization) -> StoreResult<LocalizationRecord> {
        self.run(move |s| s.create_localization(new)).await
    }

    async fn get_localization(&self, id: u64) -> StoreResult<LocalizationRecord> {
        self.run(move |s| s.get_localization(id)).await
    }

    async fn localization_picture(&self, id: u64) -> StoreResult<Option<Vec<u8>>> {
        self.run(move |s| s.localization_picture(id)).await
    }

    async fn list_localizations(
        &self,
        map: Option<u64>,
        page: PageRequest,
    ) -> StoreResult<Page<LocalizationRecord>> {
        self.run(move |s| s.list_localizations(map, page)).await
    }

    async fn create_trip(&self, new: NewTrip) -> StoreResult<TripRecord> {
        self.run(move |s| s.create_trip(new)).await
    }

    async fn get_trip(&self, id: u64) -> StoreResult<TripRecord> {
        self.run(move |s| s.get_trip(id)).await
    }

    async fn trip_state(&self, id: u64) -> StoreResult<(TripRecord, TripState)> {
        self.run(move |s| s.trip_state(id)).await
    }

    async fn put_trip_batch(&self, id: u64, batch: TripBatch) -> StoreResult<TripRecord> {
        self.run(move |s| s.put_trip_batch(id, batch)).await
    }

    async fn close_trip(&self, id: u64) -> StoreResult<TripRecord> {
        self.run(move |s| s.close_trip(id)).await
    }

    async fn trip_estimates(&self, id: u64, from: u32) -> StoreResult<Vec<FrameEstimate>> {
        self.run(move |s| s.trip_estimates(id, from)).await
    }

    async fn list_trips(&self, map: u64, page: PageRequest) -> StoreResult<Page<TripRecord>> {
        self.run(move |s| s.list_trips(map, page)).await
    }

    async fn idempotency_record(
        &self,
        scope: &str,
        key: &str,
    ) -> StoreResult<Option<IdempotencyRecord>> {
        let (scope, key) = (scope.to_string(), key.to_string());
        self.run(move |s| s.idempotency_record(&scope, &key)).await
    }
}

/// A new empty map of 1-D precomputed descriptors, for the engine's unit tests.
#[cfg(test)]
pub(crate) fn test_map(store: &SledStore) -> u64 {
    store
        .create_map(NewMap {
            id: crate::test_id(),
            name: "m".into(),
            descriptor: seasonloc_app::model::DescriptorSettings::Precomputed { dim: 1 },
            idempotency: None,
        })
        .expect("a new map in a fresh store")
        .id
}

#[cfg(test)]
mod open_tests {
    use super::*;

    /// A folder held by a live handle is recognised as locked (and so waited for), and the
    /// wait ends in a clear `Open` error while the other handle stays open.
    #[test]
    fn a_folder_held_open_is_contention_and_fails_after_the_wait() {
        let dir = tempfile::tempdir().unwrap();
        let held = SledStore::open(dir.path()).unwrap();
        let e = sled::Config::new().path(dir.path()).open().unwrap_err();
        assert!(is_lock_contention(&e), "{e}");
        match SledStore::open(dir.path()) {
            Err(StoreError::Open { location, source }) => {
                assert_eq!(location, dir.path().display().to_string());
                assert!(source.to_string().contains("lock"), "{source}");
            }
            Err(other) => panic!("expected Open, got {other}"),
            Ok(_) => panic!("a folder held open was opened twice"),
        }
        drop(held);
    }

    /// Closing a store and reopening it at once works every time, although sled releases
    /// the folder's lock a moment after the handle is dropped.
    #[test]
    fn a_store_reopens_at_once_after_it_is_dropped() {
        let dir = tempfile::tempdir().unwrap();
        for round in 0..20u32 {
            let store = SledStore::open(dir.path()).unwrap();
            store
                .create_map(NewMap {
                    id: u64::from(round) + 1,
                    name: format!("m{round}"),
                    descriptor: seasonloc_app::model::DescriptorSettings::Precomputed { dim: 2 },
                    idempotency: None,
                })
                .unwrap();
            drop(store);
        }
        let store = SledStore::open(dir.path()).unwrap();
        assert_eq!(store.get_map(20).unwrap().name, "m19");
    }

    /// Other errors are not waited for.
    #[test]
    fn other_open_errors_are_not_contention() {
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("a-file");
        std::fs::write(&file, b"x").unwrap();
        let e = sled::Config::new().path(&file).open().unwrap_err();
        assert!(!is_lock_contention(&e), "{e}");
    }
}
