//! The one dispatch on a map's kind. A map either holds one global descriptor per image (HOG,
//! a CNN layer, or client-computed) and is localized by the flow graph
//! ([`descriptors::DescriptorMaps`]), or it is a feature co-occurrence map built from
//! its images ([`cooc::CoocMaps`]). What differs between the kinds is the small trait
//! [`MapKind`]; [`of`] is the only `match` on a map's settings in the use cases.
//!
//! Adding a kind: a variant of `model::DescriptorSettings` (with its stored encoding in the
//! engines), an arm in [`of`], and one module beside `cooc.rs` implementing [`MapKind`].

use std::ops::Range;
use std::sync::Arc;

use async_trait::async_trait;

use crate::error::AppResult;
use crate::images::{each_gray, ImageInput};
use crate::model::{DescriptorSettings, ImageMeta, MapRecord};
use crate::store::IdempotencyRecord;
use crate::App;
use seasonloc_core::cooc::{CoocMap, CoocMethod};
use seasonloc_core::localize::{Localization, LocalizeOptions};
use seasonloc_core::picture::MatrixPicture;
use seasonloc_core::Matrix;

pub(crate) mod cooc;
pub(crate) mod descriptors;

use cooc::CoocMaps;
use descriptors::DescriptorMaps;

/// What a client is about to send a map, checked before the body is read.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Upload {
    /// Reference images (`POST /v1/maps/{id}/images`).
    Images,
    /// Precomputed descriptors (`POST /v1/maps/{id}/descriptors`).
    Descriptors,
    /// A further drive of a co-occurrence map (`POST /v1/maps/{id}/drives`).
    Drive,
}

/// What the use cases do differently per kind of map.
#[async_trait]
pub(crate) trait MapKind: Send + Sync {
    /// Fails (`map_kind`) unless a map of this kind takes `upload`.
    fn accepts(&self, map: &MapRecord, upload: Upload) -> AppResult<()>;

    /// Appends a batch of reference images (one metadata entry each, counts checked) to
    /// `map`, storing `idempotency` in the same write.
    async fn append_images(
        &self,
        app: &App,
        map: MapRecord,
        images: Vec<ImageInput>,
        metas: Vec<ImageMeta>,
        idempotency: Option<IdempotencyRecord>,
    ) -> AppResult<AppendOutcome>;

    /// Localizes `queries` against `map` (the CPU work, before anything is stored).
    async fn localize(
        &self,
        app: &App,
        map: MapRecord,
        queries: Queries,
        options: &LocalizeOptions,
        method: Option<CoocMethod>,
    ) -> AppResult<Computed>;

    /// The prior column means of a new trip on `map`.
    async fn trip_prior(&self, app: &App, map: &MapRecord) -> AppResult<Arc<Vec<f32>>>;

    /// Where a trip's rows come from: the first `reference_count` references of `map`.
    async fn trip_rows(
        &self,
        app: &App,
        map: &MapRecord,
        reference_count: u32,
    ) -> AppResult<RowSource>;
}

/// The kind of `map`.
pub(crate) fn of(map: &MapRecord) -> &'static dyn MapKind {
    match &map.descriptor {
        DescriptorSettings::Cooc(_) => &CoocMaps,
        DescriptorSettings::Hog { .. }
        | DescriptorSettings::Precomputed { .. }
        | DescriptorSettings::Cnn(_) => &DescriptorMaps,
    }
}

/// What a localization computed, before it is stored: the result and what it cost.
pub(crate) struct Computed {
    /// Hypotheses and predictions.
    pub localization: Localization,
    /// Seconds reading the map (descriptors or co-occurrence map).
    pub load_references: f64,
    /// Seconds decoding and describing the queries.
    pub features: f64,
    /// Number of queries.
    pub query_count: usize,
    /// The co-occurrence method used (co-occurrence maps only).
    pub method: Option<CoocMethod>,
    /// The similarity-matrix picture and its PNG (maps with a similarity matrix only).
    pub picture: Option<(MatrixPicture, Vec<u8>)>,
}

/// The queries of a localization, in driving order.
#[derive(Clone, Debug)]
pub enum Queries {
    /// Images, described with the map's settings.
    Images(Vec<ImageInput>),
    /// Precomputed descriptors, one row per query.
    Descriptors(Matrix),
}

/// The name the service's clients use for a method (`params.method`): `flow`, `cooc`,
/// `cooc-seq` (the CLI says `cooc-flow` for the first).
pub fn service_name(m: CoocMethod) -> &'static str {
    match m {
        CoocMethod::Flow => "flow",
        CoocMethod::Single => "cooc",
        CoocMethod::Sequence => "cooc-seq",
    }
}

/// The result of an append.
#[derive(Clone, Debug, PartialEq)]
pub struct AppendOutcome {
    /// Route indices given to the new images.
    pub indices: Range<u32>,
    /// Seconds spent decoding and describing the images (none for descriptors).
    pub features_seconds: Option<f64>,
    /// Seconds of the store write, when it was a separate stage.
    pub store_seconds: Option<f64>,
    /// Whether this is the stored answer of an earlier request with the same idempotency key
    /// (nothing was appended).
    pub replayed: bool,
}

/// Where a trip's similarity rows come from: the map's reference descriptors (cosine rows), or
/// its co-occurrence model (score rows `s + 1`, as `cooc-flow` offline). Either feeds the same
/// online graph ([`seasonloc_core::trip::Trip::push_batch`]).
pub(crate) enum RowSource {
    /// Reference descriptors of a HOG/CNN map, L2-normalised
    /// ([`seasonloc_core::similarity::l2_normalized_rows`]).
    Descriptors(Arc<Matrix>),
    /// The decoded co-occurrence map.
    Cooc(Box<CoocMap>),
}

impl RowSource {
    /// The rows of a batch of frames on a co-occurrence map: quantised with its vocabulary and
    /// scored against every location ([`CoocMap::trip_rows`]).
    pub(crate) fn cooc_rows(
        map: &CoocMap,
        frames: &[ImageInput],
        max_pixels: u64,
    ) -> AppResult<Matrix> {
        // Each frame is decoded, quantised and dropped in turn (no batch held decoded).
        let words = each_gray(frames, max_pixels, |p, gray| {
            Ok(map.quantize(&p.name, gray)?)
        })?;
        Ok(map.trip_rows(&words))
    }
}
