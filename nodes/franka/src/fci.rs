//! The `fci` backend: a real FR3 (or franka-sim) through franka-rs's joint target control.
//! franka-rs runs the 1 kHz FCI loop on a thread of its own and plans a jerk-limited
//! trajectory to the newest target, which is the shape of a 20 Hz rig; this wrapper keeps
//! franka-rs behind [`ArmBackend`] so the node never sees its types.

use crate::backend::{ArmBackend, ArmReading, BackendError};
use franka::{Backend, FrankaError, JointTargetControl, JointTargetControlOptions, RealtimeConfig, Robot};
use labrig_arm::Joints;
use labrig_msgs::Invalid;
use serde::Deserialize;
use std::sync::Arc;

/// What turns franka-rs's planned joint positions into FCI commands.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum Controller {
    /// A joint position stream to the FR3's own joint impedance controller (libfranka's
    /// joint position interface, with its rate limiter as the backstop).
    #[default]
    Robot,
    /// franka-rs's own joint impedance law sending torques.
    Impedance,
}

/// The `[fci]` section of the franka node's config.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct FciConfig {
    /// Require a realtime kernel (the real FR3). `false` runs anyway (franka-sim, a laptop).
    pub realtime: bool,
    pub controller: Controller,
    /// How far (rad) a joint may move from where the session started before franka-rs
    /// freezes the target and ends it (a guard against runaway targets).
    pub max_deviation_rad: f64,
    /// The share of the FR3's joint velocity, acceleration and jerk limits franka-rs's
    /// trajectory generator plans under (franka-rs's own default is 0.2, which caps joints at
    /// about 0.5 rad/s; the safety layer already keeps targets under 0.8 of the velocity
    /// limits).
    pub limit_fraction: f64,
}

impl FciConfig {
    pub fn validate(&self) -> Result<(), Invalid> {
        if !(self.limit_fraction.is_finite() && self.limit_fraction > 0.0 && self.limit_fraction <= 1.0) {
            return Err(Invalid::new(
                "fci.limit_fraction",
                format!("franka config: `fci.limit_fraction` is {}, must be in (0, 1]", self.limit_fraction),
            ));
        }
        if !(self.max_deviation_rad.is_finite() && self.max_deviation_rad > 0.0) {
            return Err(Invalid::new(
                "fci.max_deviation_rad",
                format!("franka config: `fci.max_deviation_rad` is {}, must be > 0", self.max_deviation_rad),
            ));
        }
        Ok(())
    }
}

impl Default for FciConfig {
    fn default() -> Self {
        FciConfig { realtime: true, controller: Controller::Robot, max_deviation_rad: 3.0, limit_fraction: 0.5 }
    }
}

/// The FR3 over the FCI.
pub struct FciArm {
    address: String,
    cfg: FciConfig,
    robot: Arc<Robot>,
    control: Option<JointTargetControl>,
}

impl std::fmt::Debug for FciArm {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("FciArm").field("address", &self.address).field("cfg", &self.cfg).finish_non_exhaustive()
    }
}

fn connect(address: &str, cfg: &FciConfig) -> Result<Arc<Robot>, BackendError> {
    let realtime = if cfg.realtime { RealtimeConfig::Enforce } else { RealtimeConfig::Ignore };
    let address = address.to_owned();
    // Robot::new raises the calling thread to SCHED_FIFO; a thread of its own takes that,
    // never one of the node's async workers.
    std::thread::spawn(move || Robot::new(&address, realtime))
        .join()
        .map_err(|_| BackendError::Start("the connecting thread panicked".into()))?
        .map(Arc::new)
        .map_err(|e| BackendError::Start(e.to_string()))
}

/// Connects to the FCI at `address` (`ip` or `ip:port`) and disconnects, commanding nothing
/// (`labrig doctor`): the FCI version the robot speaks, or why there is none (refused, no
/// answer within `within`, a version franka-rs does not speak). Real-time is not asked for.
pub fn probe(address: &str, within: std::time::Duration) -> Result<u16, ProbeError> {
    let (tx, rx) = std::sync::mpsc::channel();
    let address = address.to_owned();
    // A connect to an address nobody answers waits for TCP's own timeout (minutes): the thread
    // is left to it, the answer is not waited for.
    std::thread::spawn(move || {
        let r = Robot::new(&address, RealtimeConfig::Ignore).map(|r| r.server_version()).map_err(ProbeError::Fci);
        let _ = tx.send(r);
    });
    rx.recv_timeout(within).unwrap_or(Err(ProbeError::NoAnswer { within }))
}

/// Why [`probe`] found no FCI.
#[derive(Debug, thiserror::Error)]
pub enum ProbeError {
    /// franka-rs's answer: refused, unreachable, a version it does not speak, ...
    #[error(transparent)]
    Fci(FrankaError),
    #[error("no answer within {:.0} s", .within.as_secs_f64())]
    NoAnswer { within: std::time::Duration },
}

/// A franka-rs error in the node's terms: a control exception (a reflex, a limit the
/// robot's controller refused) is recoverable, a network failure is a lost connection.
fn classify(e: FrankaError) -> BackendError {
    match e {
        FrankaError::Network(m) => BackendError::Disconnected(m),
        FrankaError::Control(c) => BackendError::Reflex(c.to_string()),
        FrankaError::InvalidArgument(m) => BackendError::Refused(m),
        other => BackendError::Reflex(other.to_string()),
    }
}

impl FciArm {
    /// Connects to the FCI at `address` and starts joint target control holding the arm
    /// where it is.
    pub fn connect(address: &str, cfg: FciConfig) -> Result<FciArm, BackendError> {
        let robot = connect(address, &cfg)?;
        let mut arm = FciArm { address: address.to_owned(), cfg, robot, control: None };
        arm.start()?;
        Ok(arm)
    }

    fn start(&mut self) -> Result<(), BackendError> {
        let backend = match self.cfg.controller {
            Controller::Robot => Backend::RobotController,
            Controller::Impedance => JointTargetControlOptions::default().backend,
        };
        let limits = JointTargetControlOptions::scaled_limits(self.robot.fci_version(), self.cfg.limit_fraction);
        let options = JointTargetControlOptions::default()
            .with_backend(backend)
            .with_limits(limits)
            .with_max_deviation(self.cfg.max_deviation_rad);
        let control = self.robot.start_joint_target_control(options).map_err(|e| BackendError::Start(e.to_string()))?;
        self.control = Some(control);
        Ok(())
    }

    /// The running session, or the reason it ended (the session is stopped to get it).
    fn running(&mut self) -> Result<&JointTargetControl, BackendError> {
        match &self.control {
            Some(c) if c.is_running() => {}
            Some(_) => {
                let ended = self.control.take().expect("checked").stop();
                return Err(match ended {
                    Err(e) => classify(e),
                    Ok(()) => BackendError::Reflex("the FCI control loop ended".into()),
                });
            }
            None => return Err(BackendError::Reflex("no control session: call /arm/recover".into())),
        }
        Ok(self.control.as_ref().expect("checked"))
    }
}

impl ArmBackend for FciArm {
    fn name(&self) -> &'static str {
        "fci"
    }

    fn read(&mut self) -> Result<ArmReading, BackendError> {
        let c = self.running()?;
        let s = c.state();
        Ok(ArmReading { q: s.q, dq: s.dq, q_target: c.target(), tau_measured: s.tau_J, tau_commanded: s.tau_J_d })
    }

    fn set_target(&mut self, target: &Joints) -> Result<(), BackendError> {
        let c = self.running()?;
        c.set_joints(*target).map_err(classify)
    }

    fn recover(&mut self) -> Result<(), BackendError> {
        if let Some(c) = self.control.take() {
            let _ = c.stop();
        }
        if self.robot.automatic_error_recovery().is_err() {
            // The connection itself is gone (a restarted controller or simulator): reconnect.
            self.robot = connect(&self.address, &self.cfg)?;
            self.robot.automatic_error_recovery().map_err(classify)?;
        }
        self.start()
    }

    fn stop(&mut self) {
        if let Some(c) = self.control.take()
            && let Err(e) = c.stop()
        {
            tracing::warn!("stopping the FCI session: {e}");
        }
    }
}
