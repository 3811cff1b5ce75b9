//! `std_srvs`.
use crate::{RosService, ros_message};
use serde::{Deserialize, Serialize};

/// std_srvs/srv/SetBool request.
#[derive(Debug, Clone, PartialEq, Eq, Default, Serialize, Deserialize)]
pub struct SetBoolRequest {
    pub data: bool,
}
ros_message!(SetBoolRequest, "std_srvs/srv/SetBool_Request", [], "bool data\n");

/// std_srvs/srv/SetBool response.
#[derive(Debug, Clone, PartialEq, Eq, Default, Serialize, Deserialize)]
pub struct SetBoolResponse {
    pub success: bool,
    pub message: String,
}
ros_message!(SetBoolResponse, "std_srvs/srv/SetBool_Response", [], "bool success\nstring message\n");

/// std_srvs/srv/SetBool.
#[derive(Debug)]
pub struct SetBool;
impl RosService for SetBool {
    const TYPE_NAME: &'static str = "std_srvs/srv/SetBool";
    type Request = SetBoolRequest;
    type Response = SetBoolResponse;
}

/// std_srvs/srv/Trigger request (empty: CDR encodes an empty struct as one zero byte, as
/// rosidl's generated `structure_needs_at_least_one_member` field does).
#[derive(Debug, Clone, PartialEq, Eq, Default, Serialize, Deserialize)]
pub struct TriggerRequest {
    #[serde(default)]
    pub structure_needs_at_least_one_member: u8,
}
ros_message!(TriggerRequest, "std_srvs/srv/Trigger_Request", [], "uint8 structure_needs_at_least_one_member\n");

/// std_srvs/srv/Trigger response.
#[derive(Debug, Clone, PartialEq, Eq, Default, Serialize, Deserialize)]
pub struct TriggerResponse {
    pub success: bool,
    pub message: String,
}
ros_message!(TriggerResponse, "std_srvs/srv/Trigger_Response", [], "bool success\nstring message\n");

/// std_srvs/srv/Trigger.
#[derive(Debug)]
pub struct Trigger;
impl RosService for Trigger {
    const TYPE_NAME: &'static str = "std_srvs/srv/Trigger";
    type Request = TriggerRequest;
    type Response = TriggerResponse;
}
