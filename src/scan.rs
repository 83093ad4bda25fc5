//! Laser observations, generic over dimension.
//!
//! A [`Scan`] is what the filter consumes: beams in the **sensor frame** and
//! the sensor's mounting pose in the **robot frame**. 2-D laser lines and 3-D
//! sweeps are both converted into this one form.

use crate::geometry::Pose;

/// One laser beam in the sensor frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Beam<const D: usize> {
    /// Unit direction of the beam in the sensor frame.
    pub dir: [f64; D],
    /// Measured range in metres. For `no_return` beams this is the range up to
    /// which the beam is known to have travelled freely (the usable maximum).
    pub range: f64,
    /// The sensor reported no return (max-range reading, NaN or ≥ its limit):
    /// the beam adds free space but no hit.
    pub no_return: bool,
}

/// A scan: beams in the sensor frame plus the sensor's mounting pose.
#[derive(Debug, Clone)]
pub struct Scan<const D: usize, P: Pose<D>> {
    /// Sensor pose in the robot (odometry) frame.
    pub sensor: P,
    /// Beams in the sensor frame.
    pub beams: Vec<Beam<D>>,
}

impl<const D: usize, P: Pose<D>> Scan<D, P> {
    /// The endpoints of the beams that hit something (not `no_return`), in
    /// the robot frame (m): through the sensor's mount.
    pub fn returns_in_robot_frame(&self) -> Vec<[f64; D]> {
        self.beams
            .iter()
            .filter(|b| !b.no_return)
            .map(|b| {
                self.sensor
                    .transform_point(std::array::from_fn(|k| b.dir[k] * b.range))
            })
            .collect()
    }
}

/// A 2-D laser reading as it comes from a log, before beam selection.
#[derive(Debug, Clone, PartialEq)]
pub struct LaserScan2d {
    /// Time stamp (s) from the log; `None` for formats without time stamps.
    pub timestamp: Option<f64>,
    /// Robot pose from odometry at the time of the scan (odometry frame).
    pub odometry: crate::geometry::Pose2,
    /// Laser pose as written in the log (CARMEN `x y theta`; for corrected
    /// logs this is the reference pose). `None` where the format has none.
    pub logged_pose: Option<crate::geometry::Pose2>,
    /// Ranges in metres. NaN, ±inf and values ≥ `max_range` mean "no return".
    pub ranges: Vec<f64>,
    /// Angle of the first beam relative to the laser's forward axis (rad).
    pub angle_min: f64,
    /// Angle between consecutive beams (rad).
    pub angle_increment: f64,
    /// Readings at or above this (m) are "no return".
    pub max_range: f64,
    /// 1-based line of the scan in its source file (for messages).
    pub line: usize,
}

/// One 2-D laser reading as a driver reports it (sensor frame), borrowed:
/// what [`crate::slam::Slam2d::add_scan`] takes.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Ranges2d<'a> {
    /// Ranges, m, counter-clockwise from `angle_min`. NaN, ±inf, values
    /// ≤ 0 and values ≥ `max_range` mean "no return".
    pub ranges: &'a [f64],
    /// Angle of the first beam from the laser's forward axis, rad.
    pub angle_min: f64,
    /// Angle between consecutive beams, rad.
    pub angle_increment: f64,
    /// Readings at or above this (m) are "no return".
    pub max_range: f64,
}

impl Ranges2d<'_> {
    /// The reading with "no return" from `at` m on instead of from its
    /// declared maximum (`None`: as declared), for lasers whose declaration
    /// understates what they return.
    pub fn with_no_return_at(self, at: Option<f64>) -> Self {
        Self {
            max_range: at.unwrap_or(self.max_range),
            ..self
        }
    }

    /// Whether reading `i` is a "no return".
    pub fn is_no_return(&self, i: usize) -> bool {
        let r = self.ranges[i];
        !r.is_finite() || r >= self.max_range || r <= 0.0
    }

    /// Why the reading cannot be used, if it cannot: no beams, or
    /// non-finite angles or maximum range.
    pub fn check(&self) -> std::result::Result<(), String> {
        if self.ranges.is_empty() {
            return Err("the laser reading has no beams".into());
        }
        if !(self.angle_min.is_finite() && self.angle_increment.is_finite()) {
            return Err("the laser reading's angles are not finite".into());
        }
        if self.max_range.is_nan() || self.max_range <= 0.0 {
            return Err(format!(
                "the laser reading's maximum range {} is not positive",
                self.max_range
            ));
        }
        Ok(())
    }
}

impl LaserScan2d {
    /// Whether reading `i` is a "no return" (see [`Ranges2d::is_no_return`]).
    pub fn is_no_return(&self, i: usize) -> bool {
        self.as_ranges().is_no_return(i)
    }

    /// The reading alone, for [`crate::slam::Slam2d::add_scan`].
    pub fn as_ranges(&self) -> Ranges2d<'_> {
        Ranges2d {
            ranges: &self.ranges,
            angle_min: self.angle_min,
            angle_increment: self.angle_increment,
            max_range: self.max_range,
        }
    }
}
