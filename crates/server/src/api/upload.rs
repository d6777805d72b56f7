//! Reading request bodies into the use cases' input: multipart batches (parts `image`, plus
//! one JSON part such as `metadata` or `params`) and precomputed descriptors (JSON rows or raw
//! little-endian `f32`).
//!
//! Every image part is named `image[k] ("file name")`, `k` counting the batch's image parts
//! from 0, so later errors about it name it the same way. Limits are checked as early as
//! possible: the image count and body size while streaming (the pixel count is checked by the
//! use case from each image's header, before decoding).

use axum::body::Bytes;
use axum::extract::multipart::{Multipart, MultipartError, MultipartRejection};
use axum::http::{header, HeaderMap};
use seasonloc_app::AppError;

use super::error::ApiError;
use seasonloc_app::ImageInput;
use seasonloc_core::Matrix;

/// One uploaded image part.
pub type ImagePart = ImageInput;

/// A parsed multipart batch.
#[derive(Debug, Default)]
pub struct Upload {
    /// Image parts in order.
    pub images: Vec<ImagePart>,
    /// The optional JSON part (`metadata` or `params`).
    pub json: Option<Bytes>,
}

/// Maps the multipart extractor's rejection (a missing or other content type, a missing
/// boundary) to 415, saying which of them it was from the request's `headers`.
pub fn rejection(r: MultipartRejection, headers: &HeaderMap) -> ApiError {
    let got = headers.get(header::CONTENT_TYPE).map(|v| {
        String::from_utf8_lossy(v.as_bytes())
            .chars()
            .take(120)
            .collect::<String>()
    });
    ApiError::UnsupportedMediaType(match got {
        None => "expected `Content-Type: multipart/form-data` with `image` parts; the request \
                 has no Content-Type"
            .into(),
        Some(t)
            if t.trim_start()
                .to_ascii_lowercase()
                .starts_with("multipart/form-data") =>
        {
            format!(
                "`{t}` is not usable: {} (send the boundary its parts are separated by)",
                r.body_text()
            )
        }
        Some(t) => {
            format!("expected `Content-Type: multipart/form-data` with `image` parts, got `{t}`")
        }
    })
}

fn stream_error(e: MultipartError, max_body: usize) -> ApiError {
    if super::extract::is_body_timeout(&e) {
        ApiError::BodyTimeout
    } else if e.status() == axum::http::StatusCode::PAYLOAD_TOO_LARGE {
        ApiError::PayloadTooLarge(max_body)
    } else {
        ApiError::BadRequest(format!("malformed multipart body: {}", e.body_text()))
    }
}

/// Reads every part. `json_part` names the one optional JSON part accepted besides `image`
/// (e.g. `metadata` or `params`), if any; any other part name is 400. More than `max_images`
/// image parts is 400 `batch_too_large`, none is 400 `empty_batch`.
pub async fn read(
    mut multipart: Multipart,
    json_part: Option<&'static str>,
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
        } else if json_part == Some(part.as_str()) {
            if upload.json.is_some() {
                return Err(ApiError::BadRequest(format!("part `{part}` appears twice")));
            }
            upload.json = Some(field.bytes().await.map_err(|e| stream_error(e, max_body))?);
        } else {
            return Err(ApiError::BadRequest(match json_part {
                Some(json) => format!(
                    "unknown part `{part}` (expected `image` parts and an optional `{json}` part)"
                ),
                None => format!("unknown part `{part}` (expected only `image` parts)"),
            }));
        }
    }
    if upload.images.is_empty() {
        return Err(ApiError::App(AppError::EmptyBatch(
            "no `image` parts in the request".into(),
        )));
    }
    Ok(upload)
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
        return Err(ApiError::App(AppError::EmptyBatch(
            "`descriptors` is empty".into(),
        )));
    }
    if rows.len() > max_rows {
        return Err(ApiError::BatchTooLarge {
            what: "descriptors",
            limit: max_rows,
        });
    }
    let dim = expected_dim.map_or(rows[0].len(), |d| d as usize);
    if dim == 0 {
        return Err(ApiError::App(AppError::DescriptorLength(
            "descriptors must not be empty vectors".into(),
        )));
    }
    let mut out = Matrix::zeros(rows.len(), dim);
    for (i, row) in rows.iter().enumerate() {
        if row.len() != dim {
            return Err(ApiError::App(AppError::DescriptorLength(format!(
                "descriptors[{i}] has length {}, expected {dim}",
                row.len()
            ))));
        }
        for (j, (out, &v)) in out.row_mut(i).iter_mut().zip(row).enumerate() {
            let x = v as f32;
            if !x.is_finite() {
                return Err(ApiError::App(AppError::NonFinite(format!(
                    "descriptors[{i}][{j}] = {v} is not a finite 32-bit float"
                ))));
            }
            *out = x;
        }
    }
    Ok(out)
}

/// Parses a raw little-endian `f32` body of `dim`-long rows.
pub fn raw_descriptor_matrix(body: &[u8], dim: u32, max_rows: usize) -> Result<Matrix, ApiError> {
    let dim = dim as usize;
    if dim == 0 {
        return Err(ApiError::param("dim", "must be at least 1"));
    }
    if body.is_empty() {
        return Err(ApiError::App(AppError::EmptyBatch(
            "the body holds no descriptors".into(),
        )));
    }
    if !body.len().is_multiple_of(4 * dim) {
        return Err(ApiError::App(AppError::DescriptorLength(format!(
            "a body of {} bytes is not a whole number of {dim}-value rows of 4-byte floats",
            body.len()
        ))));
    }
    let rows = body.len() / (4 * dim);
    if rows > max_rows {
        return Err(ApiError::BatchTooLarge {
            what: "descriptors",
            limit: max_rows,
        });
    }
    // `rows * dim * 4 == body.len()` was checked above, so the matrix takes every 4-byte chunk.
    let mut out = Matrix::zeros(rows, dim);
    for (v, c) in out.as_mut_slice().iter_mut().zip(body.chunks_exact(4)) {
        *v = f32::from_le_bytes([c[0], c[1], c[2], c[3]]);
    }
    let data = out.as_slice();
    if let Some(k) = data.iter().position(|v| !v.is_finite()) {
        return Err(ApiError::App(AppError::NonFinite(format!(
            "descriptors[{}][{}] = {} is not finite",
            k / dim,
            k % dim,
            data[k]
        ))));
    }
    Ok(out)
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
        assert!(matches!(e, ApiError::App(AppError::NonFinite(_))), "{e}");
        let e = descriptor_matrix(&[vec![1.0]], Some(2), 10).unwrap_err();
        assert!(
            matches!(e, ApiError::App(AppError::DescriptorLength(_))),
            "{e}"
        );
        assert!(matches!(
            descriptor_matrix(&[], None, 10),
            Err(ApiError::App(AppError::EmptyBatch(_)))
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
            Err(ApiError::App(AppError::DescriptorLength(_)))
        ));
    }
}
