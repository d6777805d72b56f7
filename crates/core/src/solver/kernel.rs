//! The forward row step of the `F = 1` dynamic programme, written for speed and exactness.
//!
//! Row `i` from row `i-1` (notation of `shortest_path.rs`): `base_j = min M_{i-1}[j-K..=j]`,
//! `X[j] = min(base_j + c_j, X[j-1] + c_j)`, `H[j] = min(base_j + W, H[j-1])`, `M = min(X, H)`.
//! A row is processed in L1-sized blocks of columns, each in four passes:
//!
//! 1. node costs `c_j = 1/ĉ_ij` (`+inf` when unusable or blocked), vectorised;
//! 2. the window minimum `base_j` and its offset ([`crate::window::trailing_min_offsets`]: `K`
//!    shifted compare-and-select passes for small `K`, a monotone deque otherwise; the latest
//!    column on ties), vectorised for small `K`;
//! 3. the horizontal recurrences, the only serial part: the block is cut into [`LANES`] chunks
//!    that are scanned *interleaved* with a `+inf` carry-in (independent dependency chains, so the
//!    core overlaps them), then each chunk is fixed up from the true carry-out of the chunk to
//!    its left. For `X` the fix-up walks while the carried value changes the result; once a
//!    recomputed value equals the local one every later value is equal too (same inputs, same
//!    operations), so the walk stops. `H` is a running minimum, so its true value is simply
//!    `min(carry, H_local)` and is applied in pass 4;
//! 4. `H` with the carry, `M`, and the packed back-pointer of each cell, vectorised.
//!
//! Exactness: every value is produced by the same floating-point operations as the plain
//! left-to-right scan (`left + c` against `base + c`, strict `<`), so values, pointers and ties
//! are bit-identical to it; `shortest_path.rs` tests this against a plain scan. Whether a step was
//! horizontal is recovered from the values: `X != base + c` exactly when `X` came from the left.
//!
//! Back-pointers: one [`BackPtr`] per cell (not per node): the window offset (shared by `x_ij`
//! and `h_ij`, which have the same forward predecessors), whether `M` of the cell is the hidden
//! node (what a successor row needs to know), and the "came horizontally" flag of each node.

use super::graph::{match_cost, Blocked};
use crate::window::{trailing_min_offsets, trailing_min_value, MonoDeque, Scan};

/// Independent chunks scanned together in pass 3.
pub(crate) const LANES: usize = 8;

/// Columns per block (the block's five 8-byte buffers, 40 KiB, stay in the 48 KiB L1).
pub(crate) const BLOCK: usize = 1024;

/// A compact per-cell back-pointer (see the module doc).
pub(crate) trait BackPtr: Copy + Default + Send + Sync {
    /// Largest window offset that fits.
    const MAX_OFFSET: usize;
    /// Packs the window offset (`<= MAX_OFFSET`), whether `M` of the cell is hidden, and
    /// whether `x` / `h` came horizontally.
    fn pack(offset: u64, m_hidden: bool, x_horizontal: bool, h_horizontal: bool) -> Self;
    /// The window offset: the predecessor is `offset` columns left in the previous row.
    fn offset(self) -> usize;
    /// Whether `M` of this cell is the hidden node.
    fn m_hidden(self) -> bool;
    /// Whether `x` of this cell came horizontally.
    fn x_horizontal(self) -> bool;
    /// Whether `h` of this cell came horizontally.
    fn h_horizontal(self) -> bool;
}

macro_rules! back_ptr {
    ($t:ty, $off_bits:expr) => {
        impl BackPtr for $t {
            const MAX_OFFSET: usize = (1 << $off_bits) - 1;
            #[inline]
            fn pack(offset: u64, m_hidden: bool, x_horizontal: bool, h_horizontal: bool) -> Self {
                // Offsets are <= MAX_OFFSET: the truncation keeps them whole.
                (offset as $t)
                    | (<$t>::from(m_hidden) << $off_bits)
                    | (<$t>::from(x_horizontal) << ($off_bits + 1))
                    | (<$t>::from(h_horizontal) << ($off_bits + 2))
            }
            #[inline]
            fn offset(self) -> usize {
                usize::from(self & ((1 << $off_bits) - 1))
            }
            #[inline]
            fn m_hidden(self) -> bool {
                (self >> $off_bits) & 1 != 0
            }
            #[inline]
            fn x_horizontal(self) -> bool {
                (self >> ($off_bits + 1)) & 1 != 0
            }
            #[inline]
            fn h_horizontal(self) -> bool {
                (self >> ($off_bits + 2)) & 1 != 0
            }
        }
    };
}

back_ptr!(u8, 4);
back_ptr!(u16, 12);

/// Per-block work buffers, reused from block to block and row to row.
#[derive(Default)]
pub(crate) struct Scratch {
    dq: MonoDeque,
    cost: Vec<f64>,
    base: Vec<f64>,
    /// Window offsets, 64-bit like the values so the window pass selects them with the
    /// compare's bit mask and vectorises.
    off: Vec<u64>,
    x: Vec<f64>,
    h: Vec<f64>,
}

/// What one row step reads: the graph and the rows involved.
#[derive(Clone, Copy)]
pub(crate) struct RowCtx<'a> {
    /// `ĉ` of this row.
    pub row: &'a [f32],
    /// This row's index in `blocked`.
    pub i: usize,
    /// Matching nodes that must not be used.
    pub blocked: Option<&'a Blocked>,
    /// `M` of the previous row (`None` for the first row: every node starts from the source).
    pub prev: Option<&'a [f64]>,
    /// Fan-out `K`.
    pub k: usize,
    /// Horizontal edges on or off.
    pub horizontal: bool,
    /// Hidden cost `W`.
    pub w: f64,
    /// Window strategy.
    pub window: Scan,
    /// Columns per block (tests use tiny blocks to exercise chunk borders).
    pub block: usize,
}

/// Where a row step writes, for the columns `[lo, lo + len)` of the row (slices start at `lo`).
pub(crate) enum Dest<'a, P> {
    /// `M` and the back-pointers (the path search).
    Path { m: &'a mut [f64], ptr: &'a mut [P] },
    /// `M`, `X` and `H` (the min-marginals).
    Values {
        m: &'a mut [f64],
        x: &'a mut [f64],
        h: &'a mut [f64],
    },
}

impl<'a, P> Dest<'a, P> {
    /// Number of columns.
    pub(crate) fn len(&self) -> usize {
        match self {
            Dest::Path { m, .. } | Dest::Values { m, .. } => m.len(),
        }
    }

    /// The columns `[a, b)` (relative to this destination).
    fn sub(&mut self, a: usize, b: usize) -> Dest<'_, P> {
        match self {
            Dest::Path { m, ptr } => Dest::Path {
                m: &mut m[a..b],
                ptr: &mut ptr[a..b],
            },
            Dest::Values { m, x, h } => Dest::Values {
                m: &mut m[a..b],
                x: &mut x[a..b],
                h: &mut h[a..b],
            },
        }
    }

    /// Splits at column `mid` (relative).
    pub(crate) fn split_at(self, mid: usize) -> (Dest<'a, P>, Dest<'a, P>) {
        match self {
            Dest::Path { m, ptr } => {
                let (m0, m1) = m.split_at_mut(mid);
                let (p0, p1) = ptr.split_at_mut(mid);
                (Dest::Path { m: m0, ptr: p0 }, Dest::Path { m: m1, ptr: p1 })
            }
            Dest::Values { m, x, h } => {
                let (m0, m1) = m.split_at_mut(mid);
                let (x0, x1) = x.split_at_mut(mid);
                let (h0, h1) = h.split_at_mut(mid);
                (
                    Dest::Values {
                        m: m0,
                        x: x0,
                        h: h0,
                    },
                    Dest::Values {
                        m: m1,
                        x: x1,
                        h: h1,
                    },
                )
            }
        }
    }
}

/// The cost of node `x_ij` for column `j` of `ctx`'s row (`+inf` when unusable or blocked).
#[inline]
pub(crate) fn node_cost(ctx: &RowCtx<'_>, j: usize) -> f64 {
    if ctx.blocked.is_some_and(|b| b.is_blocked(ctx.i, j)) {
        f64::INFINITY
    } else {
        match_cost(ctx.row[j])
    }
}

/// `base_j` alone (the value of the window minimum, no offset), for one column.
#[inline]
pub(crate) fn base_value(ctx: &RowCtx<'_>, j: usize) -> f64 {
    match ctx.prev {
        None => 0.0,
        Some(p) => trailing_min_value(p, j, ctx.k),
    }
}

/// Row step over the columns `[lo, lo + dest.len())` with carry-in `(X, H)` of column `lo - 1`
/// (`+inf` for none); returns the carry-out `(X, H)` of the last column. Exact for any `lo`
/// when the carry is the true one.
pub(crate) fn range_step<P: BackPtr>(
    ctx: &RowCtx<'_>,
    lo: usize,
    dest: &mut Dest<'_, P>,
    carry: (f64, f64),
    s: &mut Scratch,
) -> (f64, f64) {
    let hi = lo + dest.len();
    let block = ctx.block.max(1);
    for v in [&mut s.cost, &mut s.base, &mut s.x, &mut s.h] {
        if v.len() < block {
            v.resize(block, 0.0);
        }
    }
    if s.off.len() < block {
        s.off.resize(block, 0);
    }
    if ctx.window == Scan::Deque {
        if let Some(p) = ctx.prev {
            s.dq.start(p, lo, ctx.k);
        }
    }
    let mut carry = carry;
    for b0 in (lo..hi).step_by(block) {
        let b1 = (b0 + block).min(hi);
        let n = b1 - b0;
        costs(ctx, b0, &mut s.cost[..n]);
        window(ctx, b0, &mut s.base[..n], &mut s.off[..n], &mut s.dq);
        let (cost, base, off) = (&s.cost[..n], &s.base[..n], &s.off[..n]);
        let (xs, hs) = (&mut s.x[..n], &mut s.h[..n]);
        let out = dest.sub(b0 - lo, b1 - lo);
        carry = if ctx.horizontal {
            scan_lanes(ctx.w, cost, base, xs, hs);
            fix_up_and_combine(ctx.w, carry, cost, base, off, xs, hs, out)
        } else {
            for (((x, h), &b), &c) in xs.iter_mut().zip(hs.iter_mut()).zip(base).zip(cost) {
                *x = b + c;
                *h = b + ctx.w;
            }
            combine(ctx.w, f64::INFINITY, cost, base, off, xs, hs, out);
            (f64::INFINITY, f64::INFINITY)
        };
    }
    carry
}

/// Pass 1: node costs of columns `b0 .. b0 + cost.len()`.
fn costs(ctx: &RowCtx<'_>, b0: usize, cost: &mut [f64]) {
    let n = cost.len();
    row_costs(
        &ctx.row[b0..b0 + n],
        ctx.blocked.map(|b| (b, ctx.i, b0)),
        cost,
    );
}

/// `cost[t] = 1/row[t]` (`+inf` when `row[t] <= 0`), and `+inf` for the blocked nodes of
/// `blocked = (set, row i, first column)`. Vectorised; the blocked set costs one word test per
/// 64 columns.
pub(crate) fn row_costs(row: &[f32], blocked: Option<(&Blocked, usize, usize)>, cost: &mut [f64]) {
    for (c, &v) in cost.iter_mut().zip(row) {
        *c = match_cost(v);
    }
    if let Some((b, i, b0)) = blocked {
        b.for_each_in_row(i, b0, b0 + row.len(), |j| cost[j - b0] = f64::INFINITY);
    }
}

/// Pass 2: `base[t] = min M_prev[j-K..=j]` for `j = b0 + t`, `off[t]` = `j` minus the argmin
/// (the latest column on ties, the one rule of [`crate::window`]).
fn window(ctx: &RowCtx<'_>, b0: usize, base: &mut [f64], off: &mut [u64], dq: &mut MonoDeque) {
    match ctx.prev {
        None => {
            base.fill(0.0);
            off.fill(0);
        }
        Some(p) => trailing_min_offsets(p, b0, ctx.k, ctx.window, base, off, dq),
    }
}

/// One step of the horizontal recurrences from the left values `(lx, lh)`.
#[inline(always)]
fn step(w: f64, c: f64, b: f64, lx: f64, lh: f64) -> (f64, f64) {
    let ex = b + c;
    let hx = lx + c;
    let eh = b + w;
    (if hx < ex { hx } else { ex }, if lh < eh { lh } else { eh })
}

/// Plain scan of `X`, `H` from the carry-in `(lx, lh)`.
fn scan_from(
    w: f64,
    (mut lx, mut lh): (f64, f64),
    cost: &[f64],
    base: &[f64],
    xs: &mut [f64],
    hs: &mut [f64],
) {
    for (((&c, &b), x), h) in cost.iter().zip(base).zip(xs.iter_mut()).zip(hs.iter_mut()) {
        (lx, lh) = step(w, c, b, lx, lh);
        *x = lx;
        *h = lh;
    }
}

/// Pass 3a: local scans of [`LANES`] chunks with a `+inf` carry-in, interleaved. Chunk `l` is
/// `[l·len, (l+1)·len)` with `len = n / LANES`; the last chunk also takes the remainder. With
/// fewer than `LANES` columns there is one chunk.
fn scan_lanes(w: f64, cost: &[f64], base: &[f64], xs: &mut [f64], hs: &mut [f64]) {
    let n = cost.len();
    let len = n / LANES;
    let inf = (f64::INFINITY, f64::INFINITY);
    if len == 0 {
        scan_from(w, inf, cost, base, xs, hs);
        return;
    }
    let body = LANES * len;
    let c: [&[f64]; LANES] = std::array::from_fn(|l| &cost[l * len..(l + 1) * len]);
    let b: [&[f64]; LANES] = std::array::from_fn(|l| &base[l * len..(l + 1) * len]);
    let (x_body, x_tail) = xs.split_at_mut(body);
    let (h_body, h_tail) = hs.split_at_mut(body);
    let mut xi = x_body.chunks_exact_mut(len);
    let mut hi = h_body.chunks_exact_mut(len);
    let x: [&mut [f64]; LANES] = std::array::from_fn(|_| xi.next().expect("LANES chunks of len"));
    let h: [&mut [f64]; LANES] = std::array::from_fn(|_| hi.next().expect("LANES chunks of len"));
    let mut lx = [f64::INFINITY; LANES];
    let mut lh = [f64::INFINITY; LANES];
    for t in 0..len {
        for l in 0..LANES {
            let (vx, vh) = step(w, c[l][t], b[l][t], lx[l], lh[l]);
            lx[l] = vx;
            lh[l] = vh;
            x[l][t] = vx;
            h[l][t] = vh;
        }
    }
    let last = (lx[LANES - 1], lh[LANES - 1]);
    scan_from(w, last, &cost[body..], &base[body..], x_tail, h_tail);
}

/// Pass 3b and 4: fixes up each chunk from the true carry of the chunk to its left and
/// writes the block. Returns the block's carry-out.
#[allow(clippy::too_many_arguments)]
fn fix_up_and_combine<P: BackPtr>(
    w: f64,
    (mut cx, mut ch): (f64, f64),
    cost: &[f64],
    base: &[f64],
    off: &[u64],
    xs: &mut [f64],
    hs: &[f64],
    mut dest: Dest<'_, P>,
) -> (f64, f64) {
    let n = cost.len();
    let len = n / LANES;
    let chunks = if len == 0 { 1 } else { LANES };
    for l in 0..chunks {
        let s = l * len;
        let e = if l + 1 == chunks { n } else { s + len };
        // X: walk while the true carry changes the value.
        let mut left = cx;
        for t in s..e {
            let c = cost[t];
            let ex = base[t] + c;
            let hx = left + c;
            let v = if hx < ex { hx } else { ex };
            if v == xs[t] {
                break;
            }
            xs[t] = v;
            left = v;
        }
        combine(
            w,
            ch,
            &cost[s..e],
            &base[s..e],
            &off[s..e],
            &xs[s..e],
            &hs[s..e],
            dest.sub(s, e),
        );
        cx = xs[e - 1];
        let hl = hs[e - 1];
        ch = if ch < hl { ch } else { hl };
    }
    (cx, ch)
}

/// Pass 4 on one chunk: `H = min(carry, H_local)`, `M`, and the pointers or values.
#[allow(clippy::too_many_arguments)]
fn combine<P: BackPtr>(
    w: f64,
    ch: f64,
    cost: &[f64],
    base: &[f64],
    off: &[u64],
    xs: &[f64],
    hs: &[f64],
    dest: Dest<'_, P>,
) {
    let cells = xs.iter().zip(hs).zip(base.iter().zip(cost));
    match dest {
        Dest::Path { m, ptr } => {
            for ((((&x, &hl), (&b, &c)), (mo, po)), &o) in
                cells.zip(m.iter_mut().zip(ptr.iter_mut())).zip(off)
            {
                let h = if ch < hl { ch } else { hl };
                let hidden = h < x;
                *mo = if hidden { h } else { x };
                *po = P::pack(o, hidden, x != b + c, h != b + w);
            }
        }
        Dest::Values { m, x: xo, h: ho } => {
            for (((&x, &hl), _), ((mo, xv), hv)) in
                cells.zip(m.iter_mut().zip(xo.iter_mut()).zip(ho.iter_mut()))
            {
                let h = if ch < hl { ch } else { hl };
                *mo = if h < x { h } else { x };
                *xv = x;
                *hv = h;
            }
        }
    }
}

/// One row of the forward values DP of a standalone run of rows (no back-pointers, nothing
/// blocked): `prev` is `M` of the row before (`None`: a free start, every node reachable at cost
/// 0 plus its own). Writes `X`, `H` and `M`; the same operations as the solver's row step.
#[allow(clippy::too_many_arguments)]
pub(crate) fn forward_values_row(
    row: &[f32],
    prev: Option<&[f64]>,
    k: usize,
    horizontal: bool,
    w: f64,
    (x, h, m): (&mut [f64], &mut [f64], &mut [f64]),
    scratch: &mut Scratch,
) {
    let ctx = RowCtx {
        row,
        i: 0,
        blocked: None,
        prev,
        k,
        horizontal,
        w,
        window: Scan::for_fan_out(k),
        block: BLOCK,
    };
    let inf = (f64::INFINITY, f64::INFINITY);
    range_step::<u8>(&ctx, 0, &mut Dest::Values { m, x, h }, inf, scratch);
}
