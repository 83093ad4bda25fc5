//! The 2-D trajectory's final alignment against the run's own map.
//!
//! The filter places each scan against its particle's map *as it was at
//! that step*, a map still missing everything seen later, and reports
//! poses that carry each step's sampling noise (a sample is drawn, not the
//! mode). After the run, the map of all scans is known: each scan is
//! re-aligned, from its pose, to a likelihood field of the hits of every
//! scan at its pose (a sub-cell hill-climb, as the proposal's refinement
//! does). The field is an average over hundreds of scans, so each scan's
//! own noise pulls it little, and a pass lowers the scans' noise relative
//! to the map they agree on. The global shape, loops included, is the
//! filter's: the climb moves most scans by a centimetre or two, and a
//! climb's reach is a few decimetres. Nothing here touches
//! the DP-map or the particles.
//!
//! Memory follows the area mapped, not the log's length: the scans are read
//! again, in order, by each pass ([`refine_poses`]); only the hit grid
//! (occupied cells, sparse) and a few hundred scans at a time are held.
//!
//! Measured on the raw logs with Kümmerle relations (docs/PROPOSAL-2D.md,
//! session 25): it lowers the relations' errors on all three and leaves the
//! global error (ATE) of the perturbed logs where the filter left it.

use crate::config::RefineConfig;
use crate::geometry::{Pose, Pose2, pose2, xyt};
use crate::scan_match::bilinear;
use crate::{Error, Result};
use rayon::prelude::*;
use rustc_hash::FxHashMap;

/// Scans aligned together against one field: consecutive scans overlap,
/// so one field over their union serves them all.
const GROUP: usize = 32;
/// Groups read before they are aligned in parallel.
const BATCH: usize = 8 * GROUP;
/// Occupied cells are bucketed in square tiles of this many cells.
const TILE: i32 = 128;
/// Hill-climb levels, each halving the steps; moves per level at most.
const LEVELS: usize = 5;
const MOVES_PER_LEVEL: usize = 10;
/// Fewer endpoints than this: the scan keeps its pose.
const MIN_POINTS: usize = 20;

/// What [`refine_poses`] did.
#[derive(Debug, Clone, PartialEq)]
pub struct Refined {
    /// The refined poses, one per scan (map frame, robot pose).
    pub poses: Vec<Pose2>,
    /// Median of how far each scan moved over all passes, m.
    pub moved_median_m: f64,
    /// Largest move, m.
    pub moved_max_m: f64,
    /// Median heading change, rad.
    pub turned_median_rad: f64,
}

/// Re-aligns every scan to the map of all scans, `cfg.passes` times.
///
/// `poses` are the robot's poses (map frame), one per scan. `scans` opens
/// the scans anew, in the same order, each as its robot-frame endpoints
/// (m, [`Scan::returns_in_robot_frame`](crate::scan::Scan::returns_in_robot_frame)); it is called twice per pass (to build the map,
/// then to align), so memory does not grow with the log. The result is the
/// same for any thread count.
pub fn refine_poses<I>(
    cfg: &RefineConfig,
    poses: &[Pose2],
    scans: impl Fn() -> Result<I>,
) -> Result<Refined>
where
    I: Iterator<Item = Result<Vec<[f64; 2]>>>,
{
    let mut now = poses.to_vec();
    for _ in 0..cfg.passes {
        let map = HitMap::build(cfg, &now, scans()?)?;
        now = align_pass(cfg, &map, &now, scans()?)?;
    }
    let mut moved: Vec<f64> = poses
        .iter()
        .zip(&now)
        .map(|(a, b)| (a.translation.vector - b.translation.vector).norm())
        .collect();
    let mut turned: Vec<f64> = poses
        .iter()
        .zip(&now)
        .map(|(a, b)| (a.inverse() * b).rotation.angle().abs())
        .collect();
    Ok(Refined {
        poses: now,
        moved_median_m: median(&mut moved),
        moved_max_m: moved.iter().copied().fold(0.0, f64::max),
        turned_median_rad: median(&mut turned),
    })
}

fn median(v: &mut [f64]) -> f64 {
    if v.is_empty() {
        return 0.0;
    }
    v.sort_unstable_by(f64::total_cmp);
    v[v.len() / 2]
}

fn count_mismatch(scans: usize, poses: usize) -> Error {
    Error::Invalid(format!(
        "refine: the scans were read as {scans} scans, the trajectory has {poses} poses"
    ))
}

/// The occupied cells of the map of all scans, bucketed by tile.
struct HitMap {
    res: f64,
    /// Tile → its occupied cells, each as the mean of its endpoints (m).
    tiles: FxHashMap<[i32; 2], Vec<[f64; 2]>>,
}

impl HitMap {
    /// Counts every endpoint of `scans` at `poses` into a grid of
    /// `cfg.resolution`, keeping cells with at least `cfg.min_hits`.
    fn build<I>(cfg: &RefineConfig, poses: &[Pose2], scans: I) -> Result<Self>
    where
        I: Iterator<Item = Result<Vec<[f64; 2]>>>,
    {
        let res = cfg.resolution;
        // Per cell: hits and the sum of their points. The mean, not the
        // cell's centre, stands for the cell: a wall crossing a cell off its
        // centre would otherwise pull every scan that sees it by up to half
        // a cell.
        let mut hits: FxHashMap<[i32; 2], (u32, [f64; 2])> = FxHashMap::default();
        let mut n = 0;
        for points in scans {
            let points = points?;
            let pose = poses
                .get(n)
                .ok_or_else(|| count_mismatch(n + 1, poses.len()))?;
            for p in &points {
                let w = Pose::transform_point(pose, *p);
                let (h, sum) = hits.entry(cell_of(w, res)).or_default();
                *h += 1;
                sum[0] += w[0];
                sum[1] += w[1];
            }
            n += 1;
        }
        if n != poses.len() {
            return Err(count_mismatch(n, poses.len()));
        }
        let mut tiles: FxHashMap<[i32; 2], Vec<[f64; 2]>> = FxHashMap::default();
        let mut cells: Vec<([i32; 2], [f64; 2])> = hits
            .into_iter()
            .filter(|&(_, (h, _))| h >= cfg.min_hits)
            .map(|(c, (h, sum))| (c, sum.map(|v| v / h as f64)))
            .collect();
        // The field takes the maximum over cells, so order does not change
        // it; sorting keeps the tiles' contents the same run to run anyway.
        cells.sort_unstable_by_key(|&(c, _)| c);
        for (c, mean) in cells {
            tiles
                .entry([c[0].div_euclid(TILE), c[1].div_euclid(TILE)])
                .or_default()
                .push(mean);
        }
        Ok(Self { res, tiles })
    }

    /// The occupied cells' points inside `[lo, hi]` (m).
    fn occupied_in(&self, lo: [f64; 2], hi: [f64; 2]) -> Vec<[f64; 2]> {
        let (a, b) = (cell_of(lo, self.res), cell_of(hi, self.res));
        let mut out = Vec::new();
        for ty in a[1].div_euclid(TILE)..=b[1].div_euclid(TILE) {
            for tx in a[0].div_euclid(TILE)..=b[0].div_euclid(TILE) {
                if let Some(cells) = self.tiles.get(&[tx, ty]) {
                    out.extend(
                        cells
                            .iter()
                            .filter(|c| {
                                (lo[0]..=hi[0]).contains(&c[0]) && (lo[1]..=hi[1]).contains(&c[1])
                            })
                            .copied(),
                    );
                }
            }
        }
        out
    }
}

fn cell_of(p: [f64; 2], res: f64) -> [i32; 2] {
    [(p[0] / res).floor() as i32, (p[1] / res).floor() as i32]
}

/// The log-likelihood of an endpoint over a box of the map frame:
/// `ln(floor + (1 − floor)·exp(−d²/2σ²))`, `d` the distance to the nearest
/// occupied cell's point (the mean of its endpoints). Kept in `f32`, not quantised as the proposal's
/// field is: the climb resolves millimetres, where a byte per cell leaves
/// the peak flat.
struct LogField {
    /// Map-frame corner of cell (0, 0), m.
    origin: [f64; 2],
    res: f64,
    w: usize,
    h: usize,
    /// Per cell (row-major), the value at its centre.
    values: Vec<f32>,
    /// The value far from anything occupied, `ln floor`.
    far: f64,
}

impl LogField {
    /// The field of `occupied` (map-frame points, m) over `[lo, hi]` (m).
    fn new(cfg: &RefineConfig, lo: [f64; 2], hi: [f64; 2], occupied: &[[f64; 2]]) -> Self {
        let res = cfg.resolution;
        let w = (((hi[0] - lo[0]) / res).ceil() as usize).max(1);
        let h = (((hi[1] - lo[1]) / res).ceil() as usize).max(1);
        let mut d2 = vec![f64::INFINITY; w * h];
        // Beyond 3σ the Gaussian is below 1 % of the peak, a tenth of the floor.
        let reach = (3.0 * cfg.sigma / res).ceil() as isize;
        for p in occupied {
            let (u, v) = ((p[0] - lo[0]) / res, (p[1] - lo[1]) / res);
            let (ci, cj) = (u.floor() as isize, v.floor() as isize);
            for j in (cj - reach).max(0)..=(cj + reach).min(h as isize - 1) {
                let dy = (j as f64 + 0.5 - v) * res;
                for i in (ci - reach).max(0)..=(ci + reach).min(w as isize - 1) {
                    let dx = (i as f64 + 0.5 - u) * res;
                    let cell = &mut d2[j as usize * w + i as usize];
                    *cell = cell.min(dx * dx + dy * dy);
                }
            }
        }
        let (floor, inv) = (cfg.floor, 1.0 / (2.0 * cfg.sigma * cfg.sigma));
        let values = d2
            .into_iter()
            .map(|d2| (floor + (1.0 - floor) * (-d2 * inv).exp()).ln() as f32)
            .collect();
        Self {
            origin: lo,
            res,
            w,
            h,
            values,
            far: floor.ln(),
        }
    }

    /// The field at map point `(x, y)`, bilinear between cell centres.
    #[inline]
    fn at(&self, x: f64, y: f64) -> f64 {
        bilinear(
            self.origin,
            self.res,
            [self.w, self.h],
            self.far,
            x,
            y,
            |k| self.values[k] as f64,
        )
    }

    /// The summed field of `points` (robot frame, m) at map pose `[x, y, θ]`.
    fn score(&self, points: &[[f64; 2]], pose: [f64; 3]) -> f64 {
        let (s, c) = pose[2].sin_cos();
        points
            .iter()
            .map(|p| self.at(c * p[0] - s * p[1] + pose[0], s * p[0] + c * p[1] + pose[1]))
            .sum()
    }
}

/// One pass: every scan climbed from its pose in `poses` on the field of `map`.
fn align_pass<I>(cfg: &RefineConfig, map: &HitMap, poses: &[Pose2], scans: I) -> Result<Vec<Pose2>>
where
    I: Iterator<Item = Result<Vec<[f64; 2]>>>,
{
    let mut out = Vec::with_capacity(poses.len());
    let mut batch: Vec<Vec<[f64; 2]>> = Vec::with_capacity(BATCH);
    let flush = |batch: &mut Vec<Vec<[f64; 2]>>, out: &mut Vec<Pose2>| {
        let first = out.len();
        let aligned: Vec<Vec<Pose2>> = batch
            .par_chunks(GROUP)
            .enumerate()
            .map(|(g, group)| align_group(cfg, map, &poses[first + g * GROUP..], group))
            .collect();
        out.extend(aligned.into_iter().flatten());
        batch.clear();
    };
    let mut n = 0;
    for points in scans {
        let points = points?;
        if n >= poses.len() {
            return Err(count_mismatch(n + 1, poses.len()));
        }
        batch.push(points);
        n += 1;
        if batch.len() == BATCH {
            flush(&mut batch, &mut out);
        }
    }
    flush(&mut batch, &mut out);
    if n != poses.len() {
        return Err(count_mismatch(n, poses.len()));
    }
    Ok(out)
}

/// Aligns the consecutive scans `group` (from `poses[0]` on) against one
/// field over their endpoints.
fn align_group(
    cfg: &RefineConfig,
    map: &HitMap,
    poses: &[Pose2],
    group: &[Vec<[f64; 2]>],
) -> Vec<Pose2> {
    // The field must cover wherever a climb can take an endpoint: the
    // climb's reach and the field's own tail.
    let margin = 0.5 + 4.0 * cfg.sigma;
    let (mut lo, mut hi) = ([f64::INFINITY; 2], [f64::NEG_INFINITY; 2]);
    for (points, pose) in group.iter().zip(poses) {
        for p in points {
            let w = Pose::transform_point(pose, *p);
            for a in 0..2 {
                lo[a] = lo[a].min(w[a] - margin);
                hi[a] = hi[a].max(w[a] + margin);
            }
        }
    }
    if !(lo[0] < hi[0] && lo[1] < hi[1]) {
        return poses[..group.len()].to_vec();
    }
    // Sampled on the hit grid, one sample per cell: a wall's peak then lies
    // on the cell centre nearest it, the same for every scan that sees the
    // wall, which shifts those scans together by up to half a cell and
    // leaves their relative poses alone. Sampled off the grid, or finer
    // (half or a quarter cell), the scans agreed less: relations 2–7 %
    // worse on mit-csail and aces-raw (PROPOSAL-2D.md, session 25).
    let lo = lo.map(|v| (v / cfg.resolution).floor() * cfg.resolution);
    let field = LogField::new(cfg, lo, hi, &map.occupied_in(lo, hi));
    group
        .iter()
        .zip(poses)
        .map(|(points, pose)| climb(cfg, &field, points, pose))
        .collect()
}

/// The pose of the best smooth score of `points` reached from `start` by a
/// hill-climb that halves its steps (GMapping's matcher; the first step is
/// 0.4 field cells and 0.01 rad).
fn climb(cfg: &RefineConfig, field: &LogField, points: &[[f64; 2]], start: &Pose2) -> Pose2 {
    if points.len() < MIN_POINTS {
        return *start;
    }
    let (x, y, t) = xyt(start);
    let mut p = [x, y, t];
    let mut best = field.score(points, p);
    let (mut step, mut turn) = (0.4 * cfg.resolution, 0.01);
    for _ in 0..LEVELS {
        for _ in 0..MOVES_PER_LEVEL {
            let mut moved = false;
            for d in [
                [step, 0.0, 0.0],
                [-step, 0.0, 0.0],
                [0.0, step, 0.0],
                [0.0, -step, 0.0],
                [0.0, 0.0, turn],
                [0.0, 0.0, -turn],
            ] {
                let q = [p[0] + d[0], p[1] + d[1], p[2] + d[2]];
                let s = field.score(points, q);
                if s > best + 1e-9 {
                    (best, p, moved) = (s, q, true);
                }
            }
            if !moved {
                break;
            }
        }
        step *= 0.5;
        turn *= 0.5;
    }
    pose2(p[0], p[1], p[2])
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Endpoints (robot frame) of a robot at `at` in a 10 × 6 m room with a
    /// pillar, one ray per degree. The walls are off the 5 cm hit grid, as
    /// real walls are (one on a cell boundary splits into two rows of cells
    /// and flattens the field across them).
    fn room_scan(at: &Pose2) -> Vec<[f64; 2]> {
        let off = |w: [[f64; 2]; 2]| w.map(|[x, y]| [x + 0.013, y + 0.021]);
        let walls: Vec<[[f64; 2]; 2]> = [
            [[0.0, 0.0], [10.0, 0.0]],
            [[10.0, 0.0], [10.0, 6.0]],
            [[10.0, 6.0], [0.0, 6.0]],
            [[0.0, 6.0], [0.0, 0.0]],
            [[6.0, 2.0], [6.5, 2.0]],
            [[6.5, 2.0], [6.5, 2.5]],
            [[6.5, 2.5], [6.0, 2.5]],
            [[6.0, 2.5], [6.0, 2.0]],
        ]
        .map(off)
        .to_vec();
        let (x, y, t) = xyt(at);
        (0..360)
            .filter_map(|i| {
                let a = (i as f64).to_radians();
                let d = [(t + a).cos(), (t + a).sin()];
                let mut best = f64::INFINITY;
                for w in &walls {
                    let e = [w[1][0] - w[0][0], w[1][1] - w[0][1]];
                    let den = d[0] * e[1] - d[1] * e[0];
                    if den.abs() < 1e-12 {
                        continue;
                    }
                    let q = [w[0][0] - x, w[0][1] - y];
                    let r = (q[0] * e[1] - q[1] * e[0]) / den;
                    let s = (q[0] * d[1] - q[1] * d[0]) / den;
                    if r > 0.0 && (0.0..=1.0).contains(&s) {
                        best = best.min(r);
                    }
                }
                best.is_finite().then(|| [best * a.cos(), best * a.sin()])
            })
            .collect()
    }

    #[test]
    fn scans_off_by_centimetres_return_to_the_map_the_others_agree_on() {
        let truth: Vec<Pose2> = (0..40)
            .map(|i| pose2(2.0 + 0.1 * i as f64, 3.0 + 0.02 * i as f64, 0.01 * i as f64))
            .collect();
        let scans: Vec<Vec<[f64; 2]>> = truth.iter().map(room_scan).collect();
        // Every fifth scan is off by 3.5 cm, each in another direction,
        // and by 1° either way; the map is mostly the others'.
        let given: Vec<Pose2> = truth
            .iter()
            .enumerate()
            .map(|(i, p)| {
                let a = i as f64 * 1.3;
                let turn = if i % 10 == 0 { 0.017 } else { -0.017 };
                if i % 5 == 0 {
                    p * pose2(0.035 * a.cos(), 0.035 * a.sin(), turn)
                } else {
                    *p
                }
            })
            .collect();
        let cfg = RefineConfig::default();
        let open = || Ok(scans.clone().into_iter().map(Ok));
        let r = refine_poses(&cfg, &given, open).unwrap();
        // Each pose relative to scan 1's (one that was right), against the
        // same in the truth: the map's frame may move as a whole (walls are
        // drawn to the cell centres near them), the scans' agreement may not.
        let err = |ps: &[Pose2], i: usize| {
            let d = (truth[1].inverse() * truth[i]).inverse() * (ps[1].inverse() * ps[i]);
            (d.translation.vector.norm(), d.rotation.angle().abs())
        };
        for i in (0..40).step_by(5) {
            let (t0, r0) = err(&given, i);
            let (t1, r1) = err(&r.poses, i);
            assert!(
                t1 < 0.4 * t0 && r1 < 0.4 * r0,
                "scan {i}: {t0:.3} m {r0:.4} rad -> {t1:.3} m {r1:.4} rad"
            );
        }
        // The scans that were right stay right.
        for i in (2..40).filter(|i| i % 5 != 0) {
            let (t, a) = err(&r.poses, i);
            assert!(t < 0.01 && a < 0.003, "scan {i} moved {t:.4} m {a:.4} rad");
        }
        assert!(r.moved_max_m > 0.02);
    }

    #[test]
    fn a_scan_count_that_differs_from_the_trajectory_is_an_error() {
        let p = pose2(2.0, 3.0, 0.0);
        let scans = vec![room_scan(&p); 3];
        let open = || Ok(scans.clone().into_iter().map(Ok));
        let err = refine_poses(&RefineConfig::default(), &[p, p], open).unwrap_err();
        assert!(err.to_string().contains("3 scans"), "{err}");
        let err = refine_poses(&RefineConfig::default(), &[p; 4], open).unwrap_err();
        assert!(err.to_string().contains("4 poses"), "{err}");
    }

    #[test]
    fn zero_passes_keep_the_filter_s_poses() {
        let p = pose2(2.0, 3.0, 0.1);
        let scans = vec![room_scan(&p); 2];
        let open = || Ok(scans.clone().into_iter().map(Ok));
        let cfg = RefineConfig {
            passes: 0,
            ..RefineConfig::default()
        };
        let q = p * pose2(0.05, 0.0, 0.0);
        assert_eq!(refine_poses(&cfg, &[p, q], open).unwrap().poses, vec![p, q]);
    }
}
