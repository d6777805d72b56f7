//! Stored documents: the types of what the store keeps as JSON (a localization's result, a
//! trip's parameters), and their one encoding, shared by every engine.
//!
//! These are *stored* formats, not wire formats: the API has its own DTOs and converts, so a
//! change of the HTTP contract cannot silently change stored data (and the reverse). The JSON
//! written here is byte for byte what layout 4 stores (field order, names, number formats;
//! `tests/data/store-layout4.golden` checks it): a localization document is a JSON object with
//! the localization's id and map id as 16 lowercase hex digits, then the result's fields.
//! Changing any of it is a layout change (`migrations/README.md`).

use serde::de::Error as _;
use serde::{Deserialize, Deserializer, Serialize, Serializer};

use super::{StoreError, StoreResult};
use seasonloc_core::localize::LocalizeOptions;
use seasonloc_core::localize::Prediction;
use seasonloc_core::similarity::Normalization;
use seasonloc_core::solver::{HiddenCost, Hypothesis};
use seasonloc_core::trip::TripParams;

/// A stored localization: its identity and its result, one JSON object.
#[derive(Clone, Debug, PartialEq)]
pub struct LocalizationDocument {
    /// Localization id.
    pub id: u64,
    /// The map.
    pub map_id: u64,
    /// Creation time as reported to the client, milliseconds since the Unix epoch.
    pub created_at_ms: u64,
    /// The result.
    pub result: LocalizationResult,
}

/// What a localization computed, as stored.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct LocalizationResult {
    /// Number of queries.
    pub query_count: usize,
    /// Number of reference images used.
    pub reference_count: usize,
    /// Parameters used.
    pub params: StoredParams,
    /// Sum of the hypotheses' costs.
    pub total_cost: f64,
    /// Ranked route hypotheses.
    pub hypotheses: Vec<StoredHypothesis>,
    /// At most one prediction per query.
    pub predictions: Vec<StoredPrediction>,
    /// Seconds per stage.
    pub timings: StoredTimings,
    /// The similarity-matrix picture stored with the result (its PNG is a separate blob, see
    /// `Store::localization_picture`); `None` for results stored before pictures existed
    /// (layout < 5) and for methods without a similarity matrix.
    pub picture: Option<StoredPicture>,
}

/// What a localization's similarity-matrix picture shows (`seasonloc_core::picture::MatrixPicture`).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct StoredPicture {
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

/// The co-occurrence method a localization of a `cooc` map used.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum StoredMethod {
    /// Co-occurrence scores in the flow graph.
    Flow,
    /// Single-image recognition.
    Cooc,
    /// Sequence matching.
    CoocSeq,
}

/// The parameters a localization used.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct StoredParams {
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
    pub method: Option<StoredMethod>,
}

impl StoredParams {
    /// The options of a localization, `W` as resolved, and the `cooc` method if any.
    pub fn new(
        o: &LocalizeOptions,
        resolved_hidden_cost: f64,
        method: Option<StoredMethod>,
    ) -> Self {
        StoredParams {
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
        }
    }
}

/// One matched reference of a hypothesis row.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct StoredMatch {
    /// Reference index.
    #[serde(rename = "ref")]
    pub reference: usize,
    /// `ĉ` of the matching node.
    pub similarity: f32,
}

/// One row of a hypothesis.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct StoredRow {
    /// Query index.
    pub query: usize,
    /// Matches (empty = hidden).
    pub matches: Vec<StoredMatch>,
}

/// A route hypothesis.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct StoredHypothesis {
    /// 1-based rank.
    pub rank: usize,
    /// Path cost.
    pub cost: f64,
    /// One entry per query.
    pub rows: Vec<StoredRow>,
}

impl From<&Hypothesis> for StoredHypothesis {
    fn from(h: &Hypothesis) -> Self {
        StoredHypothesis {
            rank: h.rank,
            cost: h.cost,
            rows: h
                .rows
                .iter()
                .map(|r| StoredRow {
                    query: r.query,
                    matches: r
                        .matches
                        .iter()
                        .map(|m| StoredMatch {
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
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct StoredPrediction {
    /// Query index.
    pub query: usize,
    /// Predicted reference index.
    #[serde(rename = "ref")]
    pub reference: usize,
    /// Higher = more certain.
    pub confidence: f64,
}

impl From<&Prediction> for StoredPrediction {
    fn from(p: &Prediction) -> Self {
        StoredPrediction {
            query: p.query,
            reference: p.reference,
            confidence: p.confidence,
        }
    }
}

/// Seconds per stage of a localization.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct StoredTimings {
    /// Reading the map (descriptors or co-occurrence map).
    pub load_references: f64,
    /// Decoding query images and describing them.
    pub features: f64,
    /// Similarity matrix and normalisation.
    pub similarity: f64,
    /// Solver and confidences.
    pub solve: f64,
}

/// The stored JSON object: identity first, then the result's fields (no nesting).
#[derive(Serialize)]
struct FlatOut<'a> {
    #[serde(serialize_with = "hex_out")]
    id: u64,
    #[serde(serialize_with = "hex_out")]
    map_id: u64,
    created_at_ms: u64,
    query_count: usize,
    reference_count: usize,
    params: &'a StoredParams,
    total_cost: f64,
    hypotheses: &'a [StoredHypothesis],
    predictions: &'a [StoredPrediction],
    timings: &'a StoredTimings,
    #[serde(skip_serializing_if = "Option::is_none")]
    picture: Option<&'a StoredPicture>,
}

#[derive(Deserialize)]
struct FlatIn {
    #[serde(deserialize_with = "hex_in")]
    id: u64,
    #[serde(deserialize_with = "hex_in")]
    map_id: u64,
    created_at_ms: u64,
    query_count: usize,
    reference_count: usize,
    params: StoredParams,
    total_cost: f64,
    hypotheses: Vec<StoredHypothesis>,
    predictions: Vec<StoredPrediction>,
    timings: StoredTimings,
    #[serde(default)]
    picture: Option<StoredPicture>,
}

fn hex_out<S: Serializer>(id: &u64, s: S) -> Result<S::Ok, S::Error> {
    s.serialize_str(&format!("{id:016x}"))
}

fn hex_in<'de, D: Deserializer<'de>>(d: D) -> Result<u64, D::Error> {
    let s = String::deserialize(d)?;
    if s.len() == 16 && s.bytes().all(|b| matches!(b, b'0'..=b'9' | b'a'..=b'f')) {
        u64::from_str_radix(&s, 16).map_err(D::Error::custom)
    } else {
        Err(D::Error::custom(format!("`{s}` is not a 16-digit hex id")))
    }
}

impl LocalizationDocument {
    /// The stored JSON bytes.
    pub fn to_json(&self) -> StoreResult<Vec<u8>> {
        let r = &self.result;
        let flat = FlatOut {
            id: self.id,
            map_id: self.map_id,
            created_at_ms: self.created_at_ms,
            query_count: r.query_count,
            reference_count: r.reference_count,
            params: &r.params,
            total_cost: r.total_cost,
            hypotheses: &r.hypotheses,
            predictions: &r.predictions,
            timings: &r.timings,
            picture: r.picture.as_ref(),
        };
        serde_json::to_vec(&flat).map_err(|e| StoreError::Backend(Box::new(e)))
    }

    /// Decodes the JSON stored under `key`.
    pub fn from_json(key: &[u8], bytes: &[u8]) -> StoreResult<Self> {
        let f: FlatIn = serde_json::from_slice(bytes)
            .map_err(|e| StoreError::corrupt(key, format!("localization document: {e}")))?;
        Ok(LocalizationDocument {
            id: f.id,
            map_id: f.map_id,
            created_at_ms: f.created_at_ms,
            result: LocalizationResult {
                query_count: f.query_count,
                reference_count: f.reference_count,
                params: f.params,
                total_cost: f.total_cost,
                hypotheses: f.hypotheses,
                predictions: f.predictions,
                timings: f.timings,
                picture: f.picture,
            },
        })
    }
}

/// The parameters of a trip, as stored with its record.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct TripParamsDocument {
    /// `K`.
    pub fan_out: usize,
    /// `W`, or `None` when resolved from the first batch.
    pub hidden_cost: Option<f64>,
    /// Horizontal edges.
    pub horizontal: bool,
    /// Lag window in frames.
    pub lag: usize,
    /// `R`, or `None` when relocalization is off.
    pub relocalization_cost: Option<f64>,
    /// Prior weight in frames.
    pub prior_weight: f64,
    /// Online column normalisation.
    pub normalize: bool,
}

impl From<&TripParams> for TripParamsDocument {
    fn from(p: &TripParams) -> Self {
        TripParamsDocument {
            fan_out: p.fan_out,
            hidden_cost: p.hidden_cost,
            horizontal: p.horizontal,
            lag: p.lag,
            relocalization_cost: p.relocalization,
            prior_weight: p.prior_weight,
            normalize: p.normalize,
        }
    }
}

impl TripParamsDocument {
    /// The stored JSON bytes.
    pub fn to_json(&self) -> StoreResult<Vec<u8>> {
        serde_json::to_vec(self).map_err(|e| StoreError::Backend(Box::new(e)))
    }

    /// Decodes the JSON stored under `key`.
    pub fn from_json(key: &[u8], bytes: &[u8]) -> StoreResult<Self> {
        serde_json::from_slice(bytes)
            .map_err(|e| StoreError::corrupt(key, format!("trip parameters: {e}")))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn localization_json_is_flat_with_hex_ids_and_round_trips() {
        let doc = LocalizationDocument {
            id: 0xab,
            map_id: 1,
            created_at_ms: 5,
            result: LocalizationResult {
                query_count: 1,
                reference_count: 2,
                params: StoredParams::new(&LocalizeOptions::default(), 1.25, None),
                total_cost: 3.5,
                hypotheses: Vec::new(),
                predictions: vec![StoredPrediction {
                    query: 0,
                    reference: 1,
                    confidence: 0.5,
                }],
                timings: StoredTimings::default(),
                picture: None,
            },
        };
        let json = doc.to_json().unwrap();
        let text = String::from_utf8(json.clone()).unwrap();
        assert!(
            text.starts_with(
                r#"{"id":"00000000000000ab","map_id":"0000000000000001","created_at_ms":5,"query_count":1,"#
            ),
            "{text}"
        );
        assert!(text.contains(r#""hidden_cost_mode":"auto""#), "{text}");
        assert!(!text.contains("method"), "{text}");
        assert_eq!(LocalizationDocument::from_json(b"L", &json).unwrap(), doc);
        let err = LocalizationDocument::from_json(b"L", b"{}").unwrap_err();
        assert!(matches!(err, StoreError::Corrupt { .. }), "{err}");
        let bad_id = text.replace("00000000000000ab", "xyz");
        assert!(LocalizationDocument::from_json(b"L", bad_id.as_bytes()).is_err());
    }
}
