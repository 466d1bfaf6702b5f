//! What every fuzz target shares: an allocator that turns any single allocation over 1 GiB into
//! a crash (libFuzzer's own `-malloc_limit_mb` needs a sanitizer runtime, which a stable
//! toolchain does not link), and where the shared fixtures are.

use std::alloc::{GlobalAlloc, Layout, System};
use std::path::PathBuf;

/// The largest single allocation a target may make.
pub const MAX_ALLOC: usize = 1 << 30;

/// The system allocator, aborting on an allocation over [`MAX_ALLOC`].
pub struct Capped;

// SAFETY: every call is forwarded unchanged to `System`, which upholds `GlobalAlloc`'s
// contract; the only addition is an abort before an over-large request reaches it.
unsafe impl GlobalAlloc for Capped {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        check(layout.size());
        // SAFETY: forwarded with the caller's layout.
        unsafe { System.alloc(layout) }
    }
    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        check(layout.size());
        // SAFETY: forwarded with the caller's layout.
        unsafe { System.alloc_zeroed(layout) }
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        // SAFETY: `ptr` came from `System` with this layout.
        unsafe { System.dealloc(ptr, layout) }
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        check(new_size);
        // SAFETY: forwarded unchanged; `ptr` came from `System` with `layout`.
        unsafe { System.realloc(ptr, layout, new_size) }
    }
}

fn check(size: usize) {
    if size > MAX_ALLOC {
        // No formatting (it would allocate): a fixed message, then abort, which libFuzzer
        // reports as a crash with the input saved.
        use std::io::Write;
        let _ = std::io::stderr().write_all(b"prl-fuzz: an allocation over 1 GiB\n");
        std::process::abort();
    }
}

/// `../shared` beside the repository (or `$PRL_SHARED`).
pub fn shared() -> PathBuf {
    std::env::var_os("PRL_SHARED")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(concat!(env!("CARGO_MANIFEST_DIR"), "/../../shared")))
}

/// A scratch directory of this process (fuzz targets that must go through files).
pub fn scratch(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("prl-fuzz-{name}-{}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("scratch directory");
    dir
}
