//! `labrig bench openpi`: openpi's websocket protocol on loopback and what a remote policy's
//! latency does to the 20 Hz loop.
//!
//! 1. Round trip: labrig's client sends DROID observations (two 224 x 224 RGB images, 7
//!    joints, the gripper, a prompt) and gets a 15 x 8 chunk back, against labrig's own openpi
//!    server (the protocol alone) and, where setup's openpi venv exists, openpi's upstream
//!    `WebsocketPolicyServer`: p50 / p99 / max over `--requests`.
//! 2. The rig: the simulated rig in real time with `--source remote` against a server that
//!    answers after `--latency-ms` (0, 250, 500, 1000 by default: the openpi README puts a
//!    remote GPU's chunk at 0.5-1 s), each with the rows timed from the observation (the
//!    default) and from the chunk's arrival (DROID's client): the loop's period jitter, held
//!    ticks, the lead it asked with, and the rows that had passed when their chunk came.
//!
//! The machine is shared and noisy: read percentiles, and compare runs made together.

use anyhow::Context;
use clap::Args;
use indicatif::ProgressBar;
use labrig_openpi::codec::{self, Array, Value};
use labrig_openpi::{Client, Handler, Server, droid};
use serde::Serialize;
use std::path::PathBuf;
use std::process::{Command, ExitCode, Stdio};
use std::sync::Arc;
use std::time::{Duration, Instant};

#[derive(Debug, Clone, Args)]
pub struct OpenpiBenchArgs {
    /// Requests per round-trip measurement.
    #[arg(long, default_value_t = 200)]
    pub requests: usize,
    /// Server latencies (ms) for the rig runs, comma-separated (none: skip the rig).
    #[arg(long, value_delimiter = ',', default_values_t = vec![0u64, 250, 500, 1000])]
    pub latency_ms: Vec<u64>,
    /// Steps per rig run (20 Hz).
    #[arg(long, default_value_t = 100)]
    pub steps: u64,
    /// Where the rig runs' rollouts go.
    #[arg(long, default_value = "out/bench_openpi")]
    pub out: PathBuf,
    /// DDS domain id for the rig runs.
    #[arg(long, default_value_t = 44)]
    pub domain_id: u16,
    /// Print the report as JSON.
    #[arg(long)]
    pub json: bool,
}

#[derive(Debug, Clone, Serialize)]
pub struct RoundTrip {
    pub server: String,
    pub requests: usize,
    pub request_bytes: usize,
    pub p50_ms: f64,
    pub p99_ms: f64,
    pub max_ms: f64,
}

#[derive(Debug, Clone, Serialize)]
pub struct RigRun {
    pub latency_ms: u64,
    /// `policy.chunk_timing`: rows from the observation's tick, or from the chunk's arrival.
    pub chunk_timing: &'static str,
    pub steps: u64,
    pub requests: u64,
    pub chunks: u64,
    pub rows_executed: u64,
    pub rows_skipped: u64,
    pub held_ticks: u64,
    pub lead_steps: u64,
    pub round_trip_ms_p50: f64,
    pub jitter_us: [f64; 3],
    pub missed_ticks: u64,
}

#[derive(Debug, Clone, Serialize)]
pub struct OpenpiBenchReport {
    pub round_trips: Vec<RoundTrip>,
    pub rig: Vec<RigRun>,
    pub notes: Vec<String>,
}

/// pi0.5-DROID's reply shape: 15 steps of 7 joint velocities + the gripper (a slow sine, so
/// the rig moves), after `latency`.
struct Delayed {
    latency: Duration,
}

impl Handler for Delayed {
    type Session = u64;
    /// It always answers.
    type Error = std::convert::Infallible;
    fn session(&self) -> u64 {
        0
    }
    fn infer(&self, n: &mut u64, _obs: Value) -> Result<Value, Self::Error> {
        std::thread::sleep(self.latency);
        let rows: Vec<f32> = (0..15)
            .flat_map(|i| {
                let t = (*n * 8 + i) as f32;
                let mut r: Vec<f32> = (0..7).map(|j| 0.1 * (t / 6.0 + j as f32).sin()).collect();
                r.push(0.0);
                r
            })
            .collect();
        *n += 1;
        Ok(codec::map([("actions", Array::f32(&[15, 8], &rows).to_value())]))
    }
}

fn droid_observation(seed: u8) -> Value {
    let img: Vec<u8> = (0..224 * 224 * 3).map(|i: usize| (i as u8).wrapping_mul(seed | 1)).collect();
    droid::Observation {
        exterior: (&img, 224, 224),
        wrist: (&img, 224, 224),
        joint_position: [0.0, -0.5, 0.0, -2.2, 0.0, 1.8, 0.8],
        gripper_position: 0.0,
        prompt: "put the cube in the bin",
    }
    .to_value()
}

fn round_trip(server: &str, addr: &str, n: usize, bar: &ProgressBar) -> anyhow::Result<RoundTrip> {
    let mut c = Client::connect(addr, Duration::from_secs(10))?;
    let obs = droid_observation(7);
    let bytes = codec::pack(&obs).len();
    // A few to warm up (connection buffers, the server's first call).
    for _ in 0..5 {
        c.infer(&obs, Duration::from_secs(10))?;
    }
    let mut ms = Vec::with_capacity(n);
    for _ in 0..n {
        let t = Instant::now();
        let r = c.infer(&obs, Duration::from_secs(10))?;
        ms.push(t.elapsed().as_secs_f64() * 1e3);
        anyhow::ensure!(droid::action_rows(&r, 8).is_ok(), "{server}: a reply without a 15 x 8 chunk");
        bar.inc(1);
    }
    let p = labrig_episode::inspect::Percentiles::of(ms).context("no requests")?;
    Ok(RoundTrip {
        server: server.into(),
        requests: n,
        request_bytes: bytes,
        p50_ms: p.p50,
        p99_ms: p.p99,
        max_ms: p.max,
    })
}

/// openpi's upstream server (setup's venv) serving `chunks.json`; killed on drop.
struct Upstream(std::process::Child);

impl Drop for Upstream {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

fn upstream(dir: &std::path::Path) -> anyhow::Result<Option<(Upstream, String)>> {
    let python = match std::env::var_os("LABRIG_OPENPI_PYTHON") {
        Some(p) => PathBuf::from(p),
        None => return Ok(None),
    };
    if !python.exists() {
        return Ok(None);
    }
    let script = dir.join("openpi_peer.py");
    std::fs::write(&script, include_str!("../../../tests/peers/openpi_peer.py"))?;
    let chunks = dir.join("chunks.json");
    std::fs::write(&chunks, serde_json::to_string(&vec![vec![vec![0.0f32; 8]; 15]])?)?;
    let mut child = Command::new(python)
        .arg(&script)
        .args(["serve", "--chunks"])
        .arg(&chunks)
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()?;
    let mut line = String::new();
    std::io::BufRead::read_line(&mut std::io::BufReader::new(child.stdout.take().context("stdout")?), &mut line)?;
    let guard = Upstream(child);
    let port = serde_json::from_str::<serde_json::Value>(&line)?["port"].as_u64().context("no port")?;
    let addr = format!("127.0.0.1:{port}");
    let until = Instant::now() + Duration::from_secs(30);
    while labrig_openpi::client::healthz(&addr, Duration::from_secs(1)).is_err() {
        anyhow::ensure!(Instant::now() < until, "openpi's server never answered /healthz");
        std::thread::sleep(Duration::from_millis(50));
    }
    Ok(Some((guard, addr)))
}

pub fn run(a: OpenpiBenchArgs) -> anyhow::Result<ExitCode> {
    std::fs::create_dir_all(&a.out).with_context(|| format!("creating {}", a.out.display()))?;
    let out = std::fs::canonicalize(&a.out)?;
    let mut notes = Vec::new();
    let bar = labrig_episode::progress::bar(
        "bench openpi {bar:30} {pos}/{len}",
        (2 * a.requests) as u64 + 2 * a.latency_ms.len() as u64 * a.steps,
        a.json,
    );

    let mut round_trips = Vec::new();
    bar.set_message("round trip: labrig's server");
    let own = Server::bind("127.0.0.1:0", Value::Map(vec![]), Arc::new(Delayed { latency: Duration::ZERO }))?;
    round_trips.push(round_trip("labrig-openpi server", &own.local_addr().to_string(), a.requests, &bar)?);
    drop(own);
    bar.set_message("round trip: openpi's server");
    match upstream(&out)? {
        Some((_proc, addr)) => round_trips.push(round_trip("openpi-server (Python)", &addr, a.requests, &bar)?),
        None => notes.push("openpi's own server not measured: LABRIG_OPENPI_PYTHON (setup's venv) is not set".into()),
    }

    let mut rig = Vec::new();
    let runs: Vec<(u64, labrig_launch::rollout::ChunkTimingArg)> = a
        .latency_ms
        .iter()
        .flat_map(|&l| {
            [labrig_launch::rollout::ChunkTimingArg::Observation, labrig_launch::rollout::ChunkTimingArg::Arrival]
                .map(|t| (l, t))
        })
        .collect();
    for (k, &(latency, timing)) in runs.iter().enumerate() {
        let timing_name =
            if timing == labrig_launch::rollout::ChunkTimingArg::Arrival { "arrival" } else { "observation" };
        bar.set_message(format!("the rig, {latency} ms, {timing_name}"));
        let server = Server::bind(
            "127.0.0.1:0",
            codec::map([("policy", Value::from(format!("sine after {latency} ms")))]),
            Arc::new(Delayed { latency: Duration::from_millis(latency) }),
        )?;
        let dir = out.join(format!("latency_{latency}ms_{timing_name}"));
        let args = labrig_launch::rollout::RolloutArgs {
            remote: Some(server.local_addr().to_string()),
            chunk_timing: Some(timing),
            server_timeout_s: Some((3.0 * latency as f64 / 1e3).max(5.0)),
            episodes: 1,
            first_seed: 1000 + (k / 2) as u64,
            lockstep: false,
            realtime: true,
            max_steps: a.steps,
            threads: 1,
            domain_id: a.domain_id,
            ..labrig_launch::rollout::RolloutArgs::defaults(dir.clone())
        };
        let r = labrig_launch::rollout::run_quiet(args)?;
        anyhow::ensure!(
            r.errors.is_empty() && r.rollouts.len() == 1,
            "the rig run at {latency} ms ({timing_name}) failed: {}",
            r.errors.join("; ")
        );
        let report: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(dir.join("rollouts.json"))?).context("rollouts.json")?;
        let c = &report["control"];
        let s = &c["source"];
        let u = |v: &serde_json::Value| v.as_u64().unwrap_or(0);
        let f = |v: &serde_json::Value| v.as_f64().unwrap_or(f64::NAN);
        rig.push(RigRun {
            latency_ms: latency,
            chunk_timing: timing_name,
            steps: u(&report["rollouts"][0]["steps"]),
            requests: u(&s["requests"]),
            chunks: u(&s["chunks"]),
            rows_executed: u(&s["rows_executed"]),
            rows_skipped: u(&s["rows_skipped"]),
            held_ticks: u(&c["held_ticks"]),
            lead_steps: u(&s["lead_steps"]),
            round_trip_ms_p50: f(&s["round_trip_ms"][0]),
            jitter_us: [f(&c["jitter_us"][0]), f(&c["jitter_us"][1]), f(&c["jitter_us"][2])],
            missed_ticks: u(&c["missed_ticks"]),
        });
        bar.inc(a.steps);
    }
    bar.finish_and_clear();
    let report = OpenpiBenchReport { round_trips, rig, notes };
    if a.json {
        println!("{}", serde_json::to_string(&report)?);
    } else {
        println!("openpi round trip on loopback (two 224x224 images + joints + prompt out, 15 x 8 chunk back):");
        for r in &report.round_trips {
            println!(
                "  {:24} p50 {:.2} ms  p99 {:.2} ms  max {:.2} ms  ({} requests of {} kB)",
                r.server,
                r.p50_ms,
                r.p99_ms,
                r.max_ms,
                r.requests,
                r.request_bytes / 1000
            );
        }
        if !report.rig.is_empty() {
            println!("the sim rig in real time, --source remote, DROID chunks of 15 at 15 Hz, 8 executed (10 ticks):");
            println!(
                "  latency  rows from    steps  requests  chunks  rows run  rows skipped  held ticks  lead  rtt p50 ms  jitter p50/p99 us"
            );
            for r in &report.rig {
                println!(
                    "  {:>5} ms {:11} {:>6} {:>9} {:>7} {:>9} {:>13} {:>11} {:>5} {:>11.1}  {:.0}/{:.0}",
                    r.latency_ms,
                    r.chunk_timing,
                    r.steps,
                    r.requests,
                    r.chunks,
                    r.rows_executed,
                    r.rows_skipped,
                    r.held_ticks,
                    r.lead_steps,
                    r.round_trip_ms_p50,
                    r.jitter_us[0],
                    r.jitter_us[1]
                );
            }
        }
        for n in &report.notes {
            println!("note: {n}");
        }
    }
    Ok(ExitCode::SUCCESS)
}
