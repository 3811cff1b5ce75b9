//! labrig-control: the 20 Hz rig loop.
//!
//! - [`config`]: the node's keys (the loop, the source, the clock, `[policy]`); [`report`]:
//!   what a run reports (episodes, the summary's figures, DROID's action dictionary);
//!   [`info`]: what a policy server serves. These import no module above them.
//! - [`frames`]: per camera, the recent frames' times; the frame nearest a tick; skew.
//! - [`episode`]: the episode state machine (idle -> recording -> success | failure |
//!   discarded -> resetting -> idle), driven by events.
//! - [`step`]: one `labrig_msgs/Step` record per tick from the observation, the action and
//!   the tick's timing.
//! - [`source`]: action sources behind one trait (the sim's scripted expert, teleop).
//! - [`policy`]: the policy server as an action source (chunks timed to ticks, blending,
//!   asynchronous requests).
//! - [`takeover`]: an operator (the Quest, or the sim's expert) taking over from the policy.
//! - [`rig`]: the loop as a state machine ([`rig::RigLoop`]: begin a tick, observe, decide,
//!   act), driven tick by tick by the node or by a test with in-memory inputs and outputs.
//! - [`node`]: the node (`labrig-control run`) feeding the state machine from ROS 2 and shared
//!   memory on the sim's or the wall clock.

pub mod config;
pub mod episode;
pub mod frames;
pub mod info;
pub mod node;
pub mod policy;
pub mod remote;
pub mod report;
pub mod rig;
pub mod source;
pub mod step;
pub mod takeover;

use config::{ClockKind, ControlConfig, SourceKind};
use labrig_msgs::Invalid;
use labrig_runtime::node::{is_false, negated};
use labrig_runtime::{RosConfig, Shutdown};
use report::Summary;
use std::path::Path;

/// The rig loop node: `labrig-control run` (`labrig_runtime::node_main`).
#[derive(Debug)]
pub struct ControlNode;

/// `labrig-control run`'s own flags; each sets the config key of its name.
#[derive(Debug, clap::Args, serde::Serialize)]
pub struct ControlFlags {
    /// The action source (hold and teleop also turn auto_start off).
    #[arg(long, value_enum)]
    #[serde(skip_serializing_if = "Option::is_none")]
    source: Option<SourceKind>,
    /// The loop's clock: `sim` (the bridge's time; lockstep-safe) or `wall` (the real rig).
    #[arg(long, value_enum)]
    #[serde(skip_serializing_if = "Option::is_none")]
    clock: Option<ClockKind>,
    /// Episodes to run, then exit (0: until stopped).
    #[arg(long)]
    #[serde(skip_serializing_if = "Option::is_none")]
    episodes: Option<u64>,
    /// The first scene seed (`/sim/reset`); the next episodes take the following seeds.
    #[arg(long)]
    #[serde(skip_serializing_if = "Option::is_none")]
    first_seed: Option<u64>,
    /// Do not ask the sim for a new scene per episode (reseed = false).
    #[arg(long)]
    #[serde(rename = "reseed", skip_serializing_if = "is_false", serialize_with = "negated")]
    no_reseed: bool,
    /// Episodes only from /rig/request (auto_start = false).
    #[arg(long)]
    #[serde(rename = "auto_start", skip_serializing_if = "is_false", serialize_with = "negated")]
    manual: bool,
    /// Step budget per episode.
    #[arg(long)]
    #[serde(skip_serializing_if = "Option::is_none")]
    max_steps: Option<u64>,
}

impl labrig_runtime::Node for ControlNode {
    const NAME: &'static str = "labrig-control";
    const ABOUT: &'static str =
        "The 20 Hz rig loop: observations, actions through the safety layer, Step records, episodes";
    type Config = ControlConfig;
    type Flags = ControlFlags;
    type Stats = Summary;

    fn ros(config: &mut ControlConfig) -> &mut RosConfig {
        &mut config.ros
    }

    fn apply(f: &ControlFlags, cfg: &mut ControlConfig, _file: Option<&Path>) {
        // No source to follow: episodes come from the operator.
        if matches!(f.source, Some(SourceKind::Hold | SourceKind::Teleop)) {
            cfg.auto_start = false;
        }
    }

    fn validate(config: &ControlConfig) -> Result<(), Invalid> {
        config.validate()
    }

    async fn run(config: ControlConfig, shutdown: Shutdown) -> anyhow::Result<Summary> {
        let summary = node::run(config, shutdown).await?;
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
        Ok(summary)
    }
}

#[cfg(test)]
mod tests {
    use std::collections::BTreeMap;

    /// The modules' references to each other (`crate::<module>` outside comments), per module.
    fn imports() -> BTreeMap<String, Vec<String>> {
        let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
        let mut graph = BTreeMap::new();
        for entry in std::fs::read_dir(&dir).unwrap() {
            let path = entry.unwrap().path();
            let name = path.file_stem().unwrap().to_string_lossy().into_owned();
            if path.extension().is_none_or(|e| e != "rs") || name == "lib" || name == "main" {
                continue;
            }
            let mut uses: Vec<String> = Vec::new();
            for line in std::fs::read_to_string(&path).unwrap().lines() {
                let code = line.split("//").next().unwrap_or("");
                for (i, _) in code.match_indices("crate::") {
                    let rest = &code[i + "crate::".len()..];
                    let module: String = rest.chars().take_while(|c| c.is_alphanumeric() || *c == '_').collect();
                    if !module.is_empty() && module != name && !uses.contains(&module) {
                        uses.push(module);
                    }
                }
            }
            graph.insert(name, uses);
        }
        graph
    }

    /// The modules import each other in one direction only: the node's config and report
    /// sit below the loop, the policy source and the node (a cycle made every change to
    /// one of them a change to all).
    #[test]
    fn the_modules_import_each_other_without_a_cycle() {
        let graph = imports();
        assert!(graph.len() >= 10 && graph["node"].contains(&"rig".to_string()), "{graph:?}");
        // Depth-first search; a module met again on the current path closes a cycle.
        fn visit(m: &str, graph: &BTreeMap<String, Vec<String>>, path: &mut Vec<String>, done: &mut Vec<String>) {
            if done.iter().any(|d| d == m) {
                return;
            }
            if let Some(at) = path.iter().position(|p| p == m) {
                panic!("the modules import each other in a circle: {} -> {m}", path[at..].join(" -> "));
            }
            path.push(m.to_string());
            for next in graph.get(m).into_iter().flatten() {
                visit(next, graph, path, done);
            }
            path.pop();
            done.push(m.to_string());
        }
        let mut done = Vec::new();
        for m in graph.keys() {
            visit(m, &graph, &mut Vec::new(), &mut done);
        }
    }
}
