//! Chains of axis moves as one permuting copy ([`Permute`]).
//!
//! HMG's attention splits its `qkv` product into pieces and heads with three transposes in a
//! row (tract's `MoveAxis`: `[N, 3, 12, 3, 16]` tokens by feature, heads, q/k/v and head
//! width, to `[3, 3, 12, N, 16]`): three passes over 3 MB, each on one thread, 0.25 ms a block
//! on either thread count (0.5 ms of PRL-Track's step, a tenth of what stays serial at two
//! threads). Here the moves are composed into one permutation and the output written once, in
//! order, split over the pool's threads; rows the permutation keeps whole (the 16 values of a
//! head's width) are copied as rows.

use tract_nnef::internal::*;

use super::act::sole_consumer;
use super::{output_tensor_written, par_chunks, SHARE};

/// `y[i0, .., ir] = x[j]` where output axis `a` is input axis `perm[a]`: the transposes of a
/// chain of tract's axis moves, in one copy.
#[derive(Debug, Clone, PartialEq, Eq, Hash)]
pub struct Permute {
    /// Output axis `a` is input axis `perm[a]`.
    perm: TVec<usize>,
}

impl Permute {
    /// Output axis `a` is input axis `perm()[a]`.
    pub(super) fn perm(&self) -> &[usize] {
        &self.perm
    }

    /// The copy of `input_shape` by `perm`: the output's lengths, and as few (length, source
    /// stride) axes as describe it (axes of length 1 dropped, axes consecutive in both the
    /// output and the input merged; at least one).
    fn plan(&self, input_shape: &[usize]) -> (TVec<usize>, Vec<(usize, usize)>) {
        let strides: TVec<usize> = (0..input_shape.len()).map(|i| input_shape[i + 1..].iter().product()).collect();
        let out_shape: TVec<usize> = self.perm.iter().map(|&a| input_shape[a]).collect();
        let mut axes: Vec<(usize, usize)> = vec![];
        for &a in &self.perm {
            let (len, stride) = (input_shape[a], strides[a]);
            if len == 1 {
                continue;
            }
            match axes.last_mut() {
                Some(last) if last.1 == len * stride => *last = (last.0 * len, stride),
                _ => axes.push((len, stride)),
            }
        }
        if axes.is_empty() {
            axes.push((1, 1));
        }
        (out_shape, axes)
    }
}

impl Op for Permute {
    fn name(&self) -> StaticName {
        "Permute".into()
    }

    fn info(&self) -> TractResult<Vec<String>> {
        Ok(vec![format!("axes {:?}", self.perm)])
    }

    op_as_typed_op!();
}

impl EvalOp for Permute {
    op_out_of_plan!();

    fn eval(&self, _ctx: &EvalContext, inputs: TVec<TValue>) -> TractResult<TVec<TValue>> {
        let input = args_1!(inputs);
        let (out_shape, axes) = self.plan(input.shape());
        let xs = input.try_as_plain_ram()?;
        let xs = xs.as_slice::<f32>()?;
        let &(run, last_stride) = axes.last().expect("at least one axis");
        let outer = &axes[..axes.len() - 1];
        // Whole rows per share of the work.
        let rows = (SHARE / run).max(1);
        // SAFETY: the shares cover the output, and each share's rows are written whole.
        let out = unsafe {
            output_tensor_written(&out_shape, |ys| {
                par_chunks(ys, rows * run, |share, ys| {
                    // The share's first row as an index on the outer axes (the last fastest).
                    let mut index = vec![0usize; outer.len()];
                    let mut r = share * rows;
                    for (i, &(len, _)) in outer.iter().enumerate().rev() {
                        index[i] = r % len;
                        r /= len;
                    }
                    let mut at: usize = index.iter().zip(outer).map(|(&i, &(_, s))| i * s).sum();
                    for y in ys.chunks_mut(run) {
                        copy_run(y, &xs[at..], last_stride);
                        // The next row: the odometer on the outer axes.
                        for (i, &(len, stride)) in outer.iter().enumerate().rev() {
                            index[i] += 1;
                            at += stride;
                            if index[i] < len {
                                break;
                            }
                            index[i] = 0;
                            at -= len * stride;
                        }
                    }
                });
                Ok(())
            })?
        };
        Ok(tvec!(out.into_tvalue()))
    }
}

/// `ys[i] = xs[i · stride]`; contiguous rows (stride 1) by blocks of 16, which the compiler
/// copies as vectors (a `memcpy` call per row of 16 cost more than the copy).
#[inline]
fn copy_run(ys: &mut [f32], xs: &[f32], stride: usize) {
    if stride == 1 {
        let xs = &xs[..ys.len()];
        let mut blocks = ys.chunks_exact_mut(16);
        let mut from = xs.chunks_exact(16);
        for (y, x) in (&mut blocks).zip(&mut from) {
            let x: &[f32; 16] = x.try_into().expect("a block of 16");
            let y: &mut [f32; 16] = y.try_into().expect("a block of 16");
            *y = *x;
        }
        for (y, x) in blocks.into_remainder().iter_mut().zip(from.remainder()) {
            *y = *x;
        }
    } else {
        for (i, y) in ys.iter_mut().enumerate() {
            *y = xs[i * stride];
        }
    }
}

impl TypedOp for Permute {
    fn output_facts(&self, inputs: &[&TypedFact]) -> TractResult<TVec<TypedFact>> {
        let shape = &inputs[0].shape;
        Ok(tvec!(f32::fact(self.perm.iter().map(|&a| shape[a].clone()).collect::<TVec<_>>())))
    }

    as_op!();
}

/// A [`Permute`] for `node` and the axis moves after it, when `node` is one of tract's axis
/// moves on an f32 tensor of known shape whose sole consumer is another: the op and the nodes
/// it stands for, the last of which it replaces. A lone move stays tract's.
pub(crate) fn permute(model: &TypedModel, node: &TypedNode) -> TractResult<Option<(Permute, Vec<usize>)>> {
    let as_move = |n: &TypedNode| match n.op_as::<AxisOp>() {
        Some(&AxisOp::Move(from, to)) => Some((from, to)),
        _ => None,
    };
    let Some(first) = as_move(node) else { return Ok(None) };
    let fact = model.outlet_fact(node.inputs[0])?;
    let Some(shape) = fact.shape.as_concrete() else { return Ok(None) };
    if fact.datum_type != f32::datum_type() {
        return Ok(None);
    }
    let mut perm: TVec<usize> = (0..shape.len()).collect();
    let mut apply = |(from, to): (usize, usize)| {
        let axis = perm.remove(from);
        perm.insert(to, axis);
    };
    apply(first);
    let (mut chain, mut last) = (vec![node.id], node);
    while let Some(next) = sole_consumer(model, last) {
        let Some(m) = as_move(next) else { break };
        apply(m);
        chain.push(next.id);
        last = next;
    }
    Ok((chain.len() > 1).then_some((Permute { perm }, chain)))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `moves` after a source of `shape`, run by tract and after
    /// [`accelerate`](super::super::accelerate): the same values, and `made` ops made.
    fn check(shape: &[usize], moves: &[(usize, usize)], made: usize) {
        let mut model = TypedModel::default();
        let mut y = model.add_source("x", f32::fact(shape)).unwrap();
        for (i, &(from, to)) in moves.iter().enumerate() {
            y = model.wire_node(format!("move{i}"), AxisOp::Move(from, to), &[y]).unwrap()[0];
        }
        model.select_output_outlets(&[y]).unwrap();
        let len: usize = shape.iter().product();
        let input = Tensor::from_shape(shape, &(0..len).map(|i| i as f32).collect::<Vec<_>>()).unwrap();
        let want = model.clone().into_runnable().unwrap().run(tvec![input.clone().into_tvalue()]).unwrap();
        let done = super::super::accelerate(&mut model).unwrap();
        let got = model.nodes().iter().filter(|n| n.op_is::<Permute>()).count();
        assert_eq!((got, done.permutes), (made, made), "{shape:?} {moves:?}");
        let got = model.into_runnable().unwrap().run(tvec![input.into_tvalue()]).unwrap();
        assert_eq!(got[0].shape(), want[0].shape());
        let (got, want) = (got[0].try_as_plain_ram().unwrap(), want[0].try_as_plain_ram().unwrap());
        assert_eq!(got.as_slice::<f32>().unwrap(), want.as_slice::<f32>().unwrap(), "{shape:?} {moves:?}");
    }

    #[test]
    fn a_chain_of_moves_copies_as_tract_s_moves_do() {
        // HMG's heads (tokens, pieces, heads, q/k/v, width): transposes [1,0,2,3,4],
        // [0,3,1,2,4], [0,1,3,2,4]; with enough tokens to be split over the threads.
        check(&[441, 3, 12, 3, 16], &[(1, 0), (3, 1), (2, 3)], 1);
        check(&[7, 3, 12, 3, 16], &[(1, 0), (3, 1), (2, 3)], 1);
        // The last axis moves (values gathered one by one), axes of length 1, odd lengths.
        check(&[5, 1, 7, 9], &[(3, 0), (1, 3)], 1);
        check(&[3, 700, 19], &[(2, 0), (0, 1), (2, 1)], 1);
        // Moves that undo each other: a plain copy.
        check(&[4, 6, 8], &[(0, 2), (2, 0)], 1);
        // A lone move stays tract's.
        check(&[4, 6, 8], &[(0, 2)], 0);
    }
}
