//! Drives 2-D DP-SLAM scan by scan, as robot code would: read a log (the
//! embedded simulated loop by default), hand each laser scan and its
//! odometry pose to [`Slam2d::add_scan`], print the online estimate as it
//! goes (stderr), and at the end the whole corrected trajectory in TUM form
//! (stdout), which equals `dpslam map2d`'s `trajectory_filter.tum` for the
//! same log and seed (its `trajectory.tum` is that trajectory after the
//! final alignment, [`dpslam::refine`]).
//!
//! ```sh
//! cargo run --release --example online2d > trajectory.tum
//! cargo run --release --example online2d -- LOG [PARTICLES] > trajectory.tum
//! ```

use dpslam::config::Config;
use dpslam::geometry::{Pose, xyt};
use dpslam::io::log2d::open_log2d;
use dpslam::io::tum::tum_line;
use dpslam::pipeline::map2d::{RangeSettings, sensor_mount};
use dpslam::slam::Slam2d;
use std::path::PathBuf;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut args = std::env::args().skip(1);
    let log = args.next().map(PathBuf::from).unwrap_or_else(|| {
        PathBuf::from(concat!(env!("CARGO_MANIFEST_DIR"), "/data/sim2d/sim2d.clf"))
    });
    let mut cfg = Config::default();
    if let Some(n) = args.next() {
        cfg.filter.particles = n.parse()?;
    }

    let mut slam = Slam2d::new(cfg.clone())?;
    // What `map2d` does before mapping: survey the whole log for the "no
    // return" threshold (readings that contradict the declared maximum) and
    // the default usable range (raised outdoors).
    RangeSettings::of_log(&log, &cfg)?.apply(&mut slam);
    let reader = open_log2d(&log)?;
    slam.set_mount(sensor_mount(&cfg, reader.format()));

    for item in reader {
        let scan = item?;
        let stamp = scan.timestamp.unwrap_or(slam.scans() as f64);
        let estimate = slam.add_scan(stamp, scan.odometry, &scan.as_ranges())?;
        if estimate.processed && estimate.index % 25 == 0 {
            let (x, y, th) = xyt(&estimate.pose);
            eprintln!(
                "scan {:5} t {:10.3}: x {x:8.3} m, y {y:8.3} m, θ {:7.2}°",
                estimate.index,
                estimate.stamp,
                th.to_degrees()
            );
        }
    }
    slam.finish();
    for (t, pose) in slam.trajectory()? {
        println!("{}", tum_line(t, &Pose::<2>::to_tum(&pose)));
    }
    Ok(())
}
