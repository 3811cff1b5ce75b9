//! `labrig demo`: the main job on a fresh machine.
//!
//! Until the MuJoCo sim bridge lands, the demo runs the rig's transport end to end in one
//! process: an arm-state publisher and a subscriber on separate DDS participants (over
//! loopback, exactly as two nodes would talk), and the five cameras' frame streams over
//! iceoryx2 shared memory, then reports what arrived, at what rate, and the camera skew.

use anyhow::bail;
use clap::Args;
use futures::StreamExt;
use indicatif::{ProgressBar, ProgressStyle};
use labrig_msgs::Nanos;
use labrig_msgs::sensor_msgs::JointState;
use labrig_msgs::std_msgs::Header;
use labrig_runtime::frames::{FrameEncoding, FrameFormat, FrameNode};
use labrig_runtime::ros::{Ros, qos};
use labrig_runtime::{Clock, RosConfig};
use serde_json::json;
use std::process::ExitCode;
use std::time::Duration;

use labrig_msgs::labrig_msgs::{DROID_RESET_POSE as RESET, RIG_CAMERAS as CAMERAS};

/// FR3 joints + the 2F-85's driving joint, as the sim bridge will name them.
pub const JOINTS: [&str; 8] =
    ["fr3_joint1", "fr3_joint2", "fr3_joint3", "fr3_joint4", "fr3_joint5", "fr3_joint6", "fr3_joint7", "finger_joint"];
#[derive(Debug, Args)]
pub struct DemoArgs {
    /// Seconds to run.
    #[arg(long, default_value_t = 5.0)]
    pub seconds: f64,
    /// Control rate in Hz.
    #[arg(long, default_value_t = 20.0)]
    pub rate: f64,
    /// DDS domain id for the demo's nodes.
    #[arg(long, default_value_t = 42)]
    pub domain_id: u16,
    /// Print the report as JSON.
    #[arg(long)]
    pub json: bool,
    /// Skip the simulated rig (transport only).
    #[arg(long)]
    pub no_sim: bool,
    /// Seeded pick-and-place scenes the scripted expert runs in the sim.
    #[arg(long, default_value_t = 3)]
    pub episodes: u64,
    /// Where the demo writes its pictures.
    #[arg(long, default_value = "out/demo")]
    pub out: std::path::PathBuf,
}

pub fn run(args: DemoArgs) -> anyhow::Result<ExitCode> {
    if !(args.seconds > 0.0 && args.seconds <= 600.0 && args.rate > 0.0 && args.rate <= 200.0) {
        bail!("--seconds must be in (0, 600] and --rate in (0, 200]");
    }
    let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build()?;
    rt.block_on(demo(args))
}

async fn demo(args: DemoArgs) -> anyhow::Result<ExitCode> {
    let cfg = RosConfig { domain_id: args.domain_id, ..RosConfig::default() };
    cfg.validate(std::path::Path::new("<command line>"))?;
    let mut arm = Ros::new(&cfg, "labrig_demo_arm")?;
    let mut recorder = Ros::new(&cfg, "labrig_demo_recorder")?;
    let publisher = arm.publisher::<JointState>("/joint_states", qos::reliable(10))?;
    let subscription = recorder.subscription::<JointState>("/joint_states", qos::reliable(100))?;
    if !arm.wait_for_subscribers("/joint_states", 1, Duration::from_secs(10)).await {
        bail!("the demo's subscriber did not match /joint_states within 10 s");
    }
    let frames = FrameNode::new()?;
    let fmt = FrameFormat { encoding: FrameEncoding::Rgb8, width: 128, height: 128 };
    let run_id = std::process::id();
    let ids: Vec<String> = CAMERAS.iter().map(|c| format!("demo{run_id}_{c}")).collect();
    let mut cams = ids.iter().map(|c| frames.publisher(c, fmt.clone())).collect::<Result<Vec<_>, _>>()?;
    let subs = ids.iter().map(|c| frames.subscriber(c)).collect::<Result<Vec<_>, _>>()?;

    let ticks = (args.seconds * args.rate).round() as u64;
    let period = Duration::from_secs_f64(1.0 / args.rate);
    let clock = Clock::Wall;
    let bar =
        ProgressBar::new(ticks).with_style(ProgressStyle::with_template("{spinner} demo {bar:30} {pos}/{len} ticks")?);
    let mut pixels = vec![0u8; fmt.frame_bytes()];
    let mut frames_received = [0u64; 5];
    let mut skews_us = Vec::new();
    let mut states_received = 0u64;
    let mut stream = Box::pin(subscription.stream());
    let mut interval = tokio::time::interval(period);
    for tick in 0..ticks {
        interval.tick().await;
        let now = clock.now();
        let t = tick as f64 / args.rate;
        let mut position: Vec<f64> = RESET.iter().enumerate().map(|(j, q)| q + 0.1 * (t + j as f64).sin()).collect();
        position.push(0.0);
        publisher.publish(JointState {
            header: Header { stamp: now.into(), frame_id: "fr3_link0".into() },
            name: JOINTS.iter().map(|s| s.to_string()).collect(),
            position,
            velocity: vec![0.0; 8],
            effort: vec![],
        })?;
        for (i, cam) in cams.iter_mut().enumerate() {
            pixels.iter_mut().for_each(|p| *p = (tick as u8).wrapping_add(i as u8 * 40));
            let capture = clock.now();
            cam.publish(&pixels, capture, capture)?;
        }
        // One observation per tick: the newest frame of each camera, and their skew.
        let mut captures = Vec::new();
        for (i, sub) in subs.iter().enumerate() {
            let mut newest = None;
            while let Some(f) = sub.receive()? {
                frames_received[i] += 1;
                newest = Some(f.header().capture_ns);
            }
            captures.extend(newest);
        }
        if captures.len() == CAMERAS.len() {
            let (lo, hi) = (captures.iter().min().copied().unwrap_or(0), captures.iter().max().copied().unwrap_or(0));
            skews_us.push((hi - lo) as f64 / 1000.0);
        }
        while let Ok(Some(item)) = tokio::time::timeout(Duration::ZERO, stream.next()).await {
            match item {
                Ok(_) => states_received += 1,
                Err(e) => tracing::warn!("{e}"),
            }
        }
        bar.inc(1);
    }
    // Let the last states arrive (bounded).
    let deadline = clock.now() + Nanos::from_millis(500);
    while states_received < ticks && clock.now() < deadline {
        if let Ok(Some(Ok(_))) = tokio::time::timeout(Duration::from_millis(50), stream.next()).await {
            states_received += 1;
        }
    }
    bar.finish_and_clear();
    skews_us.sort_by(f64::total_cmp);
    let p =
        |q: f64| skews_us.get(((q * (skews_us.len().max(1) - 1) as f64).round()) as usize).copied().unwrap_or(f64::NAN);
    let transport_ok = states_received == ticks && frames_received.iter().all(|&n| n == ticks);
    let sim = if args.no_sim { None } else { Some(sim_part(&args)?) };
    let sim_ok = sim.as_ref().is_none_or(|s| s["ok"] == true);
    let ok = transport_ok && sim_ok;
    let report = json!({
        "ticks": ticks,
        "rate_hz": args.rate,
        "joint_states": { "published": ticks, "received": states_received },
        "cameras": CAMERAS.iter().zip(frames_received).map(|(c, n)| json!({"camera": c, "published": ticks, "received": n})).collect::<Vec<_>>(),
        "camera_skew_us": { "p50": p(0.5), "p99": p(0.99) },
        "sim": sim,
        "ok": ok,
    });
    if args.json {
        println!("{report}");
    } else {
        println!("labrig demo: {ticks} ticks at {} Hz (DDS on loopback, domain {})", args.rate, args.domain_id);
        println!("  /joint_states  sensor_msgs/JointState  {states_received}/{ticks} received over DDS");
        for (c, n) in CAMERAS.iter().zip(frames_received) {
            println!("  camera {c:<6} 128x128 rgb8 over iceoryx2  {n}/{ticks} frames");
        }
        println!("  camera skew per observation: p50 {:.0} us, p99 {:.0} us", p(0.5), p(0.99));
        println!("  {}", if transport_ok { "all data arrived" } else { "DATA WAS LOST (see counts above)" });
        if let Some(sim) = &sim {
            println!("simulated rig (MuJoCo): scripted experts on seeded scenes");
            for (task, eval) in sim["tasks"].as_object().into_iter().flatten() {
                println!("  {task}: {}/{} succeeded", eval["successes"], eval["episodes"]);
                for r in eval["results"].as_array().into_iter().flatten() {
                    println!(
                        "    seed {}: {} in {} ticks, cameras {}",
                        r["seed"],
                        if r["success"] == true { "success" } else { "FAILED" },
                        r["ticks"],
                        r["camera_bins"]
                            .as_array()
                            .map(|b| b.iter().filter_map(|x| x.as_str()).collect::<Vec<_>>().join(" "))
                            .unwrap_or_default()
                    );
                }
            }
            for shot in sim["snapshots"].as_array().into_iter().flatten() {
                println!("  the five cameras: {}", shot.as_str().unwrap_or_default());
            }
        }
        println!("Recording these episodes as DROID-format MCAP comes with the rig loop and recorder (issue 5).");
    }
    Ok(if ok { ExitCode::SUCCESS } else { ExitCode::from(1) })
}

/// The scenes the demo runs the experts on (built into labrig-sim).
const DEMO_TASKS: [&str; 3] = ["pick_place", "drawer_open", "drawer_close"];

/// The simulated rig's part: the scripted experts on seeded scenes of each task (`labrig sim
/// eval`) and snapshots of the five cameras (`labrig sim snapshot`), run by the sim binary.
fn sim_part(args: &DemoArgs) -> anyhow::Result<serde_json::Value> {
    let exe = crate::cli::sibling_binary("labrig-sim")?;
    let bar = ProgressBar::new_spinner();
    bar.enable_steady_tick(Duration::from_millis(120));
    let mut tasks = serde_json::Map::new();
    let mut ok = true;
    for task in DEMO_TASKS {
        bar.set_message(format!("simulated rig: {task} expert on {} scenes", args.episodes));
        let out = std::process::Command::new(&exe)
            .args(["eval", "--json", "--scene", task, "--episodes", &args.episodes.to_string()])
            .stderr(std::process::Stdio::inherit())
            .output()?;
        if !out.status.success() {
            bar.finish_and_clear();
            bail!("labrig sim eval --scene {task} failed ({})", out.status);
        }
        let eval: serde_json::Value = serde_json::from_slice(&out.stdout)?;
        ok &= eval["successes"] == eval["episodes"];
        tasks.insert(task.to_owned(), eval);
    }
    let mut snapshots = Vec::new();
    for task in ["pick_place", "drawer_open"] {
        bar.set_message(format!("simulated rig: snapshot of {task}"));
        let dir = args.out.join(format!("snapshot_{task}_seed0"));
        let status = std::process::Command::new(&exe)
            .args(["snapshot", "--scene", task, "--seed", "0", "--out"])
            .arg(&dir)
            .stdout(std::process::Stdio::null())
            .status()?;
        if !status.success() {
            bar.finish_and_clear();
            bail!("labrig sim snapshot --scene {task} failed ({status})");
        }
        let sheet = dir.join("cameras.png");
        ok &= sheet.exists();
        snapshots.push(sheet.display().to_string());
    }
    bar.finish_and_clear();
    Ok(json!({ "tasks": tasks, "snapshots": snapshots, "ok": ok }))
}
