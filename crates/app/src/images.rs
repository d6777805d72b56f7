//! Uploaded images: checking them (format and pixel count from the header, before decoding)
//! and turning them into descriptor rows or grey images, on the current rayon pool.
//!
//! Every image error names its part as the front end named it (the API uses
//! `image[k] ("file name")`, `k` counting the batch's images from 0).

use std::io::Cursor;

use bytes::Bytes;
use image::GrayImage;
use rayon::prelude::*;

use super::error::{AppError, AppResult};
use seasonloc_core::features::{self, Extractor};
use seasonloc_core::Matrix;

/// One uploaded image.
#[derive(Clone, Debug)]
pub struct ImageInput {
    /// How errors name it, e.g. `image[2] ("a.png")`.
    pub name: String,
    /// Encoded bytes (JPEG or PNG).
    pub bytes: Bytes,
}

/// Width and height from the header, without decoding the pixels: the image as it decodes
/// (upright, after its Exif orientation).
pub(crate) fn dimensions(part: &ImageInput) -> AppResult<(u32, u32)> {
    let reader = image::ImageReader::new(Cursor::new(&part.bytes[..]))
        .with_guessed_format()
        .map_err(|e| invalid(part, e.to_string()))?;
    match reader.format() {
        Some(image::ImageFormat::Png | image::ImageFormat::Jpeg) => {}
        Some(other) => {
            return Err(invalid(
                part,
                format!("{other:?} is not supported; send JPEG or PNG"),
            ))
        }
        None => return Err(invalid(part, "not a JPEG or PNG image".into())),
    }
    features::upright_dimensions(reader)
        .map_err(|e| invalid(part, format!("unreadable image header: {e}")))
}

fn invalid(part: &ImageInput, reason: String) -> AppError {
    AppError::InvalidImage {
        part: part.name.clone(),
        reason,
    }
}

/// Decodes the parts and extracts one descriptor row per image, in order. All images must give
/// descriptors of one length, equal to `expected_dim` when given (the map's); violations name
/// the first offending part, and at most `max_len` (checked from the header, before anything
/// is decoded, so a request's memory is bounded in advance). Blocking: run on the CPU pool.
pub fn describe(
    extractor: &dyn Extractor,
    parts: &[ImageInput],
    max_pixels: u64,
    max_len: usize,
    expected_dim: Option<u32>,
) -> AppResult<Matrix> {
    let images = decode_checked(
        extractor,
        parts,
        max_pixels,
        max_len,
        expected_dim,
        extractor.pixels(),
    )?;
    Ok(features::extract_batch(extractor, &images)?)
}

/// [`describe`] for reference images: also the JPEG thumbnail of each image
/// ([`seasonloc_core::picture::thumbnail_jpeg`]), from the same decoded pixels. Blocking.
pub fn describe_with_thumbnails(
    extractor: &dyn Extractor,
    parts: &[ImageInput],
    max_pixels: u64,
    max_len: usize,
    expected_dim: Option<u32>,
) -> AppResult<(Matrix, Vec<Vec<u8>>)> {
    // Thumbnails show colour; the descriptors read what the extractor reads (a camera JPEG's
    // Y plane for HOG), exactly as for queries, so references and queries match.
    let images = decode_checked(
        extractor,
        parts,
        max_pixels,
        max_len,
        expected_dim,
        features::Pixels::Colour,
    )?;
    let descriptors = if extractor.pixels() == features::Pixels::Colour {
        features::extract_batch(extractor, &images)?
    } else {
        // The extractor's own pixels from the colour decode where they are the same image
        // (PNG), decoded again where not (a camera JPEG's Y plane).
        let own = parts
            .par_iter()
            .zip(&images)
            .map(|(p, colour)| {
                match features::from_colour_decode(&p.bytes, colour, extractor.pixels()) {
                    Some(image) => Ok(image),
                    None => {
                        features::decode_image_as(&p.name, &p.bytes, max_pixels, extractor.pixels())
                            .map_err(AppError::from)
                    }
                }
            })
            .collect::<AppResult<Vec<_>>>()?;
        features::extract_batch(extractor, &own)?
    };
    let thumbnails = images
        .par_iter()
        .map(|img| seasonloc_core::picture::thumbnail_jpeg(img).map_err(AppError::from))
        .collect::<AppResult<Vec<_>>>()?;
    Ok((descriptors, thumbnails))
}

/// Checks every part's header (format, pixel count, descriptor length) before decoding any,
/// then decodes them all.
fn decode_checked(
    extractor: &dyn Extractor,
    parts: &[ImageInput],
    max_pixels: u64,
    max_len: usize,
    expected_dim: Option<u32>,
    pixels: features::Pixels,
) -> AppResult<Vec<image::DynamicImage>> {
    let dims = parts
        .par_iter()
        .map(|p| {
            let (w, h) = dimensions(p)?;
            let pixels = u64::from(w) * u64::from(h);
            if pixels > max_pixels {
                return Err(AppError::ImageTooLarge {
                    part: p.name.clone(),
                    width: w,
                    height: h,
                    pixels,
                    limit: max_pixels,
                });
            }
            let dim = extractor
                .dim_for(w, h)
                .map_err(|e| invalid(p, e.to_string()))?;
            Ok((w, h, dim))
        })
        .collect::<Vec<_>>();
    let mut first: Option<(u32, u32, usize)> = None;
    for (p, d) in parts.iter().zip(dims) {
        let (w, h, dim) = d?;
        if dim > max_len {
            return Err(AppError::DescriptorLength(format!(
                "{} is {w}x{h} and would give descriptors of length {dim}, more than the \
                 server's limit of {max_len} (send smaller images, or use a larger cell size \
                 or a `resize`)",
                p.name
            )));
        }
        if let Some(expected) = expected_dim {
            if dim != expected as usize {
                return Err(AppError::DescriptorLength(format!(
                    "{} is {w}x{h} and gives descriptors of length {dim}; this map's descriptors \
                     have length {expected} (send images of the map's size)",
                    p.name
                )));
            }
        }
        match first {
            None => first = Some((w, h, dim)),
            Some((w0, h0, d0)) if d0 != dim => {
                return Err(AppError::DescriptorLength(format!(
                    "{} is {w}x{h} (descriptor length {dim}) but image[0] is {w0}x{h0} \
                     (length {d0}); a batch must give descriptors of one length",
                    p.name
                )))
            }
            Some(_) => {}
        }
    }
    decode_all(parts, max_pixels, pixels)
}

/// Decodes every part as `pixels`, in order (headers already checked). Blocking.
fn decode_all(
    parts: &[ImageInput],
    max_pixels: u64,
    pixels: features::Pixels,
) -> AppResult<Vec<image::DynamicImage>> {
    parts
        .par_iter()
        .map(|p| {
            features::decode_image_as(&p.name, &p.bytes, max_pixels, pixels).map_err(AppError::from)
        })
        .collect()
}

/// Decodes the parts to grey images, in order (the co-occurrence method's input). Blocking.
pub fn decode_gray(parts: &[ImageInput], max_pixels: u64) -> AppResult<Vec<GrayImage>> {
    parts
        .par_iter()
        .map(|p| Ok(features::decode_gray(&p.name, &p.bytes, max_pixels)?))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn corrupt_images_are_named_before_decoding() {
        struct Never;
        impl Extractor for Never {
            fn dim_for(&self, _: u32, _: u32) -> seasonloc_core::Result<usize> {
                Ok(1)
            }
            fn extract(&self, _: &image::DynamicImage) -> seasonloc_core::Result<Vec<f32>> {
                unreachable!("the batch is rejected before extraction")
            }
        }
        let parts = vec![ImageInput {
            name: "image[0] (\"x.png\")".into(),
            bytes: Bytes::from_static(b"not an image"),
        }];
        let e = describe(&Never, &parts, 100, 10, None).unwrap_err();
        assert!(
            matches!(&e, AppError::InvalidImage { part, .. } if part.contains("x.png")),
            "{e}"
        );
        let mut png = Vec::new();
        image::DynamicImage::new_luma8(20, 10)
            .write_to(&mut Cursor::new(&mut png), image::ImageFormat::Png)
            .unwrap();
        let parts = vec![ImageInput {
            name: "image[0]".into(),
            bytes: Bytes::from(png),
        }];
        let e = describe(&Never, &parts, 100, 10, None).unwrap_err();
        assert!(
            matches!(e, AppError::ImageTooLarge { pixels: 200, .. }),
            "{e}"
        );
        // 20x10 gives 200 values here: over a cap of 199, before any decoding.
        struct PerPixel;
        impl Extractor for PerPixel {
            fn dim_for(&self, w: u32, h: u32) -> seasonloc_core::Result<usize> {
                Ok((w * h) as usize)
            }
            fn extract(&self, _: &image::DynamicImage) -> seasonloc_core::Result<Vec<f32>> {
                unreachable!("the batch is rejected before extraction")
            }
        }
        let e = describe(&PerPixel, &parts, 1000, 199, None).unwrap_err();
        assert!(
            matches!(&e, AppError::DescriptorLength(m) if m.contains("200") && m.contains("199")),
            "{e}"
        );
    }
}
