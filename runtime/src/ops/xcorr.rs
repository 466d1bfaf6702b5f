//! The depthwise cross-correlation of search features with template features (`s1..s5`) as one
//! operator of our own.
//!
//! In the official network each correlation is a depthwise convolution whose kernel is a graph
//! input (the template features). tract runs such a convolution as a direct loop made for small
//! constant kernels: `s1` (96 channels, 69x69 input, 29x29 kernel) took 53 ms of a 336 ms frame
//! on 2 threads. [`super::accelerate`] replaces every depthwise `Conv` with a non-constant
//! kernel by [`DepthwiseXCorr`], which keeps 16-column strips of output rows in registers
//! ([`super::xcorr_kernel`]) and spreads channels over tract's thread pool.
//!
//! In an int8 plan the search features come out of integer layers as u8 and were dequantised
//! for the correlation alone: a pass writing f32 maps of up to 1.8 MB that the memory bus, not
//! the cores, bounds (PRL-Track's five took 0.8 ms of a 25 ms two-thread step and did not
//! scale with threads). The correlation reads the u8 features instead and dequantises each
//! channel's plane into the thread's scratch on its way ([`DepthwiseXCorr::reading`]).

use tract_nnef::internal::*;
use tract_nnef::tract_core::ops::cnn::{Conv, KernelFormat};
use tract_nnef::tract_core::ops::nn::DataFormat;

use super::quant::{DequantizeU8, Planes};
use super::xcorr_kernel::{correlate_channel, Geometry};
use super::{all_ones, no_padding, output_tensor_written, par_chunks};

/// `out[n,c,y,x] = bias[c] + Σ_{i,j} input[n,c,y+i,x+j]·kernel[c,0,i,j]`: inputs `input`
/// `[N,C,H,W]`, `kernel` `[C,1,kh,kw]` and `bias` (a scalar or `[C]`), all f32; no padding, stride 1.
/// Or `input` u8, dequantised plane by plane on its way ([`Self::reading`]).
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct DepthwiseXCorr {
    /// The input is u8, dequantised by this (and its activation) plane by plane.
    dequant: Option<DequantizeU8>,
}

impl DepthwiseXCorr {
    /// The correlation of f32 inputs.
    pub fn new() -> Self {
        DepthwiseXCorr::default()
    }

    /// The correlation of `dequant`'s output, reading its u8 input instead: each channel's
    /// plane is dequantised (with the dequantiser's activation) into the thread's scratch, the
    /// values the dequantiser would have written, so the same outputs bit for bit.
    pub(crate) fn reading(dequant: DequantizeU8) -> Self {
        DepthwiseXCorr { dequant: Some(dequant) }
    }
}

impl Op for DepthwiseXCorr {
    fn name(&self) -> StaticName {
        "DepthwiseXCorr".into()
    }

    fn info(&self) -> TractResult<Vec<String>> {
        Ok(if self.dequant.is_some() { vec!["u8 input dequantised".to_string()] } else { vec![] })
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
        let (kernel, bias) = (kernel.try_as_plain_ram()?, bias.try_as_plain_ram()?);
        let (kernel, bias) = (kernel.as_slice::<f32>()?, bias.as_slice::<f32>()?);
        ensure!(bias.len() == 1 || bias.len() == c, "DepthwiseXCorr: {} bias values for {c} channels", bias.len());
        // The data: f32, or u8 dequantised plane by plane.
        let data = Planes::of("DepthwiseXCorr", &input, self.dequant.as_ref())?;
        let plane = g.out_h() * g.out_w();
        // Each thread's scratch is its own and kept from frame to frame (correlate_channel
        // writes every value it reads; a dequantised plane is written whole before it is read).
        let dequantised = data.buffer_len(h * w);
        let one = |plane_ix: usize, dst: &mut [f32]| {
            super::with_padded(dequantised + g.scratch_len(), &[], |buffer| {
                let (plane, scratch) = buffer.split_at_mut(dequantised);
                let src = data.plane(plane_ix * h * w..(plane_ix + 1) * h * w, plane);
                let ch = plane_ix % c;
                let k = &kernel[ch * kh * kw..(ch + 1) * kh * kw];
                let b = if bias.len() == 1 { bias[0] } else { bias[ch] };
                correlate_channel(g, src, k, b, dst, scratch);
            })
        };
        // SAFETY: every channel's plane is written whole (`correlate_channel` writes every
        // output of its channel).
        let out = unsafe {
            output_tensor_written(&[n, c, g.out_h(), g.out_w()], |out: &mut [f32]| {
                par_chunks(out, plane, one);
                Ok(())
            })?
        };
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

/// The [`DepthwiseXCorr`] for `node` of `model` if it is a depthwise cross-correlation
/// ([`matches`]), with its inputs: the u8 data of a dequantiser that feeds it alone where there
/// is one ([`DepthwiseXCorr::reading`]).
pub(crate) fn xcorr(model: &TypedModel, node: &TypedNode) -> TractResult<Option<(DepthwiseXCorr, TVec<OutletId>)>> {
    if !matches(model, node)? {
        return Ok(None);
    }
    let mut inputs: TVec<OutletId> = node.inputs.iter().copied().collect();
    Ok(Some(match super::quant::dequantized_input(model, inputs[0]) {
        Some((dq, x)) => {
            inputs[0] = x;
            (DepthwiseXCorr::reading(dq), inputs)
        }
        None => (DepthwiseXCorr::new(), inputs),
    }))
}

/// Whether `node` of `model` is a depthwise cross-correlation: a float `Conv` with one group
/// per channel, a kernel that is not a constant, no padding, stride and dilation 1, NCHW.
fn matches(model: &TypedModel, node: &TypedNode) -> TractResult<bool> {
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ops::act::Activation;

    /// Reading u8 data through a dequantiser (and its activation) gives, bit for bit, the
    /// correlation of what the dequantiser writes, with a kernel as wide as the input and one
    /// that leaves two strips of output columns, a bias per channel and a shared one.
    #[test]
    fn reading_u8_equals_the_correlation_of_the_dequantised_input() {
        let relu = Activation { lo: 0.0, hi: f32::INFINITY, hard_swish: false };
        for (n, c, h, w, kh, kw, act, per_channel) in [
            (1, 3, 6, 75, 3, 3, relu, true),
            (2, 5, 13, 13, 13, 13, Activation::NONE, false),
            (1, 4, 31, 33, 7, 5, relu, true),
        ] {
            let n_in = n * c * h * w;
            let bytes: Vec<u8> = (0..n_in).map(|i| (i * 7919 % 251) as u8).collect();
            let kernel: Vec<f32> = (0..c * kh * kw).map(|i| ((i * 104729 % 997) as f32) / 498.0 - 1.0).collect();
            let bias: Vec<f32> = if per_channel { (0..c).map(|o| o as f32 / 4.0).collect() } else { vec![0.5] };
            let dq = DequantizeU8::new(0.0473, 117).with_act(act);
            let mut dequantised = vec![0f32; n_in];
            dq.apply(&bytes, &mut dequantised);
            assert!(dequantised.iter().any(|&v| v > 0.0) && dequantised.iter().any(|&v| v <= 0.0));
            let run = |op: &DepthwiseXCorr, x: Tensor| {
                let k = tract_ndarray::Array4::from_shape_vec((c, 1, kh, kw), kernel.clone()).unwrap().into_tensor();
                let b = tract_ndarray::Array1::from_vec(bias.clone()).into_tensor();
                let out =
                    op.eval(&EvalContext::out_of_plan(), tvec![x.into_tvalue(), k.into_tvalue(), b.into_tvalue()]);
                out.unwrap()[0].try_as_plain_ram().unwrap().as_slice::<f32>().unwrap().to_vec()
            };
            let dims = (n, c, h, w);
            let want = run(
                &DepthwiseXCorr::new(),
                tract_ndarray::Array4::from_shape_vec(dims, dequantised).unwrap().into_tensor(),
            );
            let got = run(
                &DepthwiseXCorr::reading(dq),
                tract_ndarray::Array4::from_shape_vec(dims, bytes).unwrap().into_tensor(),
            );
            assert_eq!(got.len(), n * c * (h - kh + 1) * (w - kw + 1));
            assert!(got.iter().zip(&want).all(|(a, b)| a.to_bits() == b.to_bits()), "{:?}", (n, c, h, w, kh, kw));
        }
    }
}
