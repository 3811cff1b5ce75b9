//! `labrig-teleop`: the Quest teleoperation node.

use clap::{Parser, Subcommand};
use labrig_teleop::input::InputKind;
use labrig_teleop::node::TeleopConfig;
use std::path::PathBuf;
use std::process::ExitCode;

#[derive(Debug, Parser)]
#[command(
    name = "labrig-teleop",
    about = "Quest controller (logcat) -> DROID's VRPolicy -> /teleop/action, /teleop/state, /rig/request"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Run the node (the flags override the config file).
    Run(RunArgs),
}

#[derive(Debug, clap::Args)]
struct RunArgs {
    /// Node config (TOML).
    #[arg(long)]
    config: Option<PathBuf>,
    /// Where lines come from: the headset over adb, or a recorded logcat file.
    #[arg(long, value_enum)]
    input: Option<InputKind>,
    /// Playback: the recorded logcat file (implies --input playback).
    #[arg(long)]
    file: Option<PathBuf>,
    /// Playback time scale.
    #[arg(long)]
    speed: Option<f64>,
    /// Playback: start again at the end.
    #[arg(long)]
    repeat: bool,
    /// adb: the headset's serial or ip:port.
    #[arg(long)]
    device: Option<String>,
    /// The controller that drives the arm: right or left.
    #[arg(long)]
    hand: Option<String>,
    /// Exit a second after a playback ends.
    #[arg(long)]
    exit_at_end: bool,
    /// Print the run's figures (lines, actions, latency) as JSON on exit.
    #[arg(long)]
    json: bool,
    /// Also write them to this file.
    #[arg(long)]
    stats_out: Option<PathBuf>,
    /// DDS domain id.
    #[arg(long, env = "ROS_DOMAIN_ID")]
    domain_id: Option<u16>,
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    let Command::Run(a) = cli.command;
    labrig_runtime::main_node("labrig-teleop", |shutdown| async move {
        let mut cfg: TeleopConfig = match &a.config {
            Some(p) => {
                let mut c: TeleopConfig = labrig_runtime::load_config(p)?;
                // A trace named in a config file is relative to that file.
                if let (Some(f), Some(dir)) = (c.input.file.as_mut(), p.parent())
                    && f.is_relative()
                {
                    *f = dir.join(&*f);
                }
                c
            }
            None => TeleopConfig::default(),
        };
        if let Some(k) = a.input {
            cfg.input.kind = k;
        }
        if let Some(f) = a.file {
            cfg.input.kind = InputKind::Playback;
            cfg.input.file = Some(f);
        }
        if a.repeat {
            cfg.input.repeat = true;
        }
        if let Some(s) = a.speed {
            cfg.input.speed = s;
        }
        if let Some(d) = a.device {
            cfg.input.device = d;
        }
        if let Some(h) = a.hand {
            cfg.policy.hand = h;
        }
        if let Some(d) = a.domain_id {
            cfg.ros.domain_id = d;
        }
        let stats = labrig_teleop::node::run(cfg, shutdown, a.exit_at_end).await?;
        let text = serde_json::to_string(&stats)?;
        if a.json {
            println!("{text}");
        }
        if let Some(p) = a.stats_out {
            std::fs::write(&p, text).map_err(|e| anyhow::anyhow!("{}: {e}", p.display()))?;
        }
        Ok(())
    })
}
