//! The x86 tiles of [`super::LanePack`]: the compact ones on AVX2 (16 channels by 6 positions, in
//! assembly) and AVX-512, the wide ones on AVX-512, and the AVX-512 stores that turn a tile's
//! sums into channels' planes.

use super::super::act::Activation;
use super::super::conv_kernel::Layout;
use super::super::SyncPtr;
use super::{COMPACT_P, L};

/// Taps per pass over the tiles: a pass's weights (at most 128 x 48 values, 24 KB) stay in L1.
#[cfg(target_arch = "x86_64")]
const CHUNK: usize = 128;

/// [`super::store_sums`] on AVX-512: 16 places at a time, each 16-channel group of their sums
/// transposed in registers (16 x 16), then each channel's 16 values `act(sum + bias)` stored as
/// one vector (masked for the last places). The scalar stores took a quarter of PRL-Track's
/// first layer (3 input channels, 363 taps: an output for every 363 multiply-adds); alone on
/// one thread of an AVX-512 Xeon, the template's first layer took 1.61-1.63 ms so, 1.21
/// without any store. Gathering each channel's 16 sums instead of the transpose: 1.45-1.47 ms
/// (the transpose 4-5% faster in an alternation), and the search graph's first layer 18%
/// slower than with the transpose (10.3-10.4 ms against 8.3-8.6).
///
/// # Safety
/// The CPU has AVX-512F; as [`super::store_sums`]; the places' output positions are consecutive;
/// every place's sums hold `rows` rounded up to 16 values.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
#[allow(clippy::too_many_arguments)]
pub(super) unsafe fn store_sums_avx512(
    dst: &SyncPtr<f32>,
    sums: &[f32],
    first: usize,
    rows: usize,
    plane: usize,
    places: &[(usize, usize)],
    bias: &[f32],
    act: Activation,
) {
    use std::arch::x86_64::*;
    let store = |c: usize, r: __m512, at: usize, keep: u16| {
        let o = first + c;
        let v = act.apply_avx512(_mm512_add_ps(r, _mm512_set1_ps(bias[o])));
        // SAFETY: channel `o` at the consecutive positions from `at` that `keep` marks, within
        // its plane and this caller's alone (the caller's promises).
        unsafe { _mm512_mask_storeu_ps(dst.at(o * plane + at), keep, v) };
    };
    // SAFETY: the CPU has AVX-512F.
    unsafe { by_channel_avx512(sums, rows, places, store) }
}

/// The walk the AVX-512 stores of the f32 and int8 tiles share ([`store_sums_avx512`] and
/// `qconv_lanes`' requantisation): the sums of 16 places at a time (each place's sums from
/// index `places[k].0`, their output positions consecutive) transposed 16 x 16 in registers a
/// group of 16 channels at a time, then `f(channel, its 16 values, the first place's position,
/// the places kept)` for every channel below `rows`. Sums of 4-byte integers come as their
/// bits in f32 lanes.
///
/// # Safety
/// The CPU has AVX-512F.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
#[inline]
pub(in crate::ops) unsafe fn by_channel_avx512<T: Copy>(
    sums: &[T],
    rows: usize,
    places: &[(usize, usize)],
    mut f: impl FnMut(usize, std::arch::x86_64::__m512, usize, u16),
) {
    use std::arch::x86_64::*;
    assert!(size_of::<T>() == 4 && places.iter().all(|&(i, _)| i + rows.div_ceil(L) * L <= sums.len()));
    for k0 in (0..places.len()).step_by(L) {
        let m = (places.len() - k0).min(L);
        let keep = ((1u32 << m) - 1) as u16;
        for j in 0..rows.div_ceil(L) {
            let mut r = [_mm512_setzero_ps(); L];
            for (i, r) in r.iter_mut().enumerate().take(m) {
                // SAFETY: channels 16j .. 16j + 16 of place k0 + i's sums, 4 bytes each
                // (asserted).
                *r = unsafe { _mm512_loadu_ps(sums.as_ptr().add(places[k0 + i].0 + L * j).cast()) };
            }
            transpose(&mut r);
            for (c, r) in r.iter().enumerate().take((rows - L * j).min(L)) {
                f(L * j + c, *r, places[k0].1, keep);
            }
        }
    }
}

/// Transpose sixteen 16-lane rows in place (`r[i][j]` becomes `r[j][i]`; the lanes' bits as they
/// are): pairs interleaved, then quads, then 128-bit lanes twice.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
#[inline]
pub(super) fn transpose(r: &mut [std::arch::x86_64::__m512; 16]) {
    use std::arch::x86_64::*;
    let mut t = [_mm512_setzero_ps(); 16];
    for i in 0..8 {
        t[2 * i] = _mm512_unpacklo_ps(r[2 * i], r[2 * i + 1]);
        t[2 * i + 1] = _mm512_unpackhi_ps(r[2 * i], r[2 * i + 1]);
    }
    for i in 0..4 {
        let (a, b, c, d) = (t[4 * i], t[4 * i + 1], t[4 * i + 2], t[4 * i + 3]);
        r[4 * i] = _mm512_shuffle_ps::<0x44>(a, c);
        r[4 * i + 1] = _mm512_shuffle_ps::<0xEE>(a, c);
        r[4 * i + 2] = _mm512_shuffle_ps::<0x44>(b, d);
        r[4 * i + 3] = _mm512_shuffle_ps::<0xEE>(b, d);
    }
    for g in [0, 8] {
        for j in 0..4 {
            t[g + j] = _mm512_shuffle_f32x4::<0x88>(r[g + j], r[g + j + 4]);
            t[g + j + 4] = _mm512_shuffle_f32x4::<0xDD>(r[g + j], r[g + j + 4]);
        }
    }
    for j in 0..8 {
        r[j] = _mm512_shuffle_f32x4::<0x88>(t[j], t[j + 8]);
        r[j + 8] = _mm512_shuffle_f32x4::<0xDD>(t[j], t[j + 8]);
    }
}

/// How many taps ahead the first tile of a pass asks for the weights it will read. A layer's
/// weights come from L3 in a graph (the layer before evicted them from L2), and the hardware
/// prefetcher did not keep up: PRL-Track's template layer 4 (384 channels, 10x10) and `zf5`
/// took 1.24-1.40 and 0.60-0.74 ms so (L2 cold), 0.90-1.03 and 0.39-0.45 with the weights in
/// L2; 1.01-1.14 and 0.49-0.59 cold with the prefetches (Xeon, AVX-512, one thread).
#[cfg(target_arch = "x86_64")]
const PREFETCH: usize = 16;

/// Taps per pass over the compact tiles (16 KB of weights, half an L1).
#[cfg(target_arch = "x86_64")]
const COMPACT_CHUNK: usize = 256;

/// [`super::compact_tiles`] on AVX2: 12 accumulators (6 positions by two registers of 8 channels),
/// two weight loads and six broadcasts a tap, the taps taken [`COMPACT_CHUNK`] at a time over
/// every tile. In assembly, as [`crate::ops::conv_kernel`]'s AVX2 tile, so that the 12
/// accumulators, two weights and a broadcast keep to the 16 registers.
///
/// # Safety
/// The CPU has AVX2 and FMA; every tap from every offset of `offsets` (6 per tile of `sums`)
/// is within `padded`; `weights` holds 16 values per tap, 32-byte aligned (`Line`).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
pub(super) unsafe fn compact_avx2(l: &Layout, padded: &[f32], weights: &[f32], offsets: &[usize], sums: &mut [f32]) {
    use std::arch::x86_64::*;
    for (c, taps) in l.taps.chunks(COMPACT_CHUNK).enumerate() {
        for (tile, at) in sums.chunks_exact_mut(L * COMPACT_P).zip(offsets.chunks_exact(COMPACT_P)) {
            let p: [*const f32; COMPACT_P] = std::array::from_fn(|q| {
                // SAFETY: an offset within `padded` (every output position's tap 0 is).
                unsafe { padded.as_ptr().add(at[q]) }
            });
            let s = tile.as_mut_ptr();
            // SAFETY (reads and writes): `tile` holds 6 x 16 values; the caller's promises
            // for `padded` and `weights`; the loop runs `taps.len() >= 1` times, reading one tap
            // offset, two weight vectors and six inputs a time.
            unsafe {
                let mut a: [__m256; 2 * COMPACT_P] = if c == 0 {
                    [_mm256_setzero_ps(); 2 * COMPACT_P]
                } else {
                    std::array::from_fn(|v| _mm256_loadu_ps(s.add(8 * v)))
                };
                let [a0, a1, a2, a3, a4, a5, a6, a7, a8, a9, a10, a11] = &mut a;
                std::arch::asm!(
                    "2:",
                    "mov {t}, qword ptr [{taps}]",
                    "vmovaps ymm12, ymmword ptr [{w}]",
                    "vmovaps ymm13, ymmword ptr [{w} + 32]",
                    "vbroadcastss ymm14, dword ptr [{p0} + 4*{t}]",
                    "vfmadd231ps ymm0, ymm14, ymm12",
                    "vfmadd231ps ymm1, ymm14, ymm13",
                    "vbroadcastss ymm15, dword ptr [{p1} + 4*{t}]",
                    "vfmadd231ps ymm2, ymm15, ymm12",
                    "vfmadd231ps ymm3, ymm15, ymm13",
                    "vbroadcastss ymm14, dword ptr [{p2} + 4*{t}]",
                    "vfmadd231ps ymm4, ymm14, ymm12",
                    "vfmadd231ps ymm5, ymm14, ymm13",
                    "vbroadcastss ymm15, dword ptr [{p3} + 4*{t}]",
                    "vfmadd231ps ymm6, ymm15, ymm12",
                    "vfmadd231ps ymm7, ymm15, ymm13",
                    "vbroadcastss ymm14, dword ptr [{p4} + 4*{t}]",
                    "vfmadd231ps ymm8, ymm14, ymm12",
                    "vfmadd231ps ymm9, ymm14, ymm13",
                    "vbroadcastss ymm15, dword ptr [{p5} + 4*{t}]",
                    "vfmadd231ps ymm10, ymm15, ymm12",
                    "vfmadd231ps ymm11, ymm15, ymm13",
                    "add {taps}, 8",
                    "add {w}, 64",
                    "dec {n}",
                    "jnz 2b",
                    taps = inout(reg) taps.as_ptr() => _,
                    w = inout(reg) weights.as_ptr().add(c * COMPACT_CHUNK * L) => _,
                    n = inout(reg) taps.len() => _,
                    t = out(reg) _,
                    p0 = in(reg) p[0], p1 = in(reg) p[1], p2 = in(reg) p[2],
                    p3 = in(reg) p[3], p4 = in(reg) p[4], p5 = in(reg) p[5],
                    inout("ymm0") *a0, inout("ymm1") *a1, inout("ymm2") *a2, inout("ymm3") *a3,
                    inout("ymm4") *a4, inout("ymm5") *a5, inout("ymm6") *a6, inout("ymm7") *a7,
                    inout("ymm8") *a8, inout("ymm9") *a9, inout("ymm10") *a10, inout("ymm11") *a11,
                    out("ymm12") _, out("ymm13") _, out("ymm14") _, out("ymm15") _,
                    options(nostack, readonly),
                );
                for (v, a) in a.iter().enumerate() {
                    _mm256_storeu_ps(s.add(8 * v), *a);
                }
            }
        }
    }
}

/// [`super::compact_tiles`] on AVX-512: `16·V` channels by `P` output positions, each position
/// reading through its own pointer ([`lane_tiles_avx512`]).
///
/// # Safety
/// The CPU has AVX-512F; every tap from every offset of `offsets` (`P` per tile of `sums`) is
/// within `padded`; `weights` holds `16·V` values per tap, 64-byte aligned (`Line`).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
pub(super) unsafe fn compact_avx512<const V: usize, const P: usize>(
    l: &Layout,
    padded: &[f32],
    weights: &[f32],
    offsets: &[usize],
    sums: &mut [f32],
) {
    // SAFETY: the caller's promises; each tile's pointers are its positions' offsets.
    unsafe {
        lane_tiles_avx512::<V, P>(l, weights, sums, |k| {
            std::array::from_fn(|q| padded.as_ptr().add(offsets[k * P + q]))
        })
    }
}

/// [`super::tiles`] on AVX-512: `V·P` accumulators (24 or 27 of the 32 registers), the tile's `P`
/// consecutive wide positions from one pointer ([`lane_tiles_avx512`]).
///
/// # Safety
/// The CPU has AVX-512F; every tap's `P` positions from any tile of `sums` (from tile `first`)
/// are within `padded`; `weights` holds `16·V` values per tap, 64-byte aligned (`Line`).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
pub(super) unsafe fn tiles_avx512<const V: usize, const P: usize>(
    l: &Layout,
    padded: &[f32],
    weights: &[f32],
    first: usize,
    sums: &mut [f32],
) {
    // SAFETY: the caller's promises (`run` asserted them).
    unsafe {
        lane_tiles_avx512::<V, P>(l, weights, sums, |k| {
            let base = padded.as_ptr().add((first + k) * P);
            std::array::from_fn(|q| base.add(q))
        })
    }
}

/// The AVX-512 tiles of `16·V` channels by `P` positions, position `q` of tile `k` reading
/// tap `t` at `inputs(k)[q] + t`: the taps taken `CHUNK` at a time over every tile, the
/// partial sums kept in `sums` (`[tile][position][16·V]`). Per tap, `V` aligned weight loads,
/// `P` broadcasts and `V·P` fused multiply-adds, in tap order from zero.
///
/// # Safety
/// The CPU has AVX-512F; every tap from every pointer `inputs` gives is readable; `weights`
/// holds `16·V` values per tap, 64-byte aligned (`Line`).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
unsafe fn lane_tiles_avx512<const V: usize, const P: usize>(
    l: &Layout,
    weights: &[f32],
    sums: &mut [f32],
    inputs: impl Fn(usize) -> [*const f32; P],
) {
    use std::arch::x86_64::*;
    let oc = L * V;
    for (c, taps) in l.taps.chunks(CHUNK).enumerate() {
        for (k, tile) in sums.chunks_exact_mut(oc * P).enumerate() {
            let p = inputs(k);
            // SAFETY (pointer reads and writes): the caller's promises for the inputs and
            // `weights`; `tile` holds `P · oc` values.
            unsafe {
                let s = tile.as_mut_ptr();
                let mut a = [[_mm512_setzero_ps(); V]; P];
                if c > 0 {
                    for (q, a) in a.iter_mut().enumerate() {
                        for (v, a) in a.iter_mut().enumerate() {
                            *a = _mm512_loadu_ps(s.add(oc * q + L * v));
                        }
                    }
                }
                let mut w = weights.as_ptr().add(c * CHUNK * oc);
                for &t in taps {
                    if k == 0 {
                        // The pass's first tile brings its weights in (the later ones find
                        // them in L1): ask for them ahead (a hint; it never faults).
                        for v in 0..V {
                            _mm_prefetch::<_MM_HINT_T0>(w.wrapping_add(oc * PREFETCH + L * v) as *const i8);
                        }
                    }
                    let wv: [__m512; V] = std::array::from_fn(|v| _mm512_load_ps(w.add(L * v)));
                    for (a, p) in a.iter_mut().zip(&p) {
                        let b = _mm512_set1_ps(*p.add(t));
                        for (a, &w) in a.iter_mut().zip(&wv) {
                            *a = _mm512_fmadd_ps(b, w, *a);
                        }
                    }
                    w = w.add(oc);
                }
                for (q, a) in a.iter().enumerate() {
                    for (v, a) in a.iter().enumerate() {
                        _mm512_storeu_ps(s.add(oc * q + L * v), *a);
                    }
                }
            }
        }
    }
}
