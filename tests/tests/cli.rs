//! The `labrig` binary end to end: demo, shm bench (functional, not timing), argument errors.

use labrig_tests::{labrig_bin, sim_bin};
use serde_json::Value;
use std::process::Command;

#[test]
fn demo_delivers_every_state_and_frame_and_runs_the_sim_expert() {
    sim_bin(); // `labrig demo` runs the sim binary built beside it
    let dir = tempfile::tempdir().unwrap();
    let out = Command::new(labrig_bin())
        .args(["demo", "--seconds", "1", "--json", "--domain-id", "201", "--episodes", "2", "--out"])
        .arg(dir.path())
        .output()
        .unwrap();
    assert!(out.status.success(), "demo failed: {}", String::from_utf8_lossy(&out.stderr));
    let r: Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(r["ok"], true);
    assert_eq!(r["joint_states"]["received"], r["ticks"]);
    assert_eq!(r["cameras"].as_array().unwrap().len(), 5);
    for task in ["pick_place", "drawer_open", "drawer_close"] {
        let eval = &r["sim"]["tasks"][task];
        assert_eq!(eval["episodes"], 2, "{task}: {eval}");
        assert_eq!(eval["successes"], 2, "{task}: {eval}");
        assert_eq!(eval["results"][0]["task"], task);
    }
    for task in ["pick_place", "drawer_open"] {
        let sheet = dir.path().join(format!("snapshot_{task}_seed0/cameras.png"));
        assert!(std::fs::metadata(&sheet).unwrap().len() > 10_000, "contact sheet {} too small", sheet.display());
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
    for s in r["streams"].as_array().unwrap() {
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
