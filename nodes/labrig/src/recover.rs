//! `labrig recover <episode_dir>`: an episode whose recorder was killed (or lost power) made
//! whole: every chunk that closed (each at most one second) is copied into a valid
//! `episode_0.mcap`, the damaged file kept beside it as `episode_0.mcap.damaged`, and
//! metadata.yaml rewritten for what was recovered.

use clap::Args;
use serde_json::json;
use std::path::PathBuf;
use std::process::ExitCode;

#[derive(Debug, Args)]
pub struct RecoverArgs {
    /// The episode directory (holding episode_0.mcap).
    dir: PathBuf,
    #[arg(long)]
    json: bool,
}

pub fn run(a: RecoverArgs) -> anyhow::Result<ExitCode> {
    anyhow::ensure!(a.dir.is_dir(), "{} is not an episode directory", a.dir.display());
    let r = labrig_episode::recover::recover_in_place(&a.dir)?;
    let secs = (r.end_ns - r.start_ns).max(0) as f64 / 1e9;
    if a.json {
        println!(
            "{}",
            json!({ "messages": r.messages, "chunks": r.chunks, "metadata": r.metadata, "attachments": r.attachments,
                    "start_ns": r.start_ns, "end_ns": r.end_ns, "seconds": secs, "stopped": r.stopped })
        );
    } else {
        println!(
            "recovered {} messages ({:.1} s, {} chunks, {} metadata records, {} attachments) into {}\n{}",
            r.messages,
            secs,
            r.chunks,
            r.metadata,
            r.attachments,
            a.dir.join(labrig_episode::episode::EPISODE_FILE).display(),
            r.stopped
        );
    }
    Ok(ExitCode::SUCCESS)
}
