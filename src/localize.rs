//! One call from descriptor matrices to a localization result: similarity (Eq. 1), column
//! normalisation (Eq. 2), the graph solver, and per-query predictions with confidence.
//!
//! Shared by `seasonloc eval`, the HTTP service and trips, so all of them give the same answer
//! for the same descriptors and parameters.

use std::time::Instant;

use crate::confidence::{score_hypothesis, ConfidenceParams, GraphParams};
use crate::picture::MatrixPicture;
use crate::similarity::{self, Normalization};
use crate::solver::{solve, Solution, SolverParams};
use crate::{Matrix, Result};

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

/// Options of [`localize`].
#[derive(Clone, Debug, Default, PartialEq)]
pub struct LocalizeOptions {
    /// Graph and solver parameters.
    pub solver: SolverParams,
    /// How `C` is normalised before the graph (default: Eq. 2 with a floored column mean).
    pub normalization: Normalization,
    /// How per-query confidences are computed.
    pub confidence: ConfidenceParams,
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
    queries: &Matrix,
    references: &Matrix,
    options: &LocalizeOptions,
) -> Result<Localization> {
    localize_inspecting(queries, references, options, |_| Ok(())).map(|(l, ())| l)
}

/// [`localize`], plus the bounded picture of the normalised similarity matrix `ĉ` that the
/// graph was solved on (the dashboard's figure; its time counts as similarity time).
pub fn localize_with_picture(
    queries: &Matrix,
    references: &Matrix,
    options: &LocalizeOptions,
) -> Result<(Localization, MatrixPicture)> {
    localize_inspecting(queries, references, options, MatrixPicture::bounded)
}

fn localize_inspecting<T>(
    queries: &Matrix,
    references: &Matrix,
    options: &LocalizeOptions,
    inspect: impl FnOnce(&Matrix) -> Result<T>,
) -> Result<(Localization, T)> {
    options.solver.validate()?;
    let started = Instant::now();
    let c = similarity::cosine_matrix(queries, references)?;
    let chat = options.normalization.apply(&c)?;
    let seen = inspect(&chat)?;
    let similarity_seconds = started.elapsed().as_secs_f64();
    let (solution, predictions) = solve_with_confidence(&chat, options)?;
    let localization = Localization {
        solution,
        predictions,
        timings: StageTimings {
            similarity: similarity_seconds,
            solve: started.elapsed().as_secs_f64() - similarity_seconds,
        },
    };
    Ok((localization, seen))
}

/// Solves the graph on a (normalised) similarity matrix and reduces the hypotheses to at most
/// one prediction per query: for a query matched by several hypotheses, the one whose local
/// min-marginal ratio ([`crate::confidence`]) is highest.
pub fn solve_with_confidence(
    chat: &Matrix,
    options: &LocalizeOptions,
) -> Result<(Solution, Vec<Prediction>)> {
    let solution = solve(chat, &options.solver)?;
    let graph = GraphParams {
        fan_out: options.solver.fan_out,
        horizontal: options.solver.horizontal,
        hidden_cost: solution.hidden_cost,
    };
    let mut best: Vec<Option<Prediction>> = vec![None; chat.rows()];
    for hypothesis in &solution.hypotheses {
        for row in score_hypothesis(chat, &graph, hypothesis, &options.confidence)? {
            let slot = &mut best[row.query];
            if slot.is_none_or(|p| row.confidence > p.confidence) {
                *slot = Some(Prediction {
                    query: row.query,
                    reference: row.reference,
                    confidence: row.confidence,
                });
            }
        }
    }
    Ok((solution, best.into_iter().flatten().collect()))
}
