//! Measurements of the co-occurrence method on Gardens Point dev (`../shared/data/gardenspoint_dev`,
//! three traversals of one route: day_left, day_right, night_right; image `k` of every traversal
//! is location `k`), printed for `docs/cooc.md`: extraction speed, single-drive maps and fused
//! maps for every query traversal, for `cooc`, `cooc-seq` and `cooc-flow`, scored as spec §4
//! with tolerance 2.
//!
//! Settings are given as `key=value` arguments (unset = the library default): `upsample`,
//! `max_width`, `kp` (max keypoints), `nms`, `cell`, `octaves`, `branching`, `depth`, `grid`
//! (`CxR`), `tol`, `merge` (0/1), `train` (max training descriptors), `seed`, and `maps`
//! (`pairs`: the single-drive and fused maps of the issue; `loo`: leave-one-out only).
//!
//! Several settings run one after the other (images loaded once, features re-extracted only
//! when the keypoint settings change) when separated by `/`.
//!
//! Run: `cargo run --release --example cooc_gardens -- [DATA_DIR] [key=value ...] [/ key=value ...]`.

use std::path::{Path, PathBuf};
use std::time::Instant;

use image::GrayImage;
use rayon::prelude::*;
use seasonloc::cooc::keypoints::{Features, KeypointParams};
use seasonloc::cooc::{
    extract_all, CoocMap, CoocMethod, CoocOptions, CoocParams, CoocQueries, DriveFeatures,
};
use seasonloc::eval::{evaluate, Exclusions, GroundTruth};
use seasonloc::features::{list_images, load_image_file};

const TRAVERSALS: [&str; 3] = ["day_left", "day_right", "night_right"];
/// Time of day of each traversal (only the order matters): both day walks, then night.
const TIMES: [f64; 3] = [12.0, 13.0, 22.0];

fn load(dir: &Path) -> Vec<GrayImage> {
    let files = list_images(dir).expect("image folder");
    files
        .par_iter()
        .map(|f| load_image_file(f).expect("readable image").to_luma8())
        .collect()
}

fn parse_params(args: &[String]) -> (CoocParams, String, bool) {
    let mut p = CoocParams::default();
    let mut maps = "pairs".to_string();
    let mut vocab_all = true;
    for a in args {
        let (k, v) = a
            .split_once('=')
            .unwrap_or_else(|| panic!("expected key=value: {a}"));
        let n = || {
            v.parse::<u64>()
                .unwrap_or_else(|_| panic!("{k}: not a number: {v}"))
        };
        match k {
            "upsample" => p.keypoints.upsample = n() as u32,
            "max_width" => p.keypoints.max_width = n() as u32,
            "kp" => p.keypoints.max_keypoints = n() as usize,
            "nms" => p.keypoints.nms_radius = n() as u32,
            "cell" => p.keypoints.cell_size = n() as u32,
            "octaves" => p.keypoints.octaves = n() as u32,
            "branching" => p.vocabulary_branching = n() as usize,
            "depth" => p.vocabulary_depth = n() as usize,
            "tol" => p.spatial_tolerance = n() as u16,
            "merge" => p.merge_adjacent_drives = n() != 0,
            "train" => p.max_training_descriptors = n() as usize,
            "seed" => p.seed = n(),
            "grid" => {
                let (c, r) = v.split_once('x').expect("grid=CxR");
                p.grid_cols = c.parse().expect("columns");
                p.grid_rows = r.parse().expect("rows");
            }
            "maps" => maps = v.to_string(),
            "vocab" => vocab_all = v == "all",
            other => panic!("unknown setting {other}"),
        }
    }
    p.validate().expect("valid settings");
    (p, maps, vocab_all)
}

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let (dir, rest) = match args.first() {
        Some(a) if !a.contains('=') => (PathBuf::from(a), &args[1..]),
        _ => (PathBuf::from("../shared/data/gardenspoint_dev"), &args[..]),
    };
    if !dir.join("day_right").is_dir() {
        eprintln!("skipping: {} not found", dir.display());
        return;
    }
    let images: Vec<Vec<GrayImage>> = TRAVERSALS.iter().map(|t| load(&dir.join(t))).collect();
    let mut cached: Option<(KeypointParams, Vec<Vec<Features>>)> = None;
    for config in rest.split(|a| a == "/") {
        let (params, maps, vocab_all) = parse_params(config);
        if cached.as_ref().is_none_or(|c| c.0 != params.keypoints) {
            cached = Some((params.keypoints.clone(), extract(&params, &images)));
        }
        let features = &cached.as_ref().expect("extracted above").1;
        run(&params, &maps, vocab_all, &images, features);
    }
}

fn extract(params: &CoocParams, images: &[Vec<GrayImage>]) -> Vec<Vec<Features>> {
    let mut features: Vec<Vec<Features>> = Vec::new();
    for (t, imgs) in TRAVERSALS.iter().zip(images) {
        let started = Instant::now();
        let f = extract_all(params, 0, imgs).expect("features");
        let ms = started.elapsed().as_secs_f64() * 1000.0 / imgs.len() as f64;
        let per: f64 = f.iter().map(|x| x.keypoints.len() as f64).sum::<f64>() / f.len() as f64;
        println!(
            "{t}: {}x{}, extraction {ms:.1} ms/image (wall, all cores), {per:.0} keypoints/image",
            imgs[0].width(),
            imgs[0].height()
        );
        features.push(f);
    }
    features
}

fn run(
    params: &CoocParams,
    maps: &str,
    vocab_all: bool,
    images: &[Vec<GrayImage>],
    features: &[Vec<Features>],
) {
    println!(
        "settings: {params:?}, vocabulary from {}",
        if vocab_all {
            "all drives"
        } else {
            "the first drive"
        }
    );
    let n = images[1].len();
    let gt = GroundTruth::from_pairs((0..n).map(|k| (k, k)));
    let drive = |t: usize| DriveFeatures {
        time: TIMES[t],
        features: features[t].clone(),
        locations: (0..features[t].len()).collect(),
    };
    let sets: Vec<(Vec<usize>, usize)> = match maps {
        "pairs" => vec![
            (vec![1], 0),
            (vec![1, 2], 0),
            (vec![0, 1], 2),
            (vec![1], 2),
            (vec![2], 0),
            (vec![0], 1),
            (vec![0, 2], 1),
            (vec![2], 1),
            (vec![0], 2),
        ],
        "loo" => vec![(vec![1, 2], 0), (vec![0, 2], 1), (vec![0, 1], 2)],
        "main" => vec![(vec![1], 0)],
        "day" => vec![(vec![1], 0), (vec![0], 1)],
        other => panic!("unknown maps={other}"),
    };
    println!(
        "| map | query | cooc AP | top-1 | cooc-seq AP | cooc-flow AP | size AP | margin AP | ratio AP | build s | score s |"
    );
    println!("| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |");
    for (map_drives, query) in sets {
        let started = Instant::now();
        let drives: Vec<DriveFeatures> = map_drives.iter().map(|&t| drive(t)).collect();
        let map = if vocab_all {
            CoocMap::from_features(params, &drives).expect("map")
        } else {
            let mut m = CoocMap::from_features(params, &drives[..1]).expect("map");
            for d in &drives[1..] {
                m.add_features(d).expect("drive");
            }
            m
        };
        let build = started.elapsed().as_secs_f64();
        let words = features[query]
            .par_iter()
            .map(|f| map.quantize_features(f))
            .collect();
        let queries = CoocQueries::from_words(&map, words);
        let options = CoocOptions::default();
        let mut row = Vec::new();
        for method in CoocMethod::ALL {
            let r = queries.localize(method, &options).expect("localize");
            let m = evaluate(&r.predictions, &gt, n, 2, &Exclusions::none()).expect("metrics");
            row.push(format!("{:.3}", m.ap));
            if method == CoocMethod::Single {
                row.push(format!("{:.2}", m.correct as f64 / n as f64));
            }
        }
        // Single image from the full scores with three confidences: the group size (the paper's),
        // and its margin over the best location more than 10 locations away (difference, ratio).
        for mode in [0, 1, 2] {
            let preds = margin_predictions(queries.scores(), 10, mode);
            let m = evaluate(&preds, &gt, n, 2, &Exclusions::none()).expect("metrics");
            row.push(format!("{:.3}", m.ap));
        }
        let name: Vec<&str> = map_drives.iter().map(|&t| TRAVERSALS[t]).collect();
        println!(
            "| {} | {} | {} | {build:.1} | {:.2} |",
            name.join("+"),
            TRAVERSALS[query],
            row.join(" | "),
            queries.score_seconds()
        );
    }
}

fn margin_predictions(
    scores: &seasonloc::Matrix,
    exclusion: usize,
    mode: u8,
) -> Vec<seasonloc::eval::Prediction> {
    (0..scores.rows())
        .filter_map(|q| {
            let row = scores.row(q);
            let (best, &s1) = row
                .iter()
                .enumerate()
                .max_by(|a, b| a.1.total_cmp(b.1).then(b.0.cmp(&a.0)))?;
            if s1 <= 0.0 {
                return None;
            }
            let s2 = row
                .iter()
                .enumerate()
                .filter(|(l, _)| l.abs_diff(best) > exclusion)
                .map(|(_, &s)| s)
                .fold(0.0f32, f32::max);
            let confidence = match mode {
                0 => f64::from(s1),
                1 => f64::from(s1 - s2),
                _ => f64::from(s1) / f64::from(s2.max(1.0)),
            };
            Some(seasonloc::eval::Prediction {
                query: q,
                reference: best,
                confidence,
            })
        })
        .collect()
}
