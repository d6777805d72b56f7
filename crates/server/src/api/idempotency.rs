//! The `Idempotency-Key` request header of the routes that create or append (`POST /v1/maps`,
//! `POST /v1/maps/{id}/images`, `/descriptors`, `/drives`, `/trips`, `/localize`,
//! `POST /v1/trips/{id}/frames`; decision D5; the use case is `seasonloc_app::Idempotency`): a
//! retried request with the same key and the same content is applied once and answered as the
//! first time, with `Idempotent-Replayed: true`; the same key with other content is 409
//! `idempotency_key_reused`.
//!
//! The request's fingerprint is a SHA-256 over what defines it, not over the raw body: for
//! multipart batches its parts' contents (each image's bytes and the JSON part, length-prefixed,
//! in order; a retry has a new multipart boundary, and file names are cosmetic); for JSON and
//! raw bodies the body (for descriptors with its media type and `?dim=`). Routes that share a
//! key space (a map's images, descriptors, drives, trips and localizations) hash a route tag
//! first (images: none, as stored since the header was introduced), so a key of one route
//! never replays another's answer.

use axum::http::{HeaderMap, HeaderName, HeaderValue};
use sha2::{Digest, Sha256};

use super::error::ApiError;
use super::upload::Upload;
use seasonloc_app::Idempotency;

/// The request header.
pub const KEY: HeaderName = HeaderName::from_static("idempotency-key");

/// The response header on a replayed answer.
pub const REPLAYED: HeaderName = HeaderName::from_static("idempotent-replayed");

/// The request's key and fingerprint, `None` without the header: a batch of images (and its
/// JSON part) appended to a map or a trip.
pub fn from_request(headers: &HeaderMap, upload: &Upload) -> Result<Option<Idempotency>, ApiError> {
    from_upload(headers, None, upload)
}

/// [`from_request`] for an upload whose route shares a map's key space with the image
/// appends but means something else (`drives`): `tag` is hashed first.
pub fn from_tagged_request(
    headers: &HeaderMap,
    tag: &str,
    upload: &Upload,
) -> Result<Option<Idempotency>, ApiError> {
    from_upload(headers, Some(tag), upload)
}

/// The key of a request defined by `parts` (each length-prefixed, in order) after `tag`.
pub fn from_parts(
    headers: &HeaderMap,
    tag: &str,
    parts: &[&[u8]],
) -> Result<Option<Idempotency>, ApiError> {
    let Some(key) = key_of(headers)? else {
        return Ok(None);
    };
    let mut hash = tagged(Some(tag));
    for part in parts {
        hash.update((part.len() as u64).to_le_bytes());
        hash.update(part);
    }
    Ok(Some(Idempotency::new(key, hash.finalize().to_vec())?))
}

fn from_upload(
    headers: &HeaderMap,
    tag: Option<&str>,
    upload: &Upload,
) -> Result<Option<Idempotency>, ApiError> {
    let Some(key) = key_of(headers)? else {
        return Ok(None);
    };
    let mut hash = tagged(tag);
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

/// A hash that starts with `tag` (length-prefixed behind a marker no untagged fingerprint
/// starts with: those start with a part's length or a 0/1 byte, never `u64::MAX`).
fn tagged(tag: Option<&str>) -> Sha256 {
    let mut hash = Sha256::new();
    if let Some(tag) = tag {
        hash.update(u64::MAX.to_le_bytes());
        hash.update((tag.len() as u64).to_le_bytes());
        hash.update(tag.as_bytes());
    }
    hash
}

/// The header's value, `None` without it.
fn key_of(headers: &HeaderMap) -> Result<Option<&str>, ApiError> {
    let Some(value) = headers.get(KEY) else {
        return Ok(None);
    };
    value.to_str().map(Some).map_err(|_| {
        ApiError::param(
            "Idempotency-Key",
            "must be visible ASCII characters (e.g. a UUID)",
        )
    })
}

/// The response headers: `Idempotent-Replayed: true` on a replay.
pub fn headers(replayed: bool) -> HeaderMap {
    let mut h = HeaderMap::new();
    if replayed {
        h.insert(REPLAYED, HeaderValue::from_static("true"));
    }
    h
}
