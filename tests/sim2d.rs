//! The 2-D simulator end to end: determinism, ray casting, the shape of the
//! loop, the odometry noise, the written files and the shipped data set.

use dpslam::geometry::{Pose2, wrap_angle, xyt};
use dpslam::io::carmen::CarmenParser;
use dpslam::sim::sim2d::{
    NO_RETURN_RANGE, OdometryNoise, Segment2, Sim2dConfig, World2d, simulate2d, write_sim2d,
};
use std::path::{Path, PathBuf};

fn shipped(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("data/sim2d")
        .join(name)
}

/// Relative motion from `a` to `b` in `a`'s frame: (distance m, turn rad).
fn step(a: &Pose2, b: &Pose2) -> (f64, f64) {
    let (dx, dy, dth) = xyt(&(a.inverse() * b));
    (dx.hypot(dy), dth)
}

#[test]
fn same_seed_same_output_other_seed_other_noise() {
    let cfg = Sim2dConfig {
        waypoints: vec![[2.0, 0.0], [20.0, 0.0], [20.0, 6.0]],
        ..Sim2dConfig::default()
    };
    let a = simulate2d(&cfg, 7).unwrap();
    let b = simulate2d(&cfg, 7).unwrap();
    let c = simulate2d(&cfg, 8).unwrap();
    assert_eq!(a.scans, b.scans);
    assert_eq!(a.truth, b.truth);
    assert_eq!(a.clf_text(), b.clf_text());
    // The truth is the planned path, whatever the seed; the noise is not.
    assert_eq!(a.truth, c.truth);
    let same_ranges = a
        .scans
        .iter()
        .zip(&c.scans)
        .filter(|(x, y)| x.ranges == y.ranges)
        .count();
    assert_eq!(same_ranges, 0, "range noise should differ in every scan");
    assert_ne!(
        a.scans.last().unwrap().odometry,
        c.scans.last().unwrap().odometry
    );
}

#[test]
fn ray_casting_against_a_hand_computed_wall() {
    // One wall x = 3, y ∈ [−10, 10]; the robot sits at the origin facing it.
    let world = World2d {
        segments: vec![Segment2 {
            a: [3.0, -10.0],
            b: [3.0, 10.0],
        }],
    };
    assert_eq!(world.cast([0.0, 0.0], 0.0), Some(3.0));
    let d30 = world.cast([0.0, 0.0], 30f64.to_radians()).unwrap();
    assert!((d30 - 3.0 / 30f64.to_radians().cos()).abs() < 1e-12);
    assert_eq!(
        world.cast([0.0, 0.0], 80f64.to_radians()),
        None,
        "passes the wall's end"
    );
    assert_eq!(
        world.cast([0.0, 0.0], 180f64.to_radians()),
        None,
        "wall behind"
    );

    // The same wall through the whole pipeline, without noise.
    let cfg = Sim2dConfig {
        waypoints: vec![[0.0, 0.0], [1.0, 0.0]],
        range_sigma: 0.0,
        odometry: OdometryNoise::zero(),
        world: Some(world),
        ..Sim2dConfig::default()
    };
    let sim = simulate2d(&cfg, 1).unwrap();
    let s0 = &sim.scans[0];
    assert_eq!(s0.ranges.len(), 181);
    assert!((s0.angle_min + std::f64::consts::FRAC_PI_2).abs() < 1e-12);
    assert!((s0.angle_increment - 1f64.to_radians()).abs() < 1e-12);
    // Beam 90 looks straight ahead, beam 120 30° to the left.
    assert_eq!(s0.ranges[90], 3.0);
    assert_eq!(s0.ranges[120], 3.464); // 3 / cos 30° = 3.4641
    assert_eq!(s0.ranges[60], 3.464);
    // 3 / cos θ exceeds 8 m beyond θ = 67.98°: beam 157 (+67°) reads
    // 3 / cos 67° = 7.678 m, beam 158 (+68°) would read 8.008 m: no return.
    assert_eq!(s0.ranges[157], 7.678);
    assert_eq!(s0.ranges[23], 7.678);
    for i in (0..23).chain(158..181) {
        assert_eq!(s0.ranges[i], NO_RETURN_RANGE, "beam {i}");
        assert!(s0.is_no_return(i));
    }
    // Half a metre later the wall is 2.5 m ahead.
    let k = 10;
    assert!((sim.truth[k].1.translation.x - 0.5).abs() < 1e-12);
    assert_eq!(sim.scans[k].ranges[90], 2.5);
}

#[test]
fn truth_drives_a_long_loop_that_closes() {
    let sim = simulate2d(&Sim2dConfig::default(), 1).unwrap();
    assert!(sim.path_length >= 50.0, "path {} m", sim.path_length);
    let n = sim.truth.len();
    assert!((1000..=1500).contains(&n), "{n} scans");
    for w in sim.truth.windows(2) {
        assert!((w[1].0 - w[0].0 - 0.1).abs() < 1e-9, "10 Hz");
        let (d, dth) = step(&w[0].1, &w[1].1);
        // On the 1 m arcs the chord is 2·sin(0.025) = 0.0499948 m.
        assert!((d - 0.05).abs() < 1e-5, "0.5 m/s: step {d}");
        assert!(dth.abs() <= 0.05 + 1e-9, "smooth turns: {dth} rad per step");
    }
    // The loop goes round the whole ring...
    let xs: Vec<f64> = sim.truth.iter().map(|(_, p)| p.translation.x).collect();
    let ys: Vec<f64> = sim.truth.iter().map(|(_, p)| p.translation.y).collect();
    let span = |v: &[f64]| {
        v.iter().cloned().fold(f64::MIN, f64::max) - v.iter().cloned().fold(f64::MAX, f64::min)
    };
    assert!(span(&xs) > 19.0 && span(&ys) > 11.0);
    // ...comes back through the start pose, with the same heading, in its
    // second half, and drives on past it so the loop can be closed.
    let start = sim.truth[0].1;
    let back = sim.truth[n / 2..]
        .iter()
        .position(|(_, p)| {
            let (d, dth) = step(&start, p);
            d < 0.05 && dth.abs() < 1e-6
        })
        .map(|i| i + n / 2)
        .expect("the path never returns to its start");
    let beyond: f64 = sim.truth[back..]
        .windows(2)
        .map(|w| step(&w[0].1, &w[1].1).0)
        .sum();
    assert!(beyond > 3.0, "only {beyond} m driven past the start");
}

#[test]
fn odometry_drifts_but_each_step_is_close_to_the_truth() {
    let cfg = Sim2dConfig::default();
    let sim = simulate2d(&cfg, 1).unwrap();
    let summary = sim.summary();
    assert!(
        summary.final_odometry_error >= 0.5,
        "odometry alone should drift: {summary}"
    );
    assert_eq!(
        sim.scans[0].odometry, sim.truth[0].1,
        "odometry starts at the truth"
    );
    let bias = cfg.odometry.rot_bias_deg_per_m.to_radians();
    let (mut sum_d_err, mut sum_rot_err, mut big) = (0.0, 0.0, 0);
    for k in 1..sim.scans.len() {
        let (d, dth) = step(&sim.truth[k - 1].1, &sim.truth[k].1);
        let (od, odth) = step(&sim.scans[k - 1].odometry, &sim.scans[k].odometry);
        let sd = cfg.odometry.trans_per_m * d;
        let sr = cfg.odometry.rot_per_m * d + cfg.odometry.rot_per_rad * dth.abs();
        let (e_d, e_r) = (od - d, wrap_angle(odth - dth) - bias * d);
        // 5σ: a few thousand draws essentially never reach it.
        assert!(
            e_d.abs() <= 5.0 * sd + 1e-9,
            "step {k}: distance error {e_d}"
        );
        assert!(e_r.abs() <= 5.0 * sr + 1e-9, "step {k}: turn error {e_r}");
        if e_d.abs() > 2.0 * sd || e_r.abs() > 2.0 * sr {
            big += 1;
        }
        sum_d_err += e_d;
        sum_rot_err += wrap_angle(odth - dth);
    }
    let steps = (sim.scans.len() - 1) as f64;
    // Beyond 2σ happens to 1 − 0.954² ≈ 9% of steps (two draws each).
    let frac = big as f64 / steps;
    assert!((0.05..0.14).contains(&frac), "{frac} of steps beyond 2σ");
    // Translation noise is unbiased: the mean error is far below σ ≈ 2.5 mm.
    assert!(
        (sum_d_err / steps).abs() < 3e-4,
        "mean distance error {}",
        sum_d_err / steps
    );
    // The systematic turn bias shows in the total: 0.5°/m over the path.
    let per_m = sum_rot_err / sim.path_length;
    assert!(
        (per_m - bias).abs() < 0.3 * bias,
        "rotation drift {per_m} rad/m, bias {bias}"
    );
}

#[test]
fn written_log_parses_with_the_carmen_reader() {
    let dir = tempfile::tempdir().unwrap();
    let (clf, tum) = (dir.path().join("s.clf"), dir.path().join("s.tum"));
    let summary = write_sim2d(&clf, &tum, 3).unwrap();
    let sim = simulate2d(&Sim2dConfig::default(), 3).unwrap();
    assert_eq!(summary, sim.summary());

    let text = std::fs::read_to_string(&clf).unwrap();
    let mut parser = CarmenParser::new();
    let mut parsed = Vec::new();
    for (i, line) in text.lines().enumerate() {
        if let Some(s) = parser.parse_line(&clf, i + 1, line).unwrap() {
            parsed.push(s);
        }
    }
    parser.finish(&clf).unwrap();
    assert_eq!(parser.flaser_max_range(), 8.0);
    assert_eq!(parsed.len(), sim.scans.len());
    for (p, s) in parsed.iter().zip(&sim.scans) {
        assert_eq!(p.line, s.line);
        assert_eq!(p.ranges.len(), 181);
        assert!((p.angle_min - s.angle_min).abs() < 1e-12);
        assert!((p.angle_increment - s.angle_increment).abs() < 1e-12);
        for i in 0..181 {
            assert_eq!(
                p.is_no_return(i),
                s.is_no_return(i),
                "line {} beam {i}",
                s.line
            );
            if !s.is_no_return(i) {
                assert_eq!(p.ranges[i], s.ranges[i]);
            }
        }
        let ((px, py, pt), (sx, sy, st)) = (xyt(&p.odometry), xyt(&s.odometry));
        assert!(
            (px - sx).abs() <= 5e-7 && (py - sy).abs() <= 5e-7 && wrap_angle(pt - st).abs() <= 5e-7
        );
        let lp = p.logged_pose.expect("FLASER carries the laser pose");
        assert!((lp.inverse() * p.odometry).translation.vector.norm() < 1e-12);
        assert!((p.timestamp.unwrap() - s.timestamp.unwrap()).abs() < 5e-7);
    }
    // Every scan has both hits and (down the corridors) no-returns.
    let hits: usize = parsed
        .iter()
        .map(|s| (0..181).filter(|&i| !s.is_no_return(i)).count())
        .sum();
    let total = parsed.len() * 181;
    assert!(hits > total / 2 && hits < total, "{hits} hits of {total}");

    let truth = dpslam::io::tum::read_tum(&tum).unwrap();
    assert_eq!(truth.len(), sim.truth.len());
    for (r, (t, p)) in truth.iter().zip(&sim.truth) {
        assert!((r.t - t).abs() < 5e-7);
        let (x, y, th) = xyt(p);
        let yaw = r.pose.rotation.euler_angles().2;
        assert!((r.pose.translation.x - x).abs() < 1e-8 && (r.pose.translation.y - y).abs() < 1e-8);
        assert!(r.pose.translation.z == 0.0 && wrap_angle(yaw - th).abs() < 1e-8);
    }
}

#[test]
fn writing_refuses_one_path_for_both_files() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("x");
    assert!(matches!(
        write_sim2d(&p, &p, 1),
        Err(dpslam::Error::Config(_))
    ));
    assert!(!p.exists());
    let missing = dir.path().join("no/such/dir/s.clf");
    assert!(matches!(
        write_sim2d(&missing, &dir.path().join("t.tum"), 1),
        Err(dpslam::Error::Io { .. })
    ));
}

#[test]
fn config_file_overrides_and_reports_errors_by_line() {
    let dir = tempfile::tempdir().unwrap();
    let good = dir.path().join("good.toml");
    std::fs::write(&good, "speed = 1.0\n[odometry]\nrot_bias_deg_per_m = 0.0\n").unwrap();
    let cfg = Sim2dConfig::load(&good).unwrap();
    assert_eq!(cfg.speed, 1.0);
    assert_eq!(cfg.odometry.rot_bias_deg_per_m, 0.0);
    assert_eq!(
        cfg.odometry.trans_per_m, 0.05,
        "unnamed fields keep defaults"
    );
    assert_eq!(cfg.waypoints, Sim2dConfig::default().waypoints);

    let bad = dir.path().join("bad.toml");
    std::fs::write(&bad, "speed = 1.0\n\nsped = 2.0\n").unwrap();
    let e = Sim2dConfig::load(&bad).unwrap_err().to_string();
    assert!(e.contains("bad.toml:line 3") && e.contains("sped"), "{e}");
    std::fs::write(&bad, "range_sigma = -1.0\n").unwrap();
    assert!(matches!(
        Sim2dConfig::load(&bad),
        Err(dpslam::Error::Config(_))
    ));
}

#[test]
fn shipped_data_set_is_reproducible() {
    let dir = tempfile::tempdir().unwrap();
    let (clf, tum) = (dir.path().join("sim2d.clf"), dir.path().join("truth.tum"));
    let cfg = dpslam::sim::sim2d::Sim2dConfig::load(&shipped("sim2d.toml")).unwrap();
    dpslam::sim::sim2d::write_sim2d_with(&cfg, &clf, &tum, 1).unwrap();
    for (made, name) in [(&clf, "sim2d.clf"), (&tum, "truth.tum")] {
        let want = std::fs::read(shipped(name)).unwrap();
        let got = std::fs::read(made).unwrap();
        assert!(
            got == want,
            "data/sim2d/{name} differs from a fresh `dpslam simulate2d --seed 1 --config data/sim2d/sim2d.toml` \
             ({} vs {} bytes): regenerate it as data/sim2d/README.md says",
            got.len(),
            want.len()
        );
    }
    let size = std::fs::metadata(shipped("sim2d.clf")).unwrap().len();
    assert!(size < 2_000_000, "log is {size} bytes");
}
