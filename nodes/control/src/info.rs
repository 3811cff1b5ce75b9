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

/// Why this loop cannot feed or execute a policy, each naming the policy.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum PolicyMismatch {
    #[error(
        "the policy {policy_id} observes {inputs:?}, which only the simulator has; this rig is not a sim rig (policy.sim_rig = false): a real rig gives a policy camera images and proprioception only"
    )]
    SimOnly { policy_id: String, inputs: Vec<String> },
    #[error(
        "the policy {policy_id} observes cameras {missing:?}, which this rig does not record (it has {rig_cameras:?})"
    )]
    Cameras { policy_id: String, missing: Vec<String>, rig_cameras: Vec<String> },
    #[error(
        "the policy {policy_id} predicts {action_space:?} actions, which the loop cannot execute (it executes {:?})",
        EXECUTABLE
    )]
    NotExecutable { policy_id: String, action_space: String },
    #[error(
        "the policy {policy_id} predicts {action_space:?} actions; this rig is configured for {configured:?} (policy.action_space)"
    )]
    ActionSpace { policy_id: String, action_space: String, configured: String },
    #[error(
        "the policy {policy_id} predicts {action_dim}-wide actions; {action_space:?} is {width} wide ({} + the gripper)",
        .width - 1
    )]
    ActionWidth { policy_id: String, action_dim: usize, action_space: String, width: usize },
    #[error(
        "the policy {policy_id} has n_obs_steps {n_obs_steps}, horizon {horizon}, n_action_steps {n_action_steps}: no action to execute"
    )]
    NoAction { policy_id: String, n_obs_steps: usize, horizon: usize, n_action_steps: usize },
}

impl PolicyInfo {
    /// Whether this loop can feed and execute the policy; the mismatch named if not.
    /// `sim_rig`: this loop runs the simulated rig (sim-only inputs allowed).
    pub fn check(&self, rig_cameras: &[String], action_space: &str, sim_rig: bool) -> Result<(), PolicyMismatch> {
        let policy_id = self.policy_id.clone();
        if !sim_rig && !self.sim_only.is_empty() {
            return Err(PolicyMismatch::SimOnly { policy_id, inputs: self.sim_only.clone() });
        }
        let missing: Vec<String> = self.cameras.iter().filter(|c| !rig_cameras.contains(c)).cloned().collect();
        if !missing.is_empty() {
            return Err(PolicyMismatch::Cameras { policy_id, missing, rig_cameras: rig_cameras.to_vec() });
        }
        if !EXECUTABLE.contains(&self.action_space.as_str()) {
            return Err(PolicyMismatch::NotExecutable { policy_id, action_space: self.action_space.clone() });
        }
        if !action_space.is_empty() && self.action_space != action_space {
            return Err(PolicyMismatch::ActionSpace {
                policy_id,
                action_space: self.action_space.clone(),
                configured: action_space.to_owned(),
            });
        }
        let width = action_width(&self.action_space);
        if self.action_dim != width {
            return Err(PolicyMismatch::ActionWidth {
                policy_id,
                action_dim: self.action_dim,
                action_space: self.action_space.clone(),
                width,
            });
        }
        if self.n_obs_steps == 0 || self.horizon < self.n_obs_steps || self.n_action_steps == 0 {
            return Err(PolicyMismatch::NoAction {
                policy_id,
                n_obs_steps: self.n_obs_steps,
                horizon: self.horizon,
                n_action_steps: self.n_action_steps,
            });
        }
        Ok(())
    }
}
