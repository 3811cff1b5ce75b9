//! labrig-policy-server: the policy server node (`labrig-policy run --checkpoint <dir>`). It
//! loads a labrig checkpoint once, takes the rig loop's requests on `/policy/request` (the
//! newest observations: robot state + the JPEG frames of the cameras the policy names) and
//! answers each with an action chunk on `/policy/chunk`. Inference runs on its own thread; a
//! request that arrives while one is computed replaces any older one still waiting (the
//! newest observation wins). The model and its arithmetic are labrig-policies'; this crate adds
//! the transport ([`serve`] has no ROS in it). With `--openpi ADDR` the same model also answers
//! openpi's websocket clients ([`openpi`]).

pub mod node;
pub mod openpi;
pub mod serve;
pub mod torchscript;

use labrig_msgs::Invalid;
use labrig_runtime::{RosConfig, Shutdown};
use node::{PolicyServerConfig, ServeStats};
use std::path::PathBuf;

/// The policy server node: `labrig-policy run` (`labrig_runtime::node_main`).
#[derive(Debug)]
pub struct PolicyServerNode;

/// `labrig-policy run`'s own flags.
#[derive(Debug, clap::Args, serde::Serialize)]
pub struct PolicyFlags {
    /// The checkpoint (`checkpoint`): a run directory (`labrig train --out`'s; its last
    /// checkpoint), a run's `checkpoints/last` or `checkpoints/step_<n>`, or an imported
    /// checkpoint directory.
    #[arg(long, conflicts_with = "torchscript")]
    #[serde(skip_serializing_if = "Option::is_none")]
    checkpoint: Option<PathBuf>,
    /// Instead of a checkpoint: a TorchScript module saved by PyTorch (`torchscript`), with
    /// `--spec`.
    #[arg(long, requires = "spec")]
    #[serde(skip_serializing_if = "Option::is_none")]
    torchscript: Option<PathBuf>,
    /// The TorchScript module's spec (`spec`, TOML: cameras, image size and range, state
    /// layout, To / Tp / Ta, action space).
    #[arg(long, requires = "torchscript")]
    #[serde(skip_serializing_if = "Option::is_none")]
    spec: Option<PathBuf>,
    /// Inference threads (`threads`; 0 = every core).
    #[arg(long)]
    #[serde(skip_serializing_if = "Option::is_none")]
    threads: Option<i32>,
    /// Also answer openpi clients (DROID's keys) on this address (`openpi`; `host:port`, or a
    /// port on 127.0.0.1).
    #[arg(long, value_name = "ADDR")]
    #[serde(skip_serializing_if = "Option::is_none")]
    openpi: Option<String>,
}

impl labrig_runtime::Node for PolicyServerNode {
    const NAME: &'static str = "labrig-policy";
    const ABOUT: &'static str = "The policy server: serves a Diffusion Policy checkpoint's or a TorchScript module's action chunks to the rig loop";
    type Config = PolicyServerConfig;
    type Flags = PolicyFlags;
    type Stats = ServeStats;

    fn ros(config: &mut PolicyServerConfig) -> &mut RosConfig {
        &mut config.ros
    }

    fn validate(config: &PolicyServerConfig) -> Result<(), Invalid> {
        config.validate()
    }

    async fn run(config: PolicyServerConfig, shutdown: Shutdown) -> anyhow::Result<ServeStats> {
        node::run(config, shutdown).await
    }
}
