//! The gripper node: `/gripper/command` (labrig_msgs/GripperCommand, DROID's 0 open .. 1
//! closed) in, `/gripper/state` (labrig_msgs/GripperState) out at `rate_hz`, and a
//! `/gripper/activate` service (std_srvs/Trigger) that re-runs the activation after a fault.
//!
//! The gripper is activated once at start. Each tick the newest valid command is written when
//! it differs from the last one written (a 20 Hz rig repeating its action does not flood the
//! RS-485 line), then the status is read and published. A refused command (NaN, outside 0..1),
//! a gripper fault or a silent gripper is reported in `/gripper/state.fault` with the reason
//! and the node keeps running; it never re-activates on its own (activation moves the fingers).

use crate::driver::{DriverConfig, GripperError, Robotiq2F85};
use crate::emulator::{Emulated2F85, EmulatorConfig, PtyEmulator};
use crate::registers::{Status, counts_to_droid, droid_to_counts, fault_meaning};
use crate::sim::SimGripper;
use labrig_msgs::Invalid;
use labrig_msgs::rig::{GripperCommand, GripperState};
use labrig_msgs::std_srvs::TriggerResponse;
use labrig_msgs::topics;
use labrig_runtime::ros::Ros;
use labrig_runtime::{Clock, RosConfig, Shutdown};
use serde::Deserialize;
use std::time::Duration;

#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize, serde::Serialize, clap::ValueEnum)]
#[serde(rename_all = "snake_case")]
pub enum Backend {
    /// A Robotiq 2F-85 on `port`.
    Robotiq,
    /// An emulated 2F-85 on a pseudo-terminal inside the node (no hardware needed).
    Emulated,
    /// The sim bridge's 2F-85 under `sim_prefix` (`labrig-sim run --hardware-prefix /sim`).
    Sim,
}

/// The node's config (TOML; every key optional, unknown keys refused).
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct GripperNodeConfig {
    pub ros: RosConfig,
    pub backend: Backend,
    /// Serial device of the 2F-85 (robotiq backend).
    pub port: String,
    /// The sim backend's bridge topics (`<sim_prefix>/gripper/command`, `.../gripper/state`).
    pub sim_prefix: String,
    pub slave: u8,
    pub baud: u32,
    /// Deadline of one Modbus exchange.
    pub request_timeout_s: f64,
    pub activation_timeout_s: f64,
    /// Status reads and `/gripper/state` per second.
    pub rate_hz: f64,
    /// Speed and force (0..1) for commands that leave theirs at 0.
    pub speed: f64,
    pub force: f64,
}

impl Default for GripperNodeConfig {
    fn default() -> Self {
        GripperNodeConfig {
            ros: RosConfig::default(),
            backend: Backend::Robotiq,
            port: "/dev/ttyUSB0".into(),
            sim_prefix: topics::SIM_HARDWARE_PREFIX.into(),
            slave: crate::registers::SLAVE_ID,
            baud: crate::registers::BAUD_RATE,
            request_timeout_s: 0.1,
            activation_timeout_s: 10.0,
            rate_hz: 50.0,
            speed: 1.0,
            force: 0.5,
        }
    }
}

impl GripperNodeConfig {
    /// Checks what serde cannot, naming the key.
    pub fn validate(&self) -> Result<(), Invalid> {
        self.ros.validate(std::path::Path::new("gripper config")).map_err(|e| Invalid::new("ros", e.to_string()))?;
        let bad = |k: &str, why: String| Err(Invalid::new(k, format!("gripper config: `{k}` {why}")));
        if !(self.rate_hz.is_finite() && (1.0..=200.0).contains(&self.rate_hz)) {
            return bad("rate_hz", format!("is {}, must be 1..=200", self.rate_hz));
        }
        for (k, v) in [("speed", self.speed), ("force", self.force)] {
            if !(v.is_finite() && (0.0..=1.0).contains(&v)) {
                return bad(k, format!("is {v}, must be 0..=1"));
            }
        }
        if !(self.request_timeout_s.is_finite() && (0.001..=5.0).contains(&self.request_timeout_s)) {
            return bad("request_timeout_s", format!("is {}, must be 0.001..=5", self.request_timeout_s));
        }
        // A Duration and a deadline after now (1e300 panicked at start): an hour at most.
        if !(self.activation_timeout_s.is_finite()
            && self.activation_timeout_s > 0.0
            && self.activation_timeout_s <= 3600.0)
        {
            return bad("activation_timeout_s", format!("is {}, must be in (0, 3600]", self.activation_timeout_s));
        }
        if self.backend == Backend::Robotiq && self.port.is_empty() {
            return bad("port", "is empty: name the 2F-85's serial device".into());
        }
        Ok(())
    }
}

/// A command as written to the gripper (counts).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Wanted {
    position: u8,
    speed: u8,
    force: u8,
}

/// Checks a `/gripper/command`; fills in the default speed and force for zeros.
fn wanted(cmd: &GripperCommand, cfg: &GripperNodeConfig) -> Result<Wanted, Invalid> {
    for (name, v) in [("position", cmd.position), ("speed", cmd.speed), ("force", cmd.force)] {
        if !v.is_finite() || !(0.0..=1.0).contains(&v) {
            return Err(Invalid::new(name, format!("refused gripper command: {name} {v} is outside 0..1")));
        }
    }
    let or_default = |v: f64, d: f64| droid_to_counts(if v == 0.0 { d } else { v });
    Ok(Wanted {
        position: droid_to_counts(cmd.position),
        speed: or_default(cmd.speed, cfg.speed),
        force: or_default(cmd.force, cfg.force),
    })
}

fn state(now: labrig_msgs::Nanos, s: Option<Status>, fault: &str) -> GripperState {
    let mut msg = GripperState::default();
    msg.header.stamp = now.into();
    msg.header.frame_id = "robotiq_2f85".into();
    if let Some(s) = s {
        msg.position = counts_to_droid(s.position);
        msg.requested_position = counts_to_droid(s.requested);
        msg.activated = s.ready();
        msg.object_detected = s.going && s.object.detected();
        msg.fault_code = s.fault;
        msg.current_ma = s.current_ma();
    }
    msg.fault = if !fault.is_empty() {
        fault.to_owned()
    } else if let Some(s) = s.filter(|s| s.fault != 0) {
        format!("2F-85 fault 0x{:02X}: {}", s.fault, fault_meaning(s.fault).unwrap_or("unlisted code"))
    } else {
        String::new()
    };
    msg
}

/// The gripper behind the node: the 2F-85 over Modbus (hardware or emulated), or the sim's.
#[derive(Debug)]
enum Gripper {
    Robotiq(Robotiq2F85),
    Sim(Box<SimGripper>),
}

impl Gripper {
    fn describe(&self) -> String {
        match self {
            Gripper::Robotiq(g) => format!("{} (slave {})", g.config().port, g.config().slave),
            Gripper::Sim(g) => format!("{g:?}"),
        }
    }

    async fn activate(&mut self, within: Duration) -> Result<Status, GripperError> {
        match self {
            Gripper::Robotiq(g) => g.activate(within).await,
            Gripper::Sim(g) => g.activate(within).await,
        }
    }

    async fn go_to(&mut self, position: u8, speed: u8, force: u8) -> Result<(), GripperError> {
        match self {
            Gripper::Robotiq(g) => g.go_to(position, speed, force).await,
            Gripper::Sim(g) => g.go_to(position, speed, force).await,
        }
    }

    async fn status(&mut self) -> Result<Status, GripperError> {
        match self {
            Gripper::Robotiq(g) => g.status().await,
            Gripper::Sim(g) => g.status().await,
        }
    }

    fn last_status(&self) -> Option<Status> {
        match self {
            Gripper::Robotiq(g) => g.last_status(),
            Gripper::Sim(g) => g.last_status(),
        }
    }
}

/// Runs the node until `shutdown`.
pub async fn run(cfg: GripperNodeConfig, shutdown: Shutdown) -> anyhow::Result<()> {
    cfg.validate()?;
    let mut ros = Ros::new(&cfg.ros, "labrig_gripper")?;
    // The emulated backend serves a 2F-85 on a pty inside the node; the driver is the same.
    let mut _emulator: Option<PtyEmulator> = None;
    let mut gripper = match cfg.backend {
        Backend::Sim => Gripper::Sim(Box::new(SimGripper::new(&mut ros, &cfg.sim_prefix)?)),
        Backend::Robotiq | Backend::Emulated => {
            let port = if cfg.backend == Backend::Emulated {
                let emu = Emulated2F85::new(EmulatorConfig { slave: cfg.slave, ..EmulatorConfig::default() });
                let pty = emu.serve_on_pty()?;
                let path = pty.path().to_owned();
                tracing::info!(port = %path, "emulated 2F-85 on a pseudo-terminal");
                _emulator = Some(pty);
                path
            } else {
                cfg.port.clone()
            };
            Gripper::Robotiq(Robotiq2F85::open(DriverConfig {
                port,
                slave: cfg.slave,
                baud: cfg.baud,
                request_timeout: Duration::from_secs_f64(cfg.request_timeout_s),
            })?)
        }
    };

    let state_pub = ros.publisher_on(&topics::GRIPPER_STATE, 10)?;
    let cmd_sub = ros.subscription_on(&topics::GRIPPER_COMMAND, 100)?;
    // Answered by the loop between ticks.
    let mut activate_rx = ros.server_on(&topics::GRIPPER_ACTIVATE)?.forward();
    let clock = Clock::Wall;
    let activation_timeout = Duration::from_secs_f64(cfg.activation_timeout_s);

    tracing::info!(gripper = %gripper.describe(), "activating the 2F-85");
    let mut fault = match gripper.activate(activation_timeout).await {
        Ok(s) => {
            tracing::info!(status = %s.describe(), "2F-85 activated");
            String::new()
        }
        Err(e) => {
            tracing::error!("{e}");
            e.to_string()
        }
    };
    let mut written: Option<Wanted> = None;
    let mut pending: Option<Wanted> = None;
    // The last failed write's error, without the command it held back.
    let mut write_error = String::new();
    let mut refusal = String::new();
    let mut ticker = tokio::time::interval(Duration::from_secs_f64(1.0 / cfg.rate_hz));
    ticker.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    let (mut commands, mut refused) = (0u64, 0u64);
    while !shutdown.is_triggered() {
        tokio::select! {
            _ = ticker.tick() => {}
            _ = shutdown.wait() => break,
        }
        if let Ok(served) = activate_rx.try_recv() {
            tracing::info!("/gripper/activate: re-running the activation");
            written = None;
            let response = match gripper.activate(activation_timeout).await {
                Ok(s) => {
                    fault.clear();
                    TriggerResponse { success: true, message: format!("activated: {}", s.describe()) }
                }
                Err(e) => {
                    fault = e.to_string();
                    TriggerResponse { success: false, message: fault.clone() }
                }
            };
            served.respond(response);
        }
        // The newest command of the tick wins; a valid one clears an earlier refusal and is
        // pending until it is written (a failed write is retried next tick). Bounded, so a
        // reader that kept failing cannot hold the tick.
        for _ in 0..1000 {
            let c = match cmd_sub.try_take() {
                Ok(Some(c)) => c,
                Ok(None) => break,
                Err(e) => {
                    refused += 1;
                    refusal = format!("refused gripper command: {e}");
                    tracing::warn!("{refusal}");
                    continue;
                }
            };
            commands += 1;
            match wanted(&c.msg, &cfg) {
                Ok(w) => {
                    refusal.clear();
                    pending = (written != Some(w)).then_some(w);
                    // Back to the command in force: none is held back, the error stays.
                    if pending.is_none() && !write_error.is_empty() && fault.starts_with(write_error.as_str()) {
                        fault = write_error.clone();
                    }
                }
                Err(why) => {
                    refused += 1;
                    tracing::warn!("{why}");
                    refusal = why.to_string();
                }
            }
        }
        if let Some(w) = pending {
            match gripper.go_to(w.position, w.speed, w.force).await {
                Ok(()) => {
                    written = Some(w);
                    pending = None;
                    fault.clear();
                }
                Err(e) => {
                    // Named with the command it held back, so the state shows the command
                    // arrived and was not written (a lost command would not say this).
                    write_error = e.to_string();
                    let e = format!("{e}; the command to {:.3} was not written", counts_to_droid(w.position));
                    if e != fault {
                        tracing::warn!("{e}");
                    }
                    fault = e;
                }
            }
        }
        // A link problem is reported while it lasts; a failed write or activation until the
        // next good one; a refused command until the next valid one.
        let (status, link) = match gripper.status().await {
            Ok(s) => (Some(s), String::new()),
            // Stale: the last status read, with the reason it is stale.
            Err(e @ (GripperError::Timeout { .. } | GripperError::Link { .. } | GripperError::Sim(_))) => {
                (gripper.last_status(), e.to_string())
            }
            Err(e) => (None, e.to_string()),
        };
        let reason = [&link, &fault, &refusal].into_iter().find(|r| !r.is_empty()).map_or("", |r| r.as_str());
        if let Err(e) = state_pub.publish(state(clock.now(), status, reason)) {
            tracing::warn!("/gripper/state: {e}");
        }
    }
    tracing::info!(commands, refused, "gripper node stopped");
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn config_keys_are_checked_and_named() {
        let cfg: GripperNodeConfig =
            labrig_runtime::config::parse_config("backend = \"emulated\"\nrate_hz = 20.0\n", "g.toml".as_ref())
                .unwrap();
        assert_eq!((cfg.backend, cfg.rate_hz, cfg.slave), (Backend::Emulated, 20.0, 9));
        cfg.validate().unwrap();
        let err =
            labrig_runtime::config::parse_config::<GripperNodeConfig>("prot = \"/dev/ttyUSB1\"\n", "g.toml".as_ref())
                .unwrap_err();
        assert!(err.to_string().contains("unknown field `prot`"), "{err}");
        let cfg = GripperNodeConfig { force: 1.5, ..Default::default() };
        assert_eq!(cfg.validate().unwrap_err().to_string(), "gripper config: `force` is 1.5, must be 0..=1");
    }

    #[test]
    fn the_example_config_parses() {
        let text = include_str!("../../../launch_configs/nodes/gripper_2f85.toml");
        let cfg: GripperNodeConfig = labrig_runtime::config::parse_config(text, "gripper_2f85.toml".as_ref()).unwrap();
        cfg.validate().unwrap();
        assert_eq!((cfg.backend, cfg.port.as_str(), cfg.slave), (Backend::Robotiq, "/dev/ttyUSB0", 9));
    }

    #[test]
    fn commands_take_the_default_speed_and_force_for_zero() {
        let cfg = GripperNodeConfig::default();
        let w = wanted(&GripperCommand { position: 1.0, ..Default::default() }, &cfg).unwrap();
        assert_eq!(w, Wanted { position: 255, speed: 255, force: 128 });
        let err = wanted(&GripperCommand { position: 0.5, speed: -0.1, ..Default::default() }, &cfg).unwrap_err();
        assert_eq!(err.to_string(), "refused gripper command: speed -0.1 is outside 0..1");
    }
}
