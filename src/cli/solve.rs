//! `seasonloc solve`: the graph solver on a similarity matrix from a `.npy` file (spec §5).
//!
//! stdout: `{"total_cost", "hidden_cost", "hypotheses": [{"rank", "cost", "rows": [{"query",
//! "matches": [{"ref", "similarity"}]}]}], "predictions": [{"query", "ref", "confidence"}]}`.
//! `total_cost` is the sum of the hypotheses' costs; a hidden row has `"matches": []`.

use std::path::PathBuf;

use anyhow::Result;
use clap::Args;
use serde_json::{json, Value};

use super::SolverArgs;
use seasonloc_core::localize::Prediction;
use seasonloc_core::localize::{solve_with_confidence, LocalizeOptions};
use seasonloc_core::similarity::normalize_columns;
use seasonloc_core::solver::Solution;

/// Flags of `seasonloc solve`.
#[derive(Debug, Args)]
pub struct SolveArgs {
    /// Similarity matrix, NumPy .npy, float32 or float64, shape (Q, D). Used as ĉ directly
    /// unless --normalize.
    #[arg(long)]
    pub similarity: PathBuf,
    /// Treat the matrix as raw cosine similarities C and apply the column normalisation (Eq. 2).
    #[arg(long)]
    pub normalize: bool,
    /// Graph and solver parameters.
    #[command(flatten)]
    pub solver: SolverArgs,
    /// Reference frames within which a prediction counts as right: what each prediction's
    /// `p_correct` is the probability of.
    #[arg(long, default_value_t = seasonloc_core::trip::DEFAULT_TOLERANCE, value_parser = super::parse_tolerance)]
    pub tolerance: usize,
}

/// Runs `solve` and returns the JSON document to print.
pub fn run(args: &SolveArgs) -> Result<Value> {
    let params = args.solver.to_params()?;
    let matrix = super::npy::read_matrix(&args.similarity)?;
    matrix.check_finite("similarity matrix")?;
    let chat = if args.normalize {
        normalize_columns(&matrix)?
    } else {
        matrix
    };
    let options = LocalizeOptions {
        solver: params,
        tolerance: args.tolerance,
        ..LocalizeOptions::default()
    };
    let (solution, predictions) = solve_with_confidence(&chat, &options)?;
    Ok(solution_json(&solution, &predictions))
}

/// The JSON shape of spec §5 for a solution, plus `hidden_cost` and `predictions`.
pub fn solution_json(solution: &Solution, predictions: &[Prediction]) -> Value {
    let hypotheses: Vec<Value> = solution
        .hypotheses
        .iter()
        .map(|h| {
            let rows: Vec<Value> = h
                .rows
                .iter()
                .map(|r| {
                    let matches: Vec<Value> = r
                        .matches
                        .iter()
                        .map(|m| json!({"ref": m.reference, "similarity": m.similarity}))
                        .collect();
                    json!({"query": r.query, "matches": matches})
                })
                .collect();
            json!({"rank": h.rank, "cost": h.cost, "rows": rows})
        })
        .collect();
    json!({
        "total_cost": solution.total_cost(),
        "hidden_cost": solution.hidden_cost,
        "hypotheses": hypotheses,
        "predictions": predictions_json(predictions),
    })
}

/// `[{"query", "ref", "confidence", "p_correct"}]` (`p_correct` only for methods that have
/// one).
pub fn predictions_json(predictions: &[Prediction]) -> Vec<Value> {
    predictions
        .iter()
        .map(|p| {
            let mut v = json!({"query": p.query, "ref": p.reference, "confidence": p.confidence});
            if let (Some(pc), Some(o)) = (p.p_correct, v.as_object_mut()) {
                o.insert("p_correct".into(), json!(pc));
            }
            v
        })
        .collect()
}
