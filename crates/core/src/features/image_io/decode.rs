//! Decoding JPEG/PNG bytes into pixels: format sniffing by content, the pixel limit checked
//! from the header before any pixel is decoded, and JPEG through `zune-jpeg` in strict mode,
//! giving only the pixels the caller reads ([`super::Pixels`]: the Y plane alone for gray
//! descriptors), turned upright by the image's Exif orientation (as a viewer or a browser shows
//! it; a phone or a camera mounted on its side tags its frames rather than rotating them).
//! Apart from conversion and resizing because it is the only part that reads untrusted bytes:
//! every error here names the image.

use std::io::Cursor;

use image::metadata::Orientation;
use image::{DynamicImage, GrayImage, ImageDecoder, ImageFormat, ImageReader, RgbImage};

use super::{to_gray, Pixels};
use crate::{Error, Result};

/// Decodes one JPEG/PNG image given as bytes; `name` (file or multipart part name) appears in
/// errors. Images with more than `max_pixels` pixels are rejected before being decoded. The
/// image comes upright: an Exif orientation tag (JPEG `APP1`, PNG `eXIf`) other than 1 is
/// applied (rotation and/or mirroring, so a tag of 5-8 swaps width and height); a missing or
/// unreadable tag means "as stored".
/// The colour decode ([`Pixels::Colour`]); see [`decode_image_as`].
pub fn decode_image(name: &str, bytes: &[u8], max_pixels: u64) -> Result<DynamicImage> {
    decode_image_as(name, bytes, max_pixels, Pixels::Colour)
}

/// [`decode_image`] of only the pixels the caller reads ([`Pixels`]); with [`Pixels::Gray`]
/// the result is always an `ImageLuma8`.
pub fn decode_image_as(
    name: &str,
    bytes: &[u8],
    max_pixels: u64,
    pixels: Pixels,
) -> Result<DynamicImage> {
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
    let (mut image, orientation) = if format == ImageFormat::Jpeg {
        decode_jpeg(bytes, max_pixels, pixels).map_err(fail)?
    } else {
        let header = |e: image::ImageError| fail(format!("cannot read the {format:?} header: {e}"));
        // The header is read without `image`'s memory limits, whose estimate of a row buffer
        // would refuse a huge width as "Memory limit exceeded" before the pixel limit could
        // name its size; once the size passes, the default limits guard the decode.
        let mut reader = ImageReader::with_format(Cursor::new(bytes), format);
        reader.no_limits();
        let mut decoder = reader.into_decoder().map_err(header)?;
        let (w, h) = decoder.dimensions();
        check_pixel_limit(w, h, max_pixels).map_err(fail)?;
        decoder
            .set_limits(image::Limits::default())
            .map_err(header)?;
        // An unreadable orientation tag is no reason to refuse the pixels.
        let orientation = decoder.orientation().unwrap_or(Orientation::NoTransforms);
        let image = DynamicImage::from_decoder(decoder)
            .map_err(|e| fail(format!("cannot decode the {w}x{h} {format:?} image: {e}")))?;
        (image, orientation)
    };
    image.apply_orientation(orientation);
    Ok(match pixels {
        Pixels::Colour => image,
        Pixels::Gray => gray_image(image),
    })
}

/// The `(width, height)` of the image `reader` holds as [`decode_image`] gives it (upright:
/// swapped when its Exif orientation turns it a quarter), from the header alone.
///
/// Read without `image`'s memory limits (nothing is allocated for pixels here): a header with
/// a huge width gives its size, for the caller's pixel limit to refuse by name, instead of a
/// "Memory limit exceeded" from the decoder's row-buffer estimate.
pub fn upright_dimensions<R: std::io::BufRead + std::io::Seek>(
    mut reader: ImageReader<R>,
) -> image::ImageResult<(u32, u32)> {
    reader.no_limits();
    let mut decoder = reader.into_decoder()?;
    let (w, h) = decoder.dimensions();
    let orientation = decoder.orientation().unwrap_or(Orientation::NoTransforms);
    Ok(if quarter_turn(orientation) {
        (h, w)
    } else {
        (w, h)
    })
}

/// Whether `orientation` swaps width and height.
fn quarter_turn(orientation: Orientation) -> bool {
    matches!(
        orientation,
        Orientation::Rotate90
            | Orientation::Rotate270
            | Orientation::Rotate90FlipH
            | Orientation::Rotate270FlipH
    )
}

/// [`decode_image_as`]`(bytes, pixels)` from the [`Pixels::Colour`] decode of the same bytes,
/// without decoding them again, where that gives the same image: for PNG (its gray is the
/// colour image converted) and for [`Pixels::Colour`]. `None` for a JPEG read as gray, whose
/// Y plane is decoded directly and differs from converting its colour decode.
pub fn from_colour_decode(
    bytes: &[u8],
    colour: &DynamicImage,
    pixels: Pixels,
) -> Option<DynamicImage> {
    match (pixels, image::guess_format(bytes)) {
        (Pixels::Colour, _) => Some(colour.clone()),
        (Pixels::Gray, Ok(ImageFormat::Png)) => {
            Some(DynamicImage::ImageLuma8(to_gray(colour).into_owned()))
        }
        (Pixels::Gray, _) => None,
    }
}

/// The decoded gray image of JPEG/PNG bytes ([`Pixels::Gray`]): the input of co-occurrence
/// extraction.
pub fn decode_gray(name: &str, bytes: &[u8], max_pixels: u64) -> Result<GrayImage> {
    match decode_image_as(name, bytes, max_pixels, Pixels::Gray)? {
        DynamicImage::ImageLuma8(gray) => Ok(gray),
        // Not reached: `Pixels::Gray` always gives `ImageLuma8`.
        other => Ok(to_gray(&other).into_owned()),
    }
}

/// `image` as an `ImageLuma8` ([`to_gray`]), without a copy when it already is one.
fn gray_image(image: DynamicImage) -> DynamicImage {
    match image {
        gray @ DynamicImage::ImageLuma8(_) => gray,
        other => DynamicImage::ImageLuma8(to_gray(&other).into_owned()),
    }
}

fn check_pixel_limit(w: u32, h: u32, max_pixels: u64) -> std::result::Result<(), String> {
    let pixels = u64::from(w) * u64::from(h);
    if pixels > max_pixels {
        return Err(format!(
            "{w}x{h} px = {pixels} pixels exceeds the limit of {max_pixels} pixels"
        ));
    }
    Ok(())
}

/// JPEG with `zune-jpeg` directly (the decoder `image` wraps), in *strict* mode: `image` runs
/// it lenient, which decodes a truncated or corrupt entropy stream into an image padded with
/// grey and no error; a localization service must reject such a frame instead. Going direct
/// also decodes without `image`'s copy of the input. Gray JPEGs give `Luma8`; YCbCr JPEGs give
/// their Y plane alone when only gray is wanted ([`Pixels::Gray`]); every other case `Rgb8`
/// (as `image` does, alpha aside). Also returns the Exif orientation (`NoTransforms` without a
/// readable tag), not yet applied.
fn decode_jpeg(
    bytes: &[u8],
    max_pixels: u64,
    pixels: Pixels,
) -> std::result::Result<(DynamicImage, Orientation), String> {
    use zune_jpeg::zune_core::bytestream::ZCursor;
    use zune_jpeg::zune_core::colorspace::ColorSpace;
    use zune_jpeg::zune_core::options::DecoderOptions;

    let options = DecoderOptions::default()
        .set_strict_mode(true)
        .set_max_width(usize::from(u16::MAX))
        .set_max_height(usize::from(u16::MAX));
    let mut decoder = zune_jpeg::JpegDecoder::new_with_options(ZCursor::new(bytes), options);
    decoder
        .decode_headers()
        .map_err(|e| format!("cannot read the Jpeg header: {e}"))?;
    let (w, h) = decoder
        .dimensions()
        .ok_or_else(|| "cannot read the Jpeg header: no frame size".to_string())?;
    // JPEG sizes are 16-bit, so these conversions cannot fail.
    let (w, h) = (
        u32::try_from(w).unwrap_or(u32::MAX),
        u32::try_from(h).unwrap_or(u32::MAX),
    );
    check_pixel_limit(w, h, max_pixels)?;
    let orientation = decoder
        .exif()
        .and_then(|exif| Orientation::from_exif_chunk(exif))
        .unwrap_or(Orientation::NoTransforms);
    // zune-jpeg turns YCbCr into Luma by keeping Y and skipping the chroma components' IDCT
    // and upsampling; it has no other "to Luma" conversion, so RGB, CMYK and YCCK JPEGs are
    // decoded to RGB and made gray by the caller.
    let out = match decoder.input_colorspace() {
        Some(ColorSpace::Luma | ColorSpace::LumaA) => JpegOut::Luma,
        Some(ColorSpace::YCbCr) if pixels == Pixels::Gray => {
            // zune-jpeg 0.5.15's Luma output decodes twice the MCU rows (the second half past
            // the end of the data) when chroma is subsampled vertically only (4:4:0): 1.5x the
            // time of a colour decode on such a camera JPEG (BENCHMARKS.md). There the Y plane
            // comes from the YCbCr output instead (no colour conversion; the same Y, a test
            // checks both against each other and against libjpeg-turbo).
            match decoder.info().map(|i| i.sample_ratio) {
                Some(zune_jpeg::SampleRatios::V) => JpegOut::YOfYCbCr,
                _ => JpegOut::Luma,
            }
        }
        _ => JpegOut::Rgb,
    };
    let colorspace = match out {
        JpegOut::Luma => ColorSpace::Luma,
        JpegOut::YOfYCbCr => ColorSpace::YCbCr,
        JpegOut::Rgb => ColorSpace::RGB,
    };
    // A fresh decoder with the output colour space set before its headers are read (as
    // `image` does); the headers are a few hundred bytes.
    let mut decoder = zune_jpeg::JpegDecoder::new_with_options(
        ZCursor::new(bytes),
        options.jpeg_set_out_colorspace(colorspace),
    );
    let failed = |e: &dyn std::fmt::Display| format!("cannot decode the {w}x{h} Jpeg image: {e}");
    let decoded = decoder.decode().map_err(|e| failed(&e))?;
    let image = match out {
        JpegOut::Luma => GrayImage::from_raw(w, h, decoded).map(DynamicImage::ImageLuma8),
        JpegOut::YOfYCbCr => {
            let y = decoded.chunks_exact(3).map(|p| p[0]).collect();
            GrayImage::from_raw(w, h, y).map(DynamicImage::ImageLuma8)
        }
        JpegOut::Rgb => RgbImage::from_raw(w, h, decoded).map(DynamicImage::ImageRgb8),
    };
    image
        .map(|image| (image, orientation))
        .ok_or_else(|| failed(&"the decoder returned a buffer of the wrong size"))
}

/// What [`decode_jpeg`] asks zune-jpeg for.
#[derive(Clone, Copy, PartialEq, Eq)]
enum JpegOut {
    /// The Y plane alone (gray JPEGs; YCbCr JPEGs when only gray is wanted).
    Luma,
    /// Y taken from the YCbCr output (4:4:0 JPEGs when only gray is wanted).
    YOfYCbCr,
    /// Colour.
    Rgb,
}

#[cfg(test)]
mod tests {
    use super::super::tests::{encode, noisy_rgb, reason, sample_rgb};
    use super::super::{load_image_file, load_image_file_as};
    use super::*;

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
    fn truncated_or_corrupt_jpeg_is_an_image_error() {
        let bytes = encode(&noisy_rgb(64, 48, 5), ImageFormat::Jpeg);
        // Cut in the entropy-coded data: `image`'s lenient decoding would pad it with grey.
        let (name, why) =
            reason(decode_image("cut.jpg", &bytes[..bytes.len() * 2 / 3], 10_000).unwrap_err());
        assert_eq!(name, "cut.jpg");
        assert!(why.contains("cannot decode the 64x48 Jpeg"), "{why}");
        // A marker in the middle of the entropy-coded data.
        let mut corrupt = bytes.clone();
        let at = corrupt.len() / 2;
        corrupt[at..at + 2].copy_from_slice(&[0xff, 0xc0]);
        let (_, why) = reason(decode_image("bad.jpg", &corrupt, 10_000).unwrap_err());
        assert!(why.contains("cannot decode the 64x48 Jpeg"), "{why}");
        // Only the start of the headers.
        let (_, why) = reason(decode_image("hdr.jpg", &bytes[..20], 10_000).unwrap_err());
        assert!(why.contains("cannot read the Jpeg header"), "{why}");
        // The pixel limit comes from the header, before decoding.
        let (_, why) = reason(decode_image("big.jpg", &bytes, 3071).unwrap_err());
        assert!(why.contains("64x48 px = 3072 pixels exceeds"), "{why}");
    }

    #[test]
    fn jpeg_decoding_matches_image_and_keeps_gray_jpegs_gray() {
        let rgb = noisy_rgb(61, 37, 9);
        let bytes = encode(&rgb, ImageFormat::Jpeg);
        let ours = decode_image("c.jpg", &bytes, 10_000).unwrap();
        let theirs = image::load_from_memory_with_format(&bytes, ImageFormat::Jpeg).unwrap();
        assert_eq!(ours.as_rgb8().unwrap(), theirs.as_rgb8().unwrap());
        let gray = DynamicImage::ImageRgb8(rgb).to_luma8();
        let mut out = Cursor::new(Vec::new());
        gray.write_to(&mut out, ImageFormat::Jpeg).unwrap();
        let ours = decode_image("g.jpg", out.get_ref(), 10_000).unwrap();
        let theirs = image::load_from_memory_with_format(out.get_ref(), ImageFormat::Jpeg).unwrap();
        assert_eq!(ours.as_luma8().unwrap(), theirs.as_luma8().unwrap());
    }

    /// Camera JPEGs of every common chroma sampling, odd sizes (partial MCUs), made by
    /// `testdata/make_jpegs.py` with OpenCV, beside the Y plane libjpeg-turbo decodes.
    fn sampled_jpegs() -> [(&'static str, &'static [u8], &'static [u8]); 4] {
        [
            (
                "4:2:0",
                include_bytes!("../testdata/sampling_420.jpg"),
                include_bytes!("../testdata/sampling_420_y.pgm"),
            ),
            (
                "4:2:2",
                include_bytes!("../testdata/sampling_422.jpg"),
                include_bytes!("../testdata/sampling_422_y.pgm"),
            ),
            (
                "4:4:0",
                include_bytes!("../testdata/sampling_440.jpg"),
                include_bytes!("../testdata/sampling_440_y.pgm"),
            ),
            (
                "4:4:4",
                include_bytes!("../testdata/sampling_444.jpg"),
                include_bytes!("../testdata/sampling_444_y.pgm"),
            ),
        ]
    }

    /// Pixels of a binary PGM with a `P5\nW H\n255\n` header.
    fn pgm_pixels(pgm: &[u8]) -> &[u8] {
        let mut newlines = 0;
        let start = pgm
            .iter()
            .position(|&b| {
                newlines += usize::from(b == b'\n');
                newlines == 3
            })
            .unwrap();
        &pgm[start + 1..]
    }

    /// The Y plane of a YCbCr JPEG's full decode (chroma included), from zune-jpeg.
    fn y_of_full_decode(bytes: &[u8]) -> Vec<u8> {
        use zune_jpeg::zune_core::{
            bytestream::ZCursor, colorspace::ColorSpace, options::DecoderOptions,
        };
        let options = DecoderOptions::default().jpeg_set_out_colorspace(ColorSpace::YCbCr);
        let ycbcr = zune_jpeg::JpegDecoder::new_with_options(ZCursor::new(bytes), options)
            .decode()
            .unwrap();
        ycbcr.chunks_exact(3).map(|p| p[0]).collect()
    }

    #[test]
    fn a_pngs_gray_from_its_colour_decode_is_its_gray_decode() {
        let (w, h) = (37, 23);
        let px = |x: u32, y: u32, k: u32| ((x * 7 + y * 13 + k * 61) % 256) as u8;
        let pngs: Vec<DynamicImage> = vec![
            DynamicImage::ImageRgb8(image::RgbImage::from_fn(w, h, |x, y| {
                image::Rgb([px(x, y, 0), px(x, y, 1), px(x, y, 2)])
            })),
            DynamicImage::ImageRgba8(image::RgbaImage::from_fn(w, h, |x, y| {
                image::Rgba([px(x, y, 0), px(x, y, 1), px(x, y, 2), px(x, y, 3)])
            })),
            DynamicImage::ImageLuma8(image::GrayImage::from_fn(w, h, |x, y| {
                image::Luma([px(x, y, 0)])
            })),
            DynamicImage::ImageLumaA8(image::GrayAlphaImage::from_fn(w, h, |x, y| {
                image::LumaA([px(x, y, 0), px(x, y, 1)])
            })),
            DynamicImage::ImageRgb16(image::ImageBuffer::from_fn(w, h, |x, y| {
                image::Rgb([
                    257 * u16::from(px(x, y, 0)),
                    3 * u16::from(px(x, y, 1)),
                    65535,
                ])
            })),
        ];
        for img in pngs {
            let mut bytes = Vec::new();
            img.write_to(&mut Cursor::new(&mut bytes), ImageFormat::Png)
                .unwrap();
            let colour = decode_image("x.png", &bytes, 10_000).unwrap();
            for pixels in [Pixels::Gray, Pixels::Colour] {
                let direct = decode_image_as("x.png", &bytes, 10_000, pixels).unwrap();
                let reused = from_colour_decode(&bytes, &colour, pixels).unwrap();
                assert_eq!(reused, direct, "{:?} {pixels:?}", img.color());
            }
        }
        // A colour JPEG read as gray is decoded again (its Y plane).
        let (_, jpeg, _) = sampled_jpegs()[0];
        let colour = decode_image("y.jpg", jpeg, 10_000).unwrap();
        assert_eq!(from_colour_decode(jpeg, &colour, Pixels::Gray), None);
        assert_eq!(
            from_colour_decode(jpeg, &colour, Pixels::Colour),
            Some(colour)
        );
    }

    #[test]
    fn gray_decoding_of_ycbcr_jpegs_is_their_y_plane() {
        for (sampling, jpeg, pgm) in sampled_jpegs() {
            let gray = decode_image_as("y.jpg", jpeg, 10_000, Pixels::Gray).unwrap();
            let DynamicImage::ImageLuma8(gray) = gray else {
                panic!("{sampling}: Pixels::Gray must give Luma8");
            };
            assert_eq!(gray.dimensions(), (45, 29), "{sampling}");
            // The Y plane the decoder computes when it decodes the chroma too, exactly.
            assert_eq!(gray.as_raw(), &y_of_full_decode(jpeg), "{sampling}");
            // libjpeg-turbo's Y (another IDCT): within one level everywhere.
            let anchor = pgm_pixels(pgm);
            assert_eq!(anchor.len(), gray.as_raw().len(), "{sampling}");
            let worst = gray
                .as_raw()
                .iter()
                .zip(anchor)
                .map(|(a, b)| a.abs_diff(*b))
                .max()
                .unwrap();
            assert!(worst <= 1, "{sampling}: {worst} levels from libjpeg-turbo");
            // It is not the Rec. 709 luma of the colour decode (a different, cheaper path),
            // and colour decoding is unchanged.
            let colour = decode_image("c.jpg", jpeg, 10_000).unwrap();
            assert!(colour.as_rgb8().is_some(), "{sampling}");
            assert_ne!(*to_gray(&colour), gray, "{sampling}");
            assert_eq!(decode_gray("g.jpg", jpeg, 10_000).unwrap(), gray);
        }
    }

    #[test]
    fn gray_decoding_stays_strict_and_limited() {
        for (sampling, jpeg, _) in sampled_jpegs() {
            // Cut in the entropy-coded data: the skipped chroma blocks still have to parse.
            let cut = &jpeg[..jpeg.len() * 3 / 4];
            let (name, why) = reason(decode_gray("cut.jpg", cut, 10_000).unwrap_err());
            assert_eq!(name, "cut.jpg", "{sampling}");
            assert!(
                why.contains("cannot decode the 45x29 Jpeg"),
                "{sampling}: {why}"
            );
            let (_, why) = reason(decode_gray("big.jpg", jpeg, 45 * 29 - 1).unwrap_err());
            assert!(why.contains("exceeds the limit"), "{sampling}: {why}");
        }
    }

    #[test]
    fn gray_decoding_of_other_images_is_to_gray_of_their_colour() {
        let rgb = noisy_rgb(61, 37, 4);
        let png = encode(&rgb, ImageFormat::Png);
        let gray = decode_gray("a.png", &png, 10_000).unwrap();
        assert_eq!(gray, DynamicImage::ImageRgb8(rgb.clone()).to_luma8());
        let luma = DynamicImage::ImageRgb8(rgb).to_luma8();
        let mut gray_jpeg = Cursor::new(Vec::new());
        luma.write_to(&mut gray_jpeg, ImageFormat::Jpeg).unwrap();
        let colour = decode_image("g.jpg", gray_jpeg.get_ref(), 10_000).unwrap();
        assert_eq!(
            decode_gray("g.jpg", gray_jpeg.get_ref(), 10_000).unwrap(),
            *colour.as_luma8().unwrap()
        );
        // Colour is the default everywhere it is not asked for.
        assert_eq!(Pixels::default(), Pixels::Colour);
        let file = tempfile::NamedTempFile::new().unwrap();
        std::fs::write(file.path(), &png).unwrap();
        assert!(load_image_file(file.path()).unwrap().as_rgb8().is_some());
        assert_eq!(
            *load_image_file_as(file.path(), Pixels::Gray)
                .unwrap()
                .as_luma8()
                .unwrap(),
            gray
        );
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

    /// `png` with its IHDR's width and height replaced (and the chunk's CRC recomputed).
    fn png_claiming(png: &[u8], width: u32, height: u32) -> Vec<u8> {
        let mut out = png.to_vec();
        // Signature (8), IHDR length (4), "IHDR" (4), width (4), height (4), 5 more bytes.
        out[16..20].copy_from_slice(&width.to_be_bytes());
        out[20..24].copy_from_slice(&height.to_be_bytes());
        let mut crc = 0xFFFF_FFFFu32;
        for &b in &out[12..29] {
            crc ^= u32::from(b);
            for _ in 0..8 {
                crc = if crc & 1 == 1 {
                    (crc >> 1) ^ 0xEDB8_8320
                } else {
                    crc >> 1
                };
            }
        }
        out[29..33].copy_from_slice(&(!crc).to_be_bytes());
        out
    }

    #[test]
    fn a_huge_png_header_is_refused_by_the_pixel_limit_by_size() {
        let bytes = encode(&sample_rgb(4, 2), ImageFormat::Png);
        for (w, h) in [(i32::MAX as u32, 1), (500_000_000, 1), (1, i32::MAX as u32)] {
            let huge = png_claiming(&bytes, w, h);
            let reader = ImageReader::new(Cursor::new(&huge[..]))
                .with_guessed_format()
                .unwrap();
            assert_eq!(upright_dimensions(reader).unwrap(), (w, h));
            let (_, why) = reason(decode_image("huge.png", &huge, 1 << 24).unwrap_err());
            assert!(why.contains(&format!("{w}x{h} px")), "{why}");
            assert!(why.contains("exceeds the limit"), "{why}");
        }
        // The patch itself keeps a valid PNG: the original size still decodes.
        assert!(decode_image("same.png", &png_claiming(&bytes, 4, 2), 8).is_ok());
    }

    /// A minimal little-endian Exif (TIFF) block whose first IFD holds one Orientation entry.
    fn exif_orientation(value: u16) -> Vec<u8> {
        let mut tiff = b"II*\0\x08\0\0\0".to_vec();
        tiff.extend_from_slice(&1u16.to_le_bytes()); // one entry
        tiff.extend_from_slice(&0x0112u16.to_le_bytes()); // Orientation
        tiff.extend_from_slice(&3u16.to_le_bytes()); // SHORT
        tiff.extend_from_slice(&1u32.to_le_bytes()); // count
        tiff.extend_from_slice(&value.to_le_bytes());
        tiff.extend_from_slice(&[0, 0]);
        tiff.extend_from_slice(&0u32.to_le_bytes()); // no next IFD
        tiff
    }

    /// `img` encoded as `format` (JPEG or PNG) with the Exif block `exif` (JPEG `APP1`, PNG
    /// `eXIf`).
    fn encode_tagged(img: &image::RgbImage, format: ImageFormat, exif: &[u8]) -> Vec<u8> {
        use image::codecs::{jpeg::JpegEncoder, png::PngEncoder};
        use image::{ExtendedColorType, ImageEncoder};
        fn write(mut encoder: impl ImageEncoder, img: &image::RgbImage, exif: &[u8]) {
            encoder.set_exif_metadata(exif.to_vec()).unwrap();
            let (w, h) = img.dimensions();
            encoder
                .write_image(img.as_raw(), w, h, ExtendedColorType::Rgb8)
                .unwrap();
        }
        let mut out = Vec::new();
        match format {
            ImageFormat::Jpeg => write(JpegEncoder::new(&mut out), img, exif),
            _ => write(PngEncoder::new(&mut out), img, exif),
        }
        out
    }

    #[test]
    fn an_exif_orientation_turns_the_image_upright() {
        let img = noisy_rgb(40, 24, 5);
        let header = |bytes: &[u8]| {
            upright_dimensions(
                ImageReader::new(Cursor::new(bytes))
                    .with_guessed_format()
                    .unwrap(),
            )
            .unwrap()
        };
        for (name, format) in [("jpeg", ImageFormat::Jpeg), ("png", ImageFormat::Png)] {
            let tag = |exif: &[u8]| encode_tagged(&img, format, exif);
            let plain = encode(&img, format);
            for pixels in [Pixels::Colour, Pixels::Gray] {
                let stored = decode_image_as(name, &plain, 10_000, pixels).unwrap();
                // 1: as stored; 6: a quarter turn clockwise; 3: half a turn; 5: a quarter
                // turn and a mirror image.
                for (value, want) in [
                    (1, stored.clone()),
                    (6, stored.rotate90()),
                    (3, stored.rotate180()),
                    (5, stored.rotate90().fliph()),
                ] {
                    let tagged = tag(&exif_orientation(value));
                    let got = decode_image_as(name, &tagged, 10_000, pixels).unwrap();
                    assert_eq!(got, want, "{name} {pixels:?} orientation {value}");
                    // The header-only size is the decoded one: the map's geometry and the
                    // descriptor-length checks see the upright image.
                    assert_eq!(
                        header(&tagged),
                        (got.width(), got.height()),
                        "{name} {value}"
                    );
                }
                // A tag that cannot be read (no TIFF header, or an orientation of 9) leaves
                // the pixels as stored instead of refusing them.
                for exif in [b"not a tiff block".to_vec(), exif_orientation(9)] {
                    let tagged = tag(&exif);
                    assert_eq!(
                        decode_image_as(name, &tagged, 10_000, pixels).unwrap(),
                        stored
                    );
                    assert_eq!(header(&tagged), (40, 24));
                }
            }
        }
        // The pixel limit still comes from the header, whatever the orientation.
        let tagged = encode_tagged(&img, ImageFormat::Jpeg, &exif_orientation(6));
        let (_, why) = reason(decode_image("big", &tagged, 959).unwrap_err());
        assert!(why.contains("exceeds the limit of 959"), "{why}");
    }
}
