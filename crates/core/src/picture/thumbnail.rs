//! Thumbnails of reference images: what a person needs to recognise a place on a dashboard,
//! stored with each image at upload.
//!
//! An image is scaled down (never up) to fit [`MAX_WIDTH`] x [`MAX_HEIGHT`], keeping its
//! aspect ratio, and encoded as a baseline JPEG of quality [`QUALITY`]; grey images stay grey
//! (one channel, a third of the bytes). Scaling uses a triangle (bilinear) filter, which is
//! fast and, after the encoder's own smoothing, indistinguishable from Lanczos at this size.

use std::io::Cursor;

use image::codecs::jpeg::JpegEncoder;
use image::imageops::FilterType;
use image::{DynamicImage, GenericImageView};

use crate::{Error, Result};

/// Largest thumbnail width in pixels.
pub const MAX_WIDTH: u32 = 160;
/// Largest thumbnail height in pixels (tall images are bounded by this instead).
pub const MAX_HEIGHT: u32 = 160;
/// JPEG quality (1-100).
pub const QUALITY: u8 = 80;

/// The size `(w, h)` of the thumbnail of a `width` x `height` image: scaled down to fit
/// [`MAX_WIDTH`] x [`MAX_HEIGHT`], aspect ratio kept (rounded), at least 1 x 1.
pub fn thumbnail_size(width: u32, height: u32) -> (u32, u32) {
    let (w, h) = (u64::from(width.max(1)), u64::from(height.max(1)));
    let (mw, mh) = (u64::from(MAX_WIDTH), u64::from(MAX_HEIGHT));
    if w <= mw && h <= mh {
        return (w as u32, h as u32);
    }
    // Scale by min(mw / w, mh / h), in integers.
    let (tw, th) = if w * mh >= h * mw {
        (mw, (h * mw + w / 2) / w)
    } else {
        ((w * mh + h / 2) / h, mh)
    };
    (tw.clamp(1, mw) as u32, th.clamp(1, mh) as u32)
}

/// The JPEG thumbnail of `image` (see the module doc).
pub fn thumbnail_jpeg(image: &DynamicImage) -> Result<Vec<u8>> {
    let (w, h) = image.dimensions();
    let (tw, th) = thumbnail_size(w, h);
    let small = if (tw, th) == (w, h) {
        image.clone()
    } else {
        image.resize_exact(tw, th, FilterType::Triangle)
    };
    let small = if small.color().has_color() {
        DynamicImage::ImageRgb8(small.to_rgb8())
    } else {
        DynamicImage::ImageLuma8(small.to_luma8())
    };
    let mut out = Vec::with_capacity(4096);
    JpegEncoder::new_with_quality(&mut Cursor::new(&mut out), QUALITY)
        .encode_image(&small)
        .map_err(|e| Error::Image {
            name: "thumbnail".into(),
            reason: format!("JPEG encoding failed: {e}"),
        })?;
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use image::{GrayImage, ImageFormat, Rgb, RgbImage};

    fn decode(bytes: &[u8]) -> DynamicImage {
        assert_eq!(image::guess_format(bytes).unwrap(), ImageFormat::Jpeg);
        image::load_from_memory(bytes).unwrap()
    }

    #[test]
    fn sizes_fit_the_box_keep_the_aspect_and_never_grow() {
        assert_eq!(
            thumbnail_size(64, 32),
            (64, 32),
            "small images keep their size"
        );
        assert_eq!(thumbnail_size(160, 160), (160, 160));
        assert_eq!(thumbnail_size(960, 540), (160, 90));
        assert_eq!(thumbnail_size(640, 360), (160, 90));
        assert_eq!(thumbnail_size(4000, 3000), (160, 120));
        assert_eq!(
            thumbnail_size(1080, 1920),
            (90, 160),
            "portrait is bounded by height"
        );
        assert_eq!(thumbnail_size(100_000, 1), (160, 1), "never 0 pixels");
        assert_eq!(thumbnail_size(1, 100_000), (1, 160));
        for (w, h) in [(161, 7), (333, 999), (u32::MAX, u32::MAX), (0, 0)] {
            let (tw, th) = thumbnail_size(w, h);
            assert!(
                (1..=MAX_WIDTH).contains(&tw) && (1..=MAX_HEIGHT).contains(&th),
                "{w}x{h}"
            );
        }
    }

    #[test]
    fn a_colour_camera_frame_becomes_a_small_colour_jpeg() {
        let img = RgbImage::from_fn(960, 540, |x, y| {
            Rgb([(x % 256) as u8, (y % 256) as u8, ((x + y) % 256) as u8])
        });
        let bytes = thumbnail_jpeg(&DynamicImage::ImageRgb8(img)).unwrap();
        let back = decode(&bytes);
        assert_eq!(back.dimensions(), (160, 90));
        assert!(back.color().has_color());
        assert!(bytes.len() < 20_000, "{} bytes", bytes.len());
    }

    #[test]
    fn a_grey_frame_stays_grey_and_keeps_its_content() {
        // Left half dark, right half bright: the thumbnail shows the same.
        let img = GrayImage::from_fn(64, 32, |x, _| image::Luma([if x < 32 { 20 } else { 230 }]));
        let bytes = thumbnail_jpeg(&DynamicImage::ImageLuma8(img)).unwrap();
        let back = decode(&bytes).to_luma8();
        assert_eq!(back.dimensions(), (64, 32));
        assert!(back.get_pixel(8, 16)[0] < 60, "{:?}", back.get_pixel(8, 16));
        assert!(
            back.get_pixel(56, 16)[0] > 190,
            "{:?}",
            back.get_pixel(56, 16)
        );
    }
}
