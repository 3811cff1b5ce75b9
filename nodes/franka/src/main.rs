//! `labrig-franka`: the FR3 arm node (declared in the library: [`labrig_franka::FrankaNode`])
//! and its benchmarks.

use labrig_franka::{FrankaNode, FrankaTools};

fn main() -> std::process::ExitCode {
    labrig_runtime::node_main_with::<FrankaNode, FrankaTools, _>(|tool, _, _| match tool {
        FrankaTools::Bench(a) => labrig_franka::bench::run(a),
        FrankaTools::BenchIk(a) => labrig_franka::bench_ik::run(a),
    })
}
