//! The rig loop (`labrig-control run`) against the sim bridge in lockstep, with this test as
//! its action source on the scripted source's topics: valid actions move the arm; NaN and
//! stale actions are refused and the arm holds where it was commanded (recorded as holds in
//! the Steps); a target far outside the workspace is clipped to one step inside it; the step
//! budget fails the episode and the loop exits once the arm is back at DROID's reset pose.

use labrig_msgs::Nanos;
use labrig_msgs::rig::{ArmCommand, ArmCommandMode, EpisodeEvent, RobotState, Step};
use labrig_msgs::std_msgs::StringMsg;
use labrig_runtime::RosConfig;
use labrig_runtime::frames::NAMESPACE_ENV;
use labrig_runtime::ros::{Ros, qos};
use labrig_tests::{Proc, domain_for, rt, sim_bin, workspace_bin};
use std::collections::BTreeMap;
use std::process::Command;
use std::time::{Duration, Instant};

/// Ticks (step indices) whose action is bad: NaN; stamped half a second before the tick;
/// a target 2.5 m out (outside the workspace box, x <= 0.9 m).
const NAN_STEPS: std::ops::Range<u64> = 10..14;
const STALE_STEP: u64 = 18;
const FAR_STEPS: std::ops::Range<u64> = 22..25;
const MAX_STEPS: u64 = 30;

/// The sim bridge in lockstep without cameras (the loop's hardware in these tests).
fn lockstep_bridge(domain: u16, frames_ns: &str) -> Proc {
    let mut bridge = Command::new(sim_bin());
    bridge
        .args(["run", "--mode", "lockstep", "--no-cameras", "--domain-id", &domain.to_string()])
        .env(NAMESPACE_ENV, frames_ns);
    Proc::spawn("labrig-sim run", bridge)
}

/// A tick with one of the bad actions.
fn special(k: u64) -> bool {
    NAN_STEPS.contains(&k) || k == STALE_STEP || FAR_STEPS.contains(&k)
}

#[test]
fn the_loop_follows_good_actions_refuses_bad_ones_and_fails_over_budget() {
    let domain = domain_for("control_loop_vs_lockstep_bridge");
    let ns = format!("control_{}", std::process::id());
    let _bridge = lockstep_bridge(domain, &ns);
    let stats = tempfile::NamedTempFile::new().unwrap();
    let mut control = Command::new(workspace_bin("labrig-control", "labrig-control"));
    control
        .args(["run", "--clock", "sim", "--no-reseed", "--episodes", "1", "--max-steps", &MAX_STEPS.to_string()])
        .args(["--domain-id", &domain.to_string(), "--stats-out"])
        .arg(stats.path())
        .env(NAMESPACE_ENV, &ns);
    let mut control = Proc::spawn("labrig-control run", control);

    let steps: BTreeMap<u64, Step> = rt().block_on(async {
        let cfg = RosConfig { domain_id: domain, ..Default::default() };
        let mut ros = Ros::new(&cfg, "control_test_source").unwrap();
        let actions = ros.publisher::<ArmCommand>("/sim/expert/action", qos::reliable(10)).unwrap();
        let status = ros.publisher::<StringMsg>("/sim/expert/status", qos::reliable(10)).unwrap();
        let states = ros.subscription::<RobotState>("/arm/state", qos::reliable(100)).unwrap();
        let step_sub = ros.subscription::<Step>("/rig/step", qos::reliable(1000)).unwrap();
        let events = ros.subscription::<EpisodeEvent>("/rig/episode", qos::reliable(100)).unwrap();
        assert!(ros.wait_for_subscribers("/sim/expert/action", 1, Duration::from_secs(60)).await, "no control loop");
        let mut steps = BTreeMap::new();
        let mut last_stamp = i64::MIN;
        let mut episode_started = None;
        let deadline = Instant::now() + Duration::from_secs(120);
        // Act on every new state until the loop is done (bounded).
        while Instant::now() < deadline && control.wait_exit(Duration::ZERO).is_none() {
            while let Some(e) = events.try_take().unwrap() {
                if e.msg.kind == 0 {
                    episode_started = Some(Nanos::from(e.msg.header.stamp).0);
                }
            }
            while let Some(s) = step_sub.try_take().unwrap() {
                steps.insert(s.msg.step_index, s.msg);
            }
            let Some(s) = states.try_take().unwrap() else {
                tokio::time::sleep(Duration::from_micros(300)).await;
                continue;
            };
            let t = Nanos::from(s.msg.header.stamp).0;
            if t <= last_stamp {
                continue;
            }
            last_stamp = t;
            // The step this action will be recorded as (the loop starts at its first tick).
            let k = episode_started.map_or(0, |t0| ((t - t0) / 50_000_000) as u64);
            let mut target = s.msg.cartesian_position;
            target[1] += 0.004; // 4 mm a tick along +y
            if NAN_STEPS.contains(&k) {
                target[0] = f64::NAN;
            } else if FAR_STEPS.contains(&k) {
                target[0] = 2.5;
            }
            let mut cmd = ArmCommand {
                mode: ArmCommandMode::CartesianPosition as u8,
                cartesian_position: target,
                gripper_position: 0.0,
                seq: k,
                ..Default::default()
            };
            // The stale one: the loop waits for its tick's action (5 s), then refuses the old one.
            let stamp = if k == STALE_STEP && episode_started.is_some() { t - 500_000_000 } else { t };
            cmd.header.stamp = Nanos(stamp).into();
            actions.publish(cmd).unwrap();
            let verdict = serde_json::json!({ "stamp_ns": t, "done": false, "success": false });
            status.publish(StringMsg { data: verdict.to_string() }).unwrap();
        }
        tokio::time::sleep(Duration::from_millis(300)).await;
        while let Some(s) = step_sub.try_take().unwrap() {
            steps.insert(s.msg.step_index, s.msg);
        }
        steps
    });
    assert_eq!(control.wait_exit(Duration::from_secs(60)), Some(0), "the loop exits 0 after its episode");
    let summary: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(stats.path()).unwrap()).unwrap();
    // The budget ends the episode as a failure, and the arm went home before the loop exited.
    assert_eq!(summary["episodes"][0]["outcome"], "failure", "{summary}");
    assert_eq!(summary["episodes"][0]["steps"], MAX_STEPS, "{summary}");
    assert_eq!(steps.len() as u64, MAX_STEPS, "one Step per tick: {:?}", steps.keys().collect::<Vec<_>>());
    // The safety layer refused the NaN actions and nothing else; the stale one was held too.
    let nan = NAN_STEPS.end - NAN_STEPS.start;
    assert_eq!(summary["refused"], nan, "{summary}");
    assert_eq!(summary["held_ticks"], nan + 1, "{summary}");
    let joints = |k: u64| steps[&k].action.joint_position;
    let tcp = |k: u64| steps[&k].action.cartesian_position;
    for k in FAR_STEPS {
        let dx = tcp(k)[0] - tcp(k - 1)[0];
        assert!(dx > 0.01 && dx <= 0.075 + 1e-6, "step {k}: toward the far target by {dx} m (at most one 7.5 cm step)");
        assert!(tcp(k)[0] <= 0.9 + 1e-6, "step {k}: x {} is inside the workspace", tcp(k)[0]);
        assert!(steps[&k].movement_enabled);
    }
    for k in 1..MAX_STEPS {
        let refused = NAN_STEPS.contains(&k) || k == STALE_STEP;
        if refused {
            // Held where it was commanded the tick before: the same joint targets.
            assert_eq!(joints(k), joints(k - 1), "step {k}: a refused action must hold the arm");
            assert!(!steps[&k].movement_enabled, "step {k} is recorded as a hold");
        } else if k > 1 && !special(k) && !special(k - 1) {
            // A plain step after a plain step: the 4 mm beyond the measured TCP it asked for.
            let dy = tcp(k)[1] - steps[&k].robot_state.cartesian_position[1];
            assert!((dy - 0.004).abs() < 5e-4, "step {k}: the target is {dy} m along y from the TCP (4 mm asked)");
        }
        // Every recorded action is finite (a NaN never reaches a command or the record).
        assert!(joints(k).iter().all(|q| q.is_finite()), "step {k}");
        let a = &steps[&k].action;
        let values = a.cartesian_position.iter().chain(&a.cartesian_velocity).chain(&a.target_cartesian_position);
        assert!(values.chain(&a.joint_velocity).all(|v| v.is_finite()), "step {k}: {a:?}");
        assert!(steps[&k].robot_state.joint_positions.iter().all(|q| q.is_finite()));
    }
}

/// Operator events (`labrig episode ...` on /rig/request) drive the loop's episodes: one out
/// of place is refused, Start carries the instruction, Success ends the episode, the arm
/// (already home) is reported home, and the loop exits after its one episode.
#[test]
fn operator_events_start_and_end_episodes() {
    let domain = domain_for("control_loop_operator_events");
    let ns = format!("control_ops_{}", std::process::id());
    let _bridge = lockstep_bridge(domain, &ns);
    let mut control = Command::new(workspace_bin("labrig-control", "labrig-control"));
    control
        // Lockstep without cameras runs far faster than 20 Hz: no step budget in the way.
        .args(["run", "--source", "hold", "--clock", "sim", "--no-reseed", "--episodes", "1", "--max-steps", "1000000"])
        .args(["--domain-id", &domain.to_string()])
        .env(NAMESPACE_ENV, &ns);
    let mut control = Proc::spawn("labrig-control run", control);
    // `labrig episode` exits with the loop's verdict on its own request: 0 taken, 1 refused.
    let episode_says = |args: &[&str]| {
        let out = Command::new(labrig_tests::labrig_bin())
            .arg("episode")
            .args(args)
            .args(["--domain-id", &domain.to_string(), "--wait", "60"])
            .output()
            .unwrap();
        (out.status.code(), format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr)))
    };
    let episode = |args: &[&str]| {
        let (code, said) = episode_says(args);
        assert_eq!(code, Some(0), "labrig episode {args:?}: {said}");
        assert!(said.contains("the rig loop took"), "{said}");
    };
    let (events, steps) = rt().block_on(async {
        let cfg = RosConfig { domain_id: domain, ..Default::default() };
        let mut ros = Ros::new(&cfg, "control_ops_test").unwrap();
        let events = ros.subscription::<EpisodeEvent>("/rig/episode", qos::reliable(100)).unwrap();
        let step_sub = ros.subscription::<Step>("/rig/step", qos::reliable(1000)).unwrap();
        // The loop's writers matched before any event (so this test sees all of them).
        let deadline = Instant::now() + Duration::from_secs(60);
        while (ros.publisher_count("/rig/episode") == 0 || ros.publisher_count("/rig/step") == 0)
            && Instant::now() < deadline
        {
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
        let mut got = Vec::new();
        let mut steps = 0u64;
        let drain = |got: &mut Vec<EpisodeEvent>, steps: &mut u64| {
            while let Some(e) = events.try_take().unwrap() {
                got.push(e.msg);
            }
            while step_sub.try_take().unwrap().is_some() {
                *steps += 1;
            }
        };
        // Success while idle: the loop refuses it, says so and why, and publishes nothing.
        let (code, said) = episode_says(&["success"]);
        assert_eq!(code, Some(1), "an event out of place is refused: {said}");
        assert!(said.contains("the rig loop refused Success: "), "{said}");
        drain(&mut got, &mut steps);
        assert!(got.is_empty(), "a refused event publishes nothing: {got:?}");
        episode(&["start", "--note", "wipe the table"]);
        let deadline = Instant::now() + Duration::from_secs(60);
        while steps < 10 && Instant::now() < deadline {
            tokio::time::sleep(Duration::from_millis(20)).await;
            drain(&mut got, &mut steps);
        }
        assert!(steps >= 10, "steps while recording: {steps}");
        episode(&["success"]);
        let deadline = Instant::now() + Duration::from_secs(60);
        while got.len() < 3 && Instant::now() < deadline {
            tokio::time::sleep(Duration::from_millis(20)).await;
            drain(&mut got, &mut steps);
        }
        (got, steps)
    });
    let kinds: Vec<u8> = events.iter().map(|e| e.kind).collect();
    assert_eq!(kinds, vec![0, 2, 5], "Start, Success, Reset: {events:?}");
    assert_eq!(events[0].note, "wipe the table");
    assert!(!events[0].episode_id.is_empty() && events.iter().all(|e| e.episode_id == events[0].episode_id));
    assert!(steps >= 10);
    assert_eq!(control.wait_exit(Duration::from_secs(30)), Some(0), "the loop exits after its one episode");
}
