//! The graph rewrite that puts [`DepthwiseConv`] into a loaded model: finds tract's depthwise
//! convolutions it can run, takes in the clamps (ReLU6) right before and after each and, on
//! large planes, the convolution in front of it (a 1x1 expansion `EinSum` or a group-1 `Conv`
//! behind a zero `Pad`), reads their constant weights, and patches the graph. Kept apart from
//! the operator and its kernels: this half only reads and rewires tract's graph.

use std::sync::Arc;

use tract_onnx::prelude::*;
use tract_onnx::tract_core::ops::array::{Pad, PadMode};
use tract_onnx::tract_core::ops::binary::TypedBinOp;
use tract_onnx::tract_core::ops::cnn::{Conv, KernelFormat};
use tract_onnx::tract_core::ops::einsum::EinSum;
use tract_onnx::tract_core::ops::nn::DataFormat;

use super::{DepthwiseConv, Expand, Geometry, EXPAND_MIN_PLANE};

/// Replaces every depthwise convolution of `model` that [`DepthwiseConv`] can run (and the
/// `Max`/`Min` with a constant that directly follow it or feed only it) by a
/// [`DepthwiseConv`], taking in the convolution in front of it on large planes; returns how
/// many depthwise layers and how many of those with a front convolution. `model` must be typed
/// and decluttered (tract's `Conv` ops, 1x1 convolutions as `EinSum`, constants folded).
pub(crate) fn rewrite(model: &mut TypedModel) -> TractResult<(usize, usize)> {
    let convs: Vec<usize> = model
        .nodes()
        .iter()
        .filter(|n| n.op_is::<Conv>())
        .map(|n| n.id)
        .collect();
    let (mut count, mut fronts) = (0, 0);
    for id in convs {
        let Some((op, source, last)) = replacement(model, id)? else {
            continue;
        };
        fronts += usize::from(op.expand.is_some());
        let node = model.node(id);
        let mut patch = TypedModelPatch::new(format!("depthwise {}", node.name));
        let input = patch.tap_model(model, source)?;
        let wired = patch.wire_node(format!("{}.depthwise", node.name), op, &[input])?;
        patch.shunt_outside(model, last, wired[0])?;
        patch.apply(model)?;
        count += 1;
    }
    if count > 0 {
        model.compact()?;
    }
    Ok((count, fronts))
}

/// A float 2-D convolution in the layouts [`DepthwiseConv`] and [`Expand`] read directly: not
/// quantised, OIHW kernel, NCHW/CHW data, no dilation.
fn plain_2d(conv: &Conv) -> bool {
    let spec = &conv.pool_spec;
    conv.q_params.is_none()
        && conv.kernel_fmt == KernelFormat::OIHW
        && matches!(spec.data_format, DataFormat::NCHW | DataFormat::CHW)
        && spec.kernel_shape.len() == 2
        && spec.dilations().iter().all(|&d| d == 1)
}

/// The concrete shape of `outlet` when it is `f32` planes with `channels` channels
/// (`[.., channels, h, w]`), `None` otherwise.
fn f32_planes(
    model: &TypedModel,
    outlet: OutletId,
    channels: usize,
) -> TractResult<Option<TVec<usize>>> {
    let fact = model.outlet_fact(outlet)?;
    let Some(dims) = fact.shape.as_concrete() else {
        return Ok(None);
    };
    let r = dims.len();
    let planes = fact.datum_type == f32::datum_type() && r >= 3 && dims[r - 3] == channels;
    Ok(planes.then(|| dims.into()))
}

/// The operator replacing node `id`, the outlet it reads (the conv's input, or the input of
/// the clamps fused before it) and the outlet it stands for (the conv's, or the last fused
/// clamp's), or `None` when `id` is not a depthwise convolution [`DepthwiseConv`] runs.
fn replacement(
    model: &TypedModel,
    id: usize,
) -> TractResult<Option<(DepthwiseConv, OutletId, OutletId)>> {
    let node = model.node(id);
    let Some(conv) = node.op_as::<Conv>() else {
        return Ok(None);
    };
    let spec = &conv.pool_spec;
    let channels = spec.input_channels;
    let plain = plain_2d(conv)
        && conv.group == channels
        && spec.output_channels == channels
        && node.inputs.len() == 3;
    if !plain {
        return Ok(None);
    }
    let Some(dims) = f32_planes(model, node.inputs[0], channels)? else {
        return Ok(None);
    };
    let (h, w) = (dims[dims.len() - 2], dims[dims.len() - 1]);
    let (kh, kw) = (spec.kernel_shape[0], spec.kernel_shape[1]);
    let strides = spec.strides();
    let padding = spec.computed_padding(&[h, w]);
    let geometry = Geometry {
        channels,
        input: (h, w),
        output: (padding[0].convoluted, padding[1].convoluted),
        kernel: (kh, kw),
        stride: (strides[0], strides[1]),
        pad_before: (padding[0].pad_before, padding[1].pad_before),
    };
    let out_fact = model.outlet_fact(OutletId::new(id, 0))?;
    let out_dims = out_fact.shape.as_concrete();
    if geometry.stride.0 == 0
        || geometry.stride.1 == 0
        || out_dims.is_none_or(|d| d[d.len() - 2..] != [geometry.output.0, geometry.output.1])
    {
        return Ok(None);
    }
    let Some(weights) = const_f32(model, node.inputs[1], channels * kh * kw)? else {
        return Ok(None);
    };
    let Some(bias) = const_bias(model, node.inputs[2], channels)? else {
        return Ok(None);
    };
    let mut op = DepthwiseConv {
        geometry,
        weights: Arc::new(weights),
        bias: Arc::new(bias),
        clamp: (f32::NEG_INFINITY, f32::INFINITY),
        expand: None,
        input_clamp: None,
    };
    // A `Max(x, lo)` then `Min(x, hi)` (ReLU6) feeding only this convolution, or either alone
    // (walked backwards from the input: the `Min` first).
    let mut source = node.inputs[0];
    for (bound, is_lower) in [("Min", false), ("Max", true)] {
        let Some((input, value)) = clamp_before(model, source, bound)? else {
            continue;
        };
        let (lo, hi) = op
            .input_clamp
            .get_or_insert((f32::NEG_INFINITY, f32::INFINITY));
        if is_lower {
            *lo = value;
        } else {
            *hi = value;
        }
        source = input;
    }
    if h * w >= EXPAND_MIN_PLANE {
        let front = match expansion(model, source, channels)? {
            Some(found) => Some(found),
            None => front_conv(model, source, channels)?,
        };
        if let Some((input, expand)) = front {
            if expand.geometry.output == (h, w) {
                op.expand = Some(expand);
                source = input;
            }
        }
    }
    let mut last = OutletId::new(id, 0);
    // A following `Max(x, lo)` then `Min(x, hi)` (ReLU6), or either alone.
    for (bound, is_lower) in [("Max", true), ("Min", false)] {
        let Some((next, value)) = clamp_after(model, last, bound)? else {
            continue;
        };
        if is_lower {
            op.clamp.0 = value;
        } else {
            op.clamp.1 = value;
        }
        last = OutletId::new(next, 0);
    }
    Ok(Some((op, source, last)))
}

/// When `outlet` is a 1x1 convolution with `channels` outputs as tract's decluttering leaves
/// it (an `EinSum` `..k..,ck->..c..` of the NCHW input with constant `[channels, k]` weights,
/// then, unless the bias is zero, an `Add` of a constant per-channel bias), each node used
/// only by the next: the convolution's input and the [`Expand`] computing it.
fn expansion(
    model: &TypedModel,
    outlet: OutletId,
    channels: usize,
) -> TractResult<Option<(OutletId, Expand)>> {
    if !only_use(model, outlet)? {
        return Ok(None);
    }
    let mut node = model.node(outlet.node);
    let mut bias = None;
    if node.op_is::<TypedBinOp>() && node.op().name() == "Add" && node.inputs.len() == 2 {
        let shape = model.outlet_fact(outlet)?.shape.clone();
        let rank = shape.rank();
        let per_channel = |o: OutletId| -> TractResult<Option<Vec<f32>>> {
            let fact = model.outlet_fact(o)?;
            let Some(dims) = fact.shape.as_concrete() else {
                return Ok(None);
            };
            let broadcast = dims.len() >= 3
                && dims.len() <= rank
                && dims
                    .iter()
                    .rev()
                    .enumerate()
                    .all(|(i, &d)| d == if i == 2 { channels } else { 1 });
            if !broadcast {
                return Ok(None);
            }
            const_f32(model, o, channels)
        };
        for slot in 0..2 {
            let (data, konst) = (node.inputs[slot], node.inputs[1 - slot]);
            if let Some(values) = per_channel(konst)? {
                if model.outlet_fact(data)?.shape == shape && only_use(model, data)? {
                    bias = Some(values);
                    node = model.node(data.node);
                    break;
                }
            }
        }
        if bias.is_none() {
            return Ok(None);
        }
    }
    let Some(einsum) = node.op_as::<EinSum>() else {
        return Ok(None);
    };
    if einsum.q_params.is_some()
        || einsum.operating_dt != f32::datum_type()
        || node.inputs.len() != 2
    {
        return Ok(None);
    }
    let (ins, outs) = einsum.axes.to_strs();
    let chars = |s: &String| s.chars().collect::<Vec<char>>();
    let ([x, w], [y]) = (&ins[..], &outs[..]) else {
        return Ok(None);
    };
    let (x, w, y) = (chars(x), chars(w), chars(y));
    let r = x.len();
    // `x` = `..k..` (channel axis third from last), `w` = `ck`, `y` = `x` with `k` -> `c`.
    let matmul = r >= 3
        && w.len() == 2
        && y.len() == r
        && w[1] == x[r - 3]
        && y[r - 3] == w[0]
        && !x.contains(&w[0])
        && (0..r).all(|i| i == r - 3 || y[i] == x[i])
        && (0..r).all(|i| x[i + 1..].iter().all(|c| *c != x[i]));
    let fact = model.outlet_fact(node.inputs[0])?;
    let Some(dims) = fact.shape.as_concrete() else {
        return Ok(None);
    };
    if !matmul || fact.datum_type != f32::datum_type() || dims.len() != r {
        return Ok(None);
    }
    let k = dims[r - 3];
    let Some(weights) = const_f32(model, node.inputs[1], channels * k)? else {
        return Ok(None);
    };
    if model.outlet_fact(node.inputs[1])?.shape.as_concrete() != Some(&[channels, k][..]) {
        return Ok(None);
    }
    let (h, w) = (dims[r - 2], dims[r - 1]);
    let expand = Expand {
        in_channels: k,
        geometry: Geometry {
            channels: k,
            input: (h, w),
            output: (h, w),
            kernel: (1, 1),
            stride: (1, 1),
            pad_before: (0, 0),
        },
        weights: Arc::new(weights),
        bias: bias.map(Arc::new),
    };
    Ok(Some((node.inputs[0], expand)))
}

/// When `outlet` is a float convolution with `channels` outputs (group 1, dilation 1, constant
/// weights and bias, NCHW), possibly after a zero `Pad` of its spatial axes, each node used only
/// by the next: its input and the [`Expand`] computing it.
fn front_conv(
    model: &TypedModel,
    outlet: OutletId,
    channels: usize,
) -> TractResult<Option<(OutletId, Expand)>> {
    let node = model.node(outlet.node);
    let Some(conv) = node.op_as::<Conv>() else {
        return Ok(None);
    };
    if !only_use(model, outlet)? || node.inputs.len() != 3 {
        return Ok(None);
    }
    let spec = &conv.pool_spec;
    let k = spec.input_channels;
    let plain = plain_2d(conv)
        && spec.strides().iter().all(|&s| s > 0)
        && conv.group == 1
        && spec.output_channels == channels;
    if !plain {
        return Ok(None);
    }
    let mut input = node.inputs[0];
    let Some(dims) = f32_planes(model, input, k)? else {
        return Ok(None);
    };
    let r = dims.len();
    let padded = (dims[r - 2], dims[r - 1]);
    let padding = spec.computed_padding(&[padded.0, padded.1]);
    let mut pad_before = (padding[0].pad_before, padding[1].pad_before);
    let mut plane = padded;
    // A zero `Pad` of only the two spatial axes in front (TF exports pad stride-2 "SAME"
    // convolutions explicitly): the phases pad with zeros anyway.
    let producer = model.node(input.node);
    if let Some(pad) = producer.op_as::<Pad>() {
        let zero = match &pad.mode {
            PadMode::Constant(v) => {
                v.len() == 1
                    && v.datum_type() == f32::datum_type()
                    && v.try_as_plain_ram()?.as_slice::<f32>()?[0].to_bits() == 0
            }
            _ => false,
        };
        let spatial_only =
            pad.pads.len() == r && pad.pads[..r - 2].iter().all(|&(a, b)| a == 0 && b == 0);
        if zero && spatial_only && only_use(model, input)? && producer.inputs.len() == 1 {
            let (top, bottom) = pad.pads[r - 2];
            let (left, right) = pad.pads[r - 1];
            let Some(src) = model.outlet_fact(producer.inputs[0])?.shape.as_concrete() else {
                return Ok(None);
            };
            if src.len() != r || (src[r - 2] + top + bottom, src[r - 1] + left + right) != padded {
                return Ok(None);
            }
            pad_before = (pad_before.0 + top, pad_before.1 + left);
            plane = (src[r - 2], src[r - 1]);
            input = producer.inputs[0];
        }
    }
    let (kh, kw) = (spec.kernel_shape[0], spec.kernel_shape[1]);
    let strides = spec.strides();
    let geometry = Geometry {
        channels: k,
        input: plane,
        output: (padding[0].convoluted, padding[1].convoluted),
        kernel: (kh, kw),
        stride: (strides[0], strides[1]),
        pad_before,
    };
    let Some(weights) = const_f32(model, node.inputs[1], channels * k * kh * kw)? else {
        return Ok(None);
    };
    let Some(bias) = const_bias(model, node.inputs[2], channels)? else {
        return Ok(None);
    };
    let expand = Expand {
        in_channels: k,
        geometry,
        weights: Arc::new(weights),
        bias: Some(Arc::new(bias)),
    };
    Ok(Some((input, expand)))
}

/// Whether `o` is its node's first output, feeds exactly one node and is not a model output:
/// the condition for folding its node into the one that follows.
fn only_use(model: &TypedModel, o: OutletId) -> TractResult<bool> {
    Ok(o.slot == 0
        && model.outlet_successors(o).len() == 1
        && !model.output_outlets()?.contains(&o))
}

/// When `outlet` is the output of a `bound` (`Max` or `Min`) with a constant scalar, used only
/// by the one node that follows and of the shape of its other input: that input and the
/// constant.
fn clamp_before(
    model: &TypedModel,
    outlet: OutletId,
    bound: &str,
) -> TractResult<Option<(OutletId, f32)>> {
    let node = model.node(outlet.node);
    if !node.op_is::<TypedBinOp>()
        || node.op().name() != bound
        || node.inputs.len() != 2
        || !only_use(model, outlet)?
    {
        return Ok(None);
    }
    for slot in 0..2 {
        let Some(value) = const_f32(model, node.inputs[slot], 1)? else {
            continue;
        };
        let input = node.inputs[1 - slot];
        let same_shape = model.outlet_fact(input)?.shape == model.outlet_fact(outlet)?.shape;
        if same_shape && !value[0].is_nan() {
            return Ok(Some((input, value[0])));
        }
    }
    Ok(None)
}

/// The node applying `bound` (`Max` or `Min`) with a constant scalar to `outlet`, when it is
/// the outlet's only use and keeps its shape; with that constant.
fn clamp_after(
    model: &TypedModel,
    outlet: OutletId,
    bound: &str,
) -> TractResult<Option<(usize, f32)>> {
    if model.output_outlets()?.contains(&outlet) {
        return Ok(None);
    }
    let [inlet] = model.outlet_successors(outlet) else {
        return Ok(None);
    };
    let next = model.node(inlet.node);
    if !next.op_is::<TypedBinOp>() || next.op().name() != bound || next.inputs.len() != 2 {
        return Ok(None);
    }
    let other = next.inputs[1 - inlet.slot];
    let Some(value) = const_f32(model, other, 1)? else {
        return Ok(None);
    };
    let same_shape =
        model.outlet_fact(OutletId::new(next.id, 0))?.shape == model.outlet_fact(outlet)?.shape;
    if !same_shape || value[0].is_nan() {
        return Ok(None);
    }
    Ok(Some((next.id, value[0])))
}

/// A convolution's constant `f32` bias at `outlet` for `channels` outputs: one value per
/// channel, or one value for all of them (broadcast here).
fn const_bias(
    model: &TypedModel,
    outlet: OutletId,
    channels: usize,
) -> TractResult<Option<Vec<f32>>> {
    Ok(match const_f32(model, outlet, channels)? {
        Some(bias) => Some(bias),
        None => const_f32(model, outlet, 1)?.map(|one| vec![one[0]; channels]),
    })
}

/// The constant `f32` values at `outlet` when there are exactly `len` of them.
fn const_f32(model: &TypedModel, outlet: OutletId, len: usize) -> TractResult<Option<Vec<f32>>> {
    let fact = model.outlet_fact(outlet)?;
    let Some(konst) = &fact.konst else {
        return Ok(None);
    };
    if konst.datum_type() != f32::datum_type() || konst.len() != len {
        return Ok(None);
    }
    Ok(Some(konst.try_as_plain_ram()?.as_slice::<f32>()?.to_vec()))
}
