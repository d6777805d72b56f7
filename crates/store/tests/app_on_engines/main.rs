//! Two `App`s over one real store: two replicas of the service sharing one database, in one
//! process. What a shared engine must make true is checked on both engines (each test runs
//! once on sled and once on PostgreSQL, see [`on_both_engines`]): caches follow the store's
//! versions, and batches of one trip apply one at a time wherever they arrive. Also on both
//! engines: a localization gives its CPU turn back before its result is written.

use std::io::Cursor;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::Arc;

use async_trait::async_trait;
use bytes::Bytes;

use seasonloc_app::model::*;
use seasonloc_app::store::*;
use seasonloc_app::*;
use seasonloc_core::localize::LocalizeOptions;
use seasonloc_core::trip::FrameEstimate;
use seasonloc_core::trip::TripParams;
use seasonloc_core::Matrix;
use seasonloc_store::{PgStore, SledStore};

/// Frame `i` of a synthetic skyline route (64x32), `dark` for the "other season".
fn frame(i: u32, dark: bool) -> ImageInput {
    let mut s = 0x5eed_u64;
    let mut next = |n: u32| {
        s = s
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        ((s >> 33) as u32) % n
    };
    let width = 64 + 8 * 64;
    let mut strip = vec![0u8; (width * 32) as usize];
    let mut x = 0;
    while x < width {
        let (w, roof, shade) = (2 + next(9), 4 + next(26), 40 + next(200) as u8);
        for xx in x..(x + w).min(width) {
            for y in 0..32u32 {
                strip[(y * width + xx) as usize] = if y < roof { 230 - 3 * y as u8 } else { shade };
            }
        }
        x += w;
    }
    let img = image::GrayImage::from_fn(64, 32, |x, y| {
        let v = f32::from(strip[(y * width + i * 8 + x) as usize]);
        image::Luma([if dark { v * 0.6 + 30.0 } else { v } as u8])
    });
    let mut png = Vec::new();
    img.write_to(&mut Cursor::new(&mut png), image::ImageFormat::Png)
        .unwrap();
    ImageInput {
        name: format!("image[{i}]"),
        bytes: Bytes::from(png),
    }
}

/// A store engine the tests run on.
#[derive(Clone, Copy, Debug)]
enum Engine {
    Sled,
    Postgres,
}

/// A fresh, empty store and what keeps it alive; `None` when PostgreSQL is not installed (the
/// test is skipped, except under `CI=true` where it fails).
async fn fresh(engine: Engine) -> Option<(Arc<dyn Store>, Option<tempfile::TempDir>)> {
    match engine {
        Engine::Sled => {
            let dir = tempfile::tempdir().unwrap();
            let store = SledStore::open(dir.path()).unwrap();
            Some((Arc::new(store), Some(dir)))
        }
        Engine::Postgres => {
            let url = tokio::task::spawn_blocking(|| {
                seasonloc_test_support::postgres::database("app test on PostgreSQL")
            })
            .await
            .unwrap()?;
            Some((Arc::new(PgStore::connect(&url).await.unwrap()), None))
        }
    }
}

/// One `#[tokio::test]` per engine for each named `async fn(Engine)`, in modules `sled` and
/// `postgres`.
macro_rules! on_both_engines {
    ($($name:ident),* $(,)?) => {
        mod sled {
            $(
                #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
                async fn $name() {
                    super::$name(super::Engine::Sled).await
                }
            )*
        }
        mod postgres {
            $(
                #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
                async fn $name() {
                    super::$name(super::Engine::Postgres).await
                }
            )*
        }
    };
}

on_both_engines!(
    the_cpu_is_released_before_a_localization_is_stored,
    an_append_on_one_replica_is_seen_by_the_next_localize_on_another,
    a_trip_alternating_between_replicas_equals_one_replica,
    concurrent_batches_of_one_trip_on_two_replicas_apply_one_after_the_other,
    a_trip_is_extended_and_closed_only_by_its_opener_or_an_admin,
);

fn app(store: Arc<dyn Store>) -> App {
    App::new(
        store,
        AppConfig {
            worker_threads: 2,
            max_image_pixels: 1 << 20,
            max_batch_pixels: 1 << 28,
            default_cnn_model: None,
            max_descriptor_len: 1 << 20,
            models: seasonloc_app::ModelPolicy {
                dir: None,
                max_bytes: 1 << 20,
            },
        },
    )
    .unwrap()
}

async fn hog_map(app: &App, images: std::ops::Range<u32>) -> MapRecord {
    let map = app
        .create_map(
            NewMapSpec {
                name: "route".into(),
                descriptor: DescriptorSpec::Settings(DescriptorSettings::Hog {
                    cell_size: 8,
                    resize: None,
                }),
            },
            None,
        )
        .await
        .unwrap()
        .0;
    append(app, map.id, images).await;
    app.get_map(map.id).await.unwrap()
}

async fn append(app: &App, map: u64, images: std::ops::Range<u32>) {
    let frames: Vec<ImageInput> = images.map(|i| frame(i, false)).collect();
    let metas = vec![ImageMeta::default(); frames.len()];
    let target = app.map_for(map, Upload::Images).await.unwrap();
    app.append_images(target, frames, metas, None)
        .await
        .unwrap();
}

fn queries(range: std::ops::Range<u32>) -> LocalizeInput {
    LocalizeInput {
        queries: Queries::Images(range.map(|i| frame(i, true)).collect()),
        options: LocalizeOptions::default(),
        method: None,
    }
}

/// `cpu_done` (the API ends the request's CPU turn there) is called once the result is
/// computed and before it is stored; never for a failed computation or a replay.
async fn the_cpu_is_released_before_a_localization_is_stored(engine: Engine) {
    let Some((plain, _dir)) = fresh(engine).await else {
        return;
    };
    let probed = Arc::new(Probed::new(plain, None));
    let app = app(Arc::clone(&probed) as Arc<dyn Store>);
    let map = hog_map(&app, 0..20).await;
    let hook = |flag: &Arc<AtomicBool>| {
        let flag = Arc::clone(flag);
        move || flag.store(true, Ordering::SeqCst)
    };
    let key = || Some(Idempotency::new("k-1", b"the same request".to_vec()).unwrap());
    let (first, replayed) = app
        .localize(map.id, queries(5..15), key(), hook(&probed.computed))
        .await
        .unwrap();
    assert!(!replayed);
    assert_eq!(*probed.computed_when_stored.lock().unwrap(), [true]);
    // A replay computes nothing.
    let again = Arc::new(AtomicBool::new(false));
    let (second, replayed) = app
        .localize(map.id, queries(5..15), key(), hook(&again))
        .await
        .unwrap();
    assert!(replayed);
    assert_eq!(second.id, first.id);
    assert!(!again.load(Ordering::SeqCst));
    // Nor does a computation that fails (descriptors of another length than the map's).
    let failed = Arc::new(AtomicBool::new(false));
    let wrong = LocalizeInput {
        queries: Queries::Descriptors(Matrix::zeros(2, 3)),
        options: LocalizeOptions::default(),
        method: None,
    };
    let e = app
        .localize(map.id, wrong, None, hook(&failed))
        .await
        .unwrap_err();
    assert!(matches!(e, AppError::DescriptorLength(_)), "{e}");
    assert!(!failed.load(Ordering::SeqCst));
    assert_eq!(probed.computed_when_stored.lock().unwrap().len(), 1);
}

async fn an_append_on_one_replica_is_seen_by_the_next_localize_on_another(engine: Engine) {
    let Some((store, _dir)) = fresh(engine).await else {
        return;
    };
    let (a, b) = (app(Arc::clone(&store)), app(Arc::clone(&store)));
    let map = hog_map(&a, 0..20).await;
    // B caches the 20-image matrix.
    let first = b
        .localize(map.id, queries(5..15), None, || {})
        .await
        .unwrap()
        .0;
    assert_eq!(first.result.reference_count, 20);
    // A appends; B's next localization uses all 40 images, exactly as a fresh process does.
    append(&a, map.id, 20..40).await;
    let second = b
        .localize(map.id, queries(25..35), None, || {})
        .await
        .unwrap()
        .0;
    assert_eq!(second.result.reference_count, 40);
    let fresh = app(Arc::clone(&store))
        .localize(map.id, queries(25..35), None, || {})
        .await
        .unwrap()
        .0;
    assert_eq!(second.result.hypotheses, fresh.result.hypotheses);
    assert_eq!(second.result.predictions, fresh.result.predictions);
    // The queries are frames 25..35 of the route: the appended part was used.
    let refs: Vec<usize> = second
        .result
        .predictions
        .iter()
        .map(|p| p.reference)
        .collect();
    assert!(refs.iter().any(|&r| r >= 20), "{refs:?}");
    // A map deleted on one replica is gone on the other, whatever it cached.
    a.delete_map(map.id).await.unwrap();
    assert!(matches!(
        b.localize(map.id, queries(0..3), None, || {}).await,
        Err(AppError::Store(StoreError::MapNotFound(_)))
    ));
}

async fn a_trip_alternating_between_replicas_equals_one_replica(engine: Engine) {
    let Some((store, _dir)) = fresh(engine).await else {
        return;
    };
    let (a, b) = (app(Arc::clone(&store)), app(Arc::clone(&store)));
    let map = hog_map(&a, 0..40).await;
    let params = TripParams {
        lag: 6,
        ..TripParams::default()
    };
    let shared = a.open_trip(map.id, params, None, None).await.unwrap().0;
    let single = a.open_trip(map.id, params, None, None).await.unwrap().0;
    for (k, start) in (0..30).step_by(5).enumerate() {
        let batch: Vec<ImageInput> = (start..start + 5).map(|i| frame(i, true)).collect();
        let replica = if k % 2 == 0 { &a } else { &b };
        let x = replica
            .post_frames(shared.id, batch.clone(), None, None)
            .await
            .unwrap();
        let y = a.post_frames(single.id, batch, None, None).await.unwrap();
        assert_eq!(x.update, y.update, "batch {k}");
    }
    let (_, s1) = store.trip_state(shared.id).await.unwrap();
    let (_, s2) = store.trip_state(single.id).await.unwrap();
    assert_eq!(s1, s2);
    assert_eq!(
        a.get_trip(shared.id, 0).await.unwrap().1,
        b.get_trip(single.id, 0).await.unwrap().1
    );
}

/// The real store with two probes. With `barrier`, the first two reads of a trip's record
/// (the first read of a batch) wait for each other: two replicas then compute their batches
/// from the same state, and one of the conditional writes must lose. `computed`, set by a
/// test's `cpu_done` hook, is read when a localization is stored (`computed_when_stored`).
struct Probed {
    inner: Arc<dyn Store>,
    reads: AtomicUsize,
    barrier: Option<tokio::sync::Barrier>,
    computed: Arc<AtomicBool>,
    computed_when_stored: std::sync::Mutex<Vec<bool>>,
}

impl Probed {
    fn new(inner: Arc<dyn Store>, barrier: Option<tokio::sync::Barrier>) -> Self {
        Probed {
            inner,
            reads: AtomicUsize::new(0),
            barrier,
            computed: Arc::default(),
            computed_when_stored: std::sync::Mutex::default(),
        }
    }
}

#[async_trait]
impl Store for Probed {
    fn location(&self) -> String {
        self.inner.location()
    }
    async fn check(&self) -> StoreResult<()> {
        self.inner.check().await
    }
    async fn flush(&self) -> StoreResult<()> {
        self.inner.flush().await
    }
    async fn create_map(&self, new: NewMap) -> StoreResult<MapRecord> {
        self.inner.create_map(new).await
    }
    async fn get_map(&self, id: u64) -> StoreResult<MapRecord> {
        self.inner.get_map(id).await
    }
    async fn list_maps(&self) -> StoreResult<Vec<MapRecord>> {
        self.inner.list_maps().await
    }
    async fn delete_map(&self, id: u64) -> StoreResult<()> {
        self.inner.delete_map(id).await
    }
    async fn append_images(&self, batch: ImageBatch) -> StoreResult<std::ops::Range<u32>> {
        self.inner.append_images(batch).await
    }
    async fn descriptors(&self, map: u64, rows: std::ops::Range<u32>) -> StoreResult<Matrix> {
        self.inner.descriptors(map, rows).await
    }
    async fn image_metadata(
        &self,
        map: u64,
        rows: std::ops::Range<u32>,
    ) -> StoreResult<Vec<ImageMeta>> {
        self.inner.image_metadata(map, rows).await
    }
    async fn cooc_map(&self, map: u64) -> StoreResult<Option<Vec<u8>>> {
        self.inner.cooc_map(map).await
    }
    async fn put_cooc_map(&self, write: CoocWrite) -> StoreResult<std::ops::Range<u32>> {
        self.inner.put_cooc_map(write).await
    }
    async fn create_localization(&self, new: NewLocalization) -> StoreResult<LocalizationRecord> {
        let computed = self.computed.load(Ordering::SeqCst);
        self.computed_when_stored.lock().unwrap().push(computed);
        self.inner.create_localization(new).await
    }
    async fn get_localization(&self, id: u64) -> StoreResult<LocalizationRecord> {
        self.inner.get_localization(id).await
    }
    async fn list_localizations(
        &self,
        map: Option<u64>,
        page: PageRequest,
    ) -> StoreResult<Page<LocalizationRecord>> {
        self.inner.list_localizations(map, page).await
    }
    async fn create_trip(&self, new: NewTrip) -> StoreResult<TripRecord> {
        self.inner.create_trip(new).await
    }
    async fn get_trip(&self, id: u64) -> StoreResult<TripRecord> {
        let record = self.inner.get_trip(id).await;
        if let Some(barrier) = &self.barrier {
            if self.reads.fetch_add(1, Ordering::SeqCst) < 2 {
                barrier.wait().await;
            }
        }
        record
    }
    async fn trip_state(&self, id: u64) -> StoreResult<(TripRecord, TripState)> {
        self.inner.trip_state(id).await
    }
    async fn put_trip_batch(&self, id: u64, batch: TripBatch) -> StoreResult<TripRecord> {
        self.inner.put_trip_batch(id, batch).await
    }
    async fn close_trip(&self, id: u64) -> StoreResult<TripRecord> {
        self.inner.close_trip(id).await
    }
    async fn trip_estimates(&self, id: u64, from: u32) -> StoreResult<Vec<FrameEstimate>> {
        self.inner.trip_estimates(id, from).await
    }
    async fn thumbnail(&self, map: u64, index: u32) -> StoreResult<Option<Vec<u8>>> {
        self.inner.thumbnail(map, index).await
    }
    async fn localization_picture(&self, id: u64) -> StoreResult<Option<Vec<u8>>> {
        self.inner.localization_picture(id).await
    }
    async fn list_trips(&self, map: u64, page: PageRequest) -> StoreResult<Page<TripRecord>> {
        self.inner.list_trips(map, page).await
    }
    async fn idempotency_record(
        &self,
        scope: &str,
        key: &str,
    ) -> StoreResult<Option<IdempotencyRecord>> {
        self.inner.idempotency_record(scope, key).await
    }
}

async fn concurrent_batches_of_one_trip_on_two_replicas_apply_one_after_the_other(engine: Engine) {
    let Some((plain, _dir)) = fresh(engine).await else {
        return;
    };
    let gated: Arc<dyn Store> = Arc::new(Probed::new(
        Arc::clone(&plain),
        Some(tokio::sync::Barrier::new(2)),
    ));
    let (a, b) = (app(Arc::clone(&gated)), app(Arc::clone(&gated)));
    let map = hog_map(&app(Arc::clone(&plain)), 0..30).await;
    let trip = a
        .open_trip(map.id, TripParams::default(), None, None)
        .await
        .unwrap()
        .0;
    let first: Vec<ImageInput> = (0..4).map(|i| frame(i, true)).collect();
    let second: Vec<ImageInput> = (4..10).map(|i| frame(i, true)).collect();
    let (x, y) = tokio::join!(
        a.post_frames(trip.id, first.clone(), None, None),
        b.post_frames(trip.id, second.clone(), None, None)
    );
    let (x, y) = (x.unwrap(), y.unwrap());
    // Both applied, once each: one saw the other's frames already in the trip.
    let mut counts = [x.trip.frame_count, y.trip.frame_count];
    counts.sort_unstable();
    assert!(counts == [4, 10] || counts == [6, 10], "{counts:?}");
    let (record, estimates) = a.get_trip(trip.id, 0).await.unwrap();
    assert_eq!(record.frame_count, 10);
    assert_eq!(estimates.len(), 10);
    // The stored state is that of the two batches applied in the order they won.
    let order = if x.trip.frame_count == 4 {
        [first, second]
    } else {
        [second, first]
    };
    let single = app(Arc::clone(&plain));
    let reference = single
        .open_trip(map.id, TripParams::default(), None, None)
        .await
        .unwrap()
        .0;
    for batch in order {
        single
            .post_frames(reference.id, batch, None, None)
            .await
            .unwrap();
    }
    let (_, want) = plain.trip_state(reference.id).await.unwrap();
    let (_, got) = plain.trip_state(trip.id).await.unwrap();
    assert_eq!(got, want);
}

/// Issue 42, defect 8: the key that opened a trip is stored with it (read back by another
/// replica), and another non-admin key may neither post frames to it nor close it (403,
/// nothing applied); the opener and an admin may. A trip opened without a caller (keyless
/// serving) has no owner and refuses no one.
async fn a_trip_is_extended_and_closed_only_by_its_opener_or_an_admin(engine: Engine) {
    use seasonloc_app::caller::Caller;
    let Some((store, _dir)) = fresh(engine).await else {
        return;
    };
    let (a, b) = (app(Arc::clone(&store)), app(Arc::clone(&store)));
    let map = hog_map(&a, 0..30).await;
    let key = |name: &str, admin: bool| Caller {
        name: name.into(),
        admin,
    };
    let (va, vb, ops) = (
        key("vehicle-a", false),
        key("vehicle-b", false),
        key("ops", true),
    );
    let trip = a
        .open_trip(map.id, TripParams::default(), None, Some(&va))
        .await
        .unwrap()
        .0;
    assert_eq!(trip.owner.as_deref(), Some("vehicle-a"));
    let batch = |lo: u32| (lo..lo + 3).map(|i| frame(i, true)).collect::<Vec<_>>();
    let e = b
        .post_frames(trip.id, batch(0), None, Some(&vb))
        .await
        .unwrap_err();
    assert_eq!(e.code(), ErrorCode::Forbidden, "{e}");
    let e = b.close_trip(trip.id, Some(&vb)).await.unwrap_err();
    assert_eq!(e.code(), ErrorCode::Forbidden, "{e}");
    let stored = store.get_trip(trip.id).await.unwrap();
    assert_eq!((stored.frame_count, stored.closed_ms), (0, None));
    assert_eq!(stored.owner.as_deref(), Some("vehicle-a"));
    b.post_frames(trip.id, batch(0), None, Some(&va))
        .await
        .unwrap();
    a.post_frames(trip.id, batch(3), None, Some(&ops))
        .await
        .unwrap();
    assert!(b
        .close_trip(trip.id, Some(&ops))
        .await
        .unwrap()
        .closed_ms
        .is_some());
    let open = b
        .open_trip(map.id, TripParams::default(), None, None)
        .await
        .unwrap()
        .0;
    assert_eq!(store.get_trip(open.id).await.unwrap().owner, None);
    a.post_frames(open.id, batch(0), None, Some(&vb))
        .await
        .unwrap();
    assert!(a
        .close_trip(open.id, Some(&vb))
        .await
        .unwrap()
        .closed_ms
        .is_some());
}
