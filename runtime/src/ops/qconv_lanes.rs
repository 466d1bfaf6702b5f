//! [`super::PackedQConv`] on AVX-512 VNNI with the output channels in the vector lanes: the
//! integer form of [`super::conv_lanes`].
//!
//! A tile is `16·V` output channels (`V` registers of i32 lanes) by `P` consecutive positions:
//! per tap group (four input channels of one tap, one 32-bit word of u8 inputs), `V` aligned
//! loads of weight words, `P` broadcasts of one input word each and `V·P` `vpdpbusd`. The
//! positions-in-lanes tile loads 64 bytes of input words from any offset (a split cache line
//! 15 times in 16). The sums are exact integers either way; the requantisation is the scalar
//! formula lane by lane (each lane its channel's offset and scale), so the bytes are the same.

use super::conv_kernel::Layout;
#[cfg(target_arch = "x86_64")]
use super::conv_lanes::by_channel_avx512;
use super::conv_lanes::{for_each_item, places, store_by_channel, Lanes, Tile};
#[cfg(target_arch = "x86_64")]
use super::qconv_kernel::requant_lanes;
use super::qconv_kernel::requant_one;
use super::{with_words, SyncPtr};

/// Output channels per register.
const L: usize = 16;
/// Tap groups per pass over the tiles (a pass's weights, at most 128 x 48 words, stay in L1).
#[cfg(target_arch = "x86_64")]
const CHUNK: usize = 128;

/// Weight words packed for tiles of `16·v` channels ([`Lanes`]: `[block][group][16·v]`, zero
/// past the last channel), with each channel's requantisation.
pub(crate) struct QLanePack {
    lanes: Lanes<i32>,
    /// Per channel, padded to whole blocks: `bias − x0·Σw` and the scale.
    offset: Vec<i32>,
    scale: Vec<f32>,
    /// One scale for every channel: requantised exactly ([`super::qconv_kernel::requant_one`]).
    exact: bool,
}

impl QLanePack {
    /// The tile for `co` channels (as [`Lanes::registers_for`]), or `None`.
    pub(crate) fn registers_for(co: usize) -> Option<usize> {
        Lanes::<i32>::registers_for(co)
    }

    /// Pack `words` (`[co][groups]`, four i8 weights each) for `v` registers.
    pub(crate) fn new(
        words: &[i32],
        groups: usize,
        co: usize,
        v: usize,
        offset: &[i32],
        (scale, exact): (&[f32], bool),
    ) -> QLanePack {
        let lanes = Lanes::pack(co, groups, Tile::wide(v), |o, g| words[o * groups + g]);
        let padded = co.div_ceil(lanes.channels()) * lanes.channels();
        let offset = (0..padded).map(|o| if o < co { offset[o] } else { 0 }).collect();
        let scale = (0..padded).map(|o| if o < co { scale[o] } else { 0.0 }).collect();
        QLanePack { lanes, offset, scale, exact }
    }

    /// Channels per tile.
    pub(crate) fn channels(&self) -> usize {
        self.lanes.channels()
    }

    /// The packed words as one slice.
    pub(crate) fn values(&self) -> &[i32] {
        self.lanes.values()
    }

    /// `out` (`co` planes of `oh·ow` bytes): the requantised convolution of `words` (u8 inputs,
    /// four channels a word, extending `P` words past the last tap of the last position), split
    /// over tract's threads by channel block and, where there are few blocks, by runs of
    /// positions.
    pub(crate) fn run(&self, g: &Layout, words: &[u32], y0: u8, out: &mut [u8]) {
        let (oc, px) = (self.channels(), self.lanes.positions());
        let (co, groups) = self.lanes.shape();
        assert!(g.taps.len() == groups);
        assert!(g.taps.iter().all(|&t| t + g.positions() + px <= words.len()));
        assert!(out.len() == co * g.oh * g.ow);
        let dst = SyncPtr(out.as_mut_ptr());
        for_each_item(co.div_ceil(oc), g.positions().div_ceil(px), |b, first, count| {
            with_words(count * oc * px, |sums: &mut [i32]| {
                let weights = self.lanes.block(b);
                match oc / L {
                    // SAFETY: `QLanePack`s are made only where the CPU has AVX-512 VNNI
                    // (`PackedQConv::new`); every read stays in `words` (asserted above) and
                    // `weights`.
                    #[cfg(target_arch = "x86_64")]
                    3 if crate::isa().vnni => unsafe { tiles_vnni::<3, 8>(g, words, weights, first, sums) },
                    // SAFETY: as above.
                    #[cfg(target_arch = "x86_64")]
                    2 if crate::isa().vnni => unsafe { tiles_vnni::<2, 12>(g, words, weights, first, sums) },
                    _ => tiles(g, oc, px, words, weights, first, sums),
                }
                let rows = oc.min(co - b * oc);
                let plane = g.oh * g.ow;
                let offset = &self.offset[b * oc..(b + 1) * oc];
                let scale = &self.scale[b * oc..(b + 1) * oc];
                let vector = cfg!(target_arch = "x86_64") && crate::isa().avx512;
                // The item's real output positions: consecutive outputs (the wide columns, where
                // there are some, left out), each with its first sum.
                let places: Vec<(usize, usize)> =
                    places(g, px, first, count * px).map(|(q, at)| (q * oc, at)).collect();
                #[cfg(target_arch = "x86_64")]
                if vector && places.windows(2).all(|p| p[1].1 == p[0].1 + 1) {
                    // SAFETY: the CPU has AVX-512F; channels `b·oc .. b·oc + rows < co` at the
                    // places (within a plane) are within `out` (asserted) and this item's alone;
                    // `offset` and `scale` hold `oc` values, a multiple of 16.
                    unsafe {
                        requant_transposed(
                            sums,
                            oc,
                            rows,
                            offset,
                            (scale, self.exact),
                            y0,
                            dst.at(b * oc * plane),
                            plane,
                            &places,
                        )
                    };
                    return;
                }
                // Each position's bytes, then stored channel by channel (`store_by_channel`).
                let mut bytes = vec![0u8; sums.len()];
                for &(i, _) in &places {
                    requantise_lanes(vector, &sums[i..i + oc], offset, (scale, self.exact), y0, &mut bytes[i..i + oc]);
                }
                // SAFETY: each place is within a plane; channels `b·oc .. b·oc + rows <= co`
                // (asserted); this item's alone.
                unsafe { store_by_channel(&dst, &bytes, b * oc, rows, plane, &places, |_, v| v) };
            })
        });
    }
}

/// `out[r] = requant_one(sums[r] + offset[r], scale[r], exact, y0)`, lane by lane (one channel
/// per lane); `vector`: on AVX-512 (the CPU must have it; x86_64 only).
#[cfg_attr(not(target_arch = "x86_64"), allow(unused_variables))]
fn requantise_lanes(
    vector: bool,
    sums: &[i32],
    offset: &[i32],
    (scale, exact): (&[f32], bool),
    y0: u8,
    out: &mut [u8],
) {
    #[cfg(target_arch = "x86_64")]
    if vector {
        for (((s, o), c), out) in
            sums.chunks_exact(L).zip(offset.chunks_exact(L)).zip(scale.chunks_exact(L)).zip(out.chunks_exact_mut(L))
        {
            // SAFETY: the CPU has AVX-512F; 16 values in each slice.
            unsafe { requant16_lanes(s, o, c, exact, y0, out) };
        }
        return;
    }
    for (((&s, &o), &c), out) in sums.iter().zip(offset).zip(scale).zip(out) {
        *out = requant_one(s + o, c, exact, y0);
    }
}

/// [`requantise_lanes`] on 16 lanes ([`requant_lanes`] with a vector of offsets and one of
/// scales).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
unsafe fn requant16_lanes(sums: &[i32], offset: &[i32], scale: &[f32], exact: bool, y0: u8, out: &mut [u8]) {
    use std::arch::x86_64::*;
    assert!(sums.len() == L && offset.len() == L && scale.len() == L && out.len() == L);
    // SAFETY: 16 values in and out (asserted).
    unsafe {
        let (v, o) = (_mm512_loadu_si512(sums.as_ptr().cast()), _mm512_loadu_si512(offset.as_ptr().cast()));
        let q = requant_lanes(v, o, _mm512_loadu_ps(scale.as_ptr()), exact, y0);
        _mm_storeu_si128(out.as_mut_ptr().cast(), _mm512_cvtepi32_epi8(q));
    }
}

/// [`requantise_lanes`] for the `sums` (`oc` per position) of `places` (each position's first
/// sum and its output position; the output positions consecutive), written channel by channel:
/// sixteen positions' sums transposed (16 x 16 i32), then each channel's sixteen requantised
/// with its own offset and scale ([`requant_lanes`], so the same bytes) and stored as 16
/// consecutive bytes of its plane (`out + c·plane + position`): no byte-by-byte scatter. (The
/// wide tiles stored byte by byte took 5.1 ms of PRL-Track's int8 first layer on one thread
/// of an AVX-512 Xeon, an output for every 363 multiply-adds.)
///
/// # Safety
/// The CPU has AVX-512F; `out + c·plane + p` is writable for every channel `c < rows` and
/// place's position `p`; each place's `oc` sums are within `sums`; `offset` and `scale` hold
/// `rows` values, rounded up to 16.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
#[allow(clippy::too_many_arguments)]
unsafe fn requant_transposed(
    sums: &[i32],
    oc: usize,
    rows: usize,
    offset: &[i32],
    (scale, exact): (&[f32], bool),
    y0: u8,
    out: *mut u8,
    plane: usize,
    places: &[(usize, usize)],
) {
    use std::arch::x86_64::*;
    assert!(offset.len() >= rows.div_ceil(L) * L && scale.len() >= rows.div_ceil(L) * L && oc.is_multiple_of(L));
    assert!(places.iter().all(|&(i, _)| i + oc <= sums.len()));
    let store = |ch: usize, r: __m512, at: usize, keep: u16| {
        let (o, c) = (_mm512_set1_epi32(offset[ch]), _mm512_set1_ps(scale[ch]));
        let q = requant_lanes(_mm512_castps_si512(r), o, c, exact, y0);
        // SAFETY: channel ch < rows, at the consecutive positions from `at` that `keep` marks
        // (the caller's promise).
        unsafe { _mm512_mask_cvtepi32_storeu_epi8(out.add(ch * plane + at).cast(), keep, q) };
    };
    // SAFETY: the CPU has AVX-512F.
    unsafe { by_channel_avx512(sums, rows, places, store) }
}

/// The dot product of four u8 inputs and four i8 weights packed in words.
fn dot4(x: u32, w: i32) -> i32 {
    let (x, w) = (x.to_le_bytes(), w.to_le_bytes());
    (0..4).map(|k| x[k] as i32 * w[k] as i8 as i32).sum()
}

/// The portable tiles (the reference the VNNI ones are tested against): tiles `first..` (as
/// many as `sums` holds), `sums[tile][position][channel]`.
fn tiles(g: &Layout, oc: usize, px: usize, words: &[u32], weights: &[i32], first: usize, sums: &mut [i32]) {
    sums.fill(0);
    for (k, tile) in sums.chunks_exact_mut(oc * px).enumerate() {
        let base = (first + k) * px;
        for (q, s) in tile.chunks_exact_mut(oc).enumerate() {
            for (&t, w) in g.taps.iter().zip(weights.chunks_exact(oc)) {
                let x = words[base + q + t];
                for (s, &w) in s.iter_mut().zip(w) {
                    *s += dot4(x, w);
                }
            }
        }
    }
}

/// [`tiles`] on AVX-512 VNNI: `V·P` accumulators, the tap groups taken `CHUNK` at a time over
/// every tile, the partial sums kept in `sums`.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512vnni")]
unsafe fn tiles_vnni<const V: usize, const P: usize>(
    g: &Layout,
    words: &[u32],
    weights: &[i32],
    first: usize,
    sums: &mut [i32],
) {
    use std::arch::x86_64::*;
    let oc = L * V;
    for (c, taps) in g.taps.chunks(CHUNK).enumerate() {
        for (k, tile) in sums.chunks_exact_mut(oc * P).enumerate() {
            // SAFETY (pointer reads and writes): `run` asserted every group's `P` words from
            // any tile in `words`; `weights` holds `oc` words per group, 64-byte aligned
            // (`Line`); `tile` holds `P · oc` values.
            unsafe {
                let s = tile.as_mut_ptr();
                let mut a = [[_mm512_setzero_si512(); V]; P];
                if c > 0 {
                    for (q, a) in a.iter_mut().enumerate() {
                        for (v, a) in a.iter_mut().enumerate() {
                            *a = _mm512_loadu_si512(s.add(oc * q + L * v).cast());
                        }
                    }
                }
                let base = words.as_ptr().add((first + k) * P).cast::<i32>();
                let mut w = weights.as_ptr().add(c * CHUNK * oc);
                for &t in taps {
                    let wv: [__m512i; V] = std::array::from_fn(|v| _mm512_load_si512(w.add(L * v).cast()));
                    let x = base.add(t);
                    for (q, a) in a.iter_mut().enumerate() {
                        let b = _mm512_set1_epi32(*x.add(q));
                        for (a, &w) in a.iter_mut().zip(&wv) {
                            *a = _mm512_dpbusd_epi32(*a, b, w);
                        }
                    }
                    w = w.add(oc);
                }
                for (q, a) in a.iter().enumerate() {
                    for (v, a) in a.iter().enumerate() {
                        _mm512_storeu_si512(s.add(oc * q + L * v).cast(), *a);
                    }
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The dispatched tiles and requantisation give the portable ones' bytes, for both tile
    /// shapes, with a partial block and several chunks of tap groups.
    #[test]
    fn dispatched_tiles_equal_the_portable_ones() {
        if !crate::isa().vnni {
            println!("NOTE: no AVX-512 VNNI here (or PRL_ISA caps it): PackedQConv's channels-in-lanes VNNI tiles are not tested here");
        }
        let (cg, h, w, k) = (20, 11, 23, 3);
        let g = Layout::dense(cg, h, w, k);
        let taps = &g.taps;
        let words: Vec<u32> = (0..cg * h * w + 64).map(|i| (i as u32).wrapping_mul(2_654_435_761)).collect();
        // Per-channel scales (the f32 product), and one scale for all (the exact product).
        for (co, exact) in [(40, false), (96, false), (40, true), (96, true)] {
            let groups = taps.len();
            let wq: Vec<i32> = (0..co * groups).map(|i| (i as i32).wrapping_mul(-1_640_531_535)).collect();
            let offset: Vec<i32> = (0..co as i32).map(|o| 1000 * o - 30_000).collect();
            let scale: Vec<f32> = (0..co).map(|o| 1.0 / (2000.0 + if exact { 0.0 } else { 37.0 * o as f32 })).collect();
            let v = QLanePack::registers_for(co).unwrap();
            let pack = QLanePack::new(&wq, groups, co, v, &offset, (&scale, exact));
            let mut got = vec![0u8; co * g.oh * g.ow];
            pack.run(&g, &words, 9, &mut got);
            let mut want = vec![0u8; co * g.oh * g.ow];
            let mut spread = std::collections::HashSet::new();
            for o in 0..co {
                for y in 0..g.oh {
                    for x in 0..g.ow {
                        let p = y * g.wp + x;
                        let s: i32 =
                            taps.iter().enumerate().map(|(gi, &t)| dot4(words[p + t], wq[o * groups + gi])).sum();
                        let q = requant_one(s + offset[o], scale[o], exact, 9);
                        want[(o * g.oh + y) * g.ow + x] = q;
                        spread.insert(q);
                    }
                }
            }
            assert!(spread.len() > 100, "the test's outputs should spread over the bytes: {}", spread.len());
            if let Some(i) = (0..want.len()).find(|&i| got[i] != want[i]) {
                panic!("{co} channels, exact {exact}: output {i} is {} instead of {}", got[i], want[i]);
            }
        }
    }
}
