//! Golden store: every record kind of layout 4 as written by the code *before* the
//! architecture refactor (issue 10), and the proof that today's code reads those bytes and
//! writes them back identically.
//!
//! `tests/data/store-layout4.golden` (one line per sled key: `hex(key) hex(value)`) was written
//! once by an ignored generator test on commit 80e0535 (the last commit before the refactor;
//! see it there), through that code's store API, with the inputs below: maps of all four
//! descriptor kinds, images with metadata, a co-occurrence map, a flow and a `cooc-seq`
//! localization document, one trip with two batches and one closed trip. Never regenerate it:
//! its point is that it was written by other code.

use seasonloc_core::calibration::FrameStatus;
use std::sync::Arc;

use super::*;
use seasonloc_app::model::{
    CnnSettings, DescriptorSettings, LocalizationRecord, LocalizationResult,
};
use seasonloc_app::model::{LocalizationParams, LocalizationTimings};
use seasonloc_app::store::TripStateWrite;
use seasonloc_core::cooc::CoocMethod;
use seasonloc_core::features::cnn::{CnnOptions, CnnResize, ModelIdentity};
use seasonloc_core::localize::{localize, LocalizeOptions};
use seasonloc_core::trip::{column_prior, Trip, TripParams, TripStatus};

/// Path of the golden dump.
pub(crate) fn golden_path() -> std::path::PathBuf {
    std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../tests/data/store-layout4.golden")
}

/// Deterministic descriptor rows.
pub(crate) fn rows(n: usize, dim: usize, seed: usize) -> Matrix {
    Matrix::from_vec(
        n,
        dim,
        (0..n * dim)
            .map(|k| ((k * 7 + seed * 13) % 11) as f32 / 4.0 + 0.25)
            .collect(),
    )
    .unwrap()
}

/// Deterministic raw cosine batch for the trips.
pub(crate) fn cos_batch(first: usize, n: usize, d: usize) -> Matrix {
    let mut m = Matrix::zeros(n, d);
    for k in 0..n {
        for j in 0..d {
            let i = first + k;
            let peak = if j == i % d { 0.5 } else { 0.0 };
            m.set(k, j, 0.3 + ((i * 31 + j * 17) % 23) as f32 / 100.0 + peak);
        }
    }
    m
}

pub(crate) fn hog_metas() -> Vec<ImageMeta> {
    vec![
        ImageMeta::default(),
        ImageMeta {
            timestamp: Some("2020-06-01T12:00:00Z".into()),
            latitude: Some(63.4305),
            longitude: Some(10.3951),
            label: Some("bridge ✓".into()),
        },
        ImageMeta {
            label: Some("tunnel".into()),
            ..ImageMeta::default()
        },
    ]
}

pub(crate) fn cnn_crop() -> CnnSettings {
    CnnSettings {
        options: CnnOptions::efficientnet_lite0("/models/effnet.onnx"),
        identity: ModelIdentity {
            sha256: "ab".repeat(32),
            layer: "block10".into(),
            preprocessing: "224x224 RGB, short side 256 + centre crop".into(),
        },
    }
}

pub(crate) fn cnn_stretch() -> CnnSettings {
    CnnSettings {
        options: CnnOptions {
            resize: CnnResize::Stretch,
            mean: [1.5, -2.0, 0.25],
            layer: "pooled".into(),
            ..CnnOptions::efficientnet_lite0("m.onnx")
        },
        identity: ModelIdentity {
            sha256: "00".repeat(32),
            layer: "pooled".into(),
            preprocessing: String::new(),
        },
    }
}

/// The co-occurrence settings the golden map was written with: the library defaults of that
/// commit spelled out (80 keypoints, virtual images on), so that a later change of the defaults
/// cannot change what the stored record is expected to hold.
pub(crate) fn cooc_params() -> seasonloc_core::cooc::CoocParams {
    seasonloc_core::cooc::CoocParams {
        keypoints: seasonloc_core::cooc::keypoints::KeypointParams {
            max_keypoints: 80,
            ..seasonloc_core::cooc::keypoints::KeypointParams::default()
        },
        vocabulary_branching: 4,
        vocabulary_depth: 2,
        merge_adjacent_drives: true,
        ..seasonloc_core::cooc::CoocParams::default()
    }
}

fn golden() -> Vec<(Vec<u8>, Vec<u8>)> {
    let text = std::fs::read_to_string(golden_path()).unwrap();
    let unhex = |h: &str| -> Vec<u8> {
        (0..h.len())
            .step_by(2)
            .map(|k| u8::from_str_radix(&h[k..k + 2], 16).unwrap())
            .collect()
    };
    text.lines()
        .map(|l| {
            let (k, v) = l.split_once(' ').unwrap();
            (unhex(k), unhex(v))
        })
        .collect()
}

/// A sled store holding exactly the golden keys and values.
fn golden_store() -> (tempfile::TempDir, SledStore) {
    let dir = tempfile::tempdir().unwrap();
    {
        let db = ::sled::open(dir.path()).unwrap();
        for (k, v) in golden() {
            db.insert(k, v).unwrap();
        }
        db.flush().unwrap();
    }
    let store = SledStore::open(dir.path()).unwrap();
    (dir, store)
}

fn trip_params_custom() -> TripParams {
    TripParams {
        fan_out: 2,
        hidden_cost: Some(1.5),
        lag: 4,
        relocalization: None,
        normalize: false,
        ..TripParams::default()
    }
}

/// Every stored value decodes, and re-encoding it with today's code gives the same bytes.
#[test]
fn every_golden_record_is_rewritten_byte_for_byte() {
    let all = golden();
    let mut kinds = std::collections::BTreeMap::new();
    for (k, v) in &all {
        *kinds.entry(k[0]).or_insert(0) += 1;
        match k[0] {
            b'M' => assert_eq!(&codec::encode_map(&codec::decode_map(k, v).unwrap()), v),
            b'I' => {
                let mut d = Vec::new();
                let meta = codec::decode_image_into(k, v, &mut d).unwrap();
                assert_eq!(&codec::encode_image(&d, &meta), v);
            }
            b'L' => {
                let r = codec::decode_localization(k, v).unwrap();
                assert_eq!(&codec::encode_localization(&r).unwrap(), v);
            }
            b'T' => {
                let r = codec::decode_trip(k, v).unwrap();
                assert_eq!(&codec::encode_trip(&r).unwrap(), v);
            }
            // Layout 7 appended `p_correct` and a status to a frame's value: a layout-4 frame
            // reads as an estimate nothing calibrated, and its layout-7 encoding is the old
            // value with the two fields after it.
            b'F' => {
                let f = codec::decode_frame(k, v).unwrap();
                assert_eq!(f.p_correct, 0.0);
                assert_eq!(f.status, FrameStatus::before_calibration(f.reference));
                let now = codec::encode_frame(&f).unwrap();
                assert_eq!((&now[..v.len()], now.len()), (&v[..], v.len() + 9));
                assert_eq!(codec::decode_frame(k, &now).unwrap(), f);
            }
            // Format-1 trip states are read (layout 6 replaces them by parts at the trip's
            // next batch; `the_pre_refactor_store_reads_back_through_the_trait`).
            b'S' => assert!(Trip::from_legacy_bytes(v).is_ok()),
            b'C' => assert_eq!(
                &seasonloc_core::cooc::CoocMap::from_bytes(v)
                    .unwrap()
                    .to_bytes(),
                v
            ),
            b'l' | b't' => assert!(v.is_empty()),
            b'm' => assert_eq!(v, &4u32.to_be_bytes()),
            other => panic!("unexpected key prefix {other}"),
        }
    }
    let counts: Vec<(char, i32)> = kinds.into_iter().map(|(k, n)| (k as char, n)).collect();
    assert_eq!(
        counts,
        vec![
            ('C', 1),
            ('F', 7),
            ('I', 11),
            ('L', 2),
            ('M', 5),
            ('S', 2),
            ('T', 2),
            ('l', 2),
            ('m', 1),
            ('t', 2)
        ]
    );
}

/// Reading the golden store through the [`Store`] trait gives what the old code wrote, and
/// today's computations give the stored trip states and localization document exactly.
#[tokio::test]
async fn the_pre_refactor_store_reads_back_through_the_trait() {
    let (_dir, sled) = golden_store();
    let store: Arc<dyn Store> = Arc::new(sled);
    let maps = store.list_maps().await.unwrap();
    let names: Vec<&str> = maps.iter().map(|m| m.name.as_str()).collect();
    assert_eq!(names, ["route ✓", "own", "cnn", "cnn2", "cooc"]);
    let [hog, pre, cnn, cnn2, cooc] = [0, 1, 2, 3, 4].map(|k| maps[k].clone());
    assert_eq!(
        hog.descriptor,
        DescriptorSettings::Hog {
            cell_size: 8,
            resize: Some((64, 32))
        }
    );
    assert_eq!(pre.descriptor, DescriptorSettings::Precomputed { dim: 2 });
    assert_eq!(
        cnn.descriptor,
        DescriptorSettings::Cnn(Box::new(cnn_crop()))
    );
    assert_eq!(
        cnn2.descriptor,
        DescriptorSettings::Cnn(Box::new(cnn_stretch()))
    );
    assert_eq!(
        cooc.descriptor,
        DescriptorSettings::Cooc(Box::new(cooc_params()))
    );
    assert_eq!((hog.image_count, hog.dim), (3, Some(4)));
    assert_eq!(
        store.descriptors(hog.id, 0..3).await.unwrap(),
        rows(3, 4, 1)
    );
    assert_eq!(
        store.image_metadata(hog.id, 0..3).await.unwrap(),
        hog_metas()
    );
    let refs = store.descriptors(pre.id, 0..4).await.unwrap();
    let mut expected = rows(2, 2, 2).as_slice().to_vec();
    expected.extend_from_slice(rows(2, 2, 3).as_slice());
    assert_eq!(refs.as_slice(), &expected[..]);
    assert_eq!(
        store.descriptors(pre.id, 2..4).await.unwrap(),
        rows(2, 2, 3)
    );
    assert_eq!(cooc.image_count, 4);
    assert!(store.cooc_map(cooc.id).await.unwrap().is_some());

    // Localizations: the flow result recomputed today is the stored document, byte for byte.
    let page = PageRequest {
        before: None,
        limit: 10,
    };
    let locs = store.list_localizations(None, page).await.unwrap().items;
    assert_eq!(locs.len(), 2);
    let (seq, flow) = (&locs[0], &locs[1]);
    assert_eq!(seq.result.params.method, Some(CoocMethod::Sequence));
    assert_eq!(flow.result.params.method, None);
    // The stored result was computed when the box window was the default confidence (today
    // the discounted ratio); recomputed with the same confidence it is the same document.
    let options = LocalizeOptions {
        confidence: seasonloc_core::confidence::ConfidenceParams::window(),
        ..LocalizeOptions::default()
    };
    let result = localize(&rows(3, 2, 5), &refs, &options).unwrap();
    let today = LocalizationRecord {
        id: flow.id,
        map_id: pre.id,
        created_ms: flow.created_ms,
        result: LocalizationResult {
            query_count: 3,
            reference_count: 4,
            params: LocalizationParams::new(&options, result.solution.hidden_cost, None),
            total_cost: result.solution.total_cost(),
            hypotheses: result.solution.hypotheses.clone(),
            // Results stored before `p_correct` existed have none (today's carry it).
            predictions: result
                .predictions
                .iter()
                .map(|p| seasonloc_core::localize::Prediction {
                    p_correct: None,
                    ..*p
                })
                .collect(),
            timings: LocalizationTimings {
                load_references: 0.000125,
                features: 0.0,
                similarity: 1.0 / 3.0,
                solve: 0.02,
            },
            picture: None,
        },
    };
    let stored = golden()
        .into_iter()
        .find(|(k, _)| k == &codec::localization_key(flow.id))
        .unwrap()
        .1;
    let stored_doc = &stored[1 + 8 + 8 + 8 + 4..];
    assert_eq!(
        crate::document::localization_json(&today).unwrap(),
        stored_doc
    );

    // Trips: records, estimates, and the states today's trip code computes from the inputs.
    let trips = store.list_trips(hog.id, page).await.unwrap().items;
    assert_eq!(trips.len(), 2);
    let (closed, driven) = (&trips[0], &trips[1]);
    assert!(closed.closed_ms.is_some() && driven.closed_ms.is_none());
    assert_eq!((driven.frame_count, closed.frame_count), (7, 0));
    assert_eq!(closed.status, None);
    assert!(driven.status.is_some());
    assert_eq!(driven.params, TripParams::default());
    assert_eq!(closed.params, trip_params_custom());
    let estimates = store.trip_estimates(driven.id, 0).await.unwrap();
    assert_eq!(
        estimates.iter().map(|e| e.frame).collect::<Vec<_>>(),
        (0..7).collect::<Vec<_>>()
    );
    let prior = column_prior(&rows(3, 4, 1)).unwrap();
    let mut trip = Trip::new(prior.clone(), TripParams::default()).unwrap();
    let mut status = None;
    for (b, n) in [(0usize, 4usize), (4, 3)] {
        status = Some(trip.push_batch(&cos_batch(b, n, 3)).unwrap().status);
    }
    assert_eq!(driven.status, status);
    assert!(matches!(
        status,
        Some(TripStatus::Localized | TripStatus::Lost | TripStatus::Relocalized)
    ));
    // The stored format-1 state continues exactly as today's trip fed the same frames (both
    // windows still hold the whole trip, so the confidences agree too).
    let (_, state) = store.trip_state(driven.id).await.unwrap();
    let TripState::Legacy(blob) = state else {
        panic!("a layout-4 trip state read as parts")
    };
    let mut old = Trip::from_legacy_bytes(&blob).unwrap();
    assert_eq!(old.frames(), 7);
    let next = cos_batch(7, 5, 3);
    let want = trip.push_batch(&next).unwrap();
    assert_eq!(old.push_batch(&next).unwrap(), want);
    // Its next batch stores it in layout 6's parts (a base and a full snapshot, no log),
    // atomically with the record; read back, it is the same trip.
    let delta = old.take_delta();
    assert!(delta.base.is_some() && delta.snapshot.is_some() && delta.log.is_empty());
    store
        .put_trip_batch(
            driven.id,
            TripBatch {
                expected_frames: 7,
                frame_count: 12,
                status: want.status,
                state: TripStateWrite {
                    base: delta.base,
                    snapshot: delta.snapshot,
                    log: delta.log,
                    drop_log_before: delta.drop_log_before,
                },
                estimates: Vec::new(),
                idempotency: None,
            },
        )
        .await
        .unwrap();
    let (record, state) = store.trip_state(driven.id).await.unwrap();
    assert_eq!(record.frame_count, 12);
    let TripState::Parts {
        base,
        snapshot,
        log,
    } = state
    else {
        panic!("the blob was not replaced")
    };
    assert!(log.is_empty());
    let restored = Trip::restore(&base, &snapshot, &[], 12).unwrap();
    assert_eq!(restored.image_bytes(), old.image_bytes());
    // The closed trip never had a batch: its blob is a fresh trip with its parameters.
    let (_, state) = store.trip_state(closed.id).await.unwrap();
    let TripState::Legacy(blob) = state else {
        panic!("a layout-4 trip state read as parts")
    };
    let fresh = Trip::from_legacy_bytes(&blob).unwrap();
    let custom = trip_params_custom();
    assert_eq!((fresh.frames(), fresh.references()), (0, 3));
    assert_eq!(
        (
            fresh.params().lag,
            fresh.params().fan_out,
            fresh.hidden_cost()
        ),
        (custom.lag, custom.fan_out, custom.hidden_cost)
    );
    assert_eq!(fresh.params().discount(), custom.discount());
}
