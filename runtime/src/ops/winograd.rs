//! 3x3 and 5x5 stride-1 float convolutions as Winograd's F(2x2, 3x3) and F(2x2, 5x5)
//! ([`WinogradConv`]): each 2x2 block of outputs from an `α x α` block of inputs (`α = r + 1`)
//! with `α²` multiplications per input channel where the direct form takes `4r²`: 0.44 of the
//! direct convolution's multiply-adds for 3x3 kernels, 0.36 for 5x5.
//!
//! Lavin and Gray's form ("Fast Algorithms for Convolutional Neural Networks", 2016): the
//! outputs of a tile are `Aᵀ [Σ_c (G g Gᵀ) ⊙ (Bᵀ d B)] A` for matrices made from `α − 1`
//! interpolation points and infinity (Toom-Cook): for 3x3 kernels the paper's (points 0, ±1);
//! for 5x5 the points 0, ±1, 1/2, −2. The weights' transform `U = G g Gᵀ` is made once, when
//! the plan is loaded (in f64, rounded once). For each frame:
//!
//! 1. the input transform `V = Bᵀ d B` of every channel's tiles (overlapping by `α − 2`), laid
//!    out `[ξ][channel][tile]` for the `α²` positions `ξ` of a tile (on AVX2 packed in runs of
//!    24 tiles, `[ξ][run][channel][24]`, so that each tile of a product reads its taps one
//!    after the other);
//! 2. `α²` matrix products `M_ξ = U_ξ · V_ξ` (`[co x ci] · [ci x tiles]`), by the direct
//!    convolution's kernel: on AVX2 its assembly tile over the packed runs
//!    ([`super::conv_kernel::packed_products_avx2`]), elsewhere
//!    [`super::conv_kernel::channel_block`] itself (a product is a convolution whose taps are
//!    the channels, one row of `tiles` positions), so every instruction set the direct form has
//!    (AVX-512, AVX2 + FMA, NEON, portable) serves;
//! 3. the output transform `Aᵀ M A`, the bias and the activation, written into the output.
//!
//! **Off unless asked for** ([`crate::Winograd`]: `prl compile --winograd`, `PRL_WINOGRAD`).
//! The sums differ from the direct form's in their rounding. F(2x2, 3x3)'s transforms add and subtract at most four values
//! and halve, so its error stays at the level of a reordered direct sum (3e-7 of the output's
//! range on random layers, against 1.4e-7 for the direct f32 sum); F(2x2, 5x5)'s coefficients
//! (up to 5/2, and 1/15 in `G`) give 1.5e-6; F(4x4, 3x3), 5e-6, is not used. On PRL-Track's
//! reference checkpoint the network's stages come out no further from the official PyTorch
//! ones with them than without, but the tracker's boxes on the official traces move from
//! within 1e-4 px of the official ones to within 2e-4 px (docs/performance.md): a precision
//! the user chooses, not a default.

use std::sync::Arc;

use tract_nnef::internal::*;

use crate::Winograd;

use super::act::{output_fact, reshape_output, Activation, Tail};
use super::conv::ConvShape;
use super::conv_kernel::{channel_block, tile_positions, Layout, MAX_PX, ROWS};
#[cfg(target_arch = "x86_64")]
use super::conv_kernel::{packed_products_avx2, PACKED_PX};
use super::conv_lanes::LanePack;
use super::{output_tensor_written, par_chunks, same_bits, with_padded};

/// One F(2x2, r x r) algorithm: its kernel side `r`, tile side `alpha = r + 1` and matrices
/// (row-major): `Bᵀ` (`α x α`), `G` (`α x r`), `Aᵀ` (`2 x α`).
#[derive(Debug)]
struct Form {
    r: usize,
    alpha: usize,
    bt: &'static [f32],
    g: &'static [f64],
    at: &'static [f32],
}

/// F(2x2, 3x3), Lavin and Gray's matrices (points 0, 1, −1 and infinity).
const F2_3: Form = Form {
    r: 3,
    alpha: 4,
    #[rustfmt::skip]
    bt: &[
        1.0, 0.0, -1.0, 0.0,
        0.0, 1.0, 1.0, 0.0,
        0.0, -1.0, 1.0, 0.0,
        0.0, 1.0, 0.0, -1.0,
    ],
    #[rustfmt::skip]
    g: &[
        1.0, 0.0, 0.0,
        0.5, 0.5, 0.5,
        0.5, -0.5, 0.5,
        0.0, 0.0, 1.0,
    ],
    #[rustfmt::skip]
    at: &[
        1.0, 1.0, 1.0, 0.0,
        0.0, 1.0, -1.0, -1.0,
    ],
};

/// F(2x2, 5x5) from the points 0, 1, −1, 1/2, −2 and infinity: `Bᵀ`'s row `i` holds the
/// coefficients (lowest power first) of `Π_k (x − p_k) / (x − p_i)`, the last `Π_k (x − p_k)`;
/// `G[i][j] = p_iʲ / Π_{k≠i} (p_i − p_k)`; `Aᵀ[l][i] = p_iˡ` (infinity: `[0, 1]`). Of the
/// point sets tried in f32 on random layers (0, ±1 with ±2, ±1/2, 2 and −1/2, 1/2 and −2) this
/// one and its mirror gave the smallest error (1.5e-6 of the range, ±2 and ±1/2 4e-6).
const F2_5: Form = Form {
    r: 5,
    alpha: 6,
    #[rustfmt::skip]
    bt: &[
        1.0, -1.5, -2.0, 1.5, 1.0, 0.0,
        0.0, -1.0, 0.5, 2.5, 1.0, 0.0,
        0.0, 1.0, -2.5, 0.5, 1.0, 0.0,
        0.0, -2.0, -1.0, 2.0, 1.0, 0.0,
        0.0, 0.5, -1.0, -0.5, 1.0, 0.0,
        0.0, 1.0, -1.5, -2.0, 1.5, 1.0,
    ],
    #[rustfmt::skip]
    g: &[
        1.0, 0.0, 0.0, 0.0, 0.0,
        1.0 / 3.0, 1.0 / 3.0, 1.0 / 3.0, 1.0 / 3.0, 1.0 / 3.0,
        -1.0 / 3.0, 1.0 / 3.0, -1.0 / 3.0, 1.0 / 3.0, -1.0 / 3.0,
        -16.0 / 15.0, -8.0 / 15.0, -4.0 / 15.0, -2.0 / 15.0, -1.0 / 15.0,
        1.0 / 15.0, -2.0 / 15.0, 4.0 / 15.0, -8.0 / 15.0, 16.0 / 15.0,
        0.0, 0.0, 0.0, 0.0, 1.0,
    ],
    #[rustfmt::skip]
    at: &[
        1.0, 1.0, 1.0, 1.0, 1.0, 0.0,
        0.0, 1.0, -1.0, 0.5, -2.0, 1.0,
    ],
};

/// The form for an `r x r` kernel, if there is one.
fn form(r: usize) -> Option<&'static Form> {
    match r {
        3 => Some(&F2_3),
        5 => Some(&F2_5),
        _ => None,
    }
}

/// `dst[x] = Σ_i coef[i]·src_i[x]` over the nonzero coefficients (a coefficient of ±1 adds or
/// subtracts exactly; the first term is `0 + c·x`, so `c·x`, rounded once).
#[inline(always)]
fn combine<'a>(dst: &mut [f32], coef: &[f32], src: impl Fn(usize) -> &'a [f32]) {
    let mut first = true;
    for (i, &c) in coef.iter().enumerate() {
        if c == 0.0 {
            continue;
        }
        let x = &src(i)[..dst.len()];
        if first {
            dst.iter_mut().zip(x).for_each(|(d, &x)| *d = c * x);
        } else {
            dst.iter_mut().zip(x).for_each(|(d, &x)| *d += c * x);
        }
        first = false;
    }
    if first {
        dst.fill(0.0);
    }
}

/// Whether a convolution of `shape` pays as F(2x2, r x r): a square kernel with a [`Form`] and
/// stride 1, enough channels for the transforms (one pass per input and per output channel)
/// to be small beside the products, and products that are at most [`PRODUCTS_PAY`] of the
/// direct form's multiply-adds as the kernels run them: `α²` per tile against `r²` per wide
/// position of [`super::PackedConv`] (`(oh − 1)·Wp + ow`, the padded rows' dropped columns
/// included), each rounded up to whole tiles of the kernel; or, where `PackedConv` runs the
/// layer in compact tiles (AVX2 or AVX-512, where they pay), `r²` per output position,
/// rounded up to them.
pub(crate) fn suits(shape: &ConvShape) -> bool {
    let Some(f) = form(shape.kh) else { return false };
    if shape.kw != shape.kh || shape.stride != 1 || shape.ci < 32 || shape.co < 32 {
        return false;
    }
    let (oh, ow) = shape.out();
    let px = tile_positions();
    let whole = |n: usize| n.div_ceil(px) * px;
    let winograd = f.alpha * f.alpha * whole(oh.div_ceil(2) * ow.div_ceil(2));
    let direct = f.r
        * f.r
        * if LanePack::compact_pays(shape) {
            LanePack::compact_positions(shape)
        } else {
            whole((oh - 1) * shape.phase().1 + ow)
        };
    winograd * PRODUCTS_PAY.1 <= direct * PRODUCTS_PAY.0
}

/// The share of the direct form's multiply-adds under which F(2x2, r x r) pays (the
/// transforms take the rest), from PRL-Track's layers on an AMD EPYC (Zen 2), one thread,
/// with the transforms as they are now: the template's 3x3 layer 5 (6 x 6 outputs, 9 tiles in
/// a kernel tile of 24) at 0.89 of the direct form's products was 1.03 -> 1.23 ms; its layer 3
/// at 0.71 2.31 -> 2.06 ms, the heads' (11 x 11) at 0.59 1.07 -> 0.89, the template's layer 4
/// at 0.44 2.79 -> 1.75.
const PRODUCTS_PAY: (usize, usize) = (3, 4);

/// A 3x3 or 5x5 stride-1 convolution with constant weights as Winograd's F(2x2, r x r) (module
/// docs):
/// `out[n,o,y,x] = act(bias[o] + Σ_{c,i,j} pad(input)[n,c,y+i,x+j]·weight[o,c,i,j])`, up to
/// rounding.
#[derive(Clone)]
pub struct WinogradConv {
    shape: ConvShape,
    form: &'static Form,
    /// Tile rows and columns: `ceil(oh / 2)`, `ceil(ow / 2)`.
    tiles: (usize, usize),
    /// The products' taps (input channel `c` at `c·ld`, or `c·24` within a packed run) and
    /// one row of `ld` positions ([`Self::stride`]), made once.
    layout: Arc<Layout>,
    /// `U_ξ` for each of the `α²` positions `ξ`, packed as the direct kernel takes them:
    /// `[ξ][block][c][ROWS]`.
    weights: Arc<Vec<f32>>,
    /// Tiles per run where the transformed input is packed in runs ([`Self::packed_run`]),
    /// chosen once when the operator is made: the products' kernel and the transforms'
    /// layout read this one value.
    packed: Option<usize>,
    bias: Arc<Vec<f32>>,
    act: Activation,
    /// The output's shape where the fused nodes end in another shape than `[n, co, oh, ow]`.
    reshape: Option<TVec<usize>>,
}

impl std::fmt::Debug for WinogradConv {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "WinogradConv({:?})", self.shape)
    }
}

impl PartialEq for WinogradConv {
    fn eq(&self, other: &Self) -> bool {
        self.shape == other.shape
            && same_bits(&self.weights, &other.weights)
            && same_bits(&self.bias, &other.bias)
            && self.act == other.act
            && self.reshape == other.reshape
    }
}

impl Eq for WinogradConv {}

/// `U = G g Gᵀ` of one `r x r` kernel `g` (row-major) into `u` (`α x α`), in f64 (`G g`
/// first, then `· Gᵀ`), rounded once.
fn transform_kernel(f: &Form, g: &[f32], u: &mut [f32]) {
    let (r, al) = (f.r, f.alpha);
    let mut gg = [0f64; 6 * 5];
    for a in 0..al {
        for j in 0..r {
            gg[a * r + j] = (0..r).map(|i| f.g[a * r + i] * g[i * r + j] as f64).sum();
        }
    }
    for a in 0..al {
        for b in 0..al {
            u[a * al + b] = (0..r).map(|j| gg[a * r + j] * f.g[b * r + j]).sum::<f64>() as f32;
        }
    }
}

impl WinogradConv {
    /// Transform and pack OIHW `weight` (`[co, ci, r, r]`) and `bias` (one value or `co`).
    pub fn new(shape: ConvShape, weight: &[f32], bias: &[f32]) -> TractResult<WinogradConv> {
        ensure!(suits(&shape), "WinogradConv: {shape:?} is not a convolution it serves");
        let f = form(shape.kh).expect("suits");
        let (ci, co, r, xis) = (shape.ci, shape.co, f.r, f.alpha * f.alpha);
        ensure!(weight.len() == co * ci * r * r, "WinogradConv: {} weights for {shape:?}", weight.len());
        ensure!(bias.len() == 1 || bias.len() == co, "WinogradConv: {} bias values for {shape:?}", bias.len());
        let (oh, ow) = shape.out();
        let tiles = (oh.div_ceil(2), ow.div_ceil(2));
        let blocks = co.div_ceil(ROWS);
        let mut weights = vec![0f32; xis * blocks * ci * ROWS];
        let mut u = vec![0f32; xis];
        for o in 0..co {
            for c in 0..ci {
                transform_kernel(f, &weight[(o * ci + c) * r * r..][..r * r], &mut u);
                for (xi, &v) in u.iter().enumerate() {
                    weights[((xi * blocks + o / ROWS) * ci + c) * ROWS + o % ROWS] = v;
                }
            }
        }
        let bias = (0..co).map(|o| if bias.len() == 1 { bias[0] } else { bias[o] }).collect();
        let ld = (tiles.0 * tiles.1).div_ceil(tile_positions()) * tile_positions();
        let packed = Self::packed_run();
        let step = packed.unwrap_or(ld);
        let layout = Layout { taps: (0..ci).map(|c| c * step).collect(), wp: ld, oh: 1, ow: ld };
        Ok(WinogradConv {
            shape,
            form: f,
            tiles,
            layout: Arc::new(layout),
            weights: Arc::new(weights),
            packed,
            bias: Arc::new(bias),
            act: Activation::NONE,
            reshape: None,
        })
    }

    /// The convolution followed by the nodes of `tail` ([`super::act::tail`]).
    pub(crate) fn fused(self, tail: &Tail) -> TractResult<WinogradConv> {
        ensure!(tail.bias.is_none(), "WinogradConv: a convolution has its own bias");
        Ok(WinogradConv { act: tail.act, reshape: tail.reshaped(), ..self })
    }

    /// Tiles of one plane.
    fn tile_count(&self) -> usize {
        self.tiles.0 * self.tiles.1
    }

    /// Tiles per run where the transformed input is packed in runs (on AVX2, for
    /// `conv_kernel::packed_products_avx2`); `None` where it is not.
    fn packed_run() -> Option<usize> {
        #[cfg(target_arch = "x86_64")]
        if crate::isa::f32_kernel() == crate::isa::F32Kernel::Avx2Fma {
            return Some(PACKED_PX);
        }
        None
    }

    /// Positions per channel of the transformed input and of the products: the tiles rounded
    /// up to whole tiles of the kernel (the positions after the last tile are zero in, ignored
    /// out), so that the kernel stores every tile whole (a partial one goes value by value).
    fn stride(&self) -> usize {
        self.layout.wp
    }

    /// Row `a` of `Bᵀ d` (`ξ = α·a + b`) of every tile of one channel's plane `src`
    /// (`[h, w]`), left in `sc.cols` as `α` blocks of [`Self::tile_count`] values: block `j`
    /// holds column `j` of the row of every tile (`ty·tw + tx`), so that `· B` is one pass
    /// over long vectors per `b` ([`Self::run`]).
    ///
    /// The padded plane is kept as its even rows and its odd rows, so that row `2·ty + i` of
    /// every tile row is one slice and `Bᵀ d`'s row `a` one pass over the whole plane too.
    #[inline(always)]
    fn transform_input(&self, src: &[f32], a: usize, sc: &mut Scratch) {
        let (s, f) = (&self.shape, self.form);
        let al = f.alpha;
        let (rows, tw) = self.tiles;
        // The padded plane the tiles read (`2·th + α − 2` rows of `2·tw + α − 2`): the input
        // where it falls, zero elsewhere (the padding, and under a last tile half outside).
        let (hp, wp) = (2 * rows + al - 2, 2 * tw + al - 2);
        assert!(s.pad[0] + s.h <= hp && s.pad[1] + s.w <= wp && hp.is_multiple_of(2));
        let half_plane = hp / 2 * wp;
        sc.pad.clear();
        sc.pad.resize(2 * half_plane, 0.0);
        for (y, row) in src.chunks_exact(s.w).enumerate() {
            let y = y + s.pad[0];
            sc.pad[(y % 2) * half_plane + y / 2 * wp + s.pad[1]..][..s.w].copy_from_slice(row);
        }
        // Row a of Bᵀ d for every tile row: its row i is padded row 2ty + i.
        let n = rows * wp;
        sc.row.resize(n, 0.0);
        let pad = &sc.pad;
        combine(&mut sc.row, &f.bt[a * al..][..al], |i| &pad[(i % 2) * half_plane + i / 2 * wp..][..n]);
        // Tile tx reads columns 2tx .. 2tx + α − 1 of its tile row.
        let t = rows * tw;
        sc.cols.resize(al * t, 0.0);
        for (j, col) in sc.cols.chunks_exact_mut(t).enumerate() {
            for (dst, row) in col.chunks_exact_mut(tw).zip(sc.row.chunks_exact(wp)) {
                // Every other value: as pairs (the indexed form stayed scalar, with a bounds
                // check a value, on NEON), the last tile's from the odd one left.
                let (pairs, last) = row[j..][..2 * tw - 1].as_chunks::<2>();
                for (d, p) in dst.iter_mut().zip(pairs) {
                    *d = p[0];
                }
                dst[tw - 1] = last[0];
            }
        }
    }

    /// `act(bias + Aᵀ M A)` of channels `o0 .. o0 + g` (`out` holds their `[oh, ow]` planes)
    /// from the products `m` (`[ξ][o][ld]`, `co_pad` channels). The transform runs on the
    /// `g·ld` values of the group's channels (every position), by pieces of [`OUT_PIECE`], so
    /// its vectors are long whatever the map's width.
    #[inline(always)]
    fn transform_output(
        &self,
        m: &[f32],
        (ld, co_pad): (usize, usize),
        (o0, g): (usize, usize),
        out: &mut [f32],
        sc: &mut Scratch,
    ) {
        let f = self.form;
        let al = f.alpha;
        let (oh, ow) = self.shape.out();
        let tw = self.tiles.1;
        let n = g * ld;
        // `c[i][j]`: row i of Aᵀ m, column j; then `y[2i + l]`, the outputs (2ty + i, 2tx + l).
        // By pieces of `OUT_PIECE` values, so that `Aᵀ m` stays in the cache between the
        // passes.
        sc.pad.resize(2 * al * OUT_PIECE, 0.0);
        sc.row.resize(4 * n, 0.0);
        let (c, y) = (&mut sc.pad, &mut sc.row);
        for p0 in (0..n).step_by(OUT_PIECE) {
            let len = OUT_PIECE.min(n - p0);
            let block = |xi: usize| &m[(xi * co_pad + o0) * ld + p0..][..len];
            for i in 0..2 {
                for j in 0..al {
                    combine(&mut c[(i * al + j) * len..][..len], &f.at[i * al..][..al], |k| block(k * al + j));
                }
            }
            for i in 0..2 {
                for l in 0..2 {
                    let c = &c[..2 * al * len];
                    combine(&mut y[(2 * i + l) * n + p0..][..len], &f.at[l * al..][..al], |j| {
                        &c[(i * al + j) * len..][..len]
                    });
                }
            }
        }
        // Each tile to its 2x2 outputs, row of outputs by row.
        for (o, plane) in out.chunks_exact_mut(oh * ow).enumerate() {
            let bias = self.bias[o0 + o];
            for (yo, row) in plane.chunks_exact_mut(ow).enumerate() {
                let (ty, i) = (yo / 2, yo % 2);
                let at = o * ld + ty * tw;
                let (even, odd) = (&y[2 * i * n + at..][..tw], &y[(2 * i + 1) * n + at..][..tw]);
                let (pairs, last) = row.as_chunks_mut::<2>();
                for ((pair, &e), &o) in pairs.iter_mut().zip(even).zip(odd) {
                    *pair = [bias + e, bias + o];
                }
                if let [v] = last {
                    *v = bias + even[pairs.len()];
                }
            }
            self.act.apply_all(plane);
        }
    }

    /// Step 1 of [`Self::run`] for row `a` of the tiles' transform: `part` (`[b][c][ld]`, or
    /// on AVX2 `[b][run][c][24]`) takes the `α` blocks `ξ = α·a + b` of every channel of
    /// `src`. On AVX2 (and AVX-512) the transforms are compiled for 8 lanes (the crate's
    /// baseline is SSE2's 4): the same operations, so the same bits.
    fn input_part(&self, src: &[f32], a: usize, part: &mut [f32]) {
        #[cfg(target_arch = "x86_64")]
        if crate::isa::isa().avx2_fma {
            // SAFETY: the CPU has AVX2 and FMA.
            return unsafe { self.input_part_avx2(src, a, part) };
        }
        self.input_part_inline(src, a, part)
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,fma")]
    unsafe fn input_part_avx2(&self, src: &[f32], a: usize, part: &mut [f32]) {
        self.input_part_inline(src, a, part)
    }

    /// [`Self::input_part`]'s loop: the channels by groups of [`IN_GROUP`], each channel's
    /// `α` blocks into `sc.tmp`, then (packed) the group's runs, each `IN_GROUP·24` values
    /// one after the other in `part`, so that whole lines are written (one channel's runs,
    /// 96 bytes each `24·ci` values apart, took 5 of PRL-Track's layer 2's 8.6 ms).
    #[inline(always)]
    fn input_part_inline(&self, src: &[f32], a: usize, part: &mut [f32]) {
        let (ci, hw) = (self.shape.ci, self.shape.h * self.shape.w);
        let (al, ld, t) = (self.form.alpha, self.stride(), self.tile_count());
        let packed = self.packed;
        Scratch::with(|sc| {
            for c0 in (0..ci).step_by(IN_GROUP) {
                let g = IN_GROUP.min(ci - c0);
                sc.tmp.resize(g * al * ld, 0.0);
                for c in c0..c0 + g {
                    self.transform_input(&src[c * hw..][..hw], a, sc);
                    // · B: column j of every tile's row a is block j of `cols`.
                    let cols = &sc.cols;
                    let column = |j: usize| &cols[j * t..][..t];
                    for b in 0..al {
                        let row = match packed {
                            None => &mut part[(b * ci + c) * ld..][..ld],
                            Some(_) => &mut sc.tmp[((c - c0) * al + b) * ld..][..ld],
                        };
                        combine(&mut row[..t], &self.form.bt[b * al..][..al], column);
                        row[t..].fill(0.0);
                    }
                }
                let Some(px) = packed else { continue };
                for b in 0..al {
                    for r in 0..ld / px {
                        let dst = &mut part[b * ci * ld + (r * ci + c0) * px..][..g * px];
                        for (k, run) in dst.chunks_exact_mut(px).enumerate() {
                            run.copy_from_slice(&sc.tmp[(k * al + b) * ld + r * px..][..px]);
                        }
                    }
                }
            }
        })
    }

    /// Step 3 of [`Self::run`] for output channels `o0 .. o0 + g` ([`Self::transform_output`]),
    /// compiled for 8 lanes on AVX2 as [`Self::input_part`].
    fn output_group(&self, m: &[f32], lds: (usize, usize), group: (usize, usize), out: &mut [f32]) {
        Scratch::with(|sc| {
            #[cfg(target_arch = "x86_64")]
            if crate::isa::isa().avx2_fma {
                // SAFETY: the CPU has AVX2 and FMA.
                return unsafe { self.output_group_avx2(m, lds, group, out, sc) };
            }
            self.transform_output(m, lds, group, out, sc)
        })
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,fma")]
    unsafe fn output_group_avx2(
        &self,
        m: &[f32],
        lds: (usize, usize),
        group: (usize, usize),
        out: &mut [f32],
        sc: &mut Scratch,
    ) {
        self.transform_output(m, lds, group, out, sc)
    }

    /// One image: `src` (`[ci, h, w]`) into `dst` (`[co, oh, ow]`); `buf` is scratch for the
    /// transformed input `[ξ][c][ld]` (with the kernel's slack after it) and the products
    /// `[ξ][o][ld]` ([`Self::stride`]).
    fn run(&self, src: &[f32], dst: &mut [f32], buf: &mut [f32]) {
        let (ci, co) = (self.shape.ci, self.shape.co);
        let (al, xis) = (self.form.alpha, self.form.alpha * self.form.alpha);
        let (blocks, ld) = (co.div_ceil(ROWS), self.stride());
        let co_pad = blocks * ROWS;
        let (oh, ow) = self.shape.out();
        let (v, m) = buf.split_at_mut(xis * ci * ld + MAX_PX);
        // Step 1: `v[ξ][c][tile]`, by row `a` of the tile's transform (the `α` blocks
        // `ξ = α·a .. α·a + α − 1`) on the threads. On AVX2 the transformed input is packed
        // `[ξ][run][c][24]` for `conv_kernel::packed_products_avx2`, so that each tile of the
        // products reads its taps one after the other (through the direct kernel, rows `ld`
        // apart, the products ran at 65 GFLOP/s where the direct convolution reaches 88 on an
        // AMD EPYC); elsewhere `[ξ][c][ld]`, for the direct kernel.
        par_chunks(&mut v[..xis * ci * ld], al * ci * ld, |a, part| self.input_part(src, a, part));
        v[xis * ci * ld..].fill(0.0);
        // Step 2: `m[ξ][o][tile] = Σ_c U_ξ[o][c]·v[ξ][c][tile]`, by block of `ROWS` output
        // channels on the threads: the direct kernel with the channels as taps.
        let zero = [0f32; ROWS];
        let v: &[f32] = v;
        let m = &mut m[..xis * co_pad * ld];
        par_chunks(m, ROWS * ld, |k, m| {
            let (xi, b) = (k / blocks, k % blocks);
            let weights = &self.weights[(xi * blocks + b) * ci * ROWS..][..ci * ROWS];
            let v = &v[xi * ci * ld..];
            #[cfg(target_arch = "x86_64")]
            if let Some(px) = self.packed {
                // SAFETY: the CPU has AVX2 and FMA (the table's kernel); the taps are `24c`
                // for `c < ci`; `v` holds `ld / 24` runs of `24·ci` values, `weights`
                // `ROWS·ci`, `m` `ROWS` rows of `ld`.
                return unsafe { packed_products_avx2(v, &self.layout.taps, ld / px, weights, m, ld) };
            }
            channel_block(&self.layout, v, weights, &zero, Activation::NONE, m);
        });
        // Step 3: every output channel's plane, by group of channels on the threads.
        let m: &[f32] = m;
        par_chunks(dst, OUT_GROUP * oh * ow, |k, out| {
            let g = out.len() / (oh * ow);
            self.output_group(m, (ld, co_pad), (k * OUT_GROUP, g), out);
        });
    }

    /// Values of [`Self::run`]'s scratch: the transformed input, the kernel's slack and the
    /// products.
    fn scratch_len(&self) -> usize {
        let xis = self.form.alpha * self.form.alpha;
        xis * (self.shape.ci + self.shape.co.div_ceil(ROWS) * ROWS) * self.stride() + MAX_PX
    }
}

/// Input channels whose transforms are packed together ([`WinogradConv::input_part`]).
const IN_GROUP: usize = 16;

/// Output channels per task of the output transform.
const OUT_GROUP: usize = 16;

/// Positions per pass of the output transform: its `2·α` rows of `Aᵀ m` (48 KiB for
/// F(2x2, 5x5)) stay in the first-level cache, where over a whole group at once they took
/// 845 KiB on PRL-Track's layer 2. (No faster by itself on an AMD EPYC: the transform is
/// bound by reading the products, 40 MB on that layer, from memory.)
const OUT_PIECE: usize = 1024;

/// A task's buffers for the transforms: each thread's own, kept from frame to frame
/// ([`Scratch::with`]); every value is written before it is read.
#[derive(Default)]
struct Scratch {
    /// The input transform's padded plane (its even rows, then its odd rows); the output
    /// transform's `Aᵀ m`.
    pad: Vec<f32>,
    /// A row of `Bᵀ d` for every tile row; the output transform's outputs before they are
    /// scattered.
    row: Vec<f32>,
    /// That row's columns, tile by tile ([`WinogradConv::transform_input`]).
    cols: Vec<f32>,
    /// A group of channels' transformed rows before they are packed in runs
    /// ([`WinogradConv::input_part`]).
    tmp: Vec<f32>,
}

impl Scratch {
    /// `f` on this thread's buffers (the group buffer alone is 16·α·ld values, 0.4 MB on
    /// PRL-Track's layer 2: not allocated again for every task of every frame).
    fn with<R>(f: impl FnOnce(&mut Scratch) -> R) -> R {
        use std::cell::RefCell;
        thread_local! {
            static SCRATCH: RefCell<Scratch> = RefCell::default();
        }
        SCRATCH.with(|s| match s.try_borrow_mut() {
            Ok(mut s) => f(&mut s),
            // In use further up this thread's stack (not the case today): buffers of its own.
            Err(_) => f(&mut Scratch::default()),
        })
    }
}

impl Op for WinogradConv {
    fn name(&self) -> StaticName {
        "WinogradConv".into()
    }

    fn info(&self) -> TractResult<Vec<String>> {
        let (s, r) = (&self.shape, self.form.r);
        Ok(vec![format!(
            "F(2x2, {r}x{r}), {} -> {} channels, pad {:?}, {}x{} tiles, activation {}",
            s.ci,
            s.co,
            s.pad,
            self.tiles.0,
            self.tiles.1,
            self.act.describe()
        )])
    }

    op_as_typed_op!();
}

impl EvalOp for WinogradConv {
    op_out_of_plan!();

    fn eval(&self, _ctx: &EvalContext, inputs: TVec<TValue>) -> TractResult<TVec<TValue>> {
        let input = args_1!(inputs);
        let s = &self.shape;
        let (n, ci, h, w) = (s.batch_of("WinogradConv", input.shape())?, s.ci, s.h, s.w);
        let input = input.try_as_plain_ram()?;
        let input = input.as_slice::<f32>()?;
        let (oh, ow) = s.out();
        let fill = |out: &mut [f32]| {
            // Written whole before it is read (the kernel's slack by `run`).
            with_padded(self.scratch_len(), &[], |buf| {
                for (src, dst) in input.chunks_exact(ci * h * w).zip(out.chunks_exact_mut(s.co * oh * ow)) {
                    self.run(src, dst, buf);
                }
                Ok(())
            })
        };
        // SAFETY: every output is written: each channel's plane, row by row.
        let out = unsafe { output_tensor_written(&[n, s.co, oh, ow], fill)? };
        Ok(tvec!(reshape_output(out, self.reshape.as_ref())?.into_tvalue()))
    }
}

impl TypedOp for WinogradConv {
    fn output_facts(&self, inputs: &[&TypedFact]) -> TractResult<TVec<TypedFact>> {
        Ok(tvec!(output_fact(self.reshape.as_ref(), || self.shape.output_fact(&inputs[0].shape[0]))))
    }

    fn cost(&self, inputs: &[&TypedFact]) -> TractResult<TVec<(Cost, TDim)>> {
        // The products' multiply-adds (the transforms' additions are not counted).
        let s = &self.shape;
        let macs = self.form.alpha * self.form.alpha * s.co * s.ci * self.tile_count();
        Ok(tvec!((Cost::FMA(f32::datum_type()), inputs[0].shape[0].clone() * macs)))
    }

    as_op!();
}

/// The [`WinogradConv`] for `node` of `model` if it is a float convolution of
/// [`super::conv::plain_conv`]'s kind that [`suits`] F(2x2, r x r), of a side `choice` names.
pub(crate) fn winograd(model: &TypedModel, node: &TypedNode, choice: Winograd) -> TractResult<Option<WinogradConv>> {
    if choice.is_off() {
        return Ok(None);
    }
    let Some((shape, weight, bias)) = super::conv::plain_conv(model, node)? else { return Ok(None) };
    if !suits(&shape) || !choice.kernel_sides().contains(&shape.kh) {
        return Ok(None);
    }
    Ok(Some(WinogradConv::new(shape, weight, bias)?))
}

#[cfg(test)]
mod tests;
