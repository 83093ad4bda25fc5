//! Absolute trajectory error (ATE): the position error of an estimated
//! trajectory after the rigid motion that best aligns it with the truth.
//!
//! The estimate's world frame is arbitrary (SLAM starts wherever the robot
//! is), so it is first aligned to the truth by least squares on positions:
//! SE(2) (rotation about z + xy translation) when both trajectories are
//! planar, SE(3) (Horn/Umeyama without scale) otherwise. No scale is fitted:
//! a laser SLAM system knows metric scale, and fitting it would hide errors.

use crate::eval::relations::mean_std;
use crate::io::tum::{Stamped, TimeIndex};
use crate::{Error, Result};
use nalgebra::{Isometry3, Matrix3, Translation3, UnitQuaternion, Vector3};
use serde::Serialize;

/// Default association tolerance, s: the two trajectories' stamps must agree
/// to better than this to be paired.
pub const DEFAULT_MAX_DT_S: f64 = 0.01;

/// A pose counts as planar when |z| (m) and the x, y components of its unit
/// quaternion are below this. Files written by [`crate::io::tum`] print 9
/// decimals, so a 2-D trajectory read back is planar to ~1e-9.
pub const PLANAR_EPS: f64 = 1e-6;

/// Which rigid alignment to fit.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Alignment {
    /// SE(2) when both matched trajectories are planar, SE(3) otherwise.
    #[default]
    Auto,
    /// Always SE(3).
    Se3,
}

/// The alignment that was fitted.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum AlignmentKind {
    /// Rotation about z and translation in x, y.
    Se2,
    /// Full 3-D rotation and translation.
    Se3,
}

impl std::fmt::Display for AlignmentKind {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            AlignmentKind::Se2 => "SE(2)",
            AlignmentKind::Se3 => "SE(3)",
        })
    }
}

/// Options of [`evaluate_ate`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AteOptions {
    /// Largest time difference (s) between paired truth and estimate stamps.
    pub max_dt_s: f64,
    /// Alignment to fit.
    pub alignment: Alignment,
}

impl Default for AteOptions {
    fn default() -> Self {
        Self {
            max_dt_s: DEFAULT_MAX_DT_S,
            alignment: Alignment::Auto,
        }
    }
}

/// Absolute trajectory error after alignment.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct AteReport {
    /// Number of matched (truth, estimate) pose pairs.
    pub n: usize,
    /// The alignment fitted.
    pub alignment: AlignmentKind,
    /// Root mean square of the position errors, m.
    pub rmse_m: f64,
    /// Mean position error, m.
    pub mean_m: f64,
    /// Median position error, m.
    pub median_m: f64,
    /// Largest position error, m.
    pub max_m: f64,
    /// Mean rotation angle between aligned estimate and truth orientations, degrees.
    pub rot_mean_deg: f64,
}

impl std::fmt::Display for AteReport {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "ate: {} poses, {} alignment, rmse {:.3} m, mean {:.3} m, median {:.3} m, max {:.3} m, rotation {:.2} deg",
            self.n,
            self.alignment,
            self.rmse_m,
            self.mean_m,
            self.median_m,
            self.max_m,
            self.rot_mean_deg
        )
    }
}

/// Pairs truth and estimate poses one-to-one by time stamp: each estimate
/// proposes its nearest truth stamp within `max_dt_s` (s); candidate pairs are
/// accepted closest first, and a pose already paired is not reused (as TUM's
/// `associate.py`). Returns `(truth index, estimate index)` sorted by truth time.
pub fn associate(truth: &[Stamped], estimate: &[Stamped], max_dt_s: f64) -> Vec<(usize, usize)> {
    let index = TimeIndex::new(truth);
    let mut cand: Vec<(f64, usize, usize)> = estimate
        .iter()
        .enumerate()
        .filter_map(|(j, e)| index.nearest(e.t, max_dt_s).map(|(i, dt)| (dt, i, j)))
        .collect();
    cand.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)).then(a.2.cmp(&b.2)));
    let mut truth_used = vec![false; truth.len()];
    let mut pairs = Vec::with_capacity(cand.len());
    // Each estimate appears at most once among the candidates, so only truth
    // poses can be claimed twice.
    for (_, i, j) in cand {
        if !truth_used[i] {
            truth_used[i] = true;
            pairs.push((i, j));
        }
    }
    pairs.sort_by(|a, b| truth[a.0].t.total_cmp(&truth[b.0].t).then(a.1.cmp(&b.1)));
    pairs
}

fn is_planar(p: &Isometry3<f64>) -> bool {
    let q = p.rotation.quaternion();
    p.translation.z.abs() <= PLANAR_EPS && q.i.abs() <= PLANAR_EPS && q.j.abs() <= PLANAR_EPS
}

fn centroid(pts: &[Vector3<f64>]) -> Vector3<f64> {
    pts.iter().sum::<Vector3<f64>>() / pts.len() as f64
}

/// The rotation about z and xy translation S minimising Σ‖dst − S·src‖² over
/// the x, y components (m); z is carried through unchanged. Closed form: the
/// angle is atan2 of the summed cross and dot products of the centred points.
/// `src` and `dst` have equal, non-zero length.
pub fn align_se2(src: &[Vector3<f64>], dst: &[Vector3<f64>]) -> Isometry3<f64> {
    let (cs, cd) = (centroid(src), centroid(dst));
    let (mut cross, mut dot) = (0.0, 0.0);
    for (s, d) in src.iter().zip(dst) {
        let (s, d) = (s - cs, d - cd);
        cross += s.x * d.y - s.y * d.x;
        dot += s.x * d.x + s.y * d.y;
    }
    let rot = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), cross.atan2(dot));
    let mut t = cd - rot * cs;
    t.z = 0.0;
    Isometry3::from_parts(Translation3::from(t), rot)
}

/// The rigid transform S (proper rotation, no scale) minimising
/// Σ‖dst − S·src‖² (m), by Umeyama's method: SVD of the cross-covariance,
/// with the sign of the last singular direction flipped when the best
/// orthogonal matrix would be a reflection. `src` and `dst` have equal,
/// non-zero length. With collinear points the rotation about their line is
/// undetermined and one minimiser is returned.
pub fn align_se3(src: &[Vector3<f64>], dst: &[Vector3<f64>]) -> Isometry3<f64> {
    let (cs, cd) = (centroid(src), centroid(dst));
    // H = Σ (dst − c_d)(src − c_s)ᵀ; the best rotation is U·diag(1,1,d)·Vᵀ.
    let h: Matrix3<f64> = src
        .iter()
        .zip(dst)
        .map(|(s, d)| (d - cd) * (s - cs).transpose())
        .sum();
    let svd = h.svd(true, true);
    let (u, v_t) = (svd.u.expect("requested U"), svd.v_t.expect("requested Vᵀ"));
    let d = (u * v_t).determinant().signum();
    let r = u * Matrix3::from_diagonal(&Vector3::new(1.0, 1.0, d)) * v_t;
    let rot = UnitQuaternion::from_matrix(&r);
    Isometry3::from_parts(Translation3::from(cd - rot * cs), rot)
}

/// Absolute trajectory error of `estimate` against `truth` (poses in any
/// order, metres, each in its own world frame). Poses are paired by
/// [`associate`]; the estimate is aligned to the truth (see [`Alignment`]);
/// the report gives position error statistics (m) and the mean rotation error
/// (deg) of the aligned estimate. Errors: a non-positive or non-finite
/// `max_dt_s`, non-finite poses, and fewer than 2 pairs.
pub fn evaluate_ate(
    truth: &[Stamped],
    estimate: &[Stamped],
    opts: &AteOptions,
) -> Result<AteReport> {
    if !(opts.max_dt_s.is_finite() && opts.max_dt_s >= 0.0) {
        return Err(Error::Config(format!(
            "association tolerance must be a finite number of seconds ≥ 0, got {}",
            opts.max_dt_s
        )));
    }
    for (name, traj) in [("truth", truth), ("estimate", estimate)] {
        if let Some((i, s)) = traj.iter().enumerate().find(|(_, s)| !s.is_finite()) {
            return Err(Error::Invalid(format!(
                "{name} pose {} (t = {}) is not finite",
                i + 1,
                s.t
            )));
        }
    }
    let pairs = associate(truth, estimate, opts.max_dt_s);
    if pairs.len() < 2 {
        return Err(Error::Invalid(format!(
            "only {} of {} estimate poses match a truth pose (of {}) within {} s; \
             at least 2 are needed to align (are the time stamps in the same clock?)",
            pairs.len(),
            estimate.len(),
            truth.len(),
            opts.max_dt_s
        )));
    }
    let gt: Vec<Isometry3<f64>> = pairs.iter().map(|&(i, _)| truth[i].pose).collect();
    let est: Vec<Isometry3<f64>> = pairs.iter().map(|&(_, j)| estimate[j].pose).collect();
    let gt_pos: Vec<Vector3<f64>> = gt.iter().map(|p| p.translation.vector).collect();
    let est_pos: Vec<Vector3<f64>> = est.iter().map(|p| p.translation.vector).collect();
    let planar = gt.iter().chain(&est).all(is_planar);
    let (kind, s) = if opts.alignment == Alignment::Auto && planar {
        (AlignmentKind::Se2, align_se2(&est_pos, &gt_pos))
    } else {
        (AlignmentKind::Se3, align_se3(&est_pos, &gt_pos))
    };
    let mut errs = Vec::with_capacity(gt.len());
    let mut rot = Vec::with_capacity(gt.len());
    for (g, e) in gt.iter().zip(&est) {
        let aligned = s * e;
        errs.push((aligned.translation.vector - g.translation.vector).norm());
        rot.push(
            (g.rotation.inverse() * aligned.rotation)
                .angle()
                .to_degrees(),
        );
    }
    let n = errs.len();
    let rmse_m = (errs.iter().map(|e| e * e).sum::<f64>() / n as f64).sqrt();
    let (mean_m, _) = mean_std(&errs);
    let (rot_mean_deg, _) = mean_std(&rot);
    let max_m = errs.iter().copied().fold(0.0, f64::max);
    errs.sort_by(f64::total_cmp);
    let median_m = if n % 2 == 1 {
        errs[n / 2]
    } else {
        0.5 * (errs[n / 2 - 1] + errs[n / 2])
    };
    Ok(AteReport {
        n,
        alignment: kind,
        rmse_m,
        mean_m,
        median_m,
        max_m,
        rot_mean_deg,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::eval::relations::pose_from_xyz_rpy;
    use rand::SeedableRng;
    use rand_distr::{Distribution, Normal};

    /// A planar figure-of-eight, 1 pose per 0.1 s, heading along the path.
    fn eight(n: usize) -> Vec<Stamped> {
        (0..n)
            .map(|i| {
                let s = i as f64 * 0.05;
                let (x, y) = (4.0 * s.sin(), 2.0 * (2.0 * s).sin());
                let th = (4.0 * (2.0 * s).cos()).atan2(4.0 * s.cos());
                Stamped::planar(1000.0 + i as f64 * 0.1, x, y, th)
            })
            .collect()
    }

    /// A 3-D helix with roll and pitch.
    fn helix(n: usize) -> Vec<Stamped> {
        (0..n)
            .map(|i| {
                let s = i as f64 * 0.05;
                Stamped::new(
                    i as f64 * 0.1,
                    pose_from_xyz_rpy(
                        3.0 * s.cos(),
                        3.0 * s.sin(),
                        0.5 * s,
                        0.3 * s.sin(),
                        0.2 * s.cos(),
                        s,
                    ),
                )
            })
            .collect()
    }

    fn moved(traj: &[Stamped], g: Isometry3<f64>, dt: f64) -> Vec<Stamped> {
        traj.iter()
            .map(|s| Stamped::new(s.t + dt, g * s.pose))
            .collect()
    }

    #[test]
    fn rigidly_moved_planar_copy_has_zero_error() {
        let truth = eight(200);
        let g = pose_from_xyz_rpy(12.0, -7.0, 0.0, 0.0, 0.0, 2.5);
        let est = moved(&truth, g, 0.003);
        let r = evaluate_ate(&truth, &est, &AteOptions::default()).unwrap();
        assert_eq!((r.n, r.alignment), (200, AlignmentKind::Se2));
        assert!(
            r.rmse_m < 1e-9 && r.max_m < 1e-9 && r.rot_mean_deg < 1e-6,
            "{r}"
        );
        // SE(3) on the same data also aligns exactly.
        let opts = AteOptions {
            alignment: Alignment::Se3,
            ..Default::default()
        };
        let r = evaluate_ate(&truth, &est, &opts).unwrap();
        assert_eq!(r.alignment, AlignmentKind::Se3);
        assert!(r.rmse_m < 1e-9 && r.rot_mean_deg < 1e-6, "{r}");
    }

    #[test]
    fn rigidly_moved_3d_copy_with_roll_and_pitch_has_zero_error() {
        let truth = helix(150);
        let g = pose_from_xyz_rpy(-4.0, 9.0, 2.0, 0.7, -0.5, 1.9);
        let est = moved(&truth, g, -0.002);
        let r = evaluate_ate(&truth, &est, &AteOptions::default()).unwrap();
        assert_eq!((r.n, r.alignment), (150, AlignmentKind::Se3));
        assert!(
            r.rmse_m < 1e-9 && r.max_m < 1e-9 && r.rot_mean_deg < 1e-6,
            "{r}"
        );
        // Without alignment the error would be large: the test can fail.
        let unaligned = truth
            .iter()
            .zip(&est)
            .map(|(a, b)| (a.pose.translation.vector - b.pose.translation.vector).norm())
            .fold(0.0, f64::max);
        assert!(unaligned > 5.0);
    }

    #[test]
    fn se3_alignment_never_returns_a_reflection() {
        // A mirror image is best fitted by a reflection; Umeyama must return a
        // proper rotation instead, and a worse but honest error.
        let src: Vec<Vector3<f64>> = [
            [0.0, 0.0, 0.0],
            [1.0, 0.0, 0.0],
            [0.0, 2.0, 0.0],
            [0.0, 0.0, 3.0],
            [1.0, 1.0, 1.0],
        ]
        .iter()
        .map(|p| Vector3::from(*p))
        .collect();
        let dst: Vec<Vector3<f64>> = src.iter().map(|p| Vector3::new(p.x, p.y, -p.z)).collect();
        let s = align_se3(&src, &dst);
        let r = s.rotation.to_rotation_matrix().into_inner();
        assert!((r.determinant() - 1.0).abs() < 1e-9);
        assert!((r.transpose() * r - Matrix3::identity()).norm() < 1e-9);
        // Coplanar points rotated in 3-D (rank-2 cross-covariance, where the
        // sign of the third direction is arbitrary) are aligned exactly.
        let flat: Vec<Vector3<f64>> = eight(60)
            .iter()
            .map(|s| s.pose.translation.vector)
            .collect();
        let g = pose_from_xyz_rpy(1.0, 2.0, 3.0, 2.0, 0.4, -1.0);
        let rotated: Vec<Vector3<f64>> = flat
            .iter()
            .map(|p| g * nalgebra::Point3::from(*p))
            .map(|p| p.coords)
            .collect();
        let s = align_se3(&flat, &rotated);
        assert!((s.inverse() * g).rotation.angle() < 1e-9);
        assert!((s.translation.vector - g.translation.vector).norm() < 1e-9);
    }

    #[test]
    fn gaussian_position_noise_gives_rayleigh_statistics() {
        // Planar noise N(0, σ²) per axis: the error norm is Rayleigh(σ), with
        // rmse σ√2, mean σ√(π/2), median σ√(2 ln 2). The alignment absorbs
        // only 3 of 2n degrees of freedom, a negligible bias for n = 4000.
        let truth = eight(4000);
        let sigma = 0.05;
        let noise = Normal::new(0.0, sigma).unwrap();
        let mut rng = rand_pcg::Pcg64::seed_from_u64(7);
        let g = pose_from_xyz_rpy(3.0, 1.0, 0.0, 0.0, 0.0, -0.7);
        let est: Vec<Stamped> = truth
            .iter()
            .map(|s| {
                let mut p = s.pose;
                p.translation.x += noise.sample(&mut rng);
                p.translation.y += noise.sample(&mut rng);
                Stamped::new(s.t, g * p)
            })
            .collect();
        let r = evaluate_ate(&truth, &est, &AteOptions::default()).unwrap();
        let close = |got: f64, want: f64| (got / want - 1.0).abs() < 0.04;
        assert!(close(r.rmse_m, sigma * 2f64.sqrt()), "{r}");
        assert!(
            close(r.mean_m, sigma * std::f64::consts::FRAC_PI_2.sqrt()),
            "{r}"
        );
        assert!(close(r.median_m, sigma * (2.0 * 2f64.ln()).sqrt()), "{r}");
        assert!(r.max_m > 3.0 * sigma && r.max_m < 6.0 * sigma, "{r}");
        assert!(r.rot_mean_deg < 0.05, "{r}");
    }

    #[test]
    fn orientation_errors_and_exact_statistics() {
        // Positions exact, so the alignment is the identity; headings off by
        // +2°, −4°, +6°, −8° give a mean rotation error of 5° (positions
        // alone decide the alignment).
        let truth: Vec<Stamped> = (0..4)
            .map(|i| Stamped::planar(i as f64, i as f64, (i * i) as f64, 0.3))
            .collect();
        let offs = [2.0f64, -4.0, 6.0, -8.0];
        let est: Vec<Stamped> = truth
            .iter()
            .zip(offs)
            .map(|(s, o)| {
                let p = s.pose.translation;
                Stamped::planar(s.t, p.x, p.y, 0.3 + o.to_radians())
            })
            .collect();
        let r = evaluate_ate(&truth, &est, &AteOptions::default()).unwrap();
        assert!(
            (r.rot_mean_deg - 5.0).abs() < 1e-9 && r.rmse_m < 1e-12,
            "{r}"
        );

        // Points on the x axis at x = 0..3 with y offsets +d, −d, −d, +d: the
        // offsets have zero mean and no moment about the centroid, so the
        // best alignment is the identity and every error is exactly d.
        let d = 0.25;
        let truth: Vec<Stamped> = (0..4)
            .map(|i| Stamped::planar(i as f64, i as f64, 0.0, 0.0))
            .collect();
        let est: Vec<Stamped> = truth
            .iter()
            .zip([d, -d, -d, d])
            .map(|(s, o)| Stamped::planar(s.t, s.pose.translation.x, o, 0.0))
            .collect();
        let r = evaluate_ate(&truth, &est, &AteOptions::default()).unwrap();
        for v in [r.rmse_m, r.mean_m, r.median_m, r.max_m] {
            assert!((v - d).abs() < 1e-12, "{r}");
        }
        assert!(r.rot_mean_deg < 1e-9);
    }

    #[test]
    fn association_is_nearest_one_to_one_within_tolerance() {
        let truth: Vec<Stamped> = [0.0, 1.0, 2.0, 3.0]
            .iter()
            .map(|&t| Stamped::planar(t, t, 0.0, 0.0))
            .collect();
        // 0.004 and 0.008 both want truth 0: the closer one wins; 1.02 is out
        // of tolerance; 2.009 pairs with 2; 3.0 exactly with 3.
        let est: Vec<Stamped> = [0.008, 0.004, 1.02, 2.009, 3.0]
            .iter()
            .map(|&t| Stamped::planar(t, t, 0.0, 0.0))
            .collect();
        assert_eq!(associate(&truth, &est, 0.01), vec![(0, 1), (2, 3), (3, 4)]);
        let r = evaluate_ate(&truth, &est, &AteOptions::default()).unwrap();
        assert_eq!(r.n, 3);
        // Tighter tolerance leaves fewer than 2 pairs: an error, not a report.
        let opts = AteOptions {
            max_dt_s: 0.001,
            ..Default::default()
        };
        let msg = evaluate_ate(&truth, &est, &opts).unwrap_err().to_string();
        assert!(msg.contains("only 1 of 5"), "{msg}");
        let bad = AteOptions {
            max_dt_s: f64::NAN,
            ..Default::default()
        };
        assert!(evaluate_ate(&truth, &est, &bad).is_err());
        let mut nan = est.clone();
        nan[2].pose.translation.y = f64::INFINITY;
        assert!(
            evaluate_ate(&truth, &nan, &AteOptions::default())
                .unwrap_err()
                .to_string()
                .contains("estimate pose 3")
        );
    }
}
