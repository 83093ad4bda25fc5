//! `dpslam-bench 3d` end to end on a tiny sequence: the report has a row per
//! method with a finite ATE, the pictures are written and small. KISS-ICP
//! runs only where `kiss_icp_pipeline` is on the PATH (not in CI), and is
//! reported as not run otherwise.

use dpslam_bench::bench3d::{
    Bench3dOptions, DPSLAM, KISS_ICP, ODOMETRY, find_on_path, quick_sequences, run_bench3d,
};
use std::path::PathBuf;

#[test]
fn tiny_bench_reports_every_method_with_a_finite_ate() {
    let dir = tempfile::tempdir().unwrap();
    let mut opts = Bench3dOptions::new(PathBuf::from(env!("CARGO_BIN_EXE_dpslam")));
    opts.sequences = quick_sequences()
        .into_iter()
        .filter(|s| s.name == "corridors-tiny")
        .collect();
    assert_eq!(opts.sequences.len(), 1);
    opts.out = dir.path().join("out");
    opts.docs = dir.path().join("docs");
    opts.command = "test".into();
    let kiss = find_on_path("kiss_icp_pipeline").is_some();
    assert_eq!(opts.kiss_icp.is_some(), kiss);

    let r = run_bench3d(&opts).unwrap();
    let s = &r.sequences[0];
    assert_eq!((s.sweeps, s.reused), (8, false));
    assert!(s.points_per_sweep > 1000.0, "{}", s.points_per_sweep);
    let dp = s.run(DPSLAM).expect("dpslam ran");
    let odo = s.run(ODOMETRY).expect("odometry scored");
    for m in [dp, odo] {
        assert!(
            m.ate_rmse_m.is_finite() && m.ate_rot_deg.is_finite(),
            "{m:?}"
        );
        assert_eq!(m.poses, 8);
    }
    let u = dp.usage.expect("measured");
    assert!(u.cpu_s > 0.0 && u.peak_rss_mib > 1.0, "{u:?}");
    assert!(dp.time_per_sweep_s.is_some_and(|t| t > 0.0));
    // The sweeps alone do better than the noisy odometry round the corner.
    assert!(
        dp.ate_rmse_m < odo.ate_rmse_m,
        "{} vs {}",
        dp.ate_rmse_m,
        odo.ate_rmse_m
    );
    if kiss {
        assert!(s.run(KISS_ICP).is_some_and(|k| k.ate_rmse_m.is_finite()));
    } else {
        assert!(s.not_run.iter().any(|n| n.method == KISS_ICP));
    }

    let md = std::fs::read_to_string(opts.docs.join("RESULTS-3D.md")).unwrap();
    for needle in [
        "## corridors-tiny",
        "| dpslam map3d |",
        "| odometry |",
        "ATE RMSE m",
    ] {
        assert!(md.contains(needle), "{needle} missing from\n{md}");
    }
    for m in &s.runs {
        let pic = opts.docs.join(m.picture.as_ref().unwrap());
        let size = std::fs::metadata(&pic).unwrap().len();
        assert!(
            size > 1000 && size < 300_000,
            "{}: {size} bytes",
            pic.display()
        );
    }
    assert!(opts.out.join("results-3d.json").is_file());
}
