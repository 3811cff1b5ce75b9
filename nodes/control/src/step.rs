//! One `labrig_msgs/Step` per tick: the observation the action was chosen from (robot state,
//! the camera frames used, their skew), the action in DROID's keys, and the tick's timing in
//! DROID's `observation/timestamp/control` keys.

use crate::frames::TickFrames;
use labrig_msgs::Nanos;
use labrig_msgs::rig::{ActionDict, ControlTiming, GripperState, RobotState, Step};
use labrig_msgs::std_msgs::Header;

/// Times of one tick (ns), in the order the loop takes them.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct TickTimes {
    /// The tick's scheduled time (the step's stamp).
    pub tick_ns: i64,
    pub step_start: i64,
    /// The action source was asked.
    pub policy_start: i64,
    /// Commands sent; the loop sleeps from here.
    pub sleep_start: i64,
    /// The commands were handed to the arm and gripper.
    pub control_start: i64,
    pub step_end: i64,
}

/// What a tick observed.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Observation {
    pub robot: RobotState,
    pub gripper: Option<GripperState>,
    pub frames: TickFrames,
}

/// What the action source chose.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Decision {
    pub action: ActionDict,
    /// A `Step::SOURCE_*` value.
    pub source: u8,
    /// The deadman (teleop grip) or the source's own go-ahead.
    pub movement_enabled: bool,
    /// A policy's action: which chunk and row it came from.
    pub chunk: Option<ChunkRef>,
}

/// Where a policy's action came from: the checkpoint, the chunk (the request id it answers)
/// and the row in it.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct ChunkRef {
    pub policy_id: String,
    pub chunk_id: u64,
    pub row: u32,
}

/// Assembles the Step of one tick. The gripper's measured position goes into the robot
/// state's `gripper_position` (DROID keeps it there).
pub fn make_step(episode_id: &str, step_index: u64, obs: &Observation, decision: &Decision, times: &TickTimes) -> Step {
    let mut robot = obs.robot.clone();
    if let Some(g) = &obs.gripper {
        robot.gripper_position = g.position;
    }
    Step {
        header: Header { stamp: Nanos(times.tick_ns).into(), frame_id: "base".into() },
        episode_id: episode_id.to_owned(),
        step_index,
        robot_state: robot,
        cameras: obs.frames.refs.clone(),
        camera_skew_ns: obs.frames.skew_ns,
        timing: ControlTiming {
            step_start: times.step_start,
            policy_start: times.policy_start,
            sleep_start: times.sleep_start,
            control_start: times.control_start,
            step_end: times.step_end,
            ..Default::default()
        },
        action: decision.action.clone(),
        action_source: decision.source,
        movement_enabled: decision.movement_enabled,
        policy_id: decision.chunk.as_ref().map(|c| c.policy_id.clone()).unwrap_or_default(),
        chunk_id: decision.chunk.as_ref().map_or(0, |c| c.chunk_id),
        chunk_row: decision.chunk.as_ref().map_or(0, |c| c.row),
        ..Default::default()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frames::{FrameBook, FrameTimes};

    #[test]
    fn a_step_carries_the_observation_action_and_timing() {
        let mut book = FrameBook::new(&["ext1", "wrist"]);
        book.push("ext1", FrameTimes { sequence: 7, capture_ns: 990, arrival_ns: 995 });
        book.push("wrist", FrameTimes { sequence: 9, capture_ns: 970, arrival_ns: 980 });
        let frames = book.at(Nanos(1_000), Nanos(50));
        let robot = RobotState { joint_positions: [0.1; 7], ..Default::default() };
        let gripper = GripperState { position: 0.4, ..Default::default() };
        let action = ActionDict { gripper_position: 1.0, ..Default::default() };
        let times = TickTimes {
            tick_ns: 1_000,
            step_start: 1_001,
            policy_start: 1_002,
            sleep_start: 1_003,
            control_start: 1_004,
            step_end: 1_005,
        };
        let obs = Observation { robot, gripper: Some(gripper), frames };
        let chunk = Some(ChunkRef { policy_id: "run@600".into(), chunk_id: 4, row: 2 });
        let decision = Decision { action, source: Step::SOURCE_POLICY, movement_enabled: true, chunk };
        let s = make_step("ep", 3, &obs, &decision, &times);
        assert_eq!((s.policy_id.as_str(), s.chunk_id, s.chunk_row), ("run@600", 4, 2));
        assert_eq!(s.step_index, 3);
        assert_eq!(s.robot_state.gripper_position, 0.4);
        assert_eq!(s.cameras.iter().map(|c| c.sequence).collect::<Vec<_>>(), vec![7, 9]);
        assert_eq!(s.camera_skew_ns, 20);
        assert_eq!((s.timing.step_start, s.timing.step_end), (1_001, 1_005));
        assert_eq!(Nanos::from(s.header.stamp).0, 1_000);
        assert_eq!(s.action.gripper_position, 1.0);
        // The record is valid on the wire.
        let bytes = labrig_msgs::encode(&s).unwrap();
        assert_eq!(labrig_msgs::decode::<Step>(&bytes).unwrap(), s);
    }
}
