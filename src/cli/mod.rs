//! Command-line definitions and dispatch. Each subcommand lives in its own file
//! and calls into the library.

mod eval;
mod map2d;
mod map3d;
mod perturb;
mod progress;
mod simulate;

use clap::{Parser, Subcommand};

/// DP-SLAM: laser SLAM with distributed-particle maps, 2-D and 3-D.
#[derive(Parser, Debug)]
#[command(name = "dpslam", version, about, long_about = None)]
pub struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// Build a 2-D map and trajectory from a CARMEN or DP-SLAM log.
    Map2d(map2d::Map2dArgs),
    /// Build a 3-D voxel map and 6-DoF trajectory from a directory of sweeps.
    Map3d(map3d::Map3dArgs),
    /// Write a simulated 2-D CARMEN log with ground truth.
    Simulate2d(simulate::Simulate2dArgs),
    /// Write a simulated 3-D sweep sequence with odometry and ground truth.
    Simulate3d(simulate::Simulate3dArgs),
    /// Turn a corrected log into a SLAM benchmark: noisy odometry plus truth.
    Perturb(perturb::PerturbArgs),
    /// Accuracy metrics.
    #[command(subcommand)]
    Eval(eval::EvalCommand),
}

/// Runs one parsed command line.
pub fn run(cli: Cli) -> dpslam::Result<()> {
    match cli.command {
        Command::Map2d(a) => map2d::run(a),
        Command::Map3d(a) => map3d::run(a),
        Command::Simulate2d(a) => simulate::run2d(a),
        Command::Simulate3d(a) => simulate::run3d(a),
        Command::Perturb(a) => perturb::run(a),
        Command::Eval(c) => eval::run(c),
    }
}
