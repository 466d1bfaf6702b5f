//! The inner loop of the depthwise cross-correlation: one channel at a time, output rows
//! accumulated in registers as 16-wide strips of columns, one fused multiply-add per kernel tap
//! and column (on AVX-512, four output rows at a time, so each input load serves four). Every output value is the sum over the kernel rows, then columns, in that order.

/// Columns per accumulator block (one AVX-512 register, two AVX ones, four NEON ones).
const LANES: usize = 16;
/// Accumulator blocks per strip: 3 blocks cover the 41 columns of `s1`.
const MAX_BLOCKS: usize = 4;

/// One channel's geometry.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Geometry {
    /// Input rows and columns.
    pub h: usize,
    pub w: usize,
    /// Kernel rows and columns.
    pub kh: usize,
    pub kw: usize,
}

impl Geometry {
    pub fn out_h(&self) -> usize {
        self.h - self.kh + 1
    }

    pub fn out_w(&self) -> usize {
        self.w - self.kw + 1
    }

    /// Row stride of the padded copy of the input: room for a whole last block past any column.
    fn padded_w(&self) -> usize {
        self.out_w().div_ceil(LANES) * LANES + self.kw - 1
    }

    /// Floats of scratch [`correlate_channel`] needs: the padded input, and on aarch64 the
    /// kernel's taps for four output rows at once ([`row_taps`]).
    pub fn scratch_len(&self) -> usize {
        self.h * self.padded_w() + self.taps_len()
    }

    /// Floats of [`row_taps`] (none where the NEON path is not compiled).
    fn taps_len(&self) -> usize {
        if cfg!(target_arch = "aarch64") {
            (self.kh + NEON_ROWS - 1) * self.kw * NEON_ROWS
        } else {
            0
        }
    }
}

/// Output rows the NEON strips take at once.
const NEON_ROWS: usize = 4;

/// `out[y,x] = bias + Σ_{i,j} input[y+i, x+j]·kernel[i,j]` for one channel (`input` [h,w],
/// `kernel` [kh,kw], `out` [h−kh+1, w−kw+1], all row-major). `scratch` holds the input with its
/// rows padded to whole blocks (and, on aarch64, the kernel's taps; [`Geometry::scratch_len`]).
pub(crate) fn correlate_channel(
    g: Geometry,
    input: &[f32],
    kernel: &[f32],
    bias: f32,
    out: &mut [f32],
    scratch: &mut [f32],
) {
    let wp = g.padded_w();
    let (scratch, _taps) = scratch[..g.scratch_len()].split_at_mut(g.h * wp);
    for (dst, src) in scratch.chunks_exact_mut(wp).zip(input.chunks_exact(g.w)) {
        dst[..g.w].copy_from_slice(src);
        dst[g.w..].fill(0.0);
    }
    use crate::isa::F32Kernel;
    match crate::isa::f32_kernel() {
        // SAFETY: the CPU has the features the function is compiled for (the table's needs).
        #[cfg(target_arch = "x86_64")]
        F32Kernel::Avx512 => unsafe { strips_avx512(g, scratch, kernel, bias, out) },
        // SAFETY: as above.
        #[cfg(target_arch = "x86_64")]
        F32Kernel::Avx2Fma => unsafe { strips_avx2_fma(g, scratch, kernel, bias, out) },
        // SAFETY: NEON is part of the aarch64 baseline (and the probe found it).
        #[cfg(target_arch = "aarch64")]
        F32Kernel::Neon => unsafe { strips_neon(g, scratch, kernel, bias, out, _taps) },
        _ => strips::<false>(g, scratch, kernel, bias, out),
    }
}

/// NEON: strips of 16 columns (four 4-lane registers), four output rows at a time: 16
/// accumulators and four input loads per kernel tap, so each load serves up to four kernel
/// rows. Where all four rows have a kernel row for an input row (all but the first and last
/// three input rows of a block), their four taps are one vector (made once per channel in
/// `taps`, [`Geometry::taps_len`] floats or more) and each multiply-add takes its tap by lane:
/// no scalar loads, no branches (`FMLA v.4s, v.4s, v.s[q]`). Fused multiply-adds in the generic order: the same bits as
/// the AVX paths.
#[cfg(target_arch = "aarch64")]
#[target_feature(enable = "neon")]
unsafe fn strips_neon(g: Geometry, padded: &[f32], kernel: &[f32], bias: f32, out: &mut [f32], taps: &mut [f32]) {
    const R: usize = NEON_ROWS;
    let taps = &mut taps[..g.taps_len()];
    row_taps::<R>(g, kernel, taps);
    let taps = &*taps;
    walk(g, LANES, R, |rows, y, x0, cols| {
        let a = (g, padded, kernel, bias, &mut *out, y, x0, cols);
        // SAFETY: NEON is enabled here; the loads stay in `padded` (rows padded to whole
        // 16-column blocks), the stores in `out` (`cols` values a row).
        unsafe {
            match (rows, cols.div_ceil(4)) {
                (R, 1) => rows_neon::<R, 1>(a, taps),
                (R, 2) => rows_neon::<R, 2>(a, taps),
                (R, 3) => rows_neon::<R, 3>(a, taps),
                (R, _) => rows_neon::<R, 4>(a, taps),
                (_, 1) => rows_neon::<1, 1>(a, taps),
                (_, 2) => rows_neon::<1, 2>(a, taps),
                (_, 3) => rows_neon::<1, 3>(a, taps),
                _ => rows_neon::<1, 4>(a, taps),
            }
        }
    });
}

/// The taps `R` consecutive output rows take from input row `r` (of a block) at kernel column
/// `j`: `taps[(r·kw + j)·R + q] = kernel[(r − q)·kw + j]`, for the input rows where every `q`
/// has one (`R − 1 <= r < kh`; the others are set to 0 and not read). `taps` holds
/// `(kh + R − 1)·kw·R` floats.
#[cfg(target_arch = "aarch64")]
fn row_taps<const R: usize>(g: Geometry, kernel: &[f32], taps: &mut [f32]) {
    taps.fill(0.0);
    for r in R - 1..g.kh {
        for j in 0..g.kw {
            for q in 0..R {
                taps[(r * g.kw + j) * R + q] = kernel[(r - q) * g.kw + j];
            }
        }
    }
}

/// The strips of an output: columns `max_cols` at a time, and in each, rows `group` at a time
/// (single rows for the last few): `f(rows, y, x0, cols)` for each block.
#[cfg(any(target_arch = "x86_64", target_arch = "aarch64"))]
#[inline(always)]
fn walk(g: Geometry, max_cols: usize, group: usize, mut f: impl FnMut(usize, usize, usize, usize)) {
    let (ow, oh) = (g.out_w(), g.out_h());
    let mut x0 = 0;
    while x0 < ow {
        let cols = (ow - x0).min(max_cols);
        let mut y = 0;
        while y < oh {
            let rows = if oh - y >= group { group } else { 1 };
            f(rows, y, x0, cols);
            y += rows;
        }
        x0 += cols;
    }
}

/// The arguments of a row-block kernel: the geometry, the padded input, the kernel, the bias,
/// the output, and the block's first row, first column and column count.
#[cfg(any(target_arch = "x86_64", target_arch = "aarch64"))]
type Block<'a> = (Geometry, &'a [f32], &'a [f32], f32, &'a mut [f32], usize, usize, usize);

/// Output rows `y..y+R`, columns `x0..x0+cols` (`B` registers of 4), as [`rows_avx512`].
#[cfg(target_arch = "aarch64")]
#[target_feature(enable = "neon")]
unsafe fn rows_neon<const R: usize, const B: usize>((g, padded, kernel, bias, out, y, x0, cols): Block, taps: &[f32]) {
    use std::arch::aarch64::*;
    let (wp, ow) = (g.padded_w(), g.out_w());
    assert!((y + R + g.kh - 1) * wp <= padded.len() && x0 + 4 * B + g.kw - 1 <= wp && kernel.len() == g.kh * g.kw);
    assert!(cols <= 4 * B && (y + R - 1) * ow + x0 + cols <= out.len());
    assert!(R != 4 || taps.len() == (g.kh + R - 1) * g.kw * R);
    let mut acc = [[vdupq_n_f32(bias); B]; R];
    for r in 0..g.kh + R - 1 {
        // SAFETY: row `y + r` lies in `padded` (asserted above).
        let row = unsafe { padded.as_ptr().add((y + r) * wp + x0) };
        if R == 4 && r + 1 >= R && r < g.kh {
            for j in 0..g.kw {
                // SAFETY: within the row, and `taps` holds `R` values for `(r, j)` (asserted).
                let (v, t): ([float32x4_t; B], _) = unsafe {
                    (
                        std::array::from_fn(|b| vld1q_f32(row.add(j + 4 * b))),
                        vld1q_f32(taps.as_ptr().add((r * g.kw + j) * R)),
                    )
                };
                for b in 0..B {
                    acc[0][b] = vfmaq_laneq_f32::<0>(acc[0][b], v[b], t);
                    acc[1][b] = vfmaq_laneq_f32::<1>(acc[1][b], v[b], t);
                    acc[2][b] = vfmaq_laneq_f32::<2>(acc[2][b], v[b], t);
                    acc[3][b] = vfmaq_laneq_f32::<3>(acc[3][b], v[b], t);
                }
            }
            continue;
        }
        for j in 0..g.kw {
            // SAFETY: within the row (asserted above).
            let v: [float32x4_t; B] = std::array::from_fn(|b| unsafe { vld1q_f32(row.add(j + 4 * b)) });
            for (q, acc) in acc.iter_mut().enumerate() {
                if r >= q && r - q < g.kh {
                    let k = kernel[(r - q) * g.kw + j];
                    for (a, v) in acc.iter_mut().zip(v) {
                        *a = vfmaq_n_f32(*a, v, k);
                    }
                }
            }
        }
    }
    for (q, acc) in acc.iter().enumerate() {
        let dst = &mut out[(y + q) * ow + x0..(y + q) * ow + x0 + cols];
        for (b, a) in acc.iter().enumerate() {
            let n = cols.saturating_sub(b * 4).min(4);
            let mut lanes = [0f32; 4];
            // SAFETY: four floats into a local array.
            unsafe { vst1q_f32(lanes.as_mut_ptr(), *a) };
            dst[b * 4..b * 4 + n].copy_from_slice(&lanes[..n]);
        }
    }
}

/// AVX2: strips of 16 columns (two registers), 4 output rows at a time, as on AVX-512: 8
/// accumulators, and each input vector loaded serves up to 4 kernel rows (the generic strips
/// loaded one vector for every multiply-add: `s1` ran at 37 GFLOP/s on an AMD EPYC).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn strips_avx2_fma(g: Geometry, padded: &[f32], kernel: &[f32], bias: f32, out: &mut [f32]) {
    const R: usize = 4;
    walk(g, LANES, R, |rows, y, x0, cols| {
        let a = (g, padded, kernel, bias, &mut *out, y, x0, cols);
        // SAFETY: the features are enabled here; the loads stay in `padded` (rows padded to
        // whole blocks of 16), the stores in `out` (`cols` values).
        unsafe {
            match (rows, cols.div_ceil(8)) {
                (R, 1) => rows_avx2::<R, 1>(a),
                (R, _) => rows_avx2::<R, 2>(a),
                (_, 1) => rows_avx2::<1, 1>(a),
                _ => rows_avx2::<1, 2>(a),
            }
        }
    });
}

/// Output rows `y..y+R`, columns `x0..x0+cols` (`B` registers of 8), as [`rows_avx512`].
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn rows_avx2<const R: usize, const B: usize>((g, padded, kernel, bias, out, y, x0, cols): Block) {
    use std::arch::x86_64::*;
    let (wp, ow) = (g.padded_w(), g.out_w());
    assert!((y + R + g.kh - 1) * wp <= padded.len() && x0 + 8 * B + g.kw - 1 <= wp && kernel.len() == g.kh * g.kw);
    assert!(cols <= 8 * B && (y + R - 1) * ow + x0 + cols <= out.len());
    let mut acc = [[_mm256_set1_ps(bias); B]; R];
    for r in 0..g.kh + R - 1 {
        // SAFETY: row `y + r` lies in `padded` (asserted above).
        let row = unsafe { padded.as_ptr().add((y + r) * wp + x0) };
        for j in 0..g.kw {
            // SAFETY: within the row (asserted above).
            let v: [__m256; B] = std::array::from_fn(|b| unsafe { _mm256_loadu_ps(row.add(j + 8 * b)) });
            for (q, acc) in acc.iter_mut().enumerate() {
                if r >= q && r - q < g.kh {
                    // SAFETY: row r − q < kh and column j < kw of the kernel (asserted length).
                    let k = _mm256_broadcast_ss(unsafe { kernel.get_unchecked((r - q) * g.kw + j) });
                    for (a, v) in acc.iter_mut().zip(v) {
                        *a = _mm256_fmadd_ps(k, v, *a);
                    }
                }
            }
        }
    }
    for (q, acc) in acc.iter().enumerate() {
        let dst = &mut out[(y + q) * ow + x0..(y + q) * ow + x0 + cols];
        for (b, a) in acc.iter().enumerate() {
            let n = cols.saturating_sub(b * 8).min(8);
            if n == 8 {
                // SAFETY: 8 floats from `8·b` lie in `dst`.
                unsafe { _mm256_storeu_ps(dst.as_mut_ptr().add(8 * b), *a) };
                continue;
            }
            let mut lanes = [0f32; 8];
            // SAFETY: eight floats into a local array.
            unsafe { _mm256_storeu_ps(lanes.as_mut_ptr(), *a) };
            dst[8 * b..8 * b + n].copy_from_slice(&lanes[..n]);
        }
    }
}

/// AVX-512: strips of up to 3 registers of columns, 4 output rows at a time, so that each
/// input vector loaded serves up to 4 kernel rows (the generic strips reload it for each).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
unsafe fn strips_avx512(g: Geometry, padded: &[f32], kernel: &[f32], bias: f32, out: &mut [f32]) {
    const R: usize = 4;
    walk(g, 3 * LANES, R, |rows, y, x0, cols| {
        let a = (g, padded, kernel, bias, &mut *out, y, x0, cols);
        // SAFETY: the feature is enabled here; the loads stay in `padded` (rows padded to
        // whole blocks), the stores in `out` (masked to `cols`).
        unsafe {
            match (rows, cols.div_ceil(LANES)) {
                (R, 1) => rows_avx512::<R, 1>(a),
                (R, 2) => rows_avx512::<R, 2>(a),
                (R, _) => rows_avx512::<R, 3>(a),
                (_, 1) => rows_avx512::<1, 1>(a),
                (_, 2) => rows_avx512::<1, 2>(a),
                _ => rows_avx512::<1, 3>(a),
            }
        }
    });
}

/// Output rows `y..y+R`, columns `x0..x0+cols` (`B` registers): input row `y + r` adds to
/// output row `y + q` with kernel row `r − q`, so the sums keep their (row, column) order.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
unsafe fn rows_avx512<const R: usize, const B: usize>((g, padded, kernel, bias, out, y, x0, cols): Block) {
    use std::arch::x86_64::*;
    let (wp, ow) = (g.padded_w(), g.out_w());
    assert!((y + R + g.kh - 1) * wp <= padded.len() && x0 + B * LANES + g.kw - 1 <= wp && kernel.len() == g.kh * g.kw);
    let mut acc = [[_mm512_set1_ps(bias); B]; R];
    for r in 0..g.kh + R - 1 {
        let row = padded.as_ptr().add((y + r) * wp + x0);
        for j in 0..g.kw {
            // SAFETY: within the row (asserted above).
            let v: [__m512; B] = std::array::from_fn(|b| unsafe { _mm512_loadu_ps(row.add(j + b * LANES)) });
            for (q, acc) in acc.iter_mut().enumerate() {
                if r >= q && r - q < g.kh {
                    let k = _mm512_set1_ps(kernel[(r - q) * g.kw + j]);
                    for (a, v) in acc.iter_mut().zip(v) {
                        *a = _mm512_fmadd_ps(k, v, *a);
                    }
                }
            }
        }
    }
    for (q, acc) in acc.iter().enumerate() {
        let dst = &mut out[(y + q) * ow + x0..(y + q) * ow + x0 + cols];
        for (b, a) in acc.iter().enumerate() {
            let n = cols.saturating_sub(b * LANES).min(LANES);
            // SAFETY: `n` floats from `b·16` lie in `dst`.
            unsafe { _mm512_mask_storeu_ps(dst.as_mut_ptr().add(b * LANES), ((1u32 << n) - 1) as u16, *a) };
        }
    }
}

/// Every strip of up to `MAX_BLOCKS` blocks of output columns. `FUSED`: use fused multiply-add
/// (only where the target has it in hardware; elsewhere `mul_add` is a slow library call).
#[inline(always)]
fn strips<const FUSED: bool>(g: Geometry, padded: &[f32], kernel: &[f32], bias: f32, out: &mut [f32]) {
    let ow = g.out_w();
    let mut x0 = 0;
    while x0 < ow {
        let cols = (ow - x0).min(MAX_BLOCKS * LANES);
        match cols.div_ceil(LANES) {
            1 => strip::<1, FUSED>(g, padded, kernel, bias, out, x0, cols),
            2 => strip::<2, FUSED>(g, padded, kernel, bias, out, x0, cols),
            3 => strip::<3, FUSED>(g, padded, kernel, bias, out, x0, cols),
            _ => strip::<4, FUSED>(g, padded, kernel, bias, out, x0, cols),
        }
        x0 += cols;
    }
}

/// Output columns `x0..x0+cols` (at most `B` blocks) of every output row.
#[inline(always)]
fn strip<const B: usize, const FUSED: bool>(
    g: Geometry,
    padded: &[f32],
    kernel: &[f32],
    bias: f32,
    out: &mut [f32],
    x0: usize,
    cols: usize,
) {
    let (wp, ow) = (g.padded_w(), g.out_w());
    for y in 0..g.out_h() {
        let mut acc = [[bias; LANES]; B];
        for i in 0..g.kh {
            let row = &padded[(y + i) * wp + x0..(y + i + 1) * wp];
            for (j, &k) in kernel[i * g.kw..(i + 1) * g.kw].iter().enumerate() {
                let taps = &row[j..j + B * LANES];
                for (b, block) in acc.iter_mut().enumerate() {
                    for (l, a) in block.iter_mut().enumerate() {
                        let v = taps[b * LANES + l];
                        *a = if FUSED { k.mul_add(v, *a) } else { k * v + *a };
                    }
                }
            }
        }
        let dst = &mut out[y * ow + x0..y * ow + x0 + cols];
        for (d, a) in dst.iter_mut().zip(acc.iter().flatten()) {
            *d = *a;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn direct(g: Geometry, input: &[f32], kernel: &[f32], bias: f32) -> Vec<f32> {
        let mut out = Vec::new();
        for y in 0..g.out_h() {
            for x in 0..g.out_w() {
                let mut s = bias as f64;
                for i in 0..g.kh {
                    for j in 0..g.kw {
                        s += input[(y + i) * g.w + x + j] as f64 * kernel[i * g.kw + j] as f64;
                    }
                }
                out.push(s as f32);
            }
        }
        out
    }

    #[test]
    fn equals_the_direct_sum_for_every_strip_width() {
        // Output widths of 1, 16, 17, 41 (three blocks), 64 and 70 (two strips) columns; output
        // heights of 1, 16 (groups of 4 rows), 41 and 7 (a group and single rows).
        for (h, w, kh, kw) in
            [(5, 5, 5, 5), (20, 20, 5, 5), (9, 19, 3, 3), (69, 69, 29, 29), (8, 66, 3, 3), (7, 75, 4, 6), (7, 75, 1, 6)]
        {
            let g = Geometry { h, w, kh, kw };
            let input: Vec<f32> = (0..h * w).map(|i| ((i * 7919 % 1000) as f32) / 500.0 - 1.0).collect();
            let kernel: Vec<f32> = (0..kh * kw).map(|i| ((i * 104729 % 997) as f32) / 498.0 - 1.0).collect();
            let mut out = vec![f32::NAN; g.out_h() * g.out_w()];
            let mut scratch = vec![f32::NAN; g.scratch_len()];
            correlate_channel(g, &input, &kernel, 0.25, &mut out, &mut scratch);
            let want = direct(g, &input, &kernel, 0.25);
            // Every path on the padded input the dispatched one left in `scratch`.
            let mut paths = vec![("dispatched", out.clone())];
            let mut portable = vec![f32::NAN; out.len()];
            strips::<false>(g, &scratch, &kernel, 0.25, &mut portable);
            paths.push(("portable", portable));
            #[cfg(target_arch = "x86_64")]
            if super::super::avx2_fma() {
                let mut fma = vec![f32::NAN; out.len()];
                // SAFETY: the CPU has AVX2 and FMA.
                unsafe { strips_avx2_fma(g, &scratch, &kernel, 0.25, &mut fma) };
                let mut fused = vec![f32::NAN; out.len()];
                strips::<true>(g, &scratch, &kernel, 0.25, &mut fused);
                assert!(fma == fused, "{h}x{w} by {kh}x{kw}: AVX2 differs from the portable fused loop");
                paths.push(("avx2", fma));
            }
            #[cfg(target_arch = "aarch64")]
            {
                let mut neon = vec![f32::NAN; out.len()];
                // SAFETY: NEON is part of the aarch64 baseline.
                let mut taps = vec![f32::NAN; g.taps_len()];
                unsafe { strips_neon(g, &scratch, &kernel, 0.25, &mut neon, &mut taps) };
                let mut fused = vec![f32::NAN; out.len()];
                strips::<true>(g, &scratch, &kernel, 0.25, &mut fused);
                assert!(neon == fused, "{h}x{w} by {kh}x{kw}: NEON differs from the portable fused loop");
                paths.push(("neon", neon));
            }
            for (path, got) in paths {
                let worst = got.iter().zip(&want).map(|(a, b)| (a - b).abs()).fold(0.0f32, f32::max);
                assert!(worst < 1e-4 * (kh * kw) as f32, "{path}: {h}x{w} by {kh}x{kw}: off by {worst}");
            }
        }
    }
}
