//! `labrig bench record`: what recording an episode costs. A synthetic rig at 20 Hz — five
//! 128x128 cameras (a moving pattern, JPEG-encoded as the recorder does), /rig/step,
//! /arm/state at 40 Hz — written with labrig-recorder's EpisodeWriter, either in real
//! time (`--realtime`, as a rig would) or as fast as it goes. Prints a JSON line each time a
//! chunk closes (what a crash can no longer take) and the totals: MB/s, CPU, JPEG time; with
//! `--progress`, a line per step written as well.

use clap::Args;
use labrig_episode::bag::Reliability;
use labrig_episode::{EpisodeMetadata, EpisodeWriter, Outcome, RigIdentity, episode_dir};
use labrig_msgs::Nanos;
use labrig_msgs::rig::{CameraFrameRef, RIG_CAMERAS, RobotState, Step};
use labrig_msgs::sensor_msgs::CompressedImage;
use labrig_msgs::std_msgs::Header;
use labrig_msgs::topics;
use serde_json::json;
use std::path::PathBuf;
use std::process::ExitCode;
use std::time::{Duration, Instant};

#[derive(Debug, Args)]
pub struct RecordArgs {
    /// Seconds of rig time to record.
    #[arg(long, default_value_t = 10.0)]
    seconds: f64,
    /// Pace the ticks at 20 Hz of wall time (else as fast as the writer goes).
    #[arg(long)]
    realtime: bool,
    /// Camera image size (square).
    #[arg(long, default_value_t = 128)]
    size: u16,
    /// Where the episode goes (DROID layout below it); default: a temporary directory.
    #[arg(long)]
    out: Option<PathBuf>,
    #[arg(long)]
    json: bool,
    /// Also print `{"written": n, "stamp_ns": t}` after each step the writer took (n steps so
    /// far, the last one stamped t): what a crash test measures its loss against.
    #[arg(long)]
    progress: bool,
}

fn now_ns() -> i64 {
    std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).unwrap_or_default().as_nanos() as i64
}

pub fn run(a: RecordArgs) -> anyhow::Result<ExitCode> {
    anyhow::ensure!(a.seconds > 0.0 && a.seconds <= 3600.0, "--seconds must be in (0, 3600]");
    anyhow::ensure!((16..=1024).contains(&a.size), "--size must be 16..=1024");
    let tmp;
    let root = match &a.out {
        Some(p) => p.clone(),
        None => {
            tmp = tempdir()?;
            tmp.clone()
        }
    };
    let t0 = now_ns();
    let meta = EpisodeMetadata::new(&RigIdentity::default(), "bench", "record a synthetic episode", Nanos(t0));
    let dir = episode_dir(&root, Outcome::Success, Nanos(t0));
    let mut w = EpisodeWriter::create(&dir, meta)?;
    println!("{}", json!({ "episode": dir }));
    let ticks = (a.seconds * 20.0).round() as u64;
    let n = a.size as usize;
    let mut rgb = vec![0u8; n * n * 3];
    let (mut jpeg_us, mut jpeg_bytes) = (Vec::new(), 0u64);
    let cpu0 = labrig_runtime::bench::process_cpu_seconds();
    let wall = Instant::now();
    let mut next = Instant::now();
    let mut closed = 0;
    for k in 0..ticks {
        let t = if a.realtime { now_ns() } else { t0 + k as i64 * 50_000_000 };
        let header = |frame: &str| Header { stamp: Nanos(t).into(), frame_id: frame.into() };
        let mut refs = Vec::new();
        for (c, cam) in RIG_CAMERAS.iter().enumerate() {
            for (i, px) in rgb.iter_mut().enumerate() {
                let (x, y) = ((i / 3) % n, (i / 3) / n);
                *px = ((x + y + k as usize * 3 + c * 40 + (i % 3) * 60) % 256) as u8;
            }
            let j0 = Instant::now();
            let data = labrig_episode::jpeg::encode_rgb(&rgb, a.size, a.size, 90).map_err(anyhow::Error::msg)?;
            jpeg_us.push(j0.elapsed().as_secs_f64() * 1e6);
            jpeg_bytes += data.len() as u64;
            let img = CompressedImage { header: header(&format!("{cam}_optical")), format: "jpeg".into(), data };
            w.write(&topics::camera_image(cam), &img, Nanos(t), Nanos(t), Reliability::BestEffort)?;
            refs.push(CameraFrameRef {
                camera_id: (*cam).into(),
                sequence: k,
                capture_ns: t,
                arrival_ns: t,
                ..Default::default()
            });
        }
        for j in 0..2 {
            let ts = t + j * 25_000_000;
            let s = RobotState { header: header("base"), joint_positions: [k as f64 * 1e-3; 7], ..Default::default() };
            w.write(topics::ARM_STATE.name, &s, Nanos(ts), Nanos(ts), Reliability::Reliable)?;
        }
        let step = Step {
            header: header("base"),
            step_index: k,
            cameras: refs,
            action_source: Step::SOURCE_SCRIPTED,
            ..Default::default()
        };
        w.write(topics::RIG_STEP.name, &step, Nanos(t), Nanos(t), Reliability::Reliable)?;
        if a.progress {
            println!("{}", json!({ "written": k + 1, "stamp_ns": t }));
        }
        if w.closed_chunks() != closed {
            closed = w.closed_chunks();
            println!("{}", json!({ "closed_chunks": closed, "steps": k, "messages": w.messages() }));
        }
        if a.realtime {
            next += Duration::from_millis(50);
            std::thread::sleep(next.saturating_duration_since(Instant::now()));
        }
    }
    w.metadata_mut().trajectory_length = ticks;
    w.metadata_mut().success = Some(true);
    let summary = w.finish()?;
    let wall_s = wall.elapsed().as_secs_f64();
    let cpu_s = labrig_runtime::bench::process_cpu_seconds() - cpu0;
    jpeg_us.sort_by(f64::total_cmp);
    let p = |q: f64| jpeg_us[((jpeg_us.len() - 1) as f64 * q).round() as usize];
    let mb = summary.bytes as f64 / 1e6;
    let report = json!({
        "steps": ticks, "messages": summary.messages, "file_mb": mb, "wall_s": wall_s,
        "write_mb_per_s": mb / wall_s, "cpu_s": cpu_s, "cpu_share_of_one_core": cpu_s / wall_s,
        "rig_seconds": a.seconds, "realtime_factor": a.seconds / wall_s,
        "jpeg_p50_us": p(0.5), "jpeg_p99_us": p(0.99), "jpeg_mean_bytes": jpeg_bytes as f64 / jpeg_us.len() as f64,
        "path": summary.path,
    });
    if a.json {
        println!("{report}");
    } else {
        println!(
            "recorded {} steps ({} messages, {:.1} MB) in {:.2} s: {:.1} MB/s, {:.0}x real time, CPU {:.0}% of a core; JPEG {:.0} B/frame, p50 {:.0} us, p99 {:.0} us\n{}",
            ticks,
            summary.messages,
            mb,
            wall_s,
            mb / wall_s,
            a.seconds / wall_s,
            100.0 * cpu_s / wall_s,
            report["jpeg_mean_bytes"].as_f64().unwrap_or(0.0),
            p(0.5),
            p(0.99),
            summary.path.display()
        );
    }
    Ok(ExitCode::SUCCESS)
}

fn tempdir() -> anyhow::Result<PathBuf> {
    let p = std::env::temp_dir().join(format!("labrig-bench-record-{}", std::process::id()));
    std::fs::create_dir_all(&p)?;
    Ok(p)
}
