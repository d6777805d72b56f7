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
//! The row steps are the offline ones: [`crate::solver::forward_values_row`] and the same
//! backward arithmetic as `confidence/discounted.rs` (written out here because that module's
//! step is private to it), so the values are bit-identical.

use crate::confidence::GraphParams;
use crate::solver::{forward_values_row, match_cost, RowScratch};
use crate::window::leading_min_in_place;

/// The graph and the discount `g` the trip scores with.
#[derive(Clone, Copy, Debug)]
pub(super) struct Discount {
    pub graph: GraphParams,
    pub g: f64,
    pub radius: usize,
}

/// Forward values of one row: `x`, `h` and `m = min(x, h)` along the window minimum.
struct Forward {
    x: Vec<f64>,
    h: Vec<f64>,
    m: Vec<f64>,
}

impl Forward {
    fn new(d: usize) -> Self {
        Forward {
            x: vec![0.0; d],
            h: vec![0.0; d],
            m: vec![0.0; d],
        }
    }
}

/// Backward values of one row.
struct Backward {
    x: Vec<f64>,
    h: Vec<f64>,
}

impl Discount {
    /// Forward values of `row` from the previous row's `m` (`None`: the trip's first row).
    fn forward(
        &self,
        row: &[f32],
        prev: Option<&[f64]>,
        out: &mut Forward,
        scaled: &mut [f64],
        s: &mut RowScratch,
    ) {
        let prev = prev.map(|p| {
            for (o, &v) in scaled.iter_mut().zip(p) {
                *o = self.g * v;
            }
            &scaled[..]
        });
        let Forward { x, h, m } = out;
        forward_values_row(
            row,
            prev,
            self.graph.fan_out,
            self.graph.horizontal,
            self.graph.hidden_cost,
            (&mut x[..], &mut h[..], &mut m[..]),
            s,
        );
    }

    /// Backward values of `row` from the next row (`None`: the newest row, the sink).
    fn backward(
        &self,
        row: &[f32],
        next: Option<(&[f32], &Backward)>,
        out: &mut Backward,
        succ: &mut [f64],
        tmp: &mut [f64],
    ) {
        let w = self.graph.hidden_cost;
        succ.fill(0.0);
        if let Some((next_row, n)) = next {
            for (((s, &v), &x), &h) in succ.iter_mut().zip(next_row).zip(&n.x).zip(&n.h) {
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
                out.x[j] = succ[j].min(right_x);
                out.h[j] = succ[j].min(right_h);
                right_x = match_cost(row[j]) + out.x[j];
                right_h = out.h[j];
            }
        } else {
            out.x.copy_from_slice(succ);
            out.h.copy_from_slice(succ);
        }
    }

    /// The ratio of a row from its forward and backward values, for the prediction `j_star`.
    fn ratio(&self, f: &Forward, b: &Backward, j_star: usize) -> f64 {
        let d = f.x.len();
        let lo = j_star.saturating_sub(self.radius);
        let hi = (j_star + self.radius).min(d - 1);
        let mut inside = f64::INFINITY;
        let mut outside = f64::INFINITY;
        for j in 0..d {
            let through = f.x[j] + b.x[j];
            if (lo..=hi).contains(&j) {
                inside = inside.min(through);
            } else {
                outside = outside.min(through);
            }
            outside = outside.min(f.h[j] + b.h[j]);
        }
        if inside.is_finite() {
            outside / inside
        } else {
            0.0
        }
    }

    /// The discounted ratio of the window's rows on the frames so far: `rows` are the lag
    /// window's `ĉ` rows (oldest first, the newest frame last), `before` the forward `m` of
    /// the row before the window (`None` when the window starts at the trip's first row), and
    /// `targets` the `(window index, prediction)` pairs to score. One backward pass over the
    /// window, then one forward pass that scores as it goes.
    pub fn window_ratios(
        &self,
        rows: &[&[f32]],
        before: Option<&[f64]>,
        targets: &[(usize, usize)],
    ) -> Vec<f64> {
        let (n, d) = (rows.len(), rows.first().map_or(0, |r| r.len()));
        if n == 0 || d == 0 || targets.is_empty() {
            return vec![0.0; targets.len()];
        }
        // Backward rows from the first scored row on (the earlier ones are not needed).
        let first = targets.iter().map(|t| t.0).min().unwrap_or(0);
        let mut back: Vec<Backward> = (first..n)
            .map(|_| Backward {
                x: vec![0.0; d],
                h: vec![0.0; d],
            })
            .collect();
        let (mut succ, mut tmp) = (vec![0.0; d], vec![0.0; d]);
        for i in (first..n).rev() {
            let (head, tail) = back.split_at_mut(i - first + 1);
            let next = (i + 1 < n).then(|| (rows[i + 1], &tail[0]));
            self.backward(rows[i], next, &mut head[i - first], &mut succ, &mut tmp);
        }
        let mut out = vec![0.0; targets.len()];
        let mut cur = Forward::new(d);
        let mut prev: Option<Vec<f64>> = before.map(<[f64]>::to_vec);
        let (mut scaled, mut scratch) = (vec![0.0; d], RowScratch::default());
        for (i, row) in rows.iter().enumerate() {
            self.forward(row, prev.as_deref(), &mut cur, &mut scaled, &mut scratch);
            for (o, &(t, j)) in out.iter_mut().zip(targets) {
                if t == i {
                    *o = self.ratio(&cur, &back[i - first], j);
                }
            }
            let m = std::mem::replace(&mut cur.m, prev.take().unwrap_or_else(|| vec![0.0; d]));
            prev = Some(m);
        }
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
        let mut cur = Forward::new(d);
        let (mut scaled, mut scratch) = (vec![0.0; d], RowScratch::default());
        discount.forward(row, self.0.as_deref(), &mut cur, &mut scaled, &mut scratch);
        self.0 = Some(cur.m);
    }

    /// Approximate heap bytes held.
    pub fn heap_bytes(&self) -> usize {
        self.0.as_ref().map_or(0, |m| m.capacity() * 8)
    }
}
