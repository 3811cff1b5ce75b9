//! `labrig-control`: the rig loop node.

use clap::{Parser, Subcommand};
use labrig_control::node::{ClockKind, ControlConfig, SourceKind};
use std::path::PathBuf;
use std::process::ExitCode;

#[derive(Debug, Parser)]
#[command(
    name = "labrig-control",
    about = "The 20 Hz rig loop: observations, actions through the safety layer, Step records, episodes"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Run the loop (the flags override the config file).
    Run(RunArgs),
}

#[derive(Debug, clap::Args)]
struct RunArgs {
    /// Node config (TOML).
    #[arg(long)]
    config: Option<PathBuf>,
    /// The action source.
    #[arg(long, value_enum)]
    source: Option<SourceKind>,
    /// The loop's clock: `sim` (the bridge's time; lockstep-safe) or `wall` (the real rig).
    #[arg(long, value_enum)]
    clock: Option<ClockKind>,
    /// Episodes to run, then exit (0: until stopped).
    #[arg(long)]
    episodes: Option<u64>,
    /// The first scene seed (`/sim/reset`); the next episodes take the following seeds.
    #[arg(long)]
    first_seed: Option<u64>,
    /// Do not ask the sim for a new scene per episode.
    #[arg(long)]
    no_reseed: bool,
    /// Episodes only from /rig/request (no automatic start).
    #[arg(long)]
    manual: bool,
    /// Step budget per episode.
    #[arg(long)]
    max_steps: Option<u64>,
    /// Print the run's summary as JSON on exit.
    #[arg(long)]
    json: bool,
    /// Also write the summary (JSON) to this file on exit.
    #[arg(long)]
    stats_out: Option<PathBuf>,
    /// DDS domain id.
    #[arg(long, env = "ROS_DOMAIN_ID")]
    domain_id: Option<u16>,
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    let Command::Run(a) = cli.command;
    labrig_runtime::main_node("labrig-control", |shutdown| async move {
        let mut cfg: ControlConfig = match &a.config {
            Some(p) => labrig_runtime::load_config(p)?,
            None => ControlConfig::default(),
        };
        if let Some(s) = a.source {
            cfg.source = s;
            if s == SourceKind::Hold || s == SourceKind::Teleop {
                cfg.auto_start = false;
            }
        }
        if let Some(c) = a.clock {
            cfg.clock = c;
        }
        if let Some(n) = a.episodes {
            cfg.episodes = n;
        }
        if let Some(s) = a.first_seed {
            cfg.first_seed = s;
        }
        if let Some(m) = a.max_steps {
            cfg.max_steps = m;
        }
        if a.no_reseed {
            cfg.reseed = false;
        }
        if a.manual {
            cfg.auto_start = false;
        }
        if let Some(d) = a.domain_id {
            cfg.ros.domain_id = d;
        }
        let summary = labrig_control::node::run(cfg, shutdown).await?;
        if a.json {
            println!("{}", serde_json::to_string(&summary)?);
        }
        if let Some(p) = &a.stats_out {
            std::fs::write(p, serde_json::to_string_pretty(&summary)?)
                .map_err(|e| anyhow::anyhow!("writing {}: {e}", p.display()))?;
        }
        tracing::info!(
            ticks = summary.ticks,
            episodes = summary.episodes.len(),
            held_ticks = summary.held_ticks,
            missed_ticks = summary.missed_ticks,
            jitter_p50_us = summary.jitter_us[0],
            jitter_p99_us = summary.jitter_us[1],
            jitter_max_us = summary.jitter_us[2],
            "control loop stopped"
        );
        Ok(())
    })
}
