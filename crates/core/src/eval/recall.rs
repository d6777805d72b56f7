//! Recall@N, the retrieval metric of the visual place recognition field, on a similarity
//! matrix: a query counts at `N` when one of its `N` most similar references is a true match.
//!
//! Why beside the PR metrics: those score one prediction per query by its confidence; Recall@N
//! scores the *ranking* of every reference for every query, which is what descriptor papers
//! report (VPR-methods-evaluation's `recall@N`, VPR_Tutorial's `recallAtK`). Definitions and
//! sources: `docs/metrics.md`.
//!
//! Protocol, exactly:
//! * The similarity matrix is Q x D (one row per query, higher = more similar). A row is ranked
//!   by decreasing similarity; equal similarities rank the lower reference index first, so the
//!   result does not depend on a sort's stability.
//! * Scored queries are `0..Q` minus the [`Exclusions`], and only those with at least one true
//!   reference (VPR_Tutorial discards queries without a match; VPR-methods-evaluation's datasets
//!   have one for every query, so the two agree there).
//! * A reference is a true match when [`GroundTruth::is_correct`] at `tolerance` (0: the ground
//!   truth's references only, as both sources count).
//! * Recall@N = scored queries whose best-ranked true match has rank `< N`, over the scored
//!   queries (0 when there are none).

use super::{Exclusions, GroundTruth};
use crate::{Error, Matrix, Result};

/// The `N`s the field reports (VPR-methods-evaluation's default `recall_values` up to 20).
pub const STANDARD_NS: [usize; 4] = [1, 5, 10, 20];

/// Recall at one `N`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RecallAtN {
    /// How many top-ranked references a query may look at.
    pub n: usize,
    /// Fraction of the scored queries with a true match among their `n` most similar
    /// references, in `[0, 1]`.
    pub recall: f64,
}

/// Recall@N of `similarity` (Q x D, queries as rows) for each of `ns` (see the module doc).
///
/// Errors: an `N` of 0 ([`Error::InvalidParameter`] `n`), a non-finite similarity
/// ([`Error::NonFinite`]), a ground truth naming a query or reference outside the matrix
/// ([`Error::Shape`]).
pub fn recall_at_n(
    similarity: &Matrix,
    gt: &GroundTruth,
    ns: &[usize],
    tolerance: usize,
    exclusions: &Exclusions,
) -> Result<Vec<RecallAtN>> {
    if let Some(n) = ns.iter().find(|&&n| n == 0) {
        return Err(Error::param("n", format!("Recall@N needs N >= 1, got {n}")));
    }
    similarity.check_finite("similarity matrix")?;
    let (queries, refs) = (similarity.rows(), similarity.cols());
    if let Some(q) = gt.max_query_index().filter(|&q| q >= queries) {
        return Err(Error::Shape(format!(
            "the ground truth names query {q} but the similarity matrix has {queries} rows"
        )));
    }
    if let Some(r) = gt.max_reference_index().filter(|&r| r >= refs) {
        return Err(Error::Shape(format!(
            "the ground truth names reference {r} but the similarity matrix has {refs} columns"
        )));
    }
    let mut scored = 0usize;
    // For each scored query, the rank (0-based) of its best-ranked true match, if any.
    let mut best_ranks = Vec::new();
    for q in (0..queries).filter(|&q| !exclusions.contains(q) && gt.has_match(q)) {
        scored += 1;
        let row = similarity.row(q);
        // The best-ordered true match: highest similarity, lowest index among equals.
        let best =
            (0..refs)
                .filter(|&j| gt.is_correct(q, j, tolerance))
                .fold(None::<usize>, |best, j| match best {
                    Some(b) if row[b] >= row[j] => Some(b),
                    _ => Some(j),
                });
        if let Some(b) = best {
            let v = row[b];
            let ahead = row
                .iter()
                .enumerate()
                .filter(|&(j, &s)| s > v || (s == v && j < b))
                .count();
            best_ranks.push(ahead);
        }
    }
    Ok(ns
        .iter()
        .map(|&n| RecallAtN {
            n,
            recall: if scored == 0 {
                0.0
            } else {
                best_ranks.iter().filter(|&&r| r < n).count() as f64 / scored as f64
            },
        })
        .collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn close(a: f64, b: f64) -> bool {
        (a - b).abs() < 1e-12
    }

    /// 6 queries x 6 references; query i ranks reference (i + r) % 6 at rank r (distinct
    /// values), so a true match at rank r is found from N = r + 1 on.
    fn rotated(d: usize) -> Matrix {
        let mut m = Matrix::zeros(d, d);
        for i in 0..d {
            for j in 0..d {
                let r = (j + d - i) % d;
                m.set(i, j, 1.0 - 0.1 * r as f32);
            }
        }
        m
    }

    #[test]
    fn hand_computed_recall_at_n() {
        let s = rotated(6);
        // Ranks of the true matches: q0 0, q1 1, q2 {4, 2} -> 2, q3 5, q4 0, q5: no match.
        let ranks: [&[usize]; 5] = [&[0], &[1], &[4, 2], &[5], &[0]];
        let gt = GroundTruth::from_pairs(
            ranks
                .iter()
                .enumerate()
                .flat_map(|(q, rs)| rs.iter().map(move |r| (q, (q + r) % 6))),
        );
        let got = recall_at_n(&s, &gt, &[1, 2, 3, 5, 6], 0, &Exclusions::none()).unwrap();
        // 5 scored queries (q5 has no match): at N=1 {q0, q4}; N=2 +q1; N=3 +q2; N=6 +q3.
        let want = [2.0 / 5.0, 3.0 / 5.0, 4.0 / 5.0, 4.0 / 5.0, 1.0];
        for (g, w) in got.iter().zip(want) {
            assert!(close(g.recall, w), "N={}: {} != {w}", g.n, g.recall);
        }
        // Excluding q0 leaves 4 scored queries.
        let ex = Exclusions::parse("0").unwrap();
        let got = recall_at_n(&s, &gt, &[1], 0, &ex).unwrap();
        assert!(close(got[0].recall, 1.0 / 4.0));
    }

    #[test]
    fn tolerance_widens_true_matches_and_ties_rank_the_lower_index_first() {
        let s = rotated(6);
        // q1's true match is reference 3 (rank 2); with tolerance 1, reference 2 (rank 1) counts.
        let gt = GroundTruth::from_pairs([(1, 3)]);
        let at = |t| recall_at_n(&s, &gt, &[1, 2], t, &Exclusions::none()).unwrap();
        assert_eq!((at(0)[0].recall, at(0)[1].recall), (0.0, 0.0));
        assert_eq!((at(1)[0].recall, at(1)[1].recall), (0.0, 1.0));
        // All equal: reference 0 ranks first, so a match at 2 needs N = 3.
        let flat = Matrix::from_vec(1, 4, vec![0.5; 4]).unwrap();
        let gt = GroundTruth::from_pairs([(0, 2)]);
        let got = recall_at_n(&flat, &gt, &[2, 3], 0, &Exclusions::none()).unwrap();
        assert_eq!((got[0].recall, got[1].recall), (0.0, 1.0));
    }

    #[test]
    fn bad_input_is_an_error() {
        let s = rotated(3);
        let gt = GroundTruth::from_pairs([(0, 0)]);
        assert!(recall_at_n(&s, &gt, &[0], 0, &Exclusions::none()).is_err());
        let far = GroundTruth::from_pairs([(5, 0)]);
        let err = recall_at_n(&s, &far, &[1], 0, &Exclusions::none()).unwrap_err();
        assert!(err.to_string().contains("query 5"), "{err}");
        let mut nan = rotated(3);
        nan.set(1, 1, f32::NAN);
        assert!(matches!(
            recall_at_n(&nan, &gt, &[1], 0, &Exclusions::none()),
            Err(Error::NonFinite { .. })
        ));
    }
}
