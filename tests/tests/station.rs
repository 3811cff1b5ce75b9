//! `labrig station` on the simulated rig (launch_configs/sim_droid.toml as `labrig launch`
//! starts it, the station on a free loopback port, the scripted expert as the loop's source so
//! an episode the page starts runs until the page or the expert ends it): the page and its API over real HTTP; the
//! cameras' thumbnails update; a session set on the page is in the next episode's metadata
//! (operator and lab in its uuid); start then success from the page records an episode that
//! `labrig inspect` accepts; relabel moves it to failure/ and inspect sees the new flag; the
//! contact sheet; trash moves it to trash/ (never erased); requests without the token or from
//! another origin are refused and reach nothing.

use labrig_tests::{Proc, domain_for, labrig_bin, repo_root};
use serde_json::{Value, json};
use std::io::Read;
use std::process::Command;
use std::time::{Duration, Instant};

struct Http {
    base: String,
    token: String,
}

enum Reply {
    Ok(Vec<u8>),
    Err(u16, String),
}

fn reply(r: Result<ureq::Response, ureq::Error>) -> Reply {
    match r {
        Ok(resp) => {
            let mut b = Vec::new();
            resp.into_reader().read_to_end(&mut b).unwrap();
            Reply::Ok(b)
        }
        Err(ureq::Error::Status(code, resp)) => Reply::Err(code, resp.into_string().unwrap_or_default()),
        Err(e) => Reply::Err(0, e.to_string()),
    }
}

impl Http {
    fn get(&self, path: &str) -> Reply {
        reply(ureq::get(&format!("{}{path}", self.base)).timeout(Duration::from_secs(10)).call())
    }
    fn get_json(&self, path: &str) -> Value {
        match self.get(path) {
            Reply::Ok(b) => serde_json::from_slice(&b).unwrap(),
            Reply::Err(c, e) => panic!("GET {path}: {c} {e}"),
        }
    }
    fn post_with(&self, path: &str, body: &Value, token: Option<&str>, origin: Option<&str>) -> Reply {
        let mut r = ureq::post(&format!("{}{path}", self.base))
            .timeout(Duration::from_secs(10))
            .set("content-type", "application/json");
        if let Some(t) = token {
            r = r.set("x-labrig-token", t);
        }
        if let Some(o) = origin {
            r = r.set("origin", o);
        }
        reply(r.send_string(&body.to_string()))
    }
    fn post(&self, path: &str, body: Value) -> Value {
        let origin = self.base.trim_end_matches('/').to_owned();
        match self.post_with(path, &body, Some(&self.token), Some(&origin)) {
            Reply::Ok(b) => serde_json::from_slice(&b).unwrap(),
            Reply::Err(c, e) => panic!("POST {path}: {c} {e}"),
        }
    }
}

fn wait_for<T>(what: &str, timeout: Duration, mut f: impl FnMut() -> Option<T>) -> T {
    let t0 = Instant::now();
    loop {
        if let Some(v) = f() {
            return v;
        }
        assert!(t0.elapsed() < timeout, "timed out after {timeout:?} waiting for {what}");
        std::thread::sleep(Duration::from_millis(200));
    }
}

/// `labrig inspect --json`: the episode reads whole (exit 0, or 3 when something is flagged: a
/// real-time rig beside a browser on two cores may miss a tick, which inspect rightly names).
fn inspect(dir: &str) -> Value {
    let out = Command::new(labrig_bin()).args(["inspect", "--json", dir]).output().unwrap();
    assert!(matches!(out.status.code(), Some(0 | 3)), "labrig inspect {dir}: {}", labrig_tests::output_text(&out));
    let i: Value = serde_json::from_slice(&out.stdout).unwrap();
    assert!(i["complete"] == true && i["damage"].is_null() && i["steps"].as_u64().unwrap() > 10, "{i}");
    for f in i["flags"].as_array().unwrap() {
        let f = f.as_str().unwrap();
        assert!(
            f.contains("missed control ticks") || f.contains("frames dropped"),
            "flagged for more than timing: {f}"
        );
    }
    i
}

/// sim_droid.toml as `labrig launch` starts it, the station on a free loopback port, episodes
/// under a fresh folder; returns once every node is healthy.
struct Rig {
    proc: Proc,
    port: u16,
    domain: u16,
    dir: tempfile::TempDir,
    stopped: bool,
}

impl Drop for Rig {
    /// A test that failed midway leaves no node running (the launcher's children outlive a
    /// killed launcher).
    fn drop(&mut self) {
        if !self.stopped {
            let _ = Command::new("kill").args(["-INT", &self.proc.child.id().to_string()]).status();
            let _ = self.proc.wait_exit(Duration::from_secs(20));
            labrig_tests::kill_domain(self.domain);
        }
    }
}

/// launch_configs/nodes/teleop_sim_trace.toml's controller trace without its A presses (the
/// controller still moves and grips, so the page shows a live teleop node), written under
/// `dir`; returns the teleop config that plays it.
fn quiet_trace(dir: &std::path::Path) -> String {
    let trace = repo_root().join("nodes/quest_teleop/tests/fixtures/square.logcat");
    let text = std::fs::read_to_string(&trace).unwrap();
    assert!(text.contains(",A,"), "{} has no A press: update this test", trace.display());
    std::fs::write(dir.join("no_buttons.logcat"), text.replace(",A,", ",")).unwrap();
    let cfg = dir.join("teleop_no_buttons.toml");
    std::fs::write(&cfg, "[input]\nkind = \"playback\"\nfile = \"no_buttons.logcat\"\nspeed = 1.0\nrepeat = true\n")
        .unwrap();
    cfg.display().to_string()
}

fn start_rig(name: &str) -> Rig {
    for p in ["labrig-sim", "labrig-franka", "labrig-gripper", "labrig-recorder", "labrig-control", "labrig-teleop"] {
        labrig_tests::workspace_bin(p, p);
    }
    labrig_tests::workspace_bin("labrig-station", "labrig-station");
    let port = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
    let dir = tempfile::tempdir().unwrap();
    let repo_cfg = repo_root().join("launch_configs/sim_droid.toml");
    let text = std::fs::read_to_string(&repo_cfg).unwrap();
    let station_args = "args = [\"run\", \"--root\", \"episodes\"]\nafter = [\"control\"]";
    for line in [
        station_args,
        "\"--hardware-prefix\", \"/sim\"]",
        "\"--source\", \"teleop\", \"--clock\", \"sim\", \"--manual\"]",
    ] {
        assert!(text.contains(line), "sim_droid.toml changed ({line}): update this test");
    }
    let text = text
        .replace(
            station_args,
            &format!(
                "args = [\"run\", \"--root\", \"episodes\", \"--listen\", \"127.0.0.1:{port}\"]\nafter = [\"control\"]"
            ),
        )
        // The scripted expert moves the arm once the page starts an episode.
        .replace(
            "args = [\"run\", \"--mode\", \"realtime\", \"--hardware-prefix\", \"/sim\"]",
            "args = [\"run\", \"--mode\", \"realtime\", \"--hardware-prefix\", \"/sim\", \"--expert\"]",
        )
        .replace(
            "args = [\"run\", \"--source\", \"teleop\", \"--clock\", \"sim\", \"--manual\"]",
            "args = [\"run\", \"--source\", \"scripted\", \"--clock\", \"sim\", \"--manual\"]",
        )
        // The teleop node plays the committed trace with its A presses taken out: the trace
        // presses A (success) every 8.5 s, which ended the page's episode 0.7 s after its
        // Start in a CI run, before the page had seen it run.
        .replace("config = \"nodes/teleop_sim_trace.toml\"", &format!("config = {:?}", quiet_trace(dir.path())));
    let cfg = dir.path().join("sim_droid.toml");
    std::fs::write(&cfg, text).unwrap();
    let domain = domain_for(name);
    let mut cmd = Command::new(labrig_bin());
    cmd.args(["launch", "--json", "--seconds", "240", "--domain-id", &domain.to_string()])
        .arg(&cfg)
        .current_dir(dir.path())
        .env(labrig_runtime::frames::NAMESPACE_ENV, format!("{name}_{}", std::process::id()));
    let mut proc = Proc::spawn("labrig launch", cmd);
    let h = proc.wait_json(Duration::from_secs(120), "every node healthy", |v| {
        v["event"] == "health" && v["nodes"].as_array().is_some_and(|n| n.iter().all(|n| n["up"] == true))
    });
    assert!(h["nodes"].as_array().unwrap().iter().any(|n| n["node"] == "station"), "{h}");
    Rig { proc, port, domain, dir, stopped: false }
}

impl Rig {
    /// Stopped like an operator stops it (SIGINT): every node gone.
    fn stop(mut self) {
        let pid = self.proc.child.id().to_string();
        assert!(Command::new("kill").args(["-INT", &pid]).status().unwrap().success());
        let end = self.proc.wait_json(Duration::from_secs(60), "the stop", |v| v["event"] == "stopped");
        assert!(end.get("error").is_none(), "{end}");
        assert_eq!(self.proc.wait_exit(Duration::from_secs(30)), Some(0));
        let left = labrig_tests::nodes_on_domain(self.domain);
        self.stopped = true;
        assert!(left.is_empty(), "nodes left running: {left}");
    }
}

/// A Node peer (tests/peers/*.mjs) run from the folder setup installed its packages in.
fn node_peer(script: &str, args: &[&str]) -> std::process::Output {
    let peers = std::env::var_os("LABRIG_NODE_PEERS")
        .map(std::path::PathBuf::from)
        .unwrap_or_else(|| labrig_tests::cache_dir().join("node-peers"));
    assert!(
        peers.join("node_modules").is_dir(),
        "{} has no node_modules: run `bash scripts/setup.sh`",
        peers.display()
    );
    // ES modules resolve packages beside the script: it runs from there.
    let copy = peers.join(script);
    std::fs::copy(repo_root().join("tests/peers").join(script), &copy).unwrap();
    let node = std::env::var("LABRIG_NODE").unwrap_or_else(|_| "node".into());
    Command::new(node).arg(&copy).args(args).output().unwrap()
}

#[test]
fn the_station_runs_a_session_from_the_page_on_the_simulated_rig() {
    let rig = start_rig("station_sim_droid");
    let (port, dir) = (rig.port, rig.dir.path().to_owned());
    let mut rig = rig;

    // The page, with the token it gives (loopback).
    let mut http = Http { base: format!("http://127.0.0.1:{port}"), token: String::new() };
    let page = match http.get("/") {
        Reply::Ok(b) => String::from_utf8(b).unwrap(),
        Reply::Err(c, e) => panic!("GET /: {c} {e}"),
    };
    assert!(page.contains("<title>labrig station</title>"));
    let at = page.find("let token = \"").unwrap() + "let token = \"".len();
    http.token = page[at..at + page[at..].find('"').unwrap()].to_owned();
    assert!(http.token.len() >= 16, "the loopback page carries the token");

    // Live state: the arm, the loop, the recorder, every camera with frames.
    let status = wait_for("the rig's state and every camera", Duration::from_secs(30), || {
        let s = http.get_json("/api/status");
        let cams_ok = s["cameras"].as_object().unwrap().values().all(|c| c["fps"].as_f64().is_some_and(|f| f > 0.0));
        (s["robot"].is_object() && s["loop"].is_object() && s["recorder"].is_object() && cams_ok).then_some(s)
    });
    assert_eq!(status["robot"]["joints"].as_array().unwrap().len(), 7, "{status}");
    assert_eq!(status["cameras"].as_object().unwrap().len(), 5, "{status}");
    let thumb = |cam: &str| match http.get(&format!("/api/cameras/{cam}.jpg")) {
        Reply::Ok(b) => b,
        Reply::Err(c, e) => panic!("{cam}: {c} {e}"),
    };
    let first = thumb("ext1");
    assert_eq!(&first[..2], &[0xFF, 0xD8], "a JPEG");

    // Foxglove: its own client (@foxglove/ws-protocol) lists the channels, subscribes, and
    // Foxglove's ros2msg/CDR readers decode the joint states and a camera preview.
    let out = node_peer("foxglove_client.mjs", &[&format!("ws://127.0.0.1:{port}/foxglove"), "ext1"]);
    assert!(out.status.success(), "foxglove_client.mjs: {}", labrig_tests::output_text(&out));
    let fox: Value = serde_json::from_slice(&out.stdout).unwrap();
    let topics: Vec<&str> = fox["channels"].as_array().unwrap().iter().map(|c| c["topic"].as_str().unwrap()).collect();
    for t in [
        "/joint_states",
        "/tf",
        "/tf_static",
        "/rig/step",
        "/rig/episode",
        "/cameras/ext1/camera_info",
        "/cameras/wrist/preview/compressed",
    ] {
        assert!(topics.contains(&t), "channel {t} missing: {topics:?}");
    }
    assert!(fox["channels"].as_array().unwrap().iter().all(|c| c["encoding"] == "cdr"), "{fox}");
    let js = &fox["joint_state"];
    assert!(js["position"].as_array().unwrap().len() >= 7 && js["name"][0].as_str().unwrap().contains("joint"), "{js}");
    let img = &fox["image"];
    assert_eq!(
        (img["format"].as_str(), img["jpeg"].as_bool(), img["frame_id"].as_str()),
        (Some("jpeg"), Some(true), Some("ext1_optical")),
        "{img}"
    );

    // Refused: no token, a wrong one, another origin; none reaches the rig.
    let sent_before = http.get_json("/api/status")["requests_sent"].as_u64().unwrap();
    let origin = http.base.clone();
    for (token, org, code) in [
        (None, Some(origin.as_str()), 401),
        (Some("wrong-token"), Some(origin.as_str()), 401),
        (Some(http.token.as_str()), Some("http://evil.example"), 403),
    ] {
        match http.post_with("/api/episode/start", &json!({}), token, org) {
            Reply::Err(c, _) => assert_eq!(c, code, "{token:?} {org:?}"),
            Reply::Ok(_) => panic!("{token:?} {org:?} was let through"),
        }
    }
    assert_eq!(http.get_json("/api/status")["requests_sent"].as_u64().unwrap(), sent_before);

    // The session, then an episode from the page.
    let session = json!({"operator": "alice", "lab": "AUTOLab", "building": "B1", "scene_id": "table_3",
                         "task": "move the arm along x"});
    http.post("/api/session", session.clone());
    // Started once the recorder says it holds the session (the episode's metadata is its).
    wait_for("the recorder holding the session", Duration::from_secs(20), || {
        let s = http.get_json("/api/status");
        (s["recorder"]["seen"]["session"]["operator"] == "alice").then_some(())
    });
    http.post("/api/episode/start", json!({}));
    wait_for("the episode recording", Duration::from_secs(20), || {
        let s = http.get_json("/api/status");
        (s["loop"]["state"] == "Recording" && s["loop"]["steps"].as_u64().unwrap_or(0) >= 20).then_some(())
    });
    // The recorder's status says how large the episode is on disk so far, and it grows (a
    // chunk is closed every 250 ms; the status comes once a second).
    let bytes = || {
        let r = http.get_json("/api/status")["recorder"].clone();
        (r["state"] == "recording").then(|| r["bytes"].as_u64().unwrap_or(0)).filter(|&b| b > 0)
    };
    let b0 = wait_for("the recorder's episode size", Duration::from_secs(10), &bytes);
    wait_for("the episode's size growing", Duration::from_secs(10), || bytes().filter(|&b| b > b0));
    // The arm moves (the expert): the thumbnails change.
    let moving = wait_for("a thumbnail that changed", Duration::from_secs(20), || {
        let t = thumb("ext1");
        (t != first).then_some(t)
    });
    assert_eq!(&moving[..2], &[0xFF, 0xD8]);
    // Success from the page (the expert may have finished first: either way a success).
    http.post("/api/episode/success", json!({}));
    let ep = wait_for("the episode listed", Duration::from_secs(30), || {
        let l = http.get_json("/api/episodes");
        l["episodes"].as_array().unwrap().first().cloned()
    });
    assert_eq!(ep["outcome"], "success", "{ep}");
    assert_eq!((ep["operator"].as_str(), ep["task"].as_str()), (Some("alice"), Some("move the arm along x")), "{ep}");
    assert_eq!(
        (ep["lab"].as_str(), ep["building"].as_str(), ep["scene_id"].as_str()),
        (Some("AUTOLab"), Some("B1"), Some("table_3"))
    );
    let id = ep["id"].as_str().unwrap().to_owned();
    assert!(id.starts_with("AUTOLab+alice+"), "{id}");
    let episodes = dir.join("episodes");
    let found = labrig_episode::episode::find_episodes(&episodes.join("success"));
    assert_eq!(found.len(), 1, "{found:?}");
    let i = inspect(found[0].to_str().unwrap());
    assert_eq!(
        (i["metadata"]["user"].as_str(), i["metadata"]["task_instruction"].as_str()),
        (Some("alice"), Some("move the arm along x"))
    );

    // The contact sheet.
    match http.get(&format!("/api/episodes/{id}/sheet.png")) {
        Reply::Ok(b) => assert!(b.starts_with(b"\x89PNG") && b.len() > 20_000, "{} bytes", b.len()),
        Reply::Err(c, e) => panic!("sheet: {c} {e}"),
    }
    // Relabel: moved to failure/, judged.json beside it, inspect reads the new flag.
    let r = http.post(&format!("/api/episodes/{id}/relabel"), json!({"success": false}));
    assert!(r["dir"].as_str().unwrap().starts_with("failure/"), "{r}");
    let moved = episodes.join(r["dir"].as_str().unwrap());
    assert!(moved.join("judged.json").is_file() && !found[0].exists());
    assert_eq!(inspect(moved.to_str().unwrap())["metadata"]["success"], false);
    let l = http.get_json("/api/episodes");
    assert_eq!(
        (l["episodes"][0]["outcome"].as_str(), l["episodes"][0]["relabeled"].as_bool()),
        (Some("failure"), Some(true))
    );
    // Trash: moved under trash/, the files whole.
    let r = http.post(&format!("/api/episodes/{id}/trash"), json!({}));
    let trashed = episodes.join(r["dir"].as_str().unwrap());
    assert!(r["dir"].as_str().unwrap().starts_with("trash/") && trashed.join("episode_0.mcap").is_file(), "{r}");
    assert_eq!(http.get_json("/api/episodes")["episodes"], json!([]));
    match http.post_with(&format!("/api/episodes/{id}/trash"), &json!({}), Some(&http.token), None) {
        Reply::Err(c, _) => assert_eq!(c, 404, "a trashed episode is no longer listed"),
        Reply::Ok(_) => panic!("trashed twice"),
    }

    // Home while idle: the loop takes the request and says the arm is home (a new Reset event).
    let seq = http.get_json("/api/status")["last_event"]["seq"].as_u64().unwrap_or(0);
    http.post("/api/episode/reset", json!({}));
    wait_for("the loop's Reset after the page's Home", Duration::from_secs(20), || {
        let e = http.get_json("/api/status")["last_event"].clone();
        (e["seq"].as_u64().unwrap_or(0) > seq && e["kind"] == "reset").then_some(())
    });

    // The station dies: the rig goes on (the loop keeps ticking), the launcher starts the
    // station again on the same address, and the page's API answers again.
    let ticks = http.get_json("/api/status")["loop"]["ticks"].as_u64().unwrap();
    let pattern = format!("labrig-station run --root episodes --listen 127.0.0.1:{port}");
    assert!(Command::new("pkill").args(["-KILL", "-f", &pattern]).status().unwrap().success(), "no station to kill");
    let r = rig.proc.wait_json(Duration::from_secs(30), "the station's restart", |v| v["event"] == "restart");
    assert_eq!(r["node"], "station", "{r}");
    // (The loop's status is latched and refreshed each second: the relaunched station may hear
    // the last one first.)
    let s =
        wait_for("the station back, the loop ticking on", Duration::from_secs(30), || match http.get("/api/status") {
            Reply::Ok(b) => serde_json::from_slice::<Value>(&b)
                .ok()
                .filter(|s| s["loop"]["ticks"].as_u64().is_some_and(|t| t > ticks)),
            Reply::Err(..) => None,
        });
    assert_eq!(s["session"]["operator"], "alice", "the session is kept across a restart");

    rig.stop();
}

/// The page itself in a real browser (Debian's chromium, headless, driven by playwright-core:
/// tests/peers/station_browser.mjs): it goes live, the thumbnails change while the arm moves,
/// the session form, Start and Success (clicked) record an episode that `labrig inspect`
/// accepts with the session's operator and task, "to failure" relabels it (judged.json's
/// history), "trash" moves it under trash/; the station frozen, the page says it is
/// disconnected, and live again by itself once the station is thawed. The screenshots are kept
/// for the README.
#[test]
fn the_station_page_records_judges_and_trashes_an_episode_in_a_browser() {
    let rig = start_rig("station_browser");
    let shots = rig.dir.path().join("shots");
    std::fs::create_dir_all(&shots).unwrap();
    // `[n]`: the pattern matches the station, not the script's own command line that holds it.
    let station = format!("labrig-statio[n] run --root episodes --listen 127.0.0.1:{}", rig.port);
    let out = node_peer(
        "station_browser.mjs",
        &[&format!("http://127.0.0.1:{}/", rig.port), shots.to_str().unwrap(), &station],
    );
    let stdout = String::from_utf8_lossy(&out.stdout).into_owned();
    assert!(out.status.success(), "station_browser.mjs: {}", labrig_tests::output_text(&out));
    let stages: Vec<Value> = stdout.lines().filter_map(|l| serde_json::from_str(l).ok()).collect();
    let names: Vec<&str> = stages.iter().map(|s| s["stage"].as_str().unwrap()).collect();
    assert_eq!(
        names,
        ["live", "session", "recording", "recorded", "relabeled", "trashed", "disconnected", "reconnected"],
        "{stdout}"
    );
    assert_eq!(stages[7]["said"], true, "the page's log says it reconnected: {stdout}");
    assert_eq!(stages[0]["cameras"], 5);
    // The thumbnails changed while the arm moved.
    let before = std::fs::read(shots.join("cams_before.png")).unwrap();
    let after = std::fs::read(shots.join("cams_after.png")).unwrap();
    assert!(before.len() > 10_000 && before != after, "the camera thumbnails did not change");
    let id = stages[3]["id"].as_str().unwrap();
    assert!(id.starts_with("RAILab+bob+"), "{id}");
    let cells = stages[3]["cells"].as_array().unwrap();
    assert_eq!((cells[7].as_str(), cells[8].as_str()), (Some("bob"), Some("push the cube forward")), "{cells:?}");
    // On disk: the episode is in trash/, whole; inspect accepts it with the session in its
    // metadata and the relabel in judged.json.
    let trashed = labrig_episode::episode::find_episodes(&rig.dir.path().join("episodes/trash"));
    assert_eq!(trashed.len(), 1, "{trashed:?}");
    let i = inspect(trashed[0].to_str().unwrap());
    let m = &i["metadata"];
    assert_eq!(
        (
            m["user"].as_str(),
            m["lab"].as_str(),
            m["building"].as_str(),
            m["scene_id"].as_str(),
            m["task_instruction"].as_str()
        ),
        (Some("bob"), Some("RAILab"), Some("B2"), Some("kitchen_1"), Some("push the cube forward"))
    );
    assert_eq!(m["success"], false, "relabelled to failure");
    let judged: Value =
        serde_json::from_str(&std::fs::read_to_string(trashed[0].join("judged.json")).unwrap()).unwrap();
    assert_eq!(
        (judged["history"][0]["from"].as_bool(), judged["history"][0]["to"].as_bool()),
        (Some(true), Some(false))
    );
    assert!(judged["history"][0]["by"].as_str().unwrap().contains("bob"), "{judged}");
    assert!(labrig_episode::episode::find_episodes(&rig.dir.path().join("episodes/success")).is_empty());
    assert!(std::fs::metadata(shots.join("page.png")).unwrap().len() > 50_000);
    // LABRIG_STATION_SHOTS=<dir> keeps the screenshots (the README's figure comes from there).
    if let Some(keep) = std::env::var_os("LABRIG_STATION_SHOTS") {
        for f in ["page.png", "cams_before.png", "cams_after.png"] {
            std::fs::copy(shots.join(f), std::path::Path::new(&keep).join(f)).unwrap();
        }
    }
    rig.stop();
}

/// `labrig bench station` (functional, not timing: the figures are the README's): both runs
/// report the loop's jitter and the recordings; the station's page and a Foxglove client
/// were served while the rig ran.
#[test]
fn the_station_bench_measures_the_rig_alone_and_with_the_station() {
    for p in ["labrig-sim", "labrig-recorder", "labrig-control", "labrig-station"] {
        labrig_tests::workspace_bin(p, p);
    }
    let domain = domain_for("bench_station").to_string();
    let out = Command::new(labrig_bin())
        .args(["bench", "station", "--seconds", "10", "--clients", "1", "--json", "--domain-id", &domain])
        .env(labrig_runtime::frames::NAMESPACE_ENV, format!("bench_station_{}", std::process::id()))
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", labrig_tests::output_text(&out));
    let r: Value =
        serde_json::from_slice(&out.stdout).unwrap_or_else(|e| panic!("{e}: {}", labrig_tests::output_text(&out)));
    for run in ["alone", "with_station"] {
        assert!(r[run]["ticks"].as_u64().unwrap() > 100, "{run}: {}", r[run]);
        assert!(r[run]["tick_jitter_us"]["p99"].is_number() && r[run]["dropped_frames"].is_u64(), "{}", r[run]);
    }
    assert!(r["alone"]["cpu_percent"].get("labrig-station").is_none());
    assert!(r["with_station"]["cpu_percent"]["labrig-station"].is_number(), "{}", r["with_station"]);
    let load = &r["with_station"]["load"];
    // Every request answered (a thumbnail asked for before the camera's first frame is a 503).
    assert!(load["page"]["requests"].as_u64().unwrap() > 50 && load["page"]["errors"] == 0, "{load}");
    assert!(load["foxglove"][0]["messages"].as_u64().unwrap() > 100, "{load}");
    assert!(r["p99_jitter_ratio"].is_number());
}

/// `labrig bench soak` at CI size (a minute): the machinery of the hour-long session
/// benchmark, not its figures. Every process of the rig (and the station) is sampled through
/// the run; the loop's windows come from the control loop and add up with its own count of
/// ticks; the episodes the loop ended are the episodes recorded and inspected; the report and
/// the picture are written; and a helper planted beside the rig, growing 300 MB an hour, is
/// named in the verdict with about that rate.
#[test]
fn a_short_soak_samples_every_process_and_names_a_planted_growth() {
    for p in ["labrig-sim", "labrig-recorder", "labrig-control", "labrig-station"] {
        labrig_tests::workspace_bin(p, p);
    }
    let domain = domain_for("bench_soak").to_string();
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("soak");
    let o = Command::new(labrig_bin())
        .args(["bench", "soak", "--minutes", "1", "--warmup-min", "0.25", "--window-min", "0.25", "--sample-s", "3"])
        .args(["--station", "--plant-growth-mb-per-h", "300", "--json", "--domain-id", &domain, "--out"])
        .arg(&out)
        .env(labrig_runtime::frames::NAMESPACE_ENV, format!("bench_soak_{}", std::process::id()))
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", labrig_tests::output_text(&o));
    let r: Value =
        serde_json::from_slice(&o.stdout).unwrap_or_else(|e| panic!("{e}: {}", labrig_tests::output_text(&o)));
    // Every process sampled from start to end (a sample every 3 s over a minute).
    let samples = r["samples"].as_object().unwrap();
    for p in ["labrig-sim", "labrig-control", "labrig-recorder", "labrig-station", "labrig-grow"] {
        let v = samples.get(p).and_then(Value::as_array).unwrap_or_else(|| panic!("{p} not sampled: {samples:?}"));
        assert!(v.len() >= 12, "{p}: {} samples", v.len());
        assert!(v.iter().all(|s| s["rss_bytes"].as_u64().unwrap() > 1_000_000 && s["threads"].as_u64().unwrap() >= 1));
        assert!(v.last().unwrap()["t_s"].as_f64().unwrap() > 50.0, "{p}: sampled to the end");
    }
    // The windows (15 s each) are the control loop's own: their ticks add up to the run's
    // within the part after the last full window.
    let windows = r["windows"].as_array().unwrap();
    assert!(windows.len() >= 3, "{windows:?}");
    let ticks: u64 = windows.iter().map(|w| w["ticks"].as_u64().unwrap()).sum();
    let run_ticks = r["run"]["ticks"].as_u64().unwrap();
    assert!(ticks <= run_ticks && run_ticks - ticks <= 20 * 16, "windows {ticks} of {run_ticks} ticks");
    assert!(windows.iter().all(|w| w["jitter_us"][1].as_f64().unwrap() > 0.0), "{windows:?}");
    // The episodes: what the loop ended is what was recorded, and each was inspected.
    let ended = r["run"]["episodes"].as_u64().unwrap();
    assert!(ended >= 3, "{}", r["run"]);
    assert_eq!(r["episodes"]["episodes"].as_u64(), Some(ended), "{}", r["episodes"]);
    assert_eq!(r["run"]["recorded_episodes"].as_u64(), Some(ended));
    // The planted growth is named, at about its rate; the verdict fails on it.
    let v = &r["verdict"];
    let grower = v["growing"].as_array().unwrap().iter().find(|g| g[0] == "labrig-grow");
    let rate = grower.unwrap_or_else(|| panic!("the planted growth is not named: {v}"))[1].as_f64().unwrap();
    assert!((200.0..400.0).contains(&rate), "planted 300 MB/h, measured {rate}");
    assert_eq!(v["pass"], false);
    assert!(
        v["failed"].as_array().unwrap().iter().any(|f| f.as_str().unwrap().starts_with("labrig-grow grows")),
        "{v}"
    );
    assert!(samples.get("labrig").is_none(), "the soak itself is not among the rig's processes");
    let procs = r["processes"].as_array().unwrap();
    assert!(procs.iter().any(|p| p["name"] == "labrig-station" && p["cpu_percent"].as_f64().unwrap() > 0.0));
    // The report and the picture.
    let report: Value = serde_json::from_str(&std::fs::read_to_string(out.join("soak.json")).unwrap()).unwrap();
    assert_eq!(report["verdict"], *v);
    assert_eq!(&std::fs::read(out.join("soak.png")).unwrap()[..8], b"\x89PNG\r\n\x1a\n");
    // A second soak into the same folder is refused (its episodes would mix).
    let again = Command::new(labrig_bin())
        .args(["bench", "soak", "--minutes", "1", "--warmup-min", "0", "--out"])
        .arg(&out)
        .output()
        .unwrap();
    assert!(!again.status.success() && labrig_tests::output_text(&again).contains("episodes of an earlier soak"));
}
