//! Trajectory files: TUM (`t x y z qx qy qz qw`) and KITTI odometry poses
//! (12 numbers per line, a row-major 3×4 `[R | t]`), read into time-stamped
//! 3-D poses; and a TUM writer.
//!
//! Every pose maps points from the body frame (robot or sensor) into the
//! trajectory's world frame, metres, right-handed. 2-D trajectories are stored
//! as 3-D poses with z = 0 and a rotation about z only, so that one evaluator
//! serves both.

use crate::geometry::{Pose, Pose3, pose2};
use crate::io::source::{TextSource, parse_f64};
use crate::{Error, Result};
use nalgebra::{Matrix3, Quaternion, Rotation3, Translation3, UnitQuaternion};
use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};

/// Number of fields of a TUM line: `t x y z qx qy qz qw`.
pub const TUM_FIELDS: usize = 8;
/// Number of fields of a KITTI poses line: `r11 r12 r13 tx r21 … r33 tz`.
pub const KITTI_FIELDS: usize = 12;

/// Largest Frobenius norm of `RᵀR − I` accepted for a KITTI rotation block.
/// KITTI files print about 7 significant digits, so a valid rotation is off by
/// ~1e-6; anything far beyond that is not a rotation and rounding it to the
/// nearest one would hide a broken file.
const KITTI_ORTHO_TOL: f64 = 1e-3;

/// A pose with its time stamp.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Stamped {
    /// Time stamp in seconds: as written in a TUM file (usually Unix time), or
    /// the 0-based frame index for KITTI poses, which carry no time.
    pub t: f64,
    /// Body pose in the trajectory's world frame (metres; maps body-frame
    /// points into the world frame).
    pub pose: Pose3,
}

impl Stamped {
    /// A stamped pose at time `t` (s).
    pub fn new(t: f64, pose: Pose3) -> Self {
        Self { t, pose }
    }

    /// A planar pose at time `t` (s): position `x, y` (m) with z = 0, heading
    /// `theta` (rad, counter-clockwise about +z from +x).
    pub fn planar(t: f64, x: f64, y: f64, theta: f64) -> Self {
        let p = pose2(x, y, theta);
        Self {
            t,
            pose: <Pose3 as Pose<3>>::from_tum(p.to_tum()),
        }
    }

    /// TUM fields `x y z qx qy qz qw` of the pose (metres, unit quaternion).
    pub fn tum(&self) -> [f64; 7] {
        self.pose.to_tum()
    }

    /// Time and pose are all finite.
    pub fn is_finite(&self) -> bool {
        self.t.is_finite() && Pose::<3>::is_finite(&self.pose)
    }
}

/// Whether a line carries data: not blank and not a `#` comment.
pub(crate) fn is_data_line(line: &str) -> bool {
    let t = line.trim_start();
    !t.is_empty() && !t.starts_with('#')
}

/// Parses exactly `N` whitespace-separated finite numbers named by `names`,
/// with an error naming `path`, `line_no` and the offending field.
pub(crate) fn parse_record<const N: usize>(
    path: &Path,
    line_no: usize,
    line: &str,
    names: &[&str; N],
    format: &str,
) -> Result<[f64; N]> {
    let toks: Vec<&str> = line.split_whitespace().collect();
    if toks.len() != N {
        return Err(Error::at_line(
            path,
            line_no,
            format!(
                "expected {N} fields ({format}: {}), found {}",
                names.join(" "),
                toks.len()
            ),
        ));
    }
    let mut out = [0.0; N];
    for (i, (tok, name)) in toks.iter().zip(names).enumerate() {
        let v = parse_f64(Some(tok), name).map_err(|r| Error::at_line(path, line_no, r))?;
        if !v.is_finite() {
            return Err(Error::at_line(
                path,
                line_no,
                format!("{name} is not finite ('{tok}')"),
            ));
        }
        out[i] = v;
    }
    Ok(out)
}

/// Reads every data line of `path` with `parse`, failing on an empty file.
fn read_lines<T>(
    path: &Path,
    mut parse: impl FnMut(usize, &str, usize) -> Result<T>,
) -> Result<Vec<T>> {
    let mut src = TextSource::open(path)?;
    let mut out = Vec::new();
    while let Some((line_no, line)) = src.next_line()? {
        if is_data_line(line) {
            let item = parse(line_no, line, out.len())?;
            out.push(item);
        }
    }
    if out.is_empty() {
        return Err(Error::in_file(path, "no poses (empty trajectory)"));
    }
    Ok(out)
}

/// Reads a TUM trajectory: one `t x y z qx qy qz qw` per line (s, m, quaternion
/// of the body-to-world rotation). Blank lines and `#` comments are skipped;
/// gzip is decompressed transparently. Quaternions are normalised, because
/// files print them with a few digits; a zero or non-finite one is an error
/// naming the line. Poses keep the order of the file.
pub fn read_tum(path: &Path) -> Result<Vec<Stamped>> {
    const NAMES: [&str; TUM_FIELDS] = ["t", "x", "y", "z", "qx", "qy", "qz", "qw"];
    read_lines(path, |line_no, line, _| {
        let v = parse_record(path, line_no, line, &NAMES, "TUM")?;
        let q = Quaternion::new(v[7], v[4], v[5], v[6]);
        let norm = q.norm();
        // Squared components of finite inputs can still overflow to ∞.
        if !norm.is_finite() || norm < 1e-12 {
            return Err(Error::at_line(
                path,
                line_no,
                format!("quaternion has norm {norm:e}: not a rotation"),
            ));
        }
        let rot = UnitQuaternion::new_unchecked(q / norm);
        Ok(Stamped::new(
            v[0],
            Pose3::from_parts(Translation3::new(v[1], v[2], v[3]), rot),
        ))
    })
}

/// Reads KITTI odometry poses: 12 numbers per line, the row-major 3×4 matrix
/// `[R | t]` of the camera-to-world transform (m). The time stamp of each pose
/// is its 0-based index among the pose lines (the KITTI frame number). The
/// rotation block is projected onto the nearest rotation; one that is not
/// close to orthonormal with determinant +1 is an error naming the line.
pub fn read_kitti_poses(path: &Path) -> Result<Vec<Stamped>> {
    const NAMES: [&str; KITTI_FIELDS] = [
        "r11", "r12", "r13", "tx", "r21", "r22", "r23", "ty", "r31", "r32", "r33", "tz",
    ];
    read_lines(path, |line_no, line, index| {
        let v = parse_record(path, line_no, line, &NAMES, "KITTI")?;
        let m = Matrix3::new(v[0], v[1], v[2], v[4], v[5], v[6], v[8], v[9], v[10]);
        let ortho = (m.transpose() * m - Matrix3::identity()).norm();
        let det = m.determinant();
        if !ortho.is_finite() || ortho > KITTI_ORTHO_TOL || det.is_nan() || det <= 0.0 {
            return Err(Error::at_line(
                path,
                line_no,
                format!(
                    "rotation block is not a rotation (|RᵀR − I| = {ortho:.2e}, det = {det:.4})"
                ),
            ));
        }
        let rot = Rotation3::from_matrix(&m);
        Ok(Stamped::new(
            index as f64,
            Pose3::from_parts(
                Translation3::new(v[3], v[7], v[11]),
                UnitQuaternion::from_rotation_matrix(&rot),
            ),
        ))
    })
}

/// Reads a trajectory in TUM or KITTI format, chosen by the field count of the
/// first data line (8 → TUM, 12 → KITTI); see [`read_tum`] and
/// [`read_kitti_poses`].
pub fn read_poses(path: &Path) -> Result<Vec<Stamped>> {
    let mut src = TextSource::open(path)?;
    while let Some((line_no, line)) = src.next_line()? {
        if !is_data_line(line) {
            continue;
        }
        return match line.split_whitespace().count() {
            TUM_FIELDS => read_tum(path),
            KITTI_FIELDS => read_kitti_poses(path),
            n => Err(Error::at_line(
                path,
                line_no,
                format!(
                    "expected {TUM_FIELDS} fields (TUM: t x y z qx qy qz qw) or \
                     {KITTI_FIELDS} (KITTI: 3×4 pose matrix), found {n}"
                ),
            )),
        };
    }
    Err(Error::in_file(path, "no poses (empty trajectory)"))
}

/// Streams a TUM trajectory to a temporary file next to the destination and
/// renames it into place on [`TumWriter::finish`], so that readers never see
/// a half-written file. Dropped without `finish`, it removes the temporary
/// file and leaves any existing destination untouched.
///
/// Times are printed with 6 decimals (µs, the resolution of CARMEN and TUM
/// time stamps) and pose fields with 9 (nm and ~1e-9 rad).
pub struct TumWriter {
    path: PathBuf,
    tmp: PathBuf,
    out: Option<BufWriter<File>>,
    rows: usize,
}

impl TumWriter {
    /// Starts writing the trajectory that will end up at `path`. No header
    /// line: tools count on exactly one line per pose.
    pub fn create(path: &Path) -> Result<Self> {
        let tmp = crate::io::atomic::temp_path(path)?;
        let file = File::create(&tmp).map_err(|e| Error::io(&tmp, e))?;
        Ok(Self {
            path: path.to_path_buf(),
            tmp,
            out: Some(BufWriter::new(file)),
            rows: 0,
        })
    }

    fn write_raw(&mut self, args: std::fmt::Arguments<'_>) -> Result<()> {
        let out = self.out.as_mut().expect("TumWriter used after finish");
        out.write_fmt(args).map_err(|e| Error::io(&self.tmp, e))
    }

    /// Appends one pose: time `t` (s) and TUM fields `x y z qx qy qz qw`
    /// (m, quaternion of the body-to-world rotation). Non-finite values are an
    /// error naming the destination and the row, since they would make the
    /// file unreadable.
    pub fn write(&mut self, t: f64, pose: &[f64; 7]) -> Result<()> {
        self.rows += 1;
        if !t.is_finite() || pose.iter().any(|v| !v.is_finite()) {
            return Err(Error::Invalid(format!(
                "{}: pose {} (t = {t}) is not finite: {pose:?}",
                self.path.display(),
                self.rows
            )));
        }
        self.write_raw(format_args!("{}\n", tum_line(t, pose)))
    }

    /// Appends a stamped pose; see [`TumWriter::write`].
    pub fn write_stamped(&mut self, s: &Stamped) -> Result<()> {
        self.write(s.t, &s.tum())
    }

    /// Flushes the data and moves the file to its destination.
    pub fn finish(mut self) -> Result<()> {
        let out = self.out.take().expect("TumWriter finished twice");
        let file = out
            .into_inner()
            .map_err(|e| Error::io(&self.tmp, e.into_error()))?;
        file.sync_all().map_err(|e| Error::io(&self.tmp, e))?;
        drop(file);
        std::fs::rename(&self.tmp, &self.path).map_err(|e| {
            let _ = std::fs::remove_file(&self.tmp);
            Error::io(&self.path, e)
        })
    }
}

impl Drop for TumWriter {
    fn drop(&mut self) {
        if self.out.take().is_some() {
            let _ = std::fs::remove_file(&self.tmp);
        }
    }
}

/// Writes a whole TUM trajectory (`(t, [x y z qx qy qz qw])` rows, s and m)
/// atomically; see [`TumWriter`].
pub fn write_tum(path: &Path, rows: &[(f64, [f64; 7])]) -> Result<()> {
    let mut w = TumWriter::create(path)?;
    for (t, pose) in rows {
        w.write(*t, pose)?;
    }
    w.finish()
}

/// One TUM row, as [`TumWriter`] writes it (no newline): time `t` (s, 6
/// decimals) and `x y z qx qy qz qw` (9 decimals).
pub fn tum_line(t: f64, pose: &[f64; 7]) -> String {
    let [x, y, z, qx, qy, qz, qw] = *pose;
    format!("{t:.6} {x:.9} {y:.9} {z:.9} {qx:.9} {qy:.9} {qz:.9} {qw:.9}")
}

/// Writes stamped poses as a TUM trajectory atomically; see [`TumWriter`].
pub fn write_stamped(path: &Path, poses: &[Stamped]) -> Result<()> {
    let mut w = TumWriter::create(path)?;
    for s in poses {
        w.write_stamped(s)?;
    }
    w.finish()
}

/// Nearest-time lookup into a trajectory whose stamps need not be sorted.
pub struct TimeIndex {
    /// `(t, index into the trajectory)`, sorted by `t`; non-finite times left out.
    sorted: Vec<(f64, usize)>,
}

impl TimeIndex {
    /// Indexes the time stamps of `poses`; poses with a non-finite time can
    /// never be found.
    pub fn new(poses: &[Stamped]) -> Self {
        let mut sorted: Vec<(f64, usize)> = poses
            .iter()
            .enumerate()
            .filter(|(_, s)| s.t.is_finite())
            .map(|(i, s)| (s.t, i))
            .collect();
        sorted.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
        Self { sorted }
    }

    /// The index of the pose whose time is nearest to `t` (s) and the absolute
    /// time difference (s), if one lies within `tol` (s). Ties go to the
    /// earlier stamp.
    pub fn nearest(&self, t: f64, tol: f64) -> Option<(usize, f64)> {
        let k = self.sorted.partition_point(|&(s, _)| s < t);
        let mut best: Option<(usize, f64)> = None;
        for j in [k.checked_sub(1), Some(k)].into_iter().flatten() {
            if let Some(&(s, i)) = self.sorted.get(j) {
                let dt = (s - t).abs();
                if dt <= tol && best.is_none_or(|(_, d)| dt < d) {
                    best = Some((i, dt));
                }
            }
        }
        best
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Vector3;

    fn write(dir: &tempfile::TempDir, name: &str, text: &str) -> PathBuf {
        let p = dir.path().join(name);
        std::fs::write(&p, text).unwrap();
        p
    }

    fn err_text(r: Result<Vec<Stamped>>) -> String {
        r.expect_err("expected an error").to_string()
    }

    #[test]
    fn reads_tum_skipping_comments_and_normalising_quaternions() {
        let dir = tempfile::tempdir().unwrap();
        let p = write(
            &dir,
            "a.tum",
            "# t x y z qx qy qz qw\n\n1.5 1 2 3 0 0 0 2\n  # indented comment\n2.0 0 0 0 0 0 1 1\n",
        );
        let v = read_tum(&p).unwrap();
        assert_eq!(v.len(), 2);
        assert_eq!(v[0].t, 1.5);
        assert_eq!(v[0].pose.translation.vector, Vector3::new(1.0, 2.0, 3.0));
        assert!(v[0].pose.rotation.angle() < 1e-12);
        // (0,0,1,1)/√2 is a 90° turn about z.
        assert!((v[1].pose.rotation.angle() - std::f64::consts::FRAC_PI_2).abs() < 1e-12);
        let q = v[1].pose.rotation.quaternion();
        assert!((q.norm() - 1.0).abs() < 1e-15);
    }

    #[test]
    fn tum_errors_name_file_line_and_reason() {
        let dir = tempfile::tempdir().unwrap();
        let cases = [
            ("0 0 0 0 0 0 0 1\n1 0 0 0 0 0 0 0\n", "line 2", "quaternion"),
            ("# c\n0 0 0 0 0 0 1\n", "line 2", "expected 8 fields"),
            ("0 0 0 0 0 0 0 1 9\n", "line 1", "found 9"),
            ("0 0 nan 0 0 0 0 1\n", "line 1", "y is not finite"),
            ("0 0 0 0 0 0 0 1\n\n0 0 0 x 0 0 0 1\n", "line 3", "z: 'x'"),
            ("0 0 0 0 1e200 1e200 0 0\n", "line 1", "quaternion"),
        ];
        for (i, (text, line, reason)) in cases.iter().enumerate() {
            let p = write(&dir, &format!("bad{i}.tum"), text);
            let msg = err_text(read_tum(&p));
            assert!(
                msg.contains(&format!("bad{i}.tum")) && msg.contains(line) && msg.contains(reason),
                "case {i}: {msg}"
            );
        }
        let empty = write(&dir, "empty.tum", "# nothing\n\n");
        assert!(err_text(read_tum(&empty)).contains("no poses"));
        assert!(err_text(read_poses(&empty)).contains("no poses"));
    }

    #[test]
    fn reads_kitti_poses_with_frame_index_as_time() {
        let dir = tempfile::tempdir().unwrap();
        // Second pose: 90° about z, at (1, 2, 3); the matrix is printed with
        // 7 digits, as KITTI does.
        let p = write(
            &dir,
            "k.txt",
            "1 0 0 0 0 1 0 0 0 0 1 0\n\
             6.123234e-17 -1.000000e+00 0 1 1.000000e+00 6.123234e-17 0 2 0 0 1 3\n",
        );
        let v = read_kitti_poses(&p).unwrap();
        assert_eq!(v.iter().map(|s| s.t).collect::<Vec<_>>(), vec![0.0, 1.0]);
        assert_eq!(v[1].pose.translation.vector, Vector3::new(1.0, 2.0, 3.0));
        let x = v[1].pose.rotation * Vector3::x();
        assert!((x - Vector3::y()).norm() < 1e-9, "{x}");
        assert_eq!(read_poses(&p).unwrap(), v);
    }

    #[test]
    fn kitti_rejects_non_rotations() {
        let dir = tempfile::tempdir().unwrap();
        let scaled = write(
            &dir,
            "s.txt",
            "1 0 0 0 0 1 0 0 0 0 1 0\n2 0 0 0 0 2 0 0 0 0 2 0\n",
        );
        let msg = err_text(read_kitti_poses(&scaled));
        assert!(
            msg.contains("s.txt:line 2") && msg.contains("not a rotation"),
            "{msg}"
        );
        let mirror = write(&dir, "m.txt", "1 0 0 0 0 1 0 0 0 0 -1 0\n");
        let msg = err_text(read_kitti_poses(&mirror));
        assert!(msg.contains("m.txt:line 1") && msg.contains("det"), "{msg}");
    }

    #[test]
    fn read_poses_dispatches_on_field_count() {
        let dir = tempfile::tempdir().unwrap();
        let tum = write(&dir, "a.tum", "# h\n7.25 1 0 0 0 0 0 1\n");
        assert_eq!(read_poses(&tum).unwrap()[0].t, 7.25);
        let kitti = write(&dir, "b.txt", "1 0 0 5 0 1 0 0 0 0 1 0\n");
        let v = read_poses(&kitti).unwrap();
        assert_eq!((v[0].t, v[0].pose.translation.x), (0.0, 5.0));
        let odd = write(&dir, "c.txt", "\n1 2 3 4 5 6 7 8 9 10\n");
        let msg = err_text(read_poses(&odd));
        assert!(
            msg.contains("c.txt:line 2") && msg.contains("found 10"),
            "{msg}"
        );
        // A later line that switches format is caught by the chosen reader.
        let mixed = write(&dir, "d.txt", "0 0 0 0 0 0 0 1\n1 0 0 5 0 1 0 0 0 0 1 0\n");
        assert!(err_text(read_poses(&mixed)).contains("d.txt:line 2"));
    }

    #[test]
    fn write_then_read_round_trips_with_stated_precision() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("out.tum");
        let pose = Pose3::new(
            Vector3::new(1.234567891234, -2.0, 0.5),
            Vector3::new(0.3, -0.2, 1.1),
        );
        let rows = vec![
            (1134864629.895182, pose.to_tum()),
            (
                1134864630.105179,
                Stamped::planar(0.0, 3.0, 4.0, -2.5).tum(),
            ),
        ];
        write_tum(&p, &rows).unwrap();
        let text = std::fs::read_to_string(&p).unwrap();
        assert!(
            text.lines()
                .next()
                .unwrap()
                .starts_with("1134864629.895182 1.234567891 ")
        );
        assert_eq!(text.lines().count(), 2, "one line per pose, no header");
        let back = read_tum(&p).unwrap();
        assert_eq!(back.len(), 2);
        assert!((back[0].t - rows[0].0).abs() < 1e-6);
        let d = back[0].pose.inverse() * pose;
        assert!(d.translation.vector.norm() < 1e-8 && d.rotation.angle() < 1e-8);
        let (x, y, th) = (
            back[1].pose.translation.x,
            back[1].pose.translation.y,
            back[1].pose.rotation.euler_angles().2,
        );
        assert!((x - 3.0).abs() < 1e-9 && (y - 4.0).abs() < 1e-9 && (th + 2.5).abs() < 1e-8);
        // Only the destination is left in the directory.
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);
    }

    #[test]
    fn failed_write_leaves_the_old_file_and_no_temporary() {
        let dir = tempfile::tempdir().unwrap();
        let p = write(&dir, "keep.tum", "0 0 0 0 0 0 0 1\n");
        let rows = [
            (0.0, [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0]),
            (1.0, [f64::NAN; 7]),
        ];
        let msg = write_tum(&p, &rows).unwrap_err().to_string();
        assert!(msg.contains("keep.tum") && msg.contains("pose 2"), "{msg}");
        assert_eq!(std::fs::read_to_string(&p).unwrap(), "0 0 0 0 0 0 0 1\n");
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);
    }

    #[test]
    fn reads_gzip_tum() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("a.tum.gz");
        let mut e = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::default());
        e.write_all(b"1 0 0 0 0 0 0 1\n2 1 0 0 0 0 0 1\n").unwrap();
        std::fs::write(&p, e.finish().unwrap()).unwrap();
        assert_eq!(read_poses(&p).unwrap().len(), 2);
    }

    #[test]
    fn time_index_finds_nearest_within_tolerance() {
        let poses: Vec<Stamped> = [3.0, 1.0, 2.0, 2.0005]
            .iter()
            .map(|&t| Stamped::planar(t, 0.0, 0.0, 0.0))
            .collect();
        let idx = TimeIndex::new(&poses);
        assert_eq!(idx.nearest(1.0004, 1e-3).map(|m| m.0), Some(1));
        assert_eq!(idx.nearest(2.0004, 1e-3).map(|m| m.0), Some(3));
        assert_eq!(idx.nearest(2.0001, 1e-3).map(|m| m.0), Some(2));
        assert_eq!(idx.nearest(3.5, 1e-3), None);
        assert_eq!(idx.nearest(0.0, 1e-3), None);
        assert_eq!(idx.nearest(3.0, 0.0).map(|m| m.0), Some(0));
    }
}
