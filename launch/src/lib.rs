//! labrig-launch: what starts and supervises rigs, the library under every `labrig` command
//! that runs one (the demo, rollouts, the benches, the experiment, the calibration capture) and
//! under labrig-doctor.
//!
//! - [`config`]: launch configs (`launch_configs/*.toml`), validated, with their start order.
//! - [`supervise`]: the nodes started as processes in order, watched, restarted or stopped.
//! - [`programs`]: the labrig programs installed beside the `labrig` binary, and running one.
//! - [`sim`]: the simulated rigs (the demo's, the rollouts'), supervised in the background.
//! - [`rollout`]: a policy's closed-loop success rate on the simulated rig, and its report.
//! - [`measure`]: the rig loop measured free-running (jitter, dropped frames, CPU, MB/s).
//!
//! The CLI's command modules (`nodes/labrig`) each build on this library and on the other
//! libraries, never on each other; this crate depends on no command (both checked by
//! `tests/tests/layering.rs`).

pub mod clients;
pub mod config;
pub mod measure;
pub mod programs;
pub mod rollout;
pub mod sim;
pub mod supervise;
