//! A trip's parameters and answers: [`TripParams`] (validated once, before a trip exists),
//! what a batch returns ([`BatchUpdate`]: per-frame [`FrameEstimate`]s and the [`TripStatus`])
//! and the thresholds they are read with. Kept apart from the [`super::Trip`] driver so the
//! service and the CLI can build and check parameters without the state machine.

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
}

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
}

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
}

impl FrameEstimate {
    /// Not localized: no reference (hidden, or off the map by the stretch) or a confidence of
    /// at most [`LOST_RATIO`] (no local evidence for the match). A latest frame that is lost
    /// makes the trip [`TripStatus::Lost`].
    pub fn is_lost(&self) -> bool {
        self.reference.is_none() || self.confidence <= LOST_RATIO
    }
}

/// Where the trip stands after a batch.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum TripStatus {
    /// The latest frame is matched with local support.
    Localized,
    /// The latest frame has no reference (hidden, or off the map by the stretch) or no local
    /// support.
    Lost,
    /// The path re-entered the map by a jump during this batch.
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
