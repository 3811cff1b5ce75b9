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

use crate::config::{ClockKind, ControlConfig, SourceKind, TakeoverKind};
use crate::frames::FrameTimes;
use crate::policy::PolicySource;
use crate::report::{Spread, Summary};
use crate::rig::{RigLoop, RigOutputs};
use crate::source::RgbFrame;
use crate::source::{ActionSource, ScriptedExpert};
use crate::takeover::{ExpertRule, Takeover};
use anyhow::Context;
use labrig_arm::ik::{Ik, IkConfig};
use labrig_arm::safety::SafetyFilter;
use labrig_arm::{Fr3Kinematics, TcpOffset};
use labrig_msgs::Nanos;
use labrig_msgs::rig::{ArmCommand, EpisodeEvent, GripperCommand, GripperState, RobotState, Step};
use labrig_msgs::rosgraph_msgs::Clock;
use labrig_msgs::std_msgs::StringMsg;
use labrig_msgs::topics;
use labrig_runtime::Shutdown;
use labrig_runtime::frames::FrameEncoding;
use labrig_runtime::frames::{FrameNode, FrameSubscriber};
use labrig_runtime::ros::{Ros, RosError, RosPublisher, RosSubscription};
use serde_json::json;
use std::collections::VecDeque;
use std::sync::Arc;
use std::time::{Duration, Instant};

struct Pubs {
    arm: RosPublisher<ArmCommand>,
    gripper: RosPublisher<GripperCommand>,
    step: RosPublisher<Step>,
    episode: RosPublisher<EpisodeEvent>,
    reset: RosPublisher<StringMsg>,
    status: RosPublisher<StringMsg>,
}

impl Pubs {
    /// The loop's publishers, in the order the loop has always created them.
    fn open(ros: &mut Ros) -> anyhow::Result<Pubs> {
        Ok(Pubs {
            arm: ros.publisher_on(&topics::ARM_COMMAND, 10)?,
            gripper: ros.publisher_on(&topics::GRIPPER_COMMAND, 10)?,
            // Ten seconds of steps and the last 100 events kept for a recorder that restarts.
            step: ros.publisher_on(&topics::RIG_STEP, 200)?,
            episode: ros.publisher_on(&topics::RIG_EPISODE, 100)?,
            reset: ros.publisher_on(&topics::SIM_RESET, 10)?,
            status: ros.publisher_on(&topics::CONTROL_STATUS, 1)?,
        })
    }
}

/// Runs the rig loop until its episodes are done or it is shut down: the stages of each tick
/// are numbered below.
/// Appends one line to `path` (the loop's window figures: one short write every few minutes).
fn append_line(path: &std::path::Path, line: &str) -> anyhow::Result<()> {
    use std::io::Write;
    let mut f = std::fs::OpenOptions::new()
        .create(true)
        .append(true)
        .open(path)
        .with_context(|| format!("window_stats {}", path.display()))?;
    writeln!(f, "{line}").with_context(|| format!("window_stats {}", path.display()))?;
    Ok(())
}

pub async fn run(cfg: ControlConfig, shutdown: Shutdown) -> anyhow::Result<Summary> {
    cfg.validate()?;
    check_calibration(&cfg);
    let (kin, filter) = safety_layer(&cfg)?;
    let mut ros = Ros::new(&cfg.ros, "labrig_control")?;
    let pubs = Pubs::open(&mut ros)?;
    let subs = Subs::open(&mut ros, cfg.clock)?;
    let mut source = action_source(&mut ros, &cfg, &shutdown).await?;
    let mut cams = Cameras::open(&cfg, source.as_deref())?;
    let robot = first_state(&subs.arm_state, &shutdown).await?;
    wait_for_readers(&ros, &cfg).await?;
    raise_priority(&cfg);
    tracing::info!(source = ?cfg.source, clock = ?cfg.clock, episodes = cfg.episodes, "control loop up");
    let _ = pubs.status.publish(StringMsg { data: json!({ "state": "Idle", "ticks": 0 }).to_string() });

    let mut rig = RigLoop::new(cfg.clone(), kin, filter, robot);
    let mut out = RosOutputs(pubs);
    let mut ticker = Ticker::new(rig.period());
    while !shutdown.is_triggered() {
        // 1. Wait for the tick.
        let tick_ns = match ticker.wait(&cfg, &subs, &mut rig, &shutdown).await? {
            Tick::At(t) => t,
            Tick::Shutdown => break,
            Tick::ClockStopped(why) => return Err(end_on_stopped_clock(rig, &mut out, &why).await),
        };
        rig.begin_tick(Nanos(tick_ns), Instant::now());
        if let Some(path) = &cfg.window_stats
            && let Some(w) = rig.take_window(Instant::now())
        {
            append_line(path, &w.to_string())?;
        }
        // 2. Everything that arrived (on the sim's clock, the tick's own gripper state and
        // frames trail its arm state on their own channels: wait for them, bounded).
        subs.take_gripper(&mut rig, &shutdown).await?;
        subs.take_scene(&mut rig)?;
        cams.take_frames(&mut rig, &shutdown).await?;
        subs.take_requests(&mut rig)?;
        if let Some(s) = source.as_mut() {
            s.poll()?;
        }
        // 3. The episodes asked for are done.
        if rig.done() {
            break;
        }
        subs.wait_for_scene(&mut rig, &shutdown).await?;
        // 4. Episode events.
        rig.decide(source.as_deref_mut(), &mut out)?;
        observe_in_lockstep(source.as_deref_mut(), &rig, &mut cams, &cfg, Nanos(tick_ns), &shutdown).await?;
        // 5. The action, the commands, the record.
        rig.act(source.as_deref_mut(), &mut out)?;
    }
    let mut summary = rig.finish(&mut out);
    summary.source = source.as_ref().and_then(|s| s.stats());
    summary.clock_ticks = ticker.clock_ticks;
    summary.tick_lateness_us = ticker.lateness_ns.percentiles_us();
    // The last events reach their readers (the recorder) before the participant goes.
    tokio::time::sleep(Duration::from_millis(1000)).await;
    Ok(summary)
}

/// Warns of each camera whose calibration is missing or older than the config allows.
fn check_calibration(cfg: &ControlConfig) {
    let Some(dir) = &cfg.calibration else { return };
    let cameras: Vec<&str> = cfg.cameras.iter().map(String::as_str).collect();
    let now = labrig_runtime::Clock::Wall.now().0 / 1_000_000_000;
    let warnings = labrig_episode::calibration::load(dir, &cameras).warnings(now, cfg.calibration_max_age_s);
    for w in &warnings {
        tracing::warn!("calibration: {w}");
    }
    if warnings.is_empty() {
        tracing::info!("calibration: all {} cameras calibrated within {} s", cameras.len(), cfg.calibration_max_age_s);
    }
}

/// The arm's kinematics and the safety filter every action passes through.
fn safety_layer(cfg: &ControlConfig) -> anyhow::Result<(Fr3Kinematics, SafetyFilter)> {
    let urdf = labrig_arm::urdf_path(cfg.urdf.as_deref());
    let kin = Fr3Kinematics::from_urdf_file(&urdf, TcpOffset::ROBOTIQ_2F85)
        .with_context(|| format!("loading the FR3 URDF {}", urdf.display()))?;
    let filter =
        SafetyFilter::new(Ik::new(kin.clone(), IkConfig::default()), cfg.safety.clone()).map_err(anyhow::Error::msg)?;
    Ok((kin, filter))
}

/// The loop's subscriptions (besides the source's own).
struct Subs {
    arm_state: RosSubscription<RobotState>,
    /// The sim's `/clock`, on the sim's clock.
    sim_clock: Option<RosSubscription<Clock>>,
    gripper_state: RosSubscription<GripperState>,
    scene: RosSubscription<StringMsg>,
    requests: RosSubscription<EpisodeEvent>,
    recorder_status: RosSubscription<StringMsg>,
    session: RosSubscription<StringMsg>,
}

impl Subs {
    /// Subscribes, in the order the loop has always subscribed.
    fn open(ros: &mut Ros, clock: ClockKind) -> anyhow::Result<Subs> {
        let arm_state: RosSubscription<RobotState> = ros.subscription_on(&topics::ARM_STATE, 10)?;
        // On the sim's clock the tick follows the sim's own time (`/clock`, published on each of
        // its steps), not the arm node's state rate (50 Hz in front of the bridge: ticks would
        // land up to 20 ms late).
        let sim_clock = match clock {
            ClockKind::Sim => Some(ros.subscription_on(&topics::CLOCK, 10)?),
            ClockKind::Wall => None,
        };
        Ok(Subs {
            arm_state,
            sim_clock,
            gripper_state: ros.subscription_on(&topics::GRIPPER_STATE, 10)?,
            scene: ros.subscription_on(&topics::SIM_SCENE, 1)?,
            requests: ros.subscription_on(&topics::RIG_REQUEST, 10)?,
            recorder_status: ros.subscription_on(&topics::RECORDER_STATUS, 1)?,
            session: ros.subscription_on(&topics::RIG_SESSION, 1)?,
        })
    }

    /// The gripper states that arrived; on the sim's clock, the tick's own waited for (bounded).
    async fn take_gripper(&self, rig: &mut RigLoop, shutdown: &Shutdown) -> anyhow::Result<()> {
        while let Some(g) = self.gripper_state.try_take()? {
            rig.push_gripper(g.msg);
        }
        let deadline = Instant::now() + Duration::from_millis(500);
        while rig.gripper_behind() && Instant::now() < deadline && !shutdown.is_triggered() {
            tokio::time::sleep(Duration::from_micros(100)).await;
            while let Some(g) = self.gripper_state.try_take()? {
                rig.push_gripper(g.msg);
            }
        }
        Ok(())
    }

    /// The scene messages that arrived.
    fn take_scene(&self, rig: &mut RigLoop) -> anyhow::Result<()> {
        while let Some(s) = self.scene.try_take()? {
            rig.push_scene(&s.msg.data);
        }
        Ok(())
    }

    /// The session, the episode requests and the recorder's status that arrived.
    fn take_requests(&self, rig: &mut RigLoop) -> anyhow::Result<()> {
        // The session before the requests: a Start sent right after a session change has it.
        while let Some(s) = self.session.try_take()? {
            rig.push_session(&s.msg.data);
        }
        while let Some(r) = self.requests.try_take().unwrap_or_else(|e| {
            tracing::warn!("/rig/request: {e}");
            None
        }) {
            rig.push_request(&r.msg);
        }
        while let Some(r) = self.recorder_status.try_take()? {
            rig.push_recorder_status(&r.msg.data);
        }
        Ok(())
    }

    /// The new scene's message, which may trail its first state (waited for, bounded).
    async fn wait_for_scene(&self, rig: &mut RigLoop, shutdown: &Shutdown) -> anyhow::Result<()> {
        if rig.scene_due().is_some() {
            let deadline = Instant::now() + Duration::from_secs(30);
            while rig.scene_due().is_some() && Instant::now() < deadline && !shutdown.is_triggered() {
                tokio::time::sleep(Duration::from_micros(200)).await;
                while let Some(m) = self.scene.try_take()? {
                    rig.push_scene(&m.msg.data);
                }
            }
        }
        Ok(())
    }
}

/// The configured action source (none: the arm is held), connected.
async fn action_source(
    ros: &mut Ros,
    cfg: &ControlConfig,
    shutdown: &Shutdown,
) -> anyhow::Result<Option<Box<dyn ActionSource>>> {
    Ok(match cfg.source {
        SourceKind::Scripted => Some(Box::new(ScriptedExpert::new(ros)?)),
        SourceKind::Hold => None,
        SourceKind::Teleop => {
            Some(Box::new(crate::source::Teleop::new(ros, Duration::from_secs_f64(cfg.teleop_max_age_s))?))
        }
        SourceKind::Policy | SourceKind::Remote => {
            let period = Nanos::from_secs_rounded(cfg.period_s);
            let p = if cfg.source == SourceKind::Remote {
                PolicySource::connect_remote(
                    ros,
                    cfg.policy.clone(),
                    cfg.remote.clone(),
                    cfg.clock,
                    period,
                    &cfg.cameras,
                )
                .await?
            } else {
                PolicySource::connect(ros, cfg.policy.clone(), cfg.clock, period, &cfg.cameras, shutdown).await?
            };
            let teleop_age = Duration::from_secs_f64(cfg.teleop_max_age_s);
            match cfg.policy.takeover {
                TakeoverKind::None => Some(Box::new(p)),
                TakeoverKind::Teleop => Some(Box::new(Takeover::new(
                    Box::new(p),
                    Box::new(crate::source::Teleop::new(ros, teleop_age)?),
                    None,
                ))),
                TakeoverKind::Expert => Some(Box::new(Takeover::new(
                    Box::new(p),
                    Box::new(ScriptedExpert::new(ros)?),
                    Some(ExpertRule::new(&cfg.policy)),
                ))),
            }
        }
    })
}

/// The cameras' frames: every configured camera's timing, and the pixels of those the
/// source observes.
struct Cameras {
    /// Declared before the node, so they are dropped before it.
    subs: Vec<(String, FrameSubscriber)>,
    _node: FrameNode,
    /// The cameras whose pixels the source observes: their newest frames, copied.
    pixels: Vec<PixelRing>,
}

impl Cameras {
    /// Subscribes to each configured camera's frames.
    fn open(cfg: &ControlConfig, source: Option<&dyn ActionSource>) -> anyhow::Result<Cameras> {
        let pixels: Vec<PixelRing> = source
            .map(|s| s.cameras().iter().map(|c| PixelRing { camera: c.clone(), frames: VecDeque::new() }).collect())
            .unwrap_or_default();
        let node = match &cfg.frames_namespace {
            Some(ns) => FrameNode::new_in(ns)?,
            None => FrameNode::new()?,
        };
        let subs: Vec<(String, FrameSubscriber)> =
            cfg.cameras.iter().map(|c| Ok((c.clone(), node.subscriber(c)?))).collect::<anyhow::Result<_>>()?;
        Ok(Cameras { subs, _node: node, pixels })
    }

    /// The frames that arrived; the tick's own waited for while any camera's is pending (bounded).
    async fn take_frames(&mut self, rig: &mut RigLoop, shutdown: &Shutdown) -> anyhow::Result<()> {
        let frames_deadline = Instant::now() + Duration::from_millis(200);
        loop {
            for (name, sub) in &self.subs {
                while let Some(f) = sub.receive()? {
                    let h = f.header();
                    rig.push_frame(
                        name,
                        FrameTimes { sequence: h.sequence, capture_ns: h.capture_ns, arrival_ns: h.arrival_ns },
                    );
                    if let Some(ring) = self.pixels.iter_mut().find(|r| &r.camera == name) {
                        ring.push(&f);
                    }
                }
            }
            if !rig.frames_pending() || Instant::now() >= frames_deadline || shutdown.is_triggered() {
                return Ok(());
            }
            tokio::time::sleep(Duration::from_micros(100)).await;
        }
    }
}

/// The first state (the arm node or the sim bridge may still be starting), waited for up to
/// two minutes.
async fn first_state(arm_state: &RosSubscription<RobotState>, shutdown: &Shutdown) -> anyhow::Result<RobotState> {
    let waited = Instant::now();
    loop {
        if let Some(s) = arm_state.try_take()? {
            return Ok(s.msg);
        }
        anyhow::ensure!(!shutdown.is_triggered(), "stopped before the arm came up");
        anyhow::ensure!(
            waited.elapsed() < Duration::from_secs(120),
            "no /arm/state within 120 s: is the arm node (or the sim bridge) running on this domain?"
        );
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
}

/// Waits for the commands' (and, with `auto_start`, the episodes') readers and lets the
/// writers match them.
async fn wait_for_readers(ros: &Ros, cfg: &ControlConfig) -> anyhow::Result<()> {
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
    Ok(())
}

/// On the wall clock, raises the loop's thread to the configured realtime priority.
fn raise_priority(cfg: &ControlConfig) {
    if cfg.clock == ClockKind::Wall && cfg.realtime_priority > 0 {
        // This future runs on the thread that called block_on: the loop's own thread.
        if let Err(e) = labrig_runtime::realtime_priority(cfg.realtime_priority) {
            tracing::warn!("{e}; the loop runs at normal priority");
        }
    }
}

/// What waiting for a tick came to.
enum Tick {
    /// The tick's time (ns).
    At(i64),
    Shutdown,
    /// The sim's clock stopped: why.
    ClockStopped(String),
}

/// Waits for each tick on the configured clock, and measures how late each one began.
struct Ticker {
    period: Nanos,
    /// Wall clock: the next tick's scheduled instant.
    next_wall: Instant,
    /// Sim clock: whether the sim publishes /clock (then it sets the ticks).
    clock_seen: bool,
    clock_ticks: u64,
    /// How late each tick began after its boundary (wall clock: the scheduled instant; sim
    /// clock: the sim's /clock message for it), ns.
    lateness_ns: Spread,
}

impl Ticker {
    /// The first wall-clock tick a period from now.
    fn new(period: Nanos) -> Ticker {
        let next_wall = Instant::now() + Duration::from_nanos(period.0 as u64);
        Ticker { period, next_wall, clock_seen: false, clock_ticks: 0, lateness_ns: Spread::default() }
    }

    /// The next tick, the arm's newest state given to `rig`.
    async fn wait(
        &mut self,
        cfg: &ControlConfig,
        subs: &Subs,
        rig: &mut RigLoop,
        shutdown: &Shutdown,
    ) -> anyhow::Result<Tick> {
        match cfg.clock {
            ClockKind::Sim => self.wait_sim(cfg, subs, rig, shutdown).await,
            ClockKind::Wall => self.wait_wall(subs, rig, shutdown),
        }
    }

    /// On the sim's clock: the first `/clock` (or, without one, `/arm/state`) a period after
    /// the last tick; or none for `tick_timeout_s`: the sim's clock stopped.
    async fn wait_sim(
        &mut self,
        cfg: &ControlConfig,
        subs: &Subs,
        rig: &mut RigLoop,
        shutdown: &Shutdown,
    ) -> anyhow::Result<Tick> {
        let waiting_since = Instant::now();
        loop {
            if shutdown.is_triggered() {
                return Ok(Tick::Shutdown);
            }
            if waiting_since.elapsed().as_secs_f64() > cfg.tick_timeout_s {
                return Ok(Tick::ClockStopped(format!(
                    "no new /arm/state tick for {:.1} s: the sim's clock stopped (the sim bridge or the arm node is gone)",
                    cfg.tick_timeout_s
                )));
            }
            let mut newest = None;
            while let Some(s) = subs.arm_state.try_take()? {
                newest = Some(s.msg);
            }
            if let Some(s) = newest {
                let t = Nanos::from(s.header.stamp).0;
                rig.set_robot(s);
                // Without /clock (a sim that does not publish it) the states set the ticks.
                if !self.clock_seen && rig.is_new_tick(Nanos(t)) {
                    return Ok(Tick::At(t));
                }
            }
            let mut clock_ns = None;
            let mut clock_sent = 0;
            while let Some(c) = subs.sim_clock.as_ref().map(|c| c.try_take()).transpose()?.flatten() {
                clock_ns = Some(Nanos::from(c.msg.clock).0);
                clock_sent = c.source_time.unwrap_or(c.receive_time).0;
                self.clock_seen = true;
            }
            if let Some(t) = clock_ns.filter(|&t| rig.is_new_tick(Nanos(t))) {
                take_state_after_clock(&subs.arm_state, rig, t).await?;
                self.clock_ticks += 1;
                // Late by: the wall time from the sim's /clock going out to this tick.
                self.lateness_ns.push((labrig_runtime::Clock::Wall.now().0 - clock_sent).max(0));
                return Ok(Tick::At(t));
            }
            // The loop's own thread polls (tokio's timers wake 1-5 ms late on a busy machine).
            std::thread::sleep(Duration::from_micros(200));
        }
    }

    /// On the wall clock: sleeps to the scheduled instant, skipping (and counting) the ticks
    /// lost when behind by more than a period.
    fn wait_wall(&mut self, subs: &Subs, rig: &mut RigLoop, shutdown: &Shutdown) -> anyhow::Result<Tick> {
        // The loop's own thread sleeps to the tick (a high-resolution timer; at
        // SCHED_FIFO it runs the moment it wakes). tokio's timers are woken by its
        // workers at normal priority: 1-5 ms late on a busy machine.
        std::thread::sleep(self.next_wall.saturating_duration_since(Instant::now()));
        if shutdown.is_triggered() {
            return Ok(Tick::Shutdown);
        }
        let now = Instant::now();
        self.lateness_ns.push(now.saturating_duration_since(self.next_wall).as_nanos() as i64);
        // Behind by more than a period: skip the lost ticks, count them.
        let behind = now.saturating_duration_since(self.next_wall).as_nanos() as i64 / self.period.0;
        rig.count_missed(behind as u64);
        self.next_wall += Duration::from_nanos((self.period.0 * (behind + 1)) as u64);
        while let Some(s) = subs.arm_state.try_take()? {
            rig.set_robot(s.msg);
        }
        Ok(Tick::At(labrig_runtime::Clock::Wall.now().0))
    }
}

/// The sim's clock stopped: the episode ends (its Stop given time to reach the recorder) and
/// the loop fails with `why`.
async fn end_on_stopped_clock(rig: RigLoop, out: &mut RosOutputs, why: &str) -> anyhow::Error {
    tracing::error!("{why}");
    rig.finish_because(out, why);
    // The Stop reaches the recorder before the participant goes.
    tokio::time::sleep(Duration::from_millis(1000)).await;
    anyhow::anyhow!("{why}")
}

/// The sim reached the boundary `t`. Its state of that instant: from the bridge itself it went
/// out just before the clock (lockstep pairs them); an arm node in front of it relays at its
/// own rate, up to a period later: waited for briefly, else the newest is used (its stamp is
/// in the step).
async fn take_state_after_clock(
    arm_state: &RosSubscription<RobotState>,
    rig: &mut RigLoop,
    t: i64,
) -> anyhow::Result<()> {
    let deadline = Instant::now() + STATE_AFTER_CLOCK;
    let mut stamp = i64::MIN;
    loop {
        while let Some(s) = arm_state.try_take()? {
            stamp = Nanos::from(s.msg.header.stamp).0;
            rig.set_robot(s.msg);
        }
        if stamp >= t || Instant::now() >= deadline {
            return Ok(());
        }
        tokio::time::sleep(Duration::from_micros(100)).await;
    }
}

/// The tick as recorded, to a source that observes (the policy's request goes out here). In
/// lockstep (sim clock, recording) the source first settles what it decides from at the tick
/// (a takeover: the operator's status stamped at it), so the decision does not race the sim,
/// and afterwards its action for this state is waited for, to come right after the state.
async fn observe_in_lockstep(
    mut source: Option<&mut (dyn ActionSource + '_)>,
    rig: &RigLoop,
    cams: &mut Cameras,
    cfg: &ControlConfig,
    tick: Nanos,
    shutdown: &Shutdown,
) -> anyhow::Result<()> {
    if let (Some(s), ClockKind::Sim, true) = (source.as_deref_mut(), cfg.clock, rig.recording()) {
        poll_until(s, cfg, shutdown, |s| s.settled(tick)).await?;
    }
    if let (Some(s), Some(mut view)) = (source.as_deref_mut(), rig.view()) {
        view.images = cams.pixels.iter_mut().filter_map(|r| r.at(view.tick).map(|f| (r.camera.as_str(), f))).collect();
        s.observe(view);
    }
    if let (Some(s), ClockKind::Sim, true) = (source, cfg.clock, rig.recording()) {
        poll_until(s, cfg, shutdown, |s| s.has(tick)).await?;
    }
    Ok(())
}

/// Polls `source` until `done` holds, for at most `source_timeout_s`.
async fn poll_until(
    source: &mut (dyn ActionSource + '_),
    cfg: &ControlConfig,
    shutdown: &Shutdown,
    done: impl Fn(&dyn ActionSource) -> bool,
) -> anyhow::Result<()> {
    let deadline = Instant::now() + Duration::from_secs_f64(cfg.source_timeout_s);
    while !done(source) && Instant::now() < deadline && !shutdown.is_triggered() {
        tokio::time::sleep(Duration::from_micros(100)).await;
        source.poll()?;
    }
    Ok(())
}

/// One camera's newest frames, pixels copied out of shared memory, for a source that
/// observes them. A passed-through JPEG is kept as it came and decoded only when a tick takes
/// it (at most one decode per camera and tick, not one per frame drained).
struct PixelRing {
    camera: String,
    frames: VecDeque<Pixels>,
}

/// A kept frame: decoded, or a camera's JPEG waiting for a tick to need it.
enum Pixels {
    Rgb(Arc<RgbFrame>),
    Jpeg { bytes: Vec<u8>, capture_ns: i64 },
}

impl Pixels {
    fn capture_ns(&self) -> i64 {
        match self {
            Pixels::Rgb(f) => f.capture_ns,
            Pixels::Jpeg { capture_ns, .. } => *capture_ns,
        }
    }
}

impl PixelRing {
    /// Frames kept: the tick's own may be followed by a newer one before the tick reads it.
    const DEPTH: usize = 3;

    fn push(&mut self, f: &labrig_runtime::frames::Frame) {
        let h = *f.header();
        if h.encoding() == Some(FrameEncoding::Jpeg) {
            // A camera's `jpeg_passthrough`: decoded in `at`, only because a policy observes it.
            self.keep(Pixels::Jpeg { bytes: f.pixels().to_vec(), capture_ns: h.capture_ns });
            return;
        }
        if h.encoding() != Some(FrameEncoding::Rgb8) {
            return;
        }
        let (w, stride) = (h.width as usize * 3, h.stride as usize);
        let px = f.pixels();
        let pixels = if stride == w || stride == 0 {
            px.get(..w * h.height as usize).map(<[u8]>::to_vec)
        } else {
            (0..h.height as usize)
                .map(|y| px.get(y * stride..y * stride + w))
                .collect::<Option<Vec<_>>>()
                .map(|r| r.concat())
        };
        let Some(pixels) = pixels else { return };
        self.keep(Pixels::Rgb(Arc::new(RgbFrame {
            width: h.width,
            height: h.height,
            pixels,
            capture_ns: h.capture_ns,
        })));
    }

    fn keep(&mut self, frame: Pixels) {
        self.frames.push_back(frame);
        while self.frames.len() > Self::DEPTH {
            self.frames.pop_front();
        }
    }

    /// The newest frame captured at or before `tick` (the Step's frame), decoded now if it is
    /// a JPEG (and kept decoded). A JPEG that does not decode is warned and dropped.
    fn at(&mut self, tick: Nanos) -> Option<Arc<RgbFrame>> {
        let i = self.frames.iter().rposition(|f| f.capture_ns() <= tick.0)?;
        if let Pixels::Jpeg { bytes, capture_ns } = &self.frames[i] {
            match labrig_episode::jpeg::decode_rgb(bytes) {
                Ok(rgb) => {
                    let frame = RgbFrame {
                        width: rgb.width as u32,
                        height: rgb.height as u32,
                        pixels: rgb.pixels,
                        capture_ns: *capture_ns,
                    };
                    self.frames[i] = Pixels::Rgb(Arc::new(frame));
                }
                Err(e) => {
                    tracing::warn!(camera = %self.camera, "a JPEG frame that does not decode: {e}");
                    self.frames.remove(i);
                    return None;
                }
            }
        }
        match &self.frames[i] {
            Pixels::Rgb(f) => Some(f.clone()),
            Pixels::Jpeg { .. } => None,
        }
    }
}

/// On the sim's clock, how long a tick started by `/clock` waits for the arm's state of its
/// instant before it uses the newest one.
const STATE_AFTER_CLOCK: Duration = Duration::from_millis(1);

/// The loop's outputs on ROS 2.
struct RosOutputs(Pubs);

impl RigOutputs for RosOutputs {
    fn arm(&mut self, cmd: ArmCommand) -> Result<(), RosError> {
        self.0.arm.publish(cmd)
    }
    fn gripper(&mut self, cmd: GripperCommand) -> Result<(), RosError> {
        self.0.gripper.publish(cmd)
    }
    fn step(&mut self, step: Step) -> Result<(), RosError> {
        self.0.step.publish(step)
    }
    fn episode(&mut self, event: EpisodeEvent) -> Result<(), RosError> {
        self.0.episode.publish(event)
    }
    fn reset_scene(&mut self, seed: u64) -> Result<(), RosError> {
        self.0.reset.publish(StringMsg { data: json!({ "seed": seed }).to_string() })
    }
    fn status(&mut self, json: String) -> Result<(), RosError> {
        self.0.status.publish(StringMsg { data: json })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_passed_through_jpeg_is_decoded_only_when_a_tick_takes_it() {
        let mut ring = PixelRing { camera: "ext1".into(), frames: VecDeque::new() };
        let rgb: Vec<u8> = (0..16 * 8 * 3).map(|i| (i * 7 % 256) as u8).collect();
        let jpeg = labrig_episode::jpeg::encode_rgb(&rgb, 16, 8, 90).unwrap();
        for t in [100, 200, 300, 400] {
            ring.keep(Pixels::Jpeg { bytes: jpeg.clone(), capture_ns: t });
        }
        ring.keep(Pixels::Jpeg { bytes: b"not a jpeg".to_vec(), capture_ns: 500 });
        // The newest three are kept (300, 400 and the bad one at 500); none is decoded yet.
        assert_eq!(ring.frames.len(), PixelRing::DEPTH);
        assert!(ring.frames.iter().all(|f| matches!(f, Pixels::Jpeg { .. })));
        let f = ring.at(Nanos(350)).expect("the frame of 300");
        assert_eq!((f.width, f.height, f.capture_ns, f.pixels.len()), (16, 8, 300, 16 * 8 * 3));
        let decoded: Vec<bool> = ring.frames.iter().map(|f| matches!(f, Pixels::Rgb(_))).collect();
        assert_eq!(decoded, [true, false, false], "only the frame the tick took is decoded");
        assert!(ring.at(Nanos(250)).is_none(), "nothing captured by then is kept");
        // A JPEG that does not decode gives no frame and is dropped.
        assert!(ring.at(Nanos(600)).is_none());
        assert_eq!(ring.frames.len(), 2);
        assert_eq!(ring.at(Nanos(600)).unwrap().capture_ns, 400);
    }

    /// The grip cannot be both the policy's deadman and the operator's takeover; the expert
    /// plays the operator in the sim only; the rule's numbers are checked by name.
    #[test]
    fn a_takeover_config_that_cannot_work_is_refused_by_key() {
        let load = |toml: &str| -> ControlConfig {
            labrig_runtime::config::parse_config(toml, std::path::Path::new("test.toml")).unwrap()
        };
        let c = load("source = \"policy\"\n[policy]\ntakeover = \"teleop\"\n");
        assert_eq!(c.validate(), Ok(()));
        let e = load("[policy]\ntakeover = \"teleop\"\ndeadman = true\n").validate().unwrap_err();
        assert_eq!(e.key, "policy.takeover");
        assert!(e.to_string().contains("cannot mean both"), "{e}");
        let e = load("[policy]\ntakeover = \"expert\"\n").validate().unwrap_err();
        assert!(e.to_string().contains("needs policy.sim_rig = true"), "{e}");
        let c = load("[policy]\ntakeover = \"expert\"\nsim_rig = true\ntakeover_stall_ticks = 20\n");
        assert_eq!(c.validate(), Ok(()));
        assert_eq!((c.policy.takeover_stall_ticks, c.policy.takeover_ticks, c.policy.takeover_max), (20, 40, 3));
        let e = load("[policy]\ntakeover_distance_m = -1.0\n").validate().unwrap_err();
        assert_eq!(e.key, "policy.takeover_distance_m");
        assert!(
            labrig_runtime::config::parse_config::<ControlConfig>(
                "[policy]\ntakeover = \"someone\"\n",
                std::path::Path::new("test.toml")
            )
            .is_err()
        );
    }

    #[test]
    fn the_real_rigs_config_file_loads() {
        let p = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../launch_configs/nodes/control_real.toml");
        let c: ControlConfig = labrig_runtime::load_config(&p).unwrap();
        assert_eq!(c.validate(), Ok(()));
        assert_eq!((c.source, c.clock, c.auto_start), (SourceKind::Teleop, ClockKind::Wall, false));
        assert_eq!(c.teleop_max_age_s, 0.035);
        assert_eq!(c.safety.max_command_age_s, 0.0);
    }

    #[test]
    fn the_real_rigs_policy_config_loads() {
        let p = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../../launch_configs/nodes/control_real_policy.toml");
        let c: ControlConfig = labrig_runtime::load_config(&p).unwrap();
        assert_eq!(c.validate(), Ok(()));
        assert_eq!((c.source, c.clock, c.auto_start), (SourceKind::Policy, ClockKind::Wall, false));
        assert!(c.policy.deadman && c.policy.action_space == "eef_axis_angle");
    }

    #[test]
    fn configs_are_checked_by_field() {
        let mut c = ControlConfig::default();
        assert_eq!(c.validate(), Ok(()));
        c.period_s = 0.1;
        assert!(c.validate().unwrap_err().to_string().contains("safety.period_s"));
        let c = ControlConfig { source: SourceKind::Hold, ..ControlConfig::default() };
        assert!(c.validate().unwrap_err().to_string().contains("auto_start"));
        let c = ControlConfig { stale_frame_s: f64::NAN, ..ControlConfig::default() };
        assert!(c.validate().unwrap_err().to_string().contains("stale_frame_s"));
    }
}
