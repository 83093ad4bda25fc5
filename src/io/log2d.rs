//! One streaming reader for 2-D laser logs, CARMEN or DP-SLAM, plain or gzip,
//! and ROS bags ([`crate::io::bag`]).
//!
//! The format is told from the first line that is neither empty nor a `#`
//! comment: `Odometry` or `Laser` means the DP-SLAM format
//! ([`crate::io::dpslam_log`]), anything else CARMEN ([`crate::io::carmen`]).
//! Scans are parsed one line at a time, so memory does not grow with the
//! length of the log.

use crate::geometry::Pose2;
use crate::io::bag::scans2d::{BagScans2d, TopicChoice};
use crate::io::carmen::CarmenParser;
use crate::io::dpslam_log::{DpSlamParser, is_dpslam_keyword};
use crate::io::source::TextSource;
use crate::scan::LaserScan2d;
use crate::{Error, Result};
use std::path::{Path, PathBuf};

/// The dialect of a 2-D laser log.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LogFormat {
    /// CARMEN (`FLASER`, `ROBOTLASER1`, `RAWLASERk` + `ODOM`, `PARAM`, …).
    Carmen,
    /// DP-SLAM 0.1.1 (`Odometry` / `Laser` pairs).
    DpSlam,
    /// A ROS bag (ROS 1, MCAP, sqlite3 or a ROS 2 bag directory) with
    /// `sensor_msgs/LaserScan` messages ([`crate::io::bag::scans2d`]).
    RosBag,
}

enum Parser {
    Carmen(CarmenParser),
    DpSlam(DpSlamParser),
}

/// A text log being read.
struct TextLog {
    src: TextSource,
    parser: Parser,
    /// The line used to detect the format, parsed on the first `next`.
    pending: Option<(usize, String)>,
}

enum Input {
    Text(Box<TextLog>),
    Bag(Box<BagScans2d>),
}

/// Streaming iterator over the laser scans of a 2-D log.
///
/// Yields `Ok(scan)` in file order; the first `Err` (malformed line,
/// truncated gzip, I/O failure, or a log that ends without any laser scan)
/// is the last item.
pub struct LogReader2d {
    input: Input,
    path: PathBuf,
    format: LogFormat,
    scans_read: usize,
    done: bool,
}

/// Opens the 2-D log at `path` (plain or gzip text, or a ROS bag with its
/// topics guessed) and detects its format.
///
/// Errors: the file cannot be opened or read (named by path), or it holds no
/// line other than comments and blank lines ("no laser scans").
pub fn open_log2d(path: &Path) -> Result<LogReader2d> {
    open_log2d_with(path, &TopicChoice::default())
}

/// [`open_log2d`], with the topics to read when `path` is a ROS bag.
pub fn open_log2d_with(path: &Path, topics: &TopicChoice) -> Result<LogReader2d> {
    if crate::io::bag::is_bag(path) {
        return Ok(LogReader2d {
            input: Input::Bag(Box::new(BagScans2d::open(path, topics)?)),
            path: path.to_path_buf(),
            format: LogFormat::RosBag,
            scans_read: 0,
            done: false,
        });
    }
    let mut src = TextSource::open(path)?;
    let pending = loop {
        match src.next_line()? {
            None => {
                return Err(Error::in_file(
                    path,
                    "no laser scans (the file is empty or holds only comments)",
                ));
            }
            Some((n, line)) => {
                let t = line.trim_start();
                if !t.is_empty() && !t.starts_with('#') {
                    break (n, line.to_string());
                }
            }
        }
    };
    let first_word = pending.1.split_ascii_whitespace().next().unwrap_or("");
    let (format, parser) = if is_dpslam_keyword(first_word) {
        (LogFormat::DpSlam, Parser::DpSlam(DpSlamParser::new()))
    } else {
        (LogFormat::Carmen, Parser::Carmen(CarmenParser::new()))
    };
    Ok(LogReader2d {
        input: Input::Text(Box::new(TextLog {
            src,
            parser,
            pending: Some(pending),
        })),
        path: path.to_path_buf(),
        format,
        scans_read: 0,
        done: false,
    })
}

impl LogReader2d {
    /// The detected format.
    pub fn format(&self) -> LogFormat {
        self.format
    }

    /// Bytes of the file on disk consumed so far (compressed bytes for gzip;
    /// for a bag, its size times the share of scans delivered); with
    /// [`LogReader2d::total_bytes`], for progress reports.
    pub fn bytes_read(&self) -> u64 {
        match &self.input {
            Input::Text(t) => t.src.bytes_read(),
            Input::Bag(b) => {
                let n = b.total_scans().max(1) as u64;
                self.total_bytes() / n * b.scans_read() as u64
            }
        }
    }

    /// Size of the file on disk (bytes).
    pub fn total_bytes(&self) -> u64 {
        match &self.input {
            Input::Text(t) => t.src.total_bytes(),
            Input::Bag(b) => b
                .bag()
                .files
                .iter()
                .map(|f| std::fs::metadata(f).map_or(0, |m| m.len()))
                .sum(),
        }
    }

    /// The path being read.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Scans delivered so far.
    pub fn scans_read(&self) -> usize {
        self.scans_read
    }

    /// The bag being read, for a ROS bag.
    pub fn bag_scans(&self) -> Option<&BagScans2d> {
        match &self.input {
            Input::Bag(b) => Some(b),
            Input::Text(_) => None,
        }
    }

    /// The laser's pose in the robot frame (m, m, rad) when the log states it:
    /// CARMEN ROBOTLASER1 (laser pose relative to robot pose, latest scan) or
    /// `PARAM robot_frontlaser_offset`; a bag's static transforms from the
    /// base frame to the laser's. `None` otherwise, including DP-SLAM
    /// logs (the release assumes 0.40 m forward, which the log does not say).
    pub fn sensor_offset(&self) -> Option<Pose2> {
        match &self.input {
            Input::Text(t) => match &t.parser {
                Parser::Carmen(c) => c.sensor_offset(),
                Parser::DpSlam(_) => None,
            },
            Input::Bag(b) => b.sensor_offset(),
        }
    }

    fn next_scan(&mut self) -> Result<Option<LaserScan2d>> {
        let t = match &mut self.input {
            Input::Bag(b) => return b.next().transpose(),
            Input::Text(t) => t,
        };
        if let Some((n, line)) = t.pending.take()
            && let Some(s) = parse(&mut t.parser, &self.path, n, &line)?
        {
            return Ok(Some(s));
        }
        // Disjoint field borrows: the line lives in the source's buffer.
        while let Some((n, line)) = t.src.next_line()? {
            if let Some(s) = parse(&mut t.parser, &self.path, n, line)? {
                return Ok(Some(s));
            }
        }
        if let Parser::Carmen(c) = &t.parser {
            c.finish(&self.path)?;
        }
        if self.scans_read == 0 {
            return Err(Error::in_file(
                &self.path,
                "no laser scans (no FLASER, ROBOTLASER1, RAWLASER or Laser line)",
            ));
        }
        Ok(None)
    }
}

fn parse(
    parser: &mut Parser,
    path: &Path,
    line_no: usize,
    line: &str,
) -> Result<Option<LaserScan2d>> {
    match parser {
        Parser::Carmen(c) => c.parse_line(path, line_no, line),
        Parser::DpSlam(d) => d.parse_line(path, line_no, line),
    }
}

impl Iterator for LogReader2d {
    type Item = Result<LaserScan2d>;

    fn next(&mut self) -> Option<Self::Item> {
        if self.done {
            return None;
        }
        match self.next_scan() {
            Ok(Some(s)) => {
                self.scans_read += 1;
                Some(Ok(s))
            }
            Ok(None) => {
                self.done = true;
                None
            }
            Err(e) => {
                self.done = true;
                Some(Err(e))
            }
        }
    }
}

impl std::iter::FusedIterator for LogReader2d {}

#[cfg(test)]
mod tests {
    use super::*;
    use std::io::Write;

    fn write(dir: &Path, name: &str, text: &str) -> PathBuf {
        let p = dir.join(name);
        std::fs::write(&p, text).unwrap();
        p
    }

    #[test]
    fn detects_format_and_keeps_the_detection_line() {
        let dir = tempfile::tempdir().unwrap();
        let d = write(
            dir.path(),
            "a.log",
            "\n# note\nOdometry 1 2 0.5\nLaser 3 1 2 3\nOdometry 2 2 0.5\nLaser 3 1 2 3\n",
        );
        let r = open_log2d(&d).unwrap();
        assert_eq!(r.format(), LogFormat::DpSlam);
        let scans: Vec<_> = r.collect::<Result<_>>().unwrap();
        assert_eq!(scans.len(), 2);
        assert_eq!((scans[0].line, scans[1].line), (4, 6));

        // The first data line is itself a scan: it must not be lost.
        let c = write(dir.path(), "b.clf", "FLASER 2 1 2 0 0 0 0 0 0 1.5 h 1.5\n");
        let mut r = open_log2d(&c).unwrap();
        assert_eq!(r.format(), LogFormat::Carmen);
        assert_eq!(r.next().unwrap().unwrap().timestamp, Some(1.5));
        assert!(r.next().is_none());
        assert_eq!(r.scans_read(), 1);
        assert!(r.bytes_read() > 0 && r.bytes_read() == r.total_bytes());
    }

    #[test]
    fn logs_without_scans_are_errors_naming_the_file() {
        let dir = tempfile::tempdir().unwrap();
        for (name, text) in [("empty.clf", ""), ("comments.clf", "# a\n\n  # b\n")] {
            let p = write(dir.path(), name, text);
            let e = open_log2d(&p)
                .err()
                .expect("no scans must be an error")
                .to_string();
            assert!(e.contains(name) && e.contains("no laser scans"), "{e}");
        }
        let p = write(
            dir.path(),
            "odom.clf",
            "PARAM a 1 0 h 0\nODOM 0 0 0 0 0 0 1 h 1\n",
        );
        let mut r = open_log2d(&p).unwrap();
        let e = r.next().unwrap().unwrap_err().to_string();
        assert!(
            e.contains("odom.clf") && e.contains("no laser scans"),
            "{e}"
        );
        assert!(r.next().is_none(), "the iterator ends after an error");
    }

    #[test]
    fn iteration_stops_at_the_first_error() {
        let dir = tempfile::tempdir().unwrap();
        let p = write(
            dir.path(),
            "e.log",
            "Odometry 0 0 0\nLaser 2 1 2\nLaser 3 1 2\nLaser 2 1 2\n",
        );
        let mut r = open_log2d(&p).unwrap();
        assert!(r.next().unwrap().is_ok());
        let e = r.next().unwrap().unwrap_err().to_string();
        assert!(
            e.contains("e.log:line 3") && e.contains("declares 3 readings"),
            "{e}"
        );
        assert!(r.next().is_none());
    }

    #[test]
    fn reads_gzip_transparently() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("z.log");
        let mut e = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::default());
        for i in 0..100 {
            writeln!(e, "ODOM {i} 0 0 0 0 0 {i}.5 h 0").unwrap();
            writeln!(e, "FLASER 3 1 2 3 {i} 0 0 {i} 0 0 {i}.5 h 0").unwrap();
        }
        std::fs::write(&p, e.finish().unwrap()).unwrap();
        let scans: Vec<_> = open_log2d(&p).unwrap().collect::<Result<_>>().unwrap();
        assert_eq!(scans.len(), 100);
        assert_eq!(scans[99].timestamp, Some(99.5));
        assert_eq!(scans[99].line, 200);
    }
}
