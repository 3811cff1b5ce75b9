//! labrig-teleop: the Quest teleoperation node (DROID's oculus_reader + VRPolicy lineage).
//!
//! - [`logcat`]: the headset app's logcat lines -> both controllers' poses and buttons.
//! - [`policy`]: DROID's VRPolicy: deadman, origins, forward, gains -> cartesian velocity.
//! - [`input`]: where readings come from: `adb logcat` (reconnecting), a recorded file played
//!   back at its own timing, or the keyboard ([`keyboard`]: a virtual controller).
//! - [`node`]: the ROS 2 node: `/teleop/state`, `/teleop/action`, `/rig/request`.

pub mod input;
pub mod keyboard;
pub mod logcat;
pub mod node;
pub mod policy;
