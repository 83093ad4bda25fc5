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

    /// Log density (natural log) of drawing `sample` (map frame) from
    /// `prev` for the odometry motion `delta`, in the coordinates of
    /// [`Pose::perturbation_to`] from `prev · delta` (2-D `[x m, y m, θ
    /// rad]`, 3-D `[ω rad, t m]`; the 2-D C/D/T coordinates have the same
    /// density, their Jacobian being 1). The importance weight of a sample
    /// drawn from another proposal is likelihood × this / proposal density.
    /// `None`: the model has no density (e.g. [`Exact`]); samples are then
    /// weighed by likelihood alone.
    fn log_density(&self, _prev: &P, _delta: &P, _sample: &P) -> Option<f64> {
        None
    }
}

/// `ln Σ exp(xᵢ)` without overflow (−∞ for none or all −∞): the log of a
/// sum of densities or weights given as logs.
pub(crate) fn log_sum_exp(xs: &[f64]) -> f64 {
    let top = xs.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    if !top.is_finite() {
        return top;
    }
    top + xs.iter().map(|x| (x - top).exp()).sum::<f64>().ln()
}

/// `ln N(x; 0, σ²)`.
#[inline]
pub fn normal_log_density(x: f64, sigma: f64) -> f64 {
    const HALF_LN_TAU: f64 = 0.918_938_533_204_672_7;
    -0.5 * (x / sigma) * (x / sigma) - sigma.ln() - HALF_LN_TAU
}

/// The motion exactly as given, without noise: for filters built only for
/// their map, whose particles never move by sampling.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Exact;

impl<const D: usize, P: Pose<D>> MotionModel<D, P> for Exact {
    fn sample(&self, prev: &P, delta: &P, _rng: &mut Pcg64) -> P {
        prev.compose(delta)
    }
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

impl CdtModel {
    /// Means and stds of (D, C, T) for the odometry motion `delta`: `([D m,
    /// C m, T rad], [σ_D m, σ_C m, σ_T rad])`.
    pub fn components(&self, delta: &Pose2) -> ([f64; 3], [f64; 3]) {
        let m = &self.cfg;
        let (d, c, t) = cdt_of(delta);
        let lin = |k: [f64; 2]| k[0] * d + k[1] * t;
        let std = |k: [f64; 2], floor: f64| ((k[0] * d).abs() + (k[1] * t).abs()).max(floor);
        (
            [lin(m.mean_d), c + lin(m.mean_c), lin(m.mean_t)],
            [
                std(m.std_d, m.min_std_xy),
                std(m.std_c, m.min_std_xy),
                std(m.std_t, m.min_std_t),
            ],
        )
    }

    /// The model's motion linearised at its mean: mean `[x m, y m, θ rad]`
    /// and covariance of the new pose in the previous robot frame, for
    /// fusing with a scan match (the C/D/T components are independent
    /// Gaussians; the pose is a smooth function of them).
    pub fn local_gaussian(&self, delta: &Pose2) -> ([f64; 3], nalgebra::Matrix3<f64>) {
        let ([d, c, t], [sd, sc, st]) = self.components(delta);
        let p = Self::apply(&Pose2::identity(), d, c, t);
        let (s, co) = (t / 2.0).sin_cos();
        let j = nalgebra::Matrix3::new(
            co,
            -s,
            0.5 * (-d * s - c * co),
            s,
            co,
            0.5 * (d * co - c * s),
            0.0,
            0.0,
            1.0,
        );
        let n =
            nalgebra::Matrix3::from_diagonal(&nalgebra::Vector3::new(sd * sd, sc * sc, st * st));
        let (x, y, th) = xyt(&p);
        ([x, y, th], j * n * j.transpose())
    }
}

impl MotionModel<2, Pose2> for CdtModel {
    fn sample(&self, prev: &Pose2, delta: &Pose2, rng: &mut Pcg64) -> Pose2 {
        let ([d, c, t], [sd, sc, st]) = self.components(delta);
        let mut n = || -> f64 { StandardNormal.sample(rng) };
        let dd = d + sd * n();
        let cc = c + sc * n();
        let tt = t + st * n();
        Self::apply(prev, dd, cc, tt)
    }

    fn log_density(&self, prev: &Pose2, delta: &Pose2, sample: &Pose2) -> Option<f64> {
        let ([d, c, t], [sd, sc, st]) = self.components(delta);
        // The sample's own (D, C, T): `apply` from the identity inverts
        // exactly for turns inside (−π, π].
        let (dd, cc, tt) = cdt_of(&(prev.inverse() * sample));
        Some(
            normal_log_density(dd - d, sd)
                + normal_log_density(cc - c, sc)
                + normal_log_density(crate::geometry::wrap_angle(tt - t), st),
        )
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

/// 6-DoF motion model for 3-D sweeps: the given relative motion `delta`
/// (previous robot frame) followed by a Gaussian perturbation, also in the
/// robot frame, of the translation (m, per axis) and of the rotation (rad,
/// small-angle axis vector, per axis). Each std is proportional to the size
/// of the motion, with a floor, from [`crate::config::Map3dConfig`]:
/// `σ_t = max(a_t·|t| + b_t·θ, min_t)`, `σ_r = max(a_r·|t| + b_r·θ, min_r)`
/// with `|t|` the translation (m) and θ the rotation angle (rad) of `delta`.
#[derive(Debug, Clone, PartialEq)]
pub struct Gaussian6dModel {
    /// Translation std per metre of motion (m/m) and per radian (m/rad).
    pub trans_std: [f64; 2],
    /// Rotation std per metre of motion (rad/m) and per radian (rad/rad).
    pub rot_std: [f64; 2],
    /// Floors of the translation (m) and rotation (rad) stds.
    pub min_std: [f64; 2],
}

impl Gaussian6dModel {
    /// The model with the noise parameters of `cfg`.
    pub fn from_config(cfg: &crate::config::Map3dConfig) -> Self {
        Self {
            trans_std: [cfg.trans_std_per_m, cfg.trans_std_per_rad],
            rot_std: [cfg.rot_std_per_m, cfg.rot_std_per_rad],
            min_std: [cfg.min_trans_std, cfg.min_rot_std],
        }
    }

    /// Stds `(translation m, rotation rad)` for the motion `delta`.
    pub fn stds(&self, delta: &crate::geometry::Pose3) -> (f64, f64) {
        let d = delta.translation.vector.norm();
        let a = delta.rotation.angle();
        let st = (self.trans_std[0] * d + self.trans_std[1] * a).max(self.min_std[0]);
        let sr = (self.rot_std[0] * d + self.rot_std[1] * a).max(self.min_std[1]);
        (st, sr)
    }

    /// The covariance (body frame of the new pose, `[ω rad, t m]`) of the
    /// product of two Gaussians over the new pose: the scan matcher's,
    /// `icp` (same frame and order), and this model's for the motion `delta`
    /// (isotropic per block, so its frame does not matter):
    /// `(icp⁻¹ + motion⁻¹)⁻¹`. A singular `icp` (a direction the sweep does
    /// not constrain) leaves the motion model's spread in that direction.
    pub fn fuse(
        &self,
        delta: &crate::geometry::Pose3,
        icp: &nalgebra::Matrix6<f64>,
    ) -> Option<nalgebra::Matrix6<f64>> {
        let (st, sr) = self.stds(delta);
        let mut motion_info = nalgebra::Matrix6::zeros();
        for i in 0..3 {
            motion_info[(i, i)] = 1.0 / (sr * sr).max(1e-18);
            motion_info[(i + 3, i + 3)] = 1.0 / (st * st).max(1e-18);
        }
        let icp_info = icp.try_inverse()?;
        let fused = (icp_info + motion_info).try_inverse()?;
        // Symmetrise: the inverse of a symmetric matrix is symmetric only up
        // to rounding, and the Cholesky factor reads the lower triangle.
        Some((fused + fused.transpose()) * 0.5)
    }
}

impl MotionModel<3, crate::geometry::Pose3> for Gaussian6dModel {
    fn sample(
        &self,
        prev: &crate::geometry::Pose3,
        delta: &crate::geometry::Pose3,
        rng: &mut Pcg64,
    ) -> crate::geometry::Pose3 {
        use nalgebra::{Translation3, UnitQuaternion, Vector3};
        let (st, sr) = self.stds(delta);
        let mut n = || -> f64 { StandardNormal.sample(rng) };
        let dt = Vector3::new(n(), n(), n()) * st;
        let dr = Vector3::new(n(), n(), n()) * sr;
        let noisy = crate::geometry::Pose3::from_parts(
            Translation3::from(delta.translation.vector + dt),
            delta.rotation * UnitQuaternion::from_scaled_axis(dr),
        );
        // `Pose::compose` renormalises: the 3-D pipeline chains poses through
        // inverses and products every sweep, and an unnormalised quaternion's
        // error grows geometrically along that chain.
        prev.compose(&noisy)
    }

    /// Density of the translation noise (previous robot frame) and of the
    /// rotation noise's axis-angle vector. Against [`crate::proposal`]'s
    /// body-frame coordinates the translation differs by a rotation
    /// (Jacobian 1) and the rotation by a fixed left factor, whose
    /// Jacobian is 1 up to O(θ²) for the small angles of one step.
    fn log_density(
        &self,
        prev: &crate::geometry::Pose3,
        delta: &crate::geometry::Pose3,
        sample: &crate::geometry::Pose3,
    ) -> Option<f64> {
        let (st, sr) = self.stds(delta);
        let local = prev.inverse() * sample;
        let dt = local.translation.vector - delta.translation.vector;
        let dr = (delta.rotation.inverse() * local.rotation).scaled_axis();
        Some(
            (0..3)
                .map(|i| normal_log_density(dt[i], st) + normal_log_density(dr[i], sr))
                .sum(),
        )
    }
}

#[cfg(test)]
mod tests_6d {
    use super::*;
    use crate::geometry::Pose3;
    use nalgebra::Vector3;
    use rand::SeedableRng;

    #[test]
    fn samples_centre_on_delta_with_configured_spread() {
        let model = Gaussian6dModel::from_config(&crate::config::Map3dConfig::default());
        let prev = Pose3::new(Vector3::new(1.0, 2.0, 0.5), Vector3::new(0.0, 0.0, 0.4));
        let delta = Pose3::new(Vector3::new(2.0, 0.0, 0.0), Vector3::new(0.0, 0.0, 0.1));
        let (st, sr) = model.stds(&delta);
        assert!((st - (0.005 * 2.0 + 0.02 * 0.1)).abs() < 1e-12);
        assert!((sr - (0.001 * 2.0 + 0.01 * 0.1)).abs() < 1e-12);
        let expect = prev * delta;
        let mut rng = Pcg64::seed_from_u64(9);
        let n = 20000;
        let (mut sum, mut sq, mut rsq) = (Vector3::zeros(), Vector3::zeros(), 0.0);
        for _ in 0..n {
            let p = model.sample(&prev, &delta, &mut rng);
            let e = expect.inverse() * p;
            sum += e.translation.vector;
            sq += e.translation.vector.component_mul(&e.translation.vector);
            rsq += e.rotation.scaled_axis().norm_squared();
        }
        let mean = sum / n as f64;
        assert!(mean.norm() < 0.003, "mean {mean}");
        for i in 0..3 {
            let std = (sq[i] / n as f64).sqrt();
            assert!((std - st).abs() < 0.05 * st, "axis {i}: {std} vs {st}");
        }
        // Three independent axes: E|r|² = 3σ_r².
        let rstd = (rsq / (3.0 * n as f64)).sqrt();
        assert!((rstd - sr).abs() < 0.05 * sr, "{rstd} vs {sr}");
    }

    #[test]
    fn fusion_keeps_the_tighter_gaussian_per_direction() {
        let model = Gaussian6dModel::from_config(&crate::config::Map3dConfig::default());
        let delta = Pose3::new(Vector3::new(1.0, 0.0, 0.0), Vector3::zeros());
        let (st, sr) = model.stds(&delta);
        // The matcher pins roll, pitch and z to 0.1 mm / 1e-4 rad and leaves
        // yaw, x and y free (1 rad, 1 m).
        let icp = nalgebra::Matrix6::from_diagonal(&nalgebra::Vector6::new(
            1e-8, 1e-8, 1.0, 1.0, 1.0, 1e-8,
        ));
        let f = model.fuse(&delta, &icp).unwrap();
        for k in [0, 1, 5] {
            assert!((f[(k, k)].sqrt() - 1e-4).abs() < 1e-6, "{k}");
        }
        assert!((f[(2, 2)].sqrt() - sr).abs() < 1e-3 * sr);
        for k in [3, 4] {
            assert!((f[(k, k)].sqrt() - st).abs() < 1e-3 * st);
        }
    }

    #[test]
    fn a_matched_proposal_samples_with_its_covariance_or_falls_back() {
        use crate::proposal::Proposal;
        use nalgebra::{DMatrix, Vector6};
        let base = Gaussian6dModel::from_config(&crate::config::Map3dConfig::default());
        let prev = Pose3::new(Vector3::new(1.0, 2.0, 0.5), Vector3::new(0.1, 0.0, 0.4));
        let delta = Pose3::new(Vector3::new(1.5, 0.2, 0.0), Vector3::new(0.0, 0.0, 0.05));
        let expect = prev * delta;
        let mut rng = Pcg64::seed_from_u64(3);
        // Body-frame stds [ω, t]: 1 mrad, 2 mrad, 3 mrad, 1 mm, 2 mm, 3 mm.
        let sd = Vector6::new(1e-3, 2e-3, 3e-3, 1e-3, 2e-3, 3e-3);
        let cov = DMatrix::from_diagonal(&nalgebra::DVector::from_column_slice(
            sd.component_mul(&sd).as_slice(),
        ));
        let matched = Proposal::matched(delta, cov).unwrap();
        let n = 20000;
        let mut sq = Vector6::<f64>::zeros();
        for _ in 0..n {
            let p = matched.sample::<3>(&base, &prev, &Pose3::identity(), &mut rng);
            let e = expect.inverse() * p;
            let w = e.rotation.scaled_axis();
            let t = e.translation.vector;
            let xi = Vector6::new(w.x, w.y, w.z, t.x, t.y, t.z);
            sq += xi.component_mul(&xi);
        }
        for k in 0..6 {
            let got = (sq[k] / n as f64).sqrt();
            assert!(
                (got - sd[k]).abs() < 0.05 * sd[k],
                "{k}: {got} vs {}",
                sd[k]
            );
        }
        // The motion proposal: the plain model, sample for sample.
        let mut a = Pcg64::seed_from_u64(4);
        let mut b = Pcg64::seed_from_u64(4);
        assert_eq!(
            Proposal::Motion.sample::<3>(&base, &prev, &delta, &mut a),
            base.sample(&prev, &delta, &mut b)
        );
    }

    #[test]
    fn floors_apply_when_still() {
        let model = Gaussian6dModel::from_config(&crate::config::Map3dConfig::default());
        let (st, sr) = model.stds(&Pose3::identity());
        assert_eq!((st, sr), (0.005, 0.002));
    }
}
