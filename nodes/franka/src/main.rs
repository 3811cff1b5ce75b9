//! `labrig-franka`: the FR3 arm node (declared in the library: [`labrig_franka::FrankaNode`]).

fn main() -> std::process::ExitCode {
    labrig_runtime::node_main::<labrig_franka::FrankaNode>()
}
