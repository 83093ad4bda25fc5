//! `dpslam eval`: accuracy of a trajectory against ground truth.
//!
//! Output contract (other tools parse it): one readable line on stdout, or
//! with `--json` one JSON object on stdout (the fields of
//! `dpslam::eval::relations::RelationsReport` / `dpslam::eval::ate::AteReport`).

use clap::Subcommand;
use dpslam::eval::ate::{Alignment, AteOptions, DEFAULT_MAX_DT_S, evaluate_ate};
use dpslam::eval::relations::{evaluate_relations, read_relations};
use dpslam::io::tum::read_poses;
use dpslam::{Error, Result};
use serde::Serialize;
use std::path::{Path, PathBuf};

/// Accuracy metrics.
#[derive(Subcommand, Debug)]
pub enum EvalCommand {
    /// Relative-pose error (Kümmerle et al. 2009) against a relations file:
    /// mean ± std of translation (m) and rotation (deg).
    Relations {
        /// Relations file: `t1 t2 x y z roll pitch yaw` per line (s, m, rad).
        #[arg(long)]
        relations: PathBuf,
        /// Estimated trajectory, TUM (`t x y z qx qy qz qw`) or KITTI poses.
        #[arg(long)]
        trajectory: PathBuf,
        /// Print one JSON object instead of a readable line.
        #[arg(long)]
        json: bool,
    },
    /// Absolute trajectory error after rigid alignment (SE(2) for planar
    /// trajectories, SE(3) otherwise).
    Ate {
        /// Ground-truth trajectory, TUM or KITTI poses.
        #[arg(long)]
        truth: PathBuf,
        /// Estimated trajectory, TUM or KITTI poses.
        #[arg(long)]
        trajectory: PathBuf,
        /// Print one JSON object instead of a readable line.
        #[arg(long)]
        json: bool,
        /// Always fit a full SE(3) alignment, even for planar trajectories.
        #[arg(long)]
        se3: bool,
        /// Largest time difference (s) between paired truth and estimate poses.
        #[arg(long, default_value_t = DEFAULT_MAX_DT_S)]
        max_dt: f64,
    },
}

/// Prints `report` as one JSON object or as its one-line summary.
fn print<T: Serialize + std::fmt::Display>(report: &T, json: bool) -> Result<()> {
    if json {
        let s = serde_json::to_string(report)
            .map_err(|e| Error::Invalid(format!("cannot encode the report as JSON: {e}")))?;
        println!("{s}");
    } else {
        println!("{report}");
    }
    Ok(())
}

/// Adds the file names to an error that the library could only phrase in
/// terms of poses, so that the user knows which inputs to look at.
fn with_inputs(e: Error, inputs: &[&Path]) -> Error {
    let names = inputs
        .iter()
        .map(|p| p.display().to_string())
        .collect::<Vec<_>>()
        .join(" vs ");
    match e {
        Error::Invalid(m) => Error::Invalid(format!("{names}: {m}")),
        // A relation time missing from the trajectory is reported at the
        // relations line; name the trajectory it was looked up in.
        Error::Parse {
            path,
            location,
            reason,
        } if inputs.len() > 1 && path == inputs[0] => Error::Parse {
            path,
            location,
            reason: format!("{reason} (in {})", inputs[1].display()),
        },
        other => other,
    }
}

/// Runs one `dpslam eval` subcommand.
pub fn run(c: EvalCommand) -> dpslam::Result<()> {
    match c {
        EvalCommand::Relations {
            relations,
            trajectory,
            json,
        } => {
            let rels = read_relations(&relations)?;
            let traj = read_poses(&trajectory)?;
            let report = evaluate_relations(&rels, &traj)
                .map_err(|e| with_inputs(e, &[&relations, &trajectory]))?;
            print(&report, json)
        }
        EvalCommand::Ate {
            truth,
            trajectory,
            json,
            se3,
            max_dt,
        } => {
            let gt = read_poses(&truth)?;
            let est = read_poses(&trajectory)?;
            let opts = AteOptions {
                max_dt_s: max_dt,
                alignment: if se3 { Alignment::Se3 } else { Alignment::Auto },
            };
            let report = evaluate_ate(&gt, &est, &opts)
                .map_err(|e| with_inputs(e, &[&truth, &trajectory]))?;
            print(&report, json)
        }
    }
}
