//! `labrig-policy`: the policy server node (declared in the library:
//! [`labrig_policy_server::PolicyServerNode`]), and `check`, which loads a checkpoint as `run`
//! would and exits.

#[derive(Debug, clap::Subcommand)]
enum Tools {
    /// Load the checkpoint as `run` would (the same flags and --config), check it against the
    /// rig's cameras, compute one chunk, print what it is, and exit (`labrig doctor` asks this).
    Check {
        /// `run`'s flags: --checkpoint <dir> | --torchscript <model.pt> --spec <spec.toml>, --config ...
        #[arg(trailing_var_arg = true, allow_hyphen_values = true)]
        args: Vec<String>,
    },
}

fn main() -> std::process::ExitCode {
    labrig_runtime::node_main_with::<labrig_policy_server::PolicyServerNode, Tools, _>(|tool, _, _| match tool {
        Tools::Check { args } => {
            println!("{}", labrig_policy_server::node::check(&args)?);
            Ok(std::process::ExitCode::SUCCESS)
        }
    })
}
