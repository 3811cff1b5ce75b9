//! labrig-gripper: the Robotiq 2F-85 over Modbus RTU.
//!
//! - [`registers`]: the register map, status decoding, fault codes, DROID's 0 open .. 1 closed.
//! - [`driver`]: [`driver::Robotiq2F85`], tokio-modbus over a serial port, every request with a
//!   deadline.
//! - [`emulator`]: [`emulator::Emulated2F85`], the register protocol behind a Modbus RTU
//!   server on a pseudo-terminal, for tests and for running without the hardware.

pub mod driver;
pub mod emulator;
pub mod node;
pub mod registers;
pub mod sim;

pub use driver::{DriverConfig, GripperError, Robotiq2F85};
pub use emulator::{Emulated2F85, EmulatorConfig, PtyEmulator};

use labrig_msgs::Invalid;
use labrig_runtime::{RosConfig, Shutdown};
use node::{Backend, GripperNodeConfig};

/// The gripper node: `labrig-gripper run` (`labrig_runtime::node_main_with`, with the
/// [`GripperTools`]).
#[derive(Debug)]
pub struct GripperNode;

/// `labrig-gripper run`'s own flags.
#[derive(Debug, clap::Args, serde::Serialize)]
pub struct GripperFlags {
    #[arg(long, value_enum)]
    #[serde(skip_serializing_if = "Option::is_none")]
    backend: Option<Backend>,
    /// Serial device of the 2F-85.
    #[arg(long)]
    #[serde(skip_serializing_if = "Option::is_none")]
    port: Option<String>,
}

/// `labrig-gripper`'s tools beside `run`.
#[derive(Debug, clap::Subcommand)]
pub enum GripperTools {
    /// Serve an emulated 2F-85 on a new pseudo-terminal, print its path, run until Ctrl-C.
    Emulate {
        /// An object between the fingers: closing stops at this position (0..255 counts).
        #[arg(long)]
        object_at: Option<u8>,
    },
}

impl GripperTools {
    pub async fn run(self, shutdown: Shutdown) -> anyhow::Result<std::process::ExitCode> {
        match self {
            GripperTools::Emulate { object_at } => {
                shutdown.trigger_on_signals()?;
                let emu = Emulated2F85::new(EmulatorConfig::default());
                emu.place_object(object_at);
                let pty = emu.serve_on_pty()?;
                println!("{}", pty.path());
                shutdown.wait().await;
                Ok(std::process::ExitCode::SUCCESS)
            }
        }
    }
}

impl labrig_runtime::Node for GripperNode {
    const NAME: &'static str = "labrig-gripper";
    const ABOUT: &'static str = "The Robotiq 2F-85 gripper node (Modbus RTU)";
    type Config = GripperNodeConfig;
    type Flags = GripperFlags;
    type Stats = ();

    fn ros(config: &mut GripperNodeConfig) -> &mut RosConfig {
        &mut config.ros
    }

    fn validate(config: &GripperNodeConfig) -> Result<(), Invalid> {
        config.validate()
    }

    async fn run(config: GripperNodeConfig, shutdown: Shutdown) -> anyhow::Result<()> {
        node::run(config, shutdown).await
    }
}
