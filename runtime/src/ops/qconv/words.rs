//! How a [`PackedQConv`] runs an image: the input copied once into words of four channels
//! (four u8 inputs side by side, one 32-bit word, padded with the input zero point; stride 2
//! stored as four phases), then the tiles of the CPU's words path over every tap group, and
//! the sums requantised; and the byte-layout helpers that copy: rows of channels into words,
//! four planes interleaved, the output transposed to positions first.

use std::ops::Range;

use super::super::par::{par_runs, parts};
#[cfg(target_arch = "x86_64")]
use super::super::par_for;
#[cfg(target_arch = "aarch64")]
use super::super::qconv_kernel::tiles_sdot;
use super::super::qconv_kernel::{bytemuck_words, tiles_avx2, tiles_vnni};
#[cfg(target_arch = "x86_64")]
use super::super::qconv_kernel::{tiles_avx2_requant, tiles_vnni_requant, Planes};
use super::super::{par_chunks, with_words, SyncPtr};
use super::{PackedQConv, WordsPath, PX, ROWS};

impl PackedQConv {
    /// One image on words of four channels: AVX-512 VNNI, AVX2 or aarch64 SDOT, into `dst`
    /// as channels' planes or (`positions_first`, a matrix product's output on the x86 paths)
    /// as rows of channels.
    pub(super) fn run_words(
        &self,
        path: WordsPath,
        src: Src,
        requant: impl Fn(usize, &[i32], &mut [u8]) + Sync,
        dst: &mut [u8],
        positions_first: bool,
    ) {
        let s = &self.shape;
        let (hq, wq) = s.phase();
        let (oh, ow) = s.out();
        let plane = oh * ow;
        // Words of four channels, each group's plane stored as its `stride²` phases
        // ([`ConvShape::phase`]); room past the end for the last tile.
        let group_words = s.stride * s.stride * hq * wq;
        // SDOT takes i8 inputs: x − 128, the top bit of every byte flipped as it is written.
        let flip = if path == WordsPath::Sdot { 0x80u8 } else { 0 };
        let flip4 = u32::from_ne_bytes([flip; 4]);
        let mut words = vec![u32::from_ne_bytes([self.x0 ^ flip; 4]); s.ci.div_ceil(4) * group_words + PX + wq];
        // Each group of four channels fills its own words, the groups side by side on the threads.
        let row_parts = parts(s.ci.div_ceil(4), 1, s.h);
        par_chunks(bytemuck_words(&mut words), group_words * 4, |g, bytes| {
            let src = match src {
                Src::Planes(src) => src,
                Src::Rows(rows) => return row_words(rows, s.ci, g, bytes, flip),
            };
            if s.stride == 1 && 4 * g + 4 <= s.ci {
                // Four whole channels: each position's word from the four rows at once (the byte
                // by byte form below cost as much as the products on NanoTrack's 1x1 layers).
                // SAFETY: the chunk is whole words of the `u32` buffer (`group_words · 4` bytes
                // from a word boundary), and any four bytes are a valid `u32`.
                let (head, group, _) = unsafe { bytes.align_to_mut::<u32>() };
                debug_assert!(head.is_empty());
                let plane = |c: usize, y: usize| &src[((4 * g + c) * s.h + y) * s.w..][..s.w];
                if s.pad == [0; 4] {
                    // Unpadded rows follow each other: the planes interleaved whole.
                    let n = s.h * s.w;
                    let plane = |c: usize| &src[(4 * g + c) * n..][..n];
                    interleave4([plane(0), plane(1), plane(2), plane(3)], &mut group[..n], flip4);
                    return;
                }
                for y in 0..s.h {
                    let at = (y + s.pad[0]) * wq + s.pad[1];
                    interleave4([plane(0, y), plane(1, y), plane(2, y), plane(3, y)], &mut group[at..at + s.w], flip4);
                }
                return;
            }
            // Channel by channel, byte by byte; the rows in parts over the threads where the
            // groups alone would leave threads idle (backbone layer 1: three channels, one
            // group, 287 rows of 287 bytes).
            let len = bytes.len();
            let dst = SyncPtr(bytes.as_mut_ptr());
            // The `n` words from word `at` of this group's chunk, as bytes: the words of one
            // padded row (each row's runs lie in rows of its phases that no other row has).
            let run = |at: usize, n: usize| {
                assert!((at + n) * 4 <= len, "PackedQConv: a row's words past its group");
                // SAFETY: within the chunk (asserted); each part writes its own rows' words
                // alone, and a part's runs are used one at a time.
                unsafe { std::slice::from_raw_parts_mut(dst.at(at * 4), n * 4) }
            };
            par_runs(1, row_parts, s.h, |_, ys| {
                for c in 4 * g..(4 * g + 4).min(s.ci) {
                    for y in ys.clone() {
                        let row = &src[(c * s.h + y) * s.w..(c * s.h + y + 1) * s.w];
                        let yp = y + s.pad[0];
                        if s.stride == 1 {
                            let words = run(yp * wq + s.pad[1], s.w);
                            for (word, &v) in words.chunks_exact_mut(4).zip(row) {
                                word[c % 4] = v ^ flip;
                            }
                            continue;
                        }
                        // Stride 2: even and odd padded columns go to the row's two phases.
                        for (first, at) in s.phase_runs(yp) {
                            let words = run(at, (s.w - first).div_ceil(2));
                            for (word, &v) in words.chunks_exact_mut(4).zip(row[first..].iter().step_by(2)) {
                                word[c % 4] = v ^ flip;
                            }
                        }
                    }
                }
            });
        });
        let (words, taps) = (&words, &self.layout.taps);
        #[cfg(target_arch = "x86_64")]
        if matches!(path, WordsPath::Vnni | WordsPath::Avx2) && wq == ow && s.kh * s.kw == 1 && s.stride == 1 {
            // A 1x1 layer of stride 1: each tile of positions is consecutive outputs,
            // requantised in the tile's registers (VNNI's tiles of 32 positions, AVX2's of 8).
            let per_block = taps.len() * ROWS;
            let positions = self.layout.positions();
            // Channel block `b`'s `rows` channels from `out`, in planes or positions first.
            let block = |b: usize, out: *mut u8, rows: usize, positions_first: Option<usize>| {
                let channels = b * ROWS..(b + 1) * ROWS;
                let planes = Planes {
                    out,
                    plane,
                    rows,
                    offset: &self.offset[channels.clone()],
                    scale: &self.scale[channels],
                    exact: self.exact,
                    y0: self.y0,
                    positions_first,
                };
                // SAFETY: the path is one the CPU has ([`words_path`]: AVX-512F and VNNI, or
                // AVX2 and FMA); every tile of every tap lies in `words` (padded by `PX + wp`
                // words); `out` holds the block's `rows <= ROWS` channels of `positions`
                // outputs (below); `pairs` holds two words per weight word.
                unsafe {
                    if path == WordsPath::Vnni {
                        let weights = &self.weights[b * per_block..(b + 1) * per_block];
                        tiles_vnni_requant(words, taps, weights, positions, &planes)
                    } else {
                        let pairs = self.pairs.as_deref().expect("the AVX2 path's pairs are packed with the op");
                        tiles_avx2_requant(
                            words,
                            taps,
                            &pairs[2 * b * per_block..2 * (b + 1) * per_block],
                            positions,
                            &planes,
                        )
                    }
                }
            };
            if positions_first {
                // Rows of `co` channels, one per position: each block writes its channels'
                // bytes of every row (disjoint columns of the same rows).
                assert_eq!(dst.len(), s.co * plane);
                let out = SyncPtr(dst.as_mut_ptr());
                // SAFETY: `b · ROWS < co`, within `dst`; the blocks' columns are disjoint.
                par_for(s.co.div_ceil(ROWS), |b| {
                    block(b, unsafe { out.at(b * ROWS) }, (s.co - b * ROWS).min(ROWS), Some(s.co))
                });
            } else {
                // Each chunk is `rows` whole planes.
                par_chunks(dst, ROWS * plane, |b, out| block(b, out.as_mut_ptr(), out.len() / plane, None));
            }
            return;
        }
        assert!(!positions_first, "PackedQConv: rows of channels are written by the x86 1x1 tiles only");
        if let (WordsPath::Vnni, Some(lanes)) = (path, &self.lanes) {
            lanes.run(&self.layout, words, self.y0, dst);
            return;
        }
        // Each channel block whole, or, where whole blocks would leave threads idle, its output
        // rows in runs ([`parts`]): a run's positions start at its first row, and its sums (exact
        // integers) are those of the whole block's.
        assert_eq!(dst.len(), s.co * plane);
        let blocks = s.co.div_ceil(ROWS);
        let out = SyncPtr(dst.as_mut_ptr());
        par_runs(blocks, parts(blocks, 1, oh), oh, |b, Range { start: y0, end: y1 }| {
            let rows = ROWS.min(s.co - b * ROWS);
            let (n, positions) = ((y1 - y0) * ow, (y1 - y0 - 1) * wq + ow);
            let words = &words[y0 * wq..];
            // SAFETY: rows `y0 .. y1` of channel `b·ROWS + r < co`'s plane, within `dst`
            // (asserted); no other item writes them.
            let channel =
                |r: usize| unsafe { std::slice::from_raw_parts_mut(out.at((b * ROWS + r) * plane + y0 * ow), n) };
            // Every tile's sums are written before they are read: the thread's buffer.
            with_words(positions.div_ceil(PX) * PX * ROWS, |sums: &mut [i32]| {
                let weights = &self.weights[b * taps.len() * ROWS..(b + 1) * taps.len() * ROWS];
                match path {
                    // SAFETY: the path is one the CPU has ([`words_path`]); every tile of every tap
                    // lies in `words` (padded by `PX + wp` words past the last row's positions).
                    WordsPath::Vnni => unsafe { tiles_vnni(words, taps, weights, positions, sums) },
                    WordsPath::Avx2 => {
                        let pairs = self.pairs.as_deref().expect("the AVX2 path's pairs are packed with the op");
                        let pairs = &pairs[2 * b * taps.len() * ROWS..2 * (b + 1) * taps.len() * ROWS];
                        // SAFETY: as above; `pairs` holds two words per weight word.
                        unsafe { tiles_avx2(words, taps, pairs, positions, sums) }
                    }
                    // SAFETY: as above.
                    #[cfg(target_arch = "aarch64")]
                    WordsPath::Sdot => unsafe { tiles_sdot(words, taps, weights, positions, sums) },
                    #[cfg(not(target_arch = "aarch64"))]
                    WordsPath::Sdot => unreachable!("SDOT is aarch64's"),
                }
                if wq == ow {
                    // No wide columns (a 1x1 layer without padding): each tile's row of sums is
                    // `PX` consecutive outputs, requantised where it lies (a gather value by value
                    // cost as much as the products on AVX2).
                    for r in 0..rows {
                        for (tile, out) in channel(r).chunks_mut(PX).enumerate() {
                            let at = tile * PX * ROWS + r * PX;
                            requant(b * ROWS + r, &sums[at..at + out.len()], out);
                        }
                    }
                    return;
                }
                // Each channel's rows gathered whole, then requantised in one pass (row by row, a
                // map 26 wide left 10 of every 26 values to the scalar remainder).
                let mut gathered = vec![0i32; n];
                for r in 0..rows {
                    for (y, row) in gathered.chunks_exact_mut(ow).enumerate() {
                        // The row's positions `y·wq ..` by the runs that lie in one tile (value by
                        // value, the gather took 7 of a 187 ms int8 step on a modelled A78).
                        let mut x = 0;
                        while x < ow {
                            let p = y * wq + x;
                            let n = (PX - p % PX).min(ow - x);
                            let at = (p / PX) * PX * ROWS + r * PX + p % PX;
                            row[x..x + n].copy_from_slice(&sums[at..at + n]);
                            x += n;
                        }
                    }
                    requant(b * ROWS + r, &gathered, channel(r));
                }
            })
        });
    }
}

/// The input of [`PackedQConv::run_words`]: channels' planes (NCHW), or, for a matrix product,
/// rows of `K` channels one position after another (`[M, K]`, HMG's tokens).
#[derive(Clone, Copy)]
pub(super) enum Src<'a> {
    Planes(&'a [u8]),
    Rows(&'a [u8]),
}

/// Group `g`'s words of a 1x1 layer without padding from rows of `ci` channels a position
/// (`rows` is `[positions, ci]`): position `p`'s word is its channels `4g .. 4g + 4`, the
/// four bytes read as they lie (with the top bits flipped for SDOT). `bytes` is the group's
/// share of the words (the part past the last group is padding, left as it is).
fn row_words(rows: &[u8], ci: usize, g: usize, bytes: &mut [u8], flip: u8) {
    let (lo, hi) = (4 * g, (4 * g + 4).min(ci));
    if lo >= ci {
        return;
    }
    if hi - lo == 4 {
        // Whole words: each position's four bytes copied as one (byte by byte this took as
        // many instructions as the products on NanoTrack's channels-last layers on aarch64).
        let flip = u32::from_ne_bytes([flip; 4]);
        for (row, word) in rows.chunks_exact(ci).zip(bytes.chunks_exact_mut(4)) {
            let w = u32::from_ne_bytes(row[lo..hi].try_into().expect("four bytes")) ^ flip;
            word.copy_from_slice(&w.to_ne_bytes());
        }
        return;
    }
    for (p, row) in rows.chunks_exact(ci).enumerate() {
        for (c, &v) in row[lo..hi].iter().enumerate() {
            bytes[4 * p + c] = v ^ flip;
        }
    }
}

/// Positions a thread's share of a product's output transpose holds ([`transpose_block`]).
pub(super) const TRANSPOSE_ROWS: usize = 32;

/// `rows[r][o] = planes[o][first + r]` for the output rows `rows` (each `co` long) of a product
/// whose channels' planes of `m` positions are `planes`: one block of the transpose from
/// channels first to positions first, in squares of 8 channels by 8 positions
/// ([`transpose8x8`]; byte by byte it took as many instructions as the products on NanoTrack's
/// channels-last layers on aarch64), the rest byte by byte.
pub(super) fn transpose_block(planes: &[u8], m: usize, first: usize, rows: &mut [u8]) {
    let co = planes.len() / m;
    let n = rows.len() / co;
    let (whole_c, whole_p) = (co / 8 * 8, n / 8 * 8);
    for o0 in (0..whole_c).step_by(8) {
        for r0 in (0..whole_p).step_by(8) {
            let at = |o: usize| first + r0 + (o0 + o) * m;
            let square = std::array::from_fn(|o| u64::from_le_bytes(planes[at(o)..at(o) + 8].try_into().expect("8")));
            for (r, v) in transpose8x8(square).into_iter().enumerate() {
                rows[(r0 + r) * co + o0..][..8].copy_from_slice(&v.to_le_bytes());
            }
        }
    }
    for (r, row) in rows.chunks_exact_mut(co).enumerate() {
        let channels = if r < whole_p { whole_c..co } else { 0..co };
        for o in channels {
            row[o] = planes[o * m + first + r];
        }
    }
}

/// The 8x8 byte matrix `a` (row `i`'s byte `j`: `a[i] >> 8j`) transposed, in three rounds of
/// swaps of 1-, 2- and 4-byte blocks between rows.
pub(super) fn transpose8x8(mut a: [u64; 8]) -> [u64; 8] {
    for (shift, mask) in [(8, 0x00FF_00FF_00FF_00FFu64), (16, 0x0000_FFFF_0000_FFFF), (32, 0x0000_0000_FFFF_FFFF)] {
        let step = shift / 8;
        for i in (0..8).filter(|i| i & step == 0) {
            let t = ((a[i] >> shift) ^ a[i + step]) & mask;
            a[i + step] ^= t;
            a[i] ^= t << shift;
        }
    }
    a
}

/// `words[x] = [rows[0][x], rows[1][x], rows[2][x], rows[3][x]] ^ flip` for every `x` of the
/// words: four channels' bytes side by side. Sixteen positions at a time, on x86 with SSE2's
/// byte and word unpacks (the byte-by-byte loop took a quarter of a 1x1 layer's time on
/// NanoTrack's head: 5.6 of 21 µs), on aarch64 with NEON's four-way interleaving store. (`flip`
/// is the same byte four times: 0, or 0x80 for SDOT's i8 inputs.)
pub(super) fn interleave4(rows: [&[u8]; 4], words: &mut [u32], flip: u32) {
    let n = words.len();
    assert!(rows.iter().all(|r| r.len() >= n));
    #[allow(unused_mut)]
    let mut done = 0;
    #[cfg(target_arch = "x86_64")]
    {
        use std::arch::x86_64::*;
        // SAFETY: SSE2 is part of x86_64; every load reads 16 bytes at `x < n - 15` of rows at
        // least `n` long, every store 64 bytes at words `x..x + 16` of `n`.
        unsafe {
            let f = _mm_set1_epi32(flip as i32);
            let load = |r: &[u8], x: usize| _mm_loadu_si128(r.as_ptr().add(x).cast());
            while done + 16 <= n {
                let x = done;
                let (r0, r1, r2, r3) = (load(rows[0], x), load(rows[1], x), load(rows[2], x), load(rows[3], x));
                let (lo01, hi01) = (_mm_unpacklo_epi8(r0, r1), _mm_unpackhi_epi8(r0, r1));
                let (lo23, hi23) = (_mm_unpacklo_epi8(r2, r3), _mm_unpackhi_epi8(r2, r3));
                let out = words.as_mut_ptr().add(x).cast::<__m128i>();
                _mm_storeu_si128(out, _mm_xor_si128(_mm_unpacklo_epi16(lo01, lo23), f));
                _mm_storeu_si128(out.add(1), _mm_xor_si128(_mm_unpackhi_epi16(lo01, lo23), f));
                _mm_storeu_si128(out.add(2), _mm_xor_si128(_mm_unpacklo_epi16(hi01, hi23), f));
                _mm_storeu_si128(out.add(3), _mm_xor_si128(_mm_unpackhi_epi16(hi01, hi23), f));
                done += 16;
            }
        }
    }
    #[cfg(target_arch = "aarch64")]
    {
        use std::arch::aarch64::*;
        // SAFETY: NEON is part of aarch64; every load reads 16 bytes at `x < n - 15` of rows at
        // least `n` long; `st4` stores 64 bytes, words `x..x + 16` of `n`, each word its four
        // rows' bytes in order.
        unsafe {
            let f = vreinterpretq_u8_u32(vdupq_n_u32(flip));
            while done + 16 <= n {
                let x = done;
                let load = |r: &[u8]| veorq_u8(vld1q_u8(r.as_ptr().add(x)), f);
                let v = uint8x16x4_t(load(rows[0]), load(rows[1]), load(rows[2]), load(rows[3]));
                vst4q_u8(words.as_mut_ptr().add(x).cast(), v);
                done += 16;
            }
        }
    }
    for (x, w) in words.iter_mut().enumerate().skip(done) {
        *w = u32::from_ne_bytes([rows[0][x], rows[1][x], rows[2][x], rows[3][x]]) ^ flip;
    }
}
