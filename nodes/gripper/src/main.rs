//! `labrig-gripper`: the Robotiq 2F-85 node (declared in the library:
//! [`labrig_gripper::GripperNode`]), and an emulated 2F-85 to try it without one.

fn main() -> std::process::ExitCode {
    labrig_runtime::node_main_with::<labrig_gripper::GripperNode, labrig_gripper::GripperTools, _, _>(
        |tool, shutdown| tool.run(shutdown),
    )
}
