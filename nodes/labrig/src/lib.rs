//! The `labrig` command-line interface: the one user-facing entry point (`labrig topic ...`,
//! `labrig bench ...`, `labrig demo`, and later launch/replay/inspect/export).
//! `main()` only parses arguments and calls [`cli::run`], so every command is testable.

pub mod bench;
pub mod bench_cameras;
pub mod bench_faults;
pub mod bench_latency;
pub mod bench_loop;
pub mod bench_openpi;
pub mod bench_station;
pub mod calib_capture;
pub mod cli;
pub mod demo;
pub mod episode;
pub mod experiment;
pub mod inspect;
pub mod json;
pub mod launch;
pub mod programs;
pub mod recover;
pub mod rollout;
pub mod topic;
