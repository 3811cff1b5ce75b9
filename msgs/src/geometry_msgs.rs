//! `geometry_msgs`.
use crate::ros_message;
use crate::std_msgs::Header;
use serde::{Deserialize, Serialize};

/// geometry_msgs/msg/Point.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct Point {
    pub x: f64,
    pub y: f64,
    pub z: f64,
}
ros_message!(Point, "geometry_msgs/msg/Point", [], "float64 x\nfloat64 y\nfloat64 z\n");

/// geometry_msgs/msg/Vector3.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct Vector3 {
    pub x: f64,
    pub y: f64,
    pub z: f64,
}
ros_message!(Vector3, "geometry_msgs/msg/Vector3", [], "float64 x\nfloat64 y\nfloat64 z\n");

/// geometry_msgs/msg/Quaternion (x, y, z, w; identity by default as in the .msg file).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Quaternion {
    pub x: f64,
    pub y: f64,
    pub z: f64,
    pub w: f64,
}
impl Default for Quaternion {
    fn default() -> Self {
        Quaternion { x: 0.0, y: 0.0, z: 0.0, w: 1.0 }
    }
}
ros_message!(Quaternion, "geometry_msgs/msg/Quaternion", [], "float64 x 0\nfloat64 y 0\nfloat64 z 0\nfloat64 w 1\n");

/// geometry_msgs/msg/Pose.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct Pose {
    pub position: Point,
    pub orientation: Quaternion,
}
ros_message!(
    Pose,
    "geometry_msgs/msg/Pose",
    [Point, Quaternion],
    "geometry_msgs/Point position\ngeometry_msgs/Quaternion orientation\n"
);

/// geometry_msgs/msg/PoseStamped.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct PoseStamped {
    pub header: Header,
    pub pose: Pose,
}
ros_message!(
    PoseStamped,
    "geometry_msgs/msg/PoseStamped",
    [Header, Pose],
    "std_msgs/Header header\ngeometry_msgs/Pose pose\n"
);

/// geometry_msgs/msg/Transform.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct Transform {
    pub translation: Vector3,
    pub rotation: Quaternion,
}
ros_message!(
    Transform,
    "geometry_msgs/msg/Transform",
    [Vector3, Quaternion],
    "geometry_msgs/Vector3 translation\ngeometry_msgs/Quaternion rotation\n"
);

/// geometry_msgs/msg/TransformStamped: `header.frame_id` is the parent frame.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct TransformStamped {
    pub header: Header,
    pub child_frame_id: String,
    pub transform: Transform,
}
ros_message!(
    TransformStamped,
    "geometry_msgs/msg/TransformStamped",
    [Header, Transform],
    "std_msgs/Header header\nstring child_frame_id\ngeometry_msgs/Transform transform\n"
);

/// geometry_msgs/msg/Twist.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct Twist {
    pub linear: Vector3,
    pub angular: Vector3,
}
ros_message!(
    Twist,
    "geometry_msgs/msg/Twist",
    [Vector3],
    "geometry_msgs/Vector3 linear\ngeometry_msgs/Vector3 angular\n"
);
