//! `labrig-doctor` (`labrig doctor`): whether a rig is ready, part by part
//! ([`labrig_doctor`]).

use clap::Parser;

#[derive(Debug, Parser)]
#[command(
    name = "labrig doctor",
    about = "Whether this machine and the rig a launch config names are ready: every part checked (FR3 and its FCI version, gripper, cameras by serial, Quest, calibration, disk, clock, DDS, real-time settings, policy checkpoint), a table of part / state / fix (exit 0: ready, 3: not ready)"
)]
struct Cli {
    #[command(flatten)]
    args: labrig_doctor::DoctorArgs,
}

fn main() -> std::process::ExitCode {
    let cli = Cli::parse();
    if labrig_msgs::parse_only() {
        return std::process::ExitCode::SUCCESS;
    }
    match labrig_doctor::run(cli.args) {
        Ok(code) => code,
        Err(e) => {
            eprintln!("labrig doctor: {e:#}");
            std::process::ExitCode::from(1)
        }
    }
}
