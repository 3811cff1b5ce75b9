//! `tf2_msgs` (not on PyPI; a sequence of `TransformStamped`, so its bytes follow from those).
use crate::geometry_msgs::TransformStamped;
use crate::ros_message;
use serde::{Deserialize, Serialize};

/// tf2_msgs/msg/TFMessage, published on `/tf` and `/tf_static`.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct TFMessage {
    pub transforms: Vec<TransformStamped>,
}
ros_message!(TFMessage, "tf2_msgs/msg/TFMessage", [TransformStamped], "geometry_msgs/TransformStamped[] transforms\n");
