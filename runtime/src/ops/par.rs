//! The operators' threads: tract's executor's pool, the work each operator hands it
//! ([`par_for`], [`par_chunks`]), when an operator is too small to split, and the pointer the
//! threads share to write disjoint outputs.

/// A pointer that threads writing disjoint elements share.
pub(super) struct SyncPtr<T>(pub(super) *mut T);

// SAFETY: users write disjoint elements only, and the buffer outlives the threads' work.
unsafe impl<T> Send for SyncPtr<T> {}
// SAFETY: as above.
unsafe impl<T> Sync for SyncPtr<T> {}

impl<T> SyncPtr<T> {
    /// The element at `i`.
    ///
    /// # Safety
    /// `i` is within the buffer, and no other thread accesses that element meanwhile.
    pub(super) unsafe fn at(&self, i: usize) -> *mut T {
        // SAFETY: the caller keeps `i` within the buffer.
        unsafe { self.0.add(i) }
    }
}

/// The threads [`par_for`] and [`par_chunks`] run on (tract's executor's).
pub(super) fn threads() -> usize {
    use tract_linalg::multithread::{current_tract_executor, Executor};
    match current_tract_executor() {
        Executor::SingleThread => 1,
        Executor::MultiThread(pool) => pool.current_num_threads(),
        Executor::RayonGlobal => rayon::current_num_threads(),
    }
}

/// Multiply-adds under which an operator runs on the calling thread alone, even where its graph
/// is split over threads: about 50 µs of work, of which handing it to the pool's threads costs a
/// good part (PRL-Track's three head convolutions, 0.8 M each, took 0.045-0.064 ms on one thread
/// and 0.053-0.076 over two).
pub(super) const SERIAL_MACS: usize = 1 << 20;

/// `f` with tract's executor set to the calling thread alone where `macs` is under
/// [`SERIAL_MACS`] (so that the operator's [`par_for`]s and [`par_chunks`] run inline), else `f`.
pub(super) fn serial_if_small<R>(macs: usize, f: impl FnOnce() -> R) -> R {
    use tract_linalg::multithread::{multithread_tract_scope, Executor};
    if macs < SERIAL_MACS {
        multithread_tract_scope(Executor::SingleThread, f)
    } else {
        f()
    }
}

/// Run `f(i)` for every `i < n`, on tract's thread pool when it has one.
pub(super) fn par_for(n: usize, f: impl Fn(usize) + Sync) {
    use rayon::prelude::*;
    use tract_linalg::multithread::{current_tract_executor, Executor};
    match current_tract_executor() {
        Executor::SingleThread => (0..n).for_each(f),
        Executor::MultiThread(pool) => pool.install(|| (0..n).into_par_iter().for_each(&f)),
        Executor::RayonGlobal => (0..n).into_par_iter().for_each(&f),
    }
}

/// Values in one share of an element-wise operator's work handed to the pool's threads
/// ([`par_chunks`]; [`super::QuantizeU8`], [`super::DequantizeU8`],
/// [`super::BroadcastBinary`]'s whole rows): a tensor of fewer stays on the calling thread (a
/// hand-over costs about what 30 000 elements take).
pub(super) const SHARE: usize = 1 << 15;

/// Run `f(i, chunk)` on every `len`-long chunk of `out` (the last may be shorter), on tract's
/// thread pool when it has one.
pub(super) fn par_chunks<T: Send>(out: &mut [T], len: usize, f: impl Fn(usize, &mut [T]) + Sync) {
    use rayon::prelude::*;
    use tract_linalg::multithread::{current_tract_executor, Executor};
    let chunks = out.par_chunks_mut(len).enumerate();
    match current_tract_executor() {
        Executor::SingleThread => out.chunks_mut(len).enumerate().for_each(|(i, c)| f(i, c)),
        Executor::MultiThread(pool) => pool.install(|| chunks.for_each(|(i, c)| f(i, c))),
        Executor::RayonGlobal => chunks.for_each(|(i, c)| f(i, c)),
    }
}
