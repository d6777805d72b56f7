//! The one step from a map's descriptor settings to query descriptors of uploaded images,
//! shared by localizations and trips, so every map kind that can describe images (HOG today,
//! CNN when it lands) serves both routes the same way.

use super::error::ApiError;
use super::maps::hog_spec;
use super::upload::{self, ImagePart};
use crate::store::MapRecord;
use crate::Matrix;

/// Whether query *images* can be described for this map (a map of client-computed
/// descriptors cannot: the server does not know how they were computed).
pub fn describes_images(map: &MapRecord) -> Result<bool, ApiError> {
    Ok(hog_spec(map.descriptor)?.is_some())
}

/// One descriptor row per image part, in order, with the map's settings and descriptor
/// length; `None` when the map's kind cannot describe images (see [`describes_images`]).
/// Runs on the current rayon pool.
pub fn query_descriptors(
    map: &MapRecord,
    parts: &[ImagePart],
    max_pixels: u64,
) -> Result<Option<Matrix>, ApiError> {
    let Some(spec) = hog_spec(map.descriptor)? else {
        return Ok(None);
    };
    upload::extract(&spec, parts, max_pixels, map.dim).map(Some)
}
