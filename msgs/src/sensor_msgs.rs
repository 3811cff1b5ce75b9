//! `sensor_msgs`.
use crate::ros_message;
use crate::std_msgs::Header;
use serde::{Deserialize, Serialize};

/// sensor_msgs/msg/JointState.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct JointState {
    pub header: Header,
    pub name: Vec<String>,
    pub position: Vec<f64>,
    pub velocity: Vec<f64>,
    pub effort: Vec<f64>,
}
ros_message!(
    JointState,
    "sensor_msgs/msg/JointState",
    [Header],
    "std_msgs/Header header\nstring[] name\nfloat64[] position\nfloat64[] velocity\nfloat64[] effort\n"
);

/// sensor_msgs/msg/Image (raw pixels; `data` is `uint8[]`, decoded as one block).
#[derive(Debug, Clone, PartialEq, Eq, Default, Serialize, Deserialize)]
pub struct Image {
    pub header: Header,
    pub height: u32,
    pub width: u32,
    pub encoding: String,
    pub is_bigendian: u8,
    pub step: u32,
    #[serde(with = "serde_bytes")]
    pub data: Vec<u8>,
}
ros_message!(
    Image,
    "sensor_msgs/msg/Image",
    [Header],
    "std_msgs/Header header\nuint32 height\nuint32 width\nstring encoding\nuint8 is_bigendian\nuint32 step\nuint8[] data\n"
);

/// sensor_msgs/msg/CompressedImage (`format` is e.g. "jpeg" or "png").
#[derive(Debug, Clone, PartialEq, Eq, Default, Serialize, Deserialize)]
pub struct CompressedImage {
    pub header: Header,
    pub format: String,
    #[serde(with = "serde_bytes")]
    pub data: Vec<u8>,
}
ros_message!(
    CompressedImage,
    "sensor_msgs/msg/CompressedImage",
    [Header],
    "std_msgs/Header header\nstring format\nuint8[] data\n"
);

/// sensor_msgs/msg/RegionOfInterest.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
pub struct RegionOfInterest {
    pub x_offset: u32,
    pub y_offset: u32,
    pub height: u32,
    pub width: u32,
    pub do_rectify: bool,
}
ros_message!(
    RegionOfInterest,
    "sensor_msgs/msg/RegionOfInterest",
    [],
    "uint32 x_offset\nuint32 y_offset\nuint32 height\nuint32 width\nbool do_rectify\n"
);

/// sensor_msgs/msg/CameraInfo: intrinsics (`k`, row-major 3x3), distortion `d`, rectification
/// `r` and projection `p` (row-major 3x4).
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct CameraInfo {
    pub header: Header,
    pub height: u32,
    pub width: u32,
    pub distortion_model: String,
    pub d: Vec<f64>,
    pub k: [f64; 9],
    pub r: [f64; 9],
    pub p: [f64; 12],
    pub binning_x: u32,
    pub binning_y: u32,
    pub roi: RegionOfInterest,
}
ros_message!(
    CameraInfo,
    "sensor_msgs/msg/CameraInfo",
    [Header, RegionOfInterest],
    "std_msgs/Header header\nuint32 height\nuint32 width\nstring distortion_model\nfloat64[] d\nfloat64[9] k\nfloat64[9] r\nfloat64[12] p\nuint32 binning_x\nuint32 binning_y\nsensor_msgs/RegionOfInterest roi\n"
);
