//! The dashboard's pictures, computed on the request path: the bounded similarity-matrix
//! picture of every localization (max pooling into at most 512 x 512 pixels, plus its PNG) and
//! the JPEG thumbnail of every uploaded reference image. Throughput of the matrix picture is in
//! matrix cells per second, so it compares directly with `normalize_columns` in
//! `benches/similarity.rs` (one pass over the same cells).
//!
//! Run: `cargo bench --bench picture -- --warm-up-time 1 --measurement-time 3`

use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion, Throughput};
use image::{DynamicImage, Rgb, RgbImage};
use seasonloc_core::picture::{thumbnail_jpeg, MatrixPicture};

mod fixture;
use fixture::uniform_matrix;

fn bench_matrix_picture(c: &mut Criterion) {
    let mut group = c.benchmark_group("matrix_picture");
    group.sample_size(10);
    // Nordland dev split (no downsampling of rows); a long batch against a 30,000-image map.
    for (q, d) in [(2400, 2400), (1000, 30_000)] {
        let m = uniform_matrix(q, d, 7);
        group.throughput(Throughput::Elements((q * d) as u64));
        group.bench_with_input(BenchmarkId::new("pool", format!("{q}x{d}")), &m, |b, m| {
            b.iter(|| MatrixPicture::bounded(m).expect("valid input"))
        });
        let p = MatrixPicture::bounded(&m).expect("valid input");
        group.bench_with_input(BenchmarkId::new("png", format!("{q}x{d}")), &p, |b, p| {
            b.iter(|| p.to_png().expect("encodes"))
        });
    }
    group.finish();
}

fn bench_thumbnail(c: &mut Criterion) {
    let mut group = c.benchmark_group("thumbnail");
    // A Nordland frame (64x32 grey, no scaling) and a Gardens Point frame (960x540 colour).
    let gray = DynamicImage::ImageLuma8(image::GrayImage::from_fn(64, 32, |x, y| {
        image::Luma([((x * 7 + y * 3) % 256) as u8])
    }));
    let colour = DynamicImage::ImageRgb8(RgbImage::from_fn(960, 540, |x, y| {
        Rgb([(x % 256) as u8, (y % 256) as u8, ((x ^ y) % 256) as u8])
    }));
    for (name, img) in [("64x32-grey", gray), ("960x540-rgb", colour)] {
        group.bench_with_input(BenchmarkId::from_parameter(name), &img, |b, img| {
            b.iter(|| thumbnail_jpeg(img).expect("encodes"))
        });
    }
    group.finish();
}

criterion_group!(benches, bench_matrix_picture, bench_thumbnail);
criterion_main!(benches);
