//! The simulated rigs the CLI's commands start: the demo's and the rollouts' launch configs
//! (compiled in; the same files `labrig launch` reads), a rig supervised in the background until
//! its job is done, and the helpers its callers share.

use crate::config::LaunchConfig;
use crate::supervise::{Output, supervise_until};
use labrig_runtime::Shutdown;
use std::path::{Path, PathBuf};
use std::process::ExitCode;

/// The demo's rig, compiled in (the same file `labrig launch` reads).
pub const SIM_DEMO: &str = include_str!("../../launch_configs/sim_demo.toml");

/// The rollout rig, compiled in (the same file `labrig launch` reads).
pub const SIM_ROLLOUT: &str = include_str!("../../launch_configs/sim_rollout.toml");

/// Sets `flag`'s value in `args` (appended when absent).
pub fn set_arg(args: &mut Vec<String>, flag: &str, value: &str) {
    match args.iter().position(|a| a == flag) {
        Some(i) if i + 1 < args.len() => args[i + 1] = value.to_owned(),
        _ => args.extend([flag.to_owned(), value.to_owned()]),
    }
}

/// A simulated rig supervised in the background until its `completes` node is done: `watch`
/// triggers when it has stopped, `stop` (also set by SIGINT/SIGTERM) stops it.
#[derive(Debug)]
pub struct SimRig {
    pub watch: Shutdown,
    pub stop: Shutdown,
    pub rig: tokio::task::JoinHandle<anyhow::Result<ExitCode>>,
}

impl SimRig {
    pub fn start(cfg: LaunchConfig, order: Vec<usize>, domain: u16) -> anyhow::Result<SimRig> {
        let watch = Shutdown::new();
        let stop = Shutdown::new();
        stop.trigger_on_signals()?;
        let rig = {
            let (watch, stop) = (watch.clone(), stop.clone());
            tokio::spawn(async move {
                let dir = PathBuf::from("launch_configs");
                let r = supervise_until(cfg, order, dir, domain, None, Output::Quiet, stop).await;
                watch.trigger();
                r
            })
        };
        Ok(SimRig { watch, stop, rig })
    }
}

/// One PNG: a row per moment (first, middle, last recorded frame), a column per camera.
pub fn contact_sheet(mcap_file: &Path, png_out: &Path) -> anyhow::Result<()> {
    Ok(labrig_episode::sheet::contact_sheet(mcap_file, png_out)?)
}
