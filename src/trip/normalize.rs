//! Online column normalisation of a trip: the map's prior column means ([`column_prior`]) and the
//! running means a trip divides each arriving row by (Eq. 2 with the prior; see the
//! [`crate::trip`] module doc for the formula and why rows are never revised).

use super::Trip;
use crate::{similarity, Error, Matrix, Result};

/// How many map images [`column_prior`] compares each reference with.
const PRIOR_SAMPLE: usize = 256;

/// The map's prior column means: for each reference, its mean cosine similarity with an evenly
/// spaced sample of at most 256 of the map's own images.
pub fn column_prior(references: &Matrix) -> Result<Vec<f32>> {
    let n = references.rows();
    if n == 0 {
        return Err(Error::Empty("the map has no reference images".into()));
    }
    let take = n.min(PRIOR_SAMPLE);
    let rows: Vec<&[f32]> = (0..take).map(|s| references.row(s * n / take)).collect();
    let sample = Matrix::from_rows(&rows)?;
    let c = similarity::cosine_matrix(&sample, references)?;
    let mut prior = vec![0.0f64; n];
    for row in c.iter_rows() {
        for (p, v) in prior.iter_mut().zip(row) {
            *p += f64::from(*v);
        }
    }
    Ok(prior.iter().map(|p| (p / take as f64) as f32).collect())
}

impl Trip {
    /// Normalises a batch with the running column means (see the module doc), updating them.
    pub(super) fn normalize(&mut self, c: &Matrix) -> Matrix {
        let n0 = self.params.prior_weight;
        if !self.params.normalize {
            return c.clone();
        }
        let mut out = Matrix::zeros(c.rows(), c.cols());
        let mut means = vec![0.0f64; c.cols()];
        let mut scratch = vec![0.0f64; c.cols()];
        for (i, row) in c.iter_rows().enumerate() {
            for (s, v) in self.column_sums.iter_mut().zip(row) {
                *s += f64::from(*v);
            }
            self.similarity_sum +=
                row.iter().map(|v| f64::from(*v)).sum::<f64>() / row.len() as f64;
            let n = (self.frames + i + 1) as f64;
            let scale = if self.prior_mean > 0.0 {
                (self.similarity_sum / n) / self.prior_mean
            } else {
                0.0
            };
            // Floor every column mean at half the median column mean, as the offline default
            // (`similarity::normalize_columns_floored`): a near-empty reference (a dark tunnel
            // frame) would otherwise get an exploding `ĉ` and hold the path for good.
            for (m, (p, s)) in means
                .iter_mut()
                .zip(self.prior.iter().zip(&self.column_sums))
            {
                *m = (n0 * scale * f64::from(*p) + s) / (n0 + n);
            }
            scratch.copy_from_slice(&means);
            let mid = scratch.len() / 2;
            let (_, median, _) = scratch.select_nth_unstable_by(mid, f64::total_cmp);
            let floor = similarity::MEAN_FLOOR_FRACTION * *median;
            let out_row = out.row_mut(i);
            for j in 0..row.len() {
                let mean = means[j].max(floor);
                out_row[j] = if mean > 1e-12 {
                    (f64::from(row[j]) / mean) as f32
                } else {
                    0.0
                };
            }
        }
        out
    }
}
