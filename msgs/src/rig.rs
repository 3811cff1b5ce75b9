//! The rig's own types: the ROS 2 package `labrig_msgs` (`labrig_msgs/msg/Step`, ...), as
//! `std_msgs` and `sensor_msgs` are the modules of theirs (here `labrig_msgs::rig`, not
//! `labrig_msgs::labrig_msgs`).
//!
//! Every type starts with a `uint16 version` field holding its schema version, checked on
//! decode: a file or peer of another schema gets an error naming the type and both versions
//! instead of silently misread fields. Bump a type's version (and keep a reader for the old one)
//! whenever its fields change.
//!
//! Each type's `.msg` text is the file of the ROS 2 interface package `ros2/labrig_msgs/msg/`
//! (included here, so the package, these types' schemas in every recording and the type
//! hashes cannot drift apart); `colcon build` of that package gives ROS 2 nodes the same types.
//!
//! Conventions (DROID's): gripper 0 = open, 1 = closed; cartesian positions are xyz (m) +
//! euler xyz (rad) in the robot base frame; cartesian velocity actions are in [-1, 1] and scale
//! to at most 0.075 m and 0.15 rad per control step.
use crate::geometry_msgs::Pose;
use crate::std_msgs::Header;
use crate::{Invalid, RosMessage};
use serde::{Deserialize, Serialize};

/// DROID's reset pose of the FR3 (rad): `[0, -pi/5, 0, -4pi/5, 0, 3pi/5, 0]`.
pub const DROID_RESET_POSE: [f64; 7] = [
    0.0,
    -std::f64::consts::PI / 5.0,
    0.0,
    -4.0 * std::f64::consts::PI / 5.0,
    0.0,
    3.0 * std::f64::consts::PI / 5.0,
    0.0,
];

/// The rig's five cameras, named like the real ones: two ZED 2 on the platform (left images),
/// the wrist ZED Mini, two RealSense D435. Camera ids on the wire and in recordings.
pub const RIG_CAMERAS: [&str; 5] = ["ext1", "ext2", "wrist", "rs1", "rs2"];

/// The schema version every `labrig_msgs` type carries in its `version` field.
pub const SCHEMA_VERSION: u16 = 1;

/// The `version` field of every labrig type: a `uint16` on the wire, [`SCHEMA_VERSION`] by default.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(transparent)]
pub struct SchemaVersion(pub u16);

impl Default for SchemaVersion {
    fn default() -> Self {
        SchemaVersion(SCHEMA_VERSION)
    }
}

macro_rules! versioned {
    ($($ty:ty),* $(,)?) => {$(
        impl $ty {
            /// Checks the schema version; called by [`crate::decode`] through `validate`.
            fn check_version(&self) -> Result<(), Invalid> {
                if self.version.0 == SCHEMA_VERSION {
                    Ok(())
                } else {
                    Err(Invalid::new("version", format!(
                        "schema version {} is not supported (this build reads version {SCHEMA_VERSION})",
                        self.version.0
                    )))
                }
            }
        }
    )*};
}

/// Implements RosMessage for a labrig type with the version check as its validation.
macro_rules! labrig_message {
    ($ty:ty, $name:literal, [$($dep:ty),* $(,)?], $text:expr, legacy = $old:ty) => {
        labrig_message!(@impl $ty, $name, [$($dep),*], $text,
            fn decode_legacy(id: [u8; 2], body: &[u8]) -> Option<Result<(Self, usize), cdr_encoding::Error>> {
                Some(crate::codec::from_cdr::<$old>(id, body).map(|(m, used)| (Self::from(m), used)))
            }
        );
    };
    ($ty:ty, $name:literal, [$($dep:ty),* $(,)?], $text:expr) => {
        labrig_message!(@impl $ty, $name, [$($dep),*], $text,);
    };
    (@impl $ty:ty, $name:literal, [$($dep:ty),* $(,)?], $text:expr, $($legacy:item)?) => {
        impl RosMessage for $ty {
            $($legacy)?
            const TYPE_NAME: &'static str = $name;
            const MSG_TEXT: &'static str = $text;
            #[allow(unused_variables)]
            fn dependencies(out: &mut Vec<(&'static str, &'static str)>) {
                $(
                    out.push((<$dep as RosMessage>::TYPE_NAME, <$dep as RosMessage>::MSG_TEXT));
                    <$dep as RosMessage>::dependencies(out);
                )*
            }
            fn validate(&self) -> Result<(), Invalid> {
                self.check_version()?;
                self.check_fields()
            }
        }
    };
}

/// Which representation of the action an [`ArmCommand`] carries.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
#[repr(u8)]
pub enum ArmCommandMode {
    /// `cartesian_velocity` in [-1, 1] (DROID's recorded action space).
    CartesianVelocity = 0,
    /// `cartesian_position`: xyz + euler xyz target (DROID's cartesian_position).
    CartesianPosition = 1,
    /// `cartesian_position`: xyz + axis-angle target (the paper's action space).
    CartesianPositionAxisAngle = 2,
    /// `joint_velocity` in rad/s.
    JointVelocity = 3,
    /// `joint_position` target in rad (what IK produces for the arm).
    JointPosition = 4,
}

impl TryFrom<u8> for ArmCommandMode {
    type Error = Invalid;
    fn try_from(v: u8) -> Result<Self, Invalid> {
        Ok(match v {
            0 => Self::CartesianVelocity,
            1 => Self::CartesianPosition,
            2 => Self::CartesianPositionAxisAngle,
            3 => Self::JointVelocity,
            4 => Self::JointPosition,
            other => return Err(Invalid::new("mode", format!("unknown arm command mode {other} (expected 0..=4)"))),
        })
    }
}

/// labrig_msgs/msg/ArmCommand on `/arm/command`: one action for the arm and the gripper.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct ArmCommand {
    pub version: SchemaVersion,
    pub header: Header,
    /// An [`ArmCommandMode`] value.
    pub mode: u8,
    pub cartesian_velocity: [f64; 6],
    pub cartesian_position: [f64; 6],
    pub joint_velocity: [f64; 7],
    pub joint_position: [f64; 7],
    /// Gripper target, 0 = open .. 1 = closed.
    pub gripper_position: f64,
    /// Monotonic command counter, so the arm node can tell repeats from fresh commands.
    pub seq: u64,
}
impl ArmCommand {
    pub fn mode(&self) -> Result<ArmCommandMode, Invalid> {
        ArmCommandMode::try_from(self.mode)
    }
    fn check_fields(&self) -> Result<(), Invalid> {
        self.mode().map(|_| ())
    }
}
labrig_message!(
    ArmCommand,
    "labrig_msgs/msg/ArmCommand",
    [Header],
    include_str!("../../ros2/labrig_msgs/msg/ArmCommand.msg")
);

/// labrig_msgs/msg/ActionDict: DROID's recorded action dictionary, every representation of
/// the action taken at one step.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct ActionDict {
    pub version: SchemaVersion,
    pub cartesian_velocity: [f64; 6],
    pub cartesian_position: [f64; 6],
    pub joint_velocity: [f64; 7],
    pub joint_position: [f64; 7],
    pub gripper_velocity: f64,
    pub gripper_position: f64,
    pub target_cartesian_position: [f64; 6],
    pub target_gripper_position: f64,
}
impl ActionDict {
    fn check_fields(&self) -> Result<(), Invalid> {
        Ok(())
    }
}
labrig_message!(
    ActionDict,
    "labrig_msgs/msg/ActionDict",
    [],
    include_str!("../../ros2/labrig_msgs/msg/ActionDict.msg")
);

/// labrig_msgs/msg/RobotState on `/arm/state`: DROID's `observation/robot_state` fields plus
/// the arm's mode and fault text.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct RobotState {
    pub version: SchemaVersion,
    pub header: Header,
    pub cartesian_position: [f64; 6],
    pub gripper_position: f64,
    pub joint_positions: [f64; 7],
    pub joint_velocities: [f64; 7],
    pub joint_torques_computed: [f64; 7],
    pub prev_joint_torques_computed: [f64; 7],
    pub prev_joint_torques_computed_safened: [f64; 7],
    pub motor_torques_measured: [f64; 7],
    pub prev_controller_latency_ms: f64,
    pub prev_command_successful: bool,
    /// One of the `MODE_*` constants.
    pub mode: u8,
    /// Empty unless `mode` is `MODE_FAULT` or `MODE_STOPPED`: what happened, for the operator.
    pub fault: String,
}
impl RobotState {
    pub const MODE_IDLE: u8 = 0;
    pub const MODE_MOVING: u8 = 1;
    pub const MODE_STOPPED: u8 = 2;
    pub const MODE_FAULT: u8 = 3;
    fn check_fields(&self) -> Result<(), Invalid> {
        if self.mode > Self::MODE_FAULT {
            return Err(Invalid::new("mode", format!("unknown robot mode {}", self.mode)));
        }
        Ok(())
    }
}
labrig_message!(
    RobotState,
    "labrig_msgs/msg/RobotState",
    [Header],
    include_str!("../../ros2/labrig_msgs/msg/RobotState.msg")
);

/// labrig_msgs/msg/GripperCommand on `/gripper/command`: all fields in 0..1.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct GripperCommand {
    pub version: SchemaVersion,
    pub header: Header,
    /// 0 = open .. 1 = closed (the 2F-85's rPR 0..255).
    pub position: f64,
    pub speed: f64,
    pub force: f64,
}
impl GripperCommand {
    fn check_fields(&self) -> Result<(), Invalid> {
        Ok(())
    }
}
labrig_message!(
    GripperCommand,
    "labrig_msgs/msg/GripperCommand",
    [Header],
    include_str!("../../ros2/labrig_msgs/msg/GripperCommand.msg")
);

/// labrig_msgs/msg/GripperState on `/gripper/state`.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct GripperState {
    pub version: SchemaVersion,
    pub header: Header,
    /// Measured opening, 0 = open .. 1 = closed.
    pub position: f64,
    /// The last commanded position echoed back.
    pub requested_position: f64,
    pub activated: bool,
    pub object_detected: bool,
    /// The 2F-85's gFLT code; 0 = no fault.
    pub fault_code: u8,
    pub fault: String,
    pub current_ma: f64,
}
impl GripperState {
    fn check_fields(&self) -> Result<(), Invalid> {
        Ok(())
    }
}
labrig_message!(
    GripperState,
    "labrig_msgs/msg/GripperState",
    [Header],
    include_str!("../../ros2/labrig_msgs/msg/GripperState.msg")
);

/// labrig_msgs/msg/TeleopState on `/teleop/state`: the controller as the teleop node sees it.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct TeleopState {
    pub version: SchemaVersion,
    pub header: Header,
    pub controller_connected: bool,
    /// `"right"` or `"left"`.
    pub hand: String,
    /// Controller pose in the robot frame (after the forward redefinition).
    pub controller_pose: Pose,
    /// Grip held: the deadman; the arm may move only while true.
    pub movement_enabled: bool,
    pub grip: f64,
    pub trigger: f64,
    pub joystick: [f64; 2],
    pub joystick_pressed: bool,
    pub button_success: bool,
    pub button_failure: bool,
}
impl TeleopState {
    fn check_fields(&self) -> Result<(), Invalid> {
        Ok(())
    }
}
labrig_message!(
    TeleopState,
    "labrig_msgs/msg/TeleopState",
    [Header, Pose],
    include_str!("../../ros2/labrig_msgs/msg/TeleopState.msg")
);

/// What an [`EpisodeEvent`] announces.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
#[repr(u8)]
pub enum EpisodeEventKind {
    Start = 0,
    Stop = 1,
    Success = 2,
    Failure = 3,
    Discard = 4,
    Reset = 5,
}

impl TryFrom<u8> for EpisodeEventKind {
    type Error = Invalid;
    fn try_from(v: u8) -> Result<Self, Invalid> {
        Ok(match v {
            0 => Self::Start,
            1 => Self::Stop,
            2 => Self::Success,
            3 => Self::Failure,
            4 => Self::Discard,
            5 => Self::Reset,
            other => return Err(Invalid::new("kind", format!("unknown episode event kind {other} (expected 0..=5)"))),
        })
    }
}

/// labrig_msgs/msg/EpisodeEvent on `/episode/events`.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct EpisodeEvent {
    pub version: SchemaVersion,
    pub header: Header,
    /// An [`EpisodeEventKind`] value.
    pub kind: u8,
    pub episode_id: String,
    pub note: String,
}
impl EpisodeEvent {
    pub fn kind(&self) -> Result<EpisodeEventKind, Invalid> {
        EpisodeEventKind::try_from(self.kind)
    }
    fn check_fields(&self) -> Result<(), Invalid> {
        self.kind().map(|_| ())
    }
}
labrig_message!(
    EpisodeEvent,
    "labrig_msgs/msg/EpisodeEvent",
    [Header],
    include_str!("../../ros2/labrig_msgs/msg/EpisodeEvent.msg")
);

/// labrig_msgs/msg/ActionChunk: a policy's prediction, `horizon` actions of `action_dim` each,
/// row-major in `actions`; the first is meant for the control tick `first_step`, and row `i`
/// for the time `times_ns[i]` (the observation's time plus `i` control periods): a loop skips
/// the rows whose time has passed when the chunk arrives. `request_id` names the request it
/// answers (the chunk's id in the loop's records).
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct ActionChunk {
    pub version: SchemaVersion,
    pub header: Header,
    pub policy_id: String,
    /// The step index of the newest observation the chunk was computed from.
    pub observation_step: u64,
    pub first_step: u64,
    pub horizon: u32,
    pub action_dim: u32,
    pub actions: Vec<f64>,
    pub inference_ms: f64,
    pub request_id: u64,
    /// When each row is meant to be executed (ns on the loop's clock).
    pub times_ns: Vec<i64>,
}
impl ActionChunk {
    fn check_fields(&self) -> Result<(), Invalid> {
        if self.times_ns.len() != self.horizon as usize {
            return Err(Invalid::new(
                "times_ns",
                format!("{} action times for horizon {}", self.times_ns.len(), self.horizon),
            ));
        }
        let expected = self.horizon as usize * self.action_dim as usize;
        if self.actions.len() != expected {
            return Err(Invalid::new(
                "actions",
                format!(
                    "{} action values for horizon {} x action_dim {} (expected {expected})",
                    self.actions.len(),
                    self.horizon,
                    self.action_dim
                ),
            ));
        }
        Ok(())
    }
    /// The action for row `i` of the chunk.
    pub fn action(&self, i: usize) -> Option<&[f64]> {
        let d = self.action_dim as usize;
        self.actions.get(i * d..(i + 1) * d)
    }
}
labrig_message!(
    ActionChunk,
    "labrig_msgs/msg/ActionChunk",
    [Header],
    include_str!("../../ros2/labrig_msgs/msg/ActionChunk.msg")
);

/// labrig_msgs/msg/PolicyObservation: one control step as a policy sees it: the step's robot
/// state and the JPEG frames (as recorded) of the cameras the policy names, each with its
/// camera id in `header.frame_id`.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct PolicyObservation {
    pub version: SchemaVersion,
    /// The tick's time.
    pub header: Header,
    pub step_index: u64,
    pub robot_state: RobotState,
    pub images: Vec<crate::sensor_msgs::CompressedImage>,
}
impl PolicyObservation {
    fn check_fields(&self) -> Result<(), Invalid> {
        self.robot_state.validate()
    }
}
labrig_message!(
    PolicyObservation,
    "labrig_msgs/msg/PolicyObservation",
    [Header, RobotState, crate::sensor_msgs::CompressedImage],
    include_str!("../../ros2/labrig_msgs/msg/PolicyObservation.msg")
);

/// labrig_msgs/msg/PolicyRequest: the rig loop asking the policy server for an action chunk
/// from its most recent observations (oldest first, as many as the policy observes); `scene`
/// is the sim scene's JSON where a policy conditions on it (empty on a real rig). `seed`
/// seeds the diffusion's initial noise with the newest step (the sim scene's seed, so
/// lockstep rollouts repeat; on a real rig one drawn per episode); `period_ns` is the loop's
/// control period, which spaces the chunk's action times.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct PolicyRequest {
    pub version: SchemaVersion,
    pub header: Header,
    pub request_id: u64,
    pub episode_id: String,
    pub scene: String,
    pub observations: Vec<PolicyObservation>,
    pub seed: u64,
    pub period_ns: i64,
    /// Real-time chunking: the rows of the chunk the loop is executing, from the newest
    /// observation's tick on (row-major, the policy's action width), in the robot's units.
    /// Empty: no guidance asked for.
    pub prefix_actions: Vec<f64>,
    /// Of those rows, how many the loop executes before the new chunk can start (the inference
    /// delay in ticks, `d`): the new chunk's first `d` rows are these, exactly.
    pub prefix_frozen_steps: u32,
    /// The largest weight of the guidance toward the prefix (the RTC paper's beta; 0: none,
    /// the rows are frozen only).
    pub guidance_max_weight: f64,
}
impl PolicyRequest {
    fn check_fields(&self) -> Result<(), Invalid> {
        if self.observations.is_empty() {
            return Err(Invalid::new("observations", "a request without observations"));
        }
        if self.period_ns <= 0 {
            return Err(Invalid::new("period_ns", format!("period_ns = {} must be > 0", self.period_ns)));
        }
        if let Some(v) = self.prefix_actions.iter().find(|v| !v.is_finite()) {
            return Err(Invalid::new("prefix_actions", format!("a prefix action of {v}")));
        }
        if !(self.guidance_max_weight.is_finite() && self.guidance_max_weight >= 0.0) {
            return Err(Invalid::new(
                "guidance_max_weight",
                format!("guidance_max_weight = {} must be >= 0", self.guidance_max_weight),
            ));
        }
        self.observations.iter().try_for_each(|o| o.validate())
    }
}
/// A real-time chunking setting a policy's chunks cannot hold (the RTC paper's bounds).
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum RtcBoundsError {
    #[error(
        "real-time chunking: the inference delay d = {d} ticks is not shorter than the policy's chunk ({rows} rows from the observation on); nothing of a new chunk would be left to run"
    )]
    DelayBeyondChunk { d: u32, rows: u32 },
    #[error(
        "real-time chunking: the execution horizon s = {s} (policy.execute_steps, or the policy's n_action_steps) must lie in [d, rows - d] = [{d}, {}] for d = {d} ticks of delay and a chunk of {rows} rows",
        rows.saturating_sub(*d)
    )]
    Horizon { s: u32, d: u32, rows: u32 },
}

/// Real-time chunking's bounds, d <= s <= H - d: `d` the delay in ticks (the rows a request's
/// `prefix_frozen_steps` freezes), `s` the rows executed per chunk, `rows` (H) a chunk's rows
/// from the observation on. One request at a time is in flight, so a chunk runs at least d
/// rows (s >= d), and those must be there after the d it arrives late (s <= H - d).
pub fn rtc_bounds(d: u32, s: u32, rows: u32) -> Result<(), RtcBoundsError> {
    if d >= rows {
        return Err(RtcBoundsError::DelayBeyondChunk { d, rows });
    }
    if s < d || s > rows - d {
        return Err(RtcBoundsError::Horizon { s, d, rows });
    }
    Ok(())
}

labrig_message!(
    PolicyRequest,
    "labrig_msgs/msg/PolicyRequest",
    [Header, PolicyObservation],
    include_str!("../../ros2/labrig_msgs/msg/PolicyRequest.msg")
);

/// labrig_msgs/msg/CameraFrameRef: which frame of one camera went into an observation.
#[derive(Debug, Clone, PartialEq, Eq, Default, Serialize, Deserialize)]
pub struct CameraFrameRef {
    pub version: SchemaVersion,
    pub camera_id: String,
    pub sequence: u64,
    /// Hardware capture time (or the arrival time where a camera has none), ns.
    pub capture_ns: i64,
    pub arrival_ns: i64,
}
impl CameraFrameRef {
    fn check_fields(&self) -> Result<(), Invalid> {
        Ok(())
    }
}
labrig_message!(
    CameraFrameRef,
    "labrig_msgs/msg/CameraFrameRef",
    [],
    include_str!("../../ros2/labrig_msgs/msg/CameraFrameRef.msg")
);

/// labrig_msgs/msg/ControlTiming: DROID's `observation/timestamp/control` keys, ns.
#[derive(Debug, Clone, PartialEq, Eq, Default, Serialize, Deserialize)]
pub struct ControlTiming {
    pub version: SchemaVersion,
    pub step_start: i64,
    pub policy_start: i64,
    pub sleep_start: i64,
    pub control_start: i64,
    pub step_end: i64,
}
impl ControlTiming {
    fn check_fields(&self) -> Result<(), Invalid> {
        Ok(())
    }
}
labrig_message!(
    ControlTiming,
    "labrig_msgs/msg/ControlTiming",
    [],
    include_str!("../../ros2/labrig_msgs/msg/ControlTiming.msg")
);

/// labrig_msgs/msg/Step on `/rig/step`: one record per control tick — the observation used,
/// the action taken (DROID's keys) and the tick's timing.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct Step {
    pub version: SchemaVersion,
    pub header: Header,
    pub episode_id: String,
    pub step_index: u64,
    pub robot_state: RobotState,
    pub cameras: Vec<CameraFrameRef>,
    /// Largest minus smallest `capture_ns` among `cameras`.
    pub camera_skew_ns: i64,
    pub timing: ControlTiming,
    pub action: ActionDict,
    /// One of the `SOURCE_*` constants.
    pub action_source: u8,
    pub movement_enabled: bool,
    /// A policy's action: the checkpoint's id (`<dir>@<step>`), else empty.
    pub policy_id: String,
    /// A policy's action: the chunk it came from (the request id that chunk answers), else 0.
    pub chunk_id: u64,
    /// A policy's action: its row in that chunk.
    pub chunk_row: u32,
}

/// Step as recorded before the policy fields: what episodes recorded then hold, decoded by
/// [`Step`]'s legacy path with the policy fields empty.
#[derive(Deserialize)]
#[cfg_attr(test, derive(Serialize, Clone))]
struct StepV1 {
    version: SchemaVersion,
    header: Header,
    episode_id: String,
    step_index: u64,
    robot_state: RobotState,
    cameras: Vec<CameraFrameRef>,
    camera_skew_ns: i64,
    timing: ControlTiming,
    action: ActionDict,
    action_source: u8,
    movement_enabled: bool,
}

impl From<StepV1> for Step {
    fn from(o: StepV1) -> Step {
        Step {
            version: o.version,
            header: o.header,
            episode_id: o.episode_id,
            step_index: o.step_index,
            robot_state: o.robot_state,
            cameras: o.cameras,
            camera_skew_ns: o.camera_skew_ns,
            timing: o.timing,
            action: o.action,
            action_source: o.action_source,
            movement_enabled: o.movement_enabled,
            policy_id: String::new(),
            chunk_id: 0,
            chunk_row: 0,
        }
    }
}

impl Step {
    pub const SOURCE_NONE: u8 = 0;
    pub const SOURCE_TELEOP: u8 = 1;
    pub const SOURCE_POLICY: u8 = 2;
    pub const SOURCE_SCRIPTED: u8 = 3;
    pub const SOURCE_REPLAY: u8 = 4;

    /// Whether a step with this action source is an operator's, not the policy's (nor an idle
    /// tick's): the Quest's teleop, the scripted expert, or a replay. The one rule the loop,
    /// the recorder, inspect, rollouts and the trainer use to tell an operator's correction
    /// from the policy's own steps.
    pub const fn is_operator(source: u8) -> bool {
        matches!(source, Self::SOURCE_TELEOP | Self::SOURCE_SCRIPTED | Self::SOURCE_REPLAY)
    }

    fn check_fields(&self) -> Result<(), Invalid> {
        if self.action_source > Self::SOURCE_REPLAY {
            return Err(Invalid::new("action_source", format!("unknown action source {}", self.action_source)));
        }
        self.robot_state.validate()?;
        self.timing.validate()?;
        self.action.validate()?;
        self.cameras.iter().try_for_each(|c| c.validate())
    }
}
labrig_message!(
    Step,
    "labrig_msgs/msg/Step",
    [Header, RobotState, CameraFrameRef, ControlTiming, ActionDict],
    include_str!("../../ros2/labrig_msgs/msg/Step.msg"),
    legacy = StepV1
);

versioned!(
    ArmCommand,
    ActionDict,
    RobotState,
    GripperCommand,
    GripperState,
    TeleopState,
    EpisodeEvent,
    ActionChunk,
    PolicyObservation,
    PolicyRequest,
    CameraFrameRef,
    ControlTiming,
    Step,
);

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn steps_recorded_before_the_policy_fields_still_decode() {
        let old = StepV1 {
            version: SchemaVersion::default(),
            header: Header::default(),
            episode_id: "LAB+op+2026-11-01-10h-00m-00s".into(),
            step_index: 7,
            robot_state: RobotState::default(),
            cameras: vec![CameraFrameRef { camera_id: "ext1".into(), sequence: 3, ..Default::default() }],
            camera_skew_ns: 5,
            timing: ControlTiming::default(),
            action: ActionDict::default(),
            action_source: Step::SOURCE_SCRIPTED,
            movement_enabled: true,
        };
        let mut bytes = crate::codec::CDR_LE.to_vec();
        bytes.extend([0, 0]);
        bytes.extend(cdr_encoding::to_vec::<_, byteorder::LittleEndian>(&old).unwrap());
        let step: Step = crate::decode(&bytes).unwrap();
        assert_eq!(step, Step::from(old.clone()));
        assert_eq!((step.step_index, step.cameras[0].sequence, step.chunk_id), (7, 3, 0));
        // The current layout round-trips with its own fields.
        let new = Step { policy_id: "run@600".into(), chunk_id: 4, chunk_row: 2, ..Step::from(old) };
        assert_eq!(crate::decode::<Step>(&crate::encode(&new).unwrap()).unwrap(), new);
        // A body that fits neither layout is still refused.
        assert!(crate::decode::<Step>(&bytes[..bytes.len() - 12]).is_err());
    }
}
