//! The HTTP side: the page and its JSON API (axum), with the token and origin checks.
//!
//! - `GET /` the page; `GET /api/status` the rig's state; `GET /api/cameras/<id>.jpg[?large=1]`
//!   a camera's newest thumbnail; `GET /api/episodes` the episodes, newest first;
//!   `GET /api/episodes/<id>/sheet.png` an episode's contact sheet.
//! - `POST /api/session` (JSON: operator, lab, building, scene_id, task),
//!   `POST /api/episode/<start|success|failure|discard|stop|reset>` (optional JSON `{"note"}`; a
//!   start without one takes the session's task), `POST /api/episodes/<id>/relabel`
//!   (`{"success": bool}`), `POST /api/episodes/<id>/trash`.
//!
//! Every POST carries the token (header `x-labrig-token`) and, when a browser sends one, an
//! `Origin` equal to the page's own; on loopback the page is given the token, beyond loopback
//! the page asks for it and every API request (GETs too; `?token=` for images) needs it.

use crate::episodes::{Episodes, EpisodesError, check_id};
use crate::live::{Command, Live};
use crate::thumbs::Thumbs;
use crate::{StationConfig, StationStats};
use axum::Router;
use axum::body::Body;
use axum::extract::{Path as UrlPath, Query, Request, State};
use axum::http::{HeaderMap, Method, StatusCode, header};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};
use labrig_msgs::rig::EpisodeEventKind;
use labrig_msgs::session::Session;
use labrig_runtime::Shutdown;
use serde_json::{Value, json};
use std::collections::HashMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Instant;

/// The page (plain HTML + JS, no build step), with `__LABRIG_TOKEN__` filled in on loopback.
const PAGE: &str = include_str!("page.html");

struct App {
    cfg: StationConfig,
    token: String,
    loopback: bool,
    live: Arc<Mutex<Live>>,
    thumbs: Thumbs,
    episodes: Mutex<Episodes>,
    commands: tokio::sync::mpsc::UnboundedSender<Command>,
    started: Instant,
    requests: AtomicU64,
    hub: Arc<crate::foxglove::Hub>,
    shutdown: Shutdown,
}

type Shared = Arc<App>;

fn error(status: StatusCode, msg: impl Into<String>) -> Response {
    (status, axum::Json(json!({ "error": msg.into() }))).into_response()
}

/// Equal in constant time (a token compare leaks no prefix length).
fn same(a: &str, b: &str) -> bool {
    a.len() == b.len() && a.bytes().zip(b.bytes()).fold(0u8, |acc, (x, y)| acc | (x ^ y)) == 0
}

fn token_of(headers: &HeaderMap, query: Option<&str>) -> Option<String> {
    if let Some(t) = headers.get("x-labrig-token").and_then(|v| v.to_str().ok()) {
        return Some(t.to_owned());
    }
    query?.split('&').find_map(|kv| kv.strip_prefix("token=")).map(str::to_owned)
}

/// The checks every API request passes: the token (POSTs always; beyond loopback every
/// request) and, for POSTs from a browser, the page's own origin.
async fn guard(State(app): State<Shared>, req: Request, next: Next) -> Response {
    app.requests.fetch_add(1, Ordering::Relaxed);
    let path = req.uri().path().to_owned();
    let headers = req.headers();
    if path == "/foxglove" {
        // A WebSocket is not held to the same-origin rule: on loopback, a browser page may
        // connect only from this station's own origin or Foxglove's web app; anything else,
        // and everything beyond loopback, needs the token.
        let origin = headers.get(header::ORIGIN).and_then(|v| v.to_str().ok());
        let host = headers.get(header::HOST).and_then(|v| v.to_str().ok()).unwrap_or("");
        let trusted = origin.is_none_or(|o| o == format!("http://{host}") || o == "https://app.foxglove.dev");
        if !(app.loopback && trusted) {
            match token_of(headers, req.uri().query()) {
                Some(t) if same(&t, &app.token) => {}
                _ => {
                    return error(
                        StatusCode::UNAUTHORIZED,
                        "the Foxglove connection needs ?token=<the station's token>",
                    );
                }
            }
        }
        return next.run(req).await;
    }
    if !path.starts_with("/api/") {
        return next.run(req).await;
    }
    let is_post = req.method() == Method::POST;
    if is_post || !app.loopback {
        match token_of(headers, req.uri().query()) {
            Some(t) if same(&t, &app.token) => {}
            Some(_) => return error(StatusCode::UNAUTHORIZED, "wrong token"),
            None => return error(StatusCode::UNAUTHORIZED, "this request needs the station's token (x-labrig-token)"),
        }
    }
    if is_post && let Some(origin) = headers.get(header::ORIGIN).and_then(|v| v.to_str().ok()) {
        let host = headers.get(header::HOST).and_then(|v| v.to_str().ok()).unwrap_or("");
        if origin != format!("http://{host}") && origin != format!("https://{host}") {
            return error(StatusCode::FORBIDDEN, format!("origin {origin} is not this station's (http://{host})"));
        }
    }
    next.run(req).await
}

async fn page(State(app): State<Shared>) -> Response {
    let token = if app.loopback { app.token.as_str() } else { "" };
    let html = PAGE.replace("__LABRIG_TOKEN__", token);
    ([(header::CONTENT_TYPE, "text/html; charset=utf-8"), (header::CACHE_CONTROL, "no-store")], html).into_response()
}

async fn status(State(app): State<Shared>) -> Response {
    let mut v = app.live.lock().expect("live state").status(app.cfg.calibration_max_age_s);
    let cams: serde_json::Map<String, Value> = {
        let thumbs = app.thumbs.lock().expect("thumbnails");
        app.cfg
            .cameras
            .iter()
            .map(|c| {
                let t = thumbs.get(c);
                (
                    c.clone(),
                    json!({"fps": t.map(|t| t.fps), "age_s": t.map(|t| t.made.elapsed().as_secs_f64()),
                           "sequence": t.map(|t| t.sequence), "capture_ns": t.map(|t| t.capture_ns)}),
                )
            })
            .collect()
    };
    if let Some(o) = v.as_object_mut() {
        o.insert("cameras".into(), Value::Object(cams));
        o.insert(
            "station".into(),
            json!({"listen": app.cfg.listen, "root": app.cfg.root, "loopback": app.loopback,
                   "up_s": app.started.elapsed().as_secs_f64()}),
        );
    }
    axum::Json(v).into_response()
}

async fn camera(
    State(app): State<Shared>,
    UrlPath(file): UrlPath<String>,
    Query(q): Query<HashMap<String, String>>,
) -> Response {
    let Some(cam) = file.strip_suffix(".jpg") else { return error(StatusCode::NOT_FOUND, "cameras are <id>.jpg") };
    if !app.cfg.cameras.iter().any(|c| c == cam) {
        return error(StatusCode::NOT_FOUND, format!("no camera {cam:?} (cameras: {})", app.cfg.cameras.join(", ")));
    }
    let Some(t) = app.thumbs.lock().expect("thumbnails").get(cam).cloned() else {
        return error(StatusCode::SERVICE_UNAVAILABLE, format!("no frame from {cam} yet"));
    };
    let bytes = if q.contains_key("large") {
        match t.large_jpeg() {
            Some(b) => b,
            None => return error(StatusCode::INTERNAL_SERVER_ERROR, format!("encoding {cam}'s enlarged view")),
        }
    } else {
        t.jpeg.to_vec()
    };
    ([(header::CONTENT_TYPE, "image/jpeg"), (header::CACHE_CONTROL, "no-store")], Body::from(bytes)).into_response()
}

/// Runs blocking episode work off the async threads.
async fn with_episodes<T: Send + 'static>(
    app: &Shared,
    f: impl FnOnce(&mut Episodes, &std::path::Path) -> Result<T, EpisodesError> + Send + 'static,
) -> Result<T, Response> {
    let app = app.clone();
    let r = tokio::task::spawn_blocking(move || {
        let mut e = app.episodes.lock().expect("episodes");
        f(&mut e, &app.cfg.root)
    })
    .await
    .map_err(|e| error(StatusCode::INTERNAL_SERVER_ERROR, e.to_string()))?;
    r.map_err(|e| match e {
        EpisodesError::Unknown(_) => error(StatusCode::NOT_FOUND, e.to_string()),
        EpisodesError::BadId(_) => error(StatusCode::BAD_REQUEST, e.to_string()),
        other => error(StatusCode::INTERNAL_SERVER_ERROR, other.to_string()),
    })
}

async fn episodes(State(app): State<Shared>) -> Response {
    match with_episodes(&app, |e, root| Ok(e.list(root, crate::episodes::LISTED))).await {
        Ok(list) => axum::Json(json!({ "episodes": list })).into_response(),
        Err(r) => r,
    }
}

async fn sheet(State(app): State<Shared>, UrlPath((id, file)): UrlPath<(String, String)>) -> Response {
    if file != "sheet.png" {
        return error(StatusCode::NOT_FOUND, "an episode has sheet.png");
    }
    match with_episodes(&app, move |e, root| e.sheet(root, &id)).await {
        Ok(png) => ([(header::CONTENT_TYPE, "image/png")], png).into_response(),
        Err(r) => r,
    }
}

#[derive(serde::Deserialize)]
struct RelabelBody {
    success: bool,
}

async fn episode_action(
    State(app): State<Shared>,
    UrlPath((id, action)): UrlPath<(String, String)>,
    body: axum::body::Bytes,
) -> Response {
    if let Err(e) = check_id(&id) {
        return error(StatusCode::BAD_REQUEST, e.to_string());
    }
    let by = {
        let op = app.live.lock().expect("live state").session.operator.clone();
        if op.is_empty() { "station".to_owned() } else { format!("station:{op}") }
    };
    let r = match action.as_str() {
        "relabel" => {
            let Ok(b) = serde_json::from_slice::<RelabelBody>(&body) else {
                return error(StatusCode::BAD_REQUEST, "relabel takes {\"success\": true|false}");
            };
            with_episodes(&app, move |e, root| e.relabel(root, &id, b.success, &by)).await
        }
        "trash" => with_episodes(&app, move |e, root| e.trash(root, &id)).await,
        other => return error(StatusCode::NOT_FOUND, format!("no episode action {other:?} (relabel, trash)")),
    };
    match r {
        Ok(dir) => axum::Json(json!({ "dir": rel(&app.cfg.root, &dir) })).into_response(),
        Err(r) => r,
    }
}

/// `dir` relative to the root, for the page (no absolute paths go out).
fn rel(root: &std::path::Path, dir: &std::path::Path) -> String {
    dir.strip_prefix(root).unwrap_or(dir).display().to_string()
}

#[derive(serde::Deserialize)]
#[serde(deny_unknown_fields)]
struct NoteBody {
    #[serde(default)]
    note: String,
}

async fn episode_event(State(app): State<Shared>, UrlPath(kind): UrlPath<String>, body: axum::body::Bytes) -> Response {
    let k = match kind.as_str() {
        "start" => EpisodeEventKind::Start,
        "success" => EpisodeEventKind::Success,
        "failure" => EpisodeEventKind::Failure,
        "discard" => EpisodeEventKind::Discard,
        "stop" => EpisodeEventKind::Stop,
        // Idle: the loop sends the arm home (after an episode it goes there by itself).
        "reset" => EpisodeEventKind::Reset,
        other => {
            return error(
                StatusCode::NOT_FOUND,
                format!("no event {other:?} (start, success, failure, discard, stop, reset)"),
            );
        }
    };
    // An empty body is no note; a body must be `{"note": "..."}`.
    let mut note = if body.iter().all(u8::is_ascii_whitespace) {
        String::new()
    } else {
        match serde_json::from_slice::<NoteBody>(&body) {
            Ok(b) => b.note,
            Err(e) => return error(StatusCode::BAD_REQUEST, format!("the body is not {{\"note\": \"...\"}}: {e}")),
        }
    };
    if note.len() > labrig_msgs::session::MAX_FIELD || note.chars().any(char::is_control) {
        return error(StatusCode::BAD_REQUEST, "note: at most 200 bytes, no control characters");
    }
    if k == EpisodeEventKind::Start && note.is_empty() {
        note = app.live.lock().expect("live state").session.task.clone();
    }
    if app.commands.send(Command::Episode(k, note.clone())).is_err() {
        return error(StatusCode::SERVICE_UNAVAILABLE, "the station's ROS side is down");
    }
    axum::Json(json!({ "sent": kind, "note": note })).into_response()
}

async fn set_session(State(app): State<Shared>, body: axum::Json<Value>) -> Response {
    let s: Session = match serde_json::from_value(body.0) {
        Ok(s) => s,
        Err(e) => return error(StatusCode::BAD_REQUEST, format!("not a session: {e}")),
    };
    if let Err(e) = s.validate() {
        return error(StatusCode::BAD_REQUEST, e.to_string());
    }
    let path = app.cfg.session_path();
    if let Err(e) = save_session(&path, &s) {
        return error(StatusCode::INTERNAL_SERVER_ERROR, format!("keeping the session in {}: {e}", path.display()));
    }
    if app.commands.send(Command::Session(s.clone())).is_err() {
        return error(StatusCode::SERVICE_UNAVAILABLE, "the station's ROS side is down");
    }
    axum::Json(json!({ "session": s })).into_response()
}

fn save_session(path: &std::path::Path, s: &Session) -> std::io::Result<()> {
    if let Some(p) = path.parent() {
        std::fs::create_dir_all(p)?;
    }
    let tmp = path.with_extension("json.tmp");
    std::fs::write(&tmp, serde_json::to_string_pretty(s).expect("plain data"))?;
    std::fs::rename(&tmp, path)
}

fn load_session(path: &std::path::Path) -> Session {
    match std::fs::read_to_string(path) {
        Ok(t) => serde_json::from_str(&t).unwrap_or_else(|e| {
            tracing::warn!("{}: not a session ({e}): starting with an empty one", path.display());
            Session::default()
        }),
        Err(_) => Session::default(),
    }
}

async fn foxglove_ws(State(app): State<Shared>, ws: axum::extract::WebSocketUpgrade) -> Response {
    let (hub, stop) = (app.hub.clone(), app.shutdown.clone());
    let started_ms =
        std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map(|d| d.as_millis() as u64).unwrap_or(0);
    ws.protocols([crate::foxglove::SUBPROTOCOL])
        .on_upgrade(move |socket| crate::foxglove::serve(socket, hub, started_ms, stop))
}

/// The channels Foxglove is offered.
fn hub_for(cfg: &StationConfig) -> crate::foxglove::Hub {
    use labrig_msgs::RosMessage;
    use labrig_msgs::rig::{EpisodeEvent, Step};
    use labrig_msgs::sensor_msgs::{CameraInfo, CompressedImage, JointState};
    use labrig_msgs::tf2_msgs::TFMessage;
    use labrig_msgs::{schema_text, topics};
    let mut hub = crate::foxglove::Hub::default();
    hub.add(topics::JOINT_STATES.name, JointState::TYPE_NAME, schema_text::<JointState>(), false);
    hub.add(topics::TF.name, TFMessage::TYPE_NAME, schema_text::<TFMessage>(), false);
    hub.add(topics::TF_STATIC.name, TFMessage::TYPE_NAME, schema_text::<TFMessage>(), true);
    hub.add(topics::RIG_STEP.name, Step::TYPE_NAME, schema_text::<Step>(), false);
    hub.add(topics::RIG_EPISODE.name, EpisodeEvent::TYPE_NAME, schema_text::<EpisodeEvent>(), true);
    for c in &cfg.cameras {
        hub.add(&topics::camera_info(c), CameraInfo::TYPE_NAME, schema_text::<CameraInfo>(), false);
        hub.add(&crate::thumbs::preview_topic(c), CompressedImage::TYPE_NAME, schema_text::<CompressedImage>(), false);
    }
    hub
}

fn router(app: Shared) -> Router {
    Router::new()
        .route("/", get(page))
        .route("/foxglove", get(foxglove_ws))
        .route("/api/status", get(status))
        .route("/api/cameras/{file}", get(camera))
        .route("/api/episodes", get(episodes))
        .route("/api/episodes/{id}/{file}", get(sheet).post(episode_action))
        .route("/api/episode/{kind}", post(episode_event))
        .route("/api/session", post(set_session))
        .layer(axum::middleware::from_fn_with_state(app.clone(), guard))
        .with_state(app)
}

fn random_token() -> String {
    use rand::Rng;
    let mut r = rand::rng();
    (0..32).map(|_| format!("{:x}", r.random_range(0..16u8))).collect()
}

/// The station until `shutdown`: the ROS side on this task, thumbnails on their thread, the
/// server on the runtime.
pub async fn run(cfg: StationConfig, shutdown: Shutdown) -> anyhow::Result<StationStats> {
    let addr: std::net::SocketAddr = cfg.listen.parse()?;
    let loopback = addr.ip().is_loopback();
    let token = cfg.token.clone().unwrap_or_else(random_token);
    let live = Arc::new(Mutex::new(Live { session: load_session(&cfg.session_path()), ..Live::default() }));
    let hub = Arc::new(hub_for(&cfg));
    let (thumbs, thumbs_thread) = crate::thumbs::spawn(
        cfg.frames_namespace.clone(),
        cfg.cameras.clone(),
        cfg.thumbnail_hz,
        cfg.thumbnail_width,
        hub.clone(),
        shutdown.clone(),
    )?;
    let (tx, rx) = tokio::sync::mpsc::unbounded_channel();
    let listener = tokio::net::TcpListener::bind(addr)
        .await
        .map_err(|e| anyhow::anyhow!("listening on {addr}: {e} (another station, or --listen elsewhere)"))?;
    let bound = listener.local_addr()?;
    let app: Shared = Arc::new(App {
        cfg: StationConfig { listen: bound.to_string(), ..cfg.clone() },
        token,
        loopback,
        live: live.clone(),
        thumbs,
        episodes: Mutex::new(Episodes::default()),
        commands: tx,
        started: Instant::now(),
        requests: AtomicU64::new(0),
        hub: hub.clone(),
        shutdown: shutdown.clone(),
    });
    tracing::info!(url = %format!("http://{bound}/"), root = %cfg.root.display(), loopback, "station up");
    // For the operator at a terminal (stderr: a node's stdout is left to its stats).
    eprintln!("labrig station: http://{bound}/");
    let server = {
        let stop = shutdown.clone();
        let app = app.clone();
        tokio::spawn(async move {
            axum::serve(listener, router(app)).with_graceful_shutdown(async move { stop.wait().await }).await
        })
    };
    let url = format!("http://{bound}/");
    let ros = crate::live::run(&cfg.ros, &url, hub, live.clone(), rx, shutdown.clone()).await;
    shutdown.trigger();
    let served = server.await;
    let _ = thumbs_thread.join();
    ros?;
    served??;
    let sent = live.lock().expect("live state").sent;
    Ok(StationStats { requests: app.requests.load(Ordering::Relaxed), events_sent: sent })
}

/// For tests: the router on an app with no ROS side and no cameras.
#[doc(hidden)]
pub fn test_router(
    cfg: StationConfig,
    token: &str,
    loopback: bool,
) -> (Router, tokio::sync::mpsc::UnboundedReceiver<Command>) {
    let (tx, rx) = tokio::sync::mpsc::unbounded_channel();
    let app = Arc::new(App {
        token: token.to_owned(),
        loopback,
        live: Arc::default(),
        thumbs: Arc::default(),
        episodes: Mutex::new(Episodes::default()),
        hub: Arc::new(hub_for(&cfg)),
        cfg,
        commands: tx,
        started: Instant::now(),
        requests: AtomicU64::new(0),
        shutdown: Shutdown::new(),
    });
    (router(app), rx)
}

#[cfg(test)]
mod tests {
    use super::*;
    use axum::http::Request as HttpRequest;
    use tower::ServiceExt;

    const TOKEN: &str = "s3cret-token-1234";

    async fn call(
        router: &Router,
        method: &str,
        uri: &str,
        headers: &[(&str, &str)],
        body: &str,
    ) -> (StatusCode, String) {
        let mut b = HttpRequest::builder().method(method).uri(uri).header("host", "127.0.0.1:8080");
        for (k, v) in headers {
            b = b.header(*k, *v);
        }
        let r = router.clone().oneshot(b.body(Body::from(body.to_owned())).unwrap()).await.unwrap();
        let status = r.status();
        let bytes = axum::body::to_bytes(r.into_body(), 1 << 20).await.unwrap();
        (status, String::from_utf8_lossy(&bytes).into_owned())
    }

    fn cfg(root: &std::path::Path) -> StationConfig {
        StationConfig { root: root.to_owned(), ..StationConfig::default() }
    }

    #[tokio::test]
    async fn posts_need_the_token_and_the_pages_origin() {
        let dir = tempfile::tempdir().unwrap();
        let (router, mut rx) = test_router(cfg(dir.path()), TOKEN, true);
        let json = [("content-type", "application/json")];
        // On loopback the page carries the token and reads need none.
        let (s, page) = call(&router, "GET", "/", &[], "").await;
        assert!(s.is_success() && page.contains(TOKEN));
        assert_eq!(call(&router, "GET", "/api/status", &[], "").await.0, StatusCode::OK);
        // A POST without the token, with a wrong one, from another origin: refused.
        let (s, e) = call(&router, "POST", "/api/episode/start", &json, "{}").await;
        assert_eq!(s, StatusCode::UNAUTHORIZED, "{e}");
        let wrong = [("content-type", "application/json"), ("x-labrig-token", "nope-nope-nope")];
        assert_eq!(call(&router, "POST", "/api/episode/start", &wrong, "{}").await.0, StatusCode::UNAUTHORIZED);
        let evil = [("content-type", "application/json"), ("x-labrig-token", TOKEN), ("origin", "http://evil.example")];
        let (s, e) = call(&router, "POST", "/api/episode/start", &evil, "{}").await;
        assert!(s == StatusCode::FORBIDDEN && e.contains("is not this station's"), "{s} {e}");
        assert!(rx.try_recv().is_err(), "nothing refused reached the rig");
        // With both: the request goes to the rig, a Start with the session's task.
        let ok = [("content-type", "application/json"), ("x-labrig-token", TOKEN), ("origin", "http://127.0.0.1:8080")];
        let (s, e) = call(&router, "POST", "/api/session", &ok, r#"{"operator": "alice", "task": "wipe"}"#).await;
        assert_eq!(s, StatusCode::OK, "{e}");
        assert!(matches!(rx.try_recv(), Ok(Command::Session(s)) if s.operator == "alice"));
        assert!(dir.path().join("session.json").is_file(), "the session is kept");
        let (s, e) = call(&router, "POST", "/api/session", &ok, r#"{"operator": "a b"}"#).await;
        assert!(s == StatusCode::BAD_REQUEST && e.contains("part of the episode's uuid"), "{e}");
        assert_eq!(call(&router, "POST", "/api/episode/start", &ok, "{}").await.0, StatusCode::OK);
        // (The test router has no ROS side to keep the session: the note is the request's.)
        assert!(matches!(rx.try_recv(), Ok(Command::Episode(EpisodeEventKind::Start, _))));
        let (s, _) = call(&router, "POST", "/api/episode/launch", &ok, "{}").await;
        assert_eq!(s, StatusCode::NOT_FOUND);
        // Episode ids are checked before anything is looked up.
        let (s, e) = call(&router, "POST", "/api/episodes/..%2Fx/trash", &ok, "").await;
        assert!(s == StatusCode::BAD_REQUEST && e.contains("not an episode id"), "{s} {e}");
        let (s, _) = call(&router, "POST", "/api/episodes/LAB+a+2026/trash", &ok, "").await;
        assert_eq!(s, StatusCode::NOT_FOUND);
        let (s, _) = call(&router, "GET", "/api/cameras/ext9.jpg", &[], "").await;
        assert_eq!(s, StatusCode::NOT_FOUND);
    }

    #[tokio::test]
    async fn beyond_loopback_every_api_request_needs_the_token() {
        let dir = tempfile::tempdir().unwrap();
        let (router, _rx) = test_router(cfg(dir.path()), TOKEN, false);
        let (s, page) = call(&router, "GET", "/", &[], "").await;
        assert!(s.is_success() && !page.contains(TOKEN), "the page asks for the token instead");
        assert_eq!(call(&router, "GET", "/api/status", &[], "").await.0, StatusCode::UNAUTHORIZED);
        assert_eq!(call(&router, "GET", "/api/episodes", &[], "").await.0, StatusCode::UNAUTHORIZED);
        assert_eq!(call(&router, "GET", "/api/status", &[("x-labrig-token", TOKEN)], "").await.0, StatusCode::OK);
        let q = format!("/api/episodes?token={TOKEN}");
        assert_eq!(call(&router, "GET", &q, &[], "").await.0, StatusCode::OK);
    }
}
