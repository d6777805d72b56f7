//! Golden store dump: every record kind of layout 4, written by the code *before* the
//! architecture refactor (issue 10), so later code can prove it reads and writes the same bytes.
//!
//! `write_layout4_golden` (ignored) ran once on the pre-refactor commit and wrote
//! `tests/data/store-layout4.golden`: one line per sled key, `hex(key) hex(value)`.

use std::fmt::Write as _;

use super::*;
use crate::api::dto::{
    format_id, HypothesisDto, LocalizationResponse, ParamsUsed, PredictionDto, TimingsDto,
};
use crate::api::trips::{TripParamsDto, TripParamsUsed};
use crate::features::cnn::{CnnOptions, CnnResize, ModelIdentity};
use crate::localize::{localize, LocalizeOptions};
use crate::trip::{column_prior, Trip};

/// Path of the golden dump.
pub(crate) fn golden_path() -> std::path::PathBuf {
    std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/store-layout4.golden")
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

/// A synthetic scene for the co-occurrence map: bright squares on a dark background.
pub(crate) fn scene(seed: u32) -> image::GrayImage {
    let mut img = image::GrayImage::from_pixel(64, 32, image::Luma([20]));
    for k in 0..6u32 {
        let x = (seed * 17 + k * 23) % 50;
        let y = (seed * 5 + k * 11) % 20;
        for yy in y..y + 8 {
            for xx in x..x + 8 {
                img.put_pixel(xx, yy, image::Luma([200 - (k * 20) as u8]));
            }
        }
    }
    img
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

pub(crate) fn cooc_params() -> crate::cooc::CoocParams {
    crate::cooc::CoocParams {
        vocabulary_branching: 4,
        vocabulary_depth: 2,
        ..crate::cooc::CoocParams::default()
    }
}

#[test]
#[ignore = "writes tests/data/store-layout4.golden; ran once on the pre-refactor code"]
fn write_layout4_golden() {
    let dir = tempfile::tempdir().unwrap();
    let store = Store::open(dir.path()).unwrap();
    let new = |name: &str, descriptor| NewMap {
        name: name.into(),
        descriptor,
    };
    // Maps of every kind.
    let hog = store
        .create_map(new(
            "route ✓",
            DescriptorSettings::Hog {
                cell_size: 8,
                resize: Some((64, 32)),
            },
        ))
        .unwrap();
    store
        .append_images(hog.id, &rows(3, 4, 1), &hog_metas())
        .unwrap();
    let pre = store
        .create_map(new("own", DescriptorSettings::Precomputed { dim: 2 }))
        .unwrap();
    store
        .append_images(pre.id, &rows(2, 2, 2), &vec![ImageMeta::default(); 2])
        .unwrap();
    store
        .append_images(pre.id, &rows(2, 2, 3), &vec![ImageMeta::default(); 2])
        .unwrap();
    store
        .create_map(new("cnn", DescriptorSettings::Cnn(Box::new(cnn_crop()))))
        .unwrap();
    store
        .create_map(new(
            "cnn2",
            DescriptorSettings::Cnn(Box::new(cnn_stretch())),
        ))
        .unwrap();
    let cooc = store
        .create_map(new(
            "cooc",
            DescriptorSettings::Cooc(Box::new(cooc_params())),
        ))
        .unwrap();
    let images: Vec<_> = (0..4).map(scene).collect();
    let built = crate::cooc::CoocMap::build(
        &cooc_params(),
        &[crate::cooc::Drive::sequential(0.0, images).unwrap()],
    )
    .unwrap();
    store
        .put_cooc_map(cooc.id, None, &built.to_bytes(), &vec![ImageMeta::default(); 4])
        .unwrap();

    // A flow localization, stored exactly as `api::localize::run` does.
    let (_, refs) = store.references(pre.id).unwrap();
    let options = LocalizeOptions::default();
    let result = localize(&rows(3, 2, 5), &refs, &options).unwrap();
    let id = store.new_localization_id().unwrap();
    let doc = LocalizationResponse {
        id: format_id(id),
        map_id: format_id(pre.id),
        created_at_ms: now_ms(),
        query_count: 3,
        reference_count: 4,
        params: ParamsUsed::new(&options, result.solution.hidden_cost),
        total_cost: result.solution.total_cost(),
        hypotheses: result
            .solution
            .hypotheses
            .iter()
            .map(HypothesisDto::from)
            .collect(),
        predictions: result.predictions.iter().map(PredictionDto::from).collect(),
        timings: TimingsDto {
            load_references: 0.000125,
            features: 0.0,
            similarity: 1.0 / 3.0,
            solve: 0.02,
        },
    };
    store
        .put_localization(id, pre.id, serde_json::to_vec(&doc).unwrap())
        .unwrap();
    // A co-occurrence localization (method set, no hypotheses).
    let id = store.new_localization_id().unwrap();
    let doc = LocalizationResponse {
        id: format_id(id),
        map_id: format_id(cooc.id),
        created_at_ms: now_ms(),
        query_count: 2,
        reference_count: 4,
        params: ParamsUsed {
            method: crate::api::dto::LocalizeParams::from_json(br#"{"method": "cooc-seq"}"#)
                .unwrap()
                .method,
            ..ParamsUsed::new(&options, 0.0)
        },
        total_cost: 0.0,
        hypotheses: Vec::new(),
        predictions: vec![PredictionDto {
            query: 1,
            reference: 3,
            confidence: 7.0,
        }],
        timings: TimingsDto::default(),
    };
    store
        .put_localization(id, cooc.id, serde_json::to_vec(&doc).unwrap())
        .unwrap();

    // Trips, stored exactly as `api::trips` does.
    let (_, hog_refs) = store.references(hog.id).unwrap();
    let prior = column_prior(&hog_refs).unwrap();
    let open = |dto: TripParamsDto| {
        let params = dto.into_params().unwrap();
        let trip = Trip::new(prior.clone(), params).unwrap();
        let doc = serde_json::to_vec(&TripParamsUsed::from(&params)).unwrap();
        let record = store.create_trip(hog.id, 3, doc, trip.to_bytes()).unwrap();
        (record, trip)
    };
    let (t1, mut trip) = open(TripParamsDto::default());
    let mut frames = 0u64;
    for (b, n) in [(0usize, 4usize), (4, 3)] {
        let update = trip.push_batch(&cos_batch(b, n, 3)).unwrap();
        let estimates = update
            .window
            .iter()
            .chain(&update.estimates)
            .map(|e| FrameRecord {
                frame: e.frame as u32,
                reference: e.reference.map(|j| j as u32),
                confidence: e.confidence,
            })
            .collect();
        let status = match update.status {
            crate::trip::TripStatus::Localized => 1,
            crate::trip::TripStatus::Lost => 2,
            crate::trip::TripStatus::Relocalized => 3,
        };
        store
            .put_trip_batch(
                t1.id,
                BatchWrite {
                    expected_frames: frames,
                    frame_count: frames + n as u64,
                    status,
                    state: trip.to_bytes(),
                    estimates,
                },
            )
            .unwrap();
        frames += n as u64;
    }
    let custom: TripParamsDto = serde_json::from_str(
        r#"{"fan_out": 2, "hidden_cost": 1.5, "lag": 4, "relocalization": false, "normalize": false}"#,
    )
    .unwrap();
    let (t2, _) = open(custom);
    store.close_trip(t2.id).unwrap();
    drop(trip);

    let mut out = String::new();
    for kv in store.db.iter() {
        let (k, v) = kv.unwrap();
        let hex = |b: &[u8]| b.iter().map(|x| format!("{x:02x}")).collect::<String>();
        writeln!(out, "{} {}", hex(&k), hex(&v)).unwrap();
    }
    let path = golden_path();
    std::fs::create_dir_all(path.parent().unwrap()).unwrap();
    std::fs::write(&path, out).unwrap();
}
