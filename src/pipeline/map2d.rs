//! The 2-D mapping run: a CARMEN or DP-SLAM log in, a run folder out.

use crate::ancestry::{NodeId, Numbering};
use crate::config::Config;
use crate::config::Motion2dConfig;
use crate::dpmap::DpMap;
use crate::filter::{ParticleFilter, Stamp, StepStats};
use crate::geometry::{Pose, Pose2, pose2};
use crate::hierarchy::HierarchicalFilter;
use crate::io::log2d::{LogFormat, LogReader2d, open_log2d, open_log2d_with};
use crate::io::map_image::{OccupancyRaster, write_map};
use crate::io::tum::write_tum;
use crate::laser_model::LaserModel;
use crate::motion_learning::{LearnOptions, MotionFit, MotionSample, fit_cdt};
use crate::motion_model::CdtModel;
use crate::scan::{Beam, LaserScan2d, Scan};
use crate::{Error, Result};
use serde::Serialize;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// Hard cap on the default usable range (m): traces cost time linear in range.
pub const DEFAULT_RANGE_CAP: f64 = 20.0;

/// The DP-SLAM release's laser mounting for its own log format (m ahead).
pub const DPSLAM_LASER_OFFSET: f64 = 0.40;

/// The laser's pose in the robot frame: the configured offset, else the log
/// format's default.
pub fn sensor_mount(cfg: &Config, format: LogFormat) -> Pose2 {
    match cfg.motion2d.sensor_offset {
        Some([x, y, th]) => pose2(x, y, th),
        None => match format {
            LogFormat::DpSlam => pose2(DPSLAM_LASER_OFFSET, 0.0, 0.0),
            LogFormat::Carmen | LogFormat::RosBag => Pose2::identity(),
        },
    }
}

/// [`sensor_mount`] for an open log: a ROS bag's laser mount from its
/// static transforms, unless the configuration sets one.
pub fn sensor_mount_of(cfg: &Config, reader: &LogReader2d) -> Pose2 {
    match (cfg.motion2d.sensor_offset, reader.format()) {
        (None, LogFormat::RosBag) => reader.sensor_offset().unwrap_or_else(Pose2::identity),
        _ => sensor_mount(cfg, reader.format()),
    }
}

/// The usable range (m) for a log whose sensor limit is `sensor_max`.
pub fn usable_range(cfg: &Config, sensor_max: f64) -> f64 {
    if cfg.laser.max_range > 0.0 {
        cfg.laser.max_range
    } else {
        sensor_max.min(DEFAULT_RANGE_CAP)
    }
}

/// A filter as `map2d` sets it up: particles at the origin, `first` in the map.
pub fn new_filter(
    cfg: &Config,
    laser: LaserModel,
    first: &Scan<2, Pose2>,
    index: u32,
) -> ParticleFilter<2, Pose2> {
    let motion = Box::new(CdtModel {
        cfg: cfg.motion2d.clone(),
    });
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
    filter
}

/// What a 2-D run did; written as `run.json`.
#[derive(Debug, Clone, Serialize, serde::Deserialize)]
pub struct Map2dSummary {
    /// dpslam version.
    pub version: String,
    /// Input log.
    pub input: PathBuf,
    /// Detected log format.
    pub format: String,
    /// Laser scans in the input (= lines of `trajectory.tum`).
    pub scans: usize,
    /// Scans the filter processed (the others moved too little).
    pub scans_processed: usize,
    /// Particles.
    pub particles: usize,
    /// Samples per particle.
    pub samples_per_particle: usize,
    /// Beams used per scan (after even thinning).
    pub beams_per_scan: usize,
    /// Usable laser range, m.
    pub max_range_m: f64,
    /// Time span of the log, s (`None` without time stamps).
    pub data_duration_s: Option<f64>,
    /// Wall-clock time of the run, s.
    pub wall_time_s: f64,
    /// Data duration / wall time (`None` without time stamps).
    pub real_time_factor: Option<f64>,
    /// Peak resident memory, MiB.
    pub peak_memory_mib: Option<f64>,
    /// Entries in the DP-map at the end.
    pub map_entries: usize,
    /// Approximate DP-map size, MiB.
    pub map_memory_mib: f64,
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
    /// Problems with the input worth a look (also printed on stderr).
    pub warnings: Vec<String>,
    /// Seed.
    pub seed: u64,
    /// Worker threads.
    pub threads: usize,
}

/// Converts one log scan to the filter's form: evenly thinned to at most
/// `max_beams` beams, readings beyond `max_range` (m), or none, as "no return".
///
/// Readings at or above the log's declared maximum (`s.max_range`) are "no
/// return" too, unless `max_range` is above that maximum: a configured
/// `laser.max_range` beyond the declared one says the header understates
/// the laser (edmonton's declares 10 m and holds returns to 50 m), and real
/// returns below it are kept.
pub fn to_scan(s: &LaserScan2d, sensor: Pose2, max_beams: usize, max_range: f64) -> Scan<2, Pose2> {
    let n = s.ranges.len();
    let stride = n.div_ceil(max_beams.max(1)).max(1);
    let trust_beyond_declared = max_range > s.max_range;
    let beams = (0..n)
        .step_by(stride)
        .map(|i| {
            let a = s.angle_min + i as f64 * s.angle_increment;
            let r = s.ranges[i];
            let kept = trust_beyond_declared && r.is_finite() && r > 0.0;
            let no_return = (s.is_no_return(i) && !kept) || r > max_range;
            Beam {
                dir: [a.cos(), a.sin()],
                range: if no_return { max_range } else { r },
                no_return,
            }
        })
        .collect();
    Scan { sensor, beams }
}

/// How a log's readings sit against its declared maximum range, from one
/// pass over the log before mapping (parsing is cheap next to SLAM).
///
/// Some logs declare a maximum below what their laser returns: edmonton's
/// header gives `robot_front_laser_max 10` (a navigation setting) while a
/// third of its readings are real returns between 10 and 51 m, with 51.15 m
/// marking "no return". Taking the declaration at its word drops those
/// returns and leaves open spaces featureless.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct RangeSurvey {
    /// Readings seen (every beam of every scan).
    pub readings: usize,
    /// Finite readings above 1.01 × the declared maximum and below 0.999 ×
    /// the largest reading: neither under the declaration nor saturated.
    pub between: usize,
    /// Largest finite reading, m.
    pub largest: f64,
    /// Largest declared maximum range, m.
    pub declared: f64,
}

impl RangeSurvey {
    /// Surveys every scan of `log`.
    pub fn of_log(log: &Path) -> Result<Self> {
        Self::of_scans(open_log2d(log)?)
    }

    /// Surveys `scans` (a log's, in any order).
    pub fn of_scans(scans: impl IntoIterator<Item = Result<LaserScan2d>>) -> Result<Self> {
        let mut survey = Self::default();
        // Readings above their scan's declaration, by millimetre: whether
        // each is saturated is known only once the largest reading is.
        let mut above: rustc_hash::FxHashMap<u64, usize> = Default::default();
        for item in scans {
            let s = item?;
            survey.readings += s.ranges.len();
            survey.declared = survey.declared.max(s.max_range);
            for &r in s.ranges.iter().filter(|r| r.is_finite()) {
                survey.largest = survey.largest.max(r);
                if r > s.max_range * 1.01 {
                    *above.entry((r * 1000.0) as u64).or_default() += 1;
                }
            }
        }
        let saturated = (survey.largest * 0.999 * 1000.0) as u64;
        survey.between = above
            .iter()
            .filter(|&(&mm, _)| mm < saturated)
            .map(|(_, &n)| n)
            .sum();
        Ok(survey)
    }

    /// What a run of `log` with the "no return" threshold `sensor_max` (from
    /// [`RangeSurvey::sensor_max`]) and the usable range `max_range` (m)
    /// should warn about.
    pub fn warnings(&self, log: &Path, sensor_max: Option<f64>, max_range: f64) -> Vec<String> {
        let share = 100.0 * self.between as f64 / self.readings.max(1) as f64;
        let (declared, largest) = (self.declared, self.largest);
        let mut out = Vec::new();
        if let Some(m) = sensor_max {
            out.push(format!(
                "{}: {share:.0} % of the laser readings lie between the log's declared maximum \
                 range of {declared} m and its largest reading, {m:.2} m: taken as returns, with \
                 {m:.2} m as \"no return\" (set laser.trust_declared_max_range = true to keep \
                 the declaration)",
                log.display(),
            ));
        } else if self.contradicts_declaration() && max_range <= declared {
            out.push(format!(
                "{}: {share:.0} % of the laser readings lie above the log's declared maximum \
                 range of {declared} m (up to {largest:.1} m) and were taken as \"no return\" \
                 (laser.trust_declared_max_range = true)",
                log.display(),
            ));
        }
        out
    }

    /// Whether ≥ 1 % of the readings contradict the declared maximum.
    pub fn contradicts_declaration(&self) -> bool {
        self.readings > 0 && self.between * 100 >= self.readings
    }

    /// The "no return" threshold to use, m: the largest reading where the
    /// declaration is contradicted (that value is the laser's saturation),
    /// else `None` (keep each scan's declared maximum).
    pub fn sensor_max(&self, trust_declared: bool) -> Option<f64> {
        (!trust_declared && self.contradicts_declaration()).then_some(self.largest)
    }
}

/// Map images show, per cell, the probability that a beam is stopped within
/// this many metres of travel through material of the cell's density. One
/// cell's width would render a wall seen a handful of times as light grey
/// (a fresh cell carries 4 cells of prior path); 10 cm makes such walls dark
/// while free space (density 0) stays white.
pub const DISPLAY_PATH: f64 = 0.10;

/// Renders the map as the particle at `index` sees it.
pub fn raster_of(filter: &ParticleFilter<2, Pose2>, index: usize) -> Result<OccupancyRaster> {
    raster_of_view(
        filter.map(),
        filter.numbering(),
        filter.particles()[index].node,
    )
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
    let mut cells = vec![None; width * height];
    let mut view = map.view(numbering, node);
    let c = map.cell_size();
    map.for_each_cell(|k, _| {
        if let Some((h, d)) = view.lookup(k) {
            let rho = if h > 0.0 { h as f64 / d as f64 } else { 0.0 };
            let i = (k[1] - lo[1]) as usize * width + (k[0] - lo[0]) as usize;
            cells[i] = Some((1.0 - (-rho * DISPLAY_PATH).exp()) as f32);
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

/// Runs 2-D DP-SLAM on `log` and writes the run folder `out`.
pub fn run_map2d(log: &Path, out: &Path, cfg: &Config) -> Result<Map2dSummary> {
    run_map2d_with(log, out, cfg, crate::backend::Backend::Cpu)
}

/// The filter of a 2-D run: DP-SLAM, or hierarchical DP-SLAM over it.
pub enum Slam2d {
    /// One particle filter over the whole log.
    Flat(Box<ParticleFilter<2, Pose2>>),
    /// Windows of the log under a high-level filter (`[hierarchy]`).
    Hierarchical(Box<HierarchicalFilter<2, Pose2>>),
}

impl Slam2d {
    fn step(&mut self, delta: &Pose2, scan: &Scan<2, Pose2>, index: u32) -> StepStats {
        match self {
            Slam2d::Flat(f) => f.step(delta, scan, index),
            Slam2d::Hierarchical(h) => h.step(delta, scan, index),
        }
    }

    /// The best trajectory: one stamp per processed scan, in order.
    pub fn best_trajectory(&self) -> Vec<Stamp<Pose2>> {
        match self {
            Slam2d::Flat(f) => f.best_trajectory(),
            Slam2d::Hierarchical(h) => h.best_trajectory(),
        }
    }

    /// The map of the whole run.
    pub fn map(&self) -> &DpMap<2> {
        match self {
            Slam2d::Flat(f) => f.map(),
            Slam2d::Hierarchical(h) => h.map(),
        }
    }

    /// The map as the best particle sees it.
    pub fn raster(&self) -> Result<OccupancyRaster> {
        match self {
            Slam2d::Flat(f) => raster_of(f, f.best_index()),
            Slam2d::Hierarchical(h) => raster_of_view(h.map(), h.numbering(), h.best_node()),
        }
    }

    /// Live ancestry nodes (the high level's, hierarchically).
    pub fn tree_nodes(&self) -> usize {
        match self {
            Slam2d::Flat(f) => f.tree().len(),
            Slam2d::Hierarchical(h) => h.tree_nodes(),
        }
    }

    /// The scan scorer (the low level's, hierarchically).
    pub fn scorer(&self) -> &dyn crate::scorer::Scorer<2, Pose2> {
        match self {
            Slam2d::Flat(f) => f.scorer(),
            Slam2d::Hierarchical(h) => h.low().scorer(),
        }
    }
}

/// A 2-D filter run over a whole log, before anything is written.
pub struct FilterRun2d {
    /// The filter after the last scan.
    pub filter: Slam2d,
    /// Per input scan: its time (s, or its index without time stamps) and
    /// odometry. Small, and needed for the skipped scans' poses; the maps
    /// themselves do not grow with the log.
    pub stamps: Vec<(f64, Pose2)>,
    /// What each filter step did.
    pub stats: Vec<StepStats>,
    /// Detected log format.
    pub format: LogFormat,
    /// Usable laser range, m.
    pub max_range: f64,
    /// Beams used per scan.
    pub beams_per_scan: usize,
    /// Time span of the log, s (`None` without time stamps).
    pub data_duration_s: Option<f64>,
    /// What the range survey found worth a warning.
    pub warnings: Vec<String>,
    /// Scan-likelihood backend used.
    pub backend: String,
}

/// Runs 2-D DP-SLAM over `log`, scoring scans on `backend` (see
/// [`crate::backend::make_scorer`]); writes nothing.
pub fn run_filter2d(
    log: &Path,
    cfg: &Config,
    backend: crate::backend::Backend,
) -> Result<FilterRun2d> {
    cfg.validate()?;
    let (scorer, backend_used) = crate::backend::make_scorer::<2, Pose2>(backend)?;
    let mut scorer = Some(scorer);
    let mut reader = open_log2d_with(log, &cfg.bag)?;
    let format = reader.format();
    let mount = sensor_mount_of(cfg, &reader);
    let bar = super::progress_bar(reader.total_bytes(), "map2d");
    let f = &cfg.filter;

    let mut stamps: Vec<(f64, Pose2)> = Vec::new();
    let mut filter: Option<Slam2d> = None;
    let mut last_processed: Option<(usize, Pose2)> = None;
    let mut stats: Vec<StepStats> = Vec::new();
    let mut max_range = 0.0;
    let mut beams_per_scan = 0;
    let mut first_time = None;
    let mut last_time = None;
    let survey = RangeSurvey::of_scans(open_log2d_with(log, &cfg.bag)?)?;
    let sensor_max = survey.sensor_max(cfg.laser.trust_declared_max_range);

    while let Some(item) = reader.next() {
        let mut s = item?;
        if let Some(m) = sensor_max {
            s.max_range = m;
        }
        let index = stamps.len();
        let t = s.timestamp.unwrap_or(index as f64);
        if s.timestamp.is_some() {
            first_time.get_or_insert(t);
            last_time = Some(t);
        }
        stamps.push((t, s.odometry));
        let sensor = mount;
        match (&mut filter, last_processed) {
            (None, _) => {
                max_range = usable_range(cfg, s.max_range);
                let scan = to_scan(&s, sensor, cfg.laser.max_beams, max_range);
                beams_per_scan = scan.beams.len();
                let laser = LaserModel::new(&cfg.laser, cfg.cell_size(), max_range);
                let mut filt = new_filter(cfg, laser, &scan, index as u32);
                if let Some(sc) = scorer.take() {
                    filt.set_scorer(sc);
                }
                filter = Some(if cfg.hierarchy.enabled {
                    let h = &cfg.hierarchy;
                    // A zero motion through the C/D/T model draws each
                    // axis from its floor: x, y ~ N(0, σ_xy), θ ~ N(0, σ_θ).
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
                    Slam2d::Hierarchical(Box::new(HierarchicalFilter::new(
                        filt,
                        cfg,
                        Box::new(perturb),
                        &scan,
                        index as u32,
                    )))
                } else {
                    Slam2d::Flat(Box::new(filt))
                });
                last_processed = Some((index, s.odometry));
            }
            (Some(filt), Some((_, odo0))) => {
                let delta = odo0.inverse() * s.odometry;
                if delta.translation.vector.norm() >= f.min_translation
                    || delta.rotation.angle().abs() >= f.min_rotation
                {
                    let scan = to_scan(&s, sensor, cfg.laser.max_beams, max_range);
                    stats.push(filt.step(&delta, &scan, index as u32));
                    last_processed = Some((index, s.odometry));
                }
            }
            (Some(_), None) => unreachable!("a filter exists only after the first scan"),
        }
        bar.set_position(reader.bytes_read());
    }
    bar.finish_and_clear();
    let mut filter = filter.ok_or_else(|| Error::in_file(log, "no laser scans"))?;
    if let Slam2d::Hierarchical(h) = &mut filter {
        h.finish();
    }
    let data_duration_s = match (first_time, last_time) {
        (Some(a), Some(b)) if b > a => Some(b - a),
        _ => None,
    };
    Ok(FilterRun2d {
        filter,
        stamps,
        stats,
        format,
        max_range,
        beams_per_scan,
        data_duration_s,
        warnings: survey.warnings(log, sensor_max, max_range),
        backend: backend_used,
    })
}

impl FilterRun2d {
    /// The trajectory, one `(time, TUM pose)` row per input scan: processed
    /// scans from the best particle, the others carried by odometry from the
    /// last processed one.
    pub fn trajectory(&self) -> Result<Vec<(f64, [f64; 7])>> {
        let corrected = self.filter.best_trajectory();
        let mut rows = Vec::with_capacity(self.stamps.len());
        let mut next = corrected.iter().peekable();
        // (corrected, odometry) of the last processed scan.
        let mut anchor: Option<(Pose2, Pose2)> = None;
        for (i, (t, odo)) in self.stamps.iter().enumerate() {
            let pose = match next.peek() {
                Some(st) if st.scan as usize == i => {
                    let p = st.pose;
                    next.next();
                    anchor = Some((p, *odo));
                    p
                }
                _ => {
                    let (p, o) = anchor.expect("the first scan is always processed");
                    p * (o.inverse() * odo)
                }
            };
            if !Pose::<2>::is_finite(&pose) {
                return Err(Error::Invalid(format!("non-finite pose at scan {i}")));
            }
            rows.push((*t, Pose::<2>::to_tum(&pose)));
        }
        Ok(rows)
    }

    /// Odometry and best-trajectory motion between consecutive processed
    /// scans, for learning the motion model ([`crate::motion_learning`]).
    pub fn motion_samples(&self) -> Vec<MotionSample> {
        self.filter
            .best_trajectory()
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

/// As [`run_map2d`], scoring scans on `backend` (see [`crate::backend::make_scorer`]).
pub fn run_map2d_with(
    log: &Path,
    out: &Path,
    cfg: &Config,
    backend: crate::backend::Backend,
) -> Result<Map2dSummary> {
    let start = Instant::now();
    let run = run_filter2d(log, cfg, backend)?;
    let rows = run.trajectory()?;
    let FilterRun2d {
        filter,
        stamps,
        stats,
        format,
        max_range,
        beams_per_scan,
        data_duration_s: duration,
        warnings,
        backend: backend_used,
    } = run;
    let f = &cfg.filter;

    if std::env::var_os("DPSLAM_DEBUG").is_some() {
        eprintln!("list lengths: {:?}", filter.map().list_length_histogram(64));
    }
    let raster = filter.raster()?;
    let wall = start.elapsed().as_secs_f64();
    let n_steps = stats.len().max(1) as f64;
    for w in &warnings {
        eprintln!("dpslam: warning: {w}");
    }
    let summary = Map2dSummary {
        version: env!("CARGO_PKG_VERSION").to_string(),
        input: log.to_path_buf(),
        format: format!("{format:?}"),
        scans: stamps.len(),
        scans_processed: stats.len() + 1,
        particles: f.particles,
        samples_per_particle: f.samples_per_particle,
        beams_per_scan,
        max_range_m: max_range,
        data_duration_s: duration,
        wall_time_s: wall,
        real_time_factor: duration.map(|d| d / wall),
        peak_memory_mib: super::peak_memory_mib(),
        map_entries: filter.map().entry_count(),
        map_memory_mib: filter.map().memory_bytes() as f64 / (1024.0 * 1024.0),
        tree_nodes: filter.tree_nodes(),
        mean_after_quick: stats.iter().map(|s| s.after_quick as f64).sum::<f64>() / n_steps,
        mean_after_full: stats.iter().map(|s| s.after_full as f64).sum::<f64>() / n_steps,
        backend: backend_used,
        gpu_transfers: filter.scorer().transfers(),
        warnings,
        seed: cfg.seed,
        threads: rayon::current_num_threads(),
    };

    super::create_out_dir(out)?;
    write_map(out, "map", &raster)?;
    write_tum(&out.join("trajectory.tum"), &rows)?;
    super::write_atomic(&out.join("config.toml"), cfg.to_toml().as_bytes())?;
    super::write_json(&out.join("run.json"), &summary)?;
    Ok(summary)
}

/// One EM round of motion learning ([`learn_motion2d`]).
#[derive(Debug, Clone, Serialize)]
pub struct LearnRound {
    /// Round number, from 1.
    pub round: usize,
    /// Wall-clock time of the round's SLAM run and fit, s.
    pub wall_time_s: f64,
    /// The model fitted in this round (used by the next).
    pub fit: MotionFit,
}

/// Learns the C/D/T motion model of `log` (dissertation ch. 6): `rounds`
/// rounds of a full SLAM run with the current model (E-step) and a fit of
/// the model to the best trajectory's motions (M-step, [`fit_cdt`]),
/// starting from `cfg.motion2d`, calling `on_round` after each. Returns
/// `cfg` with the learned model and the rounds; writes nothing.
pub fn learn_motion2d(
    log: &Path,
    cfg: &Config,
    backend: crate::backend::Backend,
    rounds: usize,
    mut on_round: impl FnMut(&LearnRound),
) -> Result<(Config, Vec<LearnRound>)> {
    let mut cfg = cfg.clone();
    let opts = LearnOptions::from_config(&cfg);
    let mut history = Vec::with_capacity(rounds);
    for round in 1..=rounds {
        let start = Instant::now();
        let run = run_filter2d(log, &cfg, backend)?;
        let fit = fit_cdt(&run.motion_samples(), &cfg.motion2d, &opts)?;
        cfg.motion2d = fit.model.clone();
        let r = LearnRound {
            round,
            wall_time_s: start.elapsed().as_secs_f64(),
            fit,
        };
        on_round(&r);
        history.push(r);
    }
    Ok((cfg, history))
}

/// [`learn_motion2d`], then [`run_map2d_with`] with the learned model: the
/// run folder's `config.toml` holds the learned model (so `--config` on it
/// reproduces the final run) and `motion_learning.json` the rounds.
pub fn run_map2d_learning(
    log: &Path,
    out: &Path,
    cfg: &Config,
    backend: crate::backend::Backend,
    rounds: usize,
    on_round: impl FnMut(&LearnRound),
) -> Result<(Map2dSummary, Vec<LearnRound>)> {
    let (learned, history) = learn_motion2d(log, cfg, backend, rounds, on_round)?;
    let summary = run_map2d_with(log, out, &learned, backend)?;
    super::write_json(&out.join("motion_learning.json"), &history)?;
    Ok((summary, history))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn scan(ranges: Vec<f64>, declared: f64) -> LaserScan2d {
        LaserScan2d {
            timestamp: None,
            odometry: Pose2::identity(),
            logged_pose: None,
            ranges,
            angle_min: 0.0,
            angle_increment: 0.01,
            max_range: declared,
            line: 1,
        }
    }

    fn flags(s: &Scan<2, Pose2>) -> Vec<(bool, f64)> {
        s.beams.iter().map(|b| (b.no_return, b.range)).collect()
    }

    #[test]
    fn a_configured_range_above_the_declared_maximum_keeps_real_returns() {
        let s = scan(vec![5.0, 15.0, 10.0, f64::NAN, 25.0], 10.0);
        // Default: the declared 10 m rules.
        let d = to_scan(&s, Pose2::identity(), 181, 10.0);
        assert_eq!(
            flags(&d),
            [
                (false, 5.0),
                (true, 10.0),
                (true, 10.0),
                (true, 10.0),
                (true, 10.0)
            ]
        );
        // laser.max_range = 20 above the declared 10 m: 15 m is a return.
        let c = to_scan(&s, Pose2::identity(), 181, 20.0);
        assert_eq!(
            flags(&c),
            [
                (false, 5.0),
                (false, 15.0),
                (false, 10.0),
                (true, 20.0),
                (true, 20.0)
            ]
        );
        // A usable range below the declared maximum changes nothing but the cut.
        let s = scan(vec![5.0, 15.0, 81.9], 81.9);
        let u = to_scan(&s, Pose2::identity(), 181, 20.0);
        assert_eq!(flags(&u), [(false, 5.0), (false, 15.0), (true, 20.0)]);
    }

    #[test]
    fn readings_between_the_declaration_and_saturation_overrule_it() {
        // Declared 10 m; returns at 15 and 30 m; 51.15 m is the saturation value.
        let scans = || {
            (0..10).map(|i| {
                Ok(scan(
                    vec![5.0, 15.0 + i as f64, 51.15, f64::NAN, 30.0, 51.15],
                    10.0,
                ))
            })
        };
        let survey = RangeSurvey::of_scans(scans()).unwrap();
        assert_eq!(survey.readings, 60);
        assert_eq!(survey.between, 20);
        assert_eq!(survey.largest, 51.15);
        assert!(survey.contradicts_declaration());
        assert_eq!(survey.sensor_max(false), Some(51.15));
        assert_eq!(survey.sensor_max(true), None);
        // With the saturation value as the limit, returns up to the usable
        // range are kept and the saturated readings mean "no return".
        let mut s = scan(vec![5.0, 15.0, 51.15, 30.0], 10.0);
        s.max_range = 51.15;
        let u = to_scan(&s, Pose2::identity(), 181, 20.0);
        assert_eq!(
            flags(&u),
            [(false, 5.0), (false, 15.0), (true, 20.0), (true, 20.0)]
        );

        // Only saturated readings above the declaration (csail-corrected:
        // declared 50 m, "no return" written as 81.91): nothing to overrule.
        let sat = (0..10).map(|_| Ok(scan(vec![5.0, 81.91, 81.91, 12.0], 50.0)));
        let survey = RangeSurvey::of_scans(sat).unwrap();
        assert_eq!(survey.between, 0);
        assert_eq!(survey.sensor_max(false), None);
        // Stray readings (< 1 %) above the declaration do not overrule it either.
        let mut few: Vec<Result<LaserScan2d>> =
            (0..200).map(|_| Ok(scan(vec![5.0; 10], 10.0))).collect();
        few.push(Ok(scan(vec![12.0, 30.0], 10.0)));
        let survey = RangeSurvey::of_scans(few).unwrap();
        assert_eq!(survey.between, 1);
        assert!(!survey.contradicts_declaration());
    }
}
