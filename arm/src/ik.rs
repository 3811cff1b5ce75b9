//! Inverse kinematics and DROID's action spaces.
//!
//! [`Ik::solve`] runs damped-least-squares iterations on the URDF Jacobian from a seed
//! configuration toward a TCP pose, with a nullspace pull toward DROID's reset pose and the
//! joints kept a margin inside their limits. DROID's RobotIKSolver is the behavioural reference
//! for the action spaces: a cartesian velocity in [-1, 1] is at most 0.075 m and 0.15 rad per
//! control step ([`velocity_to_delta`]); absolute poses are xyz + extrinsic xyz euler (DROID's
//! `cartesian_position`) or xyz + axis-angle.

use crate::kinematics::{DOF, Fr3Kinematics, Joints};
use nalgebra::{Isometry3, Matrix6, SMatrix, SVector, Translation3, UnitQuaternion, Vector3};

/// The largest TCP translation (m) and rotation (rad) a full-scale velocity action asks for in
/// one control step (DROID: `max_lin_delta`, `max_rot_delta`).
pub const MAX_LIN_DELTA: f64 = 0.075;
pub const MAX_ROT_DELTA: f64 = 0.15;

/// DROID's cartesian velocity action -> (translation, rotation vector) for one step. The linear
/// and angular parts are each scaled down to norm 1 first if longer (DROID does the same).
pub fn velocity_to_delta(v: &[f64; 6]) -> (Vector3<f64>, Vector3<f64>) {
    let unit = |x: Vector3<f64>| if x.norm() > 1.0 { x / x.norm() } else { x };
    (unit(Vector3::new(v[0], v[1], v[2])) * MAX_LIN_DELTA, unit(Vector3::new(v[3], v[4], v[5])) * MAX_ROT_DELTA)
}

/// The inverse of [`velocity_to_delta`] for deltas inside the limits (recording a velocity
/// action for a pose step); longer deltas come out clipped to norm 1.
pub fn delta_to_velocity(lin: &Vector3<f64>, rot: &Vector3<f64>) -> [f64; 6] {
    let unit = |x: Vector3<f64>| if x.norm() > 1.0 { x / x.norm() } else { x };
    let l = unit(lin / MAX_LIN_DELTA);
    let r = unit(rot / MAX_ROT_DELTA);
    [l.x, l.y, l.z, r.x, r.y, r.z]
}

/// The pose one velocity action moves `from` to: translation added in the base frame, rotation
/// applied in the base frame (DROID adds euler angles as rotations composed on the left).
pub fn apply_velocity(from: &Isometry3<f64>, v: &[f64; 6]) -> Isometry3<f64> {
    let (lin, rot) = velocity_to_delta(v);
    Isometry3::from_parts(
        Translation3::from(from.translation.vector + lin),
        UnitQuaternion::from_scaled_axis(rot) * from.rotation,
    )
}

/// A pose from DROID's `cartesian_position`: x y z (m) + extrinsic xyz euler angles (rad).
pub fn pose_from_xyz_euler(a: &[f64; 6]) -> Isometry3<f64> {
    Isometry3::from_parts(Translation3::new(a[0], a[1], a[2]), UnitQuaternion::from_euler_angles(a[3], a[4], a[5]))
}

/// DROID's `cartesian_position` of a pose.
pub fn xyz_euler(p: &Isometry3<f64>) -> [f64; 6] {
    let (r, pi, y) = p.rotation.euler_angles();
    let t = p.translation.vector;
    [t.x, t.y, t.z, r, pi, y]
}

/// A rotation's quaternion on the hemisphere of the top-down grasp (x >= 0; q and -q are the
/// same rotation), as (x, y, z, w). The same rule everywhere, with no history: training and
/// the policy server give a pose the same numbers. (A top-down grasp has w near 0, where the
/// usual `w >= 0` rule flips x between +1 and -1 from one step to the next; this one is
/// continuous for every orientation within a quarter turn of top-down, the tabletop's.)
pub fn canonical_quaternion(q: &UnitQuaternion<f64>) -> [f64; 4] {
    let v = [q.i, q.j, q.k, q.w];
    if v[0] < 0.0 { v.map(|x| -x) } else { v }
}

/// The axis-angle vector of a rotation from its [`canonical_quaternion`]: angle in [0, 2 pi)
/// about the axis on the top-down hemisphere, so a top-down grasp reads about (pi, 0, 0)
/// whichever way its roll wobbles, never (-pi, 0, 0) on the next step.
pub fn canonical_axis_angle(q: &UnitQuaternion<f64>) -> [f64; 3] {
    let [x, y, z, w] = canonical_quaternion(q);
    let s = (x * x + y * y + z * z).sqrt();
    if s < 1e-12 {
        return [0.0; 3];
    }
    let angle = 2.0 * s.atan2(w);
    [x / s * angle, y / s * angle, z / s * angle]
}

/// A pose from x y z (m) + an axis-angle rotation vector (rad).
pub fn pose_from_xyz_axis_angle(a: &[f64; 6]) -> Isometry3<f64> {
    Isometry3::from_parts(
        Translation3::new(a[0], a[1], a[2]),
        UnitQuaternion::from_scaled_axis(Vector3::new(a[3], a[4], a[5])),
    )
}

/// The translation (m) and rotation vector (rad) from `from` to `to`, in the base frame.
pub fn pose_error(from: &Isometry3<f64>, to: &Isometry3<f64>) -> (Vector3<f64>, Vector3<f64>) {
    (to.translation.vector - from.translation.vector, (to.rotation * from.rotation.inverse()).scaled_axis())
}

#[derive(Debug, Clone, PartialEq)]
pub struct IkConfig {
    /// Damping of the least-squares step (m or rad); larger is steadier near singularities.
    pub damping: f64,
    /// Fraction of the way to the rest pose pulled per iteration, in the Jacobian's nullspace.
    pub nullspace_gain: f64,
    /// The configuration the nullspace pulls toward (DROID's reset pose).
    pub rest: Joints,
    /// Joints stay this far inside their limits (rad).
    pub limit_margin: f64,
    pub max_iterations: u32,
    /// Converged when both errors are below these (m, rad).
    pub tolerance_m: f64,
    pub tolerance_rad: f64,
}

impl Default for IkConfig {
    fn default() -> Self {
        IkConfig {
            damping: 0.01,
            nullspace_gain: 0.02,
            rest: labrig_msgs::rig::DROID_RESET_POSE,
            limit_margin: 0.02,
            max_iterations: 12,
            tolerance_m: 1e-5,
            tolerance_rad: 1e-4,
        }
    }
}

/// One IK result: joints (always inside the limits by the margin) and how far their TCP is
/// from the target.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct IkSolution {
    pub joints: Joints,
    pub position_error_m: f64,
    pub rotation_error_rad: f64,
    pub iterations: u32,
}

impl IkSolution {
    pub fn converged(&self, cfg: &IkConfig) -> bool {
        self.position_error_m <= cfg.tolerance_m && self.rotation_error_rad <= cfg.tolerance_rad
    }
}

/// The IK solver: kinematics + configuration.
#[derive(Debug, Clone)]
pub struct Ik {
    kin: Fr3Kinematics,
    cfg: IkConfig,
    /// Limits shrunk by the margin.
    bounds: [[f64; 2]; DOF],
}

impl Ik {
    pub fn new(kin: Fr3Kinematics, cfg: IkConfig) -> Ik {
        let bounds = kin.limits().map(|[lo, hi]| [lo + cfg.limit_margin, hi - cfg.limit_margin]);
        Ik { kin, cfg, bounds }
    }

    pub fn kinematics(&self) -> &Fr3Kinematics {
        &self.kin
    }

    pub fn config(&self) -> &IkConfig {
        &self.cfg
    }

    /// The limits the solver keeps joints inside ([`Fr3Kinematics::limits`] less the margin).
    pub fn bounds(&self) -> [[f64; 2]; DOF] {
        self.bounds
    }

    /// Joints that put the TCP at `target`, iterating from `seed` (the last command, so the
    /// solution stays on the same branch). The result is inside the bounds even when the
    /// target is not reachable; the errors say how far off it is.
    pub fn solve(&self, seed: &Joints, target: &Isometry3<f64>) -> IkSolution {
        let mut q = self.clamp(seed);
        let mut iterations = 0;
        loop {
            let (pose, j) = self.kin.tcp_pose_and_jacobian(&q);
            let (dp, dr) = pose_error(&pose, target);
            let done = dp.norm() <= self.cfg.tolerance_m && dr.norm() <= self.cfg.tolerance_rad;
            if done || iterations == self.cfg.max_iterations {
                return IkSolution {
                    joints: q,
                    position_error_m: dp.norm(),
                    rotation_error_rad: dr.norm(),
                    iterations,
                };
            }
            let err = SVector::<f64, 6>::new(dp.x, dp.y, dp.z, dr.x, dr.y, dr.z);
            let jjt = j * j.transpose() + Matrix6::identity() * self.cfg.damping.powi(2);
            let Some(inv) = jjt.try_inverse() else {
                return IkSolution {
                    joints: q,
                    position_error_m: dp.norm(),
                    rotation_error_rad: dr.norm(),
                    iterations,
                };
            };
            let pinv = j.transpose() * inv;
            let rest = SVector::<f64, DOF>::from_fn(|i, _| self.cfg.nullspace_gain * (self.cfg.rest[i] - q[i]));
            let dq = pinv * err + (SMatrix::<f64, DOF, DOF>::identity() - pinv * j) * rest;
            q = self.clamp(&std::array::from_fn(|i| q[i] + dq[i]));
            iterations += 1;
        }
    }

    fn clamp(&self, q: &Joints) -> Joints {
        std::array::from_fn(|i| q[i].clamp(self.bounds[i][0], self.bounds[i][1]))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn full_scale_velocity_is_droids_largest_step() {
        let (lin, rot) = velocity_to_delta(&[1.0, 0.0, 0.0, 0.0, 0.0, -1.0]);
        assert_eq!(lin, Vector3::new(0.075, 0.0, 0.0));
        assert_eq!(rot, Vector3::new(0.0, 0.0, -0.15));
        // Longer than 1: scaled down to norm 1, direction kept.
        let (lin, _) = velocity_to_delta(&[3.0, 4.0, 0.0, 0.0, 0.0, 0.0]);
        assert!((lin - Vector3::new(0.6, 0.8, 0.0) * 0.075).norm() < 1e-15);
        let v = [0.2, -0.4, 0.1, 0.3, 0.0, -0.5];
        let (l, r) = velocity_to_delta(&v);
        let back = delta_to_velocity(&l, &r);
        for k in 0..6 {
            assert!((back[k] - v[k]).abs() < 1e-12);
        }
    }

    #[test]
    fn euler_poses_round_trip() {
        let a = [0.4, -0.1, 0.3, 3.0, -0.2, 0.7];
        let b = xyz_euler(&pose_from_xyz_euler(&a));
        for k in 0..6 {
            assert!((a[k] - b[k]).abs() < 1e-12, "{a:?} {b:?}");
        }
    }
}
