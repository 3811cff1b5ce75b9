//! The node's configuration, which every other module reads: the control keys
//! ([`ControlConfig`]), the action source and clock, `[policy]` ([`PolicySourceConfig`]: the
//! schedule of chunks, blending, who may take over). It imports only [`crate::remote`]'s `[remote]`
//! keys and [`crate::info`]'s action spaces, which import nothing above them.

use crate::info::EXECUTABLE;
use labrig_arm::safety::SafetyConfig;
use labrig_msgs::Invalid;
use labrig_msgs::rig::RIG_CAMERAS;
use labrig_runtime::RosConfig;
use serde::{Deserialize, Serialize};
use std::path::PathBuf;

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
    /// The policy server (`labrig-policy run`): action chunks for the loop's observations
    /// (`[policy]`); in the sim `/sim/task` judges success, on a real rig the operator.
    Policy,
    /// A policy behind openpi's websocket protocol (pi0 / pi0.5-DROID on openpi's server, or
    /// `labrig policy run --openpi`): `[remote]` maps DROID's observation and 15 Hz joint
    /// velocity chunks; scheduled, judged and made safe as `policy` is (`[policy]`).
    Remote,
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
    /// Control period (s); DROID: 0.05 (20 Hz).
    pub period_s: f64,
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
    /// A camera frame older than this at a tick is stale (s).
    pub stale_frame_s: f64,
    /// A source action older than this at a tick is refused (s; realtime only, lockstep
    /// waits for the tick's own action).
    pub max_action_age_s: f64,
    /// Teleop: an action that arrived longer ago than this is not followed (s). The headset
    /// sends ~72 readings/s, so 35 ms is ~2 missed ones; with a 50 ms tick a vanished
    /// controller holds the arm within 35 + 50 ms.
    pub teleop_max_age_s: f64,
    /// How long a lockstep tick waits for the source's action before holding (s).
    pub source_timeout_s: f64,
    /// On the sim's clock, no new tick for this long (s, wall time: the sim or the arm node is
    /// gone, its clock stopped): the open episode stops, naming it, and the node exits with
    /// an error.
    pub tick_timeout_s: f64,
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
    /// The policy source (`source = "policy"`, and the scheduling of `source = "remote"`).
    pub policy: PolicySourceConfig,
    /// The openpi server and DROID's conventions (`source = "remote"`).
    pub remote: crate::remote::RemoteConfig,
    /// The rig's camera calibrations (a folder of `<camera>.json`, e.g. `calibration/<rig>`):
    /// the loop warns at start for each of `cameras` whose calibration is missing, unreadable
    /// or older than `calibration_max_age_s` (DROID's GUI warns after an hour).
    pub calibration: Option<PathBuf>,
    pub calibration_max_age_s: f64,
    /// Append the loop's figures per window of `window_s` seconds to this file, one JSON line
    /// each (ticks, missed and held ticks, steps with a missing or stale frame, period jitter and
    /// camera skew percentiles): `labrig bench soak` reads them. None by default.
    pub window_stats: Option<PathBuf>,
    pub window_s: f64,
}

impl Default for ControlConfig {
    fn default() -> Self {
        ControlConfig {
            ros: RosConfig::default(),
            source: SourceKind::Scripted,
            clock: ClockKind::Sim,
            period_s: 0.05,
            auto_start: true,
            episodes: 0,
            reseed: true,
            first_seed: 0,
            max_steps: 400,
            cameras: RIG_CAMERAS.iter().map(|c| c.to_string()).collect(),
            frames_namespace: labrig_runtime::frames::default_namespace(),
            stale_frame_s: 0.1,
            max_action_age_s: 0.15,
            teleop_max_age_s: 0.035,
            source_timeout_s: 5.0,
            tick_timeout_s: 2.0,
            home_tolerance_rad: 0.02,
            reset_timeout_s: 20.0,
            realtime_priority: 20,
            lab: "LABRIG".into(),
            user: "operator".into(),
            // The loop makes its own commands each tick: no age check on them.
            safety: SafetyConfig { max_command_age_s: 0.0, ..SafetyConfig::default() },
            urdf: None,
            policy: PolicySourceConfig::default(),
            remote: crate::remote::RemoteConfig::default(),
            calibration: None,
            calibration_max_age_s: labrig_episode::calibration::DEFAULT_MAX_AGE_S,
            window_stats: None,
            window_s: 300.0,
        }
    }
}

impl ControlConfig {
    pub fn validate(&self) -> Result<(), Invalid> {
        if !(self.period_s.is_finite() && (0.001..=1.0).contains(&self.period_s)) {
            return Err(Invalid::new("period_s", format!("period_s = {} must be in 0.001..=1", self.period_s)));
        }
        if (self.safety.period_s - self.period_s).abs() > 1e-9 {
            return Err(Invalid::new(
                "safety.period_s",
                format!(
                    "safety.period_s = {} must equal period_s = {} (the per-step limits are per period)",
                    self.safety.period_s, self.period_s
                ),
            ));
        }
        for (name, v) in [
            ("stale_frame_s", self.stale_frame_s),
            ("max_action_age_s", self.max_action_age_s),
            ("source_timeout_s", self.source_timeout_s),
            ("tick_timeout_s", self.tick_timeout_s),
            ("home_tolerance_rad", self.home_tolerance_rad),
            ("reset_timeout_s", self.reset_timeout_s),
            ("window_s", self.window_s),
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
        if !(self.teleop_max_age_s.is_finite() && self.teleop_max_age_s > 0.0) {
            return Err(Invalid::new(
                "teleop_max_age_s",
                format!("teleop_max_age_s: {} must be positive", self.teleop_max_age_s),
            ));
        }
        // Both become a Duration (and a deadline after now) when the node starts: 1e300 passed
        // the checks above and panicked there.
        for (name, v) in [("source_timeout_s", self.source_timeout_s), ("teleop_max_age_s", self.teleop_max_age_s)] {
            if v > 86_400.0 {
                return Err(Invalid::new(name, format!("{name} = {v} must be at most 86400 (a day)")));
            }
        }
        self.policy.validate()?;
        if self.source == SourceKind::Remote {
            self.remote.validate()?;
        }
        self.safety.validate()
    }
}

/// Who may take over from the policy (`policy.takeover`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum TakeoverKind {
    /// Nobody: the policy acts every tick.
    #[default]
    None,
    /// The Quest operator, by holding the grip.
    Teleop,
    /// The sim's scripted expert, by [`ExpertRule`].
    Expert,
}

/// How a new chunk meets the rest of the old one.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Blend {
    /// The new chunk's rows only.
    Replace,
    /// Overlapping rows averaged, newer chunks weighted up.
    Exponential,
    /// Synchronous: the next chunk is asked for once `execute_steps` rows of this one have run,
    /// and the arm holds until it comes; its rows run from its arrival (nothing skipped).
    Wait,
    /// Real-time chunking: as `replace`, and each request carries the rows the loop executes
    /// meanwhile, which the server's sampler freezes and guides the new chunk's overlap toward
    /// (`guidance_max_weight`; labrig's Diffusion Policy checkpoints; other servers get the
    /// schedule without the guidance, as the log says).
    Rtc,
}

impl Blend {
    pub fn name(self) -> &'static str {
        match self {
            Blend::Replace => "replace",
            Blend::Exponential => "exponential",
            Blend::Wait => "wait",
            Blend::Rtc => "rtc",
        }
    }
}

/// When a chunk's rows are meant to run.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ChunkTiming {
    /// Row i at the observation's tick + i periods (what the policy predicted for): rows whose
    /// time passed before the chunk came are skipped.
    Observation,
    /// Row 0 at the first tick after the chunk came, the rest one period apart (DROID's own
    /// client, which blocks on the server and then executes the chunk): nothing is skipped,
    /// but every row is as old as the round trip.
    Arrival,
}

/// `[policy]` in the control node's config.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct PolicySourceConfig {
    pub blend: Blend,
    /// Exponential blending: a chunk's weight is `exp(-blend_decay * k)`, `k` how many steps
    /// older its newest observation is than the newest chunk's (0: a plain average).
    pub blend_decay: f64,
    /// When a chunk's rows run: from its observation's tick (`"observation"`) or from its
    /// arrival (`"arrival"`, DROID's client's behaviour behind a slow remote server).
    pub chunk_timing: ChunkTiming,
    /// Rows of a chunk executed before the next one is due (0: the checkpoint's
    /// `n_action_steps`).
    pub execute_steps: u32,
    /// Lockstep only: a chunk asked for at step t is used from step t + this (0: the loop
    /// waits for it).
    pub lockstep_delay_steps: u32,
    /// On the wall clock: a request goes out when the rows left fall to the expected delay
    /// (the slowest of the last 20 round trips, in ticks, rounded up) plus this many ticks,
    /// so that in steady state a chunk arrives before the arm runs out of rows.
    pub request_margin_steps: u32,
    /// `blend = "rtc"`: the inference delay d in ticks (the rows frozen to the old chunk's).
    /// 0: measured (the expected delay above), or in lockstep `lockstep_delay_steps`.
    pub rtc_delay_steps: u32,
    /// `blend = "rtc"`: the clip (beta) of the guidance weight toward the old chunk's rows;
    /// 0 freezes the first d rows and guides nothing.
    pub guidance_max_weight: f64,
    /// How long the node waits at start for the server's `/policy/info` (s).
    pub server_wait_s: f64,
    /// A request unanswered this long (s, wall time) fails the episode.
    pub server_timeout_s: f64,
    /// The action space this rig executes (`eef_axis_angle` or `cartesian_velocity`); a policy
    /// predicting another is refused at start. Empty: either.
    pub action_space: String,
    /// JPEG quality of the observation images: the recorder's, so the policy sees the
    /// compression it was trained on.
    pub jpeg_quality: u8,
    /// On a real arm: the policy moves it only while the Quest's grip is held (`/teleop/state`
    /// from `labrig-teleop`, no older than 0.1 s), as teleop does; released, the arm holds.
    pub deadman: bool,
    /// This rig is the simulated one. A policy that observes inputs only a simulator has (the
    /// scene's object positions, `sim_only` in `/policy/info`) is refused unless this is set;
    /// a real rig gives a policy only pixels and proprioception.
    pub sim_rig: bool,
    /// Who may take over from the policy mid-rollout, its ticks recorded as theirs
    /// (operator corrections; [`crate::takeover`]): `"none"`, `"teleop"` (the Quest operator
    /// while the grip is held: `/teleop/action` replaces the policy's actions) or `"expert"`
    /// (the sim's scripted expert, by the rule `takeover_*`; needs `sim_rig` and a bridge run
    /// with `--expert --expert-resume`).
    ///
    /// `"teleop"` refuses `deadman = true`: the grip cannot mean both "the policy may move"
    /// and "the operator takes over". With a takeover the policy moves without the grip, and
    /// the operator stops it by taking over (the grip, and the arm goes where the Quest says)
    /// or ends the rollout (B/Y).
    pub takeover: TakeoverKind,
    /// `takeover = "expert"`: the stall window (ticks): less than `takeover_progress_m`
    /// progress toward the expert's target over this many ticks, and it takes over.
    pub takeover_stall_ticks: u32,
    /// `takeover = "expert"`: the least progress (m) over the stall window.
    pub takeover_progress_m: f64,
    /// `takeover = "expert"`: the TCP farther than this (m) from the expert's plan, and it
    /// takes over.
    pub takeover_distance_m: f64,
    /// `takeover = "expert"`: it hands back after this many ticks.
    pub takeover_ticks: u32,
    /// `takeover = "expert"`: at most this many takeovers per episode.
    pub takeover_max: u32,
}

impl Default for PolicySourceConfig {
    fn default() -> Self {
        PolicySourceConfig {
            blend: Blend::Replace,
            blend_decay: 0.5,
            chunk_timing: ChunkTiming::Observation,
            execute_steps: 0,
            lockstep_delay_steps: 0,
            request_margin_steps: 1,
            rtc_delay_steps: 0,
            guidance_max_weight: 5.0,
            server_wait_s: 120.0,
            server_timeout_s: 1.0,
            action_space: String::new(),
            jpeg_quality: 90,
            deadman: false,
            sim_rig: false,
            takeover: TakeoverKind::None,
            takeover_stall_ticks: 40,
            takeover_progress_m: 0.01,
            takeover_distance_m: 0.15,
            takeover_ticks: 40,
            takeover_max: 3,
        }
    }
}

impl PolicySourceConfig {
    pub fn validate(&self) -> Result<(), labrig_msgs::Invalid> {
        use labrig_msgs::Invalid;
        for (name, v) in
            [("policy.server_wait_s", self.server_wait_s), ("policy.server_timeout_s", self.server_timeout_s)]
        {
            if !(v.is_finite() && v > 0.0 && v <= 86_400.0) {
                return Err(Invalid::new(name, format!("{name} = {v} must be in (0, 86400]")));
            }
        }
        if !(self.blend_decay.is_finite() && self.blend_decay >= 0.0) {
            return Err(Invalid::new(
                "policy.blend_decay",
                format!("policy.blend_decay = {} must be >= 0", self.blend_decay),
            ));
        }
        if !(self.guidance_max_weight.is_finite() && (0.0..=1000.0).contains(&self.guidance_max_weight)) {
            return Err(Invalid::new(
                "policy.guidance_max_weight",
                format!("policy.guidance_max_weight = {} must be in [0, 1000]", self.guidance_max_weight),
            ));
        }
        if self.blend != Blend::Rtc && self.rtc_delay_steps != 0 {
            return Err(Invalid::new(
                "policy.rtc_delay_steps",
                format!("policy.rtc_delay_steps = {} is for policy.blend = \"rtc\" only", self.rtc_delay_steps),
            ));
        }
        if !self.action_space.is_empty() && !EXECUTABLE.contains(&self.action_space.as_str()) {
            return Err(Invalid::new(
                "policy.action_space",
                format!("policy.action_space = {:?}: the loop executes {EXECUTABLE:?}", self.action_space),
            ));
        }
        if !(1..=100).contains(&self.jpeg_quality) {
            return Err(Invalid::new("policy.jpeg_quality", "policy.jpeg_quality must be 1..=100"));
        }
        if self.takeover == TakeoverKind::Teleop && self.deadman {
            return Err(Invalid::new(
                "policy.takeover",
                "policy.takeover = \"teleop\" and policy.deadman = true: the Quest's grip cannot mean both \"the policy may move\" (deadman) and \"the operator takes over\"; set one",
            ));
        }
        if self.takeover == TakeoverKind::Expert && !self.sim_rig {
            return Err(Invalid::new(
                "policy.takeover",
                "policy.takeover = \"expert\" is the sim's scripted expert: it needs policy.sim_rig = true",
            ));
        }
        for (name, v) in
            [("policy.takeover_stall_ticks", self.takeover_stall_ticks), ("policy.takeover_ticks", self.takeover_ticks)]
        {
            if !(1..=100_000).contains(&v) {
                return Err(Invalid::new(name, format!("{name} = {v} must be in 1..=100000")));
            }
        }
        for (name, v) in [
            ("policy.takeover_progress_m", self.takeover_progress_m),
            ("policy.takeover_distance_m", self.takeover_distance_m),
        ] {
            if !(v.is_finite() && v > 0.0 && v <= 10.0) {
                return Err(Invalid::new(name, format!("{name} = {v} must be in (0, 10] m")));
            }
        }
        Ok(())
    }
}
