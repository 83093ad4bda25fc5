//! Accuracy metrics end to end: trajectory files, relations files, the
//! published raw-odometry baseline of the MIT CSAIL log, and the
//! `dpslam eval` command line.

use dpslam::eval::ate::{AlignmentKind, AteOptions, evaluate_ate};
use dpslam::eval::relations::{
    Relation, evaluate_relations, pose_from_xyz_rpy, read_relations, relation_errors,
};
use dpslam::io::source::TextSource;
use dpslam::io::tum::{Stamped, read_poses, read_tum, write_stamped};
use std::path::{Path, PathBuf};
use std::process::Command;

const CLF: &str = concat!(
    env!("CARGO_MANIFEST_DIR"),
    "/../shared/datasets/carmen/mit-csail/mit-csail.clf"
);
const RELATIONS: &str = concat!(
    env!("CARGO_MANIFEST_DIR"),
    "/../shared/datasets/carmen/mit-csail/mit-csail.relations"
);

/// The raw odometry of every `FLASER` line: after `FLASER n r_1 … r_n` come
/// `x y theta odom_x odom_y odom_theta ipc_timestamp …`; t = ipc_timestamp.
fn flaser_odometry(path: &Path) -> Vec<Stamped> {
    let mut src = TextSource::open(path).unwrap();
    let mut out = Vec::new();
    while let Some((line_no, line)) = src.next_line().unwrap() {
        let f: Vec<&str> = line.split_whitespace().collect();
        if f.first() != Some(&"FLASER") {
            continue;
        }
        let n: usize = f[1].parse().unwrap();
        let num = |k: usize| -> f64 {
            f[2 + n + k]
                .parse()
                .unwrap_or_else(|_| panic!("line {line_no}: field {k} after ranges"))
        };
        out.push(Stamped::planar(num(6), num(3), num(4), num(5)));
    }
    out
}

fn bin() -> Command {
    Command::new(env!("CARGO_BIN_EXE_dpslam"))
}

fn write_relations(path: &Path, rels: &[Relation]) {
    let mut text = String::from("# t1 t2 x y z roll pitch yaw\n");
    for r in rels {
        let t = r.rel.translation.vector;
        let (roll, pitch, yaw) = r.rel.rotation.euler_angles();
        text += &format!(
            "{:.6} {:.6} {:.9} {:.9} {:.9} {:.9} {:.9} {:.9}\n",
            r.t1, r.t2, t.x, t.y, t.z, roll, pitch, yaw
        );
    }
    std::fs::write(path, text).unwrap();
}

#[test]
fn mit_csail_raw_odometry_relations_error_matches_published_baseline() {
    let odom = flaser_odometry(Path::new(CLF));
    assert_eq!(odom.len(), 1988, "FLASER lines in mit-csail.clf");
    // Through a TUM file, so that the 6-decimal time stamps of the writer are
    // shown to match the relations' scan times.
    let dir = tempfile::tempdir().unwrap();
    let tum = dir.path().join("odom.tum");
    write_stamped(&tum, &odom).unwrap();
    let traj = read_tum(&tum).unwrap();
    let rels = read_relations(Path::new(RELATIONS)).unwrap();
    assert_eq!(rels.len(), 1172);
    let r = evaluate_relations(&rels, &traj).unwrap();
    eprintln!("raw odometry on mit-csail: {r}");
    assert_eq!(r.n, 1172);
    assert!(
        (1.5..1.9).contains(&r.trans_mean_m),
        "raw-odometry translational error {r}"
    );
    // Odometry is far from the truth over long relations, and exact over none.
    assert!(r.rot_mean_deg > 1.0 && r.trans_std_m > 0.1, "{r}");
}

#[test]
fn mit_csail_relations_of_the_trajectory_itself_score_zero() {
    // Relations generated from the odometry itself, written in the file
    // format (roll-pitch-yaw) and read back, give zero error: file format,
    // angle convention and time matching agree with each other.
    let odom = flaser_odometry(Path::new(CLF));
    let truth_rels = read_relations(Path::new(RELATIONS)).unwrap();
    let find = |t: f64| {
        odom.iter()
            .min_by(|a, b| (a.t - t).abs().total_cmp(&(b.t - t).abs()))
            .unwrap()
    };
    let rels: Vec<Relation> = truth_rels
        .iter()
        .map(|r| {
            let (a, b) = (find(r.t1), find(r.t2));
            Relation::new(a.t, b.t, a.pose.inverse() * b.pose, r.line)
        })
        .collect();
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("self.relations");
    write_relations(&p, &rels);
    let r = evaluate_relations(&read_relations(&p).unwrap(), &odom).unwrap();
    assert_eq!(r.n, 1172);
    assert!(r.trans_mean_m < 1e-6 && r.rot_mean_deg < 1e-5, "{r}");
}

#[test]
fn relations_3d_file_round_trip_and_known_error() {
    // A 3-D trajectory with roll and pitch; relations written in the file
    // format give zero error, and a trajectory whose every pose is followed
    // by the same body-frame error D scores |t(D)| per consecutive relation.
    let truth: Vec<Stamped> = (0..80)
        .map(|i| {
            let s = i as f64 * 0.1;
            Stamped::new(
                50.0 + s,
                pose_from_xyz_rpy(s, s.sin(), 0.2 * s, 0.3 * s.cos(), 0.25 * s.sin(), 0.5 * s),
            )
        })
        .collect();
    let rels: Vec<Relation> = truth
        .windows(2)
        .enumerate()
        .map(|(i, w)| Relation::new(w[0].t, w[1].t, w[0].pose.inverse() * w[1].pose, i + 1))
        .collect();
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("r3.relations");
    write_relations(&p, &rels);
    let from_file = read_relations(&p).unwrap();
    let r = evaluate_relations(&from_file, &truth).unwrap();
    assert!(r.trans_mean_m < 1e-8 && r.rot_mean_deg < 1e-6, "{r}");

    let d = pose_from_xyz_rpy(0.0, 0.0, 0.05, 0.0, 0.0, 0.0);
    let est: Vec<Stamped> = truth
        .iter()
        .map(|s| Stamped::new(s.t, s.pose * d))
        .collect();
    // P1⁻¹·P2 = D⁻¹·R·D, so E = D⁻¹·R·D·R⁻¹: not zero whenever R rotates.
    for (e, rel) in relation_errors(&from_file, &est).unwrap().iter().zip(&rels) {
        let want = (d.inverse() * rel.rel * d) * rel.rel.inverse();
        assert!((e.trans_m - want.translation.vector.norm()).abs() < 1e-7);
        assert!(
            e.trans_m > 1e-4,
            "a body-frame offset under rotation shows up"
        );
    }
}

#[test]
fn ate_of_rigidly_moved_odometry_is_zero_and_noise_is_measured() {
    let odom = flaser_odometry(Path::new(CLF));
    let g = pose_from_xyz_rpy(-20.0, 35.0, 0.0, 0.0, 0.0, 1.0);
    let est: Vec<Stamped> = odom
        .iter()
        .map(|s| Stamped::new(s.t + 0.004, g * s.pose))
        .collect();
    let r = evaluate_ate(&odom, &est, &AteOptions::default()).unwrap();
    assert_eq!((r.n, r.alignment), (1988, AlignmentKind::Se2));
    assert!(r.rmse_m < 1e-8 && r.rot_mean_deg < 1e-6, "{r}");
    // Alternating ±10 cm offsets along z make the data 3-D: SE(3) is chosen,
    // and since the offsets average out and do not correlate with the path,
    // the alignment stays near the true one and every error is close to 0.1 m.
    let bumped: Vec<Stamped> = est
        .iter()
        .enumerate()
        .map(|(i, s)| {
            let mut p = s.pose;
            p.translation.z += if i % 2 == 0 { 0.1 } else { -0.1 };
            Stamped::new(s.t, p)
        })
        .collect();
    let r = evaluate_ate(&odom, &bumped, &AteOptions::default()).unwrap();
    assert_eq!(r.alignment, AlignmentKind::Se3);
    assert!((r.rmse_m - 0.1).abs() < 2e-3 && r.max_m < 0.11, "{r}");
}

fn tum_of(dir: &Path, name: &str, poses: &[Stamped]) -> PathBuf {
    let p = dir.join(name);
    write_stamped(&p, poses).unwrap();
    p
}

#[test]
fn cli_relations_prints_one_line_or_one_json_object() {
    let dir = tempfile::tempdir().unwrap();
    let tum = tum_of(dir.path(), "odom.tum", &flaser_odometry(Path::new(CLF)));
    let out = bin()
        .args([
            "eval",
            "relations",
            "--relations",
            RELATIONS,
            "--trajectory",
        ])
        .arg(&tum)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let text = String::from_utf8(out.stdout).unwrap();
    assert_eq!(text.lines().count(), 1);
    assert!(
        text.starts_with("relations: 1172 pairs, translation "),
        "{text}"
    );

    let out = bin()
        .args([
            "eval",
            "relations",
            "--json",
            "--relations",
            RELATIONS,
            "--trajectory",
        ])
        .arg(&tum)
        .output()
        .unwrap();
    assert!(out.status.success());
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(v["n"], 1172);
    let t = v["trans_mean_m"].as_f64().unwrap();
    assert!((1.5..1.9).contains(&t), "{v}");
    for k in ["trans_std_m", "rot_mean_deg", "rot_std_deg"] {
        assert!(v[k].as_f64().is_some(), "{k} in {v}");
    }
}

#[test]
fn cli_ate_text_json_and_se3() {
    let dir = tempfile::tempdir().unwrap();
    let truth: Vec<Stamped> = (0..100)
        .map(|i| {
            let s = i as f64 * 0.1;
            Stamped::planar(s, 3.0 * s.cos(), 2.0 * s.sin(), s)
        })
        .collect();
    let g = pose_from_xyz_rpy(1.0, 2.0, 0.0, 0.0, 0.0, 0.5);
    let est: Vec<Stamped> = truth
        .iter()
        .map(|s| Stamped::new(s.t, g * s.pose))
        .collect();
    let (gt, tr) = (
        tum_of(dir.path(), "gt.tum", &truth),
        tum_of(dir.path(), "est.tum", &est),
    );
    let out = bin()
        .args(["eval", "ate", "--truth"])
        .arg(&gt)
        .arg("--trajectory")
        .arg(&tr)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let text = String::from_utf8(out.stdout).unwrap();
    assert!(
        text.starts_with("ate: 100 poses, SE(2) alignment, rmse 0.000 m"),
        "{text}"
    );

    let out = bin()
        .args(["eval", "ate", "--json", "--se3", "--truth"])
        .arg(&gt)
        .arg("--trajectory")
        .arg(&tr)
        .output()
        .unwrap();
    assert!(out.status.success());
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(
        (v["n"].as_u64(), v["alignment"].as_str()),
        (Some(100), Some("se3"))
    );
    assert!(v["rmse_m"].as_f64().unwrap() < 1e-6, "{v}");
}

#[test]
fn cli_errors_name_file_and_line() {
    let dir = tempfile::tempdir().unwrap();
    let bad = dir.path().join("bad.tum");
    std::fs::write(&bad, "0 0 0 0 0 0 0 1\n1 0 0 0 0 0 0 0\n").unwrap();
    let out = bin()
        .args(["eval", "ate", "--truth"])
        .arg(&bad)
        .arg("--trajectory")
        .arg(&bad)
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("bad.tum:line 2") && err.contains("quaternion"),
        "{err}"
    );

    // A trajectory that covers only the first scans misses relation times.
    let short: Vec<Stamped> = flaser_odometry(Path::new(CLF))
        .into_iter()
        .take(100)
        .collect();
    let tum = tum_of(dir.path(), "short.tum", &short);
    let out = bin()
        .args([
            "eval",
            "relations",
            "--relations",
            RELATIONS,
            "--trajectory",
        ])
        .arg(&tum)
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("mit-csail.relations:line ")
            && err.contains("no trajectory pose within")
            && err.contains("short.tum"),
        "{err}"
    );
    // Same through the library: the error names the relations line.
    let rels = read_relations(Path::new(RELATIONS)).unwrap();
    let msg = evaluate_relations(&rels, &read_poses(&tum).unwrap())
        .unwrap_err()
        .to_string();
    assert!(msg.contains("mit-csail.relations:line "), "{msg}");
}
