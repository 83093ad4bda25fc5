//! The f32 point path on glam (SIMD [`Vec3A`]): a sweep's points from the
//! reader to the registration's down-sampled clouds and local maps.
//!
//! Sweeps arrive as f32 and are tens of thousands of points each: their
//! transforms and voxel grids run here, four lanes at a time. Poses and the
//! registration's linear algebra stay f64 on nalgebra ([`crate::icp`]); a
//! cloud crosses over once, after down-sampling, with [`to_f64`].

use crate::geometry::Pose3;
use glam::{Affine3A, Quat, Vec3A};
use nalgebra::Vector3;
use rustc_hash::FxHashMap;

/// A sweep's points (sensor frame, m) as SIMD vectors.
pub fn from_sweep(points: &[[f32; 3]]) -> impl Iterator<Item = Vec3A> + '_ {
    points.iter().map(|p| Vec3A::from_array(*p))
}

/// `pose` (sensor → map, f64) as an f32 affine transform for points.
pub fn affine(pose: &Pose3) -> Affine3A {
    let q = pose.rotation.quaternion();
    let t = pose.translation.vector;
    Affine3A::from_rotation_translation(
        Quat::from_xyzw(q.i as f32, q.j as f32, q.k as f32, q.w as f32),
        glam::Vec3::new(t.x as f32, t.y as f32, t.z as f32),
    )
}

/// The voxel of edge `size` (m) containing `p`.
#[inline]
pub fn voxel_of(p: Vec3A, size: f32) -> [i32; 3] {
    let k = (p / size).floor();
    [k.x as i32, k.y as i32, k.z as i32]
}

/// Centroid down-sampling: one point per voxel of edge `size` (m), the mean
/// of the points in it, in the order the voxels are first seen (so the
/// result is the same on every run).
pub fn voxel_downsample(points: impl IntoIterator<Item = Vec3A>, size: f32) -> Vec<Vec3A> {
    let mut slot: FxHashMap<[i32; 3], u32> = FxHashMap::default();
    let mut acc: Vec<(Vec3A, u32)> = Vec::new();
    for p in points {
        let i = *slot.entry(voxel_of(p, size)).or_insert_with(|| {
            acc.push((Vec3A::ZERO, 0));
            (acc.len() - 1) as u32
        }) as usize;
        acc[i].0 += p;
        acc[i].1 += 1;
    }
    acc.into_iter().map(|(s, n)| s / n as f32).collect()
}

/// A point as nalgebra f64, for the registration's linear algebra.
#[inline]
pub fn to_f64(p: Vec3A) -> Vector3<f64> {
    Vector3::new(p.x as f64, p.y as f64, p.z as f64)
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Translation3, UnitQuaternion};

    #[test]
    fn affine_matches_the_f64_pose() {
        let pose = Pose3::from_parts(
            Translation3::new(12.5, -3.25, 1.5),
            UnitQuaternion::from_euler_angles(0.1, -0.2, 2.5),
        );
        let a = affine(&pose);
        for p in [[1.0f32, 2.0, 3.0], [-40.0, 0.5, -2.0]] {
            let got = a.transform_point3a(Vec3A::from_array(p));
            let want = pose * nalgebra::Point3::new(p[0] as f64, p[1] as f64, p[2] as f64);
            assert!((to_f64(got) - want.coords).norm() < 1e-4, "{got} vs {want}");
        }
    }

    #[test]
    fn voxel_downsample_keeps_one_centroid_per_voxel_in_first_seen_order() {
        let pts = [
            Vec3A::new(0.05, 0.05, 0.05),
            Vec3A::new(1.05, 0.0, 0.0),
            Vec3A::new(0.15, 0.15, 0.15),
            Vec3A::new(-0.05, 0.0, 0.0),
        ];
        let d = voxel_downsample(pts, 0.2);
        assert_eq!(d.len(), 3);
        assert!((d[0] - Vec3A::splat(0.1)).length() < 1e-6);
        assert_eq!(d[1], Vec3A::new(1.05, 0.0, 0.0));
        assert_eq!(d[2], Vec3A::new(-0.05, 0.0, 0.0));
    }
}
