//! A filter on a real log, ready to time: the scans the filter would process
//! (same motion gate and beam thinning as `map2d`), a filter warmed up on the
//! first of them, and the pieces of one step that can be timed on their own.

use dpslam::config::Config;
use dpslam::filter::{ParticleFilter, Sample, StepInput};
use dpslam::geometry::{Pose, Pose2};
use dpslam::laser_model::{LaserModel, Trace};
use dpslam::pipeline::map2d::{RangeSettings, sensor_mount};
use dpslam::scan::Scan;
use dpslam::scorer::{BeamSubset, Candidate, CpuScorer, ScoreContext, Scorer};
use dpslam::slam::slam2d::{moved_enough, new_filter, to_scan};
use dpslam::{Error, Result};
use std::path::Path;

/// One filter step's input.
#[derive(Debug, Clone)]
pub struct PreparedStep {
    /// Odometry motion since the previous processed scan (its robot frame).
    pub delta: Pose2,
    /// The scan, thinned and range-capped as `map2d` does.
    pub scan: Scan<2, Pose2>,
    /// Index of the scan in the input.
    pub index: u32,
}

impl PreparedStep {
    /// The filter step's input: samples from the motion model.
    pub fn input(&self) -> StepInput<'_, 2, Pose2> {
        StepInput::motion(self.delta, &self.scan, self.index)
    }
}

/// The processed scans of a log, in memory.
#[derive(Debug, Clone)]
pub struct PreparedLog {
    /// The first scan (it seeds the map).
    pub first: Scan<2, Pose2>,
    /// Every later scan that passes the motion gate.
    pub steps: Vec<PreparedStep>,
    /// The laser model `map2d` would use for this log.
    pub laser: LaserModel,
    cfg: Config,
}

/// Reads `log` and keeps the scans `map2d` would process with `cfg`: the first,
/// then each one after the robot moved `min_translation` or turned
/// `min_rotation` since the last kept one; at most `max_steps` after the first.
/// The opt-in confirmed gate (`filter.confirmed_translation`) is not applied:
/// it needs the filter's own matches.
pub fn prepare_log(log: &Path, cfg: &Config, max_steps: usize) -> Result<PreparedLog> {
    cfg.validate()?;
    // The "no return" threshold and usable range map2d would take.
    let ranges = RangeSettings::of_log(log, cfg)?;
    let reader = dpslam::pipeline::map2d::open_configured(log, cfg)?;
    let sensor = sensor_mount(cfg, reader.format());
    let f = &cfg.filter;
    let mut first = None;
    let mut last_odo = Pose2::identity();
    let mut max_range = 0.0;
    let mut steps = Vec::new();
    for (index, item) in reader.enumerate() {
        let s = item?;
        let reading = s.as_ranges().with_no_return_at(ranges.no_return_at);
        let index = index as u32;
        if first.is_none() {
            max_range = ranges.usable_range(cfg, reading.max_range);
            first = Some(to_scan(
                &reading,
                sensor,
                cfg.laser.max_beams,
                max_range,
                cfg.laser.no_return,
            ));
            last_odo = s.odometry;
        } else {
            let delta = last_odo.inverse() * s.odometry;
            if moved_enough(f, &delta) {
                steps.push(PreparedStep {
                    delta,
                    scan: to_scan(
                        &reading,
                        sensor,
                        cfg.laser.max_beams,
                        max_range,
                        cfg.laser.no_return,
                    ),
                    index,
                });
                last_odo = s.odometry;
                if steps.len() >= max_steps {
                    break;
                }
            }
        }
    }
    let first = first.ok_or_else(|| Error::in_file(log, "no laser scans"))?;
    Ok(PreparedLog {
        first,
        steps,
        laser: LaserModel::new(&cfg.laser, cfg.cell_size(), max_range),
        cfg: cfg.clone(),
    })
}

impl PreparedLog {
    /// A fresh filter with `particles` particles and the first scan in its map
    /// (otherwise configured as `map2d` would be).
    pub fn new_filter(&self, particles: usize) -> ParticleFilter<2, Pose2> {
        let mut cfg = self.cfg.clone();
        cfg.filter.particles = particles;
        new_filter(&cfg, self.laser.clone(), &self.first, 0)
    }

    /// A filter that has already processed the first `warmup` steps.
    pub fn warm_filter(&self, particles: usize, warmup: usize) -> Result<ParticleFilter<2, Pose2>> {
        if warmup > self.steps.len() {
            return Err(Error::Config(format!(
                "{warmup} warm-up steps asked for, the log has {} processed scans after the first",
                self.steps.len()
            )));
        }
        let mut filter = self.new_filter(particles);
        for s in &self.steps[..warmup] {
            filter.step(&s.input());
        }
        Ok(filter)
    }
}

/// Scores every particle, moved by `delta`, on `scan` with the full trace and
/// all beams: the likelihood work of one step for one sample per particle.
pub fn score_particles(
    filter: &ParticleFilter<2, Pose2>,
    scorer: &CpuScorer<2>,
    delta: &Pose2,
    scan: &Scan<2, Pose2>,
) -> Vec<f64> {
    let ctx = ScoreContext {
        map: filter.map(),
        numbering: filter.numbering(),
        laser: filter.laser(),
        scan,
    };
    let candidates: Vec<Candidate<Pose2>> = filter
        .particles()
        .iter()
        .map(|p| Candidate {
            node: p.node,
            pose: p.pose.compose(delta),
        })
        .collect();
    Scorer::<2, Pose2>::score(scorer, &ctx, &candidates, BeamSubset::ALL, Trace::Full)
}

/// One sample per particle at its pose moved by `delta`, drawn from the
/// particles at `parents` (indices into `filter.particles()`).
pub fn moved_samples(
    filter: &ParticleFilter<2, Pose2>,
    parents: &[usize],
    delta: &Pose2,
) -> Vec<Sample<Pose2>> {
    parents
        .iter()
        .map(|&i| Sample {
            pose: filter.particles()[i].pose.compose(delta),
            parent: i,
        })
        .collect()
}

/// The map update of one step, by the filter's own code: every sample becomes
/// a particle with a new ancestry node holding its observation of `scan`.
pub fn update_map(
    filter: &mut ParticleFilter<2, Pose2>,
    samples: &[Sample<Pose2>],
    scan: &Scan<2, Pose2>,
) {
    let scores = vec![0.0; samples.len()];
    let chosen: Vec<usize> = (0..samples.len()).collect();
    filter.update(samples, &scores, &chosen, scan, u32::MAX);
}

/// Ancestry maintenance of one step, by the filter's own code: prune and
/// collapse the tree, mirror the edits in the map, renumber.
pub fn maintain(filter: &mut ParticleFilter<2, Pose2>) {
    filter.prune();
}
