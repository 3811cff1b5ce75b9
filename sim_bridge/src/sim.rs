//! The rig's physics in lockstep: each [`Sim::step`] advances exactly one control period.

use crate::rig::{self, ARM_JOINTS, GRIPPER_ACTUATOR, GRIPPER_DRIVER_JOINT};
use labrig_msgs::Nanos;
use mujoco_rs::prelude::*;
use std::path::Path;
use std::sync::Arc;

/// Closing range of the 2F-85's driver joint (rad), for the 0..1 gripper position.
const DRIVER_CLOSED_RAD: f64 = 0.8;

#[derive(Debug, thiserror::Error)]
pub enum SimError {
    #[error(transparent)]
    Rig(#[from] rig::RigError),
    #[error("MuJoCo could not load the rig: {0}")]
    Load(String),
    #[error("the rig model lacks {kind} `{name}`")]
    MissingName { kind: &'static str, name: String },
    #[error("control period {period:?} is not a positive multiple of the physics timestep {timestep} s")]
    Period { period: Nanos, timestep: f64 },
    /// A command that must never reach the physics: the arm holds its last target.
    #[error("refused {what}: {reason}")]
    Refused { what: &'static str, reason: String },
}

/// One tick's command: FR3 joint position targets and the gripper closing command.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ArmTarget {
    pub joints: [f64; 7],
    /// 0 = open .. 1 = closed.
    pub gripper: f64,
}

/// The simulated rig.
pub struct Sim {
    data: MjData<Arc<MjModel>>,
    arm_actuators: [usize; 7],
    arm_qpos: [usize; 7],
    arm_limits: [[f64; 2]; 7],
    gripper_actuator: usize,
    gripper_qpos: usize,
    reset_key: usize,
    substeps: u32,
    ticks: u64,
    period: Nanos,
}

impl std::fmt::Debug for Sim {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Sim").field("ticks", &self.ticks).field("period", &self.period).finish()
    }
}

impl Sim {
    /// Loads the rig from `assets` (see [`rig::DEFAULT_ASSETS`]) and resets it to DROID's
    /// reset pose. `period` is the control period each [`Sim::step`] advances.
    pub fn new(assets: &Path, period: Nanos) -> Result<Sim, SimError> {
        let xml = rig::compose(assets)?;
        let model = Arc::new(MjModel::from_xml_string(&xml).map_err(|e| SimError::Load(format!("{e:?}")))?);
        let timestep = model.opt().timestep;
        let ratio = period.as_secs_f64() / timestep;
        if period.0 <= 0 || (ratio - ratio.round()).abs() > 1e-6 {
            return Err(SimError::Period { period, timestep });
        }
        let id = |kind: MjtObjBase, label: &'static str, name: &str| {
            model.name_to_id(kind, name).ok_or_else(|| SimError::MissingName { kind: label, name: name.to_owned() })
        };
        let mut arm_actuators = [0; 7];
        let mut arm_qpos = [0; 7];
        let mut arm_limits = [[0.0; 2]; 7];
        for (i, name) in ARM_JOINTS.iter().enumerate() {
            arm_actuators[i] = id(MjtObjBase::mjOBJ_ACTUATOR, "actuator", name)?;
            let joint = id(MjtObjBase::mjOBJ_JOINT, "joint", name)?;
            arm_qpos[i] = model.jnt_qposadr()[joint] as usize;
            arm_limits[i] = model.jnt_range()[joint];
        }
        let gripper_actuator = id(MjtObjBase::mjOBJ_ACTUATOR, "actuator", GRIPPER_ACTUATOR)?;
        let driver = id(MjtObjBase::mjOBJ_JOINT, "joint", GRIPPER_DRIVER_JOINT)?;
        let gripper_qpos = model.jnt_qposadr()[driver] as usize;
        let reset_key = id(MjtObjBase::mjOBJ_KEY, "keyframe", "reset")?;
        let data = MjData::new(model.clone());
        let mut sim = Sim {
            data,
            arm_actuators,
            arm_qpos,
            arm_limits,
            gripper_actuator,
            gripper_qpos,
            reset_key,
            substeps: ratio.round() as u32,
            ticks: 0,
            period,
        };
        sim.reset();
        Ok(sim)
    }

    /// Back to DROID's reset pose, time 0.
    pub fn reset(&mut self) {
        self.data.reset_keyframe(self.reset_key).expect("the reset keyframe id was looked up from this model");
        self.data.forward();
        self.ticks = 0;
    }

    /// Checks a command before it can touch the physics: finite values, joints inside the
    /// FR3's limits, gripper in 0..1.
    pub fn check(&self, target: &ArmTarget) -> Result<(), SimError> {
        for (i, (&q, [lo, hi])) in target.joints.iter().zip(self.arm_limits).enumerate() {
            if !q.is_finite() {
                return Err(SimError::Refused { what: "arm target", reason: format!("{} is {q}", ARM_JOINTS[i]) });
            }
            if q < lo || q > hi {
                return Err(SimError::Refused {
                    what: "arm target",
                    reason: format!("{} = {q:.4} rad is outside its limits [{lo:.4}, {hi:.4}]", ARM_JOINTS[i]),
                });
            }
        }
        if !(0.0..=1.0).contains(&target.gripper) {
            return Err(SimError::Refused {
                what: "gripper command",
                reason: format!("{} is outside 0..1", target.gripper),
            });
        }
        Ok(())
    }

    /// Applies `target` (after [`Sim::check`]) and advances exactly one control period.
    /// A refused command leaves the previous targets in place and the time unchanged.
    pub fn step(&mut self, target: &ArmTarget) -> Result<(), SimError> {
        self.check(target)?;
        let ctrl = self.data.ctrl_mut();
        for (i, &a) in self.arm_actuators.iter().enumerate() {
            ctrl[a] = target.joints[i];
        }
        // The 2F-85 takes 0..255 (the real gripper's rPR scale).
        ctrl[self.gripper_actuator] = (target.gripper * 255.0).round();
        for _ in 0..self.substeps {
            self.data.step();
        }
        self.ticks += 1;
        Ok(())
    }

    /// Simulated time: ticks x control period (exact, no float accumulation).
    pub fn time(&self) -> Nanos {
        Nanos(self.period.0 * self.ticks as i64)
    }

    pub fn joint_positions(&self) -> [f64; 7] {
        let qpos = self.data.qpos();
        std::array::from_fn(|i| qpos[self.arm_qpos[i]])
    }

    /// Gripper opening as 0 = open .. 1 = closed, from the driver joint.
    pub fn gripper_position(&self) -> f64 {
        (self.data.qpos()[self.gripper_qpos] / DRIVER_CLOSED_RAD).clamp(0.0, 1.0)
    }

    /// The whole physics state (for determinism checks and snapshots).
    pub fn qpos(&self) -> &[f64] {
        self.data.qpos()
    }
}
