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
mod permute;
mod pointwise;
mod pool;
mod qconv;
mod qconv_amx;
mod qconv_kernel;
mod qconv_lanes;
mod quant;
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

/// A zero-filled tensor of `shape` that `fill` writes an operator's output into. (tract's
/// conversions from a `Vec` or an ndarray copy the data into a tensor of their own: one more
/// pass over every output.)
fn output_tensor<T: Datum>(shape: &[usize], fill: impl FnOnce(&mut [T]) -> TractResult<()>) -> TractResult<Tensor> {
    let mut t = Tensor::zero_dt(T::datum_type(), shape)?;
    {
        let mut plain = t.try_as_plain_ram_mut()?;
        fill(plain.as_slice_mut::<T>()?)?;
    }
    Ok(t)
}

/// As [`output_tensor`] for f32 or u8, without zeroing the tensor first (a pass over the
/// whole output on one thread, and page faults on large ones, that a kernel writing every
/// element does not need). In debug builds (the tests) every byte is 0xFF first, so that a
/// value left unwritten reads as NaN (f32) or 255 (u8), not as a zero that fresh memory
/// happens to hold.
///
/// # Safety
/// `fill` writes every element of the slice it is given before the tensor is read.
unsafe fn output_tensor_written<T: Datum + Copy>(
    shape: &[usize],
    fill: impl FnOnce(&mut [T]) -> TractResult<()>,
) -> TractResult<Tensor> {
    debug_assert!([f32::datum_type(), u8::datum_type()].contains(&T::datum_type()));
    // SAFETY: every bit pattern is an f32 or a u8 (asserted), and the caller's `fill` writes
    // every element.
    let mut t = unsafe { Tensor::uninitialized_dt(T::datum_type(), shape)? };
    {
        let mut plain = t.try_as_plain_ram_mut()?;
        let values = plain.as_slice_mut::<T>()?;
        #[cfg(debug_assertions)]
        // SAFETY: the slice's own bytes; all-ones bytes are a valid f32 (NaN) and u8 (255).
        unsafe {
            std::ptr::write_bytes(values.as_mut_ptr(), 0xFF, values.len())
        };
        fill(values)?;
    }
    Ok(t)
}

/// A value of four bytes for which every bit pattern is valid (the kernels' sums, the padded
/// inputs).
trait Word: Copy {}
impl Word for f32 {}
impl Word for i32 {}

/// A thread's buffer kept from call to call ([`with_padded`], [`with_words`]).
type Kept = std::thread::LocalKey<std::cell::RefCell<Vec<u32>>>;

/// Run `f` on `len` values of the calling thread's buffer `kept`, which grows to the largest
/// `len` asked for: the values are whatever its last use left. In use further up this thread's
/// stack (not the case today), a zeroed buffer of its own.
fn lend<T: Word, R>(kept: &'static Kept, len: usize, f: impl FnOnce(&mut [T]) -> R) -> R {
    const { assert!(size_of::<T>() == 4 && align_of::<T>() == 4) };
    let words = |v: &mut [u32]| {
        // SAFETY: `T` is four bytes with no invalid bit pattern ([`Word`]: f32, i32), as
        // aligned as u32; the values are initialised u32s, borrowed mutably here alone.
        unsafe { std::slice::from_raw_parts_mut(v.as_mut_ptr().cast::<T>(), v.len()) }
    };
    kept.with(|b| match b.try_borrow_mut() {
        Ok(mut v) => {
            if v.len() < len {
                v.resize(len, 0);
            }
            f(words(&mut v[..len]))
        }
        Err(_) => f(words(&mut vec![0u32; len])),
    })
}

/// Run `f` on a buffer of `len` values whose positions `borders` lists (runs `(start, len)`)
/// are zero and the others hold whatever the thread's last use left: the scratch of a padded
/// input, whose interior the caller writes whole before reading it. The buffer is the calling
/// thread's own and kept from call to call (it grows to the largest `len` asked for), so a
/// padded plane costs neither an allocation nor the zeroing of its interior (the stem's 0.8 MB
/// and the depthwise layers' planes were zeroed on every frame: 2% of NanoTrack's step).
fn with_padded<R>(len: usize, borders: &[(usize, usize)], f: impl FnOnce(&mut [f32]) -> R) -> R {
    thread_local! {
        static PADDED: std::cell::RefCell<Vec<u32>> = const { std::cell::RefCell::new(Vec::new()) };
    }
    lend(&PADDED, len, |buf: &mut [f32]| {
        for &(at, n) in borders {
            buf[at..at + n].fill(0.0);
        }
        f(buf)
    })
}

/// Run `f` on the calling thread's buffer of `len` values of four bytes, kept from call to call
/// (it grows to the largest `len` asked for): the values are whatever its last use left, so
/// `f` writes before it reads. The tiles' sums: an item of PRL-Track's template layer 1 took
/// 0.67 MB of sums, allocated and zeroed for each of its two channel blocks (0.05 of 1.7 ms).
/// A buffer of its own, not [`with_padded`]'s: the sums are made while the padded input is in
/// use.
fn with_words<T: Word, R>(len: usize, f: impl FnOnce(&mut [T]) -> R) -> R {
    thread_local! {
        static WORDS: std::cell::RefCell<Vec<u32>> = const { std::cell::RefCell::new(Vec::new()) };
    }
    lend(&WORDS, len, f)
}

/// Run `f` on the calling thread's buffer of `len` bytes, kept from call to call (it grows to
/// the largest `len` asked for): the bytes are whatever its last use left, so `f` writes before
/// it reads. The integer depthwise layers' padded planes (allocated per channel group and
/// frame before).
#[cfg(any(target_arch = "x86_64", target_arch = "aarch64"))]
fn with_bytes<R>(len: usize, f: impl FnOnce(&mut [u8]) -> R) -> R {
    thread_local! {
        static BYTES: std::cell::RefCell<Vec<u8>> = const { std::cell::RefCell::new(Vec::new()) };
    }
    BYTES.with(|b| match b.try_borrow_mut() {
        Ok(mut v) => {
            if v.len() < len {
                v.resize(len, 0);
            }
            f(&mut v[..len])
        }
        Err(_) => f(&mut vec![0u8; len]),
    })
}

/// The runs `(start, len)` of a `len`-long buffer that `write` leaves as they were: what
/// [`with_padded`] must zero for a padded input that `write` fills (found once, when an
/// operator is made, by writing into a buffer of NaNs).
fn unwritten_runs(len: usize, write: impl FnOnce(&mut [f32])) -> Vec<(usize, usize)> {
    let mut buf = vec![f32::NAN; len];
    write(&mut buf);
    let mut runs: Vec<(usize, usize)> = vec![];
    for (i, v) in buf.iter().enumerate() {
        if !v.is_nan() {
            continue;
        }
        match runs.last_mut() {
            Some((at, n)) if *at + *n == i => *n += 1,
            _ => runs.push((i, 1)),
        }
    }
    runs
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

/// A pointer that threads writing disjoint elements share.
struct SyncPtr<T>(*mut T);

// SAFETY: users write disjoint elements only, and the buffer outlives the threads' work.
unsafe impl<T> Send for SyncPtr<T> {}
// SAFETY: as above.
unsafe impl<T> Sync for SyncPtr<T> {}

impl<T> SyncPtr<T> {
    /// The element at `i`.
    ///
    /// # Safety
    /// `i` is within the buffer, and no other thread accesses that element meanwhile.
    unsafe fn at(&self, i: usize) -> *mut T {
        // SAFETY: the caller keeps `i` within the buffer.
        unsafe { self.0.add(i) }
    }
}

/// The threads [`par_for`] and [`par_chunks`] run on (tract's executor's).
fn threads() -> usize {
    use tract_linalg::multithread::{current_tract_executor, Executor};
    match current_tract_executor() {
        Executor::SingleThread => 1,
        Executor::MultiThread(pool) => pool.current_num_threads(),
        Executor::RayonGlobal => rayon::current_num_threads(),
    }
}

/// Multiply-adds under which an operator runs on the calling thread alone, even where its graph
/// is split over threads: about 50 µs of work, of which handing it to the pool's threads costs a
/// good part (PRL-Track's three head convolutions, 0.8 M each, took 0.045-0.064 ms on one thread
/// and 0.053-0.076 over two).
const SERIAL_MACS: usize = 1 << 20;

/// `f` with tract's executor set to the calling thread alone where `macs` is under
/// [`SERIAL_MACS`] (so that the operator's [`par_for`]s and [`par_chunks`] run inline), else `f`.
fn serial_if_small<R>(macs: usize, f: impl FnOnce() -> R) -> R {
    use tract_linalg::multithread::{multithread_tract_scope, Executor};
    if macs < SERIAL_MACS {
        multithread_tract_scope(Executor::SingleThread, f)
    } else {
        f()
    }
}

/// Run `f(i)` for every `i < n`, on tract's thread pool when it has one.
fn par_for(n: usize, f: impl Fn(usize) + Sync) {
    use rayon::prelude::*;
    use tract_linalg::multithread::{current_tract_executor, Executor};
    match current_tract_executor() {
        Executor::SingleThread => (0..n).for_each(f),
        Executor::MultiThread(pool) => pool.install(|| (0..n).into_par_iter().for_each(&f)),
        Executor::RayonGlobal => (0..n).into_par_iter().for_each(&f),
    }
}

/// Values in one share of an element-wise operator's work handed to the pool's threads
/// ([`par_chunks`]; [`QuantizeU8`], [`DequantizeU8`], [`BroadcastBinary`]'s whole rows): a
/// tensor of fewer stays on the calling thread (a hand-over costs about what 30 000 elements
/// take).
const SHARE: usize = 1 << 15;

/// Run `f(i, chunk)` on every `len`-long chunk of `out` (the last may be shorter), on tract's
/// thread pool when it has one.
fn par_chunks<T: Send>(out: &mut [T], len: usize, f: impl Fn(usize, &mut [T]) + Sync) {
    use rayon::prelude::*;
    use tract_linalg::multithread::{current_tract_executor, Executor};
    let chunks = out.par_chunks_mut(len).enumerate();
    match current_tract_executor() {
        Executor::SingleThread => out.chunks_mut(len).enumerate().for_each(|(i, c)| f(i, c)),
        Executor::MultiThread(pool) => pool.install(|| chunks.for_each(|(i, c)| f(i, c))),
        Executor::RayonGlobal => chunks.for_each(|(i, c)| f(i, c)),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_thread_s_padded_buffer_has_zero_borders_whatever_it_held() {
        // A plane padded for a 3x3 stride-2 convolution: what its padding leaves unwritten.
        let s = ConvShape { ci: 1, h: 5, w: 7, co: 1, kh: 3, kw: 3, pad: [1, 1, 1, 1], stride: 2 };
        let (hq, wq) = s.phase();
        let len = 4 * hq * wq + 3;
        let borders = unwritten_runs(len, |b| s.pad_plane(&[0.0; 35], b));
        let unwritten: usize = borders.iter().map(|r| r.1).sum();
        assert_eq!(unwritten, len - 35, "35 values written, the rest padding and slack");
        // Dirty the buffer (a larger one first), then take it back with those borders.
        with_padded(2 * len, &[], |b| b.fill(f32::NAN));
        let src: Vec<f32> = (1..=35).map(|v| v as f32).collect();
        let got = with_padded(len, &borders, |b| {
            s.pad_plane(&src, b);
            b.to_vec()
        });
        let mut want = vec![0.0; len];
        s.pad_plane(&src, &mut want);
        assert_eq!(got, want);
    }
}
