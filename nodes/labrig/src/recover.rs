//! `labrig recover <episode_dir>`: an episode whose recorder was killed (or lost power) made
//! whole, for files copied off a dead machine (a running recorder recovers its own on restart):
//! every chunk that closed (each at most a quarter second) of each unfinished part is copied into a
//! valid `episode_<k>.mcap`, the damaged file kept beside it as `episode_<k>.mcap.damaged`, and
//! metadata.yaml rewritten for every part.

use clap::Args;
use serde_json::json;
use std::path::PathBuf;
use std::process::ExitCode;

#[derive(Debug, Args)]
pub struct RecoverArgs {
    /// The episode directory (holding episode_0.mcap, and episode_1.mcap ... when recorded in parts).
    dir: PathBuf,
    #[arg(long)]
    json: bool,
}

pub fn run(a: RecoverArgs) -> anyhow::Result<ExitCode> {
    anyhow::ensure!(a.dir.is_dir(), "{} is not an episode directory", a.dir.display());
    let r = labrig_episode::recover::recover_in_place(&a.dir)?;
    let secs = (r.info.end_ns - r.info.start_ns).max(0) as f64 / 1e9;
    let parts: Vec<_> = r
        .parts
        .iter()
        .map(|p| match &p.report {
            Some(r) => json!({ "file": p.file, "recovered": true, "messages": r.messages, "chunks": r.chunks,
                               "metadata": r.metadata, "attachments": r.attachments, "start_ns": r.start_ns,
                               "end_ns": r.end_ns, "stopped": r.stopped }),
            None => json!({ "file": p.file, "recovered": false }),
        })
        .collect();
    if a.json {
        println!(
            "{}",
            json!({ "messages": r.messages(), "start_ns": r.info.start_ns, "end_ns": r.info.end_ns, "seconds": secs,
                    "parts": parts })
        );
        return Ok(ExitCode::SUCCESS);
    }
    for p in &r.parts {
        match &p.report {
            Some(r) => println!(
                "recovered {} messages ({:.1} s, {} chunks, {} metadata records, {} attachments) into {}: {}",
                r.messages,
                (r.end_ns - r.start_ns).max(0) as f64 / 1e9,
                r.chunks,
                r.metadata,
                r.attachments,
                p.file.display(),
                r.stopped
            ),
            None => println!("{}: finished, left as it is", p.file.display()),
        }
    }
    println!("episode: {} messages, {secs:.1} s, {} part(s)", r.messages(), r.parts.len());
    Ok(ExitCode::SUCCESS)
}
