//! Evaluation protocol of `spec.md` §4: ground truth (the CSV and the field's forms), query
//! exclusions, precision-recall metrics, the field's Recall@N and prediction CSVs (the PR plots are drawn by the binary, `src/cli/plot.rs`).
//!
//! Every method reduces its result to at most one [`Prediction`] per query; [`evaluate`] sweeps
//! the confidence threshold over them. The protocol is method-agnostic: it only sees
//! `(query, reference, confidence)` triples.

mod file_names;
mod forms;
mod ground_truth;
mod metrics;
mod predictions;
mod recall;

pub use file_names::{FileNameCheck, GroundTruthFiles};
pub use forms::{utm_of_file_name, utm_of_files, DEFAULT_POSITIVE_DISTANCE_M};
pub use ground_truth::{Exclusions, GroundTruth};
pub use metrics::{evaluate, Metrics, PrPoint};
pub use predictions::write_predictions_csv;
pub use recall::{recall_at_n, RecallAtN, STANDARD_NS};

/// Every method's output type lives in the core next to [`crate::localize::localize`]; it is
/// re-exported here because the protocol consumes it.
pub use crate::localize::Prediction;
