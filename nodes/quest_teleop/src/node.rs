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
use labrig_msgs::rig::{ArmCommand, ArmCommandMode, EpisodeEvent, EpisodeEventKind, RobotState, TeleopState};
use labrig_msgs::std_msgs::Header;
use labrig_msgs::topics;
use labrig_runtime::ros::{Ros, RosPublisher, RosSubscription, qos};
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
    let mut node = Teleop::new(cfg, state_pub, action_pub, request_pub, arm);
    let mut input_open = true;
    let mut tick = tokio::time::interval(Duration::from_millis(10));
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    tracing::info!(input = ?node.cfg.input.kind, hand = %node.hand_name, "teleop up");
    loop {
        tokio::select! {
            _ = shutdown.wait() => break,
            ev = rx.recv(), if input_open => {
                let Some(ev) = ev else {
                    // The input thread is gone (playback done): keep publishing the stale state.
                    input_open = false;
                    node.ended_at.get_or_insert_with(Instant::now);
                    continue;
                };
                if let Flow::Quit = node.on_input(ev)? {
                    break;
                }
            }
            _ = tick.tick() => {
                node.on_tick()?;
                if exit_at_end && node.ended_at.is_some_and(|e| e.elapsed() > Duration::from_secs(1)) {
                    break;
                }
            }
        }
    }
    Ok(node.finish())
}

/// What the loop does after an input event.
enum Flow {
    Continue,
    /// Quit at the keyboard.
    Quit,
}

/// The running node: its endpoints, the mapping and the guards around it, and what it saw.
struct Teleop {
    cfg: TeleopConfig,
    state_pub: RosPublisher<TeleopState>,
    action_pub: RosPublisher<ArmCommand>,
    request_pub: RosPublisher<EpisodeEvent>,
    arm: RosSubscription<RobotState>,
    /// The right hand's controller drives (else the left).
    right: bool,
    hand_name: String,
    policy: VrPolicy,
    stats: TeleopStats,
    /// Line read -> action published, microseconds.
    latencies: Vec<f64>,
    /// The arm's newest state, and when it arrived.
    robot: Option<(RobotView, Instant)>,
    last_reading: Option<(Instant, Reading)>,
    guard: JumpGuard,
    /// The success and failure buttons as last read (events go out on the press).
    prev_buttons: (bool, bool),
    seq: u64,
    /// When the input ended (or its thread went).
    ended_at: Option<Instant>,
    /// When each input note was last logged.
    notes: std::collections::HashMap<String, Instant>,
    disabled_published_at: Instant,
    stale_announced: bool,
    warned_no_state: bool,
}

impl Teleop {
    fn new(
        cfg: TeleopConfig,
        state_pub: RosPublisher<TeleopState>,
        action_pub: RosPublisher<ArmCommand>,
        request_pub: RosPublisher<EpisodeEvent>,
        arm: RosSubscription<RobotState>,
    ) -> Teleop {
        Teleop {
            right: cfg.policy.hand == "right",
            policy: VrPolicy::new(cfg.policy.clone()),
            stats: TeleopStats::default(),
            latencies: Vec::new(),
            robot: None,
            last_reading: None,
            guard: JumpGuard::default(),
            prev_buttons: (false, false),
            seq: 0,
            ended_at: None,
            notes: std::collections::HashMap::new(),
            disabled_published_at: Instant::now() - Duration::from_secs(1),
            stale_announced: false,
            warned_no_state: false,
            hand_name: cfg.policy.hand.clone(),
            cfg,
            state_pub,
            action_pub,
            request_pub,
            arm,
        }
    }

    /// `/teleop/state` at `t`: the controller as read (`r`), its pose in the robot frame when
    /// known.
    fn state_msg(
        &self,
        t: i64,
        connected: bool,
        enabled: bool,
        r: Option<&Reading>,
        controller: Option<&Matrix4<f64>>,
    ) -> TeleopState {
        let h = r.map(|r| *r.hand(self.right)).unwrap_or_default();
        TeleopState {
            header: Header { stamp: Nanos(t).into(), frame_id: "base".into() },
            controller_connected: connected,
            hand: self.hand_name.clone(),
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
    }

    /// An input event: a reading mapped to an action, or a line, note or end taken note of.
    fn on_input(&mut self, ev: InputEvent) -> anyhow::Result<Flow> {
        let (reading, read_at) = match ev {
            InputEvent::Line { text, read_at } => match self.stats.lines.take(&text) {
                None => return Ok(Flow::Continue),
                Some(Err(e)) => {
                    tracing::debug!("bad line: {e}");
                    return Ok(Flow::Continue);
                }
                Some(Ok(r)) => (r, read_at),
            },
            InputEvent::Reading { reading, read_at } => {
                self.stats.lines.readings += 1;
                (*reading, read_at)
            }
            InputEvent::Note(n) => {
                self.note(n);
                return Ok(Flow::Continue);
            }
            InputEvent::End => {
                tracing::info!("input ended");
                self.ended_at = Some(Instant::now());
                return Ok(Flow::Continue);
            }
            InputEvent::Quit => {
                tracing::info!("quit at the keyboard");
                return Ok(Flow::Quit);
            }
        };
        self.on_reading(reading, read_at)?;
        Ok(Flow::Continue)
    }

    /// An input note, logged: adb retrying every second says the same things each time: each
    /// at most every 30 s.
    fn note(&mut self, n: String) {
        let due = self.notes.get(&n).is_none_or(|at: &Instant| at.elapsed() > Duration::from_secs(30));
        if due {
            tracing::info!("input: {n}");
            self.notes.insert(n, Instant::now());
        }
    }

    /// A controller reading (read at `read_at`): the buttons' events, the glitch guard, and
    /// against a fresh arm state the action and state published.
    fn on_reading(&mut self, reading: Reading, read_at: Instant) -> anyhow::Result<()> {
        self.take_arm_state()?;
        let hand = *reading.hand(self.right);
        let Some(pose) = hand.pose else { return Ok(()) };
        let t = Clock::Wall.now().0;
        self.publish_button_events(&reading, t)?;
        if !self.pose_accepted(&pose, &reading, t)? {
            return Ok(());
        }
        self.last_reading = Some((read_at, reading));
        self.stale_announced = false;
        let Some(rv) = self.fresh_robot(&reading, t)? else { return Ok(()) };
        self.act(&reading, &rv, t, read_at)
    }

    /// The arm's states that arrived (the newest kept).
    fn take_arm_state(&mut self) -> anyhow::Result<()> {
        while let Some(s) = self.arm.try_take()? {
            let view =
                RobotView { cartesian_position: s.msg.cartesian_position, gripper_position: s.msg.gripper_position };
            self.robot = Some((view, Instant::now()));
        }
        Ok(())
    }

    /// Episode events on the press, from either controller.
    fn publish_button_events(&mut self, reading: &Reading, t: i64) -> anyhow::Result<()> {
        let buttons = (reading.right.success || reading.left.success, reading.right.failure || reading.left.failure);
        for (pressed, was, kind, name) in [
            (buttons.0, self.prev_buttons.0, EpisodeEventKind::Success, "success (A/X)"),
            (buttons.1, self.prev_buttons.1, EpisodeEventKind::Failure, "failure (B/Y)"),
        ] {
            if pressed && !was {
                let ev = EpisodeEvent {
                    header: Header { stamp: Nanos(t).into(), frame_id: String::new() },
                    kind: kind as u8,
                    note: format!("teleop: {name}"),
                    ..EpisodeEvent::default()
                };
                self.request_pub.publish(ev)?;
                self.stats.events.push(name.to_owned());
            }
        }
        self.prev_buttons = buttons;
        Ok(())
    }

    /// Whether the glitch guard accepts `pose`; a refused one is counted and warned, and one
    /// that moved for good disables motion until the grip is pressed again.
    fn pose_accepted(&mut self, pose: &Matrix4<f64>, reading: &Reading, t: i64) -> anyhow::Result<bool> {
        let (accepted, relocated) = self.guard.check(pose, &self.cfg);
        if accepted {
            return Ok(true);
        }
        self.stats.jumps_refused += 1;
        if relocated {
            // The controller is somewhere else for good: motion needs a new press.
            tracing::warn!("the controller's pose moved for good: press the grip again to move");
            self.policy.release();
            self.state_pub.publish(self.state_msg(t, true, false, Some(reading), None))?;
        } else {
            // A glitch: skipped, the origins kept (the next good reading goes on).
            tracing::warn!("refused a controller pose that jumped (tracking glitch)");
        }
        Ok(false)
    }

    /// The arm's state when fresh. The mapping closes its loop on it: without a fresh one the
    /// action would chase an offset the arm may already have made up, so motion is disabled.
    fn fresh_robot(&mut self, reading: &Reading, t: i64) -> anyhow::Result<Option<RobotView>> {
        let max_age = self.cfg.max_state_age_s;
        let Some(rv) = self.robot.filter(|(_, at)| at.elapsed().as_secs_f64() <= max_age).map(|(v, _)| v) else {
            if !self.warned_no_state {
                tracing::warn!("no fresh {}: motion disabled until the arm's state arrives", self.cfg.state_topic);
                self.warned_no_state = true;
            }
            self.policy.release();
            self.state_pub.publish(self.state_msg(t, true, false, Some(reading), None))?;
            return Ok(None);
        };
        self.warned_no_state = false;
        Ok(Some(rv))
    }

    /// The mapping's action for `reading` against the arm's state: `/teleop/state` and
    /// `/teleop/action` published, the latency since `read_at` kept.
    fn act(&mut self, reading: &Reading, rv: &RobotView, t: i64, read_at: Instant) -> anyhow::Result<()> {
        let Some(a) = self.policy.step(reading, rv) else { return Ok(()) };
        let gripper = (rv.gripper_position + a.velocity[6] * self.cfg.gripper_delta).clamp(0.0, 1.0);
        self.seq += 1;
        let cmd = ArmCommand {
            header: Header { stamp: Nanos(t).into(), frame_id: "base".into() },
            mode: ArmCommandMode::CartesianVelocity as u8,
            cartesian_velocity: [
                a.velocity[0],
                a.velocity[1],
                a.velocity[2],
                a.velocity[3],
                a.velocity[4],
                a.velocity[5],
            ],
            gripper_position: if a.movement_enabled { gripper } else { rv.gripper_position },
            seq: self.seq,
            ..ArmCommand::default()
        };
        self.state_pub.publish(self.state_msg(t, true, a.movement_enabled, Some(reading), Some(&a.controller)))?;
        self.action_pub.publish(cmd)?;
        self.stats.actions += 1;
        self.latencies.push(read_at.elapsed().as_secs_f64() * 1e6);
        Ok(())
    }

    /// The 10 ms tick: no reading for `stale_s` disables motion, announced once and then
    /// published every 100 ms.
    fn on_tick(&mut self) -> anyhow::Result<()> {
        let age = self.last_reading.as_ref().map(|(at, _)| at.elapsed());
        let stale = age.is_none_or(|a| a.as_secs_f64() > self.cfg.stale_s);
        if stale {
            let just_now = !self.stale_announced && age.is_some();
            if just_now {
                self.stale_announced = true;
                self.stats.stale_holds += 1;
                self.policy.release();
                tracing::warn!("no controller reading for {:.0} ms: motion disabled", self.cfg.stale_s * 1e3);
            }
            // Disabled at once when it turned stale, then every 100 ms.
            if just_now || self.disabled_published_at.elapsed() >= Duration::from_millis(100) {
                let connected = age.is_some_and(|a| a.as_secs_f64() < self.cfg.controller_timeout_s);
                let last = self.last_reading.as_ref().map(|(_, r)| r);
                self.state_pub.publish(self.state_msg(Clock::Wall.now().0, connected, false, last, None))?;
                self.disabled_published_at = Instant::now();
            }
        }
        Ok(())
    }

    /// The run's figures (the latency percentiles computed), logged.
    fn finish(mut self) -> TeleopStats {
        let mut stats = std::mem::take(&mut self.stats);
        let latencies = &mut self.latencies;
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
        stats
    }
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
