//! `labrig launch <launch_config.toml>`: start and supervise a rig (the launch library,
//! `labrig_launch`, does the work: [`labrig_launch::config`], [`labrig_launch::supervise`]).

use clap::Args;
use labrig_launch::config::LaunchConfig;
use labrig_launch::supervise::{Output, supervise};
use serde_json::json;
use std::path::{Path, PathBuf};
use std::process::ExitCode;

#[derive(Debug, Args)]
pub struct LaunchArgs {
    /// The launch config (launch_configs/*.toml).
    config: PathBuf,
    /// Validate the file, print the start order, start nothing.
    #[arg(long)]
    check: bool,
    /// Stop the rig after this many seconds (default: run until Ctrl-C).
    #[arg(long)]
    seconds: Option<f64>,
    /// Override the rig's DDS domain.
    #[arg(long)]
    domain_id: Option<u16>,
    /// Status as JSON lines.
    #[arg(long)]
    json: bool,
}

pub fn run(a: LaunchArgs) -> anyhow::Result<ExitCode> {
    let (cfg, order) = LaunchConfig::load(&a.config)?;
    let dir = a.config.parent().unwrap_or(Path::new(".")).to_owned();
    let names: Vec<&str> = order.iter().map(|&i| cfg.nodes[i].name.as_str()).collect();
    if a.check {
        if a.json {
            println!("{}", json!({ "rig": cfg.rig.name, "valid": true, "start_order": names }));
        } else {
            println!("{}: valid; start order: {}", a.config.display(), names.join(" -> "));
        }
        return Ok(ExitCode::SUCCESS);
    }
    let domain = a.domain_id.unwrap_or(cfg.rig.domain_id);
    let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build()?;
    let out = if a.json { Output::Json } else { Output::Text };
    rt.block_on(supervise(cfg, order, dir, domain, a.seconds, out))
}
