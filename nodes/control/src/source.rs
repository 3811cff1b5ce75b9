//! Action sources: what the rig loop asks for an action each tick. The scripted expert (the
//! sim bridge's `/sim/expert/action`), teleop and the policy server ([`crate::policy`]), behind
//! the same trait. A source proposes an arm command (any `ArmCommand` mode) and may say the
//! task is over; the loop passes the proposal through the safety layer, never the source.

use crate::step::ChunkRef;
use labrig_msgs::Nanos;
use labrig_msgs::rig::{ArmCommand, RobotState, Step, TeleopState};
use labrig_msgs::std_msgs::StringMsg;
use labrig_msgs::topics;
use labrig_runtime::ros::{Ros, RosError, RosSubscription};

/// A source's action for one tick.
#[derive(Debug, Clone, PartialEq)]
pub struct Proposal {
    pub command: ArmCommand,
    /// The deadman (teleop grip) or the source's own go-ahead; a disabled proposal holds.
    pub movement_enabled: bool,
    /// A policy's action: the chunk and row it came from (recorded in the Step).
    pub chunk: Option<ChunkRef>,
}

/// What a source says about the task at a tick.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Verdict {
    Running,
    Succeeded,
    /// The task failed; `why` goes into the episode's end event where the source knows it.
    Failed {
        why: Option<String>,
    },
}

/// What a source sees of a tick while an episode is recorded: the observation a policy is
/// given (the Step's robot state and the pixels of the cameras it names).
#[derive(Debug)]
pub struct TickView<'a> {
    pub tick: Nanos,
    pub step_index: u64,
    pub episode_id: &'a str,
    /// The Step's robot state (the gripper's measured opening in `gripper_position`).
    pub robot: RobotState,
    /// The sim scene's JSON (empty on a real rig) and its seed.
    pub scene: &'a str,
    pub scene_seed: Option<u64>,
    /// The episode's language instruction (a remote policy's prompt).
    pub instruction: &'a str,
    /// Per camera the source names ([`ActionSource::cameras`]), its frame at the tick.
    pub images: Vec<(&'a str, std::sync::Arc<RgbFrame>)>,
}

/// One camera frame's pixels, copied out of shared memory.
#[derive(Debug, Clone, PartialEq)]
pub struct RgbFrame {
    pub width: u32,
    pub height: u32,
    /// RGB8, tightly packed.
    pub pixels: Vec<u8>,
    pub capture_ns: i64,
}

/// The scripted expert's plan at a tick (`/sim/expert/status` from a bridge run with
/// `--expert-resume`), what the expert takeover rule measures the arm against.
#[derive(Debug, Clone, PartialEq)]
pub struct Guidance {
    pub stamp_ns: i64,
    /// The current phase's target for the TCP (m, base frame).
    pub target: [f64; 3],
    /// Its whole path for the scene: a polyline from the reset pose's TCP.
    pub plan: Vec<[f64; 3]>,
    /// The task is solved (judged on the physics).
    pub success: bool,
}

/// Why a source had no action for a tick.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum SourceError {
    #[error("no action from {from} yet")]
    Silent { from: &'static str },
    #[error("{from}'s newest action is {age_ms:.1} ms old at the tick (limit {limit_ms:.1} ms)")]
    Stale { from: &'static str, age_ms: f64, limit_ms: f64 },
}

pub trait ActionSource: Send {
    fn name(&self) -> &'static str;
    /// The `Step::SOURCE_*` value recorded with its actions.
    fn kind(&self) -> u8;
    /// Takes what arrived since the last call.
    fn poll(&mut self) -> Result<(), RosError>;
    /// Whether the action for the tick at `tick` has arrived (lockstep waits for it).
    fn has(&self, tick: Nanos) -> bool;
    /// The action for the tick at `tick`; `max_age` bounds how old it may be.
    fn action(&mut self, tick: Nanos, max_age: Nanos) -> Result<Proposal, SourceError>;
    /// The task's state as the source judges it at the tick (its newest judgement since the
    /// episode began).
    fn verdict(&self, tick: Nanos) -> Verdict;
    /// A new episode begins at `start` (a source with memory of the last one forgets it).
    fn restart(&mut self, start: Nanos);
    /// The cameras whose pixels the source observes (the loop copies their frames).
    fn cameras(&self) -> &[String] {
        &[]
    }
    /// The tick as recorded, before [`ActionSource::has`] and [`ActionSource::action`] are
    /// asked (a policy sends its request from here).
    fn observe(&mut self, _view: TickView<'_>) {}
    /// Whether an episode may start at `tick` (auto_start on the wall clock): by default, when
    /// the source has an action for it.
    fn ready(&mut self, tick: Nanos, max_age: Nanos) -> bool {
        self.action(tick, max_age).is_ok()
    }
    /// What the source did over the run, for the loop's summary.
    fn stats(&self) -> Option<serde_json::Value> {
        None
    }
    /// Whether what [`ActionSource::observe`] decides from has arrived for the tick (lockstep
    /// waits for it before observing, as for the action before acting): an operator's status
    /// for a takeover ([`crate::takeover`]).
    fn settled(&self, _tick: Nanos) -> bool {
        true
    }
    /// An operator: whether it holds control at the tick (the Quest's grip).
    fn engaged(&self, _tick: Nanos) -> bool {
        false
    }
    /// An operator's link: whether it could take over now (the Quest: a state at most 100 ms
    /// old with the controller connected). A source without one is always linked.
    fn linked(&self, _tick: Nanos) -> bool {
        true
    }
    /// The scripted expert: its target and plan at the tick, when its bridge sends them.
    fn guidance(&self, _tick: Nanos) -> Option<Guidance> {
        None
    }
    /// A policy: an operator takes over (`true`: drop what it has and asks for, ask for
    /// nothing) or hands back (`false`: drop what it has, ask afresh).
    fn suspend(&mut self, _on: bool) {}
}

/// The sim bridge's scripted expert (`labrig sim run --expert`): its action for every sim
/// state on `/sim/expert/action`, and its progress (done, success judged on the physics) on
/// `/sim/expert/status`.
pub struct ScriptedExpert {
    actions: RosSubscription<ArmCommand>,
    status: RosSubscription<StringMsg>,
    latest: Option<ArmCommand>,
    /// (stamp, done, success) of the newest status.
    progress: Option<(i64, bool, bool)>,
    /// Its target and plan, when the status has them (`--expert-resume`).
    guidance: Option<Guidance>,
    /// The current episode's first tick: older verdicts are the last episode's.
    since_ns: i64,
}

impl std::fmt::Debug for ScriptedExpert {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ScriptedExpert").field("progress", &self.progress).finish_non_exhaustive()
    }
}

impl ScriptedExpert {
    pub fn new(ros: &mut Ros) -> Result<ScriptedExpert, RosError> {
        Ok(ScriptedExpert {
            actions: ros.subscription_on(&topics::SIM_EXPERT_ACTION, 100)?,
            status: ros.subscription_on(&topics::SIM_EXPERT_STATUS, 100)?,
            latest: None,
            progress: None,
            guidance: None,
            since_ns: i64::MIN,
        })
    }
}

fn stamp_ns(c: &ArmCommand) -> i64 {
    Nanos::from(c.header.stamp).0
}

impl ActionSource for ScriptedExpert {
    fn name(&self) -> &'static str {
        "the scripted expert (/sim/expert/action)"
    }

    fn kind(&self) -> u8 {
        Step::SOURCE_SCRIPTED
    }

    fn poll(&mut self) -> Result<(), RosError> {
        while let Some(a) = self.actions.try_take()? {
            self.latest = Some(a.msg);
        }
        while let Some(s) = self.status.try_take()? {
            let Ok(v) = serde_json::from_str::<serde_json::Value>(&s.msg.data) else {
                tracing::warn!("/sim/expert/status: not JSON: {:?}", s.msg.data);
                continue;
            };
            let stamp = v["stamp_ns"].as_i64().unwrap_or(i64::MIN);
            self.progress = Some((stamp, v["done"] == true, v["success"] == true));
            let point = |p: &serde_json::Value| -> Option<[f64; 3]> {
                let a = p.as_array().filter(|a| a.len() == 3)?;
                Some([a[0].as_f64()?, a[1].as_f64()?, a[2].as_f64()?])
            };
            let plan: Option<Vec<[f64; 3]>> = v["plan"].as_array().map(|a| a.iter().filter_map(point).collect());
            self.guidance = point(&v["target"]).zip(plan).map(|(target, plan)| Guidance {
                stamp_ns: stamp,
                target,
                plan,
                success: v["success"] == true,
            });
        }
        Ok(())
    }

    fn has(&self, tick: Nanos) -> bool {
        let tick_ns = tick.0;
        self.latest.as_ref().is_some_and(|a| stamp_ns(a) >= tick_ns)
            && self.progress.is_some_and(|(t, _, _)| t >= tick_ns)
    }

    fn action(&mut self, tick: Nanos, max_age: Nanos) -> Result<Proposal, SourceError> {
        let (tick_ns, max_age_ns) = (tick.0, max_age.0);
        let source = "the scripted expert";
        let a = self.latest.as_ref().ok_or(SourceError::Silent { from: source })?;
        let age = tick_ns - stamp_ns(a);
        if age > max_age_ns {
            return Err(SourceError::Stale {
                from: source,
                age_ms: age as f64 / 1e6,
                limit_ms: max_age_ns as f64 / 1e6,
            });
        }
        Ok(Proposal { command: a.clone(), movement_enabled: true, chunk: None })
    }

    fn verdict(&self, _tick: Nanos) -> Verdict {
        match self.progress {
            Some((t, true, ok)) if t >= self.since_ns => {
                if ok {
                    Verdict::Succeeded
                } else {
                    Verdict::Failed { why: None }
                }
            }
            _ => Verdict::Running,
        }
    }

    /// Actions are matched to ticks by their sim-time stamps; verdicts count from the
    /// episode's first tick.
    fn restart(&mut self, start: Nanos) {
        self.since_ns = start.0;
    }

    fn settled(&self, tick: Nanos) -> bool {
        self.progress.is_some_and(|(t, _, _)| t >= tick.0)
    }

    fn guidance(&self, _tick: Nanos) -> Option<Guidance> {
        self.guidance.clone()
    }
}

/// The Quest teleop node (`labrig-teleop`): its DROID cartesian-velocity action on
/// `/teleop/action` and the controller on `/teleop/state` (the deadman, connected). Actions
/// come at the headset's rate on the wall clock, so their age is the wall clock's now minus
/// their DDS source timestamp (when the node published them; the two processes share the
/// machine's clock, or a synchronised one), whatever the loop's own clock: older than the
/// source's limit, the arm holds. (Taking the age from when the loop polled them would hide up
/// to a tick of silence: the loop polls once per tick.) A state
/// with the deadman released (or the controller gone) holds too. Episode events come from the
/// node's `/rig/request` (A/X success, B/Y failure), not from a verdict.
pub struct Teleop {
    actions: RosSubscription<ArmCommand>,
    states: RosSubscription<TeleopState>,
    /// The newest action and when it was sent (wall ns).
    latest: Option<(ArmCommand, i64)>,
    /// The newest state and when it arrived.
    state: Option<(TeleopState, std::time::Instant)>,
    max_age: std::time::Duration,
}

/// A takeover holds while the Quest's state is this fresh (the node sends one per reading,
/// and at least every 100 ms), as the policy's deadman does.
pub const TELEOP_STATE_MAX_AGE: std::time::Duration = std::time::Duration::from_millis(100);

impl std::fmt::Debug for Teleop {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Teleop").field("max_age", &self.max_age).finish_non_exhaustive()
    }
}

impl Teleop {
    pub fn new(ros: &mut Ros, max_age: std::time::Duration) -> Result<Teleop, RosError> {
        Ok(Teleop {
            actions: ros.subscription_on(&topics::TELEOP_ACTION, 100)?,
            states: ros.subscription_on(&topics::TELEOP_STATE, 100)?,
            latest: None,
            state: None,
            max_age,
        })
    }
}

impl ActionSource for Teleop {
    fn name(&self) -> &'static str {
        "teleop (/teleop/action)"
    }

    fn kind(&self) -> u8 {
        Step::SOURCE_TELEOP
    }

    fn poll(&mut self) -> Result<(), RosError> {
        while let Some(a) = self.actions.try_take()? {
            let sent = a.source_time.unwrap_or(a.receive_time).0;
            self.latest = Some((a.msg, sent));
        }
        while let Some(s) = self.states.try_take()? {
            self.state = Some((s.msg, std::time::Instant::now()));
        }
        Ok(())
    }

    /// Teleop runs at its own rate: a tick never waits for it.
    fn has(&self, _tick: Nanos) -> bool {
        true
    }

    fn action(&mut self, _tick: Nanos, max_age: Nanos) -> Result<Proposal, SourceError> {
        let max_age_ns = max_age.0;
        let source = "teleop";
        let (a, sent) = self.latest.as_ref().ok_or(SourceError::Silent { from: source })?;
        let limit = (self.max_age.as_nanos() as i64).min(max_age_ns);
        let age = labrig_runtime::Clock::Wall.now().0 - sent;
        if age > limit {
            return Err(SourceError::Stale { from: source, age_ms: age as f64 / 1e6, limit_ms: limit as f64 / 1e6 });
        }
        let enabled = self.state.as_ref().is_some_and(|(s, _)| s.movement_enabled && s.controller_connected);
        Ok(Proposal { command: a.clone(), movement_enabled: enabled, chunk: None })
    }

    fn verdict(&self, _tick: Nanos) -> Verdict {
        Verdict::Running
    }

    fn restart(&mut self, _start: Nanos) {}

    /// The grip held on a connected controller, the state fresh.
    fn engaged(&self, _tick: Nanos) -> bool {
        self.state
            .as_ref()
            .is_some_and(|(s, at)| s.movement_enabled && s.controller_connected && at.elapsed() <= TELEOP_STATE_MAX_AGE)
    }

    fn linked(&self, _tick: Nanos) -> bool {
        self.state.as_ref().is_some_and(|(s, at)| s.controller_connected && at.elapsed() <= TELEOP_STATE_MAX_AGE)
    }
}
