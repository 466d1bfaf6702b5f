//! Squeeze-excitation blocks as one operator ([`SqueezeExcite`]): `x · gate(mean(x))` per
//! channel, with the activation after it (MobileNetV3's hard-swish).
//!
//! In a decluttered graph a block is a dozen small nodes: the spatial sum and its scaling, two
//! fully connected layers as einsums with their transposes and squeezes, the bias `Add`s, the
//! ReLU and hard-sigmoid as binary operators with constants, and the broadcast product. tract
//! runs the two layers as packed matrix products on one column (1.5-2.5 GFLOP/s), and every
//! node costs a dispatch: 27 µs a block on NanoTrack's search graph, 8 blocks. Here the gate is
//! a short list of steps on one vector ([`Step`]), read off the graph by [`squeeze_excite`].

use std::sync::Arc;

use tract_nnef::internal::*;
use tract_nnef::tract_core::ops::binary::TypedBinOp;
use tract_nnef::tract_core::ops::element_wise::ElementWiseOp;
use tract_nnef::tract_core::ops::math::{Add, Div, Max, Min, Mul, Sub};
use tract_nnef::tract_core::ops::nn::{Reduce, Reducer};

use super::act::{other_const, sole_consumer, tail, Activation};
use super::matmul::{const_product, ConstProduct};
use super::same_bits;

/// An element-wise operation of a gate step with a constant.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum BinKind {
    Add,
    Sub,
    Mul,
    Div,
    Max,
    Min,
}

impl BinKind {
    fn of(op: &TypedBinOp) -> Option<BinKind> {
        let k = &op.0;
        Some(if k.is::<Add>() {
            BinKind::Add
        } else if k.is::<Sub>() {
            BinKind::Sub
        } else if k.is::<Mul>() {
            BinKind::Mul
        } else if k.is::<Div>() {
            BinKind::Div
        } else if k.is::<Max>() {
            BinKind::Max
        } else if k.is::<Min>() {
            BinKind::Min
        } else {
            return None;
        })
    }

    /// `a ∘ b`, as tract computes it on f32.
    #[inline]
    fn apply(self, a: f32, b: f32) -> f32 {
        match self {
            BinKind::Add => a + b,
            BinKind::Sub => a - b,
            BinKind::Mul => a * b,
            BinKind::Div => a / b,
            BinKind::Max => a.max(b),
            BinKind::Min => a.min(b),
        }
    }
}

/// One step of the gate, on a vector of the length the step before left.
#[derive(Debug, Clone)]
enum Step {
    /// `v ∘ c` (or `c ∘ v` when `const_first`), `c` of one value or one per element.
    Bin { kind: BinKind, konst: Arc<Vec<f32>>, const_first: bool },
    /// `v' = W v`, `W` stored transposed: `v.len()` columns of `rows` values (so that the
    /// product is a sum of scaled columns, which vectorises without horizontal sums).
    MatVec { w: Arc<Vec<f32>>, rows: usize },
    /// tract's element-wise operator (a sigmoid, say), run on the vector.
    Unary(ElementWiseOp),
}

impl PartialEq for Step {
    fn eq(&self, other: &Self) -> bool {
        match (self, other) {
            (Step::Bin { kind: a, konst: ca, const_first: fa }, Step::Bin { kind: b, konst: cb, const_first: fb }) => {
                a == b && fa == fb && same_bits(ca, cb)
            }
            (Step::MatVec { w: a, rows: ra }, Step::MatVec { w: b, rows: rb }) => ra == rb && same_bits(a, b),
            (Step::Unary(a), Step::Unary(b)) => a.0.name() == b.0.name() && a.1 == b.1,
            _ => false,
        }
    }
}

impl Step {
    /// The step on `v`.
    fn run(&self, v: Vec<f32>) -> TractResult<Vec<f32>> {
        Ok(match self {
            Step::Bin { kind, konst, const_first } => {
                let c = |i: usize| if konst.len() == 1 { konst[0] } else { konst[i] };
                (v.iter().enumerate())
                    .map(|(i, &x)| if *const_first { kind.apply(c(i), x) } else { kind.apply(x, c(i)) })
                    .collect()
            }
            Step::MatVec { w, rows } => mat_vec(w, *rows, &v),
            Step::Unary(op) => {
                let t = Tensor::from_shape(&[v.len()], &v)?;
                let out = op.eval(&EvalContext::out_of_plan(), tvec![t.into_tvalue()])?.remove(0);
                let out = out.try_as_plain_ram()?;
                out.as_slice::<f32>()?.to_vec()
            }
        })
    }
}

/// `W v` for `W` stored as columns of `rows` values, each output summed as tract's AVX-512
/// matrix-vector kernel (`avx512_mmm_f32_16x1`) sums it, so that the gate has its bits: with
/// at least 8 terms, four fused multiply-add chains over `k ≡ 0..3 (mod 4)` added up in order,
/// then the last `k mod 4` terms; with fewer, one chain. (The tracker is sensitive to the
/// last bit: on NanoTrack's `building4` a gate summed in another order moved one frame's peak
/// to another cell, and the track 13 px off the official one.)
fn mat_vec(w: &[f32], rows: usize, v: &[f32]) -> Vec<f32> {
    #[inline(always)]
    fn columns(w: &[f32], rows: usize, v: &[f32]) -> Vec<f32> {
        let k = v.len();
        let col = |i: usize| &w[i * rows..(i + 1) * rows];
        let fma_col = |acc: &mut [f32], i: usize| {
            acc.iter_mut().zip(col(i)).for_each(|(a, &c)| *a = c.mul_add(v[i], *a));
        };
        let mut out = vec![0f32; rows];
        let mut done = 0;
        if k >= 8 {
            let mut chains = [vec![0f32; rows], vec![0f32; rows], vec![0f32; rows], vec![0f32; rows]];
            while done + 4 <= k {
                for (j, chain) in chains.iter_mut().enumerate() {
                    fma_col(chain, done + j);
                }
                done += 4;
            }
            let [c0, c1, c2, c3] = &chains;
            for r in 0..rows {
                out[r] = ((c0[r] + c1[r]) + c2[r]) + c3[r];
            }
        }
        for i in done..k {
            fma_col(&mut out, i);
        }
        out
    }
    #[cfg(target_arch = "x86_64")]
    if crate::isa::isa().avx2_fma {
        #[target_feature(enable = "avx2,fma")]
        unsafe fn fused(w: &[f32], rows: usize, v: &[f32]) -> Vec<f32> {
            columns(w, rows, v)
        }
        // SAFETY: the CPU has AVX2 and FMA (the table's needs).
        return unsafe { fused(w, rows, v) };
    }
    // Elsewhere `mul_add` is the instruction (aarch64) or a correctly rounded library call.
    columns(w, rows, v)
}

/// `Σ xs` as ndarray sums a contiguous lane (which tract's `Reduce<Sum>` over the trailing
/// axes uses): eight running sums over `i ≡ 0..7 (mod 8)`, added pairwise (0+4, 1+5, 2+6,
/// 3+7) into the total in order, then the rest one by one.
#[inline(always)]
fn sum(xs: &[f32]) -> f32 {
    let mut lanes = [0f32; 8];
    let chunks = xs.chunks_exact(8);
    let rest = chunks.remainder();
    for x in chunks {
        for l in 0..8 {
            lanes[l] += x[l];
        }
    }
    let mut total = 0f32;
    for l in 0..4 {
        total += lanes[l] + lanes[l + 4];
    }
    rest.iter().fold(total, |t, &x| t + x)
}

/// `out(c, p) = act(x(c, p) · s(c))` with `s = gate(Σ_p x(c, p))` on `x` laid out `[c][p]`
/// (channels first, positions contiguous, any leading axes of length 1).
#[derive(Debug, Clone, PartialEq)]
pub struct SqueezeExcite {
    channels: usize,
    positions: usize,
    gate: Vec<Step>,
    act: Activation,
    output_shape: TVec<usize>,
}

// The constants are compared bit for bit and never NaN-sensitive: equality is an equivalence.
impl Eq for SqueezeExcite {}

impl Op for SqueezeExcite {
    fn name(&self) -> StaticName {
        "SqueezeExcite".into()
    }

    fn info(&self) -> TractResult<Vec<String>> {
        let (c, p, steps) = (self.channels, self.positions, self.gate.len());
        Ok(vec![format!("channels {c}, positions {p}, {steps} gate steps, activation {}", self.act.describe())])
    }

    op_as_typed_op!();
}

impl EvalOp for SqueezeExcite {
    op_out_of_plan!();

    fn eval(&self, _ctx: &EvalContext, inputs: TVec<TValue>) -> TractResult<TVec<TValue>> {
        let x = args_1!(inputs);
        let (c, p) = (self.channels, self.positions);
        ensure!(x.len() == c * p, "SqueezeExcite: {} inputs for {c} channels x {p} positions", x.len());
        let mut out = x.into_tensor();
        {
            let mut plain = out.try_as_plain_ram_mut()?;
            let data = plain.as_slice_mut::<f32>()?;
            let mut v: Vec<f32> = data.chunks_exact(p).map(sums).collect();
            for step in &self.gate {
                v = step.run(v)?;
            }
            ensure!(v.len() == c, "SqueezeExcite: the gate gave {} values for {c} channels", v.len());
            for (row, &s) in data.chunks_exact_mut(p).zip(&v) {
                scale(row, s);
                self.act.apply_all(row);
            }
        }
        out.set_shape(&self.output_shape)?;
        Ok(tvec!(out.into_tvalue()))
    }
}

/// [`sum`] on AVX-512 where there is.
fn sums(xs: &[f32]) -> f32 {
    #[cfg(target_arch = "x86_64")]
    if crate::isa::f32_kernel() == crate::isa::F32Kernel::Avx512 {
        #[target_feature(enable = "avx512f")]
        unsafe fn wide(xs: &[f32]) -> f32 {
            sum(xs)
        }
        // SAFETY: the CPU has AVX-512F (the table's needs).
        return unsafe { wide(xs) };
    }
    sum(xs)
}

/// `row *= s`, on AVX-512 where there is.
fn scale(row: &mut [f32], s: f32) {
    #[cfg(target_arch = "x86_64")]
    if crate::isa::f32_kernel() == crate::isa::F32Kernel::Avx512 {
        #[target_feature(enable = "avx512f")]
        unsafe fn wide(row: &mut [f32], s: f32) {
            row.iter_mut().for_each(|v| *v *= s)
        }
        // SAFETY: the CPU has AVX-512F (the table's needs).
        return unsafe { wide(row, s) };
    }
    row.iter_mut().for_each(|v| *v *= s)
}

impl TypedOp for SqueezeExcite {
    fn output_facts(&self, _inputs: &[&TypedFact]) -> TractResult<TVec<TypedFact>> {
        Ok(tvec!(f32::fact(&self.output_shape)))
    }

    fn cost(&self, _inputs: &[&TypedFact]) -> TractResult<TVec<(Cost, TDim)>> {
        let gate: usize = (self.gate.iter()).map(|s| if let Step::MatVec { w, .. } = s { w.len() } else { 0 }).sum();
        Ok(tvec!((Cost::FMA(f32::datum_type()), (2 * self.channels * self.positions + gate).into())))
    }

    as_op!();
}

/// The element count of an f32 fact with at most one axis longer than 1 (a vector, whatever
/// its rank: reshaping or transposing it keeps its values in order).
fn vector_len(fact: &TypedFact) -> Option<usize> {
    let shape = fact.shape.as_concrete()?;
    (fact.datum_type == f32::datum_type() && shape.iter().filter(|&&d| d > 1).count() <= 1)
        .then(|| shape.iter().product())
}

/// The [`SqueezeExcite`] that starts at `node`, its input and the nodes it stands for (in
/// order), if `node` is the spatial sum of one: an f32 `Reduce<Sum>` over the trailing axes
/// of a channels-first `x` (leading axes 1), whose sole consumers lead, one vector at a time,
/// through element-wise steps with constants, products with constant matrices and reshapes,
/// to a vector of one value per channel that multiplies `x`. The activation after the product
/// is taken in too.
pub(crate) fn squeeze_excite(
    model: &TypedModel,
    node: &TypedNode,
) -> TractResult<Option<(SqueezeExcite, OutletId, Vec<usize>)>> {
    let Some(reduce) = node.op_as::<Reduce>() else { return Ok(None) };
    let x = node.inputs[0];
    let Some(xs) = model.outlet_fact(x)?.shape.as_concrete().map(<[usize]>::to_vec) else { return Ok(None) };
    let rank = xs.len();
    let mut axes = reduce.axes.to_vec();
    axes.sort_unstable();
    // The channel axis is the one before the summed ones; the axes before it are 1.
    let Some(ch) = axes.first().and_then(|a| a.checked_sub(1)) else { return Ok(None) };
    if reduce.reducer != Reducer::Sum
        || model.outlet_fact(x)?.datum_type != f32::datum_type()
        || axes != (ch + 1..rank).collect::<Vec<_>>()
        || xs[..ch].iter().any(|&d| d != 1)
    {
        return Ok(None);
    }
    let (channels, positions) = (xs[ch], xs[ch + 1..].iter().product::<usize>());
    let (mut gate, mut chain, mut len, mut last) = (vec![], vec![node.id], channels, node);
    let product = loop {
        let Some(next) = sole_consumer(model, last) else { return Ok(None) };
        let from = OutletId::new(last.id, 0);
        let Some(out_len) = vector_len(&next.outputs[0].fact) else {
            // Not a vector: the product with `x`, or something else.
            break next;
        };
        if next.op_as::<AxisOp>().is_some() {
            // The same values in the same order.
        } else if let Some(bin) = next.op_as::<TypedBinOp>() {
            let Some(kind) = BinKind::of(bin) else { return Ok(None) };
            let Some(c) = other_const(model, next, from) else { return Ok(None) };
            if c.datum_type() != f32::datum_type() || !(c.len() == 1 || c.len() == len) || out_len != len {
                return Ok(None);
            }
            let konst = c.try_as_plain_ram()?.as_slice::<f32>()?.to_vec();
            gate.push(Step::Bin { kind, konst: Arc::new(konst), const_first: next.inputs[0] != from });
        } else if let Some(e) = next.op_as::<ElementWiseOp>() {
            if out_len != len {
                return Ok(None);
            }
            gate.push(Step::Unary(e.clone()));
        } else if let Some(ConstProduct { k, m, n, konst, data, .. }) = const_product(model, next)? {
            if data != from || k.0 != len || n.0 != 1 || m.0 != out_len {
                return Ok(None);
            }
            let w = konst.try_as_plain_ram()?;
            let w = w.as_slice::<f32>()?;
            let cols: Vec<f32> = (0..k.0).flat_map(|i| (0..m.0).map(move |r| w[r * m.1[0] + i * k.1[0]])).collect();
            gate.push(Step::MatVec { w: Arc::new(cols), rows: m.0 });
        } else {
            return Ok(None);
        }
        len = out_len;
        chain.push(next.id);
        last = next;
    };
    // The product: `x · s`, `s` one value per channel on `x`'s channel axis.
    let s = OutletId::new(last.id, 0);
    let s_shape = model.outlet_fact(s)?.shape.as_concrete().map(<[usize]>::to_vec);
    let per_channel =
        s_shape.is_some_and(|s| s.len() == rank && (0..rank).all(|a| s[a] == if a == ch { channels } else { 1 }));
    let is_mul = product.op_as::<TypedBinOp>().is_some_and(|b| b.0.is::<Mul>());
    let inputs_ok = product.inputs.len() == 2 && product.inputs.contains(&x) && product.inputs.contains(&s);
    if !is_mul || !inputs_ok || !per_channel || len != channels || gate.is_empty() {
        return Ok(None);
    }
    let Some(t) = tail(model, product, None)? else { return Ok(None) };
    if t.bias.is_some() || t.shape.iter().product::<usize>() != channels * positions {
        return Ok(None);
    }
    chain.extend(t.chain);
    let op = SqueezeExcite { channels, positions, gate, act: t.act, output_shape: t.shape };
    Ok(Some((op, x, chain)))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ops::attention::tests::values;
    use tract_nnef::tract_core::ops::einsum::EinSum;
    use tract_nnef::tract_core::ops::math::{add, max, min, mul};
    use tract_nnef::tract_core::ops::nn::{hard_swish, sigmoid};

    fn konst(model: &mut TypedModel, name: &str, shape: &[usize], v: &[f32]) -> OutletId {
        model.add_const(name, Tensor::from_shape(shape, v).unwrap()).unwrap()
    }

    /// NanoTrack's block as tract declutters it (rank 3, the batch axis gone): sum, scale,
    /// transpose, einsum with `[1, r, c]`, squeezes, bias, ReLU, unsqueezes, einsum with
    /// `[1, 1, c, r]`, transposes, squeeze, bias `[c, 1, 1]`, hard-sigmoid as four binary
    /// operators (or a sigmoid), the product with `x`, hard-swish.
    fn block(c: usize, r: usize, hw: usize, hard: bool) -> TypedModel {
        let mut m = TypedModel::default();
        let x = m.add_source("x", f32::fact([c, hw, hw])).unwrap();
        let s = m.wire_node("sum", Reduce::new(tvec![1, 2], Reducer::Sum), &[x]).unwrap()[0];
        let k = konst(&mut m, "recip", &[1, 1, 1], &[1.0 / (hw * hw) as f32]);
        let s = m.wire_node("norm", mul(), &[s, k]).unwrap()[0];
        let s = m.wire_node("t0", AxisOp::Move(0, 2), &[s]).unwrap()[0];
        let w1 = konst(&mut m, "w1", &[1, r, c], &values(r * c, 3));
        let e1 = EinSum::new("abk,ank->abn".parse().unwrap(), f32::datum_type());
        let s = m.wire_node("fc0", e1, &[s, w1]).unwrap()[0];
        let s = m.wire_node("sq0", AxisOp::Rm(1), &[s]).unwrap()[0];
        let s = m.wire_node("sq1", AxisOp::Rm(0), &[s]).unwrap()[0];
        let b1 = konst(&mut m, "b1", &[r], &values(r, 5));
        let s = m.wire_node("bias0", add(), &[s, b1]).unwrap()[0];
        let zero = konst(&mut m, "zero", &[1], &[0.0]);
        let s = m.wire_node("relu", max(), &[s, zero]).unwrap()[0];
        let s = m.wire_node("u0", AxisOp::Add(0), &[s]).unwrap()[0];
        let s = m.wire_node("u1", AxisOp::Add(0), &[s]).unwrap()[0];
        let s = m.wire_node("u2", AxisOp::Add(0), &[s]).unwrap()[0];
        let w2 = konst(&mut m, "w2", &[1, 1, c, r], &values(r * c, 9));
        let e2 = EinSum::new("abik,abnk->abin".parse().unwrap(), f32::datum_type());
        let s = m.wire_node("fc2", e2, &[s, w2]).unwrap()[0];
        let s = m.wire_node("t1", AxisOp::Move(3, 1), &[s]).unwrap()[0];
        let s = m.wire_node("sq2", AxisOp::Rm(0), &[s]).unwrap()[0];
        let b2 = konst(&mut m, "b2", &[c, 1, 1], &values(c, 11));
        let mut s = m.wire_node("bias2", add(), &[s, b2]).unwrap()[0];
        if hard {
            for (name, op, v) in
                [("alpha", mul(), 1.0 / 6.0), ("beta", add(), 0.5), ("one", min(), 1.0), ("zero2", max(), 0.0)]
            {
                let k = konst(&mut m, &format!("{name}_c"), &[1, 1, 1], &[v]);
                s = m.wire_node(name, op, &[s, k]).unwrap()[0];
            }
        } else {
            s = m.wire_node("sigmoid", sigmoid(), &[s]).unwrap()[0];
        }
        let y = m.wire_node("scale", mul(), &[x, s]).unwrap()[0];
        let y = m.wire_node("hs", hard_swish(), &[y]).unwrap()[0];
        m.select_output_outlets(&[y]).unwrap();
        m
    }

    #[test]
    fn a_block_is_one_operator_that_computes_what_tract_does() {
        // The kernel is the process's (CI runs the tests again with PRL_ISA capping it).
        let isa = crate::isa::f32_kernel();
        {
            for (c, r, hw, hard) in [(96, 24, 16, true), (40, 10, 7, true), (24, 8, 5, false)] {
                let mut model = block(c, r, hw, hard);
                let input = || tvec![Tensor::from_shape(&[c, hw, hw], &values(c * hw * hw, 1)).unwrap().into_tvalue()];
                let want = model.clone().into_runnable().unwrap().run(input()).unwrap();
                let done = super::super::accelerate(&mut model).unwrap();
                assert_eq!(done.squeeze_excite, 1, "{isa:?} c {c}");
                let ops: Vec<_> = model.nodes().iter().map(|n| n.op.name().to_string()).collect();
                assert_eq!(ops, ["Source", "SqueezeExcite"], "{isa:?} c {c}");
                let got = model.into_runnable().unwrap().run(input()).unwrap();
                assert_eq!(got[0].shape(), want[0].shape());
                let (got, want) = (got[0].try_as_plain_ram().unwrap(), want[0].try_as_plain_ram().unwrap());
                let (got, want) = (got.as_slice::<f32>().unwrap(), want.as_slice::<f32>().unwrap());
                for (i, (g, w)) in got.iter().zip(want).enumerate() {
                    assert!((g - w).abs() <= 2e-6 * w.abs().max(1.0), "{isa:?} c {c}, element {i}: {g} vs {w}");
                }
            }
        }
    }

    #[test]
    fn a_gate_that_is_not_per_channel_is_left_to_tract() {
        // The gate's second layer gives r values, not c: the product broadcasts otherwise.
        let mut m = TypedModel::default();
        let x = m.add_source("x", f32::fact([8, 4, 4])).unwrap();
        let s = m.wire_node("sum", Reduce::new(tvec![1, 2], Reducer::Sum), &[x]).unwrap()[0];
        let k = konst(&mut m, "k", &[1, 1, 1], &[0.5]);
        let s = m.wire_node("norm", mul(), &[s, k]).unwrap()[0];
        let s = m.wire_node("t", AxisOp::Move(0, 2), &[s]).unwrap()[0];
        // [1, 1, 8] · [1, 1, 1]-broadcast x [8, 4, 4]: not a per-channel product.
        let y = m.wire_node("scale", mul(), &[x, s]).unwrap()[0];
        m.select_output_outlets(&[y]).unwrap();
        let sum = m.node_by_name("sum").unwrap();
        assert!(squeeze_excite(&m, sum).unwrap().is_none());
    }
}
