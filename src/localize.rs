//! One call from descriptor matrices to a localization result: similarity (Eq. 1), column
//! normalisation (Eq. 2), the graph solver, and per-query predictions with confidence.
//!
//! Shared by `seasonloc eval`, the HTTP service and trips, so all of them give the same answer
//! for the same descriptors and parameters.

use crate::eval::Prediction;
use crate::solver::{Solution, SolverParams};
use crate::{Matrix, Result};

/// Options of [`localize`].
#[derive(Clone, Debug, PartialEq)]
pub struct LocalizeOptions {
    /// Graph and solver parameters.
    pub solver: SolverParams,
    /// Apply the column normalisation of Eq. 2 (default true).
    pub normalize: bool,
}

impl Default for LocalizeOptions {
    fn default() -> Self {
        LocalizeOptions {
            solver: SolverParams::default(),
            normalize: true,
        }
    }
}

/// Seconds spent per stage.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct StageTimings {
    /// Similarity matrix and normalisation.
    pub similarity: f64,
    /// Graph solver and confidences.
    pub solve: f64,
}

/// The result of [`localize`].
#[derive(Clone, Debug, PartialEq)]
pub struct Localization {
    /// Ranked route hypotheses.
    pub solution: Solution,
    /// At most one prediction per query row.
    pub predictions: Vec<Prediction>,
    /// Time per stage.
    pub timings: StageTimings,
}

/// Localizes the query descriptors (one row per query image, in driving order) against the
/// reference descriptors (one row per map image, in route order).
pub fn localize(
    _queries: &Matrix,
    _references: &Matrix,
    _options: &LocalizeOptions,
) -> Result<Localization> {
    todo!("localize facade")
}
