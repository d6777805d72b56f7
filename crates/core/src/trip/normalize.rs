//! Online column normalisation of a trip: the map's prior column means ([`column_prior`]) and the
//! running means a trip divides each arriving row by (Eq. 2 with the prior; see the
//! [`crate::trip`] module doc for the formula and why rows are never revised).

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

/// The running sums of the raw rows a trip has seen: the whole state of its online Eq. 2
/// besides the (constant) prior.
#[derive(Clone, Debug, PartialEq)]
pub(super) struct Sums {
    /// `Σ_i c_ij` per column.
    pub columns: Vec<f64>,
    /// `Σ_i mean_j c_ij`.
    pub similarity: f64,
}

impl Sums {
    pub fn new(d: usize) -> Self {
        Sums {
            columns: vec![0.0; d],
            similarity: 0.0,
        }
    }

    /// Adds one raw row.
    pub fn add(&mut self, row: &[f32]) {
        for (s, v) in self.columns.iter_mut().zip(row) {
            *s += f64::from(*v);
        }
        self.similarity += row.iter().map(|v| f64::from(*v)).sum::<f64>() / row.len() as f64;
    }
}

/// The constant part of the normalisation: the map's prior and its weight.
pub(super) struct Prior<'a> {
    pub means: &'a [f32],
    pub mean: f64,
    pub weight: f64,
}

/// Work buffers of [`Prior::normalize_row`].
#[derive(Default)]
pub(super) struct NormScratch {
    means: Vec<f64>,
    select: Vec<f64>,
}

impl Prior<'_> {
    /// Adds raw `row` (the `n`-th row of the trip, counting from 1) to `sums` and writes its
    /// normalised values to `out`: `c_ij / max(m_j, floor)` with the running means of the
    /// module doc.
    pub fn normalize_row(
        &self,
        sums: &mut Sums,
        n: usize,
        row: &[f32],
        out: &mut [f32],
        s: &mut NormScratch,
    ) {
        let n0 = self.weight;
        sums.add(row);
        let n = n as f64;
        let scale = if self.mean > 0.0 {
            (sums.similarity / n) / self.mean
        } else {
            0.0
        };
        s.means.resize(row.len(), 0.0);
        // Floor every column mean at half the median column mean, as the offline default
        // (`similarity::normalize_columns_floored`): a near-empty reference (a dark tunnel
        // frame) would otherwise get an exploding `ĉ` and hold the path for good.
        for (m, (p, c)) in s.means.iter_mut().zip(self.means.iter().zip(&sums.columns)) {
            *m = (n0 * scale * f64::from(*p) + c) / (n0 + n);
        }
        s.select.clear();
        s.select.extend_from_slice(&s.means);
        let mid = s.select.len() / 2;
        let (_, median, _) = s.select.select_nth_unstable_by(mid, f64::total_cmp);
        let floor = similarity::MEAN_FLOOR_FRACTION * *median;
        for ((o, &v), &m) in out.iter_mut().zip(row).zip(&s.means) {
            let mean = m.max(floor);
            *o = if mean > 1e-12 {
                (f64::from(v) / mean) as f32
            } else {
                0.0
            };
        }
    }
}
