//! Error type shared by the library and the CLI.
//!
//! Every error that comes from input data names the file, the line (or byte
//! offset) and the reason, so that a user can fix the input without a debugger.

use std::path::{Path, PathBuf};

/// Where in an input file a problem was found.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Location {
    /// 1-based line number in a text file.
    Line(usize),
    /// 0-based byte offset in a binary file.
    Byte(u64),
    /// The file as a whole (empty, truncated, wrong size, ...).
    File,
}

impl std::fmt::Display for Location {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Location::Line(n) => write!(f, "line {n}"),
            Location::Byte(b) => write!(f, "byte {b}"),
            Location::File => write!(f, "file"),
        }
    }
}

/// Errors of the dpslam library.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// Malformed or inconsistent input data.
    #[error("{}:{location}: {reason}", path.display())]
    Parse {
        /// The file.
        path: PathBuf,
        /// Where in it (line, message index, ...).
        location: Location,
        /// What is wrong.
        reason: String,
    },
    /// An operating-system I/O failure on a path.
    #[error("{}: {source}", path.display())]
    Io {
        /// The path.
        path: PathBuf,
        /// The operating system's error.
        #[source]
        source: std::io::Error,
    },
    /// A configuration value out of range, or an unusable combination of options.
    #[error("configuration: {0}")]
    Config(String),
    /// Valid input that cannot be processed (e.g. a log with no laser scans).
    #[error("{0}")]
    Invalid(String),
    /// The GPU path could not be used.
    #[error("gpu: {0}")]
    Gpu(String),
}

/// Result alias for the library.
pub type Result<T, E = Error> = std::result::Result<T, E>;

impl Error {
    /// A parse error at a 1-based line of `path`.
    pub fn at_line(path: &Path, line: usize, reason: impl Into<String>) -> Self {
        Error::Parse {
            path: path.to_path_buf(),
            location: Location::Line(line),
            reason: reason.into(),
        }
    }

    /// A parse error at a byte offset of `path`.
    pub fn at_byte(path: &Path, byte: u64, reason: impl Into<String>) -> Self {
        Error::Parse {
            path: path.to_path_buf(),
            location: Location::Byte(byte),
            reason: reason.into(),
        }
    }

    /// A problem with `path` as a whole.
    pub fn in_file(path: &Path, reason: impl Into<String>) -> Self {
        Error::Parse {
            path: path.to_path_buf(),
            location: Location::File,
            reason: reason.into(),
        }
    }

    /// An I/O error on `path`.
    pub fn io(path: &Path, source: std::io::Error) -> Self {
        Error::Io {
            path: path.to_path_buf(),
            source,
        }
    }
}
