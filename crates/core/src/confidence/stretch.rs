//! Off the map by the stretch: a run of a route's matches that stands out of its rows no more
//! than a route through unrelated frames would.
//!
//! The row's own min-marginals ([`super::off_the_map`]) cannot see a detour that is as long
//! as the section it bypasses: the route drives that section during the detour, each match
//! costs about what a chance match costs, hiding one row frees nothing, and the rows on each
//! side hold the route in place. What does tell is the *contrast* of the matches: a true match
//! stands out of its query row's distribution of `ĉ` (robust `z`: `(ĉ - median) / (1.4826 ·
//! MAD)` over the row), a match on a detour is only the best of the few places the route may
//! step to next. One row says little (a right match can be weak), a stretch of them says
//! more: a route whose matches over `L` consecutive matched rows average a contrast no higher
//! than the expected best of the `K + 1` places a route with fan-out `K` chooses from at each
//! step (`E[max of K + 1 standard normals]`, 1.163 for `K = 4`: [`chance_contrast`]) is as well
//! explained by chance as by the map, and its rows get no prediction from that route, except
//! a row whose match is an outlier of its row on its own ([`OUTLIER_CONTRAST`]).
//!
//! `L` is the confidence's evidence span on both sides (`2 · 5 = 10` rows by default,
//! [`crate::confidence::ConfidenceParams::evidence_span`]): a detour shorter than that is left to the row's own
//! test. Measured effect: ARCHITECTURE.md, "Off the map". Cost: one median and one MAD per
//! matched row, shared by the hypotheses that match it (two linear-time selections over at most
//! [`SAMPLE`] of its `D` values, [`RowSpread`]), rows in parallel; trips keep them for the rows
//! of their lag window (`trip/stretch.rs`).

use rayon::prelude::*;

use crate::Matrix;

/// The robust contrast of `row[j]`: `(row[j] - median) / (1.4826 · MAD)` over the usable
/// (finite) values of the row (an even-strided sample of at most [`SAMPLE`] of them on longer
/// rows). A row whose values do not spread (MAD 0) gives `+inf` to a value
/// above its median and 0 otherwise; a non-finite `row[j]` or a row without usable values gives 0.
pub fn row_contrast(row: &[f32], j: usize, scratch: &mut Vec<f32>) -> f64 {
    let Some(&v) = row.get(j) else {
        return 0.0;
    };
    if !v.is_finite() {
        return 0.0;
    }
    RowSpread::of(row, scratch).map_or(0.0, |s| s.contrast(v))
}

/// Where a query row's values sit and how far they spread: the median and `1.4826 · MAD` of
/// its usable values (see [`row_contrast`]). Computed once per row, it gives the contrast of
/// any of the row's values in `O(1)`: what a trip keeps for the rows of its lag window, whose
/// matches move while they are re-traced.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RowSpread {
    median: f64,
    scale: f64,
}

impl RowSpread {
    /// The spread of `row`; `None` when it has no finite value. `scratch` is reused.
    pub fn of(row: &[f32], scratch: &mut Vec<f32>) -> Option<RowSpread> {
        scratch.clear();
        // Rows longer than SAMPLE are read at an even stride: a median and a MAD from 4,096
        // values are exact to a few hundredths of a deviation, and a city-scale map (30,790
        // places) then costs a ninth of the full selections (the solve with predictions stays
        // near the solve).
        let stride = row.len().div_ceil(SAMPLE).max(1);
        scratch.extend(
            row.iter()
                .step_by(stride)
                .copied()
                .filter(|x| x.is_finite()),
        );
        if scratch.is_empty() {
            return None;
        }
        let median = f64::from(median_in_place(scratch));
        for x in scratch.iter_mut() {
            *x = (f64::from(*x) - median).abs() as f32;
        }
        let scale = 1.4826 * f64::from(median_in_place(scratch));
        Some(RowSpread { median, scale })
    }

    /// The row's median.
    pub fn median(&self) -> f64 {
        self.median
    }

    /// The row's robust standard deviation, `1.4826 · MAD`.
    pub fn scale(&self) -> f64 {
        self.scale
    }

    /// The robust `z` of `v` in this row (`+inf` above the median of a row that does not
    /// spread, 0 at or below it; 0 for a non-finite `v`).
    pub fn contrast(&self, v: f32) -> f64 {
        if !v.is_finite() {
            return 0.0;
        }
        let excess = f64::from(v) - self.median;
        if self.scale > 0.0 {
            excess / self.scale
        } else if excess > 0.0 {
            f64::INFINITY
        } else {
            0.0
        }
    }
}

/// Most values of a row [`row_contrast`] reads (every value up to this many places).
pub const SAMPLE: usize = 4096;

/// The median of `values` (the upper one of an even count), reordering them.
fn median_in_place(values: &mut [f32]) -> f32 {
    let mid = values.len() / 2;
    *values.select_nth_unstable_by(mid, f32::total_cmp).1
}

/// `E[max of n independent standard normals]`: the contrast a route picks by chance when it
/// chooses the best of `n` places (`n = K + 1` for fan-out `K`). Numerical integration of
/// `∫ x · n φ(x) Φ(x)^(n-1) dx`; 0 for `n <= 1`.
pub fn chance_contrast(n: usize) -> f64 {
    if n <= 1 {
        return 0.0;
    }
    let (lo, hi, steps) = (-12.0f64, 12.0f64, 24_000usize);
    let h = (hi - lo) / steps as f64;
    let n_f = n as f64;
    let f = |x: f64| {
        let pdf = (-0.5 * x * x).exp() / (2.0 * std::f64::consts::PI).sqrt();
        x * n_f * pdf * normal_cdf(x).powf(n_f - 1.0)
    };
    // Simpson's rule (an even number of steps).
    let mut sum = f(lo) + f(hi);
    for s in 1..steps {
        let w = if s % 2 == 1 { 4.0 } else { 2.0 };
        sum += w * f(lo + s as f64 * h);
    }
    sum * h / 3.0
}

/// The standard normal CDF, `Φ(x) = erfc(-x / √2) / 2`, with `erfc` from its Chebyshev-fitted
/// form (Numerical Recipes' `erfcc`, relative error below 1.2e-7 everywhere).
fn normal_cdf(x: f64) -> f64 {
    0.5 * erfc(-x / std::f64::consts::SQRT_2)
}

fn erfc(x: f64) -> f64 {
    let z = x.abs();
    let t = 1.0 / (1.0 + 0.5 * z);
    let poly = -z * z - 1.265_512_23
        + t * (1.000_023_68
            + t * (0.374_091_96
                + t * (0.096_784_18
                    + t * (-0.186_288_06
                        + t * (0.278_868_07
                            + t * (-1.135_203_98
                                + t * (1.488_515_87 + t * (-0.822_152_23 + t * 0.170_872_77))))))));
    let r = t * poly.exp();
    if x >= 0.0 {
        r
    } else {
        2.0 - r
    }
}

/// Which entries of `contrast` (the matched rows of one route, in row order) lie in a stretch
/// of `len` consecutive entries whose mean is below `bar`. With fewer than `len` entries there
/// is no stretch to judge and none is weak (a short batch keeps every prediction). `O(n)` with
/// a sliding sum and a difference array; an infinite contrast (a row that does not spread)
/// counts as [`STRONG`], a NaN as 0.
pub fn weak_stretches(contrast: &[f64], len: usize, bar: f64) -> Vec<bool> {
    let n = contrast.len();
    let len = len.max(1);
    if n < len {
        return vec![false; n];
    }
    let c: Vec<f64> = contrast.iter().map(|&x| counted(x)).collect();
    let mut marks = vec![0i64; n + 1];
    let mut sum: f64 = c[..len].iter().sum();
    for s in 0..=n - len {
        if s > 0 {
            sum += c[s + len - 1] - c[s - 1];
        }
        if sum < bar * len as f64 {
            marks[s] += 1;
            marks[s + len] -= 1;
        }
    }
    let mut depth = 0i64;
    marks[..n]
        .iter()
        .map(|&d| {
            depth += d;
            depth > 0
        })
        .collect()
}

/// The contrast an infinite one counts as in a stretch's mean: far above any bar.
pub const STRONG: f64 = 1e3;

/// What a contrast counts as in a stretch's mean: clamped to `±`[`STRONG`], a NaN as 0.
fn counted(x: f64) -> f64 {
    if x.is_nan() {
        0.0
    } else {
        x.clamp(-STRONG, STRONG)
    }
}

/// For each route (`(row, reference)` of each matched row, in row order), the rows that lie in
/// a stretch of `len` matched rows whose mean contrast is below `bar` (the chance bar of the
/// routes' fan-out `K`, [`chance_contrast`]`(K + 1)`) and whose own contrast is below
/// [`OUTLIER_CONTRAST`]. `chat` is the normalised similarity matrix the routes were found on;
/// every `(row, reference)` must lie in it. A row several routes match (`F > 1`) has its median
/// and MAD computed once.
pub fn chance_stretches(
    chat: &Matrix,
    routes: &[Vec<(usize, usize)>],
    len: usize,
    bar: f64,
) -> Vec<Vec<bool>> {
    let mut rows: Vec<usize> = routes.iter().flatten().map(|&(i, _)| i).collect();
    rows.sort_unstable();
    rows.dedup();
    let spreads: Vec<Option<RowSpread>> = rows
        .par_iter()
        .map_init(Vec::new, |scratch, &i| RowSpread::of(chat.row(i), scratch))
        .collect();
    routes
        .iter()
        .map(|route| {
            let contrast: Vec<f64> = route
                .iter()
                .map(|&(i, j)| {
                    let spread = rows
                        .binary_search(&i)
                        .ok()
                        .and_then(|k| spreads.get(k).copied().flatten());
                    match (spread, chat.row(i).get(j)) {
                        (Some(s), Some(&v)) => s.contrast(v),
                        _ => 0.0,
                    }
                })
                .collect();
            chance_marks(&contrast, len, bar)
        })
        .collect()
}

/// The off-the-map marks of a route whose matched rows have these contrasts (in row order):
/// in a weak stretch ([`weak_stretches`]) and not an outlier on its own
/// ([`OUTLIER_CONTRAST`]). [`chance_stretches`] offline, a trip on its lag window.
pub fn chance_marks(contrast: &[f64], len: usize, bar: f64) -> Vec<bool> {
    weak_stretches(contrast, len, bar)
        .into_iter()
        .zip(contrast)
        .map(|(weak, &c)| weak && c < OUTLIER_CONTRAST)
        .collect()
}

/// A match whose contrast reaches this stands out of its row on its own (the usual outlier bar
/// for robust `z`, Iglewicz and Hoaglin's 3.5): it keeps its prediction even inside a weak
/// stretch, such as the first right row after a detour.
pub const OUTLIER_CONTRAST: f64 = 3.5;

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn chance_contrast_is_the_expected_best_of_n_normals() {
        // Closed forms for n = 2 and 3, tabulated values for 5 and 10.
        let pi = std::f64::consts::PI;
        assert_eq!(chance_contrast(0), 0.0);
        assert_eq!(chance_contrast(1), 0.0);
        assert!((chance_contrast(2) - 1.0 / pi.sqrt()).abs() < 1e-6);
        assert!((chance_contrast(3) - 1.5 / pi.sqrt()).abs() < 1e-6);
        assert!((chance_contrast(5) - 1.162_964).abs() < 1e-5);
        assert!((chance_contrast(10) - 1.538_753).abs() < 1e-5);
    }

    #[test]
    fn row_contrast_is_the_robust_z_of_the_value() {
        let mut s = Vec::new();
        // median 3, absolute deviations 2 1 0 1 97 -> MAD 1.
        let row = [1.0, 2.0, 3.0, 4.0, 100.0];
        assert!((row_contrast(&row, 4, &mut s) - 97.0 / 1.4826).abs() < 1e-9);
        assert!((row_contrast(&row, 0, &mut s) + 2.0 / 1.4826).abs() < 1e-9);
        // Non-finite values are not part of the row's distribution.
        let row = [1.0, f32::NAN, 2.0, 3.0, 4.0, 100.0, f32::INFINITY];
        assert!((row_contrast(&row, 5, &mut s) - 97.0 / 1.4826).abs() < 1e-9);
        assert_eq!(row_contrast(&row, 1, &mut s), 0.0);
        // A row that does not spread: a peak is infinitely distinct, the rest is not.
        let flat = [1.0, 1.0, 1.0, 5.0, 1.0];
        assert_eq!(row_contrast(&flat, 3, &mut s), f64::INFINITY);
        assert_eq!(row_contrast(&flat, 0, &mut s), 0.0);
        assert_eq!(row_contrast(&[], 0, &mut s), 0.0);
        // A row longer than SAMPLE is read at a stride: 0..10000 read every 3rd value (3,334
        // values) has median 5001 and MAD 2502 (the full row: 5000 and 2500).
        let long: Vec<f32> = (0..10_000).map(|v| v as f32).collect();
        let z = row_contrast(&long, 9_999, &mut s);
        assert!(
            (z - (9_999.0 - 5_001.0) / (1.4826 * 2_502.0)).abs() < 1e-9,
            "{z}"
        );
        assert_eq!(row_contrast(&row, 99, &mut s), 0.0);
    }

    /// Brute force: entry `t` is weak when a stretch of `len` entries holding it has a mean
    /// below `bar`.
    fn weak_slow(c: &[f64], len: usize, bar: f64) -> Vec<bool> {
        let n = c.len();
        let len = len.max(1);
        let c: Vec<f64> = c.iter().map(|&x| counted(x)).collect();
        (0..n)
            .map(|t| {
                (t.saturating_sub(len - 1)..=t)
                    .filter(|&s| s + len <= n)
                    .any(|s| c[s..s + len].iter().sum::<f64>() / (len as f64) < bar)
            })
            .collect()
    }

    proptest! {
        #[test]
        fn weak_stretches_match_brute_force(
            c in proptest::collection::vec(
                prop_oneof![-3.0f64..8.0, Just(f64::INFINITY), Just(f64::NAN)], 0..60),
            len in 1usize..14,
            bar in 0.0f64..3.0,
        ) {
            let fast = weak_stretches(&c, len, bar);
            let slow = weak_slow(&c, len, bar);
            // Sliding sums may differ from exact sums in the last bits: compare away from ties.
            let n = c.len();
            for t in 0..n {
                if fast[t] != slow[t] {
                    let l = len.max(1);
                    let near_tie = (t.saturating_sub(l - 1)..=t).filter(|&s| s + l <= n).any(|s| {
                        let m: f64 = c[s..s + l]
                            .iter()
                            .map(|&x| counted(x))
                            .sum::<f64>() / l as f64;
                        (m - bar).abs() < 1e-9
                    });
                    prop_assert!(near_tie, "entry {}: fast {} slow {}", t, fast[t], slow[t]);
                }
            }
        }
    }

    #[test]
    fn a_stretch_of_chance_matches_is_weak_and_distinct_matches_are_not() {
        // 30 rows x 40 places: rows 0-9 and 20-29 match place i + 5 sharply, rows 10-19 sit on
        // places whose value is the row's median (contrast 0).
        let (q, d) = (30, 40);
        let mut data = Vec::with_capacity(q * d);
        for i in 0..q {
            for j in 0..d {
                let noise = ((i * 7 + j * 13) % 11) as f32 / 10.0;
                let peak = if !(10..20).contains(&i) {
                    5.0 * f32::from(j == i + 5)
                } else {
                    0.0
                };
                data.push(1.0 + noise + peak);
            }
        }
        let chat = Matrix::from_vec(q, d, data).unwrap();
        let mut scratch = Vec::new();
        let route: Vec<(usize, usize)> = (0..q)
            .map(|i| {
                if (10..20).contains(&i) {
                    // The place whose value is the row's median.
                    let row = chat.row(i);
                    let j = (0..d)
                        .min_by(|&a, &b| {
                            row_contrast(row, a, &mut scratch)
                                .abs()
                                .total_cmp(&row_contrast(row, b, &mut scratch).abs())
                        })
                        .unwrap();
                    (i, j)
                } else {
                    (i, i + 5)
                }
            })
            .collect();
        let weak =
            chance_stretches(&chat, std::slice::from_ref(&route), 10, chance_contrast(5)).remove(0);
        // Routes sharing rows (F > 1) share their spreads and get each their own marks: a
        // route of the sharp rows alone, and this one again.
        let sharp_rows: Vec<(usize, usize)> = route
            .iter()
            .copied()
            .filter(|&(i, _)| !(10..20).contains(&i))
            .collect();
        let both = chance_stretches(
            &chat,
            &[sharp_rows.clone(), route.clone()],
            10,
            chance_contrast(5),
        );
        assert_eq!(both[1], weak);
        assert_eq!(both[0], vec![false; sharp_rows.len()]);
        assert!(weak[10..20].iter().all(|&w| w), "{weak:?}");
        assert!(
            weak[..10].iter().chain(&weak[20..]).all(|&w| !w),
            "{weak:?}"
        );
        // Shorter than the stretch: a chance run of 4 rows among sharp ones is not weak.
        let route: Vec<(usize, usize)> = (0..q)
            .map(|i| {
                if (12..16).contains(&i) {
                    route[i]
                } else {
                    (i, (i + 5).min(d - 1))
                }
            })
            .collect();
        let mut sharp = chat.clone();
        for i in 10..20 {
            if !(12..16).contains(&i) {
                sharp.set(i, i + 5, 6.0);
            }
        }
        assert!(chance_stretches(&sharp, &[route], 10, chance_contrast(5))
            .iter()
            .flatten()
            .all(|&w| !w));
    }
}
