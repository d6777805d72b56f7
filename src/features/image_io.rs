//! Image input: decoding JPEG/PNG bytes with a pixel limit, loading files, listing a folder.
//!
//! The pixel limit is checked from the image header *before* any pixel is decoded, so a small
//! upload that claims a huge size (a decompression bomb) costs nothing. Formats are detected by
//! content, never by file name. Every error names the image (file path or multipart part name).

use std::io::Cursor;
use std::path::{Path, PathBuf};

use image::{DynamicImage, ImageFormat, ImageReader};

use crate::{Error, Result};

/// Pixel limit used by [`load_image_file`]: 100 megapixels.
pub const DEFAULT_MAX_PIXELS: u64 = 100_000_000;

/// File extensions [`list_images`] accepts (compared case-insensitively).
pub const IMAGE_EXTENSIONS: [&str; 3] = ["png", "jpg", "jpeg"];

/// Decodes one JPEG/PNG image given as bytes; `name` (file or multipart part name) appears in
/// errors. Images with more than `max_pixels` pixels are rejected before being decoded.
pub fn decode_image(name: &str, bytes: &[u8], max_pixels: u64) -> Result<DynamicImage> {
    let fail = |reason: String| Error::Image {
        name: name.to_string(),
        reason,
    };
    if bytes.is_empty() {
        return Err(fail("is empty (0 bytes)".into()));
    }
    let format = match image::guess_format(bytes) {
        Ok(f @ (ImageFormat::Png | ImageFormat::Jpeg)) => f,
        Ok(other) => {
            return Err(fail(format!(
                "unsupported format {other:?}: only PNG and JPEG are accepted"
            )))
        }
        Err(_) => {
            return Err(fail(format!(
                "not a PNG or JPEG image ({} bytes of unrecognised content)",
                bytes.len()
            )))
        }
    };
    let (w, h) = ImageReader::with_format(Cursor::new(bytes), format)
        .into_dimensions()
        .map_err(|e| fail(format!("cannot read the {format:?} header: {e}")))?;
    let pixels = u64::from(w) * u64::from(h);
    if pixels > max_pixels {
        return Err(fail(format!(
            "{w}x{h} px = {pixels} pixels exceeds the limit of {max_pixels} pixels"
        )));
    }
    ImageReader::with_format(Cursor::new(bytes), format)
        .decode()
        .map_err(|e| fail(format!("cannot decode the {w}x{h} {format:?} image: {e}")))
}

/// Reads and decodes one JPEG/PNG file (at most [`DEFAULT_MAX_PIXELS`] pixels); errors name
/// the path.
pub fn load_image_file(path: &Path) -> Result<DynamicImage> {
    let bytes = std::fs::read(path).map_err(|source| Error::Io {
        path: path.to_path_buf(),
        source,
    })?;
    decode_image(&path.display().to_string(), &bytes, DEFAULT_MAX_PIXELS)
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
    use image::{ImageBuffer, Rgb, RgbImage};

    fn sample_rgb(w: u32, h: u32) -> RgbImage {
        ImageBuffer::from_fn(w, h, |x, y| Rgb([(x * 7) as u8, (y * 11) as u8, 90]))
    }

    fn encode(img: &RgbImage, format: ImageFormat) -> Vec<u8> {
        let mut out = Cursor::new(Vec::new());
        img.write_to(&mut out, format).unwrap();
        out.into_inner()
    }

    fn reason(err: Error) -> (String, String) {
        match err {
            Error::Image { name, reason } => (name, reason),
            other => panic!("expected Error::Image, got {other:?}"),
        }
    }

    #[test]
    fn png_round_trips_exactly() {
        let img = sample_rgb(20, 10);
        let decoded = decode_image("a.png", &encode(&img, ImageFormat::Png), 1000).unwrap();
        assert_eq!(decoded.to_rgb8(), img);
    }

    #[test]
    fn jpeg_round_trips_with_its_size() {
        let img = sample_rgb(24, 16);
        let decoded = decode_image("b", &encode(&img, ImageFormat::Jpeg), 1000).unwrap();
        assert_eq!((decoded.width(), decoded.height()), (24, 16));
        // Lossy, but close to the smooth original.
        let diff: u64 = decoded
            .to_rgb8()
            .as_raw()
            .iter()
            .zip(img.as_raw())
            .map(|(&a, &b)| u64::from(a.abs_diff(b)))
            .sum();
        assert!(diff / (24 * 16 * 3) < 12, "mean abs diff too large: {diff}");
    }

    #[test]
    fn garbage_and_empty_bytes_name_the_part() {
        let (name, why) =
            reason(decode_image("part-3", b"definitely not an image", 1000).unwrap_err());
        assert_eq!(name, "part-3");
        assert!(why.contains("not a PNG or JPEG"), "{why}");
        let (_, why) = reason(decode_image("e", b"", 1000).unwrap_err());
        assert!(why.contains("empty"), "{why}");
    }

    #[test]
    fn unsupported_format_is_rejected_by_content() {
        let (_, why) = reason(decode_image("x.png", b"GIF89a\x01\x00\x01\x00", 1000).unwrap_err());
        assert!(why.contains("unsupported format Gif"), "{why}");
    }

    #[test]
    fn truncated_png_is_an_image_error() {
        let bytes = encode(&sample_rgb(40, 40), ImageFormat::Png);
        let (name, why) =
            reason(decode_image("cut.png", &bytes[..bytes.len() / 2], 10_000).unwrap_err());
        assert_eq!(name, "cut.png");
        assert!(why.contains("cannot decode the 40x40 Png"), "{why}");
    }

    #[test]
    fn pixel_limit_is_checked_from_the_header_before_decoding() {
        let bytes = encode(&sample_rgb(100, 50), ImageFormat::Png);
        let (_, why) = reason(decode_image("big.png", &bytes, 4999).unwrap_err());
        assert!(
            why.contains("100x50 px = 5000 pixels exceeds the limit of 4999"),
            "{why}"
        );
        assert!(decode_image("ok.png", &bytes, 5000).is_ok());
        // Cut a few bytes into the pixel data (IDAT): it could never be decoded, yet the limit
        // error comes first.
        let idat = bytes.windows(4).position(|w| w == b"IDAT").unwrap();
        let head = &bytes[..idat + 10];
        let (_, why) = reason(decode_image("hdr.png", head, 4999).unwrap_err());
        assert!(why.contains("exceeds the limit"), "{why}");
        let (_, why) = reason(decode_image("hdr.png", head, 5000).unwrap_err());
        assert!(why.contains("cannot decode"), "{why}");
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
