//! Teleop end to end in the simulated rig: the committed controller trace
//! (nodes/quest_teleop/tests/fixtures/square.logcat, 72 Hz, written from the documented
//! logcat format) played back by `labrig-teleop` drives the rig loop (`--source teleop`)
//! in front of the sim bridge in real time, with the recorder running:
//! - the TCP follows the traced path: 8 cm along +x while the grip is held, then 5 cm up
//!   after it is pressed again (error against the trace reported, bounded at 5 mm);
//! - with the grip released (the deadman) the arm holds while the controller moves 8 cm;
//! - the one-frame tracking glitch (40 cm) is refused, not followed;
//! - A ends the episode: recorded under success/ with success = true, steps from teleop;
//!   B (fail.logcat) records a failure;
//! - a vanished controller (vanish.logcat) holds the arm within 100 ms;
//! - the adb input starts the app and starts adb again when it drops.

use labrig_msgs::Nanos;
use labrig_runtime::frames::NAMESPACE_ENV;
use labrig_tests::{Proc, domain_for, labrig_bin, repo_root, sim_bin, workspace_bin};
use serde_json::Value;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant};

fn find_episode(root: &Path) -> Option<PathBuf> {
    let mut stack = vec![root.join("success"), root.join("failure")];
    while let Some(d) = stack.pop() {
        let Ok(entries) = std::fs::read_dir(&d) else { continue };
        for e in entries.flatten() {
            if e.path().join("metadata.yaml").is_file() {
                return Some(e.path());
            }
            if e.path().is_dir() {
                stack.push(e.path());
            }
        }
    }
    None
}

fn tcp(s: &labrig_msgs::rig::Step) -> [f64; 3] {
    let c = s.robot_state.cartesian_position;
    [c[0], c[1], c[2]]
}

fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

/// The sim bridge in real time (no cameras, sim time on the wall clock's line, as the teleop
/// node's stamps are), the recorder and the rig loop with the teleop source on operator
/// events, one episode; the episode started.
struct Rig {
    domain: String,
    root: PathBuf,
    control: Proc,
    _bridge: Proc,
    _recorder: Proc,
    _tmp: tempfile::TempDir,
}

impl Rig {
    fn start(key: &str, note: &str) -> Rig {
        let domain = domain_for(key).to_string();
        let ns = format!("{key}_{}", std::process::id());
        let tmp = tempfile::tempdir().unwrap();
        let root = tmp.path().join("episodes");
        let mut bridge = Command::new(sim_bin());
        bridge
            .args(["run", "--mode", "realtime", "--no-cameras", "--wall-clock-origin", "--domain-id", &domain])
            .env(NAMESPACE_ENV, &ns);
        let bridge = Proc::spawn("labrig-sim run", bridge);
        let mut recorder = Command::new(workspace_bin("labrig-recorder", "labrig-recorder"));
        recorder.args(["run", "--domain-id", &domain, "--root"]).arg(&root).env(NAMESPACE_ENV, &ns);
        let recorder = Proc::spawn("labrig-recorder run", recorder);
        let mut control = Command::new(workspace_bin("labrig-control", "labrig-control"));
        control
            .args(["run", "--source", "teleop", "--clock", "sim", "--manual", "--no-reseed", "--episodes", "1"])
            .args(["--domain-id", &domain])
            .env(NAMESPACE_ENV, &ns);
        let control = Proc::spawn("labrig-control run", control);
        // The operator starts the episode (`labrig episode` waits for the loop itself).
        let rig = Rig { domain, root, control, _bridge: bridge, _recorder: recorder, _tmp: tmp };
        rig.event("start", note);
        rig
    }

    fn event(&self, kind: &str, note: &str) {
        let out = Command::new(labrig_bin())
            .args(["episode", kind, "--note", note, "--domain-id", &self.domain])
            .output()
            .unwrap();
        assert!(out.status.success(), "episode {kind}: {}", String::from_utf8_lossy(&out.stderr));
    }

    /// Plays a committed trace through `labrig-teleop` to its end; its figures.
    fn play(&self, trace: &str) -> Value {
        let trace = repo_root().join("nodes/quest_teleop/tests/fixtures").join(trace);
        let teleop = Command::new(workspace_bin("labrig-teleop", "labrig-teleop"))
            .args(["run", "--exit-at-end", "--json", "--domain-id", &self.domain, "--file"])
            .arg(&trace)
            .output()
            .unwrap();
        assert!(teleop.status.success(), "teleop: {}", String::from_utf8_lossy(&teleop.stderr));
        let stats: Value = serde_json::from_slice(&teleop.stdout).unwrap();
        eprintln!("teleop: {stats}");
        stats
    }

    /// Waits for the loop to finish its episode and the recorder to file it.
    fn recorded(&mut self) -> (PathBuf, labrig_episode::inspect::EpisodeData) {
        assert_eq!(self.control.wait_exit(Duration::from_secs(60)), Some(0), "the loop ends after its episode");
        let deadline = Instant::now() + Duration::from_secs(20);
        let dir = loop {
            if let Some(d) = find_episode(&self.root) {
                break d;
            }
            assert!(Instant::now() < deadline, "no episode recorded under {}", self.root.display());
            std::thread::sleep(Duration::from_millis(200));
        };
        let ep = labrig_episode::inspect::read_episode(&dir).unwrap();
        (dir, ep)
    }
}

#[test]
fn a_recorded_controller_trace_drives_the_sim_rig() {
    let mut rig = Rig::start("teleop_square_trace_drives_the_rig", "teleop square trace");
    let stats = rig.play("square.logcat");
    assert_eq!(stats["lines"]["bad"], 0);
    assert!(stats["lines"]["readings"].as_u64().unwrap() >= 600, "{stats}");
    assert_eq!(stats["jumps_refused"], 1, "the glitch frame: {stats}");
    assert_eq!(stats["events"], serde_json::json!(["success (A/X)"]));

    // A -> Success -> the arm home -> the loop exits (one episode); the recorder files it.
    let (dir, ep) = rig.recorded();
    assert!(dir.starts_with(rig.root.join("success")), "{}", dir.display());
    let meta = ep.metadata.unwrap();
    assert_eq!(meta.success, Some(true));
    assert_eq!(meta.task_instruction, "teleop square trace");
    let steps = ep.steps;
    assert!(steps.len() > 100, "{} steps", steps.len());
    assert!(steps.iter().all(|s| s.action_source == labrig_msgs::rig::Step::SOURCE_TELEOP));

    // The phases, from the recorded deadman: off, on (8 cm +x), off (controller moves 8 cm
    // +y), on (5 cm up).
    let mut runs: Vec<(bool, usize, usize)> = Vec::new();
    for (i, s) in steps.iter().enumerate() {
        match runs.last_mut() {
            Some((on, _, end)) if *on == s.movement_enabled => *end = i,
            _ => runs.push((s.movement_enabled, i, i)),
        }
    }
    let on: Vec<&(bool, usize, usize)> = runs.iter().filter(|r| r.0).collect();
    assert_eq!(on.len(), 2, "two grip presses: {runs:?}");
    let (first, second) = (on[0], on[1]);
    // Between them, the deadman released: the arm stays.
    let (hold_from, hold_to) = (first.2 + 1, second.1 - 1);
    assert!(hold_to > hold_from + 20, "about 1.5 s released: {runs:?}");
    let held = tcp(&steps[hold_from]);
    let drift = (hold_from..=hold_to)
        .map(|i| sub(tcp(&steps[i]), held).iter().map(|v| v * v).sum::<f64>().sqrt())
        .fold(0.0, f64::max);
    let first_move = sub(tcp(&steps[first.2]), tcp(&steps[first.1]));
    let second_move = sub(tcp(&steps[second.2]), tcp(&steps[second.1]));
    let err1 = sub(first_move, [0.08, 0.0, 0.0]).iter().map(|v| v * v).sum::<f64>().sqrt();
    let err2 = sub(second_move, [0.0, 0.0, 0.05]).iter().map(|v| v * v).sum::<f64>().sqrt();
    eprintln!(
        "teleop trace: first press moved {first_move:?} (error {:.1} mm), released drift {:.2} mm, second press moved {second_move:?} (error {:.1} mm)",
        err1 * 1e3,
        drift * 1e3,
        err2 * 1e3
    );
    assert!(err1 < 0.005, "8 cm along +x followed within 5 mm: {first_move:?}");
    assert!(err2 < 0.005, "5 cm up followed within 5 mm: {second_move:?}");
    assert!(drift < 0.002, "the arm holds while the grip is released: {drift}");
    // The glitch was not followed: no step moved the TCP more than the safety layer's 7.5 cm
    // bound, and none more than 2 cm at all (the trace moves at most ~6 cm/s).
    let max_step = steps
        .windows(2)
        .map(|w| sub(tcp(&w[1]), tcp(&w[0])).iter().map(|v| v * v).sum::<f64>().sqrt())
        .fold(0.0, f64::max);
    assert!(max_step < 0.02, "largest TCP step {max_step}");
    // The recording carries the controller as the node saw it.
    let topics = labrig_episode::inspect::inspect(&dir).unwrap().topics;
    let count = |t: &str| topics.iter().find(|x| x.topic == t).map_or(0, |x| x.count);
    assert!(count("/teleop/state") > 300 && count("/teleop/action") > 300, "{topics:?}");
}

/// The controller vanishes mid-motion (the trace's lines stop while the grip is held and the
/// hand moves): the loop follows no reading older than 35 ms and holds the arm on the tick
/// after (35 ms + a 50 ms tick after the last reading, on time), and it stays held.
#[test]
fn a_vanished_controller_holds_the_arm_on_the_next_tick() {
    let mut rig = Rig::start("teleop_vanished_controller_holds", "teleop vanish");
    let stats = rig.play("vanish.logcat");
    assert_eq!(stats["lines"]["bad"], 0);
    assert_eq!(stats["stale_holds"], 1, "the node saw the controller go: {stats}");
    rig.event("failure", "the controller vanished");
    let (dir, ep) = rig.recorded();
    assert!(dir.starts_with(rig.root.join("failure")), "{}", dir.display());
    // The last reading the node turned into an action (recorded on /teleop/action).
    let last_action = last_stamp(&dir, "/teleop/action");
    let steps = ep.steps;
    let moving: Vec<usize> = (0..steps.len()).filter(|&i| steps[i].movement_enabled).collect();
    assert!(moving.len() > 20, "the arm moved while the grip was held: {} steps", moving.len());
    let last_moving = *moving.last().unwrap();
    let held = &steps[last_moving + 1];
    assert!(!held.movement_enabled);
    let hold_ms = (held.timing.step_start - last_action) as f64 / 1e6;
    let moving_ms = (steps[last_moving].timing.step_start - last_action) as f64 / 1e6;
    eprintln!(
        "vanished controller: last moving step {moving_ms:.1} ms after the last reading, hold {hold_ms:.1} ms after it"
    );
    // The rule, exact in the loop's own stamps: it follows an action only while it is at most
    // teleop_max_age_s (35 ms) old when the tick starts, so the last moving step started
    // within 35 ms of the last reading. The hold then comes on the next tick: 35 ms + one 50 ms
    // period on time; the slack above that (65 ms) is for a tick that starts late on a busy
    // shared machine (two processes and the sim in real time), so this checks "the next tick
    // or so", not a latency figure.
    assert!(moving_ms <= 35.0, "the loop followed a reading {moving_ms:.1} ms old (limit 35 ms)");
    assert!(hold_ms <= 35.0 + 50.0 + 65.0, "held {hold_ms:.1} ms after the last reading");
    // Held: from the hold on, every step commands the same joints (the arm's last target),
    // and the TCP, once it has caught up with that target (0.3 s), stays.
    let target = steps[last_moving + 1].action.joint_position;
    assert!(steps[last_moving + 1..].iter().all(|s| s.action.joint_position == target), "the held target changed");
    assert!(steps.len() > last_moving + 12, "the hold was recorded for a while: {} steps", steps.len());
    let stop = tcp(&steps[last_moving + 7]);
    let drift = steps[last_moving + 7..]
        .iter()
        .map(|s| sub(tcp(s), stop).iter().map(|v| v * v).sum::<f64>().sqrt())
        .fold(0.0, f64::max);
    assert!(drift < 0.002, "the arm stays held: {drift}");
}

/// The newest header stamp on `topic` in an episode (read with the PyPI-independent path:
/// this crate's own MCAP reader through labrig-recorder).
fn last_stamp(dir: &Path, topic: &str) -> i64 {
    let file = dir.join(labrig_episode::episode::EPISODE_FILE);
    let buf = std::fs::read(&file).unwrap();
    let mut last = i64::MIN;
    for m in mcap::MessageStream::new(&buf).unwrap() {
        let m = m.unwrap();
        if m.channel.topic == topic {
            let a: labrig_msgs::rig::ArmCommand = labrig_msgs::decode(&m.data).unwrap();
            last = last.max(Nanos::from(a.header.stamp).0);
        }
    }
    last
}

/// B ends the episode as a failure: recorded under failure/ with success = false, after the
/// arm followed the trace's 3 cm toward -y.
#[test]
fn b_records_a_failure() {
    let mut rig = Rig::start("teleop_b_records_a_failure", "teleop fail trace");
    let stats = rig.play("fail.logcat");
    assert_eq!(stats["events"], serde_json::json!(["failure (B/Y)"]));
    let (dir, ep) = rig.recorded();
    assert!(dir.starts_with(rig.root.join("failure")), "{}", dir.display());
    assert_eq!(ep.metadata.unwrap().success, Some(false));
    let moving: Vec<&labrig_msgs::rig::Step> = ep.steps.iter().filter(|s| s.movement_enabled).collect();
    let moved = sub(tcp(moving.last().unwrap()), tcp(moving[0]));
    eprintln!("fail trace: moved {moved:?}");
    let err = sub(moved, [0.0, -0.03, 0.0]).iter().map(|v| v * v).sum::<f64>().sqrt();
    assert!(err < 0.005, "3 cm toward -y followed within 5 mm: {moved:?}");
}

/// The adb input: the node starts the headset app, runs `adb logcat`, and when adb exits (the
/// device dropped) starts it again. Against a stand-in `adb` script (no headset here) that
/// logs its arguments and prints 40 lines of the square trace per logcat run, then exits.
#[test]
fn the_adb_input_starts_the_app_and_reconnects_when_adb_drops() {
    let domain = domain_for("teleop_adb_reconnects").to_string();
    let tmp = tempfile::tempdir().unwrap();
    let log = tmp.path().join("adb.log");
    let adb = tmp.path().join("adb");
    std::fs::write(
        &adb,
        "#!/bin/sh\necho \"$@\" >> \"$ADB_LOG\"\ncase \"$*\" in\n  *logcat*) head -n 40 \"$ADB_TRACE\"; exit 0 ;;\nesac\nexit 0\n",
    )
    .unwrap();
    std::process::Command::new("chmod").arg("+x").arg(&adb).status().unwrap();
    let cfg = tmp.path().join("teleop.toml");
    std::fs::write(
        &cfg,
        format!("[input]\nkind = \"adb\"\nadb = \"{}\"\ndevice = \"1WMHH0TEST\"\nreconnect_s = 0.2\n", adb.display()),
    )
    .unwrap();
    let mut cmd = Command::new(workspace_bin("labrig-teleop", "labrig-teleop"));
    cmd.args(["run", "--json", "--domain-id", &domain, "--config"])
        .arg(&cfg)
        .env("ADB_LOG", &log)
        .env("ADB_TRACE", repo_root().join("nodes/quest_teleop/tests/fixtures/square.logcat"))
        .stdout(std::process::Stdio::piped());
    let child = cmd.spawn().unwrap();
    std::thread::sleep(Duration::from_secs(3));
    Command::new("kill").args(["-TERM", &child.id().to_string()]).status().unwrap();
    let out = child.wait_with_output().unwrap();
    assert!(out.status.success(), "{:?}", out.status);
    let stats: Value = serde_json::from_slice(&out.stdout).unwrap();
    let calls = std::fs::read_to_string(&log).unwrap();
    let logcats = calls.lines().filter(|l| l.contains("logcat")).count();
    eprintln!("adb calls:\n{calls}\nteleop: {stats}");
    assert!(logcats >= 3, "adb logcat started again after each drop: {logcats}");
    assert!(calls.lines().all(|l| l.starts_with("-s 1WMHH0TEST ")), "every call names the device: {calls}");
    assert!(calls.contains("shell am start -n com.rail.oculus.teleop/com.rail.oculus.teleop.MainActivity"));
    assert!(calls.contains("logcat -T 0 -v epoch wE9ryARX:V *:S"), "{calls}");
    let readings = stats["lines"]["readings"].as_u64().unwrap();
    // Every line of every finished run is read; the run our SIGTERM cut short may have been
    // logged by the stand-in before its lines reached the node (seen once under load: 584/600).
    let finished = 40 * (logcats as u64 - 1);
    assert!(
        (finished..=40 * logcats as u64).contains(&readings),
        "every line of every run read: {readings} readings from {logcats} runs of 40: {stats}"
    );
}
