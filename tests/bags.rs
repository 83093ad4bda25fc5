//! ROS bags in: the readers against the real bags of `../shared/datasets/ros`
//! (ROS 1 uncompressed, bz2 and lz4; MCAP with zstd chunks; rosbag2
//! sqlite3), checked against the CARMEN log rebuilt from the same recording
//! and against each other; point clouds against the PCDs they were made
//! from; and hostile bags made from the real ones in a temporary folder.

use dpslam::geometry::{Pose2, xyt};
use dpslam::io::bag::scans2d::{BagScans2d, TopicChoice};
use dpslam::io::bag::sweeps3d::SweepSource;
use dpslam::io::bag::{Bag, Storage};
use dpslam::io::log2d::{LogFormat, OdometryPairing, open_log2d, open_log2d_with};
use dpslam::io::sweeps::read_sweep;
use dpslam::scan::LaserScan2d;
use std::f64::consts::PI;
use std::path::{Path, PathBuf};
use std::process::Command;

fn ds(rel: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../shared/datasets")
        .join(rel)
}

fn scans(path: &Path) -> Vec<LaserScan2d> {
    open_log2d(path)
        .unwrap_or_else(|e| panic!("{}: {e}", path.display()))
        .collect::<dpslam::Result<Vec<_>>>()
        .unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

/// How far apart two odometry poses are: (metres, |radians|).
fn odometry_gap(a: &Pose2, b: &Pose2) -> (f64, f64) {
    let d = a.inverse() * b;
    (d.translation.vector.norm(), d.rotation.angle().abs())
}

/// A CARMEN log's scans with `input.odometry = "retimed"`.
fn retimed(path: &Path) -> Vec<LaserScan2d> {
    open_log2d(path)
        .unwrap()
        .with_odometry(OdometryPairing::Retimed)
        .collect::<dpslam::Result<Vec<_>>>()
        .unwrap()
}

/// The first error reading all scans of `path` with `choice`.
fn error_of(path: &Path, choice: &TopicChoice) -> String {
    match open_log2d_with(path, choice) {
        Err(e) => e.to_string(),
        Ok(r) => {
            for s in r {
                if let Err(e) = s {
                    return e.to_string();
                }
            }
            panic!("{} read without error", path.display())
        }
    }
}

fn same_scans(a: &[LaserScan2d], b: &[LaserScan2d], what: &str) {
    assert_eq!(a.len(), b.len(), "{what}: scan counts");
    for (i, (x, y)) in a.iter().zip(b).enumerate() {
        assert_eq!(x.timestamp, y.timestamp, "{what}: scan {i} stamp");
        assert_eq!(x.ranges, y.ranges, "{what}: scan {i} ranges");
        assert_eq!(x.odometry, y.odometry, "{what}: scan {i} odometry");
        assert_eq!(x.angle_min, y.angle_min, "{what}: scan {i}");
        assert_eq!(x.angle_increment, y.angle_increment, "{what}: scan {i}");
    }
}

#[test]
fn aces_bag_lists_its_topics_and_matches_the_carmen_log_of_the_same_recording() {
    let path = ds("ros/ros1/aces.bag");
    let bag = Bag::open(&path).unwrap();
    assert_eq!(bag.storage, Storage::Ros1);
    let topic = |n: &str| {
        let t = &bag.topics[bag.topic_index(n).unwrap()];
        (t.msg_type.as_str(), t.count)
    };
    assert_eq!(topic("/scan"), ("sensor_msgs/LaserScan", 7374));
    assert_eq!(topic("/odom"), ("nav_msgs/Odometry", 7375));
    assert_eq!(topic("/tf_static").0, "tf2_msgs/TFMessage");

    let r = open_log2d(&path).unwrap();
    assert_eq!(r.format(), LogFormat::RosBag);
    assert_eq!(r.sensor_offset().map(|p| xyt(&p)), Some((0.0, 0.0, 0.0)));
    let b = scans(&path);
    let c = retimed(&ds("carmen/aces-raw/aces-raw.clf.gz"));
    assert_eq!(b.len(), 7374);
    assert_eq!(c.len(), 7374);
    let mut kept = 0;
    for (i, (x, y)) in b.iter().zip(&c).enumerate() {
        assert_eq!(x.ranges.len(), 180);
        // Header stamps are the log's ipc timestamps (µs in the log).
        let (tx, ty) = (x.timestamp.unwrap(), y.timestamp.unwrap());
        assert!((tx - ty).abs() < 1e-6, "scan {i}: {tx} vs {ty}");
        // Beam angles: the bag spans -90° to +90° in 179 steps; the CARMEN
        // convention for 180 FLASER beams is 1° steps from -90°.
        assert!((x.angle_min - y.angle_min).abs() < 1e-6, "scan {i}");
        assert!((x.angle_increment - PI / 179.0).abs() < 1e-7, "scan {i}");
        assert!((y.angle_increment - PI / 180.0).abs() < 1e-12, "scan {i}");
        for (k, (&u, &v)) in x.ranges.iter().zip(&y.ranges).enumerate() {
            if x.is_no_return(k) {
                // the bag's range_max (50 m) marks no return
                assert!(v >= 50.0 || !v.is_finite(), "scan {i} beam {k}: {u} vs {v}");
            } else {
                assert_eq!(u, v, "scan {i} beam {k}");
            }
        }
        // The bag interpolates /odom at each scan's stamp; the log's FLASER
        // lines carry the logger's pairing (mostly the latest ODOM, up to
        // 0.25 s older), which `input.odometry = "retimed"` re-times from
        // the same ODOM stream.
        // Where the logged pairing is off the stream's path around the
        // stamp (25 scans), the line is kept.
        let (dx, dth) = odometry_gap(&x.odometry, &y.odometry);
        if dx > 1e-6 || dth > 1e-6 {
            kept += 1;
        }
    }
    assert!(kept <= 30, "{kept} scans' odometry differs from the bag's");
    let logged: Vec<_> = scans(&ds("carmen/aces-raw/aces-raw.clf.gz"))
        .into_iter()
        .map(|s| s.odometry)
        .collect();
    let gap: f64 = logged
        .iter()
        .zip(&c)
        .map(|(l, r)| odometry_gap(l, &r.odometry).0)
        .sum::<f64>()
        / logged.len() as f64;
    assert!(
        gap > 0.01 && gap < 0.05,
        "re-timing moves the logged odometry by {gap} m on average"
    );
}

/// With `input.odometry = "retimed"`, raw logs' laser lines, paired from
/// their own ODOM stream, are re-timed; corrected logs' poses come from a SLAM run, not from their
/// ODOM lines, and are kept; a log without ODOM lines is kept.
#[test]
fn raw_carmen_logs_are_re_timed_corrected_ones_are_not() {
    for (log, retimed) in [
        ("carmen/aces-raw/aces-raw.clf.gz", true),
        ("carmen/fr079-raw/fr079-raw.clf.gz", true),
        ("carmen/aces/aces-corrected.log.gz", false),
        ("carmen/fr079/freiburg-079-corrected.log.gz", false),
        ("carmen/mit-csail/csail-corrected.log.gz", false),
        ("carmen/other-corrected/seattle-corrected.log.gz", false),
        ("carmen/mit-csail/mit-csail.clf", false),
    ] {
        let mut r = open_log2d(&ds(log))
            .unwrap()
            .with_odometry(OdometryPairing::Retimed);
        assert!(!r.retimed(), "{log}: decided before the first scan");
        r.next().unwrap().unwrap();
        assert_eq!(r.retimed(), retimed, "{log}");
    }
    // The fr079 bag interpolates the same stream.
    let b = scans(&ds("ros/ros1/fr079.bag"));
    let c = retimed(&ds("carmen/fr079-raw/fr079-raw.clf.gz"));
    let differ = b
        .iter()
        .zip(&c)
        .filter(|(x, y)| odometry_gap(&x.odometry, &y.odometry).0 > 1e-6)
        .count();
    // The first scan precedes the first ODOM; 21 stamps disagree with the
    // logger's pairing by 0.2–0.5 s and keep it.
    assert!(
        differ <= 25,
        "{differ} of fr079's scans differ from the bag's odometry"
    );
}

#[test]
fn example_configs_give_the_converted_bags_their_logs_geometry() {
    let example = |name: &str| {
        let p = Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("docs/examples")
            .join(name);
        dpslam::config::Config::from_toml_file(&p).unwrap_or_else(|e| panic!("{e}"))
    };
    for (cfg, bag, log) in [
        (
            example("aces-bag.toml"),
            "ros/ros1/aces.bag",
            "carmen/aces-raw/aces-raw.clf.gz",
        ),
        (
            example("fr079-bag.toml"),
            "ros/ros1/fr079.bag",
            "carmen/fr079-raw/fr079-raw.clf.gz",
        ),
    ] {
        let b = open_log2d(&ds(bag)).unwrap().next().unwrap().unwrap();
        let mut c = open_log2d(&ds(log)).unwrap();
        let first = c.next().unwrap().unwrap();
        // The reader `map2d` (and the bench rig) opens applies them.
        let read = dpslam::pipeline::map2d::open_configured(&ds(bag), &cfg)
            .unwrap()
            .next()
            .unwrap()
            .unwrap();
        let (min, inc) = (read.angle_min, read.angle_increment);
        assert!(
            (inc - b.angle_increment).abs() > 1e-5,
            "{bag}: the bag states another step"
        );
        assert!((min - first.angle_min).abs() < 1e-6, "{bag}: {min}");
        assert!((inc - first.angle_increment).abs() < 1e-12, "{bag}: {inc}");
        if let Some([x, y, th]) = cfg.motion2d.sensor_offset {
            let (lx, ly, lth) = xyt(&c.sensor_offset().unwrap());
            assert_eq!((x, y, th), (lx, ly, lth), "{bag}: the log's laser mount");
        }
    }
}

#[test]
fn compressed_ros1_mcap_and_sqlite3_bags_hold_the_same_scans() {
    let full = scans(&ds("ros/ros1/aces.bag"));
    for rel in [
        "ros/ros1/aces-head-bz2.bag",
        "ros/ros1/aces-head-lz4.bag",
        "ros/ros2/aces-head-sqlite3",
        "ros/ros2/aces-head-sqlite3/aces-head-sqlite3.db3",
    ] {
        // The heads end at their 1000th scan: odometry after it was cut, so
        // that scan's odometry is the last message's, not interpolated.
        let s = scans(&ds(rel));
        assert_eq!(s.len(), 1000, "{rel}");
        same_scans(&s[..999], &full[..999], rel);
    }
    let mcap_dir = ds("ros/ros2/aces-mcap");
    assert_eq!(Bag::open(&mcap_dir).unwrap().storage, Storage::Mcap);
    same_scans(&scans(&mcap_dir), &full, "aces-mcap");
    same_scans(
        &scans(&mcap_dir.join("aces-mcap.mcap")),
        &full,
        "aces-mcap.mcap",
    );
}

#[test]
fn fr079_bag_gives_360_beams_and_the_tf_laser_mount() {
    let path = ds("ros/ros1/fr079.bag");
    let r = BagScans2d::open(&path, &TopicChoice::default()).unwrap();
    // The bag's tf_static says +0.04 m (the dataset README: the sign is wrong).
    let (x, y, th) = xyt(&r.sensor_offset().unwrap());
    assert!((x - 0.04).abs() < 1e-9 && y.abs() < 1e-9 && th.abs() < 1e-9);
    assert_eq!(
        r.odometry_source(),
        "/odom (nav_msgs/Odometry of base_link)"
    );
    let s: Vec<_> = r.collect::<dpslam::Result<_>>().unwrap();
    assert_eq!(s.len(), 4934);
    assert!(s.iter().all(|s| s.ranges.len() == 360));
    let c = scans(&ds("carmen/fr079-raw/fr079-raw.clf.gz"));
    assert_eq!(c.len(), 4934);
    for (i, (a, b)) in s.iter().zip(&c).enumerate() {
        assert!(
            (a.timestamp.unwrap() - b.timestamp.unwrap()).abs() < 1e-6,
            "scan {i}"
        );
    }
}

#[test]
fn odometry_from_tf_when_the_odometry_topic_is_not_used() {
    // --odom-topic /tf: odom -> base_link from tf gives the same poses as /odom.
    let path = ds("ros/ros1/aces-head-lz4.bag");
    let choice = TopicChoice {
        odom_topic: Some("/tf".into()),
        ..Default::default()
    };
    let r = BagScans2d::open(&path, &choice).unwrap();
    assert_eq!(r.odometry_source(), "tf odom -> base_link");
    let a: Vec<_> = r.collect::<dpslam::Result<_>>().unwrap();
    let b = scans(&path);
    let worst = a
        .iter()
        .zip(&b)
        .map(|(x, y)| odometry_gap(&x.odometry, &y.odometry).0)
        .fold(0.0, f64::max);
    assert!(worst < 1e-6, "{worst}");
}

#[test]
fn fast_gicp_bags_hold_the_pcd_points() {
    let pcds = [
        read_sweep(&ds("3d/fast_gicp/251370668.pcd")).unwrap(),
        read_sweep(&ds("3d/fast_gicp/251371071.pcd")).unwrap(),
    ];
    for rel in ["ros/ros1/fast_gicp.bag", "ros/ros2/fast_gicp-mcap"] {
        let src = SweepSource::open(&ds(rel), &TopicChoice::default()).unwrap();
        assert_eq!(src.len(), 2, "{rel}");
        assert_eq!(src.stamp(0), Some(1000.0));
        assert_eq!(src.stamp(1), Some(1001.0));
        for (i, pcd) in pcds.iter().enumerate() {
            let s = src.read(i).unwrap();
            assert_eq!(s.points, pcd.points, "{rel} cloud {i}");
            assert!(s.prior.is_none(), "no odometry in {rel}");
        }
    }
}

#[test]
fn ambiguous_or_wrong_topics_are_errors_listing_the_bags_topics() {
    let path = ds("ros/ros1/aces-head-lz4.bag");
    let wrong = TopicChoice {
        scan_topic: Some("/odom".into()),
        ..Default::default()
    };
    let e = error_of(&path, &wrong);
    assert!(
        e.contains("aces-head-lz4.bag")
            && e.contains("topic /odom (--scan-topic) is nav_msgs/Odometry")
            && e.contains("/scan  sensor_msgs/LaserScan  (1000 messages)"),
        "{e}"
    );
    let missing = TopicChoice {
        scan_topic: Some("/base_scan".into()),
        ..Default::default()
    };
    let e = error_of(&path, &missing);
    assert!(
        e.contains("no topic /base_scan") && e.contains("/tf_static"),
        "{e}"
    );
    // A point-cloud bag has no LaserScan topic.
    let e = error_of(&ds("ros/ros1/fast_gicp.bag"), &TopicChoice::default());
    assert!(
        e.contains("no laser scan topic") && e.contains("sensor_msgs/PointCloud2"),
        "{e}"
    );
}

// ---- hostile bags, made from the real ones ------------------------------

fn copy_to(dir: &Path, src: &Path, name: &str) -> PathBuf {
    let p = dir.join(name);
    std::fs::copy(src, &p).unwrap();
    let mut perm = std::fs::metadata(&p).unwrap().permissions();
    #[allow(clippy::permissions_set_readonly_false)]
    perm.set_readonly(false);
    std::fs::set_permissions(&p, perm).unwrap();
    p
}

fn truncated(dir: &Path, src: &Path, name: &str, keep: f64) -> PathBuf {
    let bytes = std::fs::read(src).unwrap();
    let p = dir.join(name);
    std::fs::write(&p, &bytes[..(bytes.len() as f64 * keep) as usize]).unwrap();
    p
}

/// Flips 64 bytes inside a compressed chunk past the middle of the file:
/// for MCAP, the middle of the first chunk record (opcode 6) there; for
/// ROS 1 bags the middle of the file (chunks are nearly all of it).
fn corrupted(dir: &Path, src: &Path, name: &str) -> PathBuf {
    let mut bytes = std::fs::read(src).unwrap();
    let mut mid = bytes.len() / 2;
    if bytes.starts_with(b"\x89MCAP") {
        let mut p = 8;
        loop {
            let len = u64::from_le_bytes(bytes[p + 1..p + 9].try_into().unwrap()) as usize;
            if bytes[p] == 6 && p > bytes.len() / 2 {
                mid = p + 9 + len / 2;
                break;
            }
            p += 9 + len;
        }
    }
    for b in &mut bytes[mid..mid + 64] {
        *b ^= 0x5a;
    }
    let p = dir.join(name);
    std::fs::write(&p, &bytes).unwrap();
    p
}

#[test]
fn truncated_and_corrupt_bags_are_errors_naming_the_file() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let cases = [
        truncated(d, &ds("ros/ros1/aces-head-lz4.bag"), "cut.bag", 0.6),
        truncated(d, &ds("ros/ros1/aces-head-bz2.bag"), "cut-bz2.bag", 0.01),
        truncated(d, &ds("ros/ros2/aces-mcap/aces-mcap.mcap"), "cut.mcap", 0.6),
        truncated(
            d,
            &ds("ros/ros2/aces-head-sqlite3/aces-head-sqlite3.db3"),
            "cut.db3",
            0.5,
        ),
        corrupted(d, &ds("ros/ros1/aces-head-lz4.bag"), "bad-lz4.bag"),
        corrupted(d, &ds("ros/ros1/aces-head-bz2.bag"), "bad-bz2.bag"),
        corrupted(d, &ds("ros/ros2/aces-mcap/aces-mcap.mcap"), "bad.mcap"),
    ];
    for p in &cases {
        let e = error_of(p, &TopicChoice::default());
        let name = p.file_name().unwrap().to_str().unwrap();
        assert!(e.contains(name), "{name}: {e}");
        assert!(
            ["truncated", "corrupt", "ends early", "error"]
                .iter()
                .any(|w| e.contains(w)),
            "{name}: {e}"
        );
    }
    // A cut ROS 1 bag names what to do about it.
    let e = error_of(&cases[0], &TopicChoice::default());
    assert!(e.contains("rosbag reindex"), "{e}");
}

/// A copy of the sqlite3 bag, edited with `edit`.
fn edited_db3(dir: &Path, name: &str, edit: impl FnOnce(&rusqlite::Connection)) -> PathBuf {
    let p = copy_to(
        dir,
        &ds("ros/ros2/aces-head-sqlite3/aces-head-sqlite3.db3"),
        name,
    );
    let c = rusqlite::Connection::open(&p).unwrap();
    edit(&c);
    drop(c);
    p
}

#[test]
fn a_scan_whose_ranges_disagree_with_its_angles_names_topic_and_message() {
    let dir = tempfile::tempdir().unwrap();
    // Message 17 of /scan: angle_increment doubled (CDR: header 4, stamp 8,
    // "laser" 4 + 6, pad 2, then angle_min, angle_max, angle_increment).
    let p = edited_db3(dir.path(), "geometry.db3", |c| {
        let (id, mut data): (i64, Vec<u8>) = c
            .query_row(
                "SELECT m.id, m.data FROM messages m JOIN topics t ON m.topic_id = t.id \
                 WHERE t.name = '/scan' ORDER BY m.timestamp, m.id LIMIT 1 OFFSET 17",
                [],
                |r| Ok((r.get(0)?, r.get(1)?)),
            )
            .unwrap();
        assert_eq!(&data[16..22], b"laser\0");
        let inc = f32::from_le_bytes(data[32..36].try_into().unwrap());
        data[32..36].copy_from_slice(&(2.0 * inc).to_le_bytes());
        c.execute("UPDATE messages SET data = ?1 WHERE id = ?2", (data, id))
            .unwrap();
    });
    let e = error_of(&p, &TopicChoice::default());
    assert!(
        e.contains("geometry.db3:topic /scan, message 17:")
            && e.contains("180 ranges")
            && e.contains("give 91 beams"),
        "{e}"
    );
    // A message cut short.
    let p = edited_db3(dir.path(), "short.db3", |c| {
        c.execute(
            "UPDATE messages SET data = substr(data, 1, 100) WHERE id = (SELECT m.id FROM \
             messages m JOIN topics t ON m.topic_id = t.id WHERE t.name = '/scan' \
             ORDER BY m.timestamp, m.id LIMIT 1 OFFSET 3)",
            [],
        )
        .unwrap();
    });
    let e = error_of(&p, &TopicChoice::default());
    assert!(
        e.contains("short.db3:topic /scan, message 3:") && e.contains("ranges"),
        "{e}"
    );
}

#[test]
fn empty_topics_and_unknown_types_are_errors() {
    let dir = tempfile::tempdir().unwrap();
    let p = edited_db3(dir.path(), "noscans.db3", |c| {
        c.execute(
            "DELETE FROM messages WHERE topic_id = (SELECT id FROM topics WHERE name = '/scan')",
            [],
        )
        .unwrap();
    });
    let e = error_of(&p, &TopicChoice::default());
    assert!(
        e.contains("noscans.db3") && e.contains("topic /scan has no messages"),
        "{e}"
    );
    let p = edited_db3(dir.path(), "noodom.db3", |c| {
        c.execute(
            "DELETE FROM messages WHERE topic_id IN (SELECT id FROM topics WHERE name IN \
             ('/odom', '/tf'))",
            [],
        )
        .unwrap();
    });
    let e = error_of(&p, &TopicChoice::default());
    assert!(
        e.contains("noodom.db3") && e.contains("the odometry topic /odom has no messages"),
        "{e}"
    );
    // The scan topic declared as a type we do not read: no LaserScan topic.
    let p = edited_db3(dir.path(), "types.db3", |c| {
        c.execute(
            "UPDATE topics SET type = 'sensor_msgs/msg/MultiEchoLaserScan' WHERE name = '/scan'",
            [],
        )
        .unwrap();
    });
    let e = error_of(&p, &TopicChoice::default());
    assert!(
        e.contains("no laser scan topic") && e.contains("/scan  sensor_msgs/MultiEchoLaserScan"),
        "{e}"
    );
    // Serialised in something else than CDR.
    let p = edited_db3(dir.path(), "json.db3", |c| {
        c.execute(
            "UPDATE topics SET serialization_format = 'json' WHERE name = '/scan'",
            [],
        )
        .unwrap();
    });
    let e = error_of(&p, &TopicChoice::default());
    assert!(e.contains("serialised as 'json'"), "{e}");
}

#[test]
fn the_cli_refuses_a_hostile_bag_with_a_clear_error_and_writes_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let bag = truncated(
        dir.path(),
        &ds("ros/ros1/aces-head-lz4.bag"),
        "cut.bag",
        0.6,
    );
    let out = dir.path().join("run");
    let o = Command::new(env!("CARGO_BIN_EXE_dpslam"))
        .arg("map2d")
        .arg(&bag)
        .arg("--out")
        .arg(&out)
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success(), "{err}");
    assert!(
        err.contains("cut.bag") && err.contains("rosbag reindex"),
        "{err}"
    );
    assert!(!err.contains("panicked"), "{err}");
    assert!(!out.exists(), "no output for a failed run");
    // A wrong topic flag, on map3d.
    let o = Command::new(env!("CARGO_BIN_EXE_dpslam"))
        .arg("map3d")
        .arg(ds("ros/ros1/fast_gicp.bag"))
        .args(["--scan-topic", "/points", "--out"])
        .arg(&out)
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success());
    assert!(
        err.contains("no topic /points") && err.contains("/velodyne_points"),
        "{err}"
    );
    assert!(!out.exists());
}

#[test]
fn map2d_on_the_sqlite3_bag_writes_one_pose_per_scan_at_the_header_stamps() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("run");
    let o = Command::new(env!("CARGO_BIN_EXE_dpslam"))
        .arg("map2d")
        .arg(ds("ros/ros2/aces-head-sqlite3"))
        .args(["--particles", "5", "--out"])
        .arg(&out)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let tum = std::fs::read_to_string(out.join("trajectory.tum")).unwrap();
    let stamps: Vec<f64> = tum
        .lines()
        .filter(|l| !l.starts_with('#'))
        .map(|l| l.split_whitespace().next().unwrap().parse().unwrap())
        .collect();
    assert_eq!(stamps.len(), 1000);
    let s = scans(&ds("ros/ros2/aces-head-sqlite3"));
    for (a, b) in stamps.iter().zip(&s) {
        assert!((a - b.timestamp.unwrap()).abs() < 1e-6);
    }
    let run: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("run.json")).unwrap()).unwrap();
    assert_eq!(run["format"], "RosBag");
    assert_eq!(run["scans"], 1000);
}

#[test]
fn mcap_with_lz4_chunks_reads_like_zstd() {
    // Rewrite the zstd MCAP with lz4 chunks (mcap's writer), read both.
    let src = ds("ros/ros2/aces-mcap/aces-mcap.mcap");
    let dir = tempfile::tempdir().unwrap();
    let dst = dir.path().join("aces-lz4.mcap");
    let buf = std::fs::read(&src).unwrap();
    {
        let f = std::io::BufWriter::new(std::fs::File::create(&dst).unwrap());
        let mut w = mcap::WriteOptions::new()
            .compression(Some(mcap::Compression::Lz4))
            .create(f)
            .unwrap();
        for m in mcap::MessageStream::new(&buf).unwrap() {
            w.write(&m.unwrap()).unwrap();
        }
        w.finish().unwrap();
    }
    let raw = std::fs::read(&dst).unwrap();
    assert!(
        raw.windows(3).any(|w| w == b"lz4"),
        "the rewritten file has lz4 chunks"
    );
    same_scans(&scans(&dst), &scans(&src), "lz4 mcap");
}
