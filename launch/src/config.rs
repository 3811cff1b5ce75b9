//! Launch configs: a rig as the nodes it runs (`[[node]]`: the labrig program, its arguments, an
//! optional node config file, the nodes it starts after, the topic that shows it is up, what to
//! do when it dies) and the real rig's devices. [`LaunchConfig::load`] validates a file (unknown
//! keys, unknown programs or dependencies, cycles, missing config files: each named) and gives
//! the start order.

use anyhow::Context;
use labrig_runtime::RosConfig;
use serde::Deserialize;
use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

/// The programs a launch config may start (built beside the `labrig` binary). Only programs
/// that exist: a config naming another one (a node still to come, a typo) is refused by name.
pub const PROGRAMS: [&str; 9] = [
    "labrig-sim",
    "labrig-franka",
    "labrig-gripper",
    "labrig-recorder",
    "labrig-control",
    "labrig-teleop",
    "labrig-policy",
    "labrig-cameras",
    "labrig-station",
];

#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum OnFailure {
    /// Start the node again (up to `max_restarts`), the rig keeps running.
    Restart,
    /// Stop the whole rig.
    #[default]
    Stop,
}

/// The real rig's devices: written once here, handed by the launcher to every node it starts.
pub use labrig_runtime::devices::Devices;

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Rig {
    pub name: String,
    #[serde(default)]
    pub description: String,
    #[serde(default)]
    pub domain_id: u16,
    #[serde(default)]
    pub on_failure: OnFailure,
    #[serde(default)]
    pub devices: Devices,
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct NodeSpec {
    pub name: String,
    pub program: String,
    #[serde(default)]
    pub args: Vec<String>,
    /// A node config file, relative to the launch config; passed as `--config <path>`.
    pub config: Option<PathBuf>,
    /// Nodes that must be up before this one starts.
    #[serde(default)]
    pub after: Vec<String>,
    /// The topic whose messages show the node is up.
    pub health: String,
    pub on_failure: Option<OnFailure>,
    #[serde(default = "three")]
    pub max_restarts: u32,
    /// The node is the rig's job (a control loop collecting N episodes): when it exits
    /// with status 0 the rig stops, successfully.
    #[serde(default)]
    pub completes: bool,
    /// Environment variables for the node's process (e.g. `LABRIG_FRAMES_NAMESPACE` for two
    /// rigs on one machine).
    #[serde(default)]
    pub env: BTreeMap<String, String>,
}

fn three() -> u32 {
    3
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LaunchConfig {
    pub rig: Rig,
    #[serde(rename = "node")]
    pub nodes: Vec<NodeSpec>,
}

impl LaunchConfig {
    /// Loads and validates `path`; returns the config and the start order.
    pub fn load(path: &Path) -> anyhow::Result<(LaunchConfig, Vec<usize>)> {
        let cfg: LaunchConfig = labrig_runtime::load_config(path)?;
        let order = cfg
            .validate(path.parent().unwrap_or(Path::new(".")))
            .with_context(|| format!("invalid launch config {}", path.display()))?;
        Ok((cfg, order))
    }

    /// Parses and validates a config's text (`origin` names it in errors; config files are
    /// looked up beside it).
    pub fn parse(text: &str, origin: &Path) -> anyhow::Result<(LaunchConfig, Vec<usize>)> {
        let cfg: LaunchConfig = labrig_runtime::config::parse_config(text, origin)?;
        let order = cfg
            .validate(origin.parent().unwrap_or(Path::new(".")))
            .with_context(|| format!("invalid launch config {}", origin.display()))?;
        Ok((cfg, order))
    }

    /// The node called `name`.
    pub fn node_mut(&mut self, name: &str) -> Option<&mut NodeSpec> {
        self.nodes.iter_mut().find(|n| n.name == name)
    }

    /// Checks what serde cannot; returns the nodes' start order (dependencies first).
    pub fn validate(&self, dir: &Path) -> anyhow::Result<Vec<usize>> {
        let mut names = BTreeSet::new();
        anyhow::ensure!(!self.nodes.is_empty(), "the rig has no [[node]]");
        anyhow::ensure!(self.rig.domain_id <= RosConfig::MAX_DOMAIN_ID, "rig.domain_id must be 0..=232");
        for n in &self.nodes {
            anyhow::ensure!(names.insert(n.name.as_str()), "node `{}` is defined twice", n.name);
            anyhow::ensure!(
                PROGRAMS.contains(&n.program.as_str()),
                "node `{}`: unknown program `{}` (one of {})",
                n.name,
                n.program,
                PROGRAMS.join(", ")
            );
            anyhow::ensure!(
                n.health.starts_with('/'),
                "node `{}`: health topic `{}` must start with /",
                n.name,
                n.health
            );
            if let Some(c) = &n.config {
                let p = dir.join(c);
                anyhow::ensure!(p.is_file(), "node `{}`: config file {} does not exist", n.name, p.display());
            }
        }
        for n in &self.nodes {
            for a in &n.after {
                anyhow::ensure!(
                    names.contains(a.as_str()),
                    "node `{}` starts after `{a}`, which is not a node",
                    n.name
                );
            }
        }
        // Kahn's order; what is left is a cycle.
        let mut order = Vec::new();
        let mut done: BTreeSet<&str> = BTreeSet::new();
        while order.len() < self.nodes.len() {
            let ready: Vec<usize> = (0..self.nodes.len())
                .filter(|&i| !done.contains(self.nodes[i].name.as_str()))
                .filter(|&i| self.nodes[i].after.iter().all(|a| done.contains(a.as_str())))
                .collect();
            if ready.is_empty() {
                let left: Vec<&str> =
                    self.nodes.iter().map(|n| n.name.as_str()).filter(|n| !done.contains(n)).collect();
                anyhow::bail!("the nodes {left:?} wait for each other (a dependency cycle)");
            }
            for i in ready {
                done.insert(self.nodes[i].name.as_str());
                order.push(i);
            }
        }
        Ok(order)
    }
}
