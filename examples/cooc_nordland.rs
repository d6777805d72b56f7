//! Measurements of the co-occurrence method on the real Nordland dev data, printed for
//! `docs/cooc.md`: keypoint repeatability across seasons at 1x/2x/4x upsampling, then the dev
//! evaluation of spec §4 (winter queries vs the summer map, tolerance 1, queries 0-16 excluded)
//! for single images, sequences and the flow graph on co-occurrence scores.
//!
//! A dataset harness, so it lives here rather than in the algorithm layer.
//! Run: `cargo run --release --example cooc_nordland [-- DATA/nordland_64x32]`.

use std::path::{Path, PathBuf};
use std::time::Instant;

use image::GrayImage;
use seasonloc_core::cooc::keypoints::{extract, KeypointParams};
use seasonloc_core::cooc::SequenceParams;
use seasonloc_core::cooc::{CoocMap, CoocMethod, CoocOptions, CoocParams, CoocQueries, Drive};
use seasonloc_core::eval::{evaluate, Exclusions, GroundTruth, Prediction};
use seasonloc_core::similarity::Normalization;

fn frame(dir: &Path, season: &str, i: usize) -> GrayImage {
    let path = dir
        .join(season)
        .join(format!("images-{:05}.png", (i + 1) * 10));
    image::open(&path)
        .unwrap_or_else(|e| panic!("{}: {e}", path.display()))
        .to_luma8()
}

/// Fraction of summer keypoints with a winter keypoint within 1 original pixel in the same
/// frame (frames 17, 27, ..., 2397), against chance (the winter frame 500 frames away).
fn repeatability(dir: &Path) {
    let near = |a: &seasonloc_core::cooc::keypoints::Keypoint,
                b: &seasonloc_core::cooc::keypoints::Keypoint| {
        ((a.x - b.x) * 64.0).abs() <= 1.0 && ((a.y - b.y) * 32.0).abs() <= 1.0
    };
    for upsample in [1u32, 2, 4] {
        let params = KeypointParams {
            upsample,
            nms_radius: upsample,
            ..KeypointParams::default()
        };
        let (mut hit, mut total, mut count) = (0usize, 0usize, 0usize);
        let frames: Vec<usize> = (17..2400).step_by(10).collect();
        for &i in &frames {
            let s = extract("summer", &frame(dir, "summer", i), &params).expect("valid frame");
            let w = extract("winter", &frame(dir, "winter", i), &params).expect("valid frame");
            count += s.keypoints.len() + w.keypoints.len();
            for a in &s.keypoints {
                total += 1;
                hit += usize::from(w.keypoints.iter().any(|b| near(a, b)));
            }
        }
        let (mut chance, mut chance_total) = (0usize, 0usize);
        for &i in frames.iter().take(60) {
            let s = extract("summer", &frame(dir, "summer", i), &params).expect("valid frame");
            let w = extract("winter", &frame(dir, "winter", (i + 500) % 2400), &params)
                .expect("valid frame");
            for a in &s.keypoints {
                chance_total += 1;
                chance += usize::from(w.keypoints.iter().any(|b| near(a, b)));
            }
        }
        println!(
            "upsample {upsample}: {:.1} keypoints/image, repeatability within 1 px {:.3} (chance {:.3})",
            count as f64 / (2 * frames.len()) as f64,
            hit as f64 / total.max(1) as f64,
            chance as f64 / chance_total.max(1) as f64
        );
    }
}

fn evaluation(dir: &Path) {
    let load =
        |season: &str| -> Vec<GrayImage> { (0..2400).map(|i| frame(dir, season, i)).collect() };
    let (summer, winter) = (load("summer"), load("winter"));
    let gt = GroundTruth::from_csv(&dir.join("ground_truth.csv")).expect("ground truth");
    let exclusions = Exclusions::parse("0-16").expect("valid range");
    let report = |name: &str, p: &[Prediction], seconds: f64| {
        let m = evaluate(p, &gt, winter.len(), 1, &exclusions).expect("valid predictions");
        println!(
            "| cooc {name} | {:.3} | {:.3} | {:.3} | {:.3} | {:.3} | {seconds:.2} s |",
            m.ap, m.recall_at_100p, m.recall_at_99p, m.max_f1, m.precision_at_full
        );
    };
    let t = Instant::now();
    let map = CoocMap::build(
        &CoocParams::default(),
        &[Drive::sequential(0.0, summer).expect("drive")],
    )
    .expect("map");
    println!(
        "map build (features, vocabulary, models): {:.1} s, {} bytes encoded",
        t.elapsed().as_secs_f64(),
        map.to_bytes().len()
    );
    let t = Instant::now();
    let queries = CoocQueries::new(&map, &winter).expect("queries");
    println!("query features: {:.1} s", t.elapsed().as_secs_f64());
    println!("| method | AP | R@100P | R@99P | max F1 | P@full | time |");
    println!("| --- | --- | --- | --- | --- | --- | --- |");
    let run = |method: CoocMethod, options: &CoocOptions| {
        let r = queries.localize(method, options).expect("localize");
        (r.predictions, r.timings.similarity + r.timings.solve)
    };
    let defaults = CoocOptions::default();
    let (p, s) = run(CoocMethod::Single, &defaults);
    report("single image (best-first)", &p, s);
    for length in [10, 20] {
        let options = CoocOptions {
            sequence: SequenceParams {
                length,
                ..SequenceParams::default()
            },
            ..CoocOptions::default()
        };
        let (p, s) = run(CoocMethod::Sequence, &options);
        report(&format!("sequences ds={length}"), &p, s);
    }
    println!("score matrix: {:.2} s", queries.score_seconds());
    let mut options = CoocOptions::default();
    options.flow.normalization = Normalization::Columns;
    let (p, s) = run(CoocMethod::Flow, &options);
    report("scores -> flow graph (F=1, Eq. 2)", &p, s);
}

fn main() {
    let dir = std::env::args()
        .nth(1)
        .map(PathBuf::from)
        .or_else(seasonloc_test_support::datasets::nordland)
        .unwrap_or_default();
    if !dir.join("summer").is_dir() {
        eprintln!("skipping: {} not found", dir.display());
        return;
    }
    repeatability(&dir);
    evaluation(&dir);
}
