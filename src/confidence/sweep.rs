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
//!   minimum) takes `min(carry, local)`.
//! * **AVX2.** The row steps are compiled again for AVX2 and picked at run time ([`Isa`]): a
//!   lane row is then one register instead of two SSE2 ones. Same operations, same values.
//! * **`f32`.** Values are `f32` (node costs `1/ĉ` of the `f32` matrix), half the memory
//!   traffic and twice the lanes of `f64`. The discount keeps sums short (a route's weight
//!   `Σ g^|t-i|` is at most `(1+g)/(1-g)`), so rounding stays at a few `f32` ulps of the result;
//!   the property tests compare with the `f64` brute force at a relative `1e-5`. The solver's
//!   path and costs stay `f64`: only the confidence, a ranking, is `f32`.
//! * **Meeting in the middle, nothing recomputed.** Phase 1 runs the forward pass over the top
//!   half of the rows on one thread while the backward pass runs over the bottom half on the
//!   other, each keeping its values of the rows to score. Phase 2 continues both passes into
//!   the other half, where each row's own values meet the stored ones of the other pass. One
//!   forward and one backward pass in total, on two threads; memory: the `X` values of the
//!   scored rows (`4·D` bytes a row; 664 MB for every row of a 5,392 x 30,790 matrix) and, for
//!   the hidden nodes, only the steps of `H` (with horizontal edges `FH_i` is non-increasing
//!   and `BH_i` non-decreasing in `j`, so `min_j FH_i[j] + BH_i[j]` is reached at a step of the
//!   stored one). Stored rows are freed as soon as they are scored.

// The readout's lane code indexes several `[f32; LANES]` rows by the same index.
#![allow(clippy::needless_range_loop)]

mod lanes;

use super::GraphParams;
use crate::Matrix;
use lanes::{min, Graph, Isa, Lanes, Layout, RowValues, Steps, Work, LANES};

/// A row kept by one pass for the other.
struct Stored {
    x: Lanes,
    hidden: Vec<(u32, f32)>,
}

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
    sweep_on(Isa::detect(), chat, graph, discount, scored, read)
}

/// [`sweep`] with the row steps on `isa`.
fn sweep_on<R: Send>(
    isa: Isa,
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
    // A fresh row for a pass to write its next `X` into, so that a row to keep is moved, not
    // copied: zeroed memory straight from the allocator (every value is written before read).
    let fresh = || vec![[0.0f32; LANES]; lay.n];
    let mid = q / 2;
    // Pass state carried from phase 1 to phase 2.
    let mut fw = Work::new(&lay);
    let mut fcur = RowValues::new(&lay);
    let mut bw = Work::new(&lay);
    let mut bcur = RowValues::new(&lay);
    let mut bnext = RowValues::new(&lay);

    // Phase 1: forward over rows 0..mid, backward over rows q-1 down to mid.
    let (top, bottom) = rayon::join(
        || {
            let mut kept: Vec<Option<Stored>> = (0..mid).map(|_| None).collect();
            for i in 0..mid {
                st.costs(chat.row(i), &mut fw.cost);
                st.forward(i > 0, &mut fw, &mut fcur);
                if scored[i] {
                    // The next row's forward step reads `M` (in `fw.m`), not `X`.
                    kept[i] = Some(Stored {
                        hidden: st.hidden_steps(&fcur, true),
                        x: std::mem::replace(&mut fcur.x, fresh()),
                    });
                }
            }
            kept
        },
        || {
            let mut kept: Vec<Option<Stored>> = (mid..q).map(|_| None).collect();
            for i in (mid..q).rev() {
                if i + 1 < q {
                    std::mem::swap(&mut bw.cost, &mut bw.cost_next);
                }
                st.costs(chat.row(i), &mut bw.cost);
                let next = (i + 1 < q).then_some(&bnext);
                st.backward(next, &mut bw, &mut bcur);
                // Row i+1's values (in `bnext`) have been read for the last time: keep them.
                if i + 1 < q && scored[i + 1] {
                    kept[i + 1 - mid] = Some(Stored {
                        hidden: st.hidden_steps(&bnext, false),
                        x: std::mem::replace(&mut bnext.x, fresh()),
                    });
                }
                std::mem::swap(&mut bcur, &mut bnext);
            }
            // Row `mid` goes on into phase 2 (its values start the backward pass there).
            if mid < q && scored[mid] {
                kept[0] = Some(Stored {
                    hidden: st.hidden_steps(&bnext, false),
                    x: bnext.x.clone(),
                });
            }
            kept
        },
    );

    // Phase 2: each pass continues into the other half and meets the stored rows there.
    let combine = |stored: &Stored, own: &RowValues| {
        stored
            .hidden
            .iter()
            .map(|&(j, v)| v + own.h_at(&lay, j as usize))
            .fold(f32::INFINITY, min)
    };
    let (mut upper, mut lower) = rayon::join(
        || {
            let mut bottom = bottom;
            let mut out = Vec::new();
            for i in mid..q {
                st.costs(chat.row(i), &mut fw.cost);
                st.forward(i > 0, &mut fw, &mut fcur);
                if let Some(b) = bottom[i - mid].take() {
                    let view = RowView {
                        lay,
                        fx: &fcur.x,
                        bx: &b.x,
                        hidden: combine(&b, &fcur),
                    };
                    out.push((i, read(i, &view)));
                }
            }
            out
        },
        || {
            let mut top = top;
            let mut out = Vec::new();
            for i in (0..mid).rev() {
                // The first row here continues from row `mid` (`mid < q` always: `q >= 1`).
                std::mem::swap(&mut bw.cost, &mut bw.cost_next);
                st.costs(chat.row(i), &mut bw.cost);
                st.backward(Some(&bnext), &mut bw, &mut bcur);
                std::mem::swap(&mut bcur, &mut bnext);
                if let Some(f) = top[i].take() {
                    let view = RowView {
                        lay,
                        fx: &f.x,
                        bx: &bnext.x,
                        hidden: combine(&f, &bnext),
                    };
                    out.push((i, read(i, &view)));
                }
            }
            out
        },
    );
    lower.reverse();
    lower.append(&mut upper);
    lower
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// Every value a reader can see of every row: `m(x_ij)` of every column, the best route
    /// outside a band and the best hidden route.
    fn everything(isa: Isa, chat: &Matrix, gp: &GraphParams, g: f64) -> Vec<(usize, Vec<u32>)> {
        everything_of(isa, chat, gp, g, &vec![true; chat.rows()])
    }

    /// [`everything`] of the rows with `scored[i]` only (the others are not kept by either
    /// pass).
    fn everything_of(
        isa: Isa,
        chat: &Matrix,
        gp: &GraphParams,
        g: f64,
        scored: &[bool],
    ) -> Vec<(usize, Vec<u32>)> {
        sweep_on(isa, chat, gp, g, scored, |i, view| {
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
            q in 1usize..16, d in 1usize..120, k in 0usize..20, horizontal: bool,
            w in 0.3f64..2.5, g in 0.3f64..0.95, seed: u64, mask: u16,
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
                // Some rows not scored (not kept, and on either side of the middle row).
                let scored: Vec<bool> = (0..q).map(|i| mask >> i & 1 == 1).collect();
                let some: Vec<(usize, Vec<u32>)> =
                    plain.iter().filter(|(i, _)| scored[*i]).cloned().collect();
                prop_assert_eq!(&everything_of(isa, &chat, &gp, g, &scored), &some, "{:?}", isa);
            }
        }
    }
}
