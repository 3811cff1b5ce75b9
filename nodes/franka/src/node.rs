//! The franka node: `/arm/command` (labrig_msgs/ArmCommand, any of DROID's modes, 20 Hz) ->
//! the safety layer (refusals, clips, IK to joint targets) -> an [`ArmBackend`] (the FCI's
//! 1 kHz loop interpolates between targets). Publishes `/arm/state` (DROID's RobotState:
//! cartesian_position as xyz + euler XYZ of the 2F-85's TCP, joints, torques, the command's
//! latency, mode and fault), `/joint_states` and `/tf` (base -> tcp) at `rate_hz`;
//! `/arm/target` (sensor_msgs/JointState: the joint targets sent, stamped with the command's
//! stamp) once per accepted command; and serves `/arm/recover`
//! (std_srvs/Trigger) to clear a reflex or reconnect.
//!
//! The watchdog runs on the node's monotonic clock: when no accepted command arrives for
//! `safety.watchdog_periods` control periods (100 ms at 20 Hz), the arm is held at its
//! measured joints at that deadline, not at the next state tick.

use crate::backend::{ArmBackend, ArmReading, BackendError};
use crate::fci::FciArm;
use crate::sim::SimArm;
use futures::StreamExt;
use labrig_arm::ik::{Ik, IkConfig, xyz_euler};
use labrig_arm::safety::{ArmView, SafeCommand, SafetyConfig, SafetyFilter, Watchdog};
use labrig_arm::{Fr3Kinematics, Joints, TcpOffset};
use labrig_msgs::Invalid;
use labrig_msgs::Nanos;
use labrig_msgs::geometry_msgs::{Quaternion, Transform, TransformStamped, Vector3 as RosVector3};
use labrig_msgs::rig::{ArmCommand, RobotState};
use labrig_msgs::sensor_msgs::JointState;
use labrig_msgs::std_msgs::Header;
use labrig_msgs::std_srvs::TriggerResponse;
use labrig_msgs::tf2_msgs::TFMessage;
use labrig_msgs::topics;
use labrig_runtime::ros::{Received, Ros, RosError};
use labrig_runtime::{Clock, RosConfig, Shutdown};
use serde::Deserialize;
use std::path::PathBuf;
use std::time::Duration;
use tokio::time::Instant;

pub const JOINT_NAMES: [&str; 7] =
    ["fr3_joint1", "fr3_joint2", "fr3_joint3", "fr3_joint4", "fr3_joint5", "fr3_joint6", "fr3_joint7"];
const BASE_FRAME: &str = "base";

/// Which arm the node drives.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize, serde::Serialize, clap::ValueEnum)]
#[serde(rename_all = "snake_case")]
pub enum BackendKind {
    /// A real FR3 (or franka-sim) through franka-rs over the FCI.
    Fci,
    /// The sim bridge's FR3, served under `sim_prefix` (`labrig-sim run --hardware-prefix /sim`).
    Sim,
}

/// The node's config (TOML; every key optional, unknown keys refused).
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct FrankaNodeConfig {
    pub ros: RosConfig,
    pub backend: BackendKind,
    /// The FR3's FCI address (franka-sim: 127.0.0.1).
    pub robot_ip: String,
    /// The sim backend's bridge topics (`<sim_prefix>/arm/command`, `.../arm/state`).
    pub sim_prefix: String,
    /// The FR3 URDF (default: the one setup extracts).
    pub urdf: Option<PathBuf>,
    /// `/arm/state`, `/joint_states`, `/tf` per second.
    pub rate_hz: f64,
    pub safety: SafetyConfig,
    pub fci: crate::fci::FciConfig,
    /// Keep trying to reach the FCI this long at start (a booting robot or simulator), s.
    pub connect_timeout_s: f64,
}

impl Default for FrankaNodeConfig {
    fn default() -> Self {
        FrankaNodeConfig {
            ros: RosConfig::default(),
            backend: BackendKind::Fci,
            robot_ip: "172.16.0.2".into(),
            sim_prefix: topics::SIM_HARDWARE_PREFIX.into(),
            urdf: None,
            rate_hz: 50.0,
            safety: SafetyConfig::default(),
            fci: crate::fci::FciConfig::default(),
            connect_timeout_s: 30.0,
        }
    }
}

impl FrankaNodeConfig {
    pub fn validate(&self) -> Result<(), Invalid> {
        self.ros.validate(std::path::Path::new("franka config")).map_err(|e| Invalid::new("ros", e.to_string()))?;
        self.safety.validate()?;
        if !(self.rate_hz.is_finite() && (1.0..=1000.0).contains(&self.rate_hz)) {
            return Err(Invalid::new(
                "rate_hz",
                format!("franka config: `rate_hz` is {}, must be 1..=1000", self.rate_hz),
            ));
        }
        if self.robot_ip.is_empty() {
            return Err(Invalid::new("robot_ip", "franka config: `robot_ip` is empty"));
        }
        self.fci.validate()?;
        if !(self.connect_timeout_s.is_finite() && (0.0..=86_400.0).contains(&self.connect_timeout_s)) {
            return Err(Invalid::new(
                "connect_timeout_s",
                format!("franka config: `connect_timeout_s` is {}, must be 0..=86400", self.connect_timeout_s),
            ));
        }
        Ok(())
    }
}

/// What the node last did, for `/arm/state`.
#[derive(Debug, Default)]
struct Report {
    commanded: Option<Joints>,
    gripper: f64,
    last_ok: bool,
    holding: bool,
    /// A refusal, a watchdog hold or a backend fault, for the operator.
    fault: String,
    /// The arm itself is in a reflex or gone: commands are refused until `/arm/recover`.
    backend_down: Option<BackendError>,
    latency_ms: f64,
    commands: u64,
    refused: u64,
    clipped: u64,
}

fn header(t: Nanos, frame: &str) -> Header {
    Header { stamp: t.into(), frame_id: frame.to_owned() }
}

/// Runs the node on the backend its config names: the sim bridge's arm, or the FR3's FCI
/// (retried until `connect_timeout_s` while the robot or simulator boots).
pub async fn serve(cfg: FrankaNodeConfig, shutdown: Shutdown) -> anyhow::Result<()> {
    cfg.validate()?;
    if cfg.backend == BackendKind::Sim {
        let prefix = cfg.sim_prefix.clone();
        return run(cfg, |ros, clock| Ok(Box::new(SimArm::new(ros, &prefix, clock.clone())?)), shutdown).await;
    }
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs_f64(cfg.connect_timeout_s.max(0.0));
    let arm = loop {
        let (ip, fci) = (cfg.robot_ip.clone(), cfg.fci.clone());
        match tokio::task::spawn_blocking(move || FciArm::connect(&ip, fci)).await? {
            Ok(arm) => break arm,
            Err(e) if std::time::Instant::now() < deadline && !shutdown.is_triggered() => {
                tracing::info!("waiting for the FCI at {}: {e}", cfg.robot_ip);
                tokio::time::sleep(std::time::Duration::from_millis(250)).await;
            }
            Err(e) => anyhow::bail!("{e} (FCI at {})", cfg.robot_ip),
        }
    };
    run(cfg, |_, _| Ok(Box::new(arm)), shutdown).await
}

/// Runs the node until `shutdown` on the backend `make` builds (it gets the node's ROS handle
/// and clock: wall time for `fci`, the bridge's `/clock` for `sim`).
pub async fn run(
    cfg: FrankaNodeConfig,
    make: impl FnOnce(&mut Ros, &Clock) -> anyhow::Result<Box<dyn ArmBackend>>,
    shutdown: Shutdown,
) -> anyhow::Result<()> {
    cfg.validate()?;
    let kin = Fr3Kinematics::from_urdf_file(&labrig_arm::urdf_path(cfg.urdf.as_deref()), TcpOffset::ROBOTIQ_2F85)?;
    let filter =
        SafetyFilter::new(Ik::new(kin.clone(), IkConfig::default()), cfg.safety.clone()).map_err(anyhow::Error::msg)?;
    let watchdog = Watchdog::new(cfg.safety.watchdog_timeout());
    // In sim, time is the bridge's: commands are stamped in it and, in lockstep, it stands
    // still between commands, so the watchdog runs on it too (checked each state tick).
    let sim = cfg.backend == BackendKind::Sim;
    let clock = if sim { Clock::manual(Nanos::ZERO) } else { Clock::Wall };

    let mut ros = Ros::new(&cfg.ros, "labrig_franka")?;
    let sim_clock = if sim { Some(ros.subscription_on(&topics::CLOCK, 10)?) } else { None };
    let mut backend = make(&mut ros, &clock)?;
    let pubs = StatePubs {
        arm_state: ros.publisher_on(&topics::ARM_STATE, 10)?,
        joint_states: ros.publisher_on(&topics::JOINT_STATES, 10)?,
        tf: ros.publisher_on(&topics::TF, 10)?,
        sim,
    };
    let arm_target = ros.publisher_on(&topics::ARM_TARGET, 10)?;
    let commands = ros.subscription_on(&topics::ARM_COMMAND, 100)?;
    let mut recover_rx = ros.server_on(&topics::ARM_RECOVER)?.forward();

    let report = Report { last_ok: true, ..Report::default() };
    let reading = first_reading(&mut *backend, &shutdown).await?;
    tracing::info!(backend = backend.name(), q = ?reading.q, "franka node up");
    let mut node = ArmNode {
        bounds: filter.ik().bounds(),
        kin,
        filter,
        watchdog,
        sim,
        clock,
        sim_clock,
        backend,
        pubs,
        arm_target,
        report,
        reading,
        started: Instant::now(),
        period_ns: (cfg.safety.period_s * 1e9) as i64,
        clock_at: Instant::now(),
    };
    let mut ticker = tokio::time::interval(Duration::from_secs_f64(1.0 / cfg.rate_hz));
    ticker.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    let mut stream = Box::pin(commands.stream());
    loop {
        let deadline = node.hold_deadline();
        tokio::select! {
            _ = shutdown.wait() => break,
            Some(served) = recover_rx.recv() => served.respond(node.recover()),
            // tokio's timers have 1 ms granularity (they fire up to ~1.5 ms late): wake 1 ms
            // early and sleep the rest on the thread, so the hold lands at the deadline.
            _ = async { tokio::time::sleep_until(deadline.expect("guarded") - Duration::from_millis(1)).await },
                if deadline.is_some() => node.hold_at(deadline.expect("guarded")),
            msg = stream.next() => {
                let Some(msg) = msg else { break };
                node.command(msg, Instant::now());
            }
            _ = ticker.tick() => node.state_tick(),
        }
    }
    node.backend.stop();
    tracing::info!(
        commands = node.report.commands,
        refused = node.report.refused,
        clipped = node.report.clipped,
        "franka node stopped"
    );
    Ok(())
}

/// The first reading (the sim bridge may still be starting), waited for up to a minute; the
/// backend stopped if none comes.
async fn first_reading(backend: &mut dyn ArmBackend, shutdown: &Shutdown) -> anyhow::Result<ArmReading> {
    let waited = Instant::now();
    loop {
        match backend.read() {
            Ok(r) => return Ok(r),
            Err(e) if waited.elapsed() < Duration::from_secs(60) && !shutdown.is_triggered() => {
                tracing::debug!("waiting for the arm: {e}");
                tokio::time::sleep(Duration::from_millis(50)).await;
            }
            Err(e) => {
                backend.stop();
                return Err(e.into());
            }
        }
    }
}

/// The running node: the safety layer, the backend, the node's clock and what it last did.
struct ArmNode {
    kin: Fr3Kinematics,
    filter: SafetyFilter,
    watchdog: Watchdog,
    /// In front of the sim bridge (its time is the bridge's `/clock`).
    sim: bool,
    clock: Clock,
    sim_clock: Option<labrig_runtime::ros::RosSubscription<labrig_msgs::rosgraph_msgs::Clock>>,
    backend: Box<dyn ArmBackend>,
    pubs: StatePubs,
    arm_target: labrig_runtime::ros::RosPublisher<JointState>,
    report: Report,
    reading: ArmReading,
    /// The safety layer's joint bounds, which a hold stays inside.
    bounds: [[f64; 2]; 7],
    started: Instant,
    period_ns: i64,
    /// When the last `/clock` arrived.
    clock_at: Instant,
}

impl ArmNode {
    /// Sim time from the bridge's /clock. Between two /clock messages (one per bridge tick) the
    /// node adds the wall time since the last one, at most one period, as the bridge itself
    /// does for arrivals: in realtime that tracks sim time, in lockstep (sim time standing
    /// still between commands) it never adds up to a watchdog's silence.
    fn sync_clock(&mut self) {
        let Some(sub) = &self.sim_clock else { return };
        loop {
            match sub.try_take() {
                Ok(Some(c)) => {
                    let t = Nanos::from(c.msg.clock);
                    if t.0 + 1_000_000_000 < self.clock.now().0 {
                        tracing::warn!("/clock went back to {:.3} s: the sim bridge restarted", t.as_secs_f64());
                        self.clock.reset(t);
                    } else {
                        self.clock.set(t);
                    }
                    self.clock_at = Instant::now();
                }
                Ok(None) => break,
                Err(e) => tracing::warn!("/clock: {e}"),
            }
        }
    }

    /// The wall time since the last /clock, at most a period short of one (ns).
    fn since_clock(&self) -> i64 {
        (self.clock_at.elapsed().as_nanos() as i64).min(self.period_ns - 1)
    }

    /// On the wall clock, when the watchdog holds the arm unless a command comes first.
    fn hold_deadline(&self) -> Option<Instant> {
        self.watchdog.deadline().filter(|_| !self.sim).map(|d| self.started + Duration::from_nanos(d.0.max(0) as u64))
    }

    /// `/arm/recover`: the backend recovered and read again, its fault cleared; the answer.
    fn recover(&mut self) -> TriggerResponse {
        let response = match self.backend.recover().and_then(|()| self.backend.read()) {
            Ok(r) => {
                self.reading = r;
                self.report.backend_down = None;
                self.report.fault.clear();
                self.report.commanded = None;
                TriggerResponse { success: true, message: format!("{} recovered", self.backend.name()) }
            }
            Err(e) => TriggerResponse { success: false, message: e.to_string() },
        };
        tracing::info!("/arm/recover: {}", response.message);
        response
    }

    /// Woken just before the watchdog's `deadline`: sleeps the rest on the thread, then holds
    /// the arm (and says so at once) if no command came.
    fn hold_at(&mut self, deadline: Instant) {
        let rest = deadline.saturating_duration_since(Instant::now());
        std::thread::sleep(rest);
        if let Some(silence) = self.watchdog.check(Nanos(self.started.elapsed().as_nanos() as i64)) {
            hold(&mut *self.backend, &mut self.report, silence.0, &self.bounds);
            self.pubs.publish(&self.clock, &self.kin, &self.reading, &self.report);
        }
    }

    /// An arm command (`received` when it was taken): refused and named, or through the safety
    /// layer to the backend.
    fn command(&mut self, msg: Result<Received<ArmCommand>, RosError>, received: Instant) {
        self.report.commands += 1;
        let cmd = match msg {
            Ok(m) => m.msg,
            Err(e) => {
                // A malformed command: refused and named; the node goes on.
                self.refuse(format!("refused arm command: {e}"), true);
                return;
            }
        };
        self.sync_clock();
        // Arrival on the watchdog's time line: monotonic, or sim time.
        let arrival =
            if self.sim { self.clock.now().0 + self.since_clock() } else { self.started.elapsed().as_nanos() as i64 };
        if let Some(e) = &self.report.backend_down {
            let fault = format!("refused arm command seq {}: {e}; call /arm/recover", cmd.seq);
            self.refuse(fault, false);
            return;
        }
        let view = ArmView { measured: self.reading.q, commanded: self.report.commanded.unwrap_or(self.reading.q) };
        match self.filter.filter(&cmd, &view, self.clock.now()) {
            Ok(ok) => {
                if !ok.clipped.is_empty() {
                    self.report.clipped += 1;
                    tracing::debug!(seq = cmd.seq, clipped = ?ok.clipped, "arm command clipped");
                }
                self.send_target(&cmd, &ok, received, arrival);
            }
            Err(refusal) => self.refuse(format!("refused arm command seq {}: {refusal}", cmd.seq), true),
        }
    }

    /// A command the safety layer passed: its joint targets to the backend and, accepted,
    /// echoed on `/arm/target`, the watchdog fed at its `arrival`.
    fn send_target(&mut self, cmd: &ArmCommand, ok: &SafeCommand, received: Instant, arrival: i64) {
        match self.backend.set_target(&ok.joints) {
            Ok(()) => {
                self.report.latency_ms = received.elapsed().as_secs_f64() * 1e3;
                // Each accepted command's joint targets, stamped with the
                // command's own stamp (what the recorder pairs them by).
                let echo = self.arm_target.publish(JointState {
                    header: Header { stamp: cmd.header.stamp, frame_id: BASE_FRAME.into() },
                    name: JOINT_NAMES.iter().map(|s| s.to_string()).collect(),
                    position: ok.joints.to_vec(),
                    velocity: vec![],
                    effort: vec![],
                });
                if let Err(e) = echo {
                    tracing::warn!("/arm/target: {e}");
                }
                self.report.commanded = Some(ok.joints);
                self.report.gripper = ok.gripper;
                self.report.last_ok = true;
                self.report.holding = false;
                self.report.fault.clear();
                self.watchdog.feed(Nanos(arrival));
            }
            Err(BackendError::Refused(why)) => {
                self.refuse(format!("refused arm command seq {}: {why}", cmd.seq), true);
            }
            Err(e) => down(&mut self.report, e),
        }
    }

    /// A refused command counted and its `fault` reported (and warned, when `warn`).
    fn refuse(&mut self, fault: String, warn: bool) {
        self.report.refused += 1;
        self.report.last_ok = false;
        self.report.fault = fault;
        if warn {
            tracing::warn!("{}", self.report.fault);
        }
    }

    /// The state tick: the arm read, in sim the watchdog checked on sim time, the state published.
    fn state_tick(&mut self) {
        self.sync_clock();
        match self.backend.read() {
            Ok(r) => self.reading = r,
            Err(e) => down(&mut self.report, e),
        }
        if self.sim
            && let Some(silence) = self.watchdog.check(Nanos(self.clock.now().0 + self.since_clock()))
        {
            hold(&mut *self.backend, &mut self.report, silence.0, &self.bounds);
        }
        self.pubs.publish(&self.clock, &self.kin, &self.reading, &self.report);
    }
}

/// The watchdog tripped after `silence` ns: hold the arm where it is (its measured joints,
/// kept inside the safety layer's joint bounds, so the hold itself is a valid target).
fn hold(backend: &mut dyn ArmBackend, report: &mut Report, silence: i64, bounds: &[[f64; 2]; 7]) {
    let held = backend.read().and_then(|r| {
        let q: Joints = std::array::from_fn(|i| r.q[i].clamp(bounds[i][0], bounds[i][1]));
        backend.set_target(&q).map(|()| q)
    });
    match held {
        Ok(q) => {
            report.commanded = Some(q);
            report.holding = true;
            report.fault =
                format!("watchdog: no arm command for {:.1} ms; holding at the measured joints", silence as f64 / 1e6);
            tracing::warn!("{}", report.fault);
        }
        Err(e) => down(report, e),
    }
}

/// The arm faulted or is gone: the first reason is kept until a recovery.
fn down(report: &mut Report, e: BackendError) {
    if report.backend_down.is_some() {
        return;
    }
    tracing::error!("{e}");
    report.fault = format!("{e}; call /arm/recover");
    report.last_ok = false;
    report.backend_down = Some(e);
}

/// What the node publishes at its state rate.
struct StatePubs {
    arm_state: labrig_runtime::ros::RosPublisher<RobotState>,
    joint_states: labrig_runtime::ros::RosPublisher<JointState>,
    tf: labrig_runtime::ros::RosPublisher<TFMessage>,
    /// In front of the sim bridge, which publishes /joint_states and /tf for the whole rig.
    sim: bool,
}

impl StatePubs {
    /// A subscriber that cannot keep up must not take the arm node down: reported, skipped.
    fn publish(&self, clock: &Clock, kin: &Fr3Kinematics, r: &ArmReading, report: &Report) {
        if let Err(e) = self.publish_all(clock, kin, r, report) {
            tracing::warn!("publishing the arm's state: {e}");
        }
    }

    fn publish_all(&self, clock: &Clock, kin: &Fr3Kinematics, r: &ArmReading, report: &Report) -> anyhow::Result<()> {
        let StatePubs { arm_state, joint_states, tf, sim } = self;
        let sim = *sim;
        let t = clock.now();
        let tcp = kin.tcp_pose(&r.q);
        let names: Vec<String> = JOINT_NAMES.iter().map(|s| s.to_string()).collect();
        let moving = r.dq.iter().any(|v| v.abs() > 1e-3);
        arm_state.publish(RobotState {
            header: header(t, BASE_FRAME),
            cartesian_position: xyz_euler(&tcp),
            gripper_position: report.gripper,
            joint_positions: r.q,
            joint_velocities: r.dq,
            joint_torques_computed: r.tau_commanded,
            motor_torques_measured: r.tau_measured,
            prev_controller_latency_ms: report.latency_ms,
            prev_command_successful: report.last_ok,
            mode: if report.backend_down.is_some() || (!report.fault.is_empty() && !report.holding) {
                RobotState::MODE_FAULT
            } else if report.holding {
                RobotState::MODE_STOPPED
            } else if moving {
                RobotState::MODE_MOVING
            } else {
                RobotState::MODE_IDLE
            },
            fault: report.fault.clone(),
            ..RobotState::default()
        })?;
        if sim {
            // The bridge publishes the whole rig's joints (arm and gripper) and frames.
            return Ok(());
        }
        joint_states.publish(JointState {
            header: header(t, BASE_FRAME),
            name: names,
            position: r.q.to_vec(),
            velocity: r.dq.to_vec(),
            effort: r.tau_measured.to_vec(),
        })?;
        let q = tcp.rotation;
        tf.publish(TFMessage {
            transforms: vec![TransformStamped {
                header: header(t, BASE_FRAME),
                child_frame_id: "tcp".into(),
                transform: Transform {
                    translation: RosVector3 { x: tcp.translation.x, y: tcp.translation.y, z: tcp.translation.z },
                    rotation: Quaternion { x: q.i, y: q.j, z: q.k, w: q.w },
                },
            }],
        })?;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_example_config_parses_and_bad_keys_are_named() {
        let text = include_str!("../../../launch_configs/nodes/franka_fr3.toml");
        let cfg: FrankaNodeConfig = labrig_runtime::config::parse_config(text, "franka_fr3.toml".as_ref()).unwrap();
        cfg.validate().unwrap();
        assert_eq!(cfg.safety, SafetyConfig::default(), "the example lists the defaults");
        let err = labrig_runtime::config::parse_config::<FrankaNodeConfig>(
            "[safety]\nworkspace_mn = [0, 0, 0]\n",
            "f.toml".as_ref(),
        )
        .unwrap_err();
        assert!(err.to_string().contains("unknown field `workspace_mn`"), "{err}");
        {
            let cfg = FrankaNodeConfig {
                fci: crate::fci::FciConfig { limit_fraction: 1.5, ..Default::default() },
                ..Default::default()
            };
            assert!(cfg.validate().unwrap_err().to_string().contains("fci.limit_fraction"));
        }
    }
}
