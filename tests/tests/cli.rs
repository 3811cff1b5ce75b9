//! The `labrig` binary end to end: demo (recorded episodes), shm bench (functional, not timing), argument errors.

use labrig_tests::labrig_bin;
use serde_json::Value;
use std::process::Command;

/// The rig's five cameras, sorted as the reports' keys and names compare: every per-camera
/// array or map below is checked against it first, so a report that lost a camera (or all
/// of them) fails instead of looping over nothing.
const CAMERAS: [&str; 5] = ["ext1", "ext2", "rs1", "rs2", "wrist"];

/// The sorted names of a per-camera report.
fn sorted<'a>(names: impl Iterator<Item = &'a str>) -> Vec<&'a str> {
    let mut v: Vec<&str> = names.collect();
    v.sort_unstable();
    v
}

/// The README's main command: the simulated rig (sim bridge, recorder, control loop with the
/// scripted expert) records seeded pick-and-place episodes; each is complete, unflagged,
/// successful, holds every step and camera frame, and is read in full by the reference
/// readers (PyPI mcap + mcap-ros2-support, rosbags).
#[test]
fn demo_records_expert_episodes_that_the_reference_readers_read() {
    for p in ["labrig-sim", "labrig-recorder", "labrig-control"] {
        labrig_tests::workspace_bin(p, p); // `labrig demo` starts them from beside itself
    }
    let dir = tempfile::tempdir().unwrap();
    let domain = labrig_tests::domain_for("demo_records_expert_episodes");
    let out = Command::new(labrig_bin())
        .args(["demo", "--episodes", "2", "--first-seed", "3", "--json", "--domain-id", &domain.to_string(), "--out"])
        .arg(dir.path())
        .env(labrig_runtime::frames::NAMESPACE_ENV, format!("demo_{}", std::process::id()))
        .output()
        .unwrap();
    assert!(out.status.success(), "demo failed: {}", labrig_tests::output_text(&out));
    let r: Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(r["recorded"], 2, "{r}");
    assert_eq!(r["successes"], 2, "{r}");
    assert_eq!(r["ok"], true);
    let mut uuids = Vec::new();
    let episodes = r["episodes"].as_array().unwrap();
    assert_eq!(episodes.len(), 2, "one report per recorded episode: {r}");
    for (k, e) in episodes.iter().enumerate() {
        let i = &e["inspect"];
        assert_eq!(i["flags"], serde_json::json!([]), "episode {k}: {i}");
        assert_eq!(i["complete"], true);
        let steps = i["steps"].as_u64().unwrap();
        assert!((40..400).contains(&steps), "episode {k}: {steps} steps");
        assert_eq!(i["metadata"]["trajectory_length"], steps);
        assert_eq!(i["metadata"]["success"], true);
        assert_eq!(i["metadata"]["task_instruction"], "put the cube in the bin");
        // The scene of each episode is its own seed's (3, then 4).
        let scene: Value = serde_json::from_str(i["metadata"]["sim_scene"].as_str().unwrap()).unwrap();
        assert_eq!(scene["seed"], 3 + k as u64);
        let cameras = i["cameras"].as_array().unwrap();
        assert_eq!(sorted(cameras.iter().map(|c| c["camera"].as_str().unwrap())), CAMERAS, "episode {k}: {i}");
        for c in cameras {
            assert!(c["frames"].as_u64().unwrap() >= steps, "{c}");
            assert_eq!(c["dropped"], 0, "{c}");
        }
        uuids.push(i["metadata"]["uuid"].as_str().unwrap().to_owned());
        let sheet = std::path::PathBuf::from(e["contact_sheet"].as_str().unwrap());
        assert!(std::fs::metadata(&sheet).unwrap().len() > 20_000, "contact sheet {} too small", sheet.display());
        // Every message of the episode decodes in the reference readers.
        let episode_dir = std::path::PathBuf::from(e["dir"].as_str().unwrap());
        assert!(episode_dir.starts_with(dir.path().join("episodes/success")), "{}", episode_dir.display());
        let v = labrig_tests::read_episode_with_python(&episode_dir);
        assert_eq!(v["mcap"]["failures"], serde_json::json!([]), "{v}");
        assert_eq!(v["mcap"]["counts"]["/rig/step"], steps, "{v}");
        assert_eq!(v["rosbags_dir"], v["mcap"]["counts"], "rosbags on the directory: {v}");
        assert_eq!(v["rosbags_file"], v["mcap"]["counts"], "rosbags on the bare file: {v}");
        let mcap_total: u64 = v["mcap"]["counts"].as_object().unwrap().values().map(|n| n.as_u64().unwrap()).sum();
        assert_eq!(mcap_total, i["messages"].as_u64().unwrap(), "every message read");
        // Record, then replay in lockstep: the same robot states, step for step.
        let out = Command::new(labrig_bin()).args(["replay", "--sim", "--json"]).arg(&episode_dir).output().unwrap();
        assert!(out.status.success(), "replay: {}", String::from_utf8_lossy(&out.stderr));
        let rep: Value = serde_json::from_slice(&out.stdout).unwrap();
        assert_eq!(rep["steps"], steps);
        assert_eq!(rep["aligned_ticks"], 0);
        let joints = rep["joint_rad"].as_array().unwrap();
        assert_eq!(joints.len(), 7, "one series per FR3 joint: {joints:?}");
        for (j, e) in joints.iter().enumerate() {
            assert_eq!(e["max"], 0.0, "joint {j}: replayed states equal the recorded ones bit for bit");
        }
        assert_eq!(rep["tcp_m"]["max"], 0.0);
        assert_eq!(rep["gripper"]["max"], 0.0);
        assert_eq!(rep["success_replayed"], true);
    }
    assert_ne!(uuids[0], uuids[1]);
    // The recordings as DROID raw data, the whole directory at once: DROID's layout as h5py
    // and ffprobe read it, an MP4 frame per step.
    labrig_tests::workspace_bin("labrig-droid", "labrig-droid");
    let droid = dir.path().join("droid");
    let out = Command::new(labrig_bin())
        .args(["export", "droid", "--json"])
        .arg(dir.path().join("episodes"))
        .arg(&droid)
        .output()
        .unwrap();
    assert!(out.status.success(), "export: {}", String::from_utf8_lossy(&out.stderr));
    let exported: Vec<Value> =
        String::from_utf8_lossy(&out.stdout).lines().map(|l| serde_json::from_str(l).unwrap()).collect();
    assert_eq!(exported.len(), 2);
    for e in &exported {
        // Every step's observation frame of every camera is in the recording (the first
        // step's too: it is published before the episode's Start).
        assert_eq!(e["frames_filled"], 0, "{e}");
    }
    let (good, reports, problems) = labrig_tests::check_droid_with_python(&droid);
    assert!(good, "{problems}");
    assert_eq!(reports.len(), 2);
    for (r, e) in reports.iter().zip(episodes) {
        assert!(r["dir"].as_str().unwrap().starts_with("success/"), "{r}");
        assert_eq!(r["steps"], e["inspect"]["steps"]);
        // One MP4 per camera, named by its serial (the sim's cameras have none: their id).
        let mp4 = r["mp4"].as_object().unwrap();
        assert_eq!(sorted(mp4.keys().map(String::as_str)), CAMERAS, "{r}");
        for v in mp4.values() {
            assert_eq!(v["frames"], e["inspect"]["steps"]);
        }
    }
}

#[test]
fn shm_bench_delivers_frames_between_processes() {
    let out = Command::new(labrig_bin())
        .args([
            "bench",
            "shm",
            "--streams",
            "2",
            "--width",
            "64",
            "--height",
            "48",
            "--rate",
            "30",
            "--seconds",
            "1",
            "--json",
        ])
        .output()
        .unwrap();
    assert!(out.status.success(), "bench failed: {}", String::from_utf8_lossy(&out.stderr));
    let r: Value = serde_json::from_slice(&out.stdout).unwrap();
    let streams = r["streams"].as_array().unwrap();
    assert_eq!(streams.len(), 2, "one report per --streams: {r}");
    for s in streams {
        assert_eq!(s["published"], 30);
        assert_eq!(s["delivered"], s["published"], "{s}");
        assert_eq!(s["sequence_gaps"], 0);
        assert!(s["latency_p50_us"].as_f64().unwrap() > 0.0);
    }
}

#[test]
fn bad_arguments_are_named() {
    let out = Command::new(labrig_bin()).args(["bench", "shm", "--rate", "0"]).output().unwrap();
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("--rate 0 is out of range"));
    let out = Command::new(labrig_bin()).args(["topic", "echo", "/x", "--domain-id", "300"]).output().unwrap();
    assert!(!out.status.success());
    assert!(
        String::from_utf8_lossy(&out.stderr).contains("ros.domain_id` is 300"),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let dir = tempfile::tempdir().unwrap();
    let out = Command::new(labrig_bin())
        .args(["demo", "--scene", "no/such_scene.toml", "--out"])
        .arg(dir.path())
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("--scene no/such_scene.toml: no such spec file"), "{err}");
}

#[test]
fn sigint_and_sigterm_stop_a_running_command_cleanly() {
    for signal in ["-INT", "-TERM"] {
        stops_cleanly_on(signal);
    }
}

/// `topic echo` with an explicit type waits for messages forever; the signal must end it with
/// exit code 0 (the runtime's Shutdown token), not kill it mid-write.
fn stops_cleanly_on(signal: &str) {
    let mut child = Command::new(labrig_bin())
        .args(["topic", "echo", "/nobody_here", "--type", "std_msgs/msg/String"])
        .env("ROS_DOMAIN_ID", labrig_tests::domain_for("sigint").to_string())
        .stdout(std::process::Stdio::null())
        .spawn()
        .unwrap();
    std::thread::sleep(std::time::Duration::from_millis(1500));
    assert!(child.try_wait().unwrap().is_none(), "echo exited before the signal");
    Command::new("kill").args([signal, &child.id().to_string()]).status().unwrap();
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(10);
    let status = loop {
        if let Some(s) = child.try_wait().unwrap() {
            break s;
        }
        assert!(std::time::Instant::now() < deadline, "echo did not stop within 10 s of {signal}");
        std::thread::sleep(std::time::Duration::from_millis(20));
    };
    assert_eq!(status.code(), Some(0), "{signal}: {status:?}");
}

#[test]
fn ik_bench_reports_every_series() {
    let out = Command::new(labrig_bin()).args(["bench", "ik", "--ticks", "50", "--json"]).output().unwrap();
    assert!(out.status.success(), "bench ik failed: {}", String::from_utf8_lossy(&out.stderr));
    let r: Value = serde_json::from_slice(&out.stdout).unwrap();
    for key in ["fk_and_jacobian", "ik_solve", "safety_filter_cartesian_position", "safety_filter_cartesian_velocity"] {
        assert_eq!(r[key]["n"], 50, "{key}: {r}");
        assert!(r[key]["p50_us"].as_f64().unwrap() > 0.0);
    }
    assert!(r["ik_worst_residual_m"].as_f64().unwrap() < 1e-4, "{r}");
}
