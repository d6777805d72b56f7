//! [`Prediction`]: every method's answer for one query, what the evaluation protocol scores and
//! the service stores. Its own module, below the methods and the calibration that all use it.

/// One method's answer for one query: at most one per query, higher confidence = more certain.
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
pub struct Prediction {
    /// Query index `i`.
    pub query: usize,
    /// Predicted reference index `j`.
    #[cfg_attr(feature = "serde", serde(rename = "ref"))]
    pub reference: usize,
    /// Higher = more certain. Finite. The method's own score: its scale differs between
    /// routes and methods (research, ranking).
    pub confidence: f64,
    /// The calibrated probability that `reference` is within the localization's tolerance of
    /// the true place ([`crate::calibration::offline_p_correct`]); `None` for methods without a
    /// calibration (the baselines, the co-occurrence methods without the flow graph) and in
    /// results stored before it existed.
    #[cfg_attr(
        feature = "serde",
        serde(default, skip_serializing_if = "Option::is_none")
    )]
    pub p_correct: Option<f64>,
}
