//! labrig-recorder: the recorder node (DDS topics + shared-memory frames -> one episode per
//! `/rig/episode` start/end). The episode format itself (writing, reading, inspection,
//! recovery) is labrig-episode; this crate adds only the transport.

pub mod bench;
mod filer;
pub mod node;

use labrig_msgs::Invalid;
use labrig_runtime::{RosConfig, Shutdown};
use node::RecorderConfig;
use std::path::PathBuf;

/// The recorder node: `labrig-recorder run` (`labrig_runtime::node_main`).
#[derive(Debug)]
pub struct RecorderNode;

/// `labrig-recorder run`'s own flags.
#[derive(Debug, clap::Args, serde::Serialize)]
pub struct RecorderFlags {
    /// Where episodes go (`root`).
    #[arg(long)]
    #[serde(skip_serializing_if = "Option::is_none")]
    root: Option<PathBuf>,
}

impl labrig_runtime::Node for RecorderNode {
    const NAME: &'static str = "labrig-recorder";
    const ABOUT: &'static str = "Records the rig's episodes as DROID-format MCAP";
    type Config = RecorderConfig;
    type Flags = RecorderFlags;
    type Stats = ();

    fn ros(config: &mut RecorderConfig) -> &mut RosConfig {
        &mut config.ros
    }

    fn validate(config: &RecorderConfig) -> Result<(), Invalid> {
        config.validate()
    }

    async fn run(config: RecorderConfig, shutdown: Shutdown) -> anyhow::Result<()> {
        node::run(config, shutdown).await
    }
}

/// `labrig-recorder`'s tools beside `run`.
#[derive(Debug, clap::Subcommand)]
pub enum RecorderTools {
    /// Recording an episode: writer MB/s, CPU, JPEG encoding (`labrig bench record`).
    Bench(bench::RecordArgs),
}
