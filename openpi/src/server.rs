//! A server speaking openpi's protocol (as `WebsocketPolicyServer` does): on connect the
//! metadata frame, then per binary request one binary reply with `server_timing` added; an
//! error becomes a text frame (the error, traceback-like, last line the reason) and a close
//! with code 1011. `GET /healthz` answers 200 "OK". Requests are answered one at a time across
//! connections, as openpi's single event loop does.

use crate::codec::{self, Value};
use std::io::{self, Read, Write};
use std::net::{SocketAddr, TcpListener, TcpStream};
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};
use tungstenite::protocol::WebSocketConfig;
use tungstenite::protocol::frame::CloseFrame;
use tungstenite::protocol::frame::coding::CloseCode;
use tungstenite::{Message, WebSocket};

/// What a server answers with.
pub trait Handler: Send + Sync + 'static {
    /// Per-connection state (e.g. a policy's observation history).
    type Session: Send + 'static;
    /// Why a request fails; its text (`Display`) is what the client is sent.
    type Error: std::error::Error;
    fn session(&self) -> Self::Session;
    /// The result map for one observation, or the error the client is sent.
    fn infer(&self, session: &mut Self::Session, obs: Value) -> Result<Value, Self::Error>;
}

/// Why a connection ended early (logged, never sent: the client sees the closed socket).
#[derive(Debug, thiserror::Error)]
enum ServerError {
    #[error(transparent)]
    Io(#[from] io::Error),
    #[error("handshake: {0}")]
    Handshake(#[source] tungstenite::Error),
    /// The handshake's read timed out (the stream's read timeout) before the request was whole.
    #[error("handshake: Interrupted handshake (WouldBlock)")]
    HandshakeInterrupted,
    #[error(transparent)]
    WebSocket(#[from] tungstenite::Error),
}

/// Counters of a running server.
#[derive(Debug, Default)]
pub struct ServerCounters {
    pub connections: AtomicU64,
    pub requests: AtomicU64,
    pub errors: AtomicU64,
    pub health_checks: AtomicU64,
}

/// At most this many connections at once; more are answered 503.
pub const MAX_CONNECTIONS: usize = 16;

pub struct Server {
    addr: SocketAddr,
    stop: Arc<AtomicBool>,
    counters: Arc<ServerCounters>,
    thread: Option<JoinHandle<()>>,
}

impl std::fmt::Debug for Server {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Server").field("addr", &self.addr).finish_non_exhaustive()
    }
}

impl Server {
    /// Binds `addr` (e.g. `127.0.0.1:8000`; port 0 picks one) and serves until dropped.
    pub fn bind<H: Handler>(addr: &str, metadata: Value, handler: Arc<H>) -> io::Result<Server> {
        let listener = TcpListener::bind(addr)?;
        listener.set_nonblocking(true)?;
        let addr = listener.local_addr()?;
        let stop = Arc::new(AtomicBool::new(false));
        let counters = Arc::new(ServerCounters::default());
        let thread = {
            let (stop, counters) = (Arc::clone(&stop), Arc::clone(&counters));
            let metadata = codec::pack(&metadata);
            let lock = Arc::new(Mutex::new(()));
            std::thread::Builder::new().name("openpi-accept".into()).spawn(move || {
                let open = Arc::new(AtomicUsize::new(0));
                while !stop.load(Ordering::Relaxed) {
                    match listener.accept() {
                        Ok((stream, peer)) => {
                            let _ = stream.set_nonblocking(false);
                            let (stop, counters, handler, metadata, lock, open) = (
                                Arc::clone(&stop),
                                Arc::clone(&counters),
                                Arc::clone(&handler),
                                metadata.clone(),
                                Arc::clone(&lock),
                                Arc::clone(&open),
                            );
                            let n = open.fetch_add(1, Ordering::SeqCst);
                            let spawned = std::thread::Builder::new().name("openpi-conn".into()).spawn(move || {
                                let r = if n >= MAX_CONNECTIONS {
                                    refuse_busy(stream)
                                } else {
                                    connection(stream, &stop, &counters, &*handler, &metadata, &lock)
                                };
                                if let Err(e) = r {
                                    tracing::debug!(%peer, "openpi connection: {e}");
                                }
                                open.fetch_sub(1, Ordering::SeqCst);
                            });
                            if spawned.is_err() {
                                tracing::warn!("openpi server: cannot start a connection thread");
                            }
                        }
                        Err(e) if e.kind() == io::ErrorKind::WouldBlock => {
                            std::thread::sleep(Duration::from_millis(10));
                        }
                        Err(e) => {
                            tracing::warn!("openpi server: accept: {e}");
                            std::thread::sleep(Duration::from_millis(10));
                        }
                    }
                }
            })?
        };
        Ok(Server { addr, stop, counters, thread: Some(thread) })
    }

    pub fn local_addr(&self) -> SocketAddr {
        self.addr
    }

    pub fn counters(&self) -> &ServerCounters {
        &self.counters
    }
}

impl Drop for Server {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

/// A stream that first replays the bytes already read (the request head looked at for
/// `/healthz`).
struct Replay {
    head: io::Cursor<Vec<u8>>,
    stream: TcpStream,
}

impl Read for Replay {
    fn read(&mut self, buf: &mut [u8]) -> io::Result<usize> {
        if (self.head.position() as usize) < self.head.get_ref().len() {
            return self.head.read(buf);
        }
        self.stream.read(buf)
    }
}

impl Write for Replay {
    fn write(&mut self, buf: &[u8]) -> io::Result<usize> {
        self.stream.write(buf)
    }
    fn flush(&mut self) -> io::Result<()> {
        self.stream.flush()
    }
}

/// Reads the HTTP request head (bounded: 16 KiB, 10 s).
fn read_head(stream: &mut TcpStream) -> io::Result<Vec<u8>> {
    stream.set_read_timeout(Some(Duration::from_secs(10)))?;
    let mut head = Vec::new();
    let mut buf = [0u8; 1024];
    while !head.windows(4).any(|w| w == b"\r\n\r\n") {
        if head.len() > 16 * 1024 {
            return Err(io::Error::new(io::ErrorKind::InvalidData, "request head over 16 KiB"));
        }
        let n = stream.read(&mut buf)?;
        if n == 0 {
            return Err(io::Error::new(io::ErrorKind::UnexpectedEof, "closed before the request head"));
        }
        head.extend_from_slice(&buf[..n]);
    }
    Ok(head)
}

fn path_of(head: &[u8]) -> Option<String> {
    let mut headers = [httparse::EMPTY_HEADER; 64];
    let mut req = httparse::Request::new(&mut headers);
    req.parse(head).ok()?;
    req.path.map(str::to_owned)
}

fn refuse_busy(mut stream: TcpStream) -> Result<(), ServerError> {
    let _ = read_head(&mut stream);
    stream.write_all(b"HTTP/1.1 503 Service Unavailable\r\nContent-Length: 5\r\nConnection: close\r\n\r\nbusy\n")?;
    Ok(())
}

fn connection<H: Handler>(
    mut stream: TcpStream,
    stop: &AtomicBool,
    counters: &ServerCounters,
    handler: &H,
    metadata: &[u8],
    lock: &Mutex<()>,
) -> Result<(), ServerError> {
    let _ = stream.set_nodelay(true);
    let head = read_head(&mut stream)?;
    if path_of(&head).as_deref() == Some("/healthz") {
        counters.health_checks.fetch_add(1, Ordering::Relaxed);
        stream.write_all(
            b"HTTP/1.1 200 OK\r\nContent-Type: text/plain\r\nContent-Length: 3\r\nConnection: close\r\n\r\nOK\n",
        )?;
        return Ok(());
    }
    let config = WebSocketConfig::default().max_message_size(None).max_frame_size(None);
    let replay = Replay { head: io::Cursor::new(head), stream: stream.try_clone()? };
    let mut ws: WebSocket<Replay> = tungstenite::accept_with_config(replay, Some(config)).map_err(|e| match e {
        tungstenite::HandshakeError::Failure(e) => ServerError::Handshake(e),
        tungstenite::HandshakeError::Interrupted(_) => ServerError::HandshakeInterrupted,
    })?;
    counters.connections.fetch_add(1, Ordering::Relaxed);
    // Reads wake every 100 ms to notice the server stopping.
    stream.set_read_timeout(Some(Duration::from_millis(100)))?;
    ws.send(Message::Binary(metadata.to_vec().into()))?;
    let mut session = handler.session();
    let mut prev_total_ms: Option<f64> = None;
    loop {
        if stop.load(Ordering::Relaxed) {
            let _ = ws.close(Some(CloseFrame { code: CloseCode::Away, reason: "server stopping".into() }));
            let _ = ws.flush();
            return Ok(());
        }
        let msg = match ws.read() {
            Ok(m) => m,
            Err(tungstenite::Error::Io(e))
                if matches!(e.kind(), io::ErrorKind::WouldBlock | io::ErrorKind::TimedOut) =>
            {
                continue;
            }
            Err(tungstenite::Error::ConnectionClosed | tungstenite::Error::AlreadyClosed) => return Ok(()),
            Err(e) => return Err(e.into()),
        };
        let bytes = match msg {
            Message::Binary(b) => b,
            Message::Text(_) => {
                fail(&mut ws, counters, "a text frame: openpi requests are binary msgpack frames");
                return Ok(());
            }
            Message::Close(_) => {
                // tungstenite answers the close; drive it out.
                let _ = ws.flush();
                return Ok(());
            }
            _ => continue,
        };
        let start = Instant::now();
        counters.requests.fetch_add(1, Ordering::Relaxed);
        let obs = match codec::unpack(&bytes) {
            Ok(v) => v,
            Err(e) => {
                fail(&mut ws, counters, format_args!("the request is not msgpack: {e}"));
                return Ok(());
            }
        };
        let result = {
            let _one_at_a_time = lock.lock().unwrap_or_else(|p| p.into_inner());
            let t = Instant::now();
            handler.infer(&mut session, obs).map(|r| (r, t.elapsed().as_secs_f64() * 1e3))
        };
        let (mut reply, infer_ms) = match result {
            Ok(r) => r,
            Err(e) => {
                // The handler's error crosses to the client as its text.
                fail(&mut ws, counters, e);
                return Ok(());
            }
        };
        let mut timing = vec![(Value::from("infer_ms"), Value::F64(infer_ms))];
        if let Some(p) = prev_total_ms {
            timing.push((Value::from("prev_total_ms"), Value::F64(p)));
        }
        codec::set(&mut reply, "server_timing", Value::Map(timing));
        ws.send(Message::Binary(codec::pack(&reply).into()))?;
        prev_total_ms = Some(start.elapsed().as_secs_f64() * 1e3);
    }
}

/// openpi's error reply: the error as a text frame, then close 1011.
fn fail<S: Read + Write>(ws: &mut WebSocket<S>, counters: &ServerCounters, error: impl std::fmt::Display) {
    counters.errors.fetch_add(1, Ordering::Relaxed);
    tracing::warn!("openpi request failed: {error}");
    let text = format!("Traceback (labrig-openpi server):\n{error}\n");
    let _ = ws.send(Message::Text(text.into()));
    let _ = ws.close(Some(CloseFrame {
        code: CloseCode::Error,
        reason: "Internal server error. Traceback included in previous frame.".into(),
    }));
    // Let the client's close answer come back (bounded by the read timeouts).
    for _ in 0..20 {
        match ws.read() {
            Err(tungstenite::Error::Io(e))
                if matches!(e.kind(), io::ErrorKind::WouldBlock | io::ErrorKind::TimedOut) => {}
            Err(_) => break,
            Ok(_) => {}
        }
    }
}
