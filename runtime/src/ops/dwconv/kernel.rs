//! [`super::DepthwiseConv`]'s row kernel, compiled for AVX-512, for AVX2 + FMA and
//! generically; the CPU's best is chosen when run.

/// The arguments of every path: the padded plane, its row length, the taps' offsets and
/// weights, the bias, the output rows and their length.
#[cfg(test)]
pub(super) type Rows = fn(&[f32], usize, &[usize], &[f32], f32, &mut [f32], usize);

/// Every output row of one channel: `dst` (`ow` columns a row) is `bias` plus, for each tap,
/// its weight times the padded input from its offset on (row `y` of the output reads from
/// `offset + y * wq`).
pub(super) fn rows(src: &[f32], wq: usize, offs: &[usize], ws: &[f32], bias: f32, dst: &mut [f32], ow: usize) {
    use crate::isa::F32Kernel;
    match crate::isa::f32_kernel() {
        // SAFETY: the CPU has AVX-512F, AVX2 and FMA (the table's needs).
        #[cfg(target_arch = "x86_64")]
        F32Kernel::Avx512 => unsafe { rows_avx512(src, wq, offs, ws, bias, dst, ow) },
        // SAFETY: the CPU has AVX2 and FMA (the table's needs).
        #[cfg(target_arch = "x86_64")]
        F32Kernel::Avx2Fma => unsafe { rows_avx2(src, wq, offs, ws, bias, dst, ow) },
        #[cfg(target_arch = "aarch64")]
        F32Kernel::Neon => rows_neon(src, wq, offs, ws, bias, dst, ow),
        _ => rows_generic::<false>(src, wq, offs, ws, bias, dst, ow),
    }
}

/// NEON: blocks of 16 columns (four 4-lane registers) by four rows, 16 accumulators, fused
/// multiply-adds (the 32-column blocks of the AVX-512 form would need all 32 registers for
/// accumulators alone). The same sums in the same order as the AVX paths: the same bits.
#[cfg(target_arch = "aarch64")]
pub(super) fn rows_neon(src: &[f32], wq: usize, offs: &[usize], ws: &[f32], bias: f32, dst: &mut [f32], ow: usize) {
    rows_blocked::<true, 16>(src, wq, offs, ws, bias, dst, ow)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx2,fma")]
pub(super) unsafe fn rows_avx512(
    src: &[f32],
    wq: usize,
    offs: &[usize],
    ws: &[f32],
    bias: f32,
    dst: &mut [f32],
    ow: usize,
) {
    rows_generic::<true>(src, wq, offs, ws, bias, dst, ow)
}

/// AVX2: blocks of 16 columns (two 8-lane registers) by four rows, 8 accumulators (32
/// columns by four rows would need all 16 registers for accumulators alone).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
pub(super) unsafe fn rows_avx2(
    src: &[f32],
    wq: usize,
    offs: &[usize],
    ws: &[f32],
    bias: f32,
    dst: &mut [f32],
    ow: usize,
) {
    rows_blocked::<true, 16>(src, wq, offs, ws, bias, dst, ow)
}

/// `B` output columns of `R` consecutive output rows from `at` on (rows `wq` apart), into
/// `out`: `R` rows of `ow` values, of which columns `x0 .. x0 + n` are written. `R`
/// independent accumulators keep the FMA units busy (one row alone is a chain of dependent
/// multiply-adds, bound by their latency).
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn block<const FUSED: bool, const B: usize, const R: usize>(
    src: &[f32],
    at: usize,
    wq: usize,
    offs: &[usize],
    ws: &[f32],
    bias: f32,
    out: &mut [f32],
    (ow, x0, n): (usize, usize, usize),
) {
    let mut acc = [[bias; B]; R];
    // One bounds check for the block (not one per tap and row: they cost more than the
    // multiply-adds).
    let reach = offs.iter().max().map_or(0, |&o| at + (R - 1) * wq + o + B);
    assert!(reach <= src.len() && ws.len() >= offs.len(), "taps within the padded plane");
    for (&off, &w) in offs.iter().zip(ws) {
        for (r, acc) in acc.iter_mut().enumerate() {
            // SAFETY: `at + r·wq + off + B <= reach <= src.len()` (asserted above).
            let s: &[f32; B] = unsafe { &*src.as_ptr().add(at + r * wq + off).cast::<[f32; B]>() };
            for l in 0..B {
                acc[l] = if FUSED { w.mul_add(s[l], acc[l]) } else { acc[l] + w * s[l] };
            }
        }
    }
    for (r, acc) in acc.iter().enumerate() {
        let out = &mut out[r * ow + x0..r * ow + x0 + n];
        if n == B {
            // A whole block: a copy of known length (vector stores, not a library call).
            out.copy_from_slice(acc);
        } else {
            out.copy_from_slice(&acc[..n]);
        }
    }
}

/// `R` output rows starting at row `y` (`out` holds exactly them).
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn row_group<const FUSED: bool, const WIDE: usize, const R: usize>(
    src: &[f32],
    wq: usize,
    offs: &[usize],
    ws: &[f32],
    bias: f32,
    out: &mut [f32],
    ow: usize,
    y: usize,
) {
    let base = y * wq;
    let mut x0 = 0;
    while x0 + WIDE <= ow {
        block::<FUSED, WIDE, R>(src, base + x0, wq, offs, ws, bias, out, (ow, x0, WIDE));
        x0 += WIDE;
    }
    while x0 < ow {
        let n = (ow - x0).min(16);
        if n <= 8 {
            // An 8x8 map (MobileNet's last layers on a template) fills half a 16-lane block.
            block::<FUSED, 8, R>(src, base + x0, wq, offs, ws, bias, out, (ow, x0, n));
        } else {
            block::<FUSED, 16, R>(src, base + x0, wq, offs, ws, bias, out, (ow, x0, n));
        }
        x0 += n;
    }
}

/// The portable form; `FUSED` uses fused multiply-adds (only where the CPU has them:
/// elsewhere `mul_add` is a library call). Rows go four at a time (eight on maps up to 8
/// wide), in blocks of 32 columns, then 16 (a 16x16 map wastes nothing), then 8 for what is
/// left; the last block of a row computes past its end into the scratch's slack and keeps
/// only the columns that exist.
#[inline(always)]
pub(super) fn rows_generic<const FUSED: bool>(
    src: &[f32],
    wq: usize,
    offs: &[usize],
    ws: &[f32],
    bias: f32,
    dst: &mut [f32],
    ow: usize,
) {
    rows_blocked::<FUSED, 32>(src, wq, offs, ws, bias, dst, ow)
}

/// [`rows_generic`] with blocks of `WIDE` columns (32 or 16) before the 16-column ones.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn rows_blocked<const FUSED: bool, const WIDE: usize>(
    src: &[f32],
    wq: usize,
    offs: &[usize],
    ws: &[f32],
    bias: f32,
    dst: &mut [f32],
    ow: usize,
) {
    let oh = dst.len() / ow;
    let mut y = 0;
    if ow <= 8 {
        // One 8-column block a row: eight rows at once (eight independent accumulators;
        // four leave the multiply-adds waiting on each other's latency).
        for out in dst.chunks_exact_mut(8 * ow) {
            row_group::<FUSED, WIDE, 8>(src, wq, offs, ws, bias, out, ow, y);
            y += 8;
        }
    }
    for out in dst[y * ow..].chunks_exact_mut(4 * ow) {
        row_group::<FUSED, WIDE, 4>(src, wq, offs, ws, bias, out, ow, y);
        y += 4;
    }
    for out in dst[y * ow..].chunks_exact_mut(ow) {
        row_group::<FUSED, WIDE, 1>(src, wq, offs, ws, bias, out, ow, y);
        y += 1;
    }
    debug_assert_eq!(y, oh);
}
