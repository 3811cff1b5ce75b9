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
    fn session(&self) -> u32 {
        0
    }
    fn infer(&self, n: &mut u32, obs: Value) -> Result<Value, String> {
        for key in [droid::EXTERIOR_IMAGE, droid::WRIST_IMAGE, droid::JOINT_POSITION] {
            codec::get(&obs, key).ok_or_else(|| format!("KeyError: the observation has no {key:?}"))?;
        }
        let (_, q) = codec::numbers(&obs, droid::JOINT_POSITION).map_err(|e| e.to_string())?;
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
