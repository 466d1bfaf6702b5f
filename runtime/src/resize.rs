//! OpenCV's `resize(INTER_LINEAR)` on 8-bit images, bit for bit (as opencv-python computes it):
//! half-pixel centres, 11-bit fixed-point coefficients rounded half to even, horizontal pass into
//! i32 row buffers, vertical pass with OpenCV's SIMD rounding.

const COEF_SCALE: f32 = 2048.0;

/// Per destination index: the two source indices and their fixed-point weights.
struct Taps {
    idx: Vec<[usize; 2]>,
    w: Vec<[i32; 2]>,
}

impl Taps {
    /// Per destination pixel of an interleaved row of `channels` channels: the offsets of its
    /// two source pixels' first channel within the source row (one entry a pixel, not a value:
    /// a table a third as long for BGR rows; the weights are [`Taps::w`] as they are).
    fn pixel_offsets(&self, channels: usize) -> Vec<[usize; 2]> {
        self.idx.iter().map(|i| i.map(|i| i * channels)).collect()
    }
}

fn round_half_even(v: f32) -> i32 {
    v.round_ties_even() as i32
}

/// Coefficients along one axis. `clamp_weights` is OpenCV's horizontal rule (weights forced to
/// (1, 0) past the borders); the vertical rule keeps fractional weights and clamps only indices.
fn taps(src: usize, dst: usize, clamp_weights: bool) -> Taps {
    let scale = 1.0 / (dst as f64 / src as f64);
    let last = src as i64 - 1;
    let mut idx = Vec::with_capacity(dst);
    let mut w = Vec::with_capacity(dst);
    for d in 0..dst {
        let f = ((d as f64 + 0.5) * scale - 0.5) as f32;
        let mut s = f.floor() as i64;
        let mut f = f - s as f32;
        if clamp_weights {
            if s < 0 {
                f = 0.0;
                s = 0;
            }
            if s >= last {
                f = 0.0;
                s = last;
            }
        }
        let i0 = s.clamp(0, last) as usize;
        let i1 = (s + 1).clamp(0, last) as usize;
        idx.push([i0, i1]);
        w.push([round_half_even((1.0 - f) * COEF_SCALE), round_half_even(f * COEF_SCALE)]);
    }
    Taps { idx, w }
}

/// Resize an interleaved 8-bit image of `channels` channels from `sw`x`sh` to `dw`x`dh` exactly
/// as `cv2.resize(img, (dw, dh))` does.
pub fn resize_linear_u8(src: &[u8], sw: usize, sh: usize, channels: usize, dw: usize, dh: usize) -> Vec<u8> {
    assert_eq!(src.len(), sw * sh * channels, "source buffer size");
    let row_len = sw * channels;
    resize_linear_u8_rows(sw, sh, channels, dw, dh, |y, row| row.copy_from_slice(&src[y * row_len..(y + 1) * row_len]))
}

/// [`resize_linear_u8`] of an image that is never materialised: `fill_row(y, row)` writes source
/// row `y` (`sw * channels` bytes) when the resize needs it. Only the rows the output samples
/// are asked for (at most two per output row), so memory is one source row, not the image.
pub fn resize_linear_u8_rows(
    sw: usize,
    sh: usize,
    channels: usize,
    dw: usize,
    dh: usize,
    mut fill_row: impl FnMut(usize, &mut [u8]),
) -> Vec<u8> {
    let tx = taps(sw, dw, true);
    let ty = taps(sh, dh, false);
    let row_len = dw * channels;
    let (offs, ws) = (tx.pixel_offsets(channels), &tx.w);
    let mut src_row = vec![0u8; sw * channels];
    // Horizontal pass for one source row, cached since consecutive output rows share rows.
    let mut hrow = |y: usize, out: &mut [i32]| {
        fill_row(y, &mut src_row);
        passes::horizontal(&src_row, channels, &offs, ws, out);
    };
    let mut cache: [(usize, Vec<i32>); 2] = [(usize::MAX, vec![0; row_len]), (usize::MAX, vec![0; row_len])];
    let mut out = vec![0u8; dh * row_len];
    for ((iy, wy), dst) in ty.idx.iter().zip(&ty.w).zip(out.chunks_exact_mut(row_len.max(1))) {
        if cache[0].0 != iy[0] {
            if cache[1].0 == iy[0] {
                cache.swap(0, 1);
            } else {
                hrow(iy[0], &mut cache[0].1);
                cache[0].0 = iy[0];
            }
        }
        if cache[1].0 != iy[1] {
            hrow(iy[1], &mut cache[1].1);
            cache[1].0 = iy[1];
        }
        passes::vertical(&cache[0].1, &cache[1].1, *wy, dst);
    }
    out
}

/// The two passes' loops, compiled for the widest vectors the CPU has (the loops are the same;
/// integer arithmetic, so every form gives the same bytes) and kept out of line: inlined into
/// their caller for the baseline's 16-byte vectors, the crop took 0.29 or 0.35 ms depending on
/// what else the crate held (NanoTrack's step on an AVX-512 Xeon, 2026-12-05).
mod passes {
    #[cfg(target_arch = "x86_64")]
    use crate::isa::F32Kernel;

    /// `out[i·channels + c] = row[offs[i][0] + c]·ws[i][0] + row[offs[i][1] + c]·ws[i][1]`.
    pub(super) fn horizontal(row: &[u8], channels: usize, offs: &[[usize; 2]], ws: &[[i32; 2]], out: &mut [i32]) {
        match crate::isa::f32_kernel() {
            // SAFETY: the CPU has AVX-512F, AVX2 and FMA (the table's needs).
            #[cfg(target_arch = "x86_64")]
            F32Kernel::Avx512 => unsafe { horizontal_avx512(row, channels, offs, ws, out) },
            // SAFETY: the CPU has AVX2 and FMA (the table's needs).
            #[cfg(target_arch = "x86_64")]
            F32Kernel::Avx2Fma => unsafe { horizontal_avx2(row, channels, offs, ws, out) },
            _ => horizontal_generic(row, channels, offs, ws, out),
        }
    }

    /// OpenCV's vertical pass of two horizontally filtered rows into one output row.
    pub(super) fn vertical(r0: &[i32], r1: &[i32], wy: [i32; 2], dst: &mut [u8]) {
        match crate::isa::f32_kernel() {
            // SAFETY: the CPU has AVX-512F, AVX2 and FMA (the table's needs).
            #[cfg(target_arch = "x86_64")]
            F32Kernel::Avx512 => unsafe { vertical_avx512(r0, r1, wy, dst) },
            // SAFETY: the CPU has AVX2 and FMA (the table's needs).
            #[cfg(target_arch = "x86_64")]
            F32Kernel::Avx2Fma => unsafe { vertical_avx2(r0, r1, wy, dst) },
            _ => vertical_generic(r0, r1, wy, dst),
        }
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx512f,avx2,fma")]
    pub(super) unsafe fn horizontal_avx512(
        row: &[u8],
        channels: usize,
        offs: &[[usize; 2]],
        ws: &[[i32; 2]],
        out: &mut [i32],
    ) {
        horizontal_generic(row, channels, offs, ws, out)
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,fma")]
    pub(super) unsafe fn horizontal_avx2(
        row: &[u8],
        channels: usize,
        offs: &[[usize; 2]],
        ws: &[[i32; 2]],
        out: &mut [i32],
    ) {
        horizontal_generic(row, channels, offs, ws, out)
    }

    /// [`horizontal`]'s loop, a pixel at a time, BGR and grey rows with their channel count
    /// known to the compiler (a table entry a value before: the pass took 20% less time in
    /// NanoTrack's search crop on a Zen 3, about 0.24 -> 0.19 ms, three alternated `perf` runs).
    #[inline(always)]
    pub(super) fn horizontal_generic(
        row: &[u8],
        channels: usize,
        offs: &[[usize; 2]],
        ws: &[[i32; 2]],
        out: &mut [i32],
    ) {
        match channels {
            0 => {}
            1 => pixels::<1>(row, offs, ws, out),
            3 => pixels::<3>(row, offs, ws, out),
            c => {
                for ((o, off), w) in out.chunks_exact_mut(c).zip(offs).zip(ws) {
                    for (k, o) in o.iter_mut().enumerate() {
                        *o = row[off[0] + k] as i32 * w[0] + row[off[1] + k] as i32 * w[1];
                    }
                }
            }
        }
    }

    /// [`horizontal_generic`] for rows of `C` channels.
    #[inline(always)]
    fn pixels<const C: usize>(row: &[u8], offs: &[[usize; 2]], ws: &[[i32; 2]], out: &mut [i32]) {
        for ((o, off), w) in out.chunks_exact_mut(C).zip(offs).zip(ws) {
            let a: &[u8; C] = row[off[0]..off[0] + C].try_into().expect("C values");
            let b: &[u8; C] = row[off[1]..off[1] + C].try_into().expect("C values");
            for k in 0..C {
                o[k] = a[k] as i32 * w[0] + b[k] as i32 * w[1];
            }
        }
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx512f,avx2,fma")]
    pub(super) unsafe fn vertical_avx512(r0: &[i32], r1: &[i32], wy: [i32; 2], dst: &mut [u8]) {
        vertical_generic(r0, r1, wy, dst)
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,fma")]
    pub(super) unsafe fn vertical_avx2(r0: &[i32], r1: &[i32], wy: [i32; 2], dst: &mut [u8]) {
        vertical_generic(r0, r1, wy, dst)
    }

    /// Shifts, adds and a clamp on i32 lanes (vectorised by the compiler).
    #[inline(always)]
    pub(super) fn vertical_generic(r0: &[i32], r1: &[i32], wy: [i32; 2], dst: &mut [u8]) {
        for ((d, &a), &b) in dst.iter_mut().zip(r0).zip(r1) {
            let v = ((wy[0] * (a >> 4)) >> 16) + ((wy[1] * (b >> 4)) >> 16);
            *d = ((v + 2) >> 2).clamp(0, 255) as u8;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The straightforward form (one value at a time): what the fast one must equal.
    fn reference(src: &[u8], sw: usize, sh: usize, channels: usize, dw: usize, dh: usize) -> Vec<u8> {
        assert_eq!(src.len(), sw * sh * channels, "source buffer size");
        let tx = taps(sw, dw, true);
        let ty = taps(sh, dh, false);
        let row_len = dw * channels;
        // Horizontal pass for one source row, cached since consecutive output rows share rows.
        let hrow = |y: usize, out: &mut Vec<i32>| {
            out.clear();
            let row = &src[y * sw * channels..(y + 1) * sw * channels];
            for (i, wt) in tx.idx.iter().zip(&tx.w) {
                for c in 0..channels {
                    out.push(row[i[0] * channels + c] as i32 * wt[0] + row[i[1] * channels + c] as i32 * wt[1]);
                }
            }
        };
        let mut cache: [(usize, Vec<i32>); 2] = [(usize::MAX, Vec::new()), (usize::MAX, Vec::new())];
        let mut out = Vec::with_capacity(dh * row_len);
        for (iy, wy) in ty.idx.iter().zip(&ty.w) {
            if cache[0].0 != iy[0] {
                if cache[1].0 == iy[0] {
                    cache.swap(0, 1);
                } else {
                    hrow(iy[0], &mut cache[0].1);
                    cache[0].0 = iy[0];
                }
            }
            if cache[1].0 != iy[1] {
                hrow(iy[1], &mut cache[1].1);
                cache[1].0 = iy[1];
            }
            let (r0, r1) = (&cache[0].1, &cache[1].1);
            for x in 0..row_len {
                let v = ((wy[0] * (r0[x] >> 4)) >> 16) + ((wy[1] * (r1[x] >> 4)) >> 16);
                out.push(((v + 2) >> 2).clamp(0, 255) as u8);
            }
        }
        out
    }

    #[test]
    fn equals_the_straightforward_form() {
        // BGR and grey rows (their own loops) and 4 and 2 channels (the loop for any count).
        for (sw, sh, c, dw, dh) in [
            (300, 290, 3, 255, 255),
            (611, 589, 3, 127, 127),
            (97, 53, 3, 287, 287),
            (40, 30, 1, 17, 61),
            (23, 19, 4, 31, 7),
            (5, 5, 2, 9, 3),
        ] {
            let src: Vec<u8> = (0..sw * sh * c).map(|i| ((i * 7919 + i / 13) % 256) as u8).collect();
            assert_eq!(
                resize_linear_u8(&src, sw, sh, c, dw, dh),
                reference(&src, sw, sh, c, dw, dh),
                "{sw}x{sh} -> {dw}x{dh}"
            );
        }
    }

    #[test]
    fn identity_size_copies() {
        let src: Vec<u8> = (0..4 * 3 * 3).map(|i| (i * 7) as u8).collect();
        assert_eq!(resize_linear_u8(&src, 4, 3, 3, 4, 3), src);
    }

    #[test]
    fn upscale_of_a_constant_is_constant() {
        let src = vec![200u8; 5 * 5 * 3];
        assert!(resize_linear_u8(&src, 5, 5, 3, 9, 9).iter().all(|&v| v == 200));
    }

    /// Every compiled form of the two passes this CPU can run gives the portable loops' values.
    #[test]
    fn every_form_of_the_passes_equals_the_portable_one() {
        let row: Vec<u8> = (0..3 * 611).map(|i| ((i * 7919 + i / 13) % 256) as u8).collect();
        let tx = taps(611, 255, true);
        let (offs, ws) = (tx.pixel_offsets(3), &tx.w);
        let mut want_h = vec![0i32; 3 * offs.len()];
        passes::horizontal_generic(&row, 3, &offs, ws, &mut want_h);
        let r1: Vec<i32> = want_h.iter().rev().copied().collect();
        let mut want_v = vec![0u8; want_h.len()];
        passes::vertical_generic(&want_h, &r1, [1500, 548], &mut want_v);
        let mut forms: Vec<(&str, Vec<i32>, Vec<u8>)> = vec![];
        let (mut h, mut v) = (vec![0i32; want_h.len()], vec![0u8; want_v.len()]);
        passes::horizontal(&row, 3, &offs, ws, &mut h);
        passes::vertical(&want_h, &r1, [1500, 548], &mut v);
        forms.push(("dispatched", h, v));
        #[cfg(target_arch = "x86_64")]
        {
            type Horizontal = unsafe fn(&[u8], usize, &[[usize; 2]], &[[i32; 2]], &mut [i32]);
            type Vertical = unsafe fn(&[i32], &[i32], [i32; 2], &mut [u8]);
            let isa = crate::isa::isa();
            let compiled: [(&str, bool, Horizontal, Vertical); 2] = [
                ("AVX2", isa.avx2_fma, passes::horizontal_avx2, passes::vertical_avx2),
                ("AVX-512", isa.avx512, passes::horizontal_avx512, passes::vertical_avx512),
            ];
            for (name, runs, horizontal, vertical) in compiled {
                if !runs {
                    eprintln!("NOTE: no {name} here (or PRL_ISA caps it): the resize's {name} form is NOT tested");
                    continue;
                }
                let (mut h, mut v) = (vec![0i32; want_h.len()], vec![0u8; want_v.len()]);
                // SAFETY: the CPU has the form's instruction sets (checked just above).
                unsafe {
                    horizontal(&row, 3, &offs, ws, &mut h);
                    vertical(&want_h, &r1, [1500, 548], &mut v);
                }
                forms.push((name, h, v));
            }
        }
        assert!(want_v.iter().any(|&b| b > 0 && b < 255));
        for (name, h, v) in forms {
            assert_eq!(h, want_h, "{name}");
            assert_eq!(v, want_v, "{name}");
        }
    }
}
