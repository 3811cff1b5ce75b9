//! `labrig inspect <episode> [--json]`: duration, per-topic counts and rates, malformed and
//! out-of-order messages, dropped and late camera frames, camera skew per step, control
//! jitter, DROID metadata. Exit code 0: a good episode; 3: readable, with flags (listed);
//! 1: not readable.

use clap::Args;
use std::path::PathBuf;
use std::process::ExitCode;

#[derive(Debug, Args)]
pub struct InspectArgs {
    /// The episode: its directory or its .mcap file.
    episode: PathBuf,
    #[arg(long)]
    json: bool,
}

pub fn run(a: InspectArgs) -> anyhow::Result<ExitCode> {
    let i = labrig_episode::inspect::inspect(&a.episode).map_err(anyhow::Error::msg)?;
    if a.json {
        println!("{}", serde_json::to_string(&i)?);
    } else {
        print!("{}", i.text());
    }
    Ok(if i.flags.is_empty() { ExitCode::SUCCESS } else { ExitCode::from(3) })
}
