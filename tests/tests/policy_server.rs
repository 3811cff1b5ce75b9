//! The policy server node (`labrig-policy run`) against a real client on DDS: a checkpoint
//! trained for a few steps on a demo episode (the small preset: camera ext1), requests built
//! from that episode's recorded robot states and JPEG frames, chunks back on /policy/chunk.
//! The mechanics, not a success rate: the chunk's ids, shape and finiteness, the same request
//! giving the same chunk, a request missing its camera answered by nothing but the next good
//! one still served, and a checkpoint needing a camera the rig lacks refused at start.

use labrig_msgs::rig::{ActionChunk, PolicyObservation, PolicyRequest};
use labrig_msgs::sensor_msgs::CompressedImage;
use labrig_msgs::topics;
use labrig_runtime::RosConfig;
use labrig_runtime::ros::{Ros, RosSubscription};
use labrig_tests::{Proc, domain_for, labrig_bin, rt, workspace_bin};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant};

/// The committed demo episode (tests/fixtures/episodes/pick_place_seed7, recorded by `labrig
/// demo`) and a checkpoint of the small preset trained 3 steps on it.
fn episode_and_checkpoint(dir: &Path) -> (PathBuf, PathBuf) {
    workspace_bin("labrig-policies", "labrig-policies");
    let episode = labrig_tests::repo_root().join("tests/fixtures/episodes/pick_place_seed7");
    let preset = dir.join("p.toml");
    std::fs::write(&preset, "preset = \"small\"\n[train]\nbatch_size = 4\nval_fraction = 0.0\n").unwrap();
    let run = dir.join("run");
    let o = Command::new(labrig_bin())
        .args(["train", "--include-failures", "--steps", "3", "--threads", "1", "--target"])
        .arg(&episode)
        .arg("--preset")
        .arg(&preset)
        .arg("--out")
        .arg(&run)
        .output()
        .unwrap();
    assert!(o.status.success(), "train: {}", String::from_utf8_lossy(&o.stderr));
    (episode, run.join("checkpoints/step_3"))
}

/// Steps `at` of the episode as observations: robot state and camera ext1's recorded JPEG.
fn observations(episode: &Path, at: &[usize]) -> Vec<PolicyObservation> {
    let data = labrig_episode::read_episode(episode).unwrap();
    let buf = std::fs::read(&data.file).unwrap();
    let mut jpeg: BTreeMap<i64, CompressedImage> = BTreeMap::new();
    for m in mcap::MessageStream::new(&buf).unwrap() {
        let m = m.unwrap();
        if m.channel.topic == topics::camera_image("ext1") {
            let img: CompressedImage = labrig_msgs::decode(&m.data).unwrap();
            jpeg.insert(labrig_msgs::Nanos::from(img.header.stamp).0, img);
        }
    }
    at.iter()
        .map(|&k| {
            let s = &data.steps[k];
            let t = s.cameras.iter().find(|c| c.camera_id == "ext1").unwrap().capture_ns;
            let mut img = jpeg[&t].clone();
            img.header.frame_id = "ext1".into();
            PolicyObservation {
                header: s.header.clone(),
                step_index: s.step_index,
                robot_state: s.robot_state.clone(),
                images: vec![img],
                ..PolicyObservation::default()
            }
        })
        .collect()
}

/// The next JSON message on a string topic (`/policy/info`, `/policy/refused`); panics naming
/// `what` after `timeout`.
async fn next_json(
    sub: &RosSubscription<labrig_msgs::std_msgs::StringMsg>,
    timeout: Duration,
    what: &str,
) -> serde_json::Value {
    let until = Instant::now() + timeout;
    loop {
        if let Some(m) = sub.try_take().unwrap() {
            return serde_json::from_str(&m.msg.data).unwrap();
        }
        assert!(Instant::now() < until, "no {what}");
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
}

async fn next_chunk(chunks: &RosSubscription<ActionChunk>, timeout: Duration) -> Option<ActionChunk> {
    let until = Instant::now() + timeout;
    while Instant::now() < until {
        if let Some(c) = chunks.try_take().unwrap() {
            return Some(c.msg);
        }
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
    None
}

#[test]
fn the_policy_server_answers_requests_with_chunks() {
    let dir = tempfile::tempdir().unwrap();
    let (episode, ckpt) = episode_and_checkpoint(dir.path());
    let domain = domain_for("policy_server_node_serves");
    let server_bin = workspace_bin("labrig-policy", "labrig-policy-server");

    // A rig without ext1 refuses the checkpoint at start, naming the camera.
    let o = Command::new(&server_bin)
        .args([
            "run",
            "--threads",
            "1",
            "--set",
            "rig_cameras=[\"wrist\"]",
            "--domain-id",
            &domain.to_string(),
            "--checkpoint",
        ])
        .arg(&ckpt)
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(err.contains("the policy observes cameras [\"ext1\"], which the rig does not have"), "{err}");

    let mut cmd = Command::new(&server_bin);
    cmd.args(["run", "--threads", "1", "--domain-id", &domain.to_string(), "--checkpoint"]).arg(&ckpt);
    let _server = Proc::spawn("labrig-policy run", cmd);
    let obs = observations(&episode, &[10, 11]);
    rt().block_on(async move {
        let mut ros = Ros::new(&RosConfig { domain_id: domain, ..RosConfig::default() }, "policy_client").unwrap();
        let requests = ros.publisher_on(&topics::POLICY_REQUEST, 10).unwrap();
        let chunks = ros.subscription_on(&topics::POLICY_CHUNK, 10).unwrap();
        assert!(ros.wait_for_subscribers(topics::POLICY_REQUEST.name, 1, Duration::from_secs(60)).await, "no server");
        let request = |id: u64, observations: Vec<PolicyObservation>| PolicyRequest {
            request_id: id,
            episode_id: "policy-server-test".into(),
            observations,
            seed: 11,
            period_ns: 50_000_000,
            ..PolicyRequest::default()
        };
        // What it serves, latched for the loop. Like the rig's loop, the client asks only once
        // /policy/info has come and the server's chunk writer is known: a chunk published
        // before that writer has matched this reader is not delivered (volatile), which failed
        // this test once in CI on a loaded machine.
        let info = ros.subscription_on(&topics::POLICY_INFO, 1).unwrap();
        let refused = ros.subscription_on(&topics::POLICY_REFUSED, 10).unwrap();
        let served = next_json(&info, Duration::from_secs(60), "/policy/info").await;
        let until = Instant::now() + Duration::from_secs(60);
        while ros.publisher_count(topics::POLICY_CHUNK.name) < 1 {
            assert!(Instant::now() < until, "no /policy/chunk publisher");
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
        requests.publish(request(1, obs.clone())).unwrap();
        let a = next_chunk(&chunks, Duration::from_secs(60)).await.expect("a chunk");
        assert_eq!(a.policy_id, "run@3");
        assert_eq!((a.observation_step, a.first_step), (11, 11));
        // Tp 16 - To 2 + 1 actions from the newest observation's step on, 7 values each.
        assert_eq!((a.horizon, a.action_dim, a.actions.len()), (15, 7, 105));
        assert!(a.actions.iter().all(|v| v.is_finite()) && a.inference_ms > 0.0, "{a:?}");
        assert_eq!(a.header.stamp, obs[1].header.stamp, "stamped with the newest observation's time");
        let t0 = labrig_msgs::Nanos::from(obs[1].header.stamp).0;
        assert_eq!(a.request_id, 1);
        assert_eq!(a.times_ns, (0..15).map(|i| t0 + i * 50_000_000).collect::<Vec<_>>(), "one time per action");
        assert_eq!(served["policy_id"], "run@3");
        assert_eq!(served["cameras"], serde_json::json!(["ext1"]));
        assert_eq!(
            (served["n_obs_steps"].as_i64(), served["action_space"].as_str()),
            (Some(2), Some("eef_axis_angle"))
        );

        // The same request, the same chunk (the initial noise is seeded by the seed and step).
        requests.publish(request(2, obs.clone())).unwrap();
        let b = next_chunk(&chunks, Duration::from_secs(60)).await.expect("a second chunk");
        assert_eq!(b.request_id, 2);
        assert_eq!(a.actions, b.actions);

        // A request without the camera's image is refused, by id and naming the camera, on
        // /policy/refused (not left to a timeout); no chunk answers it; the server goes on.
        let mut blind = obs.clone();
        blind[1].images.clear();
        requests.publish(request(3, blind)).unwrap();
        let refusal = next_json(&refused, Duration::from_secs(60), "/policy/refused for a request without ext1").await;
        assert_eq!((refusal["request_id"].as_u64(), refusal["policy_id"].as_str()), (Some(3), Some("run@3")));
        assert!(refusal["error"].as_str().is_some_and(|e| e.contains("ext1")), "{refusal}");
        let one = vec![obs[1].clone()];
        requests.publish(request(4, one)).unwrap();
        let c = next_chunk(&chunks, Duration::from_secs(60)).await.expect("served after the bad request");
        assert_eq!(c.request_id, 4, "the chunk after the refusal answers request 4, not 3");
        assert_eq!(c.observation_step, 11);
        assert_ne!(c.actions, a.actions, "one observation (repeated) is another input than two");
        assert!(refused.try_take().unwrap().is_none(), "one refusal only");
    });
}
