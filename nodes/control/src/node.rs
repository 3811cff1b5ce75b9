//! The control node (`labrig-control run`): the rig loop at 20 Hz.
//!
//! Each tick it takes the newest `/arm/state` and `/gripper/state`, each camera's newest
//! frame at or before the tick (iceoryx2 headers: which frame, its capture time, the skew),
//! asks the action source for an action, passes it through the safety layer (labrig-franka's
//! filter and IK: NaN and stale actions refused, workspace, joint limits and margins, per-step
//! limits), sends the joint targets on `/arm/command` and the gripper on `/gripper/command`,
//! and, while an episode is recorded, publishes one `labrig_msgs/Step` on `/rig/step`.
//!
//! Episodes: `/rig/episode` carries the events the recorder follows (Start with the task
//! instruction, Success, Failure, Discard, Reset). Events come from `/rig/request` (buttons,
//! `labrig episode ...`, a UI) and, with `auto_start`, from the loop itself: the scripted
//! expert's verdict ends an episode, a step budget fails it. After an episode the arm goes
//! back to DROID's reset pose (gripper open, joint steps inside the safety limits); `Reset` is
//! published when it is there. In the sim, with `reseed`, each episode gets a new scene
//! (`/sim/reset`, seeds `first_seed`, `first_seed + 1`, ...).
//!
//! Clocks: `sim` ticks on the sim bridge's time (a tick is the first `/arm/state` stamped a
//! period after the last tick; in
//! lockstep the bridge steps once per arm command, so the loop and the physics advance
//! together and the result does not depend on machine speed); `wall` ticks on the monotonic
//! clock (the real rig). The loop always commands the arm, holding it while idle, so sim time
//! runs and the arm node's watchdog stays fed. Step timing (DROID's step_start ..
//! step_end) is on the loop's clock: in sim, the tick's sim time plus wall time spent in it.

use crate::episode::{Effect, Ending, Episodes, State};
use crate::frames::{FrameBook, FrameTimes};
use crate::source::{ActionSource, Proposal, ScriptedExpert, Verdict};
use crate::step::{Decision, Observation, TickTimes, make_step};
use anyhow::Context;
use labrig_arm::ik::{Ik, IkConfig, delta_to_velocity, pose_error, xyz_euler};
use labrig_arm::safety::{ArmView, SafetyConfig, SafetyFilter};
use labrig_arm::{Fr3Kinematics, Joints, TcpOffset};
use labrig_msgs::Invalid;
use labrig_msgs::Nanos;
use labrig_msgs::labrig_msgs::{
    ActionDict, ArmCommand, ArmCommandMode, DROID_RESET_POSE, EpisodeEvent, EpisodeEventKind, GripperCommand,
    GripperState, RIG_CAMERAS, RobotState, Step,
};
use labrig_msgs::std_msgs::{Header, StringMsg};
use labrig_msgs::topics;
use labrig_runtime::frames::{FrameNode, FrameSubscriber};
use labrig_runtime::ros::{Ros, RosPublisher, RosSubscription};
use labrig_runtime::{RosConfig, Shutdown};
use serde::{Deserialize, Serialize};
use serde_json::json;
use std::path::PathBuf;
use std::time::{Duration, Instant};

/// In sim time, a state this close to a period after the last tick starts the next one.
const TICK_TOLERANCE_NS: i64 = 1_000_000;

/// DROID's `max_gripper_delta`: a full-scale gripper velocity moves it this far per step.
pub const MAX_GRIPPER_DELTA: f64 = 0.25;
/// DROID's per-joint `max_joint_delta` (rad per step at full-scale joint velocity).
pub const MAX_JOINT_DELTA: f64 = 0.2;

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "snake_case")]
pub enum SourceKind {
    /// The sim bridge's scripted expert (`labrig sim run --expert`).
    Scripted,
    /// No source: the arm holds; episodes only from `/rig/request`.
    Hold,
    /// The Quest teleop node (`labrig-teleop`): `/teleop/action`, deadman on `/teleop/state`;
    /// episodes from `/rig/request` (the operator's and the controller's A/B).
    Teleop,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "snake_case")]
pub enum ClockKind {
    /// The sim bridge's time: one tick per new `/arm/state` stamp.
    Sim,
    /// The monotonic wall clock (the real rig).
    Wall,
}

/// The node's config (TOML; every key optional, unknown keys refused).
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ControlConfig {
    pub ros: RosConfig,
    pub source: SourceKind,
    pub clock: ClockKind,
    /// Control period (ms); DROID: 50 (20 Hz).
    pub period_ms: u64,
    /// Start episodes without an operator (the scripted expert).
    pub auto_start: bool,
    /// Episodes to run before the node exits (0: until stopped).
    pub episodes: u64,
    /// Sim only: a new scene per episode through `/sim/reset`, seeds from `first_seed`.
    pub reseed: bool,
    pub first_seed: u64,
    /// An episode longer than this many steps fails.
    pub max_steps: u64,
    /// The cameras whose frames each step references.
    pub cameras: Vec<String>,
    pub frames_namespace: Option<String>,
    /// A camera frame older than this at a tick is stale (ms).
    pub stale_frame_ms: f64,
    /// A source action older than this at a tick is refused (ms; realtime only, lockstep
    /// waits for the tick's own action).
    pub max_action_age_ms: f64,
    /// Teleop: an action that arrived longer ago than this is not followed (ms). The headset
    /// sends ~72 readings/s, so 35 ms is ~2 missed ones; with a 50 ms tick a vanished
    /// controller holds the arm within 35 + 50 ms.
    pub teleop_max_age_ms: f64,
    /// How long a lockstep tick waits for the source's action before holding (s).
    pub source_timeout_s: f64,
    /// The arm counts as home when every joint is this close to DROID's reset pose (rad).
    pub home_tolerance_rad: f64,
    /// Giving up on reaching home after this long (s of the loop's clock): the node stops.
    pub reset_timeout_s: f64,
    /// On the wall clock, run the loop's thread at this SCHED_FIFO priority (1..99; 0: off).
    /// Needs root or CAP_SYS_NICE; without them the loop runs at normal priority, warned.
    pub realtime_priority: u8,
    /// DROID's uuid parts: `<lab>+<user>+<timestamp>`.
    pub lab: String,
    pub user: String,
    pub safety: SafetyConfig,
    /// The FR3 URDF (default: the one setup installs).
    pub urdf: Option<PathBuf>,
}

impl Default for ControlConfig {
    fn default() -> Self {
        ControlConfig {
            ros: RosConfig::default(),
            source: SourceKind::Scripted,
            clock: ClockKind::Sim,
            period_ms: 50,
            auto_start: true,
            episodes: 0,
            reseed: true,
            first_seed: 0,
            max_steps: 400,
            cameras: RIG_CAMERAS.iter().map(|c| c.to_string()).collect(),
            frames_namespace: labrig_runtime::frames::default_namespace(),
            stale_frame_ms: 100.0,
            max_action_age_ms: 150.0,
            teleop_max_age_ms: 35.0,
            source_timeout_s: 5.0,
            home_tolerance_rad: 0.02,
            reset_timeout_s: 20.0,
            realtime_priority: 20,
            lab: "LABRIG".into(),
            user: "operator".into(),
            // The loop makes its own commands each tick: no age check on them.
            safety: SafetyConfig { max_command_age_s: 0.0, ..SafetyConfig::default() },
            urdf: None,
        }
    }
}

impl ControlConfig {
    pub fn validate(&self) -> Result<(), Invalid> {
        if !(1..=1000).contains(&self.period_ms) {
            return Err(Invalid::new("period_ms", format!("period_ms = {} must be in 1..=1000", self.period_ms)));
        }
        if (self.safety.period_s * 1e3 - self.period_ms as f64).abs() > 1e-6 {
            return Err(Invalid::new(
                "safety.period_s",
                format!(
                    "safety.period_s = {} must equal period_ms = {} (the per-step limits are per period)",
                    self.safety.period_s, self.period_ms
                ),
            ));
        }
        for (name, v) in [
            ("stale_frame_ms", self.stale_frame_ms),
            ("max_action_age_ms", self.max_action_age_ms),
            ("source_timeout_s", self.source_timeout_s),
            ("home_tolerance_rad", self.home_tolerance_rad),
            ("reset_timeout_s", self.reset_timeout_s),
        ] {
            if !(v.is_finite() && v > 0.0) {
                return Err(Invalid::new(name, format!("{name} = {v} must be > 0")));
            }
        }
        if self.realtime_priority > 99 {
            return Err(Invalid::new(
                "realtime_priority",
                format!("realtime_priority = {} must be 0..=99", self.realtime_priority),
            ));
        }
        if self.max_steps == 0 {
            return Err(Invalid::new("max_steps", "max_steps must be > 0"));
        }
        if self.source == SourceKind::Hold && self.auto_start {
            return Err(Invalid::new("auto_start", "auto_start needs an action source (source = \"hold\" has none)"));
        }
        if self.source == SourceKind::Teleop && self.auto_start {
            return Err(Invalid::new(
                "auto_start",
                "auto_start: teleop episodes start on /rig/request (the operator), not by themselves",
            ));
        }
        if !(self.teleop_max_age_ms.is_finite() && self.teleop_max_age_ms > 0.0) {
            return Err(Invalid::new(
                "teleop_max_age_ms",
                format!("teleop_max_age_ms: {} must be positive", self.teleop_max_age_ms),
            ));
        }
        self.safety.validate()
    }
}

/// One finished episode, as the loop saw it.
#[derive(Debug, Clone, Serialize)]
pub struct EpisodeReport {
    pub episode_id: String,
    pub seed: Option<u64>,
    pub instruction: String,
    pub outcome: String,
    pub steps: u64,
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
    /// Recorded steps with a camera missing, or with a frame older than `stale_frame_ms`.
    pub steps_missing_frames: u64,
    pub steps_stale_frames: u64,
    /// Camera skew per recorded step (us): p50, p99, max.
    pub skew_us: [f64; 3],
    pub seconds: f64,
}

struct Pubs {
    arm: RosPublisher<ArmCommand>,
    gripper: RosPublisher<GripperCommand>,
    step: RosPublisher<Step>,
    episode: RosPublisher<EpisodeEvent>,
    reset: RosPublisher<StringMsg>,
    status: RosPublisher<StringMsg>,
}

/// The latest scene the sim published (`/sim/scene`).
#[derive(Debug, Clone, Default)]
struct Scene {
    seed: Option<u64>,
    instruction: String,
}

impl Scene {
    fn parse(json: &str) -> Result<Scene, serde_json::Error> {
        let v: serde_json::Value = serde_json::from_str(json)?;
        Ok(Scene { seed: v["seed"].as_u64(), instruction: v["instruction"].as_str().unwrap_or_default().to_owned() })
    }
}

/// What the loop is doing between episodes.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Between {
    /// Waiting for `/sim/scene` to show this seed.
    Reseeding {
        seed: u64,
        asked_at: i64,
    },
    Ready,
}

pub async fn run(cfg: ControlConfig, shutdown: Shutdown) -> anyhow::Result<Summary> {
    cfg.validate()?;
    let period = Nanos::from_millis(cfg.period_ms as i64);
    let urdf = labrig_arm::urdf_path(cfg.urdf.as_deref());
    let kin = Fr3Kinematics::from_urdf_file(&urdf, TcpOffset::ROBOTIQ_2F85)
        .with_context(|| format!("loading the FR3 URDF {}", urdf.display()))?;
    let filter =
        SafetyFilter::new(Ik::new(kin.clone(), IkConfig::default()), cfg.safety.clone()).map_err(anyhow::Error::msg)?;

    let mut ros = Ros::new(&cfg.ros, "labrig_control")?;
    let pubs = Pubs {
        arm: ros.publisher_on(&topics::ARM_COMMAND, 10)?,
        gripper: ros.publisher_on(&topics::GRIPPER_COMMAND, 10)?,
        step: ros.publisher_on(&topics::RIG_STEP, 100)?,
        episode: ros.publisher_on(&topics::RIG_EPISODE, 100)?,
        reset: ros.publisher_on(&topics::SIM_RESET, 10)?,
        status: ros.publisher_on(&topics::CONTROL_STATUS, 1)?,
    };
    let arm_state: RosSubscription<RobotState> = ros.subscription_on(&topics::ARM_STATE, 10)?;
    let gripper_state: RosSubscription<GripperState> = ros.subscription_on(&topics::GRIPPER_STATE, 10)?;
    let scene_sub: RosSubscription<StringMsg> = ros.subscription_on(&topics::SIM_SCENE, 1)?;
    let requests: RosSubscription<EpisodeEvent> = ros.subscription_on(&topics::RIG_REQUEST, 10)?;
    let mut source: Option<Box<dyn ActionSource>> = match cfg.source {
        SourceKind::Scripted => Some(Box::new(ScriptedExpert::new(&mut ros)?)),
        SourceKind::Hold => None,
        SourceKind::Teleop => {
            Some(Box::new(crate::source::Teleop::new(&mut ros, Duration::from_secs_f64(cfg.teleop_max_age_ms / 1e3))?))
        }
    };
    let frame_node = match &cfg.frames_namespace {
        Some(ns) => FrameNode::new_in(ns)?,
        None => FrameNode::new()?,
    };
    let cams: Vec<(String, FrameSubscriber)> =
        cfg.cameras.iter().map(|c| Ok((c.clone(), frame_node.subscriber(c)?))).collect::<anyhow::Result<_>>()?;
    let camera_names: Vec<&str> = cfg.cameras.iter().map(String::as_str).collect();
    let mut book = FrameBook::new(&camera_names);

    // The first state (the arm node or the sim bridge may still be starting).
    let waited = Instant::now();
    let mut robot: RobotState = loop {
        if let Some(s) = arm_state.try_take()? {
            break s.msg;
        }
        anyhow::ensure!(!shutdown.is_triggered(), "stopped before the arm came up");
        anyhow::ensure!(
            waited.elapsed() < Duration::from_secs(120),
            "no /arm/state within 120 s: is the arm node (or the sim bridge) running on this domain?"
        );
        tokio::time::sleep(Duration::from_millis(20)).await;
    };
    // Commands reach their subscriber before the first tick's (lockstep needs each one).
    if !ros.wait_for_subscribers(topics::ARM_COMMAND.name, 1, Duration::from_secs(30)).await {
        anyhow::bail!("nothing subscribes to /arm/command within 30 s");
    }
    if cfg.auto_start {
        // The recorder should hear the first episode's Start.
        if !ros.wait_for_subscribers(topics::RIG_EPISODE.name, 1, Duration::from_secs(30)).await {
            tracing::warn!("nothing subscribes to /rig/episode: episodes will not be recorded");
        }
    }
    // The graph shows a reader a little before our writers have matched it: let them settle.
    tokio::time::sleep(Duration::from_millis(300)).await;
    if cfg.clock == ClockKind::Wall && cfg.realtime_priority > 0 {
        // This future runs on the thread that called block_on: the loop's own thread.
        if let Err(e) = labrig_runtime::realtime_priority(cfg.realtime_priority) {
            tracing::warn!("{e}; the loop runs at normal priority");
        }
    }
    tracing::info!(source = ?cfg.source, clock = ?cfg.clock, episodes = cfg.episodes, "control loop up");
    let _ = pubs.status.publish(StringMsg { data: json!({ "state": "Idle", "ticks": 0 }).to_string() });

    let mut gripper: Option<GripperState> = None;
    let mut scene = Scene::default();
    let mut episodes = Episodes::default();
    let mut between = Between::Ready;
    let mut summary = Summary::default();
    let mut commanded: Option<Joints> = None;
    let mut gripper_target = 0.0f64;
    let mut seq = 0u64;
    let mut episode_id = String::new();
    let mut episode_seed: Option<u64> = None;
    let mut episode_instruction = String::new();
    let mut next_seed = cfg.first_seed;
    let mut reset_started: i64 = 0;
    let mut last_tick_ns: Option<i64> = None;
    let mut last_tick_wall: Option<Instant> = None;
    let mut jitter_ns: Vec<i64> = Vec::new();
    let mut skew_ns: Vec<i64> = Vec::new();
    let started = Instant::now();
    let mut next_wall = Instant::now() + Duration::from_nanos(period.0 as u64);
    // An operator's event and its note (a Start's task instruction).
    let mut pending_request: Option<(EpisodeEventKind, String)> = None;

    let publish_event = |kind: EpisodeEventKind, id: &str, note: &str, t: i64| {
        let ev = EpisodeEvent {
            header: Header { stamp: Nanos(t).into(), frame_id: String::new() },
            kind: kind as u8,
            episode_id: id.to_owned(),
            note: note.to_owned(),
            ..Default::default()
        };
        if let Err(e) = pubs.episode.publish(ev) {
            tracing::error!("/rig/episode: {e}");
        }
    };

    'ticks: while !shutdown.is_triggered() {
        // Wait for the tick.
        let tick_ns = match cfg.clock {
            ClockKind::Sim => loop {
                if shutdown.is_triggered() {
                    break 'ticks;
                }
                let mut newest = None;
                while let Some(s) = arm_state.try_take()? {
                    newest = Some(s.msg);
                }
                if let Some(s) = newest {
                    let t = Nanos::from(s.header.stamp).0;
                    robot = s;
                    // A new period (an arm node may publish states faster than the loop runs).
                    if last_tick_ns.is_none_or(|l| t >= l + period.0 - TICK_TOLERANCE_NS) {
                        break t;
                    }
                }
                tokio::time::sleep(Duration::from_micros(200)).await;
            },
            ClockKind::Wall => {
                // The loop's own thread sleeps to the tick (a high-resolution timer; at
                // SCHED_FIFO it runs the moment it wakes). tokio's timers are woken by its
                // workers at normal priority: 1-5 ms late on a busy machine.
                std::thread::sleep(next_wall.saturating_duration_since(Instant::now()));
                if shutdown.is_triggered() {
                    break 'ticks;
                }
                let now = Instant::now();
                // Behind by more than a period: skip the lost ticks, count them.
                let behind = now.saturating_duration_since(next_wall).as_nanos() as i64 / period.0;
                summary.missed_ticks += behind as u64;
                next_wall += Duration::from_nanos((period.0 * (behind + 1)) as u64);
                while let Some(s) = arm_state.try_take()? {
                    robot = s.msg;
                }
                labrig_runtime::Clock::Wall.now().0
            }
        };
        let tick_wall = Instant::now();
        if let (Some(l), ClockKind::Sim) = (last_tick_ns, cfg.clock) {
            let missed = (tick_ns - l) / period.0 - 1;
            if missed > 0 {
                summary.missed_ticks += missed as u64;
            }
        }
        if let Some(w) = last_tick_wall {
            jitter_ns.push((tick_wall.duration_since(w).as_nanos() as i64 - period.0).abs());
        }
        let prev_tick_ns = last_tick_ns.replace(tick_ns);
        last_tick_wall = Some(tick_wall);
        summary.ticks += 1;
        // The loop's clock inside the tick.
        let now = |at: Instant| tick_ns + at.duration_since(tick_wall).as_nanos() as i64;
        let step_start = now(Instant::now());

        // Everything that arrived.
        while let Some(g) = gripper_state.try_take()? {
            gripper = Some(g.msg);
        }
        // On the sim's clock the gripper's state of this same instant follows the arm's on its
        // own topic: wait for it (bounded), so a step's gripper reading is not a tick old.
        if cfg.clock == ClockKind::Sim && gripper.is_some() {
            let stamp = |g: &Option<GripperState>| g.as_ref().map_or(i64::MIN, |g| Nanos::from(g.header.stamp).0);
            let deadline = Instant::now() + Duration::from_millis(500);
            while stamp(&gripper) < tick_ns && Instant::now() < deadline && !shutdown.is_triggered() {
                tokio::time::sleep(Duration::from_micros(100)).await;
                while let Some(g) = gripper_state.try_take()? {
                    gripper = Some(g.msg);
                }
            }
        }
        while let Some(s) = scene_sub.try_take()? {
            match Scene::parse(&s.msg.data) {
                Ok(sc) => scene = sc,
                Err(e) => tracing::warn!("/sim/scene is not JSON: {e}"),
            }
        }
        // On the sim's clock a camera that kept pace with the last tick has this tick's frame
        // on its way (it trails the state on its own channel; after a scene rebuild by more):
        // wait for it (bounded), so a step never pairs this state with the last tick's image.
        let frames_deadline = Instant::now() + Duration::from_millis(200);
        loop {
            for (name, sub) in &cams {
                while let Some(f) = sub.receive()? {
                    let h = f.header();
                    book.push(
                        name,
                        FrameTimes { sequence: h.sequence, capture_ns: h.capture_ns, arrival_ns: h.arrival_ns },
                    );
                }
            }
            let waiting =
                cfg.clock == ClockKind::Sim && prev_tick_ns.is_some_and(|p| !book.keeping_pace(p, tick_ns).is_empty());
            if !waiting || Instant::now() >= frames_deadline || shutdown.is_triggered() {
                break;
            }
            tokio::time::sleep(Duration::from_micros(100)).await;
        }
        while let Some(r) = requests.try_take().unwrap_or_else(|e| {
            tracing::warn!("/rig/request: {e}");
            None
        }) {
            match r.msg.kind() {
                Ok(k) => pending_request = Some((k, r.msg.note)),
                Err(e) => tracing::warn!("/rig/request: {e}"),
            }
        }
        if let Some(s) = source.as_mut() {
            s.poll()?;
        }

        // Episode events: the operator's, then the loop's own.
        let mut skip_command = false;
        let (mut event, mut instruction) = match pending_request.take() {
            Some((k, note)) => (Some(k), note),
            None => (None, String::new()),
        };
        if instruction.is_empty() {
            instruction.clone_from(&scene.instruction);
        }
        let state = episodes.state();
        if state == State::Idle && cfg.episodes > 0 && summary.episodes.len() as u64 >= cfg.episodes {
            break;
        }
        if let Between::Reseeding { seed, asked_at } = between {
            // Lockstep: the state after the rebuild is the first tick of the new scene (the
            // bridge resumes a period on); its scene message may trail it on its own topic.
            if cfg.clock == ClockKind::Sim && tick_ns > asked_at && scene.seed != Some(seed) {
                let deadline = Instant::now() + Duration::from_secs(30);
                while scene.seed != Some(seed) && Instant::now() < deadline && !shutdown.is_triggered() {
                    tokio::time::sleep(Duration::from_micros(200)).await;
                    while let Some(m) = scene_sub.try_take()? {
                        scene = Scene::parse(&m.msg.data).unwrap_or(scene);
                    }
                }
            }
            if scene.seed == Some(seed) {
                // This tick starts the episode, from the new scene's first state.
                between = Between::Ready;
                commanded = None;
            } else if tick_ns - asked_at > 30_000_000_000 {
                anyhow::bail!(
                    "the sim did not load scene seed {seed} within 30 s of /sim/reset (is it `labrig sim run`?)"
                );
            }
        }
        if event.is_none() && state == State::Idle && cfg.auto_start && between == Between::Ready {
            // Not before the source has an action for now (after a scene rebuild it may lag).
            let age_ns = (cfg.max_action_age_ms * 1e6) as i64;
            let source_ready =
                cfg.clock == ClockKind::Sim || source.as_mut().is_none_or(|s| s.action(tick_ns, age_ns).is_ok());
            // Nor while a camera that has been sending lags (after a scene rebuild, say).
            let lagging = book.at(tick_ns, (cfg.stale_frame_ms * 1e6) as i64).stale;
            if !lagging.is_empty() && summary.ticks.is_multiple_of(40) {
                let seen = book.at(i64::MAX, i64::MAX).refs;
                let ages: Vec<f64> = seen.iter().map(|r| (tick_ns - r.capture_ns) as f64 / 1e6).collect();
                tracing::warn!(cameras = ?lagging, ages_ms = ?ages, "waiting for fresh frames before starting the episode");
            }
            if !source_ready || !lagging.is_empty() {
            } else if cfg.reseed {
                if scene.seed == Some(next_seed) && episode_seed.is_none_or(|s| s != next_seed) {
                    event = Some(EpisodeEventKind::Start);
                } else {
                    let msg = StringMsg { data: json!({ "seed": next_seed }).to_string() };
                    pubs.reset.publish(msg)?;
                    between = Between::Reseeding { seed: next_seed, asked_at: tick_ns };
                    // Lockstep: no step of the old scene after this; the next state is the new one's.
                    skip_command = cfg.clock == ClockKind::Sim;
                }
            } else {
                event = Some(EpisodeEventKind::Start);
            }
        }
        if event.is_none() && episodes.recording() {
            let verdict = source.as_ref().map_or(Verdict::Running, |s| s.verdict(tick_ns));
            event = match verdict {
                Verdict::Succeeded => Some(EpisodeEventKind::Success),
                Verdict::Failed => Some(EpisodeEventKind::Failure),
                Verdict::Running if episodes.steps >= cfg.max_steps => {
                    tracing::warn!(steps = episodes.steps, "step budget spent: the episode failed");
                    Some(EpisodeEventKind::Failure)
                }
                Verdict::Running => None,
            };
        }
        if let State::Resetting(_) = state {
            let home =
                robot.joint_positions.iter().zip(DROID_RESET_POSE).all(|(q, h)| (q - h).abs() < cfg.home_tolerance_rad);
            if home {
                event = Some(EpisodeEventKind::Reset);
            } else if tick_ns - reset_started > (cfg.reset_timeout_s * 1e9) as i64 {
                let worst =
                    robot.joint_positions.iter().zip(DROID_RESET_POSE).map(|(q, h)| (q - h).abs()).fold(0.0, f64::max);
                anyhow::bail!(
                    "the arm did not reach the reset pose within {} s ({worst:.3} rad away; mode {}, {:?})",
                    cfg.reset_timeout_s,
                    robot.mode,
                    robot.fault
                );
            }
        }
        if let Some(kind) = event {
            match episodes.on(kind) {
                Ok(Effect::StartRecording) => {
                    episode_id = episode_uuid(&cfg.lab, &cfg.user, &summary.episodes);
                    episode_seed = scene.seed;
                    if let Some(s) = source.as_mut() {
                        s.restart(tick_ns);
                    }
                    publish_event(kind, &episode_id, &instruction, tick_ns);
                    tracing::info!(episode = %episode_id, seed = ?scene.seed, %instruction, "episode started");
                    episode_instruction.clone_from(&instruction);
                }
                Ok(Effect::EndRecording(ending)) => {
                    publish_event(kind, &episode_id, "", tick_ns);
                    let outcome = match ending {
                        Ending::Success => "success",
                        Ending::Failure => "failure",
                        Ending::Discarded => "discarded",
                    };
                    tracing::info!(episode = %episode_id, steps = episodes.steps, outcome, "episode ended");
                    summary.episodes.push(EpisodeReport {
                        episode_id: episode_id.clone(),
                        seed: episode_seed,
                        instruction: episode_instruction.clone(),
                        outcome: outcome.into(),
                        steps: episodes.steps,
                    });
                    reset_started = tick_ns;
                    if cfg.reseed {
                        next_seed += 1;
                    }
                }
                Ok(Effect::Ready) => {
                    publish_event(kind, &episode_id, "", tick_ns);
                    tracing::info!("the arm is home");
                }
                Err(refused) => tracing::warn!("{refused}"),
            }
        }

        // Lockstep: the source's action for this state comes right after the state.
        if let (Some(s), ClockKind::Sim, true) = (source.as_mut(), cfg.clock, episodes.recording()) {
            let deadline = Instant::now() + Duration::from_secs_f64(cfg.source_timeout_s);
            while !s.has(tick_ns) && Instant::now() < deadline && !shutdown.is_triggered() {
                tokio::time::sleep(Duration::from_micros(100)).await;
                s.poll()?;
            }
        }
        // The action: the source's while recording, home while resetting, else hold.
        let policy_start = now(Instant::now());
        let view = ArmView { measured: robot.joint_positions, commanded: commanded.unwrap_or(robot.joint_positions) };
        let (proposal, source_kind) = match episodes.state() {
            State::Recording => match source.as_mut() {
                Some(s) => match s.action(tick_ns, (cfg.max_action_age_ms * 1e6) as i64) {
                    Ok(p) => (Some(p), s.kind()),
                    Err(e) => {
                        tracing::warn!("{e}: holding");
                        summary.held_ticks += 1;
                        (None, s.kind())
                    }
                },
                None => (None, Step::SOURCE_NONE),
            },
            State::Resetting(_) => {
                let cmd = ArmCommand {
                    mode: ArmCommandMode::JointPosition as u8,
                    joint_position: DROID_RESET_POSE,
                    gripper_position: 0.0,
                    ..Default::default()
                };
                (Some(Proposal { command: cmd, movement_enabled: true }), Step::SOURCE_NONE)
            }
            State::Idle => (None, Step::SOURCE_NONE),
        };
        let hold = || ArmCommand {
            mode: ArmCommandMode::JointPosition as u8,
            joint_position: view.commanded,
            gripper_position: gripper_target,
            ..Default::default()
        };
        let (mut wanted, mut moving) = match proposal.filter(|p| p.movement_enabled) {
            Some(p) => (p.command, true),
            None => (hold(), false),
        };
        let safe = match filter.filter(&wanted, &view, tick_ns) {
            Ok(s) => s,
            Err(refusal) => {
                moving = false;
                // The record holds what was done (a hold), never the refused values.
                wanted = hold();
                summary.refused += 1;
                summary.held_ticks += 1;
                tracing::warn!("refused the action: {refusal}; holding");
                filter.filter(&wanted, &view, tick_ns).map_err(|e| anyhow::anyhow!("cannot even hold the arm: {e}"))?
            }
        };
        let action = action_dict(&kin, &robot, gripper.as_ref(), &wanted, &safe.joints, safe.gripper);
        // Send.
        let sleep_start = now(Instant::now());
        seq += 1;
        let stamp: labrig_msgs::builtin_interfaces::Time = Nanos(tick_ns).into();
        let control_start = now(Instant::now());
        if skip_command {
            continue 'ticks;
        }
        if let Err(e) = pubs.gripper.publish(GripperCommand {
            header: Header { stamp, frame_id: String::new() },
            position: safe.gripper,
            speed: 1.0,
            force: 0.5,
            ..Default::default()
        }) {
            tracing::warn!("/gripper/command: {e}");
        }
        pubs.arm.publish(ArmCommand {
            header: Header { stamp, frame_id: "base".into() },
            mode: ArmCommandMode::JointPosition as u8,
            joint_position: safe.joints,
            gripper_position: safe.gripper,
            seq,
            ..Default::default()
        })?;
        commanded = Some(safe.joints);
        gripper_target = safe.gripper;
        if episodes.recording() {
            let frames = book.at(tick_ns, (cfg.stale_frame_ms * 1e6) as i64);
            if !frames.missing.is_empty() || !frames.stale.is_empty() {
                tracing::debug!(missing = ?frames.missing, stale = ?frames.stale, "cameras");
            }
            summary.steps_missing_frames += u64::from(!frames.missing.is_empty());
            summary.steps_stale_frames += u64::from(!frames.stale.is_empty());
            skew_ns.push(frames.skew_ns);
            let times = TickTimes {
                tick_ns,
                step_start,
                policy_start,
                sleep_start,
                control_start,
                step_end: now(Instant::now()),
            };
            let obs = Observation { robot: robot.clone(), gripper: gripper.clone(), frames };
            let decision = Decision { action, source: source_kind, movement_enabled: moving };
            pubs.step.publish(make_step(&episode_id, episodes.steps, &obs, &decision, &times))?;
            episodes.tick();
        }
        if summary.ticks % 20 == 0 {
            let status = json!({
                "state": format!("{:?}", episodes.state()),
                "episode": episode_id,
                "steps": episodes.steps,
                "episodes": summary.episodes.len(),
                "ticks": summary.ticks,
                "held_ticks": summary.held_ticks,
                "missed_ticks": summary.missed_ticks,
                "seconds": started.elapsed().as_secs_f64(),
            });
            let _ = pubs.status.publish(StringMsg { data: status.to_string() });
        }
    }
    // An episode still open when the loop stops ends as a failure, so the recorder closes it.
    if episodes.recording() {
        let t = last_tick_ns.unwrap_or(0);
        let _ = episodes.on(EpisodeEventKind::Stop);
        publish_event(EpisodeEventKind::Stop, &episode_id, "the control loop stopped", t);
    }
    summary.jitter_us = percentiles_us(&mut jitter_ns);
    summary.skew_us = percentiles_us(&mut skew_ns);
    summary.seconds = started.elapsed().as_secs_f64();
    // The last events reach their readers (the recorder) before the participant goes.
    tokio::time::sleep(Duration::from_millis(1000)).await;
    Ok(summary)
}

/// p50, p99 and max of `v` (ns) in us; NaN when empty.
fn percentiles_us(v: &mut [i64]) -> [f64; 3] {
    v.sort_unstable();
    let at = |q: f64| v.get(((v.len().max(1) - 1) as f64 * q).round() as usize).map_or(f64::NAN, |&x| x as f64 / 1e3);
    [at(0.5), at(0.99), at(1.0)]
}

/// DROID's uuid `<lab>+<user>+<YYYY-MM-DD-HHh-MMm-SSs>` (wall time); a second episode in the
/// same second gets `-2`, `-3`, ...
fn episode_uuid(lab: &str, user: &str, earlier: &[EpisodeReport]) -> String {
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
fn action_dict(
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
        };
        let second = episode_uuid("LAB", "op", &[report(&first)]);
        assert_ne!(first, second);
        assert!(first.starts_with("LAB+op+20"));
    }

    #[test]
    fn the_real_rigs_config_file_loads() {
        let p = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../launch_configs/nodes/control_real.toml");
        let c: ControlConfig = labrig_runtime::load_config(&p).unwrap();
        assert_eq!(c.validate(), Ok(()));
        assert_eq!((c.source, c.clock, c.auto_start), (SourceKind::Teleop, ClockKind::Wall, false));
        assert_eq!(c.teleop_max_age_ms, 35.0);
        assert_eq!(c.safety.max_command_age_s, 0.0);
    }

    #[test]
    fn configs_are_checked_by_field() {
        let mut c = ControlConfig::default();
        assert_eq!(c.validate(), Ok(()));
        c.period_ms = 100;
        assert!(c.validate().unwrap_err().to_string().contains("safety.period_s"));
        let c = ControlConfig { source: SourceKind::Hold, ..ControlConfig::default() };
        assert!(c.validate().unwrap_err().to_string().contains("auto_start"));
        let c = ControlConfig { stale_frame_ms: f64::NAN, ..ControlConfig::default() };
        assert!(c.validate().unwrap_err().to_string().contains("stale_frame_ms"));
    }
}
