//! `labrig-sim` (run as `labrig sim ...`): the simulated rig's commands.

use anyhow::Context;
use clap::{Args, Subcommand};
use labrig_msgs::Nanos;
use labrig_sim::expert::{self, EpisodeResult};
use labrig_sim::replay::ReplayOptions;
use labrig_sim::{Meshes, Sim};
use labrig_sim_bridge::bridge::BridgeNode;
use std::path::PathBuf;
use std::process::ExitCode;

/// `labrig-sim`'s tools beside `run` (the bridge node, [`BridgeNode`]).
#[derive(Debug, Subcommand)]
enum Tool {
    /// Render the five cameras of a scene to PNGs, with the scene's sampled values as JSON.
    Snapshot(SnapshotArgs),
    /// Run the scripted expert of the scene's task on many seeded scenes; report its success rate.
    Eval(EvalArgs),
    /// Physics steps per second, render time per frame, real-time factor.
    Bench(labrig_sim_bridge::bench::BenchArgs),
    /// Replay a recorded episode's actions against its rebuilt scene; compare the states (exit 5 beyond tolerances).
    Replay(ReplayArgs),
    /// Take a camera's calibration views: the board in the scene, the arm through the safety
    /// layer over DROID's pose set (what `labrig calibrate --sim` runs).
    CalibCapture(CalibCaptureArgs),
}

#[derive(Debug, Args)]
struct CalibCaptureArgs {
    #[command(flatten)]
    scene: SceneArgs,
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// ext1, ext2, wrist, rs1 or rs2.
    #[arg(long)]
    camera: String,
    /// The board's print (PNG, edge to edge).
    #[arg(long)]
    print: PathBuf,
    /// The board's spec (JSON, labrig_msgs::calibration::BoardSpec).
    #[arg(long)]
    board: PathBuf,
    #[arg(long, default_value_t = 60)]
    views: usize,
    /// Views are rendered at the real cameras' resolution.
    #[arg(long, default_value_t = 1280)]
    width: usize,
    #[arg(long, default_value_t = 720)]
    height: usize,
    #[arg(long, default_value_t = 0.10)]
    amplitude_m: f64,
    #[arg(long, default_value_t = 0.2)]
    amplitude_rad: f64,
    /// Move the camera by dx,dy,dz (m, base frame) from where the scene puts it.
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true)]
    move_camera: Option<Vec<f64>>,
    /// The print's width,height (m) when it is not the board `--board` describes (default:
    /// the board's own size).
    #[arg(long, value_delimiter = ',')]
    print_size_m: Option<Vec<f64>>,
    #[arg(long, default_value = "sim")]
    rig: String,
    /// Output folder (capture.json + view_NNN.pgm).
    #[arg(long)]
    out: PathBuf,
    /// No progress bar.
    #[arg(long)]
    quiet: bool,
}

/// Which scene: a spec file (default: the built-in pick-and-place scene) and a seed.
#[derive(Debug, Clone, Args)]
pub struct SceneArgs {
    /// Scene spec (TOML file) or a built-in scene: pick_place (default), drawer_open, drawer_close.
    #[arg(long)]
    scene: Option<PathBuf>,
    /// Where setup extracted the MuJoCo models (default: $LABRIG_MUJOCO_DIR/assets, else
    /// .labrig/mujoco/assets in the repository).
    #[arg(long, env = "LABRIG_SIM_ASSETS")]
    assets: Option<PathBuf>,
}

#[derive(Debug, Args)]
struct SnapshotArgs {
    #[command(flatten)]
    scene: SceneArgs,
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Output folder (created).
    #[arg(long)]
    out: PathBuf,
    #[arg(long, default_value_t = 320)]
    width: usize,
    #[arg(long, default_value_t = 240)]
    height: usize,
    /// visual or collision.
    #[arg(long, default_value_t = Meshes::Visual)]
    meshes: Meshes,
}

#[derive(Debug, Args)]
struct EvalArgs {
    #[command(flatten)]
    scene: SceneArgs,
    /// Number of seeded scenes (seeds first..first+episodes).
    #[arg(long, default_value_t = 50)]
    episodes: u64,
    #[arg(long, default_value_t = 0)]
    first_seed: u64,
    /// Tick budget per episode (20 Hz).
    #[arg(long, default_value_t = 400)]
    max_ticks: u64,
    /// Print one JSON object instead of text.
    #[arg(long)]
    json: bool,
    /// Exit non-zero when the success rate is below this (0..1).
    #[arg(long)]
    min_success: Option<f64>,
    /// The expert that looks and corrects (`expert_aim_error_m`): its first approach stops up
    /// to this far (m) beside the object (handle). 0 = the exact expert.
    #[arg(long, default_value_t = 0.0)]
    aim_error_m: f64,
    /// Demos with a missed grasp and its recovery (`expert_miss_fraction`): in this fraction
    /// of the scenes the first grasp closes beside the object (handle) on purpose. 0 = never.
    #[arg(long, default_value_t = 0.0)]
    miss_fraction: f64,
}

/// Exit status when the replay deviates beyond the tolerances.
const EXIT_DEVIATION: u8 = 5;

#[derive(Debug, Args)]
struct ReplayArgs {
    /// The episode: its directory or its .mcap file.
    episode: PathBuf,
    /// Replay against the simulated rig: the only replay target (no real-robot replay), which
    /// `labrig replay` asks to be named.
    #[arg(long)]
    sim: bool,
    /// Rebuild the scene from this spec (file or built-in name) instead of the episode's.
    #[arg(long)]
    scene: Option<PathBuf>,
    /// The scene seed (default: the episode's).
    #[arg(long)]
    seed: Option<u64>,
    #[arg(long, env = "LABRIG_SIM_ASSETS")]
    assets: Option<PathBuf>,
    /// Render the five cameras every step (as the bridge does), for the speed figure.
    #[arg(long)]
    cameras: bool,
    #[arg(long, default_value_t = 128)]
    width: usize,
    #[arg(long, default_value_t = 128)]
    height: usize,
    /// Tolerances: the replay fails (exit 5) when a maximum error exceeds one.
    #[arg(long, default_value_t = 0.01)]
    max_joint_error_rad: f64,
    #[arg(long, default_value_t = 0.005)]
    max_tcp_error_m: f64,
    #[arg(long, default_value_t = 0.02)]
    max_rotation_error_rad: f64,
    #[arg(long, default_value_t = 0.05)]
    max_gripper_error: f64,
    /// Add this (rad) to every recorded joint-1 target: a what-if, and the proof the check fails.
    #[arg(long, default_value_t = 0.0)]
    perturb_joint1_rad: f64,
    #[arg(long)]
    json: bool,
    /// Write a PNG: recorded vs replayed TCP trajectory, and the errors over time.
    #[arg(long)]
    plot: Option<PathBuf>,
}

fn main() -> ExitCode {
    labrig_runtime::node_main_with::<BridgeNode, Tool, _>(|tool, _, _| match tool {
        Tool::Snapshot(a) => snapshot(a),
        Tool::Eval(a) => eval(a),
        Tool::Bench(a) => labrig_sim_bridge::bench::run(a),
        Tool::Replay(a) => replay(a),
        Tool::CalibCapture(a) => calib_capture(a),
    })
}

fn snapshot(a: SnapshotArgs) -> anyhow::Result<ExitCode> {
    let (spec, assets) = labrig_sim::resolve_scene(a.scene.scene.as_deref(), a.scene.assets.as_deref())?;
    let shot = labrig_sim::snapshot::snapshot(&assets, &spec, a.seed, &a.out, (a.width, a.height), a.meshes)?;
    for p in &shot.images {
        println!("{}", p.display());
    }
    println!("{}  (all five cameras)", shot.sheet.display());
    println!("{}  (scene values)", shot.values.display());
    Ok(ExitCode::SUCCESS)
}

fn eval(a: EvalArgs) -> anyhow::Result<ExitCode> {
    let (spec, assets) = labrig_sim::resolve_scene(a.scene.scene.as_deref(), a.scene.assets.as_deref())?;
    let bar = labrig_episode::progress::bar("{bar:30} {pos}/{len} scenes", a.episodes, a.json);
    let mut results: Vec<EpisodeResult> = Vec::new();
    for seed in a.first_seed..a.first_seed + a.episodes {
        let mut sim = Sim::new(&assets, &spec, seed, Nanos::from_millis(50)).with_context(|| format!("seed {seed}"))?;
        let e = expert::Expert::new(&sim).with_aim_error(&sim, a.aim_error_m).with_missed_grasp(&sim, a.miss_fraction);
        let r = expert::run_episode_with(&mut sim, e, a.max_ticks, |_, _| Ok(()))?;
        results.push(r);
        let ok = results.iter().filter(|r| r.success).count();
        bar.set_message(format!("{ok} succeeded"));
        bar.inc(1);
    }
    bar.finish_and_clear();
    let ok = results.iter().filter(|r| r.success).count();
    let rate = ok as f64 / results.len().max(1) as f64;
    // Success per camera bin of ext1 (the camera that draws from all five bins).
    let mut per_bin: std::collections::BTreeMap<String, (u32, u32)> = Default::default();
    for r in &results {
        for b in &r.camera_bins {
            let e = per_bin.entry(b.clone()).or_default();
            e.1 += 1;
            e.0 += r.success as u32;
        }
    }
    if a.json {
        let json = serde_json::json!({
            "scene": spec.name, "episodes": results.len(), "successes": ok, "success_rate": rate,
            "per_camera_bin": per_bin.iter().map(|(k, (s, n))| (k.clone(), serde_json::json!({"successes": s, "episodes": n}))).collect::<serde_json::Map<_, _>>(),
            "results": results,
        });
        println!("{}", serde_json::to_string_pretty(&json)?);
    } else {
        println!("scene {}: {ok}/{} episodes succeeded ({:.0}%)", spec.name, results.len(), rate * 100.0);
        let ticks: Vec<u64> = results.iter().filter(|r| r.success).map(|r| r.ticks).collect();
        if !ticks.is_empty() {
            let mean = ticks.iter().sum::<u64>() as f64 / ticks.len() as f64;
            println!("successful episodes take {mean:.0} ticks on average ({:.1} s at 20 Hz)", mean / 20.0);
        }
        for r in results.iter().filter(|r| !r.success) {
            let [x, y, z] = r.object_position;
            let state = match r.drawer_opening {
                Some([from, to]) if r.task != labrig_sim::scene::Task::PickPlace => {
                    format!("drawer opening {from:.3} m -> {to:.3} m")
                }
                _ => format!(
                    "object at [{x:.3}, {y:.3}, {z:.3}], bin at [{:.3}, {:.3}]",
                    r.receptacle_position[0], r.receptacle_position[1]
                ),
            };
            println!("  failed: seed {} (phase {:?}, {state})", r.seed, r.final_phase);
        }
        println!("per camera bin (successes/episodes):");
        for (k, (s, n)) in &per_bin {
            println!("  {k:24} {s}/{n}");
        }
    }
    if let Some(min) = a.min_success
        && rate < min
    {
        eprintln!("success rate {rate:.2} is below --min-success {min}");
        return Ok(ExitCode::from(4));
    }
    Ok(ExitCode::SUCCESS)
}

fn replay(a: ReplayArgs) -> anyhow::Result<ExitCode> {
    let opts = ReplayOptions {
        episode: a.episode,
        scene: a.scene,
        seed: a.seed,
        assets: a.assets,
        cameras: a.cameras,
        width: a.width,
        height: a.height,
        max_joint_error_rad: a.max_joint_error_rad,
        max_tcp_error_m: a.max_tcp_error_m,
        max_rotation_error_rad: a.max_rotation_error_rad,
        max_gripper_error: a.max_gripper_error,
        perturb_joint1_rad: a.perturb_joint1_rad,
    };
    let _ = a.sim; // the simulated rig is what this program replays against
    let r = labrig_sim::replay::replay(&opts)?;
    if let Some(path) = &a.plot {
        labrig_sim::replay::plot(&r, path)?;
    }
    if a.json {
        println!("{}", serde_json::to_string(&r)?);
    } else {
        print!("{}", labrig_sim::replay::text(&r));
    }
    // Where the picture went (on stderr under --json, which keeps stdout one JSON object).
    if let Some(path) = &a.plot {
        let line = format!("plot: {}", std::fs::canonicalize(path).unwrap_or_else(|_| path.clone()).display());
        if a.json { eprintln!("{line}") } else { println!("{line}") }
    }
    Ok(if r.exceeded.is_empty() { ExitCode::SUCCESS } else { ExitCode::from(EXIT_DEVIATION) })
}

fn calib_capture(a: CalibCaptureArgs) -> anyhow::Result<ExitCode> {
    let (spec, assets) = labrig_sim::resolve_scene(a.scene.scene.as_deref(), a.scene.assets.as_deref())?;
    let camera = labrig_sim::rig::CAMERAS.iter().copied().find(|c| *c == a.camera).with_context(|| {
        format!("unknown camera `{}` (the rig's: {})", a.camera, labrig_sim::rig::CAMERAS.join(", "))
    })?;
    let text = std::fs::read_to_string(&a.board).with_context(|| format!("reading {}", a.board.display()))?;
    let board: labrig_msgs::calibration::BoardSpec =
        serde_json::from_str(&text).with_context(|| format!("{} is not a board spec", a.board.display()))?;
    let shift = match a.move_camera.as_deref() {
        None => [0.0; 3],
        Some(&[x, y, z]) => [x, y, z],
        Some(other) => anyhow::bail!("--move-camera takes dx,dy,dz (3 numbers), not {other:?}"),
    };
    let print_size_m = match a.print_size_m.as_deref() {
        None => board.size_m(),
        Some(&[w, h]) if w > 0.0 && h > 0.0 => [w, h],
        Some(other) => anyhow::bail!("--print-size-m takes width,height (2 positive numbers), not {other:?}"),
    };
    let opts = labrig_sim_bridge::calib::CaptureOptions {
        assets,
        spec,
        seed: a.seed,
        print: a.print,
        board,
        print_size_m,
        camera,
        views: a.views,
        width: a.width,
        height: a.height,
        amplitude_m: a.amplitude_m,
        amplitude_rad: a.amplitude_rad,
        camera_shift_m: shift,
        out: a.out,
        rig: a.rig,
    };
    let bar =
        labrig_episode::progress::bar(&format!("{{bar:30}} {{pos}}/{{len}} {camera} views"), a.views as u64, a.quiet);
    let report = labrig_sim_bridge::calib::capture(&opts, &bar)?;
    bar.finish_and_clear();
    if !a.quiet {
        eprintln!(
            "{camera}: {} views, {} poses unreachable -> {}",
            report.views,
            report.unreachable,
            report.capture.display()
        );
    }
    Ok(ExitCode::SUCCESS)
}
