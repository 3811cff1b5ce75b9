//! `labrig-station`: the operator station (declared in the library: [`labrig_station::StationNode`]).

fn main() -> std::process::ExitCode {
    labrig_runtime::node_main::<labrig_station::StationNode>()
}
