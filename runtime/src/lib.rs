//! labrig-runtime: what every labrig node shares.
//!
//! - [`config`]: typed TOML config, unknown keys rejected with the key named, parse-then-validate.
//! - [`devices`]: the real rig's devices, handed by the launcher to every node.
//! - [`node`]: the one shape of a node: a [`node::Node`] declaration and `node_main`.
//! - [`lifecycle`]: SIGINT/SIGTERM -> a [`lifecycle::Shutdown`] token every loop watches.
//! - [`clock`]: one [`clock::Clock`]: wall time on hardware, sim time from `/clock`, or a mock.
//! - [`ros`]: ROS 2 through ros2-client with explicit QoS, DDS on loopback unless configured
//!   otherwise, typed publishers/subscriptions/services over labrig-msgs' codec.
//! - [`frames`]: iceoryx2 zero-copy camera frame channels with a [`frames::FrameHeader`].
//! - [`bench`]: what the benchmarks share (CPU seconds from /proc, percentile summaries).
//! - [`logging`]: tracing setup with the project's level policy.
//!
//! Depends on labrig-msgs, ros2-client/rustdds, iceoryx2, tokio. Must never depend on tch,
//! mujoco or opencv (checked by `tests/tests/layering.rs`).

pub mod bench;
pub mod clock;
pub mod config;
pub mod devices;
pub mod frames;
pub mod lifecycle;
pub mod logging;
pub mod node;
pub mod ros;

pub use clock::Clock;
pub use config::{ConfigError, RosConfig, load_config};
pub use lifecycle::{PriorityError, Shutdown, realtime_priority};
pub use node::{Node, node_main, node_main_with};
