//! The simulated hardware driven command by command and period by period, in memory: no ROS,
//! no processes (the bridge's process-level behaviour is in tests/tests/sim_bridge.rs).

use labrig_msgs::Nanos;
use labrig_msgs::rig::{ArmCommand, ArmCommandMode};
use labrig_sim::Sim;
use labrig_sim_bridge::hardware::SimHardware;

const PERIOD: Nanos = Nanos::from_millis(50);

fn sim(seed: u64) -> Sim {
    let (spec, assets) = labrig_sim::resolve_scene(None, None).unwrap();
    Sim::new(&assets, &spec, seed, PERIOD).unwrap()
}

fn hardware(arm_sets_gripper: bool) -> SimHardware {
    SimHardware::new(sim(0), labrig_sim::safety_filter(PERIOD, None).unwrap(), arm_sets_gripper)
}

fn joints(hw: &SimHardware, dq1: f64) -> ArmCommand {
    let mut q = hw.sim().joint_targets();
    q[0] += dq1;
    ArmCommand { mode: ArmCommandMode::JointPosition as u8, joint_position: q, ..Default::default() }
}

/// Commands `cmd` at the sim's current time and steps one period.
fn tick(hw: &mut SimHardware, cmd: Option<&ArmCommand>) {
    if let Some(c) = cmd {
        let now = hw.sim().time();
        hw.arm_command(c, now);
    }
    hw.step().unwrap();
}

#[test]
fn a_good_command_is_followed_for_one_period() {
    let mut hw = hardware(true);
    let (t0, q0) = (hw.sim().time(), hw.sim().joint_positions()[0]);
    let cmd = joints(&hw, 0.03);
    tick(&mut hw, Some(&cmd));
    let s = hw.state();
    assert!(s.last_ok && s.fault.is_empty(), "{s:?}");
    assert_eq!((s.commands, s.refused), (1, 0));
    assert_eq!(hw.sim().time(), t0 + PERIOD);
    let moved = hw.sim().joint_positions()[0] - q0;
    assert!(moved > 0.005, "joint 1 moved {moved} rad toward a target 0.03 rad away");
}

#[test]
fn bad_commands_are_refused_counted_and_the_arm_holds() {
    let mut hw = hardware(true);
    let q0 = hw.sim().joint_positions();
    let mut nan = joints(&hw, 0.03);
    nan.joint_position[2] = f64::NAN;
    tick(&mut hw, Some(&nan));
    let s = hw.state();
    assert!(!s.last_ok && s.fault.starts_with("refused arm command"), "{s:?}");
    assert_eq!(s.refused, 1);
    let drift = hw.sim().joint_positions().iter().zip(q0).map(|(a, b)| (a - b).abs()).fold(0.0, f64::max);
    assert!(drift < 1e-3, "the arm held: {drift} rad");
    hw.gripper_command(1.5);
    assert_eq!(hw.state().refused, 2);
    assert!(hw.state().fault.contains("outside 0..1"));
    hw.gripper_command(0.8);
    assert_eq!(hw.state().gripper, 0.8);
    // A good command clears the fault.
    let cmd = joints(&hw, 0.01);
    tick(&mut hw, Some(&cmd));
    assert!(hw.state().last_ok && hw.state().fault.is_empty());
}

#[test]
fn the_watchdog_holds_the_arm_once_commands_stop_and_a_fresh_one_releases_it() {
    let mut hw = hardware(true);
    let cmd = joints(&hw, 0.02);
    tick(&mut hw, Some(&cmd));
    // Two periods of silence is the default timeout (100 ms at 20 Hz).
    tick(&mut hw, None);
    assert!(!hw.state().holding, "one silent period is not yet a trip");
    tick(&mut hw, None);
    let s = hw.state();
    assert!(s.holding && s.fault.starts_with("watchdog: no arm command for 100.0 ms"), "{s:?}");
    let held = hw.sim().joint_targets();
    tick(&mut hw, None);
    assert_eq!(hw.sim().joint_targets(), held, "holding where it stopped");
    let cmd = joints(&hw, 0.01);
    tick(&mut hw, Some(&cmd));
    assert!(!hw.state().holding && hw.state().fault.is_empty());
}

#[test]
fn behind_a_hardware_prefix_only_joint_targets_are_taken() {
    let mut hw = hardware(false);
    let cmd = ArmCommand { mode: ArmCommandMode::CartesianPosition as u8, ..Default::default() };
    tick(&mut hw, Some(&cmd));
    assert!(hw.state().fault.contains("joint position targets only"), "{:?}", hw.state());
    let cmd = joints(&hw, 0.02);
    tick(&mut hw, Some(&cmd));
    assert!(hw.state().last_ok);
}

#[test]
fn a_new_scene_starts_the_hardware_over_and_keeps_the_counts() {
    let mut hw = hardware(true);
    let mut nan = joints(&hw, 0.0);
    nan.joint_position[0] = f64::NAN;
    tick(&mut hw, Some(&nan));
    let cmd = joints(&hw, 0.02);
    tick(&mut hw, Some(&cmd));
    hw.replace_scene(sim(1));
    let s = hw.state();
    assert_eq!((s.commands, s.refused), (2, 1));
    assert!(s.arm.is_none() && s.fault.is_empty() && !s.holding && s.last_ok);
    assert_eq!(hw.sim().scene().seed, 1);
    // The new scene's watchdog starts unfed: silence does not trip it.
    for _ in 0..4 {
        tick(&mut hw, None);
    }
    assert!(!hw.state().holding);
}
