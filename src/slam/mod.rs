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
    /// Best robot pose now (map frame): the best particle's pose, carried by
    /// odometry from the last processed scan when this one was skipped.
    pub pose: P,
    /// Whether the filter processed the scan (it moved enough since the last
    /// processed one; the first scan is always processed).
    pub processed: bool,
}

/// One trajectory row per input scan from the corrected poses of the
/// processed ones (`corrected`, in input order) and each scan's time and
/// prior pose (`stamps`): a skipped scan is placed by its prior motion from
/// the last processed scan.
pub(crate) fn fill_trajectory<const D: usize, P: Pose<D>>(
    stamps: &[(f64, P)],
    corrected: &[Stamp<P>],
) -> Result<Vec<(f64, P)>> {
    let mut rows = Vec::with_capacity(stamps.len());
    let mut next = corrected.iter().peekable();
    // (corrected, prior) of the last processed scan.
    let mut anchor: Option<(P, P)> = None;
    for (i, (t, prior)) in stamps.iter().enumerate() {
        let pose = match next.peek() {
            Some(st) if st.scan as usize == i => {
                let p = st.pose;
                next.next();
                anchor = Some((p, *prior));
                p
            }
            _ => {
                let (p, o) = anchor
                    .ok_or_else(|| Error::Invalid(format!("scan {i} precedes the first pose")))?;
                p.compose(&o.inverse().compose(prior))
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
