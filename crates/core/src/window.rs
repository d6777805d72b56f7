//! Sliding-window minima over a row of the graph: the one home of the window minimum, with one
//! tie rule, used by the offline `F = 1` kernel (`solver::kernel`), the online row step
//! (`trip::online`), the box-window and the trips' confidences (`confidence`,
//! `trip::confidence`; the default discounted sweep has its own `f32` lane minima,
//! `confidence/sweep/lanes.rs`, checked against a reference built on this module) and the
//! min-marginals (`solver::marginals`).
//!
//! Two shapes:
//! * [`trailing_min_offsets`]: `base[j] = min prev[j-K ..= j]` and the offset of the argmin, for
//!   the forward steps that keep back-pointers. For `K <=` [`DIRECT_MAX_K`] it is `K` shifted
//!   compare-and-select passes that vectorise (the offset is selected with the compare's bit
//!   mask); above, a monotone deque ([`MonoDeque`], `O(1)` amortised per column).
//! * [`leading_min_in_place`]: `v[j] = min v[j ..= j+K]`, values only, for the backward passes
//!   (shifted passes for small `K`, van Herk / Gil-Werman blocks above: `O(len)` for any `K`).
//!
//! **Tie rule: the latest column wins** (the smallest offset, i.e. the predecessor that advances
//! the least along the route). Both strategies follow it: the shifted passes visit candidates
//! from the nearest to the farthest and replace only on a strictly smaller value; the deque
//! drops a candidate as soon as a later one is no larger. Why this rule: it is the one the
//! offline kernel has always used, so stored localizations, the CLI's JSON and the
//! bit-identity tests against the plain scan stay as they were; it is also the rule that
//! vectorises (a strict compare per shifted pass). Ties are common, not exotic: along hidden
//! stretches `M` is flat over many columns, so the rule decides where a path sits while it is
//! hidden. The online solver uses the same rule, so an online trip and an offline solve of the
//! same rows resolve ties alike. Values-only minima have no argmin and so no tie to break.

/// Largest fan-out for which the window minimum is a direct scan instead of a monotone deque
/// (measured with `benches/solver.rs`, `solver_2400x2400/f1_k{4,8,9,64}`; BENCHMARKS.md).
pub const DIRECT_MAX_K: usize = 8;

/// How [`trailing_min_offsets`] computes the window minimum.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Scan {
    /// `K` shifted compare-and-select passes over the `K + 1` candidates (vectorises).
    Direct,
    /// Monotone deque of candidate columns.
    Deque,
}

impl Scan {
    /// The faster strategy for fan-out `k`.
    pub fn for_fan_out(k: usize) -> Self {
        if k <= DIRECT_MAX_K {
            Scan::Direct
        } else {
            Scan::Deque
        }
    }
}

/// Monotone deque of column indices with strictly increasing values front to back, for
/// [`Scan::Deque`].
#[derive(Clone, Debug, Default)]
pub struct MonoDeque {
    idx: Vec<usize>,
    head: usize,
}

impl MonoDeque {
    /// Prepares a run of consecutive blocks starting at column `lo` of `vals`: forgets every
    /// column, then takes the `K` columns before `lo`.
    pub fn start(&mut self, vals: &[f64], lo: usize, k: usize) {
        self.idx.clear();
        self.head = 0;
        for kk in lo.saturating_sub(k)..lo {
            self.push_min(vals, kk, k);
        }
    }

    /// Pushes column `kk` of `vals` and returns the argmin of `vals[kk-k..=kk]` (latest on
    /// ties). Columns must be pushed in increasing order.
    #[inline]
    pub fn push_min(&mut self, vals: &[f64], kk: usize, k: usize) -> usize {
        let v = vals[kk];
        while self.idx.len() > self.head && vals[self.idx[self.idx.len() - 1]] >= v {
            self.idx.pop();
        }
        self.idx.push(kk);
        while self.idx[self.head] + k < kk {
            self.head += 1;
        }
        self.idx[self.head]
    }

    /// Approximate heap bytes held.
    pub fn heap_bytes(&self) -> usize {
        self.idx.capacity() * std::mem::size_of::<usize>()
    }
}

/// `base[t] = min prev[j-k ..= j]` (the window clamped at column 0) for `j = b0 + t`, and
/// `off[t] = j - argmin`, the latest column on ties (see the module doc), for the columns
/// `b0 .. b0 + base.len()`.
///
/// With [`Scan::Deque`] the blocks of one run must follow each other without a gap and
/// `dq` must have been [`MonoDeque::start`]ed at the run's first column; [`Scan::Direct`]
/// ignores `dq`.
pub fn trailing_min_offsets(
    prev: &[f64],
    b0: usize,
    k: usize,
    strategy: Scan,
    base: &mut [f64],
    off: &mut [u64],
    dq: &mut MonoDeque,
) {
    let n = base.len();
    let b1 = b0 + n;
    match strategy {
        Scan::Direct => {
            base.copy_from_slice(&prev[b0..b1]);
            off[..n].fill(0);
            for o in 1..=k.min(b1.saturating_sub(1)) {
                // Columns b0+t with b0+t >= o have a candidate at b0+t-o.
                let first = o.saturating_sub(b0).min(n);
                let of_o = o as u64;
                for ((b, of), &cand) in base[first..]
                    .iter_mut()
                    .zip(off[first..n].iter_mut())
                    .zip(&prev[b0 + first - o..b1 - o])
                {
                    // The offset is selected with a bit mask: a plain `if` here compiles to
                    // a branch per cell (SSE2 has no blend), the mask form vectorises.
                    let better = cand < *b;
                    let mask = 0u64.wrapping_sub(u64::from(better));
                    *b = if better { cand } else { *b };
                    *of = (*of & !mask) | (of_o & mask);
                }
            }
        }
        Scan::Deque => {
            for (t, (b, of)) in base.iter_mut().zip(off[..n].iter_mut()).enumerate() {
                let kk = b0 + t;
                let j = dq.push_min(prev, kk, k);
                *b = prev[j];
                *of = (kk - j) as u64;
            }
        }
    }
}

/// `min prev[j-k ..= j]` (clamped at column 0) for one column, value only.
#[inline]
pub fn trailing_min_value(prev: &[f64], j: usize, k: usize) -> f64 {
    prev[j.saturating_sub(k)..=j]
        .iter()
        .fold(f64::INFINITY, |a, &v| if v < a { v } else { a })
}

/// In place: `v[j] = min(v[j ..= j+k])` (clamped at the end), values only; `tmp` is scratch
/// of `v.len()`. `k` shifted passes that vectorise for `k <=` [`DIRECT_MAX_K`], van Herk /
/// Gil-Werman blocks above.
pub fn leading_min_in_place(v: &mut [f64], k: usize, tmp: &mut [f64]) {
    let d = v.len();
    tmp.copy_from_slice(v);
    if k > DIRECT_MAX_K {
        leading_min_blocks(tmp, k, v);
        return;
    }
    for o in 1..=k.min(d.saturating_sub(1)) {
        for (a, &b) in v[..d - o].iter_mut().zip(&tmp[o..]) {
            *a = a.min(b);
        }
    }
}

/// `out[j] = min(m[j ..= j+k])` (clamped at the end) in `O(len)` for any `k`: a window of
/// `k + 1` consecutive elements spans at most two blocks of size `k + 1`, so its minimum is the
/// smaller of a suffix minimum of the first block and a prefix minimum of the second.
fn leading_min_blocks(m: &[f64], k: usize, out: &mut [f64]) {
    let n = m.len();
    if k == 0 || n == 0 {
        out.copy_from_slice(m);
        return;
    }
    let size = k + 1;
    let mut prefix = m.to_vec();
    let mut suffix = m.to_vec();
    for start in (0..n).step_by(size) {
        let end = (start + size).min(n);
        for j in start + 1..end {
            prefix[j] = prefix[j].min(prefix[j - 1]);
        }
        for j in (start..end - 1).rev() {
            suffix[j] = suffix[j].min(suffix[j + 1]);
        }
    }
    for j in 0..n {
        let block_end = (j / size) * size + size - 1;
        // In the last block, the suffix minimum already covers `j..n`; a prefix minimum of the
        // same block would also cover elements left of `j`.
        out[j] = if block_end >= n - 1 {
            suffix[j]
        } else {
            suffix[j].min(prefix[(j + k).min(n - 1)])
        };
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// The window's minimum value and the offset of its latest minimal element.
    fn naive_trailing(m: &[f64], j: usize, k: usize) -> (f64, u64) {
        let lo = j.saturating_sub(k);
        let mut best = (m[j], 0);
        for (o, &v) in m[lo..=j].iter().rev().enumerate() {
            if v < best.0 {
                best = (v, o as u64);
            }
        }
        best
    }

    proptest! {
        #[test]
        fn trailing_minima_match_naive_with_latest_ties(
            vals in prop::collection::vec(-3i32..3, 1..60),
            k in 0usize..14,
            block in 1usize..20,
        ) {
            // Few distinct values: ties everywhere.
            let m: Vec<f64> = vals.iter().map(|&x| f64::from(x)).collect();
            let n = m.len();
            let want: Vec<(f64, u64)> = (0..n).map(|j| naive_trailing(&m, j, k)).collect();
            for strategy in [Scan::Direct, Scan::Deque] {
                // In blocks, as the kernel calls it, and from a start column other than 0.
                let lo = (block / 2).min(n - 1);
                let (mut base, mut off) = (vec![0.0; n], vec![0u64; n]);
                let mut dq = MonoDeque::default();
                dq.start(&m, lo, k);
                for b0 in (lo..n).step_by(block) {
                    let b1 = (b0 + block).min(n);
                    trailing_min_offsets(&m, b0, k, strategy, &mut base[b0..b1], &mut off[b0..b1], &mut dq);
                }
                for j in lo..n {
                    prop_assert_eq!((base[j], off[j]), want[j], "{:?} column {}", strategy, j);
                    prop_assert_eq!(trailing_min_value(&m, j, k), want[j].0);
                }
            }
        }

        #[test]
        fn leading_minima_match_naive(vals in prop::collection::vec(-3i32..3, 1..40), k in 0usize..14) {
            // Values only, in place: every k, both strategies.
            let n = vals.len();
            let mut v: Vec<f64> = vals.iter().map(|&x| f64::from(x)).collect();
            let mut tmp = vec![0.0; n];
            leading_min_in_place(&mut v, k, &mut tmp);
            let want: Vec<f64> = (0..n)
                .map(|j| vals[j..=(j + k).min(n - 1)].iter().copied().min().map(f64::from).unwrap_or(f64::NAN))
                .collect();
            prop_assert_eq!(v, want);
        }
    }
}
