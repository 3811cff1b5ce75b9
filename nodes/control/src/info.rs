//! The action spaces the loop executes, what a policy server serves (`/policy/info`) and
//! whether this loop can feed and execute it. Imports no module of this crate.

use serde::{Deserialize, Serialize};

/// The action spaces the loop executes (`joint_position`: 7 joint targets + the gripper, what
/// a remote openpi policy's chunk becomes, see [`crate::remote`]).
pub const EXECUTABLE: [&str; 3] = ["eef_axis_angle", "cartesian_velocity", "joint_position"];

/// An action space's width: 6 + the gripper, or 7 joints + the gripper.
pub fn action_width(action_space: &str) -> usize {
    if action_space == "joint_position" { 8 } else { 7 }
}

/// What the server serves (`/policy/info`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PolicyInfo {
    pub policy_id: String,
    pub cameras: Vec<String>,
    pub n_obs_steps: usize,
    pub horizon: usize,
    pub n_action_steps: usize,
    pub action_space: String,
    pub action_dim: usize,
    /// The inputs it observes that only a simulator has (empty: pixels and proprioception).
    #[serde(default)]
    pub sim_only: Vec<String>,
}

impl PolicyInfo {
    /// Whether this loop can feed and execute the policy; the mismatch named if not.
    /// `sim_rig`: this loop runs the simulated rig (sim-only inputs allowed).
    pub fn check(&self, rig_cameras: &[String], action_space: &str, sim_rig: bool) -> Result<(), String> {
        let id = &self.policy_id;
        if !sim_rig && !self.sim_only.is_empty() {
            return Err(format!(
                "the policy {id} observes {:?}, which only the simulator has; this rig is not a sim rig (policy.sim_rig = false): a real rig gives a policy camera images and proprioception only",
                self.sim_only
            ));
        }
        let missing: Vec<&String> = self.cameras.iter().filter(|c| !rig_cameras.contains(c)).collect();
        if !missing.is_empty() {
            return Err(format!(
                "the policy {id} observes cameras {missing:?}, which this rig does not record (it has {rig_cameras:?})"
            ));
        }
        if !EXECUTABLE.contains(&self.action_space.as_str()) {
            return Err(format!(
                "the policy {id} predicts {:?} actions, which the loop cannot execute (it executes {EXECUTABLE:?})",
                self.action_space
            ));
        }
        if !action_space.is_empty() && self.action_space != action_space {
            return Err(format!(
                "the policy {id} predicts {:?} actions; this rig is configured for {action_space:?} (policy.action_space)",
                self.action_space
            ));
        }
        let width = action_width(&self.action_space);
        if self.action_dim != width {
            return Err(format!(
                "the policy {id} predicts {}-wide actions; {:?} is {width} wide ({} + the gripper)",
                self.action_dim,
                self.action_space,
                width - 1
            ));
        }
        if self.n_obs_steps == 0 || self.horizon < self.n_obs_steps || self.n_action_steps == 0 {
            return Err(format!(
                "the policy {id} has n_obs_steps {}, horizon {}, n_action_steps {}: no action to execute",
                self.n_obs_steps, self.horizon, self.n_action_steps
            ));
        }
        Ok(())
    }
}
