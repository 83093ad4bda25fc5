//! Criterion benchmarks of one filter iteration and its parts, at 100, 300,
//! 1000 and 3000 particles, on the shipped simulated loop.
//!
//! For each particle count a filter is warmed up on the first processed scans
//! of `data/sim2d/sim2d.clf` (so the map and tree are not trivially small);
//! then, on the next scan:
//! - `likelihood`: the full-trace score of that scan for every particle (one
//!   sample each; the filter draws `samples_per_particle` and culls);
//! - `map_update`: every particle's observation added under a new child node
//!   (as the filter's update, on clones of its map and tree);
//! - `ancestry`: prune and collapse the tree after a multinomial resampling,
//!   mirror the edits in the map, renumber;
//! - `full_step`: `ParticleFilter::step`, consecutive scans of the log.
//!
//! Run: `cargo bench --bench iteration`. `DPSLAM_BENCH_PARTICLES=100,300`
//! limits the counts (3000 particles cost tens of seconds of set-up).

use criterion::{BatchSize, BenchmarkId, Criterion, criterion_group, criterion_main};
use dpslam::config::Config;
use dpslam::filter::{ParticleFilter, stream};
use dpslam::geometry::Pose2;
use dpslam::scorer::CpuScorer;
use dpslam_bench::rig::{
    PreparedLog, maintain, moved_samples, prepare_log, score_particles, update_map,
};
use rand::RngExt;
use std::hint::black_box;
use std::path::Path;
use std::time::{Duration, Instant};

/// Processed scans that build the map before anything is timed.
const WARMUP: usize = 5;
/// Scans available to the full-step benchmark before the filter is rebuilt.
const TIMED_SCANS: usize = 30;

fn particle_counts() -> Vec<usize> {
    std::env::var("DPSLAM_BENCH_PARTICLES")
        .ok()
        .map(|s| s.split(',').filter_map(|x| x.trim().parse().ok()).collect())
        .filter(|v: &Vec<usize>| !v.is_empty())
        .unwrap_or_else(|| vec![100, 300, 1000, 3000])
}

fn prepared() -> (PreparedLog, Config) {
    let cfg = Config::default();
    let log = Path::new(env!("CARGO_MANIFEST_DIR")).join("data/sim2d/sim2d.clf");
    let prepared = prepare_log(&log, &cfg, WARMUP + TIMED_SCANS).expect("the shipped log reads");
    (prepared, cfg)
}

fn warm(log: &PreparedLog, n: usize) -> ParticleFilter<2, Pose2> {
    log.warm_filter(n, WARMUP).expect("enough scans to warm up")
}

fn iteration(c: &mut Criterion) {
    let (log, cfg) = prepared();
    let next = &log.steps[WARMUP];
    let mut group = c.benchmark_group("iteration");
    group
        .sample_size(10)
        .warm_up_time(Duration::from_millis(500))
        .measurement_time(Duration::from_secs(3));
    for n in particle_counts() {
        let filter = warm(&log, n);
        let scorer = CpuScorer::<2>::new();
        group.bench_with_input(BenchmarkId::new("likelihood", n), &n, |b, _| {
            b.iter(|| black_box(score_particles(&filter, &scorer, &next.delta, &next.scan)))
        });

        let everyone: Vec<usize> = (0..n).collect();
        let samples = moved_samples(&filter, &everyone, &next.delta);
        group.bench_with_input(BenchmarkId::new("map_update", n), &n, |b, _| {
            b.iter_batched(
                || filter.clone(),
                |mut f| {
                    update_map(&mut f, &samples, &next.scan);
                    black_box(f)
                },
                BatchSize::PerIteration,
            )
        });

        // Resampled parents: n uniform draws, so about 1 − 1/e of the
        // lineages survive, as with equal weights.
        let mut rng = stream(cfg.seed, 0, n as u64);
        let resampled: Vec<usize> = (0..n)
            .map(|_| (rng.random::<f64>() * n as f64) as usize % n)
            .collect();
        let resampled = moved_samples(&filter, &resampled, &next.delta);
        group.bench_with_input(BenchmarkId::new("ancestry", n), &n, |b, _| {
            b.iter_batched(
                || {
                    let mut f = filter.clone();
                    update_map(&mut f, &resampled, &next.scan);
                    f
                },
                |mut f| {
                    maintain(&mut f);
                    black_box(f)
                },
                BatchSize::PerIteration,
            )
        });
        drop(filter);

        group.bench_with_input(BenchmarkId::new("full_step", n), &n, |b, _| {
            let mut filter = warm(&log, n);
            let mut i = WARMUP;
            b.iter_custom(|iters| {
                let mut total = Duration::ZERO;
                for _ in 0..iters {
                    if i == log.steps.len() {
                        filter = warm(&log, n);
                        i = WARMUP;
                    }
                    let s = &log.steps[i];
                    let t = Instant::now();
                    black_box(filter.step(&s.input()));
                    total += t.elapsed();
                    i += 1;
                }
                total
            })
        });
    }
    group.finish();
}

criterion_group!(benches, iteration);
criterion_main!(benches);
