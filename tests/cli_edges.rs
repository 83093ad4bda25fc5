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
