//! `labrig bench shm`: camera frames over iceoryx2 between processes — delivered/expected
//! frames, latency percentiles and CPU per stream. Figures vary on a shared 2-core machine:
//! read them as a distribution, not a single truth.

use anyhow::{Context, bail};
use clap::Args;
use labrig_msgs::Nanos;
use labrig_runtime::Clock;
use labrig_runtime::frames::{FrameEncoding, FrameFormat, FrameNode};
use serde::{Deserialize, Serialize};
use std::io::{BufRead, BufReader};
use std::process::{Command, ExitCode, Stdio};
use std::time::{Duration, Instant};

#[derive(Debug, Clone, Args)]
pub struct ShmArgs {
    /// Number of camera streams (one publisher process each).
    #[arg(long, default_value_t = 5)]
    pub streams: usize,
    #[arg(long, default_value_t = 640)]
    pub width: u32,
    #[arg(long, default_value_t = 480)]
    pub height: u32,
    /// Frames per second per stream.
    #[arg(long, default_value_t = 30.0)]
    pub rate: f64,
    /// Seconds each publisher runs.
    #[arg(long, default_value_t = 10.0)]
    pub seconds: f64,
    /// Subscriber polling period in microseconds (bounds the added latency).
    #[arg(long, default_value_t = 100)]
    pub poll_us: u64,
    /// Print the report as JSON.
    #[arg(long)]
    pub json: bool,
}

#[derive(Debug, Clone, Args)]
pub struct ShmPublisherArgs {
    #[arg(long)]
    pub camera: String,
    #[arg(long)]
    pub width: u32,
    #[arg(long)]
    pub height: u32,
    #[arg(long)]
    pub rate: f64,
    #[arg(long)]
    pub seconds: f64,
}

/// What a publisher process reports on stdout when done.
#[derive(Debug, Serialize, Deserialize)]
struct PublisherReport {
    published: u64,
    cpu_s: f64,
    wall_s: f64,
}

/// Per-stream result.
#[derive(Debug, Clone, Serialize)]
pub struct StreamReport {
    pub camera: String,
    pub published: u64,
    pub delivered: u64,
    pub expected: u64,
    pub sequence_gaps: u64,
    pub latency_p50_us: f64,
    pub latency_p99_us: f64,
    pub latency_max_us: f64,
    pub publisher_cpu_percent: f64,
}

/// The whole benchmark.
#[derive(Debug, Clone, Serialize)]
pub struct ShmReport {
    pub streams: Vec<StreamReport>,
    pub frame_bytes: usize,
    pub rate_hz: f64,
    pub seconds: f64,
    pub delivered_total: u64,
    pub expected_total: u64,
    pub latency_p50_us: f64,
    pub latency_p99_us: f64,
    /// Subscriber process CPU (all streams) divided by the number of streams.
    pub subscriber_cpu_percent_per_stream: f64,
    pub poll_us: u64,
}

fn percentile(sorted: &[f64], q: f64) -> f64 {
    if sorted.is_empty() {
        return f64::NAN;
    }
    sorted[((q * (sorted.len() - 1) as f64).round() as usize).min(sorted.len() - 1)]
}

fn validate(width: u32, height: u32, rate: f64, seconds: f64) -> anyhow::Result<()> {
    if width == 0 || height == 0 || width > 8192 || height > 8192 {
        bail!("frame size {width}x{height} is out of range (1..=8192 each)");
    }
    if !(rate.is_finite() && rate > 0.0 && rate <= 1000.0) {
        bail!("--rate {rate} is out of range (0, 1000]");
    }
    if !(seconds.is_finite() && seconds > 0.0 && seconds <= 600.0) {
        bail!("--seconds {seconds} is out of range (0, 600]");
    }
    Ok(())
}

/// The publisher process: one camera, frames at a fixed rate for a fixed time.
pub fn shm_publisher(args: ShmPublisherArgs) -> anyhow::Result<ExitCode> {
    validate(args.width, args.height, args.rate, args.seconds)?;
    let node = FrameNode::new()?;
    let format = FrameFormat { encoding: FrameEncoding::Rgb8, width: args.width, height: args.height };
    let mut pixels = vec![0u8; format.frame_bytes()];
    pixels.iter_mut().enumerate().for_each(|(i, p)| *p = (i % 251) as u8);
    let mut publisher = node.publisher(&args.camera, format)?;
    let period = Duration::from_secs_f64(1.0 / args.rate);
    let frames = (args.seconds * args.rate).round() as u64;
    let start = Instant::now();
    let cpu0 = labrig_runtime::bench::process_cpu_seconds();
    let clock = Clock::Wall;
    for i in 0..frames {
        let due = start + period * i as u32;
        if let Some(wait) = due.checked_duration_since(Instant::now()) {
            std::thread::sleep(wait);
        }
        pixels[0] = i as u8;
        let now = clock.now();
        publisher.publish(&pixels, now, now)?;
    }
    let report = PublisherReport {
        published: frames,
        cpu_s: labrig_runtime::bench::process_cpu_seconds() - cpu0,
        wall_s: start.elapsed().as_secs_f64(),
    };
    println!("{}", serde_json::to_string(&report)?);
    Ok(ExitCode::SUCCESS)
}

pub fn shm(args: ShmArgs) -> anyhow::Result<ExitCode> {
    validate(args.width, args.height, args.rate, args.seconds)?;
    if args.streams == 0 || args.streams > 16 {
        bail!("--streams {} is out of range (1..=16)", args.streams);
    }
    let report = run_shm(&args)?;
    if args.json {
        println!("{}", serde_json::to_string_pretty(&report)?);
    } else {
        print_report(&report);
    }
    Ok(ExitCode::SUCCESS)
}

pub fn run_shm(args: &ShmArgs) -> anyhow::Result<ShmReport> {
    let node = FrameNode::new()?;
    let cameras: Vec<String> = (0..args.streams).map(|i| format!("bench{}_{i}", std::process::id())).collect();
    let subscribers = cameras.iter().map(|c| node.subscriber(c)).collect::<Result<Vec<_>, _>>()?;
    let exe = std::env::current_exe().context("locating the labrig binary")?;
    let mut children = Vec::new();
    for camera in &cameras {
        let child = Command::new(&exe)
            .args(["bench", "shm-publisher", "--camera", camera])
            .args(["--width", &args.width.to_string(), "--height", &args.height.to_string()])
            .args(["--rate", &args.rate.to_string(), "--seconds", &args.seconds.to_string()])
            .stdout(Stdio::piped())
            .spawn()
            .with_context(|| format!("starting publisher for {camera}"))?;
        children.push(child);
    }
    let clock = Clock::Wall;
    let cpu0 = labrig_runtime::bench::process_cpu_seconds();
    let mut latencies: Vec<Vec<f64>> = vec![Vec::new(); args.streams];
    let mut gaps = vec![0u64; args.streams];
    let mut last_seq: Vec<Option<u64>> = vec![None; args.streams];
    let bar = labrig_episode::progress::bar(
        &format!("shm bench {{bar:30}} of {:.0} s", args.seconds),
        (args.seconds * 10.0) as u64,
        false,
    );
    let started = Instant::now();
    // Run until every publisher has exited, then drain what is left; bounded in any case.
    let hard_stop = started + Duration::from_secs_f64(args.seconds + 30.0);
    let mut exited = vec![false; children.len()];
    let mut drain_until: Option<Instant> = None;
    loop {
        for (i, sub) in subscribers.iter().enumerate() {
            while let Some(frame) = sub.receive()? {
                let h = frame.header();
                let now = clock.now();
                latencies[i].push((now - Nanos(h.publish_ns)).0 as f64 / 1000.0);
                if let Some(prev) = last_seq[i] {
                    gaps[i] += h.sequence.saturating_sub(prev + 1);
                }
                last_seq[i] = Some(h.sequence);
            }
        }
        bar.set_position((started.elapsed().as_secs_f64() * 10.0) as u64);
        if drain_until.is_none() {
            for (i, c) in children.iter_mut().enumerate() {
                if !exited[i] && c.try_wait()?.is_some() {
                    exited[i] = true;
                }
            }
            if exited.iter().all(|&e| e) {
                drain_until = Some(Instant::now() + Duration::from_millis(200));
            }
        }
        let now = Instant::now();
        if drain_until.is_some_and(|d| now >= d) || now >= hard_stop {
            break;
        }
        std::thread::sleep(Duration::from_micros(args.poll_us));
    }
    bar.finish_and_clear();
    let sub_cpu = labrig_runtime::bench::process_cpu_seconds() - cpu0;
    let wall = started.elapsed().as_secs_f64();
    let mut streams = Vec::new();
    let mut all = Vec::new();
    for (i, mut child) in children.into_iter().enumerate() {
        let status = child.wait()?;
        let mut line = String::new();
        if let Some(out) = child.stdout.take() {
            BufReader::new(out).read_line(&mut line)?;
        }
        if !status.success() {
            bail!("publisher {} failed ({status})", cameras[i]);
        }
        let pr: PublisherReport =
            serde_json::from_str(line.trim()).with_context(|| format!("publisher {} report {line:?}", cameras[i]))?;
        let mut l = std::mem::take(&mut latencies[i]);
        l.sort_by(f64::total_cmp);
        all.extend_from_slice(&l);
        streams.push(StreamReport {
            camera: cameras[i].clone(),
            published: pr.published,
            delivered: l.len() as u64,
            expected: (args.seconds * args.rate).round() as u64,
            sequence_gaps: gaps[i],
            latency_p50_us: percentile(&l, 0.5),
            latency_p99_us: percentile(&l, 0.99),
            latency_max_us: l.last().copied().unwrap_or(f64::NAN),
            publisher_cpu_percent: 100.0 * pr.cpu_s / pr.wall_s.max(1e-9),
        });
    }
    all.sort_by(f64::total_cmp);
    Ok(ShmReport {
        frame_bytes: (args.width * args.height * 3) as usize,
        rate_hz: args.rate,
        seconds: args.seconds,
        delivered_total: streams.iter().map(|s| s.delivered).sum(),
        expected_total: streams.iter().map(|s| s.expected).sum(),
        latency_p50_us: percentile(&all, 0.5),
        latency_p99_us: percentile(&all, 0.99),
        subscriber_cpu_percent_per_stream: 100.0 * sub_cpu / wall / args.streams as f64,
        poll_us: args.poll_us,
        streams,
    })
}

fn print_report(r: &ShmReport) {
    println!(
        "iceoryx2 camera frames: {} streams x {} bytes at {} Hz for {} s (subscriber polls every {} us)",
        r.streams.len(),
        r.frame_bytes,
        r.rate_hz,
        r.seconds,
        r.poll_us
    );
    println!(
        "{:<16} {:>9} {:>9} {:>5} {:>9} {:>9} {:>9} {:>8}",
        "stream", "delivered", "expected", "gaps", "p50 us", "p99 us", "max us", "pub cpu"
    );
    for s in &r.streams {
        println!(
            "{:<16} {:>9} {:>9} {:>5} {:>9.1} {:>9.1} {:>9.1} {:>7.2}%",
            s.camera,
            s.delivered,
            s.expected,
            s.sequence_gaps,
            s.latency_p50_us,
            s.latency_p99_us,
            s.latency_max_us,
            s.publisher_cpu_percent
        );
    }
    println!(
        "total: {}/{} frames delivered, latency p50 {:.1} us p99 {:.1} us, subscriber cpu {:.2}% per stream",
        r.delivered_total, r.expected_total, r.latency_p50_us, r.latency_p99_us, r.subscriber_cpu_percent_per_stream
    );
}
