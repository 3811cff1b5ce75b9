//! The `sim` backend: the gripper node in front of the sim bridge's 2F-85, served under a
//! prefix (`labrig-sim run --hardware-prefix /sim`). Requests go to `<prefix>/gripper/command`;
//! the bridge's `<prefix>/gripper/state` is read back as the 2F-85's status registers, so the
//! node's logic (writes on change, refusals, reports) is the same as on the hardware.

use crate::driver::GripperError;
use crate::registers::{Activation, Object, Status, counts_to_droid, droid_to_counts};
use labrig_msgs::rig::{GripperCommand, GripperState};
use labrig_msgs::topics;
use labrig_runtime::ros::{Ros, RosError, RosPublisher, RosSubscription};
use std::time::{Duration, Instant};

/// No state from the bridge for this long: the link is lost.
const STALE: Duration = Duration::from_secs(1);

pub struct SimGripper {
    prefix: String,
    command: RosPublisher<GripperCommand>,
    state: RosSubscription<GripperState>,
    latest: Option<(GripperState, Instant)>,
    last: Option<Status>,
    requested: u8,
}

impl std::fmt::Debug for SimGripper {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("SimGripper").field("prefix", &self.prefix).field("last", &self.last).finish_non_exhaustive()
    }
}

impl SimGripper {
    pub fn new(ros: &mut Ros, prefix: &str) -> Result<SimGripper, RosError> {
        let p = prefix.trim_end_matches('/');
        Ok(SimGripper {
            prefix: p.to_owned(),
            command: ros.publisher_at(p, &topics::GRIPPER_COMMAND, 10)?,
            state: ros.subscription_at(p, &topics::GRIPPER_STATE, 100)?,
            latest: None,
            last: None,
            requested: 0,
        })
    }

    fn link(&self, why: String) -> GripperError {
        GripperError::Sim(format!("{}/gripper/state: {why}", self.prefix))
    }

    /// The simulated gripper needs no activation; waits for the bridge's first state.
    pub async fn activate(&mut self, within: Duration) -> Result<Status, GripperError> {
        let deadline = Instant::now() + within;
        loop {
            match self.status().await {
                Ok(s) => return Ok(s),
                Err(e) if Instant::now() >= deadline => return Err(e),
                Err(_) => tokio::time::sleep(Duration::from_millis(20)).await,
            }
        }
    }

    pub async fn go_to(&mut self, position: u8, speed: u8, force: u8) -> Result<(), GripperError> {
        let cmd = GripperCommand {
            position: counts_to_droid(position),
            speed: counts_to_droid(speed),
            force: counts_to_droid(force),
            ..GripperCommand::default()
        };
        self.command.publish(cmd).map_err(|e| self.link(e.to_string()))?;
        self.requested = position;
        Ok(())
    }

    /// The bridge's latest state as 2F-85 registers: always activated, no faults (the sim has
    /// none), gOBJ 2 when the bridge reports an object, else moving until the fingers are
    /// within 2 counts of the request.
    pub async fn status(&mut self) -> Result<Status, GripperError> {
        while let Some(s) = self.state.try_take().map_err(|e| self.link(e.to_string()))? {
            self.latest = Some((s.msg, Instant::now()));
        }
        let Some((g, at)) = &self.latest else { return Err(self.link("no state from the sim bridge yet".into())) };
        if at.elapsed() > STALE {
            return Err(self.link(format!("no state from the sim bridge for {:.1} s", at.elapsed().as_secs_f64())));
        }
        let position = droid_to_counts(g.position);
        let requested = droid_to_counts(g.requested_position);
        let object = if g.object_detected {
            Object::ContactClosing
        } else if position.abs_diff(requested) <= 2 {
            Object::AtRequest
        } else {
            Object::Moving
        };
        let status = Status {
            activated: true,
            going: true,
            activation: Activation::Complete,
            object,
            fault: 0,
            controller_fault: 0,
            requested,
            position,
            current: (g.current_ma / 10.0).clamp(0.0, 255.0) as u8,
        };
        self.last = Some(status);
        Ok(status)
    }

    pub fn last_status(&self) -> Option<Status> {
        self.last
    }
}
