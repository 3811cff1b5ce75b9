//! Controller -> DROID action, after DROID's VRPolicy (droid/controllers/oculus_controller.py,
//! FACTS.md): the controller pose is taken into the robot's frame as
//! `reorder @ inv(pose when forward was defined) @ pose` with the axis reorder
//! `[-2, -1, -3, 4]` (robot x = -vr y, robot y = -vr x, robot z = -vr z); while the grip is held
//! (the deadman) the action moves the robot's TCP offset from where it was at the grip press
//! toward the controller's offset from where it was then:
//! `pos = (vr - vr_origin) - (robot - robot_origin)`, rotation = the quaternion difference of
//! the two offsets as Euler angles, gripper = trigger * 1.5 - gripper state; gains 5 / 2 / 3,
//! each part norm-clipped to 1, then every element to [-1, 1] (DROID's cartesian velocity
//! space). Each grip press re-zeroes both origins; a joystick press redefines forward.

use crate::logcat::Reading;
use labrig_msgs::Invalid;
use nalgebra::{Matrix4, Rotation3, UnitQuaternion, Vector3};
use serde::Deserialize;

/// The mapping's settings (a `[policy]` section of the node's config).
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct PolicyConfig {
    /// Which controller drives the arm: "right" or "left".
    pub hand: String,
    pub position_gain: f64,
    pub rotation_gain: f64,
    pub gripper_gain: f64,
    /// DROID's `rmat_reorder`: robot axis i = sign * vr axis |v_i| (1-based, 4 = homogeneous).
    pub axis_reorder: [i8; 4],
    /// The controller's motion is scaled by this before the gains (DROID's spatial_coeff).
    pub spatial_coeff: f64,
}

impl Default for PolicyConfig {
    fn default() -> Self {
        PolicyConfig {
            hand: "right".into(),
            position_gain: 5.0,
            rotation_gain: 2.0,
            gripper_gain: 3.0,
            axis_reorder: [-2, -1, -3, 4],
            spatial_coeff: 1.0,
        }
    }
}

impl PolicyConfig {
    pub fn validate(&self) -> Result<(), Invalid> {
        if self.hand != "right" && self.hand != "left" {
            return Err(Invalid::new(
                "policy.hand",
                format!("policy.hand: {:?}, expected \"right\" or \"left\"", self.hand),
            ));
        }
        let mut seen = [false; 4];
        for v in self.axis_reorder {
            let i = v.unsigned_abs() as usize;
            if !(1..=4).contains(&i) || seen[i - 1] {
                return Err(Invalid::new(
                    "policy.axis_reorder",
                    format!("policy.axis_reorder: {:?} is not a signed permutation of 1..4", self.axis_reorder),
                ));
            }
            seen[i - 1] = true;
        }
        // The homogeneous coordinate stays put, and the 3x3 part must be a rotation (a
        // reflection has no quaternion: the rotation actions would come out wrong).
        let m = reorder_matrix(&self.axis_reorder);
        if self.axis_reorder[3] != 4 || m.fixed_view::<3, 3>(0, 0).determinant() < 0.0 {
            return Err(Invalid::new(
                "policy.axis_reorder",
                format!(
                    "policy.axis_reorder: {:?} must end in 4 and turn (not mirror) the axes (DROID's: [-2, -1, -3, 4])",
                    self.axis_reorder
                ),
            ));
        }
        for (k, v) in [
            ("position_gain", self.position_gain),
            ("rotation_gain", self.rotation_gain),
            ("gripper_gain", self.gripper_gain),
            ("spatial_coeff", self.spatial_coeff),
        ] {
            if !v.is_finite() || v <= 0.0 {
                return Err(Invalid::new(format!("policy.{k}"), format!("policy.{k}: {v} must be a positive number")));
            }
        }
        Ok(())
    }

    fn reorder(&self) -> Matrix4<f64> {
        reorder_matrix(&self.axis_reorder)
    }
}

/// DROID's `vec_to_reorder_mat`: row i takes VR axis |v_i| with the sign of v_i.
pub fn reorder_matrix(v: &[i8; 4]) -> Matrix4<f64> {
    let mut m = Matrix4::zeros();
    for (row, v) in v.iter().enumerate() {
        m[(row, v.unsigned_abs() as usize - 1)] = f64::from(v.signum());
    }
    m
}

/// The robot's side of the mapping: its TCP (xyz + extrinsic xyz Euler) and gripper (0..1).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RobotView {
    pub cartesian_position: [f64; 6],
    pub gripper_position: f64,
}

/// One mapped sample.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Action {
    /// DROID's cartesian velocity (lin xyz, rot xyz) and gripper velocity, each in [-1, 1].
    pub velocity: [f64; 7],
    /// Grip held and a pose of the hand seen: the arm may move.
    pub movement_enabled: bool,
    /// The controller's pose in the robot frame (after the forward definition).
    pub controller: Matrix4<f64>,
}

/// DROID's VRPolicy state.
#[derive(Debug, Clone)]
pub struct VrPolicy {
    cfg: PolicyConfig,
    reorder: Matrix4<f64>,
    /// inv(pose when forward was defined).
    vr_to_global: Matrix4<f64>,
    /// Forward follows the controller until the grip or the joystick is pressed (DROID).
    reset_orientation: bool,
    enabled: bool,
    /// After `release()`, motion waits for the grip to be let go and pressed again.
    needs_release: bool,
    origin: Option<Origins>,
}

/// The controller's and the robot's poses at the grip press.
#[derive(Debug, Clone, Copy)]
struct Origins {
    vr_pos: Vector3<f64>,
    vr_rot: UnitQuaternion<f64>,
    robot_pos: Vector3<f64>,
    robot_rot: UnitQuaternion<f64>,
}

fn euler_quat(e: &[f64]) -> UnitQuaternion<f64> {
    UnitQuaternion::from_euler_angles(e[0], e[1], e[2])
}

impl VrPolicy {
    pub fn new(cfg: PolicyConfig) -> VrPolicy {
        let reorder = cfg.reorder();
        VrPolicy {
            cfg,
            reorder,
            vr_to_global: Matrix4::identity(),
            reset_orientation: true,
            enabled: false,
            needs_release: false,
            origin: None,
        }
    }

    pub fn config(&self) -> &PolicyConfig {
        &self.cfg
    }

    fn right(&self) -> bool {
        self.cfg.hand == "right"
    }

    /// Whether the deadman is held (as of the last reading).
    pub fn enabled(&self) -> bool {
        self.enabled
    }

    /// Drops the origins (the controller vanished, the arm's state went stale): motion needs
    /// the grip let go and pressed again.
    pub fn release(&mut self) {
        self.enabled = false;
        self.needs_release = true;
        self.origin = None;
    }

    /// Maps a reading against the robot's state. `None` when the hand's pose is unknown.
    pub fn step(&mut self, reading: &Reading, robot: &RobotView) -> Option<Action> {
        let hand = *reading.hand(self.right());
        let pose = hand.pose?;
        // Forward (DROID): follows the controller until the grip or the joystick is pressed,
        // then stays; a joystick press takes the pose at that press as the new forward.
        if hand.joystick_pressed {
            self.reset_orientation = true;
        }
        let mut forward_changed = false;
        if self.reset_orientation {
            if hand.joystick_pressed || hand.grip_pressed {
                self.reset_orientation = false;
            }
            if let Some(inv) = pose.try_inverse() {
                forward_changed = inv != self.vr_to_global;
                self.vr_to_global = inv;
            }
        }
        let m = self.reorder * self.vr_to_global * pose;
        let vr_pos = m.fixed_view::<3, 1>(0, 3).into_owned() * self.cfg.spatial_coeff;
        let vr_rot =
            UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix(&m.fixed_view::<3, 3>(0, 0).into_owned()));
        let robot_pos =
            Vector3::new(robot.cartesian_position[0], robot.cartesian_position[1], robot.cartesian_position[2]);
        let robot_rot = euler_quat(&robot.cartesian_position[3..]);

        if self.needs_release && !hand.grip_pressed {
            self.needs_release = false;
        }
        let was = self.enabled;
        self.enabled = hand.grip_pressed && !self.needs_release;
        // A press, or forward redefined while held (the old origin is in the old frame):
        // both origins from here.
        if self.enabled && (!was || forward_changed) {
            self.origin = Some(Origins { vr_pos, vr_rot, robot_pos, robot_rot });
        }
        if !self.enabled {
            self.origin = None;
            return Some(Action { velocity: [0.0; 7], movement_enabled: false, controller: m });
        }
        let Origins { vr_pos: vo, vr_rot: vq, robot_pos: ro, robot_rot: rq } = self.origin.expect("set on the press");
        let pos = ((vr_pos - vo) - (robot_pos - ro)) * self.cfg.position_gain;
        let target_offset = vr_rot * vq.inverse();
        let robot_offset = robot_rot * rq.inverse();
        let (rx, ry, rz) = (target_offset * robot_offset.inverse()).euler_angles();
        let rot = Vector3::new(rx, ry, rz) * self.cfg.rotation_gain;
        let grip = (hand.trigger * 1.5 - robot.gripper_position) * self.cfg.gripper_gain;
        let clip_norm = |v: Vector3<f64>| if v.norm() > 1.0 { v / v.norm() } else { v };
        let (lin, rot) = (clip_norm(pos), clip_norm(rot));
        let mut velocity = [lin.x, lin.y, lin.z, rot.x, rot.y, rot.z, grip.clamp(-1.0, 1.0)];
        for v in &mut velocity {
            *v = v.clamp(-1.0, 1.0);
        }
        Some(Action { velocity, movement_enabled: true, controller: m })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::logcat::Hand;

    fn reading(pose: Matrix4<f64>, grip: bool, trigger: f64) -> Reading {
        let right = Hand { pose: Some(pose), present: true, grip_pressed: grip, trigger, ..Hand::default() };
        Reading { right, ..Reading::default() }
    }

    fn at(x: f64, y: f64, z: f64) -> Matrix4<f64> {
        Matrix4::new_translation(&Vector3::new(x, y, z))
    }

    const HOME: RobotView =
        RobotView { cartesian_position: [0.5, 0.0, 0.4, std::f64::consts::PI, 0.0, 0.0], gripper_position: 0.0 };

    #[test]
    fn the_deadman_gates_motion_and_each_press_re_zeroes() {
        let mut p = VrPolicy::new(PolicyConfig::default());
        // Not held: no motion, whatever the controller does.
        let a = p.step(&reading(at(0.0, 0.0, 0.0), false, 0.0), &HOME).unwrap();
        assert!(!a.movement_enabled);
        assert_eq!(a.velocity, [0.0; 7]);
        let a = p.step(&reading(at(0.3, 0.0, 0.0), false, 0.0), &HOME).unwrap();
        assert_eq!(a.velocity, [0.0; 7]);
        // Pressed here: this is the origin, so no action yet.
        let a = p.step(&reading(at(0.3, 0.0, 0.0), true, 0.0), &HOME).unwrap();
        assert!(a.movement_enabled);
        assert!(a.velocity[..6].iter().all(|v| v.abs() < 1e-12), "{:?}", a.velocity);
        // 1 cm along vr -y = robot +x: 5 cm/s-ish, gain 5 -> 0.05.
        let a = p.step(&reading(at(0.3, -0.01, 0.0), true, 0.0), &HOME).unwrap();
        assert!((a.velocity[0] - 0.05).abs() < 1e-12 && a.velocity[1].abs() < 1e-12, "{:?}", a.velocity);
        // vr +x = robot -y, vr +y... vr -z = robot +z.
        let a = p.step(&reading(at(0.31, 0.0, -0.01), true, 0.0), &HOME).unwrap();
        assert!((a.velocity[1] + 0.05).abs() < 1e-12 && (a.velocity[2] - 0.05).abs() < 1e-12, "{:?}", a.velocity);
        // Released and pressed elsewhere: the new place is the origin.
        p.step(&reading(at(0.0, 0.0, 0.0), false, 0.0), &HOME).unwrap();
        let a = p.step(&reading(at(0.9, 0.9, 0.9), true, 0.0), &HOME).unwrap();
        assert!(a.velocity[..6].iter().all(|v| v.abs() < 1e-12), "{:?}", a.velocity);
    }

    #[test]
    fn the_robot_closes_the_gap_so_the_action_goes_to_zero() {
        let mut p = VrPolicy::new(PolicyConfig::default());
        p.step(&reading(at(0.0, 0.0, 0.0), true, 0.0), &HOME);
        // Controller 4 cm along robot +x; the robot followed by 4 cm: nothing left to do.
        let moved = RobotView { cartesian_position: [0.54, 0.0, 0.4, std::f64::consts::PI, 0.0, 0.0], ..HOME };
        let a = p.step(&reading(at(0.0, -0.04, 0.0), true, 0.0), &moved).unwrap();
        assert!(a.velocity[..6].iter().all(|v| v.abs() < 1e-12), "{:?}", a.velocity);
        // Far away: each part norm-clipped to 1.
        let a = p.step(&reading(at(-1.0, -1.0, 0.0), true, 0.0), &HOME).unwrap();
        let n = (a.velocity[0].powi(2) + a.velocity[1].powi(2) + a.velocity[2].powi(2)).sqrt();
        assert!((n - 1.0).abs() < 1e-12, "{n}");
    }

    #[test]
    fn rotation_and_gripper_follow_droid() {
        let mut p = VrPolicy::new(PolicyConfig::default());
        p.step(&reading(at(0.0, 0.0, 0.0), true, 0.0), &HOME);
        // Controller turned 0.1 rad about vr -z = robot +z (reorder keeps it an axis).
        let turn = Matrix4::from(Rotation3::from_axis_angle(&Vector3::z_axis(), -0.1));
        let a = p.step(&reading(turn, true, 1.0), &HOME).unwrap();
        assert!((a.velocity[5] - 0.2).abs() < 1e-9, "rotation gain 2: {:?}", a.velocity);
        // Trigger fully pressed, gripper open: (1.5 - 0) * 3 clipped to 1.
        assert_eq!(a.velocity[6], 1.0);
        let closed = RobotView { gripper_position: 1.0, ..HOME };
        let a = p.step(&reading(turn, true, 0.0), &closed).unwrap();
        assert_eq!(a.velocity[6], -1.0, "trigger released: open");
    }

    #[test]
    fn after_a_release_motion_needs_the_grip_let_go_and_pressed_again() {
        let mut p = VrPolicy::new(PolicyConfig::default());
        p.step(&reading(at(0.0, 0.0, 0.0), true, 0.0), &HOME);
        p.release();
        // Still held: no motion, however far the hand goes.
        let a = p.step(&reading(at(0.0, -0.2, 0.0), true, 0.0), &HOME).unwrap();
        assert!(!a.movement_enabled && a.velocity == [0.0; 7]);
        p.step(&reading(at(0.0, -0.2, 0.0), false, 0.0), &HOME);
        let a = p.step(&reading(at(0.0, -0.2, 0.0), true, 0.0), &HOME).unwrap();
        assert!(a.movement_enabled && a.velocity[..6].iter().all(|v| v.abs() < 1e-12), "a new origin: {a:?}");
    }

    #[test]
    fn forward_follows_the_controller_until_the_first_press() {
        let mut p = VrPolicy::new(PolicyConfig::default());
        // Picked up from the table turned a quarter about vr y, then pressed: forward is
        // the pose at the press, not the first one seen.
        p.step(&reading(Matrix4::identity(), false, 0.0), &HOME);
        let facing = Matrix4::from(Rotation3::from_axis_angle(&Vector3::y_axis(), std::f64::consts::FRAC_PI_2));
        p.step(&reading(facing, true, 0.0), &HOME);
        let a = p.step(&reading(facing * at(0.0, -0.01, 0.0), true, 0.0), &HOME).unwrap();
        assert!((a.velocity[0] - 0.05).abs() < 1e-9, "{:?}", a.velocity);
        // Forward redefined while held: origins re-zeroed there, no jump.
        let mut j = reading(Matrix4::identity(), true, 0.0);
        j.right.joystick_pressed = true;
        let a = p.step(&j, &HOME).unwrap();
        assert!(a.velocity[..6].iter().all(|v| v.abs() < 1e-12), "{:?}", a.velocity);
    }

    #[test]
    fn the_joystick_redefines_forward() {
        let mut p = VrPolicy::new(PolicyConfig::default());
        // Forward defined facing vr +x (a quarter turn about vr y).
        let facing = Matrix4::from(Rotation3::from_axis_angle(&Vector3::y_axis(), std::f64::consts::FRAC_PI_2));
        let mut r = reading(facing, false, 0.0);
        r.right.joystick_pressed = true;
        p.step(&r, &HOME);
        p.step(&reading(facing, false, 0.0), &HOME);
        p.step(&reading(facing, true, 0.0), &HOME);
        // Moving 1 cm along the controller's own forward now reads as the old mapping did
        // for the first pose.
        let moved = facing * at(0.0, -0.01, 0.0);
        let a = p.step(&reading(moved, true, 0.0), &HOME).unwrap();
        assert!((a.velocity[0] - 0.05).abs() < 1e-9, "{:?}", a.velocity);
    }

    #[test]
    fn config_errors_name_the_field() {
        let bad = PolicyConfig { axis_reorder: [1, 1, 3, 4], ..PolicyConfig::default() };
        assert!(bad.validate().unwrap_err().to_string().contains("policy.axis_reorder"));
        for mirror in [[1, 2, -3, 4], [4, -1, -3, 2]] {
            let bad = PolicyConfig { axis_reorder: mirror, ..PolicyConfig::default() };
            assert!(bad.validate().unwrap_err().to_string().contains("must end in 4"), "{mirror:?}");
        }
        let bad = PolicyConfig { hand: "both".into(), ..PolicyConfig::default() };
        assert!(bad.validate().unwrap_err().to_string().contains("policy.hand"));
        let bad = PolicyConfig { position_gain: f64::NAN, ..PolicyConfig::default() };
        assert!(bad.validate().unwrap_err().to_string().contains("policy.position_gain"));
    }
}
