//! `labrig-calibrate` (run as `labrig calibrate ...`): camera calibration.
//!
//! - `labrig calibrate --sim [--scene S --seed N] --camera ext1|...|all [--json]`: the simulated
//!   rig end to end (capture in `labrig-sim calib-capture`, solve here), and the errors against
//!   the sim's truth;
//! - `labrig calibrate --rig <launch config> --camera ext1|...|all [--json]`: a live rig (real,
//!   or simulated behind the same topics) drives its arm over the pose set and takes the views
//!   (`labrig calibrate capture`, in the `labrig` CLI, which talks to the rig), solved here;
//! - `labrig calibrate board --out board.png`: the board's print at scale;
//! - `labrig calibrate solve <capture dir>`: a capture to `calibration/<rig>/<camera>.json`;
//! - `labrig calibrate check --sim|--rig <launch config> --camera C`: a few fresh views against
//!   the stored calibration.

use anyhow::{Context, bail};
use clap::{Args, Parser, Subcommand};
use labrig_calibration::run::{self, SolveOptions, SolveReport};
use labrig_calibration::solve::{self, HandEyeMethod, Pinhole};
use labrig_calibration::{board, figures};
use labrig_episode::progress;
use labrig_msgs::calibration::{BoardSpec, CalibrationFile};
use std::path::{Path, PathBuf};
use std::process::{Command, ExitCode};
use std::time::Instant;

#[derive(Debug, Parser)]
#[command(name = "labrig calibrate", about = "Camera calibration: ChArUco board + hand-eye (OpenCV 4.6)")]
#[command(args_conflicts_with_subcommands = true)]
struct Cli {
    #[command(subcommand)]
    cmd: Option<Cmd>,
    #[command(flatten)]
    run: RunArgs,
}

#[derive(Debug, Subcommand)]
enum Cmd {
    /// Write the board's print at scale (PNG with its resolution, or any image OpenCV writes).
    Board(BoardArgs),
    /// Solve a capture folder (capture.json + views) into a calibration file.
    Solve(SolveArgs),
    /// Take a few fresh views and report the drift against the stored calibration.
    Check(Box<CheckArgs>),
}

/// The board and how to solve (shared by every command).
#[derive(Debug, Clone, Args)]
struct SolveFlags {
    /// Hand-eye method of the closed-form solution.
    #[arg(long, value_enum, default_value_t = HandEyeMethod::Daniilidis)]
    method: HandEyeMethod,
    /// Keep the closed-form solution (no refinement by reprojection).
    #[arg(long)]
    no_refine: bool,
    /// Calibrate the intrinsics from the views even where the camera has its own.
    #[arg(long)]
    intrinsics: bool,
    /// Seed of DROID's 70/30 check.
    #[arg(long, default_value_t = 0)]
    split_seed: u64,
}

impl SolveFlags {
    fn options(&self) -> SolveOptions {
        SolveOptions {
            method: self.method,
            refine: !self.no_refine,
            intrinsics: self.intrinsics,
            seed: self.split_seed,
            ..SolveOptions::default()
        }
    }
}

/// The simulated rig a capture is taken on.
#[derive(Debug, Clone, Args)]
struct SimFlags {
    /// Scene spec (TOML) or built-in scene name (default pick_place).
    #[arg(long)]
    scene: Option<PathBuf>,
    #[arg(long, default_value_t = 0)]
    seed: u64,
    #[arg(long, env = "LABRIG_SIM_ASSETS")]
    assets: Option<PathBuf>,
    /// Views per camera (DROID takes ~60).
    #[arg(long, default_value_t = 60)]
    views: usize,
    /// The board (TOML with squares_x, squares_y, square_m, marker_m, dictionary); default DROID's.
    #[arg(long)]
    board: Option<PathBuf>,
    /// The board the sim prints, if not the one the solver is told (a print that does not
    /// match its spec).
    #[arg(long, hide = true)]
    printed_board: Option<PathBuf>,
    /// Where views are written (default: a temporary folder, removed unless --keep-views).
    #[arg(long)]
    work: Option<PathBuf>,
    #[arg(long)]
    keep_views: bool,
}

/// How a live rig's views are taken (`--rig`).
#[derive(Debug, Clone, Args)]
struct RigFlags {
    /// Where the pose set is centred: `camera` (facing the camera's published pose, holding the
    /// board where the rig says it is), `here` (the arm's pose now: put the board in view
    /// first), or `auto` (camera where the rig publishes both poses, else here).
    #[arg(long, default_value = "auto")]
    start: String,
    /// DDS domain (default: the launch config's).
    #[arg(long)]
    domain_id: Option<u16>,
}

#[derive(Debug, Args)]
struct RunArgs {
    /// Calibrate the simulated rig in one process (the sim renders the board; no nodes).
    #[arg(long, conflicts_with = "rig")]
    sim: bool,
    /// Calibrate a live rig: a launch config (real, or simulated behind the same topics), whose
    /// hardware nodes are started and whose arm takes the views.
    #[arg(long)]
    rig: Option<PathBuf>,
    #[command(flatten)]
    rig_flags: RigFlags,
    /// ext1, ext2, wrist, rs1, rs2 or all.
    #[arg(long, default_value = "all")]
    camera: String,
    #[command(flatten)]
    sim_flags: SimFlags,
    #[command(flatten)]
    solve: SolveFlags,
    /// Where calibrations are written: <out-dir>/<camera>.json (default calibration/<rig name>).
    #[arg(long)]
    out_dir: Option<PathBuf>,
    /// The rig's name (the folder under calibration/) for `--sim`; a launch config names its own.
    #[arg(long, default_value = "sim")]
    rig_name: String,
    /// One JSON object on stdout instead of text.
    #[arg(long)]
    json: bool,
}

#[derive(Debug, Args)]
struct BoardArgs {
    /// Output: .pdf (one page at true size), .png (with its physical resolution and a 5 mm
    /// margin) or another image format.
    #[arg(long)]
    out: PathBuf,
    /// The board (TOML); default DROID's.
    #[arg(long)]
    board: Option<PathBuf>,
    /// Resolution of the print.
    #[arg(long, default_value_t = 300.0)]
    dpi: f64,
}

#[derive(Debug, Args)]
struct SolveArgs {
    /// The capture folder (capture.json and its images).
    capture: PathBuf,
    /// The calibration file to write (default calibration/<rig>/<camera>.json).
    #[arg(long)]
    out: Option<PathBuf>,
    #[command(flatten)]
    solve: SolveFlags,
    /// Also write <camera>_views.png and <camera>_residuals.png in this folder.
    #[arg(long)]
    figures: Option<PathBuf>,
    #[arg(long)]
    json: bool,
}

#[derive(Debug, Args)]
struct CheckArgs {
    /// Check the simulated rig.
    #[arg(long, conflicts_with = "rig")]
    sim: bool,
    /// Check a live rig (a launch config).
    #[arg(long)]
    rig: Option<PathBuf>,
    #[command(flatten)]
    rig_flags: RigFlags,
    #[arg(long)]
    camera: String,
    /// The stored calibration (default calibration/<rig name>/<camera>.json).
    #[arg(long)]
    calibration: Option<PathBuf>,
    /// The rig's name (the folder under calibration/).
    #[arg(long, default_value = "sim")]
    rig_name: String,
    #[command(flatten)]
    sim_flags: SimFlags,
    /// Move the camera by dx,dy,dz (m, base frame) before the views: a knocked camera.
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true)]
    move_camera: Option<Vec<f64>>,
    /// Drift beyond these fails the check (exit 3).
    #[arg(long, default_value_t = 5.0)]
    max_drift_mm: f64,
    #[arg(long, default_value_t = 0.5)]
    max_drift_deg: f64,
    #[arg(long)]
    json: bool,
}

/// Exit status of a check that found drift.
const EXIT_DRIFT: u8 = 3;
/// Exit status of a calibration that failed acceptance.
const EXIT_REJECTED: u8 = 4;

fn main() -> ExitCode {
    let cli = Cli::parse();
    if labrig_msgs::parse_only() {
        return ExitCode::SUCCESS;
    }
    let result = match cli.cmd {
        Some(Cmd::Board(a)) => board_cmd(a),
        Some(Cmd::Solve(a)) => solve_cmd(a),
        Some(Cmd::Check(a)) => check_cmd(*a),
        None => run_cmd(cli.run),
    };
    match result {
        Ok(code) => code,
        Err(e) => {
            eprintln!("labrig calibrate: {e:#}");
            if e.chain().any(|c| matches!(c.downcast_ref(), Some(labrig_calibration::CalibError::Rejected { .. }))) {
                ExitCode::from(EXIT_REJECTED)
            } else {
                ExitCode::FAILURE
            }
        }
    }
}

fn load_board(path: Option<&Path>) -> anyhow::Result<BoardSpec> {
    let spec = match path {
        None => BoardSpec::droid(),
        Some(p) => {
            let text = std::fs::read_to_string(p).with_context(|| format!("reading {}", p.display()))?;
            toml::from_str(&text).with_context(|| format!("{} is not a board spec", p.display()))?
        }
    };
    spec.validate().map_err(|e| anyhow::anyhow!("board: {e}"))?;
    Ok(spec)
}

fn board_cmd(a: BoardArgs) -> anyhow::Result<ExitCode> {
    let spec = load_board(a.board.as_deref())?;
    let px = (a.dpi / 0.0254 * spec.square_m).round().max(8.0) as u32;
    let ext = a.out.extension().and_then(|e| e.to_str()).map(str::to_ascii_lowercase);
    if ext.as_deref() == Some("pdf") {
        board::write_pdf(&spec, px, &a.out)?;
        let [w, h] = spec.size_m();
        println!(
            "{}: one page of {:.0} x {:.0} mm (the board and a 5 mm margin); print at 100% (actual size), then \
             measure a square: it must be {} mm",
            a.out.display(),
            w * 1e3 + 10.0,
            h * 1e3 + 10.0,
            spec.square_m * 1e3
        );
    } else if ext.as_deref() == Some("png") {
        let dpi = board::write_png(&spec, px, true, &a.out)?;
        let [w, h] = spec.size_m();
        println!(
            "{}: {} x {} squares of {} mm, {} mm markers, {}; {:.0} x {:.0} mm at {dpi:.0} dpi (print at 100%, \
             then measure a square: it must be {} mm)",
            a.out.display(),
            spec.squares_x,
            spec.squares_y,
            spec.square_m * 1e3,
            spec.marker_m * 1e3,
            spec.dictionary,
            w * 1e3,
            h * 1e3,
            spec.square_m * 1e3
        );
    } else {
        board::write_image(&spec, px, &a.out)?;
        println!("{}", a.out.display());
    }
    Ok(ExitCode::SUCCESS)
}

fn write_figures(
    dir: &Path,
    capture: &Path,
    file: &CalibrationFile,
    fits: &[solve::ViewFit],
) -> anyhow::Result<Vec<PathBuf>> {
    std::fs::create_dir_all(dir)?;
    let views = dir.join(format!("{}_views.png", file.camera));
    let residuals = dir.join(format!("{}_residuals.png", file.camera));
    if let Some(best) = fits.iter().max_by_key(|f| f.detection.corners.len()) {
        let cam = Pinhole::of(&file.intrinsics);
        figures::overlay(
            capture,
            best,
            &cam,
            file.mount,
            &solve::iso_of(&file.pose),
            &solve::iso_of(&file.board_pose),
            &views,
        )?;
    }
    figures::residual_plot(file, &residuals)?;
    Ok(vec![views, residuals])
}

fn report_text(r: &SolveReport, file: &CalibrationFile, path: &Path, seconds: f64) -> String {
    let mut s = format!(
        "{} ({:?}): {} of {} views used, {:.3} px RMS, {} -> {}; 70/30 check {:.2} mm / {:.3} deg; {:.1} s -> {}\n",
        r.camera,
        file.mount,
        r.views_used,
        r.views_captured,
        r.rms_px,
        file.parent_frame,
        file.child_frame,
        file.check.mean_position_error_mm,
        file.check.mean_rotation_error_deg,
        seconds,
        path.display()
    );
    for (why, n) in &r.dropped {
        s += &format!("    dropped {n}: {why}\n");
    }
    if r.unreachable_poses > 0 {
        s += &format!("    {} poses of the set were unreachable (skipped)\n", r.unreachable_poses);
    }
    if let (Some(mm), Some(deg)) = (r.position_error_mm, r.rotation_error_deg) {
        s += &format!("    against the sim's truth: {mm:.3} mm, {deg:.4} deg ({})\n", file.method);
        for m in &r.methods {
            s += &format!(
                "      {:10} closed form {:7.3} mm {:7.4} deg   refined {:7.3} mm {:7.4} deg\n",
                m.method, m.closed_form_mm, m.closed_form_deg, m.refined_mm, m.refined_deg
            );
        }
    }
    s
}

fn solve_cmd(a: SolveArgs) -> anyhow::Result<ExitCode> {
    let t0 = Instant::now();
    let cap = run::read_capture(&a.capture)?;
    let bar = progress::bar("{bar:30} {pos}/{len} views detected", cap.views.len() as u64, a.json);
    let (file, report, fits) = run::solve_capture(&a.capture, &a.solve.options(), &bar)?;
    bar.finish_and_clear();
    let out =
        a.out.unwrap_or_else(|| PathBuf::from("calibration").join(&file.rig).join(format!("{}.json", file.camera)));
    run::write_calibration(&out, &file)?;
    let figs = match &a.figures {
        Some(dir) => write_figures(dir, &a.capture, &file, &fits)?,
        None => Vec::new(),
    };
    if a.json {
        println!("{}", serde_json::json!({"calibration": out, "report": report, "figures": figs}));
    } else {
        print!("{}", report_text(&report, &file, &out, t0.elapsed().as_secs_f64()));
    }
    Ok(ExitCode::SUCCESS)
}

/// `labrig-sim`, built beside this program.
fn sim_program() -> anyhow::Result<PathBuf> {
    let exe = std::env::current_exe().context("locating labrig-calibrate")?;
    let sim = exe.with_file_name("labrig-sim");
    if !sim.exists() {
        bail!(
            "{} is missing: build the workspace (cargo build) so labrig-sim sits beside labrig-calibrate",
            sim.display()
        );
    }
    Ok(sim)
}

/// Runs `labrig-sim calib-capture` for one camera into `out`.
fn sim_capture(
    f: &SimFlags,
    work: &Work,
    camera: &str,
    views: usize,
    out: &Path,
    (rig, move_camera): (&str, Option<&[f64]>),
    quiet: bool,
) -> anyhow::Result<()> {
    let mut cmd = Command::new(sim_program()?);
    // Mesa's llvmpipe renders on every core by default; one leaves the rest of the machine
    // (a rig, other tests) its share. An LP_NUM_THREADS given by the caller wins.
    if std::env::var_os("LP_NUM_THREADS").is_none() {
        cmd.env("LP_NUM_THREADS", "1");
    }
    cmd.arg("calib-capture").args([
        "--camera",
        camera,
        "--seed",
        &f.seed.to_string(),
        "--views",
        &views.to_string(),
        "--rig",
        rig,
    ]);
    work.capture_args(&mut cmd, out, move_camera)?;
    if let Some(s) = &f.scene {
        cmd.arg("--scene").arg(s);
    }
    if let Some(a) = &f.assets {
        cmd.arg("--assets").arg(a);
    }
    if quiet {
        cmd.arg("--quiet");
    }
    let status = cmd.status().context("running labrig-sim calib-capture")?;
    if !status.success() {
        bail!("labrig-sim calib-capture for `{camera}` failed ({status})");
    }
    Ok(())
}

/// The work folder, the board's print and its spec as JSON for the sim.
struct Work {
    dir: PathBuf,
    temporary: bool,
    print: PathBuf,
    /// The spec the capture records (the one the solver is told).
    board_json: PathBuf,
    /// The print's size when it is not that board (`--printed-board`).
    print_size_m: Option<[f64; 2]>,
}

impl Work {
    /// What both captures take: the print, the board, the output, a camera moved, the print's
    /// size where it is not the board's.
    fn capture_args(&self, cmd: &mut Command, out: &Path, move_camera: Option<&[f64]>) -> anyhow::Result<()> {
        cmd.arg("--print").arg(&self.print).arg("--board").arg(&self.board_json).arg("--out").arg(out);
        if let Some(m) = move_camera {
            let [x, y, z] = m else { bail!("--move-camera takes dx,dy,dz (3 numbers), not {m:?}") };
            cmd.arg(format!("--move-camera={x},{y},{z}"));
        }
        if let Some([w, h]) = self.print_size_m {
            cmd.arg(format!("--print-size-m={w},{h}"));
        }
        Ok(())
    }

    fn new(f: &SimFlags, spec: &BoardSpec) -> anyhow::Result<Work> {
        let (dir, temporary) = match &f.work {
            Some(d) => (d.clone(), false),
            None => (std::env::temp_dir().join(format!("labrig-calibrate-{}", std::process::id())), !f.keep_views),
        };
        std::fs::create_dir_all(&dir).with_context(|| format!("creating {}", dir.display()))?;
        // The print the sim carries: 100 px per square, edge to edge.
        let printed = match &f.printed_board {
            Some(p) => load_board(Some(p))?,
            None => spec.clone(),
        };
        let print = dir.join("board.png");
        board::write_png(&printed, 100, false, &print)?;
        let board_json = dir.join("board.json");
        std::fs::write(&board_json, serde_json::to_string(spec)?)?;
        let print_size_m = (printed != *spec).then(|| printed.size_m());
        Ok(Work { dir, temporary, print, board_json, print_size_m })
    }
}

impl Drop for Work {
    fn drop(&mut self) {
        if self.temporary {
            let _ = std::fs::remove_dir_all(&self.dir);
        }
    }
}

fn cameras(arg: &str) -> anyhow::Result<Vec<&'static str>> {
    let all = labrig_msgs::rig::RIG_CAMERAS;
    if arg == "all" {
        return Ok(all.to_vec());
    }
    arg.split(',')
        .map(|c| {
            all.iter()
                .copied()
                .find(|a| *a == c)
                .ok_or_else(|| anyhow::anyhow!("unknown camera `{c}` (the rig's cameras: {}, or all)", all.join(", ")))
        })
        .collect()
}

/// Where a calibration's views come from.
enum Source<'a> {
    /// `labrig-sim calib-capture`: the sim in one process.
    Sim,
    /// `labrig calibrate capture`: a live rig from its launch config.
    Rig(&'a Path, &'a RigFlags),
}

impl Source<'_> {
    fn of<'a>(sim: bool, rig: Option<&'a Path>, flags: &'a RigFlags) -> anyhow::Result<Source<'a>> {
        match (sim, rig) {
            (true, _) => Ok(Source::Sim),
            (false, Some(r)) => Ok(Source::Rig(r, flags)),
            (false, None) => bail!(
                "say where the views come from: `--rig <launch config>` (a live rig, real or simulated), `--sim` \
                 (the simulated rig in one process), or solve views taken by hand with `labrig calibrate solve <capture dir>`"
            ),
        }
    }

    /// The rig's name: a launch config's `[rig] name`, else `name`.
    fn rig_name(&self, name: &str) -> anyhow::Result<String> {
        let Source::Rig(path, _) = self else { return Ok(name.to_owned()) };
        let text = std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
        let v: toml::Table =
            toml::from_str(&text).with_context(|| format!("{} is not a launch config", path.display()))?;
        v.get("rig")
            .and_then(|r| r.get("name"))
            .and_then(|n| n.as_str())
            .map(str::to_owned)
            .with_context(|| format!("{} has no [rig] name", path.display()))
    }

    /// Takes `views` views of `camera` into `out`.
    #[allow(clippy::too_many_arguments)] // one capture's settings, passed once
    fn capture(
        &self,
        f: &SimFlags,
        work: &Work,
        camera: &str,
        views: usize,
        out: &Path,
        (rig_name, move_camera): (&str, Option<&[f64]>),
        quiet: bool,
    ) -> anyhow::Result<()> {
        match self {
            Source::Sim => sim_capture(f, work, camera, views, out, (rig_name, move_camera), quiet),
            Source::Rig(rig, flags) => rig_capture(rig, flags, work, camera, views, out, move_camera, quiet),
        }
    }
}

/// Runs `labrig calibrate capture` (the `labrig` CLI beside this program) for one camera.
#[allow(clippy::too_many_arguments)] // one capture's settings, passed once
fn rig_capture(
    rig: &Path,
    flags: &RigFlags,
    work: &Work,
    camera: &str,
    views: usize,
    out: &Path,
    move_camera: Option<&[f64]>,
    quiet: bool,
) -> anyhow::Result<()> {
    let exe = std::env::current_exe().context("locating labrig-calibrate")?.with_file_name("labrig");
    if !exe.exists() {
        bail!("{} is missing: build the workspace (cargo build) so labrig sits beside labrig-calibrate", exe.display());
    }
    let mut cmd = Command::new(exe);
    if std::env::var_os("LP_NUM_THREADS").is_none() {
        cmd.env("LP_NUM_THREADS", "1");
    }
    cmd.args(["calibrate", "capture", "--camera", camera, "--views", &views.to_string(), "--start", &flags.start])
        .arg("--rig")
        .arg(rig);
    work.capture_args(&mut cmd, out, move_camera)?;
    if let Some(d) = flags.domain_id {
        cmd.args(["--domain-id", &d.to_string()]);
    }
    if quiet {
        cmd.arg("--json").stdout(std::process::Stdio::null());
    }
    let status = cmd.status().context("running labrig calibrate capture")?;
    if !status.success() {
        bail!("taking the views of `{camera}` on {} failed ({status})", rig.display());
    }
    Ok(())
}

fn run_cmd(a: RunArgs) -> anyhow::Result<ExitCode> {
    let source = Source::of(a.sim, a.rig.as_deref(), &a.rig_flags)?;
    let rig_name = source.rig_name(&a.rig_name)?;
    let spec = load_board(a.sim_flags.board.as_deref())?;
    let cams = cameras(&a.camera)?;
    let work = Work::new(&a.sim_flags, &spec)?;
    let out_dir = a.out_dir.clone().unwrap_or_else(|| PathBuf::from("calibration").join(&rig_name));
    let t_all = Instant::now();
    let mut rows = Vec::new();
    let mut failed = Vec::new();
    for cam in cams {
        let t0 = Instant::now();
        let dir = work.dir.join(cam);
        if !a.json {
            let on = match &source {
                Source::Sim => "in the sim".to_owned(),
                Source::Rig(r, _) => format!("on {}", r.display()),
            };
            eprintln!("{cam}: capturing {} views {on}", a.sim_flags.views);
        }
        source.capture(&a.sim_flags, &work, cam, a.sim_flags.views, &dir, (&rig_name, None), a.json)?;
        let t_capture = t0.elapsed().as_secs_f64();
        let bar = progress::bar(
            &format!("{{bar:30}} {{pos}}/{{len}} {cam} views detected"),
            a.sim_flags.views as u64,
            a.json,
        );
        let solved = run::solve_capture(&dir, &a.solve.options(), &bar);
        bar.finish_and_clear();
        match solved {
            Ok((file, report, fits)) => {
                let path = out_dir.join(format!("{cam}.json"));
                run::write_calibration(&path, &file)?;
                let figs = write_figures(&out_dir, &dir, &file, &fits)?;
                let seconds = t0.elapsed().as_secs_f64();
                if !a.json {
                    print!("{}", report_text(&report, &file, &path, seconds));
                }
                rows.push(serde_json::json!({
                    "camera": cam, "ok": true, "calibration": path, "figures": figs, "report": report,
                    "capture_s": t_capture, "total_s": seconds, "droid_extrinsics": file.droid_extrinsics,
                    "check": file.check,
                }));
            }
            Err(e) => {
                if !a.json {
                    println!("{cam}: {e}");
                }
                rows.push(serde_json::json!({"camera": cam, "ok": false, "error": e.to_string()}));
                failed.push(cam);
            }
        }
    }
    let total = t_all.elapsed().as_secs_f64();
    if a.json {
        println!("{}", serde_json::json!({"rig": rig_name, "cameras": rows, "total_s": total}));
    } else {
        println!("{} cameras in {total:.0} s; calibrations in {}", rows.len(), out_dir.display());
    }
    Ok(if failed.is_empty() { ExitCode::SUCCESS } else { ExitCode::from(EXIT_REJECTED) })
}

fn check_cmd(a: CheckArgs) -> anyhow::Result<ExitCode> {
    let source = Source::of(a.sim, a.rig.as_deref(), &a.rig_flags)?;
    let rig_name = source.rig_name(&a.rig_name)?;
    let cam = *cameras(&a.camera)?.first().context("one camera")?;
    let path = a
        .calibration
        .clone()
        .unwrap_or_else(|| PathBuf::from("calibration").join(&rig_name).join(format!("{cam}.json")));
    let stored = run::read_calibration(&path).with_context(|| format!("the stored calibration of `{cam}`"))?;
    let work = Work::new(&a.sim_flags, &stored.board)?;
    let dir = work.dir.join(format!("{cam}-check"));
    let views = a.sim_flags.views.min(12);
    source.capture(&a.sim_flags, &work, cam, views, &dir, (&rig_name, a.move_camera.as_deref()), a.json)?;
    let cap = run::read_capture(&dir)?;
    let detector = labrig_calibration::detect::Detector::new(&stored.board)?;
    let bar = progress::bar("{bar:30} {pos}/{len} views detected", cap.views.len() as u64, a.json);
    let detections = run::detect_all(&dir, &cap, &detector, &bar)?;
    bar.finish_and_clear();
    let x = solve::iso_of(&stored.pose);
    let y = solve::iso_of(&stored.board_pose);
    let cam_model = Pinhole::of(&stored.intrinsics);
    // Each view alone gives the camera's pose through the stored board mount: X_i = A_i Y B_i^-1.
    let mut poses = Vec::new();
    let mut rms = Vec::new();
    for (v, d) in cap.views.iter().zip(detections) {
        let tcp = solve::iso_of(&v.tcp);
        if let Ok(fit) = solve::fit_view(&detector, &stored.intrinsics, 0, v.image.clone(), tcp, d)? {
            rms.push(solve::view_rms(&cam_model, stored.mount, &fit, &x, &y));
            let a_i = match stored.mount {
                labrig_msgs::calibration::Mount::EyeToHand => fit.tcp,
                labrig_msgs::calibration::Mount::EyeInHand => fit.tcp.inverse(),
            };
            poses.push(a_i * y * fit.board.inverse());
        }
    }
    if poses.len() < 3 {
        bail!("only {} of {} check views show the board; cannot check `{cam}`", poses.len(), cap.views.len());
    }
    let (mut mm, mut deg) = (0.0f64, 0.0f64);
    for p in &poses {
        let (d_mm, d_deg) = solve::pose_difference(p, &x);
        mm += d_mm;
        deg += d_deg;
    }
    let n = poses.len() as f64;
    let (mm, deg) = (mm / n, deg / n);
    let rms_px = (rms.iter().map(|r| r * r).sum::<f64>() / rms.len() as f64).sqrt();
    let age_s = stored.age_s(chrono::Utc::now().timestamp());
    let moved = mm > a.max_drift_mm || deg > a.max_drift_deg;
    if a.json {
        println!(
            "{}",
            serde_json::json!({"camera": cam, "views": poses.len(), "drift_mm": mm, "drift_deg": deg,
                "rms_px": rms_px, "age_s": age_s, "calibrated": stored.date, "moved": moved})
        );
    } else {
        println!(
            "{cam}: {} views, drift {mm:.2} mm / {deg:.3} deg from the calibration of {} ({age_s} s old), \
             {rms_px:.2} px RMS through it: {}",
            poses.len(),
            stored.date,
            if moved { "MOVED: calibrate again" } else { "ok" }
        );
    }
    Ok(if moved { ExitCode::from(EXIT_DRIFT) } else { ExitCode::SUCCESS })
}
