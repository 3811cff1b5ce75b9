//! `std_msgs`.
use crate::builtin_interfaces::Time;
use crate::ros_message;
use serde::{Deserialize, Serialize};

/// std_msgs/msg/Header: a timestamp and the frame the data is in.
#[derive(Debug, Clone, PartialEq, Eq, Default, Serialize, Deserialize)]
pub struct Header {
    pub stamp: Time,
    pub frame_id: String,
}
ros_message!(Header, "std_msgs/msg/Header", [Time], "builtin_interfaces/Time stamp\nstring frame_id\n");

/// std_msgs/msg/String.
#[derive(Debug, Clone, PartialEq, Eq, Default, Serialize, Deserialize)]
pub struct String_ {
    pub data: String,
}
pub use String_ as StringMsg;
ros_message!(String_, "std_msgs/msg/String", [], "string data\n");
