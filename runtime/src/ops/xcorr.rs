//! The depthwise cross-correlation of search features with template features (`s1..s5`) as one
//! operator of our own.
//!
//! In the official network each correlation is a depthwise convolution whose kernel is a graph
//! input (the template features). tract runs such a convolution as a direct loop made for small
//! constant kernels: `s1` (96 channels, 69x69 input, 29x29 kernel) took 53 ms of a 336 ms frame
//! on 2 threads. [`super::accelerate`] replaces every depthwise `Conv` with a non-constant
//! kernel by [`DepthwiseXCorr`], which keeps 16-column strips of output rows in registers
//! ([`super::xcorr_kernel`]) and spreads channels over tract's thread pool.

use tract_nnef::internal::*;
use tract_nnef::tract_core::ops::cnn::{Conv, KernelFormat};
use tract_nnef::tract_core::ops::nn::DataFormat;

use super::xcorr_kernel::{correlate_channel, Geometry};
use super::{all_ones, no_padding, output_tensor, par_chunks};

/// `out[n,c,y,x] = bias[c] + Σ_{i,j} input[n,c,y+i,x+j]·kernel[c,0,i,j]`: inputs `input`
/// `[N,C,H,W]`, `kernel` `[C,1,kh,kw]` and `bias` (a scalar or `[C]`), all f32; no padding, stride 1.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct DepthwiseXCorr;

impl Op for DepthwiseXCorr {
    fn name(&self) -> StaticName {
        "DepthwiseXCorr".into()
    }

    op_as_typed_op!();
}

impl EvalOp for DepthwiseXCorr {
    op_out_of_plan!();

    fn eval(&self, _ctx: &EvalContext, inputs: TVec<TValue>) -> TractResult<TVec<TValue>> {
        let (input, kernel, bias) = args_3!(inputs);
        let [n, c, h, w] = *input.shape() else { bail!("DepthwiseXCorr: input {:?} is not rank 4", input.shape()) };
        let [kc, 1, kh, kw] = *kernel.shape() else {
            bail!("DepthwiseXCorr: kernel {:?} is not [C,1,kh,kw]", kernel.shape())
        };
        ensure!(
            kc == c && kh <= h && kw <= w,
            "DepthwiseXCorr: kernel {:?} for input {:?}",
            kernel.shape(),
            input.shape()
        );
        let g = Geometry { h, w, kh, kw };
        let (input, kernel, bias) = (input.try_as_plain_ram()?, kernel.try_as_plain_ram()?, bias.try_as_plain_ram()?);
        let (input, kernel, bias) = (input.as_slice::<f32>()?, kernel.as_slice::<f32>()?, bias.as_slice::<f32>()?);
        ensure!(bias.len() == 1 || bias.len() == c, "DepthwiseXCorr: {} bias values for {c} channels", bias.len());
        let plane = g.out_h() * g.out_w();
        let one = |plane_ix: usize, dst: &mut [f32], scratch: &mut [f32]| {
            let ch = plane_ix % c;
            let src = &input[plane_ix * h * w..(plane_ix + 1) * h * w];
            let k = &kernel[ch * kh * kw..(ch + 1) * kh * kw];
            let b = if bias.len() == 1 { bias[0] } else { bias[ch] };
            correlate_channel(g, src, k, b, dst, scratch);
        };
        let out = output_tensor(&[n, c, g.out_h(), g.out_w()], |out: &mut [f32]| {
            // Each thread's scratch is its own and kept from frame to frame (correlate_channel
            // writes every value it reads).
            par_chunks(out, plane, |i, dst| super::with_padded(g.scratch_len(), &[], |s| one(i, dst, s)));
            Ok(())
        })?;
        Ok(tvec!(out.into_tvalue()))
    }
}

impl TypedOp for DepthwiseXCorr {
    fn output_facts(&self, inputs: &[&TypedFact]) -> TractResult<TVec<TypedFact>> {
        let (input, kernel) = (&inputs[0].shape, &inputs[1].shape);
        ensure!(input.rank() == 4 && kernel.rank() == 4, "DepthwiseXCorr: input {input:?}, kernel {kernel:?}");
        let out = |d: usize| input[d].clone() - kernel[d].clone() + 1;
        Ok(tvec!(f32::fact([input[0].clone(), input[1].clone(), out(2), out(3)])))
    }

    fn cost(&self, inputs: &[&TypedFact]) -> TractResult<TVec<(Cost, TDim)>> {
        let out = self.output_facts(inputs)?.remove(0);
        let taps = inputs[1].shape[2].clone() * inputs[1].shape[3].clone();
        Ok(tvec!((Cost::FMA(f32::datum_type()), out.shape.volume() * taps)))
    }

    as_op!();
}

/// Whether `node` of `model` is a depthwise cross-correlation: a float `Conv` with one group
/// per channel, a kernel that is not a constant, no padding, stride and dilation 1, NCHW.
pub(crate) fn matches(model: &TypedModel, node: &TypedNode) -> TractResult<bool> {
    let Some(conv) = node.op_as::<Conv>() else { return Ok(false) };
    let facts = model.node_input_facts(node.id)?;
    let ps = &conv.pool_spec;
    Ok(conv.q_params.is_none()
        && conv.kernel_fmt == KernelFormat::OIHW
        && ps.data_format == DataFormat::NCHW
        && ps.kernel_shape.len() == 2
        && conv.group == ps.input_channels
        && ps.input_channels == ps.output_channels
        && all_ones(&ps.strides)
        && all_ones(&ps.dilations)
        && no_padding(&ps.padding)
        && facts.len() == 3
        && facts[1].konst.is_none()
        && facts.iter().all(|f| f.datum_type == f32::datum_type())
        && facts[1].shape.as_concrete().is_some_and(|s| s.len() == 4 && s[1] == 1))
}
