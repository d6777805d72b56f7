//! Time of the baselines on a Nordland-sized (2400 x 2400) similarity matrix: best match and
//! SeqSLAM with OpenSeqSLAM's defaults (ds = 10, 5 velocities). When the real Nordland dev
//! data is present (`../shared/data/nordland_64x32` beside the repository, or the folder
//! `$SEASONLOC_SHARED/data/nordland_64x32`), the matrix is built from it with whole-image
//! grayscale descriptors (mean-centred pixels, so cosine = normalised cross-correlation) and
//! the benchmark also prints both baselines' AP (±1 frame, queries 0-16 excluded) as a sanity
//! check of the pipeline; otherwise a synthetic matrix is used and a message says so.
//!
//! Run: `cargo bench --bench baselines -- --warm-up-time 1 --measurement-time 3`

mod fixture;

use std::path::{Path, PathBuf};

use criterion::{criterion_group, criterion_main, Criterion};
use seasonloc_core::baselines::{best_match, seqslam, SeqSlamParams};
use seasonloc_core::eval::{evaluate, Exclusions, GroundTruth};
use seasonloc_core::similarity::cosine_matrix;
use seasonloc_core::Matrix;

fn nordland_dir() -> PathBuf {
    fixture::data_dir("nordland_64x32")
}

/// Mean-centred grayscale pixels of every PNG in `dir`, in file-name order.
fn pixel_descriptors(dir: &Path) -> Matrix {
    let mut files: Vec<PathBuf> = std::fs::read_dir(dir)
        .expect("readable image folder")
        .map(|e| e.expect("directory entry").path())
        .filter(|p| p.extension().is_some_and(|e| e == "png"))
        .collect();
    files.sort();
    let rows: Vec<Vec<f32>> = files
        .iter()
        .map(|f| {
            let img = image::open(f).expect("decodable PNG").to_luma8();
            let v: Vec<f32> = img.pixels().map(|p| f32::from(p.0[0])).collect();
            let mean = v.iter().sum::<f32>() / v.len() as f32;
            v.into_iter().map(|x| x - mean).collect()
        })
        .collect();
    Matrix::from_rows(&rows).expect("equally sized images")
}

fn synthetic_similarity(q: usize, d: usize) -> Matrix {
    let mut s = 0x2545_F491_4F6C_DD1Du64;
    let mut m = Matrix::zeros(q, d);
    for i in 0..q {
        for j in 0..d {
            s ^= s << 13;
            s ^= s >> 7;
            s ^= s << 17;
            let noise = (s >> 40) as f32 / (1u64 << 24) as f32;
            m.set(i, j, if i == j { 0.8 } else { 0.9 * noise });
        }
    }
    m
}

fn bench_baselines(c: &mut Criterion) {
    let dir = nordland_dir();
    let sim = if dir.join("ground_truth.csv").exists() {
        let q = pixel_descriptors(&dir.join("winter"));
        let d = pixel_descriptors(&dir.join("summer"));
        let sim = cosine_matrix(&q, &d).expect("valid descriptors");
        let gt = GroundTruth::from_csv(&dir.join("ground_truth.csv")).expect("valid CSV");
        let ex = Exclusions::parse("0-16").expect("valid exclusions");
        let params = SeqSlamParams::default();
        for (name, preds) in [
            ("best match", best_match(&sim)),
            ("seqslam", seqslam(&sim, &params).expect("valid input")),
        ] {
            let m = evaluate(&preds, &gt, sim.rows(), 1, &ex).expect("valid predictions");
            println!(
                "nordland raw-pixel NCC {}x{}: {name}: AP {:.3}, recall@100p {:.3}, \
                 recall@99p {:.3}, max F1 {:.3}, precision@full {:.3}",
                sim.rows(),
                sim.cols(),
                m.ap,
                m.recall_at_100p,
                m.recall_at_99p,
                m.max_f1,
                m.precision_at_full
            );
        }
        sim
    } else {
        println!(
            "Nordland data not found at {}: timing a synthetic 2400x2400 matrix instead",
            dir.display()
        );
        synthetic_similarity(2400, 2400)
    };
    let shape = format!("{}x{}", sim.rows(), sim.cols());
    let mut group = c.benchmark_group("baselines");
    group.sample_size(10);
    group.bench_function(format!("best_match/{shape}"), |b| {
        b.iter(|| best_match(&sim))
    });
    let params = SeqSlamParams::default();
    group.bench_function(format!("seqslam/{shape}"), |b| {
        b.iter(|| seqslam(&sim, &params).expect("valid input"))
    });
    group.finish();
}

criterion_group!(benches, bench_baselines);
criterion_main!(benches);
