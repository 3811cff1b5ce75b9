//! Episodes written by labrig-recorder, read back by the reference readers: PyPI `mcap` +
//! `mcap-ros2-support` (every message decoded through the schema embedded in the file) and
//! `rosbags` 0.11.9 (the directory through metadata.yaml, and the bare .mcap).

use labrig_episode::bag::Reliability;
use labrig_episode::{EpisodeMetadata, EpisodeWriter, Outcome, RigIdentity, episode_dir};
use labrig_msgs::Nanos;
use labrig_msgs::geometry_msgs::TransformStamped;
use labrig_msgs::rig::{CameraFrameRef, RobotState, Step};
use labrig_msgs::sensor_msgs::{CameraInfo, CompressedImage};
use labrig_msgs::std_msgs::Header;
use labrig_msgs::tf2_msgs::TFMessage;
use serde_json::Value;
use std::path::Path;
use std::process::Command;

const T0: i64 = 1_795_000_000_000_000_000;
const TICK: i64 = 50_000_000;

/// A small JPEG-shaped payload (SOI ... EOI); the readers only carry the bytes.
fn jpeg(k: i64) -> Vec<u8> {
    let mut v = vec![0xFF, 0xD8];
    v.extend((0..2000).map(|i| ((i + k) % 251) as u8));
    v.extend([0xFF, 0xD9]);
    v
}

fn header(t: i64, frame: &str) -> Header {
    Header { stamp: Nanos(t).into(), frame_id: frame.into() }
}

/// Writes a 2 s episode: Step at 20 Hz, two cameras at 20 Hz, /tf at 20 Hz, /arm/state at 50 Hz.
fn write_episode(root: &Path) -> (std::path::PathBuf, EpisodeMetadata) {
    let mut meta =
        EpisodeMetadata::new(&RigIdentity::default(), "pick_place_cube", "put the cube in the bin", Nanos(T0));
    meta.extrinsics.insert("ext1".into(), [0.5, -0.4, 0.6, 0.1, 0.2, 0.3]);
    let dir = episode_dir(root, Outcome::Success, Nanos(T0));
    let mut w = EpisodeWriter::create(&dir, meta.clone()).unwrap();
    w.attach("scene.json", "application/json", br#"{"seed": 3}"#, Nanos(T0)).unwrap();
    for k in 0..100i64 {
        let t = T0 + k * 20_000_000;
        let state =
            RobotState { header: header(t, "base"), joint_positions: [k as f64 * 0.01; 7], ..Default::default() };
        w.write("/arm/state", &state, Nanos(t + 1_000), Nanos(t), Reliability::Reliable).unwrap();
    }
    for k in 0..40i64 {
        let t = T0 + k * TICK;
        for cam in ["ext1", "wrist"] {
            let img =
                CompressedImage { header: header(t, &format!("{cam}_optical")), format: "jpeg".into(), data: jpeg(k) };
            w.write(
                &format!("/cameras/{cam}/image/compressed"),
                &img,
                Nanos(t + 2_000),
                Nanos(t),
                Reliability::BestEffort,
            )
            .unwrap();
        }
        let tf = TFMessage {
            transforms: vec![TransformStamped {
                header: header(t, "base"),
                child_frame_id: "tcp".into(),
                ..Default::default()
            }],
        };
        w.write("/tf", &tf, Nanos(t + 3_000), Nanos(t), Reliability::Reliable).unwrap();
        let step = Step {
            header: header(t, "base"),
            episode_id: meta.uuid.clone(),
            step_index: k as u64,
            robot_state: RobotState { joint_positions: [k as f64; 7], ..Default::default() },
            cameras: ["ext1", "wrist"]
                .iter()
                .map(|c| CameraFrameRef {
                    camera_id: (*c).into(),
                    sequence: k as u64,
                    capture_ns: t,
                    arrival_ns: t + 2_000,
                    ..Default::default()
                })
                .collect(),
            action_source: Step::SOURCE_SCRIPTED,
            ..Default::default()
        };
        w.write("/rig/step", &step, Nanos(t + 4_000), Nanos(t), Reliability::Reliable).unwrap();
    }
    w.metadata_mut().success = Some(true);
    w.metadata_mut().trajectory_length = 40;
    let summary = w.finish().unwrap();
    assert_eq!(summary.messages, 100 + 40 * 4);
    let meta = EpisodeMetadata { success: Some(true), trajectory_length: 40, ..meta };
    (dir, meta)
}

#[test]
fn the_reference_readers_read_every_message_of_an_episode() {
    let root = tempfile::tempdir().unwrap();
    let (dir, meta) = write_episode(root.path());
    assert!(dir.starts_with(root.path().join("success")), "{}", dir.display());
    assert!(dir.join("metadata.yaml").exists() && dir.join("episode_0.mcap").exists());
    let v = labrig_tests::read_episode_with_python(&dir);
    let expected = serde_json::json!({
        "/arm/state": 100, "/cameras/ext1/image/compressed": 40, "/cameras/wrist/image/compressed": 40,
        "/tf": 40, "/rig/step": 40,
    });
    assert_eq!(v["mcap"]["counts"], expected, "mcap + mcap-ros2-support: {v}");
    assert_eq!(v["mcap"]["failures"], serde_json::json!([]));
    assert_eq!(v["mcap"]["profile"], "ros2");
    assert_eq!(v["rosbags_dir"], expected, "rosbags on the directory (metadata.yaml): {v}");
    assert_eq!(v["rosbags_file"], expected, "rosbags on the bare .mcap: {v}");
    // DROID's record (the final one) and the rosbag2 record.
    let droid = &v["mcap"]["metadata"]["droid_episode"];
    assert_eq!(droid["uuid"], meta.uuid.as_str());
    assert_eq!(droid["success"], "true");
    assert_eq!(droid["trajectory_length"], "40");
    assert_eq!(droid["current_task"], "put the cube in the bin");
    assert!(v["mcap"]["metadata"]["rosbag2"]["serialized_metadata"].as_str().unwrap().contains("message_count: 260"));
    assert_eq!(v["mcap"]["attachments"], serde_json::json!(["scene.json"]));
    // Values survive the round trip.
    let s = &v["mcap"]["samples"];
    assert_eq!(s["last_step_index"], 39);
    assert_eq!(s["last_step_joint_positions"], serde_json::json!(vec![39.0; 7]));
    assert_eq!(s["step_cameras"], serde_json::json!(["ext1", "wrist"]));
    assert_eq!(s["image_format"], "jpeg");
    assert_eq!(s["image_jpeg_markers"], true);
}

/// A recorder killed with SIGKILL at a random point mid-episode: `labrig recover` makes the
/// file whole, and the reference readers read every step the writer had taken but at most the
/// last second's (counted against the steps it reported written before it died).
#[test]
fn a_killed_recorder_loses_at_most_the_last_second() {
    let root = tempfile::tempdir().unwrap();
    let mut cmd = Command::new(labrig_tests::labrig_bin());
    cmd.args(["bench", "record", "--realtime", "--seconds", "30", "--json", "--progress", "--out"]).arg(root.path());
    let mut rec = labrig_tests::Proc::spawn("labrig bench record", cmd);
    let first = rec.wait_json(std::time::Duration::from_secs(30), "the episode path", |v| v["episode"].is_string());
    let dir = std::path::PathBuf::from(first["episode"].as_str().unwrap());
    // Two seconds in (so that losing more than the last one would show), then on to a
    // random point 0..3 s later, not just after a chunk closed (the best case; a chunk closes
    // every 250 ms of log time); the delay is printed to repeat a failure.
    rec.wait_json(std::time::Duration::from_secs(30), "40 steps written", |v| {
        v["written"].as_u64().is_some_and(|n| n >= 40)
    });
    let delay_ms = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).unwrap().subsec_nanos() % 3000;
    let until = std::time::Instant::now() + std::time::Duration::from_millis(delay_ms as u64);
    while std::time::Instant::now() < until {
        rec.next_line(until.saturating_duration_since(std::time::Instant::now()));
    }
    rec.child.kill().unwrap(); // SIGKILL
    rec.child.wait().unwrap();
    // What the writer had taken when it died: the last `written` line it printed (the pipe
    // keeps what was printed before the kill; a step written but not yet printed is at most 1).
    while rec.next_line(std::time::Duration::from_secs(2)).is_some() {}
    // Step n's stamp (n = steps written so far), from every progress line.
    let mut stamps = std::collections::BTreeMap::new();
    for l in &rec.seen {
        if let Ok(v) = serde_json::from_str::<Value>(l)
            && let (Some(n), Some(t)) = (v["written"].as_u64(), v["stamp_ns"].as_i64())
        {
            stamps.insert(n, t);
        }
    }
    let (&sent, &last_sent_ns) = stamps.last_key_value().expect("progress lines");
    assert!(sent >= 40, "the writer reported only {sent} steps written before the kill");
    // Before recovery inspect reads it up to the damage and says what to do.
    let (code, v) = inspect(&dir);
    assert_eq!(code, Some(3), "{v}");
    assert_eq!(v["complete"], false);
    assert!(v["flags"].as_array().unwrap().iter().any(|f| f.as_str().unwrap().contains("run `labrig recover`")), "{v}");
    let out = Command::new(labrig_tests::labrig_bin()).args(["recover", "--json"]).arg(&dir).output().unwrap();
    assert!(out.status.success(), "labrig recover: {}", String::from_utf8_lossy(&out.stderr));
    let r: Value = serde_json::from_slice(&out.stdout).unwrap();
    assert!(r["parts"][0]["stopped"].as_str().unwrap().starts_with("stopped at"), "the file was damaged: {r}");
    assert!(dir.join("episode_0.mcap.damaged").exists());
    let v = labrig_tests::read_episode_with_python(&dir);
    // No step at all is a count of 0 (the bound below then names the loss).
    let steps = v["mcap"]["counts"]["/rig/step"].as_u64().unwrap_or(0);
    // At most the last second lost (in the steps' own time, so a slow machine does not
    // stretch the bound), and nothing that was never written.
    assert!(steps <= sent + 1, "recovered {steps} steps, more than the {sent} written");
    let last_kept_ns = stamps.get(&steps).copied().unwrap_or(stamps[&1] - 50_000_000);
    let lost_ms = (last_sent_ns - last_kept_ns) as f64 / 1e6;
    assert!(
        lost_ms <= 1000.0,
        "killed {delay_ms} ms after step 40 with {sent} steps written: recovered {steps}, losing {lost_ms:.0} ms"
    );
    assert_eq!(v["rosbags_dir"], v["mcap"]["counts"], "rosbags reads the recovered episode too: {v}");
    // A chunk can close between a tick's frames and its step record.
    let frames = v["mcap"]["counts"]["/cameras/wrist/image/compressed"].as_u64().unwrap();
    assert!(frames == steps || frames == steps + 1, "{frames} wrist frames for {steps} steps");
    assert!(v["mcap"]["metadata"]["droid_episode"]["uuid"].as_str().unwrap().starts_with("LABRIG+operator+"));
    eprintln!(
        "killed {delay_ms} ms after step 40, {sent} steps written; recovered {steps} (lost {lost_ms:.0} ms): {r}"
    );
}

/// A full disk: the next episode fails with an error that says so, and the episode recorded
/// before it stays whole. (/dev/full answers every write with ENOSPC.)
#[test]
fn a_full_disk_stops_recording_and_keeps_earlier_episodes() {
    let root = tempfile::tempdir().unwrap();
    let (good, _) = write_episode(root.path());
    let full_dir = root.path().join("failure/next");
    std::fs::create_dir_all(&full_dir).unwrap();
    std::os::unix::fs::symlink("/dev/full", full_dir.join("episode_0.mcap")).unwrap();
    let meta = EpisodeMetadata::new(&RigIdentity::default(), "pick_place_cube", "again", Nanos(T0 + 60_000_000_000));
    let err = EpisodeWriter::create(&full_dir, meta).unwrap_err();
    assert!(err.is_disk_full(), "{err:?}");
    assert!(err.to_string().contains("No space left on device"), "{err}");
    assert!(err.to_string().contains("episode_0.mcap"), "the error names the file: {err}");
    let v = labrig_tests::read_episode_with_python(&good);
    assert_eq!(v["rosbags_dir"]["/rig/step"], 40, "the earlier episode is intact: {v}");
}

fn inspect(path: &Path) -> (Option<i32>, Value) {
    let out = Command::new(labrig_tests::labrig_bin()).args(["inspect", "--json"]).arg(path).output().unwrap();
    let v = serde_json::from_slice(&out.stdout)
        .unwrap_or_else(|e| panic!("inspect --json: {e}: {}", String::from_utf8_lossy(&out.stderr)));
    (out.status.code(), v)
}

#[test]
fn inspect_reports_a_good_episode() {
    let root = tempfile::tempdir().unwrap();
    let (dir, meta) = write_episode(root.path());
    let (code, v) = inspect(&dir);
    assert_eq!(code, Some(0), "{v}");
    assert_eq!(v["complete"], true);
    assert_eq!(v["messages"], 260);
    assert_eq!(v["steps"], 40);
    assert_eq!(v["metadata"]["uuid"], meta.uuid.as_str());
    assert_eq!(v["flags"], serde_json::json!([]));
    assert_eq!(v["missed_ticks"], 0);
    assert_eq!(v["control_period_ms"]["p50"], 50.0);
    let step = v["topics"].as_array().unwrap().iter().find(|t| t["topic"] == "/rig/step").unwrap();
    assert!((step["rate_hz"].as_f64().unwrap() - 20.0).abs() < 1e-6, "{step}");
    let wrist = v["cameras"].as_array().unwrap().iter().find(|c| c["camera"] == "wrist").unwrap();
    assert_eq!((wrist["frames"].as_u64(), wrist["dropped"].as_u64()), (Some(40), Some(0)));
    assert_eq!(wrist["image"], "unknown", "no camera_info recorded: {wrist}");

    // The recording says what its images are, from each camera's camera_info: a rectified ZED
    // eye (no distortion, a rectifying R), a raw one (its distortion), a plain pinhole, none.
    let dir = root.path().join("models");
    let mut w =
        EpisodeWriter::create(&dir, EpisodeMetadata::new(&RigIdentity::default(), "s", "t", Nanos(T0))).unwrap();
    let k = [500.0, 0.0, 320.0, 0.0, 500.0, 240.0, 0.0, 0.0, 1.0];
    let eye = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0];
    let tilted = [1.0, 0.0, 0.0, 0.0, 0.9999, -0.0141, 0.0, 0.0141, 0.9999];
    let infos = [
        ("ext1", k, vec![0.0; 5], tilted, "rectified"),
        ("ext2", k, vec![-0.04, 0.01, 0.0, 0.0, -0.005], eye, "distorted"),
        ("wrist", k, vec![0.0; 5], eye, "pinhole"),
        ("rs1", [0.0; 9], vec![0.0; 5], eye, "uncalibrated"),
    ];
    for (cam, k, d, r, _) in &infos {
        let img =
            CompressedImage { header: header(T0, &format!("{cam}_optical")), format: "jpeg".into(), data: jpeg(0) };
        w.write(&format!("/cameras/{cam}/image/compressed"), &img, Nanos(T0), Nanos(T0), Reliability::BestEffort)
            .unwrap();
        let info = CameraInfo {
            header: header(T0, &format!("{cam}_optical")),
            k: *k,
            d: d.clone(),
            r: *r,
            ..Default::default()
        };
        w.write(&format!("/cameras/{cam}/camera_info"), &info, Nanos(T0), Nanos(T0), Reliability::Reliable).unwrap();
    }
    w.finish().unwrap();
    let (_, v) = inspect(&dir);
    let cams = v["cameras"].as_array().unwrap();
    assert_eq!(cams.len(), infos.len(), "{v}");
    for (cam, .., want) in &infos {
        let c = cams.iter().find(|c| c["camera"] == *cam).unwrap();
        assert_eq!(c["image"], *want, "{c}");
    }
}

/// Malformed and out-of-order messages are counted and flagged, gaps in a camera's frames are
/// counted as dropped, an episode without camera frames is flagged: inspect exits 3.
#[test]
fn inspect_flags_bad_input() {
    let root = tempfile::tempdir().unwrap();
    let meta = EpisodeMetadata::new(&RigIdentity::default(), "s", "t", Nanos(T0));
    let dir = root.path().join("bad");
    let mut w = EpisodeWriter::create(&dir, meta).unwrap();
    let step_schema = labrig_msgs::schema_text::<Step>();
    let step_type = labrig_episode::episode::RawType { name: "labrig_msgs/msg/Step", schema: &step_schema };
    for k in 0..10i64 {
        let t = T0 + k * TICK;
        // Step 4 never arrives (a missed tick); step 7 is garbage.
        if k == 7 {
            w.write_cdr("/rig/step", &step_type, &[0, 1, 0, 0, 0xde, 0xad], Nanos(t), Nanos(t), Reliability::Reliable)
                .unwrap();
        } else if k != 4 {
            let step = Step { header: header(t, "base"), step_index: k as u64, ..Default::default() };
            w.write("/rig/step", &step, Nanos(t), Nanos(t), Reliability::Reliable).unwrap();
        }
        // /arm/state: the sample of tick 5 is logged before the one of tick 4.
        let log = if k == 5 { T0 + 3 * TICK + 1 } else { t };
        let s = RobotState { header: header(t, "base"), ..Default::default() };
        w.write("/arm/state", &s, Nanos(log), Nanos(t), Reliability::Reliable).unwrap();
    }
    w.finish().unwrap();
    let (code, v) = inspect(&dir);
    assert_eq!(code, Some(3), "{v}");
    let flags: Vec<&str> = v["flags"].as_array().unwrap().iter().map(|f| f.as_str().unwrap()).collect();
    assert!(flags.contains(&"/rig/step: 1 malformed messages"), "{flags:?}");
    assert!(flags.contains(&"/arm/state: 1 messages out of order"), "{flags:?}");
    assert!(flags.contains(&"no camera frames: the episode has no images"), "{flags:?}");
    // Steps 4 (never sent) and 7 (unreadable) leave two gaps.
    assert!(flags.contains(&"2 missed control ticks"), "{flags:?}");
    assert_eq!(v["steps"], 8);

    // A camera whose frames 3..5 are missing.
    let dir = root.path().join("gaps");
    let mut w =
        EpisodeWriter::create(&dir, EpisodeMetadata::new(&RigIdentity::default(), "s", "t", Nanos(T0))).unwrap();
    for k in (0..10i64).filter(|k| !(3..6).contains(k)) {
        let t = T0 + k * TICK;
        let img = CompressedImage { header: header(t, "ext1_optical"), format: "jpeg".into(), data: jpeg(k) };
        w.write("/cameras/ext1/image/compressed", &img, Nanos(t), Nanos(t), Reliability::BestEffort).unwrap();
    }
    w.finish().unwrap();
    let (_, v) = inspect(&dir);
    assert_eq!(v["cameras"][0]["dropped"], 3, "{v}");
    assert!(v["flags"].as_array().unwrap().iter().any(|f| f == "camera ext1: 3 frames dropped"), "{v}");

    // A sim episode (its scene set at T0 + 2 ticks) holding the last scene's frame of T0 + 1
    // tick, and a step that names a frame the file does not hold; steps span 9 ticks of sim
    // time, recorded in a fraction of that: rates and the duration are in the episode's time.
    let dir = root.path().join("foreign");
    let mut meta = EpisodeMetadata::new(&RigIdentity::default(), "s", "t", Nanos(T0));
    meta.sim_scene = Some(format!(r#"{{"seed": 2, "since_ns": {}}}"#, T0 + 2 * TICK));
    let mut w = EpisodeWriter::create(&dir, meta).unwrap();
    for k in 1..12i64 {
        let t = T0 + k * TICK;
        let log = T0 + k * 1_000_000;
        let img = CompressedImage { header: header(t, "ext1_optical"), format: "jpeg".into(), data: jpeg(k) };
        if k != 6 {
            w.write("/cameras/ext1/image/compressed", &img, Nanos(log), Nanos(t), Reliability::BestEffort).unwrap();
        }
        if k >= 2 {
            let cameras = vec![CameraFrameRef { camera_id: "ext1".into(), capture_ns: t, ..Default::default() }];
            let step = Step { header: header(t, "base"), step_index: k as u64, cameras, ..Default::default() };
            w.write("/rig/step", &step, Nanos(log), Nanos(t), Reliability::Reliable).unwrap();
        }
    }
    w.finish().unwrap();
    let (_, v) = inspect(&dir);
    let flags: Vec<&str> = v["flags"].as_array().unwrap().iter().map(|f| f.as_str().unwrap()).collect();
    assert!(
        flags.contains(&"camera ext1: 1 frames captured before the episode's scene was set (another episode's)"),
        "{flags:?}"
    );
    assert!(
        flags.contains(&"camera ext1: 1 steps name a frame the file does not hold (step_index 6 of 2..=11)"),
        "{flags:?}"
    );
    assert_eq!(v["clock"], "sim");
    assert!((v["duration_s"].as_f64().unwrap() - 0.45).abs() < 1e-9, "{v}");
    assert!((v["wall_duration_s"].as_f64().unwrap() - 0.010).abs() < 1e-9, "{v}");
    let step_rate = v["topics"].as_array().unwrap().iter().find(|t| t["topic"] == "/rig/step").unwrap()["rate_hz"]
        .as_f64()
        .unwrap();
    assert!((step_rate - 20.0).abs() < 1e-9, "10 steps over 0.45 s of sim time: {step_rate} Hz");
}

/// The recorder's next `/recorder/status` whose state is `want` (30 s at most).
async fn recorder_says(
    status: &labrig_runtime::ros::RosSubscription<labrig_msgs::std_msgs::StringMsg>,
    want: &str,
) -> Value {
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(30);
    while std::time::Instant::now() < deadline {
        while let Some(s) = status.try_take().unwrap() {
            let v: Value = serde_json::from_str(&s.msg.data).unwrap();
            if v["state"] == want {
                return v;
            }
        }
        tokio::time::sleep(std::time::Duration::from_millis(20)).await;
    }
    panic!("the recorder never said {want}");
}

/// The recorder node (its own process) records what the sim bridge publishes — DDS topics as
/// they came and the five cameras from shared memory as JPEG — between /rig/episode events,
/// files the episode in DROID's layout, and deletes a discarded one.
#[test]
fn the_recorder_node_records_the_sim_rig() {
    use labrig_msgs::rig::{EpisodeEvent, EpisodeEventKind};
    use labrig_msgs::std_msgs::StringMsg;
    use labrig_runtime::ros::{Ros, qos};
    use std::time::{Duration, Instant};
    let domain = labrig_tests::domain_for("recorder_node_vs_sim_bridge");
    let ns = format!("recorder_{}", std::process::id());
    let root = tempfile::tempdir().unwrap();
    let mut bridge = Command::new(labrig_tests::sim_bin());
    bridge
        .args(["run", "--mode", "realtime", "--max-ticks", "2000", "--domain-id", &domain.to_string()])
        .env(labrig_runtime::frames::NAMESPACE_ENV, &ns);
    let _bridge = labrig_tests::Proc::spawn("labrig-sim run", bridge);
    let mut rec = Command::new(labrig_tests::workspace_bin("labrig-recorder", "labrig-recorder"));
    rec.args(["run", "--domain-id", &domain.to_string(), "--root"])
        .arg(root.path())
        .env(labrig_runtime::frames::NAMESPACE_ENV, &ns);
    let _rec = labrig_tests::Proc::spawn("labrig-recorder run", rec);
    let dir = labrig_tests::rt().block_on(async move {
        let cfg = labrig_runtime::RosConfig { domain_id: domain, ..Default::default() };
        let mut ros = Ros::new(&cfg, "recorder_test").unwrap();
        let events = ros.publisher_on(&labrig_msgs::topics::RIG_EPISODE, 10).unwrap();
        let steps = ros.publisher_on(&labrig_msgs::topics::RIG_STEP, 100).unwrap();
        let status = ros.subscription::<StringMsg>("/recorder/status", qos::latched(1)).unwrap();
        assert!(ros.wait_for_subscribers("/rig/episode", 1, Duration::from_secs(60)).await, "no recorder");
        assert!(ros.wait_for_subscribers("/rig/step", 1, Duration::from_secs(60)).await);
        // The bridge comes up after the recorder on a loaded machine: start once the recorder
        // says it holds the scene and /tf_static and has frames from every camera.
        let deadline = Instant::now() + Duration::from_secs(60);
        let mut last = Value::Null;
        loop {
            while let Some(m) = status.try_take().unwrap() {
                last = serde_json::from_str(&m.msg.data).unwrap();
            }
            let has = |key: &str, want: &str| last["seen"][key].as_array().is_some_and(|a| a.iter().any(|x| x == want));
            if has("latched", "/sim/scene")
                && has("latched", "/tf_static")
                && labrig_msgs::rig::RIG_CAMERAS.iter().all(|c| has("cameras", c))
            {
                break;
            }
            assert!(Instant::now() < deadline, "the recorder never saw the scene, /tf_static and every camera: {last}");
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
        let wait_status = |want: &'static str| recorder_says(&status, want);
        let event = |kind: EpisodeEventKind, note: &str| EpisodeEvent {
            kind: kind as u8,
            note: note.into(),
            ..Default::default()
        };
        // A discarded episode leaves nothing.
        events.publish(event(EpisodeEventKind::Start, "discard me")).unwrap();
        wait_status("recording").await;
        tokio::time::sleep(Duration::from_millis(500)).await;
        events.publish(event(EpisodeEventKind::Discard, "")).unwrap();
        wait_status("discarded").await;
        // A 3 s episode with 20 Hz steps.
        events.publish(event(EpisodeEventKind::Start, "put the cube in the bin")).unwrap();
        wait_status("recording").await;
        for k in 0..60u64 {
            let t = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).unwrap().as_nanos() as i64;
            steps.publish(Step { header: header(t, "base"), step_index: k, ..Default::default() }).unwrap();
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
        events.publish(event(EpisodeEventKind::Success, "")).unwrap();
        let done = wait_status("recorded").await;
        assert_eq!(done["outcome"], "success", "{done}");
        std::path::PathBuf::from(done["dir"].as_str().unwrap())
    });
    assert!(dir.starts_with(root.path().join("success")), "{}", dir.display());
    let recording: Vec<_> = std::fs::read_dir(root.path().join(".recording")).unwrap().collect();
    assert!(recording.is_empty(), "the discarded and the moved episodes left nothing behind");
    let v = labrig_tests::read_episode_with_python(&dir);
    let counts = &v["mcap"]["counts"];
    assert_eq!(counts["/rig/step"], 60, "{v}");
    assert_eq!(v["rosbags_dir"], *counts, "rosbags agrees: {v}");
    for cam in labrig_msgs::rig::RIG_CAMERAS {
        let n = counts[format!("/cameras/{cam}/image/compressed")].as_u64().unwrap_or(0);
        assert!((45..=75).contains(&n), "camera {cam}: {n} frames in ~3 s at 20 Hz: {v}");
    }
    for t in ["/arm/state", "/tf", "/joint_states", "/tf_static", "/sim/scene"] {
        assert!(counts[t].as_u64().unwrap_or(0) > 0, "{t} missing: {v}");
    }
    assert_eq!(v["mcap"]["samples"]["image_format"], "jpeg");
    assert_eq!(v["mcap"]["samples"]["image_jpeg_markers"], true);
    let droid = &v["mcap"]["metadata"]["droid_episode"];
    assert_eq!(droid["success"], "true");
    assert_eq!(droid["trajectory_length"], "60");
    assert_eq!(droid["current_task"], "put the cube in the bin");
    assert_eq!(droid["scene_id"], "pick_place_cube");
    let extrinsics: Value = serde_json::from_str(droid["extrinsics"].as_str().unwrap()).unwrap();
    // The four fixed cameras (the wrist camera moves: its pose is in /tf every step).
    let ext = extrinsics.as_object().unwrap();
    assert_eq!(ext.keys().collect::<Vec<_>>(), ["ext1", "ext2", "rs1", "rs2"], "{extrinsics}");
    assert!(droid["sim_scene"].as_str().unwrap().contains("\"seed\""));
}

/// An episode recorded in two parts (a recorder killed mid-episode and restarted): the first
/// part recovered in place, the second written beside it. `inspect`, `read_episode` and the
/// reference readers (mcap-ros2-support, rosbags on the directory's metadata.yaml) read both
/// as one episode; the gap between them is counted and named.
#[test]
fn an_episode_in_two_parts_reads_as_one_with_its_gap_named() {
    let root = tempfile::tempdir().unwrap();
    let meta = EpisodeMetadata::new(&RigIdentity::default(), "pick_place_cube", "two parts", Nanos(T0));
    let dir = root.path().join(".recording/ep");
    let step = |k: i64| Step {
        header: header(T0 + k * TICK, "base"),
        episode_id: meta.uuid.clone(),
        step_index: k as u64,
        ..Default::default()
    };
    // Part 0: steps 0..60 (three seconds, so chunks close), then "killed" (never finished).
    let mut w = EpisodeWriter::create(&dir, meta.clone()).unwrap();
    for k in 0..60 {
        let t = T0 + k * TICK;
        w.write("/rig/step", &step(k), Nanos(t + 1_000), Nanos(t), Reliability::Reliable).unwrap();
    }
    let closed = w.closed_chunks();
    assert!(closed >= 2, "{closed} chunks closed");
    std::mem::forget(w); // SIGKILL: no summary, no footer, the open chunk never written
    let (code, v) = inspect(&dir);
    assert_eq!((code, &v["complete"]), (Some(3), &Value::Bool(false)), "{v}");
    let recovered = labrig_episode::recover::recover_in_place(&dir).unwrap();
    let kept = recovered.messages();
    assert!((40..60).contains(&kept), "part 0 keeps its closed chunks: {kept} steps");
    // Part 1: from step 70 on (steps kept..70 lost in the gap).
    let mut w = EpisodeWriter::create_part(&dir, meta.clone(), vec![recovered.info.clone()]).unwrap();
    for k in 70..100 {
        let t = T0 + k * TICK;
        w.write("/rig/step", &step(k), Nanos(t + 1_000), Nanos(t), Reliability::Reliable).unwrap();
    }
    w.metadata_mut().success = Some(true);
    w.finish().unwrap();
    assert!(dir.join("episode_1.mcap").exists() && dir.join("episode_0.mcap.damaged").exists());
    let (code, v) = inspect(&dir);
    assert_eq!(v["complete"], true, "{v}");
    assert_eq!(v["steps"], kept + 30, "{v}");
    assert_eq!(v["parts"].as_array().unwrap().len(), 2, "{v}");
    assert_eq!(v["gaps"][0]["steps_missing"], 70 - kept, "{v}");
    let gap_s = v["gaps"][0]["seconds"].as_f64().unwrap();
    assert!((gap_s - (70 - kept + 1) as f64 * 0.05).abs() < 1e-6, "gap {gap_s} s: {v}");
    assert!(v["flags"].as_array().unwrap().iter().any(|f| f.as_str().unwrap().contains("recorded in parts")), "{v}");
    assert_eq!(code, Some(3), "a gap is flagged: {v}");
    assert_eq!(v["metadata"]["success"], true, "the last part's record wins: {v}");
    let data = labrig_episode::read_episode(&dir).unwrap();
    assert_eq!((data.parts, data.steps.len() as u64), (2, kept + 30));
    assert!(data.steps.windows(2).all(|w| w[0].step_index < w[1].step_index));
    let v = labrig_tests::read_episode_with_python(&dir);
    let expected = serde_json::json!({ "/rig/step": kept + 30 });
    assert_eq!(v["parts"], 2, "{v}");
    assert_eq!(v["mcap"]["counts"], expected, "mcap + mcap-ros2-support over both parts: {v}");
    assert_eq!(v["rosbags_dir"], expected, "rosbags on the directory (metadata.yaml lists both): {v}");
    assert_eq!(v["rosbags_file"], expected, "rosbags on the two files: {v}");
}

/// A staging directory a dead recorder left, whose episode nobody speaks for (no loop on the
/// domain): the next recorder recovers it (every closed chunk) and files it where the
/// operator looks — `failure/`, complete, `success` unknown and `recovered` saying why —
/// leaving nothing in `.recording/`.
#[test]
fn a_dead_recorders_episode_is_recovered_and_filed_unjudged_on_restart() {
    let root = tempfile::tempdir().unwrap();
    let meta = EpisodeMetadata::new(&RigIdentity::default(), "pick_place_cube", "left behind", Nanos(T0));
    let staging = root.path().join(".recording").join("LABRIG+operator+left");
    let mut w = EpisodeWriter::create(&staging, meta.clone()).unwrap();
    for k in 0..40i64 {
        let t = T0 + k * TICK;
        let step = Step { header: header(t, "base"), step_index: k as u64, ..Default::default() };
        w.write("/rig/step", &step, Nanos(t + 1_000), Nanos(t), Reliability::Reliable).unwrap();
    }
    std::mem::forget(w); // killed: no summary, the open chunk lost
    let domain = labrig_tests::domain_for("recorder_orphan_unjudged");
    let mut rec = Command::new(labrig_tests::workspace_bin("labrig-recorder", "labrig-recorder"));
    rec.args(["run", "--domain-id", &domain.to_string(), "--set", "rejoin_wait_s=1", "--root"])
        .arg(root.path())
        .env(labrig_runtime::frames::NAMESPACE_ENV, format!("orphan_{}", std::process::id()));
    let _rec = labrig_tests::Proc::spawn("labrig-recorder run", rec);
    let failure = root.path().join("failure");
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(60);
    let dir = loop {
        let filed = std::fs::read_dir(&failure)
            .ok()
            .and_then(|mut days| days.next())
            .and_then(|d| std::fs::read_dir(d.unwrap().path()).ok()?.next())
            .map(|e| e.unwrap().path());
        if let Some(d) = filed {
            break d;
        }
        assert!(
            std::time::Instant::now() < deadline,
            "never filed: {:?}",
            std::fs::read_dir(root.path().join(".recording"))
        );
        std::thread::sleep(std::time::Duration::from_millis(100));
    };
    assert!(!staging.exists(), "moved out of .recording");
    let (_, v) = inspect(&dir);
    assert_eq!(v["complete"], true, "{v}");
    let flags = v["flags"].as_array().unwrap();
    assert!(flags.iter().all(|f| f.as_str().unwrap().starts_with("no camera frames")), "recovered and whole: {v}");
    let steps = v["steps"].as_u64().unwrap();
    assert!((30..40).contains(&steps), "the closed chunks' steps: {steps}");
    assert_eq!(v["metadata"]["success"], Value::Null, "unjudged: {v}");
    assert!(v["metadata"]["recovered"].as_str().unwrap().contains("unjudged"), "{v}");
    assert_eq!(v["metadata"]["uuid"], meta.uuid.as_str());
    let py = labrig_tests::read_episode_with_python(&dir);
    assert_eq!(py["rosbags_dir"]["/rig/step"], steps, "{py}");
}

/// An episode holds no frame of the scene before it (issue 54: a demo's second episode opened
/// on the first one's last image). The sim bridge stamps `/sim/scene` with the sim time it set
/// the scene (`since_ns`); the idle recorder keeps each camera's newest frame for the next
/// Start, and when that frame is the last scene's (captured 50 ms before the new scene, well
/// inside the 200 ms pre-roll) it must stay out. Driven by hand so the timing that showed the
/// bug is the timing here: the old frame is held, the new scene comes, the Start comes before
/// the new scene's first frame.
#[test]
fn an_episode_holds_no_frame_of_the_scene_before_it() {
    use labrig_msgs::rig::{EpisodeEvent, EpisodeEventKind};
    use labrig_msgs::std_msgs::StringMsg;
    use labrig_runtime::frames::{FrameEncoding, FrameFormat, FrameNode};
    use labrig_runtime::ros::{Ros, qos};
    use std::time::Duration;
    let domain = labrig_tests::domain_for("recorder_scene_bound");
    let ns = format!("recorder_scene_{}", std::process::id());
    let root = tempfile::tempdir().unwrap();
    let mut rec = Command::new(labrig_tests::workspace_bin("labrig-recorder", "labrig-recorder"));
    rec.args(["run", "--domain-id", &domain.to_string(), "--root"])
        .arg(root.path())
        .env(labrig_runtime::frames::NAMESPACE_ENV, &ns);
    let _rec = labrig_tests::Proc::spawn("labrig-recorder run", rec);
    let frames = FrameNode::new_in(&ns).unwrap();
    let mut ext1 =
        frames.publisher("ext1", FrameFormat { encoding: FrameEncoding::Rgb8, width: 32, height: 24 }).unwrap();
    const S: i64 = 1_000_000_000;
    let (old_scene_frame, new_scene) = (2 * S, 2 * S + TICK);
    let dir = labrig_tests::rt().block_on(async move {
        let cfg = labrig_runtime::RosConfig { domain_id: domain, ..Default::default() };
        let mut ros = Ros::new(&cfg, "recorder_scene_test").unwrap();
        let events = ros.publisher_on(&labrig_msgs::topics::RIG_EPISODE, 10).unwrap();
        let steps = ros.publisher_on(&labrig_msgs::topics::RIG_STEP, 100).unwrap();
        let scene = ros.publisher_on(&labrig_msgs::topics::SIM_SCENE, 1).unwrap();
        let status = ros.subscription::<StringMsg>("/recorder/status", qos::latched(1)).unwrap();
        assert!(ros.wait_for_subscribers("/rig/episode", 1, Duration::from_secs(60)).await, "no recorder");
        assert!(ros.wait_for_subscribers("/sim/scene", 1, Duration::from_secs(60)).await);
        tokio::time::sleep(Duration::from_millis(500)).await;
        let wait_status = |want: &'static str| recorder_says(&status, want);
        let wall =
            || Nanos(std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).unwrap().as_nanos() as i64);
        let pixels = |k: u8| vec![k; 32 * 24 * 3];
        // The last scene, and its last render, which the idle recorder keeps.
        // (A few renders: a shared-memory publisher's first sample may reach a subscriber only
        // once the two have connected.)
        scene.publish(StringMsg { data: format!(r#"{{"seed": 1, "since_ns": {S}}}"#) }).unwrap();
        for k in (0..5i64).rev() {
            ext1.publish(&pixels(10), Nanos(old_scene_frame - k * TICK), wall()).unwrap();
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
        tokio::time::sleep(Duration::from_millis(300)).await;
        // The new scene, then the Start on its first tick before its first frame comes.
        scene.publish(StringMsg { data: format!(r#"{{"seed": 2, "since_ns": {new_scene}}}"#) }).unwrap();
        tokio::time::sleep(Duration::from_millis(300)).await;
        let event = |kind: EpisodeEventKind, t: i64| EpisodeEvent {
            header: header(t, ""),
            kind: kind as u8,
            note: "put the cube in the bin".into(),
            ..Default::default()
        };
        events.publish(event(EpisodeEventKind::Start, new_scene)).unwrap();
        wait_status("recording").await;
        for k in 0..10i64 {
            let t = new_scene + k * TICK;
            ext1.publish(&pixels(100 + k as u8), Nanos(t), wall()).unwrap();
            let cameras = vec![CameraFrameRef { camera_id: "ext1".into(), capture_ns: t, ..Default::default() }];
            steps
                .publish(Step { header: header(t, "base"), step_index: k as u64, cameras, ..Default::default() })
                .unwrap();
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
        events.publish(event(EpisodeEventKind::Success, new_scene + 10 * TICK)).unwrap();
        let done = wait_status("recorded").await;
        std::path::PathBuf::from(done["dir"].as_str().unwrap())
    });
    let file = labrig_episode::episode::part_files(&dir).unwrap().remove(0);
    let images = &labrig_tests::camera_images(&file)["ext1"];
    let stamps: Vec<i64> = images.iter().map(|(t, _)| *t).collect();
    assert_eq!(stamps, (0..10).map(|k| new_scene + k * TICK).collect::<Vec<_>>(), "the last scene's frame got in");
    // inspect knows the scene's time and would name such a frame.
    let (code, report) = inspect(&dir);
    assert_eq!(code, Some(0), "{report:#}");
    assert_eq!(report["clock"], "sim", "{report:#}");
    assert_eq!(report["cameras"][0]["frames_before_scene"], 0, "{report:#}");
}
