//! The rig's physics in lockstep: each [`Sim::step`] advances exactly one control period.

use crate::render::{Cameras, Meshes, RenderError, RenderedFrame};
use crate::rig::{self, ARM_JOINTS, GRIPPER_ACTUATOR, GRIPPER_DRIVER_JOINT};
use crate::scene::{self, SceneSpec, SceneValues};
use labrig_msgs::Nanos;
use mujoco_rs::prelude::*;
use std::path::Path;
use std::sync::{Arc, Once};

/// The gripper's tool centre point: the 2F-85's pinch site, between the finger pads.
pub const TCP_SITE: &str = "gripper_pinch";

/// Routes MuJoCo's warnings to `log` (and so to tracing) instead of `MUJOCO_LOG.TXT` in the
/// working directory. Done once, before any model loads.
fn route_mujoco_log() {
    static ONCE: Once = Once::new();
    ONCE.call_once(|| {
        // SAFETY: called once, before this process loads a model, so no other thread is inside
        // MuJoCo while the handler is swapped.
        #[allow(unsafe_code)]
        unsafe {
            mujoco_rs::logging::install_logging_hook()
        };
    });
}

/// Closing range of the 2F-85's driver joint (rad), for the 0..1 gripper position.
const DRIVER_CLOSED_RAD: f64 = 0.8;

#[derive(Debug, thiserror::Error)]
pub enum SimError {
    #[error(transparent)]
    Rig(#[from] rig::RigError),
    #[error(transparent)]
    Scene(#[from] scene::SceneError),
    #[error(transparent)]
    Render(#[from] RenderError),
    #[error("cameras are not enabled: call Sim::enable_cameras first")]
    NoCameras,
    #[error("MuJoCo could not load the rig: {0}")]
    Load(String),
    #[error("the rig model lacks {kind} `{name}`")]
    MissingName { kind: &'static str, name: String },
    #[error("control period {period:?} is not a positive multiple of the physics timestep {timestep} s")]
    Period { period: Nanos, timestep: f64 },
    /// A command that must never reach the physics: the arm holds its last target.
    #[error("refused {what}: {reason}")]
    Refused { what: &'static str, reason: String },
}

/// One tick's command: FR3 joint position targets and the gripper closing command.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ArmTarget {
    pub joints: [f64; 7],
    /// 0 = open .. 1 = closed.
    pub gripper: f64,
}

/// The simulated rig.
pub struct Sim {
    data: MjData<Arc<MjModel>>,
    scene: SceneValues,
    cameras: Option<Cameras>,
    tcp_site: usize,
    object_body: usize,
    /// The drawer's slide joint qpos address and the handle site, when the scene has a cabinet.
    drawer: Option<(usize, usize)>,
    arm_dofs: [usize; 7],
    arm_actuators: [usize; 7],
    arm_qpos: [usize; 7],
    arm_limits: [[f64; 2]; 7],
    gripper_actuator: usize,
    gripper_qpos: usize,
    reset_key: usize,
    substeps: u32,
    ticks: u64,
    period: Nanos,
}

impl std::fmt::Debug for Sim {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Sim").field("ticks", &self.ticks).field("period", &self.period).finish()
    }
}

impl Sim {
    /// Loads the rig from `assets` (see [`rig::DEFAULT_ASSETS`]) set up as `spec` + `seed`
    /// say, and resets it to DROID's reset pose. `period` is the control period each
    /// [`Sim::step`] advances.
    pub fn new(assets: &Path, spec: &SceneSpec, seed: u64, period: Nanos) -> Result<Sim, SimError> {
        Sim::build(assets, spec, seed, period, None)
    }

    /// [`Sim::new`] with what calibration adds: a board in the scene (its frame is body
    /// [`rig::BOARD_BODY`], see [`Sim::body_pose`]), a camera moved from where the scene put it.
    pub fn with_extras(
        assets: &Path,
        spec: &SceneSpec,
        seed: u64,
        period: Nanos,
        extras: &rig::Extras,
    ) -> Result<Sim, SimError> {
        Sim::build(assets, spec, seed, period, Some(extras))
    }

    fn build(
        assets: &Path,
        spec: &SceneSpec,
        seed: u64,
        period: Nanos,
        extras: Option<&rig::Extras>,
    ) -> Result<Sim, SimError> {
        route_mujoco_log();
        let mut scene = spec.sample(seed)?;
        if let Some((camera, shift)) = extras.and_then(|e| e.move_camera.as_ref())
            && let Some(pose) = scene.cameras.get_mut(camera)
        {
            for (p, d) in pose.position.iter_mut().zip(shift) {
                *p += d;
            }
        }
        let xml = rig::compose_with_board(assets, &scene, extras.and_then(|e| e.board.as_ref()))?;
        let mut model = MjModel::from_xml_string(&xml).map_err(|e| SimError::Load(format!("{e:?}")))?;
        fill_texture(&mut model, rig::OBJECT_TEXTURE, &scene::object_texture(&scene, spec.object.noise_octaves))?;
        fill_texture(&mut model, rig::TABLE_TEXTURE, &scene::table_texture(&scene, spec.table.jitter))?;
        let model = Arc::new(model);
        let timestep = model.opt().timestep;
        let ratio = period.as_secs_f64() / timestep;
        if period.0 <= 0 || (ratio - ratio.round()).abs() > 1e-6 {
            return Err(SimError::Period { period, timestep });
        }
        let id = |kind: MjtObjBase, label: &'static str, name: &str| {
            model.name_to_id(kind, name).ok_or_else(|| SimError::MissingName { kind: label, name: name.to_owned() })
        };
        let mut arm_actuators = [0; 7];
        let mut arm_qpos = [0; 7];
        let mut arm_limits = [[0.0; 2]; 7];
        let mut arm_dofs = [0; 7];
        for (i, name) in ARM_JOINTS.iter().enumerate() {
            arm_actuators[i] = id(MjtObjBase::mjOBJ_ACTUATOR, "actuator", name)?;
            let joint = id(MjtObjBase::mjOBJ_JOINT, "joint", name)?;
            arm_qpos[i] = model.jnt_qposadr()[joint] as usize;
            arm_dofs[i] = model.jnt_dofadr()[joint] as usize;
            arm_limits[i] = model.jnt_range()[joint];
        }
        let gripper_actuator = id(MjtObjBase::mjOBJ_ACTUATOR, "actuator", GRIPPER_ACTUATOR)?;
        let driver = id(MjtObjBase::mjOBJ_JOINT, "joint", GRIPPER_DRIVER_JOINT)?;
        let gripper_qpos = model.jnt_qposadr()[driver] as usize;
        let reset_key = id(MjtObjBase::mjOBJ_KEY, "keyframe", "reset")?;
        let tcp_site = id(MjtObjBase::mjOBJ_SITE, "site", TCP_SITE)?;
        let object_body = id(MjtObjBase::mjOBJ_BODY, "body", "object")?;
        let drawer = match scene.drawer {
            None => None,
            Some(_) => {
                let joint = id(MjtObjBase::mjOBJ_JOINT, "joint", rig::DRAWER_JOINT)?;
                Some((model.jnt_qposadr()[joint] as usize, id(MjtObjBase::mjOBJ_SITE, "site", rig::HANDLE_SITE)?))
            }
        };
        let data = MjData::new(model.clone());
        let mut sim = Sim {
            data,
            scene,
            cameras: None,
            tcp_site,
            object_body,
            drawer,
            arm_dofs,
            arm_actuators,
            arm_qpos,
            arm_limits,
            gripper_actuator,
            gripper_qpos,
            reset_key,
            substeps: ratio.round() as u32,
            ticks: 0,
            period,
        };
        sim.reset();
        Ok(sim)
    }

    /// Back to DROID's reset pose, time 0.
    pub fn reset(&mut self) {
        self.data.reset_keyframe(self.reset_key).expect("the reset keyframe id was looked up from this model");
        self.data.forward();
        self.ticks = 0;
    }

    /// Checks a command before it can touch the physics: finite values, joints inside the
    /// FR3's limits, gripper in 0..1.
    pub fn check(&self, target: &ArmTarget) -> Result<(), SimError> {
        for (i, (&q, [lo, hi])) in target.joints.iter().zip(self.arm_limits).enumerate() {
            if !q.is_finite() {
                return Err(SimError::Refused { what: "arm target", reason: format!("{} is {q}", ARM_JOINTS[i]) });
            }
            if q < lo || q > hi {
                return Err(SimError::Refused {
                    what: "arm target",
                    reason: format!("{} = {q:.4} rad is outside its limits [{lo:.4}, {hi:.4}]", ARM_JOINTS[i]),
                });
            }
        }
        if !(0.0..=1.0).contains(&target.gripper) {
            return Err(SimError::Refused {
                what: "gripper command",
                reason: format!("{} is outside 0..1", target.gripper),
            });
        }
        Ok(())
    }

    /// Applies `target` (after [`Sim::check`]) and advances exactly one control period.
    /// A refused command leaves the previous targets in place and the time unchanged.
    pub fn step(&mut self, target: &ArmTarget) -> Result<(), SimError> {
        self.check(target)?;
        let ctrl = self.data.ctrl_mut();
        for (i, &a) in self.arm_actuators.iter().enumerate() {
            ctrl[a] = target.joints[i];
        }
        // The 2F-85 takes 0..255 (the real gripper's rPR scale).
        ctrl[self.gripper_actuator] = (target.gripper * 255.0).round();
        for _ in 0..self.substeps {
            self.compensate_gravity();
            self.data.step();
        }
        self.ticks += 1;
        Ok(())
    }

    /// One control period in which a stop lands mid-tick: `target` for the first `after`
    /// physics steps, then the arm is held where it is (its measured joints become the
    /// target) for the rest of the period. Returns the joints it holds at. `after` at or past
    /// the period's physics steps is a plain [`Sim::step`] followed by the hold.
    pub fn step_then_hold(&mut self, target: &ArmTarget, after: u32) -> Result<[f64; 7], SimError> {
        self.check(target)?;
        let ctrl = self.data.ctrl_mut();
        for (i, &a) in self.arm_actuators.iter().enumerate() {
            ctrl[a] = target.joints[i];
        }
        ctrl[self.gripper_actuator] = (target.gripper * 255.0).round();
        let mut hold = None;
        for k in 0..self.substeps {
            if k == after {
                hold = Some(self.hold_here());
            }
            self.compensate_gravity();
            self.data.step();
        }
        self.ticks += 1;
        Ok(hold.unwrap_or_else(|| self.hold_here()))
    }

    /// Makes the measured arm joints the position targets; returns them.
    fn hold_here(&mut self) -> [f64; 7] {
        let q = self.joint_positions();
        let ctrl = self.data.ctrl_mut();
        for (i, &a) in self.arm_actuators.iter().enumerate() {
            ctrl[a] = q[i];
        }
        q
    }

    /// Length of one physics step.
    pub fn substep(&self) -> Nanos {
        Nanos(self.period.0 / self.substeps.max(1) as i64)
    }

    /// The FR3's controller compensates gravity (and the tool's weight) itself; the sim does the
    /// same: the arm joints get the bias forces (gravity + Coriolis) of the last physics step
    /// as applied torques, so the position servos only track.
    fn compensate_gravity(&mut self) {
        let bias: [f64; 7] = std::array::from_fn(|i| self.data.qfrc_bias()[self.arm_dofs[i]]);
        let applied = self.data.qfrc_applied_mut();
        for (i, &dof) in self.arm_dofs.iter().enumerate() {
            applied[dof] = bias[i];
        }
    }

    /// Continues the clock of an earlier scene: time goes on from `t` (rounded down to a
    /// period), so a rig re-seeded between episodes keeps one monotonic time line.
    pub fn resume_clock(&mut self, t: Nanos) {
        self.ticks = (t.0.max(0) / self.period.0) as u64;
    }

    /// Simulated time: ticks x control period (exact, no float accumulation).
    pub fn time(&self) -> Nanos {
        Nanos(self.period.0 * self.ticks as i64)
    }

    pub fn joint_positions(&self) -> [f64; 7] {
        let qpos = self.data.qpos();
        std::array::from_fn(|i| qpos[self.arm_qpos[i]])
    }

    /// Gripper opening as 0 = open .. 1 = closed, from the driver joint.
    pub fn gripper_position(&self) -> f64 {
        (self.data.qpos()[self.gripper_qpos] / DRIVER_CLOSED_RAD).clamp(0.0, 1.0)
    }

    /// The whole physics state (for determinism checks and snapshots).
    pub fn qpos(&self) -> &[f64] {
        self.data.qpos()
    }

    /// Physics steps per control period.
    pub fn substeps(&self) -> u32 {
        self.substeps
    }

    /// The control period each [`Sim::step`] advances.
    pub fn period(&self) -> Nanos {
        self.period
    }

    /// The FR3's joint position limits from the model, [lower, upper] per joint (rad).
    pub fn joint_limits(&self) -> [[f64; 2]; 7] {
        self.arm_limits
    }

    pub fn joint_velocities(&self) -> [f64; 7] {
        let qvel = self.data.qvel();
        std::array::from_fn(|i| qvel[self.arm_dofs[i]])
    }

    /// The arm's last commanded joint targets (the actuators' ctrl).
    pub fn joint_targets(&self) -> [f64; 7] {
        let ctrl = self.data.ctrl();
        std::array::from_fn(|i| ctrl[self.arm_actuators[i]])
    }

    /// The TCP (pinch site) position and rotation matrix (row-major) in the robot base frame.
    pub fn tcp_pose(&self) -> ([f64; 3], [f64; 9]) {
        (self.data.site_xpos()[self.tcp_site], self.data.site_xmat()[self.tcp_site])
    }

    /// The TCP's 6x7 geometric Jacobian over the arm joints: rows vx vy vz wx wy wz.
    pub fn tcp_jacobian(&self) -> [[f64; 7]; 6] {
        let (jacp, jacr) = self.data.jac_site(true, true, self.tcp_site);
        let nv = self.data.qvel().len();
        std::array::from_fn(|r| {
            let (m, row) = if r < 3 { (&jacp, r) } else { (&jacr, r - 3) };
            std::array::from_fn(|c| m[row * nv + self.arm_dofs[c]])
        })
    }

    /// The 2F-85's driver joint angle (rad; 0 open .. ~0.8 closed).
    pub fn gripper_driver_angle(&self) -> f64 {
        self.data.qpos()[self.gripper_qpos]
    }

    /// A camera's id in the model.
    pub fn camera_id(&self, name: &str) -> Option<usize> {
        self.data.model().name_to_id(MjtObjBase::mjOBJ_CAMERA, name)
    }

    /// A camera's position and rotation (MuJoCo convention: looks along -z, y up) in the
    /// robot base frame, for the current state.
    pub fn camera_pose(&self, name: &str) -> Option<([f64; 3], nalgebra::Matrix3<f64>)> {
        let id = self.camera_id(name)?;
        let m = self.data.cam_xmat()[id];
        Some((self.data.cam_xpos()[id], nalgebra::Matrix3::from_row_slice(&m)))
    }

    /// A body's position and rotation (row-major) in the robot base frame, by name.
    pub fn body_pose(&self, name: &str) -> Option<([f64; 3], [f64; 9])> {
        let id = self.data.model().name_to_id(MjtObjBase::mjOBJ_BODY, name)?;
        Some((self.data.xpos()[id], self.data.xmat()[id]))
    }

    /// Puts the arm at `q` (no physics step, velocities zeroed) and recomputes the kinematics:
    /// for comparing kinematics, never while a controller runs. `q` is checked like a command.
    pub fn set_arm_configuration(&mut self, q: &[f64; 7]) -> Result<(), SimError> {
        self.check(&ArmTarget { joints: *q, gripper: 0.0 })?;
        let qpos = self.data.qpos_mut();
        for (i, &adr) in self.arm_qpos.iter().enumerate() {
            qpos[adr] = q[i];
        }
        let qvel = self.data.qvel_mut();
        for &adr in &self.arm_dofs {
            qvel[adr] = 0.0;
        }
        self.data.forward();
        Ok(())
    }

    /// The object's centre in the robot base frame.
    pub fn object_position(&self) -> [f64; 3] {
        self.data.xpos()[self.object_body]
    }

    /// The object's yaw (rad): the heading of its x axis in the base frame's table plane (for
    /// an object that lies flat, its turn about z).
    pub fn object_yaw(&self) -> f64 {
        let m = self.data.xmat()[self.object_body];
        m[3].atan2(m[0])
    }

    /// How far the drawer is open (m; 0 = shut), if the scene has one.
    pub fn drawer_opening(&self) -> Option<f64> {
        self.drawer.map(|(qpos, _)| self.data.qpos()[qpos])
    }

    /// The drawer handle's grip point in the robot base frame, if the scene has one.
    pub fn handle_position(&self) -> Option<[f64; 3]> {
        self.drawer.map(|(_, site)| self.data.site_xpos()[site])
    }

    /// The values this scene was built from.
    pub fn scene(&self) -> &SceneValues {
        &self.scene
    }

    /// The physics model (names, sizes, camera intrinsics).
    pub fn model(&self) -> &MjModel {
        self.data.model()
    }

    /// Opens the offscreen renderer for the five cameras at `width` x `height`.
    pub fn enable_cameras(&mut self, width: usize, height: usize, meshes: Meshes) -> Result<(), SimError> {
        self.cameras = Some(Cameras::new(self.data.model(), width, height, meshes)?);
        Ok(())
    }

    /// Takes `from`'s cameras (the scene this one replaces), their OpenGL context kept: a rig
    /// that rebuilds its scene every episode opens one context for its whole run, not one per
    /// scene (Mesa kept memory of every context it had opened: the bridge grew by ~44 MB an
    /// hour over 589 episodes). Without cameras in `from`, this sim has none either.
    pub fn adopt_cameras(&mut self, from: &mut Sim) -> Result<(), SimError> {
        if let Some(mut cameras) = from.cameras.take() {
            cameras.retarget(from.data.model(), self.data.model())?;
            self.cameras = Some(cameras);
        }
        Ok(())
    }

    /// Renders one camera for the current state into `out` (RGB8, top row first).
    pub fn render_into(&mut self, camera: &'static str, out: &mut Vec<u8>) -> Result<(), SimError> {
        let cameras = self.cameras.as_mut().ok_or(SimError::NoCameras)?;
        Ok(cameras.render_into(&mut self.data, camera, out)?)
    }

    /// Renders all five cameras for the current state.
    pub fn render_all(&mut self) -> Result<Vec<RenderedFrame>, SimError> {
        let cameras = self.cameras.as_mut().ok_or(SimError::NoCameras)?;
        Ok(cameras.render_all(&mut self.data)?)
    }
}

/// Overwrites texture `name` (declared flat in the MJCF) with `texels` (a square RGB tile,
/// repeated over the texture's rows and columns, e.g. over each face of a cube texture).
fn fill_texture(model: &mut MjModel, name: &str, texels: &[u8]) -> Result<(), SimError> {
    let id = model
        .name_to_id(MjtObjBase::mjOBJ_TEXTURE, name)
        .ok_or_else(|| SimError::MissingName { kind: "texture", name: name.to_owned() })?;
    let (w, h) = (model.tex_width()[id] as usize, model.tex_height()[id] as usize);
    let channels = model.tex_nchannel()[id] as usize;
    let adr = model.tex_adr()[id] as usize;
    let tile = scene::TEXTURE_SIZE;
    let data = &mut model.tex_data_mut()[adr..adr + w * h * channels];
    for r in 0..h {
        for c in 0..w {
            let src = ((r % tile) * tile + (c % tile)) * 3;
            let dst = (r * w + c) * channels;
            data[dst..dst + 3].copy_from_slice(&texels[src..src + 3]);
        }
    }
    Ok(())
}
