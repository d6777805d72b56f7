//! Measurements of the co-occurrence method on Gardens Point dev (`gardenspoint_dev`,
//! three traversals of one route: day_left, day_right, night_right; image `k` of every traversal
//! is location `k`), printed for `docs/cooc.md`: extraction speed, single-drive maps and fused
//! maps for every query traversal, for `cooc`, `cooc-seq` and `cooc-flow`, scored as spec §4
//! with tolerance 2; and a trip on each map fed the query drive's frames in batches of 10
//! (`CoocMap::trip_rows`, default trip parameters), scored at arrival and after the lag window.
//! Each fused map also prints the `pooled (...)` lines: the three methods with the sources pooled
//! by maximum-ratio combining (`support/pooled_fusion.rs`; `docs/cooc.md`, session 10), the
//! alternative measured against the shipped most-decisive-source rule and not adopted; and the
//! `decisiveness floor (...)` lines: the shipped rule with the decisiveness's spread floor of 1
//! (`None`, reproducing the table row), without a floor (`Some(0)`, a plain z-score) and with a
//! floor of one correspondence in normalised units (`Some(1)`), with the rows' off-peak spread
//! (`docs/cooc.md`, session 12).
//!
//! Settings are given as `key=value` arguments (unset = the library default): `upsample`,
//! `max_width`, `kp` (max keypoints), `nms`, `cell`, `octaves`, `branching`, `depth`, `grid`
//! (`CxR`), `tol`, `merge` (0/1), `train` (max training descriptors), `seed`, `seqnorm`
//! (`cooc-seq`'s score normalisation: `floored`, the default, `eq2` or `none`), `fusewin`
//! (`CoocOptions::fusion_window`: queries over which a fused map's source is chosen; 0, the
//! default, = the sequence length), `vocab` (`all`:
//! trained on every drive of the map, the default here; `first`: on the first drive, as `eval`
//! and the service; `sep`: on the traversal that is neither mapped nor queried, the paper's
//! separate training images), and `maps`
//! (`pairs`: the single-drive and fused maps of the issue; `loo`: leave-one-out only; `fusion`:
//! every single-drive map, then the same map, same vocabulary, plus the third walk; `fused`: the
//! fused maps of `fusion` only; `main`: day_right -> day_left; `day`: the two day pairs; `scale`:
//! recognition time per query on a map of 2,200 locations, see [`scale`]), and `gray` (`rgb`, the
//! default: Rec. 709 luma of the RGB decode; `y`: the JPEG's Y plane, as `seasonloc eval` and the
//! service decode; applies to every setting of the run).
//!
//! Several settings run one after the other (images loaded once, features re-extracted only
//! when the keypoint settings change) when separated by `/`.
//!
//! Run: `cargo run --release --example cooc_gardens -- [DATA_DIR] [key=value ...] [/ key=value ...]`.

use std::path::{Path, PathBuf};
use std::time::Instant;

use image::GrayImage;
use rayon::prelude::*;
use seasonloc_core::cooc::keypoints::{Features, KeypointParams};
use seasonloc_core::cooc::recognition::{self, Schedule};
use seasonloc_core::cooc::sequence::{match_sequences, SequenceParams};
use seasonloc_core::cooc::{
    extract_all, CoocMap, CoocMethod, CoocOptions, CoocParams, CoocQueries, DriveFeatures,
};
use seasonloc_core::eval::{evaluate, Exclusions, GroundTruth, Prediction};
use seasonloc_core::features::{list_images, load_image_file_as, Pixels};
use seasonloc_core::similarity::Normalization;
use seasonloc_core::trip::TripParams;

#[path = "support/pooled_fusion.rs"]
mod pooled_fusion;
#[path = "support/trip_stream.rs"]
mod trip_stream;
use pooled_fusion::{pooled_aps, PoolWeight};
use trip_stream::{predictions, stream};

const TRAVERSALS: [&str; 3] = ["day_left", "day_right", "night_right"];
/// Time of day of each traversal (only the order matters): both day walks, then night.
const TIMES: [f64; 3] = [12.0, 13.0, 22.0];

/// The gray images of one traversal: with `y_plane`, the JPEG's Y plane (BT.601 luma, what
/// `seasonloc eval` and the service decode); otherwise the Rec. 709 luma of the RGB decode (the
/// path before the Y-plane decode).
fn load(dir: &Path, y_plane: bool) -> Vec<GrayImage> {
    let files = list_images(dir).expect("image folder");
    let pixels = if y_plane {
        Pixels::Gray
    } else {
        Pixels::Colour
    };
    files
        .par_iter()
        .map(|f| {
            load_image_file_as(f, pixels)
                .expect("readable image")
                .to_luma8()
        })
        .collect()
}

fn parse_params(args: &[String]) -> (CoocParams, String, String, Normalization, usize) {
    let mut p = CoocParams::default();
    let mut seqnorm = SequenceParams::default().normalization;
    let mut maps = "pairs".to_string();
    let mut vocab = "all".to_string();
    let mut fusion_window = 0usize;
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
            "fusewin" => fusion_window = n() as usize,
            // Read by `main` before any setting (the images are loaded once).
            "gray" => assert!(v == "y" || v == "rgb", "gray: y or rgb, not {v}"),
            "vocab" => vocab = v.to_string(),
            "seqnorm" => {
                seqnorm = match v {
                    "none" => Normalization::None,
                    "eq2" => Normalization::Columns,
                    "floored" => Normalization::FlooredColumns,
                    other => panic!("seqnorm: none, eq2 or floored, not {other}"),
                }
            }
            other => panic!("unknown setting {other}"),
        }
    }
    p.validate().expect("valid settings");
    (p, maps, vocab, seqnorm, fusion_window)
}

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let (dir, rest) = match args.first() {
        Some(a) if !a.contains('=') => (PathBuf::from(a), &args[1..]),
        _ => (
            seasonloc_test_support::datasets::gardens_point().unwrap_or_default(),
            &args[..],
        ),
    };
    if !dir.join("day_right").is_dir() {
        eprintln!("skipping: {} not found", dir.display());
        return;
    }
    let y_plane = rest.iter().any(|a| a == "gray=y");
    println!(
        "gray images: {}",
        if y_plane {
            "the JPEG's Y plane (BT.601), as eval and the service"
        } else {
            "Rec. 709 luma of the RGB decode"
        }
    );
    let images: Vec<Vec<GrayImage>> = TRAVERSALS
        .iter()
        .map(|t| load(&dir.join(t), y_plane))
        .collect();
    let mut cached: Option<(KeypointParams, Vec<Vec<Features>>)> = None;
    for config in rest.split(|a| a == "/") {
        let (params, maps, vocab, seqnorm, fusion_window) = parse_params(config);
        if cached.as_ref().is_none_or(|c| c.0 != params.keypoints) {
            cached = Some((params.keypoints.clone(), extract(&params, &images)));
        }
        let features = &cached.as_ref().expect("extracted above").1;
        if maps == "scale" {
            scale(&params, &images, &features[0]);
        } else {
            run(
                &params,
                &maps,
                &vocab,
                (seqnorm, fusion_window),
                &images,
                features,
            );
        }
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
    vocab: &str,
    (seqnorm, fusion_window): (Normalization, usize),
    images: &[Vec<GrayImage>],
    features: &[Vec<Features>],
) {
    println!(
        "settings: {params:?}, vocabulary from {}",
        match vocab {
            "first" => "the first drive",
            "sep" => "the traversal neither mapped nor queried (all drives when none is left)",
            _ => "all drives",
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
        // Every single-drive map, then the same map (same vocabulary) plus the third drive.
        "fusion" => vec![
            (vec![1], 0),
            (vec![1, 2], 0),
            (vec![2], 0),
            (vec![2, 1], 0),
            (vec![0], 1),
            (vec![0, 2], 1),
            (vec![2], 1),
            (vec![2, 0], 1),
            (vec![0], 2),
            (vec![0, 1], 2),
            (vec![1], 2),
            (vec![1, 0], 2),
        ],
        "fused" => vec![
            (vec![1, 2], 0),
            (vec![2, 1], 0),
            (vec![0, 2], 1),
            (vec![2, 0], 1),
            (vec![0, 1], 2),
            (vec![1, 0], 2),
        ],
        "main" => vec![(vec![1], 0)],
        "day" => vec![(vec![1], 0), (vec![0], 1)],
        other => panic!("unknown maps={other}"),
    };
    println!(
        "| map | query | cooc AP | top-1 | cooc-seq AP | cooc-flow AP | seq contrast 10 AP | top/true/wrong | size AP | margin AP | ratio AP | trip AP arrival / lag | build s | score s |"
    );
    println!(
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"
    );
    for (map_drives, query) in sets {
        let started = Instant::now();
        let drives: Vec<DriveFeatures> = map_drives.iter().map(|&t| drive(t)).collect();
        let separate: Vec<&Features> = (0..TRAVERSALS.len())
            .filter(|t| !map_drives.contains(t) && *t != query)
            .flat_map(|t| &features[t])
            .collect();
        let map = match vocab {
            "first" => {
                let mut m = CoocMap::from_features(params, &drives[..1]).expect("map");
                for d in &drives[1..] {
                    m.add_features(d).expect("drive");
                }
                m
            }
            "sep" if !separate.is_empty() => {
                CoocMap::from_features_and_training(params, &separate, &drives).expect("map")
            }
            _ => CoocMap::from_features(params, &drives).expect("map"),
        };
        let build = started.elapsed().as_secs_f64();
        let words = features[query]
            .par_iter()
            .map(|f| map.quantize_features(f))
            .collect();
        let queries = CoocQueries::from_words(&map, words);
        let options = CoocOptions {
            sequence: SequenceParams {
                normalization: seqnorm,
                ..SequenceParams::default()
            },
            fusion_window,
            ..CoocOptions::default()
        };
        let mut row = Vec::new();
        for method in CoocMethod::ALL {
            let r = queries.localize(method, &options).expect("localize");
            let m = evaluate(&r.predictions, &gt, n, 2, &Exclusions::none()).expect("metrics");
            row.push(format!("{:.3}", m.ap));
            if method == CoocMethod::Single {
                row.push(format!("{:.2}", m.correct as f64 / n as f64));
            }
        }
        if map.locations().sources() > 1 {
            // Session 13: the window over which single-image `cooc` chooses its source (1:
            // the rule before; the whole batch: the shipped one, the table's `cooc` column).
            let single: Vec<String> = [1, 10, seasonloc_core::cooc::WHOLE_BATCH]
                .iter()
                .map(|&window| {
                    let excl = options.sequence.exclusion;
                    let scores = queries
                        .fused_scores(Normalization::default(), excl, window)
                        .expect("fused");
                    let preds = seasonloc_core::cooc::best_per_query(&scores);
                    let m = evaluate(&preds, &gt, n, 2, &Exclusions::none()).expect("metrics");
                    format!("{:.3}", m.ap)
                })
                .collect();
            println!(
                "  single-image source chosen per query / over 10 queries / over the batch (shipped): cooc AP {}",
                single.join(" / ")
            );
            // Session 10: the sources pooled by maximum-ratio combining instead of one source
            // per query window, for three signal-to-noise estimates.
            // Session 12: the decisiveness's spread floor in the units of the normalised rows.
            for floor in [None, Some(0), Some(1)] {
                let f = pooled_fusion::floored_aps(&map, &queries, &options, floor, &gt, n);
                println!(
                    "  decisiveness floor {floor:?}: cooc / cooc-seq / cooc-flow AP {:.3} / {:.3} / {:.3}, sources chosen {:?} (cooc) / {:?} (window); off-peak spread 5 % / median / 95 % / max {:.3} / {:.3} / {:.3} / {:.3}",
                    f.aps[0], f.aps[1], f.aps[2], f.chosen_single, f.chosen_window,
                    f.spread[0], f.spread[1], f.spread[2], f.spread[3]
                );
            }
            for weight in [
                PoolWeight::Margin,
                PoolWeight::Decisiveness,
                PoolWeight::ExcessMargin,
            ] {
                let aps = pooled_aps(&map, &queries, &options, weight, &gt, n);
                println!(
                    "  pooled ({weight:?}): cooc / cooc-seq / cooc-flow AP {:.3} / {:.3} / {:.3}",
                    aps[0], aps[1], aps[2]
                );
            }
        }
        // The sequence matching with SeqSLAM's local contrast enhancement (10 locations).
        let contrast = SequenceParams {
            contrast_window: 10,
            ..options.sequence
        };
        let p = match_sequences(queries.scores(), &contrast).expect("sequences");
        let m = evaluate(&p, &gt, n, 2, &Exclusions::none()).expect("metrics");
        row.push(format!("{:.3}", m.ap));
        // Diagnosis: how often the true place (within 2) has the top score, mean true score,
        // mean best wrong score.
        let s = queries.scores();
        let (mut top, mut tsum, mut wsum) = (0usize, 0f64, 0f64);
        for q in 0..s.rows() {
            let r = s.row(q);
            let t = (q.saturating_sub(2)..=(q + 2).min(r.len() - 1))
                .map(|l| r[l])
                .fold(0f32, f32::max);
            let w = r
                .iter()
                .enumerate()
                .filter(|(l, _)| l.abs_diff(q) > 2)
                .map(|(_, &v)| v)
                .fold(0f32, f32::max);
            top += usize::from(t > w);
            tsum += f64::from(t);
            wsum += f64::from(w);
        }
        let nq = s.rows() as f64;
        row.push(format!("{top} {:.1} {:.1}", tsum / nq, wsum / nq));
        // Single image from the full scores with three confidences: the group size (the paper's),
        // and its margin over the best location more than 10 locations away (difference, ratio).
        for mode in [0, 1, 2] {
            let preds = margin_predictions(queries.scores(), 10, mode);
            let m = evaluate(&preds, &gt, n, 2, &Exclusions::none()).expect("metrics");
            row.push(format!("{:.3}", m.ap));
        }
        // A trip on the map, frames in batches of 10, as the service runs it.
        let (arrival, last) = trip(&map, queries.words(), 10);
        let a = evaluate(&arrival, &gt, n, 2, &Exclusions::none()).expect("metrics");
        let b = evaluate(&last, &gt, n, 2, &Exclusions::none()).expect("metrics");
        row.push(format!("{:.3} / {:.3}", a.ap, b.ap));
        if map.locations().sources() > 1 {
            // The alternative measured against it (not used): each frame's row from its most
            // decisive source, `s + 1` over the row's mean on that source's locations.
            for window in [1, 10] {
                let (arrival, last) = trip_decisive(&map, queries.words(), 10, window);
                let a = evaluate(&arrival, &gt, n, 2, &Exclusions::none()).expect("metrics");
                let b = evaluate(&last, &gt, n, 2, &Exclusions::none()).expect("metrics");
                println!(
                    "  trip fed each frame's most decisive source (window {window}): AP {:.3} / {:.3}",
                    a.ap, b.ap
                );
            }
        }
        // Fused maps: how often each source is chosen (window = sequence length, on the
        // normalised rows) and how often each source's own row has its top at the place.
        if map.locations().sources() > 1 {
            let per_source = map.score_matrices_by_source(queries.words());
            let present = map.locations().source_present();
            let l = n;
            let norm: Vec<seasonloc_core::Matrix> = per_source
                .iter()
                .map(|m| {
                    seqnorm
                        .apply(&seasonloc_core::cooc::flow_similarity(m))
                        .expect("norm")
                })
                .collect();
            let len = if fusion_window == 0 {
                options.sequence.length
            } else {
                fusion_window
            };
            let order =
                seasonloc_core::cooc::source_order(&norm, &present, 10, len).expect("order");
            let top = |m: &seasonloc_core::Matrix, q: usize| {
                let r = m.row(q);
                let best = (0..l).fold(0, |b, j| if r[j] > r[b] { j } else { b });
                best.abs_diff(q) <= 2
            };
            let mut diag = Vec::new();
            for (d, nd) in norm.iter().enumerate() {
                let chosen = order.iter().filter(|o| o[0] == d).count();
                let right = (0..n).filter(|&q| top(nd, q)).count();
                let chosen_right = (0..n).filter(|&q| order[q][0] == d && top(nd, q)).count();
                diag.push(format!(
                    "source {d}: chosen {chosen}, top at place {right}, chosen+top {chosen_right}"
                ));
            }
            println!("  fused diagnosis: {}", diag.join("; "));
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

/// Streams the quantised frames through a trip on `map` (its prior from 256 of the map's own
/// images, as the service), `batch` at a time; the predictions at arrival and after the lag
/// window.
fn trip(
    map: &CoocMap,
    frames: &[Vec<seasonloc_core::cooc::Word>],
    batch: usize,
) -> (Vec<Prediction>, Vec<Prediction>) {
    let rows = map.trip_rows(frames);
    let prior = map.trip_prior(256).expect("trip prior");
    streamed(&rows, &prior, batch)
}

/// [`trip`] fed the alternative fusion of the per-source scores, for comparison: each frame's
/// row from the source with the best mean `decisiveness` over `window` frames centred on it
/// (window 1: causal, what a trip could run), as `flow_similarity` divided by its mean over that
/// source's locations (one scale for all sources); its prior the same rows of 256 of the map's
/// own images.
fn trip_decisive(
    map: &CoocMap,
    frames: &[Vec<seasonloc_core::cooc::Word>],
    batch: usize,
    window: usize,
) -> (Vec<Prediction>, Vec<Prediction>) {
    let rows_of = |words: &[Vec<seasonloc_core::cooc::Word>], window: usize| {
        let per_source = map.score_matrices_by_source(words);
        let present = map.locations().source_present();
        let l = map.location_count();
        let order =
            seasonloc_core::cooc::source_order(&per_source, &present, 10, window).expect("order");
        let mut out = seasonloc_core::Matrix::zeros(words.len(), l);
        for (i, o) in order.iter().enumerate() {
            let scaled: Vec<Vec<f32>> = per_source
                .iter()
                .enumerate()
                .map(|(s, m)| {
                    let has = &present[s * l..(s + 1) * l];
                    let row: Vec<f32> = m.row(i).iter().map(|v| v + 1.0).collect();
                    let (sum, k) = row
                        .iter()
                        .zip(has)
                        .filter(|(_, &p)| p)
                        .fold((0f64, 0usize), |(a, k), (&v, _)| (a + f64::from(v), k + 1));
                    let mean = if k == 0 { 1.0 } else { (sum / k as f64) as f32 };
                    row.iter().map(|v| v / mean).collect()
                })
                .collect();
            for (j, v) in out.row_mut(i).iter_mut().enumerate() {
                let s = o.iter().copied().find(|&s| present[s * l + j]).unwrap_or(0);
                *v = scaled[s][j];
            }
        }
        out
    };
    let rows = rows_of(frames, window);
    let r = rows_of(&map.trip_prior_images(256).expect("map images"), 1);
    let prior: Vec<f32> = (0..r.cols())
        .map(|j| (0..r.rows()).map(|i| f64::from(r.get(i, j))).sum::<f64>() / r.rows() as f64)
        .map(|v| v as f32)
        .collect();
    streamed(&rows, &prior, batch)
}

/// [`stream`] with the default trip parameters, as predictions.
fn streamed(
    rows: &seasonloc_core::Matrix,
    prior: &[f32],
    batch: usize,
) -> (Vec<Prediction>, Vec<Prediction>) {
    let (arrival, last) = stream(rows, prior, TripParams::default(), batch);
    (predictions(&arrival), predictions(&last))
}

fn margin_predictions(
    scores: &seasonloc_core::Matrix,
    exclusion: usize,
    mode: u8,
) -> Vec<seasonloc_core::eval::Prediction> {
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
            Some(seasonloc_core::eval::Prediction {
                query: q,
                reference: best,
                confidence,
                p_correct: None,
            })
        })
        .collect()
}

/// Variants of one frame that make distinct map locations: 85 % crops at 9 positions (3 x 3)
/// and the whole frame and its centre crop mirrored left-right.
const VARIANTS: usize = 11;

fn variant(img: &GrayImage, v: usize) -> GrayImage {
    let (w, h) = img.dimensions();
    let (cw, ch) = (w * 85 / 100, h * 85 / 100);
    match v {
        0..=8 => {
            let (x, y) = ((v % 3) as u32 * (w - cw) / 2, (v / 3) as u32 * (h - ch) / 2);
            image::imageops::crop_imm(img, x, y, cw, ch).to_image()
        }
        9 => image::imageops::flip_horizontal(img),
        _ => {
            let c = image::imageops::crop_imm(img, (w - cw) / 2, (h - ch) / 2, cw, ch).to_image();
            image::imageops::flip_horizontal(&c)
        }
    }
}

/// Recognition time per query on a map of 2,200 locations (the size of the paper's tours),
/// built from the real Gardens Point images: the 200 frames of day_right and night_right, each
/// in [`VARIANTS`] versions (crops at 9 positions, mirrored whole and centre crop), one drive of
/// 2,200 locations ordered variant, traversal, frame (so the route runs 22 times along the
/// map). Queries: 20 consecutive day_left frames (40..60). Prints extraction and map build time, then per query
/// (one thread, mean over the queries): best-first single-image recognition (the bound of
/// II-D), exhaustive recognition (every candidate location's `J`), a full score row (what the
/// sequence matching and the flow graph need) and the sequence matching (II-F) over the
/// 100 x 2,200 score matrix; and how often the answer shows the query's place (any variant of
/// frames k-2..=k+2 of either traversal).
fn scale(params: &CoocParams, images: &[Vec<GrayImage>], queries: &[Features]) {
    let frames = images[1].len();
    let sources: Vec<GrayImage> = (0..VARIANTS)
        .flat_map(|v| {
            [1usize, 2]
                .into_iter()
                .flat_map(move |t| (0..frames).map(move |k| (v, t, k)))
        })
        .collect::<Vec<_>>()
        .par_iter()
        .map(|&(v, t, k)| variant(&images[t][k], v))
        .collect();
    let n = sources.len();
    let frame_of = |l: usize| l % frames;
    let started = Instant::now();
    let features = extract_all(params, 0, &sources).expect("features");
    let extract_s = started.elapsed().as_secs_f64();
    let started = Instant::now();
    let drive = DriveFeatures {
        time: 0.0,
        features,
        locations: (0..n).collect(),
    };
    let map = CoocMap::from_features(params, &[drive]).expect("map");
    let build_s = started.elapsed().as_secs_f64();
    println!(
        "scale map: {n} locations from {} real frames x {VARIANTS} variants; extraction {:.1} ms/image \
         (wall, all cores), vocabulary + models {build_s:.1} s, {} words",
        2 * frames,
        extract_s * 1000.0 / n as f64,
        map.vocabulary().len()
    );
    // 20 consecutive day_left frames (40..60) keep the run within a CPU-queue hold and the
    // sequence matching meaningful.
    const FIRST: usize = 40;
    let words: Vec<Vec<_>> = queries[FIRST..FIRST + 20]
        .iter()
        .map(|f| map.quantize_features(f))
        .collect();
    let near = |q: usize, l: usize| frame_of(l).abs_diff(q + FIRST) <= 2;
    let time_per_query = |f: &dyn Fn(usize) -> Option<usize>| -> (f64, usize) {
        let started = Instant::now();
        let ok = (0..words.len())
            .filter(|&q| f(q).is_some_and(|l| near(q, l)))
            .count();
        (
            started.elapsed().as_secs_f64() * 1000.0 / words.len() as f64,
            ok,
        )
    };
    let mut evaluated = 0usize;
    let (best_first_ms, best_first_ok) = time_per_query(&|q| {
        map.recognize_words(&words[q], Schedule::BestFirst)
            .map(|r| r.location)
    });
    for w in &words {
        evaluated += map
            .recognize_words(w, Schedule::BestFirst)
            .map_or(0, |r| r.evaluated);
    }
    println!(
        "best-first: {best_first_ms:.1} ms/query, {:.0} J built per query, top-1 at the place {best_first_ok}/{}",
        evaluated as f64 / words.len() as f64,
        words.len()
    );
    let (exhaustive_ms, exhaustive_ok) = time_per_query(&|q| {
        map.recognize_words(&words[q], Schedule::Exhaustive)
            .map(|r| r.location)
    });
    println!("exhaustive: {exhaustive_ms:.1} ms/query, top-1 at the place {exhaustive_ok}");
    let started = Instant::now();
    let rows: Vec<Vec<u32>> = words
        .iter()
        .map(|w| recognition::scores(map.locations(), w))
        .collect();
    let row_ms = started.elapsed().as_secs_f64() * 1000.0 / words.len() as f64;
    let mut scores = seasonloc_core::Matrix::zeros(words.len(), n);
    for (i, r) in rows.iter().enumerate() {
        for (o, &v) in scores.row_mut(i).iter_mut().zip(r) {
            *o = v as f32;
        }
    }
    let started = Instant::now();
    let seq = match_sequences(&scores, &SequenceParams::default()).expect("sequences");
    let seq_ms = started.elapsed().as_secs_f64() * 1000.0 / words.len() as f64;
    let seq_ok = seq.iter().filter(|p| near(p.query, p.reference)).count();
    let candidates: f64 = (0..words.len())
        .map(|q| scores.row(q).iter().filter(|&&s| s > 0.0).count() as f64)
        .sum::<f64>()
        / words.len() as f64;
    println!(
        "per query (one thread, {} queries): best-first {best_first_ms:.1} ms ({:.0} of {candidates:.0} \
         scored locations' J built; top-1 at the place {best_first_ok}), exhaustive \
         {exhaustive_ms:.1} ms (top-1 at the place {exhaustive_ok}), full score row {row_ms:.1} ms, \
         sequence matching {seq_ms:.2} ms (sequence answer at the place {seq_ok}); \
         score row + sequences = {:.1} ms",
        words.len(),
        evaluated as f64 / words.len() as f64,
        row_ms + seq_ms
    );
}
