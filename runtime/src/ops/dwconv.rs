//! Depthwise convolutions with constant weights (MobileNet's 3x3 and 5x5 layers, stride 1 or 2)
//! as [`DepthwiseConv`], a direct per-channel convolution whose output is accumulated in register
//! blocks of four rows by 32 (or 16) columns.
//!
//! tract runs these as `DepthWiseConv`, a loop that reached 2-2.4 GFLOP/s on NanoTrack's early
//! layers (16-72 channels of 64x64 to 128x128) and took half of its search step. Here each
//! channel's plane is zero-padded once (as its phases with stride 2, so every tap reads
//! consecutive inputs) and every output row is the sum over taps of a weight times a shifted
//! input row; channels are spread over tract's thread pool. In int8 plans a convolution whose
//! input is dequantised for it alone reads the u8 data and dequantises each plane on its way
//! into the padded plane ([`DepthwiseConv::reading`]); one whose output only a quantiser reads
//! writes the quantiser's bytes itself, each plane quantised while in the cache
//! ([`DepthwiseConv::writing`]).

use std::sync::Arc;

use tract_nnef::internal::*;
use tract_nnef::tract_core::ops::nn::DataFormat;

use super::act::{output_fact, reshape_output, Activation, Tail};
use super::conv::{ConstConv, ConvShape};
use super::quant::{DequantizeU8, Planes, QuantizeU8};
use super::{output_tensor_written, par_chunks, same_bits, serial_if_small, SERIAL_MACS};

/// Output columns accumulated at once (two 16-lane registers on AVX-512).
const BLOCK: usize = 32;

/// `out[n,c,y,x] = bias[c] + Σ_{i,j} pad(input)[n,c,s·y+i,s·x+j]·weight[c,0,i,j]`, stride `s`
/// 1 or 2, zero padding: a depthwise convolution with constant weights.
#[derive(Clone)]
pub struct DepthwiseConv {
    /// `ci == co` channels; the kernel is `kh` x `kw`.
    shape: ConvShape,
    /// The data has a batch axis (NCHW); else it is CHW (tract drops a batch axis of 1).
    batch: bool,
    /// Each tap's offset in the padded (phase-split) plane, the same for every channel.
    offsets: Arc<Vec<usize>>,
    weights: Arc<Vec<f32>>,
    bias: Arc<Vec<f32>>,
    /// Applied to each channel's output once written (the graph's activation after it).
    act: Activation,
    /// The scratch's positions a channel's padding does not write ([`super::with_padded`]).
    borders: Arc<Vec<(usize, usize)>>,
    /// The output's shape where the fused nodes end in another shape than the convolution's.
    reshape: Option<TVec<usize>>,
    /// The input is u8, dequantised by this (and its activation) plane by plane ([`Self::reading`]).
    dequant: Option<DequantizeU8>,
    /// The output is u8, each plane quantised by this as it is written ([`Self::writing`]).
    quant: Option<QuantizeU8>,
}

impl std::fmt::Debug for DepthwiseConv {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "DepthwiseConv({:?})", self.shape)
    }
}

impl PartialEq for DepthwiseConv {
    fn eq(&self, other: &Self) -> bool {
        self.shape == other.shape
            && self.batch == other.batch
            && same_bits(&self.weights, &other.weights)
            && same_bits(&self.bias, &other.bias)
            && self.act == other.act
            && self.reshape == other.reshape
            && self.dequant == other.dequant
            && self.quant == other.quant
    }
}

impl Eq for DepthwiseConv {}

impl DepthwiseConv {
    /// A depthwise convolution of `shape` (`ci == co`) with weights `[c, 1, kh, kw]` row-major
    /// and `bias` (one value or one per channel), on NCHW data (`batch`) or CHW.
    pub fn new(shape: ConvShape, batch: bool, weight: &[f32], bias: &[f32]) -> TractResult<DepthwiseConv> {
        let c = shape.ci;
        ensure!(shape.co == c && matches!(shape.stride, 1 | 2), "DepthwiseConv: shape {shape:?}");
        ensure!(weight.len() == c * shape.kh * shape.kw, "DepthwiseConv: {} weights for {shape:?}", weight.len());
        ensure!(bias.len() == 1 || bias.len() == c, "DepthwiseConv: {} bias values for {shape:?}", bias.len());
        let bias = (0..c).map(|o| if bias.len() == 1 { bias[0] } else { bias[o] }).collect();
        let offsets = Arc::new(shape.tap_offsets(1));
        let (weights, bias) = (Arc::new(weight.to_vec()), Arc::new(bias));
        let borders = Arc::new(super::unwritten_runs(Self::scratch_len(&shape), |buf| {
            shape.pad_plane(&vec![0.0; shape.h * shape.w], buf)
        }));
        let act = Activation::NONE;
        Ok(DepthwiseConv {
            shape,
            batch,
            offsets,
            weights,
            bias,
            act,
            borders,
            reshape: None,
            dequant: None,
            quant: None,
        })
    }

    /// The length of the scratch plane: the padded input (its phases with stride 2), with room
    /// for a whole column block past the end.
    fn scratch_len(s: &ConvShape) -> usize {
        let (hq, wq) = s.phase();
        s.stride * s.stride * hq * wq + BLOCK
    }

    /// The convolution followed by the nodes of `tail` ([`super::act::tail`]).
    pub(crate) fn fused(self, tail: &Tail) -> TractResult<DepthwiseConv> {
        ensure!(tail.bias.is_none(), "DepthwiseConv: a convolution has its own bias");
        Ok(DepthwiseConv { act: tail.act, reshape: tail.reshaped(), ..self })
    }

    /// The convolution of `dequant`'s output, reading its u8 input instead: each plane is
    /// dequantised (with the dequantiser's activation) into a plane of the thread's before it is
    /// padded, the values the dequantiser would have written, so the same outputs. NanoTrack's
    /// int8 plan has 13 such pairs (its expanding pointwise layers and the head's towers are
    /// integer, the depthwise layers after them f32): the dequantised tensors no longer go
    /// through memory.
    pub(crate) fn reading(self, dequant: DequantizeU8) -> DepthwiseConv {
        DepthwiseConv { dequant: Some(dequant), ..self }
    }

    /// The convolution followed by `quant`: each output plane (after the activation) quantised
    /// to u8 while it is in the thread's cache, the bytes `quant` would have written from the
    /// f32 tensor. NanoTrack's int8 plan has 14 such pairs (the depthwise layers before an
    /// integer pointwise one without a squeeze-excitation between).
    pub(crate) fn writing(self, quant: QuantizeU8) -> DepthwiseConv {
        DepthwiseConv { quant: Some(quant), ..self }
    }

    /// A zeroed scratch plane for [`Self::channel`] ([`Self::scratch_len`] long; the operator
    /// itself takes a thread's buffer, [`super::with_padded`]). Its borders stay zero from
    /// channel to channel, since every channel writes the same interior positions.
    #[cfg(test)]
    fn scratch(&self) -> Vec<f32> {
        vec![0.0; Self::scratch_len(&self.shape)]
    }

    /// One channel: `src` `[h, w]` into `dst` `[oh, ow]`, with `scratch` from [`Self::scratch`].
    fn channel(&self, ch: usize, src: &[f32], dst: &mut [f32], scratch: &mut [f32]) {
        let s = &self.shape;
        s.pad_plane(src, scratch);
        let wq = s.phase().1;
        let taps = s.kh * s.kw;
        let (_, ow) = s.out();
        kernel::rows(scratch, wq, &self.offsets, &self.weights[ch * taps..(ch + 1) * taps], self.bias[ch], dst, ow);
        self.act.apply_all(dst);
    }
}

/// The row kernel, compiled for AVX-512, for AVX2 + FMA and generically; the CPU's best is
/// chosen when run.
mod kernel {
    /// The arguments of every path: the padded plane, its row length, the taps' offsets and
    /// weights, the bias, the output rows and their length.
    #[cfg(test)]
    pub(super) type Rows = fn(&[f32], usize, &[usize], &[f32], f32, &mut [f32], usize);

    /// Every output row of one channel: `dst` (`ow` columns a row) is `bias` plus, for each tap,
    /// its weight times the padded input from its offset on (row `y` of the output reads from
    /// `offset + y * wq`).
    pub(super) fn rows(src: &[f32], wq: usize, offs: &[usize], ws: &[f32], bias: f32, dst: &mut [f32], ow: usize) {
        use crate::isa::F32Kernel;
        match crate::isa::f32_kernel() {
            // SAFETY: the CPU has AVX-512F, AVX2 and FMA (the table's needs).
            #[cfg(target_arch = "x86_64")]
            F32Kernel::Avx512 => unsafe { rows_avx512(src, wq, offs, ws, bias, dst, ow) },
            // SAFETY: the CPU has AVX2 and FMA (the table's needs).
            #[cfg(target_arch = "x86_64")]
            F32Kernel::Avx2Fma => unsafe { rows_avx2(src, wq, offs, ws, bias, dst, ow) },
            #[cfg(target_arch = "aarch64")]
            F32Kernel::Neon => rows_neon(src, wq, offs, ws, bias, dst, ow),
            _ => rows_generic::<false>(src, wq, offs, ws, bias, dst, ow),
        }
    }

    /// NEON: blocks of 16 columns (four 4-lane registers) by four rows, 16 accumulators, fused
    /// multiply-adds (the 32-column blocks of the AVX-512 form would need all 32 registers for
    /// accumulators alone). The same sums in the same order as the AVX paths: the same bits.
    #[cfg(target_arch = "aarch64")]
    pub(super) fn rows_neon(src: &[f32], wq: usize, offs: &[usize], ws: &[f32], bias: f32, dst: &mut [f32], ow: usize) {
        rows_blocked::<true, 16>(src, wq, offs, ws, bias, dst, ow)
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx512f,avx2,fma")]
    pub(super) unsafe fn rows_avx512(
        src: &[f32],
        wq: usize,
        offs: &[usize],
        ws: &[f32],
        bias: f32,
        dst: &mut [f32],
        ow: usize,
    ) {
        rows_generic::<true>(src, wq, offs, ws, bias, dst, ow)
    }

    /// AVX2: blocks of 16 columns (two 8-lane registers) by four rows, 8 accumulators (32
    /// columns by four rows would need all 16 registers for accumulators alone).
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,fma")]
    pub(super) unsafe fn rows_avx2(
        src: &[f32],
        wq: usize,
        offs: &[usize],
        ws: &[f32],
        bias: f32,
        dst: &mut [f32],
        ow: usize,
    ) {
        rows_blocked::<true, 16>(src, wq, offs, ws, bias, dst, ow)
    }

    /// `B` output columns of `R` consecutive output rows from `at` on (rows `wq` apart), into
    /// `out`: `R` rows of `ow` values, of which columns `x0 .. x0 + n` are written. `R`
    /// independent accumulators keep the FMA units busy (one row alone is a chain of dependent
    /// multiply-adds, bound by their latency).
    #[inline(always)]
    #[allow(clippy::too_many_arguments)]
    fn block<const FUSED: bool, const B: usize, const R: usize>(
        src: &[f32],
        at: usize,
        wq: usize,
        offs: &[usize],
        ws: &[f32],
        bias: f32,
        out: &mut [f32],
        (ow, x0, n): (usize, usize, usize),
    ) {
        let mut acc = [[bias; B]; R];
        // One bounds check for the block (not one per tap and row: they cost more than the
        // multiply-adds).
        let reach = offs.iter().max().map_or(0, |&o| at + (R - 1) * wq + o + B);
        assert!(reach <= src.len() && ws.len() >= offs.len(), "taps within the padded plane");
        for (&off, &w) in offs.iter().zip(ws) {
            for (r, acc) in acc.iter_mut().enumerate() {
                // SAFETY: `at + r·wq + off + B <= reach <= src.len()` (asserted above).
                let s: &[f32; B] = unsafe { &*src.as_ptr().add(at + r * wq + off).cast::<[f32; B]>() };
                for l in 0..B {
                    acc[l] = if FUSED { w.mul_add(s[l], acc[l]) } else { acc[l] + w * s[l] };
                }
            }
        }
        for (r, acc) in acc.iter().enumerate() {
            let out = &mut out[r * ow + x0..r * ow + x0 + n];
            if n == B {
                // A whole block: a copy of known length (vector stores, not a library call).
                out.copy_from_slice(acc);
            } else {
                out.copy_from_slice(&acc[..n]);
            }
        }
    }

    /// `R` output rows starting at row `y` (`out` holds exactly them).
    #[inline(always)]
    #[allow(clippy::too_many_arguments)]
    fn row_group<const FUSED: bool, const WIDE: usize, const R: usize>(
        src: &[f32],
        wq: usize,
        offs: &[usize],
        ws: &[f32],
        bias: f32,
        out: &mut [f32],
        ow: usize,
        y: usize,
    ) {
        let base = y * wq;
        let mut x0 = 0;
        while x0 + WIDE <= ow {
            block::<FUSED, WIDE, R>(src, base + x0, wq, offs, ws, bias, out, (ow, x0, WIDE));
            x0 += WIDE;
        }
        while x0 < ow {
            let n = (ow - x0).min(16);
            if n <= 8 {
                // An 8x8 map (MobileNet's last layers on a template) fills half a 16-lane block.
                block::<FUSED, 8, R>(src, base + x0, wq, offs, ws, bias, out, (ow, x0, n));
            } else {
                block::<FUSED, 16, R>(src, base + x0, wq, offs, ws, bias, out, (ow, x0, n));
            }
            x0 += n;
        }
    }

    /// The portable form; `FUSED` uses fused multiply-adds (only where the CPU has them:
    /// elsewhere `mul_add` is a library call). Rows go four at a time (eight on maps up to 8
    /// wide), in blocks of 32 columns, then 16 (a 16x16 map wastes nothing), then 8 for what is
    /// left; the last block of a row computes past its end into the scratch's slack and keeps
    /// only the columns that exist.
    #[inline(always)]
    pub(super) fn rows_generic<const FUSED: bool>(
        src: &[f32],
        wq: usize,
        offs: &[usize],
        ws: &[f32],
        bias: f32,
        dst: &mut [f32],
        ow: usize,
    ) {
        rows_blocked::<FUSED, 32>(src, wq, offs, ws, bias, dst, ow)
    }

    /// [`rows_generic`] with blocks of `WIDE` columns (32 or 16) before the 16-column ones.
    #[inline(always)]
    #[allow(clippy::too_many_arguments)]
    fn rows_blocked<const FUSED: bool, const WIDE: usize>(
        src: &[f32],
        wq: usize,
        offs: &[usize],
        ws: &[f32],
        bias: f32,
        dst: &mut [f32],
        ow: usize,
    ) {
        let oh = dst.len() / ow;
        let mut y = 0;
        if ow <= 8 {
            // One 8-column block a row: eight rows at once (eight independent accumulators;
            // four leave the multiply-adds waiting on each other's latency).
            for out in dst.chunks_exact_mut(8 * ow) {
                row_group::<FUSED, WIDE, 8>(src, wq, offs, ws, bias, out, ow, y);
                y += 8;
            }
        }
        for out in dst[y * ow..].chunks_exact_mut(4 * ow) {
            row_group::<FUSED, WIDE, 4>(src, wq, offs, ws, bias, out, ow, y);
            y += 4;
        }
        for out in dst[y * ow..].chunks_exact_mut(ow) {
            row_group::<FUSED, WIDE, 1>(src, wq, offs, ws, bias, out, ow, y);
            y += 1;
        }
        debug_assert_eq!(y, oh);
    }
}

impl Op for DepthwiseConv {
    fn name(&self) -> StaticName {
        "DepthwiseConv".into()
    }

    fn info(&self) -> TractResult<Vec<String>> {
        let s = &self.shape;
        Ok(vec![format!(
            "{}x{} kernel, stride {}, {} channels, pad {:?}, activation {}{}{}",
            s.kh,
            s.kw,
            s.stride,
            s.ci,
            s.pad,
            self.act.describe(),
            if self.dequant.is_some() { ", u8 input dequantised" } else { "" },
            if self.quant.is_some() { ", u8 output quantised" } else { "" }
        )])
    }

    op_as_typed_op!();
}

impl EvalOp for DepthwiseConv {
    op_out_of_plan!();

    fn eval(&self, _ctx: &EvalContext, inputs: TVec<TValue>) -> TractResult<TVec<TValue>> {
        let input = args_1!(inputs);
        let s = &self.shape;
        let (n, c, h, w) = match (self.batch, input.shape()) {
            (true, &[n, c, h, w]) => (n, c, h, w),
            (false, &[c, h, w]) => (1, c, h, w),
            _ => bail!("DepthwiseConv: input {:?} for {s:?}", input.shape()),
        };
        ensure!((c, h, w) == (s.ci, s.h, s.w), "DepthwiseConv: input {:?} for {s:?}", input.shape());
        // The data: f32, or u8 dequantised plane by plane ([`Self::reading`]).
        let data = Planes::of("DepthwiseConv", &input, self.dequant.as_ref())?;
        let (oh, ow) = s.out();
        let shape: TVec<usize> = if self.batch { tvec![n, c, oh, ow] } else { tvec![c, oh, ow] };
        let plane = oh * ow;
        // Channels go in groups of about SERIAL_MACS / 8 multiply-adds, each group with one
        // scratch plane; a layer under SERIAL_MACS stays on this thread (handing it to others
        // costs more than it saves).
        let macs = plane * s.kh * s.kw;
        let group = (SERIAL_MACS / 8 / macs.max(1)).clamp(1, n * c);
        // The thread's buffer: the padded scratch (its borders zero), then a plane for the
        // dequantised input where the input is u8 (allocated per group and frame, it was),
        // then, where the output is u8, a plane of f32 outputs to quantise.
        let scratch_len = Self::scratch_len(s);
        let in_len = data.buffer_len(h * w);
        let out_len = if self.quant.is_some() { plane } else { 0 };
        let buffer_len = scratch_len + in_len + out_len;
        // Channel `k` of group `g` into `d`.
        let channels = |g: usize, k: usize, d: &mut [f32], scratch: &mut [f32], dequantised: &mut [f32]| {
            let p = g * group + k;
            self.channel(p % c, data.plane(p * h * w..(p + 1) * h * w, dequantised), d, scratch);
        };
        // The thread's buffer as its three parts: scratch, dequantised input, f32 outputs.
        let buffers = |f: &mut Parts| {
            super::with_padded(buffer_len, &self.borders, |buffer| {
                let (scratch, rest) = buffer.split_at_mut(scratch_len);
                let (dequantised, values) = rest.split_at_mut(in_len);
                f(scratch, dequantised, values)
            })
        };
        let len = group * plane;
        // SAFETY (both): every channel's plane is written whole (every row, every column block).
        let out = serial_if_small(n * c * macs, || match &self.quant {
            None => unsafe {
                output_tensor_written(&shape, |out: &mut [f32]| {
                    par_chunks(out, len, |g, dst| {
                        buffers(&mut |scratch, dequantised, _| {
                            for (k, d) in dst.chunks_exact_mut(plane).enumerate() {
                                channels(g, k, d, scratch, dequantised);
                            }
                        })
                    });
                    Ok(())
                })
            },
            Some(q) => unsafe {
                output_tensor_written(&shape, |out: &mut [u8]| {
                    par_chunks(out, len, |g, dst| {
                        buffers(&mut |scratch, dequantised, values| {
                            for (k, d) in dst.chunks_exact_mut(plane).enumerate() {
                                channels(g, k, values, scratch, dequantised);
                                q.apply(values, d);
                            }
                        })
                    });
                    Ok(())
                })
            },
        })?;
        Ok(tvec!(reshape_output(out, self.reshape.as_ref())?.into_tvalue()))
    }
}

/// What runs on a thread's buffer split in its three parts (scratch, dequantised input, f32
/// outputs).
type Parts<'a> = dyn FnMut(&mut [f32], &mut [f32], &mut [f32]) + 'a;

impl TypedOp for DepthwiseConv {
    fn output_facts(&self, inputs: &[&TypedFact]) -> TractResult<TVec<TypedFact>> {
        let fact = || {
            let (oh, ow) = self.shape.out();
            let (c, oh, ow): (TDim, TDim, TDim) = (self.shape.co.into(), oh.into(), ow.into());
            if self.batch {
                f32::fact([inputs[0].shape[0].clone(), c, oh, ow])
            } else {
                f32::fact([c, oh, ow])
            }
        };
        let mut fact = output_fact(self.reshape.as_ref(), fact);
        if self.quant.is_some() {
            fact.datum_type = u8::datum_type();
        }
        Ok(tvec!(fact))
    }

    fn cost(&self, inputs: &[&TypedFact]) -> TractResult<TVec<(Cost, TDim)>> {
        let (oh, ow) = self.shape.out();
        let s = &self.shape;
        let n = if self.batch { inputs[0].shape[0].clone() } else { 1.into() };
        Ok(tvec!((Cost::FMA(f32::datum_type()), n * (s.co * oh * ow * s.kh * s.kw))))
    }

    as_op!();
}

/// A [`ConstConv`] with one group per channel, its data format (NCHW, CHW or HWC) and its
/// shape, if its padded input holds the kernel: what both depthwise operators take.
pub(super) fn depthwise_shape(c: &ConstConv) -> Option<(DataFormat, ConvShape)> {
    let ps = &c.conv.pool_spec;
    let (ci, h, w) = match (ps.data_format, c.input) {
        (DataFormat::NCHW, &[_, ci, h, w]) | (DataFormat::CHW, &[ci, h, w]) | (DataFormat::HWC, &[h, w, ci]) => {
            (ci, h, w)
        }
        _ => return None,
    };
    let g = c.conv.group;
    if !(g > 1 && g == ci && g == ps.input_channels && g == ps.output_channels) {
        return None;
    }
    let (kh, kw) = c.kernel;
    let shape = ConvShape { ci, h, w, co: ci, kh, kw, pad: c.pad, stride: c.stride };
    (shape.padded().0 >= kh && shape.padded().1 >= kw).then_some((ps.data_format, shape))
}

/// The [`DepthwiseConv`] for `node` of `model` if it is a [`ConstConv`] with one group per
/// channel, NCHW (or CHW, where tract dropped a batch axis of 1).
pub(crate) fn depthwise(model: &TypedModel, node: &TypedNode) -> TractResult<Option<DepthwiseConv>> {
    let Some(c) = super::conv::const_conv(model, node)? else { return Ok(None) };
    let (batch, shape) = match depthwise_shape(&c) {
        Some((DataFormat::NCHW, shape)) => (true, shape),
        Some((DataFormat::CHW, shape)) => (false, shape),
        _ => return Ok(None),
    };
    Ok(Some(DepthwiseConv::new(shape, batch, c.weight, c.bias)?))
}

/// `op` (standing for `node`) reading the u8 input of the [`DequantizeU8`] that makes its
/// input, where that is the dequantiser's only reader ([`DepthwiseConv::reading`],
/// [`super::quant::dequantized_input`]), with the input it reads; else `op` and its own input.
pub(crate) fn past_dequantize(model: &TypedModel, node: &TypedNode, op: DepthwiseConv) -> (DepthwiseConv, OutletId) {
    match super::quant::dequantized_input(model, node.inputs[0]) {
        Some((dq, x)) => (op.reading(dq), x),
        None => (op, node.inputs[0]),
    }
}

/// The [`QuantizeU8`] node that is the sole reader of `last`'s output (the last node a
/// depthwise convolution stands for), where there is one: the convolution can write its bytes.
pub(crate) fn quantized_after(model: &TypedModel, last: &TypedNode) -> TractResult<Option<(QuantizeU8, usize)>> {
    let Some(next) = super::act::sole_consumer(model, last) else { return Ok(None) };
    Ok(super::quant::quantize_u8(model, next)?.map(|q| (q, next.id)))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn direct(s: &ConvShape, input: &[f32], weight: &[f32], bias: &[f32]) -> Vec<f32> {
        super::super::conv::direct(s, s.ci, input, weight, bias)
    }

    use kernel::Rows;

    /// Every row kernel this CPU can run, by name.
    fn paths() -> Vec<(&'static str, Rows)> {
        #[allow(unused_mut)]
        let mut v: Vec<(&'static str, Rows)> = vec![("generic", kernel::rows_generic::<false>)];
        #[cfg(target_arch = "aarch64")]
        v.push(("neon", kernel::rows_neon));
        #[cfg(target_arch = "x86_64")]
        {
            if super::super::avx2_fma() {
                // SAFETY (of the call through this pointer): AVX2 and FMA are present.
                v.push(("avx2", |a, b, c, d, e, f, g| unsafe { kernel::rows_avx2(a, b, c, d, e, f, g) }));
            } else {
                eprintln!("NOTE: no AVX2+FMA here (or PRL_ISA caps it): DepthwiseConv's AVX2 path is not tested here");
            }
            if super::super::avx512_fma() {
                // SAFETY (of the call through this pointer): AVX-512F, AVX2 and FMA are present.
                v.push(("avx512", |a, b, c, d, e, f, g| unsafe { kernel::rows_avx512(a, b, c, d, e, f, g) }));
            } else {
                eprintln!(
                    "NOTE: no AVX-512 here (or PRL_ISA caps it): DepthwiseConv's AVX-512 path is not tested here"
                );
            }
        }
        v
    }

    #[test]
    fn every_path_equals_the_direct_sum() {
        for s in [
            ConvShape { ci: 3, h: 9, w: 7, co: 3, kh: 3, kw: 3, pad: [1, 1, 1, 1], stride: 1 },
            ConvShape { ci: 4, h: 37, w: 70, co: 4, kh: 5, kw: 5, pad: [2, 2, 2, 2], stride: 1 },
            ConvShape { ci: 5, h: 33, w: 65, co: 5, kh: 3, kw: 3, pad: [1, 1, 1, 1], stride: 2 },
            ConvShape { ci: 2, h: 16, w: 16, co: 2, kh: 5, kw: 5, pad: [2, 2, 2, 2], stride: 2 },
            ConvShape { ci: 3, h: 10, w: 13, co: 3, kh: 4, kw: 3, pad: [0, 1, 2, 0], stride: 2 },
            // 8 columns (an 8-column block), 27 (two 16-column blocks, one part-filled).
            ConvShape { ci: 3, h: 8, w: 8, co: 3, kh: 5, kw: 5, pad: [2, 2, 2, 2], stride: 1 },
            ConvShape { ci: 2, h: 9, w: 27, co: 2, kh: 3, kw: 3, pad: [1, 1, 1, 1], stride: 1 },
            // 16 columns, 13 rows: four at a time, then one.
            ConvShape { ci: 2, h: 13, w: 16, co: 2, kh: 3, kw: 3, pad: [1, 1, 1, 1], stride: 1 },
            // Over SERIAL_MACS: channels in groups (on the pool, when there is one).
            ConvShape { ci: 16, h: 64, w: 64, co: 16, kh: 5, kw: 5, pad: [2, 2, 2, 2], stride: 1 },
        ] {
            let n_in = s.ci * s.h * s.w;
            let input: Vec<f32> = (0..2 * n_in).map(|i| ((i * 7919 % 1000) as f32) / 500.0 - 1.0).collect();
            let weight: Vec<f32> = (0..s.ci * s.kh * s.kw).map(|i| ((i * 104729 % 997) as f32) / 498.0 - 1.0).collect();
            let bias: Vec<f32> = (0..s.ci).map(|o| o as f32 / 4.0).collect();
            let op = DepthwiseConv::new(s.clone(), true, &weight, &bias).unwrap();
            let (oh, ow) = s.out();
            for (name, path) in paths() {
                for n in 0..2 {
                    let want = direct(&s, &input[n * n_in..(n + 1) * n_in], &weight, &bias);
                    let mut got = vec![0f32; s.ci * oh * ow];
                    let mut scratch = op.scratch();
                    let taps = s.kh * s.kw;
                    for (c, dst) in got.chunks_exact_mut(oh * ow).enumerate() {
                        let src = &input[n * n_in + c * s.h * s.w..][..s.h * s.w];
                        op.channel(c, src, dst, &mut scratch);
                        // The same channel through the path under test.
                        let ws = &weight[c * taps..(c + 1) * taps];
                        path(&scratch, s.phase().1, &op.offsets, ws, bias[c], dst, ow);
                    }
                    let worst = got.iter().zip(&want).map(|(a, b)| (a - b).abs()).fold(0.0f32, f32::max);
                    assert!(worst < 1e-4, "{name} {s:?} image {n}: off by {worst}");
                }
            }
            // And the operator as tract runs it.
            let x = tract_ndarray::Array4::from_shape_vec((2, s.ci, s.h, s.w), input.clone()).unwrap();
            let out = op.eval(&EvalContext::out_of_plan(), tvec![x.into_tensor().into_tvalue()]).unwrap();
            let out = out[0].try_as_plain_ram().unwrap();
            let out = out.as_slice::<f32>().unwrap();
            for n in 0..2 {
                let want = direct(&s, &input[n * n_in..(n + 1) * n_in], &weight, &bias);
                let got = &out[n * want.len()..(n + 1) * want.len()];
                let worst = got.iter().zip(&want).map(|(a, b)| (a - b).abs()).fold(0.0f32, f32::max);
                assert!(worst < 1e-4, "op {s:?} image {n}: off by {worst}");
            }
        }
    }

    /// The u8 tests' layers: stride 1 on the calling thread, stride 2, and stride 1 in channel
    /// groups (over the pool where there is one).
    fn u8_shapes() -> [ConvShape; 3] {
        [
            ConvShape { ci: 3, h: 9, w: 7, co: 3, kh: 3, kw: 3, pad: [1, 1, 1, 1], stride: 1 },
            ConvShape { ci: 5, h: 33, w: 65, co: 5, kh: 3, kw: 3, pad: [1, 1, 1, 1], stride: 2 },
            ConvShape { ci: 16, h: 64, w: 64, co: 16, kh: 5, kw: 5, pad: [2, 2, 2, 2], stride: 1 },
        ]
    }

    /// Reading u8 data through a dequantiser (and its activation) gives, bit for bit, the
    /// convolution of what the dequantiser writes: stride 1 and 2, one layer on the calling
    /// thread and one in channel groups.
    #[test]
    fn reading_u8_equals_the_convolution_of_the_dequantised_input() {
        let relu6 = Activation { lo: 0.0, hi: 6.0, hard_swish: false };
        let hard_swish = Activation { hard_swish: true, ..Activation::NONE };
        for (s, act) in u8_shapes().into_iter().zip([relu6, hard_swish, hard_swish]) {
            let n_in = s.ci * s.h * s.w;
            let bytes: Vec<u8> = (0..n_in).map(|i| (i * 7919 % 251) as u8).collect();
            let weight: Vec<f32> = (0..s.ci * s.kh * s.kw).map(|i| ((i * 104729 % 997) as f32) / 498.0 - 1.0).collect();
            let bias: Vec<f32> = (0..s.ci).map(|o| o as f32 / 4.0).collect();
            let dq = DequantizeU8::new(0.0473, 117).with_act(act);
            let mut dequantised = vec![0f32; n_in];
            dq.apply(&bytes, &mut dequantised);
            assert!(dequantised.iter().any(|&v| v > 0.0) && dequantised.iter().any(|&v| v <= 0.0));
            let op = DepthwiseConv::new(s.clone(), true, &weight, &bias).unwrap();
            let reading = op.clone().reading(dq);
            let run = |op: &DepthwiseConv, x: Tensor| {
                let out = op.eval(&EvalContext::out_of_plan(), tvec![x.into_tvalue()]).unwrap();
                out[0].try_as_plain_ram().unwrap().as_slice::<f32>().unwrap().to_vec()
            };
            let dims = (1, s.ci, s.h, s.w);
            let want = run(&op, tract_ndarray::Array4::from_shape_vec(dims, dequantised).unwrap().into_tensor());
            let got = run(&reading, tract_ndarray::Array4::from_shape_vec(dims, bytes).unwrap().into_tensor());
            assert!(got.iter().zip(&want).all(|(a, b)| a.to_bits() == b.to_bits()), "{s:?}");
        }
    }

    /// Writing u8 through a quantiser gives, byte for byte, what the quantiser makes of the
    /// f32 output (activation included): stride 1 and 2, f32 input and u8 read through a
    /// dequantiser, on the calling thread and over a pool of two.
    #[test]
    fn writing_u8_equals_the_quantised_output() {
        use tract_linalg::multithread::{multithread_tract_scope, Executor};
        let hard_swish = Activation { hard_swish: true, ..Activation::NONE };
        for (s, reads) in u8_shapes().into_iter().zip([false, true, false]) {
            let n_in = s.ci * s.h * s.w;
            let weight: Vec<f32> = (0..s.ci * s.kh * s.kw).map(|i| ((i * 104729 % 997) as f32) / 998.0 - 0.5).collect();
            let bias: Vec<f32> = (0..s.ci).map(|o| o as f32 / 8.0 - 0.3).collect();
            let op = DepthwiseConv { act: hard_swish, ..DepthwiseConv::new(s.clone(), true, &weight, &bias).unwrap() };
            let (op, x) = if reads {
                let bytes: Vec<u8> = (0..n_in).map(|i| (i * 7919 % 251) as u8).collect();
                let op = op.reading(DequantizeU8::new(0.0173, 117));
                (op, tract_ndarray::Array4::from_shape_vec((1, s.ci, s.h, s.w), bytes).unwrap().into_tensor())
            } else {
                let values: Vec<f32> = (0..n_in).map(|i| ((i * 7919 % 1000) as f32) / 500.0 - 1.0).collect();
                (op, tract_ndarray::Array4::from_shape_vec((1, s.ci, s.h, s.w), values).unwrap().into_tensor())
            };
            let q = QuantizeU8::new(1.0 / 0.013, 21);
            let writing = op.clone().writing(q.clone());
            let run = |op: &DepthwiseConv, e: Executor| {
                multithread_tract_scope(e, || {
                    op.eval(&EvalContext::out_of_plan(), tvec![x.clone().into_tvalue()]).unwrap()
                })
            };
            let values = run(&op, Executor::SingleThread);
            let values = values[0].try_as_plain_ram().unwrap();
            let values = values.as_slice::<f32>().unwrap();
            let mut want = vec![0u8; values.len()];
            q.apply(values, &mut want);
            let distinct = want.iter().collect::<std::collections::HashSet<_>>().len();
            assert!(distinct > 10 && want.contains(&0), "{s:?}: {distinct} distinct bytes");
            for e in [Executor::SingleThread, Executor::multithread(2)] {
                let got = run(&writing, e);
                assert_eq!(got[0].datum_type(), u8::datum_type());
                let got = got[0].try_as_plain_ram().unwrap();
                // SAFETY: the output is u8.
                let got = unsafe { got.as_slice_unchecked::<u8>() };
                assert!(got == want.as_slice(), "{s:?}: other bytes");
            }
        }
    }
}
