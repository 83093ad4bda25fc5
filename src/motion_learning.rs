//! Learning the 2-D motion model from the log itself (dissertation ch. 6;
//! Eliazar & Parr, ICML 2004): expectation–maximisation with SLAM in the loop.
//!
//! The release's C/D/T constants were learned for one ATRV Jr on carpet; on
//! another robot they are too wide (samples wasted far from the truth) or too
//! narrow (the filter loses the track). Each EM round here:
//!
//! - **E-step**: a SLAM run with the current model gives the best particle's
//!   trajectory; each processed step yields a pair (odometry motion, motion
//!   of the trajectory), both in the previous robot frame ([`MotionSample`]).
//! - **M-step** ([`fit_cdt`]): per component (D along the mean heading, C
//!   across it, T turn) the mean is fitted as linear in the odometry's `d`
//!   and `t` by weighted least squares, and the variance as
//!   `σ² = α·d² + β·t² + γ` (α, β, γ ≥ 0) by iteratively reweighted
//!   non-negative least squares on the squared residuals (weights 1/σ⁴, the
//!   variance of a squared Gaussian residual, which makes it the Gaussian
//!   maximum-likelihood fit). Steps more than [`LearnOptions::outlier_sigmas`]
//!   from the first fit are left out (a loss of track is not motion noise).
//!
//! The variance form is mapped onto the C/D/T model's `std = max(|a·d| +
//! |b·t|, floor)` with `a = √α`, `b = √β`, `floor = √γ`: the model's std is
//! then never below the fitted one, and equal to it for pure translation,
//! pure rotation and standing still. C and D share one floor in the model
//! (`min_std_xy`), the larger of their two. Floors are kept at or above
//! [`LearnOptions::min_std_xy`] and [`LearnOptions::min_std_t`]: a proposal
//! much narrower than a grid cell cannot be told apart by the map, and a
//! model learned from a filter's own output must not shrink to nothing.

use crate::config::Motion2dConfig;
use crate::geometry::Pose2;
use crate::motion_model::cdt_of;
use crate::{Error, Result};
use serde::Serialize;

/// One processed step: what odometry reported and what the SLAM trajectory
/// did, each as a relative pose in the previous robot frame (m, rad).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MotionSample {
    /// Odometry motion between the two scans.
    pub odometry: Pose2,
    /// Motion of the estimated trajectory between the same two scans.
    pub estimate: Pose2,
}

/// Settings of [`fit_cdt`].
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct LearnOptions {
    /// Lower bound of the learned C/D floor, m.
    pub min_std_xy: f64,
    /// Lower bound of the learned T floor, rad.
    pub min_std_t: f64,
    /// Steps whose residual exceeds this many stds of the first fit (in any
    /// component) are left out of the final fit.
    pub outlier_sigmas: f64,
    /// Reweighting rounds of the variance fit.
    pub rounds: usize,
    /// Factor on every learned std (slopes and floors) of the model the
    /// filter samples from.
    pub inflation: f64,
}

impl LearnOptions {
    /// The options of `cfg` (`[motion_learning]`) for its grid, with 5
    /// reweighting rounds.
    pub fn from_config(cfg: &crate::config::Config) -> Self {
        let m = &cfg.motion_learning;
        Self {
            min_std_xy: m.min_std_xy_cells * cfg.cell_size(),
            min_std_t: m.min_std_t,
            outlier_sigmas: m.outlier_sigmas,
            rounds: 5,
            inflation: m.inflation,
        }
    }
}

/// Fewer steps than this cannot pin down 2 mean and 3 variance terms
/// per component with any confidence.
pub const MIN_STEPS: usize = 20;

/// The fit of one component (D, C or T).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct ComponentFit {
    /// Mean `[k_d, k_t]`: `k_d·d + k_t·t` (D, T) or added to the odometry's C.
    pub mean: [f64; 2],
    /// Variance terms `[α (per m²), β (per rad²), γ]`: `σ² = α·d² + β·t² + γ`,
    /// in m² (D, C) or rad² (T).
    pub variance: [f64; 3],
    /// Root mean square of the residuals, m or rad.
    pub rms: f64,
}

/// What [`fit_cdt`] learned.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct MotionFit {
    /// The learned model (`sensor_offset` kept from the prior).
    pub model: Motion2dConfig,
    /// Fits of D, C and T.
    pub d: ComponentFit,
    /// Fit of C.
    pub c: ComponentFit,
    /// Fit of T.
    pub t: ComponentFit,
    /// Steps used.
    pub steps: usize,
    /// Steps left out as outliers.
    pub outliers: usize,
    /// Mean log-likelihood per step of the samples under the prior model.
    pub prior_log_likelihood: f64,
    /// The same under the learned model (higher is a better explanation).
    pub log_likelihood: f64,
}

/// Odometry `(d, c, t)` and the estimate's `(D, C, T)` of one sample, the
/// turn of the estimate unwrapped next to the odometry's.
fn components(s: &MotionSample) -> ([f64; 3], [f64; 3]) {
    let (d, c, t) = cdt_of(&s.odometry);
    let (ed, ec, et) = cdt_of(&s.estimate);
    ([d, c, t], [ed, ec, et])
}

/// The component's regression target: D and T as they are, C minus the
/// odometry's C (the model adds its mean to it).
fn target(k: usize, odo: [f64; 3], est: [f64; 3]) -> f64 {
    if k == 1 { est[1] - odo[1] } else { est[k] }
}

/// σ of the C/D/T model for odometry `(d, t)` (see `CdtModel::sample`).
fn model_std(std: [f64; 2], floor: f64, d: f64, t: f64) -> f64 {
    ((std[0] * d).abs() + (std[1] * t).abs()).max(floor)
}

/// Means and stds of the model per component: `(mean, std, floor)`.
fn model_terms(m: &Motion2dConfig) -> [([f64; 2], [f64; 2], f64); 3] {
    [
        (m.mean_d, m.std_d, m.min_std_xy),
        (m.mean_c, m.std_c, m.min_std_xy),
        (m.mean_t, m.std_t, m.min_std_t),
    ]
}

/// Mean log-likelihood per sample under the C/D/T model `m`.
pub fn mean_log_likelihood(m: &Motion2dConfig, samples: &[MotionSample]) -> f64 {
    let terms = model_terms(m);
    let total: f64 = samples
        .iter()
        .map(|s| {
            let (odo, est) = components(s);
            (0..3)
                .map(|k| {
                    let (mean, std, floor) = terms[k];
                    let sigma = model_std(std, floor, odo[0], odo[2]);
                    let r = target(k, odo, est) - (mean[0] * odo[0] + mean[1] * odo[2]);
                    -0.5 * (r / sigma).powi(2) - sigma.ln() - 0.5 * std::f64::consts::TAU.ln()
                })
                .sum::<f64>()
        })
        .sum();
    total / samples.len().max(1) as f64
}

/// Solves the 2×2 (or 3×3) normal equations `a·x = b` by Gaussian
/// elimination with partial pivoting; `None` when singular.
fn solve<const N: usize>(mut a: [[f64; N]; N], mut b: [f64; N]) -> Option<[f64; N]> {
    let scale = a
        .iter()
        .flatten()
        .fold(0.0f64, |m, v| m.max(v.abs()))
        .max(f64::MIN_POSITIVE);
    for col in 0..N {
        let piv = (col..N).max_by(|&i, &j| a[i][col].abs().total_cmp(&a[j][col].abs()))?;
        if a[piv][col].abs() <= 1e-12 * scale {
            return None;
        }
        a.swap(col, piv);
        b.swap(col, piv);
        let (pivot, pb) = (a[col], b[col]);
        for row in col + 1..N {
            let f = a[row][col] / pivot[col];
            for (v, p) in a[row].iter_mut().zip(pivot).skip(col) {
                *v -= f * p;
            }
            b[row] -= f * pb;
        }
    }
    let mut x = [0.0; N];
    for row in (0..N).rev() {
        let s: f64 = (row + 1..N).map(|k| a[row][k] * x[k]).sum();
        x[row] = (b[row] - s) / a[row][row];
    }
    Some(x)
}

/// Weighted least squares of `y` on the regressors `x` restricted to the
/// columns in `active`, the others fixed at 0: the coefficients and the
/// weighted squared error.
fn wls<const N: usize>(
    rows: &[([f64; N], f64, f64)],
    active: [bool; N],
) -> Option<([f64; N], f64)> {
    let mut a = [[0.0; N]; N];
    let mut b = [0.0; N];
    for (x, y, w) in rows {
        for i in 0..N {
            b[i] += w * x[i] * y;
            for j in 0..N {
                a[i][j] += w * x[i] * x[j];
            }
        }
    }
    // Inactive columns: the identity row pins the coefficient at 0.
    for i in 0..N {
        if !active[i] {
            a[i] = [0.0; N];
            a[i][i] = 1.0;
            b[i] = 0.0;
            for (j, row) in a.iter_mut().enumerate() {
                if j != i {
                    row[i] = 0.0;
                }
            }
        }
    }
    let coef = solve(a, b)?;
    let err = rows
        .iter()
        .map(|(x, y, w)| w * (y - (0..N).map(|i| coef[i] * x[i]).sum::<f64>()).powi(2))
        .sum();
    Some((coef, err))
}

/// Non-negative weighted least squares with three coefficients: the best
/// of the feasible solutions over every set of free coefficients (an exact
/// active-set search, 7 candidates).
fn nnls3(rows: &[([f64; 3], f64, f64)]) -> [f64; 3] {
    let mut best: Option<([f64; 3], f64)> = None;
    for mask in 1u8..8 {
        let active = [mask & 1 != 0, mask & 2 != 0, mask & 4 != 0];
        if let Some((coef, err)) = wls(rows, active)
            && coef.iter().all(|&c| c >= 0.0)
            && best.is_none_or(|b| err < b.1)
        {
            best = Some((coef, err));
        }
    }
    best.map_or([0.0; 3], |b| b.0)
}

/// Fits one component's mean and variance to `rows` of `(d, t, y)` starting
/// from the prior's σ per row.
fn fit_component(rows: &[(f64, f64, f64)], prior_sigma: &[f64], rounds: usize) -> ComponentFit {
    let mut sigma2: Vec<f64> = prior_sigma.iter().map(|s| s * s).collect();
    let mut mean = [0.0; 2];
    let mut variance = [0.0; 3];
    for _ in 0..rounds.max(1) {
        let m_rows: Vec<([f64; 2], f64, f64)> = rows
            .iter()
            .zip(&sigma2)
            .map(|(&(d, t, y), &s2)| ([d, t], y, 1.0 / s2))
            .collect();
        mean = wls(&m_rows, [true, true]).map_or(mean, |m| m.0);
        let v_rows: Vec<([f64; 3], f64, f64)> = rows
            .iter()
            .zip(&sigma2)
            .map(|(&(d, t, y), &s2)| {
                let r = y - (mean[0] * d + mean[1] * t);
                ([d * d, t * t, 1.0], r * r, 1.0 / (s2 * s2))
            })
            .collect();
        variance = nnls3(&v_rows);
        for (s2, &(d, t, _)) in sigma2.iter_mut().zip(rows) {
            // Keep weights finite where the fit says "no noise at all".
            let floor = 1e-6 * prior_sigma[0].powi(2).max(f64::MIN_POSITIVE);
            *s2 = (variance[0] * d * d + variance[1] * t * t + variance[2]).max(floor);
        }
    }
    let rms = (rows
        .iter()
        .map(|&(d, t, y)| (y - (mean[0] * d + mean[1] * t)).powi(2))
        .sum::<f64>()
        / rows.len().max(1) as f64)
        .sqrt();
    ComponentFit {
        mean,
        variance,
        rms,
    }
}

/// Fits all three components to `samples` (see the module docs), starting
/// from `prior` (its σ gives the first weights), and returns the learned
/// model with how well each explains the samples.
pub fn fit_cdt(
    samples: &[MotionSample],
    prior: &Motion2dConfig,
    opts: &LearnOptions,
) -> Result<MotionFit> {
    if samples.len() < MIN_STEPS {
        return Err(Error::Invalid(format!(
            "motion learning needs at least {MIN_STEPS} processed steps, the run has {}",
            samples.len()
        )));
    }
    let comps: Vec<([f64; 3], [f64; 3])> = samples.iter().map(components).collect();
    let terms = model_terms(prior);
    let fit_all = |keep: &[bool]| -> [ComponentFit; 3] {
        std::array::from_fn(|k| {
            let (_, std, floor) = terms[k];
            let (rows, sig): (Vec<_>, Vec<_>) = comps
                .iter()
                .zip(keep)
                .filter(|(_, k)| **k)
                .map(|((odo, est), _)| {
                    (
                        (odo[0], odo[2], target(k, *odo, *est)),
                        model_std(std, floor, odo[0], odo[2]),
                    )
                })
                .unzip();
            fit_component(&rows, &sig, opts.rounds)
        })
    };
    let first = fit_all(&vec![true; comps.len()]);
    let keep: Vec<bool> = comps
        .iter()
        .map(|(odo, est)| {
            (0..3).all(|k| {
                let f = &first[k];
                let (d, t) = (odo[0], odo[2]);
                let r = target(k, *odo, *est) - (f.mean[0] * d + f.mean[1] * t);
                let s2 = f.variance[0] * d * d + f.variance[1] * t * t + f.variance[2];
                r * r <= opts.outlier_sigmas.powi(2) * s2
            })
        })
        .collect();
    let kept = keep.iter().filter(|k| **k).count();
    let fits = if kept >= MIN_STEPS && kept < comps.len() {
        fit_all(&keep)
    } else {
        first
    };
    let [fd, fc, ft] = fits;
    let k = opts.inflation;
    let std_of = |f: &ComponentFit| [k * f.variance[0].sqrt(), k * f.variance[1].sqrt()];
    let model = Motion2dConfig {
        mean_d: fd.mean,
        mean_c: fc.mean,
        mean_t: ft.mean,
        std_d: std_of(&fd),
        std_c: std_of(&fc),
        std_t: std_of(&ft),
        min_std_xy: (k * fd.variance[2].sqrt().max(fc.variance[2].sqrt())).max(opts.min_std_xy),
        min_std_t: (k * ft.variance[2].sqrt()).max(opts.min_std_t),
        sensor_offset: prior.sensor_offset,
    };
    let used: Vec<MotionSample> = samples
        .iter()
        .zip(&keep)
        .filter(|(_, k)| **k || kept < MIN_STEPS)
        .map(|(s, _)| *s)
        .collect();
    Ok(MotionFit {
        prior_log_likelihood: mean_log_likelihood(prior, &used),
        log_likelihood: mean_log_likelihood(&model, &used),
        model,
        d: fd,
        c: fc,
        t: ft,
        steps: used.len(),
        outliers: samples.len() - used.len(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::motion_model::{CdtModel, MotionModel};
    use rand::SeedableRng;
    use rand_distr::{Distribution, StandardNormal};
    use rand_pcg::Pcg64;

    /// Odometry motions of a robot that drives and turns by varying amounts.
    fn odometry(n: usize, rng: &mut Pcg64) -> Vec<Pose2> {
        (0..n)
            .map(|i| {
                let d = 0.05 + 0.6 * ((i * 37 % 101) as f64 / 100.0);
                let t = 0.8 * (((i * 53 % 97) as f64 / 96.0) - 0.5);
                let c: f64 = StandardNormal.sample(rng);
                let (s, co) = (t / 2.0).sin_cos();
                let c = 0.01 * c;
                crate::geometry::pose2(d * co - c * s, d * s + c * co, t)
            })
            .collect()
    }

    #[test]
    fn recovers_the_model_that_generated_the_motions() {
        let truth = Motion2dConfig {
            mean_d: [0.97, 0.02],
            mean_c: [0.01, -0.005],
            mean_t: [0.004, 1.03],
            std_d: [0.04, 0.02],
            std_c: [0.03, 0.01],
            std_t: [0.01, 0.05],
            min_std_xy: 0.01,
            min_std_t: 0.008,
            sensor_offset: None,
        };
        let model = CdtModel { cfg: truth.clone() };
        let mut rng = Pcg64::seed_from_u64(3);
        let origin = Pose2::identity();
        let samples: Vec<MotionSample> = odometry(4000, &mut rng)
            .into_iter()
            .map(|o| MotionSample {
                odometry: o,
                estimate: model.sample(&origin, &o, &mut rng),
            })
            .collect();
        let prior = Motion2dConfig::default();
        let fit = fit_cdt(
            &samples,
            &prior,
            &LearnOptions::from_config(&crate::config::Config::default()),
        )
        .unwrap();
        let m = &fit.model;
        let close = |a: f64, b: f64, tol: f64, what: &str| {
            assert!((a - b).abs() <= tol, "{what}: learned {a}, true {b}");
        };
        close(m.mean_d[0], 0.97, 0.005, "mean_d k_d");
        close(m.mean_t[1], 1.03, 0.01, "mean_t k_t");
        close(m.mean_c[0], 0.01, 0.005, "mean_c k_d");
        // The max(|a d| + |b t|, floor) form against the fitted
        // α d² + β t² + γ: the slopes come back within ~30 %.
        close(m.std_d[0], 0.04, 0.012, "std_d a");
        close(m.std_t[1], 0.05, 0.015, "std_t b");
        close(m.std_c[0], 0.03, 0.01, "std_c a");
        assert!(
            fit.log_likelihood > fit.prior_log_likelihood + 1.0,
            "{fit:?}"
        );
        // Each learned σ is close to the true one where it matters: the
        // learned model explains the data about as well as the truth does.
        let truth_ll = mean_log_likelihood(&truth, &samples);
        assert!(
            fit.log_likelihood > truth_ll - 0.1,
            "learned {} vs true {truth_ll}",
            fit.log_likelihood
        );
    }

    #[test]
    fn a_loss_of_track_is_left_out_and_floors_are_bounded() {
        let mut rng = Pcg64::seed_from_u64(9);
        let mut samples: Vec<MotionSample> = odometry(300, &mut rng)
            .into_iter()
            .map(|o| MotionSample {
                odometry: o,
                estimate: o,
            })
            .collect();
        // One step where the estimate jumped 2 m.
        samples[100].estimate = crate::geometry::pose2(2.0, 1.0, 0.5) * samples[100].estimate;
        let mut cfg = crate::config::Config::default();
        cfg.map.cells_per_metre = 20.0;
        let opts = LearnOptions::from_config(&cfg);
        let fit = fit_cdt(&samples, &Motion2dConfig::default(), &opts).unwrap();
        assert_eq!(fit.outliers, 1);
        // Noise-free motion: everything at the floors' lower bounds.
        assert!(
            (fit.model.min_std_xy - 0.025).abs() < 1e-12,
            "{:?}",
            fit.model
        );
        assert!((fit.model.min_std_t - 0.005).abs() < 1e-12);
        assert!(fit.model.std_d[0] < 1e-3 && fit.model.std_t[1] < 1e-3);
        assert!((fit.model.mean_d[0] - 1.0).abs() < 1e-6);
    }

    #[test]
    fn too_few_steps_is_an_error() {
        let s = MotionSample {
            odometry: Pose2::identity(),
            estimate: Pose2::identity(),
        };
        let e = fit_cdt(
            &[s; 5],
            &Motion2dConfig::default(),
            &LearnOptions::from_config(&crate::config::Config::default()),
        );
        assert!(e.unwrap_err().to_string().contains("at least 20"));
    }

    #[test]
    fn nnls_keeps_coefficients_non_negative() {
        // y = 2·x0 − 1·x1 on positive data: the unconstrained fit has a
        // negative coefficient, the constrained one sets it to 0.
        let rows: Vec<([f64; 3], f64, f64)> = (1..50)
            .map(|i| {
                let x0 = i as f64;
                let x1 = (i % 7) as f64;
                ([x0, x1, 1.0], 2.0 * x0 - x1, 1.0)
            })
            .collect();
        let c = nnls3(&rows);
        assert!(c.iter().all(|&v| v >= 0.0), "{c:?}");
        assert!(c[1] == 0.0);
        assert_eq!(
            solve([[2.0, 1.0], [1.0, 3.0]], [3.0, 5.0]).map(|x| x.map(|v| (v * 1e9).round() / 1e9)),
            Some([0.8, 1.4])
        );
        assert!(solve([[1.0, 2.0], [2.0, 4.0]], [1.0, 2.0]).is_none());
    }
}
