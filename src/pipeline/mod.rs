//! Whole runs: read an input, drive the filter, write the run folder.
//!
//! A run folder holds the map, `trajectory.tum`, `run.json` (what ran, how
//! long, how much memory) and `config.toml` (the configuration as used). Every
//! file is written under a temporary name and renamed, and only after the
//! whole input was processed, so a failed run leaves no half-written output.

pub mod learn_motion;
pub mod map2d;
pub mod map3d;
pub mod preflight;

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

/// A progress bar on stderr: drawn when stderr is a terminal; otherwise
/// (CI, nohup, a pipe) plain lines, see [`progress_lines`].
pub fn progress_bar(total: u64, what: &str) -> indicatif::ProgressBar {
    use std::io::IsTerminal;
    if !std::io::stderr().is_terminal() {
        let pb = indicatif::ProgressBar::hidden();
        pb.set_length(total);
        progress_lines(&pb, what, PROGRESS_STEP_PERCENT, PROGRESS_EVERY);
        return pb;
    }
    let pb = indicatif::ProgressBar::new(total);
    pb.set_style(
        indicatif::ProgressStyle::with_template(
            "{spinner} {msg} [{elapsed_precise}] {wide_bar} {percent}% (eta {eta})",
        )
        .expect("valid template"),
    );
    pb.set_message(what.to_string());
    pb
}

/// Progress lines on a non-terminal stderr: one per this many percent...
pub const PROGRESS_STEP_PERCENT: u64 = 5;
/// ... or after this long without one.
pub const PROGRESS_EVERY: std::time::Duration = std::time::Duration::from_secs(10);

/// Prints `what: P % (elapsed s, eta s)` on stderr each time `pb` passes
/// another `step` percent, or `every` after the last line, until it is
/// finished or dropped (a thread polls it twice a second).
pub fn progress_lines(
    pb: &indicatif::ProgressBar,
    what: &str,
    step: u64,
    every: std::time::Duration,
) {
    let weak = pb.downgrade();
    let what = what.to_string();
    std::thread::spawn(move || {
        let step = step.max(1);
        let mut next = step;
        let mut last = std::time::Instant::now();
        loop {
            std::thread::sleep(std::time::Duration::from_millis(500));
            let Some(pb) = weak.upgrade() else { return };
            if pb.is_finished() {
                return;
            }
            let total = pb.length().unwrap_or(0).max(1);
            let pct = (pb.position().min(total) * 100 / total).min(100);
            if pct >= next || last.elapsed() >= every {
                let t = pb.elapsed().as_secs_f64();
                let eta = if pct > 0 {
                    format!(", eta {:.0} s", t * (100 - pct) as f64 / pct as f64)
                } else {
                    String::new()
                };
                eprintln!("{what}: {pct} % ({t:.0} s{eta})");
                next = (pct / step + 1) * step;
                last = std::time::Instant::now();
            }
        }
    });
}
