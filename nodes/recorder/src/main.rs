//! `labrig-recorder`: the episode recorder node.

use clap::{Parser, Subcommand};
use labrig_recorder::node::RecorderConfig;
use std::path::PathBuf;
use std::process::ExitCode;

#[derive(Debug, Parser)]
#[command(name = "labrig-recorder", about = "Records the rig's episodes as DROID-format MCAP")]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Run the node: episodes start and end on /rig/episode events.
    Run {
        /// Node config (TOML); the flags below override it.
        #[arg(long)]
        config: Option<PathBuf>,
        /// Where episodes go.
        #[arg(long)]
        root: Option<PathBuf>,
        /// DDS domain id.
        #[arg(long, env = "ROS_DOMAIN_ID")]
        domain_id: Option<u16>,
    },
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    labrig_runtime::main_node("labrig-recorder", |shutdown| async move {
        match cli.command {
            Command::Run { config, root, domain_id } => {
                let mut cfg: RecorderConfig = match &config {
                    Some(p) => labrig_runtime::load_config(p)?,
                    None => RecorderConfig::default(),
                };
                if let Some(r) = root {
                    cfg.root = r;
                }
                if let Some(d) = domain_id {
                    cfg.ros.domain_id = d;
                }
                labrig_recorder::node::run(cfg, shutdown).await
            }
        }
    })
}
