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

/// Runs the labrig program `name` (built beside this binary) with `args` in this process's
/// place (exec): the node keeps this pid, so a signal sent to `labrig <node> ...` (SIGTERM from
/// a supervisor, SIGKILL from a test) reaches the node, and none is left running behind a
/// killed `labrig`. Returns only when the program cannot be started.
///
/// `shown` is the labrig command the user typed in front of the words `name` parses first
/// (`labrig sim` for `labrig sim run ...` -> `labrig-sim run ...`; `labrig` for `labrig replay
/// ...` -> `labrig-sim replay ...`): the program gets it as its argv[0], from which clap takes
/// the name its usage lines (in help and in errors) show, so they name the command the user
/// typed rather than the program. Where the program's subcommand is not the word typed, see
/// [`node_renamed`].
pub fn node(name: &str, shown: &str, args: &[String]) -> anyhow::Result<ExitCode> {
    use std::os::unix::process::CommandExt;
    let exe = sibling_binary(name)?;
    let e = std::process::Command::new(&exe).arg0(shown).args(args).exec();
    Err(anyhow::anyhow!("cannot run {}: {e}", exe.display()))
}

/// `typed <args...>` run as `name sub <args...>` where the program's subcommand `sub` is not
/// what the user typed (`labrig export lerobot` is `labrig-dataset export-lerobot`, `labrig
/// bench ik` is `labrig-franka bench-ik`), so no argv[0] makes clap's usage lines say `typed`.
/// The program first parses the arguments alone (`LABRIG_PARSE_ONLY`, output captured): its
/// help, version or refusal is printed with `name sub` replaced by `typed`, and ends the
/// command with the program's exit status; arguments that parse run as [`node`] runs them.
pub fn node_renamed(name: &str, sub: &str, typed: &str, args: &[String]) -> anyhow::Result<ExitCode> {
    let exe = sibling_binary(name)?;
    let forwarded: Vec<String> = std::iter::once(sub.to_owned()).chain(args.iter().cloned()).collect();
    let check = std::process::Command::new(&exe)
        .args(&forwarded)
        .env("LABRIG_PARSE_ONLY", "1")
        .stdin(std::process::Stdio::null())
        .output()
        .map_err(|e| anyhow::anyhow!("cannot run {}: {e}", exe.display()))?;
    if labrig_msgs::parse_only() || !check.status.success() || !check.stdout.is_empty() {
        let internal = format!("{name} {sub}");
        let show = |bytes: &[u8]| rename_command(&String::from_utf8_lossy(bytes), &internal, typed);
        print!("{}", show(&check.stdout));
        eprint!("{}", show(&check.stderr));
        let code = check.status.code().map_or(1, |c| u8::try_from(c).unwrap_or(1));
        return Ok(ExitCode::from(code));
    }
    node(name, name, &forwarded)
}

/// `text` with every `from` that is a whole command (not followed by more of a word, as
/// `labrig-droid export` in `labrig-droid export-mcap`) replaced by `to`.
fn rename_command(text: &str, from: &str, to: &str) -> String {
    let mut out = String::with_capacity(text.len());
    let mut rest = text;
    while let Some(i) = rest.find(from) {
        let after = &rest[i + from.len()..];
        let whole = !after.starts_with(|c: char| c.is_alphanumeric() || c == '-' || c == '_');
        out.push_str(&rest[..i]);
        out.push_str(if whole { to } else { from });
        rest = after;
    }
    out.push_str(rest);
    out
}

#[cfg(test)]
mod tests {
    use super::rename_command;

    #[test]
    fn only_whole_commands_are_renamed() {
        let help = "Usage: labrig-droid export [OPTIONS] <SOURCE> <OUT>\n(see labrig-droid export-mcap)\n";
        assert_eq!(
            rename_command(help, "labrig-droid export", "labrig export droid"),
            "Usage: labrig export droid [OPTIONS] <SOURCE> <OUT>\n(see labrig-droid export-mcap)\n"
        );
        assert_eq!(
            rename_command("x labrig-franka bench-ik", "labrig-franka bench-ik", "labrig bench ik"),
            "x labrig bench ik"
        );
    }
}
