//! The accuracy benchmark: `map2d` on every dataset with a reference, scored
//! against it, written up as `docs/RESULTS.md`.
//!
//! Datasets (read in place from the shared datasets folder):
//! - **sim2d**: the simulator's loop shipped in `data/sim2d/` with its truth.
//! - **mit-csail**, **aces-raw**, **fr079-raw**: raw-odometry logs with the
//!   Kümmerle et al. 2009 relations, beside that paper's published scan
//!   matching / RBPF (GMapping, 50 particles) / graph mapping figures
//!   ([`PUBLISHED`](super::report::PUBLISHED)); fr079-raw's laser is 0.04 m behind its odometry
//!   (`[motion2d] sensor_offset = [-0.04, 0, 0]`, its dataset README).
//! - **perturbed corrected logs** (fr079, aces and the others): the corrected
//!   poses are the truth; the odometry is the truth corrupted by
//!   [`dpslam::sim::perturb::perturb_log`] with the seed and noise model of
//!   [`AccuracyOptions`], written into the run folder (same seed, same files).
//!
//! Truth is paired with the estimate by time stamp when the log's stamps are
//! strictly increasing, else by scan index (both files hold one pose per input
//! scan, in input order); such logs also have no usable data duration.

use super::plot::{PALETTE, Plot, Series};
use super::report::{AccuracyReport, Matching, RunResult, Skipped, results_markdown};
use super::scaling::{ScalingOptions, ScalingReport, run_scaling, write_scaling_plot};
use dpslam::config::Config;
use dpslam::eval::ate::{AteOptions, align_se2, associate, evaluate_ate};
use dpslam::eval::relations::{
    RELATION_TIME_TOLERANCE_S, Relation, evaluate_relations, read_relations,
};
use dpslam::geometry::xyt;
use dpslam::io::log2d::open_log2d;
use dpslam::io::tum::{Stamped, read_tum};
use dpslam::pipeline::learn_motion::run_map2d_learning;
use dpslam::pipeline::map2d::RangeSettings;
use dpslam::pipeline::map2d::run_map2d;
use dpslam::sim::perturb::{NoiseModel, perturb_log};
use dpslam::{Error, Result};
use nalgebra::{Isometry3, Point3, Vector3};
use std::io::{BufRead, BufReader, Read, Write};
use std::path::{Path, PathBuf};
use std::time::Instant;

/// Seed of the odometry noise of the perturbed logs, unless overridden.
pub const DEFAULT_NOISE_SEED: u64 = 2009;

/// Scans of each log kept by `--quick`.
pub const QUICK_SCANS: usize = 300;

/// Longest side of the map images copied into the docs, pixels.
const DOC_MAP_SIDE: u32 = 800;

/// Corrected logs whose time stamps cannot order the scans, and why: their
/// truth is matched by scan index and their data duration is unknown.
const BAD_TIMESTAMPS: [(&str, &str); 2] = [
    (
        "infinite-corridor",
        "time stamps are garbage (negative, not increasing)",
    ),
    (
        "csail-corrected",
        "time stamps printed with 6 significant digits (1.13486e+09)",
    ),
];

/// fr079-raw's laser pose in the robot frame: 0.04 m behind the odometry's
/// reference point (the log's own laser offset is 0).
pub const FR079_SENSOR_OFFSET: [f64; 3] = [-0.04, 0.0, 0.0];

/// Where the reference comes from.
#[derive(Debug, Clone, PartialEq)]
pub enum Source {
    /// A raw log, scored with a relations file.
    Raw {
        /// The log.
        log: PathBuf,
        /// Its relations file.
        relations: PathBuf,
    },
    /// A corrected log: perturbed into noisy odometry plus truth.
    Corrected {
        /// The corrected log.
        log: PathBuf,
    },
    /// A simulated log with its truth trajectory.
    Simulated {
        /// The log.
        log: PathBuf,
        /// Truth, TUM.
        truth: PathBuf,
    },
}

/// One benchmark dataset.
#[derive(Debug, Clone, PartialEq)]
pub struct Dataset {
    /// Name: table row and run folder.
    pub name: String,
    /// The input and its reference.
    pub source: Source,
    /// Keep only this many scans (`--quick`).
    pub max_scans: Option<usize>,
    /// Laser pose in the robot frame for this log (`[motion2d]
    /// sensor_offset`), where the log's own is wrong; `None`: the config's.
    pub sensor_offset: Option<[f64; 3]>,
}

impl Dataset {
    /// The mapping configuration of this dataset: `cfg` with its overrides.
    pub fn config(&self, cfg: &Config) -> Config {
        let mut cfg = cfg.clone();
        if let Some(o) = self.sensor_offset {
            cfg.motion2d.sensor_offset = Some(o);
        }
        cfg
    }
}

/// Settings of [`run_accuracy`].
#[derive(Debug, Clone)]
pub struct AccuracyOptions {
    /// Short subset (simulator and the first scans of the raw logs).
    pub quick: bool,
    /// Run folders go here.
    pub out: PathBuf,
    /// `RESULTS.md` goes here, its images into `results/` below it.
    pub docs: PathBuf,
    /// The shared datasets folder (holds `carmen/`).
    pub datasets: PathBuf,
    /// The simulator's log and truth (`sim2d.clf`, `truth.tum`).
    pub sim_dir: PathBuf,
    /// Only these datasets (all when empty).
    pub only: Vec<String>,
    /// Mapping configuration (particles included).
    pub cfg: Config,
    /// Seed of the odometry noise of the perturbed logs.
    pub noise_seed: u64,
    /// Odometry noise of the perturbed logs.
    pub noise: NoiseModel,
    /// Command line, for the report.
    pub command: String,
    /// The particle-scaling measurement to run after the datasets (its table
    /// and plot go into the report); `None` skips it, and `quick` never runs it.
    pub scaling: Option<ScalingOptions>,
    /// A `dpslam` executable to run each dataset's `map2d` in a process of
    /// its own, so that its peak memory is its own (the allocator of one
    /// process keeps memory from the runs before); `None`: in this process.
    pub mapper: Option<PathBuf>,
    /// Rounds of motion-model learning before each dataset's final run
    /// (`map2d --learn-motion N`, dissertation ch. 6); 0 maps with the
    /// configured model. The wall time then covers the rounds as well.
    pub learn_motion: usize,
    /// Reuse a dataset's earlier `map2d` run in `out` when it was made with
    /// the same settings ([`run_settings`]): rescore and redraw only. The
    /// settings do not include the code, so clear `out` after changing it.
    /// Not with `learn_motion` (the learning rounds' time is not recorded).
    pub reuse_runs: bool,
}

impl AccuracyOptions {
    /// Defaults: out `target/bench-accuracy`, docs `docs`, datasets
    /// `../shared/datasets`, all relative to the repository root.
    pub fn new(cfg: Config) -> Self {
        let root = Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/.."));
        let scaling_cfg = cfg.clone();
        Self {
            quick: false,
            out: root.join("target/bench-accuracy"),
            docs: root.join("docs"),
            datasets: root.join("../shared/datasets"),
            sim_dir: root.join("data/sim2d"),
            only: Vec::new(),
            cfg,
            noise_seed: DEFAULT_NOISE_SEED,
            noise: NoiseModel::default(),
            command: String::new(),
            mapper: None,
            learn_motion: 0,
            reuse_runs: false,
            scaling: Some(ScalingOptions {
                log: root.join("data/sim2d/sim2d.clf"),
                particles: vec![100, 300, 1000, 3000],
                warmup_scans: 20,
                timed_steps: 10,
                cfg: scaling_cfg,
            }),
        }
    }
}

/// The datasets to run, and those that cannot be (missing files).
pub fn plan(opts: &AccuracyOptions) -> (Vec<Dataset>, Vec<Skipped>) {
    let carmen = opts.datasets.join("carmen");
    let quick = opts.quick.then_some(QUICK_SCANS);
    let mut all = vec![
        Dataset {
            name: "sim2d".into(),
            source: Source::Simulated {
                log: opts.sim_dir.join("sim2d.clf"),
                truth: opts.sim_dir.join("truth.tum"),
            },
            max_scans: quick,
            sensor_offset: None,
        },
        Dataset {
            name: "mit-csail".into(),
            source: Source::Raw {
                log: carmen.join("mit-csail/mit-csail.clf"),
                relations: carmen.join("mit-csail/mit-csail.relations"),
            },
            max_scans: quick,
            sensor_offset: None,
        },
        Dataset {
            name: "aces-raw".into(),
            source: Source::Raw {
                log: carmen.join("aces-raw/aces-raw.clf.gz"),
                relations: carmen.join("aces-raw/aces.relations"),
            },
            max_scans: quick,
            sensor_offset: None,
        },
        Dataset {
            name: "fr079-raw".into(),
            source: Source::Raw {
                log: carmen.join("fr079-raw/fr079-raw.clf.gz"),
                relations: carmen.join("fr079-raw/fr079.relations"),
            },
            max_scans: quick,
            sensor_offset: Some(FR079_SENSOR_OFFSET),
        },
    ];
    if !opts.quick {
        let mut corrected = vec![
            (
                "aces".to_string(),
                carmen.join("aces/aces-corrected.log.gz"),
            ),
            (
                "fr079".to_string(),
                carmen.join("fr079/freiburg-079-corrected.log.gz"),
            ),
        ];
        let other = carmen.join("other-corrected");
        let mut names: Vec<PathBuf> = std::fs::read_dir(&other)
            .map(|d| d.filter_map(|e| e.ok().map(|e| e.path())).collect())
            .unwrap_or_default();
        names.sort();
        for p in names {
            let file = p.file_name().and_then(|n| n.to_str()).unwrap_or("");
            if let Some(stem) = file.strip_suffix("-corrected.log.gz") {
                corrected.push((stem.to_string(), p.clone()));
            }
        }
        corrected.push((
            "csail-corrected".into(),
            carmen.join("mit-csail/csail-corrected.log.gz"),
        ));
        all.extend(corrected.into_iter().map(|(name, log)| Dataset {
            name,
            source: Source::Corrected { log },
            max_scans: None,
            sensor_offset: None,
        }));
    }
    let mut run = Vec::new();
    let mut skipped = Vec::new();
    for d in all {
        if !opts.only.is_empty() && !opts.only.contains(&d.name) {
            continue;
        }
        let files: Vec<&PathBuf> = match &d.source {
            Source::Raw { log, relations } => vec![log, relations],
            Source::Corrected { log } => vec![log],
            Source::Simulated { log, truth } => vec![log, truth],
        };
        match files.iter().find(|f| !f.is_file()) {
            Some(f) => skipped.push(Skipped {
                name: d.name.clone(),
                reason: format!("missing input {}", f.display()),
            }),
            None => run.push(d),
        }
    }
    (run, skipped)
}

/// Resets the kernel's peak-RSS counter of this process (Linux
/// `/proc/self/clear_refs`), so that the next `VmHWM` read is the peak since
/// now. Returns whether that worked.
pub fn reset_peak_memory() -> bool {
    std::fs::write("/proc/self/clear_refs", b"5").is_ok()
}

/// Copies the header and the first `scans` laser lines of a CARMEN or DP-SLAM
/// log (plain or gzip) to `out` as plain text; returns the laser lines copied.
pub fn truncate_log(input: &Path, out: &Path, scans: usize) -> Result<usize> {
    let file = std::fs::File::open(input).map_err(|e| Error::io(input, e))?;
    let mut head = BufReader::new(file);
    let gz = head
        .fill_buf()
        .map_err(|e| Error::io(input, e))?
        .starts_with(&[0x1f, 0x8b]);
    let reader: Box<dyn Read> = if gz {
        Box::new(flate2::read::MultiGzDecoder::new(head))
    } else {
        Box::new(head)
    };
    let mut w = Vec::new();
    let mut n = 0;
    for line in BufReader::new(reader).lines() {
        let line = line.map_err(|e| Error::io(input, e))?;
        let word = line.split_ascii_whitespace().next().unwrap_or("");
        let laser = matches!(word, "FLASER" | "RLASER" | "ROBOTLASER1" | "Laser")
            || word.starts_with("RAWLASER");
        if laser {
            if n == scans {
                break;
            }
            n += 1;
        }
        writeln!(w, "{line}").expect("write to Vec");
    }
    dpslam::pipeline::write_atomic(out, &w)?;
    Ok(n)
}

/// Odometry of every scan of `log` as planar poses stamped with the log's
/// time (or the index where the log has none), and whether the stamps are
/// strictly increasing.
pub fn odometry_trajectory(log: &Path) -> Result<(Vec<Stamped>, bool)> {
    let reader = open_log2d(log)?;
    let mut out = Vec::new();
    let mut increasing = true;
    for item in reader {
        let s = item?;
        let t = s.timestamp.unwrap_or(out.len() as f64);
        if s.timestamp.is_none() || out.last().is_some_and(|p: &Stamped| p.t >= t) {
            increasing = false;
        }
        let (x, y, th) = xyt(&s.odometry);
        out.push(Stamped::planar(t, x, y, th));
    }
    Ok((out, increasing))
}

/// The same poses stamped with their index.
fn by_index(poses: &[Stamped]) -> Vec<Stamped> {
    poses
        .iter()
        .enumerate()
        .map(|(i, p)| Stamped::new(i as f64, p.pose))
        .collect()
}

/// Relations whose two times fall within the span of `traj` (a log cut short).
fn relations_within(rels: &[Relation], traj: &[Stamped]) -> Vec<Relation> {
    let last = traj.iter().map(|p| p.t).fold(f64::NEG_INFINITY, f64::max);
    let limit = last + RELATION_TIME_TOLERANCE_S;
    rels.iter()
        .filter(|r| r.t1 <= limit && r.t2 <= limit)
        .cloned()
        .collect()
}

/// `poses` moved by the SE(2) fit of their positions onto `target` (pairs by
/// time within `max_dt`; fewer than two pairs: unmoved).
fn aligned_xy(poses: &[Stamped], target: &[Stamped], max_dt: f64) -> Vec<[f64; 2]> {
    let pairs = associate(target, poses, max_dt);
    let s = if pairs.len() >= 2 {
        let src: Vec<Vector3<f64>> = pairs
            .iter()
            .map(|&(_, j)| poses[j].pose.translation.vector)
            .collect();
        let dst: Vec<Vector3<f64>> = pairs
            .iter()
            .map(|&(i, _)| target[i].pose.translation.vector)
            .collect();
        align_se2(&src, &dst)
    } else {
        Isometry3::identity()
    };
    poses
        .iter()
        .map(|p| {
            // A point, not a vector: the alignment's translation must apply.
            let v = s * Point3::from(p.pose.translation.vector);
            [v.x, v.y]
        })
        .collect()
}

fn xy(poses: &[Stamped]) -> Vec<[f64; 2]> {
    poses
        .iter()
        .map(|p| [p.pose.translation.x, p.pose.translation.y])
        .collect()
}

/// Writes a smaller copy of a map image: each output pixel is the darkest of
/// its block, so thin walls survive the reduction.
pub fn shrink_map(src: &Path, dst: &Path, max_side: u32) -> Result<()> {
    let img = image::open(src)
        .map_err(|e| Error::Invalid(format!("{}: {e}", src.display())))?
        .to_luma8();
    let k = img
        .width()
        .max(img.height())
        .div_ceil(max_side.max(1))
        .max(1);
    let (w, h) = (img.width().div_ceil(k), img.height().div_ceil(k));
    let mut out = image::GrayImage::new(w, h);
    for (x, y, p) in out.enumerate_pixels_mut() {
        let mut v = 255u8;
        for yy in y * k..((y + 1) * k).min(img.height()) {
            for xx in x * k..((x + 1) * k).min(img.width()) {
                v = v.min(img.get_pixel(xx, yy).0[0]);
            }
        }
        p.0[0] = v;
    }
    let mut png = Vec::new();
    out.write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png)
        .map_err(|e| Error::Invalid(format!("PNG encoding failed: {e}")))?;
    dpslam::pipeline::write_atomic(dst, &png)
}

/// Maps one dataset and scores it. Files: `<out>/<name>/` (input copies,
/// `run/` from `map2d`, `trajectory.png`, `result.json`); the map and the
/// trajectory plot are also copied into `<docs>/results/`.
pub fn run_dataset(d: &Dataset, opts: &AccuracyOptions) -> Result<RunResult> {
    let dir = opts.out.join(&d.name);
    std::fs::create_dir_all(&dir).map_err(|e| Error::io(&dir, e))?;
    let mut notes = Vec::new();
    // The log to map, its truth (if any) and its relations (if any).
    let (mut log, mut truth, relations, kind) = match &d.source {
        Source::Raw { log, relations } => (
            log.clone(),
            None,
            Some(read_relations(relations)?),
            "raw log + relations",
        ),
        Source::Simulated { log, truth } => {
            (log.clone(), Some(read_tum(truth)?), None, "simulated")
        }
        Source::Corrected { log } => {
            let noisy = dir.join("odometry.clf");
            let truth_path = dir.join("truth.tum");
            let s = perturb_log(log, &noisy, &truth_path, &opts.noise, opts.noise_seed)?;
            notes.push(format!(
                "odometry drift {:.2} m over a {:.0} m path",
                s.final_position_error_m, s.path_length_m
            ));
            (
                noisy,
                Some(read_tum(&truth_path)?),
                None,
                "perturbed corrected log",
            )
        }
    };
    if let Some(n) = d.max_scans {
        let cut = dir.join("input.clf");
        let kept = truncate_log(&log, &cut, n)?;
        notes.push(format!("first {kept} scans only"));
        log = cut;
    }
    let (odometry, stamps_ok) = odometry_trajectory(&log)?;
    let bad = BAD_TIMESTAMPS.iter().find(|(n, _)| *n == d.name);
    let matching = if stamps_ok && bad.is_none() {
        Matching::Time
    } else {
        notes.push(format!(
            "{}: truth matched by scan index, no data duration",
            bad.map_or("time stamps not strictly increasing", |b| b.1)
        ));
        Matching::ScanIndex
    };

    let run_dir = dir.join("run");
    let cfg = d.config(&opts.cfg);
    if let Some(o) = d.sensor_offset {
        notes.push(format!(
            "laser pose {o:?} in the robot frame (sensor_offset)"
        ));
    }
    let settings = run_settings(d, &cfg, opts);
    let settings_path = dir.join("run.settings");
    let earlier = reusable_run(&run_dir, &settings_path, &settings, opts);
    if earlier.is_none() {
        // A run cut short must not look reusable later.
        match std::fs::remove_file(&settings_path) {
            Err(e) if e.kind() != std::io::ErrorKind::NotFound => {
                return Err(Error::io(&settings_path, e));
            }
            _ => {}
        }
    }
    let mapping = Instant::now();
    let (mut summary, peak) = match (earlier, &opts.mapper) {
        (Some(s), _) => {
            notes.push("mapping reused from an earlier run with the same settings".into());
            let peak = s.peak_memory_mib;
            (s, peak)
        }
        (None, Some(exe)) => {
            let config = dir.join("config.toml");
            let s = map2d_process(exe, &log, &run_dir, &config, &cfg, opts.learn_motion)?;
            dpslam::pipeline::write_atomic(&settings_path, settings.as_bytes())?;
            let peak = s.peak_memory_mib;
            (s, peak)
        }
        (None, None) => {
            let reset = reset_peak_memory();
            let s = if opts.learn_motion > 0 {
                let backend = dpslam::backend::Backend::Cpu;
                let ranges = RangeSettings::of_log(&log, &cfg)?;
                let rounds = opts.learn_motion;
                run_map2d_learning(&log, &run_dir, &cfg, backend, &ranges, rounds, |_| {})?.0
            } else {
                run_map2d(&log, &run_dir, &cfg)?
            };
            dpslam::pipeline::write_atomic(&settings_path, settings.as_bytes())?;
            (s, dpslam::pipeline::peak_memory_mib().filter(|_| reset))
        }
    };
    if opts.learn_motion > 0 {
        // The learning rounds are part of what it costs to get this result.
        summary.wall_time_s = mapping.elapsed().as_secs_f64();
        notes.push(format!(
            "motion model learned from the log ({} rounds, included in the wall time)",
            opts.learn_motion
        ));
    }
    let mut estimate = read_tum(&run_dir.join("trajectory.tum"))?;
    let mut odometry = odometry;
    if matching == Matching::ScanIndex {
        let t = truth.as_ref().map_or(estimate.len(), |t| t.len());
        if t != estimate.len() || odometry.len() != estimate.len() {
            return Err(Error::Invalid(format!(
                "{}: cannot match by scan index: {} truth poses, {} estimated, {} odometry",
                d.name,
                t,
                estimate.len(),
                odometry.len()
            )));
        }
        estimate = by_index(&estimate);
        odometry = by_index(&odometry);
        truth = truth.map(|t| by_index(&t));
    }

    let (rel, odo_rel) = match &relations {
        Some(all) => {
            let rels = if d.max_scans.is_some() {
                relations_within(all, &estimate)
            } else {
                all.clone()
            };
            if d.max_scans.is_some() {
                notes.push(format!(
                    "{} of {} relations (those inside the subset)",
                    rels.len(),
                    all.len()
                ));
            }
            if rels.is_empty() {
                (None, None)
            } else {
                (
                    Some(evaluate_relations(&rels, &estimate)?),
                    Some(evaluate_relations(&rels, &odometry)?),
                )
            }
        }
        None => (None, None),
    };
    let ate_opts = AteOptions::default();
    let (ate, odo_ate) = match &truth {
        Some(t) => (
            Some(evaluate_ate(t, &estimate, &ate_opts)?.rmse_m),
            Some(evaluate_ate(t, &odometry, &ate_opts)?.rmse_m),
        ),
        None => (None, None),
    };

    // Trajectory plot: everything in the truth's frame, else in the estimate's.
    let mut plot = Plot::new(640, 640);
    plot.equal_aspect = true;
    let dt = ate_opts.max_dt_s;
    let (est_xy, odo_xy) = match &truth {
        Some(t) => (aligned_xy(&estimate, t, dt), aligned_xy(&odometry, t, dt)),
        None => (xy(&estimate), aligned_xy(&odometry, &estimate, dt)),
    };
    plot.series.push(Series {
        label: "odometry".into(),
        points: odo_xy,
        color: PALETTE[2],
        markers: false,
    });
    if let Some(t) = &truth {
        // Only the span that was mapped (a `--quick` subset maps part of the log).
        let (first, last) = (estimate[0].t, estimate[estimate.len() - 1].t);
        let span: Vec<Stamped> = t
            .iter()
            .filter(|p| p.t >= first - dt && p.t <= last + dt)
            .copied()
            .collect();
        plot.series.push(Series {
            label: "truth".into(),
            points: xy(&span),
            color: PALETTE[1],
            markers: false,
        });
    }
    plot.series.push(Series {
        label: "estimate".into(),
        points: est_xy,
        color: PALETTE[0],
        markers: false,
    });
    let results = opts.docs.join("results");
    std::fs::create_dir_all(&results).map_err(|e| Error::io(&results, e))?;
    plot.write_png(&dir.join("trajectory.png"))?;
    let traj_name = format!("{}-trajectory.png", d.name);
    std::fs::copy(dir.join("trajectory.png"), results.join(&traj_name))
        .map_err(|e| Error::io(&results.join(&traj_name), e))?;
    let map_name = format!("{}-map.png", d.name);
    shrink_map(
        &run_dir.join("map.png"),
        &results.join(&map_name),
        DOC_MAP_SIDE,
    )?;

    let duration = summary
        .data_duration_s
        .filter(|_| matching == Matching::Time);
    let result = RunResult {
        name: d.name.clone(),
        kind: kind.into(),
        scans: summary.scans,
        scans_processed: summary.scans_processed,
        particles: summary.particles,
        relations: rel,
        odometry_relations: odo_rel,
        ate_rmse_m: ate,
        odometry_ate_rmse_m: odo_ate,
        matching: truth.as_ref().map(|_| matching),
        wall_time_s: summary.wall_time_s,
        data_duration_s: duration,
        peak_memory_mib: peak,
        map_memory_mib: summary.map_memory_mib,
        map_image: Some(format!("results/{map_name}")),
        trajectory_plot: Some(format!("results/{traj_name}")),
        note: (!notes.is_empty()).then(|| notes.join("; ")),
    };
    dpslam::pipeline::write_json(&dir.join("result.json"), &result)?;
    Ok(result)
}

/// What a dataset's mapping depends on, besides the code and the input
/// files: the configuration as `map2d` gets it, the subset, the odometry
/// noise of a perturbed log, the learning rounds. Stored beside a finished
/// run (`run.settings`) for [`AccuracyOptions::reuse_runs`].
pub fn run_settings(d: &Dataset, cfg: &Config, opts: &AccuracyOptions) -> String {
    let noise = match d.source {
        Source::Corrected { .. } => format!("{} seed {}", opts.noise, opts.noise_seed),
        _ => "none".into(),
    };
    format!(
        "{}\n# input: {:?}\n# max_scans: {:?}\n# odometry noise: {noise}\n# learn_motion: {}\n",
        cfg.to_toml().trim_end(),
        d.source,
        d.max_scans,
        opts.learn_motion
    )
}

/// The summary of the earlier run in `run_dir`, if reuse is on and it was
/// made with `settings`.
fn reusable_run(
    run_dir: &Path,
    settings_path: &Path,
    settings: &str,
    opts: &AccuracyOptions,
) -> Option<dpslam::pipeline::map2d::Map2dSummary> {
    if !opts.reuse_runs || opts.learn_motion > 0 {
        return None;
    }
    if std::fs::read_to_string(settings_path).ok()? != settings {
        return None;
    }
    for f in ["trajectory.tum", "map.png"] {
        if !run_dir.join(f).is_file() {
            return None;
        }
    }
    let text = std::fs::read_to_string(run_dir.join("run.json")).ok()?;
    serde_json::from_str(&text).ok()
}

/// The source tree's git commit (short hash, "+ changes" when tracked files
/// differ from it), if this build's source folder is a git checkout.
pub(crate) fn source_commit() -> Option<String> {
    let git = |args: &[&str]| {
        std::process::Command::new("git")
            .arg("-C")
            .arg(env!("CARGO_MANIFEST_DIR"))
            .args(args)
            .output()
            .ok()
            .filter(|o| o.status.success())
            .map(|o| String::from_utf8_lossy(&o.stdout).trim().to_string())
    };
    let hash = git(&["rev-parse", "--short", "HEAD"]).filter(|h| !h.is_empty())?;
    let dirty =
        git(&["status", "--porcelain", "--untracked-files=no"]).is_some_and(|s| !s.is_empty());
    Some(if dirty {
        format!("{hash} + changes")
    } else {
        hash
    })
}

/// Runs `exe map2d LOG --out OUT --config CONFIG [--learn-motion N]` with
/// `cfg` written to `config`, and returns the summary it wrote (`OUT/run.json`).
fn map2d_process(
    exe: &Path,
    log: &Path,
    out: &Path,
    config: &Path,
    cfg: &Config,
    learn_motion: usize,
) -> Result<dpslam::pipeline::map2d::Map2dSummary> {
    dpslam::pipeline::write_atomic(config, cfg.to_toml().as_bytes())?;
    let mut command = std::process::Command::new(exe);
    command
        .arg("map2d")
        .arg(log)
        .arg("--out")
        .arg(out)
        .arg("--config")
        .arg(config);
    if learn_motion > 0 {
        command.arg("--learn-motion").arg(learn_motion.to_string());
    }
    let run = command
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::piped())
        .output()
        .map_err(|e| Error::io(exe, e))?;
    if !run.status.success() {
        let err = String::from_utf8_lossy(&run.stderr);
        return Err(Error::Invalid(format!(
            "{} map2d {} failed ({}): {}",
            exe.display(),
            log.display(),
            run.status,
            err.trim()
        )));
    }
    let json = out.join("run.json");
    let text = std::fs::read_to_string(&json).map_err(|e| Error::io(&json, e))?;
    serde_json::from_str(&text).map_err(|e| Error::Invalid(format!("{}: {e}", json.display())))
}

/// Runs the scaling bench with `so` (its own `particles` per point, the
/// rest of the configuration from `so.cfg`) and writes
/// `time-vs-particles.png` and `scaling.json` into `dir`.
pub fn run_scaling_into(so: &ScalingOptions, dir: &Path) -> Result<ScalingReport> {
    let r = run_scaling(so)?;
    std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
    write_scaling_plot(&r, &dir.join("time-vs-particles.png"))?;
    dpslam::pipeline::write_json(&dir.join("scaling.json"), &r)?;
    Ok(r)
}

/// Runs every planned dataset and then the scaling bench (unless
/// `opts.scaling` is `None`), then writes `<docs>/RESULTS.md` and
/// `<out>/results.json`. A dataset that fails is reported as not run (with
/// the error) rather than losing the others.
pub fn run_accuracy(opts: &AccuracyOptions) -> Result<AccuracyReport> {
    opts.cfg.validate()?;
    opts.noise.validate()?;
    let start = Instant::now();
    // Before this run rewrites the tracked result files.
    let commit = source_commit();
    let (datasets, mut skipped) = plan(opts);
    if datasets.is_empty() {
        return Err(Error::Config(format!(
            "no dataset to run (only: {:?}; not run: {:?})",
            opts.only, skipped
        )));
    }
    let mut runs = Vec::new();
    for d in &datasets {
        eprintln!("bench accuracy: {} ...", d.name);
        match run_dataset(d, opts) {
            Ok(r) => {
                eprintln!(
                    "bench accuracy: {}: {:.1} s wall, ATE {:?} m, relations {:?}",
                    r.name,
                    r.wall_time_s,
                    r.ate_rmse_m,
                    r.relations.map(|x| x.trans_mean_m)
                );
                runs.push(r);
            }
            Err(e) => {
                eprintln!("bench accuracy: {}: failed: {e}", d.name);
                skipped.push(Skipped {
                    name: d.name.clone(),
                    reason: format!("run failed: {e}"),
                });
            }
        }
    }
    let mut scaling = None;
    if let Some(so) = opts.scaling.as_ref().filter(|_| !opts.quick) {
        eprintln!(
            "bench accuracy: scaling ({:?} particles, {} warm-up scans, {} timed steps) ...",
            so.particles, so.warmup_scans, so.timed_steps
        );
        match run_scaling_into(so, &opts.docs.join("results")) {
            Ok(r) => {
                eprintln!(
                    "bench accuracy: scaling: {:.2} ms per particle, 3000/300 = {:?}",
                    r.slope_ms_per_particle, r.ratio_3000_300
                );
                scaling = Some(r);
            }
            Err(e) => {
                eprintln!("bench accuracy: scaling: failed: {e}");
                skipped.push(Skipped {
                    name: "scaling".into(),
                    reason: format!("run failed: {e}"),
                });
            }
        }
    }
    let scaling_png = opts.docs.join("results/time-vs-particles.png");
    let report = AccuracyReport {
        quick: opts.quick,
        command: opts.command.clone(),
        version: match commit {
            Some(c) => format!("{} (commit {c})", env!("CARGO_PKG_VERSION")),
            None => env!("CARGO_PKG_VERSION").into(),
        },
        threads: rayon::current_num_threads(),
        noise_seed: opts.noise_seed,
        noise: opts.noise.to_string(),
        memory_note: if opts.mapper.is_some() {
            "peak resident memory of each run's own `dpslam map2d` process (VmHWM)".into()
        } else {
            "peak resident memory of the process during each run \
             (VmHWM, reset before each run via /proc/self/clear_refs; \
             memory the allocator kept from earlier runs counts)"
                .into()
        },
        total_wall_s: start.elapsed().as_secs_f64(),
        runs,
        skipped,
        scaling_plot: scaling_png
            .is_file()
            .then(|| "results/time-vs-particles.png".into()),
        scaling,
    };
    std::fs::create_dir_all(&opts.out).map_err(|e| Error::io(&opts.out, e))?;
    dpslam::pipeline::write_json(&opts.out.join("results.json"), &report)?;
    dpslam::pipeline::write_atomic(
        &opts.docs.join("RESULTS.md"),
        results_markdown(&report).as_bytes(),
    )?;
    Ok(report)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn alignment_moves_points_onto_the_target() {
        let target: Vec<Stamped> = (0..20)
            .map(|i| {
                Stamped::planar(
                    i as f64,
                    i as f64 * 0.5,
                    (i as f64 * 0.3).sin(),
                    0.1 * i as f64,
                )
            })
            .collect();
        // The same path in a frame rotated by 1 rad and shifted far away.
        let g = dpslam::geometry::pose2(576.0, -40.0, 1.0);
        let moved: Vec<Stamped> = target
            .iter()
            .map(|p| {
                let (x, y, th) = xyt(&(g * dpslam::geometry::pose2(
                    p.pose.translation.x,
                    p.pose.translation.y,
                    p.pose.rotation.angle(),
                )));
                Stamped::planar(p.t, x, y, th)
            })
            .collect();
        let aligned = aligned_xy(&moved, &target, 0.01);
        for (a, t) in aligned.iter().zip(xy(&target)) {
            assert!(
                (a[0] - t[0]).abs() < 1e-6 && (a[1] - t[1]).abs() < 1e-6,
                "{a:?} vs {t:?}"
            );
        }
    }

    #[test]
    fn relations_outside_the_subset_are_dropped() {
        let traj: Vec<Stamped> = (0..5)
            .map(|i| Stamped::planar(i as f64, 0.0, 0.0, 0.0))
            .collect();
        let rels = vec![
            Relation::new(0.0, 4.0, Isometry3::identity(), 1),
            Relation::new(1.0, 4.0005, Isometry3::identity(), 2),
            Relation::new(3.0, 5.0, Isometry3::identity(), 3),
        ];
        let kept = relations_within(&rels, &traj);
        assert_eq!(kept.iter().map(|r| r.line).collect::<Vec<_>>(), vec![1, 2]);
    }
}
