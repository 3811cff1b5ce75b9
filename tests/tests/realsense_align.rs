//! Issue 57: a RealSense's depth aligned to colour in Rust, against librealsense itself.
//!
//! A recording made by librealsense's own recorder from its software device
//! (`nodes/cameras/python/realsense_bag.py`: a wall at 1000 mm with a 900 mm block, depth seen
//! with fx x 0.8 from 15 mm along x of the colour camera) gives the calibration through
//! `labrig-cameras realsense-export` (pyrealsense2, the set-up step), then one frameset: its raw
//! Z16 depth and librealsense's `align` to colour. labrig's alignment of the raw depth with the
//! exported calibration must match librealsense's within 1 mm on 99% of the valid pixels.

use labrig_cameras::realsense::{RealSenseCalibration, align_depth_to_colour, z16};
use labrig_tests::{repo_root, workspace_bin};
use std::process::Command;

#[test]
fn depth_aligned_in_rust_matches_librealsense_on_a_recording() {
    let python = labrig_tests::realsense_python();
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    let rec = dir.join("d435.db3");
    let o = Command::new(&python)
        .arg(repo_root().join("nodes/cameras/python/realsense_bag.py"))
        .arg(&rec)
        .args(["--frames", "5", "--width", "640", "--height", "480", "--fx", "612.25", "--fy", "611.75", "--depth"])
        .output()
        .unwrap();
    assert!(o.status.success(), "recording: {}", String::from_utf8_lossy(&o.stderr));

    // The set-up step, as an operator runs it.
    let cal_path = dir.join("rs1.json");
    let o = Command::new(workspace_bin("labrig-cameras", "labrig-cameras"))
        .args(["realsense-export", "--recording"])
        .arg(&rec)
        .arg("--out")
        .arg(&cal_path)
        .env("LABRIG_REALSENSE_PYTHON", &python)
        .output()
        .unwrap();
    assert!(o.status.success(), "realsense-export: {}", String::from_utf8_lossy(&o.stderr));
    let cal = RealSenseCalibration::load(&cal_path).unwrap();
    // What the recording's device was made with.
    assert_eq!(cal.serial, "BAG-000000001");
    assert_eq!((cal.colour.width, cal.colour.height, cal.colour.fx, cal.colour.fy), (640, 480, 612.25, 611.75));
    assert_eq!((cal.colour.ppx, cal.colour.ppy), (319.5, 239.5));
    assert_eq!((cal.depth.fx, cal.depth.fy), ((612.25f64 * 0.8) as f32, (611.75f64 * 0.8) as f32));
    assert_eq!(cal.depth_to_colour.translation, [0.015, 0.0, 0.0]);
    assert_eq!(cal.depth_to_colour.rotation, [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]);
    assert!((cal.depth_scale_m - 0.001).abs() < 1e-9, "{}", cal.depth_scale_m);

    // One frameset: the raw depth and librealsense's alignment of it.
    let frames = dir.join("frames");
    let o = Command::new(&python)
        .arg(repo_root().join("nodes/cameras/python/realsense_export.py"))
        .arg("--file")
        .arg(&rec)
        .arg("--out")
        .arg(dir.join("again.json"))
        .arg("--frames")
        .arg(&frames)
        .output()
        .unwrap();
    assert!(o.status.success(), "frames: {}", String::from_utf8_lossy(&o.stderr));
    let raw = z16(&std::fs::read(frames.join("depth.u16")).unwrap());
    let theirs = z16(&std::fs::read(frames.join("aligned.u16")).unwrap());
    // Z16 as the recording holds it, byte for byte: the wall and the block.
    let wall: Vec<u16> = (0..640 * 480).map(|i| if (400..480).contains(&(i % 640)) { 900 } else { 1000 }).collect();
    assert_eq!(raw, wall, "the raw Z16 frame");

    let ours = align_depth_to_colour(&cal, &raw).unwrap();
    assert_eq!(ours.len(), theirs.len());
    let valid: Vec<(u16, u16)> =
        ours.iter().zip(&theirs).filter(|(a, b)| **a != 0 || **b != 0).map(|(a, b)| (*a, *b)).collect();
    assert!(valid.len() > 640 * 400, "only {} valid pixels", valid.len());
    let close = valid.iter().filter(|(a, b)| a.abs_diff(*b) <= 1).count();
    let share = close as f64 / valid.len() as f64;
    assert!(
        share >= 0.99,
        "{:.3}% of {} valid pixels within 1 mm of librealsense's alignment",
        share * 100.0,
        valid.len()
    );
    // Alignment moved the block (seen from 15 mm along x, with another focal length): the raw
    // depth would not pass.
    let raw_close = raw.iter().zip(&theirs).filter(|(a, b)| a.abs_diff(**b) <= 1).count();
    assert!((raw_close as f64) < 0.97 * 640.0 * 480.0, "the raw depth matches librealsense's alignment: {raw_close}");
    eprintln!("aligned depth: {close} of {} valid pixels within 1 mm ({:.4}%)", valid.len(), share * 100.0);
}

/// A RealSense's colour read in Rust is librealsense's image byte for byte: a YUYV frame of
/// random bytes (every Y, U, V value) through librealsense's own `yuy_decoder` (a software
/// device, tests/peers/realsense_yuyv.py) and through labrig's conversion.
#[test]
fn colour_yuyv_converts_as_librealsense_does_byte_for_byte() {
    let python = labrig_tests::realsense_python();
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    let (w, h) = (640u32, 480u32);
    let o = Command::new(&python)
        .arg(repo_root().join("tests/peers/realsense_yuyv.py"))
        .arg(dir)
        .args(["--width", &w.to_string(), "--height", &h.to_string()])
        .output()
        .unwrap();
    assert!(o.status.success(), "librealsense: {}", String::from_utf8_lossy(&o.stderr));
    let yuyv = std::fs::read(dir.join("yuyv.bin")).unwrap();
    let theirs = std::fs::read(dir.join("rgb.bin")).unwrap();
    assert_eq!((yuyv.len(), theirs.len()), ((w * h * 2) as usize, (w * h * 3) as usize));
    let ours = labrig_cameras::convert::yuyv_to_rgb_librealsense(&yuyv, w, h).unwrap();
    let differ = ours.iter().zip(&theirs).filter(|(a, b)| a != b).count();
    assert_eq!(differ, 0, "{differ} of {} bytes differ from librealsense's", theirs.len());
    // The generic UVC conversion (rounded) is not librealsense's: the test sees the difference.
    let generic = labrig_cameras::convert::yuyv_to_rgb(&yuyv, w, h, None).unwrap();
    let pixels_differing = generic.chunks_exact(3).zip(theirs.chunks_exact(3)).filter(|(a, b)| a != b).count();
    assert!(pixels_differing > (w * h / 2) as usize, "{pixels_differing} pixels differ");
}
