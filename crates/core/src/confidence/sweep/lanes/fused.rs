//! The row steps of [`super`] in one pass over the row, for the common graph: horizontal edges
//! and a fan-out `K` of at most [`MAX_K`], shorter than a chunk.
//!
//! The flat row steps of [`super::Graph`] make `K + 6` passes over a row (`K` shifted minima,
//! the factor `g`, the scan, the carry, `M`): each is a streaming element-wise loop, but the row
//! (123 KB for 30,790 columns) comes from L2 every time, and the profile showed the steps at
//! about 30 cycles per layout row where the scan's own dependency chain (`min` then `add`) needs
//! five. Here one loop per row does it all: the window minimum reads the `K + 1` rows of the
//! previous `M` again from L1 (the loop writes none of them), then the factor, both scans, and
//! the value the next row step reads (`M` forward, `A` = the best way on from a node
//! backward), written to the other of two buffers.
//!
//! **Lazy carries.** A chunk's hidden values start from a `+inf` carry; the true carry (the
//! running minimum of the chunks before) is only known at the end of the row and is the same
//! for every value of the chunk. Instead of a pass that applies it, it is kept beside the row
//! ([`RowValues::carry`], [`Work::carry`]) and applied where a value is read: a minimum is
//! exact, and `W + min(h, c) = min(W + h, W + c)` exactly (rounding is monotone), so every
//! value is the one the flat steps compute.
//!
//! The values are the flat steps' bit for bit: the same element-wise operations in the same
//! order per value, checked by `the_lanes_match_a_plain_f32_pass_bit_for_bit`, which covers
//! both kinds of row step.

use super::{min, Graph, RowValues, Work, LANES};

/// The largest fan-out with a one-pass row step; larger ones take the flat passes.
pub(super) const MAX_K: usize = 8;

/// Whether the one-pass steps apply to `g`.
#[inline(always)]
pub(super) fn applies(g: &Graph) -> bool {
    g.horizontal && g.k <= MAX_K && g.k < g.lay.n
}

/// Calls `$f::<K>($args)` for the run-time fan-out `$k` (at most [`MAX_K`]).
macro_rules! with_k {
    ($k:expr, $f:ident($($arg:expr),*)) => {
        match $k {
            0 => $f::<0>($($arg),*),
            1 => $f::<1>($($arg),*),
            2 => $f::<2>($($arg),*),
            3 => $f::<3>($($arg),*),
            4 => $f::<4>($($arg),*),
            5 => $f::<5>($($arg),*),
            6 => $f::<6>($($arg),*),
            7 => $f::<7>($($arg),*),
            _ => $f::<8>($($arg),*),
        }
    };
}

/// The forward row step of [`Graph::forward_body`] with a previous row, in one pass (see the
/// module doc). Expects `w.m`, `w.carry` = `M` of row `i-1` and `w.cost` = row `i`'s costs;
/// leaves `X`, `H` of row `i` in `out` and its `M` in `w.m`, `w.carry`.
#[inline(always)]
pub(super) fn forward(g: &Graph, w: &mut Work, out: &mut RowValues) {
    debug_assert!(applies(g));
    with_k!(g.k, forward_k(g, w, out))
}

/// The backward row step of [`Graph::backward_body`] after a row `i+1`, in one pass. Expects
/// `w.m`, `w.carry` = `A` of row `i+1` and `w.cost` = row `i`'s costs; leaves `BX`, `BH` of
/// row `i` in `out` and its `A` in `w.m`, `w.carry`.
#[inline(always)]
pub(super) fn backward(g: &Graph, w: &mut Work, out: &mut RowValues) {
    debug_assert!(applies(g));
    with_k!(g.k, backward_k(g, w, out))
}

/// `min(a, b)` lane by lane.
#[inline(always)]
fn vmin(a: [f32; LANES], b: &[f32; LANES]) -> [f32; LANES] {
    std::array::from_fn(|l| min(a[l], b[l]))
}

/// `v` with lane `l` taken from lane `l - 1` (lane 0: `+inf`).
#[inline(always)]
fn from_left(v: &[f32; LANES]) -> [f32; LANES] {
    std::array::from_fn(|l| if l == 0 { f32::INFINITY } else { v[l - 1] })
}

/// `v` with lane `l` taken from lane `l + 1` (the last lane: `+inf`).
#[inline(always)]
fn from_right(v: &[f32; LANES]) -> [f32; LANES] {
    std::array::from_fn(|l| v.get(l + 1).copied().unwrap_or(f32::INFINITY))
}

/// One forward scan step at a layout row from the window minimum `b` (carry applied): `X = c +
/// min(g·b, X_left)`, `H = min(g·b + W, H_left)`; returns `(X, H, min(X, H))`.
#[inline(always)]
fn forward_step(
    b: [f32; LANES],
    c: &[f32; LANES],
    gs: f32,
    wv: f32,
    lx: &mut [f32; LANES],
    lh: &mut [f32; LANES],
) -> ([f32; LANES], [f32; LANES], [f32; LANES]) {
    for l in 0..LANES {
        let bl = b[l] * gs;
        lx[l] = c[l] + min(bl, lx[l]);
        lh[l] = min(bl + wv, lh[l]);
    }
    (*lx, *lh, vmin(*lx, lh))
}

/// One backward scan step from the window minimum `s` of `A` (carry applied): `BX = min(g·s,
/// Y_right)` with `Y = c + BX`, `BH = min(g·s, BH_right)`; returns `(BX, BH, A)` with this
/// row's `A = min(c + BX, W + BH)`.
#[inline(always)]
fn backward_step(
    s: [f32; LANES],
    c: &[f32; LANES],
    gs: f32,
    wv: f32,
    ly: &mut [f32; LANES],
    lh: &mut [f32; LANES],
) -> ([f32; LANES], [f32; LANES], [f32; LANES]) {
    let mut x = [0.0; LANES];
    let mut a = [0.0; LANES];
    for l in 0..LANES {
        let sl = s[l] * gs;
        x[l] = min(sl, ly[l]);
        ly[l] = c[l] + x[l];
        lh[l] = min(sl, lh[l]);
        a[l] = min(ly[l], wv + lh[l]);
    }
    (x, *lh, a)
}

#[inline(always)]
fn forward_k<const K: usize>(g: &Graph, w: &mut Work, out: &mut RowValues) {
    let n = g.lay.n;
    let (gs, wv) = (g.g, g.w);
    let Work {
        cost,
        m: prev,
        m_next: next,
        carry,
        ..
    } = w;
    let (prev, cost) = (&*prev, &*cost);
    // `M` of the previous row is `min(prev, carry)` lane by lane: the chunk before reads
    // through its own lane's carry.
    let (own, left) = (*carry, from_left(carry));
    let (mut lx, mut lh) = ([f32::INFINITY; LANES], [f32::INFINITY; LANES]);
    // Rows t < K: the window also holds the last rows of the chunk before (none for chunk 0).
    for t in 0..K {
        let mut b = own;
        for row in &prev[..=t] {
            b = vmin(b, row);
        }
        let mut before = left;
        for row in &prev[n + t - K..] {
            before = vmin(before, &from_left(row));
        }
        b = vmin(b, &before);
        (out.x[t], out.h[t], next[t]) = forward_step(b, &cost[t], gs, wv, &mut lx, &mut lh);
    }
    // The other rows: the window is rows t-K ..= t of the chunk.
    let rows = prev
        .windows(K + 1)
        .zip(&cost[K..])
        .zip(out.x[K..].iter_mut().zip(out.h[K..].iter_mut()))
        .zip(next[K..].iter_mut());
    for (((win, c), (x, h)), m) in rows {
        let mut b = own;
        for row in win {
            b = vmin(b, row);
        }
        (*x, *h, *m) = forward_step(b, c, gs, wv, &mut lx, &mut lh);
    }
    // The factor-`g` window minimum of column `(t, l)`, for the few values the fix-up walks.
    let base = |t: usize, l: usize| {
        let mut v = own[l];
        for row in &prev[t.saturating_sub(K)..=t] {
            v = min(v, row[l]);
        }
        if t < K && l > 0 {
            v = min(v, left[l]);
            for row in &prev[n + t - K..] {
                v = min(v, row[l - 1]);
            }
        }
        v * gs
    };
    // Fix up chunk l from the true carry of chunk l-1, as the flat step does; the hidden
    // carry is kept, not applied.
    let mut carry_h = [f32::INFINITY; LANES];
    for l in 1..LANES {
        let mut left_x = out.x[n - 1][l - 1];
        for t in 0..n {
            let v = cost[t][l] + min(base(t, l), left_x);
            if v == out.x[t][l] {
                break;
            }
            out.x[t][l] = v;
            next[t][l] = min(v, out.h[t][l]);
            left_x = v;
        }
        carry_h[l] = min(carry_h[l - 1], out.h[n - 1][l - 1]);
    }
    std::mem::swap(&mut w.m, &mut w.m_next);
    out.carry = carry_h;
    w.carry = carry_h;
}

#[inline(always)]
fn backward_k<const K: usize>(g: &Graph, w: &mut Work, out: &mut RowValues) {
    let n = g.lay.n;
    let (gs, wv) = (g.g, g.w);
    let Work {
        cost,
        m: after,
        m_next: next,
        carry,
        ..
    } = w;
    let (after, cost) = (&*after, &*cost);
    // `A` of row i+1 is `min(after, carry)` lane by lane.
    let (own, right) = (*carry, from_right(carry));
    let (mut ly, mut lh) = ([f32::INFINITY; LANES], [f32::INFINITY; LANES]);
    // Rows t > n-1-K: the window also holds the first rows of the chunk after (none after the
    // last chunk). Padding columns need no mask: their costs are `+inf`, their hidden values
    // and carries too (nothing lies after them), and so is every `A` the window of one sees.
    for t in (n - K..n).rev() {
        let mut s = own;
        for row in &after[t..] {
            s = vmin(s, row);
        }
        let mut beyond = right;
        for row in &after[..=t + K - n] {
            beyond = vmin(beyond, &from_right(row));
        }
        s = vmin(s, &beyond);
        (out.x[t], out.h[t], next[t]) = backward_step(s, &cost[t], gs, wv, &mut ly, &mut lh);
    }
    let rows = after
        .windows(K + 1)
        .zip(cost)
        .zip(out.x.iter_mut().zip(out.h.iter_mut()))
        .zip(next.iter_mut());
    for (((win, c), (x, h)), a) in rows.rev() {
        let mut s = own;
        for row in win {
            s = vmin(s, row);
        }
        (*x, *h, *a) = backward_step(s, c, gs, wv, &mut ly, &mut lh);
    }
    // The factor-`g` window minimum of `A` at column `(t, l)`, for the fix-up.
    let succ = |t: usize, l: usize| {
        let mut v = own[l];
        for row in &after[t..=(t + K).min(n - 1)] {
            v = min(v, row[l]);
        }
        if t + K >= n && l + 1 < LANES {
            v = min(v, right[l]);
            for row in &after[..=t + K - n] {
                v = min(v, row[l + 1]);
            }
        }
        v * gs
    };
    let mut carry_h = [f32::INFINITY; LANES];
    for l in (0..LANES - 1).rev() {
        let mut right_y = cost[0][l + 1] + out.x[0][l + 1];
        for t in (0..n).rev() {
            let v = min(succ(t, l), right_y);
            if v == out.x[t][l] {
                break;
            }
            out.x[t][l] = v;
            right_y = cost[t][l] + v;
            next[t][l] = min(right_y, wv + out.h[t][l]);
        }
        carry_h[l] = min(carry_h[l + 1], out.h[0][l + 1]);
    }
    std::mem::swap(&mut w.m, &mut w.m_next);
    out.carry = carry_h;
    w.carry = std::array::from_fn(|l| wv + carry_h[l]);
}
