//! f32 matrix products with a constant operand ([`ConstMatMul`]): HMG's linear layers (`qkv`,
//! `proj`, `fc1`, `fc2`) and its patch embedding, which tract declutters into two-input einsums
//! such as `akm,kn->mn` or `km,nk->amn` (one side the weights, the layouts mixed).
//!
//! tract ran them at 9-65 GFLOP/s here (its f32 kernel does not block the reduction, and the
//! patch embedding's split token axis took a slow path). Here the weights are packed once, at
//! load, into panels of 32 output features x K; each call copies the activations into rows of K
//! and runs a 6 x 32 register tile (6 x 16 without AVX-512), panels spread over the threads.
//! The sums run in order of k.

use std::sync::Arc;

use tract_nnef::internal::*;
use tract_nnef::tract_core::ops::einsum::EinSum;

use super::par::{par_runs, parts};
use super::SyncPtr;

/// Output features per packed panel.
const PANEL: usize = 32;
/// Activation rows per register tile.
const ROWS: usize = 6;

/// One merged group of axes: its length and its stride in each tensor that holds it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
struct Dim {
    len: usize,
    /// Stride in the activations (`k`, `n`) or the weights (`m`).
    input: usize,
    /// Stride in the output (`m`, `n`); 0 for `k`.
    output: usize,
}

/// `out(m, n) = Σ_k w(m, k) · x(k, n)` with `w` constant (packed) and `x` the one input, each
/// index a merged group of the einsum's axes, addressed by strides.
#[derive(Debug, Clone, PartialEq)]
pub struct ConstMatMul {
    /// `[m / 32][k][32]`, zero past `m`.
    panels: Arc<Vec<f32>>,
    m: Dim,
    n: Dim,
    k: Dim,
    output_shape: TVec<usize>,
}

impl Eq for ConstMatMul {}

impl Op for ConstMatMul {
    fn name(&self) -> StaticName {
        "ConstMatMul".into()
    }

    fn info(&self) -> TractResult<Vec<String>> {
        Ok(vec![format!("m {}, n {}, k {}", self.m.len, self.n.len, self.k.len)])
    }

    op_as_typed_op!();
}

impl EvalOp for ConstMatMul {
    op_out_of_plan!();

    fn eval(&self, _ctx: &EvalContext, inputs: TVec<TValue>) -> TractResult<TVec<TValue>> {
        let x = args_1!(inputs);
        let x = x.try_as_plain_ram()?;
        let x = x.as_slice::<f32>()?;
        let (m, n, k) = (self.m, self.n, self.k);
        // Activations as rows of k, one per n: the input itself where it is laid out so (HMG's
        // `proj`, `fc2`, the `[n][k]` products), else gathered over the threads (copied and
        // then the output zeroed on one thread, the two took 1.3 of a 6.3 ms share of
        // PRL-Track's two-thread step that does not halve).
        ensure!(x.len() > (n.len - 1) * n.input + (k.len - 1) * k.input, "ConstMatMul: {} inputs", x.len());
        let gathered;
        let rows: &[f32] = if k.input == 1 && n.input == k.len {
            &x[..n.len * k.len]
        } else {
            let mut buffer = vec![0f32; n.len * k.len];
            // Blocks of 8 rows: each reads 8 consecutive inputs per k where n is the inner axis.
            super::par_chunks(&mut buffer, 8 * k.len, |b, block| {
                for i in 0..k.len {
                    for (r, row) in block.chunks_exact_mut(k.len).enumerate() {
                        row[i] = x[(8 * b + r) * n.input + i * k.input];
                    }
                }
            });
            gathered = buffer;
            &gathered
        };
        let fill = |out: &mut [f32]| {
            let dst = SyncPtr(out.as_mut_ptr());
            // Each panel whole, or its rows in runs where whole panels would leave threads idle
            // (HMG's 576 features, 18 panels, over eight threads: [`parts`]).
            let (panels, tiles) = (m.len.div_ceil(PANEL), n.len.div_ceil(ROWS));
            par_runs(panels, parts(panels, 1, tiles), tiles, |p, run| {
                let panel = &self.panels[p * k.len * PANEL..(p + 1) * k.len * PANEL];
                let features = PANEL.min(m.len - p * PANEL);
                for j0 in (run.start * ROWS..n.len.min(run.end * ROWS)).step_by(ROWS) {
                    let tile = tile(panel, rows, k.len, j0, ROWS.min(n.len - j0));
                    for (r, acc) in tile.iter().enumerate().take(n.len - j0) {
                        for (f, &v) in acc.iter().enumerate().take(features) {
                            let at = (p * PANEL + f) * m.output + (j0 + r) * n.output;
                            // SAFETY: `at` is within the output; items write disjoint features
                            // (panels) or rows (runs).
                            unsafe { *dst.at(at) = v };
                        }
                    }
                }
            });
            Ok(())
        };
        // SAFETY: every output is written: each of the `m · n` values (the whole output,
        // checked when the op was made) by the panel holding its feature, at its row.
        let out = unsafe { super::output_tensor_written(&self.output_shape, fill)? };
        Ok(tvec!(out.into_tvalue()))
    }
}

impl TypedOp for ConstMatMul {
    fn output_facts(&self, _inputs: &[&TypedFact]) -> TractResult<TVec<TypedFact>> {
        Ok(tvec!(f32::fact(&self.output_shape)))
    }

    fn cost(&self, _inputs: &[&TypedFact]) -> TractResult<TVec<(Cost, TDim)>> {
        Ok(tvec!((Cost::FMA(f32::datum_type()), (self.m.len * self.n.len * self.k.len).into())))
    }

    as_op!();
}

/// Sums of rows `j0..j0 + rows` of `x` (rows of `k`) with a panel (`[k][32]`): `[row][feature]`.
fn tile(panel: &[f32], x: &[f32], k: usize, j0: usize, rows: usize) -> [[f32; PANEL]; ROWS] {
    // Rows past the last are the last again (computed, not stored).
    let xs: [&[f32]; ROWS] = std::array::from_fn(|r| &x[(j0 + r.min(rows - 1)) * k..][..k]);
    #[cfg(target_arch = "x86_64")]
    if crate::isa::f32_kernel() == crate::isa::F32Kernel::Avx512 {
        // SAFETY: the CPU has the features the function is compiled for (the table's needs).
        return unsafe { tile_avx512(panel, xs) };
    }
    let mut out = [[0f32; PANEL]; ROWS];
    for half in 0..PANEL / 16 {
        let acc = tile_half(panel, half, xs);
        for (o, a) in out.iter_mut().zip(acc) {
            o[half * 16..(half + 1) * 16].copy_from_slice(&a);
        }
    }
    out
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx2,fma")]
unsafe fn tile_avx512(panel: &[f32], xs: [&[f32]; ROWS]) -> [[f32; PANEL]; ROWS] {
    use std::arch::x86_64::*;
    let k = panel.len() / PANEL;
    assert!(xs.iter().all(|x| x.len() >= k), "rows of k activations");
    let mut acc = [[_mm512_setzero_ps(); 2]; ROWS];
    let (w, xp): (*const f32, [*const f32; ROWS]) = (panel.as_ptr(), std::array::from_fn(|r| xs[r].as_ptr()));
    for i in 0..k {
        // SAFETY: i < k: the panel holds k rows of 32, every activation row k values (asserted).
        unsafe {
            let w0 = _mm512_loadu_ps(w.add(i * PANEL));
            let w1 = _mm512_loadu_ps(w.add(i * PANEL + 16));
            for (acc, x) in acc.iter_mut().zip(xp) {
                let c = _mm512_set1_ps(*x.add(i));
                acc[0] = _mm512_fmadd_ps(c, w0, acc[0]);
                acc[1] = _mm512_fmadd_ps(c, w1, acc[1]);
            }
        }
    }
    let mut out = [[0f32; PANEL]; ROWS];
    for (o, a) in out.iter_mut().zip(acc) {
        // SAFETY: 32 floats of each output row.
        unsafe {
            _mm512_storeu_ps(o.as_mut_ptr(), a[0]);
            _mm512_storeu_ps(o.as_mut_ptr().add(16), a[1]);
        }
    }
    out
}

/// Half a panel (16 features) on 16-lane registers: AVX2 + FMA, NEON, or plain.
fn tile_half(panel: &[f32], half: usize, xs: [&[f32]; ROWS]) -> [[f32; 16]; ROWS] {
    use crate::isa::F32Kernel;
    match crate::isa::f32_kernel() {
        // SAFETY: the CPU has the features the function is compiled for (AVX-512 implies
        // AVX2 + FMA).
        #[cfg(target_arch = "x86_64")]
        F32Kernel::Avx512 | F32Kernel::Avx2Fma => unsafe { tile_half_fma(panel, half, xs) },
        // NEON: 6 rows x 16 features is 24 of the 32 registers, fused.
        F32Kernel::Neon => tile_generic::<16, true>(panel, half * 16, xs),
        _ => tile_generic::<16, false>(panel, half * 16, xs),
    }
}

/// [`tile_generic`] fused, on AVX2: 12 accumulators (6 rows x 2 registers of 8 features), two
/// weight loads and a broadcast a step: 15 of the 16 registers.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn tile_half_fma(panel: &[f32], half: usize, xs: [&[f32]; ROWS]) -> [[f32; 16]; ROWS] {
    use std::arch::x86_64::*;
    let k = panel.len() / PANEL;
    assert!(xs.iter().all(|x| x.len() >= k), "rows of k activations");
    let mut acc = [[_mm256_setzero_ps(); 2]; ROWS];
    let w = panel.as_ptr().wrapping_add(half * 16);
    let xp: [*const f32; ROWS] = std::array::from_fn(|r| xs[r].as_ptr());
    for i in 0..k {
        // SAFETY: i < k: the panel holds k rows of 32 (16 from `half · 16`), every activation
        // row k values (asserted).
        unsafe {
            let w0 = _mm256_loadu_ps(w.add(i * PANEL));
            let w1 = _mm256_loadu_ps(w.add(i * PANEL + 8));
            for (acc, x) in acc.iter_mut().zip(xp) {
                let c = _mm256_broadcast_ss(&*x.add(i));
                acc[0] = _mm256_fmadd_ps(c, w0, acc[0]);
                acc[1] = _mm256_fmadd_ps(c, w1, acc[1]);
            }
        }
    }
    let mut out = [[0f32; 16]; ROWS];
    for (o, a) in out.iter_mut().zip(acc) {
        // SAFETY: 16 floats of each output row.
        unsafe {
            _mm256_storeu_ps(o.as_mut_ptr(), a[0]);
            _mm256_storeu_ps(o.as_mut_ptr().add(8), a[1]);
        }
    }
    out
}

#[inline(always)]
fn tile_generic<const L: usize, const FUSED: bool>(panel: &[f32], at: usize, xs: [&[f32]; ROWS]) -> [[f32; L]; ROWS] {
    let mut acc = [[0f32; L]; ROWS];
    // Checked once, not on every step (a bounds check per step cost a cycle of twelve on a
    // modelled A78).
    assert!(xs.iter().all(|x| x.len() >= panel.len() / PANEL), "rows of k activations");
    for (i, w) in panel.chunks_exact(PANEL).enumerate() {
        let w: &[f32; L] = w[at..at + L].try_into().expect("a panel row holds 32 features");
        for (acc, x) in acc.iter_mut().zip(&xs) {
            // SAFETY: `i < k`, the length of every row (asserted).
            let c = unsafe { *x.get_unchecked(i) };
            for (a, &w) in acc.iter_mut().zip(w) {
                *a = if FUSED { c.mul_add(w, *a) } else { c * w + *a };
            }
        }
    }
    acc
}

/// One einsum axis longer than 1: its length and its position in the constant, the data and
/// the output.
#[derive(Debug, Clone, Copy)]
struct AxisAt {
    len: usize,
    at: [Option<usize>; 3],
}

/// Merge a group of axes into one index, in the order they have in tensor `order` (0: the
/// constant, 1: the data). Every tensor that holds the group must hold it as one strided run;
/// returns the length and the stride in each tensor (0 where absent).
fn merge(group: &mut [AxisAt], order: usize, strides: [&[usize]; 3]) -> Option<(usize, [usize; 3])> {
    group.sort_by_key(|a| a.at[order]);
    let mut stride = [0; 3];
    for (t, st) in strides.iter().enumerate() {
        let Some(pos) = group.iter().map(|a| a.at[t]).collect::<Option<Vec<usize>>>() else { continue };
        for (w, p) in group.windows(2).zip(pos.windows(2)) {
            if st[p[0]] != w[1].len * st[p[1]] {
                return None;
            }
        }
        stride[t] = pos.last().map_or(0, |&p| st[p]);
    }
    Some((group.iter().map(|a| a.len).product(), stride))
}

/// One index of a [`ConstProduct`]: its length and its stride in the constant, the data and
/// the output (0 where absent).
pub(super) type Index = (usize, [usize; 3]);

/// An f32 two-input `EinSum` with one constant operand read as one product
/// `out(m, n) = Σ_k w(m, k) · x(k, n)`, each index a merged group of the einsum's axes.
pub(super) struct ConstProduct {
    /// Summed over both inputs.
    pub k: Index,
    /// From the constant to the output.
    pub m: Index,
    /// From the data to the output.
    pub n: Index,
    /// The constant operand (`w`).
    pub konst: Arc<Tensor>,
    /// The data input (`x`).
    pub data: OutletId,
    /// The einsum's output shape.
    pub output_shape: TVec<usize>,
}

/// The einsum `node` as a [`ConstProduct`], if it is one: f32, two inputs of which one is
/// constant, whose axes (ignoring those of length 1) are only summed over both inputs (k), from
/// the constant to the output (m) and from the data to the output (n), each group mergeable
/// into one strided index in every tensor that holds it.
pub(super) fn const_product(model: &TypedModel, node: &TypedNode) -> TractResult<Option<ConstProduct>> {
    let Some(e) = node.op_as::<EinSum>() else { return Ok(None) };
    let facts = model.node_input_facts(node.id)?;
    if e.q_params.is_some() || e.operating_dt != f32::datum_type() || facts.len() != 2 {
        return Ok(None);
    }
    let (c, d) = match (&facts[0].konst, &facts[1].konst) {
        (Some(_), None) => (0, 1),
        (None, Some(_)) => (1, 0),
        _ => return Ok(None),
    };
    let out_fact = &node.outputs[0].fact;
    let shapes = [facts[c].shape.as_concrete(), facts[d].shape.as_concrete(), out_fact.shape.as_concrete()];
    let [Some(cs), Some(ds), Some(os)] = shapes else { return Ok(None) };
    if facts.iter().any(|f| f.datum_type != f32::datum_type()) {
        return Ok(None);
    }
    let strides = |s: &[usize]| -> Vec<usize> { (0..s.len()).map(|i| s[i + 1..].iter().product()).collect() };
    let strides = [strides(cs), strides(ds), strides(os)];
    // k, m, n
    let mut groups: [Vec<AxisAt>; 3] = Default::default();
    for axis in e.axes.iter_all_axes() {
        let lists = [&axis.inputs[c], &axis.inputs[d], &axis.outputs[0]];
        if lists.iter().any(|l| l.len() > 1) {
            return Ok(None);
        }
        let at = lists.map(|l| l.first().copied());
        let len = [cs, ds, os].iter().zip(at).find_map(|(s, i)| i.map(|i| s[i])).unwrap_or(1);
        if len == 1 {
            continue;
        }
        let g = match at.map(|i| i.is_some()) {
            [true, true, false] => 0,
            [true, false, true] => 1,
            [false, true, true] => 2,
            _ => return Ok(None),
        };
        groups[g].push(AxisAt { len, at });
    }
    let st = [&strides[0][..], &strides[1][..], &strides[2][..]];
    let [gk, gm, gn] = &mut groups;
    // k in the data's order (it must merge the same way in the constant), m in the constant's.
    let (Some(k), Some(m), Some(n)) = (merge(gk, 1, st), merge(gm, 0, st), merge(gn, 1, st)) else {
        return Ok(None);
    };
    let konst = facts[c].konst.clone().expect("the constant operand");
    Ok(Some(ConstProduct { k, m, n, konst, data: node.inputs[d], output_shape: os.iter().copied().collect() }))
}

/// The shortest reduction [`ConstMatMul`] takes over from tract.
const MIN_K: usize = 128;

/// The [`ConstMatMul`] and its data input for a [`ConstProduct`] large enough to fill the tile.
pub(crate) fn const_matmul(model: &TypedModel, node: &TypedNode) -> TractResult<Option<(ConstMatMul, OutletId)>> {
    let Some(ConstProduct { k, m, n, konst, data, output_shape }) = const_product(model, node)? else {
        return Ok(None);
    };
    // Products too small to fill the register tile stay with tract, and so do short
    // reductions: on NanoTrack's pointwise convolutions (k = 40..96) tract's packed kernels were
    // faster (search step 2.65 -> 2.2 ms without this op there); HMG's k is 192..768.
    if m.0 < 2 * PANEL || n.0 < 2 * ROWS || k.0 < MIN_K {
        return Ok(None);
    }
    // The op writes each of the `m · n` outputs once and zeroes nothing: other outputs stay
    // with tract.
    if output_shape.iter().product::<usize>() != m.0 * n.0 {
        return Ok(None);
    }
    let w = konst.try_as_plain_ram()?;
    let w = w.as_slice::<f32>()?;
    let mut panels = vec![0f32; m.0.div_ceil(PANEL) * PANEL * k.0];
    for f in 0..m.0 {
        for i in 0..k.0 {
            panels[((f / PANEL) * k.0 + i) * PANEL + f % PANEL] = w[f * m.1[0] + i * k.1[0]];
        }
    }
    let op = ConstMatMul {
        panels: Arc::new(panels),
        m: Dim { len: m.0, input: m.1[0], output: m.1[2] },
        n: Dim { len: n.0, input: n.1[1], output: n.1[2] },
        k: Dim { len: k.0, input: k.1[1], output: 0 },
        output_shape,
    };
    Ok(Some((op, data)))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Run `expr` on a data input of `data` shape and a constant of `konst` shape (the constant
    /// first when `konst_first`), as tract's einsum and as [`ConstMatMul`].
    fn check(expr: &str, konst_first: bool, data: &[usize], konst: &[usize]) {
        check_made(expr, konst_first, data, konst, 1)
    }

    /// As [`check`], with `made` products expected to become [`ConstMatMul`].
    fn check_made(expr: &str, konst_first: bool, data: &[usize], konst: &[usize], made: usize) {
        let values = |shape: &[usize], seed: usize| -> Tensor {
            let v: Vec<f32> =
                (0..shape.iter().product()).map(|i| (((i + seed) * 7919 % 1000) as f32) / 500.0 - 1.0).collect();
            Tensor::from_shape(shape, &v).unwrap()
        };
        let mut model = TypedModel::default();
        let x = model.add_source("x", f32::fact(data)).unwrap();
        let w = model.add_const("w", values(konst, 3)).unwrap();
        let inputs = if konst_first { [w, x] } else { [x, w] };
        let op = EinSum::new(expr.parse().unwrap(), f32::datum_type());
        let y = model.wire_node("product", op, &inputs).unwrap();
        model.select_output_outlets(&y).unwrap();
        let input = values(data, 1);
        let want = model.clone().into_runnable().unwrap().run(tvec![input.clone().into_tvalue()]).unwrap();
        let done = super::super::accelerate(&mut model).unwrap();
        assert_eq!(done.matmuls, made, "{expr}");
        let runnable = model.into_runnable().unwrap();
        let got = runnable.run(tvec![input.clone().into_tvalue()]).unwrap();
        // Over eight threads, where few panels are cut in runs of rows: the same bits.
        let eight = tract_linalg::multithread::multithread_tract_scope(
            tract_linalg::multithread::Executor::multithread(8),
            || runnable.run(tvec![input.into_tvalue()]).unwrap(),
        );
        assert!(eight[0] == got[0], "{expr}: eight threads differ");
        assert_eq!(got[0].shape(), want[0].shape(), "{expr}");
        let (got, want) = (got[0].try_as_plain_ram().unwrap(), want[0].try_as_plain_ram().unwrap());
        let (got, want) = (got.as_slice::<f32>().unwrap(), want.as_slice::<f32>().unwrap());
        for (i, (g, w)) in got.iter().zip(want).enumerate() {
            assert!((g - w).abs() <= 1e-4 * w.abs().max(1.0), "{expr}: element {i}: {g} vs {w}");
        }
    }

    #[test]
    fn equals_the_einsums_of_hmg_in_each_layout() {
        // The linear layers' forms after tract's declutter (m = 70 and 100: partial panels,
        // n = 13: a partial tile of rows), and the patch embedding's split token axis.
        check("akm,kn->mn", false, &[1, 140, 13], &[140, 70]);
        check("km,nk->amn", true, &[13, 140], &[140, 70]);
        check("bkm,nbk->amn", true, &[13, 4, 35], &[4, 35, 100]);
        check("mk,akbn->ambn", true, &[1, 140, 4, 5], &[70, 140]);
        // A short reduction (a MobileNet pointwise convolution) stays with tract.
        check_made("mk,kn->mn", true, &[40, 256], &[96, 40], 0);
    }

    #[test]
    fn every_kernel_path_gives_the_same_tile() {
        let k = 37;
        let panel: Vec<f32> = (0..k * PANEL).map(|i| ((i * 31 % 17) as f32) * 0.25 - 2.0).collect();
        let x: Vec<f32> = (0..ROWS * k).map(|i| ((i * 13 % 11) as f32) * 0.5 - 2.5).collect();
        let xs: [&[f32]; ROWS] = std::array::from_fn(|r| &x[r * k..(r + 1) * k]);
        let want: Vec<Vec<f32>> = (0..ROWS)
            .map(|r| (0..PANEL).map(|f| (0..k).map(|i| xs[r][i] * panel[i * PANEL + f]).sum()).collect())
            .collect();
        let dispatched = tile(&panel, &x, k, 0, ROWS);
        for half in 0..2 {
            let fused = tile_half(&panel, half, xs);
            let plain = tile_generic::<16, false>(&panel, half * 16, xs);
            for r in 0..ROWS {
                for f in 0..16 {
                    let w = want[r][half * 16 + f];
                    for (path, v) in [
                        ("dispatched", dispatched[r][half * 16 + f]),
                        ("16 lanes", fused[r][f]),
                        ("plain", plain[r][f]),
                    ] {
                        assert!((v - w).abs() <= 1e-4 * w.abs().max(1.0), "{path}: row {r} feature {f}: {v} vs {w}");
                    }
                }
            }
        }
        // Values whose products round: every fused path (AVX-512, AVX2, NEON) sums in order of k
        // with one rounding per multiply-add, the portable fused loop's bits.
        if crate::isa::f32_kernel() != crate::isa::F32Kernel::Portable {
            let panel: Vec<f32> = (0..k * PANEL).map(|i| ((i * 7919 % 1000) as f32) / 333.0 - 1.5).collect();
            let x: Vec<f32> = (0..ROWS * k).map(|i| ((i * 104729 % 997) as f32) / 123.0 - 4.0).collect();
            let xs: [&[f32]; ROWS] = std::array::from_fn(|r| &x[r * k..(r + 1) * k]);
            let dispatched = tile(&panel, &x, k, 0, ROWS);
            for half in 0..2 {
                let want = tile_generic::<16, true>(&panel, half * 16, xs);
                assert!(tile_half(&panel, half, xs) == want, "16 lanes, half {half}");
                for r in 0..ROWS {
                    assert!(dispatched[r][half * 16..(half + 1) * 16] == want[r], "dispatched, row {r}, half {half}");
                }
            }
        }
    }

    #[test]
    fn leaves_small_or_batched_products_to_tract() {
        let mut model = TypedModel::default();
        let x = model.add_source("x", f32::fact([3, 40, 13])).unwrap();
        let w = model.add_const("w", Tensor::zero::<f32>(&[3, 40, 70]).unwrap()).unwrap();
        let op = EinSum::new("bkm,bkn->bmn".parse().unwrap(), f32::datum_type());
        let y = model.wire_node("batched", op, &[w, x]).unwrap();
        model.select_output_outlets(&y).unwrap();
        assert_eq!(super::super::accelerate(&mut model).unwrap().matmuls, 0);
    }
}
