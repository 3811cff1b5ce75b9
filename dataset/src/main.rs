//! `labrig-dataset` (run as `labrig dataset ...`): the paper's dataset tools.
//!
//! - `labrig dataset index <root>... --out <index dir> [--shard I/N] [--json]`: one row per
//!   episode (labrig MCAP and DROID raw, found by auto-detection) into a Parquet part;
//! - `labrig dataset merge <parts dir> --out <index dir> [--json]`: a whole set of shard parts
//!   as one index, hive-partitioned by source format (`source_format=<f>/part-*.parquet`);
//! - `labrig dataset retrieve --index <dir> --target <episodes dir|index dir|target.toml>
//!   --align object,skill,camPose,objTex,objSpat --out manifest.json [--json]`.

use anyhow::{Context, bail};
use clap::{Args, Parser, Subcommand};
use labrig_dataset::dv::{GraspParams, Vocabulary};
use labrig_dataset::retrieve::{self, Dim, Target, Thresholds};
use labrig_dataset::row::IndexRow;
use labrig_dataset::source::{self, Derive};
use labrig_dataset::table;
use labrig_episode::progress;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::Instant;

#[derive(Debug, Parser)]
#[command(name = "labrig dataset", about = "The paper's dataset tools: index, retrieve by alignment, manifests")]
struct Cli {
    #[command(subcommand)]
    cmd: Cmd,
}

#[derive(Debug, Subcommand)]
enum Cmd {
    /// Index episodes (labrig MCAP, DROID raw) into a directory of Parquet parts.
    Index(IndexArgs),
    /// Merge a whole set of shard parts into one index, hive-partitioned by source format.
    Merge(MergeArgs),
    /// Retrieve the demos aligned with a target into a manifest.
    Retrieve(RetrieveArgs),
    /// What an index holds, by bin, object and primitive; with --target, the funnel; --plot a PNG.
    Stats(StatsArgs),
    /// Retrieval over a synthetic index (p50/p99 per --align combination) and, with --episodes-root,
    /// index throughput against merely reading the files.
    Bench(BenchArgs),
    /// labrig episodes as a LeRobot dataset (format v3.0): `labrig export lerobot <episode|dir>... <out>`.
    ExportLerobot(ExportLerobotArgs),
    /// A LeRobot dataset (v3.0, v2.1) as labrig episodes: `labrig import lerobot <root> [--episodes 0,3-5] <out>`.
    ImportLerobot(ImportLerobotArgs),
}

#[derive(Debug, Args)]
struct ImportLerobotArgs {
    /// The dataset's root (the folder holding meta/info.json).
    root: PathBuf,
    /// Where the episodes go (the recorder's layout: <out>/success|failure/<date>/<time>).
    out: PathBuf,
    /// Only these episodes (LeRobot's indices: `0,3,5-9`).
    #[arg(long)]
    episodes: Option<String>,
    /// Replace episodes imported before (the same uuid).
    #[arg(long)]
    overwrite: bool,
    /// JPEG quality of the imported frames.
    #[arg(long, default_value_t = 90)]
    jpeg_quality: u8,
    /// Print the report as JSON.
    #[arg(long)]
    json: bool,
}

#[derive(Debug, Args)]
struct ExportLerobotArgs {
    /// Episodes (directories or MCAP files), folders holding them or manifests listing them
    /// (`labrig dataset retrieve`'s), then the output directory.
    #[arg(required = true, num_args = 2..)]
    paths: Vec<PathBuf>,
    /// LeRobot's dataset format: v3.0 (LeRobot 0.4+) or v2.1 (LeRobot 0.3, what openpi reads);
    /// default v3.0, v2.1 with `--schema openpi-droid`.
    #[arg(long)]
    format: Option<String>,
    /// The keys: `droid` (DROID's, as the LeRobot DROID port), `openpi-droid` (the flat keys of
    /// openpi's pi05_droid_finetune), `labrig` (what labrig's Diffusion Policy trains on: TCP
    /// pose + gripper -> eef_axis_angle, for LeRobot's trainer and `labrig policy import-lerobot`).
    #[arg(long, default_value = "droid")]
    schema: String,
    /// Only these cameras (labrig's ids, e.g. `ext1,ext2`); default every recorded one.
    #[arg(long, value_delimiter = ',')]
    cameras: Option<Vec<String>>,
    /// Replace an existing output.
    #[arg(long)]
    overwrite: bool,
    /// Print the report as JSON.
    #[arg(long)]
    json: bool,
}

#[derive(Debug, Args)]
struct StatsArgs {
    #[arg(long)]
    index: PathBuf,
    /// A target (as `retrieve --target`) whose retrieval is drawn over the index.
    #[arg(long)]
    target: Option<PathBuf>,
    /// The dimensions to align with the target.
    #[arg(long, value_delimiter = ',', default_value = "object,skill,camPose,objSpat")]
    align: Vec<String>,
    /// The picture (PNG): cameras by bin and objects from above and from the side.
    #[arg(long)]
    plot: Option<PathBuf>,
    #[arg(long)]
    json: bool,
}

#[derive(Debug, Args)]
struct BenchArgs {
    /// Synthetic episodes in the index.
    #[arg(long, default_value_t = 1_000_000)]
    episodes: usize,
    /// Retrievals timed per combination.
    #[arg(long, default_value_t = 20)]
    runs: usize,
    /// A folder of episodes whose indexing is timed.
    #[arg(long)]
    episodes_root: Option<PathBuf>,
    #[arg(long)]
    json: bool,
}

#[derive(Debug, Args)]
struct IndexArgs {
    /// Folders searched for episodes.
    #[arg(required = true)]
    roots: Vec<PathBuf>,
    /// The index directory (created); this run writes part-<I>-of-<N>.parquet there.
    #[arg(long)]
    out: PathBuf,
    /// Index the I-th of N disjoint slices of the episodes found (0-based), e.g. 3/16.
    #[arg(long, default_value = "0/1")]
    shard: String,
    /// The vocabulary of objects, primitives and colours (TOML; default dataset/vocabulary.toml).
    #[arg(long)]
    vocabulary: Option<PathBuf>,
    /// The table centre in the base frame (m): the origin of the cameras' spherical coordinates.
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true, default_value = "0.5,0,0")]
    table_centre: Vec<f64>,
    /// The gripper signal is averaged over this many steps to find the first real close.
    #[arg(long, default_value_t = 15)]
    grasp_window: usize,
    /// The averaged gripper signal (0 open .. 1 closed) above which the gripper is closed.
    #[arg(long, default_value_t = 0.5)]
    grasp_threshold: f64,
    /// Re-calibrated extrinsics (DROID's cam2base_extrinsics.json: episode -> camera serial ->
    /// x, y, z, roll, pitch, yaw) that replace an episode's own where it names the serial.
    #[arg(long)]
    extrinsics: Option<PathBuf>,
    #[arg(long)]
    json: bool,
}

#[derive(Debug, Args)]
struct MergeArgs {
    /// The directory the shards wrote (`labrig dataset index --shard I/N --out <parts dir>`).
    parts: PathBuf,
    /// The merged index: `<out>/source_format=<f>/part-*.parquet` and `_index.json`.
    #[arg(long)]
    out: PathBuf,
    #[arg(long)]
    json: bool,
}

#[derive(Debug, Args)]
struct RetrieveArgs {
    /// The index directory to retrieve from.
    #[arg(long)]
    index: PathBuf,
    /// The target: a folder of episodes, an index directory, or a TOML spec (cameras,
    /// object_position, object, skill, colour).
    #[arg(long)]
    target: PathBuf,
    /// Dimensions to align, any of object, skill, camPose, objTex, objSpat (applied in that
    /// order, the paper's).
    #[arg(long, value_delimiter = ',', required = true)]
    align: Vec<String>,
    /// The manifest to write.
    #[arg(long)]
    out: PathBuf,
    /// camPose: a demo camera within this of the target camera in x and in y (m).
    #[arg(long, default_value_t = 0.20)]
    cam_xy_m: f64,
    /// camPose: ... and in z (m).
    #[arg(long, default_value_t = 0.10)]
    cam_z_m: f64,
    /// objSpat: the cuboid's size around the target's object position (m).
    #[arg(long, value_delimiter = ',', default_value = "0.6,0.6,0.3")]
    obj_box_m: Vec<f64>,
    /// Keep the target's own episodes out of the result (by episode id).
    #[arg(long)]
    exclude_target: bool,
    #[arg(long)]
    json: bool,
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    if labrig_msgs::parse_only() {
        return ExitCode::SUCCESS;
    }
    let result = match cli.cmd {
        Cmd::Index(a) => index(a),
        Cmd::Merge(a) => merge(a),
        Cmd::Retrieve(a) => retrieve_cmd(a),
        Cmd::Bench(a) => bench(a),
        Cmd::Stats(a) => stats(a),
        Cmd::ExportLerobot(a) => export_lerobot(a),
        Cmd::ImportLerobot(a) => import_lerobot(a),
    };
    match result {
        Ok(c) => c,
        Err(e) => {
            eprintln!("labrig dataset: {e:#}");
            ExitCode::FAILURE
        }
    }
}

fn export_lerobot(a: ExportLerobotArgs) -> anyhow::Result<ExitCode> {
    let (out, inputs) = a.paths.split_last().expect("two or more");
    let mut episodes = Vec::new();
    for p in inputs {
        let mcap = p.is_file() && p.extension().is_some_and(|x| x == "mcap");
        if mcap || p.join(labrig_episode::episode::EPISODE_FILE).is_file() {
            episodes.push(p.clone());
        } else if p.exists() {
            // A folder of episodes, or a manifest (`labrig dataset retrieve`'s JSON or a list of
            // paths), so a retrieved co-training set exports as it trains.
            let found = labrig_episode::episode::episodes_of(p).map_err(anyhow::Error::msg)?;
            anyhow::ensure!(!found.is_empty(), "{}: no labrig episodes in it", p.display());
            episodes.extend(found);
        } else {
            bail!("{}: no such episode, folder or manifest", p.display());
        }
    }
    let bar = progress::bar("export lerobot {bar:30} {pos}/{len} episodes", episodes.len() as u64, a.json);
    use labrig_dataset::lerobot::{Format, Schema, Spec};
    let schema = Schema::parse(&a.schema).map_err(anyhow::Error::msg)?;
    let format = match (&a.format, schema) {
        (Some(f), _) => Format::parse(f).map_err(anyhow::Error::msg)?,
        (None, Schema::OpenpiDroid) => Format::V21,
        (None, _) => Format::V30,
    };
    let spec = Spec { format, schema, cameras: a.cameras.clone() };
    let r =
        labrig_dataset::lerobot::export(&episodes, out, &spec, a.overwrite, |done, _| bar.set_position(done as u64))?;
    bar.finish_and_clear();
    if a.json {
        println!("{}", serde_json::to_string(&r)?);
    } else {
        println!(
            "labrig export lerobot: {} episodes, {} frames, cameras {:?} -> {} (LeRobot {}, {:.1} MB, {:.1} s)",
            r.episodes,
            r.frames,
            r.cameras,
            r.out.display(),
            r.format.version(),
            r.bytes as f64 / 1e6,
            r.seconds
        );
        for (c, n) in r.frames_filled.iter().filter(|(_, n)| **n > 0) {
            println!("  camera {c}: {n} steps had no frame of their own (the previous frame repeated)");
        }
        for (p, why) in &r.skipped {
            println!("  skipped {}: {why}", p.display());
        }
    }
    Ok(if r.skipped.is_empty() { ExitCode::SUCCESS } else { ExitCode::from(2) })
}

fn import_lerobot(a: ImportLerobotArgs) -> anyhow::Result<ExitCode> {
    use labrig_dataset::lerobot_import;
    let only = a.episodes.as_deref().map(lerobot_import::parse_episodes).transpose().map_err(anyhow::Error::msg)?;
    let bar = progress::bar("import lerobot {bar:30} {pos}/{len} episodes", 0, a.json);
    let opts = labrig_droid::import::ImportOptions { overwrite: a.overwrite, jpeg_quality: a.jpeg_quality };
    let r = lerobot_import::import(&a.root, only.as_deref(), &a.out, &opts, |done, total| {
        bar.set_length(total as u64);
        bar.set_position(done as u64);
    })?;
    bar.finish_and_clear();
    if a.json {
        println!("{}", serde_json::to_string(&r)?);
    } else {
        println!(
            "labrig import lerobot: {} episodes ({} steps, {} frames, cameras {}) from {} (LeRobot {}) -> {} in {:.1} s",
            r.episodes.len(),
            r.steps,
            r.frames,
            r.cameras.iter().map(|c| format!("{} as {}", c.key, c.id)).collect::<Vec<_>>().join(", "),
            r.source.display(),
            r.version,
            r.out.display(),
            r.seconds
        );
        for (i, dir, steps, _) in &r.episodes {
            println!("  episode {i}: {steps} steps -> {}", dir.display());
        }
        for (k, n) in &r.absent {
            println!("  {k}: not in the dataset ({n} episodes): left at zero");
        }
        for w in &r.warnings {
            println!("  warning: {w}");
        }
        for (i, why) in &r.skipped {
            println!("  skipped episode {i}: {why}");
        }
    }
    if r.episodes.is_empty() {
        bail!("no episode could be imported from {}", a.root.display());
    }
    Ok(if r.skipped.is_empty() { ExitCode::SUCCESS } else { ExitCode::from(2) })
}

fn shard_of(s: &str) -> anyhow::Result<(usize, usize)> {
    let (i, n) = s.split_once('/').with_context(|| format!("--shard {s}: expected I/N, e.g. 0/4"))?;
    let (i, n): (usize, usize) = (i.trim().parse()?, n.trim().parse()?);
    anyhow::ensure!(n >= 1 && i < n, "--shard {s}: I must be in 0..N");
    Ok((i, n))
}

fn derive_of(a: &IndexArgs) -> anyhow::Result<Derive> {
    let vocabulary = match &a.vocabulary {
        None => Vocabulary::default_words(),
        Some(p) => Vocabulary::parse(&std::fs::read_to_string(p).with_context(|| format!("reading {}", p.display()))?)
            .with_context(|| format!("{} is not a vocabulary", p.display()))?,
    };
    let [x, y, z] = a.table_centre.as_slice() else { bail!("--table-centre takes x,y,z") };
    anyhow::ensure!(a.grasp_window >= 1, "--grasp-window must be at least 1");
    let recalibration = match &a.extrinsics {
        None => None,
        Some(p) => Some(std::sync::Arc::new(
            labrig_dataset::recal::Recalibration::load(p).map_err(|e| anyhow::anyhow!("--extrinsics {e}"))?,
        )),
    };
    Ok(Derive {
        vocabulary,
        grasp: GraspParams { window: a.grasp_window, threshold: a.grasp_threshold },
        table_centre: [*x, *y, *z],
        recalibration,
    })
}

fn index(a: IndexArgs) -> anyhow::Result<ExitCode> {
    let t0 = Instant::now();
    let (i, n) = shard_of(&a.shard)?;
    let derive = derive_of(&a)?;
    let mut found = Vec::new();
    for root in &a.roots {
        anyhow::ensure!(root.is_dir(), "{}: no such folder", root.display());
        found.extend(source::discover(root));
    }
    found.sort();
    found.dedup();
    let total = found.len();
    // Disjoint slices: every N-th episode of the sorted list, so slices are balanced.
    let mine: Vec<_> = found.into_iter().enumerate().filter(|(k, _)| k % n == i).map(|(_, f)| f).collect();
    std::fs::create_dir_all(&a.out).with_context(|| format!("creating {}", a.out.display()))?;
    let part = a.out.join(table::part_name(i, n));
    // Rows of an unchanged episode (same path, size and mtime) are kept from the last run,
    // if it used the same --extrinsics file (or none).
    let recal_stamp = derive.recalibration.as_ref().map(|r| r.stamp.as_str()).unwrap_or("");
    let same_override = table::part_recalibration(&part).is_some_and(|s| s == recal_stamp);
    let previous: BTreeMap<String, IndexRow> = if part.exists() && same_override {
        table::read_part(&part)
            .map(|rows| rows.into_iter().map(|r| (r.source_path.clone(), r)).collect())
            .unwrap_or_default()
    } else {
        BTreeMap::new()
    };
    let bar = progress::bar("{bar:30} {pos}/{len} episodes", mine.len() as u64, a.json);
    let (mut rows, mut bad, mut skipped) = (Vec::new(), Vec::new(), 0usize);
    let mut bytes = 0u64;
    for f in &mine {
        let key = f.dir.display().to_string();
        // The rows the last run made of it (an RLDS shard's are `<file>#<k>`).
        let before: Vec<&IndexRow> = previous
            .range(key.clone()..)
            .take_while(|(p, _)| p.starts_with(&key))
            .filter(|(p, _)| **p == key || p[key.len()..].starts_with('#'))
            .map(|(_, r)| r)
            .collect();
        let stamp = source::stamp(f).ok();
        if !before.is_empty() && before.iter().all(|r| stamp == Some((r.file_size, r.file_mtime_ns))) {
            skipped += before.len();
            rows.extend(before.into_iter().cloned());
        } else {
            match source::rows(f, &derive) {
                Ok(r) => {
                    bytes += r.first().map(|r| r.file_size).unwrap_or(0);
                    rows.extend(r);
                }
                Err(why) => bad.push(labrig_reports::BadSource {
                    path: key,
                    format: f.format.name().to_owned(),
                    reason: why.to_string(),
                }),
            }
        }
        bar.inc(1);
    }
    bar.finish_and_clear();
    table::write_part(&part, &rows, recal_stamp)?;
    let seconds = t0.elapsed().as_secs_f64();
    let mut by_format: BTreeMap<&str, usize> = BTreeMap::new();
    for r in &rows {
        *by_format.entry(r.source_format.as_str()).or_default() += 1;
    }
    // What the override changed: episodes with a re-calibrated camera, and those the file names
    // whose metadata has none of its serials (DROID's RLDS release carries no serials).
    let recalibration = derive.recalibration.as_ref().map(|r| {
        let changed = rows
            .iter()
            .filter(|row| row.cameras.iter().any(|c| c.extrinsics_from.as_deref() == Some("recalibrated")))
            .count();
        let unmatched = rows
            .iter()
            .filter(|row| {
                r.has(&row.episode_id)
                    && !row.cameras.iter().any(|c| c.extrinsics_from.as_deref() == Some("recalibrated"))
            })
            .count();
        serde_json::json!({"file_episodes": r.episodes(), "recalibrated": changed, "named_without_serials": unmatched})
    });
    if a.json {
        println!(
            "{}",
            serde_json::to_string(&labrig_reports::IndexReport {
                part: part.clone(),
                shard: [i, n],
                found: total,
                in_shard: mine.len(),
                indexed: rows.len() - skipped,
                unchanged: skipped,
                bad: bad.clone(),
                by_format: by_format.iter().map(|(k, v)| ((*k).to_owned(), *v)).collect(),
                extrinsics_override: recalibration.clone(),
                seconds,
                episodes_per_s: mine.len() as f64 / seconds.max(1e-9),
                mb_per_s: bytes as f64 / 1e6 / seconds.max(1e-9),
            })?
        );
    } else {
        println!(
            "{}: {} episodes ({} indexed, {} unchanged, {} bad) from {} sources found, shard {i}/{n}, {seconds:.1} s",
            part.display(),
            rows.len(),
            rows.len() - skipped,
            skipped,
            bad.len(),
            total
        );
        for (f, k) in &by_format {
            println!("    {f}: {k}");
        }
        if let Some(r) = &recalibration {
            println!(
                "    --extrinsics: {} episodes re-calibrated; {} named by the file without a matching camera serial",
                r["recalibrated"], r["named_without_serials"]
            );
        }
        for b in &bad {
            println!("    skipped {}: {}", b.path, b.reason);
        }
    }
    Ok(ExitCode::SUCCESS)
}

fn merge(a: MergeArgs) -> anyhow::Result<ExitCode> {
    let t0 = Instant::now();
    anyhow::ensure!(
        !a.out.exists() || a.parts.canonicalize().ok() != a.out.canonicalize().ok(),
        "--out must be another directory than the parts ({})",
        a.parts.display()
    );
    let m = table::merge(&a.parts, &a.out)?;
    let seconds = t0.elapsed().as_secs_f64();
    if a.json {
        let mut v = serde_json::to_value(&m)?;
        v["index"] = serde_json::json!(a.out);
        v["seconds"] = serde_json::json!(seconds);
        println!("{v}");
    } else {
        println!("{}: {} episodes from {} shards, {seconds:.1} s", a.out.display(), m.rows, m.shards);
        for (f, k) in &m.by_format {
            println!("    {}={f}: {k}", table::PARTITION_KEY);
        }
    }
    Ok(ExitCode::SUCCESS)
}

/// The target from a folder of episodes, an index directory or a TOML spec.
fn target_of(path: &Path) -> anyhow::Result<(Target, Vec<String>)> {
    if path.is_file() {
        let text = std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
        let t: Target = toml::from_str(&text).with_context(|| format!("{} is not a target spec", path.display()))?;
        return Ok((t, Vec::new()));
    }
    anyhow::ensure!(path.is_dir(), "--target {}: no such file or folder", path.display());
    let rows = if table::parts(path).map(|p| !p.is_empty()).unwrap_or(false) {
        table::read_index(path)?
    } else {
        let derive = Derive::default();
        let found = source::discover(path);
        anyhow::ensure!(!found.is_empty(), "--target {}: no episodes and no index there", path.display());
        let mut rows = Vec::new();
        for f in &found {
            rows.extend(source::rows(f, &derive).map_err(|e| anyhow::anyhow!("target episode: {e}"))?);
        }
        rows
    };
    Ok((Target::of_episodes(&rows), rows.into_iter().map(|r| r.episode_id).collect()))
}

fn retrieve_cmd(a: RetrieveArgs) -> anyhow::Result<ExitCode> {
    let t0 = Instant::now();
    let align: Vec<Dim> =
        a.align.iter().map(|s| Dim::parse(s)).collect::<Result<_, _>>().map_err(anyhow::Error::msg)?;
    let [bx, by, bz] = a.obj_box_m.as_slice() else { bail!("--obj-box-m takes x,y,z") };
    let thresholds = Thresholds { cam_xy_m: a.cam_xy_m, cam_z_m: a.cam_z_m, obj_box_m: [*bx, *by, *bz] };
    let (target, target_ids) = target_of(&a.target)?;
    let missing = target.missing(&align);
    anyhow::ensure!(missing.is_empty(), "cannot align: {}", missing.join("; "));
    let mut rows = table::read_index(&a.index)?;
    if a.exclude_target {
        rows.retain(|r| !target_ids.contains(&r.episode_id));
    }
    let t_read = t0.elapsed().as_secs_f64();
    let mut manifest = retrieve::retrieve(&rows, &target, &align, &thresholds);
    let t_query = t0.elapsed().as_secs_f64() - t_read;
    // The index holds the paths as it was given them (relative to where it ran); a manifest's
    // readers resolve a relative path against the manifest's folder: absolute paths mean the
    // same episodes to both.
    let cwd = std::env::current_dir()?;
    for e in &mut manifest.episodes {
        let p = Path::new(&e.path);
        if p.is_relative() {
            e.path = std::fs::canonicalize(p).unwrap_or_else(|_| cwd.join(p)).to_string_lossy().into_owned();
        }
    }
    if let Some(dir) = a.out.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir)?;
    }
    std::fs::write(&a.out, serde_json::to_string_pretty(&manifest)? + "\n")
        .with_context(|| format!("writing {}", a.out.display()))?;
    if a.json {
        println!(
            "{}",
            serde_json::json!({"manifest": a.out, "funnel": manifest.funnel, "retrieved": manifest.episodes.len(),
                "target": manifest.target, "read_s": t_read, "query_s": t_query})
        );
    } else {
        println!("{} episodes retrieved -> {}", manifest.episodes.len(), a.out.display());
        println!("    {:<10} {:>10}", "stage", "kept");
        for s in &manifest.funnel {
            println!("    {:<10} {:>10}", s.stage, s.kept);
        }
    }
    Ok(ExitCode::SUCCESS)
}

fn pct(sorted: &[f64], p: f64) -> f64 {
    sorted[((sorted.len() as f64 - 1.0) * p).round() as usize]
}

fn bench(a: BenchArgs) -> anyhow::Result<ExitCode> {
    use labrig_dataset::bench;
    anyhow::ensure!(a.episodes >= 1 && a.runs >= 1, "--episodes and --runs must be at least 1");
    let t0 = Instant::now();
    let rows = bench::synthetic(a.episodes, 7);
    let t_gen = t0.elapsed().as_secs_f64();
    let dir = tempfile::tempdir()?;
    let part = dir.path().join(table::part_name(0, 1));
    let t1 = Instant::now();
    table::write_part(&part, &rows, "")?;
    let t_write = t1.elapsed().as_secs_f64();
    let bytes = std::fs::metadata(&part)?.len();
    drop(rows);
    let t2 = Instant::now();
    let rows = table::read_index(dir.path())?;
    let t_read = t2.elapsed().as_secs_f64();
    let t3 = Instant::now();
    let columns = retrieve::Columns::of(&rows);
    let t_columns = t3.elapsed().as_secs_f64();
    let mut results = Vec::new();
    for align in bench::combinations() {
        let (ms, kept, manifest_ms) = bench::time_retrieval(&rows, &columns, &align, a.runs);
        let names: Vec<&str> = align.iter().map(|d| d.name()).collect();
        results.push(serde_json::json!({"align": names.join(","), "p50_ms": pct(&ms, 0.5), "p99_ms": pct(&ms, 0.99),
            "kept": kept, "manifest_ms": manifest_ms}));
    }
    let mut throughput = serde_json::Value::Null;
    if let Some(root) = &a.episodes_root {
        let found = source::discover(root);
        anyhow::ensure!(!found.is_empty(), "{}: no episodes", root.display());
        // The disk's part: reading every file an episode is, byte for byte.
        let t3 = Instant::now();
        let mut read_bytes = 0u64;
        for f in &found {
            for file in source::files_of(f)? {
                read_bytes += std::fs::read(&file)?.len() as u64;
            }
        }
        let t_files = t3.elapsed().as_secs_f64();
        let t4 = Instant::now();
        let derive = Derive::default();
        let ok: usize = found.iter().filter_map(|f| source::rows(f, &derive).ok()).map(|r| r.len()).sum();
        let t_index = t4.elapsed().as_secs_f64();
        // Episodes are rows (an RLDS shard holds many), not the sources found.
        throughput = serde_json::json!({"sources": found.len(), "indexed": ok, "mb": read_bytes as f64 / 1e6,
            "index_s": t_index, "index_episodes_per_s": ok as f64 / t_index,
            "index_mb_per_s": read_bytes as f64 / 1e6 / t_index,
            "read_files_s": t_files, "read_mb_per_s": read_bytes as f64 / 1e6 / t_files});
    }
    let report = serde_json::json!({"episodes": a.episodes, "generate_s": t_gen, "write_s": t_write,
        "parquet_mb": bytes as f64 / 1e6, "read_s": t_read, "columns_s": t_columns, "retrieval": results, "index_throughput": throughput});
    if a.json {
        println!("{report}");
    } else {
        println!(
            "{} synthetic episodes: Parquet {:.1} MB, written in {t_write:.1} s, read back in {t_read:.1} s, \
             columns for retrieval in {t_columns:.2} s",
            a.episodes,
            bytes as f64 / 1e6
        );
        println!("    {:<40} {:>9} {:>9} {:>9} {:>12}", "align", "p50 ms", "p99 ms", "kept", "manifest ms");
        for r in &results {
            println!(
                "    {:<40} {:>9.2} {:>9.2} {:>9} {:>12.1}",
                r["align"].as_str().unwrap_or(""),
                r["p50_ms"].as_f64().unwrap_or(0.0),
                r["p99_ms"].as_f64().unwrap_or(0.0),
                r["kept"],
                r["manifest_ms"].as_f64().unwrap_or(0.0)
            );
        }
        if !throughput.is_null() {
            let t = &throughput;
            let f = |k: &str| t[k].as_f64().unwrap_or(0.0);
            println!(
                "index throughput: {} episodes from {} sources, {:.1} MB: {:.0} episodes/s, {:.0} MB/s indexing \
                 ({:.2} s) against {:.0} MB/s merely reading the files ({:.2} s, read first: a cold cache)",
                t["indexed"],
                t["sources"],
                f("mb"),
                f("index_episodes_per_s"),
                f("index_mb_per_s"),
                f("index_s"),
                f("read_mb_per_s"),
                f("read_files_s")
            );
        }
    }
    Ok(ExitCode::SUCCESS)
}

fn stats(a: StatsArgs) -> anyhow::Result<ExitCode> {
    use labrig_dataset::stats;
    let rows = table::read_index(&a.index)?;
    let manifest = match &a.target {
        None => None,
        Some(t) => {
            let align: Vec<Dim> =
                a.align.iter().map(|s| Dim::parse(s)).collect::<Result<_, _>>().map_err(anyhow::Error::msg)?;
            let (target, _) = target_of(t)?;
            let missing = target.missing(&align);
            anyhow::ensure!(missing.is_empty(), "cannot align: {}", missing.join("; "));
            Some(retrieve::retrieve(&rows, &target, &align, &Thresholds::default()))
        }
    };
    let by_bin = stats::bins(&rows);
    let by_object = stats::counts(&rows, |r| vec![r.object.as_deref()]);
    let by_primitive = stats::counts(&rows, |r| vec![r.primitive.as_deref()]);
    let by_format = stats::counts(&rows, |r| vec![Some(r.source_format.as_str())]);
    let with_object = rows.iter().filter(|r| r.object_position.is_some()).count();
    if let Some(p) = &a.plot {
        stats::plot(&rows, manifest.as_ref(), p).map_err(anyhow::Error::msg)?;
    }
    if a.json {
        println!(
            "{}",
            serde_json::json!({"episodes": rows.len(), "with_object_position": with_object, "camera_bins": by_bin,
                "objects": by_object, "primitives": by_primitive, "formats": by_format,
                "funnel": manifest.as_ref().map(|m| &m.funnel), "plot": a.plot})
        );
    } else {
        println!("{} episodes ({with_object} with an object position)", rows.len());
        for (name, map) in
            [("format", &by_format), ("camera bin", &by_bin), ("object", &by_object), ("primitive", &by_primitive)]
        {
            println!("    {name:<11} {}", map.iter().map(|(k, v)| format!("{k} {v}")).collect::<Vec<_>>().join(", "));
        }
        if let Some(m) = &manifest {
            println!("    {:<10} {:>10}", "stage", "kept");
            for s in &m.funnel {
                println!("    {:<10} {:>10}", s.stage, s.kept);
            }
        }
        if let Some(p) = &a.plot {
            println!("    plot: {}", p.display());
        }
    }
    Ok(ExitCode::SUCCESS)
}
