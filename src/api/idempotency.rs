//! The `Idempotency-Key` request header of `POST /v1/trips/{id}/frames` and
//! `POST /v1/maps/{id}/images` (decision D5; the use case is `crate::app::Idempotency`): a
//! retried batch with the same key and the same parts is applied once and answered as the
//! first time, with `Idempotent-Replayed: true`; the same key with other parts is 409
//! `idempotency_key_reused`.
//!
//! The request's fingerprint is a SHA-256 over its parts' contents (each image's bytes and the
//! JSON part, length-prefixed, in order), not over the raw body: a retry has a new multipart
//! boundary, and file names are cosmetic.

use axum::http::{HeaderMap, HeaderName, HeaderValue};
use sha2::{Digest, Sha256};

use super::error::ApiError;
use super::upload::Upload;
use crate::app::Idempotency;

/// The request header.
pub const KEY: HeaderName = HeaderName::from_static("idempotency-key");

/// The response header on a replayed answer.
pub const REPLAYED: HeaderName = HeaderName::from_static("idempotent-replayed");

/// The request's key and fingerprint, `None` without the header.
pub fn from_request(headers: &HeaderMap, upload: &Upload) -> Result<Option<Idempotency>, ApiError> {
    let Some(value) = headers.get(KEY) else {
        return Ok(None);
    };
    let key = value.to_str().map_err(|_| {
        ApiError::param(
            "Idempotency-Key",
            "must be visible ASCII characters (e.g. a UUID)",
        )
    })?;
    let mut hash = Sha256::new();
    for image in &upload.images {
        hash.update((image.bytes.len() as u64).to_le_bytes());
        hash.update(&image.bytes);
    }
    match &upload.json {
        Some(json) => {
            hash.update([1]);
            hash.update((json.len() as u64).to_le_bytes());
            hash.update(json);
        }
        None => hash.update([0]),
    }
    Ok(Some(Idempotency::new(key, hash.finalize().to_vec())?))
}

/// The response headers: `Idempotent-Replayed: true` on a replay.
pub fn headers(replayed: bool) -> HeaderMap {
    let mut h = HeaderMap::new();
    if replayed {
        h.insert(REPLAYED, HeaderValue::from_static("true"));
    }
    h
}
