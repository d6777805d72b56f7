//! SeqSLAM (Milford & Wyeth, ICRA 2012) as implemented by OpenSeqSLAM (Sünderhauf 2013), run
//! on a given similarity matrix instead of on its own patch-normalised image differences.
//!
//! Steps, for a Q x D similarity matrix `c`:
//! 1. **Difference matrix** `d_ij = 1 - c_ij` (cosine distance).
//! 2. **Local contrast enhancement** ([`enhance_contrast`]): each `d_ij` becomes
//!    `(d_ij - mean) / std` over the window of columns `j - w/2 ..= j + w/2` (clipped at the
//!    matrix border) of its query row `i` — OpenSeqSLAM's window along the reference axis with
//!    `R = w`. `std` is the sample standard deviation (as MATLAB's `std`), floored at
//!    [`STD_FLOOR`] so constant windows (e.g. identical black frames) give 0 instead of a
//!    division by zero. As in OpenSeqSLAM (`DD - min(min(DD))`) the whole enhanced matrix is then
//!    shifted so that its minimum is 0: every score below is a sum of non-negative values, which
//!    makes the best/second-best ratio meaningful.
//! 3. **Trajectory search**: for query `i`, the `ds` query frames `i-ds+1 ..= i` *ending* at `i`
//!    (online form; OpenSeqSLAM centres the window), for every velocity `v` in
//!    `v_min, v_min + v_step, .. <= v_max` and every end column `j`, the score is the sum of the
//!    enhanced differences at `(i - t, j - round(v·t))`, `t = 0..ds`. Lines that would leave the
//!    matrix on the left are invalid (OpenSeqSLAM pads with infinite cost), so end columns
//!    `j < round(v·(ds-1))` only have the slower lines, or none. The score of `j` is the minimum
//!    over velocities; the match is the `j` with the smallest score (first one on ties).
//!    Queries with fewer than `ds` predecessors (`i < ds - 1`) use the `i + 1` frames that
//!    exist; their scores are sums of fewer terms and so less discriminative.
//! 4. **Confidence**: OpenSeqSLAM's uniqueness ratio `best / second`, where `second` is the
//!    smallest score outside the columns `best_j ± exclusion_window`, is lower-is-better. We
//!    report the monotone equivalent `1 - best / second` in `[0, 1]` (higher = more certain).
//!    It is 0 when no finite score exists outside the window (nothing to compare with) or when
//!    `second == 0`.
//!
//! A query gets no prediction only when no line fits into the matrix at all.
//! Cost: `O(Q·D)` for the enhancement, `O(Q·D·ds·n_velocities)` for the search, parallel
//! over queries (rayon); velocities that round to the same column offsets are searched once.

use rayon::prelude::*;

use crate::localize::Prediction;
use crate::{Error, Matrix, Result};

/// Smallest standard deviation used in the contrast enhancement.
pub const STD_FLOOR: f64 = 1e-6;
/// Largest accepted trajectory length `ds`.
pub const MAX_DS: usize = 1000;
/// Largest accepted number of velocities `(v_max - v_min) / v_step + 1`.
pub const MAX_VELOCITIES: usize = 1000;

/// Parameters of [`seqslam`]; the defaults are OpenSeqSLAM's.
#[derive(Clone, Debug, PartialEq)]
pub struct SeqSlamParams {
    /// Trajectory length in query frames (`ds`), >= 1.
    pub ds: usize,
    /// Contrast-enhancement window along the reference axis (`R`), >= 2.
    pub enhance_window: usize,
    /// Slowest velocity in reference frames per query frame, > 0.
    pub v_min: f64,
    /// Fastest velocity, >= `v_min`.
    pub v_max: f64,
    /// Velocity step, > 0.
    pub v_step: f64,
    /// Columns within `±exclusion_window` of the best are ignored when looking for the second
    /// best score.
    pub exclusion_window: usize,
}

impl Default for SeqSlamParams {
    fn default() -> Self {
        SeqSlamParams {
            ds: 10,
            enhance_window: 10,
            v_min: 0.8,
            v_max: 1.2,
            v_step: 0.1,
            exclusion_window: 10,
        }
    }
}

impl SeqSlamParams {
    /// Checks every parameter's range.
    pub fn validate(&self) -> Result<()> {
        if self.ds == 0 || self.ds > MAX_DS {
            return Err(Error::param(
                "ds",
                format!("must be between 1 and {MAX_DS}, got {}", self.ds),
            ));
        }
        if self.enhance_window < 2 {
            return Err(Error::param(
                "enhance_window",
                format!("must be at least 2, got {}", self.enhance_window),
            ));
        }
        if !(self.v_min.is_finite() && self.v_min > 0.0) {
            return Err(Error::param(
                "v_min",
                format!("must be a finite number > 0, got {}", self.v_min),
            ));
        }
        if !(self.v_max.is_finite() && self.v_max >= self.v_min) {
            return Err(Error::param(
                "v_max",
                format!(
                    "must be finite and >= v_min ({}), got {}",
                    self.v_min, self.v_max
                ),
            ));
        }
        if !(self.v_step.is_finite() && self.v_step > 0.0) {
            return Err(Error::param(
                "v_step",
                format!("must be a finite number > 0, got {}", self.v_step),
            ));
        }
        let n = (self.v_max - self.v_min) / self.v_step;
        if n >= MAX_VELOCITIES as f64 {
            return Err(Error::param(
                "v_step",
                format!(
                    "gives {} velocities between {} and {}, at most {MAX_VELOCITIES} allowed",
                    n.floor() + 1.0,
                    self.v_min,
                    self.v_max
                ),
            ));
        }
        Ok(())
    }

    /// The velocities searched: `v_min, v_min + v_step, ...` up to `v_max` (with a tolerance of
    /// 1e-9 for accumulated rounding).
    pub fn velocities(&self) -> Vec<f64> {
        let mut v = Vec::new();
        let mut k = 0usize;
        loop {
            let x = self.v_min + k as f64 * self.v_step;
            if x > self.v_max + 1e-9 || v.len() >= MAX_VELOCITIES {
                break v;
            }
            v.push(x);
            k += 1;
        }
    }
}

/// The contrast-enhanced difference matrix (steps 1-2 of the module doc): `1 - c`, normalised
/// per element by the mean and sample std of its `window` neighbours along the reference axis,
/// then shifted so that the global minimum is 0. Fails on an empty or non-finite matrix or a
/// window < 2.
pub fn enhance_contrast(c: &Matrix, window: usize) -> Result<Matrix> {
    if c.rows() == 0 || c.cols() == 0 {
        return Err(Error::Empty(format!(
            "similarity matrix is {}x{}",
            c.rows(),
            c.cols()
        )));
    }
    if window < 2 {
        return Err(Error::param(
            "enhance_window",
            format!("must be at least 2, got {window}"),
        ));
    }
    c.check_finite("similarity matrix")?;
    let cols = c.cols();
    let half = window / 2;
    let mut e = Matrix::zeros(c.rows(), cols);
    e.as_mut_slice()
        .par_chunks_mut(cols)
        .zip(c.as_slice().par_chunks(cols))
        .for_each_init(
            || (vec![0.0f64; cols + 1], vec![0.0f64; cols + 1]),
            |(s1, s2), (out, row)| {
                // Prefix sums of d and d² make every window O(1).
                for (j, &v) in row.iter().enumerate() {
                    let d = 1.0 - f64::from(v);
                    s1[j + 1] = s1[j] + d;
                    s2[j + 1] = s2[j] + d * d;
                }
                for (j, o) in out.iter_mut().enumerate() {
                    let (a, b) = (j.saturating_sub(half), (j + half).min(cols - 1) + 1);
                    let n = (b - a) as f64;
                    let (sum, sq) = (s1[b] - s1[a], s2[b] - s2[a]);
                    let mean = sum / n;
                    let var = if n > 1.0 {
                        ((sq - sum * mean) / (n - 1.0)).max(0.0)
                    } else {
                        0.0
                    };
                    let d = 1.0 - f64::from(row[j]);
                    *o = ((d - mean) / var.sqrt().max(STD_FLOOR)) as f32;
                }
            },
        );
    let min = e
        .as_slice()
        .par_iter()
        .copied()
        .reduce(|| f32::INFINITY, f32::min);
    e.as_mut_slice().par_iter_mut().for_each(|v| *v -= min);
    Ok(e)
}

/// SeqSLAM on the similarity matrix `c` (Q x D); see the module doc for the exact steps and the
/// confidence. Predictions are in increasing query order.
pub fn seqslam(c: &Matrix, params: &SeqSlamParams) -> Result<Vec<Prediction>> {
    params.validate()?;
    let e = enhance_contrast(c, params.enhance_window)?;
    let cols = e.cols();
    let velocities = params.velocities();
    let predictions = (0..e.rows())
        .into_par_iter()
        .map_init(
            || (vec![0.0f32; cols], vec![0.0f32; cols]),
            |(score, acc), i| {
                search_query(&e, i, params, &velocities, score, acc).map(|(j, conf)| Prediction {
                    query: i,
                    reference: j,
                    confidence: conf,
                    p_correct: None,
                })
            },
        )
        .flatten()
        .collect();
    Ok(predictions)
}

/// Trajectory search for query `i`: `(best column, confidence)`, or `None` when no line fits.
fn search_query(
    e: &Matrix,
    i: usize,
    params: &SeqSlamParams,
    velocities: &[f64],
    score: &mut [f32],
    acc: &mut [f32],
) -> Option<(usize, f64)> {
    let cols = e.cols();
    let frames = params.ds.min(i + 1);
    score.fill(f32::INFINITY);
    let mut seen: Vec<Vec<usize>> = Vec::with_capacity(velocities.len());
    for &v in velocities {
        let offsets: Vec<usize> = (0..frames)
            .map(|t| (v * t as f64).round() as usize)
            .collect();
        if seen.contains(&offsets) {
            continue;
        }
        let max_off = offsets[frames - 1];
        if max_off >= cols {
            seen.push(offsets);
            continue;
        }
        // acc[k] = score of end column j = max_off + k along this line.
        let width = cols - max_off;
        let acc = &mut acc[..width];
        acc.copy_from_slice(&e.row(i)[max_off..]);
        for (t, &off) in offsets.iter().enumerate().skip(1) {
            let row = &e.row(i - t)[max_off - off..cols - off];
            acc.iter_mut().zip(row).for_each(|(a, &x)| *a += x);
        }
        score[max_off..]
            .iter_mut()
            .zip(acc.iter())
            .for_each(|(s, &a)| *s = s.min(a));
        seen.push(offsets);
    }
    let (best_j, best) = score
        .iter()
        .copied()
        .enumerate()
        .fold(
            (0, f32::INFINITY),
            |b, (j, s)| if s < b.1 { (j, s) } else { b },
        );
    if !best.is_finite() {
        return None;
    }
    let (lo, hi) = (
        best_j.saturating_sub(params.exclusion_window),
        best_j.saturating_add(params.exclusion_window),
    );
    let second = score
        .iter()
        .enumerate()
        .filter(|&(j, _)| j < lo || j > hi)
        .map(|(_, &s)| s)
        .fold(f32::INFINITY, f32::min);
    let confidence = if second.is_finite() && second > 0.0 {
        1.0 - f64::from(best) / f64::from(second)
    } else {
        0.0
    };
    Some((best_j, confidence))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::baselines::best_match;

    /// Deterministic xorshift noise in [0, 1).
    struct Noise(u64);
    impl Noise {
        fn next(&mut self) -> f32 {
            self.0 ^= self.0 << 13;
            self.0 ^= self.0 >> 7;
            self.0 ^= self.0 << 17;
            (self.0 >> 40) as f32 / (1u64 << 24) as f32
        }
    }

    /// Uniform noise similarities in [0, 1) with `planted(i)` columns set to `value`.
    fn planted(q: usize, d: usize, seed: u64, value: f32, line: impl Fn(usize) -> usize) -> Matrix {
        let mut noise = Noise(seed);
        let mut m = Matrix::zeros(q, d);
        m.as_mut_slice().iter_mut().for_each(|v| *v = noise.next());
        for i in 0..q {
            let j = line(i);
            if j < d {
                m.set(i, j, value);
            }
        }
        m
    }

    fn accuracy(p: &[Prediction], line: impl Fn(usize) -> usize, from: usize) -> f64 {
        let ok = p
            .iter()
            .filter(|p| p.query >= from && p.reference.abs_diff(line(p.query)) <= 1)
            .count();
        ok as f64 / p.iter().filter(|p| p.query >= from).count().max(1) as f64
    }

    #[test]
    fn recovers_a_planted_diagonal_where_best_match_fails() {
        let line = |i: usize| i + 5;
        let c = planted(120, 140, 42, 0.85, line);
        let seq = seqslam(&c, &SeqSlamParams::default()).unwrap();
        assert_eq!(seq.len(), 120);
        let bm = best_match(&c);
        let (acc_seq, acc_bm) = (accuracy(&seq, line, 9), accuracy(&bm, line, 9));
        assert!(acc_seq > 0.95, "seqslam accuracy {acc_seq}");
        assert!(acc_bm < 0.2, "best match accuracy {acc_bm}");
    }

    #[test]
    fn recovers_a_slope_1_2_line() {
        // Rounded lines of slope 1.2 miss the planted (also rounded) line by one column in a
        // few of their frames, so the noise is weaker here ([0, 0.5)); each row also gets one
        // distractor (0.95, higher than the place) at a random column, which fools best match.
        let line = |i: usize| (1.2 * i as f64).round() as usize + 3;
        let mut c = planted(100, 130, 7, 0.85, line);
        c.as_mut_slice()
            .iter_mut()
            .filter(|v| **v < 0.85)
            .for_each(|v| *v *= 0.5);
        let mut noise = Noise(99);
        for i in 0..100 {
            let j = (noise.next() * 130.0) as usize;
            if j.abs_diff(line(i)) > 2 {
                c.set(i, j, 0.95);
            }
        }
        let seq = seqslam(&c, &SeqSlamParams::default()).unwrap();
        // A rounded line of slope 1.2 meets the rounded search lines in only 6-8 of its 10
        // frames, so a few queries are lost to the distractors; slower velocities alone fail.
        let acc = accuracy(&seq, line, 9);
        assert!(acc > 0.85, "seqslam accuracy {acc}");
        let slow = SeqSlamParams {
            v_max: 1.0,
            ..SeqSlamParams::default()
        };
        let acc_slow = accuracy(&seqslam(&c, &slow).unwrap(), line, 9);
        assert!(acc_slow < 0.5, "seqslam with v <= 1.0: accuracy {acc_slow}");
        assert!(accuracy(&best_match(&c), line, 9) < 0.2);
    }

    #[test]
    fn planted_sequence_is_more_confident_than_noise() {
        let line = |i: usize| i;
        let clean = planted(60, 80, 3, 0.85, line);
        let noise = planted(60, 80, 3, 0.0, |_| usize::MAX);
        let mean_conf = |m: &Matrix| {
            let p = seqslam(m, &SeqSlamParams::default()).unwrap();
            let tail: Vec<f64> = p
                .iter()
                .filter(|p| p.query >= 9)
                .map(|p| p.confidence)
                .collect();
            tail.iter().sum::<f64>() / tail.len() as f64
        };
        let (c_clean, c_noise) = (mean_conf(&clean), mean_conf(&noise));
        assert!(
            c_clean > 2.0 * c_noise,
            "clean {c_clean} vs noise {c_noise}"
        );
        for p in seqslam(&noise, &SeqSlamParams::default()).unwrap() {
            assert!((0.0..=1.0).contains(&p.confidence), "{p:?}");
        }
    }

    #[test]
    fn early_queries_use_the_frames_that_exist() {
        let mut c = planted(12, 30, 11, 0.95, |i| i + 2);
        // Halve the noise so the planted column stands out even for a one-frame search.
        c.as_mut_slice()
            .iter_mut()
            .filter(|v| **v < 0.95)
            .for_each(|v| *v *= 0.5);
        let p = seqslam(&c, &SeqSlamParams::default()).unwrap();
        // Query 0 is a single-frame search: its best column is the row's smallest difference.
        assert_eq!(p[0].query, 0);
        assert_eq!(p[0].reference, 2);
        assert_eq!(p.len(), 12);
    }

    #[test]
    fn no_prediction_when_no_line_fits() {
        // D = 3 columns: a line over f frames needs round(0.8 (f - 1)) < 3, i.e. f <= 4, so
        // only queries 0..=3 (which have at most 4 frames) can be predicted.
        let c = planted(12, 3, 5, 0.9, |i| i);
        let p = seqslam(&c, &SeqSlamParams::default()).unwrap();
        let queries: Vec<usize> = p.iter().map(|p| p.query).collect();
        assert_eq!(queries, vec![0, 1, 2, 3]);
    }

    #[test]
    fn enhanced_matrix_is_shifted_to_zero_and_constant_windows_stay_flat() {
        let c = Matrix::from_rows(&[vec![0.5; 6], vec![0.1, 0.9, 0.2, 0.8, 0.3, 0.7]]).unwrap();
        let e = enhance_contrast(&c, 4).unwrap();
        let min = e.as_slice().iter().copied().fold(f32::INFINITY, f32::min);
        assert_eq!(min, 0.0);
        // Row 0 is constant: all its enhanced values are equal (0 before the shift).
        assert!(e.row(0).iter().all(|&v| v == e.row(0)[0]));
        // Row 1: the most similar column has the lowest enhanced difference.
        let argmin = (0..6)
            .min_by(|&a, &b| e.get(1, a).total_cmp(&e.get(1, b)))
            .unwrap();
        assert_eq!(argmin, 1);
        // Hand check of element (1, 0): window columns 0..=2, d = [0.9, 0.1, 0.8].
        let d = [0.9f64, 0.1, 0.8];
        let mean = d.iter().sum::<f64>() / 3.0;
        let std = (d.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / 2.0).sqrt();
        let want = (0.9 - mean) / std;
        // Row 0's raw enhanced values are 0, so e(0, 0) is exactly the global shift.
        let raw = f64::from(e.get(1, 0)) - f64::from(e.get(0, 0));
        assert!((raw - want).abs() < 1e-5, "{raw} vs {want}");
    }

    #[test]
    fn validation_names_the_parameter() {
        let ok = SeqSlamParams::default();
        assert!(ok.validate().is_ok());
        assert_eq!(ok.velocities().len(), 5);
        let cases = [
            (
                SeqSlamParams {
                    ds: 0,
                    ..ok.clone()
                },
                "ds",
            ),
            (
                SeqSlamParams {
                    enhance_window: 1,
                    ..ok.clone()
                },
                "enhance_window",
            ),
            (
                SeqSlamParams {
                    v_min: 0.0,
                    ..ok.clone()
                },
                "v_min",
            ),
            (
                SeqSlamParams {
                    v_max: 0.5,
                    ..ok.clone()
                },
                "v_max",
            ),
            (
                SeqSlamParams {
                    v_step: f64::NAN,
                    ..ok.clone()
                },
                "v_step",
            ),
            (
                SeqSlamParams {
                    v_step: 1e-6,
                    ..ok.clone()
                },
                "v_step",
            ),
        ];
        for (p, name) in cases {
            match p.validate() {
                Err(Error::InvalidParameter { name: n, .. }) => assert_eq!(n, name),
                other => panic!("{name}: expected InvalidParameter, got {other:?}"),
            }
        }
        let c = Matrix::from_rows(&[vec![0.5, f32::NAN]]).unwrap();
        assert!(matches!(seqslam(&c, &ok), Err(Error::NonFinite { .. })));
        assert!(matches!(
            seqslam(&Matrix::zeros(0, 4), &ok),
            Err(Error::Empty(_))
        ));
    }
}
