//! `labrig-teleop`: the Quest teleoperation node (declared in the library:
//! [`labrig_quest_teleop::TeleopNode`]).

fn main() -> std::process::ExitCode {
    labrig_runtime::node_main::<labrig_quest_teleop::TeleopNode>()
}
