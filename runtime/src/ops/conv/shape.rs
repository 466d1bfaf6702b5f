//! [`ConvShape`]: a convolution's shape, and its input written into the zero-padded form the
//! kernels read (stride 2's four phases: rows copied and de-interleaved, AVX-512 and AVX2 where
//! the CPU has them).

use tract_nnef::internal::*;

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
pub(super) fn deinterleave(row: &[f32], even: &mut [f32], odd: &mut [f32]) {
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
