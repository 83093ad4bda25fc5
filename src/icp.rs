//! 3-D scan registration for the proposal of 3-D DP-SLAM (dissertation
//! ch. 11): before the filter samples, each new sweep is aligned to the map
//! built so far, so that the particles are drawn around a pose that explains
//! the sweep instead of around the raw prior (odometry, pose file or
//! constant velocity); see [`crate::proposal::Proposal::Matched`].
//!
//! Alignment is multi-resolution point-to-plane ICP against a [`LocalMap`]:
//! the down-sampled points of the best particle's most recent sweeps, put in
//! the map frame with that particle's poses. Each level has a voxel size
//! (centroid down-sampling of map and sweep alike) and a correspondence
//! radius; a voxel hash of that radius finds neighbours (the 27 cells around
//! a point), and the map points' normals come from the covariance of their
//! neighbours. Coarse levels have large radii so that motion the prior does
//! not explain (1 m and 10° and more) is pulled in; fine levels refine it.
//!
//! Everything here is deterministic: points are processed in input order and
//! per-point terms are computed in parallel but summed in order, so the
//! result does not depend on the thread count. Memory is bounded by the
//! window of sweeps, not by the length of the run.

use crate::config::Map3dConfig;
use crate::geometry::Pose3;
use crate::points;
use glam::Vec3A;
use nalgebra::{Matrix3, Matrix6, SymmetricEigen, Translation3, UnitQuaternion, Vector3, Vector6};
use rayon::prelude::*;
use rustc_hash::FxHashMap;
use std::collections::VecDeque;

/// Fewer correspondences than this and an ICP level is not trusted.
const MIN_CORRESPONDENCES: usize = 30;
/// A neighbourhood is a plane when its smallest covariance eigenvalue is at
/// most this fraction of the sum (flat enough for a point-to-plane residual).
const PLANARITY: f64 = 0.08;
/// ... and its middle eigenvalue at least this fraction (not a line).
const LINEARITY: f64 = 0.05;
/// Fewest neighbours for a normal.
const MIN_NORMAL_NEIGHBOURS: usize = 5;
/// ICP stops a level when the update is below this (rad and m).
const CONVERGED: f64 = 1e-5;
/// Cauchy scale in units of the residual std for 95 % asymptotic efficiency
/// under Gaussian noise (Holland & Welsch 1977).
const CAUCHY_95: f64 = 2.385;
/// Smallest Cauchy scale, m: about a lidar's range noise, so that exact
/// synthetic data (residual spread → 0) keeps a usable weight.
const MIN_SCALE: f64 = 0.01;

/// Parameters of the registration, from [`Map3dConfig`].
#[derive(Debug, Clone, PartialEq)]
pub struct IcpParams {
    /// Sweeps kept in the local map.
    pub window: usize,
    /// ICP levels, coarse to fine: `(voxel m, correspondence radius m)`.
    pub levels: Vec<(f64, f64)>,
    /// Gauss-Newton iterations per level, at most.
    pub iterations: usize,
    /// Source points per level, at most.
    pub max_points: usize,
}

impl IcpParams {
    /// The parameters of `cfg`: `icp_levels` levels whose voxel doubles from
    /// `icp_voxel` (finest) and whose radius halves from `icp_max_distance`
    /// (coarsest); a radius never falls below 2.5 voxels, so normals have
    /// neighbours.
    pub fn from_config(cfg: &Map3dConfig) -> Self {
        let n = cfg.icp_levels.max(1);
        let levels = (0..n)
            .map(|i| {
                let coarse = (n - 1 - i) as i32;
                let voxel = cfg.icp_voxel * 2f64.powi(coarse);
                let radius = (cfg.icp_max_distance / 2f64.powi(i as i32)).max(2.5 * voxel);
                (voxel, radius)
            })
            .collect();
        Self {
            window: cfg.local_map_sweeps.max(1),
            levels,
            iterations: cfg.icp_iterations.max(1),
            max_points: cfg.icp_max_points.max(MIN_CORRESPONDENCES),
        }
    }
}

/// The voxel of edge `size` containing `p`.
#[inline]
fn voxel_of(p: &Vector3<f64>, size: f64) -> [i32; 3] {
    [
        (p.x / size).floor() as i32,
        (p.y / size).floor() as i32,
        (p.z / size).floor() as i32,
    ]
}

/// `source` (sensor frame, m) down-sampled to voxels of edge `size` m on the
/// f32 point path, as f64 for the alignment's algebra.
fn downsample(source: &[Vec3A], size: f64) -> Vec<Vector3<f64>> {
    points::voxel_downsample(source.iter().copied(), size as f32)
        .into_iter()
        .map(points::to_f64)
        .collect()
}

/// Keeps at most `max` points with an even stride (deterministic).
pub(crate) fn thin<T: Copy>(v: &[T], max: usize) -> Vec<T> {
    let stride = v.len().div_ceil(max.max(1)).max(1);
    v.iter().step_by(stride).copied().collect()
}

/// One resolution of the local map: points, their normals (where the
/// neighbourhood is planar) and a voxel hash of cell = correspondence radius.
#[derive(Debug, Clone)]
struct Level {
    voxel: f64,
    radius: f64,
    points: Vec<Vector3<f64>>,
    normals: Vec<Option<Vector3<f64>>>,
    grid: FxHashMap<[i32; 3], Vec<u32>>,
}

impl Level {
    fn build(points: Vec<Vector3<f64>>, voxel: f64, radius: f64) -> Self {
        let mut grid: FxHashMap<[i32; 3], Vec<u32>> = FxHashMap::default();
        for (i, p) in points.iter().enumerate() {
            grid.entry(voxel_of(p, radius)).or_default().push(i as u32);
        }
        let mut level = Self {
            voxel,
            radius,
            points,
            normals: Vec::new(),
            grid,
        };
        // Normals from neighbours within half the radius: a local plane fit
        // that stays local at coarse levels too.
        let r_normal = (0.5 * radius).max(1.5 * voxel);
        level.normals = level
            .points
            .par_iter()
            .map(|p| level.normal_at(p, r_normal))
            .collect();
        level
    }

    /// Calls `f` with the index of every point in the 27 cells around `p`.
    #[inline]
    fn for_near(&self, p: &Vector3<f64>, mut f: impl FnMut(usize)) {
        let c = voxel_of(p, self.radius);
        for dx in -1..=1 {
            for dy in -1..=1 {
                for dz in -1..=1 {
                    if let Some(list) = self.grid.get(&[c[0] + dx, c[1] + dy, c[2] + dz]) {
                        for &i in list {
                            f(i as usize);
                        }
                    }
                }
            }
        }
    }

    fn normal_at(&self, p: &Vector3<f64>, r: f64) -> Option<Vector3<f64>> {
        let r2 = r * r;
        let mut n = 0usize;
        let mut sum = Vector3::zeros();
        let mut outer = Matrix3::zeros();
        self.for_near(p, |i| {
            let q = self.points[i];
            if (q - p).norm_squared() <= r2 {
                n += 1;
                sum += q;
                outer += q * q.transpose();
            }
        });
        if n < MIN_NORMAL_NEIGHBOURS {
            return None;
        }
        let mean = sum / n as f64;
        let cov = outer / n as f64 - mean * mean.transpose();
        let eig = SymmetricEigen::new(cov);
        let mut order = [0usize, 1, 2];
        order.sort_by(|&a, &b| eig.eigenvalues[a].total_cmp(&eig.eigenvalues[b]));
        let l = order.map(|i| eig.eigenvalues[i].max(0.0));
        let total = l[0] + l[1] + l[2];
        // Flat (small l0) but not a line: one lidar ring alone has two small
        // eigenvalues and no defined normal.
        if total <= 0.0 || l[0] > PLANARITY * total || l[1] < LINEARITY * total {
            return None;
        }
        let imin = order[0];
        Some(eig.eigenvectors.column(imin).into_owned())
    }

    /// The nearest map point to `p` within the radius, if any.
    fn nearest(&self, p: &Vector3<f64>) -> Option<usize> {
        let mut best = (self.radius * self.radius, None);
        self.for_near(p, |i| {
            let d = (self.points[i] - p).norm_squared();
            if d < best.0 {
                best = (d, Some(i));
            }
        });
        best.1
    }
}

/// The map the proposal aligns sweeps to: recent sweeps of one particle at
/// every ICP resolution, in the map frame.
#[derive(Debug, Clone)]
pub struct LocalMap {
    levels: Vec<Level>,
}

impl LocalMap {
    /// Builds the map from `(pose, points)` pairs: sensor-frame points (m)
    /// and the pose mapping them into the map frame. The clouds are placed
    /// and down-sampled on the f32 point path ([`crate::points`]).
    pub fn build(clouds: &[(Pose3, &[Vec3A])], params: &IcpParams) -> Self {
        let placed: Vec<Vec3A> = clouds
            .iter()
            .flat_map(|(pose, pts)| {
                let a = points::affine(pose);
                pts.iter().map(move |p| a.transform_point3a(*p))
            })
            .collect();
        let levels = params
            .levels
            .iter()
            .map(|&(voxel, radius)| {
                let pts = points::voxel_downsample(placed.iter().copied(), voxel as f32)
                    .into_iter()
                    .map(points::to_f64)
                    .collect();
                Level::build(pts, voxel, radius)
            })
            .collect();
        Self { levels }
    }

    /// Points at the finest level.
    pub fn len(&self) -> usize {
        self.levels.last().map_or(0, |l| l.points.len())
    }

    /// The map has no points.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

/// The result of aligning one sweep.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Alignment {
    /// Aligned sensor pose in the map frame.
    pub pose: Pose3,
    /// Correspondences at the finest level in the last iteration.
    pub inliers: usize,
    /// Root mean square point-to-plane residual of those, m.
    pub rms: f64,
    /// Gauss-Newton iterations over all levels.
    pub iterations: usize,
    /// Covariance of the aligned pose as a right (body-frame) perturbation
    /// `pose · exp([ω, t])`, ω in rad and t in m, sensor frame.
    pub covariance: Matrix6<f64>,
}

/// `exp` of a twist `[ω, t]` applied on the left: rotation by the small-angle
/// vector ω (rad) and translation t (m), both in the map frame.
fn left_update(pose: &Pose3, xi: &Vector6<f64>) -> Pose3 {
    let w = Vector3::new(xi[0], xi[1], xi[2]);
    let t = Vector3::new(xi[3], xi[4], xi[5]);
    let step = Pose3::from_parts(Translation3::from(t), UnitQuaternion::from_scaled_axis(w));
    step * pose
}

/// The matrix taking a left (map-frame) twist `[ω, t]` at `pose` to the
/// equal right (body-frame) twist: `exp(ξ)·T = T·exp(A·ξ)` to first order,
/// `A = [[Rᵀ, 0], [−Rᵀ[p]×, Rᵀ]]` for `T = (R, p)`.
fn body_adjoint(pose: &Pose3) -> Matrix6<f64> {
    let rt = pose.rotation.to_rotation_matrix().into_inner().transpose();
    let p = pose.translation.vector;
    let mut a = Matrix6::zeros();
    a.fixed_view_mut::<3, 3>(0, 0).copy_from(&rt);
    a.fixed_view_mut::<3, 3>(3, 3).copy_from(&rt);
    a.fixed_view_mut::<3, 3>(3, 0)
        .copy_from(&(-rt * p.cross_matrix()));
    a
}

/// The outcome of Gauss-Newton on one level.
struct LevelFit {
    pose: Pose3,
    /// Correspondences and their rms point-to-plane residual, m, in the
    /// last iteration.
    last: (usize, f64),
    /// Information of the pose (normal matrix over the residual variance).
    info: Matrix6<f64>,
    iterations: usize,
}

/// Point-to-plane Gauss-Newton of `src` (sensor frame) against one level
/// from `pose`, at most `iterations` iterations; `None` when an iteration
/// finds too few correspondences.
fn fit_level(
    level: &Level,
    src: &[Vector3<f64>],
    mut pose: Pose3,
    iterations: usize,
) -> Option<LevelFit> {
    let mut sigma: Option<f64> = None;
    let mut last = (0usize, 0.0f64);
    let mut info = Matrix6::<f64>::zeros();
    let mut done = 0;
    for it in 0..iterations {
        done += 1;
        // Residual scale of the robust (Cauchy) weight: the level's
        // radius, annealed, at the first iterations; from the second on
        // at most the spread of the last residuals, 2.385·σ̂ with σ̂ =
        // 1.4826·median|r| (the Cauchy constant of 95 % efficiency under
        // Gaussian noise, and a spread that outliers do not inflate).
        // A fixed floor such as the voxel size gives mis-matched points
        // (edges, clutter) near-full weight once the residuals of the
        // true matches are centimetres, and biases the pose by as much.
        let anneal = level.radius / (1.0 + it as f64);
        let scale = match sigma {
            Some(s) => anneal.min((CAUCHY_95 * s).max(MIN_SCALE)),
            None => anneal,
        };
        let terms: Vec<Option<(Vector6<f64>, f64, f64)>> = src
            .par_iter()
            .map(|p| {
                let q = pose * nalgebra::Point3::from(*p);
                let q = q.coords;
                let j = level.nearest(&q)?;
                let n = level.normals[j]?;
                let r = n.dot(&(q - level.points[j]));
                let jac = q.cross(&n);
                let row = Vector6::new(jac.x, jac.y, jac.z, n.x, n.y, n.z);
                let w = 1.0 / (1.0 + (r / scale) * (r / scale));
                Some((row, r, w))
            })
            .collect();
        let mut h = Matrix6::<f64>::zeros();
        let mut g = Vector6::<f64>::zeros();
        let mut count = 0usize;
        let mut sq = 0.0;
        let mut abs_r: Vec<f64> = Vec::with_capacity(src.len());
        for (row, r, w) in terms.into_iter().flatten() {
            abs_r.push(r.abs());
            h += row * row.transpose() * w;
            g += row * (w * r);
            count += 1;
            sq += r * r;
        }
        if count < MIN_CORRESPONDENCES {
            return None;
        }
        last = (count, (sq / count as f64).sqrt());
        let mid = abs_r.len() / 2;
        let med = *abs_r.select_nth_unstable_by(mid, |a, b| a.total_cmp(b)).1;
        let s = (1.4826 * med).max(MIN_SCALE / CAUCHY_95);
        sigma = Some(s);
        // Information of the pose: the Gauss-Newton normal matrix over
        // the residual variance (before damping).
        info = h / (s * s);
        // Light damping keeps directions without planes (a corridor's
        // axis) from jumping.
        let damping = 1e-6 * h.trace().max(1e-12);
        for i in 0..6 {
            h[(i, i)] += damping;
        }
        let xi = h.cholesky()?.solve(&(-g));
        pose = left_update(&pose, &xi);
        if xi.norm() < CONVERGED {
            break;
        }
    }
    Some(LevelFit {
        pose,
        last,
        info,
        iterations: done,
    })
}

/// How well `src` (sensor frame) placed at `pose` agrees with one level:
/// the sum over the points of a Cauchy weight of their point-to-plane
/// residual at the scale of the level's voxel (0 for a point with no
/// planar neighbour within the radius). Counts the points that the map
/// explains; a wrong placement explains few.
fn consensus(level: &Level, src: &[Vector3<f64>], pose: &Pose3) -> f64 {
    let scale = level.voxel;
    let w: Vec<f64> = src
        .par_iter()
        .map(|p| {
            let q = (pose * nalgebra::Point3::from(*p)).coords;
            let Some(j) = level.nearest(&q) else {
                return 0.0;
            };
            let Some(n) = level.normals[j] else {
                return 0.0;
            };
            let r = n.dot(&(q - level.points[j])) / scale;
            let d2 = (q - level.points[j]).norm_squared() / (level.radius * level.radius);
            (1.0 - d2).max(0.0) / (1.0 + r * r)
        })
        .collect();
    w.iter().sum()
}

/// Aligns `source` (sensor-frame points, m) to `map` starting from `initial`
/// (sensor pose in the map frame). Returns `None` when a level finds too few
/// correspondences to be trusted (the caller keeps its prior then).
pub fn align(
    map: &LocalMap,
    source: &[Vec3A],
    initial: &Pose3,
    params: &IcpParams,
) -> Option<Alignment> {
    let mut pose = *initial;
    let mut iterations = 0;
    let mut last = (0usize, 0.0f64);
    let mut info = Matrix6::<f64>::zeros();
    for level in &map.levels {
        let src = thin(&downsample(source, level.voxel), params.max_points);
        let fit = fit_level(level, &src, pose, params.iterations)?;
        pose = fit.pose;
        last = fit.last;
        info = fit.info;
        iterations += fit.iterations;
    }
    // A weak prior (1 m, 1 rad per axis) keeps the inverse finite where the
    // sweep leaves the pose free (a lone plane, a corridor's axis): there the
    // covariance is ~1 and fusion leaves the motion noise in charge.
    let cov_map = (info + Matrix6::identity())
        .try_inverse()
        .unwrap_or_else(Matrix6::identity);
    let a = body_adjoint(&pose);
    Some(Alignment {
        pose,
        inliers: last.0,
        rms: last.1,
        iterations,
        covariance: a * cov_map * a.transpose(),
    })
}

/// The start of a wide search: the poses from which [`align_wide`] tries
/// the coarsest level, around a guess `g` of the sensor pose with the last
/// sensor pose `from`. With the guess's motion `m = from⁻¹·g`: the guess,
/// the motion turned by each yaw offset (about the sensor's z axis, half
/// before and half after the translation, as along an arc), and each of
/// these without translation (the platform stopped, or turned on the spot).
pub fn search_seeds(
    from: &Pose3,
    guess: &Pose3,
    yaw_step_deg: f64,
    yaw_max_deg: f64,
) -> Vec<Pose3> {
    let m = from.inverse() * guess;
    let mut seeds = vec![*guess];
    let mut yaws = vec![0.0];
    if yaw_step_deg > 0.0 {
        let n = (yaw_max_deg / yaw_step_deg).floor() as i32;
        for k in 1..=n {
            let a = (k as f64 * yaw_step_deg).to_radians();
            yaws.push(a);
            yaws.push(-a);
        }
    }
    let still = Pose3::from_parts(Translation3::identity(), m.rotation);
    for (i, &yaw) in yaws.iter().enumerate() {
        let half = Pose3::from_parts(
            Translation3::identity(),
            UnitQuaternion::from_euler_angles(0.0, 0.0, 0.5 * yaw),
        );
        if i > 0 {
            seeds.push(from * (half * m * half));
        }
        seeds.push(from * (half * still * half));
    }
    seeds
}

/// Distinct coarse optima refined through every level by [`align_wide`].
const WIDE_REFINE: usize = 4;
/// Metres of translation that weigh as much as a radian of rotation when
/// [`align_wide`] asks which optimum is closest to the guess.
const PRIOR_M_PER_RAD: f64 = 1.0;
/// Two coarse optima closer than this in rotation (rad) ...
const SAME_ROTATION: f64 = 0.087;

/// [`align`] from the best of several starts, coarse to fine.
///
/// The first seed (the guess) is fitted on the coarsest level alone and
/// scored by its consensus with that level as a fraction of the sweep's
/// points (`consensus`). When that fraction is at least
/// `(1 − min_gain)·expected` (`expected`: what the last sweeps scored,
/// `None` on the first), the guess is trusted: the full alignment runs from
/// it, and the search cost one coarse fit.
///
/// Otherwise every seed is fitted on the coarsest level; the optima are
/// merged where they agree (within the coarsest voxel and 5°), the best
/// `WIDE_REFINE` (4) of them by coarse consensus, and the guess's, are
/// aligned through all levels, and each is scored by its consensus with the
/// finest level, which tells apart what the coarse level cannot (an optimum
/// slid along a corridor, a floor taken for a ramp). Of those that explain
/// at least `1 − min_gain` of what the best explains there, the one closest
/// to the guess wins (the motion prior breaks the map's ties). Returns the winner with its coarse consensus fraction (the scale
/// of `expected`).
pub fn align_wide(
    map: &LocalMap,
    source: &[Vec3A],
    seeds: &[Pose3],
    params: &IcpParams,
    min_gain: f64,
    expected: Option<f64>,
) -> Option<(Alignment, f64)> {
    let (first, rest) = seeds.split_first()?;
    let (Some(level), Some(finest)) = (map.levels.first(), map.levels.last()) else {
        return align(map, source, first, params).map(|a| (a, 0.0));
    };
    let src = thin(&downsample(source, level.voxel), params.max_points);
    let n = src.len().max(1) as f64;
    let score = |seed: &Pose3| -> Option<(Pose3, f64)> {
        let fit = fit_level(level, &src, *seed, params.iterations)?;
        Some((fit.pose, consensus(level, &src, &fit.pose) / n))
    };
    let base = score(first);
    let good = match (base, expected) {
        (Some(b), Some(e)) => b.1 >= (1.0 - min_gain) * e,
        _ => false,
    };
    if good || rest.is_empty() {
        return align(map, source, first, params).map(|a| (a, base.map_or(0.0, |b| b.1)));
    }
    // Coarse optima of every seed, best first (ties: seed order), merged
    // where they agree.
    let mut optima: Vec<(usize, Pose3, f64)> = seeds
        .iter()
        .enumerate()
        .filter_map(|(i, s)| {
            if i == 0 {
                base.map(|(p, c)| (0, p, c))
            } else {
                score(s).map(|(p, c)| (i, p, c))
            }
        })
        .collect();
    optima.sort_by(|a, b| b.2.total_cmp(&a.2).then(a.0.cmp(&b.0)));
    let mut distinct: Vec<(usize, Pose3, f64)> = Vec::new();
    for o in optima {
        let same = distinct.iter().any(|d| {
            let e = d.1.inverse() * o.1;
            e.translation.vector.norm() < level.voxel && e.rotation.angle() < SAME_ROTATION
        });
        if !same {
            distinct.push(o);
        }
    }
    let mut chosen: Vec<(usize, Pose3, f64)> = distinct.iter().take(WIDE_REFINE).copied().collect();
    if let Some(g) = distinct.iter().find(|d| d.0 == 0)
        && !chosen.iter().any(|c| c.0 == 0)
    {
        chosen.push(*g);
    }
    let fine_src = thin(&downsample(source, finest.voxel), params.max_points);
    let nf = fine_src.len().max(1) as f64;
    let refined: Vec<(usize, Alignment, f64, f64)> = chosen
        .iter()
        .filter_map(|&(i, p, c)| {
            let a = align(map, source, &p, params)?;
            let f = consensus(finest, &fine_src, &a.pose) / nf;
            Some((i, a, c, f))
        })
        .collect();
    // The map alone cannot tell apart optima that explain the sweep about
    // equally well (a corridor's corner seen turned by 90°, a slide along
    // a corridor): among those within `min_gain` of the best, the motion
    // prior decides, and the one closest to the guess wins.
    let top = refined
        .iter()
        .map(|r| r.3)
        .fold(f64::NEG_INFINITY, f64::max);
    let off = |a: &Alignment| {
        let e = first.inverse() * a.pose;
        e.translation.vector.norm() + PRIOR_M_PER_RAD * e.rotation.angle()
    };
    let won = refined
        .iter()
        .filter(|r| r.3 >= (1.0 - min_gain) * top)
        .copied()
        .reduce(|b, r| if off(&r.1) < off(&b.1) { r } else { b })?;
    Some((won.1, won.2))
}

/// The registration's memory: the down-sampled points of the last `window`
/// sweeps (sensor frame), keyed by their input index.
#[derive(Debug, Clone)]
pub struct SweepWindow {
    params: IcpParams,
    recent: VecDeque<(u32, Vec<Vec3A>)>,
}

impl SweepWindow {
    /// An empty proposal.
    pub fn new(params: IcpParams) -> Self {
        Self {
            params,
            recent: VecDeque::new(),
        }
    }

    /// The parameters.
    pub fn params(&self) -> &IcpParams {
        &self.params
    }

    /// Down-samples `points` (sensor frame, m) to the finest ICP voxel: the
    /// form in which sweeps are aligned and kept.
    pub fn prepare(&self, points: &[[f32; 3]]) -> Vec<Vec3A> {
        let finest = self.params.levels.last().map_or(0.2, |l| l.0);
        points::voxel_downsample(points::from_sweep(points), finest as f32)
    }

    /// Remembers sweep `index` (prepared points) and forgets the oldest
    /// beyond the window.
    pub fn push(&mut self, index: u32, prepared: Vec<Vec3A>) {
        self.recent.push_back((index, prepared));
        while self.recent.len() > self.params.window {
            self.recent.pop_front();
        }
    }

    /// Input indices of the remembered sweeps, oldest first.
    pub fn indices(&self) -> impl Iterator<Item = u32> + '_ {
        self.recent.iter().map(|r| r.0)
    }

    /// Aligns `prepared` (points of the new sweep) to the remembered sweeps,
    /// each placed with `pose_of(index)` (`None`: left out), from `initial`.
    pub fn align(
        &self,
        prepared: &[Vec3A],
        initial: &Pose3,
        pose_of: impl Fn(u32) -> Option<Pose3>,
    ) -> Option<Alignment> {
        let map = self.local_map(pose_of)?;
        align(&map, prepared, initial, &self.params)
    }

    /// The local map of the remembered sweeps, each placed with
    /// `pose_of(index)` (`None`: left out); `None` if none is placed.
    pub fn local_map(&self, pose_of: impl Fn(u32) -> Option<Pose3>) -> Option<LocalMap> {
        let clouds: Vec<(Pose3, &[Vec3A])> = self
            .recent
            .iter()
            .filter_map(|(i, pts)| pose_of(*i).map(|p| (p, pts.as_slice())))
            .collect();
        if clouds.is_empty() {
            return None;
        }
        Some(LocalMap::build(&clouds, &self.params))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Vector3;

    /// Points on the inside of a 12 × 9 × 3 m room with two pillars, seen from
    /// `sensor` (map frame), in the sensor frame. Deterministic grid sampling.
    fn room_points(sensor: &Pose3) -> Vec<Vector3<f64>> {
        let mut pts = Vec::new();
        let s = 0.1;
        let (lx, ly, lz) = (12.0, 9.0, 3.0);
        let mut add = |p: Vector3<f64>| pts.push(sensor.inverse() * nalgebra::Point3::from(p));
        let steps = |a: f64| (0..=((a / s) as i32)).map(move |i| i as f64 * s);
        for x in steps(lx) {
            for y in steps(ly) {
                add(Vector3::new(x - 6.0, y - 4.5, -1.0));
            }
            for z in steps(lz) {
                add(Vector3::new(x - 6.0, -4.5, z - 1.0));
                add(Vector3::new(x - 6.0, 4.5, z - 1.0));
            }
        }
        for y in steps(ly) {
            for z in steps(lz) {
                add(Vector3::new(-6.0, y - 4.5, z - 1.0));
                add(Vector3::new(6.0, y - 4.5, z - 1.0));
            }
        }
        for (cx, cy) in [(2.0, 1.5), (-3.0, -2.0)] {
            for a in 0..40 {
                let t = a as f64 / 40.0 * std::f64::consts::TAU;
                for z in steps(lz) {
                    add(Vector3::new(
                        cx + 0.4 * t.cos(),
                        cy + 0.4 * t.sin(),
                        z - 1.0,
                    ));
                }
            }
        }
        pts.into_iter().map(|p| p.coords).collect()
    }

    #[test]
    fn recovers_a_metre_and_ten_degrees() {
        let params = IcpParams::from_config(&Map3dConfig::default());
        let first = Pose3::identity();
        let truth = Pose3::new(Vector3::new(0.8, 0.3, 0.05), Vector3::new(0.01, -0.01, 0.2));
        // The prior is off by 1.2 m and 12° (mostly yaw) from the truth.
        let err = Pose3::new(Vector3::new(1.0, -0.6, 0.1), Vector3::new(0.0, 0.02, -0.21));
        let initial = truth * err;
        assert!(err.translation.vector.norm() >= 1.0 && err.rotation.angle() >= 10f64.to_radians());
        let mut prop = SweepWindow::new(params);
        let a = prop.prepare(&to_f32(&room_points(&first)));
        prop.push(0, a);
        let b = prop.prepare(&to_f32(&room_points(&truth)));
        let got = prop.align(&b, &initial, |_| Some(first)).expect("aligned");
        let e = truth.inverse() * got.pose;
        assert!(e.translation.vector.norm() < 0.02, "{e:?}");
        assert!(e.rotation.angle() < 0.3f64.to_radians(), "{e:?}");
        assert!(got.inliers > 500);
    }

    /// The covariance is small where the sweep constrains the pose and large
    /// where it does not: on a lone floor, x, y and yaw are free.
    #[test]
    fn covariance_follows_what_the_geometry_constrains() {
        let params = IcpParams::from_config(&Map3dConfig::default());
        let floor = |sensor: &Pose3| -> Vec<Vector3<f64>> {
            let mut v = Vec::new();
            for i in -60..=60 {
                for j in -60..=60 {
                    let p = Vector3::new(i as f64 * 0.1, j as f64 * 0.1, -1.0);
                    v.push((sensor.inverse() * nalgebra::Point3::from(p)).coords);
                }
            }
            v
        };
        let truth = Pose3::new(Vector3::new(0.3, 0.0, 0.0), Vector3::zeros());
        let map = LocalMap::build(
            &[(Pose3::identity(), &to_vec3a(&floor(&Pose3::identity()))[..])],
            &params,
        );
        let got = align(&map, &to_vec3a(&floor(&truth)), &truth, &params).expect("aligned");
        let c = got.covariance;
        // [ωx, ωy, ωz, tx, ty, tz]: roll, pitch and height are fixed by the
        // plane to well under a millimetre / a hundredth of a degree ...
        for k in [0, 1, 5] {
            assert!(c[(k, k)].sqrt() < 1e-3, "{k}: {}", c[(k, k)].sqrt());
        }
        // ... yaw, x and y not at all.
        for k in [2, 3, 4] {
            assert!(c[(k, k)].sqrt() > 0.1, "{k}: {}", c[(k, k)].sqrt());
        }

        // In the room everything is constrained, to millimetres.
        let mut prop = SweepWindow::new(params);
        let a = prop.prepare(&to_f32(&room_points(&Pose3::identity())));
        prop.push(0, a);
        let b = prop.prepare(&to_f32(&room_points(&truth)));
        let got = prop
            .align(&b, &truth, |_| Some(Pose3::identity()))
            .expect("aligned");
        for k in 0..6 {
            let s = got.covariance[(k, k)].sqrt();
            assert!(s > 0.0 && s < 0.005, "{k}: {s}");
        }
    }

    #[test]
    fn too_few_points_is_no_alignment() {
        let params = IcpParams::from_config(&Map3dConfig::default());
        let map = LocalMap::build(
            &[(Pose3::identity(), &[Vec3A::new(1.0, 0.0, 0.0)][..])],
            &params,
        );
        assert_eq!(map.len(), 1);
        assert!(
            align(
                &map,
                &[Vec3A::new(1.0, 0.0, 0.0)],
                &Pose3::identity(),
                &params
            )
            .is_none()
        );
    }

    fn to_vec3a(v: &[Vector3<f64>]) -> Vec<Vec3A> {
        v.iter()
            .map(|p| Vec3A::new(p.x as f32, p.y as f32, p.z as f32))
            .collect()
    }

    fn to_f32(v: &[Vector3<f64>]) -> Vec<[f32; 3]> {
        v.iter()
            .map(|p| [p.x as f32, p.y as f32, p.z as f32])
            .collect()
    }
}
