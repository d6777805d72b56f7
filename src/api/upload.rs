//! Reading multipart batches (parts `image`, plus `metadata` or `params`) and turning image
//! parts into descriptors on the CPU pool.
//!
//! Every image error names its part as `image[k] ("file name")`, `k` counting the batch's image
//! parts from 0. Limits (count, pixels, body size) are checked as early as possible: the count
//! while streaming, the pixel count from the image header before decoding.

use std::io::Cursor;

use axum::body::Bytes;
use axum::extract::multipart::{Multipart, MultipartError, MultipartRejection};
use rayon::prelude::*;

use super::error::ApiError;
use crate::features::{self, Extractor};
use crate::Matrix;

/// One uploaded image.
#[derive(Clone, Debug)]
pub struct ImagePart {
    /// `image[k]` or `image[k] ("file.png")`.
    pub name: String,
    /// Encoded bytes.
    pub bytes: Bytes,
}

/// A parsed multipart batch.
#[derive(Debug, Default)]
pub struct Upload {
    /// Image parts in order.
    pub images: Vec<ImagePart>,
    /// The optional JSON part (`metadata` or `params`).
    pub json: Option<Bytes>,
}

/// Maps the multipart extractor's rejection (missing boundary, wrong content type).
pub fn rejection(r: MultipartRejection) -> ApiError {
    ApiError::UnsupportedMediaType(format!(
        "expected a multipart/form-data body with `image` parts: {}",
        r.body_text()
    ))
}

fn stream_error(e: MultipartError, max_body: usize) -> ApiError {
    if e.status() == axum::http::StatusCode::PAYLOAD_TOO_LARGE {
        ApiError::PayloadTooLarge(max_body)
    } else {
        ApiError::BadRequest(format!("malformed multipart body: {}", e.body_text()))
    }
}

/// Reads every part. `json_part` names the one optional JSON part accepted besides `image`
/// (e.g. `metadata` or `params`); any other part name is 400. More than `max_images` image
/// parts is 400 `batch_too_large`, none is 400 `empty_batch`.
pub async fn read(
    mut multipart: Multipart,
    json_part: &'static str,
    max_images: usize,
    max_body: usize,
) -> Result<Upload, ApiError> {
    let mut upload = Upload::default();
    while let Some(field) = multipart
        .next_field()
        .await
        .map_err(|e| stream_error(e, max_body))?
    {
        let part = field.name().unwrap_or("").to_string();
        if part == "image" {
            if upload.images.len() == max_images {
                return Err(ApiError::BatchTooLarge {
                    what: "images",
                    limit: max_images,
                });
            }
            let k = upload.images.len();
            let name = match field.file_name() {
                Some(f) => format!("image[{k}] ({f:?})"),
                None => format!("image[{k}]"),
            };
            let bytes = field.bytes().await.map_err(|e| stream_error(e, max_body))?;
            upload.images.push(ImagePart { name, bytes });
        } else if part == json_part {
            if upload.json.is_some() {
                return Err(ApiError::BadRequest(format!("part `{part}` appears twice")));
            }
            upload.json = Some(field.bytes().await.map_err(|e| stream_error(e, max_body))?);
        } else {
            return Err(ApiError::BadRequest(format!(
                "unknown part `{part}` (expected `image` parts and an optional `{json_part}` part)"
            )));
        }
    }
    if upload.images.is_empty() {
        return Err(ApiError::EmptyBatch(
            "no `image` parts in the request".into(),
        ));
    }
    Ok(upload)
}

/// Width and height from the header, without decoding the pixels.
fn dimensions(part: &ImagePart) -> Result<(u32, u32), ApiError> {
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
    reader
        .into_dimensions()
        .map_err(|e| invalid(part, format!("unreadable image header: {e}")))
}

fn invalid(part: &ImagePart, reason: String) -> ApiError {
    ApiError::InvalidImage {
        part: part.name.clone(),
        reason,
    }
}

/// Decodes the parts and extracts one descriptor row per image, in order, on the current rayon
/// pool. All images must give descriptors of one length, equal to `expected_dim` when given
/// (the map's); violations name the first offending part.
pub fn extract(
    extractor: &dyn Extractor,
    parts: &[ImagePart],
    max_pixels: u64,
    expected_dim: Option<u32>,
) -> Result<Matrix, ApiError> {
    let dims = parts
        .par_iter()
        .map(|p| {
            let (w, h) = dimensions(p)?;
            let pixels = u64::from(w) * u64::from(h);
            if pixels > max_pixels {
                return Err(ApiError::ImageTooLarge {
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
        if let Some(expected) = expected_dim {
            if dim != expected as usize {
                return Err(ApiError::DescriptorLength(format!(
                    "{} is {w}x{h} and gives descriptors of length {dim}; this map's descriptors \
                     have length {expected} (send images of the map's size)",
                    p.name
                )));
            }
        }
        match first {
            None => first = Some((w, h, dim)),
            Some((w0, h0, d0)) if d0 != dim => {
                return Err(ApiError::DescriptorLength(format!(
                    "{} is {w}x{h} (descriptor length {dim}) but image[0] is {w0}x{h0} \
                     (length {d0}); a batch must give descriptors of one length",
                    p.name
                )))
            }
            Some(_) => {}
        }
    }
    let images = parts
        .par_iter()
        .map(|p| features::decode_image(&p.name, &p.bytes, max_pixels).map_err(ApiError::from))
        .collect::<Result<Vec<_>, _>>()?;
    Ok(features::extract_batch(extractor, &images)?)
}

/// Checks client descriptors (`what` is "descriptors" or "query descriptors") and packs them
/// into a matrix of `f32`: all rows of one length, equal to `expected_dim` when given, every
/// value finite as `f32`.
pub fn descriptor_matrix(
    rows: &[Vec<f64>],
    expected_dim: Option<u32>,
    max_rows: usize,
) -> Result<Matrix, ApiError> {
    if rows.is_empty() {
        return Err(ApiError::EmptyBatch("`descriptors` is empty".into()));
    }
    if rows.len() > max_rows {
        return Err(ApiError::BatchTooLarge {
            what: "descriptors",
            limit: max_rows,
        });
    }
    let dim = expected_dim.map_or(rows[0].len(), |d| d as usize);
    if dim == 0 {
        return Err(ApiError::DescriptorLength(
            "descriptors must not be empty vectors".into(),
        ));
    }
    let mut data = Vec::with_capacity(rows.len() * dim);
    for (i, row) in rows.iter().enumerate() {
        if row.len() != dim {
            return Err(ApiError::DescriptorLength(format!(
                "descriptors[{i}] has length {}, expected {dim}",
                row.len()
            )));
        }
        for (j, &v) in row.iter().enumerate() {
            let x = v as f32;
            if !x.is_finite() {
                return Err(ApiError::NonFinite(format!(
                    "descriptors[{i}][{j}] = {v} is not a finite 32-bit float"
                )));
            }
            data.push(x);
        }
    }
    Ok(Matrix::from_vec(rows.len(), dim, data).expect("rows * dim values were pushed"))
}

/// Parses a raw little-endian `f32` body of `dim`-long rows.
pub fn raw_descriptor_matrix(body: &[u8], dim: u32, max_rows: usize) -> Result<Matrix, ApiError> {
    let dim = dim as usize;
    if dim == 0 {
        return Err(ApiError::param("dim", "must be at least 1"));
    }
    if body.is_empty() {
        return Err(ApiError::EmptyBatch("the body holds no descriptors".into()));
    }
    if body.len() % (4 * dim) != 0 {
        return Err(ApiError::DescriptorLength(format!(
            "a body of {} bytes is not a whole number of {dim}-value rows of 4-byte floats",
            body.len()
        )));
    }
    let rows = body.len() / (4 * dim);
    if rows > max_rows {
        return Err(ApiError::BatchTooLarge {
            what: "descriptors",
            limit: max_rows,
        });
    }
    let data: Vec<f32> = body
        .chunks_exact(4)
        .map(|c| f32::from_le_bytes(c.try_into().expect("chunks of 4")))
        .collect();
    if let Some(k) = data.iter().position(|v| !v.is_finite()) {
        return Err(ApiError::NonFinite(format!(
            "descriptors[{}][{}] = {} is not finite",
            k / dim,
            k % dim,
            data[k]
        )));
    }
    Ok(Matrix::from_vec(rows, dim, data).expect("length is a multiple of dim"))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn descriptor_rows_are_checked() {
        let m = descriptor_matrix(&[vec![1.0, 2.0], vec![3.0, 4.0]], None, 10).unwrap();
        assert_eq!((m.rows(), m.cols()), (2, 2));
        let e = descriptor_matrix(&[vec![1.0, 2.0], vec![3.0]], None, 10).unwrap_err();
        assert!(e.to_string().contains("descriptors[1] has length 1"), "{e}");
        let e = descriptor_matrix(&[vec![1.0, 1e39]], None, 10).unwrap_err();
        assert!(matches!(e, ApiError::NonFinite(_)), "{e}");
        let e = descriptor_matrix(&[vec![1.0]], Some(2), 10).unwrap_err();
        assert!(matches!(e, ApiError::DescriptorLength(_)), "{e}");
        assert!(matches!(
            descriptor_matrix(&[], None, 10),
            Err(ApiError::EmptyBatch(_))
        ));
        assert!(matches!(
            descriptor_matrix(&[vec![1.0], vec![1.0]], None, 1),
            Err(ApiError::BatchTooLarge { .. })
        ));
    }

    #[test]
    fn raw_rows_are_checked() {
        let bytes: Vec<u8> = [1.0f32, 2.0, 3.0, f32::NAN]
            .iter()
            .flat_map(|v| v.to_le_bytes())
            .collect();
        let e = raw_descriptor_matrix(&bytes, 2, 10).unwrap_err();
        assert!(e.to_string().contains("descriptors[1][1]"), "{e}");
        let m = raw_descriptor_matrix(&bytes[..8], 2, 10).unwrap();
        assert_eq!(m.row(0), &[1.0, 2.0]);
        assert!(matches!(
            raw_descriptor_matrix(&bytes[..6], 2, 10),
            Err(ApiError::DescriptorLength(_))
        ));
    }

    #[test]
    fn corrupt_images_are_named_before_decoding() {
        struct Never;
        impl Extractor for Never {
            fn dim_for(&self, _: u32, _: u32) -> crate::Result<usize> {
                Ok(1)
            }
            fn extract(&self, _: &image::DynamicImage) -> crate::Result<Vec<f32>> {
                unreachable!("the batch is rejected before extraction")
            }
        }
        let parts = vec![ImagePart {
            name: "image[0] (\"x.png\")".into(),
            bytes: Bytes::from_static(b"not an image"),
        }];
        let e = extract(&Never, &parts, 100, None).unwrap_err();
        assert!(
            matches!(&e, ApiError::InvalidImage { part, .. } if part.contains("x.png")),
            "{e}"
        );
        let mut png = Vec::new();
        image::DynamicImage::new_luma8(20, 10)
            .write_to(&mut Cursor::new(&mut png), image::ImageFormat::Png)
            .unwrap();
        let parts = vec![ImagePart {
            name: "image[0]".into(),
            bytes: Bytes::from(png),
        }];
        let e = extract(&Never, &parts, 100, None).unwrap_err();
        assert!(
            matches!(e, ApiError::ImageTooLarge { pixels: 200, .. }),
            "{e}"
        );
    }
}
