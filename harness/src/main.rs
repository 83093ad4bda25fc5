//! `dpslam-bench ...`: the development benchmarks (accuracy suite, scaling
//! with particles, likelihood backends). Run from the repository root, after
//! `cargo build --release` (the accuracy suite maps each dataset with the
//! `dpslam` binary that sits next to this one):
//! `cargo run --release -p dpslam-bench -- accuracy`; the 3-D benchmark:
//! `PATH=/path/to/kiss-icp/bin:$PATH cargo run --release -p dpslam-bench -- 3d`.

use clap::{Parser, Subcommand};
use std::path::{Path, PathBuf};

#[global_allocator]
static ALLOC: mimalloc::MiMalloc = mimalloc::MiMalloc;

/// The repository root (this crate's parent folder).
fn repo() -> &'static Path {
    Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/.."))
}

/// dpslam's development benchmarks.
#[derive(Parser, Debug)]
#[command(name = "dpslam-bench", version, about, long_about = None)]
struct Cli {
    #[command(subcommand)]
    command: BenchCommand,
}

fn main() -> std::process::ExitCode {
    match run(Cli::parse().command) {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("dpslam-bench: error: {e}");
            std::process::ExitCode::FAILURE
        }
    }
}

#[derive(Subcommand, Debug)]
enum BenchCommand {
    /// Map every dataset with a reference, score it, write docs/RESULTS.md.
    Accuracy(AccuracyArgs),
    /// Time per filter iteration against particle count (one JSON object).
    Scaling(ScalingArgs),
    /// Scan-likelihood throughput on the CPU and GPU paths, and their difference (one JSON object).
    Likelihood(LikelihoodArgs),
    /// map3d, KISS-ICP (if on the PATH) and odometry on long simulated 3-D
    /// sequences, scored with ATE; writes docs/RESULTS-3D.md.
    #[command(name = "3d")]
    ThreeD(Bench3dArgs),
}

fn run(c: BenchCommand) -> dpslam::Result<()> {
    match c {
        BenchCommand::Accuracy(a) => run_accuracy(a),
        BenchCommand::Scaling(a) => run_scaling(a),
        BenchCommand::Likelihood(a) => run_likelihood(a),
        BenchCommand::ThreeD(a) => run_3d(a),
    }
}

/// Options of `dpslam-bench likelihood`.
#[derive(clap::Args, Debug)]
struct LikelihoodArgs {
    /// Backends to time
    #[arg(long, value_enum, default_value = "both")]
    backend: dpslam_bench::fixtures::BenchBackends,
    /// 2-D (hall mapped at 35 cells/m) or 3-D (voxel hall, 0.2 m voxels)
    #[arg(long, default_value_t = 2)]
    dim: usize,
    /// Candidate poses scored per iteration (the filter's particles × samples) [default: 500 in 2-D, 200 in 3-D]
    #[arg(long)]
    particles: Option<usize>,
    /// Beams per scan [default: 181 in 2-D, 2000 in 3-D]
    #[arg(long)]
    beams: Option<usize>,
    /// Time each backend for at least this long, s
    #[arg(long, default_value_t = 2.0)]
    min_time: f64,
    /// Seed of the map-building filter and of the candidates
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Arithmetic of the GPU shader (auto: f64 where the adapter has it)
    #[arg(long, value_enum, default_value_t = dpslam::backend::GpuPrecision::Auto)]
    precision: dpslam::backend::GpuPrecision,
}

fn run_likelihood(a: LikelihoodArgs) -> dpslam::Result<()> {
    let three = a.dim == 3;
    let spec = dpslam_bench::fixtures::LikelihoodBenchSpec {
        dim: a.dim,
        candidates: a.particles.unwrap_or(if three { 200 } else { 500 }),
        beams: a.beams.unwrap_or(if three { 2000 } else { 181 }),
        backends: a.backend,
        min_time_s: a.min_time,
        seed: a.seed,
        precision: a.precision,
    };
    let report = dpslam_bench::fixtures::bench_likelihood(&spec)?;
    println!(
        "{}",
        serde_json::to_string(&report).map_err(|e| dpslam::Error::Invalid(e.to_string()))?
    );
    Ok(())
}

/// Options of `dpslam-bench accuracy`.
#[derive(clap::Args, Debug)]
struct AccuracyArgs {
    /// Short subset (the simulator and the raw logs mit-csail, aces-raw, fr079-raw, first 300 scans each): a smoke test
    #[arg(long)]
    quick: bool,
    /// Folder for the per-dataset runs [default: target/bench-accuracy]
    #[arg(long)]
    out: Option<std::path::PathBuf>,
    /// Particles [default: 50, or the config file's]
    #[arg(long)]
    particles: Option<usize>,
    /// Configuration file (TOML; see docs/CONFIG.md)
    #[arg(long)]
    config: Option<std::path::PathBuf>,
    /// Folder for RESULTS.md and results/*.png [default: docs]
    #[arg(long)]
    docs: Option<std::path::PathBuf>,
    /// Shared datasets folder (holds carmen/) [default: ../shared/datasets]
    #[arg(long)]
    datasets: Option<std::path::PathBuf>,
    /// Run only these datasets (comma-separated names, e.g. sim2d,mit-csail)
    #[arg(long, value_delimiter = ',')]
    only: Vec<String>,
    /// Seed of the odometry noise added to the corrected logs
    #[arg(long, default_value_t = dpslam_bench::accuracy::DEFAULT_NOISE_SEED)]
    noise_seed: u64,
    /// Worker threads (0 = all cores)
    #[arg(long)]
    threads: Option<usize>,
    /// Skip the particle-scaling measurement (100-3000 particles on the
    /// simulated log, ~3 min on 2 cores) that follows the datasets
    #[arg(long)]
    no_scaling: bool,
    /// Learn each log's motion model first (N EM rounds, as `map2d
    /// --learn-motion N`; the wall time includes them)
    #[arg(long, default_value_t = 0, value_name = "N")]
    learn_motion: usize,
    /// Reuse each dataset's earlier run in --out when it was made with the
    /// same settings (configuration, subset, odometry noise): rescore and
    /// redraw only. The code is not compared: clear --out after changing it
    #[arg(long)]
    reuse_runs: bool,
}

/// A benchmark's configuration: as `map2d`'s, without a `--seed` flag (the
/// seed is the config file's or the default).
fn bench_config(
    config: Option<PathBuf>,
    threads: Option<usize>,
    particles: Option<usize>,
) -> dpslam::Result<dpslam::config::Config> {
    let mut cfg = match &config {
        Some(p) => dpslam::config::Config::from_toml_file(p)?,
        None => dpslam::config::Config::default(),
    };
    if let Some(n) = particles {
        cfg.filter.particles = n;
    }
    if let Some(t) = threads {
        cfg.threads = t;
    }
    cfg.validate()?;
    cfg.install_thread_pool();
    Ok(cfg)
}

/// The `dpslam` binary next to this one (cargo builds both into one folder).
fn mapper() -> dpslam::Result<PathBuf> {
    let exe = std::env::current_exe().map_err(|e| dpslam::Error::Invalid(e.to_string()))?;
    let m = exe.with_file_name(format!("dpslam{}", std::env::consts::EXE_SUFFIX));
    if m.is_file() {
        Ok(m)
    } else {
        Err(dpslam::Error::Invalid(format!(
            "{} not found: build it first (`cargo build --release`)",
            m.display()
        )))
    }
}

fn run_accuracy(a: AccuracyArgs) -> dpslam::Result<()> {
    use dpslam_bench::accuracy::{AccuracyOptions, run_accuracy};
    let cfg = bench_config(a.config.clone(), a.threads, a.particles)?;
    let mut opts = AccuracyOptions::new(cfg);
    opts.quick = a.quick;
    opts.only = a.only;
    opts.noise_seed = a.noise_seed;
    opts.learn_motion = a.learn_motion;
    opts.reuse_runs = a.reuse_runs;
    opts.command = std::env::args().collect::<Vec<_>>().join(" ");
    // Each dataset in a `dpslam map2d` process of its own: per-run peak memory.
    opts.mapper = Some(mapper()?);
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

/// Options of `dpslam-bench scaling`.
#[derive(clap::Args, Debug)]
struct ScalingArgs {
    /// Particle counts to time (comma-separated)
    #[arg(long, value_delimiter = ',', default_value = "100,300,1000,3000")]
    particles: Vec<usize>,
    /// Processed scans that build the map before timing
    #[arg(long, default_value_t = 20)]
    scans: usize,
    /// Steps timed per particle count (the counts take turns, step by step)
    #[arg(long, default_value_t = 10)]
    steps: usize,
    /// 2-D log [default: the shipped simulated loop]
    #[arg(long)]
    log: Option<std::path::PathBuf>,
    /// Where to write the plot (time-vs-particles.png) [default: docs/results]
    #[arg(long)]
    plot_dir: Option<std::path::PathBuf>,
    /// Configuration file (TOML; see docs/CONFIG.md)
    #[arg(long)]
    config: Option<std::path::PathBuf>,
    /// Worker threads (0 = all cores)
    #[arg(long)]
    threads: Option<usize>,
}

fn run_scaling(a: ScalingArgs) -> dpslam::Result<()> {
    use dpslam_bench::scaling::{ScalingOptions, run_scaling, write_scaling_plot};
    let cfg = bench_config(a.config.clone(), a.threads, None)?;
    let opts = ScalingOptions {
        log: a.log.unwrap_or_else(|| repo().join("data/sim2d/sim2d.clf")),
        particles: a.particles,
        warmup_scans: a.scans,
        timed_steps: a.steps,
        cfg,
    };
    let report = run_scaling(&opts)?;
    let dir = a.plot_dir.unwrap_or_else(|| repo().join("docs/results"));
    std::fs::create_dir_all(&dir).map_err(|e| dpslam::Error::io(&dir, e))?;
    write_scaling_plot(&report, &dir.join("time-vs-particles.png"))?;
    println!(
        "{}",
        serde_json::to_string(&report).map_err(|e| dpslam::Error::Invalid(e.to_string()))?
    );
    Ok(())
}

/// Options of `dpslam-bench 3d`.
#[derive(clap::Args, Debug)]
struct Bench3dArgs {
    /// Two tiny sequences (8 sweeps each): a smoke test in seconds
    #[arg(long)]
    quick: bool,
    /// Run only these sequences (comma-separated: building-seed5, corridors)
    #[arg(long, value_delimiter = ',')]
    only: Vec<String>,
    /// Scratch folder for the sequences and runs (reused when present) [default: target/bench-3d]
    #[arg(long)]
    out: Option<PathBuf>,
    /// Folder for RESULTS-3D.md and results-3d/*.png [default: docs]
    #[arg(long)]
    docs: Option<PathBuf>,
    /// Particles of the dpslam runs
    #[arg(long, default_value_t = dpslam_bench::bench3d::DEFAULT_PARTICLES)]
    particles: usize,
    /// Worker threads of the dpslam runs [default: all cores]
    #[arg(long)]
    threads: Option<usize>,
    /// Do not run KISS-ICP even where `kiss_icp_pipeline` is on the PATH
    #[arg(long)]
    no_kiss: bool,
    /// Reuse each method's earlier run on the same sequence and settings
    /// (trajectory and recorded CPU, memory, time): rescore and redraw only
    #[arg(long)]
    reuse_runs: bool,
}

fn run_3d(a: Bench3dArgs) -> dpslam::Result<()> {
    use dpslam_bench::bench3d::{Bench3dOptions, quick_sequences, run_bench3d};
    let mut opts = Bench3dOptions::new(mapper()?);
    if a.quick {
        opts.sequences = quick_sequences();
    }
    if !a.only.is_empty() {
        let known: Vec<String> = opts.sequences.iter().map(|s| s.name.clone()).collect();
        if let Some(bad) = a.only.iter().find(|n| !known.contains(n)) {
            return Err(dpslam::Error::Config(format!(
                "bench 3d: no sequence {bad:?} (have {known:?})"
            )));
        }
        opts.sequences.retain(|s| a.only.contains(&s.name));
    }
    if let Some(o) = a.out {
        opts.out = o;
    }
    if let Some(d) = a.docs {
        opts.docs = d;
    }
    if a.no_kiss {
        opts.kiss_icp = None;
    }
    opts.particles = a.particles;
    opts.reuse_runs = a.reuse_runs;
    opts.threads = a.threads;
    opts.command = std::env::args().collect::<Vec<_>>().join(" ");
    let r = run_bench3d(&opts)?;
    println!(
        "bench 3d: {} sequences, {:.0} s -> {}",
        r.sequences.len(),
        r.total_wall_s,
        opts.docs.join("RESULTS-3D.md").display()
    );
    Ok(())
}
