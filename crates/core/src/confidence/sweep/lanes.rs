//! The lane kernels of [`super`]: one row step of each pass on a row stored as [`LANES`]
//! transposed chunks, the node costs, and the steps of the hidden values kept for the other
//! pass; compiled for the build's target and again for AVX2, picked at run time ([`Isa`]).
//! The driver (which rows, which thread, what is kept and how rows meet) is [`super`].

// Lane code indexes several `[f32; LANES]` rows (and chunk rows `t`) by the same index;
// iterator chains over four or five zipped rows would hide the recurrences.
#![allow(clippy::needless_range_loop)]

mod fused;

/// Chunks processed together (eight `f32`: one AVX register, two SSE registers). 32 lanes
/// (four AVX registers, shorter scans) measured slower: the transpose of [`costs`] reads 32
/// streams of the matrix row at once.
pub(in crate::confidence) const LANES: usize = 8;

/// One transposed row: `v[t][l]` is column `l·n + t`.
pub(super) type Lanes = Vec<[f32; LANES]>;

/// The transposed layout of a row of `d` columns.
#[derive(Clone, Copy, Debug)]
pub(in crate::confidence) struct Layout {
    /// Columns.
    pub(in crate::confidence) d: usize,
    /// Chunk length: `ceil(d / LANES)`.
    pub(in crate::confidence) n: usize,
}

impl Layout {
    pub(super) fn new(d: usize) -> Self {
        Layout {
            d,
            n: d.div_ceil(LANES).max(1),
        }
    }

    /// `(t, l)` of column `j`.
    #[inline]
    pub(in crate::confidence) fn at(&self, j: usize) -> (usize, usize) {
        (j % self.n, j / self.n)
    }

    /// Column of `(t, l)` (may be `>= d`: padding).
    #[inline]
    pub(super) fn col(&self, t: usize, l: usize) -> usize {
        l * self.n + t
    }

    fn blank(&self) -> Lanes {
        vec![[f32::INFINITY; LANES]; self.n]
    }
}

/// The graph and the discount, as the passes use them.
#[derive(Clone, Copy)]
pub(super) struct Graph {
    pub(super) k: usize,
    pub(super) horizontal: bool,
    pub(super) w: f32,
    pub(super) g: f32,
    pub(super) lay: Layout,
}

/// Node costs of one row in the lane layout: `1/ĉ` (`+inf` when `ĉ <= 0` and in the padding).
/// `avx2`: transpose blocks of eight layout rows in registers (the CPU has AVX2).
#[inline(always)]
fn costs(row: &[f32], lay: &Layout, out: &mut Lanes, avx2: bool) {
    let (n, d) = (lay.n, lay.d);
    // Transpose: row t of the layout takes column l·n + t of every chunk l (`LANES` sequential
    // read streams, one sequential write stream). Rows below `full` have all `LANES` columns.
    let full = d.saturating_sub((LANES - 1) * n).min(n);
    let chunks: [&[f32]; LANES] = std::array::from_fn(|l| &row[(l * n).min(d)..]);
    // Blocks of `LANES` rows by an in-register transpose where the CPU has one; element by
    // element (what the loop below does) LLVM made scalar loads and inserts through the stack.
    let blocks = if avx2 { full / LANES * LANES } else { 0 };
    #[cfg(target_arch = "x86_64")]
    for (b, o) in out[..blocks].chunks_exact_mut(LANES).enumerate() {
        // SAFETY: `avx2` is true only in `avx2::costs`, which runs after
        // `is_x86_feature_detected!("avx2")` (see `Steps`).
        #[allow(unsafe_code)]
        unsafe {
            avx2::transpose(&chunks, b * LANES, o)
        };
    }
    for (t, o) in out[..full].iter_mut().enumerate().skip(blocks) {
        for l in 0..LANES {
            o[l] = chunks[l][t];
        }
    }
    for (t, o) in out.iter_mut().enumerate().skip(full) {
        for l in 0..LANES {
            o[l] = chunks[l]
                .get(t)
                .copied()
                .filter(|_| l * n + t < d)
                .unwrap_or(0.0);
        }
    }
    for c in out.as_flattened_mut() {
        *c = if *c > 0.0 { 1.0 / *c } else { f32::INFINITY };
    }
}

/// Sets the padding columns (`>= d`) to `+inf`: the tail of the last chunks only.
#[inline(always)]
fn pad(lay: &Layout, v: &mut Lanes) {
    for l in lay.d / lay.n..LANES {
        let first = lay.d.saturating_sub(l * lay.n).min(lay.n);
        for row in &mut v[first..] {
            row[l] = f32::INFINITY;
        }
    }
}

/// The value at column `j` (`+inf` out of range).
#[inline(always)]
pub(super) fn get(lay: &Layout, v: &Lanes, j: usize) -> f32 {
    if j >= lay.d {
        return f32::INFINITY;
    }
    let (t, l) = lay.at(j);
    v[t][l]
}

/// The smaller of two values: one `minps` (no NaN reaches the passes: costs are `1/ĉ` of
/// positive `ĉ` or `+inf`, every value a sum of them and of `W` scaled by `g`).
#[inline(always)]
pub(super) fn min(a: f32, b: f32) -> f32 {
    if b < a {
        b
    } else {
        a
    }
}

/// [`min`] for updating a value in memory, `*a = min_mem(*a, b)`. Written as [`min`], LLVM
/// turns such an update into a conditional store and vectorises it with AVX2 as masked stores
/// (`vmaskmovps`), several times slower than `vminps` on AMD cores (measured: the passes took
/// twice as long). `f32::min` is not a select; without NaN it is the same value as [`min`].
#[inline(always)]
fn min_mem(a: f32, b: f32) -> f32 {
    a.min(b)
}

/// `out[t] = min(out[t], v[t - o])` for `t >= o` (chunk-internal shift by `o` rows), flat.
#[inline(always)]
fn min_shifted_down(out: &mut Lanes, v: &Lanes, o: usize) {
    let (out, v) = (out.as_flattened_mut(), v.as_flattened());
    let s = o * LANES;
    for (a, &b) in out[s..].iter_mut().zip(&v[..v.len() - s]) {
        *a = min_mem(*a, b);
    }
}

/// `out[t] = min(out[t], v[t + o])` for `t + o < n`, flat.
#[inline(always)]
fn min_shifted_up(out: &mut Lanes, v: &Lanes, o: usize) {
    let (out, v) = (out.as_flattened_mut(), v.as_flattened());
    let s = o * LANES;
    let len = out.len() - s;
    for (a, &b) in out[..len].iter_mut().zip(&v[s..]) {
        *a = min_mem(*a, b);
    }
}

/// `v *= scale`, flat.
#[inline(always)]
fn scale_all(v: &mut Lanes, scale: f32) {
    for x in v.as_flattened_mut() {
        *x *= scale;
    }
}

/// `out[j] = scale · min v[j-K ..= j]` (trailing window, clamped at column 0).
#[inline(always)]
fn trailing_min(g: &Graph, v: &Lanes, scale: f32, out: &mut Lanes) {
    let (lay, k) = (g.lay, g.k);
    let n = lay.n;
    // Inside a chunk: shifted minima (the first shift also copies).
    if k == 0 || n == 1 {
        out.copy_from_slice(v);
    } else {
        out[0] = v[0];
        let (o, a) = (out.as_flattened_mut(), v.as_flattened());
        for ((x, &p), &q) in o[LANES..]
            .iter_mut()
            .zip(&a[LANES..])
            .zip(&a[..a.len() - LANES])
        {
            *x = min(p, q);
        }
        for o in 2..=k.min(n - 1) {
            min_shifted_down(out, v, o);
        }
    }
    if k >= n {
        // A window longer than a chunk: column by column (tiny rows only).
        for t in 0..n {
            for l in 0..LANES {
                let j = lay.col(t, l);
                let mut m = f32::INFINITY;
                for jj in j.saturating_sub(k)..=j {
                    m = min(m, get(&lay, v, jj));
                }
                out[t][l] = m;
            }
        }
    } else {
        // The first K rows of each chunk also see the end of the chunk before.
        for t in 0..k {
            for l in 1..LANES {
                let mut m = out[t][l];
                for tt in n + t - k..n {
                    m = min(m, v[tt][l - 1]);
                }
                out[t][l] = m;
            }
        }
    }
    scale_all(out, scale);
}

/// `out[j] = scale · min v[j ..= j+K]` (leading window, clamped at the last column).
#[inline(always)]
fn leading_min(g: &Graph, v: &Lanes, scale: f32, out: &mut Lanes) {
    let (lay, k) = (g.lay, g.k);
    let n = lay.n;
    if k == 0 || n == 1 {
        out.copy_from_slice(v);
    } else {
        out[n - 1] = v[n - 1];
        let (o, a) = (out.as_flattened_mut(), v.as_flattened());
        let len = o.len() - LANES;
        for ((x, &p), &q) in o[..len].iter_mut().zip(&a[..len]).zip(&a[LANES..]) {
            *x = min(p, q);
        }
        for o in 2..=k.min(n - 1) {
            min_shifted_up(out, v, o);
        }
    }
    if k >= n {
        for t in 0..n {
            for l in 0..LANES {
                let j = lay.col(t, l);
                let mut m = f32::INFINITY;
                for jj in j..=j + k {
                    m = min(m, get(&lay, v, jj));
                }
                out[t][l] = m;
            }
        }
    } else {
        // The last K rows of each chunk also see the start of the chunk after.
        for t in n - k..n {
            for l in 0..LANES - 1 {
                let mut m = out[t][l];
                for tt in 0..=t + k - n {
                    m = min(m, v[tt][l + 1]);
                }
                out[t][l] = m;
            }
        }
    }
    scale_all(out, scale);
}

/// One row's values of one pass.
#[derive(Clone)]
pub(super) struct RowValues {
    /// `X` (forward: `FX`, backward: `BX`).
    pub x: Lanes,
    /// `H` (forward: `FH`, backward: `BH`) before its chunk's carry: the value at `[t][l]` is
    /// `min(h[t][l], carry[l])` (see `fused`: the one-pass steps keep the carry instead of
    /// applying it; the flat steps apply it and leave `+inf` here).
    pub h: Lanes,
    /// The running minimum of the hidden values of the chunks before (forward) or after
    /// (backward) each chunk.
    pub carry: [f32; LANES],
}

impl RowValues {
    pub(super) fn new(lay: &Layout) -> Self {
        RowValues {
            x: lay.blank(),
            h: lay.blank(),
            carry: [f32::INFINITY; LANES],
        }
    }

    /// `H` at column `j` (`+inf` out of range), its carry applied.
    #[inline]
    pub(super) fn h_at(&self, lay: &Layout, j: usize) -> f32 {
        if j >= lay.d {
            return f32::INFINITY;
        }
        let (t, l) = lay.at(j);
        min(self.h[t][l], self.carry[l])
    }
}

/// Work rows of a pass.
pub(super) struct Work {
    pub(super) cost: Lanes,
    base: Lanes,
    /// What the next row step reads of the last row: its `M = min(X, H)` (forward) or, for the
    /// one-pass backward step, its `A = min(c + BX, W + BH)`; lane `l` is `min(m, carry[l])`.
    m: Lanes,
    /// The one-pass steps' second `m` (they read one and write the other).
    m_next: Lanes,
    /// The lane carries of `m`.
    carry: [f32; LANES],
}

/// Where a pass stands after a row: what its next row step reads (`M` forward, `A`
/// backward, with their carries). A pass restarted from it computes the rows after it again,
/// bit for bit.
pub(super) struct Checkpoint {
    m: Lanes,
    carry: [f32; LANES],
}

impl Work {
    /// The pass's state after its last row.
    pub(super) fn checkpoint(&self) -> Checkpoint {
        Checkpoint {
            m: self.m.clone(),
            carry: self.carry,
        }
    }

    /// Goes on from `c` (a checkpoint of a pass on the same graph).
    pub(super) fn resume(&mut self, c: &Checkpoint) {
        self.m.copy_from_slice(&c.m);
        self.carry = c.carry;
    }

    pub(super) fn new(lay: &Layout) -> Self {
        Work {
            cost: lay.blank(),
            base: lay.blank(),
            m: lay.blank(),
            m_next: lay.blank(),
            carry: [f32::INFINITY; LANES],
        }
    }
}

impl Graph {
    /// Forward row `i` from `M = min(X, H)` of row `i-1` in `w.m` (`has_prev` false: the
    /// source). Expects `w.cost` to hold row `i`'s costs; leaves `M` of row `i` in `w.m`.
    #[inline(always)]
    fn forward_body(&self, has_prev: bool, w: &mut Work, out: &mut RowValues) {
        if has_prev && fused::applies(self) {
            return fused::forward(self, w, out);
        }
        let n = self.lay.n;
        if has_prev {
            trailing_min(self, &w.m, self.g, &mut w.base);
        } else {
            w.base.as_flattened_mut().fill(0.0);
        }
        let (cost, base) = (&w.cost, &w.base);
        let wv = self.w;
        if self.horizontal {
            // Local scans of every chunk from a +inf carry, all chunks at once.
            let (mut lx, mut lh) = ([f32::INFINITY; LANES], [f32::INFINITY; LANES]);
            for (((c, b), x), h) in cost.iter().zip(base).zip(&mut out.x).zip(&mut out.h) {
                for l in 0..LANES {
                    lx[l] = c[l] + min(b[l], lx[l]);
                    lh[l] = min(b[l] + wv, lh[l]);
                }
                *x = lx;
                *h = lh;
            }
            // Fix up chunk l from the true carry of chunk l-1.
            let mut carry_h = [f32::INFINITY; LANES];
            for l in 1..LANES {
                let mut left = out.x[n - 1][l - 1];
                for t in 0..n {
                    let v = cost[t][l] + min(base[t][l], left);
                    if v == out.x[t][l] {
                        break;
                    }
                    out.x[t][l] = v;
                    left = v;
                }
                carry_h[l] = min(carry_h[l - 1], out.h[n - 1][l - 1]);
            }
            for h in out.h.iter_mut() {
                for l in 0..LANES {
                    h[l] = min_mem(h[l], carry_h[l]);
                }
            }
        } else {
            let (c, b) = (cost.as_flattened(), base.as_flattened());
            for ((x, &c), &b) in out.x.as_flattened_mut().iter_mut().zip(c).zip(b) {
                *x = c + b;
            }
            for (h, &b) in out.h.as_flattened_mut().iter_mut().zip(b) {
                *h = b + wv;
            }
        }
        pad(&self.lay, &mut out.x);
        pad(&self.lay, &mut out.h);
        let (x, h) = (out.x.as_flattened(), out.h.as_flattened());
        for ((m, &x), &h) in w.m.as_flattened_mut().iter_mut().zip(x).zip(h) {
            *m = min(x, h);
        }
        out.carry = [f32::INFINITY; LANES];
        w.carry = [f32::INFINITY; LANES];
    }

    /// Backward row `i` after row `i+1` (`has_next` false: the sink). Expects `w.cost` to hold
    /// row `i`'s costs and `w.m`, `w.carry` row `i+1`'s `A` (left by the step of row `i+1`);
    /// leaves row `i`'s in them.
    #[inline(always)]
    fn backward_body(&self, has_next: bool, w: &mut Work, out: &mut RowValues) {
        if has_next && fused::applies(self) {
            return fused::backward(self, w, out);
        }
        let n = self.lay.n;
        if has_next {
            debug_assert!(w.carry.iter().all(|c| c.is_infinite()));
            leading_min(self, &w.m, self.g, &mut w.base);
        } else {
            w.base.as_flattened_mut().fill(0.0);
        }
        pad(&self.lay, &mut w.base);
        let (cost, succ) = (&w.cost, &w.base);
        if self.horizontal {
            // BX[j] = min(succ[j], Y[j+1]) with Y[j] = c[j] + BX[j]; BH a running minimum.
            let (mut ly, mut lh) = ([f32::INFINITY; LANES], [f32::INFINITY; LANES]);
            let rows = cost
                .iter()
                .zip(succ)
                .zip(out.x.iter_mut().zip(out.h.iter_mut()));
            for ((c, s), (x, h)) in rows.rev() {
                for l in 0..LANES {
                    let bx = min(s[l], ly[l]);
                    x[l] = bx;
                    ly[l] = c[l] + bx;
                    lh[l] = min(s[l], lh[l]);
                }
                *h = lh;
            }
            let mut carry_h = [f32::INFINITY; LANES];
            for l in (0..LANES - 1).rev() {
                let mut right = cost[0][l + 1] + out.x[0][l + 1];
                for t in (0..n).rev() {
                    let v = min(succ[t][l], right);
                    if v == out.x[t][l] {
                        break;
                    }
                    out.x[t][l] = v;
                    right = cost[t][l] + v;
                }
                carry_h[l] = min(carry_h[l + 1], out.h[0][l + 1]);
            }
            for h in out.h.iter_mut() {
                for l in 0..LANES {
                    h[l] = min_mem(h[l], carry_h[l]);
                }
            }
        } else {
            out.x.copy_from_slice(succ);
            out.h.copy_from_slice(succ);
        }
        pad(&self.lay, &mut out.x);
        pad(&self.lay, &mut out.h);
        out.carry = [f32::INFINITY; LANES];
        // What the step of row i-1 reads: `A = min(c + BX, W + BH)`.
        let (c, x, h) = (
            w.cost.as_flattened(),
            out.x.as_flattened(),
            out.h.as_flattened(),
        );
        for (((a, &c), &x), &h) in w.m.as_flattened_mut().iter_mut().zip(c).zip(x).zip(h) {
            *a = min(c + x, self.w + h);
        }
        w.carry = [f32::INFINITY; LANES];
    }
}

/// The instruction set the row steps are compiled for, picked once per sweep. The row steps
/// are plain element-wise `f32` operations (no fused multiply-add, no reassociation), so every
/// instruction set gives bit-identical values (test `every_instruction_set_gives_the_same_values`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) enum Isa {
    /// Whatever the build targets (SSE2 on a plain `x86_64` build: a lane row is two registers).
    Portable,
    /// AVX2: a lane row of eight `f32` is one register.
    #[cfg(target_arch = "x86_64")]
    Avx2,
}

impl Isa {
    /// The widest instruction set of this CPU the row steps have a version for.
    pub(super) fn detect() -> Self {
        #[cfg(target_arch = "x86_64")]
        {
            if std::arch::is_x86_feature_detected!("avx2") {
                return Isa::Avx2;
            }
        }
        Isa::Portable
    }
}

/// The row steps of [`Graph`] compiled for AVX2 (the `_body` functions and their helpers are
/// `#[inline(always)]`, so they are compiled again inside these functions).
#[cfg(target_arch = "x86_64")]
mod avx2 {
    use super::{Graph, Lanes, Layout, RowValues, Work, LANES};
    use std::arch::x86_64::{
        __m256, _mm256_loadu_ps, _mm256_permute2f128_ps, _mm256_shuffle_ps, _mm256_storeu_ps,
        _mm256_unpackhi_ps, _mm256_unpacklo_ps,
    };

    /// `out[t][l] = chunks[l][t0 + t]` for `t, l < 8`: eight loads, the usual 8x8 transpose
    /// (unpack, shuffle, lane permute), eight stores.
    #[target_feature(enable = "avx2")]
    #[allow(unsafe_code)]
    pub(super) fn transpose(chunks: &[&[f32]; LANES], t0: usize, out: &mut [[f32; LANES]]) {
        let load = |l: usize| {
            let src: &[f32; LANES] = chunks[l][t0..t0 + LANES].try_into().expect("8 values");
            // SAFETY: `src` is 8 readable `f32` (an unaligned load is allowed).
            unsafe { _mm256_loadu_ps(src.as_ptr()) }
        };
        let r: [__m256; LANES] = std::array::from_fn(load);
        let a0 = _mm256_unpacklo_ps(r[0], r[1]);
        let a1 = _mm256_unpackhi_ps(r[0], r[1]);
        let a2 = _mm256_unpacklo_ps(r[2], r[3]);
        let a3 = _mm256_unpackhi_ps(r[2], r[3]);
        let a4 = _mm256_unpacklo_ps(r[4], r[5]);
        let a5 = _mm256_unpackhi_ps(r[4], r[5]);
        let a6 = _mm256_unpacklo_ps(r[6], r[7]);
        let a7 = _mm256_unpackhi_ps(r[6], r[7]);
        let b0 = _mm256_shuffle_ps::<0x44>(a0, a2);
        let b1 = _mm256_shuffle_ps::<0xEE>(a0, a2);
        let b2 = _mm256_shuffle_ps::<0x44>(a1, a3);
        let b3 = _mm256_shuffle_ps::<0xEE>(a1, a3);
        let b4 = _mm256_shuffle_ps::<0x44>(a4, a6);
        let b5 = _mm256_shuffle_ps::<0xEE>(a4, a6);
        let b6 = _mm256_shuffle_ps::<0x44>(a5, a7);
        let b7 = _mm256_shuffle_ps::<0xEE>(a5, a7);
        let rows = [
            _mm256_permute2f128_ps::<0x20>(b0, b4),
            _mm256_permute2f128_ps::<0x20>(b1, b5),
            _mm256_permute2f128_ps::<0x20>(b2, b6),
            _mm256_permute2f128_ps::<0x20>(b3, b7),
            _mm256_permute2f128_ps::<0x31>(b0, b4),
            _mm256_permute2f128_ps::<0x31>(b1, b5),
            _mm256_permute2f128_ps::<0x31>(b2, b6),
            _mm256_permute2f128_ps::<0x31>(b3, b7),
        ];
        for (o, v) in out[..LANES].iter_mut().zip(rows) {
            // SAFETY: `o` is 8 writable `f32`.
            unsafe { _mm256_storeu_ps(o.as_mut_ptr(), v) }
        }
    }

    #[target_feature(enable = "avx2")]
    pub(super) fn costs(row: &[f32], lay: &Layout, out: &mut Lanes) {
        super::costs(row, lay, out, true);
    }

    #[target_feature(enable = "avx2")]
    pub(super) fn forward(g: &Graph, has_prev: bool, w: &mut Work, out: &mut RowValues) {
        g.forward_body(has_prev, w, out);
    }

    #[target_feature(enable = "avx2")]
    pub(super) fn backward(g: &Graph, has_next: bool, w: &mut Work, out: &mut RowValues) {
        g.backward_body(has_next, w, out);
    }

    #[target_feature(enable = "avx2")]
    pub(super) fn hidden_steps(
        lay: &Layout,
        h: &RowValues,
        forward: bool,
        horizontal: bool,
    ) -> Vec<(u32, f32)> {
        super::hidden_steps(lay, h, forward, horizontal)
    }
}

/// The row steps on the instruction set `isa` (see [`Isa`]).
#[derive(Clone, Copy)]
pub(super) struct Steps {
    pub(super) g: Graph,
    pub(super) isa: Isa,
}

// SAFETY (every `unsafe` block below): `Isa::Avx2` is only built by `Isa::detect` after
// `is_x86_feature_detected!("avx2")`, the one precondition of the `avx2` functions.
#[allow(unsafe_code)]
impl Steps {
    pub(super) fn costs(&self, row: &[f32], out: &mut Lanes) {
        match self.isa {
            #[cfg(target_arch = "x86_64")]
            Isa::Avx2 => unsafe { avx2::costs(row, &self.g.lay, out) },
            Isa::Portable => costs(row, &self.g.lay, out, false),
        }
    }

    pub(super) fn forward(&self, has_prev: bool, w: &mut Work, out: &mut RowValues) {
        match self.isa {
            #[cfg(target_arch = "x86_64")]
            Isa::Avx2 => unsafe { avx2::forward(&self.g, has_prev, w, out) },
            Isa::Portable => self.g.forward_body(has_prev, w, out),
        }
    }

    pub(super) fn backward(&self, has_next: bool, w: &mut Work, out: &mut RowValues) {
        match self.isa {
            #[cfg(target_arch = "x86_64")]
            Isa::Avx2 => unsafe { avx2::backward(&self.g, has_next, w, out) },
            Isa::Portable => self.g.backward_body(has_next, w, out),
        }
    }

    pub(super) fn hidden_steps(&self, h: &RowValues, forward: bool) -> Vec<(u32, f32)> {
        let (lay, horizontal) = (&self.g.lay, self.g.horizontal);
        match self.isa {
            #[cfg(target_arch = "x86_64")]
            Isa::Avx2 => unsafe { avx2::hidden_steps(lay, h, forward, horizontal) },
            Isa::Portable => hidden_steps(lay, h, forward, horizontal),
        }
    }
}

/// The hidden nodes of a stored row, reduced to the columns where the minimum over `j` of
/// `H_stored[j] + H_other[j]` can be reached (see the module doc): `(column, value)`.
#[inline(always)]
fn hidden_steps(lay: &Layout, row: &RowValues, forward: bool, horizontal: bool) -> Vec<(u32, f32)> {
    let (n, d) = (lay.n, lay.d);
    // Columns fit in u32: a row of 2^32 columns would not fit in memory as f32 lanes.
    let entry = |j: usize| (j as u32, row.h_at(lay, j));
    if !horizontal {
        return (0..d).map(entry).filter(|e| e.1.is_finite()).collect();
    }
    // With horizontal edges `H` is monotone along the row and changes at a few columns only:
    // find them by comparing each layout row with the next (all chunks at once: one vector
    // compare, the lanes looked at only where one differs).
    let carry = &row.carry;
    let at = |t: usize| -> [f32; LANES] { std::array::from_fn(|l| min(row.h[t][l], carry[l])) };
    let mut changes: Vec<usize> = Vec::new(); // columns j with H[j] != H[j+1]
    let mut here = at(0);
    for t in 0..n.saturating_sub(1) {
        let after = at(t + 1);
        let mut differs = false;
        for l in 0..LANES {
            differs |= here[l] != after[l];
        }
        if differs {
            for l in 0..LANES {
                if here[l] != after[l] {
                    changes.push(lay.col(t, l));
                }
            }
        }
        here = after;
    }
    let (last, first) = (at(n - 1), at(0));
    for l in 0..LANES - 1 {
        if last[l] != first[l + 1] {
            changes.push(lay.col(n - 1, l));
        }
    }
    changes.retain(|&j| j + 1 < d);
    let columns: Vec<usize> = if forward {
        // FH non-increasing: the first column of each constant run (BH is smallest there).
        std::iter::once(0)
            .chain(changes.iter().map(|&j| j + 1))
            .collect()
    } else {
        // BH non-decreasing: the last column of each constant run (FH is smallest there).
        changes
            .iter()
            .copied()
            .chain(std::iter::once(d - 1))
            .collect()
    };
    columns
        .into_iter()
        .map(entry)
        .filter(|e| e.1.is_finite())
        .collect()
}
