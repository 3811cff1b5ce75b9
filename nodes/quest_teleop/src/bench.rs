//! `labrig bench teleop` (`labrig-teleop bench`): the Quest teleop node's latency, logcat line in -> action out.
//! Starts `labrig-teleop run` playing a recorded controller trace (the committed
//! square.logcat by default) on a private DDS domain, plays the arm's `/arm/state` to it
//! at 50 Hz from this process, and measures:
//! - in the node: the line read from the input -> its action published (the node's figures);
//! - across DDS: the reading's time (the action's stamp) -> the action received here.

use clap::Args;
use labrig_msgs::Nanos;
use labrig_msgs::rig::RobotState;
use labrig_msgs::topics;
use labrig_runtime::ros::Ros;
use serde_json::json;
use std::path::PathBuf;
use std::process::{Command, ExitCode, Stdio};
use std::time::Duration;

#[derive(Debug, Args)]
pub struct TeleopArgs {
    /// The recorded logcat trace to play (default: the committed square trace).
    #[arg(long)]
    trace: Option<PathBuf>,
    /// Playback speed (2 = twice the headset's rate).
    #[arg(long, default_value_t = 1.0)]
    speed: f64,
    /// DDS domain for the bench's node.
    #[arg(long, default_value_t = 232)]
    domain_id: u16,
    #[arg(long)]
    json: bool,
}

/// A file deleted on drop.
struct Removed(PathBuf);
impl Drop for Removed {
    fn drop(&mut self) {
        let _ = std::fs::remove_file(&self.0);
    }
}

/// The default trace (tests/fixtures/square.logcat), carried in the binary: one built in
/// another clone of the repository (a shared target directory) finds no path of its own.
const SQUARE_TRACE: &str = include_str!("../tests/fixtures/square.logcat");

pub fn run(a: TeleopArgs) -> anyhow::Result<ExitCode> {
    // The default trace goes to a temporary file for the node's `--file` (deleted at the end).
    let default_trace = match &a.trace {
        Some(_) => None,
        None => {
            let p = std::env::temp_dir().join(format!("labrig-bench-teleop-{}.logcat", std::process::id()));
            std::fs::write(&p, SQUARE_TRACE)?;
            Some(Removed(p))
        }
    };
    let trace: PathBuf = match (&a.trace, &default_trace) {
        (Some(t), _) => t.clone(),
        (None, Some(p)) => p.0.clone(),
        (None, None) => unreachable!("a default trace is written when none is given"),
    };
    anyhow::ensure!(trace.is_file(), "{}: no such trace", trace.display());
    let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build()?;
    let (node, received) = rt.block_on(async {
        let cfg = labrig_runtime::RosConfig { domain_id: a.domain_id, ..Default::default() };
        let mut ros = Ros::new(&cfg, "labrig_bench_teleop")?;
        let state = ros.publisher_on(&topics::ARM_STATE, 100)?;
        let actions = ros.subscription_on(&topics::TELEOP_ACTION, 1000)?;
        let child = Command::new(std::env::current_exe()?)
            .args(["run", "--json", "--exit-at-end", "--speed", &a.speed.to_string()])
            .args(["--domain-id", &a.domain_id.to_string(), "--file"])
            .arg(&trace)
            .stdout(Stdio::piped())
            .stderr(Stdio::null())
            .spawn()?;
        let waiter = tokio::task::spawn_blocking(move || child.wait_with_output());
        let mut received = Vec::new();
        let home =
            RobotState { cartesian_position: [0.5, 0.0, 0.4, std::f64::consts::PI, 0.0, 0.0], ..RobotState::default() };
        let mut next_state = tokio::time::Instant::now();
        while !waiter.is_finished() {
            if tokio::time::Instant::now() >= next_state {
                state.publish(home.clone())?;
                next_state += Duration::from_millis(20);
            }
            while let Some(m) = actions.try_take()? {
                let now = labrig_runtime::Clock::Wall.now().0;
                received.push((now - Nanos::from(m.msg.header.stamp).0) as f64 / 1e3);
            }
            tokio::time::sleep(Duration::from_micros(200)).await;
        }
        let out = waiter.await??;
        anyhow::ensure!(out.status.success(), "labrig-teleop failed ({})", out.status);
        let node: serde_json::Value = serde_json::from_slice(&out.stdout)?;
        anyhow::Ok((node, received))
    })?;
    let report = json!({
        "trace": trace,
        "readings": node["lines"]["readings"],
        "actions": node["actions"],
        "node_line_to_action_published": {
            "p50_us": node["latency_us_p50"], "p99_us": node["latency_us_p99"],
            "max_us": node["latency_us_max"], "n": node["latency_n"],
        },
        "reading_to_action_received": labrig_runtime::bench::summary(received, "us"),
    });
    if a.json {
        println!("{report}");
    } else {
        let line = |name: &str, v: &serde_json::Value| {
            println!(
                "{name:<44} p50 {:>7.0} us  p99 {:>7.0} us  max {:>7.0} us  (n = {})",
                v["p50_us"].as_f64().unwrap_or(f64::NAN),
                v["p99_us"].as_f64().unwrap_or(f64::NAN),
                v["max_us"].as_f64().unwrap_or(f64::NAN),
                v["n"]
            )
        };
        println!(
            "teleop node: {} readings played from {} at {}x, {} actions",
            report["readings"],
            trace.display(),
            a.speed,
            report["actions"]
        );
        line("in the node: line read -> action published", &report["node_line_to_action_published"]);
        line("reading -> action received (one DDS hop)", &report["reading_to_action_received"]);
    }
    Ok(ExitCode::SUCCESS)
}
