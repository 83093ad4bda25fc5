//! Motion-model learning over a whole log (dissertation ch. 6): rounds of a
//! full 2-D SLAM run (E-step) and a fit of the C/D/T model to the best
//! trajectory's motions (M-step), then the final run with the learned model.

use super::map2d::{Map2dSummary, RangeSettings, run_filter2d_observed, run_map2d_observed};
use crate::Result;
use crate::config::Config;
use crate::motion_learning::{LearnOptions, MotionFit, fit_cdt};
use serde::Serialize;
use std::path::Path;
use std::time::Instant;

/// One EM round of motion learning ([`learn_motion2d`]).
#[derive(Debug, Clone, Serialize)]
pub struct LearnRound {
    /// Round number, from 1.
    pub round: usize,
    /// Wall-clock time of the round's SLAM run and fit, s.
    pub wall_time_s: f64,
    /// The model fitted in this round (used by the next).
    pub fit: MotionFit,
}

/// Learns the C/D/T motion model of `log` (dissertation ch. 6): `rounds`
/// rounds of a full SLAM run with the current model (E-step) and a fit of
/// the model to the best trajectory's motions (M-step, [`fit_cdt`]),
/// starting from `cfg.motion2d`, calling `on_round` after each; every run
/// takes the range settings `ranges` ([`RangeSettings::of_log`]). Returns
/// `cfg` with the learned model and the rounds; writes nothing.
pub fn learn_motion2d(
    log: &Path,
    cfg: &Config,
    backend: crate::backend::Backend,
    ranges: &RangeSettings,
    rounds: usize,
    mut on_round: impl FnMut(&LearnRound),
) -> Result<(Config, Vec<LearnRound>)> {
    let mut cfg = cfg.clone();
    let opts = LearnOptions::from_config(&cfg);
    let mut history = Vec::with_capacity(rounds);
    for round in 1..=rounds {
        let start = Instant::now();
        let run = run_filter2d_observed(log, &cfg, backend, ranges, &mut super::no_progress)?;
        let fit = fit_cdt(&run.slam.motion_samples(), &cfg.motion2d, &opts)?;
        cfg.motion2d = fit.model.clone();
        let r = LearnRound {
            round,
            wall_time_s: start.elapsed().as_secs_f64(),
            fit,
        };
        on_round(&r);
        history.push(r);
    }
    Ok((cfg, history))
}

/// [`learn_motion2d`], then [`run_map2d_observed`] with the learned model
/// (every run with the range settings `ranges`): the run folder's
/// `config.toml` holds the learned model (so `--config` on it reproduces
/// the final run) and `motion_learning.json` the rounds.
pub fn run_map2d_learning(
    log: &Path,
    out: &Path,
    cfg: &Config,
    backend: crate::backend::Backend,
    ranges: &RangeSettings,
    rounds: usize,
    on_round: impl FnMut(&LearnRound),
) -> Result<(Map2dSummary, Vec<LearnRound>)> {
    let (learned, history) = learn_motion2d(log, cfg, backend, ranges, rounds, on_round)?;
    let summary = run_map2d_observed(log, out, &learned, backend, ranges, &mut super::no_progress)?;
    super::write_json(&out.join("motion_learning.json"), &history)?;
    Ok((summary, history))
}
