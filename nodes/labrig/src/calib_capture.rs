//! `labrig calibrate capture --rig <launch config> --camera C --out DIR`: a live rig takes one
//! camera's calibration views, as DROID's rig does. The rig's hardware nodes are started from
//! its launch config (the arm, the gripper, the cameras, or the sim bridge standing in for
//! them; never the rig loop, the recorder, the teleop node or the policy server, which would
//! command the arm too), then the arm is driven over DROID's pose set
//! (`labrig_arm::calib_path`) by joint targets on `/arm/command`, through the franka node's
//! safety layer like every command. Before each view the arm is still for 0.5 s (by the arm's
//! own stamps); the view is the first frame captured after that, saved with the TCP pose the
//! arm reports (`/arm/state`). The capture folder (`capture.json`, `view_NNN.pgm`) is what
//! `labrig calibrate solve` reads; `labrig calibrate --rig` runs both.
//!
//! On a simulated rig (a `labrig-sim` node in the config) the bridge is told to put the board
//! in the scene (held by the gripper for an external camera, on the table for the wrist
//! camera), to render only this camera at the real cameras' 1280x720 a few times a second, and
//! to publish the scene's camera poses (any calibration it was given is left out): those are
//! then the truth the report compares against.

use anyhow::{Context, bail};
use clap::{Args, ValueEnum};
use labrig_arm::calib_path;
use labrig_arm::ik::{Ik, IkConfig, pose_from_xyz_euler};
use labrig_arm::safety::{SafetyConfig, SafetyFilter};
use labrig_arm::{Fr3Kinematics, Joints, TcpOffset};
use labrig_launch::config::LaunchConfig;
use labrig_launch::supervise::Output;
use labrig_msgs::Nanos;
use labrig_msgs::calibration::{
    BoardSpec, CAPTURE_VERSION, CaptureFile, CaptureTruth, CapturedView, Intrinsics, Mount, Pose,
};
use labrig_msgs::rig::{ArmCommand, ArmCommandMode, RIG_CAMERAS, RobotState};
use labrig_msgs::sensor_msgs::CameraInfo;
use labrig_msgs::std_msgs::StringMsg;
use labrig_msgs::tf2_msgs::TFMessage;
use labrig_msgs::topics;
use labrig_runtime::frames::{FrameEncoding, FrameNode, FrameSubscriber};
use labrig_runtime::ros::{Ros, RosPublisher, RosSubscription, qos};
use labrig_runtime::{RosConfig, Shutdown};
use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion, Vector3};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::{Duration, Instant};

/// The programs a capture never starts: they command the arm or record.
const NOT_STARTED: [&str; 5] =
    ["labrig-control", "labrig-recorder", "labrig-teleop", "labrig-policy", "labrig-station"];
/// Command period (wall clock), as the rig loop's.
const PERIOD: Duration = Duration::from_millis(50);
/// DROID pauses 0.5 s before each view (the arm's time).
const SETTLE_NS: i64 = 500_000_000;
/// A pose counts as reached when every joint is this close to its target (rad).
const REACH_RAD: f64 = 0.002;
/// Time (the arm's) allowed to reach a pose of the set.
const REACH_NS: i64 = 4_000_000_000;
/// Time (the arm's) allowed for a frame after the pause.
const FRAME_NS: i64 = 5_000_000_000;
/// Wall time without a new arm state or frame after which the rig counts as stopped.
const SILENCE: Duration = Duration::from_secs(30);
/// Wall time allowed for the rig to come up.
const STARTUP: Duration = Duration::from_secs(180);
/// A simulated rig renders the calibrated camera this often (frames per second of sim time).
const SIM_CAMERA_HZ: f64 = 4.0;

#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum Start {
    /// `camera` where the rig publishes the camera's and the board's poses, else `here`.
    Auto,
    /// Around a pose facing the camera, found from the rig's published camera and board poses
    /// (`/tf_static`: the rig config's extrinsics, the board's nominal mount).
    Camera,
    /// Around the arm's pose now (the operator put the board in view, as with DROID's GUI).
    Here,
}

#[derive(Debug, Args)]
pub struct CaptureArgs {
    /// The rig: a launch config, whose hardware nodes are started for the capture.
    #[arg(long)]
    pub rig: PathBuf,
    /// ext1, ext2, wrist, rs1 or rs2.
    #[arg(long)]
    pub camera: String,
    /// The capture folder (created): capture.json and the views.
    #[arg(long)]
    pub out: PathBuf,
    /// Views (DROID takes ~60).
    #[arg(long, default_value_t = 60)]
    pub views: usize,
    /// The board (JSON, labrig_msgs::calibration::BoardSpec); default DROID's.
    #[arg(long)]
    pub board: Option<PathBuf>,
    /// The board's print (PNG, edge to edge) a simulated rig puts in its scene.
    #[arg(long)]
    pub print: Option<PathBuf>,
    /// The print's width,height (m) when it is not the board `--board` describes.
    #[arg(long, value_delimiter = ',')]
    pub print_size_m: Option<Vec<f64>>,
    /// Where the pose set is centred.
    #[arg(long, value_enum, default_value_t = Start::Auto)]
    pub start: Start,
    /// DDS domain (default: the launch config's).
    #[arg(long)]
    pub domain_id: Option<u16>,
    /// A simulated rig moves the camera by dx,dy,dz (m, base frame) first: a knocked camera.
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true)]
    pub move_camera: Option<Vec<f64>>,
    /// The point external cameras look at (the table centre, base frame, m): the start pose
    /// holds the board on the line from the camera to it.
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true, default_value = "0.5,0,0")]
    pub aim: Vec<f64>,
    /// Size a simulated rig renders the camera at (the real cameras' 1280x720).
    #[arg(long, default_value_t = 1280)]
    pub width: usize,
    #[arg(long, default_value_t = 720)]
    pub height: usize,
    /// One JSON line on stdout, no progress bar.
    #[arg(long)]
    pub json: bool,
}

pub fn run(a: CaptureArgs) -> anyhow::Result<ExitCode> {
    let camera =
        RIG_CAMERAS.iter().copied().find(|c| *c == a.camera).with_context(|| {
            format!("unknown camera `{}` (the rig's cameras: {})", a.camera, RIG_CAMERAS.join(", "))
        })?;
    anyhow::ensure!((1..=500).contains(&a.views), "--views must be in 1..=500");
    let board: BoardSpec = match &a.board {
        None => BoardSpec::droid(),
        Some(p) => {
            serde_json::from_str(&std::fs::read_to_string(p).with_context(|| format!("reading {}", p.display()))?)
                .with_context(|| format!("{} is not a board spec (JSON)", p.display()))?
        }
    };
    board.validate().map_err(|e| anyhow::anyhow!("board: {e}"))?;
    let mount = if camera == "wrist" { Mount::EyeInHand } else { Mount::EyeToHand };
    let (cfg, order, sim) = rig_for_capture(&a, camera, mount, &board)?;
    let dir = a.rig.parent().unwrap_or(Path::new(".")).to_owned();
    let domain = a.domain_id.unwrap_or(cfg.rig.domain_id);
    std::fs::create_dir_all(&a.out).with_context(|| format!("creating {}", a.out.display()))?;
    let rig_name = cfg.rig.name.clone();
    let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build()?;
    let shutdown = Shutdown::new();
    let result = rt.block_on(async {
        shutdown.trigger_on_signals()?;
        let rig = tokio::spawn(labrig_launch::supervise::supervise_until(
            cfg,
            order,
            dir,
            domain,
            None,
            Output::Quiet,
            shutdown.clone(),
        ));
        let captured = capture(&a, camera, mount, &board, domain, sim, &shutdown, &rig).await;
        shutdown.trigger();
        let stopped = rig.await;
        match (captured, stopped) {
            (Ok(c), Ok(Ok(_))) => Ok(c),
            (Err(e), _) => Err(e),
            (Ok(_), Ok(Err(e))) => Err(e.context("the rig")),
            (Ok(_), Err(e)) => Err(anyhow::anyhow!("the rig's supervisor: {e}")),
        }
    });
    drop(rt);
    let mut file = result?;
    file.rig = rig_name;
    let path = a.out.join("capture.json");
    std::fs::write(&path, serde_json::to_string_pretty(&file)?)
        .with_context(|| format!("writing {}", path.display()))?;
    if a.json {
        println!(
            "{}",
            serde_json::json!({"camera": camera, "views": file.views.len(), "unreachable": file.unreachable,
                "capture": path, "simulated": file.sim_scene.is_some()})
        );
    } else {
        println!(
            "{camera}: {} views, {} poses unreachable (skipped) -> {}",
            file.views.len(),
            file.unreachable,
            path.display()
        );
    }
    Ok(ExitCode::SUCCESS)
}

/// The launch config with only the hardware nodes, and the sim told what calibration needs.
/// Returns it, its start order, and whether the rig is simulated.
fn rig_for_capture(
    a: &CaptureArgs,
    camera: &str,
    mount: Mount,
    board: &BoardSpec,
) -> anyhow::Result<(LaunchConfig, Vec<usize>, bool)> {
    let (mut cfg, _) = LaunchConfig::load(&a.rig)?;
    cfg.nodes.retain(|n| !NOT_STARTED.contains(&n.program.as_str()));
    let kept: Vec<String> = cfg.nodes.iter().map(|n| n.name.clone()).collect();
    for n in &mut cfg.nodes {
        n.after.retain(|d| kept.contains(d));
        // The rig's job is calibration now: no node's exit completes it.
        n.completes = false;
    }
    anyhow::ensure!(
        cfg.nodes.iter().any(|n| ["labrig-franka", "labrig-sim"].contains(&n.program.as_str())),
        "{} starts no arm (a labrig-franka or labrig-sim node)",
        a.rig.display()
    );
    let mut simulated = false;
    for n in cfg.nodes.iter_mut().filter(|n| n.program == "labrig-sim") {
        simulated = true;
        let print = a.print.as_ref().context("a simulated rig needs the board's print (--print board.png)")?;
        let print = std::fs::canonicalize(print).with_context(|| format!("--print {}", print.display()))?;
        let size = match &a.print_size_m {
            Some(v) => match v.as_slice() {
                [w, h] => [*w, *h],
                _ => bail!("--print-size-m takes width,height (2 numbers), not {v:?}"),
            },
            None => board.size_m(),
        };
        // The scene's own camera poses on /tf_static: they are the truth the report uses.
        drop_flag(&mut n.args, "--calibration");
        drop_set(&mut n.args, "calibration");
        labrig_launch::sim::set_arg(&mut n.args, "--width", &a.width.to_string());
        labrig_launch::sim::set_arg(&mut n.args, "--height", &a.height.to_string());
        let mount = if mount == Mount::EyeInHand { "table" } else { "gripper" };
        n.args.extend([
            "--set".into(),
            format!(
                "calib_board={{print = {:?}, size_m = [{}, {}], mount = {mount:?}}}",
                print.display().to_string(),
                size[0],
                size[1]
            ),
            "--set".into(),
            format!("only_cameras=[{camera:?}]"),
            "--set".into(),
            format!("camera_rate_hz={SIM_CAMERA_HZ}"),
        ]);
        if let Some(m) = &a.move_camera {
            let [x, y, z] = m.as_slice() else { bail!("--move-camera takes dx,dy,dz (3 numbers), not {m:?}") };
            n.args.extend(["--set".into(), format!("move_camera={{camera = {camera:?}, shift_m = [{x}, {y}, {z}]}}")]);
        }
    }
    if !simulated && a.move_camera.is_some() {
        bail!("--move-camera moves a simulated camera; {} has no labrig-sim node", a.rig.display());
    }
    let order = cfg.validate(a.rig.parent().unwrap_or(Path::new(".")))?;
    Ok((cfg, order, simulated))
}

/// Removes every `--set <key>=...` (the pair) from `args`.
fn drop_set(args: &mut Vec<String>, key: &str) {
    let prefix = format!("{key}=");
    while let Some(i) = args.windows(2).position(|w| w[0] == "--set" && w[1].starts_with(&prefix)) {
        args.drain(i..i + 2);
    }
}

/// Removes `flag` and its value from `args`.
fn drop_flag(args: &mut Vec<String>, flag: &str) {
    while let Some(i) = args.iter().position(|x| x == flag) {
        args.drain(i..(i + 2).min(args.len()));
    }
}

fn iso_of(t: &labrig_msgs::geometry_msgs::Transform) -> Isometry3<f64> {
    let (p, q) = (&t.translation, &t.rotation);
    Isometry3::from_parts(
        Translation3::new(p.x, p.y, p.z),
        UnitQuaternion::from_quaternion(Quaternion::new(q.w, q.x, q.y, q.z)),
    )
}

fn pose_of(iso: &Isometry3<f64>) -> Pose {
    let q = iso.rotation.quaternion();
    Pose { position: iso.translation.vector.into(), quaternion_wxyz: [q.w, q.i, q.j, q.k] }
}

/// What the capture reads from the rig.
struct Link {
    state: RosSubscription<RobotState>,
    tf_static: RosSubscription<TFMessage>,
    tf: RosSubscription<TFMessage>,
    info: RosSubscription<CameraInfo>,
    scene: RosSubscription<StringMsg>,
    calibration: RosSubscription<StringMsg>,
    command: RosPublisher<ArmCommand>,
    frames: Option<FrameSubscriber>,
    frame_node: FrameNode,
    camera: &'static str,
    /// The newest arm state, and when it arrived.
    last: Option<(RobotState, Instant)>,
    last_frame_at: Instant,
    /// child -> (parent, pose), from /tf_static.
    statics: BTreeMap<String, (String, Isometry3<f64>)>,
    /// tcp -> wrist_optical from a /tf message carrying both.
    wrist_in_tcp: Option<Isometry3<f64>>,
    info_msg: Option<CameraInfo>,
    scene_msg: Option<serde_json::Value>,
    calibrated: Vec<String>,
    seq: u64,
}

/// A frame copied out of shared memory, as 8-bit grey.
struct Grey {
    width: usize,
    height: usize,
    pixels: Vec<u8>,
}

impl Link {
    fn new(ros: &mut Ros, camera: &'static str) -> anyhow::Result<Link> {
        Ok(Link {
            state: ros.subscription_on(&topics::ARM_STATE, 10)?,
            tf_static: ros.subscription_on(&topics::TF_STATIC, 10)?,
            tf: ros.subscription_on(&topics::TF, 10)?,
            info: ros.subscription(&topics::camera_info(camera), qos::reliable(10))?,
            scene: ros.subscription_on(&topics::SIM_SCENE, 1)?,
            calibration: ros.subscription_on(&topics::CALIBRATION, 1)?,
            command: ros.publisher_on(&topics::ARM_COMMAND, 10)?,
            frames: None,
            // The rig's frames: in the namespace its supervisor gave it (one per domain).
            frame_node: FrameNode::new_in(&labrig_launch::supervise::frames_namespace(ros.domain_id()))?,
            camera,
            last: None,
            last_frame_at: Instant::now(),
            statics: BTreeMap::new(),
            wrist_in_tcp: None,
            info_msg: None,
            scene_msg: None,
            calibrated: Vec::new(),
            seq: 0,
        })
    }

    /// Takes what arrived on every topic (malformed messages are errors: they name the topic).
    fn poll(&mut self) -> anyhow::Result<()> {
        while let Some(m) = self.state.try_take()? {
            self.last = Some((m.msg, Instant::now()));
        }
        while let Some(m) = self.tf_static.try_take()? {
            for t in m.msg.transforms {
                self.statics.insert(t.child_frame_id.clone(), (t.header.frame_id.clone(), iso_of(&t.transform)));
            }
        }
        while let Some(m) = self.tf.try_take()? {
            let find = |child: &str| m.msg.transforms.iter().find(|t| t.child_frame_id == child);
            if let (Some(tcp), Some(cam)) = (find("tcp"), find("wrist_optical")) {
                self.wrist_in_tcp = Some(iso_of(&tcp.transform).inverse() * iso_of(&cam.transform));
            }
        }
        while let Some(m) = self.info.try_take()? {
            self.info_msg = Some(m.msg);
        }
        while let Some(m) = self.scene.try_take()? {
            self.scene_msg = serde_json::from_str(&m.msg.data).ok();
        }
        while let Some(m) = self.calibration.try_take()? {
            if let Ok(serde_json::Value::Object(o)) = serde_json::from_str::<serde_json::Value>(&m.msg.data) {
                self.calibrated = o.keys().cloned().collect();
            }
        }
        if self.frames.is_none() {
            // The camera's shared-memory service exists once its node (or the sim) is up.
            self.frames = self.frame_node.subscriber(self.camera).ok();
        }
        Ok(())
    }

    /// The first frame captured at or after `after_ns` (older ones are dropped), as grey.
    fn frame_after(&mut self, after_ns: i64) -> anyhow::Result<Option<Grey>> {
        let Some(sub) = &self.frames else { return Ok(None) };
        while let Some(f) = sub.receive()? {
            self.last_frame_at = Instant::now();
            let h = *f.header();
            if h.capture_ns >= after_ns {
                return Ok(Some(grey(&h, f.pixels()).with_context(|| format!("a frame of `{}`", self.camera))?));
            }
        }
        Ok(None)
    }

    fn state(&self) -> Option<&RobotState> {
        self.last.as_ref().map(|(s, _)| s)
    }

    /// The arm's time now: its last state's stamp plus the wall time since, at most a period.
    fn now(&self) -> Nanos {
        match &self.last {
            Some((s, at)) => {
                Nanos(Nanos::from(s.header.stamp).0 + (at.elapsed().as_nanos() as i64).min(PERIOD.as_nanos() as i64))
            }
            None => Nanos::ZERO,
        }
    }

    /// Joint targets on /arm/command (the franka node's safety layer checks and limits them).
    fn command(&mut self, q: &Joints) -> anyhow::Result<()> {
        self.seq += 1;
        let mut cmd = ArmCommand {
            mode: ArmCommandMode::JointPosition as u8,
            joint_position: *q,
            // Where the gripper is: a rig whose arm command also drives the gripper keeps it.
            gripper_position: self.state().map(|s| s.gripper_position.clamp(0.0, 1.0)).unwrap_or(0.0),
            seq: self.seq,
            ..ArmCommand::default()
        };
        cmd.header.stamp = self.now().into();
        self.command.publish(cmd)?;
        Ok(())
    }

    /// Fails when the rig stopped talking.
    fn alive(&self) -> anyhow::Result<()> {
        if let Some((_, at)) = &self.last
            && at.elapsed() > SILENCE
        {
            bail!("the arm has sent no /arm/state for {} s", SILENCE.as_secs());
        }
        if self.last_frame_at.elapsed() > SILENCE {
            bail!("camera `{}` has sent no frame for {} s (disconnected?)", self.camera, SILENCE.as_secs());
        }
        Ok(())
    }
}

/// A frame as 8-bit grey (BT.601 luma).
fn grey(h: &labrig_runtime::frames::FrameHeader, px: &[u8]) -> anyhow::Result<Grey> {
    let (w, ht, stride) = (h.width as usize, h.height as usize, h.stride as usize);
    let luma = labrig_episode::grey::luma;
    let enc = h.encoding().context("unknown frame encoding")?;
    let rows = |bpp: usize| -> anyhow::Result<Vec<&[u8]>> {
        let stride = if stride == 0 { w * bpp } else { stride };
        anyhow::ensure!(px.len() >= stride * (ht.max(1) - 1) + w * bpp, "{} bytes for {w}x{ht}", px.len());
        Ok((0..ht).map(|y| &px[y * stride..y * stride + w * bpp]).collect())
    };
    let pixels: Vec<u8> = match enc {
        FrameEncoding::Rgb8 => {
            rows(3)?.iter().flat_map(|r| r.chunks_exact(3).map(|p| luma(p[0], p[1], p[2]))).collect()
        }
        FrameEncoding::Bgr8 => {
            rows(3)?.iter().flat_map(|r| r.chunks_exact(3).map(|p| luma(p[2], p[1], p[0]))).collect()
        }
        FrameEncoding::Mono8 => rows(1)?.concat(),
        FrameEncoding::Jpeg => {
            let rgb = labrig_episode::jpeg::decode_rgb(px)?;
            return Ok(Grey {
                width: rgb.width,
                height: rgb.height,
                pixels: labrig_episode::grey::from_rgb(&rgb.pixels),
            });
        }
        FrameEncoding::Depth16 => bail!("a depth stream cannot be calibrated; name the colour camera"),
    };
    Ok(Grey { width: w, height: ht, pixels })
}

fn write_pgm(path: &Path, g: &Grey) -> anyhow::Result<()> {
    labrig_episode::grey::write_pgm(path, g.width, g.height, &g.pixels)
        .with_context(|| format!("writing {}", path.display()))
}

fn intrinsics_of(info: &CameraInfo) -> Intrinsics {
    Intrinsics {
        width: info.width,
        height: info.height,
        fx: info.k[0],
        fy: info.k[4],
        cx: info.k[2],
        cy: info.k[5],
        distortion: info.d.clone(),
        source: "camera_info".into(),
    }
}

/// Waits (polling, sending nothing) until `ready` holds, failing when the rig stops.
async fn wait_for(
    link: &mut Link,
    what: &str,
    rig: &tokio::task::JoinHandle<anyhow::Result<ExitCode>>,
    shutdown: &Shutdown,
    mut ready: impl FnMut(&mut Link) -> anyhow::Result<bool>,
) -> anyhow::Result<()> {
    let t0 = Instant::now();
    loop {
        link.poll()?;
        if ready(link)? {
            return Ok(());
        }
        if rig.is_finished() {
            bail!("the rig stopped while waiting for {what} (its nodes' errors are above)");
        }
        if shutdown.is_triggered() {
            bail!("interrupted");
        }
        if t0.elapsed() > STARTUP {
            bail!("no {what} within {} s of starting the rig", STARTUP.as_secs());
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
}

#[allow(clippy::too_many_arguments)] // one capture's settings, passed once
async fn capture(
    a: &CaptureArgs,
    camera: &'static str,
    mount: Mount,
    board: &BoardSpec,
    domain: u16,
    simulated: bool,
    shutdown: &Shutdown,
    rig: &tokio::task::JoinHandle<anyhow::Result<ExitCode>>,
) -> anyhow::Result<CaptureFile> {
    let ros_cfg = RosConfig { domain_id: domain, ..RosConfig::default() };
    let mut ros = Ros::new(&ros_cfg, "labrig_calibrate")?;
    let mut link = Link::new(&mut ros, camera)?;
    wait_for(&mut link, "/arm/state", rig, shutdown, |l| Ok(l.last.is_some())).await?;
    wait_for(&mut link, &format!("{} and a frame", topics::camera_info(camera)), rig, shutdown, |l| {
        Ok(l.info_msg.is_some() && l.frame_after(i64::MIN)?.is_some())
    })
    .await?;
    link.last_frame_at = Instant::now();
    // Latched topics (the scene, calibrations, the static transforms) a moment to arrive.
    let settle = Instant::now();
    while settle.elapsed() < Duration::from_millis(500) {
        link.poll()?;
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    let info = link.info_msg.clone().expect("waited for");
    let intrinsics = intrinsics_of(&info);

    let kin = Fr3Kinematics::from_urdf_file(&labrig_arm::urdf_path(None), TcpOffset::ROBOTIQ_2F85)?;
    let safety = SafetyFilter::new(Ik::new(kin, IkConfig::default()), SafetyConfig::default())
        .map_err(|e| anyhow::anyhow!("safety layer: {e}"))?;
    let state = link.state().expect("waited for").clone();
    let tcp_now = pose_from_xyz_euler(&state.cartesian_position);
    let reset: Joints = state.joint_positions;
    let amp_rad = match mount {
        Mount::EyeToHand => calib_path::AMPLITUDE_RAD,
        Mount::EyeInHand => calib_path::AMPLITUDE_RAD / calib_path::WRIST_ANGLE_DIVISOR,
    };
    let amp_m = calib_path::AMPLITUDE_M;
    let (start, pivot, published_camera, published_board) =
        start_pose(a, camera, mount, board, &link, &safety, (&tcp_now, &reset), (amp_m, amp_rad))?;
    let poses = calib_path::pose_set(&start, &pivot, a.views, amp_m, amp_rad);
    let bar =
        labrig_episode::progress::bar(&format!("{{bar:30}} {{pos}}/{{len}} {camera} views"), a.views as u64, a.json);
    let mut views = Vec::new();
    let mut unreachable = 0usize;
    let mut faults: BTreeMap<String, usize> = BTreeMap::new();
    let mut last_q = reset;
    let mut tick = tokio::time::interval(PERIOD);
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    for (i, want) in poses.iter().enumerate() {
        let Some(q) = calib_path::joints_for(&safety, &last_q, want) else {
            unreachable += 1;
            bar.inc(1);
            continue;
        };
        let view = drive_to_view(&mut link, &q, camera, &mut tick, &mut faults, shutdown, rig).await?;
        bar.inc(1);
        let Some((g, s)) = view else {
            unreachable += 1;
            continue;
        };
        last_q = q;
        let image = format!("view_{i:03}.pgm");
        write_pgm(&a.out.join(&image), &g)?;
        views.push(CapturedView { image, tcp: pose_of(&pose_from_xyz_euler(&s.cartesian_position)) });
    }
    bar.finish_and_clear();
    for (fault, n) in &faults {
        eprintln!("{camera}: {n} poses not reached; the arm said: {fault}");
    }
    // The sim's scene poses are the truth, unless the rig published a calibration of its own.
    let sim_scene =
        link.scene_msg.as_ref().filter(|_| simulated).and_then(|s| {
            Some(labrig_msgs::calibration::sim_scene_name(s["spec"]["name"].as_str()?, s["seed"].as_u64()?))
        });
    let truth = match (&sim_scene, published_camera, &published_board) {
        (Some(_), Some(cam), Some((_, b))) if !link.calibrated.iter().any(|c| c == camera) => {
            Some(CaptureTruth { camera: pose_of(&cam), board: pose_of(b) })
        }
        _ => None,
    };
    Ok(CaptureFile {
        version: CAPTURE_VERSION,
        rig: String::new(),
        camera: camera.to_owned(),
        mount,
        board: board.clone(),
        intrinsics: Some(intrinsics),
        views,
        unreachable,
        truth,
        sim_scene,
    })
}

/// The views' start pose and pivot, and the camera and board poses the rig publishes (the
/// board's with its parent frame).
type StartPose = (Isometry3<f64>, Vector3<f64>, Option<Isometry3<f64>>, Option<(String, Isometry3<f64>)>);

/// Where the views start and the point they turn about: facing the published camera with the
/// board (`--start camera`), or around the arm's pose now (`--start here`, or nothing
/// published); with the camera and board poses the rig publishes.
#[allow(clippy::too_many_arguments)]
fn start_pose(
    a: &CaptureArgs,
    camera: &str,
    mount: Mount,
    board: &BoardSpec,
    link: &Link,
    safety: &SafetyFilter,
    (tcp_now, reset): (&Isometry3<f64>, &Joints),
    (amp_m, amp_rad): (f64, f64),
) -> anyhow::Result<StartPose> {
    let aim = match a.aim.as_slice() {
        [x, y, z] => Vector3::new(*x, *y, *z),
        other => bail!("--aim takes x,y,z (3 numbers), not {other:?}"),
    };
    // The camera and the board as the rig publishes them.
    let published_camera = match mount {
        Mount::EyeToHand => link.statics.get(&format!("{camera}_optical")).map(|(_, p)| *p),
        Mount::EyeInHand => link.wrist_in_tcp,
    };
    let published_board = link.statics.get(labrig_msgs::calibration::BOARD_FRAME).cloned();
    let start_at = match a.start {
        Start::Auto if published_camera.is_some() && published_board.is_some() => Start::Camera,
        Start::Auto => {
            eprintln!(
                "{camera}: the rig publishes no {} pose: the views are taken around the arm's pose now \
                 (the board must be in view)",
                if published_camera.is_none() { "camera" } else { "board" }
            );
            Start::Here
        }
        s => s,
    };
    let (start, pivot) = match start_at {
        Start::Auto | Start::Here => (*tcp_now, tcp_now.translation.vector),
        Start::Camera => {
            let cam = published_camera.with_context(|| {
                format!(
                    "the rig publishes no pose for `{camera}` ({}): put the board in view and use --start here",
                    if mount == Mount::EyeToHand {
                        format!("/tf_static base -> {camera}_optical")
                    } else {
                        "/tf tcp, wrist_optical".into()
                    }
                )
            })?;
            let (parent, board_pose) = published_board.clone().with_context(|| {
                format!(
                    "the rig publishes no board pose (/tf_static -> {}): put the board in view and use --start here",
                    labrig_msgs::calibration::BOARD_FRAME
                )
            })?;
            let size = board.size_m();
            match mount {
                Mount::EyeToHand => {
                    anyhow::ensure!(
                        parent == "tcp",
                        "the board is on `{parent}`, not in the gripper (`tcp`), for `{camera}`"
                    );
                    calib_path::start_facing_camera(
                        safety,
                        reset,
                        &cam.translation.vector,
                        &aim,
                        &board_pose,
                        size,
                        (amp_m, amp_rad),
                    )
                    .with_context(|| format!("`{camera}`"))?
                }
                Mount::EyeInHand => {
                    anyhow::ensure!(
                        parent == "base",
                        "the board is on `{parent}`, not on the table (`base`), for the wrist camera"
                    );
                    calib_path::start_above_board(tcp_now, &cam, &board_pose, size)
                }
            }
        }
    };
    Ok((start, pivot, published_camera, published_board))
}

/// Drives the arm to `q`, holds it still for the settle time and takes the first frame after:
/// `None` when the pose is not reached in time (a fault the arm names is counted in `faults`).
async fn drive_to_view(
    link: &mut Link,
    q: &Joints,
    camera: &str,
    tick: &mut tokio::time::Interval,
    faults: &mut BTreeMap<String, usize>,
    shutdown: &Shutdown,
    rig: &tokio::task::JoinHandle<anyhow::Result<ExitCode>>,
) -> anyhow::Result<Option<(Grey, RobotState)>> {
    // Drive until the joints are there, then hold still 0.5 s, then the first frame after.
    let t_start = link.now().0;
    let mut reached_at: Option<i64> = None;
    let view: Option<(Grey, RobotState)> = loop {
        tick.tick().await;
        if shutdown.is_triggered() {
            bail!("interrupted");
        }
        if rig.is_finished() {
            bail!("the rig stopped during the capture (its nodes' errors are above)");
        }
        link.poll()?;
        link.alive()?;
        link.command(q)?;
        let Some(s) = link.state().cloned() else { continue };
        let t = Nanos::from(s.header.stamp).0;
        match reached_at {
            None => {
                if s.joint_positions.iter().zip(q).all(|(a, b)| (a - b).abs() < REACH_RAD) {
                    reached_at = Some(t);
                } else if t - t_start > REACH_NS {
                    if s.mode == RobotState::MODE_FAULT && !s.fault.is_empty() {
                        *faults.entry(s.fault.clone()).or_default() += 1;
                    }
                    break None;
                }
            }
            Some(r) if t - r >= SETTLE_NS => {
                if let Some(g) = link.frame_after(r + SETTLE_NS)? {
                    break Some((g, s));
                }
                if t - r > SETTLE_NS + FRAME_NS {
                    bail!("camera `{camera}` sent no frame within {} s of the arm stopping", FRAME_NS / 1_000_000_000);
                }
            }
            Some(_) => {
                // Frames of the motion are dropped as they come.
                link.frame_after(i64::MAX)?;
            }
        }
    };
    Ok(view)
}
