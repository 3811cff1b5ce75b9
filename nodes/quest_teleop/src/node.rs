//! The teleop node: input lines -> readings -> DROID's VRPolicy against the arm's state ->
//!
//! - `/teleop/state` (TeleopState): the controller as seen (pose in the robot frame, deadman,
//!   grip, trigger, joystick, buttons, connected), per reading and every 100 ms without one;
//! - `/teleop/action` (ArmCommand, cartesian_velocity + gripper target, stamped with the
//!   reading's time): the rig loop's teleop source; the loop holds when it is older than its
//!   limit or the deadman is released;
//! - `/rig/request` (EpisodeEvent): A/X success, B/Y failure, on the press.
//!
//! Safety: no reading for `stale_s` (or no `/arm/state` for `max_state_age_s`) disables
//! motion (the origins are dropped: moving again takes the grip let go and pressed again); `controller_timeout_s` without one marks the controller gone;
//! a reading whose pose jumped more than `max_jump_m` / `max_jump_rad` from the last accepted
//! one is refused (a tracking glitch: skipped, nothing published); only `jump_confirm`
//! agreeing readings make the new place the reference, and then motion is disabled until the
//! grip is pressed again.

use crate::input::{InputConfig, InputEvent};
use crate::logcat::{LineStats, Reading};
use crate::policy::{PolicyConfig, RobotView, VrPolicy};
use labrig_msgs::Invalid;
use labrig_msgs::Nanos;
use labrig_msgs::geometry_msgs::{Point, Pose, Quaternion};
use labrig_msgs::labrig_msgs::{ArmCommand, ArmCommandMode, EpisodeEvent, EpisodeEventKind, RobotState, TeleopState};
use labrig_msgs::std_msgs::Header;
use labrig_msgs::topics;
use labrig_runtime::ros::{Ros, qos};
use labrig_runtime::{Clock, RosConfig, Shutdown};
use nalgebra::{Matrix4, Rotation3, UnitQuaternion};
use serde::Deserialize;
use std::time::{Duration, Instant};

/// The node's config (TOML; every key optional, unknown keys refused).
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct TeleopConfig {
    pub ros: RosConfig,
    pub input: InputConfig,
    pub policy: PolicyConfig,
    /// No reading for this long disables motion (s).
    pub stale_s: f64,
    /// No reading for this long: the controller is gone (s; DROID: 5).
    pub controller_timeout_s: f64,
    /// A pose that moved more than this since the last accepted reading is refused (m).
    pub max_jump_m: f64,
    /// ... or turned more than this (rad).
    pub max_jump_rad: f64,
    /// Readings agreeing with a jumped pose before it becomes the reference.
    pub jump_confirm: u32,
    /// The gripper target moves by at most this per action at gripper velocity 1.
    pub gripper_delta: f64,
    /// The arm's state the mapping closes its loop on.
    pub state_topic: String,
    /// An arm state older than this is not closed on: motion disabled (s).
    pub max_state_age_s: f64,
}

impl Default for TeleopConfig {
    fn default() -> Self {
        TeleopConfig {
            ros: RosConfig::default(),
            input: InputConfig::default(),
            policy: PolicyConfig::default(),
            stale_s: 0.05,
            controller_timeout_s: 5.0,
            max_jump_m: 0.05,
            max_jump_rad: 0.5,
            jump_confirm: 3,
            gripper_delta: 0.25,
            state_topic: topics::ARM_STATE.name.into(),
            max_state_age_s: 0.2,
        }
    }
}

impl TeleopConfig {
    pub fn validate(&self) -> Result<(), Invalid> {
        self.input.validate()?;
        self.policy.validate()?;
        for (k, v) in [
            ("stale_s", self.stale_s),
            ("controller_timeout_s", self.controller_timeout_s),
            ("max_jump_m", self.max_jump_m),
            ("max_jump_rad", self.max_jump_rad),
            ("gripper_delta", self.gripper_delta),
            ("max_state_age_s", self.max_state_age_s),
        ] {
            if !(v.is_finite() && v > 0.0) {
                return Err(Invalid::new(k, format!("{k}: {v} must be positive")));
            }
        }
        Ok(())
    }
}

/// What a run saw, printed and written at its end.
#[derive(Debug, Clone, Default, serde::Serialize)]
pub struct TeleopStats {
    pub lines: LineStats,
    pub actions: u64,
    pub jumps_refused: u64,
    pub stale_holds: u64,
    pub events: Vec<String>,
    /// Line read -> action published, microseconds.
    pub latency_us_p50: f64,
    pub latency_us_p99: f64,
    pub latency_us_max: f64,
    pub latency_n: usize,
}

fn pose_msg(m: &Matrix4<f64>) -> Pose {
    let q = UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix(&m.fixed_view::<3, 3>(0, 0).into_owned()));
    Pose {
        position: Point { x: m[(0, 3)], y: m[(1, 3)], z: m[(2, 3)] },
        orientation: Quaternion { x: q.i, y: q.j, z: q.k, w: q.w },
    }
}

/// The glitch guard: the last accepted pose and how many readings agree with a jump.
#[derive(Debug, Default)]
struct JumpGuard {
    reference: Option<Matrix4<f64>>,
    candidate: Option<(Matrix4<f64>, u32)>,
}

fn distance(a: &Matrix4<f64>, b: &Matrix4<f64>) -> (f64, f64) {
    let d = (a.fixed_view::<3, 1>(0, 3) - b.fixed_view::<3, 1>(0, 3)).norm();
    let ra = Rotation3::from_matrix(&a.fixed_view::<3, 3>(0, 0).into_owned());
    let rb = Rotation3::from_matrix(&b.fixed_view::<3, 3>(0, 0).into_owned());
    (d, ra.rotation_to(&rb).angle())
}

impl JumpGuard {
    /// Whether `pose` is accepted; `relocated` when a confirmed jump moved the reference.
    fn check(&mut self, pose: &Matrix4<f64>, cfg: &TeleopConfig) -> (bool, bool) {
        let Some(r) = self.reference else {
            self.reference = Some(*pose);
            return (true, false);
        };
        let (d, a) = distance(&r, pose);
        if d <= cfg.max_jump_m && a <= cfg.max_jump_rad {
            self.reference = Some(*pose);
            self.candidate = None;
            return (true, false);
        }
        let agree = self.candidate.is_some_and(|(c, _)| {
            let (d, a) = distance(&c, pose);
            d <= cfg.max_jump_m && a <= cfg.max_jump_rad
        });
        let n = if agree { self.candidate.map_or(1, |(_, n)| n + 1) } else { 1 };
        if n >= cfg.jump_confirm {
            self.reference = Some(*pose);
            self.candidate = None;
            return (false, true);
        }
        self.candidate = Some((*pose, n));
        (false, false)
    }
}

/// Runs the node until `shutdown` (or, with `input.exit_at_end`, a second after a playback ends).
pub async fn run(cfg: TeleopConfig, shutdown: Shutdown) -> anyhow::Result<TeleopStats> {
    let exit_at_end = cfg.input.exit_at_end;
    cfg.validate().map_err(|e| anyhow::anyhow!("teleop config: {e}"))?;
    let mut ros = Ros::new(&cfg.ros, "labrig_teleop")?;
    let state_pub = ros.publisher_on(&topics::TELEOP_STATE, 100)?;
    let action_pub = ros.publisher_on(&topics::TELEOP_ACTION, 100)?;
    let request_pub = ros.publisher_on(&topics::RIG_REQUEST, 10)?;
    let arm = ros.subscription::<RobotState>(&cfg.state_topic, qos::reliable(100))?;
    let (tx, mut rx) = tokio::sync::mpsc::unbounded_channel();
    let _input = crate::input::start(&cfg.input, tx, crate::policy::reorder_matrix(&cfg.policy.axis_reorder))?;
    let right = cfg.policy.hand == "right";
    let mut policy = VrPolicy::new(cfg.policy.clone());
    let mut stats = TeleopStats::default();
    let mut latencies: Vec<f64> = Vec::new();
    let mut robot: Option<(RobotView, Instant)> = None;
    let mut last_reading: Option<(Instant, Reading)> = None;
    let mut guard = JumpGuard::default();
    let mut prev_buttons = (false, false);
    let mut seq = 0u64;
    let mut ended_at: Option<Instant> = None;
    let mut input_open = true;
    let mut notes: std::collections::HashMap<String, Instant> = std::collections::HashMap::new();
    let mut disabled_published_at = Instant::now() - Duration::from_secs(1);
    let mut stale_announced = false;
    let mut warned_no_state = false;
    let hand_name = cfg.policy.hand.clone();
    let mut tick = tokio::time::interval(Duration::from_millis(10));
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    tracing::info!(input = ?cfg.input.kind, hand = %hand_name, "teleop up");

    let state_msg = |t: i64, connected: bool, enabled: bool, r: Option<&Reading>, controller: Option<&Matrix4<f64>>| {
        let h = r.map(|r| *r.hand(right)).unwrap_or_default();
        TeleopState {
            header: Header { stamp: Nanos(t).into(), frame_id: "base".into() },
            controller_connected: connected,
            hand: hand_name.clone(),
            controller_pose: controller.map(pose_msg).unwrap_or_default(),
            movement_enabled: enabled,
            grip: h.grip,
            trigger: h.trigger,
            joystick: h.joystick,
            joystick_pressed: h.joystick_pressed,
            button_success: h.success,
            button_failure: h.failure,
            ..TeleopState::default()
        }
    };

    loop {
        tokio::select! {
            _ = shutdown.wait() => break,
            ev = rx.recv(), if input_open => {
                let Some(ev) = ev else {
                    // The input thread is gone (playback done): keep publishing the stale state.
                    input_open = false;
                    ended_at.get_or_insert_with(Instant::now);
                    continue;
                };
                let (reading, read_at) = match ev {
                    InputEvent::Line { text, read_at } => match stats.lines.take(&text) {
                        None => continue,
                        Some(Err(e)) => { tracing::debug!("bad line: {e}"); continue; }
                        Some(Ok(r)) => (r, read_at),
                    },
                    InputEvent::Reading { reading, read_at } => {
                        stats.lines.readings += 1;
                        (*reading, read_at)
                    }
                    InputEvent::Note(n) => {
                        // adb retrying every second says the same things each time: each at
                        // most every 30 s.
                        let due = notes.get(&n).is_none_or(|at: &Instant| at.elapsed() > Duration::from_secs(30));
                        if due {
                            tracing::info!("input: {n}");
                            notes.insert(n, Instant::now());
                        }
                        continue;
                    }
                    InputEvent::End => { tracing::info!("input ended"); ended_at = Some(Instant::now()); continue; }
                    InputEvent::Quit => { tracing::info!("quit at the keyboard"); break; }
                };
                while let Some(s) = arm.try_take()? {
                    let view = RobotView { cartesian_position: s.msg.cartesian_position, gripper_position: s.msg.gripper_position };
                    robot = Some((view, Instant::now()));
                }
                let hand = *reading.hand(right);
                let Some(pose) = hand.pose else { continue };
                let t = Clock::Wall.now().0;
                // Episode events on the press, from either controller.
                let buttons = (reading.right.success || reading.left.success, reading.right.failure || reading.left.failure);
                for (pressed, was, kind, name) in [
                    (buttons.0, prev_buttons.0, EpisodeEventKind::Success, "success (A/X)"),
                    (buttons.1, prev_buttons.1, EpisodeEventKind::Failure, "failure (B/Y)"),
                ] {
                    if pressed && !was {
                        let ev = EpisodeEvent {
                            header: Header { stamp: Nanos(t).into(), frame_id: String::new() },
                            kind: kind as u8,
                            note: format!("teleop: {name}"),
                            ..EpisodeEvent::default()
                        };
                        request_pub.publish(ev)?;
                        stats.events.push(name.to_owned());
                    }
                }
                prev_buttons = buttons;
                let (accepted, relocated) = guard.check(&pose, &cfg);
                if !accepted {
                    stats.jumps_refused += 1;
                    if relocated {
                        // The controller is somewhere else for good: motion needs a new press.
                        tracing::warn!("the controller's pose moved for good: press the grip again to move");
                        policy.release();
                        state_pub.publish(state_msg(t, true, false, Some(&reading), None))?;
                    } else {
                        // A glitch: skipped, the origins kept (the next good reading goes on).
                        tracing::warn!("refused a controller pose that jumped (tracking glitch)");
                    }
                    continue;
                }
                last_reading = Some((read_at, reading));
                stale_announced = false;
                // The mapping closes its loop on the arm's state: without a fresh one the
                // action would chase an offset the arm may already have made up.
                let Some(rv) = robot.filter(|(_, at)| at.elapsed().as_secs_f64() <= cfg.max_state_age_s).map(|(v, _)| v) else {
                    if !warned_no_state {
                        tracing::warn!("no fresh {}: motion disabled until the arm's state arrives", cfg.state_topic);
                        warned_no_state = true;
                    }
                    policy.release();
                    state_pub.publish(state_msg(t, true, false, Some(&reading), None))?;
                    continue;
                };
                warned_no_state = false;
                let Some(a) = policy.step(&reading, &rv) else { continue };
                let gripper = (rv.gripper_position + a.velocity[6] * cfg.gripper_delta).clamp(0.0, 1.0);
                seq += 1;
                let cmd = ArmCommand {
                    header: Header { stamp: Nanos(t).into(), frame_id: "base".into() },
                    mode: ArmCommandMode::CartesianVelocity as u8,
                    cartesian_velocity: [a.velocity[0], a.velocity[1], a.velocity[2], a.velocity[3], a.velocity[4], a.velocity[5]],
                    gripper_position: if a.movement_enabled { gripper } else { rv.gripper_position },
                    seq,
                    ..ArmCommand::default()
                };
                state_pub.publish(state_msg(t, true, a.movement_enabled, Some(&reading), Some(&a.controller)))?;
                action_pub.publish(cmd)?;
                stats.actions += 1;
                latencies.push(read_at.elapsed().as_secs_f64() * 1e6);
            }
            _ = tick.tick() => {
                let age = last_reading.as_ref().map(|(at, _)| at.elapsed());
                let stale = age.is_none_or(|a| a.as_secs_f64() > cfg.stale_s);
                if stale {
                    let just_now = !stale_announced && age.is_some();
                    if just_now {
                        stale_announced = true;
                        stats.stale_holds += 1;
                        policy.release();
                        tracing::warn!("no controller reading for {:.0} ms: motion disabled", cfg.stale_s * 1e3);
                    }
                    // Disabled at once when it turned stale, then every 100 ms.
                    if just_now || disabled_published_at.elapsed() >= Duration::from_millis(100) {
                        let connected = age.is_some_and(|a| a.as_secs_f64() < cfg.controller_timeout_s);
                        state_pub.publish(state_msg(Clock::Wall.now().0, connected, false, last_reading.as_ref().map(|(_, r)| r), None))?;
                        disabled_published_at = Instant::now();
                    }
                }
                if exit_at_end && ended_at.is_some_and(|e| e.elapsed() > Duration::from_secs(1)) {
                    break;
                }
            }
        }
    }
    latencies.sort_by(f64::total_cmp);
    let pct = |p: f64| {
        if latencies.is_empty() { 0.0 } else { latencies[((latencies.len() - 1) as f64 * p).round() as usize] }
    };
    stats.latency_us_p50 = pct(0.5);
    stats.latency_us_p99 = pct(0.99);
    stats.latency_us_max = pct(1.0);
    stats.latency_n = latencies.len();
    tracing::info!(
        readings = stats.lines.readings,
        bad = stats.lines.bad,
        actions = stats.actions,
        jumps_refused = stats.jumps_refused,
        p50_us = stats.latency_us_p50,
        p99_us = stats.latency_us_p99,
        "teleop stopped"
    );
    Ok(stats)
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Vector3;

    #[test]
    fn a_jump_is_refused_and_only_a_confirmed_one_moves_the_reference() {
        let cfg = TeleopConfig::default();
        let mut g = JumpGuard::default();
        let at = |x: f64| Matrix4::new_translation(&Vector3::new(x, 0.0, 0.0));
        assert_eq!(g.check(&at(0.0), &cfg), (true, false));
        assert_eq!(g.check(&at(0.01), &cfg), (true, false));
        // One glitch, then back: the glitch is refused, the next is fine.
        assert_eq!(g.check(&at(0.5), &cfg), (false, false));
        assert_eq!(g.check(&at(0.02), &cfg), (true, false));
        // A real relocation: refused until three readings agree, then the new reference.
        assert_eq!(g.check(&at(1.0), &cfg), (false, false));
        assert_eq!(g.check(&at(1.0), &cfg), (false, false));
        assert_eq!(g.check(&at(1.01), &cfg), (false, true));
        assert_eq!(g.check(&at(1.02), &cfg), (true, false));
        // A turn counts too.
        let turned = at(1.02) * Matrix4::from(Rotation3::from_axis_angle(&Vector3::z_axis(), 1.0));
        assert_eq!(g.check(&turned, &cfg), (false, false));
    }

    #[test]
    fn the_launch_configs_teleop_files_load_and_pass() {
        let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../launch_configs/nodes");
        for name in ["teleop_quest.toml", "teleop_sim_trace.toml"] {
            let c: TeleopConfig = labrig_runtime::load_config(&dir.join(name)).unwrap();
            assert_eq!(c.validate(), Ok(()), "{name}");
        }
        let c: TeleopConfig = labrig_runtime::load_config(&dir.join("teleop_quest.toml")).unwrap();
        assert_eq!((c.stale_s, c.max_state_age_s), (0.05, 0.2));
    }

    #[test]
    fn config_is_validated_by_field() {
        let c = TeleopConfig { stale_s: 0.0, ..TeleopConfig::default() };
        assert!(c.validate().unwrap_err().to_string().contains("stale_s"));
        let mut c = TeleopConfig::default();
        c.input.kind = crate::input::InputKind::Playback;
        assert!(c.validate().unwrap_err().to_string().contains("input.file"));
    }
}
