//! The softmax of a row of f32 (HMG's attention: rows of 242 scores), `exp` by a degree-6
//! polynomial (relative error ~1e-7), optionally after multiplying the row by a constant.
//!
//! Every path gives the portable loop's bits: the same unfused operations in the same order,
//! the max and the sum over sixteen lanes reduced as the portable loop reduces them. The
//! compiler vectorised the portable loop poorly (on AVX-512 a row of 242 took about 35 cycles a
//! vector of sixteen); the AVX-512, AVX2 and NEON forms here are written out.

use crate::isa::F32Kernel;

/// `r = softmax(scale · r)` (`scale` absent: `softmax(r)`); each value multiplied by `scale`
/// first, rounded to f32, as a separate multiply would.
pub(super) fn softmax_row(r: &mut [f32], scale: Option<f32>) {
    match crate::isa::f32_kernel() {
        // SAFETY: the CPU has the features the function is compiled for (the table's needs).
        #[cfg(target_arch = "x86_64")]
        F32Kernel::Avx512 => unsafe { softmax_row_avx512(r, scale) },
        // SAFETY: as above.
        #[cfg(target_arch = "x86_64")]
        F32Kernel::Avx2Fma => unsafe { softmax_row_avx2(r, scale) },
        // SAFETY: NEON is part of the aarch64 baseline (and the probe found it).
        #[cfg(target_arch = "aarch64")]
        F32Kernel::Neon => unsafe {
            scale_row(r, scale);
            softmax_row_neon(r)
        },
        _ => softmax_row_portable(r, scale),
    }
}

/// `r = scale · r`, value by value.
#[inline(always)]
fn scale_row(r: &mut [f32], scale: Option<f32>) {
    if let Some(s) = scale {
        r.iter_mut().for_each(|v| *v *= s);
    }
}

/// The reference every path is tested against: the multiply, then [`softmax_row_generic`].
fn softmax_row_portable(r: &mut [f32], scale: Option<f32>) {
    scale_row(r, scale);
    softmax_row_generic(r)
}

/// [`softmax_row_portable`] in AVX-512, bit for bit: the sixteen lanes of the portable loop are
/// one register; the multiply by the scale is in the max pass, the sum in the exponential's.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
unsafe fn softmax_row_avx512(r: &mut [f32], scale: Option<f32>) {
    use std::arch::x86_64::*;
    const L: usize = 16;
    let full = r.len() / L * L;
    let p = r.as_mut_ptr();
    let lanes16 = |v: __m512| {
        let mut lanes = [0f32; L];
        // SAFETY: sixteen floats into a local array of sixteen.
        unsafe { _mm512_storeu_ps(lanes.as_mut_ptr(), v) };
        lanes
    };
    // SAFETY (every block below): the loads and stores are at `i..i + 16` with `i + 16 <= full
    // <= r.len()`.
    let max = unsafe {
        let mut m = _mm512_set1_ps(f32::NEG_INFINITY);
        for i in (0..full).step_by(L) {
            let mut v = _mm512_loadu_ps(p.add(i));
            if let Some(s) = scale {
                v = _mm512_mul_ps(v, _mm512_set1_ps(s));
                _mm512_storeu_ps(p.add(i), v);
            }
            m = _mm512_max_ps(m, v);
        }
        scale_row(&mut r[full..], scale);
        r[full..].iter().chain(&lanes16(m)).fold(f32::NEG_INFINITY, |m, &v| m.max(v))
    };
    let sum = unsafe {
        let mv = _mm512_set1_ps(max);
        let mut s = _mm512_setzero_ps();
        for i in (0..full).step_by(L) {
            let x = _mm512_max_ps(_mm512_sub_ps(_mm512_loadu_ps(p.add(i)), mv), _mm512_set1_ps(EXP_MIN));
            let n = _mm512_roundscale_ps::<{ _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC }>(_mm512_mul_ps(
                x,
                _mm512_set1_ps(std::f32::consts::LOG2_E),
            ));
            let rr = _mm512_add_ps(
                _mm512_sub_ps(x, _mm512_mul_ps(n, _mm512_set1_ps(LN2_HI))),
                _mm512_mul_ps(n, _mm512_set1_ps(LN2_LO)),
            );
            let mut q = _mm512_mul_ps(rr, _mm512_set1_ps(1.0 / 720.0));
            for c in [1.0 / 120.0, 1.0 / 24.0, 1.0 / 6.0, 0.5, 1.0] {
                q = _mm512_mul_ps(rr, _mm512_add_ps(_mm512_set1_ps(c), q));
            }
            let q = _mm512_add_ps(_mm512_set1_ps(1.0), q);
            let bits = _mm512_slli_epi32::<23>(_mm512_add_epi32(_mm512_cvttps_epi32(n), _mm512_set1_epi32(127)));
            let e = _mm512_mul_ps(q, _mm512_castsi512_ps(bits));
            _mm512_storeu_ps(p.add(i), e);
            s = _mm512_add_ps(s, e);
        }
        for v in &mut r[full..] {
            *v = exp_nonpositive(*v - max);
        }
        let sum: f32 = lanes16(s).iter().chain(&r[full..]).sum();
        sum
    };
    let inv = 1.0 / sum;
    // SAFETY: as above.
    unsafe {
        for i in (0..full).step_by(L) {
            _mm512_storeu_ps(p.add(i), _mm512_mul_ps(_mm512_loadu_ps(p.add(i)), _mm512_set1_ps(inv)));
        }
    }
    r[full..].iter_mut().for_each(|v| *v *= inv);
}

/// [`softmax_row_avx512`] on AVX2: the sixteen lanes in two registers.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn softmax_row_avx2(r: &mut [f32], scale: Option<f32>) {
    use std::arch::x86_64::*;
    const L: usize = 16;
    let full = r.len() / L * L;
    let p = r.as_mut_ptr();
    let lanes16 = |v: [__m256; 2]| {
        let mut lanes = [0f32; L];
        // SAFETY: eight floats into each half of a local array of sixteen.
        unsafe {
            _mm256_storeu_ps(lanes.as_mut_ptr(), v[0]);
            _mm256_storeu_ps(lanes.as_mut_ptr().add(8), v[1]);
        }
        lanes
    };
    // SAFETY (every block below): the loads and stores are at `i + 8·h .. i + 8·h + 8`, h < 2,
    // with `i + 16 <= full <= r.len()`.
    let max = unsafe {
        let mut m = [_mm256_set1_ps(f32::NEG_INFINITY); 2];
        for i in (0..full).step_by(L) {
            for (h, m) in m.iter_mut().enumerate() {
                let mut v = _mm256_loadu_ps(p.add(i + 8 * h));
                if let Some(s) = scale {
                    v = _mm256_mul_ps(v, _mm256_set1_ps(s));
                    _mm256_storeu_ps(p.add(i + 8 * h), v);
                }
                *m = _mm256_max_ps(*m, v);
            }
        }
        scale_row(&mut r[full..], scale);
        r[full..].iter().chain(&lanes16(m)).fold(f32::NEG_INFINITY, |m, &v| m.max(v))
    };
    let sum = unsafe {
        let mv = _mm256_set1_ps(max);
        let mut s = [_mm256_setzero_ps(); 2];
        for i in (0..full).step_by(L) {
            for (h, s) in s.iter_mut().enumerate() {
                let x = _mm256_max_ps(_mm256_sub_ps(_mm256_loadu_ps(p.add(i + 8 * h)), mv), _mm256_set1_ps(EXP_MIN));
                let n = _mm256_round_ps::<{ _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC }>(_mm256_mul_ps(
                    x,
                    _mm256_set1_ps(std::f32::consts::LOG2_E),
                ));
                let rr = _mm256_add_ps(
                    _mm256_sub_ps(x, _mm256_mul_ps(n, _mm256_set1_ps(LN2_HI))),
                    _mm256_mul_ps(n, _mm256_set1_ps(LN2_LO)),
                );
                let mut q = _mm256_mul_ps(rr, _mm256_set1_ps(1.0 / 720.0));
                for c in [1.0 / 120.0, 1.0 / 24.0, 1.0 / 6.0, 0.5, 1.0] {
                    q = _mm256_mul_ps(rr, _mm256_add_ps(_mm256_set1_ps(c), q));
                }
                let q = _mm256_add_ps(_mm256_set1_ps(1.0), q);
                let bits = _mm256_slli_epi32::<23>(_mm256_add_epi32(_mm256_cvttps_epi32(n), _mm256_set1_epi32(127)));
                let e = _mm256_mul_ps(q, _mm256_castsi256_ps(bits));
                _mm256_storeu_ps(p.add(i + 8 * h), e);
                *s = _mm256_add_ps(*s, e);
            }
        }
        for v in &mut r[full..] {
            *v = exp_nonpositive(*v - max);
        }
        let sum: f32 = lanes16(s).iter().chain(&r[full..]).sum();
        sum
    };
    let inv = 1.0 / sum;
    // SAFETY: as above.
    unsafe {
        for i in (0..full).step_by(L) {
            for h in 0..2 {
                let at = p.add(i + 8 * h);
                _mm256_storeu_ps(at, _mm256_mul_ps(_mm256_loadu_ps(at), _mm256_set1_ps(inv)));
            }
        }
    }
    r[full..].iter_mut().for_each(|v| *v *= inv);
}

/// [`softmax_row_generic`] in NEON intrinsics, bit for bit: the compiler leaves its max loop
/// scalar (`fmaxnm` on single lanes) and its exponential four lanes at a time with one chain in
/// flight. Here the max, the exponential and the sum go sixteen lanes at a time (four
/// independent chains), the exponential and the sum in one pass; the same unfused operations
/// in the same order, and the lanes reduced as the portable loop reduces them.
#[cfg(target_arch = "aarch64")]
#[target_feature(enable = "neon")]
unsafe fn softmax_row_neon(r: &mut [f32]) {
    use std::arch::aarch64::*;
    const L: usize = 16;
    let full = r.len() / L * L;
    let p = r.as_mut_ptr();
    // SAFETY (every block below): the loads and stores are at `i..i + 16` with `i + 16 <= full
    // <= r.len()`.
    let max = unsafe {
        let mut m = [vdupq_n_f32(f32::NEG_INFINITY); 4];
        for i in (0..full).step_by(L) {
            for (k, m) in m.iter_mut().enumerate() {
                *m = vmaxnmq_f32(*m, vld1q_f32(p.add(i + 4 * k)));
            }
        }
        r[full..].iter().chain(&lanes16(m)).fold(f32::NEG_INFINITY, |m, &v| m.max(v))
    };
    /// Four registers' lanes in order, as the portable loop's sixteen.
    #[inline(always)]
    fn lanes16(v: [float32x4_t; 4]) -> [f32; 16] {
        let mut lanes = [0f32; 16];
        for (k, v) in v.iter().enumerate() {
            // SAFETY: four floats into lanes 4k..4k + 4 of sixteen; NEON is baseline.
            unsafe { vst1q_f32(lanes.as_mut_ptr().add(4 * k), *v) };
        }
        lanes
    }
    /// [`exp_nonpositive`] of `x - max` on four lanes, the same operations in the same order.
    #[inline(always)]
    unsafe fn exp4(x: float32x4_t, max: float32x4_t) -> float32x4_t {
        let x = vmaxnmq_f32(vsubq_f32(x, max), vdupq_n_f32(EXP_MIN));
        let n = vrndnq_f32(vmulq_n_f32(x, std::f32::consts::LOG2_E));
        let r = vaddq_f32(vsubq_f32(x, vmulq_n_f32(n, LN2_HI)), vmulq_n_f32(n, LN2_LO));
        let mut q = vmulq_n_f32(r, 1.0 / 720.0);
        for c in [1.0 / 120.0, 1.0 / 24.0, 1.0 / 6.0, 0.5, 1.0] {
            q = vmulq_f32(r, vaddq_f32(vdupq_n_f32(c), q));
        }
        let q = vaddq_f32(vdupq_n_f32(1.0), q);
        let two_n = vreinterpretq_f32_s32(vshlq_n_s32::<23>(vaddq_s32(vcvtq_s32_f32(n), vdupq_n_s32(127))));
        vmulq_f32(q, two_n)
    }
    let sum = unsafe {
        let mv = vdupq_n_f32(max);
        let mut s = [vdupq_n_f32(0.0); 4];
        for i in (0..full).step_by(L) {
            for (k, s) in s.iter_mut().enumerate() {
                let e = exp4(vld1q_f32(p.add(i + 4 * k)), mv);
                vst1q_f32(p.add(i + 4 * k), e);
                *s = vaddq_f32(*s, e);
            }
        }
        for v in &mut r[full..] {
            *v = exp_nonpositive(*v - max);
        }
        let sum: f32 = lanes16(s).iter().chain(&r[full..]).sum();
        sum
    };
    let inv = 1.0 / sum;
    // SAFETY: as above.
    unsafe {
        for i in (0..full).step_by(L) {
            for k in 0..4 {
                vst1q_f32(p.add(i + 4 * k), vmulq_n_f32(vld1q_f32(p.add(i + 4 * k)), inv));
            }
        }
    }
    r[full..].iter_mut().for_each(|v| *v *= inv);
}

#[inline(always)]
fn softmax_row_generic(r: &mut [f32]) {
    // Sixteen lanes of max and sum, so that the loops vectorise.
    const L: usize = 16;
    let mut lanes = [f32::NEG_INFINITY; L];
    let mut chunks = r.chunks_exact(L);
    for c in &mut chunks {
        for (m, &v) in lanes.iter_mut().zip(c) {
            *m = m.max(v);
        }
    }
    let max = chunks.remainder().iter().chain(&lanes).fold(f32::NEG_INFINITY, |m, &v| m.max(v));
    for v in r.iter_mut() {
        *v = exp_nonpositive(*v - max);
    }
    let mut sums = [0f32; L];
    let mut chunks = r.chunks_exact(L);
    for c in &mut chunks {
        for (s, &v) in sums.iter_mut().zip(c) {
            *s += v;
        }
    }
    let sum: f32 = sums.iter().chain(chunks.remainder()).sum();
    let inv = 1.0 / sum;
    r.iter_mut().for_each(|v| *v *= inv);
}

/// Where [`exp_nonpositive`] clamps its input (`e^x` underflows f32 below it).
const EXP_MIN: f32 = -87.0;
/// ln 2 in two parts (Cephes): `LN2_HI − LN2_LO`, the first exact in a product by small `n`.
const LN2_HI: f32 = 0.693_359_4;
const LN2_LO: f32 = 2.121_944_4e-4;

/// `e^x` for `x <= 0` (a softmax's shifted inputs): `2^n · p(r)` with `x = n·ln2 + r`,
/// `|r| <= ln2/2`, `p` the degree-6 Taylor polynomial (relative error under 2e-7); 0 below
/// -87 (where f32 underflows anyway).
#[inline(always)]
fn exp_nonpositive(x: f32) -> f32 {
    let x = x.max(EXP_MIN);
    let n = (x * std::f32::consts::LOG2_E).round_ties_even();
    let r = x - n * LN2_HI + n * LN2_LO;
    let p = 1.0 + r * (1.0 + r * (0.5 + r * (1.0 / 6.0 + r * (1.0 / 24.0 + r * (1.0 / 120.0 + r * (1.0 / 720.0))))));
    // SAFETY: `n` is a whole number in [-126, 0] (x is clamped), so the cast is exact.
    let n = unsafe { n.to_int_unchecked::<i32>() };
    p * f32::from_bits(((n + 127) as u32) << 23)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ops::attention::tests::values;

    /// The dispatched softmax (the path the machine runs: AVX-512, AVX2 or NEON) gives the
    /// portable loop's bits, on rows with and without a remainder past the sixteen lanes, with
    /// inputs far enough below the max to underflow, with and without a scale.
    #[test]
    fn softmax_paths_equal_the_portable_loop() {
        for n in [1usize, 3, 15, 16, 17, 40, 121, 242, 625] {
            let mut row: Vec<f32> = values(n, n).iter().map(|v| v * 30.0).collect();
            if n > 2 {
                row[n / 2] = -200.0;
            }
            for scale in [None, Some(0.144_337_56f32), Some(-1.5)] {
                let (mut got, mut want) = (row.clone(), row.clone());
                softmax_row(&mut got, scale);
                softmax_row_portable(&mut want, scale);
                let same = got.iter().zip(&want).all(|(x, y)| x.to_bits() == y.to_bits());
                assert!(same, "row of {n}, scale {scale:?}");
            }
        }
    }

    #[test]
    fn exp_is_accurate_over_the_softmax_range() {
        for i in 0..=8700 {
            let x = -(i as f32) / 100.0;
            let (got, want) = (exp_nonpositive(x), (x as f64).exp());
            assert!(((got as f64 - want) / want).abs() < 5e-7, "exp({x}) = {got}, want {want}");
        }
    }
}
