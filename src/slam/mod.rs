//! The online SLAM API: feed scans as they come, read the estimate at any
//! time.
//!
//! [`Slam2d`] takes 2-D laser scans with odometry, [`Slam3d`] takes 3-D
//! sweeps with an optional prior pose. Each does per scan what a robot's
//! SLAM node would: convert the reading to the filter's [`crate::scan::Scan`],
//! decide whether the robot moved enough to process it, build the step's
//! [`crate::proposal::Proposal`] and run one
//! [`crate::filter::ParticleFilter::step`]. Whole-file runs
//! ([`crate::pipeline`]) are thin loops over them.
//!
//! ```
//! use dpslam::config::Config;
//! use dpslam::geometry::pose2;
//! use dpslam::scan::Ranges2d;
//! use dpslam::slam::Slam2d;
//!
//! let mut cfg = Config::default();
//! cfg.filter.particles = 5;
//! let mut slam = Slam2d::new(cfg).unwrap();
//! // A robot 2 m from a wall ahead, with a 181-beam laser over 180°.
//! let ranges: Vec<f64> = (0..181)
//!     .map(|i| {
//!         let a = (i as f64 - 90.0).to_radians();
//!         if a.cos() > 0.3 { 2.0 / a.cos() } else { f64::NAN }
//!     })
//!     .collect();
//! let reading = Ranges2d {
//!     ranges: &ranges,
//!     angle_min: -std::f64::consts::FRAC_PI_2,
//!     angle_increment: std::f64::consts::PI / 180.0,
//!     max_range: 30.0,
//! };
//! let first = slam.add_scan(0.0, pose2(0.0, 0.0, 0.0), &reading).unwrap();
//! assert!(first.processed);
//! // Standing still: nothing to process, the estimate stays put.
//! let still = slam.add_scan(0.1, pose2(0.0, 0.0, 0.0), &reading).unwrap();
//! assert!(!still.processed);
//! assert_eq!(slam.trajectory().unwrap().len(), 2);
//! ```

pub mod slam2d;
pub mod slam3d;

pub use slam2d::Slam2d;
pub use slam3d::Slam3d;

use crate::filter::Stamp;
use crate::geometry::Pose;
use crate::{Error, Result};

/// The estimate after one input scan.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Estimate<P> {
    /// Index of the scan in the input (0-based).
    pub index: usize,
    /// Time stamp of the scan, s (as given).
    pub stamp: f64,
    /// Best robot pose now (map frame): the best particle's pose; when this
    /// scan was skipped, moved from it by the scan's match against the best
    /// particle's map (`filter.match_skipped`, 2-D) or else by odometry.
    pub pose: P,
    /// Whether the filter processed the scan (it moved enough since the last
    /// processed one and, under the opt-in confirmed gate, its match did
    /// not confirm the odometry; the first scan is always processed).
    pub processed: bool,
}

/// One trajectory row per input scan from the corrected poses of the
/// processed ones (`corrected`, in input order) and each scan's time and
/// prior pose (`stamps`). A skipped scan with a match in `matched` (input
/// index, motion from the last processed scan's pose, in input order) is
/// placed by it. Any other skipped scan is placed by its prior motion from
/// the processed scans on both sides, the two placements blended by time:
/// the correction between them is spread along the gap instead of all
/// landing on the next processed scan, whose odometry would otherwise carry
/// the whole gap's drift (a turn's rotation error above all). After the
/// last processed scan, the prior motion from it alone.
pub(crate) fn fill_trajectory<const D: usize, P: Pose<D>>(
    stamps: &[(f64, P)],
    corrected: &[Stamp<P>],
    matched: &[(usize, P)],
) -> Result<Vec<(f64, P)>> {
    // (scan index, corrected pose) of the processed scans, in order.
    let anchors: Vec<(usize, P)> = corrected
        .iter()
        .map(|st| (st.scan as usize, st.pose))
        .collect();
    let placed = |a: &(usize, P), i: usize| {
        let (j, pose) = a;
        pose.compose(&stamps[*j].1.inverse().compose(&stamps[i].1))
    };
    let mut rows = Vec::with_capacity(stamps.len());
    let mut matches = matched.iter().peekable();
    let mut next = 0;
    for (i, (t, _)) in stamps.iter().enumerate() {
        while next < anchors.len() && anchors[next].0 < i {
            next += 1;
        }
        while matches.peek().is_some_and(|m| m.0 < i) {
            matches.next();
        }
        let pose = match (next.checked_sub(1).map(|k| &anchors[k]), anchors.get(next)) {
            (_, Some(b)) if b.0 == i => b.1,
            (None, _) => {
                return Err(Error::Invalid(format!("scan {i} precedes the first pose")));
            }
            (Some(a), _) if matches.peek().is_some_and(|m| m.0 == i) => {
                a.1.compose(&matches.next().expect("peeked").1)
            }
            (Some(a), None) => placed(a, i),
            (Some(a), Some(b)) => {
                let (from, to) = (placed(a, i), placed(b, i));
                let (ta, tb) = (stamps[a.0].0, stamps[b.0].0);
                let s = if tb > ta {
                    ((t - ta) / (tb - ta)).clamp(0.0, 1.0)
                } else {
                    (i - a.0) as f64 / (b.0 - a.0) as f64
                };
                let xi: Vec<f64> = from.perturbation_to(&to).iter().map(|v| v * s).collect();
                from.perturbed(&P::identity(), &xi)
            }
        };
        if !pose.is_finite() {
            return Err(Error::Invalid(format!("non-finite pose at scan {i}")));
        }
        rows.push((*t, pose));
    }
    Ok(rows)
}

/// Checks a scan's time stamp and prior pose before they reach the filter.
pub(crate) fn check_input<const D: usize, P: Pose<D>>(
    index: usize,
    stamp: f64,
    prior: Option<&P>,
) -> Result<()> {
    if !stamp.is_finite() {
        return Err(Error::Invalid(format!(
            "scan {index}: time stamp {stamp} is not finite"
        )));
    }
    if let Some(p) = prior
        && !p.is_finite()
    {
        return Err(Error::Invalid(format!(
            "scan {index}: odometry pose is not finite"
        )));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::{Pose2, pose2, xyt};

    fn stamp(scan: u32, pose: Pose2) -> Stamp<Pose2> {
        Stamp { scan, pose }
    }

    #[test]
    fn a_skipped_scan_is_placed_by_its_match_or_by_odometry_from_both_sides() {
        // Odometry straight along x, 1 m per scan; the corrections put scan
        // 2 0.2 m to the left of where odometry from scan 0 would.
        let stamps: Vec<(f64, Pose2)> = (0..4)
            .map(|i| (i as f64, pose2(i as f64, 0.0, 0.0)))
            .collect();
        let corrected = [
            stamp(0, pose2(0.0, 0.0, 0.0)),
            stamp(2, pose2(2.0, 0.2, 0.0)),
        ];
        let rows = fill_trajectory(&stamps, &corrected, &[]).unwrap();
        // Halfway between the placements from scan 0 (1, 0) and scan 2 (1, 0.2).
        let (x, y, t) = xyt(&rows[1].1);
        assert!((x - 1.0).abs() < 1e-12 && (y - 0.1).abs() < 1e-12 && t.abs() < 1e-12);
        // After the last processed scan, odometry from it.
        let (x, y, _) = xyt(&rows[3].1);
        assert!((x - 3.0).abs() < 1e-12 && (y - 0.2).abs() < 1e-12);
        // A matched skipped scan: its match from the processed scan before.
        let matched = [(1, pose2(0.9, -0.05, 0.1)), (3, pose2(1.0, 0.0, -0.1))];
        let rows = fill_trajectory(&stamps, &corrected, &matched).unwrap();
        let (x, y, t) = xyt(&rows[1].1);
        assert!((x - 0.9).abs() < 1e-12 && (y + 0.05).abs() < 1e-12 && (t - 0.1).abs() < 1e-12);
        let (x, y, t) = xyt(&rows[3].1);
        assert!((x - 3.0).abs() < 1e-12 && (y - 0.2).abs() < 1e-12 && (t + 0.1).abs() < 1e-12);
        // Processed rows are the corrected poses.
        assert_eq!(rows[2].1, corrected[1].pose);
    }
}
