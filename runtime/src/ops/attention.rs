//! HMG's hierarchical cross-attention, per head: `scores = q·[k_a, k_b]ᵀ` and `mix =
//! softmax(scores)·[v_a, v_b]` ([`AttnScores`], [`AttnMix`]), and the softmax over the last axis
//! ([`RowSoftmax`]).
//!
//! The products are small (121 tokens, parts of 16, two key sets): tract runs each einsum as a
//! packed matrix product at 1-5 GFLOP/s, and its softmax takes a slower path for rows of 242
//! (not a multiple of 4). Here each head is a few vectorised loops, heads spread over the
//! thread pool. Matched on the einsum expressions the builder's attention makes.

use crate::isa::F32Kernel;
use tract_nnef::internal::*;
use tract_nnef::tract_core::ops::einsum::EinSum;
use tract_nnef::tract_core::ops::nn::{Softmax, SoftmaxKind};

use super::softmax::softmax_row;
use super::{output_tensor_written, par_chunks};

/// `scores[a,m,b,n] = Σ_k q[0,a,m,k]·keys[b,a,n,k]` (`camk,bank->ambn`).
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct AttnScores;

/// `out[m,a,n] = Σ_{b,k} p[a,m,b,k]·values[b,a,k,n]` (`ambk,bakn->man`).
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct AttnMix;

/// Softmax of f32 over the last axis, `exp` by a degree-6 polynomial (relative error ~1e-7).
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct RowSoftmax;

fn slice(v: &TValue) -> TractResult<&[f32]> {
    v.try_as_plain_ram()?.as_slice::<f32>()
}

impl Op for AttnScores {
    fn name(&self) -> StaticName {
        "AttnScores".into()
    }
    op_as_typed_op!();
}

impl EvalOp for AttnScores {
    op_out_of_plan!();

    fn eval(&self, _ctx: &EvalContext, inputs: TVec<TValue>) -> TractResult<TVec<TValue>> {
        let (q, keys) = args_2!(inputs);
        let (&[1, heads, m, p], &[b, kh, n, kp]) = (q.shape(), keys.shape()) else {
            bail!("AttnScores: q {:?}, keys {:?}", q.shape(), keys.shape())
        };
        ensure!(kh == heads && kp == p, "AttnScores: q {:?}, keys {:?}", q.shape(), keys.shape());
        let (qs, ks) = (slice(&q)?, slice(&keys)?);
        let (row, view) = (b * n, View::contiguous(0..b, [heads, n, p]));
        // Key rows padded to whole vectors of 16.
        let ldk = row.next_multiple_of(NR);
        // SAFETY: the chunks of `m·row` cover the output, and `gemm` writes every value of
        // its chunk (`m` rows of `row`).
        let out = unsafe {
            output_tensor_written(&[heads, m, b, n], |out: &mut [f32]| {
                par_chunks(out, m * row, |a, out| {
                    let kt = keys_transposed(ks, &view, [n, p], a, ldk);
                    gemm(out, row, &qs[a * m * p..(a + 1) * m * p], p, &kt, ldk);
                });
                Ok(())
            })?
        };
        Ok(tvec!(out.into_tvalue()))
    }
}

impl Op for AttnMix {
    fn name(&self) -> StaticName {
        "AttnMix".into()
    }
    op_as_typed_op!();
}

impl EvalOp for AttnMix {
    op_out_of_plan!();

    fn eval(&self, _ctx: &EvalContext, inputs: TVec<TValue>) -> TractResult<TVec<TValue>> {
        let (probs, values) = args_2!(inputs);
        let (&[heads, m, b, k], &[vb, vh, vk, n]) = (probs.shape(), values.shape()) else {
            bail!("AttnMix: probs {:?}, values {:?}", probs.shape(), values.shape())
        };
        ensure!((vb, vh, vk) == (b, heads, k), "AttnMix: probs {:?}, values {:?}", probs.shape(), values.shape());
        let (ps, vs) = (slice(&probs)?, slice(&values)?);
        let view = View::contiguous(0..b, [heads, k, n]);
        // Per head [m][n], then laid out [m][a][n].
        let mut per_head = vec![0f32; heads * m * n];
        par_chunks(&mut per_head, m * n, |a, out| {
            let (rows, ld) = (b * k, n.next_multiple_of(NR));
            let va = values_rows(vs, &view, [k, n], a, ld);
            gemm(out, n, &ps[a * m * rows..(a + 1) * m * rows], rows, &va, ld);
        });
        // SAFETY: the loops copy a value to every position `(mi·heads + a)·n + j`.
        let out = unsafe {
            output_tensor_written(&[m, heads, n], |out: &mut [f32]| {
                for a in 0..heads {
                    for mi in 0..m {
                        out[(mi * heads + a) * n..(mi * heads + a + 1) * n]
                            .copy_from_slice(&per_head[(a * m + mi) * n..(a * m + mi + 1) * n]);
                    }
                }
                Ok(())
            })?
        };
        Ok(tvec!(out.into_tvalue()))
    }
}

/// Where an operand of an attention is in its input: row `t` of head `a` of piece `i` (its
/// values consecutive) from `pieces[i] + a·head + t·token`. A contiguous `[_, heads, tokens,
/// width]` tensor is one ([`View::contiguous`]); so is the `qkv` product before HMG's transposes.
#[derive(Debug, Clone, PartialEq, Eq, Hash)]
pub struct View {
    /// Where each piece starts.
    pub pieces: TVec<usize>,
    /// From one head to the next.
    pub head: usize,
    /// From one row (token) to the next.
    pub token: usize,
}

impl View {
    /// Slices `pieces` of the first axis of a contiguous `[_, heads, tokens, width]` tensor.
    pub fn contiguous(pieces: impl IntoIterator<Item = usize>, [heads, tokens, width]: [usize; 3]) -> View {
        let piece = heads * tokens * width;
        View { pieces: pieces.into_iter().map(|i| i * piece).collect(), head: tokens * width, token: width }
    }

    /// One past the last value read for `heads` heads of `tokens` rows of `width`; `None` on
    /// overflow.
    pub fn extent(&self, [heads, tokens, width]: [usize; 3]) -> Option<usize> {
        let last = self
            .head
            .checked_mul(heads.checked_sub(1)?)?
            .checked_add(self.token.checked_mul(tokens.checked_sub(1)?)?)?;
        self.pieces.iter().map(|&p| p.checked_add(last)?.checked_add(width)).try_fold(0, |m, e| Some(m.max(e?)))
    }

    /// Where row `t` of head `a` of piece `i` starts.
    pub fn row(&self, i: usize, a: usize, t: usize) -> usize {
        self.pieces[i] + a * self.head + t * self.token
    }
}

/// Head `a`'s keys transposed: `p` rows of `ldk >= b·n` values, `[k][(b, n)]` then zeros, so
/// that the scores are `q · kt`; key set `bi` is piece `bi` of `view` (`n` rows of `p`).
pub(super) fn keys_transposed(keys: &[f32], view: &View, [n, p]: [usize; 2], a: usize, ldk: usize) -> Vec<f32> {
    let mut kt = vec![0f32; p * ldk];
    for bi in 0..view.pieces.len() {
        for j in 0..n {
            let row = &keys[view.row(bi, a, j)..][..p];
            for (k, &v) in row.iter().enumerate() {
                kt[k * ldk + bi * n + j] = v;
            }
        }
    }
    kt
}

/// Head `a`'s values as one `[(b, k)]` by `n` matrix, rows of `ld >= n` (zeros past `n`); value
/// set `bi` is piece `bi` of `view` (`k` rows of `n`).
pub(super) fn values_rows(values: &[f32], view: &View, [k, n]: [usize; 2], a: usize, ld: usize) -> Vec<f32> {
    let mut va = Vec::with_capacity(view.pieces.len() * k * ld);
    for bi in 0..view.pieces.len() {
        for t in 0..k {
            va.extend_from_slice(&values[view.row(bi, a, t)..][..n]);
            va.resize(va.len() + ld - n, 0.0);
        }
    }
    va
}

/// Rows of `dst` computed together (accumulators: 6 x 16 lanes).
pub(super) const MR: usize = 6;
/// Columns of `dst` computed together.
pub(super) const NR: usize = 16;

/// `dst[i][j] = Σ_k a[i][k]·b[k][j]` for `j < n`: `a` is rows of `kl`, `b` is `kl` rows of
/// `ldb` (a multiple of [`NR`], at least `n`, zero past `n`), `dst` rows of `n`. Sums in order
/// of `k`.
pub(super) fn gemm(dst: &mut [f32], n: usize, a: &[f32], kl: usize, b: &[f32], ldb: usize) {
    match crate::isa::f32_kernel() {
        // SAFETY: the CPU has the features the function is compiled for (the table's needs).
        #[cfg(target_arch = "x86_64")]
        F32Kernel::Avx512 => unsafe { gemm_avx512(dst, n, a, kl, b, ldb) },
        // SAFETY: as above.
        #[cfg(target_arch = "x86_64")]
        F32Kernel::Avx2Fma => unsafe { gemm_fma(dst, n, a, kl, b, ldb) },
        // SAFETY: NEON is part of the aarch64 baseline (and the probe found it).
        #[cfg(target_arch = "aarch64")]
        F32Kernel::Neon => unsafe { gemm_neon(dst, n, a, kl, b, ldb) },
        _ => gemm_generic::<false>(dst, n, a, kl, b, ldb),
    }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx2,fma")]
unsafe fn gemm_avx512(dst: &mut [f32], n: usize, a: &[f32], kl: usize, b: &[f32], ldb: usize) {
    gemm_generic::<true>(dst, n, a, kl, b, ldb)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn gemm_fma(dst: &mut [f32], n: usize, a: &[f32], kl: usize, b: &[f32], ldb: usize) {
    gemm_generic::<true>(dst, n, a, kl, b, ldb)
}

/// NEON: the 6 x 16 tile in registers (24 accumulators, four vectors of `b` and each value of
/// `a` taken by element: `FMLA v.4s, v.4s, v.s[0]`), fused, in the order of
/// [`gemm_generic`]: the same bits. The portable tile compiled for NEON kept only part of its
/// accumulators in registers and stored the rest to the stack on every `k` (modelled on a
/// Cortex-A78 class core: 1.9 multiply-adds a cycle of 8).
#[cfg(target_arch = "aarch64")]
#[target_feature(enable = "neon")]
unsafe fn gemm_neon(dst: &mut [f32], n: usize, a: &[f32], kl: usize, b: &[f32], ldb: usize) {
    use std::arch::aarch64::*;
    let m = a.len() / kl;
    assert!(b.len() >= kl * ldb && n <= ldb && ldb.is_multiple_of(NR), "b holds kl rows of whole vectors");
    assert!(dst.len() >= m * n && a.len() == m * kl);
    for i in (0..m).step_by(MR) {
        let mr = MR.min(m - i);
        // Rows past the last are computed again from the last (and not stored).
        let rows: [&[f32]; MR] = std::array::from_fn(|r| &a[(i + r.min(mr - 1)) * kl..][..kl]);
        for j0 in (0..n).step_by(NR) {
            let mut acc = [[vdupq_n_f32(0.0); NR / 4]; MR];
            for k in 0..kl {
                // SAFETY: row k of `b` holds `ldb >= j0 + 16` values (asserted); `k < kl`, the
                // length of every row of `a`.
                unsafe {
                    let bk = b.as_ptr().add(k * ldb + j0);
                    let bv: [float32x4_t; NR / 4] = std::array::from_fn(|q| vld1q_f32(bk.add(4 * q)));
                    for (acc, row) in acc.iter_mut().zip(&rows) {
                        let c = *row.get_unchecked(k);
                        for (x, &y) in acc.iter_mut().zip(&bv) {
                            *x = vfmaq_n_f32(*x, y, c);
                        }
                    }
                }
            }
            let w = NR.min(n - j0);
            for (r, acc) in acc.iter().enumerate().take(mr) {
                let mut lanes = [0f32; NR];
                for (q, v) in acc.iter().enumerate() {
                    // SAFETY: four floats into a local array of 16.
                    unsafe { vst1q_f32(lanes.as_mut_ptr().add(4 * q), *v) };
                }
                dst[(i + r) * n + j0..][..w].copy_from_slice(&lanes[..w]);
            }
        }
    }
}

#[inline(always)]
fn gemm_generic<const FUSED: bool>(dst: &mut [f32], n: usize, a: &[f32], kl: usize, b: &[f32], ldb: usize) {
    let m = a.len() / kl;
    for i in (0..m).step_by(MR) {
        let mr = MR.min(m - i);
        // Rows past the last are computed again from the last (and not stored).
        let rows: [&[f32]; MR] = std::array::from_fn(|r| &a[(i + r.min(mr - 1)) * kl..][..kl]);
        assert!(b.len() >= kl * ldb && n <= ldb && ldb.is_multiple_of(NR), "b holds kl rows of whole vectors");
        for j0 in (0..n).step_by(NR) {
            let mut acc = [[0f32; NR]; MR];
            for k in 0..kl {
                // SAFETY: row k of `b` holds `ldb >= j0 + 16` values (asserted); `k < kl`, the
                // length of every row of `a`. (With bounds checks in this loop the compiler kept
                // the accumulators in memory, storing all of them on every `k`.)
                let (brow, cs): (&[f32; NR], [f32; MR]) = unsafe {
                    (
                        &*b.as_ptr().add(k * ldb + j0).cast::<[f32; NR]>(),
                        std::array::from_fn(|r| *rows[r].get_unchecked(k)),
                    )
                };
                for (acc, c) in acc.iter_mut().zip(cs) {
                    for (x, &y) in acc.iter_mut().zip(brow) {
                        *x = if FUSED { c.mul_add(y, *x) } else { c * y + *x };
                    }
                }
            }
            let w = NR.min(n - j0);
            for (r, acc) in acc.iter().enumerate().take(mr) {
                dst[(i + r) * n + j0..][..w].copy_from_slice(&acc[..w]);
            }
        }
    }
}

impl Op for RowSoftmax {
    fn name(&self) -> StaticName {
        "RowSoftmax".into()
    }
    op_as_typed_op!();
}

impl EvalOp for RowSoftmax {
    op_out_of_plan!();

    fn eval(&self, _ctx: &EvalContext, inputs: TVec<TValue>) -> TractResult<TVec<TValue>> {
        let input = args_1!(inputs);
        let row = *input.shape().last().context("RowSoftmax: scalar input")?;
        let mut out = input.into_tensor();
        {
            let mut plain = out.try_as_plain_ram_mut()?;
            let data = plain.as_slice_mut::<f32>()?;
            let rows_per_task = (data.len() / row).div_ceil(8).max(1);
            par_chunks(data, rows_per_task * row, |_, chunk| {
                for r in chunk.chunks_exact_mut(row) {
                    softmax_row(r, None);
                }
            });
        }
        Ok(tvec!(out.into_tvalue()))
    }
}

macro_rules! same_shape_typed_op {
    ($op:ty, $facts:expr) => {
        impl TypedOp for $op {
            fn output_facts(&self, inputs: &[&TypedFact]) -> TractResult<TVec<TypedFact>> {
                #[allow(clippy::redundant_closure_call)]
                Ok(tvec!(($facts)(inputs)?))
            }
            as_op!();
        }
    };
}

same_shape_typed_op!(AttnScores, |i: &[&TypedFact]| -> TractResult<TypedFact> {
    let (q, k) = (&i[0].shape, &i[1].shape);
    Ok(f32::fact([q[1].clone(), q[2].clone(), k[0].clone(), k[2].clone()]))
});
same_shape_typed_op!(AttnMix, |i: &[&TypedFact]| -> TractResult<TypedFact> {
    let (p, v) = (&i[0].shape, &i[1].shape);
    Ok(f32::fact([p[1].clone(), p[0].clone(), v[3].clone()]))
});
same_shape_typed_op!(RowSoftmax, |i: &[&TypedFact]| -> TractResult<TypedFact> { Ok(i[0].without_value()) });

/// Which attention operator replaces `node`, if any: the two einsums of the builder's
/// attention (f32, no quantisation, concrete shapes) and f32 softmax over the last axis.
pub(crate) fn attention_op(model: &TypedModel, node: &TypedNode) -> TractResult<Option<Box<dyn TypedOp>>> {
    let facts = model.node_input_facts(node.id)?;
    let f32_inputs = facts.iter().all(|f| f.datum_type == f32::datum_type() && f.shape.is_concrete());
    if let Some(e) = node.op_as::<EinSum>() {
        if e.q_params.is_some() || e.operating_dt != f32::datum_type() || facts.len() != 2 || !f32_inputs {
            return Ok(None);
        }
        return Ok(match e.axes.to_string().as_str() {
            "camk,bank->ambn" if facts[0].shape[0].to_usize()? == 1 => Some(Box::new(AttnScores)),
            "ambk,bakn->man" => Some(Box::new(AttnMix)),
            _ => None,
        });
    }
    if let Some(s) = node.op_as::<Softmax>() {
        let last = facts[0].rank().checked_sub(1);
        let plain = s.kind == SoftmaxKind::Softmax && s.quant_output_dt.is_none() && f32_inputs;
        return Ok((plain && s.axes.as_slice() == last.as_slice()).then(|| Box::new(RowSoftmax) as Box<dyn TypedOp>));
    }
    Ok(None)
}

#[cfg(test)]
pub(super) mod tests {
    use super::*;

    /// `op`'s first output on `inputs` (also the fused attention's and the softmax's tests').
    pub(in crate::ops) fn run(op: &dyn EvalOp, inputs: Vec<Tensor>) -> Tensor {
        let inputs = inputs.into_iter().map(|t| t.into_tvalue()).collect();
        op.eval(&EvalContext::out_of_plan(), inputs).unwrap().remove(0).into_tensor()
    }

    /// `n` values in [-2, 2), a spread that depends on `seed`.
    pub(in crate::ops) fn values(n: usize, seed: usize) -> Vec<f32> {
        (0..n).map(|i| (((i + seed) * 7919 % 1000) as f32) / 250.0 - 2.0).collect()
    }

    fn close(a: &[f32], b: &[f32]) {
        assert_eq!(a.len(), b.len());
        for (x, y) in a.iter().zip(b) {
            assert!((x - y).abs() <= 1e-5 * y.abs().max(1.0), "{x} vs {y}");
        }
    }

    #[test]
    fn scores_mix_and_softmax_equal_their_definitions() {
        let (heads, m, b, n, p) = (3, 5, 2, 7, 16);
        let q = values(heads * m * p, 1);
        let k = values(b * heads * n * p, 2);
        let scores = run(
            &AttnScores,
            vec![
                Tensor::from_shape(&[1, heads, m, p], &q).unwrap(),
                Tensor::from_shape(&[b, heads, n, p], &k).unwrap(),
            ],
        );
        let mut want = vec![];
        for a in 0..heads {
            for mi in 0..m {
                for bi in 0..b {
                    for j in 0..n {
                        want.push(
                            (0..p)
                                .map(|x| q[(a * m + mi) * p + x] * k[((bi * heads + a) * n + j) * p + x])
                                .sum::<f32>(),
                        );
                    }
                }
            }
        }
        assert_eq!(scores.shape(), &[heads, m, b, n]);
        close(scores.try_as_plain_ram().unwrap().as_slice::<f32>().unwrap(), &want);

        let probs = run(&RowSoftmax, vec![Tensor::from_shape(&[heads, m, b * n], &want).unwrap()]);
        let probs = probs.try_as_plain_ram().unwrap().as_slice::<f32>().unwrap().to_vec();
        for (row, got) in want.chunks(b * n).zip(probs.chunks(b * n)) {
            let max = row.iter().fold(f32::NEG_INFINITY, |a, &v| a.max(v));
            let sum: f64 = row.iter().map(|&v| ((v - max) as f64).exp()).sum();
            let exact: Vec<f32> = row.iter().map(|&v| (((v - max) as f64).exp() / sum) as f32).collect();
            close(got, &exact);
        }

        let v = values(b * heads * n * p, 3);
        let mix = run(
            &AttnMix,
            vec![
                Tensor::from_shape(&[heads, m, b, n], &probs).unwrap(),
                Tensor::from_shape(&[b, heads, n, p], &v).unwrap(),
            ],
        );
        let mut want = vec![0f32; m * heads * p];
        for mi in 0..m {
            for a in 0..heads {
                for x in 0..p {
                    want[(mi * heads + a) * p + x] = (0..b)
                        .flat_map(|bi| (0..n).map(move |j| (bi, j)))
                        .map(|(bi, j)| probs[((a * m + mi) * b + bi) * n + j] * v[((bi * heads + a) * n + j) * p + x])
                        .sum();
                }
            }
        }
        assert_eq!(mix.shape(), &[m, heads, p]);
        close(mix.try_as_plain_ram().unwrap().as_slice::<f32>().unwrap(), &want);
    }

    /// The dispatched product (the SIMD path the machine runs) gives the portable tile's bits.
    #[test]
    fn gemm_paths_equal_the_portable_tile() {
        let fused = crate::isa::f32_kernel() != F32Kernel::Portable;
        for (m, n, kl) in [(1usize, 1usize, 1usize), (6, 16, 8), (7, 17, 33), (121, 121, 64), (13, 40, 5)] {
            let ldb = n.div_ceil(NR) * NR;
            let a = values(m * kl, 4);
            let mut b = values(kl * ldb, 5);
            for (k, v) in b.iter_mut().enumerate() {
                if k % ldb >= n {
                    *v = 0.0;
                }
            }
            let (mut got, mut want) = (vec![f32::NAN; m * n], vec![f32::NAN; m * n]);
            gemm(&mut got, n, &a, kl, &b, ldb);
            match fused {
                true => gemm_generic::<true>(&mut want, n, &a, kl, &b, ldb),
                false => gemm_generic::<false>(&mut want, n, &a, kl, &b, ldb),
            }
            assert!(got.iter().zip(&want).all(|(x, y)| x.to_bits() == y.to_bits()), "{m}x{n}x{kl}");
        }
    }
}
