//! The compiler's error type.

use std::path::PathBuf;

/// Everything that can go wrong while importing weights, building graphs or running them.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// A file could not be read or written.
    #[error("{path}: {err}")]
    Io {
        /// The file.
        path: PathBuf,
        /// What the OS said (in the message, not a separate source, so a one-line report
        /// says it once).
        err: std::io::Error,
    },
    /// A checkpoint or golden file is malformed, truncated or of an unsupported kind.
    #[error("{path}: {msg}")]
    Format { path: PathBuf, msg: String },
    /// A weight the network needs is absent.
    #[error("{source_name}: missing weight `{key}` (expected shape {expected:?})")]
    MissingWeight { source_name: String, key: String, expected: Vec<usize> },
    /// A weight has the wrong shape.
    #[error("{source_name}: weight `{key}` has shape {actual:?}, expected {expected:?}")]
    WrongShape { source_name: String, key: String, expected: Vec<usize>, actual: Vec<usize> },
    /// A weight the network needs is not a plain tensor in the checkpoint.
    #[error("{source_name}: weight `{key}` is not a tensor: {what}")]
    NotATensor { source_name: String, key: String, what: String },
    /// A weight holds NaN or infinite values: every output would be NaN.
    #[error("{source_name}: weight `{key}` holds {count} NaN or infinite values (a corrupt or diverged checkpoint?)")]
    NonFinite { source_name: String, key: String, count: usize },
    /// The ONNX builder was asked for something inconsistent.
    #[error("graph `{graph}`, node `{node}`: {msg}")]
    Graph { graph: String, node: String, msg: String },
    /// tract refused or failed on a model.
    #[error("{context}: {msg}")]
    Tract { context: String, msg: String },
    /// Quantisation was asked for something it cannot do.
    #[error("quantize: {0}")]
    Quantize(String),
    /// Anything else, stated plainly.
    #[error("{0}")]
    Other(String),
}

impl Error {
    pub(crate) fn io(path: impl Into<PathBuf>, source: std::io::Error) -> Self {
        Error::Io { path: path.into(), err: source }
    }
    pub(crate) fn format(path: impl Into<PathBuf>, msg: impl Into<String>) -> Self {
        Error::Format { path: path.into(), msg: msg.into() }
    }
    pub(crate) fn tract(context: impl Into<String>, e: impl std::fmt::Display) -> Self {
        // tract errors are chains; `{:#}` would be multi-line, keep one line.
        Error::Tract { context: context.into(), msg: e.to_string() }
    }
}

/// The compiler's result type.
pub type Result<T, E = Error> = std::result::Result<T, E>;
