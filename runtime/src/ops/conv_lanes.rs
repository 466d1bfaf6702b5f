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
//!
//! The same packing serves the compact tiles ([`LanePack::run_compact`]): `16·V` channels by
//! consecutive *output* positions (AVX2: 16 by 6; AVX-512: 48 by 8, 32 by 10 or 9, the tile
//! that leaves the fewest positions over in the last one: [`compact_tile`]), each position
//! reading its own row of the padded input through its own pointer, so that a wide row's
//! dropped columns are not computed at all. Where they compute at least 5% fewer values
//! ([`LanePack::tile_for`]) they run faster on both (AVX-512 Xeon: 2-16% on PRL-Track's
//! layers, a few percent fewer multiply-adds a second than the wide tiles).

use super::act::Activation;
use super::conv::ConvShape;
use super::conv_kernel::{tile_positions, Layout, ROWS};
use super::{par_for, with_words, SyncPtr};

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
    /// The tiles the values are packed for (compact ones run by [`LanePack::run_compact`]).
    tile: Tile,
    taps: usize,
    co: usize,
    lines: Vec<Line<T>>,
}

/// The shape of a channels-in-lanes tile: `16·v` output channels by `px` positions, compact
/// (output positions) or wide (positions of the padded rows).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct Tile {
    /// Registers (16 channels each) per tap.
    pub v: usize,
    /// Positions per tile.
    pub px: usize,
    /// Compact rather than wide.
    pub compact: bool,
}

impl Tile {
    /// The wide tile of `v` registers: 48 channels by 8 positions, or `16·v` by 12.
    pub(crate) fn wide(v: usize) -> Tile {
        Tile { v, px: wide_tile_positions(v), compact: false }
    }
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

    /// Pack `taps` taps of `co` channels for `tile` (its `v` registers): `weight(o, tap)`.
    pub(crate) fn pack(co: usize, taps: usize, tile: Tile, weight: impl Fn(usize, usize) -> T) -> Lanes<T> {
        assert!(size_of::<T>() == 4, "lines of 16 values of 4 bytes");
        let v = tile.v;
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
        Lanes { tile, taps, co, lines }
    }

    /// Channels per tile.
    pub(crate) fn channels(&self) -> usize {
        L * self.tile.v
    }

    /// Positions per tile.
    pub(crate) fn positions(&self) -> usize {
        self.tile.px
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
    /// Pack OIHW `weight` (`[co][taps]`) for the tiles [`LanePack::tile_for`] chooses,
    /// keeping the taps `live`; `None` where neither suits this machine.
    pub(crate) fn new(weight: &[f32], taps: usize, live: &[usize], shape: &ConvShape) -> Option<LanePack> {
        let tile = Self::tile_for(shape)?;
        Some(Self::with_tile(weight, taps, live, shape.co, tile))
    }

    /// Pack OIHW `weight` (`[co][taps]`) for `tile`, keeping the taps `live`.
    pub(crate) fn with_tile(weight: &[f32], taps: usize, live: &[usize], co: usize, tile: Tile) -> LanePack {
        Lanes::pack(co, live.len(), tile, |o, i| weight[o * taps + live[i]])
    }

    /// The tile for a convolution of `shape` on this machine; `None` where
    /// [`super::conv_kernel`]'s tiles (channels in rows, positions in lanes) serve.
    ///
    /// - AVX-512, 32 channels or more ([`Lanes::registers_for`]): the wide tiles of `16·v`
    ///   channels, or the compact ones ([`compact_tile`]: 48 channels by 8 output positions or
    ///   32 by 10 or 9) where they compute at least 5% fewer values.
    /// - AVX2: the compact tiles of 16 channels by 6 output positions where they compute at
    ///   least 5% fewer values than [`super::conv_kernel`]'s tiles of 4 channels (half a block)
    ///   by [`tile_positions`] wide positions.
    ///
    /// On AVX2, compact tiles only for 16 input channels or more: on an AMD EPYC (Zen 2) both
    /// tiles run alike per value, except on a layer of few input channels (PRL-Track's first, 3
    /// channels, 11x11, stride 2: 5-10% slower in compact tiles). On AVX-512 they run alike on
    /// that layer too (Intel Xeon, 2026-12-06: its template form, 7.6% fewer values in compact
    /// tiles, made the template graph 1.5% faster on one and on two threads). Small maps, where
    /// a wide row's dropped columns are a large share (PRL-Track's template layers 1-5:
    /// 8-25%), take the compact tiles.
    pub(crate) fn tile_for(shape: &ConvShape) -> Option<Tile> {
        use crate::isa::F32Kernel;
        let ((oh, ow), wp, co) = (shape.out(), shape.phase().1, shape.co);
        let (v, wide_channels, wide_px, (cv, cpx)) = match crate::isa::f32_kernel() {
            F32Kernel::Avx512 => {
                let v = Self::registers_for(co)?;
                (v, L * v, wide_tile_positions(v), compact_tile(co, oh * ow))
            }
            F32Kernel::Avx2Fma => (1, ROWS / 2, tile_positions(), (1, COMPACT_P)),
            _ => return None,
        };
        let wide = ((oh - 1) * wp + ow).div_ceil(wide_px) * wide_px * co.div_ceil(wide_channels) * wide_channels;
        let compact = computed(co, oh * ow, (cv, cpx));
        if co >= L && (shape.ci >= L || cv > 1) && compact * 20 < wide * 19 {
            return Some(Tile { v: cv, px: cpx, compact: true });
        }
        (v > 1).then_some(Tile::wide(v))
    }

    /// Whether [`super::conv::PackedConv`] runs a convolution of `shape` in the compact tiles
    /// on this machine ([`LanePack::tile_for`]).
    pub(crate) fn compact_pays(shape: &ConvShape) -> bool {
        Self::tile_for(shape).is_some_and(|t| t.compact)
    }

    /// The output positions the compact tiles compute for `shape`: the plane's, rounded up to
    /// whole tiles.
    pub(crate) fn compact_positions(shape: &ConvShape) -> usize {
        let (oh, ow) = shape.out();
        let px = Self::tile_for(shape).map_or(COMPACT_P, |t| t.px);
        (oh * ow).div_ceil(px) * px
    }

    /// Whether the packing is for the compact tiles ([`LanePack::run_compact`]).
    pub(crate) fn compact(&self) -> bool {
        self.tile.compact
    }

    /// [`LanePack::run`] for a compact packing, followed by `act`: tiles of `16·v` channels by
    /// [`LanePack::positions`] consecutive output positions, each position reading its own row
    /// of `padded`, so no wide column is computed. `padded` extends past the last tap of the
    /// last position.
    pub(crate) fn run_compact(&self, l: &Layout, padded: &[f32], bias: &[f32], act: Activation, out: &mut [f32]) {
        let (plane, oc, px) = (l.oh * l.ow, self.channels(), self.positions());
        assert!(self.tile.compact && l.taps.len() == self.taps && plane > 0);
        assert!(l.taps.iter().all(|&t| t + l.positions() <= padded.len()));
        assert!(out.len() == self.co * plane && bias.len() >= self.co);
        let dst = SyncPtr(out.as_mut_ptr());
        for_each_item(self.co.div_ceil(oc), plane.div_ceil(px), |b, first, count| {
            with_words(count * oc * px, |sums: &mut [f32]| {
                let weights = self.block(b);
                #[cfg(target_arch = "x86_64")]
                let offsets = compact_offsets(l, first * px, count * px);
                match (self.tile.v, px, crate::isa::f32_kernel()) {
                    // SAFETY: the CPU has AVX2 and FMA; every read stays in `padded` (asserted
                    // above: every tap from any output position's offset) and `weights`.
                    #[cfg(target_arch = "x86_64")]
                    (1, COMPACT_P, crate::isa::F32Kernel::Avx2Fma | crate::isa::F32Kernel::Avx512) => unsafe {
                        compact_avx2(l, padded, weights, &offsets, sums)
                    },
                    // SAFETY: the CPU has AVX-512F; as above.
                    #[cfg(target_arch = "x86_64")]
                    (3, 8, crate::isa::F32Kernel::Avx512) => unsafe {
                        compact_avx512::<3, 8>(l, padded, weights, &offsets, sums)
                    },
                    // SAFETY: as above.
                    #[cfg(target_arch = "x86_64")]
                    (2, 10, crate::isa::F32Kernel::Avx512) => unsafe {
                        compact_avx512::<2, 10>(l, padded, weights, &offsets, sums)
                    },
                    // SAFETY: as above.
                    #[cfg(target_arch = "x86_64")]
                    (2, 9, crate::isa::F32Kernel::Avx512) => unsafe {
                        compact_avx512::<2, 9>(l, padded, weights, &offsets, sums)
                    },
                    _ => compact_tiles(l, oc, px, padded, weights, first, sums),
                }
                let rows = oc.min(self.co - b * oc);
                let places: Vec<(usize, usize)> =
                    (0..count * px).map(|q| (q * oc, first * px + q)).take_while(|&(_, at)| at < plane).collect();
                // SAFETY: each place is within the plane; channels `b·oc .. b·oc + rows <= co`
                // (asserted); this item's alone.
                unsafe { store_sums(&dst, sums, b * oc, rows, plane, &places, bias, act) };
            })
        });
    }

    /// `out` (`co` planes of `oh·ow`) = `act(bias + the convolution of padded)` (`padded`
    /// extends `P` values past the last tap of the last position), split over tract's threads
    /// by channel block and, where there are few blocks, by runs of positions.
    pub(crate) fn run(&self, l: &Layout, padded: &[f32], bias: &[f32], act: Activation, out: &mut [f32]) {
        let (oc, px) = (self.channels(), self.positions());
        assert!(l.taps.len() == self.taps);
        assert!(l.taps.iter().all(|&t| t + l.positions() + px <= padded.len()));
        assert!(out.len() == self.co * l.oh * l.ow && bias.len() >= self.co);
        let dst = SyncPtr(out.as_mut_ptr());
        for_each_item(self.co.div_ceil(oc), l.positions().div_ceil(px), |b, first, count| {
            with_words(count * oc * px, |sums: &mut [f32]| {
                let weights = self.block(b);
                match (self.tile.v, crate::isa::f32_kernel()) {
                    // SAFETY: the CPU has AVX-512F; every read stays in `padded` (asserted
                    // above: the last tile's `px` positions from any tap) and `weights`.
                    #[cfg(target_arch = "x86_64")]
                    (3, crate::isa::F32Kernel::Avx512) => unsafe {
                        tiles_avx512::<3, 8>(l, padded, weights, first, sums)
                    },
                    // SAFETY: as above.
                    #[cfg(target_arch = "x86_64")]
                    (2, crate::isa::F32Kernel::Avx512) => unsafe {
                        tiles_avx512::<2, 12>(l, padded, weights, first, sums)
                    },
                    _ => tiles(l, oc, px, padded, weights, first, sums),
                }
                let rows = oc.min(self.co - b * oc);
                let plane = l.oh * l.ow;
                let places: Vec<(usize, usize)> =
                    places(l, px, first, count * px).map(|(q, at)| (q * oc, at)).collect();
                // SAFETY: each place is within a plane; channels `b·oc .. b·oc + rows <= co`
                // (asserted); this item's alone.
                unsafe { store_sums(&dst, sums, b * oc, rows, plane, &places, bias, act) };
            })
        });
    }
}

/// Store an item's sums (`[position][channel]`; or the int8 tiles' requantised bytes) into
/// channels `first ..` (`rows` of them) of `dst`'s planes of `plane` values as `f(channel,
/// sum)`, for every `(index in sums, place in the plane)` of `places` (a real output
/// position's first sum and its place): channel by channel, so that consecutive stores fall in
/// one plane. Position by position they fell in
/// `rows` planes at once: PRL-Track's first layer (3 input channels, 363 taps, so many outputs
/// for its products) took 1.78-1.83 ms so alone on one thread of an AVX-512 Xeon, 1.65 now.
///
/// # Safety
/// Every place is below `plane`, channels `first .. first + rows` are `dst`'s, and no other
/// thread writes these channels at these places meanwhile.
pub(super) unsafe fn store_by_channel<T: Copy, U>(
    dst: &SyncPtr<U>,
    sums: &[T],
    first: usize,
    rows: usize,
    plane: usize,
    places: &[(usize, usize)],
    f: impl Fn(usize, T) -> U,
) {
    for r in 0..rows {
        let o = first + r;
        for &(i, at) in places {
            // SAFETY: the caller's promises.
            unsafe { *dst.at(o * plane + at) = f(o, sums[i + r]) };
        }
    }
}

/// `act(sum + bias)` of an item's f32 sums stored as [`store_by_channel`] does (the same
/// values), on AVX-512 16 places at a time where the places are consecutive outputs (as an
/// item's real positions are): each channel's 16 values stored as one vector.
///
/// # Safety
/// As [`store_by_channel`]; `bias` holds channels `first .. first + rows`.
#[allow(clippy::too_many_arguments)]
unsafe fn store_sums(
    dst: &SyncPtr<f32>,
    sums: &[f32],
    first: usize,
    rows: usize,
    plane: usize,
    places: &[(usize, usize)],
    bias: &[f32],
    act: Activation,
) {
    #[cfg(target_arch = "x86_64")]
    if crate::isa::f32_kernel() == crate::isa::F32Kernel::Avx512
        && places.windows(2).all(|p| p[1].1 == p[0].1 + 1)
        && places.iter().all(|&(i, _)| i + rows.div_ceil(L) * L <= sums.len())
    {
        // SAFETY: the CPU has AVX-512F; the caller's promises; the places are consecutive.
        return unsafe { store_sums_avx512(dst, sums, first, rows, plane, places, bias, act) };
    }
    // SAFETY: the caller's promises.
    unsafe { store_by_channel(dst, sums, first, rows, plane, places, |o, s| act.apply(s + bias[o])) }
}

/// [`store_sums`] on AVX-512: 16 places at a time, each 16-channel group of their sums
/// transposed in registers (16 x 16), then each channel's 16 values `act(sum + bias)` stored as
/// one vector (masked for the last places). The scalar stores took a quarter of PRL-Track's
/// first layer (3 input channels, 363 taps: an output for every 363 multiply-adds); alone on
/// one thread of an AVX-512 Xeon, the template's first layer took 1.61-1.63 ms so, 1.21
/// without any store. Gathering each channel's 16 sums instead of the transpose: 1.45-1.47 ms
/// (the transpose 4-5% faster in an alternation), and the search graph's first layer 18%
/// slower than with the transpose (10.3-10.4 ms against 8.3-8.6).
///
/// # Safety
/// The CPU has AVX-512F; as [`store_sums`]; the places' output positions are consecutive;
/// every place's sums hold `rows` rounded up to 16 values.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
#[allow(clippy::too_many_arguments)]
unsafe fn store_sums_avx512(
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
pub(super) unsafe fn by_channel_avx512<T: Copy>(
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
fn transpose(r: &mut [std::arch::x86_64::__m512; 16]) {
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

/// Run `f(block, first tile, tiles)` over `blocks` channel blocks of `tiles` tiles each on
/// tract's threads: each block whole, or, on several threads where there are fewer than 12
/// blocks, in runs of tiles, so that every thread has work.
pub(super) fn for_each_item(blocks: usize, tiles: usize, f: impl Fn(usize, usize, usize) + Sync) {
    // One thread: each block whole (its weights read once; split in two, the second half
    // read them again from L3 in a graph: PRL-Track's template layer 4 and zf5 5-15% slower).
    let items: usize = if super::threads() > 1 { 12 } else { 1 };
    let parts = items.div_ceil(blocks).clamp(1, tiles.max(1));
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
#[cfg(test)]
fn outputs<'a, T>(
    l: &'a Layout,
    sums: &'a [T],
    oc: usize,
    px: usize,
    first: usize,
) -> impl Iterator<Item = (&'a [T], usize)> + 'a {
    places(l, px, first, sums.len() / oc).map(move |(q, at)| (&sums[q * oc..(q + 1) * oc], at))
}

/// Of `n` positions of wide tiles of `px` from tile `first`, each real output position's index
/// among them and its index in an output plane (the wide columns and the positions past the
/// end left out).
pub(super) fn places(l: &Layout, px: usize, first: usize, n: usize) -> impl Iterator<Item = (usize, usize)> + '_ {
    (0..n).filter_map(move |i| {
        let p = first * px + i;
        let (y, x) = (p / l.wp, p % l.wp);
        (p < l.positions() && x < l.ow).then_some((i, y * l.ow + x))
    })
}

/// The portable form of the tiles (the reference the AVX-512 one is tested against): for tiles
/// `first..` (as many as `sums` holds), `sums[tile][position][channel]`, fused multiply-adds
/// in tap order from zero.
fn tiles(l: &Layout, oc: usize, px: usize, padded: &[f32], weights: &[f32], first: usize, sums: &mut [f32]) {
    sums.fill(0.0);
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

/// Output positions per AVX2 compact tile (16 channels).
pub(crate) const COMPACT_P: usize = 6;

/// Positions per wide tile of `v` registers on AVX-512: 8 for three (24 accumulators), 12 for
/// two (also 24).
fn wide_tile_positions(v: usize) -> usize {
    if v == 3 {
        8
    } else {
        12
    }
}

/// Output positions per compact tile of `v` registers: 6 on AVX2 (one register of 16
/// channels: 12 accumulators of 8 lanes), 8 on AVX-512 (16 or 24 accumulators).
/// The values a layer of `co` channels and `plane` output positions computes in compact tiles
/// of `16·v` channels by `px` positions (both rounded up to whole tiles).
fn computed(co: usize, plane: usize, (v, px): (usize, usize)) -> usize {
    plane.div_ceil(px) * px * co.div_ceil(L * v) * L * v
}

/// The AVX-512 compact tile (registers, positions) for `co` channels and `plane` output
/// positions: 48 channels by 8 where 48 divides `co`, else 32 by 10; or 32 by 10 or by 9 where
/// that computes at least 2% fewer values (PRL-Track's template: `zf5`'s 6x6 map is four tiles
/// of 9, not of 10, 10% fewer values, 0.65 -> 0.58 ms on one thread; layer 3's 10x10 ten
/// tiles of 10, not 13 of 8).
fn compact_tile(co: usize, plane: usize) -> (usize, usize) {
    let first = if co.is_multiple_of(3 * L) { (3, 8) } else { (2, 10) };
    let best = [first, (2, 10), (2, 9)].into_iter().min_by_key(|&t| computed(co, plane, t)).unwrap_or(first);
    if computed(co, plane, best) * 50 < computed(co, plane, first) * 49 {
        best
    } else {
        first
    }
}

/// Where output position `at` (of `oh·ow`, clamped to the last) reads tap 0 in the padded input.
fn compact_offset(l: &Layout, at: usize) -> usize {
    let at = at.min(l.oh * l.ow - 1);
    at / l.ow * l.wp + at % l.ow
}

/// [`compact_offset`] of the `n` positions from `from`, stepping through the rows (one division
/// for the lot: the kernels' tap passes would otherwise divide once per position and pass, a
/// tenth of a small tile's time on an AVX-512 Xeon).
#[cfg(target_arch = "x86_64")]
fn compact_offsets(l: &Layout, from: usize, n: usize) -> Vec<usize> {
    let last = compact_offset(l, usize::MAX);
    let (mut y, mut x) = (from / l.ow, from % l.ow);
    (0..n)
        .map(|_| {
            let at = if y < l.oh { y * l.wp + x } else { last };
            x += 1;
            if x == l.ow {
                (y, x) = (y + 1, 0);
            }
            at
        })
        .collect()
}

/// The portable form of the compact tiles (the reference the SIMD ones are tested against):
/// for tiles of `oc` channels by `px` positions from tile `first` (as many as `sums` holds),
/// `sums[tile][position][channel]`, fused multiply-adds in tap order from zero; positions past
/// the plane repeat its last.
fn compact_tiles(l: &Layout, oc: usize, px: usize, padded: &[f32], weights: &[f32], first: usize, sums: &mut [f32]) {
    sums.fill(0.0);
    for (i, s) in sums.chunks_exact_mut(oc).enumerate() {
        let base = compact_offset(l, first * px + i);
        for (&t, w) in l.taps.iter().zip(weights.chunks_exact(oc)) {
            let x = padded[base + t];
            for (s, &w) in s.iter_mut().zip(w) {
                *s = x.mul_add(w, *s);
            }
        }
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

/// [`compact_tiles`] on AVX2: 12 accumulators (6 positions by two registers of 8 channels),
/// two weight loads and six broadcasts a tap, the taps taken [`COMPACT_CHUNK`] at a time over
/// every tile. In assembly, as [`super::conv_kernel`]'s AVX2 tile, so that the 12
/// accumulators, two weights and a broadcast keep to the 16 registers.
///
/// # Safety
/// The CPU has AVX2 and FMA; every tap from every offset of `offsets` (6 per tile of `sums`)
/// is within `padded`; `weights` holds 16 values per tap, 32-byte aligned (`Line`).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn compact_avx2(l: &Layout, padded: &[f32], weights: &[f32], offsets: &[usize], sums: &mut [f32]) {
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

/// [`compact_tiles`] on AVX-512: `16·V` channels by `P` output positions, each position
/// reading through its own pointer ([`lane_tiles_avx512`]).
///
/// # Safety
/// The CPU has AVX-512F; every tap from every offset of `offsets` (`P` per tile of `sums`) is
/// within `padded`; `weights` holds `16·V` values per tap, 64-byte aligned (`Line`).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
unsafe fn compact_avx512<const V: usize, const P: usize>(
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

/// [`tiles`] on AVX-512: `V·P` accumulators (24 or 27 of the 32 registers), the tile's `P`
/// consecutive wide positions from one pointer ([`lane_tiles_avx512`]).
///
/// # Safety
/// The CPU has AVX-512F; every tap's `P` positions from any tile of `sums` (from tile `first`)
/// are within `padded`; `weights` holds `16·V` values per tap, 64-byte aligned (`Line`).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
unsafe fn tiles_avx512<const V: usize, const P: usize>(
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::isa::F32Kernel;

    #[test]
    #[cfg(target_arch = "x86_64")]
    fn transposes_sixteen_rows() {
        if !crate::isa().avx512 {
            eprintln!("NOTE: no AVX-512 here (or PRL_ISA caps it): the 16 x 16 transpose is NOT tested here");
            return;
        }
        use std::arch::x86_64::*;
        let m: Vec<f32> = (0..256).map(|i| i as f32).collect();
        // SAFETY: the CPU has AVX-512F (checked above); every load and store is 16 of the 256.
        unsafe {
            let mut r: [__m512; 16] = std::array::from_fn(|i| _mm512_loadu_ps(m.as_ptr().add(16 * i)));
            transpose(&mut r);
            let mut out = vec![0f32; 256];
            for (i, r) in r.iter().enumerate() {
                _mm512_storeu_ps(out.as_mut_ptr().add(16 * i), *r);
            }
            for i in 0..16 {
                for j in 0..16 {
                    assert_eq!(out[i * 16 + j], m[j * 16 + i], "({i}, {j})");
                }
            }
        }
    }

    /// The compact tiles (AVX2's of one register, AVX-512's of two and three, where the CPU
    /// has them) give the bits of the portable compact tiles and of the wide ones (every path
    /// sums in tap order, one rounding per multiply-add), and the convolution's sums: partial
    /// channel blocks, several tap passes, maps smaller than a tile.
    #[test]
    fn compact_tiles_equal_the_portable_and_the_wide_ones() {
        if !matches!(crate::isa::f32_kernel(), F32Kernel::Avx2Fma | F32Kernel::Avx512) {
            println!("NOTE: no AVX2 here (or PRL_ISA caps it): the compact tiles run their portable form only");
        } else if crate::isa::f32_kernel() != F32Kernel::Avx512 {
            println!("NOTE: no AVX-512 here (or PRL_ISA caps it): the compact tiles of 2 and 3 registers run their portable form only");
        }
        for (ci, h, w, k, co) in
            [(30, 11, 23, 3, 40), (40, 12, 12, 3, 16), (7, 5, 6, 5, 48), (3, 4, 4, 3, 33), (20, 9, 9, 3, 96)]
        {
            let l = Layout::dense(ci, h, w, k);
            let taps = l.taps.len();
            let padded: Vec<f32> = (0..ci * h * w + 64).map(|i| ((i * 7919 % 1000) as f32) / 500.0 - 1.0).collect();
            let weight: Vec<f32> = (0..co * taps).map(|i| ((i * 104729 % 997) as f32) / 498.0 - 1.0).collect();
            let live: Vec<usize> = (0..taps).collect();
            let bias: Vec<f32> = (0..co).map(|o| o as f32 / 8.0).collect();
            let plane = l.oh * l.ow;
            for (v, px) in [(1, COMPACT_P), (2, 10), (2, 9), (3, 8)] {
                let pack = LanePack::with_tile(&weight, taps, &live, co, Tile { v, px, compact: true });
                let oc = pack.channels();
                assert!(pack.compact() && px == pack.positions());
                let mut got = vec![0f32; co * plane];
                pack.run_compact(&l, &padded, &bias, Activation::NONE, &mut got);
                let (tiles_n, wide_n) = (plane.div_ceil(px), l.positions().div_ceil(px));
                for b in 0..co.div_ceil(oc) {
                    let block = pack.block(b);
                    let mut sums = vec![0f32; tiles_n * oc * px];
                    compact_tiles(&l, oc, px, &padded, block, 0, &mut sums);
                    let mut wide = vec![0f32; wide_n * oc * px];
                    tiles(&l, oc, px, &padded, block, 0, &mut wide);
                    for (s, at) in outputs(&l, &wide, oc, px, 0) {
                        for (r, s) in s.iter().enumerate().take(co - b * oc) {
                            let o = b * oc + r;
                            let want = s + bias[o];
                            assert!(
                                sums[at * oc + r] + bias[o] == want,
                                "{co} channels, {v}x{px}: compact and wide sums differ"
                            );
                            assert!(
                                got[o * plane + at] == want,
                                "{co} channels, {v}x{px}: output {o} at {at}: dispatched differs"
                            );
                        }
                    }
                }
                // With an activation: applied to every output, as the wide tiles' callers do.
                let act = Activation { lo: -1.0, hi: 2.0, hard_swish: true };
                let mut with_act = vec![0f32; co * plane];
                pack.run_compact(&l, &padded, &bias, act, &mut with_act);
                let mut want = got.clone();
                act.apply_all(&mut want);
                assert!(with_act == want, "{co} channels, {v}x{px}: the activation differs");
                for o in [0, co - 1] {
                    for at in [0, plane - 1] {
                        let (y, x) = (at / l.ow, at % l.ow);
                        let mut acc = bias[o] as f64;
                        for (tap, &t) in l.taps.iter().enumerate() {
                            acc += padded[y * l.wp + x + t] as f64 * weight[o * taps + tap] as f64;
                        }
                        let g = got[o * plane + at] as f64;
                        assert!((g - acc).abs() < 1e-3, "{co} channels, output {o} at {at}: {g} against {acc}");
                    }
                }
            }
        }
    }

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
            let pack = LanePack::with_tile(&weight, taps, &live, co, Tile::wide(v));
            let bias: Vec<f32> = (0..co).map(|o| o as f32 / 8.0).collect();
            let mut got = vec![0f32; co * l.oh * l.ow];
            pack.run(&l, &padded, &bias, Activation::NONE, &mut got);
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
            // With an activation: applied to every output as it is written.
            let act = Activation { lo: -1.0, hi: 2.0, hard_swish: true };
            let mut with_act = vec![0f32; co * l.oh * l.ow];
            pack.run(&l, &padded, &bias, act, &mut with_act);
            act.apply_all(&mut want);
            assert!(with_act == want, "{co} channels: the activation differs");
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
