//! `labrig-control`: the rig loop node (declared in the library: [`labrig_control::ControlNode`]).

fn main() -> std::process::ExitCode {
    labrig_runtime::node_main::<labrig_control::ControlNode>()
}
