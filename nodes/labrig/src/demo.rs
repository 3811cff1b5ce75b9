//! `labrig demo`: the main job on a fresh machine. The simulated DROID rig
//! (launch_configs/sim_demo.toml: the MuJoCo bridge in lockstep as the FR3, the 2F-85 and the
//! five cameras; the recorder; the control loop with the scripted expert as its action
//! source) collects seeded pick-and-place episodes as DROID-format MCAP. The demo then prints
//! where each episode is with its `labrig inspect` summary and writes a contact sheet of the
//! five cameras per episode (first, middle and last recorded frame).

use anyhow::{Context, bail};
use clap::Args;
use labrig_episode::progress;
use labrig_launch::config::LaunchConfig;
use labrig_launch::sim::{SIM_DEMO, SimRig, contact_sheet, set_arg};
use labrig_msgs::rig::EpisodeEventKind;
use labrig_msgs::std_msgs::StringMsg;
use labrig_msgs::topics;
use labrig_runtime::RosConfig;
use labrig_runtime::ros::{Ros, qos};
use serde_json::json;
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::Duration;

#[derive(Debug, Args)]
pub struct DemoArgs {
    /// Seeded pick-and-place episodes to record.
    #[arg(long, default_value_t = 3)]
    pub episodes: u64,
    /// The first scene seed (the episodes take seeds first..first+episodes).
    #[arg(long, default_value_t = 0)]
    pub first_seed: u64,
    /// The scene: a built-in one (pick_place, drawer_open, drawer_close) or a spec file
    /// (sim/scenes/*.toml shows the format): camera bins, object boxes, textures.
    #[arg(long, default_value = "pick_place")]
    pub scene: String,
    /// Run the sim in real time instead of lockstep.
    #[arg(long)]
    pub realtime: bool,
    /// Where the episodes (DROID layout under `episodes/`) and the contact sheets go.
    #[arg(long, default_value = "out/demo")]
    pub out: PathBuf,
    /// DDS domain id for the demo's rig.
    #[arg(long, default_value_t = 42)]
    pub domain_id: u16,
    /// Print the report as JSON.
    #[arg(long)]
    pub json: bool,
    /// Camera calibrations (`labrig calibrate --sim --out-dir DIR`): the rig publishes them on
    /// /tf_static and /calibration, every episode's metadata carries them, and the loop warns
    /// at start for cameras without a current one.
    #[arg(long)]
    pub calibration: Option<PathBuf>,
    /// Demos that look and correct: the expert's first approach stops up to this far (m)
    /// beside the cube (the drawer's handle), in a direction drawn from the seed, then corrects
    /// over it; its descent pauses 5 cm above the grasp a third as far off and corrects again.
    /// Every recorded action is still the expert's. Image policies learn from these to centre
    /// the cube (handle) in the wrist camera before they grasp. 0 = the exact expert.
    #[arg(long, default_value_t = 0.0)]
    pub expert_aim_error_m: f64,
    /// Demos with a missed grasp and its recovery: in this fraction of the scenes (drawn from
    /// the seed) the expert's first grasp closes on nothing on purpose (4-5.5 cm beside the
    /// cube; 6-7.5 cm toward the robot from the drawer handle's centre), then it rises,
    /// opens, comes back and grasps. The miss's descent and close are not labels for training
    /// (`skip_missed_grasps`); the way back is. 0 = never.
    #[arg(long, default_value_t = 0.0)]
    pub expert_miss_fraction: f64,
}

pub fn run(args: DemoArgs) -> anyhow::Result<ExitCode> {
    anyhow::ensure!((1..=100).contains(&args.episodes), "--episodes must be in 1..=100");
    let origin = Path::new("launch_configs/sim_demo.toml");
    let (mut cfg, order) = LaunchConfig::parse(SIM_DEMO, origin)?;
    std::fs::create_dir_all(&args.out).with_context(|| format!("creating {}", args.out.display()))?;
    let out = std::fs::canonicalize(&args.out)?;
    let root = out.join("episodes");
    // A spec file is handed to the sim by its absolute path (the nodes' working folder may differ).
    let scene = match Path::new(&args.scene) {
        p if p.is_file() => std::fs::canonicalize(p)?.display().to_string(),
        p if p.extension().is_some_and(|e| e == "toml") || args.scene.contains('/') => {
            bail!("--scene {}: no such spec file", p.display())
        }
        // A built-in name: the sim node knows them and names a wrong one.
        _ => args.scene.clone(),
    };
    let calibration = match &args.calibration {
        Some(dir) => Some(
            std::fs::canonicalize(dir)
                .with_context(|| format!("--calibration {}: no such folder", dir.display()))?
                .display()
                .to_string(),
        ),
        None => None,
    };
    {
        let sim = cfg.node_mut("sim").context("sim_demo.toml has no `sim` node")?;
        set_arg(&mut sim.args, "--mode", if args.realtime { "realtime" } else { "lockstep" });
        set_arg(&mut sim.args, "--scene", &scene);
        if let Some(dir) = &calibration {
            set_arg(&mut sim.args, "--calibration", dir);
        }
        if args.expert_aim_error_m != 0.0 {
            set_arg(&mut sim.args, "--expert-aim-error-m", &args.expert_aim_error_m.to_string());
        }
        if args.expert_miss_fraction != 0.0 {
            set_arg(&mut sim.args, "--expert-miss-fraction", &args.expert_miss_fraction.to_string());
        }
        if args.realtime {
            sim.args.extend(["--wall-clock-origin".into(), "--realtime-priority".into(), "10".into()]);
        }
        let rec = cfg.node_mut("recorder").context("sim_demo.toml has no `recorder` node")?;
        set_arg(&mut rec.args, "--root", &root.display().to_string());
        let ctl = cfg.node_mut("control").context("sim_demo.toml has no `control` node")?;
        if let Some(dir) = &calibration {
            ctl.args.extend(["--set".into(), format!("calibration={dir:?}")]);
        }
        set_arg(&mut ctl.args, "--episodes", &args.episodes.to_string());
        set_arg(&mut ctl.args, "--first-seed", &args.first_seed.to_string());
        if args.realtime {
            set_arg(&mut ctl.args, "--clock", "wall");
        } else {
            // In lockstep the sim keeps no pace of its own: a scene rebuild between episodes on
            // a busy machine took over the loop's default 2 s and ended two 100-episode demos
            // early (as sim_rollout.toml says for rollouts). A bridge that is gone still ends it.
            ctl.args.extend(["--set".into(), "tick_timeout_s=15".into()]);
        }
    }
    let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build()?;
    // What was saved is reported before any error that came after it (a full disk, a node
    // that died): the error is the run's last word, not its only one.
    let (recorded, failure) = rt.block_on(collect(&args, cfg, order));
    drop(rt);

    let mut reports = Vec::new();
    let mut problems: Vec<String> = failure.iter().map(|e| format!("{e:#}")).collect();
    let mut ok = recorded.len() as u64 == args.episodes && failure.is_none();
    for (k, dir) in recorded.iter().enumerate() {
        let inspection = match labrig_episode::inspect::inspect(dir) {
            Ok(i) => i,
            Err(e) => {
                problems.push(format!("episode {k}: {e}"));
                ok = false;
                continue;
            }
        };
        let sheet = out.join(format!("episode_{k}_cameras.png"));
        let sheet = match contact_sheet(&inspection.path, &sheet) {
            Ok(()) => Some(sheet),
            Err(e) => {
                problems.push(format!("contact sheet of episode {k} ({}): {e:#}", dir.display()));
                None
            }
        };
        ok &= inspection.flags.is_empty();
        reports.push((dir.clone(), inspection, sheet));
    }
    let successes =
        reports.iter().filter(|(_, i, _)| i.metadata.as_ref().and_then(|m| m.success) == Some(true)).count();
    if args.json {
        let episodes: Vec<_> =
            reports.iter().map(|(dir, i, sheet)| json!({ "dir": dir, "contact_sheet": sheet, "inspect": i })).collect();
        let report = labrig_reports::DemoReport {
            episodes,
            recorded: reports.len(),
            successes,
            root: root.clone(),
            ok,
            errors: problems.clone(),
        };
        println!("{}", serde_json::to_string(&report)?);
    } else {
        println!(
            "labrig demo: {} of {} episodes recorded ({} successful) under {}",
            reports.len(),
            args.episodes,
            successes,
            root.display()
        );
        for (k, (dir, i, sheet)) in reports.iter().enumerate() {
            println!();
            print!("{}", summary_text(k, dir, i));
            if let Some(sheet) = sheet {
                println!("  cameras (first, middle, last frame): {}", sheet.display());
            }
        }
        println!();
        println!("Inspect one again: labrig inspect <dir>; replay it: labrig replay <dir> --sim [--plot replay.png];");
        println!(
            "read them with any MCAP or rosbag2 reader; as DROID raw data: labrig export droid <episodes dir> <out dir>."
        );
        for p in &problems {
            eprintln!("error: {p}");
        }
    }
    Ok(if ok { ExitCode::SUCCESS } else { ExitCode::from(1) })
}

/// A few lines per episode (the whole report: `labrig inspect <dir>`).
fn summary_text(k: usize, dir: &Path, i: &labrig_episode::inspect::Inspection) -> String {
    use std::fmt::Write;
    let mut s = String::new();
    let meta = i.metadata.as_ref();
    let _ = writeln!(s, "episode {k}: {}", dir.display());
    let _ = writeln!(
        s,
        "  {}  task \"{}\"  success {}",
        meta.map_or("-", |m| m.uuid.as_str()),
        meta.map_or("", |m| m.task_instruction.as_str()),
        meta.and_then(|m| m.success).map_or("unknown".into(), |b| b.to_string())
    );
    let frames: Vec<String> = i.cameras.iter().map(|c| format!("{} {}", c.camera, c.frames)).collect();
    let dropped: u64 = i.cameras.iter().map(|c| c.dropped).sum();
    let _ = writeln!(
        s,
        "  {} steps, {:.1} s, {} messages, {:.1} MB; frames: {}; dropped {dropped}",
        i.steps,
        i.duration_s,
        i.messages,
        std::fs::metadata(&i.path).map_or(0.0, |m| m.len() as f64 / 1e6),
        frames.join(", ")
    );
    let pct = |p: &Option<labrig_episode::inspect::Percentiles>| {
        p.as_ref().map_or("-".into(), |p| format!("p50 {:.3} / p99 {:.3} / max {:.3} ms", p.p50, p.p99, p.max))
    };
    let _ = writeln!(
        s,
        "  camera skew {}; control jitter {}; missed ticks {}",
        pct(&i.camera_skew_ms),
        pct(&i.control_jitter_ms),
        i.missed_ticks
    );
    let _ = writeln!(s, "  inspect: {}", if i.flags.is_empty() { "OK".to_string() } else { i.flags.join("; ") });
    s
}

/// Runs the rig until the control loop has its episodes; returns the episode directories
/// the recorder reported, in order, and what stopped the run early, if anything.
async fn collect(args: &DemoArgs, cfg: LaunchConfig, order: Vec<usize>) -> (Vec<PathBuf>, Option<anyhow::Error>) {
    let mut recorded = Vec::new();
    let failure = run_rig(args, cfg, order, &mut recorded).await.err();
    (recorded, failure)
}

async fn run_rig(
    args: &DemoArgs,
    cfg: LaunchConfig,
    order: Vec<usize>,
    recorded: &mut Vec<PathBuf>,
) -> anyhow::Result<()> {
    let ros_cfg = RosConfig { domain_id: args.domain_id, ..RosConfig::default() };
    ros_cfg.validate(Path::new("<command line>"))?;
    let mut ros = Ros::new(&ros_cfg, "labrig_demo")?;
    let events = ros.subscription_on(&topics::RIG_EPISODE, 100)?;
    let steps = ros.subscription_on(&topics::RIG_STEP, 1000)?;
    let status = ros.subscription::<StringMsg>(topics::RECORDER_STATUS.name, qos::reliable(100))?;
    let bar = progress::bar("demo {bar:25} {pos}/{len} episodes", args.episodes, args.json);
    bar.set_message("starting the simulated rig");
    let SimRig { watch, stop, rig } = SimRig::start(cfg, order, args.domain_id)?;
    let mut refusal: Option<String> = None;
    let mut step_count = 0u64;
    let mut episode = 0u64;
    loop {
        while let Some(e) = events.try_take()? {
            match e.msg.kind() {
                Ok(EpisodeEventKind::Start) => {
                    episode += 1;
                    step_count = 0;
                    bar.set_message(format!("episode {episode}: \"{}\"", e.msg.note));
                }
                Ok(EpisodeEventKind::Success) => bar.set_message(format!("episode {episode}: success, arm going home")),
                Ok(EpisodeEventKind::Failure | EpisodeEventKind::Stop) => {
                    bar.set_message(format!("episode {episode}: failure, arm going home"))
                }
                _ => {}
            }
        }
        while steps.try_take()?.is_some() {
            step_count += 1;
            if step_count.is_multiple_of(10) {
                bar.set_message(format!("episode {episode}: {step_count} steps"));
            }
        }
        while let Some(s) = status.try_take()? {
            let v: serde_json::Value = serde_json::from_str(&s.msg.data).unwrap_or_default();
            if v["state"] == "recorded"
                && let Some(dir) = v["dir"].as_str()
            {
                let dir = PathBuf::from(dir);
                if !recorded.contains(&dir) {
                    recorded.push(dir);
                    bar.inc(1);
                }
            } else if v["state"] == "error" {
                bar.println(format!("recorder: {}", v["error"]));
            }
            // No space for another episode: the loop holds the rig Idle; the demo stops.
            if v["accepting"] == false && refusal.is_none() && v["state"] != "recording" {
                let why = format!(
                    "the recorder takes no more episodes: {:.1} MB free under {}, {:.1} MB needed",
                    v["free_bytes"].as_f64().unwrap_or(0.0) / 1e6,
                    args.out.display(),
                    v["needed_bytes"].as_f64().unwrap_or(0.0) / 1e6
                );
                bar.println(format!("{why}: stopping the rig"));
                refusal = Some(why);
                stop.trigger();
            }
        }
        if watch.is_triggered() {
            break;
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    bar.finish_and_clear();
    let code = rig.await.context("the launcher task")??;
    if let Some(why) = refusal {
        bail!("{why}");
    }
    if code != ExitCode::SUCCESS {
        bail!("the simulated rig stopped with an error (see above)");
    }
    Ok(())
}
