//! The operators' memory: output tensors written in place, and each thread's buffers kept from
//! call to call (padded inputs, tiles' sums, bytes), so that a frame allocates and zeroes none.

use tract_nnef::internal::*;

/// A zero-filled tensor of `shape` that `fill` writes an operator's output into. (tract's
/// conversions from a `Vec` or an ndarray copy the data into a tensor of their own: one more
/// pass over every output.)
pub(super) fn output_tensor<T: Datum>(
    shape: &[usize],
    fill: impl FnOnce(&mut [T]) -> TractResult<()>,
) -> TractResult<Tensor> {
    let mut t = Tensor::zero_dt(T::datum_type(), shape)?;
    {
        let mut plain = t.try_as_plain_ram_mut()?;
        fill(plain.as_slice_mut::<T>()?)?;
    }
    Ok(t)
}

/// As [`output_tensor`] for f32 or u8, without zeroing the tensor first (a pass over the
/// whole output on one thread, and page faults on large ones, that a kernel writing every
/// element does not need). In debug builds (the tests) every byte is 0xFF first, so that a
/// value left unwritten reads as NaN (f32) or 255 (u8), not as a zero that fresh memory
/// happens to hold.
///
/// # Safety
/// `fill` writes every element of the slice it is given before the tensor is read.
pub(super) unsafe fn output_tensor_written<T: Datum + Copy>(
    shape: &[usize],
    fill: impl FnOnce(&mut [T]) -> TractResult<()>,
) -> TractResult<Tensor> {
    debug_assert!([f32::datum_type(), u8::datum_type()].contains(&T::datum_type()));
    // SAFETY: every bit pattern is an f32 or a u8 (asserted), and the caller's `fill` writes
    // every element.
    let mut t = unsafe { Tensor::uninitialized_dt(T::datum_type(), shape)? };
    {
        let mut plain = t.try_as_plain_ram_mut()?;
        let values = plain.as_slice_mut::<T>()?;
        #[cfg(debug_assertions)]
        // SAFETY: the slice's own bytes; all-ones bytes are a valid f32 (NaN) and u8 (255).
        unsafe {
            std::ptr::write_bytes(values.as_mut_ptr(), 0xFF, values.len())
        };
        fill(values)?;
    }
    Ok(t)
}

/// A value of four bytes for which every bit pattern is valid (the kernels' sums, the padded
/// inputs).
pub(super) trait Word: Copy {}
impl Word for f32 {}
impl Word for i32 {}

/// A thread's buffer kept from call to call ([`with_padded`], [`with_words`]).
pub(super) type Kept = std::thread::LocalKey<std::cell::RefCell<Vec<u32>>>;

/// Run `f` on `len` values of the calling thread's buffer `kept`, which grows to the largest
/// `len` asked for: the values are whatever its last use left. In use further up this thread's
/// stack (not the case today), a zeroed buffer of its own.
pub(super) fn lend<T: Word, R>(kept: &'static Kept, len: usize, f: impl FnOnce(&mut [T]) -> R) -> R {
    const { assert!(size_of::<T>() == 4 && align_of::<T>() == 4) };
    let words = |v: &mut [u32]| {
        // SAFETY: `T` is four bytes with no invalid bit pattern ([`Word`]: f32, i32), as
        // aligned as u32; the values are initialised u32s, borrowed mutably here alone.
        unsafe { std::slice::from_raw_parts_mut(v.as_mut_ptr().cast::<T>(), v.len()) }
    };
    kept.with(|b| match b.try_borrow_mut() {
        Ok(mut v) => {
            if v.len() < len {
                v.resize(len, 0);
            }
            f(words(&mut v[..len]))
        }
        Err(_) => f(words(&mut vec![0u32; len])),
    })
}

/// Run `f` on a buffer of `len` values whose positions `borders` lists (runs `(start, len)`)
/// are zero and the others hold whatever the thread's last use left: the scratch of a padded
/// input, whose interior the caller writes whole before reading it. The buffer is the calling
/// thread's own and kept from call to call (it grows to the largest `len` asked for), so a
/// padded plane costs neither an allocation nor the zeroing of its interior (the stem's 0.8 MB
/// and the depthwise layers' planes were zeroed on every frame: 2% of NanoTrack's step).
pub(super) fn with_padded<R>(len: usize, borders: &[(usize, usize)], f: impl FnOnce(&mut [f32]) -> R) -> R {
    thread_local! {
        static PADDED: std::cell::RefCell<Vec<u32>> = const { std::cell::RefCell::new(Vec::new()) };
    }
    lend(&PADDED, len, |buf: &mut [f32]| {
        for &(at, n) in borders {
            buf[at..at + n].fill(0.0);
        }
        f(buf)
    })
}

/// Run `f` on the calling thread's buffer of `len` values of four bytes, kept from call to call
/// (it grows to the largest `len` asked for): the values are whatever its last use left, so
/// `f` writes before it reads. The tiles' sums: an item of PRL-Track's template layer 1 took
/// 0.67 MB of sums, allocated and zeroed for each of its two channel blocks (0.05 of 1.7 ms).
/// A buffer of its own, not [`with_padded`]'s: the sums are made while the padded input is in
/// use.
pub(super) fn with_words<T: Word, R>(len: usize, f: impl FnOnce(&mut [T]) -> R) -> R {
    thread_local! {
        static WORDS: std::cell::RefCell<Vec<u32>> = const { std::cell::RefCell::new(Vec::new()) };
    }
    lend(&WORDS, len, f)
}

/// Run `f` on the calling thread's buffer of `len` bytes, kept from call to call (it grows to
/// the largest `len` asked for): the bytes are whatever its last use left, so `f` writes before
/// it reads. The integer depthwise layers' padded planes (allocated per channel group and
/// frame before).
#[cfg(any(target_arch = "x86_64", target_arch = "aarch64"))]
pub(super) fn with_bytes<R>(len: usize, f: impl FnOnce(&mut [u8]) -> R) -> R {
    thread_local! {
        static BYTES: std::cell::RefCell<Vec<u8>> = const { std::cell::RefCell::new(Vec::new()) };
    }
    BYTES.with(|b| match b.try_borrow_mut() {
        Ok(mut v) => {
            if v.len() < len {
                v.resize(len, 0);
            }
            f(&mut v[..len])
        }
        Err(_) => f(&mut vec![0u8; len]),
    })
}

/// The runs `(start, len)` of a `len`-long buffer that `write` leaves as they were: what
/// [`with_padded`] must zero for a padded input that `write` fills (found once, when an
/// operator is made, by writing into a buffer of NaNs).
pub(super) fn unwritten_runs(len: usize, write: impl FnOnce(&mut [f32])) -> Vec<(usize, usize)> {
    let mut buf = vec![f32::NAN; len];
    write(&mut buf);
    let mut runs: Vec<(usize, usize)> = vec![];
    for (i, v) in buf.iter().enumerate() {
        if !v.is_nan() {
            continue;
        }
        match runs.last_mut() {
            Some((at, n)) if *at + *n == i => *n += 1,
            _ => runs.push((i, 1)),
        }
    }
    runs
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ops::ConvShape;

    #[test]
    fn a_thread_s_padded_buffer_has_zero_borders_whatever_it_held() {
        // A plane padded for a 3x3 stride-2 convolution: what its padding leaves unwritten.
        let s = ConvShape { ci: 1, h: 5, w: 7, co: 1, kh: 3, kw: 3, pad: [1, 1, 1, 1], stride: 2 };
        let (hq, wq) = s.phase();
        let len = 4 * hq * wq + 3;
        let borders = unwritten_runs(len, |b| s.pad_plane(&[0.0; 35], b));
        let unwritten: usize = borders.iter().map(|r| r.1).sum();
        assert_eq!(unwritten, len - 35, "35 values written, the rest padding and slack");
        // Dirty the buffer (a larger one first), then take it back with those borders.
        with_padded(2 * len, &[], |b| b.fill(f32::NAN));
        let src: Vec<f32> = (1..=35).map(|v| v as f32).collect();
        let got = with_padded(len, &borders, |b| {
            s.pad_plane(&src, b);
            b.to_vec()
        });
        let mut want = vec![0.0; len];
        s.pad_plane(&src, &mut want);
        assert_eq!(got, want);
    }
}
