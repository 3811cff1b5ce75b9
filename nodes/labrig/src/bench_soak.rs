//! `labrig bench soak --minutes N`: an operator's session, measured. The demo's rig in real time
//! (as `labrig bench loop` runs it: the sim rendering five cameras, the 20 Hz loop on the wall
//! clock, the scripted expert recording episodes back to back, the recorder writing them),
//! optionally with the operator station, its page's polling and Foxglove clients beside it.
//!
//! Every `--sample-s` (10 s): each of the rig's processes' resident memory, CPU, open file
//! descriptors and threads (`/proc`), the recordings' bytes on disk and the free space. Every
//! `--window-min` (5 min): the loop's own figures for the window (ticks, missed and held ticks,
//! steps with a missing or stale frame, period jitter and camera skew percentiles, written by
//! the control loop itself), and the episodes recorded in it with their `inspect` verdicts.
//!
//! Out: `soak.json` (every sample and window, and the verdict), `soak.png` (memory, descriptors
//! and the loop's jitter over time, a line per process) and the verdict on stdout: each
//! process's memory growth per hour after the warm-up (a least-squares line), the descriptors'
//! and threads' drift, the disk an 8-hour day takes at this rate, and the session's goals
//! (under 2 MB/h per process, descriptors and threads flat, no missed tick, no dropped frame,
//! every episode inspected clean, the last window's p99 jitter within 1.5x the first's).
//! Ctrl-C ends it early with the report so far.

use anyhow::Context;
use clap::Args;
use labrig_launch::measure::{Hooks, LoopArgs, measure_with};
use labrig_runtime::bench::{ProcSample, growth_per_hour, sample_of};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::{Duration, Instant};

#[derive(Debug, Args)]
pub struct SoakArgs {
    /// How long the session lasts (the figure is 60).
    #[arg(long, default_value_t = 60.0)]
    pub minutes: f64,
    /// Seconds between two samples of the processes.
    #[arg(long, default_value_t = 10.0)]
    pub sample_s: f64,
    /// Minutes per window of the loop's figures.
    #[arg(long, default_value_t = 5.0)]
    pub window_min: f64,
    /// Minutes left out of the growth fits (caches and pools fill first).
    #[arg(long, default_value_t = 10.0)]
    pub warmup_min: f64,
    /// Camera image size.
    #[arg(long, default_value_t = 128)]
    pub width: u32,
    #[arg(long, default_value_t = 128)]
    pub height: u32,
    /// The operator station beside the rig, with its page's polling and `--clients` Foxglove
    /// clients.
    #[arg(long)]
    pub station: bool,
    #[arg(long, default_value_t = 1)]
    pub clients: usize,
    /// Where the episodes and the report go.
    #[arg(long, default_value = "out/bench_soak")]
    pub out: PathBuf,
    #[arg(long, default_value_t = 45)]
    pub domain_id: u16,
    /// A check of the verdict: a helper process beside the rig that grows by this many MB per
    /// hour (the verdict must name it).
    #[arg(long, hide = true)]
    pub plant_growth_mb_per_h: Option<f64>,
    #[arg(long)]
    pub json: bool,
}

/// The planted-growth helper (`labrig bench grow`): allocates and touches memory at a steady
/// rate until its parent goes.
#[derive(Debug, Args)]
pub struct GrowArgs {
    #[arg(long)]
    pub mb_per_h: f64,
    /// Names the rig it stands beside (the soak finds the rig's processes by it).
    #[arg(long)]
    pub domain_id: u16,
    /// It stops growing after this many seconds (a bound: the soak stops it first).
    #[arg(long, default_value_t = 7200.0)]
    pub seconds: f64,
}

pub fn grow(a: &GrowArgs) -> anyhow::Result<ExitCode> {
    anyhow::ensure!(a.mb_per_h.is_finite() && (0.0..=10_000.0).contains(&a.mb_per_h), "--mb-per-h in 0..=10000");
    let per_s = (a.mb_per_h * 1e6 / 3600.0) as usize;
    let started = Instant::now();
    let mut held: Vec<Vec<u8>> = Vec::new();
    while started.elapsed().as_secs_f64() < a.seconds {
        // Touched, so the pages are resident.
        held.push(vec![1u8; per_s]);
        std::thread::sleep(Duration::from_secs(1));
    }
    drop(held);
    Ok(ExitCode::SUCCESS)
}

/// One sample of one process.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Sample {
    pub t_s: f64,
    #[serde(flatten)]
    pub proc: ProcSample,
}

/// The disk at one sample: the recordings' bytes and the free space where they go.
#[derive(Debug, Clone, Copy, Serialize, Deserialize)]
pub struct DiskSample {
    pub t_s: f64,
    pub recorded_bytes: u64,
    pub free_bytes: u64,
}

/// A process's verdict.
#[derive(Debug, Clone, Serialize)]
pub struct ProcessVerdict {
    pub name: String,
    pub samples: usize,
    pub rss_first_mb: f64,
    pub rss_last_mb: f64,
    /// Least-squares growth after the warm-up, and its standard error (the samples' scatter
    /// about the line: an allocator that gives back and takes again makes it wide).
    pub rss_mb_per_h: Option<f64>,
    pub rss_mb_per_h_se: Option<f64>,
    /// The growth of the floor: the line through the lowest RSS of each run of
    /// [`FLOOR_SAMPLES`] samples after the warm-up. The verdict's figure: memory that swings
    /// between fixed levels (a scene built while the last one still stands, an allocator
    /// trimming now and then) leaves it flat; a leak raises it.
    #[serde(default)]
    pub rss_floor_mb_per_h: Option<f64>,
    pub fds_per_h: Option<f64>,
    pub threads_per_h: Option<f64>,
    pub fds_range: [u32; 2],
    pub threads_range: [u32; 2],
    /// Mean CPU over the run, % of one core.
    pub cpu_percent: f64,
}

/// The loop's window, as the control loop wrote it, with the episodes it recorded.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Window {
    pub end_s: f64,
    pub seconds: f64,
    pub ticks: u64,
    pub missed_ticks: u64,
    pub held_ticks: u64,
    pub steps_missing_frames: u64,
    pub steps_stale_frames: u64,
    pub episodes: u64,
    pub jitter_us: [f64; 3],
    pub skew_us: [f64; 3],
    #[serde(default)]
    pub recorded: u64,
    #[serde(default)]
    pub dropped_frames: u64,
    #[serde(default)]
    pub flagged: Vec<String>,
}

/// The session's goals, each with its figure.
#[derive(Debug, Clone, Serialize)]
pub struct Verdict {
    /// Processes growing 2 MB/h or more after the warm-up.
    pub growing: Vec<(String, f64)>,
    /// Processes whose descriptors or threads drift (one or more an hour after the warm-up).
    pub drifting: Vec<String>,
    pub missed_ticks: u64,
    pub dropped_frames: u64,
    pub flagged_episodes: u64,
    pub episodes: u64,
    /// The last window's p99 jitter over the first's.
    pub jitter_p99_ratio: Option<f64>,
    /// The recordings' growth and what an 8-hour day of it takes.
    pub disk_mb_per_h: Option<f64>,
    pub disk_gb_per_8h_day: Option<f64>,
    pub pass: bool,
    pub failed: Vec<String>,
}

/// Memory growth per hour at or above this fails (the goal).
pub const MAX_MB_PER_H: f64 = 2.0;
/// Descriptors or threads gained per hour at or above this is a drift.
pub const MAX_DRIFT_PER_H: f64 = 1.0;

/// Each process's verdict from its samples.
pub fn verdicts(samples: &BTreeMap<String, Vec<Sample>>, warmup_s: f64) -> Vec<ProcessVerdict> {
    samples
        .iter()
        .filter(|(_, v)| !v.is_empty())
        .map(|(name, v)| {
            let series =
                |f: &dyn Fn(&ProcSample) -> f64| -> Vec<(f64, f64)> { v.iter().map(|s| (s.t_s, f(&s.proc))).collect() };
            let range = |f: &dyn Fn(&ProcSample) -> u32| {
                let it = v.iter().filter(|s| s.t_s >= warmup_s).map(|s| f(&s.proc));
                [it.clone().min().unwrap_or(0), it.max().unwrap_or(0)]
            };
            let (first, last) = (&v[0], &v[v.len() - 1]);
            let span = (last.t_s - first.t_s).max(1e-9);
            ProcessVerdict {
                name: name.clone(),
                samples: v.len(),
                rss_first_mb: first.proc.rss_bytes as f64 / 1e6,
                rss_last_mb: last.proc.rss_bytes as f64 / 1e6,
                rss_mb_per_h: growth_per_hour(&series(&|p| p.rss_bytes as f64 / 1e6), warmup_s),
                rss_mb_per_h_se: slope_se(&series(&|p| p.rss_bytes as f64 / 1e6), warmup_s).map(|se| se * 3600.0),
                rss_floor_mb_per_h: floor_growth_per_hour(&series(&|p| p.rss_bytes as f64 / 1e6), warmup_s),
                fds_per_h: growth_per_hour(&series(&|p| f64::from(p.fds)), warmup_s),
                threads_per_h: growth_per_hour(&series(&|p| f64::from(p.threads)), warmup_s),
                fds_range: range(&|p| p.fds),
                threads_range: range(&|p| p.threads),
                cpu_percent: 100.0 * (last.proc.cpu_s - first.proc.cpu_s) / span,
            }
        })
        .collect()
}

/// Samples per run whose lowest value is one point of the floor (a minute at the default 10 s).
pub const FLOOR_SAMPLES: usize = 6;

/// The growth per hour of the floor of `samples` after `warmup_s`: the least-squares line
/// through the lowest value of each run of [`FLOOR_SAMPLES`] samples (at the run's mean time);
/// None with fewer than two runs.
pub fn floor_growth_per_hour(samples: &[(f64, f64)], warmup_s: f64) -> Option<f64> {
    let after: Vec<(f64, f64)> = samples.iter().copied().filter(|(t, _)| *t >= warmup_s).collect();
    let floor: Vec<(f64, f64)> = after
        .chunks(FLOOR_SAMPLES)
        .filter(|c| c.len() == FLOOR_SAMPLES)
        .map(|c| {
            let t = c.iter().map(|(t, _)| t).sum::<f64>() / c.len() as f64;
            (t, c.iter().map(|(_, v)| *v).fold(f64::INFINITY, f64::min))
        })
        .collect();
    labrig_runtime::bench::slope(&floor).map(|per_s| per_s * 3600.0)
}

/// The standard error of the least-squares slope through the points after `warmup_s` (per
/// unit of x); None with fewer than three.
pub fn slope_se(points: &[(f64, f64)], warmup_s: f64) -> Option<f64> {
    let p: Vec<(f64, f64)> = points.iter().copied().filter(|(t, _)| *t >= warmup_s).collect();
    let b = labrig_runtime::bench::slope(&p)?;
    let n = p.len() as f64;
    if p.len() < 3 {
        return None;
    }
    let (mx, my) = p.iter().fold((0.0, 0.0), |(a, c), (x, y)| (a + x / n, c + y / n));
    let sxx: f64 = p.iter().map(|(x, _)| (x - mx).powi(2)).sum();
    let rss: f64 = p.iter().map(|(x, y)| (y - (my + b * (x - mx))).powi(2)).sum();
    Some((rss / (n - 2.0) / sxx).sqrt())
}

/// The goals judged from the processes, the windows and the disk.
pub fn verdict(
    procs: &[ProcessVerdict],
    windows: &[Window],
    judged: &Judged,
    disk: &[DiskSample],
    warmup_s: f64,
) -> Verdict {
    let growing: Vec<(String, f64)> = procs
        .iter()
        .filter_map(|p| p.rss_floor_mb_per_h.filter(|g| *g >= MAX_MB_PER_H).map(|g| (p.name.clone(), g)))
        .collect();
    // A drift is a fitted gain that adds up to a whole descriptor or thread over the hour and
    // shows in the range (a steady count fluctuating by one is not a drift).
    let drifts = |rate: Option<f64>, range: [u32; 2]| rate.is_some_and(|r| r >= MAX_DRIFT_PER_H) && range[1] > range[0];
    let drifting: Vec<String> = procs
        .iter()
        .filter(|p| drifts(p.fds_per_h, p.fds_range) || drifts(p.threads_per_h, p.threads_range))
        .map(|p| p.name.clone())
        .collect();
    let missed = windows.iter().map(|w| w.missed_ticks).sum::<u64>();
    let (dropped, flagged, episodes) = (judged.dropped_frames, judged.flagged.len() as u64, judged.episodes);
    let jitter_p99_ratio = match (windows.first(), windows.last()) {
        (Some(f), Some(l)) if windows.len() >= 2 && f.jitter_us[1] > 0.0 => Some(l.jitter_us[1] / f.jitter_us[1]),
        _ => None,
    };
    let disk_mb_per_h = growth_per_hour(
        &disk.iter().map(|d| (d.t_s, d.recorded_bytes as f64 / 1e6)).collect::<Vec<_>>(),
        warmup_s.min(disk.last().map_or(0.0, |d| d.t_s / 2.0)),
    );
    let mut failed = Vec::new();
    for (name, g) in &growing {
        failed.push(format!("{name} grows {g:.1} MB/h (goal < {MAX_MB_PER_H})"));
    }
    for name in &drifting {
        failed.push(format!("{name}: descriptors or threads drift"));
    }
    if missed > 0 {
        failed.push(format!("{missed} missed ticks"));
    }
    if dropped > 0 {
        failed.push(format!("{dropped} dropped frames"));
    }
    if flagged > 0 {
        failed.push(format!("{flagged} episodes flagged by inspect"));
    }
    if jitter_p99_ratio.is_some_and(|r| r > 1.5) {
        failed.push(format!(
            "last window's p99 jitter {:.2}x the first's (goal <= 1.5)",
            jitter_p99_ratio.unwrap_or(0.0)
        ));
    }
    Verdict {
        growing,
        drifting,
        missed_ticks: missed,
        dropped_frames: dropped,
        flagged_episodes: flagged,
        episodes,
        jitter_p99_ratio,
        disk_mb_per_h,
        disk_gb_per_8h_day: disk_mb_per_h.map(|m| m * 8.0 / 1e3),
        pass: failed.is_empty(),
        failed,
    }
}

/// The recordings' bytes under `root`.
fn dir_bytes(root: &Path) -> u64 {
    let Ok(dir) = std::fs::read_dir(root) else { return 0 };
    dir.flatten()
        .map(|e| match e.file_type() {
            Ok(t) if t.is_dir() => dir_bytes(&e.path()),
            Ok(_) => e.metadata().map_or(0, |m| m.len()),
            Err(_) => 0,
        })
        .sum()
}

/// Every episode recorded, inspected: the totals, and each counted in the window its
/// recording began in (those after the last full window only in the totals).
#[derive(Debug, Clone, Default, Serialize)]
pub struct Judged {
    pub episodes: u64,
    pub dropped_frames: u64,
    pub flagged: Vec<String>,
}

fn judge_episodes(root: &Path, windows: &mut [Window], started_ns: i64) -> anyhow::Result<Judged> {
    let mut all = Judged::default();
    for path in labrig_episode::episode::find_episodes(root) {
        let i = labrig_episode::inspect::inspect(&path).map_err(|e| anyhow::anyhow!("{}: {e}", path.display()))?;
        let dropped = i.cameras.iter().map(|c| c.dropped).sum::<u64>();
        let flag = (!i.flags.is_empty()).then(|| format!("{}: {}", path.display(), i.flags.join("; ")));
        all.episodes += 1;
        all.dropped_frames += dropped;
        all.flagged.extend(flag.clone());
        let at_s = (i.start_ns - started_ns) as f64 / 1e9;
        if let Some(w) = windows.iter_mut().find(|w| at_s < w.end_s) {
            w.recorded += 1;
            w.dropped_frames += dropped;
            w.flagged.extend(flag);
        }
    }
    Ok(all)
}

#[derive(Debug, Serialize)]
struct Report {
    minutes: f64,
    interrupted: bool,
    sample_s: f64,
    window_s: f64,
    warmup_s: f64,
    cameras: String,
    station: bool,
    planted_mb_per_h: Option<f64>,
    processes: Vec<ProcessVerdict>,
    samples: BTreeMap<String, Vec<Sample>>,
    disk: Vec<DiskSample>,
    windows: Vec<Window>,
    episodes: Judged,
    verdict: Verdict,
    /// The whole run as `labrig bench loop` reports it.
    run: serde_json::Value,
}

pub fn run(a: &SoakArgs) -> anyhow::Result<ExitCode> {
    anyhow::ensure!((0.5..=24.0 * 60.0).contains(&a.minutes), "--minutes must be in [0.5, 1440]");
    anyhow::ensure!((1.0..=600.0).contains(&a.sample_s), "--sample-s must be in [1, 600]");
    anyhow::ensure!(a.window_min * 60.0 >= a.sample_s, "--window-min must hold at least one sample");
    anyhow::ensure!(a.warmup_min >= 0.0 && a.warmup_min < a.minutes, "--warmup-min must be shorter than --minutes");
    anyhow::ensure!(a.clients <= 16, "--clients must be at most 16");
    std::fs::create_dir_all(&a.out)?;
    let out = std::fs::canonicalize(&a.out)?;
    let root = out.join("episodes");
    anyhow::ensure!(
        !root.exists() || std::fs::read_dir(&root)?.next().is_none(),
        "{} holds episodes of an earlier soak: give another --out",
        root.display()
    );
    let windows_path = out.join("windows.jsonl");
    let _ = std::fs::remove_file(&windows_path);
    let (seconds, window_s, warmup_s) = (a.minutes * 60.0, a.window_min * 60.0, a.warmup_min * 60.0);
    let started_ns = labrig_runtime::Clock::Wall.now().0;
    // The planted growth: a helper beside the rig, found with it by its domain.
    let mut planted = match a.plant_growth_mb_per_h {
        Some(mb) => {
            let mut cmd = std::process::Command::new(std::env::current_exe()?);
            // Its own name among the rig's processes (they are named by their first argument).
            std::os::unix::process::CommandExt::arg0(&mut cmd, "labrig-grow");
            cmd.args(["bench", "grow", "--mb-per-h", &mb.to_string(), "--domain-id", &a.domain_id.to_string()])
                .args(["--seconds", &(seconds + 60.0).to_string()]);
            labrig_launch::supervise::stop_with_launcher(&mut cmd);
            Some(cmd.spawn().context("starting the planted-growth helper")?)
        }
        None => None,
    };
    let mut samples: BTreeMap<String, Vec<Sample>> = BTreeMap::new();
    let mut disk = Vec::new();
    let mut next_sample = 0.0;
    let mut every = |pids: &BTreeMap<String, u32>, t: f64| {
        if t < next_sample {
            return;
        }
        next_sample = t + a.sample_s;
        // (The soak itself carries the rig's --domain-id too.)
        for (name, pid) in pids.iter().filter(|(_, p)| **p != std::process::id()) {
            if let Some(p) = sample_of(*pid) {
                samples.entry(name.clone()).or_default().push(Sample { t_s: t, proc: p });
            }
        }
        let free_bytes = labrig_launch::measure::free_bytes(&out);
        disk.push(DiskSample { t_s: t, recorded_bytes: dir_bytes(&root), free_bytes });
    };
    let loop_args = LoopArgs {
        seconds,
        width: a.width,
        height: a.height,
        out: Some(out.clone()),
        domain_id: a.domain_id,
        json: a.json,
    };
    let beside = if a.station { Some(labrig_launch::clients::station_beside(&root, a.clients)?) } else { None };
    let hooks = Hooks {
        control_sets: vec![
            ("window_stats".into(), windows_path.display().to_string()),
            ("window_s".into(), window_s.to_string()),
        ],
        every: Some(&mut every),
        interruptible: true,
    };
    let result = measure_with(&loop_args, &out, beside, hooks);
    if let Some(c) = planted.as_mut() {
        let _ = c.kill();
        let _ = c.wait();
    }
    let run = result?;
    let mut windows: Vec<Window> = std::fs::read_to_string(&windows_path)
        .unwrap_or_default()
        .lines()
        .map(|l| serde_json::from_str(l).with_context(|| format!("{}: {l}", windows_path.display())))
        .collect::<anyhow::Result<_>>()?;
    let judged = judge_episodes(&root, &mut windows, started_ns)?;
    let processes = verdicts(&samples, warmup_s);
    let verdict = verdict(&processes, &windows, &judged, &disk, warmup_s);
    let report = Report {
        minutes: run["seconds"].as_f64().unwrap_or(seconds) / 60.0,
        interrupted: run["interrupted"].as_bool().unwrap_or(false),
        sample_s: a.sample_s,
        window_s,
        warmup_s,
        cameras: run["cameras"].as_str().unwrap_or_default().to_owned(),
        station: a.station,
        planted_mb_per_h: a.plant_growth_mb_per_h,
        processes,
        samples,
        disk,
        windows,
        episodes: judged,
        verdict,
        run,
    };
    std::fs::write(out.join("soak.json"), serde_json::to_string_pretty(&report)? + "\n")?;
    plot(&report, &out.join("soak.png"))?;
    if a.json {
        println!("{}", serde_json::to_string(&report)?);
    } else {
        print_report(&report, &out);
    }
    Ok(ExitCode::SUCCESS)
}

fn print_report(r: &Report, out: &Path) {
    println!(
        "labrig bench soak: {:.1} min{} of the demo's rig in real time ({}{}), sampled every {:.0} s, windows of {:.1} min, warm-up {:.1} min",
        r.minutes,
        if r.interrupted { " (ended early)" } else { "" },
        r.cameras,
        if r.station { ", the station with its page and Foxglove" } else { "" },
        r.sample_s,
        r.window_s / 60.0,
        r.warmup_s / 60.0
    );
    println!("  (a shared 2-core machine: timings are noisy)");
    println!(
        "  {:<22} {:>8} {:>8} {:>16} {:>10} {:>9} {:>11} {:>7}",
        "process", "RSS MB", "-> MB", "MB/h (± s.e.)", "floor MB/h", "fds", "threads", "cpu %"
    );
    let rate = |v: Option<f64>, se: Option<f64>| match (v, se) {
        (Some(g), Some(se)) => format!("{g:+.2} ±{se:.2}"),
        (Some(g), None) => format!("{g:+.2}"),
        _ => "-".to_owned(),
    };
    for p in &r.processes {
        println!(
            "  {:<22} {:>8.1} {:>8.1} {:>16} {:>10} {:>4}-{:<4} {:>5}-{:<5} {:>7.1}",
            p.name,
            p.rss_first_mb,
            p.rss_last_mb,
            rate(p.rss_mb_per_h, p.rss_mb_per_h_se),
            rate(p.rss_floor_mb_per_h, None),
            p.fds_range[0],
            p.fds_range[1],
            p.threads_range[0],
            p.threads_range[1],
            p.cpu_percent
        );
    }
    for w in &r.windows {
        println!(
            "  window to {:>6.0} s: {} ticks, {} missed, jitter p50 {:.0} / p99 {:.0} / max {:.0} us, skew p99 {:.0} us, {} episodes ({} flagged, {} frames dropped)",
            w.end_s,
            w.ticks,
            w.missed_ticks,
            w.jitter_us[0],
            w.jitter_us[1],
            w.jitter_us[2],
            w.skew_us[1],
            w.recorded,
            w.flagged.len(),
            w.dropped_frames
        );
    }
    let v = &r.verdict;
    println!(
        "  episodes: {} recorded and inspected, {} flagged, {} frames dropped",
        r.episodes.episodes,
        r.episodes.flagged.len(),
        r.episodes.dropped_frames
    );
    println!(
        "  disk: {} MB/h recorded, {} GB for an 8-hour day",
        v.disk_mb_per_h.map_or("-".into(), |m| format!("{m:.0}")),
        v.disk_gb_per_8h_day.map_or("-".into(), |g| format!("{g:.1}"))
    );
    if v.pass {
        println!(
            "  verdict: PASS (no growth >= {MAX_MB_PER_H} MB/h, no drift, 0 missed ticks, 0 dropped frames, every episode clean)"
        );
    } else {
        println!("  verdict: FAIL: {}", v.failed.join("; "));
    }
    println!("  report: {}  picture: {}", out.join("soak.json").display(), out.join("soak.png").display());
}

/// Memory and descriptors per process over time, and the loop's jitter per window.
fn plot(r: &Report, path: &Path) -> anyhow::Result<()> {
    use plotters::prelude::*;
    let font = labrig_episode::font::dejavu_sans().map_err(anyhow::Error::msg)?;
    let _ = plotters::style::register_font("sans-serif", FontStyle::Normal, font);
    let e = |e: DrawingAreaErrorKind<_>| anyhow::anyhow!("{e:?}");
    let root = BitMapBackend::new(path, (1100, 1000)).into_drawing_area();
    root.fill(&WHITE).map_err(e)?;
    let panels = root.split_evenly((3, 1));
    let t_max = (r.minutes * 60.0).max(1.0) / 60.0;
    let series = |f: &dyn Fn(&ProcSample) -> f64| -> Vec<(String, Vec<(f64, f64)>)> {
        r.samples.iter().map(|(n, v)| (n.clone(), v.iter().map(|s| (s.t_s / 60.0, f(&s.proc))).collect())).collect()
    };
    let draw = |area: &DrawingArea<BitMapBackend, plotters::coord::Shift>,
                title: &str,
                y: &str,
                lines: Vec<(String, Vec<(f64, f64)>)>|
     -> anyhow::Result<()> {
        let y_max = lines.iter().flat_map(|(_, v)| v.iter().map(|p| p.1)).fold(1.0f64, f64::max) * 1.1;
        let mut chart = ChartBuilder::on(area)
            .caption(title, ("sans-serif", 18))
            .margin(10)
            .x_label_area_size(35)
            .y_label_area_size(60)
            .build_cartesian_2d(0.0..t_max, 0.0..y_max)
            .map_err(e)?;
        chart.configure_mesh().x_desc("minutes").y_desc(y).draw().map_err(e)?;
        for (k, (name, v)) in lines.into_iter().enumerate() {
            let colour = Palette99::pick(k).to_rgba();
            chart
                .draw_series(LineSeries::new(v, colour.stroke_width(2)))
                .map_err(e)?
                .label(name)
                .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 16, y)], colour.stroke_width(2)));
        }
        chart
            .configure_series_labels()
            .background_style(WHITE.mix(0.8))
            .border_style(BLACK)
            .position(SeriesLabelPosition::UpperLeft)
            .draw()
            .map_err(e)?;
        Ok(())
    };
    draw(&panels[0], "resident memory per process", "MB", series(&|p| p.rss_bytes as f64 / 1e6))?;
    draw(&panels[1], "open file descriptors per process", "descriptors", series(&|p| f64::from(p.fds)))?;
    let jitter = |i: usize| r.windows.iter().map(|w| (w.end_s / 60.0, w.jitter_us[i])).collect::<Vec<_>>();
    draw(
        &panels[2],
        "the loop's period jitter per window (control loop)",
        "us",
        vec![("p50".into(), jitter(0)), ("p99".into(), jitter(1))],
    )?;
    root.present().map_err(e)?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn samples(mb_per_h: f64, fds: impl Fn(f64) -> u32) -> Vec<Sample> {
        (0..=60)
            .map(|k| {
                let t = f64::from(k) * 60.0;
                // A 100 MB jump in the warm-up's first 5 minutes, then the steady rate.
                let rss =
                    50e6 + if t < 300.0 { t / 300.0 * 100e6 } else { 100e6 + (t - 300.0) / 3600.0 * mb_per_h * 1e6 };
                Sample { t_s: t, proc: ProcSample { rss_bytes: rss as u64, fds: fds(t), threads: 9, cpu_s: t * 0.1 } }
            })
            .collect()
    }

    fn window(p99: f64, missed: u64) -> Window {
        Window {
            end_s: 300.0,
            seconds: 300.0,
            ticks: 6000,
            missed_ticks: missed,
            held_ticks: 0,
            steps_missing_frames: 0,
            steps_stale_frames: 0,
            episodes: 3,
            jitter_us: [10.0, p99, 2.0 * p99],
            skew_us: [1.0, 2.0, 3.0],
            recorded: 3,
            dropped_frames: 0,
            flagged: vec![],
        }
    }

    #[test]
    fn a_planted_growth_fails_the_verdict_and_a_flat_rig_passes() {
        let mut all = BTreeMap::new();
        all.insert("labrig-recorder".to_owned(), samples(0.0, |_| 40));
        all.insert("grower".to_owned(), samples(30.0, |_| 5));
        // A descriptor leak: one more every 10 minutes.
        all.insert("labrig-station".to_owned(), samples(0.5, |t| 20 + (t / 600.0) as u32));
        let procs = verdicts(&all, 600.0);
        let by = |n: &str| procs.iter().find(|p| p.name == n).unwrap();
        assert!((by("grower").rss_mb_per_h.unwrap() - 30.0).abs() < 1e-6, "{:?}", by("grower"));
        assert!(by("labrig-recorder").rss_mb_per_h.unwrap().abs() < 1e-6);
        assert!((by("grower").rss_floor_mb_per_h.unwrap() - 30.0).abs() < 1e-6, "{:?}", by("grower"));
        // Memory swinging between two fixed levels, more often at the high one late in the
        // run: the mean's line rises, the floor's does not.
        let swing: Vec<(f64, f64)> = (0..360)
            .map(|k| {
                let t = f64::from(k) * 10.0;
                let high = k % FLOOR_SAMPLES as i32 != 0 && (k > 180 || k % 3 == 1);
                (t, if high { 870.0 } else { 810.0 })
            })
            .collect();
        assert!(growth_per_hour(&swing, 0.0).unwrap() > 20.0);
        assert_eq!(floor_growth_per_hour(&swing, 0.0), Some(0.0));
        // On a line the standard error is 0; scatter about it widens it.
        assert!(by("grower").rss_mb_per_h_se.unwrap() < 1e-6);
        let noisy: Vec<(f64, f64)> = (0..100).map(|k| (f64::from(k), if k % 2 == 0 { 1.0 } else { -1.0 })).collect();
        let se = slope_se(&noisy, 0.0).unwrap();
        assert!((0.003..0.004).contains(&se), "1 / sqrt(sxx = 83325): {se}");
        assert!((by("labrig-recorder").cpu_percent - 10.0).abs() < 1e-9);
        let windows = [window(100.0, 0), window(120.0, 0)];
        let disk: Vec<DiskSample> = (0..=60)
            .map(|k| DiskSample {
                t_s: f64::from(k) * 60.0,
                recorded_bytes: k as u64 * 10_000_000,
                free_bytes: 1 << 40,
            })
            .collect();
        let judged = Judged { episodes: 6, dropped_frames: 0, flagged: vec![] };
        let v = verdict(&procs, &windows, &judged, &disk, 600.0);
        assert_eq!(v.growing.len(), 1, "{v:?}");
        assert_eq!(v.growing[0].0, "grower");
        assert_eq!(v.drifting, ["labrig-station"], "{v:?}");
        assert!(!v.pass);
        assert!(v.failed[0].contains("grower grows 30.0 MB/h"), "{:?}", v.failed);
        assert!((v.disk_mb_per_h.unwrap() - 600.0).abs() < 1e-6, "10 MB a minute");
        assert!((v.disk_gb_per_8h_day.unwrap() - 4.8).abs() < 1e-9);
        assert!((v.jitter_p99_ratio.unwrap() - 1.2).abs() < 1e-12);
        // Without the grower and the leak: it passes.
        all.remove("grower");
        all.insert("labrig-station".to_owned(), samples(0.5, |t| 20 + u32::from((t as u64).is_multiple_of(120))));
        let v = verdict(&verdicts(&all, 600.0), &windows, &judged, &disk, 600.0);
        assert!(v.pass, "{v:?}");
        assert_eq!(v.episodes, 6);
        // A missed tick, a jitter that doubled: each named.
        let v = verdict(&verdicts(&all, 600.0), &[window(100.0, 0), window(200.0, 2)], &judged, &disk, 600.0);
        assert_eq!(v.missed_ticks, 2);
        assert!(
            v.failed.iter().any(|f| f.contains("2 missed ticks")) && v.failed.iter().any(|f| f.contains("2.00x")),
            "{v:?}"
        );
    }
}
