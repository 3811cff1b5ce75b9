//! `labrig-franka`: the FR3 arm node (safety layer + IK -> franka-rs over the FCI).

use clap::{Parser, Subcommand};
use labrig_franka::fci::FciArm;
use labrig_franka::node::{BackendKind, FrankaNodeConfig};
use labrig_franka::sim::SimArm;
use std::path::PathBuf;
use std::process::ExitCode;

#[derive(Debug, Parser)]
#[command(name = "labrig-franka", about = "The FR3 arm node: /arm/command -> safety layer -> FCI")]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Run the node: /arm/command in; /arm/state, /arm/target, /joint_states, /tf out;
    /// /arm/recover service.
    Run {
        /// Node config (TOML, see launch_configs/nodes/franka_fr3.toml); the flags below override it.
        #[arg(long)]
        config: Option<PathBuf>,
        /// fci: a real FR3 or franka-sim; sim: the sim bridge run with `--hardware-prefix /sim`.
        #[arg(long, value_enum)]
        backend: Option<BackendKind>,
        /// The FR3's FCI address (franka-sim: 127.0.0.1).
        #[arg(long)]
        robot_ip: Option<String>,
        /// Run without a realtime kernel (franka-sim, a development machine).
        #[arg(long)]
        no_realtime: bool,
        /// DDS domain id.
        #[arg(long, env = "ROS_DOMAIN_ID")]
        domain_id: Option<u16>,
        /// Keep trying to reach the FCI this long at start (a booting robot or simulator).
        #[arg(long, default_value_t = 30.0)]
        connect_timeout_s: f64,
    },
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    labrig_runtime::main_node("labrig-franka", |shutdown| async move {
        match cli.command {
            Command::Run { config, backend, robot_ip, no_realtime, domain_id, connect_timeout_s } => {
                let mut cfg: FrankaNodeConfig = match &config {
                    Some(p) => labrig_runtime::load_config(p)?,
                    None => FrankaNodeConfig::default(),
                };
                if let Some(b) = backend {
                    cfg.backend = b;
                }
                if let Some(ip) = robot_ip {
                    cfg.robot_ip = ip;
                }
                if no_realtime {
                    cfg.fci.realtime = false;
                }
                if let Some(d) = domain_id {
                    cfg.ros.domain_id = d;
                }
                cfg.validate().map_err(anyhow::Error::msg)?;
                anyhow::ensure!(
                    connect_timeout_s.is_finite() && (0.0..=86_400.0).contains(&connect_timeout_s),
                    "--connect-timeout-s is {connect_timeout_s}, must be 0..=86400"
                );
                if cfg.backend == BackendKind::Sim {
                    let prefix = cfg.sim_prefix.clone();
                    return labrig_franka::node::run(
                        cfg,
                        |ros, clock| Ok(Box::new(SimArm::new(ros, &prefix, clock.clone())?)),
                        shutdown,
                    )
                    .await;
                }
                let deadline =
                    std::time::Instant::now() + std::time::Duration::from_secs_f64(connect_timeout_s.max(0.0));
                let arm = loop {
                    let (ip, fci) = (cfg.robot_ip.clone(), cfg.fci.clone());
                    match tokio::task::spawn_blocking(move || FciArm::connect(&ip, fci)).await? {
                        Ok(arm) => break arm,
                        Err(e) if std::time::Instant::now() < deadline && !shutdown.is_triggered() => {
                            tracing::info!("waiting for the FCI at {}: {e}", cfg.robot_ip);
                            tokio::time::sleep(std::time::Duration::from_millis(250)).await;
                        }
                        Err(e) => anyhow::bail!("{e} (FCI at {})", cfg.robot_ip),
                    }
                };
                labrig_franka::node::run(cfg, |_, _| Ok(Box::new(arm)), shutdown).await
            }
        }
    })
}
