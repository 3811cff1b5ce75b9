//! The scripted experts solve pick-and-place on seeded scenes across all five camera bins and
//! the spec's object and bin boxes (the bar: at least 90% of 50 scenes), and open and
//! close the drawer; success is judged on the physics.

use labrig_msgs::Nanos;
use labrig_sim::expert::{self, Phase};
use labrig_sim::rig::DEFAULT_ASSETS;
use labrig_sim::scene::{CameraBin, DRAWER_CLOSED_M, DRAWER_OPEN_M, Task};
use labrig_sim::{SceneSpec, Sim};
use std::collections::BTreeSet;
use std::path::PathBuf;

fn assets() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("..").join(DEFAULT_ASSETS)
}

#[test]
fn the_expert_solves_at_least_90_percent_of_50_seeded_scenes() {
    let spec = SceneSpec::default_pick_place();
    let mut successes = 0;
    let mut bins = BTreeSet::new();
    let mut boxes = BTreeSet::new();
    for seed in 0..50 {
        let mut sim = Sim::new(&assets(), &spec, seed, Nanos::from_millis(50)).unwrap();
        for pose in sim.scene().cameras.values() {
            bins.insert(pose.bin.unwrap());
        }
        boxes.insert((sim.scene().receptacle_position[1] > 0.0) as u8);
        let r = expert::run_episode(&mut sim, 400, |_, _| Ok(())).unwrap();
        successes += r.success as u32;
        if r.success {
            assert_eq!(r.final_phase, Phase::Done);
        }
    }
    assert_eq!(bins.len(), CameraBin::ALL.len(), "the 50 scenes must cover all five camera bins");
    assert_eq!(boxes.len(), 2, "the 50 scenes must use both receptacle boxes");
    assert!(successes >= 45, "expert succeeded on {successes}/50 scenes");
}

#[test]
fn success_is_judged_on_the_physics_not_on_the_script() {
    // Without the expert the object stays where it was put: not a success.
    let mut sim = Sim::new(&assets(), &SceneSpec::default_pick_place(), 5, Nanos::from_millis(50)).unwrap();
    let hold = labrig_sim::ArmTarget { joints: labrig_sim::rig::RESET_POSE, gripper: 0.0 };
    for _ in 0..20 {
        sim.step(&hold).unwrap();
    }
    assert!(!expert::pick_place_success(&sim));
    // A run with its tick budget cut short (before the carry) fails too.
    let mut sim = Sim::new(&assets(), &SceneSpec::default_pick_place(), 5, Nanos::from_millis(50)).unwrap();
    let r = expert::run_episode(&mut sim, 30, |_, _| Ok(())).unwrap();
    assert!(!r.success, "{r:?}");
}

fn drawer_rate(scene: &str, seeds: std::ops::Range<u64>) -> (u32, Vec<expert::EpisodeResult>) {
    let spec = SceneSpec::builtin(scene).unwrap();
    let mut ok = 0;
    let mut failed = Vec::new();
    for seed in seeds {
        let mut sim = Sim::new(&assets(), &spec, seed, Nanos::from_millis(50)).unwrap();
        let r = expert::run_episode(&mut sim, 400, |_, _| Ok(())).unwrap();
        let [from, to] = r.drawer_opening.expect("a drawer scene reports the drawer");
        if r.success {
            ok += 1;
            assert_eq!(r.final_phase, Phase::Done);
            // The predicate agrees with the drawer's travel on the physics.
            match r.task {
                Task::DrawerOpen => assert!(from < DRAWER_OPEN_M && to >= DRAWER_OPEN_M, "{r:?}"),
                _ => assert!(from > DRAWER_CLOSED_M && to <= DRAWER_CLOSED_M, "{r:?}"),
            }
        } else {
            failed.push(r);
        }
    }
    (ok, failed)
}

#[test]
fn the_expert_opens_the_drawer() {
    let (ok, failed) = drawer_rate("drawer_open", 0..20);
    assert!(ok >= 18, "drawer_open: {ok}/20, failed: {failed:?}");
}

#[test]
fn the_expert_closes_the_drawer() {
    let (ok, failed) = drawer_rate("drawer_close", 0..20);
    assert!(ok >= 18, "drawer_close: {ok}/20, failed: {failed:?}");
}

#[test]
fn the_drawer_stays_put_untouched_and_is_not_a_success() {
    for scene in ["drawer_open", "drawer_close"] {
        let mut sim = Sim::new(&assets(), &SceneSpec::builtin(scene).unwrap(), 3, Nanos::from_millis(50)).unwrap();
        let start = sim.drawer_opening().unwrap();
        assert!((start - sim.scene().drawer.as_ref().unwrap().opening_m).abs() < 1e-9);
        let hold = labrig_sim::ArmTarget { joints: labrig_sim::rig::RESET_POSE, gripper: 0.0 };
        for _ in 0..40 {
            sim.step(&hold).unwrap();
        }
        let end = sim.drawer_opening().unwrap();
        assert!((end - start).abs() < 1e-3, "{scene}: the drawer slid by itself from {start} to {end}");
        assert!(!expert::task_success(&sim), "{scene}: untouched drawer judged a success");
        // An expert cut short (before it slides the drawer) fails too.
        let mut sim = Sim::new(&assets(), &SceneSpec::builtin(scene).unwrap(), 3, Nanos::from_millis(50)).unwrap();
        let r = expert::run_episode(&mut sim, 25, |_, _| Ok(())).unwrap();
        assert!(!r.success, "{r:?}");
    }
}

/// Drives `sim` with `expert` (and the crate's IK) until it is done or `max_ticks` pass.
fn drive(sim: &mut Sim, expert: &mut expert::Expert, max_ticks: u32) -> Phase {
    let ik = expert::CartesianIk::new(sim);
    for _ in 0..max_ticks {
        let a = expert.act(sim);
        let joints = ik.solve(sim, &a.cartesian_position);
        sim.step(&labrig_sim::ArmTarget { joints, gripper: a.gripper_position }).unwrap();
        if a.phase == Phase::Done {
            break;
        }
    }
    let hold = labrig_sim::ArmTarget { joints: sim.joint_targets(), gripper: 0.0 };
    for _ in 0..10 {
        sim.step(&hold).unwrap();
    }
    expert.phase()
}

/// A takeover mid-episode (`Expert::resume`): from wherever another driver left the arm, the
/// expert infers its phase from the physics and still solves the scene. From mid-air (the
/// arm moved off to the side, nothing held), and from an object already in the fingers and
/// lifted (it carries on, not dropping it with an approach).
#[test]
fn the_expert_resumed_mid_episode_solves_the_scene_from_where_it_finds_it() {
    let spec = SceneSpec::default_pick_place();
    for seed in [0, 1, 2] {
        // Mid-air: the reset pose with joints 1 and 4 turned, the gripper open.
        let mut sim = Sim::new(&assets(), &spec, seed, Nanos::from_millis(50)).unwrap();
        let template = expert::Expert::new(&sim);
        let mut off = labrig_sim::rig::RESET_POSE;
        off[0] += 0.3;
        off[3] += 0.2;
        for _ in 0..30 {
            sim.step(&labrig_sim::ArmTarget { joints: off, gripper: 0.0 }).unwrap();
        }
        let mut resumed = template.resume(&sim);
        assert_eq!(resumed.phase(), Phase::Approach);
        let plan = resumed.plan(&sim);
        assert_eq!(plan.len(), 6, "{plan:?}");
        drive(&mut sim, &mut resumed, 300);
        assert!(expert::pick_place_success(&sim), "seed {seed}: from mid-air, ended in {:?}", resumed.phase());

        // Held: the expert's own run stopped once the object is up, then a fresh expert
        // resumed from there.
        let mut sim = Sim::new(&assets(), &spec, seed, Nanos::from_millis(50)).unwrap();
        let template = expert::Expert::new(&sim);
        let mut first = template.clone();
        let ik = expert::CartesianIk::new(&sim);
        for _ in 0..300 {
            let a = first.act(&sim);
            let joints = ik.solve(&sim, &a.cartesian_position);
            sim.step(&labrig_sim::ArmTarget { joints, gripper: a.gripper_position }).unwrap();
            if a.phase == Phase::Carry {
                break;
            }
        }
        assert!(sim.object_position()[2] > labrig_sim::scene::OBJECT_SIZE, "seed {seed}: the object is up");
        let mut resumed = template.resume(&sim);
        assert_eq!(resumed.phase(), Phase::Lift, "seed {seed}: a held object is carried on");
        drive(&mut sim, &mut resumed, 300);
        assert!(expert::pick_place_success(&sim), "seed {seed}: from the held object, ended in {:?}", resumed.phase());
    }
}

#[test]
fn the_expert_that_aims_off_stops_beside_the_object_corrects_over_it_and_still_solves() {
    let spec = SceneSpec::default_pick_place();
    let max_m = 0.06;
    let mut successes = 0;
    for seed in 0..10 {
        let mut sim = Sim::new(&assets(), &spec, seed, Nanos::from_millis(50)).unwrap();
        let obj = sim.object_position();
        let aimed = expert::Expert::new(&sim).with_aim_error(&sim, max_m);
        // Where the approach first heads: its phase target on the first tick.
        let first_target = aimed.clone().act(&sim).target;
        let off = ((first_target[0] - obj[0]).powi(2) + (first_target[1] - obj[1]).powi(2)).sqrt();
        assert!(
            (0.4 * max_m - 1e-9..=max_m + 1e-9).contains(&off),
            "seed {seed}: the first hover point is {off:.4} m off the object, not 0.4..1 x {max_m}"
        );
        // The same seed draws the same offset; the exact expert heads straight over the object.
        assert_eq!(expert::Expert::new(&sim).with_aim_error(&sim, max_m).act(&sim).target, first_target);
        let exact = expert::Expert::new(&sim).act(&sim).target;
        assert!((exact[0] - obj[0]).abs() < 1e-9 && (exact[1] - obj[1]).abs() < 1e-9, "{exact:?} {obj:?}");
        // Over the run the phase target moves from the aimed-off point to the object itself
        // before the fingers close: the grasp waits for the correction.
        let mut targets_before_grasp = Vec::new();
        let mut closed = false;
        let r = expert::run_episode_with(&mut sim, aimed, 400, |_, a| {
            closed |= a.gripper_position >= 0.5;
            if !closed {
                targets_before_grasp.push(a.target);
            }
            Ok(())
        })
        .unwrap();
        let last = targets_before_grasp.last().unwrap();
        assert!(
            (last[0] - obj[0]).abs() < 1e-6 && (last[1] - obj[1]).abs() < 1e-6,
            "seed {seed}: the last target before the grasp {last:?} is not over the object {obj:?}"
        );
        successes += r.success as u32;
    }
    assert!(successes >= 9, "the aiming expert succeeded on {successes}/10 scenes");
}

/// With a miss fraction of 1 every scene's first grasp closes on nothing 4-5.5 cm beside the
/// cube (the fingers shut: the gripper reads near 1 while the arm is still down); the expert
/// then rises, opens, comes back over the cube and grasps it, and still solves. With 0 the
/// seeds' first grasps hold. The same seed draws the same miss.
#[test]
fn the_expert_that_misses_on_purpose_closes_beside_the_cube_then_recovers() {
    let spec = SceneSpec::default_pick_place();
    let mut successes = 0;
    for seed in 0..6 {
        for fraction in [0.0, 1.0] {
            let mut sim = Sim::new(&assets(), &spec, seed, Nanos::from_millis(50)).unwrap();
            let obj = sim.object_position();
            let e = expert::Expert::new(&sim).with_aim_error(&sim, 0.06).with_missed_grasp(&sim, fraction);
            // (command closed, TCP xy distance from the cube, gripper reading) per tick.
            let mut ticks: Vec<(bool, f64, f64)> = Vec::new();
            let r = expert::run_episode_with(&mut sim, e, 500, |sim, a| {
                let (p, _) = sim.tcp_pose();
                let o = sim.object_position();
                ticks.push((a.gripper_position >= 0.5, (p[0] - o[0]).hypot(p[1] - o[1]), sim.gripper_position()));
                Ok(())
            })
            .unwrap();
            let closes: Vec<usize> = (1..ticks.len()).filter(|&t| ticks[t].0 && !ticks[t - 1].0).collect();
            if fraction == 0.0 {
                assert_eq!(closes.len(), 1, "seed {seed}: the first grasp should hold ({} closes)", closes.len());
                continue;
            }
            assert_eq!(closes.len(), 2, "seed {seed}: a miss and a grasp, not {} closes", closes.len());
            let miss_off = ticks[closes[0]].1;
            assert!(
                (0.03..0.07).contains(&miss_off),
                "seed {seed}: the miss closed {miss_off:.3} m from the cube ({obj:?})"
            );
            let shut = ticks[closes[0]..closes[1]].iter().map(|t| t.2).fold(0.0, f64::max);
            assert!(shut > 0.8, "seed {seed}: the fingers shut on nothing should read near 1, read {shut:.2}");
            let grasp_off = ticks[closes[1]].1;
            assert!(grasp_off < 0.01, "seed {seed}: the retry closed {grasp_off:.3} m from the cube");
            successes += r.success as u32;
        }
    }
    assert_eq!(successes, 6, "the missing expert solved {successes}/6 scenes");
}

/// The drawer experts look and correct, and miss on purpose, as the pick-and-place one does:
/// with a miss fraction of 1 the first close comes down 6-7.5 cm toward the robot from the
/// handle's centre (past the bar's free end) and shuts on nothing (the gripper reads more than it does on the 16 mm bar); the
/// slide finds no handle in the fingers, and the retry grasps the handle and solves. With 0
/// the first close is on the handle (it may still slip while sliding, as the exact expert's
/// does in some scenes, and be grasped again); the aimed approach first heads beside it.
#[test]
fn the_drawer_experts_aim_off_and_miss_on_purpose_then_recover() {
    for scene in ["drawer_open", "drawer_close"] {
        let spec = SceneSpec::builtin(scene).unwrap();
        let mut successes = 0;
        for seed in 0..4 {
            for fraction in [0.0, 1.0] {
                let mut sim = Sim::new(&assets(), &spec, seed, Nanos::from_millis(50)).unwrap();
                let h = sim.handle_position().unwrap();
                let e = expert::Expert::new(&sim).with_aim_error(&sim, 0.06).with_missed_grasp(&sim, fraction);
                let first = e.clone().act(&sim).target;
                let off = (first[0] - h[0]).hypot(first[1] - h[1]);
                assert!((0.024 - 1e-9..=0.06 + 1e-9).contains(&off), "{scene} seed {seed}: first hover {off:.3} m off");
                // (command closed, TCP xy distance from the handle, gripper reading) per tick.
                let mut ticks: Vec<(bool, f64, f64)> = Vec::new();
                let r = expert::run_episode_with(&mut sim, e, 500, |sim, a| {
                    let (p, _) = sim.tcp_pose();
                    let h = sim.handle_position().unwrap();
                    ticks.push((a.gripper_position >= 0.5, (p[0] - h[0]).hypot(p[1] - h[1]), sim.gripper_position()));
                    Ok(())
                })
                .unwrap();
                let closes: Vec<usize> = (1..ticks.len()).filter(|&t| ticks[t].0 && !ticks[t - 1].0).collect();
                let reading = |from: usize, to: usize| ticks[from..to].iter().map(|t| t.2).fold(0.0, f64::max);
                successes += r.success as u32;
                if fraction == 0.0 {
                    let first = ticks[closes[0]].1;
                    assert!(first < 0.02, "{scene} seed {seed}: the first close was {first:.3} m from the handle");
                    continue;
                }
                assert!(closes.len() >= 2, "{scene} seed {seed}: a miss and a grasp, not {closes:?}");
                let miss_off = ticks[closes[0]].1;
                assert!((0.05..0.09).contains(&miss_off), "{scene} seed {seed}: the miss closed {miss_off:.3} m off");
                let (on_nothing, on_handle) = (reading(closes[0], closes[1]), reading(closes[1], ticks.len()));
                assert!(
                    on_nothing > 0.95 && on_handle < 0.9,
                    "{scene} seed {seed}: shut on nothing reads {on_nothing:.2}, on the handle {on_handle:.2}"
                );
                let grasp_off = ticks[closes[1]].1;
                assert!(grasp_off < 0.02, "{scene} seed {seed}: the retry closed {grasp_off:.3} m from the handle");
            }
        }
        assert!(successes >= 7, "{scene}: the aiming, missing expert solved {successes}/8");
    }
}
