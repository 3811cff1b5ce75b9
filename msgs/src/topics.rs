//! The rig's contract in one place: every ROS 2 topic and service labrig uses, with its
//! message type and the delivery its publishers promise, and the shared-memory (iceoryx2)
//! service names of the camera frames.
//!
//! A [`Topic`] ties a name to its message type, so a node cannot subscribe to `/arm/state`
//! with the wrong type; its [`Delivery`] is the part of the QoS that peers must agree on
//! (reliability and durability). The history depth is each endpoint's own choice and is given
//! where the endpoint is made (`labrig_runtime::ros::Ros::publisher_on(&topics::ARM_STATE, 10)`).
//! Tools that learn topics at run time (`labrig topic echo`, the recorder) still take names.

use crate::rig::{
    ActionChunk, ArmCommand, EpisodeEvent, GripperCommand, GripperState, PolicyRequest, RobotState, Step, TeleopState,
};
use crate::rosgraph_msgs::Clock;
use crate::sensor_msgs::{CameraInfo, CompressedImage, JointState};
use crate::std_msgs::StringMsg;
use crate::std_srvs::Trigger;
use crate::tf2_msgs::TFMessage;
use std::marker::PhantomData;

/// What a topic's publishers promise and its subscribers ask for (ROS 2 reliability and
/// durability; the history depth is chosen per endpoint).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Delivery {
    /// Reliable, volatile: every message to every subscriber present when it is sent.
    Reliable,
    /// Reliable, transient local: late joiners get the last messages (status, scene, tf_static).
    Latched,
    /// Best effort, volatile: the newest value matters, a lost one does not.
    BestEffort,
}

/// A ROS 2 topic of message type `T`.
#[derive(Debug)]
pub struct Topic<T> {
    /// The name without a namespace, e.g. `/arm/state`.
    pub name: &'static str,
    pub delivery: Delivery,
    _type: PhantomData<fn() -> T>,
}

impl<T> Topic<T> {
    pub const fn new(name: &'static str, delivery: Delivery) -> Topic<T> {
        Topic { name, delivery, _type: PhantomData }
    }

    /// The name under a prefix (`/sim` + `/arm/state` -> `/sim/arm/state`); an empty prefix
    /// gives the name itself.
    pub fn at(&self, prefix: &str) -> String {
        format!("{}{}", prefix.trim_end_matches('/'), self.name)
    }
}

/// A ROS 2 service of type `S`.
#[derive(Debug)]
pub struct Service<S> {
    pub name: &'static str,
    _type: PhantomData<fn() -> S>,
}

impl<S> Service<S> {
    pub const fn new(name: &'static str) -> Service<S> {
        Service { name, _type: PhantomData }
    }
}

use Delivery::{Latched, Reliable};

// --- the arm (franka node, or the sim bridge standing in for it) ---
/// Arm commands: from the rig loop (joint positions) or a tool, through the safety layer.
pub const ARM_COMMAND: Topic<ArmCommand> = Topic::new("/arm/command", Reliable);
/// The arm's state in DROID's robot_state keys, with its mode and fault.
pub const ARM_STATE: Topic<RobotState> = Topic::new("/arm/state", Reliable);
/// The joint target the franka node last sent to the arm.
pub const ARM_TARGET: Topic<JointState> = Topic::new("/arm/target", Reliable);
/// Clears a reflex and restarts the arm's control.
pub const ARM_RECOVER: Service<Trigger> = Service::new("/arm/recover");
/// The FR3's seven joints and the 2F-85's driver, standard type.
pub const JOINT_STATES: Topic<JointState> = Topic::new("/joint_states", Reliable);
pub const TF: Topic<TFMessage> = Topic::new("/tf", Reliable);
pub const TF_STATIC: Topic<TFMessage> = Topic::new("/tf_static", Latched);

// --- the gripper ---
pub const GRIPPER_COMMAND: Topic<GripperCommand> = Topic::new("/gripper/command", Reliable);
pub const GRIPPER_STATE: Topic<GripperState> = Topic::new("/gripper/state", Reliable);
pub const GRIPPER_ACTIVATE: Service<Trigger> = Service::new("/gripper/activate");

// --- the rig loop and the recorder ---
/// One Step record per control tick. Latched: the loop keeps the last ten seconds, so a
/// restarted recorder gets the steps it missed (volatile subscribers match it too).
pub const RIG_STEP: Topic<Step> = Topic::new("/rig/step", Latched);
/// Episode events as the loop decided them (start, success, failure, discard, reset).
/// Latched: a restarted recorder learns what happened while it was down.
pub const RIG_EPISODE: Topic<EpisodeEvent> = Topic::new("/rig/episode", Latched);
/// Operator requests to the loop (`labrig episode ...`, the Quest's A/B buttons).
pub const RIG_REQUEST: Topic<EpisodeEvent> = Topic::new("/rig/request", Reliable);
/// The operator's session (JSON, [`crate::session::Session`]: operator, lab, building, scene
/// id, task), latched: the operator station sets it; the loop and the recorder put it into
/// each episode.
pub const RIG_SESSION: Topic<StringMsg> = Topic::new("/rig/session", Latched);
/// The operator station's status (JSON: its URL, requests served), latched, once a second
/// (the launcher's heartbeat for it).
pub const STATION_STATUS: Topic<StringMsg> = Topic::new("/station/status", Latched);
/// The loop's status (JSON), latched.
pub const CONTROL_STATUS: Topic<StringMsg> = Topic::new("/control/status", Latched);
/// The recorder's status (JSON), latched.
pub const RECORDER_STATUS: Topic<StringMsg> = Topic::new("/recorder/status", Latched);

// --- teleoperation ---
pub const TELEOP_STATE: Topic<TeleopState> = Topic::new("/teleop/state", Reliable);
/// Teleop actions (cartesian velocity + gripper), stamped with the controller reading's time.
pub const TELEOP_ACTION: Topic<ArmCommand> = Topic::new("/teleop/action", Reliable);

// --- the policy server ---
/// The rig loop's requests for an action chunk (its newest observations).
pub const POLICY_REQUEST: Topic<PolicyRequest> = Topic::new("/policy/request", Reliable);
/// The policy server's chunks, stamped with the newest observation's time (action `i` is
/// meant for that time + i control periods).
pub const POLICY_CHUNK: Topic<ActionChunk> = Topic::new("/policy/chunk", Reliable);
/// What the server serves (JSON: policy_id, cameras, image_size, n_obs_steps, horizon,
/// n_action_steps, action_space, action_dim), latched: the loop reads it before it sends a
/// request and refuses a policy it cannot feed or execute.
pub const POLICY_INFO: Topic<StringMsg> = Topic::new("/policy/info", Latched);
/// A request the server could not answer (JSON: request_id, policy_id, error naming why, e.g.
/// a camera's image missing): the asker learns it was refused, and why, instead of waiting
/// out its timeout for a chunk that will not come.
pub const POLICY_REFUSED: Topic<StringMsg> = Topic::new("/policy/refused", Reliable);

// --- the simulated rig ---
/// Sim time (rosgraph_msgs/Clock).
pub const CLOCK: Topic<Clock> = Topic::new("/clock", Reliable);
/// The scene's sampled values and spec (JSON), latched.
pub const SIM_SCENE: Topic<StringMsg> = Topic::new("/sim/scene", Latched);
/// The rig's camera calibrations in force (JSON: per camera its date, method, extrinsics),
/// latched; published by whoever loads them (the camera node, the sim bridge).
pub const CALIBRATION: Topic<StringMsg> = Topic::new("/calibration", Latched);
/// `{"seed": N}`: rebuild the scene.
pub const SIM_RESET: Topic<StringMsg> = Topic::new("/sim/reset", Reliable);
/// Faults the sim injects on request (JSON, e.g. `{"stall_camera": {"camera": "wrist",
/// "seconds": 1.0}}`): `labrig bench faults` and the fault suite.
pub const SIM_FAULT: Topic<StringMsg> = Topic::new("/sim/fault", Reliable);
/// The scripted expert's action for the current state.
pub const SIM_EXPERT_ACTION: Topic<ArmCommand> = Topic::new("/sim/expert/action", Reliable);
/// The scripted expert's progress (JSON: phase, done, success).
pub const SIM_EXPERT_STATUS: Topic<StringMsg> = Topic::new("/sim/expert/status", Reliable);
/// The task's success predicate judged on the physics after every step (JSON: stamp_ns,
/// seed, success), whatever moves the arm: how a rollout of a policy is judged in the sim.
pub const SIM_TASK: Topic<StringMsg> = Topic::new("/sim/task", Reliable);
/// The prefix the bridge serves the hardware topics under when the franka and gripper nodes'
/// `sim` backends stand in front of it.
pub const SIM_HARDWARE_PREFIX: &str = "/sim";

// --- cameras ---
/// `/cameras/<id>/camera_info`.
pub fn camera_info(camera: &str) -> String {
    format!("/cameras/{camera}/camera_info")
}
/// The type of [`camera_info`] topics.
pub const CAMERA_INFO_TYPE: &str = <CameraInfo as crate::RosMessage>::TYPE_NAME;
/// `/cameras/<id>/image/compressed`: the recorder's JPEG frames (in episodes and previews).
pub fn camera_image(camera: &str) -> String {
    format!("/cameras/{camera}/image/compressed")
}
/// The type of [`camera_image`] topics.
pub const CAMERA_IMAGE_TYPE: &str = <CompressedImage as crate::RosMessage>::TYPE_NAME;
/// `/cameras/<id>/preview/compressed`: the camera node's low-rate JPEG preview of each camera
/// (for rviz, Foxglove, rclpy; not recorded).
pub fn camera_preview(camera: &str) -> String {
    format!("/cameras/{camera}/preview/compressed")
}
/// The camera node's status (JSON: per camera its state, since when, why, frames, drops),
/// latched.
pub const CAMERAS_STATUS: Topic<StringMsg> = Topic::new("/cameras/status", Latched);
/// The prefix every camera topic starts with.
pub const CAMERAS_PREFIX: &str = "/cameras/";
/// The iceoryx2 publish-subscribe service of a camera's raw frames, `labrig/camera/<id>/frames`,
/// optionally inside a namespace (two rigs or two tests on one machine).
pub fn frame_service(namespace: Option<&str>, camera: &str) -> String {
    match namespace {
        Some(ns) => format!("labrig/{ns}/camera/{camera}/frames"),
        None => format!("labrig/camera/{camera}/frames"),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn prefixed_names() {
        assert_eq!(ARM_STATE.at(""), "/arm/state");
        assert_eq!(ARM_STATE.at("/sim"), "/sim/arm/state");
        assert_eq!(ARM_STATE.at("/sim/"), "/sim/arm/state");
        assert_eq!(camera_info("ext1"), "/cameras/ext1/camera_info");
        assert!(camera_image("wrist").starts_with(CAMERAS_PREFIX));
    }
}
