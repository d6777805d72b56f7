//! The fitting and checking tools of the calibration, small enough to own: L2-regularised
//! logistic regression by Newton's method (IRLS), pool-adjacent-violators (isotonic regression)
//! and the expected calibration error with its reliability bins. `examples/calibrate.rs`
//! regenerates the shipped constants (`fitted.rs`) with them; nothing here runs in a request.

/// A logistic model: `p = 1 / (1 + exp(-(b0 + Σ b_k x_k)))`, `coefficients[0]` the intercept.
#[derive(Clone, Debug, PartialEq)]
pub struct Logistic {
    /// Intercept first, then one per feature.
    pub coefficients: Vec<f64>,
}

/// The logistic function.
pub fn sigmoid(t: f64) -> f64 {
    if t >= 0.0 {
        1.0 / (1.0 + (-t).exp())
    } else {
        let e = t.exp();
        e / (1.0 + e)
    }
}

impl Logistic {
    /// `p` for the features `x` (as many as the model has, the intercept excluded).
    pub fn predict(&self, x: &[f64]) -> f64 {
        sigmoid(linear(&self.coefficients, x))
    }
}

/// `b0 + Σ b_k x_k`.
pub fn linear(b: &[f64], x: &[f64]) -> f64 {
    b[0] + b[1..].iter().zip(x).map(|(b, x)| b * x).sum::<f64>()
}

/// Fits `y ~ x` (each row of `x` one sample's features, `y` in {0, 1}, `w` sample weights) by
/// minimising `Σ w_i · logloss_i + (l2 / 2) · |b_1..|²` (the intercept unpenalised: the
/// objective of scikit-learn's `LogisticRegression(C = 1 / l2)`), with Newton steps until the
/// step is below `1e-10` (at most 100). `None` when there are no samples or the system is
/// singular.
pub fn fit_logistic(x: &[Vec<f64>], y: &[bool], w: &[f64], l2: f64) -> Option<Logistic> {
    let n = x.len();
    if n == 0 || y.len() != n || w.len() != n {
        return None;
    }
    let k = x[0].len() + 1;
    let mut b = vec![0.0; k];
    for _ in 0..100 {
        let mut grad = vec![0.0; k];
        let mut hess = vec![vec![0.0; k]; k];
        for ((xi, &yi), &wi) in x.iter().zip(y).zip(w) {
            let p = sigmoid(linear(&b, xi));
            let r = wi * (p - f64::from(u8::from(yi)));
            let s = wi * (p * (1.0 - p)).max(1e-12);
            let f: Vec<f64> = std::iter::once(1.0).chain(xi.iter().copied()).collect();
            for (a, (g, row)) in grad.iter_mut().zip(hess.iter_mut()).enumerate() {
                *g += r * f[a];
                for (h, fc) in row.iter_mut().zip(&f).take(a + 1) {
                    *h += s * f[a] * fc;
                }
            }
        }
        for (a, (g, bi)) in grad.iter_mut().zip(&b).enumerate().skip(1) {
            *g += l2 * bi;
            hess[a][a] += l2;
        }
        // The lower triangle was accumulated; mirror it.
        let lower = hess.clone();
        for (a, row) in hess.iter_mut().enumerate() {
            for (c, h) in row.iter_mut().enumerate().skip(a + 1) {
                *h = lower[c][a];
            }
        }
        let step = solve(hess, grad)?;
        let mut size: f64 = 0.0;
        for (bi, si) in b.iter_mut().zip(&step) {
            *bi -= si;
            size = size.max(si.abs());
        }
        if size < 1e-10 {
            break;
        }
    }
    Some(Logistic { coefficients: b })
}

/// Solves `a · x = v` by Gaussian elimination with partial pivoting (`None` when singular).
fn solve(mut a: Vec<Vec<f64>>, mut v: Vec<f64>) -> Option<Vec<f64>> {
    let n = v.len();
    for col in 0..n {
        let pivot = (col..n).max_by(|&i, &j| a[i][col].abs().total_cmp(&a[j][col].abs()))?;
        if a[pivot][col].abs() < 1e-300 {
            return None;
        }
        a.swap(col, pivot);
        v.swap(col, pivot);
        let (top, rest) = a.split_at_mut(col + 1);
        let pivot_row = &top[col];
        for (k, row) in rest.iter_mut().enumerate() {
            let f = row[col] / pivot_row[col];
            if f != 0.0 {
                for (x, p) in row[col..].iter_mut().zip(&pivot_row[col..]) {
                    *x -= f * p;
                }
                v[col + 1 + k] -= f * v[col];
            }
        }
    }
    let mut x = vec![0.0; n];
    for row in (0..n).rev() {
        let s: f64 = (row + 1..n).map(|c| a[row][c] * x[c]).sum();
        x[row] = (v[row] - s) / a[row][row];
    }
    Some(x)
}

/// A monotone (non-decreasing) step function from a score to a probability: `p(s)` is the
/// value of the last knot at or below `s` (the first knot's value below it). What
/// pool-adjacent-violators ([`fit_isotonic`]) gives.
#[derive(Clone, Debug, PartialEq)]
pub struct Isotonic {
    /// `(score, p)` knots, scores increasing, `p` non-decreasing.
    pub knots: Vec<(f64, f64)>,
}

impl Isotonic {
    /// `p` at score `s`.
    pub fn predict(&self, s: f64) -> f64 {
        isotonic_at(&self.knots, s)
    }
}

/// `p` at score `s` of isotonic knots (see [`Isotonic`]); 0 without knots.
pub fn isotonic_at(knots: &[(f64, f64)], s: f64) -> f64 {
    match knots.partition_point(|&(k, _)| k <= s) {
        0 => knots.first().map_or(0.0, |k| k.1),
        i => knots[i - 1].1,
    }
}

/// Isotonic regression of `y` on `score` (weights `w`) by pool-adjacent-violators: the
/// non-decreasing step function closest to the labels in weighted squared error. Each knot
/// is a pooled block's smallest score and its mean label.
pub fn fit_isotonic(score: &[f64], y: &[bool], w: &[f64]) -> Isotonic {
    let mut order: Vec<usize> = (0..score.len()).collect();
    order.sort_by(|&a, &b| score[a].total_cmp(&score[b]));
    // Blocks: (first score, weighted sum of labels, weight).
    let mut blocks: Vec<(f64, f64, f64)> = Vec::new();
    for i in order {
        let (s, yi, wi) = (score[i], f64::from(u8::from(y[i])), w[i]);
        match blocks.last_mut() {
            // Equal scores always share a block (a step function cannot split them).
            Some(last) if last.0 == s => {
                last.1 += wi * yi;
                last.2 += wi;
            }
            _ => blocks.push((s, wi * yi, wi)),
        }
        while blocks.len() >= 2 {
            let n = blocks.len();
            let (a, b) = (blocks[n - 2], blocks[n - 1]);
            // Equal means pool too: the same function with fewer knots.
            if a.1 / a.2 >= b.1 / b.2 {
                blocks[n - 2] = (a.0, a.1 + b.1, a.2 + b.2);
                blocks.pop();
            } else {
                break;
            }
        }
    }
    Isotonic {
        knots: blocks
            .into_iter()
            .filter(|b| b.2 > 0.0)
            .map(|(s, sy, sw)| (s, sy / sw))
            .collect(),
    }
}

/// One bin of a reliability diagram: predictions with `p` in `[lo, hi)` (the last bin
/// includes 1).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ReliabilityBin {
    /// Lower edge.
    pub lo: f64,
    /// Upper edge.
    pub hi: f64,
    /// Predictions in the bin.
    pub count: usize,
    /// Their mean `p` (0 when empty).
    pub predicted: f64,
    /// The fraction of them that is right (0 when empty).
    pub observed: f64,
}

/// The reliability diagram of `(p, right)` pairs in `bins` equal bins over `[0, 1]`.
pub fn reliability(pairs: &[(f64, bool)], bins: usize) -> Vec<ReliabilityBin> {
    let bins = bins.max(1);
    let mut sums = vec![(0usize, 0.0f64, 0usize); bins];
    for &(p, ok) in pairs {
        let b = ((p * bins as f64).floor().max(0.0) as usize).min(bins - 1);
        sums[b].0 += 1;
        sums[b].1 += p;
        sums[b].2 += usize::from(ok);
    }
    sums.into_iter()
        .enumerate()
        .map(|(b, (n, sp, right))| ReliabilityBin {
            lo: b as f64 / bins as f64,
            hi: (b + 1) as f64 / bins as f64,
            count: n,
            predicted: if n > 0 { sp / n as f64 } else { 0.0 },
            observed: if n > 0 { right as f64 / n as f64 } else { 0.0 },
        })
        .collect()
}

/// Expected calibration error over `bins` equal bins: `Σ_b n_b / n · |mean p_b - right_b|`
/// (the definition of `check_trust.py`); 0 without pairs.
pub fn expected_calibration_error(pairs: &[(f64, bool)], bins: usize) -> f64 {
    let n = pairs.len();
    if n == 0 {
        return 0.0;
    }
    reliability(pairs, bins)
        .iter()
        .map(|b| b.count as f64 / n as f64 * (b.predicted - b.observed).abs())
        .sum()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn logistic_regression_recovers_a_known_model() {
        // Labels drawn deterministically from p = sigmoid(-1 + 2 x): for each x on a grid,
        // a share p of 200 copies is positive. Unregularised, the fit is the generating model.
        let (mut x, mut y) = (Vec::new(), Vec::new());
        for k in 0..41 {
            let xv = -2.0 + 0.1 * f64::from(k);
            let p = sigmoid(-1.0 + 2.0 * xv);
            let pos = (p * 200.0).round() as usize;
            for c in 0..200 {
                x.push(vec![xv]);
                y.push(c < pos);
            }
        }
        let w = vec![1.0; x.len()];
        let m = fit_logistic(&x, &y, &w, 0.0).unwrap();
        assert!((m.coefficients[0] + 1.0).abs() < 0.02, "{m:?}");
        assert!((m.coefficients[1] - 2.0).abs() < 0.02, "{m:?}");
        // A penalty shrinks the slope, not the intercept's role.
        let shrunk = fit_logistic(&x, &y, &w, 1000.0).unwrap();
        assert!(shrunk.coefficients[1].abs() < m.coefficients[1].abs());
        assert!(fit_logistic(&[], &[], &[], 1.0).is_none());
    }

    #[test]
    fn pool_adjacent_violators_gives_the_monotone_fit() {
        // Labels 0 1 0 1 1 at scores 1..5: the violation at 2-3 pools to 0.5.
        let s = [1.0, 2.0, 3.0, 4.0, 5.0];
        let y = [false, true, false, true, true];
        let m = fit_isotonic(&s, &y, &[1.0; 5]);
        assert_eq!(m.knots, vec![(1.0, 0.0), (2.0, 0.5), (4.0, 1.0)]);
        assert_eq!(m.predict(0.0), 0.0);
        assert_eq!(m.predict(2.5), 0.5);
        assert_eq!(m.predict(3.99), 0.5);
        assert_eq!(m.predict(9.0), 1.0);
        // Monotone whatever the labels.
        let y: Vec<bool> = (0..50).map(|i| (i * 7) % 3 == 0).collect();
        let s: Vec<f64> = (0..50).map(f64::from).collect();
        let m = fit_isotonic(&s, &y, &[1.0; 50]);
        assert!(m
            .knots
            .windows(2)
            .all(|k| k[0].1 <= k[1].1 && k[0].0 < k[1].0));
    }

    #[test]
    fn ece_is_the_weighted_gap_of_the_bins() {
        // Bin 9: p 0.95 twice, one right (gap 0.45); bin 0: p 0.05, wrong (gap 0.05).
        let pairs = [(0.95, true), (0.95, false), (0.05, false), (1.0, true)];
        let bins = reliability(&pairs, 10);
        assert_eq!(bins[9].count, 3);
        assert_eq!(bins[0].count, 1);
        let want = 3.0 / 4.0 * ((0.95 + 0.95 + 1.0) / 3.0 - 2.0 / 3.0) + 1.0 / 4.0 * 0.05;
        assert!((expected_calibration_error(&pairs, 10) - want).abs() < 1e-12);
        assert_eq!(expected_calibration_error(&[], 10), 0.0);
    }
}
