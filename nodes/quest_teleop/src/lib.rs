//! labrig-quest-teleop (program `labrig-teleop`, `labrig teleop`): the Quest teleoperation node
//! (DROID's oculus_reader + VRPolicy lineage).
//!
//! - [`logcat`]: the headset app's logcat lines -> both controllers' poses and buttons.
//! - [`policy`]: DROID's VRPolicy: deadman, origins, forward, gains -> cartesian velocity.
//! - [`input`]: where readings come from: `adb logcat` (reconnecting), a recorded file played
//!   back at its own timing, or the keyboard ([`keyboard`]: a virtual controller).
//! - [`node`]: the ROS 2 node: `/teleop/state`, `/teleop/action`, `/rig/request`.

pub mod bench;
pub mod input;
pub mod keyboard;
pub mod logcat;
pub mod node;
pub mod policy;

use input::InputKind;
use labrig_msgs::Invalid;
use labrig_runtime::node::is_false;
use labrig_runtime::{RosConfig, Shutdown};
use node::{TeleopConfig, TeleopStats};
use std::path::{Path, PathBuf};

/// The teleop node: `labrig-teleop run` (`labrig_runtime::node_main`).
#[derive(Debug)]
pub struct TeleopNode;

/// `labrig-teleop run`'s own flags; each sets the config key named with it.
#[derive(Debug, clap::Args, serde::Serialize)]
pub struct TeleopFlags {
    /// Where lines come from: the headset over adb, a recorded logcat file, or the keyboard.
    #[arg(long, value_enum)]
    #[serde(rename = "input.kind", skip_serializing_if = "Option::is_none")]
    input: Option<InputKind>,
    /// Playback: the recorded logcat file (implies --input playback).
    #[arg(long)]
    #[serde(rename = "input.file", skip_serializing_if = "Option::is_none")]
    file: Option<PathBuf>,
    /// Playback time scale.
    #[arg(long)]
    #[serde(rename = "input.speed", skip_serializing_if = "Option::is_none")]
    speed: Option<f64>,
    /// Playback: start again at the end.
    #[arg(long)]
    #[serde(rename = "input.repeat", skip_serializing_if = "is_false")]
    repeat: bool,
    /// adb: the headset's serial or ip:port.
    #[arg(long)]
    #[serde(rename = "input.device", skip_serializing_if = "Option::is_none")]
    device: Option<String>,
    /// The controller that drives the arm: right or left.
    #[arg(long)]
    #[serde(rename = "policy.hand", skip_serializing_if = "Option::is_none")]
    hand: Option<String>,
    /// Exit a second after a playback ends.
    #[arg(long)]
    #[serde(rename = "input.exit_at_end", skip_serializing_if = "is_false")]
    exit_at_end: bool,
}

impl labrig_runtime::Node for TeleopNode {
    const NAME: &'static str = "labrig-teleop";
    const ABOUT: &'static str =
        "Quest controller (logcat) -> DROID's VRPolicy -> /teleop/action, /teleop/state, /rig/request";
    type Config = TeleopConfig;
    type Flags = TeleopFlags;
    type Stats = TeleopStats;

    fn ros(config: &mut TeleopConfig) -> &mut RosConfig {
        &mut config.ros
    }

    fn apply(f: &TeleopFlags, cfg: &mut TeleopConfig, file: Option<&Path>) {
        if f.file.is_some() {
            // A trace named on the command line is played (and is relative to the working
            // directory, as given).
            cfg.input.kind = InputKind::Playback;
        } else if let (Some(trace), Some(dir)) = (cfg.input.file.as_mut(), file.and_then(Path::parent))
            && trace.is_relative()
        {
            // A trace named in a config file is relative to that file.
            *trace = dir.join(&*trace);
        }
    }

    fn validate(config: &TeleopConfig) -> Result<(), Invalid> {
        config.validate()
    }

    async fn run(config: TeleopConfig, shutdown: Shutdown) -> anyhow::Result<TeleopStats> {
        node::run(config, shutdown).await
    }
}

/// `labrig-teleop`'s tools beside `run`.
#[derive(Debug, clap::Subcommand)]
pub enum TeleopTools {
    /// The node's latency, logcat line in -> action out (`labrig bench teleop`).
    Bench(bench::TeleopArgs),
}
