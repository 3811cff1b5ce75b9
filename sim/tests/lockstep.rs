//! The simulated rig in lockstep: loads, holds DROID's reset pose, is deterministic, and never
//! lets a bad command reach the physics.

use labrig_msgs::Nanos;
use labrig_sim::rig::{DEFAULT_ASSETS, RESET_POSE};
use labrig_sim::{ArmTarget, SceneSpec, Sim, SimError};
use std::path::PathBuf;

fn assets() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("..").join(DEFAULT_ASSETS)
}

fn sim() -> Sim {
    Sim::new(&assets(), &SceneSpec::default_pick_place(), 0, Nanos::from_millis(50)).unwrap()
}

/// A scripted sequence: move joints 1 and 4, close the gripper half way through.
fn target(tick: u64) -> ArmTarget {
    let t = tick as f64 * 0.05;
    let mut joints = RESET_POSE;
    joints[0] = 0.3 * (0.5 * t).sin();
    joints[3] = RESET_POSE[3] + 0.2 * (0.3 * t).sin();
    ArmTarget { joints, gripper: if tick > 40 { 1.0 } else { 0.0 } }
}

#[test]
fn the_rig_holds_droids_reset_pose() {
    let mut s = sim();
    for _ in 0..40 {
        s.step(&ArmTarget { joints: RESET_POSE, gripper: 0.0 }).unwrap();
    }
    assert_eq!(s.time(), Nanos::from_millis(2000));
    let q = s.joint_positions();
    for (i, (a, b)) in q.iter().zip(RESET_POSE).enumerate() {
        assert!((a - b).abs() < 0.02, "joint {} at {a:.4}, target {b:.4}", i + 1);
    }
    assert!(s.gripper_position() < 0.05, "gripper should be open: {}", s.gripper_position());
}

#[test]
fn the_gripper_closes_on_command() {
    let mut s = sim();
    for _ in 0..30 {
        s.step(&ArmTarget { joints: RESET_POSE, gripper: 1.0 }).unwrap();
    }
    assert!(s.gripper_position() > 0.9, "gripper at {}", s.gripper_position());
}

#[test]
fn the_same_commands_give_bit_identical_trajectories() {
    let run = || {
        let mut s = sim();
        let mut traj = Vec::new();
        for tick in 0..80 {
            s.step(&target(tick)).unwrap();
            traj.extend(s.qpos().iter().map(|q| q.to_bits()));
        }
        traj
    };
    let (a, b) = (run(), run());
    assert_eq!(a.len(), b.len());
    assert!(a == b, "two lockstep runs diverged");
    // Guards the guard: the trajectory does move.
    assert_ne!(a[..22], a[a.len() - 22..]);
}

#[test]
fn nan_and_out_of_limit_targets_never_reach_the_physics() {
    let mut s = sim();
    s.step(&ArmTarget { joints: RESET_POSE, gripper: 0.0 }).unwrap();
    let before: Vec<u64> = s.qpos().iter().map(|q| q.to_bits()).collect();
    let mut nan = RESET_POSE;
    nan[2] = f64::NAN;
    let err = s.step(&ArmTarget { joints: nan, gripper: 0.0 }).unwrap_err();
    assert!(matches!(err, SimError::Refused { .. }) && err.to_string().contains("fr3_joint3 is NaN"), "{err}");
    let mut far = RESET_POSE;
    far[3] = 0.5; // joint 4 must stay below -0.1518 rad
    let err = s.step(&ArmTarget { joints: far, gripper: 0.0 }).unwrap_err();
    assert!(err.to_string().contains("fr3_joint4 = 0.5000 rad is outside its limits"), "{err}");
    let err = s.step(&ArmTarget { joints: RESET_POSE, gripper: 1.5 }).unwrap_err();
    assert!(err.to_string().contains("gripper command"), "{err}");
    let after: Vec<u64> = s.qpos().iter().map(|q| q.to_bits()).collect();
    assert_eq!(before, after, "a refused command changed the state");
    assert_eq!(s.time(), Nanos::from_millis(50), "a refused command advanced time");
}

#[test]
fn a_period_that_is_not_a_multiple_of_the_timestep_is_refused() {
    let err = Sim::new(&assets(), &SceneSpec::default_pick_place(), 0, Nanos(1_000_100)).unwrap_err();
    assert!(matches!(err, SimError::Period { .. }), "{err}");
}
