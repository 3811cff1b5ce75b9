//! `labrig bench station`: is the operator station felt? The demo's rig in real time (as
//! `labrig bench loop` runs it) measured twice: alone, then with the station beside it, its
//! page's traffic (status 4 times a second, the five thumbnails 4 times a second, the episode
//! list every 3 s, as the page polls) and three Foxglove clients subscribed to every channel.
//! Reports the loop's tick jitter (p50/p99/max), missed ticks, camera skew, dropped frames and
//! flagged episodes of each run side by side, the ratio of the p99s, the station's CPU and
//! what its clients received.

use clap::Args;
use labrig_launch::config::NodeSpec;
use labrig_launch::measure::{Beside, LoopArgs, measure};
use serde_json::{Value, json};
use std::process::ExitCode;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

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

/// The page's polling, as the page does it; returns what it fetched.
fn page_client(base: String, stop: Arc<AtomicBool>) -> Value {
    let agent = ureq::AgentBuilder::new().timeout(Duration::from_secs(5)).build();
    // `refused`: answered with an error status (a camera with no frame yet answers 503);
    // `errors`: no answer at all.
    let (mut requests, mut bytes, mut errors, mut refused) = (0u64, 0u64, 0u64, 0u64);
    let mut last_list = Instant::now() - Duration::from_secs(10);
    let mut get = |path: &str| match agent.get(&format!("{base}{path}")).call() {
        Ok(r) => {
            let mut b = Vec::new();
            let _ = std::io::Read::read_to_end(&mut r.into_reader(), &mut b);
            requests += 1;
            bytes += b.len() as u64;
        }
        Err(ureq::Error::Status(..)) => refused += 1,
        Err(_) => errors += 1,
    };
    while !stop.load(Ordering::Relaxed) {
        let t = Instant::now();
        get("/api/status");
        for c in labrig_msgs::rig::RIG_CAMERAS {
            get(&format!("/api/cameras/{c}.jpg"));
        }
        if last_list.elapsed() > Duration::from_secs(3) {
            last_list = Instant::now();
            get("/api/episodes");
        }
        std::thread::sleep(Duration::from_millis(250).saturating_sub(t.elapsed()));
    }
    json!({"requests": requests, "bytes": bytes, "errors": errors, "refused": refused})
}

/// A Foxglove client subscribed to every advertised channel; returns what it received.
fn foxglove_client(url: String, stop: Arc<AtomicBool>) -> Value {
    use tungstenite::client::IntoClientRequest;
    let mut req = match url.as_str().into_client_request() {
        Ok(r) => r,
        Err(e) => return json!({"error": e.to_string()}),
    };
    req.headers_mut().insert("sec-websocket-protocol", "foxglove.websocket.v1".parse().expect("static header"));
    let (mut ws, _) = match tungstenite::connect(req) {
        Ok(c) => c,
        Err(e) => return json!({"error": e.to_string()}),
    };
    if let tungstenite::stream::MaybeTlsStream::Plain(s) = ws.get_ref() {
        let _ = s.set_read_timeout(Some(Duration::from_millis(200)));
    }
    let (mut messages, mut bytes, mut channels) = (0u64, 0u64, 0usize);
    while !stop.load(Ordering::Relaxed) {
        match ws.read() {
            Ok(tungstenite::Message::Text(t)) => {
                let v: Value = serde_json::from_str(&t).unwrap_or(Value::Null);
                if v["op"] == "advertise" {
                    let subs: Vec<Value> = v["channels"]
                        .as_array()
                        .into_iter()
                        .flatten()
                        .map(|c| json!({"id": c["id"], "channelId": c["id"]}))
                        .collect();
                    channels = subs.len();
                    let _ = ws.send(tungstenite::Message::Text(
                        json!({"op": "subscribe", "subscriptions": subs}).to_string().into(),
                    ));
                }
            }
            Ok(tungstenite::Message::Binary(b)) => {
                messages += 1;
                bytes += b.len() as u64;
            }
            Ok(_) => {}
            Err(tungstenite::Error::Io(e))
                if matches!(e.kind(), std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut) => {}
            Err(e) => return json!({"error": e.to_string(), "messages": messages}),
        }
    }
    let _ = ws.close(None);
    json!({"channels": channels, "messages": messages, "bytes": bytes})
}

fn free_port() -> anyhow::Result<u16> {
    Ok(std::net::TcpListener::bind("127.0.0.1:0")?.local_addr()?.port())
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
    let port = free_port()?;
    let node = NodeSpec {
        name: "station".into(),
        program: "labrig-station".into(),
        args: vec![
            "run".into(),
            "--root".into(),
            with_dir.join("episodes").display().to_string(),
            "--listen".into(),
            format!("127.0.0.1:{port}"),
        ],
        config: None,
        after: vec!["control".into()],
        health: labrig_msgs::topics::STATION_STATUS.name.into(),
        on_failure: None,
        max_restarts: 0,
        completes: false,
        env: Default::default(),
    };
    let clients = a.clients;
    let load = Box::new(move |stop: Arc<AtomicBool>| {
        std::thread::spawn(move || {
            let base = format!("http://127.0.0.1:{port}");
            // The station is up once its port answers.
            let t0 = Instant::now();
            while std::net::TcpStream::connect(("127.0.0.1", port)).is_err() && t0.elapsed() < Duration::from_secs(30) {
                std::thread::sleep(Duration::from_millis(100));
            }
            let page = {
                let (b, s) = (base.clone(), stop.clone());
                std::thread::spawn(move || page_client(b, s))
            };
            let fox: Vec<_> = (0..clients)
                .map(|_| {
                    let (u, s) = (format!("ws://127.0.0.1:{port}/foxglove"), stop.clone());
                    std::thread::spawn(move || foxglove_client(u, s))
                })
                .collect();
            let page = page.join().unwrap_or(Value::Null);
            let fox: Vec<Value> = fox.into_iter().map(|t| t.join().unwrap_or(Value::Null)).collect();
            json!({"page": page, "foxglove": fox})
        })
    });
    if !a.json {
        eprintln!("2/2: the rig with the station, its page and {} Foxglove clients for {:.0} s", a.clients, a.seconds);
    }
    let with = measure(&loop_args(a.json), &with_dir, Some(Beside { node, load }))?;
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
