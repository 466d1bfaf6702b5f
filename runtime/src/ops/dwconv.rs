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

mod kernel;

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
mod tests;
