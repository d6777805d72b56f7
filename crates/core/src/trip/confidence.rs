//! A trip's confidence: the discounted min-marginal ratio of [`crate::confidence`] (the offline
//! default, `confidence/discounted.rs`) on the frames seen so far, in `O(lag · D)` per batch.
//!
//! Offline, the ratio of row `i` is `outside / inside` over the routes through row `i`, every
//! node cost of row `t` weighted `g^|t-i|`: `m(x_ij) = FX_i[j] + BX_i[j]`, the forward values
//! (rows `<= i`, the solver's forward row step on the previous row's `min(FX, FH)` scaled by
//! `g`) plus the backward values (rows `> i`, the backward step on the next row's scaled by
//! `g`). A trip after `T` frames scores with the same statistic on the prefix `[0, T)`:
//!
//! * `F_i` depends only on rows `<= i`, so it never changes once row `i` has arrived. The trip
//!   keeps one row of it, `m` of the row *before* its lag window ([`DiscountedForward`]),
//!   advanced by one forward step whenever a row leaves the window; the window's `F` rows are
//!   recomputed from it per batch (`lag` forward steps).
//! * `B_i` on the prefix covers rows `i+1 .. T`: for the rows in the lag window that is a
//!   backward pass over the window only (`lag` backward steps), the newest row's being empty.
//!
//! So the newest frame's confidence is the causal form (the forward pass alone, the scored
//! frame last), a frame still in the window is re-scored with the frames that arrived after
//! it, and both equal the offline discounted ratio computed on the trip's frames so far
//! (property test `trip_confidence_is_the_offline_discounted_ratio_of_the_prefix`). Only the
//! paper's graph is scored (no relocalization edges), as offline.
//!
//! The row steps are the exact (`f64`) ones: [`crate::solver::forward_values_row`] and the
//! backward arithmetic of the offline reference passes (`confidence/discounted/plain.rs`); the
//! shipped offline sweep runs the same steps in `f32` lanes (`confidence/sweep.rs`), so the
//! two agree up to that rounding (relative 1e-5 in the property test). The forward and the backward pass
//! over the window run on two threads; their buffers are kept per thread between batches.

use std::cell::RefCell;

use crate::confidence::{band_costs, BandCosts, GraphParams};
use crate::solver::{forward_values_row, match_cost, RowScratch};
use crate::window::leading_min_in_place;

/// The graph and the discount `g` the trip scores with.
#[derive(Clone, Copy, Debug)]
pub(super) struct Discount {
    pub graph: GraphParams,
    pub g: f64,
    pub radius: usize,
}

thread_local! {
    /// Spare pass buffers of this thread (at most [`SPARE_BUFFERS`]), so a batch's passes do
    /// not allocate and zero `2 · lag · D` values each time: on a 30,790-image map at lag 32
    /// that is 16 MB per pass, whose page faults cost about as much as the pass.
    static SPARE: RefCell<Vec<Vec<f64>>> = const { RefCell::new(Vec::new()) };
}

/// Spare buffers kept per thread.
const SPARE_BUFFERS: usize = 4;

/// A buffer of at least `len` values (contents unspecified: every pass writes before it reads).
fn take_buffer(len: usize) -> Vec<f64> {
    let mut v = SPARE
        .with(|s| s.try_borrow_mut().ok().and_then(|mut s| s.pop()))
        .unwrap_or_default();
    if v.len() < len {
        v.resize(len, 0.0);
    }
    v
}

/// Returns a buffer to this thread's spares.
fn give_back(v: Vec<f64>) {
    SPARE.with(|s| {
        if let Ok(mut s) = s.try_borrow_mut() {
            if s.len() < SPARE_BUFFERS {
                s.push(v);
            }
        }
    });
}

/// One row's `x` and `h` values inside a pass buffer laid out row by row, `x` then `h`.
fn row_pair(buf: &mut [f64], i: usize, d: usize) -> (&mut [f64], &mut [f64]) {
    buf[2 * i * d..2 * (i + 1) * d].split_at_mut(d)
}

impl Discount {
    /// Forward values `x`, `h`, `m` of `row` from the previous row's `m` (`None`: the trip's
    /// first row).
    #[allow(clippy::too_many_arguments)]
    fn forward(
        &self,
        row: &[f32],
        prev: Option<&[f64]>,
        x: &mut [f64],
        h: &mut [f64],
        m: &mut [f64],
        scaled: &mut [f64],
        s: &mut RowScratch,
    ) {
        let prev = prev.map(|p| {
            for (o, &v) in scaled.iter_mut().zip(p) {
                *o = self.g * v;
            }
            &scaled[..]
        });
        forward_values_row(
            row,
            prev,
            self.graph.fan_out,
            self.graph.horizontal,
            self.graph.hidden_cost,
            (x, h, m),
            s,
        );
    }

    /// Backward values `x`, `h` of `row` from the next row (`None`: the newest row, the sink).
    fn backward(
        &self,
        row: &[f32],
        next: Option<(&[f32], &[f64], &[f64])>,
        (x, h): (&mut [f64], &mut [f64]),
        succ: &mut [f64],
        tmp: &mut [f64],
    ) {
        let w = self.graph.hidden_cost;
        succ.fill(0.0);
        if let Some((next_row, nx, nh)) = next {
            for (((s, &v), &x), &h) in succ.iter_mut().zip(next_row).zip(nx).zip(nh) {
                *s = (match_cost(v) + x).min(w + h);
            }
            leading_min_in_place(succ, self.graph.fan_out, tmp);
            for s in succ.iter_mut() {
                *s *= self.g;
            }
        }
        if self.graph.horizontal {
            let (mut right_x, mut right_h) = (f64::INFINITY, f64::INFINITY);
            for j in (0..row.len()).rev() {
                x[j] = succ[j].min(right_x);
                h[j] = succ[j].min(right_h);
                right_x = match_cost(row[j]) + x[j];
                right_h = h[j];
            }
        } else {
            x.copy_from_slice(succ);
            h.copy_from_slice(succ);
        }
    }

    /// The forward pass over `rows` from `before` into `buf` (rows `0..rows.len()`).
    fn forward_pass(&self, rows: &[&[f32]], before: Option<&[f64]>, buf: &mut [f64]) {
        let d = rows[0].len();
        let mut prev: Vec<f64> = before.map_or_else(|| vec![0.0; d], <[f64]>::to_vec);
        let (mut m, mut scaled) = (vec![0.0; d], vec![0.0; d]);
        let mut scratch = RowScratch::default();
        for (i, row) in rows.iter().enumerate() {
            let (x, h) = row_pair(buf, i, d);
            let p = (i > 0 || before.is_some()).then_some(&prev[..]);
            self.forward(row, p, x, h, &mut m, &mut scaled, &mut scratch);
            std::mem::swap(&mut prev, &mut m);
        }
    }

    /// The backward pass over `rows[first..]` into `buf` (row `i` at `i - first`).
    fn backward_pass(&self, rows: &[&[f32]], first: usize, buf: &mut [f64]) {
        let (n, d) = (rows.len(), rows[0].len());
        let (mut succ, mut tmp) = (vec![0.0; d], vec![0.0; d]);
        for i in (first..n).rev() {
            let (head, tail) = buf.split_at_mut(2 * (i - first + 1) * d);
            let out = row_pair(head, i - first, d);
            let next = (i + 1 < n).then(|| {
                let (nx, nh) = tail[..2 * d].split_at(d);
                (rows[i + 1], nx, nh)
            });
            self.backward(rows[i], next, out, &mut succ, &mut tmp);
        }
    }

    /// The discounted ratio of the window's rows on the frames so far: `rows` are the lag
    /// window's `ĉ` rows (oldest first, the newest frame last), `before` the forward `m` of
    /// the row before the window (`None` when the window starts at the trip's first row), and
    /// `targets` the `(window index, prediction)` pairs to score. The forward and the backward
    /// pass over the window run at the same time (two threads of the current pool), then each
    /// target's band costs are read from its row's values ([`band_costs`]; `None` for an empty
    /// window).
    pub fn window_bands(
        &self,
        rows: &[&[f32]],
        before: Option<&[f64]>,
        targets: &[(usize, usize)],
    ) -> Vec<Option<BandCosts>> {
        let (n, d) = (rows.len(), rows.first().map_or(0, |r| r.len()));
        if n == 0 || d == 0 || targets.is_empty() {
            return vec![None; targets.len()];
        }
        // Backward rows from the first scored row on (the earlier ones are not needed).
        let first = targets.iter().map(|t| t.0).min().unwrap_or(0).min(n - 1);
        let last = targets.iter().map(|t| t.0).max().unwrap_or(0).min(n - 1);
        let (fwd, bwd) = rayon::join(
            || {
                let mut buf = take_buffer(2 * (last + 1) * d);
                self.forward_pass(&rows[..=last], before, &mut buf);
                buf
            },
            || {
                let mut buf = take_buffer(2 * (n - first) * d);
                self.backward_pass(rows, first, &mut buf);
                buf
            },
        );
        let out = targets
            .iter()
            .map(|&(i, j)| {
                let f = fwd[2 * i * d..2 * (i + 1) * d].split_at(d);
                let b = bwd[2 * (i - first) * d..2 * (i - first + 1) * d].split_at(d);
                Some(band_costs(f, b, j, self.radius))
            })
            .collect();
        give_back(fwd);
        give_back(bwd);
        out
    }
}

/// The discounted forward value `m` of the row before a trip's lag window: the one row of the
/// forward pass a trip keeps (see the module doc). `None` until a row leaves the window.
#[derive(Clone, Debug, Default, PartialEq)]
pub(super) struct DiscountedForward(pub Option<Vec<f64>>);

impl DiscountedForward {
    /// Advances by the row that just left the lag window.
    pub fn advance(&mut self, discount: &Discount, row: &[f32]) {
        let d = row.len();
        let mut buf = take_buffer(3 * d);
        let (x, rest) = buf[..3 * d].split_at_mut(d);
        let (h, scaled) = rest.split_at_mut(d);
        let mut m = vec![0.0; d];
        let mut scratch = RowScratch::default();
        discount.forward(row, self.0.as_deref(), x, h, &mut m, scaled, &mut scratch);
        give_back(buf);
        self.0 = Some(m);
    }

    /// Approximate heap bytes held.
    pub fn heap_bytes(&self) -> usize {
        self.0.as_ref().map_or(0, |m| m.capacity() * 8)
    }
}
