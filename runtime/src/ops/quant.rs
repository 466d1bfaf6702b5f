//! The quantisation of f32 activations to u8 at the entry of every int8 region, as
//! [`QuantizeU8`]: the formula of tract's `QuantizeLinearU8`, bit for bit, on vector lanes; and
//! the way back at its exit, as [`DequantizeU8`] (tract's `DequantizeLinearF32` on u8).
//!
//! tract evaluates `QuantizeLinearU8` one element at a time through a branchy software
//! round-half-to-even; in NanoTrack's int8 plan its 21 instances took 1.6 ms of a 5.5 ms search
//! step (about 1 ns an element). Here the same `round_ties_even(x * scale) + zero_point`,
//! clamped to 0..=255, runs on AVX-512 or AVX2 lanes (`vroundps`), or portably.

use tract_nnef::internal::*;
use tract_nnef::tract_core::ops::element_wise::ElementWiseOp;
use tract_nnef::tract_core::ops::quant::{DequantizeLinearF32, QuantizeLinearU8};

use super::act::{Activation, Tail};
use super::{output_tensor_written, par_chunks, SHARE};

/// `y = clamp(round_half_even(x * scale) + zero_point, 0, 255)` for f32 `x` (`scale` is the
/// reciprocal of the tensor's quantisation step, as in tract's `QuantizeLinearU8`).
#[derive(Debug, Clone, PartialEq)]
pub struct QuantizeU8 {
    scale: f32,
    zero_point: u8,
}

impl Eq for QuantizeU8 {}

impl QuantizeU8 {
    /// The quantiser with `scale` (1 / step) and `zero_point`.
    pub fn new(scale: f32, zero_point: u8) -> Self {
        QuantizeU8 { scale, zero_point }
    }

    /// `ys = quantise(xs)`, on this thread: the bytes the operator writes for these values.
    pub(crate) fn apply(&self, xs: &[f32], ys: &mut [u8]) {
        kernel::quantize(xs, ys, self.scale, self.zero_point as i32)
    }
}

/// The portable formula: tract's for every value whose scaled magnitude fits an `i32`; NaN gives
/// the zero point as there, and values beyond (±inf) saturate to 0 or 255, as ONNX's
/// `QuantizeLinear` says (tract's own addition overflows there: a panic in a debug build, a
/// wrap to 0 in a release one).
#[inline(always)]
fn one(x: f32, scale: f32, zp: i32) -> u8 {
    ((x * scale).round_ties_even() as i32).saturating_add(zp).clamp(0, 255) as u8
}

mod kernel {
    /// Quantise `xs` into `ys` on the best path this CPU has.
    pub(super) fn quantize(xs: &[f32], ys: &mut [u8], scale: f32, zp: i32) {
        #[cfg(target_arch = "x86_64")]
        use crate::isa::F32Kernel;
        match crate::isa::f32_kernel() {
            // SAFETY: the CPU has AVX-512F, AVX2 and FMA (the table's needs).
            #[cfg(target_arch = "x86_64")]
            F32Kernel::Avx512 => unsafe { quantize_avx512(xs, ys, scale, zp) },
            // SAFETY: the CPU has AVX2 and FMA (the table's needs).
            #[cfg(target_arch = "x86_64")]
            F32Kernel::Avx2Fma => unsafe { quantize_avx2(xs, ys, scale, zp) },
            // NEON is the aarch64 baseline: the portable loop compiles to `frintn` on 4 lanes.
            _ => quantize_generic(xs, ys, scale, zp),
        }
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx512f,avx2,fma")]
    pub(super) unsafe fn quantize_avx512(xs: &[f32], ys: &mut [u8], scale: f32, zp: i32) {
        // 16 values a step: the compiler's form of `one` converts one value at a time (Rust's
        // saturating float-to-int cast). Rounded, NaN made 0 (as the cast does), clamped in
        // floats to what the zero point leaves of 0..=255 (as saturating and clamping after it
        // do), then converted exactly and narrowed.
        use std::arch::x86_64::*;
        let n = xs.len().min(ys.len());
        let blocks = n / 16;
        let (s, z) = (_mm512_set1_ps(scale), _mm512_set1_epi32(zp));
        let (lo, hi) = (_mm512_set1_ps(-zp as f32), _mm512_set1_ps((255 - zp) as f32));
        for b in 0..blocks {
            // SAFETY: 16 values of `xs` and of `ys` from 16·b < n (both hold n or more).
            unsafe {
                let x = _mm512_mul_ps(_mm512_loadu_ps(xs.as_ptr().add(16 * b)), s);
                let r = _mm512_roundscale_ps::<{ _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC }>(x);
                let r = _mm512_maskz_mov_ps(_mm512_cmp_ps_mask::<_CMP_ORD_Q>(r, r), r);
                let r = _mm512_min_ps(_mm512_max_ps(r, lo), hi);
                let q = _mm512_add_epi32(_mm512_cvtps_epi32(r), z);
                _mm_storeu_si128(ys.as_mut_ptr().add(16 * b).cast(), _mm512_cvtepi32_epi8(q));
            }
        }
        quantize_generic(&xs[16 * blocks..n], &mut ys[16 * blocks..n], scale, zp)
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,fma")]
    pub(super) unsafe fn quantize_avx2(xs: &[f32], ys: &mut [u8], scale: f32, zp: i32) {
        // [`quantize_avx512`]'s steps on 8 values (the compiler's form of `one` converted one
        // value at a time: NanoTrack's int8 step spent 1 ms of 6.2 here on an AMD EPYC).
        use std::arch::x86_64::*;
        let n = xs.len().min(ys.len());
        let blocks = n / 8;
        let (s, z) = (_mm256_set1_ps(scale), _mm256_set1_epi32(zp));
        let (lo, hi) = (_mm256_set1_ps(-zp as f32), _mm256_set1_ps((255 - zp) as f32));
        for b in 0..blocks {
            // SAFETY: 8 values of `xs` and of `ys` from 8·b < n (both hold n or more).
            unsafe {
                let x = _mm256_mul_ps(_mm256_loadu_ps(xs.as_ptr().add(8 * b)), s);
                let r = _mm256_round_ps::<{ _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC }>(x);
                let r = _mm256_and_ps(r, _mm256_cmp_ps::<_CMP_ORD_Q>(r, r));
                let r = _mm256_min_ps(_mm256_max_ps(r, lo), hi);
                let q = _mm256_add_epi32(_mm256_cvtps_epi32(r), z);
                // Eight values in 0..=255: narrowing with unsigned saturation keeps them.
                let w = _mm_packus_epi32(_mm256_castsi256_si128(q), _mm256_extracti128_si256::<1>(q));
                _mm_storel_epi64(ys.as_mut_ptr().add(8 * b).cast(), _mm_packus_epi16(w, w));
            }
        }
        quantize_generic(&xs[8 * blocks..n], &mut ys[8 * blocks..n], scale, zp)
    }

    #[inline(always)]
    pub(super) fn quantize_generic(xs: &[f32], ys: &mut [u8], scale: f32, zp: i32) {
        ys.iter_mut().zip(xs).for_each(|(y, &x)| *y = super::one(x, scale, zp));
    }
}

impl Op for QuantizeU8 {
    fn name(&self) -> StaticName {
        "QuantizeU8".into()
    }

    fn info(&self) -> TractResult<Vec<String>> {
        Ok(vec![format!("scale: {} zero_point: {}", self.scale, self.zero_point)])
    }

    op_as_typed_op!();
}

impl EvalOp for QuantizeU8 {
    op_out_of_plan!();

    fn eval(&self, _ctx: &EvalContext, inputs: TVec<TValue>) -> TractResult<TVec<TValue>> {
        let input = args_1!(inputs);
        let shape: TVec<usize> = input.shape().into();
        let xs = input.try_as_plain_ram()?;
        let xs = xs.as_slice::<f32>()?;
        let (scale, zp, share) = (self.scale, self.zero_point as i32, SHARE);
        // SAFETY: the chunks cover the whole output, and each is written whole.
        let out = unsafe {
            output_tensor_written::<u8>(&shape, |ys| {
                par_chunks(ys, share, |i, ys| kernel::quantize(&xs[i * share..][..ys.len()], ys, scale, zp));
                Ok(())
            })?
        };
        Ok(tvec!(out.into_tvalue()))
    }
}

impl TypedOp for QuantizeU8 {
    fn output_facts(&self, inputs: &[&TypedFact]) -> TractResult<TVec<TypedFact>> {
        Ok(tvec!(u8::fact(inputs[0].shape.clone())))
    }

    as_op!();
}

/// The [`QuantizeU8`] for `node` if it is tract's `QuantizeLinearU8` of an f32 tensor.
pub(crate) fn quantize_u8(model: &TypedModel, node: &TypedNode) -> TractResult<Option<QuantizeU8>> {
    let Some(ew) = node.op_as::<ElementWiseOp>() else { return Ok(None) };
    let Some(q) = ew.0.downcast_ref::<QuantizeLinearU8>() else { return Ok(None) };
    let facts = model.node_input_facts(node.id)?;
    if facts.len() != 1 || facts[0].datum_type != f32::datum_type() || ew.1.is_some_and(|dt| dt != u8::datum_type()) {
        return Ok(None);
    }
    Ok(Some(QuantizeU8::new(q.scale, q.zero_point)))
}

/// `y = (x - zero_point) * scale` for u8 `x`, as tract's `DequantizeLinearF32` computes it (an
/// exact integer difference, an exact conversion, one rounded product: the same bits on every
/// path), on vector lanes and, for large tensors, over the pool's threads. tract's loop, one
/// element at a time through a generic conversion, took 0.11-0.2 ms for each of PRL-Track's
/// backbone features (0.9 ms of a 42 ms int8 search step, and none of it split over threads).
///
/// The activation after it (a clamp, tract's hard-swish: [`super::act::tail`]) is applied to
/// each share of the output as it is written, not in a pass of its own (NanoTrack's int8 plan:
/// a hard-swish or a ReLU after most of its integer convolutions).
#[derive(Debug, Clone, PartialEq)]
pub struct DequantizeU8 {
    scale: f32,
    zero_point: i32,
    act: Activation,
}

impl Eq for DequantizeU8 {}

impl DequantizeU8 {
    /// The dequantiser with `scale` (the step) and `zero_point`.
    pub fn new(scale: f32, zero_point: i32) -> Self {
        DequantizeU8 { scale, zero_point, act: Activation::NONE }
    }

    /// `ys = act((xs - zero_point) * scale)`, what the operator writes for `xs` (element by
    /// element: the same bits for any split of the data).
    pub(crate) fn apply(&self, xs: &[u8], ys: &mut [f32]) {
        dequantize::dequantize(xs, ys, self.scale, self.zero_point);
        self.act.apply_all(ys);
    }

    /// This dequantiser with `act` after it.
    #[cfg(test)]
    pub(crate) fn with_act(self, act: Activation) -> DequantizeU8 {
        DequantizeU8 { act, ..self }
    }

    /// This dequantiser with the activation of `tail` after it, where the tail ends in the
    /// same `shape` and adds no bias.
    pub(crate) fn fused(&self, tail: &Tail, shape: &[usize]) -> Option<DequantizeU8> {
        (tail.bias.is_none() && tail.shape.as_slice() == shape).then(|| DequantizeU8 { act: tail.act, ..self.clone() })
    }
}

mod dequantize {
    /// Dequantise `xs` into `ys` on the widest lanes this CPU has (the loop is the same; the
    /// compiler vectorises it for each).
    pub(super) fn dequantize(xs: &[u8], ys: &mut [f32], scale: f32, zp: i32) {
        #[cfg(target_arch = "x86_64")]
        use crate::isa::F32Kernel;
        match crate::isa::f32_kernel() {
            // SAFETY: the CPU has AVX-512F, AVX2 and FMA (the table's needs).
            #[cfg(target_arch = "x86_64")]
            F32Kernel::Avx512 => unsafe { dequantize_avx512(xs, ys, scale, zp) },
            // SAFETY: the CPU has AVX2 and FMA (the table's needs).
            #[cfg(target_arch = "x86_64")]
            F32Kernel::Avx2Fma => unsafe { dequantize_avx2(xs, ys, scale, zp) },
            // NEON is the aarch64 baseline: the loop compiles to `uxtl`, `ucvtf`, `fmul`.
            _ => dequantize_generic(xs, ys, scale, zp),
        }
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx512f,avx2,fma")]
    pub(super) unsafe fn dequantize_avx512(xs: &[u8], ys: &mut [f32], scale: f32, zp: i32) {
        dequantize_generic(xs, ys, scale, zp)
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,fma")]
    pub(super) unsafe fn dequantize_avx2(xs: &[u8], ys: &mut [f32], scale: f32, zp: i32) {
        dequantize_generic(xs, ys, scale, zp)
    }

    #[inline(always)]
    pub(super) fn dequantize_generic(xs: &[u8], ys: &mut [f32], scale: f32, zp: i32) {
        ys.iter_mut().zip(xs).for_each(|(y, &x)| *y = (x as i32 - zp) as f32 * scale);
    }
}

impl Op for DequantizeU8 {
    fn name(&self) -> StaticName {
        "DequantizeU8".into()
    }

    fn info(&self) -> TractResult<Vec<String>> {
        Ok(vec![format!("scale: {} zero_point: {}, activation {}", self.scale, self.zero_point, self.act.describe())])
    }

    op_as_typed_op!();
}

impl EvalOp for DequantizeU8 {
    op_out_of_plan!();

    fn eval(&self, _ctx: &EvalContext, inputs: TVec<TValue>) -> TractResult<TVec<TValue>> {
        let input = args_1!(inputs);
        let shape: TVec<usize> = input.shape().into();
        let xs = input.try_as_plain_ram()?;
        // SAFETY: u8, possibly with quantisation parameters (checked when the op was made).
        let xs = unsafe { xs.as_slice_unchecked::<u8>() };
        let share = SHARE;
        // SAFETY: the chunks cover the whole output, and each is written whole.
        let out = unsafe {
            output_tensor_written(&shape, |ys| {
                par_chunks(ys, share, |i, ys| self.apply(&xs[i * share..][..ys.len()], ys));
                Ok(())
            })?
        };
        Ok(tvec!(out.into_tvalue()))
    }
}

impl TypedOp for DequantizeU8 {
    fn output_facts(&self, inputs: &[&TypedFact]) -> TractResult<TVec<TypedFact>> {
        Ok(tvec!(f32::fact(inputs[0].shape.clone())))
    }

    as_op!();
}

/// An operator's f32 data input, or the u8 data it reads instead through the dequantiser that
/// made it ([`dequantized_input`]), dequantised one plane at a time.
#[derive(Clone, Copy)]
pub(crate) enum Planes<'a> {
    F32(&'a [f32]),
    /// u8, and the dequantiser it goes through.
    U8(&'a [u8], &'a DequantizeU8),
}

impl<'a> Planes<'a> {
    /// `input`'s data: f32, or u8 where the operator reads through `dequant` (`op` names the
    /// operator in the error).
    pub(crate) fn of(op: &str, input: &'a Tensor, dequant: Option<&'a DequantizeU8>) -> TractResult<Planes<'a>> {
        let plain = input.try_as_plain_ram()?;
        Ok(match dequant {
            None => Planes::F32(plain.as_slice::<f32>()?),
            Some(dq) => {
                let dt = input.datum_type();
                ensure!(dt.unquantized() == u8::datum_type(), "{op}: input is {dt:?}, not u8");
                // SAFETY: the storage is u8, possibly with quantisation parameters (checked).
                Planes::U8(unsafe { plain.as_slice_unchecked::<u8>() }, dq)
            }
        })
    }

    /// The buffer [`Self::plane`] needs for planes of `len` values (none for f32 data).
    pub(crate) fn buffer_len(&self, len: usize) -> usize {
        match self {
            Planes::F32(_) => 0,
            Planes::U8(..) => len,
        }
    }

    /// Values `range` as f32: the data's own, or dequantised into `buffer` (at least
    /// [`Self::buffer_len`] long).
    pub(crate) fn plane<'b>(&self, range: std::ops::Range<usize>, buffer: &'b mut [f32]) -> &'b [f32]
    where
        'a: 'b,
    {
        match *self {
            Planes::F32(x) => &x[range],
            Planes::U8(x, dq) => {
                let values = &mut buffer[..range.len()];
                dq.apply(&x[range], values);
                values
            }
        }
    }
}

/// The [`DequantizeU8`] that makes `x` and the u8 outlet it reads, where `x` has no other
/// reader and is not a graph output: an operator that can dequantise its input itself reads
/// the u8 data instead (the dequantiser, left without readers, goes when the graph is
/// compacted).
pub(crate) fn dequantized_input(model: &TypedModel, x: OutletId) -> Option<(DequantizeU8, OutletId)> {
    let producer = model.node(x.node);
    let dq = producer.op_as::<DequantizeU8>()?;
    let alone = model.outlet_successors(x).len() == 1 && !model.output_outlets().is_ok_and(|o| o.contains(&x));
    alone.then(|| (dq.clone(), producer.inputs[0]))
}

/// The [`DequantizeU8`] for `node` if it is tract's `DequantizeLinearF32` of a u8 tensor.
pub(crate) fn dequantize_u8(model: &TypedModel, node: &TypedNode) -> TractResult<Option<DequantizeU8>> {
    let Some(op) = node.op_as::<DequantizeLinearF32>() else { return Ok(None) };
    let facts = model.node_input_facts(node.id)?;
    if facts.len() != 1 || facts[0].datum_type.unquantized() != u8::datum_type() {
        return Ok(None);
    }
    Ok(Some(DequantizeU8::new(op.scale, op.zero_point)))
}

#[cfg(test)]
mod tests {
    use super::*;
    use tract_nnef::tract_core::ops::quant::quantize_linear_f32_u8;

    #[test]
    fn every_path_equals_tracts_formula() {
        let mut xs: Vec<f32> = (-3000..3000).map(|i| i as f32 * 0.25).collect();
        xs.extend([0.5, 1.5, 2.5, -0.5, -1.5, 1e6, -1e6, f32::NAN, -0.0]);
        xs.extend((0..5000).map(|i| ((i * 7919 % 10007) as f32 - 5000.0) / 37.0));
        for (scale, zp) in [(1.0, 0u8), (4.0, 128), (0.37, 17), (12.5, 255)] {
            let want: Vec<u8> = xs.iter().map(|&x| quantize_linear_f32_u8(x, scale, zp as i32)).collect();
            let mut paths: Vec<(&str, Vec<u8>)> = vec![];
            let mut ys = vec![0u8; xs.len()];
            kernel::quantize_generic(&xs, &mut ys, scale, zp as i32);
            paths.push(("generic", ys.clone()));
            #[cfg(target_arch = "x86_64")]
            {
                if super::super::avx2_fma() {
                    // SAFETY: AVX2 and FMA are present.
                    unsafe { kernel::quantize_avx2(&xs, &mut ys, scale, zp as i32) };
                    paths.push(("avx2", ys.clone()));
                } else {
                    eprintln!("NOTE: no AVX2+FMA here (or PRL_ISA caps it): QuantizeU8's AVX2 path is not tested here");
                }
                if super::super::avx512_fma() {
                    // SAFETY: AVX-512F, AVX2 and FMA are present.
                    unsafe { kernel::quantize_avx512(&xs, &mut ys, scale, zp as i32) };
                    paths.push(("avx512", ys.clone()));
                } else {
                    eprintln!(
                        "NOTE: no AVX-512 here (or PRL_ISA caps it): QuantizeU8's AVX-512 path is not tested here"
                    );
                }
            }
            for (name, got) in paths {
                let bad = got.iter().zip(&want).position(|(a, b)| a != b);
                assert!(
                    bad.is_none(),
                    "{name}, scale {scale}: x = {} gives {} not {}",
                    xs[bad.unwrap()],
                    got[bad.unwrap()],
                    want[bad.unwrap()]
                );
            }
        }
        // Beyond an i32, ONNX's saturation.
        let (inf, mut ys) = ([f32::INFINITY, 1e30, f32::NEG_INFINITY, -1e30], [0u8; 4]);
        kernel::quantize(&inf, &mut ys, 1.0, 128);
        assert_eq!(ys, [255, 255, 0, 0]);
    }

    #[test]
    fn dequantizing_equals_tracts_op_on_every_path_and_share() -> TractResult<()> {
        use tract_nnef::tract_core::ops::quant::DequantizeLinearF32;
        // Longer than two shares and not a multiple of any lane count: the tails and the seams.
        let n = 2 * SHARE + 77;
        let xs: Vec<u8> = (0..n).map(|i| (i * 7919 % 256) as u8).collect();
        let input = tensor1(&xs).into_shape(&[1, n])?.into_tvalue();
        for (scale, zp) in [(0.03160982f32, 0), (100.79951, 0), (0.37, 17), (1e-3, 255)] {
            let theirs = DequantizeLinearF32 { scale, zero_point: zp }
                .eval(&EvalContext::out_of_plan(), tvec!(input.clone()))?
                .remove(0);
            let want = theirs.try_as_plain_ram()?.as_slice::<f32>()?.to_vec();
            let mut paths: Vec<(&str, Vec<f32>)> = vec![];
            let mut ys = vec![f32::NAN; n];
            dequantize::dequantize_generic(&xs, &mut ys, scale, zp);
            paths.push(("generic", ys.clone()));
            #[cfg(target_arch = "x86_64")]
            {
                if super::super::avx2_fma() {
                    // SAFETY: AVX2 and FMA are present.
                    unsafe { dequantize::dequantize_avx2(&xs, &mut ys, scale, zp) };
                    paths.push(("avx2", ys.clone()));
                } else {
                    eprintln!(
                        "NOTE: no AVX2+FMA here (or PRL_ISA caps it): DequantizeU8's AVX2 path is not tested here"
                    );
                }
                if super::super::avx512_fma() {
                    // SAFETY: AVX-512F, AVX2 and FMA are present.
                    unsafe { dequantize::dequantize_avx512(&xs, &mut ys, scale, zp) };
                    paths.push(("avx512", ys.clone()));
                } else {
                    eprintln!(
                        "NOTE: no AVX-512 here (or PRL_ISA caps it): DequantizeU8's AVX-512 path is not tested here"
                    );
                }
            }
            // The op as the graph runs it, over a two-thread pool (three shares).
            let op = DequantizeU8::new(scale, zp);
            let pool = tract_linalg::multithread::Executor::multithread(2);
            let ours = tract_linalg::multithread::multithread_tract_scope(pool, || {
                op.eval(&EvalContext::out_of_plan(), tvec!(input.clone()))
            })?;
            paths.push(("op", ours[0].try_as_plain_ram()?.as_slice::<f32>()?.to_vec()));
            for (name, got) in paths {
                let bad = got.iter().zip(&want).position(|(a, b)| a.to_bits() != b.to_bits());
                assert!(bad.is_none(), "{name}, scale {scale}, zero point {zp}: element {}", bad.unwrap());
            }
        }
        Ok(())
    }

    /// A dequantisation with the activations NanoTrack's int8 plan puts after it (tract's
    /// hard-swish; a ReLU6 as `Max` then `Min`), by tract and after [`accelerate`]: one op,
    /// the same bits.
    #[test]
    fn the_activation_after_a_dequantisation_is_fused_with_the_same_bits() -> TractResult<()> {
        use tract_nnef::tract_core::ops::math::{max, min};
        use tract_nnef::tract_core::ops::nn::hard_swish;
        let n = 3 * SHARE + 101;
        let xs: Vec<u8> = (0..n).map(|i| (i * 7919 % 256) as u8).collect();
        let input = tensor1(&xs).into_shape(&[1, n])?;
        type Wire = fn(&mut TypedModel, OutletId) -> TractResult<OutletId>;
        let tails: [(&str, Wire); 2] = [
            ("hard-swish", |m, y| Ok(m.wire_node("hs", hard_swish(), &[y])?[0])),
            ("relu6", |m, y| {
                let (lo, hi) = (m.add_const("lo", tensor2(&[[0f32]]))?, m.add_const("hi", tensor2(&[[6f32]]))?);
                let y = m.wire_node("max", max(), &[y, lo])?[0];
                Ok(m.wire_node("min", min(), &[y, hi])?[0])
            }),
        ];
        for (name, tail) in tails {
            let mut model = TypedModel::default();
            let x = model.add_source("x", u8::fact([1, n]))?;
            let y = model.wire_node("dq", DequantizeLinearF32 { scale: 0.0471, zero_point: 117 }, &[x])?[0];
            let y = tail(&mut model, y)?;
            model.select_output_outlets(&[y])?;
            let want = model.clone().into_runnable()?.run(tvec![input.clone().into_tvalue()])?;
            let done = super::super::accelerate(&mut model)?;
            assert_eq!(done.quantizers, 1, "{name}");
            assert_eq!(model.nodes().len(), 2, "{name}: the source and one op");
            let got = model.into_runnable()?.run(tvec![input.clone().into_tvalue()])?;
            let (got, want) = (got[0].try_as_plain_ram()?, want[0].try_as_plain_ram()?);
            let (got, want) = (got.as_slice::<f32>()?, want.as_slice::<f32>()?);
            let bad = got.iter().zip(want).position(|(a, b)| a.to_bits() != b.to_bits());
            assert!(bad.is_none(), "{name}: element {}", bad.unwrap());
        }
        Ok(())
    }
}
