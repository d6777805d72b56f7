//! `F = 1`: the shortest source-sink path by dynamic programming over the DAG, row by row.
//!
//! For row `i` let `X_i[j]` / `H_i[j]` be the cheapest cost of a path from the source that ends
//! at `x_ij` / `h_ij` (node cost included) and `M_i[j] = min(X_i[j], H_i[j])`. A forward edge
//! into column `k` of row `i+1` comes from a column `j` in `[k-K, k]` of row `i`, so
//! `base_k = min_{j in [k-K, k]} M_i[j]` is a sliding-window minimum; then
//! `X_{i+1}[k] = min(base_k + c_k, X_{i+1}[k-1] + c_k)` and `H_{i+1}[k] = min(base_k + W,
//! H_{i+1}[k-1])` (the second terms only with horizontal edges), one left-to-right pass.
//! The row step itself (blocks, interleaved chunk scans with an exact fix-up, packed pointers)
//! is in `kernel.rs`. The window minimum is `crate::window`'s: a direct scan for
//! `K <= DIRECT_MAX_K` and a monotone deque (amortised O(1) per cell, independent of `K`)
//! above; both give the same answer, ties to the latest column.
//!
//! Wide rows (at least [`SPLIT_MIN_COLS`] columns) are split in two halves computed on two
//! threads (`rayon::join`). The right half starts from the exact `H` carry (`W` plus the
//! minimum of the previous row's `M` left of the split: `H` is a running minimum) and from an
//! `X` carry of `+inf`; afterwards the true `X` carry is checked at the split column, and in the
//! rare row where it would change that column the right half is recomputed from the true carry.
//! Results never depend on the split.
//!
//! Costs are accumulated in `f64`. Memory: two `f64` vectors of length `D` (previous and current
//! `M`) plus one back-pointer per cell: one byte (`K <= 15`) or two bytes (`K <= 4095`), packing
//! the window offset `0..=K`, whether `M` of the cell is hidden, and the "came horizontally"
//! flags of `x_ij` and `h_ij`.
//!
//! Tie-breaking (deterministic): among equal window minima the largest column (smallest
//! offset) wins; a matching node beats a hidden node of the same cell (`M` takes `x` unless
//! `h` is strictly cheaper); entering a node by a forward edge beats arriving horizontally; at
//! the sink the smallest column of the last row wins.

use super::graph::{check_inputs, hypothesis_from_steps, Blocked, Kind, Step};
use super::kernel::{self, base_value, node_cost, range_step, BackPtr, Dest, RowCtx};
use super::Hypothesis;
use crate::{Matrix, Result};

use crate::window::Scan;

/// Rows with at least this many columns are computed on two threads (two halves).
pub(crate) const SPLIT_MIN_COLS: usize = 8192;

/// The shortest source-sink path for hidden cost `w`, never using a node of `blocked`.
///
/// Runs in `O(Q·D)` time whatever the fan-out, with `O(D)` cost memory and one or two bytes of
/// back-pointer per cell. The returned hypothesis has rank 1. Fails on an empty or non-finite
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

/// The DP values of one row.
#[derive(Clone, Debug)]
pub(crate) struct RowState {
    /// `X[j]`: cheapest path from the source ending at `x_ij` (`+inf` when unusable).
    pub x: Vec<f64>,
    /// `H[j]`: cheapest path from the source ending at `h_ij`.
    pub h: Vec<f64>,
    /// `min(X[j], H[j])`.
    pub m: Vec<f64>,
}

impl RowState {
    pub(crate) fn new(d: usize) -> Self {
        RowState {
            x: vec![0.0; d],
            h: vec![0.0; d],
            m: vec![0.0; d],
        }
    }
}

/// Work buffers of a row step (one per half of a split row), reused from row to row.
#[derive(Default)]
pub(crate) struct Scratch {
    halves: [kernel::Scratch; 2],
}

/// One dynamic programme over the graph of `chat`.
pub(crate) struct Dp<'a> {
    chat: &'a Matrix,
    blocked: Option<&'a Blocked>,
    k: usize,
    horizontal: bool,
    w: f64,
    window: Scan,
    block: usize,
    split_min: usize,
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
        let window = Scan::for_fan_out(k);
        Dp {
            chat,
            blocked,
            k,
            horizontal,
            w,
            window,
            block: kernel::BLOCK,
            split_min: SPLIT_MIN_COLS,
        }
    }

    /// Forces a window strategy (tests).
    #[cfg(test)]
    pub(crate) fn with_window(mut self, window: Scan) -> Self {
        self.window = window;
        self
    }

    /// Forces the block size and the split threshold (tests: tiny chunks, splits of tiny rows).
    #[cfg(test)]
    pub(crate) fn with_layout(mut self, block: usize, split_min: usize) -> Self {
        self.block = block;
        self.split_min = split_min;
        self
    }

    /// Computes row `i` into `dest` (all `D` columns) from `M` of the previous row (`None` for
    /// row 0). Splits wide rows between two threads (see the module doc).
    fn row_step<P: BackPtr>(
        &self,
        i: usize,
        prev: Option<&[f64]>,
        mut dest: Dest<'_, P>,
        scratch: &mut Scratch,
    ) {
        let ctx = RowCtx {
            row: self.chat.row(i),
            i,
            blocked: self.blocked,
            prev,
            k: self.k,
            horizontal: self.horizontal,
            w: self.w,
            window: self.window,
            block: self.block,
        };
        let d = dest.len();
        let inf = (f64::INFINITY, f64::INFINITY);
        let [s0, s1] = &mut scratch.halves;
        if d < self.split_min.max(2) {
            range_step(&ctx, 0, &mut dest, inf, s0);
            return;
        }
        let mid = d / 2;
        // H is a running minimum of `base + W`: its carry at `mid` is exact without the left half.
        let h_mid = prev.map_or(0.0, |p| {
            p[..mid].iter().fold(f64::INFINITY, |a, &v| a.min(v))
        }) + self.w;
        let (mut left, mut right) = dest.split_at(mid);
        let (carry, ()) = rayon::join(
            || range_step(&ctx, 0, &mut left, inf, s0),
            || {
                range_step(&ctx, mid, &mut right, (f64::INFINITY, h_mid), s1);
            },
        );
        if self.horizontal {
            debug_assert_eq!(carry.1, h_mid, "exact H carry at the split");
            // The right half assumed X[mid] came by a forward edge; redo it when it did not.
            let c = node_cost(&ctx, mid);
            let ex = base_value(&ctx, mid) + c;
            if carry.0 + c < ex {
                range_step(&ctx, mid, &mut right, (carry.0, h_mid), s1);
            }
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
        let dest: Dest<u8> = Dest::Values {
            m: &mut cur.m,
            x: &mut cur.x,
            h: &mut cur.h,
        };
        self.row_step(i, prev.map(|p| &p.m[..]), dest, scratch);
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
        let mut ptr = vec![P::default(); q * d];
        let mut prev = vec![0.0; d];
        let mut cur = vec![0.0; d];
        let mut scratch = Scratch::default();
        // The rows run on a pool thread: a wide row's halves are then a local `join` (one job
        // pushed, stolen by the other thread), where from a thread outside the pool every
        // row's `join` is injected into the pool while the caller blocks (two hand-offs a
        // row; the solve alone varied from 0.7 s to 1.2 s on 5,392 x 30,790 that way).
        rayon::scope(|_| {
            for (i, p) in ptr.chunks_exact_mut(d).enumerate() {
                let before = (i > 0).then_some(&prev[..]);
                let dest = Dest::Path {
                    m: &mut cur,
                    ptr: p,
                };
                self.row_step(i, before, dest, &mut scratch);
                std::mem::swap(&mut prev, &mut cur);
            }
        });
        // `prev` now holds M of the last row. Sink: smallest column on ties.
        let mut j = 0;
        for (jj, &v) in prev.iter().enumerate().skip(1) {
            if v < prev[j] {
                j = jj;
            }
        }
        let kind_at = |i: usize, j: usize| {
            if ptr[i * d + j].m_hidden() {
                Kind::Hidden
            } else {
                Kind::Match
            }
        };
        let mut i = q - 1;
        let mut kind = kind_at(i, j);
        let mut steps = Vec::with_capacity(q);
        loop {
            steps.push(Step {
                row: i,
                col: j,
                kind,
            });
            let p = ptr[i * d + j];
            let horizontal = match kind {
                Kind::Match => p.x_horizontal(),
                Kind::Hidden => p.h_horizontal(),
            };
            if horizontal {
                j -= 1;
                continue;
            }
            if i == 0 {
                break;
            }
            i -= 1;
            j -= p.offset();
            kind = kind_at(i, j);
        }
        steps.reverse();
        steps
    }
}

#[cfg(test)]
mod tests {
    use super::super::graph::match_cost;
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
            let a = Dp::new(&chat, k, horizontal, w, None).with_window(Scan::Direct).shortest_steps();
            let b = Dp::new(&chat, k, horizontal, w, None).with_window(Scan::Deque).shortest_steps();
            prop_assert_eq!(a, b);
        }

        #[test]
        fn kernel_is_bit_identical_to_the_plain_scan(
            (chat, blocked) in wide_instance(),
            k in 0usize..=12,
            horizontal: bool,
            w in prop::sample::select(vec![0.5f64, 1.0, 1.25, 3.0, 40.0]),
            block in prop::sample::select(vec![1usize, 2, 3, 7, 8, 9, 16, 17, 64, 1024]),
            split_min in prop::sample::select(vec![1usize, 2, 5, 33, usize::MAX]),
            deque: bool,
        ) {
            let b = blocked.as_ref();
            let (want, want_rows) = plain(&chat, k, horizontal, w, b);
            let window = if deque { Scan::Deque } else { Scan::Direct };
            let dp = Dp::new(&chat, k, horizontal, w, b)
                .with_window(window)
                .with_layout(block, split_min);
            let got = dp.shortest_steps();
            prop_assert_eq!(&got, &want);
            let (hg, hw) = (hypothesis_from_steps(&chat, w, &got, 1), hypothesis_from_steps(&chat, w, &want, 1));
            prop_assert_eq!(hg.cost.to_bits(), hw.cost.to_bits());
            // The values pass of the min-marginals goes through the same kernel.
            let d = chat.cols();
            let (mut prev, mut cur) = (RowState::new(d), RowState::new(d));
            let mut scratch = Scratch::default();
            for (i, (x, h, m)) in want_rows.iter().enumerate() {
                dp.values_step(i, (i > 0).then_some(&prev), &mut cur, &mut scratch);
                prop_assert_eq!(bits(&cur.x), bits(x), "X of row {}", i);
                prop_assert_eq!(bits(&cur.h), bits(h), "H of row {}", i);
                prop_assert_eq!(bits(&cur.m), bits(m), "M of row {}", i);
                std::mem::swap(&mut prev, &mut cur);
            }
        }
    }

    fn bits(v: &[f64]) -> Vec<u64> {
        v.iter().map(|x| x.to_bits()).collect()
    }

    /// Wider random instances than `random_instance`, from a few exactly representable values
    /// (so costs tie often, also at chunk borders) plus noise, with a random blocked set.
    fn wide_instance() -> impl Strategy<Value = (Matrix, Option<Blocked>)> {
        (1usize..=7, 1usize..=90).prop_flat_map(|(q, d)| {
            let value = prop_oneof![
                prop::sample::select(vec![-1.0f32, 0.0, 0.5, 1.0, 2.0, 4.0, 8.0]),
                0.05f32..5.0,
            ];
            (
                prop::collection::vec(value, q * d),
                prop::collection::vec(0u8..12, q * d),
                any::<bool>(),
                Just((q, d)),
            )
                .prop_map(|(v, mask, use_blocked, (q, d))| {
                    let chat = Matrix::from_vec(q, d, v).expect("q*d values");
                    let blocked = use_blocked.then(|| {
                        let mut b = Blocked::new(q, d);
                        for (n, &r) in mask.iter().enumerate() {
                            if r == 0 {
                                b.block(n / d, n % d);
                            }
                        }
                        b
                    });
                    (chat, blocked)
                })
        })
    }

    type RowValues = (Vec<f64>, Vec<f64>, Vec<f64>);

    /// The plain fused left-to-right scan, one cell at a time with per-node pointers (the
    /// solver before `kernel.rs`): the reference the kernel must equal bit for bit. Returns the
    /// path and every row's `(X, H, M)`.
    fn plain(
        chat: &Matrix,
        k: usize,
        horizontal: bool,
        w: f64,
        blocked: Option<&Blocked>,
    ) -> (Vec<Step>, Vec<RowValues>) {
        #[derive(Clone, Copy, Default)]
        struct Ptr {
            horizontal: bool,
            pred_hidden: bool,
            offset: usize,
        }
        let (q, d) = (chat.rows(), chat.cols());
        let mut px = vec![Ptr::default(); q * d];
        let mut ph = vec![Ptr::default(); q * d];
        let mut rows: Vec<RowValues> = Vec::new();
        let mut prev_m = vec![0.0; d];
        let mut prev_fh = vec![false; d];
        for i in 0..q {
            let (mut x, mut h, mut m, mut fh) =
                (vec![0.0; d], vec![0.0; d], vec![0.0; d], vec![false; d]);
            let (mut lx, mut lh) = (f64::INFINITY, f64::INFINITY);
            for j in 0..d {
                let c = if blocked.is_some_and(|b| b.is_blocked(i, j)) {
                    f64::INFINITY
                } else {
                    match_cost(chat.get(i, j))
                };
                let (b, o) = if i == 0 {
                    (0.0, 0)
                } else {
                    let (mut b, mut o) = (prev_m[j], 0);
                    for oo in 1..=k.min(j) {
                        if prev_m[j - oo] < b {
                            (b, o) = (prev_m[j - oo], oo);
                        }
                    }
                    (b, o)
                };
                let fwd = Ptr {
                    horizontal: false,
                    pred_hidden: i > 0 && prev_fh[j - o],
                    offset: o,
                };
                let horiz = Ptr {
                    horizontal: true,
                    ..Ptr::default()
                };
                let (ex, hx) = (b + c, lx + c);
                let vx = if hx < ex { hx } else { ex };
                let (eh, vh) = (b + w, if lh < b + w { lh } else { b + w });
                px[i * d + j] = if hx < ex { horiz } else { fwd };
                ph[i * d + j] = if lh < eh { horiz } else { fwd };
                if horizontal {
                    (lx, lh) = (vx, vh);
                }
                (x[j], h[j]) = (vx, vh);
                fh[j] = vh < vx;
                m[j] = if fh[j] { vh } else { vx };
            }
            prev_m.clone_from(&m);
            prev_fh = fh;
            rows.push((x, h, m));
        }
        let mut j = 0;
        for jj in 1..d {
            if prev_m[jj] < prev_m[j] {
                j = jj;
            }
        }
        let mut kind = if prev_fh[j] {
            Kind::Hidden
        } else {
            Kind::Match
        };
        let mut i = q - 1;
        let mut steps = Vec::new();
        loop {
            steps.push(Step {
                row: i,
                col: j,
                kind,
            });
            let p = match kind {
                Kind::Match => px[i * d + j],
                Kind::Hidden => ph[i * d + j],
            };
            if p.horizontal {
                j -= 1;
                continue;
            }
            if i == 0 {
                break;
            }
            i -= 1;
            j -= p.offset;
            kind = if p.pred_hidden {
                Kind::Hidden
            } else {
                Kind::Match
            };
        }
        steps.reverse();
        (steps, rows)
    }

    #[test]
    fn long_horizontal_runs_cross_chunk_and_split_borders() {
        // Row 0 is usable only at column 0, row 2 only at the last column, row 1 is cheap
        // everywhere and W is high: the path of row 1 enters at the left and walks right
        // through every chunk border and the split.
        let d = 300;
        let mut r0 = vec![-1.0f32; d];
        r0[0] = 1.0;
        let r1 = vec![10.0f32; d];
        let mut r2 = vec![-1.0f32; d];
        r2[d - 1] = 50.0;
        let chat = Matrix::from_rows(&[r0, r1, r2]).unwrap();
        let (want, _) = plain(&chat, 2, true, 100.0, None);
        let h = hypothesis_from_steps(&chat, 100.0, &want, 1);
        assert!(h.rows[1].matches.len() > 250, "{:?}", cols(&h)[1].len());
        for block in [1, 3, 8, 16, 50, 64, 1024] {
            for split_min in [1, 2, 64, usize::MAX] {
                for window in [Scan::Direct, Scan::Deque] {
                    let got = Dp::new(&chat, 2, true, 100.0, None)
                        .with_window(window)
                        .with_layout(block, split_min)
                        .shortest_steps();
                    assert_eq!(got, want, "block {block}, split at {split_min}, {window:?}");
                }
            }
        }
    }

    #[test]
    fn equal_costs_everywhere_break_ties_like_the_plain_scan() {
        let chat = Matrix::from_vec(6, 200, vec![2.0f32; 1200]).unwrap();
        for (k, w) in [(0, 0.5), (1, 0.5), (4, 0.5), (4, 1.0), (9, 0.25)] {
            let (want, _) = plain(&chat, k, true, w, None);
            for block in [1, 8, 24, 1024] {
                for split_min in [1, usize::MAX] {
                    let got = Dp::new(&chat, k, true, w, None)
                        .with_layout(block, split_min)
                        .shortest_steps();
                    assert_eq!(got, want, "K {k}, W {w}, block {block}, split {split_min}");
                }
            }
        }
    }
}
