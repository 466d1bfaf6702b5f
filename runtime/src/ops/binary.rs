//! f32 products and sums where one operand is broadcast ([`BroadcastBinary`]): the regulators'
//! gates (`[1,384,21,21] · [1,1,21,21]`) and squeeze-excitation scalings (`[1,192,11,11] ·
//! [1,192,1,1]`).
//!
//! tract's broadcasting binary operators walked these element by element (0.4 GFLOP/s, about
//! 0.8 ms a gate here). Here the axes are merged into runs where the small operand is either
//! read along with the large one or held, so the inner loop is a plain vectorised zip or a
//! scalar times a row.

use tract_nnef::internal::*;
use tract_nnef::tract_core::ops::binary::TypedBinOp;
use tract_nnef::tract_core::ops::math::{Add, Mul};

use super::act::{Activation, Tail};
use super::SHARE;

/// Which operation.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Binary {
    /// `a · b`
    Mul,
    /// `a + b`
    Add,
}

/// `out = act(full ∘ small)` (`∘` commutative) where `small` has the rank of `full` and each of
/// its axes is either `full`'s or 1, and `act` the activation after it in the graph, if any
/// (squeeze-excitation's scaling is followed by hard-swish in MobileNetV3); or, `residual`,
/// `out = full + full ∘ small`, the sum after it taken in (the regulators' gates `x + x·t`).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct BroadcastBinary {
    /// The operation.
    pub op: Binary,
    /// Which input has the output's shape (0 or 1).
    pub full: usize,
    act: Activation,
    /// The output is `full` plus the operation's result.
    residual: bool,
}

impl BroadcastBinary {
    /// The operation followed by the nodes of `tail` ([`super::act::tail`]), where they keep
    /// its output's shape.
    pub(crate) fn fused(&self, tail: &Tail, shape: &[usize]) -> Option<BroadcastBinary> {
        (tail.bias.is_none() && tail.shape.as_slice() == shape && !self.residual)
            .then(|| BroadcastBinary { act: tail.act, ..self.clone() })
    }

    /// The operation of `node` with the `Add` after it that sums its result with its full
    /// operand (`x + x·t`, in either order) taken in, and that `Add`'s node; none where
    /// `node`'s output has other readers or the `Add` is something else.
    pub(crate) fn with_residual(&self, model: &TypedModel, node: &TypedNode) -> Option<(BroadcastBinary, usize)> {
        let add = super::act::sole_consumer(model, node)?;
        let is_add = add.op_as::<TypedBinOp>().is_some_and(|b| b.0.is::<Add>());
        let ours = OutletId::new(node.id, 0);
        let full = node.inputs[self.full];
        let pair = add.inputs[..] == [full, ours] || add.inputs[..] == [ours, full];
        let same = model.outlet_fact(ours).ok()?.shape == add.outputs[0].fact.shape;
        (is_add && pair && same && !self.residual && self.act == Activation::NONE)
            .then(|| (BroadcastBinary { residual: true, ..self.clone() }, add.id))
    }
}

impl Op for BroadcastBinary {
    fn name(&self) -> StaticName {
        "BroadcastBinary".into()
    }

    fn info(&self) -> TractResult<Vec<String>> {
        let residual = if self.residual { ", plus the full operand" } else { "" };
        Ok(vec![format!("{:?}{residual}, activation {}", self.op, self.act.describe())])
    }

    op_as_typed_op!();
}

/// The shapes as runs `(length, small operand's stride)` of merged axes: stride 0 where the
/// small operand is held, its row-major stride where it is read along.
fn runs(full: &[usize], small: &[usize]) -> Vec<(usize, usize)> {
    let mut runs: Vec<(usize, bool)> = vec![];
    for (&f, &s) in full.iter().zip(small) {
        if f == 1 {
            continue;
        }
        let read = s == f;
        match runs.last_mut() {
            Some((len, r)) if *r == read => *len *= f,
            _ => runs.push((f, read)),
        }
    }
    let mut stride = 1;
    let mut out: Vec<(usize, usize)> = runs
        .iter()
        .rev()
        .map(|&(len, read)| {
            let s = if read { stride } else { 0 };
            if read {
                stride *= len;
            }
            (len, s)
        })
        .collect();
    out.reverse();
    out
}

impl EvalOp for BroadcastBinary {
    op_out_of_plan!();

    fn eval(&self, _ctx: &EvalContext, inputs: TVec<TValue>) -> TractResult<TVec<TValue>> {
        let (a, b) = args_2!(inputs);
        let (full, small) = if self.full == 0 { (a, b) } else { (b, a) };
        ensure!(
            full.rank() == small.rank() && full.shape().iter().zip(small.shape()).all(|(&f, &s)| s == f || s == 1),
            "BroadcastBinary: {:?} and {:?}",
            full.shape(),
            small.shape()
        );
        let runs = runs(full.shape(), small.shape());
        let small = small.try_as_plain_ram()?;
        let small = small.as_slice::<f32>()?;
        let (inner, inner_stride) = runs.last().copied().unwrap_or((1, 0));
        let outer = &runs[..runs.len().saturating_sub(1)];
        // Whole rows to a share, at least [`SHARE`] values (fewer stay on one thread).
        let rows = SHARE.div_ceil(inner.max(1));
        // Row `r` of the output (`full`'s row in it, or given as `src`).
        let row = |r: usize, src: Option<&[f32]>, chunk: &mut [f32]| {
            // The small operand's offset for this row (mixed radix over the outer runs).
            let (mut rest, mut at) = (r, 0);
            for &(len, stride) in outer.iter().rev() {
                at += (rest % len) * stride;
                rest /= len;
            }
            let f = |x: f32, s: f32| match self.op {
                Binary::Mul => x * s,
                Binary::Add => x + s,
            };
            match (src, inner_stride) {
                (None, 0) => chunk.iter_mut().for_each(|v| *v = f(*v, small[at])),
                (None, _) => chunk.iter_mut().zip(&small[at..at + inner]).for_each(|(v, &s)| *v = f(*v, s)),
                (Some(src), 0) => chunk.iter_mut().zip(src).for_each(|(v, &x)| *v = x + f(x, small[at])),
                (Some(src), _) => {
                    let pairs = src.iter().zip(&small[at..at + inner]);
                    chunk.iter_mut().zip(pairs).for_each(|(v, (&x, &s))| *v = x + f(x, s))
                }
            }
            self.act.apply_all(chunk);
        };
        if self.residual {
            // A new tensor (`full` is read by the sum too: taking it would copy it whole on one
            // thread).
            let src = full.try_as_plain_ram()?;
            let src = src.as_slice::<f32>()?;
            let fill = |out: &mut [f32]| {
                super::par_chunks(out, rows * inner.max(1), |c, share| {
                    let src = &src[c * rows * inner.max(1)..][..share.len()];
                    for (r, (chunk, src)) in share.chunks_exact_mut(inner).zip(src.chunks_exact(inner)).enumerate() {
                        row(c * rows + r, Some(src), chunk);
                    }
                });
                Ok(())
            };
            // SAFETY: the shares cover the output, each row of each share written whole.
            let out = unsafe { super::output_tensor_written(full.shape(), fill)? };
            return Ok(tvec!(out.into_tvalue()));
        }
        let mut out = full.into_tensor();
        {
            let mut plain = out.try_as_plain_ram_mut()?;
            let data = plain.as_slice_mut::<f32>()?;
            super::par_chunks(data, rows * inner.max(1), |c, share| {
                for (r, chunk) in share.chunks_exact_mut(inner).enumerate() {
                    row(c * rows + r, None, chunk);
                }
            });
        }
        Ok(tvec!(out.into_tvalue()))
    }
}

impl TypedOp for BroadcastBinary {
    fn output_facts(&self, inputs: &[&TypedFact]) -> TractResult<TVec<TypedFact>> {
        Ok(tvec!(inputs[self.full].without_value()))
    }
    as_op!();
}

/// The [`BroadcastBinary`] for an f32 `Mul` or `Add` of two non-constant inputs of one rank
/// where one is broadcast against the other (at least 4096 outputs).
pub(crate) fn broadcast_binary(model: &TypedModel, node: &TypedNode) -> TractResult<Option<BroadcastBinary>> {
    let Some(bin) = node.op_as::<TypedBinOp>() else { return Ok(None) };
    let op = if bin.0.is::<Mul>() {
        Binary::Mul
    } else if bin.0.is::<Add>() {
        Binary::Add
    } else {
        return Ok(None);
    };
    let facts = model.node_input_facts(node.id)?;
    if facts.len() != 2 || facts.iter().any(|f| f.datum_type != f32::datum_type() || f.konst.is_some()) {
        return Ok(None);
    }
    let (Some(a), Some(b)) = (facts[0].shape.as_concrete(), facts[1].shape.as_concrete()) else { return Ok(None) };
    if a.len() != b.len() || a == b {
        return Ok(None);
    }
    let covers = |f: &[usize], s: &[usize]| f.iter().zip(s).all(|(&f, &s)| s == f || s == 1);
    let full = if covers(a, b) {
        0
    } else if covers(b, a) {
        1
    } else {
        return Ok(None);
    };
    let outputs: usize = [a, b][full].iter().product();
    Ok((outputs >= 4096).then_some(BroadcastBinary { op, full, act: Activation::NONE, residual: false }))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn broadcasts_like_tract() {
        // The gate (small operand read along the plane, held over channels), the SE scaling
        // (read along channels, held over the plane), a mixed one, and the small one first.
        for (a, b) in [
            (vec![1, 6, 5, 7], vec![1, 1, 5, 7]),
            (vec![1, 6, 5, 7], vec![1, 6, 1, 1]),
            (vec![2, 6, 5, 7], vec![2, 1, 5, 1]),
            (vec![1, 1, 5, 7], vec![3, 6, 5, 7]),
            // PRL-Track's gate and a scaling, over several shares of the threads' work (the
            // rows' offsets across their seams).
            (vec![1, 384, 21, 21], vec![1, 1, 21, 21]),
            (vec![1, 192, 11, 11], vec![1, 192, 1, 1]),
            (vec![2, 96, 17, 23], vec![2, 1, 17, 1]),
        ] {
            let values = |s: &[usize], k: usize| {
                let v: Vec<f32> = (0..s.iter().product()).map(|i| ((i * k % 13) as f32) - 6.0).collect();
                Tensor::from_shape(s, &v).unwrap()
            };
            for (op, tract_op) in [
                (Binary::Mul, tract_nnef::tract_core::ops::math::mul()),
                (Binary::Add, tract_nnef::tract_core::ops::math::add()),
            ] {
                let (x, y) = (values(&a, 7), values(&b, 5));
                let inputs = tvec![x.clone().into_tvalue(), y.clone().into_tvalue()];
                let want = tract_op.eval(&EvalContext::out_of_plan(), inputs).unwrap().remove(0);
                let full = if a.iter().product::<usize>() >= b.iter().product() { 0 } else { 1 };
                let ours = BroadcastBinary { op, full, act: Activation::NONE, residual: false };
                let pool = tract_linalg::multithread::Executor::multithread(2);
                let got = tract_linalg::multithread::multithread_tract_scope(pool, || {
                    ours.eval(&EvalContext::out_of_plan(), tvec![x.clone().into_tvalue(), y.clone().into_tvalue()])
                        .unwrap()
                });
                assert_eq!(got[0].shape(), want.shape());
                let same = |got: &TValue, want: &TValue| {
                    let (got, want) = (got.try_as_plain_ram().unwrap(), want.try_as_plain_ram().unwrap());
                    assert_eq!(got.as_slice::<f32>().unwrap(), want.as_slice::<f32>().unwrap(), "{op:?} {a:?} {b:?}");
                };
                same(&got[0], &want);
                // With the sum of the full operand and the result taken in (tract's `Add` after
                // it as the reference), on one thread and on two.
                let full_value = if full == 0 { &x } else { &y };
                let add = tract_nnef::tract_core::ops::math::add();
                let inputs = tvec![full_value.clone().into_tvalue(), want];
                let want = add.eval(&EvalContext::out_of_plan(), inputs).unwrap().remove(0);
                let ours = BroadcastBinary { residual: true, ..ours };
                for threads in [1, 2] {
                    let pool = tract_linalg::multithread::Executor::multithread(threads);
                    let got = tract_linalg::multithread::multithread_tract_scope(pool, || {
                        let inputs = tvec![x.clone().into_tvalue(), y.clone().into_tvalue()];
                        ours.eval(&EvalContext::out_of_plan(), inputs).unwrap()
                    });
                    same(&got[0], &want);
                }
            }
        }
    }
}
