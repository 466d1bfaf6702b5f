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
use super::{with_words, SyncPtr};

#[cfg(test)]
mod tests;
#[cfg(target_arch = "x86_64")]
mod x86;

#[cfg(target_arch = "x86_64")]
pub(super) use x86::by_channel_avx512;
#[cfg(target_arch = "x86_64")]
use x86::{compact_avx2, compact_avx512, store_sums_avx512, tiles_avx512};

/// Output channels per register.
const L: usize = 16;

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

/// Run `f(block, first tile, tiles)` over `blocks` channel blocks of `tiles` tiles each on
/// tract's threads: each block whole, or, on several threads where there are fewer than 12
/// blocks or they would leave threads idle ([`super::par::parts`]), in runs of tiles, so that
/// every thread has work.
pub(super) fn for_each_item(blocks: usize, tiles: usize, f: impl Fn(usize, usize, usize) + Sync) {
    // One thread: each block whole (its weights read once; split in two, the second half
    // read them again from L3 in a graph: PRL-Track's template layer 4 and zf5 5-15% slower).
    let parts = super::par::parts(blocks, 12, tiles);
    super::par::par_runs(blocks, parts, tiles, |b, run| f(b, run.start, run.len()));
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
