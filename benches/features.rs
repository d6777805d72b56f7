//! HOG extraction benches: the paper's 1024x768 / 32 px grid single-threaded (HOG alone on a
//! gray image, and camera-image preparation alone: JPEG decode + gray + resize, with the shipped
//! path (the JPEG's Y plane decoded alone) and, for back-to-back before/afters, the colour
//! decode + Rec. 709 luma it replaced for gray descriptors and the `image` crate's `to_luma8` +
//! `imageops::resize` before that), a 64x32 Nordland frame with 8 px cells, and batch throughput across all cores
//! (`extract_batch` on decoded frames, `extract_files` with PNG decoding). Compare with
//! `benches/opencv_hog.py`.

use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use image::DynamicImage;
use seasonloc_core::features::hog::{HogOptions, HogSpec};
use seasonloc_core::features::{
    extract_batch, extract_files, load_image_file, load_image_file_as, prepare_gray, Extractor,
    Pixels,
};

mod fixture;

fn hog(cell_size: u32, resize: Option<(u32, u32)>) -> HogSpec {
    HogSpec::new(HogOptions { cell_size, resize }).expect("valid bench options")
}

fn single(c: &mut Criterion) {
    let mut g = c.benchmark_group("hog_single");
    if let Some(gray) = fixture::sample_gray("dog", 1024, 768) {
        let image = DynamicImage::ImageLuma8(gray);
        let spec = hog(32, None);
        g.bench_function("gray_1024x768_cell32", |b| {
            b.iter(|| spec.extract(&image).expect("extracts"))
        });
        if fixture::thread_cpu_time().is_some() {
            g.bench_function("gray_1024x768_cell32_thread_cpu_time", |b| {
                b.iter_custom(|n| {
                    fixture::cpu_time_of(n, || spec.extract(&image).expect("extracts"))
                })
            });
        }
    }
    if let Some(path) = fixture::shared("models/samples/dog.jpg") {
        let spec = hog(32, Some((1024, 768)));
        g.bench_function("jpeg_decode_to_hog_1024x768_cell32", |b| {
            b.iter(|| {
                spec.extract(&load_image_file_as(&path, spec.pixels()).expect("decodes"))
                    .expect("extracts")
            })
        });
        // The shipped preparation path of gray descriptors (what `extract_files` and HOG's
        // `extract` with `resize` run): the Y plane alone, then the resize.
        let prepare = || {
            let img = load_image_file_as(&path, Pixels::Gray).expect("decodes");
            prepare_gray(&img, Some((1024, 768)))
                .expect("resizes")
                .into_owned()
        };
        // The colour path (still the CNN's decode) + Rec. 709 luma, which gray descriptors
        // used before, kept for back-to-back comparisons.
        let prepare_colour = || {
            let img = load_image_file(&path).expect("decodes");
            prepare_gray(&img, Some((1024, 768)))
                .expect("resizes")
                .into_owned()
        };
        // The path before that.
        let prepare_image_crate = || {
            let img = load_image_file(&path).expect("decodes").to_luma8();
            image::imageops::resize(&img, 1024, 768, image::imageops::FilterType::Triangle)
        };
        let decode_only = || load_image_file(&path).expect("decodes");
        let decode_y_only = || load_image_file_as(&path, Pixels::Gray).expect("decodes");
        // The two stages after decoding, alone (where the time goes).
        let decoded = load_image_file(&path).expect("decodes");
        g.bench_function("gray_only_768x576", |b| {
            b.iter(|| seasonloc_core::features::to_gray(&decoded).into_owned())
        });
        let gray = prepare_gray(&decoded, None).expect("gray").into_owned();
        g.bench_function("resize_gray_only_768x576_to_1024x768", |b| {
            b.iter(|| {
                seasonloc_core::features::resize_gray(&gray, 1024, 768)
                    .expect("resizes")
                    .into_owned()
            })
        });
        g.bench_function("jpeg_decode_gray_resize_1024x768", |b| b.iter(prepare));
        g.bench_function("jpeg_decode_colour_gray_resize_1024x768", |b| {
            b.iter(prepare_colour)
        });
        g.bench_function("jpeg_decode_gray_resize_1024x768_image_crate", |b| {
            b.iter(prepare_image_crate)
        });
        g.bench_function("jpeg_decode_y_only_768x576", |b| b.iter(decode_y_only));
        g.bench_function("jpeg_decode_only_768x576", |b| b.iter(decode_only));
        if fixture::thread_cpu_time().is_some() {
            g.bench_function("jpeg_decode_gray_resize_1024x768_thread_cpu_time", |b| {
                b.iter_custom(|n| fixture::cpu_time_of(n, prepare))
            });
            g.bench_function(
                "jpeg_decode_colour_gray_resize_1024x768_thread_cpu_time",
                |b| b.iter_custom(|n| fixture::cpu_time_of(n, prepare_colour)),
            );
            g.bench_function(
                "jpeg_decode_gray_resize_1024x768_image_crate_thread_cpu_time",
                |b| b.iter_custom(|n| fixture::cpu_time_of(n, prepare_image_crate)),
            );
        }
    }
    // A camera JPEG with the common 4:2:0 chroma sampling (dog.jpg is 4:4:0, where zune-jpeg's
    // Y-only output does not pay: `image_io`), colour against Y-only decoding.
    if let Some(path) = fixture::shared("data/gardenspoint_dev/day_right/Image000.jpg") {
        g.bench_function("jpeg_decode_only_960x540_420", |b| {
            b.iter(|| load_image_file(&path).expect("decodes"))
        });
        g.bench_function("jpeg_decode_y_only_960x540_420", |b| {
            b.iter(|| load_image_file_as(&path, Pixels::Gray).expect("decodes"))
        });
    }
    if let Some(frames) = fixture::nordland_images("summer", 600) {
        let spec = hog(8, None);
        let frame = &frames[500];
        g.bench_function("nordland_64x32_cell8", |b| {
            b.iter(|| spec.extract(frame).expect("extracts"))
        });
    }
    g.finish();
}

fn batch(c: &mut Criterion) {
    let mut g = c.benchmark_group("hog_batch");
    g.sample_size(10);
    if let Some(gray) = fixture::sample_gray("eagle", 1024, 768) {
        let images = vec![DynamicImage::ImageLuma8(gray); 200];
        let spec = hog(32, None);
        g.throughput(Throughput::Elements(images.len() as u64));
        g.bench_function("extract_batch_200x_1024x768_cell32", |b| {
            b.iter(|| extract_batch(&spec, &images).expect("extracts"))
        });
    }
    if let Some(paths) = fixture::nordland_paths("winter", 200) {
        let spec = hog(8, None);
        g.throughput(Throughput::Elements(paths.len() as u64));
        g.bench_function("extract_files_200_nordland_png_cell8", |b| {
            b.iter(|| extract_files(&spec, &paths, &|| {}).expect("extracts"))
        });
    }
    g.finish();
}

criterion_group!(benches, single, batch);
criterion_main!(benches);
