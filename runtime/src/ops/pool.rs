//! Unpadded max pooling of f32 or u8 (int8 plans) as [`ChannelMaxPool`]: channels spread over
//! the thread pool (tract's max pool runs on one thread: 9 ms of the search network on 2
//! threads).

use tract_nnef::internal::*;
use tract_nnef::tract_core::ops::cnn::MaxPool;
use tract_nnef::tract_core::ops::nn::DataFormat;

use super::{all_ones, no_padding, output_tensor, par_chunks};

/// `out[n,c,y,x] = max_{i<k, j<k} input[n,c,y·s+i,x·s+j]`: a `k` x `k` window, stride `s`, no
/// padding, NCHW, f32 or u8 (quantised u8 too: a positive scale keeps the order).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ChannelMaxPool {
    /// Window side.
    pub k: usize,
    /// Stride on both axes.
    pub stride: usize,
}

impl ChannelMaxPool {
    fn out(&self, side: usize) -> usize {
        (side - self.k) / self.stride + 1
    }
}

impl Op for ChannelMaxPool {
    fn name(&self) -> StaticName {
        "ChannelMaxPool".into()
    }

    fn info(&self) -> TractResult<Vec<String>> {
        Ok(vec![format!("{k}x{k} window, stride {}", self.stride, k = self.k)])
    }

    op_as_typed_op!();
}

impl EvalOp for ChannelMaxPool {
    op_out_of_plan!();

    fn eval(&self, _ctx: &EvalContext, inputs: TVec<TValue>) -> TractResult<TVec<TValue>> {
        let input = args_1!(inputs);
        let &[n, c, h, w] = input.shape() else { bail!("ChannelMaxPool: input {:?} is not rank 4", input.shape()) };
        ensure!(h >= self.k && w >= self.k, "ChannelMaxPool: input {:?} smaller than the window", input.shape());
        let dt = input.datum_type();
        let plain = input.try_as_plain_ram()?;
        let mut out = if dt == f32::datum_type() {
            #[cfg(target_arch = "x86_64")]
            let fast = (self.k == 3 && self.stride == 2 && crate::isa::f32_kernel() == crate::isa::F32Kernel::Avx512)
                .then_some(plane_k3s2_avx512 as PlaneFn<f32>);
            #[cfg(target_arch = "aarch64")]
            let fast = (self.k == 3 && self.stride == 2 && crate::isa::f32_kernel() == crate::isa::F32Kernel::Neon)
                .then_some(plane_k3s2_neon as PlaneFn<f32>);
            #[cfg(not(any(target_arch = "x86_64", target_arch = "aarch64")))]
            let fast = None;
            self.pool(plain.as_slice::<f32>()?, [n, c, h, w], f32::NEG_INFINITY, f32::max, fast)?
        } else {
            ensure!(dt.unquantized() == u8::datum_type(), "ChannelMaxPool: input is {dt:?}");
            // SAFETY: the storage is u8 (plain or quantised), checked above.
            let data = unsafe { plain.as_slice_unchecked::<u8>() };
            self.pool(data, [n, c, h, w], 0u8, u8::max, None)?
        };
        // SAFETY: same storage type; the input's quantisation parameters carry over.
        unsafe { out.set_datum_type(dt) };
        Ok(tvec!(out.into_tvalue()))
    }
}

/// A plane pooled by a SIMD kernel: `src` (rows of `w`) into `dst`.
///
/// # Safety
/// The CPU has the kernel's instruction set.
type PlaneFn<T> = unsafe fn(src: &[T], w: usize, dst: &mut [T]);

impl ChannelMaxPool {
    fn pool<T: Datum + Copy>(
        &self,
        input: &[T],
        [n, c, h, w]: [usize; 4],
        lowest: T,
        max: impl Fn(T, T) -> T + Copy + Sync,
        fast: Option<PlaneFn<T>>,
    ) -> TractResult<Tensor> {
        let (oh, ow) = (self.out(h), self.out(w));
        output_tensor(&[n, c, oh, ow], |out: &mut [T]| {
            par_chunks(out, oh * ow, |plane, dst| {
                let src = &input[plane * h * w..(plane + 1) * h * w];
                if let Some(fast) = fast {
                    // SAFETY: `fast` is only given where the CPU has its instruction set.
                    return unsafe { fast(src, w, dst) };
                }
                #[cfg(target_arch = "x86_64")]
                if crate::isa::f32_kernel() != crate::isa::F32Kernel::Portable {
                    // SAFETY: every x86 kernel of the table but the portable one needs AVX2.
                    return unsafe { self.plane_avx2(src, w, lowest, max, dst) };
                }
                self.plane(src, w, lowest, max, dst)
            });
            Ok(())
        })
    }

    /// [`Self::plane`] compiled for AVX2 (the compiler's vectors of 32 bytes instead of 16:
    /// PRL-Track's two pools 3.7 -> 2.7 ms a search step on an AMD EPYC).
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    unsafe fn plane_avx2<T: Copy>(&self, src: &[T], w: usize, lowest: T, max: impl Fn(T, T) -> T, dst: &mut [T]) {
        self.plane(src, w, lowest, max, dst)
    }

    /// One plane `src` (rows of `w`) pooled into `dst` (rows of `ow`): the window's rows reduced
    /// first, then its columns at every column (both element-wise over shifted slices,
    /// vectorised), then every `stride`-th kept.
    #[inline(always)]
    fn plane<T: Copy>(&self, src: &[T], w: usize, lowest: T, max: impl Fn(T, T) -> T, dst: &mut [T]) {
        let ow = self.out(w);
        let mut cols = vec![lowest; w];
        let mut wide = vec![lowest; w - self.k + 1];
        for (y, row) in dst.chunks_exact_mut(ow).enumerate() {
            cols.fill(lowest);
            for r in src[y * self.stride * w..(y * self.stride + self.k) * w].chunks_exact(w) {
                for (m, &v) in cols.iter_mut().zip(r) {
                    *m = max(*m, v);
                }
            }
            wide.fill(lowest);
            for j in 0..self.k {
                for (m, &v) in wide.iter_mut().zip(&cols[j..]) {
                    *m = max(*m, v);
                }
            }
            for (d, &m) in row.iter_mut().zip(wide.iter().step_by(self.stride)) {
                *d = m;
            }
        }
    }
}

/// [`ChannelMaxPool::plane`] for a 3 x 3 window of stride 2 on AVX-512: 16 outputs at a time
/// from the three input rows' columns `2x ..` and `2x + 2 ..` (two vectors each, masked at the
/// row's end), reduced over the rows, then the even columns, the odd columns and the even
/// columns two on picked out (two-source permutes), `vmaxps` throughout (the same maxima as
/// `f32::max` without NaNs). The first form stored each output row's reduced row and read it
/// back at offsets of 2 (store-to-load forwarding failed on every such read): PRL-Track's
/// template pools took 0.10 and 0.095 ms so alone on one thread of an AVX-512 Xeon, 0.044 and
/// 0.023 now (ONNX Runtime's 0.035 and 0.023 in its profile); the search graph's first 0.47
/// -> 0.43 (its 7.4 MB input comes from L3).
///
/// # Safety
/// The CPU has AVX-512F.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
unsafe fn plane_k3s2_avx512(src: &[f32], w: usize, dst: &mut [f32]) {
    use std::arch::x86_64::*;
    let ow = (w - 3) / 2 + 1;
    assert!(w >= 3 && dst.len().is_multiple_of(ow) && src.len() >= ((dst.len() / ow - 1) * 2 + 3) * w);
    let even = _mm512_setr_epi32(0, 2, 4, 6, 8, 10, 12, 14, 16, 18, 20, 22, 24, 26, 28, 30);
    let odd = _mm512_setr_epi32(1, 3, 5, 7, 9, 11, 13, 15, 17, 19, 21, 23, 25, 27, 29, 31);
    // The lanes of a 16-column load from column `at` that fall within the row.
    let lanes = |at: usize| -> u16 { ((1u32 << w.saturating_sub(at).min(16)) - 1) as u16 };
    let (oh, out) = (dst.len() / ow, dst.as_mut_ptr());
    // Bands of 8 output rows (their 17 input rows stay in L1 while each column block passes
    // over them), column blocks within a band (their masks made once).
    for band in (0..oh).step_by(8) {
        let mut x = 0;
        while x < ow {
            let n = 16.min(ow - x);
            // Output x + i reads columns 2(x + i) ..= 2(x + i) + 2, all below w for i < n; the
            // lanes past the row's end load as 0 and reach only outputs that are not stored.
            let at = [2 * x, 2 * x + 16, 2 * x + 2, 2 * x + 18];
            let masks = at.map(lanes);
            for y in band..oh.min(band + 8) {
                // SAFETY: each load is masked to the columns (below `w`) of a row of the window,
                // within `src` (asserted); the store is masked to the `n` outputs left of row `y`.
                unsafe {
                    let rows: [*const f32; 3] = std::array::from_fn(|i| src.as_ptr().add((2 * y + i) * w));
                    let v: [__m512; 4] = std::array::from_fn(|k| {
                        let load = |r: *const f32| _mm512_maskz_loadu_ps(masks[k], r.wrapping_add(at[k]));
                        _mm512_max_ps(_mm512_max_ps(load(rows[0]), load(rows[1])), load(rows[2]))
                    });
                    let m = _mm512_max_ps(
                        _mm512_max_ps(
                            _mm512_permutex2var_ps(v[0], even, v[1]),
                            _mm512_permutex2var_ps(v[0], odd, v[1]),
                        ),
                        _mm512_permutex2var_ps(v[2], even, v[3]),
                    );
                    _mm512_mask_storeu_ps(out.add(y * ow + x), ((1u32 << n) - 1) as u16, m);
                }
            }
            x += n;
        }
    }
}

/// [`ChannelMaxPool::plane`] for a 3 x 3 window of stride 2 on NEON: 8 outputs at a time, each
/// input row's columns `2x ..` and `2x + 2 ..` loaded de-interleaved (`ld2`: even and odd
/// columns in two registers, so the stride costs no shuffles), reduced over the three rows and
/// the window's three columns with `fmaxnm` (`f32::max`'s maximum, NaNs included); the outputs
/// whose window reaches past what a whole load may read, one at a time. The portable form
/// reduced every column of the window before keeping every other one, twice the work and a
/// strided copy.
///
/// # Safety
/// The CPU has NEON (the aarch64 baseline).
#[cfg(target_arch = "aarch64")]
#[target_feature(enable = "neon")]
unsafe fn plane_k3s2_neon(src: &[f32], w: usize, dst: &mut [f32]) {
    use std::arch::aarch64::*;
    let ow = (w - 3) / 2 + 1;
    let oh = dst.len() / ow;
    assert!(w >= 3 && dst.len() == oh * ow && src.len() >= ((oh.max(1) - 1) * 2 + 3) * w);
    // Outputs x .. x + 8 read columns 2x .. 2x + 18 (`ld2` of 8 from 2x, 2x + 2, 2x + 8 and
    // 2x + 10: through 2x + 17, of which 2x + 16 is kept): blocks of 8 outputs within the row
    // that start at or before (w - 18) / 2.
    let blocks = if w >= 18 { ((w - 18) / 2 / 8 + 1).min(ow / 8) } else { 0 };
    for y in 0..oh {
        let rows: [&[f32]; 3] = std::array::from_fn(|i| &src[(2 * y + i) * w..(2 * y + i + 1) * w]);
        let out = &mut dst[y * ow..(y + 1) * ow];
        for b in 0..blocks {
            let x = 8 * b;
            // SAFETY: each row's reads are columns 2x .. 2x + 18 <= w (`blocks`); the stores are
            // outputs x .. x + 8 <= ow.
            unsafe {
                let mut m = [vdupq_n_f32(f32::NEG_INFINITY); 2];
                for r in rows {
                    let p = r.as_ptr().add(2 * x);
                    for (h, m) in m.iter_mut().enumerate() {
                        let a = vld2q_f32(p.add(8 * h));
                        let c = vld2q_f32(p.add(8 * h + 2));
                        *m = vmaxnmq_f32(*m, vmaxnmq_f32(vmaxnmq_f32(a.0, a.1), c.0));
                    }
                }
                vst1q_f32(out.as_mut_ptr().add(x), m[0]);
                vst1q_f32(out.as_mut_ptr().add(x + 4), m[1]);
            }
        }
        for (x, o) in out.iter_mut().enumerate().skip(8 * blocks) {
            *o = rows.iter().flat_map(|r| &r[2 * x..2 * x + 3]).fold(f32::NEG_INFINITY, |a, &b| a.max(b));
        }
    }
}

impl TypedOp for ChannelMaxPool {
    fn output_facts(&self, inputs: &[&TypedFact]) -> TractResult<TVec<TypedFact>> {
        let s = &inputs[0].shape;
        let out = |d: usize| (s[d].clone() - self.k) / self.stride + 1;
        Ok(tvec!(inputs[0].datum_type.fact([s[0].clone(), s[1].clone(), out(2), out(3)])))
    }

    as_op!();
}

/// The [`ChannelMaxPool`] for `node` of `model` if it is an f32 or u8 NCHW max pool with a
/// square window, equal strides, no padding, no dilation and no index output.
pub(crate) fn channel_max_pool(model: &TypedModel, node: &TypedNode) -> TractResult<Option<ChannelMaxPool>> {
    let Some(pool) = node.op_as::<MaxPool>() else { return Ok(None) };
    let fact = model.outlet_fact(node.inputs[0])?;
    let ps = &pool.pool_spec;
    let k = ps.kernel_shape.as_slice();
    let strides = ps.strides.as_ref().map(|s| s.to_vec()).unwrap_or_else(|| vec![1; k.len()]);
    let plain = pool.with_index_outputs.is_none()
        && ps.data_format == DataFormat::NCHW
        && (fact.datum_type == f32::datum_type() || fact.datum_type.unquantized() == u8::datum_type())
        && fact.rank() == 4
        && k.len() == 2
        && k[0] == k[1]
        && strides.len() == 2
        && strides[0] == strides[1]
        && all_ones(&ps.dilations)
        && no_padding(&ps.padding);
    Ok(plain.then_some(ChannelMaxPool { k: k[0], stride: strides[0] }))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pools_u8_like_f32() {
        let op = ChannelMaxPool { k: 3, stride: 2 };
        let v: Vec<u8> = (0..2 * 35).map(|i| ((i * 37) % 251) as u8).collect();
        let as_f32: Vec<f32> = v.iter().map(|&b| b as f32).collect();
        let run = |t: Tensor| op.eval(&EvalContext::out_of_plan(), tvec![t.into_tvalue()]).unwrap().remove(0);
        let a = run(tract_ndarray::Array4::from_shape_vec((1, 2, 7, 5), v).unwrap().into_tensor());
        let b = run(tract_ndarray::Array4::from_shape_vec((1, 2, 7, 5), as_f32).unwrap().into_tensor());
        let a: Vec<f32> = a.try_as_plain_ram().unwrap().as_slice::<u8>().unwrap().iter().map(|&x| x as f32).collect();
        assert_eq!(a, b.try_as_plain_ram().unwrap().as_slice::<f32>().unwrap());
    }

    #[test]
    fn takes_the_maximum_of_each_window() {
        // Windows and strides of the networks' pools and others, odd and even sides; channel 1
        // holds the negated values.
        // (3, 2) with rows of more than 16 outputs: on AVX-512 (NEON) its vector kernel, whole
        // vectors (blocks of 8) and a tail, several bands of rows.
        if !matches!(crate::isa::f32_kernel(), crate::isa::F32Kernel::Avx512 | crate::isa::F32Kernel::Neon) {
            println!("NOTE: no AVX-512 or NEON here (or PRL_ISA caps them): the 3 x 3 stride-2 pool kernels are not tested here");
        }
        for (k, stride, h, w) in [
            (3, 2, 7, 5),
            (3, 2, 8, 10),
            (2, 2, 6, 9),
            (3, 1, 5, 6),
            (5, 3, 11, 12),
            (3, 2, 9, 71),
            (3, 2, 6, 66),
            (3, 2, 5, 35),
            // More output rows than a band of the vector kernel (8), not a multiple of it; a
            // plane one output wide.
            (3, 2, 41, 37),
            (3, 2, 20, 3),
        ] {
            let op = ChannelMaxPool { k, stride };
            let (oh, ow) = (op.out(h), op.out(w));
            let v: Vec<f32> = (0..h * w).map(|i| ((i * 17) % 23) as f32).collect();
            let data: Vec<f32> = v.iter().copied().chain(v.iter().map(|x| -x)).collect();
            let v = &v;
            let x = tract_ndarray::Array4::from_shape_vec((1, 2, h, w), data).unwrap();
            let out = op.eval(&EvalContext::out_of_plan(), tvec![x.into_tensor().into_tvalue()]).unwrap();
            let out = out[0].try_as_plain_ram().unwrap();
            let out = out.as_slice::<f32>().unwrap();
            assert_eq!(out.len(), 2 * oh * ow);
            for c in 0..2 {
                let sign = if c == 0 { 1.0 } else { -1.0 };
                for y in 0..oh {
                    for x in 0..ow {
                        let want = (0..k)
                            .flat_map(|i| (0..k).map(move |j| sign * v[(stride * y + i) * w + stride * x + j]))
                            .fold(f32::NEG_INFINITY, f32::max);
                        assert_eq!(out[(c * oh + y) * ow + x], want, "k {k} stride {stride}: channel {c} ({y},{x})");
                    }
                }
            }
        }
    }
}
