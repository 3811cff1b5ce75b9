//! The 2F-85 driver: Modbus RTU over a serial port with tokio-modbus.
//!
//! Every request has a deadline ([`DriverConfig::request_timeout`]); a gripper that does not
//! answer is an error naming the request, never a hang. After a timeout the port is reopened
//! before the next request, so a late answer cannot be taken for the next one's.

use crate::registers::{
    Activation, BAUD_RATE, Object, REGISTERS, REQUEST_REGISTER, Request, SLAVE_ID, STATUS_REGISTER, Status,
    fault_is_major, fault_meaning,
};
use std::time::Duration;
use tokio::time::Instant;
use tokio_modbus::client::{Context, Reader, Writer};
use tokio_modbus::{ExceptionCode, Slave};
use tokio_serial::{DataBits, Parity, SerialStream, StopBits};

/// How often the status is polled while waiting for the gripper.
const POLL: Duration = Duration::from_millis(10);

#[derive(Debug, thiserror::Error)]
pub enum GripperError {
    #[error("cannot open the 2F-85's serial port {port}: {source}")]
    Port {
        port: String,
        #[source]
        source: tokio_serial::Error,
    },
    #[error(
        "no answer from the 2F-85 (slave {slave}) to {what} within {after:?}: check the cable, its power and the slave id"
    )]
    Timeout { what: &'static str, slave: u8, after: Duration },
    #[error("the 2F-85 refused {what}: Modbus exception {code}")]
    Exception { what: &'static str, code: ExceptionCode },
    #[error("Modbus link to the 2F-85 failed during {what}: {source}")]
    Link {
        what: &'static str,
        #[source]
        source: tokio_modbus::Error,
    },
    #[error("the 2F-85 answered {what} with {got} registers, expected {expected}")]
    ShortRead { what: &'static str, got: usize, expected: usize },
    #[error("2F-85 fault 0x{code:02X}: {meaning} ({status})")]
    Fault { code: u8, meaning: &'static str, status: String },
    #[error("the 2F-85 did not finish activating within {after:?} (last status: {status})")]
    ActivationTimeout { after: Duration, status: String },
    #[error("the 2F-85 is not activated (status: {status}); activate it first")]
    NotActivated { status: String },
    #[error("the simulated 2F-85 ({0})")]
    Sim(String),
    #[error("the 2F-85's fingers did not stop within {after:?} (last status: {status})")]
    MotionTimeout { after: Duration, status: String },
}

impl GripperError {
    fn fault(status: &Status) -> GripperError {
        GripperError::Fault {
            code: status.fault,
            meaning: fault_meaning(status.fault).unwrap_or("a fault code the manual does not list"),
            status: status.describe(),
        }
    }
}

/// How to reach the gripper.
#[derive(Debug, Clone, PartialEq)]
pub struct DriverConfig {
    /// Serial device, e.g. /dev/ttyUSB0 (the 2F-85's RS-485 to USB converter).
    pub port: String,
    pub slave: u8,
    pub baud: u32,
    /// Deadline for one request/answer exchange.
    pub request_timeout: Duration,
}

impl DriverConfig {
    pub fn new(port: impl Into<String>) -> DriverConfig {
        DriverConfig {
            port: port.into(),
            slave: SLAVE_ID,
            baud: BAUD_RATE,
            request_timeout: Duration::from_millis(100),
        }
    }
}

/// A Robotiq 2F-85 on a serial line.
pub struct Robotiq2F85 {
    cfg: DriverConfig,
    /// `None` after a timeout or link error: the port is reopened before the next request, so
    /// a late answer cannot be taken for the next one's.
    ctx: Option<Context>,
    last: Option<Status>,
    /// The last motion request written.
    requested: Option<Request>,
}

impl std::fmt::Debug for Robotiq2F85 {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Robotiq2F85").field("cfg", &self.cfg).field("last", &self.last).finish_non_exhaustive()
    }
}

fn open_port(cfg: &DriverConfig) -> Result<SerialStream, GripperError> {
    let builder =
        tokio_serial::new(&cfg.port, cfg.baud).data_bits(DataBits::Eight).parity(Parity::None).stop_bits(StopBits::One);
    SerialStream::open(&builder).map_err(|source| GripperError::Port { port: cfg.port.clone(), source })
}

impl Robotiq2F85 {
    /// Opens the port (115200 8N1 unless configured otherwise). Talks to nothing yet.
    pub fn open(cfg: DriverConfig) -> Result<Robotiq2F85, GripperError> {
        let port = open_port(&cfg)?;
        let ctx = tokio_modbus::client::rtu::attach_slave(port, Slave(cfg.slave));
        Ok(Robotiq2F85 { cfg, ctx: Some(ctx), last: None, requested: None })
    }

    pub fn config(&self) -> &DriverConfig {
        &self.cfg
    }

    /// The last status read.
    pub fn last_status(&self) -> Option<Status> {
        self.last
    }

    async fn exchange<T>(
        &mut self,
        what: &'static str,
        f: impl AsyncFnOnce(&mut Context) -> tokio_modbus::Result<T>,
    ) -> Result<T, GripperError> {
        let ctx = match &mut self.ctx {
            Some(ctx) => ctx,
            // The old port is closed (its lock released) before it is opened again.
            None => {
                self.ctx.insert(tokio_modbus::client::rtu::attach_slave(open_port(&self.cfg)?, Slave(self.cfg.slave)))
            }
        };
        let after = self.cfg.request_timeout;
        match tokio::time::timeout(after, f(ctx)).await {
            Ok(Ok(Ok(v))) => Ok(v),
            Ok(Ok(Err(code))) => Err(GripperError::Exception { what, code }),
            Ok(Err(source)) => {
                self.ctx = None;
                Err(GripperError::Link { what, source })
            }
            Err(_) => {
                self.ctx = None;
                Err(GripperError::Timeout { what, slave: self.cfg.slave, after })
            }
        }
    }

    /// Writes the three request registers.
    pub async fn write(&mut self, request: Request) -> Result<(), GripperError> {
        let words = request.to_registers();
        self.exchange("a request write", async move |ctx| ctx.write_multiple_registers(REQUEST_REGISTER, &words).await)
            .await
    }

    /// Reads the three status registers.
    pub async fn status(&mut self) -> Result<Status, GripperError> {
        let words = self
            .exchange("a status read", async |ctx| ctx.read_holding_registers(STATUS_REGISTER, REGISTERS).await)
            .await?;
        let regs: [u16; 3] = words.as_slice().try_into().map_err(|_| GripperError::ShortRead {
            what: "a status read",
            got: words.len(),
            expected: REGISTERS as usize,
        })?;
        let status = Status::from_registers(regs);
        self.last = Some(status);
        Ok(status)
    }

    /// The activation sequence: reset (rACT = 0, which also clears major faults), activate
    /// (rACT = 1), then poll until gSTA = 3 (an exchange that times out is tried again until
    /// `within` is spent). The fingers open and close once while it runs.
    pub async fn activate(&mut self, within: Duration) -> Result<Status, GripperError> {
        let deadline = Instant::now() + within;
        // An exchange that times out (a lost frame, a starved port) is tried again until the
        // deadline: the port is reopened, so a late answer cannot be taken for the next one,
        // and the writes are the same registers again.
        let again = |e: &GripperError| matches!(e, GripperError::Timeout { .. }) && Instant::now() < deadline;
        for request in [Request::RESET, Request::ACTIVATE] {
            loop {
                match self.write(request).await {
                    Ok(()) => break,
                    Err(e) if again(&e) => tracing::warn!("activating the 2F-85: {e}; trying again"),
                    Err(e) => return Err(e),
                }
                tokio::time::sleep(POLL).await;
            }
        }
        loop {
            let s = match self.status().await {
                Ok(s) => s,
                Err(e) if again(&e) => {
                    tracing::warn!("activating the 2F-85: {e}; asking again");
                    tokio::time::sleep(POLL).await;
                    continue;
                }
                Err(e) => return Err(e),
            };
            if s.activation == Activation::Complete {
                return Ok(s);
            }
            if fault_is_major(s.fault) {
                return Err(GripperError::fault(&s));
            }
            if Instant::now() >= deadline {
                return Err(GripperError::ActivationTimeout { after: within, status: s.describe() });
            }
            tokio::time::sleep(POLL).await;
        }
    }

    /// Asks for `position` (0 open .. 255 closed) at `speed` with `force`; does not wait.
    /// Refused without a write when the last status says the gripper is not activated or
    /// stopped by a fault.
    pub async fn go_to(&mut self, position: u8, speed: u8, force: u8) -> Result<(), GripperError> {
        let s = match self.last {
            Some(s) => s,
            None => self.status().await?,
        };
        if fault_is_major(s.fault) {
            return Err(GripperError::fault(&s));
        }
        if s.activation != Activation::Complete {
            return Err(GripperError::NotActivated { status: s.describe() });
        }
        let request = Request::go_to(position, speed, force);
        self.write(request).await?;
        self.requested = Some(request);
        Ok(())
    }

    /// Polls until the fingers stop after the last [`Robotiq2F85::go_to`] (its position echoed
    /// in gPR): at the requested position, or on an object. A major fault is an error.
    pub async fn wait_until_stopped(&mut self, within: Duration) -> Result<Status, GripperError> {
        let deadline = Instant::now() + within;
        loop {
            let s = self.status().await?;
            if fault_is_major(s.fault) {
                return Err(GripperError::fault(&s));
            }
            let echoed = self.requested.is_none_or(|r| r.position == s.requested);
            if s.going && echoed && s.object != Object::Moving {
                return Ok(s);
            }
            if Instant::now() >= deadline {
                return Err(GripperError::MotionTimeout { after: within, status: s.describe() });
            }
            tokio::time::sleep(POLL).await;
        }
    }
}
