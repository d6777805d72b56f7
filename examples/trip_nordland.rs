//! Streams the Nordland winter frames through a trip, in batches of 10, against the summer map
//! (HOG, 8 px cells), and prints the spec's metrics (`crate::eval`) of the per-frame online
//! estimates next to the offline result; then the derived jump route (see `docs/parameters.md`)
//! and how many frames each jump took to relocalize.
//!
//! Run: `cargo run --release --example trip_nordland [-- DATA/nordland_64x32]`.

use std::path::{Path, PathBuf};

use seasonloc_core::eval::{evaluate, Exclusions, GroundTruth, Metrics, Prediction};
use seasonloc_core::features::extract_files;
use seasonloc_core::features::hog::{HogOptions, HogSpec};
use seasonloc_core::localize::{localize, LocalizeOptions};
use seasonloc_core::similarity::{cosine_matrix, Normalization};
use seasonloc_core::trip::{Trip, TripParams};
use seasonloc_core::Matrix;

#[path = "../tests/trip_jump/route.rs"]
mod route;
#[path = "support/trip_stream.rs"]
mod trip_stream;
use route::{jump_route, relocalization_delays};
use trip_stream::{predictions, stream};

fn files(dir: &Path) -> Vec<PathBuf> {
    let mut f: Vec<PathBuf> = std::fs::read_dir(dir)
        .unwrap_or_else(|e| panic!("{}: {e}", dir.display()))
        .map(|e| e.expect("readable folder").path())
        .filter(|p| p.extension().is_some_and(|e| e == "png"))
        .collect();
    f.sort();
    f
}

fn row(name: &str, m: &Metrics) {
    println!(
        "| {name} | {:.3} | {:.3} | {:.3} | {:.3} | {:.3} |",
        m.ap, m.recall_at_100p, m.recall_at_99p, m.max_f1, m.precision_at_full
    );
}

fn main() {
    let dir = std::env::args()
        .nth(1)
        .map(PathBuf::from)
        .or_else(seasonloc_test_support::datasets::nordland)
        .expect("the Nordland dev folder (give it as the first argument)");
    let spec = HogSpec::new(HogOptions {
        cell_size: 8,
        resize: None,
    })
    .expect("valid HOG");
    let summer = extract_files(&spec, &files(&dir.join("summer")), &|| {}).expect("summer");
    let winter = extract_files(&spec, &files(&dir.join("winter")), &|| {}).expect("winter");
    let gt = GroundTruth::from_csv(&dir.join("ground_truth.csv")).expect("ground truth");
    let exclusions = Exclusions::parse("0-16").expect("range");
    let q = winter.rows();
    let score = |p: &[Prediction]| evaluate(p, &gt, q, 1, &exclusions).expect("scorable");

    println!("| method | AP | recall @ 100 % precision | recall @ 99 % precision | max F1 | precision at full recall |");
    println!("| --- | --- | --- | --- | --- | --- |");
    let offline = localize(&winter, &summer, &LocalizeOptions::default()).expect("offline");
    row(
        "offline flow, F = 1 (whole sequence known)",
        &score(&offline.predictions),
    );

    let c = cosine_matrix(&winter, &summer).expect("cosine");
    let prior = seasonloc_core::trip::column_prior(&summer).expect("prior");
    let defaults = TripParams::default();
    let (arrival, last) = stream(&c, &prior, defaults, 10);
    let mut probe = Trip::new(prior.clone(), defaults).expect("valid parameters");
    let (mut written, mut most, mut batches) = (0usize, 0usize, 0usize);
    for start in (0..q).step_by(10) {
        let rows: Vec<&[f32]> = (start..(start + 10).min(q)).map(|i| c.row(i)).collect();
        probe
            .push_batch(&Matrix::from_rows(&rows).expect("rows"))
            .expect("batch");
        let bytes = probe.take_delta().bytes();
        (written, most, batches) = (written + bytes, most.max(bytes), batches + 1);
    }
    let stored = probe.stored_state();
    let state = format!(
        "state after {q} frames on a {}-image map: a batch of 10 writes {} bytes on average \
         (at most {most}); stored form {} bytes (base {}, snapshot {}, {} log rows); {} bytes of heap",
        summer.rows(),
        written / batches,
        stored.base.len()
            + stored.snapshot.len()
            + stored.log.iter().map(|(_, r)| r.len()).sum::<usize>(),
        stored.base.len(),
        stored.snapshot.len(),
        stored.log.len(),
        probe.heap_bytes()
    );
    row(
        "trip, defaults (R = 1, lag 32): estimate at arrival",
        &score(&predictions(&arrival)),
    );
    row(
        "trip, defaults: estimate after the lag window",
        &score(&predictions(&last)),
    );
    let forward = TripParams {
        relocalization: None,
        ..defaults
    };
    let (arrival, last) = stream(&c, &prior, forward, 10);
    row(
        "trip, no relocalization: at arrival",
        &score(&predictions(&arrival)),
    );
    row(
        "trip, no relocalization: after the lag window",
        &score(&predictions(&last)),
    );
    // The cost of online Eq. 2 alone: the same online solver fed the offline-normalised rows.
    let chat = Normalization::default().apply(&c).expect("normalise");
    let offline_norm = TripParams {
        relocalization: None,
        normalize: false,
        ..defaults
    };
    let (arrival, last) = stream(&chat, &prior, offline_norm, 10);
    row(
        "online solver on offline-normalised rows (no relocalization): at arrival",
        &score(&predictions(&arrival)),
    );
    row(
        "online solver on offline-normalised rows: after the lag window",
        &score(&predictions(&last)),
    );

    println!();
    println!("{state}");
    let route = jump_route();
    let map_rows: Vec<&[f32]> = (0..route.map_len).map(|j| summer.row(j)).collect();
    let map = Matrix::from_rows(&map_rows).expect("map");
    let frames: Vec<&[f32]> = route.frames.iter().map(|&i| winter.row(i)).collect();
    let cq = cosine_matrix(&Matrix::from_rows(&frames).expect("frames"), &map).expect("cosine");
    let prior = seasonloc_core::trip::column_prior(&map).expect("prior");
    let (arrival, _) = stream(&cq, &prior, defaults, 10);
    println!("jump route (summer 0-{} as the map):", route.map_len - 1);
    for (seg, delay) in route
        .segments
        .iter()
        .zip(relocalization_delays(&route, &arrival))
    {
        println!(
            "  winter {}-{} (from trip frame {}): {}",
            seg.1,
            seg.2 - 1,
            seg.0,
            match delay {
                Some(d) => format!("found after {d} frames"),
                None => "not found".into(),
            }
        );
    }
}
