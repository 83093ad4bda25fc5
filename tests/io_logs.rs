//! Integration tests of the 2-D log readers on the real logs of
//! `../shared/datasets`, of their error messages, and of `perturb`.

use dpslam::geometry::xyt;
use dpslam::io::log2d::{LogFormat, open_log2d};
use dpslam::scan::LaserScan2d;
use dpslam::sim::perturb::{NoiseModel, perturb_log};
use std::f64::consts::{FRAC_PI_2, PI};
use std::path::{Path, PathBuf};

const MIT_CSAIL: &str = concat!(
    env!("CARGO_MANIFEST_DIR"),
    "/../shared/datasets/carmen/mit-csail/mit-csail.clf"
);
const LOOP5: &str = concat!(
    env!("CARGO_MANIFEST_DIR"),
    "/../shared/datasets/dpslam/loop5.log"
);
const FR079: &str = concat!(
    env!("CARGO_MANIFEST_DIR"),
    "/../shared/datasets/carmen/fr079/freiburg-079-corrected.log.gz"
);
const ACES: &str = concat!(
    env!("CARGO_MANIFEST_DIR"),
    "/../shared/datasets/carmen/aces/aces-corrected.log.gz"
);

fn read_all(path: &Path) -> Vec<LaserScan2d> {
    open_log2d(path)
        .unwrap()
        .collect::<dpslam::Result<Vec<_>>>()
        .unwrap()
}

/// The error of the first failing scan of `path`, as text.
fn first_error(path: &Path) -> String {
    match open_log2d(path) {
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

fn assert_names(msg: &str, path: &Path, line: usize, reason: &str) {
    let at = format!("{}:line {line}:", path.display());
    assert!(msg.contains(&at), "'{msg}' does not name {at}");
    assert!(
        msg.contains(reason),
        "'{msg}' does not give the reason '{reason}'"
    );
}

#[test]
fn mit_csail_raw_log_scans_timestamps_and_beam_angles() {
    let mut r = open_log2d(Path::new(MIT_CSAIL)).unwrap();
    assert_eq!(r.format(), LogFormat::Carmen);
    let first = r.next().unwrap().unwrap();
    assert_eq!(
        format!("{:.6}", first.timestamp.unwrap()),
        "1134864629.895182"
    );
    assert_eq!(first.line, 4);
    assert_eq!(first.ranges.len(), 361);
    assert_eq!(first.ranges[0], 1.40);
    let (x, y, t) = xyt(&first.odometry);
    assert!((x - 576.536523).abs() < 1e-9 && (y - 0.106594).abs() < 1e-9);
    assert!((t + 2.255213).abs() < 1e-9);
    assert_eq!(first.logged_pose, Some(first.odometry));
    // Beams from −90° to +90° in 0.5° steps.
    assert!((first.angle_min + FRAC_PI_2).abs() < 1e-12);
    assert!((first.angle_increment - 0.5f64.to_radians()).abs() < 1e-12);
    let last = first.angle_min + 360.0 * first.angle_increment;
    assert!((last - FRAC_PI_2).abs() < 1e-12);
    // 81.91 is the SICK's "no return" and must be read as one.
    assert!(first.is_no_return(24) && !first.is_no_return(0));

    let rest: Vec<_> = r.by_ref().collect::<dpslam::Result<_>>().unwrap();
    assert_eq!(rest.len() + 1, 1988);
    assert!(rest.iter().all(|s| s.ranges.len() == 361));
    assert!(
        rest.windows(2)
            .all(|w| w[1].timestamp.unwrap() > w[0].timestamp.unwrap())
    );
    assert_eq!(r.scans_read(), 1988);
    assert_eq!(r.bytes_read(), r.total_bytes());
}

#[test]
fn loop5_dpslam_log_has_551_scans_of_181_beams() {
    let r = open_log2d(Path::new(LOOP5)).unwrap();
    assert_eq!(r.format(), LogFormat::DpSlam);
    let scans: Vec<_> = r.collect::<dpslam::Result<_>>().unwrap();
    assert_eq!(scans.len(), 551);
    assert!(scans.iter().all(|s| s.ranges.len() == 181));
    let s = &scans[0];
    assert_eq!(xyt(&s.odometry), (-2.424026, 4.800517, 2.590948));
    assert_eq!((s.timestamp, s.logged_pose, s.line), (None, None, 2));
    assert!((s.angle_increment - PI / 180.0).abs() < 1e-15);
    assert!((s.angle_min + 180.0 * s.angle_increment - FRAC_PI_2).abs() < 1e-12);
    // 8.183 ("no return" of this SICK) is beyond the release's 7.95 m.
    let nr = scans
        .iter()
        .flat_map(|s| {
            (0..181)
                .filter(move |&i| s.ranges[i] >= 8.18)
                .map(move |i| s.is_no_return(i))
        })
        .collect::<Vec<_>>();
    assert!(nr.len() > 6000 && nr.iter().all(|&b| b));
    assert_eq!(scans[550].line, 1102);
}

#[test]
fn corrected_gzip_logs_read_with_param_max_range() {
    let path = Path::new(FR079);
    let mut r = open_log2d(path).unwrap();
    let mut n = 0;
    let mut last_t = f64::NEG_INFINITY;
    for s in r.by_ref() {
        let s = s.unwrap();
        assert_eq!(s.ranges.len(), 360);
        // PARAM robot_front_laser_max 80.99: 81.91 readings are no return.
        assert_eq!(s.max_range, 80.99);
        assert!(s.timestamp.unwrap() > last_t);
        last_t = s.timestamp.unwrap();
        n += 1;
    }
    assert_eq!(n, 4791);
    assert_eq!(r.bytes_read(), r.total_bytes());
    // Even count: 360 beams of 0.5° from −90°.
    let a = read_all(Path::new(ACES));
    assert_eq!(a.len(), 440);
    assert!((a[0].angle_increment - PI / 180.0).abs() < 1e-15 && a[0].ranges.len() == 180);
    assert_eq!(a[0].max_range, dpslam::io::carmen::FLASER_DEFAULT_MAX_RANGE);
}

struct Tmp(tempfile::TempDir);

impl Tmp {
    fn new() -> Self {
        Tmp(tempfile::tempdir().unwrap())
    }
    fn file(&self, name: &str, text: &str) -> PathBuf {
        let p = self.0.path().join(name);
        std::fs::write(&p, text).unwrap();
        p
    }
}

#[test]
fn malformed_logs_give_errors_with_file_line_and_reason() {
    let d = Tmp::new();
    let ok = "FLASER 3 1 2 3 0 0 0 0 0 0 10.5 h 10.5\n";

    let p = d.file(
        "count.clf",
        &format!("# c\n{ok}FLASER 361 1 2 3 0 0 0 0 0 0 11 h 11\n"),
    );
    assert_names(
        &first_error(&p),
        &p,
        3,
        "FLASER declares 361 readings but the line has 3 values",
    );

    let p = d.file(
        "field.clf",
        &format!("{ok}{ok}FLASER 3 1 2 3 0 zero 0 0 0 0 12 h 12\n"),
    );
    assert_names(&first_error(&p), &p, 3, "y: 'zero' is not a number");

    let p = d.file("nanpose.clf", "FLASER 2 1 2 0 0 NaN 0 0 0 1 h 1\n");
    assert_names(&first_error(&p), &p, 1, "theta is not finite");

    let p = d.file(
        "odomnan.log",
        "Odometry 0 0 0\nLaser 1 2\nOdometry 1 nan 0\n",
    );
    assert_names(&first_error(&p), &p, 3, "Odometry y is not finite");

    let p = d.file("order.log", "\nLaser 2 1 2\nOdometry 0 0 0\n");
    assert_names(&first_error(&p), &p, 2, "Laser before any Odometry");

    let p = d.file("dpcount.log", "Odometry 0 0 0\nLaser 181 1 2\n");
    assert_names(
        &first_error(&p),
        &p,
        2,
        "Laser declares 181 readings but the line has 2 values",
    );

    // No line to point at: the message names the file and the reason.
    let p = d.file("empty.clf", "");
    let e = first_error(&p);
    assert!(
        e.contains(&p.display().to_string()) && e.contains("no laser scans"),
        "{e}"
    );
    let p = d.file("onlyodom.clf", "# c\nODOM 0 0 0 0 0 0 1 h 1\n");
    let e = first_error(&p);
    assert!(
        e.contains(&p.display().to_string()) && e.contains("no laser scans"),
        "{e}"
    );
}

#[test]
fn truncated_gzip_log_is_an_error_naming_file_and_line() {
    let d = Tmp::new();
    let bytes = std::fs::read(FR079).unwrap();
    let p = d.0.path().join("cut.log.gz");
    std::fs::write(&p, &bytes[..bytes.len() / 3]).unwrap();
    let mut r = open_log2d(&p).unwrap();
    let mut good = 0;
    let err = loop {
        match r.next() {
            Some(Ok(_)) => good += 1,
            Some(Err(e)) => break e.to_string(),
            None => panic!("a truncated gzip log read to the end without error"),
        }
    };
    assert!(good > 100, "{good} scans before the cut");
    assert!(r.next().is_none());
    assert!(err.contains(&format!("{}:line ", p.display())), "{err}");
    assert!(err.contains("truncated gzip"), "{err}");
}

#[test]
fn nan_and_inf_ranges_are_valid_no_return_readings() {
    let d = Tmp::new();
    let p = d.file(
        "nan.clf",
        "FLASER 4 NaN 1.5 inf -inf 0 0 0 0 0 0 1 h 1\nODOM 0 0 0 0 0 0 1 h 1\n",
    );
    let s = read_all(&p);
    assert_eq!(s.len(), 1);
    assert!(s[0].ranges[0].is_nan() && s[0].ranges[2].is_infinite());
    assert!(
        s[0].is_no_return(0)
            && !s[0].is_no_return(1)
            && s[0].is_no_return(2)
            && s[0].is_no_return(3)
    );
    let p = d.file("nan.log", "Odometry 0 0 0\nLaser 3 nan 1 NaN\n");
    let s = read_all(&p);
    assert!(s[0].is_no_return(0) && !s[0].is_no_return(1) && s[0].is_no_return(2));
}

fn data_lines(path: &Path) -> Vec<String> {
    std::fs::read_to_string(path)
        .unwrap()
        .lines()
        .filter(|l| !l.starts_with('#'))
        .map(String::from)
        .collect()
}

#[test]
fn perturb_is_reproducible_per_seed() {
    let d = Tmp::new();
    let out = |name: &str| d.0.path().join(name);
    let noise = NoiseModel::default();
    let s1 = perturb_log(Path::new(ACES), &out("a.clf"), &out("a.tum"), &noise, 7).unwrap();
    let s2 = perturb_log(Path::new(ACES), &out("b.clf"), &out("b.tum"), &noise, 7).unwrap();
    let s3 = perturb_log(Path::new(ACES), &out("c.clf"), &out("c.tum"), &noise, 8).unwrap();
    assert_eq!(s1, s2);
    let read = |n: &str| std::fs::read(out(n)).unwrap();
    assert_eq!(read("a.clf"), read("b.clf"));
    assert_eq!(read("a.tum"), read("b.tum"));
    assert_ne!(read("a.clf"), read("c.clf"));
    // The truth does not depend on the seed.
    assert_eq!(read("a.tum"), read("c.tum"));
    assert_ne!(s1.final_position_error_m, s3.final_position_error_m);

    assert_eq!(s1.scans, 440);
    assert_eq!(data_lines(&out("a.tum")).len(), 440);
    // The noisy log reads back with the input's ranges and time stamps.
    let input = read_all(Path::new(ACES));
    let noisy = read_all(&out("a.clf"));
    assert_eq!(noisy.len(), 440);
    for (a, b) in input.iter().zip(&noisy) {
        assert_eq!(
            format!("{:.6}", a.timestamp.unwrap()),
            format!("{:.6}", b.timestamp.unwrap())
        );
        assert_eq!(a.ranges.len(), b.ranges.len());
        assert!(
            a.ranges
                .iter()
                .zip(&b.ranges)
                .all(|(x, y)| (x - y).abs() < 5e-4)
        );
        assert_eq!(b.logged_pose, Some(b.odometry));
    }
    // The default model drifts, by a few metres over this 320 m run.
    assert!(
        s1.final_position_error_m > 0.3 && s1.max_position_error_m < 60.0,
        "{s1:?}"
    );
}

#[test]
fn perturb_without_noise_reproduces_the_truth() {
    let d = Tmp::new();
    let (out, truth) = (d.0.path().join("z.clf.gz"), d.0.path().join("z.tum"));
    let s = perturb_log(Path::new(FR079), &out, &truth, &NoiseModel::zero(), 1).unwrap();
    assert_eq!(s.scans, 4791);
    assert!(s.path_length_m > 400.0 && s.path_length_m < 450.0, "{s:?}");
    assert!(s.max_position_error_m < 1e-9, "{s:?}");

    let input = read_all(Path::new(FR079));
    let noisy = read_all(&out);
    let rows = data_lines(&truth);
    assert_eq!((noisy.len(), rows.len()), (4791, 4791));
    for ((a, b), row) in input.iter().zip(&noisy).zip(&rows) {
        let (tx, ty, tt) = xyt(&a.logged_pose.unwrap());
        let (ox, oy, ot) = xyt(&b.odometry);
        assert!(
            (tx - ox).abs() < 2e-6 && (ty - oy).abs() < 2e-6,
            "line {}",
            b.line
        );
        assert!(
            dpslam::geometry::wrap_angle(tt - ot).abs() < 2e-6,
            "line {}",
            b.line
        );
        let f: Vec<f64> = row.split(' ').map(|v| v.parse().unwrap()).collect();
        assert_eq!(f.len(), 8);
        assert_eq!(
            format!("{:.6}", f[0]),
            format!("{:.6}", a.timestamp.unwrap())
        );
        assert!((f[1] - tx).abs() < 1e-8 && (f[2] - ty).abs() < 1e-8 && f[3] == 0.0);
        assert!(dpslam::geometry::wrap_angle(2.0 * f[6].atan2(f[7]) - tt).abs() < 1e-7);
    }
}

#[test]
fn perturb_failure_leaves_no_output() {
    let d = Tmp::new();
    let mut text = String::new();
    for i in 0..20 {
        text.push_str(&format!("FLASER 2 1 2 {i} 0 0 {i} 0 0 {i}.0 h 0\n"));
    }
    text.push_str("FLASER 2 1 2 x 0 0 0 0 0 1 h 0\n");
    let input = d.file("in.clf", &text);
    let (out, truth) = (d.0.path().join("o.clf"), d.0.path().join("o.tum"));
    let e = perturb_log(&input, &out, &truth, &NoiseModel::default(), 1).unwrap_err();
    assert_names(&e.to_string(), &input, 21, "x: 'x' is not a number");
    let left: Vec<_> = std::fs::read_dir(d.0.path())
        .unwrap()
        .map(|e| e.unwrap().file_name())
        .collect();
    assert_eq!(left, vec![std::ffi::OsString::from("in.clf")]);

    // A DP-SLAM log has no reference poses to perturb.
    let dp = d.file("l.log", "Odometry 0 0 0\nLaser 1 1\n");
    let e = perturb_log(&dp, &out, &truth, &NoiseModel::default(), 1).unwrap_err();
    assert_names(&e.to_string(), &dp, 2, "no logged pose");
    assert!(!out.exists() && !truth.exists());
}
