//! Operator corrections (human-gated DAgger) end to end, with the committed tiny policy
//! (tests/fixtures/policies/tiny_lowdim, a sim-only policy) in the lockstep sim rig:
//!
//! - `policy.takeover = "teleop"`: this test plays the Quest node (`/teleop/state` with the
//!   grip, `/teleop/action`), takes over mid-rollout and lets go. The recorded steps go policy
//!   -> teleop -> policy; the first policy step after the hand-back runs a fresh chunk (a
//!   request newer than any before the takeover, from its first row); the loop's stats, the
//!   episode metadata and `labrig inspect` count one takeover and the same operator steps.
//! - `labrig rollout --intervene expert`: the sim's scripted expert takes over by the loop's
//!   rule from a policy that stalls, and hands back; the same accounting.

use labrig_msgs::rig::{ArmCommand, ArmCommandMode, Step, TeleopState};
use labrig_msgs::topics;
use labrig_runtime::RosConfig;
use labrig_runtime::frames::NAMESPACE_ENV;
use labrig_runtime::ros::Ros;
use labrig_tests::{Proc, domain_for, labrig_bin, repo_root, rt, sim_bin, workspace_bin};
use serde_json::Value;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

fn tiny() -> PathBuf {
    repo_root().join("tests/fixtures/policies/tiny_lowdim")
}

/// The runs of consecutive steps by the same source: (source, first step index, steps).
fn runs(steps: &[Step]) -> Vec<(u8, u64, u64)> {
    let mut out: Vec<(u8, u64, u64)> = Vec::new();
    for s in steps {
        match out.last_mut() {
            Some((src, _, n)) if *src == s.action_source => *n += 1,
            _ => out.push((s.action_source, s.step_index, 1)),
        }
    }
    out
}

/// After every run of operator steps that the policy resumes from, its first step executes row
/// 0 of a chunk newer than any the policy ran before the takeover (its stale chunk and the
/// answer to a request in flight are dropped; it asked afresh at the hand-back tick).
fn assert_fresh_chunk_after_each_hand_back(steps: &[Step], operator: u8) {
    let mut handed_back = 0;
    for w in steps.windows(2) {
        if w[0].action_source == operator && w[1].action_source == Step::SOURCE_POLICY {
            let k = w[1].step_index as usize;
            let before = steps[..k].iter().filter(|s| s.action_source == Step::SOURCE_POLICY).map(|s| s.chunk_id).max();
            let resumed = &steps[k];
            assert!(resumed.movement_enabled, "lockstep waits for the fresh chunk: step {k} acts");
            assert!(
                Some(resumed.chunk_id) > before,
                "step {k}: chunk {} after the hand-back, the policy ran up to chunk {before:?} before it",
                resumed.chunk_id
            );
            assert_eq!(resumed.chunk_row, 0, "step {k}: the fresh chunk runs from its first row");
            handed_back += 1;
        }
    }
    assert!(handed_back >= 1, "no hand-back in {:?}", runs(steps));
}

/// `labrig inspect --json` of an episode directory.
fn inspect(dir: &Path) -> Value {
    let o = Command::new(labrig_bin()).arg("inspect").arg(dir).arg("--json").output().unwrap();
    let stdout = String::from_utf8_lossy(&o.stdout);
    serde_json::from_str(stdout.lines().last().unwrap_or_default())
        .unwrap_or_else(|e| panic!("{e}: {stdout}\n{}", String::from_utf8_lossy(&o.stderr)))
}

#[test]
fn a_quest_operator_takes_over_mid_rollout_and_the_policy_resumes_with_a_fresh_chunk() {
    let dir = tempfile::tempdir().unwrap();
    let domain = domain_for("takeover_grip");
    let d = domain.to_string();
    let ns = format!("takeover_grip_{}", std::process::id());
    let mut sim = Command::new(sim_bin());
    sim.args(["run", "--mode", "lockstep", "--seed", "1000", "--domain-id", &d]).env(NAMESPACE_ENV, &ns);
    let mut rec = Command::new(workspace_bin("labrig-recorder", "labrig-recorder"));
    rec.args(["run", "--domain-id", &d, "--root"]).arg(dir.path()).env(NAMESPACE_ENV, &ns);
    let mut pol = Command::new(workspace_bin("labrig-policy", "labrig-policy-server"));
    pol.args(["run", "--threads", "1", "--domain-id", &d, "--checkpoint"]).arg(tiny());
    let (_sim, _rec, _pol) =
        (Proc::spawn("labrig-sim", sim), Proc::spawn("labrig-recorder", rec), Proc::spawn("labrig-policy", pol));

    // The grip cannot be both the deadman and the takeover: refused by key, before anything.
    let control = workspace_bin("labrig-control", "labrig-control");
    let base = ["run", "--source", "policy", "--clock", "sim", "--episodes", "1", "--first-seed", "1000"];
    let takeover = ["--set", "policy.sim_rig=true", "--set", "policy.takeover=\"teleop\""];
    let o = Command::new(&control)
        .args(base)
        .args(takeover)
        .args(["--set", "policy.deadman=true", "--domain-id", &d])
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert_ne!(o.status.code(), Some(0), "{err}");
    assert!(err.contains("policy.takeover") && err.contains("cannot mean both"), "{err}");

    let mut cmd = Command::new(&control);
    cmd.env(NAMESPACE_ENV, &ns)
        .args(base)
        .args(takeover)
        .args(["--max-steps", "90", "--domain-id", &d, "--json"])
        .stdout(Stdio::piped());
    let ctl = cmd.spawn().unwrap();
    let (live, acting_seen) = rt().block_on(async {
        let mut ros = Ros::new(&RosConfig { domain_id: domain, ..RosConfig::default() }, "takeover_quest").unwrap();
        let state_pub = ros.publisher_on(&topics::TELEOP_STATE, 10).unwrap();
        let action_pub = ros.publisher_on(&topics::TELEOP_ACTION, 10).unwrap();
        let step_sub = ros.subscription_on(&topics::RIG_STEP, 1000).unwrap();
        let status_sub = ros.subscription_on(&topics::CONTROL_STATUS, 10).unwrap();
        let mut steps: Vec<Step> = Vec::new();
        let mut acting_seen = Vec::new();
        // Grip: held from 16 policy steps on (two chunks in), let go after 12 teleop steps.
        let mut grip = false;
        let mut released = false;
        let until = Instant::now() + Duration::from_secs(240);
        while Instant::now() < until {
            while let Some(s) = step_sub.try_take().unwrap() {
                steps.push(s.msg);
            }
            while let Some(s) = status_sub.try_take().unwrap() {
                let v: Value = serde_json::from_str(&s.msg.data).unwrap_or_default();
                if let Some(a) = v["acting"].as_str()
                    && acting_seen.last().is_none_or(|l: &String| l != a)
                {
                    acting_seen.push(a.to_owned());
                }
            }
            let policy = steps.iter().filter(|s| s.action_source == Step::SOURCE_POLICY).count();
            let teleop = steps.iter().filter(|s| s.action_source == Step::SOURCE_TELEOP).count();
            if !grip && !released && policy >= 16 {
                grip = true;
            }
            if grip && teleop >= 12 {
                grip = false;
                released = true;
            }
            // The Quest node's pace: a state and an action per reading (~72 Hz; faster here so
            // the loop's 35 ms age limit never bites a lockstep tick).
            let mut state = TeleopState { controller_connected: true, movement_enabled: grip, ..Default::default() };
            state.hand = "right".into();
            state.grip = if grip { 1.0 } else { 0.0 };
            let _ = state_pub.publish(state);
            let action = ArmCommand {
                mode: ArmCommandMode::CartesianVelocity as u8,
                // Slowly up: the operator's correction.
                cartesian_velocity: [0.0, 0.0, 0.2, 0.0, 0.0, 0.0],
                gripper_position: 0.0,
                ..Default::default()
            };
            let _ = action_pub.publish(action);
            if steps.len() >= 90 || (released && policy >= 50) {
                break;
            }
            tokio::time::sleep(Duration::from_millis(5)).await;
        }
        // Until the episode ends (the loop stops publishing steps), the grip stays released.
        let quiet = Instant::now() + Duration::from_secs(120);
        let mut last_step = Instant::now();
        while Instant::now() < quiet && last_step.elapsed() < Duration::from_secs(5) {
            while let Some(s) = step_sub.try_take().unwrap() {
                steps.push(s.msg);
                last_step = Instant::now();
            }
            let state = TeleopState { controller_connected: true, movement_enabled: false, ..Default::default() };
            let _ = state_pub.publish(state);
            tokio::time::sleep(Duration::from_millis(10)).await;
        }
        (steps, acting_seen)
    });
    let out = ctl.wait_with_output().unwrap();
    assert_eq!(out.status.code(), Some(0), "the loop finishes its one episode");
    let stats: Value = serde_json::from_str(String::from_utf8_lossy(&out.stdout).lines().last().unwrap()).unwrap();

    // The recorded episode: policy -> teleop -> policy, the teleop run where the grip was.
    let recorded = labrig_tests::episode_dirs(dir.path());
    assert_eq!(recorded.len(), 1, "{recorded:?}");
    let ep = labrig_episode::read_episode(&recorded[0]).unwrap();
    let steps = ep.steps;
    let r = runs(&steps);
    let shape: Vec<u8> = r.iter().map(|(s, _, _)| *s).collect();
    assert_eq!(shape, [Step::SOURCE_POLICY, Step::SOURCE_TELEOP, Step::SOURCE_POLICY], "{r:?}");
    let (_, start, len) = r[1];
    assert!(start >= 16 && len >= 12, "{r:?}");
    assert!(
        steps[start as usize..][..len as usize].iter().all(|s| s.chunk_id == 0),
        "the operator's steps run no chunk"
    );
    assert_fresh_chunk_after_each_hand_back(&steps, Step::SOURCE_TELEOP);
    assert!(live.iter().any(|s| s.action_source == Step::SOURCE_TELEOP), "the takeover was seen live");

    // Counted alike by the loop (its stats and /control/status), the recorder and inspect.
    assert_eq!((stats["takeovers"].as_u64(), stats["operator_steps"].as_u64()), (Some(1), Some(len)), "{stats}");
    assert_eq!(stats["episodes"][0]["takeovers"], 1, "{stats}");
    // Who acts goes out the tick it changes (the periodic status may not come between).
    assert!(acting_seen.windows(2).any(|w| w == ["operator", "policy"]), "/control/status: {acting_seen:?}");
    let meta = ep.metadata.unwrap();
    assert_eq!((meta.takeovers, meta.operator_steps), (Some(1), Some(len)));
    let i = inspect(&recorded[0]);
    let src = &i["sources"];
    assert_eq!(src["takeovers"], 1, "{i:#}");
    assert_eq!(src["operator_steps"].as_u64(), Some(len), "{i:#}");
    assert_eq!(src["policy_steps"].as_u64(), Some(steps.len() as u64 - len), "{i:#}");
    assert_eq!(src["takeover_segments"][0]["start_step"].as_u64(), Some(start), "{i:#}");
    assert_eq!(src["takeover_segments"][0]["steps"].as_u64(), Some(len), "{i:#}");
    assert_eq!(src["takeover_segments"][0]["source"], "teleop", "{i:#}");
}

#[test]
fn the_scripted_expert_takes_over_a_stalled_policy_and_hands_back() {
    let dir = tempfile::tempdir().unwrap();
    let key = "takeover_expert";
    let o = Command::new(labrig_bin())
        .args(["rollout", "--threads", "1", "--json", "--domain-id", &domain_for("takeover_expert").to_string()])
        .arg("--policy")
        .arg(tiny())
        .arg("--out")
        .arg(dir.path())
        .args(["--episodes", "1", "--max-steps", "200", "--intervene", "expert", "--takeover-ticks", "20"])
        .env(NAMESPACE_ENV, format!("rollout_{key}_{}", std::process::id()))
        .current_dir(repo_root())
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&o.stdout);
    let report: Value = serde_json::from_str(stdout.lines().last().unwrap_or_default())
        .unwrap_or_else(|e| panic!("{e}: {stdout}\n{}", String::from_utf8_lossy(&o.stderr)));
    assert_eq!(o.status.code(), Some(0), "{report:#}\n{}", String::from_utf8_lossy(&o.stderr));
    assert_eq!(report["intervene"], "expert", "{report:#}");
    let rollout = &report["rollouts"][0];
    let ep = labrig_episode::read_episode(Path::new(rollout["dir"].as_str().unwrap())).unwrap();
    let steps = ep.steps;
    let r = runs(&steps);
    let segments: Vec<&(u8, u64, u64)> = r.iter().filter(|(s, _, _)| *s == Step::SOURCE_SCRIPTED).collect();
    assert!(!segments.is_empty(), "no expert takeover: {r:?}");
    assert!(r.iter().all(|(s, _, _)| *s == Step::SOURCE_SCRIPTED || *s == Step::SOURCE_POLICY), "{r:?}");
    assert!(segments.len() <= 3, "at most three takeovers: {r:?}");
    // Handed back after 20 ticks (a run that ends the episode may be cut short).
    for (k, (src, _, n)) in r.iter().enumerate() {
        if *src == Step::SOURCE_SCRIPTED {
            assert!(*n == 20 || (k + 1 == r.len() && *n <= 20), "{r:?}");
        }
    }
    assert_fresh_chunk_after_each_hand_back(&steps, Step::SOURCE_SCRIPTED);
    let operator: u64 = segments.iter().map(|(_, _, n)| n).sum();
    assert_eq!(rollout["takeovers"].as_u64(), Some(segments.len() as u64), "{report:#}");
    assert_eq!(rollout["operator_steps"].as_u64(), Some(operator), "{report:#}");
    assert_eq!(report["takeovers"], rollout["takeovers"]);
    let meta = ep.metadata.unwrap();
    assert_eq!((meta.takeovers, meta.operator_steps), (Some(segments.len() as u64), Some(operator)));
    let json: Value =
        serde_json::from_str(&std::fs::read_to_string(dir.path().join("rollouts.json")).unwrap()).unwrap();
    assert_eq!(json["rollouts"][0]["takeovers"], rollout["takeovers"]);
    assert_eq!(json["control"]["takeovers"], rollout["takeovers"], "the loop counted the same");
}
