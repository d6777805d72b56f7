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

/// Every method's output type lives in the core next to [`crate::localize::localize`]; it is
/// re-exported here because the protocol consumes it.
pub use crate::localize::Prediction;
