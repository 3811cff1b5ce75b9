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

mod stats;

#[derive(Debug, Subcommand)]
pub enum ExperimentCommand {
    /// The paper's result in the sim: co-training on retrieved demos (camPose, objSpat, ...)
    /// against the target demos alone and against every prior demo; resumable, with a table and
    /// a figure (experiments/retrieval/README.md).
    Retrieval(RetrievalArgs),
    /// How many training seeds and rollouts a difference between two conditions needs: the
    /// power of the comparison's permutation test over seeds, simulated, with the spread
    /// between training runs estimated from a finished run's results.json.
    Power(PowerArgs),
}

#[derive(Debug, Args)]
pub struct PowerArgs {
    /// A run's results.json: the conditions' success (their spread gives the spread between
    /// training runs, an upper bound) and the time a policy took to train and judge.
    #[arg(long, default_value = "experiments/retrieval/results/results.json")]
    pub from: PathBuf,
    /// The spread between training seeds (a standard deviation of success rates) instead of the
    /// estimate.
    #[arg(long)]
    pub sd: Option<f64>,
    /// The weaker condition's success rate (default: the run's mean).
    #[arg(long)]
    pub base: Option<f64>,
    /// True differences to find (success rate, 0..1).
    #[arg(long, value_delimiter = ',', default_values_t = [0.15, 0.2])]
    pub diff: Vec<f64>,
    /// Training seeds (policies) per condition.
    #[arg(long, value_delimiter = ',', default_values_t = [3, 5, 8])]
    pub seeds: Vec<usize>,
    /// Rollouts per policy.
    #[arg(long, value_delimiter = ',', default_values_t = [20, 40])]
    pub rollouts: Vec<u64>,
    /// The test's level (two-sided).
    #[arg(long, default_value_t = 0.05)]
    pub alpha: f64,
    /// Simulated experiments per point.
    #[arg(long, default_value_t = 1000)]
    pub sims: usize,
    #[arg(long)]
    pub json: bool,
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
    /// The training seed (default: the preset's), when `train_seeds` is empty.
    #[serde(default)]
    pub train_seed: Option<u64>,
    /// Training seeds: each condition is trained once per seed (its `seeds` first ones), every
    /// policy judged on the same rollout seeds, into `<condition>/seed_<s>/`. Empty: one
    /// training per condition (at `train_seed`), in the condition's own folder.
    #[serde(default)]
    pub train_seeds: Vec<u64>,
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
    /// Paired comparisons `[a, b]` (does a beat b?) the summary tests over training seeds
    /// ([`stats`]).
    #[serde(default)]
    pub compare: Vec<[String; 2]>,
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
    /// Train only the first this many of `train_seeds` (default: every one). May be raised
    /// later: the policies done are kept.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub seeds: Option<usize>,
    /// This condition's training preset (default: the experiment's), e.g. an ablation's.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub preset: Option<String>,
}

impl ConditionSpec {
    /// How many policies the condition trains: one per training seed it takes.
    fn seed_count(&self, cfg: &ExperimentConfig) -> usize {
        if cfg.train_seeds.is_empty() { 1 } else { self.seeds.unwrap_or(cfg.train_seeds.len()) }
    }

    /// What a condition's folder must keep to be continued: everything but `seeds` (raising
    /// it later trains more policies and keeps the done ones).
    fn identity(&self) -> anyhow::Result<Value> {
        Ok(serde_json::to_value(ConditionSpec { seeds: None, ..self.clone() })?)
    }

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
            if let Some(n) = c.seeds {
                ensure!(
                    !self.train_seeds.is_empty() && (1..=self.train_seeds.len()).contains(&n),
                    "condition `{}`: seeds = {n} must be in 1..={} (the train_seeds given)",
                    c.name,
                    self.train_seeds.len()
                );
            }
            ensure!(
                !self.prior.is_empty() || (!c.all && c.align.is_empty()),
                "condition `{}` co-trains on prior data, but the config has no [[prior]]",
                c.name
            );
        }
        let mut seeds = BTreeSet::new();
        for s in &self.train_seeds {
            ensure!(seeds.insert(s), "train_seeds names seed {s} twice");
        }
        ensure!(
            self.train_seeds.is_empty() || self.train_seed.is_none(),
            "train_seed and train_seeds exclude each other"
        );
        for [a, b] in &self.compare {
            for n in [a, b] {
                ensure!(conditions.contains(n.as_str()), "compare: no condition `{n}`");
            }
            ensure!(a != b, "compare: `{a}` against itself");
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
    /// A condition's `index`th policy (its training seed's).
    fn unit(&self, cfg: &ExperimentConfig, c: &ConditionSpec, index: usize) -> Unit {
        let dir = self.condition(&c.name);
        match cfg.train_seeds.get(index) {
            Some(&s) => Unit {
                seed: Some(s),
                dir: dir.join(format!("seed_{s}")),
                name: format!("{} seed {s}", c.name),
                log: format!("{}_seed{s}", c.name),
            },
            None => Unit { seed: cfg.train_seed, dir, name: c.name.clone(), log: c.name.clone() },
        }
    }
    /// Every policy of a condition.
    fn units(&self, cfg: &ExperimentConfig, c: &ConditionSpec) -> Vec<Unit> {
        (0..c.seed_count(cfg)).map(|i| self.unit(cfg, c, i)).collect()
    }
}

/// One policy of a condition: its training seed, its folder (`run/`, the rollout sets), its
/// name in stage lines and its logs' stem.
struct Unit {
    seed: Option<u64>,
    dir: PathBuf,
    name: String,
    log: String,
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
    let identity = json!({
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
    });
    // (Not `train_seeds`: a policy's folder is named by its seed, so seeds may be added to a
    // run later and the policies done are kept.)
    Ok(identity)
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
        ExperimentCommand::Power(a) => power(&a),
    }
}

/// What `labrig experiment power` reads of a run's results.json.
#[derive(Debug, Deserialize)]
struct JudgedRun {
    conditions: Vec<JudgedCondition>,
}

#[derive(Debug, Deserialize)]
struct JudgedCondition {
    successes: Option<u64>,
    rollouts: Option<u64>,
    train_wall_s: Option<f64>,
    rollout_wall_s: Option<f64>,
    #[serde(default)]
    policies: Vec<serde::de::IgnoredAny>,
}

/// One point of the power table.
#[derive(Debug, Serialize)]
struct PowerPoint {
    diff: f64,
    seeds: usize,
    rollouts: u64,
    power: f64,
    /// Machine time for the two conditions' policies at the run's pace (minutes).
    minutes: Option<f64>,
}

fn power(a: &PowerArgs) -> anyhow::Result<ExitCode> {
    ensure!((0.0..1.0).contains(&a.alpha) && a.alpha > 0.0, "--alpha must be in (0, 1)");
    ensure!(a.sims >= 10, "--sims must be at least 10");
    ensure!(
        a.seeds.iter().all(|&k| k >= 1) && a.rollouts.iter().all(|&n| n >= 1),
        "--seeds and --rollouts must be >= 1"
    );
    let text = std::fs::read_to_string(&a.from).with_context(|| format!("--from {}", a.from.display()))?;
    let run: JudgedRun = serde_json::from_str(&text)
        .with_context(|| format!("--from {}: not a results.json of `labrig experiment retrieval`", a.from.display()))?;
    let counts: Vec<(u64, u64)> = run.conditions.iter().filter_map(|c| Some((c.successes?, c.rollouts?))).collect();
    let estimate = stats::between_sd(&counts);
    let (run_mean, sd_est) = estimate.unzip();
    let sd = a.sd.or(sd_est).with_context(|| {
        format!("{}: fewer than two judged conditions to estimate the spread from; give --sd", a.from.display())
    })?;
    let base = a.base.or(run_mean).context("give --base")?;
    // The run's pace: a policy's training, and one rollout (per policy: a condition judged
    // once holds one policy).
    let policies = |c: &JudgedCondition| c.policies.len().max(1) as f64;
    let judged: Vec<&JudgedCondition> = run.conditions.iter().filter(|c| c.rollouts.is_some()).collect();
    let train_s = mean(&judged.iter().filter_map(|c| Some(c.train_wall_s? / policies(c))).collect::<Vec<_>>());
    let rollout_s =
        mean(&judged.iter().filter_map(|c| Some(c.rollout_wall_s? / c.rollouts? as f64)).collect::<Vec<_>>());
    let mut points = Vec::new();
    let bar = progress::bar("power", (a.diff.len() * a.seeds.len() * a.rollouts.len()) as u64, a.json);
    for &diff in &a.diff {
        for &seeds in &a.seeds {
            for &rollouts in &a.rollouts {
                let p = stats::power(base, diff, sd, seeds, rollouts, a.alpha, a.sims);
                let minutes =
                    train_s.zip(rollout_s).map(|(t, r)| 2.0 * seeds as f64 * (t + r * rollouts as f64) / 60.0);
                points.push(PowerPoint { diff, seeds, rollouts, power: p, minutes });
                bar.inc(1);
            }
        }
    }
    bar.finish_and_clear();
    if a.json {
        println!(
            "{}",
            json!({"from": a.from, "base": base, "sd": sd, "sd_estimated": sd_est, "alpha": a.alpha, "sims": a.sims, "points": points})
        );
        return Ok(ExitCode::SUCCESS);
    }
    println!(
        "power of the permutation test over training seeds (two-sided, level {}), {} simulated experiments per point",
        a.alpha, a.sims
    );
    println!(
        "  weaker condition {:.0}%, spread between training runs sd {:.3}{}",
        100.0 * base,
        sd,
        match (a.sd, sd_est) {
            (Some(_), _) => " (given)".to_owned(),
            (None, Some(_)) => format!(" (estimated from {}: an upper bound)", a.from.display()),
            _ => String::new(),
        }
    );
    println!("  {:>6} {:>6} {:>9} {:>6}  machine time (2 conditions)", "diff", "seeds", "rollouts", "power");
    for p in &points {
        println!(
            "  {:>5.0}% {:>6} {:>9} {:>5.0}%  {}",
            100.0 * p.diff,
            p.seeds,
            p.rollouts,
            100.0 * p.power,
            p.minutes.map_or("-".to_owned(), |m| format!("{:.0} min", m))
        );
    }
    Ok(ExitCode::SUCCESS)
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
        // Seed by seed across the conditions, so that a run cut off holds comparable policies.
        let rounds = chosen.iter().map(|c| c.seed_count(&cfg)).max().unwrap_or(0);
        let mut prepared: std::collections::BTreeMap<&str, Option<Option<PathBuf>>> = Default::default();
        for index in 0..rounds {
            for &c in &chosen {
                if index >= c.seed_count(&cfg) {
                    continue;
                }
                let cotrain = match prepared.get(c.name.as_str()) {
                    Some(p) => p.clone(),
                    None => {
                        let p = prepare_condition(&run, c)?;
                        prepared.insert(&c.name, p.clone());
                        p
                    }
                };
                // (None: the retrieval kept nothing; the condition is not trained.)
                let Some(cotrain) = cotrain else { continue };
                let unit = layout.unit(&cfg, c, index);
                train(&run, c, &unit, cotrain.as_deref())?;
                // Rollouts on the target's seeds, set by set; a set cut off runs again.
                for first in cfg.seed_sets() {
                    roll_out(&run, &unit, first)?;
                }
                // The table after every policy: a run cut off later keeps what it has.
                let _ = summarise(&cfg, &config_dir, &layout)?;
            }
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

/// A condition's folder and its co-training set: none, every prior demo, or its retrieval's
/// manifest (retrieved unless done). `None` when the retrieval kept nothing.
fn prepare_condition(run: &Run, c: &ConditionSpec) -> anyhow::Result<Option<Option<PathBuf>>> {
    let &Run { cfg, layout, args, .. } = run;
    let say = |line: String| run.say(line);
    let quiet = args.json;
    let dir = layout.condition(&c.name);
    std::fs::create_dir_all(&dir)?;
    check_identity(&dir.join("condition.json"), &c.identity()?)?;
    Ok(Some(if c.all {
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
            return Ok(None);
        }
        Some(manifest)
    }))
}

/// A policy's training: the same recipe and steps for every condition (its seed's), resumed
/// from its last checkpoint; skipped when done.
fn train(run: &Run, c: &ConditionSpec, unit: &Unit, cotrain: Option<&Path>) -> anyhow::Result<()> {
    let &Run { cfg, config_dir, layout, args } = run;
    let say = |line: String| run.say(line);
    let quiet = args.json;
    let w = c.w.unwrap_or(cfg.w);
    let run_dir = unit.dir.join("run");
    let done = labrig_reports::read::<RunReport>(&run_dir.join("run.json")).is_some_and(|r| r.steps == cfg.steps);
    let stage = format!("[train] {}", unit.name);
    if done {
        say(format!("{stage}: trained earlier ({} steps)", cfg.steps));
    } else {
        let t = Instant::now();
        let mut a = strings(&["train", "--target", &path_str(&layout.target_episodes(cfg))]);
        if let Some(co) = cotrain {
            a.extend(["--cotrain".to_owned(), path_str(co)]);
        }
        a.extend(strings(&[
            "--w",
            &w.to_string(),
            "--preset",
            &resolve_preset(c.preset.as_deref().unwrap_or(&cfg.preset), config_dir),
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
        if let Some(s) = unit.seed {
            a.extend(["--seed".to_owned(), s.to_string()]);
        }
        if let Some(v) = cfg.val_every {
            a.extend(["--val-every".to_owned(), v.to_string()]);
        }
        if let Some(n) = args.threads {
            a.extend(["--threads".to_owned(), n.to_string()]);
        }
        let resumed = run_dir.join("checkpoints/last").exists();
        let result = run_stage(&stage, &a, &[], &layout.log(&format!("{}_train", unit.log)), quiet);
        let wall = add_wall(&unit.dir.join("train_time.json"), t.elapsed().as_secs_f64())?;
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
    Ok(())
}

/// One set of rollouts of a condition's policy, from `first` seed.
fn roll_out(run: &Run, unit: &Unit, first: u64) -> anyhow::Result<()> {
    let &Run { cfg, config_dir, layout, args } = run;
    let say = |line: String| run.say(line);
    let dir = &unit.dir;
    let rollouts = dir.join(cfg.rollouts_dir(first));
    let stage = format!("[rollout] {} seeds {first}..{}", unit.name, first + cfg.rollouts - 1);
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
    let log = layout.log(&format!("{}_{}", unit.log, cfg.rollouts_dir(first).replace("rollouts", "rollout")));
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

/// One policy of a condition (one training seed): its training and its judged sets.
#[derive(Debug, Clone, Serialize)]
pub struct PolicyResult {
    /// The training seed (absent: the preset's, in a run without `train_seeds`).
    pub seed: Option<u64>,
    /// done (trained and judged on every set), partly judged, trained, pending.
    pub status: String,
    pub run: Option<RunReport>,
    pub train_wall_s: Option<f64>,
    /// Each judged set: its first seed and its successes.
    pub by_seed_set: Vec<(u64, u64)>,
    pub successes: u64,
    pub rollouts: u64,
    pub rollout_wall_s: f64,
    pub inference_ms_p50: Option<f64>,
}

impl PolicyResult {
    fn read(cfg: &ExperimentConfig, unit: &Unit) -> PolicyResult {
        let dir = &unit.dir;
        let run = labrig_reports::read::<RunReport>(&dir.join("run/run.json")).filter(|r| r.steps == cfg.steps);
        let sets: Vec<(u64, RolloutReport)> = cfg
            .seed_sets()
            .into_iter()
            .filter_map(|first| {
                Some((first, complete_rollouts(cfg, &dir.join(cfg.rollouts_dir(first)).join("rollouts.json"))?))
            })
            .collect();
        let by_seed_set: Vec<(u64, u64)> = sets.iter().map(|(first, r)| (*first, r.successes)).collect();
        let status = match (&run, sets.len()) {
            (Some(_), n) if n == cfg.seed_sets().len() => "done",
            (Some(_), n) if n > 0 => "partly judged",
            (Some(_), _) => "trained",
            _ => "pending",
        };
        let rollout_wall_s = sets
            .iter()
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
            .sum();
        PolicyResult {
            seed: unit.seed,
            status: status.to_owned(),
            train_wall_s: run
                .as_ref()
                .and_then(|_| labrig_reports::read::<WallTime>(&dir.join("train_time.json")))
                .map(|t| t.wall_s),
            run,
            successes: by_seed_set.iter().map(|(_, k)| k).sum(),
            rollouts: by_seed_set.len() as u64 * cfg.rollouts,
            by_seed_set,
            rollout_wall_s,
            inference_ms_p50: sets.first().map(|(_, r)| r.inference_ms_p50).filter(|v| v.is_finite()),
        }
    }

    fn judged(&self) -> bool {
        self.rollouts > 0
    }

    /// The success rate over every judged set.
    pub fn rate(&self) -> Option<f64> {
        self.judged().then(|| self.successes as f64 / self.rollouts as f64)
    }
}

/// One condition's row of the table: its policies, pooled.
#[derive(Debug, Clone, Serialize)]
pub struct ConditionResult {
    pub name: String,
    pub about: String,
    pub cotrain: String,
    pub w: f64,
    pub preset: String,
    /// done (every policy trained and judged), partly judged, trained, retrieved (nothing else
    /// yet), retrieved nothing, pending.
    pub status: String,
    /// The retrieval's funnel (stage, kept), when retrieved.
    pub funnel: Vec<(String, u64)>,
    /// Episodes in the co-training set given to training (before unsuccessful ones are dropped).
    pub cotrain_given: Option<u64>,
    /// What training used (the first trained policy's): target (training) episodes, held-out
    /// ones, co-training episodes, and the samples drawn from each.
    pub target_episodes: Option<u64>,
    pub val_episodes: Option<u64>,
    pub cotrain_episodes: Option<u64>,
    pub drawn_target: Option<u64>,
    pub drawn_cotrain: Option<u64>,
    pub steps: Option<u64>,
    /// Over the trained policies: wall time summed; throughput, validation loss and open-loop
    /// error averaged.
    pub train_wall_s: Option<f64>,
    pub samples_per_s: Option<f64>,
    pub last_val_loss: Option<f64>,
    pub open_loop_mm: Option<f64>,
    /// Over every judged set of every policy.
    pub successes: Option<u64>,
    pub rollouts: Option<u64>,
    /// Wilson's interval of the pooled count (it treats the rollouts as independent, which
    /// policies of different seeds are not: see `comparisons` for the test over seeds).
    pub ci95: Option<[f64; 2]>,
    /// Each seed set: its first seed and its successes over the policies judged on it.
    pub by_seed_set: Vec<(u64, u64)>,
    /// Policies trained (of `policies`) and judged on every set.
    pub policies_done: usize,
    /// The judged policies' success rates: mean and standard deviation over training seeds.
    pub seed_mean: Option<f64>,
    pub seed_sd: Option<f64>,
    pub rollout_wall_s: Option<f64>,
    pub inference_ms_p50: Option<f64>,
    pub policies: Vec<PolicyResult>,
}

#[derive(Debug, Clone, Serialize)]
pub struct Results {
    pub experiment: String,
    pub out: PathBuf,
    pub target: DataSpec,
    pub target_successful: Option<u64>,
    pub prior: Vec<DataSpec>,
    /// Each prior set's recorded and successful episodes.
    pub prior_recorded: Vec<(String, Option<u64>, Option<u64>)>,
    pub prior_episodes: Option<u64>,
    pub preset: String,
    pub steps: u64,
    pub batch_size: Option<u64>,
    pub train_seeds: Vec<u64>,
    pub rollouts: u64,
    pub rollout_first_seed: u64,
    /// Every seed set's first seed (`rollouts` rollouts each).
    pub seed_sets: Vec<u64>,
    pub max_steps: u64,
    pub conditions: Vec<ConditionResult>,
    pub comparisons: Vec<stats::Comparison>,
}

fn mean(v: &[f64]) -> Option<f64> {
    (!v.is_empty()).then(|| v.iter().sum::<f64>() / v.len() as f64)
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
        let policies: Vec<PolicyResult> = layout.units(cfg, c).iter().map(|u| PolicyResult::read(cfg, u)).collect();
        let trained: Vec<&RunReport> = policies.iter().filter_map(|p| p.run.as_ref()).collect();
        let first = trained.first();
        let judged: Vec<&PolicyResult> = policies.iter().filter(|p| p.judged()).collect();
        let done: Vec<f64> = policies.iter().filter(|p| p.status == "done").filter_map(|p| p.rate()).collect();
        let by_seed_set: Vec<(u64, u64)> = cfg
            .seed_sets()
            .into_iter()
            .filter_map(|first| {
                let ks: Vec<u64> = judged
                    .iter()
                    .filter_map(|p| p.by_seed_set.iter().find(|(f, _)| *f == first).map(|(_, k)| *k))
                    .collect();
                (!ks.is_empty()).then(|| (first, ks.iter().sum()))
            })
            .collect();
        let (succeeded, n): (u64, u64) =
            (judged.iter().map(|p| p.successes).sum(), judged.iter().map(|p| p.rollouts).sum());
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
        let status = if !policies.is_empty() && policies.iter().all(|p| p.status == "done") {
            "done"
        } else if !judged.is_empty() {
            "partly judged"
        } else if !trained.is_empty() {
            "trained"
        } else {
            match retrieved {
                Some(0) => "retrieved nothing",
                Some(_) => "retrieved",
                None => "pending",
            }
        };
        let seed_mean = mean(&done);
        let seed_sd = seed_mean
            .filter(|_| done.len() > 1)
            .map(|m| (done.iter().map(|r| (r - m).powi(2)).sum::<f64>() / (done.len() - 1) as f64).sqrt());
        let of_trained =
            |f: &dyn Fn(&RunReport) -> Option<f64>| mean(&trained.iter().filter_map(|r| f(r)).collect::<Vec<_>>());
        rows.push(ConditionResult {
            name: c.name.clone(),
            about: c.about.clone(),
            cotrain: c.cotrain(),
            w: c.w.unwrap_or(cfg.w),
            preset: c.preset.clone().unwrap_or_else(|| cfg.preset.clone()),
            status: status.to_owned(),
            funnel,
            cotrain_given,
            target_episodes: first.map(|r| r.target_episodes as u64),
            val_episodes: first.map(|r| r.val_episodes as u64),
            cotrain_episodes: first.map(|r| r.cotrain_episodes as u64),
            drawn_target: first.map(|r| r.drawn_target),
            drawn_cotrain: first.map(|r| r.drawn_cotrain),
            steps: first.map(|r| r.steps),
            train_wall_s: (!trained.is_empty()).then(|| policies.iter().filter_map(|p| p.train_wall_s).sum()),
            samples_per_s: of_trained(&|r| Some(r.samples_per_s)),
            last_val_loss: of_trained(&|r| r.last_val_loss),
            open_loop_mm: of_trained(&|r| r.last_open_loop_mm),
            successes: (!judged.is_empty()).then_some(succeeded),
            rollouts: (!judged.is_empty()).then_some(n),
            ci95: (!judged.is_empty()).then(|| wilson95(succeeded, n)),
            by_seed_set,
            policies_done: done.len(),
            seed_mean,
            seed_sd,
            rollout_wall_s: (!judged.is_empty()).then(|| judged.iter().map(|p| p.rollout_wall_s).sum()),
            inference_ms_p50: mean(&judged.iter().filter_map(|p| p.inference_ms_p50).collect::<Vec<_>>()),
            policies,
        });
    }
    let comparisons = cfg
        .compare
        .iter()
        .filter_map(|[a, b]| {
            let rates = |name: &str| -> Vec<f64> {
                rows.iter()
                    .find(|r| r.name == name)
                    .map(|r| r.policies.iter().filter(|p| p.status == "done").filter_map(|p| p.rate()).collect())
                    .unwrap_or_default()
            };
            stats::compare(a, &rates(a), b, &rates(b))
        })
        .collect();
    let results = Results {
        experiment: cfg.name.clone(),
        out: layout.out.clone(),
        target: cfg.target.clone(),
        target_successful: demo(&cfg.target, true).map(|r| r.successes as u64),
        prior: cfg.prior.clone(),
        prior_recorded: cfg
            .prior
            .iter()
            .map(|d| {
                let r = demo(d, false);
                (d.name.clone(), r.as_ref().map(|r| r.recorded as u64), r.as_ref().map(|r| r.successes as u64))
            })
            .collect(),
        prior_episodes,
        preset: resolve_preset(&cfg.preset, config_dir),
        steps: cfg.steps,
        batch_size: cfg.batch_size,
        train_seeds: cfg.train_seeds.clone(),
        rollouts: cfg.rollouts,
        rollout_first_seed: cfg.rollout_first_seed,
        seed_sets: cfg.seed_sets(),
        max_steps: cfg.max_steps,
        conditions: rows,
        comparisons,
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
            if r.policies.len() > 1 {
                let per: Vec<String> = r
                    .policies
                    .iter()
                    .map(|p| if p.judged() { format!("{}/{}", p.successes, p.rollouts) } else { "-".to_owned() })
                    .collect();
                t += &format!(" [by training seed: {}]", per.join(" "));
            } else if r.by_seed_set.len() > 1 {
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
    for c in &r.comparisons {
        s += &format!("  {}\n", comparison_text(c));
    }
    s
}

/// A comparison on one line.
fn comparison_text(c: &stats::Comparison) -> String {
    format!(
        "{} vs {}: {:+.0} points ({:.0}% of {} policies vs {:.0}% of {}; 95% bootstrap {:+.0} to {:+.0}), permutation p = {:.3} over {} relabellings (smallest possible {:.3})",
        c.a,
        c.b,
        100.0 * c.diff,
        100.0 * c.rate_a,
        c.policies_a,
        100.0 * c.rate_b,
        c.policies_b,
        100.0 * c.diff_ci95[0],
        100.0 * c.diff_ci95[1],
        c.p_permutation,
        c.relabellings,
        c.p_min
    )
}

fn table_markdown(r: &Results) -> String {
    let mut s = format!(
        "# {}: co-training on retrieved data (labrig experiment retrieval)\n\n\
         Target: `{}`, {} demos (seeds {}..{}; {} successful). Prior: {} episodes ({}). \
         Training: preset `{}`, {} steps{} for every condition{}. Judged by {} rollouts per seed set of at most {} steps \
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
        if r.train_seeds.is_empty() {
            String::new()
        } else {
            format!(
                ", once per training seed ({}; a condition may take the first few)",
                r.train_seeds.iter().map(|s| s.to_string()).collect::<Vec<_>>().join(", ")
            )
        },
        r.rollouts,
        r.max_steps,
        seeds_text(r),
    );
    s += "| condition | co-training set | retrieval funnel | co-training episodes (used) | w | samples drawn target / co-training | steps | train wall | samples/s | val loss | open loop (mm) | success | over training seeds | rollouts wall |\n";
    s += "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|\n";
    for c in &r.conditions {
        let funnel = if c.funnel.is_empty() {
            "-".to_owned()
        } else {
            c.funnel.iter().map(|(k, n)| format!("{k} {n}")).collect::<Vec<_>>().join(" → ")
        };
        let seeds = match (c.seed_mean, c.seed_sd) {
            (Some(m), Some(sd)) => {
                format!("{:.0}% ± {:.0} ({} of {} policies)", 100.0 * m, 100.0 * sd, c.policies_done, c.policies.len())
            }
            (Some(m), None) => format!("{:.0}% ({} of {} policies)", 100.0 * m, c.policies_done, c.policies.len()),
            _ => format!("- (0 of {} policies)", c.policies.len()),
        };
        s += &format!(
            "| {} | {} | {} | {} ({}) | {} | {} / {} | {} | {} | {} | {} | {} | {} | {} | {} |\n",
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
            seeds,
            c.rollout_wall_s.map_or("-".to_owned(), minutes),
        );
    }
    if !r.comparisons.is_empty() {
        s += "\nPaired comparisons over training seeds (policies as the unit; an exact permutation test of the \
              difference of mean success, two-sided, and a bootstrap interval of it):\n\n";
        for c in &r.comparisons {
            s += &format!("- {}\n", comparison_text(c));
        }
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
        // Each judged policy's own rate (one dot per training seed).
        let dots: Vec<(f64, f64)> = c
            .policies
            .iter()
            .filter_map(|p| p.rate())
            .enumerate()
            .map(|(i, rate)| (x - 0.2 + 0.1 * (i % 5) as f64, 100.0 * rate))
            .collect();
        if c.policies.len() > 1 {
            chart.draw_series(dots.into_iter().map(|p| Circle::new(p, 4, BLACK.mix(0.7).filled()))).map_err(e)?;
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
        for f in ["full.toml", "ci.toml", "droid.toml", "ci_droid.toml"] {
            let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../experiments/retrieval").join(f);
            let cfg = ExperimentConfig::load(&path).unwrap();
            assert!(cfg.condition.len() >= 3, "{f}");
            let dir = path.parent().unwrap();
            for d in std::iter::once(&cfg.target).chain(&cfg.prior) {
                resolve_scene(&d.scene, dir).unwrap();
            }
            for c in &cfg.condition {
                if let Some(p) = &c.preset {
                    assert!(Path::new(&resolve_preset(p, dir)).is_file(), "{f}: {}", c.name);
                }
            }
        }
        // The DROID-shaped prior: 300 demos, a tenth of them aligned with the target.
        let droid = ExperimentConfig::load(
            &Path::new(env!("CARGO_MANIFEST_DIR")).join("../../experiments/retrieval/droid.toml"),
        )
        .unwrap();
        let total: u64 = droid.prior.iter().map(|d| d.episodes).sum();
        assert_eq!((total, droid.prior[0].name.as_str(), droid.prior[0].episodes), (300, "aligned", 30));
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
        assert!(err("", &format!("{a}seeds = 2\n")).contains("seeds = 2 must be in 1..=0"));
        assert!(err("train_seeds = [0, 1]\n", &format!("{a}seeds = 3\n")).contains("seeds = 3 must be in 1..=2"));
        assert!(err("train_seeds = [4, 4]\n", a).contains("seed 4 twice"));
        assert!(err("train_seeds = [4]\ntrain_seed = 1\n", a).contains("exclude each other"));
        assert!(err("compare = [[\"a\", \"b\"]]\n", a).contains("compare: no condition `b`"));
        let seeded =
            parse(&config("train_seeds = [7, 8, 9]\n", &format!("{a}seeds = 2\n[[condition]]\nname = \"b\"\n")))
                .unwrap();
        assert_eq!(seeded.condition.iter().map(|c| c.seed_count(&seeded)).collect::<Vec<_>>(), [2, 3]);
        assert_eq!(ok.condition[0].seed_count(&ok), 1, "no train_seeds: one policy");
        // Raising a condition's seeds later keeps its folder's identity.
        let mut more = seeded.condition[0].clone();
        more.seeds = Some(3);
        assert_eq!(more.identity().unwrap(), seeded.condition[0].identity().unwrap());
        let layout = Layout { out: PathBuf::from("/x") };
        let u = layout.unit(&seeded, &seeded.condition[0], 1);
        assert_eq!(
            (u.seed, u.dir.as_path(), u.name.as_str()),
            (Some(8), Path::new("/x/conditions/a/seed_8"), "a seed 8")
        );
        let u = layout.unit(&ok, &ok.condition[0], 0);
        assert_eq!((u.seed, u.dir.as_path()), (None, Path::new("/x/conditions/a")));
        assert!(
            format!("{:#}", resolve_scene("nope.toml", Path::new("/")).unwrap_err()).contains("not a built-in scene")
        );
    }
}
