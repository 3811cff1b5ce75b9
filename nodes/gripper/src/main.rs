//! `labrig-gripper`: the Robotiq 2F-85 node, and an emulated 2F-85 to try it without one.

use clap::{Parser, Subcommand};
use labrig_gripper::node::{Backend, GripperNodeConfig};
use labrig_gripper::{Emulated2F85, EmulatorConfig};
use std::path::PathBuf;
use std::process::ExitCode;

#[derive(Debug, Parser)]
#[command(name = "labrig-gripper", about = "The Robotiq 2F-85 gripper node (Modbus RTU)")]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Run the node: /gripper/command in, /gripper/state out, /gripper/activate service.
    Run {
        /// Node config (TOML); the flags below override it.
        #[arg(long)]
        config: Option<PathBuf>,
        #[arg(long, value_enum)]
        backend: Option<Backend>,
        /// Serial device of the 2F-85.
        #[arg(long)]
        port: Option<String>,
        /// DDS domain id.
        #[arg(long, env = "ROS_DOMAIN_ID")]
        domain_id: Option<u16>,
    },
    /// Serve an emulated 2F-85 on a new pseudo-terminal, print its path, run until Ctrl-C.
    Emulate {
        /// An object between the fingers: closing stops at this position (0..255 counts).
        #[arg(long)]
        object_at: Option<u8>,
    },
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    labrig_runtime::main_node("labrig-gripper", |shutdown| async move {
        match cli.command {
            Command::Run { config, backend, port, domain_id } => {
                let mut cfg: GripperNodeConfig = match &config {
                    Some(p) => labrig_runtime::load_config(p)?,
                    None => GripperNodeConfig::default(),
                };
                if let Some(b) = backend {
                    cfg.backend = b;
                }
                if let Some(p) = port {
                    cfg.port = p;
                }
                if let Some(d) = domain_id {
                    cfg.ros.domain_id = d;
                }
                labrig_gripper::node::run(cfg, shutdown).await
            }
            Command::Emulate { object_at } => {
                let emu = Emulated2F85::new(EmulatorConfig::default());
                emu.place_object(object_at);
                let pty = emu.serve_on_pty()?;
                println!("{}", pty.path());
                shutdown.wait().await;
                Ok(())
            }
        }
    })
}
