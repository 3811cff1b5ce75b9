//! The arm's motion for a calibration capture, as DROID's rig moves it: a pose set on a smooth
//! closed path around a start pose (+-10 cm, +-0.2 rad; the angles / 1.5 for the wrist
//! camera), each pose turned into joint targets the safety layer accepts. Shared by the sim's
//! capture (`labrig-sim calib-capture`) and a live rig's (`labrig calibrate capture --rig`), so
//! both drive the arm over the same poses.

use crate::Joints;
use crate::safety::SafetyFilter;
use nalgebra::{Isometry3, Matrix3, Point3, Rotation3, Translation3, UnitQuaternion, Vector3};

/// The board's centre is put no closer to an external camera than this (m).
pub const MIN_CAMERA_DISTANCE_M: f64 = 0.42;
/// The wrist camera looks at the table's board from this far (m).
pub const WRIST_BOARD_DISTANCE_M: f64 = 0.38;
/// Poses closer than this to the safety layer's workspace limits are skipped (m).
pub const WORKSPACE_MARGIN_M: f64 = 0.005;
/// The start is chosen where the arm reaches this share of a coarse probe of the pose set.
const PROBE_POSES: usize = 20;
const PROBE_REACHED: f64 = 0.9;

/// DROID's amplitudes: translation (m) and rotation (rad); the wrist camera's rotation is
/// divided by 1.5.
pub const AMPLITUDE_M: f64 = 0.10;
pub const AMPLITUDE_RAD: f64 = 0.2;
pub const WRIST_ANGLE_DIVISOR: f64 = 1.5;

/// Why no start pose was found.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum StartError {
    #[error(
        "the arm cannot hold the board toward the camera anywhere on its line of sight to the table \
         (camera at [{:.2}, {:.2}, {:.2}] m in the base frame)", camera[0], camera[1], camera[2]
    )]
    NoLineOfSight { camera: [f64; 3] },
}

/// The pose set: `n` poses on a smooth closed path around `start` (base -> tcp); the angles turn
/// about `pivot` (a point fixed to the board, in the base frame) so the board stays in view.
pub fn pose_set(
    start: &Isometry3<f64>,
    pivot: &Vector3<f64>,
    n: usize,
    amp_m: f64,
    amp_rad: f64,
) -> Vec<Isometry3<f64>> {
    (0..n)
        .map(|k| {
            let t = std::f64::consts::TAU * k as f64 / n as f64;
            let dp = Vector3::new(t.sin(), (2.0 * t + 0.7).sin(), 0.6 * (3.0 * t + 1.3).sin()) * amp_m;
            let dr = Vector3::new((2.0 * t + 0.3).sin(), (t + 1.1).sin(), 0.8 * (3.0 * t + 0.5).sin()) * amp_rad;
            let turn = UnitQuaternion::from_scaled_axis(dr);
            let p = start.translation.vector;
            let p_new = pivot + turn * (p - pivot) + dp;
            Isometry3::from_parts(Translation3::from(p_new), turn * start.rotation)
        })
        .collect()
}

/// Joints that put the TCP at `want`: the IK from `seed`, else followed along the straight path
/// (position lerp, rotation slerp) from `seed`'s pose in small steps, each seeded by the last
/// (the IK is local: a far target from a far seed lands on a joint limit). None for a pose
/// outside the safety layer's workspace (it would refuse the command) or out of reach.
pub fn joints_for(safety: &SafetyFilter, seed: &Joints, want: &Isometry3<f64>) -> Option<Joints> {
    let (lo, hi) = (safety.config().workspace_min_m, safety.config().workspace_max_m);
    let p = want.translation.vector;
    if (0..3).any(|i| p[i] < lo[i] + WORKSPACE_MARGIN_M || p[i] > hi[i] - WORKSPACE_MARGIN_M) {
        return None;
    }
    let ik = safety.ik();
    let ok = |s: &crate::ik::IkSolution| s.position_error_m < 5e-4 && s.rotation_error_rad < 2e-3;
    let first = ik.solve(seed, want);
    if ok(&first) {
        return Some(first.joints);
    }
    let from = ik.kinematics().tcp_pose(seed);
    let steps = 40;
    let mut q = *seed;
    for k in 1..=steps {
        let t = k as f64 / steps as f64;
        let p = from.translation.vector.lerp(&want.translation.vector, t);
        let r = from.rotation.slerp(&want.rotation, t);
        let sol = ik.solve(&q, &Isometry3::from_parts(Translation3::from(p), r));
        if sol.position_error_m > 0.01 || sol.rotation_error_rad > 0.05 {
            return None;
        }
        q = sol.joints;
    }
    let last = ik.solve(&q, want);
    ok(&last).then_some(last.joints)
}

/// An external camera's start (board in the gripper): the board's centre on the camera's line
/// of sight to `aim` (the table centre), its face toward the camera with its y as close to down
/// as the face allows, as close to the camera as the arm reaches nearly all of the pose set
/// from, no nearer than [`MIN_CAMERA_DISTANCE_M`]. `tcp_board` is the board's pose in the TCP
/// frame (OpenCV's board frame: origin at a corner, z into the board), `size_m` its print.
/// Returns the start (base -> tcp) and the pivot (the board's centre).
pub fn start_facing_camera(
    safety: &SafetyFilter,
    reset: &Joints,
    camera: &Vector3<f64>,
    aim: &Vector3<f64>,
    tcp_board: &Isometry3<f64>,
    size_m: [f64; 2],
    amplitude: (f64, f64),
) -> Result<(Isometry3<f64>, Vector3<f64>), StartError> {
    let centre_in_board = Vector3::new(size_m[0] / 2.0, size_m[1] / 2.0, 0.0);
    let toward = (camera - aim).normalize();
    let span = (camera - aim).norm();
    let down = Vector3::new(0.0, 0.0, -1.0);
    let z = -toward;
    let y = (down - z * down.dot(&z)).normalize();
    let x = y.cross(&z);
    let rot =
        UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(Matrix3::from_columns(&[x, y, z])));
    let tcp_for = |centre: &Vector3<f64>| {
        let origin = centre - rot * centre_in_board;
        Isometry3::from_parts(Translation3::from(origin), rot) * tcp_board.inverse()
    };
    for k in 0..=60 {
        let centre = camera - toward * (MIN_CAMERA_DISTANCE_M + (span - MIN_CAMERA_DISTANCE_M) * k as f64 / 60.0);
        if centre.z > 0.6 || centre.z < 0.2 {
            continue;
        }
        let start = tcp_for(&centre);
        let Some(mut q) = joints_for(safety, reset, &start) else { continue };
        let probe = pose_set(&start, &centre, PROBE_POSES, amplitude.0, amplitude.1);
        let mut reached = 0;
        for p in &probe {
            if let Some(next) = joints_for(safety, &q, p) {
                q = next;
                reached += 1;
            }
        }
        if reached as f64 >= PROBE_REACHED * PROBE_POSES as f64 {
            return Ok((start, centre));
        }
    }
    Err(StartError::NoLineOfSight { camera: (*camera).into() })
}

/// The wrist camera's start (board on the table): the TCP keeps its orientation and moves so
/// that the camera's optical axis meets the board's centre [`WRIST_BOARD_DISTANCE_M`] away.
/// `tcp` is the TCP now (base -> tcp), `tcp_camera` the camera in the TCP frame (optical),
/// `board` the board's pose in the base frame. Returns the start and the pivot (the board's
/// centre).
pub fn start_above_board(
    tcp: &Isometry3<f64>,
    tcp_camera: &Isometry3<f64>,
    board: &Isometry3<f64>,
    size_m: [f64; 2],
) -> (Isometry3<f64>, Vector3<f64>) {
    let centre = board * Point3::new(size_m[0] / 2.0, size_m[1] / 2.0, 0.0);
    let axis = tcp.rotation * (tcp_camera.rotation * Vector3::z());
    let cam_pos = centre.coords - axis * WRIST_BOARD_DISTANCE_M;
    let p = cam_pos - tcp.rotation * tcp_camera.translation.vector;
    (Isometry3::from_parts(Translation3::from(p), tcp.rotation), centre.coords)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_pose_set_stays_within_its_amplitudes_around_the_start() {
        let start = Isometry3::from_parts(Translation3::new(0.5, 0.0, 0.4), UnitQuaternion::identity());
        let pivot = Vector3::new(0.5, 0.0, 0.4);
        let set = pose_set(&start, &pivot, 60, AMPLITUDE_M, AMPLITUDE_RAD);
        assert_eq!(set.len(), 60);
        let mut max_angle: f64 = 0.0;
        for p in &set {
            // Pivot at the TCP: the shift is the translation term alone.
            let d = p.translation.vector - start.translation.vector;
            assert!(d.x.abs() <= AMPLITUDE_M + 1e-12 && d.y.abs() <= AMPLITUDE_M + 1e-12, "{d}");
            assert!(d.z.abs() <= 0.6 * AMPLITUDE_M + 1e-12, "{d}");
            max_angle = max_angle.max(p.rotation.angle_to(&start.rotation));
        }
        // Three sinusoids of 0.2, 0.2 and 0.16 rad: never more than their norm, and they do turn.
        assert!(max_angle <= (0.2f64.powi(2) * 2.0 + 0.16f64.powi(2)).sqrt() + 1e-9, "{max_angle}");
        assert!(max_angle > 0.15, "{max_angle}");
    }

    #[test]
    fn the_wrist_start_puts_the_board_centre_on_the_camera_axis() {
        let tcp =
            Isometry3::from_parts(Translation3::new(0.45, 0.05, 0.5), UnitQuaternion::from_euler_angles(3.1, 0.1, 0.2));
        let tcp_camera = Isometry3::from_parts(
            Translation3::new(0.02, -0.06, -0.08),
            UnitQuaternion::from_euler_angles(0.2, 0.0, 0.1),
        );
        let board = Isometry3::from_parts(Translation3::new(0.4, -0.1, 0.0), UnitQuaternion::identity());
        let (start, centre) = start_above_board(&tcp, &tcp_camera, &board, [0.28, 0.18]);
        let cam = start * tcp_camera;
        let in_cam = cam.inverse() * Point3::from(centre);
        assert!(in_cam.x.abs() < 1e-12 && in_cam.y.abs() < 1e-12, "{in_cam}");
        assert!((in_cam.z - WRIST_BOARD_DISTANCE_M).abs() < 1e-12, "{in_cam}");
        assert!(start.rotation.angle_to(&tcp.rotation) < 1e-12);
    }
}
