//! A filter on a real log, ready to time: the scans the filter would process
//! (same motion gate and beam thinning as `map2d`), a filter warmed up on the
//! first of them, and the pieces of one step that can be timed on their own.

use crate::ancestry::{AncestryTree, Change, NodeId, Numbering};
use crate::config::Config;
use crate::dpmap::{DpMap, ViewCache};
use crate::filter::{ParticleFilter, Stamp};
use crate::geometry::{Pose, Pose2, pose2};
use crate::io::log2d::{LogFormat, open_log2d};
use crate::laser_model::{LaserModel, Trace};
use crate::motion_model::CdtModel;
use crate::pipeline::map2d::to_scan;
use crate::raycast::CellKey;
use crate::scan::Scan;
use crate::scorer::{BeamSubset, Candidate, CpuScorer, ScoreContext, Scorer};
use crate::{Error, Result};
use rayon::prelude::*;
use rustc_hash::FxHashMap;
use std::path::Path;

/// Mirrors `map2d`'s default usable-range cap (m).
const DEFAULT_RANGE_CAP: f64 = 20.0;

/// Mirrors `map2d`'s laser mounting for DP-SLAM-format logs (m ahead).
const DPSLAM_LASER_OFFSET: f64 = 0.40;

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
pub fn prepare_log(log: &Path, cfg: &Config, max_steps: usize) -> Result<PreparedLog> {
    cfg.validate()?;
    let reader = open_log2d(log)?;
    let sensor = match cfg.motion2d.sensor_offset {
        Some([x, y, th]) => pose2(x, y, th),
        None => match reader.format() {
            LogFormat::DpSlam => pose2(DPSLAM_LASER_OFFSET, 0.0, 0.0),
            LogFormat::Carmen => Pose2::identity(),
        },
    };
    let f = &cfg.filter;
    let mut first = None;
    let mut last_odo = Pose2::identity();
    let mut max_range = 0.0;
    let mut steps = Vec::new();
    for (index, item) in reader.enumerate() {
        let s = item?;
        let index = index as u32;
        if first.is_none() {
            max_range = if cfg.laser.max_range > 0.0 {
                cfg.laser.max_range
            } else {
                s.max_range.min(DEFAULT_RANGE_CAP)
            };
            first = Some(to_scan(&s, sensor, cfg.laser.max_beams, max_range));
            last_odo = s.odometry;
        } else {
            let delta = last_odo.inverse() * s.odometry;
            if delta.translation.vector.norm() >= f.min_translation
                || delta.rotation.angle().abs() >= f.min_rotation
            {
                steps.push(PreparedStep {
                    delta,
                    scan: to_scan(&s, sensor, cfg.laser.max_beams, max_range),
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
        let mut f = self.cfg.filter.clone();
        f.particles = particles;
        let motion = Box::new(CdtModel {
            cfg: self.cfg.motion2d.clone(),
        });
        let mut filter = ParticleFilter::new(
            f,
            self.laser.clone(),
            motion,
            self.cfg.seed,
            Pose2::identity(),
            &self.first,
            0,
        );
        filter.set_shared_free_space(self.cfg.map.shared_free_space);
        filter
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
            filter.step(&s.delta, &s.scan, s.index);
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

/// The map update of one step, as the filter does it (observations in
/// parallel, then inserted in particle order): every particle gets a child node and its observation of `scan` from pose `pose·delta` (computed
/// against its own view, free space shared when `shared_free`). Returns the new
/// nodes, one per particle.
#[allow(clippy::too_many_arguments)] // the pieces of a filter that the filter keeps private
pub fn update_map(
    map: &mut DpMap<2>,
    tree: &mut AncestryTree<Stamp<Pose2>>,
    numbering: &Numbering,
    laser: &LaserModel,
    particles: &[(NodeId, Pose2)],
    delta: &Pose2,
    scan: &Scan<2, Pose2>,
    shared_free: bool,
) -> Vec<NodeId> {
    type Obs = (Vec<(CellKey<2>, f32, f32)>, Vec<(NodeId, CellKey<2>, f32)>);
    // In parallel and through a map cache per worker, as the filter does.
    let observations: Vec<Obs> = particles
        .par_iter()
        .map_init(ViewCache::new, |cache, &(node, pose)| {
            let pose = pose.compose(delta);
            let mut view = map.view(numbering, node);
            let sensor = pose.compose(&scan.sensor);
            let origin = sensor.translation();
            let mut acc: FxHashMap<CellKey<2>, (f32, f32)> = FxHashMap::default();
            for b in &scan.beams {
                laser.trace_update(
                    origin,
                    sensor.rotate(b.dir),
                    b.range,
                    b.no_return,
                    |k, h, d| {
                        let e = acc.entry(k).or_insert((0.0, 0.0));
                        e.0 += h;
                        e.1 += d;
                    },
                );
            }
            let prior = laser.prior_distance as f32;
            let (mut new, mut free) = (Vec::new(), Vec::new());
            for (k, (h, d)) in acc {
                match view.entry_cached(cache, k) {
                    Some(e) if shared_free && e.hits <= 0.0 && h <= 0.0 => {
                        free.push((e.node, k, d))
                    }
                    Some(e) => new.push((k, e.hits + h, e.distance + d)),
                    None => new.push((k, h, d + prior)),
                }
            }
            (new, free)
        })
        .collect();
    let share = 1.0 / particles.len().max(1) as f32;
    particles
        .iter()
        .zip(observations)
        .map(|(&(parent, pose), (new, free))| {
            let node = tree.add_child(
                parent,
                Stamp {
                    scan: u32::MAX,
                    pose,
                },
            );
            for (k, h, d) in new {
                map.insert(node, k, h, d);
            }
            for (owner, k, d) in free {
                map.add_distance(owner, k, d * share);
            }
            node
        })
        .collect()
}

/// Ancestry maintenance of one step: prune and collapse the tree down to
/// `held`, mirror the edits in the map, renumber. Returns the tree edits.
pub fn maintain(
    tree: &mut AncestryTree<Stamp<Pose2>>,
    map: &mut DpMap<2>,
    held: &mut [NodeId],
    numbering: &mut Numbering,
) -> Vec<Change> {
    let changes = tree.maintain(held);
    map.apply(&changes);
    tree.number(numbering);
    changes
}
