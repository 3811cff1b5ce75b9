//! What the loop reports: a finished episode, a run's summary, the figures in them, and
//! DROID's per-step action dictionary and episode uuid.

use labrig_arm::ik::{delta_to_velocity, pose_error, xyz_euler};
use labrig_arm::{Fr3Kinematics, Joints};
use labrig_msgs::rig::{ActionDict, ArmCommand, ArmCommandMode, GripperState, RobotState};
use serde::Serialize;

/// DROID's `max_gripper_delta`: a full-scale gripper velocity moves it this far per step.
pub const MAX_GRIPPER_DELTA: f64 = 0.25;
/// DROID's per-joint `max_joint_delta` (rad per step at full-scale joint velocity).
pub const MAX_JOINT_DELTA: f64 = 0.2;

/// One finished episode, as the loop saw it.
#[derive(Debug, Clone, Serialize)]
pub struct EpisodeReport {
    pub episode_id: String,
    pub seed: Option<u64>,
    pub instruction: String,
    pub outcome: String,
    pub steps: u64,
    /// A policy rollout's operator takeovers ([`crate::takeover`]) and the steps the operator
    /// acted (0 and 0 for other sources).
    pub takeovers: u64,
    pub operator_steps: u64,
}

/// What a run did.
#[derive(Debug, Clone, Default, Serialize)]
pub struct Summary {
    pub ticks: u64,
    pub episodes: Vec<EpisodeReport>,
    /// Ticks whose source action was refused (NaN, stale) or missing: the arm held.
    pub held_ticks: u64,
    pub refused: u64,
    /// Ticks that came more than 1.5 periods after the previous one.
    pub missed_ticks: u64,
    /// Wall-clock period deviation of consecutive ticks (us): p50, p99, max.
    pub jitter_us: [f64; 3],
    /// Recorded steps with a camera missing, or with a frame older than `stale_frame_s`.
    pub steps_missing_frames: u64,
    pub steps_stale_frames: u64,
    /// Camera skew per recorded step (us): p50, p99, max.
    pub skew_us: [f64; 3],
    /// Episode starts held back because the recorder took no episode (a full disk).
    pub starts_refused: u64,
    /// Policy rollouts: operator takeovers and the steps operators acted, over all episodes.
    pub takeovers: u64,
    pub operator_steps: u64,
    /// Episodes stopped because the arm node reported a fault.
    pub arm_faults: u64,
    /// On the sim's clock, ticks started by the sim's `/clock` (the rest by the arm's state).
    pub clock_ticks: u64,
    /// What the action source reported (the policy source: requests, chunks, skipped rows,
    /// round trips).
    pub source: Option<serde_json::Value>,
    /// How late ticks began after their boundary (us): p50, p99, max. On the wall clock, from
    /// the scheduled instant; on the sim's clock, from the sim's `/clock` message of the
    /// boundary (sent the moment its step is done). The same figure in both clock modes;
    /// `jitter_us` is the spread of tick-to-tick wall intervals, which on the sim's clock also
    /// holds the sim's own step-to-step variation.
    pub tick_lateness_us: [f64; 3],
    pub seconds: f64,
}

/// The spread of a run's durations (ns) in bounded memory however long the run: a histogram to
/// three significant digits (p50 and p99 within 0.1%, the max exact to that precision), up to
/// an hour.
#[derive(Debug, Clone)]
pub(crate) struct Spread(hdrhistogram::Histogram<u64>);

impl Default for Spread {
    fn default() -> Self {
        Spread(hdrhistogram::Histogram::new_with_bounds(1, 3_600_000_000_000, 3).expect("valid histogram bounds"))
    }
}

impl Spread {
    pub(crate) fn push(&mut self, ns: i64) {
        self.0.saturating_record(ns.max(1) as u64);
    }

    /// p50, p99 and max in us; NaN when empty.
    pub(crate) fn percentiles_us(&self) -> [f64; 3] {
        if self.0.is_empty() {
            return [f64::NAN; 3];
        }
        let at = |q: f64| self.0.value_at_quantile(q) as f64 / 1e3;
        [at(0.5), at(0.99), self.0.max() as f64 / 1e3]
    }
}

/// p50, p99 and max of `v` (ns) in us; NaN when empty.
pub(crate) fn percentiles_us(v: &mut [i64]) -> [f64; 3] {
    v.sort_unstable();
    let at = |q: f64| v.get(((v.len().max(1) - 1) as f64 * q).round() as usize).map_or(f64::NAN, |&x| x as f64 / 1e3);
    [at(0.5), at(0.99), at(1.0)]
}

/// DROID's uuid `<lab>+<user>+<YYYY-MM-DD-HHh-MMm-SSs>` (wall time); a second episode in the
/// same second gets `-2`, `-3`, ...
pub(crate) fn episode_uuid(lab: &str, user: &str, earlier: &[EpisodeReport]) -> String {
    let secs = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map_or(0, |d| d.as_secs() as i64);
    let base = format!("{lab}+{user}+{}", droid_timestamp(secs));
    let taken = |id: &str| earlier.iter().any(|e| e.episode_id == id);
    if !taken(&base) {
        return base;
    }
    (2..).map(|k| format!("{base}-{k}")).find(|id| !taken(id)).expect("unbounded")
}

/// `YYYY-MM-DD-HHh-MMm-SSs` in UTC for Unix seconds.
fn droid_timestamp(secs: i64) -> String {
    chrono::DateTime::from_timestamp(secs, 0).unwrap_or_default().format("%Y-%m-%d-%Hh-%Mm-%Ss").to_string()
}

/// DROID's action dictionary for one step: the checked joint targets and every other form of
/// the same action (target pose by FK, velocities as the normalised deltas DROID records).
pub(crate) fn action_dict(
    kin: &Fr3Kinematics,
    robot: &RobotState,
    gripper: Option<&GripperState>,
    wanted: &ArmCommand,
    joints: &Joints,
    gripper_target: f64,
) -> ActionDict {
    let here = kin.tcp_pose(&robot.joint_positions);
    let target = kin.tcp_pose(joints);
    let (lin, rot) = pose_error(&here, &target);
    let joint_velocity =
        std::array::from_fn(|i| ((joints[i] - robot.joint_positions[i]) / MAX_JOINT_DELTA).clamp(-1.0, 1.0));
    let measured_gripper = gripper.map_or(robot.gripper_position, |g| g.position);
    let requested = if wanted.mode == ArmCommandMode::CartesianPosition as u8 {
        wanted.cartesian_position
    } else {
        xyz_euler(&target)
    };
    ActionDict {
        cartesian_velocity: delta_to_velocity(&lin, &rot),
        cartesian_position: xyz_euler(&target),
        joint_velocity,
        joint_position: *joints,
        gripper_velocity: ((gripper_target - measured_gripper) / MAX_GRIPPER_DELTA).clamp(-1.0, 1.0),
        gripper_position: gripper_target,
        target_cartesian_position: requested,
        target_gripper_position: wanted.gripper_position,
        ..Default::default()
    }
}

#[cfg(test)]
mod tests {
    #[test]
    fn a_spread_gives_the_percentiles_of_its_samples_in_bounded_memory() {
        let mut s = super::Spread::default();
        assert!(s.percentiles_us().iter().all(|v| v.is_nan()));
        let mut exact = Vec::new();
        for k in 1..=100_000i64 {
            // 1 us .. 100 ms.
            s.push(k * 1000);
            exact.push(k * 1000);
        }
        let (got, want) = (s.percentiles_us(), super::percentiles_us(&mut exact));
        for (g, w) in got.iter().zip(want) {
            assert!((g - w).abs() <= w * 1e-3, "{got:?} vs {want:?}");
        }
        let size = s.0.len();
        s.push(0);
        s.push(-5);
        s.push(i64::MAX);
        assert_eq!(s.0.len(), size + 3, "out-of-range samples are counted, clamped");
    }

    use super::*;

    #[test]
    fn droid_timestamps_are_utc_calendar_dates() {
        // 2023-07-07 09:42:23 UTC (DROID's own example episode).
        assert_eq!(droid_timestamp(1_688_722_943), "2023-07-07-09h-42m-23s");
        assert_eq!(droid_timestamp(0), "1970-01-01-00h-00m-00s");
        assert_eq!(droid_timestamp(951_782_400), "2000-02-29-00h-00m-00s");
    }

    #[test]
    fn episode_ids_in_the_same_second_differ() {
        let first = episode_uuid("LAB", "op", &[]);
        let report = |id: &str| EpisodeReport {
            episode_id: id.into(),
            seed: None,
            instruction: String::new(),
            outcome: "success".into(),
            steps: 1,
            takeovers: 0,
            operator_steps: 0,
        };
        let second = episode_uuid("LAB", "op", &[report(&first)]);
        assert_ne!(first, second);
        assert!(first.starts_with("LAB+op+20"));
    }
}
