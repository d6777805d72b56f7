//! The depthwise kernels behind [`DepthwiseConv`]: the run-time choice of instruction set
//! (AVX-512, AVX2 + FMA, portable), the loop over images and channels, the split of each
//! zero-padded input plane into its stride phases (with the input clamp) and the banded
//! multiply-add over every tap (with the output clamp), in tract's order of summation (see
//! [`super`]).
//!
//! Why apart from the operator: this is the arithmetic, the part profiled and tuned (band
//! sizes, fixed-tap-count loops for 3x3 and 5x5), and its test checks it against the direct
//! definition; the operator above is tract's glue (shapes, facts, equality) and changes for
//! other reasons. The front convolution's kernels are in `front.rs`.

use super::front::{expand_planes, EXPAND_BAND, EXPAND_GROUP};
use super::{DepthwiseConv, Geometry};

/// Output values accumulated per band: 4096 `f32` (16 KiB) stay in L1 with the phases' rows.
const BAND_VALUES: usize = 4096;

impl DepthwiseConv {
    /// The output of every plane of `input` (`[.., c, h, w]`, contiguous).
    #[cfg(test)]
    fn run(&self, input: &[f32]) -> Vec<f32> {
        let g = &self.geometry;
        let (h, w) = self.in_plane();
        let images = input.len() / (self.in_channels() * h * w);
        let mut output = vec![f32::NAN; images * g.channels * g.output.0 * g.output.1];
        self.run_into(input, &mut output);
        output
    }

    /// Writes every value of `output` (`[.., c, oh, ow]`) from `input` (`[.., c, h, w]`).
    pub(super) fn run_into(&self, input: &[f32], output: &mut [f32]) {
        #[cfg(target_arch = "x86_64")]
        {
            if std::arch::is_x86_feature_detected!("avx512f") {
                // SAFETY: the CPU has AVX-512F, the one precondition of this function.
                #[allow(unsafe_code)]
                unsafe {
                    simd::planes_avx512(self, input, output)
                };
                return;
            }
            if std::arch::is_x86_feature_detected!("avx2")
                && std::arch::is_x86_feature_detected!("fma")
            {
                // SAFETY: the CPU has AVX2 and FMA, the one precondition of this function.
                #[allow(unsafe_code)]
                unsafe {
                    simd::planes_avx2(self, input, output)
                };
                return;
            }
        }
        planes(self, input, output);
    }
}

#[cfg(target_arch = "x86_64")]
mod simd {
    use super::{planes, DepthwiseConv};

    /// [`planes`] compiled for AVX-512F (16 lanes; implies FMA).
    #[target_feature(enable = "avx512f")]
    pub(super) fn planes_avx512(op: &DepthwiseConv, input: &[f32], output: &mut [f32]) {
        planes(op, input, output);
    }

    /// [`planes`] compiled for AVX2 and FMA (8 lanes).
    #[target_feature(enable = "avx2,fma")]
    pub(super) fn planes_avx2(op: &DepthwiseConv, input: &[f32], output: &mut [f32]) {
        planes(op, input, output);
    }
}

/// Every output plane of `output` (`[.., channels, oh, ow]`) from `input`
/// (`[.., in_channels, h, w]`).
#[inline(always)]
fn planes(op: &DepthwiseConv, input: &[f32], output: &mut [f32]) {
    let g = &op.geometry;
    let (kh, kw) = g.kernel;
    let taps = kh * kw;
    let in_plane = g.input.0 * g.input.1;
    let out_plane = g.output.0 * g.output.1;
    let (_, wq) = g.phase_size();
    let band_rows = (BAND_VALUES / wq).max(1).min(g.output.0);
    // Zeroed once: every plane writes the same positions, so the padding stays zero.
    let mut phases = vec![0.0f32; g.stride.0 * g.stride.1 * g.phase_len()];
    let mut acc = vec![0.0f32; band_rows * wq];
    // A group of expanded planes, computed together (see [`EXPAND_GROUP`]).
    let group = if op.expand.is_some() { EXPAND_GROUP } else { 1 };
    let mut expanded = vec![
        0.0f32;
        if op.expand.is_some() {
            group * in_plane
        } else {
            0
        }
    ];
    // A front convolution other than 1x1 reads the stride phases of its input planes, on a
    // grid as wide as a phase row (like [`plane`]).
    let front = op.expand.as_ref().filter(|e| !e.is_pointwise());
    let front_phase_len = front.map_or(0, |e| e.geometry.phase_len());
    let front_phases_per_plane = front.map_or(0, |e| e.geometry.stride.0 * e.geometry.stride.1);
    let mut front_phases =
        vec![0.0f32; op.in_channels() * front_phases_per_plane * front_phase_len];
    let mut grid = vec![
        0.0f32;
        front.map_or(0, |e| {
            let (_, wq) = e.geometry.phase_size();
            group * (EXPAND_BAND / wq).max(1) * wq
        })
    ];
    let (fh, fw) = op.in_plane();
    let image_in = op.in_channels() * fh * fw;
    for (image, image_out) in input
        .chunks_exact(image_in)
        .zip(output.chunks_exact_mut(g.channels * out_plane))
    {
        if let Some(e) = front {
            let per_plane = front_phases_per_plane * front_phase_len;
            for (src, phases) in image
                .chunks_exact(fh * fw)
                .zip(front_phases.chunks_exact_mut(per_plane))
            {
                fill_phases(&e.geometry, src, phases, |v| v);
            }
        }
        for (first, dsts) in image_out.chunks_mut(group * out_plane).enumerate() {
            let c0 = first * group;
            let count = dsts.len() / out_plane;
            let sources = match &op.expand {
                None => &image[c0 * in_plane..(c0 + count) * in_plane],
                Some(e) if e.is_pointwise() => {
                    let n = fh * fw;
                    let out = &mut expanded[..count * in_plane];
                    expand_planes(e, c0, |k, _| &image[k * n..(k + 1) * n], out, None);
                    &expanded[..count * in_plane]
                }
                Some(e) => {
                    let per_plane = front_phases_per_plane * front_phase_len;
                    let phases = |k: usize, phase: usize| {
                        &front_phases[k * per_plane + phase * front_phase_len..][..front_phase_len]
                    };
                    let out = &mut expanded[..count * in_plane];
                    expand_planes(e, c0, phases, out, Some(&mut grid[..]));
                    &expanded[..count * in_plane]
                }
            };
            for (j, (src, dst)) in sources
                .chunks_exact(in_plane)
                .zip(dsts.chunks_exact_mut(out_plane))
                .enumerate()
            {
                let c = c0 + j;
                let w = &op.weights[c * taps..(c + 1) * taps];
                channel(op, c, src, &mut phases, w, &mut acc, dst);
            }
        }
    }
}

/// One output plane `dst` of channel `c` from its input plane `src`.
#[inline(always)]
fn channel(
    op: &DepthwiseConv,
    c: usize,
    src: &[f32],
    phases: &mut [f32],
    w: &[f32],
    acc: &mut [f32],
    dst: &mut [f32],
) {
    let g = &op.geometry;
    match op.input_clamp {
        None => fill_phases(g, src, phases, |v| v),
        Some((lo, hi)) => fill_phases(g, src, phases, |v| v.max(lo).min(hi)),
    }
    plane(g, phases, w, op.bias[c], op.clamp, acc, dst);
}

/// Splits the zero-padded plane `src`, each value mapped by `f` (the input clamp), into its
/// stride phases (see [`Geometry::phase_size`]). Input rows are visited once each, in order,
/// so every input value is read from memory once. Only the positions of input values are
/// written: the padding positions keep the zeros `phases` starts with.
#[inline(always)]
fn fill_phases(g: &Geometry, src: &[f32], phases: &mut [f32], f: impl Fn(f32) -> f32 + Copy) {
    let (h, w) = g.input;
    let (sh, sw) = g.stride;
    let (pt, pl) = g.pad_before;
    let (hq, wq) = g.phase_size();
    let len = g.phase_len();
    for (y, src_row) in src.chunks_exact(w).take(h).enumerate() {
        // Input row `y` is padded row `y + pt`: row `i` of the phases with row remainder `py`.
        let (i, py) = ((y + pt) / sh, (y + pt) % sh);
        if i >= hq {
            break;
        }
        if sw == 2 {
            let start = py * 2 * len + i * wq;
            deinterleave(src_row, pl, len, &mut phases[start..start + len + wq], f);
            continue;
        }
        for px in 0..sw {
            // Padded column `j * sw + px` is input column `j * sw + px - pl`: the first input
            // column of this phase and the phase column it lands in.
            let x0 = (px + sw - pl % sw) % sw;
            let j0 = (x0 + pl) / sw;
            if x0 >= w || j0 >= wq {
                continue;
            }
            let start = (py * sw + px) * len + i * wq;
            let dst = &mut phases[start + j0..start + wq];
            if sw == 1 {
                for (d, &s) in dst.iter_mut().zip(src_row) {
                    *d = f(s);
                }
            } else {
                for (d, &s) in dst.iter_mut().zip(src_row[x0..].iter().step_by(sw)) {
                    *d = f(s);
                }
            }
        }
    }
}

/// Stride 2 along columns: input column `x` is padded column `x + pl`, which goes to phase
/// `(x + pl) % 2` at column `(x + pl) / 2`. `rows` starts with the row of phase 0 and ends with
/// the `wq` values of phase 1's row, `len` (a phase's length) after it. Both rows are filled in
/// one pass over pairs of columns (vectorised) instead of two strided passes.
#[inline(always)]
fn deinterleave(src_row: &[f32], pl: usize, len: usize, rows: &mut [f32], f: impl Fn(f32) -> f32) {
    let (first, second) = rows.split_at_mut(len);
    let wq = second.len();
    let first = &mut first[..wq];
    // Even input columns land in phase `pl % 2`, odd ones in the other.
    let (even, odd) = if pl.is_multiple_of(2) {
        (first, second)
    } else {
        (second, first)
    };
    let (even, odd) = (
        &mut even[(pl / 2).min(wq)..],
        &mut odd[pl.div_ceil(2).min(wq)..],
    );
    let pairs = (src_row.len() / 2).min(even.len()).min(odd.len());
    for ((pair, e), o) in src_row
        .chunks_exact(2)
        .take(pairs)
        .zip(even.iter_mut())
        .zip(odd.iter_mut())
    {
        *e = f(pair[0]);
        *o = f(pair[1]);
    }
    // An odd last column, or the columns past the shorter phase row.
    for (x, &v) in src_row.iter().enumerate().skip(2 * pairs) {
        let dst = if x % 2 == 0 { &mut *even } else { &mut *odd };
        if let Some(d) = dst.get_mut(x / 2) {
            *d = f(v);
        }
    }
}

/// One output plane from the phases of its input plane.
#[inline(always)]
fn plane(
    g: &Geometry,
    phases: &[f32],
    taps: &[f32],
    bias: f32,
    (lo, hi): (f32, f32),
    acc: &mut [f32],
    out: &mut [f32],
) {
    let (oh, ow) = g.output;
    let (kh, kw) = g.kernel;
    let (sh, sw) = g.stride;
    let (_, wq) = g.phase_size();
    let len = g.phase_len();
    let band_rows = acc.len() / wq;
    let mut y0 = 0;
    while y0 < oh {
        let rows = band_rows.min(oh - y0);
        let n = rows * wq;
        let acc = &mut acc[..n];
        // The source run of tap (ky, kx) for this band.
        let source = |ky: usize, kx: usize| {
            let phase = &phases[((ky % sh) * sw + kx % sw) * len..][..len];
            let start = (y0 + ky / sh) * wq + kx / sw;
            &phase[start..start + n]
        };
        match (kh, kw) {
            (3, 3) => all_taps::<9>(acc, bias, taps, |t| source(t / 3, t % 3)),
            (5, 5) => all_taps::<25>(acc, bias, taps, |t| source(t / 5, t % 5)),
            _ => {
                acc.fill(bias);
                for ky in 0..kh {
                    for kx in 0..kw {
                        let t = taps[ky * kw + kx];
                        for (a, s) in acc.iter_mut().zip(source(ky, kx)) {
                            *a += t * *s;
                        }
                    }
                }
            }
        }
        for (r, row) in acc.chunks_exact(wq).enumerate() {
            let o = &mut out[(y0 + r) * ow..(y0 + r + 1) * ow];
            for (o, &a) in o.iter_mut().zip(&row[..ow]) {
                *o = a.max(lo).min(hi);
            }
        }
        y0 += rows;
    }
}

/// `acc[i] = bias + taps[0] * src(0)[i] + taps[1] * src(1)[i] + ...` in that order, all `T`
/// taps in one pass (the values stay in registers instead of going through `acc` per tap).
#[inline(always)]
fn all_taps<'a, const T: usize>(
    acc: &mut [f32],
    bias: f32,
    taps: &[f32],
    src: impl Fn(usize) -> &'a [f32],
) {
    let n = acc.len();
    let w: [f32; T] = std::array::from_fn(|t| taps[t]);
    let s: [&[f32]; T] = std::array::from_fn(|t| &src(t)[..n]);
    for (i, a) in acc.iter_mut().enumerate() {
        let mut v = bias;
        for t in 0..T {
            v += w[t] * s[t][i];
        }
        *a = v;
    }
}

#[cfg(test)]
mod tests {
    use std::sync::Arc;

    use super::super::Expand;
    use super::*;

    /// Direct definition: `out[c][y][x] = bias[c] + sum w[c][ky][kx] * in[c][y*sh+ky-pt][x*sw+kx-pl]`
    /// (input values clamped by the input clamp, zero outside the input), then the clamp; with
    /// a front convolution, `in[c][y][x]` is first the chain `v = fma(w[c][k][ky][kx],
    /// x[k][y*sh+ky-pt][x*sw+kx-pl], v)` from `v = 0` over `(k, ky, kx)` in order, `+ b[c]`.
    fn naive(op: &DepthwiseConv, input: &[f32]) -> Vec<f32> {
        let g = &op.geometry;
        let ((h, w), (oh, ow), (kh, kw)) = (g.input, g.output, g.kernel);
        let n = h * w;
        let planes: Vec<Vec<f32>> = match &op.expand {
            None => input.chunks_exact(n).map(<[f32]>::to_vec).collect(),
            Some(e) => {
                let f = &e.geometry;
                let ((fh, fw), (fkh, fkw)) = (f.input, f.kernel);
                let taps = e.in_channels * fkh * fkw;
                input
                    .chunks_exact(e.in_channels * fh * fw)
                    .flat_map(|image| {
                        (0..g.channels).map(move |c| {
                            let mut plane = Vec::new();
                            for y in 0..h {
                                for x in 0..w {
                                    let mut v = 0.0f32;
                                    for t in 0..taps {
                                        let (k, ky, kx) = (t / (fkh * fkw), t / fkw % fkh, t % fkw);
                                        let iy = (y * f.stride.0 + ky) as isize
                                            - f.pad_before.0 as isize;
                                        let ix = (x * f.stride.1 + kx) as isize
                                            - f.pad_before.1 as isize;
                                        let inside = (0..fh as isize).contains(&iy)
                                            && (0..fw as isize).contains(&ix);
                                        let value = if inside {
                                            image[(k * fh + iy as usize) * fw + ix as usize]
                                        } else {
                                            0.0
                                        };
                                        v = e.weights[c * taps + t].mul_add(value, v);
                                    }
                                    plane.push(e.bias.as_ref().map_or(v, |b| v + b[c]));
                                }
                            }
                            plane
                        })
                    })
                    .collect()
            }
        };
        let mut out = Vec::new();
        for (p, plane) in planes.iter().enumerate() {
            let c = p % g.channels;
            for y in 0..oh {
                for x in 0..ow {
                    let mut v = op.bias[c];
                    for ky in 0..kh {
                        for kx in 0..kw {
                            let iy = (y * g.stride.0 + ky) as isize - g.pad_before.0 as isize;
                            let ix = (x * g.stride.1 + kx) as isize - g.pad_before.1 as isize;
                            let inside =
                                (0..h as isize).contains(&iy) && (0..w as isize).contains(&ix);
                            let value = if inside {
                                let v = plane[iy as usize * w + ix as usize];
                                op.input_clamp.map_or(v, |(lo, hi)| v.max(lo).min(hi))
                            } else {
                                0.0
                            };
                            v += op.weights[(c * kh + ky) * kw + kx] * value;
                        }
                    }
                    out.push(v.max(op.clamp.0).min(op.clamp.1));
                }
            }
        }
        out
    }

    fn values(n: usize, seed: u32) -> Vec<f32> {
        let mut state = seed;
        (0..n)
            .map(|_| {
                state = state.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
                (state >> 8) as f32 / (1 << 23) as f32 - 1.0
            })
            .collect()
    }

    /// Every kernel size, stride and padding the fast paths take (3x3, 5x5, other) on planes
    /// whose width is not a multiple of the vector width, two images per batch; with and
    /// without a front convolution (a 1x1 expansion of 11 input channels: a chunk of 8 and
    /// single ones, with and without bias; a 3x3 stride-2 stem; planes of more than one band)
    /// and an input clamp.
    #[test]
    fn equals_the_direct_definition() {
        let cases = [
            // (h, w), kernel, stride, pad before, pad after
            ((9, 13), (3, 3), (1, 1), (1, 1), (1, 1)),
            ((9, 13), (3, 3), (2, 2), (0, 0), (1, 1)),
            ((12, 7), (5, 5), (2, 2), (1, 1), (2, 2)),
            ((12, 7), (5, 5), (1, 1), (2, 2), (2, 2)),
            ((6, 10), (2, 3), (1, 2), (0, 1), (1, 1)),
            ((5, 5), (3, 3), (3, 1), (0, 0), (0, 0)),
            ((70, 90), (3, 3), (1, 1), (1, 1), (1, 1)),
        ];
        for (case, &(input, kernel, stride, pad_before, pad_after)) in cases.iter().enumerate() {
            // A group of four planes computed together and one left over.
            let channels = 5;
            let out = |i: usize, k: usize, s: usize, before: usize, after: usize| {
                (i + before + after - k) / s + 1
            };
            let geometry = Geometry {
                channels,
                input,
                output: (
                    out(input.0, kernel.0, stride.0, pad_before.0, pad_after.0),
                    out(input.1, kernel.1, stride.1, pad_before.1, pad_after.1),
                ),
                kernel,
                stride,
                pad_before,
            };
            let op = DepthwiseConv {
                geometry,
                weights: Arc::new(values(channels * kernel.0 * kernel.1, 1 + case as u32)),
                bias: Arc::new(values(channels, 7)),
                clamp: if case % 2 == 0 {
                    (0.0, 0.5)
                } else {
                    (f32::NEG_INFINITY, f32::INFINITY)
                },
                // Clamps that cut values on both sides (inputs are in -1..1), on both paths of
                // the stride-2 columns and the generic stride.
                input_clamp: (case % 3 != 0).then_some((-0.25, 0.5)),
                expand: match case {
                    // The stem's shape: 3x3, stride 2, 3 input channels, padded after only
                    // (TF "SAME") or on both sides.
                    2 | 6 => {
                        let pad = if case == 2 { (1, 1) } else { (0, 0) };
                        let front_in = (2 * input.0, 2 * input.1);
                        Some(Expand {
                            in_channels: 3,
                            geometry: Geometry {
                                channels: 3,
                                input: front_in,
                                output: input,
                                kernel: (3, 3),
                                stride: (2, 2),
                                pad_before: pad,
                            },
                            weights: Arc::new(values(channels * 27, 3 + case as u32)),
                            bias: Some(Arc::new(values(channels, 5))),
                        })
                    }
                    0 | 4 => Some(Expand {
                        in_channels: 11,
                        geometry: Geometry {
                            channels: 11,
                            input,
                            output: input,
                            kernel: (1, 1),
                            stride: (1, 1),
                            pad_before: (0, 0),
                        },
                        weights: Arc::new(values(channels * 11, 3 + case as u32)),
                        bias: (case != 4).then(|| Arc::new(values(channels, 5))),
                    }),
                    _ => None,
                },
            };
            let (fh, fw) = op.in_plane();
            let x = values(2 * op.in_channels() * fh * fw, 99);
            let want = naive(&op, &x);
            let got = op.run(&x);
            assert_eq!(got.len(), want.len(), "case {case}");
            // NaN until written: a value the kernels miss fails the comparison.
            let mut portable = vec![f32::NAN; want.len()];
            planes(&op, &x, &mut portable);
            for (i, ((g, p), w)) in got.iter().zip(&portable).zip(&want).enumerate() {
                assert!((g - w).abs() <= 1e-6, "case {case}, value {i}: {g} != {w}");
                assert_eq!(
                    g.to_bits(),
                    p.to_bits(),
                    "case {case}: SIMD and portable differ"
                );
            }
            let k = op.in_channels();
            let shape = op.output_shape(&[2, k, fh, fw]).unwrap();
            assert_eq!(shape, [2, channels, geometry.output.0, geometry.output.1]);
            assert!(op.output_shape(&[2, k + 1, fh, fw]).is_err());
        }
    }
}
