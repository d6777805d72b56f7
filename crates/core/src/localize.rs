//! One call from descriptor matrices to a localization result: similarity (Eq. 1), column
//! normalisation (Eq. 2), the graph solver, and per-query predictions with confidence.
//!
//! Shared by `seasonloc eval`, the HTTP service and trips, so all of them give the same answer
//! for the same descriptors and parameters.

use std::time::Instant;

use crate::calibration::RankedPrediction;
use crate::confidence::{score_hypotheses, ConfidenceParams, GraphParams};
use crate::picture::MatrixPicture;
pub use crate::prediction::Prediction;
use crate::similarity::{self, Normalization};
use crate::solver::{solve, Hypothesis, Solution, SolverParams};
use crate::{Matrix, Result};

/// Options of [`localize`].
#[derive(Clone, Debug, PartialEq)]
pub struct LocalizeOptions {
    /// Graph and solver parameters.
    pub solver: SolverParams,
    /// How `C` is normalised before the graph (default: Eq. 2 with a floored column mean).
    pub normalization: Normalization,
    /// How per-query confidences are computed.
    pub confidence: ConfidenceParams,
    /// Frames a prediction claims on each side of the frame it names (`c`; discounted
    /// confidence only): 0 names the path's match; `c > 0` names the frame within `c` of it
    /// whose `±c` neighbourhood the evidence supports best ([`crate::confidence::score_hypotheses`]).
    /// `eval` sets it to its scoring tolerance.
    pub claim: usize,
    /// Frames within which a prediction counts as right: what its `p_correct` is the
    /// probability of (default [`crate::trip::DEFAULT_TOLERANCE`], 1; `eval` sets it to its
    /// scoring tolerance).
    pub tolerance: usize,
}

impl Default for LocalizeOptions {
    fn default() -> Self {
        LocalizeOptions {
            solver: SolverParams::default(),
            normalization: Normalization::default(),
            confidence: ConfidenceParams::default(),
            claim: 0,
            tolerance: crate::trip::DEFAULT_TOLERANCE,
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
/// one prediction per query, so that further flows only add:
///
/// * the first (rank 1) hypothesis's prediction of a row stands unless the first's match is
///   not preferred by the local evidence (its confidence, the local min-marginal ratio of
///   [`crate::confidence`], is at most 1) and a further hypothesis matches that row where
///   the local evidence prefers it over every alternative (confidence above 1);
/// * a row the first hypothesis leaves hidden gets a further hypothesis's match on the same
///   condition (confidence above 1: better supported than hiding the row, whose routes are in
///   the ratio's "outside");
/// * and in both cases only when the further hypothesis is a *second visit*, not another
///   timing of the first's one: it names a place the first hypothesis does not match
///   (within the ratio's radius `r`) on any row within the confidence's evidence span of the
///   row ([`ConfidenceParams::evidence_span`]). Within that span the ratio cannot tell "the
///   route passes this place again" from "the route passes it a few frames earlier or later",
///   and between two
///   timings of one traversal the first hypothesis, the best complete route, is the better
///   supported one.
///
/// A row whose own evidence puts it off the map ([`crate::confidence::RowConfidence::off_map`]:
/// a local route hidden at the row costs less than the best one through the predicted place
/// plus a quarter of what hiding that route there would cost) gets no prediction from that
/// hypothesis; for the first, it counts as unsettled, so a further
/// hypothesis may place it on the conditions above.
///
/// Among several such hypotheses the most confident wins. On a single traversal the further
/// hypotheses are other timings of the one traversal, so `F = 2` keeps `F = 1`'s predictions;
/// on a loop the rows of the second pass revisit places the first matched a whole loop
/// earlier, which one route cannot drive back to.
pub fn solve_with_confidence(
    chat: &Matrix,
    options: &LocalizeOptions,
) -> Result<(Solution, Vec<Prediction>)> {
    let (solution, ranked) = solve_ranked(chat, options)?;
    let evidence = crate::calibration::prediction_evidence(
        chat,
        &ranked,
        None,
        solution.hidden_cost,
        options.confidence.stretch_len(),
        options.confidence.radius,
    );
    let predictions = ranked
        .into_iter()
        .zip(&evidence)
        .map(|(r, e)| Prediction {
            p_correct: Some(crate::calibration::offline_p_correct(e, options.tolerance)),
            ..r.prediction
        })
        .collect();
    Ok((solution, predictions))
}

/// [`solve_with_confidence`], each prediction with the rank (0-based) of the hypothesis that
/// gave it and its readout ([`RankedPrediction`]).
pub fn solve_ranked(
    chat: &Matrix,
    options: &LocalizeOptions,
) -> Result<(Solution, Vec<RankedPrediction>)> {
    let solution = solve(chat, &options.solver)?;
    let graph = GraphParams {
        fan_out: options.solver.fan_out,
        horizontal: options.solver.horizontal,
        hidden_cost: solution.hidden_cost,
    };
    let scored = score_hypotheses(
        chat,
        &graph,
        &solution.hypotheses,
        &options.confidence,
        options.claim,
    )?;
    let span = options.confidence.evidence_span();
    let first = solution
        .hypotheses
        .first()
        .map(|h| FirstVisits::new(h, chat.rows()));
    let mut best: Vec<Option<RankedPrediction>> = vec![None; chat.rows()];
    // Rows whose first prediction the local evidence prefers (ratio above 1): they stand.
    let mut settled = vec![false; chat.rows()];
    for (rank, rows) in scored.into_iter().enumerate() {
        // A row whose own evidence puts it off the map gets no prediction from that
        // hypothesis (a further one may still place it).
        for row in rows.into_iter().filter(|r| !r.off_map) {
            let (Some(slot), Some(done)) = (best.get_mut(row.query), settled.get_mut(row.query))
            else {
                continue;
            };
            let adds = if rank == 0 {
                *done = row.confidence > 1.0;
                true
            } else {
                !*done
                    && row.confidence > 1.0
                    && slot.is_none_or(|p| row.confidence > p.prediction.confidence)
                    && first.as_ref().is_none_or(|f| {
                        !f.visits_near(row.query, row.reference, span, options.confidence.radius)
                    })
            };
            if adds {
                *slot = Some(RankedPrediction {
                    prediction: Prediction {
                        query: row.query,
                        reference: row.reference,
                        confidence: row.confidence,
                        p_correct: None,
                    },
                    rank,
                    hidden_ratio: row.hidden_ratio,
                });
            }
        }
    }
    Ok((solution, best.into_iter().flatten().collect()))
}

/// The references the first hypothesis matches, per query row (all of a row's matches).
struct FirstVisits {
    matched: Vec<Vec<usize>>,
}

impl FirstVisits {
    fn new(first: &Hypothesis, rows: usize) -> Self {
        let mut matched = vec![Vec::new(); rows];
        for row in &first.rows {
            if let Some(m) = matched.get_mut(row.query) {
                m.extend(row.matches.iter().map(|m| m.reference));
            }
        }
        FirstVisits { matched }
    }

    /// Whether the first hypothesis matches a reference within `radius` of `reference` on a
    /// row within `span` of `query`.
    fn visits_near(&self, query: usize, reference: usize, span: usize, radius: usize) -> bool {
        let rows =
            query.saturating_sub(span)..=(query + span).min(self.matched.len().saturating_sub(1));
        self.matched
            .get(rows)
            .into_iter()
            .flatten()
            .flatten()
            .any(|&j| j.abs_diff(reference) <= radius)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::solver::HiddenCost;

    /// A route of `n` places driven twice (a loop): query rows `0..n` and `n..2n` both see
    /// places `0..n` (similarity 2 on the true place, 1 elsewhere, a little texture).
    fn loop_route(n: usize) -> Matrix {
        let mut m = Matrix::zeros(2 * n, n);
        for i in 0..2 * n {
            for j in 0..n {
                let texture = ((i * 7 + j * 13) % 5) as f32 * 0.02;
                m.set(i, j, if j == i % n { 2.0 } else { 1.0 + texture });
            }
        }
        m
    }

    fn options(flows: usize) -> LocalizeOptions {
        LocalizeOptions {
            solver: SolverParams {
                flows,
                hidden_cost: HiddenCost::Fixed(0.9),
                ..SolverParams::default()
            },
            ..LocalizeOptions::default()
        }
    }

    #[test]
    fn a_matched_row_whose_evidence_puts_it_off_the_map_gets_no_prediction() {
        // Found by a random search of 6 x 6 matrices: the path matches every row but row 1
        // at reference 1, and row 2's discounted min-marginals prefer a route hidden there.
        #[rustfmt::skip]
        let values = vec![
            0.9, 2.3, 1.5, 0.5, 2.3, 0.1,
            1.0, 0.3, 2.0, 2.0, 0.1, 2.4,
            1.6, 1.3, 0.5, 1.0, 0.8, 0.3,
            0.4, 2.4, 0.1, 0.8, 0.1, 1.5,
            1.3, 1.3, 0.2, 0.6, 1.6, 1.9,
            1.5, 2.1, 0.5, 1.3, 0.8, 1.2,
        ];
        let chat = Matrix::from_vec(6, 6, values).unwrap();
        let options = LocalizeOptions {
            solver: SolverParams {
                fan_out: 2,
                hidden_cost: HiddenCost::Fixed(1.0),
                ..SolverParams::default()
            },
            ..LocalizeOptions::default()
        };
        let (solution, predictions) = solve_with_confidence(&chat, &options).unwrap();
        let matched: Vec<usize> = solution.hypotheses[0]
            .rows
            .iter()
            .filter(|r| !r.matches.is_empty())
            .map(|r| r.query)
            .collect();
        assert_eq!(matched, vec![0, 2, 3, 4, 5]);
        let graph = GraphParams {
            fan_out: 2,
            horizontal: true,
            hidden_cost: 1.0,
        };
        let scored =
            score_hypotheses(&chat, &graph, &solution.hypotheses, &options.confidence, 0).unwrap();
        let off: Vec<usize> = scored[0]
            .iter()
            .filter(|r| r.off_map)
            .map(|r| r.query)
            .collect();
        assert_eq!(off, vec![2]);
        let predicted: Vec<usize> = predictions.iter().map(|p| p.query).collect();
        assert_eq!(predicted, vec![0, 3, 4, 5]);
    }

    #[test]
    fn a_second_flow_recovers_the_second_pass_of_a_loop_and_only_adds() {
        let chat = loop_route(30);
        let (_, one) = solve_with_confidence(&chat, &options(1)).unwrap();
        let (solution, two) = solve_with_confidence(&chat, &options(2)).unwrap();
        assert_eq!(solution.hypotheses.len(), 2);
        // F = 1 follows one pass; the other pass is hidden (the route cannot go back).
        let correct = |p: &[Prediction], rows: std::ops::Range<usize>| {
            p.iter()
                .filter(|p| rows.contains(&p.query) && p.reference == p.query % 30)
                .count()
        };
        let (a1, b1) = (correct(&one, 0..30), correct(&one, 30..60));
        assert!(a1.max(b1) >= 27 && a1.min(b1) <= 3, "F=1: {a1} / {b1}");
        // F = 2 finds both passes.
        let (a2, b2) = (correct(&two, 0..30), correct(&two, 30..60));
        assert!(a2 >= 27 && b2 >= 27, "F=2: {a2} / {b2}");
        // And changes none of F = 1's predictions: here the first path hides the second pass
        // (fixed W), so it has no match the local evidence goes against. Replacing such
        // matches is tested on derived loops (tests/derived_routes, `loop_route`).
        // (A prediction is its query, place and confidence; `p_correct` reads every
        // hypothesis, so a second flow may move it.)
        let place = |p: &Prediction| (p.query, p.reference, p.confidence);
        for p in &one {
            assert!(
                two.iter().any(|q| place(q) == place(p)),
                "{p:?} changed with F = 2"
            );
        }
    }
}
