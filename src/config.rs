//! Run configuration: one typed struct, read from TOML and/or flags, echoed
//! as `config.toml` into every run's output folder.
//!
//! Defaults are the constants of the DP-SLAM 0.1.1 release (Eliazar & Parr)
//! unless a comment says why we differ. Lengths in metres, angles in radians.

use crate::{Error, Result};
use serde::{Deserialize, Serialize};
use std::path::Path;

/// Everything a mapping run needs to know.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Config {
    /// Seed of every random choice; same seed, same result, any thread count.
    pub seed: u64,
    /// Worker threads (0 = all cores).
    pub threads: usize,
    /// Particle filter.
    pub filter: FilterConfig,
    /// Grid.
    pub map: MapConfig,
    /// Laser penetration model.
    pub laser: LaserConfig,
    /// 2-D motion model.
    pub motion2d: Motion2dConfig,
    /// 3-D mode (voxel map, sweeps, 6-DoF motion and proposal).
    pub map3d: Map3dConfig,
    /// Learning the 2-D motion model from the log (`map2d --learn-motion`).
    pub motion_learning: MotionLearningConfig,
    /// Hierarchical SLAM (dissertation ch. 8), 2-D.
    pub hierarchy: HierarchyConfig,
    /// The 2-D scan-matched proposal (`filter.proposal = "scan-matched"`).
    pub scan_match: ScanMatchConfig,
    /// The GPU likelihood backend (`--features gpu`, `--backend gpu|auto`).
    pub gpu: GpuConfig,
    /// Topics read from a ROS bag input (`--scan-topic`, `--odom-topic`;
    /// unset: guessed, see [`crate::io::bag`]).
    pub bag: crate::io::bag::scans2d::TopicChoice,
    /// How 2-D inputs are read beyond their topics.
    pub input: InputConfig,
    /// The 2-D trajectory's final alignment against the run's own map
    /// ([`crate::refine`]).
    pub refine: RefineConfig,
}

/// The 2-D trajectory's refinement against the map of the whole run
/// ([`crate::refine`]): after the filter, every scan is re-aligned, from
/// its pose, to a likelihood field of the hits of all scans at their poses.
/// Lengths in metres.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct RefineConfig {
    /// Alignment passes, each against the map of the last pass's poses
    /// (0 = off: `trajectory.tum` is the filter's own).
    pub passes: usize,
    /// Cell of the hit grid and the likelihood field, m.
    pub resolution: f64,
    /// Std of the field around an occupied cell, m.
    pub sigma: f64,
    /// Hits a cell needs to count as occupied (1 lets single stray returns
    /// and moving people pull the alignment).
    pub min_hits: u32,
    /// Likelihood of an endpoint far from anything occupied, 0..1.
    pub floor: f64,
}

impl Default for RefineConfig {
    fn default() -> Self {
        Self {
            passes: 2,
            resolution: 0.05,
            sigma: 0.05,
            min_hits: 2,
            floor: 0.1,
        }
    }
}

/// How 2-D inputs are read (`[input]`).
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct InputConfig {
    /// A CARMEN log's odometry: `"logged"` (default) keeps each laser
    /// line's pairing, `"retimed"` re-times it to each scan's stamp from the
    /// log's ODOM stream where the lines were paired from that stream (raw
    /// logs) ([`crate::io::log2d::OdometryPairing`]).
    pub odometry: crate::io::log2d::OdometryPairing,
}

/// The arithmetic of the GPU likelihood shader (see `crate::gpu`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[cfg_attr(feature = "cli", derive(clap::ValueEnum))]
#[serde(rename_all = "lowercase")]
pub enum GpuPrecision {
    /// f64 where the adapter supports it (`SHADER_F64`), else f32.
    #[default]
    Auto,
    /// f32: fastest on consumer GPUs (f64 there runs at 1/32–1/64 rate);
    /// scores within ~2e-4 nats of the CPU's.
    F32,
    /// f64: scores equal the CPU's to ~1e-12, so runs follow the CPU's
    /// trajectory; an error where the adapter lacks `SHADER_F64`.
    F64,
}

impl GpuPrecision {
    /// Every value, in the order of the command line's help.
    pub const ALL: [GpuPrecision; 3] = [GpuPrecision::Auto, GpuPrecision::F32, GpuPrecision::F64];
}

/// The command-line spelling (`auto`, `f32`, `f64`), as serde writes it.
impl std::fmt::Display for GpuPrecision {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            GpuPrecision::Auto => "auto",
            GpuPrecision::F32 => "f32",
            GpuPrecision::F64 => "f64",
        })
    }
}

impl std::str::FromStr for GpuPrecision {
    type Err = Error;
    fn from_str(s: &str) -> Result<Self> {
        Self::ALL
            .into_iter()
            .find(|p| p.to_string().eq_ignore_ascii_case(s.trim()))
            .ok_or_else(|| Error::Config(format!("GPU precision {s:?}: expected auto, f32 or f64")))
    }
}

/// The GPU likelihood backend's settings.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, Default)]
#[serde(default, deny_unknown_fields)]
pub struct GpuConfig {
    /// Shader arithmetic (default `auto`: f64 where the adapter has it).
    pub precision: GpuPrecision,
    /// Caps the size of each storage binding holding the map, bytes (at
    /// least 256); 0: the adapter's own limit. For testing maps split over
    /// several bindings.
    pub max_binding: u64,
}

/// Hierarchical SLAM (dissertation ch. 8; Eliazar & Parr, NIPS 2005): the
/// filter of `[filter]` runs over windows of `window` processed scans, each
/// on a fresh map, and a second particle filter over whole windows keeps the
/// global map, drawing each window's trajectory from the low-level particles.
/// Defaults are the DP-SLAM 0.1.1 release's where it has them.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct HierarchyConfig {
    /// Run hierarchically (`map2d --hierarchical` sets it).
    pub enabled: bool,
    /// Processed scans per low-level window (release: 40).
    pub window: usize,
    /// High-level particles (release: 50).
    pub particles: usize,
    /// Window trajectories drawn per high-level particle per window.
    pub samples_per_particle: usize,
    /// Range-error variance of the high-level laser model, m² (release:
    /// 0.17, σ ≈ 0.41 m: a window's trajectory is scored as a whole, and its
    /// own small errors must not make every sample improbable).
    pub variance: f64,
    /// Std of the perturbation of each drawn trajectory's start, in x and y,
    /// in cells (release: 0.8).
    pub perturb_xy_cells: f64,
    /// Std of the perturbation of its heading, rad (release: 0.025).
    pub perturb_theta: f64,
}

/// The 2-D scan-matched proposal ([`crate::scan_match`]): a correlative
/// search of each particle's guess against a likelihood field of its map
/// view, fused with the motion model. Lengths in metres, angles in radians.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ScanMatchConfig {
    /// Search window half-width in x and y around the odometry guess, m.
    pub window_xy: f64,
    /// Search window half-width in heading, rad (0.2618 = 15°).
    pub window_theta: f64,
    /// Finest field cell, in DP-map cells.
    pub field_cells: f64,
    /// Coarse field cells are this many fine cells wide.
    pub coarse_factor: usize,
    /// Coarse poses refined at the finest level.
    pub candidates: usize,
    /// Endpoints matched per scan at most (evenly thinned).
    pub max_beams: usize,
    /// Std of the likelihood field around an occupied cell, m.
    pub sigma: f64,
    /// Endpoint likelihood far from anything seen (the field's floor, 0..1).
    pub floor: f64,
    /// Hill-climbing levels of the sub-cell refinement on the interpolated
    /// field (each halves the step; the first is half a field cell).
    pub refine_levels: usize,
    /// The match's information is the curvature of its score at the mode,
    /// scaled to the DP likelihood's (field σ² / `laser.variance` × beams /
    /// matched endpoints), divided by this: 1 draws from the Laplace
    /// approximation of that likelihood × the motion prior; above 1 widens
    /// the proposal.
    pub temperature: f64,
    /// Added to the match's x and y variance: std floor, m.
    pub min_std_xy: f64,
    /// Added to the match's heading variance: std floor, rad.
    pub min_std_theta: f64,
    /// A match with fewer endpoints than this fraction on cells the view
    /// has seen is no match: the particle samples the motion model.
    pub min_overlap: f64,
    /// Samples per particle whose proposal is a match (0:
    /// `filter.samples_per_particle`); particles that fall back to the
    /// motion model draw `filter.samples_per_particle`.
    pub samples_per_particle: usize,
    /// Run the quick (endpoint-window) culling passes under this proposal.
    pub quick_culling: bool,
    /// Register once per view group (from its first particle's guess)
    /// instead of once per particle: cheaper, not shown to be as accurate
    /// (docs/PROPOSAL-2D.md).
    pub per_group: bool,
    /// Rank the search's candidate poses by match score × motion prior
    /// (Olson 2009's posterior search) instead of match score alone: where
    /// the window holds two near-equal peaks (a door frame repeated along
    /// a corridor), take the one the odometry supports. The sub-cell
    /// refinement and the curvature still use the match score alone.
    /// Opt-in: measured better on perturbed ACES and sim2d, but it lost
    /// fr079-raw in its one run there (docs/PROPOSAL-2D.md).
    pub prior_in_search: bool,
    /// What a cell with hits weighs in the likelihood field the scan is
    /// matched against: `"walls"` (the default), `"stop-probability"` or
    /// `"hits"` ([`FieldWeight`]).
    pub field_weight: FieldWeight,
    /// Radius of the neighbourhood a cell's wall test looks at, m
    /// (`field_weight = "walls"`).
    pub wall_radius: f64,
    /// Share of a particle's samples drawn around the peak nearest its
    /// odometry guess (a hill-climb from the guess, no search) where that
    /// peak lies outside 3 σ of the searched best one: the proposal is then
    /// the two-component mixture and the importance weights (DP likelihood
    /// × motion prior / mixture density) decide between the peaks, not the
    /// matcher's score alone. 0 = off (the searched peak only).
    pub odometry_peak_share: f64,
    /// Hits a cell needs under the view before it enters the likelihood
    /// field, in hit units (a laser endpoint writes 1; `laser.surface_fill_gap`
    /// writes `laser.surface_fill_hits` into the cells it fills). 0 = any
    /// hit counts. The default, 1, keeps the fill's inferred surfaces out
    /// of the match while the DP likelihood still weighs them: with the
    /// fill in the field, fr079 and fr079-raw were lost at a narrow passage
    /// (docs/PROPOSAL-2D.md, sessions 29 and 30).
    pub field_min_hits: f64,
    /// Share of a matched particle's proposal that is the motion model
    /// itself (its Gaussian around the odometry, in [0, 1)): a defensive
    /// mixture (Hesterberg 1995). Where the match is confidently wrong (the
    /// scan is mostly a close occluder and no-returns), the samples drawn
    /// from the motion part still cover the odometry, and the importance
    /// weights (DP likelihood × motion prior / mixture density, which the
    /// motion part bounds by 1 / share) choose. 0 = the match alone.
    pub motion_share: f64,
    /// Grid spacing (m, robot frame) of the endpoints a scan is matched
    /// with: the first return in each `endpoint_spacing`-wide square is kept
    /// before the even thinning to `max_beams`, so that a surface close to
    /// the laser, which an evenly spaced fan of beams samples densely, counts
    /// as much per metre as a far one (the voxel filter of KISS-ICP and
    /// Cartographer). 0 = off: every return is a candidate. The default,
    /// 0.1 m, is two field σ: endpoints closer than that score the same
    /// stretch of the field (docs/PROPOSAL-2D.md, session 35).
    pub endpoint_spacing: f64,
}

/// What a 2-D reading the sensor flags as "no return" means
/// (`laser.no_return`; measured in docs/PROPOSAL-2D.md, session 34).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "kebab-case")]
pub enum NoReturn {
    /// Free space up to the usable range, no hit (the release): the beam
    /// went out and nothing sent it back. True of an open door or a hall
    /// longer than the laser reaches; false where the sensor reports "no
    /// return" for a surface too close, too dark or too shiny to answer,
    /// where it carves free space through what is there. The default:
    /// the other two were even with it on accuracy over three filter seeds
    /// of the short perturbed logs, but the seed-1 suite put belgioioso,
    /// edmonton and csail-corrected behind it (docs/PROPOSAL-2D.md,
    /// session 34).
    #[default]
    Free,
    /// No evidence either way: the beam is left out of the weighing and
    /// the map update, as GMapping leaves out readings beyond its laser's
    /// maximum. A left-out beam no longer breaks the surface fill
    /// (`surface_fill_gap`) between its neighbours, which still have to
    /// pass the fill's own distance and straightness tests.
    Skip,
    /// [`NoReturn::Skip`] where the sensor's "no return" limit
    /// lies beyond the usable range (`max_range`), [`NoReturn::Free`]
    /// where it does not. A laser that cannot see past the usable range
    /// (the simulator's 8 m) says "nothing within my reach" when it gets no
    /// answer; one that reaches 80 m (a SICK's 81.91 m code), indoors, has
    /// mostly failed to measure: traced as free space, the 3.3 % of
    /// mit-csail's readings that are such codes cost a fifth of its time
    /// and half its memory, and at the passage where perturbed fr079 is
    /// lost they cut through an object 0.3–1 m in front of the laser.
    Auto,
}

impl NoReturn {
    /// Whether a flagged reading of a sensor whose "no return" limit is
    /// `sensor_max` (m) is left out at usable range `usable` (m).
    pub fn skips(self, sensor_max: f64, usable: f64) -> bool {
        match self {
            NoReturn::Free => false,
            NoReturn::Skip => true,
            NoReturn::Auto => sensor_max > usable,
        }
    }
}

/// What a cell with hits weighs in the scan matcher's likelihood field
/// (`scan_match.field_weight`; measured in docs/PROPOSAL-2D.md, sessions 15
/// and 16).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "kebab-case")]
pub enum FieldWeight {
    /// Its stop probability under the view, `1 − exp(−ρ·cell)` with
    /// ρ = hits / distance travelled in it: what moved or lets the beam
    /// through (people, glass, chair legs) weighs little. So does a wall
    /// seen only at grazing incidence, where most beams ran along it before
    /// one stopped: along a corridor that pulls the match back towards the
    /// robot's last poses, where it saw the walls head-on.
    StopProbability,
    /// 1 for every cell with a hit: no pull along corridors, but what moved
    /// counts as much as what stays.
    Hits,
    /// 1 for a cell on a wall, its stop probability otherwise: a line cell
    /// is one whose hit cells within `scan_match.wall_radius` (any
    /// particle's) number at least 6 and lie on a thin line (the smaller
    /// eigenvalue of their spread ≤ 5 % of the larger), and a wall cell is
    /// any hit cell within `wall_radius` of a line cell (so corners, wall
    /// ends and door frames count). A wall seen at grazing incidence then
    /// weighs as much as one seen head-on, while blobs away from walls
    /// (people, chair legs) and scattered hits keep their stop
    /// probability. The default: the one setting measured to hold both
    /// aces-raw and fr079-raw (docs/PROPOSAL-2D.md, sessions 16 and 17).
    #[default]
    Walls,
}

impl ScanMatchConfig {
    /// Whether a cell with `hits` under a view enters the scan matcher's
    /// likelihood field (`field_min_hits`).
    pub(crate) fn field_keeps(&self, hits: f32) -> bool {
        hits > 0.0 && f64::from(hits) >= self.field_min_hits
    }
}

impl Default for ScanMatchConfig {
    fn default() -> Self {
        Self {
            window_xy: 0.5,
            window_theta: 15f64.to_radians(),
            field_cells: 2.0,
            coarse_factor: 4,
            candidates: 3,
            max_beams: 90,
            sigma: 0.05,
            floor: 0.1,
            refine_levels: 5,
            temperature: 1.0,
            min_std_xy: 0.01,
            min_std_theta: 0.002,
            min_overlap: 0.3,
            samples_per_particle: 3,
            quick_culling: true,
            per_group: false,
            prior_in_search: false,
            field_weight: FieldWeight::default(),
            wall_radius: 0.15,
            odometry_peak_share: 0.0,
            field_min_hits: 1.0,
            motion_share: 0.0,
            endpoint_spacing: 0.1,
        }
    }
}

/// Where a 2-D step's samples come from (`filter.proposal`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "kebab-case")]
pub enum ProposalKind {
    /// The motion model around the odometry (the release), kept for
    /// comparison: it wins where the odometry's noise is the release's
    /// model (the simulator), and loses robots whose odometry slips.
    Motion,
    /// Each particle's scan match against its own map view, fused with the
    /// motion model (`[scan_match]`). The default: the proposal that won
    /// over the suite (docs/PROPOSAL-2D.md, session 17).
    #[default]
    ScanMatched,
}

impl Default for HierarchyConfig {
    fn default() -> Self {
        Self {
            enabled: false,
            window: 40,
            particles: 50,
            samples_per_particle: 4,
            variance: 0.17,
            perturb_xy_cells: 0.8,
            perturb_theta: 0.025,
        }
    }
}

/// How `map2d --learn-motion N` fits the C/D/T model to the SLAM trajectory
/// (dissertation ch. 6; see `motion_learning` for the method).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct MotionLearningConfig {
    /// Lower bound of the learned C/D floor, in grid cells: a proposal much
    /// narrower than a cell cannot be told apart by the map.
    pub min_std_xy_cells: f64,
    /// Lower bound of the learned T floor, rad (0.005 rad: 2.5 cm of arc at 5 m).
    pub min_std_t: f64,
    /// Steps whose residual is beyond this many stds of a first fit (in any
    /// component) are left out: a loss of track is not motion noise.
    pub outlier_sigmas: f64,
    /// Factor on every learned std (slopes and floors); 1 is the
    /// maximum-likelihood fit.
    pub inflation: f64,
}

impl Default for MotionLearningConfig {
    fn default() -> Self {
        Self {
            min_std_xy_cells: 0.5,
            min_std_t: 0.005,
            outlier_sigmas: 4.0,
            inflation: 1.0,
        }
    }
}

/// 3-D mode settings. The 2-D sections `filter` and `laser` apply to 3-D too
/// where their meaning is the same (particles, culling, penetration model in
/// cell units); this section holds what is 3-D only. Lengths in metres,
/// angles in radians; frames are the sensor frame of each sweep (beams) and
/// the map frame (poses, voxels).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Map3dConfig {
    /// Voxel edge length of the DP-map, m.
    pub voxel_size: f64,
    /// Beams kept per sweep after down-sampling (bounds the cost per sweep).
    pub max_beams: usize,
    /// Usable range, m (longer returns count as no return up to here).
    pub max_range: f64,
    /// Points closer than this to the sensor are dropped (robot body, noise), m.
    pub min_range: f64,
    /// Beam down-sampling: one beam per voxel of this edge (m) in the sensor
    /// frame, before the even stride that enforces `max_beams`.
    pub beam_voxel: f64,
    /// Range-error variance σ² of the penetration model in 3-D, m²; replaces
    /// `laser.variance`, whose default (0.017) suits 2.9 cm cells, not voxels.
    pub variance: f64,
    /// How far (in range-error stds σ = √variance) the 3-D likelihood
    /// traces past a measured endpoint and how large a range error still
    /// counts: `laser.trace_past_cells` and `laser.max_error_cells` are 20
    /// cells, 4.4 σ on the 2-D grid but 20 σ (4 m) on 0.2 m voxels, where a
    /// Gaussian weight beyond ≈ 5 σ is below 10⁻⁵ of the beam floor and
    /// the trace past the endpoint is most of a beam's cost. 0: the
    /// `laser` settings in cells.
    pub trace_sigmas: f64,
    /// A voxel of the best particle's view is exported to `map.ply` when it
    /// has hits and a density ρ = hits / distance of at least this (stops/m).
    pub occupied_density: f64,
    /// 6-DoF motion noise: translation std per metre of motion (m/m) ...
    pub trans_std_per_m: f64,
    /// ... plus per radian of rotation (m/rad) ...
    pub trans_std_per_rad: f64,
    /// ... at least this, m (per axis).
    pub min_trans_std: f64,
    /// Rotation noise std per metre of motion (rad/m) ...
    pub rot_std_per_m: f64,
    /// ... plus per radian of rotation (rad/rad) ...
    pub rot_std_per_rad: f64,
    /// ... at least this, rad (per axis of the small-angle vector).
    pub min_rot_std: f64,
    /// Proposal: sweeps of the best particle's recent past in the local map.
    pub local_map_sweeps: usize,
    /// Proposal: voxel (m) of the finest ICP level; each coarser level doubles it.
    pub icp_voxel: f64,
    /// Proposal: number of ICP levels, coarse to fine.
    pub icp_levels: usize,
    /// Proposal: correspondence radius of the coarsest level, m; it halves
    /// at each finer level.
    pub icp_max_distance: f64,
    /// Proposal: Gauss-Newton iterations per level, at most.
    pub icp_iterations: usize,
    /// Proposal: source points used per level, at most (even stride).
    pub icp_max_points: usize,
    /// Proposal: factor on the scan matcher's covariance (σ̂²·H⁻¹, its
    /// Gauss-Newton information scaled by the residual spread) before it is
    /// fused with the motion noise into the Gaussian the filter samples
    /// from. The Hessian estimate ignores correlated errors (map blur,
    /// sampling of the surfaces) and is known to be optimistic (Censi, ICRA
    /// 2007); against true local maps of simulated sweeps its mean squared
    /// Mahalanobis error was ≈ 2× the expected 6, hence 2. 0 = sample with
    /// the motion noise alone around the aligned pose.
    pub icp_covariance_scale: f64,
    /// Proposal, wide search: yaw offsets (degrees) tried around the
    /// prior motion at the coarsest ICP level, every this many degrees up
    /// to `search_yaw_max_deg` each way, with and without the prior's
    /// translation; the best-explained start is refined (see
    /// `icp::align_wide`). 0 = align from the prior alone.
    pub search_yaw_step_deg: f64,
    /// Proposal, wide search: largest yaw offset, degrees.
    pub search_yaw_max_deg: f64,
    /// Proposal, wide search: the search runs only when the prior's
    /// consensus with the local map (the fraction of the sweep it explains)
    /// falls this fraction below that of the recent sweeps, and another
    /// start replaces the prior only when it explains this fraction more.
    pub search_min_gain: f64,
    /// Samples per particle in a step whose proposal is the scan matcher's
    /// Gaussian and whose match explains the sweep as well as the recent
    /// sweeps did (within `search_min_gain`): they lie within the matcher's
    /// uncertainty, so fewer cover it than the motion noise needs. A step
    /// whose match explains the sweep less (a sharp turn, a new room) draws
    /// `filter.samples_per_particle`, as without a match. 0: always
    /// `filter.samples_per_particle`.
    pub matched_samples_per_particle: usize,
    /// Run the quick culling passes (`filter.passes` over the endpoint
    /// windows) before the full traces. Off by default in 3-D: samples
    /// drawn from the matcher's Gaussian nearly all survive them.
    pub quick_culling: bool,
    /// `points.ply`: one registered point per voxel of this edge, m.
    pub points_voxel: f64,
}

impl Default for Map3dConfig {
    fn default() -> Self {
        Self {
            voxel_size: 0.2,
            max_beams: 3000,
            max_range: 60.0,
            min_range: 0.5,
            beam_voxel: 0.2,
            variance: 0.04,
            trace_sigmas: 5.0,
            occupied_density: 0.5,
            trans_std_per_m: 0.005,
            trans_std_per_rad: 0.02,
            min_trans_std: 0.005,
            rot_std_per_m: 0.001,
            rot_std_per_rad: 0.01,
            min_rot_std: 0.002,
            local_map_sweeps: 10,
            icp_voxel: 0.2,
            icp_levels: 3,
            icp_max_distance: 3.0,
            icp_iterations: 30,
            icp_max_points: 50000,
            icp_covariance_scale: 2.0,
            search_yaw_step_deg: 15.0,
            search_yaw_max_deg: 90.0,
            search_min_gain: 0.1,
            matched_samples_per_particle: 3,
            quick_culling: false,
            points_voxel: 0.1,
        }
    }
}

/// Particle-filter settings.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct FilterConfig {
    /// Particles kept after each resampling.
    pub particles: usize,
    /// Samples drawn per particle per step (release: 10).
    pub samples_per_particle: usize,
    /// Culling passes over interleaved beam subsets (release: 9).
    pub passes: usize,
    /// Samples worse than the best by more than this (nats) are culled (release: 13).
    pub cull_threshold: f64,
    /// A scan is processed only after this much translation (m) ...
    pub min_translation: f64,
    /// ... or this much rotation (rad) since the last processed scan.
    pub min_rotation: f64,
    /// Place each scan the filter skips (it moved less than
    /// `min_translation` and `min_rotation`) by one scan match against the
    /// best particle's map view, from its odometry guess relative to the
    /// last processed scan, instead of by odometry alone. Only with the
    /// scan-matched proposal (`proposal = "scan-matched"`) and the flat
    /// filter; the map and the particles are untouched, so this changes
    /// only the skipped scans' rows of the trajectory. Where the match
    /// fails, or with this off, a skipped scan is placed by its odometry
    /// from the processed scans on both sides, blended by time.
    pub match_skipped: bool,
    /// With `match_skipped`: a scan past `min_translation` /
    /// `min_rotation` is still skipped while the best particle's match of
    /// it confirms the odometry (agrees within `confirm_xy` and
    /// `confirm_theta`), until the robot moved this far (m, by odometry or
    /// by the match) since the last processed scan. Where odometry is
    /// good, the filter then steps about every `confirmed_translation`;
    /// where it slips, the match disagrees and every scan past the small
    /// gate is processed. 0 here or in `confirmed_rotation` (the default)
    /// turns it off. Opt-in: 0.5 m / 0.25 rad halves mit-csail's time at
    /// the same accuracy, but lost fr079-raw on every seed and gate tried
    /// (docs/PROPOSAL-2D.md, session 37).
    pub confirmed_translation: f64,
    /// ... or turned this far (rad).
    pub confirmed_rotation: f64,
    /// The largest gap (m) between odometry and the match of a skipped
    /// scan, both relative to the last processed scan, that still counts
    /// as agreement. Well inside the matcher's search window
    /// (`scan_match.window_xy`): the odometry guess a step starts from then
    /// stays within reach of every particle's match.
    pub confirm_xy: f64,
    /// The same for heading (rad), against `scan_match.window_theta`.
    pub confirm_theta: f64,
    /// Resampling scheme.
    pub resampling: Resampling,
    /// Selective resampling (Grisetti et al., IEEE T-RO 2007, 0.5 there):
    /// the particle set is drawn anew from all samples only when the
    /// effective number of particles (Kish's `(Σw)² / Σw²` of the
    /// particles' accumulated weights) falls below this fraction of
    /// `particles`. Otherwise each particle keeps one of its own samples,
    /// drawn by weight, and carries its weight (× the mean weight of its
    /// samples) to the next step, so a lineage is not lost to one step's
    /// random draw. ≥ 1: resample every step (the release).
    pub resample_below: f64,
    /// Proposal of the 2-D filter: `"motion"` or `"scan-matched"` (3-D
    /// always matches with ICP, see `map3d`).
    pub proposal: ProposalKind,
    /// The pose each 2-D step records for the trajectory: `"sample"` (the
    /// chosen sample itself, the release) or `"posterior-mean"` (the
    /// importance-weighted mean of the samples drawn against the same map
    /// view). The map is built at the samples either way. 3-D always
    /// reports the sample (its ICP proposal reads the trajectory back).
    pub report: ReportedPose,
}

/// The pose a filter step records in the trajectory (`filter.report`).
///
/// A particle filter's sample is a draw from the pose posterior, so a
/// trajectory of samples carries the posterior's width as jitter from scan
/// to scan. The samples drawn from one parent view (all particles on one
/// ancestry node) are importance samples of the pose given that view and
/// the scan; their weighted mean is the minimum-variance estimate of it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "kebab-case")]
pub enum ReportedPose {
    /// The chosen sample (the release's trajectory).
    Sample,
    /// The weighted mean of its parent view's samples (culled samples
    /// weigh nothing).
    #[default]
    PosteriorMean,
}

/// How the next particle set is drawn from the weighted samples.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Resampling {
    /// Independent draws (the release's choice).
    Multinomial,
    /// Low-variance systematic resampling (Thrun et al., Probabilistic Robotics).
    Systematic,
}

/// Grid settings.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct MapConfig {
    /// Cells per metre (release: 35; 20–35 advised).
    pub cells_per_metre: f64,
    /// Free-space evidence for cells every particle already sees as free is
    /// added in place to the shared ancestor entry (averaged over particles)
    /// instead of a new entry per particle. Hits, passes through cells with
    /// hits and newly seen cells are per particle as in the release. `false`
    /// restores the release's every-particle-every-cell update (slower, more memory).
    /// Copies of one resampled sample are one node (`filter::grow`): their
    /// descendants' shares land on that node's entries, divided by its copies
    /// in use (`filter::Copies`), as if each copy still had its own.
    pub shared_free_space: bool,
    /// With `shared_free_space`, at most this many of the new particles
    /// (evenly spread over them) add their path lengths to the shared entries,
    /// each with weight 1/n. The in-place update is an average over particles
    /// whose beams cross the same free cells almost identically; a fixed-size
    /// sample keeps its cost (serial, ~10⁴ cells per particle and scan)
    /// independent of the particle count. 0 = every particle.
    pub free_space_particles: usize,
    /// With `shared_free_space`, divide each in-place share by the owner
    /// node's copies in use (`filter::Copies`), as if each resampled copy
    /// still had its own entries; `false` pools them on the shared node
    /// (faster-growing free space in new rooms: fr079-raw is lost). 2-D
    /// only: the 3-D pipeline pools (docs/PROPOSAL-2D.md).
    pub per_copy_shares: bool,
}

/// Laser penetration model (dissertation ch. 3) and beam selection.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct LaserConfig {
    /// Variance of the range error, m² (release low level: 0.017, σ ≈ 13 cm).
    /// Smaller values sharpen the likelihood but can lose the track on long
    /// runs (docs/DESIGN.md).
    pub variance: f64,
    /// Background floor of a beam's likelihood: the chance that something the
    /// model does not explain happened. The release uses `exp(−24/σ²)` in
    /// cells² at 35 cells/m, i.e. 0.316; kept fixed here whatever the grid
    /// resolution, because sensor outliers do not depend on the grid.
    pub beam_floor: f64,
    /// The full trace runs this many cells past the measured endpoint (release: 20).
    pub trace_past_cells: f64,
    /// Cells further than this from the endpoint add nothing (release: 20).
    pub max_error_cells: f64,
    /// Prior density of unseen cells: one stop per this many metres (release: 8).
    pub prior_stop_every: f64,
    /// A new cell entry starts with this many cells of prior distance (release: 4).
    pub prior_distance_cells: f64,
    /// Culling's quick score traces from this many cells before the endpoint ...
    pub quick_before_cells: f64,
    /// ... to this many cells past it (release: 3.5 and 3).
    pub quick_after_cells: f64,
    /// Usable range, m: longer readings count as "no return" up to this range.
    /// (Release: 7.95 for its SICK; here 0 means "the log's sensor limit, at
    /// most 20 m", because traces cost time linear in range.)
    pub max_range: f64,
    /// Use at most this many beams per scan, evenly spaced (release: 180).
    pub max_beams: usize,
    /// Surface fill, m (0: off, the release's update; default 0.5, with
    /// `scan_match.field_min_hits = 1` keeping the filled cells out of the
    /// scan matcher: the pair won over the suite in session 30,
    /// docs/PROPOSAL-2D.md). A 2-D scan samples a
    /// wall at one endpoint per beam, far apart where the wall is far or
    /// seen at a grazing angle, and a wall cell between two samples then
    /// holds no hit and lets every later beam through. Where two
    /// consecutive returns lie at most this far apart on one straight
    /// surface (see `surface_fill_tolerance`), the map update also adds
    /// `surface_fill_hits` to each cell between them. Without it the likelihood of a scan
    /// in a featureless corridor peaks where the earlier scans were taken,
    /// not at the true pose (docs/PROPOSAL-2D.md, session 28). 3-D sweeps
    /// are not scan lines and never fill.
    pub surface_fill_gap: f64,
    /// Surface fill needs the returns before and after the pair to lie
    /// within this distance (m) of the line through the pair, so that it
    /// does not bridge a doorway or two objects; pairs at most two cells
    /// apart fill without that test.
    pub surface_fill_tolerance: f64,
    /// Hits that surface fill adds to each cell between two returns (a
    /// return adds 1 to its own cell). Session 28: 1 made fhw and
    /// belgioioso worse, 0.25 kept most of the corridor gain without that.
    pub surface_fill_hits: f64,
    /// Keep the log's declared maximum range (its "no return" threshold)
    /// even where the readings contradict it. By default (false) a log whose
    /// readings lie, for ≥ 1 % of them, clearly between the declared maximum
    /// and the log's largest reading is taken to understate its laser: those
    /// readings are returns and only the largest value means "no return"
    /// (CARMEN's `robot_front_laser_max` is a navigation setting, not the
    /// sensor's limit, in some logs).
    pub trust_declared_max_range: bool,
    /// What a reading the sensor flags as "no return" (NaN, ±inf, ≤ 0, or
    /// at its maximum) tells the filter ([`NoReturn`]). Returns beyond the
    /// usable range `max_range` are not affected: they are free space up to
    /// it either way.
    pub no_return: NoReturn,
    /// Angle of the first beam, degrees in the laser frame (0 = ahead,
    /// counter-clockwise positive), overriding what the input says. `None`:
    /// the input's (a bag's `angle_min`; CARMEN FLASER: −90°).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub angle_min_deg: Option<f64>,
    /// Angle between consecutive beams, degrees, overriding what the input
    /// says. `None`: the input's (a bag's `angle_increment`; CARMEN FLASER:
    /// 180°/n for an even count n, 180°/(n−1) for an odd one). For a
    /// recording whose stated geometry is a converter's guess: the ACES and
    /// fr079 ROS 1 bags state 180°/(n−1), while their SICK steps 1° or 0.5°
    /// (docs/PROPOSAL-2D.md, "Beam angles of converted bags").
    #[serde(skip_serializing_if = "Option::is_none")]
    pub angle_increment_deg: Option<f64>,
}

impl LaserConfig {
    /// The configured `(angle_min, angle_increment)` overrides in radians,
    /// `None` where the input's stand (the 2-D reader applies them:
    /// `LogReader2d::with_beam_angles`).
    pub fn beam_angle_overrides(&self) -> (Option<f64>, Option<f64>) {
        (
            self.angle_min_deg.map(f64::to_radians),
            self.angle_increment_deg.map(f64::to_radians),
        )
    }
}

/// The C/D/T motion model of DP-SLAM (dissertation ch. 6): motion along the
/// mean heading (D), across it (C) and turn (T), each Gaussian with mean linear
/// in odometry distance `d` (m) and turn `t` (rad) and std `|a·d| + |b·t|`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Motion2dConfig {
    /// Mean of D: `[k_d, k_t]` → `k_d·d + k_t·t`.
    pub mean_d: [f64; 2],
    /// Mean of C added to the lateral odometry motion.
    pub mean_c: [f64; 2],
    /// Mean of T.
    pub mean_t: [f64; 2],
    /// Std of D: `[a (m/m), b (m/rad)]`.
    pub std_d: [f64; 2],
    /// Std of C: `[a (m/m), b (m/rad)]`.
    pub std_c: [f64; 2],
    /// Std of T: `[a (rad/m), b (rad/rad)]`.
    pub std_t: [f64; 2],
    /// Lower bound of the std of C and D, m (release: 0.8 cells at 35/m).
    pub min_std_xy: f64,
    /// Lower bound of the std of T, rad (release: 0.10).
    pub min_std_t: f64,
    /// Laser pose in the robot frame `[x, y, θ]`; `None`: the log format's
    /// default (DP-SLAM logs: 0.40 m ahead, CARMEN: the logged laser pose).
    pub sensor_offset: Option<[f64; 3]>,
}

impl Default for Config {
    fn default() -> Self {
        Self {
            seed: 1,
            threads: 0,
            filter: FilterConfig::default(),
            map: MapConfig::default(),
            laser: LaserConfig::default(),
            motion2d: Motion2dConfig::default(),
            map3d: Map3dConfig::default(),
            motion_learning: MotionLearningConfig::default(),
            hierarchy: HierarchyConfig::default(),
            scan_match: ScanMatchConfig::default(),
            gpu: GpuConfig::default(),
            bag: Default::default(),
            input: Default::default(),
            refine: RefineConfig::default(),
        }
    }
}

impl Default for FilterConfig {
    fn default() -> Self {
        Self {
            particles: 50,
            samples_per_particle: 10,
            passes: 9,
            cull_threshold: 13.0,
            min_translation: 0.05,
            min_rotation: 0.03,
            match_skipped: true,
            confirmed_translation: 0.0,
            confirmed_rotation: 0.0,
            confirm_xy: 0.1,
            confirm_theta: 0.05,
            resampling: Resampling::Multinomial,
            resample_below: 1.0,
            proposal: ProposalKind::default(),
            report: ReportedPose::default(),
        }
    }
}

impl Default for MapConfig {
    fn default() -> Self {
        Self {
            cells_per_metre: 35.0,
            shared_free_space: true,
            free_space_particles: 64,
            per_copy_shares: true,
        }
    }
}

impl Default for LaserConfig {
    fn default() -> Self {
        Self {
            variance: 0.017,
            beam_floor: (-24.0f64 / (0.017 * 35.0 * 35.0)).exp(),
            trace_past_cells: 20.0,
            max_error_cells: 20.0,
            prior_stop_every: 8.0,
            prior_distance_cells: 4.0,
            quick_before_cells: 3.5,
            quick_after_cells: 3.0,
            max_range: 0.0,
            max_beams: 181,
            surface_fill_gap: 0.5,
            surface_fill_tolerance: 0.05,
            surface_fill_hits: 0.25,
            trust_declared_max_range: false,
            no_return: NoReturn::default(),
            angle_min_deg: None,
            angle_increment_deg: None,
        }
    }
}

/// The release's constants were learned in cells of 1/35 m; converted to metres here.
const RELEASE_CELL: f64 = 1.0 / 35.0;

impl Default for Motion2dConfig {
    fn default() -> Self {
        // Stds are the release's learned values. Means are unbiased: the
        // release's means (e.g. D = 0.9577·d) encode one ATRV Jr's
        // miscalibration and would bias every other robot.
        Self {
            mean_d: [1.0, 0.0],
            mean_c: [0.0, 0.0],
            mean_t: [0.0, 1.0],
            std_d: [0.1560, 1.9924 * RELEASE_CELL],
            std_c: [0.0630, 2.2992 * RELEASE_CELL],
            std_t: [0.0008 / RELEASE_CELL, 0.1405],
            min_std_xy: 0.8 * RELEASE_CELL,
            min_std_t: 0.10,
            sensor_offset: None,
        }
    }
}

/// Parses a TOML file into `T`. Syntax errors, wrong types and unknown keys
/// (where `T` denies them) name the file and the line.
pub fn read_toml<T: serde::de::DeserializeOwned>(path: &Path) -> Result<T> {
    let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
    toml::from_str(&text).map_err(|e| {
        let reason = e.message().to_string();
        match e.span() {
            Some(span) => {
                let line = text[..span.start.min(text.len())].matches('\n').count() + 1;
                Error::at_line(path, line, reason)
            }
            None => Error::in_file(path, reason),
        }
    })
}

/// Checks that every `(name, value)` is finite and positive, or (with
/// `zero_ok`) finite and ≥ 0; the error names `what` and the field.
pub fn check_values(what: &str, values: &[(&str, f64)], zero_ok: bool) -> Result<()> {
    for &(name, v) in values {
        let ok = v.is_finite() && if zero_ok { v >= 0.0 } else { v > 0.0 };
        if !ok {
            let need = if zero_ok {
                "≥ 0 and finite"
            } else {
                "positive and finite"
            };
            return Err(Error::Config(format!(
                "{what}: {name} must be {need}, got {v}"
            )));
        }
    }
    Ok(())
}

impl Config {
    /// Reads a TOML file; unknown keys are errors (typos must not pass silently).
    pub fn from_toml_file(path: &Path) -> Result<Self> {
        let cfg: Config = read_toml(path)?;
        cfg.validate()?;
        Ok(cfg)
    }

    /// The configuration as TOML text.
    pub fn to_toml(&self) -> String {
        toml::to_string_pretty(self).expect("config serializes")
    }

    /// Checks ranges of values.
    pub fn validate(&self) -> Result<()> {
        let f = &self.filter;
        let bad = |m: &str| Err(Error::Config(m.to_string()));
        if f.particles == 0 {
            return bad("filter.particles must be at least 1");
        }
        if f.samples_per_particle == 0 {
            return bad("filter.samples_per_particle must be at least 1");
        }
        if f.passes == 0 {
            return bad("filter.passes must be at least 1");
        }
        check_values(
            "filter",
            &[
                ("confirmed_translation", f.confirmed_translation),
                ("confirmed_rotation", f.confirmed_rotation),
                ("confirm_xy", f.confirm_xy),
                ("confirm_theta", f.confirm_theta),
            ],
            true,
        )?;
        if f.resample_below.is_nan() || f.resample_below < 0.0 {
            return bad("filter.resample_below must be ≥ 0 (≥ 1: every step)");
        }
        if !(self.map.cells_per_metre.is_finite() && self.map.cells_per_metre > 0.0) {
            return bad("map.cells_per_metre must be positive");
        }
        let l = &self.laser;
        if !(l.variance > 0.0 && l.variance.is_finite()) {
            return bad("laser.variance must be positive");
        }
        if l.max_range < 0.0 || !l.max_range.is_finite() {
            return bad("laser.max_range must be ≥ 0 (0 = sensor limit)");
        }
        if l.max_beams == 0 {
            return bad("laser.max_beams must be at least 1");
        }
        if let Some(a) = l.angle_min_deg
            && !(a.is_finite() && a.abs() <= 360.0)
        {
            return bad("laser.angle_min_deg must be finite, within ±360");
        }
        if let Some(a) = l.angle_increment_deg
            && !(a.is_finite() && a > 0.0 && a <= 360.0)
        {
            return bad("laser.angle_increment_deg must be in (0, 360]");
        }
        if !(l.beam_floor > 0.0 && l.beam_floor < 1.0) {
            return bad("laser.beam_floor must be in (0, 1)");
        }
        if l.prior_stop_every.is_nan() || l.prior_stop_every <= 0.0 {
            return bad("laser.prior_stop_every must be positive");
        }
        // A NaN gap would pass every pair's `len > gap` test and fill them all.
        check_values(
            "laser",
            &[
                ("surface_fill_gap", l.surface_fill_gap),
                ("surface_fill_tolerance", l.surface_fill_tolerance),
            ],
            true,
        )?;
        check_values(
            "laser",
            &[("surface_fill_hits", l.surface_fill_hits)],
            false,
        )?;
        let w = self.scan_match.wall_radius;
        if !(w.is_finite() && w > 0.0 && w <= 5.0) {
            return bad("scan_match.wall_radius must be in (0, 5] m");
        }
        check_values(
            "scan_match",
            &[
                ("field_min_hits", self.scan_match.field_min_hits),
                ("endpoint_spacing", self.scan_match.endpoint_spacing),
            ],
            true,
        )?;
        let ms = self.scan_match.motion_share;
        if !(ms.is_finite() && (0.0..1.0).contains(&ms)) {
            return bad("scan_match.motion_share must be in [0, 1)");
        }
        let h = &self.hierarchy;
        if h.window == 0 || h.particles == 0 || h.samples_per_particle == 0 {
            return bad("hierarchy.window, particles and samples_per_particle must be at least 1");
        }
        check_values(
            "hierarchy",
            &[
                ("variance", h.variance),
                ("perturb_xy_cells", h.perturb_xy_cells),
                ("perturb_theta", h.perturb_theta),
            ],
            true,
        )?;
        if h.variance <= 0.0 {
            return bad("hierarchy.variance must be positive");
        }
        let r = &self.refine;
        check_values(
            "refine",
            &[("resolution", r.resolution), ("sigma", r.sigma)],
            false,
        )?;
        if !(r.floor > 0.0 && r.floor < 1.0) {
            return bad("refine.floor must be in (0, 1)");
        }
        if r.min_hits == 0 {
            return bad("refine.min_hits must be at least 1");
        }
        let m = &self.motion_learning;
        check_values(
            "motion_learning",
            &[
                ("min_std_xy_cells", m.min_std_xy_cells),
                ("min_std_t", m.min_std_t),
                ("outlier_sigmas", m.outlier_sigmas),
                ("inflation", m.inflation),
            ],
            false,
        )?;
        validate_map3d(&self.map3d)
    }

    /// Sizes rayon's global pool to `threads` (0: leave rayon's default, all
    /// cores). A process has one global pool: once it exists, later calls
    /// change nothing.
    pub fn install_thread_pool(&self) {
        if self.threads > 0 {
            // The error says a pool already exists: keep that one.
            let _ = rayon::ThreadPoolBuilder::new()
                .num_threads(self.threads)
                .build_global();
        }
    }

    /// Cell size in metres.
    pub fn cell_size(&self) -> f64 {
        1.0 / self.map.cells_per_metre
    }
}

/// Checks the 3-D settings (part of [`Config::validate`]).
fn validate_map3d(m: &Map3dConfig) -> Result<()> {
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
    if !nonneg(m.search_yaw_step_deg) || !nonneg(m.search_yaw_max_deg) || !nonneg(m.search_min_gain)
    {
        return bad("search_yaw_step_deg, search_yaw_max_deg and search_min_gain must be ≥ 0");
    }
    if !nonneg(m.trace_sigmas) {
        return bad("trace_sigmas must be ≥ 0");
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn toml_round_trip_and_partial_files() {
        let c = Config::default();
        let back: Config = toml::from_str(&c.to_toml()).unwrap();
        assert_eq!(c, back);
        let partial: Config = toml::from_str("seed = 7\n[filter]\nparticles = 3\n").unwrap();
        assert_eq!(partial.seed, 7);
        assert_eq!(partial.filter.particles, 3);
        assert_eq!(partial.filter.passes, 9);
    }

    #[test]
    fn unknown_keys_and_bad_values_are_errors_with_line() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("c.toml");
        std::fs::write(&p, "seed = 1\n[filter]\nparticle = 3\n").unwrap();
        let e = Config::from_toml_file(&p).unwrap_err().to_string();
        assert!(e.contains("c.toml:line 3") && e.contains("particle"), "{e}");
        std::fs::write(&p, "[filter]\nparticles = 0\n").unwrap();
        let e = Config::from_toml_file(&p).unwrap_err().to_string();
        assert!(e.contains("particles"), "{e}");
        for bad in ["-0.1", "nan"] {
            std::fs::write(&p, format!("[filter]\nresample_below = {bad}\n")).unwrap();
            let e = Config::from_toml_file(&p).unwrap_err().to_string();
            assert!(e.contains("resample_below"), "{bad}: {e}");
        }
    }

    #[test]
    fn bad_surface_fill_settings_are_config_errors() {
        for (key, value) in [
            ("surface_fill_gap", f64::NAN),
            ("surface_fill_gap", -0.5),
            ("surface_fill_tolerance", f64::INFINITY),
            ("surface_fill_hits", 0.0),
            ("surface_fill_hits", -0.25),
        ] {
            let mut c = Config::default();
            match key {
                "surface_fill_gap" => c.laser.surface_fill_gap = value,
                "surface_fill_tolerance" => c.laser.surface_fill_tolerance = value,
                _ => c.laser.surface_fill_hits = value,
            }
            let e = c.validate().unwrap_err().to_string();
            assert!(e.contains(key), "{key} = {value}: {e}");
        }
        let mut c = Config::default();
        c.laser.surface_fill_gap = 0.0;
        assert!(c.validate().is_ok());
    }

    #[test]
    fn field_min_hits_keeps_fill_cells_out_of_the_match_field() {
        let mut m = ScanMatchConfig::default();
        // The default, 1: a quarter-hit fill cell stays out, an endpoint's
        // cell (1 hit) is in.
        assert!(!m.field_keeps(0.25) && !m.field_keeps(0.75));
        assert!(m.field_keeps(1.0) && m.field_keeps(1.25) && m.field_keeps(7.0));
        m.field_min_hits = 0.0;
        assert!(m.field_keeps(0.25) && m.field_keeps(1.0));
        assert!(!m.field_keeps(0.0) && !m.field_keeps(-1.0));
        for bad in [f64::NAN, -1.0, f64::INFINITY] {
            let mut c = Config::default();
            c.scan_match.field_min_hits = bad;
            let e = c.validate().unwrap_err().to_string();
            assert!(e.contains("field_min_hits"), "{bad}: {e}");
        }
    }

    #[test]
    fn a_motion_share_outside_zero_to_one_is_a_config_error() {
        for bad in [f64::NAN, -0.1, 1.0, 2.0, f64::INFINITY] {
            let mut c = Config::default();
            c.scan_match.motion_share = bad;
            let e = c.validate().unwrap_err().to_string();
            assert!(e.contains("motion_share"), "{bad}: {e}");
        }
        for ok in [0.0, 0.2, 0.99] {
            let mut c = Config::default();
            c.scan_match.motion_share = ok;
            assert!(c.validate().is_ok(), "{ok}");
        }
    }

    #[test]
    fn bad_confirmed_gate_settings_are_config_errors() {
        type Set = fn(&mut FilterConfig, f64);
        let keys: [(&str, Set); 4] = [
            ("confirmed_translation", |f, v| f.confirmed_translation = v),
            ("confirmed_rotation", |f, v| f.confirmed_rotation = v),
            ("confirm_xy", |f, v| f.confirm_xy = v),
            ("confirm_theta", |f, v| f.confirm_theta = v),
        ];
        for (key, set) in keys {
            for bad in [f64::NAN, -0.1, f64::INFINITY] {
                let mut c = Config::default();
                set(&mut c.filter, bad);
                let e = c.validate().unwrap_err().to_string();
                assert!(e.contains(key), "{key} = {bad}: {e}");
            }
            let mut c = Config::default();
            set(&mut c.filter, 0.3);
            assert!(c.validate().is_ok(), "{key}");
        }
    }

    #[test]
    fn bad_3d_settings_are_config_errors() {
        let mut c = Config::default();
        c.map3d.voxel_size = 0.0;
        assert!(c.validate().unwrap_err().to_string().contains("voxel_size"));
        assert!(Config::default().validate().is_ok());
    }

    #[test]
    fn beam_angle_overrides_replace_each_part_and_are_checked() {
        let mut c = Config::default();
        assert_eq!(c.laser.beam_angle_overrides(), (None, None));
        c.laser.angle_increment_deg = Some(0.5);
        let (min, inc) = c.laser.beam_angle_overrides();
        assert_eq!(min, None);
        assert!((inc.unwrap() - 0.5f64.to_radians()).abs() < 1e-15);
        c.laser.angle_min_deg = Some(-135.0);
        let min = c.laser.beam_angle_overrides().0.unwrap();
        assert!((min + 0.75 * std::f64::consts::PI).abs() < 1e-15);
        let back: Config = toml::from_str(&c.to_toml()).unwrap();
        assert_eq!(back, c);
        c.laser.angle_increment_deg = Some(0.0);
        assert!(
            c.validate()
                .unwrap_err()
                .to_string()
                .contains("angle_increment_deg")
        );
        c.laser.angle_increment_deg = None;
        c.laser.angle_min_deg = Some(f64::NAN);
        assert!(
            c.validate()
                .unwrap_err()
                .to_string()
                .contains("angle_min_deg")
        );
    }
}
