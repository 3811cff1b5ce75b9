//! `labrig bench faults`: faults injected into the simulated DROID rig (`labrig demo`'s rig in
//! real time: the MuJoCo bridge, the recorder, the control loop with the scripted expert,
//! under the launcher), and what each costs: data lost, time to detect, time to recover.
//!
//! - `recorder-kill`: SIGKILL of the recorder at the start, in the middle (3 s in) and at the
//!   end (on the end event) of an episode; the launcher restarts it. Steps lost are counted
//!   against every `/rig/step` the loop published (seen by this process); camera seconds lost
//!   from the frames the episode holds per camera.
//! - `disk-full`: the episodes go to a small tmpfs (needs root to mount it); the recorder
//!   refuses the episode that would not fit, the loop holds the rig Idle. `disk-full-nomargin`
//!   turns the margin off, so the disk fills mid-episode.
//! - `dds-stop`: the recorder stopped (SIGSTOP) 0.3 s and continued mid-episode: its DDS
//!   threads die, it exits, the launcher restarts it, the episode continues in a new part.
//! - `bridge-kill`: the sim bridge SIGKILLed 3 s into an episode on the DROID rig's layout
//!   (franka and gripper nodes in front of the bridge, as on the real rig): the franka node
//!   holds and reports the fault on /arm/state, the loop stops the episode naming the fault,
//!   the recorder files what was recorded.
//! - `camera-stall`: the wrist camera stops sending for 1 s (`--stall-s`) from 1 s into an
//!   episode (`/sim/fault`): every step of that second records the wrist's last frame with its
//!   old capture time, so the episode says which camera was missing, and when (`labrig
//!   inspect`: late and dropped frames per camera).
//!
//! Each run prints a table (or JSON); the figures depend on the machine (a shared 2-core
//! machine is noisy): read times as what one run measured.

use anyhow::{Context, bail};
use clap::{Args, ValueEnum};
use labrig_launch::config::{LaunchConfig, OnFailure};
use labrig_launch::supervise::Output;
use labrig_msgs::rig::EpisodeEventKind;
use labrig_msgs::topics;
use labrig_runtime::ros::Ros;
use labrig_runtime::{RosConfig, Shutdown};
use serde::Serialize;
use serde_json::{Value, json};
use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};
use std::process::{Command, ExitCode};
use std::time::{Duration, Instant};

#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum Fault {
    RecorderKill,
    DiskFull,
    DiskFullNomargin,
    DdsStop,
    BridgeKill,
    CameraStall,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum KillPoint {
    /// On the episode's Start event.
    Start,
    /// Three seconds (60 steps) into the episode.
    Mid,
    /// On the episode's end event (the recorder is closing it).
    End,
}

#[derive(Debug, Args)]
pub struct FaultArgs {
    /// The faults to inject (comma-separated).
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "recorder-kill,disk-full,disk-full-nomargin,dds-stop,bridge-kill,camera-stall"
    )]
    pub faults: Vec<Fault>,
    /// Where `recorder-kill` lands in the episode (comma-separated).
    #[arg(long, value_delimiter = ',', default_value = "start,mid,end")]
    pub kill_at: Vec<KillPoint>,
    /// Runs of each fault (kill point), for a distribution rather than one figure.
    #[arg(long, default_value_t = 1)]
    pub repeat: u32,
    /// How long `camera-stall` stalls the wrist camera (s).
    #[arg(long, default_value_t = 1.0)]
    pub stall_s: f64,
    /// Size of the tmpfs `disk-full` records into (MB).
    #[arg(long, default_value_t = 24)]
    pub disk_mb: u64,
    /// The DDS domain of the rig (each run uses its own, counting up from here).
    #[arg(long, default_value_t = 70)]
    pub domain_id: u16,
    /// Where each run's episodes go (kept for inspection); default: a temporary directory.
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Print the report as JSON (one object, last line).
    #[arg(long)]
    pub json: bool,
}

/// One fault's figures.
#[derive(Debug, Clone, Serialize)]
pub struct FaultReport {
    pub fault: String,
    /// What the rig did.
    pub outcome: String,
    /// Steps the loop published in the hit episode that no episode file holds.
    pub steps_lost: u64,
    /// Steps of that episode recorded / published.
    pub steps_recorded: u64,
    pub steps_published: u64,
    /// Seconds of camera frames missing from the hit episode (the worst camera).
    pub camera_s_lost: f64,
    /// Files the hit episode is in (more than one: continued after a restart).
    pub parts: usize,
    /// Fault to the node's own detection or the launcher's restart (ms).
    pub detect_ms: Option<f64>,
    /// Fault to the recorder recording again (ms).
    pub recover_ms: Option<f64>,
    /// Every episode filed is complete (no unfinished file) and nothing is left in `.recording/`.
    pub all_filed: bool,
    pub episodes: usize,
    /// Anything the run said that the table cannot (the refusal, the error).
    pub note: String,
    /// `camera-stall`: steps that repeat the stalled camera's last frame, and the most steps
    /// repeating any other camera's.
    pub stalled_steps: Option<u64>,
    pub other_late_steps: Option<u64>,
    /// The hit episode's directory (gone after the run unless `--out` keeps it), and the
    /// step indices the loop published in it, for a reader of one's own to check.
    pub hit_dir: Option<PathBuf>,
    pub published_steps: Vec<u64>,
}

pub fn run(a: FaultArgs) -> anyhow::Result<ExitCode> {
    anyhow::ensure!(
        a.stall_s.is_finite() && (0.0..=60.0).contains(&a.stall_s),
        "--stall-s must be 0..=60 s, got {}",
        a.stall_s
    );
    let keep = a.out.clone();
    let tmp = tempfile::tempdir()?;
    let base = keep.clone().unwrap_or_else(|| tmp.path().to_owned());
    std::fs::create_dir_all(&base).with_context(|| format!("creating {}", base.display()))?;
    let base = std::fs::canonicalize(&base)?;
    anyhow::ensure!((1..=20).contains(&a.repeat), "--repeat must be 1..=20");
    let mut plan: Vec<(Fault, Option<KillPoint>)> = Vec::new();
    for _ in 0..a.repeat {
        for &f in &a.faults {
            if f == Fault::RecorderKill {
                plan.extend(a.kill_at.iter().map(|&p| (f, Some(p))));
            } else {
                plan.push((f, None));
            }
        }
    }
    let bar = labrig_episode::progress::bar("faults {bar:20} {pos}/{len}", plan.len() as u64, a.json);
    let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build()?;
    let mut reports = Vec::new();
    for (k, (fault, point)) in plan.iter().enumerate() {
        let name = match point {
            Some(p) => format!("{}-{}", name_of(*fault), name_of(*p)),
            None => name_of(*fault),
        };
        bar.set_message(name.clone());
        let dir = base.join(format!("{k:02}-{name}"));
        std::fs::create_dir_all(&dir)?;
        let domain = a.domain_id + k as u16;
        let report = rt.block_on(run_one(*fault, *point, &dir, domain, a.disk_mb, a.stall_s, &name));
        let report = match report {
            Ok(r) => r,
            Err(e) => FaultReport { outcome: format!("ERROR: {e:#}"), ..empty(&name) },
        };
        bar.inc(1);
        if !a.json {
            bar.println(row(&report));
        }
        reports.push(report);
    }
    bar.finish_and_clear();
    if a.json {
        println!("{}", json!({ "faults": reports, "out": keep }));
    } else {
        println!("{}", header());
        for r in &reports {
            println!("{}", row(r));
        }
        for r in reports.iter().filter(|r| !r.note.is_empty()) {
            println!("  {}: {}", r.fault, r.note);
        }
    }
    let failed = reports.iter().any(|r| r.outcome.starts_with("ERROR"));
    Ok(if failed { ExitCode::from(1) } else { ExitCode::SUCCESS })
}

fn name_of<T: ValueEnum>(v: T) -> String {
    v.to_possible_value().map(|p| p.get_name().to_owned()).unwrap_or_default()
}

fn empty(name: &str) -> FaultReport {
    FaultReport {
        fault: name.to_owned(),
        outcome: String::new(),
        steps_lost: 0,
        steps_recorded: 0,
        steps_published: 0,
        camera_s_lost: 0.0,
        parts: 0,
        detect_ms: None,
        recover_ms: None,
        all_filed: false,
        episodes: 0,
        note: String::new(),
        stalled_steps: None,
        other_late_steps: None,
        hit_dir: None,
        published_steps: Vec::new(),
    }
}

fn header() -> String {
    format!(
        "{:<22} {:>6} {:>9} {:>9} {:>6} {:>10} {:>11} {:>6} {:>5}  outcome",
        "fault", "lost", "recorded", "published", "cam s", "detect ms", "recover ms", "parts", "filed"
    )
}

fn row(r: &FaultReport) -> String {
    let ms = |v: Option<f64>| v.map_or("-".into(), |v| format!("{v:.0}"));
    format!(
        "{:<22} {:>6} {:>9} {:>9} {:>6.2} {:>10} {:>11} {:>6} {:>5}  {}",
        r.fault,
        r.steps_lost,
        r.steps_recorded,
        r.steps_published,
        r.camera_s_lost,
        ms(r.detect_ms),
        ms(r.recover_ms),
        r.parts,
        if r.all_filed { "yes" } else { "NO" },
        r.outcome
    )
}

/// The camera `camera-stall` stalls.
const STALLED_CAMERA: &str = "wrist";

static NEXT_RIG: std::sync::atomic::AtomicU32 = std::sync::atomic::AtomicU32::new(0);

/// The demo's rig in real time, recording into `root`, `episodes` episodes.
fn rig(root: &Path, episodes: u64, recorder_sets: &[&str]) -> anyhow::Result<(LaunchConfig, Vec<usize>)> {
    let (mut cfg, order) =
        LaunchConfig::parse(labrig_launch::sim::SIM_DEMO, Path::new("launch_configs/sim_demo.toml"))?;
    let set = labrig_launch::sim::set_arg;
    let sim = cfg.node_mut("sim").context("no `sim` node")?;
    set(&mut sim.args, "--mode", "realtime");
    sim.args.push("--wall-clock-origin".into());
    let rec = cfg.node_mut("recorder").context("no `recorder` node")?;
    set(&mut rec.args, "--root", &root.display().to_string());
    for s in recorder_sets {
        rec.args.extend(["--set".into(), (*s).into()]);
    }
    rec.on_failure = Some(OnFailure::Restart);
    rec.max_restarts = 5;
    let ctl = cfg.node_mut("control").context("no `control` node")?;
    set(&mut ctl.args, "--episodes", &episodes.to_string());
    set(&mut ctl.args, "--clock", "wall");
    own_frames_namespace(&mut cfg);
    Ok((cfg, order))
}

/// The camera frames of this rig alone (other rigs may run on the machine): every node gets
/// the same fresh namespace.
fn own_frames_namespace(cfg: &mut LaunchConfig) {
    let ns = format!("faults_{}_{}", std::process::id(), NEXT_RIG.fetch_add(1, std::sync::atomic::Ordering::SeqCst));
    for n in &mut cfg.nodes {
        n.env.insert(labrig_runtime::frames::NAMESPACE_ENV.into(), ns.clone());
    }
}

/// The DROID rig's layout in the sim (sim_droid.toml): the bridge as hardware under /sim
/// (restarted once if it dies), the franka and gripper nodes in front of it, the recorder, the
/// loop on the wall clock with the bridge's scripted expert, one episode.
fn droid_rig(root: &Path) -> anyhow::Result<(LaunchConfig, Vec<usize>)> {
    let text = format!(
        r#"[rig]
name = "faults_bridge"
on_failure = "stop"
[[node]]
name = "sim"
program = "labrig-sim"
args = ["run", "--mode", "realtime", "--hardware-prefix", "/sim", "--expert", "--wall-clock-origin"]
health = "/joint_states"
on_failure = "restart"
max_restarts = 1
[[node]]
name = "franka"
program = "labrig-franka"
args = ["run", "--backend", "sim"]
after = ["sim"]
health = "/arm/state"
[[node]]
name = "gripper"
program = "labrig-gripper"
args = ["run", "--backend", "sim"]
after = ["sim"]
health = "/gripper/state"
[[node]]
name = "recorder"
program = "labrig-recorder"
args = ["run", "--root", "{}"]
after = ["franka", "gripper"]
health = "/recorder/status"
[[node]]
name = "control"
program = "labrig-control"
args = ["run", "--source", "scripted", "--clock", "sim", "--episodes", "1"]
after = ["franka", "gripper", "recorder"]
health = "/control/status"
"#,
        root.display()
    );
    let (mut cfg, order) = LaunchConfig::parse(&text, Path::new("<bench faults>"))?;
    own_frames_namespace(&mut cfg);
    Ok((cfg, order))
}

/// What the watcher saw of the rig.
#[derive(Debug, Default)]
struct Seen {
    /// Episode ids in the order they started.
    episodes: Vec<String>,
    /// Step indices the loop published, per episode.
    steps: BTreeMap<String, BTreeSet<u64>>,
    /// Recorder status messages with when they came.
    status: Vec<(Instant, Value)>,
    /// The control loop's last status.
    control: Value,
}

async fn run_one(
    fault: Fault,
    point: Option<KillPoint>,
    dir: &Path,
    domain: u16,
    disk_mb: u64,
    stall_s: f64,
    name: &str,
) -> anyhow::Result<FaultReport> {
    let root = dir.join("episodes");
    let _mount = if matches!(fault, Fault::DiskFull | Fault::DiskFullNomargin) {
        Some(Tmpfs::mount(&root, disk_mb)?)
    } else {
        None
    };
    let (episodes, sets): (u64, Vec<&str>) = match fault {
        Fault::RecorderKill | Fault::DdsStop | Fault::BridgeKill | Fault::CameraStall => (2, vec![]),
        Fault::DiskFull => (50, vec!["min_free_mb=1", "free_margin_episodes=2"]),
        Fault::DiskFullNomargin => (50, vec!["min_free_mb=0", "free_margin_episodes=0"]),
    };
    let (cfg, order) = if fault == Fault::BridgeKill { droid_rig(&root)? } else { rig(&root, episodes, &sets)? };
    let mut ros = Ros::new(&RosConfig { domain_id: domain, ..RosConfig::default() }, "labrig_bench_faults")?;
    let events = ros.subscription_on(&topics::RIG_EPISODE, 1000)?;
    let steps = ros.subscription_on(&topics::RIG_STEP, 1000)?;
    let rec_status = ros.subscription_on(&topics::RECORDER_STATUS, 100)?;
    let ctl_status = ros.subscription_on(&topics::CONTROL_STATUS, 10)?;
    let arm_state = ros.subscription_on(&topics::ARM_STATE, 100)?;
    let sim_fault = ros.publisher_on(&topics::SIM_FAULT, 10)?;
    let mut times = Times::default();
    let stop = Shutdown::new();
    let rig = {
        let stop = stop.clone();
        tokio::spawn(labrig_launch::supervise::supervise_until(
            cfg,
            order,
            PathBuf::from("launch_configs"),
            domain,
            Some(240.0),
            Output::Quiet,
            stop,
        ))
    };
    let recorder = format!("labrig-recorder run --root {}", root.display());
    let bridge = format!(
        "labrig-sim run --mode realtime --hardware-prefix /sim --expert --wall-clock-origin --domain-id {domain}"
    );
    let mut seen = Seen::default();
    let started = Instant::now();
    while !rig.is_finished() {
        while let Some(e) = events.try_take()? {
            let id = e.msg.episode_id.clone();
            let kind = e.msg.kind();
            if kind == Ok(EpisodeEventKind::Start) && !seen.episodes.contains(&id) {
                seen.episodes.push(id.clone());
            }
            if times.hit_at.is_some() && times.stopped.is_none() && kind == Ok(EpisodeEventKind::Stop) {
                times.stopped = Some((Instant::now(), e.msg.note.clone()));
            }
            let first = seen.episodes.first() == Some(&id);
            if times.hit_at.is_none() && first && fault == Fault::RecorderKill {
                let now = matches!(
                    (point, kind),
                    (Some(KillPoint::Start), Ok(EpisodeEventKind::Start))
                        | (Some(KillPoint::End), Ok(EpisodeEventKind::Success | EpisodeEventKind::Failure))
                );
                if now {
                    signal("-KILL", &recorder)?;
                    times.hit_at = Some(Instant::now());
                }
            }
        }
        while let Some(s) = steps.try_take()? {
            seen.steps.entry(s.msg.episode_id.clone()).or_default().insert(s.msg.step_index);
        }
        let first_steps = seen.episodes.first().and_then(|id| seen.steps.get(id)).map_or(0, |s| s.len());
        // Mid-episode: 3 s in; a camera stall 1 s in, so that the expert's episode outlasts the
        // stall (stalled at step 60, an 84-step episode ended 24 steps into a 2 s stall).
        let hit_step = if fault == Fault::CameraStall { 20 } else { 60 };
        if times.hit_at.is_none() && first_steps >= hit_step {
            match (fault, point) {
                (Fault::RecorderKill, Some(KillPoint::Mid)) => {
                    signal("-KILL", &recorder)?;
                    times.hit_at = Some(Instant::now());
                }
                (Fault::CameraStall, _) => {
                    let stall = json!({ "stall_camera": { "camera": STALLED_CAMERA, "seconds": stall_s } });
                    sim_fault.publish(labrig_msgs::std_msgs::StringMsg { data: stall.to_string() })?;
                    times.hit_at = Some(Instant::now());
                }
                (Fault::BridgeKill, _) => {
                    signal("-KILL", &bridge)?;
                    times.hit_at = Some(Instant::now());
                }
                (Fault::DdsStop, _) => {
                    signal("-STOP", &recorder)?;
                    tokio::time::sleep(Duration::from_millis(300)).await;
                    signal("-CONT", &recorder)?;
                    times.hit_at = Some(Instant::now());
                }
                _ => {}
            }
        }
        while let Some(s) = rec_status.try_take()? {
            let v: Value = serde_json::from_str(&s.msg.data).unwrap_or_default();
            if times.refused_at.is_none() && v["accepting"] == false && v["state"] != "recording" {
                times.refused_at = Some(Instant::now());
            }
            seen.status.push((Instant::now(), v));
        }
        while let Some(s) = arm_state.try_take()? {
            if times.hit_at.is_some()
                && times.arm_fault.is_none()
                && s.msg.mode == labrig_msgs::rig::RobotState::MODE_FAULT
            {
                times.arm_fault = Some((Instant::now(), s.msg.fault.clone()));
            }
        }
        // The bridge's episode is filed: the run is over.
        if fault == Fault::BridgeKill
            && times.hit_at.is_some()
            && seen.status.iter().any(|(t, v)| after(t, times.hit_at) && v["state"] == "recorded")
        {
            stop.trigger();
        }
        while let Some(s) = ctl_status.try_take()? {
            seen.control = serde_json::from_str(&s.msg.data).unwrap_or_default();
            if times.refused_at.is_some() && times.idle_at.is_none() && !seen.control["recorder_refusal"].is_null() {
                times.idle_at = Some(Instant::now());
            }
        }
        // A full disk holds the rig Idle: seen for 3 s, the run is over.
        if times.idle_at.is_some_and(|t| t.elapsed() > Duration::from_secs(3)) {
            stop.trigger();
        }
        if started.elapsed() > Duration::from_secs(300) {
            stop.trigger();
            bail!("{name}: the rig did not finish in 300 s");
        }
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
    let code = rig.await.context("the launcher task")??;
    Ok(judge(fault, name, &root, code, &seen, &times))
}

/// When the run's events happened (each the first of its kind after the fault was applied).
#[derive(Debug, Default)]
struct Times {
    /// The fault applied.
    hit_at: Option<Instant>,
    /// The recorder refused to start an episode (a full disk).
    refused_at: Option<Instant>,
    /// The loop reported the refusal and held the rig.
    idle_at: Option<Instant>,
    /// The franka node reported a fault, and what it said.
    arm_fault: Option<(Instant, String)>,
    /// The loop stopped the episode, and its note.
    stopped: Option<(Instant, String)>,
}

/// The run's report from what was seen on the wire and what was filed under `root`.
fn judge(fault: Fault, name: &str, root: &Path, code: ExitCode, seen: &Seen, times: &Times) -> FaultReport {
    let Times { hit_at, refused_at, idle_at, arm_fault, stopped } = times;
    let (hit_at, refused_at, idle_at) = (*hit_at, *refused_at, *idle_at);
    let filed = filed_episodes(root);
    let staging_left = std::fs::read_dir(root.join(".recording")).map_or(0, |d| d.count());
    let mut r = empty(name);
    r.episodes = filed.len();
    r.all_filed = staging_left == 0 && filed.iter().all(|(_, i)| i.parts.iter().all(|p| p.complete));
    // The hit episode: the first one (kills, a stop) or the one the disk filled on.
    let hit = match fault {
        Fault::DiskFull | Fault::DiskFullNomargin => seen.episodes.last().cloned(),
        _ => seen.episodes.first().cloned(),
    };
    let after_hit = |t: &Instant| after(t, hit_at);
    r.recover_ms = hit_at.and_then(|h| {
        seen.status
            .iter()
            .find(|(t, v)| after_hit(t) && v["state"] != "idle")
            .map(|(t, _)| t.duration_since(h).as_secs_f64() * 1e3)
    });
    // The launcher restarts within its 100 ms poll; the new recorder's first status is the
    // earliest sign the fault was handled.
    r.detect_ms = hit_at.and_then(|h| {
        seen.status.iter().find(|(t, _)| after_hit(t)).map(|(t, _)| t.duration_since(h).as_secs_f64() * 1e3)
    });
    if let Some(id) = &hit {
        let published = seen.steps.get(id).cloned().unwrap_or_default();
        r.steps_published = published.len() as u64;
        r.published_steps = published.iter().copied().collect();
        if let Some((dir, i)) = filed.iter().find(|(_, i)| i.metadata.as_ref().is_some_and(|m| &m.uuid == id)) {
            r.hit_dir = Some(dir.clone());
            let data = labrig_episode::read_episode(dir);
            let recorded: BTreeSet<u64> =
                data.map(|d| d.steps.iter().map(|s| s.step_index).collect()).unwrap_or_default();
            r.steps_recorded = recorded.len() as u64;
            r.steps_lost = published.difference(&recorded).count() as u64;
            r.parts = i.parts.len();
            let frames = i.cameras.iter().map(|c| c.frames).min().unwrap_or(0);
            r.camera_s_lost = (r.steps_recorded.saturating_sub(frames)) as f64 * 0.05;
        } else {
            r.steps_lost = r.steps_published;
        }
    }
    let last_error = seen.status.iter().rev().find_map(|(_, v)| v["error"].as_str().map(str::to_owned));
    r.outcome = match fault {
        Fault::RecorderKill | Fault::DdsStop => {
            format!("recorder restarted; the episode filed in {} part(s), {} steps lost", r.parts, r.steps_lost)
        }
        Fault::CameraStall => camera_stall(&mut r, hit.as_ref(), &filed),
        Fault::BridgeKill => match (&arm_fault, &stopped) {
            (Some(_), Some((_, note))) => {
                format!("the franka node held and reported; the loop stopped the episode ({note})")
            }
            (Some((_, f)), None) => format!("the franka node reported ({f}); the loop did NOT stop the episode"),
            (None, _) => "the franka node did NOT report a fault".into(),
        },
        Fault::DiskFull | Fault::DiskFullNomargin => format!(
            "{} episodes filed; then {}; the loop {}",
            r.episodes,
            if refused_at.is_some() { "the recorder refused the next" } else { "NO refusal" },
            if idle_at.is_some() { "held the rig Idle" } else { "did NOT hold the rig" }
        ),
    };
    if fault == Fault::CameraStall {
        (r.detect_ms, r.recover_ms) = (None, None);
    }
    if fault == Fault::BridgeKill {
        // Detected: the franka node's fault; recovered: the episode stopped and filed.
        r.detect_ms = hit_at.zip(arm_fault.as_ref()).map(|(h, (t, _))| t.duration_since(h).as_secs_f64() * 1e3);
        r.recover_ms = hit_at.zip(stopped.as_ref()).map(|(h, (t, _))| t.duration_since(h).as_secs_f64() * 1e3);
    }
    if let (Some(r0), Some(i0)) = (refused_at, idle_at) {
        r.detect_ms = Some(i0.duration_since(r0).as_secs_f64() * 1e3);
    }
    r.note = last_error.unwrap_or_default();
    if code != ExitCode::SUCCESS && !matches!(fault, Fault::DiskFull | Fault::DiskFullNomargin | Fault::BridgeKill) {
        r.note = format!("the rig stopped with an error; {}", r.note);
    }
    r
}

/// The camera-stall run's outcome: how many steps of the hit episode carry the stalled
/// camera's last frame again, against the other cameras.
fn camera_stall(r: &mut FaultReport, hit: Option<&String>, filed: &[(PathBuf, labrig_episode::Inspection)]) -> String {
    let hit_dir = hit.and_then(|id| filed.iter().find(|(_, i)| i.metadata.as_ref().is_some_and(|m| &m.uuid == id)));
    match hit_dir {
        Some((dir, i)) => {
            // Per step, each camera's frame reference: a step that repeats the last
            // step's frame of a camera (same sequence) had nothing newer from it.
            let steps = labrig_episode::read_episode(dir).map(|d| d.steps).unwrap_or_default();
            let mut repeated: BTreeMap<String, u64> = BTreeMap::new();
            for w in steps.windows(2) {
                for c in &w[1].cameras {
                    let before = w[0].cameras.iter().find(|p| p.camera_id == c.camera_id);
                    if before.is_some_and(|p| p.sequence == c.sequence) {
                        *repeated.entry(c.camera_id.clone()).or_default() += 1;
                    }
                }
            }
            let stalled = repeated.get(STALLED_CAMERA).copied().unwrap_or(0);
            let others = repeated.iter().filter(|(c, _)| *c != STALLED_CAMERA).map(|(_, n)| *n).max().unwrap_or(0);
            let dropped = i.cameras.iter().find(|c| c.camera == STALLED_CAMERA).map_or(0, |c| c.dropped);
            r.stalled_steps = Some(stalled);
            r.other_late_steps = Some(others);
            format!(
                "{stalled} steps carry the {STALLED_CAMERA} camera's last frame again (its capture time, so its age, in the step; inspect: {dropped} {STALLED_CAMERA} frames dropped); the other cameras at most {others}"
            )
        }
        None => "the episode was not filed".into(),
    }
}

fn after(t: &Instant, hit: Option<Instant>) -> bool {
    hit.is_some_and(|h| *t > h)
}

/// Sends `sig` to the processes whose command line contains `pattern`.
fn signal(sig: &str, pattern: &str) -> anyhow::Result<()> {
    let ok = Command::new("pkill").args([sig, "-f", "--", pattern]).status()?.success();
    anyhow::ensure!(ok, "no process matches {pattern:?}");
    Ok(())
}

/// Every episode directory under `root`'s success/ and failure/, inspected.
fn filed_episodes(root: &Path) -> Vec<(PathBuf, labrig_episode::Inspection)> {
    let mut out = Vec::new();
    for outcome in ["success", "failure"] {
        let Ok(days) = std::fs::read_dir(root.join(outcome)) else { continue };
        for day in days.filter_map(|d| d.ok()) {
            let Ok(eps) = std::fs::read_dir(day.path()) else { continue };
            for ep in eps.filter_map(|e| e.ok()) {
                if let Ok(i) = labrig_episode::inspect(&ep.path()) {
                    out.push((ep.path(), i));
                }
            }
        }
    }
    out
}

/// A tmpfs of `mb` MB mounted at `path` while it lives.
struct Tmpfs(PathBuf);

impl Tmpfs {
    fn mount(path: &Path, mb: u64) -> anyhow::Result<Tmpfs> {
        std::fs::create_dir_all(path)?;
        let out = Command::new("mount")
            .args(["-t", "tmpfs", "-o", &format!("size={mb}m"), "labrig-faults"])
            .arg(path)
            .output()
            .context("running mount")?;
        if !out.status.success() {
            bail!(
                "disk-full needs a small filesystem: mounting a {mb} MB tmpfs at {} failed (root is needed): {}",
                path.display(),
                String::from_utf8_lossy(&out.stderr).trim()
            );
        }
        Ok(Tmpfs(path.to_owned()))
    }
}

impl Drop for Tmpfs {
    fn drop(&mut self) {
        // The episodes are copied out first, so a kept --out still shows them.
        let keep = self.0.with_file_name("episodes_kept");
        let _ = Command::new("cp").arg("-a").arg(&self.0).arg(&keep).status();
        let _ = Command::new("umount").arg(&self.0).status();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_rig_restarts_the_recorder_and_records_where_asked() {
        let (cfg, _) = rig(Path::new("/data/eps"), 2, &["min_free_mb=1"]).unwrap();
        let rec = cfg.nodes.iter().find(|n| n.name == "recorder").unwrap();
        assert_eq!(rec.on_failure, Some(OnFailure::Restart));
        assert!(rec.args.windows(2).any(|w| w == ["--root", "/data/eps"]), "{:?}", rec.args);
        assert!(rec.args.windows(2).any(|w| w == ["--set", "min_free_mb=1"]), "{:?}", rec.args);
        let ctl = cfg.nodes.iter().find(|n| n.name == "control").unwrap();
        assert!(ctl.args.windows(2).any(|w| w == ["--clock", "wall"]), "{:?}", ctl.args);
        assert!(ctl.args.windows(2).any(|w| w == ["--episodes", "2"]), "{:?}", ctl.args);
    }
}
