//! labrig's own messages for ROS 2 nodes: the interface package `ros2/labrig_msgs`, built with
//! colcon from the PyPI ROS 2 (Kilted) wheels by `scripts/setup.sh`, against the Rust types.
//! labrig's type hashes equal the ones rosidl computed while building it (and the ones the
//! wheels ship for the standard types); a real rclpy node with the generated Python types reads
//! a live rollout's `/rig/step` and `/policy/chunk` field for field as labrig published them,
//! and drives the simulated FR3 through the franka node with `labrig_msgs/msg/ArmCommand`.

use labrig_msgs::rig::{ActionChunk, RIG_CAMERAS, Step};
use labrig_msgs::topics;
use labrig_runtime::RosConfig;
use labrig_runtime::frames::NAMESPACE_ENV;
use labrig_runtime::ros::Ros;
use labrig_tests::{Proc, domain_for, labrig_bin, repo_root, ros_msgs_prefix, ros_python, rt, sim_bin, workspace_bin};
use serde_json::{Value, json};
use std::collections::BTreeMap;
use std::path::Path;
use std::process::Command;
use std::time::{Duration, Instant};

/// Every `type_hashes` entry of the rosidl type description files under `share`
/// (`<pkg>/msg/*.json`, `<pkg>/srv/*.json`: a service's file also holds its request's and
/// response's).
fn rosidl_hashes(share: &Path, into: &mut BTreeMap<String, String>) {
    for pkg in std::fs::read_dir(share).unwrap().filter_map(|e| e.ok()) {
        for kind in ["msg", "srv"] {
            let Ok(files) = std::fs::read_dir(pkg.path().join(kind)) else { continue };
            for f in files.filter_map(|e| e.ok()).map(|e| e.path()) {
                if f.extension().is_some_and(|e| e == "json") {
                    let v: Value = serde_json::from_str(&std::fs::read_to_string(&f).unwrap()).unwrap();
                    for h in v["type_hashes"].as_array().into_iter().flatten() {
                        into.insert(h["type_name"].as_str().unwrap().into(), h["hash_string"].as_str().unwrap().into());
                    }
                }
            }
        }
    }
}

#[test]
fn labrig_type_hashes_equal_the_ones_rosidl_computed_building_the_package() {
    let prefix = ros_msgs_prefix();
    // The package built is this tree's: its .msg files are the ones the Rust types include.
    let src = repo_root().join("ros2/labrig_msgs/msg");
    let mut names = Vec::new();
    for f in std::fs::read_dir(&src).unwrap().map(|e| e.unwrap().path()) {
        let name = f.file_name().unwrap().to_str().unwrap().to_owned();
        let built = std::fs::read_to_string(prefix.join("share/labrig_msgs/msg").join(&name)).unwrap();
        assert_eq!(built, std::fs::read_to_string(&f).unwrap(), "{name}: the build is of another tree");
        names.push(format!("labrig_msgs/msg/{}", name.trim_end_matches(".msg")));
    }
    assert_eq!(names.len(), 13, "{names:?}");
    let mut rosidl = BTreeMap::new();
    rosidl_hashes(&prefix.join("share"), &mut rosidl);
    let venv = ros_python().parent().unwrap().parent().unwrap().to_owned();
    rosidl_hashes(&venv.join("share"), &mut rosidl);
    let o = Command::new(labrig_bin()).args(["topic", "hashes", "--json"]).output().unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let labrig: BTreeMap<String, String> = serde_json::from_slice(&o.stdout).unwrap();
    // Every package type labrig has a hash for, and every type labrig knows is compared.
    for n in &names {
        assert!(labrig.contains_key(n), "labrig has no hash for {n}");
    }
    // tf2_msgs is not on PyPI (no wheel ships its type descriptions): the one type labrig
    // knows that is not compared here.
    let mut missing = Vec::new();
    for (ty, hash) in &labrig {
        match rosidl.get(ty) {
            Some(theirs) => assert_eq!(hash, theirs, "{ty}: labrig's type hash is not rosidl's"),
            None => missing.push(ty.as_str()),
        }
    }
    assert_eq!(missing, ["tf2_msgs/msg/TFMessage"], "types rosidl computed no hash for");
    assert!(labrig.len() >= 35, "{} types compared", labrig.len());
}

/// JSON lines of a peer until it prints nothing for `quiet`.
fn drain(p: &mut Proc, quiet: Duration) -> Vec<Value> {
    let mut out = Vec::new();
    while let Some(l) = p.next_line(quiet) {
        if let Ok(v) = serde_json::from_str::<Value>(&l) {
            out.push(v);
        }
    }
    out
}

/// The hash rclpy's own subscription announced (its generated type support's).
fn own_subscription_hash(lines: &[Value]) -> String {
    let matched = lines.iter().find(|v| v.get("matched").is_some()).expect("the listener matched a publisher");
    let own = matched["type_hashes"].as_array().unwrap().iter().find(|h| h["kind"] == "subscription").unwrap();
    own["type_hash"].as_str().unwrap().to_owned()
}

#[test]
fn rclpy_reads_a_rollouts_steps_and_chunks_with_the_generated_types() {
    let domain = domain_for("ros2_interfaces_rollout");
    let listen = |topic: &str, ty: &str| {
        let mut p = Proc::ros_peer_with_labrig_msgs(
            domain,
            &["listen", "--topic", topic, "--type", ty, "--count", "100000", "--timeout", "300"],
        );
        p.wait_json(Duration::from_secs(30), "ready", |v| v["ready"] == true);
        p
    };
    let mut steps_peer = listen(topics::RIG_STEP.name, "labrig_msgs/msg/Step");
    let mut chunks_peer = listen(topics::POLICY_CHUNK.name, "labrig_msgs/msg/ActionChunk");
    // labrig's own reading of the chunks, beside rclpy's.
    let rt = rt();
    let (stop_tx, stop_rx) = std::sync::mpsc::channel::<()>();
    let cfg = RosConfig { domain_id: domain, ..RosConfig::default() };
    let ours = rt.spawn(async move {
        let mut ros = Ros::new(&cfg, "labrig_chunk_reader").unwrap();
        let sub = ros.subscription_on(&topics::POLICY_CHUNK, 1000).unwrap();
        let mut got = Vec::new();
        while stop_rx.try_recv().is_err() {
            match sub.try_take() {
                Ok(Some(r)) => got.push(r.msg),
                Ok(None) => tokio::time::sleep(Duration::from_millis(5)).await,
                Err(e) => panic!("{e}"),
            }
        }
        got
    });
    let dir = tempfile::tempdir().unwrap();
    let o = Command::new(labrig_bin())
        .args(["rollout", "--threads", "1", "--json", "--episodes", "1", "--max-steps", "30", "--policy"])
        .arg(repo_root().join("tests/fixtures/policies/tiny_lowdim"))
        .args(["--domain-id", &domain.to_string(), "--out"])
        .arg(dir.path())
        .env(NAMESPACE_ENV, format!("ros2_interfaces_{}", std::process::id()))
        .current_dir(repo_root())
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&o.stdout);
    assert!(o.status.success(), "{stdout}\n{}", String::from_utf8_lossy(&o.stderr));
    let report: Value = serde_json::from_str(stdout.lines().last().unwrap()).unwrap();
    let quiet = Duration::from_secs(3);
    let (step_lines, chunk_lines) = (drain(&mut steps_peer, quiet), drain(&mut chunks_peer, quiet));
    stop_tx.send(()).unwrap();
    let ours: Vec<ActionChunk> = rt.block_on(ours).unwrap();

    // Steps: every recorded step arrived in rclpy's generated type, every field equal
    // (floats exactly: JSON round-trips them).
    let recorded = labrig_episode::read_episode(Path::new(report["rollouts"][0]["dir"].as_str().unwrap())).unwrap();
    assert_eq!(recorded.steps.len(), 30, "{report:#}");
    let theirs: BTreeMap<(String, u64), Step> = step_lines
        .iter()
        .filter_map(|v| v.get("msg"))
        .map(|m| serde_json::from_value::<Step>(m.clone()).unwrap_or_else(|e| panic!("{e}: {m}")))
        .map(|s| ((s.episode_id.clone(), s.step_index), s))
        .collect();
    for s in &recorded.steps {
        let t = theirs.get(&(s.episode_id.clone(), s.step_index));
        assert_eq!(t, Some(s), "step {} as rclpy read it", s.step_index);
    }
    assert!(recorded.steps.iter().all(|s| s.chunk_id != 0 && s.action_source == Step::SOURCE_POLICY));
    assert!(recorded.steps.iter().any(|s| !s.robot_state.joint_positions.iter().all(|q| *q == 0.0)));
    assert_eq!(recorded.steps[0].cameras.len(), RIG_CAMERAS.len(), "nested sequences arrive too");

    // Chunks: rclpy's equal labrig's own subscriber's, one for one, and the steps ran them.
    let theirs: Vec<ActionChunk> = chunk_lines
        .iter()
        .filter_map(|v| v.get("msg"))
        .map(|m| serde_json::from_value::<ActionChunk>(m.clone()).unwrap_or_else(|e| panic!("{e}: {m}")))
        .collect();
    // /policy/chunk is reliable but volatile: a chunk sent before rclpy's reader discovered
    // the policy server (which starts with the rollout) is not resent; from rclpy's first on,
    // it read every chunk labrig read.
    assert!(theirs.len() >= 2 && ours.len() >= 3, "rclpy {} chunks, labrig {}", theirs.len(), ours.len());
    let first = theirs[0].request_id;
    let ours_from: Vec<ActionChunk> = ours.iter().filter(|c| c.request_id >= first).cloned().collect();
    assert_eq!(theirs, ours_from, "the chunks rclpy read are the ones labrig read");
    assert!(ours.iter().take(3).any(|c| c.request_id == first), "rclpy's first chunk is {first}: {ours:?}");
    for id in recorded.steps.iter().map(|s| s.chunk_id).filter(|id| *id >= first) {
        assert!(theirs.iter().any(|c| c.request_id == id), "chunk {id} executed but not received");
    }
    assert!(theirs.iter().all(|c| c.actions.len() == (c.horizon * c.action_dim) as usize && c.horizon > 0));

    // The type hash rclpy's generated types announce is labrig's.
    assert_eq!(own_subscription_hash(&step_lines), labrig_msgs::type_hash::<Step>(), "Step");
    assert_eq!(own_subscription_hash(&chunk_lines), labrig_msgs::type_hash::<ActionChunk>(), "ActionChunk");
}

#[test]
fn an_rclpy_planner_drives_the_simulated_arm_with_labrig_msgs() {
    let domain = domain_for("ros2_interfaces_arm");
    let d = domain.to_string();
    // The rig's arm as sim_droid.toml runs it: the sim bridge (its FR3 under /sim, time on the
    // wall clock's line: rclpy stamps commands with its wall clock) and the franka node.
    let mut sim = Command::new(sim_bin());
    sim.args(["run", "--mode", "realtime", "--hardware-prefix", "/sim", "--no-cameras", "--wall-clock-origin"])
        .args(["--domain-id", &d]);
    let _sim = Proc::spawn("labrig-sim run", sim);
    let mut franka = Command::new(workspace_bin("labrig-franka", "labrig-franka"));
    franka.args(["run", "--backend", "sim", "--domain-id", &d]);
    let _franka = Proc::spawn("labrig-franka run", franka);
    let reset = labrig_msgs::rig::DROID_RESET_POSE;
    let delta = [0.15, -0.1, 0.1, 0.1, -0.1, 0.1, 0.2];
    let target: Vec<f64> = reset.iter().zip(delta).map(|(q, d)| q + d).collect();
    let target_arg = target.iter().map(|q| format!("{q}")).collect::<Vec<_>>().join(",");
    let mut planner =
        Proc::ros_peer_with_labrig_msgs(domain, &["drive-arm", "--target", &target_arg, "--seconds", "12"]);
    let ready = planner.wait_json(Duration::from_secs(60), "the franka node's subscription", |v| v["ready"] == true);
    let started = Instant::now();
    // While it drives: labrig's `topic info` reads the hash rclpy announced in discovery and
    // finds it labrig's (the franka node's subscription, RustDDS's, announces none).
    let info = Command::new(labrig_bin())
        .args(["topic", "info", "/arm/command", "--json", "--wait", "3", "--domain-id", &d])
        .output()
        .unwrap();
    assert!(info.status.success(), "{}", String::from_utf8_lossy(&info.stderr));
    let info: Value = serde_json::from_slice(&info.stdout).unwrap();
    let mut states: Vec<Vec<f64>> = Vec::new();
    let mut modes = Vec::new();
    loop {
        let v = planner.wait_json(Duration::from_secs(30), "a state or the end", |v| {
            v.get("state").is_some() || v.get("done").is_some()
        });
        if v.get("done").is_some() {
            assert!(v["commands"].as_u64().unwrap() > 100, "{v}");
            break;
        }
        assert_eq!(v["state"]["fault"], "", "{v}");
        modes.push(v["state"]["mode"].as_u64().unwrap());
        states.push(serde_json::from_value(v["state"]["joint_positions"].clone()).unwrap());
        assert!(started.elapsed() < Duration::from_secs(60), "the planner runs 12 s");
    }
    let (first, last) = (states.first().expect("states read"), states.last().unwrap());
    for j in 0..7 {
        assert!((first[j] - reset[j]).abs() < 0.05, "joint {j} starts at the reset pose: {first:?}");
        assert!((last[j] - target[j]).abs() < 0.02, "joint {j} reached {} of target {}: {last:?}", last[j], target[j]);
    }
    assert!(modes.contains(&1), "the arm reported MODE_MOVING: {modes:?}");
    // The franka node's subscription and rclpy's publisher agree on the type; rclpy's
    // generated type hashes as labrig hashes it.
    let labrig = labrig_msgs::type_hash::<labrig_msgs::rig::ArmCommand>();
    let own = ready["type_hashes"].as_array().unwrap().iter().find(|h| h["kind"] == "publisher").unwrap();
    assert_eq!(own["type_hash"], labrig, "{ready}");
    let endpoints = info["endpoints"].as_array().unwrap();
    let rclpy = endpoints.iter().find(|e| e["kind"] == "publisher").unwrap_or_else(|| panic!("{info}"));
    assert_eq!((&rclpy["type"], &rclpy["type_hash"], &rclpy["matches"]), (&json!(ARM), &json!(labrig), &json!(true)));
    let node = endpoints.iter().find(|e| e["kind"] == "subscription").unwrap_or_else(|| panic!("{info}"));
    assert_eq!((&node["type"], &node["type_hash"]), (&json!(ARM), &Value::Null), "{info}");
}

const ARM: &str = "labrig_msgs/msg/ArmCommand";
