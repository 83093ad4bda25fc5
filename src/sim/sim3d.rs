//! 3-D simulator: a building of axis-aligned boxes and planar patches, a
//! vehicle driving a closed loop through it (up a ramp onto a mezzanine and
//! back down), a spinning multi-ring lidar ray-cast exactly against the
//! scene, and 6-DoF odometry corrupted by a known noise model.
//!
//! The output is what a real vehicle would log (one KITTI `.bin` sweep per
//! pose, in the sensor frame, plus the noisy odometry as a TUM trajectory)
//! and what it never knows (the true sensor poses, as a TUM trajectory), so a
//! 3-D SLAM run on the sweeps can be scored against truth.
//!
//! Frames: the **world frame** is the map frame of the truth trajectory
//! (metres, right-handed, z up, the ground floor at z = 0). Both trajectories
//! give the **sensor** pose (sensor-to-world), so a sweep's points map into
//! the world by its truth pose. The sensor sits `sensor_height` above the
//! vehicle's ground contact point along the vehicle's up axis, looking along
//! the vehicle's +x (forward) axis. Odometry starts at the true first pose and
//! then drifts in all six degrees of freedom.
//!
//! The vehicle's attitude comes from the ground under its four wheels, so
//! the ramp gives height change and pitch, and the path, which crosses the
//! ramps diagonally, gives roll as well.
//!
//! Each sweep is taken at one instant (no motion distortion within a
//! revolution). Time stamps are the sweep index in seconds.
//!
//! Everything is deterministic for a seed: the odometry noise and the range
//! noise come from two `Pcg64` streams derived from it.

use crate::eval::ate::{Alignment, AteOptions, evaluate_ate};
use crate::geometry::Pose3;
use crate::io::atomic::write_atomic;
use crate::io::tum::Stamped;
use crate::sim::path::SmoothPath;
use crate::{Error, Result};
use nalgebra::{Matrix3, Rotation3, Translation3, UnitQuaternion, Vector3};
use rand::{RngExt, SeedableRng};
use rand_distr::StandardNormal;
use rand_pcg::Pcg64;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::f64::consts::PI;
use std::io::Write as _;
use std::path::Path;

/// Bytes of one KITTI record: float32 `x y z intensity`.
pub const KITTI_RECORD: usize = 16;

/// Most rays one sweep may cast (rings × columns), so that a mistyped
/// configuration fails with a message instead of exhausting memory.
const MAX_RAYS_PER_SWEEP: usize = 1 << 22;

/// Most sweeps one simulation may produce.
const MAX_SWEEPS: usize = 1_000_000;

/// Most rays [`simulate3d`] may keep in memory in all (16 bytes a point);
/// [`write_sim3d`] streams and has no such limit.
const MAX_RAYS_IN_MEMORY: usize = 100_000_000;

/// Rays closer to parallel with a patch than this (|cos| of the angle
/// between ray and normal) miss it: a grazing ray sees nothing to stop it.
const PARALLEL_EPS: f64 = 1e-12;

// --------------------------------------------------------------- scene ---

/// An axis-aligned solid box (m, world frame).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Aabb {
    /// Corner with the smallest coordinates `[x, y, z]` (m).
    pub min: [f64; 3],
    /// Corner with the largest coordinates `[x, y, z]` (m).
    pub max: [f64; 3],
}

/// A planar parallelogram `origin + s·u + t·v`, s, t ∈ [0, 1] (m, world
/// frame); seen from both sides. Floors and ramps are patches.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Patch {
    /// One corner (m).
    pub origin: [f64; 3],
    /// First edge from `origin` (m).
    pub u: [f64; 3],
    /// Second edge from `origin` (m).
    pub v: [f64; 3],
}

/// Where a ray stopped.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Hit {
    /// Distance along the (unit) ray direction (m).
    pub distance: f64,
    /// Unit normal of the surface hit (either orientation; world frame).
    pub normal: [f64; 3],
}

fn v3(a: [f64; 3]) -> Vector3<f64> {
    Vector3::new(a[0], a[1], a[2])
}

/// First intersection at distance ≥ 0 of the ray from `origin` along unit
/// `dir` with the surface of `b`, or `None`.
///
/// Slab method. A ray that starts inside the box, or on its surface heading
/// inwards, sees nothing of it: the sensor is never inside a solid, and this
/// keeps a vehicle standing on a box top from seeing the box it stands on.
/// Rays that only graze a face or an edge count as hits.
pub fn ray_aabb(origin: [f64; 3], dir: [f64; 3], b: &Aabb) -> Option<Hit> {
    let (mut t0, mut t1) = (f64::NEG_INFINITY, f64::INFINITY);
    let mut axis = usize::MAX;
    for i in 0..3 {
        if dir[i] == 0.0 {
            // Parallel to this slab: in it for ever or never.
            if origin[i] < b.min[i] || origin[i] > b.max[i] {
                return None;
            }
            continue;
        }
        let inv = 1.0 / dir[i];
        let (mut a, mut c) = ((b.min[i] - origin[i]) * inv, (b.max[i] - origin[i]) * inv);
        if a > c {
            std::mem::swap(&mut a, &mut c);
        }
        if a > t0 {
            t0 = a;
            axis = i;
        }
        t1 = t1.min(c);
    }
    if axis == usize::MAX || t0 > t1 || t0 <= 0.0 {
        return None;
    }
    let mut normal = [0.0; 3];
    normal[axis] = -dir[axis].signum();
    Some(Hit {
        distance: t0,
        normal,
    })
}

/// Intersection at distance > 0 of the ray from `origin` along unit `dir`
/// with the patch `p` (edges included), or `None`. A ray parallel to the
/// patch misses it.
pub fn ray_patch(origin: [f64; 3], dir: [f64; 3], p: &Patch) -> Option<Hit> {
    let (o, d, u, v) = (v3(p.origin), v3(dir), v3(p.u), v3(p.v));
    let n = u.cross(&v);
    let nn = n.norm_squared();
    if nn == 0.0 {
        return None;
    }
    let denom = n.dot(&d);
    if denom.abs() <= PARALLEL_EPS * nn.sqrt() {
        return None;
    }
    let t = n.dot(&(o - v3(origin))) / denom;
    if t <= 0.0 {
        return None;
    }
    let w = v3(origin) + d * t - o;
    let s = w.cross(&v).dot(&n) / nn;
    let r = u.cross(&w).dot(&n) / nn;
    if !((0.0..=1.0).contains(&s) && (0.0..=1.0).contains(&r)) {
        return None;
    }
    let n = n / nn.sqrt();
    Some(Hit {
        distance: t,
        normal: [n.x, n.y, n.z],
    })
}

/// A scene of solid boxes and planar patches.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct World3d {
    /// Solid boxes: walls, pillars, clutter, raised floors (m, world frame).
    pub boxes: Vec<Aabb>,
    /// Planar patches: floors and ramps (m, world frame).
    pub patches: Vec<Patch>,
}

impl World3d {
    /// Nearest surface along the ray from `origin` (m, world frame) in the
    /// unit direction `dir`, or `None` if the ray escapes the scene.
    pub fn cast(&self, origin: [f64; 3], dir: [f64; 3]) -> Option<Hit> {
        let boxes = self.boxes.iter().filter_map(|b| ray_aabb(origin, dir, b));
        let patches = self
            .patches
            .iter()
            .filter_map(|p| ray_patch(origin, dir, p));
        boxes
            .chain(patches)
            .min_by(|a, b| a.distance.total_cmp(&b.distance))
    }

    /// Axis-aligned bounding box `(min, max)` of the scene (m), or `None` if
    /// it is empty.
    pub fn bounds(&self) -> Option<([f64; 3], [f64; 3])> {
        let corners =
            self.boxes
                .iter()
                .flat_map(|b| [b.min, b.max])
                .chain(self.patches.iter().flat_map(|p| {
                    let (o, u, v) = (v3(p.origin), v3(p.u), v3(p.v));
                    [o, o + u, o + v, o + u + v].map(|c| [c.x, c.y, c.z])
                }));
        corners.fold(None, |acc, c| {
            let (lo, hi) = acc.unwrap_or((c, c));
            Some((
                [0, 1, 2].map(|i| lo[i].min(c[i])),
                [0, 1, 2].map(|i| hi[i].max(c[i])),
            ))
        })
    }

    /// Height (m) of the highest surface under the point `(x, y)` (m), found
    /// by casting a ray straight down from above the scene; `None` if there
    /// is nothing underneath. Overhangs (a lintel over a doorway) count as
    /// ground, so paths must not pass under them.
    pub fn ground_height(&self, x: f64, y: f64) -> Option<f64> {
        let top = self.bounds()?.1[2] + 1.0;
        self.ground_height_below(x, y, top)
    }

    fn ground_height_below(&self, x: f64, y: f64, top: f64) -> Option<f64> {
        self.cast([x, y, top], [0.0, 0.0, -1.0])
            .map(|h| top - h.distance)
    }

    /// The built-in building, 23 m × 19 m, walls 4.5 m tall, no roof.
    ///
    /// A corridor ring 3 m wide whose centre line is the rectangle
    /// (0, 0)–(20, 0)–(20, 12)–(0, 12). The north part of the ring is a
    /// mezzanine 1.2 m up; the east and west corridors climb to it by ramps
    /// 5 m long (13.5°) between y = 3 and y = 8. Inside the ring, a block of
    /// eight rooms; south of it, a row of four rooms. Doorways have lintels
    /// at 2.1 m above their floor, some walls have windows, and pillars,
    /// crates of several heights and furniture stand about, placed
    /// irregularly so that no stretch of corridor looks like another.
    pub fn building() -> Self {
        let mut w = Builder::default();
        // Floor under the whole footprint; ramps; the mezzanine as solid
        // blocks whose tops are the upper floor.
        w.patch([-1.5, -5.5, 0.0], [23.0, 0.0, 0.0], [0.0, 19.0, 0.0]);
        w.patch([18.5, 3.0, 0.0], [3.0, 0.0, 0.0], [0.0, 5.0, MEZZANINE]);
        w.patch([-1.5, 3.0, 0.0], [3.0, 0.0, 0.0], [0.0, 5.0, MEZZANINE]);
        w.solid([18.5, 8.0, 0.0], [21.5, 13.5, MEZZANINE]);
        w.solid([-1.5, 8.0, 0.0], [1.5, 13.5, MEZZANINE]);
        w.solid([-1.5, 10.5, 0.0], [21.5, 13.5, MEZZANINE]);
        // Outer walls.
        w.wall_x(-5.5, -1.5, 21.5, &[]);
        w.wall_x(13.5, -1.5, 21.5, &[window(4.0, 6.5, 2.3, 3.6)]);
        w.wall_y(-1.5, -5.5, 13.5, &[window(-4.0, -2.5, 1.5, 2.5)]);
        w.wall_y(21.5, -5.5, 13.5, &[window(9.5, 11.0, 2.4, 3.4)]);
        // South corridor, south side, with doorways into the room row.
        w.wall_x(
            -1.5,
            -1.5,
            21.5,
            &[
                door(0.8, 1.8, 0.0),
                door(6.0, 7.0, 0.0),
                door(11.5, 12.7, 0.0),
                door(17.0, 18.0, 0.0),
            ],
        );
        for x in [4.0, 9.5, 15.5] {
            w.wall_y(x, -5.5, -1.5, &[]);
        }
        // Inner block: south wall (doorways at floor level), north wall
        // (openings from the mezzanine: the block's face below them is the
        // mezzanine's edge), west and east walls beside the ramps (windows
        // only, high enough to clear the ramp).
        w.wall_x(
            1.5,
            1.5,
            18.5,
            &[
                door(2.6, 3.6, 0.0),
                door(8.0, 9.0, 0.0),
                window(12.0, 13.5, 1.0, 2.0),
                door(15.8, 16.8, 0.0),
            ],
        );
        w.wall_x(
            10.5,
            1.5,
            18.5,
            &[
                door(3.8, 4.8, MEZZANINE),
                window(8.5, 10.0, 2.0, 3.0),
                door(12.6, 13.6, MEZZANINE),
            ],
        );
        w.wall_y(1.5, 1.5, 10.5, &[window(4.0, 5.2, 2.0, 3.0)]);
        w.wall_y(
            18.5,
            1.5,
            10.5,
            &[window(4.5, 6.0, 2.2, 3.2), door(9.0, 10.0, MEZZANINE)],
        );
        w.wall_x(
            6.0,
            1.5,
            18.5,
            &[door(3.5, 4.5, 0.0), door(11.0, 12.0, 0.0)],
        );
        w.wall_y(6.0, 1.5, 10.5, &[door(3.5, 4.5, 0.0)]);
        w.wall_y(10.5, 1.5, 10.5, &[door(7.5, 8.5, 0.0)]);
        w.wall_y(14.5, 1.5, 10.5, &[door(2.5, 3.5, 0.0), door(8.0, 9.0, 0.0)]);
        // Pillars, full height, against the corridor walls.
        for (x, y, z) in [
            (3.2, -1.2, 0.0),
            (13.8, 1.2, 0.0),
            (21.2, 1.8, 0.0),
            (18.8, 8.6, MEZZANINE),
            (10.0, 13.2, MEZZANINE),
            (-1.2, 9.8, MEZZANINE),
            (1.2, 1.8, 0.0),
        ] {
            w.solid([x - 0.2, y - 0.2, z], [x + 0.2, y + 0.2, WALL_HEIGHT]);
        }
        // Crates of several sizes and heights along the corridors.
        for (c, size, h) in [
            ([9.0, 1.1], [0.6, 0.4], 0.8),
            ([16.5, -1.1], [0.8, 0.4], 1.4),
            ([5.5, 1.15], [0.4, 0.3], 0.5),
            ([21.1, 11.0], [0.4, 0.8], 0.6),
            ([15.0, 13.1], [1.0, 0.4], 1.0),
            ([6.5, 10.9], [0.6, 0.4], 0.5),
            ([2.0, 13.1], [0.5, 0.4], 1.6),
            ([-1.1, 1.0], [0.4, 0.6], 1.0),
            ([-1.1, -0.9], [0.4, 0.4], 2.0),
            ([11.5, -1.15], [0.5, 0.3], 0.3),
        ] {
            let z = if c[1] > 10.0 { MEZZANINE } else { 0.0 };
            let (hx, hy) = (size[0] / 2.0, size[1] / 2.0);
            w.solid([c[0] - hx, c[1] - hy, z], [c[0] + hx, c[1] + hy, z + h]);
        }
        // Furniture in the rooms, seen through doorways and windows.
        for (c, size, h) in [
            ([3.8, 3.6], [1.2, 0.8], 0.75),
            ([8.5, 8.2], [0.8, 1.4], 0.75),
            ([12.3, 4.0], [1.4, 0.7], 1.1),
            ([16.6, 8.4], [1.0, 1.0], 0.45),
            ([4.0, 8.8], [0.4, 1.6], 2.0),
            ([2.4, -3.6], [1.0, 0.6], 0.75),
            ([6.6, -4.2], [1.6, 0.8], 0.9),
            ([12.6, -3.0], [0.6, 0.6], 1.8),
            ([18.8, -4.2], [1.2, 0.9], 0.6),
        ] {
            let (hx, hy) = (size[0] / 2.0, size[1] / 2.0);
            w.solid([c[0] - hx, c[1] - hy, 0.0], [c[0] + hx, c[1] + hy, h]);
        }
        World3d {
            boxes: w.boxes,
            patches: w.patches,
        }
    }
}

/// Height of the built-in building's walls (m).
const WALL_HEIGHT: f64 = 4.5;
/// Height of the built-in building's mezzanine floor (m).
const MEZZANINE: f64 = 1.2;
/// Thickness of the built-in building's walls (m).
const WALL_THICKNESS: f64 = 0.2;
/// Clear height of a doorway above its floor (m).
const DOOR_HEIGHT: f64 = 2.1;

// ------------------------------------------------------------ corridors ---

/// Centre line of [`World3d::corridors`]: a rectilinear loop, counter-clockwise
/// (m). Five left turns and one right turn; 360 m around.
const CORRIDOR_LOOP: [[f64; 2]; 6] = [
    [0.0, 0.0],
    [110.0, 0.0],
    [110.0, 40.0],
    [70.0, 40.0],
    [70.0, 70.0],
    [0.0, 70.0],
];
/// Clear width of the corridors (m).
const CORRIDOR_WIDTH: f64 = 3.0;
/// Height of the corridors' walls (m).
const CORRIDOR_WALL_HEIGHT: f64 = 3.0;
/// Distances (m) between consecutive features along a corridor, cycled: no
/// two stretches between features are alike, and most are long.
const FEATURE_SPACING: [f64; 5] = [21.0, 34.0, 17.0, 28.0, 25.0];
/// Features keep this far (m) from the corridor's corners.
const FEATURE_CORNER_CLEARANCE: f64 = 4.0;

/// What stands at one feature position of [`World3d::corridors`].
#[derive(Clone, Copy)]
enum Feature {
    /// A doorway (1.2 m wide, lintel at [`DOOR_HEIGHT`]) into a closed
    /// niche 1 m deep.
    Niche,
    /// A full-height pillar, 0.4 m square, against the wall.
    Pillar,
    /// A cabinet 1 m long, 0.5 m deep, 1.2 m tall, against the wall.
    Cabinet,
}

impl World3d {
    /// The long-corridor world: a loop of plain, 3 m wide, 3 m tall
    /// corridors (no ceiling) whose centre line is the rectilinear polygon
    /// (0, 0)–(110, 0)–(110, 40)–(70, 40)–(70, 70)–(0, 70), 360 m around,
    /// on one flat floor.
    ///
    /// The walls are featureless except for a few features 17–34 m apart
    /// (cycled spacings, alternating walls, kept 4 m from the corners):
    /// doorways into shallow niches, pillars and cabinets. Between two
    /// features, a sweep sees two parallel walls and the floor, which fix
    /// the sensor across the corridor but not along it: the degenerate case
    /// of LiDAR odometry and scan matching. Corners and features are the
    /// only along-track references; the longest straight is 110 m, beyond
    /// the lidar's default 60 m range.
    pub fn corridors() -> Self {
        let mut w = Builder::default();
        let half = CORRIDOR_WIDTH / 2.0;
        let t = WALL_THICKNESS;
        let h = CORRIDOR_WALL_HEIGHT;
        let n = CORRIDOR_LOOP.len();
        // One floor under everything (niches included).
        let (mut lo, mut hi) = ([f64::INFINITY; 2], [f64::NEG_INFINITY; 2]);
        for p in CORRIDOR_LOOP {
            lo = [lo[0].min(p[0]), lo[1].min(p[1])];
            hi = [hi[0].max(p[0]), hi[1].max(p[1])];
        }
        let margin = half + 3.0;
        w.patch(
            [lo[0] - margin, lo[1] - margin, 0.0],
            [hi[0] - lo[0] + 2.0 * margin, 0.0, 0.0],
            [0.0, hi[1] - lo[1] + 2.0 * margin, 0.0],
        );
        // +1 for a left turn at vertex i, −1 for a right turn.
        let turn = |i: usize| {
            let (a, b, c) = (
                CORRIDOR_LOOP[(i + n - 1) % n],
                CORRIDOR_LOOP[i],
                CORRIDOR_LOOP[(i + 1) % n],
            );
            let cross = (b[0] - a[0]) * (c[1] - b[1]) - (b[1] - a[1]) * (c[0] - b[0]);
            cross.signum()
        };
        let mut spacing = FEATURE_SPACING.iter().cycle();
        let mut kinds = [Feature::Niche, Feature::Pillar, Feature::Cabinet]
            .iter()
            .cycle();
        let mut side = 1.0;
        for i in 0..n {
            let (a, b) = (CORRIDOR_LOOP[i], CORRIDOR_LOOP[(i + 1) % n]);
            let len = ((b[0] - a[0]).powi(2) + (b[1] - a[1]).powi(2)).sqrt();
            let d = [(b[0] - a[0]) / len, (b[1] - a[1]) / len];
            let nrm = [-d[1], d[0]];
            // (s along the edge, o across it, +left) to world.
            let at = |s: f64, o: f64| [a[0] + s * d[0] + o * nrm[0], a[1] + s * d[1] + o * nrm[1]];
            let mut block = |s0: f64, s1: f64, o0: f64, o1: f64, z0: f64, z1: f64| {
                let (p, q) = (at(s0, o0), at(s1, o1));
                w.solid(
                    [p[0].min(q[0]), p[1].min(q[1]), z0],
                    [p[0].max(q[0]), p[1].max(q[1]), z1],
                );
            };
            // Features of this edge: (s, side, kind).
            let mut features = Vec::new();
            let mut s = FEATURE_CORNER_CLEARANCE + 2.0;
            while s < len - FEATURE_CORNER_CLEARANCE - 1.2 {
                features.push((s, side, *kinds.next().expect("cycle")));
                side = -side;
                s += spacing.next().expect("cycle");
            }
            // Walls: the inside wall of a turn stops at the other corridor's
            // wall, the outside one runs on to close the corner.
            let (ta, tb) = (turn(i), turn((i + 1) % n));
            for sgn in [1.0, -1.0] {
                let start = if ta == sgn { half } else { -half - t };
                let end = if tb == sgn {
                    len - half
                } else {
                    len + half + t
                };
                let (o0, o1) = (sgn * half, sgn * (half + t));
                let mut from = start;
                for &(fs, fside, kind) in &features {
                    if fside != sgn || !matches!(kind, Feature::Niche) {
                        continue;
                    }
                    let (g0, g1) = (fs, fs + 1.2);
                    block(from, g0, o0, o1, 0.0, h);
                    block(g0, g1, o0, o1, DOOR_HEIGHT, h);
                    // The niche: back wall and two side walls, 1 m deep.
                    let (back0, back1) = (sgn * (half + 1.0 + t), sgn * (half + 1.0 + 2.0 * t));
                    block(g0 - t, g1 + t, back0, back1, 0.0, h);
                    block(g0 - t, g0, o0, back0, 0.0, h);
                    block(g1, g1 + t, o0, back0, 0.0, h);
                    from = g1;
                }
                block(from, end, o0, o1, 0.0, h);
            }
            for &(fs, fside, kind) in &features {
                let o = fside * half;
                match kind {
                    Feature::Niche => {}
                    Feature::Pillar => block(fs, fs + 0.4, o, o - fside * 0.4, 0.0, h),
                    Feature::Cabinet => block(fs, fs + 1.0, o, o - fside * 0.5, 0.0, 1.2),
                }
            }
        }
        World3d {
            boxes: w.boxes,
            patches: w.patches,
        }
    }
}

/// An opening in a wall: from `a` to `b` along the wall (m), from height
/// `sill` to `top` (m).
#[derive(Clone, Copy)]
struct Opening {
    a: f64,
    b: f64,
    sill: f64,
    top: f64,
}

/// A doorway from `a` to `b` whose floor is at height `floor` (m).
fn door(a: f64, b: f64, floor: f64) -> Opening {
    Opening {
        a,
        b,
        sill: floor,
        top: floor + DOOR_HEIGHT,
    }
}

/// A window from `a` to `b`, open between heights `sill` and `top` (m).
fn window(a: f64, b: f64, sill: f64, top: f64) -> Opening {
    Opening { a, b, sill, top }
}

/// Collects primitives for [`World3d::building`].
#[derive(Default)]
struct Builder {
    boxes: Vec<Aabb>,
    patches: Vec<Patch>,
}

impl Builder {
    fn solid(&mut self, min: [f64; 3], max: [f64; 3]) {
        self.boxes.push(Aabb { min, max });
    }

    fn patch(&mut self, origin: [f64; 3], u: [f64; 3], v: [f64; 3]) {
        self.patches.push(Patch { origin, u, v });
    }

    /// Wall pieces along one axis from `from` to `to` with `openings`
    /// (sorted, inside), as `(a, b, z0, z1)` extents.
    fn pieces(from: f64, to: f64, openings: &[Opening]) -> Vec<(f64, f64, f64, f64)> {
        let mut out = Vec::new();
        let mut start = from;
        for o in openings {
            out.push((start, o.a, 0.0, WALL_HEIGHT));
            if o.sill > 0.0 {
                out.push((o.a, o.b, 0.0, o.sill));
            }
            out.push((o.a, o.b, o.top, WALL_HEIGHT));
            start = o.b;
        }
        out.push((start, to, 0.0, WALL_HEIGHT));
        out
    }

    /// Wall along x at `y`, from `x0` to `x1` (m).
    fn wall_x(&mut self, y: f64, x0: f64, x1: f64, openings: &[Opening]) {
        let h = WALL_THICKNESS / 2.0;
        for (a, b, z0, z1) in Self::pieces(x0, x1, openings) {
            self.solid([a, y - h, z0], [b, y + h, z1]);
        }
    }

    /// Wall along y at `x`, from `y0` to `y1` (m).
    fn wall_y(&mut self, x: f64, y0: f64, y1: f64, openings: &[Opening]) {
        let h = WALL_THICKNESS / 2.0;
        for (a, b, z0, z1) in Self::pieces(y0, y1, openings) {
            self.solid([x - h, a, z0], [x + h, b, z1]);
        }
    }
}

// --------------------------------------------------------- configuration ---

/// Odometry noise model, applied to each step's true relative motion of the
/// sensor between consecutive sweeps: translation `t` (m, length `d`) and
/// rotation `R` (angle `α`, rad), both in the previous sensor frame.
///
/// Noisy translation = `t · (1 + trans_scale_error + trans_per_m · n₁)`.
/// Noisy rotation = `R · exp(σ·[n₂, n₃, n₄] + [0, 0, yaw_bias · d])` with
/// `σ = rot_per_m · d + rot_per_rad · α` (rad) and `yaw_bias =
/// yaw_bias_deg_per_m` in rad/m; n₁…n₄ are independent standard normals. The
/// scale error and the yaw bias are systematic, as an uncalibrated wheel
/// radius and wheel base are: they make odometry drift by metres over the
/// loop; the random rotation about x and y makes it drift in height too.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Odometry3dNoise {
    /// Systematic relative error of the distance travelled (m/m; + = the
    /// odometry reports too much).
    pub trans_scale_error: f64,
    /// Random relative error: σ of the distance is this times `d` (m/m).
    pub trans_per_m: f64,
    /// Rotation noise per metre travelled: σ contribution per axis (rad/m).
    pub rot_per_m: f64,
    /// Rotation noise per radian turned: σ contribution per axis (rad/rad).
    pub rot_per_rad: f64,
    /// Systematic yaw drift (degrees per metre travelled, + = left), about
    /// the sensor's z axis.
    pub yaw_bias_deg_per_m: f64,
}

impl Default for Odometry3dNoise {
    fn default() -> Self {
        Odometry3dNoise {
            trans_scale_error: 0.03,
            trans_per_m: 0.05,
            rot_per_m: 0.004,
            rot_per_rad: 0.05,
            yaw_bias_deg_per_m: 0.6,
        }
    }
}

/// Configuration of [`simulate3d`]. Every field has a default, so a TOML file
/// need only name what it changes.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Sim3dConfig {
    /// Waypoints `[x, y]` (m, world frame) of the vehicle's ground track,
    /// driven in order; corners are rounded into arcs of `turn_radius`. The
    /// height and attitude come from the ground under the wheels.
    pub waypoints: Vec<[f64; 2]>,
    /// Radius (m) of the arcs that round the corners; shrunk where a leg is
    /// too short for it.
    pub turn_radius: f64,
    /// Number of sweeps, evenly spaced along the path from its first to its
    /// last point (at least 2).
    pub sweeps: usize,
    /// Lidar rings (laser channels), evenly spaced in elevation from
    /// `elevation_min_deg` to `elevation_max_deg`.
    pub rings: usize,
    /// Firings per ring and revolution, evenly spaced in azimuth from 0
    /// (the sensor's +x axis), counter-clockwise about +z.
    pub columns: usize,
    /// Elevation of the lowest ring (degrees above the sensor's xy plane).
    pub elevation_min_deg: f64,
    /// Elevation of the highest ring (degrees).
    pub elevation_max_deg: f64,
    /// Largest range (m) the lidar returns; farther surfaces give no point.
    pub max_range: f64,
    /// σ of the Gaussian range noise (m).
    pub range_sigma: f64,
    /// Height of the sensor above the vehicle's ground contact point (m),
    /// along the vehicle's up axis.
    pub sensor_height: f64,
    /// Distance between the front and rear axles (m); with `track`, where
    /// the ground is sampled to set the vehicle's attitude.
    pub wheelbase: f64,
    /// Distance between the left and right wheels (m).
    pub track: f64,
    /// Odometry noise model.
    pub odometry: Odometry3dNoise,
    /// Write the sweeps gzip-compressed (`NNNNNN.bin.gz`).
    pub gzip: bool,
    /// The scene; `None` means [`World3d::building`].
    #[serde(skip_serializing_if = "Option::is_none")]
    pub world: Option<World3d>,
}

impl Default for Sim3dConfig {
    fn default() -> Self {
        Sim3dConfig {
            waypoints: vec![
                [6.0, 0.0],
                [20.0, 0.0],
                [20.7, 3.0],
                [19.3, 7.5],
                [20.0, 12.0],
                [0.0, 12.0],
                [-0.7, 8.5],
                [0.7, 3.5],
                [0.0, 0.0],
                [12.0, 0.0],
            ],
            turn_radius: 1.5,
            sweeps: 200,
            rings: 32,
            columns: 1024,
            elevation_min_deg: -25.0,
            elevation_max_deg: 15.0,
            max_range: 60.0,
            range_sigma: 0.01,
            sensor_height: 1.2,
            wheelbase: 0.8,
            track: 0.6,
            odometry: Odometry3dNoise::default(),
            gzip: false,
            world: None,
        }
    }
}

impl Sim3dConfig {
    /// The configuration of the shipped data set `data/sim3d` (with seed 1):
    /// the defaults with 40 sweeps of 16 rings × 512 columns, gzipped, as
    /// `dpslam simulate3d --sweeps 40 --rings 16 --columns 512 --gzip` gives.
    pub fn embedded() -> Self {
        Sim3dConfig {
            sweeps: 40,
            rings: 16,
            columns: 512,
            gzip: true,
            ..Sim3dConfig::default()
        }
    }

    /// The long-corridor preset (`dpslam simulate3d --world corridors`):
    /// [`World3d::corridors`], driven once around its 360 m loop from
    /// (5, 0) and on past the start to (15, 0) (≈ 367 m in all, corners
    /// rounded with 1.5 m arcs), one sweep every ≈ 1 m (368 sweeps), the
    /// default lidar (32 × 1024 rays, 60 m range) and odometry noise.
    pub fn corridors() -> Self {
        Sim3dConfig {
            waypoints: vec![
                [5.0, 0.0],
                [110.0, 0.0],
                [110.0, 40.0],
                [70.0, 40.0],
                [70.0, 70.0],
                [0.0, 70.0],
                [0.0, 0.0],
                [15.0, 0.0],
            ],
            sweeps: 368,
            world: Some(World3d::corridors()),
            ..Sim3dConfig::default()
        }
    }

    /// Reads a configuration from a TOML file; absent fields keep their
    /// defaults. Syntax errors and unknown fields name the file and line.
    pub fn load(path: &Path) -> Result<Self> {
        let cfg: Sim3dConfig = crate::config::read_toml(path)?;
        cfg.validate()?;
        Ok(cfg)
    }

    /// Checks every value; the error names the offending field.
    pub fn validate(&self) -> Result<()> {
        let bad = |msg: String| Err(Error::Config(format!("simulate3d: {msg}")));
        let positive = [
            ("max_range", self.max_range),
            ("wheelbase", self.wheelbase),
            ("track", self.track),
        ];
        crate::config::check_values("simulate3d", &positive, false)?;
        let o = &self.odometry;
        let non_negative = [
            ("turn_radius", self.turn_radius),
            ("range_sigma", self.range_sigma),
            ("sensor_height", self.sensor_height),
            ("odometry.trans_per_m", o.trans_per_m),
            ("odometry.rot_per_m", o.rot_per_m),
            ("odometry.rot_per_rad", o.rot_per_rad),
        ];
        crate::config::check_values("simulate3d", &non_negative, true)?;
        if !o.yaw_bias_deg_per_m.is_finite() {
            return bad("odometry.yaw_bias_deg_per_m must be finite".into());
        }
        if !(o.trans_scale_error.is_finite() && o.trans_scale_error > -1.0) {
            return bad(format!(
                "odometry.trans_scale_error must be finite and above −1, got {}",
                o.trans_scale_error
            ));
        }
        let (lo, hi) = (self.elevation_min_deg, self.elevation_max_deg);
        if !(lo.is_finite() && hi.is_finite() && -90.0 <= lo && lo <= hi && hi <= 90.0) {
            return bad(format!(
                "elevation_min_deg ≤ elevation_max_deg, both in [−90, 90], required; got {lo}, {hi}"
            ));
        }
        if self.rings == 0 || self.columns == 0 {
            return bad(format!(
                "rings and columns must be at least 1, got {} and {}",
                self.rings, self.columns
            ));
        }
        if self.rings.saturating_mul(self.columns) > MAX_RAYS_PER_SWEEP {
            return bad(format!(
                "rings × columns = {} × {} exceeds {MAX_RAYS_PER_SWEEP} rays per sweep",
                self.rings, self.columns
            ));
        }
        if !(2..=MAX_SWEEPS).contains(&self.sweeps) {
            return bad(format!(
                "sweeps must be in 2..={MAX_SWEEPS}, got {}",
                self.sweeps
            ));
        }
        if let Some(problem) = super::path::waypoint_problem(&self.waypoints) {
            return bad(problem);
        }
        if let Some(world) = &self.world {
            let finite = |a: &[f64; 3]| a.iter().all(|v| v.is_finite());
            if world
                .boxes
                .iter()
                .any(|b| !(finite(&b.min) && finite(&b.max)))
                || world
                    .patches
                    .iter()
                    .any(|p| !(finite(&p.origin) && finite(&p.u) && finite(&p.v)))
            {
                return bad("a world coordinate is not finite".into());
            }
            if let Some(b) = world
                .boxes
                .iter()
                .find(|b| (0..3).any(|i| b.min[i] > b.max[i]))
            {
                return bad(format!("world box {b:?} has min > max"));
            }
        }
        Ok(())
    }

    /// Unit ray directions in the sensor frame, ring-major (all columns of
    /// the lowest ring first), azimuth increasing counter-clockwise from +x.
    pub fn ray_directions(&self) -> Vec<[f64; 3]> {
        let (lo, hi) = (
            self.elevation_min_deg.to_radians(),
            self.elevation_max_deg.to_radians(),
        );
        let mut dirs = Vec::with_capacity(self.rings * self.columns);
        for i in 0..self.rings {
            let el = if self.rings == 1 {
                (lo + hi) / 2.0
            } else {
                lo + (hi - lo) * i as f64 / (self.rings - 1) as f64
            };
            let (se, ce) = el.sin_cos();
            for j in 0..self.columns {
                let az = 2.0 * PI * j as f64 / self.columns as f64;
                let (sa, ca) = az.sin_cos();
                dirs.push([ce * ca, ce * sa, se]);
            }
        }
        dirs
    }
}

// ------------------------------------------------------------------ path ---

/// Pose of the sensor of a vehicle standing at ground-track point `(x, y)`
/// (m) with heading `heading` (rad), its attitude set by the ground under
/// its four wheels.
///
/// The wheels sit at ±`wheelbase`/2 along the heading and ±`track`/2 across
/// it. The vehicle's forward axis climbs by the difference of the mean
/// front and mean rear ground heights over the wheelbase, its left axis by
/// left minus right over the track; the frame is made orthonormal keeping
/// the forward axis. The contact point is at the mean of the four heights.
fn sensor_pose(
    world: &World3d,
    cfg: &Sim3dConfig,
    top: f64,
    x: f64,
    y: f64,
    heading: f64,
) -> Result<Pose3> {
    let (sin, cos) = heading.sin_cos();
    let (l2, w2) = (cfg.wheelbase / 2.0, cfg.track / 2.0);
    let mut h = [0.0; 4];
    // Front-left, front-right, rear-left, rear-right.
    for (k, (a, b)) in [(l2, w2), (l2, -w2), (-l2, w2), (-l2, -w2)]
        .into_iter()
        .enumerate()
    {
        let (wx, wy) = (x + a * cos - b * sin, y + a * sin + b * cos);
        h[k] = world.ground_height_below(wx, wy, top).ok_or_else(|| {
            Error::Config(format!(
                "simulate3d: the path leaves the ground: no surface under the wheel at ({wx:.2}, {wy:.2})"
            ))
        })?;
    }
    let forward = Vector3::new(
        cfg.wheelbase * cos,
        cfg.wheelbase * sin,
        (h[0] + h[1] - h[2] - h[3]) / 2.0,
    )
    .normalize();
    let left = Vector3::new(
        -cfg.track * sin,
        cfg.track * cos,
        (h[0] + h[2] - h[1] - h[3]) / 2.0,
    );
    let up = forward.cross(&left).normalize();
    let left = up.cross(&forward);
    let rot = UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(
        Matrix3::from_columns(&[forward, left, up]),
    ));
    let contact = Vector3::new(x, y, h.iter().sum::<f64>() / 4.0);
    let sensor = contact + rot * Vector3::new(0.0, 0.0, cfg.sensor_height);
    Ok(Pose3::from_parts(Translation3::from(sensor), rot))
}

// ------------------------------------------------------------ simulation ---

/// Mixed into the seed for the range-noise stream, so that the odometry and
/// the lidar draw from independent streams: changing the lidar settings then
/// leaves the odometry of a seed unchanged.
const LIDAR_STREAM: u64 = 0x9E37_79B9_7F4A_7C15;

/// Everything but the sweeps: computed up front (cheap); the sweeps are
/// then cast one at a time, so that writing can stream them.
struct Plan {
    world: World3d,
    truth: Vec<Stamped>,
    odometry: Vec<Stamped>,
    path_length: f64,
    dirs: Vec<[f64; 3]>,
}

impl Plan {
    fn new(cfg: &Sim3dConfig, seed: u64) -> Result<Self> {
        cfg.validate()?;
        let track = SmoothPath::new(&cfg.waypoints, cfg.turn_radius, "simulate3d")?;
        let length = track.length();
        let n = cfg.sweeps;
        let step = length / (n - 1) as f64;
        let world = cfg.world.clone().unwrap_or_else(World3d::building);
        let top = world
            .bounds()
            .ok_or_else(|| Error::Config("simulate3d: the world is empty".into()))?
            .1[2]
            + 1.0;
        let mut truth = Vec::with_capacity(n);
        for (k, (x, y, h)) in track
            .sample_xyh((0..n).map(|k| (k as f64 * step).min(length)))
            .into_iter()
            .enumerate()
        {
            truth.push(Stamped::new(
                k as f64,
                sensor_pose(&world, cfg, top, x, y, h)?,
            ));
        }
        let odometry = noisy_odometry(&truth, &cfg.odometry, seed);
        Ok(Plan {
            world,
            truth,
            odometry,
            path_length: length,
            dirs: cfg.ray_directions(),
        })
    }

    /// Casts sweep `k`: KITTI records `[x, y, z, intensity]` in the sensor
    /// frame, misses dropped; draws one range-noise sample per ray from `rng`.
    fn sweep(&self, k: usize, cfg: &Sim3dConfig, rng: &mut Pcg64) -> Vec<[f32; 4]> {
        let pose = self.truth[k].pose;
        let origin = pose.translation.vector;
        let origin = [origin.x, origin.y, origin.z];
        let hits: Vec<Option<Hit>> = self
            .dirs
            .par_iter()
            .map(|d| {
                let w = pose.rotation * v3(*d);
                self.world.cast(origin, [w.x, w.y, w.z])
            })
            .collect();
        let mut points = Vec::with_capacity(hits.len());
        for (d, hit) in self.dirs.iter().zip(hits) {
            // Drawn for every ray, hit or not, so that one ray's noise does
            // not depend on what the others saw.
            let z: f64 = rng.sample(StandardNormal);
            let Some(hit) = hit.filter(|h| h.distance <= cfg.max_range) else {
                continue;
            };
            let r = hit.distance + cfg.range_sigma * z;
            if !(r > 0.0 && r <= cfg.max_range) {
                continue;
            }
            let w = pose.rotation * v3(*d);
            let cos = (w.x * hit.normal[0] + w.y * hit.normal[1] + w.z * hit.normal[2]).abs();
            points.push([
                (d[0] * r) as f32,
                (d[1] * r) as f32,
                (d[2] * r) as f32,
                ((cos * 100.0).round() / 100.0) as f32,
            ]);
        }
        points
    }
}

/// Integrates the noisy relative motions of `truth`, from its first pose.
fn noisy_odometry(truth: &[Stamped], noise: &Odometry3dNoise, seed: u64) -> Vec<Stamped> {
    let mut rng = Pcg64::seed_from_u64(seed);
    let bias = noise.yaw_bias_deg_per_m.to_radians();
    let mut odom = truth[0].pose;
    let mut out = Vec::with_capacity(truth.len());
    out.push(truth[0]);
    for w in truth.windows(2) {
        let rel = w[0].pose.inverse() * w[1].pose;
        let d = rel.translation.vector.norm();
        let n: [f64; 4] = std::array::from_fn(|_| rng.sample(StandardNormal));
        let scale = 1.0 + noise.trans_scale_error + noise.trans_per_m * n[0];
        let sigma = noise.rot_per_m * d + noise.rot_per_rad * rel.rotation.angle();
        let err = UnitQuaternion::from_scaled_axis(Vector3::new(
            sigma * n[1],
            sigma * n[2],
            sigma * n[3] + bias * d,
        ));
        let noisy = Pose3::from_parts(
            Translation3::from(rel.translation.vector * scale),
            rel.rotation * err,
        );
        odom *= noisy;
        out.push(Stamped::new(w[1].t, odom));
    }
    out
}

/// Result of [`simulate3d`].
#[derive(Debug, Clone)]
pub struct Sim3dOutput {
    /// Per sweep, the points as written: `[x, y, z, intensity]`, x y z in the
    /// sensor frame (m), intensity the |cosine| of the angle of incidence
    /// rounded to 0.01. Rays that hit nothing within the max range give no
    /// point.
    pub sweeps: Vec<Vec<[f32; 4]>>,
    /// True sensor pose per sweep (world frame), time = sweep index (s).
    pub truth: Vec<Stamped>,
    /// Noisy odometry of the sensor per sweep (odometry frame, which starts
    /// at the true first pose), time = sweep index (s).
    pub odometry: Vec<Stamped>,
    /// The scene the lidar saw.
    pub world: World3d,
    /// Length of the vehicle's ground track (m).
    pub path_length: f64,
    /// Rays cast per sweep (rings × columns).
    pub rays_per_sweep: usize,
    /// Seed the output was generated with.
    pub seed: u64,
}

/// Headline numbers of a 3-D simulation.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Sim3dSummary {
    /// Number of sweeps.
    pub sweeps: usize,
    /// Points written, all sweeps together.
    pub points: usize,
    /// Length of the vehicle's ground track (m).
    pub path_length: f64,
    /// Lowest and highest true sensor height (m, world z).
    pub height_range: (f64, f64),
    /// Largest |pitch| and |roll| of the true sensor poses (degrees;
    /// z-y-x Euler angles).
    pub max_pitch_roll_deg: (f64, f64),
    /// Odometry-only ATE: RMS position error of the odometry against the
    /// truth after the best SE(3) alignment (m).
    pub odometry_ate: f64,
    /// Distance between the final odometry and true positions (m).
    pub final_odometry_error: f64,
    /// Rotation angle between the final odometry and true attitudes (rad).
    pub final_rotation_error: f64,
}

impl Sim3dSummary {
    fn new(
        truth: &[Stamped],
        odometry: &[Stamped],
        points: usize,
        path_length: f64,
    ) -> Result<Self> {
        let opts = AteOptions {
            alignment: Alignment::Se3,
            ..AteOptions::default()
        };
        let ate = evaluate_ate(truth, odometry, &opts)?;
        let (mut zlo, mut zhi, mut pitch, mut roll) =
            (f64::INFINITY, f64::NEG_INFINITY, 0.0f64, 0.0f64);
        for s in truth {
            let z = s.pose.translation.z;
            let (r, p, _) = s.pose.rotation.euler_angles();
            (zlo, zhi) = (zlo.min(z), zhi.max(z));
            pitch = pitch.max(p.abs());
            roll = roll.max(r.abs());
        }
        let (last_t, last_o) = (
            truth[truth.len() - 1].pose,
            odometry[odometry.len() - 1].pose,
        );
        let diff = last_t.inverse() * last_o;
        Ok(Sim3dSummary {
            sweeps: truth.len(),
            points,
            path_length,
            height_range: (zlo, zhi),
            max_pitch_roll_deg: (pitch.to_degrees(), roll.to_degrees()),
            odometry_ate: ate.rmse_m,
            final_odometry_error: (last_o.translation.vector - last_t.translation.vector).norm(),
            final_rotation_error: diff.rotation.angle(),
        })
    }
}

impl std::fmt::Display for Sim3dSummary {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "{} sweeps, {} points, path {:.2} m, sensor height {:.2}–{:.2} m, \
             max pitch {:.1}°, max roll {:.1}°, odometry-only ATE {:.3} m (SE(3) rmse), \
             final odometry error {:.3} m / {:.2}°",
            self.sweeps,
            self.points,
            self.path_length,
            self.height_range.0,
            self.height_range.1,
            self.max_pitch_roll_deg.0,
            self.max_pitch_roll_deg.1,
            self.odometry_ate,
            self.final_odometry_error,
            self.final_rotation_error.to_degrees()
        )
    }
}

impl Sim3dOutput {
    /// Summary numbers: sweeps, points, path length, height range, largest
    /// pitch and roll, odometry-only ATE and final odometry error.
    pub fn summary(&self) -> Result<Sim3dSummary> {
        let points = self.sweeps.iter().map(Vec::len).sum();
        Sim3dSummary::new(&self.truth, &self.odometry, points, self.path_length)
    }
}

/// The file name of sweep `k`: `NNNNNN.bin`, or `NNNNNN.bin.gz` when gzipped.
pub fn sweep_file_name(k: usize, gzip: bool) -> String {
    if gzip {
        format!("{k:06}.bin.gz")
    } else {
        format!("{k:06}.bin")
    }
}

/// KITTI Velodyne bytes of `points`: little-endian float32 `x y z intensity`.
pub fn kitti_bytes(points: &[[f32; 4]]) -> Vec<u8> {
    let mut out = Vec::with_capacity(points.len() * KITTI_RECORD);
    for p in points {
        for v in p {
            out.extend_from_slice(&v.to_le_bytes());
        }
    }
    out
}

/// Runs the simulation in memory: samples `cfg.sweeps` poses evenly along
/// the path, casts a sweep at each and integrates noisy odometry from the
/// true first pose. Deterministic for (`cfg`, `seed`).
///
/// Fails with [`Error::Config`] if the configuration is unusable (see
/// [`Sim3dConfig::validate`], plus coinciding waypoints, a path that turns
/// back on itself or leaves the ground, or more than 10⁸ rays in all: use
/// [`write_sim3d`], which streams, for more).
pub fn simulate3d(cfg: &Sim3dConfig, seed: u64) -> Result<Sim3dOutput> {
    cfg.validate()?;
    let rays = cfg.rings * cfg.columns;
    if rays.saturating_mul(cfg.sweeps) > MAX_RAYS_IN_MEMORY {
        return Err(Error::Config(format!(
            "simulate3d: {} sweeps × {rays} rays exceed {MAX_RAYS_IN_MEMORY} rays in memory; \
             write them to disk instead",
            cfg.sweeps
        )));
    }
    let plan = Plan::new(cfg, seed)?;
    let mut rng = Pcg64::seed_from_u64(seed ^ LIDAR_STREAM);
    let sweeps = (0..cfg.sweeps)
        .map(|k| plan.sweep(k, cfg, &mut rng))
        .collect();
    Ok(Sim3dOutput {
        sweeps,
        truth: plan.truth,
        odometry: plan.odometry,
        world: plan.world,
        path_length: plan.path_length,
        rays_per_sweep: rays,
        seed,
    })
}

/// Simulates `cfg` with `seed` and writes, under `dir` (created if needed):
/// `sweeps/NNNNNN.bin` (or `.bin.gz`, see [`Sim3dConfig::gzip`]), one KITTI
/// sweep per pose in the sensor frame; `odometry.tum`, the noisy odometry;
/// and `truth.tum`, the true sensor poses; time stamps are sweep indices (s).
///
/// Sweeps are cast and written one at a time, so memory does not grow with
/// the sequence. Every file is written to a hidden temporary sibling and
/// renamed into place, so a failed run never leaves a truncated file where a
/// good one was. Sweep files of an earlier run (`NNNNNN.bin[.gz]` names)
/// that this run did not write are removed at the end, so that `sweeps/`
/// holds exactly this sequence; other files there are left alone.
pub fn write_sim3d(dir: &Path, cfg: &Sim3dConfig, seed: u64) -> Result<Sim3dSummary> {
    let plan = Plan::new(cfg, seed)?;
    let sweep_dir = dir.join("sweeps");
    std::fs::create_dir_all(&sweep_dir).map_err(|e| Error::io(&sweep_dir, e))?;
    let mut rng = Pcg64::seed_from_u64(seed ^ LIDAR_STREAM);
    let mut points = 0;
    let mut written = std::collections::HashSet::with_capacity(cfg.sweeps);
    for k in 0..cfg.sweeps {
        let sweep = plan.sweep(k, cfg, &mut rng);
        points += sweep.len();
        let raw = kitti_bytes(&sweep);
        let bytes = if cfg.gzip { gzip(&raw) } else { raw };
        let name = sweep_file_name(k, cfg.gzip);
        write_atomic(&sweep_dir.join(&name), &bytes)?;
        written.insert(name);
    }
    remove_stale_sweeps(&sweep_dir, &written)?;
    let rows = |v: &[Stamped]| v.iter().map(|s| (s.t, s.tum())).collect::<Vec<_>>();
    crate::io::tum::write_tum(&dir.join("odometry.tum"), &rows(&plan.odometry))?;
    crate::io::tum::write_tum(&dir.join("truth.tum"), &rows(&plan.truth))?;
    Sim3dSummary::new(&plan.truth, &plan.odometry, points, plan.path_length)
}

/// Gzip with a fixed header (no name, time 0) and the best compression, so
/// that the bytes depend on the data only.
fn gzip(raw: &[u8]) -> Vec<u8> {
    let mut e = flate2::GzBuilder::new()
        .mtime(0)
        .write(Vec::with_capacity(raw.len()), flate2::Compression::best());
    // Writing to a Vec cannot fail.
    e.write_all(raw).expect("write to memory");
    e.finish().expect("write to memory")
}

/// True for the names [`sweep_file_name`] produces.
fn is_sweep_name(name: &str) -> bool {
    let stem = name
        .strip_suffix(".bin.gz")
        .or_else(|| name.strip_suffix(".bin"));
    stem.is_some_and(|s| !s.is_empty() && s.bytes().all(|b| b.is_ascii_digit()))
}

fn remove_stale_sweeps(dir: &Path, keep: &std::collections::HashSet<String>) -> Result<()> {
    for entry in std::fs::read_dir(dir).map_err(|e| Error::io(dir, e))? {
        let entry = entry.map_err(|e| Error::io(dir, e))?;
        let name = entry.file_name().to_string_lossy().into_owned();
        if is_sweep_name(&name) && !keep.contains(&name) {
            let p = entry.path();
            std::fs::remove_file(&p).map_err(|e| Error::io(&p, e))?;
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn close(a: f64, b: f64, tol: f64) -> bool {
        (a - b).abs() <= tol
    }

    #[test]
    fn ray_aabb_hand_computed() {
        let b = Aabb {
            min: [2.0, -1.0, 0.0],
            max: [3.0, 1.0, 2.0],
        };
        let h = ray_aabb([0.0, 0.0, 1.0], [1.0, 0.0, 0.0], &b).unwrap();
        assert_eq!((h.distance, h.normal), (2.0, [-1.0, 0.0, 0.0]));
        // Down at 45° from (0, 0, 4): meets z = 2 at x = 2, the box's edge.
        let s = std::f64::consts::FRAC_1_SQRT_2;
        let h = ray_aabb([0.0, 0.0, 4.0], [s, 0.0, -s], &b).unwrap();
        assert!(close(h.distance, 2.0 * 2f64.sqrt(), 1e-12), "{h:?}");
        // From above, straight down onto the top face.
        let h = ray_aabb([2.5, 0.5, 5.0], [0.0, 0.0, -1.0], &b).unwrap();
        assert_eq!((h.distance, h.normal), (3.0, [0.0, 0.0, 1.0]));
        assert!(
            ray_aabb([0.0, 0.0, 2.5], [1.0, 0.0, 0.0], &b).is_none(),
            "above"
        );
        assert!(
            ray_aabb([0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], &b).is_none(),
            "behind"
        );
        assert!(
            ray_aabb([2.5, 0.0, 1.0], [1.0, 0.0, 0.0], &b).is_none(),
            "inside"
        );
    }

    #[test]
    fn ray_patch_hand_computed() {
        // A ramp rising 1 m over 4 m in y, 2 m wide in x.
        let ramp = Patch {
            origin: [0.0, 0.0, 0.0],
            u: [2.0, 0.0, 0.0],
            v: [0.0, 4.0, 1.0],
        };
        // Straight down at (1, 2): the ramp is 0.5 m high there.
        let h = ray_patch([1.0, 2.0, 3.0], [0.0, 0.0, -1.0], &ramp).unwrap();
        assert!(close(h.distance, 2.5, 1e-12), "{h:?}");
        let n = 17f64.sqrt();
        assert!(
            close(h.normal[1].abs(), 1.0 / n, 1e-12) && close(h.normal[2].abs(), 4.0 / n, 1e-12)
        );
        // Horizontally along +y at height 0.25 from y = −1: meets the ramp at y = 1.
        let h = ray_patch([1.0, -1.0, 0.25], [0.0, 1.0, 0.0], &ramp).unwrap();
        assert!(close(h.distance, 2.0, 1e-12), "{h:?}");
        // Outside the patch in x, parallel to it, and behind.
        assert!(ray_patch([3.0, 2.0, 3.0], [0.0, 0.0, -1.0], &ramp).is_none());
        let along = [0.0, 4.0 / n, 1.0 / n];
        assert!(ray_patch([1.0, 0.0, 1.0], along, &ramp).is_none());
        assert!(ray_patch([1.0, 2.0, 3.0], [0.0, 0.0, 1.0], &ramp).is_none());
    }

    #[test]
    fn building_is_closed_and_ground_matches_the_design() {
        let w = World3d::building();
        // Mid south corridor, sensor height: walls at ±1.4 m (inner faces).
        for (dir, want) in [([0.0, 1.0, 0.0], 1.4), ([0.0, -1.0, 0.0], 1.4)] {
            let h = w.cast([7.5, 0.0, 1.2], dir).unwrap();
            assert!(close(h.distance, want, 1e-12), "{dir:?}: {h:?}");
        }
        assert_eq!(w.ground_height(7.5, 0.0), Some(0.0));
        let mezzanine = w.ground_height(10.0, 12.0).unwrap();
        assert!(close(mezzanine, MEZZANINE, 1e-12), "{mezzanine}");
        let mid_ramp = w.ground_height(20.0, 5.5).unwrap();
        assert!(close(mid_ramp, MEZZANINE / 2.0, 1e-12), "{mid_ramp}");
        // Every horizontal ray from the corridors hits something; a ray
        // straight up escapes (no roof).
        for (x, y, z) in [(3.0, 0.3, 1.2), (20.0, 5.0, 2.0), (10.0, 12.0, 2.0)] {
            for i in 0..360 {
                let a = (i as f64).to_radians();
                assert!(
                    w.cast([x, y, z], [a.cos(), a.sin(), 0.0]).is_some(),
                    "ray {i} escaped"
                );
            }
            assert!(w.cast([x, y, z], [0.0, 0.0, 1.0]).is_none());
        }
        let (lo, hi) = w.bounds().unwrap();
        assert_eq!(lo, [-1.6, -5.6, 0.0]);
        assert_eq!(hi, [21.6, 13.6, WALL_HEIGHT]);
    }

    #[test]
    fn attitude_on_a_planar_ramp_is_exact() {
        // A wide ramp rising along +y at slope 0.25; driving at heading h
        // the forward axis climbs at 0.25·sin h and the up axis is the normal.
        let world = World3d {
            boxes: vec![],
            patches: vec![Patch {
                origin: [-10.0, -10.0, 0.0],
                u: [20.0, 0.0, 0.0],
                v: [0.0, 20.0, 5.0],
            }],
        };
        let cfg = Sim3dConfig::default();
        let heading = 0.4;
        let p = sensor_pose(&world, &cfg, 10.0, 1.0, 2.0, heading).unwrap();
        let fwd = p.rotation * Vector3::x();
        let slope = fwd.z / fwd.xy().norm();
        assert!(close(slope, 0.25 * heading.sin(), 1e-12), "{fwd}");
        assert!(close(fwd.y.atan2(fwd.x), heading, 1e-12), "{fwd}");
        let normal = Vector3::new(0.0, -0.25, 1.0).normalize();
        let up = p.rotation * Vector3::z();
        assert!((up - normal).norm() < 1e-12, "{up}");
        // The sensor is sensor_height above the ground along the ramp's normal.
        let ground = 0.25 * (2.0 + 10.0);
        let expect = Vector3::new(1.0, 2.0, ground) + normal * cfg.sensor_height;
        assert!((p.translation.vector - expect).norm() < 1e-12);
    }

    #[test]
    fn bad_configs_are_rejected_not_panicked_on() {
        type Change = Box<dyn Fn(&mut Sim3dConfig)>;
        let cases: Vec<(&str, Change)> = vec![
            ("max_range", Box::new(|c| c.max_range = 0.0)),
            ("track", Box::new(|c| c.track = f64::NAN)),
            ("range_sigma", Box::new(|c| c.range_sigma = -0.1)),
            (
                "odometry.rot_per_m",
                Box::new(|c| c.odometry.rot_per_m = -1.0),
            ),
            (
                "trans_scale_error",
                Box::new(|c| c.odometry.trans_scale_error = -1.0),
            ),
            ("elevation", Box::new(|c| c.elevation_min_deg = 30.0)),
            ("rings", Box::new(|c| c.rings = 0)),
            ("rays per sweep", Box::new(|c| c.columns = usize::MAX)),
            ("sweeps", Box::new(|c| c.sweeps = 1)),
            ("two waypoints", Box::new(|c| c.waypoints.truncate(1))),
            ("coincide", Box::new(|c| c.waypoints[1] = c.waypoints[0])),
            (
                "reverses",
                Box::new(|c| c.waypoints = vec![[0.0, 0.0], [5.0, 0.0], [1.0, 0.0]]),
            ),
            (
                "leaves the ground",
                Box::new(|c| c.waypoints = vec![[0.0, 0.0], [40.0, 0.0]]),
            ),
            (
                "in memory",
                Box::new(|c| {
                    c.sweeps = 100_000;
                    c.columns = 1000;
                }),
            ),
        ];
        for (what, change) in cases {
            let mut cfg = Sim3dConfig {
                sweeps: 3,
                rings: 2,
                columns: 8,
                ..Sim3dConfig::default()
            };
            change(&mut cfg);
            match simulate3d(&cfg, 1) {
                Err(Error::Config(msg)) => assert!(msg.contains(what), "{what}: {msg}"),
                other => panic!(
                    "{what}: expected a configuration error, got {:?}",
                    other.map(|o| o.sweeps.len())
                ),
            }
        }
    }

    #[test]
    fn without_noise_points_lie_on_the_scene_and_odometry_is_truth() {
        let cfg = Sim3dConfig {
            sweeps: 5,
            rings: 8,
            columns: 90,
            range_sigma: 0.0,
            odometry: Odometry3dNoise {
                trans_scale_error: 0.0,
                trans_per_m: 0.0,
                rot_per_m: 0.0,
                rot_per_rad: 0.0,
                yaw_bias_deg_per_m: 0.0,
            },
            ..Sim3dConfig::default()
        };
        let sim = simulate3d(&cfg, 4).unwrap();
        for (k, pts) in sim.sweeps.iter().enumerate() {
            let pose = sim.truth[k].pose;
            let odo = sim.odometry[k].pose;
            assert!((pose.inverse() * odo).translation.vector.norm() < 1e-9);
            assert!(!pts.is_empty());
            for p in pts {
                // Re-cast the ray through the point: it stops at the point.
                let local = Vector3::new(p[0] as f64, p[1] as f64, p[2] as f64);
                let r = local.norm();
                let w = pose.rotation * (local / r);
                let o = pose.translation.vector;
                let hit = sim.world.cast([o.x, o.y, o.z], [w.x, w.y, w.z]).unwrap();
                assert!(close(hit.distance, r, 1e-4), "{} vs {r}", hit.distance);
                assert!((0.0..=1.0).contains(&p[3]));
            }
        }
        assert!(sim.summary().unwrap().final_odometry_error < 1e-9);
    }

    #[test]
    fn sweep_names_and_stale_file_pattern() {
        assert_eq!(sweep_file_name(7, false), "000007.bin");
        assert_eq!(sweep_file_name(123456, true), "123456.bin.gz");
        assert!(is_sweep_name("000007.bin") && is_sweep_name("12.bin.gz"));
        for other in [
            "a.bin",
            ".000001.bin.tmp-3",
            "000001.pcd",
            "000001.bin.gz.tmp",
            ".bin",
        ] {
            assert!(!is_sweep_name(other), "{other}");
        }
        let b = kitti_bytes(&[[1.0, -2.0, 0.5, 0.25]]);
        assert_eq!(b.len(), KITTI_RECORD);
        assert_eq!(&b[4..8], &(-2.0f32).to_le_bytes());
    }
}
