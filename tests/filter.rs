//! Filter-level behaviour on the shipped simulated log.

use dpslam::config::{Config, MapConfig};
use dpslam_bench::rig::prepare_log;
use std::path::Path;

/// Free path length (m) held by the tree root's entries: where the shared
/// free-space update of the first step lands (every particle's parent is the root).
fn root_free_path(filter: &dpslam::filter::ParticleFilter<2, dpslam::geometry::Pose2>) -> f64 {
    let root = filter.tree().root();
    let mut total = 0.0;
    filter.map().for_each_cell(|_, list| {
        for e in list.iter().filter(|e| e.node == root && e.hits <= 0.0) {
            total += e.distance as f64;
        }
    });
    total
}

#[test]
fn a_sample_of_particles_estimates_the_shared_free_space_update() {
    let log = Path::new(env!("CARGO_MANIFEST_DIR")).join("data/sim2d/sim2d.clf");
    let cfg = Config::default();
    // One step: both filters weigh and resample on the same map, so only
    // the in-place free-space sums can differ.
    let prepared = prepare_log(&log, &cfg, 1).unwrap();
    let particles = 200;
    let mut totals = Vec::new();
    let mut entries = Vec::new();
    for sharers in [0, 64] {
        let mut f = prepared.new_filter(particles);
        f.set_map_update(&MapConfig {
            free_space_particles: sharers,
            ..MapConfig::default()
        });
        let before = root_free_path(&f);
        for s in &prepared.steps {
            f.step(&s.input());
        }
        totals.push(root_free_path(&f) - before);
        entries.push(f.map().entry_count());
    }
    // The sample of 64 carries weight 1/64 each: the same free path length in
    // expectation as all 200 at 1/200 (a wrong weight would be off by 3×).
    let rel = (totals[1] - totals[0]).abs() / totals[0];
    assert!(
        rel < 0.01,
        "free path {:.1} m (64) vs {:.1} m (all): {rel}",
        totals[1],
        totals[0]
    );
    // Sampling only changes in-place sums, never which entries exist.
    assert!(
        totals[0] > 1.0,
        "no shared free-space update: {}",
        totals[0]
    );
    assert_eq!(entries[0], entries[1]);
}

#[test]
fn copies_of_one_sample_share_one_node_and_distinct_samples_do_not() {
    let log = Path::new(env!("CARGO_MANIFEST_DIR")).join("data/sim2d/sim2d.clf");
    let prepared = prepare_log(&log, &Config::default(), 1).unwrap();
    let mut f = prepared.new_filter(50);
    let mut shared_steps = 0;
    for s in prepared.steps.iter().take(20) {
        f.step(&s.input());
        let particles = f.particles();
        // Resampling copies a sample into every particle it picks: equal
        // poses are one sample (two draws from the noise never coincide).
        for a in particles {
            for b in particles {
                assert_eq!(a.pose == b.pose, a.node == b.node, "{a:?} vs {b:?}");
            }
        }
        let mut nodes: Vec<_> = particles.iter().map(|p| p.node).collect();
        nodes.sort_unstable();
        nodes.dedup();
        if nodes.len() < particles.len() {
            shared_steps += 1;
        }
    }
    assert!(shared_steps > 0, "no step resampled a sample twice");
}

#[test]
fn a_views_mean_weighs_its_samples_and_ignores_culled_ones() {
    use dpslam::filter::{Sample, view_means};
    use dpslam::geometry::{pose2, xyt};
    let at = |x: f64, y: f64, t: f64, parent: usize| Sample {
        pose: pose2(x, y, t),
        parent,
    };
    // View 7: three samples, weights 1/3, 1 and 0 (culled); view 9: one.
    let samples = [
        at(0.0, 0.0, 0.0, 0),
        at(0.1, 0.02, 0.01, 0),
        at(5.0, 5.0, 1.0, 1),
        at(1.0, 1.0, 0.3, 2),
    ];
    let scores = [-(3f64.ln()), 0.0, f64::NEG_INFINITY, -40.0];
    let view = |j: usize| if samples[j].parent == 2 { 9 } else { 7 };
    let means = view_means(&samples, &scores, view);
    let (x, y, t) = xyt(&means[&7]);
    // (0·1/3 + 0.1·1) / (4/3), and likewise for y and θ.
    assert!((x - 0.075).abs() < 1e-4, "x {x}");
    assert!((y - 0.015).abs() < 1e-4, "y {y}");
    assert!((t - 0.0075).abs() < 1e-6, "θ {t}");
    assert_eq!(means[&9], samples[3].pose, "a lone sample is its own mean");
    // A view whose samples were all culled keeps its first sample.
    let culled = [f64::NEG_INFINITY; 4];
    assert_eq!(view_means(&samples, &culled, view)[&7], samples[0].pose);
}

#[test]
fn reporting_the_posterior_mean_changes_the_trajectory_not_the_map() {
    use dpslam::config::ReportedPose;
    let log = Path::new(env!("CARGO_MANIFEST_DIR")).join("data/sim2d/sim2d.clf");
    let mut runs = Vec::new();
    for report in [ReportedPose::Sample, ReportedPose::PosteriorMean] {
        let mut cfg = Config::default();
        cfg.filter.report = report;
        let prepared = prepare_log(&log, &cfg, 1).unwrap();
        let mut f = prepared.new_filter(50);
        for s in prepared.steps.iter().take(30) {
            f.step(&s.input());
        }
        let mut map = Vec::new();
        f.map().for_each_cell(|k, list| {
            map.extend(
                list.iter()
                    .map(|e| (k, e.node, e.hits.to_bits(), e.distance.to_bits())),
            )
        });
        map.sort_unstable();
        let best = f.particles()[f.best_index()].pose;
        runs.push((f.best_trajectory(), map, best));
    }
    let (sample, mean) = (&runs[0], &runs[1]);
    assert_eq!(
        sample.1, mean.1,
        "the map is built at the samples either way"
    );
    assert_eq!(
        sample.0.last().unwrap().pose,
        sample.2,
        "`sample` reports the sample"
    );
    let moved: Vec<f64> = sample
        .0
        .iter()
        .zip(&mean.0)
        .map(|(a, b)| (a.pose.translation.vector - b.pose.translation.vector).norm())
        .collect();
    // Means differ from samples by a fraction of the samples' spread (cm).
    assert!(moved.iter().any(|&d| d > 1e-4), "no reported pose moved");
    assert!(moved.iter().all(|&d| d < 0.05), "{moved:?}");
}

#[test]
fn selective_resampling_keeps_every_lineage_until_the_weights_degenerate() {
    let log = Path::new(env!("CARGO_MANIFEST_DIR")).join("data/sim2d/sim2d.clf");
    let mut cfg = Config::default();
    cfg.filter.resample_below = 1.0;
    let prepared = prepare_log(&log, &cfg, 10).unwrap();
    let mut always = prepared.new_filter(50);
    for s in &prepared.steps {
        assert!(
            always.step(&s.input()).resampled,
            "the release resamples every step"
        );
        assert!(always.log_weights().iter().all(|&w| w == 0.0));
    }
    cfg.filter.resample_below = 0.25;
    // A laser model 30× wider than the default flattens the weights, as an
    // ambiguous scene (a corridor, open space) does.
    cfg.laser.variance *= 30.0;
    let prepared = prepare_log(&log, &cfg, 60).unwrap();
    let mut f = prepared.new_filter(50);
    let (mut kept, mut redrawn) = (Vec::new(), Vec::new());
    for s in &prepared.steps {
        let stats = f.step(&s.input());
        let w = f.log_weights();
        assert_eq!(w.len(), 50);
        if stats.resampled {
            assert!(w.iter().all(|&w| w == 0.0), "a redrawn set starts equal");
            redrawn.push(stats.distinct_parents);
        } else {
            // The particles carry their weights, the best at 0.
            let top = w.iter().copied().fold(f64::NEG_INFINITY, f64::max);
            assert_eq!(top, 0.0);
            assert!(w.iter().any(|&w| w < -1e-3), "{w:?}");
            kept.push(stats.distinct_parents);
        }
    }
    // Both happen on the simulated loop, and a step that keeps the set
    // continues (nearly) every lineage where a redraw continues far fewer.
    assert!(
        !kept.is_empty() && !redrawn.is_empty(),
        "kept {kept:?}, redrawn {redrawn:?}"
    );
    let mean = |v: &[usize]| v.iter().sum::<usize>() as f64 / v.len() as f64;
    assert!(mean(&kept) > 40.0, "{kept:?}");
    assert!(
        mean(&kept) > mean(&redrawn) + 10.0,
        "{kept:?} vs {redrawn:?}"
    );
}
