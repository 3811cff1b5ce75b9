//! The camera node (`labrig-cameras run`) against real, independent sources: ffmpeg serving
//! MJPEG over HTTP on 127.0.0.1 (a 2560x720 side-by-side stream: testsrc2 on the left, solid
//! blue on the right, as a ZED's two eyes; and a second, plain camera), read back through
//! shared memory as the loop reads frames, and through DDS by `labrig topic echo` and a real
//! rclpy peer. Killing one ffmpeg marks that camera down on /cameras/status while the other
//! goes on; restarting it brings the camera back.

use labrig_msgs::sensor_msgs::CameraInfo;
use labrig_msgs::std_msgs::StringMsg;
use labrig_msgs::topics;
use labrig_runtime::RosConfig;
use labrig_runtime::frames::{FrameNode, FrameSubscriber};
use labrig_runtime::ros::{Ros, RosSubscription, qos};
use labrig_tests::{Proc, domain_for, labrig_bin, rt, workspace_bin};

use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port()
}

/// ffmpeg serving one MJPEG stream on 127.0.0.1:port/cam (one client, then it exits).
fn ffmpeg_server(port: u16, filter: &str) -> Child {
    Command::new("ffmpeg")
        .args(["-nostdin", "-hide_banner", "-loglevel", "error", "-re", "-f", "lavfi", "-i", filter])
        .args(["-q:v", "5", "-f", "mpjpeg", "-listen", "1"])
        .arg(format!("http://127.0.0.1:{port}/cam"))
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .spawn()
        .expect("ffmpeg (installed by scripts/setup.sh)")
}

/// Left eye: testsrc2; right eye: solid blue.
const STEREO: &str =
    "testsrc2=size=1280x720:rate=15[l];color=c=blue:size=1280x720:rate=15[r];[l][r]hstack=inputs=2[out0]";
const PLAIN: &str = "testsrc2=size=640x480:rate=10";

fn next_frame(sub: &FrameSubscriber, timeout: Duration) -> Option<(u64, i64, u32, u32, Vec<u8>)> {
    let until = Instant::now() + timeout;
    while Instant::now() < until {
        if let Some(f) = sub.receive().unwrap() {
            let h = f.header();
            return Some((h.sequence, h.capture_ns, h.width, h.height, f.pixels().to_vec()));
        }
        std::thread::sleep(Duration::from_millis(5));
    }
    None
}

/// The status's view of one camera, waiting up to `timeout` for `state`.
fn wait_state(status: &RosSubscription<StringMsg>, camera: &str, state: &str, timeout: Duration) -> serde_json::Value {
    let until = Instant::now() + timeout;
    let mut last = serde_json::Value::Null;
    while Instant::now() < until {
        while let Some(m) = status.try_take().unwrap() {
            last = serde_json::from_str(&m.msg.data).unwrap();
            if last["cameras"][camera]["state"] == state {
                return last;
            }
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    panic!("camera {camera} never became {state}; last status: {last}");
}

#[test]
fn stream_cameras_from_ffmpeg_reach_shared_memory_ros_and_rclpy_and_survive_a_restart() {
    let cams = workspace_bin("labrig-cameras", "labrig-cameras");
    let key = "cameras_stream";
    let domain = domain_for(key);
    let ns = format!("cam_{}", std::process::id());
    let (p1, p2) = (free_port(), free_port());
    let mut ff1 = ffmpeg_server(p1, STEREO);
    let mut ff2 = ffmpeg_server(p2, PLAIN);
    let dir = tempfile::tempdir().unwrap();
    let config = dir.path().join("cameras.toml");
    std::fs::write(
        &config,
        format!(
            "stall_s = 0.5\nretry_s = 0.3\npreview_hz = 4.0\n\
             [cameras.ext1]\nsource = \"http://127.0.0.1:{p1}/cam\"\nwidth = 1280\nheight = 720\nside_by_side = true\n\
             intrinsics = {{ width = 2560, height = 1440, fx = 1400.0, fy = 1402.0, cx = 1279.5, cy = 719.5, distortion = [-0.04, 0.01, 0.0, 0.0, 0.0] }}\n\
             extrinsics = [0.2, -0.55, 0.45, -2.1, 0.0, 0.3]\n\
             [cameras.ext2]\nsource = \"http://127.0.0.1:{p2}/cam\"\njpeg_passthrough = true\n"
        ),
    )
    .unwrap();
    let rt = rt();
    let _in_rt = rt.enter();
    let ros_cfg = RosConfig { domain_id: domain, ..RosConfig::default() };
    let mut ros = Ros::new(&ros_cfg, "cameras_test").unwrap();
    let status: RosSubscription<StringMsg> = ros.subscription_on(&topics::CAMERAS_STATUS, 10).unwrap();
    let info: RosSubscription<CameraInfo> = ros.subscription(&topics::camera_info("ext1"), qos::reliable(10)).unwrap();
    let frames = FrameNode::new_in(&ns).unwrap();
    let (sub1, sub2) = (frames.subscriber("ext1").unwrap(), frames.subscriber("ext2").unwrap());

    let mut cmd = Command::new(&cams);
    cmd.args(["run", "--config"]).arg(&config).args(["--domain-id", &domain.to_string(), "--json"]);
    cmd.env(labrig_runtime::frames::NAMESPACE_ENV, &ns);
    let mut node = Proc::spawn("labrig-cameras", cmd);

    // Frames through shared memory: the left eye at 1280x720, increasing capture times.
    let mut last: Option<(u64, i64)> = None;
    for _ in 0..10 {
        let (seq, t, w, h, px) = next_frame(&sub1, Duration::from_secs(20)).expect("ext1 frames");
        assert_eq!((w, h), (1280, 720));
        assert_eq!(px.len(), 1280 * 720 * 3);
        if let Some((s0, t0)) = last {
            assert!(seq > s0 && t > t0, "sequence {s0} -> {seq}, capture {t0} -> {t}");
        }
        last = Some((seq, t));
        // The right eye is solid blue; the left (testsrc2) is mostly not.
        let blue = px.chunks(3).filter(|p| p[2] > 180 && p[0] < 60 && p[1] < 60).count() as f64 / (1280.0 * 720.0);
        assert!(blue < 0.3, "{:.0}% of the published image is the right eye's blue", blue * 100.0);
    }
    // ext2 passes its source's JPEGs through: encoding jpeg, the size from the JPEG's header.
    let until = Instant::now() + Duration::from_secs(20);
    let f2 = loop {
        if let Some(f) = sub2.receive().unwrap() {
            break f;
        }
        assert!(Instant::now() < until, "no ext2 frame");
        std::thread::sleep(Duration::from_millis(5));
    };
    let h2 = *f2.header();
    assert_eq!((h2.width, h2.height), (640, 480), "a camera without a size publishes what its source sends");
    assert_eq!(h2.encoding(), Some(labrig_runtime::frames::FrameEncoding::Jpeg));
    let rgb = labrig_episode::jpeg::decode_rgb(f2.pixels()).expect("a passed-through frame is the server's JPEG");
    assert_eq!((rgb.width, rgb.height), (640, 480));
    drop(f2);

    // camera_info with each frame: the configured intrinsics scaled from 2560x1440 to 1280x720.
    let ci = labrig_tests::first_message(&info, "camera_info for ext1", Duration::from_secs(20));
    assert_eq!((ci.width, ci.height, ci.header.frame_id.as_str()), (1280, 720, "ext1_optical"));
    assert_eq!(ci.k, [700.0, 0.0, 639.5, 0.0, 701.0, 359.5, 0.0, 0.0, 1.0]);
    assert_eq!(ci.d, vec![-0.04, 0.01, 0.0, 0.0, 0.0]);

    // labrig topic echo and a real rclpy peer see camera_info and the preview.
    let echo = Command::new(labrig_bin())
        .args(["topic", "echo", "/cameras/ext1/camera_info", "--count", "1", "--timeout", "20", "--json"])
        .args(["--domain-id", &domain.to_string()])
        .output()
        .unwrap();
    let said = String::from_utf8_lossy(&echo.stdout);
    assert!(echo.status.success() && said.contains("ext1_optical"), "labrig topic echo: {said}");
    let mut peer = Proc::ros_peer(
        domain,
        &[
            "listen",
            "--topic",
            "/cameras/ext1/camera_info",
            "--type",
            "sensor_msgs/msg/CameraInfo",
            "--count",
            "3",
            "--timeout",
            "30",
        ],
    );
    let got = peer.wait_json(Duration::from_secs(40), "camera_info from rclpy", |v| v.get("msg").is_some());
    assert_eq!((got["msg"]["width"].as_u64(), got["msg"]["k"][0].as_f64()), (Some(1280), Some(700.0)), "{got}");
    let mut peer = Proc::ros_peer(
        domain,
        &[
            "listen",
            "--topic",
            "/cameras/ext1/preview/compressed",
            "--type",
            "sensor_msgs/msg/CompressedImage",
            "--count",
            "1",
            "--timeout",
            "30",
        ],
    );
    let got = peer.wait_json(Duration::from_secs(40), "a preview from rclpy", |v| v.get("msg").is_some());
    assert_eq!(got["msg"]["format"], "jpeg", "{got}");
    drop(peer);

    // Kill ext1's source: ext1 goes down, ext2 keeps streaming; restart: ext1 comes back.
    wait_state(&status, "ext1", "streaming", Duration::from_secs(10));
    ff1.kill().unwrap();
    ff1.wait().unwrap();
    let s = wait_state(&status, "ext1", "down", Duration::from_secs(10));
    assert!(s["cameras"]["ext1"]["reason"].as_str().unwrap().contains(&format!("127.0.0.1:{p1}")), "{s}");
    assert_eq!(s["cameras"]["ext2"]["state"], "streaming", "{s}");
    while sub2.receive().unwrap().is_some() {}
    assert!(next_frame(&sub2, Duration::from_secs(5)).is_some(), "ext2 stopped when ext1's source died");
    let before = last.unwrap().0;
    ff1 = ffmpeg_server(p1, STEREO);
    let s = wait_state(&status, "ext1", "streaming", Duration::from_secs(20));
    assert_eq!(s["cameras"]["ext1"]["outages"], 1, "{s}");
    while sub1.receive().unwrap().is_some() {}
    let (seq, ..) = next_frame(&sub1, Duration::from_secs(20)).expect("ext1 frames after the restart");
    assert!(seq > before, "the frame sequence goes on: {before} -> {seq}");

    // A clean stop (SIGINT) reports each camera's frames and outages (`--json`: the run's
    // stats on stdout as it exits).
    let sent = Command::new("kill").args(["-INT", &node.child.id().to_string()]).status().unwrap();
    assert!(sent.success());
    let report = node.wait_json(Duration::from_secs(20), "the stop report", |v| v["cameras"].is_object());
    assert_eq!(node.wait_exit(Duration::from_secs(10)), Some(0), "a clean stop exits 0");
    let cams = report["cameras"].as_object().unwrap();
    assert_eq!(cams.keys().collect::<Vec<_>>(), ["ext1", "ext2"], "{report}");
    assert_eq!((cams["ext1"]["outages"].as_u64(), cams["ext2"]["outages"].as_u64()), (Some(1), Some(0)), "{report}");
    assert!(cams["ext1"]["frames"].as_u64().unwrap() >= seq, "ext1 counted its frames (seq {seq} seen): {report}");
    assert!(cams["ext2"]["frames"].as_u64().unwrap() > 0, "{report}");
    let _ = ff1.kill();
    let _ = ff2.kill();
    let _ = (ff1.wait(), ff2.wait());
}

#[test]
fn a_missing_calibration_file_or_source_is_refused_naming_the_camera() {
    let cams = workspace_bin("labrig-cameras", "labrig-cameras");
    let dir = tempfile::tempdir().unwrap();
    let config = dir.path().join("c.toml");
    // Exit 1 and what the node said, for a config file's text.
    let refused = |text: &str| {
        std::fs::write(&config, text).unwrap();
        let o = Command::new(&cams)
            .args(["run", "--config"])
            .arg(&config)
            .args(["--domain-id", &domain_for("cameras_refusals").to_string()])
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&o.stderr).into_owned();
        assert_eq!(o.status.code(), Some(1), "{err}");
        err
    };
    let err = refused(
        "[cameras.wrist]\nsource = \"http://127.0.0.1:9/cam\"\nwidth = 1280\nheight = 720\nintrinsics = \"calib/SN404.conf\"\n",
    );
    assert!(err.contains("camera wrist: ") && err.contains("calib/SN404.conf"), "{err}");
    // A device by a serial no camera here has (this machine has no V4L2 device at all).
    let err = refused("[cameras.wrist]\nsource = \"zed:SN42\"\nwidth = 1280\nheight = 720\nrectify = false\n");
    assert!(err.contains("camera wrist: no Zed camera with serial SN42 (V4L2 capture devices: "), "{err}");
    // A ZED is rectified unless told otherwise: without its factory file it is refused.
    let err = refused("[cameras.wrist]\nsource = \"zed:SN42\"\nwidth = 1280\nheight = 720\n");
    assert!(
        err.contains("`cameras.wrist.rectify` is on (the default for a ZED)")
            && err.contains("needs the camera's factory file as `intrinsics` (SN<serial>.conf)")
            && err.contains("rectify = false"),
        "{err}"
    );

    let o = Command::new(&cams).args(["run", "--camera", "ext1=/no/such/video.mp4"]).output().unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(err.contains("camera ext1: /no/such/video.mp4: no such video file"), "{err}");
}

/// `labrig launch` of the bench rig (launch_configs/bench_rig.toml): the simulated arm without
/// simulated cameras and the camera node serving five stream cameras; the scripted expert's
/// two episodes are recorded with five camera streams that `labrig inspect` accepts.
#[test]
fn the_bench_rig_records_five_stream_cameras_through_the_camera_node() {
    workspace_bin("labrig-cameras", "labrig-cameras");
    for p in ["labrig-sim", "labrig-recorder", "labrig-control"] {
        workspace_bin(p, p);
    }
    let domain = domain_for("cameras_bench_rig");
    let root = tempfile::tempdir().unwrap();
    let o = Command::new(labrig_bin())
        .args(["launch", "--seconds", "120", "--domain-id", &domain.to_string()])
        .arg(labrig_tests::repo_root().join("launch_configs/bench_rig.toml"))
        .current_dir(root.path())
        .env(labrig_runtime::frames::NAMESPACE_ENV, format!("bench_rig_{}", std::process::id()))
        .output()
        .unwrap();
    let said = format!("{}{}", String::from_utf8_lossy(&o.stdout), String::from_utf8_lossy(&o.stderr));
    assert!(o.status.success() && said.contains("completed the rig's job"), "{said}");
    let episodes = labrig_episode::episode::find_episodes(&root.path().join("episodes"));
    assert_eq!(episodes.len(), 2, "{said}");
    for ep in &episodes {
        // Exit 0, or 3 with flags: on a machine busy with other tests the real-time sim can
        // miss a tick or a stream a frame, which inspect rightly reports; the recording must
        // still be whole.
        let o = Command::new(labrig_bin()).arg("inspect").arg("--json").arg(ep).output().unwrap();
        let said = format!("{}{}", String::from_utf8_lossy(&o.stdout), String::from_utf8_lossy(&o.stderr));
        assert!(matches!(o.status.code(), Some(0 | 3)), "inspect {}: {said}", ep.display());
        let v: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
        assert_eq!(v["complete"], true, "{said}");
        let unexpected: Vec<&str> = v["flags"]
            .as_array()
            .unwrap()
            .iter()
            .filter_map(|f| f.as_str())
            .filter(|f| !f.contains("frames dropped") && !f.contains("missed control ticks"))
            .collect();
        assert!(unexpected.is_empty(), "{unexpected:?}");
        let steps = v["steps"].as_u64().unwrap();
        let cams = v["cameras"].as_array().unwrap();
        let names: Vec<&str> = cams.iter().map(|c| c["camera"].as_str().unwrap()).collect();
        assert_eq!(names, ["ext1", "ext2", "rs1", "rs2", "wrist"], "{v}");
        for c in cams {
            // 30 fps cameras under a 20 Hz loop: more frames than steps, give or take a busy machine.
            assert!(c["frames"].as_u64().unwrap() >= steps * 3 / 4, "{} frames for {steps} steps: {v}", c["frames"]);
        }
        // Every step names the frame it used from each camera, stamped on the rig's clock.
        let data = labrig_episode::read_episode(ep).unwrap();
        let with_all =
            data.steps.iter().filter(|s| s.cameras.len() == 5 && s.cameras.iter().all(|c| c.capture_ns > 0)).count();
        assert!(with_all * 10 >= data.steps.len() * 9, "{with_all} of {} steps have all five frames", data.steps.len());
    }
}

/// The RealSense source: a recording made by librealsense's own recorder from its software
/// device (synthetic frames, no camera; `nodes/cameras/python/realsense_bag.py`), played back
/// through the node's librealsense child: the frames in order (frame k's red channel is k),
/// the device's intrinsics on camera_info, and the depth aligned to the colour image by
/// librealsense on `rs1_depth`; a serial no RealSense has is refused at start.
#[test]
fn a_realsense_recording_plays_through_the_node_with_the_device_intrinsics() {
    let cams = workspace_bin("labrig-cameras", "labrig-cameras");
    let python = labrig_tests::realsense_python();
    let dir = tempfile::tempdir().unwrap();
    let rec = dir.path().join("d435.db3");
    let o = Command::new(&python)
        .arg(labrig_tests::repo_root().join("nodes/cameras/python/realsense_bag.py"))
        .arg(&rec)
        .args(["--frames", "40", "--width", "640", "--height", "480", "--fx", "612.25", "--fy", "611.75", "--depth"])
        .output()
        .unwrap();
    assert!(o.status.success(), "recording: {}", String::from_utf8_lossy(&o.stderr));
    let key = "cameras_realsense";
    let domain = domain_for(key);
    let ns = format!("rs_{}", std::process::id());
    let rt = rt();
    let _in_rt = rt.enter();
    let mut ros = Ros::new(&RosConfig { domain_id: domain, ..RosConfig::default() }, "rs_test").unwrap();
    let info: RosSubscription<CameraInfo> = ros.subscription(&topics::camera_info("rs1"), qos::reliable(10)).unwrap();
    let status: RosSubscription<StringMsg> = ros.subscription_on(&topics::CAMERAS_STATUS, 100).unwrap();
    let frames = FrameNode::new_in(&ns).unwrap();
    let sub = frames.subscriber("rs1").unwrap();
    let depth_sub = frames.subscriber("rs1_depth").unwrap();
    let mut cmd = Command::new(&cams);
    cmd.args(["run", "--camera"])
        .arg(format!("rs1={}", rec.display()))
        .args([
            "--set",
            "cameras.rs1.width=640",
            "--set",
            "cameras.rs1.height=480",
            "--set",
            "cameras.rs1.loop_file=false",
            "--set",
            "cameras.rs1.depth=true",
        ])
        .args(["--domain-id", &domain.to_string()])
        .env(labrig_runtime::frames::NAMESPACE_ENV, &ns)
        .env("LABRIG_REALSENSE_PYTHON", &python);
    let _node = Proc::spawn("labrig-cameras (RealSense)", cmd);
    let mut reds = Vec::new();
    while reds.len() < 20 {
        let Some((seq, _, w, h, px)) = next_frame(&sub, Duration::from_secs(30)) else { break };
        assert_eq!((w, h), (640, 480));
        reds.push((seq, px[0]));
    }
    assert!(reds.len() >= 20, "{} frames from the recording", reds.len());
    let read_until = labrig_runtime::Clock::Wall.now().0;
    // Played in real time a busy machine skips frames (any number of them) or plays one twice,
    // and at the end of the recording the node opens it again (an outage in its status): the
    // sequence always goes up; the red channel (the recording's frame index, 0..39) does not
    // fall within a pass, and starts a new pass (falls) only as often as the node reopened the
    // recording. Frames out of order would fall without a reopen.
    assert!(reds.windows(2).all(|w| w[1].0 > w[0].0), "the frame sequence went backwards: {reds:?}");
    let new_passes = reds.windows(2).filter(|w| w[1].1 < w[0].1).count() as u64;
    let until = Instant::now() + Duration::from_secs(10);
    let outages = 'status: loop {
        while let Some(m) = status.try_take().unwrap() {
            let v: serde_json::Value = serde_json::from_str(&m.msg.data).unwrap();
            if v["stamp_ns"].as_i64().unwrap_or(0) >= read_until {
                break 'status v["cameras"]["rs1"]["outages"].as_u64().expect("the camera's outages");
            }
        }
        assert!(Instant::now() < until, "no camera status after the frames were read");
        std::thread::sleep(Duration::from_millis(20));
    };
    assert!(
        new_passes <= outages,
        "the recording's frames fell {new_passes} times but the node reopened it {outages} times: out of order: {reds:?}"
    );
    let ci = labrig_tests::first_message(&info, "camera_info for rs1", Duration::from_secs(10));
    assert_eq!((ci.k[0], ci.k[4], ci.k[2], ci.k[5]), (612.25, 611.75, 319.5, 239.5), "the device's intrinsics");

    // Depth, aligned: the recording's depth camera (fx x 0.8, 15 mm along x) sees a wall at
    // 1000 mm with a 900 mm block in its columns [400, 480); in the colour image that block
    // lands at u = cx + fx_c (X + 0.015) / Z with X = (u_d - cx) Z / fx_d: columns ~430..530.
    let until = Instant::now() + Duration::from_secs(20);
    let (dh, depth) = loop {
        if let Some(f) = depth_sub.receive().unwrap() {
            break (*f.header(), f.pixels().to_vec());
        }
        assert!(Instant::now() < until, "no rs1_depth frame");
        std::thread::sleep(Duration::from_millis(5));
    };
    assert_eq!((dh.width, dh.height, dh.encoding()), (640, 480, Some(labrig_runtime::frames::FrameEncoding::Depth16)));
    let mm = |u: usize, v: usize| u16::from_le_bytes([depth[(v * 640 + u) * 2], depth[(v * 640 + u) * 2 + 1]]);
    let row: Vec<u16> = [100, 410, 425, 435, 470, 500, 525, 535, 600].iter().map(|&u| mm(u, 240)).collect();
    assert_eq!(row, [1000, 1000, 1000, 900, 900, 900, 900, 1000, 1000], "row 240 of the aligned depth");

    let o = Command::new(&cams)
        .args([
            "run",
            "--camera",
            "rs2=realsense:D435-NOPE",
            "--set",
            "cameras.rs2.width=640",
            "--set",
            "cameras.rs2.height=480",
        ])
        .args(["--domain-id", &domain.to_string()])
        .env("LABRIG_REALSENSE_PYTHON", &python)
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(err.contains("camera rs2: realsense:D435-NOPE: no RealSense with serial D435-NOPE (found: none)"), "{err}");
}
