//! labrig's openpi protocol (labrig-openpi) against openpi's own code from PyPI: the upstream
//! `WebsocketPolicyServer` (openpi-server 0.1.0) answering labrig's client, and openpi-client's
//! `WebsocketClientPolicy` / `ActionChunkBroker` querying labrig's server. Everything binds
//! 127.0.0.1.

use labrig_openpi::codec::{self, Array, Value};
use labrig_openpi::droid;
use labrig_openpi::{Client, ClientError, Handler, Server};
use labrig_tests::{Proc, openpi_peer};
use std::sync::Arc;
use std::time::Duration;

/// The upstream server with a test policy serving `chunks` (failing on request `fail_on`);
/// its port and its request log.
fn upstream(
    chunks: &[Vec<[f32; 8]>],
    fail_on: Option<u32>,
    dir: &std::path::Path,
) -> (Proc, String, std::path::PathBuf) {
    let file = dir.join("chunks.json");
    let list: Vec<Vec<Vec<f32>>> = chunks.iter().map(|c| c.iter().map(|r| r.to_vec()).collect()).collect();
    std::fs::write(&file, serde_json::to_string(&list).unwrap()).unwrap();
    let log = dir.join("requests.jsonl");
    let fail = fail_on.map(|n| n.to_string());
    let mut args = vec!["serve", "--chunks", file.to_str().unwrap(), "--log", log.to_str().unwrap()];
    args.extend(["--metadata", r#"{"policy": "test-chunks", "action_horizon": 15}"#]);
    if let Some(f) = &fail {
        args.extend(["--fail-on", f.as_str()]);
    }
    let mut proc = Proc::spawn("openpi server", openpi_peer(&args));
    let line = proc.next_line(Duration::from_secs(60)).expect("the openpi server prints its port");
    let port = serde_json::from_str::<serde_json::Value>(&line).unwrap()["port"].as_u64().unwrap();
    let addr = format!("127.0.0.1:{port}");
    // Up once /healthz answers (bounded).
    for _ in 0..200 {
        if labrig_openpi::client::healthz(&addr, Duration::from_secs(1)).is_ok() {
            return (proc, addr, log);
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    panic!("the openpi server on {addr} never answered /healthz");
}

fn droid_obs(seed: u8) -> Value {
    let ext: Vec<u8> = (0..224 * 224 * 3).map(|i| (i as u8).wrapping_mul(seed)).collect();
    let wrist = vec![seed; 224 * 224 * 3];
    droid::Observation {
        exterior: (&ext, 224, 224),
        wrist: (&wrist, 224, 224),
        joint_position: [0.0, -0.5, 0.0, -2.2, 0.0, 1.8, 0.8],
        gripper_position: 0.25,
        prompt: "open the drawer",
    }
    .to_value()
}

#[test]
fn labrigs_client_gets_chunks_and_errors_from_openpis_own_server() {
    let dir = tempfile::tempdir().unwrap();
    let chunk = |k: f32| (0..15).map(|i| [k, i as f32 * 0.01, 0.0, 0.0, 0.0, 0.0, -0.5, 0.9]).collect::<Vec<_>>();
    let (mut server, addr, log) = upstream(&[chunk(0.1), chunk(0.2)], Some(2), dir.path());
    let t = Duration::from_secs(10);

    let mut c = Client::connect(&addr, t).expect("connects");
    assert_eq!(codec::to_json_text(c.metadata()), r#"{"policy":"test-chunks","action_horizon":15}"#);
    for k in [0.1f32, 0.2] {
        let reply = c.infer(&droid_obs(3), t).expect("a reply");
        let rows = droid::action_rows(&reply, 8).unwrap();
        assert_eq!(rows.len(), 15);
        assert_eq!(rows[3], vec![f64::from(k), f64::from(0.03f32), 0.0, 0.0, 0.0, 0.0, -0.5, f64::from(0.9f32)]);
        let timing = codec::get(&reply, "server_timing").expect("server_timing");
        assert!(codec::numbers(timing, "infer_ms").unwrap().1[0] >= 0.0);
    }
    // Request 2 raises in the policy: the traceback's last line, and the connection is gone.
    let e = c.infer(&droid_obs(3), t).unwrap_err();
    match &e {
        ClientError::Server { last_line, traceback, .. } => {
            assert_eq!(last_line, "RuntimeError: test policy: request 2 fails on purpose");
            assert!(traceback.starts_with("Traceback"), "{traceback}");
        }
        other => panic!("expected the server's error frame, got {other}"),
    }
    assert!(e.connection_lost() && c.is_broken());
    // A new handshake works (the server's handler task died with the raise; the server lives).
    let mut again = Client::connect(&addr, t).expect("reconnects");
    assert!(again.infer(&droid_obs(5), t).is_ok());

    // What the upstream server decoded: openpi's DROID keys, dtypes and shapes.
    let first: serde_json::Value =
        serde_json::from_str(std::fs::read_to_string(&log).unwrap().lines().next().unwrap()).unwrap();
    let keys = &first["keys"];
    assert_eq!(keys[droid::EXTERIOR_IMAGE], serde_json::json!({"shape": [224, 224, 3], "dtype": "|u1"}));
    assert_eq!(keys[droid::WRIST_IMAGE], serde_json::json!({"shape": [224, 224, 3], "dtype": "|u1"}));
    assert_eq!(keys[droid::JOINT_POSITION], serde_json::json!({"shape": [7], "dtype": "<f8"}));
    assert_eq!(keys[droid::GRIPPER_POSITION], serde_json::json!({"shape": [1], "dtype": "<f8"}));
    assert_eq!(keys["prompt"], serde_json::json!({"type": "str"}));
    assert_eq!(first["joint_position"], serde_json::json!([0.0, -0.5, 0.0, -2.2, 0.0, 1.8, 0.8]));
    assert_eq!(first["prompt"], "open the drawer");

    // The server gone: named as unreachable.
    drop(again);
    let _ = server.child.kill();
    let _ = server.child.wait();
    match Client::connect(&addr, Duration::from_secs(2)) {
        Err(e @ ClientError::Unreachable { .. }) => assert!(e.to_string().contains(&addr), "{e}"),
        other => panic!("expected unreachable, got {other:?}"),
    }
}

/// A labrig server handler: a (15, 8) chunk whose first column is the request's count in this
/// connection and whose second is the joint_position's first entry; a missing key fails.
struct Counting;

impl Handler for Counting {
    type Session = u32;
    /// The text is what the client is sent.
    type Error = std::io::Error;
    fn session(&self) -> u32 {
        0
    }
    fn infer(&self, n: &mut u32, obs: Value) -> Result<Value, std::io::Error> {
        for key in [droid::EXTERIOR_IMAGE, droid::WRIST_IMAGE, droid::JOINT_POSITION] {
            codec::get(&obs, key)
                .ok_or_else(|| std::io::Error::other(format!("KeyError: the observation has no {key:?}")))?;
        }
        let (_, q) = codec::numbers(&obs, droid::JOINT_POSITION).map_err(std::io::Error::other)?;
        *n += 1;
        let rows: Vec<f32> = (0..15).flat_map(|_| [*n as f32, q[1] as f32, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0]).collect();
        Ok(codec::map([("actions", Array::f32(&[15, 8], &rows).to_value())]))
    }
}

#[test]
fn openpis_own_client_and_broker_query_labrigs_server() {
    let metadata = codec::map([("policy_id", Value::from("counting@1"))]);
    let server = Server::bind("127.0.0.1:0", metadata, Arc::new(Counting)).unwrap();
    let addr = server.local_addr();
    assert!(addr.ip().is_loopback());
    labrig_openpi::client::healthz(&addr.to_string(), Duration::from_secs(2)).expect("/healthz answers 200");
    let url = format!("ws://{addr}");
    let out = openpi_peer(&["client", "--url", &url, "--requests", "3", "--horizon", "8"]).output().unwrap();
    assert!(out.status.success(), "openpi client: {}", String::from_utf8_lossy(&out.stderr));
    let r: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(r["metadata"], serde_json::json!({"policy_id": "counting@1"}));
    let replies = r["replies"].as_array().unwrap();
    assert_eq!(replies.len(), 3);
    for (i, rep) in replies.iter().enumerate() {
        assert_eq!(rep["shape"], serde_json::json!([15, 8]));
        assert_eq!(rep["dtype"], "<f4");
        assert_eq!(rep["finite"], true);
        // The connection's own count, and the observation's joint 1 read back.
        assert_eq!(rep["first_row"][0], serde_json::json!(i as f64 + 1.0));
        assert_eq!(rep["first_row"][1], serde_json::json!(-0.5));
        assert!(rep["server_timing"]["infer_ms"].as_f64().unwrap() >= 0.0);
        if i > 0 {
            assert!(rep["server_timing"]["prev_total_ms"].as_f64().unwrap() >= 0.0, "{rep}");
        }
    }
    // ActionChunkBroker: one row per step from each chunk of 15, a new chunk after 8.
    assert_eq!(r["broker"], serde_json::json!(vec![vec![8]; 9]));
    // A request missing a key: openpi's client raises with the server's text frame.
    let err = r["error"].as_str().expect("the bad request raised");
    assert!(err.contains("Error in inference server"), "{err}");
    assert!(err.contains("the observation has no \"observation/wrist_image_left\""), "{err}");
    assert_eq!(server.counters().errors.load(std::sync::atomic::Ordering::Relaxed), 1);
    assert!(server.counters().health_checks.load(std::sync::atomic::Ordering::Relaxed) >= 1);
}

// ---------------------------------------------------------------- the rig as openpi's client

/// A smooth pi0.5-DROID stand-in: DROID step n (chunk k's row i is step 8k + i, as the client
/// runs 8 of each chunk) moves joint j at velocity 0.15 sin(2 pi n / 40 + j); the gripper
/// closes for 30 steps, opens for 30.
fn droid_chunks(n_chunks: usize, width: usize) -> Vec<Vec<Vec<f32>>> {
    (0..n_chunks)
        .map(|k| {
            (0..15)
                .map(|i| {
                    let n = (k * 8 + i) as f32;
                    let mut row: Vec<f32> =
                        (0..7).map(|j| 0.15 * (2.0 * std::f32::consts::PI * n / 40.0 + j as f32).sin()).collect();
                    row.push(if (n as usize / 30) % 2 == 1 { 1.0 } else { 0.0 });
                    row.truncate(width);
                    row
                })
                .collect()
        })
        .collect()
}

/// The upstream server on `port` (0: a free one) serving `chunks`; its port and request log.
fn upstream_serving(
    chunks: &[Vec<Vec<f32>>],
    dir: &std::path::Path,
    name: &str,
    port: u16,
    fail_on: Option<u32>,
) -> (Proc, u16, std::path::PathBuf) {
    let file = dir.join(format!("{name}.json"));
    std::fs::write(&file, serde_json::to_string(chunks).unwrap()).unwrap();
    let log = dir.join(format!("{name}.jsonl"));
    let (port_s, fail) = (port.to_string(), fail_on.map(|n| n.to_string()));
    let mut args = vec!["serve", "--chunks", file.to_str().unwrap(), "--log", log.to_str().unwrap()];
    args.extend(["--metadata", r#"{"policy": "droid-sine"}"#]);
    if port != 0 {
        args.extend(["--port", port_s.as_str()]);
    }
    if let Some(f) = &fail {
        args.extend(["--fail-on", f.as_str()]);
    }
    let mut proc = Proc::spawn(name, openpi_peer(&args));
    let line = proc.next_line(Duration::from_secs(60)).expect("the openpi server prints its port");
    let port = serde_json::from_str::<serde_json::Value>(&line).unwrap()["port"].as_u64().unwrap() as u16;
    let addr = format!("127.0.0.1:{port}");
    for _ in 0..200 {
        if labrig_openpi::client::healthz(&addr, Duration::from_secs(1)).is_ok() {
            return (proc, port, log);
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    panic!("the openpi server on {addr} never answered /healthz");
}

fn log_lines(log: &std::path::Path) -> Vec<serde_json::Value> {
    std::fs::read_to_string(log).unwrap_or_default().lines().map(|l| serde_json::from_str(l).unwrap()).collect()
}

/// `labrig rollout --remote` (lockstep, pick_place seed 1000); its report.
fn remote_rollout(key: &str, port: u16, out: &std::path::Path, extra: &[&str]) -> serde_json::Value {
    let o = std::process::Command::new(labrig_tests::labrig_bin())
        .args(["rollout", "--json", "--episodes", "1", "--domain-id", &labrig_tests::domain_for(key).to_string()])
        .args(["--remote", &format!("127.0.0.1:{port}"), "--out"])
        .arg(out)
        .args(extra)
        .env(labrig_runtime::frames::NAMESPACE_ENV, format!("rollout_{key}_{}", std::process::id()))
        .current_dir(labrig_tests::repo_root())
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&o.stdout);
    let report: serde_json::Value = serde_json::from_str(stdout.lines().last().unwrap_or_default())
        .unwrap_or_else(|e| panic!("{e}: {stdout}\n{}", String::from_utf8_lossy(&o.stderr)));
    assert_eq!(o.status.code(), Some(0), "{report:#}\n{}", String::from_utf8_lossy(&o.stderr));
    report
}

fn recorded_steps(report: &serde_json::Value) -> labrig_episode::EpisodeData {
    let dir = report["rollouts"][0]["dir"].as_str().expect("a recorded rollout");
    labrig_episode::read_episode(std::path::Path::new(dir)).unwrap()
}

/// openpi's upstream server drives the simulated rig: every executed row is the joint target
/// DROID's conventions give for the served chunk (velocity x 0.2 rad per 1/15 s from the
/// observed joints, read at the loop's own 50 ms ticks; the gripper binarised at 0.5), the
/// arm follows, and each step names the remote policy.
#[test]
fn openpis_server_drives_the_sim_rig_with_droid_joint_velocities() {
    let dir = tempfile::tempdir().unwrap();
    let chunks = droid_chunks(40, 8);
    let (_server, port, log) = upstream_serving(&chunks, dir.path(), "droid", 0, None);
    let report = remote_rollout("openpi_remote_droid", port, &dir.path().join("out"), &["--max-steps", "60"]);
    let r = &report["rollouts"][0];
    assert_eq!(r["reason"], "the step budget (60 steps) was spent", "{report:#}");
    assert_eq!(report["policy"], format!("openpi ws://127.0.0.1:{port}"));
    let data = recorded_steps(&report);
    let requests = log_lines(&log);
    let conv = droid::ActionConvention::default();
    let want_id = format!("openpi ws://127.0.0.1:{port} {{\"policy\":\"droid-sine\"}}");
    assert_eq!(data.metadata.as_ref().unwrap().policy.as_deref(), Some(want_id.as_str()));
    let mut checked = 0;
    let mut moved = 0.0f64;
    // Steps that executed a row (the first had no frames to ask with: held, no chunk).
    for s in data.steps.iter().filter(|s| s.action_source == labrig_msgs::rig::Step::SOURCE_POLICY && s.chunk_id > 0) {
        assert_eq!(s.policy_id, want_id);
        // Request ids count from 1; the server's log from 0.
        let req = &requests[s.chunk_id as usize - 1];
        let q_obs: Vec<f64> = serde_json::from_value(req["joint_position"].clone()).unwrap();
        let served: Vec<droid::Row> = serde_json::from_value::<Vec<Vec<f64>>>(req["actions"].clone())
            .unwrap()
            .iter()
            .map(|r| std::array::from_fn(|k| r[k]))
            .collect();
        let q0: [f64; 7] = std::array::from_fn(|j| q_obs[j]);
        // Worked out here, not by labrig's resampler: the command at row m is where DROID's
        // steps (0.2 rad x velocity per 1/15 s, velocities here all within [-1, 1]) have
        // brought the joints (m + 1) x 50 ms after the observation.
        let t_steps = (f64::from(s.chunk_row) + 1.0) * 0.05 * 15.0;
        let (full, frac) = (t_steps.floor() as usize, t_steps - t_steps.floor());
        let mut want = [0.0; 8];
        for (j, w) in want.iter_mut().take(7).enumerate() {
            let done: f64 = served[..full].iter().map(|r| r[j]).sum();
            let part = served.get(full).map_or(0.0, |r| r[j] * frac);
            *w = q0[j] + 0.2 * (done + part);
        }
        // The gripper of the DROID step under way at the tick (row m at m x 50 ms), at 0.5.
        let under_way = ((f64::from(s.chunk_row) * 0.05 * 15.0) + 1e-9).floor() as usize;
        want[7] = if served[under_way][7] >= 0.5 { 1.0 } else { 0.0 };
        assert_eq!(want.map(|x| x.is_finite()), [true; 8]);
        assert!(conv.rate_hz == 15.0 && conv.max_joint_delta_rad == 0.2, "DROID's defaults");
        for (j, w) in want.iter().take(7).enumerate() {
            assert!(
                (s.action.joint_position[j] - w).abs() < 1e-9,
                "step {} (chunk {} row {}): joint {j} commanded {} != DROID's {}",
                s.step_index,
                s.chunk_id,
                s.chunk_row,
                s.action.joint_position[j],
                w
            );
        }
        assert_eq!(s.action.gripper_position, want[7], "step {}", s.step_index);
        moved = moved.max((s.action.joint_position[0] - q0[0]).abs());
        checked += 1;
    }
    // Every step but the first (no frames yet) is the policy's; 8 DROID steps = 10 ticks a chunk.
    assert!(checked >= 55, "{checked} policy steps of {}", data.steps.len());
    assert!(requests.len() >= 5, "{} requests", requests.len());
    assert!(moved > 0.05, "the arm barely moved: {moved}");
    // The prompt is the scene's instruction; the images 224 x 224 RGB.
    assert!(!requests[0]["prompt"].as_str().unwrap().is_empty(), "{:?}", requests[0]["prompt"]);
    assert_eq!(requests[0]["keys"][droid::EXTERIOR_IMAGE]["shape"], serde_json::json!([224, 224, 3]));
    // The arm follows: measured joints a tick later within 2 cm-equivalent of the command.
    let lag = data
        .steps
        .windows(2)
        .filter(|w| w[0].chunk_id > 0)
        .flat_map(|w| (0..7).map(move |j| (w[1].robot_state.joint_positions[j] - w[0].action.joint_position[j]).abs()))
        .fold(0.0f64, f64::max);
    assert!(lag < 0.05, "the measured joints trail the commands by up to {lag} rad");
}

/// The faults: an error raised in the policy fails the episode with the traceback's last line;
/// a chunk of the wrong shape is named; a killed server that comes back on its port is
/// reconnected (a new handshake) and the rollout goes on.
#[test]
fn remote_policy_faults_are_named_and_a_restarted_server_is_reconnected() {
    let dir = tempfile::tempdir().unwrap();
    let key = "openpi_remote_faults";

    // No server at start: the loop exits naming it.
    let closed = free_port();
    let o = std::process::Command::new(labrig_tests::workspace_bin("labrig-control", "labrig-control"))
        .args(["run", "--source", "remote", "--domain-id", &labrig_tests::domain_for(key).to_string()])
        .args(["--set", &format!("remote.url=\"127.0.0.1:{closed}\""), "--set", "remote.connect_timeout_s=1"])
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(
        err.contains(&format!("openpi server ws://127.0.0.1:{closed}: cannot connect"))
            && err.contains("tried for 1 s"),
        "{err}"
    );

    let (_s, port, _) = upstream_serving(&droid_chunks(40, 8), dir.path(), "raises", 0, Some(2));
    let report = remote_rollout(key, port, &dir.path().join("raises_out"), &["--max-steps", "60"]);
    let reason = report["rollouts"][0]["reason"].as_str().unwrap();
    assert!(reason.contains("RuntimeError: test policy: request 2 fails on purpose"), "{reason}");
    // Two chunks of 10 rows ran (and the first step had no frames); then it ended.
    let steps = report["rollouts"][0]["steps"].as_u64().unwrap();
    assert!((20..=23).contains(&steps), "{report:#}");

    let (_s, port, _) = upstream_serving(&droid_chunks(4, 7), dir.path(), "narrow", 0, None);
    let report = remote_rollout(key, port, &dir.path().join("narrow_out"), &["--max-steps", "60"]);
    let reason = report["rollouts"][0]["reason"].as_str().unwrap();
    assert!(reason.contains("actions of shape [15, 7]: expected (N, 8)"), "{reason}");

    // Killed after 3 requests, back on the same port 1 s later.
    let (mut first, port, log) = upstream_serving(&droid_chunks(40, 8), dir.path(), "first", 0, None);
    let out = dir.path().join("restart_out");
    let run = {
        let out = out.clone();
        std::thread::spawn(move || remote_rollout(key, port, &out, &["--max-steps", "80", "--server-timeout-s", "10"]))
    };
    let until = std::time::Instant::now() + Duration::from_secs(120);
    while log_lines(&log).len() < 3 {
        assert!(std::time::Instant::now() < until, "the rollout never made 3 requests");
        std::thread::sleep(Duration::from_millis(20));
    }
    let _ = first.child.kill();
    let _ = first.child.wait();
    std::thread::sleep(Duration::from_secs(1));
    let (_second, _, log2) = upstream_serving(&droid_chunks(40, 8), dir.path(), "second", port, None);
    let report = run.join().unwrap();
    assert_eq!(report["rollouts"][0]["reason"], "the step budget (80 steps) was spent", "{report:#}");
    assert!(!log_lines(&log2).is_empty(), "the restarted server got no request");
}

// ---------------------------------------------------------------- a labrig checkpoint as openpi's server

fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port()
}

/// `labrig-policy run --openpi`: openpi's own client and broker query a labrig checkpoint
/// (pixels + proprioception) with DROID's keys; the chunk is in the checkpoint's action space;
/// a missing key gets openpi's error frame naming it; a sim-only checkpoint is refused.
#[test]
fn openpis_client_queries_a_labrig_checkpoint() {
    let root = labrig_tests::repo_root();
    let server_bin = labrig_tests::workspace_bin("labrig-policy", "labrig-policy-server");
    let domain = labrig_tests::domain_for("openpi_server_rollout").to_string();

    // The low-dim checkpoint reads the scene's positions: nothing openpi's observation has.
    let o = std::process::Command::new(&server_bin)
        .args(["run", "--threads", "1", "--domain-id", &domain, "--openpi", "0", "--checkpoint"])
        .arg(root.join("tests/fixtures/policies/tiny_lowdim"))
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(err.contains("which openpi's DROID observation does not carry"), "{err}");

    let port = free_port();
    let mut cmd = std::process::Command::new(&server_bin);
    cmd.args(["run", "--threads", "1", "--domain-id", &domain, "--openpi", &port.to_string(), "--checkpoint"])
        .arg(root.join("tests/fixtures/policies/small_vision"));
    let _server = Proc::spawn("labrig-policy --openpi", cmd);
    let addr = format!("127.0.0.1:{port}");
    let until = std::time::Instant::now() + Duration::from_secs(120);
    while labrig_openpi::client::healthz(&addr, Duration::from_secs(1)).is_err() {
        assert!(std::time::Instant::now() < until, "labrig-policy --openpi never answered /healthz on {addr}");
        std::thread::sleep(Duration::from_millis(100));
    }
    let out = openpi_peer(&["client", "--url", &format!("ws://{addr}"), "--requests", "3", "--horizon", "8"])
        .output()
        .unwrap();
    assert!(out.status.success(), "openpi client: {}", String::from_utf8_lossy(&out.stderr));
    let r: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let meta = &r["metadata"];
    assert!(meta["policy_id"].as_str().unwrap().starts_with("small_vision@"), "{meta}");
    assert_eq!(meta["cameras"], serde_json::json!(["wrist", "ext1"]));
    assert_eq!(meta["action_space"], "eef_axis_angle");
    assert_eq!(meta["action_rate_hz"], 20.0);
    assert_eq!(meta["image_keys"][droid::WRIST_IMAGE], "wrist");
    // Tp - To + 1 = 16 - 2 + 1 rows of xyz + axis-angle + gripper, finite, in the workspace.
    let replies = r["replies"].as_array().unwrap();
    assert!(replies.len() >= 2, "{} replies", replies.len());
    for rep in replies {
        assert_eq!(rep["shape"], serde_json::json!([15, 7]), "{rep}");
        assert_eq!(rep["finite"], true);
        let row: Vec<f64> = serde_json::from_value(rep["first_row"].clone()).unwrap();
        assert!(row[0] > 0.1 && row[0] < 1.0 && row[2] > -0.1 && row[2] < 1.0, "{row:?}");
        assert!(rep["server_timing"]["infer_ms"].as_f64().unwrap() > 0.0);
    }
    assert_eq!(r["broker"], serde_json::json!(vec![vec![7]; 9]));
    let err = r["error"].as_str().expect("the bad request raised");
    assert!(err.contains("the observation has no \"observation/wrist_image_left\""), "{err}");
}

/// A chunk that comes 3 ticks late (lockstep `--delay-steps 3`): timed from its observation,
/// its first 3 rows have passed and are skipped; timed from its arrival (DROID's client), it
/// runs from row 0.
#[test]
fn a_late_chunk_runs_from_its_observation_or_from_its_arrival() {
    let dir = tempfile::tempdir().unwrap();
    let (_server, port, _) = upstream_serving(&droid_chunks(40, 8), dir.path(), "late", 0, None);
    let key = "openpi_remote_timing";
    let base = ["--max-steps", "40", "--delay-steps", "3"];
    let obs = remote_rollout(key, port, &dir.path().join("obs"), &base);
    let arr = remote_rollout(key, port, &dir.path().join("arr"), &[&base[..], &["--chunk-timing", "arrival"]].concat());
    let first_rows = |report: &serde_json::Value| -> Vec<u32> {
        let data = recorded_steps(report);
        let mut seen = std::collections::BTreeMap::new();
        for s in data.steps.iter().filter(|s| s.chunk_id > 0) {
            seen.entry(s.chunk_id).or_insert(s.chunk_row);
        }
        seen.into_values().collect()
    };
    let (o, a) = (first_rows(&obs), first_rows(&arr));
    assert!(o.len() >= 3 && a.len() >= 3, "{o:?} {a:?}");
    assert!(o.iter().all(|&r| r == 3), "from the observation: the first 3 rows passed: {o:?}");
    assert!(a.iter().all(|&r| r == 0), "from the arrival: row 0 first: {a:?}");
    assert!(obs["rollouts"][0]["skipped_rows"].as_u64().unwrap() >= 9, "{obs:#}");
    assert_eq!(arr["rollouts"][0]["skipped_rows"], 0, "{arr:#}");
}
