//! Key layout and value encodings of the store.
//!
//! Everything lives in sled's default tree, under one-byte key prefixes, so one
//! `sled::Batch` can change a map and its images atomically:
//!
//! | key | value |
//! | --- | --- |
//! | `meta/schema_version` | layout version, `u32` big-endian |
//! | `M` + map id (`u64` BE) | [`MapRecord`] |
//! | `I` + map id (`u64` BE) + index (`u32` BE) | [`ImageRecord`] (descriptor as raw LE `f32`) |
//! | `L` + localization id (`u64` BE) | [`LocalizationRecord`] |
//! | `l` + map id (`u64` BE) + localization id (`u64` BE) | empty (index, layout >= 2) |
//! | `C` + map id (`u64` BE) | `CoocMap::to_bytes` of a `cooc` map (layout >= 3) |
//! | `T` + trip id (`u64` BE) | [`TripRecord`] (layout >= 4) |
//! | `S` + trip id (`u64` BE) | a trip's solver state in one blob (format 1, layouts 4-5), opaque bytes from `crate::trip`; replaced by `b`/`s`/`r` at the trip's next batch |
//! | `b` + trip id (`u64` BE) | the trip state's base (layout >= 6; `crate::trip::persist`) |
//! | `s` + trip id (`u64` BE) | the trip state's latest snapshot (layout >= 6) |
//! | `r` + trip id (`u64` BE) + frame (`u32` BE) | one log row of the trip state: the frame's raw cosine row (layout >= 6) |
//! | `F` + trip id (`u64` BE) + frame (`u32` BE) | [`FrameRecord`]: the frame's latest estimate |
//! | `t` + map id (`u64` BE) + trip id (`u64` BE) | empty (index of a map's trips) |
//! | `K` + scope + `0x00` + key | [`IdempotencyRecord`] of a request sent with an `Idempotency-Key` (additive: older stores have none) |
//!
//! Big-endian integers make sled's lexicographic order the numeric order, so a map's images
//! iterate in route order, localizations in creation order and a trip's frames in driving
//! order. Values are a small hand-written binary format ([`crate::codec`]) starting with a format byte; the
//! decoder rejects trailing or missing bytes, so corruption is reported rather than misread.

use crate::codec::{ByteReader, ByteWriter, DecodeError};
use crate::cooc::keypoints::KeypointParams;
use crate::cooc::CoocParams;
use crate::features::cnn::{CnnOptions, CnnResize, ModelIdentity};
use crate::store::{
    CnnSettings, DescriptorSettings, FrameRecord, IdempotencyRecord, ImageMeta,
    LocalizationDocument, LocalizationRecord, MapRecord, StoreError, TripParamsDocument,
    TripRecord,
};
use crate::trip::TripStatus;

/// Key of the layout version.
pub const SCHEMA_VERSION_KEY: &[u8] = b"meta/schema_version";
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

/// Encodes an idempotency record (its scope and key are in the record's key).
pub fn encode_idempotency(r: &IdempotencyRecord) -> Vec<u8> {
    let mut w = Writer::new();
    w.bytes(&r.fingerprint);
    w.bytes(&r.response);
    match &r.indices {
        None => w.u8(0),
        Some(range) => {
            w.u8(1);
            w.u32(range.start);
            w.u32(range.end);
        }
    }
    w.into_bytes()
}

/// Decodes the idempotency record of `scope` and `key` stored under `k`.
pub fn decode_idempotency(
    k: &[u8],
    scope: &str,
    key: &str,
    value: &[u8],
) -> Result<IdempotencyRecord, StoreError> {
    let mut r = Reader::new(k, value)?;
    let fingerprint = r.bytes()?.to_vec();
    let response = r.bytes()?.to_vec();
    let indices = match r.u8()? {
        0 => None,
        1 => Some(r.u32()?..r.u32()?),
        t => return Err(StoreError::corrupt(k, format!("bad option tag {t}"))),
    };
    r.finish()?;
    Ok(IdempotencyRecord {
        scope: scope.to_string(),
        key: key.to_string(),
        fingerprint,
        response,
        indices,
    })
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

const FORMAT_V1: u8 = 1;

/// Appends values in the store's binary format: the format byte, then fields written with
/// the crate's one byte codec (dereferences to [`ByteWriter`] for the fixed-width fields).
struct Writer(ByteWriter);

impl std::ops::Deref for Writer {
    type Target = ByteWriter;
    fn deref(&self) -> &ByteWriter {
        &self.0
    }
}

impl std::ops::DerefMut for Writer {
    fn deref_mut(&mut self) -> &mut ByteWriter {
        &mut self.0
    }
}

impl Writer {
    fn new() -> Self {
        let mut w = ByteWriter::new();
        w.u8(FORMAT_V1);
        Writer(w)
    }
    fn into_bytes(self) -> Vec<u8> {
        self.0.into_bytes()
    }
    fn bytes(&mut self, v: &[u8]) {
        self.u32(u32::try_from(v.len()).expect("store values are far below 4 GiB"));
        self.raw(v);
    }
    fn str(&mut self, v: &str) {
        self.bytes(v.as_bytes());
    }
    fn opt_str(&mut self, v: Option<&str>) {
        match v {
            None => self.u8(0),
            Some(s) => {
                self.u8(1);
                self.str(s);
            }
        }
    }
}

/// Reads values written by [`Writer`]; every error names the key.
struct Reader<'a> {
    key: &'a [u8],
    buf: ByteReader<'a>,
}

impl<'a> Reader<'a> {
    fn new(key: &'a [u8], buf: &'a [u8]) -> Result<Self, StoreError> {
        let mut r = Reader {
            key,
            buf: ByteReader::new(buf),
        };
        let format = r.u8()?;
        if format != FORMAT_V1 {
            return Err(StoreError::corrupt(
                key,
                format!("unknown value format {format}"),
            ));
        }
        Ok(r)
    }
    /// The store error for a failed read of the byte codec.
    fn check<T>(&self, read: Result<T, DecodeError>) -> Result<T, StoreError> {
        read.map_err(|e| match e {
            DecodeError::Truncated { .. } => StoreError::corrupt(self.key, "value is truncated"),
            DecodeError::BadTag { tag, .. } => {
                StoreError::corrupt(self.key, format!("bad option tag {tag}"))
            }
        })
    }
    fn take(&mut self, n: usize) -> Result<&'a [u8], StoreError> {
        let read = self.buf.take(n);
        self.check(read)
    }
    fn u8(&mut self) -> Result<u8, StoreError> {
        let read = self.buf.u8();
        self.check(read)
    }
    fn u32(&mut self) -> Result<u32, StoreError> {
        let read = self.buf.u32();
        self.check(read)
    }
    fn u64(&mut self) -> Result<u64, StoreError> {
        let read = self.buf.u64();
        self.check(read)
    }
    fn f64(&mut self) -> Result<f64, StoreError> {
        let read = self.buf.f64();
        self.check(read)
    }
    fn bytes(&mut self) -> Result<&'a [u8], StoreError> {
        let n = self.u32()? as usize;
        self.take(n)
    }
    fn str(&mut self) -> Result<String, StoreError> {
        let b = self.bytes()?;
        String::from_utf8(b.to_vec()).map_err(|_| StoreError::corrupt(self.key, "invalid UTF-8"))
    }
    fn opt_str(&mut self) -> Result<Option<String>, StoreError> {
        let tag = self.buf.option_tag();
        if self.check(tag)? {
            self.str().map(Some)
        } else {
            Ok(None)
        }
    }
    fn opt_f64(&mut self) -> Result<Option<f64>, StoreError> {
        let read = self.buf.opt_f64();
        self.check(read)
    }
    fn finish(self) -> Result<(), StoreError> {
        if self.buf.remaining() == 0 {
            Ok(())
        } else {
            Err(StoreError::corrupt(self.key, "trailing bytes in value"))
        }
    }
}

const KIND_HOG: u8 = 1;
const KIND_PRECOMPUTED: u8 = 2;
const KIND_CNN: u8 = 3;
const KIND_COOC: u8 = 4;

fn encode_cooc(w: &mut Writer, p: &CoocParams) {
    let k = &p.keypoints;
    w.u32(k.upsample);
    w.u64(k.max_keypoints as u64);
    w.u32(k.harris_k.to_bits());
    w.u32(k.relative_threshold.to_bits());
    w.u32(k.min_response.to_bits());
    w.u32(k.nms_radius);
    w.u32(k.cell_size);
    w.u64(p.vocabulary_branching as u64);
    w.u64(p.vocabulary_depth as u64);
    w.u64(p.kmeans_iterations as u64);
    w.u64(p.max_training_descriptors as u64);
    w.u32(u32::from(p.grid_cols));
    w.u32(u32::from(p.grid_rows));
    w.u32(u32::from(p.spatial_tolerance));
    w.u8(u8::from(p.merge_adjacent_drives));
    w.u64(p.seed);
}

fn decode_cooc(r: &mut Reader<'_>) -> Result<CoocParams, StoreError> {
    let key = r.key;
    let usize_of =
        |v: u64| usize::try_from(v).map_err(|_| StoreError::corrupt(key, "count too large"));
    let u16_of =
        |v: u32| u16::try_from(v).map_err(|_| StoreError::corrupt(key, "grid value too large"));
    let keypoints = KeypointParams {
        upsample: r.u32()?,
        max_keypoints: usize_of(r.u64()?)?,
        harris_k: f32::from_bits(r.u32()?),
        relative_threshold: f32::from_bits(r.u32()?),
        min_response: f32::from_bits(r.u32()?),
        nms_radius: r.u32()?,
        cell_size: r.u32()?,
        // Not in the record layout (yet): the settings the map is built with (stored in its
        // co-occurrence bytes once built) take the library defaults.
        ..KeypointParams::default()
    };
    Ok(CoocParams {
        keypoints,
        vocabulary_branching: usize_of(r.u64()?)?,
        vocabulary_depth: usize_of(r.u64()?)?,
        kmeans_iterations: usize_of(r.u64()?)?,
        max_training_descriptors: usize_of(r.u64()?)?,
        grid_cols: u16_of(r.u32()?)?,
        grid_rows: u16_of(r.u32()?)?,
        spatial_tolerance: u16_of(r.u32()?)?,
        merge_adjacent_drives: r.u8()? != 0,
        seed: r.u64()?,
    })
}

const RESIZE_STRETCH: u8 = 0;
const RESIZE_CROP: u8 = 1;

fn encode_cnn(w: &mut Writer, c: &CnnSettings) {
    let o = &c.options;
    w.str(&o.model.to_string_lossy());
    w.str(&o.layer);
    w.u32(o.input_size.0);
    w.u32(o.input_size.1);
    match o.resize {
        CnnResize::Stretch => w.u8(RESIZE_STRETCH),
        CnnResize::ShortSideCrop { short_side } => {
            w.u8(RESIZE_CROP);
            w.u32(short_side);
        }
    }
    for v in o.mean.iter().chain(&o.scale) {
        w.u32(v.to_bits());
    }
    w.str(&c.identity.sha256);
    w.str(&c.identity.layer);
    w.str(&c.identity.preprocessing);
}

fn decode_cnn(r: &mut Reader<'_>) -> Result<CnnSettings, StoreError> {
    let model = std::path::PathBuf::from(r.str()?);
    let layer = r.str()?;
    let input_size = (r.u32()?, r.u32()?);
    let resize = match r.u8()? {
        RESIZE_STRETCH => CnnResize::Stretch,
        RESIZE_CROP => CnnResize::ShortSideCrop {
            short_side: r.u32()?,
        },
        t => {
            return Err(StoreError::corrupt(
                r.key,
                format!("bad CNN resize tag {t}"),
            ))
        }
    };
    let mut rgb = || -> Result<[f32; 3], StoreError> {
        Ok([
            f32::from_bits(r.u32()?),
            f32::from_bits(r.u32()?),
            f32::from_bits(r.u32()?),
        ])
    };
    let mean = rgb()?;
    let scale = rgb()?;
    let identity = ModelIdentity {
        sha256: r.str()?,
        layer: r.str()?,
        preprocessing: r.str()?,
    };
    Ok(CnnSettings {
        options: CnnOptions {
            model,
            layer,
            input_size,
            resize,
            mean,
            scale,
        },
        identity,
    })
}

/// Encodes a map record.
pub fn encode_map(m: &MapRecord) -> Vec<u8> {
    let mut w = Writer::new();
    w.u64(m.id);
    w.str(&m.name);
    match m.descriptor {
        DescriptorSettings::Hog { cell_size, resize } => {
            w.u8(KIND_HOG);
            w.u32(cell_size);
            match resize {
                None => w.u8(0),
                Some((rw, rh)) => {
                    w.u8(1);
                    w.u32(rw);
                    w.u32(rh);
                }
            }
        }
        DescriptorSettings::Precomputed { dim } => {
            w.u8(KIND_PRECOMPUTED);
            w.u32(dim);
        }
        DescriptorSettings::Cnn(ref c) => {
            w.u8(KIND_CNN);
            encode_cnn(&mut w, c);
        }
        DescriptorSettings::Cooc(ref p) => {
            w.u8(KIND_COOC);
            encode_cooc(&mut w, p);
        }
    }
    match m.dim {
        None => w.u8(0),
        Some(d) => {
            w.u8(1);
            w.u32(d);
        }
    }
    w.u32(m.image_count);
    w.u64(m.created_ms);
    w.into_bytes()
}

/// Decodes a map record stored under `key`.
pub fn decode_map(key: &[u8], value: &[u8]) -> Result<MapRecord, StoreError> {
    let mut r = Reader::new(key, value)?;
    let id = r.u64()?;
    let name = r.str()?;
    let descriptor = match r.u8()? {
        KIND_HOG => {
            let cell_size = r.u32()?;
            let resize = match r.u8()? {
                0 => None,
                _ => Some((r.u32()?, r.u32()?)),
            };
            DescriptorSettings::Hog { cell_size, resize }
        }
        KIND_PRECOMPUTED => DescriptorSettings::Precomputed { dim: r.u32()? },
        KIND_CNN => DescriptorSettings::Cnn(Box::new(decode_cnn(&mut r)?)),
        KIND_COOC => DescriptorSettings::Cooc(Box::new(decode_cooc(&mut r)?)),
        k => {
            return Err(StoreError::corrupt(
                key,
                format!("unknown descriptor kind {k}"),
            ))
        }
    };
    let dim = match r.u8()? {
        0 => None,
        _ => Some(r.u32()?),
    };
    let image_count = r.u32()?;
    let created_ms = r.u64()?;
    r.finish()?;
    Ok(MapRecord {
        id,
        name,
        descriptor,
        dim,
        image_count,
        created_ms,
    })
}

/// Encodes an image record: metadata, then the descriptor as raw little-endian `f32`.
pub fn encode_image(descriptor: &[f32], meta: &ImageMeta) -> Vec<u8> {
    let mut w = Writer::new();
    w.opt_str(meta.timestamp.as_deref());
    w.opt_f64(meta.latitude);
    w.opt_f64(meta.longitude);
    w.opt_str(meta.label.as_deref());
    w.u32(u32::try_from(descriptor.len()).expect("descriptor lengths are validated"));
    w.f32s(descriptor);
    w.into_bytes()
}

/// Decodes an image record's metadata and appends its descriptor to `out`.
pub fn decode_image_into(
    key: &[u8],
    value: &[u8],
    out: &mut Vec<f32>,
) -> Result<ImageMeta, StoreError> {
    let mut r = Reader::new(key, value)?;
    let meta = ImageMeta {
        timestamp: r.opt_str()?,
        latitude: r.opt_f64()?,
        longitude: r.opt_f64()?,
        label: r.opt_str()?,
    };
    let n = r.u32()? as usize;
    let raw = r.take(n * 4)?;
    out.extend(
        raw.chunks_exact(4)
            .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]])),
    );
    r.finish()?;
    Ok(meta)
}

/// Encodes a localization record: ids and time, then the document's JSON
/// ([`LocalizationDocument::to_json`]).
pub fn encode_localization(l: &LocalizationRecord) -> Result<Vec<u8>, StoreError> {
    let mut w = Writer::new();
    w.u64(l.id);
    w.u64(l.map_id);
    w.u64(l.created_ms);
    w.bytes(&l.document.to_json()?);
    Ok(w.into_bytes())
}

/// The stored code of a trip status (0: no batch yet).
fn status_code(s: Option<TripStatus>) -> u8 {
    match s {
        None => 0,
        Some(TripStatus::Localized) => 1,
        Some(TripStatus::Lost) => 2,
        Some(TripStatus::Relocalized) => 3,
    }
}

fn status_of(key: &[u8], code: u8) -> Result<Option<TripStatus>, StoreError> {
    match code {
        0 => Ok(None),
        1 => Ok(Some(TripStatus::Localized)),
        2 => Ok(Some(TripStatus::Lost)),
        3 => Ok(Some(TripStatus::Relocalized)),
        c => Err(StoreError::corrupt(key, format!("unknown trip status {c}"))),
    }
}

/// Encodes a trip record (its parameters as [`TripParamsDocument::to_json`]).
pub fn encode_trip(t: &TripRecord) -> Result<Vec<u8>, StoreError> {
    let mut w = Writer::new();
    w.u64(t.id);
    w.u64(t.map_id);
    w.u64(t.created_ms);
    match t.closed_ms {
        None => w.u8(0),
        Some(ms) => {
            w.u8(1);
            w.u64(ms);
        }
    }
    w.u64(t.frame_count);
    w.u32(t.reference_count);
    w.u8(status_code(t.status));
    w.bytes(&t.params.to_json()?);
    Ok(w.into_bytes())
}

/// Decodes a trip record.
pub fn decode_trip(key: &[u8], value: &[u8]) -> Result<TripRecord, StoreError> {
    let mut r = Reader::new(key, value)?;
    let id = r.u64()?;
    let map_id = r.u64()?;
    let created_ms = r.u64()?;
    let closed_ms = match r.u8()? {
        0 => None,
        1 => Some(r.u64()?),
        t => return Err(StoreError::corrupt(key, format!("bad option tag {t}"))),
    };
    let frame_count = r.u64()?;
    let reference_count = r.u32()?;
    let status = status_of(key, r.u8()?)?;
    let params = TripParamsDocument::from_json(key, r.bytes()?)?;
    r.finish()?;
    Ok(TripRecord {
        id,
        map_id,
        created_ms,
        closed_ms,
        frame_count,
        reference_count,
        status,
        params,
    })
}

/// Encodes a frame's estimate.
pub fn encode_frame(f: &FrameRecord) -> Vec<u8> {
    let mut w = Writer::new();
    match f.reference {
        None => w.u8(0),
        Some(j) => {
            w.u8(1);
            w.u32(j);
        }
    }
    w.f64(f.confidence);
    w.into_bytes()
}

/// Decodes a frame's estimate stored under `key` (the frame index comes from the key).
pub fn decode_frame(key: &[u8], value: &[u8]) -> Result<FrameRecord, StoreError> {
    let frame = key
        .get(9..13)
        .and_then(|b| b.try_into().ok())
        .map(u32::from_be_bytes)
        .ok_or_else(|| StoreError::corrupt(key, "key too short for a frame"))?;
    let mut r = Reader::new(key, value)?;
    let reference = match r.u8()? {
        0 => None,
        1 => Some(r.u32()?),
        t => return Err(StoreError::corrupt(key, format!("bad option tag {t}"))),
    };
    let confidence = r.f64()?;
    r.finish()?;
    Ok(FrameRecord {
        frame,
        reference,
        confidence,
    })
}

/// The id and map id of a localization record, without decoding its document.
pub fn decode_localization_ids(key: &[u8], value: &[u8]) -> Result<(u64, u64), StoreError> {
    let mut r = Reader::new(key, value)?;
    Ok((r.u64()?, r.u64()?))
}

/// Decodes a localization record.
pub fn decode_localization(key: &[u8], value: &[u8]) -> Result<LocalizationRecord, StoreError> {
    let mut r = Reader::new(key, value)?;
    let id = r.u64()?;
    let map_id = r.u64()?;
    let created_ms = r.u64()?;
    let document = LocalizationDocument::from_json(key, r.bytes()?)?;
    r.finish()?;
    Ok(LocalizationRecord {
        id,
        map_id,
        created_ms,
        document,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn big_endian_keys_sort_numerically() {
        assert!(image_key(1, 255) < image_key(1, 256));
        assert!(image_key(1, u32::MAX) < image_key(2, 0));
        assert!(image_key(7, 3).starts_with(&images_prefix(7)));
        assert!(by_map_key(3, 10) < by_map_key(3, 11));
        assert_eq!(id_at(&map_key(42), 1).unwrap(), 42);
    }

    #[test]
    fn map_round_trip() {
        for descriptor in [
            DescriptorSettings::Hog {
                cell_size: 8,
                resize: Some((64, 32)),
            },
            DescriptorSettings::Hog {
                cell_size: 32,
                resize: None,
            },
            DescriptorSettings::Precomputed { dim: 5 },
            DescriptorSettings::Cnn(Box::new(CnnSettings {
                options: CnnOptions::efficientnet_lite0("/models/e ✓.onnx"),
                identity: ModelIdentity {
                    sha256: "ab".repeat(32),
                    layer: "block10".into(),
                    preprocessing: "224x224 RGB".into(),
                },
            })),
            DescriptorSettings::Cnn(Box::new(CnnSettings {
                options: CnnOptions {
                    resize: CnnResize::Stretch,
                    mean: [1.5, -2.0, 0.25],
                    ..CnnOptions::efficientnet_lite0("m.onnx")
                },
                identity: ModelIdentity {
                    sha256: String::new(),
                    layer: "pooled".into(),
                    preprocessing: String::new(),
                },
            })),
            DescriptorSettings::Cooc(Box::default()),
            DescriptorSettings::Cooc(Box::new(CoocParams {
                vocabulary_branching: 7,
                grid_cols: 6,
                merge_adjacent_drives: false,
                seed: u64::MAX,
                ..CoocParams::default()
            })),
        ] {
            let m = MapRecord {
                id: 9,
                name: "route 1 ✓".into(),
                descriptor: descriptor.clone(),
                dim: Some(756),
                image_count: 3,
                created_ms: 1_700_000_000_000,
            };
            assert_eq!(decode_map(b"k", &encode_map(&m)).unwrap(), m);
        }
    }

    #[test]
    fn truncated_and_trailing_values_are_corrupt() {
        let m = MapRecord {
            id: 1,
            name: "a".into(),
            descriptor: DescriptorSettings::Precomputed { dim: 2 },
            dim: None,
            image_count: 0,
            created_ms: 0,
        };
        let v = encode_map(&m);
        let err = decode_map(b"Mkey", &v[..v.len() - 1]).unwrap_err();
        assert!(err.to_string().contains("truncated"), "{err}");
        let mut long = v.clone();
        long.push(0);
        assert!(decode_map(b"Mkey", &long).is_err());
        assert!(decode_map(b"Mkey", &[]).is_err());
    }

    proptest! {
        #[test]
        fn image_round_trip(
            desc in proptest::collection::vec(-1e6f32..1e6, 0..64),
            lat in proptest::option::of(-90.0f64..90.0),
            label in proptest::option::of(".{0,12}"),
        ) {
            let meta = ImageMeta { timestamp: Some("2020-01-01T00:00:00Z".into()), latitude: lat, longitude: None, label };
            let mut out = vec![1.0];
            let back = decode_image_into(b"I", &encode_image(&desc, &meta), &mut out).unwrap();
            prop_assert_eq!(back, meta);
            prop_assert_eq!(&out[1..], &desc[..]);
        }

        #[test]
        fn localization_round_trip(
            queries in 0usize..10_000,
            cost in -1e6f64..1e6,
            confidences in proptest::collection::vec(0.0f64..1e3, 0..20),
            id in any::<u64>(),
        ) {
            use crate::store::document::{LocalizationResult, StoredParams, StoredPrediction, StoredTimings};
            let result = LocalizationResult {
                query_count: queries,
                reference_count: 3,
                params: StoredParams::new(&crate::localize::LocalizeOptions::default(), cost.abs(), None),
                total_cost: cost,
                hypotheses: Vec::new(),
                predictions: confidences
                    .iter()
                    .enumerate()
                    .map(|(k, &c)| StoredPrediction { query: k, reference: k + 1, confidence: c })
                    .collect(),
                timings: StoredTimings::default(),
                picture: None,
            };
            let document = LocalizationDocument { id, map_id: 3, created_at_ms: 4, result };
            let l = LocalizationRecord { id, map_id: 3, created_ms: 5, document };
            prop_assert_eq!(decode_localization(b"L", &encode_localization(&l).unwrap()).unwrap(), l);
        }
    }
}
