//! `labrig doctor --rig <launch config>` against what stands in for a rig's hardware here:
//! franka-sim (the FCI on 127.0.0.1), an emulated 2F-85 on a pseudo-terminal, cameras that are
//! ffmpeg's (a video file ffmpeg wrote, its test pattern), calibration files. The ready rig
//! passes (exit 0); each broken part (an unreachable robot, a silent gripper, a missing
//! gripper port, a missing camera, a wrong serial, a mode the camera does not send, a stale
//! calibration, a checkpoint that does not load) fails its own row, naming the fix, and the
//! rig is not ready (exit 3).

use labrig_gripper::{Emulated2F85, EmulatorConfig};
use labrig_msgs::calibration::CalibrationFile;
use labrig_tests::{domain_for, franka_sim, labrig_bin, output_text, rt, workspace_bin};
use serde_json::Value;
use std::path::Path;
use std::process::Command;
use std::time::{Duration, Instant};

/// The rig's files in `dir`: a launch config and its nodes' configs. `edit` changes the text
/// of a file (by name) before it is written.
fn write_rig(dir: &Path, fr3: &str, pty: &str, edit: impl Fn(&str, String) -> String) -> std::path::PathBuf {
    let files = [
        (
            "rig.toml",
            format!(
                r#"[rig]
name = "doctor_test"
[rig.devices]
robot_ip = "{fr3}"
[rig.devices.camera_serials]
[[node]]
name = "franka"
program = "labrig-franka"
args = ["run"]
config = "franka.toml"
health = "/arm/state"
[[node]]
name = "gripper"
program = "labrig-gripper"
args = ["run"]
config = "gripper.toml"
health = "/gripper/state"
[[node]]
name = "cameras"
program = "labrig-cameras"
args = ["run"]
config = "cameras.toml"
health = "/cameras/status"
[[node]]
name = "control"
program = "labrig-control"
args = ["run"]
config = "control.toml"
health = "/control/status"
[[node]]
name = "recorder"
program = "labrig-recorder"
args = ["run", "--root", "{root}"]
config = "recorder.toml"
health = "/recorder/status"
"#,
                root = dir.join("episodes").display()
            ),
        ),
        ("franka.toml", format!("backend = \"fci\"\nrobot_ip = \"{fr3}\"\n[fci]\nrealtime = false\n")),
        ("gripper.toml", format!("backend = \"robotiq\"\nport = \"{pty}\"\n")),
        (
            "cameras.toml",
            "[cameras.ext1]\nsource = \"cam.mp4\"\nwidth = 320\nheight = 240\nfps = 15\n\
             [cameras.ext2]\nsource = \"testsrc\"\nwidth = 320\nheight = 240\nfps = 15\n"
                .to_owned(),
        ),
        (
            "control.toml",
            format!(
                "source = \"hold\"\nauto_start = false\nclock = \"wall\"\ncameras = [\"ext1\", \"ext2\"]\ncalibration = \"{}\"\n",
                dir.join("calibration").display()
            ),
        ),
        (
            "recorder.toml",
            "[rig]\nlab = \"LABRIG\"\nbuilding = \"bench\"\nuser = \"ci\"\nrobot_serial = \"franka-sim\"\n\
             [rig.camera_serials]\n"
                .to_owned(),
        ),
    ];
    for (name, text) in files {
        std::fs::write(dir.join(name), edit(name, text)).unwrap();
    }
    dir.join("rig.toml")
}

/// `labrig doctor --rig <launch> --json`: the exit code and the report. The disk must hold
/// `hours` of recording (a minute by default: this machine's free space is not under test).
fn doctor_for(launch: &Path, hours: &str) -> (i32, Value) {
    let out = Command::new(labrig_bin())
        .args(["doctor", "--json", "--timeout-s", "5", "--record-hours", hours, "--rig"])
        .arg(launch)
        .output()
        .unwrap();
    let report: Value = serde_json::from_slice(&out.stdout)
        .unwrap_or_else(|e| panic!("labrig doctor printed no JSON ({e}): {}", output_text(&out)));
    (out.status.code().unwrap_or(-1), report)
}

fn doctor(launch: &Path) -> (i32, Value) {
    doctor_for(launch, "0.02")
}

/// The rows whose part starts with `part`.
fn rows<'a>(report: &'a Value, part: &str) -> Vec<&'a Value> {
    report["checks"].as_array().unwrap().iter().filter(|c| c["part"].as_str().unwrap().starts_with(part)).collect()
}

fn the_row<'a>(report: &'a Value, part: &str) -> &'a Value {
    let r = rows(report, part);
    assert_eq!(r.len(), 1, "one row `{part}` expected: {report:#}");
    r[0]
}

fn failed(report: &Value) -> Vec<String> {
    report["checks"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|c| c["state"] == "fail")
        .map(|c| c["part"].as_str().unwrap().to_owned())
        .collect()
}

/// `part` fails alone (every other row as in the ready rig), its detail and fix saying `detail`
/// and `fix`.
fn fails_alone(launch: &Path, part: &str, detail: &str, fix: &str) {
    fails_alone_for(launch, "0.02", part, detail, fix)
}

fn fails_alone_for(launch: &Path, hours: &str, part: &str, detail: &str, fix: &str) {
    let (code, report) = doctor_for(launch, hours);
    assert_eq!(code, 3, "a rig with a broken {part} is not ready: {report:#}");
    assert_eq!(report["ready"], false);
    assert_eq!(failed(&report), [part], "{report:#}");
    let row = the_row(&report, part);
    assert!(row["detail"].as_str().unwrap().contains(detail), "{part}: {row:#}");
    assert!(row["fix"].as_str().unwrap().contains(fix), "{part}'s fix: {row:#}");
}

#[test]
fn the_doctor_passes_a_ready_rig_and_names_each_broken_part_with_its_fix() {
    // Built first: labrig_bin builds only what is missing.
    let _ = (
        labrig_bin(),
        workspace_bin("labrig-doctor", "labrig-doctor"),
        workspace_bin("labrig-policy", "labrig-policy-server"),
    );
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    let port = 20_000 + domain_for("doctor_franka_sim");
    let fr3 = format!("127.0.0.1:{port}");
    let _sim = franka_sim(port, &[]);
    // The emulator serves its pty on this runtime's threads.
    let rt = rt();
    let _in_rt = rt.enter();
    let gripper = Emulated2F85::new(EmulatorConfig::default());
    let pty = gripper.serve_on_pty().unwrap();
    // A camera that is a video file: 320x240 at 15 fps, as ffmpeg wrote it.
    let made = Command::new("ffmpeg")
        .args(["-v", "error", "-y", "-f", "lavfi", "-i", "testsrc2=size=320x240:rate=15", "-t", "1"])
        .args(["-pix_fmt", "yuv420p"])
        .arg(dir.join("cam.mp4"))
        .output()
        .unwrap();
    assert!(made.status.success(), "ffmpeg: {}", output_text(&made));
    let calibration = dir.join("calibration");
    std::fs::create_dir_all(&calibration).unwrap();
    let now = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).unwrap().as_secs() as i64;
    let calibrate = |camera: &str, at: i64| {
        let f = CalibrationFile::example(camera, at);
        std::fs::write(calibration.join(format!("{camera}.json")), serde_json::to_string(&f).unwrap()).unwrap();
    };
    calibrate("ext1", now - 60);
    calibrate("ext2", now - 60);

    // franka-sim takes a few seconds to listen.
    let deadline = Instant::now() + Duration::from_secs(60);
    while std::net::TcpStream::connect(("127.0.0.1", port)).is_err() {
        assert!(Instant::now() < deadline, "franka-sim does not listen on {port}");
        std::thread::sleep(Duration::from_millis(200));
    }

    // The ready rig.
    let launch = write_rig(dir, &fr3, pty.path(), |_, t| t);
    let (code, report) = doctor(&launch);
    assert_eq!((code, &report["ready"]), (0, &Value::Bool(true)), "{report:#}");
    assert!(the_row(&report, "FR3")["detail"].as_str().unwrap().contains("FCI version"), "{report:#}");
    assert!(the_row(&report, "2F-85")["detail"].as_str().unwrap().contains("answers"), "{report:#}");
    assert!(the_row(&report, "camera ext1")["detail"].as_str().unwrap().contains("320x240 at 15.0 fps"), "{report:#}");
    assert_eq!(the_row(&report, "camera ext2")["state"], "ok");
    assert_eq!(rows(&report, "calibration ").len(), 2, "{report:#}");
    for part in ["disk", "DDS", "launch config", "episode metadata"] {
        assert_eq!(the_row(&report, part)["state"], "ok", "{report:#}");
    }
    let programs = rows(&report, "program ");
    assert!(!programs.is_empty(), "no program rows: {report:#}");
    assert!(programs.iter().all(|r| r["state"] == "ok"), "{report:#}");
    // A disk that cannot hold the hours asked for (a million hours of these cameras).
    fails_alone_for(&launch, "1000000", "disk", "1000000 h at the configured cameras", "--root");
    // The table people read: the same verdict.
    let table =
        Command::new(labrig_bin()).args(["doctor", "--record-hours", "0.02", "--rig"]).arg(&launch).output().unwrap();
    assert!(table.status.success(), "{}", output_text(&table));
    assert!(String::from_utf8_lossy(&table.stdout).contains("ready: the rig of"), "{}", output_text(&table));

    // The recorder would label real episodes with the simulator's identity (a warning: the rig
    // is still ready), or with a camera serial other than the rig's (not ready).
    let launch = write_rig(dir, &fr3, pty.path(), |name, t| if name == "recorder.toml" { String::new() } else { t });
    let (code, report) = doctor(&launch);
    assert_eq!(code, 0, "{report:#}");
    let row = the_row(&report, "episode metadata");
    assert_eq!(row["state"], "warn", "{report:#}");
    assert!(row["detail"].as_str().unwrap().contains("robot sim-fr3"), "{row:#}");
    let launch = write_rig(dir, &fr3, pty.path(), |name, t| match name {
        "rig.toml" => t.replace("[rig.devices.camera_serials]\n", "[rig.devices.camera_serials]\nrs9 = \"D435-1\"\n"),
        "recorder.toml" => format!("{t}rs9 = \"D435-2\"\n"),
        _ => t,
    });
    fails_alone(&launch, "episode metadata", "rs9 D435-2 (the rig: D435-1)", "[rig.devices.camera_serials]");

    // An unreachable robot: nothing listens at its address (on loopback: another port).
    let closed = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap();
    let nobody = closed.to_string();
    fails_alone(&write_rig(dir, &nobody, pty.path(), |_, t| t), "FR3", &nobody, "activate FCI");

    // The gripper's port is not there; then a gripper that does not answer.
    let launch = write_rig(dir, &fr3, "/dev/ttyLABRIGNONE", |_, t| t);
    fails_alone(&launch, "2F-85", "/dev/ttyLABRIGNONE", "plug in the USB-RS485 adapter");
    gripper.set_mute(true);
    let launch = write_rig(dir, &fr3, pty.path(), |_, t| t);
    fails_alone(&launch, "2F-85", "slave 9", "24 V");
    gripper.set_mute(false);

    // A missing camera; a camera whose serial differs from the rig's; a mode the camera does
    // not send.
    let with_ext3 = |source: &'static str, rig_serial: &'static str| {
        move |name: &str, t: String| match name {
            "cameras.toml" => {
                format!(
                    "{t}[cameras.ext3]\nsource = \"{source}\"\nwidth = 1280\nheight = 720\nfps = 60\nrectify = false\n"
                )
            }
            "rig.toml" if !rig_serial.is_empty() => t.replace(
                "[rig.devices.camera_serials]\n",
                &format!("[rig.devices.camera_serials]\next3 = \"{rig_serial}\"\n"),
            ),
            _ => t,
        }
    };
    let launch = write_rig(dir, &fr3, pty.path(), with_ext3("zed:LABRIG0000", ""));
    fails_alone(&launch, "camera ext3", "no such camera connected", "labrig cameras list");
    let launch = write_rig(dir, &fr3, pty.path(), with_ext3("zed:LABRIG0000", "LABRIG0001"));
    fails_alone(&launch, "camera ext3", "wrong serial", "same serial");
    // A camera named by its kind alone takes the rig's serial (sought, and not connected here);
    // with none in the rig's devices it is named.
    let launch = write_rig(dir, &fr3, pty.path(), with_ext3("zed", "LABRIG0002"));
    fails_alone(&launch, "camera ext3", "LABRIG0002", "labrig cameras list");
    let launch = write_rig(dir, &fr3, pty.path(), with_ext3("zed", ""));
    fails_alone(&launch, "camera ext3", "names no serial", "[rig.devices.camera_serials]");
    let launch = write_rig(dir, &fr3, pty.path(), |name, t| {
        if name == "cameras.toml" { t.replacen("width = 320\nheight = 240", "width = 640\nheight = 480", 1) } else { t }
    });
    fails_alone(&launch, "camera ext1", "sends 320x240, the config asks for 640x480", "width/height");

    // A stale calibration (three days; the control node allows an hour).
    calibrate("ext2", now - 3 * 86_400);
    let launch = write_rig(dir, &fr3, pty.path(), |_, t| t);
    fails_alone(&launch, "calibration ext2", "3 days ago", "labrig calibrate check --camera ext2");
    calibrate("ext2", now - 60);

    // A policy checkpoint that is not there: the policy server's own loader says so.
    let launch = write_rig(dir, &fr3, pty.path(), |name, t| {
        if name == "rig.toml" {
            format!(
                "{t}[[node]]\nname = \"policy\"\nprogram = \"labrig-policy\"\nargs = [\"run\", \"--checkpoint\", \"{}\"]\nhealth = \"/policy/info\"\n",
                dir.join("no_such_run/checkpoints/last").display()
            )
        } else {
            t
        }
    });
    fails_alone(&launch, "policy", "no_such_run", "labrig train");
}
