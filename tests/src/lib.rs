//! labrig-tests: helpers for end-to-end tests across processes and against real peers
//! (rclpy from the PyPI ROS 2 wheels, installed by `scripts/setup.sh`).
//!
//! Peers are real processes; nothing here stands in for them. Every wait is bounded.

pub mod droid_raw;

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::mpsc::{Receiver, RecvTimeoutError, channel};
use std::time::{Duration, Instant};

/// The repository root.
pub fn repo_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).parent().expect("tests/ has a parent").to_owned()
}

/// The setup cache (`$LABRIG_CACHE`, default `~/.cache/labrig`).
pub fn cache_dir() -> PathBuf {
    labrig_msgs::cache_dir().expect("LABRIG_CACHE or HOME is set")
}

/// The Python with pyrealsense2 the RealSense peers run on (`LABRIG_REALSENSE_PYTHON`, or the
/// venv `scripts/setup.sh` makes in the cache).
pub fn realsense_python() -> PathBuf {
    std::env::var_os("LABRIG_REALSENSE_PYTHON")
        .map(PathBuf::from)
        .unwrap_or_else(|| cache_dir().join("venv-realsense/bin/python"))
}

/// The Python of the rclpy venv made by `scripts/setup.sh`.
pub fn ros_python() -> PathBuf {
    let p = match std::env::var_os("LABRIG_ROS_PYTHON") {
        Some(p) => PathBuf::from(p),
        None => cache_dir().join("venv-ros/bin/python"),
    };
    assert!(p.exists(), "rclpy venv python {} is missing: run `bash scripts/setup.sh` first", p.display());
    p
}

/// The Python of the openpi venv made by `scripts/setup.sh` (openpi-client, openpi-server).
pub fn openpi_python() -> PathBuf {
    let p = match std::env::var_os("LABRIG_OPENPI_PYTHON") {
        Some(p) => PathBuf::from(p),
        None => cache_dir().join("venv-openpi/bin/python"),
    };
    assert!(p.exists(), "openpi venv python {} is missing: run `bash scripts/setup.sh` first", p.display());
    p
}

/// The Python of the LeRobot venv made by `scripts/setup.sh` (lerobot 0.4.4's dataset code).
pub fn lerobot_python() -> PathBuf {
    let p = match std::env::var_os("LABRIG_LEROBOT_PYTHON") {
        Some(p) => PathBuf::from(p),
        None => cache_dir().join("venv-lerobot-data/bin/python"),
    };
    assert!(p.exists(), "LeRobot venv python {} is missing: run `bash scripts/setup.sh` first", p.display());
    p
}

/// tests/peers/openpi_peer.py with the openpi venv's Python.
pub fn openpi_peer(args: &[&str]) -> Command {
    let mut cmd = Command::new(openpi_python());
    cmd.arg(repo_root().join("tests/peers/openpi_peer.py")).args(args);
    cmd
}

/// The `labrig` binary of this build (built on demand if a lone test run lacks it).
pub fn labrig_bin() -> PathBuf {
    workspace_bin("labrig", "labrig")
}

/// The `labrig-sim` binary (the sim bridge; the only program linking MuJoCo).
pub fn sim_bin() -> PathBuf {
    workspace_bin("labrig-sim", "labrig-sim")
}

/// A binary of this workspace's build, built on demand if a lone test run lacks it.
pub fn workspace_bin(name: &str, package: &str) -> PathBuf {
    // Test executables live in target/<profile>/deps; the binary one level up.
    let exe = std::env::current_exe().expect("current exe");
    let dir = exe.parent().and_then(Path::parent).expect("target/<profile>");
    let bin = dir.join(name);
    if !bin.exists() {
        let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".into());
        let profile = dir.file_name().and_then(|s| s.to_str()).unwrap_or("debug");
        let mut cmd = Command::new(cargo);
        cmd.args(["build", "-p", package, "--bin", name]).current_dir(repo_root());
        if profile == "release" {
            cmd.arg("--release");
        }
        let status = cmd.status().expect("running cargo build");
        assert!(status.success(), "building the {name} binary failed");
    }
    bin
}

/// The sim bridge as the hardware behind the nodes' `sim` backends: realtime, arm and
/// gripper topics under /sim, no cameras, stopped after 60 s of ticks at most.
pub fn sim_hardware(domain: u16) -> Proc {
    let mut cmd = Command::new(sim_bin());
    cmd.args(["run", "--mode", "realtime", "--no-cameras", "--hardware-prefix", "/sim", "--max-ticks", "1200"])
        .args(["--domain-id", &domain.to_string()]);
    Proc::spawn("labrig-sim run --hardware-prefix /sim", cmd)
}

/// A node program of this workspace in front of [`sim_hardware`]: `<program> run --backend sim`.
pub fn sim_backend_node(program: &str, domain: u16) -> Proc {
    let mut cmd = Command::new(workspace_bin(program, program));
    cmd.args(["run", "--backend", "sim", "--domain-id", &domain.to_string()]);
    Proc::spawn(&format!("{program} run --backend sim"), cmd)
}

/// The silence (ms) a watchdog hold reports in `/arm/state.fault`
/// ("watchdog: no arm command for 100.1 ms; ..."); panics on any other text.
pub fn watchdog_silence_ms(fault: &str) -> f64 {
    fault
        .strip_prefix("watchdog: no arm command for ")
        .and_then(|r| r.split(' ').next())
        .and_then(|v| v.parse().ok())
        .unwrap_or_else(|| panic!("unexpected hold report: {fault}"))
}

/// Every DDS domain the suite uses: (key, first domain, how many in a row). Tests run in
/// parallel, each rig on its own domain, so that no test sees another's nodes (it happened: the
/// recorder test and the lockstep test once shared a domain and the lockstep run stalled).
/// [`domain_for`] and [`domains_for`] are the only way a test gets a domain and panic on a key
/// missing here; `tests/tests/domains.rs` checks that no two entries overlap and that none
/// meets a domain labrig's commands use by default (0, `labrig demo`'s 42, 43, 44, and
/// `labrig bench faults`' 70 onward), so a developer's demo beside the suite stays apart too.
pub const TEST_DOMAINS: &[(&str, u16, u16)] = &[
    ("calibration_reaches_the_metadata", 100, 1),
    ("calibration_live_rig", 101, 1),
    ("cameras_stream", 102, 1),
    ("cameras_refusals", 103, 1),
    ("cameras_bench_rig", 104, 1),
    ("cameras_realsense", 105, 1),
    ("cdr", 106, 1),
    ("demo_records_expert_episodes", 107, 1),
    ("sigint", 108, 1),
    ("control_loop_vs_lockstep_bridge", 109, 1),
    ("control_loop_operator_events", 110, 1),
    ("fault_dds_stop_continue", 115, 1),
    ("fault_participant_limit", 116, 1),
    ("the_fci_backend_moves_franka_sims_fr3_along_commanded_paths", 117, 1),
    ("a_reflex_and_a_killed_franka_sim_are_reported_as_faults", 118, 1),
    ("the_franka_bench_reports_command_latencies", 119, 1),
    ("the_sim_backend_drives_the_sim_bridge_through_the_node", 120, 1),
    ("the_gripper_node_drives_an_emulated_2f85", 121, 1),
    ("the_gripper_node_drives_the_sim_bridges_2f85", 122, 1),
    ("launch_sim_droid_rig", 123, 1),
    ("launch_broken_rig", 124, 1),
    ("launch_orphans", 125, 1),
    ("launch_devices_handed", 184, 1),
    ("joint_states_100hz", 126, 1),
    ("pose_stamped_from_rclpy", 127, 1),
    ("rclpy_calls_labrig", 128, 1),
    ("labrig_calls_rclpy", 129, 1),
    ("topic_echo_rclpy", 130, 1),
    ("missing_topic", 131, 1),
    ("loopback_capture", 132, 1),
    ("policy_server_node_serves", 134, 1),
    ("recorder_node_vs_sim_bridge", 135, 1),
    ("recorder_orphan_unjudged", 136, 1),
    ("rollout_lockstep", 137, 1),
    ("rollout_pixels", 138, 1),
    ("rollout_delay", 139, 1),
    ("rollout_server_faults", 140, 1),
    ("rclpy_sees_the_bridges_joint_states_and_camera_info", 141, 1),
    ("lockstep_a", 142, 1),
    ("lockstep_b", 143, 1),
    ("refused_nan", 144, 1),
    ("refused_limit", 145, 1),
    ("refused_then_ok", 146, 1),
    ("the_watchdog_holds_the_arm_when_commands_stop", 147, 1),
    ("following_the_expert_over_ros", 148, 1),
    ("station_sim_droid", 149, 1),
    ("station_browser", 150, 1),
    ("bench_station", 151, 1),
    ("takeover_grip", 152, 1),
    ("takeover_expert", 153, 1),
    ("teleop_square_trace_drives_the_rig", 154, 1),
    ("teleop_vanished_controller_holds", 155, 1),
    ("teleop_b_records_a_failure", 156, 1),
    ("teleop_adb_reconnects", 157, 1),
    ("train_demo_episodes", 158, 1),
    ("fault_bench_recorder_kill", 159, 3),
    ("fault_bench_disk_full", 162, 2),
    ("fault_bench_dds_stop", 164, 1),
    ("fault_bench_bridge_kill", 165, 1),
    ("fault_bench_camera_stall", 166, 1),
    ("openpi_remote_droid", 167, 1),
    ("openpi_remote_faults", 168, 1),
    ("openpi_server_rollout", 169, 1),
    ("torchscript_rollout", 170, 1),
    ("openpi_remote_timing", 171, 1),
    ("lerobot_export_demo", 172, 1),
    ("lerobot_trained_rollout", 173, 1),
    ("experiment_retrieval_ci", 174, 2),
    ("train_distributed_demo", 111, 1),
    // (No DDS: the port of its franka-sim, 20000 + the domain, as the franka tests do.)
    ("doctor_franka_sim", 176, 1),
    ("rollout_rtc", 177, 1),
    ("rollout_rtc_refused", 178, 1),
    ("recorder_scene_bound", 179, 1),
    ("docs_guides_run", 180, 1),
    ("torchscript_rtc", 181, 1),
    ("pinned_pick_place", 182, 1),
    ("pinned_drawer", 183, 1),
    ("cameras_zed_rectified", 185, 1),
    ("launch_second_rig", 186, 1),
    ("launch_two_rigs", 187, 2),
    ("experiment_retrieval_droid_ci", 189, 2),
    ("bench_soak", 191, 1),
    ("ros2_interfaces_rollout", 192, 1),
    ("ros2_interfaces_arm", 193, 1),
];

/// The DDS domains labrig's commands use when none is given (see [`TEST_DOMAINS`]).
/// (`labrig experiment retrieval`: 50 and, with `--jobs`, up to seven more; `labrig bench
/// latency`: 47; `labrig bench soak`: 45.)
pub const DEFAULT_DOMAINS: &[std::ops::RangeInclusive<u16>] = &[0..=0, 42..=45, 47..=47, 50..=57, 70..=79];

/// franka-sim on 127.0.0.1:`port` (see scripts/franka_sim_loopback.py).
pub fn franka_sim(port: u16, flags: &[&str]) -> Proc {
    let python = std::env::var_os("LABRIG_FRANKA_SIM_PYTHON")
        .map(Into::into)
        .unwrap_or_else(|| cache_dir().join("venv-franka-sim/bin/python"));
    assert!(python.exists(), "franka-sim venv {} is missing: run `bash scripts/setup.sh`", python.display());
    // The FR3's controller is a dedicated realtime machine; on a loaded 2-core CI machine
    // franka-sim gets a realtime priority where the test may set one (root), else it runs as is.
    let realtime = Command::new("chrt").args(["--rr", "20", "true"]).status().is_ok_and(|s| s.success());
    let mut cmd = if realtime {
        let mut c = Command::new("chrt");
        c.args(["--rr", "20"]).arg(python);
        c
    } else {
        Command::new(python)
    };
    cmd.arg("-u")
        .arg(repo_root().join("scripts/franka_sim_loopback.py"))
        .args(["--no-gripper", "--port", &port.to_string()])
        .args(flags)
        .env("FR3_MJCF", cache_dir().join("franka-sim/fr3.xml"))
        .stdout(std::process::Stdio::null());
    Proc::spawn("franka-sim", cmd)
}

/// The DDS domain registered for `key` in [`TEST_DOMAINS`].
pub fn domain_for(key: &str) -> u16 {
    let (first, count) = domains_for(key);
    assert_eq!(count, 1, "test key `{key}` has {count} domains in TEST_DOMAINS: use domains_for");
    first
}

/// The first of the consecutive domains registered for `key` in [`TEST_DOMAINS`] (a command
/// that counts up from a given domain, such as `labrig bench faults`), and how many.
pub fn domains_for(key: &str) -> (u16, u16) {
    match TEST_DOMAINS.iter().find(|(k, _, _)| *k == key) {
        Some(&(_, first, count)) => (first, count),
        None => panic!("test key `{key}` has no DDS domain: add it to TEST_DOMAINS in tests/src/lib.rs"),
    }
}

/// The processes started for DDS domain `domain` by `labrig launch` (their command lines end
/// in `--domain-id <domain>`), one `pid command line` per line; empty when none.
pub fn nodes_on_domain(domain: u16) -> String {
    // `--` first: a pattern starting with `--` is otherwise read as an option, and pgrep exits
    // 2 printing nothing (which read as "none left").
    let out = Command::new("pgrep").args(["-a", "-f", "--", &format!("--domain-id {domain}$")]).output().unwrap();
    assert!(matches!(out.status.code(), Some(0 | 1)), "pgrep failed: {}", output_text(&out));
    String::from_utf8_lossy(&out.stdout).into_owned()
}

/// SIGKILLs whatever [`nodes_on_domain`] lists.
pub fn kill_domain(domain: u16) {
    let _ = Command::new("pkill").args(["-KILL", "-f", "--", &format!("--domain-id {domain}$")]).status();
}

/// Environment that keeps a Fast DDS (rclpy) process on loopback: the committed XML profile
/// (UDPv4 whitelisted to 127.0.0.1, unicast initial peers, no built-in transports) and
/// discovery range SYSTEM_DEFAULT (anything else makes rmw add multicast or LAN locators).
pub fn ros_env(cmd: &mut Command, domain: u16) {
    cmd.env("FASTDDS_DEFAULT_PROFILES_FILE", repo_root().join("scripts/fastdds_loopback.xml"))
        .env("ROS_AUTOMATIC_DISCOVERY_RANGE", "SYSTEM_DEFAULT")
        .env("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp")
        .env("ROS_DOMAIN_ID", domain.to_string());
}

/// Where `scripts/setup.sh` installed the colcon build of `ros2/labrig_msgs`
/// (`LABRIG_ROS_MSGS`, else the cache's).
pub fn ros_msgs_prefix() -> PathBuf {
    let p = match std::env::var_os("LABRIG_ROS_MSGS") {
        Some(p) => PathBuf::from(p),
        None => cache_dir().join("ros2-labrig-msgs/install/labrig_msgs"),
    };
    assert!(
        p.join("share/labrig_msgs/package.xml").exists(),
        "the colcon build of ros2/labrig_msgs is missing at {}: run `bash scripts/setup.sh` first",
        p.display()
    );
    p
}

/// What a Python process needs to import the generated labrig_msgs types: the package's
/// site-packages and its libraries (the venv's own come from the ROS wheels' bootstrapper).
pub fn labrig_msgs_env(cmd: &mut Command) {
    let prefix = ros_msgs_prefix();
    let site = std::fs::read_dir(prefix.join("lib"))
        .unwrap()
        .filter_map(|e| e.ok())
        .map(|e| e.path().join("site-packages"))
        .find(|p| p.join("labrig_msgs").exists())
        .unwrap_or_else(|| panic!("no lib/python*/site-packages/labrig_msgs under {}", prefix.display()));
    let join = |var: &str, first: PathBuf| match std::env::var_os(var) {
        Some(v) if !v.is_empty() => {
            let mut all = vec![first];
            all.extend(std::env::split_paths(&v));
            std::env::join_paths(all).unwrap()
        }
        _ => first.into_os_string(),
    };
    cmd.env("PYTHONPATH", join("PYTHONPATH", site))
        .env("LD_LIBRARY_PATH", join("LD_LIBRARY_PATH", prefix.join("lib")))
        .env("AMENT_PREFIX_PATH", join("AMENT_PREFIX_PATH", prefix));
}

/// A child process whose stdout lines arrive on a channel; killed on drop.
pub struct Proc {
    pub child: Child,
    lines: Receiver<String>,
    pub name: String,
    pub seen: Vec<String>,
}

impl Proc {
    pub fn spawn(name: &str, mut cmd: Command) -> Proc {
        cmd.stdout(Stdio::piped()).stdin(Stdio::null()).stderr(Stdio::inherit());
        let mut child = cmd.spawn().unwrap_or_else(|e| panic!("starting {name}: {e}"));
        let stdout = child.stdout.take().expect("piped stdout");
        let (tx, rx) = channel();
        std::thread::spawn(move || {
            for line in BufReader::new(stdout).lines() {
                let Ok(line) = line else { break };
                if tx.send(line).is_err() {
                    break;
                }
            }
        });
        Proc { child, lines: rx, name: name.to_owned(), seen: Vec::new() }
    }

    /// The rclpy peer (`tests/peers/ros_peer.py`) with the given arguments on `domain`.
    pub fn ros_peer(domain: u16, args: &[&str]) -> Proc {
        let mut cmd = Command::new(ros_python());
        cmd.arg(repo_root().join("tests/peers/ros_peer.py")).args(args);
        ros_env(&mut cmd, domain);
        Proc::spawn(&format!("ros_peer {}", args.first().unwrap_or(&"")), cmd)
    }

    /// The rclpy peer with labrig's own message types too: the Python types colcon generated
    /// from `ros2/labrig_msgs` (built by `scripts/setup.sh`, [`ros_msgs_prefix`]).
    pub fn ros_peer_with_labrig_msgs(domain: u16, args: &[&str]) -> Proc {
        let mut cmd = Command::new(ros_python());
        cmd.arg(repo_root().join("tests/peers/ros_peer.py")).args(args);
        ros_env(&mut cmd, domain);
        labrig_msgs_env(&mut cmd);
        Proc::spawn(&format!("ros_peer {}", args.first().unwrap_or(&"")), cmd)
    }

    /// The next stdout line, waiting at most `timeout`.
    pub fn next_line(&mut self, timeout: Duration) -> Option<String> {
        match self.lines.recv_timeout(timeout) {
            Ok(l) => {
                self.seen.push(l.clone());
                Some(l)
            }
            Err(RecvTimeoutError::Timeout | RecvTimeoutError::Disconnected) => None,
        }
    }

    /// Reads lines until one parses as JSON and satisfies `pred`; panics after `timeout`.
    pub fn wait_json(
        &mut self,
        timeout: Duration,
        what: &str,
        pred: impl Fn(&serde_json::Value) -> bool,
    ) -> serde_json::Value {
        let deadline = Instant::now() + timeout;
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            let Some(line) = self.next_line(left) else {
                panic!("{}: no {what} within {timeout:?}; output so far: {:?}", self.name, self.seen);
            };
            if let Ok(v) = serde_json::from_str::<serde_json::Value>(&line)
                && pred(&v)
            {
                return v;
            }
        }
    }

    /// Waits (bounded) for the process to exit and returns its code (checks at least once,
    /// so a zero timeout asks whether it has exited).
    pub fn wait_exit(&mut self, timeout: Duration) -> Option<i32> {
        let deadline = Instant::now() + timeout;
        loop {
            if let Some(status) = self.child.try_wait().expect("try_wait") {
                return status.code();
            }
            if Instant::now() >= deadline {
                return None;
            }
            std::thread::sleep(Duration::from_millis(20));
        }
    }
}

impl std::fmt::Debug for Proc {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "Proc({}, pid {})", self.name, self.child.id())
    }
}

impl Drop for Proc {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// The first message on `sub` within `timeout`; none: the test fails, naming `what`.
pub fn first_message<T: labrig_msgs::RosMessage>(
    sub: &labrig_runtime::ros::RosSubscription<T>,
    what: &str,
    timeout: Duration,
) -> T {
    let until = Instant::now() + timeout;
    loop {
        if let Some(m) = sub.try_take().unwrap() {
            return m.msg;
        }
        assert!(Instant::now() < until, "no {what} within {timeout:?}");
        std::thread::sleep(Duration::from_millis(10));
    }
}

/// A current-thread tokio runtime for a test body.
pub fn rt() -> tokio::runtime::Runtime {
    tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build().expect("tokio runtime")
}

/// Reads an episode directory with the reference readers (PyPI `mcap` + `mcap-ros2-support`,
/// `rosbags` on the directory and on the bare file) through tests/peers/read_episode.py.
pub fn read_episode_with_python(dir: &std::path::Path) -> serde_json::Value {
    let out = peer_script("LABRIG_READERS_PYTHON", "venv-readers", "read_episode.py", dir);
    assert!(out.status.success(), "read_episode.py failed: {}", String::from_utf8_lossy(&out.stderr));
    serde_json::from_slice(&out.stdout).expect("read_episode.py prints JSON")
}

/// The Python of a setup venv (`env` overrides it); a missing one fails, naming setup.
pub fn peer_python(env: &str, venv: &str) -> PathBuf {
    let python = std::env::var_os(env).map(PathBuf::from).unwrap_or_else(|| cache_dir().join(venv).join("bin/python"));
    assert!(python.exists(), "the venv {} is missing: run `bash scripts/setup.sh`", python.display());
    python
}

/// Runs `tests/peers/<script> <arg>` with the Python of a setup venv (`env` overrides it).
fn peer_script(env: &str, venv: &str, script: &str, arg: &std::path::Path) -> std::process::Output {
    let python = peer_python(env, venv);
    std::process::Command::new(&python)
        .arg(repo_root().join("tests/peers").join(script))
        .arg(arg)
        .output()
        .unwrap_or_else(|e| panic!("running {script}: {e}"))
}

/// tests/peers/check_droid.py (h5py, json, ffprobe) on a DROID raw root: whether it matches
/// DROID's layout, its per-episode reports, and the problems it printed.
pub fn check_droid_with_python(root: &std::path::Path) -> (bool, Vec<serde_json::Value>, String) {
    let out = peer_script("LABRIG_DROID_PYTHON", "venv-droid", "check_droid.py", root);
    let reports = String::from_utf8_lossy(&out.stdout)
        .lines()
        .map(|l| serde_json::from_str(l).expect("check_droid.py prints JSON lines"))
        .collect();
    (out.status.success(), reports, String::from_utf8_lossy(&out.stderr).into_owned())
}

/// A finished command's exit status, stdout and stderr, for assertion messages.
pub fn output_text(out: &std::process::Output) -> String {
    format!(
        "exit {:?}\nstdout: {}\nstderr: {}",
        out.status.code(),
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    )
}

/// Episode directories (holding an .mcap) under `root`.
pub fn episode_dirs(root: &std::path::Path) -> Vec<std::path::PathBuf> {
    let mut out = Vec::new();
    let Ok(rd) = std::fs::read_dir(root) else { return out };
    for e in rd.flatten() {
        let p = e.path();
        if p.is_dir() {
            if std::fs::read_dir(&p).unwrap().flatten().any(|f| f.path().extension().is_some_and(|x| x == "mcap")) {
                out.push(p);
            } else {
                out.extend(episode_dirs(&p));
            }
        }
    }
    out
}

/// Each camera's image messages in an episode file, in the file's order: (capture stamp, JPEG).
pub fn camera_images(file: &std::path::Path) -> std::collections::BTreeMap<String, Vec<(i64, Vec<u8>)>> {
    let buf = std::fs::read(file).unwrap_or_else(|e| panic!("{}: {e}", file.display()));
    let mut out: std::collections::BTreeMap<String, Vec<(i64, Vec<u8>)>> = Default::default();
    for m in mcap::MessageStream::new(&buf).expect("an MCAP file") {
        let m = m.expect("a readable message");
        let Some(rest) = m.channel.topic.strip_prefix(labrig_msgs::topics::CAMERAS_PREFIX) else { continue };
        let Some(cam) = rest.strip_suffix("/image/compressed") else { continue };
        let img: labrig_msgs::sensor_msgs::CompressedImage = labrig_msgs::decode(&m.data).expect("an image");
        out.entry(cam.to_owned()).or_default().push((labrig_msgs::Nanos::from(img.header.stamp).0, img.data));
    }
    out
}
