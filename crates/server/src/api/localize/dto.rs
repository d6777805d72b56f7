//! Wire types of localizations (`POST /v1/maps/{id}/localize`, `/v1/localizations`) and their
//! conversions from stored results. A stored result is answered byte for byte as the JSON the
//! store keeps (a test below checks it on the golden store).

use serde::{Deserialize, Serialize};

use crate::api::cooc::dto::CoocMethodDto;
use crate::api::error::ApiError;
use crate::api::wire::format_id;
use seasonloc_app::model::LocalizationRecord;
use seasonloc_app::model::{HiddenCostMode, LocalizationParams, LocalizationTimings};
use seasonloc_core::cooc::CoocMethod;
use seasonloc_core::localize::LocalizeOptions;
use seasonloc_core::localize::Prediction;
use seasonloc_core::similarity::Normalization;
use seasonloc_core::solver::Hypothesis;
use seasonloc_core::solver::{HiddenCost, SolverParams};

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
    /// Map images within which a prediction counts as right: what its `p_correct` is the
    /// probability of (default 1).
    pub tolerance: Option<usize>,
}

impl LocalizeParams {
    /// Parses a `params` part; unknown fields and wrong types are 400 `invalid_parameter`.
    pub fn from_json(bytes: &[u8]) -> Result<Self, ApiError> {
        crate::api::extract::parse_json_object(bytes, Some("params"))
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
        let tolerance = self
            .tolerance
            .unwrap_or(seasonloc_core::trip::DEFAULT_TOLERANCE);
        if tolerance > seasonloc_core::trip::MAX_TOLERANCE {
            return Err(ApiError::param(
                "tolerance",
                format!(
                    "must be at most {}, got {tolerance}",
                    seasonloc_core::trip::MAX_TOLERANCE
                ),
            ));
        }
        Ok(LocalizeOptions {
            solver,
            normalization,
            tolerance,
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
    /// The tolerance of the predictions' `p_correct` (absent when 1, the default).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub tolerance: Option<usize>,
}

impl From<&LocalizationParams> for ParamsUsed {
    fn from(p: &LocalizationParams) -> Self {
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
                CoocMethod::Flow => CoocMethodDto::Flow,
                CoocMethod::Single => CoocMethodDto::Cooc,
                CoocMethod::Sequence => CoocMethodDto::CoocSeq,
            }),
            tolerance: p.tolerance,
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

impl From<&Hypothesis> for HypothesisDto {
    fn from(h: &Hypothesis) -> Self {
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
    /// Higher = more certain: the method's own score (its scale differs between routes).
    pub confidence: f64,
    /// The calibrated probability that `ref` is within the tolerance of the true place
    /// (absent for methods without a calibration and in results stored before it existed).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub p_correct: Option<f64>,
}

impl From<&Prediction> for PredictionDto {
    fn from(p: &Prediction) -> Self {
        PredictionDto {
            query: p.query,
            reference: p.reference,
            confidence: p.confidence,
            p_correct: p.p_correct,
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

impl From<&LocalizationTimings> for TimingsDto {
    fn from(t: &LocalizationTimings) -> Self {
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
    /// Why the answer has no prediction, or why its predictions say nothing; absent otherwise.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub reason: Option<NoPredictionReason>,
}

/// Why a localization has no (informative) prediction, read from the result itself.
#[derive(Clone, Copy, Debug, Serialize, Deserialize, PartialEq, Eq)]
#[serde(rename_all = "snake_case")]
pub enum NoPredictionReason {
    /// One query with the column normalisation (Eq. 2) on: each reference's similarity is
    /// divided by its mean over the queries, itself, so every reference scores alike and any
    /// prediction is arbitrary. Send a sequence of queries (or `normalize: false`).
    TooFewQueries,
    /// Every query was left hidden: none looks enough like any place of the map.
    EveryRowHidden,
    /// Queries were matched, but the local evidence of each puts it off the map.
    OffMap,
}

impl NoPredictionReason {
    /// The reason a result has no informative prediction, if it has none.
    pub fn of(r: &seasonloc_app::model::LocalizationResult) -> Option<Self> {
        let flow = matches!(r.params.method, None | Some(CoocMethod::Flow));
        if r.query_count < 2 && r.params.normalize && flow {
            return Some(NoPredictionReason::TooFewQueries);
        }
        if !r.predictions.is_empty() {
            return None;
        }
        let matched = r
            .hypotheses
            .iter()
            .any(|h| h.rows.iter().any(|row| !row.matches.is_empty()));
        Some(if matched {
            NoPredictionReason::OffMap
        } else {
            NoPredictionReason::EveryRowHidden
        })
    }
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

impl From<&LocalizationRecord> for LocalizationResponse {
    fn from(d: &LocalizationRecord) -> Self {
        let r = &d.result;
        LocalizationResponse {
            id: format_id(d.id),
            map_id: format_id(d.map_id),
            created_at_ms: d.created_ms,
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
            reason: NoPredictionReason::of(r),
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

/// Query of `GET /v1/localizations`.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ListQuery {
    /// Only this map's results.
    pub map: Option<String>,
    /// Page size (default and range in [`crate::api::wire`]).
    pub limit: Option<usize>,
    /// Results older than this id.
    pub before: Option<String>,
}

#[cfg(test)]
mod tests {
    use super::*;

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
}
