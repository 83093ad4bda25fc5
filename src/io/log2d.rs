//! One streaming reader for 2-D laser logs, CARMEN or DP-SLAM, plain or gzip,
//! and ROS bags ([`crate::io::bag`]).
//!
//! The format is told from the first line that is neither empty nor a `#`
//! comment: `Odometry` or `Laser` means the DP-SLAM format
//! ([`crate::io::dpslam_log`]), anything else CARMEN ([`crate::io::carmen`]).
//! Scans are parsed one line at a time, so memory does not grow with the
//! length of the log (apart from the odometry track of a re-timed CARMEN
//! log, 64 bytes per ODOM message, as a bag's).
//!
//! **Odometry of CARMEN logs.** A FLASER line carries the odometry the
//! robot's logger paired with the scan, often the latest ODOM message, up
//! to one odometry period (0.1–0.25 s) older than the scan; that is what
//! the reader gives by default. With [`OdometryPairing::Retimed`], where a
//! log's laser lines were paired from its own ODOM stream
//! ([`retiming_track`] decides), each scan's odometry is re-taken as that
//! stream interpolated at the scan's time stamp, as a bag's is
//! ([`crate::io::odometry`]), if the logged pairing lies on the stream's
//! path around that stamp (else stamp and pairing disagree by more than an
//! odometry period, and the line is kept).

use crate::geometry::Pose2;
use crate::io::bag::scans2d::{BagScans2d, TopicChoice};
use crate::io::carmen::CarmenParser;
use crate::io::carmen::{CarmenRecord, parse_record};
use crate::io::dpslam_log::{DpSlamParser, is_dpslam_keyword};
use crate::io::odometry::{Track, planar, spatial};
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

/// Which odometry a CARMEN log's scans get. The `[input]` section's
/// `odometry` key.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum OdometryPairing {
    /// Each laser line's own odometry, as the robot's logger paired it.
    #[default]
    Logged,
    /// The log's ODOM stream interpolated at each scan's time stamp, where
    /// [`retiming_track`] finds the laser lines paired from that stream
    /// and the line's own pairing lies on the stream's path around its
    /// stamp; else each line's own. Not the default: on ACES and fr079 it
    /// did not map better (docs/PROPOSAL-2D.md, "Beam angles of converted
    /// bags, and re-timed CARMEN odometry").
    Retimed,
}

/// Whether a CARMEN log's scans are re-timed ([`OdometryPairing`]).
enum Retime {
    /// Not decided yet: decided on the first scan.
    Pending,
    Off,
    On(Box<Track>),
}

/// Fraction of a log's scans whose logged odometry must lie on the ODOM
/// path around their stamp for the log to count as paired from it. Raw
/// logs: 99.7 % (ACES, 24 of 7374 off), 99.6 % (fr079); corrected logs,
/// whose FLASER poses are a SLAM result while ODOM is the raw odometry:
/// 0–61 %.
const PAIRED_SHARE: f64 = 0.95;
/// "On the path": within 1 cm and 0.02 rad of the pose interpolated
/// somewhere between the ODOM messages just before and after the stamp.
const ON_PATH_M: f64 = 0.01;
const ON_PATH_RAD: f64 = 0.02;

fn ns(t: f64) -> i64 {
    (t * 1e9).round() as i64
}

/// The ODOM stream of the CARMEN log at `path`, when its laser lines'
/// odometry was paired from it: at least 10 scans with ODOM messages on
/// both sides and ≥ 95 % of them lying on the path between those two
/// messages (within 1 cm, 0.02 rad). `None` otherwise: no ODOM lines, too
/// few scans, or poses from elsewhere (corrected logs). Reading stops at
/// the first malformed line (the scan pass reports it).
pub fn retiming_track(path: &Path) -> Result<Option<Track>> {
    let mut src = TextSource::open(path)?;
    let mut odom: Vec<(f64, Pose2)> = Vec::new();
    let mut scans: Vec<(f64, Pose2)> = Vec::new();
    while let Ok(Some((n, line))) = src.next_line() {
        match parse_record(line, n, f64::INFINITY) {
            Ok(CarmenRecord::Odom {
                pose,
                timestamp: Some(t),
            }) => odom.push((t, pose)),
            Ok(CarmenRecord::Flaser(s) | CarmenRecord::RobotLaser(s)) => {
                if let Some(t) = s.timestamp {
                    scans.push((t, s.odometry));
                }
            }
            Ok(_) => {}
            Err(_) => break,
        }
    }
    odom.sort_by(|a, b| a.0.total_cmp(&b.0));
    let (mut checked, mut on_path) = (0usize, 0usize);
    for &(t, p) in &scans {
        let k = odom.partition_point(|o| o.0 <= t);
        if k == 0 || k == odom.len() {
            continue;
        }
        checked += 1;
        if lies_between(&p, &odom[k - 1].1, &odom[k].1) {
            on_path += 1;
        }
    }
    if checked < 10 || (on_path as f64) < PAIRED_SHARE * checked as f64 {
        return Ok(None);
    }
    let mut track = Track::default();
    for (t, p) in odom {
        track.push(ns(t), spatial(&p));
    }
    Ok(Some(track))
}

/// Whether `p` is within [`ON_PATH_M`] and [`ON_PATH_RAD`] of the straight
/// interpolation from `a` to `b` at some fraction in [0, 1] (found by
/// projecting the position, or the heading where `a` and `b` share a
/// position).
fn lies_between(p: &Pose2, a: &Pose2, b: &Pose2) -> bool {
    let (pa, pb, pp) = (
        a.translation.vector,
        b.translation.vector,
        p.translation.vector,
    );
    let (ta, tb, tp) = (a.rotation.angle(), b.rotation.angle(), p.rotation.angle());
    let turn = crate::geometry::wrap_angle(tb - ta);
    let d = pb - pa;
    let by_position = if d.norm_squared() > 0.0 {
        (pp - pa).dot(&d) / d.norm_squared()
    } else {
        0.0
    };
    let by_heading = if turn != 0.0 {
        crate::geometry::wrap_angle(tp - ta) / turn
    } else {
        0.0
    };
    [by_position, by_heading].into_iter().any(|s| {
        let s = s.clamp(0.0, 1.0);
        let xy = pa + d * s;
        let th = ta + turn * s;
        (pp - xy).norm() <= ON_PATH_M && crate::geometry::wrap_angle(tp - th).abs() <= ON_PATH_RAD
    })
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
    retime: Retime,
    /// `(angle_min, angle_increment)` in radians replacing the input's, each
    /// where set ([`LogReader2d::with_beam_angles`]).
    beam_angles: (Option<f64>, Option<f64>),
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
            retime: Retime::Off,
            beam_angles: (None, None),
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
        retime: Retime::Off,
        beam_angles: (None, None),
    })
}

impl LogReader2d {
    /// Chooses the odometry of a CARMEN log's scans (default
    /// [`OdometryPairing::Logged`]); no effect on other formats. Call
    /// before the first scan.
    pub fn with_odometry(mut self, pairing: OdometryPairing) -> Self {
        self.retime = match (pairing, self.format) {
            (OdometryPairing::Retimed, LogFormat::Carmen) => Retime::Pending,
            _ => Retime::Off,
        };
        self
    }

    /// Replaces the scans' stated beam geometry: `angle_min` and
    /// `angle_increment` in radians (laser frame, counter-clockwise), each
    /// where `Some`, for recordings whose stated angles are a converter's
    /// guess (`laser.angle_min_deg`, `laser.angle_increment_deg`).
    pub fn with_beam_angles(
        mut self,
        angle_min: Option<f64>,
        angle_increment: Option<f64>,
    ) -> Self {
        self.beam_angles = (angle_min, angle_increment);
        self
    }

    /// Whether the scans' odometry is re-timed from the log's ODOM stream
    /// (decided when the first scan is read; `false` before).
    pub fn retimed(&self) -> bool {
        matches!(self.retime, Retime::On(_))
    }

    /// Re-takes `s`'s odometry from the ODOM stream at its stamp, moving
    /// the logged laser pose with it, where the logged odometry lies on the
    /// stream's path around that stamp. Elsewhere the logger's pairing is
    /// kept: there the stamp and the pairing disagree by more than an
    /// odometry period, and either may be wrong (fr079: 21 of 4934 scans,
    /// whose poses match the ODOM stream 0.2–0.5 s after their stamps;
    /// ACES: 25 of 7374, 0.1–0.2 s before).
    fn retimed_scan(&mut self, mut s: LaserScan2d) -> Result<LaserScan2d> {
        if matches!(self.retime, Retime::Pending) {
            self.retime = match retiming_track(&self.path)? {
                Some(t) => Retime::On(Box::new(t)),
                None => Retime::Off,
            };
        }
        if let (Retime::On(track), Some(t)) = (&self.retime, s.timestamp)
            && let Some((a, b)) = track.around(ns(t))
            && lies_between(&s.odometry, &planar(&a), &planar(&b))
            && let Some(p) = track.at(ns(t))
        {
            let odo = planar(&p);
            s.logged_pose = s.logged_pose.map(|lp| odo * (s.odometry.inverse() * lp));
            s.odometry = odo;
        }
        Ok(s)
    }

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
        match self
            .next_scan()
            .and_then(|s| s.map(|s| self.retimed_scan(s)).transpose())
        {
            Ok(Some(mut s)) => {
                self.scans_read += 1;
                s.angle_min = self.beam_angles.0.unwrap_or(s.angle_min);
                s.angle_increment = self.beam_angles.1.unwrap_or(s.angle_increment);
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
    fn beam_angle_overrides_replace_the_stated_ones_each_where_set() {
        let dir = tempfile::tempdir().unwrap();
        let c = write(dir.path(), "b.clf", "FLASER 2 1 2 0 0 0 0 0 0 1.5 h 1.5\n");
        let stated = open_log2d(&c).unwrap().next().unwrap().unwrap();
        let half_pi = std::f64::consts::FRAC_PI_2;
        assert!((stated.angle_min + half_pi).abs() < 1e-12);
        let inc = open_log2d(&c)
            .unwrap()
            .with_beam_angles(None, Some(0.01))
            .next()
            .unwrap()
            .unwrap();
        assert_eq!(
            (inc.angle_min, inc.angle_increment),
            (stated.angle_min, 0.01)
        );
        let both = open_log2d(&c)
            .unwrap()
            .with_beam_angles(Some(-1.0), Some(0.02))
            .next()
            .unwrap()
            .unwrap();
        assert_eq!((both.angle_min, both.angle_increment), (-1.0, 0.02));
        assert_eq!(both.ranges, stated.ranges, "ranges untouched");
    }

    /// A robot driving along x at 1 m/s: ODOM at 10 Hz (t = 0.0, 0.1, …),
    /// scans at t = k·0.1 + 0.05 paired with the latest ODOM (as ACES'
    /// logger did), or with `pose(t)` for scan `k` in `odd`.
    fn raw_log(odd: &[(usize, f64)]) -> String {
        let mut s = String::new();
        for k in 0..40 {
            let t = k as f64 * 0.1;
            s += &format!("ODOM {t} 0 0 1 0 0 {t} h {t}\n");
            let ts = t + 0.05;
            let x = odd.iter().find(|o| o.0 == k).map_or(t, |o| o.1);
            s += &format!("FLASER 2 1 1 {x} 0 0 {x} 0 0 {ts} h {ts}\n");
        }
        s
    }

    fn odometry_x(path: &Path, pairing: OdometryPairing) -> (Vec<f64>, bool) {
        let mut r = open_log2d(path).unwrap().with_odometry(pairing);
        let xs = r
            .by_ref()
            .map(|s| s.unwrap().odometry.translation.x)
            .collect();
        (xs, r.retimed())
    }

    #[test]
    fn raw_logs_odometry_is_re_timed_to_the_scans_stamps() {
        let dir = tempfile::tempdir().unwrap();
        // Scan 7 paired with the pose 0.3 s after its stamp: off the path
        // between the ODOM messages around its stamp, so kept.
        let raw = write(dir.path(), "raw.clf", &raw_log(&[(7, 1.0)]));
        let (xs, retimed) = odometry_x(&raw, OdometryPairing::Retimed);
        assert!(retimed);
        for (k, x) in xs.iter().enumerate().take(39) {
            let want = if k == 7 { 1.0 } else { k as f64 * 0.1 + 0.05 };
            assert!((x - want).abs() < 1e-9, "scan {k}: {x} vs {want}");
        }
        // The last scan is after the last ODOM: kept as logged.
        assert!((xs[39] - 3.9).abs() < 1e-9);
        let (xs, retimed) = odometry_x(&raw, OdometryPairing::Logged);
        assert!(!retimed);
        assert!((xs[3] - 0.3).abs() < 1e-12);
        // Poses from elsewhere on most lines (a corrected log): all kept.
        let odd: Vec<(usize, f64)> = (0..40).map(|k| (k, k as f64 * 0.1 + 0.5)).collect();
        let corrected = write(dir.path(), "corrected.clf", &raw_log(&odd));
        let (xs, retimed) = odometry_x(&corrected, OdometryPairing::Retimed);
        assert!(!retimed);
        assert!((xs[3] - 0.8).abs() < 1e-12);
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
