//! `dpslam bench ...`: benchmarks. SHARED FILE: the benchmark-suite engineer
//! owns the `Accuracy` and `Scaling` variants, the GPU engineer owns the
//! `Likelihood` variant. Edit only your own variant, its args struct and its
//! dispatch arm; keep the rest.

use clap::Subcommand;

#[derive(Subcommand, Debug)]
pub enum BenchCommand {
    /// Map every dataset with a reference, score it, write docs/RESULTS.md.
    Accuracy(AccuracyArgs),
    /// Time per filter iteration against particle count (one JSON object).
    Scaling(ScalingArgs),
    /// Scan-likelihood throughput on the CPU and GPU paths, and their difference (one JSON object).
    Likelihood(LikelihoodArgs),
}

pub fn run(c: BenchCommand) -> dpslam::Result<()> {
    match c {
        BenchCommand::Accuracy(a) => run_accuracy(a),
        BenchCommand::Scaling(a) => run_scaling(a),
        BenchCommand::Likelihood(a) => run_likelihood(a),
    }
}

/// Options of `dpslam bench likelihood`.
#[derive(clap::Args, Debug)]
pub struct LikelihoodArgs {
    /// Backends to time
    #[arg(long, value_enum, default_value = "both")]
    pub backend: dpslam::backend::bench::BenchBackends,
    /// 2-D (hall mapped at 35 cells/m) or 3-D (voxel hall, 0.2 m voxels)
    #[arg(long, default_value_t = 2)]
    pub dim: usize,
    /// Candidate poses scored per iteration (the filter's particles × samples) [default: 500 in 2-D, 200 in 3-D]
    #[arg(long)]
    pub particles: Option<usize>,
    /// Beams per scan [default: 181 in 2-D, 2000 in 3-D]
    #[arg(long)]
    pub beams: Option<usize>,
    /// Time each backend for at least this long, s
    #[arg(long, default_value_t = 2.0)]
    pub min_time: f64,
    /// Seed of the map-building filter and of the candidates
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Arithmetic of the GPU shader (auto: f64 where the adapter has it)
    #[arg(long, value_enum, default_value_t = dpslam::backend::GpuPrecision::Auto)]
    pub precision: dpslam::backend::GpuPrecision,
}

fn run_likelihood(a: LikelihoodArgs) -> dpslam::Result<()> {
    let three = a.dim == 3;
    let spec = dpslam::backend::bench::LikelihoodBenchSpec {
        dim: a.dim,
        candidates: a.particles.unwrap_or(if three { 200 } else { 500 }),
        beams: a.beams.unwrap_or(if three { 2000 } else { 181 }),
        backends: a.backend,
        min_time_s: a.min_time,
        seed: a.seed,
        precision: a.precision,
    };
    let report = dpslam::backend::bench::bench_likelihood(&spec)?;
    println!(
        "{}",
        serde_json::to_string(&report).map_err(|e| dpslam::Error::Invalid(e.to_string()))?
    );
    Ok(())
}

/// Options of `dpslam bench accuracy`.
#[derive(clap::Args, Debug)]
pub struct AccuracyArgs {
    /// Short subset (the simulator and mit-csail, first 300 scans each): a smoke test
    #[arg(long)]
    pub quick: bool,
    /// Folder for the per-dataset runs [default: target/bench-accuracy]
    #[arg(long)]
    pub out: Option<std::path::PathBuf>,
    /// Particles [default: 50, or the config file's]
    #[arg(long)]
    pub particles: Option<usize>,
    /// Configuration file (TOML; see docs/CONFIG.md)
    #[arg(long)]
    pub config: Option<std::path::PathBuf>,
    /// Folder for RESULTS.md and results/*.png [default: docs]
    #[arg(long)]
    pub docs: Option<std::path::PathBuf>,
    /// Shared datasets folder (holds carmen/) [default: ../shared/datasets]
    #[arg(long)]
    pub datasets: Option<std::path::PathBuf>,
    /// Run only these datasets (comma-separated names, e.g. sim2d,mit-csail)
    #[arg(long, value_delimiter = ',')]
    pub only: Vec<String>,
    /// Seed of the odometry noise added to the corrected logs
    #[arg(long, default_value_t = dpslam::bench::accuracy::DEFAULT_NOISE_SEED)]
    pub noise_seed: u64,
    /// Worker threads (0 = all cores)
    #[arg(long)]
    pub threads: Option<usize>,
    /// Skip the particle-scaling measurement (100-3000 particles on the
    /// simulated log, ~3 min on 2 cores) that follows the datasets
    #[arg(long)]
    pub no_scaling: bool,
    /// Learn each log's motion model first (N EM rounds, as `map2d
    /// --learn-motion N`; the wall time includes them)
    #[arg(long, default_value_t = 0, value_name = "N")]
    pub learn_motion: usize,
}

/// A benchmark's configuration: as `map2d`'s, without a `--seed` flag (the
/// seed is the config file's or the default).
fn bench_config(
    config: Option<std::path::PathBuf>,
    threads: Option<usize>,
    particles: Option<usize>,
) -> dpslam::Result<dpslam::config::Config> {
    let run = super::map2d::RunArgs {
        seed: None,
        config,
        threads,
    };
    super::map2d::build_config(&run, particles)
}

fn run_accuracy(a: AccuracyArgs) -> dpslam::Result<()> {
    use dpslam::bench::accuracy::{AccuracyOptions, run_accuracy};
    let cfg = bench_config(a.config.clone(), a.threads, a.particles)?;
    let mut opts = AccuracyOptions::new(cfg);
    opts.quick = a.quick;
    opts.only = a.only;
    opts.noise_seed = a.noise_seed;
    opts.learn_motion = a.learn_motion;
    opts.command = std::env::args().collect::<Vec<_>>().join(" ");
    // Each dataset in a `dpslam map2d` process of its own: per-run peak memory.
    opts.mapper = std::env::current_exe().ok();
    if a.no_scaling || a.quick {
        opts.scaling = None;
    }
    if let Some(o) = a.out {
        opts.out = o;
    }
    if let Some(d) = a.docs {
        opts.docs = d;
    }
    if let Some(d) = a.datasets {
        opts.datasets = d;
    }
    let r = run_accuracy(&opts)?;
    println!(
        "bench accuracy: {} datasets run, {} not run, {:.0} s -> {}",
        r.runs.len(),
        r.skipped.len(),
        r.total_wall_s,
        opts.docs.join("RESULTS.md").display()
    );
    Ok(())
}

/// Options of `dpslam bench scaling`.
#[derive(clap::Args, Debug)]
pub struct ScalingArgs {
    /// Particle counts to time (comma-separated)
    #[arg(long, value_delimiter = ',', default_value = "100,300,1000,3000")]
    pub particles: Vec<usize>,
    /// Processed scans that build the map before timing
    #[arg(long, default_value_t = 20)]
    pub scans: usize,
    /// Steps timed per particle count
    #[arg(long, default_value_t = 5)]
    pub steps: usize,
    /// 2-D log [default: the shipped simulated loop]
    #[arg(long)]
    pub log: Option<std::path::PathBuf>,
    /// Where to write the plot (time-vs-particles.png) [default: docs/results]
    #[arg(long)]
    pub plot_dir: Option<std::path::PathBuf>,
    /// Configuration file (TOML; see docs/CONFIG.md)
    #[arg(long)]
    pub config: Option<std::path::PathBuf>,
    /// Worker threads (0 = all cores)
    #[arg(long)]
    pub threads: Option<usize>,
}

fn run_scaling(a: ScalingArgs) -> dpslam::Result<()> {
    use dpslam::bench::scaling::{ScalingOptions, run_scaling, write_scaling_plot};
    let cfg = bench_config(a.config.clone(), a.threads, None)?;
    let opts = ScalingOptions {
        log: a.log.unwrap_or_else(|| super::map2d::DEFAULT_LOG.into()),
        particles: a.particles,
        warmup_scans: a.scans,
        timed_steps: a.steps,
        cfg,
    };
    let report = run_scaling(&opts)?;
    let dir = a
        .plot_dir
        .unwrap_or_else(|| concat!(env!("CARGO_MANIFEST_DIR"), "/docs/results").into());
    std::fs::create_dir_all(&dir).map_err(|e| dpslam::Error::io(&dir, e))?;
    write_scaling_plot(&report, &dir.join("time-vs-particles.png"))?;
    println!(
        "{}",
        serde_json::to_string(&report).map_err(|e| dpslam::Error::Invalid(e.to_string()))?
    );
    Ok(())
}
