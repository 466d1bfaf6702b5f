//! `prl`: the PRL-Track deployment toolchain on the command line.

mod cli;

fn main() {
    if let Err(e) = cli::run() {
        // One line: the error and its causes.
        eprintln!("error: {e:#}");
        std::process::exit(1);
    }
}
