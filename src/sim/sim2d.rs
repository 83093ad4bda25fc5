//! 2-D simulator: an office floor of line segments, a robot driving a loop
//! through it, a planar laser ray-cast exactly against the walls, and
//! odometry corrupted by a known noise model.
//!
//! The output is what a real robot would log (a CARMEN `FLASER` log whose
//! poses are the noisy odometry) plus what it never knows (the true poses, as
//! a TUM trajectory), so a SLAM run on the log can be scored against truth.
//!
//! Frames: the **world frame** is the map frame of the truth trajectory
//! (metres, θ counter-clockwise from +x). Odometry starts at the true initial
//! pose and then drifts. The laser sits at the robot's odometry point, looking
//! along the robot's +x axis, so the logged laser pose and the odometry pose are
//! the same.
//!
//! Everything is deterministic for a seed: the odometry noise and the range
//! noise come from two `Pcg64` streams derived from it.

use crate::geometry::{Pose, Pose2, pose2, wrap_angle, xyt};
use crate::io::atomic::write_atomic;
use crate::scan::LaserScan2d;
use crate::sim::path::SmoothPath;
use crate::{Error, Result};
use rand::{RngExt, SeedableRng};
use rand_distr::StandardNormal;
use rand_pcg::Pcg64;
use serde::{Deserialize, Serialize};
use std::fmt::Write as _;
use std::path::Path;

/// Range written for a beam with no return (m), as real CARMEN logs of SICK
/// lasers do: any mapper treats it as "beyond the sensor's limit".
pub const NO_RETURN_RANGE: f64 = 81.91;

/// Hard cap on the number of scans one simulation may produce, so that a
/// mistyped configuration fails with a message instead of exhausting memory.
const MAX_SCANS: usize = 2_000_000;

/// A wall: a line segment between two points in the world frame (m).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Segment2 {
    /// First end point `[x, y]` (m, world frame).
    pub a: [f64; 2],
    /// Second end point `[x, y]` (m, world frame).
    pub b: [f64; 2],
}

/// Distance (m) along a ray from `origin` in unit direction `dir` to where it
/// crosses `seg`, or `None` if it misses.
///
/// Exact line–segment intersection; the segment's end points count as part
/// of it, so that rays cannot slip through the joint of two walls. A ray
/// parallel to the segment misses it (a grazing ray sees nothing to stop it).
pub fn ray_segment(origin: [f64; 2], dir: [f64; 2], seg: &Segment2) -> Option<f64> {
    let e = [seg.b[0] - seg.a[0], seg.b[1] - seg.a[1]];
    let denom = dir[0] * e[1] - dir[1] * e[0];
    if denom.abs() < 1e-12 {
        return None;
    }
    let w = [seg.a[0] - origin[0], seg.a[1] - origin[1]];
    let t = (w[0] * e[1] - w[1] * e[0]) / denom;
    let u = (w[0] * dir[1] - w[1] * dir[0]) / denom;
    (t >= 0.0 && (0.0..=1.0).contains(&u)).then_some(t)
}

/// A world made of wall segments.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct World2d {
    /// The walls (m, world frame).
    pub segments: Vec<Segment2>,
}

impl World2d {
    /// Distance (m) from `origin` along the direction `angle` (rad, world
    /// frame) to the nearest wall, or `None` if the ray escapes the world.
    pub fn cast(&self, origin: [f64; 2], angle: f64) -> Option<f64> {
        let dir = [angle.cos(), angle.sin()];
        self.segments
            .iter()
            .filter_map(|s| ray_segment(origin, dir, s))
            .min_by(f64::total_cmp)
    }

    /// Axis-aligned bounding box `(min, max)` of all walls (m), or `None` for
    /// an empty world.
    pub fn bounds(&self) -> Option<([f64; 2], [f64; 2])> {
        let mut pts = self.segments.iter().flat_map(|s| [s.a, s.b]);
        let first = pts.next()?;
        Some(pts.fold((first, first), |(lo, hi), p| {
            (
                [lo[0].min(p[0]), lo[1].min(p[1])],
                [hi[0].max(p[0]), hi[1].max(p[1])],
            )
        }))
    }

    /// The built-in office floor.
    ///
    /// A corridor ring 2.4 m wide whose centre line is the rectangle
    /// (0, 0)–(20, 0)–(20, 12)–(0, 12) (64 m around). Inside the ring, eight
    /// rooms of 4.4 m × 4.8 m; outside, rows of rooms 4 m deep along the south
    /// and north corridors, and alcoves and a cabinet on the east and west
    /// walls. Doorways 1–1.2 m wide open most rooms onto the corridor, and
    /// 0.4 m boxes stand against the corridor walls every few metres. The
    /// features are spaced irregularly on purpose: a corridor whose walls
    /// look the same everywhere leaves scan matching unconstrained along it.
    pub fn office() -> Self {
        let mut w = WorldBuilder::default();
        // Corridor ring, outer walls (east and west run the full height so
        // they also close the outer room rows).
        w.wall_x(
            -1.2,
            -1.2,
            21.2,
            &[(1.5, 2.5), (6.0, 7.0), (12.0, 13.2), (17.5, 18.5)],
        );
        w.wall_x(
            13.2,
            -1.2,
            21.2,
            &[(0.8, 1.8), (5.0, 6.0), (10.5, 11.5), (16.5, 17.5)],
        );
        w.wall_y(21.2, -5.2, 17.2, &[(5.0, 7.0)]);
        w.polyline(&[[21.2, 5.0], [22.0, 5.0], [22.0, 7.0], [21.2, 7.0]]);
        w.wall_y(-1.2, -5.2, 17.2, &[(3.0, 4.5)]);
        w.polyline(&[[-1.2, 3.0], [-1.8, 3.0], [-1.8, 4.5], [-1.2, 4.5]]);
        w.polyline(&[[-1.2, 8.0], [-0.85, 8.0], [-0.85, 9.2], [-1.2, 9.2]]);
        // Outer room rows.
        w.wall_x(-5.2, -1.2, 21.2, &[]);
        for x in [4.0, 9.5, 15.5] {
            w.wall_y(x, -5.2, -1.2, &[]);
        }
        w.wall_x(17.2, -1.2, 21.2, &[]);
        for x in [3.0, 8.5, 14.0] {
            w.wall_y(x, 13.2, 17.2, &[]);
        }
        // Inner block of rooms.
        w.wall_x(1.2, 1.2, 18.8, &[(2.6, 3.6), (8.2, 9.2), (11.0, 12.0)]);
        w.wall_x(
            10.8,
            1.2,
            18.8,
            &[(4.0, 5.0), (6.5, 7.5), (12.4, 13.4), (16.0, 17.0)],
        );
        w.wall_y(18.8, 1.2, 10.8, &[(3.0, 4.0)]);
        w.wall_y(1.2, 1.2, 10.8, &[(7.5, 8.5)]);
        w.wall_x(6.0, 1.2, 18.8, &[]);
        for x in [5.6, 10.0, 14.4] {
            w.wall_y(x, 1.2, 10.8, &[]);
        }
        // Boxes against the corridor walls, clear of the corners and doorways.
        for c in [
            [4.5, -0.95],
            [10.5, 0.95],
            [14.0, -0.95],
            [17.0, 0.95],
            [20.95, 2.5],
            [19.05, 8.5],
            [20.95, 10.0],
            [15.5, 12.95],
            [9.0, 11.05],
            [2.5, 12.95],
            [0.95, 4.5],
            [-0.95, 10.5],
        ] {
            w.rect(c, [0.4, 0.4]);
        }
        // Furniture seen through the doorways.
        w.rect([3.4, 3.6], [0.8, 0.6]);
        w.rect([6.75, -3.5], [1.0, 0.5]);
        w.rect([12.2, 8.5], [0.6, 1.2]);
        w.rect([11.0, 15.2], [1.2, 0.6]);
        w.rect([16.5, -3.0], [0.5, 0.5]);
        World2d { segments: w.segs }
    }
}

/// Collects segments for [`World2d::office`].
#[derive(Default)]
struct WorldBuilder {
    segs: Vec<Segment2>,
}

impl WorldBuilder {
    fn seg(&mut self, a: [f64; 2], b: [f64; 2]) {
        self.segs.push(Segment2 { a, b });
    }

    /// Pieces of `[from, to]` left once the `gaps` (sorted, inside) are cut out.
    fn pieces(from: f64, to: f64, gaps: &[(f64, f64)]) -> Vec<(f64, f64)> {
        let mut out = Vec::new();
        let mut start = from;
        for &(g0, g1) in gaps {
            out.push((start, g0));
            start = g1;
        }
        out.push((start, to));
        out
    }

    /// Horizontal wall at `y` from `x0` to `x1` with doorways `gaps` (x ranges).
    fn wall_x(&mut self, y: f64, x0: f64, x1: f64, gaps: &[(f64, f64)]) {
        for (a, b) in Self::pieces(x0, x1, gaps) {
            self.seg([a, y], [b, y]);
        }
    }

    /// Vertical wall at `x` from `y0` to `y1` with doorways `gaps` (y ranges).
    fn wall_y(&mut self, x: f64, y0: f64, y1: f64, gaps: &[(f64, f64)]) {
        for (a, b) in Self::pieces(y0, y1, gaps) {
            self.seg([x, a], [x, b]);
        }
    }

    fn polyline(&mut self, pts: &[[f64; 2]]) {
        for p in pts.windows(2) {
            self.seg(p[0], p[1]);
        }
    }

    /// Axis-aligned box with centre `c` and size `wh` (m).
    fn rect(&mut self, c: [f64; 2], wh: [f64; 2]) {
        let (hx, hy) = (wh[0] / 2.0, wh[1] / 2.0);
        let p = [
            [c[0] - hx, c[1] - hy],
            [c[0] + hx, c[1] - hy],
            [c[0] + hx, c[1] + hy],
            [c[0] - hx, c[1] + hy],
            [c[0] - hx, c[1] - hy],
        ];
        self.polyline(&p);
    }
}

/// Odometry noise model, applied to each step's true motion in the robot
/// frame: distance `d` (m) and turn `θ` (rad) between consecutive scans.
///
/// Noisy distance = `d · (1 + trans_per_m · n₁)`, in the true direction of
/// travel (σ = `trans_per_m · d`). Noisy turn = `θ + (rot_per_m · d +
/// rot_per_rad · |θ|) · n₂ + bias · d` with `bias = rot_bias_deg_per_m` in
/// rad/m; n₁, n₂ are independent standard normals. The bias is what makes
/// odometry drift by metres over a loop, as an uncalibrated wheel base does.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct OdometryNoise {
    /// Relative translation error: σ of the distance is this times `d` (m/m).
    pub trans_per_m: f64,
    /// Rotation error per metre travelled: σ contribution (rad/m).
    pub rot_per_m: f64,
    /// Rotation error per radian turned: σ contribution (rad/rad).
    pub rot_per_rad: f64,
    /// Systematic rotation bias (degrees per metre travelled, + = left).
    pub rot_bias_deg_per_m: f64,
}

impl OdometryNoise {
    /// No noise at all: the odometry reproduces the true path.
    pub fn zero() -> Self {
        Self {
            trans_per_m: 0.0,
            rot_per_m: 0.0,
            rot_per_rad: 0.0,
            rot_bias_deg_per_m: 0.0,
        }
    }
}

impl Default for OdometryNoise {
    fn default() -> Self {
        OdometryNoise {
            trans_per_m: 0.05,
            rot_per_m: 0.02,
            rot_per_rad: 0.05,
            rot_bias_deg_per_m: 0.5,
        }
    }
}

/// Configuration of [`simulate2d`]. Every field has a default, so a TOML file
/// need only name what it changes.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Sim2dConfig {
    /// Waypoints `[x, y]` (m, world frame) driven in order; corners are
    /// rounded into arcs of `turn_radius`. The robot starts at the first,
    /// facing the second.
    pub waypoints: Vec<[f64; 2]>,
    /// Forward speed (m/s), constant along the whole path.
    pub speed: f64,
    /// Radius (m) of the arcs that round the corners; shrunk where a leg is
    /// too short for it.
    pub turn_radius: f64,
    /// Time between scans (s).
    pub scan_period: f64,
    /// Number of beams per scan.
    pub beams: usize,
    /// Field of view (degrees), centred on the robot's +x axis; beams are
    /// evenly spaced from −fov/2 to +fov/2.
    pub fov_deg: f64,
    /// Largest range (m) the laser returns; beyond it a beam reads
    /// [`NO_RETURN_RANGE`].
    pub max_range: f64,
    /// σ of the Gaussian range noise (m).
    pub range_sigma: f64,
    /// Odometry noise model.
    pub odometry: OdometryNoise,
    /// Host name written in the log lines.
    pub host: String,
    /// The walls; `None` means [`World2d::office`].
    #[serde(skip_serializing_if = "Option::is_none")]
    pub world: Option<World2d>,
}

impl Default for Sim2dConfig {
    fn default() -> Self {
        Sim2dConfig {
            waypoints: vec![
                [6.0, 0.0],
                [20.0, 0.0],
                [20.0, 12.0],
                [0.0, 12.0],
                [0.0, 0.0],
                [12.0, 0.0],
            ],
            speed: 0.5,
            turn_radius: 1.0,
            scan_period: 0.1,
            beams: 181,
            fov_deg: 180.0,
            max_range: 8.0,
            range_sigma: 0.01,
            odometry: OdometryNoise::default(),
            host: "sim2d".into(),
            world: None,
        }
    }
}

impl Sim2dConfig {
    /// Reads a configuration from a TOML file; absent fields keep their
    /// defaults. Syntax errors and unknown fields name the file and line.
    pub fn load(path: &Path) -> Result<Self> {
        let cfg: Sim2dConfig = crate::config::read_toml(path)?;
        cfg.validate()?;
        Ok(cfg)
    }

    /// Checks every value; the error names the offending field.
    pub fn validate(&self) -> Result<()> {
        let bad = |msg: String| Err(Error::Config(format!("simulate2d: {msg}")));
        let positive = [
            ("speed", self.speed),
            ("scan_period", self.scan_period),
            ("fov_deg", self.fov_deg),
            ("max_range", self.max_range),
        ];
        crate::config::check_values("simulate2d", &positive, false)?;
        let non_negative = [
            ("turn_radius", self.turn_radius),
            ("range_sigma", self.range_sigma),
            ("odometry.trans_per_m", self.odometry.trans_per_m),
            ("odometry.rot_per_m", self.odometry.rot_per_m),
            ("odometry.rot_per_rad", self.odometry.rot_per_rad),
        ];
        crate::config::check_values("simulate2d", &non_negative, true)?;
        if !self.odometry.rot_bias_deg_per_m.is_finite() {
            return bad("odometry.rot_bias_deg_per_m must be finite".into());
        }
        if self.fov_deg > 360.0 {
            return bad(format!("fov_deg must be at most 360, got {}", self.fov_deg));
        }
        if self.max_range >= NO_RETURN_RANGE {
            return bad(format!(
                "max_range must be below the no-return value {NO_RETURN_RANGE}, got {}",
                self.max_range
            ));
        }
        if !(1..=100_000).contains(&self.beams) {
            return bad(format!("beams must be in 1..=100000, got {}", self.beams));
        }
        if self.host.is_empty() || self.host.chars().any(char::is_whitespace) {
            return bad(format!(
                "host must be one non-empty word, got {:?}",
                self.host
            ));
        }
        if let Some(problem) = super::path::waypoint_problem(&self.waypoints) {
            return bad(problem);
        }
        if let Some(world) = &self.world
            && world
                .segments
                .iter()
                .any(|s| s.a.iter().chain(&s.b).any(|v| !v.is_finite()))
        {
            return bad("a wall end point is not finite".into());
        }
        Ok(())
    }

    /// Beam angles relative to the laser's forward axis: (first, step) in rad.
    fn beam_angles(&self) -> (f64, f64) {
        let fov = self.fov_deg.to_radians();
        if self.beams == 1 {
            (0.0, 0.0)
        } else {
            (-fov / 2.0, fov / (self.beams - 1) as f64)
        }
    }
}

/// Result of [`simulate2d`].
#[derive(Debug, Clone)]
pub struct Sim2dOutput {
    /// The scans in time order. `odometry` and `logged_pose` are the noisy
    /// odometry (odometry frame, which starts at the true first pose);
    /// ranges are rounded to the millimetre, as written to the log;
    /// `line` is the scan's line in the log [`Sim2dOutput::clf_text`] writes.
    pub scans: Vec<LaserScan2d>,
    /// True robot (= laser) pose per scan: time stamp (s) and pose in the
    /// world frame.
    pub truth: Vec<(f64, Pose2)>,
    /// The walls the laser saw.
    pub world: World2d,
    /// Length of the true path (m).
    pub path_length: f64,
    /// Seed the output was generated with.
    pub seed: u64,
    /// Host name written in the log lines.
    pub host: String,
}

/// Headline numbers of a simulation.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Sim2dSummary {
    /// Number of scans.
    pub scans: usize,
    /// Time from the first to the last scan (s).
    pub duration: f64,
    /// Length of the true path (m).
    pub path_length: f64,
    /// Distance between the final odometry pose and the final true pose (m).
    pub final_odometry_error: f64,
    /// Heading error of the final odometry pose (rad, in (−π, π]).
    pub final_heading_error: f64,
}

impl std::fmt::Display for Sim2dSummary {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "{} scans over {:.1} s, path {:.2} m, final odometry error {:.3} m / {:.2}°",
            self.scans,
            self.duration,
            self.path_length,
            self.final_odometry_error,
            self.final_heading_error.to_degrees()
        )
    }
}

/// Header of the simulated CARMEN log: the standard one (which sets the max
/// range by `PARAM`, so readers see 8 m, not 81.91 m, as the limit) plus a
/// comment naming the simulation.
fn clf_header(max_range: f64, host: &str, seed: u64) -> String {
    let mut h = crate::io::carmen::format_header(max_range, host);
    let _ = writeln!(
        h,
        "# dpslam simulate2d, seed {seed}: true poses in a separate TUM file; \
         beams beyond the max range read {NO_RETURN_RANGE}"
    );
    h
}

impl Sim2dOutput {
    /// Summary numbers: scans, duration, path length, final odometry error.
    pub fn summary(&self) -> Sim2dSummary {
        let (t0, t1, odom, truth) = match (self.truth.first(), self.truth.last(), self.scans.last())
        {
            (Some(a), Some(b), Some(s)) => (a.0, b.0, s.odometry, b.1),
            _ => (0.0, 0.0, Pose2::identity(), Pose2::identity()),
        };
        let (ox, oy, ot) = xyt(&odom);
        let (tx, ty, tt) = xyt(&truth);
        Sim2dSummary {
            scans: self.scans.len(),
            duration: t1 - t0,
            path_length: self.path_length,
            final_odometry_error: (ox - tx).hypot(oy - ty),
            final_heading_error: wrap_angle(ot - tt),
        }
    }

    /// The CARMEN log: header, then one `FLASER` line per scan, written by
    /// [`crate::io::carmen::format_flaser`] (ranges to 3 decimals, poses and
    /// time stamps to 6).
    pub fn clf_text(&self) -> String {
        let max_range = self.scans.first().map_or(NO_RETURN_RANGE, |s| s.max_range);
        let mut out = clf_header(max_range, &self.host, self.seed);
        out.reserve(self.scans.len() * 1300);
        for s in &self.scans {
            out.push_str(&crate::io::carmen::format_flaser(s, &self.host));
            out.push('\n');
        }
        out
    }

    /// The true trajectory as TUM rows `(t, [x y z qx qy qz qw])` (s, m; 2-D:
    /// z = qx = qy = 0, qz = sin(θ/2), qw = cos(θ/2)).
    pub fn tum_rows(&self) -> Vec<(f64, [f64; 7])> {
        self.truth.iter().map(|(t, p)| (*t, p.to_tum())).collect()
    }
}

/// Mixed into the seed for the range-noise stream, so that the odometry and
/// the laser draw from independent streams: changing the laser settings then
/// leaves the odometry of a seed unchanged.
const LASER_STREAM: u64 = 0x9E37_79B9_7F4A_7C15;

/// Runs the simulation: drives the path at constant speed, takes a scan every
/// `scan_period` from t = 0, and integrates noisy odometry from the true
/// first pose. Deterministic for (`cfg`, `seed`).
///
/// Fails with [`Error::Config`] if the configuration is unusable (see
/// [`Sim2dConfig::validate`], plus coinciding waypoints, a path that turns
/// back on itself, or more than two million scans).
pub fn simulate2d(cfg: &Sim2dConfig, seed: u64) -> Result<Sim2dOutput> {
    cfg.validate()?;
    let path = SmoothPath::new(&cfg.waypoints, cfg.turn_radius, "simulate2d")?;
    let length = path.length();
    let step = cfg.speed * cfg.scan_period;
    // The small slack keeps the last scan when the length is a whole number
    // of steps but rounding put it a hair short.
    let n_steps = (length / step + 1e-9).floor();
    if n_steps.is_nan() || n_steps >= MAX_SCANS as f64 {
        return Err(Error::Config(format!(
            "simulate2d: {length:.1} m at {step} m per scan needs more than {MAX_SCANS} scans"
        )));
    }
    let n = n_steps as usize + 1;
    let poses = path.sample((0..n).map(|k| k as f64 * step));
    let world = cfg.world.clone().unwrap_or_else(World2d::office);
    let mut odo_rng = Pcg64::seed_from_u64(seed);
    let mut laser_rng = Pcg64::seed_from_u64(seed ^ LASER_STREAM);
    let (a0, da) = cfg.beam_angles();
    let noise = &cfg.odometry;
    let bias = noise.rot_bias_deg_per_m.to_radians();
    let header_lines = clf_header(cfg.max_range, &cfg.host, seed).lines().count();
    let mut odom = poses[0];
    let mut scans = Vec::with_capacity(n);
    let mut truth = Vec::with_capacity(n);
    for (k, pose) in poses.iter().enumerate() {
        if k > 0 {
            let (dx, dy, dth) = xyt(&(poses[k - 1].inverse() * pose));
            let d = dx.hypot(dy);
            let n1: f64 = odo_rng.sample(StandardNormal);
            let n2: f64 = odo_rng.sample(StandardNormal);
            let scale = 1.0 + noise.trans_per_m * n1;
            let sigma_rot = noise.rot_per_m * d + noise.rot_per_rad * dth.abs();
            odom *= pose2(dx * scale, dy * scale, dth + sigma_rot * n2 + bias * d);
        }
        let (x, y, th) = xyt(pose);
        let ranges = (0..cfg.beams)
            .map(|i| {
                // Drawn for every beam, hit or not, so that one beam's noise
                // does not depend on what the others saw.
                let z: f64 = laser_rng.sample(StandardNormal);
                match world.cast([x, y], th + a0 + i as f64 * da) {
                    Some(d) if d <= cfg.max_range => {
                        let r = ((d + cfg.range_sigma * z) * 1000.0).round() / 1000.0;
                        if r >= cfg.max_range {
                            NO_RETURN_RANGE
                        } else {
                            r.max(0.001)
                        }
                    }
                    _ => NO_RETURN_RANGE,
                }
            })
            .collect();
        let t = k as f64 * cfg.scan_period;
        scans.push(LaserScan2d {
            timestamp: Some(t),
            odometry: odom,
            logged_pose: Some(odom),
            ranges,
            angle_min: a0,
            angle_increment: da,
            max_range: cfg.max_range,
            line: header_lines + k + 1,
        });
        truth.push((t, *pose));
    }
    Ok(Sim2dOutput {
        scans,
        truth,
        world,
        path_length: length,
        seed,
        host: cfg.host.clone(),
    })
}

/// Simulates the default configuration with `seed` and writes the CARMEN log
/// to `out` and the true trajectory (TUM) to `truth`; see [`write_sim2d_with`].
pub fn write_sim2d(out: &Path, truth: &Path, seed: u64) -> Result<Sim2dSummary> {
    write_sim2d_with(&Sim2dConfig::default(), out, truth, seed)
}

/// Simulates `cfg` with `seed` and writes the CARMEN log to `out` and the
/// true trajectory (TUM) to `truth`.
///
/// Each file is written to a temporary sibling and renamed into place, so a
/// failed run never leaves a truncated log where a good one was.
pub fn write_sim2d_with(
    cfg: &Sim2dConfig,
    out: &Path,
    truth: &Path,
    seed: u64,
) -> Result<Sim2dSummary> {
    if out == truth {
        return Err(Error::Config(format!(
            "simulate2d: the log and the truth would both be written to {}",
            out.display()
        )));
    }
    let sim = simulate2d(cfg, seed)?;
    write_atomic(out, sim.clf_text().as_bytes())?;
    crate::io::tum::write_tum(truth, &sim.tum_rows())?;
    Ok(sim.summary())
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::f64::consts::FRAC_PI_2;

    fn seg(a: [f64; 2], b: [f64; 2]) -> Segment2 {
        Segment2 { a, b }
    }

    #[test]
    fn ray_segment_hand_computed() {
        let wall = seg([2.0, -1.0], [2.0, 1.0]);
        assert_eq!(ray_segment([0.0, 0.0], [1.0, 0.0], &wall), Some(2.0));
        // 45° up-right meets x = 2 at y = 2, past the wall's end.
        let d = std::f64::consts::FRAC_1_SQRT_2;
        assert_eq!(ray_segment([0.0, 0.0], [d, d], &wall), None);
        // From (0, 0.5) at 45° down-right: meets x = 2 at y = −1.5 → miss; at
        // 26.57° (slope −0.5) it meets y = −0.5 after √5 m.
        let dir = [2.0 / 5f64.sqrt(), -1.0 / 5f64.sqrt()];
        let t = ray_segment([0.0, 0.5], dir, &wall).unwrap();
        assert!((t - 5f64.sqrt()).abs() < 1e-12, "{t}");
        assert_eq!(ray_segment([0.0, 0.0], [-1.0, 0.0], &wall), None, "behind");
        assert_eq!(ray_segment([0.0, 0.0], [0.0, 1.0], &wall), None, "parallel");
        assert_eq!(
            ray_segment([0.0, 0.0], [1.0, 0.0], &seg([2.0, 0.0], [2.0, 1.0])),
            Some(2.0),
            "end point"
        );
    }

    #[test]
    fn office_walls_where_drawn() {
        let w = World2d::office();
        // Mid south corridor: walls 1.2 m either side.
        let up = w.cast([5.0, 0.0], FRAC_PI_2).unwrap();
        let down = w.cast([5.0, 0.0], -FRAC_PI_2).unwrap();
        assert!(
            (up - 1.2).abs() < 1e-12 && (down - 1.2).abs() < 1e-12,
            "{up} {down}"
        );
        // Through the doorway x ∈ [6, 7] into the south room, onto the table
        // whose near edge is at y = −3.25.
        let table = w.cast([6.5, 0.0], -FRAC_PI_2).unwrap();
        assert!((table - 3.25).abs() < 1e-12, "{table}");
        // Along the corridor towards the east end wall (x = 21.2), but the box
        // at (17.0, 0.95) is off the centre line: the ray along y = 0 is clear.
        let east = w.cast([5.0, 0.0], 0.0).unwrap();
        assert!((east - 16.2).abs() < 1e-12, "{east}");
        // Closed: every ray from the corridor hits something.
        for i in 0..360 {
            assert!(
                w.cast([3.0, 0.3], (i as f64).to_radians()).is_some(),
                "ray {i} escaped"
            );
        }
        let (lo, hi) = w.bounds().unwrap();
        assert_eq!((lo, hi), ([-1.8, -5.2], [22.0, 17.2]));
    }

    #[test]
    fn smooth_path_is_continuous_and_rounds_corners() {
        let cfg = Sim2dConfig::default();
        let path = SmoothPath::new(&cfg.waypoints, 1.0, "test").unwrap();
        // Legs 14 + 12 + 20 + 12 + 12 = 70 m; each of the 4 corners of radius
        // 1 m replaces 2 m of legs by a π/2 m arc.
        let expect = 70.0 - 4.0 * (2.0 - FRAC_PI_2);
        assert!((path.length() - expect).abs() < 1e-9, "{}", path.length());
        let ds = 0.01;
        let n = (path.length() / ds) as usize;
        let poses = path.sample((0..=n).map(|k| k as f64 * ds));
        for w in poses.windows(2) {
            let (dx, dy, dth) = xyt(&(w[0].inverse() * w[1]));
            assert!((dx.hypot(dy) - ds).abs() < 1e-6, "jump {dx} {dy}");
            assert!(dy.abs() < 1e-4, "sideways {dy}");
            assert!(dth.abs() <= ds / 1.0 + 1e-9, "heading jump {dth}");
        }
        let (x, y, th) = xyt(&poses[0]);
        assert!(x == 6.0 && y == 0.0 && th == 0.0);
        // Mid-corner of the first turn: 1 − 1/√2 inside the waypoint (20, 0).
        let mid = path.sample(std::iter::once(13.0 + FRAC_PI_2 / 2.0))[0];
        let (x, y, th) = xyt(&mid);
        let inset = 1.0 - std::f64::consts::FRAC_1_SQRT_2;
        assert!(
            (x - (20.0 - inset)).abs() < 1e-9 && (y - inset).abs() < 1e-9,
            "{x} {y}"
        );
        assert!((th - std::f64::consts::FRAC_PI_4).abs() < 1e-9);
    }

    #[test]
    fn short_legs_shrink_the_arc() {
        // A 1 m leg between two right-angle turns can lend only 0.5 m to each.
        let path = SmoothPath::new(
            &[[0.0, 0.0], [5.0, 0.0], [5.0, 1.0], [0.0, 1.0]],
            2.0,
            "test",
        )
        .unwrap();
        let expect = 4.5 + FRAC_PI_2 * 0.5 * 2.0 + 4.5;
        assert!((path.length() - expect).abs() < 1e-9, "{}", path.length());
    }

    #[test]
    fn bad_configs_are_rejected_not_panicked_on() {
        let ok = Sim2dConfig::default();
        type Change = fn(&mut Sim2dConfig);
        let cases: [(&str, Change); 11] = [
            ("speed", |c| c.speed = 0.0),
            ("scan_period", |c| c.scan_period = f64::NAN),
            ("range_sigma", |c| c.range_sigma = -0.1),
            ("odometry.rot_per_m", |c| c.odometry.rot_per_m = -1.0),
            ("max_range", |c| c.max_range = 100.0),
            ("beams", |c| c.beams = 0),
            ("host", |c| c.host = "two words".into()),
            ("two waypoints", |c| c.waypoints.truncate(1)),
            ("coincide", |c| c.waypoints[1] = c.waypoints[0]),
            ("reverses", |c| {
                c.waypoints = vec![[0.0, 0.0], [5.0, 0.0], [1.0, 0.0]]
            }),
            ("scans", |c| c.scan_period = 1e-9),
        ];
        for (what, change) in cases {
            let mut cfg = ok.clone();
            change(&mut cfg);
            match simulate2d(&cfg, 1) {
                Err(Error::Config(msg)) => assert!(msg.contains(what), "{what}: {msg}"),
                other => panic!(
                    "{what}: expected a configuration error, got {:?}",
                    other.map(|o| o.scans.len())
                ),
            }
        }
    }

    #[test]
    fn without_noise_odometry_is_truth_and_ranges_are_exact() {
        let cfg = Sim2dConfig {
            waypoints: vec![[2.0, 0.0], [18.0, 0.0], [18.0, 4.0]],
            range_sigma: 0.0,
            odometry: OdometryNoise::zero(),
            ..Sim2dConfig::default()
        };
        let sim = simulate2d(&cfg, 5).unwrap();
        for (s, (t, p)) in sim.scans.iter().zip(&sim.truth) {
            assert_eq!(s.timestamp, Some(*t));
            assert!((s.odometry.inverse() * p).translation.vector.norm() < 1e-9);
            let (x, y, th) = xyt(p);
            for (i, &r) in s.ranges.iter().enumerate() {
                let exact = sim
                    .world
                    .cast([x, y], th + s.angle_min + i as f64 * s.angle_increment);
                match exact {
                    Some(d) if d < cfg.max_range - 0.001 => {
                        assert!((r - d).abs() <= 0.0005 + 1e-12, "{r} vs {d}")
                    }
                    Some(d) if d > cfg.max_range => assert_eq!(r, NO_RETURN_RANGE),
                    _ => {}
                }
            }
        }
        assert!(sim.summary().final_odometry_error < 1e-9);
    }

    #[test]
    fn flaser_line_layout() {
        let cfg = Sim2dConfig {
            waypoints: vec![[2.0, 0.0], [3.0, 0.0]],
            ..Sim2dConfig::default()
        };
        let sim = simulate2d(&cfg, 3).unwrap();
        let text = sim.clf_text();
        let lines: Vec<&str> = text.lines().collect();
        let header = lines
            .iter()
            .take_while(|l| !l.starts_with("FLASER"))
            .count();
        assert_eq!(lines.len(), header + sim.scans.len());
        assert_eq!(sim.scans[0].line, header + 1);
        assert!(lines.contains(&"PARAM laser_front_laser_max_range 8.000 0.000000 sim2d 0.000000"));
        let k = 4;
        let line = lines[sim.scans[k].line - 1];
        let tok: Vec<&str> = line.split_whitespace().collect();
        assert_eq!(tok.len(), 2 + 181 + 6 + 3);
        assert_eq!((tok[0], tok[1]), ("FLASER", "181"));
        assert_eq!(tok[2 + 181 + 6..], ["0.400000", "sim2d", "0.400000"]);
        let r: f64 = tok[2 + 90].parse().unwrap();
        assert_eq!(r, sim.scans[k].ranges[90]);
        let odom_x: f64 = tok[2 + 181 + 3].parse().unwrap();
        assert!((odom_x - sim.scans[k].odometry.translation.x).abs() <= 5e-7);
    }
}
