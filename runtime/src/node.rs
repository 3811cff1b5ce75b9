//! The one shape of every labrig node: a declaration (an implementation of [`Node`]) and a
//! one-line `main` that calls [`node_main`].
//!
//! `<program> run [--config F] [--set key=value]... [--domain-id N] [--json] [--stats-out F]
//! [the node's own flags]`:
//! 1. the config file (TOML, unknown keys refused, naming the key and the file) or the node's
//!    defaults;
//! 2. `--set` overrides, any key of the config by its dotted path (`--set safety.max_step_m=0.02`),
//!    applied to the TOML before it is typed, so they are checked like the file;
//! 3. the node's own flags (declared once, in its [`Node::Flags`]), then `--domain-id`;
//! 4. [`Node::validate`]: every error one kind, [`labrig_msgs::Invalid`], naming the key;
//! 5. [`Node::run`] on a tokio runtime ([`Node::WORKER_THREADS`] workers; on the calling thread, so a node that raises
//!    its own priority raises only its loop), with a [`Shutdown`] token set by SIGINT/SIGTERM;
//! 6. the run's stats: printed as JSON with `--json`, written with `--stats-out`.
//!
//! Exit codes, the same for every node: 0 the node ran and stopped cleanly; 1 it could not
//! start (bad config, a peer or device missing) or failed while running; 2 a bad command line.
//! A program can carry tools of its own beside `run` ([`node_main_with`]), e.g. the gripper's
//! emulator or the sim's snapshot.

use crate::config::{ConfigError, RosConfig};
use crate::lifecycle::Shutdown;
use clap::{Args, FromArgMatches, Subcommand};
use labrig_msgs::Invalid;
use serde::Serialize;
use serde::de::DeserializeOwned;
use std::future::Future;
use std::path::{Path, PathBuf};
use std::process::ExitCode;

/// A node: what its program is called, its config, its own flags and what it does.
pub trait Node {
    /// The program, e.g. `labrig-control` (also the name in errors and logs).
    const NAME: &'static str;
    /// One line for `--help`.
    const ABOUT: &'static str;
    /// The tokio runtime's worker threads (the node's own future runs on the calling thread).
    const WORKER_THREADS: usize = 2;
    /// The typed config: `#[serde(deny_unknown_fields, default)]` on the struct, so a file
    /// (or no file: an empty table) sets what it names and the rest keeps the node's defaults.
    type Config: DeserializeOwned;
    /// The node's own command-line flags, declared once: `clap::Args` for the command line and
    /// `Serialize` with each field named by the config key it sets (`#[serde(rename =
    /// "fci.realtime")]` for a nested one). The skeleton writes the flags given into the config
    /// as `--set` would; unset ones (`None`, `false`) are skipped ([`is_false`]); a flag that
    /// turns a key off serializes through [`negated`].
    type Flags: Args + Serialize;
    /// What the run reports when it stops (`()` for none).
    type Stats: Serialize;

    /// Where the config keeps its DDS settings (`--domain-id` writes there).
    fn ros(config: &mut Self::Config) -> &mut RosConfig;

    /// What a flag implies beyond its own key (e.g. a node's `--source hold` also turns
    /// `auto_start` off), after the flags are in the config. `file` is the config file, if one
    /// was given (paths inside it are relative to it). Nothing by default.
    fn apply(flags: &Self::Flags, config: &mut Self::Config, file: Option<&Path>) {
        let _ = (flags, config, file);
    }

    /// Checks what serde cannot, naming the key.
    fn validate(config: &Self::Config) -> Result<(), Invalid>;

    /// Runs until done or until `shutdown`; returns the run's stats.
    fn run(config: Self::Config, shutdown: Shutdown) -> impl Future<Output = anyhow::Result<Self::Stats>>;
}

/// The flags every node takes (declared here once).
#[derive(Debug, Args)]
pub struct CommonFlags {
    /// The node's config (TOML); without one, the node's defaults.
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Override any config key by its dotted path, e.g. `--set safety.max_step_m=0.02`
    /// (the value is TOML: numbers, true/false, "text", [arrays]; a bare word is text).
    #[arg(long = "set", value_name = "KEY=VALUE", value_parser = key_value)]
    pub set: Vec<(String, String)>,
    /// DDS domain id (ROS_DOMAIN_ID is read as in every ROS 2 tool).
    #[arg(long, env = "ROS_DOMAIN_ID")]
    pub domain_id: Option<u16>,
    /// Print the run's stats as JSON on exit.
    #[arg(long)]
    pub json: bool,
    /// Also write the run's stats (JSON) to this file on exit.
    #[arg(long)]
    pub stats_out: Option<PathBuf>,
}

/// A `--set` argument that is not `KEY=VALUE`.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("`{arg}`: expected KEY=VALUE")]
pub struct SetFlagError {
    pub arg: String,
}

/// `--set`'s `KEY=VALUE` (a malformed one is a bad command line: exit 2).
fn key_value(arg: &str) -> Result<(String, String), SetFlagError> {
    match arg.split_once('=') {
        Some((k, v)) if !k.trim().is_empty() => Ok((k.trim().to_owned(), v.trim().to_owned())),
        _ => Err(SetFlagError { arg: arg.to_owned() }),
    }
}

#[derive(Debug, Args)]
struct RunArgs<F: Args> {
    #[command(flatten)]
    common: CommonFlags,
    #[command(flatten)]
    flags: F,
}

/// A program with no tools besides `run`.
#[derive(Debug, Subcommand)]
pub enum NoTools {}

enum Parsed<F: Args, T> {
    Run(Box<RunArgs<F>>),
    Tool(T),
}

/// `main` of a node program with no tools: `fn main() -> ExitCode { node_main::<MyNode>() }`.
pub fn node_main<N: Node>() -> ExitCode {
    node_main_with::<N, NoTools, _>(|tool, _, _| match tool {})
}

/// `main` of a node program that also carries tools (`<program> <tool> ...`: the node's
/// benchmark, an emulator, ...), with the same logging as the node. A tool runs outside the
/// runtime (it may start its own, or `block_on` the one it is given); SIGINT/SIGTERM keep their
/// default action for it (it ends) unless it calls `Shutdown::trigger_on_signals` itself.
pub fn node_main_with<N, T, H>(tool: H) -> ExitCode
where
    N: Node,
    T: Subcommand,
    H: FnOnce(T, &tokio::runtime::Runtime, Shutdown) -> anyhow::Result<ExitCode>,
{
    let parsed = match parse::<N, T>(std::env::args_os()) {
        Ok(p) => p,
        Err(e) => e.exit(),
    };
    if labrig_msgs::parse_only() {
        return ExitCode::SUCCESS;
    }
    crate::logging::init("info");
    let name = N::NAME;
    let rt = match tokio::runtime::Builder::new_multi_thread().worker_threads(N::WORKER_THREADS).enable_all().build() {
        Ok(rt) => rt,
        Err(e) => {
            eprintln!("{name}: cannot start the runtime: {e}");
            return ExitCode::FAILURE;
        }
    };
    let shutdown = Shutdown::new();
    let result = match parsed {
        Parsed::Tool(t) => tool(t, &rt, shutdown),
        Parsed::Run(run) => rt
            .block_on(async {
                shutdown.trigger_on_signals()?;
                run_node::<N>(*run, shutdown).await
            })
            .map(|()| ExitCode::SUCCESS),
    };
    match result {
        Ok(code) => code,
        Err(e) => {
            eprintln!("{name}: {e:#}");
            ExitCode::FAILURE
        }
    }
}

fn parse<N: Node, T: Subcommand>(
    args: impl IntoIterator<Item = std::ffi::OsString>,
) -> Result<Parsed<N::Flags, T>, clap::Error> {
    // Doc comments of the flag and tool types would become the help's text: set ours after.
    let run = RunArgs::<N::Flags>::augment_args(clap::Command::new("run")).about(run_about(N::ABOUT));
    let cmd = T::augment_subcommands(clap::Command::new(N::NAME))
        .about(N::ABOUT)
        .subcommand(run)
        .subcommand_required(true)
        .arg_required_else_help(true);
    let matches = cmd.try_get_matches_from(args)?;
    match matches.subcommand() {
        Some(("run", m)) => Ok(Parsed::Run(Box::new(RunArgs::from_arg_matches(m)?))),
        _ => Ok(Parsed::Tool(T::from_arg_matches(&matches)?)),
    }
}

/// `run`'s line in the help: what the node is (its [`Node::ABOUT`], so `labrig policy run
/// --help` says it runs the policy server), then how its config is given.
fn run_about(about: &str) -> String {
    let mut chars = about.trim_end_matches('.').chars();
    let what: String = chars.next().map(|c| c.to_uppercase().chain(chars).collect()).unwrap_or_default();
    format!("{what}. Run it (the flags override the config file; --set any config key)")
}

/// The config node `N` runs with when started as `<program> <args...>` (a launch config's
/// `[[node]]`: its `args` and `--config <file>`): the same parse and steps 1-4 as the program
/// itself. An `args` that does not start with `run` is refused.
pub fn run_config<N: Node>(args: &[String], config: Option<&Path>) -> anyhow::Result<N::Config> {
    let mut argv: Vec<std::ffi::OsString> = vec![N::NAME.into()];
    argv.extend(args.iter().map(Into::into));
    if let Some(c) = config {
        argv.push("--config".into());
        argv.push(c.into());
    }
    match parse::<N, NoTools>(argv) {
        Ok(Parsed::Run(run)) => Ok(load::<N>(&run.common, run.flags)?),
        Ok(Parsed::Tool(t)) => match t {},
        Err(e) => anyhow::bail!("{} {}: {}", N::NAME, args.join(" "), e.render().to_string().trim()),
    }
}

/// Steps 1-4 of the module's list: the config a node runs with.
pub fn load<N: Node>(common: &CommonFlags, flags: N::Flags) -> Result<N::Config, ConfigError> {
    let origin = common.config.clone().unwrap_or_else(|| PathBuf::from("<command line>"));
    let text = match &common.config {
        Some(path) => {
            std::fs::read_to_string(path).map_err(|source| ConfigError::Read { path: path.to_owned(), source })?
        }
        None => String::new(),
    };
    // The file alone first: its errors keep their line and column.
    let _: N::Config = crate::config::parse_config(&text, &origin)?;
    let mut table: toml::Table = crate::config::parse_config(&text, &origin)?;
    for (key, value) in &common.set {
        set_key(&mut table, key, value);
    }
    let given = toml::Table::try_from(&flags)
        .map_err(|e| ConfigError::Parse { path: origin.clone(), message: format!("the flags: {e}") })?;
    for (key, value) in given {
        set_value(&mut table, &key, value);
    }
    let mut config: N::Config = table.try_into().map_err(|e: toml::de::Error| ConfigError::Parse {
        path: origin.clone(),
        message: format!("{} (with the command line's keys)", e.to_string().trim_end()),
    })?;
    N::apply(&flags, &mut config, common.config.as_deref());
    if let Some(d) = common.domain_id {
        N::ros(&mut config).domain_id = d;
    }
    N::ros(&mut config).validate(&origin)?;
    N::validate(&config).map_err(|rule| ConfigError::Rule { path: origin, rule })?;
    Ok(config)
}

/// For a flag's `skip_serializing_if`: an unset switch sets nothing.
pub fn is_false(b: &bool) -> bool {
    !*b
}

/// For a flag's `serialize_with`: a switch that turns its key off (`--no-reseed` -> `reseed =
/// false`); with `skip_serializing_if = "is_false"` it writes only when given.
pub fn negated<S: serde::Serializer>(b: &bool, s: S) -> Result<S::Ok, S::Error> {
    s.serialize_bool(!*b)
}

/// `key` (dotted) = `value` (TOML, or a bare word as text) in `table`, making tables on the way.
fn set_key(table: &mut toml::Table, key: &str, value: &str) {
    let parsed = format!("v = {value}")
        .parse::<toml::Table>()
        .ok()
        .and_then(|mut t| t.remove("v"))
        .unwrap_or_else(|| toml::Value::String(value.to_owned()));
    set_value(table, key, parsed);
}

/// `key` (dotted) = `value` in `table`, making tables on the way.
fn set_value(table: &mut toml::Table, key: &str, parsed: toml::Value) {
    let mut parts: Vec<&str> = key.split('.').collect();
    let last = parts.pop().unwrap_or(key);
    let mut at = table;
    for p in parts {
        let entry = at.entry(p.to_owned()).or_insert_with(|| toml::Value::Table(toml::Table::new()));
        if !entry.is_table() {
            *entry = toml::Value::Table(toml::Table::new());
        }
        at = entry.as_table_mut().expect("made a table");
    }
    at.insert(last.to_owned(), parsed);
}

async fn run_node<N: Node>(args: RunArgs<N::Flags>, shutdown: Shutdown) -> anyhow::Result<()> {
    let RunArgs { common, flags } = args;
    let config = load::<N>(&common, flags)?;
    tracing::debug!(node = N::NAME, "starting");
    // A node whose DDS threads die exits (status 1) for the launcher to restart it.
    crate::ros::exit_on_dds_death(true);
    let stats = N::run(config, shutdown).await?;
    if common.json {
        println!("{}", serde_json::to_string(&stats)?);
    }
    if let Some(p) = &common.stats_out {
        std::fs::write(p, serde_json::to_string_pretty(&stats)?)
            .map_err(|e| anyhow::anyhow!("writing {}: {e}", p.display()))?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde::Deserialize;

    #[derive(Debug, Clone, PartialEq, Deserialize)]
    #[serde(deny_unknown_fields, default)]
    struct Cfg {
        ros: RosConfig,
        ticks: u32,
        inner: Inner,
    }

    #[derive(Debug, Clone, PartialEq, Default, Deserialize)]
    #[serde(deny_unknown_fields, default)]
    struct Inner {
        gain: f64,
    }

    impl Default for Cfg {
        fn default() -> Self {
            Cfg { ros: RosConfig::default(), ticks: 3, inner: Inner::default() }
        }
    }

    #[derive(Debug, Args, Serialize)]
    struct Flags {
        /// Ticks to run.
        #[arg(long)]
        #[serde(skip_serializing_if = "Option::is_none")]
        ticks: Option<u32>,
        /// inner.gain = 0.
        #[arg(long)]
        #[serde(rename = "inner.gain", skip_serializing_if = "is_false", serialize_with = "zero")]
        no_gain: bool,
    }

    fn zero<S: serde::Serializer>(_: &bool, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_f64(0.0)
    }

    struct Counter;

    impl Node for Counter {
        const NAME: &'static str = "labrig-counter";
        const ABOUT: &'static str = "counts ticks";
        type Config = Cfg;
        type Flags = Flags;
        type Stats = u32;
        fn ros(config: &mut Cfg) -> &mut RosConfig {
            &mut config.ros
        }
        fn validate(config: &Cfg) -> Result<(), Invalid> {
            if config.ticks == 0 { Err(Invalid::new("ticks", "ticks must be > 0")) } else { Ok(()) }
        }
        async fn run(config: Cfg, shutdown: Shutdown) -> anyhow::Result<u32> {
            shutdown.trigger();
            shutdown.wait().await;
            Ok(config.ticks)
        }
    }

    fn config(args: &[&str]) -> Result<Cfg, String> {
        let argv = std::iter::once("labrig-counter").chain(args.iter().copied()).map(Into::into);
        match parse::<Counter, NoTools>(argv).map_err(|e| e.to_string())? {
            Parsed::Run(r) => load::<Counter>(&r.common, r.flags).map_err(|e| e.to_string()),
            Parsed::Tool(t) => match t {},
        }
    }

    #[test]
    fn defaults_then_file_then_set_then_flags_then_domain() {
        assert_eq!(config(&["run"]).unwrap(), Cfg::default());
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("n.toml");
        std::fs::write(&path, "ticks = 5\n[inner]\ngain = 1.5\n").unwrap();
        let p = path.to_str().unwrap();
        let c = config(&["run", "--config", p]).unwrap();
        assert_eq!((c.ticks, c.inner.gain), (5, 1.5));
        let c = config(&["run", "--config", p, "--set", "inner.gain=2", "--set", "ticks=7"]).unwrap();
        assert_eq!((c.ticks, c.inner.gain), (7, 2.0));
        let c = config(&["run", "--config", p, "--set", "ticks=7", "--ticks", "9", "--domain-id", "12"]).unwrap();
        assert_eq!((c.ticks, c.ros.domain_id), (9, 12));
        let c = config(&["run", "--config", p, "--no-gain"]).unwrap();
        assert_eq!((c.ticks, c.inner.gain), (5, 0.0), "a nested key from a flag, the file's others kept");
    }

    #[test]
    fn unknown_keys_and_bad_values_are_refused_by_name() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("n.toml");
        std::fs::write(&path, "ticks = 5\ntikcs = 4\n").unwrap();
        let e = config(&["run", "--config", path.to_str().unwrap()]).unwrap_err();
        assert!(e.contains("unknown field `tikcs`") && e.contains("n.toml"), "{e}");
        let e = config(&["run", "--set", "inner.gian=2"]).unwrap_err();
        assert!(e.contains("unknown field `gian`"), "{e}");
        let e = config(&["run", "--set", "ticks"]).unwrap_err();
        assert!(e.contains("`ticks`: expected KEY=VALUE"), "{e}");
        let e = config(&["run", "--ticks", "0"]).unwrap_err();
        assert_eq!(e, "invalid config <command line>: ticks must be > 0");
        let e = config(&["run", "--domain-id", "300"]).unwrap_err();
        assert!(e.contains("`ros.domain_id` is 300"), "{e}");
        assert!(config(&["run", "--tick", "3"]).unwrap_err().contains("--tick"));
    }

    #[test]
    fn run_help_says_what_the_node_is() {
        let argv = ["labrig-counter", "run", "--help"].map(std::ffi::OsString::from);
        let Err(help) = parse::<Counter, NoTools>(argv) else { panic!("--help parsed as a run") };
        let help = help.to_string();
        assert!(help.starts_with("Counts ticks. Run it (the flags override the config file"), "{help}");
        assert!(help.contains("Usage: labrig-counter run"), "{help}");
    }

    #[test]
    fn a_node_runs_until_shutdown_and_reports_its_stats() {
        let rt = tokio::runtime::Builder::new_current_thread().enable_all().build().unwrap();
        let stats = rt.block_on(Counter::run(Cfg::default(), Shutdown::new())).unwrap();
        assert_eq!(stats, 3);
    }
}
