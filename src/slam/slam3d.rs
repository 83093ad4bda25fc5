//! Online 3-D DP-SLAM: laser sweeps (with an optional prior pose) in, 6-DoF
//! poses and a voxel map out.
//!
//! Per sweep:
//! 1. the points become a [`Scan<3, Pose3>`] ([`sweep_to_scan`]): one beam per
//!    sensor-frame point (direction `p/|p|`, range `|p|`), points closer than
//!    `map3d.min_range` dropped, down-sampled to one beam per
//!    `map3d.beam_voxel` voxel and then by an even stride to at most
//!    `map3d.max_beams` beams; returns beyond `map3d.max_range` are "no
//!    return" beams traced to that range;
//! 2. the prior motion since the previous sweep comes from the two sweeps'
//!    prior poses when both have one, else constant velocity (the best
//!    particle's last motion);
//! 3. the sweep is aligned ([`crate::icp`]) to the best particle's recent
//!    sweeps starting from `best · prior`, and the step's proposal is the
//!    alignment's Gaussian (covariance × `map3d.icp_covariance_scale`) fused
//!    with the 6-DoF [`Gaussian6dModel`] ([`Proposal::Matched`]; the motion
//!    model alone when the alignment failed);
//! 4. the particles are weighed with the penetration model on the voxel
//!    DP-map, resampled, and their maps updated: the same generic filter as
//!    2-D.
//!
//! The robot frame is the sensor frame (sweeps carry no mounting offset).
//! The map frame is the frame of the first prior pose when the first sweep
//! has one, else the first sensor frame.

use super::{Estimate, check_input};
use crate::config::{Config, FilterConfig, Map3dConfig, MapConfig, ReportedPose};
use crate::dpmap::DpMap;
use crate::filter::{ParticleFilter, PhaseTimes, Stamp, StepInput, StepStats};
use crate::geometry::{Pose, Pose3};
use crate::icp::{IcpParams, SweepWindow};
use crate::io::ply::VoxelPoint;
use crate::laser_model::LaserModel;
use crate::motion_model::Gaussian6dModel;
use crate::proposal::Proposal;
use crate::raycast::cell_centre;
use crate::scan::{Beam, Scan};
use crate::scorer::Scorer;
use crate::{Error, Result};
use nalgebra::DMatrix;
use rustc_hash::FxHashMap;

/// Converts one sweep's sensor-frame points (m) into the filter's scan (see
/// the module docs for the down-sampling). Deterministic: voxels keep their
/// first point in input order and the stride is even.
pub fn sweep_to_scan(points: &[[f32; 3]], m: &Map3dConfig) -> Scan<3, Pose3> {
    let mut seen: FxHashMap<[i32; 3], ()> = FxHashMap::default();
    let mut kept: Vec<glam::Vec3A> = Vec::new();
    let (min_range, beam_voxel) = (m.min_range as f32, m.beam_voxel as f32);
    for p in crate::points::from_sweep(points) {
        let r = p.length();
        if !r.is_finite() || r < min_range {
            continue;
        }
        if seen
            .insert(crate::points::voxel_of(p, beam_voxel), ())
            .is_none()
        {
            kept.push(p);
        }
    }
    let stride = kept.len().div_ceil(m.max_beams).max(1);
    let beams = kept
        .iter()
        .step_by(stride)
        .map(|&p| {
            let v = [p.x as f64, p.y as f64, p.z as f64];
            let r = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
            let no_return = r > m.max_range;
            Beam {
                dir: [v[0] / r, v[1] / r, v[2] / r],
                range: if no_return { m.max_range } else { r },
                no_return,
            }
        })
        .collect();
    Scan {
        sensor: Pose3::identity(),
        beams,
    }
}

/// The occupied voxels of `map` as the particle holding `node` sees it: it
/// has hits there and a density of at least `min_density` stops/m. Sorted by
/// position, so files are reproducible.
pub fn occupied_voxels_of_view(
    map: &DpMap<3>,
    numbering: &crate::ancestry::Numbering,
    node: crate::ancestry::NodeId,
    min_density: f64,
) -> Vec<VoxelPoint> {
    let mut view = map.view(numbering, node);
    let c = map.cell_size();
    let mut out = Vec::new();
    map.for_each_cell(|k, _| {
        if let Some((h, d)) = view.lookup(k) {
            let rho = if d > 0.0 { h as f64 / d as f64 } else { 0.0 };
            if h > 0.0 && rho >= min_density {
                let p = cell_centre(k, c);
                out.push(VoxelPoint {
                    position: [p[0] as f32, p[1] as f32, p[2] as f32],
                    density: rho as f32,
                    hits: h.round() as u32,
                });
            }
        }
    });
    // Brick iteration order is a hash order: sort for reproducible files.
    out.sort_by(|a, b| {
        a.position
            .iter()
            .zip(&b.position)
            .map(|(x, y)| x.total_cmp(y))
            .find(|o| o.is_ne())
            .unwrap_or(std::cmp::Ordering::Equal)
    });
    out
}

/// What the proposal did over a run, for run statistics.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct ProposalStats {
    /// Sweeps whose alignment failed (the prior was used as is).
    pub fallbacks: usize,
    /// Sum over sweeps of the alignment's correction of the prior, m.
    pub correction_m: f64,
    /// Sum over sweeps of the alignment's correction of the prior, degrees.
    pub correction_deg: f64,
    /// Time spent aligning, s.
    pub align_s: f64,
    /// Time spent in filter steps, s.
    pub filter_s: f64,
    /// Steps whose prior motion came from two prior poses (not constant
    /// velocity).
    pub prior_steps: usize,
    /// Time spent turning sweeps into scans (range filter, beam voxels), s.
    pub scan_s: f64,
    /// Time spent down-sampling sweeps for the alignment, s.
    pub prepare_s: f64,
    /// Of `align_s`: time spent building the local map, s.
    pub local_map_s: f64,
    /// The filter's phases summed over the steps.
    pub phases: PhaseTimes,
}

/// Online 3-D DP-SLAM.
///
/// Feed it every sweep ([`Slam3d::add_sweep`]): all are processed.
pub struct Slam3d {
    cfg: Config,
    motion: Gaussian6dModel,
    window: SweepWindow,
    scorer: Option<Box<dyn Scorer<3, Pose3>>>,
    filter: Option<ParticleFilter<3, Pose3>>,
    /// The previous sweep's prior pose, if it had one.
    prev_prior: Option<Pose3>,
    /// The best particle's last motion (previous robot frame).
    velocity: Pose3,
    /// Recent consensus of aligned sweeps with their local maps (fraction
    /// of points explained at the coarsest level; see `icp::align_wide`).
    consensus: Option<f64>,
    stamps: Vec<f64>,
    stats: Vec<StepStats>,
    proposal: ProposalStats,
    points_per_sweep: Vec<usize>,
    beams_per_sweep: Vec<usize>,
}

impl Slam3d {
    /// A SLAM run with the settings of `cfg` (checked here) and the CPU
    /// scorer.
    pub fn new(cfg: Config) -> Result<Self> {
        cfg.validate()?;
        let m = &cfg.map3d;
        Ok(Self {
            motion: Gaussian6dModel::from_config(m),
            window: SweepWindow::new(IcpParams::from_config(m)),
            cfg,
            scorer: None,
            filter: None,
            prev_prior: None,
            velocity: Pose3::identity(),
            consensus: None,
            stamps: Vec::new(),
            stats: Vec::new(),
            proposal: ProposalStats::default(),
            points_per_sweep: Vec::new(),
            beams_per_sweep: Vec::new(),
        })
    }

    /// Scores scans with `scorer` (e.g. the GPU backend) instead of the CPU.
    /// Takes effect from the first sweep; call it before.
    pub fn set_scorer(&mut self, scorer: Box<dyn Scorer<3, Pose3>>) -> Result<()> {
        if self.filter.is_some() {
            return Err(Error::Invalid(
                "the scorer must be set before the first sweep".into(),
            ));
        }
        self.scorer = Some(scorer);
        Ok(())
    }

    /// Adds the sweep taken at `stamp` (s): `points` in the sensor frame (m;
    /// non-finite points are dropped), `prior` the sensor's pose from
    /// odometry or a pose file, if known (any fixed frame). Returns the
    /// estimate after it.
    pub fn add_sweep(
        &mut self,
        stamp: f64,
        prior: Option<Pose3>,
        points: &[[f32; 3]],
    ) -> Result<Estimate<Pose3>> {
        let index = self.stamps.len();
        check_input::<3, Pose3>(index, stamp, prior.as_ref())?;
        let m = &self.cfg.map3d;
        let t = std::time::Instant::now();
        let scan = sweep_to_scan(points, m);
        self.proposal.scan_s += t.elapsed().as_secs_f64();
        if scan.beams.is_empty() {
            return Err(Error::Invalid(format!(
                "sweep {index}: no usable points ({} read; all closer than map3d.min_range = {} m or not finite)",
                points.len(),
                m.min_range
            )));
        }
        self.points_per_sweep.push(points.len());
        self.beams_per_sweep.push(scan.beams.len());
        self.stamps.push(stamp);
        let t = std::time::Instant::now();
        let prepared = self.window.prepare(points);
        self.proposal.prepare_s += t.elapsed().as_secs_f64();
        match self.filter.as_mut() {
            None => self.start(prior, &scan),
            Some(filter) => {
                let prior_delta = match (self.prev_prior, prior) {
                    (Some(a), Some(b)) => {
                        self.proposal.prior_steps += 1;
                        a.inverse() * b
                    }
                    _ => self.velocity,
                };
                let best = filter.particles()[filter.best_index()].pose;
                // `compose` keeps the quaternions unit along the
                // sweep-to-sweep chain.
                let guess = best.compose(&prior_delta);

                let t0 = std::time::Instant::now();
                let oldest = self.window.indices().next().unwrap_or(0);
                let recent: FxHashMap<u32, Pose3> = filter
                    .best_trajectory()
                    .iter()
                    .rev()
                    .take_while(|s| s.scan >= oldest)
                    .map(|s| (s.scan, s.pose))
                    .collect();
                let local = self.window.local_map(|j| recent.get(&j).copied());
                self.proposal.local_map_s += t0.elapsed().as_secs_f64();
                let seeds = crate::icp::search_seeds(
                    &best,
                    &guess,
                    m.search_yaw_step_deg,
                    m.search_yaw_max_deg,
                );
                let mut routine = false;
                let alignment = local
                    .as_ref()
                    .and_then(|map| {
                        crate::icp::align_wide(
                            map,
                            &prepared,
                            &seeds,
                            self.window.params(),
                            m.search_min_gain,
                            self.consensus,
                        )
                    })
                    .map(|(a, c)| {
                        // A match that explains the sweep as well as the
                        // recent ones did is sharp; one that explains it
                        // less (a turn, a new room) is in doubt.
                        routine = self
                            .consensus
                            .is_some_and(|e| c >= (1.0 - m.search_min_gain) * e);
                        // A slowly moving reference: one poor sweep does
                        // not lower the bar for the next.
                        self.consensus = Some(match self.consensus {
                            Some(e) => 0.7 * e + 0.3 * c,
                            None => c,
                        });
                        a
                    });
                let aligned = match &alignment {
                    Some(a) => a.pose,
                    None => {
                        self.proposal.fallbacks += 1;
                        guess
                    }
                };
                let corr = guess.inverse() * aligned;
                self.proposal.correction_m += corr.translation.vector.norm();
                self.proposal.correction_deg += corr.rotation.angle().to_degrees();
                self.proposal.align_s += t0.elapsed().as_secs_f64();

                let t1 = std::time::Instant::now();
                let delta = best.inverse().compose(&aligned);
                // Sample from the scan matcher's Gaussian fused with the
                // motion noise; without an alignment, or with the fusion
                // switched off, the motion noise alone.
                let scale = m.icp_covariance_scale;
                let proposal = alignment
                    .filter(|_| scale > 0.0)
                    .and_then(|a| self.motion.fuse(&delta, &(a.covariance * scale)))
                    .and_then(|c| c.cholesky())
                    .map(|c| {
                        Proposal::from_factor(
                            delta,
                            DMatrix::from_column_slice(6, 6, c.l().as_slice()),
                        )
                    })
                    .unwrap_or(Proposal::Motion);
                // Few samples cover a sharp match; a match in doubt, or
                // none, gets the motion model's count.
                let k = match (&proposal, m.matched_samples_per_particle) {
                    (Proposal::Matched { .. }, k) if k > 0 && routine => k,
                    _ => self.cfg.filter.samples_per_particle,
                };
                filter.set_samples_per_particle(k);
                let input = StepInput {
                    odometry: delta,
                    proposal,
                    scan: &scan,
                    index: index as u32,
                };
                let stats = filter.step(&input);
                self.proposal.phases += stats.times;
                self.stats.push(stats);
                self.proposal.filter_s += t1.elapsed().as_secs_f64();
                let new_best = filter.particles()[filter.best_index()].pose;
                self.velocity = best.inverse().compose(&new_best);
            }
        }
        self.prev_prior = prior;
        self.window.push(index as u32, prepared);
        Ok(Estimate {
            index,
            stamp,
            pose: self.best_pose(),
            processed: true,
        })
    }

    /// Builds the filter on the first sweep.
    fn start(&mut self, prior: Option<Pose3>, scan: &Scan<3, Pose3>) {
        let m = &self.cfg.map3d;
        let mut laser_cfg = self.cfg.laser.clone();
        laser_cfg.variance = m.variance;
        // A sweep's points in storage order are not one scan line: two
        // consecutive ones need not lie on one surface.
        laser_cfg.surface_fill_gap = 0.0;
        if m.trace_sigmas > 0.0 {
            let cells = m.trace_sigmas * m.variance.sqrt() / m.voxel_size;
            laser_cfg.trace_past_cells = cells;
            laser_cfg.max_error_cells = cells;
        }
        let laser = LaserModel::new(&laser_cfg, m.voxel_size, m.max_range);
        // The ICP proposal builds its local map from the reported
        // trajectory, so 3-D reports the samples the DP-map was built at:
        // with view means it lost `data/sim3d/sweeps` (4.56 m against
        // 0.007 m; docs/PROPOSAL-2D.md).
        let filter_cfg = FilterConfig {
            report: ReportedPose::Sample,
            ..self.cfg.filter.clone()
        };
        let mut filter = ParticleFilter::new(
            filter_cfg,
            laser,
            Box::new(self.motion.clone()),
            self.cfg.seed,
            prior.unwrap_or_else(Pose3::identity),
            scan,
            0,
        );
        // Shares divided by copies lost `data/sim3d/sweeps` from the LiDAR
        // alone (5.07 m against 0.007 m): 3-D pools them, as before.
        filter.set_map_update(&MapConfig {
            per_copy_shares: false,
            ..self.cfg.map.clone()
        });
        filter.set_quick_culling(m.quick_culling);
        if let Some(sc) = self.scorer.take() {
            filter.set_scorer(sc);
        }
        self.filter = Some(filter);
    }

    fn best_pose(&self) -> Pose3 {
        self.filter
            .as_ref()
            .map_or_else(Pose3::identity, |f| f.particles()[f.best_index()].pose)
    }

    /// Sweeps added so far.
    pub fn sweeps(&self) -> usize {
        self.stamps.len()
    }

    /// The trajectory, one `(time s, pose)` row per sweep (map frame), from
    /// the best particle.
    pub fn trajectory(&self) -> Result<Vec<(f64, Pose3)>> {
        let lineage = self.best_trajectory();
        if lineage.len() != self.stamps.len() {
            return Err(Error::Invalid(format!(
                "internal: {} poses for {} sweeps",
                lineage.len(),
                self.stamps.len()
            )));
        }
        lineage
            .iter()
            .zip(&self.stamps)
            .enumerate()
            .map(|(i, (st, &t))| {
                if st.pose.is_finite() {
                    Ok((t, st.pose))
                } else {
                    Err(Error::Invalid(format!("non-finite pose at sweep {i}")))
                }
            })
            .collect()
    }

    /// The best particle's poses, one per sweep.
    pub fn best_trajectory(&self) -> Vec<Stamp<Pose3>> {
        self.filter
            .as_ref()
            .map_or_else(Vec::new, ParticleFilter::best_trajectory)
    }

    /// The best particle's occupied voxels (see [`occupied_voxels_of_view`]
    /// and `map3d.occupied_density`).
    pub fn occupied_voxels(&self) -> Vec<VoxelPoint> {
        let Some(f) = &self.filter else {
            return Vec::new();
        };
        occupied_voxels_of_view(
            f.map(),
            f.numbering(),
            f.particles()[f.best_index()].node,
            self.cfg.map3d.occupied_density,
        )
    }

    /// The filter (`None` before the first sweep).
    pub fn filter(&self) -> Option<&ParticleFilter<3, Pose3>> {
        self.filter.as_ref()
    }

    /// What each filter step did (one per sweep after the first).
    pub fn stats(&self) -> &[StepStats] {
        &self.stats
    }

    /// What the proposal did so far.
    pub fn proposal_stats(&self) -> &ProposalStats {
        &self.proposal
    }

    /// Points per sweep as given.
    pub fn points_per_sweep(&self) -> &[usize] {
        &self.points_per_sweep
    }

    /// Beams per sweep after down-sampling.
    pub fn beams_per_sweep(&self) -> &[usize] {
        &self.beams_per_sweep
    }

    /// The configuration in use.
    pub fn config(&self) -> &Config {
        &self.cfg
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn scan_drops_near_points_caps_beams_and_marks_far_returns() {
        let m = Map3dConfig {
            max_beams: 100,
            max_range: 10.0,
            ..Map3dConfig::default()
        };
        let mut pts = vec![[0.1, 0.0, 0.0], [0.0, 0.3, 0.0]];
        for i in 0..1000 {
            let a = i as f32 * 0.01;
            pts.push([3.0 * a.cos(), 3.0 * a.sin(), 0.5]);
        }
        pts.push([20.0, 0.0, 0.0]);
        let s = sweep_to_scan(&pts, &m);
        assert!(
            s.beams.len() <= 100 && s.beams.len() >= 50,
            "{}",
            s.beams.len()
        );
        for b in &s.beams {
            let n = b.dir.iter().map(|d| d * d).sum::<f64>().sqrt();
            assert!((n - 1.0).abs() < 1e-9);
            assert!(b.range >= 0.5);
        }
        let few = sweep_to_scan(&[[20.0, 0.0, 0.0], [0.2, 0.0, 0.0]], &m);
        assert_eq!(few.beams.len(), 1);
        assert!(few.beams[0].no_return && few.beams[0].range == 10.0);
        // Deterministic.
        assert_eq!(sweep_to_scan(&pts, &m).beams, s.beams);
    }

    #[test]
    fn a_sweep_with_no_usable_point_is_an_error_not_a_step() {
        let mut slam = Slam3d::new(Config::default()).unwrap();
        let err = slam
            .add_sweep(0.0, None, &[[0.1, 0.0, 0.0], [f32::NAN, 0.0, 0.0]])
            .unwrap_err();
        assert!(err.to_string().contains("no usable points"), "{err}");
        assert_eq!(slam.sweeps(), 0);
    }
}
