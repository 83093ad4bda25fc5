//! The benchmark harness: table writer, plot writer, log preparation and an
//! end-to-end `bench accuracy --quick` on the simulator.

use dpslam::config::Config;
use dpslam::eval::relations::RelationsReport;
use dpslam_bench::accuracy::{AccuracyOptions, odometry_trajectory, run_accuracy, truncate_log};
use dpslam_bench::plot::{BACKGROUND, PALETTE, Plot, Series};
use dpslam_bench::report::{Matching, RESULT_COLUMNS, RunResult, results_table};
use dpslam_bench::rig::prepare_log;
use std::path::{Path, PathBuf};

fn sim_log() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../data/sim2d/sim2d.clf")
}

fn run(name: &str, relations: bool, matching: Option<Matching>) -> RunResult {
    RunResult {
        name: name.into(),
        kind: "test".into(),
        scans: 1988,
        scans_processed: 1500,
        particles: 50,
        relations: relations.then_some(RelationsReport {
            n: 1172,
            trans_mean_m: 0.0512,
            trans_std_m: 0.0401,
            rot_mean_deg: 0.734,
            rot_std_deg: 0.5,
        }),
        odometry_relations: None,
        ate_rmse_m: matching.map(|_| 0.25),
        odometry_ate_rmse_m: matching.map(|_| 1.5),
        matching,
        wall_time_s: 212.0,
        data_duration_s: Some(424.0),
        peak_memory_mib: Some(300.0),
        map_memory_mib: 120.4,
        map_image: Some("results/x-map.png".into()),
        trajectory_plot: None,
        note: None,
    }
}

/// Splits a Markdown table row into its cells (honouring `\|` escapes).
fn cells(row: &str) -> Vec<String> {
    let inner = row
        .strip_prefix('|')
        .and_then(|r| r.strip_suffix('|'))
        .unwrap_or_else(|| panic!("row not delimited by pipes: {row}"));
    let mut out = vec![String::new()];
    let mut chars = inner.chars().peekable();
    while let Some(c) = chars.next() {
        match c {
            '\\' if chars.peek() == Some(&'|') => {
                out.last_mut().unwrap().push('|');
                chars.next();
            }
            '|' => out.push(String::new()),
            _ => out.last_mut().unwrap().push(c),
        }
    }
    out.into_iter().map(|c| c.trim().to_string()).collect()
}

#[test]
fn table_is_well_formed_markdown() {
    let runs = [
        run("mit-csail", true, None),
        run("fr|079", false, Some(Matching::Time)),
        run("csail-corrected", false, Some(Matching::ScanIndex)),
    ];
    let table = results_table(&runs);
    let lines: Vec<&str> = table.lines().collect();
    assert_eq!(lines.len(), 2 + runs.len(), "{table}");
    let header = cells(lines[0]);
    assert_eq!(header, RESULT_COLUMNS.map(String::from).to_vec());
    assert!(cells(lines[1]).iter().all(|c| c == "---"));
    for l in &lines[2..] {
        assert_eq!(cells(l).len(), RESULT_COLUMNS.len(), "{l}");
    }
    let col = |name: &str| RESULT_COLUMNS.iter().position(|c| *c == name).unwrap();
    let csail = cells(lines[2]);
    assert_eq!(csail[col("relations trans m")], "0.051 ± 0.040");
    assert_eq!(csail[col("relations rot °")], "0.73 ± 0.50");
    assert_eq!(csail[col("ATE RMSE m")], "–");
    assert_eq!(csail[col("real-time factor")], "2.00");
    assert_eq!(csail[col("map")], "[map](results/x-map.png)");
    // A pipe in a name is escaped, not a new column.
    let fr = cells(lines[3]);
    assert_eq!(fr[0], "fr|079");
    assert_eq!(fr[col("ATE RMSE m")], "0.250");
    assert_eq!(fr[col("odometry ATE RMSE m")], "1.500");
    assert_eq!(cells(lines[4])[col("ATE RMSE m")], "0.250 (by index)");
}

#[test]
fn plot_has_expected_size_and_draws_the_line() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("p.png");
    let mut plot = Plot::new(320, 240);
    plot.series.push(Series {
        label: "diagonal".into(),
        points: vec![[0.0, 0.0], [10.0, 5.0]],
        color: PALETTE[1],
        markers: false,
    });
    plot.write_png(&path).unwrap();
    let img = image::open(&path).unwrap().to_rgb8();
    assert_eq!(img.dimensions(), (320, 240));
    let frame = plot.frame().unwrap();
    // Points along the segment are drawn in the series colour.
    for s in [0.1, 0.5, 0.9] {
        let p = frame.to_pixel([10.0 * s, 5.0 * s]);
        let (x, y) = (p[0].round() as u32, p[1].round() as u32);
        assert_eq!(img.get_pixel(x, y).0, PALETTE[1], "at {s}: ({x}, {y})");
    }
    // Far from the line, inside the plot, is background or grid, never the line.
    let off = frame.to_pixel([8.0, 1.0]);
    assert_ne!(img.get_pixel(off[0] as u32, off[1] as u32).0, PALETTE[1]);
    // Corners are background; something (axes, labels) is drawn.
    assert_eq!(img.get_pixel(0, 0).0, BACKGROUND);
    let drawn = img.pixels().filter(|p| p.0 != BACKGROUND).count();
    assert!(drawn > 500, "{drawn}");
}

#[test]
fn plot_without_data_is_an_error() {
    let mut plot = Plot::new(320, 240);
    plot.series.push(Series {
        label: "empty".into(),
        points: vec![[f64::NAN, 1.0]],
        color: PALETTE[0],
        markers: true,
    });
    assert!(plot.render().is_err());
    assert!(Plot::new(20, 20).render().is_err());
}

#[test]
fn truncated_log_keeps_the_first_scans() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("cut.clf");
    assert_eq!(truncate_log(&sim_log(), &out, 25).unwrap(), 25);
    let (odo, increasing) = odometry_trajectory(&out).unwrap();
    let (all, _) = odometry_trajectory(&sim_log()).unwrap();
    assert!(increasing);
    assert_eq!(odo.len(), 25);
    assert_eq!(odo[..], all[..25]);
}

#[test]
fn prepared_log_applies_the_motion_gate() {
    let cfg = Config::default();
    let log = prepare_log(&sim_log(), &cfg, 30).unwrap();
    assert_eq!(log.steps.len(), 30);
    for s in &log.steps {
        let moved = s.delta.translation.vector.norm() >= cfg.filter.min_translation
            || s.delta.rotation.angle().abs() >= cfg.filter.min_rotation;
        assert!(moved, "scan {} passed the gate without moving", s.index);
        assert!(s.scan.beams.len() <= cfg.laser.max_beams);
    }
    assert!(log.steps.windows(2).all(|w| w[0].index < w[1].index));
    let filter = log.warm_filter(7, 3).unwrap();
    assert_eq!(filter.particles().len(), 7);
    assert_eq!(filter.best_trajectory().len(), 4);
    assert!(log.warm_filter(7, 31).is_err());
}

/// `bench accuracy --quick --only sim2d` at 10 particles, writing below `dir`.
fn quick_sim2d(dir: &Path) -> AccuracyOptions {
    let mut cfg = Config::default();
    cfg.filter.particles = 10;
    let mut opts = AccuracyOptions::new(cfg);
    opts.quick = true;
    opts.only = vec!["sim2d".into()];
    opts.out = dir.join("out");
    opts.docs = dir.join("docs");
    opts
}

/// `bench accuracy --quick --only sim2d` end to end, with few particles so
/// that it stays well under a minute.
#[test]
fn quick_accuracy_on_the_simulator() {
    let dir = tempfile::tempdir().unwrap();
    let opts = quick_sim2d(dir.path());
    let report = run_accuracy(&opts).unwrap();
    assert_eq!(report.runs.len(), 1, "{:?}", report.skipped);
    let r = &report.runs[0];
    assert_eq!(r.scans, dpslam_bench::accuracy::QUICK_SCANS);
    assert_eq!(r.particles, 10);
    assert_eq!(r.matching, Some(Matching::Time));
    let ate = r.ate_rmse_m.unwrap();
    let odo = r.odometry_ate_rmse_m.unwrap();
    assert!(ate.is_finite() && ate >= 0.0 && odo.is_finite());
    assert!(r.data_duration_s.unwrap() > 0.0 && r.wall_time_s > 0.0);
    let md = std::fs::read_to_string(opts.docs.join("RESULTS.md")).unwrap();
    assert!(md.contains("| sim2d |"), "{md}");
    assert!(md.contains("Quick run"));
    for f in ["results/sim2d-map.png", "results/sim2d-trajectory.png"] {
        let img = image::open(opts.docs.join(f)).unwrap();
        assert!(
            img.width() > 0 && img.width() <= 800 && img.height() <= 800,
            "{f}"
        );
    }
    assert!(opts.out.join("sim2d/run/trajectory.tum").is_file());
    assert!(opts.out.join("results.json").is_file());
}

/// `--reuse-runs`: a finished dataset is rescored without mapping it again
/// when its settings are the same, and mapped again when they are not.
#[test]
fn a_finished_run_is_reused_only_with_the_same_settings() {
    let dir = tempfile::tempdir().unwrap();
    let mut opts = quick_sim2d(dir.path());
    opts.reuse_runs = true;
    let traj = opts.out.join("sim2d/run/trajectory.tum");
    let first = run_accuracy(&opts).unwrap().runs.remove(0);
    assert!(first.note.as_deref().is_none_or(|n| !n.contains("reused")));
    // A reused run keeps the file, a new run rewrites it.
    let stamp = std::fs::metadata(&traj).unwrap().modified().unwrap();
    let again = run_accuracy(&opts).unwrap().runs.remove(0);
    assert!(
        again.note.as_deref().unwrap_or("").contains("reused"),
        "{again:?}"
    );
    assert_eq!(again.ate_rmse_m, first.ate_rmse_m);
    // The first run's wall time, read back from run.json (written to the
    // nanosecond, so the last bit of the f64 may differ).
    assert!(
        (again.wall_time_s - first.wall_time_s).abs() < 1e-6,
        "{} against {}",
        again.wall_time_s,
        first.wall_time_s
    );
    assert_eq!(std::fs::metadata(&traj).unwrap().modified().unwrap(), stamp);
    // Other settings: mapped again.
    opts.cfg.filter.particles = 11;
    let other = run_accuracy(&opts).unwrap().runs.remove(0);
    assert_eq!(other.particles, 11);
    assert!(other.note.as_deref().is_none_or(|n| !n.contains("reused")));
    // Without the flag nothing is reused.
    opts.reuse_runs = false;
    let fresh = run_accuracy(&opts).unwrap().runs.remove(0);
    assert!(fresh.note.as_deref().is_none_or(|n| !n.contains("reused")));
}

/// `bench accuracy --learn-motion 1`: the dataset is mapped by a `dpslam
/// map2d --learn-motion 1` process of its own, which leaves the learned
/// model in the run folder, and the report says the model was learned.
#[test]
fn accuracy_with_motion_learning_in_a_mapper_process() {
    let dir = tempfile::tempdir().unwrap();
    let mut opts = quick_sim2d(dir.path());
    opts.mapper = Some(dpslam_binary());
    opts.learn_motion = 1;
    let report = run_accuracy(&opts).unwrap();
    assert_eq!(report.runs.len(), 1, "{:?}", report.skipped);
    let r = &report.runs[0];
    assert!(r.ate_rmse_m.unwrap().is_finite());
    assert!(r.peak_memory_mib.unwrap() > 0.0, "the child's own VmHWM");
    let note = r.note.as_deref().unwrap_or("");
    assert!(note.contains("motion model learned"), "{note}");
    let history = std::fs::read_to_string(opts.out.join("sim2d/run/motion_learning.json")).unwrap();
    let rounds: serde_json::Value = serde_json::from_str(&history).unwrap();
    assert_eq!(rounds.as_array().map(Vec::len), Some(1), "{history}");
    // The wall time covers the learning round and the final run.
    let run: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(opts.out.join("sim2d/run/run.json")).unwrap(),
    )
    .unwrap();
    assert!(r.wall_time_s > run["wall_time_s"].as_f64().unwrap());
}

/// The `dpslam` binary of this build (`cargo test --workspace` builds it
/// into the folder above this test's `deps/`).
fn dpslam_binary() -> std::path::PathBuf {
    let exe = std::env::current_exe().unwrap();
    let bin = exe
        .parent()
        .and_then(Path::parent)
        .unwrap()
        .join(format!("dpslam{}", std::env::consts::EXE_SUFFIX));
    assert!(
        bin.is_file(),
        "{} is missing: run the tests with `cargo test --workspace` (it builds the binary)",
        bin.display()
    );
    bin
}
