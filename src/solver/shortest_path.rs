//! `F = 1`: the shortest source-sink path by dynamic programming over the DAG, row by row.
//!
//! For row `i` let `X_i[j]` / `H_i[j]` be the cheapest cost of a path from the source that ends
//! at `x_ij` / `h_ij` (node cost included) and `M_i[j] = min(X_i[j], H_i[j])`. A forward edge
//! into column `k` of row `i+1` comes from a column `j` in `[k-K, k]` of row `i`, so
//! `base_k = min_{j in [k-K, k]} M_i[j]` is a sliding-window minimum; then
//! `X_{i+1}[k] = min(base_k + c_k, X_{i+1}[k-1] + c_k)` and `H_{i+1}[k] = min(base_k + W,
//! H_{i+1}[k-1])` (the second terms only with horizontal edges), one left-to-right pass.
//! The window minimum is a direct scan for `K <= DIRECT_WINDOW_MAX_K` and a monotone deque
//! (amortised O(1) per cell, independent of `K`) above; both give the same answer.
//!
//! Costs are accumulated in `f64`. Memory: four `f64` vectors of length `D` per row state (two
//! states) plus one back-pointer per node: one byte (`K <= 63`) or two bytes (`K <= 16383`),
//! encoding "came horizontally", "predecessor is hidden" and the column offset `0..=K`.
//!
//! Tie-breaking (deterministic): among equal window minima the largest column (smallest
//! offset) wins; a matching node beats a hidden node of the same cell (`M` takes `x` unless
//! `h` is strictly cheaper); entering a node by a forward edge beats arriving horizontally; at
//! the sink the smallest column of the last row wins.

use super::graph::{check_inputs, hypothesis_from_steps, match_cost, Blocked, Kind, Step};
use super::Hypothesis;
use crate::{Matrix, Result};

/// Largest fan-out for which the window minimum is a direct scan instead of a monotone deque
/// (measured with `benches/solver.rs`, group `window`).
pub(crate) const DIRECT_WINDOW_MAX_K: usize = 8;

/// The shortest source-sink path for hidden cost `w`, never using a node of `blocked`.
///
/// Runs in `O(Q·D)` time whatever the fan-out, with `O(D)` cost memory and one or two bytes of
/// back-pointer per node. The returned hypothesis has rank 1. Fails on an empty or non-finite
/// matrix, `fan_out > MAX_FAN_OUT`, a `w` that is not finite and > 0, or a blocked set of
/// another shape.
pub fn shortest_path(
    chat: &Matrix,
    fan_out: usize,
    horizontal: bool,
    w: f64,
    blocked: Option<&Blocked>,
) -> Result<Hypothesis> {
    check_inputs(chat, fan_out, w, blocked)?;
    let steps = Dp::new(chat, fan_out, horizontal, w, blocked).shortest_steps();
    Ok(hypothesis_from_steps(chat, w, &steps, 1))
}

/// How the sliding-window minimum is computed.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Window {
    /// Scan the `K + 1` candidates.
    Direct,
    /// Monotone deque of candidate columns.
    Deque,
}

/// A compact back-pointer.
trait BackPtr: Copy + Default {
    const MAX_OFFSET: usize;
    fn forward(from_hidden: bool, offset: usize) -> Self;
    fn horizontal() -> Self;
    fn is_horizontal(self) -> bool;
    fn pred_hidden(self) -> bool;
    fn offset(self) -> usize;
}

impl BackPtr for u8 {
    const MAX_OFFSET: usize = 0x3f;
    #[inline]
    fn forward(from_hidden: bool, offset: usize) -> Self {
        (u8::from(from_hidden) << 6) | offset as u8
    }
    #[inline]
    fn horizontal() -> Self {
        0x80
    }
    fn is_horizontal(self) -> bool {
        self & 0x80 != 0
    }
    fn pred_hidden(self) -> bool {
        self & 0x40 != 0
    }
    fn offset(self) -> usize {
        usize::from(self & 0x3f)
    }
}

impl BackPtr for u16 {
    const MAX_OFFSET: usize = 0x3fff;
    #[inline]
    fn forward(from_hidden: bool, offset: usize) -> Self {
        (u16::from(from_hidden) << 14) | offset as u16
    }
    #[inline]
    fn horizontal() -> Self {
        0x8000
    }
    fn is_horizontal(self) -> bool {
        self & 0x8000 != 0
    }
    fn pred_hidden(self) -> bool {
        self & 0x4000 != 0
    }
    fn offset(self) -> usize {
        usize::from(self & 0x3fff)
    }
}

/// The DP values of one row.
#[derive(Clone, Debug)]
pub(crate) struct RowState {
    /// `X[j]`: cheapest path from the source ending at `x_ij` (`+inf` when unusable).
    pub x: Vec<f64>,
    /// `H[j]`: cheapest path from the source ending at `h_ij`.
    pub h: Vec<f64>,
    /// `min(X[j], H[j])`.
    pub m: Vec<f64>,
    /// Whether `m[j]` is the hidden node (`H[j] < X[j]`).
    pub from_h: Vec<bool>,
}

impl RowState {
    pub(crate) fn new(d: usize) -> Self {
        RowState {
            x: vec![0.0; d],
            h: vec![0.0; d],
            m: vec![0.0; d],
            from_h: vec![false; d],
        }
    }
}

/// Monotone deque of column indices with strictly increasing values front to back.
#[derive(Default)]
pub(crate) struct MonoDeque {
    idx: Vec<usize>,
    head: usize,
}

impl MonoDeque {
    pub(crate) fn clear(&mut self) {
        self.idx.clear();
        self.head = 0;
    }

    /// Pushes column `kk` of `vals` and returns the argmin of `vals[kk-k..=kk]` (latest on ties).
    /// Columns must be pushed in increasing order.
    #[inline]
    pub(crate) fn push_min(&mut self, vals: &[f64], kk: usize, k: usize) -> usize {
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
}

/// Per-row work buffers of the DP, reused from row to row.
#[derive(Default)]
pub(crate) struct Scratch {
    dq: MonoDeque,
    cost: Vec<f64>,
    base: Vec<f64>,
    /// Window offsets, kept as `f64` so the window pass is all same-width selects and
    /// vectorises (an integer select beside a float compare stays a branch).
    off: Vec<f64>,
}

/// Columns per block of [`Dp::row_step`].
const BLOCK: usize = 2048;

/// What pass (3) reads: `W`, the block's costs, window minima and offsets, the previous row,
/// and the block's first column.
type ScanArgs<'a> = (
    f64,
    &'a [f64],
    &'a [f64],
    &'a [f64],
    Option<&'a RowState>,
    usize,
);

/// Pass (3) of [`Dp::row_step`] on one block: `X[j] = min(base + c, X[j-1] + c)`,
/// `H[j] = min(base + W, H[j-1])` (left terms only with horizontal edges), `M`, and the
/// back-pointers. `carry` is `(X, H)` of the column left of the block; returns the block's last.
#[inline]
fn scan<P: BackPtr, const HORIZONTAL: bool, const STORE_XH: bool>(
    (w, cost, base, off, prev, b0): ScanArgs<'_>,
    (mut left_x, mut left_h): (f64, f64),
    cur: &mut RowState,
    mut ptrs: Option<(&mut [P], &mut [P])>,
) -> (f64, f64) {
    for t in 0..cost.len() {
        let j = b0 + t;
        let (c, b) = (cost[t], base[t]);
        let ex = b + c;
        let hx = left_x + c;
        let x_horiz = hx < ex;
        let vx = if x_horiz { hx } else { ex };
        let eh = b + w;
        let h_horiz = left_h < eh;
        let vh = if h_horiz { left_h } else { eh };
        if HORIZONTAL {
            left_x = vx;
            left_h = vh;
        }
        if STORE_XH {
            cur.x[j] = vx;
            cur.h[j] = vh;
        }
        let hidden = vh < vx;
        cur.m[j] = if hidden { vh } else { vx };
        cur.from_h[j] = hidden;
        if let Some((px, ph)) = ptrs.as_mut() {
            // Offsets are small whole numbers, exact in f64.
            let o = off[t] as usize;
            let fh = prev.is_some_and(|p| p.from_h[j - o]);
            let fwd = P::forward(fh, o);
            px[t] = if x_horiz { P::horizontal() } else { fwd };
            ph[t] = if h_horiz { P::horizontal() } else { fwd };
        }
    }
    (left_x, left_h)
}

/// One dynamic programme over the graph of `chat`.
pub(crate) struct Dp<'a> {
    chat: &'a Matrix,
    blocked: Option<&'a Blocked>,
    k: usize,
    horizontal: bool,
    w: f64,
    window: Window,
}

impl<'a> Dp<'a> {
    /// A DP with the window strategy chosen by `K`. Inputs must have been checked.
    pub(crate) fn new(
        chat: &'a Matrix,
        k: usize,
        horizontal: bool,
        w: f64,
        blocked: Option<&'a Blocked>,
    ) -> Self {
        let window = if k <= DIRECT_WINDOW_MAX_K {
            Window::Direct
        } else {
            Window::Deque
        };
        Dp {
            chat,
            blocked,
            k,
            horizontal,
            w,
            window,
        }
    }

    /// Forces a window strategy (tests).
    #[cfg(test)]
    pub(crate) fn with_window(mut self, window: Window) -> Self {
        self.window = window;
        self
    }

    /// Cost of `x_ij`, `+inf` when unusable or blocked.
    #[inline]
    pub(crate) fn x_cost(&self, i: usize, j: usize, v: f32) -> f64 {
        if self.blocked.is_some_and(|b| b.is_blocked(i, j)) {
            f64::INFINITY
        } else {
            match_cost(v)
        }
    }

    /// Computes row `i` into `cur` from the previous row (`None` for row 0), writing
    /// back-pointers when `ptrs` is given.
    ///
    /// Three passes, so the first two vectorise and the third carries only the serial
    /// horizontal dependency: (1) node costs `1/ĉ` of the row; (2) the window minimum of the
    /// previous row and its offset (`K` shifted compare-and-select passes for small `K`, a
    /// monotone deque otherwise); (3) the left-to-right scan with the horizontal edges. The
    /// arithmetic and tie rules are those of one fused loop, so results do not depend on it.
    #[inline]
    fn row_step<P: BackPtr>(
        &self,
        i: usize,
        prev: Option<&RowState>,
        cur: &mut RowState,
        ptrs: Option<(&mut [P], &mut [P])>,
        scratch: &mut Scratch,
    ) {
        let row = self.chat.row(i);
        let d = row.len();
        let Scratch {
            dq,
            cost,
            base,
            off,
        } = scratch;
        cost.resize(BLOCK, 0.0);
        base.resize(BLOCK, 0.0);
        off.resize(BLOCK, 0.0);
        dq.clear();
        let mut ptrs = ptrs;
        let mut carry = (f64::INFINITY, f64::INFINITY);
        // Columns in blocks of `BLOCK`, so the per-row buffers stay in L1 on wide maps.
        for b0 in (0..d).step_by(BLOCK) {
            let b1 = (b0 + BLOCK).min(d);
            let n = b1 - b0;
            let (cost, base, off) = (&mut cost[..n], &mut base[..n], &mut off[..n]);

            // (1) Node costs.
            for (c, &v) in cost.iter_mut().zip(&row[b0..b1]) {
                *c = match_cost(v);
            }
            if let Some(b) = self.blocked {
                for (t, c) in cost.iter_mut().enumerate() {
                    if b.is_blocked(i, b0 + t) {
                        *c = f64::INFINITY;
                    }
                }
            }

            // (2) Window minimum of the previous row: base[j] = min m[j-K..=j], off = j - argmin
            // (the latest column on ties).
            match prev {
                None => {
                    base.fill(0.0);
                    off.fill(0.0);
                }
                Some(p) => match self.window {
                    Window::Direct => {
                        base.copy_from_slice(&p.m[b0..b1]);
                        off.fill(0.0);
                        // o < d keeps every candidate slice in range (the first block
                        // holds min(d, BLOCK) > o columns; later blocks start past K).
                        for o in 1..=self.k.min(d - 1) {
                            // Columns b0+t with b0+t >= o have a candidate at b0+t-o.
                            let first = o.saturating_sub(b0).min(n);
                            let of_o = o as f64;
                            for ((b, of), &cand) in base[first..]
                                .iter_mut()
                                .zip(off[first..].iter_mut())
                                .zip(&p.m[b0 + first - o..b1 - o])
                            {
                                // Unconditional selects, so this loop vectorises instead of
                                // branching on noisy data.
                                let better = cand < *b;
                                *b = if better { cand } else { *b };
                                *of = if better { of_o } else { *of };
                            }
                        }
                    }
                    Window::Deque => {
                        for t in 0..n {
                            let kk = b0 + t;
                            let j = dq.push_min(&p.m, kk, self.k);
                            base[t] = p.m[j];
                            off[t] = (kk - j) as f64;
                        }
                    }
                },
            }

            // (3) The scan along the row. `X` and `H` themselves are only stored for the
            // values pass of the min-marginals; the path search needs `M` and the pointers.
            let block_ptrs = ptrs
                .as_mut()
                .map(|(px, ph)| (&mut px[b0..b1], &mut ph[b0..b1]));
            let w = self.w;
            let args = (w, &*cost, &*base, &*off, prev, b0);
            carry = match (self.horizontal, block_ptrs.is_some()) {
                (true, true) => scan::<P, true, false>(args, carry, cur, block_ptrs),
                (true, false) => scan::<P, true, true>(args, carry, cur, block_ptrs),
                (false, true) => scan::<P, false, false>(args, carry, cur, block_ptrs),
                (false, false) => scan::<P, false, true>(args, carry, cur, block_ptrs),
            };
        }
    }

    /// Computes row `i` without back-pointers (used by the min-marginals).
    pub(crate) fn values_step(
        &self,
        i: usize,
        prev: Option<&RowState>,
        cur: &mut RowState,
        scratch: &mut Scratch,
    ) {
        self.row_step::<u8>(i, prev, cur, None, scratch);
    }

    /// The nodes of the shortest path, in visiting order.
    pub(crate) fn shortest_steps(&self) -> Vec<Step> {
        if self.k <= u8::MAX_OFFSET {
            self.run::<u8>()
        } else {
            self.run::<u16>()
        }
    }

    fn run<P: BackPtr>(&self) -> Vec<Step> {
        let (q, d) = (self.chat.rows(), self.chat.cols());
        debug_assert!(self.k <= P::MAX_OFFSET);
        let mut ptr_x = vec![P::default(); q * d];
        let mut ptr_h = vec![P::default(); q * d];
        let mut prev = RowState::new(d);
        let mut cur = RowState::new(d);
        let mut scratch = Scratch::default();
        for (i, (px, ph)) in ptr_x
            .chunks_exact_mut(d)
            .zip(ptr_h.chunks_exact_mut(d))
            .enumerate()
        {
            let p = (i > 0).then_some(&prev);
            self.row_step(i, p, &mut cur, Some((px, ph)), &mut scratch);
            std::mem::swap(&mut prev, &mut cur);
        }
        // `prev` now holds the last row. Sink: smallest column on ties.
        let mut j = 0;
        for (jj, &v) in prev.m.iter().enumerate().skip(1) {
            if v < prev.m[j] {
                j = jj;
            }
        }
        let mut kind = if prev.from_h[j] {
            Kind::Hidden
        } else {
            Kind::Match
        };
        let mut i = q - 1;
        let mut steps = Vec::with_capacity(q);
        loop {
            steps.push(Step {
                row: i,
                col: j,
                kind,
            });
            let p = match kind {
                Kind::Match => ptr_x[i * d + j],
                Kind::Hidden => ptr_h[i * d + j],
            };
            if p.is_horizontal() {
                j -= 1;
                continue;
            }
            if i == 0 {
                break;
            }
            i -= 1;
            j -= p.offset();
            kind = if p.pred_hidden() {
                Kind::Hidden
            } else {
                Kind::Match
            };
        }
        steps.reverse();
        steps
    }
}

#[cfg(test)]
mod tests {
    use super::super::reference::{brute_force_best, check_valid, random_instance};
    use super::*;
    use proptest::prelude::*;

    fn m(rows: &[&[f32]]) -> Matrix {
        Matrix::from_rows(rows).unwrap()
    }

    fn cols(h: &Hypothesis) -> Vec<Vec<usize>> {
        h.rows
            .iter()
            .map(|r| r.matches.iter().map(|m| m.reference).collect())
            .collect()
    }

    #[test]
    fn follows_the_diagonal() {
        let chat = m(&[&[3.0, 0.5, 0.5], &[0.5, 3.0, 0.5], &[0.5, 0.5, 3.0]]);
        let h = shortest_path(&chat, 1, true, 2.0, None).unwrap();
        assert_eq!(cols(&h), vec![vec![0], vec![1], vec![2]]);
        assert!((h.cost - 1.0).abs() < 1e-12);
    }

    #[test]
    fn fan_out_limits_the_jump() {
        // Row 1's only good match is 3 columns right of row 0's.
        let chat = m(&[&[5.0, 0.1, 0.1, 0.1], &[0.1, 0.1, 0.1, 5.0]]);
        let far = shortest_path(&chat, 3, false, 100.0, None).unwrap();
        assert_eq!(cols(&far), vec![vec![0], vec![3]]);
        let near = shortest_path(&chat, 2, false, 100.0, None).unwrap();
        assert_ne!(cols(&near), vec![vec![0], vec![3]]);
        check_valid(&near, &chat, 2, false, 100.0, None);
    }

    #[test]
    fn horizontal_edges_match_several_references() {
        // A slow query: row 1 sees references 1 and 2 equally well.
        let chat = m(&[
            &[4.0, 0.1, 0.1, 0.1],
            &[0.1, 4.0, 4.0, 0.1],
            &[0.1, 0.1, 0.1, 4.0],
        ]);
        let h = shortest_path(&chat, 1, true, 5.0, None).unwrap();
        assert_eq!(cols(&h), vec![vec![0], vec![1, 2], vec![3]]);
        let no_h = shortest_path(&chat, 1, false, 5.0, None).unwrap();
        assert!(no_h.rows.iter().all(|r| r.matches.len() <= 1));
    }

    #[test]
    fn low_similarity_block_goes_hidden_and_resumes() {
        let mut rows = Vec::new();
        for i in 0..8 {
            let mut r = vec![0.2f32; 8];
            if !(3..=5).contains(&i) {
                r[i] = 4.0;
            }
            rows.push(r);
        }
        let chat = Matrix::from_rows(&rows).unwrap();
        let h = shortest_path(&chat, 2, true, 1.0, None).unwrap();
        let c = cols(&h);
        for i in [0, 1, 2, 6, 7] {
            assert_eq!(c[i], vec![i], "row {i}");
        }
        for (i, r) in c.iter().enumerate().take(6).skip(3) {
            assert!(r.is_empty(), "row {i} should be hidden");
        }
    }

    #[test]
    fn all_costs_above_w_gives_all_hidden() {
        let chat = m(&[&[0.5, 0.4], &[0.3, 0.9]]);
        let h = shortest_path(&chat, 1, true, 1.0, None).unwrap();
        assert_eq!(h.hidden_fraction(), 1.0);
        assert!((h.cost - 2.0).abs() < 1e-12);
    }

    #[test]
    fn non_positive_similarity_is_never_used() {
        let chat = m(&[&[0.0, -1.0], &[-0.5, 0.0]]);
        let h = shortest_path(&chat, 1, true, 1000.0, None).unwrap();
        assert_eq!(h.hidden_fraction(), 1.0);
    }

    #[test]
    fn blocked_nodes_are_avoided() {
        let chat = m(&[&[5.0, 4.0], &[5.0, 4.0]]);
        let mut b = Blocked::new(2, 2);
        b.block(0, 0);
        b.block(1, 0);
        let h = shortest_path(&chat, 1, false, 10.0, Some(&b)).unwrap();
        assert_eq!(cols(&h), vec![vec![1], vec![1]]);
    }

    #[test]
    fn rejects_nan_and_empty() {
        let chat = m(&[&[1.0, f32::NAN]]);
        assert!(matches!(
            shortest_path(&chat, 1, true, 1.0, None),
            Err(crate::Error::NonFinite { row: 0, col: 1, .. })
        ));
        assert!(matches!(
            shortest_path(&Matrix::zeros(3, 0), 1, true, 1.0, None),
            Err(crate::Error::Empty(_))
        ));
    }

    #[test]
    fn wide_fan_out_uses_two_byte_pointers() {
        // A jump of 100 columns needs K >= 100 (u16 back-pointers).
        let mut r0 = vec![0.1f32; 200];
        let mut r1 = vec![0.1f32; 200];
        r0[10] = 5.0;
        r1[110] = 5.0;
        let chat = Matrix::from_rows(&[r0, r1]).unwrap();
        let h = shortest_path(&chat, 100, false, 50.0, None).unwrap();
        assert_eq!(cols(&h), vec![vec![10], vec![110]]);
        let h = shortest_path(&chat, 99, false, 50.0, None).unwrap();
        assert_ne!(cols(&h), vec![vec![10], vec![110]]);
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(200))]
        #[test]
        fn matches_brute_force((chat, k, horizontal, w) in random_instance()) {
            let h = shortest_path(&chat, k, horizontal, w, None).unwrap();
            check_valid(&h, &chat, k, horizontal, w, None);
            let best = brute_force_best(&chat, k, horizontal, w, None);
            prop_assert!((h.cost - best).abs() <= 1e-9 * best.max(1.0), "{} vs {}", h.cost, best);
        }

        #[test]
        fn window_strategies_agree(
            (chat, _, horizontal, w) in random_instance(),
            k in 0usize..12,
        ) {
            let a = Dp::new(&chat, k, horizontal, w, None).with_window(Window::Direct).shortest_steps();
            let b = Dp::new(&chat, k, horizontal, w, None).with_window(Window::Deque).shortest_steps();
            prop_assert_eq!(a, b);
        }
    }
}
