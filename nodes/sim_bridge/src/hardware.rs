//! The simulated hardware as a state machine: what the bridge does with each command and each
//! period, apart from where commands come from and where states go. The bridge
//! ([`crate::bridge`]) feeds it from ROS 2 and publishes what it reports; a test feeds it
//! commands in memory and steps it period by period on the sim's own clock.
//!
//! - [`SimHardware::arm_command`]: an `/arm/command` through the franka node's safety layer
//!   (or, behind a hardware prefix, the sim's own limits only), fed to the watchdog;
//! - [`SimHardware::gripper_command`]: a `/gripper/command` position, 0..1 or refused;
//! - [`SimHardware::step`]: one control period on the last good targets; when commands have
//!   stopped for the watchdog's timeout the arm is held from the physics step at the deadline on;
//! - [`SimHardware::replace_scene`]: a new scene (`/sim/reset`), the counters kept;
//! - [`SimHardware::state`]: what `/arm/state` and `/gripper/state` report (fault, mode, counts).

use labrig_arm::safety::{ArmView, SafetyFilter, Watchdog};
use labrig_msgs::Nanos;
use labrig_msgs::rig::{ArmCommand, ArmCommandMode};
use labrig_sim::{ArmTarget, Sim, SimError};

/// What the hardware last heard and did.
#[derive(Debug, Default)]
pub struct CommandState {
    /// The last accepted arm target (None: the sim's own targets, e.g. the reset pose).
    pub arm: Option<ArmTarget>,
    /// The gripper target, 0 open .. 1 closed.
    pub gripper: f64,
    /// The newest refusal or fault (empty: none since the last good command).
    pub fault: String,
    /// Whether the last command was accepted.
    pub last_ok: bool,
    pub refused: u64,
    pub clipped: u64,
    pub commands: u64,
    /// The watchdog tripped: the arm holds until a fresh command.
    pub holding: bool,
}

impl CommandState {
    fn fresh() -> CommandState {
        CommandState { gripper: 0.0, last_ok: true, ..Default::default() }
    }
}

/// The simulated FR3 + 2F-85 behind the hardware's interface.
#[derive(Debug)]
pub struct SimHardware {
    sim: Sim,
    safety: SafetyFilter,
    watchdog: Watchdog,
    state: CommandState,
    /// Without a hardware prefix the bridge stands in for the franka node too: arm commands
    /// go through the safety layer and carry the gripper.
    arm_sets_gripper: bool,
}

impl SimHardware {
    pub fn new(sim: Sim, safety: SafetyFilter, arm_sets_gripper: bool) -> SimHardware {
        let watchdog = Watchdog::new(safety.config().watchdog_timeout());
        SimHardware { sim, safety, watchdog, state: CommandState::fresh(), arm_sets_gripper }
    }

    pub fn sim(&self) -> &Sim {
        &self.sim
    }

    pub fn sim_mut(&mut self) -> &mut Sim {
        &mut self.sim
    }

    pub fn state(&self) -> &CommandState {
        &self.state
    }

    /// Counts and reports an input that was refused before it reached the hardware (a
    /// malformed message, a bad `/sim/reset`).
    pub fn refuse(&mut self, fault: String) {
        self.state.refused += 1;
        self.state.last_ok = false;
        tracing::warn!("{fault}");
        self.state.fault = fault;
    }

    /// A new scene: the hardware starts over at its reset pose; the counts go on.
    pub fn replace_scene(&mut self, next: Sim) {
        self.sim = next;
        let s = &self.state;
        self.state =
            CommandState { commands: s.commands, refused: s.refused, clipped: s.clipped, ..CommandState::fresh() };
        self.watchdog = Watchdog::new(self.safety.config().watchdog_timeout());
    }

    /// A gripper command's position (0 open .. 1 closed).
    pub fn gripper_command(&mut self, position: f64) {
        if position.is_finite() && (0.0..=1.0).contains(&position) {
            self.state.gripper = position;
        } else {
            self.state.refused += 1;
            self.state.fault = format!("refused gripper command: position {position} is outside 0..1");
            tracing::warn!("{}", self.state.fault);
        }
    }

    /// An arm command that arrived at `arrival` (on the sim's time line).
    pub fn arm_command(&mut self, cmd: &ArmCommand, arrival: Nanos) {
        let (sim, state) = (&self.sim, &mut self.state);
        state.commands += 1;
        let view = ArmView {
            measured: sim.joint_positions(),
            commanded: state.arm.map_or_else(|| sim.joint_targets(), |t| t.joints),
        };
        let checked = if self.arm_sets_gripper {
            self.safety.filter(cmd, &view, sim.time()).map_err(|e| e.to_string()).and_then(|ok| {
                let t = ArmTarget { joints: ok.joints, gripper: ok.gripper };
                sim.check(&t).map(|()| (t, ok.clipped)).map_err(|e| e.to_string())
            })
        } else {
            // Behind a prefix the bridge is the hardware: the franka node in front of it ran
            // the safety layer; like the FR3, the sim only checks its own limits.
            match cmd.mode() {
                Ok(ArmCommandMode::JointPosition) => {
                    let t = ArmTarget { joints: cmd.joint_position, gripper: state.gripper };
                    sim.check(&t).map(|()| (t, Vec::new())).map_err(|e| e.to_string())
                }
                _ => Err(format!(
                    "behind --hardware-prefix the sim takes joint position targets only (mode {})",
                    cmd.mode
                )),
            }
        };
        match checked {
            Ok((t, clipped)) => {
                if !clipped.is_empty() {
                    state.clipped += 1;
                    tracing::debug!(seq = cmd.seq, ?clipped, "arm command clipped");
                }
                state.arm = Some(t);
                state.gripper = t.gripper;
                state.last_ok = true;
                state.holding = false;
                state.fault.clear();
                self.watchdog.feed(arrival);
            }
            Err(reason) => {
                state.refused += 1;
                state.last_ok = false;
                state.fault = format!("refused arm command seq {}: {reason}", cmd.seq);
                tracing::warn!("{}", state.fault);
            }
        }
    }

    /// One control period on the last good targets. Commands stopped: the watchdog's deadline
    /// falls in this period, so the arm is held where it is (it decelerates on the servos)
    /// from the physics step at the deadline on, not at the next period.
    pub fn step(&mut self) -> Result<(), SimError> {
        let (sim, state) = (&mut self.sim, &mut self.state);
        let period = sim.period().0;
        let target =
            ArmTarget { joints: state.arm.map_or_else(|| sim.joint_targets(), |t| t.joints), gripper: state.gripper };
        let t0 = sim.time().0;
        let stop_at = self.watchdog.deadline().map(|d| d.0).filter(|&d| d < t0 + period).map(|d| {
            let substep = sim.substep().0.max(1);
            ((d - t0).max(0) + substep - 1) / substep
        });
        let stepped = match stop_at {
            Some(after) => sim.step_then_hold(&target, after as u32).map(|held| {
                let silence = self.watchdog.check(Nanos(t0 + after * sim.substep().0)).unwrap_or(Nanos::ZERO).0;
                state.arm = Some(ArmTarget { joints: held, gripper: state.gripper });
                state.holding = true;
                state.fault = format!(
                    "watchdog: no arm command for {:.1} ms; holding at the measured joints",
                    silence as f64 / 1e6
                );
                tracing::warn!("{}", state.fault);
            }),
            None => sim.step(&target),
        };
        if let Err(e) = stepped {
            // Checked on accept; a failure here is a bug, reported, never silently stepped.
            state.fault = e.to_string();
            state.last_ok = false;
            tracing::error!("{e}");
            sim.step(&ArmTarget { joints: sim.joint_targets(), gripper: state.gripper.clamp(0.0, 1.0) })?;
        }
        Ok(())
    }
}
