//! `labrig bench cameras`: N camera streams through the camera node into the rig loop's
//! observation. Each camera is an ffmpeg process serving MJPEG over HTTP on 127.0.0.1 (a
//! test pattern at the size and rate asked for: what an IP camera or a UVC camera's MJPG mode
//! sends); `labrig-cameras` reads, decodes and publishes them on shared memory; this process
//! samples them as the loop does (at each 20 Hz tick, every camera's newest frame). Reports per
//! camera the frames delivered and lost, capture -> observation latency p50/p99 (capture =
//! the node's arrival time: HTTP streams carry no device time), the skew between the cameras'
//! frames within one observation, and the CPU of the node and of the ffmpeg servers. A shared
//! 2-core machine: the servers' encoding competes with the node, so read the figures as what
//! this machine sustains, not as the node's cost alone.

use anyhow::{Context, bail};
use clap::Args;
use labrig_episode::inspect::Percentiles;
use labrig_episode::progress;
use labrig_runtime::Clock;
use labrig_runtime::frames::FrameNode;
use serde::Serialize;
use std::process::{Child, Command, ExitCode, Stdio};
use std::time::{Duration, Instant};

#[derive(Debug, Clone, Args)]
pub struct CamerasBenchArgs {
    /// Camera streams.
    #[arg(long, default_value_t = 5)]
    pub cameras: usize,
    #[arg(long, default_value_t = 1280)]
    pub width: u32,
    #[arg(long, default_value_t = 720)]
    pub height: u32,
    /// Frames per second per camera.
    #[arg(long, default_value_t = 30.0)]
    pub fps: f64,
    /// Seconds measured (after the streams are up).
    #[arg(long, default_value_t = 20.0)]
    pub seconds: f64,
    /// The loop's rate: observations per second.
    #[arg(long, default_value_t = 20.0)]
    pub observe_hz: f64,
    /// JPEG quality scale of the servers (ffmpeg -q:v, 2 best .. 31).
    #[arg(long, default_value_t = 5)]
    pub jpeg_q: u32,
    /// The cameras publish the servers' JPEGs unchanged (`jpeg_passthrough`) instead of
    /// decoding them to RGB; the recorder then stores them without re-encoding.
    #[arg(long)]
    pub jpeg_passthrough: bool,
    /// JPEG quality the recorder encodes RGB frames at (its `jpeg_quality`).
    #[arg(long, default_value_t = 90)]
    pub record_quality: u8,
    #[arg(long, default_value_t = 44)]
    pub domain_id: u16,
    #[arg(long)]
    pub json: bool,
}

#[derive(Debug, Serialize)]
struct CameraFigures {
    camera: String,
    delivered: u64,
    /// Frames the node published that this subscriber never saw (sequence gaps).
    lost_in_transport: u64,
    /// Frames the servers sent that the node did not publish (expected - published).
    short_of_rate: i64,
    fps: f64,
    latency_ms: Option<Percentiles>,
}

#[derive(Debug, Serialize)]
struct Report {
    cameras: usize,
    width: u32,
    height: u32,
    fps: f64,
    seconds: f64,
    observations: usize,
    /// Observations in which some camera had no frame yet.
    observations_missing_a_camera: usize,
    per_camera: Vec<CameraFigures>,
    /// Newest minus oldest capture time among the cameras in one observation (ms).
    skew_ms: Option<Percentiles>,
    /// Capture -> observation, all cameras (ms).
    latency_ms: Option<Percentiles>,
    node_cpu_percent: f64,
    servers_cpu_percent: f64,
    jpeg_passthrough: bool,
    /// What the recorder does to one of these frames to store it (JPEG-encode an RGB frame at
    /// `record_quality`, or copy a passed-through JPEG), timed here on one frame per camera
    /// taken at the end, after the node and the servers stopped (ms per frame, median of the
    /// repetitions), and that cost at the delivered rate (% of a core): the recorder's share,
    /// measured outside the recorder.
    record_ms_per_frame: f64,
    record_cpu_percent: f64,
    /// Bytes per recorded frame (mean over the timed frames).
    recorded_bytes_per_frame: f64,
}

struct Servers(Vec<Child>);

impl Drop for Servers {
    fn drop(&mut self) {
        for c in &mut self.0 {
            let _ = c.kill();
            let _ = c.wait();
        }
    }
}

fn free_port() -> anyhow::Result<u16> {
    Ok(std::net::TcpListener::bind("127.0.0.1:0")?.local_addr()?.port())
}

pub fn run(a: CamerasBenchArgs) -> anyhow::Result<ExitCode> {
    if a.cameras == 0 || a.cameras > 16 {
        bail!("--cameras {} must be 1..=16", a.cameras);
    }
    if !(a.fps > 0.0 && a.fps <= 120.0 && a.seconds > 0.0 && a.seconds <= 600.0) {
        bail!("--fps must be in (0, 120] and --seconds in (0, 600]");
    }
    let exe = labrig_launch::programs::sibling_binary("labrig-cameras")?;
    let ns = format!("bench_cameras_{}", std::process::id());
    let dir = tempfile::tempdir()?;
    let mut config = format!("stall_s = 1.0\nretry_s = 0.2\npreview_hz = 1.0\n[ros]\ndomain_id = {}\n", a.domain_id);
    let mut servers = Servers(Vec::new());
    let ids: Vec<String> = (0..a.cameras).map(|i| format!("cam{i}")).collect();
    for id in &ids {
        let port = free_port()?;
        let child = Command::new("ffmpeg")
            .args(["-nostdin", "-hide_banner", "-loglevel", "error", "-re", "-f", "lavfi", "-i"])
            .arg(format!("testsrc2=size={}x{}:rate={}", a.width, a.height, a.fps))
            .args(["-q:v", &a.jpeg_q.to_string(), "-f", "mpjpeg", "-listen", "1"])
            .arg(format!("http://127.0.0.1:{port}/cam"))
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            // Killing a server at the end makes it complain about the broken connection.
            .stderr(Stdio::null())
            .spawn()
            .context("ffmpeg (scripts/setup.sh installs it)")?;
        servers.0.push(child);
        config += &format!(
            "[cameras.{id}]\nsource = \"http://127.0.0.1:{port}/cam\"\nwidth = {}\nheight = {}\nfps = {}\njpeg_passthrough = {}\n",
            a.width, a.height, a.fps, a.jpeg_passthrough
        );
    }
    let cfg_path = dir.path().join("cameras.toml");
    std::fs::write(&cfg_path, config)?;
    let stats_path = dir.path().join("stats.json");
    let mut node = Command::new(exe)
        .args(["run", "--config"])
        .arg(&cfg_path)
        .arg("--stats-out")
        .arg(&stats_path)
        .env(labrig_runtime::frames::NAMESPACE_ENV, &ns)
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(std::fs::File::create(dir.path().join("node.log"))?)
        .spawn()?;
    let frames = FrameNode::new_in(&ns)?;
    let subs: Vec<_> = ids.iter().map(|id| frames.subscriber(id)).collect::<Result<_, _>>()?;

    // Wait until every camera delivers, then measure.
    let up_by = Instant::now() + Duration::from_secs(30);
    let mut seen = vec![false; ids.len()];
    let mut newest: Vec<Option<i64>> = vec![None; ids.len()];
    while seen.iter().any(|s| !s) {
        if Instant::now() > up_by {
            let _ = node.kill();
            let log = std::fs::read_to_string(dir.path().join("node.log")).unwrap_or_default();
            let silent: Vec<&String> = ids.iter().zip(&seen).filter(|(_, s)| !**s).map(|(i, _)| i).collect();
            bail!("cameras {silent:?} sent no frame within 30 s; labrig-cameras said:\n{log}");
        }
        for (k, s) in subs.iter().enumerate() {
            while let Some(f) = s.receive()? {
                seen[k] = true;
                newest[k] = Some(f.header().capture_ns);
            }
        }
        std::thread::sleep(Duration::from_millis(10));
    }
    let pid = node.id().to_string();
    let server_pids: Vec<String> = servers.0.iter().map(|c| c.id().to_string()).collect();
    let cpu = |pids: &[String]| pids.iter().filter_map(|p| labrig_runtime::bench::cpu_seconds_of(p)).sum::<f64>();
    let (node_cpu0, servers_cpu0) = (cpu(std::slice::from_ref(&pid)), cpu(&server_pids));
    let started = Instant::now();
    let period = Duration::from_secs_f64(1.0 / a.observe_hz);
    let n_obs = (a.seconds * a.observe_hz).round() as u64;
    let bar = progress::bar("observing {pos}/{len} ticks", n_obs, a.json);
    let mut last_seq: Vec<Option<u64>> = vec![None; ids.len()];
    let (mut delivered, mut lost) = (vec![0u64; ids.len()], vec![0u64; ids.len()]);
    let mut first_seq: Vec<Option<u64>> = vec![None; ids.len()];
    let mut latency: Vec<Vec<f64>> = vec![Vec::new(); ids.len()];
    let (mut skew, mut missing) = (Vec::new(), 0usize);
    let mut next = Instant::now() + period;
    for _ in 0..n_obs {
        // Drain frames as they come (as the loop's frame thread does) until the tick.
        while Instant::now() < next {
            for (k, s) in subs.iter().enumerate() {
                while let Some(f) = s.receive()? {
                    let h = f.header();
                    if let Some(p) = last_seq[k]
                        && h.sequence > p + 1
                    {
                        lost[k] += h.sequence - p - 1;
                    }
                    first_seq[k].get_or_insert(h.sequence);
                    last_seq[k] = Some(h.sequence);
                    delivered[k] += 1;
                    newest[k] = Some(h.capture_ns);
                }
            }
            std::thread::sleep(Duration::from_micros(500));
        }
        next += period;
        let tick = Clock::Wall.now().0;
        let captures: Vec<i64> = newest.iter().flatten().copied().collect();
        if captures.len() < ids.len() {
            missing += 1;
        }
        for (k, c) in newest.iter().enumerate() {
            if let Some(c) = c {
                latency[k].push((tick - c) as f64 / 1e6);
            }
        }
        if let (Some(lo), Some(hi)) = (captures.iter().min(), captures.iter().max()) {
            skew.push((hi - lo) as f64 / 1e6);
        }
        bar.inc(1);
    }
    bar.finish_and_clear();
    let wall = started.elapsed().as_secs_f64();
    let node_cpu = cpu(std::slice::from_ref(&pid)) - node_cpu0;
    let servers_cpu = cpu(&server_pids) - servers_cpu0;
    let samples = frame_samples(&subs)?;
    let _ = Command::new("kill").args(["-TERM", &pid]).status();
    let _ = node.wait();
    drop(servers);
    // Timed with the node and the servers stopped: the recorder's cost, not the contention's.
    let (record_ms, record_bytes) = record_cost(&samples, a.record_quality)?;

    let expected = (a.fps * wall).round() as i64;
    let per_camera: Vec<CameraFigures> = ids
        .iter()
        .enumerate()
        .map(|(k, id)| {
            let published = match (first_seq[k], last_seq[k]) {
                (Some(f), Some(l)) => (l - f + 1) as i64,
                _ => 0,
            };
            CameraFigures {
                camera: id.clone(),
                delivered: delivered[k],
                lost_in_transport: lost[k],
                short_of_rate: (expected - published).max(0),
                fps: delivered[k] as f64 / wall,
                latency_ms: Percentiles::of(latency[k].clone()),
            }
        })
        .collect();
    let report = Report {
        cameras: a.cameras,
        width: a.width,
        height: a.height,
        fps: a.fps,
        seconds: wall,
        observations: n_obs as usize,
        observations_missing_a_camera: missing,
        skew_ms: Percentiles::of(skew),
        latency_ms: Percentiles::of(latency.concat()),
        per_camera,
        node_cpu_percent: 100.0 * node_cpu / wall,
        servers_cpu_percent: 100.0 * servers_cpu / wall,
        jpeg_passthrough: a.jpeg_passthrough,
        record_ms_per_frame: record_ms,
        record_cpu_percent: record_ms * delivered.iter().sum::<u64>() as f64 / wall / 10.0,
        recorded_bytes_per_frame: record_bytes,
    };
    if a.json {
        println!("{}", serde_json::to_string_pretty(&report)?);
    } else {
        print(&report);
    }
    Ok(ExitCode::SUCCESS)
}

/// A frame copied out of shared memory: (encoding, width, height, bytes).
type Sample = (Option<labrig_runtime::frames::FrameEncoding>, u32, u32, Vec<u8>);

/// One frame of each camera (the next to arrive), copied out.
fn frame_samples(subs: &[labrig_runtime::frames::FrameSubscriber]) -> anyhow::Result<Vec<Sample>> {
    let mut out = Vec::new();
    for s in subs {
        let until = Instant::now() + Duration::from_secs(5);
        let frame = loop {
            if let Some(f) = s.receive()? {
                break f;
            }
            if Instant::now() > until {
                bail!("a camera sent no frame for the recorder's timing");
            }
            std::thread::sleep(Duration::from_millis(2));
        };
        let h = *frame.header();
        out.push((h.encoding(), h.width, h.height, frame.pixels().to_vec()));
    }
    Ok(out)
}

/// The recorder's work on each sampled frame: JPEG-encode an RGB frame, or copy a JPEG one,
/// repeated; (median ms per frame, mean bytes per frame).
fn record_cost(samples: &[Sample], quality: u8) -> anyhow::Result<(f64, f64)> {
    use labrig_runtime::frames::FrameEncoding;
    let mut times = Vec::new();
    let mut bytes = Vec::new();
    for (encoding, w, h, pixels) in samples {
        for _ in 0..5 {
            let t = Instant::now();
            let stored = match encoding {
                Some(FrameEncoding::Jpeg) => pixels.clone(),
                _ => labrig_episode::jpeg::encode_rgb(pixels, *w as u16, *h as u16, quality)?,
            };
            times.push(t.elapsed().as_secs_f64() * 1e3);
            bytes.push(stored.len() as f64);
        }
    }
    times.sort_by(f64::total_cmp);
    Ok((times[times.len() / 2], bytes.iter().sum::<f64>() / bytes.len().max(1) as f64))
}

fn pct(p: &Option<Percentiles>) -> String {
    p.as_ref().map_or("-".into(), |p| format!("p50 {:7.1} ms  p99 {:7.1} ms  max {:7.1} ms", p.p50, p.p99, p.max))
}

fn print(r: &Report) {
    println!(
        "labrig bench cameras: {} MJPEG streams {}x{} at {} fps over HTTP (ffmpeg on 127.0.0.1) -> labrig-cameras -> shared memory -> {} observations ({:.1} s); a shared machine: compare within one run",
        r.cameras, r.width, r.height, r.fps, r.observations, r.seconds
    );
    for c in &r.per_camera {
        println!(
            "  {:6} delivered {:5} ({:5.1} fps)  short of the rate {:4}  lost in transport {:3}  latency {}",
            c.camera,
            c.delivered,
            c.fps,
            c.short_of_rate,
            c.lost_in_transport,
            pct(&c.latency_ms)
        );
    }
    println!("  capture -> observation (all): {}", pct(&r.latency_ms));
    println!("  skew within an observation:   {}", pct(&r.skew_ms));
    println!("  observations missing a camera: {}", r.observations_missing_a_camera);
    println!(
        "  CPU: labrig-cameras {:.0}% of a core; the ffmpeg servers (the cameras' side) {:.0}%",
        r.node_cpu_percent, r.servers_cpu_percent
    );
    println!(
        "  recording them ({}): {:.2} ms per frame, {:.0}% of a core at the delivered rate, {:.0} kB per frame",
        if r.jpeg_passthrough { "JPEG passed through, copied" } else { "RGB encoded to JPEG" },
        r.record_ms_per_frame,
        r.record_cpu_percent,
        r.recorded_bytes_per_frame / 1e3
    );
}
