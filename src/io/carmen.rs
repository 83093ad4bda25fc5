//! CARMEN log format (`.clf`, `.log`): parsing line by line, and writing.
//!
//! Supported messages (metres, radians, seconds):
//!
//! ```text
//! FLASER n r_1 … r_n  x y theta  odom_x odom_y odom_theta  ipc_timestamp hostname logger_timestamp
//! ROBOTLASER1 type start_angle fov resolution max_range accuracy remission_mode
//!             n r_1 … r_n  m e_1 … e_m  laser_x laser_y laser_theta  robot_x robot_y robot_theta
//!             tv rv forward_safety_dist side_safety_dist turn_axis  ipc_timestamp hostname logger_timestamp
//! RAWLASER1..4 type start_angle fov resolution max_range accuracy remission_mode
//!             n r_1 … r_n  m e_1 … e_m  ipc_timestamp hostname logger_timestamp
//! ODOM x y theta tv rv accel ipc_timestamp hostname logger_timestamp
//! PARAM name value ipc_timestamp hostname logger_timestamp
//! # comment
//! ```
//!
//! The old FLASER form without the three trailing time/host fields is also
//! accepted (its scans have no time stamp). Other message types (NEFF, RLASER,
//! TRUEPOS, SYNC, …) are skipped.
//!
//! Conventions, as produced by the CARMEN logger:
//! - FLASER beams start at −π/2; odd `n` steps by π/(n−1) (181 → 1°,
//!   361 → 0.5°, last beam at +π/2), even `n` by π/n (180 → 1°, 360 → 0.5°).
//! - FLASER `x y theta` is the **laser** pose, `odom_*` the robot's odometry.
//!   [`LaserScan2d::logged_pose`] takes the former (the reference pose in
//!   corrected logs), [`LaserScan2d::odometry`] the latter.
//! - ROBOTLASER1 carries the laser pose and the robot pose separately: the
//!   robot pose becomes the odometry, the laser pose the logged pose, and
//!   [`CarmenParser::sensor_offset`] gives the laser in the robot frame.
//! - RAWLASERk carries no pose: it is paired with the latest `ODOM` pose (no
//!   interpolation).
//! - FLASER has no max-range field: `PARAM laser_front_laser_max_range`, else
//!   `PARAM robot_front_laser_max`, else [`FLASER_DEFAULT_MAX_RANGE`] is used.
//!   Readings at or above it, and NaN/±inf readings, are "no return".

use crate::geometry::{Pose2, pose2, xyt};
use crate::scan::LaserScan2d;
use crate::{Error, Result};
use std::f64::consts::{FRAC_PI_2, PI};
use std::fmt::Write as _;
use std::path::Path;

/// Max range (m) of FLASER readings when the log sets none by PARAM: SICK
/// logs write 81.91 for "no return".
pub const FLASER_DEFAULT_MAX_RANGE: f64 = 81.9;

/// Fields after the FLASER ranges: two poses, ipc time, host, logger time.
const FLASER_TAIL: usize = 9;
/// Fields after the ranges of the old FLASER form: two poses only.
const FLASER_OLD_TAIL: usize = 6;
/// Fields after the remissions of ROBOTLASER1: two poses, tv, rv, two safety
/// distances, turn axis, ipc time, host, logger time.
const ROBOTLASER_TAIL: usize = 14;
/// Fields after the remissions of RAWLASERk: ipc time, host, logger time.
const RAWLASER_TAIL: usize = 3;

/// Beam geometry implied by a FLASER reading count: `(angle_min, increment)`
/// in radians, in the laser frame (0 = forward, counter-clockwise positive).
///
/// Odd `n` covers −π/2…+π/2 inclusive, even `n` covers −π/2…+π/2 − π/n. A
/// single beam points at −π/2 (its increment is reported as π, never used).
pub fn flaser_geometry(n: usize) -> (f64, f64) {
    let inc = if n <= 1 {
        PI
    } else if n % 2 == 1 {
        PI / (n - 1) as f64
    } else {
        PI / n as f64
    };
    (-FRAC_PI_2, inc)
}

/// Whether `scan`'s beam angles are the ones a FLASER line of its length
/// implies (so [`format_flaser`] loses no geometry). Tolerance 1e-9 rad.
pub fn is_flaser_geometry(scan: &LaserScan2d) -> bool {
    let (a0, inc) = flaser_geometry(scan.ranges.len());
    (scan.angle_min - a0).abs() < 1e-9
        && (scan.ranges.len() <= 1 || (scan.angle_increment - inc).abs() < 1e-9)
}

/// One parsed CARMEN line.
#[derive(Debug, Clone, PartialEq)]
pub enum CarmenRecord {
    /// A FLASER scan, complete (odometry and logged laser pose from the line).
    Flaser(LaserScan2d),
    /// A ROBOTLASER1 scan: `odometry` is the robot pose, `logged_pose` the
    /// laser pose, both in the odometry frame.
    RobotLaser(LaserScan2d),
    /// A RAWLASERk scan (`index` = k, 1..=4). Its `odometry` is the identity
    /// and `logged_pose` is `None` until paired with an `ODOM` pose.
    RawLaser {
        /// Laser number k of `RAWLASERk`.
        index: u8,
        /// The scan, without pose.
        scan: LaserScan2d,
    },
    /// An ODOM message: robot pose in the odometry frame and its time stamp
    /// (s; `None` in the old 6-field form).
    Odom {
        /// Robot pose (m, m, rad) in the odometry frame.
        pose: Pose2,
        /// ipc time stamp (s).
        timestamp: Option<f64>,
    },
    /// A PARAM line: name and (first token of the) value, verbatim.
    Param {
        /// Parameter name, e.g. `robot_front_laser_max`.
        name: String,
        /// Parameter value as written.
        value: String,
    },
    /// A comment, an empty line or a message type this reader does not use.
    Skipped,
}

/// Parses a float field; `finite` rejects NaN and ±inf (poses, times).
fn num(tok: Option<&str>, what: &str, finite: bool) -> std::result::Result<f64, String> {
    let v = crate::io::source::parse_f64(tok, what)?;
    if finite && !v.is_finite() {
        return Err(format!("{what} is not finite ({v})"));
    }
    Ok(v)
}

/// Parses a non-negative count field.
fn count(tok: Option<&str>, what: &str) -> std::result::Result<usize, String> {
    let t = tok.ok_or_else(|| format!("missing {what}"))?;
    let v: i64 = t
        .parse()
        .map_err(|_| format!("{what} '{t}' is not an integer"))?;
    usize::try_from(v).map_err(|_| format!("{what} {v} is negative"))
}

/// Parses the range tokens; NaN and ±inf are valid readings ("no return").
fn ranges(toks: &[&str]) -> std::result::Result<Vec<f64>, String> {
    toks.iter()
        .enumerate()
        .map(|(i, t)| {
            t.parse::<f64>()
                .map_err(|_| format!("range reading {}: '{t}' is not a number", i + 1))
        })
        .collect()
}

/// Parses three finite pose fields named `<prefix>x`, `<prefix>y`, `<prefix>theta`.
fn pose_fields(toks: &[&str], prefix: &str) -> std::result::Result<Pose2, String> {
    let x = num(toks.first().copied(), &format!("{prefix}x"), true)?;
    let y = num(toks.get(1).copied(), &format!("{prefix}y"), true)?;
    let t = num(toks.get(2).copied(), &format!("{prefix}theta"), true)?;
    Ok(pose2(x, y, t))
}

/// Parses one CARMEN line (without its terminator) into a record.
///
/// `line_no` (1-based) goes into the scan's [`LaserScan2d::line`];
/// `flaser_max_range` (m) is the max range given to FLASER scans (the other
/// laser messages carry their own). On failure returns the reason, naming the
/// message and the field, for the caller to attach file and line.
pub fn parse_record(
    line: &str,
    line_no: usize,
    flaser_max_range: f64,
) -> std::result::Result<CarmenRecord, String> {
    let toks: Vec<&str> = line.split_ascii_whitespace().collect();
    let Some(&kind) = toks.first() else {
        return Ok(CarmenRecord::Skipped);
    };
    if kind.starts_with('#') {
        return Ok(CarmenRecord::Skipped);
    }
    match kind {
        "FLASER" => parse_flaser(&toks, line_no, flaser_max_range).map(CarmenRecord::Flaser),
        "ROBOTLASER1" => parse_robotlaser(&toks, line_no).map(CarmenRecord::RobotLaser),
        "RAWLASER1" | "RAWLASER2" | "RAWLASER3" | "RAWLASER4" => {
            let index = kind.as_bytes()[8] - b'0';
            parse_rawlaser(&toks, line_no).map(|scan| CarmenRecord::RawLaser { index, scan })
        }
        "ODOM" => {
            // ODOM x y theta tv rv accel [ipc_timestamp hostname logger_timestamp]
            if toks.len() != 7 && toks.len() != 10 {
                return Err(format!(
                    "ODOM has {} fields after the message name, expected 9 (or 6 in the old form)",
                    toks.len() - 1
                ));
            }
            let pose = pose_fields(&toks[1..4], "")?;
            for (i, what) in [(4, "tv"), (5, "rv"), (6, "accel")] {
                num(toks.get(i).copied(), what, false)?;
            }
            let timestamp = if toks.len() == 10 {
                let t = num(toks.get(7).copied(), "ipc_timestamp", true)?;
                num(toks.get(9).copied(), "logger_timestamp", false)?;
                Some(t)
            } else {
                None
            };
            Ok(CarmenRecord::Odom { pose, timestamp })
        }
        "PARAM" => {
            let name = toks.get(1).ok_or("PARAM without a name")?;
            let value = toks
                .get(2)
                .ok_or_else(|| format!("PARAM {name} without a value"))?;
            Ok(CarmenRecord::Param {
                name: name.to_string(),
                value: value.to_string(),
            })
        }
        _ => Ok(CarmenRecord::Skipped),
    }
}

fn parse_flaser(
    toks: &[&str],
    line_no: usize,
    max_range: f64,
) -> std::result::Result<LaserScan2d, String> {
    let n = count(toks.get(1).copied(), "FLASER reading count")?;
    let rest = &toks[2..];
    // The old form has 6 numeric fields after the ranges; the current one 9,
    // of which the second-to-last is a host name. A line that is short by
    // three readings must not pass for the old form, hence the numeric check.
    let tail = if rest.len() == n.saturating_add(FLASER_TAIL) {
        FLASER_TAIL
    } else if rest.len() == n.saturating_add(FLASER_OLD_TAIL)
        && rest[rest.len() - 2].parse::<f64>().is_ok()
    {
        FLASER_OLD_TAIL
    } else if rest.len() >= FLASER_TAIL {
        return Err(format!(
            "FLASER declares {n} readings but the line has {} values",
            rest.len() - FLASER_TAIL
        ));
    } else {
        return Err(format!(
            "FLASER declares {n} readings but the line has only {} fields after the count",
            rest.len()
        ));
    };
    let ranges = ranges(&rest[..n])?;
    let t = &rest[n..];
    let logged = pose_fields(&t[0..3], "")?;
    let odom = pose_fields(&t[3..6], "odom_")?;
    let timestamp = if tail == FLASER_TAIL {
        let ts = num(t.get(6).copied(), "ipc_timestamp", true)?;
        num(t.get(8).copied(), "logger_timestamp", false)?;
        Some(ts)
    } else {
        None
    };
    let (angle_min, angle_increment) = flaser_geometry(n);
    Ok(LaserScan2d {
        timestamp,
        odometry: odom,
        logged_pose: Some(logged),
        ranges,
        angle_min,
        angle_increment,
        max_range,
        line: line_no,
    })
}

/// The laser header shared by ROBOTLASER1 and RAWLASERk: fields 1..=7, then
/// the counted ranges and remissions, then `tail` fields. Returns the scan
/// with identity odometry and no pose or time stamp, for the caller to fill.
fn parse_laser_body(
    toks: &[&str],
    line_no: usize,
    tail: usize,
) -> std::result::Result<LaserScan2d, String> {
    let kind = toks[0];
    num(toks.get(1).copied(), "laser_type", false)?;
    let angle_min = num(toks.get(2).copied(), "start_angle", true)?;
    num(toks.get(3).copied(), "field_of_view", true)?;
    let angle_increment = num(toks.get(4).copied(), "angular_resolution", true)?;
    let max_range = num(toks.get(5).copied(), "maximum_range", true)?;
    if max_range <= 0.0 {
        return Err(format!("maximum_range {max_range} is not positive"));
    }
    num(toks.get(6).copied(), "accuracy", false)?;
    num(toks.get(7).copied(), "remission_mode", false)?;
    let n = count(toks.get(8).copied(), &format!("{kind} reading count"))?;
    let after_ranges = 9usize.saturating_add(n);
    if toks.len() <= after_ranges {
        return Err(format!(
            "{kind} declares {n} readings but the line has only {} values after the count",
            toks.len().saturating_sub(9)
        ));
    }
    let m = count(toks.get(after_ranges).copied(), "remission count")?;
    let expected = after_ranges
        .saturating_add(1)
        .saturating_add(m)
        .saturating_add(tail);
    if toks.len() != expected {
        return Err(format!(
            "{kind} declares {n} readings and {m} remissions, so the line should have {expected} fields, but it has {}",
            toks.len()
        ));
    }
    let ranges = ranges(&toks[9..after_ranges])?;
    Ok(LaserScan2d {
        timestamp: None,
        odometry: Pose2::identity(),
        logged_pose: None,
        ranges,
        angle_min,
        angle_increment,
        max_range,
        line: line_no,
    })
}

fn parse_robotlaser(toks: &[&str], line_no: usize) -> std::result::Result<LaserScan2d, String> {
    let mut scan = parse_laser_body(toks, line_no, ROBOTLASER_TAIL)?;
    let t = &toks[toks.len() - ROBOTLASER_TAIL..];
    scan.logged_pose = Some(pose_fields(&t[0..3], "laser_pose_")?);
    scan.odometry = pose_fields(&t[3..6], "robot_pose_")?;
    for (i, what) in [
        (6, "tv"),
        (7, "rv"),
        (8, "forward_safety_dist"),
        (9, "side_safety_dist"),
        (10, "turn_axis"),
    ] {
        num(t.get(i).copied(), what, false)?;
    }
    scan.timestamp = Some(num(t.get(11).copied(), "ipc_timestamp", true)?);
    num(t.get(13).copied(), "logger_timestamp", false)?;
    Ok(scan)
}

fn parse_rawlaser(toks: &[&str], line_no: usize) -> std::result::Result<LaserScan2d, String> {
    let mut scan = parse_laser_body(toks, line_no, RAWLASER_TAIL)?;
    let t = &toks[toks.len() - RAWLASER_TAIL..];
    scan.timestamp = Some(num(t.first().copied(), "ipc_timestamp", true)?);
    num(t.get(2).copied(), "logger_timestamp", false)?;
    Ok(scan)
}

/// Which laser message a CARMEN stream delivers.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum LaserKind {
    Flaser,
    RobotLaser,
    Raw(u8),
}

/// Stateful CARMEN reader: applies PARAM max ranges, pairs RAWLASERk with
/// the latest ODOM, and keeps one laser stream.
///
/// Loggers often write the same sensor twice (e.g. ROBOTLASER1 and RAWLASER1,
/// or FLASER and ROBOTLASER1), and a [`LaserScan2d`] has no sensor id, so the
/// first laser message type in the file (FLASER, ROBOTLASER1 or one RAWLASERk)
/// is the one delivered; other laser types are counted in
/// [`CarmenParser::skipped_lasers`] and dropped.
///
/// RAWLASERk scans before the first ODOM have no odometry and are dropped
/// (counted in [`CarmenParser::unpaired_raw`]); if the file ends without any
/// ODOM while raw scans were seen, [`CarmenParser::finish`] reports it.
#[derive(Debug, Clone, Default)]
pub struct CarmenParser {
    laser_max: Option<f64>,
    robot_max: Option<f64>,
    last_odom: Option<Pose2>,
    kind: Option<LaserKind>,
    first_unpaired_line: Option<usize>,
    unpaired_raw: usize,
    skipped_lasers: usize,
    sensor_offset: Option<Pose2>,
    frontlaser_offset: Option<f64>,
}

impl CarmenParser {
    /// A parser with no PARAM or ODOM seen yet.
    pub fn new() -> Self {
        Self::default()
    }

    /// Max range (m) currently given to FLASER scans.
    pub fn flaser_max_range(&self) -> f64 {
        self.laser_max
            .or(self.robot_max)
            .unwrap_or(FLASER_DEFAULT_MAX_RANGE)
    }

    /// The laser pose in the robot frame (m, m, rad): from the latest
    /// ROBOTLASER1 (laser pose relative to robot pose), else from
    /// `PARAM robot_frontlaser_offset` (metres forward), else `None` (FLASER
    /// logs write the laser pose only, and the offset is unknown).
    pub fn sensor_offset(&self) -> Option<Pose2> {
        self.sensor_offset
            .or_else(|| self.frontlaser_offset.map(|d| pose2(d, 0.0, 0.0)))
    }

    /// RAWLASERk scans dropped because no ODOM had been seen before them.
    pub fn unpaired_raw(&self) -> usize {
        self.unpaired_raw
    }

    /// Laser messages dropped because they are not of the stream's type.
    pub fn skipped_lasers(&self) -> usize {
        self.skipped_lasers
    }

    /// Parses one line of `path` (1-based `line_no`); returns the scan it
    /// completes, if any. Errors name the file, the line and the reason.
    pub fn parse_line(
        &mut self,
        path: &Path,
        line_no: usize,
        line: &str,
    ) -> Result<Option<LaserScan2d>> {
        let rec = parse_record(line, line_no, self.flaser_max_range())
            .map_err(|r| Error::at_line(path, line_no, r))?;
        let (kind, scan) = match rec {
            CarmenRecord::Skipped => return Ok(None),
            CarmenRecord::Odom { pose, .. } => {
                self.last_odom = Some(pose);
                return Ok(None);
            }
            CarmenRecord::Param { name, value } => {
                let slot = match name.as_str() {
                    "laser_front_laser_max_range" => &mut self.laser_max,
                    "robot_front_laser_max" => &mut self.robot_max,
                    "robot_frontlaser_offset" => {
                        let v = value.parse::<f64>().ok().filter(|v| v.is_finite());
                        self.frontlaser_offset = Some(v.ok_or_else(|| {
                            Error::at_line(
                                path,
                                line_no,
                                format!("PARAM {name}: '{value}' is not a finite number"),
                            )
                        })?);
                        return Ok(None);
                    }
                    _ => return Ok(None),
                };
                let v = value
                    .parse::<f64>()
                    .ok()
                    .filter(|v| v.is_finite() && *v > 0.0);
                *slot = Some(v.ok_or_else(|| {
                    Error::at_line(
                        path,
                        line_no,
                        format!("PARAM {name}: '{value}' is not a positive number"),
                    )
                })?);
                return Ok(None);
            }
            CarmenRecord::Flaser(s) => (LaserKind::Flaser, s),
            CarmenRecord::RobotLaser(s) => (LaserKind::RobotLaser, s),
            CarmenRecord::RawLaser { index, scan } => (LaserKind::Raw(index), scan),
        };
        if *self.kind.get_or_insert(kind) != kind {
            self.skipped_lasers += 1;
            return Ok(None);
        }
        let mut scan = scan;
        match kind {
            LaserKind::Flaser => {}
            LaserKind::RobotLaser => {
                if let Some(lp) = scan.logged_pose {
                    self.sensor_offset = Some(scan.odometry.inverse() * lp);
                }
            }
            LaserKind::Raw(_) => match self.last_odom {
                Some(o) => scan.odometry = o,
                None => {
                    self.unpaired_raw += 1;
                    self.first_unpaired_line.get_or_insert(line_no);
                    return Ok(None);
                }
            },
        }
        Ok(Some(scan))
    }

    /// Checks the end-of-file state: raw laser scans but never an ODOM is an
    /// error (naming the first such scan's line), since none could be used.
    pub fn finish(&self, path: &Path) -> Result<()> {
        match (self.first_unpaired_line, self.last_odom) {
            (Some(line), None) => Err(Error::at_line(
                path,
                line,
                format!(
                    "{} RAWLASER scans but no ODOM message in the file: no odometry to pair them with",
                    self.unpaired_raw
                ),
            )),
            _ => Ok(()),
        }
    }
}

/// Writes a range with millimetre precision. Non-finite readings (no return)
/// become the max range rounded up, so a reader applying "≥ max range" sees a
/// no-return; a finite reading below the max range is rounded down if
/// rounding would push it to the max range, so it stays a hit.
fn push_range(out: &mut String, r: f64, max_range: f64) {
    let v = if !r.is_finite() {
        (max_range * 1000.0).ceil() / 1000.0
    } else {
        let rounded = (r * 1000.0).round() / 1000.0;
        if r < max_range && rounded >= max_range {
            (r * 1000.0).floor() / 1000.0
        } else {
            r
        }
    };
    let _ = write!(out, " {v:.3}");
}

/// Formats `scan` as one FLASER line (no terminator) with host name `host`.
///
/// Ranges in metres with 3 decimals (see the no-return rule in the module
/// docs: non-finite readings are written as the max range, rounded up), poses
/// with 6 decimals (m, rad), `x y theta` = [`LaserScan2d::logged_pose`] (or
/// the odometry when `None`), `odom_*` = [`LaserScan2d::odometry`], both time
/// stamps = [`LaserScan2d::timestamp`] with 6 decimals (0 when `None`).
///
/// FLASER has no angle fields: readers infer them from the count
/// ([`flaser_geometry`]); check [`is_flaser_geometry`] first, or use
/// [`format_robotlaser1`]. The max range is not in the line either: write it
/// in the header ([`format_header`]).
pub fn format_flaser(scan: &LaserScan2d, host: &str) -> String {
    let mut s = String::with_capacity(16 + 7 * scan.ranges.len());
    let _ = write!(s, "FLASER {}", scan.ranges.len());
    for &r in &scan.ranges {
        push_range(&mut s, r, scan.max_range);
    }
    let (x, y, t) = xyt(&scan.logged_pose.unwrap_or(scan.odometry));
    let (ox, oy, ot) = xyt(&scan.odometry);
    let ts = scan.timestamp.unwrap_or(0.0);
    let _ = write!(
        s,
        " {x:.6} {y:.6} {t:.6} {ox:.6} {oy:.6} {ot:.6} {ts:.6} {host} {ts:.6}"
    );
    s
}

/// Formats `scan` as one ROBOTLASER1 line (no terminator): keeps any beam
/// geometry and the max range. Laser pose = [`LaserScan2d::logged_pose`] (or
/// the odometry when `None`), robot pose = the odometry; no remissions; laser
/// type 0, accuracy and velocities 0. Precision as in [`format_flaser`].
pub fn format_robotlaser1(scan: &LaserScan2d, host: &str) -> String {
    let n = scan.ranges.len();
    let fov = scan.angle_increment * n.saturating_sub(1) as f64;
    let mut s = String::with_capacity(64 + 7 * n);
    let _ = write!(
        s,
        "ROBOTLASER1 0 {:.9} {:.9} {:.9} {:.3} 0 0 {n}",
        scan.angle_min,
        fov,
        scan.angle_increment,
        (scan.max_range * 1000.0).ceil() / 1000.0
    );
    for &r in &scan.ranges {
        push_range(&mut s, r, scan.max_range);
    }
    let (x, y, t) = xyt(&scan.logged_pose.unwrap_or(scan.odometry));
    let (ox, oy, ot) = xyt(&scan.odometry);
    let ts = scan.timestamp.unwrap_or(0.0);
    let _ = write!(
        s,
        " 0 {x:.6} {y:.6} {t:.6} {ox:.6} {oy:.6} {ot:.6} 0 0 0 0 0 {ts:.6} {host} {ts:.6}"
    );
    s
}

/// A CARMEN header: comment lines describing the messages, then
/// `PARAM laser_front_laser_max_range` = `max_range` (m, written with 3
/// decimals rounded up, so readings at the limit stay "no return"). Each line
/// ends with `\n`.
pub fn format_header(max_range: f64, host: &str) -> String {
    let mut s = String::new();
    s.push_str("# CARMEN Logfile written by dpslam\n");
    s.push_str("# message formats defined: PARAM FLASER ROBOTLASER1\n");
    s.push_str(
        "# FLASER num_readings [range_readings] x y theta odom_x odom_y odom_theta ipc_timestamp ipc_hostname logger_timestamp\n",
    );
    s.push_str(&format_max_range_param(max_range, host));
    s.push('\n');
    s
}

/// One `PARAM laser_front_laser_max_range` line (no terminator), for logs
/// whose max range (m) changes after the header.
pub fn format_max_range_param(max_range: f64, host: &str) -> String {
    let v = (max_range * 1000.0).ceil() / 1000.0;
    format!("PARAM laser_front_laser_max_range {v:.3} 0.000000 {host} 0.000000")
}

#[cfg(test)]
mod tests {
    use super::*;

    fn flaser_line(n: i64, ranges: &str) -> String {
        format!("FLASER {n} {ranges} 1.5 -2 0.25 1.4 -2.1 0.2 1134864629.895182 b21 0.086295")
    }

    #[test]
    fn geometry_of_common_counts() {
        let deg = PI / 180.0;
        for (n, inc) in [(180, deg), (181, deg), (360, deg / 2.0), (361, deg / 2.0)] {
            let (a0, i) = flaser_geometry(n);
            assert!((a0 + FRAC_PI_2).abs() < 1e-15);
            assert!((i - inc).abs() < 1e-15, "n={n}");
        }
        // Odd counts end exactly at +90°.
        let (a0, i) = flaser_geometry(361);
        assert!((a0 + 360.0 * i - FRAC_PI_2).abs() < 1e-12);
        // Odd unusual counts work too.
        let (_, i) = flaser_geometry(5);
        assert!((i - PI / 4.0).abs() < 1e-15);
    }

    #[test]
    fn flaser_fields_and_no_return() {
        let line = flaser_line(3, "1.0 NaN 81.91");
        let CarmenRecord::Flaser(s) = parse_record(&line, 7, 81.9).unwrap() else {
            panic!("not a FLASER record");
        };
        assert_eq!(s.line, 7);
        assert_eq!(format!("{:.6}", s.timestamp.unwrap()), "1134864629.895182");
        assert_eq!(xyt(&s.logged_pose.unwrap()), (1.5, -2.0, 0.25));
        let (ox, oy, ot) = xyt(&s.odometry);
        assert!((ox - 1.4).abs() < 1e-12 && (oy + 2.1).abs() < 1e-12 && (ot - 0.2).abs() < 1e-12);
        assert_eq!(s.ranges[0], 1.0);
        assert!(s.ranges[1].is_nan());
        assert!(!s.is_no_return(0) && s.is_no_return(1) && s.is_no_return(2));
        assert!((s.angle_increment - FRAC_PI_2).abs() < 1e-15);
    }

    #[test]
    fn old_flaser_form_has_no_timestamp() {
        let CarmenRecord::Flaser(s) = parse_record("FLASER 2 1 2 0 0 0 0 0 0", 1, 81.9).unwrap()
        else {
            panic!()
        };
        assert_eq!(s.timestamp, None);
        assert_eq!(s.ranges, vec![1.0, 2.0]);
    }

    #[test]
    fn flaser_errors_name_the_reason() {
        let e = parse_record(&flaser_line(4, "1 2 3"), 1, 81.9).unwrap_err();
        assert_eq!(e, "FLASER declares 4 readings but the line has 3 values");
        // Short by exactly three: must not be taken for the old form.
        let e = parse_record(&flaser_line(5, "1 2"), 1, 81.9).unwrap_err();
        assert!(
            e.contains("declares 5 readings but the line has 2 values"),
            "{e}"
        );
        let e = parse_record(&flaser_line(2, "1 x"), 1, 81.9).unwrap_err();
        assert!(e.contains("range reading 2: 'x' is not a number"), "{e}");
        let e = parse_record(&flaser_line(-2, "1 2"), 1, 81.9).unwrap_err();
        assert!(e.contains("negative"), "{e}");
        let e = parse_record("FLASER 2 1 2 nan 0 0 0 0 0 5 h 5", 1, 81.9).unwrap_err();
        assert!(e.contains("x is not finite"), "{e}");
        let e = parse_record("FLASER 2 1 2 0 0 0 0 0 inf 5 h 5", 1, 81.9).unwrap_err();
        assert!(e.contains("odom_theta is not finite"), "{e}");
        let e = parse_record("FLASER 2 1 2 0 0 0 0 0 0 inf h 5", 1, 81.9).unwrap_err();
        assert!(e.contains("ipc_timestamp is not finite"), "{e}");
        let e = parse_record("FLASER 361 1 2", 1, 81.9).unwrap_err();
        assert!(e.contains("declares 361 readings"), "{e}");
    }

    #[test]
    fn robotlaser_uses_robot_pose_as_odometry() {
        let line = "ROBOTLASER1 0 -1.0 2.0 0.5 30.0 0.01 0 5 1 2 3 4 5 2 9 9 \
                    0.975516512 0.0958851077 0.5 0.8 0.0 0.5 0 0 0 0 0 12.5 host 12.5";
        let mut p = CarmenParser::new();
        let s = p.parse_line(Path::new("r.clf"), 3, line).unwrap().unwrap();
        assert_eq!(s.angle_min, -1.0);
        assert_eq!(s.angle_increment, 0.5);
        assert_eq!(s.max_range, 30.0);
        assert_eq!(s.ranges.len(), 5);
        assert_eq!(s.timestamp, Some(12.5));
        assert_eq!(xyt(&s.odometry).0, 0.8);
        assert_eq!(xyt(&s.logged_pose.unwrap()).0, 0.975516512);
        let off = xyt(&p.sensor_offset().unwrap());
        assert!((off.0 - 0.2).abs() < 1e-9 && off.1.abs() < 1e-9 && off.2.abs() < 1e-12);
        let bad = line.replace(" 2 9 9 ", " 3 9 9 ");
        let e = p
            .parse_line(Path::new("r.clf"), 4, &bad)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("r.clf:line 4") && e.contains("5 readings and 3 remissions"),
            "{e}"
        );
    }

    #[test]
    fn rawlaser_pairs_with_latest_odom_and_needs_one() {
        let path = Path::new("raw.clf");
        let raw = |t: f64| format!("RAWLASER1 0 -1.5 3.0 0.75 20 0.01 0 3 1 2 3 0 {t} h {t}");
        let mut p = CarmenParser::new();
        assert!(p.parse_line(path, 1, &raw(1.0)).unwrap().is_none());
        assert_eq!(p.unpaired_raw(), 1);
        assert!(
            p.parse_line(path, 2, "ODOM 1 2 0.5 0 0 0 2.0 h 2.0")
                .unwrap()
                .is_none()
        );
        let s = p.parse_line(path, 3, &raw(3.0)).unwrap().unwrap();
        assert_eq!(xyt(&s.odometry), (1.0, 2.0, 0.5));
        assert_eq!(s.logged_pose, None);
        assert_eq!(s.timestamp, Some(3.0));
        p.finish(path).unwrap();

        let mut q = CarmenParser::new();
        q.parse_line(path, 5, &raw(1.0)).unwrap();
        let e = q.finish(path).unwrap_err().to_string();
        assert!(e.contains("raw.clf:line 5") && e.contains("no ODOM"), "{e}");
    }

    #[test]
    fn params_set_flaser_max_range_with_precedence() {
        let path = Path::new("p.clf");
        let mut p = CarmenParser::new();
        assert_eq!(p.flaser_max_range(), FLASER_DEFAULT_MAX_RANGE);
        p.parse_line(path, 1, "PARAM robot_front_laser_max 50 0 h 0")
            .unwrap();
        assert_eq!(p.flaser_max_range(), 50.0);
        p.parse_line(path, 2, "PARAM laser_front_laser_max_range 30 0 h 0")
            .unwrap();
        p.parse_line(path, 3, "PARAM robot_front_laser_max 40 0 h 0")
            .unwrap();
        assert_eq!(p.flaser_max_range(), 30.0);
        let s = p
            .parse_line(path, 4, &flaser_line(2, "29.9 30"))
            .unwrap()
            .unwrap();
        assert_eq!(s.max_range, 30.0);
        assert!(!s.is_no_return(0) && s.is_no_return(1));
        let e = p
            .parse_line(path, 5, "PARAM robot_front_laser_max abc 0 h 0")
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("p.clf:line 5") && e.contains("'abc' is not a positive number"),
            "{e}"
        );
        p.parse_line(path, 6, "PARAM robot_frontlaser_offset -0.04 0 h 0")
            .unwrap();
        assert_eq!(xyt(&p.sensor_offset().unwrap()).0, -0.04);
    }

    #[test]
    fn first_laser_type_is_the_stream() {
        let path = Path::new("m.clf");
        let mut p = CarmenParser::new();
        assert!(
            p.parse_line(path, 1, &flaser_line(2, "1 2"))
                .unwrap()
                .is_some()
        );
        let raw = "RAWLASER1 0 -1.5 3.0 0.75 20 0.01 0 3 1 2 3 0 1 h 1";
        p.parse_line(path, 2, "ODOM 0 0 0 0 0 0 1 h 1").unwrap();
        assert!(p.parse_line(path, 3, raw).unwrap().is_none());
        assert_eq!(p.skipped_lasers(), 1);
        for l in ["# c", "", "NEFF 30", "RLASER 1 2 3"] {
            assert!(p.parse_line(path, 4, l).unwrap().is_none());
        }
        let e = p.parse_line(path, 9, "ODOM 0 0").unwrap_err().to_string();
        assert!(
            e.contains("m.clf:line 9") && e.contains("ODOM has 2 fields"),
            "{e}"
        );
    }

    #[test]
    fn flaser_writer_round_trips() {
        let scan = LaserScan2d {
            timestamp: Some(1134864629.895182),
            odometry: pose2(1.0, -2.0, 3.0),
            logged_pose: Some(pose2(1.1, -2.2, -3.0)),
            ranges: vec![0.5, f64::NAN, 7.9996, 8.0, 1.23456],
            angle_min: -FRAC_PI_2,
            angle_increment: PI / 4.0,
            max_range: 8.0,
            line: 0,
        };
        assert!(is_flaser_geometry(&scan));
        let text = format!(
            "{}{}",
            format_header(8.0, "sim"),
            format_flaser(&scan, "sim")
        );
        let mut p = CarmenParser::new();
        let mut got = None;
        for (i, l) in text.lines().enumerate() {
            if let Some(s) = p.parse_line(Path::new("w"), i + 1, l).unwrap() {
                got = Some(s);
            }
        }
        let got = got.unwrap();
        assert_eq!(got.max_range, 8.0);
        assert_eq!(
            format!("{:.6}", got.timestamp.unwrap()),
            "1134864629.895182"
        );
        assert_eq!(got.ranges[0], 0.5);
        assert!(got.is_no_return(1), "NaN must stay a no-return");
        assert!(!got.is_no_return(2), "a hit below the max must stay a hit");
        assert!(got.is_no_return(3));
        assert_eq!(got.ranges[4], 1.235);
        let (x, _, t) = xyt(&got.logged_pose.unwrap());
        assert!((x - 1.1).abs() < 1e-9 && (t + 3.0).abs() < 1e-6);

        // ROBOTLASER1 keeps a geometry FLASER cannot express.
        let mut narrow = scan.clone();
        narrow.angle_min = -0.5;
        narrow.angle_increment = 0.25;
        assert!(!is_flaser_geometry(&narrow));
        let rl = format_robotlaser1(&narrow, "sim");
        let CarmenRecord::RobotLaser(r) = parse_record(&rl, 1, 81.9).unwrap() else {
            panic!("{rl}")
        };
        assert!((r.angle_min + 0.5).abs() < 1e-9 && (r.angle_increment - 0.25).abs() < 1e-9);
        assert_eq!(r.max_range, 8.0);
        assert!(r.is_no_return(1) && !r.is_no_return(2));
    }
}
