//! `labrig replay <episode> --sim` (run as `labrig-sim replay`): a recorded episode's actions
//! fed back through the rig's own path against the rebuilt scene, and the resulting robot
//! state compared with the recorded one.
//!
//! The scene comes from the episode's metadata (the sim scene: spec and seed) or `--scene` /
//! `--seed`. Each step's recorded action (the joint targets the loop sent, and the gripper)
//! goes through the same safety layer as in the bridge and steps the physics one control
//! period, in lockstep. Before step 0 the rig may have stood a few ticks after its scene was
//! loaded (the loop holds the arm until the episode starts): replay holds the same way and
//! starts where the recorded first state is matched best (reported as `aligned_ticks`).
//! Compared per step before each action: joints, TCP position and orientation, gripper; at the
//! end, the task's success then (metadata) and now (the expert's predicate on the physics).

use crate::expert::{euler_xyz, task_success};
use crate::safety_filter;
use crate::scene::SceneSpec;
use crate::{ArmTarget, Meshes, Sim, SimError};
use labrig_arm::safety::{ArmView, SafetyFilter};
use labrig_msgs::Nanos;
use labrig_msgs::rig::{ArmCommand, ArmCommandMode, RobotState, Step};
use nalgebra::{Matrix3, Rotation3, UnitQuaternion};
use serde::Serialize;
use std::path::PathBuf;
use std::time::Instant;

/// What to replay and how strictly to judge it.
#[derive(Debug, Clone)]
pub struct ReplayOptions {
    /// The episode: its directory or its .mcap file.
    pub episode: PathBuf,
    /// Rebuild the scene from this spec (file or built-in name) instead of the episode's.
    pub scene: Option<PathBuf>,
    /// The scene seed (default: the episode's).
    pub seed: Option<u64>,
    pub assets: Option<PathBuf>,
    /// Render the five cameras every step (as the bridge does), for the speed figure.
    pub cameras: bool,
    pub width: usize,
    pub height: usize,
    /// Tolerances: the replay fails when a maximum error exceeds one.
    pub max_joint_error_rad: f64,
    pub max_tcp_error_m: f64,
    pub max_rotation_error_rad: f64,
    pub max_gripper_error: f64,
    /// Add this (rad) to every recorded joint-1 target: a what-if, and the proof the check fails.
    pub perturb_joint1_rad: f64,
}

/// Why an episode could not be replayed (a replay that deviates is a [`Report`] with
/// `exceeded` set, not an error).
#[derive(Debug, thiserror::Error)]
pub enum ReplayError {
    #[error(transparent)]
    Read(#[from] labrig_episode::ReadError),
    #[error("{}: no /rig/step records{hint}: nothing to replay", file.display())]
    NoSteps { file: PathBuf, hint: &'static str },
    #[error("{}: step {index} is missing (found index {found} there): replay needs every step", file.display())]
    MissingStep { file: PathBuf, index: usize, found: u64 },
    #[error("{}: steps 0 and 1 have the same stamp", file.display())]
    SameStamp { file: PathBuf },
    /// The episode's metadata does not say which scene it was recorded in.
    #[error("{0}")]
    Scene(String),
    #[error("scene {scene} seed {seed}: {source}")]
    Build {
        scene: String,
        seed: u64,
        #[source]
        source: SimError,
    },
    #[error("{what}: {source}")]
    Sim {
        what: String,
        #[source]
        source: SimError,
    },
    #[error(transparent)]
    Spec(#[from] crate::scene::SceneError),
    #[error(transparent)]
    Safety(#[from] crate::SafetySetupError),
    #[error("holding: {0}")]
    Hold(labrig_arm::safety::Refusal),
}

#[derive(Debug, Clone)]
struct FontMissing(String);

/// The plot could not be drawn or written.
#[derive(Debug, thiserror::Error)]
#[error("plotting to {}: {reason}", path.display())]
pub struct PlotError {
    pub path: PathBuf,
    pub reason: String,
}

/// Max and RMS of one error series.
#[derive(Debug, Clone, Copy, Default, Serialize, PartialEq)]
pub struct Error {
    pub max: f64,
    pub rms: f64,
}

impl Error {
    fn of(v: &[f64]) -> Error {
        if v.is_empty() {
            return Error::default();
        }
        Error {
            max: v.iter().copied().fold(0.0, f64::max),
            rms: (v.iter().map(|x| x * x).sum::<f64>() / v.len() as f64).sqrt(),
        }
    }
}

#[derive(Debug, Clone, Serialize)]
pub struct Report {
    pub episode: PathBuf,
    pub scene: String,
    pub seed: u64,
    pub steps: usize,
    pub aligned_ticks: usize,
    pub joint_rad: Vec<Error>,
    pub tcp_m: Error,
    pub rotation_rad: Error,
    pub gripper: Error,
    pub success_recorded: Option<bool>,
    pub success_replayed: bool,
    /// Simulated seconds per wall second.
    pub realtime_factor: f64,
    pub steps_per_s: f64,
    pub cameras: bool,
    /// Which tolerances were exceeded (empty: the replay passed).
    pub exceeded: Vec<String>,
    /// Recorded vs replayed TCP position per step (m).
    pub tcp_recorded: Vec<[f64; 3]>,
    pub tcp_replayed: Vec<[f64; 3]>,
    /// Per step: TCP position error (m) and the largest joint error (rad).
    pub tcp_error_m: Vec<f64>,
    pub joint_error_rad: Vec<f64>,
    /// The period the steps were recorded at (s).
    pub period_s: f64,
}

fn rotation(euler: &[f64]) -> Rotation3<f64> {
    Rotation3::from_euler_angles(euler[0], euler[1], euler[2])
}

/// The scene of a recorded episode: its spec and seed from the metadata's sim scene.
fn recorded_scene(sim_scene: Option<&str>) -> Result<(SceneSpec, u64), ReplayError> {
    let scene = |m: &str| ReplayError::Scene(m.to_owned());
    let json = sim_scene.ok_or_else(|| {
        scene("the episode has no sim scene in its metadata (not recorded in the simulated rig?): give --scene and --seed")
    })?;
    let v: serde_json::Value = serde_json::from_str(json)
        .map_err(|e| ReplayError::Scene(format!("the episode's sim scene is not JSON: {e}")))?;
    let spec = v.get("spec").cloned().ok_or_else(|| {
        scene("the episode's sim scene has no spec (recorded before scenes carried theirs): give --scene (e.g. pick_place)")
    })?;
    let spec: SceneSpec =
        serde_json::from_value(spec).map_err(|e| ReplayError::Scene(format!("the episode's scene spec: {e}")))?;
    let seed = v["seed"].as_u64().ok_or_else(|| scene("the episode's sim scene has no seed"))?;
    Ok((spec, seed))
}

/// Replays `a.episode` against its rebuilt scene and compares the states.
pub fn replay(a: &ReplayOptions) -> Result<Report, ReplayError> {
    let ep = read_steps(a)?;
    let meta = ep.metadata.as_ref();
    let (spec, seed) = scene_of(a, meta)?;
    let steps: &[Step] = &ep.steps;
    check_every_step(&ep.file, steps)?;
    let period = recorded_period(&ep.file, steps)?;
    let rig = ReplayRig {
        a,
        spec: &spec,
        seed,
        period,
        assets: crate::assets_dir(a.assets.as_deref()),
        safety: safety_filter(period, None)?,
    };
    let (mut sim, mut commanded, aligned) = rig.aligned_start(&steps[0].robot_state)?;
    let started = Instant::now();
    let mut dev = Deviations::new(steps.len());
    let mut rgb = Vec::new();
    for (k, s) in steps.iter().enumerate() {
        dev.compare(&sim, &s.robot_state);
        rig.act(&mut sim, &mut commanded, k, s)?;
        if a.cameras {
            rig.render(&mut sim, &mut rgb, k)?;
        }
    }
    let wall = started.elapsed().as_secs_f64().max(1e-9);
    let joint_rad: Vec<Error> = dev.joint.iter().map(|v| Error::of(v)).collect();
    let (tcp_m, rotation_rad, gripper) = (Error::of(&dev.tcp), Error::of(&dev.rotation), Error::of(&dev.gripper));
    let exceeded = exceeded(a, &joint_rad, tcp_m, rotation_rad, gripper);
    let joint_error_rad = dev.largest_joint_errors();
    Ok(Report {
        episode: ep.file.clone(),
        scene: spec.name.clone(),
        seed,
        steps: steps.len(),
        aligned_ticks: aligned,
        joint_rad,
        tcp_m,
        rotation_rad,
        gripper,
        success_recorded: meta.and_then(|m| m.success),
        success_replayed: task_success(&sim),
        realtime_factor: steps.len() as f64 * period.as_secs_f64() / wall,
        steps_per_s: steps.len() as f64 / wall,
        cameras: a.cameras,
        exceeded,
        tcp_recorded: dev.tcp_recorded,
        tcp_replayed: dev.tcp_replayed,
        joint_error_rad,
        tcp_error_m: dev.tcp,
        period_s: period.as_secs_f64(),
    })
}

/// The episode, which must hold steps to replay.
fn read_steps(a: &ReplayOptions) -> Result<labrig_episode::EpisodeData, ReplayError> {
    let ep = labrig_episode::read_episode(&a.episode)?;
    if ep.steps.is_empty() {
        let hint = if ep.complete {
            ""
        } else {
            " in its readable part (the file is unfinished or truncated; try `labrig recover`)"
        };
        return Err(ReplayError::NoSteps { file: ep.file.clone(), hint });
    }
    Ok(ep)
}

/// The scene to rebuild and its seed: `--scene` / `--seed` where given, else the recorded ones.
fn scene_of(
    a: &ReplayOptions,
    meta: Option<&labrig_episode::EpisodeMetadata>,
) -> Result<(SceneSpec, u64), ReplayError> {
    Ok(match &a.scene {
        Some(path) => {
            let (spec, _) = crate::resolve_scene(Some(path), a.assets.as_deref())?;
            let seed = match a.seed {
                Some(s) => s,
                None => recorded_scene(meta.and_then(|m| m.sim_scene.as_deref()))?.1,
            };
            (spec, seed)
        }
        None => {
            let (spec, seed) = recorded_scene(meta.and_then(|m| m.sim_scene.as_deref()))?;
            (spec, a.seed.unwrap_or(seed))
        }
    })
}

/// Replay needs every step: each step's index must be its place.
fn check_every_step(file: &std::path::Path, steps: &[Step]) -> Result<(), ReplayError> {
    for (k, s) in steps.iter().enumerate() {
        if s.step_index != k as u64 {
            return Err(ReplayError::MissingStep { file: file.to_owned(), index: k, found: s.step_index });
        }
    }
    Ok(())
}

/// The period the steps were recorded at (steps 0 and 1 apart; 50 ms for a single step).
fn recorded_period(file: &std::path::Path, steps: &[Step]) -> Result<Nanos, ReplayError> {
    let stamp = |s: &Step| Nanos::from(s.header.stamp).0;
    let period = if steps.len() > 1 { Nanos(stamp(&steps[1]) - stamp(&steps[0])) } else { Nanos::from_millis(50) };
    if period.0 <= 0 {
        return Err(ReplayError::SameStamp { file: file.to_owned() });
    }
    Ok(period)
}

/// A step of the sim that failed, as the replay's error, saying `what` was being done.
fn sim_err(what: String) -> impl FnOnce(SimError) -> ReplayError {
    move |source| ReplayError::Sim { what, source }
}

/// The rebuilt rig: the scene's physics behind the bridge's safety layer.
struct ReplayRig<'a> {
    a: &'a ReplayOptions,
    spec: &'a SceneSpec,
    seed: u64,
    period: Nanos,
    assets: PathBuf,
    safety: SafetyFilter,
}

impl ReplayRig<'_> {
    /// The scene built afresh (its cameras enabled when asked).
    fn build(&self) -> Result<Sim, ReplayError> {
        let built = |source| ReplayError::Build { scene: self.spec.name.clone(), seed: self.seed, source };
        let mut sim = Sim::new(&self.assets, self.spec, self.seed, self.period).map_err(built)?;
        if self.a.cameras {
            sim.enable_cameras(self.a.width, self.a.height, Meshes::Collision).map_err(built)?;
        }
        Ok(sim)
    }

    /// One tick of the arm held after the scene loaded (the loop's hold: its measured joints,
    /// gripper open).
    fn hold(&self, sim: &mut Sim, commanded: &mut Option<[f64; 7]>) -> Result<(), ReplayError> {
        let cmd = ArmCommand {
            mode: ArmCommandMode::JointPosition as u8,
            joint_position: commanded.unwrap_or_else(|| sim.joint_positions()),
            ..Default::default()
        };
        let view =
            ArmView { measured: sim.joint_positions(), commanded: commanded.unwrap_or_else(|| sim.joint_targets()) };
        let ok = self.safety.filter(&cmd, &view, sim.time()).map_err(ReplayError::Hold)?;
        let t = ArmTarget { joints: ok.joints, gripper: ok.gripper };
        sim.check(&t).map_err(sim_err("holding".into()))?;
        sim.step(&t).map_err(sim_err("holding".into()))?;
        *commanded = Some(ok.joints);
        Ok(())
    }

    /// Align: the scene held as many ticks after it loaded as match the recorded `first` state
    /// best (rebuilt for that when the search moved it); the sim, its commanded joints and the
    /// ticks held.
    fn aligned_start(&self, first: &RobotState) -> Result<(Sim, Option<[f64; 7]>, usize), ReplayError> {
        const MAX_ALIGN: usize = 20;
        let distance = |sim: &Sim, r: &RobotState| {
            let q = sim.joint_positions();
            (0..7)
                .map(|i| (q[i] - r.joint_positions[i]).abs())
                .fold((sim.gripper_position() - r.gripper_position).abs(), f64::max)
        };
        let mut sim = self.build()?;
        let mut commanded = None;
        let mut best = (distance(&sim, first), 0usize);
        for k in 1..=MAX_ALIGN {
            if best.0 == 0.0 {
                break;
            }
            self.hold(&mut sim, &mut commanded)?;
            let d = distance(&sim, first);
            if d < best.0 {
                best = (d, k);
            }
        }
        let aligned = best.1;
        if best.0 != 0.0 || commanded.is_some() {
            sim = self.build()?;
            commanded = None;
            for _ in 0..aligned {
                self.hold(&mut sim, &mut commanded)?;
            }
        }
        Ok((sim, commanded, aligned))
    }

    /// Step `k`'s recorded action through the bridge's path: safety layer, the sim's own check,
    /// one period; refused now (as it would be on the rig), the arm holds and the deviation shows.
    fn act(&self, sim: &mut Sim, commanded: &mut Option<[f64; 7]>, k: usize, s: &Step) -> Result<(), ReplayError> {
        let mut target = s.action.joint_position;
        target[0] += self.a.perturb_joint1_rad;
        let cmd = ArmCommand {
            mode: ArmCommandMode::JointPosition as u8,
            joint_position: target,
            gripper_position: s.action.gripper_position,
            ..Default::default()
        };
        let view =
            ArmView { measured: sim.joint_positions(), commanded: commanded.unwrap_or_else(|| sim.joint_targets()) };
        match self.safety.filter(&cmd, &view, sim.time()) {
            Ok(ok) => {
                let t = ArmTarget { joints: ok.joints, gripper: ok.gripper };
                sim.check(&t).map_err(sim_err(format!("step {k}")))?;
                sim.step(&t).map_err(sim_err(format!("step {k}")))?;
                *commanded = Some(ok.joints);
            }
            Err(e) => {
                tracing::warn!("step {k}: the recorded action is refused: {e}; holding");
                self.hold(sim, commanded)?;
            }
        }
        Ok(())
    }

    /// Step `k`'s five camera images rendered (for the speed figure), into `rgb`.
    fn render(&self, sim: &mut Sim, rgb: &mut Vec<u8>, k: usize) -> Result<(), ReplayError> {
        for cam in crate::rig::CAMERAS {
            sim.render_into(cam, rgb).map_err(sim_err(format!("step {k}: rendering {cam}")))?;
        }
        Ok(())
    }
}

/// The replayed state against the recorded one, per step.
struct Deviations {
    /// Per joint, per step (rad).
    joint: Vec<Vec<f64>>,
    /// TCP position (m), TCP rotation (rad), gripper.
    tcp: Vec<f64>,
    rotation: Vec<f64>,
    gripper: Vec<f64>,
    tcp_recorded: Vec<[f64; 3]>,
    tcp_replayed: Vec<[f64; 3]>,
}

impl Deviations {
    fn new(steps: usize) -> Deviations {
        Deviations {
            joint: (0..7).map(|_| Vec::with_capacity(steps)).collect(),
            tcp: Vec::new(),
            rotation: Vec::new(),
            gripper: Vec::new(),
            tcp_recorded: Vec::new(),
            tcp_replayed: Vec::new(),
        }
    }

    /// `sim`'s state before a step's action compared with the recorded `r`: joints, TCP
    /// position and orientation, gripper.
    fn compare(&mut self, sim: &Sim, r: &RobotState) {
        let q = sim.joint_positions();
        for (j, errors) in self.joint.iter_mut().enumerate() {
            errors.push((q[j] - r.joint_positions[j]).abs());
        }
        let (p, rot) = sim.tcp_pose();
        let rot = Matrix3::from_row_slice(&rot);
        let rec_p = [r.cartesian_position[0], r.cartesian_position[1], r.cartesian_position[2]];
        self.tcp.push(((p[0] - rec_p[0]).powi(2) + (p[1] - rec_p[1]).powi(2) + (p[2] - rec_p[2]).powi(2)).sqrt());
        let here = UnitQuaternion::from_rotation_matrix(&rotation(&euler_xyz(&rot)));
        let rec = UnitQuaternion::from_rotation_matrix(&rotation(&r.cartesian_position[3..6]));
        // 2 atan2(|v|, |w|) of the relative rotation: exact near zero, where acos is not.
        let rel = here.inverse() * rec;
        self.rotation.push(2.0 * rel.imag().norm().atan2(rel.scalar().abs()));
        self.gripper.push((sim.gripper_position() - r.gripper_position).abs());
        self.tcp_recorded.push(rec_p);
        self.tcp_replayed.push(p);
    }

    /// The largest joint error of each step.
    fn largest_joint_errors(&self) -> Vec<f64> {
        (0..self.joint[0].len()).map(|k| (0..7).map(|j| self.joint[j][k]).fold(0.0, f64::max)).collect()
    }
}

/// The tolerances the errors exceed, said (a NaN, a diverged replay, counts as exceeded).
fn exceeded(a: &ReplayOptions, joint_rad: &[Error], tcp_m: Error, rotation_rad: Error, gripper: Error) -> Vec<String> {
    let mut exceeded = Vec::new();
    let worst_joint = joint_rad.iter().map(|e| e.max).fold(0.0, f64::max);
    for (what, value, limit) in [
        ("joint", worst_joint, a.max_joint_error_rad),
        ("tcp position", tcp_m.max, a.max_tcp_error_m),
        ("tcp rotation", rotation_rad.max, a.max_rotation_error_rad),
        ("gripper", gripper.max, a.max_gripper_error),
    ] {
        // NaN (a diverged replay) counts as exceeded.
        if !matches!(value.partial_cmp(&limit), Some(std::cmp::Ordering::Less | std::cmp::Ordering::Equal)) {
            exceeded.push(format!("{what} error {value:.3e} > {limit:.3e}"));
        }
    }
    exceeded
}

/// The report as the text `labrig replay` prints.
pub fn text(r: &Report) -> String {
    use std::fmt::Write;
    let mut s = String::new();
    let _ = writeln!(s, "replay of {} ({} steps) in scene {} seed {}", r.episode.display(), r.steps, r.scene, r.seed);
    let _ = writeln!(s, "  started {} held ticks after the scene loaded (as recorded)", r.aligned_ticks);
    for (j, e) in r.joint_rad.iter().enumerate() {
        let _ = writeln!(s, "  joint {}: max {:.3e} rad, rms {:.3e} rad", j + 1, e.max, e.rms);
    }
    let _ = writeln!(s, "  tcp position: max {:.3e} m, rms {:.3e} m", r.tcp_m.max, r.tcp_m.rms);
    let _ = writeln!(s, "  tcp rotation: max {:.3e} rad, rms {:.3e} rad", r.rotation_rad.max, r.rotation_rad.rms);
    let _ = writeln!(s, "  gripper: max {:.3e}, rms {:.3e}", r.gripper.max, r.gripper.rms);
    let then = r.success_recorded.map_or("unknown".to_string(), |b| b.to_string());
    let _ = writeln!(s, "  task success: recorded {then}, replayed {}", r.success_replayed);
    let _ = writeln!(
        s,
        "  speed: {:.0} steps/s, {:.1}x real time ({})",
        r.steps_per_s,
        r.realtime_factor,
        if r.cameras { "five cameras rendered" } else { "no rendering" }
    );
    if r.exceeded.is_empty() {
        let _ = writeln!(s, "  PASS: within tolerances");
    } else {
        let _ = writeln!(s, "  FAIL: {}", r.exceeded.join("; "));
    }
    s
}

/// A sans-serif TrueType font for the plot's text (Debian's DejaVu, installed by setup).
/// The error is the reason (kept as text so every later plot repeats the first attempt's).
fn register_font() -> Result<(), FontMissing> {
    static DONE: std::sync::OnceLock<Result<(), FontMissing>> = std::sync::OnceLock::new();
    DONE.get_or_init(|| {
        let bytes = labrig_episode::font::dejavu_sans().map_err(|e| FontMissing(e.to_string()))?;
        plotters::style::register_font("sans-serif", plotters::style::FontStyle::Normal, bytes)
            .map_err(|_| FontMissing("DejaVuSans.ttf is not a font ab_glyph can read".into()))
    })
    .clone()
}

/// Top: recorded (solid) and replayed (dashed) TCP x, y, z over time. Bottom: the TCP position
/// error (mm) and the largest joint error (mrad) per step.
pub fn plot(r: &Report, path: &std::path::Path) -> Result<(), PlotError> {
    use plotters::prelude::*;
    let err = |e| PlotError { path: path.to_owned(), reason: format!("{e:?}") };
    register_font().map_err(|FontMissing(reason)| PlotError { path: path.to_owned(), reason })?;
    let root = BitMapBackend::new(path, (1200, 900)).into_drawing_area();
    root.fill(&WHITE).map_err(err)?;
    let (top, bottom) = root.split_vertically(520);
    let t: Vec<f64> = (0..r.steps).map(|k| k as f64 * r.period_s).collect();
    let t_end = t.last().copied().unwrap_or(1.0).max(r.period_s);
    let all = r.tcp_recorded.iter().chain(&r.tcp_replayed).flat_map(|p| p.iter().copied());
    let (lo, hi) = all.fold((f64::MAX, f64::MIN), |(lo, hi), v| (lo.min(v), hi.max(v)));
    let pad = ((hi - lo) * 0.05).max(0.01);
    let mut chart = ChartBuilder::on(&top)
        .caption(format!("{}: TCP recorded (solid) vs replayed (dashed)", r.scene), ("sans-serif", 22))
        .margin(12)
        .x_label_area_size(36)
        .y_label_area_size(60)
        .build_cartesian_2d(0.0..t_end, (lo - pad)..(hi + pad))
        .map_err(err)?;
    chart.configure_mesh().x_desc("time (s)").y_desc("position (m)").draw().map_err(err)?;
    let colours = [RED, RGBColor(0, 150, 0), BLUE];
    for (axis, name) in ["x", "y", "z"].iter().enumerate() {
        let c = colours[axis];
        let rec: Vec<(f64, f64)> = t.iter().zip(&r.tcp_recorded).map(|(&t, p)| (t, p[axis])).collect();
        chart
            .draw_series(LineSeries::new(rec, c.stroke_width(2)))
            .map_err(err)?
            .label(format!("{name} recorded"))
            .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], c.stroke_width(2)));
        let rep: Vec<(f64, f64)> = t.iter().zip(&r.tcp_replayed).map(|(&t, p)| (t, p[axis])).collect();
        chart
            .draw_series(DashedLineSeries::new(rep, 6, 4, c.stroke_width(2)))
            .map_err(err)?
            .label(format!("{name} replayed"))
            // Dashed in the legend too, as the series and the title say.
            .legend(move |(x, y)| {
                plotters::element::DashedPathElement::new(vec![(x, y), (x + 20, y)], 6, 4, c.stroke_width(2))
            });
    }
    chart.configure_series_labels().background_style(WHITE.mix(0.8)).border_style(BLACK).draw().map_err(err)?;
    let tcp_mm: Vec<f64> = r.tcp_error_m.iter().map(|e| e * 1e3).collect();
    let joint_mrad: Vec<f64> = r.joint_error_rad.iter().map(|e| e * 1e3).collect();
    let top_err = tcp_mm.iter().chain(&joint_mrad).copied().filter(|v| v.is_finite()).fold(0.0, f64::max).max(1e-3);
    let mut chart = ChartBuilder::on(&bottom)
        .caption(
            format!(
                "error per step: TCP max {:.3} mm, joint max {:.3} mrad ({})",
                r.tcp_m.max * 1e3,
                r.joint_rad.iter().map(|e| e.max).fold(0.0, f64::max) * 1e3,
                if r.exceeded.is_empty() { "within tolerances" } else { "EXCEEDS tolerances" }
            ),
            ("sans-serif", 22),
        )
        .margin(12)
        .x_label_area_size(36)
        .y_label_area_size(60)
        .build_cartesian_2d(0.0..t_end, 0.0..top_err * 1.1)
        .map_err(err)?;
    chart.configure_mesh().x_desc("time (s)").y_desc("mm / mrad").draw().map_err(err)?;
    chart
        .draw_series(LineSeries::new(t.iter().copied().zip(tcp_mm), RED.stroke_width(2)))
        .map_err(err)?
        .label("TCP position error (mm)")
        .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], RED.stroke_width(2)));
    chart
        .draw_series(LineSeries::new(t.iter().copied().zip(joint_mrad), BLUE.stroke_width(2)))
        .map_err(err)?
        .label("largest joint error (mrad)")
        .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], BLUE.stroke_width(2)));
    chart.configure_series_labels().background_style(WHITE.mix(0.8)).border_style(BLACK).draw().map_err(err)?;
    root.present().map_err(err)?;
    Ok(())
}
