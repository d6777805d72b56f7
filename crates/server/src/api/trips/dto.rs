//! Wire types of online trips (`/v1/maps/{id}/trips`, `/v1/trips/...`) and their conversions
//! from the trip's core types.

use serde::{Deserialize, Serialize};

use crate::api::error::ApiError;
use seasonloc_core::calibration::FrameStatus;
use seasonloc_core::trip::{FrameEstimate, TripParams};

/// Optional parameters of a trip (JSON body of `POST /v1/maps/{id}/trips`).
#[derive(Clone, Debug, Default, Deserialize, Serialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct TripParamsDto {
    /// `K`, fan-out (default 4).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub fan_out: Option<usize>,
    /// `W`: a number > 0 or `"auto"` (default: resolved from the first batch).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub hidden_cost: Option<serde_json::Value>,
    /// Horizontal edges (default true).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub horizontal: Option<bool>,
    /// Frames whose estimates may still be revised (default 32).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub lag: Option<usize>,
    /// Allow re-entry anywhere on the map (default true).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub relocalization: Option<bool>,
    /// Cost `R` of a re-entry (default 1.0).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub relocalization_cost: Option<f64>,
    /// Frames' worth of weight of the map's prior column means (default 100).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub prior_weight: Option<f64>,
    /// Online column normalisation (default true).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub normalize: Option<bool>,
    /// Map images within which an estimate counts as right: what `p_correct` is the
    /// probability of (default 1).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub tolerance: Option<usize>,
    /// `p_correct` from which a frame is `localized` (default 0.9).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub threshold: Option<f64>,
}

impl TripParamsDto {
    /// Resolves defaults and validates every range (errors name the field).
    pub fn into_params(self) -> Result<TripParams, ApiError> {
        let d = TripParams::default();
        let hidden_cost =
            match self.hidden_cost {
                None => d.hidden_cost,
                Some(serde_json::Value::String(s)) if s == "auto" => None,
                Some(serde_json::Value::Number(n)) => Some(n.as_f64().ok_or_else(|| {
                    ApiError::param("hidden_cost", format!("{n} is not a number"))
                })?),
                Some(other) => {
                    return Err(ApiError::param(
                        "hidden_cost",
                        format!("must be a number > 0 or \"auto\", got {other}"),
                    ))
                }
            };
        if self.relocalization == Some(false) && self.relocalization_cost.is_some() {
            return Err(ApiError::inconsistent(
                "relocalization_cost",
                "is set but `relocalization` is false",
            ));
        }
        let relocalization = match self.relocalization {
            Some(false) => None,
            Some(true) | None => Some(
                self.relocalization_cost
                    .unwrap_or(seasonloc_core::trip::DEFAULT_RELOCALIZATION_COST),
            ),
        };
        let params = TripParams {
            fan_out: self.fan_out.unwrap_or(d.fan_out),
            horizontal: self.horizontal.unwrap_or(d.horizontal),
            hidden_cost,
            lag: self.lag.unwrap_or(d.lag),
            relocalization,
            prior_weight: self.prior_weight.unwrap_or(d.prior_weight),
            normalize: self.normalize.unwrap_or(d.normalize),
            confidence: d.confidence,
            tolerance: self.tolerance.unwrap_or(d.tolerance),
            threshold: self.threshold.unwrap_or(d.threshold),
        };
        // Every range is checked by the core.
        params.validate()?;
        Ok(params)
    }
}

/// The parameters a trip uses, defaults resolved.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct TripParamsUsed {
    /// `K`.
    pub fan_out: usize,
    /// `W`, or `null` when resolved from the first batch (see `hidden_cost` of a batch).
    pub hidden_cost: Option<f64>,
    /// Horizontal edges.
    pub horizontal: bool,
    /// Lag window in frames.
    pub lag: usize,
    /// `R`, or `null` when relocalization is off.
    pub relocalization_cost: Option<f64>,
    /// Prior weight in frames.
    pub prior_weight: f64,
    /// Online column normalisation.
    pub normalize: bool,
    /// Map images within which an estimate counts as right.
    pub tolerance: usize,
    /// `p_correct` from which a frame is `localized`.
    pub threshold: f64,
}

impl From<&TripParams> for TripParamsUsed {
    fn from(p: &TripParams) -> Self {
        TripParamsUsed {
            fan_out: p.fan_out,
            hidden_cost: p.hidden_cost,
            horizontal: p.horizontal,
            lag: p.lag,
            relocalization_cost: p.relocalization,
            prior_weight: p.prior_weight,
            normalize: p.normalize,
            tolerance: p.tolerance,
            threshold: p.threshold,
        }
    }
}

/// What a frame estimate means for a vehicle, on the wire.
#[derive(Clone, Copy, Debug, Serialize, Deserialize, PartialEq, Eq)]
#[serde(rename_all = "snake_case")]
pub enum FrameStatusDto {
    /// Act on it.
    Localized,
    /// A reference not to be acted on.
    Uncertain,
    /// Not on the mapped route.
    OffMap,
    /// Not enough evidence yet, or relocalizing.
    Lost,
}

impl From<FrameStatus> for FrameStatusDto {
    fn from(s: FrameStatus) -> Self {
        match s {
            FrameStatus::Localized => FrameStatusDto::Localized,
            FrameStatus::Uncertain => FrameStatusDto::Uncertain,
            FrameStatus::OffMap => FrameStatusDto::OffMap,
            FrameStatus::Lost => FrameStatusDto::Lost,
        }
    }
}

/// One frame's estimate on the wire.
#[derive(Clone, Copy, Debug, Serialize, Deserialize, PartialEq)]
pub struct FrameEstimateDto {
    /// Frame index since the trip started.
    pub frame: usize,
    /// Estimated reference index, `null` when not on the map.
    #[serde(rename = "ref")]
    pub reference: Option<usize>,
    /// The discounted min-marginal ratio on the trip's frames so far (0 when not on the map):
    /// the raw evidence, for research; its scale differs between routes.
    pub confidence: f64,
    /// The calibrated probability that `ref` is within the trip's `tolerance` of the true place
    /// (0 without a reference).
    pub p_correct: f64,
    /// `localized` (act on it: `p_correct` reaches the trip's threshold), `uncertain` (a
    /// reference not to be acted on), `off_map` (no reference: not on the mapped route) or `lost`
    /// (not enough evidence yet, or relocalizing).
    pub status: FrameStatusDto,
}

impl From<&FrameEstimate> for FrameEstimateDto {
    fn from(e: &FrameEstimate) -> Self {
        FrameEstimateDto {
            frame: e.frame,
            reference: e.reference,
            confidence: e.confidence,
            p_correct: e.p_correct,
            status: e.status.into(),
        }
    }
}

/// A trip as returned by open, read, close and list.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct TripResponse {
    /// Trip id.
    pub id: String,
    /// The map.
    pub map_id: String,
    /// Creation time, ms since the epoch.
    pub created_at_ms: u64,
    /// Close time, `null` while open.
    pub closed_at_ms: Option<u64>,
    /// Frames consumed.
    pub frame_count: u64,
    /// Map images the trip localizes against (the map's count when it was opened).
    pub reference_count: u32,
    /// Status after the last batch (`localized`, `lost` or `relocalized`), `null` before the
    /// first.
    pub status: Option<String>,
    /// The status of the trip's latest frame (`localized`, `uncertain`, `off_map` or `lost`;
    /// `GET /v1/trips/{id}` only, `null` before the first batch).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub latest_status: Option<Option<FrameStatusDto>>,
    /// Parameters.
    pub params: TripParamsUsed,
    /// The name of the API key that opened the trip (only it or an admin may post frames to
    /// it or close it); `null` when the service runs without keys.
    pub opened_by: Option<String>,
    /// Every frame's latest estimate (`GET /v1/trips/{id}` only).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub estimates: Option<Vec<FrameEstimateDto>>,
}

/// A page of `GET /v1/maps/{id}/trips`.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct TripListResponse {
    /// Trips, newest first.
    pub items: Vec<TripResponse>,
    /// Cursor for the next page.
    pub next: Option<String>,
}

/// Seconds per stage of a batch.
#[derive(Clone, Copy, Debug, Serialize, Deserialize, PartialEq)]
pub struct BatchTimings {
    /// Loading state and references.
    pub load: f64,
    /// Decoding and describing the images.
    pub features: f64,
    /// Similarities and the online solve.
    pub solve: f64,
    /// The atomic store write.
    pub store: f64,
}

/// The answer to a batch of frames.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct FramesResponse {
    /// Trip id.
    pub trip_id: String,
    /// Frames consumed, this batch included.
    pub frame_count: u64,
    /// One estimate per new frame.
    pub estimates: Vec<FrameEstimateDto>,
    /// `localized` (the latest frame is localized), `lost` (it is not) or `relocalized` (the
    /// path re-entered the map by a jump during this batch).
    pub status: String,
    /// The status of the latest frame: `localized`, `uncertain`, `off_map` or `lost`.
    pub latest_status: FrameStatusDto,
    /// The current best hypothesis over the lag window (older frames first).
    pub window: Vec<FrameEstimateDto>,
    /// The hidden cost `W` in use.
    pub hidden_cost: f64,
    /// Seconds per stage.
    pub timings: BatchTimings,
}

/// Query of `GET /v1/trips/{id}`.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ReadQuery {
    /// Only the estimates of frames `since..` (a live view's poll); all when absent.
    pub since: Option<u32>,
}

/// Query of `GET /v1/maps/{id}/trips`.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ListQuery {
    /// Page size (default and range in [`crate::api::wire`]).
    pub limit: Option<usize>,
    /// Trips older than this id.
    pub before: Option<String>,
}
