//! CNN descriptor timings: model load, preprocessing, one image on one core, and a batch on one
//! vs two rayon threads sharing one loaded model (does the second core really help?).
//!
//! Needs `../shared/models` (skips with a message otherwise). Short runs:
//! `cargo bench --bench cnn -- --warm-up-time 1 --measurement-time 3`.

mod fixture;

use std::path::{Path, PathBuf};
use std::time::Duration;

use criterion::{BenchmarkId, Criterion, Throughput};
use image::DynamicImage;
use rayon::prelude::*;
use seasonloc_core::features::cnn::{CnnOptions, CnnResize, CnnSpec};
use seasonloc_core::features::Extractor;

fn shared_models() -> Option<PathBuf> {
    let dir = fixture::models_dir();
    dir.join("efficientnet-lite0-224.onnx")
        .is_file()
        .then_some(dir)
}

fn nordland_frame() -> Option<DynamicImage> {
    let path = fixture::data_dir("nordland_64x32").join("winter/images-00010.png");
    image::open(path).ok()
}

fn options(dir: &Path, layer: &str) -> CnnOptions {
    let mut o = CnnOptions::efficientnet_lite0(dir.join("efficientnet-lite0-224.onnx"));
    o.layer = layer.into();
    o.resize = CnnResize::Stretch;
    o
}

fn bench_load(c: &mut Criterion, dir: &Path) {
    let mut g = c.benchmark_group("cnn_load");
    g.sample_size(10);
    for layer in ["block10", "pooled"] {
        g.bench_function(BenchmarkId::from_parameter(layer), |b| {
            b.iter(|| CnnSpec::new_uncached(options(dir, layer)).expect("model loads"))
        });
    }
    g.finish();
}

fn bench_single(c: &mut Criterion, dir: &Path, images: &[(&str, DynamicImage)]) {
    let mut g = c.benchmark_group("cnn_single_image");
    g.sample_size(20);
    for layer in ["block10", "pooled"] {
        let spec = CnnSpec::new(options(dir, layer)).expect("model loads");
        for (name, img) in images {
            g.bench_function(BenchmarkId::new(layer, name), |b| {
                b.iter(|| spec.extract(img).expect("extracts"))
            });
        }
    }
    let spec = CnnSpec::new(options(dir, "block10")).expect("model loads");
    for (name, img) in images {
        g.bench_function(BenchmarkId::new("preprocess_only", name), |b| {
            b.iter(|| spec.preprocess(img).expect("preprocesses"))
        });
    }
    g.finish();
}

/// The same 8 images on a rayon pool of 1 and of 2 threads, one shared model: the per-image
/// time should halve on two free cores if the plan is truly shared without contention.
fn bench_batch(c: &mut Criterion, dir: &Path, image: &DynamicImage) {
    const BATCH: usize = 8;
    let spec = CnnSpec::new(options(dir, "block10")).expect("model loads");
    let batch: Vec<DynamicImage> = vec![image.clone(); BATCH];
    let mut g = c.benchmark_group("cnn_batch8_block10");
    g.sample_size(10);
    g.throughput(Throughput::Elements(BATCH as u64));
    for threads in [1, 2] {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .expect("thread pool");
        g.bench_function(BenchmarkId::new("threads", threads), |b| {
            b.iter(|| {
                pool.install(|| {
                    batch
                        .par_iter()
                        .map(|img| spec.extract(img).expect("extracts"))
                        .collect::<Vec<_>>()
                })
            })
        });
    }
    g.finish();
}

/// The end-to-end case: the first 400 Nordland winter frames read, decoded, stretched
/// to 224x224 and run to `block10` by `extract_files` on the global rayon pool (both cores).
/// Compare with `benches/onnxruntime_cnn.py` (same frames, same work, two threads).
fn bench_nordland400(c: &mut Criterion, dir: &Path) {
    let folder = fixture::data_dir("nordland_64x32").join("winter");
    let Ok(mut paths) = seasonloc_core::features::list_images(&folder) else {
        eprintln!("skipping cnn_nordland400: {} not found", folder.display());
        return;
    };
    paths.truncate(400);
    let spec = CnnSpec::new(options(dir, "block10")).expect("model loads");
    let mut g = c.benchmark_group("cnn_nordland400");
    g.sample_size(10);
    g.throughput(Throughput::Elements(paths.len() as u64));
    g.bench_function("block10_stretch_extract_files", |b| {
        b.iter(|| seasonloc_core::features::extract_files(&spec, &paths, &|| {}).expect("extracts"))
    });
    g.finish();
}

fn main() {
    let Some(dir) = shared_models() else {
        eprintln!("skipping cnn benches: ../shared/models is absent");
        return;
    };
    let photo = image::open(dir.join("samples/dog.jpg")).expect("samples/dog.jpg decodes");
    let mut images = vec![("photo_768x576", photo)];
    match nordland_frame() {
        Some(frame) => images.push(("nordland_64x32", frame)),
        None => eprintln!("no Nordland frame in ../shared/data: timing the photo only"),
    }
    let mut c = Criterion::default()
        .warm_up_time(Duration::from_secs(1))
        .measurement_time(Duration::from_secs(3))
        .configure_from_args();
    bench_load(&mut c, &dir);
    bench_single(&mut c, &dir, &images);
    bench_batch(&mut c, &dir, &images[0].1);
    bench_nordland400(&mut c, &dir);
    c.final_summary();
}
