//! Relative-pose ("relations") error of Kümmerle et al. 2009, "On measuring
//! the accuracy of SLAM algorithms" (Autonomous Robots 27(4)).
//!
//! A relation says where the robot truly was at time t2 as seen from where it
//! was at time t1. The score compares it with the same relative motion in the
//! estimated trajectory, so it measures local consistency and does not depend
//! on the (arbitrary) world frame of the estimate. The evaluation works in
//! SE(3); a 2-D trajectory (z = 0, rotation about z) makes it SE(2).

use crate::io::tum::{Stamped, TimeIndex, is_data_line, parse_record};
use crate::{Error, Result};
use nalgebra::{Isometry3, Translation3, UnitQuaternion};
use serde::Serialize;
use std::path::Path;
use std::sync::Arc;

/// Largest time difference (s) between a relation's time stamp and the
/// trajectory pose it is matched to. Relations are stamped with the laser
/// scan times, which a trajectory written with 6 decimals reproduces to 1 µs.
pub const RELATION_TIME_TOLERANCE_S: f64 = 1e-3;

/// One ground-truth relation: the true pose at `t2` in the frame of the true
/// pose at `t1`.
#[derive(Debug, Clone, PartialEq)]
pub struct Relation {
    /// Time of the reference pose, s.
    pub t1: f64,
    /// Time of the related pose, s.
    pub t2: f64,
    /// Pose at `t2` expressed in the body frame at `t1` (m; maps points of
    /// the `t2` body frame into the `t1` body frame).
    pub rel: Isometry3<f64>,
    /// File the relation was read from, for error messages (`None` if built
    /// in code).
    pub source: Option<Arc<Path>>,
    /// 1-based line in `source`, or the 1-based position in the list when the
    /// relation was built in code.
    pub line: usize,
}

impl Relation {
    /// A relation built in code; `line` is its 1-based position, used in error
    /// messages.
    pub fn new(t1: f64, t2: f64, rel: Isometry3<f64>, line: usize) -> Self {
        Self {
            t1,
            t2,
            rel,
            source: None,
            line,
        }
    }

    /// An error about this relation, naming its file and line when known.
    fn error(&self, reason: String) -> Error {
        match &self.source {
            Some(p) => Error::at_line(p, self.line, reason),
            None => Error::Invalid(format!("relation {}: {reason}", self.line)),
        }
    }
}

/// The pose with translation `x y z` (m) and rotation
/// R = Rz(yaw)·Ry(pitch)·Rx(roll) (rad): roll about x first, then pitch about
/// y, then yaw about z, all about the fixed axes of the parent frame. This is
/// the convention of the relations files (and of ROS / nalgebra's
/// `from_euler_angles`).
pub fn pose_from_xyz_rpy(
    x: f64,
    y: f64,
    z: f64,
    roll: f64,
    pitch: f64,
    yaw: f64,
) -> Isometry3<f64> {
    Isometry3::from_parts(
        Translation3::new(x, y, z),
        UnitQuaternion::from_euler_angles(roll, pitch, yaw),
    )
}

/// Reads a relations file: one `t1 t2 x y z roll pitch yaw` per line (s, s,
/// m, rad; see [`pose_from_xyz_rpy`]). Blank lines and `#` comments are
/// skipped; gzip is decompressed transparently. Wrong field counts, non-numbers,
/// non-finite values and an empty file are errors naming the file and line.
pub fn read_relations(path: &Path) -> Result<Vec<Relation>> {
    const NAMES: [&str; 8] = ["t1", "t2", "x", "y", "z", "roll", "pitch", "yaw"];
    let source: Arc<Path> = Arc::from(path);
    let mut src = crate::io::source::TextSource::open(path)?;
    let mut out = Vec::new();
    while let Some((line_no, line)) = src.next_line()? {
        if !is_data_line(line) {
            continue;
        }
        let v = parse_record(path, line_no, line, &NAMES, "relation")?;
        out.push(Relation {
            t1: v[0],
            t2: v[1],
            rel: pose_from_xyz_rpy(v[2], v[3], v[4], v[5], v[6], v[7]),
            source: Some(Arc::clone(&source)),
            line: line_no,
        });
    }
    if out.is_empty() {
        return Err(Error::in_file(path, "no relations (empty file)"));
    }
    Ok(out)
}

/// The error of one relation.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct RelationError {
    /// Time of the reference pose, s.
    pub t1: f64,
    /// Time of the related pose, s.
    pub t2: f64,
    /// ‖t(E)‖, m, with E = (P1⁻¹·P2)·R⁻¹.
    pub trans_m: f64,
    /// Rotation angle of E, degrees in [0, 180].
    pub rot_deg: f64,
}

/// Accuracy summary over all relations. Standard deviations are population
/// ones (divided by n), so that one relation gives 0 rather than NaN.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct RelationsReport {
    /// Number of relations scored.
    pub n: usize,
    /// Mean translational error ‖t(E)‖, m.
    pub trans_mean_m: f64,
    /// Standard deviation of the translational error, m.
    pub trans_std_m: f64,
    /// Mean rotational error |angle(E)|, degrees.
    pub rot_mean_deg: f64,
    /// Standard deviation of the rotational error, degrees.
    pub rot_std_deg: f64,
}

impl std::fmt::Display for RelationsReport {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "relations: {} pairs, translation {:.3} ± {:.3} m, rotation {:.2} ± {:.2} deg",
            self.n, self.trans_mean_m, self.trans_std_m, self.rot_mean_deg, self.rot_std_deg
        )
    }
}

/// Mean and population standard deviation; (NaN, NaN) for no values.
pub(crate) fn mean_std(xs: &[f64]) -> (f64, f64) {
    let n = xs.len() as f64;
    let mean = xs.iter().sum::<f64>() / n;
    let var = xs.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / n;
    (mean, var.sqrt())
}

/// The error of every relation against `trajectory` (poses in any order).
/// P1, P2 are the trajectory poses nearest in time to `t1`, `t2` (within
/// [`RELATION_TIME_TOLERANCE_S`]), and E = (P1⁻¹·P2)·R⁻¹. A relation time with
/// no pose that close, or a non-finite relation, is an error naming the
/// relation's file and line and the time; a non-finite trajectory pose is an
/// error too.
pub fn relation_errors(
    relations: &[Relation],
    trajectory: &[Stamped],
) -> Result<Vec<RelationError>> {
    if let Some((i, s)) = trajectory.iter().enumerate().find(|(_, s)| !s.is_finite()) {
        return Err(Error::Invalid(format!(
            "trajectory pose {} (t = {}) is not finite",
            i + 1,
            s.t
        )));
    }
    let index = TimeIndex::new(trajectory);
    let find = |r: &Relation, t: f64, which: &str| {
        index
            .nearest(t, RELATION_TIME_TOLERANCE_S)
            .map(|(i, _)| trajectory[i].pose)
            .ok_or_else(|| {
                r.error(format!(
                    "no trajectory pose within {RELATION_TIME_TOLERANCE_S} s of {which} = {t:.6}"
                ))
            })
    };
    relations
        .iter()
        .map(|r| {
            let finite = r.t1.is_finite()
                && r.t2.is_finite()
                && r.rel.translation.vector.iter().all(|v| v.is_finite())
                && r.rel.rotation.coords.iter().all(|v| v.is_finite());
            if !finite {
                return Err(r.error("relation is not finite".into()));
            }
            let p1 = find(r, r.t1, "t1")?;
            let p2 = find(r, r.t2, "t2")?;
            let e = (p1.inverse() * p2) * r.rel.inverse();
            Ok(RelationError {
                t1: r.t1,
                t2: r.t2,
                trans_m: e.translation.vector.norm(),
                rot_deg: e.rotation.angle().to_degrees(),
            })
        })
        .collect()
}

/// Scores `trajectory` against `relations`: mean ± std of the translational
/// (m) and rotational (deg) relation errors; see [`relation_errors`]. No
/// relations is an error.
pub fn evaluate_relations(
    relations: &[Relation],
    trajectory: &[Stamped],
) -> Result<RelationsReport> {
    if relations.is_empty() {
        return Err(Error::Invalid("no relations to evaluate".into()));
    }
    let errs = relation_errors(relations, trajectory)?;
    let trans: Vec<f64> = errs.iter().map(|e| e.trans_m).collect();
    let rot: Vec<f64> = errs.iter().map(|e| e.rot_deg).collect();
    let (trans_mean_m, trans_std_m) = mean_std(&trans);
    let (rot_mean_deg, rot_std_deg) = mean_std(&rot);
    Ok(RelationsReport {
        n: errs.len(),
        trans_mean_m,
        trans_std_m,
        rot_mean_deg,
        rot_std_deg,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::io::tum::Stamped;
    use nalgebra::{Matrix3, Vector3};

    fn rz(a: f64) -> Matrix3<f64> {
        let (s, c) = a.sin_cos();
        Matrix3::new(c, -s, 0.0, s, c, 0.0, 0.0, 0.0, 1.0)
    }
    fn ry(a: f64) -> Matrix3<f64> {
        let (s, c) = a.sin_cos();
        Matrix3::new(c, 0.0, s, 0.0, 1.0, 0.0, -s, 0.0, c)
    }
    fn rx(a: f64) -> Matrix3<f64> {
        let (s, c) = a.sin_cos();
        Matrix3::new(1.0, 0.0, 0.0, 0.0, c, -s, 0.0, s, c)
    }

    #[test]
    fn rpy_convention_is_rz_ry_rx() {
        let (roll, pitch, yaw) = (0.3, -0.4, 1.2);
        let p = pose_from_xyz_rpy(1.0, 2.0, 3.0, roll, pitch, yaw);
        let want = rz(yaw) * ry(pitch) * rx(roll);
        let got = p.rotation.to_rotation_matrix().into_inner();
        assert!((got - want).norm() < 1e-12, "{got}\nvs\n{want}");
        // The other common order gives a different matrix: the test can fail.
        assert!((got - rx(roll) * ry(pitch) * rz(yaw)).norm() > 0.1);
        assert_eq!(p.translation.vector, Vector3::new(1.0, 2.0, 3.0));
    }

    /// A 3-D trajectory with roll and pitch, 1 pose per 0.1 s.
    fn wavy() -> Vec<Stamped> {
        (0..50)
            .map(|i| {
                let s = i as f64 * 0.1;
                Stamped::new(
                    100.0 + s,
                    pose_from_xyz_rpy(
                        s.cos() * 3.0,
                        s.sin() * 2.0,
                        0.3 * s,
                        0.2 * s.sin(),
                        -0.1 * s,
                        s,
                    ),
                )
            })
            .collect()
    }

    #[test]
    fn exact_relations_give_zero_error() {
        let traj = wavy();
        let rels: Vec<Relation> = (0..40)
            .map(|i| {
                let (a, b) = (&traj[i], &traj[i + 7]);
                Relation::new(a.t, b.t, a.pose.inverse() * b.pose, i + 1)
            })
            .collect();
        let r = evaluate_relations(&rels, &traj).unwrap();
        assert_eq!(r.n, 40);
        assert!(r.trans_mean_m < 1e-12 && r.rot_mean_deg < 1e-6, "{r}");
        // The trajectory in a different world frame scores the same.
        let g = pose_from_xyz_rpy(5.0, -3.0, 1.0, 0.4, 0.2, -2.0);
        let moved: Vec<Stamped> = traj.iter().map(|s| Stamped::new(s.t, g * s.pose)).collect();
        let r = evaluate_relations(&rels, &moved).unwrap();
        assert!(r.trans_mean_m < 1e-12 && r.rot_mean_deg < 1e-6, "{r}");
    }

    #[test]
    fn known_offsets_give_hand_computed_errors() {
        // Truth: each relation is 1 m straight ahead.
        let fwd = pose_from_xyz_rpy(1.0, 0.0, 0.0, 0.0, 0.0, 0.0);
        let rels = vec![
            Relation::new(0.0, 1.0, fwd, 1),
            Relation::new(2.0, 3.0, fwd, 2),
        ];
        // Estimate: first pair moves 1.1 m (error 0.1 m, 0°); second pair moves
        // 1 m but turns 10°: E = (Rot10, (1,0)) · (I, (−1,0)) has translation
        // (1 − cos10°, −sin10°), of norm 2·sin 5°.
        let traj = vec![
            Stamped::planar(0.0, 0.0, 0.0, 0.0),
            Stamped::planar(1.0, 1.1, 0.0, 0.0),
            Stamped::planar(2.0, 5.0, 5.0, 0.0),
            Stamped::planar(3.0, 6.0, 5.0, 10f64.to_radians()),
        ];
        let e = relation_errors(&rels, &traj).unwrap();
        let t2 = 2.0 * 5f64.to_radians().sin();
        assert!((e[0].trans_m - 0.1).abs() < 1e-12 && e[0].rot_deg < 1e-9);
        assert!((e[1].trans_m - t2).abs() < 1e-12, "{}", e[1].trans_m);
        assert!((e[1].rot_deg - 10.0).abs() < 1e-9);
        let r = evaluate_relations(&rels, &traj).unwrap();
        assert!((r.trans_mean_m - (0.1 + t2) / 2.0).abs() < 1e-12);
        assert!((r.trans_std_m - (t2 - 0.1) / 2.0).abs() < 1e-12);
        assert!((r.rot_mean_deg - 5.0).abs() < 1e-9 && (r.rot_std_deg - 5.0).abs() < 1e-9);
        assert_eq!(
            r.to_string(),
            format!(
                "relations: 2 pairs, translation {:.3} ± {:.3} m, rotation 5.00 ± 5.00 deg",
                (0.1 + t2) / 2.0,
                (t2 - 0.1) / 2.0
            )
        );
    }

    #[test]
    fn constant_3d_perturbation_of_every_step_is_recovered() {
        // Estimate: every true step R preceded by the same error D in the
        // frame of the step's start, so P1⁻¹·P2 = D·R and E = D exactly: the
        // translational error is |t(D)| and the rotational one angle(D).
        let truth = wavy();
        let d = pose_from_xyz_rpy(0.02, -0.01, 0.03, 0.01, 0.02, -0.03);
        let mut est = vec![truth[0]];
        for w in truth.windows(2) {
            let step = w[0].pose.inverse() * w[1].pose;
            let last = est.last().unwrap().pose;
            est.push(Stamped::new(w[1].t, last * d * step));
        }
        let rels: Vec<Relation> = truth
            .windows(2)
            .enumerate()
            .map(|(i, w)| Relation::new(w[0].t, w[1].t, w[0].pose.inverse() * w[1].pose, i + 1))
            .collect();
        let r = evaluate_relations(&rels, &est).unwrap();
        assert_eq!(r.n, 49);
        assert!(
            (r.trans_mean_m - d.translation.vector.norm()).abs() < 1e-12,
            "{r}"
        );
        assert!(
            (r.rot_mean_deg - d.rotation.angle().to_degrees()).abs() < 1e-9,
            "{r}"
        );
        assert!(r.trans_std_m < 1e-12 && r.rot_std_deg < 1e-9);
    }

    #[test]
    fn reads_relations_and_matches_times_within_a_millisecond() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("r.relations");
        std::fs::write(
            &p,
            "# t1 t2 x y z roll pitch yaw\n10.0000 10.5004 1 0 0 0 0 0.5\n\n10.5 11 1 0 0  0 0 0\n",
        )
        .unwrap();
        let rels = read_relations(&p).unwrap();
        assert_eq!(rels.len(), 2);
        assert_eq!((rels[0].line, rels[1].line), (2, 4));
        assert!((rels[0].rel.rotation.angle() - 0.5).abs() < 1e-12);
        let traj = vec![
            Stamped::planar(10.0, 0.0, 0.0, 0.0),
            Stamped::planar(10.5, 1.0, 0.0, 0.5),
            Stamped::planar(11.0009, 1.0 + 0.5f64.cos(), 0.5f64.sin(), 0.5),
        ];
        let r = evaluate_relations(&rels, &traj).unwrap();
        assert!(r.trans_mean_m < 1e-12 && r.rot_mean_deg < 1e-9, "{r}");

        // The last pose is now 2 ms away from t2 of line 4.
        let late = vec![traj[0], traj[1], Stamped::planar(11.002, 0.0, 0.0, 0.0)];
        let msg = evaluate_relations(&rels, &late).unwrap_err().to_string();
        assert!(
            msg.contains("r.relations:line 4") && msg.contains("t2 = 11.000000"),
            "{msg}"
        );
    }

    #[test]
    fn malformed_relations_name_file_and_line() {
        let dir = tempfile::tempdir().unwrap();
        let cases = [
            (
                "1 2 0 0 0 0 0 0\n1 2 0 0 0 0 0\n",
                "line 2",
                "expected 8 fields",
            ),
            ("1 2 0 0 0 inf 0 0\n", "line 1", "roll is not finite"),
            ("1 2 0 0 0 0 0 yaw\n", "line 1", "yaw: 'yaw'"),
            ("# only a comment\n", "file", "no relations"),
        ];
        for (i, (text, at, reason)) in cases.iter().enumerate() {
            let p = dir.path().join(format!("bad{i}.relations"));
            std::fs::write(&p, text).unwrap();
            let msg = read_relations(&p).unwrap_err().to_string();
            assert!(
                msg.contains(&format!("bad{i}.relations:{at}")) && msg.contains(reason),
                "case {i}: {msg}"
            );
        }
        assert!(evaluate_relations(&[], &wavy()).is_err());
        let nan = vec![Stamped::planar(0.0, f64::NAN, 0.0, 0.0)];
        let rel = [Relation::new(0.0, 0.0, Isometry3::identity(), 1)];
        assert!(
            evaluate_relations(&rel, &nan)
                .unwrap_err()
                .to_string()
                .contains("not finite")
        );
    }
}
