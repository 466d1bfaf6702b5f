//! [`super::conv::PackedConv`] on AVX-512 with the output channels in the vector lanes.
//!
//! The positions and tap offsets are [`super::conv_kernel`]'s (wide rows, one offset per tap),
//! but a tile is `16·V` output channels (`V` registers) by `P` consecutive positions: per tap,
//! `V` aligned weight loads, `P` broadcasts of one input value each and `V·P` fused
//! multiply-adds. No input load crosses a cache line: the positions-in-lanes tile loads 64 bytes
//! of input from any offset, splitting a line 15 times in 16, and ran at 55-60% of this core's
//! FMA peak on an AVX-512 Xeon with two FMA units, where this tile runs at 65-75%
//! (docs/performance.md). Every output is still its bias plus the sum over the taps in packing
//! order, one rounding per multiply-add: the same bits as every other path.

use super::conv_kernel::Layout;
use super::{par_for, SyncPtr};

/// Output channels per register.
const L: usize = 16;
/// Taps per pass over the tiles: a pass's weights (at most 128 x 48 values, 24 KB) stay in L1.
#[cfg(target_arch = "x86_64")]
const CHUNK: usize = 128;

/// One 64-byte line of packed weights, f32 or i32 words (so that every tap's registers load
/// aligned).
#[derive(Clone, Copy)]
#[repr(C, align(64))]
struct Line<T>([T; L]);

/// Weights packed for tiles of `16·v` channels: `[block][tap][16·v]` values of 4 bytes (f32
/// weights, or i32 words of four i8 weights), zero past the last output channel.
pub(crate) struct Lanes<T> {
    v: usize,
    taps: usize,
    co: usize,
    lines: Vec<Line<T>>,
}

/// The f32 weights of [`super::conv::PackedConv`], packed for its channels-in-lanes tiles.
pub(crate) type LanePack = Lanes<f32>;

impl<T: Copy + Default> Lanes<T> {
    /// The tile for `co` output channels, or `None` when the positions-in-lanes tile suits them
    /// better (fewer than 32 channels would leave most lanes empty): three registers (48
    /// channels by 8 positions) where 48 divides `co`, else two (32 by 12).
    pub(crate) fn registers_for(co: usize) -> Option<usize> {
        match co {
            0..32 => None,
            _ if co.is_multiple_of(48) => Some(3),
            _ => Some(2),
        }
    }

    /// Pack `taps` taps of `co` channels for `v` registers: `weight(o, tap)`.
    pub(crate) fn pack(co: usize, taps: usize, v: usize, weight: impl Fn(usize, usize) -> T) -> Lanes<T> {
        assert!(size_of::<T>() == 4, "lines of 16 values of 4 bytes");
        let oc = L * v;
        let blocks = co.div_ceil(oc);
        let mut lines = Vec::with_capacity(blocks * taps * v);
        for b in 0..blocks {
            for t in 0..taps {
                for k in 0..v {
                    let mut line = Line([T::default(); L]);
                    for (r, w) in line.0.iter_mut().enumerate() {
                        let o = b * oc + k * L + r;
                        if o < co {
                            *w = weight(o, t);
                        }
                    }
                    lines.push(line);
                }
            }
        }
        Lanes { v, taps, co, lines }
    }

    /// Channels per tile.
    pub(crate) fn channels(&self) -> usize {
        L * self.v
    }

    /// Positions per tile.
    pub(super) fn positions(&self) -> usize {
        if self.v == 3 {
            8
        } else {
            12
        }
    }

    /// Output channels and taps packed.
    pub(super) fn shape(&self) -> (usize, usize) {
        (self.co, self.taps)
    }

    /// The packed values as one slice (for [`PartialEq`] and the kernels).
    pub(crate) fn values(&self) -> &[T] {
        // SAFETY: `Line<T>` is `repr(C)` over `[T; L]` with `T` of 4 bytes (asserted in
        // `pack`): 64 bytes, so its alignment adds no padding and the lines are `L · len`
        // contiguous, initialised values.
        unsafe { std::slice::from_raw_parts(self.lines.as_ptr().cast::<T>(), self.lines.len() * L) }
    }

    /// The values of channel block `b` (`[tap][16·v]`).
    pub(super) fn block(&self, b: usize) -> &[T] {
        let n = self.taps * self.channels();
        &self.values()[b * n..(b + 1) * n]
    }
}

impl LanePack {
    /// Pack OIHW `weight` (`[co][taps]`) for `v` registers, keeping the taps `live`.
    pub(crate) fn new(weight: &[f32], taps: usize, live: &[usize], co: usize, v: usize) -> LanePack {
        Lanes::pack(co, live.len(), v, |o, i| weight[o * taps + live[i]])
    }

    /// `out` (`co` planes of `oh·ow`) = `bias` + the convolution of `padded` (which extends
    /// `P` values past the last tap of the last position), split over tract's threads by
    /// channel block and, where there are few blocks, by runs of positions.
    pub(crate) fn run(&self, l: &Layout, padded: &[f32], bias: &[f32], out: &mut [f32]) {
        let (oc, px) = (self.channels(), self.positions());
        assert!(l.taps.len() == self.taps);
        assert!(l.taps.iter().all(|&t| t + l.positions() + px <= padded.len()));
        assert!(out.len() == self.co * l.oh * l.ow && bias.len() >= self.co);
        let dst = SyncPtr(out.as_mut_ptr());
        for_each_item(self.co.div_ceil(oc), l.positions().div_ceil(px), |b, first, count| {
            let weights = self.block(b);
            let mut sums = vec![0f32; count * oc * px];
            match (self.v, crate::isa::f32_kernel()) {
                // SAFETY: the CPU has AVX-512F; every read stays in `padded` (asserted above:
                // the last tile's `px` positions from any tap) and `weights`.
                #[cfg(target_arch = "x86_64")]
                (3, crate::isa::F32Kernel::Avx512) => unsafe {
                    tiles_avx512::<3, 8>(l, padded, weights, first, &mut sums)
                },
                // SAFETY: as above.
                #[cfg(target_arch = "x86_64")]
                (2, crate::isa::F32Kernel::Avx512) => unsafe {
                    tiles_avx512::<2, 12>(l, padded, weights, first, &mut sums)
                },
                _ => tiles(l, oc, px, padded, weights, first, &mut sums),
            }
            let rows = oc.min(self.co - b * oc);
            let plane = l.oh * l.ow;
            for (s, at) in outputs(l, &sums, oc, px, first) {
                for (r, s) in s[..rows].iter().enumerate() {
                    let o = b * oc + r;
                    // SAFETY: `o < co` and `at < plane`, within `out` (asserted); each
                    // (channel, position) belongs to one item only.
                    unsafe { *dst.at(o * plane + at) = s + bias[o] };
                }
            }
        });
    }
}

/// Run `f(block, first tile, tiles)` over `blocks` channel blocks of `tiles` tiles each on
/// tract's threads: each block whole, or, where there are fewer than 12 blocks, in runs of
/// tiles, so that every thread has work.
pub(super) fn for_each_item(blocks: usize, tiles: usize, f: impl Fn(usize, usize, usize) + Sync) {
    let parts = 12usize.div_ceil(blocks).clamp(1, tiles.max(1));
    let per_part = tiles.div_ceil(parts);
    par_for(blocks * parts, |item| {
        let first = (item % parts) * per_part;
        let count = per_part.min(tiles.saturating_sub(first));
        if count > 0 {
            f(item / parts, first, count);
        }
    });
}

/// The outputs held in `sums` (`[tile][position][oc]`, tiles of `px` positions from tile
/// `first`): each real output position's `oc` sums and its index in an output plane (the
/// wide columns and the positions past the end left out).
pub(super) fn outputs<'a, T>(
    l: &'a Layout,
    sums: &'a [T],
    oc: usize,
    px: usize,
    first: usize,
) -> impl Iterator<Item = (&'a [T], usize)> + 'a {
    sums.chunks_exact(oc).enumerate().filter_map(move |(i, s)| {
        let p = first * px + i;
        let (y, x) = (p / l.wp, p % l.wp);
        (p < l.positions() && x < l.ow).then_some((s, y * l.ow + x))
    })
}

/// The portable form of the tiles (the reference the AVX-512 one is tested against): for tiles
/// `first..` (as many as `sums` holds), `sums[tile][position][channel]`, fused multiply-adds
/// in tap order from zero.
fn tiles(l: &Layout, oc: usize, px: usize, padded: &[f32], weights: &[f32], first: usize, sums: &mut [f32]) {
    for (k, tile) in sums.chunks_exact_mut(oc * px).enumerate() {
        let base = (first + k) * px;
        for (q, s) in tile.chunks_exact_mut(oc).enumerate() {
            for (&t, w) in l.taps.iter().zip(weights.chunks_exact(oc)) {
                let x = padded[base + q + t];
                for (s, &w) in s.iter_mut().zip(w) {
                    *s = x.mul_add(w, *s);
                }
            }
        }
    }
}

/// [`tiles`] on AVX-512: `V·P` accumulators (24 or 27 of the 32 registers), the taps taken
/// `CHUNK` at a time over every tile, the partial sums kept in `sums`.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
unsafe fn tiles_avx512<const V: usize, const P: usize>(
    l: &Layout,
    padded: &[f32],
    weights: &[f32],
    first: usize,
    sums: &mut [f32],
) {
    use std::arch::x86_64::*;
    let oc = L * V;
    for (c, taps) in l.taps.chunks(CHUNK).enumerate() {
        for (k, tile) in sums.chunks_exact_mut(oc * P).enumerate() {
            // SAFETY (pointer reads and writes): `run` asserted every tap's `P` positions from
            // any tile in `padded`; `weights` holds `oc` values per tap, 64-byte aligned
            // (`Line`); `tile` holds `P · oc` values.
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
                let base = padded.as_ptr().add((first + k) * P);
                let mut w = weights.as_ptr().add(c * CHUNK * oc);
                for &t in taps {
                    let wv: [__m512; V] = std::array::from_fn(|v| _mm512_load_ps(w.add(L * v)));
                    let x = base.add(t);
                    for (q, a) in a.iter_mut().enumerate() {
                        let b = _mm512_set1_ps(*x.add(q));
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::isa::F32Kernel;

    /// The dispatched tiles give the portable tiles' bits, for both tile shapes, with a
    /// partial last block and several tap chunks.
    #[test]
    fn dispatched_tiles_equal_the_portable_ones() {
        if crate::isa::f32_kernel() != F32Kernel::Avx512 {
            println!("NOTE: no AVX-512 here (or PRL_ISA caps it): PackedConv's channels-in-lanes AVX-512 tiles are not tested here");
        }
        let (ci, h, w, k) = (30, 11, 23, 3);
        let l = Layout::dense(ci, h, w, k);
        let padded: Vec<f32> = (0..ci * h * w + 64).map(|i| ((i * 7919 % 1000) as f32) / 500.0 - 1.0).collect();
        for co in [40, 96] {
            let taps = l.taps.len();
            let weight: Vec<f32> = (0..co * taps).map(|i| ((i * 104729 % 997) as f32) / 498.0 - 1.0).collect();
            let live: Vec<usize> = (0..taps).collect();
            let v = LanePack::registers_for(co).unwrap();
            let pack = LanePack::new(&weight, taps, &live, co, v);
            let bias: Vec<f32> = (0..co).map(|o| o as f32 / 8.0).collect();
            let mut got = vec![0f32; co * l.oh * l.ow];
            pack.run(&l, &padded, &bias, &mut got);
            let (oc, px) = (pack.channels(), pack.positions());
            let tiles_n = l.positions().div_ceil(px);
            let mut want = vec![0f32; co * l.oh * l.ow];
            for b in 0..co.div_ceil(oc) {
                let mut sums = vec![0f32; tiles_n * oc * px];
                tiles(&l, oc, px, &padded, &pack.values()[b * taps * oc..(b + 1) * taps * oc], 0, &mut sums);
                for (i, s) in sums.chunks_exact(oc).enumerate() {
                    let (y, x) = (i / l.wp, i % l.wp);
                    if i >= l.positions() || x >= l.ow {
                        continue;
                    }
                    for (r, s) in s.iter().enumerate().take(co - b * oc) {
                        want[(b * oc + r) * l.oh * l.ow + y * l.ow + x] = s + bias[b * oc + r];
                    }
                }
            }
            assert!(got == want, "{co} channels: the dispatched tiles differ from the portable ones");
            // And the sums are the convolution's (f64 reference).
            for o in [0, co - 1] {
                for (y, x) in [(0, 0), (l.oh - 1, l.ow - 1), (3, 7)] {
                    let mut acc = bias[o] as f64;
                    for (tap, &t) in l.taps.iter().enumerate() {
                        acc += padded[y * l.wp + x + t] as f64 * weight[o * taps + tap] as f64;
                    }
                    let g = got[o * l.oh * l.ow + y * l.ow + x];
                    assert!(
                        (g as f64 - acc).abs() < 1e-3,
                        "{co} channels, output {o} at ({y}, {x}): {g} against {acc}"
                    );
                }
            }
        }
    }
}
