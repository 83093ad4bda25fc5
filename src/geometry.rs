//! Rigid poses, generic over dimension.
//!
//! The filter, the DP-map and the laser model are written once against
//! [`Pose<D>`]; 2-D uses [`Pose2`] (`nalgebra::Isometry2<f64>`) and 3-D uses
//! [`Pose3`] (`nalgebra::Isometry3<f64>`). A pose maps points from its local
//! frame (robot or sensor) into the parent frame (map), in metres.

use nalgebra::{
    Isometry2, Isometry3, Point2, Point3, Translation3, UnitQuaternion, Vector2, Vector3,
};
use std::fmt::Debug;

/// 2-D rigid pose: x, y in metres, θ in radians, counter-clockwise.
pub type Pose2 = Isometry2<f64>;
/// 3-D rigid pose (6-DoF), metres, right-handed, z up.
pub type Pose3 = Isometry3<f64>;

/// A rigid transform in `D` dimensions.
pub trait Pose<const D: usize>: Copy + Send + Sync + Debug + PartialEq + 'static {
    /// The identity transform.
    fn identity() -> Self;
    /// `self ∘ rhs`: first `rhs`, then `self` (nalgebra's `self * rhs`).
    fn compose(&self, rhs: &Self) -> Self;
    /// The inverse transform.
    fn inverse(&self) -> Self;
    /// Maps a point from the local frame into the parent frame.
    fn transform_point(&self, p: [f64; D]) -> [f64; D];
    /// Rotates a direction from the local frame into the parent frame.
    fn rotate(&self, v: [f64; D]) -> [f64; D];
    /// The origin of the local frame, in the parent frame.
    fn translation(&self) -> [f64; D];
    /// TUM fields `x y z qx qy qz qw` (2-D: z = 0, rotation about z).
    fn to_tum(&self) -> [f64; 7];
    /// Inverse of [`Pose::to_tum`]; a 2-D pose keeps x, y and the yaw.
    fn from_tum(v: [f64; 7]) -> Self;
    /// Rotation angle of the transform, radians in [0, π].
    fn rotation_angle(&self) -> f64;
    /// Degrees of freedom of the pose: 3 in 2-D (`x, y, θ`), 6 in 3-D.
    const DOF: usize;
    /// The pose reached from `self` by the motion `delta` (in the frame of
    /// `self`) and then the body-frame perturbation `xi` (in the frame of the
    /// moved pose): `self · delta · ε(xi)`, where `ε` translates by the
    /// translational part of `xi` (m) and rotates by its rotational part
    /// (rad). 2-D: `xi = [x, y, θ]`; 3-D: `xi = [ωx, ωy, ωz, tx, ty, tz]`
    /// (ω a small-angle axis vector). `xi.len()` is [`Pose::DOF`].
    fn perturbed(&self, delta: &Self, xi: &[f64]) -> Self;
    /// The inverse of [`Pose::perturbed`] with the identity motion: the
    /// body-frame perturbation `xi` ([`Pose::DOF`] components, same order
    /// and units) with `self · ε(xi) = other`. 2-D: exact; 3-D: ω is the
    /// rotation's axis-angle vector, exact for angles below π.
    fn perturbation_to(&self, other: &Self) -> Vec<f64>;
    /// All components are finite.
    fn is_finite(&self) -> bool {
        self.to_tum().iter().all(|v| v.is_finite())
    }
}

/// Builds a 2-D pose from x, y (m) and θ (rad).
pub fn pose2(x: f64, y: f64, theta: f64) -> Pose2 {
    Isometry2::new(Vector2::new(x, y), theta)
}

/// x, y (m) and θ (rad, in (−π, π]) of a 2-D pose.
pub fn xyt(p: &Pose2) -> (f64, f64, f64) {
    (p.translation.x, p.translation.y, p.rotation.angle())
}

/// Wraps an angle into (−π, π].
pub fn wrap_angle(a: f64) -> f64 {
    let mut a = a % std::f64::consts::TAU;
    if a > std::f64::consts::PI {
        a -= std::f64::consts::TAU;
    } else if a <= -std::f64::consts::PI {
        a += std::f64::consts::TAU;
    }
    a
}

impl Pose<2> for Pose2 {
    fn identity() -> Self {
        Isometry2::identity()
    }
    fn compose(&self, rhs: &Self) -> Self {
        self * rhs
    }
    fn inverse(&self) -> Self {
        Isometry2::inverse(self)
    }
    fn transform_point(&self, p: [f64; 2]) -> [f64; 2] {
        let q = self * Point2::new(p[0], p[1]);
        [q.x, q.y]
    }
    fn rotate(&self, v: [f64; 2]) -> [f64; 2] {
        let q = self.rotation * Vector2::new(v[0], v[1]);
        [q.x, q.y]
    }
    fn translation(&self) -> [f64; 2] {
        [self.translation.x, self.translation.y]
    }
    fn to_tum(&self) -> [f64; 7] {
        let half = self.rotation.angle() / 2.0;
        [
            self.translation.x,
            self.translation.y,
            0.0,
            0.0,
            0.0,
            half.sin(),
            half.cos(),
        ]
    }
    fn from_tum(v: [f64; 7]) -> Self {
        let q = UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(v[6], v[3], v[4], v[5]));
        let (_, _, yaw) = q.euler_angles();
        pose2(v[0], v[1], yaw)
    }
    fn rotation_angle(&self) -> f64 {
        self.rotation.angle().abs()
    }
    const DOF: usize = 3;
    fn perturbed(&self, delta: &Self, xi: &[f64]) -> Self {
        self * delta * pose2(xi[0], xi[1], xi[2])
    }
    fn perturbation_to(&self, other: &Self) -> Vec<f64> {
        let e = self.inverse() * other;
        vec![e.translation.x, e.translation.y, e.rotation.angle()]
    }
}

impl Pose<3> for Pose3 {
    fn identity() -> Self {
        Isometry3::identity()
    }
    fn compose(&self, rhs: &Self) -> Self {
        // Keep the quaternion unit: rounding errors compound along long chains.
        let mut p = self * rhs;
        p.rotation.renormalize();
        p
    }
    fn inverse(&self) -> Self {
        Isometry3::inverse(self)
    }
    fn transform_point(&self, p: [f64; 3]) -> [f64; 3] {
        let q = self * Point3::new(p[0], p[1], p[2]);
        [q.x, q.y, q.z]
    }
    fn rotate(&self, v: [f64; 3]) -> [f64; 3] {
        let q = self.rotation * Vector3::new(v[0], v[1], v[2]);
        [q.x, q.y, q.z]
    }
    fn translation(&self) -> [f64; 3] {
        [self.translation.x, self.translation.y, self.translation.z]
    }
    fn to_tum(&self) -> [f64; 7] {
        let q = self.rotation.quaternion();
        [
            self.translation.x,
            self.translation.y,
            self.translation.z,
            q.i,
            q.j,
            q.k,
            q.w,
        ]
    }
    fn from_tum(v: [f64; 7]) -> Self {
        let q = UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(v[6], v[3], v[4], v[5]));
        Isometry3::from_parts(Translation3::new(v[0], v[1], v[2]), q)
    }
    fn rotation_angle(&self) -> f64 {
        self.rotation.angle()
    }
    const DOF: usize = 6;
    fn perturbed(&self, delta: &Self, xi: &[f64]) -> Self {
        let step = Isometry3::from_parts(
            Translation3::new(xi[3], xi[4], xi[5]),
            UnitQuaternion::from_scaled_axis(Vector3::new(xi[0], xi[1], xi[2])),
        );
        (self * delta).compose(&step)
    }
    fn perturbation_to(&self, other: &Self) -> Vec<f64> {
        let e = self.inverse() * other;
        let w = e.rotation.scaled_axis();
        let t = e.translation.vector;
        vec![w.x, w.y, w.z, t.x, t.y, t.z]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tum_round_trip_2d_and_3d() {
        let p = pose2(1.5, -2.0, 2.9);
        let q = <Pose2 as Pose<2>>::from_tum(p.to_tum());
        assert!((xyt(&q).2 - 2.9).abs() < 1e-12 && (q.translation.x - 1.5).abs() < 1e-12);
        let r = Pose3::new(Vector3::new(1.0, 2.0, 3.0), Vector3::new(0.1, -0.2, 0.3));
        let s = <Pose3 as Pose<3>>::from_tum(r.to_tum());
        assert!((r.inverse() * s).translation.vector.norm() < 1e-12);
        assert!(Pose::<3>::rotation_angle(&(r.inverse() * s)) < 1e-9);
    }

    #[test]
    fn compose_applies_right_first() {
        let a = pose2(1.0, 0.0, std::f64::consts::FRAC_PI_2);
        let b = pose2(1.0, 0.0, 0.0);
        let p = Pose::<2>::transform_point(&Pose::<2>::compose(&a, &b), [0.0, 0.0]);
        assert!((p[0] - 1.0).abs() < 1e-12 && (p[1] - 1.0).abs() < 1e-12);
    }

    #[test]
    fn wrap_angle_range() {
        for a in [-10.0, -3.2, 0.0, 3.2, 7.0, std::f64::consts::PI] {
            let w = wrap_angle(a);
            assert!(w > -std::f64::consts::PI - 1e-12 && w <= std::f64::consts::PI + 1e-12);
            assert!(
                ((w - a) / std::f64::consts::TAU).fract().abs() < 1e-9
                    || ((w - a) / std::f64::consts::TAU).fract().abs() > 1.0 - 1e-9
            );
        }
    }
}
