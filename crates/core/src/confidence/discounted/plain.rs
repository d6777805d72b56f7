//! Test reference: the discounted passes in plain `f64`, column by column in natural order
//! (the implementation before the lane sweep). Checks the sweep on matrices too large for the
//! brute force.
#![allow(dead_code)]

use rayon::prelude::*;

use crate::solver::{forward_values_row, match_cost, RowScratch};
use crate::window::leading_min_in_place;
use crate::Matrix;

use crate::confidence::GraphParams;

/// The graph and the discount.
#[derive(Clone, Copy)]
pub(crate) struct Passes<'a> {
    pub(crate) chat: &'a Matrix,
    pub(crate) k: usize,
    pub(crate) horizontal: bool,
    pub(crate) w: f64,
    pub(crate) g: f64,
}

/// Two scratch rows of the backward step.
pub(crate) type Tmp = (Vec<f64>, Vec<f64>);

pub(crate) fn tmp(d: usize) -> Tmp {
    (vec![0.0; d], vec![0.0; d])
}

/// Forward values of one row: `x`, `h`, `m` (cheapest discounted path ending at the node).
#[derive(Clone)]
pub(crate) struct Forward {
    pub(crate) x: Vec<f64>,
    pub(crate) h: Vec<f64>,
    pub(crate) m: Vec<f64>,
}

/// Backward values of one row: `x`, `h` (cheapest discounted continuation after the node).
#[derive(Clone)]
pub(crate) struct Backward {
    pub(crate) x: Vec<f64>,
    pub(crate) h: Vec<f64>,
}

impl Passes<'_> {
    /// Row `i`'s forward values from row `i-1`'s `m` (`None` for row 0: the source).
    pub(crate) fn forward(
        &self,
        i: usize,
        prev: Option<&[f64]>,
        out: &mut Forward,
        scaled: &mut [f64],
        s: &mut RowScratch,
    ) {
        let prev = match prev {
            Some(p) => {
                for (o, &v) in scaled.iter_mut().zip(p) {
                    *o = self.g * v;
                }
                Some(&scaled[..])
            }
            None => None,
        };
        let Forward { x, h, m } = out;
        let out = (&mut x[..], &mut h[..], &mut m[..]);
        forward_values_row(
            self.chat.row(i),
            prev,
            self.k,
            self.horizontal,
            self.w,
            out,
            s,
        );
    }

    /// Row `i`'s backward values from row `i+1`'s (`None` for the last row: the sink).
    pub(crate) fn backward(
        &self,
        i: usize,
        next: Option<&Backward>,
        out: &mut Backward,
        tmp: &mut Tmp,
    ) {
        let d = self.chat.cols();
        let (succ, tmp) = (&mut tmp.0[..], &mut tmp.1[..]);
        succ.fill(0.0);
        if let Some(n) = next {
            for (((s, &v), &x), &h) in succ
                .iter_mut()
                .zip(self.chat.row(i + 1))
                .zip(&n.x)
                .zip(&n.h)
            {
                *s = (match_cost(v) + x).min(self.w + h);
            }
            leading_min_in_place(succ, self.k, tmp);
            for s in succ.iter_mut() {
                *s *= self.g;
            }
        }
        if self.horizontal {
            let (mut right_x, mut right_h) = (f64::INFINITY, f64::INFINITY);
            let row = self.chat.row(i);
            for j in (0..d).rev() {
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
}

/// The ratio of row `i` from its forward and backward values, for the prediction `j_star`.
pub(crate) fn ratio(f: &Forward, b: &Backward, radius: usize, j_star: usize) -> f64 {
    let d = f.x.len();
    let lo = j_star.saturating_sub(radius);
    let hi = (j_star + radius).min(d - 1);
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

/// The discounted min-marginal ratio of every `(row, prediction)` in `targets` on `chat`
/// (see the module doc), in the order given. `discount` is `g` in `(0, 1]`; rows must be in
/// the matrix (checked by the caller).
pub(crate) fn discounted_ratios(
    chat: &Matrix,
    graph: &GraphParams,
    discount: f64,
    radius: usize,
    targets: &[(usize, usize)],
) -> Vec<f64> {
    let (q, d) = (chat.rows(), chat.cols());
    if q == 0 || d == 0 || targets.is_empty() {
        return vec![0.0; targets.len()];
    }
    let p = Passes {
        chat,
        k: graph.fan_out,
        horizontal: graph.horizontal,
        w: graph.hidden_cost,
        g: discount,
    };
    let s = ((q as f64).sqrt().ceil() as usize).max(1);
    let blocks = q.div_ceil(s);
    // Phase 1, two threads: forward checkpoints (`m` of the row before each block) and
    // backward checkpoints (the row after each block).
    let (f_marks, b_marks) = rayon::join(
        || {
            let mut marks: Vec<Option<Vec<f64>>> = vec![None; blocks];
            let mut cur = Forward {
                x: vec![0.0; d],
                h: vec![0.0; d],
                m: vec![0.0; d],
            };
            let mut prev = cur.m.clone();
            let (mut scaled, mut scratch) = (vec![0.0; d], RowScratch::default());
            for i in 0..q.saturating_sub(1) {
                p.forward(
                    i,
                    (i > 0).then_some(&prev[..]),
                    &mut cur,
                    &mut scaled,
                    &mut scratch,
                );
                std::mem::swap(&mut prev, &mut cur.m);
                if (i + 1) % s == 0 {
                    marks[(i + 1) / s] = Some(prev.clone());
                }
            }
            marks
        },
        || {
            let mut marks: Vec<Option<Backward>> = vec![None; blocks];
            let blank = Backward {
                x: vec![0.0; d],
                h: vec![0.0; d],
            };
            let (mut next, mut cur) = (blank.clone(), blank);
            let mut tmp = tmp(d);
            for i in (s..q).rev() {
                p.backward(i, (i + 1 < q).then_some(&next), &mut cur, &mut tmp);
                std::mem::swap(&mut next, &mut cur);
                if i % s == 0 {
                    marks[i / s - 1] = Some(next.clone());
                }
            }
            marks
        },
    );
    let mut wanted: Vec<Vec<(usize, usize)>> = vec![Vec::new(); q];
    for (t, &(i, j)) in targets.iter().enumerate() {
        wanted[i].push((t, j));
    }
    // Phase 2: each block recomputes its backward rows, then its forward rows, and scores.
    let scored: Vec<Vec<(usize, f64)>> = (0..blocks)
        .into_par_iter()
        .map(|b| {
            let (a, e) = (b * s, ((b + 1) * s).min(q));
            if wanted[a..e].iter().all(Vec::is_empty) {
                return Vec::new();
            }
            let blank = Backward {
                x: vec![0.0; d],
                h: vec![0.0; d],
            };
            let mut back = vec![blank; e - a];
            let mut tmp = tmp(d);
            for i in (a..e).rev() {
                let (rows, after) = back.split_at_mut(i - a + 1);
                let next = if i + 1 == e {
                    b_marks[b].as_ref()
                } else {
                    after.first()
                };
                p.backward(i, next, &mut rows[i - a], &mut tmp);
            }
            let mut cur = Forward {
                x: vec![0.0; d],
                h: vec![0.0; d],
                m: vec![0.0; d],
            };
            let mut prev = f_marks[b].clone().unwrap_or_else(|| vec![0.0; d]);
            let (mut scaled, mut scratch) = (vec![0.0; d], RowScratch::default());
            let mut out = Vec::new();
            for i in a..e {
                p.forward(
                    i,
                    (i > 0).then_some(&prev[..]),
                    &mut cur,
                    &mut scaled,
                    &mut scratch,
                );
                for &(t, j) in &wanted[i] {
                    out.push((t, ratio(&cur, &back[i - a], radius, j)));
                }
                std::mem::swap(&mut prev, &mut cur.m);
            }
            out
        })
        .collect();
    let mut result = vec![0.0; targets.len()];
    for (t, r) in scored.into_iter().flatten() {
        result[t] = r;
    }
    result
}

/// A `q x d` test matrix of values in [-0.3, 2.5) (some non-positive, so `+inf` costs occur),
/// from a xorshift generator whose `state` (non-zero) carries over between calls.
pub(crate) fn noise_matrix(q: usize, d: usize, state: &mut u64) -> Matrix {
    let data: Vec<f32> = (0..q * d)
        .map(|_| {
            *state ^= *state << 13;
            *state ^= *state >> 7;
            *state ^= *state << 17;
            (*state >> 40) as f32 / (1u64 << 24) as f32 * 2.8 - 0.3
        })
        .collect();
    Matrix::from_vec(q, d, data).expect("q x d values")
}
