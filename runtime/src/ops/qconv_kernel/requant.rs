//! The requantisation [`super::super::PackedQConv`]'s tiles and [`super::super::DepthwiseQConv`]
//! share: `sat_u8(round_half_even(sum · scale) + y0)` as tract computes it, 16 lanes on
//! AVX-512, 8 on AVX2, 4 on NEON, bit for bit the scalar formula.

use tract_nnef::tract_core::tract_linalg::{mmm::RoundingPolicy, Scaler};

/// Whether [`requant_one`]'s exact rounding is vectorised for one `scale` on sums at most
/// `bound` in magnitude (`255·Σ|w| + |bias|` over a layer's output channels): from 2^-15, so
/// that a sum too large for an f32 (2^24 and up) saturates either way, while `bound · scale`
/// stays below 2^31, so that tract's fixed-point product (an i64 cut to i32) does not wrap. A
/// layer with one scale outside this stays with tract. (Scales of 1 and more come where an
/// output's calibrated range is narrow against its input's and weights', e.g. clipped by
/// `--method percentile`.)
pub(in crate::ops) fn exact_fits(scale: f32, bound: i64) -> bool {
    scale >= 1.0 / 32768.0 && (scale as f64) * (bound as f64) < 2f64.powi(31)
}

/// One requantised output: `sat_u8(round_half_even(sum · scale) + y0)`, with the product as
/// tract takes it. `exact` (one scale for every output channel): the exact product, as tract's
/// `Scaler` (fixed point, rounded half to even); else the f32 product rounded, as tract's
/// per-channel `Scale`. The two differ where the f32 product lands on a half that the exact
/// one misses.
#[inline]
pub(in crate::ops) fn requant_one(sum: i32, scale: f32, exact: bool, y0: u8) -> u8 {
    if exact {
        (sum * Scaler::new(scale, RoundingPolicy::Even)).saturating_add(y0 as i32).clamp(0, 255) as u8
    } else {
        ((sum as f32 * scale).round_ties_even() + y0 as f32).clamp(0.0, 255.0) as u8
    }
}

/// Sums whose product with `scale` rounds one way in f32 and the other exactly (where
/// [`requant_one`]'s two forms part), with outputs (zero point 100) in `0..=200`: the test
/// cases of every exact requantisation path.
#[cfg(test)]
pub(in crate::ops) fn tie_sums(scale: f32) -> Vec<i32> {
    let scaler = Scaler::new(scale, RoundingPolicy::Even);
    let limit = (100.0 / scale) as i32;
    (-limit..limit).filter(|&x| (x as f32 * scale).round_ties_even() as i32 != x * scaler).collect()
}

/// Weight scales `k` whose requantisation scales by tract's two forms (`x · k / y` and `(k · x)
/// · (1 / y)`, see [`super::qconv::requant_scales`]) part, each with a sum whose products
/// with the two round apart (rounded exactly, as tract's `Scaler`, with `exact`) and outputs
/// within 90 of the zero point 100 (unsaturated): the test cases that tell the forms apart.
#[cfg(test)]
pub(in crate::ops) fn parting_scales(x_scale: f32, y_scale: f32, exact: bool) -> impl Iterator<Item = (f32, i32)> {
    (0..20000).filter_map(move |i| {
        let k = 0.0005 + 0.0000013 * i as f32;
        let (d, r) = (x_scale * k / y_scale, (k * x_scale) * (1.0 / y_scale));
        if d.to_bits() == r.to_bits() {
            return None;
        }
        let limit = (90.0 / r) as i32;
        let b = (-limit..limit).find(|&b| requant_one(b, d, exact, 100) != requant_one(b, r, exact, 100))?;
        Some((k, b))
    })
}

/// `out[i] = requant_one(sums[i] + offset, scale, exact, y0)`, bit for bit, on the widest form
/// [`crate::isa`] allows: 16 lanes on AVX-512, 8 on AVX2, 16 on NEON, else the portable loop.
/// Every integer operator's requantisation goes through here.
pub(in crate::ops) fn requantise(sums: &[i32], offset: i32, scale: f32, exact: bool, y0: u8, out: &mut [u8]) {
    #[cfg(target_arch = "x86_64")]
    {
        let isa = crate::isa();
        if isa.avx512 {
            // SAFETY: the CPU has AVX-512F.
            return unsafe { requantise_avx512(sums, offset, scale, exact, y0, out) };
        }
        if isa.avx2_fma {
            // SAFETY: the CPU has AVX2 and FMA.
            return unsafe { requantise_avx2(sums, offset, scale, exact, y0, out) };
        }
    }
    #[cfg(target_arch = "aarch64")]
    requantise_neon(sums, offset, scale, exact, y0, out);
    #[cfg(not(target_arch = "aarch64"))]
    requantise_portable(sums, offset, scale, exact, y0, out);
}

/// [`requantise`] on 8 lanes (AVX2), bit for bit [`requant_one`].
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn requantise_avx2(sums: &[i32], offset: i32, scale: f32, exact: bool, y0: u8, out: &mut [u8]) {
    use std::arch::x86_64::*;
    let (off, sc, y) = (_mm256_set1_epi32(offset), _mm256_set1_ps(scale), _mm256_set1_ps(y0 as f32));
    let mut chunks = sums.chunks_exact(8);
    let mut outs = out.chunks_exact_mut(8);
    for (s, o) in (&mut chunks).zip(&mut outs) {
        // SAFETY: 8 i32 in, 8 bytes out.
        unsafe {
            let v = _mm256_loadu_si256(s.as_ptr().cast());
            _mm_storel_epi64(o.as_mut_ptr().cast(), requant8(v, off, sc, y, exact));
        }
    }
    for (o, &s) in outs.into_remainder().iter_mut().zip(chunks.remainder()) {
        *o = requant_one(s + offset, scale, exact, y0);
    }
}

/// [`requant_one`] of eight sums `v` (offset `off`, scale `sc`, output zero point `y`, all
/// broadcast), as eight bytes in the low half of the result.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
#[inline]
pub(in crate::ops) fn requant8(
    v: std::arch::x86_64::__m256i,
    off: std::arch::x86_64::__m256i,
    sc: std::arch::x86_64::__m256,
    y: std::arch::x86_64::__m256,
    exact: bool,
) -> std::arch::x86_64::__m128i {
    use std::arch::x86_64::*;
    let x = _mm256_cvtepi32_ps(_mm256_add_epi32(v, off));
    let p = _mm256_mul_ps(x, sc);
    let mut r = _mm256_round_ps::<{ _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC }>(p);
    if exact {
        r = exact_avx2(x, sc, p, r);
    }
    let f = _mm256_add_ps(r, y);
    let f = _mm256_min_ps(_mm256_max_ps(f, _mm256_setzero_ps()), _mm256_set1_ps(255.0));
    let i = _mm256_cvttps_epi32(f);
    // Eight values in 0..=255: narrowing with unsigned saturation keeps them.
    let w = _mm_packus_epi32(_mm256_castsi256_si128(i), _mm256_extracti128_si256::<1>(i));
    _mm_packus_epi16(w, w)
}

/// The exact product `x · scale` rounded half to even, from its f32 product `p` and that
/// rounded, `r` (x an integer below 2^24 in magnitude): `p` is a half only where the exact
/// product is that half or rounds onto it, and the product's error `x·scale − p` (exact by a
/// fused multiply-add) says which side it lies on; elsewhere `r` is already right. Where `p`
/// is `r ± ½` and the error has the same sign, the exact product is past the half: `r + 2(p −
/// r)`.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
#[inline]
fn exact_avx2(
    x: std::arch::x86_64::__m256,
    scale: std::arch::x86_64::__m256,
    p: std::arch::x86_64::__m256,
    r: std::arch::x86_64::__m256,
) -> std::arch::x86_64::__m256 {
    use std::arch::x86_64::*;
    let d = _mm256_sub_ps(p, r);
    let half = _mm256_cmp_ps::<_CMP_EQ_OQ>(_mm256_andnot_ps(_mm256_set1_ps(-0.0), d), _mm256_set1_ps(0.5));
    // Halves are rare: most groups of eight have none.
    if _mm256_movemask_ps(half) == 0 {
        return r;
    }
    let error = _mm256_fmsub_ps(x, scale, p);
    let past = _mm256_cmp_ps::<_CMP_GT_OQ>(_mm256_mul_ps(d, error), _mm256_setzero_ps());
    _mm256_add_ps(r, _mm256_and_ps(_mm256_and_ps(half, past), _mm256_add_ps(d, d)))
}

/// [`requantise`] on 16 lanes (AVX-512).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
unsafe fn requantise_avx512(sums: &[i32], offset: i32, scale: f32, exact: bool, y0: u8, out: &mut [u8]) {
    use std::arch::x86_64::*;
    let mut chunks = sums.chunks_exact(16);
    let mut outs = out.chunks_exact_mut(16);
    for (s, o) in (&mut chunks).zip(&mut outs) {
        // SAFETY: 16 i32 in, 16 bytes out.
        unsafe {
            let v = _mm512_loadu_si512(s.as_ptr().cast());
            _mm_storeu_si128(o.as_mut_ptr().cast(), requant16(v, offset, scale, exact, y0));
        }
    }
    for (o, &s) in outs.into_remainder().iter_mut().zip(chunks.remainder()) {
        *o = requant_one(s + offset, scale, exact, y0);
    }
}

/// [`requantise`] on 16 lanes, bit for bit [`requant_one`].
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
pub(in crate::ops) fn requant16(
    v: std::arch::x86_64::__m512i,
    offset: i32,
    scale: f32,
    exact: bool,
    y0: u8,
) -> std::arch::x86_64::__m128i {
    use std::arch::x86_64::*;
    _mm512_cvtepi32_epi8(requant_lanes(v, _mm512_set1_epi32(offset), _mm512_set1_ps(scale), exact, y0))
}

/// The requantisation of 16 sums, each lane with its own offset and scale, as i32 values in
/// `0..=255` (what every AVX-512 path narrows to bytes): [`requant_one`] of `v + offset`, the
/// scalar formula's operations in its order (`exact`: as [`exact_avx2`], on 16 lanes).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
#[inline]
pub(in crate::ops) fn requant_lanes(
    v: std::arch::x86_64::__m512i,
    offset: std::arch::x86_64::__m512i,
    scale: std::arch::x86_64::__m512,
    exact: bool,
    y0: u8,
) -> std::arch::x86_64::__m512i {
    use std::arch::x86_64::*;
    let x = _mm512_cvtepi32_ps(_mm512_add_epi32(v, offset));
    let p = _mm512_mul_ps(x, scale);
    let mut r = _mm512_roundscale_ps::<{ _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC }>(p);
    if exact {
        let d = _mm512_sub_ps(p, r);
        let half = _mm512_cmp_ps_mask::<_CMP_EQ_OQ>(_mm512_abs_ps(d), _mm512_set1_ps(0.5));
        // Halves are rare: most groups of sixteen have none.
        if half != 0 {
            let error = _mm512_fmsub_ps(x, scale, p);
            let past = _mm512_cmp_ps_mask::<_CMP_GT_OQ>(_mm512_mul_ps(d, error), _mm512_setzero_ps());
            r = _mm512_mask_add_ps(r, half & past, r, _mm512_add_ps(d, d));
        }
    }
    let f = _mm512_add_ps(r, _mm512_set1_ps(y0 as f32));
    let f = _mm512_min_ps(_mm512_max_ps(f, _mm512_setzero_ps()), _mm512_set1_ps(255.0));
    _mm512_cvttps_epi32(f)
}

/// [`requantise`] on NEON, sixteen at a time (the compiler's own vectorisation of the f32 form
/// took 52 instructions for sixteen, and left the exact form scalar in tract's fixed point):
/// the scalar formula's operations in its order, and the exact product as [`exact_avx2`] makes
/// it (`FMLS` gives the product's error).
#[cfg(target_arch = "aarch64")]
fn requantise_neon(sums: &[i32], offset: i32, scale: f32, exact: bool, y0: u8, out: &mut [u8]) {
    use std::arch::aarch64::*;
    let n = sums.len().min(out.len());
    let full = n / 16 * 16;
    for i in (0..full).step_by(16) {
        // SAFETY: `i + 16 <= n`: sixteen sums in, sixteen bytes out.
        unsafe {
            let mut q = [vdupq_n_u32(0); 4];
            for (k, q) in q.iter_mut().enumerate() {
                let v = vld1q_s32(sums.as_ptr().add(i + 4 * k));
                *q = requant4(v, offset, scale, exact, y0);
            }
            let lo = vcombine_u16(vmovn_u32(q[0]), vmovn_u32(q[1]));
            let hi = vcombine_u16(vmovn_u32(q[2]), vmovn_u32(q[3]));
            vst1q_u8(out.as_mut_ptr().add(i), vcombine_u8(vmovn_u16(lo), vmovn_u16(hi)));
        }
    }
    for (o, &s) in out[full..n].iter_mut().zip(&sums[full..n]) {
        *o = requant_one(s + offset, scale, exact, y0);
    }
}

/// Four lanes of [`requantise`] on NEON, as u32 values in `0..=255`.
#[cfg(target_arch = "aarch64")]
#[inline(always)]
fn requant4(
    v: std::arch::aarch64::int32x4_t,
    offset: i32,
    scale: f32,
    exact: bool,
    y0: u8,
) -> std::arch::aarch64::uint32x4_t {
    use std::arch::aarch64::*;
    // SAFETY: NEON is part of the aarch64 baseline.
    unsafe {
        let x = vcvtq_f32_s32(vaddq_s32(v, vdupq_n_s32(offset)));
        let sc = vdupq_n_f32(scale);
        let p = vmulq_f32(x, sc);
        let mut r = vrndnq_f32(p);
        if exact {
            let d = vsubq_f32(p, r);
            let half = vceqq_f32(vabsq_f32(d), vdupq_n_f32(0.5));
            // Halves are rare: most groups of four have none.
            if vmaxvq_u32(half) != 0 {
                let error = vfmsq_f32(p, x, sc); // p − x·scale, fused: minus the error
                let past = vcltq_f32(vmulq_f32(d, error), vdupq_n_f32(0.0));
                let add = vandq_u32(vandq_u32(half, past), vreinterpretq_u32_f32(vaddq_f32(d, d)));
                r = vaddq_f32(r, vreinterpretq_f32_u32(add));
            }
        }
        let f = vaddq_f32(r, vdupq_n_f32(y0 as f32));
        let f = vminq_f32(vmaxq_f32(f, vdupq_n_f32(0.0)), vdupq_n_f32(255.0));
        vcvtq_u32_f32(f)
    }
}

/// [`requantise`], the portable form (the f32 product vectorised by the compiler; the exact one
/// in tract's fixed point).
#[cfg(not(target_arch = "aarch64"))]
fn requantise_portable(sums: &[i32], offset: i32, scale: f32, exact: bool, y0: u8, out: &mut [u8]) {
    // One loop per mode, so that the f32 one stays free of the fixed-point branch and vectorises.
    if exact {
        for (o, &s) in out.iter_mut().zip(sums) {
            *o = requant_one(s + offset, scale, true, y0);
        }
    } else {
        for (o, &s) in out.iter_mut().zip(sums) {
            *o = requant_one(s + offset, scale, false, y0);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The vectorised requantisation (AVX-512 or AVX2 on x86, NEON on aarch64) gives the scalar
    /// formula's bytes, for both products: on sums that include every tie of a scale (where the
    /// f32 product and the exact one round apart), sums that saturate either way, and lengths
    /// with and without a remainder past the vectors.
    #[test]
    fn requantise_equals_the_scalar_formula() {
        // The form `PRL_ISA` leaves (AVX-512, AVX2, NEON or the portable loop): each ISA run of
        // the tests reaches another.
        let scale = 0.0069588f32 * (0.0007929764 / 32.0) / 0.0028860883;
        let ties = tie_sums(scale);
        assert!(ties.len() >= 8, "the case needs sums that round apart: {}", ties.len());
        let mut sums: Vec<i32> = (0..2000).map(|i| (i * 7919 % 60001) - 30000).collect();
        sums.extend(&ties);
        sums.extend([i32::MAX - 100, i32::MIN + 100, 1 << 24, -(1 << 24), 1 << 30]);
        for (exact, offset) in [(true, 0), (true, -37), (false, 0), (false, 91)] {
            for n in [0usize, 1, 15, 16, 17, 33, sums.len()] {
                let want: Vec<u8> = sums[..n].iter().map(|&s| requant_one(s + offset, scale, exact, 100)).collect();
                let mut got = vec![0xAAu8; n];
                requantise(&sums[..n], offset, scale, exact, 100, &mut got);
                assert_eq!(got, want, "{n} sums, exact {exact}, offset {offset}");
            }
        }
    }
}
