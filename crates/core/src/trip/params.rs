//! A trip's parameters and answers: [`TripParams`] (validated once, before a trip exists),
//! what a batch returns ([`BatchUpdate`]: per-frame [`FrameEstimate`]s and the [`TripStatus`])
//! and the thresholds they are read with. Kept apart from the [`super::Trip`] driver so the
//! service and the CLI can build and check parameters without the state machine.

use crate::calibration::{FrameStatus, DEFAULT_THRESHOLD};
use crate::confidence::{ConfidenceParams, DEFAULT_DISCOUNT};
use crate::solver::{check_fan_out, check_hidden_cost};
use crate::{Error, Result};

use super::online;

/// A latest frame whose confidence is at most this is reported as lost.
pub const LOST_RATIO: f64 = 1.0;

/// Largest accepted confidence half window `L` and radius `r`.
pub const MAX_CONFIDENCE_WINDOW: usize = 1000;

/// Parameters of a trip. Its serde form (feature `serde`) is what a trip's record stores: the
/// fields in this order, `relocalization` named `relocalization_cost`, the confidence's
/// settings not stored (a trip always scores with [`TripParams::default`]'s).
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
pub struct TripParams {
    /// Fan-out `K`.
    pub fan_out: usize,
    /// `W`, or `None` to resolve it from the first batch.
    pub hidden_cost: Option<f64>,
    /// Horizontal edges.
    pub horizontal: bool,
    /// Rows whose back-pointers are kept (older estimates are final).
    pub lag: usize,
    /// Cost `R` of re-entering the map anywhere; `None` disables relocalization.
    #[cfg_attr(feature = "serde", serde(rename = "relocalization_cost"))]
    pub relocalization: Option<f64>,
    /// Frames' worth of weight given to the map's prior column means.
    pub prior_weight: f64,
    /// Online column normalisation (Eq. 2 with the map prior); `false` uses raw cosine rows.
    pub normalize: bool,
    /// The confidence: radius `r` and discount `g` (`None`: `g = 1 - 1/(L+1)` from the half
    /// window `L`, as the offline default relates them).
    #[cfg_attr(
        feature = "serde",
        serde(skip, default = "TripParams::default_confidence")
    )]
    pub confidence: ConfidenceParams,
    /// Map images within which an estimate counts as right: what `p_correct` is the
    /// probability of ([`crate::calibration`]). Default 1. Stored only when not the default,
    /// so trips stored before it existed read back (and re-encode) unchanged.
    #[cfg_attr(
        feature = "serde",
        serde(
            default = "TripParams::default_tolerance",
            skip_serializing_if = "TripParams::is_default_tolerance"
        )
    )]
    pub tolerance: usize,
    /// `p_correct` at which an estimate is `localized` (default
    /// [`crate::calibration::DEFAULT_THRESHOLD`], 0.9), in `(0, 1]`; stored like `tolerance`.
    #[cfg_attr(
        feature = "serde",
        serde(
            default = "TripParams::default_threshold",
            skip_serializing_if = "TripParams::is_default_threshold"
        )
    )]
    pub threshold: f64,
}

/// Largest accepted [`TripParams::tolerance`].
pub const MAX_TOLERANCE: usize = 1000;

impl TripParams {
    /// Checks every parameter's range, without a map: the graph (fan-out cap, `W`) with the
    /// solver's one check ([`crate::solver::check_fan_out`], [`crate::solver::check_hidden_cost`]),
    /// the lag window and relocalization cost, the prior weight and the confidence.
    pub fn validate(&self) -> Result<()> {
        if !(self.prior_weight.is_finite() && self.prior_weight >= 0.0) {
            return Err(Error::param(
                "prior_weight",
                format!("must be a finite number >= 0, got {}", self.prior_weight),
            ));
        }
        check_fan_out(self.fan_out)?;
        if let Some(w) = self.hidden_cost {
            check_hidden_cost(w)?;
        }
        online::check_window(self.lag, self.relocalization)?;
        if self.confidence.half_window > MAX_CONFIDENCE_WINDOW
            || self.confidence.radius > MAX_CONFIDENCE_WINDOW
        {
            return Err(Error::param(
                "confidence",
                format!(
                    "half window and radius must be at most {MAX_CONFIDENCE_WINDOW}, got {:?}",
                    self.confidence
                ),
            ));
        }
        let g = self.discount();
        if !(g > 0.0 && g < 1.0) {
            return Err(Error::param(
                "discount",
                format!("must be within (0, 1), got {g}"),
            ));
        }
        if self.tolerance > MAX_TOLERANCE {
            return Err(Error::param(
                "tolerance",
                format!("must be at most {MAX_TOLERANCE}, got {}", self.tolerance),
            ));
        }
        if !(self.threshold > 0.0 && self.threshold <= 1.0) {
            return Err(Error::param(
                "threshold",
                format!("must be within (0, 1], got {}", self.threshold),
            ));
        }
        Ok(())
    }

    /// The discount `g` the trip scores with (see [`TripParams::confidence`]).
    pub fn discount(&self) -> f64 {
        self.confidence
            .discount
            .unwrap_or(1.0 - 1.0 / (self.confidence.half_window as f64 + 1.0))
    }
}

impl Default for TripParams {
    fn default() -> Self {
        TripParams {
            fan_out: 4,
            horizontal: true,
            hidden_cost: None,
            lag: 32,
            relocalization: Some(DEFAULT_RELOCALIZATION_COST),
            prior_weight: 100.0,
            normalize: true,
            confidence: TripParams::default_confidence(),
            tolerance: DEFAULT_TOLERANCE,
            threshold: DEFAULT_THRESHOLD,
        }
    }
}

impl TripParams {
    /// The confidence every trip scores with: the offline default's radius and discount.
    pub fn default_confidence() -> ConfidenceParams {
        ConfidenceParams {
            discount: Some(DEFAULT_DISCOUNT),
            ..ConfidenceParams::default()
        }
    }

    #[cfg(feature = "serde")]
    fn default_tolerance() -> usize {
        DEFAULT_TOLERANCE
    }

    #[cfg(feature = "serde")]
    fn default_threshold() -> f64 {
        DEFAULT_THRESHOLD
    }

    #[cfg(feature = "serde")]
    fn is_default_tolerance(t: &usize) -> bool {
        *t == DEFAULT_TOLERANCE
    }

    #[cfg(feature = "serde")]
    #[allow(
        clippy::trivially_copy_pass_by_ref,
        reason = "serde's skip_serializing_if signature"
    )]
    fn is_default_threshold(t: &f64) -> bool {
        *t == DEFAULT_THRESHOLD
    }
}

/// Default [`TripParams::tolerance`]: one map image either side.
pub const DEFAULT_TOLERANCE: usize = 1;

/// Default relocalization cost `R`, in units of summed node costs.
pub const DEFAULT_RELOCALIZATION_COST: f64 = 1.0;

/// A trip's answer for one frame.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FrameEstimate {
    /// Frame index since the trip started.
    pub frame: usize,
    /// Estimated reference index, `None` when not on the map (hidden by the path, or in a
    /// chance stretch: `trip/stretch.rs`).
    pub reference: Option<usize>,
    /// The discounted min-marginal ratio on the frames so far (0 without a reference): causal for the
    /// newest frame, re-scored with the later frames for the others (see `trip/confidence.rs`).
    pub confidence: f64,
    /// The calibrated probability that `reference` is within the trip's tolerance of the true
    /// place ([`crate::calibration::trip_p_correct`]); 0 without a reference.
    pub p_correct: f64,
    /// What the estimate means ([`crate::calibration::frame_status`]).
    pub status: FrameStatus,
}

impl FrameEstimate {
    /// Not localized: no reference (hidden, or off the map by the stretch) or a confidence of
    /// at most [`LOST_RATIO`] (no local evidence for the match). A latest frame that is lost
    /// makes the trip [`TripStatus::Lost`].
    pub fn is_lost(&self) -> bool {
        self.reference.is_none() || self.confidence <= LOST_RATIO
    }
}

/// Where the trip stands after a batch, in the three words of the service's contract (the
/// four-way meaning of its latest frame is that frame's [`FrameStatus`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum TripStatus {
    /// The latest frame is `localized` (its `p_correct` reaches the trip's threshold).
    Localized,
    /// The latest frame is not to be acted on (`uncertain`, `off_map` or `lost`).
    Lost,
    /// The path re-entered the map by a jump during this batch (an event, whatever the latest
    /// frame's status).
    Relocalized,
}

/// The result of one batch.
#[derive(Clone, Debug, PartialEq)]
pub struct BatchUpdate {
    /// One estimate per new frame, as seen at the end of the batch (or, in a batch longer
    /// than the lag window, when the frame was last in the window).
    pub estimates: Vec<FrameEstimate>,
    /// The best path over the lag window (older frames first), re-traced with this batch.
    pub window: Vec<FrameEstimate>,
    /// The trip's status after the batch.
    pub status: TripStatus,
}

impl BatchUpdate {
    /// The status of the trip's latest frame ([`FrameStatus`]); `Lost` for an empty update.
    pub fn latest_status(&self) -> FrameStatus {
        self.estimates
            .last()
            .map_or(FrameStatus::Lost, |e| e.status)
    }
}
