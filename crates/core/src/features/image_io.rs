//! Image input and preparation: decoding JPEG/PNG bytes with a pixel limit, loading files,
//! listing a folder, and the one colour-conversion and resize path that HOG, CNN and
//! co-occurrence extraction share (CLI and service alike).
//!
//! The pixel limit is checked from the image header *before* any pixel is decoded, so a small
//! upload that claims a huge size (a decompression bomb) costs nothing. Formats are detected by
//! content, never by file name. Every error names the image (file path or multipart part name).
//!
//! Preparation, and why it is fast (BENCHMARKS.md, "Image preparation"):
//! * JPEG is decoded by `zune-jpeg` (SIMD IDCT and colour conversion; the decoder `image`
//!   wraps) called directly in strict mode, so truncated or corrupt frames are rejected rather
//!   than padded with grey ([`decode_image`]); PNG by `image` (`png`/`fdeflate`);
//! * callers decode only the pixels their extractor reads ([`Pixels`],
//!   `Extractor::pixels`): for gray descriptors (HOG) a camera (YCbCr) JPEG gives its Y plane,
//!   decoded without the chroma IDCT, upsampling and colour conversion, as OpenCV's
//!   `IMREAD_GRAYSCALE` does; the CNN keeps the colour decode;
//! * **tolerance of gray-only decoding.** Y is BT.601 luma (`0.299 R + 0.587 G + 0.114 B`, as
//!   JFIF defines YCbCr), where gray was the Rec. 709 luma of the decoded RGB before. The Y
//!   plane is exactly the one the full decode computes and within one level of libjpeg-turbo's
//!   (test, all four chroma samplings); PNG and gray JPEGs are unchanged (bit for bit, test;
//!   Nordland is PNG). On Gardens Point (HOG 32 px at 960x540, 300 frames) the HOG
//!   descriptor of each frame keeps a cosine >= 0.99 with its former value (measured min
//!   0.9935, mean >= 0.9994) and no cross-walk similarity moves by more than 0.015 (measured
//!   0.009); a test pins both on the shared data. The README's Gardens Point HOG rows moved by
//!   at most 0.01 AP;
//! * [`to_gray`] is `image`'s `to_luma8` (Rec. 709 weights, `round(255 (kr R + kg G + kb B))`
//!   on channels scaled to `0..=1` in `f32`) bit for bit, but computed in one branch-free loop
//!   over RGB8 instead of `image`'s generic per-pixel conversion with a libm `roundf`;
//! * [`resize_gray`] / [`resize_rgb`] use `fast_image_resize`'s bilinear convolution (the
//!   triangle filter, widened when shrinking so that it antialiases: the same filter as `image`'s
//!   `FilterType::Triangle`, Pillow's and torchvision's antialiased bilinear), with AVX2/SSE4.1
//!   kernels picked at run time. Gray (HOG, co-occurrence) runs in 16-bit fixed point, ~15x
//!   faster than `image`'s `f32` `imageops::resize`, whose output it matches within one grey
//!   level (documented tolerance, checked by a test). RGB (the CNN input) runs in `f32` and
//!   rounds once at the end like `image`, because a CNN descriptor moves by up to 2e-3 when its
//!   input moves by one level; it matches `image` at all but 1 in 1,000 values when shrinking
//!   and under 1 % when enlarging, each within one level (test).

use std::path::{Path, PathBuf};

use image::DynamicImage;

use crate::{Error, Result};

mod colour;
mod decode;
mod resize;

pub use colour::{to_gray, to_rgb};
pub use decode::{
    decode_gray, decode_image, decode_image_as, from_colour_decode, upright_dimensions,
};
pub use resize::{prepare_gray, resize_gray, resize_rgb};

/// Pixel limit used by [`load_image_file`]: 100 megapixels.
pub const DEFAULT_MAX_PIXELS: u64 = 100_000_000;

/// File extensions [`list_images`] accepts (compared case-insensitively).
pub const IMAGE_EXTENSIONS: [&str; 3] = ["png", "jpg", "jpeg"];

/// Which pixels the consumer of a decoded image reads, so that decoding can skip the work
/// nobody uses.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub enum Pixels {
    /// The image as decoded: `Rgb8` for colour images, `Luma8` for gray ones (the CNN input,
    /// thumbnails, anything that shows or needs colour).
    #[default]
    Colour,
    /// 8-bit gray only (HOG, co-occurrence): always an `ImageLuma8`. A YCbCr JPEG (nearly every
    /// camera JPEG) gives its Y plane, decoded alone: the chroma blocks are entropy-decoded
    /// and skipped, with no chroma IDCT, upsampling or colour conversion (what OpenCV's
    /// `IMREAD_GRAYSCALE` does with libjpeg-turbo). Y is the JPEG's BT.601 luma, not the
    /// Rec. 709 luma [`to_gray`] takes of decoded RGB; the two differ by a few levels on
    /// natural images (documented tolerance: module doc). Every other image (PNG, gray or
    /// RGB/CMYK JPEGs) gives exactly [`to_gray`] of its colour decode.
    Gray,
}

/// Reads and decodes one JPEG/PNG file (at most [`DEFAULT_MAX_PIXELS`] pixels); errors name
/// the path.
pub fn load_image_file(path: &Path) -> Result<DynamicImage> {
    load_image_file_as(path, Pixels::Colour)
}

/// [`load_image_file`] of only the pixels the caller reads ([`decode_image_as`]).
pub fn load_image_file_as(path: &Path, pixels: Pixels) -> Result<DynamicImage> {
    let bytes = std::fs::read(path).map_err(|source| Error::Io {
        path: path.to_path_buf(),
        source,
    })?;
    decode_image_as(
        &path.display().to_string(),
        &bytes,
        DEFAULT_MAX_PIXELS,
        pixels,
    )
}

/// The PNG/JPEG files of `dir` (extensions in [`IMAGE_EXTENSIONS`], any case; not recursive),
/// sorted by file name, which is the route order of a sequence folder.
///
/// Fails with [`Error::Io`] when `dir` cannot be read and [`Error::Empty`] when it holds no
/// image.
pub fn list_images(dir: &Path) -> Result<Vec<PathBuf>> {
    let io_err = |source| Error::Io {
        path: dir.to_path_buf(),
        source,
    };
    let mut files = Vec::new();
    for entry in std::fs::read_dir(dir).map_err(io_err)? {
        let path = entry.map_err(io_err)?.path();
        let is_image = path.extension().and_then(|e| e.to_str()).is_some_and(|e| {
            IMAGE_EXTENSIONS
                .iter()
                .any(|known| e.eq_ignore_ascii_case(known))
        });
        // `is_file` follows symlinks, so linked images count too.
        if is_image && path.is_file() {
            files.push(path);
        }
    }
    if files.is_empty() {
        return Err(Error::Empty(format!(
            "no .png/.jpg/.jpeg image in {}",
            dir.display()
        )));
    }
    files.sort_by(|a, b| a.file_name().cmp(&b.file_name()));
    Ok(files)
}

#[cfg(test)]
mod tests {
    use super::*;
    use image::{ImageBuffer, ImageFormat, Rgb, RgbImage};
    use std::io::Cursor;

    pub(super) fn sample_rgb(w: u32, h: u32) -> RgbImage {
        ImageBuffer::from_fn(w, h, |x, y| Rgb([(x * 7) as u8, (y * 11) as u8, 90]))
    }

    pub(super) fn encode(img: &RgbImage, format: ImageFormat) -> Vec<u8> {
        let mut out = Cursor::new(Vec::new());
        img.write_to(&mut out, format).unwrap();
        out.into_inner()
    }

    pub(super) fn reason(err: Error) -> (String, String) {
        match err {
            Error::Image { name, reason } => (name, reason),
            other => panic!("expected Error::Image, got {other:?}"),
        }
    }

    pub(super) fn noisy_rgb(w: u32, h: u32, seed: u32) -> RgbImage {
        let mut state = seed.wrapping_mul(2_654_435_761).wrapping_add(1);
        ImageBuffer::from_fn(w, h, |x, y| {
            state = state.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
            let n = (state >> 24) as u8;
            // Smooth gradients plus noise: both flat areas and sharp edges.
            Rgb([
                n,
                ((x * 255) / w.max(1)) as u8 ^ (n & 0x0f),
                ((y * 5 + x * 3) % 256) as u8,
            ])
        })
    }

    #[test]
    fn list_images_filters_and_sorts_by_file_name() {
        let dir = tempfile::tempdir().unwrap();
        for name in ["b.PNG", "a.jpg", "c.JpEg", "notes.txt", "d.gif", "noext"] {
            std::fs::write(dir.path().join(name), b"x").unwrap();
        }
        std::fs::create_dir(dir.path().join("sub.png")).unwrap();
        let names: Vec<_> = list_images(dir.path())
            .unwrap()
            .iter()
            .map(|p| p.file_name().unwrap().to_string_lossy().into_owned())
            .collect();
        assert_eq!(names, ["a.jpg", "b.PNG", "c.JpEg"]);
    }

    #[test]
    fn list_images_errors_name_the_dir() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(dir.path().join("readme.md"), b"x").unwrap();
        match list_images(dir.path()) {
            Err(Error::Empty(msg)) => assert!(msg.contains(&dir.path().display().to_string())),
            other => panic!("expected Empty, got {other:?}"),
        }
        let missing = dir.path().join("missing");
        match list_images(&missing) {
            Err(Error::Io { path, .. }) => assert_eq!(path, missing),
            other => panic!("expected Io, got {other:?}"),
        }
    }

    #[test]
    fn load_image_file_names_the_path() {
        let dir = tempfile::tempdir().unwrap();
        let missing = dir.path().join("nope.png");
        match load_image_file(&missing) {
            Err(Error::Io { path, .. }) => assert_eq!(path, missing),
            other => panic!("expected Io, got {other:?}"),
        }
        let bad = dir.path().join("bad.jpg");
        std::fs::write(&bad, b"junk").unwrap();
        let (name, _) = reason(load_image_file(&bad).unwrap_err());
        assert_eq!(name, bad.display().to_string());
        let good = dir.path().join("good.png");
        std::fs::write(&good, encode(&sample_rgb(8, 9), ImageFormat::Png)).unwrap();
        assert_eq!(load_image_file(&good).unwrap().width(), 8);
    }
}
