//! The 2-D scan-matched proposal (Grisetti et al., IEEE T-RO 2007,
//! "improved proposal"; the wide search is Olson's correlative matcher,
//! ICRA 2009).
//!
//! For each group of particles that share a map view (the children of one
//! ancestry node: they differ only in their own last observation), the
//! cells that view sees as occupied near the scan are rasterised into a
//! likelihood field: per field cell, `occ · exp(−d²/2σ²)` of the nearest
//! occupied cell, `occ = 1 − exp(−ρ·cell)` its stop probability, 1 for
//! every cell with a hit, or 1 on walls (thin lines of hit cells) and the
//! stop probability elsewhere (`scan_match.field_weight`, [`FieldWeight`]). Each
//! particle of the group then registers the scan's endpoints against that
//! field around its own odometry guess `prev · odometry`, over the whole
//! window (`±window_xy` m, `±window_theta` rad), in two levels: a coarse
//! level whose cells hold the maximum over `coarse_factor`-times larger
//! blocks (an upper bound of every finer translation inside, as in Olson's
//! multi-resolution search) at coarse angle steps, then the finest level
//! around the best `candidates` coarse poses. The score surface gives the
//! mode and a covariance: the curvature of the score at the mode (the
//! Laplace approximation; Olson 2009's eq. 15, the weighted second moment
//! of the evaluated poses, was tried in session 15 and lost perturbed ACES),
//! which is wide along a direction the scan does not constrain (a
//! corridor's axis, open space). That Gaussian is fused with
//! the C/D/T motion model's, linearised at its mean, and the particle's
//! samples are drawn from the product ([`Proposal::Matched`]). Where too
//! few endpoints fall near anything the view has seen (a new area, an
//! empty map), the particle draws from the motion model instead.
//!
//! The match only places samples: their weights are the DP-map likelihood
//! × motion prior / this proposal's density (see [`crate::proposal`]), so
//! a poor match costs samples, not correctness.
//!
//! Frames: particle poses and the field in the map frame (m, rad); the
//! fused Gaussian in the previous robot frame; the proposal's factor in the
//! body frame of its mean.

use crate::ancestry::NodeId;
use crate::config::{FieldWeight, ScanMatchConfig};
use crate::geometry::{Pose2, pose2, wrap_angle, xyt};
use crate::motion_model::CdtModel;
use crate::proposal::{MatchContext, Proposal, ScanRegistration};
use crate::scan::Scan;
use nalgebra::{DMatrix, Matrix2, Matrix3, Vector3};
use rayon::prelude::*;
use std::sync::{Arc, Mutex};

/// The scan-matched proposal of the 2-D filter.
#[derive(Debug)]
pub struct ScanMatcher2d {
    cfg: ScanMatchConfig,
    motion: CdtModel,
    /// DP-map cell edge, m.
    cell: f64,
    /// Range-error variance of the DP laser model, m² (`laser.variance`):
    /// the match's curvature is scaled to the likelihood the samples are
    /// weighed by.
    variance: f64,
    /// The fields of the last [`ScanRegistration::propose`], for
    /// [`ScanRegistration::rematch`]: building a field costs more than
    /// many registrations against it.
    last: Mutex<LastFields>,
    /// `ln(floor + (1 − floor)·q/255)` over the field's byte values `q`.
    log_field: [f64; 256],
    /// The fields' point kernel (it depends on the settings only).
    kernel: Kernel,
}

/// The fields one [`ScanRegistration::propose`] call built: per particle of
/// its context, the field of its view group.
#[derive(Default)]
struct LastFields {
    of_particle: Vec<Option<Arc<Field>>>,
}

/// A particle's proposal and the field of its view group it was matched in.
type Registered = (usize, Proposal<Pose2>, Arc<Field>);

impl std::fmt::Debug for LastFields {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "LastFields({} particles)", self.of_particle.len())
    }
}

impl Clone for ScanMatcher2d {
    /// The same matcher, without the fields of the last call.
    fn clone(&self) -> Self {
        Self::new(
            self.cfg.clone(),
            self.motion.clone(),
            self.cell,
            self.variance,
        )
    }
}

impl ScanMatcher2d {
    /// A matcher with settings `cfg`, fusing with `motion`, on a DP-map of
    /// `cell`-metre cells whose laser model has range-error variance
    /// `variance` (m²).
    pub fn new(cfg: ScanMatchConfig, motion: CdtModel, cell: f64, variance: f64) -> Self {
        let cfg_floor = cfg.floor;
        let kernel = Kernel::new(cfg.field_cells.max(1.0) * cell, cfg.sigma);
        Self {
            cfg,
            motion,
            cell,
            variance,
            kernel,
            last: Mutex::new(LastFields::default()),
            log_field: log_table(cfg_floor),
        }
    }

    /// The returns of `scan` in the robot frame (m), one per
    /// `scan_match.endpoint_spacing` square where that is set, evenly
    /// thinned to at most `scan_match.max_beams`; and how many returns
    /// there were.
    fn endpoints(&self, scan: &Scan<2, Pose2>) -> (Vec<[f64; 2]>, usize) {
        let returns = scan.returns_in_robot_frame();
        let beams = returns.len();
        let returns = one_per_square(returns, self.cfg.endpoint_spacing);
        (crate::icp::thin(&returns, self.cfg.max_beams), beams)
    }

    /// Registers `points` (of a scan of `beams` returns) against `field`
    /// from the guess `prev · odometry`, ranking the search's candidates
    /// with the motion prior where `prior_in_search`; `None` where the match
    /// fails or too few endpoints land on seen cells (`min_overlap`).
    fn register_from(
        &self,
        field: &Field,
        points: &[[f64; 2]],
        beams: usize,
        prev: &Pose2,
        odometry: &Pose2,
    ) -> Option<Match> {
        let prior = self
            .cfg
            .prior_in_search
            .then(|| SearchPrior::new(&self.motion, prev, odometry))
            .flatten();
        self.register(
            field,
            &self.log_field,
            points,
            beams,
            &(prev * odometry),
            prior.as_ref(),
        )
        .filter(|r| r.overlap >= self.cfg.min_overlap)
    }

    /// Edge of the finest field cell, m.
    fn res(&self) -> f64 {
        self.cfg.field_cells.max(1.0) * self.cell
    }

    /// The likelihood field of `occupied` (map-frame points, m, with their
    /// stop probabilities) over the box `lo`..`hi`, at this matcher's
    /// resolution, coarse factor and σ.
    fn field(&self, lo: [f64; 2], hi: [f64; 2], occupied: &[([f64; 2], f64)]) -> Field {
        Field::new(
            lo,
            hi,
            self.res(),
            self.cfg.coarse_factor,
            &self.kernel,
            occupied,
        )
    }
}

/// `ln(floor + (1 − floor)·q/255)` over the field's byte values `q`, the
/// floor clamped to [1e-6, 1].
fn log_table(floor: f64) -> [f64; 256] {
    let floor = floor.clamp(1e-6, 1.0);
    let mut lut = [0.0f64; 256];
    for (q, v) in lut.iter_mut().enumerate() {
        *v = (floor + (1.0 - floor) * q as f64 / 255.0).ln();
    }
    lut
}

/// A likelihood field over a box of the map frame.
struct Field {
    /// Map-frame corner of cell (0, 0), m.
    origin: [f64; 2],
    res: f64,
    w: usize,
    h: usize,
    /// Per fine cell, the endpoint likelihood quantised to 0..=255.
    fine: Vec<u8>,
    /// Coarse cells are `f` fine cells wide.
    f: usize,
    cw: usize,
    ch: usize,
    /// Per coarse cell `c`, the maximum of the fine cells of blocks `c` and
    /// `c + 1` (each axis): a fine translation anywhere in `[0, f·res)`
    /// from the coarse pose keeps every endpoint inside.
    coarse: Vec<u8>,
}

/// Sub-cell bins per axis of a [`Kernel`].
const SUB: usize = 16;

/// A field's point kernel: the Gaussian of σ around a point at sub-cell
/// offset bin (bx, by) of [`SUB`] per axis (≤ res / 32 from the point's
/// true offset), over the cells within 2σ, scaled to 0..=255: no
/// exponential per point and cell.
#[derive(Debug, Clone)]
struct Kernel {
    /// Cells on each side of the point's cell.
    reach: isize,
    /// `SUB × SUB` blocks of `span × span` values, `span = 2·reach + 1`.
    table: Vec<f32>,
}

impl Kernel {
    /// The kernel of σ `sigma` (m) on cells of `res` m.
    fn new(res: f64, sigma: f64) -> Self {
        let reach = (2.0 * sigma / res).ceil() as isize;
        let inv = 1.0 / (2.0 * sigma * sigma);
        let span = (2 * reach + 1) as usize;
        let mut table = vec![0.0f32; SUB * SUB * span * span];
        for by in 0..SUB {
            for bx in 0..SUB {
                let (ox, oy) = (
                    (bx as f64 + 0.5) / SUB as f64,
                    (by as f64 + 0.5) / SUB as f64,
                );
                for dj in 0..span {
                    for di in 0..span {
                        // Cell centre minus point, in cells.
                        let xc = (di as f64 - reach as f64 + 0.5 - ox) * res;
                        let yc = (dj as f64 - reach as f64 + 0.5 - oy) * res;
                        table[((by * SUB + bx) * span + dj) * span + di] =
                            (255.0 * (-(xc * xc + yc * yc) * inv).exp()) as f32;
                    }
                }
            }
        }
        Self { reach, table }
    }
}

impl Field {
    /// Rasterises `occupied` (map-frame centres, m, with stop
    /// probabilities) into a field covering `[lo, hi]` (m), with `kernel`
    /// (made for cells of `res` m).
    fn new(
        lo: [f64; 2],
        hi: [f64; 2],
        res: f64,
        f: usize,
        kernel: &Kernel,
        occupied: &[([f64; 2], f64)],
    ) -> Self {
        let w = (((hi[0] - lo[0]) / res).ceil() as usize).max(1);
        let h = (((hi[1] - lo[1]) / res).ceil() as usize).max(1);
        let mut fine = vec![0u8; w * h];
        let reach = kernel.reach;
        let span = (2 * reach + 1) as usize;
        let kernel = &kernel.table;
        for &(p, occ) in occupied {
            let u = (p[0] - lo[0]) / res;
            let v = (p[1] - lo[1]) / res;
            let (ci, cj) = (u.floor() as isize, v.floor() as isize);
            let bx = (((u - ci as f64) * SUB as f64) as usize).min(SUB - 1);
            let by = (((v - cj as f64) * SUB as f64) as usize).min(SUB - 1);
            let k = &kernel[(by * SUB + bx) * span * span..][..span * span];
            let occ = occ as f32;
            for dj in 0..span {
                let j = cj + dj as isize - reach;
                if j < 0 || j >= h as isize {
                    continue;
                }
                let row = &mut fine[j as usize * w..(j as usize + 1) * w];
                for di in 0..span {
                    let i = ci + di as isize - reach;
                    if i < 0 || i >= w as isize {
                        continue;
                    }
                    let v = (occ * k[dj * span + di]) as u8;
                    let slot = &mut row[i as usize];
                    *slot = (*slot).max(v);
                }
            }
        }
        let f = f.max(1);
        let (cw, ch) = (w.div_ceil(f), h.div_ceil(f));
        let mut block = vec![0u8; cw * ch];
        for (j, row) in fine.chunks_exact(w).enumerate() {
            let blocks = &mut block[(j / f) * cw..][..cw];
            for (b, run) in blocks.iter_mut().zip(row.chunks(f)) {
                *b = (*b).max(run.iter().copied().max().unwrap_or(0));
            }
        }
        let mut coarse = vec![0u8; cw * ch];
        for j in 0..ch {
            for i in 0..cw {
                let mut m = 0u8;
                for (bj, bi) in [(j, i), (j, i + 1), (j + 1, i), (j + 1, i + 1)] {
                    if bj < ch && bi < cw {
                        m = m.max(block[bj * cw + bi]);
                    }
                }
                coarse[j * cw + i] = m;
            }
        }
        Self {
            origin: lo,
            res,
            w,
            h,
            fine,
            f,
            cw,
            ch,
            coarse,
        }
    }
}

/// Bilinear interpolation between the cell centres of a row-major grid of
/// `size` cells of `res` m whose cell (0, 0) has its corner at `origin`
/// (map frame, m): `value(k)` is cell `k`'s sample, `outside` stands for
/// the cells beyond the grid. Shared by the matcher's fields and the final
/// alignment's ([`crate::refine`]).
#[inline]
pub(crate) fn bilinear(
    origin: [f64; 2],
    res: f64,
    size: [usize; 2],
    outside: f64,
    x: f64,
    y: f64,
    value: impl Fn(usize) -> f64,
) -> f64 {
    let u = (x - origin[0]) / res - 0.5;
    let v = (y - origin[1]) / res - 0.5;
    let (fi, fj) = (u.floor(), v.floor());
    let (fu, fv) = (u - fi, v - fj);
    let (i0, j0) = (fi as isize, fj as isize);
    let at = |i: isize, j: isize| -> f64 {
        if i < 0 || j < 0 || i >= size[0] as isize || j >= size[1] as isize {
            outside
        } else {
            value(j as usize * size[0] + i as usize)
        }
    };
    (1.0 - fv) * ((1.0 - fu) * at(i0, j0) + fu * at(i0 + 1, j0))
        + fv * ((1.0 - fu) * at(i0, j0 + 1) + fu * at(i0 + 1, j0 + 1))
}

impl Field {
    /// The field at map point `(x, y)`, bilinear between cell centres, on
    /// the 0..=255 scale (0 outside).
    #[inline]
    fn interp(&self, x: f64, y: f64) -> f64 {
        bilinear(self.origin, self.res, [self.w, self.h], 0.0, x, y, |k| {
            self.fine[k] as f64
        })
    }

    /// The smooth score of `points` (robot frame) at map pose `[x, y, θ]`:
    /// `Σ ln(floor + (1 − floor)·field)`, the field interpolated.
    fn smooth_score(&self, points: &[[f64; 2]], floor: f64, pose: [f64; 3]) -> f64 {
        let (s, c) = pose[2].sin_cos();
        points
            .iter()
            .map(|p| {
                let q = self.interp(c * p[0] - s * p[1] + pose[0], s * p[0] + c * p[1] + pose[1]);
                (floor + (1.0 - floor) * q / 255.0).ln()
            })
            .sum()
    }
}

/// One evaluated pose: offsets from the guess (map frame, m, m, rad) and score.
#[derive(Clone, Copy)]
struct Scored {
    dx: f64,
    dy: f64,
    dt: f64,
    score: f64,
}

/// The motion model's Gaussian of a particle's new pose, in the map frame,
/// as the correlative search's prior (`scan_match.prior_in_search`).
struct SearchPrior {
    /// Mean `[x m, y m, θ rad]`.
    mean: [f64; 3],
    /// Information (inverse covariance) of `[x, y, θ]`.
    info: Matrix3<f64>,
}

impl SearchPrior {
    /// The motion model's prior of the pose reached from `prev` by the
    /// odometry motion `odometry`; `None` if its covariance is singular.
    fn new(motion: &CdtModel, prev: &Pose2, odometry: &Pose2) -> Option<Self> {
        let (mu, sigma) = motion.local_gaussian(odometry);
        let mean = xyt(&(prev * pose2(mu[0], mu[1], mu[2])));
        // Previous robot frame into the map frame.
        let r = rot3(xyt(prev).2);
        let info = r * sigma.try_inverse()? * r.transpose();
        Some(Self {
            mean: [mean.0, mean.1, mean.2],
            info,
        })
    }

    /// `ln N(pose; mean, info⁻¹)` up to a constant.
    fn log_density(&self, x: f64, y: f64, t: f64) -> f64 {
        let d = Vector3::new(
            x - self.mean[0],
            y - self.mean[1],
            wrap_angle(t - self.mean[2]),
        );
        -0.5 * d.dot(&(self.info * d))
    }
}

/// A scan registration: the refined pose and its information.
struct Match {
    /// Best pose (map frame).
    mode: Pose2,
    /// Information matrix of the match (map frame, `[x m, y m, θ rad]`),
    /// positive semi-definite: zero along directions the scan does not
    /// constrain.
    info: Matrix3<f64>,
    /// Fraction of endpoints on something the view has seen, at the mode.
    overlap: f64,
}

impl ScanMatcher2d {
    /// Registers `points` (robot frame, m; a thinning of a scan of
    /// `beams` returns) against `field` around `guess` (map frame): the
    /// correlative search over the whole window, a sub-cell hill-climb on
    /// the interpolated field, and the curvature of the score there (scaled
    /// to the DP likelihood of all `beams`); `None` without endpoints.
    fn register(
        &self,
        field: &Field,
        lut: &[f64; 256],
        points: &[[f64; 2]],
        beams: usize,
        guess: &Pose2,
        prior: Option<&SearchPrior>,
    ) -> Option<Match> {
        if points.is_empty() {
            return None;
        }
        let c = &self.cfg;
        let (scale, mean_range, fine_dt) = self.scales(field, points, beams);
        // What candidates are ranked by: the score, or with a prior the
        // log posterior up to a constant (both in the DP likelihood's nats).
        let rank = |score: f64, x: f64, y: f64, t: f64| match prior {
            Some(p) => scale * score + p.log_density(x, y, t),
            None => score,
        };
        let res = field.res;
        let f = field.f;
        let big = f as f64 * res;
        let (gx, gy, gt) = xyt(guess);
        let coarse_dt = f as f64 * fine_dt;
        let na = (c.window_theta / coarse_dt).ceil() as i64;
        let nt = (2.0 * c.window_xy / big).ceil() as usize + 1;
        // Translation origin of the coarse grid: the guess − window, so the
        // coarse poses are `t0 + (u, v)·big`, u, v in 0..nt.
        let t0 = [gx - c.window_xy, gy - c.window_xy];
        let index = |x: f64, scale: f64, origin: f64| ((x - origin) / scale).floor() as isize;
        let mut coarse: Vec<Scored> = Vec::with_capacity((2 * na as usize + 1) * nt * nt);
        let mut base: Vec<(isize, isize)> = Vec::with_capacity(points.len());
        let mut sums = vec![0.0f64; nt * nt];
        for a in -na..=na {
            let dt = a as f64 * coarse_dt;
            let (s, co) = (gt + dt).sin_cos();
            base.clear();
            for p in points {
                let x = co * p[0] - s * p[1] + t0[0];
                let y = s * p[0] + co * p[1] + t0[1];
                base.push((
                    index(x, big, field.origin[0]),
                    index(y, big, field.origin[1]),
                ));
            }
            sums.iter_mut().for_each(|v| *v = 0.0);
            for &(bx, by) in &base {
                for v in 0..nt {
                    let j = by + v as isize;
                    if j < 0 || j >= field.ch as isize {
                        for u in 0..nt {
                            sums[v * nt + u] += lut[0];
                        }
                        continue;
                    }
                    let row = &field.coarse[j as usize * field.cw..(j as usize + 1) * field.cw];
                    for u in 0..nt {
                        let i = bx + u as isize;
                        let q = if i < 0 || i >= field.cw as isize {
                            0
                        } else {
                            row[i as usize]
                        };
                        sums[v * nt + u] += lut[q as usize];
                    }
                }
            }
            for v in 0..nt {
                for u in 0..nt {
                    coarse.push(Scored {
                        // The block's translations span [0, big): its centre.
                        dx: t0[0] - gx + (u as f64 + 0.5) * big,
                        dy: t0[1] - gy + (v as f64 + 0.5) * big,
                        dt,
                        score: sums[v * nt + u],
                    });
                }
            }
        }
        // The best coarse poses, then every fine pose inside each.
        let keys: Vec<f64> = coarse
            .iter()
            .map(|p| rank(p.score, gx + p.dx, gy + p.dy, gt + p.dt))
            .collect();
        let mut order: Vec<usize> = (0..coarse.len()).collect();
        order.sort_by(|&a, &b| keys[b].total_cmp(&keys[a]).then(a.cmp(&b)));
        let mut fine: Vec<Scored> = Vec::new();
        // Fine angles reach the neighbouring coarse angles: the coarse score
        // bounds translations, not turns.
        let half = f as i64;
        for &ci in order.iter().take(c.candidates.max(1)) {
            let cp = coarse[ci];
            let bx0 = gx + cp.dx - 0.5 * big;
            let by0 = gy + cp.dy - 0.5 * big;
            for s_ in -half..=half {
                let dt = cp.dt + s_ as f64 * fine_dt;
                let (s, co) = (gt + dt).sin_cos();
                base.clear();
                for p in points {
                    let x = co * p[0] - s * p[1] + bx0;
                    let y = s * p[0] + co * p[1] + by0;
                    base.push((
                        index(x, res, field.origin[0]),
                        index(y, res, field.origin[1]),
                    ));
                }
                for v in 0..f {
                    for u in 0..f {
                        let mut score = 0.0;
                        for &(bx, by) in &base {
                            let (i, j) = (bx + u as isize, by + v as isize);
                            let q =
                                if i < 0 || j < 0 || i >= field.w as isize || j >= field.h as isize
                                {
                                    0
                                } else {
                                    field.fine[j as usize * field.w + i as usize]
                                };
                            score += lut[q as usize];
                        }
                        fine.push(Scored {
                            dx: bx0 - gx + u as f64 * res,
                            dy: by0 - gy + v as f64 * res,
                            dt,
                            score,
                        });
                    }
                }
            }
        }
        // Fine poses are cell corners; the refinement starts half a cell on.
        let key = |p: &Scored| {
            let h = 0.5 * res;
            rank(p.score, gx + p.dx + h, gy + p.dy + h, gt + p.dt)
        };
        let best = fine
            .iter()
            .copied()
            .fold(None::<(Scored, f64)>, |b, p| {
                let k = key(&p);
                match b {
                    Some(b) if b.1 >= k => Some(b),
                    _ => Some((p, k)),
                }
            })?
            .0;
        // The grid pose put endpoints in cells; the interpolated field's
        // centres are half a cell on: start from both, keep the better.
        let starts = [
            [
                gx + best.dx + 0.5 * res,
                gy + best.dy + 0.5 * res,
                gt + best.dt,
            ],
            [gx + best.dx, gy + best.dy, gt + best.dt],
        ];
        Some(self.peak(field, points, &starts, fine_dt, mean_range, scale))
    }

    /// For `points` (robot frame, m; a thinning of `beams` returns) on
    /// `field`: the factor from the field's score to the DP likelihood's
    /// nats, the endpoints' mean range (m) and the finest heading step
    /// (rad).
    fn scales(&self, field: &Field, points: &[[f64; 2]], beams: usize) -> (f64, f64, f64) {
        let c = &self.cfg;
        // The field's score is a sum over `points.len()` endpoints of a
        // σ-wide field; the samples are weighed by `beams` ranges of the DP
        // model's σ_DP: this scales the score (and its curvature) to that
        // likelihood's, then by 1 / temperature.
        let scale = (beams as f64 / points.len() as f64) * (c.sigma * c.sigma / self.variance)
            / c.temperature.max(1e-6);
        let mean_range = points
            .iter()
            .map(|p| (p[0] * p[0] + p[1] * p[1]).sqrt())
            .sum::<f64>()
            / points.len() as f64;
        // A fine angle step moves the mean endpoint by about one fine cell.
        let fine_dt = (field.res / mean_range.clamp(1.0, 30.0)).clamp(1e-3, 5e-3);
        (scale, mean_range, fine_dt)
    }

    /// The peak nearest `guess` (map frame): the hill-climb of
    /// [`ScanMatcher2d::peak`] started at the guess itself, no search;
    /// `None` without endpoints.
    fn climb(
        &self,
        field: &Field,
        points: &[[f64; 2]],
        beams: usize,
        guess: &Pose2,
    ) -> Option<Match> {
        if points.is_empty() {
            return None;
        }
        let (scale, mean_range, fine_dt) = self.scales(field, points, beams);
        let (x, y, t) = xyt(guess);
        Some(self.peak(field, points, &[[x, y, t]], fine_dt, mean_range, scale))
    }

    /// The peak of the smooth score of `points` on `field` climbed from the
    /// best of `starts` (map-frame `[x, y, θ]`, at least one; the first on
    /// ties): a sub-cell hill-climb
    /// on the interpolated field, halving the steps (GMapping's matcher;
    /// the first heading step is half of `fine_dt`), then the curvature
    /// there, scaled by `scale` to the DP likelihood (`mean_range`, m, sets
    /// the heading stencil).
    fn peak(
        &self,
        field: &Field,
        points: &[[f64; 2]],
        starts: &[[f64; 3]],
        fine_dt: f64,
        mean_range: f64,
        scale: f64,
    ) -> Match {
        let c = &self.cfg;
        let res = field.res;
        let floor = c.floor.clamp(1e-6, 1.0);
        let score = |q: [f64; 3]| field.smooth_score(points, floor, q);
        let mut cur = starts[0];
        let mut cur_s = score(cur);
        for &alt in &starts[1..] {
            let alt_s = score(alt);
            if alt_s > cur_s {
                (cur, cur_s) = (alt, alt_s);
            }
        }
        let mut step = [0.5 * res, 0.5 * res, 0.5 * fine_dt];
        for _ in 0..c.refine_levels {
            for _ in 0..16 {
                let mut next: Option<([f64; 3], f64)> = None;
                for d in 0..3 {
                    for sign in [-1.0, 1.0] {
                        let mut q = cur;
                        q[d] += sign * step[d];
                        let sq = score(q);
                        if sq > next.map_or(cur_s, |n| n.1) {
                            next = Some((q, sq));
                        }
                    }
                }
                match next {
                    Some((q, sq)) => (cur, cur_s) = (q, sq),
                    None => break,
                }
            }
            step.iter_mut().for_each(|v| *v *= 0.5);
        }
        // Curvature: a quadratic fitted to the smooth score on the 3×3×3
        // stencil of ±one field cell (heading: ±one cell at the mean range)
        // around the mode: the Laplace approximation of the match.
        let h = [res, res, res / mean_range.clamp(1.0, 30.0)];
        let mut vals = [[[0.0f64; 3]; 3]; 3];
        for (a, va) in vals.iter_mut().enumerate() {
            for (b, vb) in va.iter_mut().enumerate() {
                for (cc, v) in vb.iter_mut().enumerate() {
                    let q = [
                        cur[0] + (a as f64 - 1.0) * h[0],
                        cur[1] + (b as f64 - 1.0) * h[1],
                        cur[2] + (cc as f64 - 1.0) * h[2],
                    ];
                    *v = if (a, b, cc) == (1, 1, 1) {
                        cur_s
                    } else {
                        score(q)
                    };
                }
            }
        }
        let at = |k: [usize; 3]| vals[k[0]][k[1]][k[2]];
        let mut hess = Matrix3::zeros();
        for i in 0..3 {
            // Second difference along i, averaged over the other two axes.
            let mut sum = 0.0;
            for u in 0..3 {
                for v in 0..3 {
                    let mut k = [0usize; 3];
                    let others: Vec<usize> = (0..3).filter(|&d| d != i).collect();
                    k[others[0]] = u;
                    k[others[1]] = v;
                    let mut kp = k;
                    let mut km = k;
                    let mut k0 = k;
                    kp[i] = 2;
                    km[i] = 0;
                    k0[i] = 1;
                    sum += at(kp) + at(km) - 2.0 * at(k0);
                }
            }
            hess[(i, i)] = sum / 9.0 / (h[i] * h[i]);
            for j in (i + 1)..3 {
                // Least-squares cross term: Σ a·b·s / 12.
                let mut sum = 0.0;
                for a in 0..3 {
                    for b in 0..3 {
                        for cc in 0..3 {
                            let k = [a, b, cc];
                            let w = (k[i] as f64 - 1.0) * (k[j] as f64 - 1.0);
                            sum += w * at(k);
                        }
                    }
                }
                let v = sum / 12.0 / (h[i] * h[j]);
                hess[(i, j)] = v;
                hess[(j, i)] = v;
            }
        }
        // One Newton step on the fitted quadratic, kept if it scores better
        // (a sub-step: within the stencil).
        let mut grad = Vector3::zeros();
        for a in 0..3 {
            for b in 0..3 {
                for cc in 0..3 {
                    let k = [a, b, cc];
                    for (i, g) in grad.iter_mut().enumerate() {
                        *g += (k[i] as f64 - 1.0) * at(k) / 18.0 / h[i];
                    }
                }
            }
        }
        if let Some(ch) = (-hess).cholesky() {
            let d = ch.solve(&grad);
            if (0..3).all(|i| d[i].abs() <= h[i]) {
                let q = [cur[0] + d[0], cur[1] + d[1], cur[2] + d[2]];
                let sq = score(q);
                if sq > cur_s {
                    cur = q;
                }
            }
        }
        let mode = pose2(cur[0], cur[1], cur[2]);
        // Overlap at the mode: endpoints on a field cell above zero.
        let (s, co) = cur[2].sin_cos();
        let hits = points
            .iter()
            .filter(|p| {
                let x = co * p[0] - s * p[1] + cur[0];
                let y = s * p[0] + co * p[1] + cur[1];
                field.interp(x, y) > 0.0
            })
            .count();
        // The curvature in the DP likelihood's units (`scale`). Directions
        // the scan does not constrain (a corridor's axis: curvature ≤ 0)
        // carry no information.
        let eig = nalgebra::SymmetricEigen::new(-hess * scale);
        let floor_var = Vector3::new(
            c.min_std_xy * c.min_std_xy,
            c.min_std_xy * c.min_std_xy,
            c.min_std_theta * c.min_std_theta,
        );
        let lambda = Vector3::from_fn(|k, _| {
            let l = eig.eigenvalues[k].max(0.0);
            let e = eig.eigenvectors.column(k);
            let v: f64 = (0..3).map(|d| e[d] * e[d] * floor_var[d]).sum();
            // Floors the match's variance in this direction: 1/l + v.
            l / (1.0 + l * v)
        });
        let info =
            eig.eigenvectors * Matrix3::from_diagonal(&lambda) * eig.eigenvectors.transpose();
        Match {
            mode,
            info,
            overlap: hits as f64 / points.len() as f64,
        }
    }

    /// The fused proposal of a particle at `prev` whose scan matched at
    /// `mode` with information `info` (map frame), for the odometry motion
    /// `odometry`: the product of the two Gaussians, in information form
    /// (the motion model fills in where `info` is zero); `None` if it is
    /// not positive definite.
    pub fn fuse(
        &self,
        prev: &Pose2,
        odometry: &Pose2,
        mode: &Pose2,
        info: &Matrix3<f64>,
    ) -> Option<Proposal<Pose2>> {
        let (mu_p, sigma_p) = self.motion.local_gaussian(odometry);
        let local = prev.inverse() * mode;
        let (mx, my, mt) = xyt(&local);
        let mu_m = Vector3::new(mx, my, mu_p[2] + wrap_angle(mt - mu_p[2]));
        // Map-frame information into the previous robot frame.
        let r = rot3(-xyt(prev).2);
        let info_m = r * info * r.transpose();
        let info_p = sigma_p.try_inverse()?;
        let sigma = (info_m + info_p).try_inverse()?;
        let mu = sigma * (info_m * mu_m + info_p * Vector3::new(mu_p[0], mu_p[1], mu_p[2]));
        local_proposal([mu[0], mu[1], mu[2]], &sigma)
    }

    /// `q` joined by the motion model's Gaussian around `odometry` (a
    /// component with probability `motion_share`), or `q` itself where
    /// the share is 0 or that Gaussian is singular.
    fn defend(&self, q: Proposal<Pose2>, odometry: &Pose2) -> Proposal<Pose2> {
        let share = self.cfg.motion_share;
        if share <= 0.0 {
            return q;
        }
        let (mu, sigma) = self.motion.local_gaussian(odometry);
        let Some(Proposal::Matched {
            delta: dm,
            factor: lm,
        }) = local_proposal(mu, &sigma)
        else {
            return q;
        };
        let mut parts = match q {
            Proposal::Matched { delta, factor } => vec![(1.0 - share, delta, factor)],
            Proposal::Mixture(parts) => parts
                .into_iter()
                .map(|(w, d, f)| (w * (1.0 - share), d, f))
                .collect(),
            other => return other,
        };
        parts.push((share, dm, lm));
        Proposal::Mixture(parts)
    }

    /// The searched peak's proposal `best` of a particle at `prev`, joined
    /// by `near` (the peak nearest the odometry guess) with probability
    /// `odometry_peak_share` where `near`'s mean lies outside 3 σ of
    /// `best`'s; else `best` alone.
    fn mix(&self, prev: &Pose2, best: Proposal<Pose2>, near: Proposal<Pose2>) -> Proposal<Pose2> {
        let (
            Proposal::Matched {
                delta: db,
                factor: lb,
            },
            Proposal::Matched {
                delta: dn,
                factor: ln,
            },
        ) = (&best, &near)
        else {
            return best;
        };
        let apart = crate::proposal::whitened(prev, db, lb, &(prev * dn))
            .is_some_and(|z| z.norm_squared() > 9.0);
        if !apart {
            return best;
        }
        let share = self.cfg.odometry_peak_share.min(1.0);
        Proposal::Mixture(vec![
            (1.0 - share, *db, lb.clone()),
            (share, *dn, ln.clone()),
        ])
    }
}

/// The matched proposal N(`mu`, `sigma`) of a motion in the previous robot
/// frame (`[x m, y m, θ rad]`), its covariance turned into the body frame
/// of the mean (`pose2(μ) · pose2(ξ)` moves by R(μθ)·ξ_xy); `None` if it is
/// not positive definite.
fn local_proposal(mu: [f64; 3], sigma: &Matrix3<f64>) -> Option<Proposal<Pose2>> {
    let rb = rot3(-mu[2]);
    let body = rb * sigma * rb.transpose();
    let body = (body + body.transpose()) * 0.5;
    Proposal::matched(
        pose2(mu[0], mu[1], mu[2]),
        DMatrix::from_column_slice(3, 3, body.as_slice()),
    )
}

/// Hit cells a wall test needs around a cell to call it part of a wall.
const WALL_MIN_CELLS: f64 = 6.0;
/// Largest ratio of the smaller to the larger eigenvalue of those cells'
/// spread for a wall: a thin line (a digitised line gives ≈ 0.005–0.02, a
/// disc or a blob ≈ 1).
const WALL_MAX_SPREAD: f64 = 0.05;

/// Per cell of `cells` (distinct grid cells with hits), whether it belongs
/// to a wall: it lies within `radius` cells of a line cell, one whose
/// disc of `radius` cells holds at least [`WALL_MIN_CELLS`] of `cells`
/// spread as a thin line ([`WALL_MAX_SPREAD`]).
fn wall_cells(cells: &[[i32; 2]], radius: i32) -> Vec<bool> {
    let Some((lo, hi)) = cells
        .iter()
        .fold(None, |b: Option<([i32; 2], [i32; 2])>, k| {
            Some(match b {
                None => (*k, *k),
                Some((lo, hi)) => (
                    [lo[0].min(k[0]), lo[1].min(k[1])],
                    [hi[0].max(k[0]), hi[1].max(k[1])],
                ),
            })
        })
    else {
        return Vec::new();
    };
    let w = (hi[0] - lo[0] + 1) as usize;
    let h = (hi[1] - lo[1] + 1) as usize;
    let index = |k: &[i32; 2]| (k[1] - lo[1]) as usize * w + (k[0] - lo[0]) as usize;
    let r = radius;
    // The disc of radius `r`: offsets, row by row, with their grid steps.
    let offsets: Vec<(i32, i32, isize)> = (-r..=r)
        .flat_map(|dy| {
            (-r..=r)
                .filter(move |dx| dx * dx + dy * dy <= r * r)
                .map(move |dx| (dx, dy, dy as isize * w as isize + dx as isize))
        })
        .collect();
    // Offsets and grid indices of the disc around `k`, clipped to the box
    // (a disc inside the box, the usual case, needs no test per offset).
    let disc = |k: &[i32; 2]| {
        let (cx, cy) = (k[0] - lo[0], k[1] - lo[1]);
        let centre = cy as isize * w as isize + cx as isize;
        let inside = cx >= r && cy >= r && cx + r < w as i32 && cy + r < h as i32;
        offsets.iter().filter_map(move |&(dx, dy, step)| {
            let (x, y) = (cx + dx, cy + dy);
            (inside || (x >= 0 && x < w as i32 && y >= 0 && y < h as i32)).then_some((
                dx,
                dy,
                (centre + step) as usize,
            ))
        })
    };
    let mut grid = vec![false; w * h];
    for k in cells {
        grid[index(k)] = true;
    }
    let line: Vec<bool> = cells
        .par_iter()
        .map(|k| {
            let (mut n, mut sx, mut sy, mut sxx, mut syy, mut sxy) =
                (0.0f64, 0.0, 0.0, 0.0, 0.0, 0.0);
            for (dx, dy, at) in disc(k) {
                if grid[at] {
                    let (fx, fy) = (dx as f64, dy as f64);
                    n += 1.0;
                    sx += fx;
                    sy += fy;
                    sxx += fx * fx;
                    syy += fy * fy;
                    sxy += fx * fy;
                }
            }
            if n < WALL_MIN_CELLS {
                return false;
            }
            let (mx, my) = (sx / n, sy / n);
            let (a, b, d) = (sxx / n - mx * mx, sxy / n - mx * my, syy / n - my * my);
            let half = 0.5 * (a + d);
            let disc = (0.25 * (a - d) * (a - d) + b * b).sqrt();
            let (large, small) = (half + disc, half - disc);
            large > 0.0 && small <= WALL_MAX_SPREAD * large
        })
        .collect();
    // Corners, wall ends and door frames fail the line test (two lines in
    // one disc), yet they are what fixes a match along a corridor: weighing
    // them like the wall they end keeps that hold (sim2d ATE 0.092 → 0.056
    // m, docs/PROPOSAL-2D.md, session 17).
    let mut on = vec![false; w * h];
    for (k, _) in cells.iter().zip(&line).filter(|(_, l)| **l) {
        on[index(k)] = true;
    }
    cells
        .par_iter()
        .map(|k| disc(k).any(|(_, _, at)| on[at]))
        .collect()
}

/// How the particle groups of one step see a map cell.
#[derive(Clone, Copy)]
enum Seen {
    /// Every group sees this entry (`None`: no entry with a hit).
    Alike(Option<crate::dpmap::Entry>),
    /// The groups' lineages wrote it differently: resolve per view.
    Varying,
}

/// Rotation by `a` of the `[x, y]` block, identity on θ.
fn rot3(a: f64) -> Matrix3<f64> {
    let (s, c) = a.sin_cos();
    let r = Matrix2::new(c, -s, s, c);
    let mut m = Matrix3::identity();
    m.fixed_view_mut::<2, 2>(0, 0).copy_from(&r);
    m
}

impl ScanRegistration<2, Pose2> for ScanMatcher2d {
    fn propose(&self, ctx: &MatchContext<'_, 2, Pose2>) -> Vec<Proposal<Pose2>> {
        let c = &self.cfg;
        let res = self.res();
        // What an earlier call built is out of date from here on.
        self.last.lock().expect("not poisoned").of_particle.clear();
        let (points, beams) = self.endpoints(ctx.scan);
        let n = ctx.particles.len();
        if points.is_empty() || n == 0 {
            return vec![Proposal::Motion; n];
        }
        let reach = points
            .iter()
            .map(|p| (p[0] * p[0] + p[1] * p[1]).sqrt())
            .fold(0.0, f64::max)
            + c.window_xy
            + 2.0 * c.sigma
            + 2.0 * c.coarse_factor as f64 * res;
        let guesses: Vec<Pose2> = ctx
            .particles
            .iter()
            .map(|p| p.pose * ctx.odometry)
            .collect();
        // Groups in order of first appearance.
        let mut keys: Vec<NodeId> = Vec::new();
        let mut members: Vec<Vec<usize>> = Vec::new();
        for (i, &g) in ctx.groups.iter().enumerate() {
            match keys.iter().position(|&k| k == g) {
                Some(at) => members[at].push(i),
                None => {
                    keys.push(g);
                    members.push(vec![i]);
                }
            }
        }
        let boxes: Vec<([f64; 2], [f64; 2])> = members
            .iter()
            .map(|m| {
                let mut lo = [f64::INFINITY; 2];
                let mut hi = [f64::NEG_INFINITY; 2];
                for &i in m {
                    let t = guesses[i].translation;
                    lo = [lo[0].min(t.x - reach), lo[1].min(t.y - reach)];
                    hi = [hi[0].max(t.x + reach), hi[1].max(t.y + reach)];
                }
                (lo, hi)
            })
            .collect();
        // Cells anyone has seen a hit in, once for all groups, in storage
        // order. A cell whose list holds only observations every group
        // inherits (from a common ancestor) or none inherits looks the same
        // through every view: it is resolved here, once. Only cells written
        // since the groups' lineages split (about what the robot sees now)
        // are resolved through each group's view: on fr079-raw's first
        // ~700 scans, about 30 % of the ~6 500 hit cells in reach.
        let cell = self.cell;
        let lo = boxes.iter().fold([f64::INFINITY; 2], |a, b| {
            [a[0].min(b.0[0]), a[1].min(b.0[1])]
        });
        let hi = boxes.iter().fold([f64::NEG_INFINITY; 2], |a, b| {
            [a[0].max(b.1[0]), a[1].max(b.1[1])]
        });
        let leaves: Vec<NodeId> = members.iter().map(|m| ctx.particles[m[0]].node).collect();
        let (enter, exit) = (&ctx.numbering.enter, &ctx.numbering.exit);
        // Every leaf's pre-order index lies in [first, last]: a node whose
        // subtree holds both holds them all.
        let (first, last) = leaves.iter().fold((u32::MAX, 0), |(a, b), &n| {
            (a.min(enter[n as usize]), b.max(enter[n as usize]))
        });
        let seen_alike = |list: &[crate::dpmap::Entry]| -> Option<Option<crate::dpmap::Entry>> {
            let mut best: Option<(u32, crate::dpmap::Entry)> = None;
            for e in list {
                let (en, ex) = (enter[e.node as usize], exit[e.node as usize]);
                if en <= first && last <= ex {
                    if best.is_none_or(|b| en > b.0) {
                        best = Some((en, *e));
                    }
                } else if !(ex < first || en > last) {
                    // An ancestor of some leaves, not all.
                    return None;
                }
            }
            Some(best.map(|b| b.1))
        };
        let weight_of = |e: &crate::dpmap::Entry, wall: bool| {
            let stop = || crate::laser_model::stop_probability(e.hits, e.distance, cell);
            match c.field_weight {
                FieldWeight::StopProbability => stop(),
                FieldWeight::Hits => 1.0,
                FieldWeight::Walls if wall => 1.0,
                FieldWeight::Walls => stop(),
            }
        };
        let bits = crate::dpmap::DpMap::<2>::brick_bits();
        let brick = |x: f64| ((x / cell).floor() as i32) >> bits;
        let (bx0, bx1, by0, by1) = (brick(lo[0]), brick(hi[0]), brick(lo[1]), brick(hi[1]));
        let hit_cells: Vec<([i32; 2], Seen)> = (by0..=by1)
            .into_par_iter()
            .flat_map_iter(|by| {
                let mut out = Vec::new();
                for bx in bx0..=bx1 {
                    ctx.map.for_each_hit_cell_in_brick([bx, by], |k, list| {
                        if list.iter().any(|e| c.field_keeps(e.hits)) {
                            let seen = match seen_alike(list) {
                                Some(Some(e)) if c.field_keeps(e.hits) => Seen::Alike(Some(e)),
                                Some(_) => Seen::Alike(None),
                                None => Seen::Varying,
                            };
                            out.push((k, seen));
                        }
                    });
                }
                out
            })
            .collect();
        let walls: Vec<bool> = match c.field_weight {
            FieldWeight::Walls => {
                let radius = (c.wall_radius / cell).round().max(1.0) as i32;
                let keys: Vec<[i32; 2]> = hit_cells.iter().map(|h| h.0).collect();
                wall_cells(&keys, radius)
            }
            _ => Vec::new(),
        };
        // Field weights of the cells every view sees alike, once.
        let alike: Vec<Option<f64>> = hit_cells
            .iter()
            .enumerate()
            .map(|(at, (_, seen))| match seen {
                Seen::Alike(Some(e)) => Some(weight_of(e, walls.get(at) == Some(&true))),
                _ => None,
            })
            .collect();
        let per_group: Vec<Vec<Registered>> = members
            .par_iter()
            .zip(boxes.par_iter())
            .map(|(m, &(lo, hi))| {
                let mut view = ctx.map.view(ctx.numbering, ctx.particles[m[0]].node);
                let occupied: Vec<([f64; 2], f64)> = hit_cells
                    .iter()
                    .enumerate()
                    .filter_map(|(at, &(k, seen))| {
                        let x = (k[0] as f64 + 0.5) * cell;
                        let y = (k[1] as f64 + 0.5) * cell;
                        if x < lo[0] || x > hi[0] || y < lo[1] || y > hi[1] {
                            return None;
                        }
                        let weight = match seen {
                            Seen::Alike(_) => alike[at]?,
                            Seen::Varying => {
                                let e = view.entry(k)?;
                                if !c.field_keeps(e.hits) {
                                    return None;
                                }
                                weight_of(&e, walls.get(at) == Some(&true))
                            }
                        };
                        Some(([x, y], weight))
                    })
                    .collect();
                let field = Arc::new(self.field(lo, hi, &occupied));
                // With `per_group`, one registration per group: its members
                // share the view, and their guesses differ by their own last
                // samples' spread (cm), inside the search window, so the
                // map-frame mode and its information are the group's; each
                // member fuses them with its own motion prior. Otherwise
                // each member registers from its own guess.
                let shared = c.per_group.then(|| {
                    let first = &ctx.particles[m[0]].pose;
                    self.register_from(&field, &points, beams, first, ctx.odometry)
                });
                // Resampled copies of one sample share its node and pose, so
                // their proposals are the same: each is computed once.
                let mut known: Vec<([u64; 4], Proposal<Pose2>)> = Vec::new();
                m.iter()
                    .map(|&i| {
                        let prev = &ctx.particles[i].pose;
                        let key = pose_bits(prev);
                        if let Some((_, q)) = known.iter().find(|(k, _)| *k == key) {
                            return (i, q.clone(), field.clone());
                        }
                        let own = || self.register_from(&field, &points, beams, prev, ctx.odometry);
                        let q = match &shared {
                            Some(r) => r
                                .as_ref()
                                .and_then(|r| self.fuse(prev, ctx.odometry, &r.mode, &r.info)),
                            None => {
                                own().and_then(|r| self.fuse(prev, ctx.odometry, &r.mode, &r.info))
                            }
                        }
                        .map(|q| {
                            if c.odometry_peak_share <= 0.0 {
                                return q;
                            }
                            let near = self
                                .climb(&field, &points, beams, &guesses[i])
                                .filter(|r| r.overlap >= c.min_overlap)
                                .and_then(|r| self.fuse(prev, ctx.odometry, &r.mode, &r.info));
                            match near {
                                Some(near) => self.mix(prev, q, near),
                                None => q,
                            }
                        })
                        .map(|q| self.defend(q, ctx.odometry))
                        .unwrap_or(Proposal::Motion);
                        known.push((key, q.clone()));
                        (i, q, field.clone())
                    })
                    .collect()
            })
            .collect();
        let mut out = vec![Proposal::Motion; n];
        let mut fields = vec![None; n];
        for (i, q, field) in per_group.into_iter().flatten() {
            out[i] = q;
            fields[i] = Some(field);
        }
        self.last.lock().expect("not poisoned").of_particle = fields;
        out
    }

    fn rematch(
        &self,
        origin: usize,
        prev: &Pose2,
        odometry: &Pose2,
        scan: &Scan<2, Pose2>,
    ) -> Option<Proposal<Pose2>> {
        let field = self
            .last
            .lock()
            .expect("not poisoned")
            .of_particle
            .get(origin)?
            .clone()?;
        let (points, beams) = self.endpoints(scan);
        if points.is_empty() {
            return Some(Proposal::Motion);
        }
        let matched = self
            .register_from(&field, &points, beams, prev, odometry)
            .and_then(|r| self.fuse(prev, odometry, &r.mode, &r.info));
        Some(matched.unwrap_or(Proposal::Motion))
    }
}

/// A pose's exact bit pattern: equal keys, equal poses.
fn pose_bits(p: &Pose2) -> [u64; 4] {
    [
        p.translation.x.to_bits(),
        p.translation.y.to_bits(),
        p.rotation.re.to_bits(),
        p.rotation.im.to_bits(),
    ]
}

/// The first of `points` (in order) in each `spacing`-wide square of the
/// plane; all of them where `spacing` is not a positive number.
fn one_per_square(points: Vec<[f64; 2]>, spacing: f64) -> Vec<[f64; 2]> {
    if !spacing.is_finite() || spacing <= 0.0 {
        return points;
    }
    let mut seen = rustc_hash::FxHashSet::default();
    points
        .into_iter()
        .filter(|p| {
            seen.insert([
                (p[0] / spacing).floor() as i64,
                (p[1] / spacing).floor() as i64,
            ])
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn endpoint_spacing_keeps_one_return_per_square_in_beam_order() {
        // A fan of 1° beams: 40 returns on a post 0.4 m ahead (1 cm apart)
        // and 40 on a wall 8 m away (14 cm apart).
        let near: Vec<[f64; 2]> = (0..40)
            .map(|i| {
                let a = (i as f64 - 20.0).to_radians();
                [0.4 * a.cos(), 0.4 * a.sin()]
            })
            .collect();
        let far: Vec<[f64; 2]> = (0..40)
            .map(|i| {
                let a = (i as f64 + 30.0).to_radians();
                [8.0 * a.cos(), 8.0 * a.sin()]
            })
            .collect();
        let all: Vec<[f64; 2]> = near.iter().chain(&far).copied().collect();
        assert_eq!(one_per_square(all.clone(), 0.0), all);
        let kept = one_per_square(all.clone(), 0.1);
        let kept_near = kept.iter().filter(|p| p[0].hypot(p[1]) < 1.0).count();
        // The post spans 0.28 m across: a handful of 0.1 m squares, not 40
        // returns; the wall's returns are farther apart than a square.
        assert!(
            (2..=6).contains(&kept_near),
            "{kept_near} near returns kept"
        );
        assert_eq!(kept.len() - kept_near, 40);
        // Kept in beam order, each the first of its square.
        let pos: Vec<usize> = kept
            .iter()
            .map(|k| all.iter().position(|p| p == k).unwrap())
            .collect();
        assert!(pos.windows(2).all(|w| w[0] < w[1]));
        assert_eq!(pos[0], 0);
    }

    fn matcher() -> ScanMatcher2d {
        ScanMatcher2d::new(
            ScanMatchConfig::default(),
            CdtModel {
                cfg: crate::config::Motion2dConfig::default(),
            },
            1.0 / 35.0,
            0.017,
        )
    }

    /// A room's walls as occupied points (map frame) and the endpoints a
    /// scan from `at` sees of them (robot frame), every few degrees.
    /// Occupied points (map frame) with stop probabilities.
    type Walls = Vec<([f64; 2], f64)>;

    fn room(at: &Pose2) -> (Walls, Vec<[f64; 2]>) {
        let (w, h) = (6.0, 4.0);
        let mut walls = Vec::new();
        let step = 1.0 / 35.0;
        let mut t = 0.0;
        while t <= w {
            walls.push(([t, 0.0], 0.9));
            walls.push(([t, h], 0.9));
            t += step;
        }
        let mut t = 0.0;
        while t <= h {
            walls.push(([0.0, t], 0.9));
            walls.push(([w, t], 0.9));
            t += step;
        }
        // Ray-cast the rectangle from `at`.
        let (x0, y0, th) = xyt(at);
        let mut points = Vec::new();
        for k in 0..120 {
            let a = th + k as f64 * std::f64::consts::TAU / 120.0;
            let (dx, dy) = (a.cos(), a.sin());
            let mut best = f64::INFINITY;
            for (lim, d, o) in [(0.0, dx, x0), (w, dx, x0), (0.0, dy, y0), (h, dy, y0)] {
                if d.abs() > 1e-9 {
                    let r = (lim - o) / d;
                    if r > 0.0 {
                        let (px, py) = (x0 + r * dx, y0 + r * dy);
                        if (-1e-6..=w + 1e-6).contains(&px) && (-1e-6..=h + 1e-6).contains(&py) {
                            best = best.min(r);
                        }
                    }
                }
            }
            let p = at.inverse() * nalgebra::Point2::new(x0 + best * dx, y0 + best * dy);
            points.push([p.x, p.y]);
        }
        (walls, points)
    }

    #[test]
    fn a_slip_of_40_cm_and_12_degrees_is_found_to_a_few_centimetres() {
        let m = matcher();
        let truth = pose2(2.5, 1.8, 0.3);
        let (walls, points) = room(&truth);
        let field = m.field([-2.0, -2.0], [8.0, 6.0], &walls);
        // The odometry guess is off by 0.4 m, −0.3 m and 12°.
        let guess = pose2(2.9, 1.5, 0.3 + 12f64.to_radians());
        let r = m
            .register(&field, &m.log_field, &points, points.len(), &guess, None)
            .unwrap();
        let (mode, overlap) = (r.mode, r.overlap);
        let cov = r.info.try_inverse().unwrap();
        let e = truth.inverse() * mode;
        // Within one field cell (5.7 cm: these walls lie half-way between
        // cell centres, where the interpolated field is flat for ±res/2)
        // and 0.6°.
        assert!(e.translation.vector.norm() < 0.045, "{e:?}");
        assert!(e.rotation.angle().abs() < 0.01, "{e:?}");
        // Inside three of the match's own stds.
        let (ex, ey) = (e.translation.x, e.translation.y);
        assert!(ex.abs() < 3.0 * cov[(0, 0)].sqrt() + 0.005, "{e:?} {cov}");
        assert!(ey.abs() < 3.0 * cov[(1, 1)].sqrt() + 0.005, "{e:?} {cov}");
        assert!(overlap > 0.9, "{overlap}");
        // A closed room pins every direction: about a centimetre, < 1°.
        assert!(
            cov[(0, 0)].sqrt() < 0.03 && cov[(1, 1)].sqrt() < 0.03,
            "{cov}"
        );
        assert!(cov[(2, 2)].sqrt() < 0.015, "{cov}");
    }

    /// The room's walls, faint, where the odometry puts the robot, and a
    /// strong copy 0.3 m on: the search takes the copy, the climb from
    /// the guess stays on the faint room, and with `odometry_peak_share`
    /// the proposal draws that share of its samples there.
    #[test]
    fn a_peak_near_the_odometry_joins_a_far_better_one_in_a_mixture() {
        let mut m = matcher();
        m.cfg.odometry_peak_share = 0.25;
        let truth = pose2(2.5, 1.8, 0.0);
        let (walls, points) = room(&truth);
        let mut both: Walls = walls.iter().map(|&(p, _)| (p, 0.45)).collect();
        both.extend(walls.iter().map(|&(p, _)| ([p[0] + 0.3, p[1]], 0.9)));
        let field = m.field([-2.0, -2.0], [8.0, 6.0], &both);
        let odometry = pose2(0.5, 0.0, 0.0);
        let prev = truth * odometry.inverse();
        let lut = m.log_field;
        let far = m
            .register(&field, &lut, &points, points.len(), &truth, None)
            .unwrap();
        let near = m.climb(&field, &points, points.len(), &truth).unwrap();
        assert!(
            (far.mode.translation.x - 2.8).abs() < 0.03,
            "{:?}",
            far.mode
        );
        assert!(
            (near.mode.translation.x - 2.5).abs() < 0.03,
            "{:?}",
            near.mode
        );
        let fused = |r: &Match| m.fuse(&prev, &odometry, &r.mode, &r.info).unwrap();
        let Proposal::Mixture(parts) = m.mix(&prev, fused(&far), fused(&near)) else {
            panic!("two peaks 0.3 m apart make a mixture");
        };
        assert_eq!(parts.len(), 2);
        assert_eq!((parts[0].0, parts[1].0), (0.75, 0.25));
        for (part, x) in parts.iter().zip([2.8, 2.5]) {
            let mean = prev * part.1;
            assert!((mean.translation.x - x).abs() < 0.03, "{mean:?}");
        }
        // A peak inside the best one's spread adds nothing.
        assert!(matches!(
            m.mix(&prev, fused(&far), fused(&far)),
            Proposal::Matched { .. }
        ));
    }

    /// A match 30° off the odometry (a confident wrong peak) with
    /// `motion_share` 0.2: a fifth of the samples land around the motion
    /// model's mean, and a sample at the odometry weighs at most about
    /// 1 / share times its likelihood; with the share at 0 the match is
    /// left alone.
    #[test]
    fn a_motion_share_keeps_samples_at_the_odometry_under_a_wrong_match() {
        use crate::motion_model::MotionModel;
        use rand::SeedableRng;
        let mut m = matcher();
        let prev = pose2(1.0, 2.0, 0.3);
        let odometry = pose2(0.3, 0.0, 0.05);
        let info = Matrix3::from_diagonal(&Vector3::new(1e4, 1e4, 1e5));
        let wrong = prev * odometry * pose2(0.0, 0.0, 30f64.to_radians());
        let matched = m.fuse(&prev, &odometry, &wrong, &info).unwrap();
        assert_eq!(m.defend(matched.clone(), &odometry), matched);
        m.cfg.motion_share = 0.2;
        let Proposal::Mixture(parts) = m.defend(matched.clone(), &odometry) else {
            panic!("a motion share makes a mixture");
        };
        assert_eq!(parts.len(), 2);
        assert_eq!((parts[0].0, parts[1].0), (0.8, 0.2));
        let mix = Proposal::Mixture(parts);
        let at_odometry = prev * odometry;
        let mut rng = rand_pcg::Pcg64::seed_from_u64(7);
        let n = 20000;
        let near = (0..n)
            .filter(|_| {
                let p: Pose2 = mix.sample::<2>(&m.motion, &prev, &odometry, &mut rng);
                let e = at_odometry.inverse() * p;
                e.rotation.angle().abs() < 15f64.to_radians()
            })
            .count();
        let share = near as f64 / n as f64;
        assert!((share - 0.2).abs() < 0.015, "{share}");
        // Importance weight at the odometry: motion density / mixture
        // density, bounded by the motion part; the match alone would
        // give it almost nothing to weigh.
        let r_mix = mix.log_ratio::<2>(&m.motion, &prev, &odometry, &at_odometry);
        assert!(r_mix <= (1.0f64 / 0.2).ln() + 0.1, "{r_mix}");
        assert!(r_mix > 0.0, "{r_mix}");
        assert!(
            m.motion
                .log_density(&prev, &odometry, &at_odometry)
                .is_some()
        );
    }

    /// A corridor whose walls carry posts every 0.5 m: two poses 0.5 m
    /// apart along it inside the window match the scan equally well. The
    /// motion prior decides between them, whichever side the guess is on.
    #[test]
    fn the_motion_prior_picks_between_repeated_structures() {
        let m = matcher();
        let post = |x: f64, y: f64| ([x, y], 0.9);
        let mut walls = Vec::new();
        for k in -60..=60 {
            let x = k as f64 * 0.5;
            // A post: a 3-cell stub out of each wall.
            for d in 0..3 {
                let d = d as f64 / 35.0;
                walls.push(post(x, 0.0 + d));
                walls.push(post(x, 2.0 - d));
            }
        }
        // The scan from (0, 1), heading 0, sees the posts at x in [-2, 2].
        let points: Vec<[f64; 2]> = (-4..=4)
            .flat_map(|k| {
                let x = k as f64 * 0.5;
                (0..3).flat_map(move |d| {
                    let d = d as f64 / 35.0;
                    [[x, -1.0 + d], [x, 1.0 - d]]
                })
            })
            .collect();
        let field = m.field([-32.0, -4.0], [32.0, 6.0], &walls);
        let info = Matrix3::from_diagonal(&Vector3::new(1.0 / 0.01, 1.0 / 0.01, 1.0 / 0.01));
        for (prior_x, want_x) in [(0.15, 0.0), (0.35, 0.5), (-0.15, 0.0), (-0.35, -0.5)] {
            let prior = SearchPrior {
                mean: [prior_x, 1.0, 0.0],
                info,
            };
            // The guess is where the odometry says; the window (±0.5 m)
            // holds both the post pattern at x = 0 and a copy 0.5 m away.
            let guess = pose2(prior_x, 1.0, 0.0);
            let r = m
                .register(&field, &m.log_field, &points, 180, &guess, Some(&prior))
                .unwrap();
            let x = r.mode.translation.x;
            assert!(
                (x - want_x).abs() < 0.05,
                "prior at {prior_x}: mode {x}, want {want_x}"
            );
        }
    }

    #[test]
    fn a_corridor_leaves_its_axis_to_the_motion_model() {
        let m = matcher();
        // Two long parallel walls along x, 2 m apart; the scan sees 4 m of each.
        let mut walls = Vec::new();
        let mut t = -20.0;
        while t <= 20.0 {
            walls.push(([t, 0.0], 0.9));
            walls.push(([t, 2.0], 0.9));
            t += 1.0 / 35.0;
        }
        let points: Vec<[f64; 2]> = (0..60)
            .map(|k| {
                let x = -2.0 + k as f64 * 4.0 / 30.0;
                if k < 30 { [x, -1.0] } else { [x - 4.0, 1.0] }
            })
            .collect();
        let field = m.field([-22.0, -4.0], [22.0, 6.0], &walls);
        let guess = pose2(0.0, 1.1, 0.0);
        // The 60 endpoints thinned from a scan of 180 returns.
        let r = m
            .register(&field, &m.log_field, &points, 180, &guess, None)
            .unwrap();
        let (mode, info) = (r.mode, r.info);
        assert!((mode.translation.y - 1.0).abs() < 0.03, "{mode:?}");
        // Across: sharp (a std of a few cm); along: (almost) no information.
        assert!(info[(1, 1)] > 1.0 / (0.05 * 0.05), "{info}");
        assert!(info[(0, 0)] < 1.0 / (0.5 * 0.5), "{info}");
        // Fused with the motion model for 0.3 m straight ahead, the axis
        // keeps (about) the model's spread and the cross direction the match's.
        let prev = pose2(0.0, 1.1, 0.0);
        let odo = pose2(0.3, 0.0, 0.0);
        let q = m.fuse(&prev, &odo, &mode, &info).unwrap();
        let Proposal::Matched { delta, factor } = q else {
            panic!("not matched")
        };
        let body = &factor * factor.transpose();
        let (_, motion) = m.motion.local_gaussian(&odo);
        assert!(body[(0, 0)].sqrt() > 0.5 * motion[(0, 0)].sqrt(), "{body}");
        // Across, sharper than the motion model alone.
        assert!(body[(1, 1)] < motion[(1, 1)], "{body} {motion}");
        // The fused mean moves from the odometry (0) towards the match's y
        // (−0.1 m): 60 endpoints scaled to the DP likelihood pin y to about
        // the motion model's own 2.3 cm, so it lands in between.
        let y = delta.translation.y;
        assert!((-0.1..-0.04).contains(&y), "{delta:?}");
    }

    #[test]
    fn lines_of_hit_cells_are_walls_and_blobs_are_not() {
        // A wall along x, one along a 30° diagonal (digitised), an L, a
        // 4 × 4 blob, a ring of radius 4 cells (a person's outline) and a lone
        // cell, far enough apart not to see each other.
        let mut cells: Vec<[i32; 2]> = (0..30).map(|x| [x, 0]).collect();
        let diagonal: Vec<[i32; 2]> = (0..30)
            .map(|x| {
                [
                    x,
                    100 + (x as f64 * 30f64.to_radians().tan()).round() as i32,
                ]
            })
            .collect();
        cells.extend(&diagonal);
        let blob: Vec<[i32; 2]> = (0..16).map(|i| [200 + i % 4, 200 + i / 4]).collect();
        cells.extend(&blob);
        let mut ring: Vec<[i32; 2]> = (0..64)
            .map(|i| {
                let a = i as f64 / 64.0 * std::f64::consts::TAU;
                [
                    300 + (4.0 * a.cos()).round() as i32,
                    300 + (4.0 * a.sin()).round() as i32,
                ]
            })
            .collect();
        ring.sort();
        ring.dedup();
        cells.extend(&ring);
        cells.push([400, 400]);
        let corner = [500, 500];
        cells.extend((0..20).map(|i| [500 + i, 500]));
        cells.extend((1..20).map(|i| [500, 500 + i]));
        let walls = wall_cells(&cells, 5);
        assert_eq!(walls.len(), cells.len());
        let of = |k: [i32; 2]| walls[cells.iter().position(|c| *c == k).unwrap()];
        assert!((0..30).all(|x| of([x, 0])), "straight wall");
        assert!(diagonal.iter().all(|&k| of(k)), "diagonal wall");
        // The corner of an L: its disc holds two lines, it is no line cell,
        // but it lies next to both walls' line cells.
        assert!(of(corner), "corner");
        assert!(blob.iter().all(|&k| !of(k)), "blob");
        assert!(ring.iter().all(|&k| !of(k)), "ring");
        assert!(!of([400, 400]), "lone cell");
        assert!(wall_cells(&[], 5).is_empty());
    }

    #[test]
    fn walls_seen_head_on_pull_a_stop_probability_match_along_a_corridor() {
        let m = matcher();
        // A corridor along x, 2 m wide. The robot passed x = −1…0 before:
        // walls it saw there head-on have a high stop probability, the rest
        // (seen at grazing incidence) a low one.
        let seen_head_on = |x: f64| (-1.0..=0.0).contains(&x);
        let mut by_stop = Vec::new();
        let mut by_hits = Vec::new();
        let mut t = -20.0;
        while t <= 20.0 {
            let w = if seen_head_on(t) { 0.9 } else { 0.15 };
            for y in [0.0, 2.0] {
                by_stop.push(([t, y], w));
                by_hits.push(([t, y], 1.0));
            }
            t += 1.0 / 35.0;
        }
        // Now at x = 1 (it moved 1 m), the scan sees 4 m of each wall,
        // densest abeam.
        let points: Vec<[f64; 2]> = (0..60)
            .map(|k| {
                let a = -1.3 + 2.6 * (k % 30) as f64 / 29.0;
                let side = if k < 30 { -1.0 } else { 1.0 };
                [a.tan().clamp(-2.0, 2.0), side]
            })
            .collect();
        let guess = pose2(1.0, 1.0, 0.0);
        let mode_x = |walls: &Walls| {
            let field = m.field([-22.0, -4.0], [22.0, 6.0], walls);
            let r = m
                .register(&field, &m.log_field, &points, 180, &guess, None)
                .unwrap();
            (r.mode.translation.x, r.info[(0, 0)])
        };
        // Weighed by stop probability, the match slides back towards the
        // walls seen head-on, and says it knows x better.
        let (x, info_stop) = mode_x(&by_stop);
        assert!(x < 0.75, "{x}");
        // Every cell with a hit alike: nothing along the axis to match.
        let (_, info_hits) = mode_x(&by_hits);
        assert!(info_hits < 1.0 / (0.5 * 0.5), "{info_hits}");
        assert!(info_stop > 10.0 * info_hits, "{info_stop} {info_hits}");
    }
}
