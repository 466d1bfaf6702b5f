//! Pointwise (1x1) convolutions on channels-first data ([`PointwiseConv`]), with their bias and
//! the activation after them fused: the einsum `mk,kn->mn` that tract declutters a 1x1 `Conv`
//! into (the weights constant, the positions `n` contiguous in the data and in the output),
//! followed by the bias `Add`, a clamp (`Max` and/or `Min` with a constant: ReLU, ReLU6) and
//! tract's `HardSwish`, reshapes between them allowed.
//!
//! tract packs the data of every such product before multiplying (NanoTrack's 24 pointwise
//! convolutions: 0.3 ms of packing in a 3.3 ms search step) and picks, for the short reductions
//! of a MobileNet (k = 16..96), kernels that ran at 35-50 GFLOP/s here. Here the data is read
//! where it lies: each `k` row of 64 positions is four vectors, multiplied by 6 output channels'
//! weights (packed `[m / 6][k][6]` at load), 24 accumulators; the bias and the activation are
//! applied before the tile is stored. The sums run in order of k. PRL-Track's gating
//! convolutions (96 or 192 channels to one, in SR1, SR2 and AR) are such products too: tract
//! packed their data for 0.3 ms of a step, for 0.1 ms of multiplying.

use std::sync::Arc;

use tract_nnef::internal::*;

use super::act::{tail, Activation, Tail};
use super::matmul::{const_product, ConstProduct};
use super::{output_tensor_written, par_for, same_bits, SyncPtr, SERIAL_MACS};

/// Output channels per packed panel (rows of the register tile).
const MR: usize = 6;
/// Positions per register tile (four 16-lane vectors).
const NB: usize = 64;

/// `out(m, n) = act(bias(m) + Σ_k w(m, k) · x(k, n))` on `x` laid out `[k][n]` and `out`
/// `[m][n]` (a 1x1 convolution of one image, channels first).
#[derive(Debug, Clone)]
pub struct PointwiseConv {
    /// `[m / MR][k][MR]`, zero past `m`.
    panels: Arc<Vec<f32>>,
    /// `m` values (zero where the graph has no bias).
    bias: Arc<Vec<f32>>,
    act: Activation,
    m: usize,
    k: usize,
    n: usize,
    output_shape: TVec<usize>,
}

impl PartialEq for PointwiseConv {
    fn eq(&self, other: &Self) -> bool {
        (self.m, self.k, self.n, self.act) == (other.m, other.k, other.n, other.act)
            && self.output_shape == other.output_shape
            && same_bits(&self.panels, &other.panels)
            && same_bits(&self.bias, &other.bias)
    }
}

impl Eq for PointwiseConv {}

impl Op for PointwiseConv {
    fn name(&self) -> StaticName {
        "PointwiseConv".into()
    }

    fn info(&self) -> TractResult<Vec<String>> {
        let act = self.act.describe();
        Ok(vec![format!("m {}, n {}, k {}, activation {act}", self.m, self.n, self.k)])
    }

    op_as_typed_op!();
}

impl EvalOp for PointwiseConv {
    op_out_of_plan!();

    fn eval(&self, _ctx: &EvalContext, inputs: TVec<TValue>) -> TractResult<TVec<TValue>> {
        let x = args_1!(inputs);
        let x = x.try_as_plain_ram()?;
        let x = x.as_slice::<f32>()?;
        ensure!(x.len() == self.k * self.n, "PointwiseConv: {} inputs for k {} x n {}", x.len(), self.k, self.n);
        ensure!(self.output_shape.iter().product::<usize>() == self.m * self.n, "PointwiseConv: output shape");
        let fill = |out: &mut [f32]| {
            let dst = SyncPtr(out.as_mut_ptr());
            let blocks = self.n.div_ceil(NB);
            // SAFETY (both closures): blocks write disjoint columns of the m x n output.
            let run = |b: usize| unsafe { self.block(x, b * NB, &dst) };
            if self.m * self.n * self.k < SERIAL_MACS {
                (0..blocks).for_each(run);
            } else {
                par_for(blocks, run);
            }
            Ok(())
        };
        // SAFETY: the blocks cover the n columns of all m rows: every element is written.
        let out = unsafe { output_tensor_written(&self.output_shape, fill)? };
        Ok(tvec!(out.into_tvalue()))
    }
}

impl TypedOp for PointwiseConv {
    fn output_facts(&self, _inputs: &[&TypedFact]) -> TractResult<TVec<TypedFact>> {
        Ok(tvec!(f32::fact(&self.output_shape)))
    }

    fn cost(&self, _inputs: &[&TypedFact]) -> TractResult<TVec<(Cost, TDim)>> {
        Ok(tvec!((Cost::FMA(f32::datum_type()), (self.m * self.n * self.k).into())))
    }

    as_op!();
}

impl PointwiseConv {
    /// Every output channel at the columns `j0..j0 + NB` (fewer at the end).
    ///
    /// # Safety
    /// `out` points at the `m x n` output, whose columns `j0..j0 + NB` no other thread writes
    /// meanwhile.
    unsafe fn block(&self, x: &[f32], j0: usize, out: &SyncPtr<f32>) {
        let (k, n) = (self.k, self.n);
        let cols = NB.min(n - j0);
        // A short last block runs on a copy padded to NB columns, into a tile of its own.
        let padded: Vec<f32>;
        let (xs, ldx) = if cols == NB {
            (&x[j0..], n)
        } else {
            let mut p = Vec::with_capacity(k * NB);
            for i in 0..k {
                p.extend_from_slice(&x[i * n + j0..][..cols]);
                p.resize((i + 1) * NB, 0.0);
            }
            padded = p;
            (&padded[..], NB)
        };
        for p in 0..self.m.div_ceil(MR) {
            let panel = &self.panels[p * k * MR..(p + 1) * k * MR];
            let rows = MR.min(self.m - p * MR);
            let bias: [f32; MR] = std::array::from_fn(|r| if r < rows { self.bias[p * MR + r] } else { 0.0 });
            // SAFETY: row `p·MR + r < m` of the output, columns `j0..j0 + cols <= n`, in this
            // block's columns (the caller's promise).
            let at = unsafe { out.at(p * MR * n + j0) };
            if cols == NB {
                // SAFETY: as above, `rows` rows of NB values n apart.
                unsafe { tile(panel, xs, ldx, bias, self.act, at, n, rows) };
            } else {
                let mut t = [[0f32; NB]; MR];
                // SAFETY: the local tile holds MR rows of NB.
                unsafe { tile(panel, xs, ldx, bias, self.act, t.as_mut_ptr().cast(), NB, MR) };
                for (r, row) in t.iter().enumerate().take(rows) {
                    // SAFETY: as above.
                    unsafe { std::ptr::copy_nonoverlapping(row.as_ptr(), at.add(r * n), cols) };
                }
            }
        }
    }
}

/// One register tile: `act(bias(r) + Σ_i panel[i][r] · x[i·ldx + j])` for the panel's `MR`
/// rows and `NB` columns `j` (`x` holds `k` rows of at least `NB` values, `ldx` apart), rows
/// `r < rows` written at `out + r·ldo`.
///
/// # Safety
/// `out` is valid for writes of `rows <= MR` rows of `NB` values, `ldo` apart, that no one
/// else accesses meanwhile.
#[allow(clippy::too_many_arguments)]
unsafe fn tile(
    panel: &[f32],
    x: &[f32],
    ldx: usize,
    bias: [f32; MR],
    act: Activation,
    out: *mut f32,
    ldo: usize,
    rows: usize,
) {
    let k = panel.len() / MR;
    assert!(k == 0 || x.len() >= (k - 1) * ldx + NB, "k rows of NB values");
    assert!(rows <= MR);
    use crate::isa::F32Kernel;
    // SAFETY: the CPU has the features each function is compiled for (the table's needs;
    // AVX-512 implies AVX2 + FMA); `out` as the caller promises.
    unsafe {
        match crate::isa::f32_kernel() {
            #[cfg(target_arch = "x86_64")]
            F32Kernel::Avx512 => tile_avx512(panel, x, ldx, bias, act, out, ldo, rows),
            #[cfg(target_arch = "x86_64")]
            F32Kernel::Avx2Fma => tile_fma(panel, x, ldx, bias, act, out, ldo, rows),
            F32Kernel::Neon => tile_generic::<true>(panel, x, ldx, bias, act, out, ldo, rows),
            _ => tile_generic::<false>(panel, x, ldx, bias, act, out, ldo, rows),
        }
    }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx2,fma")]
#[allow(clippy::too_many_arguments)]
unsafe fn tile_avx512(
    panel: &[f32],
    x: &[f32],
    ldx: usize,
    bias: [f32; MR],
    act: Activation,
    out: *mut f32,
    ldo: usize,
    rows: usize,
) {
    use std::arch::x86_64::*;
    const V: usize = NB / 16;
    let k = panel.len() / MR;
    let mut acc = [[_mm512_setzero_ps(); V]; MR];
    let (w, xp) = (panel.as_ptr(), x.as_ptr());
    for i in 0..k {
        // SAFETY: i < k: the panel holds k rows of MR, x k rows of NB values ldx apart
        // (asserted by `tile`).
        unsafe {
            let xv: [__m512; V] = std::array::from_fn(|v| _mm512_loadu_ps(xp.add(i * ldx + v * 16)));
            for (r, acc) in acc.iter_mut().enumerate() {
                let c = _mm512_set1_ps(*w.add(i * MR + r));
                for (a, &xv) in acc.iter_mut().zip(&xv) {
                    *a = _mm512_fmadd_ps(c, xv, *a);
                }
            }
        }
    }
    for (r, (acc, b)) in acc.into_iter().zip(bias).enumerate().take(rows) {
        let b = _mm512_set1_ps(b);
        for (v, a) in acc.into_iter().enumerate() {
            let y = act.apply_avx512(_mm512_add_ps(a, b));
            // SAFETY: row r < rows, 16 floats at column 16·v < NB (the caller's promise).
            unsafe { _mm512_storeu_ps(out.add(r * ldo + v * 16), y) };
        }
    }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
#[allow(clippy::too_many_arguments)]
unsafe fn tile_fma(
    panel: &[f32],
    x: &[f32],
    ldx: usize,
    bias: [f32; MR],
    act: Activation,
    out: *mut f32,
    ldo: usize,
    rows: usize,
) {
    use std::arch::x86_64::*;
    let k = panel.len() / MR;
    let (w, xp) = (panel.as_ptr(), x.as_ptr());
    // 16-column quarters: MR x 2 accumulators (12 of the 16 registers), the sums in order of k
    // as every path takes them; bias and activation in registers.
    for q in 0..NB / 16 {
        let mut acc = [[_mm256_setzero_ps(); 2]; MR];
        for i in 0..k {
            // SAFETY: i < k: the panel holds k rows of MR, x k rows of NB values ldx apart
            // (asserted by `tile`).
            unsafe {
                let x0 = _mm256_loadu_ps(xp.add(i * ldx + q * 16));
                let x1 = _mm256_loadu_ps(xp.add(i * ldx + q * 16 + 8));
                for (r, acc) in acc.iter_mut().enumerate() {
                    let c = _mm256_set1_ps(*w.add(i * MR + r));
                    acc[0] = _mm256_fmadd_ps(c, x0, acc[0]);
                    acc[1] = _mm256_fmadd_ps(c, x1, acc[1]);
                }
            }
        }
        for (r, (acc, b)) in acc.into_iter().zip(bias).enumerate().take(rows) {
            let b = _mm256_set1_ps(b);
            for (v, a) in acc.into_iter().enumerate() {
                let y = act.apply_avx2(_mm256_add_ps(a, b));
                // SAFETY: row r < rows, 8 floats at column 16·q + 8·v < NB (the caller's promise).
                unsafe { _mm256_storeu_ps(out.add(r * ldo + q * 16 + v * 8), y) };
            }
        }
    }
}

/// [`tile`] in 16-column quarters of `MR x 16` accumulators (24 NEON registers; vectorised by
/// the compiler), with fused multiply-adds when `FUSED`.
///
/// # Safety
/// As [`tile`].
#[inline(always)]
#[allow(clippy::too_many_arguments)]
unsafe fn tile_generic<const FUSED: bool>(
    panel: &[f32],
    x: &[f32],
    ldx: usize,
    bias: [f32; MR],
    act: Activation,
    out: *mut f32,
    ldo: usize,
    rows: usize,
) {
    for q in 0..NB / 16 {
        let mut acc = [[0f32; 16]; MR];
        for (i, w) in panel.chunks_exact(MR).enumerate() {
            let xs: &[f32; 16] = x[i * ldx + q * 16..][..16].try_into().expect("16 values of a row");
            for (acc, &c) in acc.iter_mut().zip(w) {
                for (a, &v) in acc.iter_mut().zip(xs) {
                    *a = if FUSED { c.mul_add(v, *a) } else { c * v + *a };
                }
            }
        }
        for (r, (acc, b)) in acc.into_iter().zip(bias).enumerate().take(rows) {
            for (j, a) in acc.into_iter().enumerate() {
                // SAFETY: row r < rows, column 16·q + j < NB (the caller's promise).
                unsafe { *out.add(r * ldo + q * 16 + j) = act.apply(a + b) };
            }
        }
    }
}

/// A [`PointwiseConv`] for the einsum `node` and what follows it; returns the op, its data
/// input and the nodes it stands for, the last of which it replaces.
pub(crate) fn pointwise(
    model: &TypedModel,
    node: &TypedNode,
) -> TractResult<Option<(PointwiseConv, OutletId, Vec<usize>)>> {
    let Some(ConstProduct { k, m, n, konst, data, .. }) = const_product(model, node)? else {
        return Ok(None);
    };
    // Channels first: positions contiguous in the data and the output, rows of n (a single
    // channel in or out has no row stride: tract lays PRL-Track's one-channel gating products
    // out `[n][1]`, the same values in the same order).
    if n.1[1] != 1 || n.1[2] != 1 || (k.0 > 1 && k.1[1] != n.0) || (m.0 > 1 && m.1[2] != n.0) {
        return Ok(None);
    }
    if model.outlet_fact(data)?.shape.as_concrete().is_none_or(|s| s.iter().product::<usize>() != k.0 * n.0) {
        return Ok(None);
    }
    let Some(Tail { bias, act, chain, shape }) = tail(model, node, Some((m.0, n.0)))? else { return Ok(None) };
    let w = konst.try_as_plain_ram()?;
    let w = w.as_slice::<f32>()?;
    let mut panels = vec![0f32; m.0.div_ceil(MR) * MR * k.0];
    for f in 0..m.0 {
        for i in 0..k.0 {
            panels[((f / MR) * k.0 + i) * MR + f % MR] = w[f * m.1[0] + i * k.1[0]];
        }
    }
    let op = PointwiseConv {
        panels: Arc::new(panels),
        bias: Arc::new(bias.unwrap_or_else(|| vec![0.0; m.0])),
        act,
        m: m.0,
        k: k.0,
        n: n.0,
        output_shape: shape,
    };
    Ok(Some((op, data, chain)))
}

#[cfg(test)]
mod tests;
