//! `labrig-policies`: the program behind `labrig train`, `labrig policy ...` and `labrig bench
//! policy` (the CLI forwards to it: only this crate links libtorch).

use anyhow::Context;
use clap::{Parser, Subcommand};
use labrig_policies::train::{Preset, RunOptions};
use labrig_policies::{checkpoint, infer};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use tch::Tensor;

#[derive(Debug, Parser)]
#[command(name = "labrig-policies", version, about = "labrig's Diffusion Policy: train, infer, import, bench")]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Train a Diffusion Policy on labrig episodes (with co-training).
    Train(TrainArgs),
    /// One action chunk from a checkpoint for an observation and initial noise (safetensors).
    Infer(InferArgs),
    /// Convert a LeRobot Diffusion Policy directory (save_pretrained's) into a labrig checkpoint.
    ImportLerobot(ImportArgs),
    /// Inference latency (encoders, U-Net step, chunk: p50/p99) and training throughput.
    Bench(BenchArgs),
}

#[derive(Debug, clap::Args)]
struct BenchArgs {
    /// Presets to measure (repeatable; default paper_dp and small).
    #[arg(long)]
    preset: Vec<String>,
    /// Timed runs per stage.
    #[arg(long, default_value_t = 50)]
    runs: usize,
    #[arg(long, default_value_t = 3)]
    warmup: usize,
    /// Intra-op threads (default: every core); OMP_NUM_THREADS is reported beside it.
    #[arg(long)]
    threads: Option<i32>,
    /// Timed training steps per preset (0: none).
    #[arg(long, default_value_t = 3)]
    train_steps: usize,
    /// LeRobot's venv (scripts/lerobot_venv.sh): time its PyTorch DiffusionPolicy in the paper
    /// configuration in the same run, with the same threads (default: venv-lerobot in
    /// $LABRIG_CACHE, or ~/.cache/labrig without it, if present).
    #[arg(long)]
    lerobot_venv: Option<PathBuf>,
    /// Skip the PyTorch comparison even where the venv exists.
    #[arg(long)]
    no_lerobot: bool,
    /// Also time the whole chunk with each of these DDIM step counts (default: only the
    /// preset's own).
    #[arg(long, value_delimiter = ',')]
    inference_steps: Vec<usize>,
    /// With --episodes: this checkpoint's open-loop error (mm) per step count of
    /// --inference-steps (the preset's 16 where none is given) on those episodes.
    #[arg(long, requires = "episodes")]
    checkpoint: Option<PathBuf>,
    /// Recorded episodes (a directory or episode) the checkpoint was not trained on.
    #[arg(long, requires = "checkpoint")]
    episodes: Vec<PathBuf>,
    /// Windows spread over --episodes for the open-loop error.
    #[arg(long, default_value_t = 256)]
    samples: usize,
    #[arg(long)]
    json: bool,
}

#[derive(Debug, clap::Args)]
struct ImportArgs {
    /// LeRobot's pretrained directory (config.json, model.safetensors, policy_preprocessor*).
    dir: PathBuf,
    /// The checkpoint directory to write.
    #[arg(long)]
    out: PathBuf,
}

#[derive(Debug, clap::Args)]
struct TrainArgs {
    /// Target episodes: a directory searched for episodes, one episode, or a manifest file (one
    /// episode path per line, relative to the file). Repeatable.
    #[arg(long, required = true)]
    target: Vec<PathBuf>,
    /// Co-training episodes (same forms as --target; a retrieval manifest is a manifest file).
    #[arg(long)]
    cotrain: Vec<PathBuf>,
    /// The probability that a sample comes from the target set (the paper: 0.5; 0.3 and 0.7 ablations).
    #[arg(long, default_value_t = 0.5)]
    w: f64,
    /// paper_dp, small, or a TOML file (`preset = "small"` plus [model]/[train] overrides).
    #[arg(long, default_value = "paper_dp")]
    preset: String,
    /// The run directory (checkpoints, loss.csv, loss.png, run.json, the frame cache).
    #[arg(long)]
    out: PathBuf,
    /// Optimisation steps in all (a resumed run counts its earlier ones).
    #[arg(long, conflicts_with = "epochs")]
    steps: Option<usize>,
    /// Passes over the target training samples, instead of --steps.
    #[arg(long)]
    epochs: Option<f64>,
    /// Continue from the run's last checkpoint.
    #[arg(long)]
    resume: bool,
    /// Train on unsuccessful episodes too.
    #[arg(long)]
    include_failures: bool,
    /// Of episodes where an operator took over from a policy (corrections), train on every
    /// step (`all`) or only the operator's segments (`operator`, with --before-takeover).
    #[arg(long, value_enum, default_value = "all")]
    corrections: CorrectionsArg,
    /// With `--corrections operator`: also the N steps before each takeover.
    #[arg(long, default_value_t = 0)]
    before_takeover: usize,
    /// Where decoded frames are cached (default <out>/cache).
    #[arg(long)]
    cache: Option<PathBuf>,
    /// Intra-op threads (default: every core).
    #[arg(long)]
    threads: Option<i32>,
    /// Override the preset's batch size.
    #[arg(long)]
    batch_size: Option<usize>,
    /// Override the preset's checkpoint interval (steps).
    #[arg(long)]
    checkpoint_every: Option<usize>,
    /// Override the preset's validation interval (steps).
    #[arg(long)]
    val_every: Option<usize>,
    /// Override the preset's seed.
    #[arg(long)]
    seed: Option<u64>,
    /// Data-parallel runs (WORLD_SIZE > 1 from the launcher): how long a rank waits for the
    /// others (joining, and at each step) before it gives up with an error.
    #[arg(long, default_value_t = 1800)]
    dist_timeout_s: u64,
    /// Print the run's report as JSON.
    #[arg(long)]
    json: bool,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
enum CorrectionsArg {
    All,
    Operator,
}

#[derive(Debug, clap::Args)]
struct InferArgs {
    /// The checkpoint directory.
    checkpoint: PathBuf,
    /// `observation.images.<camera>` (B, To, 3, H, W) in [0, 1] and `observation.state` (B, To, 7).
    #[arg(long)]
    obs: PathBuf,
    /// `noise` (B, Tp, action_dim): the initial DDIM sample.
    #[arg(long)]
    noise: PathBuf,
    /// Writes `action` (B, Tp, action_dim), `action.executed` and the stages (`features.<camera>`,
    /// `global_cond`, `eps.first`, `eps.last`, `chunk.normalized`).
    #[arg(long)]
    out: PathBuf,
    #[arg(long)]
    threads: Option<i32>,
}

/// Episode paths from a --target/--cotrain argument.
fn episodes_of(arg: &Path) -> anyhow::Result<Vec<PathBuf>> {
    labrig_episode::episode::episodes_of(arg).map_err(anyhow::Error::msg)
}

fn set_threads(n: Option<i32>) -> i32 {
    let n = n.unwrap_or_else(|| std::thread::available_parallelism().map(|n| n.get() as i32).unwrap_or(1));
    tch::set_num_threads(n);
    n
}

fn train(a: TrainArgs) -> anyhow::Result<ExitCode> {
    set_threads(a.threads);
    let mut preset = Preset::resolve(&a.preset)?;
    let t = &mut preset.train;
    t.batch_size = a.batch_size.unwrap_or(t.batch_size);
    t.checkpoint_every = a.checkpoint_every.unwrap_or(t.checkpoint_every);
    t.val_every = a.val_every.unwrap_or(t.val_every);
    t.seed = a.seed.unwrap_or(t.seed);
    anyhow::ensure!(
        t.batch_size > 0 && t.checkpoint_every > 0 && t.val_every > 0,
        "batch size and intervals must be > 0"
    );
    tch::manual_seed(t.seed as i64);
    let collect = |args: &[PathBuf]| -> anyhow::Result<Vec<PathBuf>> {
        Ok(args.iter().map(|p| episodes_of(p)).collect::<anyhow::Result<Vec<_>>>()?.concat())
    };
    let target = collect(&a.target)?;
    let cotrain = collect(&a.cotrain)?;
    anyhow::ensure!((0.0..=1.0).contains(&a.w), "--w {} must be in [0, 1]", a.w);
    let length = match (a.steps, a.epochs) {
        (Some(s), _) => labrig_policies::train::Length::Steps(s),
        (None, Some(e)) => labrig_policies::train::Length::Epochs(e),
        (None, None) => anyhow::bail!("say how long to train: --steps N or --epochs N"),
    };
    // Data-parallel when a launcher (torchrun --no-python, srun, ...) set WORLD_SIZE > 1.
    let dist = match labrig_policies::dist::Launch::from_env()? {
        None => None,
        Some(l) => {
            let timeout = std::time::Duration::from_secs(a.dist_timeout_s);
            eprintln!(
                "rank {} of {}: joining the process group (Gloo) at {}:{}{}",
                l.rank,
                l.world,
                l.master_addr,
                l.master_port,
                if l.agent_store { " (the launcher's store)" } else { "" }
            );
            Some(std::sync::Arc::new(labrig_policies::dist::Group::join(&l, timeout)?))
        }
    };
    let opts = RunOptions {
        target,
        cotrain,
        w: a.w,
        preset,
        cache: a.cache.unwrap_or_else(|| a.out.join("cache")),
        out: a.out,
        length,
        resume: a.resume,
        include_failures: a.include_failures,
        progress: true,
        corrections: match a.corrections {
            CorrectionsArg::All => labrig_policies::train::Corrections::All,
            CorrectionsArg::Operator => labrig_policies::train::Corrections::Operator { before: a.before_takeover },
        },
        dist,
    };
    let r = labrig_policies::train::run(&opts)?;
    if opts.dist.as_ref().is_some_and(|g| g.rank != 0) {
        // Rank 0 reports (and wrote run.json); the others only say they finished.
        eprintln!("rank {} done: {} steps", opts.dist.as_ref().map(|g| g.rank).unwrap_or(0), r.steps);
        return Ok(ExitCode::SUCCESS);
    }
    if a.json {
        println!("{}", serde_json::to_string_pretty(&r)?);
    } else {
        let fall = match (r.first_val_loss, r.last_val_loss) {
            (Some(a), Some(b)) => format!("validation loss {a:.4} -> {b:.4} ({:.1}x lower)", a / b.max(1e-12)),
            _ => "no validation split (one target episode)".into(),
        };
        println!(
            "trained {} steps: {fall}; {:.1} samples/s on {} threads, the loader {:.1}% of a step; samples drawn: {} target, {} co-training; frames decoded in {:.1} s\ncheckpoint: {}\nloss curve: {}",
            r.steps,
            r.samples_per_s,
            r.threads,
            100.0 * r.loader_share,
            r.drawn_target,
            r.drawn_cotrain,
            r.decode_s,
            r.checkpoint.display(),
            opts.out.join("loss.png").display()
        );
    }
    Ok(ExitCode::SUCCESS)
}

fn read_tensors(path: &Path) -> anyhow::Result<BTreeMap<String, Tensor>> {
    Ok(Tensor::read_safetensors(path)
        .with_context(|| format!("reading {}", path.display()))?
        .into_iter()
        .map(|(k, v)| (k, v.to_kind(tch::Kind::Float)))
        .collect())
}

fn infer_cmd(a: InferArgs) -> anyhow::Result<ExitCode> {
    set_threads(a.threads);
    let (_vs, policy, meta) = checkpoint::load(&a.checkpoint, tch::Device::Cpu)?;
    let obs = read_tensors(&a.obs)?;
    let noise = read_tensors(&a.noise)?
        .remove("noise")
        .with_context(|| format!("{}: no tensor named `noise`", a.noise.display()))?;
    let r = infer::infer(&policy, &meta, &obs, &noise)?;
    let mut out: Vec<(String, Tensor)> = vec![
        ("action".into(), r.action),
        ("action.executed".into(), r.executed),
        ("chunk.normalized".into(), r.trace.chunk),
        ("global_cond".into(), r.trace.global_cond),
        ("eps.first".into(), r.trace.eps_first.1),
        ("t.first".into(), Tensor::from(r.trace.eps_first.0)),
        ("eps.last".into(), r.trace.eps_last.1),
        ("t.last".into(), Tensor::from(r.trace.eps_last.0)),
    ];
    for (cam, f) in meta.config.cameras.iter().zip(r.trace.features) {
        out.push((format!("features.{cam}"), f));
    }
    let out: Vec<(String, Tensor)> = out.into_iter().map(|(k, t)| (k, t.contiguous())).collect();
    Tensor::write_safetensors(&out, &a.out).with_context(|| format!("writing {}", a.out.display()))?;
    println!("{}: action {:?}", a.out.display(), out[0].1.size());
    Ok(ExitCode::SUCCESS)
}

fn import_cmd(a: ImportArgs) -> anyhow::Result<ExitCode> {
    let r = labrig_policies::lerobot::import(&a.dir, &a.out)?;
    println!(
        "{}: {} tensors, {} parameters; cameras {:?}, U-Net {:?}, {} keypoints, DDIM {} of {} steps",
        a.out.display(),
        r.tensors,
        r.parameters,
        r.config.cameras,
        r.config.down_dims,
        r.config.keypoints,
        r.config.inference_steps,
        r.config.train_steps
    );
    Ok(ExitCode::SUCCESS)
}

/// LeRobot's model timed by scripts/bench_lerobot_dp.py in its venv: the script's JSON.
fn lerobot_figures(venv: &Path, threads: i32, runs: usize, warmup: usize) -> anyhow::Result<serde_json::Value> {
    let script = Path::new("scripts/bench_lerobot_dp.py");
    anyhow::ensure!(script.is_file(), "{} not found (run from the repository root)", script.display());
    let out = tempfile_path("lerobot_bench.json");
    let status = std::process::Command::new(venv.join("bin/python"))
        .arg(script)
        .args(["--threads", &threads.to_string(), "--runs", &runs.to_string(), "--warmup", &warmup.to_string()])
        .arg("--json")
        .arg(&out)
        .env("OMP_NUM_THREADS", threads.to_string())
        .stdout(std::process::Stdio::null())
        .status()
        .with_context(|| format!("running {}", venv.join("bin/python").display()))?;
    anyhow::ensure!(status.success(), "{} failed ({status})", script.display());
    let v = serde_json::from_str(&std::fs::read_to_string(&out)?)?;
    let _ = std::fs::remove_file(&out);
    Ok(v)
}

fn tempfile_path(name: &str) -> PathBuf {
    std::env::temp_dir().join(format!("labrig-{}-{name}", std::process::id()))
}

fn bench_cmd(a: BenchArgs) -> anyhow::Result<ExitCode> {
    use labrig_policies::bench;
    let threads = set_threads(a.threads);
    let omp = std::env::var("OMP_NUM_THREADS").unwrap_or_else(|_| "unset".into());
    let presets = if a.preset.is_empty() && a.checkpoint.is_none() {
        vec!["paper_dp".to_owned(), "small".to_owned()]
    } else {
        a.preset.clone()
    };
    let venv = a.lerobot_venv.clone().or_else(|| {
        let d = labrig_msgs::cache_dir()?.join("venv-lerobot");
        d.join("bin/python").is_file().then_some(d)
    });
    let mut report = serde_json::Map::new();
    report.insert("threads".into(), threads.into());
    report.insert("omp_num_threads".into(), omp.clone().into());
    if !a.json {
        println!(
            "labrig bench policy: batch 1, {} runs per stage after {} warm-up, {threads} intra-op threads (OMP_NUM_THREADS {omp}); a shared machine: compare within one run",
            a.runs, a.warmup
        );
    }
    let budget_ms = |cfg: &labrig_policies::policy::DiffusionConfig| cfg.n_action_steps as f64 * 50.0;
    for name in &presets {
        let preset = Preset::resolve(name)?;
        let cfg = &preset.model;
        let inf = bench::inference(cfg, a.runs, a.warmup)?;
        let train = if a.train_steps > 0 { Some(bench::training(&preset, a.train_steps)?) } else { None };
        let mut entry = serde_json::json!({ "labrig": inf, "train_samples_per_s": train, "train_batch": preset.train.batch_size, "chunk_budget_ms": budget_ms(cfg) });
        if !a.json {
            let row = |what: &str, p: &labrig_episode::inspect::Percentiles| {
                println!("  {what:28} p50 {:8.1} ms   p99 {:8.1} ms", p.p50, p.p99)
            };
            println!(
                "{name}: {} cameras {}x{}, U-Net {:?}, DDIM {} steps, {:.1} M parameters",
                cfg.cameras.len(),
                cfg.image_size,
                cfg.image_size,
                cfg.down_dims,
                cfg.inference_steps,
                inf.parameters as f64 / 1e6
            );
            row("encoders (one observation)", &inf.encoder_ms);
            row("U-Net, one step", &inf.unet_step_ms);
            row("whole chunk", &inf.chunk_ms);
            println!(
                "  a chunk executes {} actions = {:.0} ms at 20 Hz: p50 is {:.2}x, p99 {:.2}x that",
                cfg.n_action_steps,
                budget_ms(cfg),
                inf.chunk_ms.p50 / budget_ms(cfg),
                inf.chunk_ms.p99 / budget_ms(cfg)
            );
            if let Some(t) = train {
                println!("  training: {t:.1} samples/s (batch {}, synthetic data)", preset.train.batch_size);
            }
        }
        if !a.inference_steps.is_empty() {
            let by_steps = bench::chunk_by_steps(cfg, &a.inference_steps, a.runs, a.warmup)?;
            for (n, p) in &by_steps {
                if !a.json {
                    println!(
                        "  whole chunk, {n:2} DDIM steps     p50 {:8.1} ms   p99 {:8.1} ms   ({:.2}x the {:.0} ms budget at p50)",
                        p.p50,
                        p.p99,
                        p.p50 / budget_ms(cfg),
                        budget_ms(cfg)
                    );
                }
            }
            entry["chunk_ms_by_steps"] = serde_json::json!(
                by_steps.iter().map(|(n, p)| serde_json::json!({"steps": n, "chunk_ms": p})).collect::<Vec<_>>()
            );
        }
        if name == "paper_dp"
            && !a.no_lerobot
            && let Some(venv) = &venv
        {
            match lerobot_figures(venv, threads, a.runs, a.warmup) {
                Ok(v) => {
                    let p = |k: &str, q: &str| {
                        v.get(k).and_then(|s| s.get(q)).and_then(serde_json::Value::as_f64).unwrap_or(f64::NAN)
                    };
                    if !a.json {
                        println!(
                            "  LeRobot {} / torch {} (PyTorch, same threads): encoders p50 {:.1} p99 {:.1} ms, U-Net step p50 {:.1} p99 {:.1} ms, chunk p50 {:.1} p99 {:.1} ms",
                            v.get("lerobot").and_then(|x| x.as_str()).unwrap_or("?"),
                            v.get("torch").and_then(|x| x.as_str()).unwrap_or("?"),
                            p("encoder_ms", "p50"),
                            p("encoder_ms", "p99"),
                            p("unet_step_ms", "p50"),
                            p("unet_step_ms", "p99"),
                            p("chunk_ms", "p50"),
                            p("chunk_ms", "p99")
                        );
                        println!(
                            "  labrig / PyTorch: chunk p50 {:.2}x, p99 {:.2}x",
                            inf.chunk_ms.p50 / p("chunk_ms", "p50"),
                            inf.chunk_ms.p99 / p("chunk_ms", "p99")
                        );
                    }
                    entry["lerobot"] = v;
                }
                Err(e) => eprintln!("  (no PyTorch comparison: {e:#})"),
            }
        }
        report.insert(name.clone(), entry);
    }
    if let Some(dir) = &a.checkpoint {
        let mut paths = Vec::new();
        for e in &a.episodes {
            paths.extend(episodes_of(e)?);
        }
        let steps = if a.inference_steps.is_empty() { vec![16, 8, 4, 2, 1] } else { a.inference_steps.clone() };
        let rows = bench::open_loop_by_steps(dir, &paths, &steps, a.samples)?;
        if !a.json {
            println!(
                "{}: open loop on {} episodes ({} windows, the same noise each), target positions of the executed rows:",
                dir.display(),
                paths.len(),
                rows.first().map_or(0, |r| r.samples)
            );
            for r in &rows {
                println!("  {:2} DDIM steps   {:6.1} mm", r.inference_steps, r.open_loop_mm);
            }
        }
        report.insert("open_loop".into(), serde_json::json!({ "checkpoint": dir, "rows": rows }));
    }
    if a.json {
        println!("{}", serde_json::to_string_pretty(&report)?);
    }
    Ok(ExitCode::SUCCESS)
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    if labrig_msgs::parse_only() {
        return ExitCode::SUCCESS;
    }
    let result = match cli.command {
        Command::Train(a) => train(a),
        Command::Infer(a) => infer_cmd(a),
        Command::ImportLerobot(a) => import_cmd(a),
        Command::Bench(a) => bench_cmd(a),
    };
    match result {
        Ok(code) => code,
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::from(1)
        }
    }
}
