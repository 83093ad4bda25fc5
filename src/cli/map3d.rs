//! `dpslam map3d`: 3-D voxel DP-SLAM with 6-DoF poses on a directory of sweeps.

use dpslam::config::Config;
use dpslam::pipeline::map3d::{DEFAULT_PARTICLES_3D, Map3dOptions, run_map3d_observed};
use std::path::{Path, PathBuf};

/// The sweeps mapped when none are given: the 3-D simulator's sequence shipped in `data/`.
pub const DEFAULT_INPUT: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/data/sim3d/sweeps");
/// The odometry prior of the shipped simulated sequence.
pub const DEFAULT_ODOMETRY: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/data/sim3d/odometry.tum");

/// A folder in the temporary folder, removed when dropped.
struct TempDir(PathBuf);

impl Drop for TempDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

#[derive(clap::Args, Debug)]
pub struct Map3dArgs {
    /// Directory of sweeps (.pcd .ply .bin .xyz .txt .vtk .3d), mapped in
    /// file-name order, or a ROS bag (.bag, .mcap, .db3 or a ROS 2 bag
    /// directory) of sensor_msgs/PointCloud2 [default: the shipped simulated
    /// sequence, with its odometry]
    pub input: Option<PathBuf>,
    /// Output folder (map.ply, trajectory.tum, run.json, config.toml, points.ply)
    #[arg(long)]
    pub out: PathBuf,
    /// Prior poses, one per sweep (TUM `t x y z qx qy qz qw` or KITTI 3×4)
    #[arg(long)]
    pub poses: Option<PathBuf>,
    /// Particles [default: 20, or the config file's `filter.particles`]
    #[arg(long, allow_negative_numbers = true, value_parser = super::map2d::parse_count)]
    pub particles: Option<usize>,
    #[command(flatten)]
    pub run: super::map2d::RunArgs,
    #[command(flatten)]
    pub topics: super::map2d::TopicArgs,
    /// Also write points.ply: the raw points registered with the trajectory
    #[arg(long)]
    pub points: bool,
    /// Where scan likelihoods are computed (gpu needs a build with --features gpu)
    #[arg(long, value_enum, default_value_t = dpslam::backend::Backend::Cpu)]
    pub backend: dpslam::backend::Backend,
}

/// Whether the config file sets `filter.particles` itself (the 3-D default
/// applies only when neither it nor the command line does).
fn file_sets_particles(file: Option<&PathBuf>) -> dpslam::Result<bool> {
    let Some(p) = file else { return Ok(false) };
    let text = std::fs::read_to_string(p).map_err(|e| dpslam::Error::io(p, e))?;
    // The file already parsed as a `Config` in `build_config`; a plain TOML
    // table tells which keys it spells out.
    let v: toml::Table =
        toml::from_str(&text).map_err(|e| dpslam::Error::in_file(p, e.to_string()))?;
    Ok(v.get("filter")
        .and_then(|f| f.as_table())
        .is_some_and(|f| f.contains_key("particles")))
}

/// The configuration of a 3-D run: file, then flags, then the 3-D default
/// particle count where neither set one.
pub fn build_config_3d(a: &Map3dArgs) -> dpslam::Result<Config> {
    let mut cfg = super::map2d::build_config(&a.run, a.particles)?;
    if a.particles.is_none() && !file_sets_particles(a.run.config.as_ref())? {
        cfg.filter.particles = DEFAULT_PARTICLES_3D;
    }
    a.topics.apply(&mut cfg);
    Ok(cfg)
}

pub fn run(a: Map3dArgs) -> dpslam::Result<()> {
    let cfg = build_config_3d(&a)?;
    dpslam::pipeline::preflight::check_memory(
        &cfg,
        dpslam::pipeline::preflight::available_memory(),
    )?;
    dpslam::pipeline::preflight::check_out_dir(&a.out)?;
    // Without the source tree (a moved or installed binary), the shipped
    // sequence is simulated again: the same configuration and seed give
    // the same files (tests/sim3d.rs checks it byte for byte).
    let _regenerated;
    let (input, poses) = match &a.input {
        Some(dir) => (dir.clone(), a.poses.clone()),
        None if !Path::new(DEFAULT_INPUT).is_dir() => {
            let dir = std::env::temp_dir().join(format!("dpslam-sim3d-{}", std::process::id()));
            eprintln!(
                "map3d: {} not found: simulating the default sequence into {}",
                DEFAULT_INPUT,
                dir.display()
            );
            let cfg3 = dpslam::sim::sim3d::Sim3dConfig::embedded();
            let written = dpslam::sim::sim3d::write_sim3d(&dir, &cfg3, 1);
            _regenerated = TempDir(dir.clone());
            written?;
            (
                dir.join("sweeps"),
                a.poses.clone().or(Some(dir.join("odometry.tum"))),
            )
        }
        None => {
            let odo = PathBuf::from(DEFAULT_ODOMETRY);
            let poses = a
                .poses
                .clone()
                .or_else(|| Path::new(&odo).exists().then_some(odo));
            (PathBuf::from(DEFAULT_INPUT), poses)
        }
    };
    let opts = Map3dOptions {
        points: a.points,
        backend: a.backend,
    };
    let mut progress = super::progress::Progress::new("map3d");
    let s = run_map3d_observed(
        &input,
        &a.out,
        &cfg,
        poses.as_deref(),
        &opts,
        &mut |done, total| progress.update(done, total),
    )?;
    progress.finish();
    super::progress::print_backend_note(&s.backend);
    super::progress::print_warnings(&s.warnings);
    println!(
        "map3d: {} sweeps, {} particles, {:.0} beams/sweep, {:.2} s/sweep, {:.1} s wall, \
         peak {:.0} MiB, {} occupied voxels -> {}",
        s.sweeps,
        s.particles,
        s.mean_beams_per_sweep,
        s.time_per_sweep_s,
        s.wall_time_s,
        s.peak_memory_mib.unwrap_or(f64::NAN),
        s.occupied_voxels,
        a.out.display()
    );
    Ok(())
}
