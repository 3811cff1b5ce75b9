//! `rosgraph_msgs`.
use crate::builtin_interfaces::Time;
use crate::ros_message;
use serde::{Deserialize, Serialize};

/// rosgraph_msgs/msg/Clock, published on `/clock` by the sim bridge.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
pub struct Clock {
    pub clock: Time,
}
ros_message!(Clock, "rosgraph_msgs/msg/Clock", [Time], "builtin_interfaces/Time clock\n");
