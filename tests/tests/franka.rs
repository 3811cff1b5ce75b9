//! The franka node's fci backend against franka-sim (PyPI franka-sim 1.1.7, speaking the
//! libfranka FCI protocol on 127.0.0.1): the node (`labrig-franka run`, its own process)
//! moves the simulated FR3 along commanded paths at 20 Hz in joint position and cartesian
//! velocity modes, its watchdog holds the arm 100 ms after the last command, and a reflex
//! (a stalled host: the FCI's communication constraints) and a killed simulator are reported
//! in /arm/state as faults while the node keeps running.

use labrig_msgs::Nanos;
use labrig_msgs::rig::{ArmCommand, ArmCommandMode, RobotState};
use labrig_msgs::std_srvs::{Trigger, TriggerRequest};
use labrig_runtime::RosConfig;
use labrig_runtime::ros::{Ros, RosPublisher, RosSubscription, qos};
use labrig_tests::{Proc, domain_for, franka_sim, rt, workspace_bin};
use std::process::Command;
use std::time::{Duration, Instant};

fn franka_node(domain: u16, port: u16, config: Option<&std::path::Path>) -> Proc {
    let mut cmd = Command::new(workspace_bin("labrig-franka", "labrig-franka"));
    if let Some(c) = config {
        cmd.args(["run", "--config"]).arg(c).args([
            "--robot-ip",
            &format!("127.0.0.1:{port}"),
            "--no-realtime",
            "--domain-id",
            &domain.to_string(),
        ]);
        return Proc::spawn("labrig-franka run", cmd);
    }
    cmd.args([
        "run",
        "--robot-ip",
        &format!("127.0.0.1:{port}"),
        "--no-realtime",
        "--domain-id",
        &domain.to_string(),
        "--connect-timeout-s",
        "60",
    ]);
    Proc::spawn("labrig-franka run", cmd)
}

fn now() -> Nanos {
    Nanos(std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).unwrap().as_nanos() as i64)
}

fn stamped(mut c: ArmCommand, seq: u64) -> ArmCommand {
    c.header.stamp = now().into();
    c.seq = seq;
    c
}

fn joints(q: [f64; 7]) -> ArmCommand {
    ArmCommand { mode: ArmCommandMode::JointPosition as u8, joint_position: q, ..ArmCommand::default() }
}

fn velocity(v: [f64; 6]) -> ArmCommand {
    ArmCommand { mode: ArmCommandMode::CartesianVelocity as u8, cartesian_velocity: v, ..ArmCommand::default() }
}

struct Rig {
    ros: Ros,
    cmd: RosPublisher<ArmCommand>,
    state: RosSubscription<RobotState>,
    seq: u64,
}

impl Rig {
    async fn new(domain: u16) -> Rig {
        let mut ros = Ros::new(&RosConfig { domain_id: domain, ..RosConfig::default() }, "franka_test").unwrap();
        let cmd = ros.publisher::<ArmCommand>("/arm/command", qos::reliable(100)).unwrap();
        let state = ros.subscription::<RobotState>("/arm/state", qos::reliable(1000)).unwrap();
        assert!(
            ros.wait_for_subscribers("/arm/command", 1, Duration::from_secs(90)).await,
            "the franka node did not come up"
        );
        Rig { ros, cmd, state, seq: 0 }
    }

    fn drain(&self, into: &mut Vec<RobotState>) {
        while let Some(s) = self.state.try_take().unwrap() {
            into.push(s.msg);
        }
    }

    /// The first state satisfying `pred` within `secs`.
    async fn wait(&self, secs: u64, what: &str, pred: impl Fn(&RobotState) -> bool) -> RobotState {
        let deadline = Instant::now() + Duration::from_secs(secs);
        let mut last = None;
        while Instant::now() < deadline {
            while let Some(s) = self.state.try_take().unwrap() {
                if pred(&s.msg) {
                    return s.msg;
                }
                last = Some(s.msg);
            }
            tokio::time::sleep(Duration::from_millis(5)).await;
        }
        panic!("no /arm/state with {what} within {secs} s; last: {last:?}");
    }

    /// Sends `commands` at 20 Hz, collecting states.
    /// Holds `target` at 20 Hz for at least 1 s and until every joint is within `tol` rad of it
    /// (at most `max_s`); returns the worst joint's error at the end. franka-sim steps its
    /// physics once per loop cycle, and its 1 kHz loop ran at 410-890 Hz in a suite here, so the
    /// arm's time runs slower than the wall's: "settles" is checked in the arm's time, not 1 s
    /// of wall time.
    async fn hold(&mut self, target: [f64; 7], tol: f64, max_s: f64, states: &mut Vec<RobotState>) -> f64 {
        let err = |s: &RobotState| (0..7).map(|i| (s.joint_positions[i] - target[i]).abs()).fold(0.0, f64::max);
        for k in 0..(max_s * 20.0) as usize {
            self.play([joints(target)], states).await;
            if k >= 19 && states.last().is_some_and(|s| err(s) < tol) {
                break;
            }
        }
        states.last().map_or(f64::INFINITY, err)
    }

    async fn play(&mut self, commands: impl IntoIterator<Item = ArmCommand>, states: &mut Vec<RobotState>) {
        let mut next = tokio::time::Instant::now();
        for c in commands {
            self.seq += 1;
            self.cmd.publish(stamped(c, self.seq)).unwrap();
            next += Duration::from_millis(50);
            tokio::time::sleep_until(next).await;
            self.drain(states);
        }
    }
}

#[test]
fn the_fci_backend_moves_franka_sims_fr3_along_commanded_paths() {
    let domain = domain_for("the_fci_backend_moves_franka_sims_fr3_along_commanded_paths");
    let port = 20_000 + domain;
    // (No --enforce-motion-limits: on a loaded 2-core CI machine franka-rs's 1 kHz loop,
    // without a realtime kernel, can miss cycles, which the enforced limits turn into
    // discontinuity reflexes; this test is about tracking, the next one about reflexes.)
    let _sim = franka_sim(port, &[]);
    let _node = franka_node(domain, port, None);
    rt().block_on(async move {
        let mut rig = Rig::new(domain).await;
        let start = rig.wait(90, "a reading", |_| true).await;
        let q0 = start.joint_positions;

        // Joint position mode: joint 1 through a 0.25 rad sine (2 s period), 3 s of commands.
        let target = |k: usize| {
            let mut q = q0;
            q[0] += 0.25 * (2.0 * std::f64::consts::PI * 0.5 * k as f64 * 0.05).sin();
            q
        };
        let mut states = Vec::new();
        rig.play((1..=60).map(|k| joints(target(k))), &mut states).await;
        let q1: Vec<f64> = states.iter().map(|s| s.joint_positions[0] - q0[0]).collect();
        let (lo, hi) = q1.iter().fold((f64::MAX, f64::MIN), |(a, b), &v| (a.min(v), b.max(v)));
        assert!(hi > 0.2 && lo < -0.2, "joint 1 swept {lo:.3}..{hi:.3} rad of the +-0.25 rad sine");
        assert!(hi < 0.27 && lo > -0.27, "overshoot: {lo:.3}..{hi:.3}");
        // Then the last target, held: the arm settles on it.
        let end = target(60);
        let err = rig.hold(end, 0.005, 4.0, &mut states).await;
        assert!(err < 0.005, "the arm rests {err:.4} rad from a target held for up to 4 s");
        assert!(states.iter().all(|s| s.mode != RobotState::MODE_FAULT), "a fault on a safe path");
        let latency: Vec<f64> = states.iter().map(|s| s.prev_controller_latency_ms).collect();
        eprintln!(
            "joint sine: swept {lo:.3}..{hi:.3} rad, settled {err:.5} rad from the target, \
             command-to-backend latency max {:.3} ms",
            latency.iter().cloned().fold(0.0, f64::max)
        );

        // To DROID's reset pose over 3 s, held for 1 s.
        let reset = labrig_msgs::rig::DROID_RESET_POSE;
        let here = rig.wait(10, "a reading", |_| true).await.joint_positions;
        let mut states = Vec::new();
        let way = |k: usize| -> [f64; 7] { std::array::from_fn(|i| here[i] + (reset[i] - here[i]) * (k as f64 / 60.0)) };
        rig.play((1..=60).map(|k| joints(way(k))), &mut states).await;
        let err = rig.hold(reset, 0.005, 4.0, &mut states).await;
        assert!(err < 0.005, "{err} rad from DROID's reset pose");

        // Cartesian velocity mode: DROID's +y at 0.1 (7.5 mm per step) for 1 s = 15 cm.
        let before = states.last().unwrap().cartesian_position;
        let mut states = Vec::new();
        rig.play((0..20).map(|_| velocity([0.0, 0.1, 0.0, 0.0, 0.0, 0.0])), &mut states).await;
        // Silence: the watchdog holds the arm 100 ms after the last command.
        let held = rig.wait(5, "the watchdog's hold", |s| s.mode == RobotState::MODE_STOPPED).await;
        let silence = labrig_tests::watchdog_silence_ms(&held.fault);
        // Never before 100 ms: exact, the watchdog trips only on a silence of at least its
        // limit. After it, by how much is the node's thread waking on a wall-clock timer beside
        // franka-sim's 1 kHz loop: under 2 ms on a quiet machine, more when a shared 2-core
        // machine is busy; 25 ms of slack keeps this a check that the hold comes at its
        // deadline, not a timing figure (the node's latencies are `labrig bench franka`'s).
        assert!((100.0..125.0).contains(&silence), "held after {silence} ms");
        // The arm comes to rest where the hold found it (the trajectory generator brakes it):
        // no joint moves more than 0.5 mrad over 200 ms. (Positions, not franka-sim's velocity
        // readings: its joint 7 reports ~0.08 rad/s at rest.)
        let t_hold = Nanos::from(held.header.stamp).0;
        let mut rest = vec![held.clone()];
        let deadline = Instant::now() + Duration::from_secs(5);
        let after = loop {
            assert!(Instant::now() < deadline, "the arm did not come to rest within 5 s of the hold");
            rig.drain(&mut rest);
            let last = rest.last().unwrap();
            let t_last = Nanos::from(last.header.stamp).0;
            let earlier = rest.iter().rev().find(|s| Nanos::from(s.header.stamp).0 <= t_last - 200_000_000);
            if let Some(e) = earlier
                && (0..7).all(|i| (e.joint_positions[i] - last.joint_positions[i]).abs() < 5e-4)
            {
                break e.clone();
            }
            tokio::time::sleep(Duration::from_millis(10)).await;
        };
        assert_eq!(after.mode, RobotState::MODE_STOPPED);
        let to_rest_ms = (Nanos::from(after.header.stamp).0 - t_hold) as f64 / 1e6;
        let dy = after.cartesian_position[1] - before[1];
        let drift = (after.cartesian_position[0] - before[0]).hypot(after.cartesian_position[2] - before[2]);
        // Never farther than commanded, and on the line.
        assert!(dy > 0.07 && dy < 0.155, "the TCP moved {dy:.4} m along y for 15 cm of commands");
        assert!(drift < 0.01, "the TCP drifted {drift:.4} m off the y line: {before:?} -> {:?}", after.cartesian_position);
        eprintln!(
            "cartesian +y: {dy:.4} m of 0.15 m commanded, off-line drift {drift:.4} m, watchdog hold after {silence:.1} ms, \
             at rest {to_rest_ms:.0} ms later"
        );
    });
}

#[test]
fn a_reflex_and_a_killed_franka_sim_are_reported_as_faults() {
    let domain = domain_for("a_reflex_and_a_killed_franka_sim_are_reported_as_faults");
    let port = 20_000 + domain;
    let mut sim = franka_sim(port, &["--enforce-motion-limits"]);
    // The default workspace box keeps the TCP in front of the robot, which also keeps the arm
    // out of its own way; an operator's wider box lets a folding path through, and then the
    // FR3's own self-collision reflex stops it.
    let dir = tempfile::tempdir().unwrap();
    let config = dir.path().join("franka.toml");
    std::fs::write(&config, "[safety]\nworkspace_min_m = [-0.9, -0.9, -0.3]\n").unwrap();
    let mut node = franka_node(domain, port, Some(&config));
    rt().block_on(async move {
        let mut rig = Rig::new(domain).await;
        let start = rig.wait(90, "a reading", |_| true).await.joint_positions;
        let recover = rig.ros.client::<Trigger>("/arm/recover", qos::reliable(10)).unwrap();
        recover.wait_for_service(&rig.ros, Duration::from_secs(30)).await.unwrap();
        // Without a realtime kernel franka-sim may abort a motion with a *_discontinuity
        // reflex when its 1 kHz Python loop misses a cycle (a loaded machine): a real stop,
        // recovered from as an operator would, and the motion goes on from where it stopped.
        // Counted and printed; more than MISSED_CYCLES_ALLOWED in the whole test fails it.
        let mut missed = 0;
        let reflex_of =
            |f: &str| f.split("reflex! [\"").nth(1).and_then(|r| r.split('"').next()).unwrap_or_default().to_owned();
        // Fold the elbow and wrist onto the upper arm over 4 s, until the FR3's own
        // self-collision reflex stops it.
        let fold = [0.0, 0.5, 0.0, -3.0, 0.0, 0.6, 0.785];
        let mut from = start;
        let (fault, mut states) = loop {
            let way =
                |k: usize| -> [f64; 7] { std::array::from_fn(|i| from[i] + (fold[i] - from[i]) * (k as f64 / 80.0)) };
            let mut states = Vec::new();
            rig.play((1..=80).map(|k| joints(way(k))), &mut states).await;
            let fault = states
                .iter()
                .find(|s| s.mode == RobotState::MODE_FAULT)
                .cloned()
                .unwrap_or_else(|| panic!("no reflex on the folding path; last: {:?}", states.last()));
            assert!(fault.fault.contains("motion aborted by reflex! [\""), "{}", fault.fault);
            let reflex = reflex_of(&fault.fault);
            if reflex == "self_collision_avoidance_violation" {
                break (fault, states);
            }
            assert!(reflex.ends_with("_discontinuity"), "unexpected reflex {reflex:?}: {}", fault.fault);
            missed += 1;
            assert!(missed <= MISSED_CYCLES_ALLOWED, "{missed} missed-cycle stops: {}", fault.fault);
            eprintln!("folding stopped by a missed cycle, recovering and going on: {}", fault.fault);
            let r = recover.call(TriggerRequest::default(), Duration::from_secs(30)).await.unwrap();
            assert!(r.success, "{}", r.message);
            from =
                rig.wait(5, "a reading after the recovery", |s| s.mode != RobotState::MODE_FAULT).await.joint_positions;
        };
        let reflex = reflex_of(&fault.fault);
        assert!(fault.fault.ends_with("call /arm/recover"), "{}", fault.fault);
        // Later commands are refused with the reason, until a recovery.
        let last = states.last().unwrap();
        assert!(last.fault.starts_with("refused arm command"), "{}", last.fault);
        assert!(last.fault.contains(&reflex), "the first reason is kept: {}", last.fault);
        // Back out the way it came (missed cycles as above: recovered, counted).
        let at = loop {
            let r = recover.call(TriggerRequest::default(), Duration::from_secs(30)).await.unwrap();
            assert!(r.success, "{}", r.message);
            let here =
                rig.wait(5, "a reading after the recovery", |s| s.mode != RobotState::MODE_FAULT).await.joint_positions;
            // Over 6 s: a missed cycle's jump in the commanded path grows with the speed, so a
            // slow path trips fewer discontinuity reflexes.
            let back =
                |k: usize| -> [f64; 7] { std::array::from_fn(|i| here[i] + (start[i] - here[i]) * (k as f64 / 120.0)) };
            let mut states = Vec::new();
            rig.play((1..=120).map(|k| joints(back(k))).chain((0..10).map(|_| joints(start))), &mut states).await;
            let last = states.last().unwrap().clone();
            // (Later commands are refused naming that reflex, so the last state may say either.)
            let missed_cycle = last.mode == RobotState::MODE_FAULT
                && last.fault.split("reflex! [").nth(1).is_some_and(|r| r.contains("_discontinuity"));
            if !missed_cycle {
                break last;
            }
            missed += 1;
            assert!(missed <= MISSED_CYCLES_ALLOWED, "{missed} missed-cycle stops: {}", last.fault);
            eprintln!("backing out stopped by a missed cycle, recovering again: {}", last.fault);
        };
        println!("missed-cycle stops recovered from: {missed} (at most {MISSED_CYCLES_ALLOWED})");
        assert_ne!(at.mode, RobotState::MODE_FAULT, "{}", at.fault);
        let err = (0..7).map(|i| (at.joint_positions[i] - start[i]).abs()).fold(0.0, f64::max);
        assert!(err < 0.01, "after the recovery the arm is {err:.4} rad from where it started");
        eprintln!("reflex reported as: {}", fault.fault);

        // The simulator dies: a fault naming the lost arm; the node lives on.
        let _ = sim.child.kill();
        let _ = sim.child.wait();
        let lost = rig.wait(15, "the lost arm", |s| s.mode == RobotState::MODE_FAULT).await;
        assert!(lost.fault.ends_with("call /arm/recover"), "{}", lost.fault);
        eprintln!("killed simulator reported as: {}", lost.fault);
        rig.play((0..5).map(|_| joints(start)), &mut states).await;
        assert!(node.child.try_wait().unwrap().is_none(), "the node exited when its simulator died");
        // /arm/recover cannot bring a dead simulator back, and says so.
        let r = recover.call(TriggerRequest::default(), Duration::from_secs(30)).await.unwrap();
        assert!(!r.success && r.message.contains("cannot start the arm"), "{}", r.message);
        // A clean stop on SIGTERM.
        let pid = node.child.id().to_string();
        assert!(Command::new("kill").args(["-TERM", &pid]).status().unwrap().success());
        assert_eq!(node.wait_exit(Duration::from_secs(20)), Some(0), "the node did not stop cleanly");
    });
}

/// The missed-cycle stops (franka-sim's 1 kHz loop on a loaded machine without a realtime
/// kernel) the reflex test recovers from before it fails: CI has seen four in one run.
const MISSED_CYCLES_ALLOWED: usize = 5;

#[test]
fn the_franka_bench_reports_command_latencies() {
    let domain = domain_for("the_franka_bench_reports_command_latencies");
    let out = Command::new(labrig_tests::labrig_bin())
        .args(["bench", "franka", "--commands", "40", "--json"])
        .args(["--port", &(20_000 + domain).to_string(), "--domain-id", &domain.to_string()])
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(v["echoed"], 40, "every command's target echoed: {v}");
    for series in ["node_command_to_backend", "round_trip_publish_to_echo"] {
        let s = &v[series];
        assert!(s["n"].as_u64().unwrap() >= 35, "{series}: {s}");
        let (p50, max) = (s["p50_ms"].as_f64().unwrap(), s["max_ms"].as_f64().unwrap());
        assert!(p50 > 0.0 && p50 <= max, "{series}: {s}");
    }
    assert!(
        v["node_command_to_backend"]["p50_ms"].as_f64() < v["round_trip_publish_to_echo"]["p50_ms"].as_f64(),
        "the node's share is part of the round trip: {v}"
    );
}

/// The franka node's `sim` backend: the node in front of the sim bridge (realtime, arm and
/// gripper topics under /sim). Joint commands on /arm/command move the simulated FR3 through
/// the node; a command stamped off the sim clock is refused as stale; the gripper the bridge
/// holds is never touched by the arm's relay; the node's own watchdog holds the arm.
#[test]
fn the_sim_backend_drives_the_sim_bridge_through_the_node() {
    let domain = domain_for("the_sim_backend_drives_the_sim_bridge_through_the_node");
    let _bridge = labrig_tests::sim_hardware(domain);
    let _node = labrig_tests::sim_backend_node("labrig-franka", domain);
    rt().block_on(async move {
        let mut rig = Rig::new(domain).await;
        let clock = rig.ros.subscription::<labrig_msgs::rosgraph_msgs::Clock>("/clock", qos::reliable(10)).unwrap();
        let gripper_cmd =
            rig.ros.publisher::<labrig_msgs::rig::GripperCommand>("/sim/gripper/command", qos::reliable(10)).unwrap();
        let gripper_state =
            rig.ros.subscription::<labrig_msgs::rig::GripperState>("/sim/gripper/state", qos::reliable(100)).unwrap();
        let start = rig.wait(60, "a reading", |_| true).await.joint_positions;
        // The gripper closes (as the gripper node would ask the bridge).
        assert!(rig.ros.wait_for_subscribers("/sim/gripper/command", 1, Duration::from_secs(30)).await);
        gripper_cmd.publish(labrig_msgs::rig::GripperCommand { position: 1.0, ..Default::default() }).unwrap();

        // Commands stamped on the sim clock, joint 1 +0.3 rad over 1 s.
        let mut sim_now = Nanos::ZERO;
        let mut states = Vec::new();
        for k in 1..=20u64 {
            while let Some(c) = clock.try_take().unwrap() {
                sim_now = Nanos::from(c.msg.clock);
            }
            let mut q = start;
            q[0] += 0.015 * k as f64;
            let mut c = joints(q);
            c.header.stamp = sim_now.into();
            c.seq = k;
            rig.cmd.publish(c).unwrap();
            tokio::time::sleep(Duration::from_millis(50)).await;
            rig.drain(&mut states);
        }
        assert!(states.iter().all(|s| s.mode != RobotState::MODE_FAULT), "{:?}", states.last());
        // The node's watchdog (on sim time, checked each state tick) holds the arm.
        let held = rig.wait(5, "the node's watchdog", |s| s.mode == RobotState::MODE_STOPPED).await;
        let silence = labrig_tests::watchdog_silence_ms(&held.fault);
        // Sim time between /clock messages is interpolated (at most one period); the check
        // runs on the 50 Hz state tick (20 ms), and a loaded machine delays that tick and the
        // /clock it interpolates from by a few ms more (CI: 125.8 ms).
        assert!((100.0..=140.0).contains(&silence), "held after {silence} ms of sim time");
        let moved = held.joint_positions[0] - start[0];
        assert!(moved > 0.2 && moved < 0.31, "joint 1 moved {moved:.3} rad of 0.3 commanded");
        let mut g = None;
        while let Some(s) = gripper_state.try_take().unwrap() {
            g = Some(s.msg);
        }
        let g = g.expect("the bridge's gripper state");
        assert_eq!(g.requested_position, 1.0, "the arm's commands changed the gripper request: {g:?}");

        // A command stamped on the wall clock is seconds off sim time: refused as stale.
        rig.play([joints(start)], &mut states).await;
        let stale = rig.wait(5, "a stale refusal", |s| s.fault.contains("stale command")).await;
        assert!(!stale.prev_command_successful);
        assert_eq!(stale.mode, RobotState::MODE_STOPPED, "the hold stands");
        let after = rig
            .wait(5, "a later state", |s| {
                Nanos::from(s.header.stamp).0 > Nanos::from(stale.header.stamp).0 + 300_000_000
            })
            .await;
        let drift = (0..7).map(|i| (after.joint_positions[i] - held.joint_positions[i]).abs()).fold(0.0, f64::max);
        // Executed, the command would take joint 1 back 0.3 rad; what remains is the hold's
        // settling from the motion it stopped (CI under load: 2.1 mrad).
        assert!(drift < 0.01, "the refused command moved the arm {drift:.4} rad");
        eprintln!("sim backend: joint 1 moved {moved:.3} rad; {}; {}", held.fault, stale.fault);
    });
}
