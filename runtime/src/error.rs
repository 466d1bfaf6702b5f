//! The runtime's error type.

use std::path::PathBuf;

/// What can go wrong when loading a plan or tracking.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// A file could not be read.
    #[error("{path}: {err}")]
    Io {
        /// The file.
        path: PathBuf,
        /// What the OS said (in the message, not a separate source, so a one-line report
        /// says it once).
        err: std::io::Error,
    },
    /// The plan is malformed, corrupt, or not one this runtime can run.
    #[error("{path}: {msg}")]
    Plan { path: PathBuf, msg: String },
    /// tract failed while running a graph.
    #[error("{graph} graph: {msg}")]
    Run { graph: &'static str, msg: String },
    /// A frame or box handed to the tracker is unusable.
    #[error("{0}")]
    Input(String),
    /// The box `init` was given cannot start a track on its frame. The box is printed plainly
    /// (`x,y,w,h`); a caller that knows how the user wrote it reports `problem` with that text.
    #[error("init box {bbox}: {problem}")]
    InitBox {
        /// The box as the tracker received it.
        bbox: crate::BBox,
        /// What is wrong with it, e.g. "is larger than the 1280x720 frame".
        problem: String,
    },
}

/// The runtime's result type.
pub type Result<T, E = Error> = std::result::Result<T, E>;
