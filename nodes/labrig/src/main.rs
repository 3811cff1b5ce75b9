use clap::Parser;

fn main() -> std::process::ExitCode {
    let cli = labrig::cli::Cli::parse();
    labrig_runtime::logging::init(if cli.verbose { "debug" } else { "info" });
    match labrig::cli::run(cli) {
        Ok(code) => code,
        Err(e) => {
            eprintln!("error: {e:#}");
            std::process::ExitCode::from(1)
        }
    }
}
