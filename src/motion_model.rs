//! Motion models: how a particle's pose moves between two processed scans.
//!
//! A model turns the odometry-reported motion (a relative pose in the previous
//! robot frame) into a random new pose. 2-D uses DP-SLAM's C/D/T model
//! (dissertation ch. 6); 3-D models implement the same trait.

use crate::config::Motion2dConfig;
use crate::geometry::{Pose, Pose2, pose2, xyt};
use rand_distr::{Distribution, StandardNormal};
use rand_pcg::Pcg64;

/// Samples a new pose from the previous one and the odometry motion.
pub trait MotionModel<const D: usize, P: Pose<D>>: Send + Sync {
    /// A sample of the new robot pose (map frame) given the previous pose
    /// `prev` and the odometry motion `delta` expressed in the previous robot frame.
    fn sample(&self, prev: &P, delta: &P, rng: &mut Pcg64) -> P;
}

/// DP-SLAM's C/D/T model. The odometry motion is split into D (along the mean
/// heading of the step), C (across it) and T (turn); each actual component is
/// Gaussian with mean and standard deviation linear in `|D|` and `|T|`.
#[derive(Debug, Clone, PartialEq)]
pub struct CdtModel {
    /// Parameters (metres, radians).
    pub cfg: Motion2dConfig,
}

/// Odometry motion `delta` as (D, C, T): along the mean heading, across it, turn.
pub fn cdt_of(delta: &Pose2) -> (f64, f64, f64) {
    let (dx, dy, t) = xyt(delta);
    let (s, c) = (t / 2.0).sin_cos();
    (dx * c + dy * s, -dx * s + dy * c, t)
}

impl CdtModel {
    /// The pose reached from `prev` by moving D along and C across the mean
    /// heading and turning T.
    pub fn apply(prev: &Pose2, d: f64, c: f64, t: f64) -> Pose2 {
        let (x, y, th) = xyt(prev);
        let ma = th + t / 2.0;
        let (s, co) = ma.sin_cos();
        pose2(x + d * co - c * s, y + d * s + c * co, th + t)
    }
}

impl MotionModel<2, Pose2> for CdtModel {
    fn sample(&self, prev: &Pose2, delta: &Pose2, rng: &mut Pcg64) -> Pose2 {
        let m = &self.cfg;
        let (d, c, t) = cdt_of(delta);
        let lin = |k: [f64; 2]| k[0] * d + k[1] * t;
        let std = |k: [f64; 2], floor: f64| ((k[0] * d).abs() + (k[1] * t).abs()).max(floor);
        let mut n = || -> f64 { StandardNormal.sample(rng) };
        let dd = lin(m.mean_d) + std(m.std_d, m.min_std_xy) * n();
        let cc = c + lin(m.mean_c) + std(m.std_c, m.min_std_xy) * n();
        let tt = lin(m.mean_t) + std(m.std_t, m.min_std_t) * n();
        Self::apply(prev, dd, cc, tt)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    #[test]
    fn cdt_round_trip() {
        let prev = pose2(1.0, 2.0, 0.7);
        let delta = pose2(0.3, -0.05, 0.2);
        let (d, c, t) = cdt_of(&delta);
        let next = CdtModel::apply(&prev, d, c, t);
        let expect = prev * delta;
        assert!((next.translation.vector - expect.translation.vector).norm() < 1e-12);
        assert!((next.rotation.angle() - expect.rotation.angle()).abs() < 1e-12);
    }

    #[test]
    fn samples_centre_on_odometry_with_release_spread() {
        let model = CdtModel {
            cfg: Motion2dConfig::default(),
        };
        let mut rng = Pcg64::seed_from_u64(5);
        let prev = pose2(0.0, 0.0, 0.0);
        let delta = pose2(1.0, 0.0, 0.0);
        let n = 20000;
        let (mut sx, mut sxx, mut st) = (0.0, 0.0, 0.0);
        for _ in 0..n {
            let p = model.sample(&prev, &delta, &mut rng);
            sx += p.translation.x;
            sxx += p.translation.x * p.translation.x;
            st += p.rotation.angle();
        }
        let mean = sx / n as f64;
        let std = (sxx / n as f64 - mean * mean).sqrt();
        assert!((mean - 1.0).abs() < 0.01, "mean {mean}");
        // std of D for 1 m straight: 0.156 m (release)
        assert!((std - 0.156).abs() < 0.01, "std {std}");
        assert!((st / n as f64).abs() < 0.01);
    }
}
