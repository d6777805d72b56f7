//! The methods on matrices: the similarity (Eq. 1, 2), the flow graph with its confidences
//! (`solve`, `localize`) and the baselines (best match, SeqSLAM), each the core function the
//! CLI calls (`seasonloc solve`, `seasonloc eval`), run without the GIL.

use numpy::{PyArray2, PyReadonlyArray2};
use pyo3::prelude::*;

use seasonloc_core::baselines::{self, SeqSlamParams};
use seasonloc_core::confidence::ConfidenceParams;
use seasonloc_core::localize::{solve_with_confidence, LocalizeOptions, Prediction};
use seasonloc_core::similarity::{cosine_matrix, normalize_columns, Normalization};
use seasonloc_core::solver::{HiddenCost, Solution, SolverParams};
use seasonloc_core::Error;

use super::{array, matrix, py_err};

/// `(query, ref, confidence, p_correct)` per prediction.
pub(crate) type PredictionRow = (usize, usize, f64, Option<f64>);
/// `(rank, cost, [(query, [(ref, similarity)])])` per hypothesis.
type HypothesisRow = (usize, f64, Vec<(usize, Vec<(usize, f32)>)>);
/// `(total_cost, hidden_cost, hypotheses, predictions)`.
type Solved = (f64, f64, Vec<HypothesisRow>, Vec<PredictionRow>);

pub(crate) fn prediction_rows(predictions: &[Prediction]) -> Vec<PredictionRow> {
    predictions
        .iter()
        .map(|p| (p.query, p.reference, p.confidence, p.p_correct))
        .collect()
}

fn solved(solution: &Solution, predictions: &[Prediction]) -> Solved {
    let hypotheses = solution
        .hypotheses
        .iter()
        .map(|h| {
            let rows = h
                .rows
                .iter()
                .map(|r| {
                    let m = r.matches.iter().map(|m| (m.reference, m.similarity));
                    (r.query, m.collect())
                })
                .collect();
            (h.rank, h.cost, rows)
        })
        .collect();
    (
        solution.total_cost(),
        solution.hidden_cost,
        hypotheses,
        prediction_rows(predictions),
    )
}

fn normalization(name: &str) -> PyResult<Normalization> {
    match name {
        "floored" => Ok(Normalization::FlooredColumns),
        "eq2" => Ok(Normalization::Columns),
        "none" => Ok(Normalization::None),
        other => Err(py_err(Error::param(
            "normalization",
            format!("expected `floored`, `eq2` or `none`, got `{other}`"),
        ))),
    }
}

/// The graph and solver parameters, validated as the CLI's flags are.
#[allow(clippy::too_many_arguments)]
fn solver_params(
    fan_out: usize,
    hidden_cost: Option<f64>,
    flows: usize,
    exact: bool,
    horizontal: bool,
    stop_hidden_fraction: Option<f64>,
) -> PyResult<SolverParams> {
    let hidden_cost = match hidden_cost {
        None => HiddenCost::Auto,
        Some(w) if w.is_finite() && w > 0.0 => HiddenCost::Fixed(w),
        Some(w) => {
            return Err(py_err(Error::param(
                "hidden_cost",
                format!("expected `auto` or a finite number > 0, got `{w}`"),
            )))
        }
    };
    let params = SolverParams {
        fan_out,
        hidden_cost,
        flows,
        exact,
        horizontal,
        stop_hidden_fraction,
    };
    params.validate().map_err(py_err)?;
    Ok(params)
}

fn check_tolerance(name: &'static str, t: usize) -> PyResult<()> {
    let max = seasonloc_core::trip::MAX_TOLERANCE;
    if t > max {
        return Err(py_err(Error::param(
            name,
            format!("must be at most {max}, got {t}"),
        )));
    }
    Ok(())
}

/// The Q x D similarity of `query` to `reference` descriptors: raw cosine `C` (Eq. 1), then
/// `normalization` (`floored`, `eq2`, `none`).
#[pyfunction]
fn similarity<'py>(
    py: Python<'py>,
    reference: PyReadonlyArray2<'py, f32>,
    query: PyReadonlyArray2<'py, f32>,
    normalization_name: &str,
) -> PyResult<Bound<'py, PyArray2<f32>>> {
    let (r, q) = (matrix(&reference)?, matrix(&query)?);
    let norm = normalization(normalization_name)?;
    let out = crate::without_gil(py, || cosine_matrix(&q, &r).and_then(|c| norm.apply(&c)))
        .map_err(py_err)?;
    array(py, out)
}

/// `seasonloc solve`: the graph on a similarity matrix (used as ĉ, or normalised by Eq. 2
/// first with `normalize`), the hypotheses and the predictions with confidence and
/// `p_correct` at `tolerance`.
#[pyfunction]
#[allow(clippy::too_many_arguments)]
fn solve(
    py: Python<'_>,
    similarity: PyReadonlyArray2<'_, f32>,
    fan_out: usize,
    hidden_cost: Option<f64>,
    flows: usize,
    exact: bool,
    horizontal: bool,
    stop_hidden_fraction: Option<f64>,
    normalize: bool,
    tolerance: usize,
) -> PyResult<Solved> {
    let params = solver_params(
        fan_out,
        hidden_cost,
        flows,
        exact,
        horizontal,
        stop_hidden_fraction,
    )?;
    check_tolerance("tolerance", tolerance)?;
    let m = matrix(&similarity)?;
    crate::without_gil(py, || {
        m.check_finite("similarity matrix")?;
        let chat = if normalize { normalize_columns(&m)? } else { m };
        let options = LocalizeOptions {
            solver: params,
            tolerance,
            ..LocalizeOptions::default()
        };
        let (solution, predictions) = solve_with_confidence(&chat, &options)?;
        Ok(solved(&solution, &predictions))
    })
    .map_err(py_err)
}

/// `seasonloc eval`'s flow method on descriptors: `C` (returned), `normalization`, the graph,
/// the confidences with `claim` and `p_correct` at `tolerance`.
#[pyfunction]
#[allow(clippy::too_many_arguments)]
fn localize<'py>(
    py: Python<'py>,
    reference: PyReadonlyArray2<'py, f32>,
    query: PyReadonlyArray2<'py, f32>,
    fan_out: usize,
    hidden_cost: Option<f64>,
    flows: usize,
    exact: bool,
    horizontal: bool,
    stop_hidden_fraction: Option<f64>,
    normalization_name: &str,
    claim: usize,
    tolerance: usize,
    confidence_radius: usize,
    confidence_discount: Option<f64>,
) -> PyResult<(Solved, Bound<'py, PyArray2<f32>>)> {
    let solver = solver_params(
        fan_out,
        hidden_cost,
        flows,
        exact,
        horizontal,
        stop_hidden_fraction,
    )?;
    check_tolerance("tolerance", tolerance)?;
    let options = LocalizeOptions {
        solver,
        normalization: normalization(normalization_name)?,
        confidence: ConfidenceParams {
            radius: confidence_radius,
            discount: confidence_discount,
            ..ConfidenceParams::default()
        },
        claim,
        tolerance,
    };
    let (r, q) = (matrix(&reference)?, matrix(&query)?);
    let (out, c) = crate::without_gil(py, || {
        // As `seasonloc eval` does: C, its normalisation, the graph with confidences.
        let c = cosine_matrix(&q, &r)?;
        let chat = options.normalization.apply(&c)?;
        let (solution, predictions) = solve_with_confidence(&chat, &options)?;
        Ok((solved(&solution, &predictions), c))
    })
    .map_err(py_err)?;
    Ok((out, array(py, c)?))
}

/// The best-match baseline on a similarity matrix.
#[pyfunction]
fn best_match(
    py: Python<'_>,
    similarity: PyReadonlyArray2<'_, f32>,
) -> PyResult<Vec<PredictionRow>> {
    let c = matrix(&similarity)?;
    crate::without_gil(py, || {
        c.check_finite("similarity matrix")?;
        Ok(prediction_rows(&baselines::best_match(&c)))
    })
    .map_err(py_err)
}

/// SeqSLAM on a (raw cosine) similarity matrix with OpenSeqSLAM's parameters by default.
#[pyfunction]
#[allow(clippy::too_many_arguments)]
fn seqslam(
    py: Python<'_>,
    similarity: PyReadonlyArray2<'_, f32>,
    ds: usize,
    enhance_window: usize,
    v_min: f64,
    v_max: f64,
    v_step: f64,
    exclusion_window: usize,
) -> PyResult<Vec<PredictionRow>> {
    let params = SeqSlamParams {
        ds,
        enhance_window,
        v_min,
        v_max,
        v_step,
        exclusion_window,
    };
    params.validate().map_err(py_err)?;
    let c = matrix(&similarity)?;
    crate::without_gil(py, || {
        c.check_finite("similarity matrix")?;
        Ok(prediction_rows(&baselines::seqslam(&c, &params)?))
    })
    .map_err(py_err)
}

/// The defaults the Python signatures show: `(seqslam, confidence discount)`.
#[pyfunction]
fn defaults() -> ((usize, usize, f64, f64, f64, usize), f64, usize) {
    let s = SeqSlamParams::default();
    (
        (
            s.ds,
            s.enhance_window,
            s.v_min,
            s.v_max,
            s.v_step,
            s.exclusion_window,
        ),
        seasonloc_core::confidence::DEFAULT_DISCOUNT,
        seasonloc_core::trip::MAX_TOLERANCE,
    )
}

pub(crate) fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(similarity, m)?)?;
    m.add_function(wrap_pyfunction!(solve, m)?)?;
    m.add_function(wrap_pyfunction!(localize, m)?)?;
    m.add_function(wrap_pyfunction!(best_match, m)?)?;
    m.add_function(wrap_pyfunction!(seqslam, m)?)?;
    m.add_function(wrap_pyfunction!(defaults, m)?)?;
    Ok(())
}
