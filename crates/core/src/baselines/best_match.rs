//! Best match: per query row, the reference column with the highest similarity.
//!
//! Confidence is that similarity itself. A row whose best value is `<= 0` (nothing resembles the
//! query, or a normalised matrix marked every column unusable) or non-finite gives no
//! prediction. Ties go to the lowest column index, so the result is deterministic.

use rayon::prelude::*;

use crate::localize::Prediction;
use crate::Matrix;

/// Per query row of `c` (Q x D, raw `C` or normalised `ĉ`) the column with the highest value,
/// with that value as confidence; rows whose best value is `<= 0` or non-finite are skipped.
/// Predictions are in increasing query order.
pub fn best_match(c: &Matrix) -> Vec<Prediction> {
    if c.cols() == 0 {
        return Vec::new();
    }
    (0..c.rows())
        .into_par_iter()
        .filter_map(|i| {
            let (j, v) = c.row(i).iter().copied().enumerate().fold(
                (0usize, f32::NEG_INFINITY),
                |best, (j, v)| if v > best.1 { (j, v) } else { best },
            );
            // A NaN row never beats NEG_INFINITY; an infinite best is rejected explicitly.
            (v.is_finite() && v > 0.0).then_some(Prediction {
                query: i,
                reference: j,
                confidence: f64::from(v),
                p_correct: None,
            })
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn picks_the_row_maximum_and_skips_unusable_rows() {
        let c = Matrix::from_rows(&[
            vec![0.1, 0.9, 0.3],
            vec![-0.2, -0.1, 0.0],
            vec![0.5, 0.5, 0.2],
            vec![f32::NAN, f32::NAN, f32::NAN],
            vec![0.0, 0.7, f32::INFINITY],
        ])
        .unwrap();
        let p = best_match(&c);
        assert_eq!(
            p,
            vec![
                Prediction {
                    query: 0,
                    reference: 1,
                    confidence: f64::from(0.9f32),
                    p_correct: None,
                },
                Prediction {
                    query: 2,
                    reference: 0,
                    confidence: 0.5,
                    p_correct: None,
                },
            ]
        );
    }

    #[test]
    fn empty_matrices_give_no_predictions() {
        assert!(best_match(&Matrix::zeros(3, 0)).is_empty());
        assert!(best_match(&Matrix::zeros(0, 3)).is_empty());
    }
}
