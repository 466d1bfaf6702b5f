//! The inner loops of [`super::PackedQConv`]: the AVX-512 VNNI tiles (8 output channels x 32
//! positions, `vpdpbusd` on words of four u8 inputs and four i8 weights), the AVX2 tiles (the
//! same sums by `vpmaddwd` on the words' bytes widened to 16 bits), the aarch64 SDOT tiles
//! (8 output channels x 8 positions, `sdot` on words of four i8 inputs and four i8 weights);
//! the requantisation they share is in [`requant`] (16 lanes on AVX-512, 8 on AVX2, 4 on NEON,
//! bit for bit the scalar formula).

#[cfg(any(target_arch = "x86_64", target_arch = "aarch64"))]
use super::qconv::{PX, ROWS};

mod requant;

#[cfg(target_arch = "x86_64")]
use requant::requant8;
pub(super) use requant::{exact_fits, requant_one, requantise};
#[cfg(test)]
pub(super) use requant::{parting_scales, tie_sums};
#[cfg(target_arch = "x86_64")]
pub(super) use requant::{requant16, requant_lanes};

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
