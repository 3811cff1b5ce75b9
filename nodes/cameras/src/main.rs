//! `labrig-cameras`: the camera node (declared in the library: [`labrig_cameras::CamerasNode`])
//! and `list`, the V4L2 devices this machine has.

use labrig_cameras::{CamerasNode, CamerasTools};

fn main() -> std::process::ExitCode {
    labrig_runtime::node_main_with::<CamerasNode, CamerasTools, _>(|tool, _rt, _shutdown| tool.run())
}
