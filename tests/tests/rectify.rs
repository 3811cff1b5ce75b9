//! Issue 57: a ZED's frames rectified from its factory file as the ZED SDK delivers them,
//! checked against OpenCV itself (opencv-python-headless: stereoRectify, initUndistortRectifyMap,
//! remap, findChessboardCorners; tests/peers/zed_rectify.py).
//!
//! The peer renders a checkerboard on a plane through the committed fixture's factory model
//! (both eyes' distortion, the stereo rotation and translation) into the side-by-side frame a
//! ZED would send, and rectifies it as Stereolabs does; `labrig-cameras rectify` rectifies the
//! same frame through labrig's code.

use labrig_msgs::sensor_msgs::CameraInfo;
use labrig_msgs::topics;
use labrig_runtime::RosConfig;
use labrig_runtime::frames::FrameNode;
use labrig_runtime::ros::{Ros, RosSubscription, qos};
use labrig_tests::{Proc, domain_for, peer_python, repo_root, rt, workspace_bin};
use serde_json::Value;
use std::path::Path;
use std::process::Command;
use std::time::{Duration, Instant};

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

fn read_png_rgb(path: &Path) -> (u32, u32, Vec<u8>) {
    let img = labrig_episode::png::decode_rgb(&std::fs::read(path).unwrap()).unwrap();
    (img.width as u32, img.height as u32, img.pixels)
}

/// The node's own path: a side-by-side frame (the peer's render, played by ffmpeg as a file
/// source, the frame a ZED would send) through `labrig-cameras run` with a ZED's settings: the
/// frame on shared memory is OpenCV's rectified left eye, and camera_info carries the
/// rectified K, zero distortion, R and P.
#[test]
fn the_camera_node_publishes_the_rectified_eye_and_its_camera_info() {
    let cams = workspace_bin("labrig-cameras", "labrig-cameras");
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    peer(&["render", repo_root().join(FIXTURE).to_str().unwrap(), "1280", "720", dir.to_str().unwrap()]);
    let theirs: Value = serde_json::from_slice(&std::fs::read(dir.join("cv.json")).unwrap()).unwrap();
    let config = dir.join("cameras.toml");
    std::fs::write(
        &config,
        format!(
            "[cameras.ext1]\nsource = \"{}\"\nwidth = 1280\nheight = 720\nfps = 10\nside_by_side = true\nrectify = true\nright_eye = true\nintrinsics = \"{}\"\n",
            dir.join("raw.png").display(),
            repo_root().join(FIXTURE).display()
        ),
    )
    .unwrap();
    let domain = domain_for("cameras_zed_rectified");
    let ns = format!("zr_{}", std::process::id());
    let rt = rt();
    let _in_rt = rt.enter();
    let mut ros = Ros::new(&RosConfig { domain_id: domain, ..RosConfig::default() }, "zed_rect_test").unwrap();
    let info: RosSubscription<CameraInfo> = ros.subscription(&topics::camera_info("ext1"), qos::reliable(10)).unwrap();
    let right_info: RosSubscription<CameraInfo> =
        ros.subscription(&topics::camera_info("ext1_right"), qos::reliable(10)).unwrap();
    let tf_static = ros.subscription_on(&topics::TF_STATIC, 10).unwrap();
    let frames = FrameNode::new_in(&ns).unwrap();
    let sub = frames.subscriber("ext1").unwrap();
    let right_sub = frames.subscriber("ext1_right").unwrap();
    let mut cmd = Command::new(&cams);
    cmd.args(["run", "--config"])
        .arg(&config)
        .args(["--domain-id", &domain.to_string()])
        .env(labrig_runtime::frames::NAMESPACE_ENV, &ns);
    let _node = Proc::spawn("labrig-cameras (rectified ZED)", cmd);

    let first_frame = |sub: &labrig_runtime::frames::FrameSubscriber, camera: &str| {
        let until = Instant::now() + Duration::from_secs(60);
        loop {
            if let Some(f) = sub.receive().unwrap() {
                let hd = f.header();
                break (hd.width, hd.height, f.pixels().to_vec());
            }
            assert!(Instant::now() < until, "no {camera} frame from the node");
            std::thread::sleep(Duration::from_millis(5));
        }
    };
    let (w, h, px) = first_frame(&sub, "ext1");
    assert_eq!((w, h), (1280, 720));
    let (cw, ch, cv) = read_png_rgb(&dir.join("cv_left.png"));
    assert_eq!((cw, ch), (1280, 720));
    let within = |ours: &[u8], cv: &[u8]| {
        ours.chunks_exact(3)
            .zip(cv.chunks_exact(3))
            .filter(|(a, b)| a.iter().zip(*b).all(|(x, y)| x.abs_diff(*y) <= 1))
            .count() as f64
            / f64::from(w * h)
    };
    let share = within(&px, &cv);
    assert!(
        share >= 0.99,
        "{:.3}% of the node's pixels within 1 grey level of OpenCV's rectified left eye",
        share * 100.0
    );
    // The right eye (`right_eye`), from the same side-by-side frame, as camera ext1_right.
    let (rw, rh, right_px) = first_frame(&right_sub, "ext1_right");
    assert_eq!((rw, rh), (1280, 720));
    let (_, _, cv_right) = read_png_rgb(&dir.join("cv_right.png"));
    let share = within(&right_px, &cv_right);
    assert!(share >= 0.99, "{:.3}% of ext1_right within 1 grey level of OpenCV's right eye", share * 100.0);
    assert!(within(&right_px, &cv) < 0.9, "the right eye is not the left one");
    // The raw left eye is not that image: the comparison sees rectification.
    let (_, _, raw) = read_png_rgb(&dir.join("raw_left.png"));
    let raw_within = raw
        .chunks_exact(3)
        .zip(cv.chunks_exact(3))
        .filter(|(a, b)| a.iter().zip(*b).all(|(x, y)| x.abs_diff(*y) <= 1))
        .count();
    assert!((raw_within as f64) < 0.9 * f64::from(w * h), "the raw eye matches too: {raw_within} pixels");

    for (eye, sub) in [("left", &info), ("right", &right_info)] {
        let ci = labrig_tests::first_message(sub, &format!("camera_info for the {eye} eye"), Duration::from_secs(20));
        assert_eq!(ci.d, vec![0.0; 5], "rectified: no distortion");
        let theirs = &theirs[eye];
        for (key, ours) in [("k", ci.k.to_vec()), ("r", ci.r.to_vec()), ("p", ci.p.to_vec())] {
            let cv = numbers(&theirs[key]);
            assert_eq!(ours.len(), cv.len(), "{eye} {key}");
            for (x, y) in ours.iter().zip(cv) {
                assert!(
                    (x - y).abs() <= 1e-6 * y.abs().max(1.0),
                    "{eye} camera_info {key}: {ours:?} vs OpenCV {}",
                    theirs[key]
                );
            }
        }
    }
    // /tf_static: the right eye's optical frame the rectified baseline along the left's x.
    let tf = labrig_tests::first_message(&tf_static, "/tf_static", Duration::from_secs(20));
    let right = tf.transforms.iter().find(|t| t.child_frame_id == "ext1_right_optical").expect("ext1_right_optical");
    assert_eq!(right.header.frame_id, "ext1_optical");
    let p = numbers(&theirs["right"]["p"]);
    let baseline_m = -p[3] / p[0];
    let t = &right.transform.translation;
    assert!((t.x - baseline_m).abs() < 1e-9 && t.y == 0.0 && t.z == 0.0, "{t:?} vs baseline {baseline_m} m");
    assert!((0.05..0.2).contains(&baseline_m), "a ZED's baseline: {baseline_m} m");
    assert_eq!(right.transform.rotation.w, 1.0);
}
