//! `dpslam perturb`: a corrected log becomes noisy odometry plus truth.

use dpslam::sim::perturb::{NoiseModel, perturb_log};
use std::io::Write;
use std::path::PathBuf;

/// Noise model text for `--help`; the equations are those of
/// `dpslam::sim::perturb`.
const NOISE_HELP: &str = "\
Noise model, per step between consecutive scans. (dx, dy, dθ) is the true
motion in the previous true pose's frame, d = √(dx² + dy²):
  dx' = (1+scale)·dx + σ_t·n1        σ_t = trans·d + trans_per_rot·|dθ|
  dy' = (1+scale)·dy + σ_t·n2        σ_r = rot_per_trans·d + rot·|dθ|
  dθ' = (1+rot_scale)·dθ + drift·d + σ_r·n3
n1, n2, n3 ~ N(0, 1) from Pcg64 seeded with --seed. The noisy steps are
chained from the first true pose. scale, rot_scale: scale biases (fraction);
drift: systematic turn (rad per metre, CCW positive); trans (m/m),
trans_per_rot (m/rad), rot_per_trans (rad/m), rot (rad/rad): noise std
coefficients. The σ terms act per step, so their effect shrinks with the scan
rate; the systematic terms do not.

--noise takes key=value pairs separated by commas, starting from the
defaults; 'none' sets all to zero and 'default' restores the defaults, e.g.
--noise none,trans=0.05,rot=0.05. Defaults: scale=0.01, rot_scale=0.02,
drift=0.001, trans=0.02, trans_per_rot=0.01, rot_per_trans=0.005, rot=0.03:
about 1-8 m of drift per 100 m on the corrected logs of ../shared/datasets.

Outputs: --out is a CARMEN log (FLASER, both pose fields = noisy odometry,
same ranges and time stamps; gzip if the name ends in .gz); --truth is TUM
(t x y z qx qy qz qw, one line per scan, z = 0, quaternion about z). Both are
written under temporary names and renamed at the end.";

/// Turn a corrected log (reference poses in `x y theta`) into a SLAM
/// benchmark: a CARMEN log whose odometry is the true motion corrupted by a
/// stated noise model, and the truth trajectory in TUM format.
#[derive(clap::Args, Debug)]
#[command(after_long_help = NOISE_HELP)]
pub struct PerturbArgs {
    /// Input log with reference poses (CARMEN, plain or gzip), e.g.
    /// freiburg-079-corrected.log.gz.
    pub log: PathBuf,
    /// Output CARMEN log with noisy odometry (.gz: gzip-compressed).
    #[arg(long)]
    pub out: PathBuf,
    /// Output truth trajectory, TUM format (s, m, quaternion).
    #[arg(long)]
    pub truth: PathBuf,
    /// Seed of the noise generator: the same seed gives identical files.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Noise spec, e.g. scale=0.02,rot_scale=0.01,drift=0.001,trans=0.05
    /// (unset keys keep their defaults; see the noise model below).
    #[arg(long, default_value = "default")]
    pub noise: NoiseModel,
}

/// Runs `dpslam perturb`: writes both files and prints the drift summary.
pub fn run(a: PerturbArgs) -> dpslam::Result<()> {
    let s = perturb_log(&a.log, &a.out, &a.truth, &a.noise, a.seed)?;
    let mut text = format!(
        "perturb: {} scans, true path {:.1} m, noise {} (seed {})\n\
         odometry drift: final {:.3} m, {:.2}°; max {:.3} m\n\
         wrote {} and {}\n",
        s.scans,
        s.path_length_m,
        a.noise,
        a.seed,
        s.final_position_error_m,
        s.final_heading_error_rad.to_degrees(),
        s.max_position_error_m,
        a.out.display(),
        a.truth.display()
    );
    if s.non_increasing_timestamps > 0 {
        text.push_str(&format!(
            "warning: {} scans have a time stamp not later than the previous one; \
             matching the truth by time will be ambiguous\n",
            s.non_increasing_timestamps
        ));
    }
    // The files are written; a closed stdout must not turn success into a panic.
    let _ = std::io::stdout().lock().write_all(text.as_bytes());
    Ok(())
}
