//! The evidence behind each offline prediction ([`crate::localize::solve_ranked`]): what the
//! offline `p_correct` is computed from. A function of the normalised matrix the graph was
//! solved on and of the predictions, so `eval`, `solve` and the service's localize give the
//! same evidence for the same inputs.

use rayon::prelude::*;

use crate::confidence::{best_node_cost, RowSpread, STRONG};
use crate::Matrix;

/// A prediction of [`crate::localize::solve_ranked`] with what its hypothesis's readout says beyond the
/// confidence: the evidence the calibration reads ([`crate::calibration`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RankedPrediction {
    /// The prediction, as [`crate::localize::solve_with_confidence`] gives it before its `p_correct`.
    pub prediction: crate::prediction::Prediction,
    /// Rank (0-based) of the hypothesis that gave it.
    pub rank: usize,
    /// [`crate::confidence::RowConfidence::hidden_ratio`] of its row on that hypothesis.
    pub hidden_ratio: f64,
}

/// The evidence of one prediction.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PredictionEvidence {
    /// Query row.
    pub query: usize,
    /// Predicted reference.
    pub reference: usize,
    /// Rank (0-based) of the hypothesis that gave the prediction.
    pub rank: usize,
    /// The discounted min-marginal ratio (the prediction's `confidence`).
    pub ratio: f64,
    /// Robust `z` of `ĉ` at the prediction in its row.
    pub contrast: f64,
    /// Mean contrast of the `L` predictions centred on this one (fewer at the ends), in query
    /// order: the stretch it lies in.
    pub stretch_centered: f64,
    /// Least mean contrast over the stretches of `L` consecutive predictions that hold this
    /// one (`NaN` with fewer than `L` predictions).
    pub stretch_min: f64,
    /// Mean advance in references per query row over the centred stretch.
    pub step_mean: f64,
    /// Mean absolute deviation of those advances from their median.
    pub step_spread: f64,
    /// `ĉ` at the prediction.
    pub chat: f64,
    /// `ĉ` at the prediction over the row's largest.
    pub chat_of_best: f64,
    /// Distance from the prediction to the row's largest `ĉ`.
    pub best_offset: usize,
    /// `W` minus the cost of the best node within `radius` of the prediction.
    pub stake: f64,
    /// The readout's cheapest route hidden at the row over the cheapest through the band
    /// ([`crate::confidence::RowConfidence::hidden_ratio`]).
    pub hidden_ratio: f64,
    /// The raw column mean of the predicted reference over the median column mean (how much
    /// Eq. 2 lifts its `ĉ`; 1 when not given).
    pub column: f64,
    /// Consecutive predictions (in query order) naming the same reference as this one, this
    /// one included: how long the route parks on the place.
    pub dwell: usize,
}

fn counted(x: f64) -> f64 {
    if x.is_nan() {
        0.0
    } else {
        x.clamp(-STRONG, STRONG)
    }
}

/// The evidence of each of `predictions` (in query order, as [`crate::localize::solve_ranked`]
/// returns them) on the normalised matrix `chat`; `column` is each reference's raw column mean
/// over the median column mean (when known), `w` the hidden cost the graph used, `len` the
/// stretch length `L` and `radius` the confidence's band radius.
pub fn prediction_evidence(
    chat: &Matrix,
    predictions: &[RankedPrediction],
    column: Option<&[f32]>,
    w: f64,
    len: usize,
    radius: usize,
) -> Vec<PredictionEvidence> {
    let len = len.max(1);
    let per_row: Vec<(f64, f64, usize, f64, f64)> = predictions
        .par_iter()
        .map_init(Vec::new, |scratch, r| {
            let p = &r.prediction;
            let row = chat.row(p.query);
            let v = row.get(p.reference).copied().unwrap_or(0.0);
            let contrast = RowSpread::of(row, scratch).map_or(0.0, |s| s.contrast(v));
            let (bj, bv) =
                row.iter()
                    .enumerate()
                    .fold((0usize, f32::NEG_INFINITY), |acc, (i, &x)| {
                        if x > acc.1 {
                            (i, x)
                        } else {
                            acc
                        }
                    });
            let of_best = if bv > 0.0 {
                f64::from(v) / f64::from(bv)
            } else {
                0.0
            };
            let stake = w - best_node_cost(row, p.reference, radius);
            (
                contrast,
                of_best,
                bj.abs_diff(p.reference),
                f64::from(v),
                stake,
            )
        })
        .collect();
    let n = predictions.len();
    // Runs of consecutive predictions at the same reference.
    let mut dwell = vec![1usize; n];
    let mut start = 0;
    while start < n {
        let j = predictions[start].prediction.reference;
        let mut end = start + 1;
        while end < n && predictions[end].prediction.reference == j {
            end += 1;
        }
        dwell[start..end].fill(end - start);
        start = end;
    }
    let z: Vec<f64> = per_row.iter().map(|r| counted(r.0)).collect();
    let mut prefix = vec![0.0; n + 1];
    for k in 0..n {
        prefix[k + 1] = prefix[k] + z[k];
    }
    let mean = |a: usize, b: usize| (prefix[b] - prefix[a]) / (b - a) as f64;
    // Mean of each full stretch by its first entry.
    let means: Vec<f64> = if n >= len {
        (0..=n - len).map(|s| mean(s, s + len)).collect()
    } else {
        Vec::new()
    };
    (0..n)
        .map(|k| {
            let RankedPrediction {
                prediction: p,
                rank,
                hidden_ratio,
            } = predictions[k];
            let half = len / 2;
            let a = k.saturating_sub(half);
            let b = (k + len - half).min(n);
            let stretch_centered = mean(a, b);
            let stretch_min = if means.is_empty() {
                f64::NAN
            } else {
                let lo = (k + 1).saturating_sub(len);
                let hi = k.min(means.len() - 1);
                means[lo..=hi].iter().copied().fold(f64::INFINITY, f64::min)
            };
            let steps: Vec<f64> = predictions[a..b]
                .windows(2)
                .map(|w| {
                    let (x, y) = (w[0].prediction, w[1].prediction);
                    (y.reference as f64 - x.reference as f64) / (y.query - x.query) as f64
                })
                .collect();
            let (step_mean, step_spread) = if steps.is_empty() {
                (f64::NAN, f64::NAN)
            } else {
                let m = steps.iter().sum::<f64>() / steps.len() as f64;
                let mut s = steps.clone();
                s.sort_by(f64::total_cmp);
                let med = s[s.len() / 2];
                (
                    m,
                    steps.iter().map(|x| (x - med).abs()).sum::<f64>() / steps.len() as f64,
                )
            };
            let r = per_row[k];
            PredictionEvidence {
                query: p.query,
                reference: p.reference,
                rank,
                ratio: p.confidence,
                contrast: r.0,
                stretch_centered,
                stretch_min,
                step_mean,
                step_spread,
                chat: r.3,
                chat_of_best: r.1,
                best_offset: r.2,
                stake: r.4,
                hidden_ratio,
                column: column
                    .and_then(|c| c.get(p.reference))
                    .map_or(1.0, |&c| f64::from(c)),
                dwell: dwell[k],
            }
        })
        .collect()
}

/// Each column's mean of the raw similarity matrix `c` over the median column mean: the
/// offline counterpart of a trip's prior over its median (how unlike the rest a reference
/// looks, which Eq. 2 turns into a lift of its `ĉ`).
pub fn relative_column_means(c: &Matrix) -> Vec<f32> {
    let (q, d) = (c.rows(), c.cols());
    if q == 0 || d == 0 {
        return vec![1.0; d];
    }
    let mut sums = vec![0.0f64; d];
    for row in c.iter_rows() {
        for (s, &v) in sums.iter_mut().zip(row) {
            *s += f64::from(v);
        }
    }
    let mut sorted = sums.clone();
    sorted.sort_by(f64::total_cmp);
    let median = sorted[d / 2];
    sums.iter()
        .map(|&s| {
            if median > 0.0 {
                (s / median) as f32
            } else {
                1.0
            }
        })
        .collect()
}
