//! `labrig launch <launch_config.toml>`: start and supervise a rig.
//!
//! A launch config names the rig's nodes (`[[node]]`: the labrig program, its arguments, an
//! optional node config file, the nodes it starts after, the topic that shows it is up, what
//! to do when it dies). The launcher validates the file (unknown keys, unknown programs or
//! dependencies, cycles, missing config files: each named), starts the nodes as processes in
//! dependency order — each one after those it names are up (their health topic seen) —
//! shows every node's health (up, the rate of its topic) every few seconds, restarts a node
//! that dies or stops the rig (as the config says), and on Ctrl-C (or `--seconds`) stops
//! everything in reverse order: SIGTERM, then SIGKILL after 10 s.

use anyhow::Context;
use clap::Args;
use labrig_msgs::dds_type_name;
use labrig_runtime::ros::{Ros, qos};
use labrig_runtime::{RosConfig, Shutdown};
use serde::Deserialize;
use serde_json::json;
use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitCode};
use std::time::{Duration, Instant};

/// The programs a launch config may start (built beside the `labrig` binary). Only programs
/// that exist: a config naming another one (a node still to come, a typo) is refused by name.
pub const PROGRAMS: [&str; 9] = [
    "labrig-sim",
    "labrig-franka",
    "labrig-gripper",
    "labrig-recorder",
    "labrig-control",
    "labrig-teleop",
    "labrig-policy",
    "labrig-cameras",
    "labrig-station",
];

#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum OnFailure {
    /// Start the node again (up to `max_restarts`), the rig keeps running.
    Restart,
    /// Stop the whole rig.
    #[default]
    Stop,
}

/// The real rig's devices (informational for the launcher; node configs use them).
#[derive(Debug, Clone, Deserialize, Default, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct Devices {
    pub robot_ip: Option<String>,
    pub gripper_port: Option<String>,
    pub quest_device: Option<String>,
    #[serde(default)]
    pub camera_serials: BTreeMap<String, String>,
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Rig {
    pub name: String,
    #[serde(default)]
    pub description: String,
    #[serde(default)]
    pub domain_id: u16,
    #[serde(default)]
    pub on_failure: OnFailure,
    #[serde(default)]
    pub devices: Devices,
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct NodeSpec {
    pub name: String,
    pub program: String,
    #[serde(default)]
    pub args: Vec<String>,
    /// A node config file, relative to the launch config; passed as `--config <path>`.
    pub config: Option<PathBuf>,
    /// Nodes that must be up before this one starts.
    #[serde(default)]
    pub after: Vec<String>,
    /// The topic whose messages show the node is up.
    pub health: String,
    pub on_failure: Option<OnFailure>,
    #[serde(default = "three")]
    pub max_restarts: u32,
    /// The node is the rig's job (a control loop collecting N episodes): when it exits
    /// with status 0 the rig stops, successfully.
    #[serde(default)]
    pub completes: bool,
    /// Environment variables for the node's process (e.g. `LABRIG_FRAMES_NAMESPACE` for two
    /// rigs on one machine).
    #[serde(default)]
    pub env: BTreeMap<String, String>,
}

fn three() -> u32 {
    3
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LaunchConfig {
    pub rig: Rig,
    #[serde(rename = "node")]
    pub nodes: Vec<NodeSpec>,
}

impl LaunchConfig {
    /// Loads and validates `path`; returns the config and the start order.
    pub fn load(path: &Path) -> anyhow::Result<(LaunchConfig, Vec<usize>)> {
        let cfg: LaunchConfig = labrig_runtime::load_config(path)?;
        let order = cfg
            .validate(path.parent().unwrap_or(Path::new(".")))
            .with_context(|| format!("invalid launch config {}", path.display()))?;
        Ok((cfg, order))
    }

    /// Parses and validates a config's text (`origin` names it in errors; config files are
    /// looked up beside it).
    pub fn parse(text: &str, origin: &Path) -> anyhow::Result<(LaunchConfig, Vec<usize>)> {
        let cfg: LaunchConfig = labrig_runtime::config::parse_config(text, origin)?;
        let order = cfg
            .validate(origin.parent().unwrap_or(Path::new(".")))
            .with_context(|| format!("invalid launch config {}", origin.display()))?;
        Ok((cfg, order))
    }

    /// The node called `name`.
    pub fn node_mut(&mut self, name: &str) -> Option<&mut NodeSpec> {
        self.nodes.iter_mut().find(|n| n.name == name)
    }

    /// Checks what serde cannot; returns the nodes' start order (dependencies first).
    pub fn validate(&self, dir: &Path) -> anyhow::Result<Vec<usize>> {
        let mut names = BTreeSet::new();
        anyhow::ensure!(!self.nodes.is_empty(), "the rig has no [[node]]");
        anyhow::ensure!(self.rig.domain_id <= RosConfig::MAX_DOMAIN_ID, "rig.domain_id must be 0..=232");
        for n in &self.nodes {
            anyhow::ensure!(names.insert(n.name.as_str()), "node `{}` is defined twice", n.name);
            anyhow::ensure!(
                PROGRAMS.contains(&n.program.as_str()),
                "node `{}`: unknown program `{}` (one of {})",
                n.name,
                n.program,
                PROGRAMS.join(", ")
            );
            anyhow::ensure!(
                n.health.starts_with('/'),
                "node `{}`: health topic `{}` must start with /",
                n.name,
                n.health
            );
            if let Some(c) = &n.config {
                let p = dir.join(c);
                anyhow::ensure!(p.is_file(), "node `{}`: config file {} does not exist", n.name, p.display());
            }
        }
        for n in &self.nodes {
            for a in &n.after {
                anyhow::ensure!(
                    names.contains(a.as_str()),
                    "node `{}` starts after `{a}`, which is not a node",
                    n.name
                );
            }
        }
        // Kahn's order; what is left is a cycle.
        let mut order = Vec::new();
        let mut done: BTreeSet<&str> = BTreeSet::new();
        while order.len() < self.nodes.len() {
            let ready: Vec<usize> = (0..self.nodes.len())
                .filter(|&i| !done.contains(self.nodes[i].name.as_str()))
                .filter(|&i| self.nodes[i].after.iter().all(|a| done.contains(a.as_str())))
                .collect();
            if ready.is_empty() {
                let left: Vec<&str> =
                    self.nodes.iter().map(|n| n.name.as_str()).filter(|n| !done.contains(n)).collect();
                anyhow::bail!("the nodes {left:?} wait for each other (a dependency cycle)");
            }
            for i in ready {
                done.insert(self.nodes[i].name.as_str());
                order.push(i);
            }
        }
        Ok(order)
    }
}

#[derive(Debug, Args)]
pub struct LaunchArgs {
    /// The launch config (launch_configs/*.toml).
    config: PathBuf,
    /// Validate the file, print the start order, start nothing.
    #[arg(long)]
    check: bool,
    /// Stop the rig after this many seconds (default: run until Ctrl-C).
    #[arg(long)]
    seconds: Option<f64>,
    /// Override the rig's DDS domain.
    #[arg(long)]
    domain_id: Option<u16>,
    /// Status as JSON lines.
    #[arg(long)]
    json: bool,
}

struct Running {
    spec: NodeSpec,
    child: Option<Child>,
    restarts: u32,
    count: u64,
    rate_hz: f64,
    up: bool,
}

fn spawn(spec: &NodeSpec, dir: &Path, domain: u16, out: Output) -> anyhow::Result<Child> {
    let exe = crate::programs::sibling_binary(&spec.program)?;
    let mut cmd = Command::new(&exe);
    // Quiet: the nodes log warnings and errors only (unless RUST_LOG says otherwise).
    if out == Output::Quiet && std::env::var_os("RUST_LOG").is_none() {
        cmd.env("RUST_LOG", "warn,rustdds=off,ros2_client=error,mujoco=warn");
    }
    cmd.args(&spec.args).envs(&spec.env);
    if let Some(c) = &spec.config {
        cmd.arg("--config").arg(dir.join(c));
    }
    cmd.args(["--domain-id", &domain.to_string()]);
    stop_with_launcher(&mut cmd);
    cmd.spawn().map_err(|e| anyhow::anyhow!("node `{}`: cannot start {}: {e}", spec.name, exe.display()))
}

/// A node gets SIGTERM when the launcher dies, however it dies (SIGKILL, a crash): no node
/// outlives the rig that started it, and each ends as it would on Ctrl-C (the recorder files
/// an open episode). Linux's parent-death signal fires when the *thread* that forked the child
/// ends: `labrig launch` forks every node, restarts included, from its main thread (the
/// supervisor runs in `block_on`); the demo, rollouts, the calibration capture and the benches
/// supervise from a tokio worker thread, which lives until their runtime shuts down, after the
/// rig is stopped; `labrig experiment` forks each stage from the thread that waits for it.
/// Nothing here may fork nodes from a thread that ends earlier (a `spawn_blocking` or
/// `block_in_place` thread).
pub(crate) fn stop_with_launcher(cmd: &mut Command) {
    use std::os::unix::process::CommandExt;
    let launcher = nix::unistd::getpid();
    // SAFETY: the closure runs in the child between fork and exec, and calls only prctl(2),
    // getppid(2) and _exit(2), which are async-signal-safe; it allocates nothing.
    #[allow(unsafe_code)]
    unsafe {
        cmd.pre_exec(move || {
            nix::sys::prctl::set_pdeathsig(nix::sys::signal::Signal::SIGTERM)?;
            // The launcher died before the prctl: the signal will never come.
            if nix::unistd::getppid() != launcher {
                nix::libc::_exit(1);
            }
            Ok(())
        });
    }
}

fn stop(r: &mut Running) {
    let Some(mut child) = r.child.take() else { return };
    let _ = Command::new("kill").args(["-TERM", &child.id().to_string()]).status();
    let deadline = Instant::now() + Duration::from_secs(10);
    while Instant::now() < deadline {
        if let Ok(Some(_)) = child.try_wait() {
            return;
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    tracing::warn!("node `{}` did not stop in 10 s: killed", r.spec.name);
    let _ = child.kill();
    let _ = child.wait();
}

pub fn run(a: LaunchArgs) -> anyhow::Result<ExitCode> {
    let (cfg, order) = LaunchConfig::load(&a.config)?;
    let dir = a.config.parent().unwrap_or(Path::new(".")).to_owned();
    let names: Vec<&str> = order.iter().map(|&i| cfg.nodes[i].name.as_str()).collect();
    if a.check {
        if a.json {
            println!("{}", json!({ "rig": cfg.rig.name, "valid": true, "start_order": names }));
        } else {
            println!("{}: valid; start order: {}", a.config.display(), names.join(" -> "));
        }
        return Ok(ExitCode::SUCCESS);
    }
    let domain = a.domain_id.unwrap_or(cfg.rig.domain_id);
    let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build()?;
    let out = if a.json { Output::Json } else { Output::Text };
    rt.block_on(supervise(cfg, order, dir, domain, a.seconds, out))
}

/// How the launcher reports.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Output {
    Text,
    Json,
    /// Failures only (a caller shows its own progress).
    Quiet,
}

/// Starts and supervises the rig until Ctrl-C, `seconds`, a failure, or its `completes`
/// node is done.
pub async fn supervise(
    cfg: LaunchConfig,
    order: Vec<usize>,
    dir: PathBuf,
    domain: u16,
    seconds: Option<f64>,
    out: Output,
) -> anyhow::Result<ExitCode> {
    let shutdown = Shutdown::new();
    shutdown.trigger_on_signals()?;
    supervise_until(cfg, order, dir, domain, seconds, out, shutdown).await
}

/// [`supervise`], also stopping (as on Ctrl-C) when `shutdown` is triggered by the caller.
pub async fn supervise_until(
    cfg: LaunchConfig,
    order: Vec<usize>,
    dir: PathBuf,
    domain: u16,
    seconds: Option<f64>,
    out: Output,
    shutdown: Shutdown,
) -> anyhow::Result<ExitCode> {
    let ros_cfg = RosConfig { domain_id: domain, ..RosConfig::default() };
    let mut ros = Ros::new(&ros_cfg, "labrig_launch")?;
    let mut running: Vec<Running> = cfg
        .nodes
        .iter()
        .map(|s| Running { spec: s.clone(), child: None, restarts: 0, count: 0, rate_hz: 0.0, up: false })
        .collect();
    let started_at = Instant::now();
    let report = |v: serde_json::Value, text: String| match out {
        Output::Json => println!("{v}"),
        Output::Text => println!("{text}"),
        Output::Quiet if v.get("error").is_some() => eprintln!("{text}"),
        Output::Quiet => {}
    };
    let mut failure: Option<String> = None;
    let mut completed: Option<String> = None;
    // Start in order; each node once the nodes it starts after are up.
    let mut health_subs = Vec::new();
    for &i in &order {
        if shutdown.is_triggered() {
            break;
        }
        let spec = running[i].spec.clone();
        running[i].child = Some(spawn(&spec, &dir, domain, out)?);
        report(json!({ "event": "started", "node": spec.name }), format!("started {} ({})", spec.name, spec.program));
        // Up when its health topic appears; a node that exits first has failed to start.
        let waited = Instant::now();
        let topic = loop {
            if shutdown.is_triggered() {
                break None;
            }
            if let Some(t) = ros.wait_for_topic(&spec.health, Duration::from_millis(200)).await {
                break Some(t);
            }
            if let Some(Ok(Some(status))) = running[i].child.as_mut().map(|c| c.try_wait()) {
                running[i].child = None;
                failure = Some(format!("node `{}` exited while starting ({status})", spec.name));
                break None;
            }
            if waited.elapsed() > Duration::from_secs(120) {
                failure =
                    Some(format!("node `{}`: its health topic {} did not appear within 120 s", spec.name, spec.health));
                break None;
            }
        };
        let Some(topic) = topic else { break };
        let sub = ros.raw_subscription(&spec.health, &dds_type_name(&topic.type_name), qos::reliable(100))?;
        health_subs.push((i, sub));
        running[i].up = true;
        report(
            json!({ "event": "up", "node": spec.name, "topic": spec.health }),
            format!("{} is up ({})", spec.name, spec.health),
        );
    }
    let deadline = seconds.map(|s| Instant::now() + Duration::from_secs_f64(s));
    let mut window = Instant::now();
    while failure.is_none()
        && completed.is_none()
        && !shutdown.is_triggered()
        && deadline.is_none_or(|d| Instant::now() < d)
    {
        tokio::time::sleep(Duration::from_millis(100)).await;
        for (i, sub) in &health_subs {
            while let Ok(Some(_)) = sub.try_take() {
                running[*i].count += 1;
            }
        }
        // A node that died: restart it or stop the rig.
        for r in running.iter_mut() {
            let Some(child) = &mut r.child else { continue };
            let Ok(Some(status)) = child.try_wait() else { continue };
            r.child = None;
            r.up = false;
            if r.spec.completes && status.success() {
                completed = Some(r.spec.name.clone());
                break;
            }
            let policy = r.spec.on_failure.unwrap_or(cfg.rig.on_failure);
            let what = format!("node `{}` exited ({status})", r.spec.name);
            if policy == OnFailure::Restart && r.restarts < r.spec.max_restarts {
                r.restarts += 1;
                report(
                    json!({ "event": "restart", "node": r.spec.name, "status": status.to_string(), "restarts": r.restarts }),
                    format!("{what}: restarting ({}/{})", r.restarts, r.spec.max_restarts),
                );
                r.child = Some(spawn(&r.spec, &dir, domain, out)?);
                r.up = true;
            } else {
                failure = Some(format!("{what}: stopping the rig (on_failure = {policy:?}, {} restarts)", r.restarts));
            }
        }
        let elapsed = window.elapsed().as_secs_f64();
        if elapsed >= 2.0 {
            window = Instant::now();
            for r in running.iter_mut() {
                r.rate_hz = r.count as f64 / elapsed;
                r.count = 0;
            }
            let nodes: Vec<_> = running
                .iter()
                .map(|r| json!({ "node": r.spec.name, "up": r.child.is_some() && r.up, "topic": r.spec.health, "rate_hz": r.rate_hz, "restarts": r.restarts }))
                .collect();
            let text = running
                .iter()
                .map(|r| {
                    format!(
                        "{} {} {:.1} Hz",
                        r.spec.name,
                        if r.child.is_some() && r.up { "up" } else { "DOWN" },
                        r.rate_hz
                    )
                })
                .collect::<Vec<_>>()
                .join(" | ");
            report(json!({ "event": "health", "seconds": started_at.elapsed().as_secs_f64(), "nodes": nodes }), text);
        }
    }
    // Stop in reverse start order.
    for &i in order.iter().rev() {
        stop(&mut running[i]);
    }
    drop(health_subs);
    match failure {
        Some(f) => {
            report(json!({ "event": "stopped", "error": f }), format!("rig stopped: {f}"));
            Ok(ExitCode::FAILURE)
        }
        None => {
            let why = completed.map(|n| format!("node `{n}` completed the rig's job"));
            report(
                json!({ "event": "stopped", "completed": why.is_some() }),
                format!("rig stopped{}", why.map(|w| format!(": {w}")).unwrap_or_default()),
            );
            Ok(ExitCode::SUCCESS)
        }
    }
}
