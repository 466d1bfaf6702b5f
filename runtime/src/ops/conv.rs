//! Float convolutions of stride 1 or 2 with constant weights as [`PackedConv`], a direct
//! convolution whose weights are packed once, when the plan is loaded ([`super::conv_kernel`]).
//! With stride 2 the padded input is stored as its four phases (even/odd rows x columns), so
//! that each tap again reads consecutive positions: the same kernel, and no extra work.
//!
//! tract runs these convolutions as an im2col and a matrix product with the whole reduction
//! (`k` = 2400 for backbone layer 2) in one pass, which here reached 25-60 GFLOP/s on one core
//! against about 100 for ONNX Runtime. The direct form reads every tap's inputs in place, with
//! no im2col buffer and no packing of the activations.

use std::sync::Arc;

use tract_nnef::internal::*;
use tract_nnef::tract_core::ops::cnn::{Conv, KernelFormat};
use tract_nnef::tract_core::ops::nn::DataFormat;

use super::act::{output_fact, reshape_output, Activation, Tail};
use super::conv_kernel::{channel_block, Layout, MAX_PX, ROWS};
use super::conv_lanes::LanePack;
use super::{all_ones, output_tensor_written, pads_2d, par_chunks, same_bits, serial_if_small};

/// `dst = src` (equal lengths), 16 values at a time by fixed-size copies: a row of a small
/// plane is too short for a library `memcpy` call to pay.
fn copy_row(src: &[f32], dst: &mut [f32]) {
    let (mut d, mut s) = (dst.chunks_exact_mut(16), src.chunks_exact(16));
    for (d, s) in (&mut d).zip(&mut s) {
        let (d, s): (&mut [f32; 16], &[f32; 16]) = (d.try_into().expect("16"), s.try_into().expect("16"));
        *d = *s;
    }
    d.into_remainder().copy_from_slice(s.remainder());
}

/// `rows` rows of `w` values from `src` (consecutive) to `dst` (`ld` apart), 16 values a step,
/// the last of each row masked: no call and no bounds check per row (a depthwise layer pads
/// thousands of rows of 8 to 32 values).
///
/// # Safety
/// The CPU has AVX-512F; `src` holds `rows · w` values, and `dst + y·ld .. + w` is writable
/// for every row `y`.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
unsafe fn copy_rows_avx512(src: *const f32, w: usize, rows: usize, dst: *mut f32, ld: usize) {
    use std::arch::x86_64::*;
    let (full, rest) = (w / 16, w % 16);
    let mask: __mmask16 = ((1u32 << rest) - 1) as __mmask16;
    for y in 0..rows {
        // SAFETY: within row y of `src` and its slot in `dst` (the caller's promise).
        unsafe {
            let (s, d) = (src.add(y * w), dst.add(y * ld));
            for k in 0..full {
                _mm512_storeu_ps(d.add(16 * k), _mm512_loadu_ps(s.add(16 * k)));
            }
            if rest > 0 {
                let v = _mm512_maskz_loadu_ps(mask, s.add(16 * full));
                _mm512_mask_storeu_ps(d.add(16 * full), mask, v);
            }
        }
    }
}

/// `row`'s values at even positions into `even`, at odd ones into `odd` (`even` holds
/// `ceil(len / 2)` values, `odd` `floor(len / 2)`).
fn deinterleave(row: &[f32], even: &mut [f32], odd: &mut [f32]) {
    assert!(even.len() == row.len().div_ceil(2) && odd.len() == row.len() / 2);
    // The pairs the vector path wrote (none where there is none).
    #[cfg(target_arch = "x86_64")]
    let done = if crate::isa::f32_kernel() == crate::isa::F32Kernel::Avx512 {
        // SAFETY: the CPU has AVX-512F (the table's needs); the lengths are asserted above.
        unsafe { deinterleave_avx512(row, even, odd) }
    } else if crate::isa::f32_kernel() == crate::isa::F32Kernel::Avx2Fma {
        // SAFETY: the CPU has AVX2 (the table's needs); the lengths are asserted above.
        unsafe { deinterleave_avx2(row, even, odd) }
    } else {
        0
    };
    #[cfg(not(target_arch = "x86_64"))]
    let done = 0;
    deinterleave_rest(row, even, odd, done);
}

/// [`deinterleave`]'s pairs from pair `done` on, one by one, and a last odd value.
fn deinterleave_rest(row: &[f32], even: &mut [f32], odd: &mut [f32], done: usize) {
    for ((e, o), pair) in even[done..].iter_mut().zip(odd[done..].iter_mut()).zip(row[2 * done..].chunks_exact(2)) {
        (*e, *o) = (pair[0], pair[1]);
    }
    if row.len() % 2 == 1 {
        even[even.len() - 1] = row[row.len() - 1];
    }
}

/// Where padded row `yp` starts in a plane padded for stride 2 (four phases `[row parity]
/// [column parity][hq][wq]`): its row parity's even-column phase, row `yp / 2`.
fn phase_slot(yp: usize, hq: usize, wq: usize) -> usize {
    (yp % 2) * 2 * hq * wq + (yp / 2) * wq
}

/// [`deinterleave`] 32 values at a time (two loads, two permutes); returns how many pairs it
/// wrote (a multiple of 16), the rest left to the caller.
///
/// # Safety
/// The CPU has AVX-512F; `even` and `odd` hold at least `row.len() / 2` values.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
unsafe fn deinterleave_avx512(row: &[f32], even: &mut [f32], odd: &mut [f32]) -> usize {
    use std::arch::x86_64::*;
    let blocks = row.len() / 32;
    let ie = _mm512_setr_epi32(0, 2, 4, 6, 8, 10, 12, 14, 16, 18, 20, 22, 24, 26, 28, 30);
    let io = _mm512_setr_epi32(1, 3, 5, 7, 9, 11, 13, 15, 17, 19, 21, 23, 25, 27, 29, 31);
    for b in 0..blocks {
        // SAFETY: 32 values of `row` from 32·b (b < len / 32), 16 of `even` and `odd` from
        // 16·b (they hold len / 2 >= 16·blocks).
        unsafe {
            let lo = _mm512_loadu_ps(row.as_ptr().add(32 * b));
            let hi = _mm512_loadu_ps(row.as_ptr().add(32 * b + 16));
            _mm512_storeu_ps(even.as_mut_ptr().add(16 * b), _mm512_permutex2var_ps(lo, ie, hi));
            _mm512_storeu_ps(odd.as_mut_ptr().add(16 * b), _mm512_permutex2var_ps(lo, io, hi));
        }
    }
    16 * blocks
}

/// [`deinterleave`] 16 values at a time on AVX2 (two loads; two in-lane shuffles and two
/// 64-bit permutes); returns how many pairs it wrote (a multiple of 8).
///
/// # Safety
/// The CPU has AVX2; `even` and `odd` hold at least `row.len() / 2` values.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn deinterleave_avx2(row: &[f32], even: &mut [f32], odd: &mut [f32]) -> usize {
    use std::arch::x86_64::*;
    let blocks = row.len() / 16;
    for b in 0..blocks {
        // SAFETY: 16 values of `row` from 16·b (b < len / 16), 8 of `even` and `odd` from 8·b
        // (they hold len / 2 >= 8·blocks).
        unsafe {
            let lo = _mm256_loadu_ps(row.as_ptr().add(16 * b));
            let hi = _mm256_loadu_ps(row.as_ptr().add(16 * b + 8));
            // Per 128-bit lane: [lo0 lo2 hi0 hi2 | lo4 lo6 hi4 hi6]; the permute puts the
            // 64-bit pairs in order.
            let e = _mm256_shuffle_ps::<0b10_00_10_00>(lo, hi);
            let o = _mm256_shuffle_ps::<0b11_01_11_01>(lo, hi);
            let order = |v: __m256| _mm256_castpd_ps(_mm256_permute4x64_pd::<0b11_01_10_00>(_mm256_castps_pd(v)));
            _mm256_storeu_ps(even.as_mut_ptr().add(8 * b), order(e));
            _mm256_storeu_ps(odd.as_mut_ptr().add(8 * b), order(o));
        }
    }
    8 * blocks
}

/// The stride-2 form of [`ConvShape::pad_plane`] for a whole plane on AVX-512: each of `rows`
/// rows of `w` values (`w >= 2`) has its even and odd values written to its row slot of the
/// phases (`(yp % 2)·2·hq·wq + (yp / 2)·wq` for padded row `yp = y + pad_top`) at `at[0]` and
/// `at[1]`: 32 values a step (two loads, two permutes), the row's rest under masks.
///
/// # Safety
/// The CPU has AVX-512F; `src` holds `rows · w` values; every row's `ceil(w / 2)` values from
/// `slot + at[0]` and `floor(w / 2)` from `slot + at[1]` are within `dst`.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
#[allow(clippy::too_many_arguments)]
unsafe fn split_rows_avx512(
    src: *const f32,
    w: usize,
    rows: usize,
    dst: *mut f32,
    at: [usize; 2],
    pad_top: usize,
    hq: usize,
    wq: usize,
) {
    use std::arch::x86_64::*;
    let ie = _mm512_setr_epi32(0, 2, 4, 6, 8, 10, 12, 14, 16, 18, 20, 22, 24, 26, 28, 30);
    let io = _mm512_setr_epi32(1, 3, 5, 7, 9, 11, 13, 15, 17, 19, 21, 23, 25, 27, 29, 31);
    let (blocks, rest) = (w / 32, w % 32);
    // The rest: up to 31 values in two masked loads, ceil(rest / 2) evens, floor(rest / 2) odds.
    let load_lo = ((1u64 << rest.min(16)) - 1) as __mmask16;
    let load_hi = ((1u64 << rest.saturating_sub(16)) - 1) as __mmask16;
    let (keep_e, keep_o) = (((1u32 << rest.div_ceil(2)) - 1) as __mmask16, ((1u32 << (rest / 2)) - 1) as __mmask16);
    for y in 0..rows {
        let slot = phase_slot(y + pad_top, hq, wq);
        // SAFETY: row y's values are within `src`, its runs within `dst` (the caller's
        // promise); masked lanes are neither read nor written.
        unsafe {
            let (row, even, odd) = (src.add(y * w), dst.add(slot + at[0]), dst.add(slot + at[1]));
            for b in 0..blocks {
                let lo = _mm512_loadu_ps(row.add(32 * b));
                let hi = _mm512_loadu_ps(row.add(32 * b + 16));
                _mm512_storeu_ps(even.add(16 * b), _mm512_permutex2var_ps(lo, ie, hi));
                _mm512_storeu_ps(odd.add(16 * b), _mm512_permutex2var_ps(lo, io, hi));
            }
            if rest > 0 {
                let lo = _mm512_maskz_loadu_ps(load_lo, row.add(32 * blocks));
                let hi = _mm512_maskz_loadu_ps(load_hi, row.add(32 * blocks + 16));
                _mm512_mask_storeu_ps(even.add(16 * blocks), keep_e, _mm512_permutex2var_ps(lo, ie, hi));
                _mm512_mask_storeu_ps(odd.add(16 * blocks), keep_o, _mm512_permutex2var_ps(lo, io, hi));
            }
        }
    }
}

/// [`copy_rows_avx512`] on AVX2: 8 values a step, a row's last `w % 8` by one more step ending at
/// its last value where the row has 8 (it rewrites values the step before wrote, with the same
/// ones), else one by one. A channel's padding by `copy_row` took a fifth to two fifths of
/// NanoTrack's depthwise layers on an AVX2-only Zen 3.
///
/// # Safety
/// The CPU has AVX2; `src` holds `rows · w` values, and `dst + y·ld .. + w` is writable for
/// every row `y`.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn copy_rows_avx2(src: *const f32, w: usize, rows: usize, dst: *mut f32, ld: usize) {
    use std::arch::x86_64::*;
    let full = w / 8;
    for y in 0..rows {
        // SAFETY: within row y of `src` and its slot in `dst` (the caller's promise).
        unsafe {
            let (s, d) = (src.add(y * w), dst.add(y * ld));
            for k in 0..full {
                _mm256_storeu_ps(d.add(8 * k), _mm256_loadu_ps(s.add(8 * k)));
            }
            if w.is_multiple_of(8) {
                continue;
            }
            if full > 0 {
                _mm256_storeu_ps(d.add(w - 8), _mm256_loadu_ps(s.add(w - 8)));
            } else {
                std::ptr::copy_nonoverlapping(s, d, w);
            }
        }
    }
}

/// [`split_rows_avx512`] on AVX2: each row by [`deinterleave_avx2`], 16 values a step, and
/// [`deinterleave_rest`] (same contract; the row's two runs are disjoint, as `w >= 2` makes
/// them). Per row through `deinterleave`, a length check, an ISA check and slicing took more
/// than the copy on NanoTrack's small planes.
///
/// # Safety
/// As [`split_rows_avx512`], the CPU having AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
#[allow(clippy::too_many_arguments)]
unsafe fn split_rows_avx2(
    src: *const f32,
    w: usize,
    rows: usize,
    dst: *mut f32,
    at: [usize; 2],
    pad_top: usize,
    hq: usize,
    wq: usize,
) {
    for y in 0..rows {
        let slot = phase_slot(y + pad_top, hq, wq);
        // SAFETY: row y's `w` values are within `src`, its runs (`ceil(w / 2)` and
        // `floor(w / 2)` values) within `dst` and apart (the caller's promise).
        unsafe {
            let row = std::slice::from_raw_parts(src.add(y * w), w);
            let even = std::slice::from_raw_parts_mut(dst.add(slot + at[0]), w.div_ceil(2));
            let odd = std::slice::from_raw_parts_mut(dst.add(slot + at[1]), w / 2);
            let done = deinterleave_avx2(row, even, odd);
            deinterleave_rest(row, even, odd, done);
        }
    }
}

/// Shape of one convolution: input `[N, ci, h, w]`, padding, kernel `kh` x `kw`, `co` outputs.
#[derive(Debug, Clone, PartialEq, Eq, Hash)]
pub struct ConvShape {
    /// Input channels, rows, columns.
    pub ci: usize,
    pub h: usize,
    pub w: usize,
    /// Output channels.
    pub co: usize,
    /// Kernel rows and columns.
    pub kh: usize,
    pub kw: usize,
    /// Zero padding: top, left, bottom, right.
    pub pad: [usize; 4],
    /// Stride, the same along rows and columns.
    pub stride: usize,
}

impl ConvShape {
    /// Rows and columns of the zero-padded input.
    pub(crate) fn padded(&self) -> (usize, usize) {
        (self.h + self.pad[0] + self.pad[2], self.w + self.pad[1] + self.pad[3])
    }

    /// Output rows and columns.
    pub(crate) fn out(&self) -> (usize, usize) {
        let (hp, wp) = self.padded();
        ((hp - self.kh) / self.stride + 1, (wp - self.kw) / self.stride + 1)
    }

    /// Rows and columns of one phase of the padded input: with stride `s`, each plane is
    /// stored as `s²` phases (rows `≡ a`, columns `≡ b` mod `s`), so that every tap reads
    /// consecutive positions of one phase. With stride 1, the padded plane itself.
    pub(crate) fn phase(&self) -> (usize, usize) {
        let (hp, wp) = self.padded();
        (hp.div_ceil(self.stride), wp.div_ceil(self.stride))
    }

    /// Offset of every tap `(plane, i, j)` in a padded input of `planes` planes (channels, or
    /// groups of four channels) stored as phases ([`Self::phase`]), in packing order.
    pub(crate) fn tap_offsets(&self, planes: usize) -> Vec<usize> {
        let (hq, wq) = self.phase();
        let (kh, kw, s) = (self.kh, self.kw, self.stride);
        let at = move |c: usize, i: usize, j: usize| ((((c * s + i % s) * s + j % s) * hq) + i / s) * wq + j / s;
        (0..planes).flat_map(|c| (0..kh).flat_map(move |i| (0..kw).map(move |j| at(c, i, j)))).collect()
    }
}

impl ConvShape {
    /// The batch size of an input of `shape` (`[n, ci, h, w]`) to `op`, or an error naming
    /// `op` where it is not this convolution's.
    pub(crate) fn batch_of(&self, op: &str, shape: &[usize]) -> TractResult<usize> {
        let &[n, ci, h, w] = shape else { bail!("{op}: input {shape:?} is not rank 4") };
        ensure!((ci, h, w) == (self.ci, self.h, self.w), "{op}: input {shape:?} for {self:?}");
        Ok(n)
    }

    /// The output fact `[n, co, oh, ow]` for a batch of `n`.
    pub(crate) fn output_fact(&self, n: &TDim) -> TypedFact {
        let (oh, ow) = self.out();
        f32::fact([n.clone(), self.co.into(), oh.into(), ow.into()])
    }
}

impl ConvShape {
    /// Write one input plane `src` (`[h, w]`) into its zero-padded form `dst` (`stride²` phases
    /// of `[hq, wq]`, [`Self::phase`]); `dst`'s padding is left as it is (zero).
    pub(crate) fn pad_plane(&self, src: &[f32], dst: &mut [f32]) {
        let (hq, wq) = self.phase();
        let w = self.w;
        #[cfg(target_arch = "x86_64")]
        let kernel = crate::isa::f32_kernel();
        #[cfg(target_arch = "x86_64")]
        let (avx512, avx2) = (kernel == crate::isa::F32Kernel::Avx512, kernel == crate::isa::F32Kernel::Avx2Fma);
        if self.stride == 1 {
            #[cfg(target_arch = "x86_64")]
            if (avx512 || avx2) && w > 0 {
                let at = self.pad[0] * wq + self.pad[1];
                let rows = src.len() / w;
                assert!(rows == 0 || at + (rows - 1) * wq + w <= dst.len(), "rows within the padded plane");
                // SAFETY: the CPU has AVX-512F, or AVX2 (the ISA table's kernel); every row's
                // `w` values are within `src` (`rows · w <= src.len()`) and its slot within
                // `dst` (asserted above).
                unsafe {
                    let (src, dst) = (src.as_ptr(), dst.as_mut_ptr().add(at));
                    if avx512 {
                        copy_rows_avx512(src, w, rows, dst, wq)
                    } else {
                        copy_rows_avx2(src, w, rows, dst, wq)
                    }
                };
                return;
            }
            for (y, row) in src.chunks_exact(w).enumerate() {
                let at = (y + self.pad[0]) * wq + self.pad[1];
                copy_row(row, &mut dst[at..at + w]);
            }
            return;
        }
        // Stride 2: a row's even and odd columns go to two phases (disjoint runs), at these
        // offsets within the row's slot (see `phase_runs`).
        let p = self.pad[1];
        let (even_at, odd_at) = ((p & 1) * hq * wq + (p >> 1), ((p + 1) & 1) * hq * wq + ((p + 1) >> 1));
        let (ne, no) = (w.div_ceil(2), w / 2);
        #[cfg(target_arch = "x86_64")]
        if (avx512 || avx2) && no > 0 {
            let rows = src.len() / w;
            // Every row's two runs within `dst` (the last two rows reach furthest: one of each
            // row parity).
            let reach = (rows.saturating_sub(2)..rows).map(|y| phase_slot(y + self.pad[0], hq, wq)).max().unwrap_or(0);
            assert!(rows == 0 || reach + even_at.max(odd_at) + ne <= dst.len(), "rows within the padded plane");
            // SAFETY: the CPU has AVX-512F, or AVX2; `rows · w <= src.len()`, and every row's
            // runs are within `dst` (asserted above: the slots grow with the row within each
            // parity).
            unsafe {
                let (src, dst, at) = (src.as_ptr(), dst.as_mut_ptr(), [even_at, odd_at]);
                if avx512 {
                    split_rows_avx512(src, w, rows, dst, at, self.pad[0], hq, wq)
                } else {
                    split_rows_avx2(src, w, rows, dst, at, self.pad[0], hq, wq)
                }
            };
            return;
        }
        for (y, row) in src.chunks_exact(w).enumerate() {
            let yp = y + self.pad[0];
            let slot = phase_slot(yp, hq, wq);
            let (e, o) = (slot + even_at, slot + odd_at);
            match dst.get_disjoint_mut([e..e + ne, o..o + no]) {
                Ok([even, odd]) => deinterleave(row, even, odd),
                // Runs of two phases do not overlap (a one-column row's odd run is empty);
                // were they to, one run after the other.
                Err(_) => {
                    for (first, at) in self.phase_runs(yp) {
                        let dst = &mut dst[at..at + (row.len() - first).div_ceil(2)];
                        dst.iter_mut().zip(row[first..].iter().step_by(2)).for_each(|(d, &v)| *d = v);
                    }
                }
            }
        }
    }

    /// Where input row `yp` (a padded row index) goes in a plane padded for stride 2 (four
    /// phases, `[row parity][column parity][hq][wq]`): for each column parity, the first of the
    /// row's values with that padded parity, `first` (0 or 1), and the phase index `at` of its
    /// slot. Values `first, first + 2, ...` go to `at, at + 1, ...`; a parity the row has no
    /// value of (a one-column row) is left out.
    pub(crate) fn phase_runs(&self, yp: usize) -> impl Iterator<Item = (usize, usize)> {
        let (hq, wq) = self.phase();
        let row_of = move |parity: usize| phase_slot(yp, hq, wq) + parity * hq * wq;
        let p = self.pad[1];
        let w = self.w;
        [(0, p & 1, p >> 1), (1, (p + 1) & 1, (p + 1) >> 1)]
            .into_iter()
            .filter(move |&(first, _, _)| first < w)
            .map(move |(first, parity, col)| (first, row_of(parity) + col))
    }
}

/// `out[n,o,y,x] = bias[o] + Σ_{c,i,j} pad(input)[n,c,y+i,x+j]·weight[o,c,i,j]`, stride 1, with
/// the weights packed `[o / 8][(c,i,j)][o % 8]` when the op is made (taps `(c,i,j)` whose
/// weights are all zero left out), or, on AVX-512 for 32 channels or more, packed for tiles
/// with the channels in the vector lanes ([`super::conv_lanes`]).
#[derive(Clone)]
pub struct PackedConv {
    shape: ConvShape,
    layout: Arc<Layout>,
    weights: Arc<Vec<f32>>,
    lanes: Option<Arc<LanePack>>,
    bias: Arc<Vec<f32>>,
    /// Applied to the output as it is written (the graph's activation after the convolution).
    act: Activation,
    /// The padded input's positions the channels' padding does not write
    /// ([`super::with_padded`]).
    borders: Arc<Vec<(usize, usize)>>,
    /// The output's shape where the fused nodes end in another shape than `[n, co, oh, ow]`.
    reshape: Option<TVec<usize>>,
}

impl std::fmt::Debug for PackedConv {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "PackedConv({:?})", self.shape)
    }
}

impl PartialEq for PackedConv {
    fn eq(&self, other: &Self) -> bool {
        fn lanes(c: &PackedConv) -> &[f32] {
            c.lanes.as_ref().map(|l| l.values()).unwrap_or_default()
        }
        self.shape == other.shape
            && same_bits(&self.weights, &other.weights)
            && same_bits(lanes(self), lanes(other))
            && same_bits(&self.bias, &other.bias)
            && self.act == other.act
            && self.reshape == other.reshape
    }
}

impl Eq for PackedConv {}

impl PackedConv {
    /// Pack OIHW `weight` ([co, ci, kh, kw], row-major) and `bias` (one value or `co`).
    pub fn new(shape: ConvShape, weight: &[f32], bias: &[f32]) -> TractResult<PackedConv> {
        let taps = shape.ci * shape.kh * shape.kw;
        ensure!(weight.len() == shape.co * taps, "PackedConv: {} weights for {shape:?}", weight.len());
        ensure!(bias.len() == 1 || bias.len() == shape.co, "PackedConv: {} bias values for {shape:?}", bias.len());
        // Taps whose weight is zero for every output (the padding of a space-to-depth kernel)
        // are left out: with finite inputs they add exact zeros.
        let mut nonzero = vec![false; taps];
        for w in weight.chunks_exact(taps) {
            nonzero.iter_mut().zip(w).for_each(|(n, &v)| *n |= v != 0.0);
        }
        let live: Vec<usize> = (0..taps).filter(|&t| nonzero[t]).collect();
        let blocks = shape.co.div_ceil(ROWS);
        let lanes = LanePack::new(weight, taps, &live, &shape).map(Arc::new);
        // Written in order, block by block: the block's rows are read as 8 streams (not at all
        // where the lanes' packing serves).
        let mut packed = Vec::new();
        if lanes.is_none() {
            packed.reserve(blocks * live.len() * ROWS);
            for rows in weight.chunks(ROWS * taps) {
                for &t in &live {
                    packed.extend((0..ROWS).map(|r| rows.get(r * taps + t).copied().unwrap_or(0.0)));
                }
            }
        }
        let bias: Vec<f32> =
            (0..blocks * ROWS).map(|o| if bias.len() == 1 { bias[0] } else { *bias.get(o).unwrap_or(&0.0) }).collect();
        let (_, wq) = shape.phase();
        let (oh, ow) = shape.out();
        let offsets = shape.tap_offsets(shape.ci);
        let layout = Layout { taps: live.iter().map(|&t| offsets[t]).collect(), wp: wq, oh, ow };
        let (weights, bias) = (Arc::new(packed), Arc::new(bias));
        let plane_in = shape.stride * shape.stride * shape.phase().0 * wq;
        let zeros = vec![0.0; shape.h * shape.w];
        let borders = Arc::new(super::unwritten_runs(Self::padded_len(&shape), |buf| {
            for plane in buf.chunks_exact_mut(plane_in).take(shape.ci) {
                shape.pad_plane(&zeros, plane);
            }
        }));
        let layout = Arc::new(layout);
        Ok(PackedConv { shape, layout, weights, lanes, bias, act: Activation::NONE, borders, reshape: None })
    }

    /// The length of the padded input: every channel's plane (its phases with stride 2), with
    /// room past the end for a tile of positions and a row.
    fn padded_len(s: &ConvShape) -> usize {
        let (hq, wq) = s.phase();
        s.ci * s.stride * s.stride * hq * wq + MAX_PX + wq
    }

    /// The convolution followed by the nodes of `tail` ([`super::act::tail`]).
    pub(crate) fn fused(self, tail: &Tail) -> TractResult<PackedConv> {
        ensure!(tail.bias.is_none(), "PackedConv: a convolution has its own bias");
        Ok(PackedConv { act: tail.act, reshape: tail.reshaped(), ..self })
    }

    /// The convolution's shape.
    pub fn shape(&self) -> &ConvShape {
        &self.shape
    }
}

impl Op for PackedConv {
    fn name(&self) -> StaticName {
        "PackedConv".into()
    }

    fn info(&self) -> TractResult<Vec<String>> {
        let s = &self.shape;
        let (kh, kw, ci, co, taps) = (s.kh, s.kw, s.ci, s.co, self.layout.taps.len());
        let tile = match &self.lanes {
            Some(l) if l.compact() => {
                format!("compact tiles of {} channels by {} output positions", l.channels(), l.positions())
            }
            Some(l) => format!("tiles of {} channels in lanes", l.channels()),
            None => format!("tiles of {ROWS} channels"),
        };
        Ok(vec![format!(
            "{kh}x{kw} kernel, stride {}, {ci} -> {co} channels, pad {:?}, {taps} taps, {tile}, activation {}",
            s.stride,
            s.pad,
            self.act.describe()
        )])
    }

    op_as_typed_op!();
}

impl EvalOp for PackedConv {
    op_out_of_plan!();

    fn eval(&self, _ctx: &EvalContext, inputs: TVec<TValue>) -> TractResult<TVec<TValue>> {
        let input = args_1!(inputs);
        let s = &self.shape;
        let (n, ci, h, w) = (s.batch_of("PackedConv", input.shape())?, s.ci, s.h, s.w);
        let input = input.try_as_plain_ram()?;
        let input = input.as_slice::<f32>()?;
        let (oh, ow) = s.out();
        let (hq, wq) = s.phase();
        let plane = oh * ow;
        let taps = self.layout.taps.len();
        let phases = s.stride * s.stride;
        let fill = |out: &mut [f32]| {
            super::with_padded(Self::padded_len(s), &self.borders, |padded| {
                for (src, dst) in input.chunks_exact(ci * h * w).zip(out.chunks_exact_mut(s.co * plane)) {
                    // The channels padded over the threads (one after another the other threads
                    // waited: 1.8 MB of input for the search graph's second layer).
                    let plane_in = phases * hq * wq;
                    par_chunks(&mut padded[..ci * plane_in], plane_in, |c, dst| {
                        s.pad_plane(&src[c * h * w..(c + 1) * h * w], dst)
                    });
                    match &self.lanes {
                        Some(lanes) if lanes.compact() => {
                            lanes.run_compact(&self.layout, padded, &self.bias, self.act, dst);
                            continue;
                        }
                        Some(lanes) => {
                            lanes.run(&self.layout, padded, &self.bias, self.act, dst);
                            continue;
                        }
                        None => {}
                    }
                    par_chunks(dst, ROWS * plane, |b, out| {
                        let weights = &self.weights[b * taps * ROWS..(b + 1) * taps * ROWS];
                        let bias: &[f32; ROWS] = self.bias[b * ROWS..(b + 1) * ROWS].try_into().expect("ROWS values");
                        channel_block(&self.layout, padded, weights, bias, self.act, out);
                    });
                }
                Ok(())
            })
        };
        let macs = [n, s.co, plane, ci, s.kh, s.kw].iter().fold(1usize, |a, &b| a.saturating_mul(b));
        // SAFETY: every output is written: the tiles cover every position of every row, each
        // channel block (or lanes' block) writes all its channels.
        let out = serial_if_small(macs, || unsafe { output_tensor_written(&[n, s.co, oh, ow], fill) })?;
        Ok(tvec!(reshape_output(out, self.reshape.as_ref())?.into_tvalue()))
    }
}

impl TypedOp for PackedConv {
    fn output_facts(&self, inputs: &[&TypedFact]) -> TractResult<TVec<TypedFact>> {
        Ok(tvec!(output_fact(self.reshape.as_ref(), || self.shape.output_fact(&inputs[0].shape[0]))))
    }

    fn cost(&self, inputs: &[&TypedFact]) -> TractResult<TVec<(Cost, TDim)>> {
        let (oh, ow) = self.shape.out();
        let s = &self.shape;
        let macs = s.co * oh * ow * self.layout.taps.len();
        Ok(tvec!((Cost::FMA(f32::datum_type()), inputs[0].shape[0].clone() * macs)))
    }

    as_op!();
}

/// A float 2-D convolution with constant OIHW weights and bias, explicit padding, dilation 1
/// and stride 1 or 2: what the runtime's convolutions take over from tract.
pub(crate) struct ConstConv<'a> {
    /// tract's operator (groups, channels, data format).
    pub conv: &'a Conv,
    /// The data input's shape.
    pub input: &'a [usize],
    /// Zero padding: top, left, bottom, right.
    pub pad: [usize; 4],
    /// Stride, the same along rows and columns.
    pub stride: usize,
    /// Kernel rows and columns.
    pub kernel: (usize, usize),
    /// The weights and bias, row-major.
    pub weight: &'a [f32],
    pub bias: &'a [f32],
}

/// `node` of `model` as a [`ConstConv`], if it is one.
pub(crate) fn const_conv<'a>(model: &'a TypedModel, node: &'a TypedNode) -> TractResult<Option<ConstConv<'a>>> {
    let Some(conv) = node.op_as::<Conv>() else { return Ok(None) };
    let facts = model.node_input_facts(node.id)?;
    let ps = &conv.pool_spec;
    let Some(pad) = pads_2d(&ps.padding) else { return Ok(None) };
    let plain = conv.q_params.is_none()
        && conv.kernel_fmt == KernelFormat::OIHW
        && ps.kernel_shape.len() == 2
        && all_ones(&ps.dilations)
        && facts.len() == 3
        && facts.iter().all(|f| f.datum_type == f32::datum_type());
    if !plain {
        return Ok(None);
    }
    let stride = match ps.strides.as_deref() {
        None | Some([1, 1]) => 1,
        Some([2, 2]) => 2,
        _ => return Ok(None),
    };
    let (Some(weight), Some(bias)) = (&facts[1].konst, &facts[2].konst) else { return Ok(None) };
    let Some(input) = facts[0].shape.as_concrete() else { return Ok(None) };
    let (weight, bias) = (weight.try_as_plain_ram()?, bias.try_as_plain_ram()?);
    let kernel = (ps.kernel_shape[0], ps.kernel_shape[1]);
    let (weight, bias) = (weight.as_slice::<f32>()?, bias.as_slice::<f32>()?);
    Ok(Some(ConstConv { conv, input, pad, stride, kernel, weight, bias }))
}

/// A convolution's shape, OIHW weights and bias.
pub(crate) type PlainConv<'a> = (ConvShape, &'a [f32], &'a [f32]);

/// The shape, OIHW weights and bias of `node` of `model` if it is a [`ConstConv`] with one
/// group, NCHW, and a kernel larger than 1x1: what [`PackedConv`] and
/// [`super::winograd::WinogradConv`] take.
pub(crate) fn plain_conv<'a>(model: &'a TypedModel, node: &'a TypedNode) -> TractResult<Option<PlainConv<'a>>> {
    let Some(c) = const_conv(model, node)? else { return Ok(None) };
    let ps = &c.conv.pool_spec;
    let (kh, kw) = c.kernel;
    let (&[_, ci, h, w], 1, DataFormat::NCHW) = (c.input, c.conv.group, ps.data_format) else { return Ok(None) };
    if kh * kw == 1 {
        return Ok(None);
    }
    let shape = ConvShape { ci, h, w, co: ps.output_channels, kh, kw, pad: c.pad, stride: c.stride };
    Ok(Some((shape, c.weight, c.bias)))
}

/// The [`PackedConv`] for `node` of `model` if it is a [`plain_conv`].
pub(crate) fn packed(model: &TypedModel, node: &TypedNode) -> TractResult<Option<PackedConv>> {
    let Some((shape, weight, bias)) = plain_conv(model, node)? else { return Ok(None) };
    Ok(Some(PackedConv::new(shape, weight, bias)?))
}

/// A direct f64 sum of a convolution of `groups` groups (OIHW weights, `[co, ci / groups, kh,
/// kw]`): the reference the kernels are tested against.
#[cfg(test)]
pub(crate) fn direct(s: &ConvShape, groups: usize, input: &[f32], weight: &[f32], bias: &[f32]) -> Vec<f32> {
    let (oh, ow) = s.out();
    let (cig, cog) = (s.ci / groups, s.co / groups);
    let at = |c: usize, y: usize, x: usize| -> f64 {
        let (y, x) = (y as isize - s.pad[0] as isize, x as isize - s.pad[1] as isize);
        if y < 0 || x < 0 || y >= s.h as isize || x >= s.w as isize {
            0.0
        } else {
            input[(c * s.h + y as usize) * s.w + x as usize] as f64
        }
    };
    let mut out = vec![];
    for o in 0..s.co {
        for y in 0..oh {
            for x in 0..ow {
                let mut acc = bias[o] as f64;
                for c in 0..cig {
                    for i in 0..s.kh {
                        for j in 0..s.kw {
                            acc += at((o / cog) * cig + c, y * s.stride + i, x * s.stride + j)
                                * weight[((o * cig + c) * s.kh + i) * s.kw + j] as f64;
                        }
                    }
                }
                out.push(acc as f32);
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn deinterleaves_rows_of_every_length() {
        // Whole blocks of 32 (AVX-512 where the CPU has it), the pairs after them, an odd end.
        for len in 0..100usize {
            let row: Vec<f32> = (0..len).map(|i| i as f32).collect();
            let (mut even, mut odd) = (vec![-1.0; len.div_ceil(2)], vec![-1.0; len / 2]);
            deinterleave(&row, &mut even, &mut odd);
            assert!(even.iter().enumerate().all(|(i, &v)| v == (2 * i) as f32), "even, {len}");
            assert!(odd.iter().enumerate().all(|(i, &v)| v == (2 * i + 1) as f32), "odd, {len}");
        }
    }

    #[test]
    fn pads_a_plane_for_stride_1() {
        // Every row length from 1 to 99 (whole steps of 16 or 8, and the rests: masked on
        // AVX-512, a step ending at the row's end or value by value on AVX2); the padding
        // stays untouched.
        for w in 1..100usize {
            for (h, pad) in [(5, [1, 1, 1, 1]), (3, [0, 2, 1, 0]), (4, [2, 0, 0, 3])] {
                let s = ConvShape { ci: 1, h, w, co: 1, kh: 3, kw: 3, pad, stride: 1 };
                let (hq, wq) = s.phase();
                let src: Vec<f32> = (0..h * w).map(|i| i as f32).collect();
                let mut got = vec![-1.0f32; hq * wq + 8];
                s.pad_plane(&src, &mut got);
                let mut want = vec![-1.0f32; got.len()];
                for y in 0..h {
                    for x in 0..w {
                        want[(y + pad[0]) * wq + x + pad[1]] = src[y * w + x];
                    }
                }
                assert_eq!(got, want, "w {w}, h {h}, pad {pad:?}");
            }
        }
    }

    #[test]
    fn pads_a_plane_for_stride_2_as_its_phases() {
        // Every row length from 1 to 99 (whole blocks of 32 on AVX-512 and masked rests), both
        // column paddings' parities, odd and even row counts; the padding stays untouched.
        for w in 1..100usize {
            for (h, pad) in [(5, [1, 1, 1, 1]), (4, [2, 2, 2, 2]), (3, [0, 1, 2, 0]), (6, [1, 0, 0, 3])] {
                let s = ConvShape { ci: 1, h, w, co: 1, kh: 3, kw: 3, pad, stride: 2 };
                let (hq, wq) = s.phase();
                let src: Vec<f32> = (0..h * w).map(|i| i as f32).collect();
                let mut got = vec![-1.0f32; 4 * hq * wq + 8];
                s.pad_plane(&src, &mut got);
                // Padded (yp, xp) goes to phase (yp % 2, xp % 2), at (yp / 2, xp / 2).
                let mut want = vec![-1.0f32; got.len()];
                for y in 0..h {
                    for x in 0..w {
                        let (yp, xp) = (y + pad[0], x + pad[1]);
                        want[((yp % 2) * 2 + xp % 2) * hq * wq + (yp / 2) * wq + xp / 2] = src[y * w + x];
                    }
                }
                assert_eq!(got, want, "w {w}, h {h}, pad {pad:?}");
            }
        }
    }

    #[test]
    fn equals_the_direct_sum_with_padding_and_a_partial_channel_block() {
        // 11 output channels: one whole block of 8 and a partial one; 3 taps chunks of 128 for
        // the 300-tap layer; outputs of 1 to 2 tiles.
        // The last: every third tap's weights are zero for all outputs (left out when packed).
        for (s, zero_taps, wide_on_avx512) in [
            (ConvShape { ci: 3, h: 9, w: 7, co: 11, kh: 3, kw: 3, pad: [1, 1, 1, 1], stride: 1 }, false, false),
            (ConvShape { ci: 12, h: 14, w: 14, co: 8, kh: 5, kw: 5, pad: [0; 4], stride: 1 }, false, false),
            (ConvShape { ci: 5, h: 6, w: 40, co: 3, kh: 2, kw: 4, pad: [0, 2, 1, 0], stride: 1 }, false, false),
            (ConvShape { ci: 4, h: 12, w: 12, co: 9, kh: 6, kw: 6, pad: [0; 4], stride: 1 }, true, false),
            // Stride 2 (the regulators' 3x3 convolutions: odd and even sizes, one-sided padding).
            (ConvShape { ci: 6, h: 21, w: 21, co: 10, kh: 3, kw: 3, pad: [1, 1, 1, 1], stride: 2 }, false, false),
            (ConvShape { ci: 3, h: 10, w: 13, co: 9, kh: 4, kw: 3, pad: [0, 1, 2, 0], stride: 2 }, false, false),
            // One column, no odd run; one column padded on the left, no even one.
            (ConvShape { ci: 2, h: 7, w: 1, co: 3, kh: 3, kw: 1, pad: [1, 0, 1, 0], stride: 2 }, false, false),
            (ConvShape { ci: 2, h: 7, w: 1, co: 3, kh: 3, kw: 2, pad: [1, 1, 1, 0], stride: 2 }, false, false),
            // 32 channels or more: on AVX-512 the channels-in-lanes tiles, on these small maps
            // the compact ones (32 x 10 with a partial block; 48 x 8, stride 2; zero taps left
            // out).
            (ConvShape { ci: 7, h: 15, w: 17, co: 40, kh: 3, kw: 3, pad: [1, 1, 1, 1], stride: 1 }, false, false),
            (ConvShape { ci: 3, h: 23, w: 21, co: 96, kh: 5, kw: 5, pad: [0, 1, 0, 1], stride: 2 }, false, false),
            (ConvShape { ci: 9, h: 8, w: 8, co: 48, kh: 3, kw: 3, pad: [0; 4], stride: 1 }, true, false),
            // A map wide enough that the wide tiles (3 and 2 registers) compute fewer values
            // than the compact ones on AVX-512 (2 of 62 columns dropped a row).
            (ConvShape { ci: 3, h: 22, w: 62, co: 48, kh: 3, kw: 3, pad: [0; 4], stride: 1 }, false, true),
            (ConvShape { ci: 3, h: 22, w: 62, co: 40, kh: 3, kw: 3, pad: [0; 4], stride: 1 }, false, true),
            // Small maps of 16 input channels or more: on AVX2 the compact tiles (a partial
            // block of 16 channels; stride 2; a map smaller than a tile).
            (ConvShape { ci: 16, h: 8, w: 8, co: 24, kh: 3, kw: 3, pad: [1, 1, 1, 1], stride: 1 }, false, false),
            (ConvShape { ci: 20, h: 11, w: 9, co: 32, kh: 3, kw: 3, pad: [1, 1, 1, 1], stride: 2 }, false, false),
            (ConvShape { ci: 16, h: 4, w: 4, co: 16, kh: 3, kw: 3, pad: [0; 4], stride: 1 }, true, false),
            // And on AVX-512 those of 32 channels by 10 positions (a partial block) and of 48
            // by 8 (zero taps left out).
            (ConvShape { ci: 24, h: 9, w: 9, co: 40, kh: 3, kw: 3, pad: [1, 1, 1, 1], stride: 1 }, false, false),
            (ConvShape { ci: 16, h: 7, w: 7, co: 48, kh: 3, kw: 3, pad: [0; 4], stride: 1 }, true, false),
        ] {
            let n_in = s.ci * s.h * s.w;
            let taps = s.ci * s.kh * s.kw;
            let input: Vec<f32> = (0..2 * n_in).map(|i| ((i * 7919 % 1000) as f32) / 500.0 - 1.0).collect();
            let weight: Vec<f32> = (0..s.co * taps)
                .map(|i| if zero_taps && i % taps % 3 == 0 { 0.0 } else { ((i * 104729 % 997) as f32) / 498.0 - 1.0 })
                .collect();
            let bias: Vec<f32> = (0..s.co).map(|o| o as f32 / 4.0).collect();
            let op = PackedConv::new(s.clone(), &weight, &bias).unwrap();
            assert_eq!(op.layout.taps.len(), if zero_taps { taps - taps.div_ceil(3) } else { taps });
            let compact = op.lanes.as_ref().is_some_and(|l| l.compact());
            match crate::isa::f32_kernel() {
                crate::isa::F32Kernel::Avx2Fma => assert_eq!(compact, s.ci >= 16, "{s:?}: compact tiles {compact}"),
                crate::isa::F32Kernel::Avx512 => {
                    assert_eq!(compact, s.co >= 32 && !wide_on_avx512, "{s:?}: compact tiles {compact}")
                }
                _ => assert!(!compact, "{s:?}: compact tiles without AVX2"),
            }
            let x = tract_ndarray::Array4::from_shape_vec((2, s.ci, s.h, s.w), input.clone()).unwrap();
            let out = op.eval(&EvalContext::out_of_plan(), tvec![x.into_tensor().into_tvalue()]).unwrap();
            let out = out[0].try_as_plain_ram().unwrap();
            let out = out.as_slice::<f32>().unwrap();
            let per_image = out.len() / 2;
            for (n, got) in out.chunks_exact(per_image).enumerate() {
                let want = direct(&s, 1, &input[n * n_in..(n + 1) * n_in], &weight, &bias);
                let worst = got.iter().zip(&want).map(|(a, b)| (a - b).abs()).fold(0.0f32, f32::max);
                assert!(worst < 1e-4, "{s:?} image {n}: off by {worst}");
            }
        }
    }
}
