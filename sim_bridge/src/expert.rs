//! The scripted expert: solves pick-and-place into the bin from the scene's ground truth,
//! producing DROID actions (absolute end-effector pose as xyz + extrinsic xyz euler, and a 0..1
//! gripper position), plus the task's success predicate.
//!
//! In the sim, [`CartesianIk`] turns the pose action into joint position targets with one
//! damped-least-squares step per tick on MuJoCo's own Jacobian — a stand-in for the franka
//! node's URDF-based IK (issue 4) so the expert can be evaluated inside this crate.

use crate::scene::{BIN_HALF, OBJECT_SIZE};
use crate::{ArmTarget, Sim, SimError};
use nalgebra::{Matrix3, Matrix6, Rotation3, SMatrix, SVector, UnitQuaternion, Vector3};
use serde::Serialize;

/// Largest TCP translation per tick (m) and rotation per tick (rad) the expert asks for:
/// 0.4 m/s and 2 rad/s at 20 Hz, inside DROID's 0.075 m / 0.15 rad per step.
pub const MAX_STEP_M: f64 = 0.02;
pub const MAX_STEP_RAD: f64 = 0.1;

/// The expert's phases, in order.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Phase {
    Approach,
    Descend,
    Grasp,
    Lift,
    Carry,
    Lower,
    Release,
    Retreat,
    Done,
}

/// One tick's action in DROID's action space.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Action {
    /// Target TCP pose: x y z (m) and extrinsic xyz euler angles (rad), robot base frame.
    pub cartesian_position: [f64; 6],
    /// 0 = open .. 1 = closed.
    pub gripper_position: f64,
    pub phase: Phase,
}

/// Extrinsic xyz euler angles (DROID's convention, scipy's `as_euler("xyz")`) of a rotation.
pub fn euler_xyz(r: &Matrix3<f64>) -> [f64; 3] {
    let (roll, pitch, yaw) = Rotation3::from_matrix_unchecked(*r).euler_angles();
    [roll, pitch, yaw]
}

/// The rotation matrix of extrinsic xyz euler angles.
pub fn from_euler_xyz(e: [f64; 3]) -> Matrix3<f64> {
    *Rotation3::from_euler_angles(e[0], e[1], e[2]).matrix()
}

fn row_major(m: [f64; 9]) -> Matrix3<f64> {
    Matrix3::from_row_slice(&m)
}

/// Pick-and-place from ground truth: approach above the object, descend, close, lift, carry
/// over the bin, lower, open, retreat.
#[derive(Debug, Clone)]
pub struct PickPlaceExpert {
    phase: Phase,
    ticks_in_phase: u32,
    /// TCP orientation at the reset pose (fingers down); grasps rotate it about world z.
    down: Matrix3<f64>,
    grasp_yaw: f64,
    bin: [f64; 3],
    /// Where the TCP is being led (position, rotation), moved at most one step per tick.
    goal: Option<(Vector3<f64>, Matrix3<f64>)>,
    carried: Vector3<f64>,
    attempts: u32,
    last_gripper: f64,
}

const HOVER_Z: f64 = 0.12;
const CARRY_Z: f64 = 0.18;
const RELEASE_Z: f64 = 0.11;
const GRIP_TICKS: u32 = 12;
/// The pinch point sits this far above the cube's centre, so the finger tips clear the table.
const GRASP_ABOVE_CENTRE: f64 = 0.008;
/// Grasp attempts before the expert gives up (a missed grasp is retried from the approach).
const MAX_ATTEMPTS: u32 = 3;
/// A phase that has not converged after this many ticks moves on anyway.
const PHASE_TIMEOUT: u32 = 80;

impl PickPlaceExpert {
    /// `sim` must be at the reset pose of the scene to solve.
    pub fn new(sim: &Sim) -> PickPlaceExpert {
        let (_, rot) = sim.tcp_pose();
        let down = row_major(rot);
        // The fingers close along the TCP's y axis: align it with a face of the cube. The
        // cube's symmetry lets the yaw be taken modulo 90 deg, into the smallest turn.
        let obj_yaw = sim.scene().object_yaw_deg.to_radians();
        let finger = down * Vector3::y();
        let finger_yaw = finger.y.atan2(finger.x);
        let quarter = std::f64::consts::FRAC_PI_2;
        let mut turn = (obj_yaw - finger_yaw).rem_euclid(quarter);
        if turn > quarter / 2.0 {
            turn -= quarter;
        }
        PickPlaceExpert {
            phase: Phase::Approach,
            ticks_in_phase: 0,
            down,
            grasp_yaw: turn,
            bin: sim.scene().receptacle_position,
            goal: None,
            carried: Vector3::zeros(),
            attempts: 1,
            last_gripper: 0.0,
        }
    }

    pub fn phase(&self) -> Phase {
        self.phase
    }

    fn next(&mut self) {
        self.phase = match self.phase {
            Phase::Approach => Phase::Descend,
            Phase::Descend => Phase::Grasp,
            Phase::Grasp => Phase::Lift,
            Phase::Lift => Phase::Carry,
            Phase::Carry => Phase::Lower,
            Phase::Lower => Phase::Release,
            Phase::Release => Phase::Retreat,
            Phase::Retreat | Phase::Done => Phase::Done,
        };
        self.ticks_in_phase = 0;
    }

    /// The next action, from the current state of the sim.
    pub fn act(&mut self, sim: &Sim) -> Action {
        let (p, r) = sim.tcp_pose();
        let pos = Vector3::from(p);
        let rot = row_major(r);
        let obj = Vector3::from(sim.object_position());
        let grasp_rot = *Rotation3::from_axis_angle(&Vector3::z_axis(), self.grasp_yaw).matrix() * self.down;
        let bin = Vector3::new(self.bin[0], self.bin[1], 0.0);
        // Each phase: where the TCP should end up, and the gripper command.
        let (target, target_rot, gripper) = match self.phase {
            Phase::Approach => (Vector3::new(obj.x, obj.y, obj.z + HOVER_Z), grasp_rot, 0.0),
            Phase::Descend => (Vector3::new(obj.x, obj.y, obj.z + GRASP_ABOVE_CENTRE), grasp_rot, 0.0),
            Phase::Grasp => {
                self.carried = pos;
                (pos, grasp_rot, 1.0)
            }
            Phase::Lift => (Vector3::new(self.carried.x, self.carried.y, CARRY_Z), grasp_rot, 1.0),
            Phase::Carry => (Vector3::new(bin.x, bin.y, CARRY_Z), grasp_rot, 1.0),
            Phase::Lower => (Vector3::new(bin.x, bin.y, RELEASE_Z), grasp_rot, 1.0),
            Phase::Release => (Vector3::new(bin.x, bin.y, RELEASE_Z), grasp_rot, 0.0),
            Phase::Retreat | Phase::Done => (Vector3::new(bin.x, bin.y, CARRY_Z + 0.05), grasp_rot, 0.0),
        };
        // Lead the goal toward the target by at most one step per tick.
        let (goal_p, goal_r) = self.goal.unwrap_or((pos, rot));
        let dp = target - goal_p;
        let next_p = goal_p + dp * (MAX_STEP_M / dp.norm().max(MAX_STEP_M));
        let dr = UnitQuaternion::from_matrix(&(target_rot * goal_r.transpose()));
        let angle = dr.angle();
        let next_r = if angle > MAX_STEP_RAD {
            *UnitQuaternion::identity().slerp(&dr, MAX_STEP_RAD / angle).to_rotation_matrix().matrix() * goal_r
        } else {
            target_rot
        };
        self.goal = Some((next_p, next_r));
        self.ticks_in_phase += 1;
        let reached = (target - pos).norm() < 0.006 && (next_p - target).norm() < 1e-9;
        let done = match self.phase {
            // Closed once the fingers stop moving (on the cube, or on nothing: Lift checks).
            Phase::Grasp => {
                self.ticks_in_phase >= GRIP_TICKS && (sim.gripper_position() - self.last_gripper).abs() < 2e-3
            }
            Phase::Release => self.ticks_in_phase >= GRIP_TICKS,
            Phase::Done => false,
            _ => reached,
        };
        self.last_gripper = sim.gripper_position();
        // A grasp that did not lift the object is retried from the approach.
        if self.phase == Phase::Lift && done && obj.z < OBJECT_SIZE && self.attempts < MAX_ATTEMPTS {
            tracing::debug!(attempt = self.attempts, "expert: the object did not come up; retrying the grasp");
            self.attempts += 1;
            self.phase = Phase::Approach;
            self.ticks_in_phase = 0;
        } else if done || (self.ticks_in_phase > PHASE_TIMEOUT && self.phase != Phase::Done) {
            tracing::debug!(
                phase = ?self.phase,
                ticks = self.ticks_in_phase,
                timed_out = !done,
                error_mm = (target - pos).norm() * 1e3,
                "expert phase done"
            );
            self.next();
        }
        let e = euler_xyz(&next_r);
        Action {
            cartesian_position: [next_p.x, next_p.y, next_p.z, e[0], e[1], e[2]],
            gripper_position: gripper,
            phase: self.phase,
        }
    }
}

/// The pick-and-place success predicate: the object rests inside the bin's walls and the
/// gripper no longer holds it.
pub fn pick_place_success(sim: &Sim) -> bool {
    let obj = sim.object_position();
    let bin = sim.scene().receptacle_position;
    let wall = 0.005;
    let inside = (obj[0] - bin[0]).abs() < BIN_HALF[0] - wall && (obj[1] - bin[1]).abs() < BIN_HALF[1] - wall;
    let resting = obj[2] < bin[2] + 0.01 + OBJECT_SIZE;
    let released = sim.gripper_position() < 0.3;
    inside && resting && released
}

/// One damped-least-squares IK step on MuJoCo's Jacobian, with a nullspace pull toward the
/// reset pose; the result is clamped inside the joint limits by a margin.
#[derive(Debug, Clone)]
pub struct CartesianIk {
    pub damping: f64,
    pub nullspace_gain: f64,
    pub limit_margin: f64,
    /// Largest lead of a target over the measured joint (rad): bounds the integrated error
    /// when the TCP is blocked (anti-windup).
    pub max_lead: f64,
    rest: [f64; 7],
    limits: [[f64; 2]; 7],
}

impl CartesianIk {
    pub fn new(sim: &Sim) -> CartesianIk {
        CartesianIk {
            damping: 0.02,
            nullspace_gain: 0.1,
            limit_margin: 0.02,
            max_lead: 0.05,
            rest: crate::rig::RESET_POSE,
            limits: sim.joint_limits(),
        }
    }

    /// Joint targets that move the TCP toward `pose` (xyz + extrinsic xyz euler). The step is
    /// added to the last targets, not the measured joints, so a steady tracking error of the
    /// joint servos (the gripper's weight sags the wrist) is integrated away.
    pub fn solve(&self, sim: &Sim, pose: &[f64; 6]) -> [f64; 7] {
        let (p, r) = sim.tcp_pose();
        let q = sim.joint_targets();
        let dp = Vector3::new(pose[0], pose[1], pose[2]) - Vector3::from(p);
        let target = from_euler_xyz([pose[3], pose[4], pose[5]]);
        let dr = UnitQuaternion::from_matrix(&(target * row_major(r).transpose())).scaled_axis();
        let err = SVector::<f64, 6>::new(dp.x, dp.y, dp.z, dr.x, dr.y, dr.z);
        let jac = sim.tcp_jacobian();
        let j = SMatrix::<f64, 6, 7>::from_fn(|row, col| jac[row][col]);
        let jjt = j * j.transpose() + Matrix6::identity() * self.damping.powi(2);
        let pinv = j.transpose() * jjt.try_inverse().unwrap_or_else(Matrix6::identity);
        let dq_task = pinv * err;
        let rest = SVector::<f64, 7>::from_fn(|i, _| self.nullspace_gain * (self.rest[i] - q[i]));
        let dq = dq_task + (SMatrix::<f64, 7, 7>::identity() - pinv * j) * rest;
        let measured = sim.joint_positions();
        std::array::from_fn(|i| {
            let [lo, hi] = self.limits[i];
            let lead = (q[i] + dq[i] - measured[i]).clamp(-self.max_lead, self.max_lead);
            (measured[i] + lead).clamp(lo + self.limit_margin, hi - self.limit_margin)
        })
    }
}

/// The outcome of one scripted episode.
#[derive(Debug, Clone, Serialize)]
pub struct EpisodeResult {
    pub seed: u64,
    pub success: bool,
    pub ticks: u64,
    pub final_phase: Phase,
    pub object_position: [f64; 3],
    pub receptacle_position: [f64; 3],
    pub camera_bins: Vec<String>,
}

/// Runs the expert on `sim` (fresh from [`Sim::new`]) for at most `max_ticks`, stopping
/// early once it is done; `on_tick` sees every tick (for rendering or recording).
pub fn run_episode(
    sim: &mut Sim,
    max_ticks: u64,
    mut on_tick: impl FnMut(&mut Sim, &Action) -> Result<(), SimError>,
) -> Result<EpisodeResult, SimError> {
    let mut expert = PickPlaceExpert::new(sim);
    let ik = CartesianIk::new(sim);
    let mut ticks = 0;
    while ticks < max_ticks {
        let action = expert.act(sim);
        let joints = ik.solve(sim, &action.cartesian_position);
        sim.step(&ArmTarget { joints, gripper: action.gripper_position })?;
        ticks += 1;
        on_tick(sim, &action)?;
        if action.phase == Phase::Done {
            break;
        }
    }
    // Let the object settle before judging.
    let hold = ArmTarget { joints: sim.joint_targets(), gripper: 0.0 };
    for _ in 0..10 {
        sim.step(&hold)?;
    }
    let scene = sim.scene();
    Ok(EpisodeResult {
        seed: scene.seed,
        success: pick_place_success(sim),
        ticks,
        final_phase: expert.phase(),
        object_position: sim.object_position(),
        receptacle_position: scene.receptacle_position,
        camera_bins: scene
            .cameras
            .iter()
            .map(|(id, c)| format!("{id}:{}", c.bin.map_or("custom", |b| b.name())))
            .collect(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn euler_round_trips_like_scipy_xyz() {
        // scipy: R.from_euler("xyz", [0.3, -0.2, 1.1]).as_matrix()[0] = [0.444..., ...]
        let e = [0.3, -0.2, 1.1];
        let m = from_euler_xyz(e);
        // Extrinsic xyz = Rz(yaw) * Ry(pitch) * Rx(roll).
        let expect = Rotation3::from_axis_angle(&Vector3::z_axis(), 1.1)
            * Rotation3::from_axis_angle(&Vector3::y_axis(), -0.2)
            * Rotation3::from_axis_angle(&Vector3::x_axis(), 0.3);
        assert!((m - expect.matrix()).norm() < 1e-12);
        let back = euler_xyz(&m);
        for k in 0..3 {
            assert!((back[k] - e[k]).abs() < 1e-12);
        }
    }
}
