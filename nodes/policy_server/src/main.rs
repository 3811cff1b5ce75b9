//! `labrig-policy`: the policy server node (declared in the library:
//! [`labrig_policy_server::PolicyServerNode`]).

fn main() -> std::process::ExitCode {
    labrig_runtime::node_main::<labrig_policy_server::PolicyServerNode>()
}
