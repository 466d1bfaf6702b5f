//! Depthwise convolutions with constant weights on channels-last data (`HWC`), as
//! [`DepthwiseConvHwc`]: what tract's declutter makes of MobileNet's depthwise layers on aarch64
//! (it moves them to channels-last there, where [`super::DepthwiseConv`] does not match).
//!
//! Channels are the vector lanes: an output position's channels `c..c+16` (four NEON registers)
//! accumulate, tap by tap in `(i, j)` order, weight `[tap][c..]` times input `[y', x', c..]`;
//! four positions at a time share each tap's weight loads (16 accumulators). Taps that fall in
//! the zero padding are skipped (the channels-first kernel adds their zero products instead:
//! the same sums).

use std::sync::Arc;

use tract_nnef::internal::*;
use tract_nnef::tract_core::ops::nn::DataFormat;

use super::conv::ConvShape;
use super::{output_tensor, par_chunks, same_bits, SERIAL_MACS};
use crate::isa::F32Kernel;

/// `out[y,x,c] = bias[c] + Σ_{i,j} pad(input)[s·y+i, s·x+j, c]·weight[c,0,i,j]` on `[h, w, c]`
/// data, stride `s` 1 or 2, zero padding.
#[derive(Clone)]
pub struct DepthwiseConvHwc {
    shape: ConvShape,
    /// `[tap][c]`: each tap's weights for every channel, contiguous.
    weights: Arc<Vec<f32>>,
    bias: Arc<Vec<f32>>,
}

impl std::fmt::Debug for DepthwiseConvHwc {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "DepthwiseConvHwc({:?})", self.shape)
    }
}

impl PartialEq for DepthwiseConvHwc {
    fn eq(&self, other: &Self) -> bool {
        self.shape == other.shape && same_bits(&self.weights, &other.weights) && same_bits(&self.bias, &other.bias)
    }
}

impl Eq for DepthwiseConvHwc {}

impl DepthwiseConvHwc {
    /// A depthwise convolution of `shape` (`ci == co`) with weights `[c, 1, kh, kw]` row-major
    /// and `bias` (one value or one per channel), on `[h, w, c]` data.
    pub fn new(shape: ConvShape, weight: &[f32], bias: &[f32]) -> TractResult<DepthwiseConvHwc> {
        let (c, taps) = (shape.ci, shape.kh * shape.kw);
        ensure!(shape.co == c && matches!(shape.stride, 1 | 2), "DepthwiseConvHwc: shape {shape:?}");
        ensure!(weight.len() == c * taps, "DepthwiseConvHwc: {} weights for {shape:?}", weight.len());
        ensure!(bias.len() == 1 || bias.len() == c, "DepthwiseConvHwc: {} bias values for {shape:?}", bias.len());
        let bias = (0..c).map(|o| if bias.len() == 1 { bias[0] } else { bias[o] }).collect();
        let weights = (0..taps).flat_map(|t| (0..c).map(move |ch| weight[ch * taps + t])).collect();
        Ok(DepthwiseConvHwc { shape, weights: Arc::new(weights), bias: Arc::new(bias) })
    }

    /// Output row `y` (`ow · c` values) into `dst`.
    fn row(&self, input: &[f32], y: usize, dst: &mut [f32]) {
        match crate::isa::f32_kernel() {
            // SAFETY: the CPU has the features the function is compiled for (the table's needs).
            #[cfg(target_arch = "x86_64")]
            F32Kernel::Avx512 => unsafe { row_avx512(self, input, y, dst) },
            // SAFETY: as above.
            #[cfg(target_arch = "x86_64")]
            F32Kernel::Avx2Fma => unsafe { row_avx2(self, input, y, dst) },
            F32Kernel::Neon => row_generic::<true>(self, input, y, dst),
            _ => row_generic::<false>(self, input, y, dst),
        }
    }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx2,fma")]
unsafe fn row_avx512(op: &DepthwiseConvHwc, input: &[f32], y: usize, dst: &mut [f32]) {
    row_generic::<true>(op, input, y, dst)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn row_avx2(op: &DepthwiseConvHwc, input: &[f32], y: usize, dst: &mut [f32]) {
    row_generic::<true>(op, input, y, dst)
}

/// The valid kernel offsets `lo..hi` along one axis for output index `o`: input `s·o + k − pad`
/// must lie in `0..len`.
#[inline(always)]
fn valid(o: usize, s: usize, pad: usize, k: usize, len: usize) -> (usize, usize) {
    let start = (s * o) as isize - pad as isize;
    let lo = (-start).max(0) as usize;
    let hi = ((len as isize - start).min(k as isize)).max(lo as isize) as usize;
    (lo, hi)
}

/// One output row, four positions at a time where every tap of the four is inside the input,
/// one position at a time elsewhere.
#[inline(always)]
fn row_generic<const FUSED: bool>(op: &DepthwiseConvHwc, input: &[f32], y: usize, dst: &mut [f32]) {
    let s = &op.shape;
    let (c, (_, ow)) = (s.ci, s.out());
    let rows = valid(y, s.stride, s.pad[0], s.kh, s.h);
    let interior = |x: usize| valid(x, s.stride, s.pad[1], s.kw, s.w) == (0, s.kw);
    let mut x = 0;
    while x < ow {
        if x + 4 <= ow && interior(x) && interior(x + 3) {
            let xs = [x, x + 1, x + 2, x + 3];
            channels::<FUSED, 4>(op, input, y, (rows, (0, s.kw)), xs, &mut dst[x * c..(x + 4) * c]);
            x += 4;
        } else {
            let cols = valid(x, s.stride, s.pad[1], s.kw, s.w);
            channels::<FUSED, 1>(op, input, y, (rows, cols), [x], &mut dst[x * c..(x + 1) * c]);
            x += 1;
        }
    }
}

/// Every channel of positions `xs` of output row `y`, taps `rows` x `cols` (the valid ones):
/// 16 channels at a time, then 8, 4 and 1.
#[inline(always)]
fn channels<const FUSED: bool, const P: usize>(
    op: &DepthwiseConvHwc,
    input: &[f32],
    y: usize,
    taps: ((usize, usize), (usize, usize)),
    xs: [usize; P],
    out: &mut [f32],
) {
    let c = op.shape.ci;
    let mut ch = 0;
    while ch < c {
        ch += match c - ch {
            16.. => lanes::<FUSED, P, 16>(op, input, y, taps, xs, ch, out),
            8..=15 => lanes::<FUSED, P, 8>(op, input, y, taps, xs, ch, out),
            4..=7 => lanes::<FUSED, P, 4>(op, input, y, taps, xs, ch, out),
            _ => lanes::<FUSED, P, 1>(op, input, y, taps, xs, ch, out),
        };
    }
}

/// Channels `ch..ch+L` of positions `xs` (all in output row `y`), into `out` (`P · c` values,
/// position-major); returns `L`.
#[inline(always)]
fn lanes<const FUSED: bool, const P: usize, const L: usize>(
    op: &DepthwiseConvHwc,
    input: &[f32],
    y: usize,
    ((i0, i1), (j0, j1)): ((usize, usize), (usize, usize)),
    xs: [usize; P],
    ch: usize,
    out: &mut [f32],
) -> usize {
    let s = &op.shape;
    let c = s.ci;
    if i0 == i1 || j0 == j1 {
        // No tap inside the input (a kernel wholly in the padding): the bias alone.
        for p in 0..P {
            out[p * c + ch..p * c + ch + L].copy_from_slice(&op.bias[ch..ch + L]);
        }
        return L;
    }
    // Input offset of each position's first valid tap, and the last one read.
    let (iy0, ix0) = (s.stride * y + i0 - s.pad[0], xs.map(|x| s.stride * x + j0 - s.pad[1]));
    let base = ix0.map(|ix| (iy0 * s.w + ix) * c + ch);
    let reach = ((i1 - 1 - i0) * s.w + (j1 - 1 - j0)) * c + L;
    assert!(base.iter().all(|&b| b + reach <= input.len()) && ch + L <= c);
    assert!((i1 - 1) * s.kw + j1 - 1 < s.kh * s.kw && P * c <= out.len());
    let (inp, wts) = (input.as_ptr(), op.weights.as_ptr());
    let b: &[f32; L] = op.bias[ch..ch + L].try_into().expect("L channels");
    let mut acc = [*b; P];
    for i in i0..i1 {
        for j in j0..j1 {
            let tap = ((i - i0) * s.w + (j - j0)) * c;
            // SAFETY: tap `(i, j)` is at most `(i1-1, j1-1)`: its `L` weights from `ch` lie in
            // `weights` (`[tap][c]`, asserted), and every position's `L` inputs from
            // `base + tap` lie in `input` (`tap + L <= reach`, asserted).
            let w: &[f32; L] = unsafe { &*(wts.add((i * s.kw + j) * c + ch) as *const [f32; L]) };
            for (a, &at) in acc.iter_mut().zip(&base) {
                // SAFETY: as above.
                let v: &[f32; L] = unsafe { &*(inp.add(at + tap) as *const [f32; L]) };
                for l in 0..L {
                    a[l] = if FUSED { w[l].mul_add(v[l], a[l]) } else { a[l] + w[l] * v[l] };
                }
            }
        }
    }
    for (p, a) in acc.iter().enumerate() {
        out[p * c + ch..p * c + ch + L].copy_from_slice(a);
    }
    L
}

impl Op for DepthwiseConvHwc {
    fn name(&self) -> StaticName {
        "DepthwiseConvHwc".into()
    }

    fn info(&self) -> TractResult<Vec<String>> {
        let s = &self.shape;
        Ok(vec![format!("{}x{} kernel, stride {}, {} channels, pad {:?}, HWC", s.kh, s.kw, s.stride, s.ci, s.pad)])
    }

    op_as_typed_op!();
}

impl EvalOp for DepthwiseConvHwc {
    op_out_of_plan!();

    fn eval(&self, _ctx: &EvalContext, inputs: TVec<TValue>) -> TractResult<TVec<TValue>> {
        let input = args_1!(inputs);
        let s = &self.shape;
        ensure!(input.shape() == [s.h, s.w, s.ci], "DepthwiseConvHwc: input {:?} for {s:?}", input.shape());
        let input = input.try_as_plain_ram()?;
        let input = input.as_slice::<f32>()?;
        let (oh, ow) = s.out();
        let row = ow * s.ci;
        let macs = oh * row * s.kh * s.kw;
        let out = output_tensor(&[oh, ow, s.ci], |out: &mut [f32]| {
            if macs < SERIAL_MACS {
                out.chunks_exact_mut(row).enumerate().for_each(|(y, d)| self.row(input, y, d));
            } else {
                par_chunks(out, row, |y, d| self.row(input, y, d));
            }
            Ok(())
        })?;
        Ok(tvec!(out.into_tvalue()))
    }
}

impl TypedOp for DepthwiseConvHwc {
    fn output_facts(&self, _inputs: &[&TypedFact]) -> TractResult<TVec<TypedFact>> {
        let (oh, ow) = self.shape.out();
        Ok(tvec!(f32::fact([oh, ow, self.shape.co])))
    }

    fn cost(&self, _inputs: &[&TypedFact]) -> TractResult<TVec<(Cost, TDim)>> {
        let (oh, ow) = self.shape.out();
        let s = &self.shape;
        Ok(tvec!((Cost::FMA(f32::datum_type()), (s.co * oh * ow * s.kh * s.kw).into())))
    }

    as_op!();
}

/// The [`DepthwiseConvHwc`] for `node` of `model` if it is a [`super::conv::ConstConv`] with one
/// group per channel on `HWC` data.
pub(crate) fn depthwise_hwc(model: &TypedModel, node: &TypedNode) -> TractResult<Option<DepthwiseConvHwc>> {
    let Some(c) = super::conv::const_conv(model, node)? else { return Ok(None) };
    let Some((DataFormat::HWC, shape)) = super::dwconv::depthwise_shape(&c) else { return Ok(None) };
    Ok(Some(DepthwiseConvHwc::new(shape, c.weight, c.bias)?))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Every path this CPU can run against the direct sum on channels-first data, transposed.
    #[test]
    fn equals_the_direct_sum_on_channels_last_data() {
        for s in [
            ConvShape { ci: 72, h: 9, w: 11, co: 72, kh: 3, kw: 3, pad: [1, 1, 1, 1], stride: 1 },
            ConvShape { ci: 88, h: 16, w: 16, co: 88, kh: 5, kw: 5, pad: [2, 2, 2, 2], stride: 2 },
            ConvShape { ci: 21, h: 13, w: 7, co: 21, kh: 3, kw: 3, pad: [1, 1, 1, 1], stride: 2 },
            ConvShape { ci: 16, h: 70, w: 70, co: 16, kh: 5, kw: 5, pad: [2, 2, 2, 2], stride: 1 },
            ConvShape { ci: 5, h: 6, w: 9, co: 5, kh: 3, kw: 3, pad: [0, 0, 0, 0], stride: 1 },
        ] {
            let (c, hw) = (s.ci, s.h * s.w);
            let chw: Vec<f32> = (0..c * hw).map(|i| ((i * 7919 % 1000) as f32) / 500.0 - 1.0).collect();
            let weight: Vec<f32> = (0..c * s.kh * s.kw).map(|i| ((i * 104729 % 997) as f32) / 498.0 - 1.0).collect();
            let bias: Vec<f32> = (0..c).map(|o| o as f32 / 4.0).collect();
            let want = super::super::conv::direct(&s, c, &chw, &weight, &bias);
            let hwc: Vec<f32> = (0..hw * c).map(|i| chw[(i % c) * hw + i / c]).collect();
            let op = DepthwiseConvHwc::new(s.clone(), &weight, &bias).unwrap();
            let (oh, ow) = s.out();
            let mut paths: Vec<(&str, Vec<f32>)> = vec![];
            let x = tract_ndarray::Array3::from_shape_vec((s.h, s.w, c), hwc.clone()).unwrap();
            let out = op.eval(&EvalContext::out_of_plan(), tvec![x.into_tensor().into_tvalue()]).unwrap();
            paths.push(("dispatched", out[0].try_as_plain_ram().unwrap().as_slice::<f32>().unwrap().to_vec()));
            for (name, fused) in [("portable", false), ("fused", true)] {
                let mut got = vec![0f32; oh * ow * c];
                for (y, d) in got.chunks_exact_mut(ow * c).enumerate() {
                    if fused {
                        row_generic::<true>(&op, &hwc, y, d);
                    } else {
                        row_generic::<false>(&op, &hwc, y, d);
                    }
                }
                paths.push((name, got));
            }
            for (name, got) in paths {
                let worst =
                    (0..oh * ow * c).map(|i| (got[i] - want[(i % c) * oh * ow + i / c]).abs()).fold(0.0f32, f32::max);
                assert!(worst < 1e-4, "{name} {s:?}: off by {worst}");
            }
        }
    }
}
