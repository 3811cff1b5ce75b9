//! The policy on the rig, end to end: `labrig rollout` with a committed tiny checkpoint
//! (tests/fixtures/policies/tiny_lowdim: the small_lowdim preset shrunk to a U-Net of 16/32,
//! 300 steps on 48 scripted demos) in the simulated rig, and the loop against a policy server
//! that is killed mid-episode or serves a policy the rig cannot execute. The mechanics, not a
//! success rate: chunks arrive, their rows execute in order, late rows are skipped and
//! counted, every step is recorded with the policy as its source, lockstep repeats itself,
//! a dead server holds the arm and fails the episode, a mismatch is refused by name.

use labrig_msgs::rig::{ActionChunk, EpisodeEvent, EpisodeEventKind, PolicyRequest, Step};
use labrig_msgs::topics;
use labrig_runtime::RosConfig;
use labrig_runtime::frames::NAMESPACE_ENV;
use labrig_runtime::ros::Ros;
use labrig_tests::{Proc, domain_for, labrig_bin, repo_root, rt, sim_bin, workspace_bin};
use serde_json::Value;
use std::ffi::OsString;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant};

const POLICY_ID: &str = "tiny_lowdim@300";

fn tiny() -> PathBuf {
    repo_root().join("tests/fixtures/policies/tiny_lowdim")
}

/// The committed pixels-and-proprioception checkpoint (`small_vision`, the README's recipe).
fn vision() -> PathBuf {
    repo_root().join("tests/fixtures/policies/small_vision")
}

/// `labrig rollout --json` with the tiny checkpoint; its report.
fn rollout(key: &str, out: &Path, extra: &[&str]) -> Value {
    rollout_of(&tiny(), key, out, extra)
}

/// `labrig rollout --json` with `policy`; its report.
fn rollout_of(policy: &Path, key: &str, out: &Path, extra: &[&str]) -> Value {
    let o = Command::new(labrig_bin())
        .args(["rollout", "--threads", "1", "--json", "--domain-id", &domain_for(key).to_string(), "--policy"])
        .arg(policy)
        .arg("--out")
        .arg(out)
        .args(extra)
        .env(NAMESPACE_ENV, format!("rollout_{key}_{}", std::process::id()))
        .current_dir(repo_root())
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&o.stdout);
    let report: Value = serde_json::from_str(stdout.lines().last().unwrap_or_default())
        .unwrap_or_else(|e| panic!("{e}: {stdout}\n{}", String::from_utf8_lossy(&o.stderr)));
    assert_eq!(o.status.code(), Some(0), "{report:#}\n{}", String::from_utf8_lossy(&o.stderr));
    report
}

fn steps(dir: &Value) -> (Vec<Step>, labrig_episode::metadata::EpisodeMetadata) {
    let data = labrig_episode::read_episode(Path::new(dir.as_str().expect("a recorded dir"))).unwrap();
    (data.steps, data.metadata.expect("DROID metadata"))
}

/// Each chunk's executed rows in step order: (chunk id, rows).
fn chunks(steps: &[Step]) -> Vec<(u64, Vec<u32>)> {
    let mut out: Vec<(u64, Vec<u32>)> = Vec::new();
    for s in steps.iter().filter(|s| s.chunk_id != 0) {
        match out.last_mut() {
            Some((id, rows)) if *id == s.chunk_id => rows.push(s.chunk_row),
            _ => out.push((s.chunk_id, vec![s.chunk_row])),
        }
    }
    out
}

#[test]
fn rollouts_execute_chunks_in_order_and_are_recorded_as_the_policys() {
    let dir = tempfile::tempdir().unwrap();
    let r = rollout("rollout_lockstep", dir.path(), &["--episodes", "2", "--max-steps", "40"]);
    let rollouts = r["rollouts"].as_array().unwrap();
    assert_eq!(rollouts.len(), 2, "{r:#}");
    assert_eq!(rollouts.iter().map(|o| o["seed"].as_u64().unwrap()).collect::<Vec<_>>(), [1000, 1001]);
    assert!(r["errors"].as_array().unwrap().is_empty(), "{r:#}");
    assert_eq!(r["held_steps"], 0, "lockstep waits for each chunk: no tick without an action");
    assert!(r["inference_ms_p50"].as_f64().unwrap() > 0.0);
    assert!(Path::new(r["summary_png"].as_str().unwrap()).is_file());
    for o in rollouts {
        let (steps, meta) = steps(&o["dir"]);
        assert_eq!(meta.policy.as_deref(), Some(POLICY_ID), "the checkpoint in the episode's metadata");
        assert_eq!(steps.len() as u64, o["steps"].as_u64().unwrap());
        assert!(steps.iter().all(|s| s.action_source == Step::SOURCE_POLICY));
        assert!(steps.iter().all(|s| s.movement_enabled && s.policy_id == POLICY_ID && s.chunk_id != 0));
        // A chunk's rows run in order from its first (nothing is late in lockstep), eight of
        // them (n_action_steps), then the next chunk takes over.
        let runs = chunks(&steps);
        assert!(runs.len() >= 2, "{runs:?}");
        for (k, (id, rows)) in runs.iter().enumerate() {
            assert_eq!(rows[0], 0, "chunk {id}: {rows:?}");
            assert!(rows.windows(2).all(|w| w[1] == w[0] + 1), "chunk {id} out of order: {rows:?}");
            if k + 1 < runs.len() {
                assert_eq!(rows.len(), 8, "chunk {id}: {rows:?}");
                assert!(runs[k + 1].0 > *id, "chunk ids increase: {runs:?}");
            }
        }
        assert_eq!(o["skipped_rows"], 0);
        assert_eq!(o["chunks"].as_u64().unwrap(), runs.len() as u64);
        if o["success"] == true {
            assert_eq!(o["reason"], "the sim's success predicate");
        } else {
            assert_eq!(o["steps"], 40);
            assert_eq!(o["reason"], "the step budget (40 steps) was spent");
        }
        assert!(Path::new(o["contact_sheet"].as_str().unwrap()).is_file());
    }
}

/// The committed vision checkpoint on the sim rig: it observes the wrist camera and ext1, so
/// every request carries their frames for every observation (none goes out without them, and
/// each is answered), its chunks execute from the first on, and the episode records it as
/// the policy. The mechanics, not a success rate.
#[test]
fn the_committed_vision_policy_runs_on_the_rig_from_its_cameras() {
    let dir = tempfile::tempdir().unwrap();
    let r = rollout_of(&vision(), "rollout_pixels", dir.path(), &["--episodes", "1", "--max-steps", "40"]);
    let rollouts = r["rollouts"].as_array().unwrap();
    assert_eq!(rollouts.len(), 1, "{r:#}");
    assert!(r["errors"].as_array().unwrap().is_empty(), "{r:#}");
    // The arm holds only on the first ticks, before both cameras' first frames are there (no
    // request goes out without every observation's frames: the server would refuse it).
    let held = r["held_steps"].as_u64().unwrap();
    assert!(held <= 3, "{r:#}");
    let source = &r["control"]["source"];
    let requests = source["requests"].as_u64().expect("the loop's policy stats");
    assert!(requests >= 3, "{source:#}");
    assert_eq!(source["requests_without_images"].as_u64().unwrap(), held, "{source:#}");
    assert_eq!(source["chunks"].as_u64().unwrap(), requests, "every request answered: {source:#}");
    let (steps, meta) = steps(&rollouts[0]["dir"]);
    let id = meta.policy.expect("the checkpoint in the metadata");
    assert!(id.starts_with("small_vision@"), "{id}");
    assert!(steps.iter().all(|s| s.action_source == Step::SOURCE_POLICY));
    assert!(steps[held as usize..].iter().all(|s| s.movement_enabled), "every step after the first chunk moves");
    // The frames the policy saw are recorded: each step it acted on names a wrist and an ext1
    // frame.
    assert!(steps.len() > held as usize + 10, "{} steps, {held} held", steps.len());
    for s in &steps[held as usize..] {
        for cam in ["wrist", "ext1"] {
            assert!(s.cameras.iter().any(|c| c.camera_id == cam), "step {} lacks {cam}", s.step_index);
        }
    }
}

#[test]
fn a_played_latency_skips_late_rows_and_lockstep_repeats_itself() {
    let (a, b) = (tempfile::tempdir().unwrap(), tempfile::tempdir().unwrap());
    let args = ["--episodes", "1", "--max-steps", "30", "--delay-steps", "3", "--first-seed", "7"];
    let first = rollout("rollout_delay", a.path(), &args);
    let second = rollout("rollout_delay", b.path(), &args);
    let (s1, _) = steps(&first["rollouts"][0]["dir"]);
    let (s2, _) = steps(&second["rollouts"][0]["dir"]);
    // A chunk asked for 3 ticks before it is due arrives with its first 3 rows in the past:
    // they are skipped and rows 3..11 run. The first one too: its 3 ticks hold the arm.
    let runs = chunks(&s1);
    assert!(runs.len() >= 3, "{runs:?}");
    for (id, rows) in &runs[..runs.len() - 1] {
        assert_eq!(rows, &(3..11).collect::<Vec<u32>>(), "chunk {id}");
    }
    assert_eq!(runs.last().unwrap().1[0], 3, "{runs:?}");
    let skipped = first["rollouts"][0]["skipped_rows"].as_u64().unwrap();
    assert_eq!(skipped, 3 * runs.len() as u64, "{first:#}");
    assert_eq!(first["rollouts"][0]["held_steps"], 3, "{first:#}");
    assert!(s1[..3].iter().all(|s| !s.movement_enabled) && s1[3].movement_enabled);
    // The same policy, seeds and latency: the same episode.
    assert_eq!(s1.len(), s2.len());
    for (x, y) in s1.iter().zip(&s2) {
        assert_eq!((x.chunk_id, x.chunk_row), (y.chunk_id, y.chunk_row));
        assert_eq!(x.action.joint_position, y.action.joint_position, "step {}", x.step_index);
        assert_eq!(x.robot_state.joint_positions, y.robot_state.joint_positions, "step {}", x.step_index);
    }
}

/// This process's own camera frames (tests run side by side).
fn frames_namespace() -> String {
    format!("rollout_faults_{}", std::process::id())
}

/// The rig by hand: the sim in lockstep, the recorder under `root`, the policy server.
fn rig(domain: u16, root: &Path) -> (Proc, Proc, Proc) {
    let d = domain.to_string();
    let ns = frames_namespace();
    let mut sim = Command::new(sim_bin());
    sim.args(["run", "--mode", "lockstep", "--seed", "1000", "--domain-id", &d]).env(NAMESPACE_ENV, &ns);
    let mut rec = Command::new(workspace_bin("labrig-recorder", "labrig-recorder"));
    rec.args(["run", "--domain-id", &d, "--root"]).arg(root).env(NAMESPACE_ENV, &ns);
    let mut pol = Command::new(workspace_bin("labrig-policy", "labrig-policy-server"));
    pol.args(["run", "--threads", "1", "--domain-id", &d, "--checkpoint"]).arg(tiny());
    (Proc::spawn("labrig-sim", sim), Proc::spawn("labrig-recorder", rec), Proc::spawn("labrig-policy", pol))
}

#[test]
fn a_killed_server_holds_the_arm_and_fails_the_episode_and_a_mismatch_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let domain = domain_for("rollout_server_faults");
    let (_sim, _rec, mut server) = rig(domain, dir.path());
    let control = workspace_bin("labrig-control", "labrig-control");
    let d = domain.to_string();
    let real = ["run", "--source", "policy", "--clock", "sim", "--episodes", "1", "--first-seed", "1000"];
    let base = [&real[..], &["--set", "policy.sim_rig=true"]].concat();

    // The tiny policy reads the sim scene's positions: a loop not configured as the sim rig
    // (a real rig's) refuses it at start, naming the input.
    let o = Command::new(&control).args(real).args(["--domain-id", &d]).output().unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(
        err.contains(&format!("the policy {POLICY_ID} observes [\"scene_state (the sim scene's object and receptacle positions)\"], which only the simulator has")),
        "{err}"
    );

    // A rig configured for another action space refuses the policy at start, by name.
    let o = Command::new(&control)
        .args(&base)
        .args(["--domain-id", &d, "--set", "policy.action_space=\"cartesian_velocity\""])
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(
        err.contains(&format!(
            "the policy {POLICY_ID} predicts \"eef_axis_angle\" actions; this rig is configured for \"cartesian_velocity\""
        )),
        "{err}"
    );

    // With the deadman (the real rig's config) and no Quest's grip, the policy's rows are
    // asked for and timed but the arm holds: every recorded step is a hold.
    let o = Command::new(&control)
        .env(NAMESPACE_ENV, frames_namespace())
        .args(&base)
        .args(["--max-steps", "20", "--set", "policy.deadman=true", "--domain-id", &d, "--json"])
        .output()
        .unwrap();
    assert_eq!(o.status.code(), Some(0), "{}", String::from_utf8_lossy(&o.stderr));
    let held: Value = serde_json::from_str(String::from_utf8_lossy(&o.stdout).lines().last().unwrap()).unwrap();
    assert_eq!(held["episodes"][0]["steps"], 20, "{held}");
    assert!(held["source"]["rows_executed"].as_u64().unwrap() >= 19, "the rows ran their course: {held}");
    let (no_grip, no_row) =
        (held["source"]["deadman_held"].as_u64().unwrap(), held["source"]["ticks_without_action"].as_u64().unwrap());
    assert_eq!(no_grip + no_row, 20, "every step held: without the grip, or before the first chunk: {held}");
    assert!(no_grip >= 19, "{held}");

    let mut cmd = Command::new(&control);
    cmd.env(NAMESPACE_ENV, frames_namespace());
    cmd.args(&base).args(["--max-steps", "400", "--set", "policy.server_timeout_s=1.0", "--domain-id", &d]);
    let mut ctl = Proc::spawn("labrig-control --source policy", cmd);
    let (steps, events) = rt().block_on(async {
        let mut ros = Ros::new(&RosConfig { domain_id: domain, ..RosConfig::default() }, "rollout_fault").unwrap();
        let step_sub = ros.subscription_on(&topics::RIG_STEP, 1000).unwrap();
        let event_sub = ros.subscription_on(&topics::RIG_EPISODE, 100).unwrap();
        let (mut steps, mut events): (Vec<Step>, Vec<EpisodeEvent>) = (Vec::new(), Vec::new());
        let until = Instant::now() + Duration::from_secs(180);
        let mut killed = false;
        while Instant::now() < until {
            while let Some(s) = step_sub.try_take().unwrap() {
                steps.push(s.msg);
            }
            while let Some(e) = event_sub.try_take().unwrap() {
                events.push(e.msg);
            }
            // Mid-rollout (three chunks in), the server dies.
            if !killed && steps.iter().filter(|s| s.chunk_id != 0).map(|s| s.chunk_id).max().unwrap_or(0) >= 3 {
                server.child.kill().unwrap();
                killed = true;
            }
            if events.iter().any(|e| e.kind().is_ok_and(|k| k != EpisodeEventKind::Start)) {
                break;
            }
            tokio::time::sleep(Duration::from_millis(5)).await;
        }
        assert!(killed, "the rollout never reached its third chunk ({} steps)", steps.len());
        (steps, events)
    });
    let end = events.iter().find(|e| e.kind().is_ok_and(|k| k != EpisodeEventKind::Start)).expect("the episode ended");
    assert_eq!(end.kind().unwrap(), EpisodeEventKind::Failure, "{end:?}");
    assert!(end.note.contains(&format!("the policy server ({POLICY_ID}) did not answer request")), "{}", end.note);
    // The arm followed the rows it had and held from the first tick without one: one period
    // after the last action's time, within the loop's staleness bound; a second (the server
    // timeout) after the unanswered request, the episode failed.
    let last = steps.iter().rposition(|s| s.movement_enabled).expect("actions executed");
    assert!(last + 1 < steps.len(), "no held step recorded after the server died");
    let t = |s: &Step| labrig_msgs::Nanos::from(s.header.stamp).0;
    let held_after_ms = (t(&steps[last + 1]) - t(&steps[last])) as f64 / 1e6;
    assert!(held_after_ms <= 100.0, "held {held_after_ms} ms after the last action");
    assert!(
        steps[last + 1..]
            .iter()
            .all(|s| !s.movement_enabled && s.chunk_id == 0 && s.action_source == Step::SOURCE_POLICY)
    );
    assert_eq!(ctl.wait_exit(Duration::from_secs(60)), Some(0), "the loop finishes its one episode");
    // The recorder filed both as failures: the deadman's, whose steps all held (no action of
    // the policy executed, so no policy in its metadata), and this one, the policy named.
    let mut recorded: Vec<PathBuf> = labrig_tests::episode_dirs(&dir.path().join("failure"));
    recorded.sort();
    assert_eq!(recorded.len(), 2, "{recorded:?}");
    let held = labrig_episode::read_episode(&recorded[0]).unwrap();
    assert!(held.steps.iter().all(|s| !s.movement_enabled && s.action_source == Step::SOURCE_POLICY));
    assert_eq!(held.metadata.unwrap().policy, None);
    let meta = labrig_episode::read_episode(&recorded[1]).unwrap().metadata.unwrap();
    assert_eq!((meta.success, meta.policy.as_deref()), (Some(false), Some(POLICY_ID)));
}

/// `labrig rollout --json` of the committed TorchScript module (one episode), its report and
/// its stderr (the rig's logs).
fn torchscript_rollout(key: &str, out: &Path, extra: &[&str]) -> (Value, String) {
    let fx = repo_root().join("tests/fixtures/policies/torchscript_tiny");
    let o = Command::new(labrig_bin())
        .args(["rollout", "--threads", "1", "--json", "--episodes", "1"])
        .args(extra)
        .args(["--domain-id", &domain_for(key).to_string(), "--torchscript"])
        .arg(fx.join("policy_scripted.pt"))
        .arg("--spec")
        .arg(fx.join("spec.toml"))
        .arg("--out")
        .arg(out)
        .env(NAMESPACE_ENV, format!("rollout_{key}_{}", std::process::id()))
        .current_dir(repo_root())
        .output()
        .unwrap();
    let (stdout, stderr) = (String::from_utf8_lossy(&o.stdout), String::from_utf8_lossy(&o.stderr).into_owned());
    let report: Value = serde_json::from_str(stdout.lines().last().unwrap_or_default())
        .unwrap_or_else(|e| panic!("{e}: {stdout}\n{stderr}"));
    assert_eq!(o.status.code(), Some(0), "{report:#}\n{stderr}");
    (report, stderr)
}

/// A TorchScript module exported by PyTorch (tests/fixtures/policies/torchscript_tiny, untrained:
/// slow DROID velocities) runs on the sim rig through `labrig rollout --torchscript`: the
/// episode is recorded, every step after the first few is the module's, named by its id, and
/// each step's recorded action is the row the server sent for it (watched on the wire): the
/// gripper target exactly, the joint target the pose its velocity asks for.
#[test]
fn a_torchscript_module_runs_on_the_sim_rig() {
    let dir = tempfile::tempdir().unwrap();
    let fx = repo_root().join("tests/fixtures/policies/torchscript_tiny");
    let args: Vec<OsString> = vec![
        "--threads".into(),
        "1".into(),
        "--episodes".into(),
        "1".into(),
        "--max-steps".into(),
        "30".into(),
        "--torchscript".into(),
        fx.join("policy_scripted.pt").into(),
        "--spec".into(),
        fx.join("spec.toml").into(),
    ];
    let (_, answers, report, _) = watched_rollout("torchscript_rollout", dir.path(), &args);
    let r = &report["rollouts"][0];
    assert_eq!(r["reason"], "the step budget (30 steps) was spent", "{report:#}");
    assert!(r["chunks"].as_u64().unwrap() >= 3, "{report:#}");
    let (steps, meta) = steps(&r["dir"]);
    assert_eq!(meta.policy.as_deref(), Some("torchscript:torchscript_tiny"));
    let by_module: Vec<&Step> =
        steps.iter().filter(|s| s.chunk_id > 0 && s.policy_id == "torchscript:torchscript_tiny").collect();
    // (The first steps hold until every camera's first frame is there.)
    assert!(by_module.len() >= 25, "{} of {} steps ran the module's rows", by_module.len(), steps.len());
    // The arm's joint target at each step is the module's velocity applied to the previous
    // target's pose (the safety filter's base while the arm keeps up), solved by the IK.
    use labrig_arm::ik::{apply_velocity, pose_error};
    use labrig_arm::kinematics::{Fr3Kinematics, TcpOffset};
    let kin = Fr3Kinematics::from_urdf_file(&labrig_arm::urdf_path(None), TcpOffset::ROBOTIQ_2F85).unwrap();
    let (mut worst_m, mut worst_rad, mut compared) = (0.0f64, 0.0f64, 0);
    for s in &by_module {
        let chunk = answers
            .iter()
            .find(|c| c.request_id == s.chunk_id)
            .unwrap_or_else(|| panic!("step {}: chunk {} was not on the wire", s.step_index, s.chunk_id));
        assert_eq!(chunk.action_dim, 7);
        let row = &chunk.actions[s.chunk_row as usize * 7..][..7];
        assert_eq!(s.action.target_gripper_position, row[6], "step {}: the gripper target", s.step_index);
        let Some(previous) = steps.iter().find(|p| p.step_index + 1 == s.step_index) else { continue };
        let v: [f64; 6] = std::array::from_fn(|i| row[i]);
        let want = apply_velocity(&kin.tcp_pose(&previous.action.joint_position), &v);
        let (dp, dr) = pose_error(&want, &kin.tcp_pose(&s.action.joint_position));
        worst_m = worst_m.max(dp.norm());
        worst_rad = worst_rad.max(dr.norm());
        compared += 1;
    }
    println!(
        "{compared} steps: each joint target is its served row's velocity from the last target, within {:.1e} m / {:.1e} rad",
        worst_m, worst_rad
    );
    assert!(compared >= 25, "{compared} steps compared");
    assert!(worst_m < 1e-4 && worst_rad < 1e-3, "a joint target off its row by {worst_m} m / {worst_rad} rad");
}

/// `labrig rollout --json` (`args` after the domain, `--out` added) watched on the wire:
/// every policy request and chunk it sent, its report and its stderr.
fn watched_rollout(key: &str, dir: &Path, args: &[OsString]) -> (Vec<PolicyRequest>, Vec<ActionChunk>, Value, String) {
    let domain = domain_for(key);
    rt().block_on(async {
        let mut ros = Ros::new(&RosConfig { domain_id: domain, ..RosConfig::default() }, "rollout_watch").unwrap();
        let request_sub = ros.subscription_on(&topics::POLICY_REQUEST, 1000).unwrap();
        let chunk_sub = ros.subscription_on(&topics::POLICY_CHUNK, 1000).unwrap();
        let (stdout, stderr) = (dir.join("stdout"), dir.join("stderr"));
        let mut child = Command::new(labrig_bin())
            .args(["rollout", "--json", "--domain-id", &domain.to_string()])
            .args(args)
            .arg("--out")
            .arg(dir.join("run"))
            .env(NAMESPACE_ENV, format!("rollout_{key}_{}", std::process::id()))
            .current_dir(repo_root())
            .stdout(std::fs::File::create(&stdout).unwrap())
            .stderr(std::fs::File::create(&stderr).unwrap())
            .spawn()
            .unwrap();
        let (mut requests, mut answers): (Vec<PolicyRequest>, Vec<ActionChunk>) = (Vec::new(), Vec::new());
        let until = Instant::now() + Duration::from_secs(300);
        let mut exited = None;
        let mut drain_until = None;
        while Instant::now() < until {
            while let Some(m) = request_sub.try_take().unwrap() {
                requests.push(m.msg);
            }
            while let Some(m) = chunk_sub.try_take().unwrap() {
                answers.push(m.msg);
            }
            if exited.is_none() {
                exited = child.try_wait().unwrap();
                if exited.is_some() {
                    drain_until = Some(Instant::now() + Duration::from_millis(500));
                }
            }
            if drain_until.is_some_and(|t| Instant::now() > t) {
                break;
            }
            tokio::time::sleep(Duration::from_millis(10)).await;
        }
        if exited.is_none() {
            let _ = child.kill();
        }
        let _ = child.wait();
        let err = std::fs::read_to_string(&stderr).unwrap_or_default();
        assert_eq!(exited.and_then(|s| s.code()), Some(0), "{err}");
        let out = std::fs::read_to_string(&stdout).unwrap();
        let report: Value = serde_json::from_str(out.lines().last().unwrap_or_default()).unwrap();
        (requests, answers, report, err)
    })
}

/// Real-time chunking in lockstep (`--blend rtc`, 2 ticks of played delay, 4 rows a chunk),
/// watched on the wire: each request but an episode's first carries the executing chunk's
/// rows from its observation's tick on, with d = 2; the answer's first 2 rows are those rows
/// exactly; the rows that run are each chunk's 2..6; and the run repeats itself bit for bit.
#[test]
fn real_time_chunking_sends_the_rows_run_meanwhile_and_repeats_itself() {
    let (a, b) = (tempfile::tempdir().unwrap(), tempfile::tempdir().unwrap());
    let key = "rollout_rtc";
    let args = ["--episodes", "1", "--max-steps", "30", "--first-seed", "7", "--blend", "rtc", "--delay-steps", "2"];
    let args = [&args[..], &["--execute-steps", "4", "--guidance-max-weight", "5"]].concat();
    let mut cmd = vec!["--threads".into(), "1".into(), "--policy".into(), tiny().into_os_string()];
    cmd.extend(args.iter().map(OsString::from));
    let (requests, answers, first, _) = watched_rollout(key, a.path(), &cmd);
    assert!(first["errors"].as_array().unwrap().is_empty(), "{first:#}");
    let (s1, _) = steps(&first["rollouts"][0]["dir"]);
    // The rows that ran: 2..6 of every chunk but the first (its 2 ticks held) and the last.
    let runs = chunks(&s1);
    assert!(runs.len() >= 5, "{runs:?}");
    for (id, rows) in &runs[..runs.len() - 1] {
        assert_eq!(rows, &(2..6).collect::<Vec<u32>>(), "chunk {id}");
    }
    // What went over the wire.
    let mut checked = 0;
    assert!(requests.len() >= runs.len(), "{} requests for {} chunks", requests.len(), runs.len());
    assert!(requests[0].prefix_actions.is_empty(), "an episode's first request has no chunk to continue");
    for r in &requests[1..] {
        let previous = answers.iter().filter(|c| c.request_id < r.request_id).max_by_key(|c| c.request_id).unwrap();
        let tick = labrig_msgs::Nanos::from(r.observations.last().unwrap().header.stamp).0;
        let from = previous.times_ns.iter().position(|&t| t == tick).expect("the observation's tick in the old chunk");
        assert_eq!(
            r.prefix_actions,
            previous.actions[from * 7..],
            "request {}: the old chunk's rows from its tick",
            r.request_id
        );
        assert_eq!(r.prefix_frozen_steps, 2, "request {}", r.request_id);
        assert_eq!(r.guidance_max_weight, 5.0);
        let Some(answer) = answers.iter().find(|c| c.request_id == r.request_id) else { continue };
        assert_eq!(answer.actions[..14], r.prefix_actions[..14], "request {}: the frozen rows, exactly", r.request_id);
        checked += 1;
    }
    assert!(checked >= 4, "{checked} requests checked against their chunks");
    // The same policy, seeds, latency and guidance: the same episode.
    let second = rollout_of(&tiny(), key, b.path(), &args);
    let (s2, _) = steps(&second["rollouts"][0]["dir"]);
    assert_eq!(s1.len(), s2.len());
    for (x, y) in s1.iter().zip(&s2) {
        assert_eq!((x.chunk_id, x.chunk_row), (y.chunk_id, y.chunk_row));
        assert_eq!(x.action.cartesian_position, y.action.cartesian_position, "step {}", x.step_index);
        assert_eq!(x.robot_state.joint_positions, y.robot_state.joint_positions, "step {}", x.step_index);
    }
}

/// Real-time chunking that the chunk cannot hold is refused at start by name: 8 ticks of
/// delay leave 7 of the tiny policy's 15 rows, fewer than the 8 a chunk must run.
#[test]
fn real_time_chunking_the_chunk_cannot_hold_is_refused_by_name() {
    let dir = tempfile::tempdir().unwrap();
    let key = "rollout_rtc_refused";
    let o = Command::new(labrig_bin())
        .args(["rollout", "--threads", "1", "--json", "--episodes", "1", "--domain-id", &domain_for(key).to_string()])
        .args(["--blend", "rtc", "--delay-steps", "8", "--policy"])
        .arg(tiny())
        .arg("--out")
        .arg(dir.path())
        .env(NAMESPACE_ENV, format!("rollout_{key}_{}", std::process::id()))
        .current_dir(repo_root())
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert_ne!(o.status.code(), Some(0), "{err}");
    assert!(
        err.contains("real-time chunking: the execution horizon s = 8 (policy.execute_steps, or the policy's n_action_steps) must lie in [d, rows - d] = [8, 7] for d = 8 ticks of delay and a chunk of 15 rows"),
        "{err}"
    );
}

/// A TorchScript module cannot be guided: with `--blend rtc` it gets real-time chunking's
/// schedule (requests carry the rows run meanwhile, d = 2) and its chunks come unguided, which
/// the server's log says.
#[test]
fn a_torchscript_module_gets_real_time_chunkings_schedule_unguided_and_the_log_says_so() {
    let dir = tempfile::tempdir().unwrap();
    let rtc = ["--max-steps", "20", "--blend", "rtc", "--delay-steps", "2", "--execute-steps", "4"];
    let (report, stderr) = torchscript_rollout("torchscript_rtc", dir.path(), &rtc);
    assert!(
        stderr.contains(
            "real-time chunking asked for, but a TorchScript module cannot be guided: its chunks come on the loop's schedule without the guidance"
        ),
        "{stderr}"
    );
    let source = &report["control"]["source"];
    assert!(source["prefix_requests"].as_u64().unwrap() >= 2, "{source:#}");
    assert_eq!(source["frozen_steps"], 2, "{source:#}");
    assert!(source["rows_executed"].as_u64().unwrap() >= 10, "{source:#}");
}

/// The shipped checkpoints' claims, pinned: lockstep rollouts repeat themselves bit for bit,
/// so two named seeds per checkpoint must keep their outcome and their step count exactly. A
/// change to inference, the observation pipeline, the loop or the sim that moves the shipped
/// policies fails here (measured with libtorch 2.13 on this machine's CPU kind, one thread).
#[test]
fn the_shipped_checkpoints_repeat_their_rollouts_exactly() {
    let fixtures = repo_root().join("tests/fixtures/policies");
    for (key, checkpoint, scene, first, want) in [
        ("pinned_pick_place", "small_vision_recover", "pick_place", "1001", [(1001, 83), (1002, 80)]),
        ("pinned_drawer", "drawer_recover", "drawer_open", "1000", [(1000, 170), (1001, 103)]),
    ] {
        let dir = tempfile::tempdir().unwrap();
        let args = ["--scene", scene, "--first-seed", first, "--episodes", "2"];
        let r = rollout_of(&fixtures.join(checkpoint), key, dir.path(), &args);
        let got: Vec<(u64, bool, u64)> = r["rollouts"]
            .as_array()
            .unwrap()
            .iter()
            .map(|o| (o["seed"].as_u64().unwrap(), o["success"] == true, o["steps"].as_u64().unwrap()))
            .collect();
        let want: Vec<(u64, bool, u64)> = want.iter().map(|&(seed, steps)| (seed, true, steps)).collect();
        assert_eq!(got, want, "{checkpoint} on {scene}: (seed, success, steps)");
    }
}
