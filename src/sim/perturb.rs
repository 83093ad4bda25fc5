//! Turning a corrected log into a SLAM benchmark: noisy odometry plus truth.
//!
//! Input: a 2-D log whose logged poses (CARMEN `x y theta`) are reference
//! poses, e.g. the `*-corrected.log.gz` logs. Output: a CARMEN log with the
//! same ranges and time stamps whose poses are odometry corrupted by a stated
//! noise model (both FLASER pose fields = the noisy odometry, as in a raw
//! log), and the truth trajectory as TUM (`t x y z qx qy qz qw`, one line per
//! scan, in input order; z = 0, rotation about z).
//!
//! # Noise model
//!
//! For each pair of consecutive scans, the true motion is taken in the frame
//! of the previous true pose: `(dx, dy)` (m) and `dθ` (rad, wrapped to
//! (−π, π]), with `d = √(dx² + dy²)`. The odometry reports
//!
//! ```text
//! dx' = (1 + scale)·dx + σ_t·n₁          σ_t = trans·d + trans_per_rot·|dθ|
//! dy' = (1 + scale)·dy + σ_t·n₂          σ_r = rot_per_trans·d + rot·|dθ|
//! dθ' = (1 + rot_scale)·dθ + drift·d + σ_r·n₃
//! ```
//!
//! with `n₁, n₂, n₃` independent standard normal draws, and composes
//! `(dx', dy', dθ')` onto the previous noisy pose. The first noisy pose is
//! the first true pose, so the odometry and truth frames coincide at the
//! start and the final position difference is the accumulated drift.
//!
//! `scale` and `rot_scale` are systematic scale biases (wheel radius,
//! wheel base), `drift` a systematic turn per metre (unequal wheels, rad/m,
//! counter-clockwise positive), and the σ terms the usual odometry model
//! whose noise grows with distance and turn. Note that the σ terms apply
//! per step between scans, so their effect over a run shrinks as the scan
//! rate grows (variance per metre ∝ step length); the systematic terms do
//! not depend on the scan rate.
//!
//! Defaults ([`NoiseModel::default`]): `scale=0.01, rot_scale=0.02,
//! drift=0.001, trans=0.02, trans_per_rot=0.01, rot_per_trans=0.005,
//! rot=0.03`. Measured over seeds 1–10 on the first ≈ 100 m of real corrected
//! logs, the final position drift is 0.2–1.9 m on Freiburg 079 (9 cm between
//! scans), 1.3–7.9 m on MIT CSAIL and 1.3–11 m on Freiburg campus (≈ 0.9 m
//! between scans); over the whole Freiburg 079 log (422 m) 2–8 m. Each run's
//! drift is reported in [`PerturbSummary`].

use crate::geometry::{Pose, Pose2, pose2, wrap_angle, xyt};
use crate::io::carmen::{
    format_flaser, format_header, format_max_range_param, format_robotlaser1, is_flaser_geometry,
};
use crate::io::log2d::open_log2d;
use crate::io::tum::TumWriter;
use crate::{Error, Result};
use rand::SeedableRng;
use rand_distr::{Distribution, StandardNormal};
use rand_pcg::Pcg64;
use serde::{Deserialize, Serialize};
use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};
use std::str::FromStr;

/// The odometry noise model of [`perturb_log`]; see the module docs for the
/// equations. All fields finite; the four σ coefficients ≥ 0.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct NoiseModel {
    /// Translation scale bias (fraction): reported translation is
    /// `(1 + scale)` × the true one.
    pub scale: f64,
    /// Rotation scale bias (fraction): reported turn is `(1 + rot_scale)` ×
    /// the true one.
    pub rot_scale: f64,
    /// Systematic extra rotation per metre travelled (rad/m, CCW positive).
    pub drift: f64,
    /// Translation noise std per metre travelled (m/m).
    pub trans: f64,
    /// Translation noise std per radian turned (m/rad).
    pub trans_per_rot: f64,
    /// Rotation noise std per metre travelled (rad/m).
    pub rot_per_trans: f64,
    /// Rotation noise std per radian turned (rad/rad).
    pub rot: f64,
}

impl Default for NoiseModel {
    fn default() -> Self {
        Self {
            scale: 0.01,
            rot_scale: 0.02,
            drift: 0.001,
            trans: 0.02,
            trans_per_rot: 0.01,
            rot_per_trans: 0.005,
            rot: 0.03,
        }
    }
}

/// Names of the spec keys, in the order of the fields.
const KEYS: [&str; 7] = [
    "scale",
    "rot_scale",
    "drift",
    "trans",
    "trans_per_rot",
    "rot_per_trans",
    "rot",
];

impl NoiseModel {
    /// No noise at all: the odometry reproduces the truth.
    pub fn zero() -> Self {
        Self {
            scale: 0.0,
            rot_scale: 0.0,
            drift: 0.0,
            trans: 0.0,
            trans_per_rot: 0.0,
            rot_per_trans: 0.0,
            rot: 0.0,
        }
    }

    fn field_mut(&mut self, key: &str) -> Option<&mut f64> {
        Some(match key {
            "scale" => &mut self.scale,
            "rot_scale" => &mut self.rot_scale,
            "drift" => &mut self.drift,
            "trans" => &mut self.trans,
            "trans_per_rot" => &mut self.trans_per_rot,
            "rot_per_trans" => &mut self.rot_per_trans,
            "rot" => &mut self.rot,
            _ => return None,
        })
    }

    fn values(&self) -> [f64; 7] {
        [
            self.scale,
            self.rot_scale,
            self.drift,
            self.trans,
            self.trans_per_rot,
            self.rot_per_trans,
            self.rot,
        ]
    }

    /// Checks that every value is finite, the σ coefficients are ≥ 0 and the
    /// scale biases > −1 (a bias of −1 or less would reverse or cancel motion).
    pub fn validate(&self) -> Result<()> {
        for (k, v) in KEYS.iter().zip(self.values()) {
            if !v.is_finite() {
                return Err(Error::Config(format!("noise {k} = {v} is not finite")));
            }
        }
        for (k, v) in KEYS[3..].iter().zip(&self.values()[3..]) {
            if *v < 0.0 {
                return Err(Error::Config(format!(
                    "noise {k} = {v} is a std, it must be ≥ 0"
                )));
            }
        }
        for (k, v) in [("scale", self.scale), ("rot_scale", self.rot_scale)] {
            if v <= -1.0 {
                return Err(Error::Config(format!("noise {k} = {v} must be > -1")));
            }
        }
        Ok(())
    }

    /// The noisy odometry increment for the true increment `(dx, dy, dθ)` in
    /// the previous pose's frame (m, m, rad); draws three normal variates.
    pub fn corrupt<R: rand::Rng + ?Sized>(
        &self,
        dx: f64,
        dy: f64,
        dtheta: f64,
        rng: &mut R,
    ) -> (f64, f64, f64) {
        let d = dx.hypot(dy);
        let turn = wrap_angle(dtheta);
        let sigma_t = self.trans * d + self.trans_per_rot * turn.abs();
        let sigma_r = self.rot_per_trans * d + self.rot * turn.abs();
        let n1: f64 = StandardNormal.sample(rng);
        let n2: f64 = StandardNormal.sample(rng);
        let n3: f64 = StandardNormal.sample(rng);
        (
            (1.0 + self.scale) * dx + sigma_t * n1,
            (1.0 + self.scale) * dy + sigma_t * n2,
            (1.0 + self.rot_scale) * turn + self.drift * d + sigma_r * n3,
        )
    }
}

impl std::fmt::Display for NoiseModel {
    /// The spec form accepted by [`NoiseModel::from_str`], all keys.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        for (i, (k, v)) in KEYS.iter().zip(self.values()).enumerate() {
            if i > 0 {
                f.write_str(",")?;
            }
            write!(f, "{k}={v}")?;
        }
        Ok(())
    }
}

impl FromStr for NoiseModel {
    type Err = String;

    /// Parses `key=value` pairs separated by commas, starting from the
    /// defaults; the words `none` (all zero) and `default` reset every key
    /// and may be followed by pairs (`none,trans=0.05`). Keys: `scale`,
    /// `rot_scale`, `drift`, `trans`, `trans_per_rot`, `rot_per_trans`, `rot`.
    fn from_str(s: &str) -> std::result::Result<Self, String> {
        let mut m = NoiseModel::default();
        for item in s.split(',').map(str::trim).filter(|t| !t.is_empty()) {
            match item {
                "none" | "zero" => m = NoiseModel::zero(),
                "default" => m = NoiseModel::default(),
                _ => {
                    let (k, v) = item.split_once('=').ok_or_else(|| {
                        format!("'{item}' is not key=value (keys: {})", KEYS.join(", "))
                    })?;
                    let (k, v) = (k.trim(), v.trim());
                    let slot = m.field_mut(k).ok_or_else(|| {
                        format!("unknown noise key '{k}' (keys: {})", KEYS.join(", "))
                    })?;
                    *slot = v
                        .parse::<f64>()
                        .map_err(|_| format!("noise {k}: '{v}' is not a number"))?;
                }
            }
        }
        m.validate().map_err(|e| e.to_string())?;
        Ok(m)
    }
}

/// What [`perturb_log`] wrote.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PerturbSummary {
    /// Scans written (= truth poses written).
    pub scans: usize,
    /// Length of the true path (m).
    pub path_length_m: f64,
    /// Distance between the last noisy odometry position and the last true
    /// position (m): the accumulated odometry drift.
    pub final_position_error_m: f64,
    /// Heading difference at the last scan (rad, in [0, π]).
    pub final_heading_error_rad: f64,
    /// Largest position difference over the run (m).
    pub max_position_error_m: f64,
    /// Scans whose time stamp is not later than the previous scan's (e.g.
    /// logs that print time stamps with 6 significant digits): the truth
    /// cannot be matched to them by time.
    pub non_increasing_timestamps: usize,
}

/// Host name written into the CARMEN lines.
const HOST: &str = "dpslam";

/// The CARMEN output: written to a temporary file, renamed on commit, removed
/// if dropped before.
struct AtomicOut {
    path: PathBuf,
    tmp: PathBuf,
    w: Option<Sink>,
}

enum Sink {
    Plain(BufWriter<File>),
    Gz(flate2::write::GzEncoder<BufWriter<File>>),
}

impl AtomicOut {
    fn create(path: &Path) -> Result<Self> {
        let tmp = crate::io::atomic::temp_path(path)?;
        let f = BufWriter::new(File::create(&tmp).map_err(|e| Error::io(path, e))?);
        let gz = path
            .extension()
            .is_some_and(|e| e.eq_ignore_ascii_case("gz"));
        let w = if gz {
            Sink::Gz(flate2::write::GzEncoder::new(
                f,
                flate2::Compression::default(),
            ))
        } else {
            Sink::Plain(f)
        };
        Ok(Self {
            path: path.to_path_buf(),
            tmp,
            w: Some(w),
        })
    }

    fn line(&mut self, s: &str) -> Result<()> {
        let w: &mut dyn Write = match self.w.as_mut() {
            Some(Sink::Plain(w)) => w,
            Some(Sink::Gz(w)) => w,
            None => return Err(Error::Invalid("output already closed".into())),
        };
        w.write_all(s.as_bytes())
            .and_then(|_| w.write_all(b"\n"))
            .map_err(|e| Error::io(&self.path, e))
    }

    /// Flushes everything to the temporary file (not yet renamed).
    fn flush(&mut self) -> Result<()> {
        let file = match self.w.take() {
            Some(Sink::Plain(w)) => w.into_inner().map_err(|e| e.into_error()),
            Some(Sink::Gz(w)) => w
                .finish()
                .and_then(|b| b.into_inner().map_err(|e| e.into_error())),
            None => return Ok(()),
        }
        .map_err(|e| Error::io(&self.path, e))?;
        file.sync_all().map_err(|e| Error::io(&self.path, e))
    }

    fn commit(mut self) -> Result<()> {
        self.flush()?;
        let r = std::fs::rename(&self.tmp, &self.path).map_err(|e| Error::io(&self.path, e));
        if r.is_err() {
            let _ = std::fs::remove_file(&self.tmp);
        }
        // Renamed or removed: nothing left for Drop.
        self.tmp = PathBuf::new();
        r
    }
}

impl Drop for AtomicOut {
    fn drop(&mut self) {
        if !self.tmp.as_os_str().is_empty() {
            self.w = None;
            let _ = std::fs::remove_file(&self.tmp);
        }
    }
}

/// Reads the corrected log `input` (CARMEN or any format with logged poses
/// and time stamps), writes the noisy CARMEN log to `out` (gzip when its name
/// ends in `.gz`) and the truth trajectory to `truth` (TUM), with noise
/// drawn from `Pcg64` seeded with `seed`: the same inputs give byte-identical
/// outputs.
///
/// Laser lines are FLASER when the scan's beam geometry is the FLASER one,
/// else ROBOTLASER1; the max range goes into a `PARAM` header line. Both
/// outputs are written under temporary names and renamed at the end, so a
/// failure leaves neither (nor changes existing files).
///
/// Errors: unreadable or malformed input (file, line, reason), a scan without
/// a logged pose or time stamp, `out` and `truth` being the same path, an
/// invalid noise model, I/O failures on the outputs.
pub fn perturb_log(
    input: &Path,
    out: &Path,
    truth: &Path,
    noise: &NoiseModel,
    seed: u64,
) -> Result<PerturbSummary> {
    noise.validate()?;
    if out == truth {
        return Err(Error::Config(format!(
            "--out and --truth are the same file: {}",
            out.display()
        )));
    }
    if out == input || truth == input {
        return Err(Error::Config(format!(
            "an output would overwrite the input {}",
            input.display()
        )));
    }
    let reader = open_log2d(input)?;
    let mut rng = Pcg64::seed_from_u64(seed);
    let mut log = AtomicOut::create(out)?;
    let mut tum = TumWriter::create(truth)?;

    let mut prev: Option<(Pose2, Pose2)> = None; // (truth, noisy)
    let mut written_max: Option<f64> = None;
    let mut summary = PerturbSummary {
        scans: 0,
        path_length_m: 0.0,
        final_position_error_m: 0.0,
        final_heading_error_rad: 0.0,
        max_position_error_m: 0.0,
        non_increasing_timestamps: 0,
    };
    let mut last_t = f64::NEG_INFINITY;
    for scan in reader {
        let mut scan = scan?;
        let true_pose = scan.logged_pose.ok_or_else(|| {
            Error::at_line(
                input,
                scan.line,
                "the scan has no logged pose (x y theta): perturb needs a log with reference poses",
            )
        })?;
        let t = scan.timestamp.ok_or_else(|| {
            Error::at_line(
                input,
                scan.line,
                "the scan has no time stamp: the truth trajectory needs one",
            )
        })?;
        let noisy = match prev {
            None => true_pose,
            Some((pt, pn)) => {
                let rel = pt.inverse() * true_pose;
                let (dx, dy, dth) = xyt(&rel);
                summary.path_length_m += dx.hypot(dy);
                let (nx, ny, nth) = noise.corrupt(dx, dy, dth, &mut rng);
                pn * pose2(nx, ny, nth)
            }
        };
        prev = Some((true_pose, noisy));
        if t <= last_t {
            summary.non_increasing_timestamps += 1;
        }
        last_t = t;

        match written_max {
            None => log.line(format_header(scan.max_range, HOST).trim_end())?,
            Some(m) if m != scan.max_range => {
                log.line(&format_max_range_param(scan.max_range, HOST))?
            }
            _ => {}
        }
        written_max = Some(scan.max_range);
        scan.odometry = noisy;
        scan.logged_pose = Some(noisy);
        let line = if is_flaser_geometry(&scan) {
            format_flaser(&scan, HOST)
        } else {
            format_robotlaser1(&scan, HOST)
        };
        log.line(&line)?;
        tum.write(t, &Pose::<2>::to_tum(&true_pose))?;

        let err = (noisy.translation.vector - true_pose.translation.vector).norm();
        summary.scans += 1;
        summary.max_position_error_m = summary.max_position_error_m.max(err);
        summary.final_position_error_m = err;
        summary.final_heading_error_rad =
            wrap_angle(noisy.rotation.angle() - true_pose.rotation.angle()).abs();
    }
    // Flush both before renaming either, so an I/O failure leaves neither.
    log.flush()?;
    tum.finish()?;
    if let Err(e) = log.commit() {
        let _ = std::fs::remove_file(truth);
        return Err(e);
    }
    Ok(summary)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn spec_parsing_defaults_and_errors() {
        assert_eq!("".parse::<NoiseModel>().unwrap(), NoiseModel::default());
        let m: NoiseModel = "none, trans=0.05 ,drift=-0.001".parse().unwrap();
        assert_eq!(m.trans, 0.05);
        assert_eq!(m.drift, -0.001);
        assert_eq!(m.scale, 0.0);
        let d: NoiseModel = "scale=0.02".parse().unwrap();
        assert_eq!((d.scale, d.rot), (0.02, NoiseModel::default().rot));
        // Display gives a spec that parses back to the same model.
        assert_eq!(d.to_string().parse::<NoiseModel>().unwrap(), d);
        for (spec, want) in [
            ("bogus=1", "unknown noise key 'bogus'"),
            ("trans", "not key=value"),
            ("trans=abc", "noise trans: 'abc' is not a number"),
            ("trans=-0.1", "must be ≥ 0"),
            ("scale=-1", "must be > -1"),
            ("drift=inf", "not finite"),
        ] {
            let e = spec.parse::<NoiseModel>().unwrap_err();
            assert!(e.contains(want), "{spec}: {e}");
        }
    }

    #[test]
    fn serde_round_trip_with_defaults_for_missing_keys() {
        let m: NoiseModel = serde_json::from_str(r#"{"trans": 0.1}"#).unwrap();
        assert_eq!(m.trans, 0.1);
        assert_eq!(m.rot, NoiseModel::default().rot);
        let back: NoiseModel = serde_json::from_str(&serde_json::to_string(&m).unwrap()).unwrap();
        assert_eq!(back, m);
        assert!(serde_json::from_str::<NoiseModel>(r#"{"tran": 0.1}"#).is_err());
    }

    #[test]
    fn systematic_terms_are_exact_and_noise_scales_with_motion() {
        let mut rng = Pcg64::seed_from_u64(3);
        let sys = NoiseModel {
            scale: 0.1,
            rot_scale: -0.5,
            drift: 0.01,
            ..NoiseModel::zero()
        };
        let (x, y, t) = sys.corrupt(3.0, 4.0, 0.2, &mut rng);
        assert!((x - 3.3).abs() < 1e-12 && (y - 4.4).abs() < 1e-12);
        assert!((t - (0.1 + 0.05)).abs() < 1e-12);

        // A standing robot gets no noise, whatever the σ coefficients.
        let noisy = NoiseModel::default();
        assert_eq!(noisy.corrupt(0.0, 0.0, 0.0, &mut rng), (0.0, 0.0, 0.0));

        // Sample std of the x error matches σ_t = trans·d for a straight step.
        let m = NoiseModel {
            trans: 0.1,
            ..NoiseModel::zero()
        };
        let n = 20000;
        let var = (0..n)
            .map(|_| (m.corrupt(0.5, 0.0, 0.0, &mut rng).0 - 0.5).powi(2))
            .sum::<f64>()
            / n as f64;
        assert!((var.sqrt() - 0.05).abs() < 0.002, "std {}", var.sqrt());
    }

    #[test]
    fn writes_noisy_log_and_truth_and_cleans_up_on_error() {
        let dir = tempfile::tempdir().unwrap();
        let input = dir.path().join("in.clf");
        let mut text = String::from("# corrected\n");
        for i in 0..50 {
            let x = 0.1 * i as f64;
            text.push_str(&format!(
                "FLASER 3 1 2 81.91 {x} 0 0.01 {x} 0 0.01 {}.25 h 0\n",
                100 + i
            ));
        }
        std::fs::write(&input, &text).unwrap();
        let out = dir.path().join("noisy.clf");
        let truth = dir.path().join("truth.tum");
        let s = perturb_log(&input, &out, &truth, &NoiseModel::default(), 1).unwrap();
        assert_eq!(s.scans, 50);
        assert!((s.path_length_m - 4.9).abs() < 1e-9);
        assert!(s.final_position_error_m > 0.0 && s.final_position_error_m < 1.0);
        let rows: Vec<_> = std::fs::read_to_string(&truth)
            .unwrap()
            .lines()
            .filter(|l| !l.starts_with('#'))
            .map(String::from)
            .collect();
        assert_eq!(rows.len(), 50);
        assert!(
            rows[1].starts_with("101.250000 0.100000000 0.000000000 0.000000000 "),
            "{}",
            rows[1]
        );
        let log: Vec<_> = crate::io::log2d::open_log2d(&out)
            .unwrap()
            .collect::<Result<_>>()
            .unwrap();
        assert_eq!(log.len(), 50);
        assert!(log[0].is_no_return(2) && !log[0].is_no_return(1));
        assert_eq!(log[7].timestamp, Some(107.25));

        // A malformed input line leaves no output and no temporary file.
        std::fs::write(&input, format!("{text}FLASER 3 1 2\n")).unwrap();
        let out2 = dir.path().join("noisy2.clf");
        let truth2 = dir.path().join("truth2.tum");
        let e = perturb_log(&input, &out2, &truth2, &NoiseModel::default(), 1).unwrap_err();
        assert!(e.to_string().contains("in.clf:line 52"), "{e}");
        let names: Vec<_> = std::fs::read_dir(dir.path())
            .unwrap()
            .map(|e| e.unwrap().file_name().into_string().unwrap())
            .collect();
        assert_eq!(names.len(), 3, "{names:?}");
        assert!(perturb_log(&input, &out, &out, &NoiseModel::default(), 1).is_err());
    }
}
