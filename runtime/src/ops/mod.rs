//! Operators of our own that tract runs in place of its generic ones where they are faster
//! here, put in by [`accelerate`] when a graph is loaded: the correlations with the template
//! ([`DepthwiseXCorr`]), convolutions ([`PackedConv`], stride 1 or 2, and [`DepthwiseConv`] for
//! depthwise ones with constant weights, and [`PackedQConv`] for int8
//! plans on CPUs with AVX-512 VNNI, on AMX tiles where there are some, or aarch64's dot product,
//! and [`DepthwiseQConv`] for their depthwise layers), max pooling
//! ([`ChannelMaxPool`]), pointwise convolutions with their bias and activation ([`PointwiseConv`]), HMG's attention ([`Attention`], fused; or [`AttnScores`], [`AttnMix`], [`RowSoftmax`]), layer
//! norms ([`LayerNormCore`]), linear layers ([`ConstMatMul`]) and broadcast products and sums
//! ([`BroadcastBinary`]), squeeze-excitation blocks ([`SqueezeExcite`]), and int8 plans' quantisation of activations
//! and back ([`QuantizeU8`], [`DequantizeU8`]). Plans
//! on disk keep tract's
//! standard operators, so the choice is made on the machine that runs the plan.

mod act;
mod attention;
mod attn_fused;
mod binary;
mod conv;
mod conv_kernel;
mod conv_lanes;
mod dwconv;
mod dwconv_hwc;
mod dwqconv;
#[cfg(target_arch = "x86_64")]
mod dwqconv_kernel;
#[cfg(target_arch = "aarch64")]
mod dwqconv_sdot;
mod matmul;
mod norm;
mod par;
mod permute;
mod pointwise;
mod pool;
mod qconv;
mod qconv_amx;
mod qconv_kernel;
mod qconv_lanes;
mod quant;
mod scratch;
mod se;
mod softmax;
mod winograd;
mod xcorr;
mod xcorr_kernel;

pub use attention::{AttnMix, AttnScores, RowSoftmax};
pub use attn_fused::Attention;
pub use binary::{Binary, BroadcastBinary};
pub use conv::{ConvShape, PackedConv};
pub use dwconv::DepthwiseConv;
pub use dwconv_hwc::DepthwiseConvHwc;
pub use dwqconv::DepthwiseQConv;
pub use matmul::ConstMatMul;
pub use norm::LayerNormCore;
pub use permute::Permute;
pub use pointwise::PointwiseConv;
pub use pool::ChannelMaxPool;
pub use qconv::PackedQConv;
pub use quant::{DequantizeU8, QuantizeU8};
pub use se::SqueezeExcite;
pub use winograd::WinogradConv;
pub use xcorr::DepthwiseXCorr;

use crate::Winograd;
use tract_nnef::internal::*;

use par::{par_chunks, par_for, serial_if_small, threads, SyncPtr, SERIAL_MACS, SHARE};
#[cfg(any(target_arch = "x86_64", target_arch = "aarch64"))]
use scratch::with_bytes;
use scratch::{output_tensor, output_tensor_written, unwritten_runs, with_padded, with_words};

/// Whether plans are loaded with the runtime's own operators: yes unless the environment
/// variable `PRL_OPS` is `tract` (tract's operators alone: what the runtime's own are measured
/// against, on any machine, the camera included).
pub fn own_operators() -> bool {
    static OWN: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
    *OWN.get_or_init(|| !std::env::var("PRL_OPS").is_ok_and(|v| v.trim().eq_ignore_ascii_case("tract")))
}

/// Whether the int8 convolutions and products are the runtime's own ([`PackedQConv`]): yes
/// unless `PRL_OPS` is `tract` or `tract-int8` (the runtime's float operators, tract's integer
/// products: the same bytes, since both requantise alike; to compare the two).
pub fn own_int8_operators() -> bool {
    static OWN: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
    *OWN.get_or_init(|| {
        own_operators() && !std::env::var("PRL_OPS").is_ok_and(|v| v.trim().eq_ignore_ascii_case("tract-int8"))
    })
}

/// How many nodes [`accelerate`] replaced.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Accelerated {
    /// Depthwise correlations made [`DepthwiseXCorr`].
    pub correlations: usize,
    /// Convolutions made [`PackedConv`] (or [`WinogradConv`]: 3x3 and 5x5 stride-1 ones where
    /// the [`Winograd`] choice asks for it).
    pub convolutions: usize,
    /// Depthwise convolutions with constant weights made [`DepthwiseConv`] (or
    /// [`DepthwiseConvHwc`] on channels-last data).
    pub depthwise: usize,
    /// Max pools made [`ChannelMaxPool`].
    pub pools: usize,
    /// Quantised (u8 x i8) convolutions made [`PackedQConv`] (or [`DepthwiseQConv`], one group
    /// per channel).
    pub int8_convolutions: usize,
    /// Attentions (scores, scale, softmax and mix) made [`Attention`]; products and
    /// softmaxes outside such a chain made [`AttnScores`], [`AttnMix`], [`RowSoftmax`].
    pub attention: usize,
    /// Layer norms (tract's centring and `RmsNorm`) made [`LayerNormCore`].
    pub norms: usize,
    /// f32 products with a constant operand made [`ConstMatMul`].
    pub matmuls: usize,
    /// Pointwise convolutions (channels-first einsums with constant weights, with the bias and
    /// activation after them) made [`PointwiseConv`].
    pub pointwise: usize,
    /// Broadcast f32 products and sums made [`BroadcastBinary`].
    pub broadcasts: usize,
    /// Quantisations of f32 activations to u8 and back made [`QuantizeU8`] and [`DequantizeU8`].
    pub quantizers: usize,
    /// Squeeze-excitation blocks (spatial mean, gate, per-channel product and the activation
    /// after it) made [`SqueezeExcite`].
    pub squeeze_excite: usize,
    /// Chains of axis moves made [`Permute`].
    pub permutes: usize,
}

/// [`accelerate_with`] the convolutions that `PRL_WINOGRAD` asks for as Winograd's (none when
/// it is unset).
pub fn accelerate(model: &mut TypedModel) -> TractResult<Accelerated> {
    accelerate_with(model, Winograd::from_env().unwrap_or_default())
}

/// Replace the nodes of a typed `model` that have a faster operator here (names kept), the
/// convolutions `winograd` names as [`WinogradConv`]; call it before tract optimises the model.
pub fn accelerate_with(model: &mut TypedModel, winograd: Winograd) -> TractResult<Accelerated> {
    let mut done = Accelerated::default();
    // Nodes a fused operator stands for: left to be removed, not replaced.
    let mut fused = std::collections::HashSet::new();
    for id in model.eval_order()? {
        if fused.contains(&id) {
            continue;
        }
        let node = model.node(id);
        // The nodes an operator stands for, in order: it replaces the last (by default the
        // node itself).
        let mut chain = vec![id];
        // Convolutions hold their weights and bias, and take in the activation after them:
        // they read only the data input.
        let (op, inputs): (Box<dyn TypedOp>, TVec<OutletId>) =
            if let Some(op) = winograd::winograd(model, node, winograd)? {
                done.convolutions += 1;
                with_tail(model, node, op, WinogradConv::fused, &mut chain)?
            } else if let Some(op) = conv::packed(model, node)? {
                done.convolutions += 1;
                with_tail(model, node, op, PackedConv::fused, &mut chain)?
            } else if let Some(op) = dwconv::depthwise(model, node)? {
                done.depthwise += 1;
                let (op, x) = dwconv::past_dequantize(model, node, op);
                let op = fuse_tail(model, node, op, DepthwiseConv::fused, &mut chain)?;
                // A quantiser after it (an integer layer reads the output): its bytes written
                // by the convolution.
                let op = match dwconv::quantized_after(model, model.node(*chain.last().expect("the node")))? {
                    Some((q, id)) => {
                        chain.push(id);
                        op.writing(q)
                    }
                    None => op,
                };
                (Box::new(op), tvec![x])
            } else if let Some(op) = dwconv_hwc::depthwise_hwc(model, node)? {
                done.depthwise += 1;
                (Box::new(op), tvec![node.inputs[0]])
            } else if let Some(op) = qconv::packed_q(model, node)? {
                done.int8_convolutions += 1;
                (Box::new(op), tvec![past_plain_cast(model, node.inputs[0])?])
            } else if let Some(op) = dwqconv::depthwise_q(model, node)? {
                done.int8_convolutions += 1;
                let (op, x) = dwqconv::past_table(model, past_plain_cast(model, node.inputs[0])?, op);
                // A dequantiser after it (f32 operators read the output): its values written by
                // the convolution.
                let op = match dwqconv::dequantized_after(model, node)? {
                    Some((dq, nodes)) => {
                        chain.extend(nodes);
                        op.dequantizing(dq)
                    }
                    None => op,
                };
                (Box::new(op), tvec![past_plain_cast(model, x)?])
            } else if let Some(op) = pool::channel_max_pool(model, node)? {
                done.pools += 1;
                (Box::new(op), tvec![node.inputs[0]])
            } else if let Some((op, inputs, c)) = attn_fused::fused_attention(model, node)? {
                done.attention += 1;
                chain = c;
                (Box::new(op), inputs)
            } else if let Some(op) = attention::attention_op(model, node)? {
                done.attention += 1;
                (op, node.inputs.iter().copied().collect())
            } else if let Some((op, x)) = norm::layer_norm(model, node)? {
                done.norms += 1;
                (Box::new(op), tvec![x])
            } else if let Some((op, x)) = matmul::const_matmul(model, node)? {
                done.matmuls += 1;
                (Box::new(op), tvec![x])
            } else if let Some((op, x, c)) = pointwise::pointwise(model, node)? {
                done.pointwise += 1;
                chain = c;
                (Box::new(op), tvec![x])
            } else if let Some(op) = binary::broadcast_binary(model, node)? {
                done.broadcasts += 1;
                let op = match op.with_residual(model, node) {
                    Some((op, add)) => {
                        chain.push(add);
                        op
                    }
                    None => with_activation(model, node, op, BroadcastBinary::fused, &mut chain)?,
                };
                (Box::new(op), node.inputs.iter().copied().collect())
            } else if let Some(op) = quant::quantize_u8(model, node)? {
                done.quantizers += 1;
                (Box::new(op), tvec![node.inputs[0]])
            } else if let Some(op) = quant::dequantize_u8(model, node)? {
                done.quantizers += 1;
                let op = with_activation(model, node, op, DequantizeU8::fused, &mut chain)?;
                (Box::new(op), tvec![node.inputs[0]])
            } else if let Some((op, x, c)) = se::squeeze_excite(model, node)? {
                done.squeeze_excite += 1;
                chain = c;
                (Box::new(op), tvec![x])
            } else if let Some((op, c)) = permute::permute(model, node)? {
                done.permutes += 1;
                chain = c;
                (Box::new(op), tvec![node.inputs[0]])
            } else if let Some((op, inputs)) = xcorr::xcorr(model, node)? {
                done.correlations += 1;
                (Box::new(op), inputs)
            } else {
                continue;
            };
        // The operator keeps the name of the first node it stands for (the convolution's, not
        // its activation's) and takes the place of the last.
        let last = *chain.last().expect("the node at least");
        let mut patch = TypedModelPatch::default();
        let taps = patch.taps(model, &inputs)?;
        let wires = patch.wire_node(&node.name, op, &taps)?;
        for (ix, &w) in wires.iter().enumerate() {
            patch.shunt_outside(model, OutletId::new(last, ix), w)?;
        }
        for &id in &chain {
            patch.obliterate(id)?;
        }
        patch.apply(model)?;
        fused.extend(chain);
    }
    if done != Accelerated::default() {
        model.compact()?;
    }
    Ok(done)
}

/// A convolution `op` standing for `node` with the activation nodes after it fused in by `fuse`
/// (`chain` then lists them all), boxed, with the data input it reads.
fn with_tail<T: TypedOp>(
    model: &TypedModel,
    node: &TypedNode,
    op: T,
    fuse: fn(T, &act::Tail) -> TractResult<T>,
    chain: &mut Vec<usize>,
) -> TractResult<(Box<dyn TypedOp>, TVec<OutletId>)> {
    Ok((Box::new(fuse_tail(model, node, op, fuse, chain)?), tvec![node.inputs[0]]))
}

/// A convolution `op` standing for `node` with the activation nodes after it fused in by `fuse`
/// (`chain` then lists them all).
fn fuse_tail<T>(
    model: &TypedModel,
    node: &TypedNode,
    op: T,
    fuse: fn(T, &act::Tail) -> TractResult<T>,
    chain: &mut Vec<usize>,
) -> TractResult<T> {
    Ok(match act::tail(model, node, None)? {
        Some(t) => {
            *chain = t.chain.clone();
            fuse(op, &t)?
        }
        None => op,
    })
}

/// `op` standing for the element-wise `node` with the activation nodes after it taken in by
/// `fuse` where it can (`chain` then lists them all; `fuse` gets the tail and `node`'s output
/// shape), else `op` as it is.
fn with_activation<T>(
    model: &TypedModel,
    node: &TypedNode,
    op: T,
    fuse: fn(&T, &act::Tail, &[usize]) -> Option<T>,
    chain: &mut Vec<usize>,
) -> TractResult<T> {
    let shape = node.outputs[0].fact.shape.as_concrete().unwrap_or_default();
    Ok(match act::tail(model, node, None)?.and_then(|t| Some((fuse(&op, &t, shape)?, t.chain))) {
        Some((fused, c)) => {
            *chain = c;
            fused
        }
        None => op,
    })
}

/// `outlet`, or the input of the cast that makes it where that cast only adds or drops
/// quantisation parameters (plain u8 to u8 with a zero point and scale, or back: tract copies
/// the bytes, 0.02-0.06 ms before each of PRL-Track's int8 convolutions, which take the
/// parameters from their own op). The cast, left without readers, goes when the graph is
/// compacted.
fn past_plain_cast(model: &TypedModel, outlet: OutletId) -> TractResult<OutletId> {
    use tract_nnef::tract_core::ops::cast::Cast;
    let node = model.node(outlet.node);
    let Some(cast) = node.op_as::<Cast>() else { return Ok(outlet) };
    let from = model.outlet_fact(node.inputs[0])?.datum_type;
    let copy = from.unquantized() == cast.to.unquantized() && !(from.is_quantized() && cast.to.is_quantized());
    Ok(if copy { node.inputs[0] } else { outlet })
}

/// Whether a pooling spec's strides or dilations (absent: 1) are all 1.
fn all_ones(v: &Option<TVec<usize>>) -> bool {
    v.as_ref().is_none_or(|v| v.iter().all(|&s| s == 1))
}

/// A 2-D padding spec as `[top, left, bottom, right]`, if it is explicit (or none).
fn pads_2d(p: &tract_nnef::tract_core::ops::cnn::PaddingSpec) -> Option<[usize; 4]> {
    use tract_nnef::tract_core::ops::cnn::PaddingSpec::*;
    match p {
        Valid => Some([0; 4]),
        Explicit(b, a) | ExplicitOnnxPool(b, a, _) if b.len() == 2 && a.len() == 2 => Some([b[0], b[1], a[0], a[1]]),
        _ => None,
    }
}

/// Whether a 2-D padding spec adds no padding.
fn no_padding(p: &tract_nnef::tract_core::ops::cnn::PaddingSpec) -> bool {
    pads_2d(p) == Some([0; 4])
}

/// Whether two f32 slices hold the same bit patterns (operator equality on constants).
fn same_bits(a: &[f32], b: &[f32]) -> bool {
    a.len() == b.len() && a.iter().zip(b).all(|(x, y)| x.to_bits() == y.to_bits())
}

/// Whether the kernels may use AVX2 and FMA ([`crate::isa`]: the CPU has them and `PRL_ISA`
/// allows them): which paths the unit tests can run (the operators dispatch on
/// [`crate::isa::F32_KERNELS`]).
#[cfg(all(test, target_arch = "x86_64"))]
fn avx2_fma() -> bool {
    crate::isa().avx2_fma
}

/// Whether the kernels may use AVX-512F (with AVX2 and FMA): the 16-lane paths of the f32
/// kernels compiled for `avx512f,avx2,fma` (for the unit tests, as above).
#[cfg(all(test, target_arch = "x86_64"))]
fn avx512_fma() -> bool {
    crate::isa().avx512
}

/// Whether the CPU and OS run AMX int8 tiles (before any `PRL_ISA` cap).
#[cfg(target_arch = "x86_64")]
pub(crate) fn amx_available() -> bool {
    qconv_amx::available()
}

/// The kernel a node of an optimised graph runs, from its operator's name and tract's
/// description of it (see [`crate::NodeTime::kernel`]).
pub(crate) fn kernel_name(op: &str, info: &str) -> String {
    let isa = crate::isa();
    match op {
        // Tiles over output positions without wide columns (small maps, AVX2).
        "PackedConv" if info.contains("compact tiles") => format!("{} compact", crate::isa::f32_kernel().name()),
        "PackedConv" | "DepthwiseConv" | "DepthwiseConvHwc" | "DepthwiseXCorr" | "ConstMatMul" | "PointwiseConv"
        | "AttnScores" | "AttnMix" | "RowSoftmax" | "Attention" | "QuantizeU8" | "DequantizeU8" | "SqueezeExcite" => {
            crate::isa::f32_kernel().name().to_string()
        }
        // The form from the operator's info ("F(2x2, 3x3), ...").
        "WinogradConv" => {
            let form = info.split("), ").next().unwrap_or("").replace(' ', "");
            format!("{} {form})", crate::isa::f32_kernel().name())
        }
        // The operator's info says which (AMX serves only kernels larger than 1x1).
        "PackedQConv" if info.contains("on AMX") => "amx".to_string(),
        "PackedQConv" if info.contains("VNNI") => "vnni".to_string(),
        "PackedQConv" => isa.int8_kernel().unwrap_or("-").to_string(),
        "DepthwiseQConv" if info.contains("VNNI") => "vnni".to_string(),
        "DepthwiseQConv" if info.contains("SDOT") => "sdot".to_string(),
        "DepthwiseQConv" => format!("{} (exact sums)", crate::isa::f32_kernel().name()),
        // 3 x 3 windows of stride 2 in AVX-512 for f32 (u8 as below).
        "ChannelMaxPool"
            if info.contains("3x3 window, stride 2") && crate::isa::f32_kernel() == crate::isa::F32Kernel::Avx512 =>
        {
            "avx512 (f32), avx2 (u8)".to_string()
        }
        // And in NEON on aarch64 (u8 in the portable form, vectorised by the compiler).
        "ChannelMaxPool"
            if info.contains("3x3 window, stride 2") && crate::isa::f32_kernel() == crate::isa::F32Kernel::Neon =>
        {
            "neon (f32), portable (u8)".to_string()
        }
        // Compiled for AVX2 on every x86 kernel of the table but the portable one.
        "ChannelMaxPool"
            if cfg!(target_arch = "x86_64") && crate::isa::f32_kernel() != crate::isa::F32Kernel::Portable =>
        {
            "avx2 (vectorised)".to_string()
        }
        "ChannelMaxPool" | "LayerNormCore" | "BroadcastBinary" | "Permute" => "portable (vectorised)".to_string(),
        _ => info
            .split(|c: char| !(c.is_alphanumeric() || c == '_'))
            .find(|w| w.contains("_mmm_"))
            .unwrap_or("")
            .to_string(),
    }
}
