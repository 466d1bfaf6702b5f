//! [`super::PackedQConv`] on Intel AMX: `tdpbusd` multiplies a tile of 16 positions x 64 u8
//! input channels by a tile of 64 channels x 16 i8 output-channel weights into 16 x 16 i32
//! sums, 16 384 multiply-adds an instruction (AVX-512 VNNI does 64).
//!
//! The input is copied once into position-major bytes `[Hp·Wp][Cp]` (channels padded to a
//! multiple of 64 with the zero point, positions padded with it too), so for a tap `(i, j)` the
//! 16 positions of an output tile are 16 rows `Cp` bytes apart, loaded as they lie: no im2col.
//! Positions run along whole padded rows (`q = y·Wp + x`); the `Wp − ow` columns past each
//! output row are computed and dropped. The weights are packed at load time into the B-tile
//! layout (`[64/4 channel groups][16 outputs][4 channels]`), in the order the kernel reads them.
//!
//! A block is 32 positions x 32 output channels: four accumulator tiles (`tmm0..3`), two input
//! tiles (`tmm4, tmm5`) and two weight tiles (`tmm6, tmm7`). Pairs of 32 output channels run
//! on the thread pool. Used only where the CPU has AMX-INT8 and Linux lets the process use it
//! (tract-linalg's gate, which asks the kernel once per process).

use super::{par_chunks, ConvShape};

/// Positions (tile rows) and output channels (tile columns) of one accumulator tile.
const T: usize = 16;
/// Input channels per step (bytes of a tile row).
const K: usize = 64;
/// Output channels per block (two weight tiles).
const CO_BLOCK: usize = 2 * T;
/// Positions per block (two input tiles).
const POS_BLOCK: usize = 2 * T;

/// Whether this CPU and OS run AMX int8 tiles.
#[cfg(target_arch = "x86_64")]
pub(crate) fn available() -> bool {
    tract_linalg::x86_64::amx::has_amx_int8()
}

/// Weights packed as B tiles, and the input offset of every step.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) struct AmxWeights {
    /// Input channels padded to a multiple of 64.
    cp: usize,
    /// `[co / 32][step][2 tiles][16 groups][16 outputs][4 channels]`, from [`Self::lead`].
    tiles: Vec<i8>,
    /// Bytes before the first tile, so that it starts on a cache line.
    lead: usize,
    /// Byte offset of each step (tap, 64-channel block) in the position-major input.
    steps: Vec<usize>,
}

impl AmxWeights {
    /// Pack OIHW i8 `kernel` of `shape`; output channels past `co` are zero.
    pub(crate) fn new(shape: &ConvShape, kernel: &[i8]) -> AmxWeights {
        let (co, ci, kh, kw) = (shape.co, shape.ci, shape.kh, shape.kw);
        let cp = ci.div_ceil(K) * K;
        let (_, wp) = shape.padded();
        let mut steps = Vec::with_capacity(kh * kw * cp / K);
        for i in 0..kh {
            for j in 0..kw {
                for cb in 0..cp / K {
                    steps.push((i * wp + j) * cp + cb * K);
                }
            }
        }
        let blocks = co.div_ceil(CO_BLOCK);
        let tile = T * K;
        let mut tiles = vec![0i8; blocks * steps.len() * 2 * tile + 63];
        let lead = tiles.as_ptr().align_offset(64);
        for o in 0..co {
            let (block, half, col) = (o / CO_BLOCK, (o % CO_BLOCK) / T, o % T);
            for c in 0..ci {
                let (cb, group, lane) = (c / K, (c % K) / 4, c % 4);
                for i in 0..kh {
                    for j in 0..kw {
                        let step = (i * kw + j) * (cp / K) + cb;
                        let at = ((block * steps.len() + step) * 2 + half) * tile + (group * T + col) * 4 + lane;
                        tiles[lead + at] = kernel[((o * ci + c) * kh + i) * kw + j];
                    }
                }
            }
        }
        AmxWeights { cp, tiles, lead, steps }
    }

    /// Convolve one NCHW u8 image `src` into NCHW u8 `out`, requantising output channel `o`'s
    /// sums with `offset[o]`, `scale[o]` (exactly or not) and `y0` (see [`super::qconv`]). The caller checked
    /// [`available`].
    pub(crate) fn run(
        &self,
        shape: &ConvShape,
        src: &[u8],
        x0: u8,
        requant: (&[i32], &[f32], bool, u8),
        out: &mut [u8],
    ) {
        let s = shape;
        let (hp, wp) = s.padded();
        let (oh, ow) = s.out();
        let cp = self.cp;
        // Output positions along whole padded rows, rounded up to blocks.
        let wide = ((oh - 1) * wp + ow).div_ceil(POS_BLOCK) * POS_BLOCK;
        let reach = wide + (s.kh - 1) * wp + s.kw;
        let mut buffer = vec![x0; hp.max(reach.div_ceil(wp)) * wp * cp + 63];
        // Rows of tiles on cache lines (`cp` is a multiple of 64).
        let lead = buffer.as_ptr().align_offset(64);
        let input = &mut buffer[lead..];
        par_chunks(&mut input[..hp * wp * cp], wp * cp, |y, row| {
            let Some(sy) = y.checked_sub(s.pad[0]).filter(|&sy| sy < s.h) else { return };
            for c in 0..s.ci {
                let line = &src[(c * s.h + sy) * s.w..(c * s.h + sy + 1) * s.w];
                for (x, &v) in line.iter().enumerate() {
                    row[(x + s.pad[1]) * cp + c] = v;
                }
            }
        });
        let plane = oh * ow;
        let per_block = self.steps.len() * 2 * T * K;
        let input = &*input;
        let tiles = &self.tiles[self.lead..];
        par_chunks(out, CO_BLOCK * plane, |block, out| {
            let weights = &tiles[block * per_block..(block + 1) * per_block];
            let channels = out.len() / plane;
            let mut acc = [0i32; 4 * T * T];
            // This block's outputs along the wide rows: [channel][position].
            let mut rows = vec![0u8; channels * wide];
            // SAFETY: the caller checked AMX is usable; the configuration is this thread's.
            unsafe { configure() };
            for p0 in (0..wide).step_by(POS_BLOCK) {
                // SAFETY: every step reads 32 rows of 64 bytes from `p0·cp + step`, within
                // `reach` positions of `input`; the weights hold `steps` pairs of tiles;
                // `rows` holds 32 positions from `p0` for every channel.
                unsafe {
                    let a = input.as_ptr().add(p0 * cp);
                    block_32x32(a, cp, &self.steps, weights.as_ptr(), acc.as_mut_ptr());
                    let o0 = block * CO_BLOCK;
                    requant_columns(
                        &acc,
                        &requant.0[o0..o0 + channels],
                        (&requant.1[o0..], requant.2),
                        requant.3,
                        &mut rows[p0..],
                        wide,
                    );
                }
            }
            for (o, out) in out.chunks_exact_mut(plane).enumerate() {
                for (y, out) in out.chunks_exact_mut(ow).enumerate() {
                    out.copy_from_slice(&rows[o * wide + y * wp..][..ow]);
                }
            }
            // SAFETY: releases this thread's tile state.
            unsafe { release() };
        });
    }
}

/// Requantise a block's sums `acc` (`[position half][channel half][16 positions][16
/// channels]`) into `rows[o·stride + position]` for the block's `offset.len()` channels.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
unsafe fn requant_columns(
    acc: &[i32; 4 * T * T],
    offset: &[i32],
    (scale, exact): (&[f32], bool),
    y0: u8,
    rows: &mut [u8],
    stride: usize,
) {
    use std::arch::x86_64::*;
    let lanes = _mm512_setr_epi32(0, 16, 32, 48, 64, 80, 96, 112, 128, 144, 160, 176, 192, 208, 224, 240);
    for (o, (&offset, &scale)) in offset.iter().zip(scale).enumerate() {
        for ph in 0..2 {
            let tile = &acc[(ph * 2 + o / T) * T * T + o % T..];
            // SAFETY: the 16 lanes read column `o % T` of a 16 x 16 tile; `rows` holds
            // `POS_BLOCK` bytes at every channel's row (the caller's slice).
            unsafe {
                let column = _mm512_i32gather_epi32::<4>(lanes, tile.as_ptr());
                let bytes = super::qconv_kernel::requant16(column, offset, scale, exact, y0);
                _mm_storeu_si128(rows[o * stride + ph * T..][..T].as_mut_ptr().cast(), bytes);
            }
        }
    }
}

#[cfg(not(target_arch = "x86_64"))]
unsafe fn requant_columns(_: &[i32; 4 * T * T], _: &[i32], _: (&[f32], bool), _: u8, _: &mut [u8], _: usize) {
    unreachable!("AMX is only used on x86_64")
}

/// Load the tile configuration: eight tiles of 16 rows x 64 bytes.
#[cfg(target_arch = "x86_64")]
unsafe fn configure() {
    let mut cfg = [0u8; 64];
    cfg[0] = 1; // palette 1
    for t in 0..8 {
        cfg[16 + 2 * t..18 + 2 * t].copy_from_slice(&(K as u16).to_le_bytes());
        cfg[48 + t] = T as u8;
    }
    // SAFETY: a valid palette-1 configuration; the caller checked AMX is usable.
    unsafe { std::arch::asm!("ldtilecfg [{}]", in(reg) cfg.as_ptr(), options(nostack, readonly)) };
}

#[cfg(target_arch = "x86_64")]
unsafe fn release() {
    // SAFETY: returns the tile state to its initial, unconfigured form.
    unsafe { std::arch::asm!("tilerelease", options(nostack, nomem)) };
}

/// `acc[ph][oh][r][c] = Σ_steps Σ_k a[(ph·16 + r)·cp + step + k] · w[step][oh][k/4][c][k%4]`
/// for a configured thread: two input tiles of 16 rows `cp` bytes apart, two weight tiles.
#[cfg(target_arch = "x86_64")]
unsafe fn block_32x32(a: *const u8, cp: usize, steps: &[usize], w: *const i8, acc: *mut i32) {
    // SAFETY: the caller guarantees the reads are in bounds and the tiles are configured.
    unsafe {
        std::arch::asm!(
            "tilezero tmm0",
            "tilezero tmm1",
            "tilezero tmm2",
            "tilezero tmm3",
            "2:",
            "mov {p}, [{steps}]",
            "add {p}, {a}",
            "tileloadd tmm4, [{p} + {cp}*1]",
            "add {p}, {a16}",
            "tileloadd tmm5, [{p} + {cp}*1]",
            "tileloadd tmm6, [{w} + {row}*1]",
            "tileloadd tmm7, [{w} + {row}*1 + 1024]",
            "add {w}, 2048",
            "tdpbusd tmm0, tmm4, tmm6",
            "tdpbusd tmm1, tmm4, tmm7",
            "tdpbusd tmm2, tmm5, tmm6",
            "tdpbusd tmm3, tmm5, tmm7",
            "add {steps}, 8",
            "dec {n}",
            "jnz 2b",
            "tilestored [{acc} + {row}*1], tmm0",
            "tilestored [{acc} + {row}*1 + 1024], tmm1",
            "tilestored [{acc} + {row}*1 + 2048], tmm2",
            "tilestored [{acc} + {row}*1 + 3072], tmm3",
            steps = inout(reg) steps.as_ptr() => _,
            n = inout(reg) steps.len() => _,
            w = inout(reg) w => _,
            p = out(reg) _,
            a = in(reg) a,
            a16 = in(reg) 16 * cp,
            cp = in(reg) cp,
            row = in(reg) K,
            acc = in(reg) acc,
            options(nostack),
        );
    }
}

#[cfg(not(target_arch = "x86_64"))]
unsafe fn configure() {}

#[cfg(not(target_arch = "x86_64"))]
unsafe fn release() {}

#[cfg(not(target_arch = "x86_64"))]
unsafe fn block_32x32(_: *const u8, _: usize, _: &[usize], _: *const i8, _: *mut i32) {
    unreachable!("AMX is only used on x86_64")
}
