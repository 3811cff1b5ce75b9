//! The rig loop as a state machine: what one tick does, apart from where its inputs come from
//! and where its outputs go. The node ([`crate::node::run`]) feeds it from ROS 2 and shared
//! memory on the sim's or the wall clock; a test feeds it in memory on a manual clock and reads
//! what it sent ([`RigOutputs`]), tick by tick.
//!
//! One tick, in order:
//! 1. [`RigLoop::begin_tick`] at the tick's time (missed ticks, jitter);
//! 2. observe: [`RigLoop::set_robot`], [`RigLoop::push_gripper`], [`RigLoop::push_scene`],
//!    [`RigLoop::push_frame`], [`RigLoop::push_request`] (the node may wait, bounded, for the
//!    tick's own gripper state, frames and scene: [`RigLoop::gripper_behind`],
//!    [`RigLoop::frames_pending`], [`RigLoop::scene_due`]);
//! 3. [`RigLoop::done`]: the episodes asked for are over;
//! 4. [`RigLoop::decide`]: episode events (the operator's, the source's verdict, the step
//!    budget, home reached, a new scene) and their effects;
//! 5. [`RigLoop::act`]: the action (the source's while recording, home while resetting, else
//!    hold) through the safety layer, the commands, the Step record, the status.

use crate::config::{ClockKind, ControlConfig, SourceKind};
use crate::episode::{Effect, Ending, Episodes, State};
use crate::frames::{FrameBook, FrameTimes};
use crate::report::{EpisodeReport, Spread, Summary, action_dict, episode_uuid, percentiles_us};
use crate::source::{ActionSource, Proposal, TickView, Verdict};
use crate::step::{Decision, Observation, TickTimes, make_step};
use labrig_arm::safety::{ArmView, Refusal, SafetyFilter};
use labrig_arm::{Fr3Kinematics, Joints};
use labrig_msgs::Nanos;
use labrig_msgs::rig::{
    ArmCommand, ArmCommandMode, DROID_RESET_POSE, EpisodeEvent, EpisodeEventKind, GripperCommand, GripperState,
    RobotState, Step,
};
use labrig_msgs::std_msgs::Header;
use labrig_runtime::ros::RosError;
use serde_json::json;
use std::time::Instant;

/// In sim time, a state this close to a period after the last tick starts the next one.
pub const TICK_TOLERANCE_NS: i64 = 1_000_000;

/// Where a tick's outputs go: ROS 2 in the node, vectors in a test.
pub trait RigOutputs {
    fn arm(&mut self, cmd: ArmCommand) -> Result<(), RosError>;
    fn gripper(&mut self, cmd: GripperCommand) -> Result<(), RosError>;
    fn step(&mut self, step: Step) -> Result<(), RosError>;
    fn episode(&mut self, event: EpisodeEvent) -> Result<(), RosError>;
    /// Ask the sim for a new scene (`/sim/reset`).
    fn reset_scene(&mut self, seed: u64) -> Result<(), RosError>;
    /// The loop's status (JSON), latched.
    fn status(&mut self, json: String) -> Result<(), RosError>;
}

/// Why the loop stopped with an error.
#[derive(Debug, thiserror::Error)]
pub enum LoopError {
    #[error(transparent)]
    Ros(#[from] RosError),
    #[error("the sim did not load scene seed {seed} within 30 s of /sim/reset (is it `labrig sim run`?)")]
    SceneTimeout { seed: u64 },
    #[error(
        "the arm did not reach the reset pose within {timeout_s} s ({worst_rad:.3} rad away; mode {mode}, {fault:?})"
    )]
    NotHome { timeout_s: f64, worst_rad: f64, mode: u8, fault: String },
    #[error("cannot even hold the arm: {0}")]
    CannotHold(Refusal),
}

/// Why an operator's request (`/rig/request`) was not applied: the status's `reason`.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum RequestRefused {
    #[error("superseded by a newer request in the same tick")]
    Superseded,
    #[error("not a request: {0}")]
    NotARequest(#[source] labrig_msgs::Invalid),
    #[error("a Reset request applies while idle only (the loop is {state:?})")]
    ResetWhileBusy { state: State },
    /// The recorder cannot record (its refusal, as it says it).
    #[error("episode start refused: {refusal}")]
    RecorderRefuses { refusal: String },
    #[error(transparent)]
    Episode(#[from] crate::episode::Refused),
    #[error("the loop applied its own {applied:?} this tick instead")]
    Overridden { applied: EpisodeEventKind },
    #[error("the loop did not apply it")]
    NotApplied,
}

/// The latest scene the sim published (`/sim/scene`).
#[derive(Debug, Clone, Default)]
struct Scene {
    seed: Option<u64>,
    instruction: String,
    json: String,
}

impl Scene {
    fn parse(json: &str) -> Result<Scene, serde_json::Error> {
        let v: serde_json::Value = serde_json::from_str(json)?;
        Ok(Scene {
            seed: v["seed"].as_u64(),
            instruction: v["instruction"].as_str().unwrap_or_default().to_owned(),
            json: json.to_owned(),
        })
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

/// The current tick.
#[derive(Debug, Clone, Copy)]
struct Tick {
    ns: i64,
    wall: Instant,
    prev_ns: Option<i64>,
    step_start: i64,
    /// Lockstep, a new scene asked for: no command this tick (the next state is the new scene's).
    skip_command: bool,
}

impl Tick {
    /// The loop's clock inside the tick: the tick's time plus the wall time spent in it.
    fn now(&self) -> i64 {
        self.ns + Instant::now().duration_since(self.wall).as_nanos() as i64
    }
}

/// The rig loop's state between ticks.
#[derive(Debug)]
pub struct RigLoop {
    cfg: ControlConfig,
    period: Nanos,
    /// `stale_frame_s` and `max_action_age_s` as the ticks use them.
    stale_frame: Nanos,
    max_action_age: Nanos,
    kin: Fr3Kinematics,
    filter: SafetyFilter,
    book: FrameBook,
    robot: RobotState,
    gripper: Option<GripperState>,
    scene: Scene,
    episodes: Episodes,
    between: Between,
    summary: Summary,
    commanded: Option<Joints>,
    gripper_target: f64,
    seq: u64,
    episode_id: String,
    episode_seed: Option<u64>,
    episode_instruction: String,
    next_seed: u64,
    reset_started: i64,
    last_tick_ns: Option<i64>,
    last_tick_wall: Option<Instant>,
    jitter_ns: Spread,
    skew_ns: Spread,
    started: Instant,
    /// The figures of the window under way (`window_stats`).
    window: Window,
    /// An operator's event and its note (a Start's task instruction).
    pending_request: Option<(EpisodeEventKind, String, i64)>,
    /// What became of the newest operator request (its stamp, kind, accepted or why not):
    /// in the status, so `labrig episode` can say whether the loop took it.
    last_request: Option<serde_json::Value>,
    /// The status goes out this tick (a request was decided), not only every 20 ticks.
    status_due: bool,
    tick: Option<Tick>,
    /// The recorder said it takes no episode (a full disk): why. Starts wait while it does.
    recorder_refusal: Option<String>,
    /// The recorder refused this episode after it started: it ends.
    refused_episode: Option<String>,
    /// Why the loop itself ends the episode (the end event's note).
    end_note: String,
    /// Consecutive ticks the arm node has reported a fault.
    fault_ticks: u32,
    /// A policy rollout: the last recorded step was an operator's (a takeover,
    /// [`crate::takeover`]); the episode's takeovers and operator steps so far.
    operator_acting: bool,
    episode_takeovers: u64,
    episode_operator_steps: u64,
}

/// One window of the loop's figures (`window_stats`): its start, the summary's counts then,
/// and its own jitter and skew samples.
#[derive(Debug, Default)]
struct Window {
    began: Option<Instant>,
    at_start: [u64; 6],
    jitter_ns: Vec<i64>,
    skew_ns: Vec<i64>,
}

/// For this many ticks after the loop starts (1 s at 20 Hz) an episode does not start while a
/// camera has sent no frame yet.
const FIRST_FRAMES_TICKS: u64 = 20;

/// An arm fault reported this many ticks in a row (a quarter second) stops the episode; a
/// single refused command does not.
pub const ARM_FAULT_TICKS: u32 = 5;

impl RigLoop {
    /// A loop starting from the arm's first state.
    pub fn new(cfg: ControlConfig, kin: Fr3Kinematics, filter: SafetyFilter, robot: RobotState) -> RigLoop {
        let camera_names: Vec<&str> = cfg.cameras.iter().map(String::as_str).collect();
        RigLoop {
            period: Nanos::from_secs_rounded(cfg.period_s),
            stale_frame: Nanos::from_secs_rounded(cfg.stale_frame_s),
            max_action_age: Nanos::from_secs_rounded(cfg.max_action_age_s),
            book: FrameBook::new(&camera_names),
            next_seed: cfg.first_seed,
            cfg,
            kin,
            filter,
            robot,
            gripper: None,
            scene: Scene::default(),
            episodes: Episodes::default(),
            between: Between::Ready,
            summary: Summary::default(),
            commanded: None,
            gripper_target: 0.0,
            seq: 0,
            episode_id: String::new(),
            episode_seed: None,
            episode_instruction: String::new(),
            reset_started: 0,
            last_tick_ns: None,
            last_tick_wall: None,
            jitter_ns: Spread::default(),
            skew_ns: Spread::default(),
            started: Instant::now(),
            window: Window::default(),
            pending_request: None,
            last_request: None,
            status_due: false,
            tick: None,
            recorder_refusal: None,
            refused_episode: None,
            end_note: String::new(),
            fault_ticks: 0,
            operator_acting: false,
            episode_takeovers: 0,
            episode_operator_steps: 0,
        }
    }

    /// The recorder's status (`/recorder/status`, JSON): while it says `accepting: false` (a
    /// full disk) no episode starts and the rig stays Idle; an episode it refused ends.
    pub fn push_recorder_status(&mut self, json: &str) {
        let Ok(v) = serde_json::from_str::<serde_json::Value>(json) else {
            tracing::warn!("/recorder/status is not JSON");
            return;
        };
        let refusal = (v["accepting"] == serde_json::Value::Bool(false)).then(|| {
            format!(
                "the recorder takes no episode: {:.1} MB free, {:.1} MB needed",
                v["free_bytes"].as_f64().unwrap_or(0.0) / 1e6,
                v["needed_bytes"].as_f64().unwrap_or(0.0) / 1e6
            )
        });
        if refusal.is_some() != self.recorder_refusal.is_some() {
            match &refusal {
                Some(why) => tracing::error!("{why}: the rig stays Idle until there is space"),
                None => tracing::info!("the recorder takes episodes again"),
            }
        }
        self.recorder_refusal = refusal;
        let lost = v["state"] == "refused" || (v["state"] == "error" && v["disk_full"] == true);
        if lost && v["episode"].as_str() == Some(self.episode_id.as_str()) {
            self.refused_episode = Some(self.episode_id.clone());
        }
    }

    /// Why episodes cannot start now, if they cannot.
    pub fn recorder_refusal(&self) -> Option<&str> {
        self.recorder_refusal.as_deref()
    }

    pub fn period(&self) -> Nanos {
        self.period
    }

    /// The last tick's time, if there was one.
    pub fn last_tick(&self) -> Option<Nanos> {
        self.last_tick_ns.map(Nanos)
    }

    pub fn summary(&self) -> &Summary {
        &self.summary
    }

    pub fn state(&self) -> State {
        self.episodes.state()
    }

    pub fn recording(&self) -> bool {
        self.episodes.recording()
    }

    /// While recording, what a source sees of this tick (the pixels are the node's to add).
    pub fn view(&self) -> Option<TickView<'_>> {
        self.episodes.recording().then(|| TickView {
            tick: Nanos(self.tick().ns),
            step_index: self.episodes.steps,
            episode_id: &self.episode_id,
            robot: RobotState {
                gripper_position: self.gripper.as_ref().map_or(self.robot.gripper_position, |g| g.position),
                ..self.robot.clone()
            },
            scene: &self.scene.json,
            scene_seed: self.scene.seed,
            instruction: &self.episode_instruction,
            images: Vec::new(),
        })
    }

    /// Counts ticks the wall clock skipped (it runs on regardless of the loop).
    pub fn count_missed(&mut self, ticks: u64) {
        self.summary.missed_ticks += ticks;
    }

    /// On the sim's clock: whether a state stamped `t` starts a new tick (the arm node may
    /// publish states faster than the loop runs).
    pub fn is_new_tick(&self, t: Nanos) -> bool {
        self.last_tick_ns.is_none_or(|l| t.0 >= l + self.period.0 - TICK_TOLERANCE_NS)
    }

    /// Step 1: a tick at `tick` on the loop's clock, begun at wall time `wall`.
    pub fn begin_tick(&mut self, tick: Nanos, wall: Instant) {
        let tick_ns = tick.0;
        if let (Some(l), ClockKind::Sim) = (self.last_tick_ns, self.cfg.clock) {
            let missed = (tick_ns - l) / self.period.0 - 1;
            if missed > 0 {
                self.summary.missed_ticks += missed as u64;
            }
        }
        if let Some(w) = self.last_tick_wall {
            let jitter = (wall.duration_since(w).as_nanos() as i64 - self.period.0).abs();
            self.jitter_ns.push(jitter);
            self.window.jitter_ns.push(jitter);
        }
        let prev_ns = self.last_tick_ns.replace(tick_ns);
        self.last_tick_wall = Some(wall);
        self.summary.ticks += 1;
        let mut tick = Tick { ns: tick_ns, wall, prev_ns, step_start: 0, skip_command: false };
        tick.step_start = tick.now();
        self.tick = Some(tick);
    }

    fn tick(&self) -> Tick {
        self.tick.expect("begin_tick before the tick's other steps")
    }

    /// Step 2: the arm's newest state.
    pub fn set_robot(&mut self, state: RobotState) {
        self.robot = state;
    }

    pub fn push_gripper(&mut self, state: GripperState) {
        self.gripper = Some(state);
    }

    /// On the sim's clock the gripper's state of the tick's instant follows the arm's on its
    /// own topic: true while the newest one is older than the tick (wait for it, bounded).
    pub fn gripper_behind(&self) -> bool {
        let stamp = self.gripper.as_ref().map_or(i64::MIN, |g| Nanos::from(g.header.stamp).0);
        self.cfg.clock == ClockKind::Sim && self.gripper.is_some() && stamp < self.tick().ns
    }

    /// A `/sim/scene` message (JSON); a bad one is logged and ignored.
    pub fn push_scene(&mut self, json: &str) {
        match Scene::parse(json) {
            Ok(sc) => self.scene = sc,
            Err(e) => tracing::warn!("/sim/scene is not JSON: {e}"),
        }
    }

    pub fn push_frame(&mut self, camera: &str, frame: FrameTimes) {
        self.book.push(camera, frame);
    }

    /// On the sim's clock a camera that kept pace with the last tick has this tick's frame on
    /// its way: true while one is missing (wait for it, bounded, so a step never pairs this
    /// state with the last tick's image).
    pub fn frames_pending(&self) -> bool {
        let t = self.tick();
        self.cfg.clock == ClockKind::Sim
            && t.prev_ns.is_some_and(|p| !self.book.keeping_pace(Nanos(p), Nanos(t.ns)).is_empty())
    }

    /// The operator's session (`/rig/session`, JSON): its lab and operator name the next
    /// episodes' uuids (`<lab>+<user>+<time>`); empty ones leave the config's.
    pub fn push_session(&mut self, json: &str) {
        match serde_json::from_str::<labrig_msgs::session::Session>(json) {
            Ok(s) => {
                if !s.lab.is_empty() {
                    self.cfg.lab = s.lab;
                }
                if !s.operator.is_empty() {
                    self.cfg.user = s.operator;
                }
            }
            Err(e) => tracing::warn!("/rig/session: not a session ({e}): the uuids keep their lab and user"),
        }
    }

    /// An operator's request (`/rig/request`); the newest one of a tick wins (an older one of
    /// the same tick is reported as superseded). Its header stamp identifies it in the status.
    pub fn push_request(&mut self, event: &EpisodeEvent) {
        let stamp = Nanos::from(event.header.stamp).0;
        match event.kind() {
            Ok(k) => {
                if let Some((old, _, old_stamp)) = self.pending_request.replace((k, event.note.clone(), stamp)) {
                    self.decided(old_stamp, old, Err(RequestRefused::Superseded));
                }
            }
            Err(e) => {
                tracing::warn!("/rig/request: {e}");
                self.decided(stamp, EpisodeEventKind::Stop, Err(RequestRefused::NotARequest(e)));
            }
        }
    }

    /// Records what became of a request, for the status.
    fn decided(&mut self, stamp: i64, kind: EpisodeEventKind, verdict: Result<(), RequestRefused>) {
        if let Err(why) = &verdict {
            tracing::warn!(?kind, "operator request refused: {why}");
        }
        self.last_request = Some(serde_json::json!({
            "stamp_ns": stamp,
            "kind": format!("{kind:?}"),
            "accepted": verdict.is_ok(),
            "reason": verdict.err().map(|why| why.to_string()),
        }));
        self.status_due = true;
    }

    /// Lockstep after `/sim/reset`: the state after the rebuild is the new scene's first tick,
    /// and its scene message may trail it on its own topic. `Some(seed)` while it is due and
    /// not here yet (wait for it, bounded).
    pub fn scene_due(&self) -> Option<u64> {
        match self.between {
            Between::Reseeding { seed, asked_at }
                if self.cfg.clock == ClockKind::Sim && self.tick().ns > asked_at && self.scene.seed != Some(seed) =>
            {
                Some(seed)
            }
            _ => None,
        }
    }

    /// Step 3: idle with the episodes asked for done: the loop ends.
    pub fn done(&self) -> bool {
        self.episodes.state() == State::Idle
            && self.cfg.episodes > 0
            && self.summary.episodes.len() as u64 >= self.cfg.episodes
    }

    /// Step 4: this tick's episode event, if any, and its effects.
    pub fn decide(
        &mut self,
        mut source: Option<&mut (dyn ActionSource + '_)>,
        out: &mut dyn RigOutputs,
    ) -> Result<(), LoopError> {
        let tick_ns = self.tick().ns;
        let request = self.pending_request.take();
        let (mut event, mut instruction) = match &request {
            // Only the loop says the arm is home: an operator's Reset means "go home", which
            // applies while idle (while resetting the arm is on its way already).
            Some((EpisodeEventKind::Reset, _, stamp)) if self.episodes.state() != State::Idle => {
                let why = RequestRefused::ResetWhileBusy { state: self.episodes.state() };
                self.decided(*stamp, EpisodeEventKind::Reset, Err(why));
                (None, String::new())
            }
            Some((k, note, _)) => (Some(*k), note.clone()),
            None => (None, String::new()),
        };
        // The request still waiting for its verdict (decided below, when the event is applied).
        let mut asked = match request {
            Some((k, _, stamp)) if event == Some(k) => Some((k, stamp)),
            _ => None,
        };
        if instruction.is_empty() {
            instruction.clone_from(&self.scene.instruction);
        }
        let state = self.episodes.state();
        if let Between::Reseeding { seed, asked_at } = self.between {
            if self.scene.seed == Some(seed) {
                // This tick starts the episode, from the new scene's first state.
                self.between = Between::Ready;
                self.commanded = None;
            } else if tick_ns - asked_at > 30_000_000_000 {
                return Err(LoopError::SceneTimeout { seed });
            }
        }
        if event == Some(EpisodeEventKind::Start) && state == State::Idle && self.recorder_refusal.is_some() {
            let why = RequestRefused::RecorderRefuses { refusal: self.recorder_refusal.clone().unwrap_or_default() };
            self.summary.starts_refused += 1;
            event = None;
            match asked.take() {
                // decided() logs it.
                Some((k, stamp)) => self.decided(stamp, k, Err(why)),
                None => tracing::warn!("{why}"),
            }
        }
        if self.recorder_refusal.is_none()
            && event.is_none()
            && state == State::Idle
            && self.cfg.auto_start
            && self.between == Between::Ready
        {
            // Not before the source has an action for now (after a scene rebuild it may lag).
            let age_ns = self.max_action_age.0;
            let source_ready = self.cfg.clock == ClockKind::Sim
                || source.as_mut().is_none_or(|s| s.ready(Nanos(tick_ns), Nanos(age_ns)));
            // Nor while a camera that has been sending lags (after a scene rebuild, say), nor,
            // for the loop's first second, while a camera has sent nothing yet (its first frames
            // may still be on their way as the rig comes up): an episode's first steps have
            // every camera's frame. A camera that never sends does not hold the rig up longer.
            let at = self.book.at(Nanos(tick_ns), self.stale_frame);
            let starting = self.summary.ticks < FIRST_FRAMES_TICKS;
            let lagging: Vec<String> =
                at.stale.into_iter().chain(at.missing.into_iter().filter(|_| starting)).collect();
            if !lagging.is_empty() && self.summary.ticks.is_multiple_of(40) {
                let seen = self.book.at(Nanos(i64::MAX), Nanos(i64::MAX)).refs;
                let ages: Vec<f64> = seen.iter().map(|r| (tick_ns - r.capture_ns) as f64 / 1e6).collect();
                tracing::warn!(cameras = ?lagging, ages_ms = ?ages, "waiting for fresh frames before starting the episode");
            }
            if !source_ready || !lagging.is_empty() {
            } else if self.cfg.reseed {
                if self.scene.seed == Some(self.next_seed) && self.episode_seed.is_none_or(|s| s != self.next_seed) {
                    event = Some(EpisodeEventKind::Start);
                } else {
                    out.reset_scene(self.next_seed)?;
                    self.between = Between::Reseeding { seed: self.next_seed, asked_at: tick_ns };
                    // Lockstep: no step of the old scene after this; the next state is the new one's.
                    if let Some(t) = self.tick.as_mut() {
                        t.skip_command = self.cfg.clock == ClockKind::Sim;
                    }
                }
            } else {
                event = Some(EpisodeEventKind::Start);
            }
        }
        self.fault_ticks = if self.robot.mode == RobotState::MODE_FAULT { self.fault_ticks + 1 } else { 0 };
        if event.is_none() && self.episodes.recording() && self.fault_ticks >= ARM_FAULT_TICKS {
            // The arm node reports a fault that lasts (a reflex, the arm or the sim bridge gone;
            // not one refused command): the arm node holds; the episode ends here, named.
            tracing::error!(episode = %self.episode_id, fault = %self.robot.fault, "the arm faulted: the episode stops");
            self.summary.arm_faults += 1;
            event = Some(EpisodeEventKind::Stop);
            self.end_note = format!("the arm faulted: {}", self.robot.fault);
        }
        if event.is_none() && self.episodes.recording() && self.refused_episode.as_deref() == Some(&self.episode_id) {
            tracing::error!(episode = %self.episode_id, "the recorder refused the episode: it stops");
            self.refused_episode = None;
            self.end_note = "the recorder could not record it (a full disk)".into();
            event = Some(EpisodeEventKind::Stop);
        }
        if event.is_none() && self.episodes.recording() {
            let verdict = source.as_ref().map_or(Verdict::Running, |s| s.verdict(Nanos(tick_ns)));
            event = match verdict {
                Verdict::Succeeded => Some(EpisodeEventKind::Success),
                Verdict::Failed { why } => {
                    if let Some(why) = why {
                        tracing::warn!(episode = %self.episode_id, "the episode failed: {why}");
                        self.end_note = why;
                    }
                    Some(EpisodeEventKind::Failure)
                }
                Verdict::Running if self.episodes.steps >= self.cfg.max_steps => {
                    tracing::warn!(steps = self.episodes.steps, "step budget spent: the episode failed");
                    self.end_note = format!("the step budget ({} steps) was spent", self.cfg.max_steps);
                    Some(EpisodeEventKind::Failure)
                }
                Verdict::Running => None,
            };
        }
        if let State::Resetting(_) = state {
            let away = |q: &f64, h: f64| (q - h).abs();
            let home = self
                .robot
                .joint_positions
                .iter()
                .zip(DROID_RESET_POSE)
                .all(|(q, h)| away(q, h) < self.cfg.home_tolerance_rad);
            if home {
                event = Some(EpisodeEventKind::Reset);
            } else if tick_ns - self.reset_started > (self.cfg.reset_timeout_s * 1e9) as i64 {
                let worst_rad = self
                    .robot
                    .joint_positions
                    .iter()
                    .zip(DROID_RESET_POSE)
                    .map(|(q, h)| away(q, h))
                    .fold(0.0, f64::max);
                return Err(LoopError::NotHome {
                    timeout_s: self.cfg.reset_timeout_s,
                    worst_rad,
                    mode: self.robot.mode,
                    fault: self.robot.fault.clone(),
                });
            }
        }
        let applied = event.map(|kind| (kind, self.apply(kind, &instruction, source, out)));
        if let Some((k, stamp)) = asked {
            let verdict = match applied {
                Some((kind, verdict)) if kind == k => verdict,
                Some((kind, _)) => Err(RequestRefused::Overridden { applied: kind }),
                None => Err(RequestRefused::NotApplied),
            };
            self.decided(stamp, k, verdict);
        }
        Ok(())
    }

    /// The summary's record of the episode that just ended.
    fn report_episode(&mut self, outcome: &str) {
        self.summary.episodes.push(EpisodeReport {
            episode_id: self.episode_id.clone(),
            seed: self.episode_seed,
            instruction: self.episode_instruction.clone(),
            outcome: outcome.into(),
            steps: self.episodes.steps,
            takeovers: self.episode_takeovers,
            operator_steps: self.episode_operator_steps,
        });
    }

    fn publish_event(&self, out: &mut dyn RigOutputs, kind: EpisodeEventKind, note: &str, t: i64) {
        let ev = EpisodeEvent {
            header: Header { stamp: Nanos(t).into(), frame_id: String::new() },
            kind: kind as u8,
            episode_id: self.episode_id.clone(),
            note: note.to_owned(),
            ..Default::default()
        };
        if let Err(e) = out.episode(ev) {
            tracing::error!("/rig/episode: {e}");
        }
    }

    fn apply(
        &mut self,
        kind: EpisodeEventKind,
        instruction: &str,
        source: Option<&mut (dyn ActionSource + '_)>,
        out: &mut dyn RigOutputs,
    ) -> Result<(), RequestRefused> {
        let tick_ns = self.tick().ns;
        match self.episodes.on(kind) {
            Ok(Effect::StartRecording) => {
                self.episode_id = episode_uuid(&self.cfg.lab, &self.cfg.user, &self.summary.episodes);
                self.episode_seed = self.scene.seed;
                (self.operator_acting, self.episode_takeovers, self.episode_operator_steps) = (false, 0, 0);
                if let Some(s) = source {
                    s.restart(Nanos(tick_ns));
                }
                self.publish_event(out, kind, instruction, tick_ns);
                tracing::info!(episode = %self.episode_id, seed = ?self.scene.seed, %instruction, "episode started");
                self.episode_instruction = instruction.to_owned();
            }
            Ok(Effect::EndRecording(ending)) => {
                let note = std::mem::take(&mut self.end_note);
                self.publish_event(out, kind, &note, tick_ns);
                let outcome = match ending {
                    Ending::Success => "success",
                    Ending::Failure => "failure",
                    Ending::Discarded => "discarded",
                    Ending::Homing => "none",
                };
                tracing::info!(episode = %self.episode_id, steps = self.episodes.steps, outcome, "episode ended");
                self.report_episode(outcome);
                self.operator_acting = false;
                self.reset_started = tick_ns;
                if self.cfg.reseed {
                    self.next_seed += 1;
                }
            }
            Ok(Effect::Ready) => {
                self.publish_event(out, kind, "", tick_ns);
                tracing::info!("the arm is home");
            }
            Ok(Effect::GoHome) => {
                self.reset_started = tick_ns;
                tracing::info!("the operator sent the arm home");
            }
            Err(refused) => {
                tracing::warn!("{refused}");
                return Err(refused.into());
            }
        }
        Ok(())
    }

    /// Step 5: the tick's action through the safety layer, the commands, the Step record.
    pub fn act(
        &mut self,
        source: Option<&mut (dyn ActionSource + '_)>,
        out: &mut dyn RigOutputs,
    ) -> Result<(), LoopError> {
        let tick = self.tick();
        let tick_ns = tick.ns;
        let policy_start = tick.now();
        let mut acting_changed = false;
        let robot = &self.robot;
        let view =
            ArmView { measured: robot.joint_positions, commanded: self.commanded.unwrap_or(robot.joint_positions) };
        let (proposal, source_kind) = match self.episodes.state() {
            State::Recording => match source {
                Some(s) => match s.action(Nanos(tick_ns), self.max_action_age) {
                    Ok(p) => (Some(p), s.kind()),
                    Err(e) => {
                        tracing::warn!("{e}: holding");
                        self.summary.held_ticks += 1;
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
                (Some(Proposal { command: cmd, movement_enabled: true, chunk: None }), Step::SOURCE_NONE)
            }
            State::Idle => (None, Step::SOURCE_NONE),
        };
        let gripper_target = self.gripper_target;
        let hold = || ArmCommand {
            mode: ArmCommandMode::JointPosition as u8,
            joint_position: view.commanded,
            gripper_position: gripper_target,
            ..Default::default()
        };
        let (mut wanted, mut moving, mut chunk) = match proposal.filter(|p| p.movement_enabled) {
            Some(p) => (p.command, true, p.chunk),
            None => (hold(), false, None),
        };
        let safe = match self.filter.filter(&wanted, &view, Nanos(tick_ns)) {
            Ok(s) => s,
            Err(refusal) => {
                moving = false;
                chunk = None;
                // The record holds what was done (a hold), never the refused values.
                wanted = hold();
                self.summary.refused += 1;
                self.summary.held_ticks += 1;
                tracing::warn!("refused the action: {refusal}; holding");
                self.filter.filter(&wanted, &view, Nanos(tick_ns)).map_err(LoopError::CannotHold)?
            }
        };
        let action = action_dict(&self.kin, &self.robot, self.gripper.as_ref(), &wanted, &safe.joints, safe.gripper);
        let sleep_start = tick.now();
        self.seq += 1;
        let stamp: labrig_msgs::builtin_interfaces::Time = Nanos(tick_ns).into();
        let control_start = tick.now();
        if tick.skip_command {
            return Ok(());
        }
        if let Err(e) = out.gripper(GripperCommand {
            header: Header { stamp, frame_id: String::new() },
            position: safe.gripper,
            speed: 1.0,
            force: 0.5,
            ..Default::default()
        }) {
            tracing::warn!("/gripper/command: {e}");
        }
        out.arm(ArmCommand {
            header: Header { stamp, frame_id: "base".into() },
            mode: ArmCommandMode::JointPosition as u8,
            joint_position: safe.joints,
            gripper_position: safe.gripper,
            seq: self.seq,
            ..Default::default()
        })?;
        self.commanded = Some(safe.joints);
        self.gripper_target = safe.gripper;
        if self.episodes.recording() {
            let frames = self.book.at(Nanos(tick_ns), self.stale_frame);
            if !frames.missing.is_empty() || !frames.stale.is_empty() {
                tracing::debug!(missing = ?frames.missing, stale = ?frames.stale, "cameras");
            }
            self.summary.steps_missing_frames += u64::from(!frames.missing.is_empty());
            self.summary.steps_stale_frames += u64::from(!frames.stale.is_empty());
            self.skew_ns.push(frames.skew_ns);
            self.window.skew_ns.push(frames.skew_ns);
            let times = TickTimes {
                tick_ns,
                step_start: tick.step_start,
                policy_start,
                sleep_start,
                control_start,
                step_end: tick.now(),
            };
            let obs = Observation { robot: self.robot.clone(), gripper: self.gripper.clone(), frames };
            let decision = Decision { action, source: source_kind, movement_enabled: moving, chunk };
            out.step(make_step(&self.episode_id, self.episodes.steps, &obs, &decision, &times))?;
            self.episodes.tick();
            // A policy rollout's step by another source is an operator's (a takeover).
            let operator =
                matches!(self.cfg.source, SourceKind::Policy | SourceKind::Remote) && Step::is_operator(source_kind);
            if operator && !self.operator_acting {
                self.episode_takeovers += 1;
                self.summary.takeovers += 1;
            }
            self.episode_operator_steps += u64::from(operator);
            self.summary.operator_steps += u64::from(operator);
            acting_changed = operator != self.operator_acting;
            self.operator_acting = operator;
        }
        // Who acts goes out at once when it changes (the station shows the operator's turn).
        if self.summary.ticks.is_multiple_of(20) || acting_changed || std::mem::take(&mut self.status_due) {
            let acting = (matches!(self.cfg.source, SourceKind::Policy | SourceKind::Remote)
                && self.episodes.recording())
            .then_some(if self.operator_acting { "operator" } else { "policy" });
            let status = json!({
                "acting": acting,
                "takeovers": self.episode_takeovers,
                "operator_steps": self.episode_operator_steps,
                "state": format!("{:?}", self.episodes.state()),
                "recorder_refusal": self.recorder_refusal,
                "last_request": self.last_request,
                "episode": self.episode_id,
                "steps": self.episodes.steps,
                "episodes": self.summary.episodes.len(),
                "ticks": self.summary.ticks,
                "held_ticks": self.summary.held_ticks,
                "missed_ticks": self.summary.missed_ticks,
                "seconds": self.started.elapsed().as_secs_f64(),
            });
            let _ = out.status(status.to_string());
        }
        Ok(())
    }

    /// The window's figures once `window_s` has passed since it began at wall time (the first
    /// call begins the first window), and a new window begins; `None` before. The counts are
    /// the window's own (the summary's growth over it).
    pub fn take_window(&mut self, wall: Instant) -> Option<serde_json::Value> {
        let window_s = self.cfg.window_s;
        let counts = self.window_counts();
        let Some(began) = self.window.began else {
            self.window = Window { began: Some(wall), at_start: counts, ..Window::default() };
            return None;
        };
        let length = wall.saturating_duration_since(began).as_secs_f64();
        if length < window_s {
            return None;
        }
        let mut done =
            std::mem::replace(&mut self.window, Window { began: Some(wall), at_start: counts, ..Window::default() });
        let d = |i: usize| counts[i] - done.at_start[i];
        Some(json!({
            "end_s": wall.saturating_duration_since(self.started).as_secs_f64(),
            "seconds": length,
            "ticks": d(0),
            "missed_ticks": d(1),
            "held_ticks": d(2),
            "steps_missing_frames": d(3),
            "steps_stale_frames": d(4),
            "episodes": d(5),
            "jitter_us": percentiles_us(&mut done.jitter_ns),
            "skew_us": percentiles_us(&mut done.skew_ns),
        }))
    }

    /// The summary's counts a window reports the growth of: ticks, missed, held, steps missing
    /// and stale frames, episodes ended.
    fn window_counts(&self) -> [u64; 6] {
        let s = &self.summary;
        [s.ticks, s.missed_ticks, s.held_ticks, s.steps_missing_frames, s.steps_stale_frames, s.episodes.len() as u64]
    }

    /// The loop stops: an episode still open ends as a failure (so the recorder closes it);
    /// the run's summary.
    pub fn finish(self, out: &mut dyn RigOutputs) -> Summary {
        self.finish_because(out, "the control loop stopped")
    }

    /// [`RigLoop::finish`], the open episode's Stop saying `why`.
    pub fn finish_because(mut self, out: &mut dyn RigOutputs, why: &str) -> Summary {
        if self.episodes.recording() {
            let t = self.last_tick_ns.unwrap_or(0);
            let _ = self.episodes.on(EpisodeEventKind::Stop);
            self.publish_event(out, EpisodeEventKind::Stop, why, t);
            // The recorder files it (as a failure): the summary lists it as every other.
            self.report_episode("failure");
        }
        self.summary.jitter_us = self.jitter_ns.percentiles_us();
        self.summary.skew_us = self.skew_ns.percentiles_us();
        self.summary.seconds = self.started.elapsed().as_secs_f64();
        self.summary
    }
}

#[cfg(test)]
mod tests {
    //! The loop driven tick by tick on a manual clock, with an in-memory action source and
    //! outputs: no processes, no DDS.
    use super::*;
    use crate::config::SourceKind;
    use crate::source::SourceError;
    use labrig_arm::TcpOffset;
    use labrig_arm::ik::{Ik, IkConfig};
    use labrig_arm::safety::SafetyConfig;
    use std::collections::VecDeque;

    const PERIOD: i64 = 50_000_000;

    #[derive(Debug, Default)]
    struct Sent {
        arm: Vec<ArmCommand>,
        gripper: Vec<GripperCommand>,
        steps: Vec<Step>,
        events: Vec<EpisodeEvent>,
        resets: Vec<u64>,
        statuses: Vec<serde_json::Value>,
    }

    impl Sent {
        fn kinds(&self) -> Vec<EpisodeEventKind> {
            self.events.iter().map(|e| e.kind().unwrap()).collect()
        }
    }

    impl RigOutputs for Sent {
        fn arm(&mut self, cmd: ArmCommand) -> Result<(), RosError> {
            self.arm.push(cmd);
            Ok(())
        }
        fn gripper(&mut self, cmd: GripperCommand) -> Result<(), RosError> {
            self.gripper.push(cmd);
            Ok(())
        }
        fn step(&mut self, step: Step) -> Result<(), RosError> {
            self.steps.push(step);
            Ok(())
        }
        fn episode(&mut self, event: EpisodeEvent) -> Result<(), RosError> {
            self.events.push(event);
            Ok(())
        }
        fn reset_scene(&mut self, seed: u64) -> Result<(), RosError> {
            self.resets.push(seed);
            Ok(())
        }
        fn status(&mut self, json: String) -> Result<(), RosError> {
            self.statuses.push(serde_json::from_str(&json).unwrap());
            Ok(())
        }
    }

    /// A source that hands out queued actions and a verdict the test sets.
    #[derive(Debug, Default)]
    struct Queue {
        actions: VecDeque<Result<Proposal, SourceError>>,
        verdict: Option<Verdict>,
        restarts: u32,
        /// Who acts, per action asked for (a takeover's source); the scripted expert when none.
        kinds: VecDeque<u8>,
        kind: Option<u8>,
    }

    impl ActionSource for Queue {
        fn name(&self) -> &'static str {
            "test queue"
        }
        fn kind(&self) -> u8 {
            self.kind.unwrap_or(Step::SOURCE_SCRIPTED)
        }
        fn poll(&mut self) -> Result<(), RosError> {
            Ok(())
        }
        fn has(&self, _tick: Nanos) -> bool {
            true
        }
        fn action(&mut self, _tick: Nanos, _max_age: Nanos) -> Result<Proposal, SourceError> {
            if let Some(k) = self.kinds.pop_front() {
                self.kind = Some(k);
            }
            self.actions.pop_front().unwrap_or(Err(SourceError::Silent { from: "test queue" }))
        }
        fn verdict(&self, _tick: Nanos) -> Verdict {
            self.verdict.clone().unwrap_or(Verdict::Running)
        }
        fn restart(&mut self, _start: Nanos) {
            self.restarts += 1;
        }
    }

    fn joints_at(offset: f64) -> [f64; 7] {
        let mut q = DROID_RESET_POSE;
        q[0] += offset;
        q
    }

    fn state(joints: [f64; 7]) -> RobotState {
        RobotState { joint_positions: joints, ..Default::default() }
    }

    fn rig(max_steps: u64) -> RigLoop {
        let cfg = ControlConfig {
            source: SourceKind::Hold,
            clock: ClockKind::Sim,
            auto_start: false,
            reseed: false,
            episodes: 1,
            max_steps,
            cameras: vec![],
            frames_namespace: None,
            ..ControlConfig::default()
        };
        cfg.validate().unwrap();
        let kin = Fr3Kinematics::from_urdf_file(&labrig_arm::urdf_path(None), TcpOffset::ROBOTIQ_2F85).unwrap();
        let filter = SafetyFilter::new(
            Ik::new(kin.clone(), IkConfig::default()),
            SafetyConfig { max_command_age_s: 0.0, ..SafetyConfig::default() },
        )
        .unwrap();
        RigLoop::new(cfg, kin, filter, state(DROID_RESET_POSE))
    }

    fn go(joints: [f64; 7]) -> Result<Proposal, SourceError> {
        let command =
            ArmCommand { mode: ArmCommandMode::JointPosition as u8, joint_position: joints, ..Default::default() };
        Ok(Proposal { command, movement_enabled: true, chunk: None })
    }

    /// One tick at `k` periods with the arm where it was last commanded (a perfect arm).
    fn tick(rig: &mut RigLoop, k: i64, source: &mut Queue, out: &mut Sent) {
        if let Some(last) = out.arm.last() {
            rig.set_robot(state(last.joint_position));
        }
        rig.begin_tick(Nanos(k * PERIOD), Instant::now());
        rig.decide(Some(source), out).unwrap();
        rig.act(Some(source), out).unwrap();
    }

    fn request(rig: &mut RigLoop, kind: EpisodeEventKind, note: &str) {
        rig.push_request(&EpisodeEvent { kind: kind as u8, note: note.into(), ..Default::default() });
    }

    /// An operator's request gets a verdict in the status the tick it is decided, by its
    /// stamp: a Success while idle is refused with the reason, a Start taken.
    #[test]
    fn a_request_is_answered_in_the_status_by_its_stamp() {
        let mut rig = rig(100);
        let (mut src, mut out) = (Queue::default(), Sent::default());
        tick(&mut rig, 0, &mut src, &mut out);
        let stamped = |kind: EpisodeEventKind, ns: i64| EpisodeEvent {
            header: Header { stamp: Nanos(ns).into(), frame_id: String::new() },
            kind: kind as u8,
            ..Default::default()
        };
        rig.push_request(&stamped(EpisodeEventKind::Success, 111));
        tick(&mut rig, 1, &mut src, &mut out);
        let r = &out.statuses.last().expect("a status the tick it was decided")["last_request"];
        assert_eq!(
            (r["stamp_ns"].as_i64(), r["kind"].as_str(), r["accepted"].as_bool()),
            (Some(111), Some("Success"), Some(false))
        );
        assert!(r["reason"].as_str().is_some_and(|w| !w.is_empty()), "{r}");
        rig.push_request(&stamped(EpisodeEventKind::Start, 222));
        src.actions.push_back(go(joints_at(0.0)));
        tick(&mut rig, 2, &mut src, &mut out);
        let r = &out.statuses.last().unwrap()["last_request"];
        assert_eq!((r["stamp_ns"].as_i64(), r["accepted"].as_bool()), (Some(222), Some(true)), "{r}");
    }

    /// A policy rollout: a run of steps by another source is an operator's takeover; the
    /// loop counts them and their steps per episode and in the run, and its status says who
    /// acts the tick it changes.
    #[test]
    fn a_policy_rollouts_operator_steps_and_takeovers_are_counted_and_reported() {
        let mut rig = rig(100);
        rig.cfg.source = SourceKind::Policy;
        let (mut src, mut out) = (Queue::default(), Sent::default());
        tick(&mut rig, 0, &mut src, &mut out);
        request(&mut rig, EpisodeEventKind::Start, "");
        const P: u8 = Step::SOURCE_POLICY;
        const T: u8 = Step::SOURCE_TELEOP;
        let who = [P, P, T, T, P, T, P];
        for (k, &w) in who.iter().enumerate() {
            src.kinds.push_back(w);
            src.actions.push_back(go(joints_at(0.001 * k as f64)));
            tick(&mut rig, 1 + k as i64, &mut src, &mut out);
        }
        assert_eq!(out.steps.iter().map(|s| s.action_source).collect::<Vec<_>>(), who);
        // The first status goes out the tick the Start request was decided (taken), then one
        // per change of who acts.
        assert_eq!(out.statuses[0]["last_request"]["kind"], "Start", "{:?}", out.statuses[0]);
        assert_eq!(out.statuses[0]["last_request"]["accepted"], true, "{:?}", out.statuses[0]);
        let acting: Vec<&str> = out.statuses.iter().filter_map(|s| s["acting"].as_str()).collect();
        assert_eq!(
            acting,
            ["policy", "operator", "policy", "operator", "policy"],
            "one status per change: {:?}",
            out.statuses
        );
        let last = out.statuses.last().unwrap();
        assert_eq!((last["takeovers"].as_u64(), last["operator_steps"].as_u64()), (Some(2), Some(3)));
        src.verdict = Some(Verdict::Succeeded);
        tick(&mut rig, 9, &mut src, &mut out);
        let report = &rig.summary().episodes[0];
        assert_eq!((report.takeovers, report.operator_steps), (2, 3));
        assert_eq!((rig.summary().takeovers, rig.summary().operator_steps), (2, 3));
    }

    #[test]
    fn idle_it_holds_the_arm_and_records_nothing() {
        let (mut rig, mut src, mut out) = (rig(100), Queue::default(), Sent::default());
        src.actions.push_back(go(joints_at(0.01)));
        for k in 0..3 {
            tick(&mut rig, k, &mut src, &mut out);
        }
        assert_eq!(out.arm.len(), 3, "the arm is commanded every tick, holding");
        assert!(out.arm.iter().all(|c| c.joint_position == DROID_RESET_POSE));
        assert!(out.steps.is_empty() && out.events.is_empty());
        assert_eq!(src.actions.len(), 1, "idle, the source is not asked");
        assert_eq!(out.arm.iter().map(|c| c.seq).collect::<Vec<_>>(), [1, 2, 3]);
    }

    #[test]
    fn the_operators_session_names_the_next_episodes_uuid() {
        let (mut rig, mut src, mut out) = (rig(100), Queue::default(), Sent::default());
        tick(&mut rig, 0, &mut src, &mut out);
        rig.push_session(r#"{"operator": "alice", "lab": "AUTOLab", "task": "wipe"}"#);
        rig.push_session("not json"); // refused, the session above stays
        request(&mut rig, EpisodeEventKind::Start, "");
        src.actions.push_back(go(joints_at(0.01)));
        tick(&mut rig, 1, &mut src, &mut out);
        assert!(out.events[0].episode_id.starts_with("AUTOLab+alice+"), "{}", out.events[0].episode_id);
    }

    #[test]
    fn an_episode_starts_is_judged_goes_home_and_ends_the_run() {
        let (mut rig, mut src, mut out) = (rig(100), Queue::default(), Sent::default());
        tick(&mut rig, 0, &mut src, &mut out);
        request(&mut rig, EpisodeEventKind::Start, "put the cube in the bin");
        src.actions.extend([go(joints_at(0.01)), go(joints_at(0.02)), go(joints_at(0.03))]);
        for k in 1..4 {
            tick(&mut rig, k, &mut src, &mut out);
        }
        assert_eq!(out.kinds(), [EpisodeEventKind::Start]);
        assert_eq!(out.events[0].note, "put the cube in the bin");
        assert_eq!(src.restarts, 1);
        assert_eq!(out.steps.len(), 3);
        assert_eq!(out.steps.iter().map(|s| s.step_index).collect::<Vec<_>>(), [0, 1, 2]);
        assert!(out.steps.iter().all(|s| s.movement_enabled && s.episode_id == out.events[0].episode_id));
        assert!((out.arm.last().unwrap().joint_position[0] - joints_at(0.03)[0]).abs() < 1e-12);
        // Each step records the state it acted on and the action it sent.
        assert_eq!(out.steps[1].robot_state.joint_positions, joints_at(0.01));
        assert_eq!(out.steps[1].action.joint_position, joints_at(0.02));
        assert_eq!(Nanos::from(out.steps[2].header.stamp).0, 3 * PERIOD);

        src.verdict = Some(Verdict::Succeeded);
        tick(&mut rig, 4, &mut src, &mut out);
        assert_eq!(out.kinds(), [EpisodeEventKind::Start, EpisodeEventKind::Success]);
        assert_eq!(out.steps.len(), 3, "no step after the verdict");
        assert_eq!(rig.summary().episodes[0].outcome, "success");
        assert_eq!(rig.summary().episodes[0].steps, 3);
        assert!(matches!(rig.state(), State::Resetting(_)));
        assert!(!rig.done(), "not done before the arm is home");
        // Resetting: the arm is sent home in steps the safety layer allows, then Reset.
        let mut k = 5;
        while !rig.done() {
            tick(&mut rig, k, &mut src, &mut out);
            k += 1;
            assert!(k < 200, "never home: {:?}", out.arm.last());
        }
        assert_eq!(out.kinds().last(), Some(&EpisodeEventKind::Reset));
        assert_eq!(rig.state(), State::Idle);
        let summary = rig.finish(&mut out);
        assert_eq!(summary.episodes.len(), 1);
        assert_eq!(out.kinds().len(), 3, "finish adds no Stop when no episode is open");
    }

    #[test]
    fn an_operators_reset_while_idle_sends_the_arm_home_and_nothing_is_recorded() {
        let (mut rig, mut src, mut out) = (rig(100), Queue::default(), Sent::default());
        // The arm away from home, idle.
        rig.set_robot(state(joints_at(0.3)));
        out.arm.push(ArmCommand { joint_position: joints_at(0.3), ..Default::default() });
        tick(&mut rig, 0, &mut src, &mut out);
        // A Reset from the operator: the loop drives it home in safe steps, then says Reset.
        request(&mut rig, EpisodeEventKind::Reset, "");
        tick(&mut rig, 1, &mut src, &mut out);
        assert!(matches!(rig.state(), State::Resetting(_)), "{:?}", rig.state());
        // A second Reset on the way is ignored (only the loop says the arm is home).
        request(&mut rig, EpisodeEventKind::Reset, "");
        let mut k = 2;
        while rig.state() != State::Idle {
            tick(&mut rig, k, &mut src, &mut out);
            k += 1;
            assert!(k < 400, "never home: {:?}", out.arm.last());
        }
        assert!(k > 4, "home took more than a tick or two from 0.3 rad away");
        let last = out.arm.last().unwrap().joint_position;
        assert!(last.iter().zip(DROID_RESET_POSE).all(|(q, h)| (q - h).abs() < 0.02), "{last:?}");
        assert_eq!(out.kinds(), [EpisodeEventKind::Reset], "no episode, only the arm home");
        assert!(out.steps.is_empty() && rig.summary().episodes.is_empty());
    }

    #[test]
    fn a_nan_action_is_refused_and_recorded_as_the_hold_it_became() {
        let (mut rig, mut src, mut out) = (rig(100), Queue::default(), Sent::default());
        request(&mut rig, EpisodeEventKind::Start, "");
        let mut nan = joints_at(0.01);
        nan[3] = f64::NAN;
        src.actions.extend([go(joints_at(0.01)), go(nan)]);
        tick(&mut rig, 0, &mut src, &mut out);
        tick(&mut rig, 1, &mut src, &mut out);
        assert_eq!(rig.summary().refused, 1);
        assert_eq!(rig.summary().held_ticks, 1);
        let held = out.arm.last().unwrap();
        assert_eq!(held.joint_position, joints_at(0.01), "the arm holds its last good target");
        let step = out.steps.last().unwrap();
        assert!(!step.movement_enabled);
        assert_eq!(step.action.joint_position, joints_at(0.01));
        assert!(step.action.target_cartesian_position.iter().all(|v| v.is_finite()), "{:?}", step.action);
    }

    #[test]
    fn a_stale_or_missing_action_holds_the_arm() {
        let (mut rig, mut src, mut out) = (rig(100), Queue::default(), Sent::default());
        request(&mut rig, EpisodeEventKind::Start, "");
        src.actions.extend([
            go(joints_at(0.01)),
            Err(SourceError::Stale { from: "test queue", age_ms: 400.0, limit_ms: 150.0 }),
        ]);
        for k in 0..3 {
            tick(&mut rig, k, &mut src, &mut out);
        }
        assert_eq!(rig.summary().held_ticks, 2, "stale, then silent");
        assert_eq!(rig.summary().refused, 0, "nothing reached the safety layer to refuse");
        assert!(out.arm[1..].iter().all(|c| c.joint_position == joints_at(0.01)));
        assert_eq!(out.steps.iter().map(|s| s.movement_enabled).collect::<Vec<_>>(), [true, false, false]);
        assert!(out.steps.iter().all(|s| s.action_source == Step::SOURCE_SCRIPTED));
    }

    #[test]
    fn the_step_budget_fails_an_episode_and_a_stop_closes_an_open_one() {
        let (mut rig, mut src, mut out) = (rig(2), Queue::default(), Sent::default());
        request(&mut rig, EpisodeEventKind::Start, "");
        src.actions.extend([go(joints_at(0.01)), go(joints_at(0.02)), go(joints_at(0.03))]);
        for k in 0..3 {
            tick(&mut rig, k, &mut src, &mut out);
        }
        assert_eq!(out.kinds(), [EpisodeEventKind::Start, EpisodeEventKind::Failure]);
        assert_eq!(out.steps.len(), 2);
        assert_eq!(rig.summary().episodes[0].outcome, "failure");

        let (mut rig, mut src, mut out) = (self::rig(100), Queue::default(), Sent::default());
        request(&mut rig, EpisodeEventKind::Start, "");
        tick(&mut rig, 0, &mut src, &mut out);
        let summary = rig.finish(&mut out);
        assert_eq!(out.kinds(), [EpisodeEventKind::Start, EpisodeEventKind::Stop]);
        assert_eq!(out.events[1].note, "the control loop stopped");
        assert_eq!(summary.ticks, 1);
        // The summary lists the episode it stopped, as the recorder files it.
        assert_eq!(summary.episodes.len(), 1);
        assert_eq!(
            (summary.episodes[0].outcome.as_str(), summary.episodes[0].episode_id.as_str()),
            ("failure", out.events[1].episode_id.as_str())
        );
    }

    #[test]
    fn a_recorder_without_space_holds_the_rig_idle_and_ends_an_episode_it_refused() {
        let (mut rig, mut src, mut out) = (rig(100), Queue::default(), Sent::default());
        let full = r#"{"state":"idle","accepting":false,"free_bytes":3000000,"needed_bytes":100000000}"#;
        rig.push_recorder_status(full);
        assert_eq!(rig.recorder_refusal(), Some("the recorder takes no episode: 3.0 MB free, 100.0 MB needed"));
        request(&mut rig, EpisodeEventKind::Start, "");
        tick(&mut rig, 0, &mut src, &mut out);
        assert!(out.events.is_empty() && out.steps.is_empty(), "no episode starts: {:?}", out.kinds());
        assert_eq!((rig.state(), rig.summary().starts_refused), (State::Idle, 1));
        // Space again: the next Start goes ahead.
        rig.push_recorder_status(
            r#"{"state":"idle","accepting":true,"free_bytes":900000000,"needed_bytes":100000000}"#,
        );
        assert_eq!(rig.recorder_refusal(), None);
        request(&mut rig, EpisodeEventKind::Start, "");
        src.actions.extend([go(joints_at(0.01)), go(joints_at(0.02))]);
        tick(&mut rig, 1, &mut src, &mut out);
        assert_eq!(out.kinds(), [EpisodeEventKind::Start]);
        // The recorder refused that episode (it raced the status): the loop stops it.
        let id = out.events[0].episode_id.clone();
        rig.push_recorder_status(&format!(r#"{{"state":"refused","episode":"{id}","accepting":false}}"#));
        tick(&mut rig, 2, &mut src, &mut out);
        assert_eq!(out.kinds(), [EpisodeEventKind::Start, EpisodeEventKind::Stop]);
        assert_eq!(rig.summary().episodes[0].outcome, "failure");
    }

    #[test]
    fn an_arm_fault_stops_the_episode_with_the_fault_named() {
        let (mut rig, mut src, mut out) = (rig(100), Queue::default(), Sent::default());
        request(&mut rig, EpisodeEventKind::Start, "");
        src.actions.extend([go(joints_at(0.01)), go(joints_at(0.02))]);
        tick(&mut rig, 0, &mut src, &mut out);
        let fault = "the sim bridge is gone: no /sim/arm/state for 1.0 s; call /arm/recover";
        let faulted = RobotState { mode: RobotState::MODE_FAULT, fault: fault.into(), ..state(joints_at(0.01)) };
        // One refused command (a fault for one tick) is not a fault that stops the episode.
        rig.begin_tick(Nanos(PERIOD), Instant::now());
        rig.set_robot(faulted.clone());
        rig.decide(Some(&mut src), &mut out).unwrap();
        rig.act(Some(&mut src), &mut out).unwrap();
        assert_eq!(out.kinds(), [EpisodeEventKind::Start]);
        // A fault that lasts does.
        for k in 2..=i64::from(ARM_FAULT_TICKS) {
            rig.begin_tick(Nanos(k * PERIOD), Instant::now());
            rig.set_robot(faulted.clone());
            rig.decide(Some(&mut src), &mut out).unwrap();
            rig.act(Some(&mut src), &mut out).unwrap();
        }
        assert_eq!(out.kinds(), [EpisodeEventKind::Start, EpisodeEventKind::Stop]);
        assert_eq!(out.events[1].note, format!("the arm faulted: {fault}"));
        assert_eq!(rig.summary().arm_faults, 1);
        assert_eq!(out.steps.len() as u32, ARM_FAULT_TICKS, "steps until the fault lasted, none after");
        assert_eq!(rig.summary().episodes[0].outcome, "failure");
    }

    #[test]
    fn an_event_out_of_place_is_refused_and_changes_nothing() {
        let (mut rig, mut src, mut out) = (rig(100), Queue::default(), Sent::default());
        request(&mut rig, EpisodeEventKind::Success, "");
        tick(&mut rig, 0, &mut src, &mut out);
        assert!(out.events.is_empty());
        assert_eq!(rig.state(), State::Idle);
    }

    #[test]
    fn ticks_on_the_sim_clock_count_the_periods_they_skip() {
        let (mut rig, mut src, mut out) = (rig(100), Queue::default(), Sent::default());
        assert!(rig.is_new_tick(Nanos(0)));
        tick(&mut rig, 0, &mut src, &mut out);
        assert!(!rig.is_new_tick(Nanos(PERIOD / 2)), "a state inside the period is not a tick");
        assert!(rig.is_new_tick(Nanos(PERIOD - TICK_TOLERANCE_NS / 2)));
        tick(&mut rig, 3, &mut src, &mut out);
        assert_eq!(rig.summary().missed_ticks, 2);
    }

    #[test]
    fn a_window_reports_its_own_counts_and_jitter_then_the_next_begins() {
        let mut rig = rig(100);
        rig.cfg.window_s = 1.0;
        let t0 = Instant::now();
        let at = |ms: u64| t0 + std::time::Duration::from_millis(ms);
        assert!(rig.take_window(at(0)).is_none(), "the first call begins the first window");
        // Ticks at 0, 50, 130 (30 ms late), 150 ms; ticks 1 and 2 skipped on the sim's clock.
        for (k, ms) in [(0, 0), (1, 50), (4, 130), (5, 150)] {
            rig.begin_tick(Nanos(k * PERIOD), at(ms));
        }
        assert!(rig.take_window(at(999)).is_none(), "not yet a second");
        let w = rig.take_window(at(1000)).unwrap();
        assert_eq!((w["ticks"].as_u64(), w["missed_ticks"].as_u64()), (Some(4), Some(2)), "{w}");
        // Intervals 50, 80, 20 ms against 50: |0|, 30, 30 ms.
        assert_eq!(w["jitter_us"][1].as_f64(), Some(30_000.0), "{w}");
        assert_eq!(w["jitter_us"][0].as_f64(), Some(30_000.0), "{w}");
        assert!((w["seconds"].as_f64().unwrap() - 1.0).abs() < 1e-9);
        // The next window holds only its own ticks.
        rig.begin_tick(Nanos(6 * PERIOD), at(1200));
        let w = rig.take_window(at(2000)).unwrap();
        assert_eq!((w["ticks"].as_u64(), w["missed_ticks"].as_u64()), (Some(1), Some(0)), "{w}");
        assert_eq!(w["jitter_us"][2].as_f64(), Some(1_000_000.0), "1050 ms after the tick before, at 1200: {w}");
        assert_eq!(rig.summary().ticks, 5, "the run's summary counts every tick");
    }
}
