//! The inner loop of [`super::conv::PackedConv`]: a direct convolution with no im2col.
//!
//! The input is copied once into a zero-padded buffer `[C, Hp, Wp]`. Output position
//! `p = y·Wp + x` ("wide" rows: the last `kw − 1` columns of each row are computed and dropped)
//! reads tap `(c, i, j)` at `p + c·Hp·Wp + i·Wp + j`, so a tile of consecutive positions reads
//! consecutive input values for every tap, across row ends. A tile is `ROWS` output channels by
//! `PX` positions held in registers; the weights are packed `[channel block][tap][ROWS]`.
//! Every output value is its bias plus the sum over taps in (c, i, j) order.

/// Output channels per tile (the packing's block).
pub(crate) const ROWS: usize = 8;

use super::act::Activation;
use crate::isa::F32Kernel;
/// Taps per pass over the tiles on AVX-512 (a pass's weights stay in L1); with no more, each
/// tile goes to the output as soon as it is summed.
#[cfg(target_arch = "x86_64")]
const CHUNK: usize = 128;

/// Positions per tile of the widest kernel (two AVX-512 registers).
pub(crate) const MAX_PX: usize = 32;

/// Positions per tile of the kernel [`channel_block`] runs on this machine: a row of positions
/// that is a multiple of it fills every tile.
pub(crate) fn tile_positions() -> usize {
    match crate::isa::f32_kernel() {
        F32Kernel::Avx512 => MAX_PX,
        #[cfg(target_arch = "x86_64")]
        F32Kernel::Avx2Fma => AVX2_PX,
        #[cfg(target_arch = "aarch64")]
        F32Kernel::Neon => NEON_PX,
        _ => 8,
    }
}

/// Where the taps and outputs of one convolution lie.
#[derive(Debug, Clone)]
pub(crate) struct Layout {
    /// Input offset of every tap `(c, i, j)` in the padded buffer, in packing order.
    pub taps: Vec<usize>,
    /// Row stride of the padded input (`Wp`).
    pub wp: usize,
    /// Output rows and columns.
    pub oh: usize,
    pub ow: usize,
}

impl Layout {
    /// Wide positions covering every output: `(oh − 1)·Wp + ow`.
    pub fn positions(&self) -> usize {
        (self.oh - 1) * self.wp + self.ow
    }

    /// A `k` x `k` convolution over `planes` unpadded `h` x `w` planes, every tap live (the
    /// kernels' tests).
    #[cfg(test)]
    pub fn dense(planes: usize, h: usize, w: usize, k: usize) -> Layout {
        let taps = (0..planes).flat_map(|c| (0..k).flat_map(move |i| (0..k).map(move |j| (c * h + i) * w + j)));
        Layout { taps: taps.collect(), wp: w, oh: h - k + 1, ow: w - k + 1 }
    }
}

/// One block of `ROWS` output channels (fewer in `out` for the last block: `out` holds
/// `out.len() / (oh·ow)` planes): `out[r] = act(bias[r] + conv(padded, weights[r]))`. `padded` must
/// extend `MAX_PX` values past the last tap of the last position.
pub(crate) fn channel_block(
    l: &Layout,
    padded: &[f32],
    weights: &[f32],
    bias: &[f32; ROWS],
    act: Activation,
    out: &mut [f32],
) {
    assert!(weights.len() == l.taps.len() * ROWS);
    assert!(l.taps.iter().all(|&t| t + l.positions() + MAX_PX <= padded.len()));
    match crate::isa::f32_kernel() {
        // SAFETY: the CPU has AVX-512F; every load stays in `padded` and `weights` (asserted).
        // The activation is applied in registers where the taps fit one chunk.
        #[cfg(target_arch = "x86_64")]
        F32Kernel::Avx512 if l.taps.len() <= CHUNK => {
            return unsafe { positions_avx512_fused(l, padded, weights, bias, act, out) };
        }
        // SAFETY: as above.
        #[cfg(target_arch = "x86_64")]
        F32Kernel::Avx512 => unsafe { positions_avx512(l, padded, weights, bias, out) },
        // SAFETY: the CPU has the features the function is compiled for; every load stays in
        // `padded` and `weights` (asserted). The activation is applied in registers.
        #[cfg(target_arch = "x86_64")]
        F32Kernel::Avx2Fma => return unsafe { positions_avx2_fma(l, padded, weights, bias, act, out) },
        // SAFETY: NEON is part of the aarch64 baseline; every load stays in `padded` and
        // `weights` (asserted).
        #[cfg(target_arch = "aarch64")]
        F32Kernel::Neon => unsafe { positions_neon(l, padded, weights, bias, out) },
        _ => positions::<false>(l, padded, weights, bias, out),
    }
    act.apply_all(out);
}

/// Write a tile's `acc[r][q]` (position `p0 + q`) to the output planes, dropping the wide
/// columns and the positions past the end.
#[inline(always)]
fn scatter<const PX: usize>(l: &Layout, acc: &[[f32; PX]; ROWS], bias: &[f32; ROWS], p0: usize, out: &mut [f32]) {
    scatter_with::<PX, true>(l, acc, bias, p0, out)
}

/// [`scatter`], adding the bias when `BIAS` (else the tile holds the outputs as they are).
#[inline(always)]
fn scatter_with<const PX: usize, const BIAS: bool>(
    l: &Layout,
    acc: &[[f32; PX]; ROWS],
    bias: &[f32; ROWS],
    p0: usize,
    out: &mut [f32],
) {
    let plane = l.oh * l.ow;
    let rows = out.len() / plane;
    let end = PX.min(l.positions() - p0);
    let mut q = 0;
    // Runs of positions within one padded row; of each, the columns that exist.
    while q < end {
        let (y, x) = ((p0 + q) / l.wp, (p0 + q) % l.wp);
        let run = (l.wp - x).min(end - q);
        let valid = l.ow.saturating_sub(x).min(run);
        for r in 0..rows {
            let dst = &mut out[r * plane + y * l.ow + x..][..valid];
            if BIAS {
                for (d, &a) in dst.iter_mut().zip(&acc[r][q..q + valid]) {
                    *d = a + bias[r];
                }
            } else {
                dst.copy_from_slice(&acc[r][q..q + valid]);
            }
        }
        q += run;
    }
}

/// Write every tile of `PX` positions held in `sums` (`[tile][row][position]`, as the SIMD
/// paths leave them) to the output planes.
#[cfg(any(target_arch = "x86_64", target_arch = "aarch64"))]
fn scatter_tiles<const PX: usize>(l: &Layout, sums: &[f32], bias: &[f32; ROWS], out: &mut [f32]) {
    for (tile, sums) in sums.chunks_exact(ROWS * PX).enumerate() {
        let mut acc = [[0f32; PX]; ROWS];
        for (a, s) in acc.iter_mut().zip(sums.chunks_exact(PX)) {
            a.copy_from_slice(s);
        }
        scatter(l, &acc, bias, tile * PX, out);
    }
}

/// Positions per AVX2 tile: three 8-lane registers.
#[cfg(target_arch = "x86_64")]
const AVX2_PX: usize = 24;

/// Taps per pass over the tiles on AVX2 (16 KB of weights, half an L1): on an AMD EPYC (Zen 2),
/// PRL-Track's backbone layer 3 29.4 -> 20.7 ms, layer 4 30.4 -> 26.9, its search graph's eight
/// largest convolutions 167 -> 152 ms; 128 taps made layers 1 and 2 6-9% slower, 512 leaves
/// them as they were.
#[cfg(target_arch = "x86_64")]
const AVX2_CHUNK: usize = 512;

/// An AVX2 tile's accumulators: four output channels by three registers of 8 positions.
#[cfg(target_arch = "x86_64")]
type Avx2Tile = [[std::arch::x86_64::__m256; 3]; 4];

/// The sums of one AVX2 tile: `a[r][v] = Σ_t w[t·ROWS + r] · base[t + 8v .. + 8]` for four
/// rows and 24 positions, in tap order, one fused multiply-add each. 12 accumulators, three
/// inputs and a broadcast take all 16 registers: written in assembly because the compiler's
/// form of the same loop spilled an accumulator to the stack (25% slower); with 8 accumulators
/// (16 positions) the FMAs wait on each other's latency (5 cycles, 2 a cycle: 10 in flight).
///
/// The sums start from `init` (zeros, or the partial sums of the taps before `taps`).
///
/// # Safety
/// The CPU has AVX2 and FMA; `taps` is not empty; `base + t .. + 24` is readable for every
/// tap `t`; `w` holds `ROWS` values per tap.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn tile_avx2(base: *const f32, taps: &[usize], w: *const f32, init: Avx2Tile) -> Avx2Tile {
    let [[mut a0, mut a1, mut a2], [mut a3, mut a4, mut a5], [mut a6, mut a7, mut a8], [mut a9, mut a10, mut a11]] =
        init;
    // SAFETY: the caller's promises; the loop runs `taps.len() >= 1` times, reading one tap
    // offset, three input vectors and four weights a time.
    unsafe {
        std::arch::asm!(
            "2:",
            "mov {t}, qword ptr [{taps}]",
            "vmovups ymm12, ymmword ptr [{base} + 4*{t}]",
            "vmovups ymm13, ymmword ptr [{base} + 4*{t} + 32]",
            "vmovups ymm14, ymmword ptr [{base} + 4*{t} + 64]",
            "vbroadcastss ymm15, dword ptr [{w}]",
            "vfmadd231ps ymm0, ymm15, ymm12",
            "vfmadd231ps ymm1, ymm15, ymm13",
            "vfmadd231ps ymm2, ymm15, ymm14",
            "vbroadcastss ymm15, dword ptr [{w} + 4]",
            "vfmadd231ps ymm3, ymm15, ymm12",
            "vfmadd231ps ymm4, ymm15, ymm13",
            "vfmadd231ps ymm5, ymm15, ymm14",
            "vbroadcastss ymm15, dword ptr [{w} + 8]",
            "vfmadd231ps ymm6, ymm15, ymm12",
            "vfmadd231ps ymm7, ymm15, ymm13",
            "vfmadd231ps ymm8, ymm15, ymm14",
            "vbroadcastss ymm15, dword ptr [{w} + 12]",
            "vfmadd231ps ymm9, ymm15, ymm12",
            "vfmadd231ps ymm10, ymm15, ymm13",
            "vfmadd231ps ymm11, ymm15, ymm14",
            "add {taps}, 8",
            "add {w}, {wstep}",
            "dec {n}",
            "jnz 2b",
            taps = inout(reg) taps.as_ptr() => _,
            w = inout(reg) w => _,
            n = inout(reg) taps.len() => _,
            t = out(reg) _,
            base = in(reg) base,
            wstep = const 4 * ROWS,
            inout("ymm0") a0, inout("ymm1") a1, inout("ymm2") a2, inout("ymm3") a3,
            inout("ymm4") a4, inout("ymm5") a5, inout("ymm6") a6, inout("ymm7") a7,
            inout("ymm8") a8, inout("ymm9") a9, inout("ymm10") a10, inout("ymm11") a11,
            out("ymm12") _, out("ymm13") _, out("ymm14") _, out("ymm15") _,
            options(nostack, readonly),
        );
    }
    [[a0, a1, a2], [a3, a4, a5], [a6, a7, a8], [a9, a10, a11]]
}

/// Positions per run of [`packed_products_avx2`]'s panels.
#[cfg(target_arch = "x86_64")]
pub(crate) const PACKED_PX: usize = AVX2_PX;

/// A matrix product on AVX2 for one block of `ROWS` output rows, the other operand packed in
/// runs of 24 columns: `out[r·ld + 24k + q] = Σ_t weights[t·ROWS + r]·panel[k·n + taps[t] + q]`
/// for every run `k < runs`, where `n = 24·taps.len()` (runs of `[tap][24]`, so that each tile
/// reads its taps one after the other) and `taps[t] = 24t`. Each run is one [`tile_avx2`] per
/// half of the block, stored whole.
///
/// # Safety
/// The CPU has AVX2 and FMA; `taps` is `24t` for `t < taps.len()` (not empty). The lengths
/// (`panel` `runs·24·taps.len()` values, `weights` `ROWS·taps.len()`, `out` `ROWS` rows of
/// `ld >= 24·runs`) and the last tap are asserted.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
pub(crate) unsafe fn packed_products_avx2(
    panel: &[f32],
    taps: &[usize],
    runs: usize,
    weights: &[f32],
    out: &mut [f32],
    ld: usize,
) {
    use std::arch::x86_64::*;
    const HALF: usize = ROWS / 2;
    let n = AVX2_PX * taps.len();
    assert!(panel.len() >= runs * n && weights.len() >= ROWS * taps.len() && out.len() >= ROWS * ld);
    assert!(ld >= runs * AVX2_PX && taps.last() == Some(&(AVX2_PX * (taps.len() - 1))));
    let zero = [[_mm256_setzero_ps(); 3]; 4];
    for k in 0..runs {
        for half in 0..ROWS / HALF {
            // SAFETY: run k's taps lie within `panel` and the weights within `weights` (the
            // caller's promises); rows half·4 .. + 4 of `out` hold 24 values from 24k.
            unsafe {
                let a = tile_avx2(panel.as_ptr().add(k * n), taps, weights.as_ptr().add(half * HALF), zero);
                for (r, a) in a.iter().enumerate() {
                    let row = out.as_mut_ptr().add((half * HALF + r) * ld + k * AVX2_PX);
                    for (v, &a) in a.iter().enumerate() {
                        _mm256_storeu_ps(row.add(8 * v), a);
                    }
                }
            }
        }
    }
}

/// AVX2 tiles of 24 positions, taken as two halves of four output channels ([`tile_avx2`]).
/// Each tile is finished in registers (bias, then `act`) and each
/// register of 8 positions stored straight into its output row where they all lie in one row's
/// columns (the rest value by value: a copy per row run through a tile buffer cost the stem
/// a fifth of its time). Past [`AVX2_CHUNK`] taps, the taps are taken that many at a time over
/// every tile, as on AVX-512, the partial sums kept in a buffer: a pass's weights stay in L1
/// and the input rows one tile reads are still there for the next (the same sums in the same
/// order).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn positions_avx2_fma(
    l: &Layout,
    padded: &[f32],
    weights: &[f32],
    bias: &[f32; ROWS],
    act: Activation,
    out: &mut [f32],
) {
    use std::arch::x86_64::*;
    const HALF: usize = ROWS / 2;
    if l.taps.is_empty() {
        // Nothing to sum (the assembly loop needs a tap): the bias alone.
        positions::<true>(l, padded, weights, bias, out);
        return act.apply_all(out);
    }
    let plane = l.oh * l.ow;
    let (rows, positions) = (out.len() / plane, l.positions());
    assert!(rows <= ROWS && out.len() == rows * plane);
    let (tiles, halves) = (positions.div_ceil(AVX2_PX), rows.div_ceil(HALF));
    let zero = [[_mm256_setzero_ps(); 3]; 4];
    let chunks = l.taps.len().div_ceil(AVX2_CHUNK);
    let mut partial = vec![zero; if chunks > 1 { tiles * halves } else { 0 }];
    for (c, taps) in l.taps.chunks(AVX2_CHUNK).enumerate() {
        for tile in 0..tiles {
            for half in 0..halves {
                // SAFETY: `channel_block` asserted every tap's `MAX_PX >= AVX2_PX` values from
                // any position in `padded`; `weights` holds `ROWS` values per tap.
                let a = unsafe {
                    let base = padded.as_ptr().add(tile * AVX2_PX);
                    let w = weights.as_ptr().add(c * AVX2_CHUNK * ROWS + half * HALF);
                    tile_avx2(base, taps, w, if c == 0 { zero } else { partial[tile * halves + half] })
                };
                if c + 1 < chunks {
                    partial[tile * halves + half] = a;
                    continue;
                }
                for v in 0..AVX2_PX / 8 {
                    let p = tile * AVX2_PX + 8 * v;
                    let (y, x) = (p / l.wp, p % l.wp);
                    let whole = p + 8 <= positions && x + 8 <= l.ow;
                    for (r, a) in a.iter().enumerate().take(rows - half * HALF) {
                        let o = half * HALF + r;
                        let value = act.apply_avx2(_mm256_add_ps(a[v], _mm256_set1_ps(bias[o])));
                        if whole {
                            // SAFETY: row o < rows, columns x..x + 8 <= ow of output row y < oh.
                            unsafe { _mm256_storeu_ps(out.as_mut_ptr().add(o * plane + y * l.ow + x), value) };
                            continue;
                        }
                        let mut vals = [0f32; 8];
                        // SAFETY: 8 values into an array of 8.
                        unsafe { _mm256_storeu_ps(vals.as_mut_ptr(), value) };
                        // Position by position from (y, x), the wide row's dropped columns
                        // skipped (no division per value: small maps store most vectors here).
                        let (mut y, mut x) = (y, x);
                        for &val in vals.iter().take(positions.saturating_sub(p)) {
                            if x < l.ow {
                                out[o * plane + y * l.ow + x] = val;
                            }
                            x += 1;
                            if x == l.wp {
                                (y, x) = (y + 1, 0);
                            }
                        }
                    }
                }
            }
        }
    }
}

/// Portable tiles of 8 positions, vectorised by the compiler. `FUSED`: fused multiply-add
/// (only where the target has it in hardware).
#[inline(always)]
fn positions<const FUSED: bool>(l: &Layout, padded: &[f32], weights: &[f32], bias: &[f32; ROWS], out: &mut [f32]) {
    const PX: usize = 8;
    for p0 in (0..l.positions()).step_by(PX) {
        let mut acc = [[0f32; PX]; ROWS];
        for (&t, w) in l.taps.iter().zip(weights.chunks_exact(ROWS)) {
            let xs: &[f32; PX] = padded[t + p0..t + p0 + PX].try_into().expect("PX values");
            for (a, &w) in acc.iter_mut().zip(w) {
                for (a, &x) in a.iter_mut().zip(xs) {
                    *a = if FUSED { w.mul_add(x, *a) } else { w * x + *a };
                }
            }
        }
        scatter(l, &acc, bias, p0, out);
    }
}

/// Tiles of 32 positions: 16 AVX-512 accumulators, two input loads and eight broadcasts per
/// tap, for more than `CHUNK` taps ([`positions_avx512_fused`] takes fewer). The taps are taken
/// `CHUNK` at a time over every tile, the partial sums kept in `sums`: a chunk's weights stay
/// in L1 and the input rows one tile reads are still there for the next.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
unsafe fn positions_avx512(l: &Layout, padded: &[f32], weights: &[f32], bias: &[f32; ROWS], out: &mut [f32]) {
    const TILE: usize = ROWS * MAX_PX;
    let tiles = l.positions().div_ceil(MAX_PX);
    // The first pass writes every sum (the thread's buffer, not zeroed: [`super::with_words`]).
    super::with_words(tiles * TILE, |sums: &mut [f32]| {
        for (c, taps) in l.taps.chunks(CHUNK).enumerate() {
            for (tile, sums) in sums.chunks_exact_mut(TILE).enumerate() {
                // SAFETY: `channel_block` asserted every tap's tile in `padded`; `weights`
                // holds `ROWS` values per tap; `sums` holds a whole tile.
                unsafe {
                    let base = padded.as_ptr().add(tile * MAX_PX);
                    tile_avx512(base, taps, weights.as_ptr().add(c * CHUNK * ROWS), sums.as_mut_ptr(), c > 0)
                };
            }
        }
        scatter_tiles::<MAX_PX>(l, sums, bias, out);
    })
}

/// [`positions_avx512`] for at most `CHUNK` taps, each tile finished in registers (bias, then
/// `act`, as [`Activation::apply`] computes them) before it goes to the output: the output is
/// not read back for the activation (a pass over it that cost the stem as much as a fifth of
/// its time).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
unsafe fn positions_avx512_fused(
    l: &Layout,
    padded: &[f32],
    weights: &[f32],
    bias: &[f32; ROWS],
    act: Activation,
    out: &mut [f32],
) {
    use std::arch::x86_64::*;
    let tiles = l.positions().div_ceil(MAX_PX);
    for tile in 0..tiles {
        let mut acc = [[0f32; MAX_PX]; ROWS];
        // SAFETY: `channel_block` asserted every tap's tile in `padded`; `weights` holds
        // `ROWS` values per tap; `acc` is a whole tile.
        unsafe {
            tile_avx512(padded.as_ptr().add(tile * MAX_PX), &l.taps, weights.as_ptr(), acc.as_mut_ptr().cast(), false)
        };
        for (row, &b) in acc.iter_mut().zip(bias) {
            let b = _mm512_set1_ps(b);
            for q in 0..MAX_PX / 16 {
                // SAFETY: 16 values of a row of MAX_PX.
                let p = unsafe { row.as_mut_ptr().add(16 * q) };
                let y = act.apply_avx512(_mm512_add_ps(unsafe { _mm512_loadu_ps(p) }, b));
                // SAFETY: as above.
                unsafe { _mm512_storeu_ps(p, y) };
            }
        }
        scatter_with::<MAX_PX, false>(l, &acc, bias, tile * MAX_PX, out);
    }
}

/// One tile's sums over `taps`: `sums[r][q] = (sums[r][q] if accumulate) + Σ_t w[t][r] ·
/// base[t + q]` for `ROWS` rows and `MAX_PX` positions q (`sums` laid out `[ROWS][MAX_PX]`).
///
/// # Safety
/// `base + t .. base + t + MAX_PX` is readable for every tap `t`, `w` holds `ROWS` values per
/// tap, `sums` is valid for reads and writes of a whole tile.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
#[inline]
unsafe fn tile_avx512(base: *const f32, taps: &[usize], mut w: *const f32, sums: *mut f32, accumulate: bool) {
    use std::arch::x86_64::*;
    // SAFETY (pointer reads and writes): the caller's promises.
    unsafe {
        let mut a = [_mm512_setzero_ps(); 2 * ROWS];
        if accumulate {
            for (q, a) in a.iter_mut().enumerate() {
                *a = _mm512_loadu_ps(sums.add(16 * q));
            }
        }
        for &t in taps {
            let x0 = _mm512_loadu_ps(base.add(t));
            let x1 = _mm512_loadu_ps(base.add(t + 16));
            for r in 0..ROWS {
                let b = _mm512_set1_ps(*w.add(r));
                a[2 * r] = _mm512_fmadd_ps(b, x0, a[2 * r]);
                a[2 * r + 1] = _mm512_fmadd_ps(b, x1, a[2 * r + 1]);
            }
            w = w.add(ROWS);
        }
        for (q, a) in a.iter().enumerate() {
            _mm512_storeu_ps(sums.add(16 * q), *a);
        }
    }
}

/// Positions per NEON tile: three 4-lane registers.
#[cfg(target_arch = "aarch64")]
const NEON_PX: usize = 12;

/// NEON tiles of 12 positions: 24 accumulators (8 channels x 3 registers), three input loads
/// and two weight loads per tap, each weight taken by lane (`FMLA v.4s, v.4s, v.s[l]`): 29 of
/// the 32 registers. Taps are taken `CHUNK` at a time over every tile, as on AVX-512.
#[cfg(target_arch = "aarch64")]
#[target_feature(enable = "neon")]
unsafe fn positions_neon(l: &Layout, padded: &[f32], weights: &[f32], bias: &[f32; ROWS], out: &mut [f32]) {
    use std::arch::aarch64::*;
    const CHUNK: usize = 128;
    const TILE: usize = ROWS * NEON_PX;
    let tiles = l.positions().div_ceil(NEON_PX);
    // The first pass writes every sum (the thread's buffer, not zeroed: [`super::with_words`]).
    super::with_words(tiles * TILE, |sums: &mut [f32]| {
        for (c, taps) in l.taps.chunks(CHUNK).enumerate() {
            for (tile, sums) in sums.chunks_exact_mut(TILE).enumerate() {
                // SAFETY (pointer reads and writes): `channel_block` asserted every tap's
                // `MAX_PX` (>= 12) values from any position in `padded`; `weights` holds `ROWS`
                // values per tap; `sums` holds a whole tile.
                unsafe {
                    let s = sums.as_mut_ptr();
                    let mut a = [vdupq_n_f32(0.0); 3 * ROWS];
                    if c > 0 {
                        for (q, a) in a.iter_mut().enumerate() {
                            *a = vld1q_f32(s.add(4 * q));
                        }
                    }
                    let base = padded.as_ptr().add(tile * NEON_PX);
                    let w = weights.as_ptr().add(c * CHUNK * ROWS);
                    // One tap: its 12 inputs, its 8 weights (the compiler makes the loads a pair
                    // load and a single one, and a pair load), 24 multiply-adds.
                    let tap = |a: &mut [float32x4_t; 3 * ROWS], t: usize, w: *const f32| {
                        let float32x4x3_t(x0, x1, x2) = vld1q_f32_x3(base.add(t));
                        let x = [x0, x1, x2];
                        let float32x4x2_t(w0, w1) = vld1q_f32_x2(w);
                        macro_rules! row {
                            ($r:expr, $wv:expr, $lane:expr) => {
                                for q in 0..3 {
                                    a[3 * $r + q] = vfmaq_laneq_f32::<$lane>(a[3 * $r + q], x[q], $wv);
                                }
                            };
                        }
                        row!(0, w0, 0);
                        row!(1, w0, 1);
                        row!(2, w0, 2);
                        row!(3, w0, 3);
                        row!(4, w1, 0);
                        row!(5, w1, 1);
                        row!(6, w1, 2);
                        row!(7, w1, 3);
                    };
                    // Two taps an iteration (in order): the loop's count and branch, and the taps'
                    // offsets (one pair load), once for both: 29.5 instructions a tap where one at a
                    // time took 31 (four at a time compiled to as many a tap).
                    let pairs = taps.chunks_exact(2);
                    let odd = pairs.remainder();
                    for (i, p) in pairs.enumerate() {
                        tap(&mut a, p[0], w.add(2 * i * ROWS));
                        tap(&mut a, p[1], w.add((2 * i + 1) * ROWS));
                    }
                    if let &[t] = odd {
                        tap(&mut a, t, w.add((taps.len() - 1) * ROWS));
                    }
                    for (q, a) in a.iter().enumerate() {
                        vst1q_f32(s.add(4 * q), *a);
                    }
                }
            }
        }
        scatter_tiles::<NEON_PX>(l, sums, bias, out);
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The portable tiles (what the Orin runs) give the sums the dispatched kernel gives.
    #[test]
    fn portable_tiles_equal_the_dispatched_kernel() {
        // 576 taps: passes of taps over the tiles on AVX-512 (128) and AVX2 (512).
        let (ci, h, w, k) = (64, 9, 37, 3);
        let l = Layout::dense(ci, h, w, k);
        let padded: Vec<f32> = (0..ci * h * w + MAX_PX).map(|i| ((i * 7919 % 1000) as f32) / 500.0 - 1.0).collect();
        let weights: Vec<f32> = (0..l.taps.len() * ROWS).map(|i| ((i * 104729 % 997) as f32) / 498.0 - 1.0).collect();
        let bias = [0.5; ROWS];
        let mut a = vec![0f32; 5 * l.oh * l.ow]; // a partial block: 5 of the 8 rows
        let mut b = a.clone();
        channel_block(&l, &padded, &weights, &bias, Activation::NONE, &mut a);
        positions::<false>(&l, &padded, &weights, &bias, &mut b);
        let worst = a.iter().zip(&b).map(|(x, y)| (x - y).abs()).fold(0.0f32, f32::max);
        assert!(worst < 1e-3, "off by {worst}");
        assert!(a.iter().all(|v| *v != 0.0));
        // Every fused path (AVX-512, AVX2, NEON) sums in the same order with one rounding per
        // multiply-add: the same bits as the portable fused loop, so plans agree across CPUs.
        if crate::isa::f32_kernel() != F32Kernel::Portable {
            let mut c = a.clone();
            positions::<true>(&l, &padded, &weights, &bias, &mut c);
            assert!(a == c, "the dispatched fused kernel differs from the portable fused loop");
        }
        // With an activation (applied in registers on AVX-512): `apply_all`'s values.
        for act in [
            Activation { lo: 0.0, hi: 6.0, hard_swish: false },
            Activation { hard_swish: true, ..Activation::NONE },
            Activation { lo: -1.0, hi: 2.0, hard_swish: true },
        ] {
            let mut d = vec![0f32; a.len()];
            channel_block(&l, &padded, &weights, &bias, act, &mut d);
            let mut want = a.clone();
            act.apply_all(&mut want);
            assert!(d == want, "{act:?}");
        }
    }
}
