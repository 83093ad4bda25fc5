//! The DP likelihood along a featureless corridor, with exact poses: the
//! bias that surface fill (`laser.surface_fill_gap`) removes. The map is
//! built by one particle at the simulator's true poses; each probed scan is
//! then weighed at its true pose shifted along the corridor.

use dpslam::config::{Config, ProposalKind};
use dpslam::filter::{Sample, StepInput};
use dpslam::geometry::{Pose2, pose2};
use dpslam::io::log2d::open_log2d;
use dpslam::laser_model::LaserModel;
use dpslam::pipeline::map2d::sensor_mount;
use dpslam::sim::sim2d::{OdometryNoise, Segment2, Sim2dConfig, World2d, simulate2d};
use dpslam::slam::slam2d::{moved_enough, new_filter, to_scan};

const MAX_RANGE: f64 = 20.0;

/// A straight corridor 1.4 m wide, driven at 0.9 m per scan with exact
/// odometry, written as a CARMEN log in `dir`.
fn corridor_log(dir: &std::path::Path) -> std::path::PathBuf {
    let wall = |a: [f64; 2], b: [f64; 2]| Segment2 { a, b };
    let cfg = Sim2dConfig {
        waypoints: vec![[0.0, 0.0], [25.0, 0.0]],
        speed: 0.9,
        scan_period: 1.0,
        beams: 361,
        fov_deg: 180.0,
        max_range: MAX_RANGE,
        odometry: OdometryNoise::zero(),
        world: Some(World2d {
            segments: vec![
                wall([-2.0, -0.7], [40.0, -0.7]),
                wall([-2.0, 0.7], [40.0, 0.7]),
                wall([-2.0, -0.7], [-2.0, 0.7]),
                wall([40.0, -0.7], [40.0, 0.7]),
            ],
        }),
        ..Sim2dConfig::default()
    };
    let out = simulate2d(&cfg, 1).unwrap();
    let path = dir.join("corridor.clf");
    std::fs::write(&path, out.clf_text()).unwrap();
    path
}

/// How far (nats) the likelihood of scan `probe` at its true pose lies
/// below the best shift along the corridor (−1.8 … +0.4 m in 5 cm steps),
/// and that best shift (m).
fn deficit_at_truth(
    log: &std::path::Path,
    fill_gap: f64,
    fill_hits: f64,
    probe: usize,
) -> (f64, f64) {
    let mut cfg = Config::default();
    cfg.filter.particles = 1;
    cfg.filter.samples_per_particle = 1;
    cfg.filter.proposal = ProposalKind::Motion;
    cfg.motion2d.std_d = [0.0, 0.0];
    cfg.motion2d.std_c = [0.0, 0.0];
    cfg.motion2d.std_t = [0.0, 0.0];
    cfg.motion2d.min_std_xy = 1e-9;
    cfg.motion2d.min_std_t = 1e-9;
    cfg.laser.surface_fill_gap = fill_gap;
    cfg.laser.surface_fill_hits = fill_hits;
    let reader = open_log2d(log).unwrap();
    let mount = sensor_mount(&cfg, reader.format());
    let mut filter = None;
    let mut last: Option<Pose2> = None;
    for (index, item) in reader.enumerate() {
        let s = item.unwrap();
        let scan = to_scan(
            &s.as_ranges(),
            mount,
            cfg.laser.max_beams,
            MAX_RANGE,
            cfg.laser.no_return,
        );
        let Some(f) = filter.as_mut() else {
            let laser = LaserModel::new(&cfg.laser, cfg.cell_size(), MAX_RANGE);
            filter = Some(new_filter(&cfg, laser, &scan, index as u32));
            last = Some(s.odometry);
            continue;
        };
        let delta = last.unwrap().inverse() * s.odometry;
        if !moved_enough(&cfg.filter, &delta) {
            continue;
        }
        if index == probe {
            let truth = f.particles()[0].pose * delta;
            let score = |dx: f64| {
                let sample = [Sample {
                    pose: truth * pose2(dx, 0.0, 0.0),
                    parent: 0,
                }];
                f.weigh(&sample, &scan).scores[0]
            };
            let at_truth = score(0.0);
            let (best, shift) = (-36..=8)
                .map(|k| (score(k as f64 * 0.05), k as f64 * 0.05))
                .fold(
                    (f64::NEG_INFINITY, 0.0),
                    |a, b| if b.0 > a.0 { b } else { a },
                );
            return (best - at_truth, shift);
        }
        f.step(&StepInput::motion(delta, &scan, index as u32));
        last = Some(s.odometry);
    }
    panic!("scan {probe} not reached");
}

#[test]
fn surface_fill_removes_most_of_the_corridor_bias() {
    let dir = tempfile::tempdir().unwrap();
    let log = corridor_log(dir.path());
    // The release's update: a scan scores far higher at the earlier scans'
    // poses (0.9 and 1.8 m back) than at its own.
    let (off, off_shift) = deficit_at_truth(&log, 0.0, 0.25, 20);
    assert!(
        off > 30.0 && off_shift < -0.8,
        "off: {off} nats, best at {off_shift} m"
    );
    // Filling the walls between sparse samples with one hit per cell: the
    // truth lies within a third of that of the best shift (16 of 63 nats)…
    let (full, _) = deficit_at_truth(&log, 0.5, 1.0, 20);
    assert!(
        full < off / 3.0,
        "fill 1: {full} nats against {off} without"
    );
    // … and with the default quarter hit, within half (24 of 63).
    let (soft, _) = deficit_at_truth(&log, 0.5, 0.25, 20);
    assert!(
        full < soft && soft < off / 2.0,
        "fill 0.25: {soft} nats against {full} (1) and {off} (off)"
    );
}
