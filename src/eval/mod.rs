//! Evaluation protocol of `spec.md` §4: ground truth, query exclusions, precision-recall
//! metrics, prediction CSVs and PR plots.
//!
//! Every method reduces its result to at most one [`Prediction`] per query; [`evaluate`] sweeps
//! the confidence threshold over them. The protocol is method-agnostic: it only sees
//! `(query, reference, confidence)` triples.

mod ground_truth;
mod metrics;
mod plot;
mod predictions;

pub use ground_truth::{Exclusions, GroundTruth};
pub use metrics::{evaluate, Metrics, PrPoint};
pub use plot::{plot_pr, PLOT_SIZE};
pub use predictions::write_predictions_csv;

/// One method's answer for one query: at most one per query, higher confidence = more certain.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Prediction {
    /// Query index `i`.
    pub query: usize,
    /// Predicted reference index `j`.
    pub reference: usize,
    /// Higher = more certain. Finite.
    pub confidence: f64,
}
