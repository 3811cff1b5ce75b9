//! An emulated 2F-85: the register protocol of the real gripper behind a Modbus RTU server on
//! a pseudo-terminal, with finger motion, object contact, faults and a mute switch, so the
//! driver and the node run (and are tested) without the hardware.
//!
//! Behaviour follows the manual: rACT 0 resets (clears faults, gSTA 0); rACT 0 -> 1 starts the
//! activation (gSTA 1 for [`EmulatorConfig::activation`], the fingers open, then gSTA 3); rGTO
//! moves the fingers toward rPR at 20..150 mm/s by rSP; closing onto a placed object stops them
//! there with gOBJ 2 and a current set by rFR; rGTO before activation is fault 0x07, during it
//! 0x05. Motion is integrated lazily from the wall clock at each request.

use crate::registers::{
    Activation, Object, REQUEST_REGISTER, Request, SLAVE_ID, STATUS_REGISTER, Status, fault_blocks_motion,
};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};
use tokio_modbus::server::Service;
use tokio_modbus::{ExceptionCode, Response, SlaveRequest};
use tokio_serial::SerialStream;

/// Full stroke, mm (85 mm between the fingers, 0 .. 255 counts).
const STROKE_MM: f64 = 85.0;
/// Speed at rSP = 0 and rSP = 255, mm/s (the 2F-85 datasheet's range).
const SPEED_MM_S: [f64; 2] = [20.0, 150.0];

#[derive(Debug, Clone, PartialEq)]
pub struct EmulatorConfig {
    pub slave: u8,
    /// How long gSTA stays 1 after rACT rises.
    pub activation: Duration,
}

impl Default for EmulatorConfig {
    fn default() -> Self {
        EmulatorConfig { slave: SLAVE_ID, activation: Duration::from_millis(300) }
    }
}

#[derive(Debug)]
struct Inner {
    cfg: EmulatorConfig,
    request: Request,
    status: Status,
    /// Finger position in counts (fractional while moving).
    position: f64,
    activating_until: Option<Instant>,
    updated: Instant,
    /// An object between the fingers: closing stops at this many counts.
    object_at: Option<u8>,
    /// Stop answering (a cut cable, a powered-off gripper).
    mute: bool,
    requests: u64,
}

impl Inner {
    fn advance(&mut self, now: Instant) {
        let dt = now.saturating_duration_since(self.updated).as_secs_f64();
        self.updated = now;
        if let Some(until) = self.activating_until {
            // Activation opens the fingers.
            self.position = (self.position - counts_per_s(255) * dt).max(0.0);
            if now >= until {
                self.activating_until = None;
                self.status.activation = Activation::Complete;
                self.position = 0.0;
                if matches!(self.status.fault, 0x05 | 0x07) {
                    self.status.fault = 0;
                }
            }
        }
        let s = &mut self.status;
        if s.activation == Activation::Complete && self.request.go_to && !fault_blocks_motion(s.fault) {
            let target = f64::from(self.request.position);
            let step = counts_per_s(self.request.speed) * dt;
            if s.object == Object::Moving {
                let next = if target > self.position {
                    (self.position + step).min(target)
                } else {
                    (self.position - step).max(target)
                };
                let blocked = self.object_at.map(f64::from).filter(|&o| self.position <= o && next >= o && target > o);
                if let Some(o) = blocked {
                    self.position = o;
                    s.object = Object::ContactClosing;
                } else {
                    self.position = next;
                    if next == target {
                        s.object = Object::AtRequest;
                    }
                }
            }
            s.current = match s.object {
                Object::Moving => 25,
                Object::ContactClosing | Object::ContactOpening => {
                    10 + (u16::from(self.request.force) * 50 / 255) as u8
                }
                Object::AtRequest => 0,
            };
        } else {
            s.current = 0;
        }
        s.position = self.position.round() as u8;
    }

    fn write(&mut self, new: Request) {
        let old = self.request;
        self.request = new;
        let s = &mut self.status;
        s.activated = new.activate;
        s.going = new.go_to;
        s.requested = new.position;
        if !new.activate {
            // Reset: clears every fault.
            s.activation = Activation::Reset;
            s.fault = 0;
            s.object = Object::Moving;
            self.activating_until = None;
            return;
        }
        if !old.activate {
            s.activation = Activation::InProgress;
            self.activating_until = Some(self.updated + self.cfg.activation);
        }
        if new.go_to {
            match s.activation {
                Activation::Complete => {
                    if !old.go_to || old.position != new.position {
                        s.object = Object::Moving;
                    }
                }
                _ => s.fault = 0x05,
            }
        }
    }

    fn call(&mut self, req: SlaveRequest<'_>) -> Result<Option<Response>, ExceptionCode> {
        if self.mute || req.slave != self.cfg.slave {
            return Ok(None);
        }
        self.requests += 1;
        self.advance(Instant::now());
        use tokio_modbus::Request as R;
        match req.request {
            R::WriteMultipleRegisters(addr, words) => {
                let offset = addr.checked_sub(REQUEST_REGISTER).filter(|o| usize::from(*o) + words.len() <= 3);
                let Some(offset) = offset else { return Err(ExceptionCode::IllegalDataAddress) };
                let mut regs = self.request.to_registers();
                regs[usize::from(offset)..usize::from(offset) + words.len()].copy_from_slice(&words);
                let new = Request::from_registers(regs);
                self.write(new);
                if new.go_to && !new.activate {
                    // rACT = 0 is a reset; the motion request on top of it is a fault.
                    self.status.fault = 0x07;
                }
                Ok(Some(Response::WriteMultipleRegisters(addr, words.len() as u16)))
            }
            R::ReadHoldingRegisters(addr, n) | R::ReadInputRegisters(addr, n) => {
                let offset =
                    addr.checked_sub(STATUS_REGISTER).filter(|o| n >= 1 && usize::from(*o) + usize::from(n) <= 3);
                let Some(offset) = offset else { return Err(ExceptionCode::IllegalDataAddress) };
                let regs = self.status.to_registers()[usize::from(offset)..usize::from(offset + n)].to_vec();
                Ok(Some(match req.request {
                    R::ReadHoldingRegisters(..) => Response::ReadHoldingRegisters(regs),
                    _ => Response::ReadInputRegisters(regs),
                }))
            }
            _ => Err(ExceptionCode::IllegalFunction),
        }
    }
}

fn counts_per_s(speed: u8) -> f64 {
    let mm_s = SPEED_MM_S[0] + (SPEED_MM_S[1] - SPEED_MM_S[0]) * f64::from(speed) / 255.0;
    mm_s * 255.0 / STROKE_MM
}

/// The emulated gripper; clones share one device.
#[derive(Debug, Clone)]
pub struct Emulated2F85 {
    inner: Arc<Mutex<Inner>>,
}

impl Emulated2F85 {
    /// A powered, unactivated gripper with its fingers half closed.
    pub fn new(cfg: EmulatorConfig) -> Emulated2F85 {
        let inner = Inner {
            cfg,
            request: Request::RESET,
            status: Status { position: 128, ..Status::default() },
            position: 128.0,
            activating_until: None,
            updated: Instant::now(),
            object_at: None,
            mute: false,
            requests: 0,
        };
        Emulated2F85 { inner: Arc::new(Mutex::new(inner)) }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, Inner> {
        self.inner.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Places an object the fingers meet at `counts` when closing (`None` removes it).
    pub fn place_object(&self, counts: Option<u8>) {
        self.lock().object_at = counts;
    }

    /// Raises a fault code (e.g. 0x0E overcurrent); a major one stops the fingers until the
    /// next reset.
    pub fn inject_fault(&self, code: u8) {
        let mut g = self.lock();
        g.advance(Instant::now());
        g.status.fault = code;
    }

    /// Stops (or resumes) answering requests.
    pub fn set_mute(&self, mute: bool) {
        self.lock().mute = mute;
    }

    /// The registers as they stand now.
    pub fn status(&self) -> Status {
        let mut g = self.lock();
        g.advance(Instant::now());
        g.status
    }

    /// Requests answered so far.
    pub fn requests(&self) -> u64 {
        self.lock().requests
    }

    /// Serves the Modbus RTU protocol on a new pseudo-terminal until the returned handle is
    /// dropped. The handle names the terminal a driver opens (e.g. /dev/pts/7).
    pub fn serve_on_pty(&self) -> std::io::Result<PtyEmulator> {
        let (master, slave) = SerialStream::pair().map_err(std::io::Error::other)?;
        let path = tokio_serial::SerialPort::name(&slave)
            .ok_or_else(|| std::io::Error::other("the pseudo-terminal has no name"))?;
        // The driver opens the terminal by its path and takes an exclusive lock, so the pair's
        // own (locked) slave end is swapped for a plain open that only keeps the terminal up.
        let keep_open = std::fs::OpenOptions::new().read(true).write(true).open(&path)?;
        drop(slave);
        let server = tokio_modbus::server::rtu::Server::new(master);
        let service = EmulatorService(self.clone());
        let task = tokio::spawn(async move {
            if let Err(e) = server.serve_forever(service).await {
                tracing::debug!("2F-85 emulator stopped: {e}");
            }
        });
        Ok(PtyEmulator { path, task, _slave: keep_open })
    }
}

/// A running emulator on a pseudo-terminal; dropping it stops the server.
#[derive(Debug)]
pub struct PtyEmulator {
    path: String,
    task: tokio::task::JoinHandle<()>,
    /// Kept open: a pty's master reads fail once no slave end is open.
    _slave: std::fs::File,
}

impl PtyEmulator {
    /// The terminal to open, e.g. /dev/pts/7.
    pub fn path(&self) -> &str {
        &self.path
    }
}

impl Drop for PtyEmulator {
    fn drop(&mut self) {
        self.task.abort();
    }
}

#[derive(Debug)]
struct EmulatorService(Emulated2F85);

impl Service for EmulatorService {
    type Request = SlaveRequest<'static>;
    type Response = Option<Response>;
    type Exception = ExceptionCode;
    type Future = std::future::Ready<Result<Option<Response>, ExceptionCode>>;

    fn call(&self, req: SlaveRequest<'static>) -> Self::Future {
        std::future::ready(self.0.lock().call(req))
    }
}
