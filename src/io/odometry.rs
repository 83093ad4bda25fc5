//! Odometry as a track of stamped poses, and the pose at any stamp.
//!
//! Odometry and laser run on their own clocks, so the pose paired with a
//! scan is the odometry interpolated at the scan's stamp: what tf2 answers
//! for a lookup at that time. Bags are read this way, and CARMEN logs whose
//! FLASER poses were paired from their own ODOM stream are re-timed the same
//! way ([`crate::io::log2d`]).

use crate::geometry::{Pose2, Pose3};

/// Poses over time, sorted by stamp.
#[derive(Debug, Clone, Default)]
pub struct Track {
    /// Header stamps, ns since the epoch, ascending.
    pub stamps_ns: Vec<i64>,
    /// The pose at each stamp (parent frame; m, unit quaternion).
    pub poses: Vec<Pose3>,
}

impl Track {
    /// Appends the pose `p` stamped `t` (ns); [`Track::sort`] orders them.
    pub fn push(&mut self, t: i64, p: Pose3) {
        self.stamps_ns.push(t);
        self.poses.push(p);
    }

    /// Orders the poses by stamp (stable for equal stamps).
    pub fn sort(&mut self) {
        let mut idx: Vec<usize> = (0..self.poses.len()).collect();
        idx.sort_by_key(|&i| self.stamps_ns[i]);
        self.stamps_ns = idx.iter().map(|&i| self.stamps_ns[i]).collect();
        self.poses = idx.iter().map(|&i| self.poses[i]).collect();
    }

    /// The pose at `t`: interpolated between the poses stamped just before
    /// and just after it (linear in translation, slerp in rotation); the
    /// first or last pose outside the track (no extrapolation).
    ///
    /// Odometry and laser run on their own clocks: the latest pose at or
    /// before a scan can be a whole odometry period old (up to 0.25 s on the
    /// ACES robot, 11° while turning in place). Interpolating is what tf2
    /// answers for a lookup at the scan's stamp.
    pub fn at(&self, t: i64) -> Option<Pose3> {
        let k = self.stamps_ns.partition_point(|&s| s <= t);
        let (a, b) = match (k.checked_sub(1), self.poses.get(k)) {
            (Some(i), Some(next)) => (
                (self.stamps_ns[i], self.poses[i]),
                (self.stamps_ns[k], *next),
            ),
            (Some(i), None) => return Some(self.poses[i]),
            (None, next) => return next.copied(),
        };
        let s = (t - a.0) as f64 / (b.0 - a.0) as f64;
        // `None` only for a degenerate rotation pair: keep the nearer pose.
        let nearer = if s < 0.5 { a.1 } else { b.1 };
        Some(a.1.try_lerp_slerp(&b.1, s, 1e-9).unwrap_or(nearer))
    }

    /// The poses stamped just before (or at) and just after `t`; `None`
    /// outside the track.
    pub fn around(&self, t: i64) -> Option<(Pose3, Pose3)> {
        let k = self.stamps_ns.partition_point(|&s| s <= t);
        Some((*self.poses.get(k.checked_sub(1)?)?, *self.poses.get(k)?))
    }

    /// Poses in the track.
    pub fn len(&self) -> usize {
        self.poses.len()
    }

    /// The track has no pose.
    pub fn is_empty(&self) -> bool {
        self.poses.is_empty()
    }
}

/// A 3-D pose's planar part (x, y, yaw).
pub fn planar(p: &Pose3) -> Pose2 {
    let (_, _, yaw) = p.rotation.euler_angles();
    crate::geometry::pose2(p.translation.vector.x, p.translation.vector.y, yaw)
}

/// A planar pose (x, y, yaw) as a 3-D one: z = 0, rotation about z; the
/// inverse of [`planar`].
pub fn spatial(p: &Pose2) -> Pose3 {
    nalgebra::Isometry3::new(
        nalgebra::Vector3::new(p.translation.x, p.translation.y, 0.0),
        nalgebra::Vector3::z() * p.rotation.angle(),
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Isometry3, Vector3};

    fn track() -> Track {
        let mut t = Track::default();
        t.push(
            1_000,
            Isometry3::new(Vector3::new(0.0, 0.0, 0.0), Vector3::z() * 0.0),
        );
        t.push(
            3_000,
            Isometry3::new(Vector3::new(2.0, -1.0, 0.0), Vector3::z() * 0.4),
        );
        t
    }

    #[test]
    fn odometry_is_interpolated_between_the_messages_around_a_stamp() {
        let t = track();
        let mid = planar(&t.at(2_500).unwrap());
        assert!((mid.translation.x - 1.5).abs() < 1e-12, "{mid:?}");
        assert!((mid.translation.y + 0.75).abs() < 1e-12, "{mid:?}");
        assert!((mid.rotation.angle() - 0.3).abs() < 1e-12, "{mid:?}");
        // On a stamp: that message's pose.
        let on = planar(&t.at(3_000).unwrap());
        assert!((on.rotation.angle() - 0.4).abs() < 1e-12);
        // Across ±π the short way round (quaternions q and −q are one rotation).
        let mut wrap = Track::default();
        for (ns, yaw) in [(0, 3.1), (10, -3.1)] {
            wrap.push(ns, Isometry3::new(Vector3::zeros(), Vector3::z() * yaw));
        }
        let yaw = planar(&wrap.at(5).unwrap()).rotation.angle();
        assert!((yaw.abs() - std::f64::consts::PI).abs() < 1e-9, "{yaw}");
        // Half a turn apart (a glitched bag): either way round, no panic.
        let mut half = Track::default();
        for (ns, yaw) in [(0, 0.0), (10, std::f64::consts::PI)] {
            half.push(ns, Isometry3::new(Vector3::zeros(), Vector3::z() * yaw));
        }
        let yaw = planar(&half.at(2).unwrap()).rotation.angle();
        assert!(
            (yaw.abs() - 0.2 * std::f64::consts::PI).abs() < 1e-9,
            "{yaw}"
        );
    }

    #[test]
    fn outside_the_odometry_span_the_nearest_pose_is_kept() {
        let t = track();
        assert_eq!(planar(&t.at(0).unwrap()).translation.x, 0.0);
        assert_eq!(planar(&t.at(9_000).unwrap()).translation.x, 2.0);
        assert!(Track::default().at(5).is_none());
    }

    #[test]
    fn a_planar_pose_survives_the_round_trip_through_3d() {
        let p = crate::geometry::pose2(1.5, -2.0, 3.0);
        let back = planar(&spatial(&p));
        assert!((back.translation.vector - p.translation.vector).norm() < 1e-12);
        assert!((back.rotation.angle() - 3.0).abs() < 1e-12);
    }
}
