//! Panics of a dependency turned into errors without a word on standard error: tract panics on
//! some malformed graphs it does not check (found by fuzzing), and a bad file must give one line
//! naming it, not a panic message and a backtrace above that line.

use std::cell::Cell;
use std::sync::Once;

thread_local! {
    /// Whether this thread is inside [`catch_quietly`].
    static QUIET: Cell<bool> = const { Cell::new(false) };
}

/// Run `f`; a panic inside it is `None`, and the panic hook stays silent about it. The hook
/// in place before the first call (the default one, or a fuzzer's) still sees every panic
/// outside these calls, on every thread, so a panic that escapes them is reported as before.
pub fn catch_quietly<R>(f: impl FnOnce() -> R) -> Option<R> {
    static HOOK: Once = Once::new();
    HOOK.call_once(|| {
        let previous = std::panic::take_hook();
        std::panic::set_hook(Box::new(move |info| {
            if !QUIET.with(Cell::get) {
                previous(info);
            }
        }));
    });
    let outer = QUIET.with(|q| q.replace(true));
    let result = std::panic::catch_unwind(std::panic::AssertUnwindSafe(f));
    QUIET.with(|q| q.set(outer));
    result.ok()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_panic_is_an_error_and_the_flag_is_restored() {
        assert_eq!(catch_quietly(|| 7), Some(7));
        let r: Option<()> = catch_quietly(|| panic!("malformed"));
        assert_eq!(r, None);
        assert!(!QUIET.with(Cell::get), "outside a call, panics reach the previous hook again");
        // Nested: the inner call leaves the outer one quiet.
        let r = catch_quietly(|| {
            let inner: Option<()> = catch_quietly(|| panic!("inner"));
            (inner, QUIET.with(Cell::get))
        });
        assert_eq!(r, Some((None, true)));
    }
}
