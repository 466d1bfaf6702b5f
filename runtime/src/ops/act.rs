//! What follows a convolution in a decluttered graph, fused into it: a per-channel bias `Add`
//! (for the einsum of a 1x1 convolution, which has none of its own), a clamp (`Max` and/or `Min`
//! with a constant: ReLU, ReLU6) and tract's `HardSwish`, with reshapes between them
//! ([`tail`]), applied by the operator to its output as it writes it ([`Activation`]).
//!
//! Each of these is otherwise a pass of its own over the output, and, on a thread pool, a
//! dispatch of its own (tract splits element-wise operators over the pool: on a 2-vCPU VM, 0.1
//! ms each for NanoTrack's small maps).

use std::sync::Arc;

use tract_nnef::internal::*;
use tract_nnef::tract_core::ops::binary::TypedBinOp;
use tract_nnef::tract_core::ops::element_wise::ElementWiseOp;
use tract_nnef::tract_core::ops::math::{Add, Max, Min};
use tract_nnef::tract_core::ops::nn::HardSwish;

/// `min(max(v, lo), hi)`, then tract's hard-swish `v · clamp(v + 3, 0, 6) · (1/6)` when
/// `hard_swish`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct Activation {
    pub lo: f32,
    pub hi: f32,
    pub hard_swish: bool,
}

// The bounds are never NaN (`tail` refuses NaN constants): equality is an equivalence.
impl Eq for Activation {}

impl Activation {
    /// The identity.
    pub const NONE: Activation = Activation { lo: f32::NEG_INFINITY, hi: f32::INFINITY, hard_swish: false };

    /// Whether there is a clamp.
    pub fn clamps(&self) -> bool {
        self.lo != f32::NEG_INFINITY || self.hi != f32::INFINITY
    }

    /// The activation of one value (the scalar form every path computes).
    #[inline(always)]
    pub fn apply(&self, v: f32) -> f32 {
        let v = if self.clamps() { v.max(self.lo).min(self.hi) } else { v };
        if self.hard_swish {
            v * (v + 3.0).clamp(0.0, 6.0) * (1.0 / 6.0)
        } else {
            v
        }
    }

    /// [`Self::apply`] on every value of `xs` (vectorised; on AVX-512 where there is).
    pub fn apply_all(&self, xs: &mut [f32]) {
        if *self == Activation::NONE {
            return;
        }
        #[cfg(target_arch = "x86_64")]
        if crate::isa::f32_kernel() == crate::isa::F32Kernel::Avx512 {
            // SAFETY: the CPU has AVX-512F (the table's needs).
            return unsafe { self.apply_all_avx512(xs) };
        }
        #[cfg(target_arch = "x86_64")]
        if crate::isa::f32_kernel() == crate::isa::F32Kernel::Avx2Fma {
            // SAFETY: the CPU has AVX2 and FMA (the table's needs).
            return unsafe { self.apply_all_avx2(xs) };
        }
        self.apply_all_inline(xs)
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,fma")]
    unsafe fn apply_all_avx2(&self, xs: &mut [f32]) {
        self.apply_all_inline(xs)
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx512f")]
    unsafe fn apply_all_avx512(&self, xs: &mut [f32]) {
        self.apply_all_inline(xs)
    }

    /// The loop of [`Self::apply_all`], one form per kind so that each vectorises.
    #[inline(always)]
    fn apply_all_inline(&self, xs: &mut [f32]) {
        let (lo, hi) = (self.lo, self.hi);
        match (self.clamps(), self.hard_swish) {
            (true, false) => xs.iter_mut().for_each(|v| *v = v.max(lo).min(hi)),
            (false, true) => xs.iter_mut().for_each(|v| *v = *v * (*v + 3.0).clamp(0.0, 6.0) * (1.0 / 6.0)),
            _ => xs.iter_mut().for_each(|v| *v = self.apply(*v)),
        }
    }

    /// [`Self::apply`] on the 16 values of `y` (in registers: what the AVX-512 tiles apply
    /// before they store; the same operations in the same order).
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx512f")]
    #[inline]
    pub fn apply_avx512(&self, y: std::arch::x86_64::__m512) -> std::arch::x86_64::__m512 {
        use std::arch::x86_64::*;
        let mut y = y;
        if self.clamps() {
            y = _mm512_min_ps(_mm512_max_ps(y, _mm512_set1_ps(self.lo)), _mm512_set1_ps(self.hi));
        }
        if self.hard_swish {
            let r6 = _mm512_min_ps(
                _mm512_max_ps(_mm512_add_ps(y, _mm512_set1_ps(3.0)), _mm512_setzero_ps()),
                _mm512_set1_ps(6.0),
            );
            y = _mm512_mul_ps(_mm512_mul_ps(y, r6), _mm512_set1_ps(1.0 / 6.0));
        }
        y
    }

    /// [`Self::apply`] on the 8 values of `y` (AVX2: what the AVX2 tiles apply before they
    /// store; the operations of [`Self::apply_avx512`]).
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,fma")]
    #[inline]
    pub fn apply_avx2(&self, y: std::arch::x86_64::__m256) -> std::arch::x86_64::__m256 {
        use std::arch::x86_64::*;
        let mut y = y;
        if self.clamps() {
            y = _mm256_min_ps(_mm256_max_ps(y, _mm256_set1_ps(self.lo)), _mm256_set1_ps(self.hi));
        }
        if self.hard_swish {
            let r6 = _mm256_min_ps(
                _mm256_max_ps(_mm256_add_ps(y, _mm256_set1_ps(3.0)), _mm256_setzero_ps()),
                _mm256_set1_ps(6.0),
            );
            y = _mm256_mul_ps(_mm256_mul_ps(y, r6), _mm256_set1_ps(1.0 / 6.0));
        }
        y
    }

    /// How `info` describes it.
    pub fn describe(&self) -> String {
        match (self.clamps(), self.hard_swish) {
            (false, false) => "none".to_string(),
            (true, false) => format!("clamp {}..{}", self.lo, self.hi),
            (false, true) => "hard-swish".to_string(),
            (true, true) => format!("clamp {}..{}, hard-swish", self.lo, self.hi),
        }
    }
}

/// What [`tail`] found after a node.
pub(crate) struct Tail {
    /// The per-channel bias, where one was asked for and found.
    pub bias: Option<Vec<f32>>,
    pub act: Activation,
    /// The node and those fused after it, in order; the operator replaces the last.
    pub chain: Vec<usize>,
    /// The last node's output shape (the same values in the same order as the first's).
    pub shape: TVec<usize>,
}

impl Tail {
    /// The shape an operator standing for the chain outputs, where it is not the first node's.
    pub fn reshaped(&self) -> Option<TVec<usize>> {
        (self.chain.len() > 1).then(|| self.shape.clone())
    }
}

/// An operator's output `out` in the shape the nodes it took in end in (`reshape`, from
/// [`Tail::reshaped`]), where they change it.
pub(crate) fn reshape_output(out: Tensor, reshape: Option<&TVec<usize>>) -> TractResult<Tensor> {
    match reshape {
        Some(shape) => out.into_shape(shape),
        None => Ok(out),
    }
}

/// The f32 output fact of an operator that took in the nodes after it: `reshape`'s shape where
/// they change it, else `fact()`.
pub(crate) fn output_fact(reshape: Option<&TVec<usize>>, fact: impl FnOnce() -> TypedFact) -> TypedFact {
    match reshape {
        Some(shape) => f32::fact(shape),
        None => fact(),
    }
}

/// The sole consumer of `node`'s single output, if it has exactly one and that output is not
/// one of the model's.
pub(super) fn sole_consumer<'m>(model: &'m TypedModel, node: &TypedNode) -> Option<&'m TypedNode> {
    let outlet = OutletId::new(node.id, 0);
    match (&node.outputs[..], model.output_outlets().ok()?.contains(&outlet)) {
        ([o], false) if o.successors.len() == 1 => Some(model.node(o.successors[0].node)),
        _ => None,
    }
}

/// Whether `op` on a value of `shape` leaves its values in the same order: a reshape, a unit
/// axis added or removed, or a move that crosses only axes of length 1 (a transpose does not).
pub(super) fn keeps_order(op: &AxisOp, shape: &[usize]) -> bool {
    match *op {
        AxisOp::Move(from, to) => {
            let unit = |a: usize| shape.get(a) == Some(&1);
            unit(from) || (from.min(to)..=from.max(to)).filter(|&a| a != from).all(unit)
        }
        AxisOp::Add(_) | AxisOp::Rm(_) | AxisOp::Reshape(..) => true,
    }
}

/// The constant other input of a binary `node` whose other input is `from`.
pub(super) fn other_const(model: &TypedModel, node: &TypedNode, from: OutletId) -> Option<Arc<Tensor>> {
    let [a, b] = node.inputs[..] else { return None };
    let other = if a == from {
        b
    } else if b == from {
        a
    } else {
        return None;
    };
    model.outlet_fact(other).ok()?.konst.clone()
}

/// The bias of a per-channel `Add` on an `[.., m, ..][n]`-shaped value of `shape`, from its
/// constant: `m` values, broadcast over the trailing axes that make up `n`.
fn bias_of(konst: &Tensor, shape: &[usize], m: usize, n: usize) -> Option<Vec<f32>> {
    if konst.datum_type() != f32::datum_type() || konst.len() != m || konst.rank() > shape.len() {
        return None;
    }
    let pad = shape.len() - konst.rank();
    let c = |a: usize| if a < pad { 1 } else { konst.shape()[a - pad] };
    // The axes from `split` on are the positions; those before it the channels.
    let split = (0..=shape.len()).find(|&j| shape[j..].iter().product::<usize>() == n)?;
    let fits = (0..shape.len()).all(|a| if a < split { c(a) == shape[a] } else { c(a) == 1 });
    fits.then(|| konst.try_as_plain_ram().ok()?.as_slice::<f32>().ok().map(<[f32]>::to_vec)).flatten()
}

/// The nodes after `node` (whose output is f32) that its operator can take in: a per-channel
/// bias `Add` first when `bias_for` gives `(m, n)` (channels, positions), then one `Max` and
/// one `Min` with a constant (lo <= hi, in either order), then `HardSwish`; reshapes between
/// them, not after the last. Each must be the sole consumer of the one before. None where
/// `node`'s output shape is not known.
pub(crate) fn tail(
    model: &TypedModel,
    node: &TypedNode,
    bias_for: Option<(usize, usize)>,
) -> TractResult<Option<Tail>> {
    let Some(shape) = node.outputs[0].fact.shape.as_concrete() else { return Ok(None) };
    let (mut bias, mut act, mut chain, mut shapes) = (None, Activation::NONE, vec![node.id], vec![shape.into()]);
    let mut last = node;
    while let Some(next) = sole_consumer(model, last) {
        let from = OutletId::new(last.id, 0);
        let bin = next.op_as::<TypedBinOp>();
        if act.hard_swish {
            break;
        } else if let Some(axes) = next.op_as::<AxisOp>() {
            // A reshape: the same values in the same order (a transpose is not taken in).
            let shape: &TVec<usize> = shapes.last().expect("non-empty");
            if !keeps_order(axes, shape) {
                break;
            }
        } else if let (Some((m, n)), None, true) = (bias_for, &bias, bin.is_some_and(|b| b.0.is::<Add>())) {
            if act != Activation::NONE {
                break;
            }
            let shape: &TVec<usize> = shapes.last().expect("non-empty");
            let Some(b) = other_const(model, next, from).and_then(|c| bias_of(&c, shape, m, n)) else { break };
            bias = Some(b);
        } else if let Some(b) = bin.filter(|b| b.0.is::<Max>() || b.0.is::<Min>()) {
            let Some(c) = other_const(model, next, from).filter(|c| c.len() == 1) else { break };
            let Ok(c) = c.cast_to_scalar::<f32>() else { break };
            let is_max = b.0.is::<Max>();
            let (bound, other) = if is_max { (&mut act.lo, act.hi) } else { (&mut act.hi, act.lo) };
            // One bound of each kind, lo <= hi: then the order they come in does not matter.
            if bound.is_finite() || c.is_nan() || (if is_max { c > other } else { c < other }) {
                break;
            }
            *bound = c;
        } else if next.op_as::<ElementWiseOp>().is_some_and(|e| e.0.is::<HardSwish>()) {
            act.hard_swish = true;
        } else {
            break;
        }
        let fact = &next.outputs[0].fact;
        let Some(s) = fact.shape.as_concrete().filter(|_| fact.datum_type == f32::datum_type()) else { break };
        shapes.push(s.into());
        chain.push(next.id);
        last = next;
    }
    // Trailing reshapes stay tract's.
    while chain.len() > 1 && model.node(*chain.last().expect("non-empty")).op_as::<AxisOp>().is_some() {
        chain.pop();
        shapes.pop();
    }
    Ok(Some(Tail { bias, act, chain, shape: shapes.pop().expect("non-empty") }))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ops::attention::tests::values;
    use tract_nnef::tract_core::ops::cnn::{Conv, KernelFormat, PaddingSpec, PoolSpec};
    use tract_nnef::tract_core::ops::math::{max, min};
    use tract_nnef::tract_core::ops::nn::{hard_swish, DataFormat};

    /// A 3x3 convolution (`groups` 1: a [`super::super::PackedConv`]; `c`: a depthwise one) on
    /// `[1, c, 12, 12]`, then `tail`, run by tract and after `accelerate`; `fused` nodes (with
    /// their constants) must be gone.
    fn check(c: usize, co: usize, groups: usize, tail: impl Fn(&mut TypedModel, OutletId) -> OutletId, fused: usize) {
        let mut model = TypedModel::default();
        let x = model.add_source("x", f32::fact([1, c, 12, 12])).unwrap();
        let w = Tensor::from_shape(&[co, c / groups, 3, 3], &values(co * c / groups * 9, 3)).unwrap();
        let w = model.add_const("w", w).unwrap();
        let b = model.add_const("b", Tensor::from_shape(&[co], &values(co, 5)).unwrap()).unwrap();
        let pool_spec = PoolSpec {
            data_format: DataFormat::NCHW,
            kernel_shape: tvec![3, 3],
            padding: PaddingSpec::Explicit(tvec![1, 1], tvec![1, 1]),
            dilations: None,
            strides: None,
            input_channels: c,
            output_channels: co,
        };
        let conv = Conv { pool_spec, kernel_fmt: KernelFormat::OIHW, group: groups, q_params: None };
        let y = model.wire_node("conv", conv, &[x, w, b]).unwrap()[0];
        let y = tail(&mut model, y);
        model.select_output_outlets(&[y]).unwrap();
        let input = Tensor::from_shape(&[1, c, 12, 12], &values(c * 144, 1)).unwrap();
        let want = model.clone().into_runnable().unwrap().run(tvec![input.clone().into_tvalue()]).unwrap();
        let nodes = model.nodes().len();
        let done = super::super::accelerate(&mut model).unwrap();
        assert_eq!(done.convolutions + done.depthwise, 1);
        assert_eq!(nodes - model.nodes().len(), fused, "nodes removed");
        let got = model.into_runnable().unwrap().run(tvec![input.into_tvalue()]).unwrap();
        assert_eq!(got[0].shape(), want[0].shape());
        let (got, want) = (got[0].try_as_plain_ram().unwrap(), want[0].try_as_plain_ram().unwrap());
        let (got, want) = (got.as_slice::<f32>().unwrap(), want.as_slice::<f32>().unwrap());
        for (i, (g, w)) in got.iter().zip(want).enumerate() {
            assert!((g - w).abs() <= 1e-4 * w.abs().max(1.0), "element {i}: {g} vs {w}");
        }
    }

    /// A scalar constant of rank `rank` (tract's binary operators take equal ranks).
    fn konst(model: &mut TypedModel, name: &str, v: f32, rank: usize) -> OutletId {
        model.add_const(name, Tensor::from_shape(&vec![1; rank], &[v]).unwrap()).unwrap()
    }

    #[test]
    fn convolutions_take_in_the_activation_after_them() {
        // The batch axis dropped, then ReLU6 (tract's order in NanoTrack: squeeze, max, min).
        let relu6 = |model: &mut TypedModel, y: OutletId| {
            let y = model.wire_node("rm_n", AxisOp::Rm(0), &[y]).unwrap()[0];
            let lo = konst(model, "lo", 0.0, 3);
            let y = model.wire_node("max", max(), &[y, lo]).unwrap()[0];
            let hi = konst(model, "hi", 6.0, 3);
            model.wire_node("min", min(), &[y, hi]).unwrap()[0]
        };
        // Removed: the weights, the bias, the convolution and the four after it (one added).
        check(3, 16, 1, relu6, 7);
        check(24, 24, 24, relu6, 7);
        // Hard-swish.
        let hs = |model: &mut TypedModel, y: OutletId| model.wire_node("hs", hard_swish(), &[y]).unwrap()[0];
        check(3, 16, 1, hs, 3);
        check(24, 24, 24, hs, 3);
        // A clamp whose second bound crosses the first: the first is fused, the second stays
        // tract's.
        let crossed = |model: &mut TypedModel, y: OutletId| {
            let hi = konst(model, "hi", -1.0, 4);
            let y = model.wire_node("min", min(), &[y, hi]).unwrap()[0];
            let lo = konst(model, "lo", 0.5, 4);
            model.wire_node("max", max(), &[y, lo]).unwrap()[0]
        };
        check(24, 24, 24, crossed, 4);
    }

    #[test]
    fn a_transpose_before_the_activation_ends_the_tail() {
        // Channels moved last, then ReLU: the values change order, so the ReLU stays tract's
        // (taken in, the output would be the untransposed values in the transposed shape).
        let moved = |axes: AxisOp| {
            move |model: &mut TypedModel, y: OutletId| {
                let y = model.wire_node("move", axes.clone(), &[y]).unwrap()[0];
                let lo = konst(model, "lo", 0.0, 4);
                model.wire_node("max", max(), &[y, lo]).unwrap()[0]
            }
        };
        // Removed: the weights and the bias only.
        check(3, 16, 1, moved(AxisOp::Move(1, 3)), 2);
        check(24, 24, 24, moved(AxisOp::Move(1, 3)), 2);
        // The batch axis (length 1) moved: the same order, taken in (and the move, the bound
        // and the ReLU removed).
        check(3, 16, 1, moved(AxisOp::Move(0, 2)), 5);
        check(24, 24, 24, moved(AxisOp::Move(0, 2)), 5);
    }

    #[test]
    fn a_broadcast_product_takes_in_the_hard_swish_after_it() {
        // Squeeze-excitation's scaling: [1, c, h, w] · [1, c, 1, 1], then hard-swish.
        let mut model = TypedModel::default();
        let x = model.add_source("x", f32::fact([1, 24, 16, 16])).unwrap();
        let s = model.add_source("s", f32::fact([1, 24, 1, 1])).unwrap();
        let y = model.wire_node("scale", tract_nnef::tract_core::ops::math::mul(), &[x, s]).unwrap()[0];
        let y = model.wire_node("hs", hard_swish(), &[y]).unwrap()[0];
        model.select_output_outlets(&[y]).unwrap();
        let inputs = || {
            let x = Tensor::from_shape(&[1, 24, 16, 16], &values(24 * 256, 1)).unwrap();
            let s = Tensor::from_shape(&[1, 24, 1, 1], &values(24, 7)).unwrap();
            tvec![x.into_tvalue(), s.into_tvalue()]
        };
        let want = model.clone().into_runnable().unwrap().run(inputs()).unwrap();
        let done = super::super::accelerate(&mut model).unwrap();
        assert_eq!(done.broadcasts, 1);
        assert_eq!(model.nodes().len(), 3, "the sources and the fused product");
        let got = model.into_runnable().unwrap().run(inputs()).unwrap();
        let (got, want) = (got[0].try_as_plain_ram().unwrap(), want[0].try_as_plain_ram().unwrap());
        let (got, want) = (got.as_slice::<f32>().unwrap(), want.as_slice::<f32>().unwrap());
        for (i, (g, w)) in got.iter().zip(want).enumerate() {
            assert!((g - w).abs() <= 1e-5 * w.abs().max(1.0), "element {i}: {g} vs {w}");
        }
    }
}
