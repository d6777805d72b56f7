//! Key layout and value encodings of the store.
//!
//! Everything lives in sled's default tree, under one-byte key prefixes, so one
//! `sled::Batch` can change a map and its images atomically:
//!
//! | key | value |
//! | --- | --- |
//! | `meta/schema_version` | layout version, `u32` big-endian |
//! | `meta/generation` | the generation of the newest write, `u64` big-endian (in every write batch; checked against the ledger file at start, `sled/ledger.rs`) |
//! | `M` + map id (`u64` BE) | [`MapRecord`](seasonloc_app::model::MapRecord) |
//! | `I` + map id (`u64` BE) + index (`u32` BE) | an image record ([`encode_image`]: [`ImageMeta`](seasonloc_app::model::ImageMeta), then the descriptor as raw LE `f32`) |
//! | `L` + localization id (`u64` BE) | [`LocalizationRecord`](seasonloc_app::model::LocalizationRecord) |
//! | `l` + map id (`u64` BE) + localization id (`u64` BE) | empty (index, layout >= 2) |
//! | `P` + localization id (`u64` BE) | the PNG of its similarity picture (layout >= 5) |
//! | `J` + map id (`u64` BE) + index (`u32` BE) | the image's JPEG thumbnail (layout >= 5) |
//! | `C` + map id (`u64` BE) | `CoocMap::to_bytes` of a `cooc` map (layout >= 3) |
//! | `T` + trip id (`u64` BE) | [`TripRecord`](seasonloc_app::model::TripRecord) (layout >= 4) |
//! | `S` + trip id (`u64` BE) | a trip's solver state in one blob (format 1, layouts 4-5), opaque bytes from `seasonloc_core::trip`; replaced by `b`/`s`/`r` at the trip's next batch |
//! | `b` + trip id (`u64` BE) | the trip state's base (layout >= 6; `seasonloc_core::trip::persist`) |
//! | `s` + trip id (`u64` BE) | the trip state's latest snapshot (layout >= 6) |
//! | `r` + trip id (`u64` BE) + frame (`u32` BE) | one log row of the trip state: the frame's raw cosine row (layout >= 6) |
//! | `F` + trip id (`u64` BE) + frame (`u32` BE) | [`FrameEstimate`](seasonloc_core::trip::FrameEstimate): the frame's latest estimate |
//! | `t` + map id (`u64` BE) + trip id (`u64` BE) | empty (index of a map's trips) |
//! | `K` + scope + `0x00` + key | [`IdempotencyRecord`](seasonloc_app::store::IdempotencyRecord) of a request sent with an `Idempotency-Key` (additive: older stores have none) |
//!
//! Big-endian integers make sled's lexicographic order the numeric order, so a map's images
//! iterate in route order, localizations in creation order and a trip's frames in driving
//! order. Values are a small hand-written binary format ([`seasonloc_core::codec`]) starting with a format byte; the
//! decoder rejects trailing or missing bytes, so corruption is reported rather than misread.

mod keys;
mod map;
mod records;
mod value;

pub use keys::*;
pub use map::{decode_image_into, decode_map, encode_image, encode_map};
pub use records::{
    decode_frame, decode_idempotency, decode_localization, decode_localization_ids, decode_trip,
    encode_frame, encode_idempotency, encode_localization, encode_trip, small_index,
};
