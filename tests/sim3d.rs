//! The 3-D simulator end to end: ray casting, determinism, the shape of the
//! trajectory, the odometry drift, the written files and the shipped data set.

use dpslam::eval::ate::{Alignment, AteOptions, evaluate_ate};
use dpslam::io::sweeps::{list_sweeps, read_sweep};
use dpslam::io::tum::read_tum;
use dpslam::sim::sim3d::{
    Aabb, Patch, Sim3dConfig, World3d, simulate3d, sweep_file_name, write_sim3d,
};
use std::path::{Path, PathBuf};

fn shipped() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("data/sim3d")
}

/// A cheap configuration: few sweeps and rays, the default loop and noise.
fn small(sweeps: usize) -> Sim3dConfig {
    Sim3dConfig {
        sweeps,
        rings: 4,
        columns: 32,
        ..Sim3dConfig::default()
    }
}

fn files_under(dir: &Path) -> Vec<PathBuf> {
    let mut out = Vec::new();
    for e in std::fs::read_dir(dir).unwrap() {
        let p = e.unwrap().path();
        if p.is_dir() {
            out.extend(files_under(&p));
        } else {
            out.push(p);
        }
    }
    out.sort();
    out
}

#[test]
fn ray_casting_against_a_hand_computed_box_and_floor() {
    // Floor z = 0 over [−10, 10]²; a box x ∈ [3, 4], y ∈ [−1, 1], z ∈ [0, 2].
    let world = World3d {
        boxes: vec![Aabb {
            min: [3.0, -1.0, 0.0],
            max: [4.0, 1.0, 2.0],
        }],
        patches: vec![Patch {
            origin: [-10.0, -10.0, 0.0],
            u: [20.0, 0.0, 0.0],
            v: [0.0, 20.0, 0.0],
        }],
    };
    let o = [0.0, 0.0, 1.0];
    let h = world.cast(o, [1.0, 0.0, 0.0]).unwrap();
    assert_eq!((h.distance, h.normal), (3.0, [-1.0, 0.0, 0.0]));
    // 30° down: the floor 1 m below is 2 m away along the ray, short of the box.
    let (s, c) = (-30f64).to_radians().sin_cos();
    let h = world.cast(o, [c, 0.0, s]).unwrap();
    assert!((h.distance - 2.0).abs() < 1e-12, "{h:?}");
    assert_eq!(h.normal[2].abs(), 1.0);
    // 10° up: x = 3 at z = 1 + 3·tan 10° = 1.53 < 2, so the box's face.
    let (s, c) = 10f64.to_radians().sin_cos();
    let h = world.cast(o, [c, 0.0, s]).unwrap();
    assert!((h.distance - 3.0 / c).abs() < 1e-12, "{h:?}");
    // 30° up clears the box (z = 2.73 at x = 3) and escapes; so does a
    // horizontal ray beside the box, parallel to the floor.
    let (s, c) = 30f64.to_radians().sin_cos();
    assert!(world.cast(o, [c, 0.0, s]).is_none());
    assert!(world.cast(o, [0.0, 1.0, 0.0]).is_none());
}

#[test]
fn same_seed_same_output_other_seed_other_noise() {
    let cfg = small(12);
    let a = simulate3d(&cfg, 7).unwrap();
    let b = simulate3d(&cfg, 7).unwrap();
    let c = simulate3d(&cfg, 8).unwrap();
    assert_eq!(a.sweeps, b.sweeps);
    assert_eq!(a.truth, b.truth);
    assert_eq!(a.odometry, b.odometry);
    // The truth is the planned path whatever the seed; the noise is not.
    assert_eq!(a.truth, c.truth);
    assert_ne!(a.odometry.last(), c.odometry.last());
    let same = a
        .sweeps
        .iter()
        .zip(&c.sweeps)
        .filter(|(x, y)| x == y)
        .count();
    assert_eq!(same, 0, "range noise should differ in every sweep");
    // The lidar's stream is separate: other lidar settings, same odometry.
    let d = simulate3d(
        &Sim3dConfig {
            rings: 3,
            ..cfg.clone()
        },
        7,
    )
    .unwrap();
    assert_eq!(a.odometry, d.odometry);
}

#[test]
fn truth_climbs_pitches_rolls_and_closes_the_loop() {
    let sim = simulate3d(&small(120), 1).unwrap();
    let s = sim.summary().unwrap();
    // The mezzanine is 1.2 m up; the ramps are 13.5° steep and crossed at
    // ~17° to their slope, which tilts the vehicle sideways by ~4°.
    let (zlo, zhi) = s.height_range;
    assert!(
        (zlo - 1.2).abs() < 1e-9 && (zhi - 2.4).abs() < 1e-9,
        "{zlo} {zhi}"
    );
    let (pitch, roll) = s.max_pitch_roll_deg;
    assert!((11.0..14.0).contains(&pitch), "pitch {pitch}");
    assert!((3.0..6.0).contains(&roll), "roll {roll}");
    // Climbing (east ramp, driving north) is nose up; the x axis points up.
    let climbing = sim
        .truth
        .iter()
        .filter(|p| (p.pose.rotation * nalgebra::Vector3::x()).z > 0.2)
        .count();
    assert!(climbing >= 5, "{climbing} poses on the way up");
    // The loop is driven once and then overlaps its start by 6 m: some late
    // pose passes within 0.5 m of the first.
    let first = sim.truth[0].pose.translation.vector;
    let back = sim.truth[sim.truth.len() * 3 / 4..]
        .iter()
        .map(|p| (p.pose.translation.vector - first).norm())
        .fold(f64::INFINITY, f64::min);
    assert!(back < 0.5, "closest return {back}");
    assert!(sim.path_length > 60.0);
    // Time stamps are the sweep indices.
    assert!(sim.truth.iter().enumerate().all(|(k, p)| p.t == k as f64));
}

#[test]
fn odometry_only_ate_is_at_least_a_metre() {
    let opts = AteOptions {
        alignment: Alignment::Se3,
        ..AteOptions::default()
    };
    for cfg in [small(200), small(40)] {
        let sim = simulate3d(&cfg, 1).unwrap();
        let ate = evaluate_ate(&sim.truth, &sim.odometry, &opts).unwrap();
        assert_eq!(ate.n, cfg.sweeps);
        assert!(ate.rmse_m >= 1.0, "{} sweeps: {ate}", cfg.sweeps);
        assert_eq!(sim.summary().unwrap().odometry_ate, ate.rmse_m);
    }
}

#[test]
fn written_sweeps_read_back_with_the_expected_points() {
    let dir = tempfile::tempdir().unwrap();
    for gzip in [false, true] {
        let cfg = Sim3dConfig { gzip, ..small(6) };
        let summary = write_sim3d(dir.path(), &cfg, 3).unwrap();
        let sim = simulate3d(&cfg, 3).unwrap();
        assert_eq!(summary, sim.summary().unwrap());
        let files = list_sweeps(&dir.path().join("sweeps")).unwrap();
        let names: Vec<String> = files
            .iter()
            .map(|p| p.file_name().unwrap().to_string_lossy().into_owned())
            .collect();
        // The run before (plain, then gzip) left no stale files behind.
        let expect: Vec<String> = (0..6).map(|k| sweep_file_name(k, gzip)).collect();
        assert_eq!(names, expect);
        let mut total = 0;
        for (f, pts) in files.iter().zip(&sim.sweeps) {
            let sweep = read_sweep(f).unwrap();
            assert_eq!(sweep.points.len(), pts.len(), "{}", f.display());
            assert!(pts.len() > 4 * 32 / 2, "most rays hit something");
            for (got, want) in sweep.points.iter().zip(pts) {
                assert_eq!(got, &[want[0], want[1], want[2]]);
            }
            total += pts.len();
        }
        assert_eq!(summary.points, total);
        for (name, traj) in [("truth.tum", &sim.truth), ("odometry.tum", &sim.odometry)] {
            let back = read_tum(&dir.path().join(name)).unwrap();
            assert_eq!(back.len(), traj.len());
            for (r, s) in back.iter().zip(traj.iter()) {
                let d = r.pose.inverse() * s.pose;
                assert!(r.t == s.t && d.translation.vector.norm() < 1e-8);
                assert!(d.rotation.angle() < 1e-8);
            }
        }
    }
    // Only the outputs are left: no temporary files.
    let all = files_under(dir.path());
    assert_eq!(all.len(), 6 + 2, "{all:?}");
}

#[test]
fn fewer_sweeps_replace_a_longer_run() {
    let dir = tempfile::tempdir().unwrap();
    write_sim3d(dir.path(), &small(5), 1).unwrap();
    std::fs::write(dir.path().join("sweeps/notes.txt"), "kept").unwrap();
    write_sim3d(dir.path(), &small(3), 1).unwrap();
    assert_eq!(list_sweeps(&dir.path().join("sweeps")).unwrap().len(), 3);
    assert!(dir.path().join("sweeps/notes.txt").exists());
    assert_eq!(read_tum(&dir.path().join("truth.tum")).unwrap().len(), 3);
}

#[test]
fn config_file_overrides_and_reports_errors_by_line() {
    let dir = tempfile::tempdir().unwrap();
    let good = dir.path().join("good.toml");
    std::fs::write(&good, "sweeps = 7\n[odometry]\nyaw_bias_deg_per_m = 0.0\n").unwrap();
    let cfg = Sim3dConfig::load(&good).unwrap();
    assert_eq!(cfg.sweeps, 7);
    assert_eq!(cfg.odometry.yaw_bias_deg_per_m, 0.0);
    assert_eq!(
        cfg.odometry.trans_per_m, 0.05,
        "unnamed fields keep defaults"
    );
    assert_eq!(cfg.waypoints, Sim3dConfig::default().waypoints);
    let bad = dir.path().join("bad.toml");
    std::fs::write(&bad, "rings = 8\n\nring = 2\n").unwrap();
    let e = Sim3dConfig::load(&bad).unwrap_err().to_string();
    assert!(e.contains("bad.toml:line 3") && e.contains("ring"), "{e}");
    std::fs::write(&bad, "max_range = -1.0\n").unwrap();
    assert!(matches!(
        Sim3dConfig::load(&bad),
        Err(dpslam::Error::Config(_))
    ));
}

#[test]
fn shipped_data_set_is_reproducible() {
    // The exact command of data/sim3d/README.md.
    let dir = tempfile::tempdir().unwrap();
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_dpslam"))
        .args(["simulate3d", "--out"])
        .arg(dir.path())
        .args([
            "--seed",
            "1",
            "--sweeps",
            "40",
            "--rings",
            "16",
            "--columns",
            "512",
        ])
        .arg("--gzip")
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        stdout.contains("40 sweeps") && stdout.contains("odometry-only ATE"),
        "{stdout}"
    );
    let rel = |root: &Path, v: Vec<PathBuf>| -> Vec<PathBuf> {
        v.into_iter()
            .map(|p| p.strip_prefix(root).unwrap().to_path_buf())
            .collect()
    };
    let made = rel(dir.path(), files_under(dir.path()));
    let want: Vec<PathBuf> = rel(&shipped(), files_under(&shipped()))
        .into_iter()
        .filter(|p| p != Path::new("README.md"))
        .collect();
    assert_eq!(made, want);
    let mut size = 0;
    for f in &made {
        let a = std::fs::read(dir.path().join(f)).unwrap();
        let b = std::fs::read(shipped().join(f)).unwrap();
        assert!(
            a == b,
            "data/sim3d/{} differs from a fresh run ({} vs {} bytes): regenerate it as \
             data/sim3d/README.md says",
            f.display(),
            a.len(),
            b.len()
        );
        size += b.len();
    }
    assert!(size <= 4_000_000, "shipped data is {size} bytes");
    // The library's preset is the same configuration.
    let sim = simulate3d(&Sim3dConfig::embedded(), 1).unwrap();
    let first = read_sweep(&shipped().join("sweeps").join(sweep_file_name(0, true))).unwrap();
    assert_eq!(first.points.len(), sim.sweeps[0].len());
    let truth = read_tum(&shipped().join("truth.tum")).unwrap();
    let odom = read_tum(&shipped().join("odometry.tum")).unwrap();
    let opts = AteOptions {
        alignment: Alignment::Se3,
        ..AteOptions::default()
    };
    let ate = evaluate_ate(&truth, &odom, &opts).unwrap();
    assert!(ate.rmse_m >= 1.0, "{ate}");
}

#[test]
fn corridors_preset_is_a_long_feature_poor_loop_and_gives_sweeps() {
    let preset = Sim3dConfig::corridors();
    assert!(preset.sweeps >= 300, "{}", preset.sweeps);
    let cfg = Sim3dConfig {
        sweeps: 60,
        rings: 4,
        columns: 64,
        ..Sim3dConfig::corridors()
    };
    let sim = simulate3d(&cfg, 1).unwrap();
    assert!(sim.path_length >= 300.0, "loop {} m", sim.path_length);
    let spacing = sim.path_length / (preset.sweeps - 1) as f64;
    assert!((0.9..1.1).contains(&spacing), "{spacing} m between sweeps");
    assert_eq!(sim.sweeps.len(), 60);
    assert!(
        sim.sweeps.iter().all(|s| s.len() > 100),
        "a sweep saw nothing"
    );
    // The loop is closed and overlaps its start.
    let first = sim.truth[0].pose.translation.vector;
    let back = sim.truth[sim.truth.len() * 3 / 4..]
        .iter()
        .map(|p| (p.pose.translation.vector - first).norm())
        .fold(f64::INFINITY, f64::min);
    assert!(back < 3.5, "closest return {back}");
    // Flat: one floor, no pitch or roll.
    let s = sim.summary().unwrap();
    assert!(s.max_pitch_roll_deg.0 < 1e-6 && s.max_pitch_roll_deg.1 < 1e-6);
    // Mid-corridor, the walls are 1.5 m to either side and nothing is
    // within 60 m along the corridor.
    let w = World3d::corridors();
    for (dir, want) in [([0.0, 1.0, 0.0], Some(1.5)), ([0.0, -1.0, 0.0], Some(1.5))] {
        let d = w.cast([40.0, 0.0, 1.2], dir).map(|h| h.distance);
        assert!(
            d.zip(want).is_some_and(|(d, w)| (d - w).abs() < 1e-9),
            "{dir:?}: {d:?}"
        );
    }
    assert!(
        w.cast([40.0, 0.0, 1.2], [1.0, 0.0, 0.0])
            .is_none_or(|h| h.distance > 60.0)
    );
}

#[test]
fn simulate3d_world_flag_selects_the_corridors() {
    let dir = tempfile::tempdir().unwrap();
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_dpslam"))
        .args(["simulate3d", "--world", "corridors", "--sweeps", "3"])
        .args(["--rings", "2", "--columns", "16", "--out"])
        .arg(dir.path())
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        text.contains("3 sweeps") && text.contains("path 36"),
        "{text}"
    );
    assert_eq!(read_tum(&dir.path().join("truth.tum")).unwrap().len(), 3);
    // --world and --config exclude each other.
    let both = std::process::Command::new(env!("CARGO_BIN_EXE_dpslam"))
        .args([
            "simulate3d",
            "--world",
            "corridors",
            "--config",
            "x.toml",
            "--out",
        ])
        .arg(dir.path())
        .output()
        .unwrap();
    assert!(!both.status.success());
}
