//! `labrig bench station`: is the operator station felt? The demo's rig in real time (as
//! `labrig bench loop` runs it) measured twice: alone, then with the station beside it, its
//! page's traffic (status 4 times a second, the five thumbnails 4 times a second, the episode
//! list every 3 s, as the page polls) and three Foxglove clients subscribed to every channel.
//! Reports the loop's tick jitter (p50/p99/max), missed ticks, camera skew, dropped frames and
//! flagged episodes of each run side by side, the ratio of the p99s, the station's CPU and
//! what its clients received.

use clap::Args;
use labrig_launch::clients::station_beside;
use labrig_launch::measure::{LoopArgs, measure};
use serde_json::{Value, json};
use std::process::ExitCode;

#[derive(Debug, Args)]
pub struct StationArgs {
    /// How long each run lasts.
    #[arg(long, default_value_t = 60.0)]
    pub seconds: f64,
    /// Foxglove clients beside the page.
    #[arg(long, default_value_t = 3)]
    pub clients: usize,
    #[arg(long, default_value_t = 44)]
    pub domain_id: u16,
    #[arg(long)]
    pub json: bool,
}

pub fn run(a: StationArgs) -> anyhow::Result<ExitCode> {
    anyhow::ensure!((10.0..=3600.0).contains(&a.seconds), "--seconds must be in [10, 3600]");
    anyhow::ensure!(a.clients <= 16, "--clients must be at most 16");
    let out = std::env::temp_dir().join(format!("labrig-bench-station-{}", std::process::id()));
    let loop_args =
        |json: bool| LoopArgs { seconds: a.seconds, width: 128, height: 128, out: None, domain_id: a.domain_id, json };
    // 1. The rig alone.
    let alone_dir = out.join("alone");
    std::fs::create_dir_all(&alone_dir)?;
    if !a.json {
        eprintln!("1/2: the rig alone for {:.0} s", a.seconds);
    }
    let alone = measure(&loop_args(a.json), &alone_dir, None)?;
    // 2. With the station, its page and the Foxglove clients.
    let with_dir = out.join("with_station");
    std::fs::create_dir_all(&with_dir)?;
    let beside = station_beside(&with_dir.join("episodes"), a.clients)?;
    if !a.json {
        eprintln!("2/2: the rig with the station, its page and {} Foxglove clients for {:.0} s", a.clients, a.seconds);
    }
    let with = measure(&loop_args(a.json), &with_dir, Some(beside))?;
    let _ = std::fs::remove_dir_all(&out);
    let p99 = |r: &Value| r["tick_jitter_us"]["p99"].as_f64().unwrap_or(f64::NAN);
    let ratio = p99(&with) / p99(&alone);
    let report = json!({"alone": alone, "with_station": with, "p99_jitter_ratio": ratio});
    if a.json {
        println!("{report}");
        return Ok(ExitCode::SUCCESS);
    }
    println!(
        "labrig bench station: the demo's rig in real time, {:.0} s each (a shared 2-core machine: noisy)",
        a.seconds
    );
    println!("  {:<34} {:>14} {:>14}", "", "alone", "with station");
    let row = |name: &str, f: &dyn Fn(&Value) -> String| println!("  {name:<34} {:>14} {:>14}", f(&alone), f(&with));
    let num = |v: &Value| v.as_f64().map_or("-".into(), |x| format!("{x:.0}"));
    row("tick jitter p50 (us)", &|r| num(&r["tick_jitter_us"]["p50"]));
    row("tick jitter p99 (us)", &|r| num(&r["tick_jitter_us"]["p99"]));
    row("tick jitter max (us)", &|r| num(&r["tick_jitter_us"]["max"]));
    row("missed ticks", &|r| r["missed_ticks"].to_string());
    row("camera skew p99 (us)", &|r| num(&r["camera_skew_us"]["p99"]));
    row("steps with a stale frame", &|r| r["steps_stale_frames"].to_string());
    row("recorded episodes", &|r| r["recorded_episodes"].to_string());
    row("dropped frames", &|r| r["dropped_frames"].to_string());
    row("flagged episodes", &|r| r["flagged_episodes"].to_string());
    row("cpu labrig-recorder (% of a core)", &|r| num(&r["cpu_percent"]["labrig-recorder"]));
    row("cpu labrig-control (% of a core)", &|r| num(&r["cpu_percent"]["labrig-control"]));
    row("cpu labrig-station (% of a core)", &|r| num(&r["cpu_percent"]["labrig-station"]));
    println!("  p99 jitter with / alone: {ratio:.2}");
    let l = &with["load"];
    println!(
        "  the page: {} requests ({:.1} MB, {} refused, {} unanswered); Foxglove: {}",
        l["page"]["requests"],
        l["page"]["bytes"].as_f64().unwrap_or(0.0) / 1e6,
        l["page"]["refused"],
        l["page"]["errors"],
        l["foxglove"]
            .as_array()
            .into_iter()
            .flatten()
            .map(|c| format!("{} msgs on {} channels", c["messages"], c["channels"]))
            .collect::<Vec<_>>()
            .join(", ")
    );
    Ok(ExitCode::SUCCESS)
}
