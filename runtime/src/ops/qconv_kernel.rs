//! The inner loops of [`super::PackedQConv`]: the AVX-512 VNNI tiles (8 output channels x 32
//! positions, `vpdpbusd` on words of four u8 inputs and four i8 weights), the AVX2 tiles (the
//! same sums by `vpmaddwd` on the words' bytes widened to 16 bits), the aarch64 SDOT tiles
//! (8 output channels x 8 positions, `sdot` on words of four i8 inputs and four i8 weights) and
//! the requantisation they share (16 lanes on AVX-512, 8 on AVX2, bit for bit the scalar
//! formula).

#[cfg(any(target_arch = "x86_64", target_arch = "aarch64"))]
use super::qconv::{PX, ROWS};
use tract_nnef::tract_core::tract_linalg::{mmm::RoundingPolicy, Scaler};

/// Whether [`requant_one`]'s exact rounding is vectorised for one `scale` on sums at most
/// `bound` in magnitude (`255·Σ|w| + |bias|` over a layer's output channels): from 2^-15, so
/// that a sum too large for an f32 (2^24 and up) saturates either way, while `bound · scale`
/// stays below 2^31, so that tract's fixed-point product (an i64 cut to i32) does not wrap. A
/// layer with one scale outside this stays with tract. (Scales of 1 and more come where an
/// output's calibrated range is narrow against its input's and weights', e.g. clipped by
/// `--method percentile`.)
pub(super) fn exact_fits(scale: f32, bound: i64) -> bool {
    scale >= 1.0 / 32768.0 && (scale as f64) * (bound as f64) < 2f64.powi(31)
}

/// One requantised output: `sat_u8(round_half_even(sum · scale) + y0)`, with the product as
/// tract takes it. `exact` (one scale for every output channel): the exact product, as tract's
/// `Scaler` (fixed point, rounded half to even); else the f32 product rounded, as tract's
/// per-channel `Scale`. The two differ where the f32 product lands on a half that the exact
/// one misses.
#[inline]
pub(super) fn requant_one(sum: i32, scale: f32, exact: bool, y0: u8) -> u8 {
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
pub(super) fn tie_sums(scale: f32) -> Vec<i32> {
    let scaler = Scaler::new(scale, RoundingPolicy::Even);
    let limit = (100.0 / scale) as i32;
    (-limit..limit).filter(|&x| (x as f32 * scale).round_ties_even() as i32 != x * scaler).collect()
}

/// Weight scales `k` whose requantisation scales by tract's two forms (`x · k / y` and `(k · x)
/// · (1 / y)`, see [`super::qconv::requant_scales`]) part, each with a sum whose products
/// with the two round apart (rounded exactly, as tract's `Scaler`, with `exact`) and outputs
/// within 90 of the zero point 100 (unsaturated): the test cases that tell the forms apart.
#[cfg(test)]
pub(super) fn parting_scales(x_scale: f32, y_scale: f32, exact: bool) -> impl Iterator<Item = (f32, i32)> {
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
pub(super) fn requantise(sums: &[i32], offset: i32, scale: f32, exact: bool, y0: u8, out: &mut [u8]) {
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
fn requant8(
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
pub(super) fn requant16(
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
pub(super) fn requant_lanes(
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

/// The bytes of a word buffer.
pub(super) fn bytemuck_words(words: &mut [u32]) -> &mut [u8] {
    // SAFETY: u32 has no padding and any byte pattern is a valid u32; the length is exact.
    unsafe { std::slice::from_raw_parts_mut(words.as_mut_ptr().cast::<u8>(), words.len() * 4) }
}

/// `sums[tile][r][q] = Σ_taps words[tap + tile·PX + q] · weights[tap][r]` (four u8 x i8
/// products per word).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512vnni")]
pub(super) unsafe fn tiles_vnni(words: &[u32], taps: &[usize], weights: &[i32], positions: usize, sums: &mut [i32]) {
    use std::arch::x86_64::*;
    for (tile, sums) in sums.chunks_exact_mut(PX * ROWS).enumerate().take(positions.div_ceil(PX)) {
        // SAFETY: the caller guarantees the loads are in bounds.
        unsafe {
            let a = tile_vnni(words.as_ptr().add(tile * PX).cast(), taps, weights);
            let s = sums.as_mut_ptr();
            for (q, a) in a.iter().enumerate() {
                _mm512_storeu_si512(s.add(16 * q).cast(), *a);
            }
        }
    }
}

/// Where the requantising tiles ([`tiles_vnni_requant`], [`tiles_avx2_requant`]) store their
/// bytes and how they requantise them: `rows` (at most `ROWS`) channels' planes of `plane`
/// bytes from `out` (or, with `positions_first`, each position's `rows` bytes side by side at
/// `out + q·stride`: a matrix product's rows of channels), with each channel's offset and
/// scale, the rounding ([`requant_one`]'s `exact`) and the output zero point.
#[cfg(target_arch = "x86_64")]
#[derive(Clone, Copy)]
pub(super) struct Planes<'a> {
    pub out: *mut u8,
    pub plane: usize,
    pub rows: usize,
    pub offset: &'a [i32],
    pub scale: &'a [f32],
    pub exact: bool,
    pub y0: u8,
    /// The bytes are stored positions first, each position's `stride` apart.
    pub positions_first: Option<usize>,
}

/// `ROWS` channels' bytes of up to 16 positions (`bytes[r]`'s byte `q`: channel `r`, position
/// `q`) stored positions first: position `q < n`'s `rows` bytes at `out + q·stride` (SSE2's
/// byte, word and dword unpacks transpose them: a scalar transpose after the product took a
/// third of HMG's products on two threads).
///
/// # Safety
/// `out + q·stride + r` is writable for `q < n <= 16`, `r < rows <= ROWS`.
#[cfg(target_arch = "x86_64")]
#[inline]
unsafe fn store_positions_first(
    bytes: &[std::arch::x86_64::__m128i; ROWS],
    n: usize,
    rows: usize,
    out: *mut u8,
    stride: usize,
) {
    use std::arch::x86_64::*;
    debug_assert!(n <= 16 && rows <= ROWS);
    // SAFETY: SSE2 is part of x86_64; the caller guarantees the stores' bounds.
    unsafe {
        let pair = |i: usize| (_mm_unpacklo_epi8(bytes[i], bytes[i + 1]), _mm_unpackhi_epi8(bytes[i], bytes[i + 1]));
        let ((a0, a1), (b0, b1), (c0, c1), (d0, d1)) = (pair(0), pair(2), pair(4), pair(6));
        // Four channels of four positions a register: channels 0-3 (e), 4-7 (f).
        let e = [
            _mm_unpacklo_epi16(a0, b0),
            _mm_unpackhi_epi16(a0, b0),
            _mm_unpacklo_epi16(a1, b1),
            _mm_unpackhi_epi16(a1, b1),
        ];
        let f = [
            _mm_unpacklo_epi16(c0, d0),
            _mm_unpackhi_epi16(c0, d0),
            _mm_unpacklo_epi16(c1, d1),
            _mm_unpackhi_epi16(c1, d1),
        ];
        for q in 0..n {
            // Positions 2i and 2i + 1's eight channels.
            let g =
                if q % 4 < 2 { _mm_unpacklo_epi32(e[q / 4], f[q / 4]) } else { _mm_unpackhi_epi32(e[q / 4], f[q / 4]) };
            let g = if q % 2 == 0 { g } else { _mm_unpackhi_epi64(g, g) };
            let at = out.add(q * stride);
            if rows == ROWS {
                _mm_storel_epi64(at.cast(), g);
            } else {
                let v = (_mm_cvtsi128_si64(g) as u64).to_le_bytes();
                std::ptr::copy_nonoverlapping(v.as_ptr(), at, rows);
            }
        }
    }
}

#[cfg(target_arch = "x86_64")]
impl<'a> Planes<'a> {
    /// These planes, checked to hold `positions` outputs of every channel and the channels'
    /// offsets and scales.
    fn checked(&self, positions: usize) -> Planes<'a> {
        let rows = self.rows;
        assert!(rows <= ROWS && self.offset.len() >= rows && self.scale.len() >= rows && positions <= self.plane);
        assert!(self.positions_first.is_none_or(|stride| stride >= rows));
        *self
    }
}

/// One tile's sums on VNNI: `ROWS` channels x `PX` positions from `base` (two registers a
/// channel), over every tap.
///
/// # Safety
/// The CPU has AVX-512F and VNNI; `PX` words from `base + t` are readable for every tap `t`;
/// `weights` holds `ROWS` words per tap.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512vnni")]
#[inline]
unsafe fn tile_vnni(base: *const i32, taps: &[usize], weights: &[i32]) -> [std::arch::x86_64::__m512i; 2 * ROWS] {
    use std::arch::x86_64::*;
    let mut a = [_mm512_setzero_si512(); 2 * ROWS];
    let mut w = weights.as_ptr();
    for &t in taps {
        // SAFETY: the caller's promise.
        unsafe {
            let x0 = _mm512_loadu_si512(base.add(t).cast());
            let x1 = _mm512_loadu_si512(base.add(t + 16).cast());
            for r in 0..ROWS {
                let b = _mm512_set1_epi32(*w.add(r));
                a[2 * r] = _mm512_dpbusd_epi32(a[2 * r], x0, b);
                a[2 * r + 1] = _mm512_dpbusd_epi32(a[2 * r + 1], x1, b);
            }
            w = w.add(ROWS);
        }
    }
    a
}

/// One group of 8 positions' sums on AVX2 ([`tiles_avx2`]'s products): `ROWS` channels from
/// `base`, over every tap.
///
/// # Safety
/// The CPU has AVX2; 8 words from `base + t` are readable for every tap `t`; `pairs` holds
/// `2·ROWS` words per tap.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
#[inline]
unsafe fn tile_avx2(base: *const i32, taps: &[usize], pairs: &[i32]) -> [std::arch::x86_64::__m256i; ROWS] {
    use std::arch::x86_64::*;
    let low_bytes = _mm256_set1_epi32(0x00ff_00ff);
    let mut a = [_mm256_setzero_si256(); ROWS];
    let mut w = pairs.as_ptr();
    for &t in taps {
        // SAFETY: the caller's promise.
        unsafe {
            let x = _mm256_loadu_si256(base.add(t).cast());
            let (lo, hi) = (_mm256_and_si256(x, low_bytes), _mm256_srli_epi16::<8>(x));
            for (r, a) in a.iter_mut().enumerate() {
                let p = _mm256_madd_epi16(lo, _mm256_set1_epi32(*w.add(2 * r)));
                let q = _mm256_madd_epi16(hi, _mm256_set1_epi32(*w.add(2 * r + 1)));
                *a = _mm256_add_epi32(*a, _mm256_add_epi32(p, q));
            }
            w = w.add(2 * ROWS);
        }
    }
    a
}

/// [`tiles_vnni`] with each tile's sums requantised where they are made ([`requant_lanes`]:
/// the same bytes) and stored as bytes in their channels' planes (`out + r·plane`), for layers
/// whose `positions` are the plane's outputs in order (1x1, no padding): no sums stored and
/// read back, no call per row of a tile. Where and how: [`Planes`]. (NanoTrack's 1x1 layers spent more time requantising sums
/// from memory, 32 at a time, than multiplying: 24 -> 96 channels on 32 x 32, 47 µs, of which
/// 20 in the tiles.)
///
/// # Safety
/// The CPU has AVX-512F and VNNI; every tile's `PX` words from each tap are in `words`;
/// `weights` holds `ROWS` words per tap; for `r < p.rows`, `q < positions`, the byte of channel
/// `r` at position `q` is writable: `p.out + r·p.plane + q` (planes), or with
/// `p.positions_first = Some(stride)`, `p.out + q·stride + r` (rows of channels).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512vnni")]
pub(super) unsafe fn tiles_vnni_requant(words: &[u32], taps: &[usize], weights: &[i32], positions: usize, p: &Planes) {
    use std::arch::x86_64::*;
    let Planes { out, plane, rows, offset, scale, exact, y0, positions_first } = p.checked(positions);
    for tile in 0..positions.div_ceil(PX) {
        // SAFETY: the caller guarantees the loads are in bounds, and the stores: within the
        // first `positions` outputs of each of the `rows` channels.
        unsafe {
            let a = tile_vnni(words.as_ptr().add(tile * PX).cast(), taps, weights);
            // The tile's real positions: all 32 but in the last.
            let n = (positions - tile * PX).min(PX);
            let keep = [(1u32 << n.min(16)) - 1, (1u32 << n.saturating_sub(16)) - 1].map(|m| m as u16);
            for h in 0..2 {
                if keep[h] == 0 {
                    continue;
                }
                let first = tile * PX + 16 * h;
                let mut bytes = [_mm_setzero_si128(); ROWS];
                for r in 0..rows {
                    let (o, c) = (_mm512_set1_epi32(offset[r]), _mm512_set1_ps(scale[r]));
                    let q = requant_lanes(a[2 * r + h], o, c, exact, y0);
                    match positions_first {
                        None => _mm512_mask_cvtepi32_storeu_epi8(out.add(r * plane + first).cast(), keep[h], q),
                        Some(_) => bytes[r] = _mm512_cvtepi32_epi8(q),
                    }
                }
                if let Some(stride) = positions_first {
                    store_positions_first(&bytes, (n - 16 * h).min(16), rows, out.add(first * stride), stride);
                }
            }
        }
    }
}

/// A weight word `[w0, w1, w2, w3]` (i8) as the two i32 words of i16 pairs [`tiles_avx2`]
/// multiplies: `[w0, w2]` and `[w1, w3]`, each sign-extended.
pub(super) fn avx2_pairs(word: i32) -> [i32; 2] {
    let [w0, w1, w2, w3] = word.to_ne_bytes().map(|b| b as i8 as i16 as u16 as u32);
    [(w0 | (w2 << 16)) as i32, (w1 | (w3 << 16)) as i32]
}

/// `sums[tile][r][q]` as [`tiles_vnni`] gives them (the same i32 sums), on AVX2 without VNNI:
/// each input word's four bytes are split into two words of two u16 (bytes 0 and 2, bytes 1
/// and 3), and `vpmaddwd` multiplies them exactly by the weight's matching i16 pairs
/// (`pairs`: [`avx2_pairs`] of every weight word, `[tap][r][2]`). A tile's 32 positions go 8
/// at a time: 8 accumulators (one per output channel), one input load per tap.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
pub(super) unsafe fn tiles_avx2(words: &[u32], taps: &[usize], pairs: &[i32], positions: usize, sums: &mut [i32]) {
    use std::arch::x86_64::*;
    for (tile, sums) in sums.chunks_exact_mut(PX * ROWS).enumerate().take(positions.div_ceil(PX)) {
        for sub in 0..PX / 8 {
            // SAFETY: the caller guarantees every tile's `PX` words from each tap are in
            // `words`; `pairs` holds `2·ROWS` words per tap; `sums` holds a whole tile.
            unsafe {
                let base = words.as_ptr().add(tile * PX + sub * 8).cast::<i32>();
                let a = tile_avx2(base, taps, pairs);
                let s = sums.as_mut_ptr();
                for (r, a) in a.iter().enumerate() {
                    _mm256_storeu_si256(s.add(r * PX + sub * 8).cast(), *a);
                }
            }
        }
    }
}

/// [`tiles_avx2`] with each group of 8 positions' sums requantised in registers ([`requant8`]:
/// the same bytes) and stored in their channels' planes, as [`tiles_vnni_requant`] does on
/// VNNI (same contract, `pairs` as [`tiles_avx2`] takes them).
///
/// # Safety
/// As [`tiles_vnni_requant`], the CPU having AVX2 and FMA.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
pub(super) unsafe fn tiles_avx2_requant(words: &[u32], taps: &[usize], pairs: &[i32], positions: usize, p: &Planes) {
    use std::arch::x86_64::*;
    let Planes { out, plane, rows, offset, scale, exact, y0, positions_first } = p.checked(positions);
    let y = _mm256_set1_ps(y0 as f32);
    for first in (0..positions).step_by(8) {
        // SAFETY: the caller guarantees every tile's `PX` words from each tap are in `words`
        // (8 from `first` among them); `pairs` holds `2·ROWS` words per tap; the stores stay
        // within the first `positions` outputs of each of the `rows` channels.
        unsafe {
            let base = words.as_ptr().add(first).cast::<i32>();
            let a = tile_avx2(base, taps, pairs);
            let n = (positions - first).min(8);
            let mut bytes = [_mm_setzero_si128(); ROWS];
            for (r, a) in a.iter().enumerate().take(rows) {
                let b = requant8(*a, _mm256_set1_epi32(offset[r]), _mm256_set1_ps(scale[r]), y, exact);
                if positions_first.is_some() {
                    bytes[r] = b;
                    continue;
                }
                let at = out.add(r * plane + first);
                if n == 8 {
                    _mm_storel_epi64(at.cast(), b);
                } else {
                    let bytes = (_mm_cvtsi128_si64(b) as u64).to_le_bytes();
                    std::ptr::copy_nonoverlapping(bytes.as_ptr(), at, n);
                }
            }
            if let Some(stride) = positions_first {
                store_positions_first(&bytes, n, rows, out.add(first * stride), stride);
            }
        }
    }
}

#[cfg(not(target_arch = "x86_64"))]
pub(super) unsafe fn tiles_avx2(_: &[u32], _: &[usize], _: &[i32], _: usize, _: &mut [i32]) {
    unreachable!("the AVX2 words path is x86_64's")
}

#[cfg(not(target_arch = "x86_64"))]
pub(super) unsafe fn tiles_vnni(_: &[u32], _: &[usize], _: &[i32], _: usize, _: &mut [i32]) {
    unreachable!("PackedQConv is only made on x86_64 with AVX-512 VNNI")
}

/// `sums[tile][r][q]` as [`tiles_vnni`] gives them, on aarch64's signed dot product: `words` hold
/// the inputs with their top bit flipped (`x − 128` as i8; SDOT multiplies i8 by i8, and the
/// A78AE has no mixed-sign USDOT), so each sum is `Σ w·x − 128·Σ w` (the caller adds the
/// second term back). A tile's 32 positions go 8 at a time: 16 accumulators (8 channels x 2
/// registers of 4 positions), two input and two weight loads per tap, each weight word taken by
/// lane (`SDOT v.4s, v.16b, v.4b[l]`).
#[cfg(target_arch = "aarch64")]
#[target_feature(enable = "neon,dotprod")]
pub(super) unsafe fn tiles_sdot(words: &[u32], taps: &[usize], weights: &[i32], positions: usize, sums: &mut [i32]) {
    use std::arch::aarch64::*;
    use std::arch::asm;
    /// `acc += dot4(x words, weight word l of w)`, lane by lane.
    macro_rules! sdot {
        ($acc:expr, $x:expr, $w:expr, $l:literal) => {
            asm!("sdot {a:v}.4s, {x:v}.16b, {w:v}.4b[{l}]", a = inout(vreg) $acc, x = in(vreg) $x, w = in(vreg) $w,
                 l = const $l, options(pure, nomem, nostack))
        };
    }
    for (tile, sums) in sums.chunks_exact_mut(PX * ROWS).enumerate().take(positions.div_ceil(PX)) {
        for sub in 0..PX / 8 {
            // SAFETY: the caller guarantees every tile's `PX` words from each tap are in
            // `words`; `weights` holds `ROWS` words per tap; `sums` holds a whole tile.
            unsafe {
                let base = words.as_ptr().add(tile * PX + sub * 8);
                let mut a = [vdupq_n_s32(0); 2 * ROWS];
                let mut w = weights.as_ptr();
                for &t in taps {
                    let x0 = vld1q_s8(base.add(t).cast());
                    let x1 = vld1q_s8(base.add(t + 4).cast());
                    let (w0, w1) = (vld1q_s8(w.cast()), vld1q_s8(w.add(4).cast()));
                    sdot!(a[0], x0, w0, 0);
                    sdot!(a[1], x1, w0, 0);
                    sdot!(a[2], x0, w0, 1);
                    sdot!(a[3], x1, w0, 1);
                    sdot!(a[4], x0, w0, 2);
                    sdot!(a[5], x1, w0, 2);
                    sdot!(a[6], x0, w0, 3);
                    sdot!(a[7], x1, w0, 3);
                    sdot!(a[8], x0, w1, 0);
                    sdot!(a[9], x1, w1, 0);
                    sdot!(a[10], x0, w1, 1);
                    sdot!(a[11], x1, w1, 1);
                    sdot!(a[12], x0, w1, 2);
                    sdot!(a[13], x1, w1, 2);
                    sdot!(a[14], x0, w1, 3);
                    sdot!(a[15], x1, w1, 3);
                    w = w.add(ROWS);
                }
                let s = sums.as_mut_ptr();
                for r in 0..ROWS {
                    vst1q_s32(s.add(r * PX + sub * 8), a[2 * r]);
                    vst1q_s32(s.add(r * PX + sub * 8 + 4), a[2 * r + 1]);
                }
            }
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
