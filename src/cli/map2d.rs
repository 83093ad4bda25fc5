//! `dpslam map2d`: 2-D DP-SLAM on a CARMEN or DP-SLAM log.

use dpslam::config::Config;
use std::path::PathBuf;

/// The shipped simulated loop (`data/sim2d`), embedded in the binary: `map2d` with no log maps it, so
/// that a moved or installed binary needs no source tree.
pub const EMBEDDED_LOG: &[u8] = include_bytes!("../../data/sim2d/sim2d.clf");

/// A file in the temporary folder, removed when dropped.
pub struct TempFile(pub PathBuf);

impl Drop for TempFile {
    fn drop(&mut self) {
        let _ = std::fs::remove_file(&self.0);
    }
}

/// Writes the embedded default log to the temporary folder.
pub fn embedded_log() -> dpslam::Result<TempFile> {
    let p = std::env::temp_dir().join(format!("dpslam-sim2d-{}.clf", std::process::id()));
    std::fs::write(&p, EMBEDDED_LOG).map_err(|e| dpslam::Error::io(&p, e))?;
    Ok(TempFile(p))
}

/// Parses a count flag (`--particles`): a whole number ≥ 1, with a message
/// that says so (clap's own tip for `-1` suggests `-- -1`, which is wrong).
pub fn parse_count(s: &str) -> Result<usize, String> {
    match s.parse::<usize>() {
        Ok(0) => Err("must be at least 1".into()),
        Ok(n) => Ok(n),
        Err(_) => Err(format!("'{s}' is not a whole number ≥ 1")),
    }
}

#[derive(clap::Args, Debug)]
pub struct Map2dArgs {
    /// CARMEN (.clf/.log) or DP-SLAM log, plain or gzip, or a ROS bag (.bag, .mcap, .db3 or a ROS 2 bag directory) [default: the shipped simulated loop]
    pub log: Option<PathBuf>,
    /// Output folder (map.png, map.pgm, map.yaml, trajectory.tum, run.json, config.toml)
    #[arg(long, default_value = "out/map2d")]
    pub out: PathBuf,
    /// Particles [default: 50, or the config file's]
    #[arg(long, allow_negative_numbers = true, value_parser = parse_count)]
    pub particles: Option<usize>,
    #[command(flatten)]
    pub run: RunArgs,
    #[command(flatten)]
    pub topics: TopicArgs,
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

/// Topic flags for ROS bag inputs.
#[derive(clap::Args, Debug)]
pub struct TopicArgs {
    /// ROS bag input: the sensor_msgs/LaserScan (map2d) or PointCloud2 (map3d) topic [default: the bag's only one]
    #[arg(long, value_name = "TOPIC")]
    pub scan_topic: Option<String>,
    /// ROS bag input: the nav_msgs/Odometry or tf topic [default: the only Odometry topic, else /tf odom -> base]
    #[arg(long, value_name = "TOPIC")]
    pub odom_topic: Option<String>,
}

impl TopicArgs {
    /// Sets the configuration's `[bag]` topics from the flags given.
    pub fn apply(&self, cfg: &mut Config) {
        if let Some(t) = &self.scan_topic {
            cfg.bag.scan_topic = Some(t.clone());
        }
        if let Some(t) = &self.odom_topic {
            cfg.bag.odom_topic = Some(t.clone());
        }
    }
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
    cfg.install_thread_pool();
    Ok(cfg)
}

pub fn run(a: Map2dArgs) -> dpslam::Result<()> {
    let mut cfg = build_config(&a.run, a.particles)?;
    cfg.hierarchy.enabled |= a.hierarchical;
    a.topics.apply(&mut cfg);
    dpslam::pipeline::preflight::check_memory(
        &cfg,
        dpslam::pipeline::preflight::available_memory(),
    )?;
    dpslam::pipeline::preflight::check_out_dir(&a.out)?;
    let embedded = match &a.log {
        Some(_) => None,
        None => Some(embedded_log()?),
    };
    let log = match (&a.log, &embedded) {
        (Some(l), _) => l.clone(),
        (None, Some(t)) => t.0.clone(),
        (None, None) => unreachable!("the embedded log is written when no log is given"),
    };
    // The range survey reads the whole log before the long work: what it
    // finds worth a warning is said now, not after the run.
    let ranges = dpslam::pipeline::map2d::RangeSettings::of_log(&log, &cfg)?;
    let early = ranges.warnings(&log, &cfg);
    super::progress::print_warnings(&early);
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
            &ranges,
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
            &ranges,
            &mut |done, total| progress.update(done, total),
        )?;
        progress.finish();
        s
    };
    super::progress::print_backend_note(&s.backend);
    let later: Vec<String> = s
        .warnings
        .iter()
        .filter(|w| !early.contains(w))
        .cloned()
        .collect();
    super::progress::print_warnings(&later);
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
