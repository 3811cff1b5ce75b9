//! Starting and supervising a rig: the nodes start as processes in dependency order, each
//! after those it names are up (their health topic seen); every node's health (up, the rate of
//! its topic) is reported every few seconds; a node that dies is restarted or the rig stopped
//! (as the config says); on Ctrl-C (or a deadline, or the caller's signal) everything stops in
//! reverse order: SIGTERM, then SIGKILL after 10 s.

use crate::config::{Devices, LaunchConfig, NodeSpec, OnFailure};
use labrig_msgs::dds_type_name;
use labrig_runtime::ros::{Ros, qos};
use labrig_runtime::{RosConfig, Shutdown};
use serde_json::json;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitCode};
use std::time::{Duration, Instant};

struct Running {
    spec: NodeSpec,
    child: Option<Child>,
    restarts: u32,
    count: u64,
    rate_hz: f64,
    up: bool,
}

fn spawn(spec: &NodeSpec, devices: &Devices, dir: &Path, domain: u16, out: Output) -> anyhow::Result<Child> {
    let exe = crate::programs::sibling_binary(&spec.program)?;
    let mut cmd = Command::new(&exe);
    // Quiet: the nodes log warnings and errors only (unless RUST_LOG says otherwise).
    if out == Output::Quiet && std::env::var_os("RUST_LOG").is_none() {
        cmd.env("RUST_LOG", "warn,rustdds=off,ros2_client=error,mujoco=warn");
    }
    cmd.args(&spec.args).envs(&spec.env);
    // The rig's camera frames in a shared-memory namespace of its own, from its domain (two
    // rigs on one machine are on two domains), unless the node's config or the caller names one.
    let ns = labrig_runtime::frames::NAMESPACE_ENV;
    if !spec.env.contains_key(ns) && labrig_runtime::frames::default_namespace().is_none() {
        cmd.env(ns, rig_namespace(domain));
    }
    // The rig's devices, written once in the launch config: the nodes take camera serials (and
    // the rest) from here instead of copies in their own configs.
    if *devices != Devices::default() {
        cmd.env(labrig_runtime::devices::DEVICES_ENV, devices.to_env());
    }
    if let Some(c) = &spec.config {
        cmd.arg("--config").arg(dir.join(c));
    }
    cmd.args(["--domain-id", &domain.to_string()]);
    stop_with_launcher(&mut cmd);
    cmd.spawn().map_err(|e| anyhow::anyhow!("node `{}`: cannot start {}: {e}", spec.name, exe.display()))
}

/// The shared-memory namespace of the camera frames of a rig on DDS domain `domain`, when the
/// caller names none (`LABRIG_FRAMES_NAMESPACE`): one per domain, so two rigs on one machine,
/// which need two domains, never mix their frames.
pub fn rig_namespace(domain: u16) -> String {
    format!("rig_d{domain}")
}

/// The namespace a process reading a rig's frames on `domain` uses: the caller's, or the one
/// the supervisor gives the rig's nodes ([`rig_namespace`]).
pub fn frames_namespace(domain: u16) -> String {
    labrig_runtime::frames::default_namespace().unwrap_or_else(|| rig_namespace(domain))
}

/// How long a starting rig listens for another rig on its domain when it is not alone there:
/// discovery on loopback takes ~0.2 s here (a participant's start to another's first message,
/// five tries); the margin is for a loaded machine.
const PROBE: Duration = Duration::from_secs(3);

/// The health topics of `cfg`'s nodes that already have a publisher on the domain `ros` is on:
/// another rig (or a node started by hand) is running there.
///
/// A participant takes the lowest free participant id of its domain on this machine (the
/// lowest free pair of its domain's ports), so id 0 means no other participant of the domain
/// runs here and there is nothing to wait for; otherwise it listens up to [`PROBE`].
async fn rig_already_there(ros: &Ros, cfg: &LaunchConfig) -> Vec<String> {
    if ros.participant_id() == 0 {
        return Vec::new();
    }
    let mut topics: Vec<&str> = cfg.nodes.iter().map(|n| n.health.as_str()).collect();
    topics.sort_unstable();
    topics.dedup();
    let until = Instant::now() + PROBE;
    loop {
        let busy: Vec<String> = topics.iter().filter(|t| ros.publisher_count(t) > 0).map(|t| (*t).to_owned()).collect();
        if !busy.is_empty() || Instant::now() >= until {
            return busy;
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
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
pub fn stop_with_launcher(cmd: &mut Command) {
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
    // One rig per domain: a second one would take the first's commands, steps and episodes.
    let busy = rig_already_there(&ros, &cfg).await;
    if !busy.is_empty() {
        anyhow::bail!(
            "DDS domain {domain} already has a rig running: {} {} a publisher there (another labrig rig, or a node started by hand). A second rig on that domain would mix with it; stop that one, or start this one on another domain with --domain-id",
            busy.join(", "),
            if busy.len() == 1 { "has" } else { "have" }
        );
    }
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
        running[i].child = Some(spawn(&spec, &cfg.rig.devices, &dir, domain, out)?);
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
                r.child = Some(spawn(&r.spec, &cfg.rig.devices, &dir, domain, out)?);
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
