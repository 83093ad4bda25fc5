//! `dpslam simulate2d` and `dpslam simulate3d`: write simulated logs with
//! known ground truth.

use dpslam::sim::sim2d::{Sim2dConfig, write_sim2d_with};
use dpslam::sim::sim3d::{Sim3dConfig, write_sim3d};
use std::path::PathBuf;

/// Arguments of `dpslam simulate2d`.
#[derive(clap::Args, Debug)]
pub struct Simulate2dArgs {
    /// CARMEN log to write: one FLASER line per scan (181 beams, 10 Hz), with
    /// the noisy odometry as both the laser and the odometry pose.
    #[arg(long, value_name = "FILE.clf")]
    out: PathBuf,
    /// True trajectory to write, TUM format (t x y z qx qy qz qw).
    #[arg(long, value_name = "FILE.tum")]
    truth: PathBuf,
    /// Seed of the odometry and range noise; seed 1 gives data/sim2d.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// TOML file overriding fields of the simulation (waypoints, speed,
    /// laser, odometry noise, walls); absent fields keep their defaults.
    #[arg(long, value_name = "FILE.toml")]
    config: Option<PathBuf>,
}

/// Arguments of `dpslam simulate3d`.
#[derive(clap::Args, Debug)]
pub struct Simulate3dArgs {
    /// Directory to write: `sweeps/NNNNNN.bin` (KITTI float32 x y z
    /// intensity, sensor frame), `odometry.tum` (noisy) and `truth.tum`;
    /// created if needed. Time stamps are sweep indices in seconds.
    #[arg(long, value_name = "DIR")]
    out: PathBuf,
    /// Seed of the odometry and range noise; seed 1 with
    /// `--sweeps 40 --rings 16 --columns 512 --gzip` gives data/sim3d.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Built-in world and path: `building` (a 23 m × 19 m building with a
    /// mezzanine, a 70 m loop, 200 sweeps) or `corridors` (plain 3 m
    /// corridors around a 360 m loop, features 17–34 m apart, 368 sweeps
    /// ≈ 1 m apart). The options below override the preset's sweeps and
    /// lidar; a `--config` file brings its own scene instead.
    #[arg(long, value_enum, default_value_t = World::Building, conflicts_with = "config")]
    world: World,
    /// Number of sweeps, evenly spaced along the loop [default: the
    /// world's, 200 or 368].
    #[arg(long)]
    sweeps: Option<usize>,
    /// Lidar rings (channels), from −25° to +15° elevation [default: 32].
    #[arg(long)]
    rings: Option<usize>,
    /// Firings per ring and revolution [default: 1024].
    #[arg(long)]
    columns: Option<usize>,
    /// Write the sweeps gzip-compressed (`NNNNNN.bin.gz`).
    #[arg(long)]
    gzip: bool,
    /// TOML file overriding fields of the simulation (waypoints, lidar,
    /// odometry noise, scene); absent fields keep their defaults, and the
    /// options above override the file.
    #[arg(long, value_name = "FILE.toml")]
    config: Option<PathBuf>,
}

/// The built-in worlds of `dpslam simulate3d --world`.
#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum World {
    /// [`Sim3dConfig::default`]: the building with a mezzanine.
    Building,
    /// [`Sim3dConfig::corridors`]: the long, feature-poor corridor loop.
    Corridors,
}

/// Runs `dpslam simulate2d` and prints a one-line summary.
pub fn run2d(a: Simulate2dArgs) -> dpslam::Result<()> {
    let cfg = match &a.config {
        Some(path) => Sim2dConfig::load(path)?,
        None => Sim2dConfig::default(),
    };
    let summary = write_sim2d_with(&cfg, &a.out, &a.truth, a.seed)?;
    println!(
        "simulate2d: seed {}: {summary} -> {}, {}",
        a.seed,
        a.out.display(),
        a.truth.display()
    );
    Ok(())
}

/// Runs `dpslam simulate3d` and prints a one-line summary.
pub fn run3d(a: Simulate3dArgs) -> dpslam::Result<()> {
    let mut cfg = match &a.config {
        Some(path) => Sim3dConfig::load(path)?,
        None => match a.world {
            World::Building => Sim3dConfig::default(),
            World::Corridors => Sim3dConfig::corridors(),
        },
    };
    if let Some(n) = a.sweeps {
        cfg.sweeps = n;
    }
    if let Some(n) = a.rings {
        cfg.rings = n;
    }
    if let Some(n) = a.columns {
        cfg.columns = n;
    }
    cfg.gzip |= a.gzip;
    let summary = write_sim3d(&a.out, &cfg, a.seed)?;
    println!(
        "simulate3d: seed {}: {summary} -> {}",
        a.seed,
        a.out.display()
    );
    Ok(())
}
