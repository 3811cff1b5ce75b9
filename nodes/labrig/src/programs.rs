//! What the CLI's commands share: the labrig programs beside the `labrig` binary and how to
//! run them, and how a command joins ROS 2. The command modules use this; `cli` uses them
//! (one direction: nothing here imports `cli`).

use clap::Args;
use labrig_runtime::RosConfig;
use std::process::ExitCode;

/// A labrig program installed next to the running `labrig` binary.
pub fn sibling_binary(name: &str) -> anyhow::Result<std::path::PathBuf> {
    let me = std::env::current_exe()?;
    let path = me.with_file_name(name);
    anyhow::ensure!(
        path.exists(),
        "{} not found next to {}: build it with `cargo build --bin {name}` (scripts/labrig does)",
        path.display(),
        me.display()
    );
    Ok(path)
}

/// How to join ROS 2 (shared by every command that does).
#[derive(Debug, Clone, Args)]
pub struct RosArgs {
    /// DDS domain id (ROS_DOMAIN_ID is read as in every ROS 2 tool).
    #[arg(long, env = "ROS_DOMAIN_ID", default_value_t = 0)]
    pub domain_id: u16,
    /// Let DDS use every network interface instead of 127.0.0.1 only.
    #[arg(long)]
    pub allow_network: bool,
}

impl RosArgs {
    pub fn config(&self) -> anyhow::Result<RosConfig> {
        let cfg = RosConfig { domain_id: self.domain_id, loopback_only: !self.allow_network, ..RosConfig::default() };
        cfg.validate(std::path::Path::new("<command line>"))?;
        Ok(cfg)
    }
}

/// Runs the node program `name` (built beside this binary) with `args` in this process's
/// place (exec): the node keeps this pid, so a signal sent to `labrig <node> ...` (SIGTERM from
/// a supervisor, SIGKILL from a test) reaches the node, and none is left running behind a
/// killed `labrig`. Returns only when the program cannot be started.
pub fn node(name: &str, args: &[String]) -> anyhow::Result<ExitCode> {
    use std::os::unix::process::CommandExt;
    let exe = sibling_binary(name)?;
    let e = std::process::Command::new(&exe).args(args).exec();
    Err(anyhow::anyhow!("cannot run {}: {e}", exe.display()))
}
