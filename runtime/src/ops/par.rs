//! The operators' threads: tract's executor's pool, the work each operator hands it
//! ([`par_for`], [`par_chunks`]), how finely blocks of work are cut for it ([`parts`],
//! [`par_runs`]), when an operator is too small to split, and the pointer the threads share to
//! write disjoint outputs.

use std::ops::Range;

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

/// Parts to cut each of `blocks` like blocks of work into (at most `most`) for tract's threads:
/// one on one thread; else at least `min_items` items in all, and more parts where they leave
/// less of the threads' last round idle, until at most a tenth of it is. PRL-Track's layer 1
/// (12 channel blocks) over eight threads (the Orin's) as whole blocks left a quarter of
/// their second round idle; in 24 parts, none.
pub(super) fn parts(blocks: usize, min_items: usize, most: usize) -> usize {
    split(blocks, min_items, most, threads())
}

/// [`parts`] for `threads` threads.
fn split(blocks: usize, min_items: usize, most: usize, threads: usize) -> usize {
    let most = most.max(1);
    if threads <= 1 || blocks == 0 {
        return 1;
    }
    let busy = |p: usize| {
        let items = blocks * p;
        items * 10 >= items.div_ceil(threads) * threads * 9
    };
    let mut p = min_items.div_ceil(blocks).clamp(1, most);
    while p < most && !busy(p) {
        p += 1;
    }
    p
}

/// Run `f(block, run)` for each of `blocks` blocks of `len` units (channels' rows, tiles) cut
/// into `parts` runs of equal length (the last shorter; [`parts`] chooses how many), on tract's
/// threads; runs past the end are skipped.
pub(super) fn par_runs(blocks: usize, parts: usize, len: usize, f: impl Fn(usize, Range<usize>) + Sync) {
    let parts = parts.max(1);
    let per = len.div_ceil(parts);
    par_for(blocks * parts, |item| {
        let first = item % parts * per;
        let end = (first + per).min(len);
        if first < end {
            f(item / parts, first..end);
        }
    });
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

#[cfg(test)]
mod tests {
    use super::split;

    #[test]
    fn parts_keep_the_threads_busy() {
        // One thread, or no blocks: whole blocks.
        assert_eq!(split(12, 12, 100, 1), 1);
        assert_eq!(split(0, 12, 100, 8), 1);
        // Two threads: the x86 paths' at least 12 items, as before; even block counts whole.
        assert_eq!(split(16, 12, 100, 2), 1);
        assert_eq!(split(3, 12, 100, 2), 4);
        assert_eq!(split(12, 1, 100, 2), 1);
        assert_eq!(split(2, 1, 100, 2), 1);
        // An odd few blocks over two threads: halves (3 blocks left half a round idle).
        assert_eq!(split(3, 1, 100, 2), 2);
        assert_eq!(split(9, 1, 100, 2), 1);
        // Eight threads: PRL-Track's layer 1 (12 blocks of 8 channels) in halves; 32 and 48
        // blocks whole; two blocks (NanoTrack's stem) in quarters.
        assert_eq!(split(12, 1, 100, 8), 2);
        assert_eq!(split(32, 1, 100, 8), 1);
        assert_eq!(split(48, 1, 100, 8), 1);
        assert_eq!(split(2, 1, 100, 8), 4);
        assert_eq!(split(3, 12, 100, 8), 5);
        // Never more than `most` (a block's rows or tiles).
        assert_eq!(split(2, 1, 3, 8), 3);
        assert_eq!(split(1, 12, 0, 8), 1);
    }
}
