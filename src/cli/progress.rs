//! Progress of long runs on stderr: a bar on a terminal, and on anything
//! else (a pipe, CI, nohup) a line every 5 % or 10 s, so logs show that a
//! run is alive and how far it is.

use std::io::IsTerminal;
use std::time::{Duration, Instant};

/// Seconds between two progress lines on a non-terminal, at most.
const LINE_EVERY: Duration = Duration::from_secs(10);

/// Draws a run's progress.
pub struct Progress {
    what: &'static str,
    bar: Option<indicatif::ProgressBar>,
    start: Instant,
    last_line: Instant,
    last_tenth: u64,
}

impl Progress {
    /// A progress display for the run `what` (e.g. "map2d").
    pub fn new(what: &'static str) -> Self {
        let bar = std::io::stderr().is_terminal().then(|| {
            let pb = indicatif::ProgressBar::new(0);
            pb.set_style(
                indicatif::ProgressStyle::with_template(
                    "{spinner} {msg} [{elapsed_precise}] {wide_bar} {percent}% (eta {eta})",
                )
                .expect("valid template"),
            );
            pb.set_message(what);
            pb
        });
        let now = Instant::now();
        Self {
            what,
            bar,
            start: now,
            last_line: now,
            last_tenth: 0,
        }
    }

    /// Reports `done` of `total` units.
    pub fn update(&mut self, done: u64, total: u64) {
        if let Some(bar) = &self.bar {
            bar.set_length(total);
            bar.set_position(done);
            return;
        }
        let tenth = (done * 20).checked_div(total).unwrap_or(0);
        if tenth > self.last_tenth || self.last_line.elapsed() >= LINE_EVERY {
            self.last_tenth = tenth;
            self.last_line = Instant::now();
            let pct = (done as f64 * 100.0 / total.max(1) as f64).min(100.0);
            eprintln!(
                "{}: {pct:.0} % ({:.0} s)",
                self.what,
                self.start.elapsed().as_secs_f64()
            );
        }
    }

    /// Removes the bar (a terminal) at the end of the run.
    pub fn finish(&self) {
        if let Some(bar) = &self.bar {
            bar.finish_and_clear();
        }
    }
}

/// Prints a run's warnings on stderr.
pub fn print_warnings(warnings: &[String]) {
    for w in warnings {
        eprintln!("dpslam: warning: {w}");
    }
}

/// Says on stderr why `--backend auto` ended on the CPU (`backend` as the
/// run summary records it: `cpu (auto: REASON)`).
pub fn print_backend_note(backend: &str) {
    if let Some(reason) = backend
        .strip_prefix("cpu (auto: ")
        .and_then(|r| r.strip_suffix(')'))
    {
        eprintln!("dpslam: {reason}; using the CPU backend");
    }
}
