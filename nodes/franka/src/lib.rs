//! labrig-franka: the FR3 arm node. The arm's maths (kinematics, IK, safety layer) is
//! labrig-arm; this crate adds the hardware behind a trait and the ROS node around it.
//!
//! - [`backend`]: [`backend::ArmBackend`], what the node drives.
//! - [`fci`]: a real FR3 (or franka-sim) through franka-rs over the FCI.
//! - [`sim`]: the sim bridge's arm under `<prefix>/arm/*`.
//! - [`node`]: `/arm/command` -> safety layer -> backend; state, target, joint states, tf.

pub mod backend;
pub mod bench;
pub mod bench_ik;
pub mod fci;
pub mod node;
pub mod sim;

use labrig_msgs::Invalid;
use labrig_runtime::node::{is_false, negated};
use labrig_runtime::{RosConfig, Shutdown};
use node::{BackendKind, FrankaNodeConfig};

/// The FR3 arm node: `labrig-franka run` (`labrig_runtime::node_main`).
#[derive(Debug)]
pub struct FrankaNode;

/// `labrig-franka run`'s own flags; each sets the config key of its name.
#[derive(Debug, clap::Args, serde::Serialize)]
pub struct FrankaFlags {
    /// fci: a real FR3 or franka-sim; sim: the sim bridge run with `--hardware-prefix /sim`.
    #[arg(long, value_enum)]
    #[serde(skip_serializing_if = "Option::is_none")]
    backend: Option<BackendKind>,
    /// The FR3's FCI address (franka-sim: 127.0.0.1).
    #[arg(long)]
    #[serde(skip_serializing_if = "Option::is_none")]
    robot_ip: Option<String>,
    /// Run without a realtime kernel (franka-sim, a development machine): fci.realtime = false.
    #[arg(long)]
    #[serde(rename = "fci.realtime", skip_serializing_if = "is_false", serialize_with = "negated")]
    no_realtime: bool,
    /// Keep trying to reach the FCI this long at start (a booting robot or simulator).
    #[arg(long)]
    #[serde(skip_serializing_if = "Option::is_none")]
    connect_timeout_s: Option<f64>,
}

impl labrig_runtime::Node for FrankaNode {
    const NAME: &'static str = "labrig-franka";
    const ABOUT: &'static str = "The FR3 arm node: /arm/command -> safety layer -> FCI";
    type Config = FrankaNodeConfig;
    type Flags = FrankaFlags;
    type Stats = ();

    fn ros(config: &mut FrankaNodeConfig) -> &mut RosConfig {
        &mut config.ros
    }

    fn validate(config: &FrankaNodeConfig) -> Result<(), Invalid> {
        config.validate()
    }

    async fn run(config: FrankaNodeConfig, shutdown: Shutdown) -> anyhow::Result<()> {
        node::serve(config, shutdown).await
    }
}

/// `labrig-franka`'s tools beside `run`.
#[derive(Debug, clap::Subcommand)]
pub enum FrankaTools {
    /// The node against franka-sim: command-to-backend latency (`labrig bench franka`).
    Bench(bench::FrankaArgs),
    /// The node's command path per tick: URDF FK + Jacobian, IK, the safety filter (`labrig bench ik`).
    BenchIk(bench_ik::IkArgs),
}
