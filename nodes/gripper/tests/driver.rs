//! The 2F-85 driver on a pseudo-terminal: the exact bytes of the manual's Modbus RTU examples,
//! then against the emulated 2F-85: activation, motion, object detection, a fault, a timeout.

use labrig_gripper::registers::{Activation, Object, Request, counts_to_droid};
use labrig_gripper::{DriverConfig, Emulated2F85, EmulatorConfig, GripperError, Robotiq2F85};
use std::time::{Duration, Instant};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio_serial::SerialStream;

fn driver(path: &str) -> Robotiq2F85 {
    Robotiq2F85::open(DriverConfig::new(path)).unwrap()
}

async fn read_frame(port: &mut SerialStream, len: usize) -> Vec<u8> {
    let mut buf = vec![0u8; len];
    tokio::time::timeout(Duration::from_secs(5), port.read_exact(&mut buf)).await.expect("no frame").unwrap();
    buf
}

fn hex(s: &str) -> Vec<u8> {
    s.split_whitespace().map(|b| u8::from_str_radix(b, 16).unwrap()).collect()
}

/// The frames are the manual's own examples (CRC included), so the driver's framing is
/// checked against the device's documentation, not against the emulator.
#[tokio::test]
async fn the_driver_writes_the_manuals_frames() {
    let (mut gripper, slave) = SerialStream::pair().unwrap();
    let path = tokio_serial::SerialPort::name(&slave).unwrap();
    let _keep = std::fs::OpenOptions::new().read(true).write(true).open(&path).unwrap();
    drop(slave);
    let mut d = driver(&path);
    let task = tokio::spawn(async move {
        let s = d.activate(Duration::from_secs(5)).await.unwrap();
        d.go_to(255, 255, 255).await.unwrap();
        s
    });
    // Reset: rACT = 0.
    assert_eq!(read_frame(&mut gripper, 15).await, hex("09 10 03 E8 00 03 06 00 00 00 00 00 00 73 30"));
    gripper.write_all(&hex("09 10 03 E8 00 03 01 30")).await.unwrap();
    // Activate: rACT = 1.
    assert_eq!(read_frame(&mut gripper, 15).await, hex("09 10 03 E8 00 03 06 01 00 00 00 00 00 72 E1"));
    gripper.write_all(&hex("09 10 03 E8 00 03 01 30")).await.unwrap();
    // Status read of the three input registers; answer "activation in progress" (0x11) once,
    // then "complete" (0x31).
    assert_eq!(read_frame(&mut gripper, 8).await, hex("09 03 07 D0 00 03 04 0E"));
    gripper.write_all(&hex("09 03 06 11 00 00 00 00 00 45 F4")).await.unwrap();
    assert_eq!(read_frame(&mut gripper, 8).await, hex("09 03 07 D0 00 03 04 0E"));
    gripper.write_all(&hex("09 03 06 31 00 00 00 00 00 42 94")).await.unwrap();
    // Close at full speed and force.
    assert_eq!(read_frame(&mut gripper, 15).await, hex("09 10 03 E8 00 03 06 09 00 00 FF FF FF 42 29"));
    gripper.write_all(&hex("09 10 03 E8 00 03 01 30")).await.unwrap();
    let s = task.await.unwrap();
    assert_eq!(s.activation, Activation::Complete);
    assert!(s.activated);
}

async fn activated(emu: &Emulated2F85) -> (labrig_gripper::PtyEmulator, Robotiq2F85) {
    let pty = emu.serve_on_pty().unwrap();
    let mut d = driver(pty.path());
    d.activate(Duration::from_secs(5)).await.unwrap();
    (pty, d)
}

#[tokio::test]
async fn activation_runs_the_sequence_and_waits_for_gsta_3() {
    let emu = Emulated2F85::new(EmulatorConfig { activation: Duration::from_millis(300), ..Default::default() });
    let pty = emu.serve_on_pty().unwrap();
    let mut d = driver(pty.path());
    // Motion before activation is refused by the driver without a write ...
    let err = d.go_to(255, 255, 255).await.unwrap_err();
    assert!(matches!(err, GripperError::NotActivated { .. }), "{err}");
    // ... and by the gripper itself with fault 0x07 when a request forces it.
    d.write(Request { go_to: true, position: 255, ..Request::RESET }).await.unwrap();
    assert_eq!(d.status().await.unwrap().fault, 0x07);
    let t = Instant::now();
    d.write(Request::RESET).await.unwrap();
    d.write(Request::ACTIVATE).await.unwrap();
    let during = d.status().await.unwrap();
    assert_eq!(during.activation, Activation::InProgress, "{}", during.describe());
    assert!(during.activated && during.fault == 0, "reset cleared the fault: {}", during.describe());
    let s = d.activate(Duration::from_secs(5)).await.unwrap();
    assert!(t.elapsed() >= Duration::from_millis(300), "gSTA 3 before the activation time");
    assert_eq!(s.activation, Activation::Complete);
    assert_eq!(s.position, 0, "activation leaves the fingers open");
    assert!(s.ready());
}

/// A gripper that misses exchanges while it activates (a lost frame, a starved port): the
/// driver tries again until its deadline and the activation completes; one that stays silent
/// past the deadline is named.
#[tokio::test]
async fn activation_tries_again_after_missed_exchanges() {
    let emu = Emulated2F85::new(EmulatorConfig { activation: Duration::from_millis(300), ..Default::default() });
    let pty = emu.serve_on_pty().unwrap();
    let mut d = driver(pty.path());
    // Silent from the first write for 350 ms: the reset write times out at least once.
    emu.set_mute(true);
    let silent = emu.clone();
    let muter = tokio::spawn(async move {
        tokio::time::sleep(Duration::from_millis(350)).await;
        silent.set_mute(false);
    });
    let s = d.activate(Duration::from_secs(5)).await.unwrap();
    muter.await.unwrap();
    assert_eq!(s.activation, Activation::Complete);
    emu.set_mute(true);
    let err = d.activate(Duration::from_millis(500)).await.unwrap_err();
    assert!(matches!(err, GripperError::Timeout { .. }), "{err}");
}

#[tokio::test]
async fn the_fingers_move_to_the_request_and_report_it() {
    let emu = Emulated2F85::new(EmulatorConfig::default());
    let (_pty, mut d) = activated(&emu).await;
    d.go_to(200, 255, 100).await.unwrap();
    tokio::time::sleep(Duration::from_millis(100)).await;
    let moving = d.status().await.unwrap();
    assert_eq!(moving.object, Object::Moving);
    assert!(moving.position > 0 && moving.position < 200, "{}", moving.describe());
    assert!(moving.current > 0, "the motor draws current while moving");
    let s = d.wait_until_stopped(Duration::from_secs(3)).await.unwrap();
    assert_eq!((s.object, s.position, s.requested), (Object::AtRequest, 200, 200), "{}", s.describe());
    assert!(!s.object.detected());
    // Slowest speed takes longer over the same stroke: 20 vs 150 mm/s.
    let t = Instant::now();
    d.go_to(100, 0, 100).await.unwrap();
    let s = d.wait_until_stopped(Duration::from_secs(5)).await.unwrap();
    assert_eq!(s.position, 100);
    assert!(t.elapsed() > Duration::from_millis(800), "100 counts (33 mm) at 20 mm/s took {:?}", t.elapsed());
    assert!((counts_to_droid(s.position) - 100.0 / 255.0).abs() < 1e-12);
}

#[tokio::test]
async fn closing_on_an_object_stops_the_fingers_and_reports_it() {
    let emu = Emulated2F85::new(EmulatorConfig::default());
    let (_pty, mut d) = activated(&emu).await;
    emu.place_object(Some(150));
    d.go_to(255, 255, 255).await.unwrap();
    let s = d.wait_until_stopped(Duration::from_secs(3)).await.unwrap();
    assert_eq!(s.object, Object::ContactClosing, "{}", s.describe());
    assert!(s.object.detected());
    assert_eq!((s.position, s.requested), (150, 255));
    assert!(s.current_ma() > 100.0, "holding an object at full force: {} mA", s.current_ma());
    // Opening again releases it and reaches the request.
    d.go_to(0, 255, 255).await.unwrap();
    let s = d.wait_until_stopped(Duration::from_secs(3)).await.unwrap();
    assert_eq!((s.object, s.position), (Object::AtRequest, 0));
}

#[tokio::test]
async fn a_fault_stops_the_gripper_until_it_is_reactivated() {
    let emu = Emulated2F85::new(EmulatorConfig::default());
    let (_pty, mut d) = activated(&emu).await;
    d.go_to(255, 0, 100).await.unwrap();
    tokio::time::sleep(Duration::from_millis(100)).await;
    emu.inject_fault(0x0E);
    let err = d.wait_until_stopped(Duration::from_secs(3)).await.unwrap_err();
    let text = err.to_string();
    assert!(matches!(err, GripperError::Fault { code: 0x0E, .. }), "{text}");
    assert!(text.contains("0x0E") && text.contains("overcurrent"), "{text}");
    let stopped_at = emu.status().position;
    tokio::time::sleep(Duration::from_millis(200)).await;
    assert_eq!(emu.status().position, stopped_at, "a major fault stops the fingers");
    let err = d.go_to(0, 255, 255).await.unwrap_err();
    assert!(matches!(err, GripperError::Fault { code: 0x0E, .. }), "refused while faulted: {err}");
    // Reactivation (reset, then activate) clears it.
    let s = d.activate(Duration::from_secs(5)).await.unwrap();
    assert_eq!(s.fault, 0);
    d.go_to(255, 255, 255).await.unwrap();
    assert_eq!(d.wait_until_stopped(Duration::from_secs(3)).await.unwrap().position, 255);
}

#[tokio::test]
async fn a_silent_gripper_is_a_timeout_naming_it_and_the_link_recovers() {
    let emu = Emulated2F85::new(EmulatorConfig::default());
    let (_pty, mut d) = activated(&emu).await;
    emu.set_mute(true);
    let err = d.status().await.unwrap_err();
    let text = err.to_string();
    assert!(matches!(err, GripperError::Timeout { slave: 9, .. }), "{text}");
    assert!(text.contains("no answer from the 2F-85 (slave 9) to a status read within 100ms"), "{text}");
    let err = d.go_to(255, 255, 255).await.unwrap_err();
    assert!(matches!(err, GripperError::Timeout { what: "a request write", .. }), "{err}");
    emu.set_mute(false);
    let s = d.status().await.unwrap();
    assert_eq!(s.activation, Activation::Complete);
}

#[tokio::test]
async fn a_missing_port_is_named() {
    let err = Robotiq2F85::open(DriverConfig::new("/dev/labrig-no-such-tty")).unwrap_err();
    assert!(err.to_string().contains("cannot open the 2F-85's serial port /dev/labrig-no-such-tty"), "{err}");
}
