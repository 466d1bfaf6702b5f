//! The softmax of a row of f32 (HMG's attention: rows of 242 scores), `exp` by a degree-6
//! polynomial (relative error ~1e-7), optionally after multiplying the row by a constant.
//!
//! Every path gives the portable loop's bits: the same unfused operations in the same order,
//! the max and the sum over sixteen lanes reduced as the portable loop reduces them. The
//! compiler vectorised the portable loop poorly (on AVX-512 a row of 242 took about 35 cycles a
//! vector of sixteen); the AVX-512, AVX2 and NEON forms here are one body written out over
//! sixteen lanes ([`softmax_row_lanes`]), in each path's registers.

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
        F32Kernel::Neon => unsafe { softmax_row_neon(r, scale) },
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

/// [`softmax_row_lanes`] on one AVX-512 register.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
unsafe fn softmax_row_avx512(r: &mut [f32], scale: Option<f32>) {
    // SAFETY: this function's features are those `Avx512`'s operations use.
    unsafe { softmax_row_lanes::<lanes::Avx512>(r, scale) }
}

/// [`softmax_row_lanes`] on two AVX2 registers.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn softmax_row_avx2(r: &mut [f32], scale: Option<f32>) {
    // SAFETY: this function's features are those `Avx2`'s operations use.
    unsafe { softmax_row_lanes::<lanes::Avx2>(r, scale) }
}

/// [`softmax_row_lanes`] on four NEON registers. The compiler left the portable loop's max
/// scalar (`fmaxnm` on single lanes) and its exponential four lanes at a time with one chain in
/// flight; here sixteen lanes go at a time (four independent chains).
#[cfg(target_arch = "aarch64")]
#[target_feature(enable = "neon")]
unsafe fn softmax_row_neon(r: &mut [f32], scale: Option<f32>) {
    // SAFETY: this function's features are those `Neon`'s operations use.
    unsafe { softmax_row_lanes::<lanes::Neon>(r, scale) }
}

/// [`softmax_row_portable`] sixteen lanes at a time in `V`'s registers, bit for bit: the
/// sixteen lanes of the portable loop's max and sum are `V`'s, the same unfused operations in
/// the same order; the multiply by the scale is in the max pass, the sum in the exponential's.
///
/// # Safety
/// The CPU has `V`'s instructions (this is inlined into the `#[target_feature]` function of
/// `V`'s path, so that `V`'s operations inline into it).
#[inline(always)]
unsafe fn softmax_row_lanes<V: lanes::Lanes>(r: &mut [f32], scale: Option<f32>) {
    const L: usize = 16;
    let full = r.len() / L * L;
    let p = r.as_mut_ptr();
    // SAFETY (every block below): the loads and stores are at `i..i + 16` with `i + 16 <= full
    // <= r.len()`; the CPU has `V`'s instructions (the caller's promise).
    let max = unsafe {
        let mut m = V::splat(f32::NEG_INFINITY);
        for i in (0..full).step_by(L) {
            let mut v = V::load(p.add(i));
            if let Some(s) = scale {
                v = v.mul(V::splat(s));
                v.store(p.add(i));
            }
            m = m.max(v);
        }
        scale_row(&mut r[full..], scale);
        r[full..].iter().chain(&m.lanes()).fold(f32::NEG_INFINITY, |m, &v| m.max(v))
    };
    let sum = unsafe {
        let mv = V::splat(max);
        let mut s = V::splat(0.0);
        for i in (0..full).step_by(L) {
            // `exp_nonpositive(x − max)`, the same operations in the same order.
            let x = V::load(p.add(i)).sub(mv).max(V::splat(EXP_MIN));
            let n = x.mul(V::splat(std::f32::consts::LOG2_E)).round();
            let rr = x.sub(n.mul(V::splat(LN2_HI))).add(n.mul(V::splat(LN2_LO)));
            let mut q = rr.mul(V::splat(1.0 / 720.0));
            for c in [1.0 / 120.0, 1.0 / 24.0, 1.0 / 6.0, 0.5, 1.0] {
                q = rr.mul(V::splat(c).add(q));
            }
            let e = V::splat(1.0).add(q).mul(n.exp2());
            e.store(p.add(i));
            s = s.add(e);
        }
        for v in &mut r[full..] {
            *v = exp_nonpositive(*v - max);
        }
        let sum: f32 = s.lanes().iter().chain(&r[full..]).sum();
        sum
    };
    let inv = 1.0 / sum;
    // SAFETY: as above.
    unsafe {
        for i in (0..full).step_by(L) {
            V::load(p.add(i)).mul(V::splat(inv)).store(p.add(i));
        }
    }
    r[full..].iter_mut().for_each(|v| *v *= inv);
}

/// Sixteen f32 lanes in the registers of one path, with the operations the softmax needs.
mod lanes {
    /// Sixteen lanes (one AVX-512 register, two AVX2 ones or four NEON ones) and the softmax's
    /// operations on them, lane by lane, each one instruction of the path per register.
    ///
    /// # Safety
    /// Every method runs the path's instructions: call them only where the CPU has them, from
    /// within that path's `#[target_feature]` function (where they inline).
    pub(super) trait Lanes: Copy {
        /// Every lane `v`.
        unsafe fn splat(v: f32) -> Self;
        /// Sixteen values from `p`.
        unsafe fn load(p: *const f32) -> Self;
        /// The sixteen lanes to `p`.
        unsafe fn store(self, p: *mut f32);
        /// `self + b`.
        unsafe fn add(self, b: Self) -> Self;
        /// `self − b`.
        unsafe fn sub(self, b: Self) -> Self;
        /// `self · b`.
        unsafe fn mul(self, b: Self) -> Self;
        /// The larger of `self` and `b` (the path's max instruction, `self` first).
        unsafe fn max(self, b: Self) -> Self;
        /// Rounded to the nearest whole number, ties to even.
        unsafe fn round(self) -> Self;
        /// `2^n` for whole numbers `n` (self) in [-126, 127]: the exponent field `n + 127`.
        unsafe fn exp2(self) -> Self;
        /// The sixteen lanes in order.
        #[inline(always)]
        unsafe fn lanes(self) -> [f32; 16] {
            let mut lanes = [0f32; 16];
            // SAFETY: sixteen floats into a local array of sixteen (the caller's CPU promise).
            unsafe { self.store(lanes.as_mut_ptr()) };
            lanes
        }
    }

    /// Implements [`Lanes`] for `$t`, `$n` registers of `$reg` (`$w` lanes each), from the
    /// path's instructions, one per register for each operation: `binary` ones on `self` and
    /// `b`, `unary` ones on `self` (an expression of `$x`, one register).
    macro_rules! lanes {
        ($t:ident, $reg:ty, $n:literal, $w:literal, $arch:ident, {
            splat: $splat:ident, load: $load:ident, store: $store:ident,
            binary: { $($bop:ident: $bf:ident),* $(,)? },
            unary: { $($uop:ident: |$ux:ident| $uf:expr),* $(,)? } $(,)?
        }) => {
            #[derive(Clone, Copy)]
            pub(super) struct $t([$reg; $n]);

            impl Lanes for $t {
                #[inline(always)]
                unsafe fn splat(v: f32) -> Self {
                    // SAFETY: the trait's contract (the CPU has the path's instructions).
                    $t([unsafe { std::arch::$arch::$splat(v) }; $n])
                }
                #[inline(always)]
                unsafe fn load(p: *const f32) -> Self {
                    // SAFETY: as above; `p` holds sixteen values (the caller's).
                    $t(std::array::from_fn(|k| unsafe { std::arch::$arch::$load(p.add($w * k)) }))
                }
                #[inline(always)]
                unsafe fn store(self, p: *mut f32) {
                    for (k, v) in self.0.into_iter().enumerate() {
                        // SAFETY: as above; `p` has room for sixteen values (the caller's).
                        unsafe { std::arch::$arch::$store(p.add($w * k), v) };
                    }
                }
                $(
                    #[inline(always)]
                    unsafe fn $bop(self, b: Self) -> Self {
                        // SAFETY: the trait's contract.
                        $t(std::array::from_fn(|k| unsafe { std::arch::$arch::$bf(self.0[k], b.0[k]) }))
                    }
                )*
                $(
                    #[inline(always)]
                    unsafe fn $uop(self) -> Self {
                        #[allow(unused_imports)]
                        use std::arch::$arch::*;
                        $t(std::array::from_fn(|k| {
                            let $ux = self.0[k];
                            // SAFETY: the trait's contract.
                            unsafe { $uf }
                        }))
                    }
                )*
            }
        };
    }

    #[cfg(target_arch = "x86_64")]
    lanes!(Avx512, std::arch::x86_64::__m512, 1, 16, x86_64, {
        splat: _mm512_set1_ps, load: _mm512_loadu_ps, store: _mm512_storeu_ps,
        binary: { add: _mm512_add_ps, sub: _mm512_sub_ps, mul: _mm512_mul_ps, max: _mm512_max_ps },
        unary: {
            round: |x| _mm512_roundscale_ps::<{ _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC }>(x),
            exp2: |n| _mm512_castsi512_ps(_mm512_slli_epi32::<23>(_mm512_add_epi32(
                _mm512_cvttps_epi32(n),
                _mm512_set1_epi32(127),
            ))),
        },
    });

    #[cfg(target_arch = "x86_64")]
    lanes!(Avx2, std::arch::x86_64::__m256, 2, 8, x86_64, {
        splat: _mm256_set1_ps, load: _mm256_loadu_ps, store: _mm256_storeu_ps,
        binary: { add: _mm256_add_ps, sub: _mm256_sub_ps, mul: _mm256_mul_ps, max: _mm256_max_ps },
        unary: {
            round: |x| _mm256_round_ps::<{ _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC }>(x),
            exp2: |n| _mm256_castsi256_ps(_mm256_slli_epi32::<23>(_mm256_add_epi32(
                _mm256_cvttps_epi32(n),
                _mm256_set1_epi32(127),
            ))),
        },
    });

    #[cfg(target_arch = "aarch64")]
    lanes!(Neon, std::arch::aarch64::float32x4_t, 4, 4, aarch64, {
        splat: vdupq_n_f32, load: vld1q_f32, store: vst1q_f32,
        binary: { add: vaddq_f32, sub: vsubq_f32, mul: vmulq_f32, max: vmaxnmq_f32 },
        unary: {
            round: |x| vrndnq_f32(x),
            exp2: |n| vreinterpretq_f32_s32(vshlq_n_s32::<23>(vaddq_s32(vcvtq_s32_f32(n), vdupq_n_s32(127)))),
        },
    });
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
