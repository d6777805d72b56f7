//! Depthwise convolutions (one `kh x kw` filter per channel, EfficientNet's and MobileNet's
//! inverted-residual blocks) as a tract operator of our own, wired into the graph at load time
//! in place of tract's, together with the clamps right before and after it (ReLU6) and, on
//! large planes, the convolution in front of it (a block's 1x1 expansion, or the stem).
//!
//! Why: profiling tract 0.23.9 on EfficientNet-Lite0 up to `block10` showed its depthwise
//! convolution taking over half of an inference (11.3 of 21.3 ms): its vector kernel only runs
//! on stride-1 rows, so the two stride-2 layers (`conv_18`, `conv_41`) walk every tap scalar
//! (6.5 ms together), and the 14x14 layers vectorise rows of only 14 points. The ReLU6 after
//! every depthwise layer is a separate pass over the activations (1.1 ms). On the 112x112 and
//! 56x56 planes the layer in front writes activations larger than the L2 cache (96 x 112 x 112
//! values = 4.8 MB after block 1's expansion) that the depthwise layer then reads back: tract's
//! product for that expansion ran at a third of its speed on the small planes.
//!
//! How: per channel, the zero-padded input plane is split into its `sh x sw` stride phases
//! (row and column remainders), so that every tap reads a contiguous run of one phase. The
//! output is accumulated on a grid as wide as a phase row (the columns past the output width
//! are computed and dropped), so each tap is one long, branch-free multiply-add over a band of
//! rows that stays in L1, which the compiler vectorises (AVX-512 or AVX2 + FMA when the CPU has
//! them, chosen at run time). The clamp before is applied while the phases are filled, the
//! clamp after while the band is copied out. With a front convolution, each input plane of the
//! depthwise layer is first computed from the op's input (one plane, in L1/L2) and never
//! stored: a 1x1 expansion from the input planes as they are, the stem from the stride phases
//! of the image's planes, both with the same banded multiply-add over contiguous runs, four
//! output planes per pass so that each input value loaded feeds four multiply-adds.
//!
//! Invariants: for every output value the sum is taken in tract's order (the bias, then one
//! multiply and one add per tap, taps in row-major order, no fused multiply-add), and padding
//! taps add `w * 0`, so results equal tract's up to the sign of zero; a front convolution sums
//! like tract's matrix-product kernels (one fused multiply-add chain over input channel, then
//! kernel row and column, from zero, then the bias), so it is bit-identical too. Only float
//! convolutions with constant weights, dilation 1 and NCHW/CHW layout are rewritten, everything
//! else keeps tract's operators.

use std::sync::Arc;

use tract_onnx::prelude::*;
use tract_onnx::tract_core::internal::{
    ensure, format_err, DimLike, EvalOp, Op, StaticName, Validation,
};
use tract_onnx::tract_core::plan::EvalContext;

mod rewrite;
pub(crate) use rewrite::rewrite;

/// Output values accumulated per band: 4096 `f32` (16 KiB) stay in L1 with the phases' rows.
const BAND_VALUES: usize = 4096;

/// Values of an expanded plane computed per band: the bands of a group of
/// [`EXPAND_GROUP`] planes (16 KiB) stay in L1 next to the input streams.
const EXPAND_BAND: usize = 1024;

/// Output channels of a front convolution computed together: each input value loaded once
/// feeds this many multiply-adds (one per output plane) instead of one.
const EXPAND_GROUP: usize = 4;

/// Input channels summed per pass over an expansion band (held in registers in between).
const EXPAND_CHUNK: usize = 8;

/// Smallest input plane (`h * w`) whose 1x1 expansion is fused into the depthwise layer that
/// follows it. On large planes the expanded activations (e.g. 96 x 112 x 112 = 4.8 MB) do not
/// fit in the cache and tract's matrix product is bound by writing them and the depthwise
/// layer by reading them back; computed one plane at a time they stay in L1/L2. On small
/// planes tract's products, with their register tiles, are faster than our per-plane sums.
const EXPAND_MIN_PLANE: usize = 56 * 56;

/// A full convolution computed inside [`DepthwiseConv`], right before it, one output plane
/// at a time: the 1x1 expansion of an inverted-residual block, or the network's stem (3x3,
/// stride 2, 3 -> 32 channels).
#[derive(Clone, Debug)]
struct Expand {
    in_channels: usize,
    /// Its own planes: `channels` = `in_channels` (the planes split into stride phases),
    /// `output` = the depthwise layer's input plane.
    geometry: Geometry,
    /// `channels * in_channels * kh * kw`, row-major per output channel (OIHW).
    weights: Arc<Vec<f32>>,
    /// One per output channel; `None` for a convolution without bias (nothing is added).
    bias: Option<Arc<Vec<f32>>>,
}

/// Plane sizes, kernel, strides and padding of one depthwise layer.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
struct Geometry {
    channels: usize,
    /// Input plane `(h, w)`.
    input: (usize, usize),
    /// Output plane `(h, w)`.
    output: (usize, usize),
    kernel: (usize, usize),
    stride: (usize, usize),
    /// Zero rows above and columns left of the input.
    pad_before: (usize, usize),
}

impl Geometry {
    /// Rows and columns of one stride phase of the padded plane, with room for every tap of
    /// every output: phase row `i` holds padded rows `i * sh + py`, and likewise for columns.
    fn phase_size(&self) -> (usize, usize) {
        let (oh, ow) = self.output;
        let (kh, kw) = self.kernel;
        let (sh, sw) = self.stride;
        (oh + (kh - 1) / sh, ow + (kw - 1) / sw)
    }

    /// Values of one phase: its rows plus one spare row, read (and dropped) by the last
    /// output row's taps past the output width.
    fn phase_len(&self) -> usize {
        let (hq, wq) = self.phase_size();
        (hq + 1) * wq
    }
}

/// A depthwise convolution with constant weights and bias, then `clamp(lo, hi)`.
#[derive(Clone, Debug)]
pub(crate) struct DepthwiseConv {
    geometry: Geometry,
    /// `channels * kh * kw` taps, row-major per channel.
    weights: Arc<Vec<f32>>,
    bias: Arc<Vec<f32>>,
    /// `(lo, hi)`, infinite when there is no clamp on that side.
    clamp: (f32, f32),
    /// A 1x1 convolution producing this layer's input planes from the op's input (the
    /// expansion of an inverted-residual block); `None` when the op's input is the layer's.
    expand: Option<Expand>,
    /// `(lo, hi)` applied to the values entering the convolution (a clamp right before it,
    /// e.g. the ReLU6 after the stem or after the expansion); `None` when there is none.
    /// Padding stays zero: in the graph the clamp comes before the convolution pads its input.
    input_clamp: Option<(f32, f32)>,
}

/// Bitwise equality of the parameters (tract compares operators to merge equal nodes; `Eq`
/// needs a total relation, which bit patterns give).
impl PartialEq for DepthwiseConv {
    fn eq(&self, other: &Self) -> bool {
        let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        self.geometry == other.geometry
            && bits(&self.weights) == bits(&other.weights)
            && bits(&self.bias) == bits(&other.bias)
            && bits(&[self.clamp.0, self.clamp.1]) == bits(&[other.clamp.0, other.clamp.1])
            && self.input_clamp.map(|(lo, hi)| bits(&[lo, hi]))
                == other.input_clamp.map(|(lo, hi)| bits(&[lo, hi]))
            && match (&self.expand, &other.expand) {
                (None, None) => true,
                (Some(a), Some(b)) => {
                    a.in_channels == b.in_channels
                        && a.geometry == b.geometry
                        && bits(&a.weights) == bits(&b.weights)
                        && a.bias.as_deref().map(|b| bits(b)) == b.bias.as_deref().map(|b| bits(b))
                }
                _ => false,
            }
    }
}

impl Eq for DepthwiseConv {}

impl Op for DepthwiseConv {
    fn name(&self) -> StaticName {
        "SeasonlocDepthwiseConv".into()
    }

    fn info(&self) -> TractResult<Vec<String>> {
        let g = &self.geometry;
        Ok(vec![format!(
            "{} channels ({} in), {:?} -> {:?}, kernel {:?}, stride {:?}, pad {:?}, \
             input clamp {:?}, clamp {:?}",
            g.channels,
            self.in_channels(),
            g.input,
            g.output,
            g.kernel,
            g.stride,
            g.pad_before,
            self.input_clamp,
            self.clamp
        )])
    }

    fn validation(&self) -> Validation {
        Validation::Rounding
    }

    fn as_typed(&self) -> Option<&dyn TypedOp> {
        Some(self)
    }
}

impl EvalOp for DepthwiseConv {
    fn eval(&self, _ctx: &EvalContext, inputs: TVec<TValue>) -> TractResult<TVec<TValue>> {
        let input = inputs
            .first()
            .ok_or_else(|| format_err!("depthwise convolution without input"))?;
        let shape = self.output_shape(input.shape())?;
        // The output is written in place: going through a `Vec` and `ArrayD` would copy it
        // once more (tract copies an array into a fresh aligned buffer).
        // SAFETY: an f32 tensor of `shape`; `run_into` writes every one of its values (every
        // row of every output plane) before the tensor is handed to anyone.
        #[allow(unsafe_code)]
        let mut tensor = unsafe { Tensor::uninitialized::<f32>(&shape)? };
        self.run_into(
            input.try_as_plain_ram()?.as_slice::<f32>()?,
            tensor.try_as_plain_ram_mut()?.as_slice_mut::<f32>()?,
        );
        Ok(tvec!(tensor.into_tvalue()))
    }

    fn eval_out_of_plan(&self, inputs: TVec<TValue>) -> TractResult<Option<TVec<TValue>>> {
        Ok(Some(EvalOp::eval(
            self,
            &EvalContext::out_of_plan(),
            inputs,
        )?))
    }
}

impl TypedOp for DepthwiseConv {
    fn as_op(&self) -> &dyn Op {
        self
    }

    fn as_op_mut(&mut self) -> &mut dyn Op {
        self
    }

    fn output_facts(&self, inputs: &[&TypedFact]) -> TractResult<TVec<TypedFact>> {
        let fact = inputs
            .first()
            .ok_or_else(|| format_err!("depthwise convolution without input"))?;
        ensure!(fact.datum_type == f32::datum_type());
        let dims: Vec<usize> = fact
            .shape
            .iter()
            .map(|d| d.to_usize().map_err(TractError::from))
            .collect::<TractResult<_>>()?;
        Ok(tvec!(f32::fact(self.output_shape(&dims)?)))
    }
}

impl DepthwiseConv {
    /// Channels of the op's input: the expansion's inputs, or the layer's channels.
    fn in_channels(&self) -> usize {
        self.expand
            .as_ref()
            .map_or(self.geometry.channels, |e| e.in_channels)
    }

    /// The op's input plane: the front convolution's, or the layer's.
    fn in_plane(&self) -> (usize, usize) {
        self.expand
            .as_ref()
            .map_or(self.geometry.input, |e| e.geometry.input)
    }

    /// `[.., c, oh, ow]` for an input of shape `[.., in_channels, h, w]`.
    fn output_shape(&self, input: &[usize]) -> TractResult<Vec<usize>> {
        let g = &self.geometry;
        let rank = input.len();
        let k = self.in_channels();
        let (h, w) = self.in_plane();
        ensure!(
            rank >= 3 && input[rank - 3..] == [k, h, w],
            "depthwise convolution built for [.., {k}, {h}, {w}] got {input:?}"
        );
        let mut shape = input.to_vec();
        shape[rank - 3] = g.channels;
        shape[rank - 2] = g.output.0;
        shape[rank - 1] = g.output.1;
        Ok(shape)
    }

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
    fn run_into(&self, input: &[f32], output: &mut [f32]) {
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

impl Expand {
    /// A 1x1 convolution with stride 1 and no padding: its input planes are read as they are.
    fn is_pointwise(&self) -> bool {
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
fn expand_planes<'a>(
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
    if taps % 9 == 0 {
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
    let (even, odd) = if pl % 2 == 0 {
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
