//! The proposal: the distribution each particle draws its samples from in
//! one filter step, an explicit input of [`crate::filter::ParticleFilter::step`].
//!
//! DP-SLAM's release draws from the motion model around the odometry motion
//! ([`Proposal::Motion`]). A scan matcher can do better (Grisetti et al.,
//! IEEE T-RO 2007, "improved proposal"): align the scan first and draw from
//! a Gaussian around the aligned pose, whose covariance is the match's fused
//! with the motion model's ([`Proposal::Matched`]; the 3-D ICP of
//! [`crate::icp`] makes one). The same type serves 2-D and 3-D: the
//! perturbation lives in the body frame of the new pose, with
//! [`Pose::DOF`] components ([`Pose::perturbed`]).
//!
//! [`Proposal::ScanMatched`] asks the filter to match the scan against each
//! particle's own view of the map (a [`ScanRegistration`], 2-D:
//! [`crate::scan_match`]) and to draw each particle's samples from its own
//! fused Gaussian. Samples from any proposal but [`Proposal::Motion`] are
//! weighed by likelihood × motion-prior density / proposal density
//! ([`Proposal::log_ratio`]); with the motion proposal the two densities
//! cancel and the weight is the likelihood, exactly as in the release.

use crate::ancestry::{NodeId, Numbering};
use crate::dpmap::DpMap;
use crate::geometry::Pose;
use crate::motion_model::MotionModel;
use crate::particle::Particle;
use crate::scan::Scan;
use nalgebra::{DMatrix, DVector};
use rand_distr::{Distribution, StandardNormal};
use rand_pcg::Pcg64;

/// Where the samples of one filter step come from.
#[derive(Debug, Clone, PartialEq)]
pub enum Proposal<P> {
    /// The motion model around the step's odometry motion (the release's
    /// proposal).
    Motion,
    /// A scan match for the whole particle set, expressed as a motion: each
    /// particle at pose `p` draws `p · delta · ε(ξ)` ([`Pose::perturbed`]),
    /// with ξ ~ N(0, L Lᵀ) in the body frame of the new pose.
    Matched {
        /// The matched motion (previous robot frame).
        delta: P,
        /// Lower Cholesky factor L of the body-frame covariance
        /// ([`Pose::DOF`] × [`Pose::DOF`]; 2-D `[x m, y m, θ rad]`, 3-D
        /// `[ω rad, t m]`).
        factor: DMatrix<f64>,
    },
    /// Two or more matched Gaussians, each drawn with its probability
    /// (`(probability, delta, factor)`, probabilities summing to 1): a scan
    /// match whose window holds more than one plausible peak, so that the
    /// importance weights, not the matcher, decide between them. The density
    /// is the mixture's.
    Mixture(Vec<(f64, P, DMatrix<f64>)>),
    /// Per particle, a scan match against that particle's own map view,
    /// fused with the motion model (the filter's [`ScanRegistration`]; a
    /// filter without one samples the motion model).
    ScanMatched,
}

/// What a scan registration sees of one filter step.
pub struct MatchContext<'a, const D: usize, P: Pose<D>> {
    /// The shared DP-map.
    pub map: &'a DpMap<D>,
    /// Depth-first numbering of the tree, current for `map`.
    pub numbering: &'a Numbering,
    /// Per particle, the ancestry node its view is shared from: particles
    /// with the same key differ only in their own last observation.
    pub groups: &'a [NodeId],
    /// The particles (map frame) before the step.
    pub particles: &'a [Particle<P>],
    /// Odometry motion of the step (previous robot frame).
    pub odometry: &'a P,
    /// The new scan.
    pub scan: &'a Scan<D, P>,
}

/// Registers a scan against particles' map views: one proposal per
/// particle ([`Proposal::Matched`] relative to that particle's pose, or
/// [`Proposal::Motion`] where the match fails).
pub trait ScanRegistration<const D: usize, P: Pose<D>>: Send + Sync {
    /// One proposal per particle of `ctx.particles`, in order.
    fn propose(&self, ctx: &MatchContext<'_, D, P>) -> Vec<Proposal<P>>;

    /// Registers `scan` for a particle now at `prev` (map frame) that
    /// descends from particle `origin` of the last [`Self::propose`]
    /// call, with the odometry motion `odometry` since (`prev`'s frame),
    /// reusing what that call built for `origin`'s view (the map has since
    /// gained one scan per particle, which this leaves out). `None` where
    /// nothing can be reused (the caller then calls `propose`); otherwise
    /// as one `propose` entry. The default reuses nothing.
    fn rematch(
        &self,
        origin: usize,
        prev: &P,
        odometry: &P,
        scan: &Scan<D, P>,
    ) -> Option<Proposal<P>> {
        let _ = (origin, prev, odometry, scan);
        None
    }
}

impl<P> Proposal<P> {
    /// A matched proposal with body-frame covariance `covariance`, or `None`
    /// when it is not positive definite (the caller falls back to
    /// [`Proposal::Motion`]).
    pub fn matched(delta: P, covariance: DMatrix<f64>) -> Option<Self> {
        let factor = covariance.cholesky()?.l();
        Some(Self::Matched { delta, factor })
    }

    /// A matched proposal from an already computed lower Cholesky factor.
    pub fn from_factor(delta: P, factor: DMatrix<f64>) -> Self {
        Self::Matched { delta, factor }
    }

    /// Draws the new pose of a particle at `prev` (map frame), for the
    /// odometry motion `odometry` (previous robot frame), on `rng`.
    pub fn sample<const D: usize>(
        &self,
        motion: &dyn MotionModel<D, P>,
        prev: &P,
        odometry: &P,
        rng: &mut Pcg64,
    ) -> P
    where
        P: Pose<D>,
    {
        match self {
            Proposal::Motion | Proposal::ScanMatched => motion.sample(prev, odometry, rng),
            Proposal::Matched { delta, factor } => gaussian_sample(prev, delta, factor, rng),
            Proposal::Mixture(parts) => {
                let u: f64 = rand::RngExt::random(&mut *rng);
                let mut acc = 0.0f64;
                let (_, delta, factor) = parts
                    .iter()
                    .find(|c| {
                        acc += c.0;
                        u < acc
                    })
                    .or(parts.last())
                    .expect("a mixture has components");
                gaussian_sample(prev, delta, factor, rng)
            }
        }
    }

    /// Whether samples come from a scan match ([`Proposal::Matched`] or
    /// [`Proposal::Mixture`]).
    pub fn is_matched(&self) -> bool {
        matches!(self, Proposal::Matched { .. } | Proposal::Mixture(_))
    }
}

/// `prev · delta · ε(L n)` with n standard normal.
fn gaussian_sample<const D: usize, P: Pose<D>>(
    prev: &P,
    delta: &P,
    factor: &DMatrix<f64>,
    rng: &mut Pcg64,
) -> P {
    let n = DVector::from_fn(P::DOF, |_, _| StandardNormal.sample(&mut *rng));
    let xi = factor * n;
    prev.perturbed(delta, xi.as_slice())
}

/// The offset ξ of `sample` from `prev · delta` in the body-frame
/// coordinates of [`Pose::perturbation_to`], whitened by the lower
/// Cholesky factor L: `L⁻¹ ξ` (its squared norm is the Mahalanobis
/// distance under N(0, L Lᵀ)); `None` if L is singular.
pub(crate) fn whitened<const D: usize, P: Pose<D>>(
    prev: &P,
    delta: &P,
    factor: &DMatrix<f64>,
    sample: &P,
) -> Option<DVector<f64>> {
    let mean = prev.compose(delta);
    let xi = DVector::from_vec(mean.perturbation_to(sample));
    factor.solve_lower_triangular(&xi)
}

/// Log density of `sample` under `prev · delta · ε(ξ)`, ξ ~ N(0, L Lᵀ), in
/// the body-frame coordinates of [`Pose::perturbation_to`].
fn gaussian_log_density<const D: usize, P: Pose<D>>(
    prev: &P,
    delta: &P,
    factor: &DMatrix<f64>,
    sample: &P,
) -> Option<f64> {
    let z = whitened(prev, delta, factor, sample)?;
    let log_det: f64 = (0..P::DOF).map(|i| factor[(i, i)].ln()).sum();
    Some(-0.5 * z.norm_squared() - log_det - 0.5 * P::DOF as f64 * std::f64::consts::TAU.ln())
}

impl<P> Proposal<P> {
    /// Log density (natural log) of drawing `sample` (map frame) from this
    /// proposal for a particle at `prev`, in the body-frame coordinates of
    /// [`Pose::perturbation_to`]; `None` for the motion proposals (their
    /// density is the motion model's).
    pub fn log_density<const D: usize>(&self, prev: &P, sample: &P) -> Option<f64>
    where
        P: Pose<D>,
    {
        match self {
            Proposal::Motion | Proposal::ScanMatched => None,
            Proposal::Matched { delta, factor } => {
                gaussian_log_density(prev, delta, factor, sample)
            }
            Proposal::Mixture(parts) => {
                let logs: Vec<f64> = parts
                    .iter()
                    .map(|(w, delta, factor)| {
                        Some(w.ln() + gaussian_log_density(prev, delta, factor, sample)?)
                    })
                    .collect::<Option<_>>()?;
                Some(crate::motion_model::log_sum_exp(&logs))
            }
        }
    }

    /// `ln p_motion(sample) − ln q(sample)`: what the importance weight of
    /// `sample` adds to its scan log-likelihood. 0 for the motion proposal
    /// (the densities cancel) and for a motion model without a density.
    pub fn log_ratio<const D: usize>(
        &self,
        motion: &dyn MotionModel<D, P>,
        prev: &P,
        odometry: &P,
        sample: &P,
    ) -> f64
    where
        P: Pose<D>,
    {
        match (
            self.log_density::<D>(prev, sample),
            motion.log_density(prev, odometry, sample),
        ) {
            (Some(q), Some(p)) => p - q,
            _ => 0.0,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::{Pose2, pose2};
    use crate::motion_model::Exact;
    use rand::SeedableRng;

    #[test]
    fn matched_samples_spread_as_the_covariance_says_in_the_body_frame() {
        // Heading +90°: body x is map y.
        let prev = pose2(1.0, 2.0, std::f64::consts::FRAC_PI_2);
        let delta = pose2(0.5, 0.0, 0.0);
        let sd = [0.01, 0.04, 0.002];
        let cov = DMatrix::from_diagonal(&DVector::from_iterator(3, sd.iter().map(|s| s * s)));
        let prop = Proposal::matched(delta, cov).unwrap();
        let mut rng = Pcg64::seed_from_u64(1);
        let n = 20000;
        let mut sq = [0.0; 3];
        let mean = prev * delta;
        for _ in 0..n {
            let p: Pose2 = prop.sample::<2>(&Exact, &prev, &pose2(9.0, 9.0, 1.0), &mut rng);
            let e = mean.inverse() * p;
            let v = [e.translation.x, e.translation.y, e.rotation.angle()];
            for k in 0..3 {
                sq[k] += v[k] * v[k];
            }
        }
        for k in 0..3 {
            let got = (sq[k] / n as f64).sqrt();
            assert!((got - sd[k]).abs() < 0.05 * sd[k], "{k}: {got}");
        }
    }

    #[test]
    fn a_mixture_draws_each_part_by_its_probability_and_has_the_mixture_density() {
        let prev = pose2(1.0, 2.0, 0.4);
        let cov = DMatrix::from_diagonal(&DVector::from_vec(vec![1e-4, 1e-4, 1e-5]));
        let a = Proposal::matched(pose2(0.5, 0.0, 0.0), cov.clone()).unwrap();
        let b = Proposal::matched(pose2(0.8, 0.1, 0.2), cov.clone()).unwrap();
        let factor = cov.cholesky().unwrap().l();
        let mix = Proposal::Mixture(vec![
            (0.75, pose2(0.5, 0.0, 0.0), factor.clone()),
            (0.25, pose2(0.8, 0.1, 0.2), factor),
        ]);
        let mut rng = Pcg64::seed_from_u64(3);
        let n = 20000;
        let near_b = (0..n)
            .filter(|_| {
                let p: Pose2 = mix.sample::<2>(&Exact, &prev, &pose2(0.0, 0.0, 0.0), &mut rng);
                let e = (prev * pose2(0.8, 0.1, 0.2)).inverse() * p;
                e.translation.vector.norm() < 0.1
            })
            .count();
        let share = near_b as f64 / n as f64;
        assert!((share - 0.25).abs() < 0.015, "{share}");
        // Between the two means, the density is the weighted sum of both.
        for s in [
            pose2(0.5, 0.0, 0.0),
            pose2(0.6, 0.02, 0.05),
            pose2(0.8, 0.1, 0.2),
        ] {
            let at = prev * s;
            let pa = a.log_density::<2>(&prev, &at).unwrap().exp();
            let pb = b.log_density::<2>(&prev, &at).unwrap().exp();
            let pm = mix.log_density::<2>(&prev, &at).unwrap();
            let want = (0.75 * pa + 0.25 * pb).ln();
            assert!(
                (pm - want).abs() < 1e-9 * want.abs().max(1.0),
                "{pm} {want}"
            );
        }
        assert!(mix.is_matched() && a.is_matched());
        assert!(!Proposal::<Pose2>::Motion.is_matched());
    }

    #[test]
    fn a_singular_covariance_is_no_matched_proposal() {
        let cov = DMatrix::<f64>::zeros(3, 3);
        assert!(Proposal::matched(pose2(0.0, 0.0, 0.0), cov).is_none());
    }

    #[test]
    fn the_motion_proposal_is_the_motion_model() {
        let mut a = Pcg64::seed_from_u64(2);
        let p: Pose2 = Proposal::Motion.sample::<2>(
            &Exact,
            &pose2(1.0, 0.0, 0.0),
            &pose2(1.0, 0.0, 0.5),
            &mut a,
        );
        assert_eq!(p, pose2(1.0, 0.0, 0.0) * pose2(1.0, 0.0, 0.5));
    }
}
