//! The native log format of the DP-SLAM 0.1.1 release (e.g. `loop5.log`).
//!
//! ```text
//! Odometry x y theta
//! Laser N r_1 … r_N
//! ```
//!
//! `Odometry` is the robot pose from odometry (m, m, rad, odometry frame);
//! each `Laser` line is a scan taken at the latest `Odometry` pose. Beams
//! start at −90° with the FLASER count rule (181 → 1° steps up to +90°, see
//! [`crate::io::carmen::flaser_geometry`]). Ranges in metres; readings at or
//! above [`DPSLAM_MAX_RANGE`] (the release's 7.95 m; the SICK writes 8.183
//! for "no return") and NaN/±inf are "no return". The format has no time
//! stamps and no reference poses: `timestamp` and `logged_pose` are `None`.
//!
//! The release also drops the 181st reading and puts the laser 0.40 m ahead
//! of the odometry point; both are the mapper's business, not the reader's.

use crate::geometry::{Pose2, pose2};
use crate::io::carmen::flaser_geometry;
use crate::io::source::parse_f64;
use crate::scan::LaserScan2d;
use crate::{Error, Result};
use std::path::Path;

/// Max range (m) of DP-SLAM logs: the release ignores readings at or above it.
pub const DPSLAM_MAX_RANGE: f64 = 7.95;

/// Whether a line's first word marks the DP-SLAM format (`Odometry`, `Laser`).
pub fn is_dpslam_keyword(word: &str) -> bool {
    matches!(word, "Odometry" | "Laser")
}

/// Stateful reader of DP-SLAM log lines: remembers the latest odometry pose.
#[derive(Debug, Clone, Default)]
pub struct DpSlamParser {
    last_odom: Option<Pose2>,
}

impl DpSlamParser {
    /// A parser that has seen no `Odometry` line yet.
    pub fn new() -> Self {
        Self::default()
    }

    /// Parses one line of `path` (1-based `line_no`); returns the scan of a
    /// `Laser` line. Empty lines and `#` comments are skipped; any other
    /// keyword, a `Laser` before any `Odometry`, a count that does not match
    /// the readings, a non-numeric field or a non-finite pose is an error
    /// naming the file, the line and the reason.
    pub fn parse_line(
        &mut self,
        path: &Path,
        line_no: usize,
        line: &str,
    ) -> Result<Option<LaserScan2d>> {
        self.parse(line, line_no)
            .map_err(|r| Error::at_line(path, line_no, r))
    }

    fn parse(
        &mut self,
        line: &str,
        line_no: usize,
    ) -> std::result::Result<Option<LaserScan2d>, String> {
        let mut toks = line.split_ascii_whitespace();
        let Some(kind) = toks.next() else {
            return Ok(None);
        };
        if kind.starts_with('#') {
            return Ok(None);
        }
        match kind {
            "Odometry" => {
                let mut v = [0.0; 3];
                for (slot, what) in v.iter_mut().zip(["x", "y", "theta"]) {
                    *slot = parse_f64(toks.next(), &format!("Odometry {what}"))?;
                    if !slot.is_finite() {
                        return Err(format!("Odometry {what} is not finite ({slot})"));
                    }
                }
                if let Some(extra) = toks.next() {
                    return Err(format!(
                        "Odometry has more than 3 values (unexpected '{extra}')"
                    ));
                }
                self.last_odom = Some(pose2(v[0], v[1], v[2]));
                Ok(None)
            }
            "Laser" => {
                let t = toks.next().ok_or("Laser without a reading count")?;
                let n: i64 = t
                    .parse()
                    .map_err(|_| format!("Laser reading count '{t}' is not an integer"))?;
                let n = usize::try_from(n)
                    .map_err(|_| format!("Laser reading count {n} is negative"))?;
                let ranges = toks
                    .enumerate()
                    .map(|(i, t)| {
                        t.parse::<f64>()
                            .map_err(|_| format!("range reading {}: '{t}' is not a number", i + 1))
                    })
                    .collect::<std::result::Result<Vec<f64>, String>>()?;
                if ranges.len() != n {
                    return Err(format!(
                        "Laser declares {n} readings but the line has {} values",
                        ranges.len()
                    ));
                }
                let odometry = self
                    .last_odom
                    .ok_or("Laser before any Odometry line: the scan has no pose")?;
                let (angle_min, angle_increment) = flaser_geometry(n);
                Ok(Some(LaserScan2d {
                    timestamp: None,
                    odometry,
                    logged_pose: None,
                    ranges,
                    angle_min,
                    angle_increment,
                    max_range: DPSLAM_MAX_RANGE,
                    line: line_no,
                }))
            }
            other => Err(format!(
                "unknown record '{other}' (a DP-SLAM log has only Odometry and Laser lines)"
            )),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::xyt;

    #[test]
    fn pairs_laser_with_latest_odometry() {
        let p = Path::new("l.log");
        let mut d = DpSlamParser::new();
        assert!(
            d.parse_line(p, 1, "Odometry -2.4 4.8 2.59 ")
                .unwrap()
                .is_none()
        );
        let s = d
            .parse_line(p, 2, "Laser 3 0.642 NaN 8.183")
            .unwrap()
            .unwrap();
        assert_eq!(xyt(&s.odometry), (-2.4, 4.8, 2.59));
        assert_eq!(s.line, 2);
        assert_eq!((s.timestamp, s.logged_pose), (None, None));
        assert!(!s.is_no_return(0) && s.is_no_return(1) && s.is_no_return(2));
        assert!((s.angle_increment - std::f64::consts::FRAC_PI_2).abs() < 1e-15);
        // Two scans at one odometry pose are fine.
        let s2 = d.parse_line(p, 3, "Laser 1 7.949").unwrap().unwrap();
        assert!(!s2.is_no_return(0));
    }

    #[test]
    fn errors_name_file_line_and_reason() {
        let p = Path::new("bad.log");
        let cases = [
            ("Laser 2 1 2", "Laser before any Odometry"),
            ("Odometry 1 2", "missing Odometry theta"),
            ("Odometry 1 nan 0", "Odometry y is not finite"),
            ("Odometry 1 2 3 4", "more than 3 values"),
            ("Odometry 1 b 3", "Odometry y: 'b' is not a number"),
            ("Sonar 1", "unknown record 'Sonar'"),
        ];
        for (line, want) in cases {
            let e = DpSlamParser::new()
                .parse_line(p, 12, line)
                .unwrap_err()
                .to_string();
            assert!(
                e.contains("bad.log:line 12") && e.contains(want),
                "{line}: {e}"
            );
        }
        let mut d = DpSlamParser::new();
        d.parse_line(p, 1, "Odometry 0 0 0").unwrap();
        for (line, want) in [
            (
                "Laser 181 1 2 3",
                "Laser declares 181 readings but the line has 3 values",
            ),
            ("Laser -1", "negative"),
            ("Laser 2 1 x", "range reading 2: 'x' is not a number"),
        ] {
            let e = d.parse_line(p, 2, line).unwrap_err().to_string();
            assert!(
                e.contains("bad.log:line 2") && e.contains(want),
                "{line}: {e}"
            );
        }
    }
}
