//! End-to-end 2-D mapping runs on short logs: outputs, accuracy against the
//! simulator's truth, determinism across thread counts, and bad input.

use dpslam::config::Config;
use dpslam::eval::ate::{AteOptions, evaluate_ate};
use dpslam::io::tum::read_tum;
use dpslam::pipeline::map2d::run_map2d;
use std::path::{Path, PathBuf};

const SIM_LOG: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/data/sim2d/sim2d.clf");
const SIM_TRUTH: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/data/sim2d/truth.tum");
const LOOP5: &str = concat!(
    env!("CARGO_MANIFEST_DIR"),
    "/../shared/datasets/dpslam/loop5.log"
);

/// The first `n` lines of a text file, written to `dir`.
fn prefix(src: &str, n: usize, dir: &Path, name: &str) -> PathBuf {
    let text = std::fs::read_to_string(src).unwrap();
    let head: Vec<&str> = text.lines().take(n).collect();
    let p = dir.join(name);
    std::fs::write(&p, head.join("\n") + "\n").unwrap();
    p
}

fn small_config() -> Config {
    let mut c = Config::default();
    c.filter.particles = 20;
    c
}

#[test]
fn simulated_prefix_maps_with_all_outputs_and_small_ate() {
    let dir = tempfile::tempdir().unwrap();
    let log = prefix(SIM_LOG, 250, dir.path(), "sim.clf");
    let out = dir.path().join("run");
    let s = run_map2d(&log, &out, &small_config()).unwrap();
    for f in [
        "map.png",
        "map.pgm",
        "map.yaml",
        "trajectory.tum",
        "run.json",
        "config.toml",
    ] {
        assert!(
            out.join(f).metadata().unwrap().len() > 0,
            "{f} missing or empty"
        );
    }
    let traj = read_tum(&out.join("trajectory.tum")).unwrap();
    assert_eq!(traj.len(), s.scans, "one trajectory line per input scan");
    assert!(s.scans_processed > 50 && s.scans_processed <= s.scans);
    // time stamps are the log's, in input order
    assert!(traj.windows(2).all(|w| w[1].t > w[0].t));
    let truth = read_tum(Path::new(SIM_TRUTH)).unwrap();
    let ate = evaluate_ate(&truth, &traj, &AteOptions::default()).unwrap();
    assert_eq!(ate.n, traj.len());
    assert!(
        ate.rmse_m < 0.10,
        "ATE {} m on the simulated prefix",
        ate.rmse_m
    );
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("run.json")).unwrap()).unwrap();
    assert_eq!(json["particles"], 20);
    assert!(json["wall_time_s"].as_f64().unwrap() > 0.0);
    // the echoed configuration reproduces the run's settings
    let echoed = Config::from_toml_file(&out.join("config.toml")).unwrap();
    assert_eq!(echoed, small_config());
}

#[test]
fn the_final_alignment_lowers_the_scan_to_scan_error_and_keeps_the_filter_s_poses_beside() {
    use dpslam::geometry::xyt;
    use dpslam::io::odometry::planar;
    let dir = tempfile::tempdir().unwrap();
    let log = prefix(SIM_LOG, 250, dir.path(), "sim.clf");
    let out = dir.path().join("run");
    let s = run_map2d(&log, &out, &small_config()).unwrap();
    let refined = read_tum(&out.join("trajectory.tum")).unwrap();
    let filter = read_tum(&out.join("trajectory_filter.tum")).unwrap();
    assert_eq!(refined.len(), filter.len());
    assert!(refined.iter().zip(&filter).all(|(a, b)| a.t == b.t));
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("run.json")).unwrap()).unwrap();
    assert_eq!(json["refine"]["passes"], small_config().refine.passes);
    assert!(json["refine"]["moved_median_m"].as_f64().unwrap() > 0.0);
    assert_eq!(s.scans, refined.len());
    // Each scan relative to the one before it, against the same motion in
    // the truth: the mean translation error, m.
    let truth = read_tum(Path::new(SIM_TRUTH)).unwrap();
    let step_error = |rows: &[dpslam::io::tum::Stamped]| {
        let sum: f64 = (1..rows.len())
            .map(|i| {
                let est = planar(&rows[i - 1].pose).inverse() * planar(&rows[i].pose);
                let tru = planar(&truth[i - 1].pose).inverse() * planar(&truth[i].pose);
                let (x, y, _) = xyt(&(tru.inverse() * est));
                x.hypot(y)
            })
            .sum();
        sum / (rows.len() - 1) as f64
    };
    let (e_filter, e_refined) = (step_error(&filter), step_error(&refined));
    assert!(
        e_refined < 0.5 * e_filter,
        "scan to scan: refined {e_refined:.4} m, filter {e_filter:.4} m"
    );
    // The global shape stays the filter's.
    let ate = |rows| {
        evaluate_ate(&truth, rows, &AteOptions::default())
            .unwrap()
            .rmse_m
    };
    let (a_filter, a_refined) = (ate(&filter), ate(&refined));
    assert!(
        a_refined < a_filter + 0.005,
        "ATE: refined {a_refined:.4} m, filter {a_filter:.4} m"
    );
    // Off, there is one trajectory and no stale filter trajectory.
    let mut off = small_config();
    off.refine.passes = 0;
    let s = run_map2d(&log, &out, &off).unwrap();
    assert!(!out.join("trajectory_filter.tum").exists());
    let rows = read_tum(&out.join("trajectory.tum")).unwrap();
    assert_eq!(rows.len(), s.scans);
    assert!(rows.iter().zip(&filter).all(|(a, b)| a.pose == b.pose));
}

#[test]
fn same_seed_same_trajectory_whatever_the_thread_count() {
    let dir = tempfile::tempdir().unwrap();
    let log = prefix(SIM_LOG, 120, dir.path(), "sim.clf");
    let run = |threads: usize, seed: u64| {
        let out = dir.path().join(format!("t{threads}s{seed}"));
        let mut cfg = small_config();
        cfg.seed = seed;
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap()
            .install(|| run_map2d(&log, &out, &cfg).unwrap());
        std::fs::read(out.join("trajectory.tum")).unwrap()
    };
    let one = run(1, 7);
    assert_eq!(one, run(3, 7), "1 vs 3 threads differ");
    assert_ne!(
        one,
        run(1, 8),
        "a different seed should give a different trajectory"
    );
}

#[test]
fn dpslam_format_log_runs_with_the_release_laser_offset() {
    let dir = tempfile::tempdir().unwrap();
    // 60 Odometry/Laser pairs of the release's sample log.
    let log = prefix(LOOP5, 120, dir.path(), "loop5-head.log");
    let out = dir.path().join("run");
    let s = run_map2d(&log, &out, &small_config()).unwrap();
    assert_eq!(s.format, "DpSlam");
    assert_eq!(s.scans, 60);
    let traj = read_tum(&out.join("trajectory.tum")).unwrap();
    // no time stamps: t is the scan index
    assert_eq!(traj[0].t, 0.0);
    assert_eq!(traj[59].t, 59.0);
}

#[test]
fn bad_input_fails_with_file_and_line_and_writes_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let log = prefix(SIM_LOG, 40, dir.path(), "sim.clf");
    let mut text = std::fs::read_to_string(&log).unwrap();
    text.push_str("FLASER 181 1.0 2.0\n");
    std::fs::write(&log, text).unwrap();
    let out = dir.path().join("run");
    let e = run_map2d(&log, &out, &small_config())
        .unwrap_err()
        .to_string();
    assert!(e.contains("sim.clf") && e.contains("line 41"), "{e}");
    assert!(
        !out.exists(),
        "a failed run must not leave an output folder"
    );
    let missing = dir.path().join("nope.clf");
    let e = run_map2d(&missing, &out, &small_config())
        .unwrap_err()
        .to_string();
    assert!(e.contains("nope.clf"), "{e}");
    let empty = dir.path().join("empty.clf");
    std::fs::write(&empty, "").unwrap();
    assert!(run_map2d(&empty, &out, &small_config()).is_err());
    assert!(!out.exists());
}

#[test]
fn motion_learning_recovers_the_simulated_odometry_bias_and_records_the_model() {
    let dir = tempfile::tempdir().unwrap();
    let log = prefix(SIM_LOG, 200, dir.path(), "sim.clf");
    let out = dir.path().join("run");
    let cfg = small_config();
    let mut seen = 0;
    let ranges = dpslam::pipeline::map2d::RangeSettings::of_log(&log, &cfg).unwrap();
    let (s, rounds) = dpslam::pipeline::learn_motion::run_map2d_learning(
        &log,
        &out,
        &cfg,
        dpslam::backend::Backend::Cpu,
        &ranges,
        1,
        |_| seen += 1,
    )
    .unwrap();
    assert_eq!((seen, rounds.len()), (1, 1));
    let fit = &rounds[0].fit;
    assert!(fit.steps + fit.outliers + 1 == s.scans_processed, "{fit:?}");
    assert!(fit.log_likelihood > fit.prior_log_likelihood, "{fit:?}");
    let m = &fit.model;
    // The simulator's odometry turns 0.5°/m too far left (data/sim2d): the
    // learned turn mean undoes it, −0.0087 rad per metre.
    assert!(
        (-0.015..-0.004).contains(&m.mean_t[0]),
        "turn per metre {}",
        m.mean_t[0]
    );
    // Its odometry is far better than the release's robot: every learned
    // turn std is below the release's, the floor by an order of magnitude.
    let release = Config::default().motion2d;
    assert!(
        m.std_t[1] < release.std_t[1] && m.min_std_t < 0.2 * release.min_std_t,
        "{m:?}"
    );
    // The run folder reproduces the final run: its config holds the model.
    let written = Config::from_toml_file(&out.join("config.toml")).unwrap();
    assert_eq!(&written.motion2d, m);
    let json = std::fs::read_to_string(out.join("motion_learning.json")).unwrap();
    assert!(
        json.contains("\"round\": 1") && json.contains("mean_t"),
        "{json}"
    );
    let traj = read_tum(&out.join("trajectory.tum")).unwrap();
    let truth = read_tum(Path::new(SIM_TRUTH)).unwrap();
    let ate = evaluate_ate(&truth, &traj, &AteOptions::default()).unwrap();
    assert!(ate.rmse_m < 0.10, "ATE {} m", ate.rmse_m);
}

#[test]
fn hierarchical_runs_close_every_window_and_follow_the_simulated_loop() {
    let dir = tempfile::tempdir().unwrap();
    let log = prefix(SIM_LOG, 130, dir.path(), "sim.clf");
    let mut cfg = small_config();
    cfg.hierarchy.enabled = true;
    cfg.hierarchy.window = 20;
    cfg.hierarchy.particles = 10;
    cfg.hierarchy.samples_per_particle = 2;
    let out = dir.path().join("run");
    let s = run_map2d(&log, &out, &cfg).unwrap();
    let traj = read_tum(&out.join("trajectory.tum")).unwrap();
    assert_eq!(traj.len(), s.scans);
    // Windows join up: no jump between consecutive poses larger than the
    // robot moves between scans (0.2 m at 1 m/s and 5 Hz) plus the
    // perturbation's few centimetres.
    for w in traj.windows(2) {
        let d = (w[1].pose.translation.vector - w[0].pose.translation.vector).norm();
        assert!(d < 0.4, "jump of {d} m at t = {}", w[1].t);
    }
    let truth = read_tum(Path::new(SIM_TRUTH)).unwrap();
    let ate = evaluate_ate(&truth, &traj, &AteOptions::default()).unwrap();
    assert!(ate.rmse_m < 0.15, "ATE {} m", ate.rmse_m);
    // The same seed gives the same run on another thread count.
    let out1 = dir.path().join("run1");
    rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .unwrap()
        .install(|| run_map2d(&log, &out1, &cfg).unwrap());
    assert_eq!(
        std::fs::read(out.join("trajectory.tum")).unwrap(),
        std::fs::read(out1.join("trajectory.tum")).unwrap()
    );
}

/// The CPU scorer, recording the laser variances (m²) it was asked to score
/// with: one per level of hierarchical SLAM.
struct Recording {
    inner: dpslam::scorer::CpuScorer<2>,
    variances: std::sync::Arc<std::sync::Mutex<Vec<f64>>>,
}

impl dpslam::scorer::Scorer<2, dpslam::geometry::Pose2> for Recording {
    fn name(&self) -> &'static str {
        "recording"
    }

    fn score(
        &self,
        ctx: &dpslam::scorer::ScoreContext<'_, 2, dpslam::geometry::Pose2>,
        candidates: &[dpslam::scorer::Candidate<dpslam::geometry::Pose2>],
        subset: dpslam::scorer::BeamSubset,
        trace: dpslam::laser_model::Trace,
    ) -> Vec<f64> {
        let mut seen = self.variances.lock().unwrap();
        if !seen.contains(&ctx.laser.variance) {
            seen.push(ctx.laser.variance);
        }
        drop(seen);
        self.inner.score(ctx, candidates, subset, trace)
    }
}

#[test]
fn the_chosen_scorer_scores_both_levels_of_hierarchical_slam() {
    let mut cfg = small_config();
    cfg.filter.particles = 10;
    cfg.hierarchy.enabled = true;
    cfg.hierarchy.window = 5;
    cfg.hierarchy.particles = 5;
    cfg.hierarchy.samples_per_particle = 2;
    let variances = std::sync::Arc::new(std::sync::Mutex::new(Vec::new()));
    let mut slam = dpslam::slam::Slam2d::new(cfg.clone()).unwrap();
    slam.set_scorer(Box::new(Recording {
        inner: dpslam::scorer::CpuScorer::new(),
        variances: variances.clone(),
    }))
    .unwrap();
    let dir = tempfile::tempdir().unwrap();
    let log = prefix(SIM_LOG, 40, dir.path(), "sim.clf");
    for scan in dpslam::io::log2d::open_log2d(&log).unwrap() {
        let scan = scan.unwrap();
        let stamp = scan.timestamp.unwrap_or(slam.scans() as f64);
        slam.add_scan(stamp, scan.odometry, &scan.as_ranges())
            .unwrap();
    }
    slam.finish();
    assert!(slam.stats().len() > cfg.hierarchy.window, "too few steps");
    let seen = variances.lock().unwrap().clone();
    assert_eq!(seen.len(), 2, "variances scored with: {seen:?}");
    assert!(seen.contains(&cfg.hierarchy.variance), "{seen:?}");
    assert_eq!(slam.scorer().map(|s| s.name()), Some("recording"));
}

#[test]
fn configured_beam_angles_replace_the_logs_and_are_echoed() {
    let dir = tempfile::tempdir().unwrap();
    let log = prefix(SIM_LOG, 250, dir.path(), "sim.clf");
    let run = |name: &str, cfg: &Config| {
        let out = dir.path().join(name);
        run_map2d(&log, &out, cfg).unwrap();
        let echoed = Config::from_toml_file(&out.join("config.toml")).unwrap();
        assert_eq!(&echoed, cfg, "{name}: the echo reproduces the overrides");
        std::fs::read(out.join("trajectory.tum")).unwrap()
    };
    let plain = run("plain", &small_config());
    // The simulator writes 181 beams over 180°: stating that changes nothing.
    let mut same = small_config();
    same.laser.angle_min_deg = Some(-90.0);
    same.laser.angle_increment_deg = Some(1.0);
    assert_eq!(run("same", &same), plain);
    // A scan stretched by 5 %: the beams at the edges turn 4.5°.
    let mut stretched = small_config();
    stretched.laser.angle_increment_deg = Some(1.05);
    let bent = run("stretched", &stretched);
    assert_ne!(bent, plain);
    let truth = read_tum(Path::new(SIM_TRUTH)).unwrap();
    let ate = |name: &str| {
        let t = read_tum(&dir.path().join(name).join("trajectory.tum")).unwrap();
        evaluate_ate(&truth, &t, &AteOptions::default())
            .unwrap()
            .rmse_m
    };
    let (good, bad) = (ate("plain"), ate("stretched"));
    assert!(
        bad > good,
        "a wrong beam geometry fits worse: {bad} vs {good} m"
    );
}

#[test]
fn skipped_scans_are_placed_by_their_match_not_by_bad_odometry() {
    use dpslam::geometry::{Pose2, pose2, xyt};
    // The simulator moves 0.2 m per scan: with 0.35 m between processed
    // scans every second scan is skipped. The skipped scans' odometry is
    // off by 5 cm and 1.7° (the processed scans' is the log's), as when a
    // robot's odometry slips between the scans the filter processes.
    let truth = read_tum(Path::new(SIM_TRUTH)).unwrap();
    let run = |match_skipped: bool| {
        let mut cfg = small_config();
        cfg.filter.min_translation = 0.35;
        cfg.filter.min_rotation = 0.5;
        cfg.filter.match_skipped = match_skipped;
        let mut slam = dpslam::slam::Slam2d::new(cfg).unwrap();
        let mut skipped = Vec::new();
        for (i, scan) in dpslam::io::log2d::open_log2d(Path::new(SIM_LOG))
            .unwrap()
            .take(120)
            .enumerate()
        {
            let scan = scan.unwrap();
            let odometry = match i % 2 {
                1 => scan.odometry * pose2(0.04, -0.03, 0.03),
                _ => scan.odometry,
            };
            let e = slam
                .add_scan(scan.timestamp.unwrap(), odometry, &scan.as_ranges())
                .unwrap();
            if !e.processed {
                skipped.push(i);
            }
        }
        (slam.trajectory().unwrap(), skipped)
    };
    let (on, skipped_on) = run(true);
    let (off, skipped_off) = run(false);
    assert_eq!(skipped_on, skipped_off);
    assert!(skipped_on.len() > 40, "{} skipped", skipped_on.len());
    // Each skipped scan relative to the scan before it (processed), against
    // the same relative motion in the truth: translation m, rotation rad.
    let to_pose = |p: &dpslam::io::tum::Stamped| dpslam::io::odometry::planar(&p.pose);
    let error = |rows: &[(f64, Pose2)]| {
        let (mut dt, mut dr) = (0.0, 0.0);
        for &i in &skipped_on {
            let est = rows[i - 1].1.inverse() * rows[i].1;
            let tru = to_pose(&truth[i - 1]).inverse() * to_pose(&truth[i]);
            let (x, y, t) = xyt(&(tru.inverse() * est));
            dt += x.hypot(y);
            dr += t.abs();
        }
        let n = skipped_on.len() as f64;
        (dt / n, dr / n)
    };
    let (t_on, r_on) = error(&on);
    let (t_off, r_off) = error(&off);
    // The match is fused with the motion model (the posterior of the two),
    // which pulls it part of the way back towards the odometry: it mends
    // the heading far more than the position.
    assert!(
        t_on < 0.75 * t_off && r_on < 0.5 * r_off,
        "matched {t_on:.3} m {r_on:.4} rad, by odometry {t_off:.3} m {r_off:.4} rad"
    );
    // The processed scans' rows are the filter's, the same either way.
    for i in (0..on.len()).filter(|i| !skipped_on.contains(i)) {
        assert_eq!(on[i], off[i], "row {i}");
    }
}

#[test]
fn scans_whose_match_confirms_odometry_are_skipped_and_a_slip_is_processed_scan_by_scan() {
    use dpslam::geometry::pose2;
    // The simulator moves 0.2 m per scan. Past the small gate (0.05 m) a
    // scan is still skipped while the best particle's match confirms the
    // odometry, up to the confirmed gate (0.5 m here; off by default):
    // about every third scan is processed. From scan 40 to 59 the odometry
    // reports 0.15 m more per scan than the robot drove, as a slipping
    // wheel does: there every scan past the small gate is processed.
    let run = |slip: bool| {
        let mut cfg = small_config();
        cfg.filter.confirmed_translation = 0.5;
        cfg.filter.confirmed_rotation = 0.25;
        let mut slam = dpslam::slam::Slam2d::new(cfg).unwrap();
        let mut processed = Vec::new();
        for (i, scan) in dpslam::io::log2d::open_log2d(Path::new(SIM_LOG))
            .unwrap()
            .take(80)
            .enumerate()
        {
            let scan = scan.unwrap();
            let extra = if slip { i.clamp(40, 60) - 40 } else { 0 };
            let odometry = scan.odometry * pose2(0.15 * extra as f64, 0.0, 0.0);
            let e = slam
                .add_scan(scan.timestamp.unwrap(), odometry, &scan.as_ranges())
                .unwrap();
            if e.processed {
                processed.push(i);
            }
        }
        processed
    };
    let in_slip = |p: &[usize]| p.iter().filter(|&&i| (41..60).contains(&i)).count();
    let (good, slipping) = (run(false), run(true));
    assert!(good.len() < 35, "{} of 80 processed", good.len());
    assert!(in_slip(&good) <= 8, "{good:?}");
    assert!(in_slip(&slipping) >= 17, "{slipping:?}");
    // Before the slip the two runs are the same.
    let before = |p: &[usize]| p.iter().copied().filter(|&i| i < 40).collect::<Vec<_>>();
    assert_eq!(before(&good), before(&slipping));
}
