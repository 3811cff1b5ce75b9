//! What the franka node drives: an arm that takes joint targets. Every target a backend gets
//! has passed the safety layer; backends add their own limits on top (the FCI's rate limiter
//! and reflexes), never fewer.

use labrig_arm::Joints;

/// One reading of the arm.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct ArmReading {
    /// Measured joint positions (rad) and velocities (rad/s).
    pub q: Joints,
    pub dq: Joints,
    /// The joint target the arm's own loop is tracking now (rad).
    pub q_target: Joints,
    /// Measured link-side joint torques (Nm).
    pub tau_measured: Joints,
    /// The torques the controller commanded (Nm).
    pub tau_commanded: Joints,
}

#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum BackendError {
    /// The arm stopped itself (an FCI reflex: a limit, a collision, a communication stall).
    /// It moves again after a recovery.
    #[error("the arm stopped with a reflex: {0}")]
    Reflex(String),
    /// The connection to the arm (or its simulator) is gone.
    #[error("lost the connection to the arm: {0}")]
    Disconnected(String),
    /// The arm cannot be reached or refused to start.
    #[error("cannot start the arm: {0}")]
    Start(String),
    /// The backend refused one target (e.g. inside its own joint-limit inset); the arm goes
    /// on tracking the previous one.
    #[error("the arm refused the target: {0}")]
    Refused(String),
}

/// An arm taking joint targets at the rig's rate (20 Hz) while its own loop (1 kHz on an
/// FR3) interpolates between them.
pub trait ArmBackend: Send {
    /// Short name for logs and reports.
    fn name(&self) -> &'static str;
    /// The latest state; an error when the arm faulted or is gone.
    fn read(&mut self) -> Result<ArmReading, BackendError>;
    /// Track `target` from now on (non-blocking).
    fn set_target(&mut self, target: &Joints) -> Result<(), BackendError>;
    /// Bring the arm to rest where it is: the measured joints become the target. Returns them.
    fn hold(&mut self) -> Result<Joints, BackendError> {
        let q = self.read()?.q;
        self.set_target(&q)?;
        Ok(q)
    }
    /// After a reflex or a lost connection: clear the error and take targets again.
    fn recover(&mut self) -> Result<(), BackendError>;
    /// Stop the arm's control loop (the arm holds on its brakes or its own controller).
    fn stop(&mut self);
}
