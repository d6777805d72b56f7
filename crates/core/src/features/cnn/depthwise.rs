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
//!
//! Code: this file is the operator as tract sees it (parameters, shapes, facts, equality);
//! `depthwise/kernels.rs` its arithmetic, `depthwise/front.rs` the front convolution's, and
//! `depthwise/rewrite.rs` the graph rewrite that puts it in place.

use std::sync::Arc;

use tract_onnx::prelude::*;
use tract_onnx::tract_core::internal::{
    ensure, format_err, DimLike, EvalOp, Op, StaticName, Validation,
};
use tract_onnx::tract_core::plan::EvalContext;

mod front;
mod kernels;
mod rewrite;
pub(crate) use rewrite::rewrite;

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
}
