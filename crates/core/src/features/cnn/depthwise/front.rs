//! The front convolution computed inside [`DepthwiseConv`](super::DepthwiseConv) (a block's
//! 1x1 expansion, or the network's stem): each input plane of the depthwise layer is computed
//! from the op's input, a band at a time and a group of [`EXPAND_GROUP`] output planes per
//! pass, as one fused multiply-add chain per value in the order of tract's matrix-product
//! kernels, so the values are tract's bit for bit.
//!
//! Why apart from the depthwise kernels: a full convolution sums in another order (fused, over
//! input channels, from zero) than the depthwise taps (bias first, unfused), with its own band
//! and group sizes; keeping the two in separate files keeps each order in one place.

use super::Expand;

/// Values of an expanded plane computed per band: the bands of a group of
/// [`EXPAND_GROUP`] planes (16 KiB) stay in L1 next to the input streams.
pub(super) const EXPAND_BAND: usize = 1024;

/// Output channels of a front convolution computed together: each input value loaded once
/// feeds this many multiply-adds (one per output plane) instead of one.
pub(super) const EXPAND_GROUP: usize = 4;

/// Input channels summed per pass over an expansion band (held in registers in between).
const EXPAND_CHUNK: usize = 8;

impl Expand {
    /// A 1x1 convolution with stride 1 and no padding: its input planes are read as they are.
    pub(super) fn is_pointwise(&self) -> bool {
        let g = &self.geometry;
        g.kernel == (1, 1) && g.stride == (1, 1) && g.pad_before == (0, 0) && g.input == g.output
    }
}

/// Output channels `c0..` of the front convolution `e` of one image into `out` (as many
/// planes as it holds, each the depthwise layer's input plane): `sum w[c][k][ky][kx] * x[k][..]`
/// over `(k, ky, kx)` in row-major order as one fused multiply-add chain starting from zero,
/// then `+ bias[c]`: the order of tract's matrix-product kernels over the im2col rows (so the
/// values are tract's, bit for bit). A full group of [`EXPAND_GROUP`] planes is computed in
/// one pass over the inputs. `source(k, phase)` is stride phase `phase` of input plane `k`
/// (the plane itself for a pointwise convolution); `grid` holds one band per plane of the
/// group on the phases' row width (other than pointwise).
#[inline(always)]
pub(super) fn expand_planes<'a>(
    e: &Expand,
    c0: usize,
    source: impl Fn(usize, usize) -> &'a [f32] + Copy,
    out: &mut [f32],
    grid: Option<&mut [f32]>,
) {
    let g = &e.geometry;
    let (oh, ow) = g.output;
    let (kh, kw) = g.kernel;
    let (sh, sw) = g.stride;
    let taps = kh * kw;
    let t_all = e.in_channels * taps;
    let plane = oh * ow;
    let count = out.len() / plane;
    let weights = |c: usize| &e.weights[c * t_all..(c + 1) * t_all];
    let bias = |c: usize| e.bias.as_ref().map(|b| b[c]);
    let (_, wq) = g.phase_size();
    let wq = if grid.is_some() { wq } else { ow };
    let band_rows = (EXPAND_BAND / wq).max(1).min(oh);
    let band = (EXPAND_BAND / wq).max(1) * wq;
    let mut grid = grid;
    let mut y0 = 0;
    while y0 < oh {
        let rows = band_rows.min(oh - y0);
        let n = rows * wq;
        let stream = |t: usize| {
            let (k, r) = (t / taps, t % taps);
            let (ky, kx) = (r / kw, r % kw);
            let start = (y0 + ky / sh) * wq + kx / sw;
            &source(k, (ky % sh) * sw + kx % sw)[start..start + n]
        };
        // The band of each plane: in `out` itself when pointwise, else in `grid`.
        let (bands, stride) = match grid.as_deref_mut() {
            None => (&mut out[y0 * ow..], plane),
            Some(grid) => (&mut grid[..], band),
        };
        // (Plain functions, not closures: closures do not get the caller's target features,
        // and `mul_add` without FMA is a libm call.)
        if count == EXPAND_GROUP {
            let (a0, rest) = bands.split_at_mut(stride);
            let (a1, rest) = rest.split_at_mut(stride);
            let (a2, a3) = rest.split_at_mut(stride);
            let w = [
                weights(c0),
                weights(c0 + 1),
                weights(c0 + 2),
                weights(c0 + 3),
            ];
            front_band4(
                [&mut a0[..n], &mut a1[..n], &mut a2[..n], &mut a3[..n]],
                w,
                stream,
            );
        } else {
            for j in 0..count {
                front_band(
                    &mut bands[j * stride..j * stride + n],
                    weights(c0 + j),
                    stream,
                );
            }
        }
        for j in 0..count {
            let Some(b) = bias(c0 + j) else { continue };
            match grid.as_deref_mut() {
                None => out[j * plane + y0 * ow..][..n]
                    .iter_mut()
                    .for_each(|a| *a += b),
                Some(grid) => grid[j * band..][..n].iter_mut().for_each(|a| *a += b),
            }
        }
        if let Some(grid) = grid.as_deref() {
            for j in 0..count {
                for (r, row) in grid[j * band..][..n].chunks_exact(wq).enumerate() {
                    out[j * plane + (y0 + r) * ow..][..ow].copy_from_slice(&row[..ow]);
                }
            }
        }
        y0 += rows;
    }
}

/// One band of one plane of a front convolution: `acc = fma chain of w[t] * stream(t)` over `t`
/// (the bias is added by the caller).
#[inline(always)]
fn front_band<'a>(acc: &mut [f32], w: &[f32], stream: impl Fn(usize) -> &'a [f32] + Copy) {
    acc.fill(0.0);
    let mut t = 0;
    while t + EXPAND_CHUNK <= w.len() {
        fma_chain::<EXPAND_CHUNK>(acc, &w[t..t + EXPAND_CHUNK], |j| stream(t + j));
        t += EXPAND_CHUNK;
    }
    while t < w.len() {
        fma_chain::<1>(acc, &w[t..t + 1], |_| stream(t));
        t += 1;
    }
}

/// [`front_band`] for [`EXPAND_GROUP`] planes at once: every input run is read once for all
/// four output channels.
#[inline(always)]
fn front_band4<'a>(
    [a0, a1, a2, a3]: [&mut [f32]; EXPAND_GROUP],
    w: [&[f32]; EXPAND_GROUP],
    stream: impl Fn(usize) -> &'a [f32] + Copy,
) {
    for a in [&mut *a0, &mut *a1, &mut *a2, &mut *a3] {
        a.fill(0.0);
    }
    let taps = w[0].len();
    let mut t = 0;
    // A 3x3 front convolution (the stem) in whole input channels of 9 taps.
    if taps.is_multiple_of(9) {
        while t < taps {
            let wt = w.map(|w| &w[t..t + 9]);
            fma_chain4::<9>(a0, a1, a2, a3, wt, |j| stream(t + j));
            t += 9;
        }
    }
    while t + EXPAND_CHUNK <= taps {
        let wt = w.map(|w| &w[t..t + EXPAND_CHUNK]);
        fma_chain4::<EXPAND_CHUNK>(a0, a1, a2, a3, wt, |j| stream(t + j));
        t += EXPAND_CHUNK;
    }
    while t < taps {
        let wt = w.map(|w| &w[t..t + 1]);
        fma_chain4::<1>(a0, a1, a2, a3, wt, |_| stream(t));
        t += 1;
    }
}

/// [`fma_chain`] into four planes (`a0..a3`, with weights `w[0..4]`) from the same `T` inputs:
/// four running sums per position kept in registers.
#[inline(always)]
fn fma_chain4<'a, const T: usize>(
    a0: &mut [f32],
    a1: &mut [f32],
    a2: &mut [f32],
    a3: &mut [f32],
    w: [&[f32]; EXPAND_GROUP],
    x: impl Fn(usize) -> &'a [f32],
) {
    let n = a0.len();
    let (a1, a2, a3) = (&mut a1[..n], &mut a2[..n], &mut a3[..n]);
    let w: [[f32; T]; EXPAND_GROUP] = w.map(|w| std::array::from_fn(|t| w[t]));
    let x: [&[f32]; T] = std::array::from_fn(|t| &x(t)[..n]);
    for i in 0..n {
        let mut v = [a0[i], a1[i], a2[i], a3[i]];
        for t in 0..T {
            let xv = x[t][i];
            for (v, w) in v.iter_mut().zip(&w) {
                *v = w[t].mul_add(xv, *v);
            }
        }
        [a0[i], a1[i], a2[i], a3[i]] = v;
    }
}

/// `acc[i] = fma(w[T-1], x(T-1)[i], ... fma(w[0], x(0)[i], acc[i]))`: `T` input channels in
/// order, the running sum kept in a register between them.
#[inline(always)]
fn fma_chain<'a, const T: usize>(acc: &mut [f32], w: &[f32], x: impl Fn(usize) -> &'a [f32]) {
    let n = acc.len();
    let w: [f32; T] = std::array::from_fn(|t| w[t]);
    let x: [&[f32]; T] = std::array::from_fn(|t| &x(t)[..n]);
    for (i, a) in acc.iter_mut().enumerate() {
        let mut v = *a;
        for t in 0..T {
            v = w[t].mul_add(x[t][i], v);
        }
        *a = v;
    }
}
