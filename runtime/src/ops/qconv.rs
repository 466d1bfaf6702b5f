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
//!
//! Which graph nodes become one, with tract's requantisation scales: [`matching`]; the input
//! packed into words and the tiles run over it: [`words`].

use std::sync::Arc;

use tract_nnef::internal::*;

use super::conv_kernel::Layout;
use super::qconv_amx::AmxWeights;
use super::qconv_kernel::{avx2_pairs, requantise};
use super::qconv_lanes::QLanePack;
use super::{output_tensor_written, par_chunks, same_bits, ConvShape};

mod matching;
#[cfg(test)]
mod tests;
mod words;

pub(crate) use matching::packed_q;
pub(super) use matching::{konst_values, quant_params, requant_scales, sum_bound};
#[cfg(test)]
pub(super) use tests::{parting_case, tract_q_conv};
use words::{transpose_block, Src, TRANSPOSE_ROWS};

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

/// Whether HMG's linear layers run as [`PackedQConv`]s here (`matching::matmul_shape`): on the AVX2
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
