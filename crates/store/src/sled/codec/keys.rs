//! The key layout (the table in [`super`]): one-byte prefixes, big-endian ids and indices so
//! that sled's lexicographic order is the numeric order, and the parsing of ids back out of a
//! key. Kept apart from the value encodings because every engine module builds keys while
//! only the reads and writes of one record kind need its encoding.

use seasonloc_app::store::StoreError;

/// Key of the layout version.
pub const SCHEMA_VERSION_KEY: &[u8] = b"meta/schema_version";
/// The generation of the newest write (`u64` BE), stored in every write batch and checked
/// against the ledger file at start (`sled/ledger.rs`).
pub const GENERATION_KEY: &[u8] = b"meta/generation";
/// Prefix of map records.
pub const MAP_PREFIX: u8 = b'M';
/// Prefix of image records.
pub const IMAGE_PREFIX: u8 = b'I';
/// Prefix of localization records.
pub const LOCALIZATION_PREFIX: u8 = b'L';
/// Prefix of the by-map localization index.
pub const LOCALIZATION_BY_MAP_PREFIX: u8 = b'l';
/// Prefix of encoded co-occurrence maps (layout >= 3).
pub const COOC_PREFIX: u8 = b'C';

/// `C` + map id: the encoded `CoocMap` of a `cooc` map.
pub fn cooc_key(id: u64) -> [u8; 9] {
    id_key(COOC_PREFIX, id)
}

/// Prefix of trip records.
pub const TRIP_PREFIX: u8 = b'T';
/// Prefix of trip states in one blob (format 1, layouts 4-5; read until a batch replaces them).
pub const TRIP_STATE_PREFIX: u8 = b'S';
/// Prefix of a trip state's base (layout >= 6).
pub const TRIP_BASE_PREFIX: u8 = b'b';
/// Prefix of a trip state's snapshot (layout >= 6).
pub const TRIP_SNAPSHOT_PREFIX: u8 = b's';
/// Prefix of a trip state's log rows (layout >= 6).
pub const TRIP_LOG_PREFIX: u8 = b'r';
/// Prefix of trip frame estimates.
pub const TRIP_FRAME_PREFIX: u8 = b'F';
/// Prefix of the by-map trip index.
pub const TRIP_BY_MAP_PREFIX: u8 = b't';

/// Prefix of idempotency records.
pub const IDEMPOTENCY_PREFIX: u8 = b'K';

/// `K` + scope + `0x00`: every idempotency record of one scope.
pub fn idempotency_prefix(scope: &str) -> Vec<u8> {
    let mut k = Vec::with_capacity(scope.len() + 2);
    k.push(IDEMPOTENCY_PREFIX);
    k.extend_from_slice(scope.as_bytes());
    k.push(0);
    k
}

/// `K` + scope + `0x00` + key.
pub fn idempotency_key(scope: &str, key: &str) -> Vec<u8> {
    let mut k = idempotency_prefix(scope);
    k.extend_from_slice(key.as_bytes());
    k
}

fn id_key(prefix: u8, id: u64) -> [u8; 9] {
    let mut k = [prefix; 9];
    k[1..].copy_from_slice(&id.to_be_bytes());
    k
}

fn index_key(prefix: u8, id: u64, index: u32) -> [u8; 13] {
    let mut k = [prefix; 13];
    k[1..9].copy_from_slice(&id.to_be_bytes());
    k[9..].copy_from_slice(&index.to_be_bytes());
    k
}

fn pair_key(prefix: u8, a: u64, b: u64) -> [u8; 17] {
    let mut k = [prefix; 17];
    k[1..9].copy_from_slice(&a.to_be_bytes());
    k[9..].copy_from_slice(&b.to_be_bytes());
    k
}

/// `T` + trip id.
pub fn trip_key(id: u64) -> [u8; 9] {
    id_key(TRIP_PREFIX, id)
}

/// `S` + trip id.
pub fn trip_state_key(id: u64) -> [u8; 9] {
    id_key(TRIP_STATE_PREFIX, id)
}

/// `b` + trip id: the trip state's base.
pub fn trip_base_key(id: u64) -> [u8; 9] {
    id_key(TRIP_BASE_PREFIX, id)
}

/// `s` + trip id: the trip state's snapshot.
pub fn trip_snapshot_key(id: u64) -> [u8; 9] {
    id_key(TRIP_SNAPSHOT_PREFIX, id)
}

/// `r` + trip id: the prefix of the trip state's log rows.
pub fn trip_log_prefix(id: u64) -> [u8; 9] {
    id_key(TRIP_LOG_PREFIX, id)
}

/// `r` + trip id + frame: one log row.
pub fn trip_log_key(id: u64, frame: u32) -> [u8; 13] {
    index_key(TRIP_LOG_PREFIX, id, frame)
}

/// The frame of a log row's key.
pub fn log_frame_at(key: &[u8]) -> Result<u32, StoreError> {
    let bytes: [u8; 4] = key
        .get(9..13)
        .and_then(|b| b.try_into().ok())
        .ok_or_else(|| StoreError::corrupt(key, "key too short for a frame"))?;
    Ok(u32::from_be_bytes(bytes))
}

/// `F` + trip id: the prefix of a trip's frames.
pub fn trip_frames_prefix(id: u64) -> [u8; 9] {
    id_key(TRIP_FRAME_PREFIX, id)
}

/// `F` + trip id + frame.
pub fn trip_frame_key(id: u64, frame: u32) -> [u8; 13] {
    index_key(TRIP_FRAME_PREFIX, id, frame)
}

/// `t` + map id: the prefix of a map's trip index.
pub fn trips_by_map_prefix(map: u64) -> [u8; 9] {
    id_key(TRIP_BY_MAP_PREFIX, map)
}

/// `t` + map id + trip id.
pub fn trip_by_map_key(map: u64, id: u64) -> [u8; 17] {
    pair_key(TRIP_BY_MAP_PREFIX, map, id)
}

/// `M` + id.
pub fn map_key(id: u64) -> [u8; 9] {
    id_key(MAP_PREFIX, id)
}

/// `I` + map id: the prefix of all of a map's images.
pub fn images_prefix(map: u64) -> [u8; 9] {
    id_key(IMAGE_PREFIX, map)
}

/// `I` + map id + index.
pub fn image_key(map: u64, index: u32) -> [u8; 13] {
    index_key(IMAGE_PREFIX, map, index)
}

/// `L` + id.
pub fn localization_key(id: u64) -> [u8; 9] {
    id_key(LOCALIZATION_PREFIX, id)
}

/// `l` + map id: the prefix of a map's localization index.
pub fn by_map_prefix(map: u64) -> [u8; 9] {
    id_key(LOCALIZATION_BY_MAP_PREFIX, map)
}

/// `l` + map id + localization id.
pub fn by_map_key(map: u64, id: u64) -> [u8; 17] {
    pair_key(LOCALIZATION_BY_MAP_PREFIX, map, id)
}

/// Prefix of image thumbnails (layout >= 5).
pub const THUMBNAIL_PREFIX: u8 = b'J';
/// Prefix of localizations' similarity pictures (layout >= 5).
pub const PICTURE_PREFIX: u8 = b'P';

/// `J` + map id: the prefix of all of a map's thumbnails.
pub fn thumbnails_prefix(map: u64) -> [u8; 9] {
    id_key(THUMBNAIL_PREFIX, map)
}

/// `J` + map id + index: an image's JPEG thumbnail.
pub fn thumbnail_key(map: u64, index: u32) -> [u8; 13] {
    index_key(THUMBNAIL_PREFIX, map, index)
}

/// `P` + localization id: the PNG of its similarity picture.
pub fn picture_key(id: u64) -> [u8; 9] {
    id_key(PICTURE_PREFIX, id)
}

/// Reads the `u64` at `key[at..at + 8]`.
pub fn id_at(key: &[u8], at: usize) -> Result<u64, StoreError> {
    let bytes: [u8; 8] = key
        .get(at..at + 8)
        .and_then(|b| b.try_into().ok())
        .ok_or_else(|| StoreError::corrupt(key, "key too short for an id"))?;
    Ok(u64::from_be_bytes(bytes))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn big_endian_keys_sort_numerically() {
        assert!(image_key(1, 255) < image_key(1, 256));
        assert!(image_key(1, u32::MAX) < image_key(2, 0));
        assert!(image_key(7, 3).starts_with(&images_prefix(7)));
        assert!(by_map_key(3, 10) < by_map_key(3, 11));
        assert_eq!(id_at(&map_key(42), 1).unwrap(), 42);
    }
}
