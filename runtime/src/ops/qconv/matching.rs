//! Which tract nodes become a [`PackedQConv`]: quantised `Conv`s of stride 1 or 2, the
//! `EinSum`s tract makes of 1x1 convolutions (channels first or last), and the matrix products
//! by constant weights of HMG's linear layers; and the requantisation scales, bit for bit as
//! tract's optimised plan computes them.

use std::sync::Arc;

use tract_nnef::internal::*;
use tract_nnef::tract_core::ops::cnn::{Conv, KernelFormat};
use tract_nnef::tract_core::ops::einsum::EinSum;
use tract_nnef::tract_core::ops::nn::DataFormat;

use super::super::qconv_kernel::exact_fits;
use super::super::{all_ones, pads_2d, ConvShape};
use super::{has_words_path, products_here, Batch, PackedQConv, Product, QuantParams};

/// A quantised layer's weight scales as its graph holds them: one (per-tensor weights) or one
/// per output channel (`co`); `None` if not constant or of another length.
fn weight_scales(fact: &TypedFact, co: usize) -> TractResult<Option<Vec<f32>>> {
    Ok(konst_values::<f32>(fact, 1)?.or(konst_values::<f32>(fact, co)?))
}

/// Each of `co` output channels' requantisation scale `x_scale · k_scale / y_scale`, bit for
/// bit as tract's optimised plan has it (one unit in the last place moves a sum across a half,
/// and a byte). tract wires the product and the quotient of the scales while it optimises and
/// folds an op at once only where each of its constant inputs holds fewer than 16 values; a
/// quotient left standing is turned into a product with the reciprocal by the declutter pass
/// that comes before the constants are folded. So one weight scale, or fewer than 16: a true
/// division, `x · k / y`; 16 and more: `(k · x) · (1 / y)` (NanoTrack's depthwise and head
/// layers: a few channels of each a unit apart, one sum in block 2 on a half).
pub(in crate::ops) fn requant_scales(x_scale: f32, k_scale: &[f32], y_scale: f32, co: usize) -> Vec<f32> {
    match k_scale {
        [k] => vec![x_scale * k / y_scale; co],
        _ if k_scale.len() < EAGER_FOLD_VOLUME => k_scale.iter().map(|k| x_scale * k / y_scale).collect(),
        _ => k_scale.iter().map(|k| (k * x_scale) * (1.0 / y_scale)).collect(),
    }
}

/// tract's `TypedModel::wire_node` evaluates an op at once when each of its constant inputs
/// has fewer values than this.
const EAGER_FOLD_VOLUME: usize = 16;

/// A scalar (or a vector of `n`) constant as f32 / i32 values.
pub(in crate::ops) fn konst_values<T: Datum + Copy>(fact: &TypedFact, n: usize) -> TractResult<Option<Vec<T>>> {
    let Some(k) = &fact.konst else { return Ok(None) };
    let k = k.cast_to::<T>()?;
    let k = k.try_as_plain_ram()?;
    let v = k.as_slice::<T>()?;
    Ok(match v.len() {
        1 => Some(vec![v[0]; n]),
        l if l == n => Some(v.to_vec()),
        _ => None,
    })
}

/// The [`PackedQConv`] for `node` if it is a quantised convolution with u8 input and output,
/// constant i8 weights of zero point 0 and constant quantisation parameters (tract's `Conv` of
/// stride 1 or 2, or the `EinSum` tract makes of a 1x1 convolution: HMG's patch embeddings), and
/// the CPU has AVX-512 VNNI, AVX2 or the aarch64 dot product.
pub(crate) fn packed_q(model: &TypedModel, node: &TypedNode) -> TractResult<Option<PackedQConv>> {
    if !has_words_path() || !super::super::own_int8_operators() {
        return Ok(None);
    }
    let facts = model.node_input_facts(node.id)?;
    let conv = conv_shape(node, &facts).map(|s| (s, Batch::Kept)).or_else(|| pointwise_shape(node, &facts));
    let product = || matmul_shape(node, &facts).or_else(|| channels_last_shape(node, &facts));
    let (shape, batch, matmul) = match (conv, product()) {
        (Some((shape, batch)), _) => (shape, batch, None),
        (None, Some((shape, product, io))) => (shape, Batch::None, Some((product, io))),
        (None, None) => return Ok(None),
    };
    // Both ops take x, the weights, the bias, then x0, x_scale, w0, w_scale, y0, y_scale.
    let out_dt = node.outputs[0].fact.datum_type;
    let plain = facts.len() == 9
        && out_dt.unquantized() == u8::datum_type()
        && facts[0].datum_type.unquantized() == u8::datum_type()
        && facts[1].datum_type.unquantized() == i8::datum_type();
    if !plain {
        return Ok(None);
    }
    let co = shape.co;
    let (Some(kernel), Some(bias)) = (&facts[1].konst, konst_values::<i32>(facts[2], co)?) else { return Ok(None) };
    let Some(q) = quant_params(&facts, co)? else { return Ok(None) };
    if kernel.len() != co * shape.ci * shape.kh * shape.kw {
        return Ok(None);
    }
    let kernel = kernel.try_as_plain_ram()?;
    // SAFETY: the kernel's datum type is i8, possibly with quantisation parameters (checked).
    let kernel = unsafe { kernel.as_slice_unchecked::<i8>() };
    // A product's weights `K x N` are the convolution's `N x K` transposed.
    let transposed: Vec<i8>;
    let kernel = match matmul {
        Some((_, true)) => {
            transposed = (0..co).flat_map(|o| (0..shape.ci).map(move |c| kernel[c * co + o])).collect();
            &transposed[..]
        }
        _ => kernel,
    };
    let bound = sum_bound(kernel, &bias, shape.ci * shape.kh * shape.kw);
    let op = PackedQConv::new(shape, kernel, &bias, q, out_dt)?;
    if op.exact && !exact_fits(op.scale[0], bound) {
        return Ok(None);
    }
    let matmul = matmul.map(|(product, _)| Arc::new(product));
    Ok(Some(PackedQConv { batch, matmul, ..op }))
}

/// The quantisation parameters of a quantised `Conv` or `EinSum` of `co` output channels, from
/// its inputs after the data, the weights and the bias (x0, x_scale, w0, w_scale, y0, y_scale),
/// if each is constant, the zero points are bytes and the weights' zero point is 0.
pub(in crate::ops) fn quant_params(facts: &[&TypedFact], co: usize) -> TractResult<Option<QuantParams>> {
    let params = (
        konst_values::<i32>(facts[3], 1)?,
        konst_values::<f32>(facts[4], 1)?,
        konst_values::<i32>(facts[5], co)?,
        weight_scales(facts[6], co)?,
        konst_values::<i32>(facts[7], 1)?,
        konst_values::<f32>(facts[8], 1)?,
    );
    let (Some(x0), Some(x_scale), Some(k0), Some(k_scale), Some(y0), Some(y_scale)) = params else { return Ok(None) };
    let (Ok(x0), Ok(y0)) = (u8::try_from(x0[0]), u8::try_from(y0[0])) else { return Ok(None) };
    if k0.iter().any(|&z| z != 0) {
        return Ok(None);
    }
    Ok(Some(QuantParams { x0, x_scale: x_scale[0], k_scale, y0, y_scale: y_scale[0] }))
}

/// The largest magnitude a layer's sums `Σ (x − x0)·w[o] + bias[o]` can take (`|x − x0| ≤
/// 255`), from its weights (`taps` per output channel) and biases.
pub(in crate::ops) fn sum_bound(kernel: &[i8], bias: &[i32], taps: usize) -> i64 {
    let row = |(w, &b): (&[i8], &i32)| 255 * w.iter().map(|&v| (v as i64).abs()).sum::<i64>() + (b as i64).abs();
    kernel.chunks(taps.max(1)).zip(bias).map(row).max().unwrap_or(0)
}

/// The shape of a quantised NCHW `Conv` with OIHW weights, one group, stride 1 or 2 and no
/// dilation, on a concrete input.
fn conv_shape(node: &TypedNode, facts: &[&TypedFact]) -> Option<ConvShape> {
    let conv = node.op_as::<Conv>()?;
    let ps = &conv.pool_spec;
    let plain = conv.q_params.is_some()
        && conv.kernel_fmt == KernelFormat::OIHW
        && ps.data_format == DataFormat::NCHW
        && ps.kernel_shape.len() == 2
        && conv.group == 1
        && all_ones(&ps.dilations);
    if !plain {
        return None;
    }
    let stride = match ps.strides.as_deref() {
        None | Some([1, 1]) => 1,
        Some([2, 2]) => 2,
        _ => return None,
    };
    let pad = pads_2d(&ps.padding)?;
    let &[_, ci, h, w] = facts.first()?.shape.as_concrete()? else { return None };
    let (kh, kw) = (ps.kernel_shape[0], ps.kernel_shape[1]);
    Some(ConvShape { ci, h, w, co: ps.output_channels, kh, kw, pad, stride })
}

/// The shape of the quantised `EinSum` tract makes of a 1x1 convolution, `NIHW,OI,O->NOHW`
/// (whatever its axis letters), with constant `[O, I]` weights and an i32 bias, as a 1x1
/// [`ConvShape`]. (NanoTrack's pointwise layers come as `IHW,OI,O->OHW`, without the batch
/// axis, and the first after its squeeze-excitation as `NIHW,OI,O->OHW`, the axis dropped on
/// the way out.)
fn pointwise_shape(node: &TypedNode, facts: &[&TypedFact]) -> Option<(ConvShape, Batch)> {
    let (terms, out) = q_einsum_terms(node)?;
    let [x, w, _, ..] = terms.as_slice() else { return None };
    // NCHW, or CHW (a batch axis of 1 dropped, as in NanoTrack's graphs): `nihw,oi->nohw`.
    let batch = match (x.len(), out.len()) {
        (4, 4) if out[0] == x[0] => Batch::Kept,
        (4, 3) if !out.contains(&x[0]) => Batch::Dropped,
        (3, 3) => Batch::None,
        _ => return None,
    };
    let (c, hw, ohw) = match batch {
        Batch::Kept => (1, 2, 2),
        Batch::Dropped => (1, 2, 1),
        Batch::None => (0, 1, 1),
    };
    let pointwise =
        w.len() == 2 && out[ohw - 1] == w[0] && out[ohw..] == x[hw..] && w[1] == x[c] && !out.contains(&x[c]);
    if !pointwise || !per_output_channel(&terms, w[0], facts) {
        return None;
    }
    let dims = facts.first()?.shape.as_concrete()?;
    let (ci, h, w) = match (batch, dims) {
        (Batch::Kept, &[_, ci, h, w]) | (Batch::Dropped, &[1, ci, h, w]) | (Batch::None, &[ci, h, w]) => (ci, h, w),
        _ => return None,
    };
    let &[co, wi] = facts.get(1)?.konst.as_ref()?.shape() else { return None };
    (wi == ci).then_some((ConvShape { ci, h, w, co, kh: 1, kw: 1, pad: [0; 4], stride: 1 }, batch))
}

/// The shape of the quantised `EinSum` of a 1x1 convolution with its channels last on either
/// side, as tract makes NanoTrack's pointwise layers on aarch64 (its declutter moves the
/// depthwise layers' channels last there, and the pointwise ones between them follow):
/// `HWI,OI,O->OHW`, `IHW,OI,O->HWO` or `HWI,OI,O->HWO` (whatever the letters), constant `[O, I]`
/// weights and an i32 bias: a product of `K = I` channels over `M = H·W` positions, read as
/// rows of channels where they are last and written so where they are last out.
/// (`IHW,OI,O->OHW` is [`pointwise_shape`]'s.)
fn channels_last_shape(node: &TypedNode, facts: &[&TypedFact]) -> Option<(ConvShape, Product, bool)> {
    let (terms, out) = q_einsum_terms(node)?;
    let [x, w, _, ..] = terms.as_slice() else { return None };
    let (&[x0, x1, x2], &[o0, o1, o2], &[n, k]) = (x.as_slice(), out.as_slice(), w.as_slice()) else { return None };
    let (in_last, out_last) = (x2 == k, o2 == n);
    let (hw_in, hw_out) = (if in_last { [x0, x1] } else { [x1, x2] }, if out_last { [o0, o1] } else { [o1, o2] });
    let fits = (in_last || x0 == k)
        && (out_last || o0 == n)
        && (in_last || out_last)
        && hw_in == hw_out
        && !hw_in.contains(&k)
        && !hw_in.contains(&n)
        && !out.contains(&k)
        && !x.contains(&n);
    if !fits || !per_output_channel(&terms, n, facts) {
        return None;
    }
    let (input, output) = concrete_io(node, facts)?;
    let (ci, positions) = if in_last { (input[2], input[0] * input[1]) } else { (input[0], input[1] * input[2]) };
    let &[co, wi] = facts.get(1)?.konst.as_ref()?.shape() else { return None };
    let fits = wi == ci && positions > 0 && output.iter().product::<usize>() == co * positions;
    fits.then_some((
        ConvShape { ci, h: 1, w: positions, co, kh: 1, kw: 1, pad: [0; 4], stride: 1 },
        Product { input, output, in_last, out_last },
        false,
    ))
}

/// Whether a quantised `EinSum`'s terms after the data and the weights (the bias, then the
/// quantisation parameters) are each absent or per output channel (`n`), the bias i32.
fn per_output_channel(terms: &[Vec<char>], n: char, facts: &[&TypedFact]) -> bool {
    terms[2..].iter().all(|t| t.is_empty() || t.as_slice() == [n])
        && facts.get(2).is_some_and(|f| f.datum_type == i32::datum_type())
}

/// The concrete shapes of a node's data input and of its output.
fn concrete_io(node: &TypedNode, facts: &[&TypedFact]) -> Option<(TVec<usize>, TVec<usize>)> {
    Some((facts.first()?.shape.as_concrete()?.into(), node.outputs[0].fact.shape.as_concrete()?.into()))
}

/// The axis letters of a quantised `EinSum`'s input terms and of its output.
fn q_einsum_terms(node: &TypedNode) -> Option<(Vec<Vec<char>>, Vec<char>)> {
    let einsum = node.op_as::<EinSum>()?;
    einsum.q_params?;
    let expr = einsum.axes.to_string();
    let (inputs, output) = expr.split_once("->")?;
    Some((inputs.split(',').map(|t| t.chars().collect()).collect(), output.chars().collect()))
}

/// The shape of a quantised `EinSum` that is a matrix product by constant weights, HMG's
/// linear layers (`akm,kn->mn`, `mk,kn->anm`, whatever the letters: the input `[.., K, M]` or
/// `[.., M, K]`, the weights `K x N` or `N x K`, the output `[.., M, N]` or `[.., N, M]`, a
/// leading axis of 1 allowed on either side), as a 1x1 [`ConvShape`] of `K` channels on a
/// 1 x `M` map, with its layouts and whether the weights are `K x N`. Where [`products_here`]:
/// on the AVX2 words path tract's integer kernel (`avx2_mmm_i32_8x8`) ran PRL-Track's eight
/// such products at 1.3 GOP/s on an AMD EPYC, 830 of a 1000 ms int8 step; on VNNI (AMX off)
/// its `avx512vnni_mmm_i32_16x16` with its packing took 4.8 ms a step on one thread and 2.7
/// on two, this form 2.8-2.9 and 1.7 (tokens-first rows read as words, the output written
/// tokens first by the tiles: 2026-12-06). On SDOT (instructions counted under qemu, cycles
/// modelled for a Cortex-A78) this form took 183 ms per PRL-Track int8 step against 178 with
/// tract's `arm64simd_mmm_i32_8x8_dot` on 2026-12-05, and 175.5 against 176.4 once the rows
/// were read as words and the output transposed in 8x8-byte squares (2026-12-06).
fn matmul_shape(node: &TypedNode, facts: &[&TypedFact]) -> Option<(ConvShape, Product, bool)> {
    if !products_here() {
        return None;
    }
    let (terms, out) = q_einsum_terms(node)?;
    let [x, w, _, ..] = terms.as_slice() else { return None };
    let (xr, or) = (x.len(), out.len());
    if !(2..=3).contains(&xr) || !(2..=3).contains(&or) || w.len() != 2 {
        return None;
    }
    // k: summed (in x and w, not out); m: x's other last axis; n: w's other axis.
    let k = *x[xr - 2..].iter().find(|c| w.contains(c) && !out.contains(c))?;
    let m = *x[xr - 2..].iter().find(|&&c| c != k)?;
    let n = *w.iter().find(|&&c| c != k)?;
    let (in_last, out_last, io) = (x[xr - 1] == k, out[or - 1] == n, w[0] == k);
    // A leading axis is of size 1 (checked below) and in no other term.
    let lone = |c: char| !x.contains(&c) as usize + !w.contains(&c) as usize + !out.contains(&c) as usize >= 2;
    let product = m != n
        && out[or - 2..] == if out_last { [m, n] } else { [n, m] }
        && (xr == 2 || lone(x[0]))
        && (or == 2 || lone(out[0]));
    if !product || !per_output_channel(&terms, n, facts) {
        return None;
    }
    let (input, output) = concrete_io(node, facts)?;
    let (ci, positions) = if in_last { (input[xr - 1], input[xr - 2]) } else { (input[xr - 2], input[xr - 1]) };
    let &[w0, w1] = facts.get(1)?.konst.as_ref()?.shape() else { return None };
    let (wk, co) = if io { (w0, w1) } else { (w1, w0) };
    let fits = wk == ci
        && positions > 0
        && input[..xr - 2].iter().all(|&d| d == 1)
        && output[..or - 2].iter().all(|&d| d == 1)
        && output[or - 2..] == if out_last { [positions, co] } else { [co, positions] };
    fits.then_some((
        ConvShape { ci, h: 1, w: positions, co, kh: 1, kw: 1, pad: [0; 4], stride: 1 },
        Product { input, output, in_last, out_last },
        io,
    ))
}
