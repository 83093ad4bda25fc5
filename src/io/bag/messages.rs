//! The ROS message types dpslam reads, decoded from ROS 1 or CDR bytes.
//!
//! Only the fields a SLAM run needs are kept; every field before them is
//! read (and checked) so that the offsets are right. Field layouts follow the
//! `.msg` definitions, identical in ROS 1 and ROS 2 except for `Header`
//! (ROS 1 has a `uint32 seq` first; its stamp is `uint32 secs, nsecs`, ROS
//! 2's `int32 sec, uint32 nanosec`).

// The message structs mirror the ROS message definitions field for field
// (same names, units and frames as in sensor_msgs, nav_msgs, tf2_msgs).
#![allow(missing_docs)]

use super::wire::{Encoding, Wire, WireResult};

/// `std_msgs/Header`, without ROS 1's `seq`.
#[derive(Debug, Clone, PartialEq)]
pub struct Header {
    /// Stamp in nanoseconds.
    pub stamp_ns: i64,
    /// Coordinate frame of the data.
    pub frame_id: String,
}

/// A stamp in nanoseconds as seconds (whole seconds and the fraction
/// converted apart, so that 1000 s stays 1000.0).
pub fn stamp_seconds(ns: i64) -> f64 {
    let s = ns.div_euclid(1_000_000_000);
    let f = ns.rem_euclid(1_000_000_000);
    s as f64 + f as f64 / 1e9
}

impl Header {
    /// The stamp in seconds.
    pub fn stamp_s(&self) -> f64 {
        stamp_seconds(self.stamp_ns)
    }

    fn read(w: &mut Wire, enc: Encoding) -> WireResult<Self> {
        let (sec, nsec) = match enc {
            Encoding::Ros1 => {
                w.u32("header.seq")?;
                (w.u32("header.stamp")? as i64, w.u32("header.stamp")?)
            }
            Encoding::Cdr => (w.i32("header.stamp")? as i64, w.u32("header.stamp")?),
        };
        if nsec >= 1_000_000_000 {
            return Err(format!("header.stamp: {nsec} nanoseconds (must be < 1e9)"));
        }
        Ok(Header {
            stamp_ns: sec * 1_000_000_000 + nsec as i64,
            frame_id: w.string("header.frame_id")?,
        })
    }
}

/// `sensor_msgs/LaserScan`.
#[derive(Debug, Clone, PartialEq)]
pub struct LaserScan {
    pub header: Header,
    pub angle_min: f32,
    pub angle_max: f32,
    pub angle_increment: f32,
    pub range_min: f32,
    pub range_max: f32,
    pub ranges: Vec<f32>,
}

impl LaserScan {
    /// Decodes and checks that the ranges agree with the angles:
    /// `(angle_max − angle_min) / angle_increment + 1` readings (±1, for
    /// drivers that round differently).
    pub fn decode(buf: &[u8], enc: Encoding) -> WireResult<Self> {
        let mut w = Wire::new(buf, enc)?;
        let header = Header::read(&mut w, enc)?;
        let angle_min = w.f32("angle_min")?;
        let angle_max = w.f32("angle_max")?;
        let angle_increment = w.f32("angle_increment")?;
        w.f32("time_increment")?;
        w.f32("scan_time")?;
        let range_min = w.f32("range_min")?;
        let range_max = w.f32("range_max")?;
        let ranges = w.f32_seq("ranges")?;
        w.f32_seq("intensities")?;
        let s = LaserScan {
            header,
            angle_min,
            angle_max,
            angle_increment,
            range_min,
            range_max,
            ranges,
        };
        s.check()?;
        Ok(s)
    }

    fn check(&self) -> WireResult<()> {
        let (a0, a1, da) = (self.angle_min, self.angle_max, self.angle_increment);
        if !(a0.is_finite() && a1.is_finite() && da.is_finite()) || da == 0.0 {
            return Err(format!(
                "angle_min {a0}, angle_max {a1}, angle_increment {da}: not a usable scan geometry"
            ));
        }
        if self.ranges.is_empty() {
            return Err("no ranges".into());
        }
        let expected = ((a1 as f64 - a0 as f64) / da as f64).round() + 1.0;
        let n = self.ranges.len() as f64;
        if (n - expected).abs() > 1.0 {
            return Err(format!(
                "{} ranges, but angle_min {a0}, angle_max {a1}, angle_increment {da} \
                 give {expected} beams",
                self.ranges.len()
            ));
        }
        if !(self.range_max.is_finite() && self.range_max > 0.0) {
            return Err(format!(
                "range_max {}: must be finite and > 0",
                self.range_max
            ));
        }
        Ok(())
    }
}

/// A rigid transform: translation and unit quaternion `[x, y, z, w]`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Transform {
    pub translation: [f64; 3],
    pub rotation: [f64; 4],
}

impl Transform {
    fn read(w: &mut Wire) -> WireResult<Self> {
        let translation = w.f64_array::<3>("translation")?;
        let rotation = w.f64_array::<4>("rotation")?;
        let t = Transform {
            translation,
            rotation,
        };
        if !translation.iter().chain(&rotation).all(|v| v.is_finite()) {
            return Err(format!("non-finite transform {t:?}"));
        }
        if rotation.iter().map(|v| v * v).sum::<f64>() < 1e-12 {
            return Err("zero quaternion".into());
        }
        Ok(t)
    }

    /// The heading (rotation about z, rad) of the quaternion.
    pub fn yaw(&self) -> f64 {
        let [x, y, z, w] = self.rotation;
        (2.0 * (w * z + x * y)).atan2(1.0 - 2.0 * (y * y + z * z))
    }

    /// As a 3-D isometry.
    pub fn to_pose3(&self) -> crate::geometry::Pose3 {
        let [x, y, z, w] = self.rotation;
        let q = nalgebra::UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(w, x, y, z));
        let [tx, ty, tz] = self.translation;
        crate::geometry::Pose3::from_parts(nalgebra::Translation3::new(tx, ty, tz), q)
    }

    /// As a planar pose (x, y, yaw).
    pub fn to_pose2(&self) -> crate::geometry::Pose2 {
        crate::geometry::pose2(self.translation[0], self.translation[1], self.yaw())
    }
}

/// `nav_msgs/Odometry`: the pose of `child_frame_id` in `header.frame_id`.
#[derive(Debug, Clone, PartialEq)]
pub struct Odometry {
    pub header: Header,
    pub child_frame_id: String,
    pub pose: Transform,
}

impl Odometry {
    pub fn decode(buf: &[u8], enc: Encoding) -> WireResult<Self> {
        let mut w = Wire::new(buf, enc)?;
        let header = Header::read(&mut w, enc)?;
        let child_frame_id = w.string("child_frame_id")?;
        let pose = Transform::read(&mut w)?;
        w.f64_array::<36>("pose.covariance")?;
        // twist: 6 f64 + covariance 36 f64
        w.f64_array::<42>("twist")?;
        Ok(Odometry {
            header,
            child_frame_id,
            pose,
        })
    }
}

/// `geometry_msgs/TransformStamped`: `child_frame_id` in `header.frame_id`.
#[derive(Debug, Clone, PartialEq)]
pub struct TransformStamped {
    pub header: Header,
    pub child_frame_id: String,
    pub transform: Transform,
}

/// `tf2_msgs/TFMessage` (ROS 1 `tf/tfMessage` has the same layout).
pub fn decode_tf(buf: &[u8], enc: Encoding) -> WireResult<Vec<TransformStamped>> {
    let mut w = Wire::new(buf, enc)?;
    // Each transform is at least a header stamp + two empty strings + 7 f64.
    let n = w.seq_len("transforms", 8 + 8 + 56)?;
    let mut out = Vec::with_capacity(n);
    for _ in 0..n {
        let header = Header::read(&mut w, enc)?;
        let child_frame_id = w.string("child_frame_id")?;
        let transform = Transform::read(&mut w)?;
        out.push(TransformStamped {
            header,
            child_frame_id,
            transform,
        });
    }
    Ok(out)
}

/// `sensor_msgs/PointField` data types.
const POINT_FIELD_SIZES: [usize; 9] = [0, 1, 1, 2, 2, 4, 4, 4, 8];
const FLOAT32: u8 = 7;
const FLOAT64: u8 = 8;

/// `sensor_msgs/PointField`.
#[derive(Debug, Clone, PartialEq)]
pub struct PointField {
    pub name: String,
    pub offset: u32,
    pub datatype: u8,
    pub count: u32,
}

/// `sensor_msgs/PointCloud2`, with its data borrowed from the message.
#[derive(Debug, Clone, PartialEq)]
pub struct PointCloud2<'a> {
    pub header: Header,
    pub height: u32,
    pub width: u32,
    pub fields: Vec<PointField>,
    pub is_bigendian: bool,
    pub point_step: u32,
    pub row_step: u32,
    pub data: &'a [u8],
}

impl<'a> PointCloud2<'a> {
    pub fn decode(buf: &'a [u8], enc: Encoding) -> WireResult<Self> {
        let mut w = Wire::new(buf, enc)?;
        let header = Header::read(&mut w, enc)?;
        let height = w.u32("height")?;
        let width = w.u32("width")?;
        let nf = w.seq_len("fields", 4 + 4 + 1 + 4)?;
        let mut fields = Vec::with_capacity(nf);
        for _ in 0..nf {
            fields.push(PointField {
                name: w.string("fields.name")?,
                offset: w.u32("fields.offset")?,
                datatype: w.u8("fields.datatype")?,
                count: w.u32("fields.count")?,
            });
        }
        let is_bigendian = w.bool("is_bigendian")?;
        let point_step = w.u32("point_step")?;
        let row_step = w.u32("row_step")?;
        let data = w.byte_seq("data")?;
        Ok(PointCloud2 {
            header,
            height,
            width,
            fields,
            is_bigendian,
            point_step,
            row_step,
            data,
        })
    }

    /// The points' x y z in the cloud's frame (f32 or f64 fields, any byte
    /// order, rows of `row_step` bytes), NaN and ±inf points dropped, as are
    /// points exactly at the origin ("no return" in many drivers).
    pub fn xyz(&self) -> WireResult<Vec<[f32; 3]>> {
        let field = |name: &str| -> WireResult<(usize, u8)> {
            let f = self.fields.iter().find(|f| f.name == name).ok_or_else(|| {
                let names: Vec<_> = self.fields.iter().map(|f| f.name.as_str()).collect();
                format!("no field '{name}' (fields: {})", names.join(", "))
            })?;
            if f.datatype != FLOAT32 && f.datatype != FLOAT64 {
                return Err(format!(
                    "field '{name}' has datatype {} (only FLOAT32 = 7 and FLOAT64 = 8 are read)",
                    f.datatype
                ));
            }
            let size = POINT_FIELD_SIZES[f.datatype as usize];
            if f.offset as usize + size > self.point_step as usize {
                return Err(format!(
                    "field '{name}' at offset {} does not fit in point_step {}",
                    f.offset, self.point_step
                ));
            }
            Ok((f.offset as usize, f.datatype))
        };
        let fx = field("x")?;
        let fy = field("y")?;
        let fz = field("z")?;
        let (h, wd, ps, rs) = (
            self.height as usize,
            self.width as usize,
            self.point_step as usize,
            self.row_step as usize,
        );
        if ps == 0 || rs < wd.saturating_mul(ps) {
            return Err(format!(
                "point_step {ps}, row_step {rs} for {wd} points per row: inconsistent"
            ));
        }
        let need = h.saturating_mul(rs);
        if self.data.len() < need {
            return Err(format!(
                "data holds {} bytes, but height {h} × row_step {rs} = {need}",
                self.data.len()
            ));
        }
        let big = self.is_bigendian;
        let read = |p: &[u8], (off, dt): (usize, u8)| -> f64 {
            if dt == FLOAT32 {
                let b: [u8; 4] = p[off..off + 4].try_into().expect("4 bytes");
                (if big {
                    f32::from_be_bytes(b)
                } else {
                    f32::from_le_bytes(b)
                }) as f64
            } else {
                let b: [u8; 8] = p[off..off + 8].try_into().expect("8 bytes");
                if big {
                    f64::from_be_bytes(b)
                } else {
                    f64::from_le_bytes(b)
                }
            }
        };
        let mut out = Vec::with_capacity(h * wd);
        for r in 0..h {
            let row = &self.data[r * rs..r * rs + wd * ps];
            for p in row.chunks_exact(ps) {
                let v = [read(p, fx), read(p, fy), read(p, fz)];
                if v.iter().all(|c| c.is_finite()) && v != [0.0; 3] {
                    out.push([v[0] as f32, v[1] as f32, v[2] as f32]);
                }
            }
        }
        Ok(out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cloud(big: bool, f64s: bool, pts: &[[f64; 3]]) -> Vec<u8> {
        // ROS 1 layout: header, height 1, width n, 3 fields, ...
        let mut b = Vec::new();
        b.extend(0u32.to_le_bytes());
        b.extend(7u32.to_le_bytes());
        b.extend(5u32.to_le_bytes());
        b.extend(1u32.to_le_bytes());
        b.push(b'v');
        b.extend(1u32.to_le_bytes());
        b.extend((pts.len() as u32).to_le_bytes());
        let size = if f64s { 8u32 } else { 4 };
        b.extend(3u32.to_le_bytes());
        for (i, n) in ["x", "y", "z"].iter().enumerate() {
            b.extend(1u32.to_le_bytes());
            b.extend(n.as_bytes());
            b.extend((i as u32 * size).to_le_bytes());
            b.push(if f64s { FLOAT64 } else { FLOAT32 });
            b.extend(1u32.to_le_bytes());
        }
        b.push(big as u8);
        let step = 3 * size + 4; // one padding field
        b.extend(step.to_le_bytes());
        b.extend((step * pts.len() as u32).to_le_bytes());
        let mut data = Vec::new();
        for p in pts {
            for c in p {
                match (f64s, big) {
                    (true, true) => data.extend(c.to_be_bytes()),
                    (true, false) => data.extend(c.to_le_bytes()),
                    (false, true) => data.extend((*c as f32).to_be_bytes()),
                    (false, false) => data.extend((*c as f32).to_le_bytes()),
                }
            }
            data.extend([9, 9, 9, 9]);
        }
        b.extend((data.len() as u32).to_le_bytes());
        b.extend(data);
        b.push(1);
        b
    }

    #[test]
    fn point_clouds_in_f32_f64_and_both_byte_orders_drop_nan_points() {
        let pts = [[1.0, 2.0, 3.0], [f64::NAN, 0.0, 0.0], [-1.5, 0.25, 8.0]];
        for big in [false, true] {
            for f64s in [false, true] {
                let b = cloud(big, f64s, &pts);
                let c = PointCloud2::decode(&b, Encoding::Ros1).unwrap();
                assert_eq!(c.header.frame_id, "v");
                assert_eq!(c.header.stamp_ns, 7_000_000_005);
                let xyz = c.xyz().unwrap();
                assert_eq!(
                    xyz,
                    vec![[1.0, 2.0, 3.0], [-1.5, 0.25, 8.0]],
                    "{big} {f64s}"
                );
            }
        }
        // data shorter than height × row_step
        let mut b = cloud(false, false, &pts);
        let n = b.len();
        b[n - 57..n - 53].copy_from_slice(&1000u32.to_le_bytes()); // row_step
        let c = PointCloud2::decode(&b, Encoding::Ros1).unwrap();
        let e = c.xyz().unwrap_err();
        assert!(e.contains("row_step"), "{e}");
    }

    #[test]
    fn a_scan_whose_ranges_disagree_with_its_angles_is_an_error() {
        let mut b = Vec::new();
        b.extend([0, 1, 0, 0]);
        b.extend(3i32.to_le_bytes());
        b.extend(0u32.to_le_bytes());
        b.extend(1u32.to_le_bytes());
        b.extend([0, 0, 0, 0]); // "" + NUL + pad
        for v in [-1.0f32, 1.0, 0.5, 0.0, 0.0, 0.1, 30.0] {
            b.extend(v.to_le_bytes());
        }
        let good = |n: u32| {
            let mut m = b.clone();
            m.extend(n.to_le_bytes());
            for _ in 0..n {
                m.extend(2.0f32.to_le_bytes());
            }
            m.extend(0u32.to_le_bytes());
            m
        };
        let s = LaserScan::decode(&good(5), Encoding::Cdr).unwrap();
        assert_eq!(s.ranges.len(), 5);
        assert_eq!(s.header.stamp_s(), 3.0);
        let e = LaserScan::decode(&good(9), Encoding::Cdr).unwrap_err();
        assert!(e.contains("9 ranges") && e.contains("give 5 beams"), "{e}");
    }
}
