//! Wire types of the API (JSON request and response bodies) and their conversions from and to
//! the use cases' types (store records, core types). Only this layer knows the wire format:
//! core types and stored documents can change without changing it, and the reverse.
//!
//! Ids are 16 lowercase hex digits (the store's `u64`, so they sort by creation time).

use serde::{Deserialize, Serialize};

use super::cooc::CoocMethodDto;
use super::error::ApiError;
use crate::features::cnn::CnnResize;
use crate::localize::LocalizeOptions;
use crate::similarity::Normalization;
use crate::solver::{HiddenCost, SolverParams};
use crate::store::document::{
    HiddenCostMode, StoredHypothesis, StoredMethod, StoredParams, StoredPrediction, StoredTimings,
};
use crate::store::{DescriptorSettings, ImageMeta, LocalizationDocument, MapRecord};

/// Formats a store id for the wire.
pub fn format_id(id: u64) -> String {
    format!("{id:016x}")
}

/// Parses a wire id; `None` when it cannot be an id (callers answer 404).
pub fn parse_id(s: &str) -> Option<u64> {
    if s.len() == 16
        && s.bytes()
            .all(|b| b.is_ascii_digit() || (b'a'..=b'f').contains(&b))
    {
        u64::from_str_radix(s, 16).ok()
    } else {
        None
    }
}

/// Longest accepted map name, in bytes.
pub const MAX_NAME_BYTES: usize = 200;
/// Longest accepted metadata string (timestamp, label), in bytes.
pub const MAX_META_BYTES: usize = 256;
/// Largest accepted precomputed descriptor length.
pub const MAX_DESCRIPTOR_DIM: u32 = 1 << 20;

fn default_cell_size() -> u32 {
    32
}

/// Descriptor settings of a map, as sent and returned.
#[derive(Clone, Debug, PartialEq, Deserialize, Serialize)]
#[serde(tag = "kind", rename_all = "lowercase", deny_unknown_fields)]
pub enum DescriptorDto {
    /// HOG (`cell_size` pixels per cell side, optional `resize: [width, height]`).
    Hog {
        /// Cell side in pixels (default 32).
        #[serde(default = "default_cell_size")]
        cell_size: u32,
        /// Resize to `[width, height]` before extraction.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        resize: Option<[u32; 2]>,
    },
    /// One layer of an ONNX model on the server (`docs/cnn.md`). Unset preprocessing fields
    /// take the shipped EfficientNet-Lite0 README's values (224x224, short side 256 + centre
    /// crop, `(x - 127) / 128`); in answers every field is set and `identity` is added.
    Cnn {
        /// Model path on the server (default: the server's `--cnn-model`).
        #[serde(default, skip_serializing_if = "Option::is_none")]
        model: Option<String>,
        /// Output (or node) name used as descriptor, e.g. `block10`.
        layer: String,
        /// Network input `[width, height]` (default `[224, 224]`).
        #[serde(default, skip_serializing_if = "Option::is_none")]
        input_size: Option<[u32; 2]>,
        /// `crop` (scale the short side to `short_side`, cut the centre; default) or `stretch`.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        resize: Option<CnnResizeDto>,
        /// Short side before the centre crop (default 256/224 of the larger input side).
        #[serde(default, skip_serializing_if = "Option::is_none")]
        short_side: Option<u32>,
        /// Per-channel R, G, B mean subtracted from 0..255 pixels (default 127 each).
        #[serde(default, skip_serializing_if = "Option::is_none")]
        mean: Option<[f32; 3]>,
        /// Per-channel R, G, B divisor after the mean (default 128 each).
        #[serde(default, skip_serializing_if = "Option::is_none")]
        scale: Option<[f32; 3]>,
        /// What the model was at creation (set by the server; rejected in requests).
        #[serde(default, skip_serializing_if = "Option::is_none")]
        identity: Option<ModelIdentityDto>,
    },
    /// A feature co-occurrence map (`docs/cooc.md`): built from the first batch of reference
    /// images, further drives added with `POST /v1/maps/{id}/drives`. Unset fields keep the
    /// library defaults; answers set every field.
    Cooc {
        /// Branching factor of the vocabulary tree (default 16).
        #[serde(default, skip_serializing_if = "Option::is_none")]
        vocabulary_branching: Option<usize>,
        /// Depth of the vocabulary tree (default 2: 256 words).
        #[serde(default, skip_serializing_if = "Option::is_none")]
        vocabulary_depth: Option<usize>,
        /// Upsampling before corner detection (default 2).
        #[serde(default, skip_serializing_if = "Option::is_none")]
        upsample: Option<u32>,
        /// Keypoints kept per image (default 80).
        #[serde(default, skip_serializing_if = "Option::is_none")]
        max_keypoints: Option<usize>,
        /// Spatial grid `[columns, rows]` (default `[12, 8]`).
        #[serde(default, skip_serializing_if = "Option::is_none")]
        grid: Option<[u16; 2]>,
        /// Tolerated grid-offset difference in cells (default 1).
        #[serde(default, skip_serializing_if = "Option::is_none")]
        spatial_tolerance: Option<u16>,
        /// Merge drives adjacent in time (default true).
        #[serde(default, skip_serializing_if = "Option::is_none")]
        merge_adjacent_drives: Option<bool>,
        /// Seed of the vocabulary's k-means.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        seed: Option<u64>,
    },
    /// Descriptors computed by the client, of length `dim`.
    Precomputed {
        /// Descriptor length.
        dim: u32,
    },
}

/// How a CNN map brings images to the network's input size.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Deserialize, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum CnnResizeDto {
    /// Scale the whole image to the input size.
    Stretch,
    /// Scale the short side, then cut the centred input-size window.
    Crop,
}

/// The model a CNN map was created with.
#[derive(Clone, Debug, PartialEq, Eq, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct ModelIdentityDto {
    /// Lower-case hex sha256 of the ONNX file.
    pub sha256: String,
    /// The layer used as descriptor.
    pub layer: String,
    /// One-line summary of the preprocessing.
    pub preprocessing: String,
}

impl Default for DescriptorDto {
    fn default() -> Self {
        DescriptorDto::Hog {
            cell_size: default_cell_size(),
            resize: None,
        }
    }
}

impl From<DescriptorSettings> for DescriptorDto {
    fn from(d: DescriptorSettings) -> Self {
        match d {
            DescriptorSettings::Hog { cell_size, resize } => DescriptorDto::Hog {
                cell_size,
                resize: resize.map(|(w, h)| [w, h]),
            },
            DescriptorSettings::Precomputed { dim } => DescriptorDto::Precomputed { dim },
            DescriptorSettings::Cooc(p) => DescriptorDto::Cooc {
                vocabulary_branching: Some(p.vocabulary_branching),
                vocabulary_depth: Some(p.vocabulary_depth),
                upsample: Some(p.keypoints.upsample),
                max_keypoints: Some(p.keypoints.max_keypoints),
                grid: Some([p.grid_cols, p.grid_rows]),
                spatial_tolerance: Some(p.spatial_tolerance),
                merge_adjacent_drives: Some(p.merge_adjacent_drives),
                seed: Some(p.seed),
            },
            DescriptorSettings::Cnn(c) => {
                let o = c.options;
                let (resize, short_side) = match o.resize {
                    CnnResize::Stretch => (CnnResizeDto::Stretch, None),
                    CnnResize::ShortSideCrop { short_side } => {
                        (CnnResizeDto::Crop, Some(short_side))
                    }
                };
                DescriptorDto::Cnn {
                    model: Some(o.model.to_string_lossy().into_owned()),
                    layer: o.layer,
                    input_size: Some([o.input_size.0, o.input_size.1]),
                    resize: Some(resize),
                    short_side,
                    mean: Some(o.mean),
                    scale: Some(o.scale),
                    identity: Some(ModelIdentityDto {
                        sha256: c.identity.sha256,
                        layer: c.identity.layer,
                        preprocessing: c.identity.preprocessing,
                    }),
                }
            }
        }
    }
}

/// `POST /v1/maps` body.
#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CreateMapRequest {
    /// Name, 1..=200 bytes.
    pub name: String,
    /// Descriptor settings (default HOG with 32-pixel cells).
    #[serde(default)]
    pub descriptor: DescriptorDto,
}

/// A map as returned by the API.
#[derive(Clone, Debug, Serialize)]
pub struct MapResponse {
    /// Map id.
    pub id: String,
    /// Name.
    pub name: String,
    /// Descriptor settings.
    pub descriptor: DescriptorDto,
    /// Descriptor length, known after the first batch (or at creation for precomputed).
    pub descriptor_dim: Option<u32>,
    /// Number of reference images.
    pub image_count: u32,
    /// Creation time, milliseconds since the Unix epoch.
    pub created_at_ms: u64,
}

impl From<MapRecord> for MapResponse {
    fn from(m: MapRecord) -> Self {
        MapResponse {
            id: format_id(m.id),
            name: m.name,
            descriptor: m.descriptor.into(),
            descriptor_dim: m.dim,
            image_count: m.image_count,
            created_at_ms: m.created_ms,
        }
    }
}

/// `GET /v1/maps` body.
#[derive(Clone, Debug, Serialize)]
pub struct MapListResponse {
    /// All maps, oldest first.
    pub maps: Vec<MapResponse>,
}

/// Optional metadata of one reference image.
#[derive(Clone, Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ImageMetaDto {
    /// Capture time, free-form (e.g. RFC 3339), at most 256 bytes.
    pub timestamp: Option<String>,
    /// Latitude in degrees, -90..=90.
    pub latitude: Option<f64>,
    /// Longitude in degrees, -180..=180.
    pub longitude: Option<f64>,
    /// Free-form label, at most 256 bytes.
    pub label: Option<String>,
}

impl ImageMetaDto {
    /// Validates entry `index` of a batch's metadata.
    pub fn validate(self, index: usize) -> Result<ImageMeta, ApiError> {
        let name = |f: &str| format!("metadata[{index}].{f}");
        for (field, v) in [("timestamp", &self.timestamp), ("label", &self.label)] {
            if v.as_ref().is_some_and(|s| s.len() > MAX_META_BYTES) {
                return Err(ApiError::param(
                    name(field),
                    format!("must be at most {MAX_META_BYTES} bytes"),
                ));
            }
        }
        if let Some(lat) = self.latitude {
            if !(-90.0..=90.0).contains(&lat) {
                return Err(ApiError::param(
                    name("latitude"),
                    format!("must be within [-90, 90], got {lat}"),
                ));
            }
        }
        if let Some(lon) = self.longitude {
            if !(-180.0..=180.0).contains(&lon) {
                return Err(ApiError::param(
                    name("longitude"),
                    format!("must be within [-180, 180], got {lon}"),
                ));
            }
        }
        Ok(ImageMeta {
            timestamp: self.timestamp,
            latitude: self.latitude,
            longitude: self.longitude,
            label: self.label,
        })
    }
}

/// `POST /v1/maps/{id}/descriptors` JSON body.
#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AppendDescriptorsRequest {
    /// One descriptor per reference image, in route order.
    pub descriptors: Vec<Vec<f64>>,
    /// Optional metadata, one entry per descriptor.
    #[serde(default)]
    pub metadata: Option<Vec<ImageMetaDto>>,
}

/// Answer of an append: the indices given to the new images.
#[derive(Clone, Debug, Serialize)]
pub struct AppendResponse {
    /// Route indices of the appended images, in order.
    pub indices: Vec<u32>,
    /// The map's image count after the append.
    pub image_count: u32,
}

/// Optional parameters of a localization (part `params` or field `params`).
#[derive(Clone, Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LocalizeParams {
    /// `K`, fan-out (default 4).
    pub fan_out: Option<usize>,
    /// `W`: a number > 0 or `"auto"` (default).
    pub hidden_cost: Option<serde_json::Value>,
    /// `F`, number of route hypotheses (default 1).
    pub flows: Option<usize>,
    /// Exact min-cost flow instead of greedy for `F > 1` (default false).
    pub exact: Option<bool>,
    /// Horizontal edges (default true).
    pub horizontal: Option<bool>,
    /// Column normalisation of Eq. 2 (default true).
    pub normalize: Option<bool>,
    /// Stop adding flows once a path's hidden fraction exceeds this (default none).
    pub stop_hidden_fraction: Option<f64>,
    /// `cooc` maps only: `flow` (default), `cooc` or `cooc-seq`.
    pub method: Option<CoocMethodDto>,
}

impl LocalizeParams {
    /// Parses a `params` part; unknown fields and wrong types are 400 `invalid_parameter`.
    pub fn from_json(bytes: &[u8]) -> Result<Self, ApiError> {
        super::extract::parse_json(bytes, Some("params"))
    }

    /// Resolves defaults and validates every range.
    pub fn into_options(self) -> Result<LocalizeOptions, ApiError> {
        let defaults = SolverParams::default();
        let hidden_cost = match self.hidden_cost {
            None => defaults.hidden_cost,
            Some(serde_json::Value::String(s)) if s == "auto" => HiddenCost::Auto,
            Some(serde_json::Value::Number(n)) => match n.as_f64() {
                Some(w) => HiddenCost::Fixed(w),
                None => {
                    return Err(ApiError::param(
                        "hidden_cost",
                        format!("{n} is not a number"),
                    ))
                }
            },
            Some(other) => {
                return Err(ApiError::param(
                    "hidden_cost",
                    format!("must be a number > 0 or \"auto\", got {other}"),
                ))
            }
        };
        let solver = SolverParams {
            fan_out: self.fan_out.unwrap_or(defaults.fan_out),
            hidden_cost,
            flows: self.flows.unwrap_or(defaults.flows),
            exact: self.exact.unwrap_or(defaults.exact),
            horizontal: self.horizontal.unwrap_or(defaults.horizontal),
            stop_hidden_fraction: self.stop_hidden_fraction.or(defaults.stop_hidden_fraction),
        };
        solver.validate()?;
        // `normalize: true` (the default) is the library's default normalisation, Eq. 2 with
        // a floored column mean; `false` keeps raw cosine similarities.
        let normalization = if self.normalize.unwrap_or(true) {
            Normalization::default()
        } else {
            Normalization::None
        };
        Ok(LocalizeOptions {
            solver,
            normalization,
            ..LocalizeOptions::default()
        })
    }
}

/// `POST /v1/maps/{id}/localize` JSON body (queries as precomputed descriptors).
#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LocalizeDescriptorsRequest {
    /// One descriptor per query, in driving order.
    pub descriptors: Vec<Vec<f64>>,
    /// Optional parameters.
    #[serde(default)]
    pub params: LocalizeParams,
}

/// The parameters a localization actually used.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct ParamsUsed {
    /// `K`.
    pub fan_out: usize,
    /// `"auto"` or `"fixed"`.
    pub hidden_cost_mode: String,
    /// `W` actually used (resolved when auto).
    pub hidden_cost: f64,
    /// `F`.
    pub flows: usize,
    /// Exact min-cost flow.
    pub exact: bool,
    /// Horizontal edges.
    pub horizontal: bool,
    /// Column normalisation.
    pub normalize: bool,
    /// Stopping rule.
    pub stop_hidden_fraction: Option<f64>,
    /// The method of a `cooc` map (absent for other maps).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub method: Option<CoocMethodDto>,
}

impl From<&StoredParams> for ParamsUsed {
    fn from(p: &StoredParams) -> Self {
        ParamsUsed {
            fan_out: p.fan_out,
            hidden_cost_mode: match p.hidden_cost_mode {
                HiddenCostMode::Auto => "auto".into(),
                HiddenCostMode::Fixed => "fixed".into(),
            },
            hidden_cost: p.hidden_cost,
            flows: p.flows,
            exact: p.exact,
            horizontal: p.horizontal,
            normalize: p.normalize,
            stop_hidden_fraction: p.stop_hidden_fraction,
            method: p.method.map(|m| match m {
                StoredMethod::Flow => CoocMethodDto::Flow,
                StoredMethod::Cooc => CoocMethodDto::Cooc,
                StoredMethod::CoocSeq => CoocMethodDto::CoocSeq,
            }),
        }
    }
}

/// One matched reference in a hypothesis row.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct MatchDto {
    /// Reference index.
    #[serde(rename = "ref")]
    pub reference: usize,
    /// `ĉ` of the matching node.
    pub similarity: f32,
}

/// One row of a hypothesis.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct RowDto {
    /// Query index.
    pub query: usize,
    /// Matches (empty = hidden).
    pub matches: Vec<MatchDto>,
}

/// A route hypothesis.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct HypothesisDto {
    /// 1-based rank.
    pub rank: usize,
    /// Path cost.
    pub cost: f64,
    /// One entry per query.
    pub rows: Vec<RowDto>,
}

impl From<&StoredHypothesis> for HypothesisDto {
    fn from(h: &StoredHypothesis) -> Self {
        HypothesisDto {
            rank: h.rank,
            cost: h.cost,
            rows: h
                .rows
                .iter()
                .map(|r| RowDto {
                    query: r.query,
                    matches: r
                        .matches
                        .iter()
                        .map(|m| MatchDto {
                            reference: m.reference,
                            similarity: m.similarity,
                        })
                        .collect(),
                })
                .collect(),
        }
    }
}

/// A per-query prediction.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct PredictionDto {
    /// Query index.
    pub query: usize,
    /// Predicted reference index.
    #[serde(rename = "ref")]
    pub reference: usize,
    /// Higher = more certain.
    pub confidence: f64,
}

impl From<&StoredPrediction> for PredictionDto {
    fn from(p: &StoredPrediction) -> Self {
        PredictionDto {
            query: p.query,
            reference: p.reference,
            confidence: p.confidence,
        }
    }
}

/// Seconds per stage of a localization.
#[derive(Clone, Copy, Debug, Default, Serialize, Deserialize, PartialEq)]
pub struct TimingsDto {
    /// Reading the map's reference descriptors.
    pub load_references: f64,
    /// Decoding query images and extracting their descriptors (0 for descriptor queries).
    pub features: f64,
    /// Similarity matrix and normalisation.
    pub similarity: f64,
    /// Graph solver and confidences.
    pub solve: f64,
}

impl From<&StoredTimings> for TimingsDto {
    fn from(t: &StoredTimings) -> Self {
        TimingsDto {
            load_references: t.load_references,
            features: t.features,
            similarity: t.similarity,
            solve: t.solve,
        }
    }
}

/// A stored localization result (the answer of `POST /v1/maps/{id}/localize`).
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct LocalizationResponse {
    /// Localization id.
    pub id: String,
    /// The map.
    pub map_id: String,
    /// Creation time, milliseconds since the Unix epoch.
    pub created_at_ms: u64,
    /// Number of query images.
    pub query_count: usize,
    /// Number of reference images used.
    pub reference_count: usize,
    /// Parameters used.
    pub params: ParamsUsed,
    /// Sum of the hypotheses' costs.
    pub total_cost: f64,
    /// Ranked route hypotheses.
    pub hypotheses: Vec<HypothesisDto>,
    /// At most one prediction per query.
    pub predictions: Vec<PredictionDto>,
    /// Seconds per stage.
    pub timings: TimingsDto,
    /// What the similarity picture (`GET /v1/localizations/{id}/picture`) shows; absent when
    /// the result has none.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub picture: Option<PictureDto>,
}

/// The similarity-matrix picture of a localization: `rows` x `cols` grey pixels, each the
/// largest normalised similarity of its block of queries x references, `lo` black and `hi`
/// white.
#[derive(Clone, Copy, Debug, Serialize, Deserialize, PartialEq)]
pub struct PictureDto {
    /// Height in pixels (blocks of queries).
    pub rows: usize,
    /// Width in pixels (blocks of references).
    pub cols: usize,
    /// Similarity shown black (and below).
    pub lo: f32,
    /// Similarity shown white (and above).
    pub hi: f32,
}

impl From<&LocalizationDocument> for LocalizationResponse {
    fn from(d: &LocalizationDocument) -> Self {
        let r = &d.result;
        LocalizationResponse {
            id: format_id(d.id),
            map_id: format_id(d.map_id),
            created_at_ms: d.created_at_ms,
            query_count: r.query_count,
            reference_count: r.reference_count,
            params: ParamsUsed::from(&r.params),
            total_cost: r.total_cost,
            hypotheses: r.hypotheses.iter().map(HypothesisDto::from).collect(),
            predictions: r.predictions.iter().map(PredictionDto::from).collect(),
            timings: TimingsDto::from(&r.timings),
            picture: r.picture.map(|p| PictureDto {
                rows: p.rows,
                cols: p.cols,
                lo: p.lo,
                hi: p.hi,
            }),
        }
    }
}

/// `GET /v1/localizations` body.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct LocalizationListResponse {
    /// Results, newest first.
    pub items: Vec<LocalizationResponse>,
    /// Pass as `before` for the next page; null on the last page.
    pub next: Option<String>,
}

/// Health answer.
#[derive(Clone, Debug, Serialize)]
pub struct StatusResponse {
    /// `ok` or `ready`.
    pub status: &'static str,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ids_round_trip_and_reject_garbage() {
        assert_eq!(parse_id(&format_id(0xdead_beef)), Some(0xdead_beef));
        for bad in [
            "",
            "123",
            "000000000000000G",
            "00000000000000FF",
            "0000000000000000a",
        ] {
            assert_eq!(parse_id(bad), None, "{bad}");
        }
    }

    #[test]
    fn descriptor_defaults_to_hog_32() {
        let r: CreateMapRequest = serde_json::from_str(r#"{"name": "a"}"#).unwrap();
        assert_eq!(
            r.descriptor,
            DescriptorDto::Hog {
                cell_size: 32,
                resize: None
            }
        );
        let r: CreateMapRequest =
            serde_json::from_str(r#"{"name": "a", "descriptor": {"kind": "hog", "cell_size": 8}}"#)
                .unwrap();
        assert_eq!(
            r.descriptor,
            DescriptorDto::Hog {
                cell_size: 8,
                resize: None
            }
        );
        let err = serde_json::from_str::<CreateMapRequest>(
            r#"{"name": "a", "descriptor": {"kind": "hog", "cel_size": 8}}"#,
        )
        .unwrap_err();
        assert!(err.to_string().contains("cel_size"), "{err}");
    }

    #[test]
    fn params_resolve_and_validate() {
        let o = LocalizeParams::from_json(
            br#"{"fan_out": 2, "hidden_cost": 1.5, "flows": 3, "exact": true}"#,
        )
        .unwrap()
        .into_options()
        .unwrap();
        assert_eq!(o.solver.fan_out, 2);
        assert_eq!(o.solver.hidden_cost, HiddenCost::Fixed(1.5));
        assert!(
            o.solver.exact
                && o.normalization == Normalization::FlooredColumns
                && o.solver.horizontal
        );
        let auto = LocalizeParams::from_json(br#"{"hidden_cost": "auto"}"#).unwrap();
        assert_eq!(
            auto.into_options().unwrap().solver.hidden_cost,
            HiddenCost::Auto
        );
        let unknown = LocalizeParams::from_json(br#"{"fanout": 2}"#).unwrap_err();
        assert!(unknown.to_string().contains("fanout"), "{unknown}");
        let bad_w = LocalizeParams::from_json(br#"{"hidden_cost": "high"}"#)
            .unwrap()
            .into_options()
            .unwrap_err();
        assert!(bad_w.to_string().contains("hidden_cost"), "{bad_w}");
        let zero_flows = LocalizeParams::from_json(br#"{"flows": 0}"#)
            .unwrap()
            .into_options()
            .unwrap_err();
        assert!(zero_flows.to_string().contains("flows"), "{zero_flows}");
    }

    #[test]
    fn metadata_ranges_name_the_entry() {
        let m = ImageMetaDto {
            latitude: Some(91.0),
            ..ImageMetaDto::default()
        };
        let err = m.validate(3).unwrap_err();
        assert!(err.to_string().contains("metadata[3].latitude"), "{err}");
    }

    /// Every localization in the golden store (written by the pre-refactor code, whose API
    /// answered with the stored bytes) is answered today with exactly those bytes.
    #[test]
    fn stored_localizations_are_answered_byte_for_byte() {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("tests/data/store-layout4.golden");
        let text = std::fs::read_to_string(path).unwrap();
        let unhex = |h: &str| -> Vec<u8> {
            (0..h.len())
                .step_by(2)
                .map(|k| u8::from_str_radix(&h[k..k + 2], 16).unwrap())
                .collect()
        };
        let mut seen = 0;
        for line in text.lines().filter(|l| l.starts_with("4c")) {
            let (k, v) = line.split_once(' ').unwrap();
            let (k, v) = (unhex(k), unhex(v));
            let record = crate::store::sled::codec::decode_localization(&k, &v).unwrap();
            let wire = serde_json::to_vec(&LocalizationResponse::from(&record.document)).unwrap();
            // format byte, id, map id, created, length prefix, then the stored JSON
            assert_eq!(wire, &v[1 + 8 + 8 + 8 + 4..]);
            seen += 1;
        }
        assert_eq!(seen, 2);
    }
}
