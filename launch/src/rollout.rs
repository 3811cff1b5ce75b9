//! Rollouts (`labrig rollout`, and the benches and experiments built on it): a policy's closed-loop success rate in the simulated rig, measured the
//! way the paper measures it: N rollouts from fixed, seeded initial scenes.
//!
//! The rig is launch_configs/sim_rollout.toml: the MuJoCo bridge (lockstep, or real time on
//! the wall clock), the recorder, the policy server serving the checkpoint, and the control
//! loop with the policy as its action source. Each rollout is a recorded episode (DROID
//! layout under `<out>/rollouts/`), ended by the sim's success predicate (`/sim/task`) or
//! failed at the step budget or when the server stops answering. The command prints the
//! success rate with its 95% (Wilson) interval, each rollout's outcome, length and reason,
//! the chunks' inference time (p50/p99) and the ticks the arm held for lack of an action;
//! it writes `rollouts.json`, a contact sheet per rollout and `summary.png`.
//!
//! `--intervene expert`: operator corrections (human-gated DAgger) played by the sim's
//! scripted expert. The bridge publishes the expert's plan, re-planned from the state it finds
//! (`--expert --expert-resume`), and the loop lets it take over by its rule
//! (`policy.takeover = "expert"`, `--takeover-*`; see labrig-control's `takeover` module).
//! Each rollout reports its takeovers and operator steps, counted from the steps' action
//! source; "without help" counts the successes no operator touched.

use crate::config::{LaunchConfig, NodeSpec};
use crate::sim::{SIM_ROLLOUT, SimRig, contact_sheet, set_arg};
use anyhow::{Context, bail};
use clap::Args;
use labrig_episode::progress;
use labrig_msgs::rig::{EpisodeEventKind, Step};
use labrig_msgs::std_msgs::StringMsg;
use labrig_msgs::topics;
use labrig_runtime::RosConfig;
use labrig_runtime::ros::{Ros, qos};
use serde::{Deserialize, Serialize};
use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::Duration;

#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum BlendArg {
    Replace,
    Exponential,
    /// Synchronous: the arm holds while each chunk is computed.
    Wait,
    /// Real-time chunking: the next chunk frozen to and guided toward the rows run meanwhile.
    Rtc,
}

impl BlendArg {
    pub fn name(self) -> &'static str {
        match self {
            BlendArg::Replace => "replace",
            BlendArg::Exponential => "exponential",
            BlendArg::Wait => "wait",
            BlendArg::Rtc => "rtc",
        }
    }
}

#[derive(Debug, Args)]
pub struct RolloutArgs {
    /// The checkpoint: `labrig train`'s `checkpoints/step_<n>`, its `checkpoints/last`, or the
    /// run directory (its last checkpoint).
    #[arg(long, required_unless_present_any = ["remote", "torchscript"], conflicts_with_all = ["remote", "torchscript"])]
    pub policy: Option<PathBuf>,
    /// Instead of a checkpoint: a TorchScript module saved by PyTorch, with `--spec` (what it
    /// takes and gives; see ARCHITECTURE.md).
    #[arg(long, requires = "spec", conflicts_with = "remote")]
    pub torchscript: Option<PathBuf>,
    /// `--torchscript`: the module's spec (TOML).
    #[arg(long, requires = "torchscript")]
    pub spec: Option<PathBuf>,
    /// Instead of a checkpoint: a policy behind openpi's websocket protocol at this address
    /// (`host:port` or `ws://host:port`; e.g. pi0.5-DROID on openpi's `serve_policy.py`, or
    /// `labrig policy run --openpi`). The loop's source is then `remote` (`[remote]`: DROID's
    /// observation keys and 15 Hz joint-velocity chunks by default).
    #[arg(long)]
    pub remote: Option<String>,
    /// `--remote`: what the chunk's arm columns are (`remote.actions`: joint_velocity, DROID's,
    /// or joint_position).
    #[arg(long, requires = "remote")]
    pub remote_actions: Option<String>,
    /// `--remote`: the prompt (`remote.prompt`; default: the scene's instruction).
    #[arg(long, requires = "remote")]
    pub prompt: Option<String>,
    /// When a chunk's rows run (`policy.chunk_timing`): from the observation's tick (default;
    /// rows that passed before the chunk came are skipped) or from the chunk's arrival (DROID's
    /// client's behaviour).
    #[arg(long, value_enum)]
    pub chunk_timing: Option<ChunkTimingArg>,
    /// A request unanswered this long fails the rollout (s; `policy.server_timeout_s`; the
    /// default is the loop's 1 s, or 5 s with `--remote`).
    #[arg(long)]
    pub server_timeout_s: Option<f64>,
    /// The scene: a built-in one (pick_place, drawer_open, drawer_close) or a spec file.
    #[arg(long, default_value = "pick_place")]
    pub scene: String,
    /// Rollouts (the paper: 20).
    #[arg(long, default_value_t = 20)]
    pub episodes: u64,
    /// The first scene seed; rollouts take seeds first..first+episodes. The default keeps
    /// clear of `labrig demo`'s seeds (0..), so a policy is judged on scenes it was not
    /// trained on.
    #[arg(long, default_value_t = 1000)]
    pub first_seed: u64,
    /// The sim and the loop advance together, one tick per action: the result does not
    /// depend on machine speed, and the same policy and seeds give the same episodes
    /// (the default).
    #[arg(long, conflicts_with = "realtime")]
    pub lockstep: bool,
    /// The sim in real time, the loop on the wall clock: inference latency costs what it
    /// costs on a robot.
    #[arg(long)]
    pub realtime: bool,
    /// A rollout that has not succeeded after this many steps fails.
    #[arg(long, default_value_t = 300)]
    pub max_steps: u64,
    /// Inference threads for the policy server (0: every core).
    #[arg(long, default_value_t = 0)]
    pub threads: i32,
    /// How a new chunk meets the rest of the old one (the loop's `policy.blend`).
    #[arg(long, value_enum)]
    pub blend: Option<BlendArg>,
    /// Lockstep: play an inference latency of this many ticks (`policy.lockstep_delay_steps`).
    #[arg(long)]
    pub delay_steps: Option<u32>,
    /// Rows of a chunk executed before the next is due (`policy.execute_steps`; default the
    /// checkpoint's n_action_steps).
    #[arg(long)]
    pub execute_steps: Option<u32>,
    /// `--blend rtc`: the clip (beta) of the guidance toward the rows run meanwhile
    /// (`policy.guidance_max_weight`; 0 freezes them and guides nothing).
    #[arg(long)]
    pub guidance_max_weight: Option<f64>,
    /// `--blend rtc`: the delay d in ticks (`policy.rtc_delay_steps`; default: the played delay
    /// in lockstep, the measured one in real time).
    #[arg(long)]
    pub rtc_delay_steps: Option<u32>,
    /// `--blend rtc`: the server's guidance (`rtc_guidance` of labrig-policy): `x0` (in the
    /// clean estimate's space, the default) or `vjp` (PiGDM's, through the U-Net's Jacobian).
    #[arg(long, value_parser = ["x0", "vjp"])]
    pub rtc_guidance: Option<String>,
    /// DDIM steps per chunk instead of the checkpoint's (`inference_steps` of labrig-policy):
    /// fewer are faster; experiments/latency/README.md has what they cost.
    #[arg(long)]
    pub inference_steps: Option<usize>,
    /// Where the rollouts (DROID layout under `rollouts/`), the report and the pictures go.
    #[arg(long, default_value = "out/rollout")]
    pub out: PathBuf,
    /// DDS domain id for the rollout rig.
    #[arg(long, default_value_t = 43)]
    pub domain_id: u16,
    /// Print the report as JSON.
    #[arg(long)]
    pub json: bool,
    /// Who may take over from the policy: `expert` (the sim's scripted expert, by the loop's
    /// takeover rule).
    #[arg(long, value_enum)]
    pub intervene: Option<InterveneArg>,
    /// `--intervene expert`: the stall window in ticks (`policy.takeover_stall_ticks`).
    #[arg(long, requires = "intervene")]
    pub takeover_stall_ticks: Option<u32>,
    /// `--intervene expert`: the distance from the expert's plan that triggers a takeover
    /// (m, `policy.takeover_distance_m`).
    #[arg(long, requires = "intervene")]
    pub takeover_distance_m: Option<f64>,
    /// `--intervene expert`: ticks before the expert hands back (`policy.takeover_ticks`).
    #[arg(long, requires = "intervene")]
    pub takeover_ticks: Option<u32>,
}

impl RolloutArgs {
    /// The command line's defaults (lockstep, seeds 1000.., 20 rollouts of 300 steps) writing
    /// to `out`, printing nothing: for a command that runs rollouts itself and sets the policy
    /// and what else it varies.
    pub fn defaults(out: PathBuf) -> RolloutArgs {
        RolloutArgs {
            policy: None,
            torchscript: None,
            spec: None,
            remote: None,
            remote_actions: None,
            prompt: None,
            chunk_timing: None,
            server_timeout_s: None,
            scene: "pick_place".into(),
            episodes: 20,
            first_seed: 1000,
            lockstep: true,
            realtime: false,
            max_steps: 300,
            threads: 0,
            blend: None,
            delay_steps: None,
            execute_steps: None,
            guidance_max_weight: None,
            rtc_delay_steps: None,
            rtc_guidance: None,
            inference_steps: None,
            out,
            domain_id: 43,
            json: true,
            intervene: None,
            takeover_stall_ticks: None,
            takeover_distance_m: None,
            takeover_ticks: None,
        }
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum ChunkTimingArg {
    Observation,
    Arrival,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum InterveneArg {
    /// The sim's scripted expert.
    Expert,
}

/// One rollout as the run saw it.
#[derive(Debug, Clone, Default, Serialize, Deserialize)]
pub struct Rollout {
    pub episode_id: String,
    pub seed: Option<u64>,
    pub success: bool,
    /// Why it ended (the loop's end event note: the step budget, the server, ...).
    pub reason: String,
    pub steps: u64,
    /// Recorded steps the arm held for lack of a policy action.
    pub held_steps: u64,
    /// Of those, the ones after the first step that executed a row (the wait for the first
    /// chunk left out), and the steps from that one on.
    pub held_after_first_chunk: u64,
    pub steps_after_first_chunk: u64,
    /// Chunks whose rows it executed.
    pub chunks: u64,
    /// Rows whose time had passed when their chunk arrived.
    pub skipped_rows: u64,
    pub dir: Option<PathBuf>,
    pub contact_sheet: Option<PathBuf>,
    /// `--intervene`: times an operator took over, and the steps it acted.
    pub takeovers: u64,
    pub operator_steps: u64,
}

/// The run's report.
/// The report a rollout run writes (`rollouts.json`) and its readers (the benches, the
/// experiment) read back.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct RolloutReport {
    pub policy: String,
    pub scene: String,
    pub mode: String,
    pub first_seed: u64,
    pub rollouts: Vec<Rollout>,
    pub successes: u64,
    pub success_rate: f64,
    /// Wilson score interval, 95%.
    pub ci95: [f64; 2],
    #[serde(deserialize_with = "labrig_reports::nan_if_null")]
    pub inference_ms_p50: f64,
    #[serde(deserialize_with = "labrig_reports::nan_if_null")]
    pub inference_ms_p99: f64,
    pub chunks: u64,
    pub held_steps: u64,
    /// Steps held after each episode's first executed row, over the steps from there on.
    pub held_after_first_chunk: u64,
    pub steps_after_first_chunk: u64,
    /// `--intervene`: who played the operator (None: nobody could take over).
    pub intervene: Option<String>,
    /// Takeovers and operator steps over all rollouts, and the successes without any.
    pub takeovers: u64,
    pub operator_steps: u64,
    pub successes_without_help: u64,
    /// The control loop's figures for the run (`--stats-out`): ticks, missed ticks, jitter
    /// and tick lateness (us, p50/p99/max), the policy source's requests, chunks, skipped rows
    /// and round trips.
    pub control: Option<serde_json::Value>,
    pub summary_png: Option<PathBuf>,
    pub errors: Vec<String>,
}

/// Wilson's 95% interval for `k` successes in `n` trials.
pub fn wilson95(k: u64, n: u64) -> [f64; 2] {
    if n == 0 {
        return [0.0, 1.0];
    }
    let (k, n, z) = (k as f64, n as f64, 1.959_963_984_540_054);
    let p = k / n;
    let centre = (p + z * z / (2.0 * n)) / (1.0 + z * z / n);
    let half = z * (p * (1.0 - p) / n + z * z / (4.0 * n * n)).sqrt() / (1.0 + z * z / n);
    [(centre - half).max(0.0), (centre + half).min(1.0)]
}

/// The policy files a rollout serves, made absolute: the checkpoint, or the TorchScript module and
/// its spec.
type PolicyFiles = (Option<PathBuf>, Option<(PathBuf, PathBuf)>);

/// The rollouts and their report (also written to `rollouts.json`), printing nothing.
pub fn run_quiet(args: RolloutArgs) -> anyhow::Result<RolloutReport> {
    anyhow::ensure!((1..=1000).contains(&args.episodes), "--episodes must be in 1..=1000");
    let (ckpt, torchscript) = policy_files(&args)?;
    std::fs::create_dir_all(&args.out).with_context(|| format!("creating {}", args.out.display()))?;
    let out = std::fs::canonicalize(&args.out)?;
    let (cfg, order) = rollout_rig(&args, &(ckpt.clone(), torchscript.clone()), &out)?;
    let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build()?;
    let mut seen = Seen::default();
    let failure = rt.block_on(run_rig(&args, cfg, order, &mut seen)).err();
    drop(rt);

    let mut errors: Vec<String> = failure.iter().map(|e| format!("{e:#}")).collect();
    let rollouts = collect_rollouts(&seen, &out, &mut errors);
    let n = rollouts.len() as u64;
    let mut report = summarise(&args, &(ckpt, torchscript), &seen, rollouts, &out);
    if n < args.episodes {
        errors.push(format!("{n} of {} rollouts finished", args.episodes));
    }
    if n > 0 {
        let png = out.join("summary.png");
        match plot_summary(&report, &png) {
            Ok(()) => report.summary_png = Some(png),
            Err(e) => errors.push(format!("summary plot: {e:#}")),
        }
    }
    report.errors = errors;
    std::fs::write(out.join("rollouts.json"), serde_json::to_string_pretty(&report)?)
        .with_context(|| format!("writing {}", out.join("rollouts.json").display()))?;
    Ok(report)
}

/// `--policy`, or `--torchscript` with `--spec`, made absolute (each named when it is missing).
fn policy_files(args: &RolloutArgs) -> anyhow::Result<PolicyFiles> {
    // The server resolves it (a checkpoint, `checkpoints/last`, a run) and names what is wrong.
    let ckpt = match &args.policy {
        Some(p) => {
            Some(std::fs::canonicalize(p).with_context(|| format!("the checkpoint {} (--policy)", p.display()))?)
        }
        None => None,
    };
    let torchscript = match (&args.torchscript, &args.spec) {
        (Some(m), Some(s)) => Some((
            std::fs::canonicalize(m)
                .with_context(|| format!("the TorchScript module {} (--torchscript)", m.display()))?,
            std::fs::canonicalize(s).with_context(|| format!("the spec {} (--spec)", s.display()))?,
        )),
        _ => None,
    };
    Ok((ckpt, torchscript))
}

/// The rollout rig: sim_rollout.toml with this run's scene, seeds, policy, loop settings and
/// output folder (`<out>/rollouts`), and its own camera-frame namespace.
fn rollout_rig(args: &RolloutArgs, policy: &PolicyFiles, out: &Path) -> anyhow::Result<(LaunchConfig, Vec<usize>)> {
    let (ckpt, torchscript) = policy;
    let origin = Path::new("launch_configs/sim_rollout.toml");
    let (mut cfg, mut order) = LaunchConfig::parse(SIM_ROLLOUT, origin)?;
    if args.remote.is_some() {
        // The policy is served elsewhere: no policy server node.
        cfg.nodes.retain(|n| n.name != "policy");
        for n in &mut cfg.nodes {
            n.after.retain(|d| d != "policy");
        }
        order = cfg.validate(Path::new("launch_configs"))?;
    }
    let root = out.join("rollouts");
    let sim = cfg.node_mut("sim").context("sim_rollout.toml has no `sim` node")?;
    set_arg(&mut sim.args, "--mode", if args.realtime { "realtime" } else { "lockstep" });
    set_arg(&mut sim.args, "--scene", &args.scene);
    set_arg(&mut sim.args, "--seed", &args.first_seed.to_string());
    if args.realtime {
        sim.args.extend(["--wall-clock-origin".into(), "--realtime-priority".into(), "10".into()]);
    }
    if args.intervene == Some(InterveneArg::Expert) {
        sim.args.extend(["--expert".into(), "--expert-resume".into()]);
    }
    let rec = cfg.node_mut("recorder").context("sim_rollout.toml has no `recorder` node")?;
    set_arg(&mut rec.args, "--root", &root.display().to_string());
    if let Some(ckpt) = &ckpt {
        let pol = cfg.node_mut("policy").context("sim_rollout.toml has no `policy` node")?;
        set_arg(&mut pol.args, "--checkpoint", &ckpt.display().to_string());
        set_arg(&mut pol.args, "--threads", &args.threads.to_string());
        if let Some(g) = &args.rtc_guidance {
            pol.args.extend(["--set".into(), format!("rtc_guidance=\"{g}\"")]);
        }
        if let Some(n) = args.inference_steps {
            pol.args.extend(["--set".into(), format!("inference_steps={n}")]);
        }
    }
    if let Some((module, spec)) = &torchscript {
        let pol = cfg.node_mut("policy").context("sim_rollout.toml has no `policy` node")?;
        if let Some(i) = pol.args.iter().position(|a| a == "--checkpoint") {
            pol.args.drain(i..(i + 2).min(pol.args.len()));
        }
        set_arg(&mut pol.args, "--torchscript", &module.display().to_string());
        set_arg(&mut pol.args, "--spec", &spec.display().to_string());
        set_arg(&mut pol.args, "--threads", &args.threads.to_string());
    }
    loop_settings(args, cfg.node_mut("control").context("sim_rollout.toml has no `control` node")?, out);
    // The camera frames of this rig alone (another rig may run on the machine), unless the
    // caller chose a namespace.
    if labrig_runtime::frames::default_namespace().is_none() {
        let ns = format!("rollout_{}", std::process::id());
        for n in &mut cfg.nodes {
            n.env.insert(labrig_runtime::frames::NAMESPACE_ENV.into(), ns.clone());
        }
    }
    Ok((cfg, order))
}

/// The control loop's arguments and `--set` overrides for this run (episodes, seeds, the
/// policy's execution: blend, delay, rows per chunk; a remote server; operator takeover).
fn loop_settings(args: &RolloutArgs, ctl: &mut NodeSpec, out: &Path) {
    set_arg(&mut ctl.args, "--episodes", &args.episodes.to_string());
    set_arg(&mut ctl.args, "--first-seed", &args.first_seed.to_string());
    set_arg(&mut ctl.args, "--max-steps", &args.max_steps.to_string());
    if args.realtime {
        set_arg(&mut ctl.args, "--clock", "wall");
    }
    set_arg(&mut ctl.args, "--stats-out", &out.join("control_stats.json").display().to_string());
    if args.remote.is_some() {
        set_arg(&mut ctl.args, "--source", "remote");
    }
    let mut set = |kv: String| ctl.args.extend(["--set".into(), kv]);
    // A TOML basic string (JSON's escapes are valid in one).
    let toml_str = |v: &str| serde_json::Value::String(v.to_owned()).to_string();
    if let Some(url) = &args.remote {
        set(format!("remote.url={}", toml_str(url)));
        if let Some(a) = &args.remote_actions {
            set(format!("remote.actions={}", toml_str(a)));
        }
        if let Some(p) = &args.prompt {
            set(format!("remote.prompt={}", toml_str(p)));
        }
    }
    if let Some(t) = args.chunk_timing {
        set(format!(
            "policy.chunk_timing=\"{}\"",
            if t == ChunkTimingArg::Arrival { "arrival" } else { "observation" }
        ));
    }
    match (args.server_timeout_s, args.remote.is_some()) {
        (Some(t), _) => set(format!("policy.server_timeout_s={t}")),
        (None, true) => set("policy.server_timeout_s=5.0".into()),
        (None, false) => {}
    }
    if let Some(b) = args.blend {
        set(format!("policy.blend=\"{}\"", b.name()));
    }
    if let Some(w) = args.guidance_max_weight {
        set(format!("policy.guidance_max_weight={w:?}"));
    }
    if let Some(d) = args.rtc_delay_steps {
        set(format!("policy.rtc_delay_steps={d}"));
    }
    if let Some(d) = args.delay_steps {
        set(format!("policy.lockstep_delay_steps={d}"));
    }
    if let Some(e) = args.execute_steps {
        set(format!("policy.execute_steps={e}"));
    }
    if args.intervene == Some(InterveneArg::Expert) {
        // (sim_rollout.toml sets policy.sim_rig, which the expert takeover needs too.)
        set("policy.takeover=\"expert\"".into());
        if let Some(n) = args.takeover_stall_ticks {
            set(format!("policy.takeover_stall_ticks={n}"));
        }
        if let Some(d) = args.takeover_distance_m {
            set(format!("policy.takeover_distance_m={d}"));
        }
        if let Some(n) = args.takeover_ticks {
            set(format!("policy.takeover_ticks={n}"));
        }
    }
}

/// One [`Rollout`] per episode that ended, checked against its recording (which also gives the
/// takeover counts to trust); a contact sheet for each.
fn collect_rollouts(seen: &Seen, out: &Path, errors: &mut Vec<String>) -> Vec<Rollout> {
    let mut rollouts = Vec::new();
    for (k, id) in seen.order.iter().enumerate() {
        let ep = &seen.episodes[id];
        let Some(end) = &ep.end else { continue };
        let dir = seen.recorded.get(id).cloned();
        let mut r = Rollout {
            episode_id: id.clone(),
            seed: ep.seed,
            success: end.0 == EpisodeEventKind::Success,
            reason: if end.0 == EpisodeEventKind::Success {
                "the sim's success predicate".into()
            } else {
                end.1.clone()
            },
            steps: ep.steps,
            held_steps: ep.held,
            held_after_first_chunk: ep.held_after_first,
            steps_after_first_chunk: ep.steps_after_first,
            chunks: ep.chunks.len() as u64,
            skipped_rows: ep.chunks.values().map(|&r| u64::from(r)).sum(),
            dir: dir.clone(),
            contact_sheet: None,
            takeovers: ep.takeovers,
            operator_steps: ep.operator_steps,
        };
        match &dir {
            Some(d) => match labrig_episode::inspect::inspect(d) {
                Ok(i) => {
                    // The recording's steps are the count to trust (this run may have missed a
                    // step on the wire).
                    if let Some(src) = &i.sources {
                        (r.takeovers, r.operator_steps) = (src.takeovers, src.operator_steps);
                    }
                    let sheet = out.join(format!("rollout_{k:02}_cameras.png"));
                    match contact_sheet(&i.path, &sheet) {
                        Ok(()) => r.contact_sheet = Some(sheet),
                        Err(e) => errors.push(format!("contact sheet of rollout {k}: {e:#}")),
                    }
                    if i.metadata.as_ref().and_then(|m| m.success) != Some(r.success) {
                        errors.push(format!(
                            "rollout {k}: the recording's success flag disagrees with the loop's verdict"
                        ));
                    }
                }
                Err(e) => errors.push(format!("rollout {k} ({}): {e}", d.display())),
            },
            None => errors.push(format!("rollout {k} ({id}) was not reported recorded")),
        }
        rollouts.push(r);
    }
    rollouts
}

/// The report's figures over the rollouts (errors and the summary plot are added by the caller).
fn summarise(
    args: &RolloutArgs,
    policy: &PolicyFiles,
    seen: &Seen,
    rollouts: Vec<Rollout>,
    out: &Path,
) -> RolloutReport {
    let (ckpt, torchscript) = policy;
    let n = rollouts.len() as u64;
    let successes = rollouts.iter().filter(|r| r.success).count() as u64;
    let lat = labrig_episode::inspect::Percentiles::of(seen.inference_ms.clone());
    RolloutReport {
        policy: match (&ckpt, &args.remote, &torchscript) {
            (Some(c), _, _) => c.display().to_string(),
            (None, Some(url), _) => format!("openpi {}", labrig_openpi::client::ws_url(url)),
            (None, None, Some((m, _))) => format!("torchscript {}", m.display()),
            (None, None, None) => String::new(),
        },
        scene: args.scene.clone(),
        mode: if args.realtime { "realtime" } else { "lockstep" }.to_owned(),
        first_seed: args.first_seed,
        successes,
        success_rate: if n > 0 { successes as f64 / n as f64 } else { 0.0 },
        ci95: wilson95(successes, n),
        inference_ms_p50: lat.as_ref().map_or(f64::NAN, |p| p.p50),
        inference_ms_p99: lat.as_ref().map_or(f64::NAN, |p| p.p99),
        chunks: seen.inference_ms.len() as u64,
        held_steps: rollouts.iter().map(|r| r.held_steps).sum(),
        held_after_first_chunk: rollouts.iter().map(|r| r.held_after_first_chunk).sum(),
        steps_after_first_chunk: rollouts.iter().map(|r| r.steps_after_first_chunk).sum(),
        intervene: args.intervene.map(|_| "expert".to_owned()),
        takeovers: rollouts.iter().map(|r| r.takeovers).sum(),
        operator_steps: rollouts.iter().map(|r| r.operator_steps).sum(),
        successes_without_help: rollouts.iter().filter(|r| r.success && r.takeovers == 0).count() as u64,
        rollouts,
        control: std::fs::read_to_string(out.join("control_stats.json"))
            .ok()
            .and_then(|t| serde_json::from_str(&t).ok()),
        summary_png: None,
        errors: Vec::new(),
    }
}

/// A run's `rollouts.json`, when it can be read.
pub fn read_report(path: &Path) -> Option<RolloutReport> {
    labrig_reports::read(path)
}

/// "k of n rollouts succeeded (p%, 95% CI lo-hi%)".
pub fn rate_text(r: &RolloutReport) -> String {
    format!(
        "{} of {} rollouts succeeded ({:.0}%, 95% CI {:.0}-{:.0}%)",
        r.successes,
        r.rollouts.len(),
        100.0 * r.success_rate,
        100.0 * r.ci95[0],
        100.0 * r.ci95[1]
    )
}

/// What the run heard of one episode.
#[derive(Debug, Default)]
struct EpisodeSeen {
    seed: Option<u64>,
    end: Option<(EpisodeEventKind, String)>,
    steps: u64,
    held: u64,
    /// Whether a step has executed a policy row yet; the steps and held steps from then on.
    acting: bool,
    steps_after_first: u64,
    held_after_first: u64,
    /// Chunk id -> the first row executed from it.
    chunks: BTreeMap<u64, u32>,
    /// Runs of steps by an operator (not the policy), their steps, and whether the last
    /// step was one.
    takeovers: u64,
    operator_steps: u64,
    operator_acting: bool,
}

#[derive(Debug, Default)]
struct Seen {
    order: Vec<String>,
    episodes: BTreeMap<String, EpisodeSeen>,
    recorded: BTreeMap<String, PathBuf>,
    inference_ms: Vec<f64>,
}

async fn run_rig(args: &RolloutArgs, cfg: LaunchConfig, order: Vec<usize>, seen: &mut Seen) -> anyhow::Result<()> {
    let ros_cfg = RosConfig { domain_id: args.domain_id, ..RosConfig::default() };
    ros_cfg.validate(Path::new("<command line>"))?;
    let mut ros = Ros::new(&ros_cfg, "labrig_rollout")?;
    let events = ros.subscription_on(&topics::RIG_EPISODE, 100)?;
    let steps = ros.subscription_on(&topics::RIG_STEP, 1000)?;
    let chunks = ros.subscription_on(&topics::POLICY_CHUNK, 100)?;
    let scene = ros.subscription_on(&topics::SIM_SCENE, 10)?;
    let status = ros.subscription::<StringMsg>(topics::RECORDER_STATUS.name, qos::reliable(100))?;
    let bar = progress::bar("rollout {bar:25} {pos}/{len}", args.episodes, args.json);
    bar.set_message("starting the simulated rig and loading the policy");
    let SimRig { watch, stop: _stop, rig } = SimRig::start(cfg, order, args.domain_id)?;
    let mut scene_seed: Option<u64> = None;
    let mut current: Option<String> = None;
    let mut ended = BTreeSet::new();
    loop {
        while let Some(m) = scene.try_take()? {
            scene_seed = serde_json::from_str::<serde_json::Value>(&m.msg.data).ok().and_then(|v| v["seed"].as_u64());
        }
        while let Some(e) = events.try_take()? {
            let id = e.msg.episode_id.clone();
            match e.msg.kind() {
                Ok(EpisodeEventKind::Start) => {
                    seen.order.push(id.clone());
                    seen.episodes.insert(id.clone(), EpisodeSeen { seed: scene_seed, ..EpisodeSeen::default() });
                    bar.set_message(format!("rollout {} (seed {})", seen.order.len(), scene_seed.unwrap_or_default()));
                    current = Some(id);
                }
                Ok(k @ (EpisodeEventKind::Success | EpisodeEventKind::Failure | EpisodeEventKind::Stop)) => {
                    if let Some(ep) = seen.episodes.get_mut(&id) {
                        let kind = if k == EpisodeEventKind::Stop { EpisodeEventKind::Failure } else { k };
                        ep.end = Some((kind, e.msg.note.clone()));
                        if ended.insert(id.clone()) {
                            bar.inc(1);
                        }
                        let ok = seen
                            .episodes
                            .values()
                            .filter(|e| matches!(e.end, Some((EpisodeEventKind::Success, _))))
                            .count();
                        bar.set_message(format!("{ok} of {} succeeded", ended.len()));
                    }
                }
                _ => {}
            }
        }
        while let Some(s) = steps.try_take()? {
            let s = s.msg;
            if current.as_deref() != Some(s.episode_id.as_str()) {
                continue;
            }
            let Some(ep) = seen.episodes.get_mut(&s.episode_id) else { continue };
            ep.steps += 1;
            ep.acting |= s.chunk_id != 0;
            ep.steps_after_first += u64::from(ep.acting);
            if s.action_source == Step::SOURCE_POLICY && !s.movement_enabled {
                ep.held += 1;
                ep.held_after_first += u64::from(ep.acting);
            }
            let operator = Step::is_operator(s.action_source);
            ep.takeovers += u64::from(operator && !ep.operator_acting);
            ep.operator_steps += u64::from(operator);
            ep.operator_acting = operator;
            if s.chunk_id != 0 {
                ep.chunks.entry(s.chunk_id).or_insert(s.chunk_row);
            }
        }
        while let Some(c) = chunks.try_take()? {
            seen.inference_ms.push(c.msg.inference_ms);
        }
        while let Some(s) = status.try_take()? {
            let v: serde_json::Value = serde_json::from_str(&s.msg.data).unwrap_or_default();
            if v["state"] == "recorded"
                && let (Some(dir), Some(id)) = (v["dir"].as_str(), v["episode"].as_str())
            {
                seen.recorded.insert(id.to_owned(), PathBuf::from(dir));
            } else if v["state"] == "error" {
                bar.println(format!("recorder: {}", v["error"]));
            }
        }
        if watch.is_triggered() {
            break;
        }
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    // The recorder's last reports may trail the rig's stop.
    let until = std::time::Instant::now() + Duration::from_secs(2);
    while std::time::Instant::now() < until {
        while let Some(s) = status.try_take()? {
            let v: serde_json::Value = serde_json::from_str(&s.msg.data).unwrap_or_default();
            if let (Some(dir), Some(id), true) = (v["dir"].as_str(), v["episode"].as_str(), v["state"] == "recorded") {
                seen.recorded.insert(id.to_owned(), PathBuf::from(dir));
            }
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    bar.finish_and_clear();
    let code = rig.await.context("the launcher task")??;
    if code != ExitCode::SUCCESS {
        bail!("the rollout rig stopped with an error (see above)");
    }
    Ok(())
}

/// Each rollout's length, green for a success and red for a failure, under the success rate
/// and its interval.
fn plot_summary(r: &RolloutReport, path: &Path) -> anyhow::Result<()> {
    use plotters::prelude::*;
    let font = labrig_episode::font::dejavu_sans().map_err(anyhow::Error::msg)?;
    let _ = plotters::style::register_font("sans-serif", FontStyle::Normal, font);
    let n = r.rollouts.len();
    let top = r.rollouts.iter().map(|o| o.steps).max().unwrap_or(1).max(1) as f64 * 1.15;
    let root = BitMapBackend::new(path, (1000, 560)).into_drawing_area();
    let e = |e: DrawingAreaErrorKind<_>| anyhow::anyhow!("{e:?}");
    root.fill(&WHITE).map_err(e)?;
    let name = Path::new(&r.policy).file_name().map(|f| f.to_string_lossy().into_owned()).unwrap_or_default();
    let title = format!("{name}: {}, {} {}, p50 inference {:.0} ms", rate_text(r), r.scene, r.mode, r.inference_ms_p50);
    let mut chart = ChartBuilder::on(&root)
        .caption(title, ("sans-serif", 20))
        .margin(14)
        .x_label_area_size(40)
        .y_label_area_size(60)
        .build_cartesian_2d(-0.5..(n as f64 - 0.5), 0.0..top)
        .map_err(e)?;
    chart
        .configure_mesh()
        .disable_x_mesh()
        .x_desc("rollout (scene seed)")
        .y_desc("steps (20 Hz)")
        .x_labels(n.min(25))
        .x_label_formatter(&|x| {
            let k = x.round() as usize;
            r.rollouts.get(k).and_then(|o| o.seed).map_or(String::new(), |s| s.to_string())
        })
        .draw()
        .map_err(e)?;
    let green = RGBColor(60, 160, 90);
    let red = RGBColor(210, 70, 60);
    chart
        .draw_series(r.rollouts.iter().enumerate().map(|(k, o)| {
            let c = if o.success { green } else { red };
            Rectangle::new([(k as f64 - 0.35, 0.0), (k as f64 + 0.35, o.steps as f64)], c.filled())
        }))
        .map_err(e)?;
    chart
        .draw_series(r.rollouts.iter().enumerate().filter(|(_, o)| o.held_steps > 0).map(|(k, o)| {
            Rectangle::new([(k as f64 - 0.35, 0.0), (k as f64 + 0.35, o.held_steps as f64)], BLACK.mix(0.5).filled())
        }))
        .map_err(e)?
        .label("held (no action)")
        .legend(|(x, y)| Rectangle::new([(x, y - 5), (x + 14, y + 5)], BLACK.mix(0.5).filled()));
    chart
        .draw_series(std::iter::once(Rectangle::new([(0.0, 0.0), (0.0, 0.0)], green.filled())))
        .map_err(e)?
        .label("success")
        .legend(move |(x, y)| Rectangle::new([(x, y - 5), (x + 14, y + 5)], green.filled()));
    chart
        .draw_series(std::iter::once(Rectangle::new([(0.0, 0.0), (0.0, 0.0)], red.filled())))
        .map_err(e)?
        .label("failure")
        .legend(move |(x, y)| Rectangle::new([(x, y - 5), (x + 14, y + 5)], red.filled()));
    chart.configure_series_labels().background_style(WHITE.mix(0.85)).border_style(BLACK).draw().map_err(e)?;
    root.present().map_err(e)?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn wilson_intervals_match_the_textbook() {
        // 16 of 20: 0.8, Wilson 95% [0.584, 0.919].
        let [lo, hi] = wilson95(16, 20);
        assert!((lo - 0.584).abs() < 1e-3 && (hi - 0.919).abs() < 1e-3, "{lo} {hi}");
        let [lo, hi] = wilson95(20, 20);
        assert!((lo - 0.839).abs() < 1e-3 && hi == 1.0, "{lo} {hi}");
        assert_eq!(wilson95(0, 0), [0.0, 1.0]);
    }
}
