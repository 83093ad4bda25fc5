//! 3DTK "uos" scans (`.3d`, centimetres, left-handed, y up) and the
//! `.pose` file beside each.

use super::collector::Collector;
use super::text::parse_xyz_lines;
use crate::error::{Error, Result};
use crate::geometry::Pose3;
use crate::io::ply::lines_from;
use crate::io::source::read_bytes;
use nalgebra::{Translation3, UnitQuaternion, Vector3};
use std::path::{Path, PathBuf};

/// Reads a `.3d` scan: its points converted by [`threedtk_point`], and the
/// pose of its `.pose` file, if there is one.
pub(super) fn read(path: &Path, bytes: &[u8]) -> Result<(Vec<[f32; 3]>, Option<Pose3>)> {
    let mut c = Collector::new(path, threedtk_point);
    parse_xyz_lines(path, bytes, true, &mut c)?;
    let prior = threedtk_pose_file(path)?;
    Ok((c.finish()?, prior))
}

/// Converts a 3DTK point (centimetres, left-handed, y up, z forward) into
/// metres, right-handed, z up, x forward: `(x, y, z) → (z, −x, y) / 100`.
///
/// This is the inverse of 3DTK's own `ScanDataTransform_xyz`
/// (`src/scanio/helper.cc`), which maps right-handed z-up metres into its
/// convention as `(x, y, z) → (−100·y, 100·z, 100·x)`.
pub fn threedtk_point(p: [f64; 3]) -> [f64; 3] {
    [p[2] / 100.0, -p[0] / 100.0, p[1] / 100.0]
}

/// Converts a 3DTK `.pose` (position `t` in centimetres, Euler angles
/// `rx ry rz` in degrees, both in 3DTK's left-handed y-up frame) into a pose in
/// the converted frame of [`threedtk_point`].
///
/// 3DTK builds the scan-to-world matrix with `EulerToMatrix4`
/// (`include/slam6d/globals.icc`): `M = Rx(rx)·Ry(ry)·Rz(rz)` with the usual
/// right-hand-rule rotation matrices written in 3DTK's coordinates, and maps a
/// point as `w = M·p + t`. With `C` the linear part of [`threedtk_point`]
/// (`C·p = (z, −x, y)`, a reflection, det −1), the converted world point is
/// `C·w/100 = (C·M·Cᵀ)(C·p/100) + C·t/100`. So the converted pose has
/// rotation `C·M·Cᵀ` (a proper rotation) and translation `C·t/100`.
/// Conjugating by the reflection `C` turns a rotation by θ about axis `a` into
/// a rotation by θ about `−C·a`, hence
/// `C·M·Cᵀ = Ry(rx)·Rz(−ry)·Rx(−rz)` in the converted frame: 3DTK's yaw about
/// its up axis `ry` becomes a yaw of `−ry` about z.
pub fn threedtk_pose(t_cm: [f64; 3], angles_deg: [f64; 3]) -> Pose3 {
    let [rx, ry, rz] = angles_deg.map(f64::to_radians);
    let q = UnitQuaternion::from_axis_angle(&Vector3::y_axis(), rx)
        * UnitQuaternion::from_axis_angle(&Vector3::z_axis(), -ry)
        * UnitQuaternion::from_axis_angle(&Vector3::x_axis(), -rz);
    let t = threedtk_point(t_cm);
    Pose3::from_parts(Translation3::new(t[0], t[1], t[2]), q)
}

/// The path of the `.pose` file of a `.3d` scan, if one exists.
fn threedtk_pose_path(scan: &Path) -> Option<PathBuf> {
    let name = scan.file_name()?.to_string_lossy().into_owned();
    let lower = name.to_ascii_lowercase();
    let stem_len = lower
        .strip_suffix(".gz")
        .unwrap_or(&lower)
        .strip_suffix(".3d")?
        .len();
    let stem = &name[..stem_len];
    [".pose", ".pose.gz"]
        .iter()
        .map(|s| scan.with_file_name(format!("{stem}{s}")))
        .find(|p| p.is_file())
}

/// Reads the `.pose` beside a `.3d` scan: six numbers `x y z` (cm) and
/// `rx ry rz` (degrees), normally on two lines.
fn threedtk_pose_file(scan: &Path) -> Result<Option<Pose3>> {
    let Some(path) = threedtk_pose_path(scan) else {
        return Ok(None);
    };
    let bytes = read_bytes(&path)?;
    let mut vals = Vec::with_capacity(6);
    let mut last = 0;
    for (no, _, raw) in lines_from(&bytes, 0, 1) {
        last = no;
        let text =
            std::str::from_utf8(raw).map_err(|_| Error::at_line(&path, no, "line is not text"))?;
        for t in text.split_ascii_whitespace() {
            let v: f64 = t
                .parse()
                .map_err(|_| Error::at_line(&path, no, format!("'{t}' is not a number")))?;
            if !v.is_finite() {
                return Err(Error::at_line(
                    &path,
                    no,
                    format!("non-finite pose value '{t}'"),
                ));
            }
            if vals.len() == 6 {
                return Err(Error::at_line(
                    &path,
                    no,
                    "more than 6 numbers: expected 'x y z' (cm) and 'rx ry rz' (degrees)",
                ));
            }
            vals.push(v);
        }
    }
    if vals.len() != 6 {
        return Err(Error::at_line(
            &path,
            last.max(1),
            format!(
                "found {} numbers, expected 6: 'x y z' (cm) and 'rx ry rz' (degrees)",
                vals.len()
            ),
        ));
    }
    Ok(Some(threedtk_pose(
        [vals[0], vals[1], vals[2]],
        [vals[3], vals[4], vals[5]],
    )))
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Matrix3, Point3};

    /// 3DTK's `EulerToMatrix4` rotation, transcribed element by element from
    /// its column-major `alignxf` (angles in radians).
    fn threedtk_matrix(rx: f64, ry: f64, rz: f64) -> Matrix3<f64> {
        let (sx, cx) = rx.sin_cos();
        let (sy, cy) = ry.sin_cos();
        let (sz, cz) = rz.sin_cos();
        let a = [
            cy * cz,
            sx * sy * cz + cx * sz,
            -cx * sy * cz + sx * sz,
            -cy * sz,
            -sx * sy * sz + cx * cz,
            cx * sy * sz + sx * cz,
            sy,
            -sx * cy,
            cx * cy,
        ];
        Matrix3::from_column_slice(&a)
    }

    #[test]
    fn threedtk_pose_matches_conjugated_euler_matrix_of_3dtk() {
        let c = Matrix3::new(0.0, 0.0, 1.0, -1.0, 0.0, 0.0, 0.0, 1.0, 0.0);
        for (rx, ry, rz) in [
            (10.0, 0.0, 0.0),
            (0.0, 25.0, 0.0),
            (0.0, 0.0, -40.0),
            (1.3569, -0.8524, -0.5622),
            (30.0, -70.0, 120.0),
        ] {
            let m = threedtk_matrix(
                f64::to_radians(rx),
                f64::to_radians(ry),
                f64::to_radians(rz),
            );
            let want = c * m * c.transpose();
            let got = threedtk_pose([1.0, 2.0, 3.0], [rx, ry, rz]);
            let r = got.rotation.to_rotation_matrix();
            assert!((r.matrix() - want).norm() < 1e-12, "angles {rx} {ry} {rz}");
            // And the whole map agrees on a point: C(M p + t)/100 == pose(C p/100).
            let p = [37.0, -12.0, 250.0];
            let w = m * Vector3::new(p[0], p[1], p[2]) + Vector3::new(1.0, 2.0, 3.0);
            let want_w = threedtk_point([w.x, w.y, w.z]);
            let q = threedtk_point(p);
            let got_w = got * Point3::new(q[0], q[1], q[2]);
            for k in 0..3 {
                assert!((got_w[k] - want_w[k]).abs() < 1e-12);
            }
        }
    }

    #[test]
    fn threedtk_point_is_rh_z_up_metres() {
        // 3DTK: x right, y up, z forward (cm) -> x forward, y left, z up (m).
        assert_eq!(threedtk_point([0.0, 0.0, 100.0]), [1.0, 0.0, 0.0]);
        assert_eq!(threedtk_point([100.0, 0.0, 0.0]), [0.0, -1.0, 0.0]);
        assert_eq!(threedtk_point([0.0, 100.0, 0.0]), [0.0, 0.0, 1.0]);
    }
}
