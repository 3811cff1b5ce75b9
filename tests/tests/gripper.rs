//! The gripper node (`labrig-gripper run`, its own process) against an emulated 2F-85 on a
//! pseudo-terminal in this test: activation at start, motion and object detection from
//! /gripper/command, a refused NaN command, a fault and re-activation over /gripper/activate,
//! and a silent gripper reported in /gripper/state.

use labrig_gripper::{Emulated2F85, EmulatorConfig};
use labrig_msgs::rig::{GripperCommand, GripperState};
use labrig_msgs::std_srvs::{Trigger, TriggerRequest};
use labrig_runtime::RosConfig;
use labrig_runtime::ros::{Ros, RosSubscription, qos};
use labrig_tests::{Proc, domain_for, rt, workspace_bin};
use std::process::Command;
use std::time::{Duration, Instant};

async fn wait_state(
    sub: &RosSubscription<GripperState>,
    what: &str,
    pred: impl Fn(&GripperState) -> bool,
) -> GripperState {
    let deadline = Instant::now() + Duration::from_secs(30);
    let mut last = None;
    while Instant::now() < deadline {
        while let Some(s) = sub.try_take().unwrap() {
            if pred(&s.msg) {
                return s.msg;
            }
            last = Some(s.msg);
        }
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    panic!("no /gripper/state with {what} within 30 s; last: {last:?}");
}

fn command(position: f64) -> GripperCommand {
    GripperCommand { position, speed: 1.0, force: 1.0, ..Default::default() }
}

#[test]
fn the_gripper_node_drives_an_emulated_2f85() {
    let domain = domain_for("the_gripper_node_drives_an_emulated_2f85");
    rt().block_on(async move {
        let emu = Emulated2F85::new(EmulatorConfig::default());
        let pty = emu.serve_on_pty().unwrap();
        let mut cmd = Command::new(workspace_bin("labrig-gripper", "labrig-gripper"));
        cmd.args(["run", "--port", pty.path(), "--domain-id", &domain.to_string()]);
        let _node = Proc::spawn("labrig-gripper run", cmd);

        let mut ros = Ros::new(&RosConfig { domain_id: domain, ..RosConfig::default() }, "gripper_test").unwrap();
        let cmd_pub = ros.publisher::<GripperCommand>("/gripper/command", qos::reliable(10)).unwrap();
        let states = ros.subscription::<GripperState>("/gripper/state", qos::reliable(100)).unwrap();
        let activate = ros.client::<Trigger>("/gripper/activate", qos::reliable(10)).unwrap();
        assert!(ros.wait_for_subscribers("/gripper/command", 1, Duration::from_secs(60)).await, "node did not come up");

        let s = wait_state(&states, "activated", |s| s.activated).await;
        assert_eq!((s.position, s.fault_code, s.fault.as_str()), (0.0, 0, ""), "activation opens the fingers");

        // Close on an object at 150 counts.
        emu.place_object(Some(150));
        cmd_pub.publish(command(1.0)).unwrap();
        let s = wait_state(&states, "an object", |s| s.object_detected).await;
        assert!((s.position - 150.0 / 255.0).abs() < 1e-9, "{s:?}");
        assert_eq!(s.requested_position, 1.0);
        assert!(s.current_ma > 100.0);

        // A NaN command is refused, named, and moves nothing; the same valid command as
        // before (a 20 Hz rig repeats its action) clears the refusal.
        cmd_pub.publish(command(f64::NAN)).unwrap();
        let s = wait_state(&states, "the refusal", |s| !s.fault.is_empty()).await;
        assert_eq!(s.fault, "refused gripper command: position NaN is outside 0..1");
        assert!(s.object_detected, "still holding the object");
        cmd_pub.publish(command(1.0)).unwrap();
        let s = wait_state(&states, "the refusal cleared", |s| s.fault.is_empty()).await;
        assert!(s.object_detected);

        // Open: the object is released. Then half closed.
        cmd_pub.publish(command(0.0)).unwrap();
        let s = wait_state(&states, "open", |s| s.position == 0.0 && s.fault.is_empty()).await;
        assert!(!s.object_detected);
        cmd_pub.publish(command(0.5)).unwrap();
        wait_state(&states, "half closed", |s| (s.position - 128.0 / 255.0).abs() < 1e-9).await;

        // Overcurrent: reported with its code and meaning; motion refused until re-activation.
        emu.inject_fault(0x0E);
        let s = wait_state(&states, "the fault", |s| s.fault_code == 0x0E).await;
        assert!(s.fault.contains("0x0E") && s.fault.contains("overcurrent"), "{}", s.fault);
        assert!(!s.activated, "a major fault: not ready");
        // The node says it holds the command back (so it arrived), and the 2F-85 was not written.
        cmd_pub.publish(command(0.9)).unwrap();
        let s = wait_state(&states, "the held-back command", |s| s.fault.contains("was not written")).await;
        assert!(s.fault.contains("the command to 0.902 was not written") && s.fault.contains("0x0E"), "{}", s.fault);
        let g = emu.status();
        assert_eq!((g.requested, g.position), (128, 128), "nothing written under a fault: {}", g.describe());
        // Back to the command written before the fault: nothing left to write, so nothing is
        // held back (the state says the fault alone once the command has arrived).
        cmd_pub.publish(command(0.5)).unwrap();
        let s = wait_state(&states, "nothing held back", |s| !s.fault.contains("was not written")).await;
        assert!(s.fault.contains("0x0E"), "the fault stays until re-activation: {}", s.fault);
        activate.wait_for_service(&ros, Duration::from_secs(30)).await.unwrap();
        let r = activate.call(TriggerRequest::default(), Duration::from_secs(30)).await.unwrap();
        assert!(r.success, "{}", r.message);
        let s = wait_state(&states, "re-activated", |s| s.activated && s.fault_code == 0).await;
        assert!(s.fault.is_empty(), "{}", s.fault);
        assert_eq!(emu.status().requested, 0, "activation resets the request (fingers open)");
        // The activation opened the fingers; the same 0.5 as before the fault is written again.
        cmd_pub.publish(command(0.5)).unwrap();
        wait_state(&states, "half closed again", |s| (s.position - 128.0 / 255.0).abs() < 1e-9).await;

        // A gripper that stops answering is reported, and the node recovers when it answers.
        emu.set_mute(true);
        let s = wait_state(&states, "the timeout", |s| s.fault.contains("no answer")).await;
        assert!(s.fault.contains("no answer from the 2F-85 (slave 9) to a status read"), "{}", s.fault);
        emu.set_mute(false);
        wait_state(&states, "recovery", |s| s.fault.is_empty() && s.activated).await;
    });
}

/// The gripper node's `sim` backend: in front of the sim bridge's 2F-85 (arm and gripper
/// topics under /sim). /gripper/command closes and opens the simulated fingers through the
/// node, whose /gripper/state follows the physics.
#[test]
fn the_gripper_node_drives_the_sim_bridges_2f85() {
    let domain = domain_for("the_gripper_node_drives_the_sim_bridges_2f85");
    let _bridge = labrig_tests::sim_hardware(domain);
    let _node = labrig_tests::sim_backend_node("labrig-gripper", domain);
    rt().block_on(async move {
        let mut ros = Ros::new(&RosConfig { domain_id: domain, ..RosConfig::default() }, "gripper_sim_test").unwrap();
        let cmd_pub = ros.publisher::<GripperCommand>("/gripper/command", qos::reliable(10)).unwrap();
        let states = ros.subscription::<GripperState>("/gripper/state", qos::reliable(100)).unwrap();
        assert!(ros.wait_for_subscribers("/gripper/command", 1, Duration::from_secs(60)).await, "node did not come up");
        let s = wait_state(&states, "activated", |s| s.activated && s.fault.is_empty()).await;
        assert!(s.position < 0.05, "starts open: {s:?}");
        cmd_pub.publish(command(1.0)).unwrap();
        let s = wait_state(&states, "closed", |s| s.position > 0.9).await;
        assert_eq!(s.requested_position, 1.0);
        assert!(!s.object_detected, "nothing between the fingers: {s:?}");
        cmd_pub.publish(command(0.0)).unwrap();
        wait_state(&states, "open again", |s| s.position < 0.05 && s.requested_position == 0.0).await;
        cmd_pub.publish(command(f64::INFINITY)).unwrap();
        let s = wait_state(&states, "the refusal", |s| !s.fault.is_empty()).await;
        assert_eq!(s.fault, "refused gripper command: position inf is outside 0..1");
    });
}
