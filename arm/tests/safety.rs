//! The safety layer on the FR3's real kinematics (fr3.urdf from setup): refusals name the
//! field and limit, clips keep every command inside the limits, the watchdog trips on time.

use labrig_arm::ik::{Ik, IkConfig};
use labrig_arm::safety::{ArmView, Clip, Refusal, SafetyConfig, SafetyFilter, Watchdog};
use labrig_arm::{Fr3Kinematics, TcpOffset, urdf_path};
use labrig_msgs::Nanos;
use labrig_msgs::labrig_msgs::{ArmCommand, ArmCommandMode, DROID_RESET_POSE};
use proptest::prelude::*;

const NOW: i64 = 1_000_000_000_000;

fn filter() -> SafetyFilter {
    let kin = Fr3Kinematics::from_urdf_file(&urdf_path(None), TcpOffset::ROBOTIQ_2F85).unwrap();
    SafetyFilter::new(Ik::new(kin, IkConfig::default()), SafetyConfig::default()).unwrap()
}

fn at_reset() -> ArmView {
    ArmView { measured: DROID_RESET_POSE, commanded: DROID_RESET_POSE }
}

fn command(mode: ArmCommandMode) -> ArmCommand {
    let mut c = ArmCommand { mode: mode as u8, ..Default::default() };
    c.header.stamp.sec = (NOW / 1_000_000_000) as i32;
    c.joint_position = DROID_RESET_POSE;
    c
}

#[test]
fn nan_in_a_used_field_is_refused_by_name() {
    let f = filter();
    let mut c = command(ArmCommandMode::CartesianVelocity);
    c.cartesian_velocity[4] = f64::NAN;
    let err = f.filter(&c, &at_reset(), Nanos(NOW)).unwrap_err();
    assert!(matches!(err, Refusal::NonFinite { field: "cartesian_velocity", index: 4, .. }), "{err}");
    assert_eq!(err.to_string(), "cartesian_velocity[4] is NaN: not a finite number");
    let mut c = command(ArmCommandMode::JointPosition);
    c.joint_position[6] = f64::INFINITY;
    assert!(f.filter(&c, &at_reset(), Nanos(NOW)).unwrap_err().to_string().starts_with("joint_position[6] is inf"));
    let mut c = command(ArmCommandMode::JointPosition);
    c.gripper_position = f64::NAN;
    let err = f.filter(&c, &at_reset(), Nanos(NOW)).unwrap_err();
    assert!(matches!(err, Refusal::GripperNonFinite(v) if v.is_nan()), "{err}");
    // A field the mode does not use may hold anything.
    let mut c = command(ArmCommandMode::JointPosition);
    c.cartesian_velocity = [f64::NAN; 6];
    assert!(f.filter(&c, &at_reset(), Nanos(NOW)).is_ok());
}

#[test]
fn stale_commands_and_unknown_modes_are_refused() {
    let f = filter();
    let c = command(ArmCommandMode::JointPosition);
    assert!(f.filter(&c, &at_reset(), Nanos(NOW + 50_000_000)).is_ok());
    let err = f.filter(&c, &at_reset(), Nanos(NOW + 250_000_000)).unwrap_err();
    assert!(err.to_string().contains("stale command: stamped 250 ms"), "{err}");
    let mut c = command(ArmCommandMode::JointPosition);
    c.mode = 9;
    assert_eq!(f.filter(&c, &at_reset(), Nanos(NOW)).unwrap_err(), Refusal::UnknownMode(9));
}

#[test]
fn joint_targets_outside_the_limits_are_refused_inside_the_margin_clipped() {
    let f = filter();
    let mut c = command(ArmCommandMode::JointPosition);
    c.joint_position[3] = -3.1; // fr3_joint4 lower limit -3.0421
    let err = f.filter(&c, &at_reset(), Nanos(NOW)).unwrap_err().to_string();
    assert!(err.contains("fr3_joint4 target -3.1000 rad is outside its limits [-3.0421, -0.1518]"), "{err}");
    let mut view = at_reset();
    view.commanded[3] = -3.0;
    view.measured[3] = -3.0;
    c.joint_position[3] = -3.035; // inside the limit, inside the 0.02 margin
    let ok = f.filter(&c, &view, Nanos(NOW)).unwrap();
    assert!((ok.joints[3] - (-3.0421 + 0.02)).abs() < 1e-9, "{:?}", ok.joints);
    assert!(ok.clipped.iter().any(|c| matches!(c, Clip::JointMargin { joint: 3, .. })));
}

#[test]
fn too_fast_joint_steps_are_scaled_down() {
    let f = filter();
    let mut c = command(ArmCommandMode::JointPosition);
    c.joint_position[0] += 0.5;
    c.joint_position[1] += 0.05;
    let ok = f.filter(&c, &at_reset(), Nanos(NOW)).unwrap();
    let max = f.max_joint_step();
    assert!((ok.joints[0] - DROID_RESET_POSE[0] - max[0]).abs() < 1e-12, "{:?}", ok.joints);
    // Scaled as a whole: joint 2 moved by the same fraction.
    let scale = max[0] / 0.5;
    assert!((ok.joints[1] - DROID_RESET_POSE[1] - 0.05 * scale).abs() < 1e-12);
    assert!(ok.clipped.iter().any(|c| matches!(c, Clip::JointStep { joint: 0, .. })));
}

#[test]
fn cartesian_commands_stay_in_the_workspace_and_within_a_step() {
    let f = filter();
    let here = f.ik().kinematics().tcp_pose(&DROID_RESET_POSE);
    // Velocity beyond full scale: clipped, moves at most 7.5 cm.
    let mut c = command(ArmCommandMode::CartesianVelocity);
    c.cartesian_velocity = [5.0, 0.0, 0.0, 0.0, 0.0, 0.0];
    let ok = f.filter(&c, &at_reset(), Nanos(NOW)).unwrap();
    assert!(ok.clipped.iter().any(|c| matches!(c, Clip::VelocityRange { index: 0, .. })));
    let moved = (ok.tcp.translation.vector - here.translation.vector).norm();
    assert!(moved <= 0.075 + 1e-3, "moved {moved} m in one step");
    // An absolute pose 1 m below: one step down at most, and never under the workspace floor.
    let mut c = command(ArmCommandMode::CartesianPosition);
    let mut xyz_euler = labrig_arm::ik::xyz_euler(&here);
    xyz_euler[2] = -1.0;
    c.cartesian_position = xyz_euler;
    let ok = f.filter(&c, &at_reset(), Nanos(NOW)).unwrap();
    assert!(ok.clipped.iter().any(|c| matches!(c, Clip::PoseStep { .. })));
    assert!(ok.tcp.translation.z >= here.translation.z - 0.075 - 1e-3);
    // Walk it down for 20 steps: it stops at the floor (z >= 0.02).
    let mut view = at_reset();
    for _ in 0..20 {
        let ok = f.filter(&c, &view, Nanos(NOW)).unwrap();
        view = ArmView { measured: ok.joints, commanded: ok.joints };
        assert!(ok.tcp.translation.z >= 0.02 - 1e-3, "TCP at z = {}", ok.tcp.translation.z);
    }
}

#[test]
fn joint_targets_that_take_the_tcp_out_of_the_workspace_are_refused() {
    let f = filter();
    // Shoulder pitched far forward, elbow straight: the TCP goes under the table top.
    let mut q = DROID_RESET_POSE;
    q[1] = 1.7;
    q[3] = -0.2;
    let tcp = f.ik().kinematics().tcp_pose(&q).translation.vector;
    assert!(tcp.z < 0.02 || tcp.x > 0.9, "precondition: this pose leaves the box ({tcp:?})");
    let view = ArmView { measured: q, commanded: q };
    let mut c = command(ArmCommandMode::JointPosition);
    c.joint_position = q;
    let err = f.filter(&c, &view, Nanos(NOW)).unwrap_err();
    assert!(matches!(err, Refusal::OutsideWorkspace { .. }), "{err}");
    assert!(err.to_string().contains("outside the workspace"));
}

#[test]
fn the_watchdog_trips_after_two_periods_once() {
    let cfg = SafetyConfig::default();
    assert_eq!(cfg.watchdog_timeout(), Nanos(100_000_000));
    let mut w = Watchdog::new(cfg.watchdog_timeout());
    assert_eq!(w.check(Nanos(NOW)), None, "no command yet: nothing to hold");
    assert_eq!(w.deadline(), None);
    w.feed(Nanos(NOW));
    assert_eq!(w.deadline(), Some(Nanos(NOW + 100_000_000)));
    assert_eq!(w.check(Nanos(NOW + 99_000_000)), None);
    assert_eq!(w.check(Nanos(NOW + 100_000_000)), Some(Nanos(100_000_000)));
    assert!(w.tripped());
    assert_eq!(w.deadline(), None, "holding: no deadline until a fresh command");
    assert_eq!(w.check(Nanos(NOW + 150_000_000)), None, "reported once");
    w.feed(Nanos(NOW + 200_000_000));
    assert!(!w.tripped());
    assert_eq!(w.deadline(), Some(Nanos(NOW + 300_000_000)));
}

#[test]
fn bad_safety_configs_name_the_field() {
    let cfg =
        SafetyConfig { workspace_min_m: [0.5, -0.6, 0.02], workspace_max_m: [0.4, 0.6, 0.9], ..Default::default() };
    assert!(cfg.validate().unwrap_err().to_string().contains("safety.workspace_min_m[0]"));
    let cfg = SafetyConfig { velocity_fraction: 1.5, ..Default::default() };
    assert!(cfg.validate().unwrap_err().to_string().contains("safety.velocity_fraction"));
}

fn any_mode() -> impl Strategy<Value = ArmCommandMode> {
    prop_oneof![
        Just(ArmCommandMode::CartesianVelocity),
        Just(ArmCommandMode::CartesianPosition),
        Just(ArmCommandMode::CartesianPositionAxisAngle),
        Just(ArmCommandMode::JointVelocity),
        Just(ArmCommandMode::JointPosition),
    ]
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(400))]
    /// Whatever comes in, what comes out is inside the joint bounds, within one step of the
    /// last command, and (cartesian modes) inside the workspace.
    #[test]
    fn nothing_unsafe_comes_out(mode in any_mode(), v in prop::array::uniform7(-4.0f64..4.0), g in -1.0f64..2.0) {
        let f = filter();
        let mut c = command(mode);
        c.cartesian_velocity = std::array::from_fn(|i| v[i]);
        c.cartesian_position = std::array::from_fn(|i| v[i] * 0.5);
        c.joint_velocity = v;
        c.joint_position = std::array::from_fn(|i| DROID_RESET_POSE[i] + v[i] * 0.3);
        c.gripper_position = g;
        if let Ok(ok) = f.filter(&c, &at_reset(), Nanos(NOW)) {
            let bounds = f.ik().bounds();
            let max = f.max_joint_step();
            for i in 0..7 {
                prop_assert!(ok.joints[i] >= bounds[i][0] - 1e-12 && ok.joints[i] <= bounds[i][1] + 1e-12);
                prop_assert!((ok.joints[i] - DROID_RESET_POSE[i]).abs() <= max[i] + 1e-9);
            }
            prop_assert!((0.0..=1.0).contains(&ok.gripper));
            let cfg = f.config();
            for k in 0..3 {
                let p = ok.tcp.translation.vector[k];
                prop_assert!(p >= cfg.workspace_min_m[k] - 1e-3 && p <= cfg.workspace_max_m[k] + 1e-3);
            }
        }
    }
}
