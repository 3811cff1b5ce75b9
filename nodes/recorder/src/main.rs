//! `labrig-recorder`: the episode recorder node (declared in the library:
//! [`labrig_recorder::RecorderNode`]) and its benchmark.

use labrig_recorder::{RecorderNode, RecorderTools};

fn main() -> std::process::ExitCode {
    labrig_runtime::node_main_with::<RecorderNode, RecorderTools, _>(|tool, _, _| match tool {
        RecorderTools::Bench(a) => labrig_recorder::bench::run(a),
    })
}
