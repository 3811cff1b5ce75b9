//! `labrig-gripper`: the Robotiq 2F-85 node (declared in the library:
//! [`labrig_gripper::GripperNode`]), and an emulated 2F-85 to try it without one.

use labrig_gripper::{GripperNode, GripperTools};

fn main() -> std::process::ExitCode {
    labrig_runtime::node_main_with::<GripperNode, GripperTools, _>(|tool, rt, shutdown| rt.block_on(tool.run(shutdown)))
}
