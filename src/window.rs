//! Sliding-window minima over a row of the graph, in `O(len)` for any window width
//! (van Herk / Gil-Werman): the fan-out `K` of the flow graph costs nothing.
//!
//! A window of `k + 1` consecutive elements spans at most two blocks of size `k + 1`, so its
//! minimum is the smaller of a suffix minimum of the first block and a prefix minimum of the
//! second. On ties the element further left wins, so results are deterministic.

/// `out[j] = min(m[j-k ..= j])` (clamped at 0) under `less`.
pub fn trailing_min_by<T: Copy>(m: &[T], k: usize, out: &mut [T], less: impl Fn(&T, &T) -> bool) {
    let n = m.len();
    if k == 0 || n == 0 {
        out.copy_from_slice(m);
        return;
    }
    let (prefix, suffix) = block_scans(m, k + 1, &less);
    for j in 0..n {
        out[j] = if j < k {
            prefix[j]
        } else {
            pick(suffix[j - k], prefix[j], &less)
        };
    }
}

/// `out[j] = min(m[j ..= j+k])` (clamped at the end) under `less`.
pub fn leading_min_by<T: Copy>(m: &[T], k: usize, out: &mut [T], less: impl Fn(&T, &T) -> bool) {
    let n = m.len();
    if k == 0 || n == 0 {
        out.copy_from_slice(m);
        return;
    }
    let size = k + 1;
    let (prefix, suffix) = block_scans(m, size, &less);
    for j in 0..n {
        let block_end = (j / size) * size + size - 1;
        // In the last block, the suffix minimum already covers `j..n`; a prefix minimum of the
        // same block would also cover elements left of `j`.
        out[j] = if block_end >= n - 1 {
            suffix[j]
        } else {
            pick(suffix[j], prefix[(j + k).min(n - 1)], &less)
        };
    }
}

/// `trailing_min_by` for plain `f64`.
pub fn trailing_min(m: &[f64], k: usize, out: &mut [f64]) {
    trailing_min_by(m, k, out, |a, b| a < b);
}

/// `leading_min_by` for plain `f64`.
pub fn leading_min(m: &[f64], k: usize, out: &mut [f64]) {
    leading_min_by(m, k, out, |a, b| a < b);
}

/// In place: `v[j] = min(v[j ..= j+k])` (clamped at the end), values only; `tmp` is scratch
/// of `v.len()`. `k` shifted passes that vectorise for `k <= 8`, [`leading_min`] above.
pub fn leading_min_in_place(v: &mut [f64], k: usize, tmp: &mut [f64]) {
    let d = v.len();
    tmp.copy_from_slice(v);
    if k > 8 {
        leading_min(tmp, k, v);
        return;
    }
    for o in 1..=k.min(d.saturating_sub(1)) {
        for (a, &b) in v[..d - o].iter_mut().zip(&tmp[o..]) {
            *a = a.min(b);
        }
    }
}

/// The left operand unless the right one is strictly smaller.
#[inline]
fn pick<T: Copy>(left: T, right: T, less: &impl Fn(&T, &T) -> bool) -> T {
    if less(&right, &left) {
        right
    } else {
        left
    }
}

/// Running minima within consecutive blocks of `size`: from each block's start (`prefix`) and
/// to each block's end (`suffix`).
fn block_scans<T: Copy>(m: &[T], size: usize, less: &impl Fn(&T, &T) -> bool) -> (Vec<T>, Vec<T>) {
    let n = m.len();
    let mut prefix = m.to_vec();
    let mut suffix = m.to_vec();
    for start in (0..n).step_by(size) {
        let end = (start + size).min(n);
        for j in start + 1..end {
            prefix[j] = pick(prefix[j - 1], prefix[j], less);
        }
        for j in (start..end - 1).rev() {
            suffix[j] = pick(suffix[j], suffix[j + 1], less);
        }
    }
    (prefix, suffix)
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn naive(
        m: &[(i32, usize)],
        lo: impl Fn(usize) -> usize,
        hi: impl Fn(usize) -> usize,
    ) -> Vec<(i32, usize)> {
        (0..m.len())
            .map(|j| {
                *m[lo(j)..=hi(j)]
                    .iter()
                    .min_by_key(|p| p.0)
                    .expect("non-empty window")
            })
            .collect()
    }

    proptest! {
        #[test]
        fn window_minima_match_naive_with_leftmost_ties(vals in prop::collection::vec(-3i32..3, 1..40), k in 0usize..14) {
            // Pair each value with its index: ties must resolve to the leftmost element.
            let m: Vec<(i32, usize)> = vals.iter().copied().zip(0..).collect();
            let n = m.len();
            let mut out = m.clone();
            trailing_min_by(&m, k, &mut out, |a, b| a.0 < b.0);
            prop_assert_eq!(&out, &naive(&m, |j| j.saturating_sub(k), |j| j));
            leading_min_by(&m, k, &mut out, |a, b| a.0 < b.0);
            prop_assert_eq!(&out, &naive(&m, |j| j, |j| (j + k).min(n - 1)));
            // Values only, in place: every k, both strategies.
            let mut v: Vec<f64> = vals.iter().map(|&x| f64::from(x)).collect();
            let mut tmp = vec![0.0; n];
            leading_min_in_place(&mut v, k, &mut tmp);
            let want: Vec<f64> = naive(&m, |j| j, |j| (j + k).min(n - 1)).iter().map(|p| f64::from(p.0)).collect();
            prop_assert_eq!(v, want);
        }
    }
}
