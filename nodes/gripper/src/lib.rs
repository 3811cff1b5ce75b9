//! labrig-gripper: the Robotiq 2F-85 over Modbus RTU.
//!
//! - [`registers`]: the register map, status decoding, fault codes, DROID's 0 open .. 1 closed.
//! - [`driver`]: [`driver::Robotiq2F85`], tokio-modbus over a serial port, every request with a
//!   deadline.
//! - [`emulator`]: [`emulator::Emulated2F85`], the register protocol behind a Modbus RTU
//!   server on a pseudo-terminal, for tests and for running without the hardware.

pub mod driver;
pub mod emulator;
pub mod node;
pub mod registers;
pub mod sim;

pub use driver::{DriverConfig, GripperError, Robotiq2F85};
pub use emulator::{Emulated2F85, EmulatorConfig, PtyEmulator};
