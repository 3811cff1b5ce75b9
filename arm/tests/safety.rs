//! The safety layer on the FR3's real kinematics (fr3.urdf from setup): refusals name the
//! field and limit, clips keep every command inside the limits, the watchdog trips on time.

use labrig_arm::ik::{Ik, IkConfig};
use labrig_arm::safety::{ArmView, Clip, Refusal, SafetyConfig, SafetyFilter, Watchdog};
use labrig_arm::{Fr3Kinematics, TcpOffset, urdf_path};
use labrig_msgs::Nanos;
use labrig_msgs::rig::{ArmCommand, ArmCommandMode, DROID_RESET_POSE};
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

/// What a generated command carries besides its values.
#[derive(Debug, Clone, Copy)]
enum Fault {
    None,
    /// This index of the field the mode uses is NaN (or infinite).
    NonFinite(usize, f64),
    GripperNan,
    /// Stamped this long before now (or after, as a clock ahead): past `max_command_age_s`.
    Stale(f64, bool),
}

fn fault() -> impl Strategy<Value = Fault> {
    prop_oneof![
        8 => Just(Fault::None),
        1 => (0usize..7, prop::sample::select(vec![f64::NAN, f64::INFINITY, f64::NEG_INFINITY]))
            .prop_map(|(i, x)| Fault::NonFinite(i, x)),
        1 => Just(Fault::GripperNan),
        1 => (0.11f64..10.0, any::<bool>()).prop_map(|(age, ahead)| Fault::Stale(age, ahead)),
    ]
}

/// What the filter must do with a command, decided from the command and the arm's model
/// (joint limits, FK, the configured workspace and step), not from the filter's answer.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Expect {
    /// Inside every limit: passed.
    InLimit,
    /// Outside a limit the filter clips to (a velocity beyond full scale, a pose beyond one
    /// step or outside the box, the gripper outside 0..1): passed, and the clip reported.
    Clipped,
    /// Refused, with this refusal.
    Refused(&'static str),
    /// A joint target between the FR3's limit and the margin: clipped into the margin, and
    /// then refused or not by where that puts the TCP; only the output is checked.
    Borderline,
}

fn refusal_kind(r: &Refusal) -> &'static str {
    match r {
        Refusal::UnknownMode(_) => "UnknownMode",
        Refusal::NonFinite { .. } => "NonFinite",
        Refusal::GripperNonFinite(_) => "GripperNonFinite",
        Refusal::Stale { .. } => "Stale",
        Refusal::JointOutOfLimits { .. } => "JointOutOfLimits",
        Refusal::OutsideWorkspace { .. } => "OutsideWorkspace",
    }
}

/// A command of `mode` from the case's numbers (`v` in [-1, 1], stretched by `scale`: at
/// 0.3 inside the limits, at 4 mostly beyond them) around the reset pose.
fn generated(f: &SafetyFilter, mode: ArmCommandMode, v: [f64; 7], scale: f64, g: f64, fault: Fault) -> ArmCommand {
    let here = f.ik().kinematics().tcp_pose(&DROID_RESET_POSE);
    let mut c = command(mode);
    c.cartesian_velocity = std::array::from_fn(|i| v[i] * scale);
    c.joint_velocity = v.map(|x| x * scale);
    c.joint_position = std::array::from_fn(|i| DROID_RESET_POSE[i] + v[i] * scale * 0.3);
    // Absolute targets near the TCP: 5 cm and 0.1 rad per axis at scale 1.
    let t = here.translation.vector;
    let d = |i: usize| v[i] * scale * if i < 3 { 0.05 } else { 0.1 };
    c.cartesian_position = if mode == ArmCommandMode::CartesianPositionAxisAngle {
        let r = here.rotation.scaled_axis();
        [t.x + d(0), t.y + d(1), t.z + d(2), r.x + d(3), r.y + d(4), r.z + d(5)]
    } else {
        let e = labrig_arm::ik::xyz_euler(&here);
        std::array::from_fn(|i| e[i] + d(i))
    };
    c.gripper_position = g;
    match fault {
        Fault::None => {}
        Fault::NonFinite(i, x) => match mode {
            ArmCommandMode::CartesianVelocity => c.cartesian_velocity[i % 6] = x,
            ArmCommandMode::CartesianPosition | ArmCommandMode::CartesianPositionAxisAngle => {
                c.cartesian_position[i % 6] = x
            }
            ArmCommandMode::JointVelocity => c.joint_velocity[i] = x,
            ArmCommandMode::JointPosition => c.joint_position[i] = x,
        },
        Fault::GripperNan => c.gripper_position = f64::NAN,
        Fault::Stale(age, ahead) => {
            let age_ns = (age * 1e9) as i64;
            let stamp = if ahead { NOW + age_ns } else { NOW - age_ns };
            c.header.stamp.sec = (stamp / 1_000_000_000) as i32;
            c.header.stamp.nanosec = (stamp % 1_000_000_000) as u32;
        }
    }
    c
}

fn expected(f: &SafetyFilter, c: &ArmCommand, mode: ArmCommandMode, fault: Fault) -> Expect {
    match fault {
        Fault::None => {}
        Fault::NonFinite(..) => return Expect::Refused("NonFinite"),
        Fault::GripperNan => return Expect::Refused("GripperNonFinite"),
        Fault::Stale(..) => return Expect::Refused("Stale"),
    }
    let cfg = f.config();
    let kin = f.ik().kinematics();
    let in_box = |p: &[f64]| (0..3).all(|k| p[k] >= cfg.workspace_min_m[k] && p[k] <= cfg.workspace_max_m[k]);
    let inside = match mode {
        ArmCommandMode::CartesianVelocity => c.cartesian_velocity.iter().all(|x| x.abs() <= 1.0),
        ArmCommandMode::JointVelocity => c.joint_velocity.iter().all(|x| x.abs() <= 1.0),
        ArmCommandMode::CartesianPosition | ArmCommandMode::CartesianPositionAxisAngle => {
            let target = if mode == ArmCommandMode::CartesianPosition {
                labrig_arm::ik::pose_from_xyz_euler(&c.cartesian_position)
            } else {
                labrig_arm::ik::pose_from_xyz_axis_angle(&c.cartesian_position)
            };
            let (dp, dr) = labrig_arm::ik::pose_error(&kin.tcp_pose(&DROID_RESET_POSE), &target);
            dp.norm() <= cfg.max_step_m && dr.norm() <= cfg.max_step_rad && in_box(target.translation.vector.as_slice())
        }
        ArmCommandMode::JointPosition => {
            let q = &c.joint_position;
            let limits = kin.limits();
            if (0..7).any(|i| q[i] < limits[i][0] || q[i] > limits[i][1]) {
                return Expect::Refused("JointOutOfLimits");
            }
            let m = cfg.joint_margin_rad;
            if (0..7).any(|i| q[i] < limits[i][0] + m || q[i] > limits[i][1] - m) {
                return Expect::Borderline;
            }
            if !in_box(kin.tcp_pose(q).translation.vector.as_slice()) {
                return Expect::Refused("OutsideWorkspace");
            }
            true
        }
    };
    if inside && (0.0..=1.0).contains(&c.gripper_position) { Expect::InLimit } else { Expect::Clipped }
}

/// Per mode: how many commands of each kind came, and how many of them passed.
#[derive(Debug, Default)]
struct Tally {
    in_limit: (u32, u32),
    clipped: (u32, u32),
    borderline: (u32, u32),
    /// Refusals expected, by kind: (commands, refused with that kind).
    refused: std::collections::BTreeMap<&'static str, (u32, u32)>,
}

/// Each mode passes the commands inside its limits and those it clips, refuses the bad ones
/// (NaN, stale, joint targets past the FR3's limits or taking the TCP out of the box) by
/// name, and whatever passes is inside the joint bounds, within one step of the last command
/// and (cartesian modes) inside the workspace. Counted per mode over the cases, so that a
/// filter refusing everything (or a generator that never reaches a kind of command) fails.
#[test]
fn each_mode_passes_in_limit_commands_refuses_bad_ones_and_nothing_unsafe_comes_out() {
    use proptest::test_runner::{TestCaseError, TestRunner};
    let f = filter();
    let tallies = std::cell::RefCell::new(std::collections::BTreeMap::<String, Tally>::new());
    let strategy = (
        any_mode(),
        prop::array::uniform7(-1.0f64..1.0),
        prop::sample::select(vec![0.3, 1.0, 4.0]),
        prop_oneof![3 => 0.0f64..=1.0, 1 => -1.0f64..2.0],
        fault(),
    );
    let mut runner = TestRunner::new(ProptestConfig { cases: 1500, failure_persistence: None, ..Default::default() });
    let run = runner.run(&strategy, |(mode, v, scale, g, fault)| {
        let c = generated(&f, mode, v, scale, g, fault);
        let expect = expected(&f, &c, mode, fault);
        let out = f.filter(&c, &at_reset(), Nanos(NOW));
        let mut tallies = tallies.borrow_mut();
        let t = tallies.entry(format!("{mode:?}")).or_default();
        let count = |n: &mut (u32, u32), yes: bool| {
            n.0 += 1;
            n.1 += u32::from(yes);
        };
        match expect {
            Expect::InLimit => count(&mut t.in_limit, out.is_ok()),
            Expect::Clipped => count(&mut t.clipped, out.as_ref().is_ok_and(|ok| !ok.clipped.is_empty())),
            Expect::Borderline => count(&mut t.borderline, out.is_ok()),
            Expect::Refused(kind) => {
                count(t.refused.entry(kind).or_default(), out.as_ref().is_err_and(|e| refusal_kind(e) == kind))
            }
        }
        match (&expect, &out) {
            (Expect::InLimit | Expect::Borderline, Ok(_)) | (Expect::Borderline, Err(_)) => {}
            (Expect::Clipped, Ok(ok)) => prop_assert!(!ok.clipped.is_empty(), "{mode:?} {c:?}: no clip reported"),
            (Expect::Refused(kind), Err(e)) => prop_assert_eq!(refusal_kind(e), *kind, "{:?} {:?}: {}", mode, c, e),
            _ => return Err(TestCaseError::fail(format!("{mode:?}: expected {expect:?}, got {out:?} for {c:?}"))),
        }
        if let Ok(ok) = out {
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
        Ok(())
    });
    if let Err(e) = run {
        panic!("{e}");
    }
    let tallies = tallies.into_inner();
    eprintln!("{tallies:#?}");
    assert_eq!(tallies.len(), 5, "every mode generated: {tallies:?}");
    // 1500 cases, about 300 a mode: some 110-150 inside every limit, 25-100 to clip (the joint
    // position mode clips only the gripper) and 20-40 of each refusal. The floors sit far below
    // that, so a random run does not trip them; a generator that stopped reaching a kind does.
    for (mode, t) in &tallies {
        assert!(t.in_limit.0 >= 40, "{mode}: only {} in-limit commands generated: {t:?}", t.in_limit.0);
        assert_eq!(t.in_limit.1, t.in_limit.0, "{mode}: every in-limit command passes: {t:?}");
        assert!(t.clipped.0 >= 5, "{mode}: only {} commands to clip generated: {t:?}", t.clipped.0);
        assert_eq!(t.clipped.1, t.clipped.0, "{mode}: every command beyond a clipped limit passes, clipped: {t:?}");
        let mut kinds = vec!["GripperNonFinite", "NonFinite", "Stale"];
        if mode == "JointPosition" {
            kinds.extend(["JointOutOfLimits", "OutsideWorkspace"]);
            kinds.sort_unstable();
        }
        assert_eq!(t.refused.keys().copied().collect::<Vec<_>>(), kinds, "{mode}: {t:?}");
        for (kind, (n, refused)) in &t.refused {
            assert!(*n >= 5, "{mode}: only {n} commands to refuse as {kind}: {t:?}");
            assert_eq!(refused, n, "{mode}: every {kind} command is refused as such: {t:?}");
        }
    }
}
