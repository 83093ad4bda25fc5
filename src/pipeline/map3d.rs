//! The 3-D mapping run: a directory of laser sweeps in, a run folder out.
//!
//! Per sweep (file-name order, see [`crate::io::sweeps::list_sweeps`], or a
//! bag's clouds, see [`SweepSource`]):
//! 1. the points become a [`Scan<3, Pose3>`] ([`sweep_to_scan`]): one beam per
//!    sensor-frame point (direction `p/|p|`, range `|p|`), points closer than
//!    `map3d.min_range` (0.5 m) dropped, down-sampled to one beam per
//!    `map3d.beam_voxel` (0.2 m) voxel and then by an even stride to at most
//!    **`map3d.max_beams` = 3000 beams** by default; returns beyond
//!    `map3d.max_range` (60 m) are "no return" beams traced to that range;
//! 2. the prior motion since the previous sweep comes from `--poses` (TUM or
//!    KITTI, pose *i* for sweep *i*), else from the sweeps' own priors (3DTK
//!    `.pose`, PCD `VIEWPOINT`) when both sweeps carry one, else constant
//!    velocity (the best particle's last motion);
//! 3. the proposal ([`crate::proposal`]) aligns the sweep to the best
//!    particle's recent sweeps starting from `best · prior`, and the filter
//!    samples around the aligned pose: `delta = best⁻¹ · aligned` goes to
//!    [`ParticleFilter::step`] with the [`AlignedGaussian6dModel`], which
//!    draws from the product of the alignment's Gaussian (covariance
//!    × `map3d.icp_covariance_scale`) and the 6-DoF [`Gaussian6dModel`]
//!    (the motion model alone when the alignment failed);
//! 4. the particles are weighed with the penetration model on the voxel
//!    DP-map (`map3d.voxel_size` = 0.2 m, σ² = `map3d.variance`), resampled,
//!    and their maps updated — the same generic filter as 2-D.
//!
//! The robot frame is the sensor frame (sweeps carry no mounting offset).
//! The map frame is the frame of the first prior pose when there is a prior
//! (pose file or the first sweep's own pose), else the first sensor frame.
//!
//! Outputs (written only at the end, each atomically): `map.ply` (the best
//! particle's occupied voxels: it has hits there and a density of at least
//! `map3d.occupied_density` = 0.5 stops/m), `trajectory.tum` (one line per
//! sweep; time from the pose file, else the sweep index), `run.json`
//! ([`Map3dSummary`]), `config.toml` and, on request, `points.ply` (the raw
//! points registered with the final trajectory, one per `map3d.points_voxel`
//! voxel; the sweeps are read a second time for it, so memory stays bounded).

use crate::config::{Config, Map3dConfig};
use crate::filter::{ParticleFilter, StepStats};
use crate::geometry::{Pose, Pose3};
use crate::io::bag::sweeps3d::SweepSource;
use crate::io::ply::{VoxelPoint, write_points_ply, write_voxel_ply};
use crate::io::tum::{read_poses, write_tum};
use crate::laser_model::LaserModel;
use crate::motion_model::{AlignedGaussian6dModel, Gaussian6dModel, ProposalNoise};
use crate::proposal::{Proposal, ProposalParams};
use crate::raycast::cell_centre;
use crate::scan::{Beam, Scan};
use crate::{Error, Result};
use nalgebra::Vector3;
use rustc_hash::FxHashMap;
use serde::Serialize;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// Particles of a 3-D run when neither the command line nor a config file
/// sets them: 3-D steps cost ~10× a 2-D step per particle (3000 beams through
/// voxels). The proposal samples from the scan matcher's Gaussian fused with
/// the motion noise, so the samples lie within the matcher's uncertainty and
/// most of them survive culling: a step costs about particles × samples full
/// traces. On three simulated sequences (seeds 1–3) 20 particles were as
/// accurate as 30 (ATE 6–11 mm) at two thirds of the time.
pub const DEFAULT_PARTICLES_3D: usize = 20;

/// Options of a 3-D run beyond the configuration.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Map3dOptions {
    /// Also write `points.ply` (registered raw points).
    pub points: bool,
    /// Where scan likelihoods are computed.
    pub backend: crate::backend::Backend,
}

/// Where the prior motion of the run came from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum PriorSource {
    /// A TUM/KITTI pose file.
    PoseFile,
    /// The sweeps' own poses (3DTK `.pose`, PCD `VIEWPOINT`).
    SweepPoses,
    /// None: constant velocity.
    ConstantVelocity,
}

/// What a 3-D run did; written as `run.json`.
#[derive(Debug, Clone, Serialize)]
pub struct Map3dSummary {
    /// dpslam version.
    pub version: String,
    /// Input directory.
    pub input: PathBuf,
    /// Pose file used as prior, if any.
    pub poses: Option<PathBuf>,
    /// Where the prior motion came from (for sweeps without their own pose,
    /// constant velocity fills in).
    pub prior: PriorSource,
    /// Sweeps in the input (= lines of `trajectory.tum`).
    pub sweeps: usize,
    /// Particles.
    pub particles: usize,
    /// Samples per particle.
    pub samples_per_particle: usize,
    /// Points per sweep as read (no-return points already dropped).
    pub points_per_sweep: Vec<usize>,
    /// Beams per sweep after down-sampling.
    pub beams_per_sweep: Vec<usize>,
    /// Mean of `beams_per_sweep`.
    pub mean_beams_per_sweep: f64,
    /// Voxel edge, m.
    pub voxel_size_m: f64,
    /// Usable range, m.
    pub max_range_m: f64,
    /// Wall-clock time of the run, s.
    pub wall_time_s: f64,
    /// Mean wall time per sweep after the first (proposal + filter step), s.
    pub time_per_sweep_s: f64,
    /// Mean time of the proposal (ICP) per sweep, s.
    pub proposal_time_per_sweep_s: f64,
    /// Mean time of the filter step per sweep, s.
    pub filter_time_per_sweep_s: f64,
    /// Sweeps whose alignment failed (the prior was used as is).
    pub proposal_fallbacks: usize,
    /// Mean correction of the proposal over the prior: translation, m.
    pub mean_correction_m: f64,
    /// Mean correction of the proposal over the prior: rotation, degrees.
    pub mean_correction_deg: f64,
    /// Peak resident memory, MiB.
    pub peak_memory_mib: Option<f64>,
    /// Entries in the DP-map at the end.
    pub map_entries: usize,
    /// Approximate DP-map size, MiB.
    pub map_memory_mib: f64,
    /// Voxels written to `map.ply`.
    pub occupied_voxels: usize,
    /// Points written to `points.ply` (0 without `--points`).
    pub registered_points: usize,
    /// Live ancestry nodes at the end.
    pub tree_nodes: usize,
    /// Mean number of samples surviving the quick culling passes.
    pub mean_after_quick: f64,
    /// Mean number of samples surviving all culling.
    pub mean_after_full: f64,
    /// Scan-likelihood backend used: "cpu", or "gpu", its precision and
    /// adapter, or "cpu (auto: why no GPU)".
    pub backend: String,
    /// The GPU backend's traffic (map bytes uploaded against re-uploading
    /// the whole map at every step); absent on the CPU.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub gpu_transfers: Option<crate::scorer::Transfers>,
    /// Seed.
    pub seed: u64,
    /// Worker threads.
    pub threads: usize,
}

/// Checks the 3-D settings.
pub fn validate_map3d(m: &Map3dConfig) -> Result<()> {
    let bad = |s: &str| Err(Error::Config(format!("map3d.{s}")));
    let pos = |v: f64| v.is_finite() && v > 0.0;
    let nonneg = |v: f64| v.is_finite() && v >= 0.0;
    if !pos(m.voxel_size) {
        return bad("voxel_size must be positive");
    }
    if m.max_beams == 0 {
        return bad("max_beams must be at least 1");
    }
    if !pos(m.max_range) || !nonneg(m.min_range) || m.min_range >= m.max_range {
        return bad("max_range must be positive and above min_range ≥ 0");
    }
    if !pos(m.beam_voxel)
        || !pos(m.variance)
        || !pos(m.icp_voxel)
        || !pos(m.icp_max_distance)
        || !pos(m.points_voxel)
    {
        return bad(
            "beam_voxel, variance, icp_voxel, icp_max_distance and points_voxel must be positive",
        );
    }
    if !nonneg(m.occupied_density) {
        return bad("occupied_density must be ≥ 0");
    }
    if !nonneg(m.icp_covariance_scale) {
        return bad("icp_covariance_scale must be ≥ 0");
    }
    let noise = [
        m.trans_std_per_m,
        m.trans_std_per_rad,
        m.min_trans_std,
        m.rot_std_per_m,
        m.rot_std_per_rad,
        m.min_rot_std,
    ];
    if !noise.iter().all(|&v| nonneg(v)) {
        return bad("motion noise parameters must be ≥ 0");
    }
    if m.local_map_sweeps == 0
        || m.icp_levels == 0
        || m.icp_iterations == 0
        || m.icp_max_points == 0
    {
        return bad(
            "local_map_sweeps, icp_levels, icp_iterations and icp_max_points must be at least 1",
        );
    }
    Ok(())
}

/// Converts one sweep's sensor-frame points (m) into the filter's scan (see
/// the module docs for the down-sampling). Deterministic: voxels keep their
/// first point in input order and the stride is even.
pub fn sweep_to_scan(points: &[[f32; 3]], m: &Map3dConfig) -> Scan<3, Pose3> {
    let mut seen: FxHashMap<[i32; 3], ()> = FxHashMap::default();
    let mut kept: Vec<[f64; 3]> = Vec::new();
    for p in points {
        let v = [p[0] as f64, p[1] as f64, p[2] as f64];
        let r = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
        if !r.is_finite() || r < m.min_range {
            continue;
        }
        let k = [
            (v[0] / m.beam_voxel).floor() as i32,
            (v[1] / m.beam_voxel).floor() as i32,
            (v[2] / m.beam_voxel).floor() as i32,
        ];
        if seen.insert(k, ()).is_none() {
            kept.push(v);
        }
    }
    let stride = kept.len().div_ceil(m.max_beams).max(1);
    let beams = kept
        .iter()
        .step_by(stride)
        .map(|v| {
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

/// The best particle's occupied voxels (see the module docs for "occupied").
pub fn occupied_voxels(filter: &ParticleFilter<3, Pose3>, min_density: f64) -> Vec<VoxelPoint> {
    let map = filter.map();
    let node = filter.particles()[filter.best_index()].node;
    let mut view = map.view(filter.numbering(), node);
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

/// Runs 3-D DP-SLAM on the sweeps of `input` and writes the run folder `out`.
/// `poses` (TUM or KITTI) gives one prior pose per sweep, in order.
pub fn run_map3d(
    input: &Path,
    out: &Path,
    cfg: &Config,
    poses: Option<&Path>,
) -> Result<Map3dSummary> {
    run_map3d_with(input, out, cfg, poses, &Map3dOptions::default())
}

/// [`run_map3d`] with extra output options.
pub fn run_map3d_with(
    input: &Path,
    out: &Path,
    cfg: &Config,
    poses: Option<&Path>,
    opts: &Map3dOptions,
) -> Result<Map3dSummary> {
    cfg.validate()?;
    let m = &cfg.map3d;
    validate_map3d(m)?;
    let start = Instant::now();
    let paths = SweepSource::open(input, &cfg.bag)?;
    let prior_file = match poses {
        Some(p) => {
            let v = read_poses(p)?;
            if v.len() != paths.len() {
                return Err(Error::in_file(
                    p,
                    format!(
                        "{} poses for {} sweeps in {}: the pose file needs one pose per sweep",
                        v.len(),
                        paths.len(),
                        input.display()
                    ),
                ));
            }
            Some(v)
        }
        None => None,
    };
    let bar = super::progress_bar(paths.len() as u64, "map3d");
    let mut laser_cfg = cfg.laser.clone();
    laser_cfg.variance = m.variance;
    let laser = LaserModel::new(&laser_cfg, m.voxel_size, m.max_range);
    let mut proposal = Proposal::new(ProposalParams::from_config(m));

    let first = paths.read(0)?;
    let scan0 = sweep_to_scan(&first.points, m);
    let initial = match (&prior_file, first.prior) {
        (Some(v), _) => v[0].pose,
        (None, Some(p)) => p,
        (None, None) => Pose3::identity(),
    };
    let motion = Gaussian6dModel::from_config(m);
    let noise = ProposalNoise::default();
    let mut filter = ParticleFilter::new(
        cfg.filter.clone(),
        laser,
        Box::new(AlignedGaussian6dModel {
            base: motion.clone(),
            noise: noise.clone(),
        }),
        cfg.seed,
        initial,
        &scan0,
        0,
    );
    filter.set_map_update(&cfg.map);
    let (scorer, backend_used) = crate::backend::make_scorer::<3, Pose3>(opts.backend)?;
    filter.set_scorer(scorer);
    proposal.push(0, proposal.prepare(&first.points));
    let mut points_per_sweep = vec![first.points.len()];
    let mut beams_per_sweep = vec![scan0.beams.len()];
    let mut prev_prior = first.prior;
    let mut used_sweep_prior = false;
    let mut velocity = Pose3::identity();
    let mut stats: Vec<StepStats> = Vec::new();
    let (mut t_prop, mut t_filt) = (0.0, 0.0);
    let (mut fallbacks, mut corr_t, mut corr_r) = (0usize, 0.0, 0.0);
    drop(first);
    bar.inc(1);
    let debug = std::env::var_os("DPSLAM_DEBUG").is_some();

    for i in 1..paths.len() {
        let sweep = paths.read(i)?;
        let scan = sweep_to_scan(&sweep.points, m);
        points_per_sweep.push(sweep.points.len());
        beams_per_sweep.push(scan.beams.len());
        let prior_delta = match (&prior_file, prev_prior, sweep.prior) {
            (Some(v), _, _) => v[i - 1].pose.inverse() * v[i].pose,
            (None, Some(a), Some(b)) => {
                used_sweep_prior = true;
                a.inverse() * b
            }
            _ => velocity,
        };
        prev_prior = sweep.prior;
        let best = filter.particles()[filter.best_index()].pose;
        // `compose` keeps the quaternions unit along the sweep-to-sweep chain.
        let guess = best.compose(&prior_delta);

        let t0 = Instant::now();
        let prepared = proposal.prepare(&sweep.points);
        let oldest = proposal.indices().next().unwrap_or(0);
        let lineage = filter.best_trajectory();
        let recent: FxHashMap<u32, Pose3> = lineage
            .iter()
            .rev()
            .take_while(|s| s.scan >= oldest)
            .map(|s| (s.scan, s.pose))
            .collect();
        let alignment = proposal.align(&prepared, &guess, |j| recent.get(&j).copied());
        let aligned = match &alignment {
            Some(a) => a.pose,
            None => {
                fallbacks += 1;
                guess
            }
        };
        let corr = guess.inverse() * aligned;
        corr_t += corr.translation.vector.norm();
        corr_r += corr.rotation.angle().to_degrees();
        t_prop += t0.elapsed().as_secs_f64();

        let t1 = Instant::now();
        let delta = best.inverse().compose(&aligned);
        // Sample from the scan matcher's Gaussian fused with the motion
        // noise (see AlignedGaussian6dModel); without an alignment, or with
        // the fusion switched off, the motion noise alone.
        let fused = alignment
            .filter(|_| m.icp_covariance_scale > 0.0)
            .and_then(|a| motion.fuse(&delta, &(a.covariance * m.icp_covariance_scale)));
        noise.set(fused.as_ref());
        stats.push(filter.step(&delta, &scan, i as u32));
        t_filt += t1.elapsed().as_secs_f64();
        let new_best = filter.particles()[filter.best_index()].pose;
        velocity = best.inverse().compose(&new_best);
        if debug {
            let show = |p: &Pose3| {
                let (r, pi, y) = p.rotation.euler_angles();
                let t = p.translation.vector;
                format!(
                    "[{:.3} {:.3} {:.3} | {:.2} {:.2} {:.2} deg]",
                    t.x,
                    t.y,
                    t.z,
                    r.to_degrees(),
                    pi.to_degrees(),
                    y.to_degrees()
                )
            };
            eprintln!(
                "map3d sweep {i}: guess {} aligned {} best {} quick {} full {} ll {:.1}",
                show(&guess),
                show(&aligned),
                show(&new_best),
                stats.last().map_or(0, |s| s.after_quick),
                stats.last().map_or(0, |s| s.after_full),
                stats.last().map_or(0.0, |s| s.best_log_likelihood)
            );
        }
        proposal.push(i as u32, prepared);
        bar.inc(1);
    }
    bar.finish_and_clear();

    let trajectory = filter.best_trajectory();
    if trajectory.len() != paths.len() {
        return Err(Error::Invalid(format!(
            "internal: {} poses for {} sweeps",
            trajectory.len(),
            paths.len()
        )));
    }
    let mut rows = Vec::with_capacity(trajectory.len());
    for (i, st) in trajectory.iter().enumerate() {
        if !Pose::<3>::is_finite(&st.pose) {
            return Err(Error::Invalid(format!(
                "non-finite pose at sweep {i} ({})",
                paths.describe(i)
            )));
        }
        let t = prior_file
            .as_ref()
            .map_or(paths.stamp(i).unwrap_or(i as f64), |v| v[i].t);
        rows.push((t, Pose::<3>::to_tum(&st.pose)));
    }
    let voxels = occupied_voxels(&filter, m.occupied_density);
    let points = if opts.points {
        Some(registered_points(
            &paths,
            &trajectory.iter().map(|s| s.pose).collect::<Vec<_>>(),
            m,
        )?)
    } else {
        None
    };

    let steps = stats.len().max(1) as f64;
    let wall = start.elapsed().as_secs_f64();
    let summary = Map3dSummary {
        version: env!("CARGO_PKG_VERSION").to_string(),
        input: input.to_path_buf(),
        poses: poses.map(Path::to_path_buf),
        prior: if prior_file.is_some() {
            PriorSource::PoseFile
        } else if used_sweep_prior {
            PriorSource::SweepPoses
        } else {
            PriorSource::ConstantVelocity
        },
        sweeps: paths.len(),
        particles: cfg.filter.particles,
        samples_per_particle: cfg.filter.samples_per_particle,
        mean_beams_per_sweep: beams_per_sweep.iter().sum::<usize>() as f64
            / beams_per_sweep.len() as f64,
        points_per_sweep,
        beams_per_sweep,
        voxel_size_m: m.voxel_size,
        max_range_m: m.max_range,
        wall_time_s: wall,
        time_per_sweep_s: (t_prop + t_filt) / steps,
        proposal_time_per_sweep_s: t_prop / steps,
        filter_time_per_sweep_s: t_filt / steps,
        proposal_fallbacks: fallbacks,
        mean_correction_m: corr_t / steps,
        mean_correction_deg: corr_r / steps,
        peak_memory_mib: super::peak_memory_mib(),
        map_entries: filter.map().entry_count(),
        map_memory_mib: filter.map().memory_bytes() as f64 / (1024.0 * 1024.0),
        occupied_voxels: voxels.len(),
        registered_points: points.as_ref().map_or(0, Vec::len),
        tree_nodes: filter.tree().len(),
        mean_after_quick: stats.iter().map(|s| s.after_quick as f64).sum::<f64>() / steps,
        mean_after_full: stats.iter().map(|s| s.after_full as f64).sum::<f64>() / steps,
        backend: backend_used,
        gpu_transfers: filter.scorer().transfers(),
        seed: cfg.seed,
        threads: rayon::current_num_threads(),
    };

    super::create_out_dir(out)?;
    write_voxel_ply(&out.join("map.ply"), &voxels)?;
    if let Some(p) = &points {
        write_points_ply(&out.join("points.ply"), p)?;
    }
    write_tum(&out.join("trajectory.tum"), &rows)?;
    super::write_atomic(&out.join("config.toml"), cfg.to_toml().as_bytes())?;
    super::write_json(&out.join("run.json"), &summary)?;
    Ok(summary)
}

/// Re-reads the sweeps and registers their points with `poses` (one per
/// sweep), keeping the first point per `points_voxel` voxel in the map frame.
fn registered_points(
    paths: &SweepSource,
    poses: &[Pose3],
    m: &Map3dConfig,
) -> Result<Vec<[f32; 3]>> {
    let mut seen: FxHashMap<[i32; 3], ()> = FxHashMap::default();
    let mut out = Vec::new();
    for (i, pose) in poses.iter().enumerate() {
        let sweep = paths.read(i)?;
        for p in &sweep.points {
            let v = Vector3::new(p[0] as f64, p[1] as f64, p[2] as f64);
            let r = v.norm();
            if r < m.min_range || r > m.max_range {
                continue;
            }
            let w = pose * nalgebra::Point3::from(v);
            let k = [
                (w.x / m.points_voxel).floor() as i32,
                (w.y / m.points_voxel).floor() as i32,
                (w.z / m.points_voxel).floor() as i32,
            ];
            if seen.insert(k, ()).is_none() {
                out.push([w.x as f32, w.y as f32, w.z as f32]);
            }
        }
    }
    Ok(out)
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
    fn bad_settings_are_config_errors() {
        let m = Map3dConfig {
            voxel_size: 0.0,
            ..Map3dConfig::default()
        };
        assert!(
            validate_map3d(&m)
                .unwrap_err()
                .to_string()
                .contains("voxel_size")
        );
        assert!(validate_map3d(&Map3dConfig::default()).is_ok());
    }
}
