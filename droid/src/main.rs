//! `labrig-droid`: what `labrig export droid`, `labrig import droid` and `labrig bench export`
//! run (a program of its own so only it links libhdf5 and runs ffmpeg).

use clap::{Args, Parser, Subcommand};
use indicatif::ProgressBar;
use labrig_droid::droid_mcap::{ExportedMcap, ImportedMcap, export_mcap, find_droid_mcaps, import_mcap};
use labrig_droid::export::{ExportOptions, Exported, export_episode};
use labrig_droid::import::{ImportOptions, Imported, find_droid_episodes, import_episode};
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::Instant;

#[derive(Debug, Parser)]
#[command(name = "labrig-droid", version, about = "DROID's raw episode format: export and import")]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// An MCAP episode (or every episode under a directory or in a manifest) -> DROID's raw layout under OUT:
    /// {success|failure}/<date>/<time>/{trajectory.h5, recordings/MP4/<serial>.mp4, metadata_<uuid>.json}.
    Export(ExportArgs),
    /// A DROID raw episode (or every one under a directory) -> an MCAP episode under --out.
    Import(ImportArgs),
    /// An MCAP episode (or every episode under a directory or in a manifest) -> DROID's own MCAP layout under OUT:
    /// {success|failure}/<date>/<time>/trajectory.mcap (JSON + jsonschema, base64 JPEG images).
    ExportMcap(ExportArgs),
    /// A DROID-layout MCAP file (either upstream variant, told apart by content), or every
    /// *.mcap under a directory that is not a labrig episode -> an MCAP episode under --out.
    ImportMcap(ImportMcapArgs),
    /// Export (and import back) throughput in steps per second, DROID raw and DROID MCAP.
    Bench(BenchArgs),
}

#[derive(Debug, Args)]
struct ImportMcapArgs {
    /// A DROID-layout MCAP file (trajectory.mcap), or a directory of them.
    source: PathBuf,
    /// Where the MCAP episodes go (the recorder's layout).
    #[arg(long, default_value = "episodes")]
    out: PathBuf,
    #[arg(long)]
    overwrite: bool,
    #[arg(long)]
    json: bool,
}

#[derive(Debug, Args)]
struct ExportArgs {
    /// An episode (its directory or episode_0.mcap), a directory of episodes, or a manifest
    /// (`labrig dataset retrieve`'s JSON, or a list of episode paths one a line).
    source: PathBuf,
    /// The DROID dataset root to write into.
    out: PathBuf,
    /// Replace episodes exported before.
    #[arg(long)]
    overwrite: bool,
    /// Print one JSON object per episode instead of text.
    #[arg(long)]
    json: bool,
}

#[derive(Debug, Args)]
struct ImportArgs {
    /// A DROID episode directory (holding trajectory.h5), or a directory of them.
    source: PathBuf,
    /// Where the MCAP episodes go (the recorder's layout).
    #[arg(long, default_value = "episodes")]
    out: PathBuf,
    #[arg(long)]
    overwrite: bool,
    /// JPEG quality of the imported frames.
    #[arg(long, default_value_t = 90, value_parser = clap::value_parser!(u8).range(1..=100))]
    jpeg_quality: u8,
    #[arg(long)]
    json: bool,
}

#[derive(Debug, Args)]
struct BenchArgs {
    /// The episode to export (its directory or MCAP file).
    episode: PathBuf,
    /// Exports (and imports) timed.
    #[arg(long, default_value_t = 5)]
    repeat: usize,
    #[arg(long)]
    json: bool,
}

/// The episodes `source` names: itself, or the episodes found under it.
fn sources(
    source: &Path,
    is_episode: impl Fn(&Path) -> bool,
    find: impl Fn(&Path) -> Vec<PathBuf>,
) -> anyhow::Result<Vec<PathBuf>> {
    anyhow::ensure!(source.exists(), "{}: no such file or directory", source.display());
    if source.is_file() || is_episode(source) {
        return Ok(vec![source.to_owned()]);
    }
    let found = find(source);
    anyhow::ensure!(!found.is_empty(), "{}: no episodes found under it", source.display());
    Ok(found)
}

/// The labrig episodes to export: an episode, a directory of them, or a manifest (a retrieval
/// manifest or a list of paths).
fn episodes(source: &Path) -> anyhow::Result<Vec<PathBuf>> {
    if source.is_dir() && source.join(labrig_episode::episode::EPISODE_FILE).is_file() {
        return Ok(vec![source.to_owned()]);
    }
    labrig_episode::episode::episodes_of(source).map_err(anyhow::Error::msg)
}

fn run_all<T: serde::Serialize>(
    items: &[PathBuf],
    what: &str,
    json: bool,
    one: impl Fn(&Path) -> Result<T, labrig_droid::DroidError>,
    line: impl Fn(&T) -> String,
    steps_of: impl Fn(&T) -> usize,
) -> ExitCode {
    let started = Instant::now();
    let pb = if items.len() > 1 && !json {
        labrig_episode::progress::bar(&format!("{what} {{bar:30}} {{pos}}/{{len}} episodes"), items.len() as u64, false)
    } else {
        ProgressBar::hidden()
    };
    let (mut ok, mut failed, mut steps) = (0usize, 0usize, 0usize);
    for p in items {
        pb.set_message(p.display().to_string());
        match one(p) {
            Ok(r) => {
                ok += 1;
                steps += steps_of(&r);
                if json {
                    println!("{}", serde_json::to_string(&r).unwrap_or_default());
                } else {
                    pb.suspend(|| println!("{}", line(&r)));
                }
            }
            Err(e) => {
                failed += 1;
                pb.suspend(|| eprintln!("error: {e:#}"));
            }
        }
        pb.inc(1);
    }
    pb.finish_and_clear();
    let secs = started.elapsed().as_secs_f64();
    if !json && items.len() > 1 {
        println!(
            "{what}: {ok} episodes, {steps} steps in {secs:.1} s ({:.0} steps/s){}",
            steps as f64 / secs.max(1e-9),
            if failed > 0 { format!("; {failed} failed") } else { String::new() }
        );
    }
    if failed > 0 { ExitCode::FAILURE } else { ExitCode::SUCCESS }
}

fn export_line(e: &Exported) -> String {
    format!(
        "exported {} -> {} ({} steps, {} cameras{}, {:.2} s, {:.0} steps/s)",
        e.source.display(),
        e.dir.display(),
        e.steps,
        e.cameras.len(),
        if e.frames_filled > 0 {
            format!(", {} frames filled from a neighbouring step", e.frames_filled)
        } else {
            String::new()
        },
        e.seconds,
        e.steps as f64 / e.seconds.max(1e-9)
    )
}

fn import_line(i: &Imported) -> String {
    import_line_noted(i, "")
}

/// An import's line; `note` goes first in the brackets.
fn import_line_noted(i: &Imported, note: &str) -> String {
    let mut s = format!(
        "imported {} -> {} ({note}{} steps, {} cameras, {} frames, {:.2} s)",
        i.source.display(),
        i.dir.display(),
        i.steps,
        i.cameras.len(),
        i.frames,
        i.seconds
    );
    for w in &i.warnings {
        s.push_str(&format!("\n  warning: {w}"));
    }
    s
}

fn export_mcap_line(e: &ExportedMcap) -> String {
    format!(
        "exported {} -> {} ({} steps, {} cameras, {} images{}{}, {:.1} MB, {:.2} s, {:.0} steps/s)",
        e.source.display(),
        e.file.display(),
        e.steps,
        e.cameras.len(),
        e.images,
        if e.frames_filled > 0 {
            format!(" ({} filled from a neighbouring frame)", e.frames_filled)
        } else {
            String::new()
        },
        if e.vr_messages > 0 { format!(", {} /vr_controller", e.vr_messages) } else { String::new() },
        e.bytes as f64 / 1e6,
        e.seconds,
        e.steps as f64 / e.seconds.max(1e-9)
    )
}

fn import_mcap_line(m: &ImportedMcap) -> String {
    let ms = if m.times_in_ms { ", log times read as DROID's milliseconds" } else { "" };
    import_line_noted(&m.imported, &format!("{}{ms}; ", m.variant.describe()))
}

fn percentile(v: &mut [f64], p: f64) -> f64 {
    v.sort_by(f64::total_cmp);
    v[((v.len() - 1) as f64 * p).round() as usize]
}

fn bench(a: BenchArgs) -> anyhow::Result<ExitCode> {
    anyhow::ensure!(a.repeat > 0, "--repeat must be at least 1");
    let tmp = std::env::temp_dir().join(format!("labrig-droid-bench-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&tmp);
    let (mut export_rate, mut h5_rate, mut import_rate) = (Vec::new(), Vec::new(), Vec::new());
    let (mut mcap_export_rate, mut mcap_import_rate) = (Vec::new(), Vec::new());
    let mut first: Option<Exported> = None;
    let pb = labrig_episode::progress::bar("bench droid {bar:30} {pos}/{len} round trips", a.repeat as u64, a.json);
    for _ in 0..a.repeat {
        let e = export_episode(&a.episode, &tmp.join("droid"), &ExportOptions { overwrite: true })?;
        let i =
            import_episode(&e.dir, &tmp.join("mcap"), &ImportOptions { overwrite: true, ..ImportOptions::default() })?;
        export_rate.push(e.steps as f64 / e.seconds);
        h5_rate.push(e.steps as f64 / e.h5_seconds.max(1e-9));
        import_rate.push(i.steps as f64 / i.seconds);
        // DROID's MCAP layout: the same episode out and back in.
        let m = export_mcap(&a.episode, &tmp.join("droid_mcap"), &ExportOptions { overwrite: true })?;
        let back = import_mcap(
            &m.file,
            &tmp.join("mcap_back"),
            &ImportOptions { overwrite: true, ..ImportOptions::default() },
        )?;
        mcap_export_rate.push(m.steps as f64 / m.seconds);
        mcap_import_rate.push(back.imported.steps as f64 / back.imported.seconds);
        first.get_or_insert(e);
        pb.inc(1);
    }
    pb.finish_and_clear();
    let _ = std::fs::remove_dir_all(&tmp);
    let e = first.expect("repeat > 0");
    let summary = serde_json::json!({
        "episode": e.source, "steps": e.steps, "cameras": e.cameras.len(), "repeat": a.repeat,
        "export_steps_per_s": {"p50": percentile(&mut export_rate, 0.5), "min": percentile(&mut export_rate, 0.0), "max": percentile(&mut export_rate, 1.0)},
        "h5_only_steps_per_s": {"p50": percentile(&mut h5_rate, 0.5)},
        "import_steps_per_s": {"p50": percentile(&mut import_rate, 0.5), "min": percentile(&mut import_rate, 0.0), "max": percentile(&mut import_rate, 1.0)},
        "realtime_factor_export_p50": percentile(&mut export_rate, 0.5) / 20.0,
        "droid_mcap_export_steps_per_s": {"p50": percentile(&mut mcap_export_rate, 0.5), "min": percentile(&mut mcap_export_rate, 0.0), "max": percentile(&mut mcap_export_rate, 1.0)},
        "droid_mcap_import_steps_per_s": {"p50": percentile(&mut mcap_import_rate, 0.5), "min": percentile(&mut mcap_import_rate, 0.0), "max": percentile(&mut mcap_import_rate, 1.0)},
    });
    if a.json {
        println!("{summary}");
    } else {
        println!(
            "DROID export of {} ({} steps, {} cameras), {} runs (shared 2-core machine: figures are noisy)",
            e.source.display(),
            e.steps,
            e.cameras.len(),
            a.repeat
        );
        println!(
            "  export: p50 {:.0} steps/s (min {:.0}, max {:.0}) = {:.1}x the 20 Hz recording rate; trajectory.h5 alone {:.0} steps/s",
            summary["export_steps_per_s"]["p50"].as_f64().unwrap_or(0.0),
            summary["export_steps_per_s"]["min"].as_f64().unwrap_or(0.0),
            summary["export_steps_per_s"]["max"].as_f64().unwrap_or(0.0),
            summary["realtime_factor_export_p50"].as_f64().unwrap_or(0.0),
            summary["h5_only_steps_per_s"]["p50"].as_f64().unwrap_or(0.0),
        );
        let line = |what: &str, key: &str| {
            println!(
                "  {what}: p50 {:.0} steps/s (min {:.0}, max {:.0})",
                summary[key]["p50"].as_f64().unwrap_or(0.0),
                summary[key]["min"].as_f64().unwrap_or(0.0),
                summary[key]["max"].as_f64().unwrap_or(0.0),
            )
        };
        line("import", "import_steps_per_s");
        line("DROID MCAP export", "droid_mcap_export_steps_per_s");
        line("DROID MCAP import", "droid_mcap_import_steps_per_s");
    }
    Ok(ExitCode::SUCCESS)
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    if labrig_msgs::parse_only() {
        return ExitCode::SUCCESS;
    }
    let r = match cli.command {
        Command::Export(a) => episodes(&a.source).map(|items| {
            let opts = ExportOptions { overwrite: a.overwrite };
            run_all(&items, "export", a.json, |p| export_episode(p, &a.out, &opts), export_line, |e| e.steps)
        }),
        Command::Import(a) => {
            let is_episode = |p: &Path| p.join("trajectory.h5").is_file();
            sources(&a.source, is_episode, find_droid_episodes).map(|items| {
                let opts = ImportOptions { overwrite: a.overwrite, jpeg_quality: a.jpeg_quality };
                run_all(&items, "import", a.json, |p| import_episode(p, &a.out, &opts), import_line, |i| i.steps)
            })
        }
        Command::ExportMcap(a) => episodes(&a.source).map(|items| {
            let opts = ExportOptions { overwrite: a.overwrite };
            run_all(&items, "export", a.json, |p| export_mcap(p, &a.out, &opts), export_mcap_line, |e| e.steps)
        }),
        Command::ImportMcap(a) => sources(&a.source, |_| false, find_droid_mcaps).map(|items| {
            let opts = ImportOptions { overwrite: a.overwrite, ..ImportOptions::default() };
            run_all(&items, "import", a.json, |p| import_mcap(p, &a.out, &opts), import_mcap_line, |i| i.imported.steps)
        }),
        Command::Bench(a) => bench(a),
    };
    match r {
        Ok(code) => code,
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::FAILURE
        }
    }
}
