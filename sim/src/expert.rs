//! The scripted experts: solve pick-and-place into the bin and drawer open/close from the
//! scene's ground truth, producing DROID actions (absolute end-effector pose as xyz + extrinsic
//! xyz euler, and a 0..1 gripper position), plus each task's success predicate.
//!
//! In the sim, [`CartesianIk`] turns the pose action into joint position targets with one
//! damped-least-squares step per tick on MuJoCo's own Jacobian — a stand-in for the franka
//! node's URDF-based IK (issue 4) so the expert can be evaluated inside this crate.

use crate::scene::{BIN_HALF, DRAWER_CLOSED_M, DRAWER_OPEN_M, DRAWER_TRAVEL, OBJECT_SIZE, Task};
use crate::{ArmTarget, Sim, SimError};
use nalgebra::{Matrix3, Matrix6, Rotation3, SMatrix, SVector, UnitQuaternion, Vector3};
use serde::Serialize;

/// Largest TCP translation per tick (m) and rotation per tick (rad) the expert asks for:
/// 0.4 m/s and 2 rad/s at 20 Hz, inside DROID's 0.075 m / 0.15 rad per step.
pub const MAX_STEP_M: f64 = 0.02;
pub const MAX_STEP_RAD: f64 = 0.1;

/// The expert's phases, in order.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Phase {
    Approach,
    Descend,
    Grasp,
    Lift,
    Carry,
    Lower,
    /// Drawer tasks: slide the gripped handle out / in.
    Pull,
    Push,
    Release,
    Retreat,
    Done,
}

/// One tick's action in DROID's action space.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Action {
    /// Target TCP pose: x y z (m) and extrinsic xyz euler angles (rad), robot base frame.
    pub cartesian_position: [f64; 6],
    /// 0 = open .. 1 = closed.
    pub gripper_position: f64,
    pub phase: Phase,
    /// Where the phase leads the TCP (m, robot base frame): the end of the current phase's
    /// straight line, which `cartesian_position` approaches a step per tick.
    pub target: [f64; 3],
}

/// Extrinsic xyz euler angles (DROID's convention, scipy's `as_euler("xyz")`) of a rotation.
pub fn euler_xyz(r: &Matrix3<f64>) -> [f64; 3] {
    let (roll, pitch, yaw) = Rotation3::from_matrix_unchecked(*r).euler_angles();
    [roll, pitch, yaw]
}

/// The rotation matrix of extrinsic xyz euler angles.
pub fn from_euler_xyz(e: [f64; 3]) -> Matrix3<f64> {
    *Rotation3::from_euler_angles(e[0], e[1], e[2]).matrix()
}

fn row_major(m: [f64; 9]) -> Matrix3<f64> {
    Matrix3::from_row_slice(&m)
}

/// Moves a goal pose toward `target` by at most one step per tick ([`MAX_STEP_M`],
/// [`MAX_STEP_RAD`]).
fn lead(
    (goal_p, goal_r): (Vector3<f64>, Matrix3<f64>),
    target: Vector3<f64>,
    target_rot: Matrix3<f64>,
) -> (Vector3<f64>, Matrix3<f64>) {
    let dp = target - goal_p;
    let next_p = goal_p + dp * (MAX_STEP_M / dp.norm().max(MAX_STEP_M));
    let dr = UnitQuaternion::from_matrix(&(target_rot * goal_r.transpose()));
    let angle = dr.angle();
    let next_r = if angle > MAX_STEP_RAD {
        *UnitQuaternion::identity().slerp(&dr, MAX_STEP_RAD / angle).to_rotation_matrix().matrix() * goal_r
    } else {
        target_rot
    };
    (next_p, next_r)
}

/// A grasp (or a release) is done as soon as the fingers, commanded for at least
/// [`GRIP_TICKS`], stop moving (closed on the object, on nothing: the next phase checks, or
/// open). No wait after that: a policy learning from these demos sees the fingers stop and
/// then the arm move, never a pause it has no observation to time.
fn grip_settled(ticks_in_phase: u32, gripper: f64, last_gripper: f64) -> bool {
    ticks_in_phase >= GRIP_TICKS && (gripper - last_gripper).abs() < 2e-3
}

/// The turn about world z (rad, smallest) that brings the fingers' closing axis (the TCP's y)
/// of `down` to the yaw `axis_yaw`, modulo `symmetry` (pi/2 for a cube, pi for a bar).
fn turn_to(down: &Matrix3<f64>, axis_yaw: f64, symmetry: f64) -> f64 {
    let finger = down * Vector3::y();
    let finger_yaw = finger.y.atan2(finger.x);
    let mut turn = (axis_yaw - finger_yaw).rem_euclid(symmetry);
    if turn > symmetry / 2.0 {
        turn -= symmetry;
    }
    turn
}

/// The two aim errors of an expert that looks and corrects (the approach's, then the
/// descent's a third as large), in directions drawn from the scene's `seed`; none for 0.
fn aim_offsets(seed: u64, max_m: f64) -> [Option<Vector3<f64>>; 2] {
    use rand::{Rng, SeedableRng};
    if max_m <= 0.0 {
        return [None, None];
    }
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed ^ 0xA1A1_E440);
    let mut draw = |r: f64| {
        let (len, dir) = (rng.random_range(0.4 * r..=r), rng.random_range(0.0..std::f64::consts::TAU));
        Some(Vector3::new(len * dir.cos(), len * dir.sin(), 0.0))
    };
    [draw(max_m), draw(max_m * LOW_AIM_FRACTION)]
}

/// The scene's draw for a deliberate miss: `Some` (the generator, to draw where the miss goes)
/// in `fraction` of the scenes, by `seed`; `None` for the rest, and always for 0.
fn miss_draw(seed: u64, fraction: f64) -> Option<rand_chacha::ChaCha8Rng> {
    use rand::{Rng, SeedableRng};
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed ^ 0x5EED_1A55);
    (fraction > 0.0 && rng.random::<f64>() < fraction).then_some(rng)
}

/// Whether `phase` (approach: `aim[0]`, descent: `aim[1]`) was heading for an aimed-off point
/// and is `done`: that aim is taken out, and the phase goes on over (down to) the target itself.
fn reached_aim(phase: Phase, aim: &mut [Option<Vector3<f64>>; 2], done: bool) -> bool {
    let k = match phase {
        Phase::Approach => 0,
        Phase::Descend => 1,
        _ => return false,
    };
    done && aim[k].take().is_some()
}

/// Pick-and-place from ground truth: approach above the object, descend, close, lift, carry
/// over the bin, lower, open, retreat.
#[derive(Debug, Clone)]
pub struct PickPlaceExpert {
    phase: Phase,
    ticks_in_phase: u32,
    /// TCP orientation at the reset pose (fingers down); grasps rotate it about world z.
    down: Matrix3<f64>,
    grasp_yaw: f64,
    bin: [f64; 3],
    /// Where the TCP is being led (position, rotation), moved at most one step per tick.
    goal: Option<(Vector3<f64>, Matrix3<f64>)>,
    carried: Vector3<f64>,
    attempts: u32,
    last_gripper: f64,
    /// The TCP at the reset pose: where the plan ([`Expert::plan`]) starts.
    start: Vector3<f64>,
    /// [`PickPlaceExpert::with_aim_error`]: where the first approach and the first descent
    /// stop short (offsets in the table plane from the object), each taken out when reached.
    aim: [Option<Vector3<f64>>; 2],
    /// [`PickPlaceExpert::with_missed_grasp`]: where the first descent goes instead of the
    /// object (an offset in the table plane), taken out when the missed grasp is retried.
    miss: Option<Vector3<f64>>,
}

/// A missed grasp's offset from the object across the fingers' closing axis (m): the
/// finger pads (22 mm wide) close beside the 50 mm cube, on nothing.
const MISS_ACROSS_M: std::ops::RangeInclusive<f64> = 0.04..=0.055;
/// ... and along the closing axis, where the open fingers (85 mm) still clear it.
const MISS_ALONG_M: f64 = 0.01;

const HOVER_Z: f64 = 0.12;
/// With an aim error, the descent pauses this far above the grasp point to correct its
/// smaller offset (the finger tips stay clear of the cube's top).
const LOOK_ABOVE_GRASP: f64 = 0.05;
/// The descent's aim error, as a fraction of the approach's.
const LOW_AIM_FRACTION: f64 = 1.0 / 3.0;
const CARRY_Z: f64 = 0.18;
const RELEASE_Z: f64 = 0.11;
/// The fingers take a tick to start moving, so stillness before this is not the end of a grasp.
const GRIP_TICKS: u32 = 3;
/// The pinch point sits this far above the cube's centre, so the finger tips clear the table.
const GRASP_ABOVE_CENTRE: f64 = 0.008;
/// Grasp attempts before the expert gives up (a missed grasp is retried from the approach).
const MAX_ATTEMPTS: u32 = 3;
/// A phase that has not converged after this many ticks moves on anyway.
const PHASE_TIMEOUT: u32 = 80;

impl PickPlaceExpert {
    /// `sim` must be at the reset pose of the scene to solve.
    pub fn new(sim: &Sim) -> PickPlaceExpert {
        let (start, rot) = sim.tcp_pose();
        let down = row_major(rot);
        // The fingers close along the TCP's y axis: align it with a face of the cube. The
        // cube's symmetry lets the yaw be taken modulo 90 deg, into the smallest turn.
        let obj_yaw = sim.scene().object_yaw_deg.to_radians();
        PickPlaceExpert {
            phase: Phase::Approach,
            ticks_in_phase: 0,
            down,
            grasp_yaw: turn_to(&down, obj_yaw, std::f64::consts::FRAC_PI_2),
            bin: sim.scene().receptacle_position,
            goal: None,
            carried: Vector3::zeros(),
            attempts: 1,
            last_gripper: 0.0,
            start: Vector3::from(start),
            aim: [None, None],
            miss: None,
        }
    }

    /// Demos with a missed grasp and its recovery, in `fraction` of the scenes (drawn from
    /// the seed): the first descent goes down beside the object ([`MISS_ACROSS_M`] across the
    /// fingers' closing axis, so they close on nothing) and closes; the expert's usual retry
    /// does the rest: it lifts with the fingers shut, opens, comes back over the object and
    /// grasps it. A policy's misses look like this; demos without one never show the way back.
    /// (The descent and the close of the miss are the deliberate mistake: training drops
    /// them as labels, `skip_missed_grasps`; what follows is the lesson.) 0 = never.
    pub fn with_missed_grasp(mut self, seed: u64, fraction: f64) -> PickPlaceExpert {
        use rand::Rng;
        let Some(mut rng) = miss_draw(seed, fraction) else {
            self.miss = None;
            return self;
        };
        let grasp_rot = *Rotation3::from_axis_angle(&Vector3::z_axis(), self.grasp_yaw).matrix() * self.down;
        let flat = |v: Vector3<f64>| Vector3::new(v.x, v.y, 0.0).normalize();
        let (across, along) = (flat(grasp_rot * Vector3::x()), flat(grasp_rot * Vector3::y()));
        let sign = if rng.random::<bool>() { 1.0 } else { -1.0 };
        let off =
            across * sign * rng.random_range(MISS_ACROSS_M) + along * rng.random_range(-MISS_ALONG_M..=MISS_ALONG_M);
        self.miss = Some(off);
        // The descent goes straight to the miss: no pause to correct on the way.
        self.aim[1] = None;
        self
    }

    /// Demos that look and correct (DART-like, but every recorded action is the expert's):
    /// the first approach goes to a hover point `max_m` or less beside the object (at least
    /// 0.4 `max_m`, in a direction drawn from the scene's seed), then corrects over it; the
    /// first descent stops [`LOOK_ABOVE_GRASP`] above the grasp point a third as far off and
    /// corrects again before going down. A policy trained on them sees the object off-centre
    /// in its cameras with the motion that centres it, and a grasp that waits for that,
    /// where an exact expert shows only straight lines at one pace. 0 = the exact expert.
    pub fn with_aim_error(mut self, seed: u64, max_m: f64) -> PickPlaceExpert {
        self.aim = aim_offsets(seed, max_m);
        self
    }

    /// This scene's expert (`self`, made at the reset pose) taking over from the state `sim`
    /// is in now: the phase inferred from the physics, the goal led from the TCP.
    fn resume(&self, sim: &Sim) -> PickPlaceExpert {
        let pos = Vector3::from(sim.tcp_pose().0);
        let obj = Vector3::from(sim.object_position());
        let bin = Vector3::new(self.bin[0], self.bin[1], 0.0);
        let over_bin = (obj.x - bin.x).abs() < BIN_HALF[0] && (obj.y - bin.y).abs() < BIN_HALF[1];
        let (phase, carried) = if held(sim, obj, pos) {
            // Over the bin it goes down; elsewhere up first, to carry it over.
            (if over_bin { Phase::Lower } else { Phase::Lift }, pos)
        } else if pick_place_success(sim) {
            (Phase::Retreat, Vector3::zeros())
        } else {
            // Approach opens the fingers on the way up (and retries from there).
            (Phase::Approach, Vector3::zeros())
        };
        PickPlaceExpert {
            phase,
            ticks_in_phase: 0,
            goal: None,
            carried,
            attempts: 1,
            last_gripper: sim.gripper_position(),
            aim: [None, None],
            miss: None,
            ..self.clone()
        }
    }

    /// The path it means to take from the reset pose, through the object as it lies now.
    fn plan(&self, sim: &Sim) -> Vec<[f64; 3]> {
        let obj = sim.object_position();
        let [bx, by, _] = self.bin;
        vec![
            self.start.into(),
            [obj[0], obj[1], obj[2] + HOVER_Z],
            [obj[0], obj[1], obj[2] + GRASP_ABOVE_CENTRE],
            [obj[0], obj[1], CARRY_Z],
            [bx, by, CARRY_Z],
            [bx, by, RELEASE_Z],
        ]
    }

    pub fn phase(&self) -> Phase {
        self.phase
    }

    fn next(&mut self) {
        self.phase = match self.phase {
            Phase::Approach => Phase::Descend,
            Phase::Descend => Phase::Grasp,
            Phase::Grasp => Phase::Lift,
            Phase::Lift => Phase::Carry,
            Phase::Carry => Phase::Lower,
            Phase::Lower | Phase::Pull | Phase::Push => Phase::Release,
            Phase::Release => Phase::Retreat,
            Phase::Retreat | Phase::Done => Phase::Done,
        };
        self.ticks_in_phase = 0;
    }

    /// The next action, from the current state of the sim.
    pub fn act(&mut self, sim: &Sim) -> Action {
        let (p, r) = sim.tcp_pose();
        let pos = Vector3::from(p);
        let rot = row_major(r);
        let obj = Vector3::from(sim.object_position());
        let grasp_rot = *Rotation3::from_axis_angle(&Vector3::z_axis(), self.grasp_yaw).matrix() * self.down;
        let bin = Vector3::new(self.bin[0], self.bin[1], 0.0);
        // Each phase: where the TCP should end up, and the gripper command.
        let (target, target_rot, gripper) = match self.phase {
            Phase::Approach => {
                let off = self.aim[0].unwrap_or_default();
                (Vector3::new(obj.x + off.x, obj.y + off.y, obj.z + HOVER_Z), grasp_rot, 0.0)
            }
            Phase::Descend => match (self.miss, self.aim[1]) {
                (Some(off), _) => {
                    (Vector3::new(obj.x + off.x, obj.y + off.y, obj.z + GRASP_ABOVE_CENTRE), grasp_rot, 0.0)
                }
                (None, Some(off)) => (
                    Vector3::new(obj.x + off.x, obj.y + off.y, obj.z + GRASP_ABOVE_CENTRE + LOOK_ABOVE_GRASP),
                    grasp_rot,
                    0.0,
                ),
                (None, None) => (Vector3::new(obj.x, obj.y, obj.z + GRASP_ABOVE_CENTRE), grasp_rot, 0.0),
            },
            Phase::Grasp => {
                self.carried = pos;
                (pos, grasp_rot, 1.0)
            }
            Phase::Lift => (Vector3::new(self.carried.x, self.carried.y, CARRY_Z), grasp_rot, 1.0),
            Phase::Carry => (Vector3::new(bin.x, bin.y, CARRY_Z), grasp_rot, 1.0),
            Phase::Lower => (Vector3::new(bin.x, bin.y, RELEASE_Z), grasp_rot, 1.0),
            Phase::Release => (Vector3::new(bin.x, bin.y, RELEASE_Z), grasp_rot, 0.0),
            Phase::Retreat | Phase::Done | Phase::Pull | Phase::Push => {
                (Vector3::new(bin.x, bin.y, CARRY_Z + 0.05), grasp_rot, 0.0)
            }
        };
        let (next_p, next_r) = lead(self.goal.unwrap_or((pos, rot)), target, target_rot);
        self.goal = Some((next_p, next_r));
        self.ticks_in_phase += 1;
        let reached = (target - pos).norm() < 0.006 && (next_p - target).norm() < 1e-9;
        let done = match self.phase {
            // Closed once the fingers stop moving (on the cube, or on nothing: Lift checks).
            Phase::Grasp => grip_settled(self.ticks_in_phase, sim.gripper_position(), self.last_gripper),
            Phase::Release => grip_settled(self.ticks_in_phase, sim.gripper_position(), self.last_gripper),
            Phase::Done => false,
            _ => reached,
        };
        self.last_gripper = sim.gripper_position();
        // A grasp that did not lift the object is retried from the approach.
        if reached_aim(self.phase, &mut self.aim, done) {
            self.ticks_in_phase = 0;
        } else if self.phase == Phase::Lift && done && obj.z < OBJECT_SIZE && self.attempts < MAX_ATTEMPTS {
            tracing::debug!(attempt = self.attempts, "expert: the object did not come up; retrying the grasp");
            self.attempts += 1;
            self.phase = Phase::Approach;
            self.ticks_in_phase = 0;
            self.miss = None;
            self.aim = [None, None];
            // The miss may have nudged or turned the object: turn to it as it lies now.
            self.grasp_yaw = turn_to(&self.down, sim.object_yaw(), std::f64::consts::FRAC_PI_2);
        } else if done || (self.ticks_in_phase > PHASE_TIMEOUT && self.phase != Phase::Done) {
            tracing::debug!(
                phase = ?self.phase,
                ticks = self.ticks_in_phase,
                timed_out = !done,
                error_mm = (target - pos).norm() * 1e3,
                "expert phase done"
            );
            self.next();
        }
        let e = euler_xyz(&next_r);
        Action {
            cartesian_position: [next_p.x, next_p.y, next_p.z, e[0], e[1], e[2]],
            gripper_position: gripper,
            phase: self.phase,
            target: target.into(),
        }
    }
}

/// Drawer open/close from ground truth: approach above the handle, descend, close on it,
/// slide it out (open) or in (close), let go, retreat upward.
#[derive(Debug, Clone)]
pub struct DrawerExpert {
    task: Task,
    phase: Phase,
    ticks_in_phase: u32,
    /// Fingers down, closing across the handle (along world y).
    grasp_rot: Matrix3<f64>,
    /// The handle's x when the drawer is shut.
    shut_x: f64,
    goal: Option<(Vector3<f64>, Matrix3<f64>)>,
    held: Vector3<f64>,
    attempts: u32,
    last_gripper: f64,
    /// The TCP at the reset pose: where the plan ([`Expert::plan`]) starts.
    start: Vector3<f64>,
    /// [`DrawerExpert::with_aim_error`]: where the first approach and the first descent stop
    /// short (offsets in the table plane from the handle), each taken out when reached.
    aim: [Option<Vector3<f64>>; 2],
    /// [`DrawerExpert::with_missed_grasp`]: where the first descent goes instead of the
    /// handle, taken out when the grasp is retried.
    miss: Option<Vector3<f64>>,
}

/// A missed handle grasp's offset toward the robot (-x) from the handle's grip point (m): the
/// finger pads (22 mm wide) come down past the bar's free end (35 mm from its centre) with
/// room for the drift of a close (~8 mm toward the bar), and close on nothing.
const DRAWER_MISS_OUT_M: std::ops::RangeInclusive<f64> = 0.06..=0.075;

/// The pinch point sits this far above the handle bar's centre.
const HANDLE_GRIP_ABOVE: f64 = 0.004;
/// Pull the drawer to this far short of its travel.
const PULL_SHORT_OF_END: f64 = 0.012;

impl DrawerExpert {
    /// `sim` must be at the reset pose of a scene with a drawer.
    pub fn new(sim: &Sim) -> Option<DrawerExpert> {
        let drawer = sim.scene().drawer.as_ref()?;
        let (start, rot) = sim.tcp_pose();
        let down = row_major(rot);
        // The handle is a bar along x: close the fingers across it (along y; a bar is
        // symmetric under a half turn).
        let turn = turn_to(&down, std::f64::consts::FRAC_PI_2, std::f64::consts::PI);
        Some(DrawerExpert {
            task: sim.scene().task,
            phase: Phase::Approach,
            ticks_in_phase: 0,
            grasp_rot: *Rotation3::from_axis_angle(&Vector3::z_axis(), turn).matrix() * down,
            shut_x: drawer.handle_position(0.0)[0],
            goal: None,
            held: Vector3::zeros(),
            attempts: 1,
            last_gripper: 0.0,
            start: Vector3::from(start),
            aim: [None, None],
            miss: None,
        })
    }

    /// [`PickPlaceExpert::with_aim_error`] for the handle: the first approach hovers up to
    /// `max_m` beside it, the first descent pauses [`LOOK_ABOVE_GRASP`] above the grip a third
    /// as far off; each corrects over the handle before going on. 0 = the exact expert.
    pub fn with_aim_error(mut self, seed: u64, max_m: f64) -> DrawerExpert {
        self.aim = aim_offsets(seed, max_m);
        self
    }

    /// [`PickPlaceExpert::with_missed_grasp`] for the handle, in `fraction` of the scenes: the
    /// first descent goes down [`DRAWER_MISS_OUT_M`] toward the robot from the handle, past
    /// the bar's free end (up to 1 cm aside), and closes on nothing; the slide then finds no
    /// handle in the fingers and the expert's retry (up, open, back over the handle, grasp)
    /// does the rest. 0 = never.
    pub fn with_missed_grasp(mut self, seed: u64, fraction: f64) -> DrawerExpert {
        use rand::Rng;
        let Some(mut rng) = miss_draw(seed, fraction) else {
            self.miss = None;
            return self;
        };
        let out = rng.random_range(DRAWER_MISS_OUT_M);
        self.miss = Some(Vector3::new(-out, rng.random_range(-MISS_ALONG_M..=MISS_ALONG_M), 0.0));
        self.aim[1] = None;
        self
    }

    /// This scene's expert (`self`, made at the reset pose) taking over from the state `sim`
    /// is in now: sliding on if the fingers hold the handle, else from the approach.
    fn resume(&self, sim: &Sim) -> DrawerExpert {
        let pos = Vector3::from(sim.tcp_pose().0);
        let handle = Vector3::from(sim.handle_position().expect("a drawer scene"));
        let solved = task_success(sim);
        let (phase, held_at) = if held(sim, handle, pos) && !solved {
            (if self.task == Task::DrawerClose { Phase::Push } else { Phase::Pull }, pos)
        } else if solved {
            (Phase::Retreat, Vector3::zeros())
        } else {
            (Phase::Approach, Vector3::zeros())
        };
        DrawerExpert {
            phase,
            ticks_in_phase: 0,
            goal: None,
            held: held_at,
            attempts: 1,
            last_gripper: sim.gripper_position(),
            aim: [None, None],
            miss: None,
            ..self.clone()
        }
    }

    /// The path it means to take from the reset pose: to the handle, along the slide.
    fn plan(&self, sim: &Sim) -> Vec<[f64; 3]> {
        let h = sim.handle_position().expect("a drawer scene");
        let grip = [h[0], h[1], h[2] + HANDLE_GRIP_ABOVE];
        let end_x = match self.task {
            Task::DrawerClose => self.shut_x,
            _ => self.shut_x - (DRAWER_TRAVEL - PULL_SHORT_OF_END),
        };
        vec![
            self.start.into(),
            [grip[0], grip[1], grip[2] + HOVER_Z],
            grip,
            [end_x, grip[1], grip[2]],
            [end_x, grip[1], grip[2] + HOVER_Z],
        ]
    }

    pub fn phase(&self) -> Phase {
        self.phase
    }

    pub fn act(&mut self, sim: &Sim) -> Action {
        let (p, r) = sim.tcp_pose();
        let pos = Vector3::from(p);
        let rot = row_major(r);
        let handle = Vector3::from(sim.handle_position().expect("a drawer scene"));
        let opening = sim.drawer_opening().expect("a drawer scene");
        let grip = Vector3::new(handle.x, handle.y, handle.z + HANDLE_GRIP_ABOVE);
        let slide = match self.task {
            Task::DrawerClose => Phase::Push,
            _ => Phase::Pull,
        };
        let (target, gripper) = match self.phase {
            Phase::Approach => (grip + self.aim[0].unwrap_or_default() + Vector3::z() * HOVER_Z, 0.0),
            Phase::Descend => match (self.miss, self.aim[1]) {
                (Some(off), _) => (grip + off, 0.0),
                (None, Some(off)) => (grip + off + Vector3::z() * LOOK_ABOVE_GRASP, 0.0),
                (None, None) => (grip, 0.0),
            },
            Phase::Grasp => {
                self.held = pos;
                (pos, 1.0)
            }
            Phase::Pull => {
                (Vector3::new(self.shut_x - (DRAWER_TRAVEL - PULL_SHORT_OF_END), self.held.y, self.held.z), 1.0)
            }
            Phase::Push => (Vector3::new(self.shut_x, self.held.y, self.held.z), 1.0),
            Phase::Release => (self.held_now(pos), 0.0),
            _ => (Vector3::new(handle.x, handle.y, grip.z + HOVER_Z), 0.0),
        };
        let (next_p, next_r) = lead(self.goal.unwrap_or((pos, rot)), target, self.grasp_rot);
        self.goal = Some((next_p, next_r));
        self.ticks_in_phase += 1;
        let reached = (target - pos).norm() < 0.006 && (next_p - target).norm() < 1e-9;
        let done = match self.phase {
            Phase::Grasp => grip_settled(self.ticks_in_phase, sim.gripper_position(), self.last_gripper),
            Phase::Pull => reached || opening >= DRAWER_TRAVEL - PULL_SHORT_OF_END,
            Phase::Push => reached || opening <= 0.002,
            Phase::Release => grip_settled(self.ticks_in_phase, sim.gripper_position(), self.last_gripper),
            Phase::Done => false,
            _ => reached,
        };
        self.last_gripper = sim.gripper_position();
        // The handle slipped out of the fingers while sliding: let go and grasp again.
        let slipped = matches!(self.phase, Phase::Pull | Phase::Push) && (handle - pos).norm() > 0.03;
        if reached_aim(self.phase, &mut self.aim, done) {
            self.ticks_in_phase = 0;
        } else if slipped && self.attempts < MAX_ATTEMPTS {
            tracing::debug!(attempt = self.attempts, "expert: the handle slipped (or was missed); grasping again");
            self.attempts += 1;
            self.phase = Phase::Approach;
            self.ticks_in_phase = 0;
            self.miss = None;
            self.aim = [None, None];
        } else if done || (self.ticks_in_phase > PHASE_TIMEOUT && self.phase != Phase::Done) {
            tracing::debug!(phase = ?self.phase, ticks = self.ticks_in_phase, timed_out = !done, opening, "expert phase done");
            self.phase = if self.phase == Phase::Grasp { slide } else { self.next_phase() };
            self.ticks_in_phase = 0;
        }
        let e = euler_xyz(&next_r);
        Action {
            cartesian_position: [next_p.x, next_p.y, next_p.z, e[0], e[1], e[2]],
            gripper_position: gripper,
            phase: self.phase,
            target: target.into(),
        }
    }

    /// Where to hold still while the fingers open: where the TCP is.
    fn held_now(&self, pos: Vector3<f64>) -> Vector3<f64> {
        self.goal.map_or(pos, |(p, _)| p)
    }

    fn next_phase(&self) -> Phase {
        match self.phase {
            Phase::Approach => Phase::Descend,
            Phase::Descend => Phase::Grasp,
            Phase::Pull | Phase::Push => Phase::Release,
            Phase::Release => Phase::Retreat,
            _ => Phase::Done,
        }
    }
}

/// The expert for a scene's task.
#[derive(Debug, Clone)]
pub enum Expert {
    PickPlace(PickPlaceExpert),
    Drawer(DrawerExpert),
}

impl Expert {
    /// The expert for `sim`'s task; `sim` must be at its reset pose.
    pub fn new(sim: &Sim) -> Expert {
        match sim.scene().task {
            Task::PickPlace => Expert::PickPlace(PickPlaceExpert::new(sim)),
            Task::DrawerOpen | Task::DrawerClose => {
                Expert::Drawer(DrawerExpert::new(sim).expect("the spec validated a drawer for the drawer tasks"))
            }
        }
    }

    /// Pick-and-place demos with a missed grasp and its recovery in `fraction` of the scenes:
    /// [`PickPlaceExpert::with_missed_grasp`], [`DrawerExpert::with_missed_grasp`].
    pub fn with_missed_grasp(self, sim: &Sim, fraction: f64) -> Expert {
        let seed = sim.scene().seed;
        match self {
            Expert::PickPlace(e) => Expert::PickPlace(e.with_missed_grasp(seed, fraction)),
            Expert::Drawer(e) => Expert::Drawer(e.with_missed_grasp(seed, fraction)),
        }
    }

    /// Demos that look and correct: [`PickPlaceExpert::with_aim_error`],
    /// [`DrawerExpert::with_aim_error`], the offsets drawn from `sim`'s scene seed.
    pub fn with_aim_error(self, sim: &Sim, max_m: f64) -> Expert {
        let seed = sim.scene().seed;
        match self {
            Expert::PickPlace(e) => Expert::PickPlace(e.with_aim_error(seed, max_m)),
            Expert::Drawer(e) => Expert::Drawer(e.with_aim_error(seed, max_m)),
        }
    }

    pub fn act(&mut self, sim: &Sim) -> Action {
        match self {
            Expert::PickPlace(e) => e.act(sim),
            Expert::Drawer(e) => e.act(sim),
        }
    }

    pub fn phase(&self) -> Phase {
        match self {
            Expert::PickPlace(e) => e.phase(),
            Expert::Drawer(e) => e.phase(),
        }
    }

    /// The expert taking over mid-episode from the state `sim` is in now (a policy or an
    /// operator drove until here), `self` being the scene's expert made at its reset pose
    /// (it keeps that one's fingers-down orientation and grasp turn). The phase is inferred
    /// from the physics: an object (handle) held between closed fingers is carried on (slid
    /// on), one already in the bin (a drawer already solved) is left with a retreat, anything
    /// else starts from the approach, which opens the fingers. The goal is led from the TCP
    /// where it is, not from where the last plan was.
    pub fn resume(&self, sim: &Sim) -> Expert {
        match self {
            Expert::PickPlace(e) => Expert::PickPlace(e.resume(sim)),
            Expert::Drawer(e) => Expert::Drawer(e.resume(sim)),
        }
    }

    /// The whole path it plans for the scene, as a polyline through the phases' targets,
    /// from the reset pose's TCP (m, robot base frame): how far a TCP strays from it says
    /// how far another driver has wandered from any way this expert would go.
    pub fn plan(&self, sim: &Sim) -> Vec<[f64; 3]> {
        match self {
            Expert::PickPlace(e) => e.plan(sim),
            Expert::Drawer(e) => e.plan(sim),
        }
    }
}

/// Whether the fingers hold `what` (the object's centre, the handle): closed past an open
/// hand and it is between them, within 3 cm of the pinch point.
fn held(sim: &Sim, what: Vector3<f64>, tcp: Vector3<f64>) -> bool {
    sim.gripper_position() > 0.2 && (what - tcp).norm() < 0.03
}

/// Whether the scene's task is solved, judged on the physics.
pub fn task_success(sim: &Sim) -> bool {
    match sim.scene().task {
        Task::PickPlace => pick_place_success(sim),
        Task::DrawerOpen => drawer_open_success(sim),
        Task::DrawerClose => drawer_close_success(sim),
    }
}

/// drawer_open: the drawer is out by at least [`DRAWER_OPEN_M`] and the gripper has let go.
pub fn drawer_open_success(sim: &Sim) -> bool {
    sim.drawer_opening().is_some_and(|o| o >= DRAWER_OPEN_M) && sim.gripper_position() < 0.3
}

/// drawer_close: the drawer is in to at most [`DRAWER_CLOSED_M`] and the gripper has let go.
pub fn drawer_close_success(sim: &Sim) -> bool {
    sim.drawer_opening().is_some_and(|o| o <= DRAWER_CLOSED_M) && sim.gripper_position() < 0.3
}

/// The pick-and-place success predicate: the object rests inside the bin's walls and the
/// gripper no longer holds it.
pub fn pick_place_success(sim: &Sim) -> bool {
    let obj = sim.object_position();
    let bin = sim.scene().receptacle_position;
    let wall = 0.005;
    let inside = (obj[0] - bin[0]).abs() < BIN_HALF[0] - wall && (obj[1] - bin[1]).abs() < BIN_HALF[1] - wall;
    let resting = obj[2] < bin[2] + 0.01 + OBJECT_SIZE;
    let released = sim.gripper_position() < 0.3;
    inside && resting && released
}

/// One damped-least-squares IK step on MuJoCo's Jacobian, with a nullspace pull toward the
/// reset pose; the result is clamped inside the joint limits by a margin.
#[derive(Debug, Clone)]
pub struct CartesianIk {
    pub damping: f64,
    pub nullspace_gain: f64,
    pub limit_margin: f64,
    /// Largest lead of a target over the measured joint (rad): bounds the integrated error
    /// when the TCP is blocked (anti-windup).
    pub max_lead: f64,
    rest: [f64; 7],
    limits: [[f64; 2]; 7],
}

impl CartesianIk {
    pub fn new(sim: &Sim) -> CartesianIk {
        CartesianIk {
            damping: 0.02,
            nullspace_gain: 0.1,
            limit_margin: 0.02,
            max_lead: 0.05,
            rest: crate::rig::RESET_POSE,
            limits: sim.joint_limits(),
        }
    }

    /// Joint targets that move the TCP toward `pose` (xyz + extrinsic xyz euler). The step is
    /// added to the last targets, not the measured joints, so a steady tracking error of the
    /// joint servos (the gripper's weight sags the wrist) is integrated away.
    pub fn solve(&self, sim: &Sim, pose: &[f64; 6]) -> [f64; 7] {
        let (p, r) = sim.tcp_pose();
        let q = sim.joint_targets();
        let dp = Vector3::new(pose[0], pose[1], pose[2]) - Vector3::from(p);
        let target = from_euler_xyz([pose[3], pose[4], pose[5]]);
        let dr = UnitQuaternion::from_matrix(&(target * row_major(r).transpose())).scaled_axis();
        let err = SVector::<f64, 6>::new(dp.x, dp.y, dp.z, dr.x, dr.y, dr.z);
        let jac = sim.tcp_jacobian();
        let j = SMatrix::<f64, 6, 7>::from_fn(|row, col| jac[row][col]);
        let jjt = j * j.transpose() + Matrix6::identity() * self.damping.powi(2);
        let pinv = j.transpose() * jjt.try_inverse().unwrap_or_else(Matrix6::identity);
        let dq_task = pinv * err;
        let rest = SVector::<f64, 7>::from_fn(|i, _| self.nullspace_gain * (self.rest[i] - q[i]));
        let dq = dq_task + (SMatrix::<f64, 7, 7>::identity() - pinv * j) * rest;
        let measured = sim.joint_positions();
        std::array::from_fn(|i| {
            let [lo, hi] = self.limits[i];
            let lead = (q[i] + dq[i] - measured[i]).clamp(-self.max_lead, self.max_lead);
            (measured[i] + lead).clamp(lo + self.limit_margin, hi - self.limit_margin)
        })
    }
}

/// The outcome of one scripted episode.
#[derive(Debug, Clone, Serialize)]
pub struct EpisodeResult {
    pub seed: u64,
    pub task: Task,
    pub success: bool,
    pub ticks: u64,
    pub final_phase: Phase,
    pub object_position: [f64; 3],
    pub receptacle_position: [f64; 3],
    /// The drawer's opening (m) at the start and at the end, when the scene has one.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub drawer_opening: Option<[f64; 2]>,
    pub camera_bins: Vec<String>,
}

/// Runs the expert on `sim` (fresh from [`Sim::new`]) for at most `max_ticks`, stopping
/// early once it is done; `on_tick` sees every tick (for rendering or recording).
pub fn run_episode(
    sim: &mut Sim,
    max_ticks: u64,
    on_tick: impl FnMut(&mut Sim, &Action) -> Result<(), SimError>,
) -> Result<EpisodeResult, SimError> {
    let expert = Expert::new(sim);
    run_episode_with(sim, expert, max_ticks, on_tick)
}

/// [`run_episode`] with a given expert (e.g. [`Expert::with_aim_error`]), made at `sim`'s
/// reset pose.
pub fn run_episode_with(
    sim: &mut Sim,
    mut expert: Expert,
    max_ticks: u64,
    mut on_tick: impl FnMut(&mut Sim, &Action) -> Result<(), SimError>,
) -> Result<EpisodeResult, SimError> {
    let ik = CartesianIk::new(sim);
    let opening_at_start = sim.drawer_opening();
    let mut ticks = 0;
    while ticks < max_ticks {
        let action = expert.act(sim);
        let joints = ik.solve(sim, &action.cartesian_position);
        sim.step(&ArmTarget { joints, gripper: action.gripper_position })?;
        ticks += 1;
        on_tick(sim, &action)?;
        if action.phase == Phase::Done {
            break;
        }
    }
    // Let the object settle before judging.
    let hold = ArmTarget { joints: sim.joint_targets(), gripper: 0.0 };
    for _ in 0..10 {
        sim.step(&hold)?;
    }
    let scene = sim.scene();
    Ok(EpisodeResult {
        seed: scene.seed,
        task: scene.task,
        success: task_success(sim),
        ticks,
        final_phase: expert.phase(),
        object_position: sim.object_position(),
        receptacle_position: scene.receptacle_position,
        drawer_opening: opening_at_start.zip(sim.drawer_opening()).map(|(a, b)| [a, b]),
        camera_bins: scene
            .cameras
            .iter()
            .map(|(id, c)| format!("{id}:{}", c.bin.map_or("custom", |b| b.name())))
            .collect(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn euler_round_trips_like_scipy_xyz() {
        // scipy: R.from_euler("xyz", [0.3, -0.2, 1.1]).as_matrix()[0] = [0.444..., ...]
        let e = [0.3, -0.2, 1.1];
        let m = from_euler_xyz(e);
        // Extrinsic xyz = Rz(yaw) * Ry(pitch) * Rx(roll).
        let expect = Rotation3::from_axis_angle(&Vector3::z_axis(), 1.1)
            * Rotation3::from_axis_angle(&Vector3::y_axis(), -0.2)
            * Rotation3::from_axis_angle(&Vector3::x_axis(), 0.3);
        assert!((m - expect.matrix()).norm() < 1e-12);
        let back = euler_xyz(&m);
        for k in 0..3 {
            assert!((back[k] - e[k]).abs() < 1e-12);
        }
    }
}
