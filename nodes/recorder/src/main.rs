//! `labrig-recorder`: the episode recorder node (declared in the library:
//! [`labrig_recorder::RecorderNode`]).

fn main() -> std::process::ExitCode {
    labrig_runtime::node_main::<labrig_recorder::RecorderNode>()
}
