//! Operator corrections during a policy rollout (human-gated DAgger): `[policy] takeover`.
//!
//! [`Takeover`] wraps the policy source and an operator's source. Each recorded tick it
//! decides, in [`ActionSource::observe`] (before the policy's request goes out), who acts:
//!
//! - `takeover = "teleop"`: the Quest operator, while the grip is held on a connected
//!   controller (`/teleop/state` no older than 0.1 s); the actions are `/teleop/action`'s.
//! - `takeover = "expert"` (sim only): the sim bridge's scripted expert, by the rule of
//!   [`ExpertRule`], on the expert's status for the tick (`labrig sim run --expert
//!   --expert-resume`: its phase target and its plan, re-planned from the state it finds).
//!
//! While the operator acts the policy is suspended: its chunks and any request in flight are
//! dropped (an answer that comes late is ignored, as an earlier episode's is) and it asks for
//! nothing, but it keeps observing, so when the operator lets go it asks at once, from the
//! current observation and the last `n_obs_steps` (the operator's ticks). In lockstep with
//! `lockstep_delay_steps = 0` the hand-back tick waits for that chunk; with a delay, or on the
//! wall clock, the arm holds for the round trip (recorded as held policy steps).
//!
//! Who acted goes into each Step's `action_source` (the operator's kind: TELEOP for the
//! Quest, SCRIPTED for the expert), so no message changes; the loop counts takeovers and
//! operator steps from that.

use crate::config::PolicySourceConfig;
use crate::source::{ActionSource, Guidance, Proposal, SourceError, TickView, Verdict};
use labrig_msgs::Nanos;
use labrig_runtime::ros::RosError;
use std::collections::VecDeque;

/// When the scripted expert takes over from the policy and hands back; deterministic in
/// lockstep (it sees only the tick's TCP and the expert's status stamped at the tick).
///
/// While the policy acts, the expert takes over at a tick when, and the task is unsolved:
/// - *stalled*: over the last `takeover_stall_ticks` ticks the TCP made less than
///   `takeover_progress_m` progress toward the expert's current target (per tick, how much
///   closer it came to the target the expert had at that tick, summed: a policy that moves
///   but goes nowhere stalls as one that holds does); or
/// - *strayed*: the TCP is farther than `takeover_distance_m` from the expert's plan (the
///   polyline from the reset pose's TCP through its phases' targets for the scene as it is
///   now: above the object, at it, lifted, over the bin, lowered).
///
/// It hands back after `takeover_ticks` ticks (or at once when the task is solved), and the
/// stall window starts empty again, so the policy has `takeover_stall_ticks` ticks before it
/// can stall again. At most `takeover_max` takeovers per episode.
///
/// The defaults come from the expert's own pace (sim/src/expert.rs): it leads the TCP at
/// most 2 cm per tick and never spends 40 ticks (2 s) without 1 cm of progress toward its
/// target (a grasp or release waits at most a few ticks; a phase times out after 80), so a
/// policy doing that is stuck. 40 ticks of the expert carry the TCP up to 80 cm: from a
/// stall, through an approach and a grasp, or a carry. 0.15 m off its plan is three object
/// sizes off any path it would take. Three takeovers leave most of a 300-step rollout to the
/// policy.
#[derive(Debug, Clone)]
pub struct ExpertRule {
    stall_ticks: usize,
    progress_m: f64,
    distance_m: f64,
    ticks: u32,
    max: u32,
    /// Per policy tick, how much closer the TCP came to that tick's target (m).
    progress: VecDeque<f64>,
    last_tcp: Option<[f64; 3]>,
    engaged: bool,
    operator_ticks: u32,
    takeovers: u32,
}

/// Why the expert took over.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Trigger {
    /// Progress toward the target over the window (m).
    Stalled(f64),
    /// Distance from the plan (m).
    Strayed(f64),
}

impl ExpertRule {
    pub fn new(cfg: &PolicySourceConfig) -> ExpertRule {
        ExpertRule {
            stall_ticks: cfg.takeover_stall_ticks as usize,
            progress_m: cfg.takeover_progress_m,
            distance_m: cfg.takeover_distance_m,
            ticks: cfg.takeover_ticks,
            max: cfg.takeover_max,
            progress: VecDeque::new(),
            last_tcp: None,
            engaged: false,
            operator_ticks: 0,
            takeovers: 0,
        }
    }

    /// A new episode.
    pub fn reset(&mut self) {
        self.progress.clear();
        self.last_tcp = None;
        self.engaged = false;
        self.operator_ticks = 0;
        self.takeovers = 0;
    }

    pub fn engaged(&self) -> bool {
        self.engaged
    }

    /// One tick: the TCP's position and the expert's status at it. Whether the expert acts at
    /// this tick, and what made it take over when it does from this tick on.
    pub fn update(&mut self, tcp: [f64; 3], g: &Guidance) -> (bool, Option<Trigger>) {
        if self.engaged {
            if self.operator_ticks >= self.ticks || g.success {
                self.engaged = false;
                self.progress.clear();
                self.last_tcp = Some(tcp);
                return (false, None);
            }
            self.operator_ticks += 1;
            return (true, None);
        }
        if let Some(prev) = self.last_tcp {
            self.progress.push_back(dist(prev, g.target) - dist(tcp, g.target));
            while self.progress.len() > self.stall_ticks {
                self.progress.pop_front();
            }
        }
        self.last_tcp = Some(tcp);
        if g.success || self.takeovers >= self.max {
            return (false, None);
        }
        let made: f64 = self.progress.iter().sum();
        let off = distance_to_polyline(tcp, &g.plan);
        let trigger = if self.progress.len() >= self.stall_ticks && made < self.progress_m {
            Some(Trigger::Stalled(made))
        } else if off > self.distance_m {
            Some(Trigger::Strayed(off))
        } else {
            None
        };
        if trigger.is_some() {
            self.engaged = true;
            self.operator_ticks = 1;
            self.takeovers += 1;
        }
        (self.engaged, trigger)
    }
}

fn dist(a: [f64; 3], b: [f64; 3]) -> f64 {
    ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt()
}

/// The distance from `p` to the polyline through `points` (infinite for none).
pub fn distance_to_polyline(p: [f64; 3], points: &[[f64; 3]]) -> f64 {
    if points.len() == 1 {
        return dist(p, points[0]);
    }
    points
        .windows(2)
        .map(|w| {
            let (a, b) = (w[0], w[1]);
            let ab = [b[0] - a[0], b[1] - a[1], b[2] - a[2]];
            let ap = [p[0] - a[0], p[1] - a[1], p[2] - a[2]];
            let len2 = ab.iter().map(|v| v * v).sum::<f64>();
            let t = if len2 > 0.0 {
                (ap.iter().zip(&ab).map(|(x, y)| x * y).sum::<f64>() / len2).clamp(0.0, 1.0)
            } else {
                0.0
            };
            dist(p, [a[0] + t * ab[0], a[1] + t * ab[1], a[2] + t * ab[2]])
        })
        .fold(f64::INFINITY, f64::min)
}

/// The policy with an operator who may take over (see the module doc).
pub struct Takeover {
    policy: Box<dyn ActionSource>,
    operator: Box<dyn ActionSource>,
    /// `takeover = "expert"`: the rule; `"teleop"`: the operator's grip decides.
    rule: Option<ExpertRule>,
    engaged: bool,
    warned_guidance: bool,
    warned_link: bool,
}

impl std::fmt::Debug for Takeover {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Takeover").field("engaged", &self.engaged).field("rule", &self.rule).finish_non_exhaustive()
    }
}

impl Takeover {
    pub fn new(policy: Box<dyn ActionSource>, operator: Box<dyn ActionSource>, rule: Option<ExpertRule>) -> Takeover {
        Takeover { policy, operator, rule, engaged: false, warned_guidance: false, warned_link: false }
    }

    fn actor(&self) -> &dyn ActionSource {
        if self.engaged { self.operator.as_ref() } else { self.policy.as_ref() }
    }
}

impl ActionSource for Takeover {
    fn name(&self) -> &'static str {
        "the policy server, with an operator who may take over"
    }

    fn kind(&self) -> u8 {
        self.actor().kind()
    }

    fn poll(&mut self) -> Result<(), RosError> {
        self.policy.poll()?;
        self.operator.poll()
    }

    fn has(&self, tick: Nanos) -> bool {
        self.actor().has(tick)
    }

    /// The operator's, while engaged; else the policy's, which holds (movement disabled, the
    /// chunk's timing going on) while a Quest operator's link is gone: with no fresh state, or
    /// the controller off, nobody could take over, so the policy does not move the arm either.
    fn action(&mut self, tick: Nanos, max_age: Nanos) -> Result<Proposal, SourceError> {
        if self.engaged {
            return self.operator.action(tick, max_age);
        }
        let mut p = self.policy.action(tick, max_age)?;
        if self.rule.is_none() && !self.operator.linked(tick) {
            if p.movement_enabled && !self.warned_link {
                tracing::warn!("no fresh state from the operator's Quest: the policy holds the arm until it returns");
                self.warned_link = true;
            }
            p.movement_enabled = false;
        } else {
            self.warned_link = false;
        }
        Ok(p)
    }

    /// The policy's (in the sim, `/sim/task`): the operator's opinion of the task is not the
    /// rollout's.
    fn verdict(&self, tick: Nanos) -> Verdict {
        self.policy.verdict(tick)
    }

    fn restart(&mut self, start: Nanos) {
        self.policy.restart(start);
        self.operator.restart(start);
        if let Some(r) = &mut self.rule {
            r.reset();
        }
        self.engaged = false;
    }

    fn cameras(&self) -> &[String] {
        self.policy.cameras()
    }

    /// The expert's rule needs its status for the tick.
    fn settled(&self, tick: Nanos) -> bool {
        self.rule.is_none() || self.operator.settled(tick)
    }

    fn observe(&mut self, view: TickView<'_>) {
        let tick = view.tick;
        let tcp =
            [view.robot.cartesian_position[0], view.robot.cartesian_position[1], view.robot.cartesian_position[2]];
        let (engaged, why) = match &mut self.rule {
            None => (self.operator.engaged(tick), None),
            Some(rule) => match self.operator.guidance(tick) {
                Some(g) => rule.update(tcp, &g),
                None => {
                    if !self.warned_guidance {
                        tracing::warn!(
                            "no expert target or plan at the tick: the expert cannot take over (is the sim bridge run with --expert --expert-resume?)"
                        );
                        self.warned_guidance = true;
                    }
                    (rule.engaged(), None)
                }
            },
        };
        if engaged && !self.engaged {
            tracing::info!(step = view.step_index, operator = self.operator.name(), trigger = ?why, "the operator takes over");
            self.policy.suspend(true);
        } else if !engaged && self.engaged {
            tracing::info!(step = view.step_index, "the operator hands back: the policy asks afresh");
            self.policy.suspend(false);
        }
        self.engaged = engaged;
        self.policy.observe(view);
    }

    fn ready(&mut self, tick: Nanos, max_age: Nanos) -> bool {
        self.policy.ready(tick, max_age)
    }

    fn stats(&self) -> Option<serde_json::Value> {
        self.policy.stats()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use labrig_msgs::rig::{ArmCommand, Step};

    fn rule() -> ExpertRule {
        ExpertRule::new(&PolicySourceConfig::default())
    }

    fn guide(target: [f64; 3]) -> Guidance {
        Guidance { stamp_ns: 0, target, plan: vec![[0.0, 0.0, 0.5], [0.5, 0.0, 0.1]], success: false }
    }

    #[test]
    fn a_policy_that_holds_still_is_taken_over_after_the_stall_window_and_handed_back_after_m_ticks() {
        let mut r = rule();
        let g = guide([0.5, 0.0, 0.1]);
        let tcp = [0.0, 0.0, 0.5];
        // The first tick has no progress to measure: 40 measured ticks take 41 ticks.
        for k in 0..40 {
            assert_eq!(r.update(tcp, &g), (false, None), "tick {k}");
        }
        let (on, why) = r.update(tcp, &g);
        assert!(on);
        assert!(matches!(why, Some(Trigger::Stalled(m)) if m.abs() < 1e-12), "{why:?}");
        for k in 1..40 {
            assert_eq!(r.update(tcp, &g), (true, None), "operator tick {k}");
        }
        assert_eq!(r.update(tcp, &g), (false, None), "handed back after 40 operator ticks");
        // The window starts empty again: the hand-back tick and 39 more, and the 41st stalls.
        for _ in 0..39 {
            assert!(!r.update(tcp, &g).0);
        }
        assert!(r.update(tcp, &g).0, "a second stall");
    }

    #[test]
    fn a_policy_that_moves_toward_the_target_is_left_alone() {
        let mut r = rule();
        let g = guide([0.5, 0.0, 0.1]);
        for k in 0..200 {
            // 1 mm per tick toward the target: 4 cm per window.
            let s = (k as f64 * 0.001).min(0.5);
            let tcp = [s, 0.0, 0.5 - 0.8 * s];
            assert!(!r.update(tcp, &g).0, "tick {k}");
        }
    }

    #[test]
    fn a_policy_that_moves_but_goes_nowhere_stalls() {
        let mut r = rule();
        let g = guide([0.5, 0.0, 0.1]);
        let mut fired = None;
        for k in 0..100 {
            // Back and forth by 2 cm around the start.
            let tcp = [if k % 2 == 0 { 0.0 } else { 0.02 }, 0.0, 0.5];
            if r.update(tcp, &g).0 {
                fired = Some(k);
                break;
            }
        }
        assert_eq!(fired, Some(40));
    }

    #[test]
    fn straying_from_the_plan_takes_over_at_once_and_a_solved_task_never() {
        let mut r = rule();
        let g = guide([0.5, 0.0, 0.1]);
        assert!(!r.update([0.25, 0.1, 0.3], &g).0, "0.1 m off the plan");
        let (on, why) = r.update([0.25, 0.2, 0.3], &g);
        assert!(on);
        assert!(matches!(why, Some(Trigger::Strayed(d)) if (d - 0.2).abs() < 1e-9), "{why:?}");
        let mut r = rule();
        let solved = Guidance { success: true, ..g.clone() };
        assert!(!r.update([0.25, 0.5, 0.3], &solved).0);
        // A solved task hands back at once.
        let mut r = rule();
        assert!(r.update([0.25, 0.5, 0.3], &g).0);
        assert!(!r.update([0.25, 0.5, 0.3], &solved).0);
    }

    #[test]
    fn at_most_three_takeovers_per_episode() {
        let mut r = rule();
        let g = guide([0.5, 0.0, 0.1]);
        let off = [0.0, 1.0, 0.5];
        let mut takeovers = 0;
        let mut was = false;
        for _ in 0..1000 {
            let on = r.update(off, &g).0;
            takeovers += u32::from(on && !was);
            was = on;
        }
        assert_eq!(takeovers, 3);
        r.reset();
        assert!(r.update(off, &g).0, "a new episode may be taken over again");
    }

    #[test]
    fn the_distance_to_the_plan_is_to_its_nearest_segment() {
        let plan = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 1.0, 0.0]];
        assert!((distance_to_polyline([0.5, 0.3, 0.0], &plan) - 0.3).abs() < 1e-12);
        assert!((distance_to_polyline([1.2, 0.5, 0.0], &plan) - 0.2).abs() < 1e-12);
        assert!((distance_to_polyline([-1.0, 0.0, 0.0], &plan) - 1.0).abs() < 1e-12);
        assert!((distance_to_polyline([0.0, 0.0, 2.0], &plan[..1]) - 2.0).abs() < 1e-12);
        assert_eq!(distance_to_polyline([0.0; 3], &[]), f64::INFINITY);
    }

    /// A scripted stand-in for the policy and the operator: logs what it is told.
    struct Fake {
        kind: u8,
        /// Ticks [from, to) the operator's grip is held.
        engaged_from: Option<(i64, i64)>,
        /// The operator's link lost from this tick on.
        linked_until: Option<i64>,
        log: std::sync::Arc<std::sync::Mutex<Vec<String>>>,
    }

    impl ActionSource for Fake {
        fn name(&self) -> &'static str {
            "fake"
        }
        fn kind(&self) -> u8 {
            self.kind
        }
        fn poll(&mut self) -> Result<(), RosError> {
            Ok(())
        }
        fn has(&self, _tick: Nanos) -> bool {
            true
        }
        fn action(&mut self, _tick: Nanos, _max_age: Nanos) -> Result<Proposal, SourceError> {
            Ok(Proposal { command: ArmCommand::default(), movement_enabled: true, chunk: None })
        }
        fn linked(&self, tick: Nanos) -> bool {
            self.linked_until.is_none_or(|end| tick.0 < end)
        }
        fn verdict(&self, _tick: Nanos) -> Verdict {
            Verdict::Running
        }
        fn restart(&mut self, _start: Nanos) {}
        fn engaged(&self, tick: Nanos) -> bool {
            self.engaged_from.is_some_and(|(a, b)| (a..b).contains(&tick.0))
        }
        fn suspend(&mut self, on: bool) {
            self.log.lock().unwrap().push(format!("suspend {on}"));
        }
        fn observe(&mut self, view: TickView<'_>) {
            self.log.lock().unwrap().push(format!("observe {}", view.tick.0));
        }
    }

    fn view(t: i64) -> TickView<'static> {
        TickView {
            tick: Nanos(t),
            step_index: t as u64,
            episode_id: "e",
            robot: Default::default(),
            scene: "",
            scene_seed: None,
            instruction: "",
            images: vec![],
        }
    }

    /// The teleop grip: the operator acts (and is recorded) from the tick the grip is held;
    /// the policy is suspended then and resumed (to ask afresh) the tick it is let go, and it
    /// observes every tick throughout.
    #[test]
    fn the_grip_switches_who_acts_and_suspends_and_resumes_the_policy() {
        let log = std::sync::Arc::new(std::sync::Mutex::new(Vec::new()));
        let policy = Fake { kind: Step::SOURCE_POLICY, engaged_from: None, linked_until: None, log: log.clone() };
        let operator =
            Fake { kind: Step::SOURCE_TELEOP, engaged_from: Some((3, 6)), linked_until: None, log: Default::default() };
        let mut t = Takeover::new(Box::new(policy), Box::new(operator), None);
        let mut kinds = vec![];
        for k in 0..8 {
            t.observe(view(k));
            kinds.push(t.kind());
        }
        const P: u8 = Step::SOURCE_POLICY;
        const T: u8 = Step::SOURCE_TELEOP;
        assert_eq!(kinds, vec![P, P, P, T, T, T, P, P]);
        let log = log.lock().unwrap().clone();
        let want: Vec<String> = (0..8)
            .flat_map(|k| match k {
                3 => vec!["suspend true".to_string(), format!("observe {k}")],
                6 => vec!["suspend false".to_string(), format!("observe {k}")],
                _ => vec![format!("observe {k}")],
            })
            .collect();
        assert_eq!(log, want, "suspended at the takeover's tick, resumed at the hand-back's, observing every tick");
        t.restart(Nanos(100));
        assert_eq!(t.kind(), P);
    }

    /// With a Quest operator whose link is gone (no fresh state, controller off) the policy's
    /// rows still come but the arm holds: nobody could take over. The link back, it moves.
    #[test]
    fn the_policy_holds_while_the_operators_link_is_gone() {
        let policy =
            Fake { kind: Step::SOURCE_POLICY, engaged_from: None, linked_until: None, log: Default::default() };
        let operator =
            Fake { kind: Step::SOURCE_TELEOP, engaged_from: None, linked_until: Some(4), log: Default::default() };
        let mut t = Takeover::new(Box::new(policy), Box::new(operator), None);
        let moves: Vec<bool> =
            (0..6).map(|k| t.action(Nanos(k), Nanos(1_000_000_000)).unwrap().movement_enabled).collect();
        assert_eq!(moves, [true, true, true, true, false, false]);
        // The expert (a rule) has no link to lose: its policy is never held for it.
        let rule = ExpertRule::new(&PolicySourceConfig::default());
        let policy =
            Fake { kind: Step::SOURCE_POLICY, engaged_from: None, linked_until: None, log: Default::default() };
        let operator =
            Fake { kind: Step::SOURCE_SCRIPTED, engaged_from: None, linked_until: Some(0), log: Default::default() };
        let mut t = Takeover::new(Box::new(policy), Box::new(operator), Some(rule));
        assert!(t.action(Nanos(3), Nanos(1_000_000_000)).unwrap().movement_enabled);
    }
}
