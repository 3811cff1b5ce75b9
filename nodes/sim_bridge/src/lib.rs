//! labrig-sim-bridge: the simulated rig (labrig-sim) behind the hardware's own ROS 2 topics
//! and shared-memory frames, and the `labrig-sim` program (`labrig sim ...`).
//!
//! - [`bridge`]: the bridge process (`labrig sim run`), lockstep or realtime, standing in for
//!   the franka, gripper and camera nodes; optionally the scripted expert as an action source.
//! - [`hardware`]: the simulated hardware as a state machine (commands through the safety
//!   layer, the watchdog, one period per step), unit-tested without ROS.
//! - [`bench`]: `labrig sim bench` (physics steps per second, render time per frame).
//! - [`calib`]: `labrig sim calib-capture`, a camera's calibration views taken in the sim.
//!
//! The physics, scenes, rendering, experts and replay are labrig-sim, a library with no
//! transport; this crate adds labrig-runtime (DDS, iceoryx2, tokio) and the command line.

pub mod bench;
pub mod bridge;
pub mod calib;
pub mod hardware;
