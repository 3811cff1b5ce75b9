//! The rig loop measured free-running (`labrig bench loop`, `labrig bench station`). The demo's rig
//! (launch_configs/sim_demo.toml) with the sim bridge in real time on the wall clock's time
//! line, the control loop on the wall clock, the scripted expert collecting episodes back to
//! back and the recorder writing all five cameras. Reports the loop's tick period jitter
//! (p50/p99/max), missed ticks, steps with a missing or stale camera frame, dropped frames
//! in the recordings, the recorder's (and the bridge's and loop's) CPU, and MB/s written.

use crate::config::LaunchConfig;
use crate::sim::set_arg;
use crate::supervise::Output;
use anyhow::Context;
use clap::Args;
use serde_json::json;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::{Duration, Instant};

#[derive(Debug, Args)]
pub struct LoopArgs {
    /// How long the rig runs (the figure is 300 s).
    #[arg(long, default_value_t = 300.0)]
    pub seconds: f64,
    /// Camera image size.
    #[arg(long, default_value_t = 128)]
    pub width: u32,
    #[arg(long, default_value_t = 128)]
    pub height: u32,
    /// Where the episodes and the stats go (default: a temporary directory, removed).
    #[arg(long)]
    pub out: Option<PathBuf>,
    #[arg(long, default_value_t = 43)]
    pub domain_id: u16,
    #[arg(long)]
    pub json: bool,
}

/// CPU seconds of a process and when they were read.
type CpuSample = (f64, Instant);

/// The rig's processes: program name -> pid, found by the `--domain-id <domain>` the
/// launcher gives every node.
fn rig_pids(domain: u16) -> BTreeMap<String, u32> {
    let domain = domain.to_string();
    let mut found = BTreeMap::new();
    let Ok(dir) = std::fs::read_dir("/proc") else { return found };
    for e in dir.flatten() {
        let Some(pid) = e.file_name().to_str().and_then(|s| s.parse::<u32>().ok()) else { continue };
        let Ok(cmd) = std::fs::read(format!("/proc/{pid}/cmdline")) else { continue };
        let args: Vec<String> = cmd.split(|&b| b == 0).map(|a| String::from_utf8_lossy(a).into_owned()).collect();
        if !args.windows(2).any(|w| w[0] == "--domain-id" && w[1] == domain) {
            continue;
        }
        if let Some(name) =
            args.first().and_then(|a| Path::new(a).file_name()).map(|n| n.to_string_lossy().into_owned())
        {
            found.insert(name, pid);
        }
    }
    found
}

/// The space free to an unprivileged writer on the file system holding `path` (0 when it cannot
/// be read).
pub fn free_bytes(path: &Path) -> u64 {
    nix::sys::statvfs::statvfs(path).map_or(0, |s| s.blocks_available() * s.fragment_size())
}

/// What runs beside the rig while it is measured: a node added to the launch config, and a
/// load started once the rig is up (it runs until the flag turns true).
pub struct Beside {
    pub node: crate::config::NodeSpec,
    pub load: Load,
}

/// Starts the load; it runs until the flag turns true and its thread returns its figures.
pub type Load =
    Box<dyn FnOnce(std::sync::Arc<std::sync::atomic::AtomicBool>) -> std::thread::JoinHandle<serde_json::Value>>;

impl std::fmt::Debug for Beside {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Beside").field("node", &self.node.name).finish()
    }
}

/// Called every half second with the rig's processes (program -> pid) and the seconds since
/// the start.
pub type Every<'a> = &'a mut dyn FnMut(&BTreeMap<String, u32>, f64);

/// What a long measurement adds (`labrig bench soak`).
#[derive(Default)]
pub struct Hooks<'a> {
    /// Settings for the control loop (`--set key=value`), e.g. its window figures.
    pub control_sets: Vec<(String, String)>,
    pub every: Option<Every<'a>>,
    /// A Ctrl-C (or SIGTERM) ends the measured window early with the report so far, instead of
    /// failing the run.
    pub interruptible: bool,
}

impl std::fmt::Debug for Hooks<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Hooks")
            .field("control_sets", &self.control_sets)
            .field("every", &self.every.is_some())
            .field("interruptible", &self.interruptible)
            .finish()
    }
}

/// One measured run of the demo's rig in real time for `a.seconds` (episodes under
/// `out/episodes`), with `beside` running next to it; the report as JSON (`load`: what the load
/// returned).
pub fn measure(a: &LoopArgs, out: &Path, beside: Option<Beside>) -> anyhow::Result<serde_json::Value> {
    measure_with(a, out, beside, Hooks::default())
}

/// [`measure`] with `hooks`; the report also says whether the run was `interrupted`.
pub fn measure_with(
    a: &LoopArgs,
    out: &Path,
    beside: Option<Beside>,
    mut hooks: Hooks,
) -> anyhow::Result<serde_json::Value> {
    let root = out.join("episodes");
    let stats = out.join("control_stats.json");
    let (mut cfg, order) = LaunchConfig::parse(crate::sim::SIM_DEMO, Path::new("launch_configs/sim_demo.toml"))?;
    {
        let sim = cfg.node_mut("sim").context("no `sim` node")?;
        set_arg(&mut sim.args, "--mode", "realtime");
        set_arg(&mut sim.args, "--width", &a.width.to_string());
        set_arg(&mut sim.args, "--height", &a.height.to_string());
        sim.args.extend(["--wall-clock-origin".into(), "--realtime-priority".into(), "10".into()]);
        let rec = cfg.node_mut("recorder").context("no `recorder` node")?;
        set_arg(&mut rec.args, "--root", &root.display().to_string());
        let ctl = cfg.node_mut("control").context("no `control` node")?;
        set_arg(&mut ctl.args, "--clock", "wall");
        set_arg(&mut ctl.args, "--episodes", "0");
        set_arg(&mut ctl.args, "--stats-out", &stats.display().to_string());
        for (k, v) in &hooks.control_sets {
            ctl.args.extend(["--set".into(), format!("{k}={v}")]);
        }
    }
    let (mut load, mut order) = (None, order);
    if let Some(b) = beside {
        order.push(cfg.nodes.len());
        cfg.nodes.push(b.node);
        load = Some(b.load);
    }
    let stop_load = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
    let mut load_thread = None;
    let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build()?;
    let shutdown = labrig_runtime::Shutdown::new();
    if hooks.interruptible {
        let _in_runtime = rt.enter();
        shutdown.trigger_on_signals()?;
    }
    let bar = labrig_episode::progress::bar("bench loop {bar:30} {pos}/{len} s", a.seconds as u64, a.json);
    let started = Instant::now();
    // First and last sample of each process's CPU seconds, with their times.
    let mut cpu: BTreeMap<String, [CpuSample; 2]> = BTreeMap::new();
    let code = rt.block_on(async {
        let seconds = a.seconds;
        let rig = tokio::spawn(crate::supervise::supervise_until(
            cfg,
            order,
            PathBuf::from("launch_configs"),
            a.domain_id,
            Some(seconds + 15.0),
            Output::Quiet,
            shutdown.clone(),
        ));
        let mut control_pid = None;
        while !rig.is_finished() {
            tokio::time::sleep(Duration::from_millis(500)).await;
            bar.set_position(started.elapsed().as_secs().min(seconds as u64));
            let pids = rig_pids(a.domain_id);
            for (name, pid) in &pids {
                if let Some(c) = labrig_runtime::bench::cpu_seconds_of(&pid.to_string()) {
                    let e = cpu.entry(name.clone()).or_insert([(c, Instant::now()); 2]);
                    e[1] = (c, Instant::now());
                }
            }
            if let Some(&pid) = pids.get("labrig-control") {
                control_pid = Some(pid);
            }
            if let Some(f) = hooks.every.as_mut() {
                f(&pids, started.elapsed().as_secs_f64());
            }
            // The load starts once every node of the rig is running.
            if load_thread.is_none()
                && pids.contains_key("labrig-control")
                && started.elapsed() > Duration::from_secs(3)
                && let Some(l) = load.take()
            {
                load_thread = Some(l(stop_load.clone()));
            }
            // The measured window ends after `seconds`: stop the control loop (it writes its
            // stats), the launcher then stops the rig when its job is done.
            if started.elapsed().as_secs_f64() >= seconds
                && let Some(pid) = control_pid.take()
            {
                bar.set_message("stopping");
                stop_load.store(true, std::sync::atomic::Ordering::Relaxed);
                let _ = std::process::Command::new("kill").args(["-TERM", &pid.to_string()]).status();
            }
        }
        rig.await.context("the launcher task")?
    })?;
    bar.finish_and_clear();
    stop_load.store(true, std::sync::atomic::Ordering::Relaxed);
    let load_report = load_thread.map(|t| t.join().unwrap_or(serde_json::Value::Null));
    let interrupted = hooks.interruptible && shutdown.is_triggered();
    anyhow::ensure!(code == ExitCode::SUCCESS || interrupted, "the rig stopped with an error (see above)");
    let control: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(&stats).with_context(|| format!("the control loop's stats {}", stats.display()))?,
    )?;
    // The recordings.
    let mut episodes = Vec::new();
    for outcome in ["success", "failure"] {
        let Ok(dates) = std::fs::read_dir(root.join(outcome)) else { continue };
        for d in dates.flatten() {
            for e in std::fs::read_dir(d.path())?.flatten() {
                episodes.push(e.path());
            }
        }
    }
    let (mut bytes, mut dropped, mut flagged, mut steps, mut recorded_s) = (0u64, 0u64, 0u64, 0u64, 0.0);
    for e in &episodes {
        let i = labrig_episode::inspect::inspect(e).map_err(anyhow::Error::msg)?;
        bytes += std::fs::metadata(&i.path).map_or(0, |m| m.len());
        dropped += i.cameras.iter().map(|c| c.dropped).sum::<u64>();
        flagged += u64::from(!i.flags.is_empty());
        steps += i.steps;
        recorded_s += i.duration_s;
    }
    let run_s = control["seconds"].as_f64().unwrap_or(a.seconds);
    let cpu_pct: BTreeMap<String, f64> = cpu
        .iter()
        .map(|(n, [(c0, t0), (c1, t1)])| {
            (n.clone(), 100.0 * (c1 - c0) / t1.duration_since(*t0).as_secs_f64().max(1e-9))
        })
        .collect();
    let report = json!({
        "seconds": run_s,
        "cameras": format!("5 x {}x{} rgb8 -> JPEG q90", a.width, a.height),
        "ticks": control["ticks"],
        "tick_jitter_us": { "p50": control["jitter_us"][0], "p99": control["jitter_us"][1], "max": control["jitter_us"][2] },
        "missed_ticks": control["missed_ticks"],
        "held_ticks": control["held_ticks"],
        "steps_missing_frames": control["steps_missing_frames"],
        "steps_stale_frames": control["steps_stale_frames"],
        "camera_skew_us": { "p50": control["skew_us"][0], "p99": control["skew_us"][1], "max": control["skew_us"][2] },
        "episodes": control["episodes"].as_array().map_or(0, Vec::len),
        "successes": control["episodes"].as_array().map_or(0, |v| v.iter().filter(|e| e["outcome"] == "success").count()),
        "recorded_episodes": episodes.len(),
        "recorded_steps": steps,
        "recorded_seconds": recorded_s,
        "dropped_frames": dropped,
        "flagged_episodes": flagged,
        "mb_written": bytes as f64 / 1e6,
        "mb_per_s": bytes as f64 / 1e6 / run_s,
        "mb_per_recorded_s": bytes as f64 / 1e6 / recorded_s.max(1e-9),
        "cpu_percent": cpu_pct,
        "load": load_report,
        "interrupted": interrupted,
    });
    Ok(report)
}
