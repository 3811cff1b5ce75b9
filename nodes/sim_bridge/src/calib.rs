//! `labrig-sim calib-capture`: the simulated rig takes a calibration's views the way DROID's
//! rig does. The board (its print, a PNG at true scale) is in the scene: carried by the
//! gripper for an external camera, lying on the table for the wrist camera. The arm is driven
//! through the franka node's safety layer ([`SimHardware`], cartesian position commands) over
//! a pose set around a start pose facing the camera (a smooth sinusoid, +-10 cm and
//! +-0.2 rad; the angles / 1.5 for the wrist camera), pausing 0.5 s before each view. Each view
//! is rendered at the real cameras' resolution and written as a greyscale PGM with the TCP
//! pose the arm reports, plus the ground truth only a sim has (`capture.json`,
//! [`labrig_msgs::calibration::CaptureFile`]). labrig-calibration solves it.

use crate::hardware::SimHardware;
use anyhow::Context;
use labrig_arm::calib_path::{self, joints_for, pose_set};
use labrig_arm::safety::SafetyFilter;
use labrig_msgs::Nanos;
use labrig_msgs::calibration::{
    BoardSpec, CAPTURE_VERSION, CaptureFile, CaptureTruth, CapturedView, Intrinsics, Mount, Pose,
};
use labrig_msgs::rig::{ArmCommand, ArmCommandMode};
use labrig_sim::rig::{BOARD_BODY, Board, BoardMount, Extras};
use labrig_sim::scene::{EXTERNAL_CAMERAS, SceneSpec, TABLE_CENTRE};
use labrig_sim::{Meshes, Sim};
use nalgebra::{Isometry3, Matrix3, Rotation3, Translation3, UnitQuaternion, Vector3};
use std::path::{Path, PathBuf};

/// What to capture.
#[derive(Debug, Clone)]
pub struct CaptureOptions {
    pub assets: PathBuf,
    pub spec: SceneSpec,
    pub seed: u64,
    /// The board's print (PNG) and its size (width, height; m), and the board spec the capture
    /// records (what the operator says is printed; normally the print's own).
    pub print: PathBuf,
    pub print_size_m: [f64; 2],
    pub board: BoardSpec,
    pub camera: &'static str,
    pub views: usize,
    pub width: usize,
    pub height: usize,
    /// Translation amplitude of the pose set (m) and rotation amplitude (rad).
    pub amplitude_m: f64,
    pub amplitude_rad: f64,
    /// Move the camera by this much (m, base frame) from where the scene puts it: a camera
    /// knocked after calibration, for `calibrate check`.
    pub camera_shift_m: [f64; 3],
    pub out: PathBuf,
    pub rig: String,
}

/// One control period of the capture's motion.
const PERIOD: Nanos = Nanos(50_000_000);
/// Ticks at rest before a view (DROID pauses 0.5 s).
const SETTLE_TICKS: usize = 10;
/// Ticks allowed to reach a pose of the set.
const REACH_TICKS: usize = 80;
/// A pose counts as reached when every joint is this close to its target (rad).
const REACH_RAD: f64 = 0.002;

/// The rig's mount of a camera: the wrist camera is eye-in-hand, the rest eye-to-hand.
pub fn mount_of(camera: &str) -> Mount {
    if EXTERNAL_CAMERAS.contains(&camera) { Mount::EyeToHand } else { Mount::EyeInHand }
}

fn pose_of(iso: &Isometry3<f64>) -> Pose {
    let q = iso.rotation.quaternion();
    Pose { position: iso.translation.vector.into(), quaternion_wxyz: [q.w, q.i, q.j, q.k] }
}

fn iso((p, r): ([f64; 3], [f64; 9])) -> Isometry3<f64> {
    let rot = Rotation3::from_matrix_unchecked(Matrix3::from_row_slice(&r));
    Isometry3::from_parts(Translation3::from(Vector3::from(p)), UnitQuaternion::from_rotation_matrix(&rot))
}

/// A MuJoCo camera looks along -z with y up; the optical frame looks along +z with y down.
fn optical(sim: &Sim, camera: &str) -> anyhow::Result<Isometry3<f64>> {
    let (p, r) = sim.camera_pose(camera).with_context(|| format!("the sim has no camera `{camera}`"))?;
    let rot = Rotation3::from_matrix_unchecked(crate::bridge::optical(&r));
    Ok(Isometry3::from_parts(Translation3::from(Vector3::from(p)), UnitQuaternion::from_rotation_matrix(&rot)))
}

/// The sim camera's intrinsics at `width` x `height`: square pixels, the principal point at
/// the image centre (OpenGL's pixel centres are at +0.5; OpenCV's at integers).
pub fn sim_intrinsics(fovy_deg: f64, width: usize, height: usize) -> Intrinsics {
    let f = height as f64 / 2.0 / (fovy_deg.to_radians() / 2.0).tan();
    Intrinsics {
        width: width as u32,
        height: height as u32,
        fx: f,
        fy: f,
        cx: width as f64 / 2.0 - 0.5,
        cy: height as f64 / 2.0 - 0.5,
        distortion: vec![0.0; 5],
        source: "sim".into(),
    }
}

/// The start pose (base -> tcp) and the pivot for `camera`, from what the sim knows: the
/// camera's pose, the board's.
fn start_pose(
    sim: &Sim,
    safety: &SafetyFilter,
    camera: &str,
    board: &Board,
    amplitude: (f64, f64),
) -> anyhow::Result<(Isometry3<f64>, Vector3<f64>)> {
    let tcp = iso(sim.tcp_pose());
    let board_pose = iso(sim.body_pose(BOARD_BODY).context("the scene has no board")?);
    let cam = optical(sim, camera)?;
    match board.mount {
        BoardMount::Gripper => {
            let reset = sim.joint_positions();
            calib_path::start_facing_camera(
                safety,
                &reset,
                &cam.translation.vector,
                &Vector3::from(TABLE_CENTRE),
                &(tcp.inverse() * board_pose),
                board.size_m,
                amplitude,
            )
            .with_context(|| format!("`{camera}`"))
        }
        BoardMount::Table { .. } => {
            Ok(calib_path::start_above_board(&tcp, &(tcp.inverse() * cam), &board_pose, board.size_m))
        }
    }
}

fn joint_command(q: &[f64; 7], seq: u64) -> ArmCommand {
    ArmCommand {
        mode: ArmCommandMode::JointPosition as u8,
        joint_position: *q,
        gripper_position: 0.0,
        seq,
        ..ArmCommand::default()
    }
}

/// Writes an RGB8 frame as 8-bit greyscale PGM (BT.601 luma).
fn write_pgm(path: &Path, rgb: &[u8], width: usize, height: usize) -> anyhow::Result<()> {
    use labrig_episode::grey;
    grey::write_pgm(path, width, height, &grey::from_rgb(rgb)).with_context(|| format!("writing {}", path.display()))
}

/// The capture's outcome.
#[derive(Debug, Clone, serde::Serialize)]
pub struct CaptureReport {
    pub camera: String,
    pub views: usize,
    pub unreachable: usize,
    pub capture: PathBuf,
}

/// Takes the views of one camera into `opts.out` (created) and writes `capture.json` there.
pub fn capture(opts: &CaptureOptions, progress: &indicatif::ProgressBar) -> anyhow::Result<CaptureReport> {
    let camera = opts.camera;
    let mount = mount_of(camera);
    let size_m = opts.print_size_m;
    let board = Board {
        texture: opts.print.clone(),
        size_m,
        mount: match mount {
            Mount::EyeToHand => BoardMount::Gripper,
            Mount::EyeInHand => BoardMount::on_table(),
        },
    };
    let extras = Extras { board: Some(board.clone()), move_camera: Some((camera.to_owned(), opts.camera_shift_m)) };
    let mut sim = Sim::with_extras(&opts.assets, &opts.spec, opts.seed, PERIOD, &extras)?;
    sim.enable_cameras(opts.width, opts.height, Meshes::Collision)?;
    let fovy = sim.model().cam_fovy()[sim.camera_id(camera).context("camera")?];
    let intrinsics = sim_intrinsics(fovy, opts.width, opts.height);
    let safety = labrig_sim::safety_filter(PERIOD, None)?;
    let amp_rad = match mount {
        Mount::EyeToHand => opts.amplitude_rad,
        Mount::EyeInHand => opts.amplitude_rad / 1.5,
    };
    let (start, pivot) = start_pose(&sim, &safety, camera, &board, (opts.amplitude_m, amp_rad))?;
    tracing::debug!(?start, ?pivot, camera_distance = ?optical(&sim, camera).map(|c| (c.translation.vector - pivot).norm()), "pose set");
    let poses = pose_set(&start, &pivot, opts.views, opts.amplitude_m, amp_rad);
    let mut hw = SimHardware::new(sim, safety.clone(), true);
    std::fs::create_dir_all(&opts.out).with_context(|| format!("creating {}", opts.out.display()))?;
    let truth_board = iso(hw.sim().body_pose(BOARD_BODY).context("board")?);
    let truth = match mount {
        Mount::EyeToHand => CaptureTruth {
            camera: pose_of(&optical(hw.sim(), camera)?),
            board: pose_of(&(iso(hw.sim().tcp_pose()).inverse() * truth_board)),
        },
        Mount::EyeInHand => CaptureTruth {
            camera: pose_of(&(iso(hw.sim().tcp_pose()).inverse() * optical(hw.sim(), camera)?)),
            board: pose_of(&truth_board),
        },
    };
    let mut seq = 0u64;
    let mut views = Vec::new();
    let mut unreachable = 0;
    let mut rgb = Vec::new();
    let mut last = hw.sim().joint_positions();
    for (i, want) in poses.iter().enumerate() {
        // Joints for the pose (IK from the last pose's joints, else from a family of seeds),
        // then joint targets through the safety layer until the arm is there.
        let Some(q) = joints_for(&safety, &last, want) else {
            tracing::debug!(view = i, "no IK solution");
            unreachable += 1;
            progress.inc(1);
            continue;
        };
        let mut reached = false;
        for _ in 0..REACH_TICKS {
            seq += 1;
            let t = hw.sim().time();
            hw.arm_command(&joint_command(&q, seq), t);
            hw.step()?;
            let here = hw.sim().joint_positions();
            if here.iter().zip(&q).all(|(a, b)| (a - b).abs() < REACH_RAD) {
                reached = true;
                break;
            }
        }
        if !reached {
            tracing::debug!(view = i, fault = %hw.state().fault, "pose not reached");
            unreachable += 1;
            progress.inc(1);
            continue;
        }
        last = q;
        for _ in 0..SETTLE_TICKS {
            seq += 1;
            let t = hw.sim().time();
            hw.arm_command(&joint_command(&q, seq), t);
            hw.step()?;
        }
        let tcp = iso(hw.sim().tcp_pose());
        hw.sim_mut().render_into(camera, &mut rgb)?;
        let image = format!("view_{i:03}.pgm");
        write_pgm(&opts.out.join(&image), &rgb, opts.width, opts.height)?;
        views.push(CapturedView { image, tcp: pose_of(&tcp) });
        progress.inc(1);
    }
    let file = CaptureFile {
        version: CAPTURE_VERSION,
        rig: opts.rig.clone(),
        camera: camera.to_owned(),
        mount,
        board: opts.board.clone(),
        intrinsics: Some(intrinsics),
        views,
        unreachable,
        truth: Some(truth),
        sim_scene: Some(labrig_msgs::calibration::sim_scene_name(&opts.spec.name, opts.seed)),
    };
    let path = opts.out.join("capture.json");
    std::fs::write(&path, serde_json::to_string_pretty(&file)?)
        .with_context(|| format!("writing {}", path.display()))?;
    Ok(CaptureReport { camera: camera.to_owned(), views: file.views.len(), unreachable, capture: path })
}
