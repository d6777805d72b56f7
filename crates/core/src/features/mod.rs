//! Global image descriptors: the [`Extractor`] trait, image decoding, and batch extraction
//! across cores.
//!
//! An extractor turns one decoded image into one global descriptor vector. Its length depends
//! only on the extractor's validated settings and the image size (after any resize the settings
//! ask for), so a map's descriptors are comparable with each other.
//!
//! Batch helpers run one rayon task per image and keep the input order in the output rows.
//! On failure they report the *first* bad image in input order (deterministically, whatever the
//! thread timing) and skip the work after it.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};

use image::DynamicImage;
use rayon::prelude::*;

use crate::{Error, Matrix, Result};

mod bilinear;
#[cfg(feature = "cnn")]
pub mod cnn;
pub mod geometry;
pub mod hog;
mod image_io;

pub use geometry::{image_file_size, Fit, Fitted};
pub use image_io::{
    decode_gray, decode_image, decode_image_as, from_colour_decode, list_images, load_image_file,
    load_image_file_as, prepare_gray, resize_gray, resize_rgb, to_gray, to_rgb, upright_dimensions,
    Pixels, DEFAULT_MAX_PIXELS, IMAGE_EXTENSIONS,
};

/// Turns one image into one global descriptor.
pub trait Extractor: Send + Sync {
    /// Descriptor length for an input image of `width x height` pixels, or an error when the
    /// extractor cannot use an image of that size.
    fn dim_for(&self, width: u32, height: u32) -> Result<usize>;

    /// The descriptor of one image. Never contains NaN or infinities.
    fn extract(&self, image: &image::DynamicImage) -> Result<Vec<f32>>;

    /// The pixels [`Extractor::extract`] reads: decode images for it with
    /// [`decode_image_as`] / [`load_image_file_as`] and this, so that a gray descriptor does
    /// not pay for colour it drops. The default, [`Pixels::Colour`], is always correct.
    fn pixels(&self) -> Pixels {
        Pixels::Colour
    }
}

/// Extracts the descriptors of `images` in parallel (rayon) into one row per image, in order.
///
/// Sizes are checked before any extraction: an image the extractor cannot use is an error
/// named `image #i`, and an image whose descriptor length differs from image 0's is an
/// [`Error::Shape`] naming both images and their sizes. An empty slice is [`Error::Empty`].
pub fn extract_batch(extractor: &dyn Extractor, images: &[DynamicImage]) -> Result<Matrix> {
    let first = images
        .first()
        .ok_or_else(|| Error::Empty("no images to extract descriptors from".into()))?;
    let size = |img: &DynamicImage| (img.width(), img.height());
    let (w0, h0) = size(first);
    let dim = extractor
        .dim_for(w0, h0)
        .map_err(|e| rename(e, &label(0)))?;
    for (i, img) in images.iter().enumerate().skip(1) {
        let (w, h) = size(img);
        let d = extractor.dim_for(w, h).map_err(|e| rename(e, &label(i)))?;
        if d != dim {
            return Err(Error::Shape(format!(
                "image #{i} is {w}x{h} px and gives {d} descriptor values, but image #0 is \
                 {w0}x{h0} px and gives {dim}; resize the images to one size"
            )));
        }
    }
    let mut out = Matrix::zeros(images.len(), dim);
    let first_bad = AtomicUsize::new(usize::MAX);
    let results: Vec<Result<()>> = out
        .as_mut_slice()
        .par_chunks_mut(dim.max(1))
        .zip(images.par_iter())
        .enumerate()
        .map(|(i, (row, img))| {
            if i > first_bad.load(Ordering::Relaxed) {
                return Ok(());
            }
            extractor
                .extract(img)
                .and_then(|d| fill_row(row, &d, &label(i)))
                .inspect_err(|_| {
                    first_bad.fetch_min(i, Ordering::Relaxed);
                })
        })
        .collect();
    results.into_iter().collect::<Result<()>>()?;
    Ok(out)
}

/// Decodes and extracts the image files `paths` in parallel, one row per file, in order.
///
/// Each rayon task reads, decodes and extracts one file and then drops the decoded image, so
/// at most one decoded image per worker thread is alive at a time. `progress` is called once
/// per finished image (from worker threads). The first bad file in input order is reported
/// by path; descriptor lengths that differ from the first file's are an [`Error::Shape`]
/// naming both files. An empty list is [`Error::Empty`].
pub fn extract_files(
    extractor: &dyn Extractor,
    paths: &[PathBuf],
    progress: &(dyn Fn() + Sync),
) -> Result<Matrix> {
    if paths.is_empty() {
        return Err(Error::Empty(
            "no image files to extract descriptors from".into(),
        ));
    }
    let first_bad = AtomicUsize::new(usize::MAX);
    let rows: Vec<Result<Option<FileRow>>> = paths
        .par_iter()
        .enumerate()
        .map(|(i, path)| {
            if i > first_bad.load(Ordering::Relaxed) {
                return Ok(None);
            }
            let row = extract_file(extractor, path);
            match &row {
                Ok(_) => progress(),
                Err(_) => {
                    first_bad.fetch_min(i, Ordering::Relaxed);
                }
            }
            row.map(Some)
        })
        .collect();
    let mut data = Vec::new();
    let mut first: Option<(usize, u32, u32, usize)> = None;
    for (i, row) in rows.into_iter().enumerate() {
        // A file is skipped only after a failure at a lower index, whose error returned above.
        let Some((w, h, values)) = row? else {
            continue;
        };
        match first {
            None => {
                data.reserve(values.len() * paths.len());
                first = Some((0, w, h, values.len()));
            }
            Some((f, w0, h0, dim)) if values.len() != dim => {
                return Err(Error::Shape(format!(
                    "{} is {w}x{h} px and gives {} descriptor values, but {} is {w0}x{h0} px \
                     and gives {dim}; resize the images to one size",
                    paths[i].display(),
                    values.len(),
                    paths[f].display()
                )));
            }
            Some(_) => {}
        }
        data.extend_from_slice(&values);
    }
    let dim = first.map_or(0, |(_, _, _, d)| d);
    Matrix::from_vec(paths.len(), dim, data)
}

/// A file's image size and descriptor.
type FileRow = (u32, u32, Vec<f32>);

fn extract_file(extractor: &dyn Extractor, path: &Path) -> Result<FileRow> {
    let image = load_image_file_as(path, extractor.pixels())?;
    let values = extractor
        .extract(&image)
        .map_err(|e| rename(e, &path.display().to_string()))?;
    Ok((image.width(), image.height(), values))
}

/// How batch errors name the image at index `i`.
fn label(i: usize) -> String {
    format!("#{i}")
}

/// Puts `name` into an [`Error::Image`] raised by an extractor that did not know the image's
/// name; other errors pass through.
fn rename(err: Error, name: &str) -> Error {
    match err {
        Error::Image { reason, .. } => Error::Image {
            name: name.to_string(),
            reason,
        },
        other => other,
    }
}

/// Copies a descriptor into its matrix row, checking the extractor kept its `dim_for` promise.
fn fill_row(row: &mut [f32], values: &[f32], name: &str) -> Result<()> {
    if row.len() != values.len() {
        return Err(Error::Shape(format!(
            "image {name}: the extractor produced {} values but announced {}",
            values.len(),
            row.len()
        )));
    }
    row.copy_from_slice(values);
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::hog::{HogOptions, HogSpec};
    use super::*;
    use image::{GrayImage, Luma};
    use std::sync::atomic::AtomicU32;

    fn textured(w: u32, h: u32, seed: u32) -> DynamicImage {
        DynamicImage::ImageLuma8(GrayImage::from_fn(w, h, |x, y| {
            Luma([((x * x + 3 * y * seed + x * y * seed) % 251) as u8])
        }))
    }

    fn hog(cell: u32, resize: Option<(u32, u32)>) -> HogSpec {
        HogSpec::new(HogOptions {
            cell_size: cell,
            resize,
        })
        .unwrap()
    }

    #[test]
    fn batch_equals_sequential_extraction_in_order() {
        let spec = hog(8, None);
        let images: Vec<_> = (0..13).map(|s| textured(40, 24, s + 1)).collect();
        let m = extract_batch(&spec, &images).unwrap();
        assert_eq!((m.rows(), m.cols()), (13, spec.dim_for(40, 24).unwrap()));
        for (i, img) in images.iter().enumerate() {
            assert_eq!(m.row(i), spec.extract(img).unwrap().as_slice(), "row {i}");
        }
    }

    #[test]
    fn batch_with_mixed_sizes_needs_a_resize() {
        let images = vec![
            textured(40, 24, 1),
            textured(40, 24, 2),
            textured(48, 24, 3),
        ];
        match extract_batch(&hog(8, None), &images) {
            Err(Error::Shape(msg)) => {
                assert!(msg.contains("image #2 is 48x24"), "{msg}");
                assert!(msg.contains("image #0 is 40x24"), "{msg}");
            }
            other => panic!("expected Shape, got {other:?}"),
        }
        let m = extract_batch(&hog(8, Some((32, 16))), &images).unwrap();
        assert_eq!((m.rows(), m.cols()), (3, 3 * 36));
    }

    #[test]
    fn batch_names_the_first_unusable_image() {
        let images = vec![textured(40, 24, 1), textured(4, 4, 2), textured(3, 3, 3)];
        match extract_batch(&hog(8, None), &images) {
            Err(Error::Image { name, reason }) => {
                assert_eq!(name, "#1");
                assert!(
                    reason.contains("4x4 px is smaller than one HOG cell of 8x8"),
                    "{reason}"
                );
            }
            other => panic!("expected Image, got {other:?}"),
        }
        assert!(matches!(
            extract_batch(&hog(8, None), &[]),
            Err(Error::Empty(_))
        ));
    }

    fn write_pngs(dir: &Path, sizes: &[(u32, u32)]) -> Vec<PathBuf> {
        sizes
            .iter()
            .enumerate()
            .map(|(i, &(w, h))| {
                let path = dir.join(format!("f{i:02}.png"));
                textured(w, h, i as u32 + 1).save(&path).unwrap();
                path
            })
            .collect()
    }

    #[test]
    fn extract_files_matches_batch_and_reports_progress() {
        let dir = tempfile::tempdir().unwrap();
        let paths = write_pngs(dir.path(), &[(40, 24); 9]);
        let calls = AtomicU32::new(0);
        let spec = hog(8, None);
        let m = extract_files(&spec, &paths, &|| {
            calls.fetch_add(1, Ordering::Relaxed);
        })
        .unwrap();
        let images: Vec<_> = paths.iter().map(|p| load_image_file(p).unwrap()).collect();
        assert_eq!(m, extract_batch(&spec, &images).unwrap());
        assert_eq!(calls.load(Ordering::Relaxed), 9);
    }

    #[test]
    fn extract_files_reports_the_first_bad_file_by_path() {
        let dir = tempfile::tempdir().unwrap();
        let mut paths = write_pngs(dir.path(), &[(40, 24); 6]);
        std::fs::write(&paths[2], b"broken").unwrap();
        std::fs::write(&paths[4], b"broken too").unwrap();
        match extract_files(&hog(8, None), &paths, &|| {}) {
            Err(Error::Image { name, .. }) => assert_eq!(name, paths[2].display().to_string()),
            other => panic!("expected Image, got {other:?}"),
        }
        paths[2] = dir.path().join("gone.png");
        match extract_files(&hog(8, None), &paths, &|| {}) {
            Err(Error::Io { path, .. }) => assert_eq!(path, paths[2]),
            other => panic!("expected Io, got {other:?}"),
        }
    }

    #[test]
    fn extract_files_names_small_and_mismatched_files() {
        let dir = tempfile::tempdir().unwrap();
        let paths = write_pngs(dir.path(), &[(40, 24), (40, 24), (5, 5), (48, 24)]);
        match extract_files(&hog(8, None), &paths, &|| {}) {
            Err(Error::Image { name, reason }) => {
                assert_eq!(name, paths[2].display().to_string());
                assert!(reason.contains("5x5 px"), "{reason}");
            }
            other => panic!("expected Image, got {other:?}"),
        }
        match extract_files(&hog(8, None), &[paths[0].clone(), paths[3].clone()], &|| {}) {
            Err(Error::Shape(msg)) => {
                assert!(
                    msg.contains(&format!("{} is 48x24", paths[3].display())),
                    "{msg}"
                )
            }
            other => panic!("expected Shape, got {other:?}"),
        }
        assert!(matches!(
            extract_files(&hog(8, None), &[], &|| {}),
            Err(Error::Empty(_))
        ));
    }

    /// The documented tolerance of gray-only JPEG decoding (`image_io`, `Pixels::Gray`): HOG
    /// on a camera JPEG's Y plane (BT.601) against HOG on the Rec. 709 luma of its colour
    /// decode, on Gardens Point (the map geometry and cells of the README's tables).
    #[test]
    fn gardens_point_hog_on_jpeg_y_is_within_tolerance_of_rec709_luma() {
        let Some(dir) = seasonloc_test_support::datasets::gardens_point() else {
            return;
        };
        let spec = Fitted::hog(32, (960, 540), Fit::Stretch).unwrap();
        assert_eq!(spec.pixels(), Pixels::Gray);
        let mut by_walk = Vec::new();
        for walk in ["day_right", "day_left", "night_right"] {
            let files = list_images(&dir.join(walk)).unwrap();
            let y = extract_files(&spec, &files, &|| {}).unwrap();
            let colour: Vec<_> = files.iter().map(|f| load_image_file(f).unwrap()).collect();
            let rec709 = extract_batch(&spec, &colour).unwrap();
            let cos: Vec<f64> = (0..files.len())
                .map(|i| cosine(y.row(i), rec709.row(i)))
                .collect();
            let min = cos.iter().copied().fold(1.0, f64::min);
            let mean = cos.iter().sum::<f64>() / cos.len() as f64;
            let worst_value = y
                .as_slice()
                .iter()
                .zip(rec709.as_slice())
                .map(|(a, b)| (a - b).abs())
                .fold(0.0f32, f32::max);
            eprintln!(
                "{walk}: cosine(HOG of Y, HOG of Rec. 709) min {min:.5} mean {mean:.5}, \
                 largest value change {worst_value:.4}"
            );
            // Measured: min 0.9935 (day_right), mean >= 0.9994; night_right is nearly
            // colourless and does not move.
            assert!(
                min >= 0.99 && mean >= 0.999,
                "{walk}: min {min}, mean {mean}"
            );
            by_walk.push((y, rec709));
        }
        // Similarities between walks (what the methods see) move by at most:
        let mut worst_sim = 0.0f64;
        for (a, b) in [(1, 0), (2, 0), (2, 1)] {
            let ((qy, q709), (ry, r709)) = (&by_walk[a], &by_walk[b]);
            for i in 0..qy.rows() {
                for j in 0..ry.rows() {
                    let d = (cosine(qy.row(i), ry.row(j)) - cosine(q709.row(i), r709.row(j))).abs();
                    worst_sim = worst_sim.max(d);
                }
            }
        }
        eprintln!("largest change of a cross-walk cosine similarity: {worst_sim:.5}");
        // Measured: 0.0090.
        assert!(worst_sim <= 0.015, "a similarity moved by {worst_sim}");
    }

    #[test]
    fn gray_extractors_get_the_jpeg_y_plane_and_colour_ones_colour() {
        let hog_spec = hog(8, Some((40, 24)));
        assert_eq!(hog_spec.pixels(), Pixels::Gray);
        let fitted = Fitted::hog(8, (40, 24), Fit::Crop).unwrap();
        assert_eq!(fitted.pixels(), Pixels::Gray);
        // The trait's default (the CNN keeps it: it reads RGB).
        struct Colourful;
        impl Extractor for Colourful {
            fn dim_for(&self, _: u32, _: u32) -> Result<usize> {
                Ok(3)
            }
            fn extract(&self, image: &DynamicImage) -> Result<Vec<f32>> {
                let rgb = image
                    .as_rgb8()
                    .ok_or_else(|| Error::Empty("not colour".into()))?;
                Ok(rgb.get_pixel(0, 0).0.map(f32::from).to_vec())
            }
        }
        assert_eq!(Colourful.pixels(), Pixels::Colour);
        // A 4:2:0 camera JPEG: files are decoded for what the extractor reads.
        let jpeg = include_bytes!("testdata/sampling_420.jpg");
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("frame.jpg");
        std::fs::write(&path, jpeg).unwrap();
        let paths = [path.clone(), path];
        let y = DynamicImage::ImageLuma8(decode_gray("y", jpeg, 10_000).unwrap());
        let colour = decode_image("c", jpeg, 10_000).unwrap();
        let m = extract_files(&hog_spec, &paths, &|| {}).unwrap();
        assert_eq!(m.row(1), hog_spec.extract(&y).unwrap().as_slice());
        assert_ne!(m.row(1), hog_spec.extract(&colour).unwrap().as_slice());
        let m = extract_files(&Colourful, &paths, &|| {}).unwrap();
        assert_eq!(m.row(0), Colourful.extract(&colour).unwrap().as_slice());
    }

    fn nordland() -> Option<PathBuf> {
        seasonloc_test_support::datasets::nordland()
    }

    fn cosine(a: &[f32], b: &[f32]) -> f64 {
        let dot: f64 = a.iter().zip(b).map(|(x, y)| f64::from(x * y)).sum();
        let na: f64 = a.iter().map(|x| f64::from(x * x)).sum::<f64>().sqrt();
        let nb: f64 = b.iter().map(|x| f64::from(x * x)).sum::<f64>().sqrt();
        if na == 0.0 || nb == 0.0 {
            0.0
        } else {
            dot / (na * nb)
        }
    }

    #[test]
    fn nordland_same_place_is_more_similar_than_random_pairs() {
        let Some(dir) = nordland() else { return };
        let spec = hog(8, None);
        let summer = list_images(&dir.join("summer")).unwrap();
        let winter = list_images(&dir.join("winter")).unwrap();
        assert_eq!(summer.len(), winter.len());
        let frame = load_image_file(&summer[0]).unwrap();
        assert_eq!(spec.extract(&frame).unwrap().len(), 756);
        // Frames 0..17 are the unusable standing-still frames (README).
        let (s, w) = (&summer[17..], &winter[17..]);
        let ref_m = extract_files(&spec, s, &|| {}).unwrap();
        let query_m = extract_files(&spec, w, &|| {}).unwrap();
        assert!(ref_m.as_slice().iter().all(|v| v.is_finite()));
        let n = s.len();
        let same = (0..n)
            .map(|i| cosine(query_m.row(i), ref_m.row(i)))
            .sum::<f64>()
            / n as f64;
        // Deterministic "random" partners, always at least 3 frames away.
        let mut state: u64 = 0x9e37_79b9_7f4a_7c15;
        let mut random = 0.0;
        for i in 0..n {
            state = state
                .wrapping_mul(6_364_136_223_846_793_005)
                .wrapping_add(1);
            let j = (i + 3 + (state >> 33) as usize % (n - 6)) % n;
            random += cosine(query_m.row(i), ref_m.row(j));
        }
        let random = random / n as f64;
        eprintln!("nordland HOG 8px: mean cosine same place {same:.4}, random pairs {random:.4}");
        assert!(same > random + 0.01, "same {same:.4} vs random {random:.4}");
    }
}
