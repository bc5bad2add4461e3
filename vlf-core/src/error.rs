//! The library's error type: every way a user's input can be refused.

use std::path::PathBuf;

/// Errors of `vlf-core`. Each names what was wrong and where (file and line
/// for scene input), so a binary can print it as is.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// The scene file is malformed or violates the conventions (see README).
    #[error("{file}{}: {message}", line.map(|l| format!(":{l}")).unwrap_or_default())]
    Scene {
        file: String,
        line: Option<usize>,
        message: String,
    },
    /// A parameter outside its documented range.
    #[error("invalid parameter: {0}")]
    Parameter(String),
    /// Reading or writing a file failed.
    #[error("{}: {source}", path.display())]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// A stored field or image is truncated, corrupted or of another version.
    #[error("{}: {message}", path.display())]
    Format { path: PathBuf, message: String },
    /// Stored bytes (a scene, a checkpoint, radiance maps) that do not decode
    /// or do not fit what they belong to; the caller adds where they came from.
    #[error("{0}")]
    Decode(String),
}

impl Error {
    pub(crate) fn scene(file: &str, line: Option<usize>, message: impl Into<String>) -> Self {
        Error::Scene {
            file: file.to_string(),
            line,
            message: message.into(),
        }
    }
    pub(crate) fn io(path: impl Into<PathBuf>, source: std::io::Error) -> Self {
        Error::Io {
            path: path.into(),
            source,
        }
    }
}

pub type Result<T, E = Error> = std::result::Result<T, E>;
