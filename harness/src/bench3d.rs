//! The 3-D benchmark (`dpslam-bench 3d`): `dpslam map3d` (LiDAR only), KISS-ICP
//! (where `kiss_icp_pipeline` is on the PATH) and the simulated wheel
//! odometry, on long simulated sequences with ground truth, scored with the
//! library's SE(3) ATE and written up as `docs/RESULTS-3D.md` with a
//! top-down map picture per sequence and method.
//!
//! Sequences are simulated with [`dpslam::sim::sim3d::write_sim3d`] into a
//! scratch folder (`target/bench-3d` by default, never committed) and
//! reused when the folder already holds the same configuration and seed
//! (`sequence.json`).
//!
//! Every method runs in a process of its own, reaped with `wait4`, so that
//! its CPU time (user + system) and peak resident memory are its own.
//! KISS-ICP reads the KITTI `.bin` sweeps as they are; its poses
//! (`results/latest/sweeps_poses_kitti.txt`, the sensor frame of the first
//! sweep) are stamped with their index like the truth. Where `evo_ape` is on
//! the PATH, every ATE is recomputed with it (`evo_ape tum truth est -a`) as
//! an independent check.

use super::plot::{PALETTE, Plot, Series};
use super::report::markdown_table;
use dpslam::eval::ate::{Alignment, AteOptions, align_se3, associate, evaluate_ate};
use dpslam::io::tum::{Stamped, read_poses, read_tum, write_stamped};
use dpslam::sim::sim3d::{Sim3dConfig, sweep_file_name, write_sim3d};
use dpslam::{Error, Result};
use nalgebra::{Isometry3, Point3, Vector3};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Instant;

/// Particles of the dpslam runs unless overridden (`map3d`'s default).
pub const DEFAULT_PARTICLES: usize = 20;

/// Points (about) drawn per map picture.
const PICTURE_POINTS: usize = 250_000;

/// Side of the map pictures, pixels.
const PICTURE_SIDE: u32 = 640;

/// One simulated sequence of the benchmark.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Sequence {
    /// Name: table heading and scratch folder.
    pub name: String,
    /// One line on what it is.
    pub description: String,
    /// The `dpslam simulate3d` command line that writes the same files.
    pub command: String,
    /// Simulation settings.
    pub cfg: Sim3dConfig,
    /// Simulation seed.
    pub seed: u64,
}

/// The sequences of the full benchmark: the 200-sweep building loop of
/// issue 13 (`simulate3d --seed 5`) and the long-corridor loop
/// (`simulate3d --world corridors`).
pub fn default_sequences() -> Vec<Sequence> {
    vec![
        Sequence {
            name: "building-seed5".into(),
            description: "the building loop (70 m, up a ramp to a mezzanine and back), \
                          200 sweeps of 32 × 1024 rays, 0.34 m apart"
                .into(),
            command: "dpslam simulate3d --out DIR --seed 5".into(),
            cfg: Sim3dConfig::default(),
            seed: 5,
        },
        Sequence {
            name: "corridors".into(),
            description: "the long-corridor loop (360 m of plain 3 m corridors, features \
                          17–34 m apart, driven once round and 15 m on), 368 sweeps of \
                          32 × 1024 rays, ≈ 1 m apart"
                .into(),
            command: "dpslam simulate3d --out DIR --world corridors".into(),
            cfg: Sim3dConfig::corridors(),
            seed: 1,
        },
    ]
}

/// Two tiny sequences (8 sweeps of 16 × 256 rays round a corner of each
/// world): a smoke test of the whole bench in seconds.
pub fn quick_sequences() -> Vec<Sequence> {
    let tiny = |cfg: Sim3dConfig, waypoints: Vec<[f64; 2]>| Sim3dConfig {
        waypoints,
        sweeps: 8,
        rings: 16,
        columns: 256,
        ..cfg
    };
    vec![
        Sequence {
            name: "building-tiny".into(),
            description: "8 sweeps of 16 × 256 rays, ≈ 1.2 m apart, round the building's \
                          south-east corner"
                .into(),
            command: "dpslam simulate3d --out DIR --sweeps 8 --rings 16 --columns 256 \
                      --config FILE (waypoints [[15, 0], [20, 0], [20.7, 3]])"
                .into(),
            cfg: tiny(
                Sim3dConfig::default(),
                vec![[15.0, 0.0], [20.0, 0.0], [20.7, 3.0]],
            ),
            seed: 1,
        },
        Sequence {
            name: "corridors-tiny".into(),
            description: "8 sweeps of 16 × 256 rays, ≈ 1.4 m apart, round the corridors' \
                          first corner"
                .into(),
            command: "(the corridors preset with waypoints [[103, 0], [110, 0], [110, 4]], \
                      8 sweeps of 16 × 256 rays)"
                .into(),
            cfg: tiny(
                Sim3dConfig::corridors(),
                vec![[103.0, 0.0], [110.0, 0.0], [110.0, 4.0]],
            ),
            seed: 1,
        },
    ]
}

/// Settings of [`run_bench3d`].
#[derive(Debug, Clone)]
pub struct Bench3dOptions {
    /// The sequences to run.
    pub sequences: Vec<Sequence>,
    /// Scratch folder: simulated sequences and run outputs.
    pub out: PathBuf,
    /// `RESULTS-3D.md` goes here, the pictures into `results-3d/` below it.
    pub docs: PathBuf,
    /// The `dpslam` executable that runs `map3d`.
    pub mapper: PathBuf,
    /// Particles of the dpslam runs.
    pub particles: usize,
    /// Worker threads of the dpslam runs (`None`: all cores).
    pub threads: Option<usize>,
    /// `kiss_icp_pipeline`, if it is to be run.
    pub kiss_icp: Option<PathBuf>,
    /// `evo_ape`, if the ATEs are to be cross-checked.
    pub evo_ape: Option<PathBuf>,
    /// Command line, for the report.
    pub command: String,
    /// Reuse a method's earlier run on the same sequence with the same
    /// settings (its trajectory and recorded measurements) instead of
    /// running it again: rescores and redraws only.
    pub reuse_runs: bool,
}

impl Bench3dOptions {
    /// The full benchmark with `mapper`: out `target/bench-3d`, docs `docs`
    /// (relative to the repository root), 20 particles, KISS-ICP and evo
    /// from the PATH where they are.
    pub fn new(mapper: PathBuf) -> Self {
        let root = Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/.."));
        Self {
            sequences: default_sequences(),
            out: root.join("target/bench-3d"),
            docs: root.join("docs"),
            mapper,
            particles: DEFAULT_PARTICLES,
            threads: None,
            kiss_icp: find_on_path("kiss_icp_pipeline"),
            evo_ape: find_on_path("evo_ape"),
            command: String::new(),
            reuse_runs: false,
        }
    }
}

/// The first executable file called `name` in a folder of `PATH`.
pub fn find_on_path(name: &str) -> Option<PathBuf> {
    let path = std::env::var_os("PATH")?;
    std::env::split_paths(&path)
        .map(|d| d.join(name))
        .find(|p| p.is_file())
}

/// CPU time, peak memory and wall time of one child process.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Usage {
    /// Wall-clock time, s.
    pub wall_s: f64,
    /// User + system CPU time, s.
    pub cpu_s: f64,
    /// Peak resident set size, MiB.
    pub peak_rss_mib: f64,
}

/// Runs `cmd` to completion with stdout and stderr into `log`, and measures
/// it (`wait4`). A failure exit is an error quoting the end of the log.
pub fn run_measured(mut cmd: Command, log: &Path) -> Result<Usage> {
    let file = std::fs::File::create(log).map_err(|e| Error::io(log, e))?;
    let err = file.try_clone().map_err(|e| Error::io(log, e))?;
    let what = format!("{cmd:?}");
    let start = Instant::now();
    let child = cmd
        .stdout(file)
        .stderr(err)
        .stdin(std::process::Stdio::null())
        .spawn()
        .map_err(|e| Error::Invalid(format!("{what}: cannot start: {e}")))?;
    let pid = child.id() as libc::pid_t;
    let mut status: libc::c_int = 0;
    // SAFETY: rusage is plain old data; all zeros is a valid value.
    let mut ru: libc::rusage = unsafe { std::mem::zeroed() };
    let r = loop {
        // SAFETY: `pid` is our own child, not yet reaped (std's `Child` only
        // reaps in `wait`/`try_wait`, which are never called on it); the
        // pointers are to live locals.
        let r = unsafe { libc::wait4(pid, &mut status, 0, &mut ru) };
        if r == -1 && std::io::Error::last_os_error().kind() == std::io::ErrorKind::Interrupted {
            continue;
        }
        break r;
    };
    let wall_s = start.elapsed().as_secs_f64();
    drop(child);
    if r != pid {
        return Err(Error::Invalid(format!(
            "{what}: wait4 failed: {}",
            std::io::Error::last_os_error()
        )));
    }
    if !(libc::WIFEXITED(status) && libc::WEXITSTATUS(status) == 0) {
        let text = std::fs::read_to_string(log).unwrap_or_default();
        let tail: String = text
            .lines()
            .rev()
            .take(5)
            .collect::<Vec<_>>()
            .into_iter()
            .rev()
            .collect::<Vec<_>>()
            .join(" / ");
        return Err(Error::Invalid(format!(
            "{what} failed (wait status {status}): {tail}"
        )));
    }
    let secs = |t: libc::timeval| t.tv_sec as f64 + t.tv_usec as f64 * 1e-6;
    Ok(Usage {
        wall_s,
        cpu_s: secs(ru.ru_utime) + secs(ru.ru_stime),
        // Linux reports ru_maxrss in KiB.
        peak_rss_mib: ru.ru_maxrss as f64 / 1024.0,
    })
}

/// One method on one sequence.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct MethodRun {
    /// "dpslam map3d", "KISS-ICP", "KISS-ICP, 0.2 m voxels" or "odometry".
    pub method: String,
    /// File-name form of the method: run folder, picture name.
    pub slug: String,
    /// Settings in a few words.
    pub settings: String,
    /// Poses in the trajectory.
    pub poses: usize,
    /// Process measurements (none for the odometry, which is an input).
    pub usage: Option<Usage>,
    /// Wall time per sweep as the method reports it (dpslam's run.json),
    /// else the process's wall time over the sweeps, s.
    pub time_per_sweep_s: Option<f64>,
    /// ATE after SE(3) alignment: RMSE of the positions, m.
    pub ate_rmse_m: f64,
    /// Largest position error, m.
    pub ate_max_m: f64,
    /// Mean rotation error, degrees.
    pub ate_rot_deg: f64,
    /// `evo_ape tum truth est -a` RMSE, m, where evo was run.
    pub evo_rmse_m: Option<f64>,
    /// Map picture, relative to the results document.
    pub picture: Option<String>,
    /// The trajectory scored (TUM).
    pub trajectory: PathBuf,
    /// Remarks.
    pub note: Option<String>,
    /// The process measurements come from an earlier bench's run of the
    /// same method and settings on the same sequence (`--reuse-runs`).
    pub reused_run: bool,
}

/// A method that could not be run, and why.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct NotRun {
    /// The method.
    pub method: String,
    /// Why.
    pub reason: String,
}

/// All methods on one sequence.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct SequenceResult {
    /// Sequence name.
    pub name: String,
    /// What it is.
    pub description: String,
    /// The equivalent `dpslam simulate3d` command.
    pub command: String,
    /// Sweeps.
    pub sweeps: usize,
    /// Mean points per sweep.
    pub points_per_sweep: f64,
    /// Length of the driven path, m.
    pub path_length_m: f64,
    /// Whether the files of an earlier run were reused.
    pub reused: bool,
    /// The runs, dpslam first.
    pub runs: Vec<MethodRun>,
    /// Methods not run.
    pub not_run: Vec<NotRun>,
}

impl SequenceResult {
    /// The run of `method`, if it ran.
    pub fn run(&self, method: &str) -> Option<&MethodRun> {
        self.runs.iter().find(|r| r.method == method)
    }
}

/// The whole benchmark.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Bench3dReport {
    /// Command line.
    pub command: String,
    /// dpslam version and source commit.
    pub version: String,
    /// CPU cores seen by the harness.
    pub cores: usize,
    /// Particles of the dpslam runs.
    pub particles: usize,
    /// Wall time of the whole benchmark, s.
    pub total_wall_s: f64,
    /// Per sequence.
    pub sequences: Vec<SequenceResult>,
}

/// Method names as they appear in the report.
pub const DPSLAM: &str = "dpslam map3d";
/// KISS-ICP's row (its defaults: voxels of max range / 100 = 1 m here).
pub const KISS_ICP: &str = "KISS-ICP";
/// KISS-ICP with 0.2 m voxels (dpslam's voxel size), as in issue 13.
pub const KISS_ICP_FINE: &str = "KISS-ICP, 0.2 m voxels";

/// The KISS-ICP configurations run: (row name, slug, voxel size or the default).
const KISS_VARIANTS: [(&str, &str, Option<f64>); 2] = [
    (KISS_ICP, "kiss-icp", None),
    (KISS_ICP_FINE, "kiss-icp-0.2", Some(0.2)),
];
/// The odometry's row.
pub const ODOMETRY: &str = "odometry";

/// What `sequence.json` records: a folder is reused only for the same.
#[derive(Serialize, Deserialize, PartialEq)]
struct Stamp {
    cfg: Sim3dConfig,
    seed: u64,
    path_length_m: f64,
    points: usize,
}

/// Simulates `seq` into `dir` unless `dir/sequence.json` says it already
/// holds it; returns (path length, points, reused).
fn ensure_sequence(seq: &Sequence, dir: &Path) -> Result<(f64, usize, bool)> {
    let stamp_path = dir.join("sequence.json");
    if let Ok(text) = std::fs::read_to_string(&stamp_path)
        && let Ok(stamp) = serde_json::from_str::<Stamp>(&text)
        && stamp.cfg == seq.cfg
        && stamp.seed == seq.seed
        && dir.join("truth.tum").is_file()
        && dir.join("odometry.tum").is_file()
        && (0..seq.cfg.sweeps).all(|k| {
            dir.join("sweeps")
                .join(sweep_file_name(k, seq.cfg.gzip))
                .is_file()
        })
    {
        return Ok((stamp.path_length_m, stamp.points, true));
    }
    // A stale stamp must not survive a half-written sequence.
    let _ = std::fs::remove_file(&stamp_path);
    let s = write_sim3d(dir, &seq.cfg, seq.seed)?;
    let stamp = Stamp {
        cfg: seq.cfg.clone(),
        seed: seq.seed,
        path_length_m: s.path_length,
        points: s.points,
    };
    dpslam::pipeline::write_json(&stamp_path, &stamp)?;
    Ok((s.path_length, s.points, false))
}

/// The ATE options of the benchmark: SE(3) alignment, default pairing.
fn ate_options() -> AteOptions {
    AteOptions {
        alignment: Alignment::Se3,
        ..AteOptions::default()
    }
}

/// `evo_ape tum truth est -a`: the RMSE it prints.
fn evo_rmse(evo: &Path, truth: &Path, est: &Path) -> Result<f64> {
    let out = Command::new(evo)
        .arg("tum")
        .arg(truth)
        .arg(est)
        .arg("-a")
        .arg("--no_warnings")
        .stdin(std::process::Stdio::null())
        .output()
        .map_err(|e| Error::io(evo, e))?;
    let text = String::from_utf8_lossy(&out.stdout);
    if !out.status.success() {
        return Err(Error::Invalid(format!(
            "evo_ape failed ({}): {} {}",
            out.status,
            text.trim(),
            String::from_utf8_lossy(&out.stderr).trim()
        )));
    }
    parse_evo_rmse(&text)
        .ok_or_else(|| Error::Invalid(format!("no rmse in evo_ape's output: {text}")))
}

/// The `rmse` value of `evo_ape`'s statistics block.
pub fn parse_evo_rmse(text: &str) -> Option<f64> {
    text.lines().find_map(|l| {
        let mut w = l.split_whitespace();
        (w.next() == Some("rmse"))
            .then(|| w.next()?.parse().ok())
            .flatten()
    })
}

/// Sensor-frame points of every `stride`-th sweep (each thinned to about
/// `per_sweep` points above the floor), for the map pictures: (sweep index,
/// points).
fn picture_points(dir: &Path, seq: &Sequence) -> Result<Vec<(usize, Vec<Vector3<f64>>)>> {
    let n = seq.cfg.sweeps;
    let stride = n.div_ceil(100).max(1);
    let chosen = n.div_ceil(stride);
    let per_sweep = (PICTURE_POINTS / chosen.max(1)).max(100);
    // Keep walls and objects, drop the floor under the vehicle: from 0.3 m
    // above the floor to 1.5 m above the sensor.
    let (zlo, zhi) = (0.3 - seq.cfg.sensor_height, 1.5);
    let mut out = Vec::new();
    for k in (0..n).step_by(stride) {
        let path = dir.join("sweeps").join(sweep_file_name(k, seq.cfg.gzip));
        let bytes = std::fs::read(&path).map_err(|e| Error::io(&path, e))?;
        let bytes = if seq.cfg.gzip {
            let mut v = Vec::new();
            std::io::Read::read_to_end(&mut flate2::read::GzDecoder::new(&bytes[..]), &mut v)
                .map_err(|e| Error::io(&path, e))?;
            v
        } else {
            bytes
        };
        let f = |b: &[u8]| f64::from(f32::from_le_bytes([b[0], b[1], b[2], b[3]]));
        let all: Vec<Vector3<f64>> = bytes
            .chunks_exact(16)
            .map(|r| Vector3::new(f(&r[0..4]), f(&r[4..8]), f(&r[8..12])))
            .filter(|p| p.z > zlo && p.z < zhi)
            .collect();
        let step = all.len().div_ceil(per_sweep).max(1);
        out.push((k, all.into_iter().step_by(step).collect()));
    }
    Ok(out)
}

/// `est` moved onto `truth` by the SE(3) fit of the paired positions.
fn aligned(truth: &[Stamped], est: &[Stamped]) -> Vec<Stamped> {
    let pairs = associate(truth, est, ate_options().max_dt_s);
    let g = if pairs.len() >= 3 {
        let src: Vec<_> = pairs
            .iter()
            .map(|&(_, j)| est[j].pose.translation.vector)
            .collect();
        let dst: Vec<_> = pairs
            .iter()
            .map(|&(i, _)| truth[i].pose.translation.vector)
            .collect();
        align_se3(&src, &dst)
    } else {
        Isometry3::identity()
    };
    est.iter().map(|s| Stamped::new(s.t, g * s.pose)).collect()
}

fn xy(poses: &[Stamped]) -> Vec<[f64; 2]> {
    poses
        .iter()
        .map(|p| [p.pose.translation.x, p.pose.translation.y])
        .collect()
}

/// The top-down picture of one method's run: the sweeps' points (walls and
/// objects) registered with its trajectory as grey density, the truth in
/// red and the trajectory in blue, all after the SE(3) alignment onto the
/// truth.
fn write_picture(
    path: &Path,
    truth: &[Stamped],
    est: &[Stamped],
    points: &[(usize, Vec<Vector3<f64>>)],
) -> Result<()> {
    let est = aligned(truth, est);
    let by_time: std::collections::HashMap<u64, &Stamped> =
        est.iter().map(|s| (s.t.to_bits(), s)).collect();
    let mut plot = Plot::new(PICTURE_SIDE, PICTURE_SIDE);
    plot.equal_aspect = true;
    for (k, pts) in points {
        // Sweep k's stamp is k s in every trajectory here.
        let Some(pose) = by_time.get(&(*k as f64).to_bits()) else {
            continue;
        };
        plot.cloud.extend(pts.iter().map(|p| {
            let w = pose.pose * Point3::from(*p);
            [w.x, w.y]
        }));
    }
    plot.series.push(Series {
        label: "truth".into(),
        points: xy(truth),
        color: PALETTE[1],
        markers: false,
    });
    plot.series.push(Series {
        label: "estimate".into(),
        points: xy(&est),
        color: PALETTE[0],
        markers: false,
    });
    plot.write_png(path)
}

/// Scores `est_path` against `truth` and fills a [`MethodRun`].
#[allow(clippy::too_many_arguments)]
fn score(
    method: &str,
    slug: &str,
    settings: String,
    truth_path: &Path,
    truth: &[Stamped],
    est_path: &Path,
    usage: Option<Usage>,
    time_per_sweep_s: Option<f64>,
    opts: &Bench3dOptions,
    note: Option<String>,
) -> Result<MethodRun> {
    let est = read_poses(est_path)?;
    let ate = evaluate_ate(truth, &est, &ate_options())?;
    let evo_rmse_m = match &opts.evo_ape {
        Some(evo) => match evo_rmse(evo, truth_path, est_path) {
            Ok(v) => Some(v),
            Err(e) => {
                eprintln!("bench 3d: {method}: evo_ape: {e}");
                None
            }
        },
        None => None,
    };
    Ok(MethodRun {
        method: method.into(),
        slug: slug.into(),
        settings,
        poses: est.len(),
        usage,
        time_per_sweep_s,
        ate_rmse_m: ate.rmse_m,
        ate_max_m: ate.max_m,
        ate_rot_deg: ate.rot_mean_deg,
        evo_rmse_m,
        picture: None,
        trajectory: est_path.to_path_buf(),
        note,
        reused_run: false,
    })
}

/// What a finished run records next to its outputs (`<slug>.usage.json`),
/// for `--reuse-runs`.
#[derive(Serialize, Deserialize, PartialEq)]
struct Recorded {
    settings: String,
    wall_s: f64,
    cpu_s: f64,
    peak_rss_mib: f64,
}

fn recorded_path(dir: &Path, slug: &str) -> PathBuf {
    dir.join(format!("{slug}.usage.json"))
}

/// The recorded usage of `slug`'s earlier run with `settings`, if reuse is on
/// and there is one (and its `output` exists).
fn reusable(
    dir: &Path,
    slug: &str,
    settings: &str,
    output: &Path,
    opts: &Bench3dOptions,
) -> Option<Usage> {
    if !opts.reuse_runs || !output.is_file() {
        return None;
    }
    let text = std::fs::read_to_string(recorded_path(dir, slug)).ok()?;
    let r: Recorded = serde_json::from_str(&text).ok()?;
    (r.settings == settings).then_some(Usage {
        wall_s: r.wall_s,
        cpu_s: r.cpu_s,
        peak_rss_mib: r.peak_rss_mib,
    })
}

fn record(dir: &Path, slug: &str, settings: &str, u: &Usage) -> Result<()> {
    dpslam::pipeline::write_json(
        &recorded_path(dir, slug),
        &Recorded {
            settings: settings.into(),
            wall_s: u.wall_s,
            cpu_s: u.cpu_s,
            peak_rss_mib: u.peak_rss_mib,
        },
    )
}

/// `dpslam map3d SWEEPS` (LiDAR only), measured.
fn run_dpslam(
    dir: &Path,
    truth_path: &Path,
    truth: &[Stamped],
    opts: &Bench3dOptions,
) -> Result<MethodRun> {
    let run = dir.join("dpslam");
    let key = format!(
        "map3d --particles {} --threads {:?}",
        opts.particles, opts.threads
    );
    let earlier = reusable(dir, "dpslam", &key, &run.join("trajectory.tum"), opts);
    let usage = match earlier {
        Some(u) => u,
        None => {
            std::fs::create_dir_all(&run).map_err(|e| Error::io(&run, e))?;
            let mut cmd = Command::new(&opts.mapper);
            cmd.arg("map3d")
                .arg(dir.join("sweeps"))
                .arg("--out")
                .arg(&run)
                .arg("--particles")
                .arg(opts.particles.to_string());
            if let Some(t) = opts.threads {
                cmd.arg("--threads").arg(t.to_string());
            }
            let u = run_measured(cmd, &dir.join("dpslam.log"))?;
            record(dir, "dpslam", &key, &u)?;
            u
        }
    };
    let json = run.join("run.json");
    let text = std::fs::read_to_string(&json).map_err(|e| Error::io(&json, e))?;
    let summary: serde_json::Value = serde_json::from_str(&text)
        .map_err(|e| Error::Invalid(format!("{}: {e}", json.display())))?;
    let per_sweep = summary["time_per_sweep_s"].as_f64();
    let mut notes = Vec::new();
    if let Some(n) = summary["proposal_fallbacks"].as_u64().filter(|n| *n > 0) {
        notes.push(format!("{n} sweeps whose match failed (prior kept)"));
    }
    if let Some(b) = summary["mean_beams_per_sweep"].as_f64() {
        notes.push(format!("{b:.0} beams per sweep after down-sampling"));
    }
    let threads = summary["threads"]
        .as_u64()
        .map_or(String::new(), |t| format!(", {t} threads"));
    let mut r = score(
        DPSLAM,
        "dpslam",
        format!(
            "{} particles, LiDAR only (no --poses){threads}",
            opts.particles
        ),
        truth_path,
        truth,
        &run.join("trajectory.tum"),
        Some(usage),
        per_sweep,
        opts,
        (!notes.is_empty()).then(|| notes.join("; ")),
    )?;
    r.reused_run = earlier.is_some();
    Ok(r)
}

/// `kiss_icp_pipeline SWEEPS` with its defaults, or with `voxel` m voxels
/// (`--config` with `mapping.voxel_size`), measured; its KITTI poses
/// rewritten as TUM stamped with the sweep index.
#[allow(clippy::too_many_arguments)]
fn run_kiss(
    exe: &Path,
    (method, slug, voxel): (&str, &str, Option<f64>),
    dir: &Path,
    truth_path: &Path,
    truth: &[Stamped],
    opts: &Bench3dOptions,
) -> Result<MethodRun> {
    let tum = dir.join(format!("{slug}.tum"));
    let settings = match voxel {
        None => "defaults (`kiss_icp_pipeline SWEEPS`)".to_string(),
        Some(v) => format!(
            "defaults but `mapping: voxel_size: {v}` (`kiss_icp_pipeline --config kiss.yaml SWEEPS`)"
        ),
    };
    let note = Some(
        "time per sweep: process wall time over the sweeps (Python start-up included)".to_string(),
    );
    if let Some(u) = reusable(dir, slug, &settings, &tum, opts) {
        let n = read_poses(&tum)?.len().max(1);
        let mut r = score(
            method,
            slug,
            settings,
            truth_path,
            truth,
            &tum,
            Some(u),
            Some(u.wall_s / n as f64),
            opts,
            note,
        )?;
        r.reused_run = true;
        return Ok(r);
    }
    let work = dir.join(slug);
    if work.exists() {
        std::fs::remove_dir_all(&work).map_err(|e| Error::io(&work, e))?;
    }
    std::fs::create_dir_all(&work).map_err(|e| Error::io(&work, e))?;
    // Absolute: the pipeline runs in `work` and resolves its out dir there.
    let work = std::fs::canonicalize(&work).map_err(|e| Error::io(&work, e))?;
    let results = work.join("results");
    let sweeps = std::fs::canonicalize(dir.join("sweeps")).map_err(|e| Error::io(dir, e))?;
    let mut cmd = Command::new(exe);
    if let Some(v) = voxel {
        let yaml = work.join("kiss.yaml");
        dpslam::pipeline::write_atomic(&yaml, format!("mapping:\n  voxel_size: {v}\n").as_bytes())?;
        cmd.arg("--config").arg(&yaml);
    }
    cmd.arg(&sweeps)
        .current_dir(&work)
        .env("kiss_icp_out_dir", &results);
    let usage = run_measured(cmd, &dir.join(format!("{slug}.log")))?;
    record(dir, slug, &settings, &usage)?;
    let latest = results.join("latest");
    let kitti = std::fs::read_dir(&latest)
        .map_err(|e| Error::io(&latest, e))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .find(|p| {
            p.file_name()
                .and_then(|n| n.to_str())
                .is_some_and(|n| n.ends_with("_poses_kitti.txt"))
        })
        .ok_or_else(|| Error::Invalid(format!("no *_poses_kitti.txt in {}", latest.display())))?;
    // Frame k of the KITTI file is sweep k, stamped k s like the truth.
    let poses = read_poses(&kitti)?;
    write_stamped(&tum, &poses)?;
    let n = poses.len().max(1);
    score(
        method,
        slug,
        settings,
        truth_path,
        truth,
        &tum,
        Some(usage),
        Some(usage.wall_s / n as f64),
        opts,
        note,
    )
}

/// Runs every method on one sequence and draws the pictures.
pub fn run_sequence(seq: &Sequence, opts: &Bench3dOptions) -> Result<SequenceResult> {
    let dir = opts.out.join(&seq.name);
    std::fs::create_dir_all(&dir).map_err(|e| Error::io(&dir, e))?;
    eprintln!("bench 3d: {}: simulating (or reusing) ...", seq.name);
    let (path_length_m, points, reused) = ensure_sequence(seq, &dir)?;
    let truth_path = dir.join("truth.tum");
    let truth = read_tum(&truth_path)?;
    let mut runs = Vec::new();
    let mut not_run = Vec::new();
    eprintln!("bench 3d: {}: dpslam map3d ...", seq.name);
    match run_dpslam(&dir, &truth_path, &truth, opts) {
        Ok(r) => runs.push(r),
        Err(e) => not_run.push(NotRun {
            method: DPSLAM.into(),
            reason: format!("run failed: {e}"),
        }),
    }
    for variant in KISS_VARIANTS {
        match &opts.kiss_icp {
            Some(exe) => {
                eprintln!("bench 3d: {}: {} ...", seq.name, variant.0);
                match run_kiss(exe, variant, &dir, &truth_path, &truth, opts) {
                    Ok(r) => runs.push(r),
                    Err(e) => not_run.push(NotRun {
                        method: variant.0.into(),
                        reason: format!("run failed: {e}"),
                    }),
                }
            }
            None => not_run.push(NotRun {
                method: variant.0.into(),
                reason: "`kiss_icp_pipeline` is not on the PATH".into(),
            }),
        }
    }
    runs.push(score(
        ODOMETRY,
        "odometry",
        "the simulated wheel odometry (an input, no run)".into(),
        &truth_path,
        &truth,
        &dir.join("odometry.tum"),
        None,
        None,
        opts,
        None,
    )?);
    eprintln!("bench 3d: {}: pictures ...", seq.name);
    let points_for_pictures = picture_points(&dir, seq)?;
    let pictures = opts.docs.join("results-3d");
    std::fs::create_dir_all(&pictures).map_err(|e| Error::io(&pictures, e))?;
    for r in &mut runs {
        let name = format!("{}-{}.png", seq.name, r.slug);
        let est = read_poses(&r.trajectory)?;
        write_picture(&pictures.join(&name), &truth, &est, &points_for_pictures)?;
        r.picture = Some(format!("results-3d/{name}"));
    }
    Ok(SequenceResult {
        name: seq.name.clone(),
        description: seq.description.clone(),
        command: seq.command.clone(),
        sweeps: truth.len(),
        points_per_sweep: points as f64 / truth.len().max(1) as f64,
        path_length_m,
        reused,
        runs,
        not_run,
    })
}

/// Runs every sequence, then writes `<docs>/RESULTS-3D.md` and
/// `<out>/results-3d.json`. A sequence that fails is an error (its method
/// failures are rows of the report instead).
pub fn run_bench3d(opts: &Bench3dOptions) -> Result<Bench3dReport> {
    if opts.sequences.is_empty() {
        return Err(Error::Config("bench 3d: no sequence to run".into()));
    }
    let start = Instant::now();
    let commit = super::accuracy::source_commit();
    let mut sequences = Vec::new();
    for seq in &opts.sequences {
        let r = run_sequence(seq, opts)?;
        for m in &r.runs {
            eprintln!(
                "bench 3d: {}: {}: ATE {:.3} m, {:.2}°{}",
                r.name,
                m.method,
                m.ate_rmse_m,
                m.ate_rot_deg,
                m.usage.map_or(String::new(), |u| format!(
                    ", {:.1} CPU-s, {:.0} MiB",
                    u.cpu_s, u.peak_rss_mib
                ))
            );
        }
        sequences.push(r);
    }
    let report = Bench3dReport {
        command: opts.command.clone(),
        version: match commit {
            Some(c) => format!("{} (commit {c})", env!("CARGO_PKG_VERSION")),
            None => env!("CARGO_PKG_VERSION").into(),
        },
        cores: std::thread::available_parallelism().map_or(1, |n| n.get()),
        particles: opts.particles,
        total_wall_s: start.elapsed().as_secs_f64(),
        sequences,
    };
    std::fs::create_dir_all(&opts.out).map_err(|e| Error::io(&opts.out, e))?;
    dpslam::pipeline::write_json(&opts.out.join("results-3d.json"), &report)?;
    std::fs::create_dir_all(&opts.docs).map_err(|e| Error::io(&opts.docs, e))?;
    dpslam::pipeline::write_atomic(
        &opts.docs.join("RESULTS-3D.md"),
        results3d_markdown(&report).as_bytes(),
    )?;
    Ok(report)
}

fn fmt(v: Option<f64>, decimals: usize) -> String {
    match v {
        Some(x) if x.is_finite() => format!("{x:.decimals$}"),
        _ => "–".into(),
    }
}

/// Column titles of the per-sequence tables.
pub const COLUMNS_3D: [&str; 9] = [
    "method",
    "time per sweep s (wall)",
    "CPU-s (all sweeps)",
    "CPU-s per sweep",
    "peak RSS MiB",
    "ATE RMSE m (SE(3))",
    "ATE max m",
    "rotation error ° (mean)",
    "evo_ape RMSE m",
];

/// One table row per run.
pub fn sequence_table(s: &SequenceResult) -> String {
    let rows: Vec<Vec<String>> = s
        .runs
        .iter()
        .map(|r| {
            vec![
                r.method.clone(),
                fmt(r.time_per_sweep_s, 3),
                fmt(r.usage.map(|u| u.cpu_s), 1),
                fmt(r.usage.map(|u| u.cpu_s / s.sweeps.max(1) as f64), 3),
                fmt(r.usage.map(|u| u.peak_rss_mib), 0),
                format!("{:.3}", r.ate_rmse_m),
                format!("{:.3}", r.ate_max_m),
                format!("{:.2}", r.ate_rot_deg),
                fmt(r.evo_rmse_m, 3),
            ]
        })
        .collect();
    markdown_table(&COLUMNS_3D, &rows)
}

/// dpslam's ATE over that of the KISS-ICP row `kiss` on `s`, where both ran.
pub fn dpslam_over(s: &SequenceResult, kiss: &str) -> Option<f64> {
    Some(s.run(DPSLAM)?.ate_rmse_m / s.run(kiss)?.ate_rmse_m)
}

/// `docs/RESULTS-3D.md`.
pub fn results3d_markdown(r: &Bench3dReport) -> String {
    let mut md = String::new();
    md += "# 3-D results: dpslam map3d, KISS-ICP and odometry on simulated sequences\n\n";
    md += "Written by `dpslam-bench 3d` (the harness, [`harness/src/bench3d.rs`](../harness/src/bench3d.rs)); \
           do not edit by hand.\n\n";
    md += &format!(
        "- Command: `{}`\n- Source: dpslam {}\n- Machine: {} cores seen (shared with other work: \
         compare CPU-s and ratios rather than wall times)\n- dpslam: `map3d` from the sweeps alone \
         (no odometry, constant-velocity prior), {} particles, default configuration\n\
         - KISS-ICP: `kiss_icp_pipeline SWEEPS` with its defaults, on the same KITTI `.bin` sweeps\n\
         - odometry: the simulator's noisy wheel odometry (`odometry.tum`), not a run\n\
         - ATE: `dpslam eval ate --se3` (SE(3) alignment, then RMSE of positions; rotation: mean angle); \
         evo_ape column: `evo_ape tum truth.tum est.tum -a` on the same files, an independent check\n\
         - Peak RSS and CPU-s (user + system) of each method's own process (`wait4`)\n\
         - Whole benchmark: {:.0} s wall\n\n",
        r.command, r.version, r.cores, r.particles, r.total_wall_s
    );
    md += "Pictures: top-down, everything moved onto the truth by the SE(3) alignment of the ATE; \
           grey: the points of every few sweeps from 0.3 m above the floor to 1.5 m above the sensor, \
           placed with the method's trajectory (doubled walls = drift); red: truth; blue: the method's \
           trajectory.\n\n";
    for s in &r.sequences {
        md += &format!("## {}\n\n", s.name);
        md += &format!(
            "{}: {} sweeps, {:.0} points per sweep on average, {:.1} m driven. Simulated with \
             `{}`{}.\n\n",
            s.description,
            s.sweeps,
            s.points_per_sweep,
            s.path_length_m,
            s.command,
            if s.reused {
                " (files of an earlier run reused)"
            } else {
                ""
            }
        );
        md += &sequence_table(s);
        md += "\n";
        for kiss in [KISS_ICP, KISS_ICP_FINE] {
            if let Some(ratio) = dpslam_over(s, kiss) {
                md += &format!(
                    "dpslam's ATE is **{ratio:.3} ×** that of {kiss} ({}).\n\n",
                    if ratio <= 0.5 {
                        "at most ½: issue 13's bar is met"
                    } else {
                        "more than ½: issue 13's bar is not met"
                    }
                );
            }
        }
        for m in &s.runs {
            md += &format!("- {}: {}", m.method, m.settings);
            if let Some(n) = &m.note {
                md += &format!("; {n}");
            }
            if m.reused_run {
                md += "; trajectory and measurements of an earlier bench run (`--reuse-runs`)";
            }
            md += "\n";
        }
        for n in &s.not_run {
            md += &format!("- {}: not run: {}\n", n.method, n.reason);
        }
        md += "\n";
        let pics: Vec<&MethodRun> = s.runs.iter().filter(|m| m.picture.is_some()).collect();
        if !pics.is_empty() {
            let header: Vec<&str> = pics.iter().map(|m| m.method.as_str()).collect();
            let row: Vec<String> = pics
                .iter()
                .map(|m| {
                    format!(
                        "![{} on {}]({})",
                        m.method,
                        s.name,
                        m.picture.as_deref().unwrap_or("")
                    )
                })
                .collect();
            md += &markdown_table(&header, &[row]);
            md += "\n";
        }
    }
    md
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn evo_output_is_parsed() {
        let text = "APE w.r.t. translation part (m)\n(with SE(3) Umeyama alignment)\n\n\
                    \tmax\t0.021\n\tmean\t0.005\n\tmedian\t0.004\n\tmin\t0.000\n\
                    \trmse\t0.006123\n\tsse\t0.007\n\tstd\t0.003\n";
        assert_eq!(parse_evo_rmse(text), Some(0.006123));
        assert_eq!(parse_evo_rmse("nothing"), None);
    }

    #[test]
    fn a_measured_process_reports_cpu_and_memory() {
        let dir = tempfile::tempdir().unwrap();
        let mut cmd = Command::new("sh");
        cmd.args([
            "-c",
            "i=0; while [ $i -lt 20000 ]; do i=$((i+1)); done; echo done",
        ]);
        let u = run_measured(cmd, &dir.path().join("log")).unwrap();
        assert!(
            u.cpu_s > 0.0 && u.peak_rss_mib > 0.1 && u.wall_s > 0.0,
            "{u:?}"
        );
        let mut bad = Command::new("sh");
        bad.args(["-c", "echo oops; exit 3"]);
        let e = run_measured(bad, &dir.path().join("log2")).unwrap_err();
        assert!(e.to_string().contains("oops"), "{e}");
    }
}
