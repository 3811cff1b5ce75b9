//! `labrig bench latency`: how the way chunks are executed moves a policy's success when the
//! arm does not wait for it. A sweep of the inference delay (in control ticks, played
//! deterministically in lockstep: `labrig rollout --delay-steps`) x the execution modes
//! (`wait`, `replace`, `exponential`, `rtc`) x the rows executed per chunk, each point a set of
//! seeded rollouts of the shipped checkpoints on the *tuning* seeds; then (`--judge`) the best
//! setting of each mode at the judged delays, and today's default, on the *judging* seeds
//! (five sets of 20 that choose nothing).
//!
//! Each point reports success with its Wilson interval, the ticks the arm held for lack of an
//! action, and smoothness read from the recorded joint positions: the 95th percentile of the
//! joint jerk (the norm over the 7 joints of the third difference / dt^3) at chunk switches
//! (a stencil whose steps' actions came from two chunks) and within chunks, and the TCP's path
//! length per success. Pictures: success against delay per mode, and each mode's TCP across
//! a few chunk switches.
//!
//! The run is resumable: a finished point is a JSON file under `<out>/points/`, read back
//! instead of rerun; an interrupted point starts over.

use anyhow::Context;
use clap::Args;
use labrig_episode::progress;
use labrig_launch::rollout::{BlendArg, RolloutArgs, wilson95};
use labrig_msgs::rig::Step;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use std::process::ExitCode;

#[derive(Debug, Clone, Args)]
pub struct LatencyArgs {
    /// The pick-and-place checkpoint (the shipped one by default).
    #[arg(long, default_value = "tests/fixtures/policies/small_vision_recover")]
    pub policy: PathBuf,
    /// The drawer checkpoint, swept on `--drawer-scene` after pick-and-place.
    #[arg(long, default_value = "tests/fixtures/policies/drawer_recover")]
    pub drawer_policy: PathBuf,
    #[arg(long, default_value = "drawer_open")]
    pub drawer_scene: String,
    /// Sweep pick-and-place only.
    #[arg(long)]
    pub no_drawer: bool,
    /// Inference delays, in 50 ms control ticks.
    #[arg(long, value_delimiter = ',', default_value = "0,4,8,2,6")]
    pub delays: Vec<u32>,
    /// Execution modes.
    #[arg(long, value_delimiter = ',', value_enum, default_value = "replace,rtc,exponential,wait")]
    pub modes: Vec<BlendArg>,
    /// Rows executed per chunk (`--execute-steps`).
    #[arg(long, value_delimiter = ',', default_value = "4,8,2")]
    pub execute: Vec<u32>,
    /// `rtc`: the guidance weight clips (beta) to sweep.
    #[arg(long, value_delimiter = ',', default_value = "5")]
    pub guidance: Vec<f64>,
    /// `rtc`: the server's guidance methods to sweep (`x0`, `vjp`; see labrig_policies::rtc).
    #[arg(long, value_delimiter = ',', default_value = "x0", value_parser = ["x0", "vjp"])]
    pub rtc_guidance: Vec<String>,
    /// The tuning seeds: `--episodes` from this one.
    #[arg(long, default_value_t = 1000)]
    pub tuning_seed: u64,
    /// Rollouts per point.
    #[arg(long, default_value_t = 20)]
    pub episodes: u64,
    /// After the sweep: each mode's best setting at `--judge-delays`, and the default, on the
    /// judging seeds.
    #[arg(long)]
    pub judge: bool,
    #[arg(long, value_delimiter = ',', default_value = "0,4,8")]
    pub judge_delays: Vec<u32>,
    /// The judging seed sets (20 rollouts each by default), used to choose nothing.
    #[arg(long, value_delimiter = ',', default_value = "20000,21000,22000,23000,24000")]
    pub judge_seeds: Vec<u64>,
    /// Stop after this many points have been run (the rest stay for a later run); 0: all.
    #[arg(long, default_value_t = 0)]
    pub max_points: usize,
    #[arg(long, default_value = "out/bench_latency")]
    pub out: PathBuf,
    #[arg(long, default_value_t = 300)]
    pub max_steps: u64,
    /// DDS domain of the rollout rig (its own, so a sweep runs beside other rigs).
    #[arg(long, default_value_t = 47)]
    pub domain_id: u16,
    /// Inference threads of the policy server (0: every core).
    #[arg(long, default_value_t = 0)]
    pub threads: i32,
    /// Keep each point's recorded episodes (by default they are deleted once read).
    #[arg(long)]
    pub keep_episodes: bool,
    /// Print the table and draw the pictures from the points measured so far; run nothing.
    #[arg(long)]
    pub report_only: bool,
    #[arg(long)]
    pub json: bool,
}

/// One setting of the sweep on one set of seeds.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Point {
    /// The scene (pick_place, drawer_open, ...).
    pub task: String,
    pub mode: String,
    pub delay: u32,
    pub execute: u32,
    /// `rtc`: beta.
    pub guidance: Option<f64>,
    /// `rtc`: the guidance method (`x0`, `vjp`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub method: Option<String>,
    pub first_seed: u64,
    pub episodes: u64,
    /// Tuning or judging.
    pub judging: bool,
}

impl Point {
    pub fn key(&self) -> String {
        let g = self.guidance.map_or(String::new(), |g| format!("_{}g{g}", self.method.as_deref().unwrap_or("")));
        let phase = if self.judging { "judge" } else { "tune" };
        format!("{}_{}_d{}_e{}{g}_{phase}{}", self.task, self.mode, self.delay, self.execute, self.first_seed)
    }

    /// The setting without the seeds.
    fn setting(&self) -> (String, String, u32, u32, Option<u64>, Option<String>) {
        let g = self.guidance.map(f64::to_bits);
        (self.task.clone(), self.mode.clone(), self.delay, self.execute, g, self.method.clone())
    }
}

/// A few steps of one rollout's TCP, for the trace picture.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct TraceStep {
    pub step: u64,
    pub tcp: [f64; 3],
    pub chunk_id: u64,
}

/// What a point measured.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct PointResult {
    pub point: Point,
    /// Not run: why (a real-time chunking setting the chunk cannot hold).
    pub infeasible: Option<String>,
    pub successes: u64,
    pub rollouts: u64,
    pub ci95: [f64; 2],
    pub steps: u64,
    pub held_steps: u64,
    pub chunks: u64,
    pub skipped_rows: u64,
    /// Joint jerk (rad/s^3), p95, at chunk switches and within chunks, and their ratio.
    #[serde(deserialize_with = "nan_if_null")]
    pub jerk_switch_p95: f64,
    #[serde(deserialize_with = "nan_if_null")]
    pub jerk_within_p95: f64,
    #[serde(deserialize_with = "nan_if_null")]
    pub jerk_ratio: f64,
    /// Metres of TCP path per successful rollout (mean).
    #[serde(deserialize_with = "nan_if_null")]
    pub path_per_success_m: f64,
    #[serde(deserialize_with = "nan_if_null")]
    pub inference_ms_p50: f64,
    pub wall_s: f64,
    pub trace: Vec<TraceStep>,
}

/// JSON has no NaN: serde_json writes it as null, read back here as NaN.
fn nan_if_null<'de, D: serde::Deserializer<'de>>(d: D) -> Result<f64, D::Error> {
    Ok(Option::<f64>::deserialize(d)?.unwrap_or(f64::NAN))
}

impl PointResult {
    fn rate(&self) -> f64 {
        if self.rollouts == 0 { 0.0 } else { self.successes as f64 / self.rollouts as f64 }
    }
}

/// Rows of a chunk from the observation on, for the rtc bounds: the shipped checkpoints'
/// horizon 16 with 2 observations.
fn chunk_rows(ckpt: &Path) -> anyhow::Result<u32> {
    let text = std::fs::read_to_string(ckpt.join("checkpoint.json"))
        .with_context(|| format!("{}/checkpoint.json", ckpt.display()))?;
    let v: serde_json::Value = serde_json::from_str(&text)?;
    let c = &v["config"];
    let (h, o) = (c["horizon"].as_u64().context("horizon")?, c["n_obs_steps"].as_u64().context("n_obs_steps")?);
    Ok((h + 1 - o) as u32)
}

/// The sweep's points in the order they run: each row count, each delay, each mode.
pub fn grid(a: &LatencyArgs) -> Vec<Point> {
    let mut tasks = vec![("pick_place".to_owned(), a.policy.clone())];
    if !a.no_drawer {
        tasks.push((a.drawer_scene.clone(), a.drawer_policy.clone()));
    }
    let mut points = Vec::new();
    for (task, _) in &tasks {
        for &execute in &a.execute {
            for &delay in &a.delays {
                for &mode in &a.modes {
                    // Waiting with no delay is replacing with none: the same rollouts.
                    if mode == BlendArg::Wait && delay == 0 {
                        continue;
                    }
                    let gs: Vec<(Option<f64>, Option<String>)> = if mode == BlendArg::Rtc {
                        a.rtc_guidance
                            .iter()
                            .flat_map(|m| a.guidance.iter().map(move |&g| (Some(g), Some(m.clone()))))
                            .collect()
                    } else {
                        vec![(None, None)]
                    };
                    for (guidance, method) in gs {
                        points.push(Point {
                            task: task.clone(),
                            mode: mode.name().to_owned(),
                            delay,
                            execute,
                            guidance,
                            method,
                            first_seed: a.tuning_seed,
                            episodes: a.episodes,
                            judging: false,
                        });
                    }
                }
            }
        }
    }
    points
}

fn policy_of<'a>(a: &'a LatencyArgs, task: &str) -> &'a Path {
    if task == "pick_place" { &a.policy } else { &a.drawer_policy }
}

pub fn run(a: LatencyArgs) -> anyhow::Result<ExitCode> {
    let dir = a.out.join("points");
    std::fs::create_dir_all(&dir).with_context(|| format!("creating {}", dir.display()))?;
    let mut results: Vec<PointResult> = Vec::new();
    let mut todo = grid(&a);
    let mut ran = 0usize;
    let bar = progress::bar("bench latency {bar:25} {pos}/{len} points", todo.len() as u64, a.json);
    let mut phase = 0;
    loop {
        for p in &todo {
            let file = dir.join(format!("{}.json", p.key()));
            if let Ok(text) = std::fs::read_to_string(&file) {
                results.push(serde_json::from_str(&text).with_context(|| format!("reading {}", file.display()))?);
                bar.inc(1);
                continue;
            }
            if a.report_only || (a.max_points > 0 && ran >= a.max_points) {
                bar.inc(1);
                continue;
            }
            bar.set_message(p.key());
            let r = run_point(&a, p)?;
            std::fs::write(&file, serde_json::to_string_pretty(&r)?)
                .with_context(|| format!("writing {}", file.display()))?;
            // (A hidden bar, output not a terminal, prints nothing: a log gets the line.)
            if bar.is_hidden() && !a.json {
                eprintln!("{}", line(&r));
            } else {
                bar.println(line(&r));
            }
            results.push(r);
            ran += 1;
            bar.inc(1);
        }
        phase += 1;
        if phase > 1 || !a.judge {
            break;
        }
        todo = judging_points(&a, &results);
        bar.set_length(bar.length().unwrap_or(0) + todo.len() as u64);
    }
    bar.finish_and_clear();
    results
        .sort_by_key(|r| (r.point.judging, r.point.task.clone(), r.point.execute, r.point.delay, r.point.mode.clone()));
    let pics = draw(&a.out, &results);
    if a.json {
        println!("{}", serde_json::to_string(&results)?);
    } else {
        print!("{}", table(&results));
        match pics {
            Ok(p) => p.iter().for_each(|p| println!("picture: {}", p.display())),
            Err(e) => println!("pictures: {e:#}"),
        }
    }
    Ok(ExitCode::SUCCESS)
}

/// The judged settings: per task, mode and judged delay the setting that succeeded most on
/// the tuning seeds (ties: fewer held ticks, then the lower jerk ratio), and today's default
/// (replace, 8 rows, no delay); each on every judging seed set.
fn judging_points(a: &LatencyArgs, tuned: &[PointResult]) -> Vec<Point> {
    let mut chosen: Vec<Point> = Vec::new();
    let tasks: Vec<String> =
        std::iter::once("pick_place".to_owned()).chain((!a.no_drawer).then(|| a.drawer_scene.clone())).collect();
    for task in &tasks {
        chosen.push(Point {
            task: task.clone(),
            mode: "replace".into(),
            delay: 0,
            execute: 8,
            guidance: None,
            method: None,
            first_seed: 0,
            episodes: a.episodes,
            judging: true,
        });
        for &mode in &a.modes {
            for &delay in &a.judge_delays {
                let best = tuned
                    .iter()
                    .filter(|r| {
                        r.infeasible.is_none()
                            && !r.point.judging
                            && &r.point.task == task
                            && r.point.mode == mode.name()
                            && r.point.delay == delay
                    })
                    .max_by(|x, y| {
                        (x.successes, std::cmp::Reverse(x.held_steps))
                            .cmp(&(y.successes, std::cmp::Reverse(y.held_steps)))
                            .then(y.jerk_ratio.total_cmp(&x.jerk_ratio))
                    });
                if let Some(b) = best {
                    let p = Point { judging: true, first_seed: 0, ..b.point.clone() };
                    if !chosen.iter().any(|c| c.setting() == p.setting()) {
                        chosen.push(p);
                    }
                }
            }
        }
    }
    chosen.into_iter().flat_map(|p| a.judge_seeds.iter().map(move |&s| Point { first_seed: s, ..p.clone() })).collect()
}

fn run_point(a: &LatencyArgs, p: &Point) -> anyhow::Result<PointResult> {
    let started = std::time::Instant::now();
    let ckpt = policy_of(a, &p.task);
    let mut r = PointResult {
        point: p.clone(),
        infeasible: None,
        successes: 0,
        rollouts: 0,
        ci95: [0.0, 1.0],
        steps: 0,
        held_steps: 0,
        chunks: 0,
        skipped_rows: 0,
        jerk_switch_p95: f64::NAN,
        jerk_within_p95: f64::NAN,
        jerk_ratio: f64::NAN,
        path_per_success_m: f64::NAN,
        inference_ms_p50: f64::NAN,
        wall_s: 0.0,
        trace: Vec::new(),
    };
    if p.mode == "rtc"
        && let Err(e) = labrig_msgs::rig::rtc_bounds(p.delay, p.execute, chunk_rows(ckpt)?)
    {
        r.infeasible = Some(e.to_string());
        return Ok(r);
    }
    let out = a.out.join("runs").join(p.key());
    if out.exists() {
        std::fs::remove_dir_all(&out).with_context(|| format!("clearing {}", out.display()))?;
    }
    let mode = [BlendArg::Replace, BlendArg::Exponential, BlendArg::Wait, BlendArg::Rtc]
        .into_iter()
        .find(|m| m.name() == p.mode)
        .context("unknown mode")?;
    let args = RolloutArgs {
        policy: Some(ckpt.to_owned()),
        server_timeout_s: Some(30.0),
        scene: p.task.clone(),
        episodes: p.episodes,
        first_seed: p.first_seed,
        max_steps: a.max_steps,
        threads: a.threads,
        blend: Some(mode),
        delay_steps: Some(p.delay),
        execute_steps: Some(p.execute),
        guidance_max_weight: p.guidance,
        rtc_guidance: p.method.clone(),
        domain_id: a.domain_id,
        ..RolloutArgs::defaults(out.clone())
    };
    let report = labrig_launch::rollout::run_quiet(args)?;
    anyhow::ensure!(report.errors.is_empty(), "point {}: {}", p.key(), report.errors.join("; "));
    r.rollouts = report.rollouts.len() as u64;
    r.successes = report.successes;
    r.ci95 = wilson95(r.successes, r.rollouts);
    r.steps = report.rollouts.iter().map(|o| o.steps).sum();
    r.held_steps = report.held_steps;
    r.chunks = report.rollouts.iter().map(|o| o.chunks).sum();
    r.skipped_rows = report.rollouts.iter().map(|o| o.skipped_rows).sum();
    r.inference_ms_p50 = report.inference_ms_p50;
    let (mut at_switch, mut within, mut paths) = (Vec::new(), Vec::new(), Vec::new());
    for (k, o) in report.rollouts.iter().enumerate() {
        let dir = o.dir.as_ref().with_context(|| format!("rollout {k} has no recording"))?;
        let data = labrig_episode::read_episode(dir).with_context(|| format!("reading {}", dir.display()))?;
        let s = smoothness(&data.steps, 0.05);
        at_switch.extend(s.at_switch);
        within.extend(s.within);
        if o.success {
            paths.push(s.path_m);
        }
        if r.trace.is_empty() && o.success {
            r.trace = trace(&data.steps, 60);
        }
    }
    r.jerk_switch_p95 = percentile(&mut at_switch, 0.95);
    r.jerk_within_p95 = percentile(&mut within, 0.95);
    r.jerk_ratio = r.jerk_switch_p95 / r.jerk_within_p95;
    r.path_per_success_m = if paths.is_empty() { f64::NAN } else { paths.iter().sum::<f64>() / paths.len() as f64 };
    r.wall_s = started.elapsed().as_secs_f64();
    if !a.keep_episodes {
        // The figures are read: the recordings (~MBs per rollout) and contact sheets go.
        std::fs::remove_dir_all(out.join("rollouts")).ok();
        for e in std::fs::read_dir(&out)?.flatten() {
            if e.file_name().to_string_lossy().ends_with("_cameras.png") {
                std::fs::remove_file(e.path()).ok();
            }
        }
    }
    Ok(r)
}

/// Nearest-rank percentile (NaN of nothing).
fn percentile(v: &mut [f64], q: f64) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    v.sort_by(f64::total_cmp);
    v[((v.len() - 1) as f64 * q).round() as usize]
}

/// One rollout's jerk samples and TCP path.
#[derive(Debug, Default)]
pub struct Smoothness {
    /// rad/s^3, one per stencil whose actions came from two chunks.
    pub at_switch: Vec<f64>,
    /// rad/s^3, one per stencil within one chunk.
    pub within: Vec<f64>,
    pub path_m: f64,
}

/// The joint jerk of the recorded steps: j_k = (q[k+2] - 3 q[k+1] + 3 q[k] - q[k-1]) / dt^3
/// (its norm over the joints) changes with the actions of steps k-1, k and k+1; it is within a
/// chunk when those all came from one chunk, a switch's when from two, or from a chunk and a
/// tick the arm held for lack of one (waiting for the next chunk is a switch too); a stencil
/// of held ticks only, or one before the episode's first chunk, counts in neither.
pub fn smoothness(steps: &[Step], dt: f64) -> Smoothness {
    let mut s = Smoothness::default();
    for w in steps.windows(2) {
        let (a, b) = (&w[0].robot_state.cartesian_position, &w[1].robot_state.cartesian_position);
        s.path_m += ((b[0] - a[0]).powi(2) + (b[1] - a[1]).powi(2) + (b[2] - a[2]).powi(2)).sqrt();
    }
    // Before the first chunk the arm has not moved yet: the start is no switch.
    let first = steps.iter().position(|s| s.chunk_id != 0).unwrap_or(steps.len());
    for k in (first + 1).max(1)..steps.len().saturating_sub(2) {
        let chunks = [steps[k - 1].chunk_id, steps[k].chunk_id, steps[k + 1].chunk_id];
        if chunks == [0, 0, 0] {
            continue;
        }
        let q = |i: usize| &steps[i].robot_state.joint_positions;
        let norm =
            (0..7).map(|j| (q(k + 2)[j] - 3.0 * q(k + 1)[j] + 3.0 * q(k)[j] - q(k - 1)[j]).powi(2)).sum::<f64>().sqrt()
                / dt.powi(3);
        if chunks[0] == chunks[1] && chunks[1] == chunks[2] {
            s.within.push(norm);
        } else {
            s.at_switch.push(norm);
        }
    }
    s
}

/// `n` steps of a rollout from its second chunk switch on (or its start).
fn trace(steps: &[Step], n: usize) -> Vec<TraceStep> {
    let switches: Vec<usize> =
        (1..steps.len()).filter(|&i| steps[i].chunk_id != steps[i - 1].chunk_id && steps[i].chunk_id != 0).collect();
    let from = switches.get(1).map_or(0, |&i| i.saturating_sub(3));
    steps[from..]
        .iter()
        .take(n)
        .map(|s| {
            let c = &s.robot_state.cartesian_position;
            TraceStep { step: s.step_index, tcp: [c[0], c[1], c[2]], chunk_id: s.chunk_id }
        })
        .collect()
}

fn line(r: &PointResult) -> String {
    let p = &r.point;
    let g = p.guidance.map_or(String::new(), |g| format!(" {} beta {g}", p.method.as_deref().unwrap_or("")));
    let seeds = format!("seeds {}..{}", p.first_seed, p.first_seed + p.episodes - 1);
    if let Some(why) = &r.infeasible {
        return format!("{:<11} {:<11} d {} e {}{g}: not run: {why}", p.task, p.mode, p.delay, p.execute);
    }
    format!(
        "{:<11} {:<11} d {} e {}{g} ({seeds}{}): {:>2}/{:<2} ({:>3.0}%, {:.0}-{:.0}%)  held {:>4}  jerk p95 switch {:>6.1} / within {:>6.1} (x{:.2})  path {:.2} m  {:.0} s",
        p.task,
        p.mode,
        p.delay,
        p.execute,
        if p.judging { ", judging" } else { "" },
        r.successes,
        r.rollouts,
        100.0 * r.rate(),
        100.0 * r.ci95[0],
        100.0 * r.ci95[1],
        r.held_steps,
        r.jerk_switch_p95,
        r.jerk_within_p95,
        r.jerk_ratio,
        r.path_per_success_m,
        r.wall_s
    )
}

/// The results as a table; judging points pooled over their seed sets.
pub fn table(results: &[PointResult]) -> String {
    use std::fmt::Write;
    let mut s = String::new();
    let _ = writeln!(
        s,
        "labrig bench latency (lockstep; delays in 50 ms ticks; rollouts of the scripted-expert-trained checkpoints)"
    );
    let _ = writeln!(s, "\ntuning seeds:");
    for r in results.iter().filter(|r| !r.point.judging) {
        let _ = writeln!(s, "  {}", line(r));
    }
    let judged: Vec<&PointResult> = results.iter().filter(|r| r.point.judging).collect();
    if !judged.is_empty() {
        let _ = writeln!(s, "\njudging seeds (pooled over the sets):");
        let mut settings: Vec<_> = judged.iter().map(|r| r.point.setting()).collect();
        settings.dedup();
        for st in settings {
            let rs: Vec<&&PointResult> = judged.iter().filter(|r| r.point.setting() == st).collect();
            let (k, n): (u64, u64) = rs.iter().fold((0, 0), |(k, n), r| (k + r.successes, n + r.rollouts));
            let held: u64 = rs.iter().map(|r| r.held_steps).sum();
            let ci = wilson95(k, n);
            let g = st
                .4
                .map_or(String::new(), |b| format!(" {} beta {}", st.5.as_deref().unwrap_or(""), f64::from_bits(b)));
            let _ = writeln!(
                s,
                "  {:<11} {:<11} d {} e {}{g}: {k}/{n} ({:.0}%, {:.0}-{:.0}%) over {} sets, held {held}",
                st.0,
                st.1,
                st.2,
                st.3,
                100.0 * k as f64 / n.max(1) as f64,
                100.0 * ci[0],
                100.0 * ci[1],
                rs.len()
            );
        }
    }
    s
}

/// Success against delay per mode (each mode's best row count at each delay, tuning seeds),
/// one picture per task; and each mode's TCP across chunk switches at the largest delay it ran.
fn draw(out: &Path, results: &[PointResult]) -> anyhow::Result<Vec<PathBuf>> {
    use plotters::prelude::*;
    let font = labrig_episode::font::dejavu_sans().map_err(anyhow::Error::msg)?;
    let _ = plotters::style::register_font("sans-serif", FontStyle::Normal, font);
    let e = |e: DrawingAreaErrorKind<_>| anyhow::anyhow!("{e:?}");
    let colours = [RGBColor(60, 110, 200), RGBColor(210, 70, 60), RGBColor(60, 160, 90), RGBColor(150, 90, 180)];
    let modes = ["replace", "rtc", "exponential", "wait"];
    let mut written = Vec::new();
    let tuned: Vec<&PointResult> = results.iter().filter(|r| !r.point.judging && r.infeasible.is_none()).collect();
    let mut tasks: Vec<String> = tuned.iter().map(|r| r.point.task.clone()).collect();
    tasks.sort();
    tasks.dedup();
    for task in &tasks {
        let path = out.join(format!("success_vs_delay_{task}.png"));
        let root = BitMapBackend::new(&path, (900, 560)).into_drawing_area();
        root.fill(&WHITE).map_err(e)?;
        let max_d = tuned.iter().map(|r| r.point.delay).max().unwrap_or(8).max(1) as f64;
        let mut chart = ChartBuilder::on(&root)
            .caption(format!("{task}: success against inference delay (lockstep, tuning seeds)"), ("sans-serif", 20))
            .margin(14)
            .x_label_area_size(40)
            .y_label_area_size(55)
            .build_cartesian_2d(-0.3..max_d + 0.3, 0.0..100.0)
            .map_err(e)?;
        chart
            .configure_mesh()
            .x_desc("delay (ticks of 50 ms)")
            .y_desc("success (%), best rows per chunk")
            .draw()
            .map_err(e)?;
        for (mode, colour) in modes.iter().zip(colours) {
            let mut pts: Vec<(f64, f64)> = Vec::new();
            let mut delays: Vec<u32> = tuned
                .iter()
                .filter(|r| &r.point.task == task && r.point.mode == *mode)
                .map(|r| r.point.delay)
                .collect();
            delays.sort_unstable();
            delays.dedup();
            for d in delays {
                // Waiting with no delay is replacing with none.
                let src = if *mode == "wait" && d == 0 { "replace" } else { mode };
                let best = tuned
                    .iter()
                    .filter(|r| &r.point.task == task && r.point.mode == src && r.point.delay == d)
                    .map(|r| 100.0 * r.rate())
                    .fold(f64::NAN, f64::max);
                if best.is_finite() {
                    pts.push((f64::from(d), best));
                }
            }
            if pts.is_empty() {
                continue;
            }
            chart
                .draw_series(LineSeries::new(pts.clone(), colour.stroke_width(2)))
                .map_err(e)?
                .label(*mode)
                .legend(move |(x, y)| PathElement::new([(x, y), (x + 18, y)], colour.stroke_width(2)));
            chart.draw_series(pts.iter().map(|&p| Circle::new(p, 4, colour.filled()))).map_err(e)?;
        }
        chart.configure_series_labels().background_style(WHITE.mix(0.85)).border_style(BLACK).draw().map_err(e)?;
        root.present().map_err(e)?;
        written.push(path.clone());

        // The judged settings: per mode and delay, the successes pooled over the judging sets,
        // with their Wilson 95% interval.
        let judged: Vec<&PointResult> =
            results.iter().filter(|r| r.point.judging && r.infeasible.is_none() && &r.point.task == task).collect();
        if !judged.is_empty() {
            let path = out.join(format!("success_vs_delay_judged_{task}.png"));
            let root = BitMapBackend::new(&path, (900, 560)).into_drawing_area();
            root.fill(&WHITE).map_err(e)?;
            let mut chart = ChartBuilder::on(&root)
                .caption(
                    format!("{task}: success against inference delay (lockstep, judging seeds, 95% intervals)"),
                    ("sans-serif", 18),
                )
                .margin(14)
                .x_label_area_size(40)
                .y_label_area_size(55)
                .build_cartesian_2d(-0.5..max_d + 0.5, 0.0..100.0)
                .map_err(e)?;
            chart.configure_mesh().x_desc("delay (ticks of 50 ms)").y_desc("success (%)").draw().map_err(e)?;
            for (k, (mode, colour)) in modes.iter().zip(colours).enumerate() {
                let mut by_delay: std::collections::BTreeMap<u32, (u64, u64)> = Default::default();
                for r in judged.iter().filter(|r| r.point.mode == *mode) {
                    let t = by_delay.entry(r.point.delay).or_default();
                    t.0 += r.successes;
                    t.1 += r.rollouts;
                }
                if by_delay.is_empty() {
                    continue;
                }
                // Modes side by side at each delay, so their intervals do not hide each other.
                let dx = (k as f64 - 1.5) * 0.08;
                let pts: Vec<(f64, f64, f64, f64)> = by_delay
                    .iter()
                    .map(|(&d, &(k, n))| {
                        let ci = wilson95(k, n);
                        (f64::from(d) + dx, 100.0 * k as f64 / n.max(1) as f64, 100.0 * ci[0], 100.0 * ci[1])
                    })
                    .collect();
                chart
                    .draw_series(LineSeries::new(pts.iter().map(|p| (p.0, p.1)), colour.stroke_width(2)))
                    .map_err(e)?
                    .label(*mode)
                    .legend(move |(x, y)| PathElement::new([(x, y), (x + 18, y)], colour.stroke_width(2)));
                chart
                    .draw_series(pts.iter().map(|p| PathElement::new([(p.0, p.2), (p.0, p.3)], colour.stroke_width(2))))
                    .map_err(e)?;
                chart.draw_series(pts.iter().map(|p| Circle::new((p.0, p.1), 4, colour.filled()))).map_err(e)?;
            }
            chart.configure_series_labels().background_style(WHITE.mix(0.85)).border_style(BLACK).draw().map_err(e)?;
            root.present().map_err(e)?;
            written.push(path.clone());
        }

        // TCP traces: per mode, the point at the largest delay with a trace.
        let path = out.join(format!("tcp_trace_{task}.png"));
        let root = BitMapBackend::new(&path, (1000, 220 * modes.len() as u32)).into_drawing_area();
        root.fill(&WHITE).map_err(e)?;
        let panels = root.split_evenly((modes.len(), 1));
        for ((mode, colour), panel) in modes.iter().zip(colours).zip(panels) {
            let Some(r) = tuned
                .iter()
                .filter(|r| &r.point.task == task && r.point.mode == *mode && !r.trace.is_empty())
                .max_by_key(|r| (r.point.delay, r.successes))
            else {
                continue;
            };
            let t0 = r.trace[0].step as f64;
            let xs: Vec<f64> = r.trace.iter().map(|s| (s.step as f64 - t0) * 0.05).collect();
            let z: Vec<f64> = r.trace.iter().map(|s| s.tcp[2]).collect();
            let (lo, hi) = z.iter().fold((f64::MAX, f64::MIN), |(l, h), &v| (l.min(v), h.max(v)));
            let pad = ((hi - lo) * 0.1).max(0.005);
            let mut chart = ChartBuilder::on(&panel)
                .caption(
                    format!(
                        "{mode}, d {} e {}: TCP height; grey lines at chunk switches",
                        r.point.delay, r.point.execute
                    ),
                    ("sans-serif", 15),
                )
                .margin(8)
                .x_label_area_size(25)
                .y_label_area_size(55)
                .build_cartesian_2d(0.0..xs.last().copied().unwrap_or(1.0).max(0.05), (lo - pad)..(hi + pad))
                .map_err(e)?;
            chart.configure_mesh().x_desc("s").y_desc("z (m)").draw().map_err(e)?;
            for (w, &x) in r.trace.windows(2).zip(&xs[1..]) {
                if w[1].chunk_id != w[0].chunk_id {
                    chart.draw_series(LineSeries::new([(x, lo - pad), (x, hi + pad)], BLACK.mix(0.25))).map_err(e)?;
                }
            }
            chart.draw_series(LineSeries::new(xs.iter().copied().zip(z), colour.stroke_width(2))).map_err(e)?;
        }
        root.present().map_err(e)?;
        written.push(path.clone());
    }
    Ok(written)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn args(extra: &[&str]) -> LatencyArgs {
        #[derive(clap::Parser)]
        struct P {
            #[command(flatten)]
            a: LatencyArgs,
        }
        let argv: Vec<&str> = std::iter::once("x").chain(extra.iter().copied()).collect();
        <P as clap::Parser>::parse_from(argv).a
    }

    #[test]
    fn the_grid_leaves_out_waiting_without_delay_and_sweeps_rtc_per_guidance() {
        let g = grid(&args(&["--no-drawer", "--delays", "0,4", "--execute", "4", "--guidance", "1,5"]));
        let keys: Vec<String> = g.iter().map(Point::key).collect();
        assert_eq!(
            keys,
            [
                "pick_place_replace_d0_e4_tune1000",
                "pick_place_rtc_d0_e4_x0g1_tune1000",
                "pick_place_rtc_d0_e4_x0g5_tune1000",
                "pick_place_exponential_d0_e4_tune1000",
                "pick_place_replace_d4_e4_tune1000",
                "pick_place_rtc_d4_e4_x0g1_tune1000",
                "pick_place_rtc_d4_e4_x0g5_tune1000",
                "pick_place_exponential_d4_e4_tune1000",
                "pick_place_wait_d4_e4_tune1000",
            ]
        );
    }

    fn step(k: u64, chunk: u64, q0: f64) -> Step {
        let mut s = Step { step_index: k, chunk_id: chunk, ..Step::default() };
        s.robot_state.joint_positions[0] = q0;
        s.robot_state.cartesian_position[0] = q0;
        s
    }

    /// A constant-acceleration path has no jerk; a kink where the chunk changes is the
    /// switch's, counted once per stencil that straddles it.
    #[test]
    fn jerk_is_the_third_difference_and_switches_are_told_from_within() {
        let dt = 0.05;
        let smooth: Vec<Step> = (0..10).map(|k| step(k, 1 + k / 5, 0.5 * (k as f64).powi(2) * 1e-3)).collect();
        let s = smoothness(&smooth, dt);
        assert!(s.at_switch.iter().chain(&s.within).all(|&j| j.abs() < 1e-6), "{s:?}");
        assert_eq!(s.at_switch.len() + s.within.len(), 7);
        // Chunk 1 at steps 0..5, chunk 2 from 5: stencils k = 4 and 5 straddle (k-1..k+1).
        assert_eq!(s.at_switch.len(), 2, "{s:?}");
        let mut kinked = smooth.clone();
        for (k, st) in kinked.iter_mut().enumerate().skip(6) {
            st.robot_state.joint_positions[0] += 0.01 * (k - 5) as f64;
        }
        let s = smoothness(&kinked, dt);
        assert!(s.at_switch.iter().any(|&j| j > 1.0), "{s:?}");
        // A held step (chunk 0) between two of one chunk: the stencils through it are switches;
        // a stencil of held steps only counts in neither.
        let held: Vec<Step> = (0..10).map(|k| step(k, if k == 4 { 0 } else { 1 }, 0.0)).collect();
        let s = smoothness(&held, dt);
        assert_eq!((s.at_switch.len(), s.within.len()), (3, 4), "{s:?}");
        // Before the first chunk: nothing counts.
        let idle: Vec<Step> = (0..10).map(|k| step(k, if k < 4 { 0 } else { 1 }, 0.0)).collect();
        let s = smoothness(&idle, dt);
        assert_eq!((s.at_switch.len(), s.within.len()), (0, 3), "{s:?}");
        // The path: 0.5e-3 * 81 along x.
        let s = smoothness(&smooth, dt);
        assert!((s.path_m - 0.5e-3 * 81.0).abs() < 1e-12, "{}", s.path_m);
    }
}
