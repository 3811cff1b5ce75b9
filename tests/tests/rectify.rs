//! Issue 57: a ZED's frames rectified from its factory file as the ZED SDK delivers them,
//! checked against OpenCV itself (opencv-python-headless: stereoRectify, initUndistortRectifyMap,
//! remap, findChessboardCorners; tests/peers/zed_rectify.py).
//!
//! The peer renders a checkerboard on a plane through the committed fixture's factory model
//! (both eyes' distortion, the stereo rotation and translation) into the side-by-side frame a
//! ZED would send, and rectifies it as Stereolabs does; `labrig-cameras rectify` rectifies the
//! same frame through labrig's code.

use labrig_tests::{peer_python, repo_root, workspace_bin};
use serde_json::Value;
use std::path::Path;
use std::process::Command;

const FIXTURE: &str = "nodes/cameras/tests/fixtures/SN000012345.conf";

fn peer(args: &[&str]) -> Value {
    let out = Command::new(peer_python("LABRIG_OPENCV_PYTHON", "venv-opencv"))
        .arg(repo_root().join("tests/peers/zed_rectify.py"))
        .args(args)
        .output()
        .expect("running zed_rectify.py");
    assert!(
        out.status.success(),
        "zed_rectify.py {args:?} failed: {}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    let text = String::from_utf8_lossy(&out.stdout);
    if text.trim().is_empty() {
        Value::Null
    } else {
        serde_json::from_str(text.trim()).expect("JSON from zed_rectify.py")
    }
}

fn rectify_with_labrig(dir: &Path) -> Value {
    let out = Command::new(workspace_bin("labrig-cameras", "labrig-cameras"))
        .args(["rectify", "--intrinsics"])
        .arg(repo_root().join(FIXTURE))
        .arg("--input")
        .arg(dir.join("raw.png"))
        .arg("--out")
        .arg(dir)
        .output()
        .expect("running labrig-cameras rectify");
    assert!(out.status.success(), "labrig-cameras rectify failed: {}", String::from_utf8_lossy(&out.stderr));
    serde_json::from_slice(&std::fs::read(dir.join("rectification.json")).unwrap()).unwrap()
}

fn numbers(v: &Value) -> Vec<f64> {
    v.as_array().expect("an array").iter().map(|x| x.as_f64().expect("a number")).collect()
}

#[test]
fn labrig_rectifies_a_zed_frame_as_opencv_does() {
    for (w, h) in [(1280u32, 720u32), (672, 376)] {
        let tmp = tempfile::tempdir().unwrap();
        let dir = tmp.path();
        let (ws, hs) = (w.to_string(), h.to_string());
        peer(&["render", repo_root().join(FIXTURE).to_str().unwrap(), &ws, &hs, dir.to_str().unwrap()]);
        let ours = rectify_with_labrig(dir);
        let theirs: Value = serde_json::from_slice(&std::fs::read(dir.join("cv.json")).unwrap()).unwrap();
        for eye in ["left", "right"] {
            // K, R and P as OpenCV computes them (P by ROS's convention: Tx = -fx * B for the
            // right eye), to 1e-6 relative; zero distortion.
            for key in ["k", "r", "p"] {
                let (a, b) = (numbers(&ours[eye][key]), numbers(&theirs[eye][key]));
                assert_eq!(a.len(), b.len(), "{w}x{h} {eye} {key}");
                for (i, (x, y)) in a.iter().zip(&b).enumerate() {
                    assert!(
                        (x - y).abs() <= 1e-6 * y.abs().max(1.0),
                        "{w}x{h} {eye} {key}[{i}]: labrig {x}, OpenCV {y}"
                    );
                }
            }
            assert!(numbers(&ours[eye]["d"]).iter().all(|&d| d == 0.0), "{eye}: a rectified image has no distortion");
        }
        let p_right = numbers(&ours["right"]["p"]);
        assert!(p_right[3] < 0.0 && (p_right[3] / -p_right[0] - 0.11998).abs() < 1e-3, "right P's Tx: {}", p_right[3]);

        // The images: within 1 grey level of OpenCV's on 99% of the pixels (the image border
        // aside: where the source lies within a pixel of the raw image's edge).
        let cmp = peer(&["compare", dir.to_str().unwrap()]);
        for eye in ["left", "right"] {
            let c = &cmp[eye];
            let pixels = c["pixels"].as_u64().unwrap();
            assert!(pixels as f64 > 0.95 * f64::from(w * h), "{w}x{h} {eye}: only {pixels} pixels compared");
            let within = c["within_1"].as_f64().unwrap();
            assert!(
                within >= 0.99,
                "{w}x{h} {eye}: {:.4}% within 1 grey level of OpenCV's (max diff {})",
                within * 100.0,
                c["max_diff"]
            );
        }

        // Rows are epipolar lines: the checkerboard's corners, found by OpenCV in labrig's left
        // and right images, lie on the same rows; in the raw pair they do not.
        let rect = peer(&["corners", dir.join("left.png").to_str().unwrap(), dir.join("right.png").to_str().unwrap()]);
        let raw =
            peer(&["corners", dir.join("raw_left.png").to_str().unwrap(), dir.join("raw_right.png").to_str().unwrap()]);
        let (dy, dy_raw) = (rect["mean_dy"].as_f64().unwrap(), raw["mean_dy"].as_f64().unwrap());
        assert_eq!(rect["corners"].as_u64(), Some(54), "{rect}");
        assert!(dy < 0.1, "{w}x{h}: rectified corners {dy:.3} px apart vertically (goal: under 0.1)");
        assert!(
            dy_raw > 1.0,
            "{w}x{h}: the raw pair's corners are only {dy_raw:.3} px apart: the test scene shows nothing"
        );
        eprintln!("{w}x{h}: vertical disparity {dy:.4} px rectified, {dy_raw:.2} px raw; {cmp}");
    }
}
