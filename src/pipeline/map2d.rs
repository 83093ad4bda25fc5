//! The 2-D mapping run: a CARMEN or DP-SLAM log in, a run folder out.
//!
//! A thin loop over [`Slam2d`]: survey the log's ranges, feed every scan,
//! write the map, `trajectory.tum`, `config.toml` and `run.json`.

use crate::config::Config;
use crate::geometry::{Pose, Pose2, pose2};
use crate::io::log2d::{LogFormat, LogReader2d, open_log2d_with};
use crate::io::map_image::write_map;
use crate::io::tum::write_tum;
use crate::scan::LaserScan2d;
use crate::slam::Slam2d;
use crate::slam::slam2d::{DEFAULT_RANGE_CAP, RANGE_SHARE, usable_range};
use crate::{Error, Result};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use std::time::Instant;

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

/// What a 2-D run did; written as `run.json`.
#[derive(Debug, Clone, Serialize, serde::Deserialize)]
pub struct Map2dSummary {
    /// dpslam version.
    pub version: String,
    /// Input log.
    pub input: PathBuf,
    /// Detected log format.
    pub format: String,
    /// The scans' odometry was re-timed from the CARMEN log's ODOM stream
    /// (`input.odometry`; [`crate::io::log2d`]).
    #[serde(default)]
    pub odometry_retimed: bool,
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
    /// Mean number of samples drawn per step.
    #[serde(default)]
    pub mean_samples: f64,
    /// Mean number of particles per step whose samples came from a scan
    /// match (`filter.proposal = "scan-matched"`).
    #[serde(default)]
    pub mean_matched: f64,
    /// Steps whose particle set was drawn anew from all samples (all of
    /// them unless `filter.resample_below` < 1).
    #[serde(default)]
    pub resampled_steps: usize,
    /// Wall time of each phase of the filter steps, summed over the run, s.
    #[serde(default, skip_deserializing)]
    pub phases: crate::filter::PhaseTimes,
    /// Scan-likelihood backend used: "cpu", or "gpu", its precision and
    /// adapter, or "cpu (auto: why no GPU)".
    pub backend: String,
    /// The GPU backend's traffic (map bytes uploaded against re-uploading
    /// the whole map at every step); absent on the CPU.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub gpu_transfers: Option<crate::scorer::Transfers>,
    /// Problems with the input or the backend worth a look (the CLI prints
    /// them on stderr).
    pub warnings: Vec<String>,
    /// Seed.
    pub seed: u64,
    /// Worker threads.
    pub threads: usize,
    /// What the final alignment against the run's own map did (`refine`;
    /// absent with `refine.passes = 0`). `trajectory.tum` then holds the
    /// refined poses and `trajectory_filter.tum` the filter's own.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub refine: Option<RefineSummary>,
}

/// What [`refine_trajectory2d`] did, for `run.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RefineSummary {
    /// Passes run (`refine.passes`).
    pub passes: usize,
    /// Median of how far a scan moved, m.
    pub moved_median_m: f64,
    /// Largest move of a scan, m.
    pub moved_max_m: f64,
    /// Median heading change of a scan, degrees.
    pub turned_median_deg: f64,
    /// Wall time of the refinement, s (part of `wall_time_s`).
    pub time_s: f64,
}

/// How a log's readings sit against its declared maximum range, from one
/// pass over the log before mapping (parsing is cheap next to SLAM).
///
/// Some logs declare a maximum below what their laser returns: edmonton's
/// header gives `robot_front_laser_max 10` (a navigation setting) while a
/// third of its readings are real returns between 10 and 51 m, with 51.15 m
/// marking "no return". Taking the declaration at its word drops those
/// returns and leaves open spaces featureless.
#[derive(Debug, Clone, Copy, PartialEq)]
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
    /// Finite positive readings per [`RangeSurvey::BIN`]-metre bin of range
    /// (the last bin holds everything from 99.5 m on), for
    /// [`RangeSurvey::covering`].
    pub bins: [usize; RangeSurvey::BINS],
}

impl Default for RangeSurvey {
    fn default() -> Self {
        Self {
            readings: 0,
            between: 0,
            largest: 0.0,
            declared: 0.0,
            bins: [0; Self::BINS],
        }
    }
}

impl RangeSurvey {
    /// Width of a bin of [`RangeSurvey::bins`], m.
    pub const BIN: f64 = 0.5;
    /// Bins of [`RangeSurvey::bins`]: 0.5 m up to 100 m.
    pub const BINS: usize = 200;

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
                if r > 0.0 {
                    let bin = ((r / Self::BIN) as usize).min(Self::BINS - 1);
                    survey.bins[bin] += 1;
                }
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
        if let Some(r) = self.default_range().filter(|&r| r == max_range) {
            out.push(format!(
                "{}: more than a tenth of the laser returns lie beyond {DEFAULT_RANGE_CAP} m: \
                 usable range {r} m, within which {:.0} % lie (traces cost time and memory \
                 linear in range; laser.max_range sets it)",
                log.display(),
                100.0 * RANGE_SHARE,
            ));
        }
        out
    }

    /// The range (m, a bin's upper edge) within which `share` (0..1) of the
    /// log's returns lie: finite positive readings below its saturation
    /// value (0.999 × the largest, where a laser writes "no return");
    /// `None` without returns.
    pub fn covering(&self, share: f64) -> Option<f64> {
        // The last bin also holds saturation values beyond 100 m: never returns.
        let saturated = ((self.largest * 0.999 / Self::BIN) as usize).min(Self::BINS - 1);
        let returns = &self.bins[..saturated];
        let total: usize = returns.iter().sum();
        if total == 0 {
            return None;
        }
        let want = (share.clamp(0.0, 1.0) * total as f64).ceil() as usize;
        let mut seen = 0;
        for (i, &n) in returns.iter().enumerate() {
            seen += n;
            if seen >= want {
                return Some((i + 1) as f64 * Self::BIN);
            }
        }
        Some(saturated as f64 * Self::BIN)
    }

    /// The default usable range for this log, m: the range covering
    /// [`RANGE_SHARE`] of its returns where that is beyond
    /// [`DEFAULT_RANGE_CAP`] (outdoors, where most of what the laser sees
    /// is far), else `None` (the cap).
    pub fn default_range(&self) -> Option<f64> {
        self.covering(RANGE_SHARE)
            .filter(|&r| r > DEFAULT_RANGE_CAP)
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

/// What a log's range survey sets for a 2-D run of it under a
/// configuration, decided before the run starts: the "no return" threshold
/// and the default usable range. Every consumer of a log's scans (the
/// pipeline, the benches) takes them from here.
#[derive(Debug, Clone, PartialEq)]
pub struct RangeSettings {
    /// The survey they come from.
    pub survey: RangeSurvey,
    /// Readings at or above this (m) mean "no return", whatever each
    /// reading declares (`None`: the declaration holds).
    pub no_return_at: Option<f64>,
    /// Cap on the usable range where `laser.max_range` is 0, m (`None`:
    /// [`DEFAULT_RANGE_CAP`]).
    pub default_range: Option<f64>,
}

impl RangeSettings {
    /// Surveys every scan of `log` (the `cfg.bag` topics of a bag) and
    /// decides under `cfg`.
    pub fn of_log(log: &Path, cfg: &Config) -> Result<Self> {
        let survey = RangeSurvey::of_scans(open_log2d_with(log, &cfg.bag)?)?;
        Ok(Self::of_survey(survey, cfg))
    }

    /// What `survey` sets under `cfg`.
    pub fn of_survey(survey: RangeSurvey, cfg: &Config) -> Self {
        Self {
            no_return_at: survey.sensor_max(cfg.laser.trust_declared_max_range),
            default_range: survey.default_range(),
            survey,
        }
    }

    /// Sets them on `slam`, before its first scan.
    pub fn apply(&self, slam: &mut Slam2d) {
        slam.set_no_return_range(self.no_return_at);
        slam.set_default_range(self.default_range);
    }

    /// The usable range (m) of a run under `cfg` whose first reading
    /// declares `declared` m ([`usable_range`]).
    pub fn usable_range(&self, cfg: &Config, declared: f64) -> f64 {
        usable_range(
            cfg,
            self.no_return_at.unwrap_or(declared),
            self.default_range.unwrap_or(DEFAULT_RANGE_CAP),
        )
    }

    /// What a run of `log` under `cfg` should warn about, known before it
    /// starts ([`RangeSurvey::warnings`], for the range the run will take
    /// if its readings declare the survey's largest maximum).
    pub fn warnings(&self, log: &Path, cfg: &Config) -> Vec<String> {
        let max_range = self.usable_range(cfg, self.survey.declared);
        self.survey.warnings(log, self.no_return_at, max_range)
    }
}

/// Re-aligns `poses` (the filter's trajectory of `log`, one per scan, robot
/// poses in the map frame) against the map of all of the log's scans at
/// those poses ([`crate::refine`], `cfg.refine`), reading the log again
/// once per map and once per alignment of each pass. The scans are read as
/// the run read them: the same reader settings, laser mount, "no return"
/// threshold (`ranges`) and usable range `max_range` (m), every return kept
/// (no thinning).
pub fn refine_trajectory2d(
    log: &Path,
    cfg: &Config,
    ranges: &RangeSettings,
    max_range: f64,
    poses: &[Pose2],
) -> Result<crate::refine::Refined> {
    let no_return_at = ranges.no_return_at;
    let open = || -> Result<_> {
        let reader = open_configured(log, cfg)?;
        let mount = sensor_mount_of(cfg, &reader);
        Ok(reader.map(move |item| {
            let s = item?;
            let reading = s.as_ranges().with_no_return_at(no_return_at);
            let scan = crate::slam::slam2d::to_scan(
                &reading,
                mount,
                usize::MAX,
                max_range,
                cfg.laser.no_return,
            );
            Ok(scan.returns_in_robot_frame())
        }))
    };
    crate::refine::refine_poses(&cfg.refine, poses, open)
}

/// Runs 2-D DP-SLAM on `log` and writes the run folder `out`.
pub fn run_map2d(log: &Path, out: &Path, cfg: &Config) -> Result<Map2dSummary> {
    run_map2d_with(log, out, cfg, crate::backend::Backend::Cpu)
}

/// A 2-D run over a whole log, before anything is written.
pub struct FilterRun2d {
    /// The SLAM state after the last scan.
    pub slam: Slam2d,
    /// Detected log format.
    pub format: LogFormat,
    /// The scans' odometry was re-timed from the log's ODOM stream.
    pub odometry_retimed: bool,
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
    let ranges = RangeSettings::of_log(log, cfg)?;
    run_filter2d_observed(log, cfg, backend, &ranges, &mut super::no_progress)
}

/// Opens `log` as `map2d` reads it under `cfg`: the bag topics
/// (`cfg.bag`), the odometry pairing (`cfg.input.odometry`) and the beam
/// angle overrides (`cfg.laser`) applied by the reader, so every consumer
/// of the scans sees the same ones.
pub fn open_configured(log: &Path, cfg: &Config) -> Result<LogReader2d> {
    let (angle_min, angle_increment) = cfg.laser.beam_angle_overrides();
    Ok(open_log2d_with(log, &cfg.bag)?
        .with_odometry(cfg.input.odometry)
        .with_beam_angles(angle_min, angle_increment))
}

/// [`run_filter2d`] with the range settings `ranges` (the survey of `log`
/// under `cfg`, [`RangeSettings::of_log`]), reporting progress in bytes of
/// the log read.
pub fn run_filter2d_observed(
    log: &Path,
    cfg: &Config,
    backend: crate::backend::Backend,
    ranges: &RangeSettings,
    progress: super::Progress<'_>,
) -> Result<FilterRun2d> {
    let mut slam = Slam2d::new(cfg.clone())?;
    let (scorer, backend_used) = crate::backend::make_scorer::<2, Pose2>(backend, &cfg.gpu)?;
    slam.set_scorer(scorer)?;
    ranges.apply(&mut slam);
    let mut reader = open_configured(log, cfg)?;
    let format = reader.format();
    slam.set_mount(sensor_mount_of(cfg, &reader));
    let total = reader.total_bytes();
    let (mut first_time, mut last_time) = (None, None);
    while let Some(item) = reader.next() {
        let s: LaserScan2d = item?;
        let t = s.timestamp.unwrap_or(slam.scans() as f64);
        if s.timestamp.is_some() {
            first_time.get_or_insert(t);
            last_time = Some(t);
        }
        slam.add_scan(t, s.odometry, &s.as_ranges())
            .map_err(|e| Error::in_file(log, format!("line {}: {e}", s.line)))?;
        progress(reader.bytes_read(), total);
    }
    if slam.scans() == 0 {
        return Err(Error::in_file(log, "no laser scans"));
    }
    slam.finish();
    let data_duration_s = match (first_time, last_time) {
        (Some(a), Some(b)) if b > a => Some(b - a),
        _ => None,
    };
    Ok(FilterRun2d {
        warnings: ranges
            .survey
            .warnings(log, ranges.no_return_at, slam.max_range()),
        slam,
        format,
        odometry_retimed: reader.retimed(),
        data_duration_s,
        backend: backend_used,
    })
}

/// As [`run_map2d`], scoring scans on `backend` (see [`crate::backend::make_scorer`]).
pub fn run_map2d_with(
    log: &Path,
    out: &Path,
    cfg: &Config,
    backend: crate::backend::Backend,
) -> Result<Map2dSummary> {
    let ranges = RangeSettings::of_log(log, cfg)?;
    run_map2d_observed(log, out, cfg, backend, &ranges, &mut super::no_progress)
}

/// [`run_map2d_with`] with the range settings `ranges` (the survey of `log`
/// under `cfg`, [`RangeSettings::of_log`]), reporting progress in bytes of
/// the log read.
pub fn run_map2d_observed(
    log: &Path,
    out: &Path,
    cfg: &Config,
    backend: crate::backend::Backend,
    ranges: &RangeSettings,
    progress: super::Progress<'_>,
) -> Result<Map2dSummary> {
    let start = Instant::now();
    let run = run_filter2d_observed(log, cfg, backend, ranges, progress)?;
    let trajectory = run.slam.trajectory()?;
    let tum = |rows: &[(f64, Pose2)]| -> Vec<(f64, [f64; 7])> {
        rows.iter()
            .map(|(t, p)| (*t, Pose::<2>::to_tum(p)))
            .collect()
    };
    // The refined rows and what the refinement did, where it runs.
    let (refined_rows, refine) = if cfg.refine.passes > 0 {
        let began = Instant::now();
        let poses: Vec<Pose2> = trajectory.iter().map(|r| r.1).collect();
        let refined = refine_trajectory2d(log, cfg, ranges, run.slam.max_range(), &poses)?;
        let rows: Vec<(f64, Pose2)> = trajectory
            .iter()
            .zip(&refined.poses)
            .map(|(r, p)| (r.0, *p))
            .collect();
        let summary = RefineSummary {
            passes: cfg.refine.passes,
            moved_median_m: refined.moved_median_m,
            moved_max_m: refined.moved_max_m,
            turned_median_deg: refined.turned_median_rad.to_degrees(),
            time_s: began.elapsed().as_secs_f64(),
        };
        (Some(tum(&rows)), Some(summary))
    } else {
        (None, None)
    };
    let FilterRun2d {
        slam,
        format,
        odometry_retimed,
        data_duration_s: duration,
        mut warnings,
        backend: backend_used,
    } = run;
    let f = &cfg.filter;
    let map = slam.map().expect("a run has at least one scan");
    let raster = slam.raster()?;
    let wall = start.elapsed().as_secs_f64();
    let stats = slam.stats();
    let n_steps = stats.len().max(1) as f64;
    warnings.extend(slam.scorer().map(|s| s.warnings()).unwrap_or_default());
    let summary = Map2dSummary {
        version: env!("CARGO_PKG_VERSION").to_string(),
        input: log.to_path_buf(),
        format: format!("{format:?}"),
        odometry_retimed,
        scans: slam.scans(),
        scans_processed: stats.len() + 1,
        particles: f.particles,
        samples_per_particle: f.samples_per_particle,
        beams_per_scan: slam.beams_per_scan(),
        max_range_m: slam.max_range(),
        data_duration_s: duration,
        wall_time_s: wall,
        real_time_factor: duration.map(|d| d / wall),
        peak_memory_mib: super::peak_memory_mib(),
        map_entries: map.entry_count(),
        map_memory_mib: map.memory_bytes() as f64 / (1024.0 * 1024.0),
        tree_nodes: slam.tree_nodes(),
        mean_after_quick: stats.iter().map(|s| s.after_quick as f64).sum::<f64>() / n_steps,
        mean_after_full: stats.iter().map(|s| s.after_full as f64).sum::<f64>() / n_steps,
        mean_samples: stats.iter().map(|s| s.samples as f64).sum::<f64>() / n_steps,
        mean_matched: stats.iter().map(|s| s.matched as f64).sum::<f64>() / n_steps,
        resampled_steps: stats.iter().filter(|s| s.resampled).count(),
        phases: stats.iter().fold(Default::default(), |mut a, s| {
            a += s.times;
            a
        }),
        backend: backend_used,
        gpu_transfers: slam.scorer().and_then(|s| s.transfers()),
        warnings,
        seed: cfg.seed,
        threads: rayon::current_num_threads(),
        refine,
    };

    super::create_out_dir(out)?;
    write_map(out, "map", &raster)?;
    let filter_rows = tum(&trajectory);
    let filter_path = out.join("trajectory_filter.tum");
    match &refined_rows {
        Some(rows) => {
            write_tum(&out.join("trajectory.tum"), rows)?;
            write_tum(&filter_path, &filter_rows)?;
        }
        None => {
            write_tum(&out.join("trajectory.tum"), &filter_rows)?;
            // A run folder reused from a refined run must not keep a stale one.
            if filter_path.exists() {
                std::fs::remove_file(&filter_path).map_err(|e| Error::io(&filter_path, e))?;
            }
        }
    }
    super::write_atomic(&out.join("config.toml"), cfg.to_toml().as_bytes())?;
    super::write_json(&out.join("run.json"), &summary)?;
    Ok(summary)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::NoReturn;
    use crate::scan::Scan;
    use crate::slam::slam2d::to_scan;

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
        let d = to_scan(&s.as_ranges(), Pose2::identity(), 181, 10.0, NoReturn::Free);
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
        let c = to_scan(&s.as_ranges(), Pose2::identity(), 181, 20.0, NoReturn::Free);
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
        let u = to_scan(&s.as_ranges(), Pose2::identity(), 181, 20.0, NoReturn::Free);
        assert_eq!(flags(&u), [(false, 5.0), (false, 15.0), (true, 20.0)]);
    }

    #[test]
    fn skipped_no_returns_leave_the_scan_and_returns_beyond_the_usable_range_stay() {
        // The sensor's own "no return": NaN, ±inf, ≤ 0 and its 81.91 code.
        let s = scan(
            vec![5.0, f64::NAN, 81.91, 30.0, 0.0, f64::INFINITY, 7.0],
            81.91,
        );
        let free = to_scan(&s.as_ranges(), Pose2::identity(), 181, 20.0, NoReturn::Free);
        assert_eq!(free.beams.len(), 7);
        let skip = to_scan(&s.as_ranges(), Pose2::identity(), 181, 20.0, NoReturn::Skip);
        // The 30 m return lies beyond the usable 20 m: free space to there,
        // whatever `no_return` says.
        assert_eq!(flags(&skip), [(false, 5.0), (true, 20.0), (false, 7.0)]);
        // The kept beams keep their directions.
        let angle = |b: &crate::scan::Beam<2>| b.dir[1].atan2(b.dir[0]);
        let kept: Vec<f64> = skip.beams.iter().map(angle).collect();
        let all: Vec<f64> = free.beams.iter().map(angle).collect();
        assert_eq!(kept, [all[0], all[3], all[6]]);
        // `auto` skips where the laser reaches beyond the usable range
        // (81.91 m against 20 m) ...
        let auto = to_scan(&s.as_ranges(), Pose2::identity(), 181, 20.0, NoReturn::Auto);
        assert_eq!(flags(&auto), flags(&skip));
        // ... and keeps "nothing within reach" where it does not (8 m).
        let short = scan(vec![5.0, f64::NAN, 8.0, 7.0], 8.0);
        let auto = to_scan(
            &short.as_ranges(),
            Pose2::identity(),
            181,
            8.0,
            NoReturn::Auto,
        );
        assert_eq!(
            flags(&auto),
            [(false, 5.0), (true, 8.0), (true, 8.0), (false, 7.0)]
        );
        // A reading of nothing but "no return" leaves no beam at all.
        let none = scan(vec![f64::NAN, 81.91], 81.91);
        let skip = to_scan(
            &none.as_ranges(),
            Pose2::identity(),
            181,
            20.0,
            NoReturn::Skip,
        );
        assert!(skip.beams.is_empty());
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
        let u = to_scan(&s.as_ranges(), Pose2::identity(), 181, 20.0, NoReturn::Free);
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

    #[test]
    fn the_default_range_covers_nine_tenths_of_the_returns_outdoors_only() {
        // Indoors: every return within 8 m, "no return" written as 81.91.
        let indoor = (0..10).map(|_| Ok(scan(vec![2.0, 5.0, 7.9, 81.91, f64::NAN], 81.91)));
        let survey = RangeSurvey::of_scans(indoor).unwrap();
        assert_eq!(survey.covering(1.0), Some(8.0));
        assert_eq!(survey.covering(0.5), Some(5.5));
        assert_eq!(survey.default_range(), None);
        // Outdoors: 6 of 10 returns within 20 m, 9 of 10 within 35 m; the
        // saturated 81.91 m readings are not returns.
        let ranges = vec![
            3.0, 8.0, 12.0, 15.0, 18.0, 19.0, 26.0, 31.0, 34.9, 60.0, 81.91,
        ];
        let outdoor = (0..10).map(|_| Ok(scan(ranges.clone(), 81.91)));
        let survey = RangeSurvey::of_scans(outdoor).unwrap();
        assert_eq!(survey.default_range(), Some(35.0));
        let said = survey.warnings(Path::new("campus.log"), None, 35.0);
        assert!(said[0].contains("usable range 35 m"), "{said:?}");
        assert!(
            survey
                .warnings(Path::new("campus.log"), None, 20.0)
                .is_empty()
        );
        assert_eq!(survey.covering(1.0), Some(60.5));
        // A laser writing 150 m for "no return": those are not returns either.
        let far = (0..10).map(|_| Ok(scan(vec![5.0, 150.0, 150.0], 150.0)));
        assert_eq!(RangeSurvey::of_scans(far).unwrap().covering(1.0), Some(5.5));
        // No returns at all: nothing to cover.
        let none = (0..3).map(|_| Ok(scan(vec![f64::NAN, 81.91], 81.91)));
        assert_eq!(RangeSurvey::of_scans(none).unwrap().covering(0.9), None);
    }

    #[test]
    fn range_settings_say_before_the_run_what_the_run_will_take() {
        let cfg = Config::default();
        // Declared 10 m, returns to 30 m (1 in 12 beyond 20 m), 51.15 m
        // saturated: the saturation value becomes "no return" and the
        // usable range the 20 m cap.
        let readings = [vec![5.0; 6], vec![15.0; 5], vec![30.0, 51.15]].concat();
        let edmonton = (0..10).map(|_| Ok(scan(readings.clone(), 10.0)));
        let r = RangeSettings::of_survey(RangeSurvey::of_scans(edmonton).unwrap(), &cfg);
        assert_eq!(r.no_return_at, Some(51.15));
        let s = scan(vec![5.0, 15.0], 10.0);
        assert_eq!(
            s.as_ranges().with_no_return_at(r.no_return_at).max_range,
            51.15
        );
        assert_eq!(r.usable_range(&cfg, 10.0), 20.0);
        let said = r.warnings(Path::new("e.log"), &cfg);
        assert_eq!(said.len(), 1);
        assert!(said[0].contains("51.15 m as \"no return\""), "{said:?}");
        // The same as the run says once it knows its range.
        assert_eq!(
            said,
            r.survey.warnings(Path::new("e.log"), r.no_return_at, 20.0)
        );
        // Outdoors: the range covering 9 in 10 returns, unless set.
        let ranges = vec![
            3.0, 8.0, 12.0, 15.0, 18.0, 19.0, 26.0, 31.0, 34.9, 60.0, 81.91,
        ];
        let campus = (0..10).map(|_| Ok(scan(ranges.clone(), 81.91)));
        let r = RangeSettings::of_survey(RangeSurvey::of_scans(campus).unwrap(), &cfg);
        assert_eq!((r.no_return_at, r.default_range), (None, Some(35.0)));
        assert_eq!(r.usable_range(&cfg, 81.91), 35.0);
        assert_eq!(r.warnings(Path::new("c.log"), &cfg).len(), 1);
        let mut set = cfg.clone();
        set.laser.max_range = 25.0;
        assert_eq!(r.usable_range(&set, 81.91), 25.0);
        assert!(r.warnings(Path::new("c.log"), &set).is_empty());
    }
}
