//! The two passes of the discounted min-marginals, fast: `f32` lanes, one pass each way, the
//! two running at the same time and meeting in the middle.
//!
//! What is computed is [`super::discounted`]'s definition: the forward values `FX_i`, `FH_i`
//! (cheapest discounted path from the source to `x_ij` / `h_ij`, row `t` weighted `g^(i-t)`) and
//! the backward values `BX_i`, `BH_i` (cheapest discounted continuation after the node, row
//! `t > i` weighted `g^(t-i)`), so that `FX_i[j] + BX_i[j]` is the cheapest route through
//! `x_ij` and `min_j FH_i[j] + BH_i[j]` the cheapest route hidden at row `i`. How it is fast:
//!
//! * **Lanes.** A row's `D` columns are cut into [`LANES`] contiguous chunks of `n` columns and
//!   stored transposed (`[t][l]` = column `l·n + t`), so every recurrence along a row (the
//!   horizontal steps, the running minimum of the hidden nodes, the window minimum) runs on all
//!   chunks at once as plain element-wise operations on `[f32; LANES]` that the compiler
//!   vectorises. Each chunk starts from a `+inf` carry; afterwards chunks are fixed up from the
//!   true carry of the chunk before, exactly as the solver's kernel does (`solver/kernel.rs`):
//!   the `X` chain is re-walked only while the carry changes it, the `H` chain (a running
//!   minimum) takes `min(carry, local)`, applied where a value is read.
//! * **One pass a row step** (`lanes/fused.rs`, the default graph: horizontal edges, `K <= 8`):
//!   window minimum, factor, both scans and what the next step reads in one loop over the row.
//! * **AVX2.** The row steps and the cost transpose are compiled again for AVX2 and picked at
//!   run time ([`Isa`]): a lane row is then one register instead of two SSE2 ones. Same
//!   operations, same values.
//! * **`f32`.** Values are `f32` (node costs `1/ĉ` of the `f32` matrix), half the memory
//!   traffic and twice the lanes of `f64`. The discount keeps sums short (a route's weight
//!   `Σ g^|t-i|` is at most `(1+g)/(1-g)`), so rounding stays at a few `f32` ulps of the result;
//!   the property tests compare with the `f64` brute force at a relative `1e-5`. The solver's
//!   path and costs stay `f64`: only the confidence, a ranking, is `f32`.
//! * **Meeting in the middle, checkpoints instead of kept rows.** Phase 1 runs the forward
//!   pass over the top half of the rows on one thread while the backward pass runs over the
//!   bottom half on the other. Phase 2 continues both passes into the other half, where each
//!   row's own values meet the other pass's. Those are not kept from phase 1 (that was `4·D`
//!   bytes a scored row, 516 MB at 5,392 x 30,790, whose first touches cost more than
//!   computing them again): each pass keeps a checkpoint of its state every [`SEGMENT`] rows,
//!   and the other pass computes a segment's rows again from it into buffers that stay in
//!   cache, with their costs, which it then uses for its own step. One forward and one backward
//!   pass in total plus one more row step a row, the matrix transposed once a row a pass; memory
//!   a checkpoint per segment (21 MB a thread at 5,392 x 30,790) and `3·SEGMENT` rows a
//!   thread. For the hidden nodes only the steps of the other pass's `H` are read (with
//!   horizontal edges `FH_i` is non-increasing and `BH_i` non-decreasing in `j`, so `min_j
//!   FH_i[j] + BH_i[j]` is reached at a step of either).

// The readout's lane code indexes several `[f32; LANES]` rows by the same index.
#![allow(clippy::needless_range_loop)]

mod lanes;

use super::GraphParams;
use crate::Matrix;
use std::ops::Range;

use lanes::{min, Checkpoint, Graph, Isa, Lanes, Layout, RowValues, Steps, Work, LANES};

/// What a scored row's reader sees: the two passes' `X` values and the best hidden route.
pub(super) struct RowView<'a> {
    /// The layout of `fx` and `bx`.
    pub lay: Layout,
    /// `FX_i` (lane layout).
    pub fx: &'a [[f32; LANES]],
    /// `BX_i` (lane layout).
    pub bx: &'a [[f32; LANES]],
    /// `min_j FH_i[j] + BH_i[j]`: the cheapest route hidden at row `i`.
    pub hidden: f32,
}

impl RowView<'_> {
    /// `m(x_ij) = FX_i[j] + BX_i[j]`: the cheapest route through `x_ij`.
    #[inline]
    pub(super) fn through(&self, j: usize) -> f32 {
        let (t, l) = self.lay.at(j);
        self.fx[t][l] + self.bx[t][l]
    }

    /// The cheapest route through a matching node of a column outside `lo ..= hi` (`+inf`
    /// when there is none), in one pass over the row.
    pub(super) fn best_outside(&self, lo: usize, hi: usize) -> f32 {
        let lay = self.lay;
        // The rows `t` of the lane layout that hold a column of `lo ..= hi`.
        let mut skip: Vec<usize> = (lo..=hi.min(lay.d - 1)).map(|j| lay.at(j).0).collect();
        skip.sort_unstable();
        skip.dedup();
        let mut acc = [f32::INFINITY; LANES];
        let mut from = 0;
        for &t in skip.iter().chain(std::iter::once(&lay.n)) {
            for (f, b) in self.fx[from..t].iter().zip(&self.bx[from..t]) {
                for l in 0..LANES {
                    acc[l] = min(acc[l], f[l] + b[l]);
                }
            }
            if t < lay.n {
                for l in 0..LANES {
                    let j = lay.col(t, l);
                    if !(lo..=hi).contains(&j) {
                        acc[l] = min(acc[l], self.fx[t][l] + self.bx[t][l]);
                    }
                }
            }
            from = t + 1;
        }
        acc.into_iter().fold(f32::INFINITY, min)
    }
}

/// Runs both passes over `chat` and calls `read(i, view)` for every row `i` with
/// `scored[i]`, from two threads; returns the readings in row order.
pub(super) fn sweep<R: Send>(
    chat: &Matrix,
    graph: &GraphParams,
    discount: f64,
    scored: &[bool],
    read: impl Fn(usize, &RowView<'_>) -> R + Sync,
) -> Vec<(usize, R)> {
    sweep_on(Isa::detect(), SEGMENT, chat, graph, discount, scored, read)
}

/// Rows per segment: each pass checkpoints its state at every segment start of its first
/// half, and in the second phase the other pass computes one segment again from there into
/// buffers that stay in cache (`3·SEGMENT` rows a thread; 6 MB at 30,790 columns).
const SEGMENT: usize = 16;

/// One segment of one pass, computed again: each row's values and costs (the pass that reads
/// the segment takes its own step's costs from here instead of transposing the row again).
struct Segment {
    vals: Vec<RowValues>,
    costs: Vec<Lanes>,
}

impl Segment {
    fn new(lay: &Layout, len: usize) -> Self {
        Segment {
            vals: (0..len).map(|_| RowValues::new(lay)).collect(),
            costs: (0..len).map(|_| vec![[0.0; LANES]; lay.n]).collect(),
        }
    }
}

/// One pass's row steps over a range of rows, in the pass's order (forward: increasing,
/// backward: decreasing), going on from the state in its [`Work`] (the row before, a
/// checkpoint, or nothing at the source or the sink).
struct Pass<'a> {
    st: &'a Steps,
    chat: &'a Matrix,
    forward: bool,
}

impl Pass<'_> {
    /// Computes row `i` into `out` with the costs in `w.cost`.
    fn step(&self, i: usize, w: &mut Work, out: &mut RowValues) {
        if self.forward {
            self.st.forward(i > 0, w, out);
        } else {
            self.st.backward(i + 1 < self.chat.rows(), w, out);
        }
    }

    /// The rows of `rows` in this pass's order, each one's costs transposed.
    fn run(&self, rows: Range<usize>, w: &mut Work, out: &mut RowValues) {
        for i in self.order(rows) {
            self.st.costs(self.chat.row(i), &mut w.cost);
            self.step(i, w, out);
        }
    }

    /// The rows of `rows` into `seg` (values and costs of row `rows.start + t` at `t`).
    fn run_into(&self, rows: Range<usize>, w: &mut Work, seg: &mut Segment) {
        let start = rows.start;
        for i in self.order(rows) {
            let t = i - start;
            // The step reads `w.cost`: lend it the segment's cost row (moves, no copy).
            std::mem::swap(&mut w.cost, &mut seg.costs[t]);
            self.st.costs(self.chat.row(i), &mut w.cost);
            self.step(i, w, &mut seg.vals[t]);
            std::mem::swap(&mut w.cost, &mut seg.costs[t]);
        }
    }

    /// `rows` in this pass's order.
    fn order(&self, rows: Range<usize>) -> Box<dyn Iterator<Item = usize>> {
        if self.forward {
            Box::new(rows)
        } else {
            Box::new(rows.rev())
        }
    }
}

/// [`sweep`] with the row steps on `isa` and segments of `segment` rows.
///
/// Phase 1 runs the forward pass over the top half of the rows on one thread and the backward
/// pass over the bottom half on the other, each keeping a [`Checkpoint`] at the start of every
/// [`SEGMENT`] of its half that holds a scored row. Phase 2 continues both passes into the
/// other half, a segment at a time: the other pass's rows of the segment are computed again
/// from its checkpoint into a [`Segment`] (with their costs, which the continuing pass then
/// uses), and each scored row is read out where its own values meet them. Against keeping
/// every scored row of phase 1 (4·D bytes a row, 516 MB at 5,392 x 30,790) this costs one more
/// row step per row and no more transposes, and the memory is a checkpoint per segment.
fn sweep_on<R: Send>(
    isa: Isa,
    segment: usize,
    chat: &Matrix,
    graph: &GraphParams,
    discount: f64,
    scored: &[bool],
    read: impl Fn(usize, &RowView<'_>) -> R + Sync,
) -> Vec<(usize, R)> {
    let (q, d) = (chat.rows(), chat.cols());
    if q == 0 || d == 0 {
        return Vec::new();
    }
    let lay = Layout::new(d);
    let st = Steps {
        g: Graph {
            k: graph.fan_out,
            horizontal: graph.horizontal,
            w: graph.hidden_cost as f32,
            g: discount as f32,
            lay,
        },
        isa,
    };
    let forward = Pass {
        st: &st,
        chat,
        forward: true,
    };
    let backward = Pass {
        st: &st,
        chat,
        forward: false,
    };
    let mid = q / 2;
    let segments = |rows: Range<usize>| -> Vec<Range<usize>> {
        let end = rows.end;
        rows.step_by(segment.max(1))
            .map(|a| a..(a + segment.max(1)).min(end))
            .collect()
    };
    let (top, bottom) = (segments(0..mid), segments(mid..q));

    // Phase 1: the forward pass over the top half, the backward pass over the bottom half.
    let ((mut fw, mut fcur, f_marks), (mut bw, mut bcur, b_marks)) = rayon::join(
        || forward.first_half(&top, scored),
        || backward.first_half(&bottom, scored),
    );

    // Phase 2: each pass continues into the other half, meeting the other pass's rows of each
    // segment computed again.
    let (mut upper, mut lower) = rayon::join(
        || {
            let half = Half {
                segments: &bottom,
                marks: &b_marks,
            };
            forward.meet(&backward, half, &mut fw, &mut fcur, scored, &read)
        },
        || {
            let half = Half {
                segments: &top,
                marks: &f_marks,
            };
            backward.meet(&forward, half, &mut bw, &mut bcur, scored, &read)
        },
    );
    lower.reverse();
    lower.append(&mut upper);
    lower
}

/// The half of the rows a pass continues into in phase 2: its segments (in row order) and
/// the other pass's checkpoint before each (`None`: none needed, or no scored row there).
struct Half<'a> {
    segments: &'a [Range<usize>],
    marks: &'a [Option<Checkpoint>],
}

impl Pass<'_> {
    /// Phase 1 of this pass: its half of the rows, `segments` (in row order), walked in its
    /// order. Returns its state after them and, for each segment with a scored row, a
    /// checkpoint of its state before the segment (forward: `M` of the row before it;
    /// backward: `A` of the row after it), none at the source or the sink.
    fn first_half(
        &self,
        segments: &[Range<usize>],
        scored: &[bool],
    ) -> (Work, RowValues, Vec<Option<Checkpoint>>) {
        let lay = self.st.g.lay;
        let (mut w, mut cur) = (Work::new(&lay), RowValues::new(&lay));
        let mut marks: Vec<Option<Checkpoint>> = segments.iter().map(|_| None).collect();
        for k in self.order(0..segments.len()) {
            let r = segments[k].clone();
            let at_an_end = if self.forward {
                r.start == 0
            } else {
                r.end == self.chat.rows()
            };
            if !at_an_end && scored[r.clone()].contains(&true) {
                marks[k] = Some(w.checkpoint());
            }
            self.run(r, &mut w, &mut cur);
        }
        (w, cur, marks)
    }

    /// Phase 2 of this pass: goes on from `w`, `cur` through `half`'s segments in this pass's
    /// order. A segment with a scored row is first computed again by `other` from its
    /// checkpoint, with its costs (which this pass's steps then use); every scored row is read
    /// out where the two passes' values meet. Returns the readings in this pass's order.
    fn meet<R>(
        &self,
        other: &Pass<'_>,
        half: Half<'_>,
        w: &mut Work,
        cur: &mut RowValues,
        scored: &[bool],
        read: &impl Fn(usize, &RowView<'_>) -> R,
    ) -> Vec<(usize, R)> {
        let lay = self.st.g.lay;
        let len = half.segments.iter().map(|r| r.len()).max().unwrap_or(1);
        let (mut again, mut seg) = (Work::new(&lay), Segment::new(&lay, len));
        let mut out = Vec::new();
        for k in self.order(0..half.segments.len()) {
            let r = half.segments[k].clone();
            if !scored[r.clone()].contains(&true) {
                self.run(r, w, cur);
                continue;
            }
            if let Some(mark) = &half.marks[k] {
                again.resume(mark);
            }
            other.run_into(r.clone(), &mut again, &mut seg);
            for i in self.order(r.clone()) {
                let t = i - r.start;
                std::mem::swap(&mut w.cost, &mut seg.costs[t]);
                self.step(i, w, cur);
                std::mem::swap(&mut w.cost, &mut seg.costs[t]);
                if scored[i] {
                    let theirs = &seg.vals[t];
                    let (fx, bx) = if self.forward {
                        (&cur.x, &theirs.x)
                    } else {
                        (&theirs.x, &cur.x)
                    };
                    // `min_j FH_i[j] + BH_i[j]` (the best hidden route) is reached at a step of
                    // the other row's `H` (see the module doc).
                    let hidden = self
                        .st
                        .hidden_steps(theirs, other.forward)
                        .iter()
                        .map(|&(j, v)| v + cur.h_at(&lay, j as usize))
                        .fold(f32::INFINITY, min);
                    let view = RowView {
                        lay,
                        fx,
                        bx,
                        hidden,
                    };
                    out.push((i, read(i, &view)));
                }
            }
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// Every value a reader can see of every row: `m(x_ij)` of every column, the best route
    /// outside a band and the best hidden route.
    fn everything(isa: Isa, chat: &Matrix, gp: &GraphParams, g: f64) -> Vec<(usize, Vec<u32>)> {
        everything_of(isa, SEGMENT, chat, gp, g, &vec![true; chat.rows()])
    }

    /// [`everything`] of the rows with `scored[i]` only (segments without one are not
    /// computed again), with segments of `segment` rows.
    fn everything_of(
        isa: Isa,
        segment: usize,
        chat: &Matrix,
        gp: &GraphParams,
        g: f64,
        scored: &[bool],
    ) -> Vec<(usize, Vec<u32>)> {
        sweep_on(isa, segment, chat, gp, g, scored, |i, view| {
            let d = view.lay.d;
            let mut bits: Vec<u32> = (0..d).map(|j| view.through(j).to_bits()).collect();
            bits.push(view.best_outside(i % d, (i + 2) % d).to_bits());
            bits.push(view.hidden.to_bits());
            bits
        })
    }

    #[test]
    fn every_instruction_set_gives_the_same_values() {
        let mut state = 0x9e37_79b9_7f4a_7c15u64;
        for (q, d, k, horizontal) in [
            (37, 203, 4, true),
            (20, 1000, 9, true),
            (9, 61, 3, false),
            (1, 17, 2, true),
            (12, 5, 8, true),
        ] {
            let chat = super::super::discounted::plain::noise_matrix(q, d, &mut state);
            let gp = GraphParams {
                fan_out: k,
                horizontal,
                hidden_cost: 1.2,
            };
            let portable = everything(Isa::Portable, &chat, &gp, 5.0 / 6.0);
            let detected = everything(Isa::detect(), &chat, &gp, 5.0 / 6.0);
            assert_eq!(portable.len(), q);
            assert_eq!(
                portable, detected,
                "{q}x{d}, K = {k}, horizontal {horizontal}"
            );
        }
    }

    /// `FX`, `FH`, `BX`, `BH` of every row in plain `f32`, column by column in natural order:
    /// every value from the same operations as the lanes (the window minimum, then the factor
    /// `g`; the horizontal scans), so chunking, fix-ups and padding must not change a bit.
    fn plain_f32(chat: &Matrix, gp: &GraphParams, g: f64) -> Vec<[Vec<f32>; 4]> {
        let (q, d) = (chat.rows(), chat.cols());
        let (k, w, g) = (gp.fan_out, gp.hidden_cost as f32, g as f32);
        let cost = |i: usize| -> Vec<f32> {
            let c = |v: f32| if v > 0.0 { 1.0 / v } else { f32::INFINITY };
            chat.row(i).iter().map(|&v| c(v)).collect()
        };
        let lowest = |v: &[f32]| v.iter().copied().fold(f32::INFINITY, f32::min);
        let mut fwd: Vec<(Vec<f32>, Vec<f32>)> = Vec::new();
        for i in 0..q {
            let c = cost(i);
            let base: Vec<f32> = match fwd.last() {
                None => vec![0.0; d],
                Some((x, h)) => {
                    let m: Vec<f32> = x.iter().zip(h).map(|(&a, &b)| a.min(b)).collect();
                    (0..d)
                        .map(|j| g * lowest(&m[j.saturating_sub(k)..=j]))
                        .collect()
                }
            };
            let (mut x, mut h) = (vec![0.0; d], vec![0.0; d]);
            for j in 0..d {
                x[j] = c[j] + base[j];
                h[j] = base[j] + w;
                if gp.horizontal && j > 0 {
                    x[j] = c[j] + base[j].min(x[j - 1]);
                    h[j] = h[j].min(h[j - 1]);
                }
            }
            fwd.push((x, h));
        }
        let mut bwd: Vec<(Vec<f32>, Vec<f32>)> = vec![(Vec::new(), Vec::new()); q];
        for i in (0..q).rev() {
            let succ: Vec<f32> = if i + 1 == q {
                vec![0.0; d]
            } else {
                let (cn, (nx, nh)) = (cost(i + 1), &bwd[i + 1]);
                let a: Vec<f32> = (0..d).map(|j| (cn[j] + nx[j]).min(w + nh[j])).collect();
                (0..d)
                    .map(|j| g * lowest(&a[j..=(j + k).min(d - 1)]))
                    .collect()
            };
            let c = cost(i);
            let (mut x, mut h) = (succ.clone(), succ.clone());
            if gp.horizontal {
                for j in (0..d.saturating_sub(1)).rev() {
                    x[j] = succ[j].min(c[j + 1] + x[j + 1]);
                    h[j] = succ[j].min(h[j + 1]);
                }
            }
            bwd[i] = (x, h);
        }
        fwd.into_iter()
            .zip(bwd)
            .map(|((fx, fh), (bx, bh))| [fx, fh, bx, bh])
            .collect()
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(64))]
        /// The lane steps (window minima across chunk borders, chunk fix-ups, padding,
        /// windows longer than a chunk) against the plain `f32` passes, bit for bit.
        #[test]
        fn the_lanes_match_a_plain_f32_pass_bit_for_bit(
            q in 1usize..40, d in 1usize..120, k in 0usize..20, horizontal: bool,
            w in 0.3f64..2.5, g in 0.3f64..0.95, seed: u64, mask: u64, segment in 1usize..6,
        ) {
            let mut state = seed | 1;
            let chat = super::super::discounted::plain::noise_matrix(q, d, &mut state);
            let gp = GraphParams { fan_out: k, horizontal, hidden_cost: w };
            let plain: Vec<(usize, Vec<u32>)> = plain_f32(&chat, &gp, g)
                .into_iter()
                .enumerate()
                .map(|(i, [fx, fh, bx, bh])| {
                    let through: Vec<f32> = fx.iter().zip(&bx).map(|(&a, &b)| a + b).collect();
                    let (lo, hi) = (i % d, (i + 2) % d);
                    let outside = (0..d)
                        .filter(|j| !(lo..=hi).contains(j))
                        .map(|j| through[j])
                        .fold(f32::INFINITY, f32::min);
                    let hidden = fh.iter().zip(&bh).map(|(&a, &b)| a + b).fold(f32::INFINITY, f32::min);
                    let mut bits: Vec<u32> = through.iter().map(|v| v.to_bits()).collect();
                    bits.push(outside.to_bits());
                    bits.push(hidden.to_bits());
                    (i, bits)
                })
                .collect();
            for isa in [Isa::Portable, Isa::detect()] {
                prop_assert_eq!(&everything(isa, &chat, &gp, g), &plain, "{:?}", isa);
                // Short segments (several a half, checkpoints, a short last one) and some rows
                // not scored (segments without one skipped, on either side of the middle).
                let all = vec![true; q];
                prop_assert_eq!(&everything_of(isa, segment, &chat, &gp, g, &all), &plain, "{:?}", isa);
                let scored: Vec<bool> = (0..q).map(|i| mask >> i & 1 == 1).collect();
                let some: Vec<(usize, Vec<u32>)> =
                    plain.iter().filter(|(i, _)| scored[*i]).cloned().collect();
                prop_assert_eq!(
                    &everything_of(isa, segment, &chat, &gp, g, &scored), &some, "{:?}", isa
                );
            }
        }
    }
}
