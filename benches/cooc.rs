//! Co-occurrence map benches: simultaneous matching with the maximum-potential-score bound
//! (lockstep as in the paper, and best-first) against matching every location separately, on a
//! generated map of 2,400 locations, the real Nordland map (2,400 frames) and a map of 2,200
//! camera locations from real Gardens Point frames ([`bench_recognition_gardens`]); keypoint
//! extraction on a 64x32 and a 960x540 frame; vocabulary training.
//!
//! Run: `cargo bench --bench cooc -- --warm-up-time 1 --measurement-time 3`.

mod fixture;

use criterion::measurement::WallTime;
use criterion::{criterion_group, criterion_main, BenchmarkGroup, BenchmarkId, Criterion};
use image::{GrayImage, Luma};
use seasonloc_core::cooc::keypoints::{extract, KeypointParams, DESCRIPTOR_DIM};
use seasonloc_core::cooc::model::{DriveRecord, LocationMap, Word};
use seasonloc_core::cooc::recognition::{recognize_query, Schedule};
use seasonloc_core::cooc::spatial::SpatialGrid;
use seasonloc_core::cooc::vocabulary::{TreeSpec, Vocabulary};
use seasonloc_core::cooc::{CoocMap, CoocParams, Drive};

/// SplitMix64, so the fixture is identical on every run.
struct Rng(u64);
impl Rng {
    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }
    fn below(&mut self, n: u64) -> u64 {
        self.next() % n
    }
    fn unit(&mut self) -> f32 {
        (self.next() >> 40) as f32 / (1u64 << 24) as f32
    }
}

const LOCATIONS: usize = 2400;
const FEATURES: usize = 60;
const VOCABULARY: u64 = 1000;

/// A map of random scenes, and queries that keep 2/3 of a scene's features plus 1/2 clutter.
fn fixture() -> (LocationMap, Vec<(usize, Vec<Word>)>) {
    let mut rng = Rng(42);
    let mut scenes = Vec::new();
    for _ in 0..LOCATIONS {
        let s: Vec<Word> = (0..FEATURES)
            .map(|_| Word::new(rng.below(VOCABULARY) as u32, rng.unit(), rng.unit()))
            .collect();
        scenes.push(s);
    }
    let mut map = LocationMap::new(SpatialGrid::new(12, 8).expect("valid grid"), 0, true);
    let images = scenes
        .iter()
        .enumerate()
        .map(|(l, s)| (l as u32, s.clone()))
        .collect();
    map.add_drive(DriveRecord { time: 0.0, images })
        .expect("valid drive");
    let queries = (0..20)
        .map(|k| {
            let loc = (k * 113) % LOCATIONS;
            let mut q: Vec<Word> = scenes[loc]
                .iter()
                .filter(|_| rng.below(3) > 0)
                .copied()
                .collect();
            for _ in 0..FEATURES / 2 {
                q.push(Word::new(
                    rng.below(VOCABULARY) as u32,
                    rng.unit(),
                    rng.unit(),
                ));
            }
            (loc, q)
        })
        .collect();
    (map, queries)
}

/// The Nordland folder where the tests find it ([`fixture::data_dir`]).
fn nordland_dir() -> Option<std::path::PathBuf> {
    Some(fixture::data_dir("nordland_64x32")).filter(|d| d.join("summer").is_dir())
}

fn bench_recognition(c: &mut Criterion) {
    let (map, queries) = fixture();
    // Sanity and work counts, printed once so BENCHMARKS-cooc.md can quote them.
    for schedule in [
        Schedule::Exhaustive,
        Schedule::Lockstep,
        Schedule::BestFirst,
    ] {
        let mut evaluated = 0;
        for (loc, q) in &queries {
            let r = recognize_query(&map, q, schedule).expect("queries share words with the map");
            assert_eq!(r.location, *loc, "{schedule:?} found the wrong location");
            evaluated += r.evaluated;
        }
        eprintln!(
            "{schedule:?}: consistency matrices built per query = {:.1}",
            evaluated as f64 / queries.len() as f64
        );
    }
    let mut group = c.benchmark_group("cooc_recognize_2400_locations");
    group.sample_size(10);
    for schedule in [
        Schedule::Exhaustive,
        Schedule::Lockstep,
        Schedule::BestFirst,
    ] {
        group.bench_with_input(
            BenchmarkId::from_parameter(format!("{schedule:?}")),
            &schedule,
            |b, &s| {
                b.iter(|| {
                    for (_, q) in &queries {
                        std::hint::black_box(recognize_query(&map, q, s));
                    }
                })
            },
        );
    }
    group.finish();
}

/// The same comparison on the real Nordland map (2,400 summer frames, default parameters) with
/// 21 winter queries; skipped when the shared data is absent. Building the map takes ~45 s.
fn bench_recognition_nordland(c: &mut Criterion) {
    let Some(dir) = nordland_dir() else {
        eprintln!("nordland_64x32 not found: skipping the Nordland bench");
        return;
    };
    let load = |season: &str, i: usize| -> GrayImage {
        let path = dir
            .join(season)
            .join(format!("images-{:05}.png", (i + 1) * 10));
        image::open(&path)
            .expect("readable Nordland frame")
            .to_luma8()
    };
    let summer: Vec<GrayImage> = (0..2400).map(|i| load("summer", i)).collect();
    let params = CoocParams::default();
    let map = CoocMap::build(
        &params,
        &[Drive::sequential(0.0, summer).expect("valid drive")],
    )
    .expect("map builds");
    let queries: Vec<Vec<Word>> = (17..2400)
        .step_by(119)
        .map(|i| {
            map.quantize("winter", &load("winter", i))
                .expect("valid frame")
        })
        .collect();
    for schedule in [
        Schedule::Exhaustive,
        Schedule::Lockstep,
        Schedule::BestFirst,
    ] {
        let built: usize = queries
            .iter()
            .filter_map(|q| map.recognize_words(q, schedule))
            .map(|r| r.evaluated)
            .sum();
        eprintln!(
            "Nordland {schedule:?}: consistency matrices built per query = {:.1}",
            built as f64 / queries.len() as f64
        );
    }
    let mut group = c.benchmark_group("cooc_recognize_nordland_2400");
    group.sample_size(10);
    let words: Vec<&[Word]> = queries.iter().map(Vec::as_slice).collect();
    bench_schedules(
        &mut group,
        &map,
        &words,
        &[
            Schedule::Exhaustive,
            Schedule::Lockstep,
            Schedule::BestFirst,
        ],
    );
    group.finish();
}

/// One bench per schedule in `group`: recognising every query of `queries` on `map`.
fn bench_schedules(
    group: &mut BenchmarkGroup<'_, WallTime>,
    map: &CoocMap,
    queries: &[&[Word]],
    schedules: &[Schedule],
) {
    for &schedule in schedules {
        group.bench_with_input(
            BenchmarkId::from_parameter(format!("{schedule:?}")),
            &schedule,
            |b, &s| {
                b.iter(|| {
                    for q in queries {
                        std::hint::black_box(map.recognize_words(q, s));
                    }
                })
            },
        );
    }
}

fn bench_keypoints(c: &mut Criterion) {
    let path = nordland_dir().map(|d| d.join("winter/images-05000.png"));
    let image: GrayImage = match path.as_ref().map(image::open) {
        Some(Ok(img)) => img.to_luma8(),
        _ => {
            eprintln!("Nordland frame not found: using a generated 64x32 frame");
            let mut rng = Rng(7);
            GrayImage::from_fn(64, 32, |x, y| {
                Luma([((x * 7 + y * 13) as u64 % 200 + rng.below(40)) as u8])
            })
        }
    };
    let params = KeypointParams::default();
    c.bench_function("cooc_keypoints_64x32_default", |b| {
        b.iter(|| extract("bench", std::hint::black_box(&image), &params).expect("valid image"))
    });
}

/// Extraction on a 960x540 camera frame (Gardens Point `day_right/Image000.jpg`, or a
/// generated frame of that size when the shared data is absent), default settings: the frame
/// is reduced to the 640 px working width first.
fn bench_keypoints_960x540(c: &mut Criterion) {
    let path = Some(fixture::data_dir("gardenspoint_dev").join("day_right/Image000.jpg"))
        .filter(|p| p.is_file());
    let image: GrayImage = match path.as_ref().map(image::open) {
        Some(Ok(img)) => img.to_luma8(),
        _ => {
            eprintln!("Gardens Point frame not found: using a generated 960x540 frame");
            let mut rng = Rng(9);
            GrayImage::from_fn(960, 540, |x, y| {
                Luma([((x / 9 * 7 + y / 7 * 13) as u64 % 200 + rng.below(40)) as u8])
            })
        }
    };
    let params = KeypointParams::default();
    c.bench_function("cooc_keypoints_960x540_default", |b| {
        b.iter(|| extract("bench", std::hint::black_box(&image), &params).expect("valid image"))
    });
}

/// The Gardens Point dev folder where the tests find it ([`fixture::data_dir`]).
fn gardens_dir() -> Option<std::path::PathBuf> {
    Some(fixture::data_dir("gardenspoint_dev")).filter(|d| d.join("day_right").is_dir())
}

/// The 3 x 3 non-overlapping tiles of a frame, row by row: nine images that share no pixel.
fn tiles(img: &GrayImage) -> Vec<GrayImage> {
    let (w, h) = (img.width() / 3, img.height() / 3);
    (0..9)
        .map(|t| image::imageops::crop_imm(img, (t % 3) * w, (t / 3) * h, w, h).to_image())
        .collect()
}

/// Recognition on a map of 2,200 camera locations built from real frames, with the default
/// (camera) parameters. Gardens Point has 300 frames, not 2,200 places, so every frame is cut
/// into its 3 x 3 non-overlapping tiles (each worked at the same 640 px width as a whole
/// frame): the tiles of day_right and night_right (1,800) and of day_left frames 0-44 (405),
/// the first 2,200 of them in that order. No two locations share pixels; what they share is
/// what a real fused route shares (consecutive frames overlap, and a place is seen by up to three
/// walks), unlike the earlier map of 11 crops of each frame, whose near-duplicates kept every
/// location a candidate. Queries: 20 day_left tiles of frames 50-69 (tile `k % 9` of frame
/// `50 + k`), places the map holds from the two other walks only. Skipped without the data.
fn bench_recognition_gardens(c: &mut Criterion) {
    let Some(dir) = gardens_dir() else {
        eprintln!("gardenspoint_dev not found: skipping the Gardens Point bench");
        return;
    };
    let walk = |name: &str| -> Vec<GrayImage> {
        let files = seasonloc_core::features::list_images(&dir.join(name)).expect("image folder");
        files
            .iter()
            .map(|f| {
                seasonloc_core::features::load_image_file(f)
                    .expect("readable frame")
                    .to_luma8()
            })
            .collect()
    };
    let (left, right, night) = (walk("day_left"), walk("day_right"), walk("night_right"));
    let mut map_images: Vec<GrayImage> = Vec::new();
    for frame in right.iter().chain(&night).chain(&left[..45]) {
        map_images.extend(tiles(frame));
    }
    map_images.truncate(2200);
    // Place of map location `l`: (frame, tile).
    let place = |l: usize| (l / 9 % 100, l % 9);
    let params = CoocParams::default();
    let started = std::time::Instant::now();
    let features =
        seasonloc_core::cooc::extract_all(&params, 0, &map_images).expect("map features");
    let extract_s = started.elapsed().as_secs_f64();
    let started = std::time::Instant::now();
    let drive = seasonloc_core::cooc::DriveFeatures {
        time: 0.0,
        features: features.clone(),
        locations: (0..map_images.len()).collect(),
    };
    let map = CoocMap::from_features(&params, &[drive]).expect("map builds");
    eprintln!(
        "Gardens Point tiles: {} locations, {} words; extraction {:.1} ms per tile (wall, rayon), \
         vocabulary + models {:.1} s",
        map.location_count(),
        map.vocabulary().len(),
        extract_s * 1000.0 / map_images.len() as f64,
        started.elapsed().as_secs_f64()
    );
    let queries: Vec<(usize, usize, Vec<Word>)> = (0..20)
        .map(|k| {
            let (frame, tile) = (50 + k, k % 9);
            let q = map
                .quantize("day_left tile", &tiles(&left[frame])[tile])
                .expect("valid tile");
            (frame, tile, q)
        })
        .collect();
    for schedule in [Schedule::Exhaustive, Schedule::BestFirst] {
        let (mut built, mut found) = (0, 0);
        for (frame, tile, q) in &queries {
            if let Some(r) = map.recognize_words(q, schedule) {
                built += r.evaluated;
                let (f, t) = place(r.location);
                found += usize::from(t == *tile && f.abs_diff(*frame) <= 2);
            }
        }
        eprintln!(
            "Gardens Point {schedule:?}: consistency matrices built per query = {:.1}, \
             answers at the query's place {found}/{}",
            built as f64 / queries.len() as f64,
            queries.len()
        );
    }
    let mut group = c.benchmark_group("cooc_recognize_gardens_2200");
    group.sample_size(10);
    let query_words: Vec<&[Word]> = queries.iter().map(|(_, _, q)| q.as_slice()).collect();
    bench_schedules(
        &mut group,
        &map,
        &query_words,
        &[Schedule::Exhaustive, Schedule::BestFirst],
    );
    // What cooc-seq and cooc-flow need: every location's score, then the sequence matching.
    let words: Vec<Vec<Word>> = queries.iter().map(|(_, _, q)| q.clone()).collect();
    group.bench_function("score_rows", |b| {
        b.iter(|| {
            for q in &words {
                std::hint::black_box(seasonloc_core::cooc::recognition::scores(
                    map.locations(),
                    q,
                ));
            }
        })
    });
    let scores = map.score_matrix_words(&words);
    group.bench_function("sequence_matching", |b| {
        b.iter(|| {
            seasonloc_core::cooc::sequence::match_sequences(
                std::hint::black_box(&scores),
                &seasonloc_core::cooc::SequenceParams::default(),
            )
            .expect("valid scores")
        })
    });
    group.finish();
    // The same map with the paper's vocabulary size: at most 22^3 = 10,648 words (fewer
    // candidate correspondences per location, so a cheaper `J` and a tighter bound; measured
    // to cost day-night sequence matching on Gardens Point, docs/cooc.md).
    let paper = CoocParams {
        vocabulary_branching: 22,
        vocabulary_depth: 3,
        ..params.clone()
    };
    let drive = seasonloc_core::cooc::DriveFeatures {
        time: 0.0,
        features: features.clone(),
        locations: (0..map_images.len()).collect(),
    };
    let big = CoocMap::from_features(&paper, &[drive]).expect("map builds");
    let big_queries: Vec<Vec<Word>> = (0..20)
        .map(|k| {
            big.quantize("day_left tile", &tiles(&left[50 + k])[k % 9])
                .expect("valid tile")
        })
        .collect();
    let built: usize = big_queries
        .iter()
        .filter_map(|q| big.recognize_words(q, Schedule::BestFirst))
        .map(|r| r.evaluated)
        .sum();
    eprintln!(
        "Gardens Point, {} words: BestFirst consistency matrices built per query = {:.1}",
        big.vocabulary().len(),
        built as f64 / big_queries.len() as f64
    );
    let mut group = c.benchmark_group("cooc_recognize_gardens_2200_10k_words");
    group.sample_size(10);
    let big_words: Vec<&[Word]> = big_queries.iter().map(Vec::as_slice).collect();
    bench_schedules(
        &mut group,
        &big,
        &big_words,
        &[Schedule::Exhaustive, Schedule::BestFirst],
    );
    group.finish();
    // Vocabulary training on the map's descriptors (as many as the map trains on).
    let all: Vec<f32> = features
        .iter()
        .flat_map(|f| f.descriptors.iter().copied())
        .collect();
    let n = all.len() / DESCRIPTOR_DIM;
    let stride = n.div_ceil(params.max_training_descriptors);
    let training: Vec<f32> = all
        .chunks_exact(DESCRIPTOR_DIM)
        .step_by(stride)
        .flatten()
        .copied()
        .collect();
    let spec = TreeSpec {
        branching: params.vocabulary_branching,
        depth: params.vocabulary_depth,
        iterations: params.kmeans_iterations,
        seed: params.seed,
    };
    let mut group = c.benchmark_group("cooc_vocabulary");
    group.sample_size(10);
    group.bench_function(
        format!("train_{}_descriptors", training.len() / DESCRIPTOR_DIM),
        |b| b.iter(|| Vocabulary::train(&training, DESCRIPTOR_DIM, spec).expect("trains")),
    );
    group.finish();
}

criterion_group!(
    benches,
    bench_recognition,
    bench_keypoints,
    bench_keypoints_960x540,
    bench_recognition_nordland,
    bench_recognition_gardens
);
criterion_main!(benches);
