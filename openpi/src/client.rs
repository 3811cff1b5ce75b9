//! A client of openpi's policy server (`WebsocketPolicyServer`): connect, read the server's
//! metadata frame, then one observation out and one result back per call.

use crate::codec::{self, Value};
use std::io;
use std::net::{TcpStream, ToSocketAddrs};
use std::time::{Duration, Instant};
use tungstenite::client::IntoClientRequest;
use tungstenite::protocol::WebSocketConfig;
use tungstenite::{Message, WebSocket};

/// What went wrong talking to an openpi server; each names the server.
#[derive(Debug, thiserror::Error)]
pub enum ClientError {
    #[error("openpi server {url}: cannot connect: {why}")]
    Unreachable { url: String, why: String },
    #[error("openpi server {url}: {why}")]
    Protocol { url: String, why: String },
    /// The server's policy raised: openpi sends the traceback as a text frame, then closes.
    #[error("openpi server {url} failed the request: {last_line}")]
    Server { url: String, traceback: String, last_line: String },
    #[error("openpi server {url} closed the connection: {why}")]
    Closed { url: String, why: String },
    #[error("openpi server {url}: no reply within {seconds:.1} s")]
    Timeout { url: String, seconds: f64 },
}

impl ClientError {
    /// Whether the connection is gone (reconnect, with a new handshake, before the next call).
    pub fn connection_lost(&self) -> bool {
        !matches!(self, ClientError::Protocol { .. })
    }
}

/// `host:port`, `ws://host:port[/path]`: the websocket URL.
pub fn ws_url(addr: &str) -> String {
    if addr.starts_with("ws://") || addr.starts_with("wss://") { addr.to_owned() } else { format!("ws://{addr}") }
}

/// A connection to one server.
pub struct Client {
    url: String,
    ws: WebSocket<TcpStream>,
    metadata: Value,
    /// Set once the connection is unusable (an error frame, a close, a timeout mid-reply).
    broken: bool,
}

impl std::fmt::Debug for Client {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Client").field("url", &self.url).field("broken", &self.broken).finish_non_exhaustive()
    }
}

fn unreachable(url: &str, why: impl ToString) -> ClientError {
    ClientError::Unreachable { url: url.to_owned(), why: why.to_string() }
}

impl Client {
    /// Connects and reads the metadata frame the server sends first; `timeout` bounds the TCP
    /// connect, the handshake and the metadata's arrival.
    pub fn connect(addr: &str, timeout: Duration) -> Result<Client, ClientError> {
        let url = ws_url(addr);
        if url.starts_with("wss://") {
            return Err(unreachable(&url, "wss:// (TLS) is not supported; openpi serves plain ws://"));
        }
        let request = url.as_str().into_client_request().map_err(|e| unreachable(&url, e))?;
        let host = request.uri().host().unwrap_or("").trim_start_matches('[').trim_end_matches(']').to_owned();
        let port = request.uri().port_u16().unwrap_or(80);
        let addrs: Vec<_> = (host.as_str(), port).to_socket_addrs().map_err(|e| unreachable(&url, e))?.collect();
        let mut last = None;
        let mut stream = None;
        for a in addrs {
            match TcpStream::connect_timeout(&a, timeout) {
                Ok(s) => {
                    stream = Some(s);
                    break;
                }
                Err(e) => last = Some(e),
            }
        }
        let stream =
            stream.ok_or_else(|| unreachable(&url, last.map_or_else(|| "no address".to_owned(), |e| e.to_string())))?;
        stream.set_nodelay(true).map_err(|e| unreachable(&url, e))?;
        stream.set_read_timeout(Some(timeout)).map_err(|e| unreachable(&url, e))?;
        stream.set_write_timeout(Some(timeout)).map_err(|e| unreachable(&url, e))?;
        // No size limit, as openpi's own client (images are ~150 kB a request).
        let config = WebSocketConfig::default().max_message_size(None).max_frame_size(None);
        let (ws, _) = tungstenite::client::client_with_config(request, stream, Some(config))
            .map_err(|e| unreachable(&url, format!("websocket handshake: {e}")))?;
        let mut client = Client { url, ws, metadata: Value::Nil, broken: false };
        let first = client.receive(timeout)?;
        client.metadata = first;
        Ok(client)
    }

    pub fn url(&self) -> &str {
        &self.url
    }

    /// The server's metadata (its first frame).
    pub fn metadata(&self) -> &Value {
        &self.metadata
    }

    pub fn is_broken(&self) -> bool {
        self.broken
    }

    /// One observation out, its result back, within `timeout`.
    pub fn infer(&mut self, obs: &Value, timeout: Duration) -> Result<Value, ClientError> {
        if self.broken {
            return Err(ClientError::Closed { url: self.url.clone(), why: "an earlier error ended it".into() });
        }
        let bytes = codec::pack(obs);
        if let Err(e) = self.ws.send(Message::Binary(bytes.into())) {
            self.broken = true;
            return Err(ClientError::Closed { url: self.url.clone(), why: format!("sending: {e}") });
        }
        self.receive(timeout)
    }

    /// The next binary frame as a value; an error frame, a close or a timeout break the
    /// connection (the protocol has no request ids: a late reply would answer the wrong call).
    fn receive(&mut self, timeout: Duration) -> Result<Value, ClientError> {
        let until = Instant::now() + timeout;
        let url = self.url.clone();
        loop {
            let left = until.saturating_duration_since(Instant::now()).max(Duration::from_millis(1));
            let _ = self.ws.get_ref().set_read_timeout(Some(left));
            match self.ws.read() {
                Ok(Message::Binary(b)) => {
                    return codec::unpack(&b).map_err(|e| ClientError::Protocol { url, why: e.to_string() });
                }
                Ok(Message::Text(t)) => {
                    self.broken = true;
                    let traceback = t.to_string();
                    let last_line =
                        traceback.lines().rev().find(|l| !l.trim().is_empty()).unwrap_or("").trim().to_owned();
                    let _ = self.ws.close(None);
                    return Err(ClientError::Server { url, traceback, last_line });
                }
                Ok(Message::Close(frame)) => {
                    self.broken = true;
                    let why = frame.map_or_else(|| "no close frame".to_owned(), |f| format!("{} {}", f.code, f.reason));
                    return Err(ClientError::Closed { url, why });
                }
                Ok(_) => {} // ping / pong (answered by tungstenite)
                Err(tungstenite::Error::Io(e))
                    if matches!(e.kind(), io::ErrorKind::WouldBlock | io::ErrorKind::TimedOut) =>
                {
                    if Instant::now() >= until {
                        self.broken = true;
                        return Err(ClientError::Timeout { url, seconds: timeout.as_secs_f64() });
                    }
                }
                Err(e) => {
                    self.broken = true;
                    return Err(ClientError::Closed { url, why: e.to_string() });
                }
            }
        }
    }
}

impl Drop for Client {
    fn drop(&mut self) {
        if !self.broken {
            let _ = self.ws.get_ref().set_write_timeout(Some(Duration::from_millis(200)));
            let _ = self.ws.close(None);
            let _ = self.ws.flush();
        }
    }
}

/// `GET /healthz` on an openpi server: `Ok(())` for 200.
pub fn healthz(addr: &str, timeout: Duration) -> Result<(), ClientError> {
    use std::io::{Read, Write};
    let url = ws_url(addr);
    let request = url.as_str().into_client_request().map_err(|e| unreachable(&url, e))?;
    let host = request.uri().host().unwrap_or("").to_owned();
    let port = request.uri().port_u16().unwrap_or(80);
    let a = (host.as_str(), port)
        .to_socket_addrs()
        .map_err(|e| unreachable(&url, e))?
        .next()
        .ok_or_else(|| unreachable(&url, "no address"))?;
    let mut s = TcpStream::connect_timeout(&a, timeout).map_err(|e| unreachable(&url, e))?;
    s.set_read_timeout(Some(timeout)).map_err(|e| unreachable(&url, e))?;
    write!(s, "GET /healthz HTTP/1.1\r\nHost: {host}:{port}\r\nConnection: close\r\n\r\n")
        .map_err(|e| unreachable(&url, e))?;
    let mut reply = Vec::new();
    let _ = s.take(4096).read_to_end(&mut reply);
    let text = String::from_utf8_lossy(&reply);
    if text.starts_with("HTTP/1.1 200") || text.starts_with("HTTP/1.0 200") {
        Ok(())
    } else {
        Err(ClientError::Protocol { url, why: format!("/healthz answered {:?}", text.lines().next().unwrap_or("")) })
    }
}
