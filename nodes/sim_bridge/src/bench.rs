//! `labrig sim bench`: physics steps per second, render time per frame for the five cameras at
//! two sizes and both mesh sets, and the real-time factor of physics + five cameras.

use labrig_msgs::Nanos;
use labrig_sim::expert::{CartesianIk, PickPlaceExpert};
use labrig_sim::{ArmTarget, Meshes, SceneSpec, Sim};
use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Instant;

#[derive(Debug, clap::Args)]
pub struct BenchArgs {
    /// Control ticks (50 ms of sim time each) per measurement.
    #[arg(long, default_value_t = 200)]
    pub ticks: u64,
    /// Image sizes to render, WxH.
    #[arg(long, value_delimiter = ',', default_value = "128x128,320x240")]
    pub sizes: Vec<String>,
    /// Where setup extracted the MuJoCo models.
    #[arg(long, env = "LABRIG_SIM_ASSETS")]
    pub assets: Option<PathBuf>,
    /// Print one JSON object instead of text.
    #[arg(long)]
    pub json: bool,
}

fn percentile(sorted: &[f64], p: f64) -> f64 {
    if sorted.is_empty() {
        return f64::NAN;
    }
    sorted[((sorted.len() - 1) as f64 * p).round() as usize]
}

/// Drives the sim with the expert (so the arm moves and the images change), rendering every
/// tick if `cameras` is on; returns per-tick wall times (ms) of physics and of rendering.
fn drive(sim: &mut Sim, ticks: u64, render: bool) -> anyhow::Result<(Vec<f64>, Vec<f64>)> {
    let mut expert = PickPlaceExpert::new(sim);
    let ik = CartesianIk::new(sim);
    let (mut physics, mut rendering) = (Vec::new(), Vec::new());
    let mut buf = Vec::new();
    for _ in 0..ticks {
        let t0 = Instant::now();
        let action = expert.act(sim);
        let joints = ik.solve(sim, &action.cartesian_position);
        sim.step(&ArmTarget { joints, gripper: action.gripper_position })?;
        physics.push(t0.elapsed().as_secs_f64() * 1e3);
        if render {
            let t1 = Instant::now();
            for camera in labrig_sim::rig::CAMERAS {
                sim.render_into(camera, &mut buf)?;
            }
            rendering.push(t1.elapsed().as_secs_f64() * 1e3);
        }
    }
    Ok((physics, rendering))
}

pub fn run(a: BenchArgs) -> anyhow::Result<ExitCode> {
    let assets = labrig_sim::assets_dir(a.assets.as_deref());
    let spec = SceneSpec::default_pick_place();
    let period = Nanos::from_millis(50);
    let mut report = serde_json::Map::new();
    let say = |line: String| {
        if !a.json {
            println!("{line}");
        }
    };
    say(format!("labrig sim bench: {} ticks of 50 ms per measurement (shared 2-core machine: noisy)", a.ticks));

    let mut sim = Sim::new(&assets, &spec, 1, period)?;
    let substeps = sim.substeps() as f64;
    let t0 = Instant::now();
    let (mut physics, _) = drive(&mut sim, a.ticks, false)?;
    let wall = t0.elapsed().as_secs_f64();
    physics.sort_by(f64::total_cmp);
    let steps_per_s = a.ticks as f64 * substeps / wall;
    say(format!(
        "physics: {steps_per_s:.0} steps/s (2 ms steps); tick (25 steps + expert + IK) p50 {:.2} ms, p99 {:.2} ms; \
         real-time factor without cameras {:.1}x",
        percentile(&physics, 0.5),
        percentile(&physics, 0.99),
        a.ticks as f64 * 0.05 / wall
    ));
    report.insert(
        "physics".into(),
        serde_json::json!({"steps_per_s": steps_per_s, "tick_ms_p50": percentile(&physics, 0.5),
            "tick_ms_p99": percentile(&physics, 0.99), "realtime_factor": a.ticks as f64 * 0.05 / wall}),
    );

    let mut renders = Vec::new();
    for size in &a.sizes {
        let (w, h) = size
            .split_once('x')
            .and_then(|(w, h)| Some((w.parse::<usize>().ok()?, h.parse::<usize>().ok()?)))
            .ok_or_else(|| anyhow::anyhow!("--sizes: `{size}` is not WxH"))?;
        for meshes in [Meshes::Collision, Meshes::Visual] {
            let mut sim = Sim::new(&assets, &spec, 1, period)?;
            sim.enable_cameras(w, h, meshes)?;
            sim.render_all()?; // warm-up: first frame uploads meshes and textures
            let t0 = Instant::now();
            let (_, mut rendering) = drive(&mut sim, a.ticks, true)?;
            let wall = t0.elapsed().as_secs_f64();
            rendering.sort_by(f64::total_cmp);
            let per_frame = percentile(&rendering, 0.5) / 5.0;
            let rtf = a.ticks as f64 * 0.05 / wall;
            say(format!(
                "render {w}x{h} {meshes:?} meshes: five cameras p50 {:.1} ms, p99 {:.1} ms per tick ({per_frame:.1} ms \
                 per frame); physics + 5 cameras real-time factor {rtf:.2}x ({})",
                percentile(&rendering, 0.5),
                percentile(&rendering, 0.99),
                if rtf >= 1.0 { "keeps 20 Hz in real time" } else { "slower than real time" }
            ));
            renders.push(serde_json::json!({"width": w, "height": h, "meshes": meshes,
                "five_cameras_ms_p50": percentile(&rendering, 0.5), "five_cameras_ms_p99": percentile(&rendering, 0.99),
                "frame_ms_p50": per_frame, "realtime_factor": rtf}));
        }
    }
    report.insert("render".into(), serde_json::Value::Array(renders));
    if a.json {
        println!("{}", serde_json::to_string_pretty(&report)?);
    }
    Ok(ExitCode::SUCCESS)
}
