//! Argument parsing and dispatch.

use clap::{Parser, Subcommand};
use labrig_launch::programs::{node, node_renamed};
use std::process::ExitCode;

#[derive(Debug, Parser)]
#[command(name = "labrig", version, about = "labrig: a ROS 2-integrated stack for a DROID-style robot rig")]
pub struct Cli {
    /// Log at debug level (RUST_LOG overrides).
    #[arg(long, short, global = true)]
    pub verbose: bool,
    #[command(subcommand)]
    pub command: Command,
}

#[derive(Debug, Subcommand)]
pub enum Command {
    /// Inspect ROS 2 topics of any node (no ROS installation needed).
    #[command(subcommand)]
    Topic(TopicCommand),
    /// Benchmarks that print figures.
    #[command(subcommand)]
    Bench(BenchCommand),
    /// Start and supervise a rig described by a launch config (launch_configs/*.toml).
    Launch(crate::launch::LaunchArgs),
    /// What an episode holds and how well it was recorded (exit 3 when something is flagged).
    Inspect(crate::inspect::InspectArgs),
    /// Tell the rig loop to start or end an episode, or send the idle arm home (start | success |
    /// failure | discard | stop | reset).
    Episode(crate::episode::EpisodeArgs),
    /// Make an episode whose recorder died whole again (up to its last closed chunk).
    Recover(crate::recover::RecoverArgs),
    /// The main job on a fresh machine: the simulated rig records scripted pick-and-place episodes.
    Demo(crate::demo::DemoArgs),
    /// A policy's closed-loop success rate in the simulated rig: seeded rollouts, each a
    /// recorded episode judged by the sim (`labrig rollout --policy <checkpoint>`).
    Rollout(Box<labrig_launch::rollout::RolloutArgs>),
    /// Experiments that run end to end on the simulated rig: `labrig experiment retrieval
    /// [--config experiments/retrieval/full.toml] [--out DIR]` (the paper's co-training result).
    #[command(subcommand)]
    Experiment(crate::experiment::ExperimentCommand),
    /// Whether this machine and the rig a launch config names are ready: every part checked
    /// (FR3 and its FCI version, gripper, cameras by serial, Quest, calibration, disk, clock,
    /// DDS, real-time settings, policy checkpoint), a table of part / state / fix (exit 0:
    /// ready, 3: not ready).
    #[command(disable_help_flag = true)]
    Doctor {
        /// `[--rig <launch config>] [--json]` (see `labrig doctor --help`; `labrig-doctor`).
        #[arg(trailing_var_arg = true, allow_hyphen_values = true)]
        args: Vec<String>,
    },
    /// The simulated rig (MuJoCo): `labrig sim run|snapshot|eval|bench ...` (see `labrig sim --help`).
    #[command(disable_help_flag = true)]
    Sim {
        /// Arguments for labrig-sim.
        #[arg(trailing_var_arg = true, allow_hyphen_values = true)]
        args: Vec<String>,
    },
    /// Camera calibration (ChArUco + hand-eye): `labrig calibrate --sim --camera all [--json]`,
    /// `labrig calibrate board --out board.png`, `labrig calibrate solve <capture>`,
    /// `labrig calibrate check --sim --camera ext1` (see `labrig calibrate --help`).
    #[command(disable_help_flag = true)]
    Calibrate {
        /// Arguments for labrig-calibrate.
        #[arg(trailing_var_arg = true, allow_hyphen_values = true)]
        args: Vec<String>,
    },
    /// The paper's dataset tools: `labrig dataset index <root>... --out <index>`, `labrig
    /// dataset retrieve --index <index> --target <episodes|index|target.toml> --align
    /// object,skill,camPose,objTex,objSpat --out manifest.json` (see `labrig dataset --help`).
    #[command(disable_help_flag = true)]
    Dataset {
        /// Arguments for labrig-dataset.
        #[arg(trailing_var_arg = true, allow_hyphen_values = true)]
        args: Vec<String>,
    },
    /// Replay a recorded episode against the simulated rig: `labrig replay <episode> --sim
    /// [--json] [--max-tcp-error-m 0.005 ...]` (exit 5 when it deviates beyond the tolerances).
    #[command(disable_help_flag = true)]
    Replay {
        /// The episode, `--sim`, and the options of `labrig-sim replay`.
        #[arg(trailing_var_arg = true, allow_hyphen_values = true)]
        args: Vec<String>,
    },
    /// Export episodes to another format: `labrig export droid <episode|dir> <out_dir>
    /// [--overwrite] [--json]` writes DROID's raw layout (trajectory.h5, one MP4 per camera,
    /// metadata_<uuid>.json); `labrig export droid-mcap ...` DROID's MCAP layout (trajectory.mcap);
    /// `labrig export lerobot <episode|dir>... <out>` a LeRobot dataset (format v3.0).
    #[command(disable_help_flag = true)]
    Export {
        /// The format (`droid`, `droid-mcap` or `lerobot`), then its options.
        #[arg(trailing_var_arg = true, allow_hyphen_values = true)]
        args: Vec<String>,
    },
    /// Import episodes from another format: `labrig import droid <droid_episode|dir>
    /// [--out episodes]` (DROID's raw layout), `labrig import droid-mcap <trajectory.mcap|dir>`
    /// (DROID's MCAP layout) or `labrig import lerobot <root> <out>` (a LeRobot dataset, v3.0 or
    /// v2.1) writes MCAP episodes in the recorder's layout.
    #[command(disable_help_flag = true)]
    Import {
        /// The format (`droid`, `droid-mcap` or `lerobot`), then its options.
        #[arg(trailing_var_arg = true, allow_hyphen_values = true)]
        args: Vec<String>,
    },
    /// The FR3 arm node: `labrig franka run --robot-ip 172.16.0.2`, or `--backend sim` in front
    /// of the sim bridge (see `labrig franka run --help`).
    #[command(disable_help_flag = true)]
    Franka {
        /// Arguments for labrig-franka.
        #[arg(trailing_var_arg = true, allow_hyphen_values = true)]
        args: Vec<String>,
    },
    /// The Quest teleop node: `labrig teleop run [--device <serial|ip:5555>]` (adb), or
    /// `--file trace.logcat` to play a recorded controller (see `labrig teleop run --help`).
    #[command(disable_help_flag = true)]
    Teleop {
        /// Arguments for labrig-teleop.
        #[arg(trailing_var_arg = true, allow_hyphen_values = true)]
        args: Vec<String>,
    },
    /// The Robotiq 2F-85 node: `labrig gripper run --port /dev/ttyUSB0`, or `labrig gripper
    /// emulate` for a 2F-85 on a pseudo-terminal (see `labrig gripper --help`).
    #[command(disable_help_flag = true)]
    Gripper {
        /// Arguments for labrig-gripper.
        #[arg(trailing_var_arg = true, allow_hyphen_values = true)]
        args: Vec<String>,
    },
    /// The 20 Hz rig loop: `labrig control run [--source scripted|hold|teleop] [--clock sim|wall]`
    /// (see `labrig control run --help`).
    #[command(disable_help_flag = true)]
    Control {
        /// Arguments for labrig-control.
        #[arg(trailing_var_arg = true, allow_hyphen_values = true)]
        args: Vec<String>,
    },
    /// Train a Diffusion Policy on episodes: `labrig train --target <episodes> [--cotrain
    /// <episodes|manifest>] [--w 0.5] [--preset paper_dp|small|<file.toml>] --out <run> --steps N
    /// [--resume]` (see `labrig train --help`; `labrig-policies train`).
    #[command(disable_help_flag = true)]
    Train {
        /// The options of `labrig-policies train`.
        #[arg(trailing_var_arg = true, allow_hyphen_values = true)]
        args: Vec<String>,
    },
    /// Policies: `labrig policy run --checkpoint <run|ckpt>` (the policy server: serves action
    /// chunks to the rig loop), `labrig policy infer <ckpt> --obs <obs.safetensors> --noise
    /// <noise.safetensors> --out <actions.safetensors>`, `labrig policy import-lerobot <dir>
    /// --out <ckpt>` (see `labrig policy --help`).
    #[command(disable_help_flag = true)]
    Policy {
        /// `run`, `infer` or `import-lerobot`, then its options.
        #[arg(trailing_var_arg = true, allow_hyphen_values = true)]
        args: Vec<String>,
    },
    /// The camera node: `labrig cameras run --config <cameras.toml>` or `--camera
    /// ext1=<zed:SERIAL|realsense:SERIAL|v4l2:SERIAL|/dev/videoN|http://...|rtsp://...|file|testsrc>`;
    /// `labrig cameras list` names the V4L2 devices found (see `labrig cameras --help`).
    #[command(disable_help_flag = true)]
    Cameras {
        /// Arguments for labrig-cameras.
        #[arg(trailing_var_arg = true, allow_hyphen_values = true)]
        args: Vec<String>,
    },
    /// The operator station, a web page for collecting demos: `labrig station [--listen
    /// 127.0.0.1:8080] [--root episodes] [--token T]` (see `labrig station run --help`).
    #[command(disable_help_flag = true)]
    Station {
        /// Arguments for labrig-station (`run` is implied).
        #[arg(trailing_var_arg = true, allow_hyphen_values = true)]
        args: Vec<String>,
    },
    /// The episode recorder: `labrig recorder run --root episodes` (see `labrig recorder run --help`).
    #[command(disable_help_flag = true)]
    Recorder {
        /// Arguments for labrig-recorder.
        #[arg(trailing_var_arg = true, allow_hyphen_values = true)]
        args: Vec<String>,
    },
}

/// Runs `labrig-sim` (built beside this binary; the only program that links MuJoCo) with `args`.
pub fn sim(args: &[String]) -> anyhow::Result<ExitCode> {
    node("labrig-sim", "labrig sim", args)
}

/// `labrig calibrate capture ...` takes a live rig's views here (this crate talks to the rig);
/// everything else goes to `labrig-calibrate` (the crate that links OpenCV), which runs
/// `labrig calibrate capture` itself for `--rig`.
pub fn calibrate(args: &[String]) -> anyhow::Result<ExitCode> {
    if args.first().map(String::as_str) == Some("capture") {
        #[derive(Debug, clap::Parser)]
        #[command(name = "labrig calibrate capture", about = "Take one camera's calibration views on a live rig")]
        struct Capture {
            #[command(flatten)]
            args: crate::calib_capture::CaptureArgs,
        }
        let parsed = <Capture as clap::Parser>::try_parse_from(args.iter()).unwrap_or_else(|e| e.exit());
        if labrig_msgs::parse_only() {
            return Ok(ExitCode::SUCCESS);
        }
        return crate::calib_capture::run(parsed.args);
    }
    node("labrig-calibrate", "labrig calibrate", args)
}

/// `labrig replay <episode> --sim ...` -> `labrig-sim replay <episode> --sim ...` (the
/// simulated rig is the only replay target so far; `--sim` says so explicitly, and
/// `labrig-sim replay` documents it among its flags, so `labrig replay --help` lists it).
pub fn replay(args: &[String]) -> anyhow::Result<ExitCode> {
    let help = args.iter().any(|a| a == "--help" || a == "-h");
    anyhow::ensure!(
        help || args.iter().any(|a| a == "--sim"),
        "labrig replay needs --sim: episodes replay against the simulated rig (no real-robot replay)"
    );
    node("labrig-sim", "labrig", &tool("replay", args.to_vec()))
}

/// `labrig policy --help` (and `labrig policy` alone): its commands, which two programs serve
/// (`run` is labrig-policy, the others labrig-policies), so neither program's own help lists them.
fn policy_help() -> clap::Command {
    clap::Command::new("policy")
        .bin_name("labrig policy")
        .subcommand_required(true)
        .disable_help_subcommand(true)
        .about("Policies: the policy server, and one checkpoint's chunk or import")
        .subcommand_value_name("COMMAND")
        .subcommand(clap::Command::new("run").about(
            "The policy server: serves a checkpoint's or a TorchScript module's action chunks to the rig loop \
             (`labrig policy run --checkpoint <run|checkpoint>`; see `labrig policy run --help`)",
        ))
        .subcommand(clap::Command::new("infer").about(
            "One action chunk from a checkpoint for an observation and initial noise (safetensors; see \
             `labrig policy infer --help`)",
        ))
        .subcommand(clap::Command::new("import-lerobot").about(
            "Convert a LeRobot Diffusion Policy directory (save_pretrained's) into a labrig checkpoint (see \
             `labrig policy import-lerobot --help`)",
        ))
        .after_help("Training is `labrig train`, the latency benchmark `labrig bench policy`.")
}

/// `labrig export|import <format> ...` -> `labrig-droid export|import ...` (DROID's raw format
/// is the one format so far; labrig-droid is the program that links libhdf5).
pub fn convert(verb: &str, args: &[String]) -> anyhow::Result<ExitCode> {
    use crate::formats::{FORMATS, find, names};
    match args.first().map(String::as_str) {
        Some("--help" | "-h") | None => {
            let about: Vec<String> = FORMATS.iter().map(|f| format!("{} = {}", f.name, f.about)).collect();
            println!("usage: labrig {verb} {} ... (formats: {})\n", names("|"), about.join(", "));
            let first = &FORMATS[0];
            node_renamed(
                first.program,
                first.subcommand(verb),
                &format!("labrig {verb} {}", first.name),
                &["--help".to_owned()],
            )
        }
        Some(name) => match find(name) {
            Some(f) => node_renamed(f.program, f.subcommand(verb), &format!("labrig {verb} {}", f.name), &args[1..]),
            None => anyhow::bail!("labrig {verb}: unknown format `{name}` (formats: {})", names(", ")),
        },
    }
}

#[derive(Debug, Subcommand)]
pub enum TopicCommand {
    /// List the topics seen on the DDS graph with their types.
    List(crate::topic::ListArgs),
    /// Print the messages of a topic.
    Echo(crate::topic::EchoArgs),
    /// Measure the publishing rate of a topic.
    Hz(crate::topic::HzArgs),
    /// A topic's publishers and subscriptions in other processes, with the type hash each
    /// announced and whether it is labrig's (exit code 3 when one differs).
    Info(crate::topic::InfoArgs),
    /// The RIHS01 type hash (REP 2011) of every message type labrig knows, as rosidl computes it.
    Hashes(crate::topic::HashesArgs),
}

#[derive(Debug, Subcommand)]
pub enum BenchCommand {
    /// Camera frames over iceoryx2 shared memory between processes.
    Shm(crate::bench::ShmArgs),
    /// The rig loop free-running for minutes: tick jitter, missed ticks, dropped frames, recorder CPU, MB/s.
    Loop(labrig_launch::measure::LoopArgs),
    /// Whether the operator station is felt: the rig's loop jitter, skew and dropped frames
    /// alone vs with the station, its page and three Foxglove clients.
    Station(crate::bench_station::StationArgs),
    /// An operator's session, measured for an hour (or --minutes): every process's memory,
    /// descriptors, threads and CPU every 10 s, the loop's jitter per 5-minute window, episodes
    /// inspected; a JSON report, a picture and a verdict (growth per hour, drift, disk per day).
    Soak(crate::bench_soak::SoakArgs),
    /// The soak's planted-growth helper (a process that grows at a steady rate).
    #[command(hide = true)]
    Grow(crate::bench_soak::GrowArgs),
    /// Camera streams (ffmpeg MJPEG servers) through labrig-cameras into the loop's observation:
    /// delivered/lost frames, capture -> observation latency, skew, CPU.
    Cameras(crate::bench_cameras::CamerasBenchArgs),
    /// ZED rectification's cost per frame (YUYV side by side -> eye RGB -> rectified), and the
    /// share of a core three ZEDs at 30 fps take; `labrig-cameras bench-rectify`.
    #[command(disable_help_flag = true)]
    Rectify {
        /// The options of `labrig-cameras bench-rectify` (see `labrig bench rectify --help`).
        #[arg(trailing_var_arg = true, allow_hyphen_values = true)]
        args: Vec<String>,
    },
    /// Recording an episode: writer MB/s, CPU, JPEG encoding (synthetic 5-camera rig); `labrig-recorder bench`.
    #[command(disable_help_flag = true)]
    Record {
        /// The options of `labrig-recorder bench` (see `labrig bench record --help`).
        #[arg(trailing_var_arg = true, allow_hyphen_values = true)]
        args: Vec<String>,
    },
    /// The franka node against franka-sim: command-to-backend latency (in the node and round trip); `labrig-franka bench`.
    #[command(disable_help_flag = true)]
    Franka {
        /// The options of `labrig-franka bench` (see `labrig bench franka --help`).
        #[arg(trailing_var_arg = true, allow_hyphen_values = true)]
        args: Vec<String>,
    },
    /// The franka node's command path per tick: URDF FK + Jacobian, IK, the safety filter; `labrig-franka bench-ik`.
    #[command(disable_help_flag = true)]
    Ik {
        /// The options of `labrig-franka bench-ik` (see `labrig bench ik --help`).
        #[arg(trailing_var_arg = true, allow_hyphen_values = true)]
        args: Vec<String>,
    },
    /// DROID export and import throughput (steps/s) of one episode: `labrig bench export
    /// <episode> [--repeat 5] [--json]`.
    #[command(disable_help_flag = true)]
    Export {
        /// The episode, then the options of `labrig-droid bench`.
        #[arg(trailing_var_arg = true, allow_hyphen_values = true)]
        args: Vec<String>,
    },
    /// The Quest teleop node: logcat line in -> action out, p50/p99 (a recorded trace played); `labrig-teleop bench`.
    #[command(disable_help_flag = true)]
    Teleop {
        /// The options of `labrig-teleop bench` (see `labrig bench teleop --help`).
        #[arg(trailing_var_arg = true, allow_hyphen_values = true)]
        args: Vec<String>,
    },
    /// Faults injected into the simulated rig (recorder killed, disk full, DDS stopped): data
    /// lost, time to detect, time to recover.
    Faults(crate::bench_faults::FaultArgs),
    /// The Diffusion Policy: one chunk's latency (encoders, U-Net step, chunk; p50/p99) and
    /// training samples/s per preset, beside LeRobot's PyTorch model where its venv exists;
    /// `labrig-policies bench`.
    #[command(disable_help_flag = true)]
    Policy {
        /// The options of `labrig-policies bench` (see `labrig bench policy --help`).
        #[arg(trailing_var_arg = true, allow_hyphen_values = true)]
        args: Vec<String>,
    },
    /// openpi's websocket protocol: the round trip on loopback (labrig's and openpi's own
    /// server), and the 20 Hz loop with a remote policy 0-1000 ms away (held ticks, skipped rows).
    Openpi(crate::bench_openpi::OpenpiBenchArgs),
    /// Policies under inference latency (lockstep): delay x execution mode (wait, replace,
    /// exponential, rtc) x rows per chunk on tuning seeds, then the best settings on judging
    /// seeds; success, held ticks, jerk at chunk switches; resumable.
    Latency(Box<crate::bench_latency::LatencyArgs>),
    /// (internal) one publisher process of `bench shm`.
    #[command(hide = true)]
    ShmPublisher(crate::bench::ShmPublisherArgs),
}

impl Command {
    /// Whether the command hands its arguments to another labrig program.
    fn forwards(&self) -> bool {
        use BenchCommand as B;
        match self {
            Command::Bench(b) => {
                matches!(
                    b,
                    B::Record { .. }
                        | B::Franka { .. }
                        | B::Ik { .. }
                        | B::Export { .. }
                        | B::Teleop { .. }
                        | B::Policy { .. }
                )
            }
            Command::Sim { .. }
            | Command::Calibrate { .. }
            | Command::Dataset { .. }
            | Command::Replay { .. }
            | Command::Export { .. }
            | Command::Import { .. }
            | Command::Franka { .. }
            | Command::Teleop { .. }
            | Command::Gripper { .. }
            | Command::Control { .. }
            | Command::Train { .. }
            | Command::Policy { .. }
            | Command::Cameras { .. }
            | Command::Station { .. }
            | Command::Recorder { .. }
            | Command::Doctor { .. } => true,
            Command::Topic(_)
            | Command::Launch(_)
            | Command::Inspect(_)
            | Command::Episode(_)
            | Command::Recover(_)
            | Command::Demo(_)
            | Command::Rollout(_)
            | Command::Experiment(_) => false,
        }
    }
}

/// Runs a command; the exit code tells scripts what happened.
pub fn run(cli: Cli) -> anyhow::Result<ExitCode> {
    // LABRIG_PARSE_ONLY: a command of this program is parsed (done); one that forwards to
    // another program goes there, which parses its part the same way.
    if labrig_msgs::parse_only() && !cli.command.forwards() {
        return Ok(ExitCode::SUCCESS);
    }
    match cli.command {
        Command::Topic(TopicCommand::List(a)) => crate::topic::list(a),
        Command::Topic(TopicCommand::Echo(a)) => crate::topic::echo(a),
        Command::Topic(TopicCommand::Hz(a)) => crate::topic::hz(a),
        Command::Topic(TopicCommand::Info(a)) => crate::topic::info(a),
        Command::Topic(TopicCommand::Hashes(a)) => crate::topic::hashes(a),
        Command::Bench(BenchCommand::Shm(a)) => crate::bench::shm(a),
        Command::Bench(BenchCommand::ShmPublisher(a)) => crate::bench::shm_publisher(a),
        Command::Bench(BenchCommand::Ik { args }) => {
            node_renamed("labrig-franka", "bench-ik", "labrig bench ik", &args)
        }
        Command::Bench(BenchCommand::Franka { args }) => {
            node_renamed("labrig-franka", "bench", "labrig bench franka", &args)
        }
        Command::Bench(BenchCommand::Rectify { args }) => {
            node_renamed("labrig-cameras", "bench-rectify", "labrig bench rectify", &args)
        }
        Command::Bench(BenchCommand::Record { args }) => {
            node_renamed("labrig-recorder", "bench", "labrig bench record", &args)
        }
        Command::Bench(BenchCommand::Loop(a)) => crate::bench_loop::run(a),
        Command::Bench(BenchCommand::Station(a)) => crate::bench_station::run(a),
        Command::Bench(BenchCommand::Soak(a)) => crate::bench_soak::run(&a),
        Command::Bench(BenchCommand::Grow(a)) => crate::bench_soak::grow(&a),
        Command::Bench(BenchCommand::Cameras(a)) => crate::bench_cameras::run(a),
        Command::Bench(BenchCommand::Faults(a)) => crate::bench_faults::run(a),
        Command::Bench(BenchCommand::Openpi(a)) => crate::bench_openpi::run(a),
        Command::Bench(BenchCommand::Latency(a)) => crate::bench_latency::run(*a),
        Command::Bench(BenchCommand::Teleop { args }) => {
            node_renamed("labrig-teleop", "bench", "labrig bench teleop", &args)
        }
        Command::Bench(BenchCommand::Policy { args }) => {
            node_renamed("labrig-policies", "bench", "labrig bench policy", &args)
        }
        Command::Train { args } => node("labrig-policies", "labrig", &tool("train", args)),
        Command::Policy { args } => match args.first().map(String::as_str) {
            Some("infer" | "import-lerobot") => node("labrig-policies", "labrig policy", &args),
            Some("run") => node("labrig-policy", "labrig policy", &args),
            Some("--help" | "-h") => {
                policy_help().print_help()?;
                Ok(ExitCode::SUCCESS)
            }
            None => {
                eprint!("{}", policy_help().render_help());
                Ok(ExitCode::from(2))
            }
            Some(other) => {
                anyhow::bail!("labrig policy: unknown command `{other}` (commands: run, infer, import-lerobot)")
            }
        },
        Command::Recover(a) => crate::recover::run(a),
        Command::Inspect(a) => crate::inspect::run(a),
        Command::Launch(a) => crate::launch::run(a),
        Command::Doctor { args } => node("labrig-doctor", "labrig doctor", &args),
        Command::Demo(a) => crate::demo::run(a),
        Command::Rollout(a) => crate::rollout::run(*a),
        Command::Experiment(a) => crate::experiment::run(a),
        Command::Episode(a) => crate::episode::run(a),
        Command::Replay { args } => replay(&args),
        Command::Export { args } => convert("export", &args),
        Command::Import { args } => convert("import", &args),
        Command::Bench(BenchCommand::Export { args }) => {
            node_renamed("labrig-droid", "bench", "labrig bench export", &args)
        }
        Command::Sim { args } => sim(&args),
        Command::Calibrate { args } => calibrate(&args),
        Command::Dataset { args } => node("labrig-dataset", "labrig dataset", &args),
        Command::Gripper { args } => node("labrig-gripper", "labrig gripper", &args),
        Command::Franka { args } => node("labrig-franka", "labrig franka", &args),
        Command::Teleop { args } => node("labrig-teleop", "labrig teleop", &args),
        Command::Cameras { args } => node("labrig-cameras", "labrig cameras", &args),
        Command::Control { args } => node("labrig-control", "labrig control", &args),
        Command::Recorder { args } => node("labrig-recorder", "labrig recorder", &args),
        Command::Station { args } => match args.first().map(String::as_str) {
            Some("run" | "help" | "--help" | "-h" | "--version" | "-V") => {
                node("labrig-station", "labrig station", &args)
            }
            _ => node("labrig-station", "labrig station", &tool("run", args)),
        },
    }
}

/// `<tool> <args...>`: a node program's tool invocation.
fn tool(name: &str, args: Vec<String>) -> Vec<String> {
    std::iter::once(name.to_owned()).chain(args).collect()
}
