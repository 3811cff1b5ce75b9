//! A keyboard as the controller, for sim work without a headset: a virtual right controller
//! whose pose the keys move in the robot's frame, fed to the same VRPolicy as the Quest's
//! readings (so the deadman, origins and gains behave the same).
//!
//! Keys: `w`/`s` +x/-x, `a`/`d` +y/-y, `r`/`f` up/down (one `step_m` per press or key
//! repeat), `q`/`e` turn about z (`step_rad`), space = grip (the deadman; a toggle: terminals
//! report presses, not releases), `g` = trigger (gripper closed / open, a toggle), `1` = A
//! (success), `2` = B (failure), Esc or Ctrl-C = quit.

use crate::logcat::{Hand, Reading};
use nalgebra::{Matrix4, Rotation3, Vector3};

/// What a key did.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum KeyEffect {
    Handled,
    Ignored,
    Quit,
}

/// The virtual controller.
#[derive(Debug, Clone)]
pub struct VirtualController {
    /// VR -> robot axes (the policy's reorder), to place the pose in VR coordinates.
    reorder: Matrix4<f64>,
    step_m: f64,
    step_rad: f64,
    /// The controller's offset in the robot frame.
    offset: Vector3<f64>,
    yaw: f64,
    grip: bool,
    trigger: bool,
    /// A/B held for the next reading (a press).
    success: bool,
    failure: bool,
}

impl VirtualController {
    pub fn new(reorder: Matrix4<f64>, step_m: f64, step_rad: f64) -> VirtualController {
        VirtualController {
            reorder,
            step_m,
            step_rad,
            offset: Vector3::zeros(),
            yaw: 0.0,
            grip: false,
            trigger: false,
            success: false,
            failure: false,
        }
    }

    /// One key press (or repeat).
    pub fn key(&mut self, c: char) -> KeyEffect {
        let s = self.step_m;
        match c.to_ascii_lowercase() {
            'w' => self.offset.x += s,
            's' => self.offset.x -= s,
            'a' => self.offset.y += s,
            'd' => self.offset.y -= s,
            'r' => self.offset.z += s,
            'f' => self.offset.z -= s,
            'q' => self.yaw += self.step_rad,
            'e' => self.yaw -= self.step_rad,
            ' ' => self.grip = !self.grip,
            'g' => self.trigger = !self.trigger,
            '1' => self.success = true,
            '2' => self.failure = true,
            '\u{1b}' => return KeyEffect::Quit,
            _ => return KeyEffect::Ignored,
        }
        KeyEffect::Handled
    }

    pub fn grip(&self) -> bool {
        self.grip
    }

    /// The controller now, as a reading of the right hand (A/B presses are reported once).
    pub fn reading(&mut self) -> Reading {
        // Robot-frame pose -> VR coordinates: the reorder is a signed permutation, its
        // inverse its transpose.
        let mut robot = Matrix4::from(Rotation3::from_axis_angle(&Vector3::z_axis(), self.yaw));
        robot[(0, 3)] = self.offset.x;
        robot[(1, 3)] = self.offset.y;
        robot[(2, 3)] = self.offset.z;
        let pose = self.reorder.transpose() * robot * self.reorder;
        let right = Hand {
            pose: Some(pose),
            present: true,
            grip_pressed: self.grip,
            grip: if self.grip { 1.0 } else { 0.0 },
            trigger: if self.trigger { 1.0 } else { 0.0 },
            trigger_pressed: self.trigger,
            success: std::mem::take(&mut self.success),
            failure: std::mem::take(&mut self.failure),
            ..Hand::default()
        };
        Reading { right, ..Reading::default() }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::policy::{PolicyConfig, RobotView, VrPolicy};

    const HOME: RobotView =
        RobotView { cartesian_position: [0.5, 0.0, 0.4, std::f64::consts::PI, 0.0, 0.0], gripper_position: 0.0 };

    #[test]
    fn keys_move_the_robot_along_the_robot_s_axes_through_droid_s_policy() {
        let cfg = PolicyConfig::default();
        let mut policy = VrPolicy::new(cfg.clone());
        let mut kb = VirtualController::new(crate::policy::reorder_matrix(&cfg.axis_reorder), 0.005, 0.05);
        // Not gripped: keys move the controller, the arm stays.
        kb.key('w');
        assert_eq!(policy.step(&kb.reading(), &HOME).unwrap().velocity, [0.0; 7]);
        // Grip: the origin; 4 x 5 mm forward = 2 cm along robot +x -> 0.1 (gain 5).
        assert_eq!(kb.key(' '), KeyEffect::Handled);
        policy.step(&kb.reading(), &HOME);
        for _ in 0..4 {
            kb.key('w');
        }
        let v = policy.step(&kb.reading(), &HOME).unwrap().velocity;
        assert!((v[0] - 0.1).abs() < 1e-12 && v[1].abs() < 1e-12 && v[2].abs() < 1e-12, "{v:?}");
        // Up and left, and a turn about z.
        for k in ['r', 'r', 'a', 'q'] {
            kb.key(k);
        }
        let v = policy.step(&kb.reading(), &HOME).unwrap().velocity;
        assert!((v[1] - 0.025).abs() < 1e-12 && (v[2] - 0.05).abs() < 1e-12, "{v:?}");
        assert!((v[5] - 0.1).abs() < 1e-9, "0.05 rad x gain 2: {v:?}");
        // Trigger: close the gripper; A is one press.
        kb.key('g');
        kb.key('1');
        let r = kb.reading();
        assert!(r.right.success && r.right.trigger == 1.0);
        assert!(!kb.reading().right.success, "A reported once");
        assert_eq!(kb.key('x'), KeyEffect::Ignored);
        assert_eq!(kb.key('\u{1b}'), KeyEffect::Quit);
    }
}
