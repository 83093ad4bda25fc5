//! Likelihood benchmark and test fixtures shared by `dpslam bench likelihood`
//! and `tests/gpu.rs`.
//!
//! A fixture is a real DP-map, not a hand-made grid: a synthetic box world
//! (2-D: a 30 m × 12 m hall; 3-D: a 20 m × 12 m × 4 m hall, both with
//! obstacles) is scanned from a short trajectory and mapped by the particle
//! filter itself, so the map has several ancestry nodes whose particles see
//! different cells. Candidates are the particles' poses, jittered, plus some
//! moved 6 m ahead, where their beams leave the mapped area; the hall is
//! longer than the laser's range, so some beams are "no return".

use dpslam::config::{FilterConfig, LaserConfig};
use dpslam::filter::{ParticleFilter, StepInput};
use dpslam::geometry::{Pose, Pose2, Pose3, pose2, xyt};
use dpslam::laser_model::{LaserModel, Trace};
use dpslam::motion_model::MotionModel;
use dpslam::proposal::Proposal;
use dpslam::scan::{Beam, Scan};
use dpslam::scorer::{BeamSubset, Candidate, CpuScorer, ScoreContext, Scorer};
use dpslam::{Error, Result};
use nalgebra::{Translation3, UnitQuaternion, Vector3};
use rand::SeedableRng;
use rand_distr::{Distribution, StandardNormal};
use rand_pcg::Pcg64;
use serde::Serialize;
use std::time::Instant;

/// An axis-aligned box world: the inside of a hall centred on the origin
/// plus solid boxes, lengths in metres (map frame).
#[derive(Debug, Clone, PartialEq)]
pub struct BoxWorld<const D: usize> {
    /// Half extents of the hall.
    pub half: [f64; D],
    /// Solid obstacles as `(min corner, max corner)`.
    pub boxes: Vec<([f64; D], [f64; D])>,
}

impl<const D: usize> BoxWorld<D> {
    /// Distance (m) from `o` (inside the hall) along unit `d` to the first surface.
    pub fn cast(&self, o: [f64; D], d: [f64; D]) -> f64 {
        let mut best = f64::INFINITY;
        for i in 0..D {
            if d[i] != 0.0 {
                let wall = if d[i] > 0.0 {
                    self.half[i]
                } else {
                    -self.half[i]
                };
                best = best.min((wall - o[i]) / d[i]);
            }
        }
        for (lo, hi) in &self.boxes {
            // Slab test: the largest entry and the smallest exit over the axes.
            let (mut t0, mut t1) = (0.0f64, f64::INFINITY);
            for i in 0..D {
                if d[i] == 0.0 {
                    if o[i] < lo[i] || o[i] > hi[i] {
                        t1 = -1.0;
                    }
                    continue;
                }
                let (a, b) = ((lo[i] - o[i]) / d[i], (hi[i] - o[i]) / d[i]);
                t0 = t0.max(a.min(b));
                t1 = t1.min(a.max(b));
            }
            if t0 <= t1 && t0 > 0.0 {
                best = best.min(t0);
            }
        }
        best
    }
}

/// Poses the fixtures can build: moves, jitter and a noise-only motion model.
pub trait FixturePose<const D: usize>: Pose<D> {
    /// This pose moved by `v` (m, map frame).
    fn moved(&self, v: [f64; D]) -> Self;
    /// This pose with Gaussian noise of `sxy` m per axis and `sa` rad.
    fn jittered(&self, rng: &mut Pcg64, sxy: f64, sa: f64) -> Self;
    /// A motion model: odometry composed with jitter of `sxy` m and `sa` rad.
    fn jitter_model(sxy: f64, sa: f64) -> Box<dyn MotionModel<D, Self>>;
}

fn normal(rng: &mut Pcg64) -> f64 {
    StandardNormal.sample(rng)
}

/// Odometry composed with isotropic Gaussian noise.
struct Jitter {
    sxy: f64,
    sa: f64,
}

impl MotionModel<2, Pose2> for Jitter {
    fn sample(&self, prev: &Pose2, delta: &Pose2, rng: &mut Pcg64) -> Pose2 {
        (prev * delta).jittered(rng, self.sxy, self.sa)
    }
}

impl MotionModel<3, Pose3> for Jitter {
    fn sample(&self, prev: &Pose3, delta: &Pose3, rng: &mut Pcg64) -> Pose3 {
        (prev * delta).jittered(rng, self.sxy, self.sa)
    }
}

impl FixturePose<2> for Pose2 {
    fn moved(&self, v: [f64; 2]) -> Self {
        let (x, y, t) = xyt(self);
        pose2(x + v[0], y + v[1], t)
    }
    fn jittered(&self, rng: &mut Pcg64, sxy: f64, sa: f64) -> Self {
        let (x, y, t) = xyt(self);
        pose2(
            x + sxy * normal(rng),
            y + sxy * normal(rng),
            t + sa * normal(rng),
        )
    }
    fn jitter_model(sxy: f64, sa: f64) -> Box<dyn MotionModel<2, Self>> {
        Box::new(Jitter { sxy, sa })
    }
}

impl FixturePose<3> for Pose3 {
    fn moved(&self, v: [f64; 3]) -> Self {
        Translation3::new(v[0], v[1], v[2]) * self
    }
    fn jittered(&self, rng: &mut Pcg64, sxy: f64, sa: f64) -> Self {
        let t = Translation3::new(
            sxy * normal(rng),
            sxy * normal(rng),
            0.3 * sxy * normal(rng),
        );
        let r = UnitQuaternion::from_scaled_axis(Vector3::new(
            0.3 * sa * normal(rng),
            0.3 * sa * normal(rng),
            sa * normal(rng),
        ));
        let mut p = t * self;
        p.rotation = r * p.rotation;
        p
    }
    fn jitter_model(sxy: f64, sa: f64) -> Box<dyn MotionModel<3, Self>> {
        Box::new(Jitter { sxy, sa })
    }
}

/// Size of a fixture.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FixtureSpec {
    /// Particles of the filter that builds the map (distinct map views).
    pub particles: usize,
    /// Filter steps after the first scan (more steps: more ancestry nodes).
    pub steps: usize,
    /// Candidates to score.
    pub candidates: usize,
    /// Beams per scan.
    pub beams: usize,
    /// Seed of the filter and the jitter.
    pub seed: u64,
}

/// A mapped world, a scan and candidates to score it for.
pub struct Fixture<const D: usize, P: Pose<D>> {
    /// The filter that built the map (its map, numbering and laser model).
    pub filter: ParticleFilter<D, P>,
    /// The scan to score: taken at the next pose of the trajectory.
    pub scan: Scan<D, P>,
    /// Candidates, over all particles (so over several map views).
    pub candidates: Vec<Candidate<P>>,
}

impl<const D: usize, P: Pose<D>> Fixture<D, P> {
    /// The scoring context over the filter's map.
    pub fn context(&self) -> ScoreContext<'_, D, P> {
        ScoreContext {
            map: self.filter.map(),
            numbering: self.filter.numbering(),
            laser: self.filter.laser(),
            scan: &self.scan,
        }
    }
}

fn scan_at<const D: usize, P: Pose<D>>(
    world: &BoxWorld<D>,
    robot: &P,
    sensor: P,
    dirs: &[[f64; D]],
    max_range: f64,
) -> Scan<D, P> {
    let s = robot.compose(&sensor);
    let o = s.translation();
    let beams = dirs
        .iter()
        .map(|&dir| {
            let r = world.cast(o, s.rotate(dir));
            let no_return = r > max_range;
            Beam {
                dir,
                range: if no_return { max_range } else { r },
                no_return,
            }
        })
        .collect();
    Scan { sensor, beams }
}

#[allow(clippy::too_many_arguments)]
fn build<const D: usize, P: FixturePose<D>>(
    world: &BoxWorld<D>,
    laser: LaserModel,
    dirs: &[[f64; D]],
    sensor: P,
    start: P,
    stride: [f64; D],
    samples: usize,
    spec: &FixtureSpec,
) -> Fixture<D, P> {
    let cfg = FilterConfig {
        particles: spec.particles.max(1),
        samples_per_particle: samples,
        ..FilterConfig::default()
    };
    let max_range = laser.max_range;
    let first = scan_at(world, &start, sensor, dirs, max_range);
    let motion = P::jitter_model(0.03, 0.01);
    let mut filter = ParticleFilter::new(cfg, laser, motion, spec.seed, start, &first, 0);
    let mut truth = start;
    let delta = P::identity().moved(stride);
    for i in 0..spec.steps {
        truth = truth.moved(stride);
        let scan = scan_at(world, &truth, sensor, dirs, max_range);
        if i + 1 < spec.steps {
            filter.step(&StepInput::motion(delta, &scan, i as u32 + 1));
            continue;
        }
        // The last step keeps the first sample of every particle instead
        // of resampling: however sharp the likelihood (resampling would
        // copy the best sample into every particle, one node), the
        // candidates then see several views of the map.
        let drawn = filter.predict(&delta, &Proposal::Motion, &scan);
        let weights = filter.weigh(&drawn.samples, &scan);
        let chosen: Vec<usize> = (0..filter.particles().len()).map(|j| j * samples).collect();
        filter.update(
            &drawn.samples,
            &weights.scores,
            &chosen,
            &scan,
            i as u32 + 1,
        );
        filter.prune();
    }
    let next = truth.moved(stride);
    let scan = scan_at(world, &next, sensor, dirs, max_range);
    let mut rng = Pcg64::seed_from_u64(spec.seed ^ 0x5eed);
    let particles = filter.particles().to_vec();
    let mut far = [0.0; D];
    far[0] = 6.0;
    let candidates = (0..spec.candidates)
        .map(|i| {
            let p = particles[i % particles.len()];
            let pose = p.pose.moved(stride).jittered(&mut rng, 0.05, 0.02);
            let pose = if i % 7 == 6 { pose.moved(far) } else { pose };
            Candidate { node: p.node, pose }
        })
        .collect();
    Fixture {
        filter,
        scan,
        candidates,
    }
}

/// The 2-D fixture: 35 cells/m, 10 m range, `spec.beams` beams over 360°,
/// the laser 0.2 m ahead of the robot.
pub fn fixture2d(spec: &FixtureSpec) -> Fixture<2, Pose2> {
    let world = BoxWorld {
        half: [15.0, 6.0],
        boxes: vec![
            ([-1.0, 2.0], [1.0, 3.0]),
            ([3.0, -4.0], [3.6, -1.5]),
            ([-7.0, -2.0], [-6.5, 2.5]),
            ([6.0, 1.0], [8.0, 1.3]),
        ],
    };
    let laser = LaserModel::new(&LaserConfig::default(), 1.0 / 35.0, 10.0);
    let n = spec.beams.max(1);
    let dirs: Vec<[f64; 2]> = (0..n)
        .map(|i| {
            let a = -std::f64::consts::PI + std::f64::consts::TAU * (i as f64 + 0.5) / n as f64;
            [a.cos(), a.sin()]
        })
        .collect();
    build(
        &world,
        laser,
        &dirs,
        pose2(0.2, 0.0, 0.0),
        pose2(-4.0, -0.3, 0.05),
        [0.25, 0.02],
        5,
        spec,
    )
}

/// The 3-D fixture: 0.2 m voxels, 12 m range, σ = 0.2 m, `spec.beams` beams
/// in 16 rings from −25° to +15° elevation, the sensor 0.5 m above the robot.
pub fn fixture3d(spec: &FixtureSpec) -> Fixture<3, Pose3> {
    let world = BoxWorld {
        half: [10.0, 6.0, 2.0],
        boxes: vec![
            ([-1.0, 2.0, -2.0], [1.0, 3.0, 0.5]),
            ([3.0, -4.0, -2.0], [3.6, -1.5, 2.0]),
            ([-6.0, -2.0, -2.0], [-5.5, 2.5, -0.5]),
            ([2.0, 1.0, 1.2], [5.0, 3.0, 1.6]),
        ],
    };
    let cfg = LaserConfig {
        variance: 0.04,
        ..LaserConfig::default()
    };
    let laser = LaserModel::new(&cfg, 0.2, 12.0);
    let n = spec.beams.max(1);
    let rings = 16.min(n);
    let per_ring = n.div_ceil(rings);
    let dirs: Vec<[f64; 3]> = (0..n)
        .map(|i| {
            let (ring, j) = (i % rings, i / rings);
            let el = (-25.0 + 40.0 * ring as f64 / (rings.max(2) - 1) as f64).to_radians();
            let az = std::f64::consts::TAU * (j as f64 + 0.37 * ring as f64 / rings as f64)
                / per_ring as f64;
            [el.cos() * az.cos(), el.cos() * az.sin(), el.sin()]
        })
        .collect();
    let sensor = Pose3::translation(0.0, 0.0, 0.5);
    let start = Pose3::new(Vector3::new(-4.0, -0.3, -1.0), Vector3::new(0.0, 0.0, 0.05));
    build(
        &world,
        laser,
        &dirs,
        sensor,
        start,
        [0.3, 0.02, 0.0],
        4,
        spec,
    )
}

/// What was timed on one backend.
#[derive(Debug, Clone, Serialize)]
pub struct PathTiming {
    /// Backend ("cpu" or "gpu").
    pub backend: String,
    /// Device: CPU threads, or the GPU adapter.
    pub device: String,
    /// Timed iterations (one full-trace score of every candidate, all beams).
    pub iterations: usize,
    /// Mean time per iteration, ms.
    pub ms_per_iteration: f64,
    /// Beams × candidates scored per second.
    pub beam_candidates_per_s: f64,
    /// First call after a map change (GPU: flattening and uploading the map), ms.
    pub first_call_ms: f64,
    /// Bytes sent to the device per iteration, map excluded (GPU only).
    pub upload_bytes_per_iteration: Option<u64>,
    /// Bytes of the first, full map upload: the flattened map with room to
    /// grow (GPU only).
    pub map_upload_bytes: Option<u64>,
    /// Bytes of the map without room or garbage (GPU only).
    pub map_packed_bytes: Option<u64>,
    /// Map bytes uploaded by the first call after one more filter step (a
    /// map edit), when only the changed bricks are sent (GPU only).
    pub map_bytes_after_step: Option<u64>,
    /// Bytes read back per iteration (GPU only).
    pub readback_bytes_per_iteration: Option<u64>,
    /// Shader arithmetic, "f32" or "f64" (GPU only).
    pub precision: Option<String>,
}

/// The `bench likelihood` report.
#[derive(Debug, Clone, Serialize)]
pub struct LikelihoodBench {
    /// 2 or 3.
    pub dim: usize,
    /// Candidates per iteration.
    pub candidates: usize,
    /// Beams per candidate.
    pub beams: usize,
    /// Entries in the DP-map.
    pub map_entries: usize,
    /// Live ancestry nodes (distinct map views ≤ this).
    pub tree_nodes: usize,
    /// Timings, one per backend run.
    pub paths: Vec<PathTiming>,
    /// Largest |GPU − CPU| over the candidates' log-likelihoods (both run).
    pub max_abs_diff: Option<f64>,
    /// Largest |GPU − CPU| / max(1, |CPU|).
    pub max_rel_diff: Option<f64>,
    /// GPU over CPU throughput (both run).
    pub gpu_speedup: Option<f64>,
}

/// Which backends `bench likelihood` times.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum BenchBackends {
    /// The CPU reference only.
    Cpu,
    /// The GPU path only.
    Gpu,
    /// Both, with their difference.
    Both,
}

/// Options of the likelihood benchmark.
#[derive(Debug, Clone, Copy)]
pub struct LikelihoodBenchSpec {
    /// 2 or 3.
    pub dim: usize,
    /// Candidates per iteration.
    pub candidates: usize,
    /// Beams per scan.
    pub beams: usize,
    /// Backends to time.
    pub backends: BenchBackends,
    /// Keep iterating a backend until this much time passed (s), at least 2 iterations.
    pub min_time_s: f64,
    /// Seed.
    pub seed: u64,
    /// Arithmetic of the GPU shader.
    pub precision: dpslam::backend::GpuPrecision,
}

fn time_path<const D: usize, P: Pose<D>>(
    scorer: &dyn Scorer<D, P>,
    fx: &Fixture<D, P>,
    min_time_s: f64,
    before_first: &dyn Fn(),
) -> (Vec<f64>, f64, usize, f64) {
    let ctx = fx.context();
    before_first();
    let t = Instant::now();
    let scores = scorer.score(&ctx, &fx.candidates, BeamSubset::ALL, Trace::Full);
    let first = t.elapsed().as_secs_f64();
    let t = Instant::now();
    let mut n = 0;
    while n < 2 || t.elapsed().as_secs_f64() < min_time_s {
        std::hint::black_box(scorer.score(&ctx, &fx.candidates, BeamSubset::ALL, Trace::Full));
        n += 1;
    }
    (scores, first, n, t.elapsed().as_secs_f64() / n as f64)
}

fn run_bench<const D: usize, P: FixturePose<D>>(
    fx: &mut Fixture<D, P>,
    spec: &LikelihoodBenchSpec,
) -> Result<LikelihoodBench> {
    let map_entries = fx.filter.map().entry_count();
    let tree_nodes = fx.filter.tree().len();
    let work = (fx.candidates.len() * fx.scan.beams.len()) as f64;
    let mut paths = Vec::new();
    let mut results: Vec<Vec<f64>> = Vec::new();
    if matches!(spec.backends, BenchBackends::Cpu | BenchBackends::Both) {
        let cpu = CpuScorer::<D>::new();
        let (s, first, n, per) = time_path::<D, P>(&cpu, fx, spec.min_time_s, &|| {});
        results.push(s);
        paths.push(PathTiming {
            backend: "cpu".into(),
            device: format!("{} rayon threads", rayon::current_num_threads()),
            iterations: n,
            ms_per_iteration: per * 1e3,
            beam_candidates_per_s: work / per,
            first_call_ms: first * 1e3,
            upload_bytes_per_iteration: None,
            map_upload_bytes: None,
            map_packed_bytes: None,
            map_bytes_after_step: None,
            readback_bytes_per_iteration: None,
            precision: None,
        });
    }
    if matches!(spec.backends, BenchBackends::Gpu | BenchBackends::Both) {
        paths.push(gpu_path(fx, spec, work, &mut results)?);
    }
    let (max_abs_diff, max_rel_diff) = match results.as_slice() {
        [a, b] => {
            let abs = a
                .iter()
                .zip(b)
                .map(|(x, y)| (x - y).abs())
                .fold(0.0, f64::max);
            let rel = a
                .iter()
                .zip(b)
                .map(|(x, y)| (x - y).abs() / x.abs().max(1.0))
                .fold(0.0, f64::max);
            (Some(abs), Some(rel))
        }
        _ => (None, None),
    };
    let gpu_speedup = match paths.as_slice() {
        [c, g] => Some(g.beam_candidates_per_s / c.beam_candidates_per_s),
        _ => None,
    };
    Ok(LikelihoodBench {
        dim: D,
        candidates: fx.candidates.len(),
        beams: fx.scan.beams.len(),
        map_entries,
        tree_nodes,
        paths,
        max_abs_diff,
        max_rel_diff,
        gpu_speedup,
    })
}

/// The GPU path; after timing, steps the fixture's filter once (so `fx`
/// changes) to measure the incremental map upload that follows a map edit.
#[cfg(feature = "gpu")]
fn gpu_path<const D: usize, P: FixturePose<D>>(
    fx: &mut Fixture<D, P>,
    spec: &LikelihoodBenchSpec,
    work: f64,
    results: &mut Vec<Vec<f64>>,
) -> Result<PathTiming> {
    let gpu = dpslam::gpu::GpuScorer::<D>::with_options(dpslam::gpu::GpuOptions {
        precision: spec.precision,
        max_binding: max_binding_from_env()?,
    })?;
    // Through `try_score` once: a device failure must fail the bench, not
    // silently time the CPU fallback.
    gpu.try_score(&fx.context(), &fx.candidates, BeamSubset::ALL, Trace::Full)?;
    let full = gpu.last_call();
    let (s, first, n, per) = time_path::<D, P>(&gpu, fx, spec.min_time_s, &|| gpu.invalidate());
    let last = gpu.last_call();
    results.push(s);
    let scan = fx.scan.clone();
    fx.filter
        .step(&StepInput::motion(P::identity(), &scan, u32::MAX));
    let particles = fx.filter.particles().to_vec();
    for (i, c) in fx.candidates.iter_mut().enumerate() {
        c.node = particles[i % particles.len()].node;
    }
    gpu.try_score(&fx.context(), &fx.candidates, BeamSubset::ALL, Trace::Full)?;
    let after = gpu.last_call();
    Ok(PathTiming {
        backend: "gpu".into(),
        device: gpu.adapter().to_string(),
        iterations: n,
        ms_per_iteration: per * 1e3,
        beam_candidates_per_s: work / per,
        first_call_ms: first * 1e3,
        upload_bytes_per_iteration: Some(last.upload_bytes),
        map_upload_bytes: Some(full.map_bytes),
        map_packed_bytes: Some(full.map_packed_bytes),
        map_bytes_after_step: Some(after.map_bytes),
        readback_bytes_per_iteration: Some(last.readback_bytes),
        precision: Some(gpu.precision().to_string()),
    })
}

#[cfg(not(feature = "gpu"))]
fn gpu_path<const D: usize, P: FixturePose<D>>(
    _fx: &mut Fixture<D, P>,
    _spec: &LikelihoodBenchSpec,
    _work: f64,
    _results: &mut Vec<Vec<f64>>,
) -> Result<PathTiming> {
    dpslam::backend::make_scorer::<D, P>(dpslam::backend::Backend::Gpu, &Default::default())?;
    Err(Error::Gpu("the GPU path is not compiled in".into()))
}

/// The limit in `DPSLAM_GPU_MAX_BINDING` (bytes), if set: the likelihood
/// bench's way to time maps split over several bindings.
#[cfg(feature = "gpu")]
fn max_binding_from_env() -> Result<Option<u64>> {
    match std::env::var("DPSLAM_GPU_MAX_BINDING") {
        Err(_) => Ok(None),
        Ok(v) => v.trim().parse::<u64>().map(Some).map_err(|_| {
            Error::Gpu(format!(
                "DPSLAM_GPU_MAX_BINDING is {v:?}: expected a size in bytes"
            ))
        }),
    }
}

/// Builds the fixture for `spec.dim` (4 filter particles, 3 steps) and times
/// one full-trace, all-beam scoring of every candidate per iteration on the
/// chosen backends. The GPU's map bindings follow `DPSLAM_GPU_MAX_BINDING`.
pub fn bench_likelihood(spec: &LikelihoodBenchSpec) -> Result<LikelihoodBench> {
    let fs = FixtureSpec {
        particles: 4,
        steps: 3,
        candidates: spec.candidates.max(1),
        beams: spec.beams.max(1),
        seed: spec.seed,
    };
    match spec.dim {
        2 => run_bench(&mut fixture2d(&fs), spec),
        3 => run_bench(&mut fixture3d(&fs), spec),
        d => Err(Error::Config(format!("--dim must be 2 or 3, not {d}"))),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn box_world_casts_to_walls_and_boxes() {
        let w = BoxWorld {
            half: [5.0, 2.0],
            boxes: vec![([1.0, -0.5], [2.0, 0.5])],
        };
        assert!((w.cast([0.0, 0.0], [1.0, 0.0]) - 1.0).abs() < 1e-12);
        assert!((w.cast([0.0, 0.0], [-1.0, 0.0]) - 5.0).abs() < 1e-12);
        assert!((w.cast([0.0, 1.0], [1.0, 0.0]) - 5.0).abs() < 1e-12);
        let s = std::f64::consts::FRAC_1_SQRT_2;
        assert!((w.cast([0.0, 0.0], [s, s]) - 2.0 / s).abs() < 1e-9);
    }

    #[test]
    fn fixture_has_several_views_no_returns_and_scores_on_the_cpu() {
        let fx = fixture2d(&FixtureSpec {
            particles: 4,
            steps: 2,
            candidates: 14,
            beams: 60,
            seed: 3,
        });
        let nodes: std::collections::BTreeSet<_> = fx.candidates.iter().map(|c| c.node).collect();
        assert!(nodes.len() > 1, "all candidates share one view");
        assert!(fx.scan.beams.iter().any(|b| b.no_return));
        assert!(fx.scan.beams.iter().any(|b| !b.no_return));
        let s = CpuScorer::<2>::new().score(
            &fx.context(),
            &fx.candidates,
            BeamSubset::ALL,
            Trace::Full,
        );
        assert!(s.iter().all(|v| v.is_finite() && *v <= 0.0));
    }
}
