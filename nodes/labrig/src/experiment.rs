//! `labrig experiment retrieval`: the paper's result on the simulated rig, end to end, as one
//! resumable command. A config (experiments/retrieval/*.toml) names a target task (a scene
//! spec, a few demos, the rollouts' seeds), a prior dataset in the shape of a large diverse one
//! (scene specs and demo counts), one training recipe and the conditions: the target demos
//! alone, with every prior demo, or with the demos an alignment retrieves (`labrig dataset
//! retrieve --align ...`). The command records the data (`labrig demo`, several rigs at once), indexes
//! the prior, and for each condition retrieves its manifest, trains (`labrig train`, the same
//! recipe and steps for all) and judges it (`labrig rollout` on the target's seeds), then
//! writes the table (`results.md`, `results.json`) and the paper-style figure (`results.png`).
//!
//! Every stage is the labrig command a user would type, run as a child process with its log
//! under `<out>/logs/`; a stage is done when its output is complete (a set's `demo.json`, a
//! condition's `manifest.json`, `run/run.json` at the configured steps, `rollouts/rollouts.json`),
//! so a run cut off anywhere continues where it stopped: a partly recorded set is recorded
//! again, a training resumes from its last checkpoint, a condition's rollouts run again. The
//! summary is built from whatever conditions are done (`--summary-only` builds it alone).

use anyhow::{Context, bail, ensure};
use clap::{Args, Subcommand};
use labrig_episode::progress;
use labrig_launch::rollout::{RolloutReport, wilson95};
use labrig_reports::{DemoReport, IndexReport, ManifestEpisodes, RunReport};
use serde::{Deserialize, Serialize};
use serde_json::{Value, json};
use std::collections::BTreeSet;
use std::io::Read;
use std::path::{Path, PathBuf};
use std::process::{Command, ExitCode, Stdio};
use std::time::Instant;

#[derive(Debug, Subcommand)]
pub enum ExperimentCommand {
    /// The paper's result in the sim: co-training on retrieved demos (camPose, objSpat, ...)
    /// against the target demos alone and against every prior demo; resumable, with a table and
    /// a figure (experiments/retrieval/README.md).
    Retrieval(RetrievalArgs),
}

#[derive(Debug, Args)]
pub struct RetrievalArgs {
    /// The experiment: target task, prior data, recipe, conditions (experiments/retrieval/
    /// full.toml is the documented run, ci.toml the CI-sized one).
    #[arg(long, default_value = "experiments/retrieval/full.toml")]
    pub config: PathBuf,
    /// Where everything goes; running again with the same --out continues the run.
    #[arg(long, default_value = "out/experiment/retrieval")]
    pub out: PathBuf,
    /// Run only these conditions (comma-separated names; default: all, in the config's order).
    #[arg(long, value_delimiter = ',')]
    pub conditions: Vec<String>,
    /// Demo rigs recording at once.
    #[arg(long, default_value_t = 2)]
    pub jobs: usize,
    /// DDS domain ids from this one: the demo rigs take this one and the next `--jobs - 1`,
    /// the rollout rig this one.
    #[arg(long, default_value_t = 50)]
    pub domain_id: u16,
    /// Training's intra-op threads (default: every core).
    #[arg(long)]
    pub threads: Option<i32>,
    /// Build the table and figure from the conditions done so far; run nothing.
    #[arg(long)]
    pub summary_only: bool,
    /// Print the results as JSON.
    #[arg(long)]
    pub json: bool,
}

/// An experiment config (TOML). Scene paths are relative to the config's folder, or a
/// built-in scene's name.
#[derive(Debug, Clone, Deserialize, Serialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct ExperimentConfig {
    pub name: String,
    /// `labrig train --preset` (a preset's name, or a TOML file relative to the config).
    pub preset: String,
    /// Optimisation steps, the same for every condition.
    pub steps: u64,
    #[serde(default)]
    pub batch_size: Option<u64>,
    /// The probability that a sample comes from the target demos (the paper: 0.5).
    #[serde(default = "default_w")]
    pub w: f64,
    /// The training seed (default: the preset's).
    #[serde(default)]
    pub train_seed: Option<u64>,
    /// Validation interval (default: the preset's).
    #[serde(default)]
    pub val_every: Option<u64>,
    /// Rollouts per condition (the paper: 20), on the target scene's seeds from `rollout_first_seed`.
    pub rollouts: u64,
    #[serde(default = "default_rollout_seed")]
    pub rollout_first_seed: u64,
    /// More sets of `rollouts` rollouts each, from these first seeds (e.g. [2000]): a condition's
    /// success counts every set. May be added to a run later (the done sets are kept).
    #[serde(default)]
    pub more_rollout_seeds: Vec<u64>,
    /// A rollout not solved after this many steps fails.
    #[serde(default = "default_max_steps")]
    pub max_steps: u64,
    /// The demos' expert (`labrig demo --expert-aim-error-m`, `--expert-miss-fraction`).
    #[serde(default)]
    pub expert_aim_error_m: f64,
    #[serde(default)]
    pub expert_miss_fraction: f64,
    /// `labrig dataset retrieve`'s thresholds (default: the paper's).
    #[serde(default)]
    pub retrieval: Thresholds,
    pub target: DataSpec,
    #[serde(default)]
    pub prior: Vec<DataSpec>,
    pub condition: Vec<ConditionSpec>,
}

fn default_w() -> f64 {
    0.5
}
fn default_rollout_seed() -> u64 {
    1000
}
fn default_max_steps() -> u64 {
    300
}

#[derive(Debug, Clone, Default, Deserialize, Serialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct Thresholds {
    pub cam_xy_m: Option<f64>,
    pub cam_z_m: Option<f64>,
    pub obj_box_m: Option<[f64; 3]>,
}

/// A set of demos: `labrig demo --scene <scene> --episodes <episodes> --first-seed <first_seed>`.
#[derive(Debug, Clone, Deserialize, Serialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct DataSpec {
    pub name: String,
    pub scene: String,
    pub episodes: u64,
    pub first_seed: u64,
}

/// A condition: what is co-trained with the target demos.
#[derive(Debug, Clone, Deserialize, Serialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct ConditionSpec {
    pub name: String,
    /// One line on what it is (the table's second column).
    #[serde(default)]
    pub about: String,
    /// Co-train on every prior demo.
    #[serde(default)]
    pub all: bool,
    /// Co-train on the prior demos `labrig dataset retrieve --align <align>` keeps.
    #[serde(default)]
    pub align: Vec<String>,
    /// This condition's w (default: the experiment's).
    #[serde(default)]
    pub w: Option<f64>,
}

impl ConditionSpec {
    fn cotrain(&self) -> String {
        if self.all {
            "every prior demo".to_owned()
        } else if self.align.is_empty() {
            "none".to_owned()
        } else {
            format!("retrieved: {}", self.align.join(","))
        }
    }
}

/// Demo rigs at once at most (their domains: `--domain-id` and the next seven).
const MAX_JOBS: usize = 8;
const BUILT_IN_SCENES: [&str; 3] = ["pick_place", "drawer_open", "drawer_close"];
const DIMS: [&str; 5] = ["object", "skill", "camPose", "objTex", "objSpat"];

impl ExperimentConfig {
    pub fn load(path: &Path) -> anyhow::Result<ExperimentConfig> {
        let cfg: ExperimentConfig = labrig_runtime::load_config(path)?;
        cfg.validate().with_context(|| format!("{}", path.display()))?;
        Ok(cfg)
    }

    /// The first seed of each set of rollouts, the main set first.
    fn seed_sets(&self) -> Vec<u64> {
        std::iter::once(self.rollout_first_seed).chain(self.more_rollout_seeds.iter().copied()).collect()
    }

    /// A seed set's folder in a condition's: `rollouts` for the main set, `rollouts_<first seed>`.
    fn rollouts_dir(&self, first_seed: u64) -> String {
        if first_seed == self.rollout_first_seed { "rollouts".to_owned() } else { format!("rollouts_{first_seed}") }
    }

    fn validate(&self) -> anyhow::Result<()> {
        let name_ok = |n: &str| {
            !n.is_empty() && n.chars().all(|c| c.is_ascii_alphanumeric() || "_-+.".contains(c)) && !n.starts_with('.')
        };
        ensure!(self.steps >= 1, "steps must be at least 1");
        ensure!((1..=1000).contains(&self.rollouts), "rollouts must be in 1..=1000");
        let mut sets = self.seed_sets();
        sets.sort_unstable();
        for w in sets.windows(2) {
            ensure!(
                w[1] >= w[0] + self.rollouts,
                "rollout seed sets from {} and {} overlap ({} rollouts each)",
                w[0],
                w[1],
                self.rollouts
            );
        }
        ensure!((0.0..=1.0).contains(&self.w), "w must be in 0..=1 (it is {})", self.w);
        let mut names = BTreeSet::new();
        for d in std::iter::once(&self.target).chain(&self.prior) {
            ensure!(name_ok(&d.name), "data set name `{}`: use letters, digits, _ - + .", d.name);
            ensure!(names.insert(d.name.as_str()), "two data sets are named `{}`", d.name);
            ensure!((1..=100).contains(&d.episodes), "data set `{}`: episodes must be in 1..=100", d.name);
        }
        let mut conditions = BTreeSet::new();
        ensure!(!self.condition.is_empty(), "no [[condition]]");
        for c in &self.condition {
            ensure!(name_ok(&c.name), "condition name `{}`: use letters, digits, _ - + .", c.name);
            ensure!(conditions.insert(c.name.as_str()), "two conditions are named `{}`", c.name);
            ensure!(!c.all || c.align.is_empty(), "condition `{}`: `all` and `align` exclude each other", c.name);
            for d in &c.align {
                ensure!(
                    DIMS.contains(&d.as_str()),
                    "condition `{}`: unknown alignment `{d}` (one of {DIMS:?})",
                    c.name
                );
            }
            if let Some(w) = c.w {
                ensure!((0.0..=1.0).contains(&w), "condition `{}`: w must be in 0..=1", c.name);
            }
            ensure!(
                !self.prior.is_empty() || (!c.all && c.align.is_empty()),
                "condition `{}` co-trains on prior data, but the config has no [[prior]]",
                c.name
            );
        }
        Ok(())
    }
}

/// A scene as `labrig demo --scene` takes it: a spec file relative to the config's folder (made
/// absolute), or a built-in scene's name.
fn resolve_scene(scene: &str, config_dir: &Path) -> anyhow::Result<String> {
    let p = config_dir.join(scene);
    if p.is_file() {
        return Ok(std::fs::canonicalize(&p)?.to_string_lossy().into_owned());
    }
    ensure!(
        BUILT_IN_SCENES.contains(&scene),
        "scene `{scene}`: no file {} and not a built-in scene ({BUILT_IN_SCENES:?})",
        p.display()
    );
    Ok(scene.to_owned())
}

/// What every stage of a run reads.
struct Run<'a> {
    cfg: &'a ExperimentConfig,
    config_dir: &'a Path,
    layout: &'a Layout,
    args: &'a RetrievalArgs,
}

impl Run<'_> {
    /// A stage's line on stdout (none with --json).
    fn say(&self, line: String) {
        if !self.args.json {
            println!("{line}");
        }
    }
}

/// The experiment's folders.
struct Layout {
    out: PathBuf,
}

impl Layout {
    fn data(&self, name: &str, target: bool) -> PathBuf {
        if target { self.out.join("data/target").join(name) } else { self.out.join("data/prior").join(name) }
    }
    fn prior_root(&self) -> PathBuf {
        self.out.join("data/prior")
    }
    fn target_episodes(&self, cfg: &ExperimentConfig) -> PathBuf {
        self.data(&cfg.target.name, true).join("episodes")
    }
    fn condition(&self, name: &str) -> PathBuf {
        self.out.join("conditions").join(name)
    }
    fn log(&self, stage: &str) -> PathBuf {
        self.out.join("logs").join(format!("{stage}.log"))
    }
}

/// What a run must keep from its first invocation to be continued: everything but the
/// conditions (each condition keeps its own).
fn run_identity(cfg: &ExperimentConfig, config_dir: &Path) -> anyhow::Result<Value> {
    let scene = |d: &DataSpec| -> anyhow::Result<Value> {
        let path = resolve_scene(&d.scene, config_dir)?;
        // A spec file counts by its content (the same experiment from another checkout continues).
        let content = if Path::new(&path).is_file() { std::fs::read_to_string(&path)? } else { path.clone() };
        Ok(json!({"name": d.name, "scene": content, "episodes": d.episodes, "first_seed": d.first_seed}))
    };
    let preset = resolve_preset(&cfg.preset, config_dir);
    let preset_content =
        if Path::new(&preset).is_file() { std::fs::read_to_string(&preset)? } else { preset.to_owned() };
    Ok(json!({
        "target": scene(&cfg.target)?,
        "prior": cfg.prior.iter().map(scene).collect::<anyhow::Result<Vec<_>>>()?,
        "expert_aim_error_m": cfg.expert_aim_error_m,
        "expert_miss_fraction": cfg.expert_miss_fraction,
        "retrieval": cfg.retrieval,
        "preset": preset_content,
        "steps": cfg.steps,
        "batch_size": cfg.batch_size,
        "w": cfg.w,
        "train_seed": cfg.train_seed,
        "val_every": cfg.val_every,
        "rollouts": cfg.rollouts,
        "rollout_first_seed": cfg.rollout_first_seed,
        "max_steps": cfg.max_steps,
    }))
}

/// A preset file relative to the config's folder, else the preset's name as given.
fn resolve_preset(preset: &str, config_dir: &Path) -> String {
    let p = config_dir.join(preset);
    if preset.ends_with(".toml") && p.is_file() { p.to_string_lossy().into_owned() } else { preset.to_owned() }
}

/// Refuses to continue a run made with another experiment (names what differs), or records
/// this one in `<out>/experiment.json`.
fn check_identity(path: &Path, identity: &Value) -> anyhow::Result<()> {
    if let Ok(text) = std::fs::read_to_string(path) {
        let old: Value = serde_json::from_str(&text).with_context(|| format!("{}", path.display()))?;
        if &old != identity {
            let differs: Vec<&str> = identity
                .as_object()
                .into_iter()
                .flatten()
                .filter(|(k, v)| old.get(k.as_str()) != Some(v))
                .map(|(k, _)| k.as_str())
                .collect();
            bail!(
                "{} was made by another experiment (it differs in: {}): continue it with its own config, or give another --out",
                path.parent().unwrap_or(Path::new(".")).display(),
                differs.join(", ")
            );
        }
        return Ok(());
    }
    write_json(path, identity)
}

fn write_json(path: &Path, v: &impl Serialize) -> anyhow::Result<()> {
    if let Some(dir) = path.parent() {
        std::fs::create_dir_all(dir)?;
    }
    let tmp = path.with_extension("json.part");
    std::fs::write(&tmp, serde_json::to_string_pretty(v)? + "\n")?;
    std::fs::rename(&tmp, path)?;
    Ok(())
}

/// Runs `labrig <args>` with its stderr in `log`; returns its stdout. A failure names the
/// stage, the exit status, the log and its last lines.
fn run_stage(stage: &str, args: &[String], env: &[(&str, String)], log: &Path, quiet: bool) -> anyhow::Result<String> {
    std::fs::create_dir_all(log.parent().unwrap_or(Path::new(".")))?;
    // This very binary, even when a rebuild has replaced the file meanwhile (a long run keeps
    // the labrig it started with; `current_exe` would name the deleted file).
    let exe = Path::new("/proc/self/exe");
    let exe = if exe.exists() { exe.to_owned() } else { std::env::current_exe()? };
    let mut file = std::fs::OpenOptions::new().create(true).append(true).open(log)?;
    use std::io::Write;
    writeln!(file, "\n$ labrig {}", args.join(" "))?;
    let mut cmd = Command::new(&exe);
    cmd.args(args)
        .envs(env.iter().map(|(k, v)| (*k, v.as_str())))
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::from(file));
    // A stage never outlives the experiment (killed, it would keep writing what a rerun redoes).
    labrig_launch::supervise::stop_with_launcher(&mut cmd);
    let mut child = cmd.spawn().with_context(|| format!("{stage}: cannot start {}", exe.display()))?;
    let bar = progress::bar(stage, 0, quiet);
    let mut out = String::new();
    child.stdout.take().context("stdout")?.read_to_string(&mut out)?;
    let status = child.wait()?;
    bar.finish_and_clear();
    if !status.success() {
        let text = std::fs::read_to_string(log).unwrap_or_default();
        let tail: Vec<&str> = text.lines().rev().take(8).collect::<Vec<_>>().into_iter().rev().collect();
        bail!("{stage} failed ({status}); its log is {}:\n{}", log.display(), tail.join("\n"));
    }
    Ok(out)
}

fn minutes(s: f64) -> String {
    if s < 90.0 { format!("{s:.0} s") } else { format!("{:.1} min", s / 60.0) }
}

/// A stage's wall time (`train_time.json`, a rollout set's `wall.json`): written by the stage,
/// read by the table.
#[derive(Debug, Clone, Copy, Default, Serialize, Deserialize)]
struct WallTime {
    wall_s: f64,
    /// The sittings a stage cut off and resumed took (0 where it is not counted).
    #[serde(default)]
    sittings: u64,
}

/// Adds `seconds` to the wall time kept in `path` (a stage run in several sittings).
fn add_wall(path: &Path, seconds: f64) -> anyhow::Result<f64> {
    let kept = labrig_reports::read::<WallTime>(path).unwrap_or_default();
    let wall = WallTime { wall_s: kept.wall_s + seconds, sittings: kept.sittings + 1 };
    write_json(path, &wall)?;
    Ok(wall.wall_s)
}

pub fn run(cmd: ExperimentCommand) -> anyhow::Result<ExitCode> {
    match cmd {
        ExperimentCommand::Retrieval(a) => retrieval(a),
    }
}

fn retrieval(args: RetrievalArgs) -> anyhow::Result<ExitCode> {
    let cfg = ExperimentConfig::load(&args.config)?;
    let config_dir =
        std::fs::canonicalize(args.config.parent().filter(|p| !p.as_os_str().is_empty()).unwrap_or(Path::new(".")))?;
    for c in &args.conditions {
        ensure!(
            cfg.condition.iter().any(|k| &k.name == c),
            "--conditions: no condition `{c}` in {} (it has {})",
            args.config.display(),
            cfg.condition.iter().map(|k| k.name.as_str()).collect::<Vec<_>>().join(", ")
        );
    }
    ensure!((1..=MAX_JOBS).contains(&args.jobs), "--jobs must be in 1..={MAX_JOBS}");
    std::fs::create_dir_all(&args.out)?;
    let out = std::fs::canonicalize(&args.out)?;
    let layout = Layout { out };
    let identity = run_identity(&cfg, &config_dir)?;
    let quiet = args.json;
    let run = Run { cfg: &cfg, config_dir: &config_dir, layout: &layout, args: &args };
    let say = |line: String| run.say(line);
    if !args.summary_only {
        check_identity(&layout.out.join("experiment.json"), &identity)?;
        let started = Instant::now();
        say(format!(
            "experiment {} -> {} ({} conditions, {} steps each, {} rollouts each)",
            cfg.name,
            layout.out.display(),
            cfg.condition.len(),
            cfg.steps,
            cfg.rollouts
        ));
        record_data(&run)?;
        let chosen: Vec<&ConditionSpec> =
            cfg.condition.iter().filter(|c| args.conditions.is_empty() || args.conditions.contains(&c.name)).collect();
        if chosen.iter().any(|c| !c.align.is_empty()) {
            let log = layout.log("index");
            let t = Instant::now();
            let idx = layout.out.join("index");
            let report = run_stage(
                "[index] the prior data",
                &strings(&["dataset", "index", &path_str(&layout.prior_root()), "--out", &path_str(&idx), "--json"]),
                &[],
                &log,
                quiet,
            )?;
            let r: IndexReport = serde_json::from_str(report.trim()).context("[index]: the index's report")?;
            say(format!(
                "[index] the prior data: {} episodes ({} unreadable) in {}",
                r.in_shard,
                r.bad.len(),
                minutes(t.elapsed().as_secs_f64())
            ));
        }
        for c in chosen {
            run_condition(&run, c)?;
            // The table after every condition: a run cut off later keeps what it has.
            let _ = summarise(&cfg, &config_dir, &layout)?;
        }
        say(format!("experiment {}: ran {} this sitting", cfg.name, minutes(started.elapsed().as_secs_f64())));
    }
    let results = summarise(&cfg, &config_dir, &layout)?;
    if args.json {
        println!("{}", serde_json::to_string(&results)?);
    } else {
        print!("{}", table_text(&results));
        println!(
            "table: {}  figure: {}",
            layout.out.join("results.md").display(),
            layout.out.join("results.png").display()
        );
    }
    Ok(ExitCode::SUCCESS)
}

fn strings(a: &[&str]) -> Vec<String> {
    a.iter().map(|s| (*s).to_owned()).collect()
}

fn path_str(p: &Path) -> String {
    p.to_string_lossy().into_owned()
}

/// Records every data set not yet complete, `--jobs` rigs at once (each its own DDS domain and
/// frame namespace). A set is complete when its `demo.json` (the demo's report, written last)
/// is there; a set without one was cut off and is recorded again from scratch.
fn record_data(run: &Run) -> anyhow::Result<()> {
    let &Run { cfg, config_dir, layout, args } = run;
    let say = |line: String| run.say(line);
    let mut todo = Vec::new();
    for (d, target) in std::iter::once((&cfg.target, true)).chain(cfg.prior.iter().map(|d| (d, false))) {
        let dir = layout.data(&d.name, target);
        if let Some(r) = labrig_reports::read::<DemoReport>(&dir.join("demo.json")) {
            say(format!("[data] {}: recorded earlier ({} episodes, {} successful)", d.name, r.recorded, r.successes));
            continue;
        }
        if dir.exists() {
            std::fs::remove_dir_all(&dir).with_context(|| format!("removing the partly recorded {}", dir.display()))?;
        }
        todo.push((d.clone(), target, resolve_scene(&d.scene, config_dir)?));
    }
    if todo.is_empty() {
        return Ok(());
    }
    let queue = std::sync::Mutex::new(todo.into_iter());
    let errors = std::sync::Mutex::new(Vec::new());
    let jobs = args.jobs;
    std::thread::scope(|s| {
        for j in 0..jobs {
            let (queue, errors) = (&queue, &errors);
            s.spawn(move || {
                loop {
                    let next = queue.lock().map(|mut q| q.next()).unwrap_or(None);
                    let Some((d, target, scene)) = next else { break };
                    let domain = args.domain_id + j as u16;
                    let ns = format!("exp{}j{j}", std::process::id());
                    if let Err(e) = record_set(run, &d, target, &scene, domain, &ns)
                        && let Ok(mut v) = errors.lock()
                    {
                        v.push(format!("{e:#}"));
                    }
                }
            });
        }
    });
    let errors = errors.into_inner().unwrap_or_default();
    ensure!(errors.is_empty(), "recording the data failed:\n{}", errors.join("\n"));
    Ok(())
}

fn record_set(run: &Run, d: &DataSpec, target: bool, scene: &str, domain: u16, ns: &str) -> anyhow::Result<()> {
    let &Run { cfg, layout, .. } = run;
    let say = |line: String| run.say(line);
    let dir = layout.data(&d.name, target);
    let t = Instant::now();
    let mut a = strings(&["demo", "--scene", scene]);
    a.extend(strings(&[
        "--episodes",
        &d.episodes.to_string(),
        "--first-seed",
        &d.first_seed.to_string(),
        "--out",
        &path_str(&dir),
        "--domain-id",
        &domain.to_string(),
        "--expert-aim-error-m",
        &cfg.expert_aim_error_m.to_string(),
        "--expert-miss-fraction",
        &cfg.expert_miss_fraction.to_string(),
        "--json",
    ]));
    let stage = format!("[data] {}", d.name);
    // Several rigs at once: the demo's bar would interleave, so this stage shows none.
    let report = run_stage(
        &stage,
        &a,
        &[(labrig_runtime::frames::NAMESPACE_ENV, ns.to_owned())],
        &layout.log(&format!("data_{}", d.name)),
        true,
    )?;
    let r: DemoReport = serde_json::from_str(report.trim()).with_context(|| format!("{stage}: the demo's report"))?;
    ensure!(r.ok, "{stage}: the demo reported errors: {}", r.errors.join("; "));
    write_json(&dir.join("demo.json"), &r)?;
    say(format!(
        "[data] {}: {} episodes ({} successful) of {} seeds {}.. in {}",
        d.name,
        r.recorded,
        r.successes,
        Path::new(&d.scene).file_name().map_or(d.scene.clone(), |f| f.to_string_lossy().into_owned()),
        d.first_seed,
        minutes(t.elapsed().as_secs_f64())
    ));
    Ok(())
}

/// One condition: its manifest, its training, its rollouts; each skipped when done.
fn run_condition(run: &Run, c: &ConditionSpec) -> anyhow::Result<()> {
    let &Run { cfg, config_dir, layout, args } = run;
    let say = |line: String| run.say(line);
    let quiet = args.json;
    let dir = layout.condition(&c.name);
    std::fs::create_dir_all(&dir)?;
    check_identity(&dir.join("condition.json"), &serde_json::to_value(c)?)?;
    let w = c.w.unwrap_or(cfg.w);
    // The co-training set.
    let cotrain: Option<PathBuf> = if c.all {
        Some(layout.prior_root())
    } else if c.align.is_empty() {
        None
    } else {
        let manifest = dir.join("manifest.json");
        if !manifest.exists() {
            let mut a = strings(&[
                "dataset",
                "retrieve",
                "--index",
                &path_str(&layout.out.join("index")),
                "--target",
                &path_str(&layout.target_episodes(cfg)),
                "--align",
                &c.align.join(","),
                "--out",
                &path_str(&dir.join("manifest.json.part")),
            ]);
            if let Some(v) = cfg.retrieval.cam_xy_m {
                a.extend(["--cam-xy-m".to_owned(), v.to_string()]);
            }
            if let Some(v) = cfg.retrieval.cam_z_m {
                a.extend(["--cam-z-m".to_owned(), v.to_string()]);
            }
            if let Some([x, y, z]) = cfg.retrieval.obj_box_m {
                a.extend(["--obj-box-m".to_owned(), format!("{x},{y},{z}")]);
            }
            run_stage(&format!("[retrieve] {}", c.name), &a, &[], &layout.log(&format!("{}_retrieve", c.name)), quiet)?;
            std::fs::rename(dir.join("manifest.json.part"), &manifest)?;
        }
        let m: ManifestEpisodes = labrig_reports::read(&manifest).with_context(|| format!("{}", manifest.display()))?;
        let funnel: Vec<String> = m.funnel.iter().map(|s| format!("{} {}", s.stage, s.kept)).collect();
        let kept = m.episodes.len();
        say(format!("[retrieve] {}: {kept} episodes ({})", c.name, funnel.join(" -> ")));
        if kept == 0 {
            say(format!("[retrieve] {}: nothing retrieved; the condition is not trained", c.name));
            return Ok(());
        }
        Some(manifest)
    };
    // Training: the same recipe and steps for every condition; resumed from its last checkpoint.
    let run_dir = dir.join("run");
    let done = labrig_reports::read::<RunReport>(&run_dir.join("run.json")).is_some_and(|r| r.steps == cfg.steps);
    let stage = format!("[train] {}", c.name);
    if done {
        say(format!("{stage}: trained earlier ({} steps)", cfg.steps));
    } else {
        let t = Instant::now();
        let mut a = strings(&["train", "--target", &path_str(&layout.target_episodes(cfg))]);
        if let Some(co) = &cotrain {
            a.extend(["--cotrain".to_owned(), path_str(co)]);
        }
        a.extend(strings(&[
            "--w",
            &w.to_string(),
            "--preset",
            &resolve_preset(&cfg.preset, config_dir),
            "--steps",
            &cfg.steps.to_string(),
            "--out",
            &path_str(&run_dir),
            "--resume",
            "--cache",
            &path_str(&layout.out.join("frame_cache")),
            "--json",
        ]));
        if let Some(b) = cfg.batch_size {
            a.extend(["--batch-size".to_owned(), b.to_string()]);
        }
        if let Some(s) = cfg.train_seed {
            a.extend(["--seed".to_owned(), s.to_string()]);
        }
        if let Some(v) = cfg.val_every {
            a.extend(["--val-every".to_owned(), v.to_string()]);
        }
        if let Some(n) = args.threads {
            a.extend(["--threads".to_owned(), n.to_string()]);
        }
        let resumed = run_dir.join("checkpoints/last").exists();
        let result = run_stage(&stage, &a, &[], &layout.log(&format!("{}_train", c.name)), quiet);
        let wall = add_wall(&dir.join("train_time.json"), t.elapsed().as_secs_f64())?;
        result?;
        let r: RunReport = labrig_reports::read(&run_dir.join("run.json")).context("the training wrote no run.json")?;
        say(format!(
            "{stage}: {} steps{} in {} (target {} + co-training {} episodes, {:.0} samples/s, validation loss {:.4})",
            cfg.steps,
            if resumed { " (resumed)" } else { "" },
            minutes(wall),
            r.target_episodes,
            r.cotrain_episodes,
            r.samples_per_s,
            r.last_val_loss.unwrap_or(f64::NAN),
        ));
    }
    // Rollouts on the target's seeds, set by set; a set cut off runs again.
    for first in cfg.seed_sets() {
        roll_out(run, c, first)?;
    }
    Ok(())
}

/// One set of rollouts of a condition's policy, from `first` seed.
fn roll_out(run: &Run, c: &ConditionSpec, first: u64) -> anyhow::Result<()> {
    let &Run { cfg, config_dir, layout, args } = run;
    let say = |line: String| run.say(line);
    let dir = layout.condition(&c.name);
    let rollouts = dir.join(cfg.rollouts_dir(first));
    let stage = format!("[rollout] {} seeds {first}..{}", c.name, first + cfg.rollouts - 1);
    let report_path = rollouts.join("rollouts.json");
    if let Some(r) = complete_rollouts(cfg, &report_path) {
        say(format!("{stage}: done earlier ({} of {})", r.successes, cfg.rollouts));
        return Ok(());
    }
    if rollouts.exists() {
        std::fs::remove_dir_all(&rollouts)?;
    }
    let t = Instant::now();
    let a = strings(&[
        "rollout",
        "--policy",
        &path_str(&dir.join("run")),
        "--scene",
        &resolve_scene(&cfg.target.scene, config_dir)?,
        "--episodes",
        &cfg.rollouts.to_string(),
        "--first-seed",
        &first.to_string(),
        "--max-steps",
        &cfg.max_steps.to_string(),
        "--out",
        &path_str(&rollouts),
        "--domain-id",
        &args.domain_id.to_string(),
        "--json",
    ]);
    let log = layout.log(&format!("{}_{}", c.name, cfg.rollouts_dir(first).replace("rollouts", "rollout")));
    let result = run_stage(&stage, &a, &[], &log, args.json);
    if result.is_err() {
        // An incomplete report must not count as done.
        let _ = std::fs::remove_file(&report_path);
    }
    result?;
    // The set's own wall time (a set cut off runs again from scratch: its time is the last run's).
    let wall = t.elapsed().as_secs_f64();
    write_json(&rollouts.join("wall.json"), &WallTime { wall_s: wall, sittings: 0 })?;
    let r = complete_rollouts(cfg, &report_path).context("the rollouts wrote no complete rollouts.json")?;
    let k = r.successes;
    let [lo, hi] = wilson95(k, cfg.rollouts);
    say(format!(
        "{stage}: {k} of {} ({:.0}%, 95% CI {:.0}-{:.0}%) in {}",
        cfg.rollouts,
        100.0 * k as f64 / cfg.rollouts as f64,
        100.0 * lo,
        100.0 * hi,
        minutes(wall)
    ));
    Ok(())
}

/// A set's report when it holds every rollout.
fn complete_rollouts(cfg: &ExperimentConfig, report: &Path) -> Option<RolloutReport> {
    labrig_launch::rollout::read_report(report).filter(|r| r.rollouts.len() == cfg.rollouts as usize)
}

/// One condition's row of the table.
#[derive(Debug, Clone, Serialize)]
pub struct ConditionResult {
    pub name: String,
    pub about: String,
    pub cotrain: String,
    pub w: f64,
    /// done (trained and judged), trained, retrieved (nothing else yet), not retrieved (empty), pending.
    pub status: String,
    /// The retrieval's funnel (stage, kept), when retrieved.
    pub funnel: Vec<(String, u64)>,
    /// Episodes in the co-training set given to training (before unsuccessful ones are dropped).
    pub cotrain_given: Option<u64>,
    /// What training used: target (training) episodes, held-out ones, co-training episodes.
    pub target_episodes: Option<u64>,
    pub val_episodes: Option<u64>,
    pub cotrain_episodes: Option<u64>,
    pub drawn_target: Option<u64>,
    pub drawn_cotrain: Option<u64>,
    pub steps: Option<u64>,
    pub train_wall_s: Option<f64>,
    pub samples_per_s: Option<f64>,
    pub last_val_loss: Option<f64>,
    pub open_loop_mm: Option<f64>,
    /// Over the seed sets judged so far.
    pub successes: Option<u64>,
    pub rollouts: Option<u64>,
    pub ci95: Option<[f64; 2]>,
    /// Each judged set: its first seed and its successes.
    pub by_seed_set: Vec<(u64, u64)>,
    pub rollout_wall_s: Option<f64>,
    pub inference_ms_p50: Option<f64>,
}

#[derive(Debug, Clone, Serialize)]
pub struct Results {
    pub experiment: String,
    pub out: PathBuf,
    pub target: DataSpec,
    pub target_successful: Option<u64>,
    pub prior: Vec<DataSpec>,
    pub prior_episodes: Option<u64>,
    pub preset: String,
    pub steps: u64,
    pub batch_size: Option<u64>,
    pub rollouts: u64,
    pub rollout_first_seed: u64,
    /// Every seed set's first seed (`rollouts` rollouts each).
    pub seed_sets: Vec<u64>,
    pub max_steps: u64,
    pub conditions: Vec<ConditionResult>,
}

/// Builds the table and the figure from whatever the run has (and writes them).
fn summarise(cfg: &ExperimentConfig, config_dir: &Path, layout: &Layout) -> anyhow::Result<Results> {
    let demo = |d: &DataSpec, target: bool| {
        labrig_reports::read::<DemoReport>(&layout.data(&d.name, target).join("demo.json"))
    };
    let prior_episodes: Option<u64> = cfg.prior.iter().map(|d| demo(d, false).map(|r| r.recorded as u64)).sum();
    let mut rows = Vec::new();
    for c in &cfg.condition {
        let dir = layout.condition(&c.name);
        let manifest = labrig_reports::read::<ManifestEpisodes>(&dir.join("manifest.json"));
        let run = labrig_reports::read::<RunReport>(&dir.join("run/run.json")).filter(|r| r.steps == cfg.steps);
        let sets: Vec<(u64, RolloutReport)> = cfg
            .seed_sets()
            .into_iter()
            .filter_map(|first| {
                Some((first, complete_rollouts(cfg, &dir.join(cfg.rollouts_dir(first)).join("rollouts.json"))?))
            })
            .collect();
        let by_seed_set: Vec<(u64, u64)> = sets.iter().map(|(first, r)| (*first, r.successes)).collect();
        let judged = by_seed_set.len() as u64 * cfg.rollouts;
        let succeeded: u64 = by_seed_set.iter().map(|(_, k)| k).sum();
        let all_sets = sets.len() == cfg.seed_sets().len();
        let rollouts = sets.first().map(|(_, r)| r.clone());
        let funnel: Vec<(String, u64)> =
            manifest.iter().flat_map(|m| &m.funnel).map(|s| (s.stage.clone(), s.kept as u64)).collect();
        let retrieved = manifest.as_ref().map(|m| m.episodes.len() as u64);
        let cotrain_given = if c.all {
            prior_episodes
        } else if c.align.is_empty() {
            Some(0)
        } else {
            retrieved
        };
        let status = match (&run, &rollouts, retrieved) {
            (Some(_), Some(_), _) if all_sets => "done",
            (Some(_), Some(_), _) => "partly judged",
            (Some(_), None, _) => "trained",
            (None, _, Some(0)) => "retrieved nothing",
            (None, _, Some(_)) => "retrieved",
            _ => "pending",
        };
        rows.push(ConditionResult {
            name: c.name.clone(),
            about: c.about.clone(),
            cotrain: c.cotrain(),
            w: c.w.unwrap_or(cfg.w),
            status: status.to_owned(),
            funnel,
            cotrain_given,
            target_episodes: run.as_ref().map(|r| r.target_episodes as u64),
            val_episodes: run.as_ref().map(|r| r.val_episodes as u64),
            cotrain_episodes: run.as_ref().map(|r| r.cotrain_episodes as u64),
            drawn_target: run.as_ref().map(|r| r.drawn_target),
            drawn_cotrain: run.as_ref().map(|r| r.drawn_cotrain),
            steps: run.as_ref().map(|r| r.steps),
            train_wall_s: run
                .as_ref()
                .and_then(|_| labrig_reports::read::<WallTime>(&dir.join("train_time.json")))
                .map(|t| t.wall_s),
            samples_per_s: run.as_ref().map(|r| r.samples_per_s),
            last_val_loss: run.as_ref().and_then(|r| r.last_val_loss),
            open_loop_mm: run.as_ref().and_then(|r| r.last_open_loop_mm),
            successes: rollouts.as_ref().map(|_| succeeded),
            rollouts: rollouts.as_ref().map(|_| judged),
            ci95: rollouts.as_ref().map(|_| wilson95(succeeded, judged)),
            by_seed_set,
            rollout_wall_s: rollouts.as_ref().map(|_| {
                sets.iter()
                    .filter_map(|(first, _)| {
                        let set = dir.join(cfg.rollouts_dir(*first));
                        // (Runs before the per-set file kept the main set's in the condition's folder.)
                        labrig_reports::read::<WallTime>(&set.join("wall.json"))
                            .or_else(|| {
                                labrig_reports::read::<WallTime>(&dir.join("rollout_time.json"))
                                    .filter(|_| *first == cfg.rollout_first_seed)
                            })
                            .map(|t| t.wall_s)
                    })
                    .sum()
            }),
            inference_ms_p50: rollouts.as_ref().map(|r| r.inference_ms_p50).filter(|v| v.is_finite()),
        });
    }
    let results = Results {
        experiment: cfg.name.clone(),
        out: layout.out.clone(),
        target: cfg.target.clone(),
        target_successful: demo(&cfg.target, true).map(|r| r.successes as u64),
        prior: cfg.prior.clone(),
        prior_episodes,
        preset: resolve_preset(&cfg.preset, config_dir),
        steps: cfg.steps,
        batch_size: cfg.batch_size,
        rollouts: cfg.rollouts,
        rollout_first_seed: cfg.rollout_first_seed,
        seed_sets: cfg.seed_sets(),
        max_steps: cfg.max_steps,
        conditions: rows,
    };
    write_json(&layout.out.join("results.json"), &results)?;
    std::fs::write(layout.out.join("results.md"), table_markdown(&results))?;
    plot(&results, &layout.out.join("results.png"))?;
    Ok(results)
}

fn opt<T: std::fmt::Display>(v: Option<T>) -> String {
    v.map_or("-".to_owned(), |v| v.to_string())
}

/// The success over the judged sets, each set's count when there are several, and the status
/// when not every set is judged.
fn success_text(r: &ConditionResult) -> String {
    match (r.successes, r.rollouts, r.ci95) {
        (Some(k), Some(n), Some([lo, hi])) => {
            let mut t = format!("{k}/{n} ({:.0}%, {:.0}-{:.0}%)", 100.0 * k as f64 / n as f64, 100.0 * lo, 100.0 * hi);
            if r.by_seed_set.len() > 1 {
                let sets: Vec<String> = r.by_seed_set.iter().map(|(_, k)| k.to_string()).collect();
                t += &format!(" [{}]", sets.join(" + "));
            }
            if r.status != "done" {
                t += &format!(" ({})", r.status);
            }
            t
        }
        _ => r.status.clone(),
    }
}

/// The seed sets as text: `1000..1019, 2000..2019`.
fn seeds_text(r: &Results) -> String {
    r.seed_sets.iter().map(|f| format!("{f}..{}", f + r.rollouts - 1)).collect::<Vec<_>>().join(", ")
}

fn table_text(r: &Results) -> String {
    let mut s =
        format!("{}: success on the target's rollouts (seeds {}), 95% Wilson intervals\n", r.experiment, seeds_text(r));
    s += &format!(
        "  {:<16} {:<40} {:>9} {:>7} {:>10} {:>9}  {}\n",
        "condition", "co-training", "episodes", "steps", "train", "val loss", "success"
    );
    for c in &r.conditions {
        s += &format!(
            "  {:<16} {:<40} {:>9} {:>7} {:>10} {:>9}  {}\n",
            c.name,
            c.cotrain,
            opt(c.cotrain_episodes.or(c.cotrain_given)),
            opt(c.steps),
            c.train_wall_s.map_or("-".to_owned(), minutes),
            c.last_val_loss.map_or("-".to_owned(), |v| format!("{v:.4}")),
            success_text(c)
        );
    }
    s
}

fn table_markdown(r: &Results) -> String {
    let mut s = format!(
        "# {}: co-training on retrieved data (labrig experiment retrieval)\n\n\
         Target: `{}`, {} demos (seeds {}..{}; {} successful). Prior: {} episodes ({}). \
         Training: preset `{}`, {} steps{} for every condition. Judged by {} rollouts per seed set of at most {} steps \
         on the target scene's seeds {} (lockstep). Success with its 95% Wilson interval (over every set; \
         each set's count in brackets).\n\n",
        r.experiment,
        r.target.scene,
        r.target.episodes,
        r.target.first_seed,
        r.target.first_seed + r.target.episodes - 1,
        opt(r.target_successful),
        opt(r.prior_episodes),
        r.prior
            .iter()
            .map(|d| format!("{} x{} seeds {}..", d.scene, d.episodes, d.first_seed))
            .collect::<Vec<_>>()
            .join(", "),
        r.preset,
        r.steps,
        r.batch_size.map_or(String::new(), |b| format!(" at batch {b}")),
        r.rollouts,
        r.max_steps,
        seeds_text(r),
    );
    s += "| condition | co-training set | retrieval funnel | co-training episodes (used) | w | samples drawn target / co-training | steps | train wall | samples/s | val loss | open loop (mm) | success | rollouts wall |\n";
    s += "|---|---|---|---|---|---|---|---|---|---|---|---|---|\n";
    for c in &r.conditions {
        let funnel = if c.funnel.is_empty() {
            "-".to_owned()
        } else {
            c.funnel.iter().map(|(k, n)| format!("{k} {n}")).collect::<Vec<_>>().join(" → ")
        };
        s += &format!(
            "| {} | {} | {} | {} ({}) | {} | {} / {} | {} | {} | {} | {} | {} | {} | {} |\n",
            c.name,
            c.cotrain,
            funnel,
            opt(c.cotrain_given),
            opt(c.cotrain_episodes),
            c.w,
            opt(c.drawn_target),
            opt(c.drawn_cotrain),
            opt(c.steps),
            c.train_wall_s.map_or("-".to_owned(), minutes),
            c.samples_per_s.map_or("-".to_owned(), |v| format!("{v:.0}")),
            c.last_val_loss.map_or("-".to_owned(), |v| format!("{v:.4}")),
            c.open_loop_mm.map_or("-".to_owned(), |v| format!("{v:.1}")),
            success_text(c),
            c.rollout_wall_s.map_or("-".to_owned(), minutes),
        );
    }
    s
}

/// The paper's figure: a bar per condition (success rate) with its 95% interval; conditions
/// not yet judged are named with their status.
fn plot(r: &Results, path: &Path) -> anyhow::Result<()> {
    use plotters::prelude::*;
    let font = labrig_episode::font::dejavu_sans().map_err(anyhow::Error::msg)?;
    let _ = plotters::style::register_font("sans-serif", FontStyle::Normal, font);
    let n = r.conditions.len().max(1);
    let root = BitMapBackend::new(path, (160 * n as u32 + 200, 560)).into_drawing_area();
    let e = |e: DrawingAreaErrorKind<_>| anyhow::anyhow!("{e:?}");
    root.fill(&WHITE).map_err(e)?;
    let title = format!("{}: success on the target task (seeds {}; 95% Wilson intervals)", r.experiment, seeds_text(r));
    let mut chart = ChartBuilder::on(&root)
        .caption(title, ("sans-serif", 20))
        .margin(14)
        .x_label_area_size(70)
        .y_label_area_size(60)
        .build_cartesian_2d(-0.5..(n as f64 - 0.5), 0.0..105.0)
        .map_err(e)?;
    chart
        .configure_mesh()
        .disable_x_mesh()
        .y_desc("success (%)")
        .y_label_formatter(&|y| format!("{y:.0}"))
        .x_labels(n)
        .x_label_formatter(&|x| {
            let k = x.round();
            if (x - k).abs() > 1e-6 {
                return String::new();
            }
            r.conditions.get(k as usize).map_or(String::new(), |c| c.name.clone())
        })
        .draw()
        .map_err(e)?;
    let colour = |c: &ConditionResult| {
        if c.cotrain == "every prior demo" {
            RGBColor(150, 150, 150)
        } else if c.cotrain == "none" {
            RGBColor(90, 120, 170)
        } else {
            RGBColor(60, 160, 90)
        }
    };
    for (k, c) in r.conditions.iter().enumerate() {
        let x = k as f64;
        match (c.successes, c.rollouts, c.ci95) {
            (Some(s), Some(t), Some([lo, hi])) => {
                let p = 100.0 * s as f64 / t as f64;
                chart
                    .draw_series(std::iter::once(Rectangle::new([(x - 0.32, 0.0), (x + 0.32, p)], colour(c).filled())))
                    .map_err(e)?;
                let (lo, hi) = (100.0 * lo, 100.0 * hi);
                chart
                    .draw_series([
                        PathElement::new(vec![(x, lo), (x, hi)], BLACK.stroke_width(2)),
                        PathElement::new(vec![(x - 0.08, lo), (x + 0.08, lo)], BLACK.stroke_width(2)),
                        PathElement::new(vec![(x - 0.08, hi), (x + 0.08, hi)], BLACK.stroke_width(2)),
                    ])
                    .map_err(e)?;
                chart
                    .draw_series(std::iter::once(Text::new(
                        format!("{s}/{t}"),
                        (x - 0.12, (hi + 3.0).min(101.0)),
                        ("sans-serif", 16),
                    )))
                    .map_err(e)?;
            }
            _ => {
                chart
                    .draw_series(std::iter::once(Text::new(c.status.clone(), (x - 0.3, 5.0), ("sans-serif", 15))))
                    .map_err(e)?;
            }
        }
        let used = c.cotrain_episodes.or(c.cotrain_given).map_or(String::new(), |n| format!("+{n} eps"));
        chart
            .draw_series(std::iter::once(Text::new(
                used,
                (x - 0.25, 98.0),
                ("sans-serif", 13).into_font().color(&BLACK.mix(0.6)),
            )))
            .map_err(e)?;
    }
    root.present().map_err(e)?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(text: &str) -> anyhow::Result<ExperimentConfig> {
        let cfg: ExperimentConfig = labrig_runtime::config::parse_config(text, Path::new("test.toml"))?;
        cfg.validate()?;
        Ok(cfg)
    }

    /// A config: `top` among the top-level keys, `conditions` after the tables.
    fn config(top: &str, conditions: &str) -> String {
        format!(
            "name = \"t\"\npreset = \"small\"\nsteps = 10\nrollouts = 20\n{top}\
             [target]\nname = \"target\"\nscene = \"pick_place\"\nepisodes = 2\nfirst_seed = 0\n\
             [[prior]]\nname = \"p\"\nscene = \"pick_place\"\nepisodes = 2\nfirst_seed = 100\n{conditions}"
        )
    }

    #[test]
    fn the_committed_configs_parse_and_bad_ones_are_named() {
        for f in ["full.toml", "ci.toml"] {
            let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../experiments/retrieval").join(f);
            let cfg = ExperimentConfig::load(&path).unwrap();
            assert!(cfg.condition.len() >= 6, "{f}");
            let dir = path.parent().unwrap();
            for d in std::iter::once(&cfg.target).chain(&cfg.prior) {
                resolve_scene(&d.scene, dir).unwrap();
            }
        }
        let a = "[[condition]]\nname = \"a\"\n";
        let ok = parse(&config("more_rollout_seeds = [2000]\n", &format!("{a}all = true\n"))).unwrap();
        assert_eq!(ok.seed_sets(), [1000, 2000]);
        assert_eq!((ok.rollouts_dir(1000), ok.rollouts_dir(2000)), ("rollouts".to_owned(), "rollouts_2000".to_owned()));
        let err = |top: &str, conditions: &str| format!("{:#}", parse(&config(top, conditions)).unwrap_err());
        assert!(err("more_rollout_seeds = [1010]\n", a).contains("overlap"));
        assert!(err("", &format!("{a}all = true\nalign = [\"camPose\"]\n")).contains("exclude each other"));
        assert!(err("", &format!("{a}align = [\"campose\"]\n")).contains("unknown alignment `campose`"));
        assert!(err("", &format!("{a}{a}")).contains("two conditions are named `a`"));
        assert!(err("", "[[condition]]\nname = \"../a\"\n").contains("condition name `../a`"));
        assert!(err("w = 1.5\n", a).contains("w must be in 0..=1"));
        assert!(err("", "").contains("condition"));
        assert!(
            format!("{:#}", resolve_scene("nope.toml", Path::new("/")).unwrap_err()).contains("not a built-in scene")
        );
    }
}
