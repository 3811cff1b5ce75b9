//! The clients of the operator station that the benches run beside a rig (`labrig bench
//! station`, `labrig bench soak`): its page's polling, as the page does it, and Foxglove
//! WebSocket clients subscribed to every channel.

use serde_json::{Value, json};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

/// The page's polling, as the page does it; returns what it fetched.
pub fn page_client(base: String, stop: Arc<AtomicBool>) -> Value {
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
pub fn foxglove_client(url: String, stop: Arc<AtomicBool>) -> Value {
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

/// A free TCP port on 127.0.0.1 (for a station started beside a measurement).
pub fn free_port() -> anyhow::Result<u16> {
    Ok(std::net::TcpListener::bind("127.0.0.1:0")?.local_addr()?.port())
}

/// The station as a node beside a measured rig (serving `root` on a free port of 127.0.0.1),
/// with its load: the page's polling and `clients` Foxglove clients, started once the port
/// answers; the load returns what each client received.
pub fn station_beside(root: &std::path::Path, clients: usize) -> anyhow::Result<crate::measure::Beside> {
    let port = free_port()?;
    let node = crate::config::NodeSpec {
        name: "station".into(),
        program: "labrig-station".into(),
        args: vec![
            "run".into(),
            "--root".into(),
            root.display().to_string(),
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
    Ok(crate::measure::Beside { node, load })
}
