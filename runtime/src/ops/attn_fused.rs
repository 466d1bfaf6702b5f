//! HMG's attention in one operator ([`Attention`]): per head and block of query rows, the
//! scores, their scale, the softmax and the mix, the score block staying in the thread's cache.
//!
//! Run as the three operators of `attention.rs` plus tract's multiply, each attention wrote a
//! 1.4 MB score matrix, scaled it in place, read it for the softmax and again for the mix: a
//! pass over the memory bus per step, and four hand-overs to the threads. Here a block of 24
//! rows of scores (23 KB) goes through every step before the next is made. The arithmetic is
//! the same, in the same order (the same product tiles, the multiply, the same softmax), so the
//! outputs are those of the separate operators bit for bit.

use tract_nnef::internal::*;
use tract_nnef::tract_core::ops::array::{Gather, Slice};
use tract_nnef::tract_core::ops::binary::TypedBinOp;
use tract_nnef::tract_core::ops::einsum::EinSum;
use tract_nnef::tract_core::ops::math::Mul;
use tract_nnef::tract_core::ops::nn::{Softmax, SoftmaxKind};

use super::act::{other_const, sole_consumer};
use super::attention::{gemm, keys_transposed, values_rows, MR, NR};
use super::softmax::softmax_row;
use super::{output_tensor_written, par_for, threads, SyncPtr};

/// Query rows whose scores are made, scaled, normalised and mixed together (a multiple of the
/// product tile's [`MR`] rows; 24 rows of 242 scores are 23 KB).
const BLOCK: usize = 4 * MR;

/// `out[m,a,n] = Σ_{b,k} softmax_row(scale · scores)[a,m,b,k]·values[b,a,k,n]` with
/// `scores[a,m,b,k] = Σ_j q[a,m,j]·keys[b,a,k,j]`: [`AttnScores`](super::AttnScores), the
/// multiply by `scale` (when there is one), [`RowSoftmax`](super::RowSoftmax) over each row of
/// `b·k` scores and [`AttnMix`](super::AttnMix), in one pass.
///
/// Its three inputs hold the operands as slices of their first axis: `q` is slice `q_piece` of
/// the first (`[_, heads, m, p]`), key set `bi` slice `key_pieces[bi]` of the second (`[_, heads,
/// k, p]`), value set `bi` slice `value_pieces[bi]` of the third (`[_, heads, k, n]`). So the
/// builder's slices and gathers of the tensor of all pieces (q3..v5) are read in place.
#[derive(Debug, Clone, Default)]
pub struct Attention {
    /// The constant the scores are multiplied by before the softmax.
    pub scale: Option<f32>,
    /// Which slice of the first input is `q`.
    pub q_piece: usize,
    /// Which slices of the second input are the key sets.
    pub key_pieces: TVec<usize>,
    /// Which slices of the third input are the value sets (as many as key sets).
    pub value_pieces: TVec<usize>,
}

impl PartialEq for Attention {
    fn eq(&self, other: &Self) -> bool {
        self.scale.map(f32::to_bits) == other.scale.map(f32::to_bits)
            && (self.q_piece, &self.key_pieces, &self.value_pieces)
                == (other.q_piece, &other.key_pieces, &other.value_pieces)
    }
}

impl Eq for Attention {}

impl Op for Attention {
    fn name(&self) -> StaticName {
        "Attention".into()
    }

    fn info(&self) -> TractResult<Vec<String>> {
        Ok(vec![format!("scores, scale {:?}, softmax and mix in blocks of {BLOCK} rows", self.scale)])
    }

    op_as_typed_op!();
}

impl EvalOp for Attention {
    op_out_of_plan!();

    fn eval(&self, _ctx: &EvalContext, inputs: TVec<TValue>) -> TractResult<TVec<TValue>> {
        let (q, keys, values) = args_3!(inputs);
        let bad =
            || format!("Attention {self:?}: q {:?}, keys {:?}, values {:?}", q.shape(), keys.shape(), values.shape());
        let (&[pq, heads, m, p], &[pk, kh, k, kp], &[pv, vh, vk, n]) = (q.shape(), keys.shape(), values.shape()) else {
            bail!(bad())
        };
        let b = self.key_pieces.len();
        let in_range = |pieces: &[usize], len: usize| pieces.iter().all(|&i| i < len);
        ensure!(
            (kh, kp, vh, vk, self.value_pieces.len()) == (heads, p, heads, k, b)
                && p * b * k * n > 0
                && self.q_piece < pq
                && in_range(&self.key_pieces, pk)
                && in_range(&self.value_pieces, pv),
            bad()
        );
        let (qs, ks, vs) = (slice(&q)?, slice(&keys)?, slice(&values)?);
        let qs = &qs[self.q_piece * heads * m * p..][..heads * m * p];
        let row = b * k;
        // Key rows and value rows padded to whole vectors of 16.
        let (ldk, ldv) = (row.next_multiple_of(NR), n.next_multiple_of(NR));
        // Each head whole when there are at least twice as many heads as threads; else its rows
        // in parts, so that every thread has work.
        let parts = (2 * threads()).div_ceil(heads.max(1)).clamp(1, m.div_ceil(MR).max(1));
        let per_part = m.div_ceil(parts).next_multiple_of(MR);
        let fill = |out: &mut [f32]| {
            let dst = SyncPtr(out.as_mut_ptr());
            par_for(heads * parts, |item| {
                let (a, first) = (item / parts, (item % parts) * per_part);
                let last = m.min(first + per_part);
                if first >= last {
                    return;
                }
                let kt = keys_transposed(ks, [heads, k, p], &self.key_pieces, a, ldk);
                let va = values_rows(vs, [heads, k, n], &self.value_pieces, a, ldv);
                let (mut scores, mut mixed) = (vec![0f32; BLOCK * row], vec![0f32; BLOCK * n]);
                for r0 in (first..last).step_by(BLOCK) {
                    let rows = BLOCK.min(last - r0);
                    let (scores, mixed) = (&mut scores[..rows * row], &mut mixed[..rows * n]);
                    gemm(scores, row, &qs[(a * m + r0) * p..(a * m + r0 + rows) * p], p, &kt, ldk);
                    scores.chunks_exact_mut(row).for_each(|r| softmax_row(r, self.scale));
                    gemm(mixed, n, scores, row, &va, ldv);
                    for (r, values) in mixed.chunks_exact(n).enumerate() {
                        // SAFETY: row `r0 + r < m` of head `a < heads` is `n` values at
                        // `((r0 + r)·heads + a)·n` of the `m·heads·n` output; this item alone
                        // writes head `a`'s rows `first..last`.
                        unsafe {
                            std::ptr::copy_nonoverlapping(values.as_ptr(), dst.at(((r0 + r) * heads + a) * n), n)
                        };
                    }
                }
            });
            Ok(())
        };
        // SAFETY: the items cover every head and every row `0..m` (parts of `per_part` rows,
        // `parts·per_part >= m`), and each row of each head writes its `n` values.
        let out = unsafe { output_tensor_written(&[m, heads, n], fill)? };
        Ok(tvec!(out.into_tvalue()))
    }
}

fn slice(v: &TValue) -> TractResult<&[f32]> {
    v.try_as_plain_ram()?.as_slice::<f32>()
}

impl TypedOp for Attention {
    fn output_facts(&self, inputs: &[&TypedFact]) -> TractResult<TVec<TypedFact>> {
        let (q, v) = (&inputs[0].shape, &inputs[2].shape);
        Ok(tvec!(f32::fact([q[2].clone(), q[1].clone(), v[3].clone()])))
    }
    as_op!();
}

/// An [`Attention`], its inputs and the nodes it stands for, in order.
type Fused = (Attention, TVec<OutletId>, Vec<usize>);

/// The [`Attention`] that `node` starts, with its inputs (`q`, keys, values) and the nodes it
/// stands for: `node` the scores' einsum (`camk,bank->ambn`, f32, concrete shapes), then, each
/// the sole reader of the one before, reshapes, at most one multiply by a constant, the softmax
/// over the last axis of rows of all the scores of a query, reshapes, and the mix's einsum
/// (`ambk,bakn->man`) reading it as its first input.
pub(crate) fn fused_attention(model: &TypedModel, node: &TypedNode) -> TractResult<Option<Fused>> {
    let f32_concrete = |f: &TypedFact| f.datum_type == f32::datum_type() && f.shape.is_concrete();
    let einsum = |n: &TypedNode, axes: &str| -> TractResult<bool> {
        let facts = model.node_input_facts(n.id)?;
        Ok(n.op_as::<EinSum>().is_some_and(|e| {
            e.q_params.is_none()
                && e.operating_dt == f32::datum_type()
                && e.axes.to_string() == axes
                && facts.len() == 2
                && facts.iter().all(|f| f32_concrete(f))
        }))
    };
    if !einsum(node, "camk,bank->ambn")? {
        return Ok(None);
    }
    let facts = model.node_input_facts(node.id)?;
    let (q, keys) =
        (facts[0].shape.as_concrete().unwrap_or_default(), facts[1].shape.as_concrete().unwrap_or_default());
    let (&[1, heads, m, _], &[b, _, k, _]) = (q, keys) else { return Ok(None) };
    let (mut chain, mut last, mut scale, mut softmax) = (vec![node.id], node, None, false);
    while let Some(next) = sole_consumer(model, last) {
        let from = OutletId::new(last.id, 0);
        let reshape = matches!(next.op_as::<AxisOp>(), Some(AxisOp::Add(_) | AxisOp::Rm(_) | AxisOp::Reshape(..)));
        if softmax && einsum(next, "ambk,bakn->man")? && next.inputs[0] == from {
            let facts = model.node_input_facts(next.id)?;
            let probs = facts[0].shape.as_concrete().unwrap_or_default();
            let values = facts[1].shape.as_concrete().unwrap_or_default();
            let (&[ph, pm, pb, pk], &[vb, vh, vk, _]) = (probs, values) else { return Ok(None) };
            if (ph, pm, pb, pk, vb, vh, vk) != (heads, m, b, k, b, heads, k) {
                return Ok(None);
            }
            chain.push(next.id);
            let (q, q_pieces) = pieces_of(model, node.inputs[0], 1)?;
            let (keys, key_pieces) = pieces_of(model, node.inputs[1], b)?;
            let (values, value_pieces) = pieces_of(model, next.inputs[1], b)?;
            let op = Attention { scale, q_piece: q_pieces[0], key_pieces, value_pieces };
            return Ok(Some((op, tvec![q, keys, values], chain)));
        } else if reshape {
            // The same values in the same order.
        } else if let (false, None, Some(bin)) = (softmax, scale, next.op_as::<TypedBinOp>()) {
            let c = other_const(model, next, from).filter(|c| c.len() == 1 && c.datum_type() == f32::datum_type());
            let Some(c) = c.filter(|_| bin.0.is::<Mul>()) else { return Ok(None) };
            scale = Some(c.cast_to_scalar::<f32>()?);
        } else if let (false, Some(s)) = (softmax, next.op_as::<Softmax>()) {
            let input = model.outlet_fact(from)?;
            let rank = input.rank();
            let rows = input.shape.as_concrete().and_then(|s| s.last().copied());
            if s.kind != SoftmaxKind::Softmax
                || s.quant_output_dt.is_some()
                || s.axes.as_slice() != [rank - 1]
                || rows != Some(b * k)
            {
                return Ok(None);
            }
            softmax = true;
        } else {
            return Ok(None);
        }
        if !f32_concrete(&next.outputs[0].fact) {
            return Ok(None);
        }
        chain.push(next.id);
        last = next;
    }
    Ok(None)
}

/// `outlet` (`len` slices of an f32 value's first axis) as slices of another value: the input
/// of the `Slice` of one index or the `Gather` of constant indices on axis 0 that makes it,
/// and those indices; else `outlet` itself and `0..len`.
fn pieces_of(model: &TypedModel, outlet: OutletId, len: usize) -> TractResult<(OutletId, TVec<usize>)> {
    let node = model.node(outlet.node);
    let own = (outlet, (0..len).collect());
    let Some(&src) = node.inputs.first() else { return Ok(own) };
    let fact = model.outlet_fact(src)?;
    let Some(count) = fact.shape.as_concrete().filter(|s| s.len() == 4).map(|s| s[0]) else { return Ok(own) };
    if fact.datum_type != f32::datum_type() {
        return Ok(own);
    }
    if let Some(slice) = node.op_as::<Slice>() {
        let (start, end) = (slice.start.to_usize().ok(), slice.end.to_usize().ok());
        if let (0, Some(start), Some(end), 1) = (slice.axis, start, end, len) {
            if end == start + 1 && end <= count {
                return Ok((src, tvec![start]));
            }
        }
    }
    if node.op_as::<Gather>().is_some_and(|g| g.axis == 0 && g.output_type.is_none()) {
        let indices = node.inputs.get(1).map(|&i| model.outlet_fact(i)).transpose()?.and_then(|f| f.konst.clone());
        let indices = indices
            .filter(|t| t.rank() == 1 && t.len() == len)
            .and_then(|t| t.cast_to::<i64>().ok().map(|t| t.into_owned()));
        if let Some(indices) = indices {
            let picked: Option<TVec<usize>> = indices
                .try_as_plain_ram()?
                .as_slice::<i64>()?
                .iter()
                .map(|&i| usize::try_from(i).ok().filter(|&i| i < count))
                .collect();
            if let Some(picked) = picked {
                return Ok((src, picked));
            }
        }
    }
    Ok(own)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ops::{AttnMix, AttnScores, RowSoftmax};

    fn run(op: &dyn EvalOp, inputs: Vec<Tensor>) -> Tensor {
        let inputs = inputs.into_iter().map(|t| t.into_tvalue()).collect();
        op.eval(&EvalContext::out_of_plan(), inputs).unwrap().remove(0).into_tensor()
    }

    fn values(n: usize, seed: usize) -> Vec<f32> {
        (0..n).map(|i| (((i + seed) * 7919 % 1000) as f32) / 250.0 - 2.0).collect()
    }

    fn floats(t: &Tensor) -> Vec<f32> {
        t.try_as_plain_ram().unwrap().as_slice::<f32>().unwrap().to_vec()
    }

    /// The fused operator gives the separate operators' bits: rows not a multiple of the
    /// block or of the tile, value widths below and past a vector, with and without a scale,
    /// on one thread and on tract's pool of three (heads split in parts of rows), and with its
    /// operands read as slices of larger tensors.
    #[test]
    fn equals_the_separate_operators_bit_for_bit() {
        for (heads, m, b, k, p, n, scale) in [
            (3, 5, 2, 7, 16, 16, Some(0.25f32)),
            (2, 121, 2, 121, 16, 16, Some(0.144_337_56)),
            (5, 31, 1, 40, 8, 20, None),
            (1, 1, 3, 3, 4, 3, Some(3.0)),
        ] {
            let q = Tensor::from_shape(&[1, heads, m, p], &values(heads * m * p, 1)).unwrap();
            let keys = Tensor::from_shape(&[b, heads, k, p], &values(b * heads * k * p, 2)).unwrap();
            let v = Tensor::from_shape(&[b, heads, k, n], &values(b * heads * k * n, 3)).unwrap();
            let mut scores = floats(&run(&AttnScores, vec![q.clone(), keys.clone()]));
            if let Some(s) = scale {
                scores.iter_mut().for_each(|x| *x *= s);
            }
            let probs = run(&RowSoftmax, vec![Tensor::from_shape(&[heads, m, b * k], &scores).unwrap()]);
            let probs = probs.into_shape(&[heads, m, b, k]).unwrap();
            let want = floats(&run(&AttnMix, vec![probs, v.clone()]));
            let op = Attention { scale, q_piece: 0, key_pieces: (0..b).collect(), value_pieces: (0..b).collect() };
            let single = floats(&run(&op, vec![q.clone(), keys.clone(), v.clone()]));
            let pool = tract_linalg::multithread::Executor::multithread(3);
            let pooled = tract_linalg::multithread::multithread_tract_scope(pool, || {
                floats(&run(&op, vec![q.clone(), keys.clone(), v.clone()]))
            });
            // The operands as slices of one tensor of pieces (HMG's q3..v5): q piece 1 of a
            // first input of 3, the key sets pieces 4, 0.. of 5, the value sets pieces 2.. of 6.
            let (kp, vp): (TVec<usize>, TVec<usize>) = ((0..b).map(|i| (4 + i) % 5).collect(), (2..2 + b).collect());
            let stack = |parts: usize, at: &[usize], t: &Tensor| {
                let (len, v) = (t.len() / t.shape()[0], floats(t));
                let mut all: Vec<f32> = values(parts * len, 9);
                for (i, &piece) in at.iter().enumerate() {
                    all[piece * len..(piece + 1) * len].copy_from_slice(&v[i * len..(i + 1) * len]);
                }
                let mut shape = t.shape().to_vec();
                shape[0] = parts;
                Tensor::from_shape(&shape, &all).unwrap()
            };
            let inputs = vec![stack(3, &[1], &q), stack(5, &kp, &keys), stack(6, &vp, &v)];
            let sliced = Attention { scale, q_piece: 1, key_pieces: kp.clone(), value_pieces: vp.clone() };
            let from_pieces = floats(&run(&sliced, inputs));
            for got in [single, pooled, from_pieces] {
                assert_eq!(got.len(), want.len());
                let same = got.iter().zip(&want).all(|(x, y)| x.to_bits() == y.to_bits());
                assert!(same, "heads {heads}, m {m}, b {b}, k {k}, p {p}, n {n}");
            }
        }
    }
}
