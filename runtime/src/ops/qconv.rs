//! Stride-1 and stride-2 u8 x i8 convolutions (tract's quantised `Conv`, from `QLinearConv`, and
//! the quantised `EinSum` tract makes of a 1x1 one: HMG's patch embeddings, 1.5 -> 0.09 ms) as
//! [`PackedQConv`]: the direct convolution of [`super::conv`] on AVX-512 VNNI, where
//! `vpdpbusd` multiplies four u8 inputs by four i8 weights and adds them to an i32 lane.
//!
//! tract runs these as an eager u8 im2col on one thread and an integer matrix product: in the
//! int8 plan, backbone layer 2's product took 7 ms and its im2col 25 ms. Here the input is
//! copied once into `[C/4, Hp, Wp, 4]` bytes (four channels side by side, padded with the input
//! zero point), so the four channels of a tap are one 32-bit word and a tile of 16 positions is
//! one 64-byte load; with stride 2 each group's plane is stored as its four phases, as the float
//! convolution stores it, so that a tap again reads consecutive words (backbone layer 1: 11x11,
//! stride 2, three channels in one word with a zero weight). Put in on CPUs with AVX-512 VNNI,
//! with AVX2 (`vpmaddwd` on the words' bytes widened to 16 bits: the same exact sums, where
//! tract's AVX2 integer kernel ran NanoTrack's 1x1 layers at 1.3 GOP/s on an AMD EPYC) or, on
//! aarch64, with the dot product (`sdot` on i8: the inputs go in shifted by 128, and 128·Σw is
//! added back before the requantisation); elsewhere tract's path stays. Where
//! the CPU also has AMX-INT8, stride-1 products run on AMX tiles instead ([`super::qconv_amx`],
//! 4x faster than VNNI on backbone layer 2); both requantise with the same vector code
//! ([`super::qconv_kernel`]), as tract does: a scale shared by every output channel
//! (per-tensor weights) by the exact product rounded half to even (tract's `Scaler`), a
//! per-channel one by the f32 product, so that every path gives tract's bytes.

use std::sync::Arc;

use tract_nnef::internal::*;
use tract_nnef::tract_core::ops::cnn::{Conv, KernelFormat};
use tract_nnef::tract_core::ops::einsum::EinSum;
use tract_nnef::tract_core::ops::nn::DataFormat;

use super::conv_kernel::Layout;
use super::qconv_amx::AmxWeights;
#[cfg(target_arch = "aarch64")]
use super::qconv_kernel::tiles_sdot;
use super::qconv_kernel::{avx2_pairs, bytemuck_words, exact_fits, requantise, tiles_avx2, tiles_vnni};
#[cfg(target_arch = "x86_64")]
use super::qconv_kernel::{tiles_avx2_requant, tiles_vnni_requant, Planes};
use super::qconv_lanes::QLanePack;
use super::{all_ones, output_tensor_written, pads_2d, par_chunks, same_bits, with_words, ConvShape};
#[cfg(target_arch = "x86_64")]
use super::{par_for, SyncPtr};

/// Output channels per tile.
pub(super) const ROWS: usize = 8;
/// Positions per tile (two registers of 16 i32 lanes).
pub(super) const PX: usize = 32;

/// `y[o] = sat_u8(round_half_even((Σ (x − x0)·w[o] + bias[o]) · scale[o]) + y0)` over the taps
/// of a stride-1 or stride-2 convolution, `x` u8 (zero point `x0`), `w` i8 with zero point 0, `scale[o] =
/// x_scale · w_scale[o] / y_scale`.
#[derive(Clone)]
pub struct PackedQConv {
    shape: ConvShape,
    /// `[o / 8][group (c/4, i, j)][o % 8]` words of four i8 weights (channels `4·(c/4)..+4`).
    weights: Arc<Vec<i32>>,
    /// The same words as the AVX2 path's i16 pairs (two per word, [`avx2_pairs`]), where that
    /// is the words path.
    pairs: Option<Arc<Vec<i32>>>,
    /// Word offset of every tap group `(c/4, i, j)` in the padded input, in packing order, and
    /// the output's wide positions.
    layout: Arc<Layout>,
    /// Per output channel: `bias − x0·Σw`, and the requantisation scale.
    offset: Arc<Vec<i32>>,
    /// Per output channel: `Σw` (the SDOT path's sums lack `128·Σw`).
    wsum: Arc<Vec<i32>>,
    scale: Arc<Vec<f32>>,
    /// One scale for every output channel (per-tensor weights): the sums' products with it are
    /// rounded exactly, as tract's `Scaler` does for such a scale; a per-channel scale is
    /// applied in f32, as tract's `Scale` does ([`super::qconv_kernel::requant_one`]). The two
    /// differ by one where the f32 product lands on a half (2 of 280,000 sums in range at HMG
    /// `proj`'s scale; on NanoTrack's int8 plan, one such unit early on moved cls by 0.136 and
    /// loc by 2.27).
    exact: bool,
    x0: u8,
    y0: u8,
    out_dt: DatumType,
    /// The weights as AMX tiles, where the CPU has AMX-INT8 (then used instead of VNNI).
    amx: Option<Arc<AmxWeights>>,
    /// The weights for VNNI tiles with the channels in the lanes (32 channels or more, no
    /// AMX), used instead of `weights` on VNNI.
    lanes: Option<Arc<QLanePack>>,
    /// Whether the data has a batch axis (tract drops one of 1 in some graphs).
    batch: Batch,
    /// Where the op is a matrix product (HMG's linear layers): its layouts.
    matmul: Option<Arc<Product>>,
}

impl std::fmt::Debug for PackedQConv {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "PackedQConv({:?})", self.shape)
    }
}

impl PartialEq for PackedQConv {
    fn eq(&self, other: &Self) -> bool {
        self.shape == other.shape
            && self.weights == other.weights
            && self.offset == other.offset
            && same_bits(&self.scale, &other.scale)
            && (self.x0, self.y0, self.out_dt, self.batch) == (other.x0, other.y0, other.out_dt, other.batch)
            && self.matmul == other.matmul
            && self.amx.is_some() == other.amx.is_some()
            && self.lanes.as_ref().map(|l| l.values()) == other.lanes.as_ref().map(|l| l.values())
    }
}

impl Eq for PackedQConv {}

impl Op for PackedQConv {
    fn name(&self) -> StaticName {
        "PackedQConv".into()
    }

    fn info(&self) -> TractResult<Vec<String>> {
        let s = &self.shape;
        let isa = match (&self.amx, &self.lanes, words_path()) {
            (Some(_), _, _) => "AMX".to_string(),
            (None, _, Some(WordsPath::Sdot)) => "aarch64 SDOT".to_string(),
            (None, _, Some(WordsPath::Avx2)) => "AVX2".to_string(),
            (None, Some(l), _) => format!("AVX-512 VNNI, tiles of {} channels in lanes", l.channels()),
            _ => "AVX-512 VNNI".to_string(),
        };
        let scale = if self.exact { "one scale, exact product" } else { "per-channel scales" };
        Ok(vec![format!(
            "{}x{} kernel, {} -> {} channels, u8 x i8 on {isa}, pad {:?}, {scale}",
            s.kh, s.kw, s.ci, s.co, s.pad
        )])
    }

    op_as_typed_op!();
}

impl EvalOp for PackedQConv {
    op_out_of_plan!();

    fn eval(&self, _ctx: &EvalContext, inputs: TVec<TValue>) -> TractResult<TVec<TValue>> {
        let input = args_1!(inputs);
        let s = &self.shape;
        ensure!(input.datum_type().unquantized() == u8::datum_type(), "PackedQConv: input is {:?}", input.datum_type());
        if let Some(product) = &self.matmul {
            return self.eval_product(product, input);
        }
        let (n, ci, h, w) = match (self.batch, input.shape()) {
            (Batch::Kept, &[n, ci, h, w]) | (Batch::Dropped, &[n @ 1, ci, h, w]) => (n, ci, h, w),
            (Batch::None, &[ci, h, w]) => (1, ci, h, w),
            _ => bail!("PackedQConv: input {:?} for {s:?}", input.shape()),
        };
        ensure!((ci, h, w) == (s.ci, s.h, s.w), "PackedQConv: input {:?} for {s:?}", input.shape());
        let input = input.try_as_plain_ram()?;
        // SAFETY: the datum type is u8, possibly with quantisation parameters (checked above).
        let input = unsafe { input.as_slice_unchecked::<u8>() };
        let (oh, ow) = s.out();
        let plane = oh * ow;
        let path = words_path().ok_or_else(|| format_err!("PackedQConv: no integer dot product on this CPU"))?;
        let requant = |o: usize, sums: &[i32], bytes: &mut [u8]| self.requant(path, o, sums, bytes);
        let shape: TVec<usize> = if self.batch == Batch::Kept { tvec![n, s.co, oh, ow] } else { tvec![s.co, oh, ow] };
        let fill = |out: &mut [u8]| {
            for (src, dst) in input.chunks_exact(ci * h * w).zip(out.chunks_exact_mut(s.co * plane)) {
                match &self.amx {
                    Some(amx) => amx.run(s, src, self.x0, (&self.offset, &self.scale, self.exact, self.y0), dst),
                    None => self.run_words(path, Src::Planes(src), requant, dst, false),
                }
            }
            Ok(())
        };
        // SAFETY: every output byte is written: each path requantises every output position
        // of every channel (the unit tests, whose debug builds fill the output with 255 first,
        // hold each to the scalar reference).
        let mut t = unsafe { output_tensor_written(&shape, fill)? };
        // SAFETY: same storage type (u8), the output fact's quantisation parameters.
        unsafe { t.set_datum_type(self.out_dt) };
        Ok(tvec!(t.into_tvalue()))
    }
}

/// The layouts of a [`PackedQConv`] that is a matrix product `M x K` (or `K x M`) by constant
/// weights into `M x N` (or `N x M`), a leading axis of 1 allowed on either side: run as a 1x1
/// convolution of `K` channels over `M` positions, transposed in and out where the layout is
/// tokens first.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) struct Product {
    input: TVec<usize>,
    output: TVec<usize>,
    /// The input is `[.., M, K]` (else `[.., K, M]`).
    in_last: bool,
    /// The output is `[.., M, N]` (else `[.., N, M]`).
    out_last: bool,
}

impl PackedQConv {
    /// Requantise output channel `o`'s `sums` into `bytes`.
    fn requant(&self, path: WordsPath, o: usize, sums: &[i32], bytes: &mut [u8]) {
        // The SDOT path's sums lack 128·Σw (its inputs are x − 128).
        let flip = if path == WordsPath::Sdot { 128 } else { 0 };
        requantise(sums, self.offset[o] + flip * self.wsum[o], self.scale[o], self.exact, self.y0, bytes)
    }

    /// [`EvalOp::eval`] of a matrix product ([`Product`]).
    fn eval_product(&self, product: &Product, input: TValue) -> TractResult<TVec<TValue>> {
        ensure!(input.shape() == &*product.input, "PackedQConv: input {:?} for {product:?}", input.shape());
        let path = words_path().ok_or_else(|| format_err!("PackedQConv: no integer dot product on this CPU"))?;
        let input = input.try_as_plain_ram()?;
        // SAFETY: the datum type is u8, possibly with quantisation parameters (the op's match).
        let input = unsafe { input.as_slice_unchecked::<u8>() };
        let src = if product.in_last { Src::Rows(input) } else { Src::Planes(input) };
        let requant = |o: usize, sums: &[i32], bytes: &mut [u8]| self.requant(path, o, sums, bytes);
        // Positions first out: written so by the x86 tiles; elsewhere (SDOT: NanoTrack's
        // channels-last layers on aarch64) the channels' planes transposed after.
        let tiles_transpose = matches!(path, WordsPath::Vnni | WordsPath::Avx2);
        let fill = |out: &mut [u8]| {
            if !product.out_last || tiles_transpose {
                self.run_words(path, src, requant, out, product.out_last);
                return Ok(());
            }
            let (co, m) = (self.shape.co, self.shape.w);
            let mut planes = vec![0u8; co * m];
            self.run_words(path, src, requant, &mut planes, false);
            par_chunks(out, TRANSPOSE_ROWS * co, |b, rows| transpose_block(&planes, m, b * TRANSPOSE_ROWS, rows));
            Ok(())
        };
        // SAFETY: as in [`EvalOp::eval`]: every position of every channel is requantised (and,
        // transposed, every row of the output written whole).
        let mut t = unsafe { output_tensor_written(&product.output, fill)? };
        // SAFETY: same storage type (u8), the output fact's quantisation parameters.
        unsafe { t.set_datum_type(self.out_dt) };
        Ok(tvec!(t.into_tvalue()))
    }

    /// One image on words of four channels: AVX-512 VNNI, AVX2 or aarch64 SDOT, into `dst`
    /// as channels' planes or (`positions_first`, a matrix product's output on the x86 paths)
    /// as rows of channels.
    fn run_words(
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
        let positions = self.layout.positions();
        // Words of four channels, each group's plane stored as its `stride²` phases
        // ([`ConvShape::phase`]); room past the end for the last tile.
        let group_words = s.stride * s.stride * hq * wq;
        // SDOT takes i8 inputs: x − 128, the top bit of every byte flipped as it is written.
        let flip = if path == WordsPath::Sdot { 0x80u8 } else { 0 };
        let flip4 = u32::from_ne_bytes([flip; 4]);
        let mut words = vec![u32::from_ne_bytes([self.x0 ^ flip; 4]); s.ci.div_ceil(4) * group_words + PX + wq];
        // Each group of four channels fills its own words, the groups side by side on the threads.
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
            for c in 4 * g..(4 * g + 4).min(s.ci) {
                for y in 0..s.h {
                    let row = &src[(c * s.h + y) * s.w..(c * s.h + y + 1) * s.w];
                    let yp = y + s.pad[0];
                    if s.stride == 1 {
                        let at = yp * wq + s.pad[1];
                        for (x, &v) in row.iter().enumerate() {
                            bytes[(at + x) * 4 + c % 4] = v ^ flip;
                        }
                        continue;
                    }
                    // Stride 2: even and odd padded columns go to the row's two phases.
                    for (first, at) in s.phase_runs(yp) {
                        for (i, &v) in row[first..].iter().step_by(2).enumerate() {
                            bytes[(at + i) * 4 + c % 4] = v ^ flip;
                        }
                    }
                }
            }
        });
        let (words, taps) = (&words, &self.layout.taps);
        #[cfg(target_arch = "x86_64")]
        if matches!(path, WordsPath::Vnni | WordsPath::Avx2) && wq == ow && s.kh * s.kw == 1 && s.stride == 1 {
            // A 1x1 layer of stride 1: each tile of positions is consecutive outputs,
            // requantised in the tile's registers (VNNI's tiles of 32 positions, AVX2's of 8).
            let per_block = taps.len() * ROWS;
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
        par_chunks(dst, ROWS * plane, |b, out| {
            // Every tile's sums are written before they are read: the thread's buffer.
            with_words(positions.div_ceil(PX) * PX * ROWS, |sums: &mut [i32]| {
                let weights = &self.weights[b * taps.len() * ROWS..(b + 1) * taps.len() * ROWS];
                match path {
                    // SAFETY: the path is one the CPU has ([`words_path`]); every tile of every tap
                    // lies in `words` (padded by `PX + wp` words).
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
                    for (r, out) in out.chunks_exact_mut(plane).enumerate() {
                        for (tile, out) in out.chunks_mut(PX).enumerate() {
                            let at = tile * PX * ROWS + r * PX;
                            requant(b * ROWS + r, &sums[at..at + out.len()], out);
                        }
                    }
                    return;
                }
                // Each channel's plane gathered whole, then requantised in one pass (row by row, a
                // map 26 wide left 10 of every 26 values to the scalar remainder).
                let mut gathered = vec![0i32; plane];
                for (r, out) in out.chunks_exact_mut(plane).enumerate() {
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
                    requant(b * ROWS + r, &gathered, out);
                }
            })
        });
    }
}

/// The input of [`PackedQConv::run_words`]: channels' planes (NCHW), or, for a matrix product,
/// rows of `K` channels one position after another (`[M, K]`, HMG's tokens).
#[derive(Clone, Copy)]
enum Src<'a> {
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
const TRANSPOSE_ROWS: usize = 32;

/// `rows[r][o] = planes[o][first + r]` for the output rows `rows` (each `co` long) of a product
/// whose channels' planes of `m` positions are `planes`: one block of the transpose from
/// channels first to positions first, in squares of 8 channels by 8 positions
/// ([`transpose8x8`]; byte by byte it took as many instructions as the products on NanoTrack's
/// channels-last layers on aarch64), the rest byte by byte.
fn transpose_block(planes: &[u8], m: usize, first: usize, rows: &mut [u8]) {
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
fn transpose8x8(mut a: [u64; 8]) -> [u64; 8] {
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
fn interleave4(rows: [&[u8]; 4], words: &mut [u32], flip: u32) {
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

impl TypedOp for PackedQConv {
    fn output_facts(&self, inputs: &[&TypedFact]) -> TractResult<TVec<TypedFact>> {
        let (oh, ow) = self.shape.out();
        if let Some(product) = &self.matmul {
            return Ok(tvec!(self.out_dt.fact(&*product.output)));
        }
        if self.batch != Batch::Kept {
            return Ok(tvec!(self.out_dt.fact([self.shape.co, oh, ow])));
        }
        Ok(tvec!(self.out_dt.fact([inputs[0].shape[0].clone(), self.shape.co.into(), oh.into(), ow.into()])))
    }

    fn cost(&self, inputs: &[&TypedFact]) -> TractResult<TVec<(Cost, TDim)>> {
        let s = &self.shape;
        let (oh, ow) = s.out();
        let macs = s.co * oh * ow * s.ci * s.kh * s.kw;
        let n = if self.batch == Batch::Kept { inputs[0].shape[0].clone() } else { 1.into() };
        Ok(tvec!((Cost::FMA(i32::datum_type()), n * macs)))
    }

    as_op!();
}

/// A [`PackedQConv`]'s batch axis.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Batch {
    /// NCHW in and out.
    Kept,
    /// NCHW in with N = 1, CHW out (an einsum that sums the axis of 1 away).
    Dropped,
    /// CHW in and out (tract dropped the axis before).
    None,
}

/// The integer dot products on words of four bytes [`PackedQConv`] runs on.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum WordsPath {
    /// x86_64 AVX-512 VNNI (`vpdpbusd`: u8 x i8).
    Vnni,
    /// x86_64 AVX2 (`vpmaddwd` on the bytes widened to i16).
    Avx2,
    /// aarch64 dot product (`sdot`: i8 x i8, inputs shifted by 128).
    Sdot,
}

/// The path the CPU has ([`crate::isa`]: VNNI, else AVX2, else the aarch64 dot product), if any.
fn words_path() -> Option<WordsPath> {
    let isa = crate::isa();
    if isa.vnni {
        Some(WordsPath::Vnni)
    } else if isa.avx2_fma {
        Some(WordsPath::Avx2)
    } else if isa.dotprod {
        Some(WordsPath::Sdot)
    } else {
        None
    }
}

/// Whether the words path is VNNI's (whose tiles in lanes serve 1x1 layers).
fn has_vnni_words() -> bool {
    words_path() == Some(WordsPath::Vnni)
}

/// Whether HMG's linear layers run as [`PackedQConv`]s here ([`matmul_shape`]): on the AVX2
/// and SDOT words paths, and on VNNI's unless tract's integer products run on AMX tiles (its
/// `avx512amx_mmm_i32_16x16` took them in 2.35-2.41 ms per PRL-Track int8 step on one thread,
/// 1.46-1.52 on two, against 3.0-3.1 and 1.83-1.85 on VNNI, 2026-12-06).
fn products_here() -> bool {
    match words_path() {
        Some(WordsPath::Avx2) => true,
        Some(WordsPath::Vnni) => !tract_amx_int8(),
        Some(WordsPath::Sdot) => true,
        _ => false,
    }
}

/// Whether tract's integer matrix products run on AMX tiles here (`TRACT_CPU_ISA=-amx-int8`
/// heeded).
fn tract_amx_int8() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        use tract_nnef::prelude::tract_linalg::isa::{native, Isa};
        native().has(Isa::X86_64AmxInt8) && super::qconv_amx::available()
    }
    #[cfg(not(target_arch = "x86_64"))]
    false
}

/// Whether a [`PackedQConv`] can run here.
fn has_words_path() -> bool {
    words_path().is_some()
}

/// A quantised layer's weight scales as its graph holds them: one (per-tensor weights) or one
/// per output channel (`co`); `None` if not constant or of another length.
pub(super) fn weight_scales(fact: &TypedFact, co: usize) -> TractResult<Option<Vec<f32>>> {
    Ok(konst_values::<f32>(fact, 1)?.or(konst_values::<f32>(fact, co)?))
}

/// Each of `co` output channels' requantisation scale `x_scale · k_scale / y_scale`, bit for
/// bit as tract's optimised plan has it (one unit in the last place moves a sum across a half,
/// and a byte). tract wires the product and the quotient of the scales while it optimises and
/// folds an op at once only where each of its constant inputs holds fewer than 16 values; a
/// quotient left standing is turned into a product with the reciprocal by the declutter pass
/// that comes before the constants are folded. So one weight scale, or fewer than 16: a true
/// division, `x · k / y`; 16 and more: `(k · x) · (1 / y)` (NanoTrack's depthwise and head
/// layers: a few channels of each a unit apart, one sum in block 2 on a half).
pub(super) fn requant_scales(x_scale: f32, k_scale: &[f32], y_scale: f32, co: usize) -> Vec<f32> {
    match k_scale {
        [k] => vec![x_scale * k / y_scale; co],
        _ if k_scale.len() < EAGER_FOLD_VOLUME => k_scale.iter().map(|k| x_scale * k / y_scale).collect(),
        _ => k_scale.iter().map(|k| (k * x_scale) * (1.0 / y_scale)).collect(),
    }
}

/// tract's `TypedModel::wire_node` evaluates an op at once when each of its constant inputs
/// has fewer values than this.
const EAGER_FOLD_VOLUME: usize = 16;

/// A scalar (or a vector of `n`) constant as f32 / i32 values.
pub(super) fn konst_values<T: Datum + Copy>(fact: &TypedFact, n: usize) -> TractResult<Option<Vec<T>>> {
    let Some(k) = &fact.konst else { return Ok(None) };
    let k = k.cast_to::<T>()?;
    let k = k.try_as_plain_ram()?;
    let v = k.as_slice::<T>()?;
    Ok(match v.len() {
        1 => Some(vec![v[0]; n]),
        l if l == n => Some(v.to_vec()),
        _ => None,
    })
}

/// The [`PackedQConv`] for `node` if it is a quantised convolution with u8 input and output,
/// constant i8 weights of zero point 0 and constant quantisation parameters (tract's `Conv` of
/// stride 1 or 2, or the `EinSum` tract makes of a 1x1 convolution: HMG's patch embeddings), and
/// the CPU has AVX-512 VNNI, AVX2 or the aarch64 dot product.
pub(crate) fn packed_q(model: &TypedModel, node: &TypedNode) -> TractResult<Option<PackedQConv>> {
    if !has_words_path() || !super::own_int8_operators() {
        return Ok(None);
    }
    let facts = model.node_input_facts(node.id)?;
    let conv = conv_shape(node, &facts).map(|s| (s, Batch::Kept)).or_else(|| pointwise_shape(node, &facts));
    let product = || matmul_shape(node, &facts).or_else(|| channels_last_shape(node, &facts));
    let (shape, batch, matmul) = match (conv, product()) {
        (Some((shape, batch)), _) => (shape, batch, None),
        (None, Some((shape, product, io))) => (shape, Batch::None, Some((product, io))),
        (None, None) => return Ok(None),
    };
    // Both ops take x, the weights, the bias, then x0, x_scale, w0, w_scale, y0, y_scale.
    let out_dt = node.outputs[0].fact.datum_type;
    let plain = facts.len() == 9
        && out_dt.unquantized() == u8::datum_type()
        && facts[0].datum_type.unquantized() == u8::datum_type()
        && facts[1].datum_type.unquantized() == i8::datum_type();
    if !plain {
        return Ok(None);
    }
    let co = shape.co;
    let (Some(kernel), Some(bias)) = (&facts[1].konst, konst_values::<i32>(facts[2], co)?) else { return Ok(None) };
    let params = (
        konst_values::<i32>(facts[3], 1)?,
        konst_values::<f32>(facts[4], 1)?,
        konst_values::<i32>(facts[5], co)?,
        weight_scales(facts[6], co)?,
        konst_values::<i32>(facts[7], 1)?,
        konst_values::<f32>(facts[8], 1)?,
    );
    let (Some(x0), Some(x_scale), Some(k0), Some(k_scale), Some(y0), Some(y_scale)) = params else { return Ok(None) };
    let (Ok(x0), Ok(y0)) = (u8::try_from(x0[0]), u8::try_from(y0[0])) else { return Ok(None) };
    if k0.iter().any(|&z| z != 0) || kernel.len() != co * shape.ci * shape.kh * shape.kw {
        return Ok(None);
    }
    let kernel = kernel.try_as_plain_ram()?;
    // SAFETY: the kernel's datum type is i8, possibly with quantisation parameters (checked).
    let kernel = unsafe { kernel.as_slice_unchecked::<i8>() };
    // A product's weights `K x N` are the convolution's `N x K` transposed.
    let transposed: Vec<i8>;
    let kernel = match matmul {
        Some((_, true)) => {
            transposed = (0..co).flat_map(|o| (0..shape.ci).map(move |c| kernel[c * co + o])).collect();
            &transposed[..]
        }
        _ => kernel,
    };
    let q = QuantParams { x0, x_scale: x_scale[0], k_scale, y0, y_scale: y_scale[0] };
    let bound = sum_bound(kernel, &bias, shape.ci * shape.kh * shape.kw);
    let op = PackedQConv::new(shape, kernel, &bias, q, out_dt)?;
    if op.exact && !exact_fits(op.scale[0], bound) {
        return Ok(None);
    }
    let matmul = matmul.map(|(product, _)| Arc::new(product));
    Ok(Some(PackedQConv { batch, matmul, ..op }))
}

/// The largest magnitude a layer's sums `Σ (x − x0)·w[o] + bias[o]` can take (`|x − x0| ≤
/// 255`), from its weights (`taps` per output channel) and biases.
pub(super) fn sum_bound(kernel: &[i8], bias: &[i32], taps: usize) -> i64 {
    let row = |(w, &b): (&[i8], &i32)| 255 * w.iter().map(|&v| (v as i64).abs()).sum::<i64>() + (b as i64).abs();
    kernel.chunks(taps.max(1)).zip(bias).map(row).max().unwrap_or(0)
}

/// The shape of a quantised NCHW `Conv` with OIHW weights, one group, stride 1 or 2 and no
/// dilation, on a concrete input.
fn conv_shape(node: &TypedNode, facts: &[&TypedFact]) -> Option<ConvShape> {
    let conv = node.op_as::<Conv>()?;
    let ps = &conv.pool_spec;
    let plain = conv.q_params.is_some()
        && conv.kernel_fmt == KernelFormat::OIHW
        && ps.data_format == DataFormat::NCHW
        && ps.kernel_shape.len() == 2
        && conv.group == 1
        && all_ones(&ps.dilations);
    if !plain {
        return None;
    }
    let stride = match ps.strides.as_deref() {
        None | Some([1, 1]) => 1,
        Some([2, 2]) => 2,
        _ => return None,
    };
    let pad = pads_2d(&ps.padding)?;
    let &[_, ci, h, w] = facts.first()?.shape.as_concrete()? else { return None };
    let (kh, kw) = (ps.kernel_shape[0], ps.kernel_shape[1]);
    Some(ConvShape { ci, h, w, co: ps.output_channels, kh, kw, pad, stride })
}

/// The shape of the quantised `EinSum` tract makes of a 1x1 convolution, `NIHW,OI,O->NOHW`
/// (whatever its axis letters), with constant `[O, I]` weights and an i32 bias, as a 1x1
/// [`ConvShape`]. (NanoTrack's pointwise layers come as `IHW,OI,O->OHW`, without the batch
/// axis, and the first after its squeeze-excitation as `NIHW,OI,O->OHW`, the axis dropped on
/// the way out.)
fn pointwise_shape(node: &TypedNode, facts: &[&TypedFact]) -> Option<(ConvShape, Batch)> {
    let (terms, out) = q_einsum_terms(node)?;
    let [x, w, _, ..] = terms.as_slice() else { return None };
    // NCHW, or CHW (a batch axis of 1 dropped, as in NanoTrack's graphs): `nihw,oi->nohw`.
    let batch = match (x.len(), out.len()) {
        (4, 4) if out[0] == x[0] => Batch::Kept,
        (4, 3) if !out.contains(&x[0]) => Batch::Dropped,
        (3, 3) => Batch::None,
        _ => return None,
    };
    let (c, hw, ohw) = match batch {
        Batch::Kept => (1, 2, 2),
        Batch::Dropped => (1, 2, 1),
        Batch::None => (0, 1, 1),
    };
    let pointwise =
        w.len() == 2 && out[ohw - 1] == w[0] && out[ohw..] == x[hw..] && w[1] == x[c] && !out.contains(&x[c]);
    if !pointwise || !per_output_channel(&terms, w[0], facts) {
        return None;
    }
    let dims = facts.first()?.shape.as_concrete()?;
    let (ci, h, w) = match (batch, dims) {
        (Batch::Kept, &[_, ci, h, w]) | (Batch::Dropped, &[1, ci, h, w]) | (Batch::None, &[ci, h, w]) => (ci, h, w),
        _ => return None,
    };
    let &[co, wi] = facts.get(1)?.konst.as_ref()?.shape() else { return None };
    (wi == ci).then_some((ConvShape { ci, h, w, co, kh: 1, kw: 1, pad: [0; 4], stride: 1 }, batch))
}

/// The shape of the quantised `EinSum` of a 1x1 convolution with its channels last on either
/// side, as tract makes NanoTrack's pointwise layers on aarch64 (its declutter moves the
/// depthwise layers' channels last there, and the pointwise ones between them follow):
/// `HWI,OI,O->OHW`, `IHW,OI,O->HWO` or `HWI,OI,O->HWO` (whatever the letters), constant `[O, I]`
/// weights and an i32 bias: a product of `K = I` channels over `M = H·W` positions, read as
/// rows of channels where they are last and written so where they are last out.
/// (`IHW,OI,O->OHW` is [`pointwise_shape`]'s.)
fn channels_last_shape(node: &TypedNode, facts: &[&TypedFact]) -> Option<(ConvShape, Product, bool)> {
    let (terms, out) = q_einsum_terms(node)?;
    let [x, w, _, ..] = terms.as_slice() else { return None };
    let (&[x0, x1, x2], &[o0, o1, o2], &[n, k]) = (x.as_slice(), out.as_slice(), w.as_slice()) else { return None };
    let (in_last, out_last) = (x2 == k, o2 == n);
    let (hw_in, hw_out) = (if in_last { [x0, x1] } else { [x1, x2] }, if out_last { [o0, o1] } else { [o1, o2] });
    let fits = (in_last || x0 == k)
        && (out_last || o0 == n)
        && (in_last || out_last)
        && hw_in == hw_out
        && !hw_in.contains(&k)
        && !hw_in.contains(&n)
        && !out.contains(&k)
        && !x.contains(&n);
    if !fits || !per_output_channel(&terms, n, facts) {
        return None;
    }
    let (input, output) = concrete_io(node, facts)?;
    let (ci, positions) = if in_last { (input[2], input[0] * input[1]) } else { (input[0], input[1] * input[2]) };
    let &[co, wi] = facts.get(1)?.konst.as_ref()?.shape() else { return None };
    let fits = wi == ci && positions > 0 && output.iter().product::<usize>() == co * positions;
    fits.then_some((
        ConvShape { ci, h: 1, w: positions, co, kh: 1, kw: 1, pad: [0; 4], stride: 1 },
        Product { input, output, in_last, out_last },
        false,
    ))
}

/// Whether a quantised `EinSum`'s terms after the data and the weights (the bias, then the
/// quantisation parameters) are each absent or per output channel (`n`), the bias i32.
fn per_output_channel(terms: &[Vec<char>], n: char, facts: &[&TypedFact]) -> bool {
    terms[2..].iter().all(|t| t.is_empty() || t.as_slice() == [n])
        && facts.get(2).is_some_and(|f| f.datum_type == i32::datum_type())
}

/// The concrete shapes of a node's data input and of its output.
fn concrete_io(node: &TypedNode, facts: &[&TypedFact]) -> Option<(TVec<usize>, TVec<usize>)> {
    Some((facts.first()?.shape.as_concrete()?.into(), node.outputs[0].fact.shape.as_concrete()?.into()))
}

/// The axis letters of a quantised `EinSum`'s input terms and of its output.
fn q_einsum_terms(node: &TypedNode) -> Option<(Vec<Vec<char>>, Vec<char>)> {
    let einsum = node.op_as::<EinSum>()?;
    einsum.q_params?;
    let expr = einsum.axes.to_string();
    let (inputs, output) = expr.split_once("->")?;
    Some((inputs.split(',').map(|t| t.chars().collect()).collect(), output.chars().collect()))
}

/// The shape of a quantised `EinSum` that is a matrix product by constant weights, HMG's
/// linear layers (`akm,kn->mn`, `mk,kn->anm`, whatever the letters: the input `[.., K, M]` or
/// `[.., M, K]`, the weights `K x N` or `N x K`, the output `[.., M, N]` or `[.., N, M]`, a
/// leading axis of 1 allowed on either side), as a 1x1 [`ConvShape`] of `K` channels on a
/// 1 x `M` map, with its layouts and whether the weights are `K x N`. Where [`products_here`]:
/// on the AVX2 words path tract's integer kernel (`avx2_mmm_i32_8x8`) ran PRL-Track's eight
/// such products at 1.3 GOP/s on an AMD EPYC, 830 of a 1000 ms int8 step; on VNNI (AMX off)
/// its `avx512vnni_mmm_i32_16x16` with its packing took 4.8 ms a step on one thread and 2.7
/// on two, this form 2.8-2.9 and 1.7 (tokens-first rows read as words, the output written
/// tokens first by the tiles: 2026-12-06). On SDOT (instructions counted under qemu, cycles
/// modelled for a Cortex-A78) this form took 183 ms per PRL-Track int8 step against 178 with
/// tract's `arm64simd_mmm_i32_8x8_dot` on 2026-12-05, and 175.5 against 176.4 once the rows
/// were read as words and the output transposed in 8x8-byte squares (2026-12-06).
fn matmul_shape(node: &TypedNode, facts: &[&TypedFact]) -> Option<(ConvShape, Product, bool)> {
    if !products_here() {
        return None;
    }
    let (terms, out) = q_einsum_terms(node)?;
    let [x, w, _, ..] = terms.as_slice() else { return None };
    let (xr, or) = (x.len(), out.len());
    if !(2..=3).contains(&xr) || !(2..=3).contains(&or) || w.len() != 2 {
        return None;
    }
    // k: summed (in x and w, not out); m: x's other last axis; n: w's other axis.
    let k = *x[xr - 2..].iter().find(|c| w.contains(c) && !out.contains(c))?;
    let m = *x[xr - 2..].iter().find(|&&c| c != k)?;
    let n = *w.iter().find(|&&c| c != k)?;
    let (in_last, out_last, io) = (x[xr - 1] == k, out[or - 1] == n, w[0] == k);
    // A leading axis is of size 1 (checked below) and in no other term.
    let lone = |c: char| !x.contains(&c) as usize + !w.contains(&c) as usize + !out.contains(&c) as usize >= 2;
    let product = m != n
        && out[or - 2..] == if out_last { [m, n] } else { [n, m] }
        && (xr == 2 || lone(x[0]))
        && (or == 2 || lone(out[0]));
    if !product || !per_output_channel(&terms, n, facts) {
        return None;
    }
    let (input, output) = concrete_io(node, facts)?;
    let (ci, positions) = if in_last { (input[xr - 1], input[xr - 2]) } else { (input[xr - 2], input[xr - 1]) };
    let &[w0, w1] = facts.get(1)?.konst.as_ref()?.shape() else { return None };
    let (wk, co) = if io { (w0, w1) } else { (w1, w0) };
    let fits = wk == ci
        && positions > 0
        && input[..xr - 2].iter().all(|&d| d == 1)
        && output[..or - 2].iter().all(|&d| d == 1)
        && output[or - 2..] == if out_last { [positions, co] } else { [co, positions] };
    fits.then_some((
        ConvShape { ci, h: 1, w: positions, co, kh: 1, kw: 1, pad: [0; 4], stride: 1 },
        Product { input, output, in_last, out_last },
        io,
    ))
}

/// Zero points and scales of a quantised convolution (weights: zero point 0).
#[derive(Debug, Clone)]
pub(crate) struct QuantParams {
    pub x0: u8,
    pub x_scale: f32,
    /// One (per-tensor weights) or one per output channel, as the graph holds them (tract
    /// computes the two kinds' scales apart: [`requant_scales`]).
    pub k_scale: Vec<f32>,
    pub y0: u8,
    pub y_scale: f32,
}

impl PackedQConv {
    /// Pack OIHW i8 `kernel` ([co, ci, kh, kw]) with i32 `bias` (one per output channel).
    pub(crate) fn new(
        shape: ConvShape,
        kernel: &[i8],
        bias: &[i32],
        q: QuantParams,
        out_dt: DatumType,
    ) -> TractResult<Self> {
        let (co, ci, kh, kw) = (shape.co, shape.ci, shape.kh, shape.kw);
        ensure!(
            kernel.len() == co * ci * kh * kw && bias.len() == co && (q.k_scale.len() == 1 || q.k_scale.len() == co),
            "PackedQConv: parameters for {shape:?}"
        );
        let groups = ci.div_ceil(4) * kh * kw;
        let blocks = co.div_ceil(ROWS);
        let mut words = vec![[0i8; 4]; blocks * groups * ROWS];
        // The same words as `[co][groups]`, for the channels-in-lanes packing.
        let mut by_channel = vec![[0i8; 4]; co * groups];
        let mut offset = vec![0i32; blocks * ROWS];
        let mut wsum = vec![0i32; blocks * ROWS];
        let mut scale = requant_scales(q.x_scale, &q.k_scale, q.y_scale, co);
        scale.resize(blocks * ROWS, 0.0);
        for o in 0..co {
            let mut sum = 0i32;
            for c in 0..ci {
                for i in 0..kh {
                    for j in 0..kw {
                        let v = kernel[((o * ci + c) * kh + i) * kw + j];
                        sum += v as i32;
                        let g = ((c / 4) * kh + i) * kw + j;
                        words[((o / ROWS) * groups + g) * ROWS + o % ROWS][c % 4] = v;
                        by_channel[o * groups + g][c % 4] = v;
                    }
                }
            }
            offset[o] = bias[o] - q.x0 as i32 * sum;
            wsum[o] = sum;
        }
        // Tract's criterion for its exact rounding: every value of the scale the same.
        let exact = scale[..co].iter().all(|v| v.to_bits() == scale[0].to_bits());
        let word = |b: &[i8; 4]| i32::from_ne_bytes(b.map(|v| v as u8));
        // AMX's tiles read the padded input row by row: stride 1 only. Not for 1x1 layers of
        // stride 1: those run on VNNI's tiles of positions, requantised in the tile
        // (`run_words`), no tiles with the channels in the lanes either (AMX's took NanoTrack's
        // int8 step from 1.76 to 1.9 ms; the lanes' requantisation written channel by channel
        // took 16.8 µs for 96 -> 96 channels on 16 x 16, against 11.0).
        let one_by_one = shape.kh * shape.kw == 1 && shape.stride == 1 && has_vnni_words();
        let amx =
            (crate::isa().amx && shape.stride == 1 && !one_by_one).then(|| Arc::new(AmxWeights::new(&shape, kernel)));
        let lanes = match QLanePack::registers_for(co) {
            Some(v) if amx.is_none() && !one_by_one && has_vnni_words() => {
                let by_channel: Vec<i32> = by_channel.iter().map(word).collect();
                Some(Arc::new(QLanePack::new(&by_channel, groups, co, v, &offset, (&scale, exact))))
            }
            _ => None,
        };
        let weights: Vec<i32> = words.iter().map(word).collect();
        let pairs = (words_path() == Some(WordsPath::Avx2))
            .then(|| Arc::new(weights.iter().flat_map(|&w| avx2_pairs(w)).collect::<Vec<i32>>()));
        Ok(PackedQConv {
            layout: Arc::new(Layout {
                taps: shape.tap_offsets(ci.div_ceil(4)),
                wp: shape.phase().1,
                oh: shape.out().0,
                ow: shape.out().1,
            }),
            shape,
            weights: Arc::new(weights),
            pairs,
            offset: Arc::new(offset),
            wsum: Arc::new(wsum),
            scale: Arc::new(scale),
            exact,
            x0: q.x0,
            y0: q.y0,
            out_dt,
            amx,
            lanes,
            batch: Batch::Kept,
            matmul: None,
        })
    }
}

/// tract's quantised `Conv` of `s` in `group`s (1, or `s.ci` for a depthwise one) on NCHW
/// (`batch`) or CHW data, wired in a model of its own: i8 weights spread over the bytes, input
/// zero point 117 and scale 0.02, weight zero point 0, output zero point 100; `bias`, the
/// weight scales (one, or one per output channel) and the output scale as given; the input
/// through `table` where given (tract's `LookupTable`). The tests' reference for the
/// operators that replace it.
#[cfg(test)]
pub(super) fn tract_q_conv(
    s: &ConvShape,
    group: usize,
    batch: bool,
    (bias, w_scale, y_scale): (&[i32], Tensor, f32),
    table: Option<&[u8]>,
) -> TypedModel {
    use tract_nnef::tract_core::ops::cnn::{PaddingSpec, PoolSpec};
    let mut model = TypedModel::default();
    let x_shape: TVec<usize> = if batch { tvec![1, s.ci, s.h, s.w] } else { tvec![s.ci, s.h, s.w] };
    let mut x = model.add_source("x", u8::fact(&x_shape)).unwrap();
    if let Some(t) = table {
        let lut = tract_nnef::tract_core::ops::quant::lookup_table(tract_linalg::routines::lut_u8(t).unwrap());
        x = model.wire_node("lut", lut, &[x]).unwrap()[0];
    }
    let per_group = s.ci / group;
    let w: Vec<i8> = (0..s.co * per_group * s.kh * s.kw).map(|i| ((i * 104729) % 255) as i32 as i8).collect();
    let konst = |name: &str, t: Tensor, model: &mut TypedModel| model.add_const(name, t).unwrap();
    let w = konst("w", Tensor::from_shape(&[s.co, per_group, s.kh, s.kw], &w).unwrap(), &mut model);
    let b = konst("b", Tensor::from_shape(&[s.co], bias).unwrap(), &mut model);
    let scalars = [tensor0(117i32), tensor0(0.02f32), tensor0(0i32), w_scale, tensor0(100i32), tensor0(y_scale)];
    let mut inputs = vec![x, w, b];
    for (i, t) in scalars.into_iter().enumerate() {
        inputs.push(konst(&format!("q{i}"), t, &mut model));
    }
    let pool_spec = PoolSpec {
        data_format: if batch { DataFormat::NCHW } else { DataFormat::CHW },
        kernel_shape: tvec![s.kh, s.kw],
        padding: PaddingSpec::ExplicitOnnxPool(tvec![s.pad[0], s.pad[1]], tvec![s.pad[2], s.pad[3]], false),
        dilations: None,
        strides: Some(tvec![s.stride, s.stride]),
        input_channels: s.ci,
        output_channels: s.co,
    };
    let op = Conv { pool_spec, kernel_fmt: KernelFormat::OIHW, group, q_params: Some(u8::datum_type()) };
    let y = model.wire_node("conv", op, &inputs).unwrap();
    model.select_output_outlets(&y).unwrap();
    model
}

/// A case that tells tract's two forms of per-channel requantisation scales apart (see
/// [`requant_scales`]): [`tract_q_conv`] of `s` in `group`s with weight scales where `x · k / y`
/// and `(k · x) · (1 / y)` part by a unit in the last place, one per output channel (`equal`:
/// all the same, tract's exact product) and biases whose products with the two round apart;
/// its input the zero point over the first half of every plane (outputs there: the biases
/// requantised), spread bytes below. Checks that tract's optimised plan takes the form its
/// channel count calls for, not the other, and returns the model, the input and tract's bytes.
#[cfg(test)]
pub(super) fn parting_case(s: &ConvShape, group: usize, batch: bool, equal: bool) -> (TypedModel, TValue, Vec<u8>) {
    use super::qconv_kernel::{parting_scales, requant_one};
    // [`tract_q_conv`]'s input scale and zero points.
    let (x_scale, y_scale, x0, y0) = (0.02f32, 0.0137f32, 117u8, 100u8);
    let co = s.co;
    let (k_scale, bias): (Vec<f32>, Vec<i32>) = match equal {
        false => parting_scales(x_scale, y_scale, false).take(co).unzip(),
        true => parting_scales(x_scale, y_scale, true).take(1).flat_map(|p| std::iter::repeat_n(p, co)).unzip(),
    };
    assert_eq!(k_scale.len(), co, "enough scales where the forms part");
    let model = tract_q_conv(s, group, batch, (&bias, tensor1(&k_scale), y_scale), None);
    let mut bytes: Vec<u8> = (0..s.ci * s.h * s.w).map(|i| ((i * 7919) % 256) as u8).collect();
    for plane in bytes.chunks_exact_mut(s.h * s.w) {
        plane[..s.h / 2 * s.w].fill(x0);
    }
    let shape: Vec<usize> = if batch { vec![1, s.ci, s.h, s.w] } else { vec![s.ci, s.h, s.w] };
    let input = Tensor::from_shape(&shape, &bytes).unwrap().into_tvalue();
    let out = model.clone().into_optimized().unwrap().into_runnable().unwrap().run(tvec![input.clone()]).unwrap();
    // SAFETY: the output is u8 (possibly quantised).
    let want = unsafe { out[0].try_as_plain_ram().unwrap().as_slice_unchecked::<u8>().to_vec() };
    // Row 1, column 1 of each output plane: its window reads the zero point alone.
    let at_zero: Vec<u8> = want.chunks_exact(s.out().0 * s.out().1).map(|p| p[s.out().1 + 1]).collect();
    let by = |f: &dyn Fn(f32) -> f32| -> Vec<u8> {
        k_scale.iter().zip(&bias).map(|(&k, &b)| requant_one(b, f(k), equal, y0)).collect()
    };
    let division = by(&|k| x_scale * k / y_scale);
    let reciprocal = by(&|k| (k * x_scale) * (1.0 / y_scale));
    let (expected, other) = if co < 16 { (division, reciprocal) } else { (reciprocal, division) };
    assert_eq!(at_zero, expected, "{co} channels, equal {equal}: tract's bytes");
    assert_ne!(at_zero, other, "{co} channels, equal {equal}: the forms part");
    (model, input, want)
}

#[cfg(test)]
mod tests {
    use super::super::qconv_kernel::requant_one;
    use super::*;
    use tract_nnef::tract_core::tract_linalg::{mmm::RoundingPolicy, Scaler};

    /// The direct integer formula, on `images` NCHW images of `s` (input zero point 7, output
    /// zero point 100), requantised by [`requant_one`] with `scale[o]`.
    fn direct(s: &ConvShape, input: &[u8], kernel: &[i8], bias: &[i32], (scale, exact): (&[f32], bool)) -> Vec<u8> {
        let (oh, ow) = s.out();
        let mut out = Vec::with_capacity(input.len() / (s.ci * s.h * s.w) * s.co * oh * ow);
        for img in input.chunks_exact(s.ci * s.h * s.w) {
            for o in 0..s.co {
                for y in 0..oh {
                    for x in 0..ow {
                        let mut acc = bias[o];
                        for c in 0..s.ci {
                            for i in 0..s.kh {
                                for j in 0..s.kw {
                                    let (yy, xx) = (
                                        (s.stride * y + i) as isize - s.pad[0] as isize,
                                        (s.stride * x + j) as isize - s.pad[1] as isize,
                                    );
                                    if yy < 0 || xx < 0 || yy >= s.h as isize || xx >= s.w as isize {
                                        continue;
                                    }
                                    let v = img[(c * s.h + yy as usize) * s.w + xx as usize] as i32 - 7;
                                    acc += v * kernel[((o * s.ci + c) * s.kh + i) * s.kw + j] as i32;
                                }
                            }
                        }
                        out.push(requant_one(acc, scale[o], exact, 100));
                    }
                }
            }
        }
        out
    }

    /// Pseudo-random inputs and weights for `s`.
    fn data(s: &ConvShape) -> (Vec<u8>, Vec<i8>) {
        let input = (0..2 * s.ci * s.h * s.w).map(|i| ((i * 7919) % 256) as u8).collect();
        let kernel = (0..s.co * s.ci * s.kh * s.kw).map(|i| (((i * 104729) % 255) as i32 - 127) as i8).collect();
        (input, kernel)
    }

    /// Both kernels (AMX where the CPU has it, VNNI) against [`direct`] on two images of `s`.
    fn check(s: ConvShape) {
        if !has_words_path() {
            // The op is only made where VNNI, AVX2 or SDOT may be used: say so, loudly.
            eprintln!(
                "NOTE: no AVX-512 VNNI, AVX2 or aarch64 dot product here (or PRL_ISA caps it): PackedQConv's kernels are NOT tested on this machine"
            );
            return;
        }
        let (input, kernel) = data(&s);
        let bias: Vec<i32> = (0..s.co as i32).map(|o| 100 * o - 500).collect();
        let k_scale: Vec<f32> =
            (0..s.co).map(|o| (0.001 + 0.0001 * o as f32) * 9.0 / (s.ci * s.kh * s.kw) as f32).collect();
        let scale = requant_scales(0.02, &k_scale, 0.05, s.co);
        let want = direct(&s, &input, &kernel, &bias, (&scale, false));
        let unsaturated = want.iter().filter(|&&v| v != 0 && v != 255).count();
        assert!(unsaturated > want.len() / 2, "most outputs should not saturate: {unsaturated} of {}", want.len());
        let q = QuantParams { x0: 7, x_scale: 0.02, k_scale, y0: 100, y_scale: 0.05 };
        every_path(&s, &input, &kernel, &bias, q, &want);
    }

    /// Every path of the op made for `s` (AMX where the CPU has it; VNNI, AVX2 or SDOT words;
    /// channels in lanes where packed) gives `want` on the images `input`.
    fn every_path(s: &ConvShape, input: &[u8], kernel: &[i8], bias: &[i32], q: QuantParams, want: &[u8]) {
        let amx = PackedQConv::new(s.clone(), kernel, bias, q, u8::datum_type()).unwrap();
        let vnni = PackedQConv { amx: None, ..amx.clone() };
        // The positions-in-lanes tiles too, where the channels-in-lanes ones were packed.
        let rows = PackedQConv { lanes: None, ..vnni.clone() };
        let images = input.len() / (s.ci * s.h * s.w);
        let x = tract_ndarray::Array4::from_shape_vec((images, s.ci, s.h, s.w), input.to_vec()).unwrap().into_tensor();
        let words = match words_path() {
            Some(WordsPath::Sdot) => "SDOT",
            Some(WordsPath::Avx2) => "AVX2",
            _ => "VNNI",
        };
        let lanes = if vnni.lanes.is_some() { "VNNI in lanes" } else { words };
        for (op, isa) in [(&amx, if amx.amx.is_some() { "AMX" } else { lanes }), (&vnni, lanes), (&rows, words)] {
            let out = op.eval(&EvalContext::out_of_plan(), tvec![x.clone().into_tvalue()]).unwrap();
            let out = out[0].try_as_plain_ram().unwrap();
            let got = out.as_slice::<u8>().unwrap();
            if let Some(i) = (0..want.len()).find(|&i| got[i] != want[i]) {
                panic!("{isa}, {s:?}: output {i} is {} instead of {}", got[i], want[i]);
            }
        }
    }

    /// Four rows' bytes interleaved into words, flipped or not, with lengths around the vector
    /// paths' sixteen: the scalar formula's words.
    #[test]
    fn interleaving_four_rows_gives_each_position_s_word() {
        for n in [0, 5, 16, 31, 48, 117] {
            let rows: Vec<Vec<u8>> = (0..4).map(|c| (0..n).map(|x| (x * 37 + c * 101 + 7) as u8).collect()).collect();
            for flip in [0u32, 0x8080_8080] {
                let mut got = vec![0u32; n];
                interleave4([&rows[0], &rows[1], &rows[2], &rows[3]], &mut got, flip);
                for (x, &w) in got.iter().enumerate() {
                    let want = u32::from_ne_bytes([rows[0][x], rows[1][x], rows[2][x], rows[3][x]]) ^ flip;
                    assert_eq!(w, want, "n {n}, flip {flip:x}, position {x}");
                }
            }
        }
    }

    /// With one scale for every output channel, every path rounds the exact product, as tract's
    /// `Scaler`: on an image at the input's zero point each channel's sum is its bias, chosen
    /// where the f32 product rounds the other way; the other image is the usual one.
    #[test]
    fn one_scale_rounds_the_exact_product_on_every_path() {
        // HMG `proj`'s scales, the weights' 32 times smaller: more sums in range, more ties (10).
        exact_product_on_every_path(0.0069588, 0.0007929764 / 32.0, 0.0028860883);
    }

    /// The same with a scale above 1 (tract's fixed point then shifts by less than 31; such
    /// scales come where the output's calibrated range is narrow, as `--method percentile`
    /// makes NanoTrack's first pointwise layer). There no f32 product of an integer below 2^24
    /// lands on a half that the exact one misses (the exact one is a multiple of 2^-23 times
    /// the scale's exponent, which is at least the f32 product's half unit), so the biases span
    /// the output range instead of rounding apart.
    #[test]
    fn one_scale_above_one_rounds_the_exact_product_on_every_path() {
        exact_product_on_every_path(1.0, 1.37, 1.0);
    }

    fn exact_product_on_every_path(x_scale: f32, w_scale: f32, y_scale: f32) {
        if !has_words_path() {
            eprintln!("NOTE: no AVX-512 VNNI, AVX2 or aarch64 dot product here (or PRL_ISA caps it): PackedQConv's exact requantisation is NOT tested on this machine");
            return;
        }
        let scale = x_scale * w_scale / y_scale;
        assert!(exact_fits(scale, 1 << 16), "{scale}");
        let ties = super::super::qconv_kernel::tie_sums(scale);
        assert!(scale >= 1.0 || ties.len() >= 8, "the case needs sums that round apart: {}", ties.len());
        for s in [
            // AMX (where the CPU has it) and channels in lanes (VNNI), a partial group of four.
            ConvShape { ci: 6, h: 9, w: 21, co: 40, kh: 3, kw: 3, pad: [1, 1, 1, 1], stride: 1 },
            // A 1x1 layer without padding (rows requantised where they lie), 48 outputs.
            ConvShape { ci: 8, h: 9, w: 13, co: 48, kh: 1, kw: 1, pad: [0; 4], stride: 1 },
            // Stride 2, a partial block of 8 outputs.
            ConvShape { ci: 7, h: 12, w: 15, co: 11, kh: 3, kw: 4, pad: [1, 2, 0, 1], stride: 2 },
        ] {
            let (mut input, kernel) = data(&s);
            input[s.ci * s.h * s.w..].fill(7);
            let bias: Vec<i32> = match scale >= 1.0 {
                true => (0..s.co).map(|o| (o as i32 * 13) % 141 - 70).collect(),
                false => (0..s.co).map(|o| ties[(o * 7) % ties.len()]).collect(),
            };
            let one = vec![scale; s.co];
            let want = direct(&s, &input, &kernel, &bias, (&one, true));
            let zero_point_image = &want[s.out().0 * s.out().1 * s.co..];
            if scale >= 1.0 {
                assert!(zero_point_image.iter().all(|&y| (1..255).contains(&y)), "{s:?}: outputs in range");
            } else {
                let f32_product = direct(&s, &input, &kernel, &bias, (&one, false));
                let apart = want.iter().zip(&f32_product).filter(|(a, b)| a != b).count();
                assert!(
                    apart >= s.out().0 * s.out().1 * s.co,
                    "{s:?}: every output at the zero point rounds apart: {apart}"
                );
            }
            let q = QuantParams { x0: 7, x_scale, k_scale: vec![w_scale], y0: 100, y_scale };
            every_path(&s, &input, &kernel, &bias, q, &want);
        }
    }

    #[test]
    fn equals_the_integer_formula_with_zero_points_and_padding() {
        // 6 input channels (a partial group of four), 11 outputs (a partial block), padding 1;
        // padding reads real zeros (the input zero point 7).
        check(ConvShape { ci: 6, h: 9, w: 37, co: 11, kh: 3, kw: 3, pad: [1, 1, 1, 1], stride: 1 });
        // Two 64-channel steps (the second partial), a 32-output block and a partial one, a
        // 5x5 kernel without padding, wide rows that end inside a block.
        check(ConvShape { ci: 70, h: 14, w: 19, co: 40, kh: 5, kw: 5, pad: [0; 4], stride: 1 });
        check(ConvShape { ci: 128, h: 6, w: 6, co: 32, kh: 1, kw: 1, pad: [0, 2, 1, 0], stride: 1 });
        // A 1x1 layer without padding as NanoTrack's: 117 positions (not a multiple of 16),
        // 48 outputs in lanes.
        check(ConvShape { ci: 24, h: 9, w: 13, co: 48, kh: 1, kw: 1, pad: [0; 4], stride: 1 });
        // 96 outputs: two blocks of 48 channels in lanes (on VNNI), 600 tap groups in 5 passes.
        check(ConvShape { ci: 96, h: 9, w: 12, co: 96, kh: 5, kw: 5, pad: [2, 2, 2, 2], stride: 1 });
    }

    /// Per-channel scales as tract's plan has them ([`requant_scales`]: `x · k / y` with 12
    /// output channels, `(k · x) · (1 / y)` with 20), on layers where the two forms give other
    /// bytes ([`parting_case`]; weight scales one per channel, and all equal: tract's exact
    /// product): the `PackedQConv` that `accelerate` makes gives tract's bytes.
    #[test]
    fn per_channel_scales_are_tract_s_to_the_last_bit() {
        if !has_words_path() {
            eprintln!("NOTE: no AVX-512 VNNI, AVX2 or aarch64 dot product here (or PRL_ISA caps it): PackedQConv's per-channel scales are NOT tested on this machine");
            return;
        }
        for co in [12, 20] {
            let s = ConvShape { ci: 8, h: 10, w: 13, co, kh: 3, kw: 3, pad: [1; 4], stride: 1 };
            for exact in [false, true] {
                let (model, input, want) = parting_case(&s, 1, true, exact);
                let mut fast = model;
                assert_eq!(crate::ops::accelerate(&mut fast).unwrap().int8_convolutions, 1, "{s:?}");
                let out = fast.into_runnable().unwrap().run(tvec![input]).unwrap().remove(0);
                // SAFETY: the output is u8 (possibly quantised).
                let got = unsafe { out.try_as_plain_ram().unwrap().as_slice_unchecked::<u8>().to_vec() };
                assert!(got == want, "{co} channels, exact {exact}: other bytes");
            }
        }
    }

    /// The quantised `EinSum` tract makes of a 1x1 convolution (HMG's patch embeddings) becomes
    /// a [`PackedQConv`] giving tract's own bytes; other einsums stay.
    #[test]
    fn the_einsum_of_a_pointwise_convolution_gives_tract_s_bytes() {
        let run = |expr: &str, x_shape: &[usize], w_shape: &[usize], made: usize| {
            // The product form (`akm,kn->mn`) has its channels second to last and the weights
            // `K x N` or `N x K`; the convolutions' have them third to last and `N x K`.
            let product = expr.ends_with("->mn") || expr.ends_with("->anm");
            let ci = match (product, expr.starts_with("mk") || expr.starts_with("HWI")) {
                (_, true) => x_shape[x_shape.len() - 1],
                (true, false) => x_shape[x_shape.len() - 2],
                _ => x_shape[x_shape.len() - 3],
            };
            let co = if product && expr.contains(",kn,") { w_shape[1] } else { w_shape[0] };
            let mut model = TypedModel::default();
            let x = model.add_source("x", u8::fact(x_shape)).unwrap();
            let w: Vec<i8> = (0..w_shape.iter().product()).map(|i: usize| ((i * 104729) % 255) as i32 as i8).collect();
            let konst = |name: &str, t: Tensor, model: &mut TypedModel| model.add_const(name, t).unwrap();
            let w = konst("w", Tensor::from_shape(w_shape, &w).unwrap(), &mut model);
            let bias: Vec<i32> = (0..co as i32).map(|o| 300 * o - 2000).collect();
            let b = konst("b", Tensor::from_shape(&[co], &bias).unwrap(), &mut model);
            let scalars = [
                tensor0(3i32),
                tensor0(0.02f32),
                tensor0(0i32),
                tensor0(0.2f32 / ((ci as f32).sqrt() * 127.0)),
                tensor0(100i32),
                tensor0(0.01f32),
            ];
            let mut inputs = vec![x, w, b];
            for (i, t) in scalars.into_iter().enumerate() {
                inputs.push(konst(&format!("q{i}"), t, &mut model));
            }
            let op = EinSum::newq(expr.parse().unwrap(), i32::datum_type(), u8::datum_type());
            let y = model.wire_node("embed", op, &inputs).unwrap();
            model.select_output_outlets(&y).unwrap();
            let n: usize = x_shape.iter().product();
            let input = Tensor::from_shape(x_shape, &(0..n).map(|i| ((i * 7919) % 256) as u8).collect::<Vec<_>>());
            let input = input.unwrap().into_tvalue();
            let reference = model.clone();
            let done = crate::ops::accelerate(&mut model).unwrap();
            assert_eq!(done.int8_convolutions, made, "{expr}");
            if made == 0 {
                return;
            }
            let want = reference.into_runnable().unwrap().run(tvec![input.clone()]).unwrap();
            let got = model.into_runnable().unwrap().run(tvec![input]).unwrap();
            let (got, want) = (got[0].try_as_plain_ram().unwrap(), want[0].try_as_plain_ram().unwrap());
            // SAFETY: both outputs are u8 (possibly quantised).
            let (got, want) = unsafe { (got.as_slice_unchecked::<u8>(), want.as_slice_unchecked::<u8>()) };
            let spread: std::collections::HashSet<u8> = want.iter().copied().collect();
            assert!(spread.len() > 50, "{expr}: the outputs should spread over the bytes: {}", spread.len());
            assert_eq!(got, want, "{expr}");
        };
        if !has_words_path() {
            eprintln!("NOTE: no AVX-512 VNNI, AVX2 or aarch64 dot product here (or PRL_ISA caps it): the pointwise einsum stays with tract and is NOT tested as a PackedQConv here");
            return;
        }
        // HMG's form (192 channels, 11x11 tokens) with other letters, and 40 outputs (32-channel tiles).
        run("aicd,bi,b,,,,,,->abcd", &[1, 192, 11, 11], &[192, 192], 1);
        run("NIHW,OI,O,,,,,,->NOHW", &[1, 24, 5, 7], &[40, 24], 1);
        // NanoTrack's forms: the batch axis dropped (CHW), and dropped on the way out.
        run("IHW,OI,O,,,,,,->OHW", &[24, 32, 32], &[88, 24], 1);
        run("NIHW,OI,O,,,,,,->OHW", &[1, 16, 24, 20], &[16, 16], 1);
        // Channels last on either side or both (NanoTrack's pointwise layers on aarch64, where
        // tract moves the depthwise layers' channels last), on every words path.
        run("HWI,OI,O,,,,,,->OHW", &[6, 7, 36], &[20, 36], 1);
        run("IHW,OI,O,,,,,,->HWO", &[36, 6, 7], &[20, 36], 1);
        run("HWI,OI,O,,,,,,->HWO", &[9, 13, 39], &[88, 39], 1);
        // Not a pointwise convolution (the weights' axes the other way round): left alone.
        run("NIHW,IO,O,,,,,,->NOHW", &[1, 24, 5, 7], &[24, 40], 0);
        run("IHW,IO,O,,,,,,->OHW", &[24, 5, 7], &[24, 40], 0);
        // HMG's linear layers (`akm,kn->mn`, tokens out last), made where `products_here`
        // says; and without the leading axis.
        let made = usize::from(products_here());
        if made == 0 {
            eprintln!("NOTE: the product form of PackedQConv is made on the AVX2, SDOT and VNNI words paths, on VNNI's where tract's AMX kernels do not take the products (TRACT_CPU_ISA=-amx-int8 reaches it): NOT tested here");
        }
        run("akm,kn,n,,,,,,->mn", &[1, 48, 121], &[48, 72], made);
        run("km,nk,n,,,,,,->mn", &[36, 37], &[20, 36], made);
        // Tokens first in, channels first out, a new leading axis (HMG's `proj` and `fc2`).
        run("mk,kn,n,,,,,,->anm", &[121, 40], &[40, 24], made);
        // Tokens first in and out, input channels that are not whole words, output channels
        // that are not whole blocks of 8, positions that are not whole tiles.
        run("mk,kn,n,,,,,,->mn", &[70, 39], &[39, 20], made);
    }

    /// With one scale, the einsums made `PackedQConv`s (a 1x1 convolution; a product, on the
    /// AVX2 words path) requantise as tract's kernels: at HMG `proj`'s scales, a sum of 48902 is
    /// 93.5 as an f32 product and just under it exactly.
    #[test]
    fn one_scale_rounds_as_tract_s_kernels() {
        if !has_words_path() {
            eprintln!("NOTE: no AVX-512 VNNI, AVX2 or aarch64 dot product here (or PRL_ISA caps it): PackedQConv's rounding is NOT compared with tract's here");
            return;
        }
        // HMG `proj`'s scales, with a sum that rounds apart in f32; and a scale above 1 (the
        // fixed point shifts by less than 31), which tract's kernels served alone until
        // 2026-12-05 (NanoTrack's first pointwise layer with `--method percentile`).
        let (x_scale, w_scale, y_scale) = (0.0069588f32, 0.0007929764f32, 0.0028860883f32);
        let scale = x_scale * w_scale / y_scale;
        let exact = 48902 * Scaler::new(scale, RoundingPolicy::Even);
        assert_ne!((48902.0 * scale).round_ties_even() as i32, exact, "the case must tell the two roundings apart");
        let cases =
            [((x_scale, w_scale, y_scale), [48902i32, -48902, 48901, 1000]), ((0.5, 2.74, 1.0), [41, -57, 3, 90])];
        for ((x_scale, w_scale, y_scale), biases) in cases {
            rounds_as_tract_s_kernels(x_scale, w_scale, y_scale, biases);
        }
    }

    fn rounds_as_tract_s_kernels(x_scale: f32, w_scale: f32, y_scale: f32, biases: [i32; 4]) {
        let scale = x_scale * w_scale / y_scale;
        let exact = biases[0] * Scaler::new(scale, RoundingPolicy::Even);
        let products = products_here();
        if !products {
            eprintln!("NOTE: the product form of PackedQConv is made on the AVX2, SDOT and VNNI words paths, on VNNI's where tract's AMX kernels do not take the products (TRACT_CPU_ISA=-amx-int8 reaches it): its rounding is NOT tested here");
        }
        let forms: [(&str, &[usize], bool); 2] =
            [("NIHW,OI,O,,,,,,->NOHW", &[1, 4, 3, 1], true), ("mk,kn,n,,,,,,->anm", &[3, 4], products)];
        for (expr, x_shape, made) in forms {
            if !made {
                continue;
            }
            let mut model = TypedModel::default();
            // Inputs at their zero point: every sum is its bias.
            let x = model.add_source("x", u8::fact(x_shape)).unwrap();
            let mut konst = |name: &str, t: Tensor| model.add_const(name, t).unwrap();
            let w = konst("w", Tensor::from_shape(&[4, 4], &[1i8; 16]).unwrap());
            let b = konst("b", Tensor::from_shape(&[4], &biases).unwrap());
            let mut inputs = vec![x, w, b];
            for (i, t) in
                [tensor0(5i32), tensor0(x_scale), tensor0(0i32), tensor0(w_scale), tensor0(128i32), tensor0(y_scale)]
                    .into_iter()
                    .enumerate()
            {
                inputs.push(konst(&format!("q{i}"), t));
            }
            let op = EinSum::newq(expr.parse().unwrap(), i32::datum_type(), u8::datum_type());
            let y = model.wire_node("proj", op, &inputs).unwrap();
            model.select_output_outlets(&y).unwrap();
            let input = Tensor::from_shape(x_shape, &[5u8; 12]).unwrap().into_tvalue();
            let reference = model.clone().into_optimized().unwrap();
            assert_eq!(crate::ops::accelerate(&mut model).unwrap().int8_convolutions, 1, "{expr}, scale {scale}");
            let want = reference.into_runnable().unwrap().run(tvec![input.clone()]).unwrap();
            let got = model.into_runnable().unwrap().run(tvec![input]).unwrap();
            let (got, want) = (got[0].try_as_plain_ram().unwrap(), want[0].try_as_plain_ram().unwrap());
            // SAFETY: both outputs are u8 (possibly quantised).
            let (got, want) = unsafe { (got.as_slice_unchecked::<u8>(), want.as_slice_unchecked::<u8>()) };
            assert_eq!(got, want, "{expr}, scale {scale}");
            assert_eq!(got[0] as i32, 128 + exact, "{expr}, scale {scale}");
        }
    }

    #[test]
    fn a_product_s_transpose_puts_each_position_s_channels_in_a_row() {
        let square: [u64; 8] = std::array::from_fn(|i| u64::from_le_bytes(std::array::from_fn(|j| (16 * i + j) as u8)));
        let t = transpose8x8(square);
        for (i, row) in t.iter().enumerate() {
            assert_eq!(row.to_le_bytes(), std::array::from_fn(|j| (16 * j + i) as u8), "row {i}");
        }
        // 21 channels of 45 positions; the blocks from position 32 (13 rows: one square and
        // five rows of bytes) and from 0 (32 rows).
        let (co, m) = (21, 45);
        let planes: Vec<u8> = (0..co * m).map(|i| (i * 7 % 251) as u8).collect();
        for (first, n) in [(0, 32), (32, 13)] {
            let mut rows = vec![0u8; n * co];
            transpose_block(&planes, m, first, &mut rows);
            for (r, row) in rows.chunks_exact(co).enumerate() {
                for (o, &v) in row.iter().enumerate() {
                    assert_eq!(v, planes[o * m + first + r], "position {}, channel {o}", first + r);
                }
            }
        }
    }

    #[test]
    fn stride_two_equals_the_integer_formula() {
        // Backbone layer 1's form: three channels (one word, a zero fourth weight), an 11x11
        // kernel, 96 outputs (channels in lanes on VNNI), odd and even padded sizes.
        check(ConvShape { ci: 3, h: 31, w: 29, co: 96, kh: 11, kw: 11, pad: [0; 4], stride: 2 });
        // Padding on odd and even sides, a partial 8-channel block, two groups of four.
        check(ConvShape { ci: 7, h: 12, w: 15, co: 11, kh: 3, kw: 4, pad: [1, 2, 0, 1], stride: 2 });
        check(ConvShape { ci: 16, h: 10, w: 10, co: 40, kh: 3, kw: 3, pad: [1, 1, 1, 1], stride: 2 });
    }
}
