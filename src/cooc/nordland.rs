//! Measurements on the real Nordland dev data (`../shared/data/nordland_64x32` beside the
//! crate), as `#[ignore]` tests that print numbers for `docs/cooc.md`; they skip with a message
//! when the data is absent. Run: `cargo test --release --lib cooc::nordland -- --ignored --nocapture`.

use std::path::PathBuf;

use image::GrayImage;

use super::keypoints::{extract, KeypointParams};

fn data_dir() -> Option<PathBuf> {
    // `../shared` beside the repository (CI); `../../shared` from a worktree under `wt/`.
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR"));
    let candidates =
        ["../shared", "../../shared"].map(|s| root.join(s).join("data/nordland_64x32"));
    let found = candidates
        .iter()
        .find(|d| d.join("summer").is_dir())
        .cloned();
    if found.is_none() {
        eprintln!("skipping: {} not found", candidates[0].display());
    }
    found
}

fn frame(dir: &std::path::Path, season: &str, i: usize) -> GrayImage {
    let path = dir
        .join(season)
        .join(format!("images-{:05}.png", (i + 1) * 10));
    image::open(&path)
        .unwrap_or_else(|e| panic!("{}: {e}", path.display()))
        .to_luma8()
}

/// Keypoint repeatability across seasons: the fraction of summer keypoints with a winter
/// keypoint within `radius` original pixels in the same frame, over frames 17, 27, ..., 2397.
#[test]
#[ignore = "reads the shared Nordland data; prints measurements"]
fn keypoint_repeatability_summer_vs_winter() {
    let Some(dir) = data_dir() else { return };
    for upsample in [1u32, 2, 4] {
        let params = KeypointParams {
            upsample,
            nms_radius: upsample,
            ..KeypointParams::default()
        };
        let (mut hit, mut total, mut count) = (0usize, 0usize, 0usize);
        let frames: Vec<usize> = (17..2400).step_by(10).collect();
        for &i in &frames {
            let s = extract("summer", &frame(&dir, "summer", i), &params).expect("valid frame");
            let w = extract("winter", &frame(&dir, "winter", i), &params).expect("valid frame");
            count += s.keypoints.len() + w.keypoints.len();
            for a in &s.keypoints {
                total += 1;
                let near = w.keypoints.iter().any(|b| {
                    ((a.x - b.x) * 64.0).abs() <= 1.0 && ((a.y - b.y) * 32.0).abs() <= 1.0
                });
                hit += usize::from(near);
            }
        }
        // Chance level: the same test against the winter keypoints of a frame 500 away.
        let mut chance = 0usize;
        let mut chance_total = 0usize;
        for &i in frames.iter().take(60) {
            let s = extract("summer", &frame(&dir, "summer", i), &params).expect("valid frame");
            let w = extract("winter", &frame(&dir, "winter", (i + 500) % 2400), &params)
                .expect("valid frame");
            for a in &s.keypoints {
                chance_total += 1;
                chance += usize::from(w.keypoints.iter().any(|b| {
                    ((a.x - b.x) * 64.0).abs() <= 1.0 && ((a.y - b.y) * 32.0).abs() <= 1.0
                }));
            }
        }
        println!(
            "upsample {upsample}: {:.1} keypoints/image, repeatability within 1 px {:.3} (chance {:.3})",
            count as f64 / (2 * frames.len()) as f64,
            hit as f64 / total.max(1) as f64,
            chance as f64 / chance_total.max(1) as f64
        );
        assert!(total > 0, "no keypoints at all");
    }
}

/// The Nordland dev evaluation of spec §4 (winter queries vs the summer map, tolerance 1,
/// queries 0-16 excluded) for single images, sequences and the flow graph on co-occurrence
/// scores.
#[test]
#[ignore = "reads the shared Nordland data (about a minute in release); prints metrics"]
fn nordland_dev_evaluation() {
    use std::time::Instant;

    use super::sequence::match_sequences;
    use super::{flow_similarity, CoocMap, CoocParams, Drive, Schedule, SequenceParams};
    use crate::eval::{evaluate, Exclusions, GroundTruth, Prediction};
    use crate::localize::{solve_with_confidence, LocalizeOptions};
    use crate::similarity::normalize_columns;

    let Some(dir) = data_dir() else { return };
    let load =
        |season: &str| -> Vec<GrayImage> { (0..2400).map(|i| frame(&dir, season, i)).collect() };
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
    let queries = map.quantize_all(&winter).expect("queries");
    println!("query features: {:.1} s", t.elapsed().as_secs_f64());
    println!("| method | AP | R@100P | R@99P | max F1 | P@full | time |");
    println!("| --- | --- | --- | --- | --- | --- | --- |");
    let t = Instant::now();
    let single: Vec<Prediction> = queries
        .iter()
        .enumerate()
        .filter_map(|(i, q)| {
            map.recognize_words(q, Schedule::BestFirst)
                .map(|r| Prediction {
                    query: i,
                    reference: r.location,
                    confidence: r.score as f64,
                })
        })
        .collect();
    report(
        "single image (best-first)",
        &single,
        t.elapsed().as_secs_f64(),
    );
    let t = Instant::now();
    let scores = map.score_matrix_words(&queries);
    let score_seconds = t.elapsed().as_secs_f64();
    println!("score matrix: {score_seconds:.2} s");
    for length in [10, 20] {
        let t = Instant::now();
        let params = SequenceParams {
            length,
            ..SequenceParams::default()
        };
        let p = match_sequences(&scores, &params).expect("sequences");
        report(
            &format!("sequences ds={length}"),
            &p,
            score_seconds + t.elapsed().as_secs_f64(),
        );
    }
    let t = Instant::now();
    let chat = normalize_columns(&flow_similarity(&scores)).expect("positive columns");
    let (_, p) = solve_with_confidence(&chat, &LocalizeOptions::default()).expect("flow");
    report(
        "scores -> flow graph (F=1)",
        &p,
        score_seconds + t.elapsed().as_secs_f64(),
    );
}
