//! The `sim` backend: the franka node in front of the sim bridge. The bridge serves the
//! simulated FR3 under a prefix (`labrig-sim run --hardware-prefix /sim`); this backend sends
//! the node's checked joint targets to `<prefix>/arm/command` and reads `<prefix>/arm/state`,
//! so the node's own path (safety layer, IK, watchdog, latency, faults) runs against physics.
//! With a prefix the bridge ignores arm commands' gripper field (the gripper node owns the
//! gripper), as the real FR3 does.

use crate::backend::{ArmBackend, ArmReading, BackendError};
use labrig_arm::Joints;
use labrig_msgs::rig::{ArmCommand, ArmCommandMode, RobotState};
use labrig_msgs::topics;
use labrig_runtime::Clock;
use labrig_runtime::ros::{Ros, RosError, RosPublisher, RosSubscription};
use std::time::{Duration, Instant};

/// No state from the bridge for this long: the connection is lost.
const STALE: Duration = Duration::from_secs(1);

pub struct SimArm {
    prefix: String,
    command: RosPublisher<ArmCommand>,
    state: RosSubscription<RobotState>,
    clock: Clock,
    latest: Option<(RobotState, Instant)>,
    target: Joints,
    seq: u64,
}

impl std::fmt::Debug for SimArm {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("SimArm").field("prefix", &self.prefix).field("seq", &self.seq).finish_non_exhaustive()
    }
}

impl SimArm {
    /// Joins the bridge's arm topics under `prefix` (e.g. `/sim`); commands are stamped on
    /// `clock` (the node's sim clock).
    pub fn new(ros: &mut Ros, prefix: &str, clock: Clock) -> Result<SimArm, RosError> {
        let p = prefix.trim_end_matches('/');
        Ok(SimArm {
            prefix: p.to_owned(),
            command: ros.publisher_at(p, &topics::ARM_COMMAND, 100)?,
            state: ros.subscription_at(p, &topics::ARM_STATE, 100)?,
            clock,
            latest: None,
            target: [0.0; 7],
            seq: 0,
        })
    }

    fn drain(&mut self) -> Result<(), BackendError> {
        let lost = |e: RosError| BackendError::Disconnected(e.to_string());
        while let Some(s) = self.state.try_take().map_err(lost)? {
            self.latest = Some((s.msg, Instant::now()));
        }
        Ok(())
    }
}

impl ArmBackend for SimArm {
    fn name(&self) -> &'static str {
        "sim"
    }

    fn read(&mut self) -> Result<ArmReading, BackendError> {
        self.drain()?;
        let Some((s, at)) = &self.latest else {
            return Err(BackendError::Start(format!("no state from the sim bridge on {}/arm/state yet", self.prefix)));
        };
        if at.elapsed() > STALE {
            return Err(BackendError::Disconnected(format!(
                "no state from the sim bridge on {}/arm/state for {:.1} s",
                self.prefix,
                at.elapsed().as_secs_f64()
            )));
        }
        if s.mode == RobotState::MODE_FAULT {
            return Err(BackendError::Reflex(format!("the sim bridge refused a target: {}", s.fault)));
        }
        let target = if self.seq == 0 { s.joint_positions } else { self.target };
        Ok(ArmReading { q: s.joint_positions, dq: s.joint_velocities, q_target: target, ..ArmReading::default() })
    }

    fn set_target(&mut self, target: &Joints) -> Result<(), BackendError> {
        self.drain()?;
        self.seq += 1;
        let mut c = ArmCommand {
            mode: ArmCommandMode::JointPosition as u8,
            joint_position: *target,
            seq: self.seq,
            ..ArmCommand::default()
        };
        c.header.stamp = self.clock.now().into();
        self.command.publish(c).map_err(|e| BackendError::Disconnected(e.to_string()))?;
        self.target = *target;
        Ok(())
    }

    fn recover(&mut self) -> Result<(), BackendError> {
        // Hold where the arm is (a fresh, valid command clears a refusal the bridge still
        // reports), then wait for a state after it that is not a fault.
        self.drain()?;
        let Some((s, _)) = &self.latest else {
            return Err(BackendError::Start(format!("no state from the sim bridge on {}/arm/state", self.prefix)));
        };
        let q = s.joint_positions;
        self.set_target(&q)?;
        let sent = Instant::now();
        let deadline = sent + Duration::from_secs(2);
        loop {
            self.drain()?;
            if let Some((s, at)) = &self.latest
                && *at > sent
                && s.mode != RobotState::MODE_FAULT
            {
                return Ok(());
            }
            if Instant::now() > deadline {
                let why = self.latest.as_ref().map_or("no state".to_owned(), |(s, _)| s.fault.clone());
                return Err(BackendError::Start(format!("the sim bridge did not take the hold: {why}")));
            }
            std::thread::sleep(Duration::from_millis(10));
        }
    }

    fn stop(&mut self) {}
}
