//! `labrig bench franka`: command-to-backend latency of the franka node against franka-sim.
//! Starts franka-sim (on 127.0.0.1) and `labrig-franka run` as processes, sends joint
//! position commands at 20 Hz, and measures per command:
//! - in the node: `/arm/command` received -> target handed to franka-rs's FCI loop (the
//!   node's `prev_controller_latency_ms` in `/arm/state`, one value per command);
//! - round trip: this process publishes the command -> receives the node's `/arm/target`
//!   echo of it (two DDS hops on loopback + the node's path), polled every 0.5 ms.

use clap::Args;
use indicatif::ProgressBar;
use labrig_msgs::Nanos;
use labrig_msgs::rig::{ArmCommand, ArmCommandMode};
use labrig_msgs::topics;
use labrig_runtime::ros::Ros;
use serde_json::json;
use std::collections::HashMap;
use std::path::PathBuf;
use std::process::{Child, Command, ExitCode, Stdio};
use std::time::{Duration, Instant};

#[derive(Debug, Args)]
pub struct FrankaArgs {
    /// Commands to send (20 Hz).
    #[arg(long, default_value_t = 400)]
    commands: usize,
    /// franka-sim's TCP port on 127.0.0.1.
    #[arg(long, default_value_t = 21337)]
    port: u16,
    /// DDS domain for the bench's node.
    #[arg(long, default_value_t = 231)]
    domain_id: u16,
    #[arg(long)]
    json: bool,
}

/// scripts/franka_sim_loopback.py, carried in the binary and run with `python -c`: a binary
/// built in another clone of the repository (a shared target directory) must not run that
/// clone's copy, or none.
const FRANKA_SIM_LOOPBACK: &str = include_str!("../../../scripts/franka_sim_loopback.py");

/// Kills the child on drop.
struct Killed(Child);
impl Drop for Killed {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

fn cache() -> PathBuf {
    labrig_msgs::cache_dir().unwrap_or_else(|| PathBuf::from(".cache/labrig"))
}

fn now() -> Nanos {
    Nanos(std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).unwrap_or_default().as_nanos() as i64)
}

pub fn run(a: FrankaArgs) -> anyhow::Result<ExitCode> {
    anyhow::ensure!(a.commands >= 20, "--commands must be at least 20");
    let python = std::env::var_os("LABRIG_FRANKA_SIM_PYTHON")
        .map(PathBuf::from)
        .unwrap_or_else(|| cache().join("venv-franka-sim/bin/python"));
    let mjcf = std::env::var_os("FR3_MJCF").map(PathBuf::from).unwrap_or_else(|| cache().join("franka-sim/fr3.xml"));
    anyhow::ensure!(python.exists(), "franka-sim is not installed ({}): run scripts/setup.sh", python.display());
    let _sim = Killed(
        Command::new(&python)
            .args(["-c", FRANKA_SIM_LOOPBACK])
            .args(["--no-gripper", "--port", &a.port.to_string()])
            .env("FR3_MJCF", &mjcf)
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .map_err(|e| anyhow::anyhow!("cannot start franka-sim ({}): {e}", python.display()))?,
    );
    let _node = Killed(
        Command::new(std::env::current_exe()?)
            .args(["run", "--robot-ip", &format!("127.0.0.1:{}", a.port), "--no-realtime"])
            .args(["--domain-id", &a.domain_id.to_string()])
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()?,
    );
    let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build()?;
    let (internal, round_trip, lost) = rt.block_on(async {
        let cfg = labrig_runtime::RosConfig { domain_id: a.domain_id, ..Default::default() };
        let mut ros = Ros::new(&cfg, "labrig_bench_franka")?;
        let cmd = ros.publisher_on(&topics::ARM_COMMAND, 100)?;
        let targets = ros.subscription_on(&topics::ARM_TARGET, 1000)?;
        let states = ros.subscription_on(&topics::ARM_STATE, 1000)?;
        anyhow::ensure!(
            ros.wait_for_subscribers(topics::ARM_COMMAND.name, 1, Duration::from_secs(90)).await,
            "the franka node did not come up within 90 s"
        );
        let start = loop {
            if let Some(s) = states.try_take()? {
                break s.msg.joint_positions;
            }
            tokio::time::sleep(Duration::from_millis(10)).await;
        };
        let bar = ProgressBar::new(a.commands as u64);
        let mut sent: HashMap<i64, Instant> = HashMap::new();
        let (mut internal, mut round_trip) = (Vec::new(), Vec::new());
        let mut next = tokio::time::Instant::now();
        let mut last_latency = f64::NAN;
        let mut collect = |sent: &HashMap<i64, Instant>, internal: &mut Vec<f64>, round_trip: &mut Vec<f64>| {
            while let Ok(Some(t)) = targets.try_take() {
                if let Some(at) = sent.get(&Nanos::from(t.msg.header.stamp).0) {
                    round_trip.push(at.elapsed().as_secs_f64() * 1e3);
                }
            }
            // States repeat the last command's latency until the next command (50 Hz vs 20 Hz).
            while let Ok(Some(s)) = states.try_take() {
                let ms = s.msg.prev_controller_latency_ms;
                if ms > 0.0 && ms != last_latency {
                    internal.push(ms);
                    last_latency = ms;
                }
            }
        };
        for k in 0..a.commands {
            let mut q = start;
            q[0] += 0.1 * (k as f64 * 0.05 * std::f64::consts::TAU * 0.5).sin();
            let mut c = ArmCommand {
                mode: ArmCommandMode::JointPosition as u8,
                joint_position: q,
                seq: k as u64,
                ..Default::default()
            };
            let stamp = now();
            c.header.stamp = stamp.into();
            sent.insert(stamp.0, Instant::now());
            cmd.publish(c)?;
            next += Duration::from_millis(50);
            // Poll for the echo every 0.5 ms until the next command is due.
            while tokio::time::Instant::now() < next {
                collect(&sent, &mut internal, &mut round_trip);
                tokio::time::sleep(Duration::from_micros(500)).await;
            }
            bar.inc(1);
        }
        tokio::time::sleep(Duration::from_millis(200)).await;
        collect(&sent, &mut internal, &mut round_trip);
        bar.finish_and_clear();
        let lost = a.commands - round_trip.len();
        anyhow::Ok((internal, round_trip, lost))
    })?;
    let report = json!({
        "commands": a.commands,
        "echoed": round_trip.len(),
        "node_command_to_backend": labrig_runtime::bench::summary(internal, "ms"),
        "round_trip_publish_to_echo": labrig_runtime::bench::summary(round_trip, "ms"),
    });
    if a.json {
        println!("{report}");
    } else {
        let line = |name: &str, v: &serde_json::Value| {
            println!(
                "{name:<42} p50 {:>7.3} ms  p99 {:>7.3} ms  max {:>7.3} ms  (n = {})",
                v["p50_ms"].as_f64().unwrap_or(f64::NAN),
                v["p99_ms"].as_f64().unwrap_or(f64::NAN),
                v["max_ms"].as_f64().unwrap_or(f64::NAN),
                v["n"]
            )
        };
        println!("franka node vs franka-sim: {} joint commands at 20 Hz, {} echoed", a.commands, report["echoed"]);
        line("in the node: received -> FCI loop target", &report["node_command_to_backend"]);
        line("round trip: publish -> /arm/target echo", &report["round_trip_publish_to_echo"]);
    }
    Ok(if lost == 0 { ExitCode::SUCCESS } else { ExitCode::from(1) })
}
