//! `dpslam simulate2d` and `dpslam simulate3d`: write simulated logs with
//! known ground truth.

use dpslam::sim::sim2d::{Sim2dConfig, write_sim2d_with};
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

#[derive(clap::Args, Debug)]
pub struct Simulate3dArgs {}

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

pub fn run3d(_a: Simulate3dArgs) -> dpslam::Result<()> {
    Err(dpslam::Error::Invalid("in progress".into()))
}
