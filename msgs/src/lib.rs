//! labrig-msgs: every message labrig puts on the wire.
//!
//! Each type is a plain serde struct whose fields follow its ROS 2 `.msg` definition in order,
//! so that [`encode`] produces exactly the CDR bytes ROS 2 (rclpy / Fast DDS) produces, and
//! [`decode`] reads them back, rejecting truncated buffers and trailing garbage with an error
//! that names the type. Every type also carries its ROS 2 type name and `.msg` text
//! ([`RosMessage`]), which the recorder needs for MCAP `ros2msg` schemas.
//!
//! This crate is the bottom layer: it depends on serde, serde_bytes, cdr-encoding and thiserror
//! only. It must never depend on tokio, a DDS implementation, iceoryx2, tch, mujoco or opencv
//! (checked by `tests/tests/layering.rs`).

pub mod calibration;
mod codec;
pub mod dv;
pub mod geometry_msgs;
mod invalid;
pub mod registry;
pub mod rig;
pub mod rosgraph_msgs;
pub mod sensor_msgs;
pub mod session;
pub mod std_msgs;
pub mod std_srvs;
pub mod tf2_msgs;
mod time;
pub mod topics;
pub mod type_hash;

pub use codec::{CDR_BE, CDR_LE, CodecError, decode, decode_payload, encode};
pub use invalid::Invalid;

/// `LABRIG_PARSE_ONLY=1`: every labrig program parses its command line, then exits 0 without
/// running it (the documentation check runs each command the guides show this way, so a
/// command line is judged by the program's own parser and nothing starts).
pub fn parse_only() -> bool {
    std::env::var_os("LABRIG_PARSE_ONLY").is_some_and(|v| !v.is_empty() && v != "0")
}

/// labrig's cache folder: `$LABRIG_CACHE`, else `~/.cache/labrig`, where `scripts/setup.sh`
/// installs what the programs and tests use beside the clone (libtorch, MuJoCo, franka-sim,
/// the Python peers' venvs); `None` when neither variable is set.
pub fn cache_dir() -> Option<std::path::PathBuf> {
    match std::env::var_os("LABRIG_CACHE") {
        Some(p) if !p.is_empty() => Some(p.into()),
        _ => std::env::var_os("HOME").map(|h| std::path::PathBuf::from(h).join(".cache/labrig")),
    }
}

pub use registry::{TypeVisitor, known_types, visit_type};
pub use time::{Nanos, builtin_interfaces};
pub use type_hash::type_hash;

/// A ROS 2 message type: its fully qualified name, its `.msg` text and its dependencies.
pub trait RosMessage:
    serde::Serialize + serde::de::DeserializeOwned + Clone + std::fmt::Debug + PartialEq + Send + 'static
{
    /// The ROS 2 type name, `package/msg/Name`.
    const TYPE_NAME: &'static str;
    /// The `.msg` definition of this type alone (nested types fully qualified as `pkg/Name`).
    const MSG_TEXT: &'static str;

    /// Appends `(type name, .msg text)` of every nested message type, depth first.
    fn dependencies(_out: &mut Vec<(&'static str, &'static str)>) {}

    /// Checks invariants the wire format cannot express (e.g. the schema version of a
    /// `labrig_msgs` type). Called by [`decode`].
    fn validate(&self) -> Result<(), Invalid> {
        Ok(())
    }

    /// The type's earlier layout, where it grew fields since: decodes a body written in it
    /// (with the bytes it used), the new fields empty. [`decode`] falls back to it when the
    /// current layout does not fit.
    fn decode_legacy(_id: [u8; 2], _body: &[u8]) -> Option<Result<(Self, usize), cdr_encoding::Error>> {
        None
    }
}

/// The ROS 2 service types labrig uses: a request and a response message.
pub trait RosService {
    /// `package/srv/Name`.
    const TYPE_NAME: &'static str;
    type Request: RosMessage;
    type Response: RosMessage;
}

/// The full MCAP `ros2msg` schema text of `T`: its own definition followed by each dependency
/// after a line of 80 `=` and `MSG: pkg/Name` (the layout rosbag2 writes).
pub fn schema_text<T: RosMessage>() -> String {
    let mut deps = Vec::new();
    T::dependencies(&mut deps);
    let mut seen: Vec<&str> = Vec::new();
    let mut text = T::MSG_TEXT.trim_end().to_owned();
    text.push('\n');
    for (name, body) in deps {
        if seen.contains(&name) {
            continue;
        }
        seen.push(name);
        text.push_str(&"=".repeat(80));
        text.push_str("\nMSG: ");
        text.push_str(&short_type_name(name));
        text.push('\n');
        text.push_str(body.trim_end());
        text.push('\n');
    }
    text
}

/// `pkg/msg/Name` -> `pkg/Name` (the form used inside `.msg` files and schema separators).
pub fn short_type_name(type_name: &str) -> String {
    type_name.replacen("/msg/", "/", 1)
}

/// The DDS type name ROS 2 uses on the wire: `pkg/msg/Name` -> `pkg::msg::dds_::Name_`.
pub fn dds_type_name(type_name: &str) -> String {
    match type_name.rsplit_once('/') {
        Some((prefix, name)) => format!("{}::dds_::{}_", prefix.replace('/', "::"), name),
        None => type_name.to_owned(),
    }
}

/// Implements [`RosMessage`] for a type: name, `.msg` text and nested types.
macro_rules! ros_message {
    ($ty:ty, $name:literal, [$($dep:ty),* $(,)?], $text:expr) => {
        impl $crate::RosMessage for $ty {
            const TYPE_NAME: &'static str = $name;
            const MSG_TEXT: &'static str = $text;
            #[allow(unused_variables)]
            fn dependencies(out: &mut Vec<(&'static str, &'static str)>) {
                $(
                    out.push((<$dep as $crate::RosMessage>::TYPE_NAME, <$dep as $crate::RosMessage>::MSG_TEXT));
                    <$dep as $crate::RosMessage>::dependencies(out);
                )*
            }
        }
    };
}
pub(crate) use ros_message;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn schema_text_lists_each_dependency_once_in_rosbag2_layout() {
        let text = schema_text::<geometry_msgs::PoseStamped>();
        assert!(text.starts_with("std_msgs/Header header\n"));
        assert_eq!(text.matches("MSG: std_msgs/Header").count(), 1);
        assert_eq!(text.matches("MSG: builtin_interfaces/Time").count(), 1);
        assert_eq!(text.matches("MSG: geometry_msgs/Quaternion").count(), 1);
        let sep = format!("{}\nMSG: ", "=".repeat(80));
        assert_eq!(text.matches(&sep).count(), 5, "{text}");
    }

    #[test]
    fn dds_type_names_follow_ros2_mangling() {
        assert_eq!(dds_type_name("sensor_msgs/msg/JointState"), "sensor_msgs::msg::dds_::JointState_");
        assert_eq!(dds_type_name("std_srvs/srv/SetBool_Request"), "std_srvs::srv::dds_::SetBool_Request_");
    }
}
