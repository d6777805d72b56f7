//! The domain model of the service: what a map, a localization and a trip are, as the use
//! cases hand them to the store and to the front ends. One set of types: the store keeps these
//! (their serde forms are the stored documents, encoded by the engines in `seasonloc-store`),
//! and the API converts them to its wire types at the edge. The algorithms' own results
//! (hypotheses, predictions, trip parameters and estimates) appear as the core's types.

use serde::{Deserialize, Serialize};

use seasonloc_core::cooc::CoocMethod;
use seasonloc_core::localize::{LocalizeOptions, Prediction};
use seasonloc_core::similarity::Normalization;
use seasonloc_core::solver::{HiddenCost, Hypothesis};
use seasonloc_core::trip::{TripParams, TripStatus};

/// How a map's descriptors are computed.
#[derive(Clone, Debug, PartialEq)]
pub enum DescriptorSettings {
    /// HOG of `features::hog` with these options.
    Hog {
        /// Cell side in pixels.
        cell_size: u32,
        /// Optional resize before extraction.
        resize: Option<(u32, u32)>,
    },
    /// Descriptors computed by the client, of a fixed length.
    Precomputed {
        /// Descriptor length.
        dim: u32,
    },
    /// One layer of an ONNX model (`features::cnn`), with the identity of the model the map
    /// was created with (layout >= 3).
    Cnn(Box<CnnSettings>),
    /// A feature co-occurrence map (`cooc`) with these parameters (layout >= 3). Its images
    /// have no descriptor rows; the encoded `CoocMap` is stored beside the map.
    Cooc(Box<seasonloc_core::cooc::CoocParams>),
}

impl DescriptorSettings {
    /// The kind's name as the API spells it: `hog`, `precomputed`, `cnn` or `cooc` (a closed
    /// set, fit for a metric label).
    pub fn kind_name(&self) -> &'static str {
        match self {
            DescriptorSettings::Hog { .. } => "hog",
            DescriptorSettings::Precomputed { .. } => "precomputed",
            DescriptorSettings::Cnn(_) => "cnn",
            DescriptorSettings::Cooc(_) => "cooc",
        }
    }
}

/// The CNN descriptor of a map: the settings to rebuild the extractor, and what the model was
/// when the map was created, so that a changed model file is detected, never silently used.
#[derive(Clone, Debug, PartialEq)]
pub struct CnnSettings {
    /// Model path, layer and preprocessing.
    pub options: seasonloc_core::features::cnn::CnnOptions,
    /// File hash, layer and preprocessing summary at creation.
    pub identity: seasonloc_core::features::cnn::ModelIdentity,
}

/// A stored map.
#[derive(Clone, Debug, PartialEq)]
pub struct MapRecord {
    /// Map id.
    pub id: u64,
    /// User-given name.
    pub name: String,
    /// Descriptor settings.
    pub descriptor: DescriptorSettings,
    /// Descriptor length, fixed by the first stored batch (or at creation for precomputed).
    pub dim: Option<u32>,
    /// Number of reference images; their indices are `0..image_count`. Images are
    /// append-only, so this is also the version of the map's descriptor matrix.
    pub image_count: u32,
    /// Creation time, milliseconds since the Unix epoch.
    pub created_ms: u64,
}

/// Optional per-image metadata.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ImageMeta {
    /// Capture time as given by the client.
    pub timestamp: Option<String>,
    /// Latitude in degrees.
    pub latitude: Option<f64>,
    /// Longitude in degrees.
    pub longitude: Option<f64>,
    /// Free-form label.
    pub label: Option<String>,
}

/// A stored localization result.
#[derive(Clone, Debug, PartialEq)]
pub struct LocalizationRecord {
    /// Localization id (growing with creation time).
    pub id: u64,
    /// The map it was computed against.
    pub map_id: u64,
    /// Creation time, milliseconds since the Unix epoch.
    pub created_ms: u64,
    /// What it computed.
    pub result: LocalizationResult,
}

/// A stored trip (its solver state is kept separately, see [`crate::store::Store::trip_state`]).
#[derive(Clone, Debug, PartialEq)]
pub struct TripRecord {
    /// Trip id (growing with creation time).
    pub id: u64,
    /// The map it localizes against.
    pub map_id: u64,
    /// Creation time, milliseconds since the Unix epoch.
    pub created_ms: u64,
    /// When it was closed, if it was.
    pub closed_ms: Option<u64>,
    /// Frames consumed so far: also the version of the trip's state (see [`crate::store::TripBatch`]).
    pub frame_count: u64,
    /// The map's image count when the trip was opened: the trip localizes against those.
    pub reference_count: u32,
    /// Status after the last batch (`None` before the first).
    pub status: Option<TripStatus>,
    /// The parameters the trip uses.
    pub params: TripParams,
    /// The name of the API key that opened it (`None` when the service ran without keys, or
    /// for a trip stored before owners were kept): only that key or an admin may post frames
    /// to it or close it.
    pub owner: Option<String>,
}

/// What a localization computed.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct LocalizationResult {
    /// Number of queries.
    pub query_count: usize,
    /// Number of reference images used.
    pub reference_count: usize,
    /// Parameters used.
    pub params: LocalizationParams,
    /// Sum of the hypotheses' costs.
    pub total_cost: f64,
    /// Ranked route hypotheses.
    pub hypotheses: Vec<Hypothesis>,
    /// At most one prediction per query.
    pub predictions: Vec<Prediction>,
    /// Seconds per stage.
    pub timings: LocalizationTimings,
    /// The similarity-matrix picture stored with the result (its PNG is a separate blob, see
    /// `Store::localization_picture`); `None` for results stored before pictures existed
    /// (layout < 5) and for methods without a similarity matrix.
    pub picture: Option<PictureInfo>,
}

/// What a localization's similarity-matrix picture shows (`seasonloc_core::picture::MatrixPicture`).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct PictureInfo {
    /// Picture height in pixels (query blocks).
    pub rows: usize,
    /// Picture width in pixels (reference blocks).
    pub cols: usize,
    /// The similarity shown black (and below).
    pub lo: f32,
    /// The similarity shown white (and above).
    pub hi: f32,
}

/// How `W` was chosen.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum HiddenCostMode {
    /// Resolved from the data.
    Auto,
    /// Given by the client.
    Fixed,
}

/// The parameters a localization used.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct LocalizationParams {
    /// `K`.
    pub fan_out: usize,
    /// `auto` or `fixed`.
    pub hidden_cost_mode: HiddenCostMode,
    /// `W` actually used.
    pub hidden_cost: f64,
    /// `F`.
    pub flows: usize,
    /// Exact min-cost flow.
    pub exact: bool,
    /// Horizontal edges.
    pub horizontal: bool,
    /// Column normalisation on.
    pub normalize: bool,
    /// Stopping rule.
    pub stop_hidden_fraction: Option<f64>,
    /// The method of a `cooc` map (absent for other maps).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub method: Option<CoocMethod>,
    /// The tolerance of the predictions' `p_correct`, when not the default of 1 (results stored
    /// before it existed have none: they have no `p_correct` either).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub tolerance: Option<usize>,
}

impl LocalizationParams {
    /// The options of a localization, `W` as resolved, and the `cooc` method if any.
    pub fn new(o: &LocalizeOptions, resolved_hidden_cost: f64, method: Option<CoocMethod>) -> Self {
        LocalizationParams {
            fan_out: o.solver.fan_out,
            hidden_cost_mode: match o.solver.hidden_cost {
                HiddenCost::Auto => HiddenCostMode::Auto,
                HiddenCost::Fixed(_) => HiddenCostMode::Fixed,
            },
            hidden_cost: resolved_hidden_cost,
            flows: o.solver.flows,
            exact: o.solver.exact,
            horizontal: o.solver.horizontal,
            normalize: o.normalization != Normalization::None,
            stop_hidden_fraction: o.solver.stop_hidden_fraction,
            method,
            tolerance: (o.tolerance != seasonloc_core::trip::DEFAULT_TOLERANCE)
                .then_some(o.tolerance),
        }
    }
}

/// Seconds per stage of a localization.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct LocalizationTimings {
    /// Reading the map (descriptors or co-occurrence map).
    pub load_references: f64,
    /// Decoding query images and describing them.
    pub features: f64,
    /// Similarity matrix and normalisation.
    pub similarity: f64,
    /// Solver and confidences.
    pub solve: f64,
}
