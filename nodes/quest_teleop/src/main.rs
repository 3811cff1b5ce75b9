//! `labrig-teleop`: the Quest teleoperation node (declared in the library:
//! [`labrig_quest_teleop::TeleopNode`]) and its benchmark.

use labrig_quest_teleop::{TeleopNode, TeleopTools};

fn main() -> std::process::ExitCode {
    labrig_runtime::node_main_with::<TeleopNode, TeleopTools, _>(|tool, _, _| match tool {
        TeleopTools::Bench(a) => labrig_quest_teleop::bench::run(a),
    })
}
