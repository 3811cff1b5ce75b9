//! The franka node's URDF kinematics (labrig-franka) against MuJoCo's own model of the rig:
//! the flange and the 2F-85's pinch point for 1,000 random joint configurations.

use labrig_arm::kinematics::TcpOffset;
use labrig_arm::{Fr3Kinematics, urdf_path};
use labrig_msgs::Nanos;
use labrig_sim::rig::DEFAULT_ASSETS;
use labrig_sim::{SceneSpec, Sim};
use nalgebra::{Matrix3, Rotation3, UnitQuaternion, Vector3};
use rand::{Rng, SeedableRng};
use std::path::PathBuf;

fn sim() -> Sim {
    let assets = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("..").join(DEFAULT_ASSETS);
    Sim::new(&assets, &SceneSpec::default_pick_place(), 0, Nanos::from_millis(50)).unwrap()
}

fn kin() -> Fr3Kinematics {
    let urdf = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("..").join(labrig_arm::DEFAULT_URDF);
    Fr3Kinematics::from_urdf_file(&urdf_path(Some(&urdf)), TcpOffset::ROBOTIQ_2F85).unwrap()
}

/// Position error (m) and rotation error (deg) between a URDF pose and a MuJoCo pose.
fn errors(p: &nalgebra::Isometry3<f64>, pos: [f64; 3], mat: [f64; 9]) -> (f64, f64) {
    let r = UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(Matrix3::from_row_slice(&mat)));
    ((p.translation.vector - Vector3::from(pos)).norm(), p.rotation.angle_to(&r).to_degrees())
}

#[test]
fn urdf_kinematics_agree_with_mujoco_on_1000_configurations() {
    let mut sim = sim();
    let kin = kin();
    // Same joints; the stricter of the URDF and datasheet limits is MuJoCo's range.
    assert_eq!(kin.joint_names(), labrig_sim::rig::ARM_JOINTS);
    for (u, m) in kin.limits().iter().zip(sim.joint_limits()) {
        assert!((u[0] - m[0]).abs() < 1e-4 && (u[1] - m[1]).abs() < 1e-4, "URDF {u:?} vs MuJoCo {m:?}");
    }
    // The rig mounts the 2F-85 on a flange body turned +90 deg about z; the URDF's flange
    // (fr3_link8) is not turned.
    let mount = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), std::f64::consts::FRAC_PI_2);
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(4);
    let limits = sim.joint_limits();
    let (mut worst_flange, mut worst_tcp) = ((0.0f64, 0.0f64), (0.0f64, 0.0f64));
    for _ in 0..1000 {
        let q: [f64; 7] = std::array::from_fn(|i| rng.random_range(limits[i][0]..=limits[i][1]));
        sim.set_arm_configuration(&q).unwrap();
        let (pos, mat) = sim.body_pose("flange").unwrap();
        let mut flange = kin.flange_pose(&q);
        flange.rotation *= mount;
        let (dp, dr) = errors(&flange, pos, mat);
        worst_flange = (worst_flange.0.max(dp), worst_flange.1.max(dr));
        let (pos, mat) = sim.tcp_pose();
        let (dp, dr) = errors(&kin.tcp_pose(&q), pos, mat);
        worst_tcp = (worst_tcp.0.max(dp), worst_tcp.1.max(dr));
    }
    eprintln!(
        "worst flange error {:.2e} m / {:.2e} deg; TCP {:.2e} m / {:.2e} deg",
        worst_flange.0, worst_flange.1, worst_tcp.0, worst_tcp.1
    );
    assert!(worst_flange.0 < 1e-4 && worst_flange.1 < 0.01, "flange: {worst_flange:?}");
    assert!(worst_tcp.0 < 1e-4 && worst_tcp.1 < 0.01, "TCP: {worst_tcp:?}");
}

#[test]
fn the_urdf_jacobian_matches_mujocos() {
    let mut sim = sim();
    let kin = kin();
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(9);
    let limits = sim.joint_limits();
    for _ in 0..100 {
        let q: [f64; 7] = std::array::from_fn(|i| rng.random_range(limits[i][0]..=limits[i][1]));
        sim.set_arm_configuration(&q).unwrap();
        let (_, j) = kin.tcp_pose_and_jacobian(&q);
        let m = sim.tcp_jacobian();
        for r in 0..6 {
            for c in 0..7 {
                assert!((j[(r, c)] - m[r][c]).abs() < 1e-4, "J[{r}][{c}] URDF {} vs MuJoCo {}", j[(r, c)], m[r][c]);
            }
        }
    }
}

/// The sim driven by joint targets from labrig-franka's IK along a cartesian path (a tilted
/// circle, r = 8 cm, 5 s a turn = 0.1 m/s, fingers down) at 20 Hz. Tracking a path = the TCP
/// MuJoCo measures stays on it: its distance to the nearest point of the path, every tick.
/// (Along the path it lags the timed target by the servos' delay; reported, not judged.)
#[test]
fn ik_tracks_a_cartesian_path_in_the_sim() {
    use labrig_arm::ik::{Ik, IkConfig};
    let mut sim = sim();
    let ik = Ik::new(kin(), IkConfig::default());
    let bounds = ik.bounds();
    let start = ik.kinematics().tcp_pose(&sim.joint_positions());
    let (r, turn_ticks) = (0.08, 100.0);
    let centre = start.translation.vector - Vector3::new(r, 0.0, 0.0);
    let path = |t: f64| {
        let a = t / turn_ticks * std::f64::consts::TAU;
        centre + Vector3::new(r * a.cos(), r * a.sin(), 0.03 * a.sin())
    };
    let dense: Vec<Vector3<f64>> = (0..=20_000).map(|k| path(k as f64 * turn_ticks / 20_000.0)).collect();
    let mut q = sim.joint_targets();
    let (mut off_path, mut lag, mut worst_ik) = (Vec::new(), Vec::new(), 0.0f64);
    for t in 1..=200 {
        let mut target = start;
        target.translation.vector = path(t as f64);
        let sol = ik.solve(&q, &target);
        worst_ik = worst_ik.max(sol.position_error_m);
        q = sol.joints;
        for (i, b) in bounds.iter().enumerate() {
            assert!(q[i] >= b[0] && q[i] <= b[1], "joint {i} = {} outside {b:?}", q[i]);
        }
        sim.step(&labrig_sim::ArmTarget { joints: q, gripper: 0.0 }).unwrap();
        let p = Vector3::from(sim.tcp_pose().0);
        lag.push((p - target.translation.vector).norm());
        // Skip the first quarter turn: the arm starts from rest.
        if t > 25 {
            off_path.push(dense.iter().map(|c| (p - c).norm()).fold(f64::INFINITY, f64::min));
        }
    }
    let pct = |v: &mut Vec<f64>, f: f64| {
        v.sort_by(f64::total_cmp);
        v[((v.len() - 1) as f64 * f) as usize] * 1e3
    };
    eprintln!(
        "IK residual max {worst_ik:.1e} m; TCP off the path p50 {:.2} mm, max {:.2} mm; behind the timed target p50 {:.1} mm",
        pct(&mut off_path, 0.5),
        pct(&mut off_path, 1.0),
        pct(&mut lag, 0.5)
    );
    assert!(worst_ik < 1e-4);
    let max = pct(&mut off_path, 1.0);
    assert!(max < 2.0, "the TCP left the path by {max:.2} mm");
}
