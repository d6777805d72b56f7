//! Uploaded images: checking them (format and pixel count from the header, before decoding)
//! and turning them into descriptor rows or grey images, on the current rayon pool.
//!
//! Memory: a descriptor map's batch is decoded one image per pool thread at a time (decoded,
//! described, dropped), so its decoded pixels never exceed `threads x max_pixels` however many
//! images it has; a co-occurrence batch that must be held whole is refused over a budget of
//! decoded pixels (`max_batch_pixels`) before anything is decoded.
//!
//! Every image error names its part as the front end named it (the API uses
//! `image[k] ("file name")`, `k` counting the batch's images from 0).

use std::io::Cursor;
use std::sync::atomic::{AtomicUsize, Ordering};

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
///
/// Each image is decoded, described and dropped by one task of the pool ([`each_part`]), so at
/// most one decoded image per pool thread is alive at a time, whatever the batch's size: the
/// decoded pixels of every request together stay under `threads x max_pixels`.
pub fn describe(
    extractor: &dyn Extractor,
    parts: &[ImageInput],
    max_pixels: u64,
    max_len: usize,
    expected_dim: Option<u32>,
) -> AppResult<Matrix> {
    let dim = check_headers(extractor, parts, max_len, max_pixels, expected_dim)?;
    let rows = each_part(parts, |p| {
        let image = decode(p, max_pixels, extractor.pixels())?;
        extract(extractor, p, &image, dim)
    })?;
    pack(rows, dim)
}

/// [`describe`] for reference images: also the JPEG thumbnail of each image
/// ([`seasonloc_core::picture::thumbnail_jpeg`]), from the same decoded pixels. Blocking; one
/// decoded image per pool thread at a time, as [`describe`].
pub fn describe_with_thumbnails(
    extractor: &dyn Extractor,
    parts: &[ImageInput],
    max_pixels: u64,
    max_len: usize,
    expected_dim: Option<u32>,
) -> AppResult<(Matrix, Vec<Vec<u8>>)> {
    let dim = check_headers(extractor, parts, max_len, max_pixels, expected_dim)?;
    let own = extractor.pixels();
    let rows = each_part(parts, |p| {
        // Thumbnails show colour; the descriptors read what the extractor reads (a camera
        // JPEG's Y plane for HOG), exactly as for queries, so references and queries match.
        let colour = decode(p, max_pixels, features::Pixels::Colour)?;
        let thumbnail = seasonloc_core::picture::thumbnail_jpeg(&colour)?;
        let values = if own == features::Pixels::Colour {
            extract(extractor, p, &colour, dim)?
        } else {
            // The extractor's own pixels from the colour decode where they are the same image
            // (PNG), decoded again where not (a camera JPEG's Y plane), the colour pixels
            // dropped first.
            let image = match features::from_colour_decode(&p.bytes, &colour, own) {
                Some(image) => image,
                None => {
                    drop(colour);
                    decode(p, max_pixels, own)?
                }
            };
            extract(extractor, p, &image, dim)?
        };
        Ok((values, thumbnail))
    })?;
    let (rows, thumbnails) = rows.into_iter().unzip();
    Ok((pack(rows, dim)?, thumbnails))
}

/// Checks every part's header (format, pixel count, descriptor length) before decoding any;
/// the batch's descriptor length.
fn check_headers(
    extractor: &dyn Extractor,
    parts: &[ImageInput],
    max_len: usize,
    max_pixels: u64,
    expected_dim: Option<u32>,
) -> AppResult<usize> {
    if parts.is_empty() {
        return Err(AppError::EmptyBatch(
            "no images to extract descriptors from".into(),
        ));
    }
    let dims = parts
        .par_iter()
        .map(|p| {
            let (w, h) = checked_dimensions(p, max_pixels)?;
            let dim = extractor
                .dim_for(w, h)
                .map_err(|e| invalid(p, e.to_string()))?;
            Ok::<_, AppError>((w, h, dim))
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
    Ok(first.map_or(0, |(_, _, d)| d))
}

/// The upright size of a part from its header, refused over `max_pixels` before decoding.
fn checked_dimensions(p: &ImageInput, max_pixels: u64) -> AppResult<(u32, u32)> {
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
    Ok((w, h))
}

/// Runs `work` on every part on the current rayon pool and gives the results in order, or the
/// error of the first failing part in order. Each task holds what `work` decodes only while it
/// runs, so a batch's decoded pixels are at most one image per pool thread; once a part
/// failed, the parts after it are not worked on.
fn each_part<T: Send>(
    parts: &[ImageInput],
    work: impl Fn(&ImageInput) -> AppResult<T> + Sync,
) -> AppResult<Vec<T>> {
    let first_bad = AtomicUsize::new(usize::MAX);
    let results: Vec<Option<AppResult<T>>> = parts
        .par_iter()
        .enumerate()
        .map(|(i, p)| {
            if i > first_bad.load(Ordering::Relaxed) {
                return None;
            }
            let r = work(p);
            if r.is_err() {
                first_bad.fetch_min(i, Ordering::Relaxed);
            }
            Some(r)
        })
        .collect();
    // A part is skipped only after a failure at a lower index, whose error returns first.
    results.into_iter().flatten().collect()
}

/// Decodes one part as `pixels` (its header already checked). Blocking.
fn decode(
    p: &ImageInput,
    max_pixels: u64,
    pixels: features::Pixels,
) -> AppResult<image::DynamicImage> {
    Ok(features::decode_image_as(
        &p.name, &p.bytes, max_pixels, pixels,
    )?)
}

/// The descriptor of one decoded part, checked to have the batch's length `dim` (the
/// extractor's promise from the header). Errors name the part.
fn extract(
    extractor: &dyn Extractor,
    p: &ImageInput,
    image: &image::DynamicImage,
    dim: usize,
) -> AppResult<Vec<f32>> {
    use seasonloc_core::Error as E;
    let values = extractor.extract(image).map_err(|e| match e {
        // The extractor does not know the part's name.
        E::Image { reason, .. } => invalid(p, reason),
        e @ (E::InvalidParameter { .. }
        | E::Inconsistent { .. }
        | E::NonFinite { .. }
        | E::Shape(_)
        | E::Empty(_)
        | E::Io { .. }
        | E::Format { .. }) => AppError::from(e),
    })?;
    if values.len() != dim {
        return Err(AppError::ShapeMismatch(format!(
            "{}: the extractor produced {} values but announced {dim}",
            p.name,
            values.len()
        )));
    }
    Ok(values)
}

/// Rows of one length `dim` as a matrix.
fn pack(rows: Vec<Vec<f32>>, dim: usize) -> AppResult<Matrix> {
    let n = rows.len();
    let mut data = Vec::with_capacity(n * dim);
    for r in rows {
        data.extend_from_slice(&r);
    }
    Ok(Matrix::from_vec(n, dim, data)?)
}

/// Decodes the parts to grey images, in order (the co-occurrence method's input, held whole:
/// a drive's model is built from all its images at once). The batch's decoded pixels, the sum
/// of its images' sizes from their headers, must stay within `max_batch_pixels`
/// ([`AppError::BatchPixels`], checked before anything is decoded). Blocking.
pub fn decode_gray(
    parts: &[ImageInput],
    max_pixels: u64,
    max_batch_pixels: u64,
) -> AppResult<Vec<GrayImage>> {
    let sizes = parts
        .par_iter()
        .map(|p| checked_dimensions(p, max_pixels))
        .collect::<AppResult<Vec<_>>>()?;
    let pixels: u64 = sizes
        .iter()
        .map(|&(w, h)| u64::from(w) * u64::from(h))
        .sum();
    if pixels > max_batch_pixels {
        return Err(AppError::BatchPixels {
            images: parts.len(),
            pixels,
            limit: max_batch_pixels,
        });
    }
    parts
        .par_iter()
        .map(|p| Ok(features::decode_gray(&p.name, &p.bytes, max_pixels)?))
        .collect()
}

/// Decodes each part to grey and hands it to `work` (e.g. extracting and quantising its
/// features), in order; the pixels are dropped as soon as `work` returns, so at most one
/// decoded image per pool thread is alive at a time ([`each_part`]). Blocking.
pub fn each_gray<T: Send>(
    parts: &[ImageInput],
    max_pixels: u64,
    work: impl Fn(&ImageInput, &GrayImage) -> AppResult<T> + Sync,
) -> AppResult<Vec<T>> {
    for p in parts {
        checked_dimensions(p, max_pixels)?;
    }
    each_part(parts, |p| {
        let gray = features::decode_gray(&p.name, &p.bytes, max_pixels)?;
        work(p, &gray)
    })
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
