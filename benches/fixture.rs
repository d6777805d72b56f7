//! Shared bench inputs: locating the public datasets and the model and loading the sample
//! images and Nordland frames (cases whose data is absent print why and are skipped), and
//! deterministic synthetic matrices.
#![allow(dead_code)] // each bench uses only some helpers

use std::path::{Path, PathBuf};
use std::time::Duration;

use image::{DynamicImage, GrayImage};
use seasonloc_core::Matrix;

/// The folder of dataset `name` (`nordland_64x32`, `gardenspoint_dev`) where the test suites
/// find it (`seasonloc_test_support::datasets`: `$SEASONLOC_DATASETS/<name>`, `data/<name>`, or
/// the folder CI places beside the repository); a path that does not exist when it is absent,
/// so the callers' existence checks skip the case.
pub fn data_dir(name: &str) -> PathBuf {
    seasonloc_test_support::datasets::dataset(name, &[])
        .unwrap_or_else(|| PathBuf::from("absent-dataset").join(name))
}

/// The CNN model folder (the ONNX model and `samples/`), or a path that does not exist.
pub fn models_dir() -> PathBuf {
    seasonloc_test_support::datasets::model_file("efficientnet-lite0-224.onnx")
        .and_then(|m| m.parent().map(Path::to_path_buf))
        .unwrap_or_else(|| PathBuf::from("absent-models"))
}

/// `rel` below the data (`data/<dataset>/...`) or the model folder (`models/...`), or `None`
/// with a printed skip message.
pub fn shared(rel: &str) -> Option<PathBuf> {
    seasonloc_test_support::datasets::resolve(rel)
}

/// A sample photo (`shared/models/samples/<name>.jpg`) as luma, resized (triangle filter) to
/// `width x height` by the product's preparation path.
pub fn sample_gray(name: &str, width: u32, height: u32) -> Option<GrayImage> {
    let path = shared(&format!("models/samples/{name}.jpg"))?;
    let image = seasonloc_core::features::load_image_file(&path).expect("sample photo decodes");
    Some(
        seasonloc_core::features::prepare_gray(&image, Some((width, height)))
            .expect("resizes")
            .into_owned(),
    )
}

/// The first `n` frames of one Nordland season (`summer` or `winter`), in route order.
pub fn nordland_paths(season: &str, n: usize) -> Option<Vec<PathBuf>> {
    let dir = shared(&format!("data/nordland_64x32/{season}"))?;
    let mut paths = seasonloc_core::features::list_images(&dir).expect("Nordland folder lists");
    paths.truncate(n);
    Some(paths)
}

/// The first `n` frames of one Nordland season, decoded.
pub fn nordland_images(season: &str, n: usize) -> Option<Vec<DynamicImage>> {
    let paths = nordland_paths(season, n)?;
    Some(
        paths
            .iter()
            .map(|p| seasonloc_core::features::load_image_file(p).expect("Nordland frame decodes"))
            .collect(),
    )
}

/// CPU time the calling thread has run so far (first field of `/proc/thread-self/schedstat`,
/// in ns), or `None` where that file is unavailable. On a machine shared with other jobs this
/// is a steadier single-threaded figure than wall time.
pub fn thread_cpu_time() -> Option<Duration> {
    let stat = std::fs::read_to_string("/proc/thread-self/schedstat").ok()?;
    let ns = stat.split_whitespace().next()?.parse().ok()?;
    Some(Duration::from_nanos(ns))
}

/// For `Bencher::iter_custom`: runs `f` `iters` times and returns the thread CPU time spent.
pub fn cpu_time_of<R>(iters: u64, mut f: impl FnMut() -> R) -> Duration {
    let start = thread_cpu_time().expect("checked with thread_cpu_time() before");
    for _ in 0..iters {
        std::hint::black_box(f());
    }
    thread_cpu_time().expect("checked with thread_cpu_time() before") - start
}

/// A deterministic `rows x cols` matrix of pseudo-random values in `[0, 1)` (xorshift64 from
/// `seed`): non-negative like HOG / ReLU descriptors, and in a cosine matrix's range.
pub fn uniform_matrix(rows: usize, cols: usize, seed: u64) -> Matrix {
    let mut s = seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1;
    let data = (0..rows * cols)
        .map(|_| {
            s ^= s << 13;
            s ^= s >> 7;
            s ^= s << 17;
            (s >> 40) as f32 / (1u64 << 24) as f32
        })
        .collect();
    Matrix::from_vec(rows, cols, data).expect("length is rows * cols")
}
