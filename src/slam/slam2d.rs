//! Online 2-D DP-SLAM: laser scans with odometry in, poses and a map out.

use super::{Estimate, check_input, fill_trajectory};
use crate::ancestry::{NodeId, Numbering};
use crate::config::{Config, FilterConfig, Motion2dConfig, NoReturn, ProposalKind};
use crate::dpmap::DpMap;
use crate::filter::{ParticleFilter, Stamp, StepInput, StepStats};
use crate::geometry::{Pose2, pose2};
use crate::hierarchy::HierarchicalFilter;
use crate::io::map_image::OccupancyRaster;
use crate::laser_model::LaserModel;
use crate::motion_learning::MotionSample;
use crate::motion_model::CdtModel;
use crate::proposal::Proposal;
use crate::scan::{Beam, Ranges2d, Scan};
use crate::scan_match::ScanMatcher2d;
use crate::scorer::Scorer;
use crate::{Error, Result};

/// Cap on the default usable range (m): traces cost time linear in range.
/// Where more than a tenth of a log's returns lie beyond it (outdoors),
/// `map2d` raises it to cover [`RANGE_SHARE`] of them
/// ([`Slam2d::set_default_range`]).
pub const DEFAULT_RANGE_CAP: f64 = 20.0;

/// Share of a log's returns the default usable range covers at least.
pub const RANGE_SHARE: f64 = 0.9;

/// Map images show, per cell, the probability that a beam is stopped within
/// this many metres of travel through material of the cell's density. One
/// cell's width would render a wall seen a handful of times as light grey
/// (a fresh cell carries 4 cells of prior path); 10 cm makes such walls dark
/// while free space (density 0) stays white.
pub const DISPLAY_PATH: f64 = 0.10;

/// The usable range (m) for a laser whose sensor limit is `sensor_max`:
/// `laser.max_range` where set, else the sensor limit capped at `cap` (m).
pub fn usable_range(cfg: &Config, sensor_max: f64, cap: f64) -> f64 {
    if cfg.laser.max_range > 0.0 {
        cfg.laser.max_range
    } else {
        sensor_max.min(cap)
    }
}

/// Converts one reading to the filter's form: evenly thinned to at most
/// `max_beams` beams, readings beyond `max_range` (m), or none, as "no return".
/// Where `flagged` says so ([`NoReturn::skips`]), the beams the sensor flags
/// as "no return" are left out after the thinning (those beyond `max_range`
/// stay, as free space).
///
/// Readings at or above the reading's declared maximum (`s.max_range`) are
/// "no return" too, unless `max_range` is above that maximum: a configured
/// `laser.max_range` beyond the declared one says the header understates
/// the laser (edmonton's declares 10 m and holds returns to 50 m), and real
/// returns below it are kept.
pub fn to_scan(
    s: &Ranges2d<'_>,
    sensor: Pose2,
    max_beams: usize,
    max_range: f64,
    flagged: NoReturn,
) -> Scan<2, Pose2> {
    let n = s.ranges.len();
    let stride = n.div_ceil(max_beams.max(1)).max(1);
    let trust_beyond_declared = max_range > s.max_range;
    let skip_flagged = flagged.skips(s.max_range, max_range);
    let beams = (0..n)
        .step_by(stride)
        .filter_map(|i| {
            let a = s.angle_min + i as f64 * s.angle_increment;
            let r = s.ranges[i];
            let kept = trust_beyond_declared && r.is_finite() && r > 0.0;
            let sensor_says_none = s.is_no_return(i) && !kept;
            if sensor_says_none && skip_flagged {
                return None;
            }
            let no_return = sensor_says_none || r > max_range;
            Some(Beam {
                dir: [a.cos(), a.sin()],
                range: if no_return { max_range } else { r },
                no_return,
            })
        })
        .collect();
    Scan { sensor, beams }
}

/// Whether the robot moved enough since the last processed scan for the
/// filter to process this one: `delta` (odometry motion, previous robot
/// frame) of at least `min_translation` m or `min_rotation` rad.
pub fn moved_enough(f: &FilterConfig, delta: &Pose2) -> bool {
    reaches(delta, f.min_translation, f.min_rotation)
}

/// Whether the motion `delta` is at least `translation` m or `rotation` rad.
fn reaches(delta: &Pose2, translation: f64, rotation: f64) -> bool {
    delta.translation.vector.norm() >= translation || delta.rotation.angle().abs() >= rotation
}

/// Whether the robot went far enough since the last processed scan that
/// the filter processes this one even where its match confirms odometry:
/// `delta` (previous robot frame) of at least `confirmed_translation` m or
/// `confirmed_rotation` rad. Always true with either at 0 (the gate off).
pub fn beyond_confirmed(f: &FilterConfig, delta: &Pose2) -> bool {
    f.confirmed_translation <= 0.0
        || f.confirmed_rotation <= 0.0
        || reaches(delta, f.confirmed_translation, f.confirmed_rotation)
}

/// Whether a skipped scan's match `matched` confirms the odometry motion
/// `delta` (both from the last processed scan, in its robot frame): they
/// differ by less than `confirm_xy` m and `confirm_theta` rad.
pub fn confirms(f: &FilterConfig, delta: &Pose2, matched: &Pose2) -> bool {
    let gap = delta.inverse() * matched;
    gap.translation.vector.norm() < f.confirm_xy && gap.rotation.angle().abs() < f.confirm_theta
}

/// The 2-D filter of a run with `cfg`: particles at the origin with `first`
/// (input index `index`) in the map, the C/D/T motion model.
pub fn new_filter(
    cfg: &Config,
    laser: LaserModel,
    first: &Scan<2, Pose2>,
    index: u32,
) -> ParticleFilter<2, Pose2> {
    let cdt = CdtModel {
        cfg: cfg.motion2d.clone(),
    };
    let motion = Box::new(cdt.clone());
    let mut filter = ParticleFilter::new(
        cfg.filter.clone(),
        laser,
        motion,
        cfg.seed,
        Pose2::identity(),
        first,
        index,
    );
    filter.set_map_update(&cfg.map);
    if cfg.filter.proposal == ProposalKind::ScanMatched {
        filter.set_scan_matcher(Box::new(ScanMatcher2d::new(
            cfg.scan_match.clone(),
            cdt,
            cfg.cell_size(),
            cfg.laser.variance,
        )));
        filter.set_matched_samples_per_particle(cfg.scan_match.samples_per_particle);
        filter.set_quick_culling(cfg.scan_match.quick_culling);
    }
    filter
}

/// The proposal of a 2-D step under `cfg` (`filter.proposal`).
pub fn proposal_of(cfg: &Config) -> Proposal<Pose2> {
    match cfg.filter.proposal {
        ProposalKind::Motion => Proposal::Motion,
        ProposalKind::ScanMatched => Proposal::ScanMatched,
    }
}

/// Renders `map` as the particle holding ancestry node `node` sees it.
pub fn raster_of_view(
    map: &DpMap<2>,
    numbering: &Numbering,
    node: NodeId,
) -> Result<OccupancyRaster> {
    let (lo, hi) = map
        .bounds()
        .ok_or_else(|| Error::Invalid("the map is empty".into()))?;
    let width = (hi[0] - lo[0] + 1) as usize;
    let height = (hi[1] - lo[1] + 1) as usize;
    let mut cells = vec![f32::NAN; width * height];
    let mut view = map.view(numbering, node);
    let c = map.cell_size();
    map.for_each_cell(|k, _| {
        if let Some((h, d)) = view.lookup(k) {
            let rho = if h > 0.0 { h as f64 / d as f64 } else { 0.0 };
            let i = (k[1] - lo[1]) as usize * width + (k[0] - lo[0]) as usize;
            cells[i] = (1.0 - (-rho * DISPLAY_PATH).exp()) as f32;
        }
    });
    Ok(OccupancyRaster {
        width,
        height,
        resolution: c,
        origin: [lo[0] as f64 * c, lo[1] as f64 * c],
        cells,
    })
}

/// The filter of a 2-D run: DP-SLAM, or hierarchical DP-SLAM over it.
enum Levels {
    /// One particle filter over the whole input.
    Flat(Box<ParticleFilter<2, Pose2>>),
    /// Windows of the input under a high-level filter (`[hierarchy]`).
    Hierarchical(Box<HierarchicalFilter<2, Pose2>>),
}

impl Levels {
    fn step(&mut self, input: &StepInput<'_, 2, Pose2>) -> StepStats {
        match self {
            Levels::Flat(f) => f.step(input),
            Levels::Hierarchical(h) => h.step(input),
        }
    }

    fn best_trajectory(&self) -> Vec<Stamp<Pose2>> {
        match self {
            Levels::Flat(f) => f.best_trajectory(),
            Levels::Hierarchical(h) => h.best_trajectory(),
        }
    }

    /// The best particle's scan match of a scan the filter skips (the flat
    /// filter only: [`ParticleFilter::match_best`]).
    fn match_best(&self, odometry: &Pose2, scan: &Scan<2, Pose2>) -> Option<Pose2> {
        match self {
            Levels::Flat(f) => f.match_best(odometry, scan),
            Levels::Hierarchical(_) => None,
        }
    }

    fn best_pose(&self) -> Pose2 {
        match self {
            Levels::Flat(f) => f.particles()[f.best_index()].pose,
            Levels::Hierarchical(h) => h.best_pose(),
        }
    }

    fn map(&self) -> &DpMap<2> {
        match self {
            Levels::Flat(f) => f.map(),
            Levels::Hierarchical(h) => h.map(),
        }
    }

    fn raster(&self) -> Result<OccupancyRaster> {
        match self {
            Levels::Flat(f) => {
                raster_of_view(f.map(), f.numbering(), f.particles()[f.best_index()].node)
            }
            Levels::Hierarchical(h) => raster_of_view(h.map(), h.numbering(), h.best_node()),
        }
    }

    fn tree_nodes(&self) -> usize {
        match self {
            Levels::Flat(f) => f.tree().len(),
            Levels::Hierarchical(h) => h.tree_nodes(),
        }
    }

    fn scorer(&self) -> &dyn Scorer<2, Pose2> {
        match self {
            Levels::Flat(f) => f.scorer(),
            Levels::Hierarchical(h) => h.low().scorer(),
        }
    }
}

/// Online 2-D DP-SLAM.
///
/// Feed it every laser scan with the robot's odometry pose at the scan's
/// time ([`Slam2d::add_scan`]); it processes a scan when the robot moved at
/// least `filter.min_translation` or turned `filter.min_rotation` since the
/// last processed one (the first is always processed) and places the
/// others by a scan match against the best particle's map
/// (`filter.match_skipped`) or by odometry. With the opt-in confirmed gate
/// (`filter.confirmed_translation`), a scan past that gate is skipped too
/// while its match confirms the odometry. The map frame is the robot
/// frame at the first scan.
pub struct Slam2d {
    cfg: Config,
    /// Laser pose in the robot frame.
    mount: Pose2,
    /// "No return" threshold overriding each reading's declared maximum, m.
    no_return_at: Option<f64>,
    /// Cap on the usable range when `laser.max_range` is 0, m.
    range_cap: f64,
    /// The scorer to use, until the filter exists (built on the first scan).
    scorer: Option<Box<dyn Scorer<2, Pose2>>>,
    levels: Option<Levels>,
    /// Odometry of the last processed scan.
    last_processed: Option<Pose2>,
    /// Per input scan: time (s) and odometry pose.
    stamps: Vec<(f64, Pose2)>,
    /// Skipped scans placed by a scan match (`filter.match_skipped`): input
    /// index and the matched motion from the last processed scan's pose
    /// (its robot frame), in input order.
    matched_skips: Vec<(usize, Pose2)>,
    stats: Vec<StepStats>,
    max_range: f64,
    beams_per_scan: usize,
}

impl Slam2d {
    /// A SLAM run with the settings of `cfg` (checked here), the laser at
    /// `motion2d.sensor_offset` in the robot frame (the robot's origin when
    /// unset) and the CPU scorer.
    pub fn new(cfg: Config) -> Result<Self> {
        cfg.validate()?;
        let mount = match cfg.motion2d.sensor_offset {
            Some([x, y, th]) => pose2(x, y, th),
            None => Pose2::identity(),
        };
        Ok(Self {
            cfg,
            mount,
            no_return_at: None,
            range_cap: DEFAULT_RANGE_CAP,
            scorer: None,
            levels: None,
            last_processed: None,
            stamps: Vec::new(),
            matched_skips: Vec::new(),
            stats: Vec::new(),
            max_range: 0.0,
            beams_per_scan: 0,
        })
    }

    /// Sets the laser's pose in the robot frame (m, rad) for the scans that
    /// follow.
    pub fn set_mount(&mut self, mount: Pose2) {
        self.mount = mount;
    }

    /// Readings at or above `range` (m) mean "no return", whatever each
    /// reading declares as its maximum (`None`: trust the declaration). For
    /// lasers whose declared maximum understates what they return (see
    /// [`crate::pipeline::map2d::RangeSurvey`]).
    pub fn set_no_return_range(&mut self, range: Option<f64>) {
        self.no_return_at = range;
    }

    /// Caps the usable range at `range` m instead of [`DEFAULT_RANGE_CAP`]
    /// when `laser.max_range` is 0 (`None`: that cap), e.g. from
    /// [`crate::pipeline::map2d::RangeSurvey::default_range`]. Takes effect
    /// from the first scan; call it before.
    pub fn set_default_range(&mut self, range: Option<f64>) {
        self.range_cap = range.unwrap_or(DEFAULT_RANGE_CAP);
    }

    /// Scores scans with `scorer` (e.g. the GPU backend) instead of the CPU.
    /// Takes effect from the first scan; call it before.
    pub fn set_scorer(&mut self, scorer: Box<dyn Scorer<2, Pose2>>) -> Result<()> {
        if self.levels.is_some() {
            return Err(Error::Invalid(
                "the scorer must be set before the first scan".into(),
            ));
        }
        self.scorer = Some(scorer);
        Ok(())
    }

    /// Adds the scan taken at time `stamp` (s) with the robot at odometry
    /// pose `odometry` (odometry frame); returns the estimate after it.
    pub fn add_scan(
        &mut self,
        stamp: f64,
        odometry: Pose2,
        reading: &Ranges2d<'_>,
    ) -> Result<Estimate<Pose2>> {
        let index = self.stamps.len();
        check_input::<2, Pose2>(index, stamp, Some(&odometry))?;
        reading
            .check()
            .map_err(|why| Error::Invalid(format!("scan {index}: {why}")))?;
        let reading = reading.with_no_return_at(self.no_return_at);
        self.stamps.push((stamp, odometry));
        let processed = match (&mut self.levels, self.last_processed) {
            (None, _) => {
                self.start(&reading, index as u32);
                true
            }
            (Some(levels), Some(odo0)) => {
                let delta = odo0.inverse() * odometry;
                let moved = moved_enough(&self.cfg.filter, &delta);
                let matching = self.cfg.filter.match_skipped
                    && self.cfg.filter.proposal == ProposalKind::ScanMatched;
                let mut step = moved;
                if moved || matching {
                    let scan = to_scan(
                        &reading,
                        self.mount,
                        self.cfg.laser.max_beams,
                        self.max_range,
                        self.cfg.laser.no_return,
                    );
                    let f = &self.cfg.filter;
                    // Past the small gate, a scan whose match confirms the
                    // odometry is still skipped, up to the confirmed gate.
                    let confirmed = (matching && moved && !beyond_confirmed(f, &delta))
                        .then(|| levels.match_best(&delta, &scan))
                        .flatten()
                        .filter(|m| confirms(f, &delta, m) && !beyond_confirmed(f, m));
                    step = moved && confirmed.is_none();
                    if step {
                        let input = StepInput {
                            odometry: delta,
                            proposal: proposal_of(&self.cfg),
                            scan: &scan,
                            index: index as u32,
                        };
                        self.stats.push(levels.step(&input));
                    } else if let Some(matched) =
                        confirmed.or_else(|| levels.match_best(&delta, &scan))
                    {
                        self.matched_skips.push((index, matched));
                    }
                }
                step
            }
            (Some(_), None) => unreachable!("a filter exists only after the first scan"),
        };
        if processed {
            self.last_processed = Some(odometry);
        }
        Ok(Estimate {
            index,
            stamp,
            pose: self.pose_now(),
            processed,
        })
    }

    /// Builds the filter on the first scan.
    fn start(&mut self, reading: &Ranges2d<'_>, index: u32) {
        let cfg = &self.cfg;
        self.max_range = usable_range(cfg, reading.max_range, self.range_cap);
        let scan = to_scan(
            reading,
            self.mount,
            cfg.laser.max_beams,
            self.max_range,
            cfg.laser.no_return,
        );
        self.beams_per_scan = scan.beams.len();
        let laser = LaserModel::new(&cfg.laser, cfg.cell_size(), self.max_range);
        let mut filter = new_filter(cfg, laser, &scan, index);
        if let Some(sc) = self.scorer.take() {
            filter.set_scorer(sc);
        }
        self.levels = Some(if cfg.hierarchy.enabled {
            let h = &cfg.hierarchy;
            // A zero motion through the C/D/T model draws each axis from
            // its floor: x, y ~ N(0, σ_xy), θ ~ N(0, σ_θ).
            let perturb = CdtModel {
                cfg: Motion2dConfig {
                    std_d: [0.0; 2],
                    std_c: [0.0; 2],
                    std_t: [0.0; 2],
                    min_std_xy: h.perturb_xy_cells * cfg.cell_size(),
                    min_std_t: h.perturb_theta,
                    ..Motion2dConfig::default()
                },
            };
            Levels::Hierarchical(Box::new(HierarchicalFilter::new(
                filter,
                cfg,
                Box::new(perturb),
                &scan,
                index,
            )))
        } else {
            Levels::Flat(Box::new(filter))
        });
    }

    /// The best pose now (map frame): past the last processed scan, by
    /// this scan's match where it was matched, else by odometry.
    fn pose_now(&self) -> Pose2 {
        let (Some(levels), Some(odo0), Some(&(_, odo))) =
            (&self.levels, self.last_processed, self.stamps.last())
        else {
            return Pose2::identity();
        };
        match self.matched_skips.last() {
            Some(&(i, matched)) if i + 1 == self.stamps.len() => levels.best_pose() * matched,
            _ => levels.best_pose() * (odo0.inverse() * odo),
        }
    }

    /// Ends the run: closes the open window of hierarchical SLAM (nothing
    /// to do for the flat filter). Call once after the last scan.
    pub fn finish(&mut self) {
        if let Some(Levels::Hierarchical(h)) = &mut self.levels {
            h.finish();
        }
    }

    /// Scans added so far.
    pub fn scans(&self) -> usize {
        self.stamps.len()
    }

    /// What each filter step did (one per processed scan after the first).
    pub fn stats(&self) -> &[StepStats] {
        &self.stats
    }

    /// The trajectory, one `(time s, pose)` row per input scan (map frame):
    /// processed scans from the best particle; the others by their scan
    /// match from the last processed one (`filter.match_skipped`), or by
    /// odometry from the processed scans on both sides.
    pub fn trajectory(&self) -> Result<Vec<(f64, Pose2)>> {
        let corrected = self.best_trajectory();
        fill_trajectory(&self.stamps, &corrected, &self.matched_skips)
    }

    /// The best particle's poses, one per processed scan.
    pub fn best_trajectory(&self) -> Vec<Stamp<Pose2>> {
        self.levels
            .as_ref()
            .map_or_else(Vec::new, Levels::best_trajectory)
    }

    /// The DP-map of the whole run (`None` before the first scan).
    pub fn map(&self) -> Option<&DpMap<2>> {
        self.levels.as_ref().map(Levels::map)
    }

    /// The map as the best particle sees it.
    pub fn raster(&self) -> Result<OccupancyRaster> {
        self.levels
            .as_ref()
            .ok_or_else(|| Error::Invalid("no scan yet: the map is empty".into()))?
            .raster()
    }

    /// Live ancestry nodes (the high level's, hierarchically).
    pub fn tree_nodes(&self) -> usize {
        self.levels.as_ref().map_or(0, Levels::tree_nodes)
    }

    /// The scan scorer in use (both levels', hierarchically).
    pub fn scorer(&self) -> Option<&dyn Scorer<2, Pose2>> {
        self.levels.as_ref().map(Levels::scorer)
    }

    /// Usable laser range, m (set by the first scan).
    pub fn max_range(&self) -> f64 {
        self.max_range
    }

    /// Beams used per scan after thinning (set by the first scan).
    pub fn beams_per_scan(&self) -> usize {
        self.beams_per_scan
    }

    /// The configuration in use.
    pub fn config(&self) -> &Config {
        &self.cfg
    }

    /// Odometry and best-trajectory motion between consecutive processed
    /// scans, for learning the motion model ([`crate::motion_learning`]).
    pub fn motion_samples(&self) -> Vec<MotionSample> {
        self.best_trajectory()
            .windows(2)
            .map(|w| {
                let (a, b) = (&w[0], &w[1]);
                let (oa, ob) = (
                    self.stamps[a.scan as usize].1,
                    self.stamps[b.scan as usize].1,
                );
                MotionSample {
                    odometry: oa.inverse() * ob,
                    estimate: a.pose.inverse() * b.pose,
                }
            })
            .collect()
    }
}
