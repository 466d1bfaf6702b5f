//! `prl`: the PRL-Track deployment toolchain on the command line.

mod cli;

/// mimalloc: tract's plan loading (NNEF parse, declutter) is allocation-bound, and loads
/// about 25% faster with it; peak memory while tracking goes from ~156 to ~210 MB.
#[global_allocator]
static ALLOCATOR: mimalloc::MiMalloc = mimalloc::MiMalloc;

fn main() {
    // Like other command-line tools, end quietly when the reader of our output goes away
    // (`prl track ... | head`) instead of failing on a broken pipe.
    #[cfg(unix)]
    // SAFETY: restoring the default disposition of SIGPIPE before any thread starts.
    unsafe {
        libc::signal(libc::SIGPIPE, libc::SIG_DFL);
    }
    if let Err(e) = cli::run() {
        // One line: the error and its causes.
        eprintln!("error: {e:#}");
        std::process::exit(1);
    }
}
