//! The safety layer every arm command passes before it can reach a backend (the FR3 through
//! FCI, or the sim), whatever produced it (teleop, policy, replay, scripts).
//!
//! What it does with a command, in order:
//! 1. Refuses an unknown mode, a NaN or infinite value in any field the mode uses or in the
//!    gripper position, and a stale command (stamped more than `max_command_age_s` before now,
//!    or as far in the future). Refused commands never reach the backend: the arm holds.
//! 2. Turns the command into a TCP target (cartesian modes) or joint targets (joint modes):
//!    velocity components outside [-1, 1] are clipped (DROID scaling: at most 0.075 m and
//!    0.15 rad a step); absolute poses farther than one such step from the TCP are clipped to
//!    one step along the way. Joint position targets outside the FR3's limits are refused;
//!    inside the limits but within the margin they are clipped to the margin.
//! 3. Keeps the TCP inside the workspace box: cartesian targets are clipped into it; joint
//!    commands whose TCP would leave it are refused.
//! 4. Cartesian targets go through the IK (seeded with the last command).
//! 5. Limits the step from the last commanded joints to each joint's velocity limit x period x
//!    `velocity_fraction`, scaling the whole step (the direction is kept).
//!
//! Every clip is reported with the command ([`SafeCommand::clipped`]), every refusal is an
//! error naming the field and the limit. The [`Watchdog`] brings the arm to a hold when no
//! fresh command arrived within `watchdog_periods` control periods.

use crate::ik::{self, Ik};
use crate::kinematics::{DOF, Joints};
use labrig_msgs::rig::{ArmCommand, ArmCommandMode};
use labrig_msgs::{Invalid, Nanos};
use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};

/// The safety limits (a node's `[safety]` config section).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SafetyConfig {
    /// Control period (s): per-step limits are per this period.
    pub period_s: f64,
    /// The TCP's allowed box in the robot base frame (m).
    pub workspace_min_m: [f64; 3],
    pub workspace_max_m: [f64; 3],
    /// Joints stay this far inside the FR3's limits (rad).
    pub joint_margin_rad: f64,
    /// Fraction of each joint's velocity limit one step may use.
    pub velocity_fraction: f64,
    /// Absolute pose targets are clipped to this far from the TCP per step (m, rad).
    pub max_step_m: f64,
    pub max_step_rad: f64,
    /// Hold the arm when no fresh command came for this many periods.
    pub watchdog_periods: f64,
    /// Refuse commands stamped this long ago (s); 0 turns the check off.
    pub max_command_age_s: f64,
    /// Velocity commands step from the last *commanded* pose while the arm tracks it within
    /// this lead (m for the TCP, rad for its rotation and for joints), so a lagging arm
    /// follows a straight line instead of re-basing each step on where it lags; beyond the
    /// lead (a hold, a contact) they step from the measured pose, as DROID does.
    pub max_lead_m: f64,
    pub max_lead_rad: f64,
}

impl Default for SafetyConfig {
    fn default() -> Self {
        SafetyConfig {
            period_s: 0.05,
            workspace_min_m: [0.15, -0.6, 0.02],
            workspace_max_m: [0.9, 0.6, 0.9],
            joint_margin_rad: 0.02,
            velocity_fraction: 0.8,
            max_step_m: ik::MAX_LIN_DELTA,
            max_step_rad: ik::MAX_ROT_DELTA,
            watchdog_periods: 2.0,
            max_command_age_s: 0.1,
            max_lead_m: 0.02,
            max_lead_rad: 0.1,
        }
    }
}

impl SafetyConfig {
    /// Checks the limits make sense; the error names the field.
    pub fn validate(&self) -> Result<(), Invalid> {
        let pos = |name: &str, v: f64| {
            if v.is_finite() && v > 0.0 {
                Ok(())
            } else {
                Err(Invalid::new(format!("safety.{name}"), format!("safety.{name} = {v} must be > 0")))
            }
        };
        pos("period_s", self.period_s)?;
        pos("velocity_fraction", self.velocity_fraction)?;
        pos("max_step_m", self.max_step_m)?;
        pos("max_step_rad", self.max_step_rad)?;
        pos("watchdog_periods", self.watchdog_periods)?;
        pos("max_lead_m", self.max_lead_m)?;
        pos("max_lead_rad", self.max_lead_rad)?;
        if self.velocity_fraction > 1.0 {
            return Err(Invalid::new(
                "safety.velocity_fraction",
                format!("safety.velocity_fraction = {} must be <= 1", self.velocity_fraction),
            ));
        }
        for k in 0..3 {
            if self.workspace_min_m[k].partial_cmp(&self.workspace_max_m[k]) != Some(std::cmp::Ordering::Less) {
                return Err(Invalid::new(
                    format!("safety.workspace_min_m[{k}]"),
                    format!(
                        "safety.workspace_min_m[{k}] = {} must be below workspace_max_m[{k}] = {}",
                        self.workspace_min_m[k], self.workspace_max_m[k]
                    ),
                ));
            }
        }
        if !(0.0..0.5).contains(&self.joint_margin_rad) {
            return Err(Invalid::new(
                "safety.joint_margin_rad",
                format!("safety.joint_margin_rad = {} must be in [0, 0.5)", self.joint_margin_rad),
            ));
        }
        if self.max_command_age_s.is_nan() || self.max_command_age_s < 0.0 {
            return Err(Invalid::new(
                "safety.max_command_age_s",
                format!("safety.max_command_age_s = {} must be >= 0", self.max_command_age_s),
            ));
        }
        Ok(())
    }

    /// The watchdog's timeout (ns).
    pub fn watchdog_timeout(&self) -> Nanos {
        Nanos((self.watchdog_periods * self.period_s * 1e9).round() as i64)
    }
}

/// Why a command was refused. Nothing of it reached the backend.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum Refusal {
    #[error("unknown command mode {0}")]
    UnknownMode(u8),
    #[error("{field}[{index}] is {value}: not a finite number")]
    NonFinite { field: &'static str, index: usize, value: f64 },
    #[error("gripper_position is {0}: not a finite number")]
    GripperNonFinite(f64),
    #[error("stale command: stamped {age_ms:.0} ms from now (limit {limit_ms:.0} ms)")]
    Stale { age_ms: f64, limit_ms: f64 },
    #[error("{joint} target {value:.4} rad is outside its limits [{lower:.4}, {upper:.4}]")]
    JointOutOfLimits { joint: String, value: f64, lower: f64, upper: f64 },
    #[error("the joint targets put the TCP at [{:.3}, {:.3}, {:.3}], outside the workspace", .tcp[0], .tcp[1], .tcp[2])]
    OutsideWorkspace { tcp: [f64; 3] },
}

/// A limit a command was clipped to (reported, the clipped command goes on).
#[derive(Debug, Clone, PartialEq, Serialize)]
#[serde(tag = "clip", rename_all = "snake_case")]
pub enum Clip {
    /// A velocity component was outside [-1, 1].
    VelocityRange { field: &'static str, index: usize, value: f64 },
    /// An absolute pose was farther than one step from the TCP.
    PoseStep { metres: f64, radians: f64 },
    /// The TCP target left the workspace on `axis` (0 x, 1 y, 2 z).
    Workspace { axis: usize, value: f64, limit: f64 },
    /// A joint target sat inside the margin of its limit.
    JointMargin { joint: usize, value: f64, limit: f64 },
    /// The joint step was faster than the velocity limits allow: scaled by `scale`.
    JointStep { joint: usize, step: f64, allowed: f64, scale: f64 },
    /// The gripper position was outside 0..1.
    Gripper { value: f64 },
    /// The IK could not reach the target exactly (m, rad from it).
    Unreachable { metres: f64, radians: f64 },
}

/// A command that passed: joint targets for the backend and what was clipped on the way.
#[derive(Debug, Clone, PartialEq)]
pub struct SafeCommand {
    pub joints: Joints,
    /// The TCP pose those joints give (FK).
    pub tcp: Isometry3<f64>,
    /// 0 open .. 1 closed.
    pub gripper: f64,
    pub clipped: Vec<Clip>,
}

/// What the filter needs to know about the arm: where it is and what it was last told.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ArmView {
    pub measured: Joints,
    pub commanded: Joints,
}

/// The safety layer: limits + the IK that turns cartesian targets into joint targets.
#[derive(Debug, Clone)]
pub struct SafetyFilter {
    cfg: SafetyConfig,
    ik: Ik,
    bounds: [[f64; 2]; DOF],
    max_joint_step: Joints,
}

impl SafetyFilter {
    pub fn new(ik: Ik, cfg: SafetyConfig) -> Result<SafetyFilter, Invalid> {
        cfg.validate()?;
        let kin = ik.kinematics();
        let bounds = kin.limits().map(|[lo, hi]| [lo + cfg.joint_margin_rad, hi - cfg.joint_margin_rad]);
        let max_joint_step = kin.velocity_limits().map(|v| v * cfg.period_s * cfg.velocity_fraction);
        Ok(SafetyFilter { cfg, ik, bounds, max_joint_step })
    }

    pub fn config(&self) -> &SafetyConfig {
        &self.cfg
    }

    pub fn ik(&self) -> &Ik {
        &self.ik
    }

    /// The largest step per control period for each joint (rad).
    pub fn max_joint_step(&self) -> Joints {
        self.max_joint_step
    }

    /// Checks `cmd` against the limits and turns it into joint targets. `now` is the
    /// node's clock (same time base as the command stamps).
    pub fn filter(&self, cmd: &ArmCommand, arm: &ArmView, now: Nanos) -> Result<SafeCommand, Refusal> {
        let mode = cmd.mode().map_err(|_| Refusal::UnknownMode(cmd.mode))?;
        let finite = |field: &'static str, v: &[f64]| -> Result<(), Refusal> {
            match v.iter().position(|x| !x.is_finite()) {
                Some(index) => Err(Refusal::NonFinite { field, index, value: v[index] }),
                None => Ok(()),
            }
        };
        match mode {
            ArmCommandMode::CartesianVelocity => finite("cartesian_velocity", &cmd.cartesian_velocity)?,
            ArmCommandMode::CartesianPosition | ArmCommandMode::CartesianPositionAxisAngle => {
                finite("cartesian_position", &cmd.cartesian_position)?
            }
            ArmCommandMode::JointVelocity => finite("joint_velocity", &cmd.joint_velocity)?,
            ArmCommandMode::JointPosition => finite("joint_position", &cmd.joint_position)?,
        }
        if !cmd.gripper_position.is_finite() {
            return Err(Refusal::GripperNonFinite(cmd.gripper_position));
        }
        let stamp = cmd.header.stamp.sec as i64 * 1_000_000_000 + cmd.header.stamp.nanosec as i64;
        if self.cfg.max_command_age_s > 0.0 {
            let age = (now.0 - stamp) as f64 * 1e-9;
            if age.abs() > self.cfg.max_command_age_s {
                return Err(Refusal::Stale { age_ms: age * 1e3, limit_ms: self.cfg.max_command_age_s * 1e3 });
            }
        }
        let mut clipped = Vec::new();
        let gripper = cmd.gripper_position.clamp(0.0, 1.0);
        if gripper != cmd.gripper_position {
            clipped.push(Clip::Gripper { value: cmd.gripper_position });
        }
        let kin = self.ik.kinematics();
        let here = kin.tcp_pose(&arm.measured);
        let joints = match mode {
            ArmCommandMode::CartesianVelocity | ArmCommandMode::JointVelocity => {
                let (field, v): (&'static str, &[f64]) = if mode == ArmCommandMode::JointVelocity {
                    ("joint_velocity", &cmd.joint_velocity)
                } else {
                    ("cartesian_velocity", &cmd.cartesian_velocity)
                };
                for (index, &value) in v.iter().enumerate() {
                    if value.abs() > 1.0 {
                        clipped.push(Clip::VelocityRange { field, index, value });
                    }
                }
                if mode == ArmCommandMode::JointVelocity {
                    let lead = (0..7).map(|i| (arm.commanded[i] - arm.measured[i]).abs()).fold(0.0, f64::max);
                    let base = if lead <= self.cfg.max_lead_rad { &arm.commanded } else { &arm.measured };
                    let q: Joints = std::array::from_fn(|i| base[i] + v[i].clamp(-1.0, 1.0) * self.max_joint_step[i]);
                    self.check_joint_targets(&q, false, &mut clipped)?
                } else {
                    let v6: [f64; 6] = std::array::from_fn(|i| v[i].clamp(-1.0, 1.0));
                    let commanded = kin.tcp_pose(&arm.commanded);
                    let (dp, dr) = ik::pose_error(&here, &commanded);
                    let base = if dp.norm() <= self.cfg.max_lead_m && dr.norm() <= self.cfg.max_lead_rad {
                        commanded
                    } else {
                        here
                    };
                    let target = ik::apply_velocity(&base, &v6);
                    self.cartesian(target, arm, &mut clipped)
                }
            }
            ArmCommandMode::CartesianPosition | ArmCommandMode::CartesianPositionAxisAngle => {
                let target = if mode == ArmCommandMode::CartesianPosition {
                    ik::pose_from_xyz_euler(&cmd.cartesian_position)
                } else {
                    ik::pose_from_xyz_axis_angle(&cmd.cartesian_position)
                };
                let target = self.limit_pose_step(&here, &target, &mut clipped);
                self.cartesian(target, arm, &mut clipped)
            }
            ArmCommandMode::JointPosition => self.check_joint_targets(&cmd.joint_position, true, &mut clipped)?,
        };
        let joints = self.limit_joint_step(&arm.commanded, joints, &mut clipped);
        Ok(SafeCommand { tcp: kin.tcp_pose(&joints), joints, gripper, clipped })
    }

    /// Clips an absolute target to one step (translation and rotation) from `here`.
    fn limit_pose_step(
        &self,
        here: &Isometry3<f64>,
        target: &Isometry3<f64>,
        clipped: &mut Vec<Clip>,
    ) -> Isometry3<f64> {
        let (dp, dr) = ik::pose_error(here, target);
        let (m, r) = (dp.norm(), dr.norm());
        if m <= self.cfg.max_step_m && r <= self.cfg.max_step_rad {
            return *target;
        }
        clipped.push(Clip::PoseStep { metres: m, radians: r });
        let dp = if m > self.cfg.max_step_m { dp * (self.cfg.max_step_m / m) } else { dp };
        let dr = if r > self.cfg.max_step_rad { dr * (self.cfg.max_step_rad / r) } else { dr };
        Isometry3::from_parts(
            Translation3::from(here.translation.vector + dp),
            UnitQuaternion::from_scaled_axis(dr) * here.rotation,
        )
    }

    /// A cartesian target: clipped into the workspace, then through the IK.
    fn cartesian(&self, mut target: Isometry3<f64>, arm: &ArmView, clipped: &mut Vec<Clip>) -> Joints {
        for axis in 0..3 {
            let v = target.translation.vector[axis];
            let (lo, hi) = (self.cfg.workspace_min_m[axis], self.cfg.workspace_max_m[axis]);
            if v < lo || v > hi {
                let limit = v.clamp(lo, hi);
                clipped.push(Clip::Workspace { axis, value: v, limit });
                target.translation.vector[axis] = limit;
            }
        }
        let sol = self.ik.solve(&arm.commanded, &target);
        if sol.position_error_m > 1e-3 || sol.rotation_error_rad > 1e-2 {
            clipped.push(Clip::Unreachable { metres: sol.position_error_m, radians: sol.rotation_error_rad });
        }
        sol.joints
    }

    /// Joint targets: refused outside the FR3's limits (`strict`) or clipped to them, clipped
    /// into the margin, and refused if their TCP leaves the workspace.
    fn check_joint_targets(&self, q: &Joints, strict: bool, clipped: &mut Vec<Clip>) -> Result<Joints, Refusal> {
        let kin = self.ik.kinematics();
        let limits = kin.limits();
        let mut out = *q;
        for i in 0..DOF {
            let [lo, hi] = limits[i];
            if strict && (q[i] < lo || q[i] > hi) {
                return Err(Refusal::JointOutOfLimits {
                    joint: kin.joint_names()[i].to_owned(),
                    value: q[i],
                    lower: lo,
                    upper: hi,
                });
            }
            let [blo, bhi] = self.bounds[i];
            if q[i] < blo || q[i] > bhi {
                let limit = q[i].clamp(blo, bhi);
                clipped.push(Clip::JointMargin { joint: i, value: q[i], limit });
                out[i] = limit;
            }
        }
        let tcp = kin.tcp_pose(&out).translation.vector;
        let inside = (0..3).all(|k| tcp[k] >= self.cfg.workspace_min_m[k] && tcp[k] <= self.cfg.workspace_max_m[k]);
        if !inside {
            return Err(Refusal::OutsideWorkspace { tcp: [tcp.x, tcp.y, tcp.z] });
        }
        Ok(out)
    }

    /// Scales the step from the last command so no joint moves faster than allowed.
    fn limit_joint_step(&self, from: &Joints, to: Joints, clipped: &mut Vec<Clip>) -> Joints {
        let mut scale = 1.0f64;
        let mut worst = None;
        for i in 0..DOF {
            let step = (to[i] - from[i]).abs();
            if step > self.max_joint_step[i] {
                let s = self.max_joint_step[i] / step;
                if s < scale {
                    scale = s;
                    worst = Some((i, step));
                }
            }
        }
        if let Some((joint, step)) = worst {
            clipped.push(Clip::JointStep { joint, step, allowed: self.max_joint_step[joint], scale });
        }
        std::array::from_fn(|i| {
            let q = from[i] + (to[i] - from[i]) * scale;
            q.clamp(self.bounds[i][0], self.bounds[i][1])
        })
    }
}

/// Brings the arm to a hold when commands stop: `expired` once no command was fed for the
/// timeout (two control periods by default, 100 ms at 20 Hz).
#[derive(Debug, Clone)]
pub struct Watchdog {
    timeout: Nanos,
    last: Option<Nanos>,
    tripped: bool,
}

impl Watchdog {
    pub fn new(timeout: Nanos) -> Watchdog {
        Watchdog { timeout, last: None, tripped: false }
    }

    /// A fresh, accepted command arrived at `now`.
    pub fn feed(&mut self, now: Nanos) {
        self.last = Some(now);
        self.tripped = false;
    }

    /// Whether the arm must hold at `now`: commands were flowing and stopped for the
    /// timeout or longer. Returns `Some(silence)` the first time it trips, for the report.
    pub fn check(&mut self, now: Nanos) -> Option<Nanos> {
        let last = self.last?;
        let silence = now - last;
        if silence >= self.timeout && !self.tripped {
            self.tripped = true;
            return Some(silence);
        }
        None
    }

    /// When the watchdog trips if no command comes first: `None` before the first command
    /// and while it is holding. A control loop that steps in coarse ticks uses it to stop
    /// mid-tick, on time, rather than at the next tick.
    pub fn deadline(&self) -> Option<Nanos> {
        match (self.last, self.tripped) {
            (Some(last), false) => Some(last + self.timeout),
            _ => None,
        }
    }

    /// Holding: commands stopped and no fresh one has come since.
    pub fn tripped(&self) -> bool {
        self.tripped
    }
}

/// A pose's position as an array (for reports).
pub fn position(p: &Isometry3<f64>) -> [f64; 3] {
    let v: Vector3<f64> = p.translation.vector;
    [v.x, v.y, v.z]
}
