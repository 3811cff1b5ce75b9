//! The fault suite (issue 16): what the rig does when a part of it fails, and what is lost.
//! Each fault is injected into real processes on the simulated rig; the figures come from
//! `labrig bench faults`, which prints them for the README's table.
//!
//! - DDS stopped and continued (SIGSTOP/SIGCONT kills RustDDS's event loops): the node
//!   notices, says so, and exits for the launcher to restart it.
//! - Too many DDS participants in one domain: refused with the limit named (20 tried).
//! - The recorder killed at the start, in the middle and at the end of an episode: the episode
//!   is recovered and complete, no step lost.
//! - A full disk: earlier episodes intact, the refusal named, the rig held Idle.

use labrig_runtime::RosConfig;
use labrig_runtime::ros::{MAX_PARTICIPANTS_PER_DOMAIN, Ros};
use labrig_tests::{domain_for, labrig_bin};
use serde_json::Value;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

/// A node stopped (SIGSTOP, as Ctrl-Z or a debugger do) and continued loses its DDS event
/// loops; it notices within a fraction of a second, names the cause and exits with status 1
/// (the launcher's cue to restart it) instead of running on deaf.
#[test]
fn a_node_stopped_and_continued_notices_its_dds_died_and_exits() {
    let domain = domain_for("fault_dds_stop_continue");
    let root = tempfile::tempdir().unwrap();
    let log = root.path().join("stderr.log");
    let mut child = Command::new(labrig_tests::workspace_bin("labrig-recorder", "labrig-recorder"))
        .args(["run", "--domain-id", &domain.to_string(), "--root"])
        .arg(root.path().join("episodes"))
        .env(labrig_runtime::frames::NAMESPACE_ENV, format!("fault_dds_{}", std::process::id()))
        .stdout(Stdio::null())
        .stderr(std::fs::File::create(&log).unwrap())
        .spawn()
        .unwrap();
    let pid = child.id().to_string();
    // Up: it says so once its participant exists.
    let deadline = Instant::now() + Duration::from_secs(60);
    while !std::fs::read_to_string(&log).unwrap().contains("recorder up") {
        assert!(Instant::now() < deadline, "the recorder never came up");
        assert!(child.try_wait().unwrap().is_none(), "the recorder exited early");
        std::thread::sleep(Duration::from_millis(50));
    }
    assert!(Command::new("kill").args(["-STOP", &pid]).status().unwrap().success());
    std::thread::sleep(Duration::from_millis(300));
    assert!(Command::new("kill").args(["-CONT", &pid]).status().unwrap().success());
    let continued = Instant::now();
    let status = loop {
        if let Some(s) = child.try_wait().unwrap() {
            break s;
        }
        if continued.elapsed() > Duration::from_secs(20) {
            let _ = child.kill();
            panic!("still running 20 s after SIGCONT: {}", std::fs::read_to_string(&log).unwrap());
        }
        std::thread::sleep(Duration::from_millis(10));
    };
    let text = std::fs::read_to_string(&log).unwrap();
    assert_eq!(status.code(), Some(1), "{text}");
    assert!(text.contains("DDS stopped") && text.contains("stopped and continued"), "{text}");
    eprintln!("detected {:.0} ms after SIGCONT", continued.elapsed().as_secs_f64() * 1e3);
}

/// Twenty participants in one domain on one machine: the first twelve discover each other;
/// the rest are refused, each with the limit and what to do named (RustDDS announces itself
/// on loopback to participant ids 0..11 only).
#[test]
fn a_domain_takes_twelve_participants_and_refuses_more_by_name() {
    let domain = domain_for("fault_participant_limit");
    let rt = labrig_tests::rt();
    rt.block_on(async {
        let cfg = RosConfig { domain_id: domain, ..Default::default() };
        let mut up = Vec::new();
        let mut refused = Vec::new();
        for k in 0..20 {
            match Ros::new(&cfg, &format!("participant_{k}")) {
                Ok(ros) => up.push(ros),
                Err(e) => refused.push(e.to_string()),
            }
        }
        assert_eq!(up.len(), MAX_PARTICIPANTS_PER_DOMAIN as usize, "refused: {refused:?}");
        assert_eq!(refused.len(), 20 - up.len());
        for r in &refused {
            assert!(r.contains("discovers only 12 per domain") && r.contains("--domain-id"), "{r}");
        }
        // The twelve see each other: each one's publisher is known to every other.
        let mut pubs = Vec::new();
        for ros in &mut up {
            pubs.push(
                ros.publisher::<labrig_msgs::std_msgs::StringMsg>("/hello", labrig_runtime::ros::qos::reliable(1))
                    .unwrap(),
            );
        }
        let deadline = Instant::now() + Duration::from_secs(60);
        loop {
            let seen: Vec<usize> = up.iter().map(|r| r.publisher_count("/hello")).collect();
            if seen.iter().all(|&n| n >= up.len() - 1) {
                break;
            }
            assert!(Instant::now() < deadline, "publishers of /hello each participant knows: {seen:?}");
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
    });
}

#[allow(dead_code)]
fn bench_faults(args: &[&str]) -> Value {
    let out = Command::new(labrig_bin()).args(["bench", "faults", "--json"]).args(args).output().unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "labrig bench faults {args:?}: {stdout}\n{}", String::from_utf8_lossy(&out.stderr));
    serde_json::from_str(stdout.lines().last().unwrap_or_default()).unwrap_or_else(|e| panic!("{e}: {stdout}"))
}
