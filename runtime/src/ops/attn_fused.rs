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
use super::attention::{gemm, keys_transposed, values_rows, View, MR, NR};
use super::par::{par_runs, parts};
use super::permute::Permute;
use super::softmax::softmax_row;
use super::{output_tensor_written, threads, SyncPtr};

/// Query rows whose scores are made, scaled, normalised and mixed together (a multiple of the
/// product tile's [`MR`] rows; 24 rows of 242 scores are 23 KB).
const BLOCK: usize = 4 * MR;

/// `out[m,a,n] = Σ_{b,k} softmax_row(scale · scores)[a,m,b,k]·values[b,a,k,n]` with
/// `scores[a,m,b,k] = Σ_j q[a,m,j]·keys[b,a,k,j]`: [`AttnScores`](super::AttnScores), the
/// multiply by `scale` (when there is one), [`RowSoftmax`](super::RowSoftmax) over each row of
/// `b·k` scores and [`AttnMix`](super::AttnMix), in one pass.
///
/// Its three inputs hold the operands where their [`View`]s say (`q` one piece of `m` rows of
/// `p`, the key sets `b` pieces of `k` rows of `p`, the value sets `b` pieces of `k` rows of
/// `n`, each of `heads` heads): so the builder's slices and gathers of the pieces q3..v5, and
/// the transposes that make those pieces of the `qkv` product, are read in place.
#[derive(Debug, Clone)]
pub struct Attention {
    /// The constant the scores are multiplied by before the softmax.
    pub scale: Option<f32>,
    /// `[heads, m, k, p, n]`.
    pub shape: [usize; 5],
    /// Where `q` is in the first input (one piece).
    pub q: View,
    /// Where the key sets are in the second input.
    pub keys: View,
    /// Where the value sets are in the third input (as many as key sets).
    pub values: View,
}

impl PartialEq for Attention {
    fn eq(&self, other: &Self) -> bool {
        self.scale.map(f32::to_bits) == other.scale.map(f32::to_bits)
            && (self.shape, &self.q, &self.keys, &self.values) == (other.shape, &other.q, &other.keys, &other.values)
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
        let [heads, m, k, p, n] = self.shape;
        let (qs, ks, vs) = (slice(&q)?, slice(&keys)?, slice(&values)?);
        let b = self.keys.pieces.len();
        let fits = |view: &View, rows: usize, width: usize, len: usize| {
            view.extent([heads, rows, width]).is_some_and(|e| e <= len)
        };
        ensure!(
            self.q.pieces.len() == 1
                && self.values.pieces.len() == b
                && heads * m * p * b * k * n > 0
                && fits(&self.q, m, p, qs.len())
                && fits(&self.keys, k, p, ks.len())
                && fits(&self.values, k, n, vs.len()),
            "Attention {self:?}: inputs of {}, {} and {} values",
            qs.len(),
            ks.len(),
            vs.len()
        );
        let row = b * k;
        // Key rows and value rows padded to whole vectors of 16.
        let (ldk, ldv) = (row.next_multiple_of(NR), n.next_multiple_of(NR));
        // Each head whole when there are at least twice as many heads as threads; else its rows
        // in parts, so that every thread has work ([`parts`]).
        let tiles = m.div_ceil(MR);
        let fill = |out: &mut [f32]| {
            let dst = SyncPtr(out.as_mut_ptr());
            par_runs(heads, parts(heads, 2 * threads(), tiles), tiles, |a, run| {
                let (first, last) = (run.start * MR, m.min(run.end * MR));
                let kt = keys_transposed(ks, &self.keys, [k, p], a, ldk);
                let va = values_rows(vs, &self.values, [k, n], a, ldv);
                let (mut scores, mut mixed) = (vec![0f32; BLOCK * row], vec![0f32; BLOCK * n]);
                let mut qrows = vec![0f32; BLOCK * p];
                for r0 in (first..last).step_by(BLOCK) {
                    let rows = BLOCK.min(last - r0);
                    let (scores, mixed) = (&mut scores[..rows * row], &mut mixed[..rows * n]);
                    // The block's rows of q, in place where they are consecutive.
                    let q = if self.q.token == p {
                        &qs[self.q.row(0, a, r0)..][..rows * p]
                    } else {
                        for (r, dst) in qrows.chunks_exact_mut(p).take(rows).enumerate() {
                            dst.copy_from_slice(&qs[self.q.row(0, a, r0 + r)..][..p]);
                        }
                        &qrows[..rows * p]
                    };
                    gemm(scores, row, q, p, &kt, ldk);
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
    fn output_facts(&self, _inputs: &[&TypedFact]) -> TractResult<TVec<TypedFact>> {
        let [heads, m, _, _, n] = self.shape;
        Ok(tvec!(f32::fact([m, heads, n])))
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
    let (&[1, heads, m, _], &[b, _, k, p]) = (q, keys) else { return Ok(None) };
    let (mut chain, mut last, mut scale, mut softmax) = (vec![node.id], node, None, false);
    while let Some(next) = sole_consumer(model, last) {
        let from = OutletId::new(last.id, 0);
        let reshape = matches!(next.op_as::<AxisOp>(), Some(AxisOp::Add(_) | AxisOp::Rm(_) | AxisOp::Reshape(..)));
        if softmax && einsum(next, "ambk,bakn->man")? && next.inputs[0] == from {
            let facts = model.node_input_facts(next.id)?;
            let probs = facts[0].shape.as_concrete().unwrap_or_default();
            let values = facts[1].shape.as_concrete().unwrap_or_default();
            let (&[ph, pm, pb, pk], &[vb, vh, vk, n]) = (probs, values) else { return Ok(None) };
            if (ph, pm, pb, pk, vb, vh, vk) != (heads, m, b, k, b, heads, k) {
                return Ok(None);
            }
            chain.push(next.id);
            let (Some((q, q_view)), Some((keys, keys_view)), Some((values, values_view))) = (
                view_of(model, node.inputs[0], 1)?,
                view_of(model, node.inputs[1], b)?,
                view_of(model, next.inputs[1], b)?,
            ) else {
                return Ok(None);
            };
            let op = Attention { scale, shape: [heads, m, k, p, n], q: q_view, keys: keys_view, values: values_view };
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

/// Where operand `outlet` (`len` pieces `[heads, tokens, width]`, f32) is read from: a tensor
/// and the [`View`] of the operand in it. Through a `Slice` or `Gather` of the first axis
/// ([`pieces_of`]), then through reshapes back to a [`Permute`] whose last three output axes
/// are the pieces' `[heads, tokens, width]` (the width consecutive in its input): that
/// `Permute`'s input (HMG's `qkv` product, before its transposes). Else the operand itself,
/// contiguous.
fn view_of(model: &TypedModel, outlet: OutletId, len: usize) -> TractResult<Option<(OutletId, View)>> {
    let shape = model.outlet_fact(outlet)?.shape.as_concrete().map(<[usize]>::to_vec).unwrap_or_default();
    let &[_, heads, tokens, width] = shape.as_slice() else { return Ok(None) };
    let own = (outlet, View::contiguous(0..len, [heads, tokens, width]));
    let (src, pieces) = pieces_of(model, outlet, len)?;
    let mut at = src;
    while let Some(AxisOp::Add(_) | AxisOp::Rm(_) | AxisOp::Reshape(..)) = model.node(at.node).op_as::<AxisOp>() {
        at = model.node(at.node).inputs[0];
    }
    let node = model.node(at.node);
    let (Some(permute), Some(input)) = (node.op_as::<Permute>(), node.inputs.first()) else {
        return Ok(Some((src, View::contiguous(pieces, [heads, tokens, width]))));
    };
    let Some(dims) = model.outlet_fact(*input)?.shape.as_concrete().map(<[usize]>::to_vec) else {
        return Ok(Some(own));
    };
    let perm = permute.perm();
    let r = perm.len();
    let strides: Vec<usize> = (0..dims.len()).map(|i| dims[i + 1..].iter().product()).collect();
    let out: Vec<usize> = perm.iter().map(|&a| dims[a]).collect();
    let src_count = model.outlet_fact(src)?.shape.as_concrete().map_or(0, |s| s[0]);
    if r < 3
        || out[r - 3..] != [heads, tokens, width]
        || out[..r - 3].iter().product::<usize>() != src_count
        || strides[perm[r - 1]] != 1
    {
        return Ok(Some((src, View::contiguous(pieces, [heads, tokens, width]))));
    }
    // Piece i: its index over the leading output axes (row-major), each axis's input stride.
    let start = |mut i: usize| {
        let mut off = 0;
        for a in (0..r - 3).rev() {
            off += (i % out[a]) * strides[perm[a]];
            i /= out[a];
        }
        off
    };
    let view = View {
        pieces: pieces.iter().map(|&i| start(i)).collect(),
        head: strides[perm[r - 3]],
        token: strides[perm[r - 2]],
    };
    Ok(Some((*input, view)))
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
    use crate::ops::attention::tests::{run, values};
    use crate::ops::{AttnMix, AttnScores, RowSoftmax};

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
            (3, 13, 2, 13, 8, 8, None),
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
            let op = Attention {
                scale,
                shape: [heads, m, k, p, n],
                q: View::contiguous([0], [heads, m, p]),
                keys: View::contiguous(0..b, [heads, k, p]),
                values: View::contiguous(0..b, [heads, k, n]),
            };
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
            let sliced = Attention {
                q: View::contiguous([1], [heads, m, p]),
                keys: View::contiguous(kp.iter().copied(), [heads, k, p]),
                values: View::contiguous(vp.iter().copied(), [heads, k, n]),
                ..op.clone()
            };
            let from_pieces = floats(&run(&sliced, inputs));
            // And read from HMG's `qkv` layout before its transposes: `[k, 3, heads, 3, p]`
            // (tokens, q/k/v, heads, part, width), piece `3·s + part` at `s·heads·3·p +
            // part·p`, heads `3·p` apart, tokens `9·heads·p` (q, keys and values of width p).
            if m == k && n == p && b == 2 {
                let qkv = values(k * 9 * heads * p, 11);
                let piece = |i: usize| -> Vec<f32> {
                    let mut out = vec![];
                    for a in 0..heads {
                        for t in 0..k {
                            let at = t * 9 * heads * p + (i / 3) * heads * 3 * p + a * 3 * p + (i % 3) * p;
                            out.extend_from_slice(&qkv[at..at + p]);
                        }
                    }
                    out
                };
                let t = |pieces: &[usize]| {
                    let v: Vec<f32> = pieces.iter().flat_map(|&i| piece(i)).collect();
                    Tensor::from_shape(&[pieces.len(), heads, k, p], &v).unwrap()
                };
                let probs = {
                    let mut sc = floats(&run(&AttnScores, vec![t(&[1]), t(&[3, 4])]));
                    if let Some(s) = scale {
                        sc.iter_mut().for_each(|x| *x *= s);
                    }
                    run(&RowSoftmax, vec![Tensor::from_shape(&[heads, m, b * k], &sc).unwrap()])
                };
                let want = floats(&run(&AttnMix, vec![probs.into_shape(&[heads, m, b, k]).unwrap(), t(&[6, 7])]));
                let view = |pieces: &[usize]| View {
                    pieces: pieces.iter().map(|&i| (i / 3) * heads * 3 * p + (i % 3) * p).collect(),
                    head: 3 * p,
                    token: 9 * heads * p,
                };
                let strided = Attention { q: view(&[1]), keys: view(&[3, 4]), values: view(&[6, 7]), ..op.clone() };
                let qkv = Tensor::from_shape(&[k, 3, heads, 3, p], &qkv).unwrap();
                let got = floats(&run(&strided, vec![qkv.clone(), qkv.clone(), qkv]));
                assert!(got.iter().zip(&want).all(|(x, y)| x.to_bits() == y.to_bits()), "qkv layout, heads {heads}");
            }
            for got in [single, pooled, from_pieces] {
                assert_eq!(got.len(), want.len());
                let same = got.iter().zip(&want).all(|(x, y)| x.to_bits() == y.to_bits());
                assert!(same, "heads {heads}, m {m}, b {b}, k {k}, p {p}, n {n}");
            }
        }
    }
}
