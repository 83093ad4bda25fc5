//! `dpslam map2d`: 2-D DP-SLAM on a CARMEN or DP-SLAM log.

use dpslam::config::Config;
use std::path::PathBuf;

/// The log mapped when none is given: the simulator's loop shipped in `data/`.
pub const DEFAULT_LOG: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/data/sim2d/sim2d.clf");

#[derive(clap::Args, Debug)]
pub struct Map2dArgs {
    /// CARMEN (.clf/.log) or DP-SLAM log, plain or gzip [default: the shipped simulated loop]
    pub log: Option<PathBuf>,
    /// Output folder (map.png, map.pgm, map.yaml, trajectory.tum, run.json, config.toml)
    #[arg(long, default_value = "out/map2d")]
    pub out: PathBuf,
    /// Particles [default: 50, or the config file's]
    #[arg(long)]
    pub particles: Option<usize>,
    #[command(flatten)]
    pub run: RunArgs,
    /// Where scan likelihoods are computed (gpu needs a build with `--features gpu` and a Vulkan driver; auto falls back to cpu)
    #[arg(long, value_enum, default_value_t = dpslam::backend::Backend::Cpu)]
    pub backend: dpslam::backend::Backend,
    /// Learn the motion model from the log first (dissertation ch. 6): this many EM rounds, each a full SLAM run, before the final run with the learned model (docs/CONFIG.md)
    #[arg(long, default_value_t = 0)]
    pub learn_motion: usize,
    /// Hierarchical SLAM (dissertation ch. 8): windows of the log under a high-level filter ([hierarchy] in the config)
    #[arg(long)]
    pub hierarchical: bool,
}

/// Flags every mapping command shares.
#[derive(clap::Args, Debug)]
pub struct RunArgs {
    /// Random seed [default: 1, or the config file's]
    #[arg(long)]
    pub seed: Option<u64>,
    /// Configuration file (TOML; see docs/CONFIG.md)
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Worker threads (0 = all cores)
    #[arg(long)]
    pub threads: Option<usize>,
}

/// `DPSLAM_GPU_PRECISION` (`auto`, `f32`, `f64`) and `DPSLAM_GPU_MAX_BINDING`
/// (bytes) override the configuration's `[gpu]` section: the command line
/// reads the environment so that the library never does.
fn gpu_settings_from_env(cfg: &mut Config) -> dpslam::Result<()> {
    if let Ok(v) = std::env::var("DPSLAM_GPU_PRECISION") {
        cfg.gpu.precision = v.parse().map_err(|_| {
            dpslam::Error::Gpu(format!(
                "DPSLAM_GPU_PRECISION is {v:?}: expected auto, f32 or f64"
            ))
        })?;
    }
    if let Ok(v) = std::env::var("DPSLAM_GPU_MAX_BINDING") {
        cfg.gpu.max_binding = v.trim().parse().map_err(|_| {
            dpslam::Error::Gpu(format!(
                "DPSLAM_GPU_MAX_BINDING is {v:?}: expected a size in bytes"
            ))
        })?;
    }
    Ok(())
}

/// Loads the config file (if any) and applies the flags over it.
pub fn build_config(run: &RunArgs, particles: Option<usize>) -> dpslam::Result<Config> {
    let (file, seed, threads) = (run.config.as_ref(), run.seed, run.threads);
    let mut cfg = match file {
        Some(p) => Config::from_toml_file(p)?,
        None => Config::default(),
    };
    if let Some(n) = particles {
        cfg.filter.particles = n;
    }
    if let Some(s) = seed {
        cfg.seed = s;
    }
    if let Some(t) = threads {
        cfg.threads = t;
    }
    gpu_settings_from_env(&mut cfg)?;
    cfg.validate()?;
    if cfg.threads > 0 {
        // Ignore the error if a pool already exists (only one global pool per process).
        let _ = rayon::ThreadPoolBuilder::new()
            .num_threads(cfg.threads)
            .build_global();
    }
    Ok(cfg)
}

pub fn run(a: Map2dArgs) -> dpslam::Result<()> {
    let mut cfg = build_config(&a.run, a.particles)?;
    cfg.hierarchy.enabled |= a.hierarchical;
    let log = a.log.unwrap_or_else(|| PathBuf::from(DEFAULT_LOG));
    let s = if a.learn_motion > 0 {
        let report = |r: &dpslam::pipeline::learn_motion::LearnRound| {
            let m = &r.fit.model;
            eprintln!(
                "learn-motion round {}/{}: {} steps ({} left out), log-likelihood per step \
                 {:.2} -> {:.2}; std D [{:.4} m/m, {:.4} m/rad] C [{:.4} m/m, {:.4} m/rad] \
                 T [{:.4} rad/m, {:.4} rad/rad], floors {:.4} m, {:.4} rad ({:.1} s)",
                r.round,
                a.learn_motion,
                r.fit.steps,
                r.fit.outliers,
                r.fit.prior_log_likelihood,
                r.fit.log_likelihood,
                m.std_d[0],
                m.std_d[1],
                m.std_c[0],
                m.std_c[1],
                m.std_t[0],
                m.std_t[1],
                m.min_std_xy,
                m.min_std_t,
                r.wall_time_s
            );
        };
        dpslam::pipeline::learn_motion::run_map2d_learning(
            &log,
            &a.out,
            &cfg,
            a.backend,
            a.learn_motion,
            report,
        )?
        .0
    } else {
        let mut progress = super::progress::Progress::new("map2d");
        let s = dpslam::pipeline::map2d::run_map2d_observed(
            &log,
            &a.out,
            &cfg,
            a.backend,
            &mut |done, total| progress.update(done, total),
        )?;
        progress.finish();
        s
    };
    super::progress::print_warnings(&s.warnings);
    println!(
        "map2d: {} scans ({} processed), {} particles, {:.1} s wall, peak {:.0} MiB -> {}",
        s.scans,
        s.scans_processed,
        s.particles,
        s.wall_time_s,
        s.peak_memory_mib.unwrap_or(f64::NAN),
        a.out.display()
    );
    Ok(())
}
