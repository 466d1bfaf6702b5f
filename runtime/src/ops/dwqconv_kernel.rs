//! The inner loops of [`super::DepthwiseQConv`] on AVX-512 VNNI with VBMI: the rows' copy into
//! the padded plane (through the byte table where there is one) and the output rows, sixteen
//! columns by four rows a step, `vpermb` making words of four taps and `vpdpbusd` summing them,
//! requantised in registers.

use std::arch::x86_64::*;

use super::conv::ConvShape;
use super::dwqconv::LANES;
use super::qconv_kernel::requant_lanes;

/// The byte permutes that make sixteen words of four consecutive input bytes, for stride 1
/// and 2: word `l`'s byte `t` is the input `l·s + t` bytes on.
const PERMUTE: [[u8; 64]; 2] = {
    let mut p = [[0u8; 64]; 2];
    let mut b = 0;
    while b < 64 {
        p[0][b] = (b / 4 + b % 4) as u8;
        p[1][b] = ((b / 4) * 2 + b % 4) as u8;
        b += 1;
    }
    p
};

/// `src` (`[h, w]` bytes) into the interior of the padded plane `pad`, 64 bytes at a time
/// (a row of a few dozen bytes is not worth a call to `memcpy`), through `table` where
/// `TABLE` (`vpermi2b` looks up 128 entries, twice, and the top bit picks).
///
/// # Safety
/// The CPU has AVX-512F, BW and VBMI; `src` is `h · w` bytes and `pad` the padded plane of
/// `s`.
#[target_feature(enable = "avx512f,avx512bw,avx512vbmi")]
pub(super) unsafe fn copy_rows<const TABLE: bool>(s: &ConvShape, src: &[u8], pad: &mut [u8], table: &[u8; 256]) {
    let (_, wp) = s.padded();
    // SAFETY: 256 bytes, four loads of 64.
    let t: [__m512i; 4] = std::array::from_fn(|k| unsafe { _mm512_loadu_si512(table.as_ptr().add(64 * k).cast()) });
    for (y, row) in src.chunks_exact(s.w).enumerate() {
        let at = (y + s.pad[0]) * wp + s.pad[1];
        let to = &mut pad[at..at + s.w];
        let mut x = 0;
        while x < s.w {
            let n = (s.w - x).min(64);
            let keep: u64 = if n == 64 { u64::MAX } else { (1u64 << n) - 1 };
            // SAFETY: `n` bytes from `x` on within `row` and within `to`.
            unsafe {
                let mut v = _mm512_maskz_loadu_epi8(keep, row.as_ptr().add(x).cast());
                if TABLE {
                    let lo = _mm512_permutex2var_epi8(t[0], v, t[1]);
                    let hi = _mm512_permutex2var_epi8(t[2], v, t[3]);
                    v = _mm512_mask_blend_epi8(_mm512_movepi8_mask(v), lo, hi);
                }
                _mm512_mask_storeu_epi8(to.as_mut_ptr().add(x).cast(), keep, v);
            }
            x += n;
        }
    }
}

/// Every output row of one channel: `pad` the padded plane (`[hp, wp]` bytes and slack),
/// `words` the kernel's words (`kh` rows of `⌈kw / 4⌉`), `(offset, scale, exact, y0)` the
/// requantisation, `dst` the `[oh, ow]` output bytes.
///
/// # Safety
/// The CPU has AVX-512F, BW, VL, VNNI and VBMI; `pad` is the padded plane of `s` with
/// [`super::dwqconv::SLACK`] bytes after it, `dst` is `oh · ow` bytes.
#[target_feature(enable = "avx512f,avx512bw,avx512vl,avx512vnni,avx512vbmi")]
pub(super) unsafe fn plane(s: &ConvShape, pad: &[u8], words: &[i32], q: (i32, f32, bool, u8), dst: &mut [u8]) {
    let (oh, ow) = s.out();
    // Word `l`'s byte `t` is the input `l·s + t` bytes on.
    let idx = if s.stride == 1 { &PERMUTE[0] } else { &PERMUTE[1] };
    // SAFETY: 64 bytes.
    let idx = unsafe { _mm512_loadu_si512(idx.as_ptr().cast()) };
    let mut y = 0;
    while y + 4 <= oh {
        // SAFETY: as the caller guarantees, for rows `y .. y + 4`.
        unsafe { rows::<4>(s, pad, words, q, dst, y, idx) };
        y += 4;
    }
    while y < oh {
        // SAFETY: as above, for row `y`.
        unsafe { rows::<1>(s, pad, words, q, dst, y, idx) };
        y += 1;
    }
    debug_assert_eq!(dst.len(), oh * ow);
}

/// Output rows `y .. y + R`, sixteen columns at a time: `R` independent sums, so that the
/// dot products' latency overlaps.
#[target_feature(enable = "avx512f,avx512bw,avx512vl,avx512vnni,avx512vbmi")]
#[inline]
#[allow(clippy::too_many_arguments)]
unsafe fn rows<const R: usize>(
    s: &ConvShape,
    pad: &[u8],
    words: &[i32],
    (offset, scale, exact, y0): (i32, f32, bool, u8),
    dst: &mut [u8],
    y: usize,
    idx: __m512i,
) {
    let (_, ow) = s.out();
    let (_, wp) = s.padded();
    let (kh, groups, st) = (s.kh, s.kw.div_ceil(4), s.stride);
    let (off, sc) = (_mm512_set1_epi32(offset), _mm512_set1_ps(scale));
    let base = pad.as_ptr();
    let mut x0 = 0;
    while x0 < ow {
        let n = (ow - x0).min(LANES);
        let mut acc = [_mm512_setzero_si512(); R];
        for i in 0..kh {
            for g in 0..groups {
                let w = _mm512_set1_epi32(words[i * groups + g]);
                for (r, acc) in acc.iter_mut().enumerate() {
                    let at = ((y + r) * st + i) * wp + x0 * st + 4 * g;
                    // SAFETY: `at` is a position of the padded plane (a row within its
                    // `hp` rows); the 64 bytes from it are within the plane and its slack.
                    let v = unsafe { _mm512_loadu_si512(base.add(at).cast()) };
                    *acc = _mm512_dpbusd_epi32(*acc, _mm512_permutexvar_epi8(idx, v), w);
                }
            }
        }
        let keep = if n == LANES { u16::MAX } else { (1u16 << n) - 1 };
        for (r, acc) in acc.iter().enumerate() {
            let bytes = _mm512_cvtepi32_epi8(requant_lanes(*acc, off, sc, exact, y0));
            let o = &mut dst[(y + r) * ow + x0..(y + r) * ow + x0 + n];
            // SAFETY: `n` bytes within `dst` (the slice above).
            unsafe { _mm_mask_storeu_epi8(o.as_mut_ptr().cast(), keep, bytes) };
        }
        x0 += n;
    }
}
