//! The discounted min-marginal ratio: the local ratio of [`super`] in `O(Q·D)` total.
//!
//! The box window of [`super::window_ratio`] (rows `i-L ..= i+L`, free ends) has to be solved
//! anew for every scored row: `(2L+1)·D` work per row. Weighting the rows of a route by
//! `g^|t-i|` instead (`0 < g < 1`) keeps the same meaning — evidence near row `i` counts, far
//! evidence fades — but decomposes: with `FX_i`, `FH_i` the cheapest *discounted* path from the
//! source to a node of row `i` (row `t` weighted `g^(i-t)`), `FX_i[j] = c_ij + min(g·base_j,
//! FX_i[j-1])` where `base` is the sliding-window minimum of row `i-1`'s `min(FX, FH)`: the
//! solver's forward row step run on the previous row scaled by `g`. The backward values
//! `BX_i`, `BH_i` (row `t > i` weighted `g^(t-i)`, node excluded) are the backward step of
//! [`crate::solver::row_alternatives`] with the next row scaled by `g`. Then
//! `m(x_ij) = FX_i[j] + BX_i[j]` is the cheapest complete route through `x_ij` with every row
//! weighted by its distance to `i`, for every `i` at once: one forward and one backward pass.
//!
//! The ratio is the one of [`super`]: `outside / inside`, `inside` the best route through a
//! match within `r` of the prediction, `outside` the best through a match further away or a
//! hidden node of row `i`. `g = 1 - 1/(L+1)` gives the rows at distance `<= L` from `i` the bulk
//! of the weight, as the box window of half-width `L`. A property test checks the result
//! against every route of small graphs enumerated by brute force.
//!
//! Online (trips) the same statistic is causal with the backward part left out: `FX_i + 0`
//! (the forward pass alone, the scored frame last).
//!
//! Memory `O(sqrt(Q)·D)`: the forward and the backward pass (run at the same time on two
//! threads) keep every `s`-th row (`s = ceil(sqrt Q)`); then blocks of `s` rows are
//! recomputed from their checkpoints, in parallel, and scored. Work: two forward and two
//! backward passes.

use rayon::prelude::*;

use crate::solver::{forward_values_row, match_cost, RowScratch};
use crate::window::leading_min_in_place;
use crate::Matrix;

use super::GraphParams;

/// The graph and the discount.
#[derive(Clone, Copy)]
struct Passes<'a> {
    chat: &'a Matrix,
    k: usize,
    horizontal: bool,
    w: f64,
    g: f64,
}

/// Two scratch rows of the backward step.
type Tmp = (Vec<f64>, Vec<f64>);

fn tmp(d: usize) -> Tmp {
    (vec![0.0; d], vec![0.0; d])
}

/// Forward values of one row: `x`, `h`, `m` (cheapest discounted path ending at the node).
#[derive(Clone)]
struct Forward {
    x: Vec<f64>,
    h: Vec<f64>,
    m: Vec<f64>,
}

/// Backward values of one row: `x`, `h` (cheapest discounted continuation after the node).
#[derive(Clone)]
struct Backward {
    x: Vec<f64>,
    h: Vec<f64>,
}

impl Passes<'_> {
    /// Row `i`'s forward values from row `i-1`'s `m` (`None` for row 0: the source).
    fn forward(
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
    fn backward(&self, i: usize, next: Option<&Backward>, out: &mut Backward, tmp: &mut Tmp) {
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
fn ratio(f: &Forward, b: &Backward, radius: usize, j_star: usize) -> f64 {
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
pub(super) fn discounted_ratios(
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

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// Every route from row 0 to the last row by brute force, each node cost weighted by
    /// `g^|t-i|`; the ratio for row `i`, prediction `js`.
    fn brute_force(chat: &Matrix, gp: &GraphParams, g: f64, r: usize, i: usize, js: usize) -> f64 {
        let (q, d) = (chat.rows(), chat.cols());
        // Per row: a run [a, b] of one kind (matching or hidden), entered within the fan-out.
        let mut routes: Vec<Vec<(usize, usize, bool)>> = vec![Vec::new()];
        for t in 0..q {
            let mut next = Vec::new();
            for trace in &routes {
                let (lo, hi) = match trace.last() {
                    None => (0, d - 1),
                    Some(&(_, b, _)) => (b, (b + gp.fan_out).min(d - 1)),
                };
                for hidden in [false, true] {
                    for a in lo..=hi {
                        let max_b = if gp.horizontal { d - 1 } else { a };
                        for b in a..=max_b {
                            if !hidden && (a..=b).any(|j| match_cost(chat.get(t, j)).is_infinite())
                            {
                                continue;
                            }
                            let mut tr = trace.clone();
                            tr.push((a, b, hidden));
                            next.push(tr);
                        }
                    }
                }
            }
            routes = next;
        }
        let (mut best_in, mut best_out) = (f64::INFINITY, f64::INFINITY);
        for trace in routes {
            let cost: f64 = trace
                .iter()
                .enumerate()
                .map(|(t, &(a, b, hidden))| {
                    let c = if hidden {
                        gp.hidden_cost
                    } else {
                        (a..=b).map(|j| match_cost(chat.get(t, j))).sum()
                    };
                    c * g.powi((t as i32 - i as i32).abs())
                })
                .sum();
            let (a, b, hidden) = trace[i];
            let (lo, hi) = (js.saturating_sub(r), js + r);
            if hidden {
                best_out = best_out.min(cost);
                continue;
            }
            if (a..=b).any(|j| (lo..=hi).contains(&j)) {
                best_in = best_in.min(cost);
            }
            if (a..=b).any(|j| !(lo..=hi).contains(&j)) {
                best_out = best_out.min(cost);
            }
        }
        if best_in.is_finite() {
            best_out / best_in
        } else {
            0.0
        }
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(48))]
        #[test]
        fn discounted_ratio_matches_brute_force(
            q in 1usize..5, d in 1usize..5, seed in prop::collection::vec(-0.3f32..2.5, 20),
            k in 0usize..3, horizontal: bool, w in 0.3f64..2.5, g in 0.3f64..1.0, r in 0usize..2,
        ) {
            let chat = Matrix::from_vec(q, d, seed[..q * d].to_vec()).unwrap();
            let gp = GraphParams { fan_out: k, horizontal, hidden_cost: w };
            let targets: Vec<(usize, usize)> =
                (0..q).flat_map(|i| (0..d).map(move |j| (i, j))).collect();
            let fast = discounted_ratios(&chat, &gp, g, r, &targets);
            for (&(i, js), f) in targets.iter().zip(&fast) {
                let slow = brute_force(&chat, &gp, g, r, i, js);
                prop_assert!((f - slow).abs() <= 1e-9 * slow.abs().max(1.0),
                    "row {i} col {js}: {f} vs {slow}");
            }
        }
    }

    #[test]
    fn blocks_and_checkpoints_do_not_change_the_result() {
        // 40 rows: 7 blocks of 7 rows (the last one shorter), against one sequential pass each
        // way that keeps every row.
        let (q, d) = (40, 9);
        let data: Vec<f32> = (0..q * d)
            .map(|n| ((n * 37 % 101) as f32) / 40.0 - 0.2)
            .collect();
        let chat = Matrix::from_vec(q, d, data).unwrap();
        let gp = GraphParams {
            fan_out: 2,
            horizontal: true,
            hidden_cost: 1.1,
        };
        let p = Passes {
            chat: &chat,
            k: 2,
            horizontal: true,
            w: 1.1,
            g: 0.8,
        };
        let mut fw: Vec<Forward> = Vec::new();
        let mut cur = Forward {
            x: vec![0.0; d],
            h: vec![0.0; d],
            m: vec![0.0; d],
        };
        let (mut scaled, mut scratch) = (vec![0.0; d], RowScratch::default());
        for i in 0..q {
            let prev = if i > 0 {
                Some(fw[i - 1].m.clone())
            } else {
                None
            };
            p.forward(i, prev.as_deref(), &mut cur, &mut scaled, &mut scratch);
            fw.push(cur.clone());
        }
        let mut bw: Vec<Backward> = Vec::new();
        let mut tmp = tmp(d);
        for i in (0..q).rev() {
            let mut out = Backward {
                x: vec![0.0; d],
                h: vec![0.0; d],
            };
            p.backward(i, bw.last(), &mut out, &mut tmp);
            bw.push(out);
        }
        bw.reverse();
        let targets: Vec<(usize, usize)> = (0..q).map(|i| (i, (i * 5) % d)).collect();
        let fast = discounted_ratios(&chat, &gp, 0.8, 1, &targets);
        for (&(i, j), f) in targets.iter().zip(&fast) {
            assert_eq!(*f, ratio(&fw[i], &bw[i], 1, j), "row {i}");
        }
    }
}
