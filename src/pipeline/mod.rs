//! Whole runs: read an input, drive the filter, write the run folder.
//!
//! A run folder holds the map, `trajectory.tum`, `run.json` (what ran, how
//! long, how much memory) and `config.toml` (the configuration as used). Every
//! file is written under a temporary name and renamed, and only after the
//! whole input was processed, so a failed run leaves no half-written output.

pub mod learn_motion;
pub mod map2d;
pub mod map3d;

use crate::{Error, Result};
use serde::Serialize;
use std::path::Path;

/// Peak resident memory of this process so far, in MiB (Linux `VmHWM`;
/// `None` elsewhere).
pub fn peak_memory_mib() -> Option<f64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kb: f64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kb / 1024.0)
}

pub use crate::io::atomic::write_atomic;

/// Writes `value` as pretty JSON to `path`.
pub fn write_json<T: Serialize>(path: &Path, value: &T) -> Result<()> {
    let mut s = serde_json::to_string_pretty(value).expect("serializable");
    s.push('\n');
    write_atomic(path, s.as_bytes())
}

/// Creates the output folder (and parents).
pub fn create_out_dir(dir: &Path) -> Result<()> {
    std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))
}

/// Reports the progress of a long run: called with `(done, total)` in the
/// run's own units (bytes of a log read, sweeps mapped) as it goes.
pub type Progress<'a> = &'a mut dyn FnMut(u64, u64);

/// A [`Progress`] that reports nothing.
pub fn no_progress(_done: u64, _total: u64) {}
