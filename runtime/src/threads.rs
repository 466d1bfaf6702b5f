//! Threads: how many the networks use ([`set_threads`], [`Threads`]), the calling thread's
//! part in that pool, how a split graph's run keeps the pool's other threads spinning between
//! operators, and [`spread`] for independent work (several targets, the long-term mode's
//! region crops).

use std::cell::RefCell;
use std::sync::{Arc, Mutex, Weak};

use rayon::ThreadPool;
use tract_linalg::multithread::{multithread_tract_scope, Executor};
use tract_nnef::prelude::tract_linalg;

/// Use `n` threads for the networks (1: single-threaded). Applies process-wide; the calling
/// thread is one of the `n` ([`executor`]).
pub fn set_threads(n: usize) {
    tract_linalg::multithread::set_default_executor(executor(n));
}

thread_local! {
    /// The pool this thread is one of the threads of ([`executor`]).
    static MEMBER_OF: RefCell<Option<Arc<ThreadPool>>> = const { RefCell::new(None) };
}

/// `n` threads for the networks, the calling thread among them (rayon's `use_current_thread`):
/// a graph run from this thread starts on it, with no hand-over to a pool thread and back.
/// Where the pool is a separate one, the calling thread sleeps through each run and has to be
/// woken after it, and for as long as the pool's idle threads yield before they sleep it shares
/// a core with them: on a 2-vCPU VM (2026-12-05, seven alternated pairs of `prl bench
/// --threads 2`) PRL-Track's int8 tracking step took 0.7-7% longer so (median 2%), the
/// tracker's post-processing after each run 0.18 ms against 0.01; the fp32 step showed no
/// difference beyond the VM's noise. Other threads' runs on these `n` go to a separate pool of `n` threads
/// ([`split_run`]): the calling thread takes work only while it runs a graph itself. A thread
/// is one such pool's at most: where it already is another size's, the `n` threads are a
/// separate pool, as they were before.
fn executor(n: usize) -> Executor {
    if n <= 1 {
        return Executor::SingleThread;
    }
    MEMBER_OF.with_borrow_mut(|member| {
        if let Some(pool) = member.as_ref().filter(|p| p.current_num_threads() == n) {
            return Executor::MultiThread(pool.clone());
        }
        if member.is_none() {
            let built = rayon::ThreadPoolBuilder::new()
                .thread_name(|i| format!("prl-{i}"))
                .num_threads(n)
                .use_current_thread()
                .build();
            if let Ok(pool) = built {
                let pool = Arc::new(pool);
                *member = Some(pool.clone());
                let mut others = OTHERS.lock().unwrap_or_else(|e| e.into_inner());
                others.retain(|(maker, _)| maker.strong_count() > 0);
                others.push((Arc::downgrade(&pool), None));
                return Executor::MultiThread(pool);
            }
        }
        Executor::multithread(n)
    })
}

/// Pools made by [`executor`] with their maker among their threads (those still in use), each
/// with the separate pool of as many threads that other threads' runs use instead (made when
/// first needed: `prl run-benchmark`'s job threads, say).
static OTHERS: Mutex<Vec<Maker>> = Mutex::new(Vec::new());

/// A pool made with its maker among its threads, and the separate pool for other threads.
type Maker = (Weak<ThreadPool>, Option<Arc<ThreadPool>>);

/// The pool to run a graph on from a thread that is not among `pool`'s: `pool` itself, unless
/// its maker is one of its threads ([`OTHERS`]).
fn for_others(pool: Arc<ThreadPool>) -> Arc<ThreadPool> {
    let mut others = OTHERS.lock().unwrap_or_else(|e| e.into_inner());
    let made_by_member = |maker: &Weak<ThreadPool>| maker.upgrade().is_some_and(|p| Arc::ptr_eq(&p, &pool));
    let Some((_, separate)) = others.iter_mut().find(|(maker, _)| made_by_member(maker)) else { return pool };
    match separate {
        Some(p) => p.clone(),
        None => match Executor::multithread(pool.current_num_threads()) {
            Executor::MultiThread(p) => separate.insert(p).clone(),
            _ => pool,
        },
    }
}

/// `f` with tract's executor on the calling thread, for a graph whose operators split over the
/// executor's threads, so that every split starts on all of them at once: where the executor
/// is a pool the calling thread is one of ([`executor`]), here while the pool's other threads
/// spin ([`spin_while`], unless [`spin`] says not); where it is not, on one of the pool's
/// threads (or [`for_others`]'), the same way.
pub(crate) fn split_run<R: Send>(f: impl FnOnce() -> R + Send) -> R {
    let Executor::MultiThread(pool) = tract_linalg::multithread::current_tract_executor() else { return f() };
    if MEMBER_OF.with_borrow(|m| m.as_ref().is_some_and(|p| Arc::ptr_eq(p, &pool))) {
        return if spin() { spin_while(f) } else { f() };
    }
    if pool.current_thread_index().is_some() {
        return f();
    }
    let pool = for_others(pool);
    let executor = Executor::MultiThread(pool.clone());
    let run = move || multithread_tract_scope(executor, f);
    pool.install(move || if spin() { spin_while(run) } else { run() })
}

/// A pool of threads for tract's matrix products that some calls run on ([`Threads::run`])
/// while the rest of the process keeps the setting of [`set_threads`]: to time one target's
/// step on every core against several targets' steps spread one thread each, in one run.
#[derive(Clone)]
pub struct Threads(Executor);

impl Threads {
    /// `n` threads (1: on the calling thread).
    pub fn new(n: usize) -> Threads {
        Threads(executor(n))
    }

    /// Run `f` with tract's products on these threads (on the calling thread's calls only).
    pub fn run<R>(&self, f: impl FnOnce() -> R) -> R {
        multithread_tract_scope(self.0.clone(), f)
    }
}

/// `f(i, item)` for every item of `items` on up to `threads` threads side by side (contiguous
/// shares; results in item order); on the calling thread for one thread or one item. For work
/// that is independent per item: several targets' steps, the long-term mode's region crops.
pub fn spread<T: Send, R: Send>(items: &mut [T], threads: usize, f: impl Fn(usize, &mut T) -> R + Sync) -> Vec<R> {
    if threads <= 1 || items.len() <= 1 {
        return items.iter_mut().enumerate().map(|(i, t)| f(i, t)).collect();
    }
    let share = items.len().div_ceil(threads);
    let f = &f;
    std::thread::scope(|s| {
        let handles: Vec<_> = items
            .chunks_mut(share)
            .enumerate()
            .map(|(c, chunk)| {
                s.spawn(move || chunk.iter_mut().enumerate().map(|(j, t)| f(c * share + j, t)).collect::<Vec<R>>())
            })
            .collect();
        handles.into_iter().flat_map(|h| h.join().unwrap_or_else(|p| std::panic::resume_unwind(p))).collect()
    })
}

/// Whether a split graph's run keeps the pool's other threads spinning ([`spin_while`]): yes,
/// unless the environment sets `PRL_SPIN=off` (or `0`), which saves their cores' power at
/// some speed (on the camera, say, where the step has time to spare).
fn spin() -> bool {
    static SPIN: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
    *SPIN.get_or_init(|| !matches!(std::env::var("PRL_SPIN").as_deref(), Ok("off" | "0")))
}

/// `f` on the calling thread, one of a rayon pool's, while the pool's other threads look for
/// work without sleeping until `f` returns (as ONNX Runtime's threads spin between operators).
///
/// A pool thread that found nothing to do goes to sleep within microseconds, and waking it
/// took 20-40 µs on a 2-vCPU VM (an idle virtual CPU is halted by the host), then as long
/// again for the first thread to learn that the second's share was done: a split of two
/// 100 µs halves took 165-180 µs, against 101 µs with the other thread spinning (measured
/// with rayon alone). PRL-Track's search graph splits about a hundred operators a frame, many
/// of them 0.1-1 ms long. The cost: the pool's other threads keep their cores busy for as long
/// as `f` runs (one graph run), not between runs.
///
/// The spinning is a short job ([`spin_once`]) that looks for work once and queues itself
/// again, never a loop until `f` ends: a pool thread waiting on a split runs whatever job it
/// finds, and a job that looped until the run's end there would hold up the split the run
/// waits on (it deadlocked so).
fn spin_while<R>(f: impl FnOnce() -> R) -> R {
    spin_until_set(Arc::default(), f)
}

/// [`spin_while`], the run's end marked by setting `done` (each queued turn holds a clone: the
/// tests watch them go).
fn spin_until_set<R>(done: Arc<std::sync::atomic::AtomicBool>, f: impl FnOnce() -> R) -> R {
    use std::sync::atomic::{AtomicBool, Ordering};
    /// Ends the spinning however `f` ends.
    struct Done(Arc<AtomicBool>);
    impl Drop for Done {
        fn drop(&mut self) {
            self.0.store(true, Ordering::Release);
        }
    }
    let done = Done(done);
    if let Some(me) = rayon::current_thread_index() {
        let flag = done.0.clone();
        rayon::spawn_broadcast(move |ctx| {
            if ctx.index() != me {
                spin_once(flag.clone(), me);
            }
        });
    }
    f()
}

/// One turn of [`spin_while`]'s spinning on a pool thread other than the run's (`me`): unless
/// the run is `done`, run one job found elsewhere (or yield the core to any other thread that
/// wants it), then queue the next turn on this thread's own deque. Where the run's thread
/// takes the turn (stealing it while it waits on a split) it only queues it again, for the
/// others to take back.
fn spin_once(done: Arc<std::sync::atomic::AtomicBool>, me: usize) {
    if done.load(std::sync::atomic::Ordering::Acquire) {
        return;
    }
    if rayon::current_thread_index() != Some(me) && rayon::yield_now() != Some(rayon::Yield::Executed) {
        // Nothing to steal: let any other thread that wants this core run (`prl track`'s frame
        // decoding, say); with none, the call returns at once.
        std::thread::yield_now();
    }
    rayon::spawn(move || spin_once(done, me));
}

#[cfg(test)]
mod tests {
    use super::spin_while;

    /// The turns still queued for a run's spinning (each holds a clone of its flag) are gone
    /// within a second.
    fn turns_end(flag: &std::sync::Arc<std::sync::atomic::AtomicBool>) -> bool {
        let t = std::time::Instant::now();
        while std::sync::Arc::strong_count(flag) > 1 && t.elapsed().as_secs() < 1 {
            std::thread::sleep(std::time::Duration::from_millis(1));
        }
        std::sync::Arc::strong_count(flag) == 1
    }

    /// `spin_while` returns what `f` returns, with the pool's other thread taking a share of
    /// `f`'s splits while it spins, and the spinning stops when `f` returns or panics (no turn
    /// queues another).
    #[test]
    fn spinning_ends_with_the_run() {
        let pool = rayon::ThreadPoolBuilder::new().num_threads(2).build().unwrap();
        let threads = std::sync::Mutex::new(std::collections::BTreeSet::new());
        let flag: std::sync::Arc<std::sync::atomic::AtomicBool> = std::sync::Arc::default();
        let sum = pool.install(|| {
            super::spin_until_set(flag.clone(), || {
                use rayon::prelude::*;
                (0..64u64)
                    .into_par_iter()
                    .map(|i| {
                        threads.lock().unwrap().insert(rayon::current_thread_index());
                        std::thread::sleep(std::time::Duration::from_millis(1));
                        i
                    })
                    .sum::<u64>()
            })
        });
        assert_eq!(sum, 63 * 64 / 2);
        assert_eq!(threads.lock().unwrap().len(), 2, "both threads took a share");
        assert!(turns_end(&flag), "the spinning went on after the run");
        let flag: std::sync::Arc<std::sync::atomic::AtomicBool> = std::sync::Arc::default();
        let panicked = pool
            .install(|| std::panic::catch_unwind(|| super::spin_until_set(flag.clone(), || panic!("a failing run"))));
        assert!(panicked.is_err());
        assert!(turns_end(&flag), "the spinning went on after the panic");
        assert_eq!(pool.broadcast(|c| c.index()), vec![0, 1]);
    }

    /// Runs one after another, each of nested splits of uneven work (the shape of a graph's
    /// operators: a pool thread that waits on a split runs whatever job it finds, the spinning
    /// of the next run included), finish: the spinning never holds up a split it is nested in.
    /// (A spinner that looped until its run ended deadlocked here, as it had in `prl bench`.)
    #[test]
    fn nested_splits_finish_while_the_threads_spin() {
        let (tx, rx) = std::sync::mpsc::channel();
        std::thread::spawn(move || {
            let pool = rayon::ThreadPoolBuilder::new().num_threads(2).build().unwrap();
            let mut total = 0u64;
            for run in 0..300u64 {
                total += pool.install(|| {
                    spin_while(|| {
                        use rayon::prelude::*;
                        (0..8u64)
                            .into_par_iter()
                            .map(|i| {
                                (0..4u64)
                                    .into_par_iter()
                                    .map(|j| {
                                        let t = std::time::Instant::now();
                                        let us = (run + i * 7 + j * 3) % 40;
                                        while t.elapsed() < std::time::Duration::from_micros(us) {
                                            std::hint::spin_loop();
                                        }
                                        1
                                    })
                                    .sum::<u64>()
                            })
                            .sum::<u64>()
                    })
                });
            }
            tx.send(total).unwrap();
        });
        let total = rx.recv_timeout(std::time::Duration::from_secs(60)).expect("the runs deadlocked");
        assert_eq!(total, 300 * 32);
    }

    /// The threads that took a share of 64 one-millisecond items split over the current pool.
    fn shares() -> std::collections::HashSet<std::thread::ThreadId> {
        use rayon::prelude::*;
        let threads = std::sync::Mutex::new(std::collections::HashSet::new());
        (0..64).into_par_iter().for_each(|_| {
            threads.lock().unwrap().insert(std::thread::current().id());
            std::thread::sleep(std::time::Duration::from_millis(1));
        });
        threads.into_inner().unwrap()
    }

    /// The thread that sets the threads is one of them: its runs start on it and split over
    /// its pool. Another thread's runs, while the maker waits outside rayon (as `prl
    /// run-benchmark`'s main thread waits for its job threads), go to a separate pool of as many
    /// threads and split over both (on the maker's pool they would get one: the maker takes no
    /// work while it waits so).
    #[test]
    fn the_maker_runs_on_its_pool_and_other_threads_on_a_separate_one() {
        use tract_linalg::multithread::{multithread_tract_scope, Executor};
        std::thread::spawn(|| {
            let me = std::thread::current().id();
            let executor = super::executor(2);
            assert!(matches!(&executor, Executor::MultiThread(p) if p.current_thread_index() == Some(0)));
            let (first, threads) = multithread_tract_scope(executor.clone(), || {
                super::split_run(|| (std::thread::current().id(), shares()))
            });
            assert_eq!(first, me, "the run starts on the calling thread");
            assert!(threads.len() == 2 && threads.contains(&me), "{threads:?}");
            let other = std::thread::scope(|s| {
                let run = || multithread_tract_scope(executor.clone(), || super::split_run(shares));
                s.spawn(run).join().unwrap()
            });
            assert!(other.len() == 2 && !other.contains(&me), "{other:?}");
            // The same size again is the same pool; another size a separate one.
            assert!(matches!(super::executor(2), Executor::MultiThread(p) if p.current_thread_index() == Some(0)));
            assert!(matches!(super::executor(3), Executor::MultiThread(p) if p.current_thread_index().is_none()));
        })
        .join()
        .unwrap();
    }
}
