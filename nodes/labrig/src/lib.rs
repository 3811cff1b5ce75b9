//! The `labrig` command-line interface: the one user-facing entry point. `main()` only parses
//! arguments and calls [`cli::run`], which dispatches to one module per command (`demo`,
//! `rollout`, `launch`, `bench_*`, ...) or execs the program beside it that owns the command
//! (`labrig replay`, `labrig export`, `labrig train`, ...).
//!
//! Each command module builds on the launch library (`labrig_launch`: launch configs, the
//! supervisor, the simulated rigs, rollouts) and the other libraries, and never imports another
//! command module (`tests/tests/layering.rs` checks it); `cli` alone knows them all.

pub mod bench;
pub mod bench_cameras;
pub mod bench_faults;
pub mod bench_latency;
pub mod bench_loop;
pub mod bench_openpi;
pub mod bench_soak;
pub mod bench_station;
pub mod calib_capture;
pub mod cli;
pub mod demo;
pub mod episode;
pub mod experiment;
pub mod formats;
pub mod inspect;
pub mod launch;
pub mod recover;
pub mod rollout;
pub mod topic;
