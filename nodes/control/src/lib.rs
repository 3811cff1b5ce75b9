//! labrig-control: the rig loop's logic, independent of transport (the node binary wires it
//! to ROS 2 and shared memory).
//!
//! - [`frames`]: per camera, the recent frames' times; the frame nearest a tick; skew.
//! - [`episode`]: the episode state machine (idle -> recording -> success | failure |
//!   discarded -> resetting -> idle), driven by events.
//! - [`step`]: one `labrig_msgs/Step` record per tick from the observation, the action and
//!   the tick's timing.

pub mod episode;
pub mod frames;
pub mod step;
