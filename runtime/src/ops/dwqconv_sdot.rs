//! The inner loops of [`super::DepthwiseQConv`] on aarch64 with the dot product (`SDOT`; the
//! Jetson Orin NX's Cortex-A78AE has it, not the mixed-sign `USDOT`): the rows' copy into the
//! padded plane with each byte's top bit flipped (`x − 128` as i8; through the byte table where
//! there is one), and the output rows, sixteen columns by four rows a step: `TBL` makes four
//! registers of four words of four consecutive taps (every second byte for stride 2) from 48
//! bytes of the padded plane, and `SDOT` multiplies each word by the kernel row's four weights.
//! The sums are `Σ (x − 128)·w`; the caller's offset adds `128·Σw` back, and each row's
//! sixteen are requantised by `PackedQConv`'s NEON requantisation (in registers instead, four
//! lanes at a time: 0.24 M more instructions a NanoTrack step under qemu).

use std::arch::aarch64::*;
use std::arch::asm;

use super::conv::ConvShape;
use super::dwqconv::LANES;
use super::qconv_kernel::requantise;

/// The byte lookups that make, for stride 1 and 2, four registers of four words: register
/// `k`'s word `j` byte `t` is the input `(4k + j)·s + t` bytes on (at most 18 for stride 1: two
/// table registers; 33 for stride 2: three).
const LOOKUP: [[[u8; 16]; 4]; 2] = {
    let mut l = [[[0u8; 16]; 4]; 2];
    let mut k = 0;
    while k < 4 {
        let mut b = 0;
        while b < 16 {
            l[0][k][b] = (4 * k + b / 4 + b % 4) as u8;
            l[1][k][b] = ((4 * k + b / 4) * 2 + b % 4) as u8;
            b += 1;
        }
        k += 1;
    }
    l
};

/// `src` (`[h, w]` bytes) into the interior of the padded plane `pad`, each byte through
/// `table` where given and its top bit flipped. The table is looked up sixteen bytes at a time:
/// `TBL` on four registers covers 64 entries, and three `TBX` (which leave a lane whose index
/// is out of their range as it was) the other 192 (the byte loop took 1.9 M instructions of a
/// NanoTrack `--depthwise` step under qemu).
pub(super) fn copy_rows(s: &ConvShape, src: &[u8], pad: &mut [u8], table: Option<&[u8; 256]>) {
    let (_, wp) = s.padded();
    // SAFETY: 64 bytes from each of the table's four quarters.
    let quarters = table.map(|t| {
        std::array::from_fn::<_, 4, _>(|k| unsafe {
            let p = t.as_ptr().add(64 * k);
            uint8x16x4_t(vld1q_u8(p), vld1q_u8(p.add(16)), vld1q_u8(p.add(32)), vld1q_u8(p.add(48)))
        })
    });
    for (y, row) in src.chunks_exact(s.w).enumerate() {
        let at = (y + s.pad[0]) * wp + s.pad[1];
        let to = &mut pad[at..at + s.w];
        match (table, &quarters) {
            (Some(tab), Some(q)) => {
                let mut ins = row.chunks_exact(16);
                let mut outs = to.chunks_exact_mut(16);
                for (i, o) in (&mut ins).zip(&mut outs) {
                    // SAFETY: sixteen bytes in, sixteen out.
                    unsafe {
                        let v = vld1q_u8(i.as_ptr());
                        let mut x = vqtbl4q_u8(q[0], v);
                        x = vqtbx4q_u8(x, q[1], vsubq_u8(v, vdupq_n_u8(64)));
                        x = vqtbx4q_u8(x, q[2], vsubq_u8(v, vdupq_n_u8(128)));
                        x = vqtbx4q_u8(x, q[3], vsubq_u8(v, vdupq_n_u8(192)));
                        vst1q_u8(o.as_mut_ptr(), veorq_u8(x, vdupq_n_u8(0x80)));
                    }
                }
                let rest = outs.into_remainder().iter_mut().zip(ins.remainder());
                rest.for_each(|(t, &v)| *t = tab[v as usize] ^ 0x80);
            }
            _ => to.iter_mut().zip(row).for_each(|(t, &v)| *t = v ^ 0x80),
        }
    }
}

/// Every output row of one channel: `pad` the padded plane of flipped bytes (`[hp, wp]` and
/// slack), `words` the kernel's words (`kh` rows of `⌈kw / 4⌉`), `(offset, scale, exact, y0)`
/// the requantisation (`offset` with `128·Σw` in), `dst` the `[oh, ow]` output bytes.
///
/// # Safety
/// The CPU has the dot product; `pad` is the padded plane of `s` with
/// [`super::dwqconv::SLACK`] bytes after it, `dst` is `oh · ow` bytes.
#[target_feature(enable = "neon,dotprod")]
pub(super) unsafe fn plane(s: &ConvShape, pad: &[u8], words: &[i32], q: (i32, f32, bool, u8), dst: &mut [u8]) {
    let (oh, ow) = s.out();
    let lookup = &LOOKUP[s.stride - 1];
    // SAFETY: 16 bytes each.
    let idx: [uint8x16_t; 4] = std::array::from_fn(|k| unsafe { vld1q_u8(lookup[k].as_ptr()) });
    let mut y = 0;
    // Stride 1 reads 19 bytes a step (two table registers), stride 2 reads 34 (three).
    while y + 4 <= oh {
        // SAFETY: as the caller guarantees, for rows `y .. y + 4`.
        unsafe {
            match s.stride {
                1 => rows::<4, false>(s, pad, words, q, dst, y, &idx),
                _ => rows::<4, true>(s, pad, words, q, dst, y, &idx),
            }
        }
        y += 4;
    }
    while y < oh {
        // SAFETY: as above, for row `y`.
        unsafe {
            match s.stride {
                1 => rows::<1, false>(s, pad, words, q, dst, y, &idx),
                _ => rows::<1, true>(s, pad, words, q, dst, y, &idx),
            }
        }
        y += 1;
    }
    debug_assert_eq!(dst.len(), oh * ow);
}

/// Output rows `y .. y + R`, sixteen columns at a time (four registers of four sums per row):
/// `4R` independent sums, so that the dot products' latency overlaps. `WIDE`: the words'
/// bytes span three registers (stride 2), else two.
#[target_feature(enable = "neon,dotprod")]
#[inline]
#[allow(clippy::too_many_arguments)]
unsafe fn rows<const R: usize, const WIDE: bool>(
    s: &ConvShape,
    pad: &[u8],
    words: &[i32],
    (offset, scale, exact, y0): (i32, f32, bool, u8),
    dst: &mut [u8],
    y: usize,
    idx: &[uint8x16_t; 4],
) {
    /// `acc += dot4(x, w)`, word by word.
    macro_rules! sdot {
        ($acc:expr, $x:expr, $w:expr) => {
            asm!("sdot {a:v}.4s, {x:v}.16b, {w:v}.16b", a = inout(vreg) $acc, x = in(vreg) $x, w = in(vreg) $w,
                 options(pure, nomem, nostack))
        };
    }
    let (_, ow) = s.out();
    let (_, wp) = s.padded();
    let (kh, groups, st) = (s.kh, s.kw.div_ceil(4), s.stride);
    let base = pad.as_ptr();
    let mut x0 = 0;
    while x0 < ow {
        let n = (ow - x0).min(LANES);
        let mut acc = [[vdupq_n_s32(0); 4]; R];
        for i in 0..kh {
            for g in 0..groups {
                let w = vreinterpretq_s8_s32(vdupq_n_s32(words[i * groups + g]));
                for (r, acc) in acc.iter_mut().enumerate() {
                    let at = ((y + r) * st + i) * wp + x0 * st + 4 * g;
                    // SAFETY: `at` is a position of the padded plane (a row within its `hp`
                    // rows); the 48 bytes from it are within the plane and its slack.
                    unsafe {
                        let p = base.add(at);
                        if WIDE {
                            let t = uint8x16x3_t(vld1q_u8(p), vld1q_u8(p.add(16)), vld1q_u8(p.add(32)));
                            for (a, &ix) in acc.iter_mut().zip(idx) {
                                sdot!(*a, vqtbl3q_u8(t, ix), w);
                            }
                        } else {
                            let t = uint8x16x2_t(vld1q_u8(p), vld1q_u8(p.add(16)));
                            for (a, &ix) in acc.iter_mut().zip(idx) {
                                sdot!(*a, vqtbl2q_u8(t, ix), w);
                            }
                        }
                    }
                }
            }
        }
        for (r, acc) in acc.iter().enumerate() {
            let mut sums = [0i32; LANES];
            for (k, a) in acc.iter().enumerate() {
                // SAFETY: four i32 within `sums`.
                unsafe { vst1q_s32(sums.as_mut_ptr().add(4 * k), *a) };
            }
            let o = &mut dst[(y + r) * ow + x0..(y + r) * ow + x0 + n];
            requantise(&sums[..n], offset, scale, exact, y0, o);
        }
        x0 += n;
    }
}
