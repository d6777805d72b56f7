//! The PostgreSQL engine against a real server ([`testing`]): start-up of several replicas at
//! once, compact descriptor batches read back across batch boundaries, conditional writes, and
//! what an unreachable database looks like. (The use-case and HTTP suites run on this engine
//! too: `seasonloc_app::tests`, `tests/service_pg`.)

use super::*;
use seasonloc_app::model::DescriptorSettings;
use seasonloc_app::store::TripStateWrite;
use seasonloc_core::calibration::FrameStatus;
use seasonloc_core::trip::{TripParams, TripStatus};
use seasonloc_test_support::postgres as testing;

async fn database(test: &str) -> Option<String> {
    let test = test.to_string();
    tokio::task::spawn_blocking(move || testing::database(&test))
        .await
        .unwrap()
}

fn rows(n: usize, dim: usize, base: f32) -> Matrix {
    Matrix::from_vec(n, dim, (0..n * dim).map(|k| base + k as f32).collect()).unwrap()
}

fn precomputed(dim: u32) -> NewMap {
    NewMap {
        id: crate::test_id(),
        name: "m".into(),
        descriptor: DescriptorSettings::Precomputed { dim },
        idempotency: None,
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn replicas_starting_together_migrate_once() {
    let Some(url) = database("migrate").await else {
        return;
    };
    let stores = futures_join_all(
        (0..4)
            .map(|_| {
                let url = url.clone();
                async move { PgStore::connect(&url).await }
            })
            .collect::<Vec<_>>(),
    )
    .await;
    for s in &stores {
        let s = s.as_ref().unwrap();
        assert_eq!(s.schema_version().await.unwrap(), migrate::newest_version());
    }
    let client = stores[0].as_ref().unwrap().client().await.unwrap();
    let applied: i64 = client
        .query_one("SELECT count(*) FROM seasonloc_schema", &[])
        .await
        .unwrap()
        .get(0);
    assert_eq!(applied, migrate::MIGRATIONS.len() as i64);
    // A database from a newer build is refused, not written.
    client
        .execute(
            "INSERT INTO seasonloc_schema VALUES (999, 'future', 0)",
            &[],
        )
        .await
        .unwrap();
    assert!(matches!(
        PgStore::connect(&url).await,
        Err(StoreError::UnsupportedSchema { found: 999, .. })
    ));
}

/// Joins futures concurrently without another dependency.
async fn futures_join_all<F: std::future::Future + Send + 'static>(
    futures: Vec<F>,
) -> Vec<F::Output>
where
    F::Output: Send + 'static,
{
    let handles: Vec<_> = futures.into_iter().map(tokio::spawn).collect();
    let mut out = Vec::with_capacity(handles.len());
    for h in handles {
        out.push(h.await.unwrap());
    }
    out
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn batches_read_back_across_their_boundaries() {
    let Some(url) = database("batches").await else {
        return;
    };
    let store = PgStore::connect(&url).await.unwrap();
    let map = store.create_map(precomputed(3)).await.unwrap();
    assert_eq!(map.dim, Some(3));
    let meta = ImageMeta {
        label: Some("bridge".into()),
        latitude: Some(63.4),
        ..ImageMeta::default()
    };
    let mut metas = vec![ImageMeta::default(); 4];
    metas[2] = meta.clone();
    let a = store
        .append_images(ImageBatch::new(map.id, rows(4, 3, 0.0), metas).unwrap())
        .await
        .unwrap();
    let b = store
        .append_images(
            ImageBatch::new(map.id, rows(3, 3, 100.0), vec![ImageMeta::default(); 3]).unwrap(),
        )
        .await
        .unwrap();
    assert_eq!((a, b), (0..4, 4..7));
    assert_eq!(store.get_map(map.id).await.unwrap().image_count, 7);
    let all = store.descriptors(map.id, 0..7).await.unwrap();
    assert_eq!(all.row(3), &[9.0, 10.0, 11.0]);
    assert_eq!(all.row(4), &[100.0, 101.0, 102.0]);
    let middle = store.descriptors(map.id, 3..5).await.unwrap();
    assert_eq!(middle.rows(), 2);
    assert_eq!(middle.row(0), all.row(3));
    assert_eq!(middle.row(1), all.row(4));
    assert_eq!(store.descriptors(map.id, 7..7).await.unwrap().rows(), 0);
    assert_eq!(
        store.image_metadata(map.id, 2..5).await.unwrap(),
        vec![meta, ImageMeta::default(), ImageMeta::default()]
    );
    // Wrong length: nothing written.
    let err = store
        .append_images(
            ImageBatch::new(map.id, rows(1, 4, 0.0), vec![ImageMeta::default()]).unwrap(),
        )
        .await
        .unwrap_err();
    assert!(
        matches!(
            err,
            StoreError::DimensionMismatch {
                expected: 3,
                got: 4,
                ..
            }
        ),
        "{err}"
    );
    assert_eq!(store.get_map(map.id).await.unwrap().image_count, 7);
    // Settings survive the round trip.
    let hog = NewMap {
        id: crate::test_id(),
        name: "h".into(),
        descriptor: DescriptorSettings::Hog {
            cell_size: 8,
            resize: Some((64, 32)),
        },
        idempotency: None,
    };
    let h = store.create_map(hog.clone()).await.unwrap();
    let listed = store.list_maps().await.unwrap();
    assert_eq!(listed.len(), 2);
    assert_eq!(listed[1], h);
    assert_eq!(listed[1].descriptor, hog.descriptor);
    assert!(h.id > map.id);
    // A taken id is refused and nothing is written (the use-case layer draws another).
    assert!(matches!(
        store.create_map(hog.clone()).await,
        Err(StoreError::IdTaken(id)) if id == h.id
    ));
    assert_eq!(store.list_maps().await.unwrap().len(), 2);
    // Deleting a map takes everything under it.
    store.delete_map(map.id).await.unwrap();
    assert!(matches!(
        store.descriptors(map.id, 0..1).await,
        Err(StoreError::MapNotFound(_))
    ));
    assert!(matches!(
        store.delete_map(map.id).await,
        Err(StoreError::MapNotFound(_))
    ));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn thumbnails_and_pictures_ride_in_their_writes() {
    use seasonloc_app::model::{LocalizationParams, LocalizationResult, LocalizationTimings};
    let Some(url) = database("pictures").await else {
        return;
    };
    let store = PgStore::connect(&url).await.unwrap();
    let map = store.create_map(precomputed(3)).await.unwrap();
    let metas = vec![ImageMeta::default(); 2];
    // A batch without thumbnails (precomputed descriptors), then one with.
    store
        .append_images(ImageBatch::new(map.id, rows(2, 3, 0.0), metas.clone()).unwrap())
        .await
        .unwrap();
    let with = ImageBatch::new(map.id, rows(2, 3, 9.0), metas.clone())
        .unwrap()
        .with_thumbnails(vec![b"jpeg-2".to_vec(), b"jpeg-3".to_vec()])
        .unwrap();
    assert_eq!(store.append_images(with).await.unwrap(), 2..4);
    // A refused batch writes neither its rows nor its thumbnails.
    let wrong = ImageBatch::new(map.id, rows(1, 4, 0.0), metas[..1].to_vec())
        .unwrap()
        .with_thumbnails(vec![b"never".to_vec()])
        .unwrap();
    assert!(store.append_images(wrong).await.is_err());
    assert_eq!(store.thumbnail(map.id, 0).await.unwrap(), None);
    assert_eq!(store.thumbnail(map.id, 1).await.unwrap(), None);
    assert_eq!(
        store.thumbnail(map.id, 2).await.unwrap(),
        Some(b"jpeg-2".to_vec())
    );
    assert_eq!(
        store.thumbnail(map.id, 3).await.unwrap(),
        Some(b"jpeg-3".to_vec())
    );
    assert_eq!(store.thumbnail(map.id, 4).await.unwrap(), None);
    assert!(matches!(
        store.thumbnail(u64::MAX - 1, 0).await,
        Err(StoreError::MapNotFound(_))
    ));

    let result = LocalizationResult {
        query_count: 1,
        reference_count: 4,
        params: LocalizationParams::new(
            &seasonloc_core::localize::LocalizeOptions::default(),
            1.0,
            None,
        ),
        total_cost: 0.0,
        hypotheses: Vec::new(),
        predictions: Vec::new(),
        timings: LocalizationTimings::default(),
        picture: None,
    };
    let plain = store
        .create_localization(NewLocalization {
            id: crate::test_id(),
            map_id: map.id,
            result: result.clone(),
            picture: None,
            idempotency: None,
        })
        .await
        .unwrap();
    let pictured = store
        .create_localization(NewLocalization {
            id: crate::test_id(),
            map_id: map.id,
            result,
            picture: Some(b"png".to_vec()),
            idempotency: None,
        })
        .await
        .unwrap();
    assert_eq!(store.localization_picture(plain.id).await.unwrap(), None);
    assert_eq!(
        store.localization_picture(pictured.id).await.unwrap(),
        Some(b"png".to_vec())
    );
    // Deleting the map takes its thumbnails and its results' pictures.
    store.delete_map(map.id).await.unwrap();
    assert!(matches!(
        store.thumbnail(map.id, 2).await,
        Err(StoreError::MapNotFound(_))
    ));
    assert!(matches!(
        store.localization_picture(pictured.id).await,
        Err(StoreError::LocalizationNotFound(_))
    ));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn trip_batches_and_cooc_maps_are_conditional() {
    let Some(url) = database("conditional").await else {
        return;
    };
    let store = PgStore::connect(&url).await.unwrap();
    let map = store.create_map(precomputed(1)).await.unwrap();
    let trip = store
        .create_trip(NewTrip {
            id: crate::test_id(),
            map_id: map.id,
            reference_count: 5,
            params: TripParams::default(),
            owner: None,
            base: vec![b'B'; 3000],
            snapshot: vec![0],
            idempotency: None,
        })
        .await
        .unwrap();
    // A batch of `n` frames: their log rows, and a snapshot `state` (dropping the log rows
    // before the batch) when `state` is even.
    let batch = |expected: u64, n: u64, state: u8| TripBatch {
        expected_frames: expected,
        frame_count: expected + n,
        status: TripStatus::Lost,
        state: TripStateWrite {
            base: None,
            snapshot: state.is_multiple_of(2).then(|| vec![state; 3]),
            log: (expected..expected + n)
                .map(|f| (f, vec![f as u8; 4000]))
                .collect(),
            drop_log_before: state.is_multiple_of(2).then_some(expected),
        },
        estimates: (expected.saturating_sub(1)..expected + n)
            .map(|f| FrameEstimate {
                frame: f as usize,
                reference: (f % 2 == 0).then_some(f as usize + state as usize),
                confidence: f as f64,
                p_correct: 1.0 / (1.0 + f as f64),
                status: FrameStatus::ALL[f as usize % 4],
            })
            .collect(),
        idempotency: None,
    };
    store.put_trip_batch(trip.id, batch(0, 3, 1)).await.unwrap();
    let r = store.put_trip_batch(trip.id, batch(3, 2, 2)).await.unwrap();
    assert_eq!((r.frame_count, r.status), (5, Some(TripStatus::Lost)));
    assert!(matches!(
        store.put_trip_batch(trip.id, batch(3, 2, 9)).await,
        Err(StoreError::TripConflict {
            stored: 5,
            expected: 3,
            ..
        })
    ));
    let (rec, state) = store.trip_state(trip.id).await.unwrap();
    assert_eq!(rec.frame_count, 5);
    assert_eq!(
        state,
        TripState::Parts {
            base: vec![b'B'; 3000],
            snapshot: vec![2; 3],
            log: vec![(3, vec![3; 4000]), (4, vec![4; 4000])],
        }
    );
    let est = store.trip_estimates(trip.id, 0).await.unwrap();
    assert_eq!(est.len(), 5);
    // Read from a frame on: the same estimates, the earlier ones left out.
    assert_eq!(store.trip_estimates(trip.id, 3).await.unwrap(), est[3..]);
    assert!(store.trip_estimates(trip.id, 9).await.unwrap().is_empty());
    // Frame 2 was revised by the second batch (its window).
    assert_eq!(est[2].reference, Some(4));
    assert_eq!(est[3].reference, None);
    // A trip written by schema 1-3: one blob in `state`, read as such; the next batch with a
    // base replaces it by parts in the same transaction.
    let other = store.create_map(precomputed(1)).await.unwrap();
    let old = store
        .create_trip(NewTrip {
            id: crate::test_id(),
            map_id: other.id,
            reference_count: 5,
            params: TripParams::default(),
            owner: None,
            base: vec![1],
            snapshot: vec![2],
            idempotency: None,
        })
        .await
        .unwrap();
    store
        .client()
        .await
        .unwrap()
        .execute(
            "UPDATE trips SET state = $2, base = NULL, snapshot = NULL WHERE id = $1",
            &[&db_id(old.id).unwrap(), &vec![7u8; 5]],
        )
        .await
        .unwrap();
    assert_eq!(
        store.trip_state(old.id).await.unwrap().1,
        TripState::Legacy(vec![7; 5])
    );
    let mut first = batch(0, 2, 4);
    first.state.base = Some(vec![b'B', 1]);
    store.put_trip_batch(old.id, first).await.unwrap();
    assert_eq!(
        store.trip_state(old.id).await.unwrap().1,
        TripState::Parts {
            base: vec![b'B', 1],
            snapshot: vec![4; 3],
            log: vec![(0, vec![0; 4000]), (1, vec![1; 4000])],
        }
    );
    let closed = store.close_trip(trip.id).await.unwrap();
    assert!(closed.closed_ms.is_some());
    assert_eq!(store.close_trip(trip.id).await.unwrap(), closed);
    assert!(matches!(
        store.put_trip_batch(trip.id, batch(5, 1, 3)).await,
        Err(StoreError::TripClosed(_))
    ));
    assert!(matches!(
        store.trip_estimates(u64::MAX, 0).await,
        Err(StoreError::TripNotFound(_))
    ));
    let page = store
        .list_trips(
            map.id,
            PageRequest {
                before: None,
                limit: 1,
            },
        )
        .await
        .unwrap();
    assert_eq!((page.items.len(), page.next), (1, None));

    let cooc = store
        .create_map(NewMap {
            id: crate::test_id(),
            name: "c".into(),
            descriptor: DescriptorSettings::Cooc(Box::default()),
            idempotency: None,
        })
        .await
        .unwrap();
    let write = |previous: Option<&[u8]>, encoded: &[u8], n: usize| CoocWrite {
        map: cooc.id,
        previous: previous.map(<[u8]>::to_vec),
        encoded: encoded.to_vec(),
        new_images: vec![ImageMeta::default(); n],
        idempotency: None,
    };
    assert_eq!(store.cooc_map(cooc.id).await.unwrap(), None);
    assert_eq!(
        store.put_cooc_map(write(None, b"v1", 3)).await.unwrap(),
        0..3
    );
    assert!(matches!(
        store.put_cooc_map(write(None, b"v1'", 0)).await,
        Err(StoreError::Conflict(_))
    ));
    assert_eq!(
        store
            .put_cooc_map(write(Some(b"v1"), b"v2", 2))
            .await
            .unwrap(),
        3..5
    );
    assert_eq!(
        store.cooc_map(cooc.id).await.unwrap().as_deref(),
        Some(&b"v2"[..])
    );
    assert_eq!(store.image_metadata(cooc.id, 0..5).await.unwrap().len(), 5);
    assert_eq!(store.descriptors(cooc.id, 0..5).await.unwrap().rows(), 5);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_unreachable_database_is_unavailable_and_then_back() {
    let Some(bin) = testing::require("unreachable database") else {
        return;
    };
    let server = tokio::task::spawn_blocking(move || testing::TestServer::start(&bin).unwrap())
        .await
        .unwrap();
    let server = std::sync::Arc::new(server);
    let url = server.database().unwrap();
    let store = PgStore::connect(&url).await.unwrap();
    assert!(!store.location().contains("password"));
    let map = store.create_map(precomputed(2)).await.unwrap();
    let s = std::sync::Arc::clone(&server);
    tokio::task::spawn_blocking(move || s.pause().unwrap())
        .await
        .unwrap();
    let started = std::time::Instant::now();
    for _ in 0..3 {
        let e = store.get_map(map.id).await.unwrap_err();
        assert!(matches!(e, StoreError::Unavailable(_)), "{e}");
        assert!(matches!(
            store.check().await,
            Err(StoreError::Unavailable(_))
        ));
    }
    assert!(
        started.elapsed() < CONNECT_TIMEOUT * 4,
        "{:?}",
        started.elapsed()
    );
    // A new replica cannot open the store.
    assert!(matches!(
        PgStore::connect(&url).await,
        Err(StoreError::Open { .. })
    ));
    let s = std::sync::Arc::clone(&server);
    tokio::task::spawn_blocking(move || s.resume().unwrap())
        .await
        .unwrap();
    store.check().await.unwrap();
    assert_eq!(store.get_map(map.id).await.unwrap().id, map.id);
}

/// A hung database (issue 42, defect 7: every server process SIGSTOPped, its sockets open, so
/// nothing is refused and nothing answers): calls in flight and new calls fail with
/// `Unavailable` within the statement timeout plus a second, calls after an unanswered one
/// within about a second more, and the store answers again once the server runs.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_hung_database_fails_calls_within_the_timeouts_and_recovers() {
    let Some(bin) = testing::require("hung database") else {
        return;
    };
    let server = tokio::task::spawn_blocking(move || testing::TestServer::start(&bin).unwrap())
        .await
        .unwrap();
    let server = std::sync::Arc::new(server);
    let url = server.database().unwrap();
    let options = PgOptions {
        statement_timeout: Duration::from_secs(2),
        tcp_user_timeout: Duration::from_secs(4),
    };
    let store = PgStore::connect_with(&url, &options).await.unwrap();
    let map = store.create_map(precomputed(2)).await.unwrap();
    // Several pooled connections, all idle when the server hangs.
    let warm: Vec<_> = (0..4)
        .map(|_| {
            let s = store.clone();
            tokio::spawn(async move { s.get_map(map.id).await.map(|_| ()) })
        })
        .collect();
    for w in warm {
        w.await.unwrap().unwrap();
    }
    let s = std::sync::Arc::clone(&server);
    tokio::task::spawn_blocking(move || s.freeze().unwrap())
        .await
        .unwrap();
    let bound = options.statement_timeout + ANSWER_MARGIN + Duration::from_millis(800);
    let started = std::time::Instant::now();
    let calls: Vec<_> = (0..3)
        .map(|k| {
            let s = store.clone();
            tokio::spawn(async move {
                let t = std::time::Instant::now();
                let r = match k {
                    0 => s.get_map(map.id).await.map(|_| ()),
                    1 => s.list_maps().await.map(|_| ()),
                    _ => s.create_map(precomputed(3)).await.map(|_| ()),
                };
                (r, t.elapsed())
            })
        })
        .collect();
    for c in calls {
        let (r, took) = tokio::time::timeout(Duration::from_secs(30), c)
            .await
            .expect("a call on a hung database was still waiting after 30 s")
            .unwrap();
        assert!(
            matches!(r, Err(StoreError::Unavailable(_))),
            "a call on a hung database: {r:?}"
        );
        assert!(took < bound, "a call on a hung database took {took:?}");
    }
    // A call after an unanswered one (a request queued behind another) fails sooner.
    let t = std::time::Instant::now();
    let r = store.get_map(map.id).await;
    assert!(matches!(r, Err(StoreError::Unavailable(_))), "{r:?}");
    assert!(
        t.elapsed() < SUSPECT_DEADLINE + Duration::from_millis(800),
        "{:?}",
        t.elapsed()
    );
    assert!(started.elapsed() < Duration::from_secs(10));
    let s = std::sync::Arc::clone(&server);
    tokio::task::spawn_blocking(move || s.thaw().unwrap())
        .await
        .unwrap();
    let back = std::time::Instant::now();
    loop {
        match store.get_map(map.id).await {
            Ok(m) => {
                assert_eq!(m.id, map.id);
                break;
            }
            Err(e) if back.elapsed() < Duration::from_secs(15) => {
                eprintln!("after the hang: {e}");
                tokio::time::sleep(Duration::from_millis(200)).await;
            }
            Err(e) => panic!("the store did not answer 15 s after the database resumed: {e}"),
        }
    }
    store.check().await.unwrap();
}
