//! What a new user hits first: a copied binary with no source tree, a bad
//! `--out`, absurd particle counts, and progress when stderr is a pipe.

use std::path::Path;
use std::process::Command;
use std::time::{Duration, Instant};

fn dpslam() -> &'static str {
    env!("CARGO_BIN_EXE_dpslam")
}

#[test]
fn a_copied_binary_in_an_empty_folder_maps_its_embedded_log_with_progress_on_a_pipe() {
    let dir = tempfile::tempdir().unwrap();
    let bin = dir.path().join("dpslam");
    std::fs::copy(dpslam(), &bin).unwrap();
    let child = Command::new(&bin)
        .current_dir(dir.path())
        .args(["map2d", "--particles", "3", "--out", "X"])
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let pid = child.id();
    let o = child.wait_with_output().unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{err}");
    let tum = std::fs::read_to_string(dir.path().join("X/trajectory.tum")).unwrap();
    // data/sim2d/sim2d.clf has 1 scan per line of its truth file.
    let truth = include_str!("../data/sim2d/truth.tum");
    let rows = |t: &str| t.lines().filter(|l| !l.starts_with('#')).count();
    assert_eq!(rows(&tum), rows(truth));
    // stderr is a pipe here: plain progress lines, every 5 %.
    let lines: Vec<&str> = err.lines().filter(|l| l.starts_with("map2d: ")).collect();
    assert!(
        lines.iter().any(|l| l.contains(" % (")),
        "no progress line on a pipe: {err}"
    );
    // The temporary copy of the embedded log is gone.
    assert!(
        !std::env::temp_dir()
            .join(format!("dpslam-sim2d-{pid}.clf"))
            .exists()
    );
}

#[test]
fn a_bad_out_is_refused_within_a_second_and_nothing_is_written() {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("afile");
    std::fs::write(&file, "x").unwrap();
    for (out, says) in [
        (file.clone(), "exists and is not a folder"),
        (file.join("run"), "is a file, not a folder"),
    ] {
        for cmd in ["map2d", "map3d"] {
            let t = Instant::now();
            let o = Command::new(dpslam())
                .arg(cmd)
                .arg("--out")
                .arg(&out)
                .output()
                .unwrap();
            let err = String::from_utf8_lossy(&o.stderr);
            assert!(!o.status.success(), "{cmd}: {err}");
            assert!(err.contains(says), "{cmd}: {err}");
            assert!(
                t.elapsed() < Duration::from_secs(1),
                "{cmd}: {:?}",
                t.elapsed()
            );
        }
    }
    assert_eq!(std::fs::read_to_string(&file).unwrap(), "x");
    assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);
}

#[test]
fn particle_counts_that_cannot_work_are_refused_saying_why() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("run");
    let o = Command::new(dpslam())
        .args(["map2d", "--particles", "-1", "--out"])
        .arg(&out)
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success());
    assert!(err.contains("'-1' is not a whole number"), "{err}");
    assert!(!err.contains("-- -1"), "clap's wrong tip: {err}");
    let t = Instant::now();
    let o = Command::new(dpslam())
        .args(["map2d", "--particles", "100000000", "--out"])
        .arg(&out)
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success());
    assert!(
        err.contains("100000000 particles") && err.contains("GiB available"),
        "{err}"
    );
    assert!(t.elapsed() < Duration::from_secs(1));
    assert!(!Path::new(&out).exists());
}

#[test]
fn what_the_range_survey_finds_is_said_before_the_mapping_and_once() {
    // A laser whose header declares 10 m while a third of its readings are
    // returns at 15 m and 51.15 m means "no return" (edmonton's case).
    let dir = tempfile::tempdir().unwrap();
    let log = dir.path().join("understated.clf");
    let mut text = String::from("PARAM robot_front_laser_max 10\n");
    for i in 0..30 {
        let ranges: Vec<String> = (0..181)
            .map(|b| match b % 3 {
                0 => "5.0",
                1 => "15.0",
                _ => "51.15",
            })
            .map(String::from)
            .collect();
        let x = 0.1 * i as f64;
        text.push_str(&format!(
            "FLASER 181 {} {x} 0 0 {x} 0 0 {i}.0 host {i}.0\n",
            ranges.join(" ")
        ));
    }
    std::fs::write(&log, text).unwrap();
    let o = Command::new(dpslam())
        .arg("map2d")
        .arg(&log)
        .args(["--particles", "3", "--threads", "1", "--out"])
        .arg(dir.path().join("run"))
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{err}");
    let lines: Vec<&str> = err.lines().collect();
    let said: Vec<usize> = (0..lines.len())
        .filter(|&i| lines[i].contains("declared maximum range of 10 m"))
        .collect();
    assert_eq!(said.len(), 1, "{err}");
    let first_progress = lines
        .iter()
        .position(|l| l.starts_with("map2d: ") && l.contains(" % ("))
        .expect("progress lines on a pipe");
    assert!(said[0] < first_progress, "{err}");
    // The run's summary keeps it for the record.
    let run = std::fs::read_to_string(dir.path().join("run/run.json")).unwrap();
    assert!(run.contains("declared maximum range of 10 m"), "{run}");
}
