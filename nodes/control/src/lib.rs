//! labrig-control: the 20 Hz rig loop.
//!
//! - [`frames`]: per camera, the recent frames' times; the frame nearest a tick; skew.
//! - [`episode`]: the episode state machine (idle -> recording -> success | failure |
//!   discarded -> resetting -> idle), driven by events.
//! - [`step`]: one `labrig_msgs/Step` record per tick from the observation, the action and
//!   the tick's timing.
//! - [`source`]: action sources behind one trait (the sim's scripted expert now).
//! - [`node`]: the node (`labrig-control run`) wiring them to ROS 2 and shared memory.

pub mod episode;
pub mod frames;
pub mod node;
pub mod source;
pub mod step;
