//! labrig-doctor (`labrig doctor [--rig <launch config>] [--json]`): whether this machine, and every part the
//! rig's launch config names, is ready, with the fix for each part that is not.
//!
//! Each node's config is read the way the node itself reads it (its own parser, the launch
//! config's `args` and `--config`), then the parts are asked directly: the FR3 over the FCI
//! (franka-rs's handshake gives its FCI version), the 2F-85 over Modbus RTU (a status read),
//! each camera by its serial among the V4L2 devices (and the configured mode among the modes
//! it offers) or, for a stream or a file, by ffprobe; the Quest through adb; the calibration
//! files and their age; the recorder's disk against an hour of recording at the configured
//! rates; the clock's synchronisation; DDS's interfaces; the CPU governor and real-time
//! limits; the policy checkpoint through the policy server's own loader.
//!
//! Exit 0: ready (no check failed; warnings are listed); 3: not ready; 1: the doctor itself
//! could not run.
//!
//! A program of its own: the drivers it asks the hardware with (franka-rs, Modbus, V4L2) stay
//! out of the `labrig` CLI's build, which `labrig demo` needs on a fresh machine.

use clap::Args;
use labrig_cameras::node::{CameraConfig, CamerasConfig, IntrinsicsSpec};
use labrig_cameras::source::{DeviceKind, SourceSpec};
use labrig_episode::metadata::RigIdentity;
use labrig_launch::config::LaunchConfig;
use labrig_launch::programs::sibling_binary;
use labrig_runtime::RosConfig;
use labrig_runtime::node::run_config;
use serde::Serialize;
use std::path::{Path, PathBuf};
use std::process::{Command, ExitCode, Stdio};
use std::time::Duration;

/// `labrig doctor`'s exit code when a check failed.
pub const EXIT_NOT_READY: u8 = 3;

#[derive(Debug, Args)]
pub struct DoctorArgs {
    /// The rig's launch config (e.g. launch_configs/real_droid.toml): every part it names is
    /// checked. Without one, this machine alone (programs, disk, clock, real-time settings).
    #[arg(long)]
    pub rig: Option<PathBuf>,
    /// The checks as JSON on stdout: `{"ready": bool, "checks": [{"part", "state", "detail", "fix"}]}`.
    #[arg(long)]
    pub json: bool,
    /// How long a device has to answer (s): the FR3's handshake, the gripper's status read,
    /// ffprobe, adb.
    #[arg(long, default_value_t = 5.0)]
    pub timeout_s: f64,
    /// The recording time the recorder's disk must hold at the configured rates (hours).
    #[arg(long, default_value_t = 1.0)]
    pub record_hours: f64,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum State {
    Ok,
    Warn,
    Fail,
}

/// One row of the table.
#[derive(Debug, Clone, Serialize)]
pub struct Check {
    pub part: String,
    pub state: State,
    pub detail: String,
    /// What to do about it (empty when ok).
    pub fix: String,
}

fn row(part: impl Into<String>, state: State, detail: impl Into<String>, fix: impl Into<String>) -> Check {
    Check { part: part.into(), state, detail: detail.into(), fix: fix.into() }
}
fn ok(part: impl Into<String>, detail: impl Into<String>) -> Check {
    row(part, State::Ok, detail, "")
}

pub fn run(a: DoctorArgs) -> anyhow::Result<ExitCode> {
    anyhow::ensure!(a.timeout_s.is_finite() && a.timeout_s > 0.0, "--timeout-s must be > 0");
    anyhow::ensure!(a.record_hours.is_finite() && a.record_hours >= 0.0, "--record-hours must be >= 0");
    let within = Duration::from_secs_f64(a.timeout_s);
    let mut checks = vec![build_profile()];
    match &a.rig {
        Some(path) => checks.extend(rig_checks(path, within, a.record_hours)),
        None => {
            let programs = ["labrig-sim", "labrig-control", "labrig-recorder", "labrig-franka", "labrig-gripper"];
            checks.extend(programs.iter().map(|p| program(p)));
            checks.push(disk(Path::new("episodes"), None, a.record_hours));
            checks.push(dds(&[("every node".into(), RosConfig::default())]));
        }
    }
    checks.push(clock_sync(within));
    checks.extend(realtime(0, false, "-"));
    let ready = checks.iter().all(|c| c.state != State::Fail);
    if a.json {
        println!("{}", serde_json::to_string_pretty(&serde_json::json!({ "ready": ready, "checks": checks }))?);
    } else {
        print!("{}", table(&checks));
        let fails = checks.iter().filter(|c| c.state == State::Fail).count();
        let warns = checks.iter().filter(|c| c.state == State::Warn).count();
        match (ready, &a.rig) {
            (true, Some(r)) => println!("ready: the rig of {} ({warns} warnings)", r.display()),
            (true, None) => {
                println!("ready: this machine ({warns} warnings; `--rig <launch config>` checks a rig's parts)")
            }
            (false, _) => {
                println!("not ready: {fails} checks failed, {warns} warnings (each failed row names its fix)")
            }
        }
    }
    Ok(if ready { ExitCode::SUCCESS } else { ExitCode::from(EXIT_NOT_READY) })
}

/// The table: part, state, detail, fix (the fix on its own line under a failed or warned row).
pub fn table(checks: &[Check]) -> String {
    let w = checks.iter().map(|c| c.part.chars().count()).max().unwrap_or(4).max(4);
    let mut out = format!("{:<w$}  {:<5}  detail\n", "part", "state");
    for c in checks {
        let state = match c.state {
            State::Ok => "ok",
            State::Warn => "WARN",
            State::Fail => "FAIL",
        };
        out.push_str(&format!("{:<w$}  {:<5}  {}\n", c.part, state, c.detail));
        if !c.fix.is_empty() {
            out.push_str(&format!("{:<w$}  {:<5}  fix: {}\n", "", "", c.fix));
        }
    }
    out
}

fn build_profile() -> Check {
    if cfg!(debug_assertions) {
        row(
            "build",
            State::Warn,
            "these are debug builds (the dev profile): fine for the sim and the tests",
            "a rig runs release builds: `bash scripts/install.sh` (docs/install.md)",
        )
    } else {
        ok("build", "release builds")
    }
}

fn program(name: &str) -> Check {
    match sibling_binary(name) {
        Ok(p) => ok(format!("program {name}"), p.display().to_string()),
        Err(e) => {
            row(format!("program {name}"), State::Fail, e.to_string(), "`bash scripts/install.sh` builds every program")
        }
    }
}

/// The node configs the doctor knows how to read (by program).
#[derive(Default)]
struct Nodes {
    franka: Option<labrig_franka::node::FrankaNodeConfig>,
    gripper: Option<labrig_gripper::node::GripperNodeConfig>,
    cameras: Option<CamerasConfig>,
    teleop: Option<labrig_quest_teleop::node::TeleopConfig>,
    control: Option<labrig_control::config::ControlConfig>,
    recorder: Option<labrig_recorder::node::RecorderConfig>,
    /// The policy server's command line and config file (its crate links libtorch: it is asked
    /// through its own program).
    policy: Option<(Vec<String>, Option<PathBuf>)>,
    ros: Vec<(String, RosConfig)>,
}

fn rig_checks(path: &Path, within: Duration, hours: f64) -> Vec<Check> {
    let mut out = Vec::new();
    let (cfg, _) = match LaunchConfig::load(path) {
        Ok(c) => c,
        Err(e) => {
            out.push(row(
                "launch config",
                State::Fail,
                format!("{e:#}"),
                "fix the file (`labrig launch --check <file>`)",
            ));
            return out;
        }
    };
    let dir = path.parent().unwrap_or(Path::new("."));
    out.push(ok("launch config", format!("{}: rig `{}`, {} nodes", path.display(), cfg.rig.name, cfg.nodes.len())));
    let mut nodes = Nodes::default();
    for n in &cfg.nodes {
        out.push(program(&n.program));
        let file = n.config.as_ref().map(|c| dir.join(c));
        let file = file.as_deref();
        let part = format!("{} config", n.name);
        let ros = &mut nodes.ros;
        let loaded: anyhow::Result<()> = match n.program.as_str() {
            "labrig-franka" => read::<labrig_franka::FrankaNode>(n, file, ros).map(|c| nodes.franka = Some(c)),
            "labrig-gripper" => read::<labrig_gripper::GripperNode>(n, file, ros).map(|c| nodes.gripper = Some(c)),
            "labrig-cameras" => read::<labrig_cameras::CamerasNode>(n, file, ros).map(|c| nodes.cameras = Some(c)),
            "labrig-teleop" => read::<labrig_quest_teleop::TeleopNode>(n, file, ros).map(|c| nodes.teleop = Some(c)),
            "labrig-control" => read::<labrig_control::ControlNode>(n, file, ros).map(|c| nodes.control = Some(c)),
            "labrig-recorder" => read::<labrig_recorder::RecorderNode>(n, file, ros).map(|c| nodes.recorder = Some(c)),
            "labrig-policy" => {
                nodes.policy = Some((n.args.clone(), file.map(Path::to_owned)));
                Ok(())
            }
            _ => Ok(()),
        };
        if let Err(e) = loaded {
            out.push(row(
                part,
                State::Fail,
                format!("{e:#}"),
                "fix the node's config or its `args` in the launch config",
            ));
        }
    }
    let devices = &cfg.rig.devices;
    if let Some(f) = &nodes.franka {
        out.extend(fr3(f, devices.robot_ip.as_deref(), within));
    }
    if let Some(g) = &nodes.gripper {
        out.push(gripper(g, devices.gripper_port.as_deref(), within));
    }
    if let Some(c) = &nodes.cameras {
        for (name, cam) in &c.cameras {
            out.push(camera(name, cam, devices.camera_serials.get(name).map(String::as_str), within));
        }
    }
    if let Some(t) = &nodes.teleop {
        out.push(quest(&t.input, within));
    }
    if let Some(c) = &nodes.control {
        out.extend(calibration(c));
        out.extend(
            realtime(c.realtime_priority, false, "control")
                .into_iter()
                .filter(|r| r.part.starts_with("real-time priority")),
        );
    }
    if let Some(r) = &nodes.recorder {
        let rate = nodes.cameras.as_ref().map(|c| recording_rate(c, r));
        out.push(disk(&r.root, rate, hours));
        out.push(episode_metadata(&r.rig, devices, nodes.franka.is_some()));
    }
    if let Some((args, file)) = &nodes.policy {
        out.push(policy(args, file.as_deref(), within));
    }
    if !nodes.ros.is_empty() {
        out.push(dds(&nodes.ros));
    }
    out
}

/// Node `N`'s config as the node reads it (its `args`, its `--config`); its `[ros]` is noted
/// for the DDS check.
fn read<N: labrig_runtime::Node>(
    n: &labrig_launch::config::NodeSpec,
    file: Option<&Path>,
    ros: &mut Vec<(String, RosConfig)>,
) -> anyhow::Result<N::Config> {
    let mut c = run_config::<N>(&n.args, file)?;
    ros.push((n.name.clone(), N::ros(&mut c).clone()));
    Ok(c)
}

// ---------------------------------------------------------------------------------- the FR3

fn fr3(f: &labrig_franka::node::FrankaNodeConfig, rig_ip: Option<&str>, within: Duration) -> Vec<Check> {
    use labrig_franka::node::BackendKind;
    if f.backend != BackendKind::Fci {
        return vec![ok("FR3", format!("the sim bridge's arm under {} (no robot)", f.sim_prefix))];
    }
    let mut out = Vec::new();
    let ip = f.robot_ip.as_str();
    if let Some(r) = rig_ip.filter(|r| *r != ip) {
        out.push(row(
            "FR3 address",
            State::Fail,
            format!("the launch config's rig.devices.robot_ip is {r}, the franka node connects to {ip}"),
            "make them agree (the node's `robot_ip` is what connects)",
        ));
    }
    out.push(match labrig_franka::fci::probe(ip, within) {
        Ok(version) => ok("FR3", format!("{ip}: FCI version {version}")),
        Err(e) => {
            let e = e.to_string();
            let fix = if e.contains("refused") {
                "the address answers but no FCI listens: power the robot, unlock the joints and activate FCI in Desk (https://<robot>/desk)"
            } else if e.contains("version") {
                "the robot's system image speaks another FCI version than labrig's franka-rs: update the robot's system image (docs/bringup.md)"
            } else if e.contains("no answer") || e.contains("unreachable") || e.contains("timed out") {
                "no answer: check the cable to the robot's Control unit, this machine's static address on the robot's network (e.g. 172.16.0.1/24), `ping` the robot"
            } else {
                "something answered that is not an FCI: is `robot_ip` the robot's address?"
            };
            row("FR3", State::Fail, format!("{ip}: {e}"), fix)
        }
    });
    if f.fci.realtime {
        out.extend(realtime(99, true, "franka"));
    }
    out
}

// ------------------------------------------------------------------------------ the gripper

fn gripper(g: &labrig_gripper::node::GripperNodeConfig, rig_port: Option<&str>, within: Duration) -> Check {
    use labrig_gripper::node::Backend;
    match g.backend {
        Backend::Sim => return ok("2F-85", format!("the sim bridge's gripper under {} (no hardware)", g.sim_prefix)),
        Backend::Emulated => return ok("2F-85", "emulated on a pseudo-terminal inside the node (no hardware)"),
        Backend::Robotiq => {}
    }
    let port = g.port.as_str();
    if let Some(r) = rig_port.filter(|r| *r != port) {
        return row(
            "2F-85",
            State::Fail,
            format!("the launch config's rig.devices.gripper_port is {r}, the gripper node opens {port}"),
            "make them agree (the node's `port` is what opens)",
        );
    }
    let cfg =
        labrig_gripper::DriverConfig { port: port.to_owned(), slave: g.slave, baud: g.baud, request_timeout: within };
    let where_ = format!("{port} (slave {}, {} baud)", g.slave, g.baud);
    let answer =
        tokio::runtime::Builder::new_current_thread().enable_all().build().map_err(|e| e.to_string()).and_then(|rt| {
            rt.block_on(async {
                let mut d = labrig_gripper::Robotiq2F85::open(cfg).map_err(|e| e.to_string())?;
                d.status().await.map_err(|e| e.to_string())
            })
        });
    match answer {
        Ok(s) => ok(
            "2F-85",
            format!(
                "{where_} answers: {}, fault {}",
                if s.activated { "activated" } else { "not activated (the node activates it)" },
                s.fault
            ),
        ),
        Err(e) => {
            let fix = if !Path::new(port).exists() {
                "plug in the USB-RS485 adapter; find it with `ls -l /dev/serial/by-id/` and set `port` (docs/bringup.md)"
            } else if e.contains("ermission denied") {
                "add the rig's user to the dialout group (`sudo usermod -aG dialout $USER`, then log in again)"
            } else {
                "the port opens but the gripper does not answer: check its 24 V supply, the RS-485 wiring (A/B), `slave` and `baud`"
            };
            row("2F-85", State::Fail, format!("{where_}: {e}"), fix)
        }
    }
}

// ------------------------------------------------------------------------------ the cameras

fn camera(name: &str, cam: &CameraConfig, rig_serial: Option<&str>, within: Duration) -> Check {
    let part = format!("camera {name}");
    let source = cam.source.as_str();
    // (Relative files in the config were made relative to its folder when it was read, as
    // the node reads them.)
    let spec = match SourceSpec::parse(source) {
        Ok(s) => s,
        Err(e) => {
            return row(part, State::Fail, e.to_string(), "fix the camera's `source` in the camera node's config");
        }
    };
    // A source named by its kind alone takes the rig's serial, as the node does.
    let spec = match (spec.needs_serial(), rig_serial) {
        (true, Some(s)) => spec.with_serial(s),
        (true, None) => {
            return row(
                part,
                State::Fail,
                format!("its source `{source}` names no serial, and rig.devices.camera_serials has none for {name}"),
                "give the launch config's [rig.devices.camera_serials] one (`labrig cameras list` prints them)",
            );
        }
        (false, _) => spec,
    };
    let serial = match &spec {
        SourceSpec::Device { serial, .. } | SourceSpec::RealSense { serial, .. } => serial.clone(),
        _ => None,
    };
    if let (Some(want), Some(have)) = (rig_serial, serial.as_deref())
        && want != have
    {
        return row(
            part,
            State::Fail,
            format!("wrong serial: rig.devices.camera_serials.{name} is {want}, the camera node's source is {source}"),
            "put the same serial in both (`labrig cameras list` prints the connected cameras' serials)",
        );
    }
    if let Some(IntrinsicsSpec::File(f)) = &cam.intrinsics
        && !f.is_file()
    {
        return row(
            part,
            State::Fail,
            format!("its intrinsics file {} is missing", f.display()),
            "a ZED's is its factory file SN<serial>.conf (download it once from Stereolabs), others a labrig intrinsics file; or drop `intrinsics`",
        );
    }
    if let Some(f) = &cam.realsense_calibration {
        // Read in Rust over V4L2: the set-up's export must be there, and this camera's.
        let fix = format!(
            "export it once: labrig cameras realsense-export --serial {} --width {} --height {} --out {}",
            serial.as_deref().unwrap_or("<serial>"),
            cam.width,
            cam.height,
            f.display()
        );
        match labrig_cameras::realsense::RealSenseCalibration::load(f) {
            Err(e) => return row(part, State::Fail, format!("its RealSense calibration: {e}"), &fix),
            Ok(c) if serial.as_deref().is_some_and(|s| s != c.serial) => {
                return row(
                    part,
                    State::Fail,
                    format!("its RealSense calibration {} is camera {}'s", f.display(), c.serial),
                    &fix,
                );
            }
            Ok(_) => {}
        }
    }
    let mode = format!("{}x{}@{}", cam.width, cam.height, cam.fps);
    // A source by kind is shown with the serial the rig gave it.
    let source = &match (&spec, source.contains(':')) {
        (SourceSpec::Device { serial: Some(s), .. } | SourceSpec::RealSense { serial: Some(s), .. }, false) => {
            format!("{source}:{s} (the serial from rig.devices.camera_serials)")
        }
        _ => source.to_owned(),
    };
    let source = source.as_str();
    match spec {
        SourceSpec::Device { kind, serial: Some(serial), .. } => device_camera(part, source, kind, &serial, cam),
        SourceSpec::RealSense { serial: Some(serial), .. } => {
            device_camera(part, source, DeviceKind::RealSense, &serial, cam)
        }
        SourceSpec::Ffmpeg { input, .. } => probe_stream(&part, &input, cam, within),
        SourceSpec::Mjpeg { url } => probe_stream(&part, &url, cam, within),
        SourceSpec::TestPattern => ok(part, format!("ffmpeg's test pattern at {mode} (no camera)")),
        SourceSpec::RealSense { file: Some(f), .. } => ok(part, format!("RealSense recording {}", f.display())),
        SourceSpec::Device { path: Some(p), .. } => {
            if p.exists() {
                ok(
                    part,
                    format!(
                        "{} (by path: a camera moved to another port is not found; prefer its serial)",
                        p.display()
                    ),
                )
            } else {
                row(
                    part,
                    State::Fail,
                    format!("{} does not exist", p.display()),
                    "name the camera by its serial (`labrig cameras list`)",
                )
            }
        }
        _ => row(part, State::Fail, format!("{source}: not a source the doctor can check"), ""),
    }
}

/// A camera on USB, found by its serial among the V4L2 devices; the configured mode among
/// those it offers (a RealSense's come from librealsense when the node starts).
fn device_camera(part: String, source: &str, kind: DeviceKind, serial: &str, cam: &CameraConfig) -> Check {
    let mode = format!("{}x{}@{}", cam.width, cam.height, cam.fps);
    let found = labrig_cameras::v4l2::list();
    let Some(dev) = found.iter().find(|d| d.serial.as_deref() == Some(serial) && d.kind() == kind) else {
        let present: Vec<String> =
            found.iter().map(|d| format!("{} {}", d.card, d.serial.as_deref().unwrap_or("(no serial)"))).collect();
        return row(
            part,
            State::Fail,
            format!(
                "{source}: no such camera connected (connected: {})",
                if present.is_empty() { "none".to_owned() } else { present.join(", ") }
            ),
            "plug it into a USB 3 port (one controller per two cameras), or fix the serial (`labrig cameras list`)",
        );
    };
    if kind == DeviceKind::RealSense {
        return ok(part, format!("{source} at {} (its modes come from librealsense at start)", dev.path.display()));
    }
    // A ZED sends both eyes side by side: the device's frame is twice as wide.
    let eyes = if cam.side_by_side.unwrap_or(kind == DeviceKind::Zed) { 2 } else { 1 };
    let offered = dev.modes.iter().any(|m| {
        m.width == cam.width * eyes && m.height == cam.height && m.fps.iter().any(|f| (f - cam.fps).abs() < 0.5)
    });
    if offered {
        return ok(part, format!("{source} at {}, {mode} offered", dev.path.display()));
    }
    let modes: Vec<String> =
        dev.modes.iter().map(|m| format!("{} {}x{}@{:?}", m.fourcc, m.width, m.height, m.fps)).collect();
    row(
        part,
        State::Fail,
        format!("{source} does not offer {mode} (it offers {})", modes.join(", ")),
        "set width/height/fps to one of its modes",
    )
}

/// A stream or a file, asked with ffprobe: its size and frame rate against the config's.
fn probe_stream(part: &str, input: &str, cam: &CameraConfig, within: Duration) -> Check {
    let out = run_bounded(
        Command::new("ffprobe").args([
            "-v",
            "error",
            "-select_streams",
            "v:0",
            "-show_entries",
            "stream=width,height,avg_frame_rate,r_frame_rate",
            "-of",
            "json",
            input,
        ]),
        within,
    );
    let text = match out {
        Ok((true, stdout, _)) => stdout,
        Ok((false, _, stderr)) => {
            return row(
                part,
                State::Fail,
                format!("{input}: {}", stderr.lines().last().unwrap_or("ffprobe failed").trim()),
                "check that the stream is up (its server, the network) or that the file exists",
            );
        }
        Err(e) => return row(part, State::Fail, format!("{input}: {e}"), "check that the stream is up"),
    };
    let v: serde_json::Value = serde_json::from_str(&text).unwrap_or_default();
    let s = &v["streams"][0];
    let (w, h) = (s["width"].as_u64().unwrap_or(0) as u32, s["height"].as_u64().unwrap_or(0) as u32);
    let fps = ["avg_frame_rate", "r_frame_rate"]
        .iter()
        .filter_map(|k| s[k].as_str())
        .filter_map(|r| r.split_once('/').and_then(|(a, b)| Some(a.parse::<f64>().ok()? / b.parse::<f64>().ok()?)))
        .find(|f| f.is_finite() && *f > 0.0);
    if w == 0 {
        return row(part, State::Fail, format!("{input}: no video stream"), "point `source` at a video");
    }
    let eyes = if cam.side_by_side.unwrap_or(false) { 2 } else { 1 };
    if cam.width != 0 && (w != cam.width * eyes || h != cam.height) {
        return row(
            part,
            State::Fail,
            format!("{input} sends {w}x{h}, the config asks for {}x{}", cam.width * eyes, cam.height),
            "set width/height to what the source sends",
        );
    }
    let fps_text = fps.map_or("?".to_owned(), |f| format!("{f:.1}"));
    ok(part.to_owned(), format!("{input}: {w}x{h} at {fps_text} fps"))
}

/// Why a helper program (adb, chronyc, ffprobe, a node's probe) gave no answer.
#[derive(Debug, thiserror::Error)]
enum RunError {
    #[error("cannot run {program}: {source}")]
    Start { program: String, source: std::io::Error },
    #[error("{program} gave no answer within {seconds:.0} s")]
    Timeout { program: String, seconds: f64 },
    #[error("{0}")]
    Output(std::io::Error),
}

/// A helper's run: whether it exited 0, its stdout and stderr.
type RunOutput = (bool, String, String);

/// Runs `cmd` for at most `within`: (success, stdout, stderr).
fn run_bounded(cmd: &mut Command, within: Duration) -> Result<RunOutput, RunError> {
    let program = cmd.get_program().to_string_lossy().into_owned();
    let mut child = match cmd.stdin(Stdio::null()).stdout(Stdio::piped()).stderr(Stdio::piped()).spawn() {
        Ok(c) => c,
        Err(source) => return Err(RunError::Start { program, source }),
    };
    let deadline = std::time::Instant::now() + within;
    loop {
        match child.try_wait() {
            Ok(Some(_)) => break,
            Ok(None) if std::time::Instant::now() < deadline => std::thread::sleep(Duration::from_millis(20)),
            _ => {
                let _ = child.kill();
                let _ = child.wait();
                return Err(RunError::Timeout { program, seconds: within.as_secs_f64() });
            }
        }
    }
    let out = child.wait_with_output().map_err(RunError::Output)?;
    Ok((
        out.status.success(),
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    ))
}

// -------------------------------------------------------------------------------- the Quest

fn quest(input: &labrig_quest_teleop::input::InputConfig, within: Duration) -> Check {
    use labrig_quest_teleop::input::InputKind;
    match input.kind {
        InputKind::Keyboard => return ok("Quest", "the keyboard plays the controller (no headset)"),
        InputKind::Playback => {
            return match &input.file {
                Some(f) if f.is_file() => ok("Quest", format!("a recorded controller: {}", f.display())),
                other => row(
                    "Quest",
                    State::Fail,
                    format!("playback file {other:?} missing"),
                    "set input.file to a recorded logcat trace",
                ),
            };
        }
        InputKind::Adb => {}
    }
    let device = input.device.as_str();
    let listed = match run_bounded(Command::new(&input.adb).arg("devices"), within) {
        Ok((true, stdout, _)) => stdout,
        Ok((false, _, stderr)) => return row("Quest", State::Fail, format!("adb devices: {}", stderr.trim()), ""),
        Err(e) => return row("Quest", State::Fail, e.to_string(), "install adb (`bash scripts/setup.sh` does)"),
    };
    match adb_state(&listed, device) {
        Some("device") => {}
        Some("unauthorized") => {
            return row(
                "Quest",
                State::Fail,
                format!("{device}: unauthorized"),
                "put the headset on and allow USB debugging for this computer",
            );
        }
        other => {
            let fix = if device.contains(':') {
                format!("`adb connect {device}` (the headset on the same network, `adb tcpip 5555` done once over USB)")
            } else {
                "plug the headset in, developer mode on, allow USB debugging (docs/bringup.md)".to_owned()
            };
            return row(
                "Quest",
                State::Fail,
                format!(
                    "{device}: {} (adb lists: {})",
                    other.unwrap_or("not connected"),
                    adb_devices(&listed).join(", ")
                ),
                fix,
            );
        }
    }
    let package = labrig_quest_teleop::input::APP_ACTIVITY.split('/').next().unwrap_or_default();
    match run_bounded(Command::new(&input.adb).args(["-s", device, "shell", "pm", "list", "packages", package]), within)
    {
        Ok((true, stdout, _)) if stdout.lines().any(|l| l.trim() == format!("package:{package}")) => {
            ok("Quest", format!("{device}: connected, {package} installed"))
        }
        Ok(_) => row(
            "Quest",
            State::Fail,
            format!("{device}: connected, but {package} is not installed"),
            "install DROID's oculus_reader app: `adb install <apk>` (docs/bringup.md)",
        ),
        Err(e) => row("Quest", State::Fail, e.to_string(), ""),
    }
}

/// `adb devices`' state of `serial` (`device`, `unauthorized`, `offline`, ...).
pub fn adb_state<'a>(listed: &'a str, serial: &str) -> Option<&'a str> {
    listed.lines().skip(1).filter_map(|l| l.split_once('\t')).find(|(s, _)| s.trim() == serial).map(|(_, st)| st.trim())
}

fn adb_devices(listed: &str) -> Vec<String> {
    let v: Vec<String> =
        listed.lines().skip(1).filter_map(|l| l.split_once('\t')).map(|(s, st)| format!("{s} {st}")).collect();
    if v.is_empty() { vec!["none".into()] } else { v }
}

// -------------------------------------------------------------------------- the calibration

fn calibration(c: &labrig_control::config::ControlConfig) -> Vec<Check> {
    let Some(dir) = &c.calibration else {
        return vec![row(
            "calibration",
            State::Warn,
            "the control node names no calibration folder (`calibration`): episodes carry no camera poses",
            "calibrate (`labrig calibrate --rig ...`, docs/operator.md) and set `calibration` in the control config",
        )];
    };
    let cameras: Vec<&str> = c.cameras.iter().map(String::as_str).collect();
    let found = labrig_episode::calibration::load(dir, &cameras);
    let now = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map_or(0, |d| d.as_secs() as i64);
    let mut out: Vec<Check> = found
        .problems
        .iter()
        .map(|p| row("calibration", State::Fail, p.clone(), "calibrate the camera (docs/operator.md)"))
        .collect();
    for (camera, f) in &found.files {
        let age = f.age_s(now);
        let part = format!("calibration {camera}");
        if age as f64 > c.calibration_max_age_s {
            out.push(row(
                part,
                State::Fail,
                format!(
                    "made {} ago ({}), older than the {} allowed (calibration_max_age_s)",
                    labrig_episode::calibration::human(age),
                    f.date,
                    labrig_episode::calibration::human(c.calibration_max_age_s as i64)
                ),
                format!("`labrig calibrate check --camera {camera} ...`, and calibrate again if it moved"),
            ));
        } else {
            out.push(ok(part, format!("made {} ago ({})", labrig_episode::calibration::human(age), f.date)));
        }
    }
    out
}

// ------------------------------------------------------------------------------------ disk

/// Bytes per second the recorder writes: each recorded camera's frames as JPEG at the
/// configured size and rate. A JPEG at the recorder's quality is taken as 0.5 byte per pixel
/// (camera images of a lab scene at quality 90 measure 0.1-0.3; the margin covers texture).
fn recording_rate(cams: &CamerasConfig, rec: &labrig_recorder::node::RecorderConfig) -> f64 {
    cams.cameras
        .iter()
        .filter(|(name, _)| rec.cameras.is_empty() || rec.cameras.contains(name))
        .map(|(_, c)| f64::from(c.width.max(320)) * f64::from(c.height.max(240)) * 0.5 * c.fps)
        .sum::<f64>()
}

/// What every episode's DROID metadata will say of the rig (the recorder's `[rig]`): its camera
/// serials must be the rig's (`rig.devices.camera_serials`); the simulator's defaults on a rig
/// that drives an arm are a warning.
fn episode_metadata(id: &RigIdentity, devices: &labrig_launch::config::Devices, drives_an_arm: bool) -> Check {
    const PART: &str = "episode metadata";
    // The recorder takes the serials its config does not name from the launcher, as here.
    let mut id = id.clone();
    id.fill_camera_serials(&devices.camera_serials);
    let id = &id;
    let wrong: Vec<String> = devices
        .camera_serials
        .iter()
        .filter_map(|(cam, want)| {
            id.camera_serials.get(cam).filter(|got| *got != want).map(|got| format!("{cam} {got} (the rig: {want})"))
        })
        .collect();
    if !wrong.is_empty() {
        return row(
            PART,
            State::Fail,
            format!("the recorder would write wrong camera serials: {}", wrong.join(", ")),
            "leave the serials to [rig.devices.camera_serials] (the recorder takes them from the launcher), or give the recorder's [rig.camera_serials] the same",
        );
    }
    let default = RigIdentity::default();
    let what = format!(
        "lab {}, building {}, robot {}, {} camera serials",
        id.lab,
        id.building,
        id.robot_serial,
        id.camera_serials.len()
    );
    if drives_an_arm && (id.robot_serial == default.robot_serial || id.building == default.building) {
        return row(
            PART,
            State::Warn,
            format!("{what}: the simulator's defaults"),
            "give the recorder a config with [rig] (launch_configs/nodes/recorder_real.toml)",
        );
    }
    ok(PART, what)
}

fn disk(root: &Path, rate_bps: Option<f64>, hours: f64) -> Check {
    // The folder may not exist yet: its nearest existing parent is what fills.
    let mut at =
        if root.is_absolute() { root.to_owned() } else { std::env::current_dir().unwrap_or_default().join(root) };
    while !at.exists() {
        if !at.pop() {
            break;
        }
    }
    let free = match nix::sys::statvfs::statvfs(&at) {
        Ok(s) => s.blocks_available() as f64 * s.fragment_size() as f64,
        Err(e) => return row("disk", State::Fail, format!("{}: {e}", at.display()), ""),
    };
    let gb = |b: f64| format!("{:.1} GB", b / 1e9);
    match rate_bps {
        Some(rate) => {
            let need = rate * 3600.0 * hours;
            let detail = format!(
                "{} free at {} for {}; {hours} h at the configured cameras (~{:.0} MB/s) needs {}",
                gb(free),
                at.display(),
                root.display(),
                rate / 1e6,
                gb(need)
            );
            if free >= need {
                ok("disk", detail)
            } else {
                row("disk", State::Fail, detail, "free space or point the recorder's `--root` at a larger disk")
            }
        }
        None => ok("disk", format!("{} free at {} for {}", gb(free), at.display(), root.display())),
    }
}

// ----------------------------------------------------------------------------------- clock

fn clock_sync(within: Duration) -> Check {
    let fix = "install chrony (`sudo apt-get install chrony`) and check `chronyc tracking`: the cameras, the arm and the recorder share this clock";
    if let Ok((true, out, _)) = run_bounded(Command::new("chronyc").arg("tracking"), within) {
        let field =
            |k: &str| out.lines().find(|l| l.starts_with(k)).and_then(|l| l.split_once(':')).map(|(_, v)| v.trim());
        let leap = field("Leap status").unwrap_or("?");
        let offset = field("System time").unwrap_or("?");
        return if leap == "Normal" {
            ok("clock", format!("chrony: synchronised, {offset}"))
        } else {
            row("clock", State::Warn, format!("chrony: leap status {leap} (not synchronised)"), fix)
        };
    }
    if let Ok((true, out, _)) =
        run_bounded(Command::new("timedatectl").args(["show", "-p", "NTPSynchronized", "--value"]), within)
    {
        return if out.trim() == "yes" {
            ok("clock", "systemd-timesyncd: synchronised")
        } else {
            row("clock", State::Warn, "not synchronised (timedatectl: NTPSynchronized=no)", fix)
        };
    }
    row("clock", State::Warn, "cannot tell: neither chronyc nor timedatectl answers", fix)
}

// ------------------------------------------------------------------------------------- DDS

fn dds(nodes: &[(String, RosConfig)]) -> Check {
    let loopback: Vec<&str> = nodes.iter().filter(|(_, r)| r.loopback_only).map(|(n, _)| n.as_str()).collect();
    let network: Vec<&str> = nodes.iter().filter(|(_, r)| !r.loopback_only).map(|(n, _)| n.as_str()).collect();
    if !loopback.is_empty() && !network.is_empty() {
        return row(
            "DDS",
            State::Fail,
            format!("{loopback:?} keep DDS on loopback, {network:?} use the network: they cannot all see each other"),
            "set `ros.loopback_only` the same in every node's config",
        );
    }
    if network.is_empty() {
        return ok("DDS", "loopback only (127.0.0.1): the rig's nodes run on this machine");
    }
    let up: Vec<String> = std::fs::read_dir("/sys/class/net")
        .into_iter()
        .flatten()
        .flatten()
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .filter(|n| n != "lo")
        .filter(|n| std::fs::read_to_string(format!("/sys/class/net/{n}/operstate")).is_ok_and(|s| s.trim() == "up"))
        .collect();
    if up.is_empty() {
        row(
            "DDS",
            State::Fail,
            "the nodes use the network, but no interface besides lo is up",
            "bring the rig's network up",
        )
    } else {
        row(
            "DDS",
            State::Warn,
            format!("on every interface that is up ({}): the rig spans machines", up.join(", ")),
            "keep the rig's network private (DDS discovery multicasts on every interface)",
        )
    }
}

// ------------------------------------------------------------------------------- real time

/// The CPU governor and the limits for SCHED_FIFO at `priority` (0: none asked). `required`:
/// the program refuses to run without it (franka-rs with `fci.realtime`), so it fails; else
/// it runs at normal priority with a warning, and so does this check.
fn realtime(priority: u8, required: bool, who: &str) -> Vec<Check> {
    let mut out = Vec::new();
    if !required {
        let governors: Vec<String> = std::fs::read_dir("/sys/devices/system/cpu")
            .into_iter()
            .flatten()
            .flatten()
            .filter_map(|e| std::fs::read_to_string(e.path().join("cpufreq/scaling_governor")).ok())
            .map(|s| s.trim().to_owned())
            .collect();
        out.push(if governors.is_empty() {
            ok("CPU governor", "not exposed (a VM or a fixed-frequency CPU)")
        } else if governors.iter().all(|g| g == "performance") {
            ok("CPU governor", format!("performance on {} CPUs", governors.len()))
        } else {
            let mut g = governors.clone();
            g.dedup();
            row(
                "CPU governor",
                State::Warn,
                format!("{}: the loop's timing varies with the clock speed", g.join(", ")),
                "`sudo cpupower frequency-set -g performance` (package linux-cpupower)",
            )
        });
    }
    if required {
        let rt = std::fs::read_to_string("/sys/kernel/realtime").is_ok_and(|s| s.trim() == "1");
        out.push(if rt {
            ok("real-time kernel", "PREEMPT_RT")
        } else {
            row(
                "real-time kernel",
                State::Fail,
                "the franka node's fci.realtime = true needs a PREEMPT_RT kernel (/sys/kernel/realtime is not 1)",
                "boot a PREEMPT_RT kernel (Debian: linux-image-rt-amd64; docs/bringup.md); fci.realtime = false is for franka-sim only",
            )
        });
    }
    if priority > 0 {
        let root = nix::unistd::geteuid().is_root();
        let limit =
            nix::sys::resource::getrlimit(nix::sys::resource::Resource::RLIMIT_RTPRIO).map_or(0, |(soft, _)| soft);
        let state = if required { State::Fail } else { State::Warn };
        let part = format!("real-time priority ({who})");
        out.push(if root || limit >= u64::from(priority) {
            ok(part, format!("SCHED_FIFO {priority} allowed ({})", if root { "root".to_owned() } else { format!("rtprio limit {limit}") }))
        } else {
            row(
                part,
                state,
                format!("SCHED_FIFO {priority} is asked for, the rtprio limit is {limit}"),
                "add `@realtime - rtprio 99` and `@realtime - memlock unlimited` to /etc/security/limits.d/99-realtime.conf, the user to group realtime, log in again",
            )
        });
    }
    out
}

// ---------------------------------------------------------------------------------- policy

/// The policy server's checkpoint, loaded by the policy server's own program (`labrig-policy
/// check`, which reads its config and loads the model as `run` would).
fn policy(args: &[String], file: Option<&Path>, within: Duration) -> Check {
    let exe = match sibling_binary("labrig-policy") {
        Ok(e) => e,
        Err(e) => return row("policy", State::Fail, e.to_string(), "`bash scripts/install.sh` builds it"),
    };
    let mut forwarded: Vec<String> = args.to_vec();
    if let Some(first) = forwarded.first_mut()
        && first == "run"
    {
        *first = "check".to_owned();
    }
    if let Some(f) = file {
        forwarded.push("--config".into());
        forwarded.push(f.display().to_string());
    }
    // Loading a checkpoint takes longer than a device's answer.
    match run_bounded(Command::new(exe).args(&forwarded), within.max(Duration::from_secs(120))) {
        Ok((true, stdout, _)) => ok("policy", stdout.lines().last().unwrap_or("loads").trim().to_owned()),
        Ok((false, _, stderr)) => row(
            "policy",
            State::Fail,
            stderr.lines().rev().find(|l| !l.trim().is_empty()).unwrap_or("does not load").trim().to_owned(),
            "point `--checkpoint` at a checkpoint `labrig train` wrote (e.g. <run>/checkpoints/last)",
        ),
        Err(e) => row("policy", State::Fail, e.to_string(), ""),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn adb_states_are_read_by_serial() {
        let listed = "List of devices attached\n1WMHH000000000\tdevice\n192.168.1.20:5555\tunauthorized\n\n";
        assert_eq!(adb_state(listed, "1WMHH000000000"), Some("device"));
        assert_eq!(adb_state(listed, "192.168.1.20:5555"), Some("unauthorized"));
        assert_eq!(adb_state(listed, "1WMHH000000001"), None);
        assert_eq!(adb_state("List of devices attached\n\n", "x"), None);
    }

    #[test]
    fn a_realsense_read_in_rust_needs_its_own_exported_calibration() {
        let dir = std::env::temp_dir().join(format!("labrig-doctor-rs-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let file = dir.join("rs1.json");
        let mut cam = CameraConfig::new("realsense:D435-1");
        (cam.width, cam.height) = (1280, 720);
        cam.realsense_calibration = Some(file.clone());
        let check = camera("rs1", &cam, None, Duration::from_secs(1));
        assert_eq!(check.state, State::Fail);
        assert!(
            check.detail.starts_with("its RealSense calibration: ") && check.detail.contains("rs1.json"),
            "{check:?}"
        );
        assert!(
            check.fix.contains("labrig cameras realsense-export --serial D435-1 --width 1280 --height 720"),
            "{check:?}"
        );
        let stream = serde_json::json!({"width": 1280, "height": 720, "fx": 600.0, "fy": 600.0, "ppx": 639.5, "ppy": 359.5,
                                        "model": "brown_conrady", "coeffs": [0.0, 0.0, 0.0, 0.0, 0.0]});
        let cal = serde_json::json!({"serial": "D435-2", "colour": stream, "depth": stream,
            "depth_to_colour": {"rotation": [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0], "translation": [0.015, 0.0, 0.0]},
            "depth_scale_m": 0.001});
        std::fs::write(&file, cal.to_string()).unwrap();
        let check = camera("rs1", &cam, None, Duration::from_secs(1));
        assert_eq!(check.state, State::Fail);
        assert!(check.detail.ends_with("is camera D435-2's"), "{check:?}");
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn the_table_puts_each_fix_under_its_row() {
        let t = table(&[ok("disk", "9 GB free"), row("FR3", State::Fail, "172.16.0.2: refused", "activate FCI")]);
        let lines: Vec<&str> = t.lines().collect();
        assert_eq!(lines.len(), 4, "{t}");
        assert!(lines[2].starts_with("FR3 ") && lines[2].contains("FAIL") && lines[2].ends_with("refused"), "{t}");
        assert!(lines[3].trim_start().starts_with("fix: activate FCI"), "{t}");
    }
}
