//! `labrig replay <episode> --sim`: the committed episode fixtures (recorded by labrig's own
//! rig: scripted expert, lockstep, 32x32 cameras) replay against their rebuilt scenes exactly;
//! a perturbed action stream fails with the deviation reported; bad input is named.

use labrig_tests::{labrig_bin, repo_root, workspace_bin};
use serde_json::Value;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

fn fixtures() -> Vec<PathBuf> {
    let dir = repo_root().join("tests/fixtures/episodes");
    let mut v: Vec<PathBuf> = std::fs::read_dir(&dir).unwrap().map(|e| e.unwrap().path()).collect();
    v.sort();
    assert!(!v.is_empty(), "no episode fixtures in {}", dir.display());
    v
}

fn replay(episode: &Path, extra: &[&str]) -> Output {
    workspace_bin("labrig-sim", "labrig-sim"); // `labrig replay` runs it from beside itself
    Command::new(labrig_bin()).arg("replay").arg(episode).arg("--sim").args(extra).output().unwrap()
}

/// The largest error of every kind in a replay report.
fn worst(r: &Value) -> f64 {
    let joints = r["joint_rad"].as_array().unwrap().iter().map(|e| e["max"].as_f64().unwrap());
    let rest = ["tcp_m", "rotation_rad", "gripper"].map(|k| r[k]["max"].as_f64().unwrap());
    joints.chain(rest).fold(0.0, f64::max)
}

#[test]
fn every_committed_fixture_replays_exactly() {
    for f in fixtures() {
        let out = replay(&f, &["--json"]);
        assert!(out.status.success(), "{}: {}", f.display(), String::from_utf8_lossy(&out.stderr));
        let r: Value = serde_json::from_slice(&out.stdout).unwrap();
        assert!(r["steps"].as_u64().unwrap() >= 20, "{r}");
        assert_eq!(r["aligned_ticks"], 0, "recorded from the scene's first state: {}", f.display());
        // Lockstep, same scene, same actions through the same path: the same states (the
        // rotation compares through Euler angles, hence not bit-exact).
        assert!(worst(&r) < 1e-9, "{}: largest error {}", f.display(), worst(&r));
        assert_eq!(r["success_recorded"], r["success_replayed"], "{}", f.display());
        assert_eq!(r["exceeded"], serde_json::json!([]));
    }
}

#[test]
fn a_perturbed_action_stream_fails_with_the_deviation_named() {
    let f = &fixtures()[0];
    let dir = tempfile::tempdir().unwrap();
    let png = dir.path().join("replay.png");
    let out = replay(f, &["--json", "--perturb-joint1-rad", "0.05", "--plot", png.to_str().unwrap()]);
    assert_eq!(out.status.code(), Some(5), "{}", String::from_utf8_lossy(&out.stderr));
    // The picture of it: recorded vs replayed TCP, errors over time.
    assert!(std::fs::metadata(&png).unwrap().len() > 20_000, "plot {} too small", png.display());
    let r: Value = serde_json::from_slice(&out.stdout).unwrap();
    let j1 = r["joint_rad"][0]["max"].as_f64().unwrap();
    assert!(j1 > 0.03, "joint 1 deviates by about the perturbation: {j1}");
    let exceeded: Vec<&str> = r["exceeded"].as_array().unwrap().iter().map(|e| e.as_str().unwrap()).collect();
    assert!(exceeded.iter().any(|e| e.starts_with("joint error")), "{exceeded:?}");
    // A tolerance wide enough passes the same replay.
    let loose = ["--perturb-joint1-rad", "0.05", "--max-joint-error-rad", "1", "--max-tcp-error-m", "1"];
    let out = replay(f, &[&loose[..], &["--max-rotation-error-rad", "1", "--max-gripper-error", "1"]].concat());
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stdout));
}

#[test]
fn bad_episodes_are_refused_by_name() {
    let dir = tempfile::tempdir().unwrap();
    let foreign = dir.path().join("foreign.mcap");
    std::fs::write(&foreign, b"not an episode").unwrap();
    let out = replay(&foreign, &[]);
    assert_eq!(out.status.code(), Some(1));
    assert!(
        String::from_utf8_lossy(&out.stderr).contains("not an MCAP file"),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    // The first 6 kB of a fixture: the header and metadata, no steps.
    let whole = std::fs::read(fixtures()[0].join("episode_0.mcap")).unwrap();
    let truncated = dir.path().join("truncated.mcap");
    std::fs::write(&truncated, &whole[..6000]).unwrap();
    let out = replay(&truncated, &[]);
    assert_eq!(out.status.code(), Some(1));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("no /rig/step records") && err.contains("truncated"), "{err}");
    // Without --sim: said so.
    let out = Command::new(labrig_bin()).arg("replay").arg(&fixtures()[0]).output().unwrap();
    assert_eq!(out.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&out.stderr).contains("needs --sim"));
    // A scene that cannot be rebuilt: a spec file that does not exist.
    let out = replay(&fixtures()[0], &["--scene", "/nonexistent/scene.toml"]);
    assert_eq!(out.status.code(), Some(1));
    assert!(
        String::from_utf8_lossy(&out.stderr).contains("/nonexistent/scene.toml"),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
}
