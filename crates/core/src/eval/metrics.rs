//! Precision-recall metrics of `spec.md` §4.
//!
//! Protocol, exactly:
//! * Scored queries are `0..num_queries` minus the [`Exclusions`]. Predictions for excluded
//!   queries are ignored; excluded queries never count as positives.
//! * `positives` = scored queries with at least one ground-truth reference. A prediction is
//!   correct when `|ref - g| <= tolerance` for some ground-truth `g` of its query; predictions
//!   for queries without a true match are always false positives.
//! * The confidence threshold is swept from high to low; predictions with *equal* confidence
//!   enter together (one sweep point per distinct confidence), so the result does not depend
//!   on the order of tied predictions. At each point precision = TP / (TP + FP) and
//!   recall = TP / positives (0 when there are no positives).
//! * `ap` = Σ_n (R_n − R_{n−1}) · P_n with R_0 = 0 (no interpolation); `recall_at_100p` /
//!   `recall_at_99p` = highest recall at a sweep point with precision >= 1.0 / >= 0.99 (tested
//!   in exact integer arithmetic), 0 if none; `max_f1` over the sweep points;
//!   `precision_at_full` = precision over all scored predictions (0 when there are none).
//! * `auc` = the area under the PR curve as VPR_Tutorial computes it (`createPR` with
//!   single-best-match and 100 thresholds, then `np.trapz(P, R)`), on the predictions: the
//!   curve starts at (R 0, P 1); at each of 100 thresholds equally spaced from the highest to
//!   the lowest scored confidence (`np.linspace`), precision and recall of the predictions with
//!   confidence >= the threshold; the trapezoids' area over recall. Unlike `ap` it depends on
//!   the confidences' spacing, not only their order. 0 without scored predictions.

use super::{Exclusions, GroundTruth, Prediction};
use crate::{Error, Result};

/// One point of the precision-recall sweep.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PrPoint {
    /// Predictions with confidence >= this value are accepted at this point.
    pub threshold: f64,
    /// TP / (TP + FP) at this threshold.
    pub precision: f64,
    /// TP / positives at this threshold.
    pub recall: f64,
}

/// The metrics of one method on one query sequence.
#[derive(Clone, Debug, PartialEq)]
pub struct Metrics {
    /// Average precision, Σ (R_n − R_{n−1}) · P_n over the sweep.
    pub ap: f64,
    /// Highest recall at a sweep point with precision 1.
    pub recall_at_100p: f64,
    /// Highest recall at a sweep point with precision >= 0.99.
    pub recall_at_99p: f64,
    /// Highest F1 score over the sweep.
    pub max_f1: f64,
    /// Precision over all scored predictions.
    pub precision_at_full: f64,
    /// Area under the PR curve as VPR_Tutorial computes it (see the module doc).
    pub auc: f64,
    /// Scored queries that have a true match (the recall denominator).
    pub positives: usize,
    /// Scored predictions (excluded queries' predictions are not counted).
    pub predicted: usize,
    /// Correct scored predictions.
    pub correct: usize,
    /// The sweep, from the highest threshold to the lowest.
    pub curve: Vec<PrPoint>,
}

/// Scores `predictions` against `gt` (see the module doc for the protocol).
///
/// Errors: a query index `>= num_queries` ([`Error::Shape`]), two predictions for one query
/// ([`Error::InvalidParameter`] `predictions`), a non-finite confidence ([`Error::NonFinite`]
/// with row = query, column = reference).
pub fn evaluate(
    predictions: &[Prediction],
    gt: &GroundTruth,
    num_queries: usize,
    tolerance: usize,
    exclusions: &Exclusions,
) -> Result<Metrics> {
    let mut seen = vec![false; num_queries];
    for p in predictions {
        if p.query >= num_queries {
            return Err(Error::Shape(format!(
                "prediction for query {} but there are only {num_queries} queries",
                p.query
            )));
        }
        if std::mem::replace(&mut seen[p.query], true) {
            return Err(Error::param(
                "predictions",
                format!("two predictions for query {}", p.query),
            ));
        }
        if !p.confidence.is_finite() {
            return Err(Error::NonFinite {
                what: "prediction confidence",
                row: p.query,
                col: p.reference,
                value: p.confidence,
            });
        }
    }
    let positives = (0..num_queries)
        .filter(|&q| !exclusions.contains(q) && gt.has_match(q))
        .count();
    let mut scored: Vec<(f64, bool)> = predictions
        .iter()
        .filter(|p| !exclusions.contains(p.query))
        .map(|p| (p.confidence, gt.is_correct(p.query, p.reference, tolerance)))
        .collect();
    scored.sort_by(|a, b| b.0.total_cmp(&a.0));

    let recall_of = |tp: usize| {
        if positives == 0 {
            0.0
        } else {
            tp as f64 / positives as f64
        }
    };
    let mut curve = Vec::new();
    let (mut tp, mut fp) = (0usize, 0usize);
    let (mut ap, mut prev_recall) = (0.0f64, 0.0f64);
    let (mut r100, mut r99, mut max_f1) = (0.0f64, 0.0f64, 0.0f64);
    let mut k = 0;
    while k < scored.len() {
        let threshold = scored[k].0;
        // Ties enter together: consume every prediction with this exact confidence.
        while k < scored.len() && scored[k].0 == threshold {
            if scored[k].1 {
                tp += 1;
            } else {
                fp += 1;
            }
            k += 1;
        }
        let precision = tp as f64 / (tp + fp) as f64;
        let recall = recall_of(tp);
        ap += (recall - prev_recall) * precision;
        prev_recall = recall;
        if fp == 0 {
            r100 = r100.max(recall);
        }
        if tp * 100 >= 99 * (tp + fp) {
            r99 = r99.max(recall);
        }
        if precision + recall > 0.0 {
            max_f1 = max_f1.max(2.0 * precision * recall / (precision + recall));
        }
        curve.push(PrPoint {
            threshold,
            precision,
            recall,
        });
    }
    let predicted = scored.len();
    let auc = vpr_tutorial_auc(&scored, positives);
    Ok(Metrics {
        ap,
        recall_at_100p: r100,
        recall_at_99p: r99,
        max_f1,
        precision_at_full: if predicted == 0 {
            0.0
        } else {
            tp as f64 / predicted as f64
        },
        auc,
        positives,
        predicted,
        correct: tp,
        curve,
    })
}

/// VPR_Tutorial's `createPR(..., matching='single', n_thresh=100)` followed by
/// `np.trapz(P, R)`, on `(confidence, correct)` pairs sorted by decreasing confidence, with
/// `positives` as its ground-truth positive count (`GTP`).
fn vpr_tutorial_auc(scored: &[(f64, bool)], positives: usize) -> f64 {
    const THRESHOLDS: usize = 100;
    let (Some(&(start, _)), Some(&(end, _))) = (scored.first(), scored.last()) else {
        return 0.0;
    };
    let gtp = positives as f64;
    let (mut p_prev, mut r_prev, mut area) = (1.0f64, 0.0f64, 0.0f64);
    // np.linspace(start, end, 100): start + i * step, the last exactly `end`.
    let step = (end - start) / (THRESHOLDS - 1) as f64;
    for i in 0..THRESHOLDS {
        let threshold = if i + 1 == THRESHOLDS {
            end
        } else {
            start + i as f64 * step
        };
        // Sorted by decreasing confidence: the accepted ones are a prefix.
        let accepted = scored.partition_point(|&(c, _)| c >= threshold);
        let tp = scored[..accepted].iter().filter(|&&(_, ok)| ok).count();
        let precision = tp as f64 / accepted.max(1) as f64;
        // np.count_nonzero(...) / 0 is nan (or inf) in numpy; seasonloc scores 0 recall then.
        let recall = if positives == 0 { 0.0 } else { tp as f64 / gtp };
        area += (recall - r_prev) * (precision + p_prev) / 2.0;
        (p_prev, r_prev) = (precision, recall);
    }
    area
}

#[cfg(test)]
mod tests {
    use super::*;

    fn p(query: usize, reference: usize, confidence: f64) -> Prediction {
        Prediction {
            query,
            reference,
            confidence,
            p_correct: None,
        }
    }

    fn diagonal(n: usize) -> GroundTruth {
        GroundTruth::from_pairs((0..n).map(|i| (i, i)))
    }

    fn close(a: f64, b: f64) -> bool {
        (a - b).abs() < 1e-12
    }

    #[test]
    fn hand_computed_example() {
        // 4 positives; ranking: correct (0.9), wrong (0.8), correct (0.7); query 3 unpredicted.
        let preds = [p(0, 0, 0.9), p(1, 5, 0.8), p(2, 2, 0.7)];
        let m = evaluate(&preds, &diagonal(4), 4, 0, &Exclusions::none()).unwrap();
        assert_eq!((m.positives, m.predicted, m.correct), (4, 3, 2));
        let pts: Vec<(f64, f64)> = m.curve.iter().map(|c| (c.precision, c.recall)).collect();
        assert_eq!(pts, vec![(1.0, 0.25), (0.5, 0.25), (2.0 / 3.0, 0.5)]);
        // AP = 0.25·1 + 0·0.5 + 0.25·(2/3).
        assert!(close(m.ap, 0.25 + 0.25 * 2.0 / 3.0), "{}", m.ap);
        assert!(close(m.recall_at_100p, 0.25) && close(m.recall_at_99p, 0.25));
        // F1 at (2/3, 1/2) = 4/7 beats F1 at (1, 1/4) = 0.4.
        assert!(close(m.max_f1, 4.0 / 7.0), "{}", m.max_f1);
        assert!(close(m.precision_at_full, 2.0 / 3.0));
        assert_eq!(m.curve[0].threshold, 0.9);
    }

    #[test]
    fn auc_is_vpr_tutorials_trapezoids_over_100_thresholds() {
        // As hand_computed_example: thresholds from 0.9 to 0.7 accept the first prediction
        // (P 1, R 1/4), then two (P 1/2, R 1/4), at 0.7 all three (P 2/3, R 1/2). From (0, 1):
        // 1/4 * (1 + 1) / 2 + 0 + 1/4 * (1/2 + 2/3) / 2.
        let preds = [p(0, 0, 0.9), p(1, 5, 0.8), p(2, 2, 0.7)];
        let m = evaluate(&preds, &diagonal(4), 4, 0, &Exclusions::none()).unwrap();
        assert!(
            close(m.auc, 0.25 + 0.25 * (0.5 + 2.0 / 3.0) / 2.0),
            "{}",
            m.auc
        );
        // One confidence for all: every threshold accepts everything.
        let flat = [p(0, 0, 0.5), p(1, 1, 0.5)];
        let m = evaluate(&flat, &diagonal(4), 4, 0, &Exclusions::none()).unwrap();
        assert!(close(m.auc, 0.5), "{}", m.auc);
        let none = evaluate(&[], &diagonal(4), 4, 0, &Exclusions::none()).unwrap();
        assert_eq!(none.auc, 0.0);
    }

    #[test]
    fn ties_enter_together_regardless_of_order() {
        // A correct and a wrong prediction share the top confidence: one sweep point at
        // precision 0.5, so there is no recall at 100 % precision.
        let a = [p(0, 0, 0.9), p(1, 7, 0.9), p(2, 2, 0.5)];
        let b = [p(1, 7, 0.9), p(0, 0, 0.9), p(2, 2, 0.5)];
        let gt = diagonal(3);
        let ma = evaluate(&a, &gt, 3, 0, &Exclusions::none()).unwrap();
        let mb = evaluate(&b, &gt, 3, 0, &Exclusions::none()).unwrap();
        assert_eq!(ma, mb);
        assert_eq!(ma.curve.len(), 2);
        assert_eq!(ma.recall_at_100p, 0.0);
        assert!(close(ma.curve[0].precision, 0.5) && close(ma.curve[0].recall, 1.0 / 3.0));
        assert!(
            close(ma.ap, 0.5 / 3.0 + (2.0 / 3.0) * (1.0 / 3.0)),
            "{}",
            ma.ap
        );
    }

    #[test]
    fn tolerance_widens_correctness() {
        let preds = [p(0, 1, 0.9), p(1, 3, 0.8)];
        let gt = diagonal(2);
        let strict = evaluate(&preds, &gt, 2, 0, &Exclusions::none()).unwrap();
        let loose = evaluate(&preds, &gt, 2, 1, &Exclusions::none()).unwrap();
        let looser = evaluate(&preds, &gt, 2, 2, &Exclusions::none()).unwrap();
        assert_eq!((strict.correct, loose.correct, looser.correct), (0, 1, 2));
    }

    #[test]
    fn exclusions_drop_predictions_and_positives() {
        // Query 0 (excluded) has a confident wrong prediction that would ruin precision.
        let preds = [p(0, 9, 1.0), p(1, 1, 0.5), p(2, 2, 0.4)];
        let ex = Exclusions::parse("0").unwrap();
        let m = evaluate(&preds, &diagonal(3), 3, 0, &ex).unwrap();
        assert_eq!((m.positives, m.predicted, m.correct), (2, 2, 2));
        assert!(close(m.ap, 1.0) && close(m.recall_at_100p, 1.0));
    }

    #[test]
    fn queries_without_true_match_are_not_positives_and_their_predictions_are_wrong() {
        // Ground truth only for queries 0 and 1; query 2 has none.
        let gt = GroundTruth::from_pairs([(0, 0), (1, 1)]);
        let preds = [p(2, 2, 0.95), p(0, 0, 0.9), p(1, 1, 0.8)];
        let m = evaluate(&preds, &gt, 3, 5, &Exclusions::none()).unwrap();
        assert_eq!((m.positives, m.correct), (2, 2));
        assert_eq!(m.recall_at_100p, 0.0);
        assert!(close(m.precision_at_full, 2.0 / 3.0));
        assert!(close(m.ap, 0.5 * 0.5 + 0.5 * (2.0 / 3.0)), "{}", m.ap);
    }

    #[test]
    fn perfect_ranking_has_ap_equal_to_the_recall_fraction() {
        // 10 positives, 6 predicted, all correct: AP = 0.6.
        let preds: Vec<Prediction> = (0..6).map(|i| p(i, i, 1.0 - i as f64 * 0.1)).collect();
        let m = evaluate(&preds, &diagonal(10), 10, 0, &Exclusions::none()).unwrap();
        assert!(close(m.ap, 0.6), "{}", m.ap);
        assert!(close(m.recall_at_100p, 0.6) && close(m.precision_at_full, 1.0));
    }

    #[test]
    fn recall_at_99p_can_exceed_recall_at_100p() {
        // 200 queries: one wrong prediction ranked 101st. Up to 100 correct: precision 1; at
        // 199 correct + 1 wrong: precision 0.995 >= 0.99.
        let mut preds: Vec<Prediction> = (0..200).map(|i| p(i, i, 1000.0 - i as f64)).collect();
        preds[100].reference = 150;
        let m = evaluate(&preds, &diagonal(200), 200, 0, &Exclusions::none()).unwrap();
        assert!(
            close(m.recall_at_100p, 100.0 / 200.0),
            "{}",
            m.recall_at_100p
        );
        assert!(close(m.recall_at_99p, 199.0 / 200.0), "{}", m.recall_at_99p);
    }

    #[test]
    fn no_predictions_and_no_positives_give_zero_metrics() {
        let m = evaluate(&[], &diagonal(3), 3, 0, &Exclusions::none()).unwrap();
        assert_eq!(
            (m.ap, m.max_f1, m.precision_at_full, m.positives),
            (0.0, 0.0, 0.0, 3)
        );
        assert!(m.curve.is_empty());
        let m = evaluate(
            &[p(0, 0, 1.0)],
            &GroundTruth::default(),
            1,
            0,
            &Exclusions::none(),
        )
        .unwrap();
        assert_eq!(
            (m.ap, m.recall_at_99p, m.positives, m.correct),
            (0.0, 0.0, 0, 0)
        );
    }

    #[test]
    fn invalid_predictions_are_rejected() {
        let gt = diagonal(3);
        let none = Exclusions::none();
        let err = evaluate(&[p(3, 0, 1.0)], &gt, 3, 0, &none).unwrap_err();
        assert!(matches!(err, Error::Shape(_)) && err.to_string().contains("query 3"));
        let err = evaluate(&[p(1, 0, 1.0), p(1, 2, 0.5)], &gt, 3, 0, &none).unwrap_err();
        assert!(
            err.to_string().contains("two predictions for query 1"),
            "{err}"
        );
        let err = evaluate(&[p(2, 1, f64::NAN)], &gt, 3, 0, &none).unwrap_err();
        assert!(
            matches!(err, Error::NonFinite { row: 2, col: 1, .. }),
            "{err}"
        );
    }
}
